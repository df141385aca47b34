"""Which results sections ran before the shipped models last changed (git history, real git)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from safeil_sumo.experiments.outputs import sections_before


def _commit(repo: Path, path: str, text: str) -> str:
    (repo / path).parent.mkdir(parents=True, exist_ok=True)
    (repo / path).write_text(text)
    env = {"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t", "PATH": "/usr/bin:/bin"}
    subprocess.run(["git", "-C", str(repo), "add", "-A"], check=True, env=env)
    subprocess.run(["git", "-C", str(repo), "commit", "-q", "-m", path], check=True, env=env)
    return subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], check=True, env=env,
                          capture_output=True, text=True).stdout.strip()


@pytest.fixture
def history(tmp_path):
    """a: models v1; b: other code; c: models v2 (the shipped ones); d: other code."""
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    a = _commit(tmp_path, "models/safeil.safetensors", "v1")
    b = _commit(tmp_path, "code.py", "1")
    c = _commit(tmp_path, "models/safeil.safetensors", "v2")
    d = _commit(tmp_path, "code.py", "2")
    return tmp_path, a, b, c, d


def test_sections_run_before_the_models_changed_are_named(history):
    repo, a, b, c, d = history
    runs = {"lodo": a, "n74": b + "-dirty", "safety": c, "whole": d + "-dirty"}
    assert sections_before("models", runs, repo) == ["lodo", "n74"]


def test_no_history_means_no_claim(tmp_path, history):
    repo, a, *_ = history
    assert sections_before("models", {}, repo) == []
    assert sections_before("not/a/path", {"lodo": a}, repo) == []  # never changed: no claim
    assert sections_before("models", {"lodo": a}, tmp_path / "not_a_repo") == []
