"""The lateral removal fixpoint (safeil_sumo.learn.lateral_invariant): by hand on toy successor
relations, against a brute-force fixpoint, and its grid, containment and membership logic."""

from __future__ import annotations

import itertools

import numpy as np

from safeil_sumo.learn import lateral_invariant as lv
from safeil_sumo.learn import loop_lateral as ll


def succ_of(shape, boxes):
    """:class:`Successors` from ``{cell: {level: (lo, hi)}}`` (cells and bounds as index
    tuples; cells not named map to themselves in their own level)."""
    levels, cells = shape[0], shape[1:]
    n, dims = int(np.prod(shape)), len(cells)
    check = np.zeros((n, levels), bool)
    lo, hi = np.zeros((n, levels, dims), int), np.zeros((n, levels, dims), int)
    for flat, cell in enumerate(itertools.product(*(range(s) for s in shape))):
        for lev, (a, b) in boxes.get(cell, {cell[0]: (cell[1:], cell[1:])}).items():
            check[flat, lev] = True
            lo[flat, lev], hi[flat, lev] = a, b
    return lv.Successors(check, lo, hi)


def test_fixpoint_by_hand_on_a_line() -> None:
    # 5 cells: 0 -> {0, 1}, 1 -> {0, 1}, 2 -> {1..3}, 3 -> {4}, 4 -> {4, 5}: 5 is off the grid
    shape = (1, 5)
    boxes = {(0, 0): {0: ((0,), (1,))}, (0, 1): {0: ((0,), (1,))}, (0, 2): {0: ((1,), (3,))},
             (0, 3): {0: ((4,), (4,))}, (0, 4): {0: ((4,), (5,))}}
    alive, rounds = lv.removal_fixpoint(np.ones(5, bool), succ_of(shape, boxes), shape)
    # 4 leaves the grid (removed before any round), then 3 (round 1), then 2 (round 2)
    assert alive.tolist() == [True, True, False, False, False]
    assert rounds == 2


def test_fixpoint_by_hand_on_two_levels_of_a_plane() -> None:
    # levels x 3 x 2 cells; (1, 2, 1) is not claimed; (0, 1, 1) can land in level 1's
    # [1..2] x [0..1] (which holds it); (0, 0, 0) in level 0's [0..1] x [0..1] (which holds
    # (0, 1, 1)) and in level 1's (0, 0); (1, 0, 0) in level 0's (0, 0) only, and a level-1
    # box off the grid that is not checked; every other cell maps to itself
    shape = (2, 3, 2)
    boxes = {(0, 1, 1): {1: ((1, 0), (2, 1))},
             (0, 0, 0): {0: ((0, 0), (1, 1)), 1: ((0, 0), (0, 0))},
             (1, 0, 0): {0: ((0, 0), (0, 0))}}
    succ = succ_of(shape, boxes)
    succ.lo[np.ravel_multi_index((1, 0, 0), shape), 1] = (-1, 0)  # unchecked: ignored
    keep = np.ones(12, bool)
    keep[np.ravel_multi_index((1, 2, 1), shape)] = False
    alive, rounds = lv.removal_fixpoint(keep, succ, shape)
    # (0, 1, 1) goes in round 1, (0, 0, 0) in round 2, (1, 0, 0) in round 3
    gone = {np.ravel_multi_index(c, shape) for c in ((1, 2, 1), (0, 1, 1), (0, 0, 0), (1, 0, 0))}
    assert alive.tolist() == [i not in gone for i in range(12)]
    assert rounds == 3


def test_fixpoint_removes_a_cell_leaving_the_grid_in_a_checked_level_only() -> None:
    shape = (2, 2)
    boxes = {(0, 0): {1: ((0,), (2,))}}  # leaves level 1's grid (2 cells) upwards
    alive, rounds = lv.removal_fixpoint(np.ones(4, bool), succ_of(shape, boxes), shape)
    assert alive.tolist() == [False, True, True, True] and rounds == 0


def brute_force(keep, succ, shape):
    """The greatest fixpoint by plain loops over cells and the cells of their boxes."""
    alive = keep.copy()
    cells = np.array(shape[1:])
    changed = True
    while changed:
        changed = False
        for c in np.flatnonzero(alive):
            for lev in np.flatnonzero(succ.check[c]):
                lo, hi = succ.lo[c, lev], succ.hi[c, lev]
                if (lo < 0).any() or (hi >= cells).any():
                    bad = True
                else:
                    bad = any(not alive[np.ravel_multi_index((lev, *t), shape)]
                              for t in itertools.product(*(range(a, b + 1)
                                                           for a, b in zip(lo, hi, strict=True))))
                if bad:
                    alive[c] = False
                    changed = True
                    break
    return alive


