"""The maths of certification: the envelope, the planner as one network of envelope
coordinates, sound lower bounds of its margins over boxes, and the boxes' envelope volume.

What a margin is, for every state of a box of the envelope (:class:`CertEnvelope`) and the plan
the network outputs there (one plan, open loop, exact features):

- the **leader margin** ``d + v_lead t_i - x_i [- (gap_min + time_gap v_x)] >= 0`` at the three
  control points' Greville times ``t_i = i T_h / 3`` (the leader at constant speed; since
  ``d + v_lead t`` is linear in tau, these are the margin's exact Bernstein coefficients, so the
  whole spline stays behind the predicted leader), the bracket as in training
  (:func:`safeil_sumo.learn.losses.envelope_barrier_terms`: only where braking can reach it);
- the **lane margin**: the 2 x 6 degree-6 Bernstein coefficients k = 1..6 of the left and right
  lateral margins along the spline (:func:`safeil_sumo.core.bspline.lateral_margin_bernstein`, vehicle
  track T from the checkpoint's training config) are >= 0, so the whole planned path is inside the
  lane (k = 0, the car itself, does not depend on the plan; the envelope keeps it >= 0.17 m).

How (all pure numpy, :mod:`safeil_sumo.learn.bounds`): the envelope coordinates ``z`` (lane
width, lateral offset, heading, curvature, ego speed, relative speed, gap[, style]) map to the
network's inputs by one affine layer with a ReLU on the leader speed (``v_lead = max(v + dv,
0)``); the features ride along the hidden layers as identity units and the residual output
mode's ``v_x t_i`` is folded into the output layer, so the margins are functions of one network's
output. The leader margin is linear in it; the lane margins contain the products ``c1 x`` and
``c2 x_i x_j``, enclosed by McCormick planes (centred: ``a b >= a_m b + b_m a - a_m b_m - Δa Δb
/ 4``; squares by tangents and chords) over the intervals CROWN gives the outputs, i.e. interval
arithmetic on the Bernstein coefficient expressions, kept linear so CROWN can bound the result.
The linear objective is bounded by CROWN back-substitution and by intervals; the larger lower
bound wins. A lane-following head's lane rows (:func:`lane_head_lane_lower`) need only the x
control points' bounds: its offsets' room less the centre fit's allowance keeps every row above
the start's and the clearance's shares wherever that room is positive. A margin counts as
proven on a box when its lower bound is at least :data:`FLOAT_MARGIN_M`, an explicit float
margin (no outward rounding).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo.core.bspline import (
    ELEVATE_3_TO_6,
    LANE_FIT_RESIDUAL,
    LANE_FIT_WEIGHT,
    PRODUCT_WEIGHTS,
    lateral_margin_bernstein,
)
from safeil_sumo.core.features import N_FEATURES
from safeil_sumo.learn import bounds as bnd
from safeil_sumo.learn.envelope import EnvelopeConfig
from safeil_sumo.learn.inference import MLPPolicy

FLOAT_MARGIN_M = 1e-6  # a margin is proven where its sound lower bound is at least this [m]
MARGINS = ("leader", "lane")
ROW_NAMES = (*(f"leader_{i}" for i in (1, 2, 3)), *(f"left_b{k}" for k in range(1, 7)),
             *(f"right_b{k}" for k in range(1, 7)))
MARGIN_ROWS = {"leader": slice(0, 3), "lane": slice(3, 15)}
DIM_NAMES = ("lane_width_m", "lateral_offset_m", "heading_error", "curvature_1pm",
             "ego_speed_mps", "relative_speed_mps", "gap_m")
STYLE_DIM = "time_gap_s"
W, OFF, HEAD, CURV, V, DV, GAP = range(7)
_SAMPLING = EnvelopeConfig()


class CertifyError(ValueError):
    """A checkpoint or setting that cannot be certified (one line for the command line)."""


@dataclass(frozen=True)
class CertEnvelope:
    """The states the certificate covers: those :func:`safeil_sumo.learn.envelope.sample_states`
    draws for the envelope barrier (defaults read from :class:`EnvelopeConfig`, so they cannot
    drift apart). States outside are not claimed.

    Lane lines in the ego frame: ``c0l = w/2 - offset``, ``c0r = -w/2 - offset``, both lines'
    ``c1 = heading_error`` and ``c2 = curvature / 2``. Leader: ``v_lead = max(v_x + dv, 0)``.
    """

    lane_width_m: tuple[float, float] = _SAMPLING.lane_width_m  # lane width w [m]
    lateral_offset_m: tuple[float, float] = _SAMPLING.lateral_offset_m  # ego left of centre [m]
    heading_error: tuple[float, float] = _SAMPLING.heading_error  # lane slope c1 [-]
    curvature_1pm: tuple[float, float] = _SAMPLING.curvature_1pm  # lane curvature 2 c2 [1/m]
    ego_speed_mps: tuple[float, float] = _SAMPLING.ego_speed_mps  # ego speed v_x [m/s]
    relative_speed_mps: tuple[float, float] = _SAMPLING.relative_speed_mps  # dv = v_lead - v_x
    # before clipping at a stopped leader [m/s]
    gap_m: tuple[float, float] = _SAMPLING.gap_m  # bumper gap d [m]; volume measured in log d,
    # as the sampler draws it log-uniform
    brake_mps2: float = _SAMPLING.brake_mps2  # recoverable: d > closing^2 / (2 brake), closing
    # = max(v_x - v_lead, 0) [m/s^2]
    radar_range_m: float = _SAMPLING.radar_range_m  # "no leader": the leader at this gap at the
    # ego's speed [m]
    no_leader_share: float = _SAMPLING.no_leader_share  # weight of the no-leader part [-]
    time_gap_s: tuple[float, float] | None = None  # style input range [s]; None: the
    # checkpoint's default setting (a style-conditioned checkpoint only)

    def __post_init__(self) -> None:
        for name in (*DIM_NAMES, "time_gap_s"):
            r = getattr(self, name)
            if r is None:
                continue
            if len(r) != 2 or not (np.isfinite(r[0]) and np.isfinite(r[1])) or r[1] < r[0]:
                raise CertifyError(f"envelope {name} must be a finite (lo, hi) with lo <= hi, "
                                   f"got {r}")
        if self.gap_m[0] <= 0:
            raise CertifyError(f"envelope gap_m must be > 0, got {self.gap_m}")
        if not 0.0 <= self.no_leader_share <= 1.0:
            raise CertifyError(f"no_leader_share must be in [0, 1], got {self.no_leader_share}")

    @property
    def dims(self) -> tuple[str, ...]:
        return DIM_NAMES + ((STYLE_DIM,) if self.time_gap_s is not None else ())

    def root_boxes(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``{"leader": (lo, hi), "free": (lo, hi)}``: the leader states and the no-leader
        states (relative speed 0 and gap at the radar range: zero-width dimensions)."""
        lo = np.array([getattr(self, n)[0] for n in self.dims], float)
        hi = np.array([getattr(self, n)[1] for n in self.dims], float)
        free_lo, free_hi = lo.copy(), hi.copy()
        free_lo[DV] = free_hi[DV] = 0.0
        free_lo[GAP] = free_hi[GAP] = self.radar_range_m
        return {"leader": (lo, hi), "free": (free_lo, free_hi)}

    def part_weights(self) -> dict[str, float]:
        return {"leader": 1.0 - self.no_leader_share, "free": self.no_leader_share}

    def features(self, z: np.ndarray) -> np.ndarray:
        """Planner features ``(..., 9)`` at envelope coordinates ``z (..., len(dims))``."""
        z = np.asarray(z, float)
        w, off, c1, c2 = z[..., W], z[..., OFF], z[..., HEAD], 0.5 * z[..., CURV]
        v = z[..., V]
        return np.stack([0.5 * w - off, c1, c2, -0.5 * w - off, c1, c2, v,
                         np.maximum(v + z[..., DV], 0.0), z[..., GAP]], axis=-1)

    def recoverable(self, z: np.ndarray) -> np.ndarray:
        """``(...)`` bool: braking at ``brake_mps2`` keeps the ego behind the leader."""
        z = np.asarray(z, float)
        closing = np.clip(np.minimum(-z[..., DV], z[..., V]), 0.0, None)
        return z[..., GAP] > closing * closing / (2.0 * self.brake_mps2)


