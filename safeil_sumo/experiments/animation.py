"""Animations of a results folder: one scenario (run folder) or one policy (replay folder), drawn
frame by frame with matplotlib from the folder's ``steps.parquet`` alone (plus the road of its
manifest or ``net/``), so ``run --animate``, ``replay --animate``, ``safeil-animate`` and the
Gymnasium envs' ``rgb_array`` frames (:class:`FrameDrawer`) are the same pictures. Each frame:
a top-down view that follows the ego (rotated so the lane ahead points right), the lane lines of
every lane, the ego and the leader as boxes, the plan being tracked (clamped cubic B-spline) and
its 4 control points, the recorded human in replay folders, a time stamp and the safety flags;
below, speed and gap over the whole scenario with a cursor at the frame's time.

Frames are taken every ``speed / fps`` seconds of simulated time from the 100 Hz log (the last
logged row at or before the frame's time). The file is an MP4 when an ffmpeg is found (on PATH, or
the optional ``imageio-ffmpeg`` wheel: ``pip install 'safeil-sumo[video]'``), else a GIF written
by Pillow (installed with matplotlib).
"""

from __future__ import annotations

import json
import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.animation import AbstractMovieWriter, FFMpegWriter, PillowWriter
from matplotlib.patches import Polygon
from matplotlib.transforms import Affine2D, Transform

from safeil_sumo.core import bspline
from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.core.geometry import ego_to_world, rectangle_corners
from safeil_sumo.roads.road import NetworkError, Road, load_road
from safeil_sumo.sim.vehicle import VehicleParams

# the view, in metres along / across the lane at the ego's front bumper: the plan reaches
# ~4.5 s x 30 m/s ahead, so most of the window is ahead of the ego
VIEW_BEHIND_M = 30.0
VIEW_AHEAD_M = 130.0
VIEW_HALF_WIDTH_M = 20.0
SPLINE_SAMPLES = 60
FIGSIZE_IN = (9.0, 4.6)  # at DEFAULT_DPI: 720 x 368 px (even, as H.264 needs)
DEFAULT_DPI = 80
DEFAULT_FPS = 10.0
FORMATS = (".mp4", ".gif")
REQUIRED_COLUMNS = ("t", "front_x", "front_y", "yaw", "v", "leader_x", "leader_y", "leader_v",
                    "gap")
PLAN_COLUMNS = ("plan_x", "plan_y", "plan_yaw", "cp1_x", "cp1_y", "cp2_x", "cp2_y", "cp3_x",
                "cp3_y")
FLAGS = (("collision", "COLLISION"), ("lane_departure", "LANE DEPARTURE"),
         ("ttc_flag", "TTC FLAG"))


class AnimateError(ValueError):
    """Bad input for an animation (missing folder, unknown scenario, no encoder): one line."""


# ------------------------------------------------------------------------------ the inputs


@dataclass(frozen=True)
class Episode:
    """What the frames of one scenario (or one replay policy) are drawn from."""

    name: str  # "s0003", or the policy of a replay folder
    log: pd.DataFrame  # its rows of steps.parquet, sorted by t
    road: Road  # world coordinates, like the log
    length_m: float  # vehicle box [m] (the leader is drawn the same size)
    width_m: float
    human: pd.DataFrame | None = None  # replay folders: t [s], x, y [m], v [m/s], gap [m]


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise AnimateError(f"{path}: unreadable ({exc})") from exc
    return data if isinstance(data, dict) else {}


def _pick(kind: str, wanted: str | None, available: list[str]) -> str:
    if wanted is None:
        return available[0]
    if wanted not in available:
        shown = ", ".join(available[:20]) + (", ..." if len(available) > 20 else "")
        raise AnimateError(f"unknown {kind} {wanted!r}; available: {shown}")
    return wanted


