"""Planar geometry: frames, polylines, projections and Frenet offsets — pure numpy.

Conventions used across the package:
- world frame: SUMO's network coordinates, x east, y north [m]; yaw [rad] counter-clockwise from +x.
- ego frame: origin at the ego's FRONT-bumper centre (SUMO's vehicle position), x forward, y left.
- SUMO angles are navigation degrees: 0 = north, clockwise; ``sumo = 90 - deg(yaw)``.
- signed lateral offsets ``d`` are positive to the LEFT of a polyline's direction.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap an angle [rad] into [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def yaw_to_sumo_angle(yaw: float) -> float:
    """Mathematical yaw [rad] -> SUMO navigation angle [deg] (0 = north, clockwise)."""
    # math.degrees and float % are numpy's degrees and remainder on one float (same rounding)
    return (90.0 - math.degrees(yaw)) % 360.0


def sumo_angle_to_yaw(angle_deg: float) -> float:
    """SUMO navigation angle [deg] -> mathematical yaw [rad] in [-pi, pi)."""
    return (math.radians(90.0 - angle_deg) + math.pi) % (2.0 * math.pi) - math.pi


def world_to_ego(points: np.ndarray, origin: np.ndarray, yaw: float | np.ndarray) -> np.ndarray:
    """Express world points ``(..., 2)`` in the frame at ``origin (2,)`` rotated by ``yaw`` [rad]
    (or, broadcast, in one frame per row: ``origin (..., 1, 2)``, ``yaw (..., 1)``)."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = np.asarray(points, dtype=float) - np.asarray(origin, dtype=float)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def ego_to_world(points: np.ndarray, origin: np.ndarray, yaw: float) -> np.ndarray:
    """Inverse of :func:`world_to_ego`: ego-frame points ``(..., 2)`` to world coordinates."""
    c, s = np.cos(yaw), np.sin(yaw)
    p = np.asarray(points, dtype=float)
    x = c * p[..., 0] - s * p[..., 1] + origin[0]
    y = s * p[..., 0] + c * p[..., 1] + origin[1]
    return np.stack([x, y], axis=-1)


def rectangle_corners(center: np.ndarray, yaw: float, length: float, width: float) -> np.ndarray:
    """Corners ``(4, 2)`` of a ``length`` x ``width`` [m] box centred at ``center``, heading ``yaw``.

    Order: front-left, front-right, rear-right, rear-left.
    """
    hl, hw = 0.5 * length, 0.5 * width
    local = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    return ego_to_world(local, np.asarray(center, dtype=float), yaw)


def rectangles_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test for two convex quadrilaterals given as corners ``(4, 2)``."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
        pa = a @ normals.T  # (4, 4): corner x axis
        pb = b @ normals.T
        if np.any((pa.max(axis=0) < pb.min(axis=0)) | (pb.max(axis=0) < pa.min(axis=0))):
            return False
    return True


