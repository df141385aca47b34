"""The road of a recorded maneuver as a SUMO net: the digital twin's geometry (paper IV-C).

From the drive rows of one maneuver (schema of :mod:`safeil_sumo.data.schema`):

1. the world points of the ego's LANE CENTRE: the ego's front bumper plus the midpoint of the
   left/right lane lines at ``x = 0`` in the ego frame, ``(c0l + c0r) / 2``, rotated by ``yaw``;
   only where the car moves (:func:`moving_points`): a standing car's receiver wanders;
2. smoothed: resampled every ``spacing_m`` along the path, then a Savitzky-Golay filter (order 3,
   window ``smooth_window_m``) on x and y — a cubic over 41 m reproduces any motorway radius
   (R = 800 m: < 1 mm off) while removing the per-sample noise of GNSS and lane-line fits; where
   it strays more than ``path_tolerance_m`` from the points (walking-pace turns, GNSS wander of a
   test track), finer fits hold them, never tighter than ``max_curvature`` (:func:`smooth_path`);
3. extended by a straight run-in behind (room to insert the ego) and a straight run-out ahead,
   long enough for the leader driven by the recorded speed (and for a policy faster than the
   human) to stay on the road;
4. decimated (Ramer-Douglas-Peucker) to a chord tolerance of :data:`REPLAY_SAGITTA_M` and chords
   turning at most ``max_turn_rad``: SUMO shapes stay lean (``moveToXY`` cost grows with shape
   points, see ``network.py``).

The net: ONE edge ``"road"``, 3 lanes of the recorded lane width (median of ``c0l - c0r``,
clipped to [2.8, 4.5] m), ego in the middle lane, ``spreadType="center"`` so the edge shape IS
the ego lane centre. Three lanes rather than one: a policy that drifts out of its lane (the paper's
BC) then sees the neighbouring lane's lines and loses its leader, as a real camera and radar would.
Coordinates are LOCAL (:class:`LocalFrame`): origin at the recorded ego position at the maneuver
start, x along the lane's initial heading (sidecar: ``origin_x/origin_y/rotation_rad``), so the
road runs along +x as in the paper's plots and large GNSS coordinates never reach SUMO.

A recording of a closed course driven in laps passes the same place again: its road crosses its
own start node (2 cm custom node shapes keep netconvert from cutting it there, and a check raises
if netconvert changes its length), and the nearest point of the road may be another lap's, so the
recorded path's stations are walked along the road from the start (:func:`recorded_stations`).

The sidecar ``<name>.track.json`` holds ``ego_lane``, ``path_start_s`` (the station of the
recorded start on the SUMO ego lane) and ``path_end_s`` (the recorded end's plus
``path_end_margin_m``: a policy faster than the human is not stopped by the runner's "completed"
check; the replay ends on time), read by :func:`safeil_sumo.roads.road.load_road`. It has no
``generator_version`` key on purpose: that key makes ``load_road`` rebuild a TrackSpec arc; a
replay's SUMO lane (5 cm chords) is its own exact geometry.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.ndimage import maximum_filter1d, uniform_filter1d
from scipy.signal import savgol_filter

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.roads import network
from safeil_sumo.roads.road import NetworkError, Road, load_road

EDGE_ID = network.EDGE_ID
ROUTE_ID = network.ROUTE_ID
REPLAY_GENERATOR_VERSION = 2  # 2: node shapes, walked stations, finer fits (ZalaZone)
# Chord tolerance [m] of the SUMO shape: ~11 m chords at R = 800 m. Finer than network.py's 10 cm
# because here the SUMO polygon is also what the camera and the monitors measure against: the
# recorded human replayed on it (sim/recorded_ego.py) must stay in its lane (5 cm let the chords
# push bodies that keep 1-2 cm from a recorded line over it; 2 cm costs ~10 % more replay time).
REPLAY_SAGITTA_M = 0.02
LANE_WIDTH_RANGE_M = (2.8, 4.5)  # [m] plausible lane widths; outside = a bad lane-line fit
# [m] custom node shapes across the road's ends (network.nodes_xml): netconvert's own, across all
# lanes, cut the road where a lap of a closed course crossed its start again
NODE_SHAPE_M = 0.02
# [m] the SUMO ego lane's length may differ from the shape written by netconvert's 1 mm
# precision per vertex; more means netconvert cut or moved the shape
SHAPE_LENGTH_TOLERANCE_M = 0.05

_NAME_RE = re.compile(r"[^A-Za-z0-9_-]+")


@dataclass(frozen=True)
class HeadingCheck:
    """When a recorded heading is believed (:func:`plausible_heading`)."""

    # largest heading - direction of travel [rad] (~8.6 deg): side-slip in ordinary driving stays
    # within ~3 deg; NGSIM's headings (from its own smoothed path) reach 0.13 rad at a few
    # recording ends, where the smoothing runs out
    max_slip_rad: float = 0.15
    # [m/s] slower than this over the window the direction of travel is receiver noise (a
    # standing car's GNSS wanders by centimetres)
    min_speed_mps: float = 1.0
    half_window_s: float = 0.5  # [s] half the window of the direction of travel

    def __post_init__(self) -> None:
        for name in ("max_slip_rad", "min_speed_mps", "half_window_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"HeadingCheck.{name} must be > 0")


@dataclass(frozen=True)
class ReplayRoadConfig:
    """How the recorded lane becomes a SUMO road."""

    lanes: int = 3  # number of lanes [-]; the ego lane is the middle one (lanes must be odd)
    spacing_m: float = 1.0  # resampling step of the lane centre [m]
    # [m/s] the lane centre is built from the samples where the car moves at least this fast
    # over the 0.5 s before and after (moving_points): a standing car's receiver wanders by
    # centimetres to decimetres, and that wander, resampled, makes the path double back
    min_speed_mps: float = 1.0
    smooth_window_m: float = 41.0  # Savitzky-Golay window (order 3) along the path [m]
    # [m] where the smoothed lane centre strays further than this from the recorded centre
    # points, finer fits hold it (smooth_path); None: the smooth_window_m fit alone. 0.1 m: the
    # OpenACC, NGSIM and synthetic recordings stay within 0.06 m of the 41 m fit (unchanged)
    path_tolerance_m: float | None = 0.1
    # [1/m] the finer fits never bend the lane tighter than a car turns (R = 5 m, a turning
    # circle of ~10 m): tighter, the recorded path is receiver wander (smooth_path)
    max_curvature: float | None = 0.2
    run_in_m: float = 30.0  # straight behind the recorded start [m] (ego insertion)
    run_out_extra_m: float = 200.0  # straight past the farthest leader position [m] (radar/camera)
    path_end_margin_m: float = 100.0  # test path end = recorded end + this [m]
    max_sagitta_m: float = REPLAY_SAGITTA_M  # chord tolerance of the SUMO shape [m]
    # [rad] most the road may turn along one chord of the SUMO shape (decimate): only curves
    # tighter than R ~ 64 m need it at a 2 cm sagitta (ZalaZone's low-speed ends)
    max_turn_rad: float | None = 0.05
    speed_limit_mps: float = 36.1  # edge speed limit [m/s] (not used by remote-controlled cars)

    def __post_init__(self) -> None:
        if self.lanes < 1 or self.lanes % 2 == 0:
            raise ValueError(f"lanes must be odd (ego in the middle), got {self.lanes}")
        for name in ("spacing_m", "smooth_window_m", "max_sagitta_m", "speed_limit_mps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ReplayRoadConfig.{name} must be > 0")
        for name in ("run_in_m", "run_out_extra_m", "path_end_margin_m", "min_speed_mps"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"ReplayRoadConfig.{name} must be >= 0")
        for name in ("path_tolerance_m", "max_turn_rad", "max_curvature"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                raise ValueError(f"ReplayRoadConfig.{name} must be > 0 (or None)")

    @property
    def ego_lane(self) -> int:
        return self.lanes // 2


# ----------------------------------------------------------------------------------- pure maths


def lane_centre_points(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, c0_left: np.ndarray,
                       c0_right: np.ndarray) -> np.ndarray:
    """World points ``(N, 2)`` [m] of the lane centre beside the ego at each sample.

    The lines' midpoint at ``x = 0`` in the ego frame is ``(0, (c0l + c0r) / 2)``; rotated by
    ``yaw`` and added to the ego position ``(x, y)``.
    """
    m = 0.5 * (np.asarray(c0_left, float) + np.asarray(c0_right, float))
    yaw = np.asarray(yaw, float)
    return np.stack([np.asarray(x, float) - m * np.sin(yaw),
                     np.asarray(y, float) + m * np.cos(yaw)], axis=1)


def course_over_ground(t: np.ndarray, x: np.ndarray, y: np.ndarray, half_window_s: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Direction of travel [rad, wrapped] and mean speed over the window [m/s], ``(N,)`` each,
    from the positions ``x, y (N,)`` [m] at times ``t (N,)`` [s, increasing]: the displacement
    between ``t - half_window_s`` and ``t + half_window_s`` (positions linearly interpolated,
    the window cut at the ends)."""
    t = np.asarray(t, float)
    a = np.maximum(t - half_window_s, t[0])
    b = np.minimum(t + half_window_s, t[-1])
    dx = np.interp(b, t, x) - np.interp(a, t, x)
    dy = np.interp(b, t, y) - np.interp(a, t, y)
    span = np.maximum(b - a, 1e-9)
    return np.arctan2(dy, dx), np.hypot(dx, dy) / span


