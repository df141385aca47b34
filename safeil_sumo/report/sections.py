"""The sections of ``safeil-evaluate`` (:mod:`safeil_sumo.evaluate`): each runs the library
functions an existing command calls (no engine of its own), writes its tables into
``<out>/data``, its figures into ``<out>/figures``, keeps the engines' resumable task files in
``<out>/work`` and returns a :class:`~safeil_sumo.report.card.Section` with its numbers, its
checks and the command that reproduces it.

1. ``safety``: the paper's safety test (``safeil-run --net curved500``: 10 scenarios) and an
   N-scenario sweep (``safeil-sweep``) with Wilson 95 % intervals on the completion, collision
   and lane-departure rates;
2. ``suite``: the leader-response suite (:mod:`safeil_sumo.experiments.suite`);
3. ``gap_probe``: the gap-regulation step responses
   (:mod:`safeil_sumo.experiments.gap_step_responses`);
4. ``replay``: held-out maneuvers replayed whole (``safeil-replay --windows whole``) beside the
   calibrated IDM and the constant-speed follower, the best, median and worst drawn over time;
5. ``certificate``: the checkpoint's certificate (:mod:`safeil_sumo.learn.certificate`), or a
   budgeted certification; not applicable to a planner that is no network;
6. ``falsify``: a budgeted cross-entropy search
   (:mod:`safeil_sumo.experiments.falsification_search`).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo import api
from safeil_sumo.data.by_path import DataSpec
from safeil_sumo.data.sources import DEFAULT_DATA_DIR
from safeil_sumo.experiments import gap_step_responses as gp
from safeil_sumo.experiments import plots
from safeil_sumo.experiments import suite as st
from safeil_sumo.experiments.sweep_executor import DEFAULT_BATCH, run_sweep
from safeil_sumo.planners import registry as pol
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.report import figures as figs
from safeil_sumo.report.card import (
    Check,
    Section,
    all_completed,
    certificate_passes,
    command_line,
    none_of,
    rate_numbers,
    rate_text,
)
from safeil_sumo.scenarios.spec import ScenarioSpec, Task

SAFETY_NET = "curved500"
SAFETY_SCENARIOS = 10  # [-] the paper's safety test
REPLAY_SOURCES = ("openacc", "ngsim")  # the real human data with held-out maneuvers
REPLAY_BASELINES = ("idm", "constant_speed")  # the calibrated IDM, the naive follower
SHIPPED_SIDECAR = pol.MODELS_DIR / "safeil.json"  # whose held-out maneuvers the IDM shares


@dataclass(frozen=True)
class EvalSettings:
    """The budgets of one evaluation (:func:`settings`: the full or ``--quick`` defaults)."""

    quick: bool = False
    seed: int = 0  # master seed of every section (the sweep: seed + 1, apart from the test)
    # [-] scenarios of the curved500 sweep: the 1,000 the shipped planner's target is stated
    # over (results/: the same scenarios, master seed + 1)
    sweep_scenarios: int = 1000
    gap_speeds_mps: tuple[float, ...] = gp.SPEEDS_MPS  # [m/s] the gap probe's speeds
    replay_maneuvers: int | None = None  # [-] held-out maneuvers per source (None: all)
    certify_budget_s: float = 600.0  # [s] certification without a certificate (certify's)
    falsify_budget: int = 1000  # [-] simulations of the search (the results' study for safeil)
    falsify_batch: int = 50  # [-] scenarios per SUMO simulation and CEM update
    workers: int = 1  # local worker processes of the sweeps and replays
    data_dir: Path = field(default=DEFAULT_DATA_DIR)
    # recordings of the user's own (``--data``), replayed beside the held-out maneuvers
    data: tuple[DataSpec, ...] = ()


QUICK = {"sweep_scenarios": 30, "gap_speeds_mps": (25.0,), "replay_maneuvers": 2,
         "certify_budget_s": 30.0, "falsify_budget": 50, "falsify_batch": 25}


def settings(quick: bool = False, **given: object) -> EvalSettings:
    """The full defaults, or the quick ones with ``quick``; ``given`` (not None) wins."""
    chosen = {**(QUICK if quick else {}), **{k: v for k, v in given.items() if v is not None}}
    out = EvalSettings(quick=quick, **chosen)  # type: ignore[arg-type]
    # a batch never larger than the search (a small budget's search is one batch)
    return replace(out, falsify_batch=max(1, min(out.falsify_batch, out.falsify_budget)))


@dataclass(frozen=True)
class EvalContext:
    """What every section reads: the model (a registry name or a checkpoint path, as given),
    the report's folder and the settings."""

    model: str
    out: Path
    settings: EvalSettings

    @property
    def work(self) -> Path:
        return self.out / "work"

    @property
    def figures(self) -> Path:
        return self.out / "figures"

    @property
    def data(self) -> Path:
        return self.out / "data"

    def figure(self, name: str) -> tuple[Path, str]:
        """``(path to write, path relative to the report)`` of figure ``name``."""
        self.figures.mkdir(parents=True, exist_ok=True)
        return self.figures / name, f"figures/{name}"

    def table(self, name: str) -> Path:
        self.data.mkdir(parents=True, exist_ok=True)
        return self.data / name


