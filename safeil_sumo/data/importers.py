"""Real recordings into the drive schema (:mod:`safeil_sumo.data.schema`): NGSIM, JRC OpenACC, highD
(:mod:`~safeil_sumo.data.highd`) and plain car-following CSVs
(:mod:`~safeil_sumo.data.car_following_csv`); :func:`safeil_sumo.data.drive_import.import_drives`
reads any of them by a ``"format:path"`` spec (``docs/your_own_drives.md``).

Every importer takes a path to the ORIGINAL file layout, checks the columns it needs (a missing
one raises :class:`~safeil_sumo.data.schema.SchemaError` naming file and column) and returns a
validated drive frame. Counts of repaired values (clipped gaps, filled leader positions, ...) are
in ``df.attrs["import_stats"]`` so a report can show them.

NGSIM (US-101 / I-80 layout, a straight road):
- world frame: ``x = Local_Y`` (along the road), ``y = -Local_X`` (Local_X grows to the RIGHT from
  the road's left edge; the schema's y is LEFT). Positions are the vehicle's front centre.
- heading ``yaw`` relative to the road = ``atan2(v_lat, max(v_long, 1 m/s))`` from Savitzky-Golay
  derivatives (window 1.5 s, order 2) of the lateral and longitudinal position: the raw lateral
  position is too noisy to differentiate directly; the 1 m/s floor keeps near-standstill heading
  from blowing up.
- lane lines: lane ``i`` (1 = leftmost) spans ``Local_X`` in ``[(i-1) W + o, i W + o]``,
  ``W = 12 ft``, with the grid offset ``o`` = the median over all rows of the vehicles' offset
  from their grid lane centre (clipped to ``±W/4``; 0 below :data:`NGSIM_GRID_MIN_ROWS` rows).
  On the I-80 pairs every lane's median sits 0.34-0.40 m left of the 12 ft grid (``o = -0.37``
  m); with the plain grid 6.7 % of the samples put a 1.76 m wide car's body over a lane line,
  with the offset grid 1.3 % (``import_stats["lane_grid_offset_m"]``).
  A straight line at world ``y = b`` seen from the ego at ``(x0, y0)`` with heading ``psi`` is
  ``c0 = (b - y0) / cos(psi)``, ``c1 = -tan(psi)``, ``c2 = c3 = 0``.
- leader: bumper gap = front-to-front distance minus ``preceding_length``, the front-to-front
  distance taken from the reconstructed positions (``preceding_local_y - local_y``; the
  ``space_headway`` column is noisier, see :func:`import_ngsim_pairs`), clipped to
  :data:`MIN_GAP` (small negatives are reconstruction artefacts; counted as ``gap_clipped``);
  lateral offset = leader front-centre ``Local_X`` minus ego's, when the leader's
  own trajectory is in the file at that frame, else the leader is put at its lane's centre
  (counted as ``lead_lateral_from_lane_centre``). Both are rotated into the ego frame.
- ``lead_v`` = the leader's recorded speed; ``lane_index`` = ``Lane_ID``; ``v_x`` = ``v_Vel``.

OpenACC (JRC; every campaign's layout, e.g. Vicolungo and ZalaZone): 5 metadata rows (``Date``,
``Vehicle_order``, ``Number_of_vehicles``, ``ACC,0|1|2``, ``Distance_setting``), then the header.
A header in another row (e.g. a file saved without its metadata rows) is rejected in one line
naming the row: the file has lost its ACC flag, so it is not read as if it were whole.
- pairs: leader ``k``, follower ``k+1`` wherever ``IVS{k}`` exists and the follower has columns.
  Vehicles may have no columns at all (ZalaZone's target car 1, and no ``IVS1``: its car 2 has
  no measured leader) and numbers may skip (no car 9: no ``IVS8``, no ``IVS9``). The follower
  needs ``Speed/E/N``; two numbered cars ``k, k+1`` without ``IVS{k}`` between them, or a
  follower with only part of ``Speed/E/N``, is a broken file (an error naming the column).
- driver: only a FOLLOWER's own matters. ``Driver{k}`` ("Human"/"ACC", per row) when present,
  else the file-wide metadata flag (``ACC,0``: all human, ``ACC,1``: all on ACC); with neither
  (no column and ``ACC,2`` = mixed, or no ACC row) one line names the file and the follower.
  ACC rows are dropped unless ``include_acc=True``; followers with no human row are skipped.
- runs: a follower's usable rows (time, ``Speed/E/N`` finite; human unless ``include_acc``) are
  cut into contiguous runs: a removed row (NaN dropout, ACC stretch) or a time step above 1.5
  median steps ends a run, and each run is smoothed alone (nothing is filtered across a gap).
  Runs shorter than the 5 s curvature window are skipped (``runs_short_skipped``,
  ``rows_short_skipped``). Recording ids: ``<file name without extensions>_f<k>``, e.g.
  ``JRC-VC_280219_part2_f3``, when follower ``k`` has one run (so whole files keep their ids),
  else ``..._f<k>_s<i>``, ``i = 1, 2, ...`` over its imported runs in time order.
- world ``x, y = E{k}, N{k}``; heading from the Savitzky-Golay smoothed path (window 2 s).
- no lane information (GNSS lateral bias 1-3 m): the follower is centred in a straight-ahead lane
  of width 3.5 m, ``c0l = +1.75``, ``c0r = -1.75``, ``c1 = 0``; the lane bends with the path:
  ``c2 = kappa / 2`` with the path curvature ``kappa = d(yaw)/ds`` from a 5 s Savitzky-Golay
  derivative of the unwrapped heading, clipped to ``|kappa| <= 1/250 m`` by default (motorway
  radii are larger; the clip stops GNSS glitches becoming sharp bends; ``max_curvature`` for a
  test track: ZalaZone's handling course has a median radius of ~150 m, 60 % of its rows
  exceed the motorway clip, 8 % exceed 1/40 m); ``c3 = 0``.
- leader: ``lead_x = IVS{k-1}`` (bumper-to-bumper, clipped to :data:`MIN_GAP`; NaN rows keep
  the follower's row with no leader), ``lead_y = 0``, ``lead_v = Speed{k-1}``. When car ``k-1``
  has no ``Speed`` column, ``lead_v`` is NaN (counted as ``lead_speed_missing``) and the
  pipeline's leader_speed step differentiates ``IVS`` and adds the follower's speed instead
  (on Vicolungo's f2: 0.20 m/s RMSE against the measured speed), rather than dropping a pair.
- ``Lat/Lon/Alt/U/VE/VN/VU`` are not used and may be absent (campaigns differ).
- ``import_stats``: ``pairs`` (followers imported), ``followers_human``,
  ``followers_acc_skipped``, ``driver_from_metadata``, ``lead_speed_missing``,
  ``ivs_without_follower``, ``rows_nan_skipped``, ``runs_short_skipped``,
  ``rows_short_skipped``, ``gap_clipped``, ``curvature_clipped``, ``recordings``, ``rows``.

highD (:func:`~safeil_sumo.data.highd.import_highd`; the levelXdata file layout, a directory, a
prefix ``DIR/01`` or ``DIR/01_tracks.csv``; each recording ``NN`` is ``NN_tracks.csv``,
``NN_tracksMeta.csv``, ``NN_recordingMeta.csv``; inD/rounD/exiD share the layout, not the columns,
and are refused in one line):
- image frame: ``x, y`` = the UPPER-LEFT corner of the axis-aligned box, y pointing DOWN; the box
  is ``width`` long along x and ``height`` wide across. ``drivingDirection`` 1 = upper lanes,
  driving towards -x; 2 = lower lanes, towards +x (``d = -1`` / ``+1``).
- road frame (the schema's world): ``X = d x``, ``Y = -d y``: every vehicle drives towards +X
  with +Y on its LEFT (direction 2: y flipped up; direction 1: the image turned 180 degrees, a
  rotation, not a mirror, so left stays left). Position = the front centre: image
  ``(x + width, y + height/2)`` for ``d = +1``, ``(x, y + height/2)`` for ``d = -1``.
- ``time = frame / frameRate`` (25 Hz); ``v_x = d xVelocity`` (the speed along the driving
  direction, = ``|xVelocity|``); a vehicle whose median is negative drives against its
  ``drivingDirection`` (an error). Heading ``yaw = atan2(-d yVelocity, max(v_x, 1 m/s))``
  (highD's tracks are smoothed already: no filter).
- lane lines: the carriageway's markings (``upperLaneMarkings`` for direction 1,
  ``lowerLaneMarkings`` for 2, ``;``-separated image y) in road-frame ``Y = -d m``; the ego's
  lane is the pair bracketing its centre ``Y`` (outside every marking: the nearest lane, counted
  as ``outside_markings``; the pipeline then drops the row as a line crossing). Straight road:
  ``c0 = (Y_line - Y) / cos(yaw)``, ``c1 = -tan(yaw)``, ``c2 = c3 = 0``. ``lane_index =
  laneId``.
- leader: ``precedingId`` (0 = none) at the same frame; bumper gap along the road = the
  leader's rear ``X`` (image ``x`` for ``d = +1``, ``x + width`` for ``d = -1``, times ``d``)
  minus the ego's front ``X``, clipped to :data:`MIN_GAP` (``gap_clipped``); lateral offset =
  leader centre ``Y`` minus ego ``Y``; both rotated into the ego frame as for NGSIM.
  ``lead_v`` = the leader's own ``d xVelocity``. A ``precedingId`` without a row of that vehicle
  at that frame is no leader (``leader_row_missing``). Lane changes stay in the recording: the
  pipeline removes them (``laneId`` changes, line crossings).
- recording ids ``highd_<NN>_<id>`` (``NN`` = recordingMeta ``id``, two digits), one per vehicle,
  cars and trucks alike. ``import_stats`` per recording: ``vehicle_class`` (id -> ``Car`` /
  ``Truck``: the schema has no column for it), ``cars``, ``trucks``, ``frame_rate_hz``,
  ``rows_without_leader``, ``leader_row_missing``, ``gap_clipped``, ``outside_markings``,
  ``recordings``, ``rows``.
- errors (one line, file, column, 0-based data row): a missing column (the columns found
  listed), an empty file, a non-number, a ``drivingDirection`` other than 1/2, fewer than two
  lane markings, a vehicle missing from tracksMeta, an ``|xVelocity|`` above
  :data:`MAX_PLAUSIBLE_SPEED` (km/h?), no row with a leader.

car-following CSV (:func:`~safeil_sumo.data.car_following_csv.import_car_following_csv`): one row
per sample; roles ``time`` [s], ``v``, ``gap`` [m, bumper to bumper, empty = no leader], optional
``lead_v``, ``id``, ``driver``, mapped from the file's columns by name (unmapped roles default to a
column of the role's own name).
- speeds in ``speed_unit``: ``"m/s"`` (default) or ``"km/h"`` (times 1/3.6); any speed above
  :data:`MAX_PLAUSIBLE_SPEED` after conversion names its row (km/h read as m/s).
- longitudinal only, as OpenACC without a path: the ego is centred in a straight lane of width
  3.5 m, ``c0l = +1.75``, ``c0r = -1.75``, ``c1 = c2 = c3 = 0``; ``x`` = trapezoid integral of
  ``v`` from 0 per recording, ``y = yaw = 0``; ``lead_x = gap`` clipped to :data:`MIN_GAP`,
  ``lead_y = 0``, ``lead_v`` NaN where not given (the pipeline differentiates the gap).
- recordings: ``<file name without extensions>[_<driver>][_<id>]``; rows grouped by recording in
  order of first appearance, time strictly increasing within one (else the file row is named).
"""

