"""A driver's style in two numbers, learned as the driver is watched: standstill distance s0 [m]
and time gap T [s] of the steady-following gap ``gap = s0 + T v``.

A recursive Bayesian (Kalman) estimate of ``theta = (s0, T)`` from steady-following samples:

- **prior** (:class:`StylePrior`): a Gaussian population of drivers, mean and covariance of
  (s0, T) measured on the shipped ``safeil``'s real training maneuvers
  (``python training/style_prior.py``: a random-effects fit of the per-maneuver least-squares
  lines, each maneuver's own estimation error taken out);
- **observation**: one steady-following sample ``(gap_m, speed_mps)`` is
  ``gap = [1, v] theta + e``, ``e ~ N(0, R(v))``, ``R(v) = (noise_rel * g0(v))^2 *
  correlation_s / dt_s`` with ``g0(v) = s0_prior + T_prior v`` the population's gap at that
  speed: the gap's scatter about a driver's line grows with speed (measured relative,
  ``noise_rel``), and samples ``dt_s`` apart are not independent (one independent observation
  per ``correlation_s``, the residuals' measured correlation time), so the posterior is as sure as
  the data allow and no surer;
- **forgetting** (:func:`forget`): between samples the driver's style may drift back towards the
  population, an Ornstein-Uhlenbeck process with time constant ``forget_tau_s``:
  ``theta' = mu0 + a (theta - mu0) + w``, ``a = exp(-elapsed / tau)``, ``w ~ N(0, (1 - a^2)
  P0)``. Its stationary law is the prior itself, so the covariance never exceeds the prior's and
  never collapses to zero (each step adds ``(1 - a^2) P0``): an estimate keeps following a
  driver whose gap-speed line changes with the traffic (the line is only locally linear:
  OpenACC drivers at 20-37 m/s keep longer time gaps the faster they go), and without steady
  following it returns to the population over ``tau``. ``forget_tau_s = inf``: no forgetting,
  the default: within the recorded drives (at most 6 min) every finite tau predicted a
  driver's later gaps worse (:attr:`StylePrior.forget_tau_s`), so forgetting is for drives much
  longer than those.

State and update are pure: :class:`StyleEstimate` is a frozen dataclass, :func:`update` returns
a new one. :func:`steady_following` selects the samples (criteria at its constants);
:func:`estimate_drive` runs the filter over a drive's rows and returns the estimate at every row
(for a plot, :func:`plot_convergence`). numpy only (matplotlib imported by the plot only).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

# steady following (steady_following): the samples that say where a driver settles
STEADY_MIN_SPEED_MPS = 2.0  # [m/s] slower: a queue's creep, gap noise ~ the gap itself
STEADY_MAX_REL_SPEED_MPS = 1.0  # [m/s] |v_lead - v| above: closing or opening, not settled
STEADY_MAX_ACCEL_MPS2 = 0.5  # [m/s^2] |ego acceleration| above: a transient
STEADY_MAX_TIME_GAP_S = 5.0  # [s] gap / v above: not following (the NGSIM pairs' own ceiling)
STEADY_MIN_GAP_M = 0.5  # [m] below: a reconstruction artefact, not a gap


def steady_following(gap_m, speed_mps, lead_speed_mps, accel_mps2=None) -> np.ndarray:
    """Which samples are steady following, a bool mask ``(N,)`` for arrays ``(N,)``: bumper
    gap ``gap_m`` [m], ego speed ``speed_mps`` [m/s], leader speed ``lead_speed_mps`` [m/s] and
    (optional) ego acceleration ``accel_mps2`` [m/s^2]. A sample is steady when it is finite and

    - the ego is faster than :data:`STEADY_MIN_SPEED_MPS` (2 m/s),
    - the relative speed ``|v_lead - v|`` is below :data:`STEADY_MAX_REL_SPEED_MPS` (1 m/s),
    - ``|accel|`` is below :data:`STEADY_MAX_ACCEL_MPS2` (0.5 m/s^2), when given,
    - the time gap ``gap / v`` is below :data:`STEADY_MAX_TIME_GAP_S` (5 s) and the gap above
      :data:`STEADY_MIN_GAP_M` (0.5 m).

    Low speeds are kept on purpose (from 2 m/s): a queue moving steadily is where the standstill
    distance shows."""
    gap = np.asarray(gap_m, float)
    v = np.asarray(speed_mps, float)
    vl = np.asarray(lead_speed_mps, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = (np.isfinite(gap) & np.isfinite(v) & np.isfinite(vl) & (v > STEADY_MIN_SPEED_MPS)
              & (np.abs(vl - v) < STEADY_MAX_REL_SPEED_MPS) & (gap > STEADY_MIN_GAP_M)
              & (gap < STEADY_MAX_TIME_GAP_S * v))
        if accel_mps2 is not None:
            a = np.asarray(accel_mps2, float)
            ok &= np.isfinite(a) & (np.abs(a) < STEADY_MAX_ACCEL_MPS2)
    return ok


@dataclass(frozen=True)
class StyleEstimate:
    """The posterior of a driver's (s0, T): Gaussian, mean ``(s0_m, time_gap_s)`` and
    covariance ``[[var_s0_m2, cov_s0_time_gap_ms], [cov_s0_time_gap_ms, var_time_gap_s2]]``;
    ``samples``: steady samples used, ``seen_s`` [s]: the time they cover, ``mean_speed_mps``
    [m/s]: their mean speed."""

    s0_m: float  # [m] standstill distance
    time_gap_s: float  # [s] time gap
    var_s0_m2: float  # [m^2]
    cov_s0_time_gap_ms: float  # [m s]
    var_time_gap_s2: float  # [s^2]
    samples: int = 0
    seen_s: float = 0.0
    # [m/s] the mean speed of the samples used (NaN before any): where the line is best known
    mean_speed_mps: float = math.nan

    @property
    def mean(self) -> np.ndarray:
        """``(2,)``: ``[s0 [m], T [s]]``."""
        return np.array([self.s0_m, self.time_gap_s])

    @property
    def cov(self) -> np.ndarray:
        """``(2, 2)``: the covariance of ``[s0, T]`` [m^2, m s; m s, s^2]."""
        c = self.cov_s0_time_gap_ms
        return np.array([[self.var_s0_m2, c], [c, self.var_time_gap_s2]])

    @property
    def sd_s0_m(self) -> float:
        return math.sqrt(max(self.var_s0_m2, 0.0))

    @property
    def sd_time_gap_s(self) -> float:
        return math.sqrt(max(self.var_time_gap_s2, 0.0))

    def gap_m(self, speed_mps: float) -> float:
        """The estimated steady gap [m] at ``speed_mps`` [m/s]: ``s0 + T v``."""
        return self.s0_m + self.time_gap_s * float(speed_mps)

    def setting_s(self, speed_mps: float) -> float:
        """The one time gap [s] that gives the estimated steady gap at ``speed_mps`` [m/s]
        (``s0 / v + T``): what a planner with a time-gap input only (``gap = T v``) is set to,
        to keep this driver's gap at that speed."""
        return self.gap_m(speed_mps) / float(speed_mps)


