"""The lateral closed-loop bound (safeil_sumo.learn.loop_lateral) against the loop's own code.

Every state the REAL camera fit, planner, pure pursuit and plant (tests/fixtures_lateral.py)
reach in one decision period from a box must lie in the box's bound, for random leaders
(sensed speed and gap), lane widths, PI integrals, tyre forces and overriding braking.
"""

from __future__ import annotations

import numpy as np
import pytest
from fixtures_lateral import real_lateral_period, steady_turn
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.learn import loop_lateral as ll
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.planners.registry import shipped_checkpoint

FIELDS = (*ll.STATE, "curvature")
WIDTH = {"e_y": 0.05, "e_psi": 0.004, "steer": 0.003, "vy": 0.04, "r": 0.01, "v": 1.0,
         "curvature": 0.0005}


@pytest.fixture(scope="module")
def safeil():
    return load_policy(shipped_checkpoint("safeil"))


def random_boxes(rng: np.random.Generator, n: int, speed=(22.0, 38.0)) -> ll.LateralBox:
    """Boxes of :data:`WIDTH` about random states near a steady turn on a random bend."""
    v = rng.uniform(*speed, n)
    k = rng.uniform(-0.0037, 0.0037, n)
    d, vy, r = steady_turn(v, k)
    centre = {"e_y": rng.uniform(-0.4, 0.4, n), "e_psi": rng.uniform(-0.015, 0.015, n),
              "steer": d + rng.uniform(-0.005, 0.005, n), "vy": vy + rng.uniform(-0.05, 0.05, n),
              "r": r + rng.uniform(-0.01, 0.01, n), "v": v, "curvature": k}
    return ll.LateralBox(*((centre[f] - WIDTH[f] / 2, centre[f] + WIDTH[f] / 2) for f in FIELDS))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=7, max_size=7), st.floats(0.0, 1.0),
       st.floats(0.0, 1.0), st.floats(0.0, 1.0))
def test_restricted_bernstein_bounds_hold(coef, a, b, at) -> None:
    lo_t, hi_t = min(a, b), max(a, b)
    c = np.array([coef])
    lo, hi = ll._restrict(c - 0.01, c + 0.01, np.array([lo_t]), np.array([hi_t]))
    tau = lo_t + at * (hi_t - lo_t)
    from safeil_sumo.core.bspline import bernstein_basis

    value = float(bernstein_basis(np.array([tau]), 6)[0] @ c[0])
    assert lo[0] - 1e-12 <= value <= hi[0] + 1e-12


def test_period_bound_contains_the_real_loop(safeil) -> None:
    rng = np.random.default_rng(11)
    a, parts = ll.LateralAssumptions(), ll.LateralParts()
    boxes = random_boxes(rng, 60)
    image = ll.period_bound(safeil, boxes, a, parts)
    assert image.ok.mean() >= 0.5  # most boxes are claimed at these speeds
    per = 60
    idx = np.repeat(np.flatnonzero(image.ok), per)
    n = len(idx)
    draw = {f: getattr(boxes, f)[0][idx] + rng.random(n) * (getattr(boxes, f)[1][idx]
                                                             - getattr(boxes, f)[0][idx])
            for f in FIELDS}
    width = rng.uniform(*a.lane_width_m, n)
    width[rng.random(n) < 0.2] = a.lane_width_m[0]
    lead = rng.uniform(0.0, 40.0, n)
    gap = np.exp(rng.uniform(np.log(3.0), np.log(150.0), n))
    accel = np.where(rng.random((n, 1)) < 0.3, rng.uniform(-9.0, 3.0, (n, a.steps_per_decision)),
                     np.nan)
    integral = rng.uniform(-1.0, 1.0, n) * parts.controller.integral_limit_m
    force = rng.uniform(-9.0, 3.0, n)
    final, path, (left, right) = real_lateral_period(
        safeil, *(draw[f] for f in FIELDS), width, lead, gap, integral, force, accel, a, parts)
    # the camera error the bound assumes
    centre, half = (left + right) / 2, (left - right) / 2
    k = draw["curvature"]
    ideal_c = np.stack([-draw["e_y"], -np.tan(draw["e_psi"]), k / 2], 1)
    ideal_h = np.stack([width / 2, 0 * k, k * k * width / 4], 1)
    assert np.all(np.abs(centre - ideal_c) <= a.camera_centre)
    assert np.all(np.abs(half - ideal_h) <= a.camera_half)
    for f, x in zip(ll.STATE, final, strict=True):
        lo, hi = (b[idx] for b in getattr(image.final, f))
        assert np.all((x >= lo) & (x <= hi)), (
            f"{f} outside its bound in {np.sum((x < lo) | (x > hi))} of {n}")
    e_lo, e_hi = (b[idx, None] for b in image.e_y_path)
    assert np.all((path >= e_lo) & (path <= e_hi))
    # not vacuous: narrower than the lane's room
    assert np.median(image.final.e_y[1] - image.final.e_y[0]) < 0.2
    assert n >= 1800