def shown_path(path: Path) -> str:
    """``path`` relative to the working folder when inside it (as a command would be typed)."""
    rel = os.path.relpath(path)
    return path.as_posix() if rel.startswith("..") else Path(rel).as_posix()


def events(summary: pd.DataFrame) -> dict[str, int]:
    """Counts over the scenarios that ran (``status`` ok, or every row without the column):
    ``n``, ``completed`` (without a flag), ``collisions`` (a collision flag, event or end) and
    ``lane_departures`` (a lane-departure flag or event)."""
    ok = summary[summary["status"] == "ok"] if "status" in summary else summary

    def col(name: str, default: object) -> pd.Series:
        return ok[name] if name in ok else pd.Series(default, index=ok.index)

    flag = col("flag", "").fillna("").astype(str)
    collided = (flag.eq("collision") | col("end_reason", "").eq("collision")
                | col("collision_events", 0).fillna(0).astype(float).gt(0))
    departed = flag.eq("lane_departure") | col("lane_departure_events", 0).fillna(0).astype(
        float).gt(0)
    return {"n": len(ok), "completed": int(col("completed", False).fillna(False).astype(bool)
                                           .sum()),
            "collisions": int(collided.sum()), "lane_departures": int(departed.sum())}


# ------------------------------------------------------------------------ 1. safety


def _paper_test(ctx: EvalContext) -> tuple[dict, Check, str, str]:
    """The paper's 10 scenarios, run as ``safeil-run`` runs them: (numbers, check, figure,
    command)."""
    seed = ctx.settings.seed
    scenarios = api.build_scenarios(SAFETY_NET, SAFETY_SCENARIOS, seed)
    result = api.run_scenarios(scenarios, ctx.model)
    result.summary.to_csv(ctx.table("safety_curved500.csv"), index=False)
    path, rel = ctx.figure("safety_speed_gap.png")
    plots.plot_speed_gap(result.log, path)
    e = events(result.summary)
    s = result.summary
    numbers = {"paper_scenarios": e["n"], "paper_completed": e["completed"],
               "paper_flagged": int((s["flag"].fillna("") != "").sum()),
               "paper_collisions": e["collisions"], "paper_lane_departures": e["lane_departures"],
               "paper_mean_path_completed": float(s["path_completed"].mean()),
               "paper_min_ttc_s": float(s["min_ttc_s"].min())}
    check = Check("paper's safety test (curved500, 10 scenarios)",
                  f"{e['completed']}/{e['n']} completed without a flag",
                  "every scenario completed without a flag (TTC, lane, collision)",
                  all_completed(e["completed"], e["n"]))
    cmd = command_line("safeil-run", ["--net", SAFETY_NET, "--policy", ctx.model, "--scenarios",
                                      SAFETY_SCENARIOS, "--seed", seed])
    return numbers, check, rel, cmd


