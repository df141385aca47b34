"""The replay of a recorded maneuver as an env task (``safeil_sumo/Replay-v0``).

The maneuver is rebuilt as ``python -m safeil_sumo.replay`` rebuilds it
(:func:`safeil_sumo.experiments.maneuver_replay.prepare_replay`): its road from the recorded ego
lane (netconvert, into a folder of the env's own, removed when the env is collected), the leader
driving the recorded speed profile (drift-corrected), the ego starting as the recorded human
(position, heading relative to the lane, speed); the episode lasts the maneuver's window. The
task keeps the human trace, so the env can reward closeness to the human
(:attr:`RewardConfig.human_gap_per_m2`: the squared error of the gap against the human's gap at
the same time) and report the human's gap in ``info["human_gap"]``.

Episode ``index`` is the replay's seed (``--seed`` of the replay CLI: SUMO's and the sensor
noise's, noise-free by default, so every index drives the same replay unless noise is set);
``reset(options={"index": 0})`` is the CLI's default run.
"""

from __future__ import annotations

import functools
import shutil
import tempfile
import weakref
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from safeil_sumo.sim.loop_types import Scenario

# the default maneuver: the replay CLI's ``--source openacc --maneuver auto`` (the 11 s window
# most like the paper's, 115 km/h and a 58.6 m gap): JRC-VC_280219_part3_f4#1 from 72 s, held
# out of the shipped safeil's training (its checkpoint's metrics.val_maneuvers)
DEFAULT_SOURCE = "openacc"
DEFAULT_MANEUVER = "auto"
MAX_INDEX = 2**31 - 1
OPTIONS = ("source", "maneuver", "start_s", "duration_s", "data_dir", "lane_noise_c0_m",
           "radar_noise_m", "master_seed", "max_time_s")


@functools.lru_cache(maxsize=4)
def _maneuvers(source: str, data_dir: str, rate_hz: float) -> pd.DataFrame:
    """The source's car-following maneuvers (the replay CLI's import and pipeline), once per
    process."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source

    maneuvers, _ = process_drive(load_source(source, Path(data_dir)),
                                 PipelineConfig(rate_hz=rate_hz))
    return maneuvers


@dataclass(frozen=True)
class ReplayTask:
    """Episodes of one recorded maneuver's replay (the :class:`~.tasks.EnvTask` interface).

    ``scenario``: the replay's closed-loop scenario (seed 0); ``human_t`` [s from the window's
    start] and ``human_gap`` [m, bumper to bumper along the lane]: the recorded human's gap at
    the recorded samples; ``net_dir``: the rebuilt net's folder (the env's own)."""

    name: str
    maneuver_id: str
    start_s: float  # [s] the window's start within the maneuver
    scenario_: Scenario
    human_t: np.ndarray
    human_gap: np.ndarray
    net_dir: Path
    max_index: int = MAX_INDEX
    family: str = ""
    traffic: bool = False
    replay: bool = True  # the reward's default is spaces.REPLAY_REWARD

    def scenario(self, index: int) -> Scenario:
        if not 0 <= index < self.max_index:
            raise ValueError(f"episode index must be in [0, {self.max_index}), got {index}")
        return replace(self.scenario_, seed=int(index))

    def draw_index(self, rng: np.random.Generator) -> int:
        return int(rng.integers(0, self.max_index))

    @property
    def net_path(self) -> Path:
        return Path(self.scenario_.road.net_path)

    def human_gap_at(self, t: np.ndarray) -> np.ndarray:
        """The human's gap [m] at times ``t`` [s from the start] (linear between samples)."""
        return np.interp(t, self.human_t, self.human_gap)


def replay_task(source: str = DEFAULT_SOURCE, maneuver: str = DEFAULT_MANEUVER,
                start_s: float = 0.0, duration_s: float | None = None,
                data_dir: str | Path | None = None, lane_noise_c0_m: float = 0.0,
                radar_noise_m: float = 0.0, master_seed: int = 0,
                max_time_s: float | None = None, **unknown: Any) -> ReplayTask:
    """The replay task of ``maneuver`` (an id, ``"auto"`` or ``"longest"``, as the replay CLI's
    ``--maneuver``) of ``source`` (``openacc``, ``zalazone``, ``ngsim`` or a drive file, in
    ``data_dir``, default ``../shared/data``), from ``start_s`` [s] (ignored with ``auto``)
    for ``duration_s`` [s] (default 11, the paper's; 0: to the maneuver's end); ``max_time_s``
    [s] caps the episode. ``lane_noise_c0_m``, ``radar_noise_m`` [m]: sensor noise (default
    none, as the CLI). ``ValueError`` for an unknown option, source or maneuver."""
    from safeil_sumo.data.sources import DEFAULT_DATA_DIR
    from safeil_sumo.experiments import maneuver_replay as rp
    from safeil_sumo.sim.sensors import SensorConfig

    if unknown:
        raise ValueError(f"unknown replay option(s) {sorted(unknown)}; options: {list(OPTIONS)}")
    if master_seed != 0:
        raise ValueError("the replay has no master seed: its episode index is the replay's seed")
    for name, value in (("start_s", start_s), ("lane_noise_c0_m", lane_noise_c0_m),
                        ("radar_noise_m", radar_noise_m)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be finite and >= 0, got {value}")
    if duration_s is not None and not (np.isfinite(duration_s) and duration_s >= 0):
        raise ValueError(f"duration_s must be >= 0 s, got {duration_s}")
    if max_time_s is not None and not (np.isfinite(max_time_s) and max_time_s > 0):
        raise ValueError(f"max_time_s must be > 0 s, got {max_time_s}")
    data_dir = Path(data_dir) if data_dir is not None else DEFAULT_DATA_DIR
    try:
        maneuvers = _maneuvers(str(source), str(data_dir), 10.0)
    except (OSError, ValueError) as exc:  # SchemaError is a ValueError
        raise ValueError(f"replay source {source!r} in {data_dir}: {exc}") from exc
    duration = rp.PAPER_DURATION_S if duration_s is None else duration_s or None
    mid, start, rows = rp.select_maneuver(maneuvers, maneuver, start_s, duration)
    net_dir = Path(tempfile.mkdtemp(prefix="safeil_replay_env_"))
    try:
        prep = rp.prepare_replay(rows, net_dir, rp.ReplayConfig(), maneuver_id=mid)
    except BaseException:
        shutil.rmtree(net_dir, ignore_errors=True)
        raise
    sc = prep.scenario
    limit_s = sc.max_time_s  # the recording's length (prepare_replay sets it)
    if max_time_s:
        limit_s = max_time_s if limit_s is None else min(limit_s, max_time_s)
    sc = replace(sc, sensors=SensorConfig(lane_noise_c0_m=float(lane_noise_c0_m),
                                          radar_noise_m=float(radar_noise_m)),
                 max_time_s=limit_s)
    task = ReplayTask(f"replay {mid} @ {start:g} s", mid, start, sc,
                      prep.human["t"].to_numpy(float), prep.human["gap"].to_numpy(float),
                      net_dir)
    weakref.finalize(task, shutil.rmtree, net_dir, True)  # the net goes with the task
    return task
