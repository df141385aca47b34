"""A forward-invariant set of the lateral closed loop: the greatest fixpoint of cell removal.

A grid over ``(v, e_y, e_psi, delta, v_y, r)`` for one lane-curvature slice ``[k_lo, k_hi]``
(:class:`LateralGrid`): speed cells ``[v_j, v_j+1]`` and, per speed cell, a lateral grid of
closed boxes centred on the steady turn at the cell's mid speed and the slice's mid curvature
(:func:`steady_turn`). Each cell's one-period image is :func:`.loop_lateral.period_bound`'s
(every leader, lane width, tyre force; the lane a circle of one curvature in the slice). Then
every cell is removed whose image is not claimed, leaves the lateral grid, or meets a removed
cell in any speed cell the image's speed range overlaps, until nothing changes
(:func:`removal_fixpoint`). The cells left, ``S``, satisfy: every state of ``S`` whose lane is a
circle (or a straight) of curvature in the slice is, one decision later, in ``S`` again or at
a speed outside ``[v_0, v_n]``. So along any run on such a lane, every decision state is in
``S`` as long as the speed at every decision so far stayed in ``[v_0, v_n]``: the claim stops
at the speed range's edges (the longitudinal loop, the leader, decides the speed; a leader
that brakes the ego below ``v_0`` ends it). The curvature is constant along the run (one circle,
as ``curved500``): a lane whose curvature changes within the camera's view is outside
:func:`period_bound`'s own assumption, so it is not covered, even between slices.

Containment is exact on the float edges: a cell is the closed box of its float edges, the
image's index range is found by comparisons against those edges (``np.searchsorted``), and the
cells in it must all be kept (a sufficient condition for the image to lie in their union).

Pure numpy; no SUMO, no torch.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from safeil_sumo.learn import loop_lateral as ll
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.sim.vehicle import VehicleParams

LATERAL = ("e_y", "e_psi", "steer", "vy", "r")  # the lateral grid's coordinates, in order
_SIDES: tuple[Literal["left", "right"], ...] = ("left", "right")
_ASSUME = ll.LateralAssumptions()
_PARTS = ll.LateralParts()


def steady_turn(v_mps: np.ndarray, curvature_1pm: np.ndarray,
                vehicle: VehicleParams = VehicleParams()) -> tuple[np.ndarray, ...]:
    """Road-wheel angle [rad], lateral speed [m/s] and yaw rate [rad/s], arrays ``(N,)``, of the
    linear single track turning steadily with ``curvature_1pm`` at speed ``v_mps`` (``(N,)``)."""
    p = vehicle
    m, lf, lr, iz = p.mass_kg, p.lf_m, p.lr_m, p.yaw_inertia_kgm2
    cf, cr = p.cornering_stiffness_front_npr, p.cornering_stiffness_rear_npr
    v = np.asarray(v_mps, float)
    r = v * np.asarray(curvature_1pm, float)
    a11, a12 = -(cf + cr) / (m * v), -(lf * cf - lr * cr) / (m * v) - v
    a21, a22 = -(lf * cf - lr * cr) / (iz * v), -(lf * lf * cf + lr * lr * cr) / (iz * v)
    b1, b2 = cf / m, lf * cf / iz
    vy = (a22 * b1 - a12 * b2) * r / (a11 * b2 - a21 * b1)
    delta = -(a11 * vy + a12 * r) / b1
    return delta, vy, r


@dataclass(frozen=True)
class LateralGrid:
    """The cells of one curvature slice. ``speed_edges_mps`` ``(nv + 1,)`` [m/s];
    ``curvature_1pm`` the slice [1/m]; ``half_range`` the lateral grid's half extent about its
    centre per :data:`LATERAL` coordinate [m, rad, rad, m/s, rad/s]; ``cells`` the cells per
    coordinate. The lateral grid of speed cell ``j`` is centred on ``(0, 0, delta, v_y, r)`` of
    :func:`steady_turn` at the cell's mid speed and the slice's mid curvature."""

    speed_edges_mps: tuple[float, ...]
    curvature_1pm: tuple[float, float]
    half_range: tuple[float, float, float, float, float]
    cells: tuple[int, int, int, int, int]
    vehicle: VehicleParams = VehicleParams()

    def __post_init__(self) -> None:
        # floats: integer speed arrays would make period_bound's working arrays integers
        object.__setattr__(self, "speed_edges_mps", tuple(float(v) for v in self.speed_edges_mps))
        object.__setattr__(self, "curvature_1pm", tuple(float(k) for k in self.curvature_1pm))
        object.__setattr__(self, "half_range", tuple(float(h) for h in self.half_range))
        if len(self.speed_edges_mps) < 2 or np.any(np.diff(self.speed_edges_mps) <= 0.0):
            raise ValueError("speed_edges_mps must increase")
        if self.curvature_1pm[0] > self.curvature_1pm[1]:
            raise ValueError("curvature_1pm must be (lo, hi)")
        if min(self.cells) < 1 or min(self.half_range) <= 0.0:
            raise ValueError("cells >= 1 and half_range > 0")

    @property
    def shape(self) -> tuple[int, ...]:
        """``(nv, *cells)``."""
        return (len(self.speed_edges_mps) - 1, *self.cells)

    def centres(self) -> np.ndarray:
        """The lateral grids' centres ``(nv, 5)``."""
        ve = np.asarray(self.speed_edges_mps)
        v_mid = (ve[:-1] + ve[1:]) / 2
        k_mid = np.full_like(v_mid, sum(self.curvature_1pm) / 2)
        d, vy, r = steady_turn(v_mid, k_mid, self.vehicle)
        zero = np.zeros_like(v_mid)
        return np.stack([zero, zero, d, vy, r], 1)

    def edges(self) -> list[list[np.ndarray]]:
        """The float edges ``edges[j][d]`` ``(cells[d] + 1,)`` of speed cell j's coordinate d:
        the cells are exactly the closed boxes between them."""
        c = self.centres()
        return [[c[j, d] + np.linspace(-h, h, n + 1)
                 for d, (h, n) in enumerate(zip(self.half_range, self.cells, strict=True))]
                for j in range(self.shape[0])]

    def boxes(self) -> ll.LateralBox:
        """Every cell as a :class:`.loop_lateral.LateralBox`, ``N = prod(shape)`` rows in
        C order of ``shape`` (speed cell first)."""
        idx = np.indices(self.shape).reshape(len(self.shape), -1)
        ve = np.asarray(self.speed_edges_mps)
        edges = self.edges()
        lat = []
        for d in range(5):
            lo = np.array([edges[j][d][i] for j, i in zip(idx[0], idx[d + 1], strict=True)])
            hi = np.array([edges[j][d][i + 1] for j, i in zip(idx[0], idx[d + 1], strict=True)])
            lat.append((lo, hi))
        n = idx.shape[1]
        k = (np.full(n, self.curvature_1pm[0]), np.full(n, self.curvature_1pm[1]))
        return ll.LateralBox(lat[0], lat[1], lat[2], lat[3], lat[4], (ve[idx[0]], ve[idx[0] + 1]),
                             k)


