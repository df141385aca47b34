"""The recorded-drive table: one documented format for every data source (Parquet; CSV accepted).

One row per timestamp of one ego vehicle; several recordings may share a file. SI units.

=============== ======== ===========================================================================
column          unit     meaning
=============== ======== ===========================================================================
``recording_id`` str     one continuous recording of one ego vehicle (e.g. an NGSIM pair ``"47-39"``)
``time``         s       strictly increasing within a recording; rows of a recording are contiguous
``x``, ``y``     m       ego FRONT-bumper centre in a world frame (x east / along the road, y left)
``yaw``          rad     ego heading in the world frame, counter-clockwise from +x (within ±2π)
``v_x``          m/s     ego longitudinal speed
``left_c0..3``   m, -,   left lane line in the ego frame: ``y = c0 + c1 x + c2 x² + c3 x³``
                 1/m,    (x forward, y LEFT, origin at the ego's front-bumper centre);
                 1/m²    ``left_c0 > 0`` is the distance to the left line
``right_c0..3``  same    right lane line, same convention (``right_c0 < 0``)
``lead_x``       m       leader's REAR-bumper centre in the ego frame (bumper-to-bumper gap);
                         NaN when there is no leader
``lead_y``       m       same point, lateral; NaN exactly when ``lead_x`` is NaN
``lead_v``       m/s     optional: leader speed when the source measures it (NaN allowed)
``lane_index``   -       optional: lane number, used to detect lane changes (NaN allowed)
``maneuver_id``  str     optional: a source-given segmentation (never split across)
=============== ======== ===========================================================================

Other columns are kept as they are. :func:`load_drive` / :func:`validate_drive` check the layout and
raise :class:`SchemaError` — naming the file, the column and the first bad row (0-based data row,
header not counted) — for: an unreadable, truncated, empty or wrong-format file; a missing column;
a non-numeric value or NaN/inf where a value is required; ``lead_x``/``lead_y`` not NaN together;
rows of a recording that are not contiguous; a time that does not increase within a recording;
implausible units (median speed above 70 m/s looks like km/h or ft/s, |yaw| above 2π looks like
degrees, a median time step above 5 s looks like milliseconds, |c0| above 50 m, a gap above
1000 m). Nothing is dropped or repaired: a file either validates unchanged or is rejected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from safeil_sumo.core.atomic import atomic_path

LINE_COLUMNS = tuple(f"{side}_c{i}" for side in ("left", "right") for i in range(4))
REQUIRED_COLUMNS = (
    "recording_id", "time", "x", "y", "yaw", "v_x", *LINE_COLUMNS, "lead_x", "lead_y",
)
OPTIONAL_COLUMNS = ("lead_v", "lane_index", "maneuver_id")
COLUMNS = REQUIRED_COLUMNS + OPTIONAL_COLUMNS
STRING_COLUMNS = ("recording_id", "maneuver_id")
NUMERIC_COLUMNS = tuple(c for c in COLUMNS if c not in STRING_COLUMNS)
# columns where NaN is meaningful (no leader, not measured, unknown lane)
NULLABLE_COLUMNS = ("lead_x", "lead_y", "lead_v", "lane_index")

MAX_MEDIAN_SPEED = 70.0  # [m/s] above: km/h or ft/s
MAX_ABS_SPEED = 100.0  # [m/s] any single sample
MAX_ABS_YAW = 2.0 * np.pi + 1e-6  # [rad] above: degrees
MAX_MEDIAN_DT = 5.0  # [s] above: milliseconds
MAX_ABS_C0 = 50.0  # [m] lane line offset
MAX_ABS_LEAD = 1000.0  # [m] leader position


class SchemaError(ValueError):
    """A drive file or frame does not follow the schema; the message names file, column, row."""


def _fail(source: str, column: str | None, row: int | None, what: str) -> SchemaError:
    where = [source]
    if column is not None:
        where.append(f"column {column!r}")
    if row is not None:
        where.append(f"row {row}")
    what = " ".join(what.split())  # reader messages may span lines: keep one line
    return SchemaError(f"{': '.join([', '.join(where), what])}")


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def validate_drive(df: pd.DataFrame, source: str = "<frame>") -> pd.DataFrame:
    """Check ``df`` against the schema; return a copy with canonical dtypes and column order.

    ``source`` names the file (or frame) in error messages. Raises :class:`SchemaError`.
    """
    _check_columns(df, source)
    out = df.reset_index(drop=True).copy()
    for col in STRING_COLUMNS:
        if col in out.columns:
            out[col] = _string_column(out[col], col, source)
    for col in NUMERIC_COLUMNS:
        if col in out.columns:
            out[col] = _numeric_column(out[col], col, source)
    lx, ly = out["lead_x"].to_numpy(), out["lead_y"].to_numpy()
    mismatch = np.isnan(lx) != np.isnan(ly)
    if mismatch.any():
        raise _fail(source, "lead_y", _first(mismatch), "lead_x and lead_y must be NaN together")
    starts, dt = _check_time_order(out, source)
    _check_plausible_units(out, starts, dt, source)
    order = [c for c in COLUMNS if c in out.columns] + [c for c in out.columns if c not in COLUMNS]
    return out[order]


def _check_columns(df: pd.DataFrame, source: str) -> None:
    """A non-empty table with unique column names and every required column."""
    if not isinstance(df, pd.DataFrame):
        raise _fail(source, None, None, f"expected a table, got {type(df).__name__}")
    if len(df) == 0:
        raise _fail(source, None, None, "no rows (empty file)")
    cols = [str(c) for c in df.columns]
    if len(set(cols)) != len(cols):
        dup = next(c for c in cols if cols.count(c) > 1)
        raise _fail(source, dup, None, "duplicate column")
    for col in REQUIRED_COLUMNS:
        if col not in df.columns:
            raise _fail(source, col, None, f"missing required column (have: {', '.join(cols)})")


def _string_column(vals: pd.Series, col: str, source: str) -> pd.Series:
    """``vals`` as strings, none missing or empty."""
    bad = vals.isna().to_numpy()
    if bad.any():
        raise _fail(source, col, _first(bad), "missing value (NaN/empty) not allowed")
    out = vals.astype(str)
    empty = (out.str.len() == 0).to_numpy()
    if empty.any():
        raise _fail(source, col, _first(empty), "empty string not allowed")
    return out


def _numeric_column(raw: pd.Series, col: str, source: str) -> np.ndarray:
    """``raw`` as finite floats (NaN only where missing, and only in a nullable column); no
    booleans, no text."""
    if pd.api.types.is_bool_dtype(raw) or raw.dtype == object and raw.map(
        lambda v: isinstance(v, (bool, np.bool_))
    ).any():
        raise _fail(source, col, None, "boolean values are not numbers")
    try:
        num = pd.to_numeric(raw, errors="coerce").astype(float).to_numpy()
    except (TypeError, ValueError, OverflowError) as exc:
        raise _fail(source, col, None, f"not numeric ({exc})") from exc
    was_missing = raw.isna().to_numpy()
    not_number = np.isnan(num) & ~was_missing
    if not_number.any():
        i = _first(not_number)
        raise _fail(source, col, i, f"not a number: {raw.iloc[i]!r}")
    if np.isinf(num).any():
        raise _fail(source, col, _first(np.isinf(num)), "infinite value")
    if col not in NULLABLE_COLUMNS and np.isnan(num).any():
        raise _fail(source, col, _first(np.isnan(num)), "missing value (NaN) not allowed")
    return num


def _check_time_order(out: pd.DataFrame, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Each recording's rows contiguous, its time strictly increasing: ``(starts, dt)``, the
    rows where a recording starts and the time steps [s] between rows."""
    rec = out["recording_id"].to_numpy()
    starts = np.r_[True, rec[1:] != rec[:-1]]
    seen: set[str] = set()
    for i in np.flatnonzero(starts):
        if rec[i] in seen:
            raise _fail(source, "recording_id", int(i), f"rows of {rec[i]!r} are not contiguous")
        seen.add(rec[i])
    t = out["time"].to_numpy()
    dt = np.diff(t)
    bad_t = np.r_[False, (dt <= 0) & ~starts[1:]]
    if bad_t.any():
        row = _first(bad_t)
        raise _fail(source, "time", row, f"time does not increase ({float(t[row - 1])!r} -> "
                    f"{float(t[row])!r})")
    return starts, dt


