"""The lateral closed loop's one-period reachable set, bounded soundly.

The lateral state at a decision is ``(e_y, e_psi, delta, v_y, r)``: the front bumper's offset
from the lane centre [m] (left +), the ego's heading less the lane's [rad] (left +), the
road-wheel angle [rad], the CoG's lateral speed [m/s] and the yaw rate [rad/s], with the ego
speed ``v`` [m/s] and the lane's curvature ``kappa`` [1/m] (a circle, left +). For boxes of
these, :func:`period_bound` bounds, by interval arithmetic, the state one decision period
(ten 0.01 s physics steps) later, for any lane width in the stated range, any camera error in
the stated bounds, any leader (its speed and gap enter the network only; bounded over their
whole ranges, cut into sub-boxes) and any longitudinal command (the tyre force anywhere in
the plant's range):

- the camera: the lines' centre ``(-e_y, -tan e_psi, kappa / 2)`` and half width ``(w/2, 0,
  0)`` in the ego frame, each coefficient within :class:`LateralAssumptions`' camera error
  (the camera's cubic fit of a circle; tests/learn/test_loop_lateral.py checks the bounds
  against :func:`safeil_sumo.sim.sensors.fit_boundary` at every state it draws);
- the network: its lateral outputs ``z`` by interval propagation of the whole network, its x
  outputs by the longitudinal tower's affine forms (:func:`.loop_invariant.plan_bounds`, reused),
  over each leader sub-box; the lane head's y control points
  (:func:`safeil_sumo.core.bspline.lane_following_y`) as centre line + bounded offsets;
- pure pursuit (:func:`safeil_sumo.sim.controller.track_values` on the plan's sampled path):
  the lookahead point lies on the chord of two consecutive path samples at distance ``L_d``
  from the rear axle, so its lateral place is the centre line at its x plus the offsets'
  Bernstein hull over the samples' spline parameters (bounded from the plan's speed bounds);
  the course angle, the understeer feed-forward and the clip;
- the plant (:class:`safeil_sumo.sim.vehicle.Plant`): the steering lag and rate limit, the
  dynamic single track (implicit Euler, linear tyres: a box where a slip angle can reach the
  tyre's saturation is not claimed), the longitudinal speed under any tyre force, the pose.

Where the argument needs it (the lookahead point ahead on the sampled path, the plan's x
increasing there, the dynamic model, linear tyres) a box that cannot be shown to satisfy it is
flagged, not bounded (``LateralImage.ok``). Ego speeds below ``speed_mps[0]`` are not covered.

Every interval is moved outwards by :data:`.loop_invariant.FLOAT_MARGIN` after each operation.
Pure numpy; no SUMO, no torch.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from safeil_sumo.core import bspline
from safeil_sumo.learn import bounds as bnd
from safeil_sumo.learn import loop_invariant as li
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.learn.towers import Y_OUTPUTS
from safeil_sumo.sim.controller import ControllerParams
from safeil_sumo.sim.vehicle import GRAVITY, VehicleParams

Interval = tuple[np.ndarray, np.ndarray]
N_SAMPLES = 51  # the tracker's path samples over the horizon (controller.make_targets)
S_TRIALS = tuple(np.linspace(0.05, 1.0, 20))  # spline parameters the plan's speed is bounded to


@dataclass(frozen=True)
class LateralAssumptions:
    """What the lateral bound assumes of the world around the loop (SI units)."""

    step_s: float = 0.01  # physics step [s]
    steps_per_decision: int = 10  # physics steps per decision period
    speed_mps: tuple[float, float] = (5.0, 40.0)  # ego speeds at decisions covered [m/s]
    curvature_1pm: tuple[float, float] = (-1.0 / 250.0, 1.0 / 250.0)  # lane curvature [1/m]
    lane_width_m: tuple[float, float] = (3.3, 3.8)  # [m]
    # |camera - ideal| of the lines' centre (c0, c1, c2) and half difference (c0, c1, c2)
    # [m, -, 1/m], the ideal centre (-e_y, -tan e_psi, k / 2) and half (w / 2, 0, k^2 w / 4);
    # tests/learn/test_loop_lateral.py checks them at every state it draws
    camera_centre: tuple[float, float, float] = (0.005, 0.0015, 1e-4)
    camera_half: tuple[float, float, float] = (0.005, 0.001, 1e-5)
    speed_sensing_mps: float = 0.2  # |sensed - true| ego speed into the network [m/s]
    leader_speed_mps: tuple[float, float] = (0.0, 40.2)  # sensed leader speed input [m/s]
    gap_m: tuple[float, float] = (2.5, 150.5)  # sensed gap input [m]
    leader_cuts: tuple[int, int] = (8, 8)  # sub-boxes of (leader speed, log gap)
    time_gap_s: tuple[float, float] | None = None  # style input; None: the policy's setting

    def __post_init__(self) -> None:
        if not 0.0 < self.speed_mps[0] <= self.speed_mps[1]:
            raise ValueError("speed_mps must be 0 < lo <= hi")
        if min(self.leader_cuts) < 1:
            raise ValueError("leader_cuts must be >= 1")


@dataclass(frozen=True)
class LateralParts:
    """The parts of the loop the bound covers, as the simulation runs them."""

    vehicle: VehicleParams = field(default_factory=VehicleParams)
    controller: ControllerParams = field(default_factory=ControllerParams)


STATE = ("e_y", "e_psi", "steer", "vy", "r", "v")


@dataclass(frozen=True)
class LateralBox:
    """N boxes: ``(lo, hi)`` arrays ``(N,)`` per coordinate: ``e_y`` [m], ``e_psi`` [rad],
    ``steer`` (road-wheel angle) [rad], ``vy`` [m/s], ``r`` [rad/s], ``v`` (ego speed) [m/s]
    and the lane's ``curvature`` [1/m]."""

    e_y: Interval
    e_psi: Interval
    steer: Interval
    vy: Interval
    r: Interval
    v: Interval
    curvature: Interval

    def __len__(self) -> int:
        return len(self.e_y[0])

    def take(self, rows: np.ndarray | slice) -> LateralBox:
        return LateralBox(*((x[0][rows], x[1][rows]) for x in self._fields()))

    def _fields(self) -> tuple[Interval, ...]:
        return (self.e_y, self.e_psi, self.steer, self.vy, self.r, self.v, self.curvature)