from __future__ import annotations

import gzip
import itertools
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.signal import savgol_filter

from safeil_sumo.data.schema import SchemaError, validate_drive

FT = 0.3048  # [m] per foot
NGSIM_LANE_WIDTH = 12 * FT  # [m]
OPENACC_LANE_WIDTH = 3.5  # [m] assumed (no lane data in OpenACC)
MIN_GAP = 0.1  # [m] smallest bumper gap kept; smaller (incl. negative) values are clipped to it
MIN_HEADING_SPEED = 1.0  # [m/s] floor on the longitudinal speed when computing heading
MAX_PATH_CURVATURE = 1.0 / 250.0  # [1/m]
MAX_PLAUSIBLE_SPEED = 70.0  # [m/s] (252 km/h) any single speed sample above: km/h read as m/s
NGSIM_GRID_MIN_ROWS = 100  # [-] fewest rows to estimate the NGSIM lane-grid offset from

NGSIM_CSV_COLUMNS = (
    "Vehicle_ID", "Frame_ID", "Total_Frames", "Global_Time", "Local_X", "Local_Y", "Global_X",
    "Global_Y", "v_Length", "v_Width", "v_Class", "v_Vel", "v_Acc", "Lane_ID", "Preceding",
    "Following", "Space_Headway", "Time_Headway",
)
NGSIM_CSV_USED = (
    "Vehicle_ID", "Frame_ID", "Local_X", "Local_Y", "v_Length", "v_Vel", "Lane_ID", "Preceding",
    "Space_Headway",
)
NGSIM_PAIRS_USED = (
    "pair_id", "time", "vehicle_id", "frame_id", "local_x", "local_y", "v_vel", "lane_id",
    "preceding", "space_headway", "preceding_local_y", "preceding_length", "preceding_vel",
)
NGSIM_DT = 0.1  # [s] one NGSIM frame
OPENACC_REQUIRED = ("Speed", "E", "N", "Driver")  # per vehicle k; plus IVS{k} for k < n


