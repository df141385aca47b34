"""An adversarial leader against the real closed loop: an upper bound on any invariant set.

Any forward-invariant set S of the longitudinal loop (issue 41) lies inside the states from
which the REAL loop stays safe against every admissible leader and sensing error
(:class:`~safeil_sumo.learn.loop_invariant.LoopAssumptions`: the leader's acceleration in
``[-6, +2]`` m/s^2 at every physics step, sensing errors within ±0.2 m/s and ±0.5 m). So the
share of the recoverable envelope's volume from which SOME admissible leader and sensing
pattern makes the real loop (:mod:`.loop_rollout`) break the margin is a lower bound on what
every S must leave out: S's share is at most one minus it.

An :class:`Encounter` is one open-loop adversary: a :class:`LeaderStrategy` (phases of constant
acceleration, then braking at the limit to a stop) and a :class:`SensingPattern` (constant
biases, or a leader-speed error that ramps across its bounds when the hard braking starts, so
that the guard's leader estimate reads less braking). :func:`measure` draws states uniformly
from the envelope's volume (seeded), runs every encounter from every state and reports which
states fail: the gap ever below the margin (and contact: at or below 0).

Pure numpy; the states ``(N,)``, an encounter's results ``(N,)``, all of them ``(K, N)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from safeil_sumo.learn import loop_rollout as rollout
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.learn.loop_invariant import Grid, LoopAssumptions, LoopParts, recoverable

SETTLE_S = 2.0  # a batch ends once every car has stood this long [s]
AFTER_STOP_S = 12.0  # run this long after the leader surely stands (an ego at 50 m/s stops) [s]
MAX_RUN_S = 30.0  # [s]


@dataclass(frozen=True)
class LeaderStrategy:
    """The leader's acceleration: ``phases`` of ``(duration [s], acceleration [m/s^2])`` in
    turn, then the hardest admissible braking until it stands."""

    name: str
    phases: tuple[tuple[float, float], ...] = ()

    @property
    def onset_s(self) -> float:
        """When the final hard braking starts [s]."""
        return float(sum(d for d, _ in self.phases))

    def accel(self, periods: int, period_s: float, a: LoopAssumptions) -> np.ndarray:
        """The acceleration per decision period ``(periods,)`` [m/s^2] (phases are rounded to
        whole periods)."""
        out = np.full(periods, a.leader_accel_mps2[0])
        k = 0
        for duration, acc in self.phases:
            m = round(duration / period_s)
            out[k:k + m] = acc
            k += m
        return out

    def run_s(self, a: LoopAssumptions) -> float:
        """How long to run it [s]: until the leader surely stands, and ``AFTER_STOP_S`` more."""
        top = a.speed_limit_mps
        return min(self.onset_s + top / -a.leader_accel_mps2[0] + AFTER_STOP_S, MAX_RUN_S)


@dataclass(frozen=True)
class SensingPattern:
    """Errors ``(ego speed [m/s], leader speed [m/s], gap [m])`` added to every reading: the
    constant ``bias``; with ``ramp_s`` [s] the leader-speed error instead sits at its lowest
    bound until the hard braking starts and then rises to its highest over ``ramp_s``."""

    name: str
    bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ramp_s: float | None = None

    def errors(self, periods: int, period_s: float, onset_s: float, a: LoopAssumptions
               ) -> np.ndarray:
        """The errors per decision ``(3, periods)``, decision k at ``k * period_s``."""
        out = np.repeat(np.asarray(self.bias, float)[:, None], periods, axis=1)
        if self.ramp_s is not None:
            t = np.arange(periods) * period_s
            rise = np.clip((t - onset_s) / max(self.ramp_s, 1e-9), 0.0, 1.0)
            out[1] = a.speed_sensing_mps * (2.0 * rise - 1.0)
        return out


@dataclass(frozen=True)
class Encounter:
    leader: LeaderStrategy
    sensing: SensingPattern

    @property
    def name(self) -> str:
        return f"{self.leader.name} / {self.sensing.name}"


def admissible(enc: Encounter, a: LoopAssumptions, periods: int = 300) -> bool:
    """Whether the encounter stays within the assumptions: leader accelerations in their range,
    every sensing error within its bound."""
    period = a.step_s * a.steps_per_decision
    acc = enc.leader.accel(periods, period, a)
    err = enc.sensing.errors(periods, period, enc.leader.onset_s, a)
    bound = np.array([[a.speed_sensing_mps], [a.speed_sensing_mps], [a.gap_sensing_m]])
    lo, hi = a.leader_accel_mps2
    return bool(np.all((acc >= lo) & (acc <= hi)) and np.all(np.abs(err) <= bound + 1e-12))


def optimistic(a: LoopAssumptions) -> tuple[float, float, float]:
    """The sensing corner that makes the situation look safest: the ego slower, the leader
    faster, the gap longer."""
    return -a.speed_sensing_mps, a.speed_sensing_mps, a.gap_sensing_m


def default_leaders(a: LoopAssumptions) -> tuple[LeaderStrategy, ...]:
    """Brake at the limit now; keep speed or accelerate at the limit for t, then brake; brake
    mildly (under the guard's activation) for t, then at the limit; brake at the limit for 1 s,
    release for t (the guard's estimate decays), brake again."""
    b, up = a.leader_accel_mps2
    out = [LeaderStrategy(f"brake {-b:g} now")]
    out += [LeaderStrategy(f"keep {t:g} s, brake", ((t, 0.0),)) for t in (1.0, 3.0)]
    out += [LeaderStrategy(f"accelerate {t:g} s, brake", ((t, up),)) for t in (0.5, 2.0)]
    out += [LeaderStrategy(f"brake {m:g} for {t:g} s, then {-b:g}", ((t, -m),))
            for m in (1.0, 2.5) for t in (2.0, 5.0)]
    out += [LeaderStrategy(f"brake 1 s, release {t:g} s, brake", ((1.0, b), (t, 0.0)))
            for t in (1.0, 3.0)]
    return tuple(out)


def default_encounters(a: LoopAssumptions) -> tuple[Encounter, ...]:
    """Every default leader with exact sensing, the optimistic corner and the optimistic
    corner with the leader-speed error ramping over 0.3 s at the hard braking; the first leader
    (braking now) also with every other corner of the sensing box."""
    opt = optimistic(a)
    patterns = (SensingPattern("exact"), SensingPattern("optimistic corner", opt),
                SensingPattern("optimistic, leader-speed ramp 0.3 s", opt, 0.3))
    leaders = default_leaders(a)
    out = [Encounter(lead, p) for lead in leaders for p in patterns]
    s, g = a.speed_sensing_mps, a.gap_sensing_m
    corners = [(e, l_, d) for e in (-s, s) for l_ in (-s, s) for d in (-g, g)]
    out += [Encounter(leaders[0], SensingPattern(f"corner {c}", c)) for c in corners if c != opt]
    return tuple(out)


def mild_sweep_encounters(a: LoopAssumptions) -> tuple[Encounter, ...]:
    """Mild braking swept wider, under the optimistic corner: 2, 3 or 4 m/s^2 for 3 or 8 s,
    then at the limit; beside the default encounters that find most (braking now, mild 2.5
    m/s^2 for 5 s, brake-release-brake), so that their union bounds the defaults' union with
    the sweep from below."""
    b = a.leader_accel_mps2[0]
    opt = SensingPattern("optimistic corner", optimistic(a))
    leaders = default_leaders(a)
    out = [LeaderStrategy(f"brake {m:g} for {t:g} s, then {-b:g}", ((t, -m),))
           for m in (2.0, 3.0, 4.0) for t in (3.0, 8.0)]
    return tuple(Encounter(lead, opt) for lead in (leaders[0], leaders[8], leaders[9], *out))


def random_encounters(count: int, rng: np.random.Generator, a: LoopAssumptions
                      ) -> tuple[Encounter, ...]:
    """``count`` random leaders under the optimistic corner, besides the default encounters
    (they may find states no scripted leader does): 1-4 phases, each 0.5-5 s long (whole
    decision periods) at an acceleration uniform in the admissible range, then the hardest
    braking; drawn from ``rng``."""
    lo, hi = a.leader_accel_mps2
    opt = SensingPattern("optimistic corner", optimistic(a))
    out = []
    for k in range(count):
        phases = tuple((round(float(rng.uniform(0.5, 5.0)), 1), float(rng.uniform(lo, hi)))
                       for _ in range(int(rng.integers(1, 5))))
        out.append(Encounter(LeaderStrategy(f"random {k}", phases), opt))
    return (*default_encounters(a), *out)


def envelope_states(n: int, grid: Grid, a: LoopAssumptions, parts: LoopParts,
                    rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """``n`` states ``(g, v, v_l, f)`` ``(n,)`` each, uniform over the recoverable envelope's
    volume inside the grid's box (drawn uniformly from the box, the unrecoverable rejected)."""
    lo = np.array([ax[0] for ax in grid.axes()])
    hi = np.array([ax[-1] for ax in grid.axes()])
    kept: list[np.ndarray] = []
    count = 0
    while count < n:
        x = rng.uniform(lo, hi, (2 * n, 4))
        x = x[recoverable(x[:, 0], x[:, 1], x[:, 2], x[:, 3], a, parts.vehicle)]
        kept.append(x)
        count += len(x)
    x = np.concatenate(kept)[:n]
    return x[:, 0], x[:, 1], x[:, 2], x[:, 3]


def run_encounters(policy: MLPPolicy, states: tuple[np.ndarray, ...], time_gap: float,
                   encounters: tuple[Encounter, ...], guard_on: bool, a: LoopAssumptions,
                   parts: LoopParts) -> np.ndarray:
    """The smallest gap [m] ``(K, N)`` the real loop meets from each of N states under each of
    the K encounters (the encounters of one leader run as one batch, for as long as the leader
    needs: :meth:`LeaderStrategy.run_s`, ending early once every car has stood
    ``SETTLE_S``)."""
    period = a.step_s * a.steps_per_decision
    n = len(states[0])
    out = np.empty((len(encounters), n))
    leaders = list(dict.fromkeys(e.leader for e in encounters))
    for leader in leaders:
        rows = [i for i, e in enumerate(encounters) if e.leader == leader]
        periods = math.ceil(leader.run_s(a) / period - 1e-9)
        acc = np.tile(leader.accel(periods, period, a), (n * len(rows), 1))
        err = np.concatenate([np.broadcast_to(
            encounters[i].sensing.errors(periods, period, leader.onset_s, a)[:, None, :],
            (3, n, periods)) for i in rows], axis=1)
        g, v, vl, f = (np.tile(x, len(rows)) for x in states)
        got = rollout.run(policy, g, v, vl, f, time_gap, acc, err, guard_on, a, parts, periods,
                          settle_s=SETTLE_S)
        out[rows] = got.g_min.reshape(len(rows), n)
    return out


@dataclass(frozen=True)
class Measurement:
    """The adversary's result at one setting: the smallest gaps ``g_min (K, N)`` [m] of the
    encounters from the N states."""

    time_gap: float
    guard_on: bool
    encounters: tuple[Encounter, ...]
    g_min: np.ndarray

    def share(self, failed: np.ndarray) -> tuple[float, float]:
        """The share of the envelope's volume of states ``failed (N,)`` and its standard error
        (the states are uniform over the volume: a binomial proportion)."""
        p = float(np.mean(failed))
        return p, math.sqrt(max(p * (1.0 - p), 0.0) / failed.size)

    def union_failed(self, margin_m: float) -> np.ndarray:
        """States ``(N,)`` whose gap falls below ``margin_m`` under some encounter."""
        return np.any(self.g_min < margin_m, axis=0)

    def by_encounter(self, margin_m: float) -> list[tuple[str, float, float]]:
        """Per encounter: its own failing share, and the share only it finds (no other
        encounter takes those states below ``margin_m``)."""
        fails = self.g_min < margin_m
        others = fails.sum(axis=0) - fails
        n = fails.shape[1]
        return [(e.name, float(fails[k].sum() / n), float((fails[k] & (others[k] == 0)).sum()
                                                           / n))
                for k, e in enumerate(self.encounters)]


def measure(policy: MLPPolicy, time_gap: float, guard_on: bool, n: int,
            rng: np.random.Generator, a: LoopAssumptions | None = None,
            parts: LoopParts | None = None, grid: Grid | None = None,
            encounters: tuple[Encounter, ...] | None = None) -> Measurement:
    """``n`` states drawn from ``rng`` uniformly over the recoverable envelope in ``grid``'s box,
    each run through every encounter (default :func:`default_encounters`) by the real loop at
    the planner's ``time_gap`` [s] setting, the guard on or off (defaults: the assumptions,
    parts and grid of :mod:`.loop_invariant`)."""
    a, parts, grid = a or LoopAssumptions(), parts or LoopParts(), grid or Grid()
    encounters = default_encounters(a) if encounters is None else encounters
    bad = [e.name for e in encounters if not admissible(e, a)]
    if bad:
        raise ValueError(f"encounters outside the assumptions: {bad}")
    states = envelope_states(n, grid, a, parts, rng)
    g_min = run_encounters(policy, states, time_gap, encounters, guard_on, a, parts)
    return Measurement(time_gap, guard_on, encounters, g_min)