def _run_road(run_dir: Path, config: dict) -> Road:
    """The road of a ``run`` folder: the manifest's net (along its route, if any), or the
    catalogue net of the same name when the folder was moved to another machine."""
    from safeil_sumo.roads.catalogue import resolve_net

    net = config.get("net")
    if not net:
        raise AnimateError(f"{run_dir}: manifest.json names no net (config.net)")
    path = Path(net)
    if not path.is_file():
        try:
            path = resolve_net(path.name.removesuffix(".net.xml"))
        except NetworkError as exc:
            raise AnimateError(f"{run_dir}: network {net} not found") from exc
    route = config.get("route") or []
    if config.get("stretch_km"):  # run --net n74 --from-km/--to-km
        from safeil_sumo.roads.n74 import stretch_road

        from_km, to_km = config["stretch_km"]
        return stretch_road(from_km, to_km, net_dir=path.parent)
    if route:  # a run along several edges (run --route)
        from safeil_sumo.roads.route import load_route

        return load_route(path, route)
    return load_road(path)


def _replay_road(run_dir: Path) -> Road:
    from safeil_sumo.roads import recorded_road as rr

    nets = sorted((run_dir / "net").glob("*.net.xml"))
    if len(nets) != 1:
        raise AnimateError(f"{run_dir}/net: expected one .net.xml, found {len(nets)}")
    return rr.load_replay_road(nets[0])[0]


def load_episode(run_dir: Path | str, scenario: str | None = None,
                 policy: str | None = None) -> Episode:
    """One scenario of a ``run`` results folder, or one policy of a ``replay`` folder (default:
    the first). Raises :class:`AnimateError` with a one-line reason for bad input."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise AnimateError(f"results folder not found: {run_dir}")
    steps_path = run_dir / "steps.parquet"
    if not steps_path.is_file():
        raise AnimateError(f"{run_dir}: no steps.parquet (not a results folder of "
                           "safeil_sumo.run or safeil_sumo.replay)")
    try:
        steps = pd.read_parquet(steps_path)
    except Exception as exc:  # pyarrow raises several kinds for a damaged file
        raise AnimateError(f"{steps_path}: unreadable ({exc})") from exc
    missing = [c for c in REQUIRED_COLUMNS if c not in steps]
    if missing:
        raise AnimateError(f"{steps_path}: missing columns {', '.join(missing)}")
    manifest = _read_json(run_dir / "manifest.json") if (run_dir / "manifest.json").is_file() \
        else {}
    config = manifest.get("config", {}) if isinstance(manifest.get("config"), dict) else {}
    human = None
    try:
        if "policy" in steps:  # a replay folder: one log per policy, the maneuver's own road
            if scenario is not None:
                raise AnimateError(f"{run_dir} is a replay folder: choose with --policy, not "
                                   "--scenario")
            name = _pick("policy", policy, list(dict.fromkeys(steps["policy"].astype(str))))
            log = steps[steps["policy"].astype(str) == name]
            road = _replay_road(run_dir)
            human = _human(run_dir / "human.parquet")
        else:
            if policy is not None:
                raise AnimateError(f"{run_dir} is a run folder (one policy): choose with "
                                   "--scenario, not --policy")
            names = (list(dict.fromkeys(steps["scenario"].astype(str))) if "scenario" in steps
                     else ["run"])
            name = _pick("scenario", scenario, names)
            log = steps[steps["scenario"].astype(str) == name] if "scenario" in steps else steps
            road = _run_road(run_dir, config)
    except NetworkError as exc:
        raise AnimateError(str(exc)) from exc
    vehicle = config.get("vehicle")
    if not isinstance(vehicle, dict):
        vehicle = {}
    default = VehicleParams()
    log = log.sort_values("t", kind="stable").reset_index(drop=True)
    if len(log) == 0:
        raise AnimateError(f"{steps_path}: {name} has no rows")
    return Episode(name, log, road, float(vehicle.get("length_m", default.length_m)),
                   float(vehicle.get("width_m", default.width_m)), human)


def _human(path: Path) -> pd.DataFrame | None:
    """The recorded human of a replay folder (front bumper; the replay's local frame is the
    SUMO net's, so the log's world coordinates)."""
    if not path.is_file():
        return None
    h = pd.read_parquet(path)
    if not {"t", "x", "y"} <= set(h.columns):
        return None
    return pd.DataFrame({col: h[col].to_numpy(float) if col in h else np.nan
                         for col in ("t", "x", "y", "v", "gap")})


# -------------------------------------------------------------------------- pure geometry


def plan_world(row: pd.Series | dict, samples: int = SPLINE_SAMPLES
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """The plan tracked at a log row in world coordinates: the spline ``(samples, 2)`` and its 4
    control points ``(4, 2)`` [m] (the first is the plan pose), or None where the row has no
    plan (NaN plan columns, or a log without them)."""
    try:
        values = np.array([float(row[c]) for c in PLAN_COLUMNS])
    except KeyError:
        return None
    if not np.all(np.isfinite(values)):
        return None
    origin, yaw = values[:2], values[2]
    free = values[3:].reshape(3, 2)  # cp1..cp3 in the plan pose's frame (x forward, y left)
    local = bspline.evaluate(free, np.linspace(0.0, 1.0, samples))
    return (ego_to_world(local, origin, yaw),
            ego_to_world(bspline.full_coefficients(free), origin, yaw))


def ego_box(front_x: float, front_y: float, yaw: float, length_m: float, width_m: float
            ) -> np.ndarray:
    """Corners ``(4, 2)`` [m] of the ego's body from its front-bumper centre and heading."""
    centre = np.array([front_x, front_y]) - 0.5 * length_m * np.array([math.cos(yaw),
                                                                       math.sin(yaw)])
    return rectangle_corners(centre, yaw, length_m, width_m)


