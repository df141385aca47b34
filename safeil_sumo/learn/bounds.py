"""Sound output bounds of a small feed-forward network over input boxes — pure numpy.

A network here is a sequence of :class:`Layer` s, each an affine map followed by an elementwise
activation chosen per unit (identity, ReLU or tanh), so the same code bounds the planner, the
planner with its features carried alongside (identity units), or a ReLU on one input only.
All functions are batched over ``N`` boxes: ``lo, hi (N, n_in)``.

Two methods, both sound for every point of the box:

- **Interval bound propagation** (:func:`propagate` with ``method="ibp"``): through ``W x + b`` as
  ``[W+ lo + W- hi + b, W+ hi + W- lo + b]`` (``W+``, ``W-`` the positive and negative parts of
  ``W``), through monotone activations elementwise.
- **CROWN-style linear relaxation** (:func:`crown`): each activation over its pre-activation
  interval ``[l, u]`` is enclosed between two lines (:func:`relax`), and an objective
  ``C y`` of the output ``y`` is back-substituted through the network to a linear function of the
  input, ``C y >= A x + c``, minimised over the box. The pre-activation intervals of every layer
  are themselves CROWN bounds of the layers below (intersected with IBP's).

Float rounding: the relaxation lines are loosened by :data:`RELAX_SLACK` relative to their
magnitude and the intermediate intervals widened by :data:`INTERVAL_SLACK`, so rounding in their
own computation cannot make them cut into the function; the remaining float64 error of the
back-substitution and of the network's own evaluation (``~1e-13`` of the values involved) is left
to an explicit margin the caller subtracts (:mod:`safeil_sumo.learn.branch_and_bound` uses
1e-6 m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

IDENTITY, RELU, TANH = 0, 1, 2
ACTIVATIONS = {"identity": IDENTITY, "relu": RELU, "tanh": TANH}
RELAX_SLACK = 1e-12  # relaxation lines loosened by this times (1 + |slope| max(|l|, |u|)) [-]
INTERVAL_SLACK = 1e-12  # intermediate intervals widened by this times (1 + |bound|) [-]
_NARROW = 1e-9  # pre-activation intervals narrower than this use the tangent at the midpoint


@dataclass(frozen=True)
class Layer:
    """``x -> act(W x + b)``; ``weight (n_out, n_in)``, ``bias (n_out,)``, ``activation (n_out,)``
    integer codes :data:`IDENTITY`, :data:`RELU`, :data:`TANH` per unit."""

    weight: np.ndarray
    bias: np.ndarray
    activation: np.ndarray

    def __post_init__(self) -> None:
        w, b, a = (np.asarray(self.weight, float), np.asarray(self.bias, float),
                   np.asarray(self.activation, np.int8))
        if w.ndim != 2 or b.shape != (w.shape[0],) or a.shape != (w.shape[0],):
            raise ValueError(f"layer shapes do not fit: weight {w.shape}, bias {b.shape}, "
                             f"activation {a.shape}")
        if not np.all(np.isfinite(w)) or not np.all(np.isfinite(b)):
            raise ValueError("layer weights must be finite")
        object.__setattr__(self, "weight", w)
        object.__setattr__(self, "bias", b)
        object.__setattr__(self, "activation", a)

    @classmethod
    def dense(cls, weight: np.ndarray, bias: np.ndarray, activation: str) -> Layer:
        """A layer whose units all share ``activation`` ("identity", "relu" or "tanh")."""
        n = np.asarray(weight).shape[0]
        return cls(weight, bias, np.full(n, ACTIVATIONS[activation], np.int8))


def forward(layers: list[Layer], x: np.ndarray) -> np.ndarray:
    """The network's output ``(..., n_out)`` at points ``x (..., n_in)`` (float64)."""
    h = np.asarray(x, float)
    for layer in layers:
        h = h @ layer.weight.T + layer.bias
        h = _activate(h, layer.activation)
    return h


def _activate(p: np.ndarray, codes: np.ndarray) -> np.ndarray:
    out = p.copy()
    relu, tanh = codes == RELU, codes == TANH
    if relu.any():
        out[..., relu] = np.maximum(p[..., relu], 0.0)
    if tanh.any():
        out[..., tanh] = np.tanh(p[..., tanh])
    return out