@dataclass(frozen=True)
class Properties:
    """The margins' settings, from the checkpoint's training config (losses.BarrierConfig)."""

    horizon_s: float  # plan horizon T_h [s]; control point i at t_i = i T_h / 3
    track_m: float = 1.76  # vehicle track T [m]: the lane margin keeps T/2 to each line
    gap_min_m: float = 0.0  # extra leader gap [m] (where braking can reach it)
    time_gap_margin_s: float = 0.0  # extra leader gap per ego speed [s] (idem)
    brake_mps2: float = 6.0  # the feasibility of that extra gap, as in training [m/s^2]
    # a lane-following lateral head (architecture "lateral_mode": "lane"): its offsets'
    # bound, half the track plus a clearance [m]; None: the paper's head (y control points)
    lane_keep_m: float | None = None

    @classmethod
    def from_metadata(cls, meta: dict, brake_mps2: float = 6.0) -> Properties:
        tc = meta.get("train_config") or {}
        arch = meta.get("architecture") or {}
        keep = float(arch["lane_keep_m"]) if arch.get("lateral_mode") == "lane" else None
        return cls(horizon_s=float(meta["horizon_s"]), track_m=float(tc.get("track", 1.76)),
                   gap_min_m=float(tc.get("gap_min", 0.0)),
                   time_gap_margin_s=float(tc.get("time_gap", 0.0)), brake_mps2=brake_mps2,
                   lane_keep_m=keep)

    @property
    def times(self) -> np.ndarray:
        return np.arange(1, 4) * (self.horizon_s / 3.0)


# ------------------------------------------------------------------ the network to bound