@dataclass(frozen=True)
class Successors:
    """Where the N cells' images can land: ``check (N, nv)`` the speed cells each image's
    speed range overlaps (closed; speed cells outside the grid's range are not checked: the
    claim stops there), ``lo, hi (N, nv, D)`` the index range of the lateral cells the image
    can meet in each (inclusive; ``lo < 0`` or ``hi >= cells``: it leaves the grid)."""

    check: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def successors(grid: LateralGrid, image: ll.LateralImage) -> Successors:
    """The :class:`Successors` of the grid's cells from their images (rows as
    :meth:`LateralGrid.boxes`)."""
    ve = np.asarray(grid.speed_edges_mps)
    v_lo, v_hi = image.final.v
    check = (ve[None, :-1] <= v_hi[:, None]) & (ve[None, 1:] >= v_lo[:, None])
    n, nv = check.shape
    lo, hi = np.empty((n, nv, 5), int), np.empty((n, nv, 5), int)
    edges = grid.edges()
    for j in range(nv):
        for d, f in enumerate(LATERAL):
            a, b = getattr(image.final, f)
            e = edges[j][d]
            lo[:, j, d] = _first_cell(e, a)
            hi[:, j, d] = np.maximum(np.searchsorted(e, b, "left") - 1, lo[:, j, d])
    return Successors(check, lo, hi)