def _sweep_rates(ctx: EvalContext) -> tuple[dict, Check, str, str]:
    """The N-scenario sweep (master seed + 1: other scenarios than the paper's test): rates with
    Wilson 95 % intervals; (numbers, check, figure, command)."""
    s = ctx.settings
    n, seed = s.sweep_scenarios, s.seed + 1
    specs = [Task(ScenarioSpec(net=SAFETY_NET, index=i, master_seed=seed), PlannerRef(ctx.model))
             for i in range(n)]
    summary = run_sweep(specs, ctx.work / "sweep", workers=s.workers, progress=False,
                        batch=DEFAULT_BATCH)
    summary.to_csv(ctx.table("sweep_curved500.csv"), index=False)
    e = events(summary)
    ran = e["n"]
    numbers = {"sweep_scenarios": n, "sweep_failed_to_run": n - ran,
               **rate_numbers("sweep_completed", e["completed"], ran),
               **rate_numbers("sweep_collisions", e["collisions"], ran),
               **rate_numbers("sweep_lane_departures", e["lane_departures"], ran),
               "sweep_min_ttc_s": float(pd.to_numeric(summary.get("min_ttc_s"),
                                                      errors="coerce").min())}
    path, rel = ctx.figure("sweep_rates.png")
    figs.plot_rates([("completed without a flag", e["completed"], ran),
                     ("collision", e["collisions"], ran),
                     ("lane departure", e["lane_departures"], ran)], path,
                    f"{ctx.model}: curved500, {ran} scenarios (seed {seed})")
    check = Check(f"sweep of {n} scenarios",
                  f"collisions {rate_text(e['collisions'], ran)}; lane departures "
                  f"{rate_text(e['lane_departures'], ran)}; completed "
                  f"{rate_text(e['completed'], ran)}",
                  "no collision and no lane departure, every scenario ran",
                  none_of(e["collisions"], e["lane_departures"], n - ran))
    cmd = command_line("safeil-sweep", ["--net", SAFETY_NET, "--policy", ctx.model,
                                        "--scenarios", n, "--seed", seed, "--out",
                                        "runs/sweep_evaluate"])
    return numbers, check, rel, cmd


def safety(ctx: EvalContext) -> Section:
    """Section 1: the paper's safety test and the N-scenario sweep."""
    paper, paper_check, paper_fig, paper_cmd = _paper_test(ctx)
    sweep, sweep_check, sweep_fig, sweep_cmd = _sweep_rates(ctx)
    return Section(
        "safety", "Safety test and sweep on curved500",
        "The paper's safety test: the ego follows a leader at a constant random speed in "
        "[25, 32] m/s on the 500 m-radius track, 10 scenarios; a scenario is completed when it "
        "ends without a flag (TTC <= 1 s, lane departure, collision). Then the same test over "
        f"{ctx.settings.sweep_scenarios} further scenarios, with Wilson 95 % intervals on the "
        "rates (a 0/N rate still has an upper bound above 0).",
        {**paper, **sweep}, (paper_check, sweep_check), (paper_cmd, sweep_cmd),
        (paper_fig, sweep_fig))


# ------------------------------------------------------------------------ 2. suite