def planner_layers(policy: MLPPolicy, style_range: bool) -> list[bnd.Layer]:
    """The planner as one network of envelope coordinates ``z`` -> ``[plan (6); features (9)]``.

    Layer 0 maps ``z`` to the features (+ style) with a ReLU on the leader speed; every hidden
    layer carries the 9 features along as identity units; the output layer adds the residual
    ``v_x t_i`` to the x control points. The plan's order is ``x1, y1, x2, y2, x3, y3`` [m].
    """
    n_z = len(DIM_NAMES) + int(style_range)
    n_in = N_FEATURES + int(style_range)
    a0 = np.zeros((n_in, n_z))
    a0[0, W], a0[0, OFF] = 0.5, -1.0
    a0[1, HEAD] = a0[4, HEAD] = 1.0
    a0[2, CURV] = a0[5, CURV] = 0.5
    a0[3, W], a0[3, OFF] = -0.5, -1.0
    a0[6, V] = 1.0
    a0[7, V] = a0[7, DV] = 1.0
    a0[8, GAP] = 1.0
    if style_range:
        a0[9, len(DIM_NAMES)] = 1.0
    codes0 = np.zeros(n_in, np.int8)
    codes0[7] = bnd.RELU
    layers = [bnd.Layer(a0, np.zeros(n_in), codes0)]
    act = bnd.ACTIVATIONS[policy.activation]
    affine = policy.affine_layers(style_input=style_range)
    eye = np.eye(N_FEATURES)
    prev = n_in  # width of the previous layer's output
    for j, (w, b) in enumerate(affine[:-1]):
        n_h = w.shape[0]
        top = w if j == 0 else np.concatenate([w, np.zeros((n_h, N_FEATURES))], axis=1)
        carry = np.zeros((N_FEATURES, prev))
        carry[:, -N_FEATURES:] = eye if j > 0 else 0.0
        if j == 0:
            carry[:, :N_FEATURES] = eye
        layers.append(bnd.Layer(np.concatenate([top, carry]), np.concatenate(
            [b, np.zeros(N_FEATURES)]), np.concatenate([np.full(n_h, act, np.int8),
                                                        np.zeros(N_FEATURES, np.int8)])))
        prev = n_h + N_FEATURES
    w, b = affine[-1]
    residual = np.zeros((6, N_FEATURES))
    times = policy.residual_times
    if times is not None:
        residual[[0, 2, 4], 6] = times
    if len(affine) == 1:  # no hidden layer: the features are the input itself
        top = np.concatenate([w[:, :N_FEATURES] + residual, w[:, N_FEATURES:]], axis=1)
        carry = np.concatenate([eye, np.zeros((N_FEATURES, prev - N_FEATURES))], axis=1)
    else:
        top = np.concatenate([w, residual], axis=1)
        carry = np.concatenate([np.zeros((N_FEATURES, w.shape[1])), eye], axis=1)
    layers.append(bnd.Layer(np.concatenate([top, carry]), np.concatenate(
        [b, np.zeros(N_FEATURES)]), np.zeros(6 + N_FEATURES, np.int8)))
    return layers


# ------------------------------------------------------------------ the margins


def reference_margins(policy: MLPPolicy, features: np.ndarray, props: Properties
                      ) -> np.ndarray:
    """The 15 margins (:data:`ROW_NAMES`) ``(M, 15)`` [m] of the network's actual plans at
    ``features (M, 9)``: :meth:`MLPPolicy.plan` and the numpy reference formulas."""
    f = np.asarray(features, float)
    cp = policy.plan(f)
    out = np.empty((len(f), 15))
    out[:, 0:3] = f[:, 8, None] + f[:, 7, None] * props.times - cp[..., 0]
    extra = _lead_extra(f[:, 6], f[:, 7], f[:, 8], props)
    out[:, 0:3] -= extra[:, None]
    half = 0.5 * props.track_m
    out[:, 3:9] = lateral_margin_bernstein(cp, f[:, 0:3], -half)[:, 1:]
    out[:, 9:15] = -lateral_margin_bernstein(cp, f[:, 3:6], half)[:, 1:]
    return out


def _lead_extra(v: np.ndarray, v_lead: np.ndarray, gap: np.ndarray, props: Properties
                ) -> np.ndarray:
    """The extra leader gap [m] where braking can still reach it, else 0 (as in training)."""
    margin = props.gap_min_m + props.time_gap_margin_s * v
    closing = np.clip(v - v_lead, 0.0, None)
    feasible = gap - margin > closing * closing / (2.0 * props.brake_mps2)
    return np.where(feasible, margin, 0.0)


def _interval_product(al, ah, bl, bh):
    c = np.stack([al * bl, al * bh, ah * bl, ah * bh])
    return c.min(0), c.max(0)