def _check_plausible_units(out: pd.DataFrame, starts: np.ndarray, dt: np.ndarray,
                           source: str) -> None:
    """Speeds, angles, offsets and time steps in the schema's units (m/s, rad, m, s), not
    km/h, degrees or milliseconds."""
    v = out["v_x"].to_numpy()
    if np.median(np.abs(v)) > MAX_MEDIAN_SPEED:
        raise _fail(source, "v_x", None, f"median speed {np.median(np.abs(v)):.1f} m/s is "
                    "implausible: looks like km/h or ft/s (schema is m/s)")
    checks = (
        ("v_x", MAX_ABS_SPEED, "speed [m/s]"),
        ("yaw", MAX_ABS_YAW, "heading [rad] (looks like degrees)"),
        ("left_c0", MAX_ABS_C0, "lane-line offset [m]"),
        ("right_c0", MAX_ABS_C0, "lane-line offset [m]"),
        ("lead_x", MAX_ABS_LEAD, "leader position [m]"),
        ("lead_y", MAX_ABS_LEAD, "leader position [m]"),
    )
    for col, limit, what in checks:
        too_big = np.abs(np.nan_to_num(out[col].to_numpy())) > limit
        if too_big.any():
            i = _first(too_big)
            raise _fail(source, col, i, f"implausible {what}: {out[col].iloc[i]!r}")
    inner = dt[~starts[1:]]
    if len(inner) and np.median(inner) > MAX_MEDIAN_DT:
        raise _fail(source, "time", None, f"median time step {np.median(inner):g} s is "
                    "implausible: looks like milliseconds (schema is seconds)")