def leader_box(rear_x: float, rear_y: float, yaw: float, length_m: float, width_m: float
               ) -> np.ndarray:
    """Corners ``(4, 2)`` [m] of the leader's body from its rear-bumper centre and heading."""
    centre = np.array([rear_x, rear_y]) + 0.5 * length_m * np.array([math.cos(yaw),
                                                                      math.sin(yaw)])
    return rectangle_corners(centre, yaw, length_m, width_m)


def frame_times(t: np.ndarray, every_s: float, start_s: float | None = None,
                end_s: float | None = None) -> np.ndarray:
    """Frame times [s]: every ``every_s`` from the first logged time (or ``start_s``) up to the
    last (or ``end_s``), both ends included when the span is a whole number of steps, so a
    duration D gives ``floor(D / every_s) + 1`` frames."""
    if not every_s > 0:
        raise AnimateError("the time between frames must be > 0 s")
    t0 = float(t[0]) if start_s is None else max(float(start_s), float(t[0]))
    t1 = float(t[-1]) if end_s is None else min(float(end_s), float(t[-1]))
    if t1 < t0:
        raise AnimateError(f"no logged time in [{start_s}, {end_s}] s (the log spans "
                           f"{t[0]:g} to {t[-1]:g} s)")
    n = math.floor((t1 - t0) / every_s + 1e-9) + 1
    return t0 + every_s * np.arange(n)


