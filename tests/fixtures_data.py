"""Small recordings in the schema and in the ORIGINAL source layouts, built in code for tests."""

from __future__ import annotations

import gzip
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.data.schema import validate_drive

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
NGSIM_PAIRS = SHARED / "ngsim_i80" / "i80_pairs.parquet"
OPENACC_DIR = SHARED / "openacc_vicolungo"


def require_file(path: Path) -> Path:
    """Skip when a real data file is missing — but FAIL under CI (env var ``CI`` set)."""
    if not path.is_file():
        msg = f"real data file missing: {path}"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return path


# ------------------------------------------------------------------------------- crafted drive

V = 20.0  # [m/s] ego speed
HZ = 10.0  # [Hz]
LANE_W = 3.5  # [m]
LANE_CHANGE_T = 10.0  # [s] first sample in the new lane
NO_LEADER = (25.0, 27.9)  # [s] first and last sample without a leader
CUT_IN_T = 40.0  # [s] first sample with the closer (cut-in) leader


def crafted_drive(duration: float = 60.0) -> pd.DataFrame:
    """One straight recording at constant speed with one lane change, one gap without leader and
    one cut-in (lead_x 40 m -> 15 m); the leader drives at the ego's speed otherwise.
    """
    t = np.round(np.arange(0.0, duration + 1e-9, 1.0 / HZ), 10)
    n = len(t)
    new_lane = t >= LANE_CHANGE_T
    # lane change to the left over 4 s, crossing the line at LANE_CHANGE_T: y ramps 0 -> LANE_W
    lat_v = LANE_W / 4.0
    y = np.clip((t - (LANE_CHANGE_T - 2.0)) * lat_v, 0.0, LANE_W)
    moving = (t > LANE_CHANGE_T - 2.0) & (t < LANE_CHANGE_T + 2.0)
    yaw = np.where(moving, np.arctan2(lat_v, V), 0.0)
    # the lane lines move with the ego's lateral position and jump by a lane width at the crossing
    c0l = 0.5 * LANE_W - y + np.where(new_lane, LANE_W, 0.0)
    lead_x = np.where(t >= CUT_IN_T, 15.0, 40.0)
    gap = (t >= NO_LEADER[0] - 1e-9) & (t <= NO_LEADER[1] + 1e-9)
    lead_x = np.where(gap, np.nan, lead_x)
    return pd.DataFrame({
        "recording_id": "crafted",
        "time": t,
        "x": V * t,
        "y": y,
        "yaw": yaw,
        "v_x": np.full(n, V),
        "left_c0": c0l, "left_c1": 0.0, "left_c2": 0.0, "left_c3": 0.0,
        "right_c0": c0l - LANE_W, "right_c1": 0.0, "right_c2": 0.0, "right_c3": 0.0,
        "lead_x": lead_x,
        "lead_y": np.where(gap, np.nan, 0.0),
        "lane_index": np.where(new_lane, 1.0, 2.0),
    })


def straight_drive(recording_id: str = "r", duration: float = 20.0, v: float = V,
                   gap: float = 30.0) -> pd.DataFrame:
    """A clean straight constant-speed car-following recording."""
    t = np.round(np.arange(0.0, duration + 1e-9, 1.0 / HZ), 10)
    n = len(t)
    return pd.DataFrame({
        "recording_id": recording_id, "time": t, "x": v * t, "y": np.zeros(n),
        "yaw": np.zeros(n), "v_x": np.full(n, v),
        "left_c0": 1.75, "left_c1": 0.0, "left_c2": 0.0, "left_c3": 0.0,
        "right_c0": -1.75, "right_c1": 0.0, "right_c2": 0.0, "right_c3": 0.0,
        "lead_x": np.full(n, gap), "lead_y": np.zeros(n), "lead_v": np.full(n, v),
    })


# ------------------------------------------------------------------------ NGSIM original CSV

NGSIM_HEADER = (
    "Vehicle_ID,Frame_ID,Total_Frames,Global_Time,Local_X,Local_Y,Global_X,Global_Y,v_Length,"
    "v_Width,v_Class,v_Vel,v_Acc,Lane_ID,Preceding,Following,Space_Headway,Time_Headway"
)


