"""Experience tuples (state, future trajectory) — the hand-off from data processing to learning.

Stored as one Parquet table, one row per tuple, plain numeric columns (no pickle):
``maneuver_id`` (str), ``source`` (str), ``t`` [s] time of the state in its recording,
``f_<name>`` the 9 planner features (:data:`safeil_sumo.core.features.FEATURE_NAMES`),
``cp_x1, cp_y1, .., cp_x3, cp_y3`` [m] least-squares B-spline control points of the future,
``fx_k, fy_k`` [m] the future trajectory (k = 1..H) in the ego frame at ``t``.
The horizon [s] and sample rate [Hz] are stored in the Parquet schema metadata.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.core.features import FEATURE_NAMES, N_FEATURES


@dataclass(frozen=True)
class Tuples:
    """N tuples with a future of H samples over ``horizon`` [s].

    features: (N, 9); control_points: (N, 3, 2) [m]; future: (N, H, 2) [m] ego frame at t;
    maneuver_id: (N,) str; source: (N,) str; t: (N,) [s].
    """

    features: np.ndarray
    control_points: np.ndarray
    future: np.ndarray
    maneuver_id: np.ndarray
    source: np.ndarray
    t: np.ndarray
    horizon: float
    rate_hz: float

    def __post_init__(self) -> None:
        n = len(self.features)
        if self.features.shape != (n, N_FEATURES):
            raise ValueError(f"features must be (N, {N_FEATURES}), got {self.features.shape}")
        if self.control_points.shape != (n, 3, 2):
            raise ValueError(f"control_points must be (N, 3, 2), got {self.control_points.shape}")
        if self.future.ndim != 3 or self.future.shape[0] != n or self.future.shape[2] != 2:
            raise ValueError(f"future must be (N, H, 2), got {self.future.shape}")
        for name in ("maneuver_id", "source", "t"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} must have length {n}")

    def __len__(self) -> int:
        return len(self.features)

    @property
    def future_times(self) -> np.ndarray:
        """Times ``(H,)`` [s] of the future samples after the state."""
        h = self.future.shape[1]
        return np.arange(1, h + 1) / self.rate_hz

    def subset(self, mask: np.ndarray) -> Tuples:
        """The tuples selected by a boolean mask or index array."""
        return Tuples(
            self.features[mask], self.control_points[mask], self.future[mask],
            self.maneuver_id[mask], self.source[mask], self.t[mask], self.horizon, self.rate_hz,
        )

    @staticmethod
    def concat(parts: list[Tuples]) -> Tuples:
        """One set from several (e.g. sources); horizons and rates must agree."""
        if not parts:
            raise ValueError("nothing to concatenate")
        first = parts[0]
        for p in parts[1:]:
            if not (np.isclose(p.horizon, first.horizon) and np.isclose(p.rate_hz, first.rate_hz)
                    and p.future.shape[1] == first.future.shape[1]):
                raise ValueError(
                    f"tuples disagree: horizon {p.horizon} vs {first.horizon} s, rate "
                    f"{p.rate_hz} vs {first.rate_hz} Hz, {p.future.shape[1]} vs "
                    f"{first.future.shape[1]} future samples"
                )
        cat = np.concatenate
        return Tuples(
            cat([p.features for p in parts]), cat([p.control_points for p in parts]),
            cat([p.future for p in parts]), cat([p.maneuver_id.astype(str) for p in parts]),
            cat([p.source.astype(str) for p in parts]), cat([p.t for p in parts]),
            first.horizon, first.rate_hz,
        )

    @property
    def maneuvers(self) -> np.ndarray:
        """Sorted unique maneuver ids."""
        return np.unique(self.maneuver_id)

    def to_frame(self) -> pd.DataFrame:
        h = self.future.shape[1]
        cols: dict[str, np.ndarray] = {
            "maneuver_id": self.maneuver_id.astype(str),
            "source": self.source.astype(str),
            "t": self.t,
        }
        for j, name in enumerate(FEATURE_NAMES):
            cols[f"f_{name}"] = self.features[:, j]
        for i in range(3):
            cols[f"cp_x{i + 1}"] = self.control_points[:, i, 0]
            cols[f"cp_y{i + 1}"] = self.control_points[:, i, 1]
        for k in range(h):
            cols[f"fx_{k + 1}"] = self.future[:, k, 0]
            cols[f"fy_{k + 1}"] = self.future[:, k, 1]
        return pd.DataFrame(cols)

    def save(self, path: str | Path) -> None:
        """Write Parquet atomically (temporary file, then rename)."""
        path = Path(path)
        table = pa.Table.from_pandas(self.to_frame(), preserve_index=False)
        meta = {"horizon_s": self.horizon, "rate_hz": self.rate_hz, "format": "safeil-tuples-1"}
        table = table.replace_schema_metadata(
            {**(table.schema.metadata or {}), b"safeil": json.dumps(meta).encode()}
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            pq.write_table(table, tmp)

    @staticmethod
    def load(path: str | Path) -> Tuples:
        """Read a tuples file; ``ValueError`` naming the file (and column, row) if it is not one
        (unreadable, truncated, no/malformed metadata, missing column, non-numeric or NaN/inf)."""
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"{path}: no such tuples file")
        try:
            table = pq.read_table(path)
        except (OSError, pa.ArrowInvalid) as exc:
            raise ValueError(f"{path}: not a readable Parquet tuples file ({exc})") from exc
        raw = (table.schema.metadata or {}).get(b"safeil")
        if raw is None:
            raise ValueError(f"{path}: Parquet file has no safeil tuples metadata")
        try:
            meta = json.loads(raw)
            horizon, rate = float(meta["horizon_s"]), float(meta["rate_hz"])
        except (ValueError, TypeError, KeyError) as exc:
            raise ValueError(f"{path}: malformed safeil tuples metadata ({exc!r})") from exc
        if not (math.isfinite(horizon) and horizon > 0 and math.isfinite(rate) and rate > 0):
            raise ValueError(f"{path}: horizon {horizon} s and rate {rate} Hz must be > 0")
        df = table.to_pandas()
        h = sum(1 for c in df.columns if c.startswith("fx_"))
        numeric = (["t", *(f"f_{n}" for n in FEATURE_NAMES)]
                   + [f"cp_{a}{i + 1}" for i in range(3) for a in "xy"]
                   + [f"f{a}_{k + 1}" for k in range(h) for a in "xy"])
        missing = [c for c in ["maneuver_id", "source", *numeric] if c not in df.columns]
        if h == 0 or missing:
            raise ValueError(f"{path}: missing tuples column(s) {missing or ['fx_1', 'fy_1']}")
        for col in numeric:  # a bad value names its column and row, never trains silently
            try:
                vals = df[col].to_numpy(float)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{path}, column {col!r}: not numeric ({exc})") from exc
            bad = ~np.isfinite(vals)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(f"{path}, column {col!r}, row {i}: non-finite value {vals[i]}")
        features = df[[f"f_{n}" for n in FEATURE_NAMES]].to_numpy(float)
        cp = np.stack(
            [df[[f"cp_x{i + 1}", f"cp_y{i + 1}"]].to_numpy(float) for i in range(3)], axis=1
        )
        fut = np.stack(
            [df[[f"fx_{k + 1}", f"fy_{k + 1}"]].to_numpy(float) for k in range(h)], axis=1
        )
        return Tuples(
            features, cp, fut, df["maneuver_id"].to_numpy(str), df["source"].to_numpy(str),
            df["t"].to_numpy(float), horizon, rate,
        )
