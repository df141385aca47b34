"""Falsification: an adaptive search for the closed-loop scenarios where a planner fails.

    python -m safeil_sumo.falsify --policy bc --method cem --budget-sims 2000 --batch 50 --seed 0

What is searched: a point ``u`` of the unit box ``[0, 1]^D``, decoded (:func:`decode`) into a
task whose scenario is of the leader-response suite's kinds (:mod:`.suite`): a scripted leader
at ``gap_m`` ahead and ``leader_speed_mps`` (a small gap and a slower leader is the suite's
cut-in, modelled as its end state), which brakes at ``brake_decel_mps2`` from
``brake_onset_s`` for ``brake_duration_s``; or a recorded NGSIM leader window
(:mod:`safeil_sumo.scenarios.recorded_leaders`, drawn from the spec's seed); on a track of
radius ``track`` (:data:`NETS`), with radar and camera noise. Every parameter, its range and
unit is in :data:`BOX`.

The objective (:func:`score`, minimised): the run's min TTC [s], capped at
:data:`TTC_CAP_S`, and at most :data:`TTC_FLAG_S` for a run with any flag (TTC <= 1 s, lane
departure, collision) — but only over *avoidable* scenarios: those where braking at 6 m/s^2
from the start (the suite's :func:`.suite.braking_avoids`) keeps the ego behind its leader
with TTC > 1 s over the run (:func:`avoidable`). Unavoidable scenarios score ``inf``: a
planner is not blamed for physics. A *failure* is a flagged avoidable run.

Methods (:func:`search`), each from one explicit seed: ``random`` (uniform in the box) and
``cem`` (the cross-entropy method: the first batch uniform, then a Gaussian per coordinate
refit to the batch's elite fraction, smoothed, clipped to the box: :func:`cem_update`). A
batch runs on the task engine (:func:`.task_engine.execute`) as sweep tasks: one SUMO
simulation (the batched closed loop) in this process, or split over local workers or a Dask
cluster; each run's record is kept as it ends, so an interrupted search started again reads
the runs it had (the same seed draws the same points) and simulates only the rest.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.experiments.suite import BRAKE_AVOID_MPS2, TTC_FLAG_S, braking_avoids
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.sim.brake_guard import when as brake_guard_when
from safeil_sumo.sim.loop_types import LoopConfig

TTC_CAP_S = 10.0  # [s] a min TTC above this (or inf: never closing) scores this
AVOID_STEP_S = 0.01  # [s] step of the braking reference (the loop's physics step)
# the tracks searched, straight to tightest curve (the results' radius grid)
NETS = ("straight", "curved1000", "curved750", "curved500", "curved300")
RECORDED_FROM = 0.75  # leader_source >= this: a recorded NGSIM window (a quarter of the box)
SCENARIO_SEEDS = 1000  # the scenario seeds searched (recorded window, sensor noise draws)
EGO_SPEED_MPS = 30.0  # [m/s] the ego's start behind a scripted leader (the suite's)
METHODS = ("cem", "random")


@dataclass(frozen=True)
class Param:
    """One coordinate of the search box: ``u`` in [0, 1] maps to ``low + u (high - low)``
    (``categorical``: to one of ``int(high)`` choices)."""

    name: str
    low: float
    high: float
    unit: str
    doc: str
    categorical: bool = False

    def value(self, u: float) -> float:
        if self.categorical:
            return float(min(int(u * self.high), int(self.high) - 1))
        return self.low + float(u) * (self.high - self.low)


BOX: tuple[Param, ...] = (
    Param("leader_source", 0.0, 1.0, "-",
          f"< {RECORDED_FROM}: a scripted leader (braking, cut-in); else a recorded NGSIM window"),
    Param("scenario_seed", 0.0, SCENARIO_SEEDS, "-",
          "the spec's master seed: the recorded window drawn and the sensor noise", True),
    Param("gap_m", 5.0, 80.0, "m", "initial bumper gap (a cut-in's distance)"),
    Param("leader_speed_mps", 10.0, 35.0, "m/s",
          "the leader's initial speed (the ego starts at 30 m/s: a cut-in's speed)"),
    Param("brake_onset_s", 0.0, 15.0, "s", "the leader starts braking at"),
    Param("brake_decel_mps2", 0.5, 9.0, "m/s^2", "the leader's deceleration"),
    Param("brake_duration_s", 0.0, 10.0, "s", "how long it brakes (down to 0 m/s at most)"),
    Param("track", 0.0, len(NETS), "-", f"the track: one of {', '.join(NETS)}", True),
    Param("radar_noise_m", 0.0, 1.5, "m", "std of the radar's range noise"),
    Param("lane_noise_m", 0.0, 0.2, "m", "std of the camera's lane-offset noise"),
)
DIM = len(BOX)


@dataclass(frozen=True)
class SearchConfig:
    """One search: method, budget and the cross-entropy method's settings."""

    method: str = "cem"  # "cem" or "random"
    budget: int = 2000  # simulations (closed-loop scenarios) the search may spend [-]
    batch: int = 50  # scenarios per SUMO simulation, and per CEM update [-]
    seed: int = 0  # seeds every draw of the search (same seed: same scenarios) [-]
    elite_fraction: float = 0.2  # CEM: share of a batch, lowest scores, refit to [-]
    smoothing: float = 0.7  # CEM: weight of the refit against the previous mean and std [-]
    min_std: float = 0.02  # CEM: floor of each coordinate's std, in box units [-]
    max_time_s: float = 30.0  # scenario duration [s]
    stop_at_failure: bool = False  # end the search after the batch of its first failure
    # the loop's brake guard under the planner (safeil_sumo.sim.brake_guard), as shipped;
    # False searches the planner and tracker alone
    brake_guard: bool = True

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.budget < 1 or self.batch < 1:
            raise ValueError(f"budget and batch must be >= 1, got {self.budget}, {self.batch}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not 0.0 < self.elite_fraction <= 1.0 or not 0.0 < self.smoothing <= 1.0:
            raise ValueError("elite fraction and smoothing must be in (0, 1]")
        if not 0.0 < self.min_std <= 0.5:
            raise ValueError(f"min std must be in (0, 0.5], got {self.min_std}")
        if not self.max_time_s > 0:
            raise ValueError(f"max time must be > 0 s, got {self.max_time_s}")


@dataclass(frozen=True)
class Outcome:
    """One evaluated scenario: its ``score`` (minimised; inf: excluded) and whether it is a
    failure (a flagged avoidable run); the rest for the report."""

    score: float
    failure: bool
    min_ttc_s: float = math.nan
    flag: str = ""
    avoidable: bool = True
    error: str = ""


@dataclass
class SearchResult:
    """A finished search: the points ``u (S, D)`` in order of evaluation, their outcomes."""

    config: SearchConfig
    u: np.ndarray
    outcomes: list[Outcome] = field(default_factory=list)

    @property
    def scores(self) -> np.ndarray:
        return np.array([o.score for o in self.outcomes], float)

    @property
    def best_so_far(self) -> np.ndarray:
        """The lowest score after each simulation ``(S,)`` (inf until an avoidable one)."""
        return np.minimum.accumulate(self.scores) if self.outcomes else np.zeros(0)

    @property
    def first_failure(self) -> int | None:
        """Simulations spent up to and including the first failure (in order of draw)."""
        return next((k + 1 for k, o in enumerate(self.outcomes) if o.failure), None)

    @property
    def best(self) -> int:
        """Index of the lowest score (the first of equals)."""
        return int(np.argmin(self.scores))


# ------------------------------------------------------------------------ pure search logic


def score(min_ttc_s: float, flag: str, avoidable: bool) -> float:
    """The objective of one run: ``inf`` if unavoidable, else its min TTC capped at
    :data:`TTC_CAP_S` (NaN, no leader seen: the cap), at most :data:`TTC_FLAG_S` if flagged."""
    if not avoidable:
        return math.inf
    s = TTC_CAP_S if math.isnan(min_ttc_s) else min(float(min_ttc_s), TTC_CAP_S)
    return min(s, TTC_FLAG_S) if flag else s


def avoidable(leader_speed: Callable[[np.ndarray], np.ndarray], gap_m: float,
              ego_speed_mps: float, horizon_s: float, step_s: float = AVOID_STEP_S,
              decel_mps2: float = BRAKE_AVOID_MPS2) -> bool:
    """Could braking at ``decel_mps2`` from the start have kept the ego behind a leader of speed
    ``leader_speed(t)`` [m/s] with TTC > 1 s for ``horizon_s`` [s]? (:func:`.suite.
    braking_avoids` on the leader's profile, at ``step_s``.)"""
    times = np.arange(0.0, max(horizon_s, step_s) + 0.5 * step_s, step_s)
    speeds = np.asarray(leader_speed(times), float) * np.ones_like(times)
    return braking_avoids(times, gap_m, ego_speed_mps, speeds, decel_mps2, TTC_FLAG_S)


def values(u: np.ndarray) -> dict[str, float]:
    """The box's parameters at ``u (D,)`` in [0, 1] (clipped), by name, in their units."""
    u = np.clip(np.asarray(u, float), 0.0, 1.0)
    if u.shape != (DIM,):
        raise ValueError(f"a point of the box has {DIM} coordinates, got shape {u.shape}")
    return {p.name: p.value(x) for p, x in zip(BOX, u, strict=True)}


def decode(u: np.ndarray, policy: str, max_time_s: float = 30.0,
           brake_guard: bool = True) -> Task:
    """The :class:`Task` at ``u (D,)``: its scenario driven by ``policy``, with the brake guard
    or without. Always ``index = 0``: the scenario's draws come from ``master_seed`` (the
    ``scenario_seed`` coordinate), so ``sweep --seed`` reruns it."""
    return Task(decode_scenario(u, max_time_s), PlannerRef(policy),
                LoopConfig(brake_guard=brake_guard_when(brake_guard)))


def decode_scenario(u: np.ndarray, max_time_s: float = 30.0) -> ScenarioSpec:
    """The :class:`ScenarioSpec` at ``u (D,)`` (index 0)."""
    v = values(u)
    common = {"net": NETS[int(v["track"])], "index": 0, "master_seed": int(v["scenario_seed"]),
              "max_time_s": max_time_s, "radar_noise_m": round(v["radar_noise_m"], 3),
              "lane_noise_c0_m": round(v["lane_noise_m"], 4)}
    if v["leader_source"] >= RECORDED_FROM:
        return ScenarioSpec(leader_kind="recorded", leader_profile="ngsim", **common)
    speed = round(v["leader_speed_mps"], 2)
    decel = round(v["brake_decel_mps2"], 2)
    to = round(max(0.0, speed - decel * v["brake_duration_s"]), 2)
    return ScenarioSpec(leader_kind="braking", leader_speed_range_mps=(speed, speed),
                        initial_gap_m=round(v["gap_m"], 2), ego_speed_mps=EGO_SPEED_MPS,
                        brake_time_s=round(v["brake_onset_s"], 2), brake_decel_mps2=decel,
                        brake_to_mps=to, **common)


def uniform_std() -> float:
    """The std of U(0, 1): the spread the CEM's first (uniform) batch is treated as having."""
    return 1.0 / math.sqrt(12.0)


def cem_update(u: np.ndarray, scores: np.ndarray, mean: np.ndarray, std: np.ndarray,
               config: SearchConfig) -> tuple[np.ndarray, np.ndarray]:
    """The cross-entropy method's step: ``mean, std (D,)`` moved towards the mean and std of
    the elite: the ``ceil(elite_fraction * S)`` (at least 2) lowest finite ``scores (S,)`` of
    the batch ``u (S, D)``, as ``smoothing * elite + (1 - smoothing) * previous``; the std
    floored at ``min_std``. Fewer than 2 finite scores: unchanged."""
    finite = np.flatnonzero(np.isfinite(scores))
    if len(finite) < 2:
        return mean, std
    k = min(len(finite), max(2, math.ceil(config.elite_fraction * len(scores))))
    elite = u[finite[np.argsort(scores[finite], kind="stable")[:k]]]
    a = config.smoothing
    new_mean = a * elite.mean(axis=0) + (1.0 - a) * mean
    new_std = a * elite.std(axis=0) + (1.0 - a) * std
    return new_mean, np.maximum(new_std, config.min_std)


def draw(rng: np.random.Generator, n: int, mean: np.ndarray | None,
         std: np.ndarray | None) -> np.ndarray:
    """``n`` points of the box: uniform without a ``mean``, else Gaussian clipped to [0, 1]."""
    if mean is None or std is None:
        return rng.random((n, DIM))
    return np.clip(mean + std * rng.standard_normal((n, DIM)), 0.0, 1.0)


Objective = Callable[[np.ndarray], Sequence[Outcome]]  # u (S, D) -> an outcome per point


def search(config: SearchConfig, objective: Objective,
           on_batch: Callable[[int], None] | None = None) -> SearchResult:
    """Spend ``config.budget`` simulations in batches of ``config.batch``, every draw from
    ``np.random.default_rng(config.seed)``; ``objective`` evaluates a batch (a closed-loop one:
    :func:`closed_loop_objective`). ``on_batch(n)`` after each batch of ``n`` (a progress bar)."""
    rng = np.random.default_rng(config.seed)
    mean = std = None
    points, outcomes = [], []
    spent = 0
    while spent < config.budget:
        n = min(config.batch, config.budget - spent)
        u = draw(rng, n, mean if config.method == "cem" else None, std)
        got = list(objective(u))
        if len(got) != n:
            raise ValueError(f"the objective gave {len(got)} outcomes for {n} points")
        points.append(u)
        outcomes += got
        spent += n
        if config.method == "cem":
            prev_mean = np.full(DIM, 0.5) if mean is None else mean
            prev_std = np.full(DIM, uniform_std()) if std is None else std
            mean, std = cem_update(u, np.array([o.score for o in got]), prev_mean, prev_std,
                                   config)
        if on_batch is not None:
            on_batch(n)
        if config.stop_at_failure and any(o.failure for o in got):
            break
    return SearchResult(config, np.concatenate(points) if points else np.zeros((0, DIM)),
                        outcomes)


# ------------------------------------------------------------------- the closed-loop objective


def outcome_of(spec: ScenarioSpec, record: dict) -> Outcome:
    """A run's :class:`Outcome` from its sweep record (:func:`.sweep.run_tasks`); the leader's
    profile is rebuilt from the scenario (same seed: the same leader) for :func:`avoidable`."""
    from safeil_sumo.scenarios.spec import build_scenario, resolve_road

    if record.get("status") != "ok":
        return Outcome(math.inf, False, error=str(record.get("error", "")), avoidable=False)
    scenario = build_scenario(spec, resolve_road(spec.net))
    ok = avoidable(scenario.leader.speed_at, scenario.initial_gap_m, scenario.ego_speed_mps,
                   float(record["sim_time_s"]))
    flag = str(record.get("flag") or "")
    # a run that never closed in has TTC inf, which a record file's JSON writes as null
    ttc = record.get("min_ttc_s")
    min_ttc = math.inf if ttc is None else float(ttc)
    return Outcome(score(min_ttc, flag, ok), ok and bool(flag), min_ttc, flag, ok)


def closed_loop_objective(policy: str, max_time_s: float = 30.0, brake_guard: bool = True,
                          tasks_dir: Path | None = None, workers: int = 1,
                          scheduler: str | None = None) -> Objective:
    """The objective of planner ``policy`` in SUMO: a batch of points decoded into specs and run
    on the task engine as one unit, i.e. side by side in ONE simulation (``workers=1``), or
    split over ``workers`` local processes or a Dask ``scheduler``. Each run's record is kept in
    ``tasks_dir`` (None: a temporary folder) as it ends; a run already recorded there is read,
    not simulated again."""
    from safeil_sumo.experiments.sweep_executor import SweepJob
    from safeil_sumo.experiments.task_engine import execute, read_record, record_path

    def evaluate(u: np.ndarray) -> list[Outcome]:
        tasks = [decode(x, policy, max_time_s, brake_guard) for x in u]
        job = SweepJob(batch=len(tasks), mixed_nets=True)
        with ExitStack() as stack:
            folder = tasks_dir or Path(stack.enter_context(tempfile.TemporaryDirectory()))
            execute(tasks, job, folder, workers, scheduler, progress=False)
            records = [read_record(record_path(folder, job, t)) or {} for t in tasks]
        return [outcome_of(t.scenario, r) for t, r in zip(tasks, records, strict=True)]

    return evaluate


def sweep_toml(task: Task, comment: str = "") -> str:
    """A sweep file (``python -m safeil_sumo.sweep --config FILE``) that reruns exactly
    ``task`` (a task of :func:`decode`: index 0, no ranges drawn but the recorded window)."""
    spec = task.scenario
    lo, hi = spec.leader_speed_range_mps
    keys: dict = {"net": [spec.net], "policy": [task.planner.policy], "scenarios": 1,
                  "seed": spec.master_seed, "leader": spec.leader_kind,
                  "leader_speed_range_mps": [lo, hi], "gap_m": spec.initial_gap_m,
                  "lane_noise_m": spec.lane_noise_c0_m, "radar_noise_m": spec.radar_noise_m,
                  "max_time_s": spec.max_time_s}
    if spec.leader_kind == "recorded":
        keys["leader_profile"] = spec.leader_profile
    else:
        keys |= {"brake_time_s": spec.brake_time_s, "brake_decel_mps2": spec.brake_decel_mps2,
                 "brake_to_mps": spec.brake_to_mps, "ego_speed_mps": spec.ego_speed_mps}
    if not task.brake_guard:
        keys["brake_guard"] = False

    def fmt(v) -> str:
        if isinstance(v, list):
            return "[" + ", ".join(fmt(x) for x in v) + "]"
        if isinstance(v, bool):
            return "true" if v else "false"
        return f'"{v}"' if isinstance(v, str) else repr(v)

    head = "".join(f"# {line}\n" for line in comment.splitlines())
    return head + "".join(f"{k} = {fmt(v)}\n" for k, v in keys.items())


# --------------------------------------------------------------------------- tables and files


def table(result: SearchResult, policy: str) -> pd.DataFrame:
    """One row per simulation, in order: the point ``u0..``, its parameters, its outcome, the
    lowest score so far and the spec (JSON)."""
    rows = []
    for k, (u, o) in enumerate(zip(result.u, result.outcomes, strict=True)):
        task = decode(u, policy, result.config.max_time_s, result.config.brake_guard)
        rows.append({"sim": k + 1, **{f"u{j}": float(x) for j, x in enumerate(u)},
                     **values(u), "net": task.scenario.net,
                     "leader_kind": task.scenario.leader_kind,
                     "score": o.score, "failure": o.failure, "min_ttc_s": o.min_ttc_s,
                     "flag": o.flag, "avoidable": o.avoidable, "error": o.error,
                     "spec": json.dumps(task.to_json(), sort_keys=True)})
    df = pd.DataFrame(rows)
    if len(df):
        df["best_so_far"] = result.best_so_far
    return df


def read_table(path: Path, config: SearchConfig) -> SearchResult:
    """The :class:`SearchResult` a :func:`table` written as CSV at ``path`` holds (empty flags
    and errors stay empty strings, a missing TTC is NaN)."""
    return from_table(pd.read_csv(path, keep_default_na=False,
                                  na_values={"min_ttc_s": ["nan", "NaN", ""]}), config)


def from_table(df: pd.DataFrame, config: SearchConfig) -> SearchResult:
    """The :class:`SearchResult` a :func:`table` holds."""
    u = df[[f"u{j}" for j in range(DIM)]].to_numpy(float) if len(df) else np.zeros((0, DIM))
    outcomes = [Outcome(float(r.score), bool(r.failure), float(r.min_ttc_s),
                        "" if pd.isna(r.flag) else str(r.flag), bool(r.avoidable),
                        "" if pd.isna(r.error) else str(r.error))
                for r in df.itertuples()]
    return SearchResult(config, u, outcomes)


def summary(result: SearchResult, policy: str) -> dict:
    """The search's numbers: simulations spent, to the first failure, failures, the lowest
    score and min TTC among avoidable runs, and the worst case's spec."""
    out = {"policy": policy, "method": result.config.method, "seed": result.config.seed,
           "simulations": len(result.outcomes), "first_failure": result.first_failure,
           "failures": int(sum(o.failure for o in result.outcomes)),
           "avoidable": int(sum(o.avoidable for o in result.outcomes)),
           "errors": int(sum(bool(o.error) for o in result.outcomes))}
    if result.outcomes and math.isfinite(result.scores.min()):
        b = result.best
        o = result.outcomes[b]
        out |= {"best_score": o.score, "best_min_ttc_s": o.min_ttc_s, "best_flag": o.flag,
                "best_sim": b + 1,
                "best_spec": decode(result.u[b], policy, result.config.max_time_s,
                                            result.config.brake_guard).to_json()}
    return out


def write_worst(result: SearchResult, policy: str, folder: Path, stem: str = "worst"
                ) -> Path | None:
    """The worst avoidable case as ``<stem>.json`` (its :class:`Task`) and ``<stem>.toml`` (a
    sweep file that reruns it); the TOML's path (None: nothing avoidable)."""
    s = summary(result, policy)
    if "best_spec" not in s:
        return None
    task = Task.from_json(s["best_spec"])
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{stem}.json").write_text(json.dumps(task.to_json(), indent=1) + "\n")
    toml = folder / f"{stem}.toml"
    flag = s["best_flag"] or "no flag"
    shown = Path(os.path.relpath(toml)).as_posix()  # from where the command runs
    toml.write_text(sweep_toml(task, (
        f"{policy}: worst avoidable case of a {s['method']} search (seed {s['seed']}, "
        f"simulation {s['best_sim']} of {s['simulations']}): min TTC {s['best_min_ttc_s']:.3f} s, "
        f"{flag}\nrerun: python -m safeil_sumo.sweep --config {shown} "
        f"--out runs/{stem}")))
    return toml


def run_or_load(policy: str, config: SearchConfig, folder: Path, progress: bool = False,
                workers: int = 1, scheduler: str | None = None) -> SearchResult:
    """The search of ``policy`` under ``config``, read from ``folder`` if a run with the same
    config and the same policy weights finished there, else run (in SUMO, on ``workers`` local
    processes or a Dask ``scheduler``) and saved: ``evaluations.csv``, ``config.json`` (with the
    policy's fingerprint, so a retrained model never reads the searches of the model before).
    While it runs, ``tasks/`` keeps each simulation's record: an interrupted search resumes
    from them (only with the same weights: the folder is cleared for others)."""
    from safeil_sumo.planners import registry as planner_registry

    done, tasks = folder / "evaluations.csv", folder / "tasks"
    cfg = {"policy": policy, "policy_fingerprint": planner_registry.fingerprint(policy),
           **asdict(config)}
    saved = folder / "config.json"
    if saved.is_file() and json.loads(saved.read_text()) == cfg:
        if done.is_file():
            return read_table(done, config)
    else:  # another search's (or another model's) records: not this search's
        shutil.rmtree(tasks, ignore_errors=True)
        done.unlink(missing_ok=True)
    folder.mkdir(parents=True, exist_ok=True)
    saved.write_text(json.dumps(cfg, indent=1) + "\n")
    from tqdm import tqdm

    bar = tqdm(total=config.budget, desc=f"{policy} {config.method} s{config.seed}",
               unit="sim", disable=not progress or None)
    try:
        result = search(config, closed_loop_objective(
            policy, config.max_time_s, config.brake_guard, tasks_dir=tasks, workers=workers,
            scheduler=scheduler), bar.update)
    finally:
        bar.close()
    with atomic_path(done) as tmp:
        table(result, policy).to_csv(tmp, index=False)
    shutil.rmtree(tasks, ignore_errors=True)  # every record is in evaluations.csv now
    return result


# ----------------------------------------------------------------- the study in results/


@dataclass(frozen=True)
class StudyRun:
    """Searches of one planner in the results' study: both methods, each seed."""

    policy: str
    budget: int  # simulations per search [-]
    batch: int  # scenarios per SUMO simulation [-]
    seeds: tuple[int, ...]  # one search per method and seed


# bc and safeil_paper: to the first failure, several seeds; safeil (with the brake guard its
# failures are rare, ~1 in 450 random runs): what 1,000 simulations per search find
STUDY: tuple[StudyRun, ...] = (
    StudyRun("bc", 200, 20, (0, 1, 2)),
    StudyRun("safeil_paper", 200, 20, (0, 1, 2)),
    StudyRun("safeil", 1000, 50, (0, 1, 2)),
)


def study_configs(run: StudyRun) -> list[SearchConfig]:
    """The searches of ``run``: per seed, CEM then random."""
    return [SearchConfig(method=m, budget=run.budget, batch=run.batch, seed=s)
            for s in run.seeds for m in METHODS]


def study_folder(work: Path, policy: str, config: SearchConfig) -> Path:
    """Where a study search is kept (resumable: :func:`run_or_load`)."""
    return Path(work) / (f"{policy}_{config.method}_s{config.seed}"
                         + ("" if config.brake_guard else "_noguard"))


def first_at_or_below(result: SearchResult, threshold_s: float) -> int | None:
    """Simulations spent up to and including the first score <= ``threshold_s`` [s] (0: an
    avoidable run that reached TTC 0, a collision)."""
    hit = np.flatnonzero(result.scores <= threshold_s)
    return int(hit[0]) + 1 if len(hit) else None


def study_rows(runs: Sequence[tuple[str, SearchResult]]) -> pd.DataFrame:
    """One row per search: planner, method, seed, budget, batch, simulations to the first
    failure and to the first avoidable TTC 0, failures, the lowest score and its run."""
    rows = []
    for policy, res in runs:
        s = summary(res, policy)
        rows.append({"policy": policy, "method": s["method"], "seed": s["seed"],
                     "budget": res.config.budget, "batch": res.config.batch,
                     "simulations": s["simulations"], "first_failure": s["first_failure"],
                     "first_ttc0": first_at_or_below(res, 0.0),
                     "failures": s["failures"], "avoidable": s["avoidable"],
                     "errors": s["errors"], "best_min_ttc_s": s.get("best_min_ttc_s"),
                     "best_flag": s.get("best_flag"), "best_sim": s.get("best_sim")})
    return pd.DataFrame(rows)


def median_to_first(rows: pd.DataFrame, column: str = "first_failure") -> pd.DataFrame:
    """Per planner x method: the median over seeds of ``column`` (a search without one counts
    as more than its budget: inf), the seeds, and how many found one."""
    out = []
    for (policy, method), g in rows.groupby(["policy", "method"], sort=False):
        got = g[column].astype(float)
        out.append({"policy": policy, "method": method, "seeds": len(g),
                    "found": int(got.notna().sum()),
                    "median": float(np.median(got.fillna(math.inf)))})
    return pd.DataFrame(out)