@dataclass(frozen=True)
class LateralImage:
    """The bound one period later, per box: ``final`` the state (curvature unchanged),
    ``e_y_path`` the front bumper's offset at every physics step of the period [m], ``ok``
    (N,) False where the box is not claimed, ``cmd`` the steering commands met [rad]."""

    final: LateralBox
    e_y_path: Interval
    ok: np.ndarray
    cmd: Interval


# ------------------------------------------------------------------ interval arithmetic


_w = li._widen


def _add(a: Interval, b: Interval) -> Interval:
    return _w((a[0] + b[0], a[1] + b[1]))


def _sub(a: Interval, b: Interval) -> Interval:
    return _w((a[0] - b[1], a[1] - b[0]))


def _mul(a: Interval, b: Interval) -> Interval:
    return _w(li._mul(a, b))


def _scale(k: float, a: Interval) -> Interval:
    return _w((np.minimum(k * a[0], k * a[1]), np.maximum(k * a[0], k * a[1])))


def _sq(a: Interval) -> Interval:
    lo2, hi2 = a[0] * a[0], a[1] * a[1]
    across = (a[0] <= 0.0) & (a[1] >= 0.0)
    return _w((np.where(across, 0.0, np.minimum(lo2, hi2)), np.maximum(lo2, hi2)))


def _div_pos(a: Interval, b: Interval) -> Interval:
    """``a / b`` for ``b > 0``."""
    q = np.stack([a[0] / b[0], a[0] / b[1], a[1] / b[0], a[1] / b[1]])
    return _w((q.min(0), q.max(0)))


def _sin(a: Interval) -> Interval:
    """On ``|a| < pi / 2`` (monotone)."""
    return _w((np.sin(a[0]), np.sin(a[1])))


def _cos(a: Interval) -> Interval:
    """On ``|a| < pi / 2``."""
    c0, c1 = np.cos(a[0]), np.cos(a[1])
    across = (a[0] <= 0.0) & (a[1] >= 0.0)
    return _w((np.minimum(c0, c1), np.where(across, 1.0, np.maximum(c0, c1))))


def _mono(fn: Callable[[np.ndarray], np.ndarray], a: Interval) -> Interval:
    """An increasing function of an interval."""
    return _w((fn(a[0]), fn(a[1])))


def _abs_max(a: Interval) -> np.ndarray:
    return np.maximum(np.abs(a[0]), np.abs(a[1]))


def _const(x: float, like: np.ndarray) -> Interval:
    return np.full_like(like, x, dtype=float), np.full_like(like, x, dtype=float)


def _hull_min_max(lo: np.ndarray, hi: np.ndarray) -> Interval:
    """The range of the values of intervals along the last axis."""
    return _w((lo.min(-1), hi.max(-1)))


def _restrict(lo: np.ndarray, hi: np.ndarray, a: np.ndarray, b: np.ndarray) -> Interval:
    """Bounds of a Bernstein polynomial with coefficient intervals ``(K, n + 1)`` over the
    parameter interval ``[a, b]`` ``(K,)`` (``0 <= a <= b <= 1``): de Casteljau splits (convex
    combinations of the coefficients, so they carry intervals soundly), then the coefficients'
    hull."""
    lo, hi = _split_left(lo, hi, b)
    s = np.where(b > 0.0, a / np.where(b > 0.0, b, 1.0), 0.0)
    lo, hi = _split_right(lo, hi, np.clip(s, 0.0, 1.0))
    return _hull_min_max(*_w((lo, hi)))


