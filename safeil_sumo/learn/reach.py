"""Sound closed-loop reachability of a network controller and a continuous-time plant — numpy.

The plant (:class:`Plant`) is linear with diagonal quadratic drag terms,

    x' = A x + B u + c + E q(x),     q_j(x) = -mu_j x[k_j]^2,

and the controller ``u = net(M x + m0)`` (a :mod:`bounds` network) is held constant over each
control period ``h``. A set of states is an affine form (a zonotope) ``x = c + G eps``,
``eps in [-1, 1]^k``, batched over ``N`` independent sets: ``center (N, n)``, ``gens (N, n, k)``.

One period (:func:`advance_period`):

1. **Network.** CROWN (:func:`bounds.propagate`, :func:`bounds.crown`) over the box hull of the
   network input gives lines ``L(in) <= net(in) <= U(in)``. As the input is affine in the state
   they are affine in ``eps``: ``u = (L + U)/2 + e`` with ``|e| <= max_Z (U - L)/2 + NET_MARGIN``,
   i.e. the controller's output keeps its dependence on the state and gains one new generator.
2. **Linear part, exact.** With ``u`` constant, ``(x, u, 1, q)`` obeys a linear ODE; its
   exponential (:func:`expm_enclosure`: Taylor series, tail bounded, rounding radius) maps the
   affine form to the one at any time ``t`` of the period, without wrapping.
3. **Drag remainder.** An a-priori box ``X`` of the states over the whole period
   (:func:`apriori_box`: first-order Picard step, ``X0 + [0, h] F(X) subset X``) bounds ``q`` in
   ``[q_mid - q_rad, q_mid + q_rad]``; ``q_mid`` enters exactly, the rest as a box of radius
   ``int_0^t |e^{A s} E| ds q_rad <= int_0^t e^{|A| s} ds |E| q_rad``.
4. **Continuous time.** A linear property ``P x + p0 >= 0`` is bounded on the affine forms at
   ``K + 1`` instants of the period and, between two instants, by the instants' bounds and the
   property's derivative over ``X`` (a convex piecewise-linear lower envelope).

Float rounding: every computed matrix, affine form and interval carries a radius of
:data:`REL` (1e-12) times the sum of the magnitudes involved, far above float64's accumulated
error for these sizes (``n u`` with ``n <= 10^3`` products, ``u = 1.1e-16``); the network's
lines are loosened by :data:`NET_MARGIN`, the margin :mod:`certify` subtracts for the same
back-substitution. ``exp`` is not used: the exponential is a finite sum of products.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from safeil_sumo.learn.bounds import Layer, crown, forward, propagate

REL = 1e-12  # relative rounding radius of every float computation [-]
NET_MARGIN = 1e-6  # the network's CROWN lines loosened by this [units of u]


@dataclass(frozen=True)
class Plant:
    """``x' = A x + B u + c + E q(x)``, ``q_j = -drag_coef_j * x[drag_index_j]^2``.

    ``a (n, n)``, ``b (n, m)``, ``c (n,)``, ``e (n, p)``, ``drag_index (p,)`` int,
    ``drag_coef (p,)`` >= 0."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    e: np.ndarray
    drag_index: np.ndarray
    drag_coef: np.ndarray

    def field(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The vector field ``(N, n)`` at states ``x (N, n)``, inputs ``u (N, m)``."""
        q = -self.drag_coef * x[:, self.drag_index] ** 2
        return x @ self.a.T + u @ self.b.T + self.c + q @ self.e.T


@dataclass(frozen=True)
class Loop:
    """The closed loop: ``u = net(in_map @ x + in_offset)`` held for ``period`` seconds; the
    property ``prop @ x + prop_offset >= 0`` (``(r, n)``, ``(r,)``) is checked at
    ``substeps + 1`` instants per period and in between."""

    plant: Plant
    layers: list[Layer]
    in_map: np.ndarray
    in_offset: np.ndarray
    period: float
    prop: np.ndarray
    prop_offset: np.ndarray
    substeps: int = 10


@dataclass(frozen=True)
class Zonotope:
    """``{center + gens @ eps : eps in [-1, 1]^k}`` per set; ``center (N, n)``,
    ``gens (N, n, k)``."""

    center: np.ndarray
    gens: np.ndarray

    @classmethod
    def from_box(cls, lo: np.ndarray, hi: np.ndarray) -> Zonotope:
        """The boxes ``[lo, hi] (N, n)``: one generator per coordinate."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        # the float midpoint may miss the true one by an ulp: the radius covers it
        center = 0.5 * (lo + hi)
        rad = np.maximum(hi - center, center - lo) * (1.0 + REL)
        return cls(center, rad[:, :, None] * np.eye(lo.shape[1]))

    def hull(self) -> tuple[np.ndarray, np.ndarray]:
        """Box hull ``(N, n)`` x2, outward."""
        r = np.abs(self.gens).sum(axis=-1)
        pad = REL * (np.abs(self.center) + r)
        return self.center - r - pad, self.center + r + pad


def _affine_lower(row: np.ndarray, z: Zonotope, offset: np.ndarray) -> np.ndarray:
    """Lower bound ``(N, r)`` of ``row @ x + offset`` over each set, ``row (r, n)``."""
    c = z.center @ row.T + offset
    g = np.abs(np.einsum("rn,Nnk->Nrk", row, z.gens)).sum(axis=-1)
    pad = REL * (np.abs(z.center) @ np.abs(row).T + np.abs(offset) + g)
    return c - g - pad


# --- the exponential -----------------------------------------------------------------------

@dataclass(frozen=True)
class MatrixEnclosure:
    """Entrywise ``[mid - rad, mid + rad]`` holding an exact matrix; ``(..., d, d)``."""

    mid: np.ndarray
    rad: np.ndarray


def expm_enclosure(m: np.ndarray, t: float) -> MatrixEnclosure:
    """An enclosure of ``exp(m t)`` for a square ``m (d, d)``: the Taylor sum up to the first
    term below 1e-30 in the infinity norm, plus the tail (``||mt||^(K+1)/(K+1)! / (1 - ||mt||/
    (K+2))``, bounding every entry) and :data:`REL` times the sum of ``|m t|^k / k!`` (the
    rounding of the products and the sum)."""
    mt = np.asarray(m, float) * t
    norm = float(np.abs(mt).sum(axis=1).max())
    term, absterm = np.eye(len(mt)), np.eye(len(mt))
    total, abstotal = term.copy(), absterm.copy()
    k = 0
    while True:
        k += 1
        term = term @ mt / k
        absterm = absterm @ np.abs(mt) / k
        total += term
        abstotal += absterm
        bound = norm ** (k + 1) / np.prod(np.arange(1, k + 2, dtype=float))
        if k + 2 > 2 * norm and bound < 1e-30:
            break
    tail = bound / (1.0 - norm / (k + 2))
    return MatrixEnclosure(total, tail + REL * abstotal * (k + 1))


@dataclass(frozen=True)
class PeriodMaps:
    """The exact linear maps of a period at ``times (K + 1,)``, each an enclosure: ``phi``
    ``(K+1, n, n)``, ``gam_b (K+1, n, m)``, ``gam_c (K+1, n, 1)``, ``gam_e (K+1, n, p)``
    (``Gamma(t) = int_0^t e^{A s} ds``), and ``kernel_abs (K+1, n, p)``, an upper bound of
    ``int_0^t |e^{A s} E| ds``."""

    times: np.ndarray
    phi: MatrixEnclosure
    gam_b: MatrixEnclosure
    gam_c: MatrixEnclosure
    gam_e: MatrixEnclosure
    kernel_abs: np.ndarray


def period_maps(plant: Plant, period: float, substeps: int) -> PeriodMaps:
    """:class:`PeriodMaps` of ``plant`` at ``j period / substeps``, ``j = 0..substeps``: the
    exponential of the augmented matrix ``[[A, B, c, E], [0, 0, 0, 0]]``."""
    n, m, p = plant.a.shape[0], plant.b.shape[1], plant.e.shape[1]
    d = n + m + 1 + p
    aug = np.zeros((d, d))
    aug[:n, :n], aug[:n, n:n + m] = plant.a, plant.b
    aug[:n, n + m], aug[:n, n + m + 1:] = plant.c, plant.e
    absaug = np.zeros((n + p, n + p))
    absaug[:n, :n], absaug[:n, n:] = np.abs(plant.a), np.abs(plant.e)
    times = np.linspace(0.0, period, substeps + 1)
    mats = [expm_enclosure(aug, t) for t in times]
    kern = [expm_enclosure(absaug, t) for t in times]
    mid = np.stack([x.mid for x in mats])
    rad = np.stack([x.rad for x in mats])

    def block(cols: slice) -> MatrixEnclosure:
        return MatrixEnclosure(mid[:, :n, cols], rad[:, :n, cols])

    kernel_abs = np.stack([x.mid[:n, n:] + x.rad[:n, n:] for x in kern])
    return PeriodMaps(times, block(slice(0, n)), block(slice(n, n + m)),
                      block(slice(n + m, n + m + 1)), block(slice(n + m + 1, d)),
                      kernel_abs * (1.0 + REL))


# --- the controller over a set -------------------------------------------------------------

@dataclass(frozen=True)
class ControlForm:
    """The controller's output over each set as an affine form in the set's ``eps`` plus an
    independent error: ``u = center + gens @ eps + e``, ``|e| <= err``; ``center (N, m)``,
    ``gens (N, m, k)``, ``err (N, m)``."""

    center: np.ndarray
    gens: np.ndarray
    err: np.ndarray

    def interval(self) -> tuple[np.ndarray, np.ndarray]:
        """Box hull ``(N, m)`` x2, outward."""
        r = np.abs(self.gens).sum(axis=-1) + self.err
        pad = REL * (np.abs(self.center) + r)
        return self.center - r - pad, self.center + r + pad


def control_form(loop: Loop, z: Zonotope) -> ControlForm:
    """:class:`ControlForm` of ``net(M x + m0)`` over the sets ``z``, from CROWN's lines over
    the box hull of the network's input (the input is affine in the state, so the lines are
    affine in ``eps``)."""
    m_in, m0 = loop.in_map, loop.in_offset
    in_c = z.center @ m_in.T + m0  # (N, n_in)
    in_g = np.einsum("in,Nnk->Nik", m_in, z.gens)
    in_r = np.abs(in_g).sum(axis=-1)
    pad = REL * (np.abs(z.center) @ np.abs(m_in).T + np.abs(m0) + in_r)
    lo, hi = in_c - in_r - pad, in_c + in_r + pad
    n_out = loop.layers[-1].weight.shape[0]
    eye = np.eye(n_out)
    nb = propagate(loop.layers, lo, hi)
    # rows 0..m-1: net >= coef_l in + const_l; rows m..2m-1: -net >= coef_u in + const_u
    lin = crown(nb, loop.layers, np.concatenate([eye, -eye]))
    coef_l, coef_u = lin.coef[:, :n_out], -lin.coef[:, n_out:]
    const_l, const_u = lin.const[:, :n_out], -lin.const[:, n_out:]
    alpha, beta = 0.5 * (coef_l + coef_u), 0.5 * (const_l + const_u)  # the middle line
    delta, gap = coef_u - coef_l, const_u - const_l  # U - L = delta in + gap >= 0
    center = _rowdot(alpha, in_c) + beta
    gens = np.einsum("Nmi,Nik->Nmk", alpha, in_g)
    # max over the set of (U - L) / 2, plus the rounding of the forms above
    half = 0.5 * (_rowdot(delta, in_c) + gap + np.abs(np.einsum("Nmi,Nik->Nmk", delta, in_g))
                  .sum(axis=-1))
    size = (_rowdot(np.abs(alpha) + np.abs(delta), np.abs(in_c) + in_r) + np.abs(beta)
            + np.abs(gap))
    err = np.maximum(half, 0.0) + NET_MARGIN + REL * size
    return ControlForm(center, gens, err)


def _rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``sum_i a[N, m, i] b[N, i]`` -> ``(N, m)``."""
    return np.einsum("Nmi,Ni->Nm", a, b)


# --- the a-priori box and the drag ---------------------------------------------------------

def _interval_matvec(mat: np.ndarray, lo: np.ndarray, hi: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``mat (r, n)`` times the boxes ``[lo, hi] (N, n)``, outward ``(N, r)`` x2."""
    mp, mn = np.maximum(mat, 0.0), np.minimum(mat, 0.0)
    a, b = lo @ mp.T + hi @ mn.T, hi @ mp.T + lo @ mn.T
    pad = REL * (np.maximum(np.abs(lo), np.abs(hi)) @ np.abs(mat).T)
    return a - pad, b + pad


def drag_interval(plant: Plant, lo: np.ndarray, hi: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The interval ``(N, p)`` x2 of ``q(x) = -mu x[k]^2`` over the boxes ``[lo, hi] (N, n)``."""
    l, u = lo[:, plant.drag_index], hi[:, plant.drag_index]
    sq_hi = np.maximum(l * l, u * u)
    sq_lo = np.where((l <= 0.0) & (u >= 0.0), 0.0, np.minimum(l * l, u * u))
    mu = plant.drag_coef
    q_lo, q_hi = -mu * sq_hi, -mu * sq_lo
    pad = REL * (1.0 + mu * sq_hi)
    return q_lo - pad, q_hi + pad


def field_interval(plant: Plant, lo: np.ndarray, hi: np.ndarray, u_lo: np.ndarray,
                   u_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward interval ``(N, n)`` x2 of the vector field over state and input boxes."""
    q_lo, q_hi = drag_interval(plant, lo, hi)
    parts = [_interval_matvec(plant.a, lo, hi), _interval_matvec(plant.b, u_lo, u_hi),
             _interval_matvec(plant.e, q_lo, q_hi)]
    f_lo = sum(p[0] for p in parts) + plant.c
    f_hi = sum(p[1] for p in parts) + plant.c
    pad = REL * (np.abs(f_lo) + np.abs(f_hi) + np.abs(plant.c))
    return f_lo - pad, f_hi + pad


def apriori_box(plant: Plant, lo: np.ndarray, hi: np.ndarray, u_lo: np.ndarray,
                u_hi: np.ndarray, period: float, iterations: int = 40
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box ``X (N, n)`` x2 holding every solution from ``[lo, hi]`` under any input in
    ``[u_lo, u_hi]`` over ``[0, period]``, and a mask ``(N,)`` of the sets where one was found.

    Picard-Lindelöf with a box: if ``X0 + [0, h] F(X) subset X`` then every solution stays in
    ``X`` on ``[0, h]``, and so in ``X0 + [0, h] F(X)`` itself (returned). Candidates are
    inflated by 10 % of their width plus 1e-9 until the inclusion holds."""
    x_lo, x_hi = lo.copy(), hi.copy()
    ok = np.zeros(len(lo), bool)
    out_lo, out_hi = lo.copy(), hi.copy()
    for _ in range(iterations):
        f_lo, f_hi = field_interval(plant, x_lo, x_hi, u_lo, u_hi)
        n_lo = lo + period * np.minimum(f_lo, 0.0)
        n_hi = hi + period * np.maximum(f_hi, 0.0)
        pad = REL * (np.abs(lo) + np.abs(hi) + period * (np.abs(f_lo) + np.abs(f_hi)))
        n_lo, n_hi = n_lo - pad, n_hi + pad
        inside = np.all((n_lo >= x_lo) & (n_hi <= x_hi), axis=1) & ~ok
        out_lo[inside], out_hi[inside] = n_lo[inside], n_hi[inside]
        ok |= inside
        if ok.all():
            break
        grow = 0.1 * (n_hi - n_lo) + 1e-9
        x_lo = np.where(ok[:, None], x_lo, np.minimum(x_lo, n_lo) - grow)
        x_hi = np.where(ok[:, None], x_hi, np.maximum(x_hi, n_hi) + grow)
    return out_lo, out_hi, ok


# --- one period ----------------------------------------------------------------------------

def _at_time(maps: PeriodMaps, j: int, z: Zonotope, u: ControlForm, q_mid: np.ndarray,
             q_rad: np.ndarray) -> Zonotope:
    """The affine form of the states at ``maps.times[j]`` (``q_mid, q_rad (N, p)``: the drag
    over the period): the exact linear image, one generator per control error, and a box for
    the drag's spread and every enclosure and rounding radius."""
    phi, gb, gc, ge = (x.mid[j] for x in (maps.phi, maps.gam_b, maps.gam_c, maps.gam_e))
    phi_r, gb_r, gc_r, ge_r = (x.rad[j] for x in (maps.phi, maps.gam_b, maps.gam_c, maps.gam_e))
    x_mag = np.abs(z.center) + np.abs(z.gens).sum(axis=-1)  # (N, n): |x| on the set
    u_mag = np.abs(u.center) + np.abs(u.gens).sum(axis=-1) + u.err
    center = z.center @ phi.T + u.center @ gb.T + gc[:, 0] + q_mid @ ge.T
    state = np.einsum("ab,Nbk->Nak", phi, z.gens) + np.einsum("am,Nmk->Nak", gb, u.gens)
    control_err = gb[None] * u.err[:, None, :]  # (N, n, m): one generator per output
    rad = (q_rad @ maps.kernel_abs[j].T  # the drag's spread about q_mid
           + x_mag @ phi_r.T + u_mag @ gb_r.T + gc_r[:, 0] + np.abs(q_mid) @ ge_r.T
           + REL * (x_mag @ np.abs(phi).T + u_mag @ np.abs(gb).T + np.abs(gc[:, 0])
                    + np.abs(q_mid) @ np.abs(ge).T + np.abs(center)))
    box = rad[:, :, None] * np.eye(len(phi))
    return Zonotope(center, np.concatenate([state, control_err, box], axis=-1))


def reduce_order(z: Zonotope, max_gens: int) -> Zonotope:
    """At most ``max_gens`` generators (``>= 2 n``): the largest ``max_gens - n`` by their 1-norm
    are kept, the others replaced by their box (one axis generator per coordinate)."""
    n, k = z.gens.shape[1:]
    if k <= max_gens:
        return z
    keep = max_gens - n
    order = np.argsort(-np.abs(z.gens).sum(axis=1), axis=-1)  # (N, k), largest first
    sorted_g = np.take_along_axis(z.gens, order[:, None, :], axis=-1)
    rest = np.abs(sorted_g[:, :, keep:]).sum(axis=-1) * (1.0 + REL)
    box = rest[:, :, None] * np.eye(n)
    return Zonotope(z.center, np.concatenate([sorted_g[:, :, :keep], box], axis=-1))


def _between(l0: np.ndarray, l1: np.ndarray, d_lo: np.ndarray, d_hi: np.ndarray, tau: float
             ) -> np.ndarray:
    """Lower bound of ``f`` on ``[0, tau]`` from ``f(0) >= l0``, ``f(tau) >= l1`` and
    ``f' in [d_lo, d_hi]``: the minimum of ``max(l0 + d_lo s, l1 - d_hi (tau - s))``, a convex
    piecewise-linear function, taken at ``s = 0``, ``tau`` and its kink (clipped)."""
    def env(s: np.ndarray) -> np.ndarray:
        return np.maximum(l0 + d_lo * s, l1 - d_hi * (tau - s))

    slope = d_lo - d_hi  # <= 0
    safe = np.where(slope < 0.0, slope, -1.0)
    kink = np.clip(np.where(slope < 0.0, (l1 - d_hi * tau - l0) / safe, 0.0), 0.0, tau)
    low = np.minimum(np.minimum(env(np.zeros_like(l0)), env(np.full_like(l0, tau))), env(kink))
    return low - REL * (np.abs(l0) + np.abs(l1) + tau * (np.abs(d_lo) + np.abs(d_hi)))


@dataclass(frozen=True)
class PeriodResult:
    """One period from the sets ``z``: the sets at its end, the property's lower bound over the
    whole period ``(N, r)`` (``-inf`` where no a-priori box was found), the a-priori box
    ``(N, n)`` x2, the controller's output interval ``(N, m)`` x2, and the sets at the
    ``substeps + 1`` instants of the period before order reduction."""

    end: Zonotope
    lower: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    u_lo: np.ndarray
    u_hi: np.ndarray
    instants: tuple[Zonotope, ...]


def advance_period(loop: Loop, maps: PeriodMaps, z: Zonotope, max_gens: int = 40
                   ) -> PeriodResult:
    """One control period from the sets ``z`` (module docstring, steps 1-4)."""
    plant = loop.plant
    u = control_form(loop, z)
    u_lo, u_hi = u.interval()
    x_lo, x_hi = z.hull()
    box_lo, box_hi, ok = apriori_box(plant, x_lo, x_hi, u_lo, u_hi, loop.period)
    q_lo, q_hi = drag_interval(plant, box_lo, box_hi)
    q_mid = 0.5 * (q_lo + q_hi)
    q_rad = np.maximum(q_hi - q_mid, q_mid - q_lo) * (1.0 + REL)
    # the property's derivative over the period: P A X + P B U + P c + P E Q
    p = loop.prop
    parts = [_interval_matvec(p @ plant.a, box_lo, box_hi),
             _interval_matvec(p @ plant.b, u_lo, u_hi),
             _interval_matvec(p @ plant.e, q_lo, q_hi)]
    pc = p @ plant.c
    slack = REL * (np.abs(p) @ np.abs(plant.c) + np.abs(pc))
    d_lo = sum(x[0] for x in parts) + pc - slack
    d_hi = sum(x[1] for x in parts) + pc + slack
    tau = loop.period / loop.substeps
    sets = tuple(_at_time(maps, j, z, u, q_mid, q_rad) for j in range(len(maps.times)))
    lows = [_affine_lower(p, s, loop.prop_offset) for s in sets]
    lower = np.min([_between(a, b, d_lo, d_hi, tau) for a, b in pairwise(lows)], axis=0)
    lower = np.where(ok[:, None], lower, -np.inf)
    end = reduce_order(sets[-1], max_gens)
    return PeriodResult(end, lower, box_lo, box_hi, u_lo, u_hi, sets)


def reach(loop: Loop, z: Zonotope, periods: int, maps: PeriodMaps | None = None,
          max_gens: int = 40) -> np.ndarray:
    """The property's lower bound per set and period ``(N, periods, r)`` over ``periods``
    control periods from the sets ``z`` (continuous time included). Sets whose bound went
    negative are not advanced further (their later periods are ``-inf``)."""
    maps = maps if maps is not None else period_maps(loop.plant, loop.period, loop.substeps)
    n = len(z.center)
    out = np.full((n, periods, loop.prop.shape[0]), -np.inf)
    live = np.arange(n)
    for k in range(periods):
        if len(live) == 0:
            break
        res = advance_period(loop, maps, z, max_gens)
        out[live, k] = res.lower
        good = np.all(res.lower >= 0.0, axis=1)
        live = live[good]
        z = Zonotope(res.end.center[good], res.end.gens[good])
    return out


# --- simulation and branch and bound -------------------------------------------------------

def simulate(loop: Loop, x0: np.ndarray, periods: int, steps: int = 100
             ) -> tuple[np.ndarray, np.ndarray]:
    """Nominal closed loop from states ``x0 (N, n)`` by RK4 with ``steps`` steps per period:
    the property's minimum over all ``periods * steps + 1`` instants ``(N, r)`` and the final
    states ``(N, n)``."""
    x = np.asarray(x0, float).copy()
    low = x @ loop.prop.T + loop.prop_offset
    for _ in range(periods):
        traj = simulate_period(loop, x, steps)
        low = np.minimum(low, (traj @ loop.prop.T + loop.prop_offset).min(axis=1))
        x = traj[:, -1]
    return low, x


def simulate_period(loop: Loop, x0: np.ndarray, steps: int = 100) -> np.ndarray:
    """States ``(N, steps + 1, n)`` at ``j period / steps`` over one period from ``x0 (N, n)``:
    the network's output at ``x0`` held, RK4 in between."""
    plant, dt = loop.plant, loop.period / steps
    u = forward(loop.layers, x0 @ loop.in_map.T + loop.in_offset)
    out = [np.asarray(x0, float)]
    x = out[0]
    for _ in range(steps):
        k1 = plant.field(x, u)
        k2 = plant.field(x + 0.5 * dt * k1, u)
        k3 = plant.field(x + 0.5 * dt * k2, u)
        k4 = plant.field(x + dt * k3, u)
        x = x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        out.append(x)
    return np.stack(out, axis=1)


@dataclass(frozen=True)
class Verdict:
    """``status``: "verified" (every set proven), "falsified" (a simulated trajectory breaks the
    property; ``counterexample`` its initial state) or "unknown" (budget spent). ``sets``: the
    sets analysed (the initial ones and every half); ``proven``: the leaves proven;
    ``min_lower``: the smallest lower bound over the proven leaves; ``min_simulated``: the
    smallest simulated property value seen (centres and corners of failed sets)."""

    status: str
    sets: int
    proven: int
    min_lower: float
    min_simulated: float
    counterexample: np.ndarray | None = None


def _split(lo: np.ndarray, hi: np.ndarray, weight: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """Each box ``(N, n)`` halved along the coordinate of largest ``width * weight``: the
    halves ``(2N, n)`` x2."""
    dim = np.argmax((hi - lo) * weight, axis=1)
    rows = np.arange(len(lo))
    mid = 0.5 * (lo[rows, dim] + hi[rows, dim])
    hi1, lo2 = hi.copy(), lo.copy()
    hi1[rows, dim], lo2[rows, dim] = mid, mid
    return np.concatenate([lo, lo2]), np.concatenate([hi1, hi])


def _probe_points(lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Centres, the two opposite corners and 4 random points of each box ``(N, n)``:
    ``(7N, n)``."""
    pts = [0.5 * (lo + hi), lo, hi]
    pts += [lo + (hi - lo) * rng.random(lo.shape) for _ in range(4)]
    return np.concatenate(pts)


def prove(loop: Loop, lo: np.ndarray, hi: np.ndarray, periods: int, *, max_sets: int = 4096,
          batch: int = 256, split_weight: np.ndarray | None = None, seed: int = 0) -> Verdict:
    """Branch and bound over the initial box ``[lo, hi] (n,)``: sets whose reachability bound
    (:func:`reach`) stays >= 0 over ``periods`` are proven; the others are probed by simulation
    (:func:`_probe_points`) and, without a counterexample, halved (:func:`_split`) until
    ``max_sets`` sets have been analysed."""
    rng = np.random.default_rng(seed)
    weight = np.ones(len(lo)) if split_weight is None else split_weight
    maps = period_maps(loop.plant, loop.period, loop.substeps)
    q_lo, q_hi = np.asarray(lo, float)[None], np.asarray(hi, float)[None]
    sets, proven, min_lower, min_sim = 0, 0, np.inf, np.inf
    while len(q_lo):
        if sets + min(len(q_lo), batch) > max_sets:
            return Verdict("unknown", sets, proven, min_lower, min_sim)
        b_lo, b_hi, q_lo, q_hi = q_lo[:batch], q_hi[:batch], q_lo[batch:], q_hi[batch:]
        sets += len(b_lo)
        low = reach(loop, Zonotope.from_box(b_lo, b_hi), periods, maps).min(axis=(1, 2))
        good = low >= 0.0
        proven += int(good.sum())
        if good.any():
            min_lower = min(min_lower, float(low[good].min()))
        if good.all():
            continue
        pts = _probe_points(b_lo[~good], b_hi[~good], rng)
        sim = simulate(loop, pts, periods)[0].min(axis=1)
        min_sim = min(min_sim, float(sim.min()))
        if (sim < 0.0).any():
            return Verdict("falsified", sets, proven, min_lower, min_sim,
                           pts[int(np.argmin(sim))])
        s_lo, s_hi = _split(b_lo[~good], b_hi[~good], weight)
        q_lo, q_hi = np.concatenate([q_lo, s_lo]), np.concatenate([q_hi, s_hi])
    return Verdict("verified", sets, proven, min_lower, min_sim)
