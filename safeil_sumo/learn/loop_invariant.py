"""The longitudinal closed loop's one-period reachable set, bounded soundly; and the fixpoint
that turns such bounds into a forward-invariant set.

The state of the loop at a decision is ``(g, v, v_l, f)``: bumper gap [m], ego speed [m/s],
leader speed [m/s] and the ego's actual longitudinal tyre force per unit mass [m/s^2] (the
actuator lag's state). The state space is cut into a grid of boxes (cells). For every cell,
:func:`period_image` bounds, by interval and affine arithmetic, every state the loop can reach
one decision period later:

- the planner's plan from affine-form bounds of the longitudinal tower (and interval bounds of
  the lateral outputs) over the cell's SENSED box (gap and speeds widened by the sensing errors,
  the lane inputs by a stated lateral band, the time-gap input by its slice), turned into the
  tracker's reference speed and feed-forward acceleration at each physics step of the period
  (the B-spline's exact derivatives);
- the tracker (:func:`safeil_sumo.sim.controller.track_values`' PID, the integral anywhere in
  its clamp) and, when on, the brake guard (:mod:`safeil_sumo.sim.brake_guard`, its leader
  acceleration estimate anywhere in its clip range), every physics step;
- the plant's longitudinal dynamics (:class:`safeil_sumo.sim.vehicle.Plant`: pedals, brake and
  drive lags, power limit, drag, rolling resistance) every physics step, the lateral coupling
  terms bounded by a stated constant;
- the leader accelerating anywhere in ``leader_accel_mps2`` at every physics step, down to
  standstill and up to the speed limit.

tests/learn/test_loop_invariant.py checks the image against the loop's own code from thousands of
random states. :func:`gap_floor` then computes the largest set, closed upwards in the gap, whose
cells' images stay in it and never reach the margin: forward invariant by construction. On
the shipped ``safeil`` at this grid (0.5 m/s speed cells) it is empty: see
docs/certification.md for why. :func:`box_period` also bounds each state's change over the
period, which :mod:`.loop_barrier` checks a smooth gap floor against.

Pure numpy; no SUMO, no torch. Arrays of cells are ``(n_g, n_v, n_l, n_f)`` in that order.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from safeil_sumo.learn import bounds as bnd
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.learn.towers import X_OUTPUTS, Y_OUTPUTS, tower_masks
from safeil_sumo.sim.brake_guard import BrakeGuard, guard_decel
from safeil_sumo.sim.controller import ControllerParams
from safeil_sumo.sim.vehicle import GRAVITY, VehicleParams
from safeil_sumo.sim.xp import ARRAYS

FLOAT_MARGIN = 1e-9  # every interval bound is moved outwards by this after each step [SI]

Interval = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class LoopAssumptions:
    """What the bounds assume of the world around the planner (SI units)."""

    step_s: float = 0.01  # physics step of the loop [s]
    steps_per_decision: int = 10  # physics steps per decision period (10 Hz planning)
    leader_accel_mps2: tuple[float, float] = (-6.0, 2.0)  # any, at every physics step
    speed_limit_mps: float = 40.0  # the leader's speeds lie in [0, this]
    gap_sensing_m: float = 0.5  # |sensed - true| bumper gap [m]
    speed_sensing_mps: float = 0.2  # |sensed - true| ego and leader speeds [m/s]
    lane_width_m: tuple[float, float] = (3.3, 3.8)  # a straight lane [m]
    lateral_offset_m: tuple[float, float] = (-0.3, 0.3)  # ego front bumper from lane centre [m]
    heading_error: tuple[float, float] = (-0.01, 0.01)  # lane slope in the ego frame [-]
    # |F_yf sin(delta) / m - v_y r| of the plant on a straight lane [m/s^2]; the containment test
    # steps the plant under the tracker's own steering within this lateral band
    lateral_coupling_mps2: float = 0.05
    margin_m: float = 1.0  # safe: bumper gap >= this [m]

    def __post_init__(self) -> None:
        lo, hi = self.leader_accel_mps2
        if not lo < 0.0 <= hi:
            raise ValueError(f"leader_accel_mps2 must be (lo < 0, hi >= 0), got "
                             f"{self.leader_accel_mps2}")
        for name in ("step_s", "speed_limit_mps", "margin_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LoopAssumptions.{name} must be > 0")
        for name in ("gap_sensing_m", "speed_sensing_mps", "lateral_coupling_mps2"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"LoopAssumptions.{name} must be >= 0")


@dataclass(frozen=True)
class Grid:
    """The cells: ``(lo, hi, width)`` per state dimension; the gap axis starts at the margin."""

    gap_m: tuple[float, float, float] = (1.0, 151.0, 1.5)
    speed_mps: tuple[float, float, float] = (0.0, 50.0, 0.5)  # the ego's
    leader_speed_mps: tuple[float, float, float] = (0.0, 40.0, 0.5)
    force_mps2: tuple[float, float, float] = (-9.0, 3.0, 1.5)  # tyre force / mass

    def axes(self) -> tuple[np.ndarray, ...]:
        """Cell edges per dimension ``(n_k + 1,)``."""
        out = []
        for lo, hi, w in (self.gap_m, self.speed_mps, self.leader_speed_mps, self.force_mps2):
            n = round((hi - lo) / w)
            if n < 1 or not math.isclose(lo + n * w, hi):
                raise ValueError(f"grid axis ({lo}, {hi}, {w}) is not a whole number of cells")
            out.append(lo + w * np.arange(n + 1))
        return tuple(out)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        n = [len(a) - 1 for a in self.axes()]
        return n[0], n[1], n[2], n[3]


# ------------------------------------------------------------------ the plan's bounds


def _widen(x: Interval) -> Interval:
    return x[0] - FLOAT_MARGIN * (1.0 + np.abs(x[0])), x[1] + FLOAT_MARGIN * (1.0 + np.abs(x[1]))


LONGITUDINAL_INPUTS = (6, 7, 8, 9)  # v_x, v_lead, d_lead, time gap: all the x tower reads


def _network(policy: MLPPolicy) -> list[bnd.Layer]:
    """The planner's network with the style inputs as columns: 10 inputs -> 6 raw outputs."""
    affine = policy.affine_layers(style_input=True)
    act = policy.activation
    return [bnd.Layer.dense(w, b, act if j < len(affine) - 1 else "identity")
            for j, (w, b) in enumerate(affine)]


