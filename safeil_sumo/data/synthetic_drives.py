"""Record the synthetic drivers in SUMO: calibrated drivers x the full n74 road.

Driver ``i`` draws its parameters from the calibrated population
(:func:`safeil_sumo.data.synthetic.sample_driver`, generator seeded with ``(seed, i)``) and drives
the whole 29.2 km with SUMO seed ``seed * 1000 + i``. libsumo runs one simulation per process,
so each drive runs in its own worker process (a ``spawn`` pool: no libsumo state is inherited).
``training/build_synthetic_dataset.py`` and ``safeil-train`` (data format ``synthetic``) call it.
"""

from __future__ import annotations

import multiprocessing as mp
from dataclasses import asdict

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from safeil_sumo.data.recorder import RecordingConfig, record_drive
from safeil_sumo.data.synthetic import sample_driver


def drive_one(job: tuple[int, int, bool]) -> tuple[pd.DataFrame, dict]:
    """Record driver ``i`` of ``job = (i, seed, lane_changes)`` (one worker process, one SUMO):
    the drive frame and its recording stats (with the driver's parameters)."""
    i, seed, lane_changes = job
    params = sample_driver(np.random.default_rng([seed, i]), lane_changes=lane_changes)
    cfg = RecordingConfig(seed=seed * 1000 + i, recording_id=f"n74_d{i:02d}")
    df = record_drive(params, cfg)
    stats = df.attrs["recording_stats"] | {"params": asdict(params)}
    df.attrs = {}
    return df, stats


def record_drivers(drivers: int, seed: int = 0, lane_changes: bool = True, workers: int = 2,
                   progress: bool = True) -> tuple[pd.DataFrame, list[dict]]:
    """``drivers`` synthetic drivers recorded in SUMO, ``workers`` at a time: the drives (one
    frame, drivers in order: the output does not depend on timing) and each driver's stats."""
    jobs = [(i, seed, lane_changes) for i in range(drivers)]
    frames: list[pd.DataFrame] = []
    stats: list[dict] = []
    with mp.get_context("spawn").Pool(workers, maxtasksperchild=1) as pool:
        results = pool.imap(drive_one, jobs)  # ordered
        for df, st in tqdm(results, total=len(jobs), unit="drive", disable=not progress,
                           desc="synthetic drivers"):
            frames.append(df)
            stats.append(st)
    return pd.concat(frames, ignore_index=True), stats
