"""Leader speed profiles: constant, piecewise-linear, or a recorded time series (CSV/Parquet).

One representation covers all three: knots ``times`` [s] and ``speeds`` [m/s], linearly
interpolated and held constant outside the knots.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np
import pandas as pd

# The fastest a real car's speed changes, averaged over PLAUSIBLE_WINDOW_S (a recorded profile
# that changes faster is a sensor dropout or glitch, not a leader to test against):
# - braking: tyre-limited, ~8-10 m/s^2 for an ordinary car with ABS on dry asphalt, ~13 m/s^2
#   for the best sports cars (100-0 km/h in ~30 m); 15 m/s^2 (1.5 g) is beyond any road car;
# - accelerating: ~2-5 m/s^2 for ordinary cars, ~1 g only in the launch of the quickest ones;
# - the window: brakes take ~0.2-0.3 s to build up, and a mean over 0.5 s makes the check
#   independent of the sample rate and blind to tracking noise.
# Measured on the human profiles the project uses (docs/reliability.md): the NGSIM and OpenACC
# leader libraries stay within -5.6 / +4.6 m/s^2, every raw speed of the shared data within
# -9.7 / +6.2 m/s^2 but one OpenACC GNSS glitch (+10.4 m/s^2 at 26-33 m/s).
MAX_BRAKING_MPS2 = 15.0  # [m/s^2]
MAX_ACCEL_MPS2 = 10.0  # [m/s^2]
PLAUSIBLE_WINDOW_S = 0.5  # [s]


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

    @overload
    def speed_at(self, t: float) -> float: ...
    @overload
    def speed_at(self, t: np.ndarray) -> np.ndarray: ...

    def speed_at(self, t: float | np.ndarray) -> float | np.ndarray:
        """Speed [m/s] at time ``t`` [s] (a float, or an array of the times' shape)."""
        return np.interp(t, self.times, self.speeds)

    @property
    def initial_speed(self) -> float:
        return float(self.speeds[0])


def implausible_change(times: np.ndarray, speeds: np.ndarray,
                       window_s: float = PLAUSIBLE_WINDOW_S,
                       max_braking_mps2: float = MAX_BRAKING_MPS2,
                       max_accel_mps2: float = MAX_ACCEL_MPS2) -> str | None:
    """The first speed change no car can make, in words, or None.

    ``times (K,)`` [s] strictly increasing, ``speeds (K,)`` [m/s], linearly interpolated as the
    leader drives them. A change is implausible when the mean acceleration over ``window_s``
    (the whole profile if shorter) falls below ``-max_braking_mps2`` or rises above
    ``max_accel_mps2``; the words name the steepest sample-to-sample step of that window, e.g.
    ``"speed falls 25.8 m/s in 0.1 s at t = 12.3 s (-258 m/s^2; ...)"``.
    """
    t, v = np.asarray(times, float), np.asarray(speeds, float)
    w = min(window_s, float(t[-1] - t[0])) if len(t) > 1 else 0.0
    if w <= 0.0:
        return None
    # v(s + w) - v(s) of a piecewise-linear v is extreme where s or s + w is a sample time
    s = np.unique(np.r_[t, t - w])
    s = s[(s >= t[0]) & (s <= t[-1] - w)]
    mean = (np.interp(s + w, t, v) - np.interp(s, t, v)) / w
    bad = np.flatnonzero((mean < -max_braking_mps2) | (mean > max_accel_mps2))
    if not len(bad):
        return None
    k = bad[0]
    sign = np.sign(mean[k])
    steps = np.flatnonzero((t[1:] > s[k]) & (t[:-1] < s[k] + w))  # steps overlapping the window
    change = sign * np.diff(v)[steps]
    i = steps[np.flatnonzero(change >= change.max() - 1e-9)[0]]  # the first of equal steps
    dv, dt = float(v[i + 1] - v[i]), float(t[i + 1] - t[i])
    limit = -max_braking_mps2 if sign < 0 else max_accel_mps2
    return (f"speed {'falls' if sign < 0 else 'rises'} {abs(dv):.1f} m/s in {dt:.2g} s at "
            f"t = {t[i + 1]:.1f} s ({dv / dt:+.0f} m/s²; {mean[k]:+.1f} m/s² over {w:.2g} s, "
            f"beyond the plausible {limit:+g} m/s²)")


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
    than ``max_gap_s`` [s] between samples, negative speeds, or a speed change no car can make
    (:func:`implausible_change`: a sensor dropout makes a meaningless scenario).
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
    profile = SpeedProfile(t - t[0], v, str(path))  # finite, increasing, >= 0 from here
    why = implausible_change(t, v)  # the file's own clock: the time the user finds in it
    if why is not None:
        raise ProfileError(f"{path}: {why}: a sensor dropout? fix or trim the profile")
    return profile