def _from(mean: np.ndarray, cov: np.ndarray, samples: int, seen_s: float,
          mean_speed_mps: float = math.nan) -> StyleEstimate:
    cov = 0.5 * (cov + cov.T)  # symmetric to round-off
    return StyleEstimate(float(mean[0]), float(mean[1]), float(cov[0, 0]), float(cov[0, 1]),
                         float(cov[1, 1]), int(samples), float(seen_s), float(mean_speed_mps))


@dataclass(frozen=True)
class StylePrior:
    """The population of drivers before any of a driver's samples is seen, and the observation
    and forgetting model. Defaults measured by ``python training/style_prior.py`` on the shipped
    ``safeil``'s training maneuvers (NGSIM I-80 and OpenACC Vicolungo, 10 Hz, its held-out
    maneuvers left out; steady samples as :func:`steady_following`)."""

    # random-effects fit of the maneuvers' lines: a line is local (a maneuver spans a few m/s),
    # so its intercept is an extrapolation and may be negative; the mean is the population's
    s0_m: float = -0.76  # [m] population mean standstill distance (of the local lines)
    time_gap_s: float = 1.64  # [s] population mean time gap
    sd_s0_m: float = 7.51  # [m] between maneuvers
    sd_time_gap_s: float = 0.95  # [s] between maneuvers
    corr: float = -0.78  # [-] correlation of s0 and T between maneuvers
    # [-] sd of a steady sample's gap about its maneuver's line, relative to the line's gap
    # (median over the maneuvers)
    noise_rel: float = 0.138
    # [s] integral correlation time of those residuals (median over the maneuvers): one
    # independent observation per correlation_s of steady samples
    correlation_s: float = 3.33
    # [s] forgetting time constant (module doc); inf: none, the default. Measured
    # (training/style_prior.py): predicting the gap of each steady sample from the estimate
    # 30 s before it, every finite tau tried predicts worse on the training maneuvers (mean
    # abs error 6.15 m without forgetting; 6.55 m at 3,600 s, 6.73 at 1,200 s, 6.92 at 300 s):
    # within the recorded drives (at most 6 min) a driver's line does not drift measurably,
    # and what forgetting follows is the gap's fluctuation, which does not persist. A finite
    # tau is for drives much longer than those (a change of traffic or driver)
    forget_tau_s: float = math.inf

    @property
    def mean(self) -> np.ndarray:
        """``(2,)``: ``[s0 [m], T [s]]``."""
        return np.array([self.s0_m, self.time_gap_s])

    @property
    def cov(self) -> np.ndarray:
        """``(2, 2)``: the population covariance of ``[s0, T]``."""
        c = self.corr * self.sd_s0_m * self.sd_time_gap_s
        return np.array([[self.sd_s0_m ** 2, c], [c, self.sd_time_gap_s ** 2]])

    def initial(self) -> StyleEstimate:
        """The estimate before any sample: the prior itself."""
        return _from(self.mean, self.cov, 0, 0.0)

    def noise_var_m2(self, speed_mps: float, dt_s: float) -> float:
        """``R(v)`` [m^2]: the variance one sample ``dt_s`` [s] after the last counts with
        (module doc): the relative scatter at the population's gap, inflated by
        ``correlation_s / dt_s`` (at least 1: a sample is never worth more than one)."""
        g0 = max(self.s0_m + self.time_gap_s * float(speed_mps), STEADY_MIN_GAP_M)
        inflation = max(self.correlation_s / max(float(dt_s), 1e-9), 1.0)
        return (self.noise_rel * g0) ** 2 * inflation