def _first_cell(edges: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Per value of ``a`` ``(N,)``, a cell of the closed cells between ``edges`` ``(n + 1,)``
    that holds it: the last whose lower edge is ``<= a`` (the top cell for the top edge), -1
    below the grid. With ``hi``, the last cell whose lower edge is ``< b`` (``e[hi + 1] >= b``)
    and at least ``lo`` (``a = b`` on an inner edge), cells ``lo..hi`` cover ``[a, b]``."""
    return np.minimum(np.searchsorted(edges, a, "right") - 1, len(edges) - 2)


def removal_fixpoint(keep: np.ndarray, succ: Successors, shape: tuple[int, ...]
                     ) -> tuple[np.ndarray, int]:
    """The greatest set of cells ``S`` within ``keep`` ``(N,)`` (N = prod(shape), C order)
    whose every checked successor box lies inside the grid and in ``S``: cells are removed,
    all at once per round, until none is. ``shape`` is ``(levels, *cells)``: each successor
    box is in one level (``succ.check``). Returns ``S`` ``(N,)`` and the rounds that removed
    something."""
    levels, cells = shape[0], shape[1:]
    dims = len(cells)
    if succ.lo.shape != (len(keep), levels, dims):
        raise ValueError(f"successors of shape {succ.lo.shape}, grid {shape}")
    ncell = np.array(cells)
    inside = (succ.lo >= 0).all(-1) & (succ.hi < ncell).all(-1)
    alive = keep & ~(succ.check & ~inside).any(1)
    rows, lev = np.nonzero(succ.check & inside)  # every (cell, level) box to look in
    lo, hi = succ.lo[rows, lev], succ.hi[rows, lev]
    corners = list(itertools.product((0, 1), repeat=dims))
    rounds = 0
    while True:
        dead = (~alive).reshape(shape).astype(np.int64)
        # prefix sums over the lateral axes, a zero row in front: P[l, i..] = dead in [0, i)
        p = np.zeros((levels, *(ncell + 1)), np.int64)
        p[(slice(None), *(slice(1, None),) * dims)] = dead
        for ax in range(1, dims + 1):
            p = np.cumsum(p, axis=ax)
        count = np.zeros(len(rows), np.int64)
        for corner in corners:  # inclusion-exclusion over the box's 2^dims corners
            idx = tuple(np.where(c, hi[:, d] + 1, lo[:, d]) for d, c in enumerate(corner))
            sign = 1 if (dims - sum(corner)) % 2 == 0 else -1
            count += sign * p[(lev, *idx)]
        bad = np.zeros(len(keep), bool)
        bad[rows[count > 0]] = True
        drop = alive & bad
        if not drop.any():
            return alive, rounds
        alive = alive & ~drop
        rounds += 1


@dataclass(frozen=True)
class InvariantResult:
    """A slice's fixpoint: ``alive (N,)`` the cells of ``S`` (rows as
    :meth:`LateralGrid.boxes`), ``claimed (N,)`` the cells whose image is claimed and inside
    the grid, the ``image`` and :class:`Successors`, the removal ``rounds`` and the wall times
    [s] of the images and of the fixpoint."""

    grid: LateralGrid
    alive: np.ndarray
    claimed: np.ndarray
    image: ll.LateralImage
    succ: Successors
    rounds: int
    image_s: float
    fixpoint_s: float

    def extent(self) -> dict[str, tuple[float, float]]:
        """The hull of ``S`` per coordinate (``v`` and :data:`LATERAL`) and of the front
        bumper's offset at every physics step from it (``e_y_path``), ``(nan, nan)`` if empty."""
        boxes = self.grid.boxes()
        out: dict[str, tuple[float, float]] = {}
        for f in ("v", *LATERAL):
            lo, hi = getattr(boxes, f)
            out[f] = ((float(lo[self.alive].min()), float(hi[self.alive].max()))
                      if self.alive.any() else (np.nan, np.nan))
        lo, hi = self.image.e_y_path
        out["e_y_path"] = ((float(lo[self.alive].min()), float(hi[self.alive].max()))
                           if self.alive.any() else (np.nan, np.nan))
        return out


def contains(grid: LateralGrid, alive: np.ndarray, v_mps: np.ndarray,
             lateral: np.ndarray) -> np.ndarray:
    """Whether states lie in ``S``: speeds ``(M,)`` [m/s], lateral states ``(M, 5)`` (as
    :data:`LATERAL`); a state is in ``S`` if some kept cell (a closed box) holds it."""
    ve = np.asarray(grid.speed_edges_mps)
    edges = grid.edges()
    alive_g = alive.reshape(grid.shape)
    ncell = np.array(grid.cells)
    out = np.zeros(len(v_mps), bool)
    for j in range(grid.shape[0]):
        at = (v_mps >= ve[j]) & (v_mps <= ve[j + 1])
        # per coordinate the cells holding x: the last whose lower edge is <= x ("right") and
        # the first whose upper edge is >= x ("left"); they differ only on an edge
        for sides in itertools.product(_SIDES, repeat=5):
            idx = np.stack([np.searchsorted(edges[j][d], lateral[:, d], side) - 1
                            for d, side in enumerate(sides)], 1)
            ok = at & (idx >= 0).all(1) & (idx < ncell).all(1)
            safe = np.where(ok[:, None], idx, 0)
            out |= ok & alive_g[(np.full(len(v_mps), j), *safe.T)]
    return out


def invariant_slice(policy: MLPPolicy, grid: LateralGrid,
                    a: ll.LateralAssumptions = _ASSUME, parts: ll.LateralParts = _PARTS,
                    chunk: int = 512
                    ) -> InvariantResult:
    """The images of the grid's cells and their removal fixpoint (:class:`InvariantResult`)."""
    if parts.vehicle != grid.vehicle:
        raise ValueError("the grid's steady turns and the bound must use one vehicle")
    t0 = time.perf_counter()
    image = ll.period_bound(policy, grid.boxes(), a, parts, chunk)
    t1 = time.perf_counter()
    succ = successors(grid, image)
    alive, rounds = removal_fixpoint(image.ok, succ, grid.shape)
    ncell = np.array(grid.cells)
    inside = ((succ.lo >= 0).all(-1) & (succ.hi < ncell).all(-1)) | ~succ.check
    claimed = image.ok & inside.all(1)
    return InvariantResult(grid, alive, claimed, image, succ, rounds, t1 - t0,
                           time.perf_counter() - t1)