def test_fixpoint_equals_brute_force_on_random_relations() -> None:
    shape = (2, 4, 3, 3)
    n = int(np.prod(shape))
    idx = np.indices(shape).reshape(len(shape), -1).T
    mid = (np.array(shape[1:]) - 1) / 2
    pull = np.sign(mid - idx[:, 1:]).astype(int)[:, None, :]
    rounds = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        check = rng.random((n, 2)) < 0.6
        check[np.arange(n), idx[:, 0]] = True
        # boxes about the cell moved one step towards the grid's middle, a few pushed off
        push = rng.integers(-1, 2, (n, 2, 3)) * (rng.random((n, 2, 3)) < 0.03)
        centre = idx[:, None, 1:] + pull + push
        lo = centre - (rng.random((n, 2, 3)) < 0.15)
        hi = centre + (rng.random((n, 2, 3)) < 0.15)
        succ = lv.Successors(check, lo, hi)
        keep = rng.random(n) < 0.99
        alive, r = lv.removal_fixpoint(keep, succ, shape)
        assert alive.tolist() == brute_force(keep, succ, shape).tolist(), seed
        rounds.append((r, int(alive.sum())))
    # not all trivial: several relations need rounds and keep part of the grid
    assert sum(1 for r, k in rounds if r >= 2 and 0 < k < n) >= 3, rounds


def small_grid() -> lv.LateralGrid:
    return lv.LateralGrid((30.0, 31.0, 32.0), (0.002, 0.002), (0.2, 0.01, 0.02, 0.2, 0.1),
                          (2, 2, 1, 1, 1))


def image_at(grid, lo, hi, v):
    """An image of every cell of ``grid``: the lateral box ``lo..hi`` ``(5,)``, speeds ``v``."""
    n = int(np.prod(grid.shape))
    fin = {f: (np.full(n, lo[d]), np.full(n, hi[d])) for d, f in enumerate(lv.LATERAL)}
    fin["v"] = (np.full(n, v[0]), np.full(n, v[1]))
    final = ll.LateralBox(*(fin[f] for f in ll.STATE), (np.zeros(n), np.zeros(n)))
    return ll.LateralImage(final, fin["e_y"], np.ones(n, bool), (np.zeros(n), np.zeros(n)))


def test_successors_on_the_float_edges() -> None:
    grid = small_grid()  # 2 e_y cells per speed cell, edges -0.2, 0, 0.2; 1 cell elsewhere
    edges = grid.edges()
    mid = np.array([(e[0] + e[1]) / 2 for e in edges[0]])  # cell 0's centre
    e_y = edges[0][0]
    assert e_y[1] == 0.0
    cases = [((0.0, 0.05), (1, 1)),  # from the inner edge up: the upper cell alone
             ((-0.05, 0.0), (0, 0)),  # up to the inner edge: the lower cell alone
             ((0.0, 0.0), (1, 1)),  # on the inner edge: one cell holding it
             ((-0.1, 0.1), (0, 1)),
             ((0.2, 0.2), (1, 1)),  # the top edge: the top cell
             ((-0.2, 0.2), (0, 1)),
             ((-0.21, 0.0), (-1, 0)),  # below the grid
             ((0.1, 0.21), (1, 2))]  # above it
    for (a, b), want in cases:
        lo, hi = mid.copy(), mid.copy()
        lo[0], hi[0] = a, b
        succ = lv.successors(grid, image_at(grid, lo, hi, (30.5, 31.0)))
        assert succ.check.all()  # closed speed cells: 31.0 lies in both
        assert (succ.lo[:, 0, 0] == want[0]).all() and (succ.hi[:, 0, 0] == want[1]).all(), (
            a, b)
        for d in range(1, 5):  # the centre of the one cell
            assert (succ.lo[:, 0, d] == 0).all() and (succ.hi[:, 0, d] == 0).all()
    succ = lv.successors(grid, image_at(grid, mid, mid, (31.5, 33.0)))
    assert not succ.check[:, 0].any() and succ.check[:, 1].all()
    # speed cell 1's grid is centred on its own steady turn: the same point is elsewhere in it
    assert not np.array_equal(grid.centres()[0], grid.centres()[1])