def _longitudinal_tower(layers: list[bnd.Layer]) -> list[bnd.Layer]:
    """The x outputs' own network (the towers checkpoint's first half of every hidden layer,
    reading :data:`LONGITUDINAL_INPUTS`); refused unless every weight it leaves out is 0."""
    widths = [layers[0].weight.shape[1], *(layer.weight.shape[0] for layer in layers[:-1])]
    masks = tower_masks(widths[0], widths[1:])
    if any(np.any(layer.weight * (1.0 - m) != 0.0) for layer, m in zip(layers, masks, strict=True)):
        raise ValueError("the closed-loop certificate needs a two-tower checkpoint")
    rows = [np.arange(w // 2) for w in widths[1:]] + [np.array(X_OUTPUTS)]
    cols = [np.array(LONGITUDINAL_INPUTS)] + [np.arange(w // 2) for w in widths[1:]]
    return [bnd.Layer(layer.weight[np.ix_(r, c)], layer.bias[r], layer.activation[r])
            for layer, r, c in zip(layers, rows, cols, strict=True)]


def network_input_box(g: tuple[np.ndarray, np.ndarray], v: tuple[np.ndarray, np.ndarray],
                      vl: tuple[np.ndarray, np.ndarray], time_gap: tuple[float, float],
                      a: LoopAssumptions) -> tuple[np.ndarray, np.ndarray]:
    """The sensed feature boxes ``(N, 10)`` x2 of true-state boxes ``g, v, vl`` ``(N,)`` each:
    lane lines of a straight lane in the stated band, speeds and gap widened by the sensing
    errors, the time-gap setting's slice."""
    n = len(g[0])
    lo, hi = np.empty((n, 10)), np.empty((n, 10))
    (w_lo, w_hi), (o_lo, o_hi), (h_lo, h_hi) = (a.lane_width_m, a.lateral_offset_m,
                                                a.heading_error)
    lane_lo = (w_lo / 2 - o_hi, h_lo, 0.0, -w_hi / 2 - o_hi, h_lo, 0.0)
    lane_hi = (w_hi / 2 - o_lo, h_hi, 0.0, -w_lo / 2 - o_lo, h_hi, 0.0)
    lo[:, :6], hi[:, :6] = lane_lo, lane_hi
    es, eg = a.speed_sensing_mps, a.gap_sensing_m
    lo[:, 6], hi[:, 6] = v[0] - es, v[1] + es
    lo[:, 7], hi[:, 7] = vl[0] - es, vl[1] + es
    lo[:, 8], hi[:, 8] = g[0] - eg, g[1] + eg
    lo[:, 9], hi[:, 9] = time_gap
    return lo, hi


@dataclass(frozen=True)
class PlanBounds:
    """The planner's outputs over N boxes. The x outputs ``(x1, x2, x3)`` before the residual
    as affine forms: ``centre + e @ gens + [-err, err]`` for every ``e`` in ``[-1, 1]^4`` (one
    per :data:`LONGITUDINAL_INPUTS`); ``centre (N, 3)``, ``gens (N, 4, 3)``, ``err (N, 3)``.
    The lateral outputs ``z (N, 3)`` as intervals; the sensed ego speed ``(N,)`` x2 (the
    residual mode adds ``v_x t_i`` to the x control points)."""

    centre: np.ndarray
    gens: np.ndarray
    err: np.ndarray
    z_lo: np.ndarray
    z_hi: np.ndarray
    v_sensed_lo: np.ndarray
    v_sensed_hi: np.ndarray

    def linear(self, coef: np.ndarray) -> Interval:
        """Interval ``(N,)`` x2 of ``coef @ (x1, x2, x3)``: the affine forms keep what the
        outputs share, so ``x2 - 2 x1`` is far tighter than its interval terms."""
        c = self.centre @ coef
        r = np.abs(self.gens @ coef).sum(-1) + self.err @ np.abs(coef)
        return _widen((c - r, c + r))


def tanh_parallel_lines(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, ...]:
    """``tanh(z) in s z + o + [-d, d]`` for every ``z in [lo, hi]``: ``s`` the chord's slope,
    ``o`` and ``d`` from the exact extremes of ``tanh(z) - s z`` (at the ends and where
    ``tanh'(z) = s``, i.e. ``z = +-atanh(sqrt(1 - s))``), widened for rounding."""
    width = hi - lo
    narrow = width < 1e-9
    mid = 0.5 * (lo + hi)
    s = np.where(narrow, 1.0 - np.tanh(mid) ** 2,
                 (np.tanh(hi) - np.tanh(lo)) / np.where(narrow, 1.0, width))
    s = np.clip(s, 1e-300, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        star = np.arctanh(np.sqrt(1.0 - s))
    dev = np.tanh(lo) - s * lo
    d_lo, d_hi = dev.copy(), dev.copy()
    for z in (star, -star):
        inside = (z > lo) & (z < hi) & np.isfinite(z)
        d = np.where(inside, np.tanh(np.where(inside, z, 0.0)) - s * np.where(inside, z, 0.0),
                     dev)
        d_lo, d_hi = np.minimum(d_lo, d), np.maximum(d_hi, d)
    # narrow intervals: the tangent at the midpoint is off by at most max|tanh''| w^2 / 8
    slack = np.where(narrow, 0.77 * width ** 2 / 8.0, 0.0) + 1e-12 * (1.0 + np.abs(dev))
    return s, 0.5 * (d_lo + d_hi), 0.5 * (d_hi - d_lo) + slack


def _affine_forms(layers: list[bnd.Layer], lo: np.ndarray, hi: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Affine forms ``(centre (N, n_out), gens (N, n_in, n_out), err (N, n_out))`` of a tanh
    network's outputs over boxes ``(N, n_in)``: each tanh is replaced by parallel lines
    (:func:`tanh_parallel_lines`), whose gap joins the independent error."""
    centre = 0.5 * (lo + hi)
    n, n_in = lo.shape
    gens = np.einsum("ij,ni->nij", np.eye(n_in), 0.5 * (hi - lo))
    err = np.zeros_like(centre)
    for k, layer in enumerate(layers):
        w = layer.weight
        centre = centre @ w.T + layer.bias
        gens = (gens.reshape(-1, w.shape[1]) @ w.T).reshape(n, n_in, -1)
        err = err @ np.abs(w).T
        err = err + FLOAT_MARGIN * (1.0 + np.abs(centre) + np.abs(gens).sum(1))
        if k == len(layers) - 1:
            break
        if not np.all(layer.activation == bnd.TANH):
            raise ValueError("the closed-loop certificate bounds tanh networks")
        r = np.abs(gens).sum(1) + err
        s, o, d = tanh_parallel_lines(centre - r, centre + r)
        centre = s * centre + o
        gens = s[:, None, :] * gens
        err = s * err + d
    return centre, gens, err


def _ibp(layers: list[bnd.Layer], lo: np.ndarray, hi: np.ndarray) -> Interval:
    """Interval propagation of the network's outputs over boxes ``(N, n_in)``."""
    a, b = lo, hi
    for k, layer in enumerate(layers):
        a, b = _widen(bnd.affine_interval(layer.weight, layer.bias, a, b))
        if k < len(layers) - 1:
            a, b = _widen((np.tanh(a), np.tanh(b)))
    return a, b


def plan_bounds(policy: MLPPolicy, lo: np.ndarray, hi: np.ndarray) -> PlanBounds:
    """Bounds of the planner's outputs over the feature boxes ``(N, 10)``: affine forms of the
    longitudinal tower, interval propagation of the lateral outputs (they enter the speed only
    through the plan's small sideways motion)."""
    if policy.residual_times is None or policy.lateral_mode != "lane":
        raise ValueError(f"{policy.name}: the closed-loop certificate needs the residual x "
                         "outputs and the lane-following y outputs (a towers checkpoint)")
    layers = _network(policy)
    cols = list(LONGITUDINAL_INPUTS)
    centre, gens, err = _affine_forms(_longitudinal_tower(layers), lo[:, cols], hi[:, cols])
    z_lo, z_hi = _ibp(layers, lo, hi)
    y = list(Y_OUTPUTS)
    return PlanBounds(centre, gens, err, z_lo[:, y], z_hi[:, y], lo[:, 6].copy(),
                      hi[:, 6].copy())


def _dot(coef: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval of ``sum_k coef_k x_k`` for ``x_k in [lo_k, hi_k]`` (last axis)."""
    return (np.where(coef >= 0, coef * lo, coef * hi).sum(-1),
            np.where(coef >= 0, coef * hi, coef * lo).sum(-1))


def _mul(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]
         ) -> tuple[np.ndarray, np.ndarray]:
    """Interval product."""
    p = np.stack([a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]])
    return p.min(0), p.max(0)


@dataclass(frozen=True)
class Reference:
    """Bounds ``(N,)`` of what the tracker reads from every plan of a cell at one time.

    The speed error ``v_ref - v`` is ``err - (v - v_0)`` while the plan runs forwards (``v_0``
    the speed at the decision: the residual's sensed ``v_s`` is ``v_0`` within the sensing
    error, so the error does not carry the cell's width twice); ``-v`` while it runs backwards.
    """

    err_lo: np.ndarray  # [m/s]
    err_hi: np.ndarray  # [m/s]
    forwards: np.ndarray  # bool: some plan runs forwards
    backwards: np.ndarray  # bool: some plan runs backwards (a stop)
    acc_lo: np.ndarray  # [m/s^2] tangential acceleration
    acc_hi: np.ndarray


def reference_bounds(pb: PlanBounds, t: float, horizon: float, keep_m: float,
                     a: LoopAssumptions) -> Reference:
    """The tracker's reference speed and tangential acceleration
    (:func:`safeil_sumo.sim.controller.plan_speed`, ``plan_accel``) at ``t`` [s] after the
    decision, for every plan of the bounded outputs (:class:`Reference`).

    The plan is the Bezier curve of control points ``P0 = 0, P1..P3``; ``x_k = o_xk + v_s t_k``
    and ``y_k = c0m + c1m x_k + h tanh(z_k)`` (:func:`safeil_sumo.core.bspline.lane_following_y` on a
    straight lane: centre ``c0m = -offset``, slope ``c1m``, half width less the keep ``h``).
    The constant-speed part ``v_s t_k`` adds exactly ``v_s`` to x' and nothing to x''.
    """
    tau = min(t, horizon) / horizon
    d1 = 3.0 / horizon * np.array([(1 - tau) ** 2 - 2 * (1 - tau) * tau,
                                   2 * (1 - tau) * tau - tau ** 2, tau ** 2])
    d2 = 6.0 / horizon ** 2 * np.array([3 * tau - 2, 1 - 3 * tau, tau])
    xd_net = pb.linear(d1)
    xd = (xd_net[0] + pb.v_sensed_lo, xd_net[1] + pb.v_sensed_hi)
    xdd = pb.linear(d2)
    th = (np.tanh(pb.z_lo), np.tanh(pb.z_hi))
    h = (max(a.lane_width_m[0] / 2 - keep_m, 0.0), max(a.lane_width_m[1] / 2 - keep_m, 0.0))
    c0m = (-a.lateral_offset_m[1], -a.lateral_offset_m[0])
    c1m = a.heading_error

    def y_derivative(coef: np.ndarray, xder: tuple[np.ndarray, np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray]:
        s = float(coef.sum())  # the constant c0m's weight (P0 = 0 carries no c0m)
        const = (min(s * c0m[0], s * c0m[1]), max(s * c0m[0], s * c0m[1]))
        slope = _mul((np.full_like(xder[0], c1m[0]), np.full_like(xder[0], c1m[1])), xder)
        bend = _mul((np.full_like(xder[0], h[0]), np.full_like(xder[0], h[1])), _dot(coef, *th))
        return const[0] + slope[0] + bend[0], const[1] + slope[1] + bend[1]

    yd, ydd = y_derivative(d1, xd), y_derivative(d2, xdd)
    y_max = np.maximum(np.abs(yd[0]), np.abs(yd[1]))
    x_pos = np.maximum(xd[0], 0.0)
    # |v| - x' = hypot(x', y') - x' is at most this for x' >= x_pos
    extra = np.hypot(x_pos, y_max) - x_pos
    es = a.speed_sensing_mps
    return Reference(xd_net[0] - es, xd_net[1] + es + extra, xd[1] >= 0.0, xd[0] < 0.0,
                     *_tangential_accel(xd, xdd, y_max, ydd))


def _tangential_accel(xd: Interval, xdd: Interval, y_max: np.ndarray, ydd: Interval
                      ) -> Interval:
    """Bounds of ``plan_accel`` from those of the plan's derivatives (``|y'| <= y_max``)."""
    # a = x'' cos + y'' sin, cos = x'/|v| in [cos_lo, 1], |sin| <= sin_hi (x' > 0)
    x_pos = np.maximum(xd[0], 0.0)
    norm = np.hypot(x_pos, y_max)
    ok = norm > 0.0
    cos_lo = np.where(ok, x_pos / np.where(ok, norm, 1.0), 0.0)
    sin_hi = np.where(ok, y_max / np.where(ok, norm, 1.0), 1.0)
    ax = _mul(xdd, (cos_lo, np.ones_like(cos_lo)))
    ay = _mul(ydd, (-sin_hi, sin_hi))
    acc_lo, acc_hi = ax[0] + ay[0], ax[1] + ay[1]
    # from rest (|v| < 1e-6): hypot(x'', y''); backwards (x' < 0): 0
    rest = xd[0] <= 1e-6
    rest_hi = np.hypot(np.maximum(np.abs(xdd[0]), np.abs(xdd[1])),
                       np.maximum(np.abs(ydd[0]), np.abs(ydd[1])))
    acc_lo = np.where(rest, np.minimum(acc_lo, 0.0), acc_lo)
    acc_hi = np.where(rest, np.maximum(acc_hi, rest_hi), acc_hi)
    back = xd[1] < 0.0
    return np.where(back, 0.0, acc_lo), np.where(back, 0.0, acc_hi)


# ------------------------------------------------------------------ one decision period


@dataclass(frozen=True)
class LoopParts:
    """The parts of the loop the certificate covers, as the simulation runs them."""

    vehicle: VehicleParams = field(default_factory=VehicleParams)
    controller: ControllerParams = field(default_factory=ControllerParams)
    guard: BrakeGuard | None = field(default_factory=BrakeGuard)


def guard_bounds(g_s: Interval, v_s: Interval, vl_s: Interval, guard: BrakeGuard
                 ) -> Interval:
    """The guard's demand [m/s^2] over sensed boxes, its leader estimate anywhere in its clip
    range: :func:`guard_decel` grows with the ego speed and the leader's braking and falls with
    the gap and the leader speed (tests/learn/test_loop_invariant.py checks it), so the corners bound
    it. Sensed speeds below 0 are taken as 0 (the demand there is below activation)."""
    b_max = guard.max_leader_decel_mps2
    lo = guard_decel(g_s[1], np.maximum(v_s[0], 0.0), np.maximum(vl_s[1], 0.0), 0.0, guard,
                     ARRAYS)
    hi = guard_decel(np.maximum(g_s[0], 1e-3), np.maximum(v_s[1], 0.0),
                     np.maximum(vl_s[0], 0.0), -b_max, guard, ARRAYS)
    return np.asarray(lo, float), np.asarray(hi, float)


def _resistance(v: np.ndarray, veh: VehicleParams) -> np.ndarray:
    """:func:`safeil_sumo.sim.vehicle.resistance_force` / mass (grows with v >= 0; 0 at rest)."""
    drag = 0.5 * veh.air_density_kgm3 * veh.drag_coefficient * veh.frontal_area_m2
    return np.where(v <= 0.0, 0.0, (drag * v * v) / veh.mass_kg
                    + veh.rolling_resistance * GRAVITY)


def _drive(v: np.ndarray, veh: VehicleParams) -> np.ndarray:
    """:func:`safeil_sumo.sim.vehicle.available_drive_force` / mass (falls with v)."""
    return np.minimum(veh.max_drive_force_n, veh.max_drive_power_w / np.maximum(v, 0.1)) \
        / veh.mass_kg


def _command(v: Interval, dv: Interval, ref: Reference, demand: Interval | None,
             parts: LoopParts) -> Interval:
    """The acceleration command's interval at speeds ``v`` (``dv``: their change since the
    decision): PID + feed-forward (any integral in its clamp), clipped, then the brake guard's
    override (demand 0: off; else the smaller of the command and ``-demand`` floored at full
    braking)."""
    c = parts.controller
    fwd_lo, fwd_hi = ref.err_lo - dv[1], ref.err_hi - dv[0]
    err_lo = np.where(ref.forwards, np.where(ref.backwards, np.minimum(fwd_lo, -v[1]), fwd_lo),
                      -v[1])
    err_hi = np.where(ref.forwards, np.where(ref.backwards, np.maximum(fwd_hi, -v[0]), fwd_hi),
                      -v[0])
    i_max = c.ki * c.integral_limit_m
    k = c.accel_feedforward_gain
    lo = np.minimum(k * ref.acc_lo, k * ref.acc_hi) + c.kp * err_lo - i_max
    hi = np.maximum(k * ref.acc_lo, k * ref.acc_hi) + c.kp * err_hi + i_max
    lo = np.clip(lo, c.accel_min_mps2, c.accel_max_mps2)
    hi = np.clip(hi, c.accel_min_mps2, c.accel_max_mps2)
    if demand is None:
        return lo, hi
    full = parts.vehicle.max_brake_decel_mps2
    guarded_lo = np.minimum(lo, np.maximum(-demand[1], -full))
    guarded_hi = np.minimum(hi, np.maximum(-demand[0], -full))
    return (np.where(demand[1] > 0.0, guarded_lo, lo),
            np.where(demand[0] > 0.0, guarded_hi, hi))


def _physics_step(state: list[Interval], cmd: Interval, a: LoopAssumptions,
                  parts: LoopParts) -> list[Interval]:
    """One physics step of ``[g, v, vl, f, dg, dv, dvl, df]`` boxes under the command interval
    (``dg .. df``: each state's change since the decision, bounded from the step's own change,
    so that a cell's width does not enter the change twice)."""
    g, v, vl, f, dg, dv, dvl, df = state
    veh, dt = parts.vehicle, a.step_s
    r = (_resistance(v[0], veh), _resistance(v[1], veh))  # 0 at rest
    drive = (_drive(v[1], veh), _drive(v[0], veh))
    full = veh.max_brake_decel_mps2
    target = (np.maximum(np.minimum(cmd[0] + r[0], drive[0]), -full),
              np.maximum(np.minimum(cmd[1] + r[1], drive[1]), -full))
    # the brake lag or the drive lag: the new force is between the old and the target either way;
    # its change (1 - d) (target - f)
    decays = (math.exp(-dt / veh.brake_time_constant_s), math.exp(-dt / veh.drive_time_constant_s))
    f_new = (np.minimum(*(d * f[0] + (1 - d) * target[0] for d in decays)),
             np.maximum(*(d * f[1] + (1 - d) * target[1] for d in decays)))
    cf = (np.minimum(*((1 - d) * (target[0] - f[1]) for d in decays)),
          np.maximum(*((1 - d) * (target[1] - f[0]) for d in decays)))
    eps = a.lateral_coupling_mps2
    acc = (f_new[0] - r[1] - eps, f_new[1] - r[0] + eps)
    v_new = (np.maximum(v[0] + acc[0] * dt, 0.0), np.maximum(v[1] + acc[1] * dt, 0.0))
    # the change max(acc dt, -v): the standstill clamp only raises it
    cv = (np.maximum(acc[0] * dt, -v[1]), np.maximum(acc[1] * dt, -v[0]))
    a_lo, a_hi = a.leader_accel_mps2
    vl_new = (np.clip(vl[0] + a_lo * dt, 0.0, a.speed_limit_mps),
              np.clip(vl[1] + a_hi * dt, 0.0, a.speed_limit_mps))
    # the leader's change: its acceleration, clamped at standstill and the speed limit
    cl = (np.maximum(a_lo * dt, -vl[1]), np.minimum(a_hi * dt, a.speed_limit_mps - vl[0]))
    # the gap moves by the speeds before or after the step (explicit or semi-implicit Euler)
    cg = ((np.minimum(vl[0], vl_new[0]) - np.maximum(v[1], v_new[1])) * dt,
          (np.maximum(vl[1], vl_new[1]) - np.minimum(v[0], v_new[0])) * dt)
    g_new = (g[0] + cg[0], g[1] + cg[1])
    changes = [(d[0] + c[0], d[1] + c[1]) for d, c in zip((dg, dv, dvl, df), (cg, cv, cl, cf),
                                                          strict=True)]
    return [_widen(x) for x in (g_new, v_new, vl_new, f_new, *changes)]


def _cell_boxes(edges: np.ndarray) -> Interval:
    return edges[:-1], edges[1:]


def box_image(policy: MLPPolicy, g: Interval, v: Interval, vl: Interval, f: Interval,
              time_gap: tuple[float, float], a: LoopAssumptions, parts: LoopParts
              ) -> tuple[list[Interval], np.ndarray]:
    """Bounds of the state one decision period after each of N boxes of true decision states:
    ``g, v, vl`` intervals of arrays ``(N,)``, ``f`` of arrays ``(N,)`` or ``(N, n_f)`` (several
    force boxes sharing one plan box). Returns ``[g, v, vl, f]`` intervals shaped as ``f`` and
    the smallest gap bound met at any physics step of the period [m]."""
    image, _, g_min = box_period(policy, g, v, vl, f, time_gap, a, parts)
    return image, g_min


def box_period(policy: MLPPolicy, g: Interval, v: Interval, vl: Interval, f: Interval,
               time_gap: tuple[float, float], a: LoopAssumptions, parts: LoopParts
               ) -> tuple[list[Interval], list[Interval], np.ndarray]:
    """:func:`box_image` and the bounds of each state's CHANGE over the period, ``[g⁺ - g,
    v⁺ - v, vl⁺ - vl, f⁺ - f]`` for every state of the box (intervals shaped as ``f``): a
    change is bounded step by step from the step's own change, so a cell's width enters it only
    through the commands and the speeds' spread, not as the difference of two boxes."""
    if parts.controller.kd != 0.0:
        raise ValueError("the closed-loop bounds cover a PI tracker (kd = 0)")
    lo, hi = network_input_box(g, v, vl, time_gap, a)
    pb = plan_bounds(policy, lo, hi)
    shape = (len(g[0]), *np.shape(f[0])[1:])
    extra = (1,) * (len(shape) - 1)  # per-box values against the force axis, if any

    def per_box(x: np.ndarray) -> np.ndarray:
        return np.asarray(x).reshape(len(x), *extra)

    demand: Interval | None = None
    if parts.guard is not None:
        d_lo, d_hi = guard_bounds((lo[:, 8], hi[:, 8]), (lo[:, 6], hi[:, 6]), (lo[:, 7], hi[:, 7]),
                                  parts.guard)
        demand = (per_box(d_lo), per_box(d_hi))
    state = [(np.broadcast_to(per_box(x[0]) if x is not f else x[0], shape).copy(),
              np.broadcast_to(per_box(x[1]) if x is not f else x[1], shape).copy())
             for x in (g, v, vl, f)]
    state.extend((np.zeros(shape), np.zeros(shape)) for _ in range(4))
    g_min = state[0][0].copy()
    keep, horizon = policy.lane_keep_m, policy.horizon
    for j in range(a.steps_per_decision):
        t = j * a.step_s
        speed = reference_bounds(pb, t + parts.controller.speed_preview_s, horizon, keep, a)
        acc = reference_bounds(pb, t + parts.controller.accel_preview_s, horizon, keep, a)
        ref = Reference(*(per_box(x) for x in (speed.err_lo, speed.err_hi, speed.forwards,
                                               speed.backwards, acc.acc_lo, acc.acc_hi)))
        cmd = _command(state[1], state[5], ref, demand, parts)
        state = _physics_step(state, cmd, a, parts)
        g_min = np.minimum(g_min, state[0][0])
    return state[:4], state[4:], g_min


def period_image(policy: MLPPolicy, grid: Grid, rows: slice, time_gap: tuple[float, float],
                 a: LoopAssumptions, parts: LoopParts) -> tuple[list[Interval], np.ndarray]:
    """:func:`box_image` of every cell of the gap rows ``rows``: intervals and the smallest
    gap, each ``(n_rows, n_v, n_l, n_f)``."""
    eg, ev, el, ef = grid.axes()
    g_c, v_c, l_c = (_cell_boxes(e) for e in (eg[rows.start:rows.stop + 1], ev, el))
    index = np.meshgrid(np.arange(len(g_c[0])), np.arange(len(v_c[0])), np.arange(len(l_c[0])),
                        indexing="ij")
    g, v, vl = ((c[0][i].ravel(), c[1][i].ravel()) for c, i in zip((g_c, v_c, l_c), index,
                                                                    strict=True))
    f_c = _cell_boxes(ef)
    image, g_min = box_image(policy, g, v, vl, (f_c[0][None, :], f_c[1][None, :]), time_gap, a,
                             parts)
    shape = (*index[0].shape, len(f_c[0]))
    return [(lo.reshape(shape), hi.reshape(shape)) for lo, hi in image], g_min.reshape(shape)


# ------------------------------------------------------------------ the invariant set


def _index_range(edges: np.ndarray, box: Interval) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells ``[first, last]`` a box's interval meets along one axis (clipped to the axis)
    and where it passes the axis' top edge."""
    n = len(edges) - 1
    w = edges[1] - edges[0]
    first = np.floor((box[0] - edges[0]) / w)
    last = np.where(box[1] == edges[-1], n - 1, np.floor((box[1] - edges[0]) / w))
    return (np.clip(first, 0, n - 1).astype(np.int16), np.clip(last, 0, n - 1).astype(np.int16),
            box[1] > edges[-1])


@dataclass
class Successors:
    """Per cell ``(n_g, n_v, n_l, n_f)``: the index box ``first, last (4, ...)`` of the cells its
    one-period image meets, and whether the image leaves the grid or the safe gap."""

    first: np.ndarray
    last: np.ndarray
    fails: np.ndarray


def successors(policy: MLPPolicy, grid: Grid, time_gap: tuple[float, float],
               a: LoopAssumptions, parts: LoopParts, rows_per_chunk: int = 10,
               progress: Callable[[int], object] | None = None) -> Successors:
    """:func:`period_image` of every cell, as the grid cells it meets."""
    shape = grid.shape
    first, last = np.empty((4, *shape), np.int16), np.empty((4, *shape), np.int16)
    fails = np.empty(shape, bool)
    axes = grid.axes()
    for start in range(0, shape[0], rows_per_chunk):
        rows = slice(start, min(start + rows_per_chunk, shape[0]))
        image, g_min = period_image(policy, grid, rows, time_gap, a, parts)
        bad = g_min < a.margin_m
        for k, (edges, box) in enumerate(zip(axes, image, strict=True)):
            first[k, rows], last[k, rows], out = _index_range(edges, box)
            # below 0 (speeds) and beyond the force limits only by the rounding margin; above
            # the gap axis is further away (gap_floor's sets are closed upwards): only the
            # ego's speed can leave the grid
            if k == 1:
                bad |= out
        fails[rows] = bad
        if progress is not None:
            progress(rows.stop - rows.start)
    return Successors(first, last, fails)


WINDOW_MAX = 8  # range maxima are read from windows of up to this many cells per axis


def _window_maxima(rho: np.ndarray, window: int = WINDOW_MAX) -> np.ndarray:
    """``out[p, q, r, i, j, k]`` = max of ``rho (n_v, n_l, n_f)`` over the window of
    ``(p + 1, q + 1, r + 1)`` cells from ``(i, j, k)`` (cut at the grid's end), windows of up
    to ``window`` cells per axis."""
    lengths = [min(window, n) for n in rho.shape]
    out = np.empty((*lengths, *rho.shape), rho.dtype)
    per_axis = [rho]
    for axis in range(3):
        stacks = []
        for base in per_axis:
            level = [base]
            for _ in range(1, lengths[axis]):
                prev = level[-1]
                shifted = np.concatenate([np.take(base, range(len(level), base.shape[axis]),
                                                  axis=axis),
                                          np.take(prev, range(base.shape[axis] - len(level),
                                                              base.shape[axis]), axis=axis)],
                                         axis=axis)
                level.append(np.maximum(prev, shifted))
            stacks.extend(level)
        per_axis = stacks
    out[...] = np.asarray(per_axis).reshape(out.shape)
    return out


def _range_max(windows: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Max over index boxes ``[first, last]`` ``(3, M)`` each, from :func:`_window_maxima`:
    two windows per axis (from the box's start and to its end) cover any box up to twice
    :data:`WINDOW_MAX` cells long."""
    lengths = np.asarray(windows.shape[:3])[:, None]
    span = last.astype(np.int64) - first + 1
    if np.any(span > 2 * lengths):
        raise ValueError("an image box is longer than two windows: refine the grid's time step")
    w = np.minimum(span, lengths)
    lowest = (np.iinfo(windows.dtype).min if np.issubdtype(windows.dtype, np.integer)
              else -np.inf)
    out = np.full(first.shape[1], lowest, windows.dtype)
    for corner in range(8):
        start = [np.where(corner >> k & 1, last[k] - w[k] + 1, first[k]) for k in range(3)]
        out = np.maximum(out, windows[w[0] - 1, w[1] - 1, w[2] - 1, start[0], start[1], start[2]])
    return out


def gap_floor(succ: Successors, max_rounds: int = 10_000) -> tuple[np.ndarray, int]:
    """The largest invariant set that is closed upwards in the gap: per ``(v, v_l, f)`` cell
    the lowest gap row ``rho (n_v, n_l, n_f)`` from which on every cell is in the set
    (``n_g``: none). A cell of the set must not fail and its image's lowest gap must be at or
    above the floor of every ``(v, v_l, f)`` cell the image meets; a failing cell lifts its
    column's floor above it. Returns ``rho`` and the rounds it took."""
    n_g = succ.fails.shape[0]
    rho = np.zeros(succ.fails.shape[1:], np.int32)
    rows = np.arange(n_g)[:, None, None, None]
    first3 = succ.first[1:].reshape(3, -1)
    last3 = succ.last[1:].reshape(3, -1)
    first_g = succ.first[0].reshape(-1)
    for rounds in range(1, max_rounds + 1):
        need = _range_max(_window_maxima(rho), first3, last3)
        bad = succ.fails.reshape(-1) | (first_g < need)
        bad = bad.reshape(succ.fails.shape) & (rows >= rho[None])
        if not bad.any():
            return rho, rounds
        top_bad = np.where(bad, rows, -1).max(axis=0)
        rho = np.maximum(rho, top_bad + 1).astype(np.int32)
    raise RuntimeError(f"no fixed point after {max_rounds} rounds")


# ------------------------------------------------------------------ what it covers


def recoverable(g: np.ndarray, v: np.ndarray, vl: np.ndarray, f: np.ndarray,
                a: LoopAssumptions, veh: VehicleParams = VehicleParams()) -> np.ndarray:
    """States ``(N,)`` from which full braking avoids contact: the ego's brake force follows
    its lag from ``f`` to full braking (the plant's brake lag, drag and rolling resistance
    helping), the leader brakes at ``-leader_accel_mps2[0]`` to a stop, and the gap stays at
    or above the margin until both stand (explicit Euler at the loop's physics step)."""
    return np.asarray(g, float) >= recoverable_gap(v, vl, f, a, veh)


def recoverable_gap(v: np.ndarray, vl: np.ndarray, f: np.ndarray, a: LoopAssumptions,
                    veh: VehicleParams = VehicleParams()) -> np.ndarray:
    """The smallest recoverable gap (:func:`recoverable`) of ``(v, v_l, f)`` ``(N,)``: the
    margin less the lowest the gap gets below its start while both brake (the gap's path does
    not depend on where it starts)."""
    v, vl, f = (np.array(x, float) for x in (v, vl, f))
    decay = math.exp(-a.step_s / veh.brake_time_constant_s)
    full, b_lead = veh.max_brake_decel_mps2, -a.leader_accel_mps2[0]
    change, lowest = np.zeros_like(v), np.zeros_like(v)
    while np.any(v > 0.0):
        f = -full + (f + full) * decay
        v = np.maximum(v + (f - _resistance(v, veh)) * a.step_s, 0.0)
        vl = np.maximum(vl - b_lead * a.step_s, 0.0)
        change = change + (vl - v) * a.step_s
        lowest = np.minimum(lowest, change)
    return a.margin_m - lowest