def plausible_heading(t: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
                      config: HeadingCheck | None = None) -> np.ndarray:
    """The recorded heading ``yaw (N,)`` [rad, wrapped] where it agrees with the direction of
    travel of the positions (:func:`course_over_ground`) within ``config.max_slip_rad``; the
    direction of travel where the car moves and the yaw does not agree; where the car barely
    moves (below ``config.min_speed_mps`` over the window) the heading of the moving samples
    interpolated (unwrapped; the ends hold the nearest one). Unchanged where it moves and agrees
    everywhere, or where it never moves.

    A car's heading and its direction of travel differ by its side-slip, a few degrees in
    ordinary driving; a yaw beyond that is a sensor glitch (a GNSS heading jump). Where the car
    barely moves the direction of travel, and a heading derived from it, is receiver noise: a
    kinematic replay would spin the body there.
    """
    config = config or HeadingCheck()
    yaw = np.asarray(yaw, float)
    course, speed = course_over_ground(t, x, y, config.half_window_s)
    moving = speed >= config.min_speed_mps
    slip = (yaw - course + math.pi) % (2.0 * math.pi) - math.pi
    agrees = np.abs(slip) <= config.max_slip_rad
    if not moving.any() or (moving & agrees).all():
        return yaw.copy()
    heading = np.unwrap(np.where(agrees, yaw, course))
    idx = np.arange(len(yaw))
    heading = np.where(moving, heading, np.interp(idx, idx[moving], heading[moving]))
    return (heading + math.pi) % (2.0 * math.pi) - math.pi