def cumulative_length(points: np.ndarray) -> np.ndarray:
    """Arc length ``(N,)`` [m] at each vertex of a polyline ``(N, 2)``, starting at 0."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def offset_polyline(points: np.ndarray, offset: float) -> np.ndarray:
    """Shift a polyline ``(N, 2)`` sideways by ``offset`` [m] (positive = left).

    Interior vertices move along the angle bisector (miter), so straight pieces stay parallel at
    exactly ``offset`` and arcs sampled as chords map to the concentric arc's chords.
    """
    p = np.asarray(points, dtype=float)
    t = np.diff(p, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)  # left normals per segment
    vn = np.empty_like(p)
    vn[0], vn[-1] = n[0], n[-1]
    if len(p) > 2:
        m = n[:-1] + n[1:]
        m /= np.linalg.norm(m, axis=1, keepdims=True)
        cos_half = np.sum(m * n[1:], axis=1, keepdims=True)
        vn[1:-1] = m / np.maximum(cos_half, 1e-6)
    return p + offset * vn


@dataclass(frozen=True)
class Polyline:
    """An immutable polyline with precomputed arc length, for projections and sampling.

    ``points`` has shape ``(N, 2)`` [m], N >= 2, no repeated consecutive vertices.
    """

    points: np.ndarray
    s: np.ndarray = field(init=False, repr=False)  # (N,) arc length at vertices [m]
    _tangents: np.ndarray = field(init=False, repr=False)  # (N-1, 2) unit segment directions
    _seg_len: np.ndarray = field(init=False, repr=False)  # (N-1,) [m]
    _py: tuple[list[float], ...] = field(init=False, repr=False)  # plain-float copies for the per-step walk

    def __post_init__(self) -> None:
        p = np.ascontiguousarray(self.points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
            raise ValueError(f"a polyline needs shape (N>=2, 2), got {p.shape}")
        seg = np.diff(p, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        if np.any(seg_len <= 1e-9):
            raise ValueError("polyline has repeated consecutive vertices")
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "_seg_len", seg_len)
        object.__setattr__(self, "_tangents", seg / seg_len[:, None])
        object.__setattr__(self, "s", np.concatenate([[0.0], np.cumsum(seg_len)]))
        t = self._tangents
        object.__setattr__(self, "_py", (
            p[:, 0].tolist(), p[:, 1].tolist(), t[:, 0].tolist(), t[:, 1].tolist(),
            seg_len.tolist(), self.s.tolist(), np.arctan2(t[:, 1], t[:, 0]).tolist(),
        ))

    @property
    def length(self) -> float:
        """Total arc length [m]."""
        return float(self.s[-1])

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frenet coordinates of points ``(..., 2)``: arc length ``s`` and signed offset ``d``.

        Points before the start / after the end are projected on the extended first / last
        segment, so ``s`` may be negative or exceed :attr:`length` and ``d`` stays meaningful.
        """
        q = np.asarray(xy, dtype=float)
        flat = q.reshape(-1, 2)
        a = self.points[:-1]  # (M, 2)
        rel = flat[:, None, :] - a[None, :, :]  # (P, M, 2)
        along = np.einsum("pmk,mk->pm", rel, self._tangents)
        along_c = np.clip(along, 0.0, self._seg_len[None, :])
        # the end segments extend beyond the polyline's ends
        along_c[:, 0] = np.minimum(along[:, 0], self._seg_len[0])
        along_c[:, -1] = np.maximum(along[:, -1], 0.0) if len(a) > 1 else along[:, -1]
        foot = a[None, :, :] + along_c[..., None] * self._tangents[None, :, :]
        dist2 = np.sum((flat[:, None, :] - foot) ** 2, axis=2)
        best = np.argmin(dist2, axis=1)
        idx = np.arange(len(flat))
        t = self._tangents[best]
        r = rel[idx, best]
        s = self.s[best] + along_c[idx, best]
        d = t[:, 0] * r[:, 1] - t[:, 1] * r[:, 0]
        shape = q.shape[:-1]
        return s.reshape(shape), d.reshape(shape)

    def project_near(self, x: float, y: float, hint: int) -> tuple[float, float, float, int]:
        """Frenet ``(s, d)``, lane heading [rad] and segment index of ONE point, walking from
        segment ``hint`` — O(1) per call for a point that moves smoothly along the polyline
        (the closed loop's hot path; :meth:`project` is the vectorised general case).

        Same result as :meth:`project` (ends extend likewise). For a point far from where
        ``hint`` left it, pass the index from a full :meth:`project` first.
        """
        xs, ys, tx, ty, seg_len, s_at, heading = self._py
        last = len(seg_len) - 1
        i = hint if 0 <= hint <= last else min(max(hint, 0), last)
        prev = -1
        while True:  # a walk one way (a turn back stops it): at most last + 1 segments
            rx, ry = x - xs[i], y - ys[i]
            along = rx * tx[i] + ry * ty[i]
            if along >= seg_len[i] and i < last:
                step = i + 1
            elif along < 0.0 and i > 0:
                step = i - 1
            else:
                break
            if step == prev:  # outside a bend, in the gap between two segments: stop
                break
            prev, i = i, step
        # Near a vertex a point inside a bend projects into both neighbouring segments and one
        # outside into neither: like project(), keep the nearest foot (ties: the lower index).
        before = i > 0 and (along <= 0.0
                            or (x - xs[i - 1]) * tx[i - 1] + (y - ys[i - 1]) * ty[i - 1]
                            <= seg_len[i - 1])
        after = i < last and (along >= seg_len[i]
                              or (x - xs[i + 1]) * tx[i + 1] + (y - ys[i + 1]) * ty[i + 1] >= 0.0)
        if not (before or after):  # the common case: the foot is inside segment i only
            return s_at[i] + along, tx[i] * ry - ty[i] * rx, heading[i], i
        candidates = [i - 1] if before else []
        candidates += [i, i + 1] if after else [i]
        best = min(candidates, key=lambda k: self._foot(x, y, k)[0])  # first minimum
        _, along, d = self._foot(x, y, best)
        return s_at[best] + along, d, heading[best], best

    def project_along(self, xy: np.ndarray, s_start: float) -> tuple[np.ndarray, np.ndarray]:
        """Frenet ``s, d`` ``(N,)`` of the points ``(N, 2)`` of a path that runs along this
        polyline: each found by :meth:`project_near`, walking from the previous point's segment,
        the first from the segment at arc length ``s_start`` [m].

        Where the polyline passes the same place more than once (the laps of a closed course),
        :meth:`project` takes the nearest pass, which may be another lap's; this keeps the
        path's own. Elsewhere both agree.
        """
        p = np.asarray(xy, dtype=float).reshape(-1, 2)
        s, d = np.empty(len(p)), np.empty(len(p))
        hint = self.segment_index(s_start)
        for i, (x, y) in enumerate(p.tolist()):
            s[i], d[i], _, hint = self.project_near(x, y, hint)
        return s, d

    def project_near_many(self, x: np.ndarray, y: np.ndarray, hint: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`project_near` of N points ``(N,)`` from their hints ``(N,)``: the same walk
        and arithmetic on arrays; a point near a vertex (two candidate segments) is resolved
        by :meth:`project_near` itself. Returns ``s, d, heading, segment`` ``(N,)`` each."""
        return _walk_many(self._arrays(), 0, len(self._py[4]) - 1, x, y, hint,
                          lambda j, xj, yj, hj: self.project_near(xj, yj, hj))

    def _arrays(self) -> tuple[np.ndarray, ...]:
        """``_py`` as arrays (built once)."""
        arrays = self.__dict__.get("_np")
        if arrays is None:
            arrays = tuple(np.array(a) for a in self._py)
            object.__setattr__(self, "_np", arrays)
        return arrays

    def max_turn(self, length_m: float) -> float:
        """The most the polyline turns [rad] within any stretch of ``length_m`` [m] of arc
        length: the largest sum of its vertices' absolute turning angles there (cached per
        length). Within a stretch that turns less than pi, every segment, and so every chord
        between two of its points (a positive sum of its segments), points within that angle of
        every other; the extensions beyond the ends add no turn."""
        cache: dict[float, float] = self.__dict__.setdefault("_max_turn", {})
        turn = cache.get(length_m)
        if turn is None:
            heading = np.array(self._py[6])
            # each inner vertex's turn, and their running sum (at[j]: vertices before j)
            turns = np.abs((np.diff(heading) + np.pi) % (2.0 * np.pi) - np.pi)
            at = np.concatenate([[0.0], np.cumsum(turns)])
            inner = self.s[1:-1]
            # a stretch's inner vertices all lie within length_m of the first of them
            end = np.searchsorted(inner, inner + length_m, side="right")
            turn = cache[length_m] = float(np.max(at[end] - at[:-1], initial=0.0))
        return turn

    def _foot(self, x: float, y: float, i: int) -> tuple[float, float, float]:
        """``(squared distance, clipped along, d)`` of a point to segment ``i``, in
        :meth:`project`'s arithmetic (same rounding, so ties resolve alike; ends extend)."""
        xs, ys, tx, ty, seg_len, _, _ = self._py
        rx, ry = x - xs[i], y - ys[i]
        along = rx * tx[i] + ry * ty[i]
        if i > 0:
            along = max(along, 0.0)
        if i < len(seg_len) - 1:
            along = min(along, seg_len[i])
        fx, fy = xs[i] + along * tx[i], ys[i] + along * ty[i]
        return (x - fx) ** 2 + (y - fy) ** 2, along, tx[i] * ry - ty[i] * rx

    def segment_index(self, s: float) -> int:
        """Index of the segment containing arc length ``s`` (clipped to the ends)."""
        return int(np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self._seg_len) - 1))

    def point_at(self, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Position ``(..., 2)`` and heading [rad] at arc length ``s``; extrapolates linearly."""
        s_arr = np.asarray(s, dtype=float)
        i = np.clip(np.searchsorted(self.s, s_arr, side="right") - 1, 0, len(self._seg_len) - 1)
        t = self._tangents[i]
        xy = self.points[i] + (s_arr - self.s[i])[..., None] * t
        return xy, np.arctan2(t[..., 1], t[..., 0])

    def xy_at(self, s: np.ndarray) -> np.ndarray:
        """Position ``(..., 2)`` of :meth:`point_at` without the heading (the camera's hot path)."""
        i = np.searchsorted(self.s, s, side="right")
        i -= 1
        np.maximum(i, 0, out=i)  # np.clip costs 4 us on small arrays; this is the same
        np.minimum(i, len(self._seg_len) - 1, out=i)
        along = s - self.s.take(i)
        return self.points.take(i, axis=0) + along[..., None] * self._tangents.take(i, axis=0)

    def resample(self, spacing: float) -> Polyline:
        """A polyline through points every ``spacing`` [m] along this one (ends kept)."""
        n = max(int(np.ceil(self.length / spacing)), 1)
        xy, _ = self.point_at(np.linspace(0.0, self.length, n + 1))
        return Polyline(xy)

    def offset(self, d: float) -> Polyline:
        """The parallel polyline at lateral offset ``d`` [m] (positive = left)."""
        return Polyline(offset_polyline(self.points, d))


class PolylineStack:
    """Several polylines' segments in one set of arrays: :meth:`project_near_many` projects
    each of N points on ITS OWN polyline in one walk (the batched loop's scenarios on different
    roads), with :meth:`Polyline.project_near_many`'s arithmetic, row by row."""

    def __init__(self, lines: list[Polyline], line_of: np.ndarray) -> None:
        """``line_of`` ``(N,)``: index into ``lines`` of each row's polyline."""
        # per line: vertex arrays (x, y, s) of n + 1, segment arrays of n, padded to n + 1 (the
        # pad is never read: a walk stays within segments 0..n-1), so one offset fits both
        arrays = []
        for line in lines:
            xs, ys, tx, ty, seg_len, s_at, heading = line._arrays()
            arrays.append((xs, ys, *(np.append(a, np.nan) for a in (tx, ty, seg_len)), s_at,
                           np.append(heading, np.nan)))
        counts = np.array([len(a[0]) for a in arrays])  # vertices
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.lines, self.line_of = lines, np.asarray(line_of)
        self.arrays = tuple(np.concatenate(parts) for parts in zip(*arrays, strict=True))
        self.first = first[self.line_of]  # (N,) each row's first vertex in the stack
        self.last = counts[self.line_of] - 2  # (N,) each row's last segment, on its own line

    def project_near_many(self, x: np.ndarray, y: np.ndarray, hint: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``s, d, heading, segment`` ``(N,)`` of each point on its polyline (segments are
        each polyline's own indices; ``hint`` likewise)."""
        lines, line_of = self.lines, self.line_of
        return _walk_many(self.arrays, self.first, self.last, x, y, hint,
                          lambda j, xj, yj, hj: lines[line_of[j]].project_near(xj, yj, hj))


def _walk_many(arrays: tuple[np.ndarray, ...], first: np.ndarray | int, last: np.ndarray | int,
               x: np.ndarray, y: np.ndarray, hint: np.ndarray,
               near: Callable[[np.intp, float, float, int], tuple[float, float, float, int]]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`Polyline.project_near_many`'s walk on segment arrays holding each row's polyline
    at segments ``first .. first + last`` (``i`` below: the index within it); ``near(j, x, y,
    hint)`` resolves row ``j`` near a vertex."""
    xs, ys, tx, ty, seg_len, s_at, heading = arrays
    i = np.clip(hint, 0, last)
    prev = np.full(len(i), -1)
    walking = np.ones(len(i), dtype=bool)
    for _ in range(int(np.max(last)) + 1):
        g = first + i
        along = (x - xs[g]) * tx[g] + (y - ys[g]) * ty[g]
        step = np.where((along >= seg_len[g]) & (i < last), i + 1,
                        np.where((along < 0.0) & (i > 0), i - 1, i))
        walking &= (step != i) & (step != prev)  # stopped: no step, or back (a bend)
        if not walking.any():
            break
        prev = np.where(walking, i, prev)
        i = np.where(walking, step, i)
    g = first + i
    along = (x - xs[g]) * tx[g] + (y - ys[g]) * ty[g]
    gm, gp = first + np.maximum(i - 1, 0), first + np.minimum(i + 1, last)
    before = (i > 0) & ((along <= 0.0)
                        | ((x - xs[gm]) * tx[gm] + (y - ys[gm]) * ty[gm] <= seg_len[gm]))
    after = (i < last) & ((along >= seg_len[g])
                          | ((x - xs[gp]) * tx[gp] + (y - ys[gp]) * ty[gp] >= 0.0))
    s = s_at[g] + along
    d = tx[g] * (y - ys[g]) - ty[g] * (x - xs[g])
    head = heading[g]
    for j in np.flatnonzero(before | after):  # near a vertex: the scalar rule, exactly
        s[j], d[j], head[j], i[j] = near(j, float(x[j]), float(y[j]), int(hint[j]))
    return s, d, head, i