def load_drive(path: str | Path) -> pd.DataFrame:
    """Read and validate a drive: Parquet, or CSV (``.csv`` / ``.csv.gz``). Raises SchemaError."""
    path = Path(path)
    name = str(path)
    if not path.is_file():
        raise _fail(name, None, None, "no such file")
    suffixes = "".join(path.suffixes[-2:]).lower()
    is_csv = suffixes.endswith((".csv", ".csv.gz"))
    try:
        if is_csv:
            df = pd.read_csv(path, dtype={"recording_id": str, "maneuver_id": str})
        else:
            df = pq.read_table(path).to_pandas()
    except pd.errors.EmptyDataError as exc:
        raise _fail(name, None, None, "empty file") from exc
    except (OSError, ValueError, pa.ArrowException, UnicodeDecodeError, EOFError) as exc:
        kind = "CSV" if is_csv else "Parquet"
        raise _fail(name, None, None, f"not a readable {kind} file (truncated or wrong "
                    f"format?): {exc}") from exc
    if suffixes.endswith(".csv") and not _ends_with_newline(path):
        # a CSV cut mid-row still parses (its last value shortened): refuse it
        raise _fail(name, None, len(df) - 1, "the file does not end with a newline "
                    "(truncated?)")
    return validate_drive(df, name)


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as f:
        f.seek(-1, 2)
        return f.read(1) in (b"\n", b"\r")


def save_drive(df: pd.DataFrame, path: str | Path) -> None:
    """Validate and write Parquet atomically (temporary file, then rename)."""
    path = Path(path)
    clean = validate_drive(df, str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        pq.write_table(pa.Table.from_pandas(clean, preserve_index=False), tmp)