def lane_width(c0_left: np.ndarray, c0_right: np.ndarray,
               limits: tuple[float, float] = LANE_WIDTH_RANGE_M) -> float:
    """Median of ``c0l - c0r`` [m], clipped to ``limits``."""
    w = np.asarray(c0_left, float) - np.asarray(c0_right, float)
    w = w[np.isfinite(w)]
    if len(w) == 0:
        raise ValueError("no finite lane-line offsets to measure the lane width")
    return float(np.clip(np.median(w), *limits))


def resample_path(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points ``(M, 2)`` every ``spacing_m`` along the polyline ``points (N, 2)`` (ends kept).

    Repeated points (a standing car) are dropped first.
    """
    p = np.asarray(points, float)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    keep = np.r_[True, step > 1e-6]
    p = p[keep]
    if len(p) < 2:
        raise ValueError("the recorded path does not move (need >= 2 distinct positions)")
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    n = max(math.ceil(s[-1] / spacing_m), 1)
    q = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(q, s, p[:, 0]), np.interp(q, s, p[:, 1])], axis=1)


def smooth_path(points: np.ndarray, spacing_m: float, window_m: float,
                tolerance_m: float | None = None, max_curvature: float | None = None
                ) -> np.ndarray:
    """Resampled every ``spacing_m`` and Savitzky-Golay smoothed (order 3, ``window_m``).

    ``tolerance_m`` [m]: where that fit strays further than this from a resampled point, finer
    fits take over (:func:`smoothing_windows`: each about half the window of the one before,
    down to 5 samples): each point is held by the widest fit within the tolerance of it; that
    choice is widened to a whole ``window_m`` around the point (a fit is trusted where its
    window holds) and blended over ``window_m`` into its neighbours' (a step between fits would
    be a kink in the lane's heading). A path every fit holds gets the ``window_m`` fit exactly.
    Tight turns at walking pace (R < 20 m, which a cubic over 41 m cannot follow) and GNSS
    wander that the recording's own lane (centred on its path) follows are what take finer fits.
    ``max_curvature`` [1/m]: a fit bending tighter than this at a point (no car turns so
    tightly: receiver wander) does not hold it; where no fit is both within the tolerance and
    below it, the finest one below it does (the widest where none is).
    """
    p = resample_path(points, spacing_m)
    windows = smoothing_windows(len(p), window_m / spacing_m)
    fits = [np.stack([savgol_filter(p[:, k], w, 3, mode="interp") for k in (0, 1)], axis=1)
            for w in windows]
    if not fits:  # too short to smooth with a cubic: keep as is
        return p
    if tolerance_m is None or len(fits) == 1:
        return fits[0]
    near = np.stack([np.linalg.norm(f - p, axis=1) <= tolerance_m for f in fits])  # (F, M)
    drivable = np.ones_like(near) if max_curvature is None else np.stack(
        [np.abs(path_curvature(f)) <= max_curvature for f in fits])
    # the widest fit that holds the point; else the finest drivable one; else the widest
    finest_drivable = len(fits) - 1 - np.argmax(drivable[::-1], axis=0)
    level = np.where((near & drivable).any(axis=0), np.argmax(near & drivable, axis=0),
                     np.where(drivable.any(axis=0), finest_drivable, 0))
    if not level.any():
        return fits[0]
    # widened, but never to a fit that bends too tightly there
    cap = np.where(drivable.any(axis=0), finest_drivable, 0)
    level = np.minimum(maximum_filter1d(level, size=windows[0], mode="nearest"), cap)
    blend = uniform_filter1d(level.astype(float), size=windows[0], mode="nearest")
    lo = np.minimum(np.floor(blend).astype(int), len(fits) - 2)
    frac = (blend - lo)[:, None]
    stacked = np.stack(fits)  # (F, M, 2)
    idx = np.arange(len(p))
    return (1.0 - frac) * stacked[lo, idx] + frac * stacked[lo + 1, idx]


def path_curvature(points: np.ndarray) -> np.ndarray:
    """Signed curvature ``(N,)`` [1/m, left +] of the polyline ``points (N >= 3, 2)`` at each
    point: the turn of the heading between its neighbouring segments over their mean length
    (the ends take their neighbour's)."""
    p = np.asarray(points, float)
    seg = np.diff(p, axis=0)
    heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
    length = np.linalg.norm(seg, axis=1)
    inner = np.diff(heading) / np.maximum(0.5 * (length[1:] + length[:-1]), 1e-9)
    return np.r_[inner[0], inner, inner[-1]]


def smoothing_windows(n: int, window: float) -> list[int]:
    """The odd Savitzky-Golay windows [samples] of :func:`smooth_path` for ``n`` points: the
    first ``window`` rounded to odd (at most ``n``), each next one about half the one before,
    down to 5 (the fewest a cubic smooths); ``[]`` when ``n`` has fewer than 5 points."""
    w = min(round(window) | 1, n if n % 2 else n - 1)
    out = []
    while w >= 5:
        out.append(w)
        w = (w // 2) | 1 if w > 5 else 0
    return out


def extend_path(points: np.ndarray, run_in_m: float, run_out_m: float) -> np.ndarray:
    """Straight, tangent extensions: ``run_in_m`` before the first and ``run_out_m`` after the
    last point (tangents from the end segments)."""
    p = np.asarray(points, float)
    t0 = p[1] - p[0]
    t1 = p[-1] - p[-2]
    t0, t1 = t0 / np.linalg.norm(t0), t1 / np.linalg.norm(t1)
    parts = []
    if run_in_m > 0:
        parts.append((p[0] - run_in_m * t0)[None])
    parts.append(p)
    if run_out_m > 0:
        parts.append((p[-1] + run_out_m * t1)[None])
    return np.vstack(parts)


def decimate(points: np.ndarray, tolerance_m: float, max_turn_rad: float | None = None
             ) -> np.ndarray:
    """Ramer-Douglas-Peucker: the fewest vertices such that every dropped point is within
    ``tolerance_m`` of its chord (the chord sagitta bound of ``network.py`` for any curve) and,
    with ``max_turn_rad``, the path turns by at most that much along each chord (the segments
    it replaces span at most that range of headings).

    The turn bound matters on tight curves only: a 2 cm sagitta makes chords that turn by
    ``2 sqrt(2 sagitta / R)``, 0.025 rad at R = 250 m but 0.2 rad at R = 4 m, and the lane's
    heading, which the monitors compare the car's with, steps by that much at each vertex.
    """
    p = np.asarray(points, float)
    seg = np.diff(p, axis=0)
    heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))  # (N-1,) of the dense segments
    keep = np.zeros(len(p), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(p) - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        chord = p[b] - p[a]
        length = np.linalg.norm(chord)
        rel = p[a + 1:b] - p[a]
        if length < 1e-12:
            dist = np.linalg.norm(rel, axis=1)
        else:
            dist = np.abs(chord[0] * rel[:, 1] - chord[1] * rel[:, 0]) / length
        i = int(np.argmax(dist))
        turns = max_turn_rad is not None and np.ptp(heading[a:b]) > max_turn_rad
        if dist[i] > tolerance_m or turns:
            k = a + 1 + i
            keep[k] = True
            stack += [(a, k), (k, b)]
    return p[keep]


def circle_radius(points: np.ndarray) -> float:
    """Least-squares (Kasa) circle radius [m] through ``points (N, 2)`` (for tests and checks)."""
    p = np.asarray(points, float)
    c = p.mean(axis=0)
    q = p - c
    a = np.column_stack([2 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(a, np.sum(q**2, axis=1), rcond=None)
    return float(math.sqrt(sol[2] + sol[0] ** 2 + sol[1] ** 2))


# ----------------------------------------------------------------------------------- the road


@dataclass(frozen=True)
class LocalFrame:
    """World -> replay frame: origin at the recorded start, x along the lane's initial heading."""

    origin_x: float  # world x of the origin [m]
    origin_y: float  # world y of the origin [m]
    rotation_rad: float  # world heading of the local +x axis [rad]

    def points(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """World points -> local ``(N, 2)`` [m]."""
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        dx, dy = np.asarray(x, float) - self.origin_x, np.asarray(y, float) - self.origin_y
        return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)

    def yaw(self, yaw: np.ndarray) -> np.ndarray:
        """World heading -> local heading [rad], wrapped to [-pi, pi)."""
        return (np.asarray(yaw, float) - self.rotation_rad + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class ReplayGeometry:
    """The lane of a recorded maneuver in the local frame (see :class:`LocalFrame`) [m]."""

    centre: np.ndarray  # (N, 2) smoothed ego-lane centre (every spacing_m) + straight ends [m]
    shape: np.ndarray  # (K, 2) the decimated SUMO edge shape [m]
    lane_width_m: float  # [m]
    frame: LocalFrame
    start_xy: np.ndarray  # (2,) recorded ego front bumper at the start, local [m]
    end_xy: np.ndarray  # (2,) recorded ego front bumper at the end, local [m]
    run_out_m: float  # straight past the recorded end [m]
    path_xy: np.ndarray  # (M, 2) the recorded ego front bumper at every sample, local [m]


def replay_geometry(rows: pd.DataFrame, config: ReplayRoadConfig = ReplayRoadConfig(),
                    leader_travel_m: float | None = None) -> ReplayGeometry:
    """Lane-centre geometry of one maneuver's drive rows (sorted by time).

    ``leader_travel_m``: how far the leader drives during the replay (default: from ``v_lead``
    or ``lead_v`` and the duration); sets the run-out.
    """
    need = ("time", "x", "y", "yaw", "v_x", "left_c0", "right_c0", "lead_x")
    missing = [c for c in need if c not in rows.columns]
    if missing:
        raise ValueError(f"drive rows lack column(s) {', '.join(missing)}")
    if len(rows) < 2:
        raise ValueError("a maneuver needs at least 2 samples")
    x, y = rows["x"].to_numpy(float), rows["y"].to_numpy(float)
    c0l, c0r = rows["left_c0"].to_numpy(float), rows["right_c0"].to_numpy(float)
    pts = lane_centre_points(x - x[0], y - y[0], rows["yaw"].to_numpy(float), c0l, c0r)
    smooth = smooth_path(pts[moving_points(rows, config)], config.spacing_m,
                         config.smooth_window_m, config.path_tolerance_m, config.max_curvature)
    heading = math.atan2(smooth[1, 1] - smooth[0, 1], smooth[1, 0] - smooth[0, 0])
    frame = LocalFrame(float(x[0]), float(y[0]), heading)
    smooth = frame.points(smooth[:, 0] + x[0], smooth[:, 1] + y[0])
    width = lane_width(c0l, c0r)
    if leader_travel_m is None:
        leader_travel_m = recorded_leader_travel(rows)
    recorded_len = float(np.sum(np.linalg.norm(np.diff(smooth, axis=0), axis=1)))
    # leader front at the end, from the recorded start: gap + its length (<= 20 m) + travel;
    # the run-out covers it (and the test-path margin) plus the sensors' reach
    lead_end = float(rows["lead_x"].iloc[0]) + 20.0 + leader_travel_m
    run_out = max(lead_end - recorded_len, config.path_end_margin_m, 0.0) \
        + config.run_out_extra_m
    dense = extend_path(smooth, config.run_in_m, run_out)
    return ReplayGeometry(
        centre=dense, shape=decimate(dense, config.max_sagitta_m, config.max_turn_rad),
        lane_width_m=width,
        frame=frame, start_xy=frame.points(x[0], y[0]), end_xy=frame.points(x[-1], y[-1]),
        run_out_m=run_out, path_xy=frame.points(x, y),
    )


def moving_points(rows: pd.DataFrame, config: ReplayRoadConfig = ReplayRoadConfig()
                  ) -> np.ndarray:
    """``(N,)`` True at the samples whose lane-centre point builds the road: where the car moves
    at least ``config.min_speed_mps`` over the 0.5 s before AND the 0.5 s after the sample (at
    the ends, the one there is), so the last positions of a standstill, whose centred window
    already sees the car leave, are not kept; every sample when fewer than 2 qualify. A
    recorded start or end at a standstill then lies on the straight run-in or run-out
    (:func:`extend_path`), within the receiver's wander."""
    t = rows["time"].to_numpy(float)
    x, y = rows["x"].to_numpy(float), rows["y"].to_numpy(float)
    before, after = _half_window_speed(t, x, y, -0.5), _half_window_speed(t, x, y, 0.5)
    keep = np.minimum(before, after) >= config.min_speed_mps
    return keep if keep.sum() >= 2 else np.ones(len(rows), dtype=bool)


def _half_window_speed(t: np.ndarray, x: np.ndarray, y: np.ndarray, window_s: float
                       ) -> np.ndarray:
    """Mean speed [m/s] ``(N,)`` over ``[t, t + window_s]`` (``window_s < 0``: before ``t``),
    positions linearly interpolated; where that window is cut to nothing by the recording's
    end, the one on the other side."""
    other = np.clip(t - window_s, t[0], t[-1])
    end = np.clip(t + window_s, t[0], t[-1])
    end = np.where(end == t, other, end)
    span = np.maximum(np.abs(end - t), 1e-9)
    return np.hypot(np.interp(end, t, x) - x, np.interp(end, t, y) - y) / span


def recorded_stations(centre: Polyline, path_xy: np.ndarray, s_start: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Frenet ``s, d`` ``(N,)`` [m] of the recorded path ``(N, 2)`` (local frame) on the
    rebuilt lane ``centre``, walking along both from the start near arc length ``s_start``
    (:meth:`Polyline.project_along`): on a closed course the road passes the recorded start
    again on every lap, and the nearest pass (``Polyline.project``) may be another lap's."""
    return centre.project_along(path_xy, s_start)


def recorded_leader_travel(rows: pd.DataFrame) -> float:
    """Distance [m] the recorded leader drives: trapezoid integral of its speed."""
    t = rows["time"].to_numpy(float)
    v = leader_speed(rows)
    return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)))


def leader_speed(rows: pd.DataFrame) -> np.ndarray:
    """Recorded leader speed ``(N,)`` [m/s]: ``v_lead`` (the pipeline's), else ``lead_v``, else
    ``v_x + d(lead_x)/dt``; gaps filled from the differentiated one; clipped at 0."""
    t = rows["time"].to_numpy(float)
    diff = rows["v_x"].to_numpy(float) + np.gradient(rows["lead_x"].to_numpy(float), t)
    v = np.full(len(rows), np.nan)
    for col in ("v_lead", "lead_v"):
        if col in rows.columns:
            v = rows[col].to_numpy(float)
            break
    return np.maximum(np.where(np.isfinite(v), v, diff), 0.0)


def drift_corrected_speed(t: np.ndarray, speed: np.ndarray, position: np.ndarray,
                          window_s: float) -> np.ndarray:
    """A speed ``(N,)`` [m/s] close to ``speed`` whose integral follows ``position`` ``(N,)`` [m].

    A recorded leader driven by its recorded speed drifts from where it was recorded: the speed
    sensor and the GNSS path (plus the radar gap) disagree by about 1 %, metres over a minute.
    The drift ``position - position[0] - integral(speed)`` is low-passed (Savitzky-Golay, order
    2, ``window_s``, on a uniform grid) and its derivative added to ``speed``: the speed keeps its
    fine detail (a braking onset) and loses the slow drift; what is left of the drift is its part
    faster than ``window_s``. ``window_s <= 0``: ``speed`` unchanged. Clipped at 0.
    """
    t = np.asarray(t, float)
    v = np.asarray(speed, float)
    if window_s <= 0 or len(t) < 2:
        return np.maximum(v, 0.0)
    p = np.asarray(position, float)
    travelled = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))]
    drift = (p - p[0]) - travelled
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    d = np.interp(grid, t, drift)
    w = min(round(window_s / dt) | 1, len(grid) if len(grid) % 2 else len(grid) - 1)
    if w >= 5:
        rate = savgol_filter(d, w, 2, deriv=1, delta=dt, mode="interp")
    else:  # too few samples for a filter: the mean drift rate
        rate = np.full(len(grid), (drift[-1] - drift[0]) / (t[-1] - t[0]))
    return np.maximum(v + np.interp(t, grid, rate), 0.0)