def _split_left(lo: np.ndarray, hi: np.ndarray, s: np.ndarray) -> Interval:
    """Coefficients ``(K, n + 1)`` of the restriction to ``[0, s]``."""
    s = s[:, None]
    out_lo, out_hi = [lo[:, 0]], [hi[:, 0]]
    for _ in range(lo.shape[1] - 1):
        lo = (1.0 - s) * lo[:, :-1] + s * lo[:, 1:]
        hi = (1.0 - s) * hi[:, :-1] + s * hi[:, 1:]
        out_lo.append(lo[:, 0])
        out_hi.append(hi[:, 0])
    return np.stack(out_lo, 1), np.stack(out_hi, 1)


def _split_right(lo: np.ndarray, hi: np.ndarray, s: np.ndarray) -> Interval:
    """Coefficients ``(K, n + 1)`` of the restriction to ``[s, 1]``."""
    s = s[:, None]
    out_lo, out_hi = [lo[:, -1]], [hi[:, -1]]
    for _ in range(lo.shape[1] - 1):
        lo = (1.0 - s) * lo[:, :-1] + s * lo[:, 1:]
        hi = (1.0 - s) * hi[:, :-1] + s * hi[:, 1:]
        out_lo.append(lo[:, -1])
        out_hi.append(hi[:, -1])
    return np.stack(out_lo[::-1], 1), np.stack(out_hi[::-1], 1)


# ------------------------------------------------------------------ the plan


@dataclass(frozen=True)
class PlanTerms:
    """What pure pursuit reads of the plans of N boxes x M leader sub-boxes (rows ``(N M,)``,
    box-major). The x control points are ``o_k + v_s t_k`` (``o``: the longitudinal tower's
    affine forms ``centre (K, 3)``, ``gens (K, 4, 3)``, ``err (K, 3)``; ``v_s`` the sensed
    speed); the y control points ``cm0 + cm1 x_k + cm2 s_k + u_k`` (the lane centre along the
    plan and the offsets ``u_k = h_k tanh(z_k)``); ``resid`` the degree-6 Bernstein
    coefficients ``(K, 7)`` of ``x(tau)^2 - S(tau)`` (what the centre fit leaves)."""

    centre: np.ndarray
    gens: np.ndarray
    err: np.ndarray
    v_s: Interval
    cm0: Interval
    cm1: Interval
    cm2: Interval
    offsets: Interval  # (K, 3) u_1..u_3 [m]
    resid: Interval  # (K, 7) [m^2]
    horizon_s: float

    def xdot(self, s: np.ndarray) -> Interval:
        """Bounds ``(K,)`` of the plan's x speed dx/dt [m/s] over ``tau in [0, s]``: the
        derivative's quadratic Bernstein coefficients on ``[0, s]``, as affine forms."""
        e0, e1, e2 = (np.array(v, float) for v in ((3, 0, 0), (-3, 3, 0), (0, -3, 3)))
        s = s[:, None]
        coefs = (np.broadcast_to(e0, s.shape[:1] + (3,)), (1 - s) * e0 + s * e1,
                 (1 - s) ** 2 * e0 + 2 * s * (1 - s) * e1 + s * s * e2)
        lo, hi = [], []
        for c in coefs:
            mid = (self.centre * c).sum(-1)
            rad = np.abs(np.einsum("kij,kj->ki", self.gens, c)).sum(-1) + (self.err * np.abs(c)
                                                                             ).sum(-1)
            lo.append(mid - rad)
            hi.append(mid + rad)
        t = self.horizon_s
        return _w((np.min(lo, 0) / t + self.v_s[0], np.max(hi, 0) / t + self.v_s[1]))


def leader_boxes(a: LateralAssumptions) -> tuple[Interval, Interval]:
    """The M leader sub-boxes: sensed leader speed and gap intervals ``(M,)`` each."""
    nv, ng = a.leader_cuts
    ev = np.linspace(*a.leader_speed_mps, nv + 1)
    eg = np.exp(np.linspace(math.log(a.gap_m[0]), math.log(a.gap_m[1]), ng + 1))
    eg[0], eg[-1] = a.gap_m  # the range's own ends, not their exp(log)
    iv, ig = np.meshgrid(np.arange(nv), np.arange(ng), indexing="ij")
    return (ev[iv.ravel()], ev[iv.ravel() + 1]), (eg[ig.ravel()], eg[ig.ravel() + 1])


