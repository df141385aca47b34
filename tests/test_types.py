"""Type checking of the pure core and the closed loop (issue 21): mypy, with the settings and
the modules of ``[tool.mypy]`` in pyproject.toml, finds nothing.

mypy runs in a subprocess from the project root; its cache is the default ``.mypy_cache``
there (gitignored), so a repeated run takes about a second and a cold one (CI) ~5-10 s on this
project's 2-core machine.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]


def _mypy(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "mypy", "--config-file", "pyproject.toml",
                           *args], check=False, cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def test_the_configured_modules_exist_and_include_the_core_and_the_loop() -> None:
    files = CONFIG["files"]
    assert [f for f in files if not (ROOT / f).is_file()] == []
    for module in ("geometry", "bspline", "features", "safety_filter", "sim/stepper",
                   "sim/runner", "sim/batch"):
        assert f"safeil_sumo/{module}.py" in files


def test_the_loop_is_checked_without_exemptions() -> None:
    """No override relaxes a checked module (sim/stepper.py had one until its Optional
    attributes and float-or-array values were narrowed in code, issue 21): only the untyped
    third-party modules have overrides."""
    overrides = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"].get(
        "overrides", [])
    checked = {f.removesuffix(".py").replace("/", ".") for f in CONFIG["files"]}
    for override in overrides:
        modules = override["module"]
        modules = [modules] if isinstance(modules, str) else modules
        assert not checked & set(modules), override


def test_mypy_finds_nothing_in_the_core_and_the_loop() -> None:
    result = _mypy()
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.startswith("Success: no issues found"), result.stdout


def test_the_settings_catch_what_they_are_for(tmp_path: Path) -> None:
    """The same settings on a module with a wrong return type, a half-annotated function and
    a needless ``type: ignore`` report all three (the clean result above is not vacuous)."""
    bad = tmp_path / "bad.py"
    bad.write_text("def wrong(x: int) -> str:\n    return x\n\n\n"
                   "def half(x: int, y):\n    return x\n\n\n"
                   "def needless(x: int) -> int:\n    return x  # type: ignore[arg-type]\n")
    result = _mypy("--cache-dir", str(tmp_path / "cache"), str(bad))
    assert result.returncode == 1, result.stdout + result.stderr
    for code in ("[return-value]", "[no-untyped-def]", "[unused-ignore]"):
        assert code in result.stdout, (code, result.stdout)