def safe_name(text: str) -> str:
    """A file-name stem from a maneuver id (``JRC-VC_280219_part3_f2#0`` -> ``JRC-VC_280219_part3_f2_0``)."""
    return _NAME_RE.sub("_", text).strip("_") or "replay"


def build_replay_net(rows: pd.DataFrame, out_dir: Path, name: str,
                     config: ReplayRoadConfig = ReplayRoadConfig(),
                     meta: dict | None = None) -> Path:
    """Write the maneuver's road into ``out_dir`` (atomically) and return the ``.net.xml`` path.

    Files: ``<name>.nod.xml``, ``.edg.xml``, ``.net.xml``, ``.rou.xml``, ``.sumocfg`` (opens in
    sumo-gui) and ``.track.json``. ``meta`` (e.g. the maneuver id) is added to the sidecar.
    Raises ValueError for unusable rows, :class:`NetworkError` when netconvert fails.
    """
    name = safe_name(name)
    geo = replay_geometry(rows, config)
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}-build-", dir=out_dir.parent))
    try:
        (tmp / f"{name}.nod.xml").write_text(network.nodes_xml(geo.shape, NODE_SHAPE_M))
        (tmp / f"{name}.edg.xml").write_text(network.edges_xml(
            geo.shape, config.lanes, geo.lane_width_m, config.speed_limit_mps))
        version = network.run_netconvert(name, tmp, "safeil_sumo.roads.recorded_road")
        (tmp / f"{name}.rou.xml").write_text(network.routes_xml())
        (tmp / f"{name}.sumocfg").write_text(network.sumocfg_xml(name))
        net = tmp / f"{name}.net.xml"
        road = load_road(net, edge_id=EDGE_ID, ego_lane=config.ego_lane)
        if len(road.lanes) != config.lanes:
            raise NetworkError(f"{net}: netconvert built {len(road.lanes)} lanes, not "
                               f"{config.lanes}")
        centre = road.lanes[config.ego_lane].centre
        kept = centre.length - float(np.sum(np.linalg.norm(np.diff(geo.shape, axis=0), axis=1)))
        if abs(kept) > SHAPE_LENGTH_TOLERANCE_M:
            raise NetworkError(f"{net}: netconvert changed the road's length by {kept:+.3f} m "
                               f"({centre.length:.1f} m of {centre.length - kept:.1f} m)")
        s = recorded_stations(centre, geo.path_xy, config.run_in_m)[0][[0, -1]]
        sidecar = {
            "name": name, "kind": "replay", "edge_id": EDGE_ID, "route_id": ROUTE_ID,
            "lanes": config.lanes, "ego_lane": config.ego_lane,
            "lane_width_m": round(geo.lane_width_m, 4),
            "path_start_s": round(float(s[0]), 3),
            "path_end_s": round(min(float(s[1]) + config.path_end_margin_m,
                                    centre.length - 1.0), 3),
            "origin_x": geo.frame.origin_x, "origin_y": geo.frame.origin_y,
            "rotation_rad": geo.frame.rotation_rad,
            "run_out_m": round(geo.run_out_m, 3), "shape_points": len(geo.shape),
            "max_sagitta_m": config.max_sagitta_m, "config": asdict(config),
            "replay_generator_version": REPLAY_GENERATOR_VERSION,
            "netconvert_version": version, **(meta or {}),
        }
        (tmp / f"{name}.track.json").write_text(json.dumps(sidecar, indent=2) + "\n")
        network.publish(tmp, out_dir, [name + sfx for sfx in (".nod.xml", ".edg.xml", ".net.xml",
                                                        ".rou.xml", ".sumocfg", ".track.json")])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir / f"{name}.net.xml"


def load_replay_road(net_path: Path) -> tuple[Road, LocalFrame]:
    """The replay road (ego lane and test path from the sidecar) and its local frame."""
    road = load_road(net_path, edge_id=EDGE_ID)
    m = road.meta
    if m.get("kind") != "replay":
        raise NetworkError(f"{net_path}: not a replay road (no replay track.json sidecar)")
    return road, LocalFrame(float(m["origin_x"]), float(m["origin_y"]), float(m["rotation_rad"]))