def frame_rows(t: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Index of the last log row at or before each frame time (the state shown then)."""
    i = np.searchsorted(np.asarray(t, float), np.asarray(times, float) + 1e-9, side="right") - 1
    return np.clip(i, 0, len(t) - 1)


# ------------------------------------------------------------------------------ the frames


class FrameDrawer:
    """A figure for one episode whose artists :meth:`draw` moves to a log row.

    The static parts (road, speed/gap curves) are drawn once; world artists share one view
    transform (world -> ego-following frame) that each frame resets, so a frame redraws only
    what moves.
    """

    def __init__(self, ep: Episode, dpi: float = DEFAULT_DPI) -> None:
        self.ep = ep
        log = ep.log
        self.t = log["t"].to_numpy(float)
        self.lane = ep.road.lanes[ep.road.ego_lane].centre
        flags = np.zeros(len(log), bool)
        for col, _ in FLAGS:
            if col in log:
                flags |= log[col].to_numpy(bool)
        self.first_flag = int(np.argmax(flags)) if flags.any() else None

        self.fig = plt.figure(figsize=FIGSIZE_IN, dpi=dpi)
        grid = self.fig.add_gridspec(2, 1, height_ratios=(2.2, 1.0), left=0.07, right=0.93,
                                     top=0.90, bottom=0.10, hspace=0.35)
        top = self.fig.add_subplot(grid[0])
        strip = self.fig.add_subplot(grid[1])
        self.top, self.strip = top, strip
        self.view = Affine2D()
        world = self.view + top.transData
        self._draw_road(world)
        self._add_movers(world)
        self._draw_strip()

    def _draw_road(self, world: Transform) -> None:
        """The road in the top view: paved area between the outer lines, solid edges, dashed
        lines between lanes."""
        top = self.top
        lanes = self.ep.road.lanes
        outline = np.concatenate([lanes[-1].left_boundary.points,
                                  lanes[0].right_boundary.points[::-1]])
        top.add_patch(Polygon(outline, closed=True, facecolor="0.88", edgecolor="none",
                              transform=world, zorder=0))
        for b in (lanes[-1].left_boundary, lanes[0].right_boundary):
            top.plot(b.points[:, 0], b.points[:, 1], color="0.25", lw=1.2, transform=world)
        for lane in lanes[1:]:
            top.plot(lane.right_boundary.points[:, 0], lane.right_boundary.points[:, 1],
                     color="white", lw=1.2, ls=(0, (6, 6)), transform=world)

    def _add_movers(self, world: Transform) -> None:
        """The top view's artists that :meth:`draw` moves (trail, plan, control points, ego,
        leader, the recorded human), its axes and the figure's time stamp and flag text."""
        top, ep = self.top, self.ep
        (self.trail,) = top.plot([], [], color="tab:blue", lw=0.8, alpha=0.5, transform=world)
        (self.spline,) = top.plot([], [], color="tab:orange", lw=1.6, transform=world,
                                  label="plan (B-spline)", zorder=4)
        (self.cps,) = top.plot([], [], "o:", color="tab:red", ms=3.5, lw=0.8, transform=world,
                               label="control points", zorder=5)
        self.ego = Polygon(np.zeros((4, 2)), closed=True, facecolor="tab:blue",
                           edgecolor="k", lw=0.6, transform=world, zorder=3, label="ego")
        self.leader = Polygon(np.zeros((4, 2)), closed=True, facecolor="0.35",
                              edgecolor="k", lw=0.6, transform=world, zorder=3, label="leader")
        top.add_patch(self.ego)
        top.add_patch(self.leader)
        self.human = None
        if ep.human is not None:
            (self.human,) = top.plot([], [], "x", color="k", ms=6, mew=1.5, transform=world,
                                     label="human (recorded)", zorder=6)
        top.set_xlim(-VIEW_BEHIND_M, VIEW_AHEAD_M)
        top.set_ylim(-VIEW_HALF_WIDTH_M, VIEW_HALF_WIDTH_M)
        top.set_aspect("equal", adjustable="box")
        top.set_xlabel("along the lane from the ego's front bumper [m]", fontsize=7, labelpad=1)
        top.set_ylabel("lateral [m]", fontsize=7)
        top.tick_params(labelsize=7)
        top.legend(loc="upper left", fontsize=6.5, ncol=5, framealpha=0.8)
        self.stamp = self.fig.text(0.07, 0.955, "", fontsize=9, family="monospace",
                                   va="center")
        self.flag_text = self.fig.text(0.93, 0.955, "", fontsize=9, weight="bold", ha="right",
                                       va="center")

    def _draw_strip(self) -> None:
        """The strip below: speeds on the left axis, gap on the right one, a cursor at the
        frame's time."""
        strip, ep, log = self.strip, self.ep, self.ep.log
        strip.plot(self.t, log["v"], color="tab:blue", lw=1.0, label="ego v")
        strip.plot(self.t, log["leader_v"], color="0.35", lw=1.0, ls="--", label="leader v")
        gap_ax = strip.twinx()
        gap = log["gap"].to_numpy(float)
        gap_ax.plot(self.t, np.where(np.isfinite(gap), gap, np.nan), color="tab:green", lw=1.0,
                    label="gap")
        if ep.human is not None:
            strip.plot(ep.human["t"], ep.human["v"], color="k", lw=0.8, ls=":",
                       label="human v")
            gap_ax.plot(ep.human["t"], ep.human["gap"], color="tab:green", lw=0.8, ls=":")
        if self.first_flag is not None:
            strip.axvline(self.t[self.first_flag], color="tab:red", lw=0.8, ls=":")
        self.cursor = strip.axvline(self.t[0], color="k", lw=1.0)
        strip.set_xlim(self.t[0], self.t[-1])
        strip.set_xlabel("time [s]", fontsize=7, labelpad=1)
        strip.set_ylabel("speed [m/s]", fontsize=7)
        gap_ax.set_ylabel("gap [m]", fontsize=7, color="tab:green")
        for ax, min_span in ((strip, 2.0), (gap_ax, 4.0)):
            ax.tick_params(labelsize=7)
            _at_least(ax, min_span)
        strip.grid(alpha=0.3)
        lines = strip.get_lines()[:2] + gap_ax.get_lines()[:1]
        strip.legend(lines, [str(ln.get_label()) for ln in lines], loc="lower left", fontsize=6.5,
                     ncol=3, framealpha=0.8)

    def _heading_at(self, x: float, y: float) -> float:
        """The ego lane's heading [rad] nearest a point: the view turns with the road, not with
        the ego's yaw, so the ego's heading error stays visible."""
        s, _ = self.lane.project(np.array([x, y]))
        return float(self.lane.point_at(s)[1])

    def draw(self, i: int) -> None:
        """Move every artist to log row ``i``."""
        ep, row = self.ep, self.ep.log.iloc[i]
        fx, fy, yaw = float(row["front_x"]), float(row["front_y"]), float(row["yaw"])
        self.view.clear().translate(-fx, -fy).rotate(-self._heading_at(fx, fy))
        self.ego.set_xy(ego_box(fx, fy, yaw, ep.length_m, ep.width_m))
        lx, ly = float(row["leader_x"]), float(row["leader_y"])
        if math.isfinite(lx) and math.isfinite(ly):
            self.leader.set_xy(leader_box(lx, ly, self._heading_at(lx, ly), ep.length_m,
                                          ep.width_m))
            self.leader.set_visible(True)
        else:
            self.leader.set_visible(False)
        plan = plan_world(row)
        if plan is None:
            self.spline.set_data([], [])
            self.cps.set_data([], [])
        else:
            self.spline.set_data(plan[0][:, 0], plan[0][:, 1])
            self.cps.set_data(plan[1][:, 0], plan[1][:, 1])
        self.trail.set_data(ep.log["front_x"].to_numpy()[: i + 1],
                            ep.log["front_y"].to_numpy()[: i + 1])
        t = float(row["t"])
        if self.human is not None and ep.human is not None:  # the line is drawn with a human
            h = ep.human
            k = int(np.clip(np.searchsorted(h["t"].to_numpy(float), t + 1e-9, side="right") - 1,
                            0, len(h) - 1))
            self.human.set_data([h["x"].iloc[k]], [h["y"].iloc[k]])
        self.cursor.set_xdata([t, t])

        gap = float(row["gap"])
        ttc = float(row["ttc"]) if "ttc" in row else math.nan
        d = float(row["d"]) if "d" in row else math.nan
        self.stamp.set_text(
            f"{ep.name}  t={t:5.1f} s  v={float(row['v']):4.1f} m/s  "
            + (f"gap={gap:5.1f} m  " if math.isfinite(gap) else "gap=  -    ")
            + (f"TTC={ttc:4.1f} s  " if math.isfinite(ttc) else "TTC=  -   ")
            + (f"d={d:+.2f} m" if math.isfinite(d) else ""))
        now = [label for col, label in FLAGS if col in row and bool(row[col])]
        if now:
            self.flag_text.set_text(" ".join(now))
            self.flag_text.set_color("tab:red")
        elif self.first_flag is not None and i >= self.first_flag:
            self.flag_text.set_text(f"flagged at {self.t[self.first_flag]:.1f} s")
            self.flag_text.set_color("tab:red")
        else:
            self.flag_text.set_text("no flag")
            self.flag_text.set_color("tab:green")

    def close(self) -> None:
        plt.close(self.fig)


