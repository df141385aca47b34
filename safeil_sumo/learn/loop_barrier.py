"""A barrier certificate of the longitudinal closed loop: a gap floor whose change along every
decision period is bounded from the period's increments.

The barrier is ``h(x) = g - phi(v, v_l, f)`` on the loop's state ``x = (g, v, v_l, f)``
(:mod:`.loop_invariant`). The floor ``phi`` is the multilinear interpolant of its values at the
nodes of the grid's ``(v, v_l, f)`` axes: continuous, and inside each lattice cell its slope
along an axis lies between the cell's smallest and largest edge difference
(:func:`slope_bounds`). The candidate set is ``S = {x : phi(v, v_l, f) <= g <= g_top}`` with
``phi >= margin`` (so S lies in the safe set), ``g_top`` the grid's top gap (151 m).

The check (:func:`check`), per grid cell ``C`` with states of S (``h_hi(C) >= 0``):
:func:`.loop_invariant.box_period` bounds, with the same interval code as the one-period image,
the CHANGE ``(Dg, Dv, Dv_l, Df)`` of every state of C over one period (step by step from each
step's own change, so that the cell's width is not subtracted from itself), the image box, and
the gap's lowest point within the period. By the mean value theorem along the segment from
``x`` to ``x+``, whose coordinate along each axis stays between the cell and the end of the
hull of C and its image it moves towards (:meth:`_Slopes.rise`),

    h(x+) - h(x) >= Dg_lo - sum_k max(slope_k * D_k)        (slope_k over those cells)

and C passes when this is at least ``-max(h_lo(C), 0)`` (so every state of C with ``h >= 0``
keeps ``h >= 0``) and the gap stays at or above the margin at every physics step (from the
lowest gap of S in C). The cell width enters only through the commands' spread over C and
the slopes' variation over the hull: not, as in :func:`.loop_invariant.gap_floor`, as a rounding
of the image to whole cells each period. If every cell passes, S is forward invariant for every
leader, sensing error, integral and guard estimate the one-period bound covers, until the gap
first exceeds ``g_top`` or the ego's speed the grid's top (50 m/s): the certified domain's
edges, where the claim stops (:data:`SPEED_OFF_GRID` marks the columns where the latter can
happen).

:func:`synthesize` searches a floor that passes: it starts from the recoverable envelope's
lower boundary (:func:`.loop_invariant.recoverable_gap`) and lifts the nodes of every failing
column by its deficit (spread to the neighbours with a bounded slope), until the check passes
or a budget ends. The search is not part of the proof; the check of its result is. A floor at
the ceiling everywhere passes vacuously: S empty.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from safeil_sumo.learn import loop_invariant as li
from safeil_sumo.learn.inference import MLPPolicy

SLOPE_WINDOW = 4  # slope maxima over hulls of up to twice this many lattice cells per axis
# why a cell fails
OK, INCREMENT, GAP_IN_PERIOD, SPEED_OFF_GRID, HULL_TOO_LONG = range(5)
REASONS = ("holds", "h can fall below 0", "the gap can drop below the margin within the period",
           "holds, or the speed leaves the grid (the domain's top)",
           "the period's hull spans too many lattice cells")


def lattice_axes(grid: li.Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The floor's nodes: the grid's ``(v, v_l, f)`` cell edges."""
    _, ev, el, ef = grid.axes()
    return ev, el, ef


def interpolate(phi: np.ndarray, grid: li.Grid, v: np.ndarray, vl: np.ndarray,
                f: np.ndarray) -> np.ndarray:
    """The floor ``phi`` (node values ``(n_v + 1, n_l + 1, n_f + 1)``) at states ``(N,)``,
    multilinear (coordinates clipped to the lattice)."""
    idx, frac = [], []
    for edges, x in zip(lattice_axes(grid), (v, vl, f), strict=True):
        w = edges[1] - edges[0]
        t = (np.clip(np.asarray(x, float), edges[0], edges[-1]) - edges[0]) / w
        i = np.minimum(np.floor(t).astype(np.int64), len(edges) - 2)
        idx.append(i)
        frac.append(t - i)
    out = np.zeros(len(idx[0]))
    for corner in range(8):
        bits = [corner >> k & 1 for k in range(3)]
        weight = np.prod([fr if b else 1.0 - fr for fr, b in zip(frac, bits, strict=True)], 0)
        out += weight * phi[idx[0] + bits[0], idx[1] + bits[1], idx[2] + bits[2]]
    return out