def _product_intervals(x_lo: np.ndarray, x_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intervals ``(N, 3, 3)`` x2 of the products ``x_i x_j`` over boxes ``[x_lo, x_hi] (N, 3)``
    (the squares exactly)."""
    p_lo, p_hi = _interval_product(x_lo[:, :, None], x_hi[:, :, None], x_lo[:, None, :],
                                   x_hi[:, None, :])
    diag = np.arange(3)
    p_lo[:, diag, diag] = np.where((x_lo > 0) | (x_hi < 0),
                                   np.minimum(x_lo ** 2, x_hi ** 2), 0.0)
    p_hi[:, diag, diag] = np.maximum(x_lo ** 2, x_hi ** 2)
    return p_lo, p_hi


def _width_shares(plan: bnd.LinearBound, width: np.ndarray, outputs: slice) -> np.ndarray:
    """Each box dimension's share ``(N, n_z)`` of how wide the plan outputs ``outputs`` are:
    their linear bounds' sensitivity to it (``plan``: CROWN of ``[eye(6); -eye(6)]``) times its
    width ``(N, n_z)``, normalised."""
    sens = np.abs(plan.coef[:, outputs]).sum(axis=1) + np.abs(plan.coef[:, 6:12][:, outputs]
                                                               ).sum(axis=1)
    infl = sens * width
    return infl / np.maximum(infl.sum(axis=1, keepdims=True), 1e-300)


def property_objective(props: Properties, f_lo: np.ndarray, f_hi: np.ndarray,
                       y_lo: np.ndarray, y_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                    np.ndarray]:
    """Linear lower bounds of the 15 margins in the network's output ``[plan; features]``:
    ``margin >= C @ out + const`` for every output in the box whose features lie in
    ``[f_lo, f_hi] (N, 9)`` and plans in ``[y_lo, y_hi] (N, 6)``.

    Returns ``C (N, 15, 15)``, ``const (N, 15)`` and the McCormick gap ``(N, 15, 3)`` of each row
    (from the ``c1 x``, ``c2 Q`` and ``x_i x_j`` enclosures: what splitting can remove).
    """
    n = len(f_lo)
    C = np.zeros((n, 15, 15))
    const = np.zeros((n, 15))
    gaps = np.zeros((n, 15, 3))
    F = 6  # features start here in the output
    # leader rows: d + v_lead t - x_i - extra
    v_lo = f_lo[:, 6]
    closing_min = np.clip(v_lo - f_hi[:, 7], 0.0, None)
    never = (f_hi[:, 8] - props.gap_min_m - props.time_gap_margin_s * v_lo
             <= closing_min ** 2 / (2.0 * props.brake_mps2))
    for i, t in enumerate(props.times):
        C[:, i, F + 8] = 1.0
        C[:, i, F + 7] = t
        C[:, i, 2 * i] = -1.0
        C[:, i, F + 6] = np.where(never, 0.0, -props.time_gap_margin_s)
        const[:, i] = np.where(never, 0.0, -props.gap_min_m)
    x_lo, x_hi = y_lo[:, 0::2], y_hi[:, 0::2]  # (N, 3)
    x_m, x_w = 0.5 * (x_lo + x_hi), x_hi - x_lo
    e = ELEVATE_3_TO_6[:, 1:]  # (7, 3), >= 0
    pw = PRODUCT_WEIGHTS[:, 1:, 1:]  # (7, 3, 3), >= 0
    p_lo, p_hi = _product_intervals(x_lo, x_hi)
    half = 0.5 * props.track_m
    for side, (s, col, off) in enumerate(((1.0, 0, -half), (-1.0, 3, half))):
        c1_lo, c1_hi = f_lo[:, col + 1], f_hi[:, col + 1]
        c2_lo, c2_hi = f_lo[:, col + 2], f_hi[:, col + 2]
        c1_m, c1_w = 0.5 * (c1_lo + c1_hi), c1_hi - c1_lo
        c2_m, c2_w = 0.5 * (c2_lo + c2_hi), c2_hi - c2_lo
        for k in range(1, 7):
            r = 3 + 6 * side + (k - 1)
            C[:, r, F + col] = s
            const[:, r] = s * off
            # - s y6
            C[:, r, 1:6:2] -= s * e[k]
            # s c1 x6 >= s c1_m x6 + s x6_m c1 - s c1_m x6_m - c1_w x6_w / 4
            x6_lo, x6_hi = x_lo @ e[k], x_hi @ e[k]
            x6_m, x6_w = 0.5 * (x6_lo + x6_hi), x6_hi - x6_lo
            C[:, r, 0:6:2] += (s * c1_m)[:, None] * e[k]
            C[:, r, F + col + 1] += s * x6_m
            gaps[:, r, 0] = 0.25 * c1_w * x6_w
            const[:, r] += -s * c1_m * x6_m - gaps[:, r, 0]
            # s c2 Q >= s c2_m Q + s Q_m c2 - s c2_m Q_m - c2_w Q_w / 4
            q_lo = np.einsum("ij,nij->n", pw[k], p_lo)
            q_hi = np.einsum("ij,nij->n", pw[k], p_hi)
            q_m, q_w = 0.5 * (q_lo + q_hi), q_hi - q_lo
            C[:, r, F + col + 2] += s * q_m
            gaps[:, r, 1] = 0.25 * c2_w * q_w
            const[:, r] += -s * c2_m * q_m - gaps[:, r, 1]
            # sigma Q >= sum_ij pw_ij (lower bound of sigma x_i x_j), sigma = s c2_m
            sigma = s * c2_m
            coef, cst, gap = _quadratic_lower(sigma, pw[k], x_lo, x_hi, x_m, x_w)
            C[:, r, 0:6:2] += coef
            const[:, r] += cst
            gaps[:, r, 2] = gap
    return C, const, gaps


def _quadratic_lower(sigma, pw, x_lo, x_hi, x_m, x_w):
    """Linear lower bound ``coef (N, 3) @ x + cst (N,)`` of ``sigma sum_ij pw_ij x_i x_j`` on the
    box ``[x_lo, x_hi] (N, 3)``, and its worst-case gap ``(N,)``."""
    n = len(sigma)
    coef, cst, gap = np.zeros((n, 3)), np.zeros(n), np.zeros(n)
    a = np.abs(sigma)
    for i in range(3):
        for j in range(3):
            w = pw[i, j]
            if w == 0.0:
                continue
            if i != j:
                # x_i x_j = centred product +- x_w_i x_w_j / 4
                coef[:, j] += w * sigma * x_m[:, i]
                coef[:, i] += w * sigma * x_m[:, j]
                cst += -w * sigma * x_m[:, i] * x_m[:, j] - w * a * x_w[:, i] * x_w[:, j] / 4
                gap += w * a * x_w[:, i] * x_w[:, j] / 2
            else:
                pos = sigma >= 0
                # sigma >= 0: tangent at the centre; sigma < 0: the chord (upper bound of x^2)
                slope = np.where(pos, 2.0 * x_m[:, i], x_lo[:, i] + x_hi[:, i])
                icpt = np.where(pos, -x_m[:, i] ** 2, -x_lo[:, i] * x_hi[:, i])
                coef[:, i] += w * sigma * slope
                cst += w * sigma * icpt
                gap += w * a * x_w[:, i] ** 2 / 4
    return coef, cst, gap


def _quadratic_form_interval(q: np.ndarray, x_lo: np.ndarray, x_hi: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Bounds ``(N, K)`` x2 of ``x^T q_k x`` for ``q (K, 3, 3)`` over boxes ``[x_lo, x_hi]
    (N, 3)``: the tighter of the products' intervals and the centred form ``R(m) + 2 m^T q
    delta + delta^T q delta``, ``|delta| <= r`` (sound both)."""
    p_lo, p_hi = _product_intervals(x_lo, x_hi)
    q_pos, q_neg = np.maximum(q, 0.0), np.minimum(q, 0.0)
    lo = np.einsum("kab,nab->nk", q_pos, p_lo) + np.einsum("kab,nab->nk", q_neg, p_hi)
    hi = np.einsum("kab,nab->nk", q_pos, p_hi) + np.einsum("kab,nab->nk", q_neg, p_lo)
    m, r = 0.5 * (x_lo + x_hi), 0.5 * (x_hi - x_lo)
    centre = np.einsum("kab,na,nb->nk", q, m, m)
    spread = 2.0 * np.abs(np.einsum("kab,na->nkb", q, m)) @ r[:, :, None]
    spread = spread[..., 0] + np.einsum("kab,na,nb->nk", np.abs(q), r, r)
    return np.maximum(lo, centre - spread), np.minimum(hi, centre + spread)


def _residual_from_linear_x(plan: bnd.LinearBound, lo: np.ndarray, hi: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Bounds ``(N, 7)`` x2 of ``R_k(x)`` from the plan's linear bounds in the envelope
    coordinates (``plan``: CROWN of ``[eye(6); -eye(6)]``, so ``A z + a <= x <= B z + b``).

    Over a box ``z = m + delta``, ``|delta| <= rho``: ``x = c + C delta + e``, ``C = (A + B) /
    2`` and ``|e| <= eps``, so ``R(x) = R(c) + 2 (Q c)^T (C delta + e) + delta^T C^T Q C delta
    + 2 delta^T C^T Q e + e^T Q e``, each term bounded over the box. Unlike the x intervals
    this keeps the control points' correlation (a faster plan moves all three, and ``R``,
    homogeneous of degree 2, vanishes along a plan that only gets faster)."""
    m, rho = 0.5 * (lo + hi), 0.5 * (hi - lo)
    a_lo, c_lo = plan.coef[:, 0:6:2], plan.const[:, 0:6:2]  # x >= A z + a
    b_hi, c_hi = -plan.coef[:, 6:12:2], -plan.const[:, 6:12:2]  # x <= B z + b
    big_c = 0.5 * (a_lo + b_hi)  # (N, 3, n_z)
    at_m_lo = np.einsum("nid,nd->ni", a_lo, m) + c_lo
    at_m_hi = np.einsum("nid,nd->ni", b_hi, m) + c_hi
    c = 0.5 * (at_m_lo + at_m_hi)
    half_d = 0.5 * (b_hi - a_lo)  # (N, 3, n_z)
    eps = 0.5 * (at_m_hi - at_m_lo) + np.einsum("nid,nd->ni", np.abs(half_d), rho)
    eps = np.maximum(eps, 0.0)
    q = LANE_FIT_RESIDUAL
    qc = np.einsum("kab,nb->nka", q, c)  # (N, 7, 3)
    centre = np.einsum("nka,na->nk", qc, c)
    slope = 2.0 * np.einsum("nka,nad->nkd", qc, big_c)  # (N, 7, n_z)
    spread = np.einsum("nkd,nd->nk", np.abs(slope), rho) + 2.0 * np.einsum(
        "nka,na->nk", np.abs(qc), eps)
    # (C delta + e)^T Q (C delta + e): the delta part as a form in the box's own coordinates
    # (M = C^T Q C keeps the cancellation along a plan that only gets faster, where R = 0)
    qbig = np.einsum("kab,nbd->nkad", q, big_c)  # (N, 7, 3, n_z)
    form = np.einsum("nae,nkad->nked", big_c, qbig)  # (N, 7, n_z, n_z)
    diag = np.einsum("nkdd->nkd", form)
    r2 = rho * rho
    offdiag = np.einsum("nkde,nd,ne->nk", np.abs(form), rho, rho) - np.einsum(
        "nkd,nd->nk", np.abs(diag), r2)
    quad_hi = np.einsum("nkd,nd->nk", np.maximum(diag, 0.0), r2) + offdiag
    quad_lo = np.einsum("nkd,nd->nk", np.minimum(diag, 0.0), r2) - offdiag
    mixed = 2.0 * np.einsum("nkad,nd,na->nk", np.abs(qbig), rho, eps) + np.einsum(
        "kab,na,nb->nk", np.abs(q), eps, eps)
    return centre - spread + quad_lo - mixed, centre + spread + quad_hi + mixed


def lane_head_lane_lower(props: Properties, lo: np.ndarray, hi: np.ndarray,
                         x_lo: np.ndarray, x_hi: np.ndarray,
                         residual: tuple[np.ndarray, np.ndarray] | None = None,
                         terms: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Sound lower bounds ``(N, 12)`` of the lane rows (``left_b1..6, right_b1..6``) of a
    lane-following head (:func:`safeil_sumo.core.bspline.lane_following_y`, ``props.lane_keep_m``)
    over envelope boxes ``[lo, hi] (N, n_z)`` whose x control points lie in ``[x_lo, x_hi]
    (N, 3)``, whatever the network's offsets. ``residual``: bounds ``(N, 7)`` x2 of ``R_k(x)``
    known otherwise (e.g. :func:`_residual_from_linear_x`), intersected with the box's own.
    ``terms``: also return how wide each row's terms are over the box ``(N, 12, 2)``: the
    fit residual's and the start's (what splitting could remove).

    The envelope's lines are concentric (``c1``, ``c2`` shared, half distance ``w/2``), so the
    left row ``k`` is ``E_k0 (w/2 - off - T/2) + sum_i E_ki (w/2 - h t_i) - (1 - E_k0) T/2 +
    c2 R_k(x)`` (the right one with ``+off`` and ``-c2 R_k``), ``|t_i| < 1``. Where the offsets'
    room ``h = w/2 - keep - |c2| A(x)`` is positive, the allowance ``A`` covers the residual
    (:func:`safeil_sumo.core.bspline.lane_fit_allowance`) and the row is at least ``E_k0 (w/2 - |off|
    - T/2) + (1 - E_k0) (keep - T/2)``, whatever x; where it may be clipped at 0 (a residual
    larger than the lane's room somewhere in the box), ``h = 0`` leaves ``(1 - E_k0) (w/2 -
    T/2) - |c2| |R_k|``, and the smaller of the two holds."""
    keep, half = float(props.lane_keep_m), 0.5 * props.track_m
    share = ELEVATE_3_TO_6[1:, 0]  # E_k0, k = 1..6
    r_lo, r_hi = _quadratic_form_interval(LANE_FIT_RESIDUAL[1:], x_lo, x_hi)
    if residual is not None:
        r_lo, r_hi = np.maximum(r_lo, residual[0][:, 1:]), np.minimum(r_hi, residual[1][:, 1:])
    r_abs = np.maximum(np.abs(r_lo), np.abs(r_hi))  # (N, 6)
    bend = 0.5 * np.maximum(np.abs(lo[:, CURV]), np.abs(hi[:, CURV]))  # |c2|
    room_lo = 0.5 * lo[:, W] - keep - bend * np.max(r_abs * LANE_FIT_WEIGHT, axis=1)
    covered = (1.0 - share) * (keep - half)  # (6,)
    clipped = (1.0 - share) * (0.5 * lo[:, W, None] - half) - bend[:, None] * r_abs
    body = np.where(room_lo[:, None] >= 0.0, covered, np.minimum(covered, clipped))
    start_left = 0.5 * lo[:, W] - hi[:, OFF] - half
    start_right = 0.5 * lo[:, W] + lo[:, OFF] - half
    out = np.concatenate([share * start_left[:, None] + body,
                          share * start_right[:, None] + body], axis=1)
    if not terms:
        return out
    fit = np.where(room_lo[:, None] >= 0.0, 0.0, bend[:, None] * r_abs)
    corner = share * (hi[:, OFF] - lo[:, OFF] + 0.5 * (hi[:, W] - lo[:, W]))[:, None]
    widths = np.stack([np.concatenate([fit] * 2, axis=1),
                       np.concatenate([corner] * 2, axis=1)], axis=-1)
    return out, widths


@dataclass(frozen=True)
class BoxBounds:
    """Bounds on a batch of ``N`` boxes: ``lower (N, 15)`` of each margin row, the linear
    bound's coefficients on ``z`` ``coef (N, 15, n_z)`` and, per row, an estimate of what
    splitting each dimension would gain ``score (N, 15, n_z)`` (for branching)."""

    lower: np.ndarray
    coef: np.ndarray
    score: np.ndarray


def bound_boxes(layers: list[bnd.Layer], props: Properties, lo: np.ndarray, hi: np.ndarray,
                margin: str = "both") -> BoxBounds:
    """Sound lower bounds of the margins' rows over each box ``[lo, hi] (N, n_z)``: the 3
    leader rows (``margin="leader"``), the 12 lane rows (``"lane"``) or all 15 (``"both"``),
    in :data:`ROW_NAMES` order."""
    rows = {"leader": MARGIN_ROWS["leader"], "lane": MARGIN_ROWS["lane"],
            "both": slice(0, 15)}[margin]
    nb = bnd.propagate(layers, lo, hi, method="crown")
    y_lo, y_hi = nb.output_interval()
    f_lo, f_hi = nb.pre[0]  # the features' pre-activations: exact intervals of affine rows
    f_lo, f_hi = f_lo[:, :N_FEATURES].copy(), f_hi[:, :N_FEATURES].copy()
    f_lo[:, 7], f_hi[:, 7] = np.maximum(f_lo[:, 7], 0.0), np.maximum(f_hi[:, 7], 0.0)
    y_lo[:, 6:] = np.maximum(y_lo[:, 6:], f_lo)
    y_hi[:, 6:] = np.minimum(y_hi[:, 6:], f_hi)
    need_plan = margin != "leader"  # the lane rows' McCormick planes need the plan's interval
    if need_plan:
        eye = np.eye(6, 15)
        out = bnd.crown(nb, layers, np.concatenate([eye, -eye]))
        y_lo[:, :6] = np.maximum(y_lo[:, :6], out.lower[:, :6])
        y_hi[:, :6] = np.minimum(y_hi[:, :6], -out.lower[:, 6:])
    C, const, gaps = property_objective(props, f_lo, f_hi, y_lo[:, :6], y_hi[:, :6])
    lane_head = need_plan and props.lane_keep_m is not None
    if lane_head:  # its lane rows in closed form below: here only a placeholder row each
        lane = MARGIN_ROWS["lane"]
        C[:, lane], const[:, lane], gaps[:, lane] = 0.0, 0.0, 0.0
    C, const, gaps = C[:, rows], const[:, rows], gaps[:, rows]
    lin = bnd.crown(nb, layers, C, const, record=True)
    interval = const + np.einsum("nmk,nk->nm", np.maximum(C, 0.0), y_lo) \
        + np.einsum("nmk,nk->nm", np.minimum(C, 0.0), y_hi)
    score = bnd.split_scores(nb, lin)
    if lane_head:
        return _with_lane_head_rows(props, lo, hi, y_lo[:, :6], y_hi[:, :6], out, rows,
                                    BoxBounds(np.maximum(lin.lower, interval), lin.coef, score))
    if need_plan:
        # the McCormick gaps: c1 x and c2 Q halve with heading / curvature, the rest with the
        # plan's width, shared among the dimensions by its sensitivity to them
        width = hi - lo
        infl = _width_shares(out, width, slice(0, 6, 2))
        score += (0.5 * gaps[..., 0] + 0.5 * gaps[..., 1] + gaps[..., 2])[..., None] \
            * infl[:, None]
        score[..., HEAD] += 0.5 * gaps[..., 0]
        score[..., CURV] += 0.5 * gaps[..., 1]
    return BoxBounds(np.maximum(lin.lower, interval), lin.coef, score)


def _with_lane_head_rows(props: Properties, lo: np.ndarray, hi: np.ndarray, out_lo: np.ndarray,
                         out_hi: np.ndarray, plan: bnd.LinearBound, rows: slice,
                         bounds: BoxBounds) -> BoxBounds:
    """``bounds`` (its ``rows`` of the 15) with the lane rows of a lane-following head from
    :func:`lane_head_lane_lower` (no linear coefficients) and split scores for them, each
    term's width given to the dimensions that narrow it; the plan's interval ``[out_lo,
    out_hi] (N, 6)`` and linear bounds ``plan`` hold x1, z1, x2, z2, x3, z3."""
    lower, coef, score = bounds.lower.copy(), bounds.coef.copy(), bounds.score.copy()
    kept = np.arange(15)[rows]
    at = np.flatnonzero(kept >= 3)  # where the lane rows sit among those returned
    lane = kept[at] - 3  # and which of the 12 they are
    bound, widths = lane_head_lane_lower(props, lo, hi, out_lo[:, 0::2], out_hi[:, 0::2],
                                         _residual_from_linear_x(plan, lo, hi), terms=True)
    lower[:, at], widths = bound[:, lane], widths[:, lane]
    coef[:, at] = 0.0
    # the residual (where it may exceed the room) shrinks with the x control points' widths,
    # and with the curvature's only by as much as halving it lowers the children's largest
    # |c2| (nothing for a box around a straight lane); the start term with the width's and
    # offset's
    shares = _width_shares(plan, hi - lo, slice(0, 6, 2))
    score[:, at] = widths[..., 0, None] * shares[:, None]
    k_lo, k_hi = np.abs(lo[:, CURV]), np.abs(hi[:, CURV])
    k_mid = np.abs(0.5 * (lo[:, CURV] + hi[:, CURV]))
    bend = np.maximum(np.maximum(k_lo, k_hi), 1e-300)
    children = 0.5 * (np.maximum(k_lo, k_mid) + np.maximum(k_mid, k_hi))
    score[:, at, CURV] += widths[..., 0] * ((bend - children) / bend)[:, None]
    score[:, at, OFF] += widths[..., 1]
    score[:, at, W] += 0.5 * widths[..., 1]
    return BoxBounds(lower, coef, score)


# ------------------------------------------------------------------ volumes


def box_shares(env: CertEnvelope, lo: np.ndarray, hi: np.ndarray, part: str,
               grid: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds ``(N,)`` x2 of the envelope volume in each box ``[lo, hi]``
    (coordinates' widths, log width for the gap; zero-width dimensions left out), restricted to
    the recoverable states: exact where a box is wholly in or out; else lower and upper Riemann
    sums on a ``grid x grid`` split of (ego speed, relative speed), exact in the gap (the
    recoverable extent of log d falls with the closing speed, which grows with v_x and falls with
    dv, so the cells' corners bound it)."""
    lo, hi = np.atleast_2d(lo), np.atleast_2d(hi)
    width = hi - lo
    logw = np.log(hi[:, GAP]) - np.log(lo[:, GAP])
    width = np.where(np.arange(lo.shape[1]) == GAP, logw[:, None], width)
    base = np.prod(np.where(width > 0, width, 1.0), axis=1)
    if part == "free":
        return base, base.copy()
    two_b = 2.0 * env.brake_mps2

    def extent(closing: np.ndarray, d_lo: np.ndarray, d_hi: np.ndarray) -> np.ndarray:
        floor = np.clip(closing * closing / two_b, d_lo, d_hi)
        return (np.log(d_hi) - np.log(floor)) / np.maximum(np.log(d_hi) - np.log(d_lo), 1e-300)

    def closing(v: np.ndarray, dv: np.ndarray) -> np.ndarray:
        return np.clip(np.minimum(-dv, v), 0.0, None)

    d_lo, d_hi = lo[:, GAP], hi[:, GAP]
    full = extent(closing(hi[:, V], lo[:, DV]), d_lo, d_hi)  # worst corner
    none = extent(closing(lo[:, V], hi[:, DV]), d_lo, d_hi)  # best corner
    low, high = full.copy(), none.copy()
    mixed = np.flatnonzero(full < none)
    if len(mixed):
        u = (np.arange(grid) + 0.0) / grid
        m_lo, m_hi = lo[mixed], hi[mixed]
        v0 = m_lo[:, V, None] + u * (m_hi[:, V] - m_lo[:, V])[:, None]  # cell lower edges
        v1 = m_lo[:, V, None] + (u + 1.0 / grid) * (m_hi[:, V] - m_lo[:, V])[:, None]
        r0 = m_lo[:, DV, None] + u * (m_hi[:, DV] - m_lo[:, DV])[:, None]
        r1 = m_lo[:, DV, None] + (u + 1.0 / grid) * (m_hi[:, DV] - m_lo[:, DV])[:, None]
        dl, dh = m_lo[:, GAP, None, None], m_hi[:, GAP, None, None]
        low[mixed] = extent(closing(v1[:, :, None], r0[:, None, :]), dl, dh).mean(axis=(1, 2))
        high[mixed] = extent(closing(v0[:, :, None], r1[:, None, :]), dl, dh).mean(axis=(1, 2))
    return base * low, base * high


def envelope_volume(env: CertEnvelope, part: str, grid: int = 1024) -> tuple[float, float]:
    """Lower and upper bounds of a part's volume (see :func:`box_shares`)."""
    lo, hi = env.root_boxes()[part]
    a, b = box_shares(env, lo[None], hi[None], part, grid)
    return float(a[0]), float(b[0])


# ------------------------------------------------------------------ sampled violations


def sampled_violations(policy: MLPPolicy, props: Properties, n: int, seed: int = 0,
                       chunk: int = 100_000, cfg: EnvelopeConfig = _SAMPLING) -> dict:
    """Monte Carlo estimate of the share of the envelope where each margin truly fails (what
    no certificate can cover), in the certificate's measure: ``n`` leader states and ``n``
    no-leader states drawn by the training's sampler (:func:`~safeil_sumo.learn.envelope.
    sample_states`), the parts weighted as the envelope weighs them (``no_leader_share``), the
    margins of the network's actual plans (:func:`reference_margins`, at its current style).

    Returns per margin the weighted violated share, the share per part, and the median and
    worst violation [m] (positive numbers) over the violating states."""
    from dataclasses import replace

    from safeil_sumo.learn.envelope import sample_states

    rng = np.random.default_rng(seed)
    parts = {"leader_states": replace(cfg, no_leader_share=0.0),
             "no_leader": replace(cfg, no_leader_share=1.0)}
    mins: dict[str, dict[str, list]] = {m: {p: [] for p in parts} for m in MARGINS}
    for part, part_cfg in parts.items():
        for start in range(0, n, chunk):
            feats = sample_states(min(chunk, n - start), rng, part_cfg)
            rows = reference_margins(policy, feats, props)
            for m in MARGINS:
                mins[m][part].append(rows[:, MARGIN_ROWS[m]].min(axis=1))
    out = {}
    w_free = cfg.no_leader_share
    for m in MARGINS:
        per = {p: np.concatenate(v) for p, v in mins[m].items()}
        share = {p: float(np.mean(v < 0.0)) for p, v in per.items()}
        bad = -np.concatenate([v[v < 0.0] for v in per.values()])
        out[m] = {"violated": (1.0 - w_free) * share["leader_states"]
                  + w_free * share["no_leader"], **share,
                  "median_m": float(np.median(bad)) if len(bad) else 0.0,
                  "worst_m": float(bad.max()) if len(bad) else 0.0}
    return out
