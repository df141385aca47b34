"""Run a training recipe (:mod:`safeil_sumo.learn.recipe`) into an output folder, resumably.

``out/`` holds ``data/`` (each source's processed tuples), ``stages/`` (each stage's checkpoint
and a ``<stage>.done.json`` marker), the final checkpoint ``<name>.safetensors`` + ``.json``, its
certificate ``<name>.certificate.json``, the IDM calibrated on the same training maneuvers
``<name>.idm.json`` (the report card's baseline) and ``summary.json`` / ``summary.md``. Every
file is written atomically (:mod:`safeil_sumo.core.atomic`), a stage's marker last: a stage whose marker
holds the same digest (the recipe's data, split and every stage up to it) and whose checkpoint
still has the weights it recorded is not run again, so a rerun after an interrupt resumes at
the first unfinished stage. Deterministic for the recipe's seeds: the stages' own functions
seed torch and fix its threads (:func:`safeil_sumo.learn.trainer.train`,
:func:`safeil_sumo.learn.finetune.finetune`, :func:`safeil_sumo.learn.lateral_refit.
refit_lateral`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.data.by_path import DataError, DataSpec, load_data, process, spec_digest
from safeil_sumo.data.sources import driver_of
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.recipe import Recipe, RecipeError, Split, Stage

Echo = Callable[[str], None]
# [s] per unit of work, measured on the shared 2-core machine by the shipped run
# (models/*.json): open loop 1,124 s for 400 epochs x 63,646 tuples (training and held out:
# both are evaluated every epoch); closed loop 2,257 s for 400 iterations x 64 episodes x 60 s;
# lateral refit 379 s for 16,000 steps x 2,048 states; certificate ~48 s for ~46,000 boxes
# (docs/certification.md)
COST_S = {"openloop": 1124.0 / (400 * 63646), "closed_loop": 2257.0 / (400 * 64 * 60.0),
          "lateral_refit": 379.0 / (16000 * 2048), "certify": 48.0 / 46000,
          # the IDM calibration, measured on OpenACC and NGSIM (111 s for 93,207 samples)
          "idm": 111.0 / 93207}
UNITS = {"openloop": "tuple-epochs", "closed_loop": "episode-seconds",
         "lateral_refit": "state-steps", "certify": "boxes"}


@dataclass(frozen=True)
class Prepared:
    """The recipe's data, processed: per data name the tuples files (recipe order), the
    maneuver ids, per-source counts, the held-out maneuver ids and the digest of all of it."""

    files: dict[str, list[Path]]
    maneuvers: dict[str, list[str]]
    counts: dict[str, dict[str, Any]]
    held_out: tuple[str, ...]
    held_out_drivers: tuple[str, ...]
    digest: str


def _sha(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, default=str) + "\n")


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _source_tuples(recipe: Recipe, out: Path, progress: bool, echo: Echo
                   ) -> list[tuple[Path, dict[str, Any]]]:
    """Each data spec's tuples file and counts, processed now or taken from ``out/data``
    when its marker holds the same digest (spec, pipeline, the files' bytes)."""
    done = []
    for i, spec in enumerate(recipe.data):
        path = out / "data" / f"{i:02d}-{spec.name}.tuples.parquet"
        marker = path.with_suffix(".done.json")
        digest = spec_digest(spec, recipe.pipeline)
        old = _read_json(marker)
        if old is not None and old.get("digest") == digest and path.is_file():
            done.append((path, old))
            continue
        echo(f"data: importing {spec.label()}")
        drive = load_data([spec], progress)[0]
        tuples, report = process(drive, spec, recipe.pipeline)
        if len(tuples) == 0:
            raise DataError(f"{spec.label()}: no maneuver left after processing "
                            f"({report.maneuvers_dropped} too short)")
        tuples.save(path)
        info = {"digest": digest, "name": spec.name, "label": spec.label(),
                "recordings": report.recordings, "maneuvers": len(tuples.maneuvers),
                "tuples": len(tuples), "events": report.events}
        _write_json(marker, info)
        done.append((path, info))
    return done


def _draw(ids: Sequence[str], fraction: float, rng: np.random.Generator) -> list[str]:
    """``round(fraction * n)`` of ``ids`` (sorted), at least 1 and at most n - 1 when the
    fraction is > 0 and there are >= 2: :func:`safeil_sumo.learn.trainer.split_by_maneuver`'s
    rule."""
    ids = sorted(ids)
    n_val = round(fraction * len(ids))
    if fraction > 0 and len(ids) >= 2:
        n_val = min(max(n_val, 1), len(ids) - 1)
    return [str(x) for x in rng.choice(np.asarray(ids), size=n_val, replace=False)]


def held_out(split: Split, maneuvers: dict[str, list[str]], formats: dict[str, str]
             ) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(maneuver ids, driver ids)`` held out. By maneuver: per source (sorted by name), as
    :func:`~safeil_sumo.learn.trainer.split_by_maneuver` draws them (so the shipped split);
    by driver: whole drivers (:func:`~safeil_sumo.data.sources.driver_of`) per source."""
    if split.by == "maneuver":
        everything = {m for ids in maneuvers.values() for m in ids}
        if split.held_out:
            unknown = sorted(set(split.held_out) - everything)
            if unknown:
                raise RecipeError(f"[split] held_out: unknown maneuver ids {unknown[:5]}")
            return tuple(sorted(split.held_out)), ()
        rng = np.random.default_rng(split.seed)
        chosen = [m for src in sorted(maneuvers) for m in _draw(sorted(set(maneuvers[src])),
                                                                split.fraction, rng)]
        return tuple(sorted(chosen)), ()
    drivers = {src: {m: driver_of(formats[src], m) for m in ids}
               for src, ids in maneuvers.items()}
    known = {d for by_m in drivers.values() for d in by_m.values()}
    if split.held_out:
        unknown = sorted(set(split.held_out) - known)
        if unknown:
            raise RecipeError(f"[split] held_out: unknown driver ids {unknown[:5]} (the data's "
                              f"drivers: {', '.join(sorted(known)[:8])}, ...)")
        chosen_drivers = set(split.held_out)
    else:
        rng = np.random.default_rng(split.seed)
        chosen_drivers = {d for src in sorted(drivers)
                          for d in _draw(sorted(set(drivers[src].values())), split.fraction, rng)}
    ids = sorted(m for by_m in drivers.values() for m, d in by_m.items() if d in chosen_drivers)
    return tuple(ids), tuple(sorted(chosen_drivers))


def prepare(recipe: Recipe, out: Path, progress: bool, echo: Echo) -> Prepared:
    """The recipe's data processed (or reused from ``out/data``) and its held-out split."""
    if not recipe.data:
        raise RecipeError(f"{recipe.path}: no data: add [[data]] tables or give --data")
    files: dict[str, list[Path]] = {}
    maneuvers: dict[str, list[str]] = {}
    counts: dict[str, dict[str, Any]] = {}
    for spec, (path, info) in zip(recipe.data, _source_tuples(recipe, out, progress, echo),
                                  strict=True):
        files.setdefault(spec.name, []).append(path)
        maneuvers.setdefault(spec.name, []).extend(map(str, Tuples.load(path).maneuvers))
        c = counts.setdefault(spec.name, {"label": [], "recordings": 0, "maneuvers": 0,
                                          "tuples": 0})
        c["label"].append(info["label"])
        for k in ("recordings", "maneuvers", "tuples"):
            c[k] += int(info[k])
    formats = {spec.name: spec.format for spec in recipe.data}
    ids, drivers = held_out(recipe.split, maneuvers, formats)
    digests = [json.loads(p.with_suffix(".done.json").read_text())["digest"]
               for paths in files.values() for p in paths]
    digest = _sha({"data": digests, "split": dataclasses.asdict(recipe.split), "held": ids})
    return Prepared(files, maneuvers, counts, ids, drivers, digest)


def stage_sources(stage: Stage, prepared: Prepared) -> list[str]:
    """The data names a stage trains on (recipe order); RecipeError for an unknown one."""
    names = list(prepared.files)
    if not stage.sources:
        return names
    unknown = [s for s in stage.sources if s not in names]
    if unknown:
        raise RecipeError(f"[{stage.name}] sources: {', '.join(unknown)} not in the data "
                          f"(its names: {', '.join(names)})")
    return [n for n in names if n in stage.sources]


def stage_paths(stage: Stage, prepared: Prepared) -> list[Path]:
    return [p for n in stage_sources(stage, prepared) for p in prepared.files[n]]


def work_units(stage: Stage, prepared: Prepared) -> tuple[float, str]:
    """A stage's work in :data:`UNITS` (an upper bound: early stopping may cut the open loop)
    and its description."""
    c = stage.config
    if stage.name == "openloop":
        held = set(prepared.held_out)
        n = sum(prepared.counts[s]["tuples"] for s in stage_sources(stage, prepared))
        n_val_m = sum(m in held for s in stage_sources(stage, prepared)
                      for m in prepared.maneuvers[s])
        text = (f"up to {c.max_epochs} epochs (patience {c.patience}) on {n:,} tuples "
                f"({n_val_m} maneuvers held out)")
        return float(c.max_epochs * n), text
    if stage.name == "closed_loop":
        return (float(c.iters * c.batch * c.window),
                f"{c.iters} iterations x {c.batch} episodes of {c.window:g} s")
    return (float(c.steps * c.batch), f"{c.steps:,} steps x {c.batch:,} states")


def describe_plan(recipe: Recipe, prepared: Prepared) -> tuple[list[str], float]:
    """What the run will cost: one line per source, per stage and the certificate, and the
    estimated seconds (from :data:`COST_S`)."""
    lines = [f"data {name}: {c['recordings']} recordings, {c['maneuvers']} maneuvers, "
             f"{c['tuples']:,} tuples ({'; '.join(c['label'])})"
             for name, c in prepared.counts.items()]
    s = recipe.split
    lines.append(f"held out: {len(prepared.held_out)} maneuvers (by {s.by}, "
                 + (f"{len(s.held_out)} named" if s.held_out else
                    f"{s.fraction:.0%} of each source, seed {s.seed}")
                 + (f"; drivers {', '.join(prepared.held_out_drivers)}" if
                    prepared.held_out_drivers and len(prepared.held_out_drivers) <= 8 else "")
                 + ")")
    total = 0.0
    for stage in recipe.stages:
        if not stage.enabled:
            lines.append(f"stage {stage.name}: off")
            continue
        units, text = work_units(stage, prepared)
        est = units * COST_S[stage.name]
        total += est
        lines.append(f"stage {stage.name}: {text}: ~{_duration(est)}")
    cert = recipe.certify
    if cert.enabled:
        est = min(cert.budget_s, (cert.max_boxes or np.inf) * COST_S["certify"])
        total += est
        lines.append(f"certificate: up to {cert.max_boxes or 'unlimited'} boxes or "
                     f"{cert.budget_s:g} s: up to ~{_duration(est)}")
    samples = sum(c["tuples"] for c in prepared.counts.values())
    est = samples * COST_S["idm"]
    total += est
    lines.append(f"IDM baseline: calibrated on the training maneuvers ({samples:,} samples): "
                 f"~{_duration(est)}")
    lines.append(f"estimated: ~{_duration(total)} (from the shipped run's costs on 2 shared "
                 "cores; finished stages are skipped)")
    return lines, total


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def stage_digest(previous: str, stage: Stage, sources: list[str],
                 init_sha256: str | None = None) -> str:
    """A stage's digest: the one before it (data and split, then each stage up to it), its
    config and sources, and (the open loop off) the weights it starts from. Not the recipe's
    name: the final checkpoint takes it (:func:`write_final`), renaming retrains nothing."""
    return _sha({"previous": previous, "stage": stage.name, "sources": sources,
                 "config": dataclasses.asdict(stage.config), "init": init_sha256})


def _finished(marker: Path, digest: str) -> dict[str, Any] | None:
    """The marker of a finished stage with this digest whose checkpoint is intact, else None."""
    done = _read_json(marker)
    if done is None or done.get("digest") != digest:
        return None
    weights = marker.with_name(marker.name.replace(".done.json", ".safetensors"))
    if not weights.is_file() or hashlib.sha256(weights.read_bytes()).hexdigest() \
            != done.get("weights_sha256"):
        return None
    return done


def _run_one(stage: Stage, recipe: Recipe, paths: list[Path], starts: tuple[Path | None,
             Path | None], held: Sequence[str], prefix: Path, progress: bool) -> None:
    """Train one stage on the tuples files ``paths`` into the checkpoint ``prefix`` (the
    stages' own functions); ``starts``: the checkpoint it starts from and the lateral refit's
    reference; ``held``: the held-out maneuver ids."""
    from safeil_sumo.learn.finetune import finetune
    from safeil_sumo.learn.lateral_refit import refit_lateral
    from safeil_sumo.learn.trainer import train_checkpoint

    if stage.name == "openloop":
        # the split is the recipe's, drawn once over all the data: named ids, no fraction
        ids = {str(m) for p in paths for m in Tuples.load(p).maneuvers}
        train_checkpoint(stage.config, paths, prefix, recipe.name, val_fraction=0.0,
                         val_maneuvers=[m for m in held if m in ids],
                         progress=progress)
        return
    init, reference = starts
    if init is None:
        raise RecipeError(f"stage {stage.name}: no checkpoint to start from")
    if stage.name == "closed_loop":
        finetune(stage.config, init, paths, prefix, progress=progress)
    elif reference is None:
        raise RecipeError("stage lateral_refit: no open-loop reference checkpoint")
    else:
        refit_lateral(stage.config, init, reference, paths, prefix, progress=progress)


def _init_checkpoint(recipe: Recipe) -> Path:
    """The checkpoint the closed loop starts from when the open loop is off."""
    from safeil_sumo.planners import registry as planner_registry

    if recipe.init is None:
        raise RecipeError(f"{recipe.path}: the openloop stage is off: set init = a checkpoint "
                          "path (or a shipped name) for the next stage to start from")
    path = planner_registry.policy_file(recipe.init)
    if not path.is_file():
        raise RecipeError(f"{recipe.path}: init {recipe.init}: no checkpoint at {path}")
    return path


def run_stages(recipe: Recipe, prepared: Prepared, out: Path, progress: bool, echo: Echo
               ) -> tuple[Path, dict[str, dict[str, Any]]]:
    """Run (or resume) the enabled stages; the last one's checkpoint prefix and per stage
    ``status`` (ran, resumed, off), ``seconds`` and the losses its checkpoint recorded."""
    digest, last, reference, init_sha = prepared.digest, None, None, None
    if not recipe.openloop.enabled:
        init = _init_checkpoint(recipe)
        last = reference = init.with_suffix("")
        init_sha = hashlib.sha256(init.read_bytes()).hexdigest()
    report: dict[str, dict[str, Any]] = {}
    for stage in recipe.stages:
        if not stage.enabled:
            report[stage.name] = {"status": "off"}
            continue
        sources = stage_sources(stage, prepared)
        digest = stage_digest(digest, stage, sources, init_sha)
        prefix = out / "stages" / stage.name
        marker = prefix.with_name(f"{stage.name}.done.json")
        done = _finished(marker, digest)
        if done is None:
            echo(f"stage {stage.name}: training on {', '.join(sources)}")
            start = time.perf_counter()
            try:
                _run_one(stage, recipe, stage_paths(stage, prepared), (last, reference),
                         prepared.held_out, prefix, progress)
            except ValueError as exc:  # a config the data or checkpoint cannot take
                raise RecipeError(f"stage {stage.name}: {exc}") from exc
            weights = prefix.with_suffix(".safetensors").read_bytes()
            done = {"digest": digest, "weights_sha256": hashlib.sha256(weights).hexdigest(),
                    "seconds": time.perf_counter() - start, "finished_unix_s": time.time()}
            _write_json(marker, done)  # last: the stage counts as finished from here
            status = "ran"
        else:
            echo(f"stage {stage.name}: finished before (same recipe and data), skipped")
            status = "resumed"
        report[stage.name] = {"status": status, "sources": sources,
                              "seconds": done["seconds"],
                              "finished_unix_s": done["finished_unix_s"],
                              "losses": stage_losses(stage.name, prefix)}
        last = prefix
        if stage.name == "openloop":
            reference = prefix
    if last is None:
        raise RecipeError(f"{recipe.path}: every stage is off: nothing to train")
    return last, report


def stage_losses(name: str, prefix: Path) -> dict[str, Any]:
    """The losses a stage's checkpoint recorded (first and final / best)."""
    meta = json.loads(prefix.with_suffix(".json").read_text())
    m = meta.get("metrics", {})
    if name == "openloop":
        return {"best_epoch": m.get("best_epoch"),
                "epochs_run": meta.get("training", {}).get("epochs_run"),
                "train_total": m.get("train_total"), "val_total": m.get("val_total")}
    part = m.get(name, {})
    last = part.get("final") if name == "closed_loop" else part.get("last_100_mean")
    keys = ("loss", "gap", "speed") if name == "closed_loop" else ("loss", "fit_m2", "lane")
    return {"first": {k: part.get("first", {}).get(k) for k in keys},
            "final": {k: (last or {}).get(k) for k in keys}}


def write_final(last: Path, out: Path, name: str, data: Sequence[DataSpec] = ()) -> Path:
    """The last stage's checkpoint as ``out/<name>.safetensors`` + ``.json``: the weights
    byte for byte, the sidecar naming the policy ``name``, its weights file and the recordings
    it was trained on (``training_data``: each spec's :meth:`~DataSpec.to_json`, where
    ``safeil-evaluate`` finds its held-out maneuvers)."""
    weights = last.with_suffix(".safetensors").read_bytes()
    meta = json.loads(last.with_suffix(".json").read_text())
    meta["name"] = name
    meta["weights_file"] = f"{name}.safetensors"
    meta["training_data"] = [spec.to_json() for spec in data]
    final = out / f"{name}.safetensors"
    with atomic_path(final) as tmp:
        tmp.write_bytes(weights)
    _write_json(final.with_suffix(".json"), meta)
    return final


def certify_final(recipe: Recipe, final: Path, out: Path, progress: bool, echo: Echo
                  ) -> dict[str, Any]:
    """The final checkpoint's certificate (as ``safeil-certify`` writes it, beside it), on the
    recipe's budget; reused when one with the same weights and budget is there. Its summary:
    certified share per margin, complete or not, seconds."""
    from safeil_sumo.learn.branch_and_bound import Budget, certify
    from safeil_sumo.learn.certificate import (
        certificate_path,
        load_certificate,
        write_certificate,
    )
    from safeil_sumo.learn.certify_margins import CertEnvelope
    from safeil_sumo.learn.inference import MLPPolicy
    from safeil_sumo.planners import registry as planner_registry

    spec = recipe.certify
    path = certificate_path(final)
    marker = out / "stages" / "certify.done.json"
    digest = _sha({"certify": dataclasses.asdict(spec),
                   "weights": json.loads(final.with_suffix(".json").read_text())
                   ["weights_sha256"]})
    done = _read_json(marker)
    if done is not None and done.get("digest") == digest and load_certificate(final).valid:
        echo("certificate: finished before (same weights and budget), skipped")
        return {**done["summary"], "status": "resumed"}
    echo(f"certificate: certifying {final.name}")
    policy = planner_registry.load(str(final))
    if not isinstance(policy, MLPPolicy):  # cannot be: a checkpoint written above
        raise RecipeError(f"{final}: not a network checkpoint")
    result = certify(policy,
                     CertEnvelope(time_gap_s=spec.time_gap_range_s),
                     budget=Budget(seconds=spec.budget_s, boxes=spec.max_boxes,
                                   batch=spec.batch, seed=spec.seed), progress=progress)
    write_certificate(result, final)
    summary = {"path": str(path), "seconds": result.seconds,
               "certified": {m: r.certified for m, r in result.margins.items()},
               "counterexample": {m: r.with_counterexample for m, r in result.margins.items()},
               "complete": all(r.stopped_by == "proven" for r in result.margins.values())}
    _write_json(marker, {"digest": digest, "summary": summary})
    return {**summary, "status": "ran"}


def fit_idm_baseline(prepared: Prepared, final: Path, out: Path, seed: int, echo: Echo
                     ) -> dict[str, Any]:
    """The IDM the report card compares the model with (``safeil-evaluate``): its five
    parameters calibrated (:func:`safeil_sumo.planners.idm.fit_idm`) on the model's training maneuvers,
    every source pooled, the held-out maneuvers left out of the fit and scored; written beside
    the checkpoint (:func:`safeil_sumo.planners.idm.baseline_path`, ``held_out_from`` naming its
    sidecar). Reused when
    its marker holds the same data digest. Its summary: path, parameters, RMSEs, seconds."""
    from safeil_sumo.planners import idm

    path, marker = idm.baseline_path(final), out / "stages" / "idm.done.json"
    digest = _sha({"idm": prepared.digest, "seed": seed})
    done = _read_json(marker)
    if done is not None and done.get("digest") == digest and idm.is_model_file(path):
        echo("IDM baseline: calibrated before (same data), skipped")
        return {**done["summary"], "status": "resumed"}
    held = set(prepared.held_out)
    maneuvers = [m for paths in prepared.files.values() for p in paths
                 for m in idm.maneuvers_from_tuples(Tuples.load(p))]
    train = [m for m in maneuvers if m.maneuver_id not in held]
    test = [m for m in maneuvers if m.maneuver_id in held]
    if not train:  # nothing to calibrate on: the report card falls back to the shipped IDM
        echo("IDM baseline: no training maneuver with a leader, not calibrated")
        return {"status": "skipped"}
    echo(f"IDM baseline: calibrating on {len(train)} training maneuvers")
    start = time.perf_counter()
    fit = idm.fit_idm(train, seed=seed)
    score: dict[str, Any] = {"fit_rmse_gap_m": fit.rmse_gap_m,
                             "fit_rmse_speed_mps": fit.rmse_speed_mps,
                             "fit_maneuvers": len(train), "held_out_maneuvers": len(test)}
    if test:
        gap, speed = idm.evaluate_fit(test, fit.params)
        score |= {"held_out_rmse_gap_m": gap, "held_out_rmse_speed_mps": speed}
    idm.save_model(path, {"training": fit}, default="training",
                   extra={"scores": {"training": score},
                          "held_out_from": [final.with_suffix(".json").name]})
    summary = {"path": str(path), "params": dataclasses.asdict(fit.params), **score,
               "seconds": time.perf_counter() - start}
    _write_json(marker, {"digest": digest, "summary": summary})
    return {**summary, "status": "ran"}


def run_recipe(recipe: Recipe, out: Path, progress: bool = True, echo: Echo = print,
               dry_run: bool = False) -> dict[str, Any]:
    """Run the recipe into ``out`` (resuming finished stages) and write the summary; with
    ``dry_run`` only process the data and return the plan. Returns the summary."""
    start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    prepared = prepare(recipe, out, progress, echo)
    plan, estimate = describe_plan(recipe, prepared)
    for line in plan:
        echo(line)
    summary: dict[str, Any] = {
        "recipe": str(recipe.path), "name": recipe.name, "seed": recipe.seed,
        "digest": prepared.digest, "data": prepared.counts,
        "split": {**dataclasses.asdict(recipe.split), "held_out_maneuvers":
                  list(prepared.held_out), "held_out_drivers": list(prepared.held_out_drivers)},
        "plan": plan, "estimated_s": estimate}
    if dry_run:
        return summary
    last, stages = run_stages(recipe, prepared, out, progress, echo)
    final = write_final(last, out, recipe.name, recipe.data)
    summary["stages"] = stages
    summary["checkpoint"] = str(final)
    if recipe.certify.enabled:
        summary["certificate"] = certify_final(recipe, final, out, progress, echo)
    summary["idm"] = fit_idm_baseline(prepared, final, out, recipe.seed, echo)
    summary["seconds"] = time.perf_counter() - start  # this run's
    summary["training_seconds"] = sum(st.get("seconds", 0.0) for st in stages.values())
    _write_json(out / "summary.json", summary)
    with atomic_path(out / "summary.md") as tmp:
        tmp.write_text(summary_markdown(summary))
    return summary


def summary_markdown(s: dict[str, Any]) -> str:
    """A short markdown of the summary: data, split, per-stage losses, certificate, time."""
    head = f"Recipe `{s['recipe']}`, seed {s['seed']}, digest `{s['digest'][:12]}`."
    lines = [f"# Training summary: {s['name']}", "", head, "",
             "| data | recordings | maneuvers | tuples |", "|---|---:|---:|---:|"]
    lines += [f"| {n} | {c['recordings']} | {c['maneuvers']} | {c['tuples']:,} |"
              for n, c in s["data"].items()]
    sp = s["split"]
    lines += ["", f"Held out (by {sp['by']}): {len(sp['held_out_maneuvers'])} maneuvers"
              + (f", drivers {', '.join(sp['held_out_drivers'])}" if sp["held_out_drivers"]
                 else "") + ".", "", "| stage | status | seconds | losses |", "|---|---|---:|---|"]
    for name, st in s["stages"].items():
        losses = json.dumps(st.get("losses", {}), default=str).replace("|", "/")
        seconds = f"{st['seconds']:.1f}" if "seconds" in st else ""
        lines.append(f"| {name} | {st['status']} | {seconds} | {losses} |")
    cert = s.get("certificate")
    if cert:
        shares = ", ".join(f"{m} {v:.4%}" for m, v in cert["certified"].items())
        lines += ["", f"Certificate: {shares}" + (" (complete)" if cert["complete"] else "")
                  + f", {cert['seconds']:.1f} s."]
    fit = s.get("idm")
    if fit and fit.get("status") != "skipped":
        held = (f", held out {fit['held_out_rmse_gap_m']:.2f} m" if "held_out_rmse_gap_m" in fit
                else "")
        text = (f"IDM baseline `{fit['path']}`: gap RMSE on its {fit['fit_maneuvers']} training "
                f"maneuvers {fit['fit_rmse_gap_m']:.2f} m{held}.")
        lines += ["", text]
    tail = (f"Checkpoint `{s['checkpoint']}`; the stages trained "
            f"{s['training_seconds']:.1f} s, this run took {s['seconds']:.1f} s.")
    lines += ["", tail, ""]
    return "\n".join(lines)