def _at_least(ax: plt.Axes, span: float) -> None:
    """Give a y axis at least ``span`` (a constant speed would otherwise show float noise)."""
    lo, hi = ax.get_ylim()
    if hi - lo < span:
        mid = 0.5 * (lo + hi)
        ax.set_ylim(mid - 0.5 * span, mid + 0.5 * span)
    ax.ticklabel_format(axis="y", useOffset=False)


def draw_frame(ep: Episode, time_s: float, dpi: float = DEFAULT_DPI) -> plt.Figure:
    """A still: the figure of the frame at ``time_s`` [s] (close it with ``plt.close``)."""
    drawer = FrameDrawer(ep, dpi)
    drawer.draw(int(frame_rows(drawer.t, np.array([time_s]))[0]))
    return drawer.fig


# ------------------------------------------------------------------------------ the writers


def find_ffmpeg() -> str | None:
    """An ffmpeg executable: on PATH, else the one bundled by the optional ``imageio-ffmpeg``."""
    found = shutil.which("ffmpeg")
    if found:
        return found
    try:
        import imageio_ffmpeg
    except ImportError:
        return None
    try:
        return imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError:  # the wheel is installed but holds no binary for this platform
        return None


class _GifWriter(PillowWriter):
    """Pillow's GIF writer keeping each frame as 1 byte per pixel (a GIF's palette) instead of
    4, so a long scenario's frames fit in memory. Octree quantisation keeps the small red
    control points that median cut merges into the orange spline."""

    def grab_frame(self, **savefig_kwargs: Any) -> None:
        super().grab_frame(**savefig_kwargs)
        from PIL import Image

        frames = getattr(self, "_frames", None)  # matplotlib's own list (>= 3.1); else as is
        if frames:
            frames[-1] = frames[-1].convert("RGB").quantize(colors=64,
                                                            method=Image.Quantize.FASTOCTREE)