def ngsim_csv_rows(frames: int = 100) -> pd.DataFrame:
    """Three vehicles in lane 2 (feet): 1 leads, 2 follows 1, 3 follows 2 then (after 2 leaves
    for lane 3 at frame 60) follows 1. Speed 30 ft/s, 15 ft long, Local_X 18 ft (lane centre).
    """
    rows = []
    for f in range(frames):
        t = f * 0.1
        y1, y2, y3 = 200.0 + 30 * t, 150.0 + 30 * t, 100.0 + 30 * t
        lane2 = 2 if f < 60 else 3
        x2 = 18.0 if f < 60 else 30.0
        pre3 = 2 if f < 60 else 1
        head3 = (y2 - y3) if f < 60 else (y1 - y3)
        rows += [
            (1, 1000 + f, frames, 1113433135300 + 100 * f, 18.0, y1, 0, 0, 15.0, 6.0, 2, 30.0,
             0.0, 2, 0, 2, 0.0, 0.0),
            (2, 1000 + f, frames, 1113433135300 + 100 * f, x2, y2, 0, 0, 15.0, 6.0, 2, 30.0,
             0.0, lane2, 1 if f < 60 else 0, 3, y1 - y2 if f < 60 else 0.0, 1.67),
            (3, 1000 + f, frames, 1113433135300 + 100 * f, 18.0, y3, 0, 0, 15.0, 6.0, 2, 30.0,
             0.0, 2, pre3, 0, head3, 1.67),
        ]
    return pd.DataFrame(rows, columns=NGSIM_HEADER.split(","))


def write_ngsim_csv(path: Path, frames: int = 100, drop: str | None = None) -> Path:
    df = ngsim_csv_rows(frames)
    if drop:
        df = df.drop(columns=[drop])
    df.to_csv(path, index=False)
    return path


# ----------------------------------------------------------------------- NGSIM pairs parquet


def ngsim_pairs_frame(n: int = 120) -> pd.DataFrame:
    """Two pairs in the I-80 pairs layout (metric): "2-1" in lane 2 and "5-4" in lane 1."""
    parts = []
    for pid, fol, lead, lane, lx in (("2-1", 2, 1, 2, 5.49), ("5-4", 5, 4, 1, 1.83)):
        t = np.round(np.arange(n) * 0.1, 10)
        ly = 50.0 + 9.0 * t
        parts.append(pd.DataFrame({
            "pair_id": pid, "time": t, "duration": t[-1], "vehicle_id": str(fol),
            "frame_id": 500.0 + np.arange(n), "local_x": lx, "local_y": ly,
            "v_length": 4.5, "v_width": 1.8, "v_class": "2", "v_vel": 9.0, "v_acc": 0.0,
            "lane_id": str(lane), "preceding": str(lead), "space_headway": 20.0,
            "time_headway": 2.2, "preceding_local_y": ly + 20.0, "preceding_length": 4.5,
            "preceding_width": 1.8, "preceding_class": "2", "preceding_vel": 9.0,
            "preceding_acc": 0.0,
        }))
    df = pd.concat(parts, ignore_index=True)
    for c in ("vehicle_id", "v_class", "lane_id", "preceding", "preceding_class"):
        df[c] = df[c].astype("category")
    return df


# -------------------------------------------------------------------------- OpenACC csv


def openacc_text(n: int = 300, drivers: tuple[str, ...] = ("Human",) * 5,
                 no_optional_for: int | None = None, drop: str | None = None,
                 v: float = 30.0, spacing: float = 40.0, length: float = 4.5) -> str:
    """An OpenACC file: 5 metadata rows, header, ``n`` rows at 10 Hz; a platoon driving north-east
    on a straight road, vehicle k starts ``spacing`` [m] behind k-1 (front to front).
    """
    k_n = len(drivers)
    t = 380000.0 + np.arange(n) * 0.1
    heading = np.pi / 4
    cols: dict[str, np.ndarray] = {"Time": t}
    for k in range(1, k_n + 1):
        s = v * (t - t[0]) - (k - 1) * spacing
        block = {
            "Speed": np.full(n, v), "Lat": np.full(n, 0.797), "Lon": np.full(n, 0.15),
            "Alt": np.full(n, 300.0), "E": s * np.cos(heading), "N": s * np.sin(heading),
            "U": np.zeros(n), "VE": np.full(n, v * np.cos(heading)),
            "VN": np.full(n, v * np.sin(heading)), "VU": np.zeros(n),
        }
        for name, val in block.items():
            if k == no_optional_for and name in ("Alt", "U", "VE", "VN", "VU"):
                continue
            cols[f"{name}{k}"] = val
    for k in range(1, k_n):
        cols[f"IVS{k}"] = np.full(n, spacing - length)
    for k in range(1, k_n + 1):
        cols[f"Driver{k}"] = np.array([drivers[k - 1]] * n)
    df = pd.DataFrame(cols)
    if drop:
        df = df.drop(columns=[drop])
    acc = 0 if all(d == "Human" for d in drivers[1:]) else 1
    meta = ("Date,28,2,2019\nVehicle_order," + ",".join(f"car{k}" for k in range(1, k_n + 1))
            + f"\nNumber_of_vehicles,{k_n}\nACC,{acc}\nDistance_setting,min\n")
    return meta + df.to_csv(index=False)


