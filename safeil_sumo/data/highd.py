"""highD recordings (the levelXdata layout) into the drive schema; the conversions are in the
module doc of :mod:`safeil_sumo.data.importers`, section "highD"."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.data.importers import (
    MIN_GAP,
    MIN_HEADING_SPEED,
    _read_table,
    _require,
    check_speeds,
)
from safeil_sumo.data.schema import SchemaError, validate_drive

HIGHD_TRACKS_USED = ("frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity",
                     "precedingId", "laneId")
HIGHD_META_USED = ("id", "class", "drivingDirection")
HIGHD_RECORDING_USED = ("id", "frameRate", "upperLaneMarkings", "lowerLaneMarkings")
# the columns inD / rounD / exiD use instead of x, y: the same file layout, other columns
LEVELX_OTHER_COLUMNS = ("xCenter", "yCenter", "heading", "lonVelocity")
_RECORDING_FILE = re.compile(r"^(?P<nn>\d+)_tracks\.csv$")


def highd_recording_files(path: str | Path) -> list[tuple[Path, Path, Path]]:
    """``(tracks, tracksMeta, recordingMeta)`` paths of each recording ``path`` names, sorted.

    ``path``: a directory (every ``NN_tracks.csv`` in it), a recording prefix (``DIR/01`` or
    ``DIR/01_``) or one of the recording's three files. Raises SchemaError when there is none.
    """
    p = Path(path)
    if p.is_dir():
        tracks = sorted(f for f in p.iterdir() if _RECORDING_FILE.match(f.name))
        if not tracks:
            raise SchemaError(f"{p}: no highD recording (no file NN_tracks.csv in the directory)")
    else:
        m = re.match(r"^(\d+)(_(tracks|tracksMeta|recordingMeta)\.csv|_)?$", p.name)
        if m is None and not p.exists():
            raise SchemaError(f"{p}: no such file or directory")
        if m is None:
            raise SchemaError(f"{p}: not a highD recording: give a directory, a prefix such as "
                              "DIR/01, or a file NN_tracks.csv")
        tracks = [p.with_name(f"{m.group(1)}_tracks.csv")]
    return [(t, t.with_name(t.name.replace("_tracks.", "_tracksMeta.")),
             t.with_name(t.name.replace("_tracks.", "_recordingMeta."))) for t in tracks]


def _numeric_table(path: Path, columns: tuple[str, ...]) -> pd.DataFrame:
    """The columns of a highD CSV as floats; a missing column or a non-number names file, column
    and row (0-based data row). inD / rounD / exiD files are told apart in the message."""
    raw = _read_table(path)
    raw.columns = [str(c).strip() for c in raw.columns]
    if len(raw) == 0:
        raise SchemaError(f"{path}: empty file (a header, no rows)")
    if any(c in raw.columns for c in LEVELX_OTHER_COLUMNS) and "x" not in raw.columns:
        raise SchemaError(f"{path}: an inD/rounD/exiD tracks file (columns xCenter, yCenter, "
                          "heading): only the highD columns are read (frame, id, x, y, ...)")
    _require(raw, columns, str(path))
    d = raw[list(columns)].apply(pd.to_numeric, errors="coerce")
    bad = d.isna().to_numpy()
    if bad.any():
        i, j = (int(k[0]) for k in np.nonzero(bad))
        col = columns[j]
        raise SchemaError(f"{path}, column {col!r}, row {i}: not a number: {raw[col].iloc[i]!r}")
    return d


def _lane_markings(meta: pd.DataFrame, column: str, path: Path) -> np.ndarray:
    """``(M,)`` image y [m] of the lane markings ``"8.51;12.59;16.43"``, sorted; at least two."""
    text = str(meta[column].iloc[0])
    try:
        ys = np.sort(np.array([float(v) for v in text.split(";") if v.strip()]))
    except ValueError as exc:
        raise SchemaError(f"{path}, column {column!r}, row 0: not ';'-separated numbers: "
                          f"{text!r}") from exc
    if len(ys) < 2 or not np.isfinite(ys).all():
        raise SchemaError(f"{path}, column {column!r}, row 0: needs two or more finite lane "
                          f"markings, got {text!r}")
    return ys


def _recording_meta(path: Path) -> tuple[int, float, dict[int, np.ndarray]]:
    """Recording number, frame rate [Hz] and each direction's lane markings (image y [m])."""
    raw = _read_table(path)
    raw.columns = [str(c).strip() for c in raw.columns]
    if len(raw) == 0:
        raise SchemaError(f"{path}: empty file (a header, no rows)")
    _require(raw, HIGHD_RECORDING_USED, str(path))
    rate = pd.to_numeric(raw["frameRate"], errors="coerce").iloc[0]
    number = pd.to_numeric(raw["id"], errors="coerce").iloc[0]
    if not np.isfinite(rate) or rate <= 0:
        raise SchemaError(f"{path}, column 'frameRate', row 0: not a positive number: "
                          f"{raw['frameRate'].iloc[0]!r}")
    if not np.isfinite(number):
        raise SchemaError(f"{path}, column 'id', row 0: not a number: {raw['id'].iloc[0]!r}")
    # drivingDirection 1 drives the upper lanes, 2 the lower ones
    lines = {1: _lane_markings(raw, "upperLaneMarkings", path),
             2: _lane_markings(raw, "lowerLaneMarkings", path)}
    return int(number), float(rate), lines