def _corners(phi: np.ndarray) -> list[np.ndarray]:
    """The 8 node arrays ``(n_v, n_l, n_f)`` at each column's corners."""
    return [phi[a:phi.shape[0] - 1 + a, b:phi.shape[1] - 1 + b, c:phi.shape[2] - 1 + c]
            for a in (0, 1) for b in (0, 1) for c in (0, 1)]


def floor_bounds(phi: np.ndarray) -> li.Interval:
    """The floor's smallest and largest value over each column ``(n_v, n_l, n_f)``: a
    multilinear interpolant's extremes over a cell are at its corners."""
    corners = np.stack(_corners(phi))
    return corners.min(0), corners.max(0)


def slope_bounds(phi: np.ndarray, grid: li.Grid) -> list[li.Interval]:
    """Per axis ``(v, v_l, f)``: the smallest and largest slope of the floor over each column
    (the slope along an axis is the multilinear interpolant of the cell's edge differences
    along it, so their extremes bound it)."""
    out = []
    for axis, edges in enumerate(lattice_axes(grid)):
        diff = np.diff(phi, axis=axis) / (edges[1] - edges[0])
        lo, hi = diff, diff
        for other in (k for k in range(3) if k != axis):
            n = diff.shape[other]
            first, second = range(n - 1), range(1, n)
            lo = np.minimum(lo.take(first, other), lo.take(second, other))
            hi = np.maximum(hi.take(first, other), hi.take(second, other))
        out.append((lo, hi))
    return out


@dataclass
class Increments:
    """Per grid cell ``(n_g, n_v, n_l, n_f)``, from :func:`.loop_invariant.box_period`: the
    bounds ``lo, hi (4, ...)`` of each state's change ``(g, v, v_l, f)`` over one period, the
    lattice cells ``first, last (3, ...)`` the hull of the cell and its image meets along
    ``(v, v_l, f)``, the gap's lowest change at any physics step of the period ``dip`` [m], and
    whether the speed can leave the grid. They do not depend on the floor."""

    lo: np.ndarray
    hi: np.ndarray
    first: np.ndarray
    last: np.ndarray
    dip: np.ndarray
    off_grid: np.ndarray
    seconds: float


def increments(policy: MLPPolicy, grid: li.Grid, time_gap: tuple[float, float],
               a: li.LoopAssumptions, parts: li.LoopParts, rows_per_chunk: int = 10,
               progress: Callable[[int], object] | None = None) -> Increments:
    """:class:`Increments` of every cell, ``rows_per_chunk`` gap rows at a time (the force
    cells of a ``(g, v, v_l)`` box share its plan bounds)."""
    start = time.perf_counter()
    shape = grid.shape
    eg, ev, el, ef = grid.axes()
    lo, hi = np.empty((4, *shape)), np.empty((4, *shape))
    first, last = np.empty((3, *shape), np.int16), np.empty((3, *shape), np.int16)
    dip, off_grid = np.empty(shape), np.empty(shape, bool)
    f_box = (ef[None, :-1], ef[None, 1:])
    for r0 in range(0, shape[0], rows_per_chunk):
        rows = slice(r0, min(r0 + rows_per_chunk, shape[0]))
        index = np.meshgrid(np.arange(rows.start, rows.stop), np.arange(shape[1]),
                            np.arange(shape[2]), indexing="ij")
        box = [(e[i].ravel(), e[i + 1].ravel()) for e, i in zip((eg, ev, el), index,
                                                                 strict=True)]
        image, change, g_min = li.box_period(policy, box[0], box[1], box[2], f_box, time_gap, a,
                                             parts)
        cut = (rows.stop - rows.start, *shape[1:])
        for k in range(4):
            lo[k, rows], hi[k, rows] = (x.reshape(cut) for x in change[k])
        dip[rows] = (g_min - box[0][0][:, None]).reshape(cut)
        own = [(np.broadcast_to(x[0][:, None], g_min.shape), np.broadcast_to(x[1][:, None],
                                                                             g_min.shape))
               for x in box[1:]] + [(np.broadcast_to(f_box[0], g_min.shape),
                                     np.broadcast_to(f_box[1], g_min.shape))]
        for k, edges in enumerate(lattice_axes(grid)):
            hull = (np.minimum(own[k][0], image[k + 1][0]), np.maximum(own[k][1],
                                                                       image[k + 1][1]))
            i0, i1, out = li._index_range(edges, hull)
            first[k, rows], last[k, rows] = i0.reshape(cut), i1.reshape(cut)
            if k == 0:  # the ego's speed above the grid (the force cannot pass its limits)
                off_grid[rows] = out.reshape(cut)
        if progress is not None:
            progress(rows.stop - rows.start)
    return Increments(lo, hi, first, last, dip, off_grid, time.perf_counter() - start)