def forget(state: StyleEstimate, prior: StylePrior, elapsed_s: float) -> StyleEstimate:
    """``state`` after ``elapsed_s`` [s] without a sample: relaxed towards the prior with
    ``a = exp(-elapsed_s / prior.forget_tau_s)``: mean ``mu0 + a (m - mu0)``, covariance
    ``a^2 P + (1 - a^2) P0``. No time, or no forgetting (tau inf): ``state`` itself."""
    if elapsed_s <= 0 or not math.isfinite(prior.forget_tau_s):
        return state
    a = math.exp(-float(elapsed_s) / prior.forget_tau_s)
    mean = prior.mean + a * (state.mean - prior.mean)
    cov = a * a * state.cov + (1.0 - a * a) * prior.cov
    return _from(mean, cov, state.samples, state.seen_s, state.mean_speed_mps)


def update(state: StyleEstimate, gap_m: float, speed_mps: float, prior: StylePrior,
           dt_s: float = 0.1, elapsed_s: float = 0.0) -> StyleEstimate:
    """The posterior after one steady sample: bumper gap ``gap_m`` [m] at ego speed
    ``speed_mps`` [m/s], ``dt_s`` [s] after the previous sample (it sets the sample's weight,
    :meth:`StylePrior.noise_var_m2`), ``elapsed_s`` [s] of forgetting first (:func:`forget`).

    The Kalman update with ``h = [1, v]``: ``S = h P h' + R``, ``K = P h' / S``,
    ``m' = m + K (gap - h m)``, ``P' = P - K h P``. A non-finite sample returns the (forgotten)
    state unchanged: select samples with :func:`steady_following`."""
    state = forget(state, prior, elapsed_s)
    gap, v = float(gap_m), float(speed_mps)
    if not (math.isfinite(gap) and math.isfinite(v)):
        return state
    h = np.array([1.0, v])
    p = state.cov
    ph = p @ h
    s = float(h @ ph) + prior.noise_var_m2(v, dt_s)
    k = ph / s
    mean = state.mean + k * (gap - float(h @ state.mean))
    cov = p - np.outer(k, ph)
    n = state.samples
    speed = v if n == 0 else (n * state.mean_speed_mps + v) / (n + 1)
    return _from(mean, cov, n + 1, state.seen_s + float(dt_s), speed)


class StyleTrajectory(NamedTuple):
    """The estimate after every row of a drive, arrays ``(N,)``: ``time_s`` [s], ``s0_m`` [m],
    ``time_gap_s`` [s], their posterior sds ``sd_s0_m`` [m] and ``sd_time_gap_s`` [s], and
    ``steady`` (bool: the row was used)."""

    time_s: np.ndarray
    s0_m: np.ndarray
    time_gap_s: np.ndarray
    sd_s0_m: np.ndarray
    sd_time_gap_s: np.ndarray
    steady: np.ndarray


def acceleration_mps2(time_s, speed_mps) -> np.ndarray:
    """Ego acceleration [m/s^2] ``(N,)`` by central differences of ``speed_mps`` over
    ``time_s`` (NaN for fewer than 2 samples)."""
    t = np.asarray(time_s, float)
    v = np.asarray(speed_mps, float)
    if len(t) < 2:
        return np.full(len(t), np.nan)
    return np.gradient(v, t)