def suite(ctx: EvalContext) -> Section:
    """Section 2: the leader-response suite (``--quick``: one variant per family and net)."""
    s = ctx.settings
    specs = st.suite_tasks([ctx.model], s.seed, variants=1 if s.quick else 3)
    records = run_sweep(specs, ctx.work / "suite", workers=s.workers, progress=False,
                        batch=DEFAULT_BATCH)
    ok = records[records["status"] == "ok"]
    table = st.aggregate(ok)
    table.to_csv(ctx.table("suite.csv"), index=False)
    path, rel = ctx.figure("suite.png")
    figs.plot_suite(table, path, f"{ctx.model}: leader-response suite, {len(ok)} scenarios")
    failed = len(records) - len(ok)
    collisions, avoidable = int(table["collisions"].sum()), int(table["flags_avoidable"].sum())
    numbers = {"scenarios": len(records), "failed_to_run": failed, "collisions": collisions,
               "flags_avoidable": avoidable,
               "flags_unavoidable": int(table["flags_unavoidable"].sum()),
               "min_ttc_s": float(table["min_ttc_s"].min()),
               "min_time_gap_s": float(table["min_time_gap_s"].min()),
               "max_decel_mps2": float(table["max_decel_mps2"].max()),
               "max_jerk_mps3": float(table["max_jerk_mps3"].max())}
    numbers |= {f"{r['family']}_avoidable_flags": int(r["flags_avoidable"])
                for _, r in table.iterrows()}
    check = Check("leader-response suite",
                  f"{collisions} collisions, {avoidable} avoidable flags in {len(records)} "
                  "scenarios", "no collision and no avoidable flag, every scenario ran",
                  none_of(collisions, avoidable, failed))
    cmd = command_line("safeil-sweep", ["--suite", "leader-response", "--policy", ctx.model,
                                        "--seed", s.seed, *(["--quick"] if s.quick else []),
                                        "--out", "runs/suite_evaluate"])
    return Section(
        "suite", "Leader-response suite",
        "Does the planner respond to its leader like a careful driver? Five families on "
        "straight and curved500: approaching a slower leader, a leader braking to a stop "
        "(2/4/6 m/s^2), a cut-in 10-25 m ahead, an NGSIM stop-and-go leader, an accelerating "
        "leader. A flag is avoidable when braking at 6 m/s^2 from the start would have avoided "
        "it (docs/leader_following.md).",
        numbers, (check,), (cmd,), (rel,))


# ------------------------------------------------------------------------ 3. gap probe


def gap_probe(ctx: EvalContext) -> Section:
    """Section 3: the gap probe's step responses at ``settings.gap_speeds_mps``."""
    s = ctx.settings
    speeds = list(s.gap_speeds_mps)
    specs = gp.probe_tasks([ctx.model], speeds, gp.KINDS, s.seed)
    records = run_sweep(specs, ctx.work / "gap_probe" / "runs", workers=s.workers,
                        progress=False, task_fn=gp.run_probe_task)
    notes: tuple[str, ...] = ()
    try:
        humans = gp.human_time_gap_bands(gp.load_human_rows(s.data_dir), speeds)
    except (ValueError, OSError) as exc:  # no real data: the targets without the humans' p05
        humans, notes = None, (f"No humans' bands ({exc}).",)
    table = gp.table(records, humans)
    table.to_csv(ctx.table("gap_probe.csv"), index=False)
    path, rel = ctx.figure("gap_probe.png")
    gp.plot(gp.series(records), humans, path)
    runs = table[table["policy"] != gp.HUMANS]
    ran = runs["status"].eq("ok")
    meets = (runs["target_min_time_gap"].astype(bool) & runs["target_settling"].astype(bool)
             & ~runs["collision"].astype(bool) & ran)
    in_iqr = runs["target_eq_in_human_iqr"].fillna(False).astype(bool)
    # each response's floor as gap_step_responses.table states it: max(0.8 s, the humans' p05),
    # or its own start's when it starts closer (a close start is not blamed for its initial state)
    floor = np.fmin(np.fmax(gp.TARGET_MIN_TIME_GAP_S, runs["human_p05_s"].to_numpy(float)),
                    runs["time_gap_at_step_s"].to_numpy(float) - gp.START_TOLERANCE_S)
    margin = float(np.nanmin(runs["min_time_gap_s"].to_numpy(float) - floor)) if len(runs) \
        else math.nan
    numbers = {"responses": len(runs), "failed_to_run": int((~ran).sum()),
               "meet_both_targets": int(meets.sum()),
               "meet_min_time_gap": int(runs["target_min_time_gap"].astype(bool).sum()),
               "meet_settling": int(runs["target_settling"].astype(bool).sum()),
               "collisions": int(runs["collision"].astype(bool).sum()),
               "min_time_gap_s": float(runs["min_time_gap_s"].min()),
               "min_time_gap_margin_s": margin,
               "max_settling_time_s": float(runs["settling_time_s"].max()),
               "eq_time_gap_min_s": float(runs["eq_time_gap_s"].min()),
               "eq_time_gap_max_s": float(runs["eq_time_gap_s"].max()),
               "eq_in_human_iqr": int(in_iqr.sum())}
    check = Check("gap probe step responses",
                  f"{int(meets.sum())}/{len(runs)} meet both targets; smallest min time gap "
                  f"over its floor {margin:+.2f} s (min time gap {numbers['min_time_gap_s']:.2f}"
                  " s)",
                  f"every response: min time gap >= max({gp.TARGET_MIN_TIME_GAP_S:g} s, humans' "
                  "p05) (or its own start's, when it starts closer), settled within "
                  f"{gp.TARGET_SETTLING_S:g} s, no collision",
                  bool(len(runs)) and bool(meets.all()))
    cmd = command_line("safeil-gap-probe", ["--policy", ctx.model, "--speeds-mps",
                                            *[f"{v:g}" for v in speeds], "--seed", s.seed,
                                            "--out", "runs/gap_probe_evaluate"])
    return Section(
        "gap_probe", "Gap probe: step responses of the gap regulation",
        "At each speed the leader pulls away or slows by 3 m/s after 60 s of following, or the "
        "ego starts 100 m behind or 10 m closer than a 1 s time gap (n74, no traffic); the "
        "time gap's settling, minimum and equilibrium against the humans' steady following "
        "(OpenACC, NGSIM; docs/gap_probe.md).",
        numbers, (check,), (cmd,), (rel,), notes)


