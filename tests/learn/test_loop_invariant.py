"""The closed-loop bounds (safeil_sumo.learn.loop_invariant) against the loop's own code.

The one-period image must contain every state the REAL tracker (controller.track_values),
brake guard and plant (vehicle.Plant) reach from states of a cell, under random leader
accelerations, sensing errors, PID integrals and guard estimates in the stated sets; the
pieces' monotonicity and relaxations are checked on their own.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.learn import bounds as bnd
from safeil_sumo.learn import loop_invariant as li
from safeil_sumo.learn import loop_rollout as lr
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.planners.registry import shipped_checkpoint
from safeil_sumo.sim import brake_guard as grd
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.xp import ARRAYS

FINITE = st.floats(-6.0, 6.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(FINITE, st.floats(0.0, 8.0), st.floats(0.0, 1.0))
def test_tanh_parallel_lines_hold_over_the_interval(lo: float, width: float, at: float) -> None:
    l, u = np.array([lo]), np.array([lo + width])
    s, o, d = li.tanh_parallel_lines(l, u)
    z = lo + at * width
    assert s[0] * z + o[0] - d[0] <= math.tanh(z) <= s[0] * z + o[0] + d[0]


def test_tanh_parallel_lines_are_tight_on_a_narrow_interval() -> None:
    s, _, d = li.tanh_parallel_lines(np.array([0.5]), np.array([0.52]))
    # the gap between chord and arc is at most max|tanh''| w^2 / 8, d is half of it
    assert d[0] <= 0.77 * 0.02 ** 2 / 16 + 1e-12
    assert s[0] == pytest.approx(1 - math.tanh(0.51) ** 2, rel=1e-3)


SPEED = st.floats(0.0, 45.0)


@settings(max_examples=400, deadline=None)
@given(st.floats(0.5, 150.0), st.floats(0.0, 20.0), SPEED, st.floats(0.0, 5.0), SPEED,
       st.floats(0.0, 5.0), st.floats(0.0, 10.0), st.floats(0.0, 5.0))
def test_guard_demand_is_monotone_in_each_argument(gap, dgap, v, dv, vl, dvl, b, db) -> None:
    """guard_bounds evaluates the demand at box corners: more gap or leader speed never asks
    for more braking, more ego speed or leader braking never for less."""
    guard = grd.BrakeGuard()

    def demand(g, ve, vle, bl):
        return float(grd.guard_decel(g, ve, vle, -bl, guard, ARRAYS))

    base = demand(gap, v, vl, b)
    assert demand(gap + dgap, v, vl, b) <= base + 1e-9
    assert demand(gap, v + dv, vl, b) >= base - 1e-9
    assert demand(gap, v, vl + dvl, b) <= base + 1e-9
    assert demand(gap, v, vl, min(b + db, 10.0)) >= base - 1e-9


def test_recoverable_by_hand() -> None:
    a = li.LoopAssumptions()
    # standing still: recoverable exactly when the gap is at least the margin
    assert list(li.recoverable([0.5, 1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], a)) == [False, True]
    # same speeds, already braking fully: the ego (9 m/s^2 + drag) out-brakes the leader (6)
    assert li.recoverable([2.0], [30.0], [30.0], [-9.0], a)[0]
    # 30 m/s onto a standing car 30 m ahead: 30^2 / 18 = 50 m of braking is needed
    assert not li.recoverable([30.0], [30.0], [0.0], [-9.0], a)[0]
    assert li.recoverable([60.0], [30.0], [0.0], [-9.0], a)[0]


def _one(x: float) -> np.ndarray:
    return np.array([x])


def test_command_by_hand() -> None:
    """PID 1.5 (v_ref - v) + feed-forward, the integral anywhere in +-0.1 * 5 m; the guard's
    demand caps the command from above where it is certainly on."""
    ref = li.Reference(_one(0.2), _one(0.2), _one(True), _one(False), _one(0.5), _one(0.5))
    v, dv = (_one(10.0), _one(10.0)), (_one(0.0), _one(0.0))
    parts = li.LoopParts()
    lo, hi = li._command(v, dv, ref, None, parts)
    assert (lo[0], hi[0]) == pytest.approx((0.3, 1.3))
    lo, hi = li._command(v, (_one(-0.1), _one(0.1)), ref, None, parts)  # sped up or slowed down
    assert (lo[0], hi[0]) == pytest.approx((0.15, 1.45))
    lo, hi = li._command(v, dv, ref, (_one(4.0), _one(4.0)), parts)
    assert (lo[0], hi[0]) == pytest.approx((-4.0, -4.0))
    lo, hi = li._command(v, dv, ref, (_one(0.0), _one(12.0)), parts)  # maybe off; full brake
    assert (lo[0], hi[0]) == pytest.approx((-9.0, 1.3))
    back = li.Reference(_one(0.2), _one(0.2), _one(False), _one(True), _one(0.0), _one(0.0))
    lo, hi = li._command(v, dv, back, None, parts)  # a stop: 1.5 * (0 - 10), clipped at -8
    assert (lo[0], hi[0]) == pytest.approx((-8.0, -8.0 + 0.0))


def test_reference_bounds_of_a_constant_speed_plan() -> None:
    """Raw x outputs 0 (the residual's constant speed) on the lane centre: the reference is
    the sensed speed, so the speed error is the sensing error, and no acceleration."""
    a = li.LoopAssumptions(lateral_offset_m=(0.0, 0.0), heading_error=(0.0, 0.0))
    pb = li.PlanBounds(np.zeros((1, 3)), np.zeros((1, 4, 3)), np.zeros((1, 3)), np.zeros((1, 3)),
                       np.zeros((1, 3)), _one(19.8), _one(20.2))
    for t in (0.0, 0.05, 0.29):
        r = li.reference_bounds(pb, t, 5.0, 0.93, a)
        assert (r.err_lo[0], r.err_hi[0]) == pytest.approx((-0.2, 0.2), abs=1e-6)
        assert (r.acc_lo[0], r.acc_hi[0]) == pytest.approx((0.0, 0.0), abs=1e-6)
        assert r.forwards[0] and not r.backwards[0]


@pytest.fixture(scope="module")
def safeil():
    return load_policy(shipped_checkpoint("safeil"))


@pytest.mark.parametrize("guard_on", [True, False])
def test_period_image_contains_the_real_loop(safeil, guard_on: bool) -> None:
    rng = np.random.default_rng(7)
    a = li.LoopAssumptions()
    parts = li.LoopParts() if guard_on else li.LoopParts(guard=None)
    grid = li.Grid()
    rows = slice(4, 6)
    time_gap = (1.2, 1.6)
    image, g_min = li.period_image(safeil, grid, rows, time_gap, a, parts)
    eg, ev, el, ef = grid.axes()
    n = 4000
    ig, iv, il, jf = (rng.integers(0, k, n) for k in image[0][0].shape)
    pick = lambda e, i, off=0: e[i + off] + rng.random(n) * (e[i + off + 1] - e[i + off])
    g, v, vl, f = pick(eg, ig, rows.start), pick(ev, iv), pick(el, il), pick(ef, jf)
    lane = (rng.uniform(*a.lane_width_m, n), rng.uniform(*a.lateral_offset_m, n),
            rng.uniform(*a.heading_error, n))
    sensing = (rng.uniform(-1, 1, (3, n)) * np.array([[a.speed_sensing_mps],
                                                      [a.speed_sensing_mps], [a.gap_sensing_m]]))
    leader = rng.uniform(*a.leader_accel_mps2, (n, a.steps_per_decision))
    leader[rng.random(n) < 0.3] = a.leader_accel_mps2[0]  # the extremes too
    integral = rng.uniform(-1, 1, n) * parts.controller.integral_limit_m
    a_est = -rng.uniform(0, grd.BrakeGuard().max_leader_decel_mps2, n)
    got = lr.one_period(safeil, g, v, vl, f, lane, rng.uniform(*time_gap), integral, leader,
                        sensing, a_est, guard_on, a, li.LoopParts())
    cell = (ig, iv, il, jf)
    for k, name in enumerate(("gap", "speed", "leader speed", "force")):
        lo, hi = image[k][0][cell], image[k][1][cell]
        assert np.all(got[k] >= lo) and np.all(got[k] <= hi), (
            f"{name} outside its bound in {np.sum((got[k] < lo) | (got[k] > hi))} of {n}")
    assert np.all(got[4] >= g_min[cell])
    # not vacuous: the image is a few cells wide, not the whole axis
    assert np.median(image[1][1] - image[1][0]) < 2.0
    assert np.median(image[3][1] - image[3][0]) < 5.0


def test_range_max_equals_brute_force() -> None:
    rng = np.random.default_rng(1)
    rho = rng.integers(0, 50, (20, 17, 8)).astype(np.int32)
    first = np.stack([rng.integers(0, n, 3000) for n in rho.shape])
    span = np.stack([rng.integers(1, 14, 3000) for _ in rho.shape])
    last = np.minimum(first + span - 1, np.array(rho.shape)[:, None] - 1)
    got = li._range_max(li._window_maxima(rho), first, last)
    want = [rho[a:d + 1, b:e + 1, c:f + 1].max() for a, b, c, d, e, f in zip(*first, *last, strict=True)]
    assert got.tolist() == want


def test_gap_floor_by_hand() -> None:
    """Four gap rows, two speed columns. Column 1's row 0 fails; column 0's cells fall one row
    per period into column 1 (from row 1 into row 0, ...); column 1's fall into themselves.
    Column 1's floor becomes 1; column 0's row 1 falls to row 0 < 1, so its floor becomes 2;
    its row 2 falls to row 1 >= 1 and stays."""
    shape = (4, 2, 1, 1)
    first = np.zeros((4, *shape), np.int16)
    last = np.zeros((4, *shape), np.int16)
    rows = np.arange(4)[:, None, None, None]
    first[0] = np.where(np.arange(2)[None, :, None, None] == 0, np.maximum(rows - 1, 0), rows)
    first[1] = last[1] = 1  # every image lies in column 1
    fails = np.zeros(shape, bool)
    fails[0, 1] = True
    first[0, 0, 0] = 0  # column 0's row 0 falls below the grid's first row: its own row
    rho, rounds = li.gap_floor(li.Successors(first, last, fails))
    assert rho[:, 0, 0].tolist() == [2, 1]
    assert rounds == 3


@pytest.mark.sumo
@pytest.mark.parametrize("guard_on", [True, False])
def test_sumo_runs_stay_inside_the_period_bound(safeil, guard_on: bool) -> None:
    """The model against SUMO itself: every decision-to-decision transition of a real libsumo
    run (straight lane, a leader braking at 5 m/s^2 from 29 to 8 m/s, exact sensing) lies in
    the bound of its decision state, and the lane stays in the stated lateral band."""
    from safeil_sumo import api
    from safeil_sumo.sim.loop_types import LoopConfig
    from safeil_sumo.sim.vehicle import resistance_force

    sc = api.scenario("straight", 0, 0, leader_kind="braking", leader_speed_range_mps=(28, 30),
                      brake_time_s=5.0, brake_decel_mps2=5.0, brake_to_mps=8.0,
                      initial_gap_m=40.0, ego_speed_mps=30.0)
    guard = grd.BrakeGuard() if guard_on else None
    log = api.run_scenarios([sc], safeil, LoopConfig(max_time_s=25.0, brake_guard=guard)).log
    a, params, dt = li.LoopAssumptions(), veh.VehicleParams(), 0.01
    # a log row is the state after its step: a plan made at plan_t used the row before
    decided = np.flatnonzero(np.diff(log["plan_t"].to_numpy()) != 0)
    r = decided[(decided >= 1) & (decided + 10 < len(log))]
    gap, v, vl = (log[c].to_numpy() for c in ("gap", "v", "leader_v"))

    def force(i: np.ndarray) -> np.ndarray:  # the plant's force per mass from its speed step
        return (v[i] - v[i - 1]) / dt + resistance_force(v[i - 1], params, ARRAYS) / params.mass_kg

    eps = a.lateral_coupling_mps2 + 1e-9
    f = force(r)
    parts = li.LoopParts() if guard_on else li.LoopParts(guard=None)
    time_gap = safeil.style["time_gap_s"]
    image, g_min = li.box_image(safeil, (gap[r], gap[r]), (v[r], v[r]), (vl[r], vl[r]),
                                (f - eps, f + eps), (time_gap, time_gap), a, parts)
    nxt = r + 10
    for k, x in enumerate((gap[nxt], v[nxt], vl[nxt])):
        assert np.all((x >= image[k][0]) & (x <= image[k][1])), f"state {k} left its bound"
    f_next = force(nxt)
    assert np.all((f_next >= image[3][0] - eps) & (f_next <= image[3][1] + eps))
    assert np.all(np.array([gap[i + 1:i + 11].min() for i in r]) >= g_min)
    assert len(r) > 200 and np.median(image[0][1] - image[0][0]) < 0.2  # not vacuous
    # the lateral band the bound assumes (offset, heading, lane width)
    assert log["d"].abs().max() <= a.lateral_offset_m[1]
    assert log["c1l"].abs().max() <= a.heading_error[1]
    width = log["c0l"] - log["c0r"]
    assert a.lane_width_m[0] <= width.min() and width.max() <= a.lane_width_m[1]


def test_network_input_box_by_hand() -> None:
    """Lane 3.3-3.8 m wide, the ego 0.3 m either side of its centre, slopes +-0.01: the lines'
    c0 of [1.35, 2.2] (left) and [-2.2, -1.35] (right); speeds widened by 0.2 m/s, the gap by
    0.5 m, the time-gap slice as given."""
    a = li.LoopAssumptions()
    lo, hi = li.network_input_box((np.array([10.0]), np.array([11.5])),
                                  (np.array([20.0]), np.array([20.5])),
                                  (np.array([19.0]), np.array([19.5])), (1.2, 1.6), a)
    np.testing.assert_allclose(lo[0], [1.35, -0.01, 0.0, -2.2, -0.01, 0.0, 19.8, 18.8, 9.5, 1.2],
                               atol=1e-12)
    np.testing.assert_allclose(hi[0], [2.2, 0.01, 0.0, -1.35, 0.01, 0.0, 20.7, 19.7, 12.0, 1.6],
                               atol=1e-12)


def test_index_range_by_hand() -> None:
    """Edges 0, 1, 2, 3: a box's first and last cells, clipped to the axis (int16), the top
    edge itself in the last cell, and whether the box passes the top."""
    first, last, out = li._index_range(np.array([0.0, 1.0, 2.0, 3.0]),
                                       (np.array([-0.5, 0.5, 2.9, 1.2]),
                                        np.array([0.2, 3.0, 3.5, 1.5])))
    assert first.tolist() == [0, 0, 2, 1] and last.tolist() == [0, 2, 2, 1]
    assert out.tolist() == [False, False, True, False]
    assert first.dtype == last.dtype == np.int16


def test_range_max_reaches_two_windows_and_keeps_the_type() -> None:
    """Maxima over index boxes from windows of 2 cells: exact up to 4 cells per axis, refused
    beyond; integer floors stay integers."""
    rng = np.random.default_rng(5)
    rho = rng.integers(0, 100, (6, 5, 4)).astype(np.int32)
    win = li._window_maxima(rho, 2)
    assert win.dtype == np.int32
    first = np.array([[0, 2, 1], [1, 0, 3], [0, 3, 0]]).T  # (3, M): boxes along each axis
    last = first + np.array([[3, 1, 0], [0, 3, 0], [2, 0, 3]]).T
    got = li._range_max(win, first, last)
    want = [rho[f[0]:l_[0] + 1, f[1]:l_[1] + 1, f[2]:l_[2] + 1].max()
            for f, l_ in zip(first.T, last.T, strict=True)]
    assert got.tolist() == want and got.dtype == np.int32
    with pytest.raises(ValueError, match="longer than two windows"):
        li._range_max(win, np.zeros((3, 1), np.int16), np.array([[4], [0], [0]], np.int16))


def test_drive_force_limit_by_hand() -> None:
    """The drive force per mass: the force limit at low speed, the power limit above."""
    p = veh.VehicleParams()
    v = np.array([0.0, 5.0, 40.0])
    want = np.minimum(p.max_drive_force_n, p.max_drive_power_w / np.array([0.1, 5.0, 40.0]))
    np.testing.assert_allclose(li._drive(v, p), want / p.mass_kg)
    assert li._drive(np.array([40.0]), p)[0] == pytest.approx(p.max_drive_power_w / 40.0
                                                               / p.mass_kg)


def test_recoverable_gap_behind_a_braking_slow_leader() -> None:
    """The ego at 30 m/s already braking fully, the leader at 10 m/s braking at 6 m/s^2: the
    ego stops after about 30^2 / (2 (9 + resistance)) m, the leader after 10^2 / 12 = 8.3 m and
    then stands; the gap is least when the ego stops, so the margin plus the difference (an
    independent Euler sum at the loop's step, resistance included)."""
    a, p = li.LoopAssumptions(), veh.VehicleParams()
    got = li.recoverable_gap(np.array([30.0]), np.array([10.0]), np.array([-9.0]), a, p)[0]
    v, x = 30.0, 0.0
    while v > 0.0:
        decel = 9.0 + float(veh.resistance_force(v, p)) / p.mass_kg
        v = max(v - decel * a.step_s, 0.0)
        x += v * a.step_s
    vl, xl = 10.0, 0.0
    while vl > 0.0:
        vl = max(vl - 6.0 * a.step_s, 0.0)
        xl += vl * a.step_s
    assert got == pytest.approx(a.margin_m + x - xl, abs=0.3)


def test_box_period_keeps_the_leader_speed_limits(safeil) -> None:
    """A leader box at the top speed (39.99-40 m/s) can gain at most what the limit leaves
    (0.01 m/s in the first step, then 0.02 per step below it: 0.19 m/s over the period); one
    at 0-0.5 m/s ends within [0, 0.7] m/s."""
    a, parts = li.LoopAssumptions(), li.LoopParts()
    f_box = (np.array([[-1.5]]), np.array([[0.0]]))
    box = lambda lo, hi: (np.array([lo]), np.array([hi]))
    image, change, _ = li.box_period(safeil, box(60.0, 61.5), box(39.0, 39.5), box(39.99, 40.0),
                                     f_box, (1.5, 1.5), a, parts)
    assert change[2][1][0, 0] == pytest.approx(0.19, abs=1e-6) and image[2][1][0, 0] <= 40.0 + 1e-6
    image, change, _ = li.box_period(safeil, box(20.0, 21.5), box(1.0, 1.5), box(0.0, 0.5),
                                     f_box, (1.5, 1.5), a, parts)
    assert image[2][0][0, 0] == pytest.approx(0.0, abs=1e-6)
    assert image[2][1][0, 0] == pytest.approx(0.7, abs=1e-6)


def test_the_bounds_refuse_what_they_do_not_cover(safeil) -> None:
    """A tracker with a derivative term, a checkpoint without the towers: one line each."""
    a = li.LoopAssumptions()
    f_box = (np.array([[-1.5]]), np.array([[0.0]]))
    one = (np.array([20.0]), np.array([21.5]))
    with_kd = li.LoopParts(controller=dataclasses.replace(li.LoopParts().controller, kd=0.1))
    with pytest.raises(ValueError, match=r"a PI tracker \(kd = 0\)"):
        li.box_period(safeil, one, one, one, f_box, (1.5, 1.5), a, with_kd)
    bc = load_policy(shipped_checkpoint("bc"))
    lo, hi = li.network_input_box(one, one, one, (1.5, 1.5), a)
    with pytest.raises(ValueError, match="needs the residual x outputs and the lane-following"):
        li.plan_bounds(bc, lo, hi)


def test_successors_are_the_images_cells(safeil) -> None:
    """successors, two gap rows at a time: every cell's image as the grid cells it meets
    (int16), failing where the gap can drop below the margin or the speed leave the grid,
    the same as the period image of all rows at once; progress counted in rows."""
    grid = li.Grid(gap_m=(1.0, 10.0, 1.5), speed_mps=(8.0, 10.0, 0.5),
                   leader_speed_mps=(8.0, 10.0, 0.5), force_mps2=(-3.0, 0.0, 1.5))
    a, parts = li.LoopAssumptions(), li.LoopParts()
    seen: list[int] = []
    succ = li.successors(safeil, grid, (1.5, 1.5), a, parts, rows_per_chunk=4,
                         progress=seen.append)
    assert seen == [4, 2]
    assert succ.first.shape == succ.last.shape == (4, *grid.shape)
    assert succ.first.dtype == succ.last.dtype == np.int16
    image, g_min = li.period_image(safeil, grid, slice(0, grid.shape[0]), (1.5, 1.5), a, parts)
    fails = g_min < a.margin_m
    for k, (edges, box) in enumerate(zip(grid.axes(), image, strict=True)):
        first, last, out = li._index_range(edges, box)
        assert np.array_equal(succ.first[k], first) and np.array_equal(succ.last[k], last)
        if k == 1:
            fails |= out
    assert np.array_equal(succ.fails, fails) and succ.fails.any() and not succ.fails.all()


def test_reference_bounds_of_one_plan_are_its_speed_and_acceleration(safeil) -> None:
    """A box of one state on a lane of one width, offset and slope, sensed exactly: the bounds
    of the tracker's reference hold the plan's own speed and acceleration
    (controller.plan_speed, plan_accel) at times from the decision to the horizon, within a
    millimetre per second and 0.05 m/s^2."""
    from safeil_sumo.sim import controller as ctl

    a = li.LoopAssumptions(lane_width_m=(3.5, 3.5), lateral_offset_m=(0.0, 0.0),
                           heading_error=(0.0, 0.0), speed_sensing_mps=0.0, gap_sensing_m=0.0)
    states = [(40.0, 25.0, 24.0), (12.0, 30.0, 20.0), (90.0, 15.0, 18.0)]  # gap, v, v_l
    box = lambda k: (np.array([s[k] for s in states]),) * 2
    lo, hi = li.network_input_box(box(0), box(1), box(2), (1.5, 1.5), a)
    pb = li.plan_bounds(safeil, lo, hi)
    safeil.set_style(time_gap_s=1.5)
    target = ctl.make_targets(safeil.plan(lo[:, :9]), np.full(3, safeil.horizon), np.zeros(3),
                              np.zeros(3), np.zeros(3))
    for t in (0.0, 0.05, 0.1, 0.3, safeil.horizon):  # the tracker reads up to 0.3 s
        ref = li.reference_bounds(pb, t, safeil.horizon, safeil.lane_keep_m, a)
        speed = ctl.plan_speed(target.coeff_x, target.coeff_y, target.horizon_s, t, ARRAYS)
        accel = ctl.plan_accel(target.coeff_x, target.coeff_y, target.horizon_s, t, ARRAYS)
        v0 = lo[:, 6]
        assert np.all(ref.err_lo + v0 <= speed + 1e-9) and np.all(speed <= ref.err_hi + v0 + 1e-9)
        assert np.all(ref.err_hi - ref.err_lo < 1e-3)
        assert np.all(ref.acc_lo <= accel + 1e-6) and np.all(accel <= ref.acc_hi + 1e-6)
        assert np.all(ref.acc_hi - ref.acc_lo < 0.05)


def test_widening_and_point_lines_by_hand() -> None:
    """Each bound moves outwards by 1e-9 (1 + |bound|); on a point interval the tanh lines are
    its tangent, their half gap the rounding allowance 1e-12 (1 + |offset|) and no more."""
    lo, hi = li._widen((np.array([2.0, -3.0]), np.array([3.0, -1.0])))
    fm = li.FLOAT_MARGIN
    assert lo.tolist() == [2.0 - fm * 3.0, -3.0 - fm * 4.0]
    assert hi.tolist() == [3.0 + fm * 4.0, -1.0 + fm * 2.0]
    for width in (0.0, 5e-10):
        z = np.array([0.7])
        s, o, d = li.tanh_parallel_lines(z, z + width)
        dev = math.tanh(0.7) - s[0] * 0.7
        assert s[0] == pytest.approx(1.0 - math.tanh(0.7 + width / 2) ** 2, rel=1e-12)
        assert abs(s[0] * 0.7 + o[0] - math.tanh(0.7)) <= d[0] <= 1e-11
        assert d[0] >= 1e-12 * (1.0 + abs(dev)) * (1 - 1e-6)


def test_guard_bounds_reach_a_standing_leader() -> None:
    """A sensed leader speed box reaching below 0: the demand's upper bound is at least the
    guard's demand behind a standing leader braking at the clip (10 m/s^2)."""
    guard = grd.BrakeGuard()
    box = lambda lo, hi: (np.array([lo]), np.array([hi]))
    _, hi = li.guard_bounds(box(8.0, 9.0), box(12.0, 12.5), box(-0.2, 0.6), guard)
    want = float(grd.guard_decel(8.0, 12.5, 0.0, -guard.max_leader_decel_mps2, guard, ARRAYS))
    assert hi[0] >= want - 1e-9 > 0.0


def test_assumptions_and_networks_refused_in_one_line(safeil) -> None:
    """Assumptions that cannot hold, a ReLU network, a network without the towers, a tracker with
    a derivative term: each a ValueError saying which."""
    with pytest.raises(ValueError, match="^LoopAssumptions.step_s must be > 0"):
        li.LoopAssumptions(step_s=0.0)
    assert li.LoopAssumptions(leader_accel_mps2=(-6.0, 0.5)).leader_accel_mps2 == (-6.0, 0.5)
    relu = [bnd.Layer.dense(np.eye(2), np.zeros(2), "relu"),
            bnd.Layer.dense(np.eye(2), np.zeros(2), "identity")]
    with pytest.raises(ValueError, match="^the closed-loop certificate bounds tanh networks$"):
        li._affine_forms(relu, np.zeros((1, 2)), np.ones((1, 2)))
    layers = li._network(safeil)
    crossed = layers[1].weight.copy()
    crossed[0, -1] = 0.1  # a longitudinal unit reading a lateral one
    layers[1] = dataclasses.replace(layers[1], weight=crossed)
    with pytest.raises(ValueError, match="^the closed-loop certificate needs a two-tower"):
        li._longitudinal_tower(layers)
    one = (np.array([20.0]), np.array([21.5]))
    with_kd = li.LoopParts(controller=dataclasses.replace(li.LoopParts().controller, kd=0.1))
    with pytest.raises(ValueError, match=r"^the closed-loop bounds cover a PI tracker \(kd = 0\)$"):
        li.box_period(safeil, one, one, one, (np.array([[-1.5]]), np.array([[0.0]])), (1.5, 1.5),
                      li.LoopAssumptions(), with_kd)
