"""Leaders on recorded human speed profiles: real stop-and-go and real braking for the safety tests.

A *library* is a list of :class:`LeaderRecording`: the leader's speed over time and the recorded
follower's state at its start (the ego starts where the human did: same speed, same bumper gap).

- ``ngsim`` / ``openacc``: every car-following maneuver of the shared NGSIM I-80 pairs (congested,
  2-22 m/s, stop-and-go) or OpenACC Vicolungo human day (motorway, 18-39 m/s), imported and cut
  by the project's processing pipeline at 10 Hz — read from the data folder at run time
  (``../shared/data`` by default), never copied into the project;
- a CSV or Parquet file with ``time`` [s] and ``speed`` [m/s] columns (one profile; the ego then
  starts at the leader's speed where the scenario starts in the profile, its first speed when
  the profile is drawn from its start, and the spec's initial gap), or a folder of such files.

A speed the spec gives explicitly (``ScenarioSpec.ego_speed_mps``, ``--ego-speed-mps``) wins over
the recording's.

Scenario ``index`` of a sweep draws its recording and a start time within it from its own seed
(:func:`draw`), so it is the same alone or in any sweep. A scenario lasts what is left of the
recording after its start (capped by the scenario's ``max_time_s``); a user profile shorter than
a requested ``max_time_s`` is an error.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from safeil_sumo.sim.leaders import ProfileError, SpeedProfile, from_file

LIBRARIES = ("ngsim", "openacc")
MIN_DURATION_S = 20.0  # [s] shortest recording drawn, and shortest remainder after the start
RATE_HZ = 10.0  # [Hz] rate of the library profiles


@dataclass(frozen=True)
class LeaderRecording:
    """A recorded leader: ``times (K,)`` [s from 0], ``speeds (K,)`` [m/s]; the recorded
    follower's speed [m/s] and bumper gap [m] at each time (NaN when not recorded)."""

    recording_id: str
    times: np.ndarray
    speeds: np.ndarray
    follower_speeds: np.ndarray
    gaps: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.times[-1] - self.times[0])


@dataclass(frozen=True)
class LeaderDraw:
    """One scenario's recorded leader: the profile from ``start_s`` and the ego's initial state:
    ``ego_speed_mps`` the recorded follower's speed there, or without a recorded follower (a
    profile file) the leader's own; ``initial_gap_m`` the recorded gap (``None``: take the
    scenario spec's)."""

    recording_id: str
    start_s: float
    profile: SpeedProfile
    ego_speed_mps: float
    initial_gap_m: float | None

    @property
    def duration_s(self) -> float:
        return float(self.profile.times[-1])


@lru_cache(maxsize=8)
def library(source: str, data_dir: str | None = None) -> tuple[LeaderRecording, ...]:
    """The recordings of ``ngsim``, ``openacc``, a profile file or a folder of profile files
    (cached per process). Raises :class:`ProfileError` with one clear line."""
    if source in LIBRARIES:
        from safeil_sumo.data.sources import DEFAULT_DATA_DIR  # the data folder every command reads

        return _from_dataset(source, Path(data_dir) if data_dir else DEFAULT_DATA_DIR)
    path = Path(source).expanduser()
    if path.is_dir():
        files = sorted([*path.glob("*.csv"), *path.glob("*.parquet")])
        if not files:
            raise ProfileError(f"{path}: no .csv or .parquet leader profiles in the folder")
    elif path.is_file():
        files = [path]
    else:
        raise ProfileError(f"leader profile {source!r}: not one of {', '.join(LIBRARIES)} and "
                           "no such file or folder")
    out = []
    for f in files:
        prof = from_file(f, time_column="time", speed_column="speed")
        nan = np.full(len(prof.times), np.nan)
        out.append(LeaderRecording(f.stem, prof.times, prof.speeds, nan, nan))
    return tuple(out)


def _from_dataset(source: str, data_dir: Path) -> tuple[LeaderRecording, ...]:
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.schema import SchemaError
    from safeil_sumo.data.sources import load_source

    try:
        rows, _ = process_drive(load_source(source, data_dir), PipelineConfig(rate_hz=RATE_HZ))
    except (OSError, SchemaError, ValueError) as exc:
        raise ProfileError(f"cannot build the {source} leader library from {data_dir}: "
                           f"{exc}") from exc
    out = []
    for mid, g in rows.groupby("maneuver_id", sort=True):
        t = g["time"].to_numpy(float)
        if t[-1] - t[0] < MIN_DURATION_S:
            continue
        out.append(LeaderRecording(
            str(mid), t - t[0], np.clip(g["v_lead"].to_numpy(float), 0.0, None),
            g["v_x"].to_numpy(float), g["lead_x"].to_numpy(float)))
    if not out:
        raise ProfileError(f"the {source} data in {data_dir} hold no maneuver of "
                           f">= {MIN_DURATION_S:g} s")
    return tuple(out)


def draw(recordings: tuple[LeaderRecording, ...], rng: np.random.Generator,
         max_time_s: float | None = None) -> LeaderDraw:
    """A recording and a start time for one scenario, from ``rng`` only.

    With ``max_time_s`` the remainder after the start must last that long (recordings too short
    are not drawn; if none is long enough: :class:`ProfileError`).
    """
    need = max(MIN_DURATION_S, max_time_s or 0.0)
    usable = [r for r in recordings if r.duration_s >= need - 1e-9]
    if not usable:
        longest = max(r.duration_s for r in recordings)
        raise ProfileError(f"leader profile too short for the scenario: the longest lasts "
                           f"{longest:.1f} s, the scenario needs {need:.1f} s")
    rec = usable[int(rng.integers(len(usable)))]
    start = float(rng.uniform(0.0, rec.duration_s - need)) if rec.duration_s > need else 0.0
    k = int(np.searchsorted(rec.times, start - 1e-9))
    times = rec.times[k:] - rec.times[k]
    profile = SpeedProfile(times, rec.speeds[k:], f"recorded {rec.recording_id} from {start:.1f} s")
    ego = float(rec.follower_speeds[k])
    # no recorded follower: the ego starts at its leader's speed (30 m/s behind a leader at
    # 6.5 m/s is an emergency stop, not car following)
    ego = ego if np.isfinite(ego) else float(rec.speeds[k])
    gap = float(rec.gaps[k])
    return LeaderDraw(rec.recording_id, float(rec.times[k]), profile, ego,
                      gap if np.isfinite(gap) and gap > 0 else None)