@dataclass
class BarrierCheck:
    """:func:`check`'s verdict per column ``(n_v, n_l, n_f)``: the worst cell's deficit [m]
    (> 0 fails; ``-inf``: the column has no state of S), why it fails (:data:`REASONS`) and in
    which gap row."""

    deficit: np.ndarray
    reason: np.ndarray
    row: np.ndarray
    speed_exits: np.ndarray  # bool: some state of S in the column can leave the speed axis' top

    @property
    def passed(self) -> bool:
        return not bool(np.any(self.deficit > 0.0))


@dataclass(frozen=True)
class _Slopes:
    """Window maxima (:func:`.loop_invariant._window_maxima`) of the floor's largest slopes and
    of its negated smallest slopes, per axis."""

    hi: tuple[np.ndarray, ...]
    neg_lo: tuple[np.ndarray, ...]

    @classmethod
    def of(cls, phi: np.ndarray, grid: li.Grid) -> _Slopes:
        bounds = slope_bounds(phi, grid)
        return cls(tuple(li._window_maxima(hi, SLOPE_WINDOW) for _, hi in bounds),
                   tuple(li._window_maxima(-lo, SLOPE_WINDOW) for lo, _ in bounds))

    def over(self, first: np.ndarray, last: np.ndarray) -> tuple[list[li.Interval], np.ndarray]:
        """Slope bounds per axis over index boxes ``(3, M)``, and where a box is longer than
        the windows reach (cut to them there: such a box must fail)."""
        first, last = first.astype(np.int64), last.astype(np.int64)
        limit = 2 * np.asarray(self.hi[0].shape[:3])[:, None]
        too_long = np.any(last - first + 1 > limit, axis=0)
        last = np.minimum(last, first + limit - 1)
        return [(-li._range_max(self.neg_lo[k], first, last),
                 li._range_max(self.hi[k], first, last)) for k in range(3)], too_long

    def rise(self, first: np.ndarray, last: np.ndarray, own: np.ndarray, lo: np.ndarray,
             hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Upper bound of ``phi(x+) - phi(x)`` for changes ``(v, v_l, f)`` in ``[lo, hi]
        (3, M)`` from cells ``own (3, M)`` whose hull with their image is ``[first, last]``:
        per axis, a rise along it lies between the cell and the hull's end it moves to, so
        the slopes there bound it (the other axes anywhere in the hull). Also the size of the
        terms (for the float margin) and where a hull is too long."""
        total, size = np.zeros(lo.shape[1]), np.zeros(lo.shape[1])
        too_long = np.zeros(lo.shape[1], bool)
        for k in range(3):
            parts = []
            for side, d in ((1, (np.maximum(lo[k], 0.0), np.maximum(hi[k], 0.0))),
                            (-1, (np.minimum(lo[k], 0.0), np.minimum(hi[k], 0.0)))):
                f_k, l_k = first.copy(), last.copy()
                if side > 0:
                    f_k[k] = own[k]
                else:
                    l_k[k] = own[k]
                slopes, long_k = self.over(f_k, l_k)
                too_long |= long_k
                prods = np.stack([slopes[k][0] * d[0], slopes[k][0] * d[1],
                                  slopes[k][1] * d[0], slopes[k][1] * d[1]])
                parts.append(prods.max(0))
                size = np.maximum(size, np.abs(prods).max(0))
            up, down = parts
            total += np.where(lo[k] >= 0.0, up, np.where(hi[k] <= 0.0, down,
                                                         np.maximum(up, down)))
        return total, size, too_long


def _cell_deficits(inc: Increments, rows: slice, phi_b: li.Interval, slopes: _Slopes,
                   edges: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Deficit [m] (> 0 fails, -inf: no state of S) and reason of the cells of gap rows
    ``rows``: every state with ``h >= 0`` must keep ``h >= 0`` (``h(x+) - h(x) >= -h(x)``,
    bounded by ``-max(h_lo, 0)``), the gap the margin within the period, the speed the grid."""
    cut = (rows.stop - rows.start, *phi_b[0].shape)
    h_lo = edges[rows, None, None, None] - phi_b[1]
    h_hi = edges[rows.start + 1:rows.stop + 1, None, None, None] - phi_b[0]
    act = np.flatnonzero((h_hi >= 0.0).ravel())
    sl = (slice(None), rows)
    lo, hi = (x[sl].reshape(4, -1)[:, act] for x in (inc.lo, inc.hi))
    own = np.stack([i.ravel()[act] for i in np.indices(cut)[1:]])
    rise, size, too_long = slopes.rise(inc.first[sl].reshape(3, -1)[:, act],
                                       inc.last[sl].reshape(3, -1)[:, act], own, lo[1:], hi[1:])
    # h(x+) - h(x) >= dg_lo - rise, less a float margin of the terms' size
    dh_lo = lo[0] - rise - li.FLOAT_MARGIN * (1.0 + 3.0 * size + np.abs(lo[0]))
    deficit = -np.maximum(h_lo.ravel()[act], 0.0) - dh_lo
    reason = np.where(deficit > 0.0, INCREMENT, OK)
    # the gap's lowest point: from the lowest gap of S in the cell
    start = np.maximum(edges[rows, None, None, None], phi_b[0]).ravel()[act]
    short = margin - (start + inc.dip[rows].ravel()[act])
    reason = np.where((short > 0.0) & (short > deficit), GAP_IN_PERIOD, reason)
    deficit = np.maximum(deficit, short)
    # a state whose speed leaves the grid leaves the certified domain (as one whose gap passes
    # its top): it is not a failure, and the slopes of its segment's part inside count
    reason = np.where(inc.off_grid[rows].ravel()[act] & (reason == OK), SPEED_OFF_GRID, reason)
    reason = np.where(too_long, HULL_TOO_LONG, reason)
    deficit = np.where(too_long, np.inf, deficit)
    out, why_out = np.full(int(np.prod(cut)), -np.inf), np.zeros(int(np.prod(cut)), np.int8)
    out[act], why_out[act] = deficit, reason
    return out.reshape(cut), why_out.reshape(cut)


def cell_deficits(inc: Increments, phi: np.ndarray, grid: li.Grid, a: li.LoopAssumptions
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Every cell's deficit [m] and reason ``(n_g, n_v, n_l, n_f)``, as :func:`check` finds
    them (for a small grid: one chunk)."""
    edges = grid.axes()[0]
    return _cell_deficits(inc, slice(0, grid.shape[0]), floor_bounds(phi),
                          _Slopes.of(phi, grid), edges, a.margin_m)


def check(inc: Increments, phi: np.ndarray, grid: li.Grid, a: li.LoopAssumptions,
          rows_per_chunk: int = 10) -> BarrierCheck:
    """The barrier check of the floor ``phi`` over every cell with states of S (module
    docstring), from the cells' :class:`Increments`."""
    if np.any(phi < a.margin_m):
        raise ValueError("the floor must lie at or above the margin (S inside the safe set)")
    phi_b = floor_bounds(phi)
    slopes = _Slopes.of(phi, grid)
    edges = grid.axes()[0]
    n_g = grid.shape[0]
    worst = np.full(phi_b[0].shape, -np.inf)
    reason = np.zeros(phi_b[0].shape, np.int8)
    row = np.full(phi_b[0].shape, -1, np.int16)
    exits = np.zeros(phi_b[0].shape, bool)
    for r0 in range(0, n_g, rows_per_chunk):
        rows = slice(r0, min(r0 + rows_per_chunk, n_g))
        deficit, why = _cell_deficits(inc, rows, phi_b, slopes, edges, a.margin_m)
        exits |= np.any(why == SPEED_OFF_GRID, axis=0)
        k = deficit.argmax(0)
        top = np.take_along_axis(deficit, k[None], 0)[0]
        better = top > worst
        worst = np.where(better, top, worst)
        reason = np.where(better, np.take_along_axis(why, k[None], 0)[0], reason)
        row = np.where(better, (k + r0).astype(np.int16), row)
    return BarrierCheck(worst, reason, row, exits)


# ------------------------------------------------------------------ a floor that passes


def recoverable_floor(grid: li.Grid, a: li.LoopAssumptions, parts: li.LoopParts) -> np.ndarray:
    """The recoverable envelope's lower boundary (:func:`.loop_invariant.recoverable_gap`) at
    the lattice's nodes, at least the margin: where the search starts (a floor much below it
    cannot hold against a leader braking at the stated limit)."""
    ev, el, ef = lattice_axes(grid)
    v, vl, f = np.meshgrid(ev, el, ef, indexing="ij")
    gap = li.recoverable_gap(v.ravel(), vl.ravel(), f.ravel(), a, parts.vehicle)
    return np.maximum(gap, a.margin_m).reshape(v.shape)


def _raise_nodes(phi: np.ndarray, deficit: np.ndarray, step_m: float, ceiling: float,
                 grid: li.Grid, lift_slope: tuple[float, float, float]) -> np.ndarray:
    """Each failing column's 8 nodes lifted by its deficit and ``step_m``, the lifts spread to
    the neighbours no steeper than ``lift_slope`` [m per unit of (v, v_l, f)] (the smallest
    such majorant: a sharp lift's own slope would fail the next check), capped at
    ``ceiling``."""
    lift = np.where(deficit > 0.0, np.minimum(deficit + step_m, ceiling), 0.0)
    node = np.zeros_like(phi)
    n_v, n_l, n_f = lift.shape
    for dv in (0, 1):
        for dl in (0, 1):
            for df in (0, 1):
                view = node[dv:dv + n_v, dl:dl + n_l, df:df + n_f]
                np.maximum(view, lift, out=view)
    for axis, edges in enumerate(lattice_axes(grid)):
        drop = lift_slope[axis] * (edges[1] - edges[0])
        view = np.moveaxis(node, axis, 0)  # a view: the loops below write into node
        for i in range(1, len(view)):  # forwards, then backwards: one axis' distance transform
            np.maximum(view[i], view[i - 1] - drop, out=view[i])
        for i in range(len(view) - 2, -1, -1):
            np.maximum(view[i], view[i + 1] - drop, out=view[i])
    return np.minimum(phi + node, ceiling)


@dataclass
class Synthesis:
    """:func:`synthesize`'s result: the last floor, its check, per round the failing columns,
    the largest finite deficit [m] and the seconds since the start, and the cells'
    increments."""

    phi: np.ndarray
    result: BarrierCheck
    rounds: list[tuple[int, float, float]]
    increments: Increments


def synthesize(policy: MLPPolicy, grid: li.Grid, time_gap: tuple[float, float],
               a: li.LoopAssumptions, parts: li.LoopParts, max_rounds: int = 200,
               budget_s: float = 600.0, step_m: float = 0.1,
               lift_slope: tuple[float, float, float] = (4.0, 4.0, 3.0),
               progress: Callable[[int, BarrierCheck], object] | None = None,
               inc: Increments | None = None) -> Synthesis:
    """Raise the floor from the recoverable boundary until :func:`check` passes, the rounds
    run out or the budget [s] is spent (the last check's verdict is the answer either way,
    and the floor returned is the one it checked); ``inc``: the cells' increments at these
    settings, if already computed."""
    start = time.perf_counter()
    if inc is None:
        inc = increments(policy, grid, time_gap, a, parts)
    phi = recoverable_floor(grid, a, parts)
    ceiling = float(grid.axes()[0][-1]) + 1.0
    rounds: list[tuple[int, float, float]] = []
    for r in range(max_rounds):
        result = check(inc, phi, grid, a)
        fails = result.deficit > 0.0
        finite = result.deficit[fails & np.isfinite(result.deficit)]
        rounds.append((int(fails.sum()), float(finite.max()) if finite.size else 0.0,
                       time.perf_counter() - start))
        if progress is not None:
            progress(r, result)
        if result.passed or time.perf_counter() - start > budget_s or r == max_rounds - 1:
            break
        phi = _raise_nodes(phi, result.deficit, step_m, ceiling, grid, lift_slope)
    return Synthesis(phi, result, rounds, inc)


# ------------------------------------------------------------------ what it covers


def envelope_share(phi: np.ndarray, grid: li.Grid, a: li.LoopAssumptions,
                   parts: li.LoopParts, samples: int = 200_000, seed: int = 0,
                   v_max: float | None = None) -> tuple[float, float]:
    """S's share of the recoverable envelope's volume over the grid's box (speeds up to
    ``v_max`` if given): ``(v, v_l, f)`` drawn uniformly from ``seed``, the gap integrated
    exactly, ``(151 - max(phi, g_R))+ / (151 - g_R)+`` summed (S's states outside the
    envelope do not count). Returns the share and its standard error."""
    rng = np.random.default_rng(seed)
    _, ev, el, ef = grid.axes()
    v = rng.uniform(ev[0], ev[-1] if v_max is None else v_max, samples)
    vl, f = rng.uniform(el[0], el[-1], samples), rng.uniform(ef[0], ef[-1], samples)
    g_top = float(grid.axes()[0][-1])
    g_r = li.recoverable_gap(v, vl, f, a, parts.vehicle)
    env = np.maximum(g_top - g_r, 0.0)
    cert = np.maximum(g_top - np.maximum(interpolate(phi, grid, v, vl, f), g_r), 0.0)
    share = cert.sum() / env.sum()
    # the ratio estimator's standard error
    err = np.sqrt(np.mean((cert - share * env) ** 2) / samples) / env.mean()
    return float(share), float(err)