def _vehicle_meta(path: Path) -> pd.DataFrame:
    """``id`` -> ``class`` (str) and ``direction`` (+1 driving +x: drivingDirection 2; -1: 1)."""
    raw = _read_table(path)
    raw.columns = [str(c).strip() for c in raw.columns]
    if len(raw) == 0:
        raise SchemaError(f"{path}: empty file (a header, no rows)")
    _require(raw, HIGHD_META_USED, str(path))
    direction = pd.to_numeric(raw["drivingDirection"], errors="coerce").to_numpy(float)
    bad = ~np.isin(direction, (1.0, 2.0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SchemaError(f"{path}, column 'drivingDirection', row {i}: must be 1 (upper lanes, "
                          f"towards -x) or 2 (lower lanes, towards +x), got "
                          f"{raw['drivingDirection'].iloc[i]!r}")
    return pd.DataFrame({"id": pd.to_numeric(raw["id"], errors="coerce").to_numpy(float),
                         "class": raw["class"].astype(str).str.strip().to_numpy(),
                         "direction": np.where(direction == 2.0, 1.0, -1.0)})


def road_frame(x: np.ndarray, y: np.ndarray, width: np.ndarray, height: np.ndarray,
               direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Front-centre ``(X, Y)`` [m] and rear ``X`` [m] of highD boxes in the road frame.

    Inputs ``(N,)``: the box's UPPER-LEFT corner ``x, y`` in the image frame (y DOWN), its length
    along x (``width``) and across (``height``), ``direction`` +1 (drives +x) or -1 (drives -x).
    The road frame is the image frame turned so the vehicle drives towards +X with +Y on its
    LEFT: ``X = d x``, ``Y = -d y``. For ``d = -1`` that is a 180 degree turn, not a mirror, so
    left stays left.
    """
    front_img = x + np.where(direction > 0, width, 0.0)
    rear_img = x + np.where(direction > 0, 0.0, width)
    centre_y = y + 0.5 * height
    return direction * front_img, -direction * centre_y, direction * rear_img


def lane_lines(y_centre: np.ndarray, direction: np.ndarray, markings: dict[int, np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Road-frame ``Y`` [m] of the left and right lines of the lane each ego is in, and whether
    its centre was outside its carriageway's markings (then the nearest lane is taken).

    ``y_centre`` ``(N,)``: the ego's road-frame ``Y``; ``direction`` ``(N,)`` +1 / -1;
    ``markings``: highD ``drivingDirection`` (1 upper, 2 lower) -> image y of the lines.
    """
    left = np.empty(len(y_centre))
    right = np.empty(len(y_centre))
    outside = np.zeros(len(y_centre), dtype=bool)
    for d, key in ((1.0, 2), (-1.0, 1)):
        rows = direction == d
        lines_y = np.sort(-d * markings[key])  # road-frame Y, right (low) to left (high)
        k = np.searchsorted(lines_y, y_centre[rows])
        outside[rows] = (k == 0) | (k == len(lines_y))
        k = np.clip(k, 1, len(lines_y) - 1)
        left[rows], right[rows] = lines_y[k], lines_y[k - 1]
    return left, right, outside


def _leader_rows(tr: pd.DataFrame) -> pd.DataFrame:
    """Each row's leader (``precedingId`` at the same frame): its rear ``X``, front-centre ``Y``
    and speed along the road; NaN where there is none or its row is missing."""
    own = tr[["id", "frame", "rear_X", "Y", "v"]].rename(
        columns={"id": "precedingId", "rear_X": "lead_rear", "Y": "lead_Y", "v": "lead_speed"})
    return tr[["precedingId", "frame"]].merge(own, how="left", on=["precedingId", "frame"])


def _highd_tracks(paths: tuple[Path, Path, Path]) -> tuple[pd.DataFrame, dict[int, np.ndarray],
                                                           int, float, pd.DataFrame]:
    """The checked tracks of one recording with road-frame columns (front ``X, Y``, ``rear_X``,
    speed ``v`` along the driving direction) added, sorted by vehicle and frame."""
    tracks_path, meta_path, rec_path = paths
    number, rate, markings = _recording_meta(rec_path)
    meta = _vehicle_meta(meta_path)
    tr = _numeric_table(tracks_path, HIGHD_TRACKS_USED)
    tr = tr.merge(meta, how="left", on="id", validate="many_to_one")
    orphan = tr["direction"].isna().to_numpy()
    if orphan.any():
        i = int(np.flatnonzero(orphan)[0])
        raise SchemaError(f"{tracks_path}, column 'id', row {i}: vehicle "
                          f"{tr['id'].iloc[i]:g} is not in {meta_path.name}")
    d = tr["direction"].to_numpy(float)
    check_speeds(np.abs(tr["xVelocity"].to_numpy(float)), str(tracks_path), "xVelocity")
    big, left, rear = road_frame(tr["x"].to_numpy(float), tr["y"].to_numpy(float),
                                 tr["width"].to_numpy(float), tr["height"].to_numpy(float), d)
    tr = tr.assign(X=big, Y=left, rear_X=rear, v=d * tr["xVelocity"].to_numpy(float),
                   v_lat=-d * tr["yVelocity"].to_numpy(float))
    wrong = (tr.groupby("id")["v"].transform("median") < 0).to_numpy()
    if wrong.any():
        i = int(np.flatnonzero(wrong)[0])
        raise SchemaError(f"{meta_path}, column 'drivingDirection': vehicle {tr['id'].iloc[i]:g} "
                          f"drives against it (xVelocity {tr['xVelocity'].iloc[i]:g} m/s in "
                          f"{tracks_path.name} row {i})")
    tr = tr.sort_values(["id", "frame"], kind="stable").reset_index(drop=True)
    return tr, markings, number, rate, meta


def import_highd_recording(paths: tuple[Path, Path, Path]) -> pd.DataFrame:
    """One highD recording ``(NN_tracks.csv, NN_tracksMeta.csv, NN_recordingMeta.csv)``: one
    drive recording per vehicle, ``highd_NN_<id>``; see the importers' module doc."""
    tracks_path = paths[0]
    src = str(tracks_path)
    tr, markings, number, rate, meta = _highd_tracks(paths)
    lead = _leader_rows(tr)
    has_pre = tr["precedingId"].to_numpy() > 0
    missing = has_pre & lead["lead_rear"].isna().to_numpy()
    has_lead = has_pre & ~missing
    if not has_lead.any():
        raise SchemaError(f"{src}, column 'precedingId': no row with a leader (0 everywhere, or "
                          "naming no vehicle of that frame)")
    d = tr["direction"].to_numpy(float)
    psi = np.arctan2(tr["v_lat"].to_numpy(float), np.maximum(tr["v"].to_numpy(float),
                                                             MIN_HEADING_SPEED))
    y_ego = tr["Y"].to_numpy(float)
    left, right, outside = lane_lines(y_ego, d, markings)
    cos, sin = np.cos(psi), np.sin(psi)
    raw_gap = lead["lead_rear"].to_numpy(float) - tr["X"].to_numpy(float)
    clipped = has_lead & (raw_gap < MIN_GAP)
    gap = np.where(has_lead, np.maximum(raw_gap, MIN_GAP), np.nan)
    dy = lead["lead_Y"].to_numpy(float) - y_ego
    # road-frame offset (gap along, dy across) rotated into the ego frame, as for NGSIM
    ids = tr["id"].to_numpy(np.int64)
    df = pd.DataFrame({
        "recording_id": [f"highd_{number:02d}_{i}" for i in ids],
        "time": tr["frame"].to_numpy(float) / rate,
        "x": tr["X"].to_numpy(float), "y": y_ego, "yaw": psi, "v_x": tr["v"].to_numpy(float),
        "left_c0": (left - y_ego) / cos, "left_c1": -np.tan(psi), "left_c2": 0.0, "left_c3": 0.0,
        "right_c0": (right - y_ego) / cos, "right_c1": -np.tan(psi), "right_c2": 0.0,
        "right_c3": 0.0,
        "lead_x": cos * gap + sin * dy, "lead_y": np.where(has_lead, -sin * gap + cos * dy, np.nan),
        "lead_v": np.where(has_lead, lead["lead_speed"].to_numpy(float), np.nan),
        "lane_index": tr["laneId"].to_numpy(float),
    })
    out = validate_drive(df, src)
    used = meta[meta["id"].isin(np.unique(ids))]
    out.attrs["import_stats"] = {
        "source": src, "recordings": len(np.unique(ids)), "rows": len(out),
        "frame_rate_hz": rate, "cars": int((used["class"] == "Car").sum()),
        "trucks": int((used["class"] == "Truck").sum()),
        "vehicle_class": {f"highd_{number:02d}_{int(i)}": c
                          for i, c in zip(used["id"], used["class"], strict=True)},
        "rows_without_leader": int((~has_pre).sum()), "leader_row_missing": int(missing.sum()),
        "gap_clipped": int(clipped.sum()), "outside_markings": int(outside.sum()),
    }
    return out


def import_highd(path: str | Path) -> pd.DataFrame:
    """highD recordings (a directory, a prefix ``DIR/01`` or a file ``DIR/01_tracks.csv``) as one
    validated drive frame; ``import_stats``: ``{"files": [per recording], "recordings", "rows"}``.
    """
    parts = [import_highd_recording(p) for p in highd_recording_files(path)]
    out = pd.concat(parts, ignore_index=True) if len(parts) > 1 else parts[0]
    out.attrs["import_stats"] = {"files": [p.attrs["import_stats"] for p in parts],
                                 "recordings": int(out["recording_id"].nunique()),
                                 "rows": len(out)}
    return out