def write_openacc(path: Path, gz: bool = False, **kwargs) -> Path:
    text = openacc_text(**kwargs)
    if gz:
        with gzip.open(path, "wt") as fh:
            fh.write(text)
    else:
        path.write_text(text)
    return path


# ------------------------------------------------------------ a long curved OpenACC recording


def _curved_path(segments: list[tuple[float, float]], ds: float = 0.5,
                 transition_m: float = 60.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arc length ``s``, points ``(N, 2)`` and heading of a road made of ``(length [m],
    curvature [1/m])`` pieces joined by linear curvature ramps (clothoids) of ``transition_m``."""
    knots_s, knots_k = [0.0], [segments[0][1]]
    for length, kappa in segments:
        knots_s += [knots_s[-1] + transition_m, knots_s[-1] + length]
        knots_k += [kappa, kappa]
    s = np.arange(0.0, knots_s[-1], ds)
    kappa = np.interp(s, knots_s, knots_k)
    heading = np.r_[0.0, np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)]
    xy = np.stack([np.r_[0.0, np.cumsum(np.cos(heading[:-1]) * ds)],
                   np.r_[0.0, np.cumsum(np.sin(heading[:-1]) * ds)]], axis=1)
    return s, xy, heading


CURVED_SEGMENTS = [(400.0, 0.0), (250.0, 1 / 200.0), (600.0, 0.0), (700.0, -1 / 500.0),
                   (500.0, 0.0), (1500.0, 1 / 1000.0), (6000.0, 0.0)]


def curved_openacc_text(duration: float = 240.0, speed_bias: float = 0.005,
                        gnss_noise_m: float = 0.02, seed: int = 0) -> str:
    """An OpenACC file of one human follower behind a human leader over ``duration`` [s] on a
    road with a tight curve (R = 200 m: the importer clips the lane curvature there), an
    S-bend and a long gentle curve (``CURVED_SEGMENTS``, clothoid transitions). The leader's
    speed swings 24-32 m/s, the bumper gap 25-45 m; the follower wanders 0.25 m in its lane; the
    GNSS positions carry white noise (``gnss_noise_m``) and the speed sensors read
    ``speed_bias`` high (so a leader driven by its speed alone drifts, ~35 m over the drive).
    """
    rng = np.random.default_rng(seed)
    s_road, xy, heading = _curved_path(CURVED_SEGMENTS)
    t = np.arange(0.0, duration + 1e-9, 0.1)
    v1 = 28.0 + 4.0 * np.sin(2 * np.pi * t / 60.0)
    s1 = 100.0 + np.r_[0.0, np.cumsum(0.5 * (v1[1:] + v1[:-1]) * 0.1)]  # leader front [m]
    gap = 35.0 + 10.0 * np.sin(2 * np.pi * t / 45.0 + 1.0)
    length = 4.5
    s2 = s1 - gap - length
    v2 = np.gradient(s2, t)
    wander = 0.25 * np.sin(2 * np.pi * t / 30.0)

    def world(s: np.ndarray, lateral: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = np.interp(s, s_road, xy[:, 0]), np.interp(s, s_road, xy[:, 1])
        h = np.interp(s, s_road, heading)
        noise = rng.normal(0.0, gnss_noise_m, size=(2, len(s)))
        return x - lateral * np.sin(h) + noise[0], y + lateral * np.cos(h) + noise[1]

    e1, n1 = world(s1, np.zeros_like(t))
    e2, n2 = world(s2, wander)
    df = pd.DataFrame({
        "Time": 1000.0 + t, "Speed1": v1 * (1.0 + speed_bias), "E1": e1, "N1": n1, "Driver1": "Human",
        "Speed2": v2 * (1.0 + speed_bias), "E2": e2, "N2": n2, "Driver2": "Human",
        "IVS1": gap,
    })
    meta = ("Date,28,2,2019\nVehicle_order,car1,car2\nNumber_of_vehicles,2\nACC,0\n"
            "Distance_setting,min\n")
    return meta + df.to_csv(index=False)


# ------------------------------------------------------------------- the tiny recipe

# safeil-train on the tiny recordings of write_tiny_recordings ({iters}: closed-loop iterations)
TINY_RECIPE = """\
name = "tiny"
[[data]]
format = "openacc"
path = "openacc"
[[data]]
format = "ngsim"
path = "pairs.parquet"
[split]
by = "driver"
fraction = 0.3
[openloop]
max_epochs = 3
patience = 3
hidden = [8, 8]
[closed_loop]
window = 10.0
iters = {iters}
batch = 4
settle_after = 5.0
[lateral_refit]
steps = 3
batch = 64
[certify]
max_boxes = 64
budget_s = 20.0
time_gap_range_s = [1.0, 2.0]
"""


def write_tiny_recordings(folder: Path) -> None:
    """Two OpenACC files (one gzipped) and an NGSIM pairs table: the tiny recipe's data."""
    (folder / "openacc").mkdir(parents=True)
    write_openacc(folder / "openacc" / "run_a.csv", n=400)
    write_openacc(folder / "openacc" / "run_b.csv.gz", gz=True, n=400, v=25.0, spacing=35.0)
    ngsim_pairs_frame(300).to_parquet(folder / "pairs.parquet")


CSV_COLUMNS = "time=t,v=spd,lead_v=ld_spd,gap=dist"  # the map of write_car_following_csv's file


def write_car_following_csv(path: Path, duration_s: float = 60.0) -> Path:
    """A car-following CSV as a user's logger might write it: its own column names
    (:data:`CSV_COLUMNS` maps them), speeds in km/h, 10 Hz, a leader swaying around 25 m/s."""
    t = np.arange(0.0, duration_s, 0.1)
    v_lead = 25.0 + 2.0 * np.sin(t / 10.0)
    v = 25.0 + 1.5 * np.sin((t - 1.5) / 10.0)
    gap = 30.0 + 3.0 * np.sin(t / 12.0)
    pd.DataFrame({"t": np.round(t, 1), "spd": v * 3.6, "ld_spd": v_lead * 3.6,
                  "dist": gap}).to_csv(path, index=False)
    return path


# ------------------------------------------------------------------------- an arc, for replays

ARC_R = 800.0  # [m] lane-centre radius of the synthetic recording
ARC_V = 30.0  # [m/s]
ARC_HALF = 1.75  # [m] half lane width
ARC_OFFSET = 0.2  # [m] the human drives this far LEFT of the lane centre (inside of the left turn)


def arc_drive(duration: float = 15.0, hz: float = 10.0, heading0: float = 0.6,
              origin: tuple[float, float] = (5.0e5, 4.9e6)) -> pd.DataFrame:
    """A schema drive on a left arc of radius ARC_R (lane centre) at ARC_V, the human ARC_OFFSET
    left of it, a leader at constant speed 50 m ahead (the analytic planner's 1.5 s + 5 m); world
    frame rotated by ``heading0`` and far from the origin."""
    t = np.arange(0.0, duration + 1e-9, 1.0 / hz)
    r = ARC_R - ARC_OFFSET
    th = ARC_V * t / r
    cx, cy = r * np.sin(th), ARC_R - r * np.cos(th)  # circle centre at (0, ARC_R)
    c, s = math.cos(heading0), math.sin(heading0)
    x = origin[0] + c * cx - s * cy
    y = origin[1] + s * cx + c * cy
    k = 1.0 / ARC_R
    return validate_drive(pd.DataFrame({
        "recording_id": "arc", "time": t, "x": x, "y": y,
        "yaw": (th + heading0 + math.pi) % (2 * math.pi) - math.pi, "v_x": ARC_V,
        "left_c0": ARC_HALF - ARC_OFFSET, "left_c1": 0.0, "left_c2": 0.5 * k, "left_c3": 0.0,
        "right_c0": -ARC_HALF - ARC_OFFSET, "right_c1": 0.0, "right_c2": 0.5 * k, "right_c3": 0.0,
        "lead_x": 50.0, "lead_y": 0.0, "lead_v": ARC_V, "maneuver_id": "arc#0",
    }))