def _require(df: pd.DataFrame, columns: tuple[str, ...] | list[str], source: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise SchemaError(f"{source}: missing column(s) {', '.join(map(repr, missing))} "
                          f"(have: {', '.join(map(str, df.columns))})")


class ImportArgumentError(SchemaError):
    """An import asked for in a way the importers do not know: a format, a column-map role or a
    unit; the message lists the known ones."""


def check_speeds(speed: np.ndarray, source: str, column: str, declared: str = "m/s") -> None:
    """Raise SchemaError naming the first row (0-based data row) of ``speed`` ``(N,)`` [m/s] above
    :data:`MAX_PLAUSIBLE_SPEED`: km/h read as m/s, say. ``declared`` is the unit the file was
    read in (named in the message). NaN passes (no sample)."""
    v = np.abs(np.asarray(speed, float))
    with np.errstate(invalid="ignore"):
        big = v > MAX_PLAUSIBLE_SPEED
    if big.any():
        i = int(np.flatnonzero(big)[0])
        hint = "km/h given where m/s is declared?" if declared == "m/s" else "is the unit right?"
        raise SchemaError(f"{source}, column {column!r}, row {i}: speed {v[i]:.4g} m/s (read "
                          f"as {declared}) is implausible, above {MAX_PLAUSIBLE_SPEED:g} m/s: "
                          f"{hint}")


def _read_table(path: Path, **kwargs: Any) -> pd.DataFrame:
    if not path.is_file():
        raise SchemaError(f"{path}: no such file")
    try:
        if path.suffix.lower() == ".parquet":
            return pd.read_parquet(path)
        return pd.read_csv(path, **kwargs)
    except pd.errors.EmptyDataError as exc:
        raise SchemaError(f"{path}: empty file") from exc
    except Exception as exc:
        raise SchemaError(f"{path}: not readable ({type(exc).__name__}: {exc})") from exc


def _savgol(values: np.ndarray, window_n: int, deriv: int, dt: float) -> np.ndarray:
    """Savitzky-Golay (order 2) value or derivative; falls back to np.gradient on short series."""
    n = len(values)
    w = min(window_n | 1, n if n % 2 else n - 1)
    if w < 3:
        if deriv == 0:
            return values.astype(float)
        return np.gradient(values, dt) if n > 1 else np.zeros(n)
    return savgol_filter(values, w, min(2, w - 1), deriv=deriv, delta=dt, mode="interp")


def _group_starts(keys: np.ndarray) -> np.ndarray:
    """Start indices of runs of equal consecutive keys, plus the end index."""
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    return np.r_[starts, len(keys)]


# ----------------------------------------------------------------------------------------- NGSIM


def _ngsim_drive(p: pd.DataFrame, source: str) -> pd.DataFrame:
    """Common NGSIM conversion. ``p`` in metres/seconds, sorted by recording then time, with columns
    recording_id, time, frame, vid, lat (from left edge, rightwards), lon, v, lane, leader,
    headway (front-to-front), lead_len, lead_v, lead_lat (NaN where unknown).
    """
    n = len(p)
    rec = p["recording_id"].to_numpy()
    lat = p["lat"].to_numpy(float)
    lon = p["lon"].to_numpy(float)
    v_lat = np.empty(n)
    v_lon = np.empty(n)
    bounds = _group_starts(rec)
    window = round(1.5 / NGSIM_DT)
    for a, b in itertools.pairwise(bounds):
        v_lat[a:b] = -_savgol(lat[a:b], window, 1, NGSIM_DT)  # y is left, lat grows right
        v_lon[a:b] = _savgol(lon[a:b], window, 1, NGSIM_DT)
    psi = np.arctan2(v_lat, np.maximum(v_lon, MIN_HEADING_SPEED))

    lane = p["lane"].to_numpy(float)
    offset = ngsim_lane_grid_offset(lat, lane)
    left_edge = (lane - 1.0) * NGSIM_LANE_WIDTH + offset  # Local_X of the lane's left line
    cos = np.cos(psi)
    c0l = (lat - left_edge) / cos
    c0r = (lat - left_edge - NGSIM_LANE_WIDTH) / cos
    c1 = -np.tan(psi)

    # leader's lateral position: given, else its own trajectory at that frame, else lane centre
    own = pd.DataFrame({"leader": p["vid"].to_numpy(), "frame": p["frame"].to_numpy(),
                        "own_lat": lat}).drop_duplicates(["leader", "frame"])
    look = p[["leader", "frame"]].merge(own, how="left", on=["leader", "frame"])
    lead_lat = p["lead_lat"].to_numpy(float)
    lead_lat = np.where(np.isnan(lead_lat), look["own_lat"].to_numpy(float), lead_lat)
    from_centre = np.isnan(lead_lat)
    lead_lat = np.where(from_centre, left_edge + 0.5 * NGSIM_LANE_WIDTH, lead_lat)

    raw_gap = p["headway"].to_numpy(float) - p["lead_len"].to_numpy(float)
    clipped = raw_gap < MIN_GAP
    gap = np.maximum(raw_gap, MIN_GAP)
    dy_world = -(lead_lat - lat)
    # world offset (gap along the road, dy across) rotated into the ego frame
    s = np.sin(psi)
    lead_x = cos * gap + s * dy_world
    lead_y = -s * gap + cos * dy_world

    df = pd.DataFrame({
        "recording_id": rec,
        "time": p["time"].to_numpy(float),
        "x": lon,
        "y": -lat,
        "yaw": psi,
        "v_x": p["v"].to_numpy(float),
        "left_c0": c0l, "left_c1": c1, "left_c2": 0.0, "left_c3": 0.0,
        "right_c0": c0r, "right_c1": c1, "right_c2": 0.0, "right_c3": 0.0,
        "lead_x": lead_x,
        "lead_y": lead_y,
        "lead_v": p["lead_v"].to_numpy(float),
        "lane_index": lane,
    })
    out = validate_drive(df, source)
    out.attrs["import_stats"] = {
        "source": source,
        "recordings": int(len(bounds) - 1),
        "rows": int(n),
        "gap_clipped": int(clipped.sum()),
        "gap_min_raw_m": float(raw_gap.min()) if n else float("nan"),
        "lead_lateral_from_lane_centre": int(from_centre.sum()),
        "lane_grid_offset_m": offset,
    }
    return out


def ngsim_lane_grid_offset(lat: np.ndarray, lane: np.ndarray) -> float:
    """Lateral shift [m] of the 12 ft lane grid that centres the vehicles in their lanes: the
    median of ``lat - (lane - 1/2) W`` (``lat`` from the left edge, rightwards), clipped to
    ``±W/4``; 0 with fewer than :data:`NGSIM_GRID_MIN_ROWS` finite rows."""
    off = np.asarray(lat, float) - (np.asarray(lane, float) - 0.5) * NGSIM_LANE_WIDTH
    off = off[np.isfinite(off)]
    if len(off) < NGSIM_GRID_MIN_ROWS:
        return 0.0
    quarter = 0.25 * NGSIM_LANE_WIDTH
    return float(np.clip(np.median(off), -quarter, quarter))


def import_ngsim_pairs(path: str | Path, headway_source: str = "positions") -> pd.DataFrame:
    """The NGSIM I-80 car-following pairs Parquet (metric; see the shared data README).

    ``headway_source="positions"`` (default) takes the front-to-front distance from the
    reconstructed positions, ``preceding_local_y - local_y``; ``"space_headway"`` uses that column.
    On the I-80 file the positions are consistent with the reconstructed speeds (leader speed by
    differentiation vs ``preceding_vel``: RMSE 0.23 m/s) while ``space_headway`` is not (1.08 m/s,
    600+ samples with |a_lead| > 7 m/s^2 that are not cut-ins), so differentiating it would flag
    noise as cut-in events.
    """
    if headway_source not in ("positions", "space_headway"):
        raise ValueError(f"headway_source must be 'positions' or 'space_headway', "
                         f"got {headway_source!r}")
    path = Path(path)
    src = str(path)
    raw = _read_table(path)
    _require(raw, NGSIM_PAIRS_USED, src)
    raw = raw.assign(pair_id=raw["pair_id"].astype(str)).sort_values(
        ["pair_id", "time"], kind="stable")
    from_positions = raw["preceding_local_y"].to_numpy(float) - raw["local_y"].to_numpy(float)
    headway = (from_positions if headway_source == "positions"
               else raw["space_headway"].to_numpy(float))
    p = pd.DataFrame({
        "recording_id": raw["pair_id"].to_numpy(),
        "time": raw["time"].to_numpy(float),
        "frame": raw["frame_id"].to_numpy(float).astype(np.int64),
        "vid": raw["vehicle_id"].astype(str).to_numpy(),
        "lat": raw["local_x"].to_numpy(float),
        "lon": raw["local_y"].to_numpy(float),
        "v": raw["v_vel"].to_numpy(float),
        "lane": raw["lane_id"].astype(float).to_numpy(),
        "leader": raw["preceding"].astype(str).to_numpy(),
        "headway": headway,
        "lead_len": raw["preceding_length"].to_numpy(float),
        "lead_v": raw["preceding_vel"].to_numpy(float),
        "lead_lat": np.nan,
    })
    out = _ngsim_drive(p, src)
    out.attrs["import_stats"]["headway_source"] = headway_source
    out.attrs["import_stats"]["space_headway_minus_positions_median_abs_m"] = float(
        np.median(np.abs(raw["space_headway"].to_numpy(float) - from_positions)))
    return out


def import_ngsim_csv(path: str | Path, min_pair_frames: int = 2) -> pd.DataFrame:
    """An ORIGINAL NGSIM trajectory CSV (feet, ft/s, 0.1 s frames) as follower-leader pairs.

    Each contiguous run of frames in which a vehicle has the same ``Preceding`` (non-zero) becomes
    one recording ``"<follower>-<leader>"`` (``_2``, ``_3``, ... if the pair recurs). The
    front-to-front distance is ``Local_Y`` of the leader's row minus the follower's (as in
    :func:`import_ngsim_pairs`); rows whose leader has no row at that frame use
    ``Space_Headway`` with a 0 leader length, the lane centre as leader lateral position and a NaN
    ``lead_v`` (counted as ``leader_row_missing``).
    Runs shorter than ``min_pair_frames`` are skipped (counted).
    """
    path = Path(path)
    src = str(path)
    raw = _read_table(path)
    raw.columns = [str(c).strip() for c in raw.columns]
    _require(raw, NGSIM_CSV_USED, src)
    d = raw[list(NGSIM_CSV_USED)].apply(pd.to_numeric, errors="coerce")
    bad = d.isna().any(axis=1).to_numpy()
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        col = d.columns[d.iloc[i].isna().to_numpy()][0]
        raise SchemaError(f"{src}, column {col!r}, row {i}: not a number: {raw[col].iloc[i]!r}")
    d = d.astype({"Vehicle_ID": np.int64, "Frame_ID": np.int64, "Preceding": np.int64,
                  "Lane_ID": np.int64})
    d = d.drop_duplicates(["Vehicle_ID", "Frame_ID"]).sort_values(["Vehicle_ID", "Frame_ID"])
    lead = d[["Vehicle_ID", "Frame_ID", "v_Length", "v_Vel", "Local_X", "Local_Y"]].rename(
        columns={"Vehicle_ID": "Preceding", "v_Length": "lead_len", "v_Vel": "lead_vel",
                 "Local_X": "lead_lx", "Local_Y": "lead_ly"})
    f = d[d["Preceding"] > 0].merge(lead, how="left", on=["Preceding", "Frame_ID"])
    f = f.sort_values(["Vehicle_ID", "Frame_ID"], kind="stable").reset_index(drop=True)
    veh = f["Vehicle_ID"].to_numpy()
    pre = f["Preceding"].to_numpy()
    frame = f["Frame_ID"].to_numpy()
    new_run = np.r_[True, (veh[1:] != veh[:-1]) | (pre[1:] != pre[:-1])
                    | (np.diff(frame) != 1)]
    run = np.cumsum(new_run) - 1
    run_len = np.bincount(run)
    keep = run_len[run] >= min_pair_frames
    base = np.char.add(np.char.add(veh.astype(str), "-"), pre.astype(str))
    # number repeated pairs: first occurrence keeps the plain id
    run_base = base[new_run]
    occurrence = pd.Series(run_base).groupby(run_base).cumcount().to_numpy()
    run_id = np.where(occurrence == 0, run_base,
                      np.char.add(np.char.add(run_base, "_"), (occurrence + 1).astype(str)))
    missing_leader = f["lead_len"].isna().to_numpy()
    # front-to-front from positions when the leader's row is there (see import_ngsim_pairs)
    from_positions = (f["lead_ly"] - f["Local_Y"]).to_numpy(float)
    headway = np.where(missing_leader, f["Space_Headway"].to_numpy(float), from_positions)
    p = pd.DataFrame({
        "recording_id": run_id[run],
        "time": frame * NGSIM_DT,
        "frame": frame,
        "vid": veh.astype(str),
        "lat": f["Local_X"].to_numpy(float) * FT,
        "lon": f["Local_Y"].to_numpy(float) * FT,
        "v": f["v_Vel"].to_numpy(float) * FT,
        "lane": f["Lane_ID"].to_numpy(float),
        "leader": pre.astype(str),
        "headway": headway * FT,
        "lead_len": np.nan_to_num(f["lead_len"].to_numpy(float)) * FT,
        "lead_v": f["lead_vel"].to_numpy(float) * FT,
        "lead_lat": f["lead_lx"].to_numpy(float) * FT,
    })[keep].reset_index(drop=True)
    if p.empty:
        raise SchemaError(f"{src}: no follower-leader pairs (column 'Preceding' is 0 everywhere)")
    out = _ngsim_drive(p, src)
    out.attrs["import_stats"].update({
        "leader_row_missing": int(missing_leader[keep].sum()),
        "short_pairs_skipped": int((run_len < min_pair_frames).sum()),
        "rows_without_leader_skipped": int((d["Preceding"] <= 0).sum()),
    })
    return out


# --------------------------------------------------------------------------------------- OpenACC

OPENACC_METADATA_KEYS = ("Date", "Vehicle_order", "Number_of_vehicles", "ACC", "Distance_setting")
OPENACC_FOLLOWER_COLUMNS = ("Speed", "E", "N")  # per follower k; the leader needs only IVS{k-1}
OPENACC_VEHICLE_COLUMN = re.compile(r"^(Speed|Lat|Lon|Alt|E|N|U|VE|VN|VU|Driver)(\d+)$")
OPENACC_IVS_COLUMN = re.compile(r"^IVS(\d+)$")
# metadata ``ACC,0``: the whole file driven by hand, ``ACC,1``: all followers on ACC; ``ACC,2``
# (mixed) or no ACC row cannot stand in for a missing Driver column
OPENACC_ACC_FLAG_HUMAN = {"0": True, "1": False}
OPENACC_HEADING_WINDOW = 2.0  # [s] Savitzky-Golay window of the path's velocity (heading)
OPENACC_CURVATURE_WINDOW = 5.0  # [s] window of d(yaw)/dt; also the shortest run imported
OPENACC_GAP_FACTOR = 1.5  # [-] a time step above this x the median step breaks a run (as the
#                            pipeline's default gap_factor)


def openacc_recording_prefix(path: str | Path) -> str:
    """The file's name without its extensions, characters other than letters, digits, ``_`` and
    ``-`` made ``_``: ``JRC-VC_280219_part2.csv.gz`` -> ``JRC-VC_280219_part2``.

    One rule for every campaign's naming (the OpenACC campaigns name their files differently), so
    ids of the files of one campaign are alike and an id names its file.
    """
    stem = Path(path).name.split(".")[0]
    return re.sub(r"[^A-Za-z0-9_-]", "_", stem) or "openacc"


def _fields(line: str) -> list[str]:
    """The comma-separated fields of one line, stripped of blanks and quotes."""
    return [f.strip().strip('"').strip() for f in line.split(",")]


def _head_lines(path: Path, n: int) -> list[str]:
    """The first ``n`` lines of a plain or gzip (``.gz``) text file; bad bytes are replaced."""
    opener = gzip.open if path.name.lower().endswith(".gz") else open
    try:
        with opener(path, "rt", errors="replace", newline="") as fh:
            return [line.rstrip("\r\n") for line in itertools.islice(fh, n)]
    except (OSError, EOFError) as exc:  # e.g. a .gz that is not gzip
        raise SchemaError(f"{path}: not readable ({type(exc).__name__}: {exc})") from exc


def read_openacc(path: str | Path) -> tuple[pd.DataFrame, list[str]]:
    """The raw OpenACC table and its 5 metadata lines (trailing empty fields dropped).

    The layout is checked on the first lines: 5 metadata rows (``Date``, ``Vehicle_order``,
    ``Number_of_vehicles``, ``ACC``, ``Distance_setting``), then the header with ``Time``. A header
    in another row is rejected with one line naming that row (a file without its metadata rows
    has lost the file-wide ACC flag, so it is not read as if it were whole); any other file gets
    one line saying it is not an OpenACC file.
    """
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: no such file")
    head = _head_lines(path, 10)
    rows = [_fields(line) for line in head]
    header = next((i for i, r in enumerate(rows) if "Time" in r), None)
    keys = ", ".join(OPENACC_METADATA_KEYS)
    if header is None:
        if rows and rows[0][0] == "Date":
            raise SchemaError(f"{path}: OpenACC metadata rows but no header with a 'Time' column "
                              f"in rows 1-{len(rows)}: not the OpenACC layout")
        start = f"row 1 starts {head[0][:40]!r}" if head else "empty file"
        raise SchemaError(f"{path}: not an OpenACC file ({start}): OpenACC files start with 5 "
                          f"metadata rows ({keys}), then a header with 'Time'")
    if header != 5:
        raise SchemaError(f"{path}: header (with 'Time') found in row {header + 1}, but OpenACC "
                          f"files start with 5 metadata rows ({keys}) and have it in row 6")
    raw = _read_table(path, skiprows=5)
    raw.columns = [str(c).strip() for c in raw.columns]
    if "Time" not in raw.columns:  # e.g. a quoted header the line check read differently
        raise SchemaError(f"{path}: missing column 'Time' after the 5 metadata rows "
                          f"(have: {', '.join(raw.columns[:8])}, ...): not the OpenACC layout")
    meta = [",".join(r).rstrip(",") for r in rows[:5]]
    return raw, meta


def read_openacc_metadata(path: str | Path) -> dict[str, list[str]]:
    """The metadata rows of an OpenACC file (:func:`openacc_metadata` of its first 5 lines),
    without reading its table."""
    return openacc_metadata(_head_lines(Path(path), 5))


def openacc_vehicle_names(meta: dict[str, list[str]]) -> dict[int, str]:
    """Vehicle number ``k`` -> its name in the metadata row ``Vehicle_order`` (``k = 1`` is the
    first name): ``{2: "TESLA_MODELX", ...}``; ``{}`` without the row. The column numbers are
    platoon positions, so the same number names different cars in files of other orders."""
    return {k: name for k, name in enumerate(meta.get("Vehicle_order", []), start=1)}


def openacc_metadata(lines: list[str]) -> dict[str, list[str]]:
    """Metadata lines as ``{key: values}``, empty fields dropped: ``"ACC, 1"`` -> ``{"ACC": ["1"]}``."""
    out: dict[str, list[str]] = {}
    for line in lines:
        f = _fields(line)
        if f[0]:
            out[f[0]] = [v for v in f[1:] if v]
    return out


def openacc_runs(time: np.ndarray, ok: np.ndarray, dt: float,
                 gap_factor: float = OPENACC_GAP_FACTOR) -> list[np.ndarray]:
    """Row indices of each contiguous run of rows where ``ok``: a row that is not ok, or a time
    step above ``gap_factor * dt``, ends a run (so nothing is smoothed across it)."""
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return []
    brk = (np.diff(idx) > 1) | (np.diff(time[idx]) > gap_factor * dt)
    return np.split(idx, np.flatnonzero(brk) + 1)


def openacc_heading_curvature(e: np.ndarray, n: np.ndarray, dt: float
                              ) -> tuple[np.ndarray, np.ndarray]:
    """Heading [rad, unwrapped] and path curvature [1/m, not clipped] of ONE contiguous run of
    positions ``e, n`` [m] sampled every ``dt`` [s]: heading = direction of the Savitzky-Golay
    velocity (window :data:`OPENACC_HEADING_WINDOW`), curvature = Savitzky-Golay d(heading)/dt
    (window :data:`OPENACC_CURVATURE_WINDOW`) over ``max(path speed, 1 m/s)``."""
    w = round(OPENACC_HEADING_WINDOW / dt)
    ve, vn = _savgol(e, w, 1, dt), _savgol(n, w, 1, dt)
    yaw = np.unwrap(np.arctan2(vn, ve))
    yaw_rate = _savgol(yaw, round(OPENACC_CURVATURE_WINDOW / dt), 1, dt)
    return yaw, yaw_rate / np.maximum(np.hypot(ve, vn), MIN_HEADING_SPEED)


def _openacc_human(raw: pd.DataFrame, meta: dict[str, list[str]], k: int,
                   src: str) -> tuple[np.ndarray, bool]:
    """``(N,)`` True where follower ``k`` drove by hand: its ``Driver{k}`` column, else the file's
    metadata ACC flag; and whether the flag was used."""
    col = f"Driver{k}"
    if col in raw.columns:
        return (raw[col].astype(str).str.strip().str.lower() == "human").to_numpy(), False
    flag = (meta.get("ACC") or [""])[0]
    if flag not in OPENACC_ACC_FLAG_HUMAN:
        got = f"metadata row 'ACC,{flag}'" if "ACC" in meta else "no metadata row 'ACC'"
        raise SchemaError(f"{src}: follower {k} has no column {col!r} and {got} cannot stand in "
                          "(ACC,0 = all human, ACC,1 = all ACC): who drove it is unknown")
    return np.full(len(raw), OPENACC_ACC_FLAG_HUMAN[flag]), True


def _numeric(raw: pd.DataFrame, column: str) -> np.ndarray:
    return pd.to_numeric(raw[column], errors="coerce").to_numpy(float)


def openacc_pairs(raw: pd.DataFrame, src: str) -> tuple[list[tuple[int, int]], int]:
    """The (leader, follower) vehicle numbers ``(k, k+1)`` of a raw OpenACC table: wherever
    ``IVS{k}`` exists and vehicle ``k+1`` has columns; and how many ``IVS`` columns name a
    follower without any column. A follower lacking one of ``Speed/E/N``, or two numbered
    vehicles ``k, k+1`` without ``IVS{k}`` between them, is a broken file (SchemaError)."""
    vehicles = {int(m.group(2)) for c in raw.columns if (m := OPENACC_VEHICLE_COLUMN.match(c))}
    ivs = sorted(int(m.group(1)) for c in raw.columns if (m := OPENACC_IVS_COLUMN.match(c)))
    _require(raw, [f"IVS{k}" for k in sorted(vehicles) if k + 1 in vehicles], src)
    pairs = [(k, k + 1) for k in ivs if k + 1 in vehicles]
    _require(raw, [f"{c}{f}" for _, f in pairs for c in OPENACC_FOLLOWER_COLUMNS], src)
    if not pairs:
        raise SchemaError(
            f"{src}: no follower pair: a pair (k, k+1) needs a column IVS<k> and vehicle k+1's "
            f"Speed/E/N (vehicles with columns: {', '.join(map(str, sorted(vehicles))) or 'none'}"
            f"; IVS columns: {', '.join(f'IVS{k}' for k in ivs) or 'none'})")
    return pairs, len(ivs) - len(pairs)


def _openacc_run(recording_id: str, time: np.ndarray, e: np.ndarray, nn: np.ndarray,
                 v: np.ndarray, gap: np.ndarray, lead_v: np.ndarray, dt: float,
                 max_curvature: float, stats: dict) -> pd.DataFrame:
    """One contiguous run of a follower as a recording: its pose from the east/north
    positions ``e``/``nn`` [m] sampled every ``dt`` [s], lane lines OPENACC_LANE_WIDTH apart
    curving as its path does (curvature clipped to ``max_curvature`` [1/m]) and its leader
    at the inter-vehicle spacing ``gap`` [m] (floored at MIN_GAP; NaN: no leader). Counts the
    clipped curvatures and gaps in ``stats``."""
    half = 0.5 * OPENACC_LANE_WIDTH
    yaw, kappa = openacc_heading_curvature(e, nn, dt)
    stats["curvature_clipped"] += int((np.abs(kappa) > max_curvature).sum())
    kappa = np.clip(kappa, -max_curvature, max_curvature)
    stats["gap_clipped"] += int((gap < MIN_GAP).sum())
    has_lead = np.isfinite(gap)
    gap = np.where(has_lead, np.maximum(gap, MIN_GAP), np.nan)
    return pd.DataFrame({
        "recording_id": recording_id,
        "time": time,
        "x": e,
        "y": nn,
        "yaw": (yaw + np.pi) % (2 * np.pi) - np.pi,
        "v_x": v,
        "left_c0": half, "left_c1": 0.0, "left_c2": 0.5 * kappa, "left_c3": 0.0,
        "right_c0": -half, "right_c1": 0.0, "right_c2": 0.5 * kappa, "right_c3": 0.0,
        "lead_x": gap,
        "lead_y": np.where(has_lead, 0.0, np.nan),
        "lead_v": lead_v,
    })


def _no_drive() -> pd.DataFrame:
    """An empty recording frame: the schema's columns, no rows."""
    out = pd.DataFrame({c: pd.Series(dtype=float) for c in (
        "time", "x", "y", "yaw", "v_x", "left_c0", "left_c1", "left_c2", "left_c3",
        "right_c0", "right_c1", "right_c2", "right_c3", "lead_x", "lead_y", "lead_v")})
    out.insert(0, "recording_id", pd.Series(dtype=str))
    return out


def import_openacc(path: str | Path, include_acc: bool = False,
                   max_curvature: float = MAX_PATH_CURVATURE) -> pd.DataFrame:
    """One OpenACC platoon file: one recording per contiguous run of each human follower (all
    followers if include_acc); see the module doc for pairs, drivers, runs and ids.

    ``max_curvature`` [1/m] clips the lane curvature; the default suits motorways (R >= 250 m),
    a test track needs more (ZalaZone's handling course: median radius ~150 m, 1 % below 50 m).
    May return an empty frame (no rows) when no follower qualifies, e.g. an ACC day.
    """
    path = Path(path)
    src = str(path)
    raw, meta_lines = read_openacc(path)
    meta = openacc_metadata(meta_lines)
    pairs, ivs_unused = openacc_pairs(raw, src)
    time = _numeric(raw, "Time")
    prefix = openacc_recording_prefix(path)
    dt = float(np.nanmedian(np.diff(time))) if len(time) > 1 else 0.1
    min_run = round(OPENACC_CURVATURE_WINDOW / dt) | 1  # the curvature filter's window
    frames: list[pd.DataFrame] = []
    stats: dict[str, Any] = {"source": src, "followers_human": 0, "followers_acc_skipped": 0,
             "rows_nan_skipped": 0, "gap_clipped": 0, "curvature_clipped": 0,
             "pairs": 0, "ivs_without_follower": ivs_unused, "driver_from_metadata": 0,
             "lead_speed_missing": 0, "runs_short_skipped": 0, "rows_short_skipped": 0}
    for lead, k in pairs:
        human, from_meta = _openacc_human(raw, meta, k, src)
        stats["driver_from_metadata"] += int(from_meta)
        if not include_acc and not human.any():
            stats["followers_acc_skipped"] += 1
            continue
        stats["followers_human"] += int(human.any())
        v, e, nn = (_numeric(raw, f"{c}{k}") for c in ("Speed", "E", "N"))
        ivs = _numeric(raw, f"IVS{lead}")
        if f"Speed{lead}" in raw.columns:
            lead_v = _numeric(raw, f"Speed{lead}")
        else:  # NaN: the pipeline's leader_speed differentiates IVS (+ follower speed) instead
            lead_v = np.full(len(raw), np.nan)
            stats["lead_speed_missing"] += 1
        ok = np.isfinite(time) & np.isfinite(e) & np.isfinite(nn) & np.isfinite(v)
        if not include_acc:
            ok &= human  # a follower switching to ACC mid-file loses those rows
        stats["rows_nan_skipped"] += int((~ok & (human | include_acc)).sum())
        runs = openacc_runs(time, ok, dt)
        short = [r for r in runs if len(r) < min_run]
        stats["runs_short_skipped"] += len(short)
        stats["rows_short_skipped"] += sum(len(r) for r in short)
        runs = [r for r in runs if len(r) >= min_run]
        stats["pairs"] += int(bool(runs))
        for i, idx in enumerate(runs, start=1):
            # one run keeps the plain id, so files without breaks keep their ids
            rid = f"{prefix}_f{k}" if len(runs) == 1 else f"{prefix}_f{k}_s{i}"
            frames.append(_openacc_run(rid, time[idx], e[idx], nn[idx], v[idx], ivs[idx],
                                       lead_v[idx], dt, max_curvature, stats))
    out = validate_drive(pd.concat(frames, ignore_index=True), src) if frames else _no_drive()
    stats["recordings"] = len(frames)
    stats["rows"] = len(out)
    out.attrs["import_stats"] = stats
    return out


def import_openacc_files(paths: Sequence[str | Path], include_acc: bool = False,
                         max_curvature: float = MAX_PATH_CURVATURE) -> pd.DataFrame:
    """Several OpenACC files into one drive frame (recording ids stay unique per file)."""
    parts = [import_openacc(p, include_acc, max_curvature) for p in paths]
    nonempty = [p for p in parts if len(p)]
    out = pd.concat(nonempty, ignore_index=True) if nonempty else parts[0].iloc[:0]
    out.attrs["import_stats"] = {"files": [p.attrs["import_stats"] for p in parts]}
    return out