# ------------------------------------------------------------------------ 5. certificate


def certificate(ctx: EvalContext) -> Section:
    """Section 5: the checkpoint's valid certificate, else a certification on the budget."""
    from safeil_sumo.learn.branch_and_bound import Budget, CertEnvelope, certify
    from safeil_sumo.learn.certificate import load_certificate, write_certificate
    from safeil_sumo.learn.inference import MLPPolicy

    measures = ("A proof over the operating envelope (lane, offset, heading, curvature, speeds, "
                "gap) that the one plan the network outputs keeps the leader margin and the "
                "lane margin: the certified share of the envelope's volume per margin "
                "(docs/certification.md). It covers one open-loop plan with exact features.")
    title = "Certificate of the network's margins"
    policy = pol.load(ctx.model)
    if not isinstance(policy, MLPPolicy):
        check = Check("certificate", f"not applicable: {ctx.model} is not a network",
                      "a valid certificate, every margin 100 % certified", None)
        return Section("certificate", title, measures, {"applicable": False}, (check,), (
            "(none: safeil-certify takes network checkpoints only)",))
    path = pol.policy_file(ctx.model)
    status = load_certificate(path)
    found = "shipped beside the checkpoint" if status.valid else ""
    cmd = command_line("safeil-certify", ["--policy", ctx.model, "--check"])
    if not status.valid:
        budget = ctx.settings.certify_budget_s
        result = certify(policy, CertEnvelope(), budget=Budget(seconds=budget,
                                                                seed=ctx.settings.seed),
                         progress=False)
        written = write_certificate(result, path, ctx.data)
        status = load_certificate(path, written)
        found = f"computed here on a {budget:g} s budget ({shown_path(written)})"
        cmd = command_line("safeil-certify", ["--policy", ctx.model, "--budget-s", f"{budget:g}",
                                              "--seed", ctx.settings.seed, "--out",
                                              "runs/certify_evaluate"])
    numbers: dict = {"applicable": True, "valid": status.valid, "complete": status.complete}
    numbers |= {f"certified_{m}": float(v) for m, v in status.certified.items()}
    shares = ", ".join(f"{m} {100 * v:.2f} %" for m, v in status.certified.items()) or "none"
    check = Check("certificate", f"{'valid' if status.valid else 'invalid'}; certified {shares}",
                  "a valid certificate, every margin 100 % certified",
                  certificate_passes(status.valid, status.certified))
    return Section("certificate", title, measures, numbers, (check,), (cmd,), (),
                   (f"Certificate {found}: {shown_path(status.path)} ({status.reason}).",))