def lane_features(box: LateralBox, a: LateralAssumptions) -> tuple[Interval, ...]:
    """The camera's lines as centre and half ``(c0, c1, c2)`` intervals ``(N,)`` each:
    ``cm0, cm1, cm2, h0, h1, h2``."""
    dc, dh = a.camera_centre, a.camera_half
    slope = _mono(np.tan, (-box.e_psi[1], -box.e_psi[0]))
    ideal = ((-box.e_y[1], -box.e_y[0]), slope, _scale(0.5, box.curvature))
    cm = tuple(_w((x[0] - d, x[1] + d)) for x, d in zip(ideal, dc, strict=True))
    n = len(box)
    w = (np.full(n, a.lane_width_m[0]), np.full(n, a.lane_width_m[1]))
    # the lines' curvatures k / (1 -+ k w / 2): half their difference ~ k^2 w / 4
    bend = _scale(0.25, _mul(_sq(box.curvature), w))
    half = ((w[0] / 2 - dh[0], w[1] / 2 + dh[0]), (np.full(n, -dh[1]), np.full(n, dh[1])),
            _w((bend[0] - dh[2], bend[1] + dh[2])))
    return (*cm, *half)


def plan_terms(policy: MLPPolicy, box: LateralBox, a: LateralAssumptions) -> PlanTerms:
    """:class:`PlanTerms` of the boxes (rows box-major over :func:`leader_boxes`)."""
    n = len(box)
    (vl_lo, vl_hi), (g_lo, g_hi) = leader_boxes(a)
    m = len(vl_lo)
    cm0, cm1, cm2, h0, h1, h2 = ((np.repeat(iv[0], m), np.repeat(iv[1], m))
                                 for iv in lane_features(box, a))
    lo, hi = np.empty((n * m, 10)), np.empty((n * m, 10))
    lines = ((cm0, h0), (cm1, h1), (cm2, h2))
    for k, (c, h) in enumerate(lines):
        lo[:, k], hi[:, k] = _add(c, h)  # left line
        lo[:, k + 3], hi[:, k + 3] = _sub(c, h)  # right line
    es = a.speed_sensing_mps
    lo[:, 6], hi[:, 6] = np.repeat(box.v[0] - es, m), np.repeat(box.v[1] + es, m)
    lo[:, 7], hi[:, 7] = np.tile(vl_lo, n), np.tile(vl_hi, n)
    lo[:, 8], hi[:, 8] = np.tile(g_lo, n), np.tile(g_hi, n)
    tg = a.time_gap_s or (policy.style["time_gap_s"],) * 2
    lo[:, 9], hi[:, 9] = tg
    pb = li.plan_bounds(policy, lo, hi)
    v_s = (pb.v_sensed_lo, pb.v_sensed_hi)
    rad = np.abs(pb.gens).sum(1) + pb.err
    o = _w((pb.centre - rad, pb.centre + rad))  # (K, 3)
    times = policy.residual_times
    assert times is not None  # li.plan_bounds refuses a policy without the residual mode
    x = _w((o[0] + v_s[0][:, None] * times, o[1] + v_s[1][:, None] * times))
    resid = _residual(pb, v_s, times)
    # the offsets' room h_k (lane_following_y), floored at 0
    xs = _w((x[0] @ bspline.LANE_FREE.T, x[1] @ bspline.LANE_FREE.T))  # (K, 21), basis >= 0
    xs2 = _sq(xs)
    fit_pos, fit_neg = np.maximum(bspline.LANE_FIT, 0.0), np.minimum(bspline.LANE_FIT, 0.0)
    s_fit = _w((xs2[0] @ fit_pos.T + xs2[1] @ fit_neg.T, xs2[1] @ fit_pos.T + xs2[0] @ fit_neg.T))
    c2l, c2r = _add(cm2, h2), _sub(cm2, h2)
    bend = _w((np.maximum(_abs_min(c2l), _abs_min(c2r)),
               np.maximum(_abs_max(c2l), _abs_max(c2r))))
    mag = (_abs_min(resid), _abs_max(resid))
    weight = bspline.LANE_FIT_WEIGHT
    allowance = _w(((mag[0][:, 1:] * weight).max(-1), (mag[1][:, 1:] * weight).max(-1)))
    col = lambda iv: (iv[0][:, None], iv[1][:, None])
    room = _sub(_add(_add(col(h0), _mul(col(h1), x)), _mul(col(h2), s_fit)),
                col(_add(_const(policy.lane_keep_m, h0[0]), _mul(bend, allowance))))
    h = (np.maximum(room[0], 0.0), np.maximum(room[1], 0.0))
    z = _lateral_z(policy, lo, hi)
    z = (np.maximum(z[0], pb.z_lo), np.minimum(z[1], pb.z_hi))  # both bounds hold
    t = _mono(np.tanh, z)  # the lateral outputs (K, 3)
    return PlanTerms(pb.centre, pb.gens, pb.err, v_s, cm0, cm1, cm2, _mul(h, t), resid,
                     policy.horizon)


