"""A plain car-following CSV (time, speed, gap, ...) into the drive schema, its columns mapped by
name; see :mod:`safeil_sumo.data.importers` (its module doc, section "car-following CSV")."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.data.importers import (
    MIN_GAP,
    OPENACC_LANE_WIDTH,
    ImportArgumentError,
    _read_table,
    check_speeds,
    openacc_recording_prefix,
)
from safeil_sumo.data.schema import SchemaError, validate_drive

# role -> what it is; the file's columns are mapped onto these names
CSV_ROLES = {
    "time": "time [s]",
    "v": "follower speed [speed unit]",
    "gap": "bumper-to-bumper gap to the leader [m], empty = no leader",
    "lead_v": "leader speed [speed unit] (optional)",
    "id": "recording id (optional): rows split into recordings by id (and driver)",
    "driver": "driver (optional): rows split into recordings by driver (and id)",
}
CSV_REQUIRED_ROLES = ("time", "v", "gap")
SPEED_UNITS = {"m/s": 1.0, "km/h": 1.0 / 3.6}  # unit -> m/s per unit


def parse_column_map(text: str) -> dict[str, str]:
    """``"time=t,v=follower_speed,gap=gap"`` -> ``{"time": "t", "v": "follower_speed", ...}``
    (role = file column, comma-separated, blanks around names ignored). Unknown or repeated
    roles and items without ``=`` raise :class:`ImportArgumentError` naming the item."""
    out: dict[str, str] = {}
    for item in (i.strip() for i in text.split(",")):
        role, sep, column = (p.strip() for p in item.partition("="))
        if not sep or not role or not column:
            raise ImportArgumentError(f"column map {text!r}: item {item!r} is not role=column")
        if role not in CSV_ROLES:
            raise ImportArgumentError(f"column map {text!r}: unknown role {role!r} (known: "
                                      f"{', '.join(CSV_ROLES)})")
        if role in out:
            raise ImportArgumentError(f"column map {text!r}: role {role!r} mapped twice")
        out[role] = column
    return out


def resolve_column_map(mapping: Mapping[str, str] | str | None, columns: list[str],
                       source: str) -> dict[str, str]:
    """Role -> the file's column: the mapped ones (each must be in ``columns``), and every other
    role whose own name is a column. A missing column names the role, the column and the columns
    found (SchemaError)."""
    given = parse_column_map(mapping) if isinstance(mapping, str) else dict(mapping or {})
    unknown = [r for r in given if r not in CSV_ROLES]
    if unknown:
        raise ImportArgumentError(f"column map: unknown role {unknown[0]!r} (known: "
                                  f"{', '.join(CSV_ROLES)})")
    have = ", ".join(columns)
    for role, col in given.items():
        if col not in columns:
            raise SchemaError(f"{source}: missing column {col!r} (mapped to {role!r}; have: "
                              f"{have})")
    out = dict(given)
    for role in CSV_ROLES:
        if role not in out and role in columns:
            out[role] = role
    for role in CSV_REQUIRED_ROLES:
        if role not in out:
            raise SchemaError(f"{source}: no column for {role!r} ({CSV_ROLES[role]}): map one, "
                              f"e.g. {role}=<column> (have: {have})")
    return out


def _numbers(raw: pd.DataFrame, column: str, source: str, required: bool) -> np.ndarray:
    """``(N,)`` floats of one column; text names the row; an empty cell too when ``required``."""
    num = pd.to_numeric(raw[column], errors="coerce").to_numpy(float)
    text = np.isnan(num) & raw[column].notna().to_numpy()
    empty = np.isnan(num) & required
    bad = text | empty
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        what = f"not a number: {raw[column].iloc[i]!r}" if text[i] else "empty (a value needed)"
        raise SchemaError(f"{source}, column {column!r}, row {i}: {what}")
    if np.isinf(num).any():
        i = int(np.flatnonzero(np.isinf(num))[0])
        raise SchemaError(f"{source}, column {column!r}, row {i}: infinite value")
    return num


def _recording_keys(raw: pd.DataFrame, cols: dict[str, str], prefix: str) -> np.ndarray:
    """``(N,)`` recording id of each row: ``<prefix>[_<driver>][_<id>]``."""
    key = pd.Series(prefix, index=raw.index, dtype=object)
    for role in ("driver", "id"):
        if role in cols:
            part = raw[cols[role]].astype(str).str.strip()
            key = key + "_" + part.str.replace(r"[^A-Za-z0-9_.-]", "_", regex=True)
    return key.to_numpy(dtype=object)


def _increasing_time(t: np.ndarray, rec: np.ndarray, order: np.ndarray, source: str,
                     column: str) -> None:
    """Time strictly increasing within each recording (rows ``order`` grouped by recording); the
    message names the FILE row."""
    ts, rs = t[order], rec[order]
    bad = np.r_[False, (np.diff(ts) <= 0) & (rs[1:] == rs[:-1])]
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise SchemaError(f"{source}, column {column!r}, row {int(order[k])}: time does not "
                          f"increase within recording {rs[k]!r} ({ts[k - 1]:g} -> {ts[k]:g})")


def import_car_following_csv(path: str | Path, mapping: Mapping[str, str] | str | None = None,
                             speed_unit: str = "m/s") -> pd.DataFrame:
    """A car-following CSV, one row per sample: ``time`` [s], follower speed ``v``, bumper gap
    ``gap`` [m] (empty: no leader), optional ``lead_v``, ``id``, ``driver`` (see
    :data:`CSV_ROLES`), mapped from the file's columns by ``mapping`` (a dict or the
    ``"time=t,v=speed,gap=gap"`` form); speeds in ``speed_unit`` (``"m/s"`` or ``"km/h"``).

    Longitudinal only: the ego drives a straight lane of width 3.5 m, centred (as OpenACC), its
    ``x`` the trapezoid integral of ``v`` from 0. Rows keep the file's order within a recording
    (recordings grouped in order of first appearance). Raises SchemaError (one line naming file,
    column and 0-based data row) on the bad inputs listed in ``docs/your_own_drives.md``.
    """
    if speed_unit not in SPEED_UNITS:
        raise ImportArgumentError(f"speed unit {speed_unit!r} unknown (known: "
                                  f"{', '.join(SPEED_UNITS)})")
    path = Path(path)
    src = str(path)
    raw = _read_table(path, dtype=str, keep_default_na=True)
    raw.columns = [str(c).strip() for c in raw.columns]
    if len(raw) == 0:
        raise SchemaError(f"{src}: empty file (a header, no rows)")
    cols = resolve_column_map(mapping, list(raw.columns), src)
    t = _numbers(raw, cols["time"], src, required=True)
    scale = SPEED_UNITS[speed_unit]
    v = _numbers(raw, cols["v"], src, required=True) * scale
    check_speeds(v, src, cols["v"], speed_unit)
    gap = _numbers(raw, cols["gap"], src, required=False)
    lead_v = (_numbers(raw, cols["lead_v"], src, required=False) * scale if "lead_v" in cols
              else np.full(len(raw), np.nan))
    check_speeds(lead_v, src, cols.get("lead_v", "lead_v"), speed_unit)
    has_lead = np.isfinite(gap)
    if not has_lead.any():
        raise SchemaError(f"{src}, column {cols['gap']!r}: no row with a leader (the gap is "
                          "empty everywhere)")
    rec = _recording_keys(raw, cols, openacc_recording_prefix(path))
    codes, _ = pd.factorize(rec)  # recordings in order of first appearance
    order = np.argsort(codes, kind="stable")
    _increasing_time(t, rec, order, src, cols["time"])
    return _car_following_drive(rec[order], t[order], v[order], gap[order], lead_v[order], src,
                                {"mapping": cols, "speed_unit": speed_unit})


def _car_following_drive(rec: np.ndarray, t: np.ndarray, v: np.ndarray, gap: np.ndarray,
                         lead_v: np.ndarray, src: str, notes: dict[str, object]) -> pd.DataFrame:
    """The drive frame of grouped, time-ordered samples ``(N,)`` in SI units."""
    starts = np.r_[True, rec[1:] != rec[:-1]]
    # x = trapezoid integral of v, restarted at 0 in each recording
    step = np.r_[0.0, 0.5 * (v[1:] + v[:-1]) * np.diff(t)]
    step[starts] = 0.0
    run = np.cumsum(starts) - 1
    total = np.cumsum(step)
    x = total - (total[starts])[run]
    has_lead = np.isfinite(gap)
    clipped = has_lead & (gap < MIN_GAP)
    half = 0.5 * OPENACC_LANE_WIDTH
    df = pd.DataFrame({
        "recording_id": rec, "time": t, "x": x, "y": 0.0, "yaw": 0.0, "v_x": v,
        "left_c0": half, "left_c1": 0.0, "left_c2": 0.0, "left_c3": 0.0,
        "right_c0": -half, "right_c1": 0.0, "right_c2": 0.0, "right_c3": 0.0,
        "lead_x": np.where(has_lead, np.maximum(gap, MIN_GAP), np.nan),
        "lead_y": np.where(has_lead, 0.0, np.nan),
        "lead_v": np.where(has_lead, lead_v, np.nan),
    })
    out = validate_drive(df, src)
    out.attrs["import_stats"] = {
        "source": src, **notes, "recordings": int(starts.sum()), "rows": len(out),
        "rows_without_leader": int((~has_lead).sum()), "gap_clipped": int(clipped.sum()),
        "lead_speed_missing": int((has_lead & ~np.isfinite(lead_v)).sum()),
    }
    return out