def estimate_drive(time_s, gap_m, speed_mps, lead_speed_mps, prior: StylePrior | None = None,
                   state: StyleEstimate | None = None) -> tuple[StyleEstimate, StyleTrajectory]:
    """Run the filter over one drive's rows, arrays ``(N,)`` in time order: ``time_s`` [s],
    bumper gap ``gap_m`` [m], ego and leader speed [m/s]. Steady rows
    (:func:`steady_following`, the acceleration from the speeds) update the estimate, each
    weighted by the time since the previous row; every row forgets the time since the previous
    one. Returns the final estimate and the estimate after every row. ``state``: start from it
    (default the prior's)."""
    prior = prior or StylePrior()
    t = np.asarray(time_s, float)
    gap = np.asarray(gap_m, float)
    v = np.asarray(speed_mps, float)
    steady = steady_following(gap, v, lead_speed_mps, acceleration_mps2(t, v))
    state = state or prior.initial()
    n = len(t)
    out = np.empty((5, n))
    dts = np.diff(t, prepend=t[0] if n else 0.0)
    nominal = float(np.median(dts[1:])) if n > 1 else 0.1
    for i in range(n):
        dt = float(dts[i]) if i else nominal
        if steady[i]:
            state = update(state, gap[i], v[i], prior, dt_s=dt, elapsed_s=dt if i else 0.0)
        elif i:
            state = forget(state, prior, dt)
        out[:, i] = (state.s0_m, state.time_gap_s, state.sd_s0_m, state.sd_time_gap_s, 0.0)
    return state, StyleTrajectory(t, out[0], out[1], out[2], out[3], steady)


def least_squares_style(gap_m, speed_mps) -> tuple[float, float]:
    """The ordinary least-squares line ``gap = s0 + T v`` [m, s] through samples ``(N,)``
    (NaN, NaN with fewer than 2 distinct speeds): a drive's hindsight values."""
    gap = np.asarray(gap_m, float)
    v = np.asarray(speed_mps, float)
    ok = np.isfinite(gap) & np.isfinite(v)
    if ok.sum() < 2 or np.ptp(v[ok]) <= 0:
        return math.nan, math.nan
    x = np.column_stack([np.ones(ok.sum()), v[ok]])
    (s0, t_gap), *_ = np.linalg.lstsq(x, gap[ok], rcond=None)
    return float(s0), float(t_gap)


def bounded_style(state: StyleEstimate, s0_range_m: tuple[float, float],
                  time_gap_range_s: tuple[float, float]) -> tuple[float, float]:
    """``(s0 [m], T [s])`` of ``state`` inside the ranges a planner accepts (e.g. the IDM's
    calibration bounds): s0 clipped, then T chosen so that the line keeps its gap at the mean
    speed of the samples used (where the data fixed it; a local line's intercept is an
    extrapolation) and clipped. Before any sample: the prior's mean, clipped."""
    s0 = min(max(state.s0_m, s0_range_m[0]), s0_range_m[1])
    t_gap = state.time_gap_s
    v = state.mean_speed_mps
    if state.samples and math.isfinite(v) and v > 0:
        t_gap = (state.gap_m(v) - s0) / v
    return s0, min(max(t_gap, time_gap_range_s[0]), time_gap_range_s[1])


def plot_convergence(traj: StyleTrajectory, path, hindsight: tuple[float, float] | None = None,
                     title: str = "") -> None:
    """Save a two-panel figure: s0 and T against time with their +-1 sd bands, the rows used
    shaded, the drive's whole-drive least-squares values (``hindsight`` (s0, T)) dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = traj.time_s - (traj.time_s[0] if len(traj.time_s) else 0.0)
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    panels = ((traj.s0_m, traj.sd_s0_m, "standstill distance s0 [m]"),
              (traj.time_gap_s, traj.sd_time_gap_s, "time gap T [s]"))
    for k, (ax, (m, sd, label)) in enumerate(zip(axes, panels, strict=True)):
        ax.fill_between(t, m - sd, m + sd, color="C0", alpha=0.25, lw=0, label="±1 sd")
        ax.plot(t, m, color="C0", lw=1.4, label="estimate")
        if hindsight is not None and np.isfinite(hindsight[k]):
            ax.axhline(hindsight[k], color="k", ls="--", lw=1.1,
                       label="whole-drive least squares")
        lo, hi = ax.get_ylim()
        ax.fill_between(t, lo, hi, where=traj.steady, color="0.85", lw=0, step="mid",
                        label="steady following", zorder=0)
        ax.set_ylim(lo, hi)
        ax.set_ylabel(label)
        ax.legend(fontsize=7, loc="best")
    axes[-1].set_xlabel("time in the drive [s]")
    if title:
        axes[0].set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
