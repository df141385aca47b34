"""The ``lodo`` and ``ablation`` sections of ``python -m safeil_sumo.results``: the studies run
by scripts of ``training/``, ``leave_one_driver_out.py`` (the shipped recipe trained without
each left-out driver, those drivers replayed whole: ``lodo/``) and
``leader_following_ablation.py`` (one lever at a time: ``leader_ablation.csv`` and
``leader_ablation.md``), each in a subprocess that writes its own files; and their parts of
``results/studies.md`` (:func:`lodo_readme`, :func:`ablation_readme`), which quote those
files."""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from safeil_sumo.studies.shared import REPO


def lodo(out: Path, workers: int) -> list[dict]:
    """``training/leave_one_driver_out.py`` (fold models cached in ``data/lodo``)."""
    import subprocess

    script = REPO / "training" / "leave_one_driver_out.py"
    subprocess.run([sys.executable, str(script), "--workers", str(workers), "--out",
                    str(out / "lodo")], check=True)
    return pd.read_csv(out / "lodo" / "summary.csv").to_dict(orient="records")


def ablation(out: Path, workers: int) -> list[dict]:
    """``training/leader_following_ablation.py`` (checkpoints cached in ``data/ablation``)."""
    import subprocess

    script = REPO / "training" / "leader_following_ablation.py"
    subprocess.run([sys.executable, str(script), "--workers", str(workers), "--out", str(out)],
                   check=True)
    return pd.read_csv(out / "leader_ablation.csv").to_dict(orient="records")


def lodo_readme(out: Path) -> list[str]:
    """The leave-one-driver-out section (``results/lodo/summary.md``)."""
    summary = out / "lodo" / "summary.md"
    text = ("`python training/leave_one_driver_out.py`: 4 folds; fold k trains the shipped "
            "two-stage recipe and calibrates the IDM without OpenACC driver f(k+2) and a quarter "
            "of the NGSIM follower vehicles, then replays those drivers' maneuvers whole; the "
            "OpenACC ones also adapted on their first 60 s (and 2, 10, 30 s), scored after "
            "them: one (s0, T) estimate of those seconds sets `safeil` to the driver's line "
            "and the IDM's s0 and T (`replay --adapt-first-s`, docs/human_likeness.md). "
            "Per driver: `lodo/per_driver.csv`; every run: `lodo/windows.csv`. The open-loop "
            "stage of the 4 folds took 64 min on 2 shared cores, 2 folds at a time; the "
            "closed-loop stage with the settling term and the replays 38 min more (the models "
            "are cached in `data/lodo/`: the section's own wall time below is the rerun's).")
    return ["## Drivers never seen in training: leave one driver out", "", text, "",
            summary.read_text() if summary.is_file() else "", ""]


def ablation_readme(out: Path) -> list[str]:
    """The one-lever-at-a-time section (``results/leader_ablation.md``)."""
    table = out / "leader_ablation.md"
    text = ("`python training/leader_following_ablation.py` (seed 0; held-out imitation "
            "error of the x control points per source [m²]; the probe; the closed-loop "
            "validation battery of `safeil_sumo/experiments/selection.py`; the replay of "
            "every 11 s window of the held-out OpenACC maneuvers).")
    return ["## Why the earlier planners ignored the leader: one lever at a time", "", text, "",
            table.read_text() if table.is_file() else "", ""]