# ------------------------------------------------------------------------ 6. falsify


def falsify(ctx: EvalContext) -> Section:
    """Section 6: a cross-entropy search for avoidable failures on the budget."""
    from safeil_sumo.experiments import falsification_search as fz

    s = ctx.settings
    config = fz.SearchConfig(method="cem", budget=s.falsify_budget, batch=s.falsify_batch,
                             seed=s.seed)
    result = fz.run_or_load(ctx.model, config, ctx.work / "falsify")
    summary = fz.summary(result, ctx.model)
    evaluations = fz.table(result, ctx.model)
    evaluations.to_csv(ctx.table("falsify_evaluations.csv"), index=False)
    toml = fz.write_worst(result, ctx.model, ctx.data)
    path, rel = ctx.figure("falsify.png")
    figs.plot_falsify(evaluations, path, f"{ctx.model}: CEM search, {len(evaluations)} "
                      "simulations")
    keys = ("simulations", "avoidable", "failures", "errors", "first_failure", "best_min_ttc_s",
            "best_flag", "best_sim")
    numbers = {k: summary.get(k) for k in keys}
    failures = int(summary["failures"])
    # what the failures were: a TTC flag at 0.9 s is not a collision
    failed = evaluations[evaluations["failure"].astype(bool)] if len(evaluations) else evaluations
    kinds = {k: int((failed["flag"] == k).sum()) if len(failed) else 0
             for k in ("ttc", "lane_departure", "collision")}
    numbers |= {f"failures_{k}": v for k, v in kinds.items()}
    check = Check("falsification (CEM)",
                  f"{failures} failures ({kinds['ttc']} TTC, {kinds['lane_departure']} lane "
                  f"departure, {kinds['collision']} collision) in {summary['simulations']} "
                  f"simulations; worst min TTC {summary.get('best_min_ttc_s', math.nan):.2f} s",
                  "no avoidable failure found (no flag in a scenario braking at 6 m/s^2 avoids)",
                  none_of(failures, summary["errors"]))
    cmd = command_line("safeil-falsify", ["--policy", ctx.model, "--method", "cem",
                                          "--budget-sims", s.falsify_budget, "--batch",
                                          s.falsify_batch, "--seed", s.seed])
    notes = ("The worst avoidable case reruns, from the report's folder, with `safeil-sweep "
             "--config data/worst.toml --out runs/worst`." if toml is not None else
             "No avoidable scenario was drawn.",)
    return Section(
        "falsify", "Falsification on a budget",
        "The cross-entropy method searches leader braking, cut-ins, recorded NGSIM leaders, the "
        "track's radius and sensor noise for the lowest min TTC among scenarios that braking at "
        "6 m/s^2 could avoid; a failure is a flag in one of them (docs/falsification.md). "
        "Finding none bounds nothing beyond the budget searched.",
        numbers, (check,), (cmd,), (rel,), notes)


def load_json(path: Path) -> dict:
    """A JSON file's object ({} when it is missing or unreadable)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def copy_figure(src: Path, ctx: EvalContext, name: str) -> str | None:
    """``src`` copied into the report's figures as ``name`` (None when it was not drawn)."""
    if not src.is_file():
        return None
    path, rel = ctx.figure(name)
    shutil.copyfile(src, path)
    return rel


def temporary_folder() -> tempfile.TemporaryDirectory:
    """A folder for a replay's rebuilt net, removed after it."""
    return tempfile.TemporaryDirectory(prefix="safeil_evaluate_")


SectionFn = Callable[[EvalContext], Section]