def default_output(run_dir: Path, name: str) -> Path:
    """``RUN_DIR/animation_<name>.mp4`` where an ffmpeg is found, else ``.gif``."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name)
    return Path(run_dir) / f"animation_{safe}{'.mp4' if find_ffmpeg() else '.gif'}"


def animate(run_dir: Path | str, scenario: str | None = None, policy: str | None = None,
            out: Path | str | None = None, fps: float = DEFAULT_FPS, every_s: float | None = None,
            start_s: float | None = None, end_s: float | None = None,
            dpi: float = DEFAULT_DPI) -> Path:
    """Write the animation of one scenario (run folder) or one policy (replay folder).

    ``fps``: frames per second of the video; ``every_s``: simulated seconds between frames
    (default ``1 / fps``: real time); ``start_s`` / ``end_s``: a time window of the log [s].
    ``out``: a ``.mp4`` or ``.gif`` path (default :func:`default_output`). Returns the path
    written; raises :class:`AnimateError` for bad input or an MP4 without an ffmpeg.
    """
    if not (math.isfinite(fps) and fps > 0):
        raise AnimateError("--fps must be > 0")
    ep = load_episode(run_dir, scenario, policy)
    out = Path(out) if out is not None else default_output(Path(run_dir), ep.name)
    if out.suffix.lower() not in FORMATS:
        raise AnimateError(f"--out {out}: the format follows the suffix, .mp4 or .gif")
    ffmpeg = find_ffmpeg() if out.suffix.lower() == ".mp4" else None
    if out.suffix.lower() == ".mp4" and ffmpeg is None:
        raise AnimateError("an .mp4 needs ffmpeg (on PATH, or pip install "
                           "'safeil-sumo[video]'); write a .gif instead")
    times = frame_times(ep.log["t"].to_numpy(float), every_s or 1.0 / fps, start_s, end_s)
    rows = frame_rows(ep.log["t"].to_numpy(float), times)
    out.parent.mkdir(parents=True, exist_ok=True)
    drawer = FrameDrawer(ep, dpi)
    try:
        # a temporary sibling ending in the same suffix (ffmpeg picks the container by it), so
        # an interrupted animation leaves no half-written file
        with atomic_path(out) as tmp, \
                matplotlib.rc_context({"animation.ffmpeg_path": ffmpeg or "ffmpeg"}):
            # matplotlib's stubs type fps as int; its writers take any positive frame rate
            writer: AbstractMovieWriter
            if ffmpeg:
                writer = FFMpegWriter(fps=fps, codec="h264", bitrate=-1)  # type: ignore[arg-type]
            else:
                writer = _GifWriter(fps=fps)  # type: ignore[arg-type]
            # GIF frame delays are whole centiseconds: fps above 50 play slower than asked
            with writer.saving(drawer.fig, str(tmp), dpi):
                for i in rows:
                    drawer.draw(int(i))
                    writer.grab_frame()
    finally:
        drawer.close()
    return out
