"""Leader speed profiles: constant, piecewise-linear, or a recorded time series (CSV/Parquet).

One representation covers all three: knots ``times`` [s] and ``speeds`` [m/s], linearly
interpolated and held constant outside the knots.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd


class ProfileError(ValueError):
    """A leader speed profile that cannot be driven (bad file, gaps, negative speeds...)."""


@dataclass(frozen=True)
class SpeedProfile:
    """Speed [m/s] as a function of time [s] since the scenario start."""

    times: np.ndarray  # (K,) strictly increasing [s]
    speeds: np.ndarray  # (K,) >= 0 [m/s]
    label: str = "profile"

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=float)
        v = np.asarray(self.speeds, dtype=float)
        if t.ndim != 1 or t.shape != v.shape or len(t) == 0:
            raise ProfileError("a speed profile needs equal-length 1-D times and speeds")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
            raise ProfileError(f"{self.label}: times and speeds must be finite (found NaN/inf)")
        if np.any(np.diff(t) <= 0):
            i = int(np.argmax(np.diff(t) <= 0)) + 1
            raise ProfileError(f"{self.label}: times must increase strictly (row {i})")
        if np.any(v < 0):
            i = int(np.argmax(v < 0))
            raise ProfileError(f"{self.label}: negative speed {v[i]:.3f} m/s at row {i}")
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "speeds", v)

    def speed_at(self, t: float | np.ndarray) -> float | np.ndarray:
        """Speed [m/s] at time ``t`` [s]."""
        return np.interp(t, self.times, self.speeds)

    @property
    def initial_speed(self) -> float:
        return float(self.speeds[0])


def constant(speed_mps: float) -> SpeedProfile:
    """A leader at constant ``speed_mps`` (the paper's safety scenarios)."""
    return SpeedProfile(np.array([0.0]), np.array([float(speed_mps)]), f"constant {speed_mps:.2f}")


def piecewise(times_s: list[float], speeds_mps: list[float]) -> SpeedProfile:
    """Linear interpolation between ``(time, speed)`` knots, e.g. a braking leader."""
    return SpeedProfile(np.asarray(times_s, float), np.asarray(speeds_mps, float), "piecewise")


def from_file(
    path: str | Path, time_column: str = "time", speed_column: str = "speed",
    max_gap_s: float = 1.0,
) -> SpeedProfile:
    """A recorded speed time series from CSV or Parquet (time from the first row).

    Raises :class:`ProfileError` for a missing file or column, non-numeric values, gaps longer
    than ``max_gap_s`` [s] between samples, or negative speeds.
    """
    path = Path(path)
    if not path.is_file():
        raise ProfileError(f"leader profile not found: {path}")
    try:
        df = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    except Exception as exc:  # pandas/pyarrow raise many types for a bad file
        raise ProfileError(f"{path}: cannot read leader profile ({exc})") from exc
    for col in (time_column, speed_column):
        if col not in df.columns:
            raise ProfileError(f"{path}: missing column {col!r} (has {list(df.columns)})")
    try:
        t = df[time_column].to_numpy(float)
        v = df[speed_column].to_numpy(float)
    except (TypeError, ValueError) as exc:
        raise ProfileError(f"{path}: non-numeric values ({exc})") from exc
    if len(t) == 0:
        raise ProfileError(f"{path}: the profile is empty")
    gaps = np.diff(t)
    if np.any(gaps > max_gap_s):
        i = int(np.argmax(gaps > max_gap_s)) + 1
        raise ProfileError(f"{path}: gap of {gaps[i - 1]:.2f} s before row {i} (> {max_gap_s} s)")
    return SpeedProfile(t - t[0], v, str(path))