def test_boxes_tile_the_grid_and_contains_finds_them() -> None:
    grid = small_grid()
    boxes = grid.boxes()
    assert len(boxes) == int(np.prod(grid.shape)) == 8
    rng = np.random.default_rng(3)
    alive = np.array([True, False, True, True, False, True, False, False])
    lat = np.stack([getattr(boxes, f)[0] + rng.random(8) * (getattr(boxes, f)[1]
                                                             - getattr(boxes, f)[0])
                    for f in lv.LATERAL], 1)
    v = boxes.v[0] + 0.5
    assert lv.contains(grid, alive, v, lat).tolist() == alive.tolist()
    # a point on the edge between a kept and a removed cell is in S
    edge = lat[1].copy()
    edge[0] = grid.edges()[0][0][1]
    assert lv.contains(grid, alive, np.array([30.5]), edge[None])[0]
    # off the grid, or at a speed outside it: not in S
    far = lat[0].copy()
    far[0] = 5.0
    assert not lv.contains(grid, alive, np.array([30.5, 35.0]), np.stack([far, lat[0]])).any()


def test_successors_hold_the_real_loop() -> None:
    """What the fixpoint rests on, against the loop's own code: from random states of every
    claimed cell of a small grid (random leaders, lane widths, PI integrals, tyre forces,
    overriding braking; seed 5), the camera fit, planner, pure pursuit and plant
    (tests/fixtures_lateral.py) end the period in a speed cell the successors check, inside the
    cells they name there (or beyond the grid's speeds, where the claim stops)."""
    from fixtures_lateral import random_loop_inputs, real_lateral_period

    from safeil_sumo.learn.inference import load_policy
    from safeil_sumo.planners.registry import shipped_checkpoint

    policy = load_policy(shipped_checkpoint("safeil"))
    grid = lv.LateralGrid((30.0, 31.0, 32.0), (0.0015, 0.0025), (0.45, 0.03, 0.015, 0.1, 0.04),
                          (3, 3, 1, 1, 1))
    a, parts = ll.LateralAssumptions(), ll.LateralParts()
    boxes = grid.boxes()
    image = ll.period_bound(policy, boxes, a, parts)
    succ = lv.successors(grid, image)
    assert image.ok.mean() >= 0.5
    # not vacuous: some images lie inside the grid in e_y and in e_psi (none in delta, v_y, r:
    # one cell there, and no image of a cell fits in it)
    inside = (succ.lo >= 0) & (succ.hi < np.array(grid.cells))
    assert (inside[succ.check][:, :2].mean(0) >= 0.2).all()
    rng = np.random.default_rng(5)
    idx = np.repeat(np.flatnonzero(image.ok), 100)
    n = len(idx)
    fields = (*ll.STATE, "curvature")
    draw = {f: getattr(boxes, f)[0][idx] + rng.random(n) * (getattr(boxes, f)[1][idx]
                                                             - getattr(boxes, f)[0][idx])
            for f in fields}
    width, lead, gap, accel, integral, force = random_loop_inputs(rng, n, a, parts)
    final, _, _ = real_lateral_period(policy, *(draw[f] for f in fields), width, lead, gap,
                                      integral, force, accel, a, parts)
    lateral = np.stack(final[:5], 1)
    v = final[5]
    ve = np.array(grid.speed_edges_mps)
    edges = grid.edges()
    inside_speeds = 0
    for j in range(grid.shape[0]):
        at = (v >= ve[j]) & (v <= ve[j + 1])
        inside_speeds += int(at.sum())
        assert succ.check[idx[at], j].all(), "a final speed in a speed cell not checked"
        for d in range(5):
            lo, hi = succ.lo[idx[at], j, d], succ.hi[idx[at], j, d]
            e = edges[j][d]
            below = np.where(lo >= 0, e[np.clip(lo, 0, len(e) - 1)], -np.inf)
            above = np.where(hi < len(e) - 1, e[np.clip(hi + 1, 0, len(e) - 1)], np.inf)
            x = lateral[at, d]
            assert np.all((below <= x) & (x <= above)), f"{lv.LATERAL[d]} outside its cells"
    assert n >= 600 and inside_speeds >= n // 2  # not vacuous
