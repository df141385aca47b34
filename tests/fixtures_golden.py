"""The golden logs' columns, tolerances and comparison (tests/sim/test_golden.py's references,
also compared by other closed-loop tests): see tests/sim/test_golden.py for what they promise."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd

GOLDEN_DIR = Path(__file__).parent / "golden"

# discrete columns: equal at every step
FLAG_COLUMNS = ("lane_departure", "ttc_flag", "collision")
# continuous columns and their absolute tolerance across machines (units in the comments);
# a relative tolerance of 1e-9 is added for the large values (x ~ 1e3 m, ttc up to 1e3 s)
CONTINUOUS_ATOL = {
    "t": 1e-9,  # s
    "x": 1e-6, "y": 1e-6, "front_x": 1e-6, "front_y": 1e-6,  # m
    "yaw": 1e-8, "steer": 1e-8, "steer_cmd": 1e-8,  # rad
    "yaw_rate": 1e-8,  # rad/s
    "v": 1e-6, "vy": 1e-6,  # m/s
    "accel_cmd": 1e-6,  # m/s^2
    "s": 1e-6, "d": 1e-6, "d_min": 1e-6, "d_max": 1e-6,  # m
    "c0l": 1e-6, "c0r": 1e-6,  # m
    "c1l": 1e-8, "c1r": 1e-8,  # -
    "c2l": 1e-10, "c2r": 1e-10,  # 1/m
    "v_lead_sensed": 1e-6, "leader_v": 1e-6,  # m/s
    "d_lead_sensed": 1e-6, "leader_x": 1e-6, "leader_y": 1e-6, "gap": 1e-6,  # m
    "ttc": 1e-6,  # s
    "path_fraction": 1e-9,  # -
}
GOLDEN_COLUMNS = tuple(CONTINUOUS_ATOL) + FLAG_COLUMNS


def log_hash(log: pd.DataFrame) -> str:
    """SHA-256 over each golden column's name and float64 bytes, in column order."""
    h = hashlib.sha256()
    for col in GOLDEN_COLUMNS:
        h.update(col.encode())
        h.update(np.ascontiguousarray(log[col].to_numpy(dtype=np.float64)).tobytes())
    return h.hexdigest()


def compare_with_reference(log: pd.DataFrame, end_reason: str, ref) -> list[str]:
    """Every difference between a log and a stored reference beyond the tolerances, as text."""
    problems = []
    if (int(ref["rows"]), str(ref["end_reason"])) != (len(log), end_reason):
        want = (int(ref["rows"]), str(ref["end_reason"]))
        return [f"outcome {(len(log), end_reason)} != reference {want}"]
    for col in FLAG_COLUMNS:
        got, want = log[col].to_numpy(dtype=np.float64), ref[col]
        if not np.array_equal(got, want):
            steps = np.flatnonzero(got != want)
            problems.append(f"{col}: differs at {len(steps)} steps, first {steps[0]}")
    for col, atol in CONTINUOUS_ATOL.items():
        got, want = log[col].to_numpy(dtype=np.float64), ref[col]
        if not np.array_equal(np.isfinite(got), np.isfinite(want)) or not np.array_equal(
                got[~np.isfinite(got)], want[~np.isfinite(want)], equal_nan=True):
            problems.append(f"{col}: non-finite values (inf/nan) at other steps")
            continue
        fin = np.isfinite(want)
        err = np.abs(got[fin] - want[fin])
        bad = err > atol + 1e-9 * np.abs(want[fin])
        if bad.any():
            problems.append(f"{col}: {int(bad.sum())} steps beyond {atol:g}, "
                            f"largest difference {err.max():.3g}")
    return problems