def _lateral_tower(policy: MLPPolicy) -> list:
    """The y outputs' own network (the second half of every hidden layer, reading all 10
    inputs); refused unless every weight it leaves out is 0 (a towers checkpoint)."""
    layers = li._network(policy)
    li._longitudinal_tower(layers)  # checks the towers' zeros
    widths = [layers[0].weight.shape[1], *(layer.weight.shape[0] for layer in layers[:-1])]
    rows = [np.arange(w // 2, w) for w in widths[1:]] + [np.array(Y_OUTPUTS)]
    cols = [np.arange(widths[0])] + [np.arange(w // 2, w) for w in widths[1:]]
    return [bnd.Layer(layer.weight[np.ix_(r, c)], layer.bias[r], layer.activation[r])
            for layer, r, c in zip(layers, rows, cols, strict=True)]


def _lateral_z(policy: MLPPolicy, lo: np.ndarray, hi: np.ndarray) -> Interval:
    """Bounds ``(K, 3)`` of the lateral outputs over feature boxes ``(K, 10)``: affine forms of
    the lateral tower (:func:`.loop_invariant._affine_forms`, tanh by parallel lines)."""
    centre, gens, err = li._affine_forms(_lateral_tower(policy), lo, hi)
    rad = np.abs(gens).sum(1) + err
    return _w((centre - rad, centre + rad))


def _abs_min(a: Interval) -> np.ndarray:
    across = (a[0] <= 0.0) & (a[1] >= 0.0)
    return np.where(across, 0.0, np.minimum(np.abs(a[0]), np.abs(a[1])))


def _residual(pb: li.PlanBounds, v_s: Interval, times: np.ndarray) -> Interval:
    """Degree-6 coefficients ``(K, 7)`` of ``x(tau)^2 - S(tau)`` for ``x_k = o_k + v_s t_k``:
    ``R_k(x) = 2 v_s (Q_k t) . o + o^T Q_k o`` (``R_k(t) = 0``: a constant-speed plan's square
    is a quadratic, fitted exactly), with ``o = c + D xi`` the affine forms (``xi`` in
    ``[-1, 1]^7``: the 4 generators and the 3 independent errors), so the outputs' shared
    dependence on the inputs is kept: ``c^T Q c + 2 c^T Q D xi + xi^T D^T Q D xi``."""
    q = bspline.LANE_FIT_RESIDUAL  # (7, 3, 3)
    c = pb.centre  # (K, 3)
    d = np.concatenate([np.transpose(pb.gens, (0, 2, 1)),
                        np.einsum("ki,ij->kij", pb.err, np.eye(3))], 2)  # (K, 3, 7)
    lo, hi = [], []
    for k in range(7):
        qk = q[k]
        qt = qk @ times
        lin_c = c @ qt
        lin_r = np.abs(np.einsum("kij,i->kj", d, qt)).sum(-1)
        lin = _w((lin_c - lin_r, lin_c + lin_r))
        cqc = np.einsum("ki,ij,kj->k", c, qk, c)
        cross = 2.0 * np.abs(np.einsum("ki,ij,kjl->kl", c, qk, d)).sum(-1)
        p = np.einsum("kia,ij,kjb->kab", d, qk, d)
        diag = np.einsum("kaa->ka", p)
        off = np.abs(p).sum((1, 2)) - np.abs(diag).sum(-1)
        quad = (cqc - cross + np.minimum(diag, 0.0).sum(-1) - off,
                cqc + cross + np.maximum(diag, 0.0).sum(-1) + off)
        r = _add(_scale(2.0, _mul(v_s, lin)), _w(quad))
        lo.append(r[0])
        hi.append(r[1])
    return np.stack(lo, 1), np.stack(hi, 1)


# ------------------------------------------------------------------ one physics step


@dataclass(frozen=True)
class _State:
    """The plant in the plan's frame (origin: the front bumper at the decision, x along the
    ego's heading then): CoG ``X, Y`` [m], yaw ``psi`` [rad], ``vx, vy`` [m/s], ``r`` [rad/s],
    ``steer`` [rad]; intervals ``(N,)``."""

    X: Interval
    Y: Interval
    psi: Interval
    vx: Interval
    vy: Interval
    r: Interval
    steer: Interval


def _rep(x: Interval, m: int) -> Interval:
    return np.repeat(x[0], m), np.repeat(x[1], m)


def steer_command(terms: PlanTerms, st: _State, m: int, parts: LateralParts
                  ) -> tuple[Interval, np.ndarray]:
    """Bounds ``(N,)`` of pure pursuit's road-wheel command over the M plans of each box, and
    where the argument holds (else the box is not claimed)."""
    veh, ctl = parts.vehicle, parts.controller
    lr, t_h = veh.lr_m, terms.horizon_s
    X, Y, psi, vx, vy, r = (_rep(x, m) for x in (st.X, st.Y, st.psi, st.vx, st.vy, st.r))
    cpsi, spsi = _cos(psi), _sin(psi)
    px, py = _sub(X, _scale(lr, cpsi)), _sub(Y, _scale(lr, spsi))
    ok = vx[0] > 1.0  # the course angle is used (vx > 1)
    heading = psi
    if ctl.use_course_angle:
        heading = _add(psi, _mono(np.arctan, _div_pos(_sub(vy, _scale(lr, r)), vx)))
    ld = _mono(lambda v: np.clip(ctl.lookahead_gain_s * v + ctl.lookahead_min_m,
                                 ctl.lookahead_min_m, ctl.lookahead_max_m), vx)
    # the ego's rear axle inside the lookahead circle of the plan's origin: the path's first
    # sample is inside, so the point is a crossing ahead (not the closest point, not the end)
    ok &= np.hypot(_abs_max(px), _abs_max(py)) < ld[0]
    # the samples the crossing can lie between: x in [x_down, x_up]; x(tau) increasing there.
    # Tried on [0, s] for growing s (a stopping plan turns back late: the first s that holds),
    # then on [0, tau_b + a sample] (tighter speed bounds)
    gap = 1.0 / (N_SAMPLES - 1)
    fine = np.zeros_like(ok)
    xd = (np.zeros_like(vx[0]), np.zeros_like(vx[0]))
    dx, x_up, tau_b = (np.zeros_like(vx[0]) for _ in range(3))
    for s in (*S_TRIALS, None):
        s_cap = np.full_like(vx[0], s) if s is not None else np.minimum(tau_b + gap + 1e-9, 1.0)
        xd_s = terms.xdot(s_cap)
        dx_s = xd_s[1] * t_h / (N_SAMPLES - 1)
        x_up_s = px[1] + ld[1] + dx_s
        tau_s = x_up_s / (t_h * np.maximum(xd_s[0], 1e-9))
        good = (xd_s[0] > 0.0) & (tau_s + gap <= s_cap)
        take = good & (~fine if s is not None else fine)
        xd = (np.where(take, xd_s[0], xd[0]), np.where(take, xd_s[1], xd[1]))
        dx, x_up, tau_b = (np.where(take, new, old) for new, old in
                           ((dx_s, dx), (x_up_s, x_up), (tau_s, tau_b)))
        if s is not None:
            fine |= take
    ok &= fine
    tau_b = np.where(fine, tau_b, 1.0)
    zero = np.zeros_like(tau_b)
    # every sample up to x_up lies within delta of the axle sideways
    b0_far = (1.0 - tau_b) ** 3
    one_minus_b0 = _w((zero, 1.0 - b0_far))
    off = _restrict(*_bern_offsets(terms), zero, tau_b)
    res = _restrict(*terms.resid, zero, tau_b)
    x_all = _w((zero, np.maximum(x_up, 0.0)))
    y_all = _add(_add(_mul(terms.cm0, one_minus_b0), _mul(terms.cm1, x_all)),
                 _add(_mul(terms.cm2, _sub(_sq(x_all), res)), off))
    delta = _abs_max(_sub(y_all, py))
    ok &= delta < 0.9 * ld[0]
    delta = np.where(ok, delta, 0.0)
    ell_lo = np.sqrt(np.maximum(ld[0] ** 2 - delta ** 2, 0.0)) * (1.0 - 1e-12)
    x_down = px[0] + ell_lo - dx
    tau_a = np.minimum(np.maximum(x_down, 0.0) / (t_h * np.maximum(xd[1], 1e-9)), tau_b)
    beta = _w(((1.0 - tau_b) ** 3, (1.0 - tau_a) ** 3))
    off = _restrict(*_bern_offsets(terms), tau_a, tau_b)
    res = _restrict(*terms.resid, tau_a, tau_b)
    gx = _w((px[0] + ell_lo, px[1] + ld[1]))
    sigma = _sub(_add(_sq(gx), (zero, dx * dx / 4.0)), res)
    lat = _sub(_add(_add(_mul(terms.cm0, _sub(_const(1.0, zero), beta)), _mul(terms.cm1, px)),
                    _add(_mul(terms.cm2, sigma), off)), py)
    ch, sh = _cos(heading), _sin(heading)
    rho = _w((np.sqrt(np.maximum(1.0 - (delta / ld[0]) ** 2, 0.0)), np.ones_like(zero)))
    ld2 = _sq(ld)
    kappa = _scale(2.0, _add(_div_pos(_mul(rho, _sub(_mul(ch, terms.cm1), sh)), ld),
                             _div_pos(_mul(ch, lat), ld2)))
    steer = _mono(lambda k: np.arctan(veh.wheelbase_m * k), kappa)
    if ctl.understeer_feedforward:
        steer = _add(steer, _scale(veh.understeer_gradient, _mul(_sq(vx), kappa)))
    steer = (np.clip(steer[0], -veh.max_steer_rad, veh.max_steer_rad),
             np.clip(steer[1], -veh.max_steer_rad, veh.max_steer_rad))
    cmd = (steer[0].reshape(-1, m).min(1), steer[1].reshape(-1, m).max(1))
    return cmd, np.asarray(ok.reshape(-1, m).all(1))


def _bern_offsets(terms: PlanTerms) -> Interval:
    """The offsets' cubic Bernstein coefficients ``(K, 4)`` (the origin's is 0)."""
    zero = np.zeros((len(terms.offsets[0]), 1))
    return (np.concatenate([zero, terms.offsets[0]], 1),
            np.concatenate([zero, terms.offsets[1]], 1))


def plant_step(st: _State, cmd: Interval, parts: LateralParts, dt: float
               ) -> tuple[_State, np.ndarray]:
    """One :meth:`Plant.step` of the boxes under the steering command interval, any tyre force
    in the plant's range; and where the dynamic model with linear tyres holds."""
    p = parts.vehicle
    m, lf, lr, iz = p.mass_kg, p.lf_m, p.lr_m, p.yaw_inertia_kgm2
    gain = 1.0 - math.exp(-dt / p.steer_time_constant_s)
    max_d = p.max_steer_rate_radps * dt

    def actuator(c: np.ndarray, d: np.ndarray) -> np.ndarray:  # increasing in both
        c = np.clip(c, -p.max_steer_rad, p.max_steer_rad)
        return d + np.clip((c - d) * gain, -max_d, max_d)

    delta = _w((actuator(cmd[0], st.steer[0]), actuator(cmd[1], st.steer[1])))
    u = st.vx
    ok = u[0] >= p.kinematic_speed_high_mps  # the dynamic model alone
    cf, cr = p.cornering_stiffness_front_npr, p.cornering_stiffness_rear_npr
    fzf = p.front_axle_load_fraction * m * GRAVITY
    fzr = m * GRAVITY - fzf
    mu = p.friction_coefficient
    alpha_f = _sub(delta, _div_pos(_add(st.vy, _scale(lf, st.r)), u))
    alpha_r = _div_pos(_sub(_scale(lr, st.r), st.vy), u)
    ok &= (cf * _abs_max(alpha_f) < mu * fzf) & (cr * _abs_max(alpha_r) < mu * fzr)
    inv_u = _div_pos(_const(1.0, u[0]), u)
    k_lat = lf * cf - lr * cr
    m11 = _add(_const(1.0, u[0]), _scale(dt * (cf + cr) / m, inv_u))
    m22 = _add(_const(1.0, u[0]), _scale(dt * (lf * lf * cf + lr * lr * cr) / iz, inv_u))
    m12 = _add(_scale(dt * k_lat / m, inv_u), _scale(dt, u))
    m21 = _scale(dt * k_lat / iz, inv_u)
    det = _sub(_mul(m11, m22), _mul(m12, m21))
    ok &= det[0] > 0.0
    det = (np.where(ok, det[0], 1.0), np.where(ok, det[1], 1.0))
    g1, g2 = dt * cf / m, dt * lf * cf / iz
    bv = _sub(_scale(g1, m22), _scale(g2, m12))
    br = _sub(_scale(g2, m11), _scale(g1, m21))
    vy_new = _div_pos(_add(_sub(_mul(m22, st.vy), _mul(m12, st.r)), _mul(bv, delta)), det)
    r_new = _div_pos(_add(_sub(_mul(m11, st.r), _mul(m21, st.vy)), _mul(br, delta)), det)
    fyf = _scale(cf, _sub(delta, _div_pos(_add(vy_new, _scale(lf, r_new)), u)))
    drag = 0.5 * p.air_density_kgm3 * p.drag_coefficient * p.frontal_area_m2
    res = _w((drag * np.maximum(u[0], 0.0) ** 2 + p.rolling_resistance * m * GRAVITY,
              drag * u[1] ** 2 + p.rolling_resistance * m * GRAVITY))
    fx = _const(0.0, u[0])
    fx = (fx[0] - p.max_brake_force_n, fx[1] + p.max_drive_force_n)
    ax = _add(_scale(1.0 / m, _sub(_sub(fx, res), _mul(fyf, _sin(delta)))), _mul(st.vy, st.r))
    vx_new = _add(u, _scale(dt, ax))
    vx_new = (np.maximum(vx_new[0], 0.0), np.maximum(vx_new[1], 0.0))
    psi = _add(st.psi, _scale(dt, r_new))
    c, s = _cos(psi), _sin(psi)
    X = _add(st.X, _scale(dt, _sub(_mul(vx_new, c), _mul(vy_new, s))))
    Y = _add(st.Y, _scale(dt, _add(_mul(vx_new, s), _mul(vy_new, c))))
    return _State(X, Y, psi, vx_new, vy_new, r_new, delta), ok


def lane_state(st: _State, box: LateralBox, veh: VehicleParams) -> tuple[Interval, Interval]:
    """The front bumper's offset and the heading error against the lane (a circle of the
    box's curvature through the decision's projection point) ``(N,)`` each."""
    d = veh.cog_to_front_bumper_m
    fx = _add(st.X, _scale(d, _cos(st.psi)))
    fy = _add(st.Y, _scale(d, _sin(st.psi)))
    ce, se = _cos(box.e_psi), _sin(box.e_psi)
    q = _add(box.e_y, _add(_mul(fx, se), _mul(fy, ce)))  # along the lane's normal
    s = _sub(_mul(fx, ce), _mul(fy, se))  # along its tangent
    k = box.curvature
    # e_y = (1 - |k| |F - O|) / k = (2 q - k (s^2 + q^2)) / (1 + sqrt(k^2 s^2 + (1 - k q)^2))
    one = _const(1.0, q[0])
    one_kq = _sub(one, _mul(k, q))
    root = _mono(np.sqrt, _add(_sq(_mul(k, s)), _sq(one_kq)))
    e_y = _div_pos(_sub(_scale(2.0, q), _mul(k, _add(_sq(s), _sq(q)))), _add(one, root))
    turn = _mono(np.arctan, _div_pos(_mul(k, s), one_kq))
    return e_y, _sub(_add(st.psi, box.e_psi), turn)


def period_bound(policy: MLPPolicy, box: LateralBox, a: LateralAssumptions = LateralAssumptions(),
                 parts: LateralParts = LateralParts(), chunk: int = 2048) -> LateralImage:
    """The lateral state one decision period after each of the N boxes (:class:`LateralImage`),
    in chunks of ``chunk`` boxes."""
    if policy.lateral_mode != "lane" or policy.residual_times is None:
        raise ValueError(f"{policy.name}: the lateral bound needs the lane head and residual x")
    # floats: integer bounds (speeds given as whole numbers) would make the working arrays
    # (np.zeros_like of them) integers and truncate
    box = LateralBox(*((np.asarray(x[0], float), np.asarray(x[1], float)) for x in box._fields()))
    parts_out = [_period(policy, box.take(slice(i, i + chunk)), a, parts)
                 for i in range(0, len(box), chunk)]
    cat = lambda xs: (np.concatenate([x[0] for x in xs]), np.concatenate([x[1] for x in xs]))
    final = LateralBox(*(cat([getattr(p.final, f) for p in parts_out])
                         for f in (*STATE, "curvature")))
    return LateralImage(final, cat([p.e_y_path for p in parts_out]),
                        np.concatenate([p.ok for p in parts_out]), cat([p.cmd for p in parts_out]))


def _period(policy: MLPPolicy, box: LateralBox, a: LateralAssumptions, parts: LateralParts
            ) -> LateralImage:
    veh = parts.vehicle
    terms = plan_terms(policy, box, a)
    m = int(np.prod(a.leader_cuts))
    n = len(box)
    zero = np.zeros(n)
    d = veh.cog_to_front_bumper_m
    st = _State((zero - d, zero - d), (zero, zero), (zero, zero), box.v, box.vy, box.r, box.steer)
    ok = (box.v[0] >= a.speed_mps[0]) & (box.v[1] <= a.speed_mps[1])
    e_lo, e_hi = box.e_y[0].copy(), box.e_y[1].copy()
    c_lo, c_hi = np.full(n, np.inf), np.full(n, -np.inf)
    for _ in range(a.steps_per_decision):
        cmd, fine = steer_command(terms, st, m, parts)
        st, fine_plant = plant_step(st, cmd, parts, a.step_s)
        ok &= fine & fine_plant
        c_lo, c_hi = np.minimum(c_lo, cmd[0]), np.maximum(c_hi, cmd[1])
        e_y, _ = lane_state(st, box, veh)
        e_lo, e_hi = np.minimum(e_lo, e_y[0]), np.maximum(e_hi, e_y[1])
    e_y, e_psi = lane_state(st, box, veh)
    final = LateralBox(e_y, e_psi, st.steer, st.vy, st.r, st.vx, box.curvature)
    return LateralImage(final, (e_lo, e_hi), ok, (c_lo, c_hi))