def affine_interval(weight: np.ndarray, bias: np.ndarray, lo: np.ndarray, hi: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Exact interval of ``W x + b`` over the box ``[lo, hi] (N, n_in)`` -> ``(N, n_out)`` x2."""
    wp, wn = np.maximum(weight, 0.0), np.minimum(weight, 0.0)
    return lo @ wp.T + hi @ wn.T + bias, hi @ wp.T + lo @ wn.T + bias


def _dtanh(p: np.ndarray) -> np.ndarray:
    return 1.0 - np.tanh(p) ** 2


def relax(codes: np.ndarray, lo: np.ndarray, hi: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lines enclosing each unit's activation on ``[lo, hi] (N, n)``:
    ``aL p + bL <= act(p) <= aU p + bU`` for every ``p`` in the interval; returns
    ``(aL, bL, aU, bU)``, each ``(N, n)``.

    - identity: slope 1, intercept 0;
    - ReLU: exact when the interval is on one side of 0; else the chord above, and below the
      line through the origin of slope 1 if ``u >= -l`` else 0 (CROWN's adaptive choice);
    - tanh (convex below 0, concave above): on ``[l, u]`` with ``l >= 0`` the chord below and
      the tangent at the midpoint above; with ``u <= 0`` the mirror; across 0 above: the tangent
      at the midpoint or, if that one cuts tanh near ``l``, at the first point whose tangent
      clears ``(l, tanh l)`` (:func:`_tangent_point`; the chord if none in ``[0, u]`` does), and
      the mirror image below.
    Each line is loosened by :data:`RELAX_SLACK` against float rounding.
    """
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    shape = np.broadcast_shapes(lo.shape, hi.shape)
    codes = np.broadcast_to(codes, shape)
    a_l, b_l = np.ones(shape), np.zeros(shape)
    a_u, b_u = np.ones(shape), np.zeros(shape)

    relu = codes == RELU
    if relu.any():
        l, u = lo[relu], hi[relu]
        dead, live = u <= 0.0, l >= 0.0
        cross = ~dead & ~live
        width = np.where(cross, u - l, 1.0)
        up_slope = np.where(dead, 0.0, np.where(live, 1.0, u / width))
        up_icpt = np.where(cross, -up_slope * l, 0.0)
        low_slope = np.where(dead, 0.0, np.where(live, 1.0, (u >= -l).astype(float)))
        a_l[relu], b_l[relu], a_u[relu], b_u[relu] = low_slope, 0.0, up_slope, up_icpt

    tanh = codes == TANH
    if tanh.any():
        l, u = lo[tanh], hi[tanh]
        tl, tu = np.tanh(l), np.tanh(u)
        width = u - l
        narrow = width < _NARROW
        chord = np.where(narrow, 0.0, (tu - tl) / np.where(narrow, 1.0, width))
        mid = 0.5 * (l + u)
        tm, dm = np.tanh(mid), _dtanh(mid)
        pos, neg = l >= 0.0, u <= 0.0
        cross = ~pos & ~neg
        # across 0: the tangent at max(d*, midpoint) above (the chord when no tangent point
        # qualifies), and the mirror image below (tanh is odd)
        d_up, d_lo = np.full_like(l, np.inf), np.full_like(l, np.inf)
        if cross.any():
            d_up[cross] = _tangent_point(l[cross], u[cross])
            d_lo[cross] = _tangent_point(-u[cross], -l[cross])
        up_tan, lo_tan = np.isfinite(d_up), np.isfinite(d_lo)
        d_up = np.where(up_tan, np.maximum(d_up, mid), 0.0)
        d_lo = np.where(lo_tan, -np.maximum(d_lo, -mid), 0.0)
        s_up = np.where(up_tan, _dtanh(d_up), chord)
        c_up = np.where(up_tan, np.tanh(d_up) - s_up * d_up, tl - chord * l)
        s_lo = np.where(lo_tan, _dtanh(d_lo), chord)
        c_lo = np.where(lo_tan, np.tanh(d_lo) - s_lo * d_lo, tl - chord * l)
        # lower line
        al = np.where(pos, chord, np.where(neg, dm, s_lo))
        bl = np.where(pos, tl - chord * l, np.where(neg, tm - dm * mid, c_lo))
        # upper line
        au = np.where(pos, dm, np.where(neg, chord, s_up))
        bu = np.where(pos, tm - dm * mid, np.where(neg, tu - chord * u, c_up))
        # a narrow interval: the tangent at the midpoint, shifted by the curvature term
        # (|tanh''| <= 0.77, so |tanh(p) - tangent| <= 0.39 width^2)
        curv = 0.39 * width * width
        al = np.where(narrow, dm, al)
        au = np.where(narrow, dm, au)
        bl = np.where(narrow, tm - dm * mid - curv, bl)
        bu = np.where(narrow, tm - dm * mid + curv, bu)
        a_l[tanh], b_l[tanh], a_u[tanh], b_u[tanh] = al, bl, au, bu

    nonlin = codes != IDENTITY
    if nonlin.any():
        scale = 1.0 + np.maximum(np.abs(a_l), np.abs(a_u)) * np.maximum(np.abs(lo), np.abs(hi))
        slack = RELAX_SLACK * scale
        b_l = np.where(nonlin, b_l - slack, b_l)
        b_u = np.where(nonlin, b_u + slack, b_u)
    return a_l, b_l, a_u, b_u


def _tangent_point(l: np.ndarray, u: np.ndarray, iterations: int = 12) -> np.ndarray:
    """For ``l < 0 < u``: the smallest ``d*`` in ``[0, u]`` whose tangent to tanh passes above
    ``(l, tanh l)`` (every tangent at ``d`` in ``[d*, u]`` then lies above tanh on ``[l, u]``:
    above it on the concave side ``[0, inf)``, and the line minus tanh is concave on ``[l, 0]``
    so it is non-negative there when it is at both ends), bracketed from above by bisection
    (sound however few iterations); ``inf`` when no tangent point in ``[0, u]`` qualifies (then
    the chord is the upper line)."""
    tl = np.tanh(l)

    def g(d: np.ndarray) -> np.ndarray:  # tangent at d minus tanh at l: < 0 below d*
        return np.tanh(d) + _dtanh(d) * (l - d) - tl

    a, b = np.zeros_like(l), u.copy()
    for _ in range(iterations):
        m = 0.5 * (a + b)
        ok = g(m) >= 0.0
        a, b = np.where(ok, a, m), np.where(ok, m, b)
    return np.where(g(u) >= 0.0, b, np.inf)


def _widen(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (lo - INTERVAL_SLACK * (1.0 + np.abs(lo)),
            hi + INTERVAL_SLACK * (1.0 + np.abs(hi)))


@dataclass(frozen=True)
class LinearBound:
    """``objective(x) >= coef @ x + const`` on the box, and its minimum ``lower`` over it.

    ``coef (N, m, n_in)``, ``const (N, m)``, ``lower (N, m)``; ``layer_coefs``, when recorded:
    per layer, the objective's coefficients on that layer's output ``(N, m, n_k)`` met on the
    way down (what :func:`split_scores` weighs the relaxation gaps with)."""

    coef: np.ndarray
    const: np.ndarray
    lower: np.ndarray
    layer_coefs: tuple = ()


def _rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``sum_k a[n, m, k] b[n, k]`` -> ``(N, m)``."""
    return np.matmul(a, b[:, :, None])[:, :, 0]


def _backsubstitute(layers: list[Layer], relaxations: list, objective: np.ndarray,
                    const: np.ndarray, lo: np.ndarray, hi: np.ndarray, record: bool = False
                    ) -> LinearBound:
    """Lower bound of ``objective @ y_K + const (N, m)``, ``y_K`` the output of ``layers`` (the
    first K), by back-substitution of the relaxations (one per layer). ``objective``: shared
    ``(m, n_K)`` (then the first step is factored: ``C+ (a_L W) + C- (a_U W)``, BLAS-sized) or
    per box ``(N, m, n_K)``."""
    c = np.array(const, dtype=float)
    steps = list(zip(reversed(layers), reversed(relaxations), strict=True))
    recorded = []
    if objective.ndim == 2 and not record:
        (layer, (a_l, b_l, a_u, b_u)), steps = steps[0], steps[1:]
        cols = np.flatnonzero(np.any(objective != 0.0, axis=0))  # units the objective uses
        obj, a_l, b_l, a_u, b_u = (objective[:, cols], a_l[:, cols], b_l[:, cols], a_u[:, cols],
                                   b_u[:, cols])
        w, bias = layer.weight[cols], layer.bias[cols]
        pos, neg = np.maximum(obj, 0.0), np.minimum(obj, 0.0)
        c += (b_l + a_l * bias) @ pos.T + (b_u + a_u * bias) @ neg.T
        lam = pos @ (a_l[:, :, None] * w) + neg @ (a_u[:, :, None] * w)
    else:
        lam = np.broadcast_to(objective, (len(c), *objective.shape[-2:]))
    for layer, (a_l, b_l, a_u, b_u) in steps:
        if record:
            recorded.append(lam)
        pos, neg = np.maximum(lam, 0.0), np.minimum(lam, 0.0)
        c += _rowdot(pos, b_l) + _rowdot(neg, b_u)
        lam = pos * a_l[:, None, :] + neg * a_u[:, None, :]
        c += lam @ layer.bias
        lam = lam @ layer.weight
    pos, neg = np.maximum(lam, 0.0), np.minimum(lam, 0.0)
    lower = c + _rowdot(pos, lo) + _rowdot(neg, hi)
    return LinearBound(lam, c, lower, tuple(reversed(recorded)))


def _bounds_pair(layers: list[Layer], relaxations: list, objective: np.ndarray,
                 const: np.ndarray, lo: np.ndarray, hi: np.ndarray
                 ) -> tuple[LinearBound, LinearBound]:
    """Lower bounds of ``objective @ y_K + const`` and of its negation (i.e. minus the upper
    bound), for a shared ``objective (m, n_K)``, ``const (m,)``. The first step uses
    ``w+ a_L + w- a_U = (w (a_L + a_U) - |w| (a_U - a_L)) / 2`` (and its mirror), i.e. two
    products with ``m`` rows instead of four."""
    (layer, (a_l, b_l, a_u, b_u)), rest = ((layers[-1], relaxations[-1]),
                                           (layers[:-1], relaxations[:-1]))
    cols = np.flatnonzero(np.any(objective != 0.0, axis=0))
    obj = objective[:, cols]
    a_l, b_l, a_u, b_u = a_l[:, cols], b_l[:, cols], a_u[:, cols], b_u[:, cols]
    w, bias = layer.weight[cols], layer.bias[cols]
    a_s, a_d = a_l + a_u, a_u - a_l
    mid = obj @ (a_s[:, :, None] * w)  # (N, m, n_{K-1})
    spread = np.abs(obj) @ (a_d[:, :, None] * w)
    c_mid = (b_l + b_u + a_s * bias) @ obj.T
    c_spread = (b_u - b_l + a_d * bias) @ np.abs(obj).T
    out = []
    for sign in (1.0, -1.0):
        lam = 0.5 * (sign * mid - spread)
        c = sign * const + 0.5 * (sign * c_mid - c_spread)
        if rest[0]:
            b = _backsubstitute(rest[0], rest[1], lam, c, lo, hi)
        else:
            pos, neg = np.maximum(lam, 0.0), np.minimum(lam, 0.0)
            b = LinearBound(lam, c, c + _rowdot(pos, lo) + _rowdot(neg, hi))
        out.append(b)
    return out[0], out[1]


@dataclass(frozen=True)
class NetworkBounds:
    """Per layer: pre-activation interval ``pre[k] = (l, u)`` and relaxation lines; what
    :func:`crown` needs for any objective on the output."""

    lo: np.ndarray
    hi: np.ndarray
    pre: list
    relaxations: list
    last_activation: np.ndarray
    sensitivity: list  # per layer: |d pre-activation / d input| estimate, (N, n_k, n_in) or
    # (n_k, n_in) for the first layer

    def output_interval(self) -> tuple[np.ndarray, np.ndarray]:
        """The last layer's output interval (post-activation), by interval propagation."""
        return _post(*self.pre[-1], self.last_activation)


def _post(l: np.ndarray, u: np.ndarray, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval of monotone activations on ``[l, u]``, widened against float rounding."""
    return _widen(_activate(l, codes), _activate(u, codes))


def propagate(layers: list[Layer], lo: np.ndarray, hi: np.ndarray, *, method: str = "crown"
              ) -> NetworkBounds:
    """Pre-activation intervals and relaxations of every layer over the boxes ``(N, n_in)``.

    ``method="ibp"``: intervals by interval propagation only (:func:`affine_interval`, then
    the monotone activations); ``"crown"``: each layer's interval from
    back-substituting the relaxations below it (only for its non-identity units), intersected
    with IBP's.
    """
    if method not in ("crown", "ibp"):
        raise ValueError(f"method must be 'crown' or 'ibp', got {method!r}")
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if lo.shape != hi.shape or lo.ndim != 2:
        raise ValueError(f"boxes must be (N, n_in) twice, got {lo.shape} and {hi.shape}")
    if np.any(hi < lo):
        raise ValueError("box with hi < lo")
    pre, relaxations, sensitivity = [], [], [np.abs(layers[0].weight)]
    a, b = lo, hi
    n = len(lo)
    for k, layer in enumerate(layers):
        pl, pu = affine_interval(layer.weight, layer.bias, a, b)
        rows = np.flatnonzero(layer.activation != IDENTITY)
        if method == "crown" and k > 0 and len(rows):
            low, up = _bounds_pair(layers[:k], relaxations, layer.weight[rows],
                                   layer.bias[rows], lo, hi)
            pl[:, rows] = np.maximum(pl[:, rows], low.lower)
            pu[:, rows] = np.minimum(pu[:, rows], -up.lower)
            sens = np.zeros((n, layer.weight.shape[0], lo.shape[1]))
            sens[:, rows] = 0.5 * (np.abs(low.coef) + np.abs(up.coef))
            sensitivity.append(sens)
        elif k > 0:
            sensitivity.append(None)
        pl, pu = _widen(pl, pu)
        pu = np.maximum(pu, pl)
        pre.append((pl, pu))
        relaxations.append(relax(layer.activation, pl, pu))
        a, b = _post(pl, pu, layer.activation)
    return NetworkBounds(lo, hi, pre, relaxations, layers[-1].activation, sensitivity)


def crown(bounds: NetworkBounds, layers: list[Layer], objective: np.ndarray,
          const: np.ndarray | None = None, record: bool = False) -> LinearBound:
    """CROWN lower bound of ``objective @ y + const`` over each box, ``y`` the network's output.

    ``objective``: ``(m, n_out)`` or per box ``(N, m, n_out)``; ``const``: ``(m,)`` or
    ``(N, m)`` (default 0). For an upper bound pass ``-objective`` and negate."""
    n = len(bounds.lo)
    obj = np.asarray(objective, float)
    shape = (n, obj.shape[-2])
    c = np.zeros(shape) if const is None else np.broadcast_to(np.asarray(const, float), shape)
    return _backsubstitute(layers, bounds.relaxations, obj, c, bounds.lo, bounds.hi, record)


def output_bounds(layers: list[Layer], lo: np.ndarray, hi: np.ndarray, *,
                  method: str = "crown") -> tuple[np.ndarray, np.ndarray]:
    """Sound interval ``(N, n_out)`` x2 of the network's outputs over the boxes:
    ``method="ibp"`` or ``"crown"`` (CROWN on each output, intersected with IBP)."""
    b = propagate(layers, lo, hi, method=method)
    low, high = b.output_interval()
    if method == "crown":
        n_out = layers[-1].weight.shape[0]
        eye = np.eye(n_out)
        bound = crown(b, layers, np.concatenate([eye, -eye]))
        low = np.maximum(low, bound.lower[:, :n_out])
        high = np.minimum(high, -bound.lower[:, n_out:])
    return low, high


def relaxation_gaps(bounds: NetworkBounds) -> list[np.ndarray]:
    """Per layer ``(N, n_k)``: the largest vertical distance between each unit's upper and lower
    relaxation lines over its interval (0 for identity units)."""
    out = []
    for (l, u), (a_l, b_l, a_u, b_u) in zip(bounds.pre, bounds.relaxations, strict=True):
        out.append(np.maximum((a_u - a_l) * l + b_u - b_l, (a_u - a_l) * u + b_u - b_l))
    return out


def split_scores(bounds: NetworkBounds, bound: LinearBound) -> np.ndarray:
    """Per box, objective row and input dimension ``(N, m, n_in)``: an estimate of how much the
    lower bound would gain from splitting the box along that dimension: ``|coef| width`` (the
    linear part) plus every unit's relaxation gap weighted by the objective's coefficient on it,
    shared among the inputs by their part in its pre-activation's width. ``bound`` must come
    from :func:`crown` with ``record=True``."""
    width = bounds.hi - bounds.lo
    score = np.abs(bound.coef) * width[:, None, :]
    gaps = relaxation_gaps(bounds)
    for k, lam in enumerate(bound.layer_coefs):
        sens = bounds.sensitivity[k]
        if sens is None or not np.any(gaps[k] > 0):
            continue
        share = sens * width[:, None, :]  # (N, n_k, n_in)
        share = share / np.maximum(share.sum(axis=-1, keepdims=True), 1e-300)
        score += (np.abs(lam) * gaps[k][:, None, :]) @ share
    return score
