"""Results folders: per-step Parquet log, per-scenario CSV/JSON, manifest, plots — written atomically.

A run's files are assembled in a temporary sibling folder and renamed into place at the end,
so a crash or a bad input never leaves a half-written results folder behind.
"""

from __future__ import annotations

import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Any

import pandas as pd

from safeil_sumo.core.atomic import atomic_path


def git_commit(repo: Path | None = None) -> str:
    """The current git commit of the project (``"unknown"`` outside a checkout)."""
    repo = repo or Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True,
                             text=True, timeout=5, check=True)
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               timeout=5, check=False).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def sections_before(path: str, section_commits: dict[str, str],
                    repo: Path | None = None) -> list[str]:
    """The sections whose last run (``section_commits``: name -> commit, maybe ``-dirty``)
    predates the last commit that changed ``path`` (e.g. the shipped models): they ran with
    other files than the checkout holds. Empty when git cannot tell (no checkout, no history)."""
    repo = repo or Path(__file__).resolve().parents[2]

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True,
                              timeout=10, check=False)

    try:
        changed = git("log", "-1", "--format=%H", "--", path).stdout.strip()
        if not changed:
            return []
        stale = []
        for name, commit in section_commits.items():
            ran_at = commit.removesuffix("-dirty")
            # exit 0: ``changed`` is an ancestor of (or is) the run's commit; 1: it is not
            if git("merge-base", "--is-ancestor", changed, ran_at).returncode == 1:
                stale.append(name)
        return stale
    except (OSError, subprocess.SubprocessError):
        return []


def versions() -> dict[str, str]:
    """Versions of the software that determines the numbers."""
    from importlib.metadata import PackageNotFoundError, version

    found = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in ("eclipse-sumo", "libsumo", "torch", "numpy", "pandas", "safeil-sumo"):
        try:
            found[pkg] = version(pkg)
        except PackageNotFoundError:
            found[pkg] = "not installed"
    return found


def manifest(config: dict[str, Any], seeds: Iterable[int]) -> dict[str, Any]:
    """What reproduces a run: config, seeds, git commit, versions, command line."""
    return {
        "config": config,
        "seeds": list(seeds),
        "git_commit": git_commit(),
        "versions": versions(),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
    }


def _json_default(obj: Any) -> Any:
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "item"):
        return obj.item()
    return str(obj)


def _clean(value: Any) -> Any:
    """JSON has no NaN/inf: write them as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_clean(v) for v in value]
    return value


def json_text(data: Any) -> str:
    """``data`` as :func:`write_json` writes it (NaN/inf as null, numpy scalars as numbers)."""
    return json.dumps(_clean(data), indent=2, default=_json_default) + "\n"


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (temporary file in the same folder, then rename)."""
    write_text(path, json_text(data))


def write_text(path: Path, text: str) -> None:
    """Write ``text`` atomically (temporary file in the same folder, then rename)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


class AtomicDir:
    """Context manager giving a temporary folder that replaces ``target`` only on success."""

    def __init__(self, target: Path) -> None:
        self.target = Path(target)

    def __enter__(self) -> Path:
        self.target.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.", dir=self.target.parent))
        return self.tmp

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            return
        old = None
        if self.target.exists():
            old = self.target.with_name(f".{self.target.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(self.target, old)
        os.replace(self.tmp, self.target)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def write_tables(folder: Path, logs: pd.DataFrame, summaries: pd.DataFrame) -> None:
    """``steps.parquet`` (all scenarios, ``scenario`` column), ``summary.csv`` and ``.json``,
    each written atomically."""
    with atomic_path(folder / "steps.parquet") as tmp:
        logs.to_parquet(tmp, index=False)
    with atomic_path(folder / "summary.csv") as tmp:
        summaries.to_csv(tmp, index=False)
    write_json(folder / "summary.json", summaries.to_dict(orient="records"))
