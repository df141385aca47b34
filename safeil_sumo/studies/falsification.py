"""The ``falsify`` section of ``python -m safeil_sumo.results``: the falsification study of
``experiments/falsification_search.py``, the cross-entropy method against random sampling at
equal budget per planner. It writes ``falsify.csv``, the curves ``falsify.png`` and each
planner's worst avoidable case in ``falsify/`` (a scenario file to rerun it), and its part of
``results/studies.md`` (:func:`falsify_readme`)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from safeil_sumo.studies.shared import COLORS, LABELS, md_table, save_csv


def falsify(out: Path, work: Path) -> dict:
    """The falsification study (``experiments/falsification_search.py``'s ``STUDY``): per
    planner, CEM and random searches at equal budget (resumable in ``work/falsify``); ``falsify.csv``, the
    curves ``falsify.png`` and each planner's worst avoidable case in ``falsify/``."""
    from safeil_sumo.experiments import falsification_search as fz

    runs = [(run.policy, fz.run_or_load(run.policy, cfg,
                                        fz.study_folder(work / "falsify", run.policy, cfg),
                                        progress=True))
            for run in fz.STUDY for cfg in fz.study_configs(run)]
    rows = fz.study_rows(runs)
    save_csv(rows, out / "falsify.csv")
    worst = {}
    for policy in dict.fromkeys(p for p, _ in runs):  # the lowest score of all its searches
        res = min((r for p, r in runs if p == policy),
                  key=lambda r: (r.scores.min(), r.outcomes[r.best].min_ttc_s))
        toml = fz.write_worst(res, policy, out / "falsify", f"worst_{policy}")
        if toml is not None:
            worst[policy] = {**fz.summary(res, policy), "toml": toml.relative_to(out).as_posix()}
    _plot_falsify(runs, out / "falsify.png")
    return {"rows": rows.to_dict(orient="records"), "worst": worst,
            "study": [{"policy": r.policy, "budget": r.budget, "batch": r.batch,
                       "seeds": list(r.seeds)} for r in fz.STUDY],
            "medians": {c: fz.median_to_first(rows, c).to_dict(orient="records")
                        for c in ("first_failure", "first_ttc0")}}


def _plot_falsify(runs: list, path: Path) -> None:
    """Per planner (columns): the lowest score (min TTC of an avoidable run, flags at <= 1 s;
    top) and the failures found (bottom) against the simulations spent, each search a line (CEM
    solid, random dashed); first failures dotted."""
    policies = list(dict.fromkeys(p for p, _ in runs))
    fig, axes = plt.subplots(2, len(policies), figsize=(4.5 * len(policies), 6.5), squeeze=False)
    for col, policy in enumerate(policies):
        top, bottom = axes[0, col], axes[1, col]
        for res in (r for p, r in runs if p == policy):
            cem = res.config.method == "cem"
            style = {"color": COLORS.get(policy, "k") if cem else "tab:gray",
                     "ls": "-" if cem else "--", "lw": 1.2, "alpha": 0.8}
            label = f"{res.config.method}" if res.config.seed == 0 else None
            sims = np.arange(1, len(res.outcomes) + 1)
            best = np.where(np.isfinite(res.best_so_far), res.best_so_far, np.nan)
            top.step(sims, best, where="post", label=label, **style)
            if res.first_failure:
                top.plot(res.first_failure, best[res.first_failure - 1], "o", ms=4,
                         color=style["color"])
            bottom.plot(sims, np.cumsum([o.failure for o in res.outcomes]), label=label, **style)
        top.axhline(1.0, color="k", lw=0.6, ls=":")
        top.set_xscale("log")
        top.set_title(LABELS.get(policy, policy), fontsize=9)
        top.legend(fontsize=7)
        bottom.set_xlabel("simulations spent")
        bottom.legend(fontsize=7)
    axes[0, 0].set_ylabel("worst min TTC found [s]\n(avoidable runs; flagged <= 1 s)")
    axes[1, 0].set_ylabel("failures found")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def falsify_readme(f: dict) -> list[str]:
    """The falsification section: first failures (median over seeds) per planner and method,
    the lowest min TTC found, the worst cases and how to rerun them."""
    def med(col: str, policy: str, method: str) -> str:
        m = next((r for r in f["medians"][col] if r["policy"] == policy
                  and r["method"] == method), None)
        if m is None:
            return "-"
        v = m["median"]
        shown = f"{v:.0f}" if v is not None and math.isfinite(v) else "none"
        return f"{shown} ({m['found']}/{m['seeds']} found one)"

    rows = []
    for st in f["study"]:
        p = st["policy"]
        mine = [r for r in f["rows"] if r["policy"] == p]
        lows = {m: min((r["best_min_ttc_s"] for r in mine if r["method"] == m
                        and r["best_min_ttc_s"] is not None), default=None)
                for m in ("cem", "random")}
        found = " / ".join(f"{np.median([r['failures'] for r in mine if r['method'] == m]):.0f}"
                           for m in ("cem", "random"))
        rows.append({"planner": LABELS.get(p, p), "budget": f"{st['budget']} x {len(st['seeds'])} "
                     f"seeds (batch {st['batch']})",
                     "cem": med("first_failure", p, "cem"),
                     "random": med("first_failure", p, "random"),
                     "cem0": med("first_ttc0", p, "cem"), "random0": med("first_ttc0", p, "random"),
                     "found": found,
                     "low": " / ".join("-" if v is None else f"{v:.2f}" for v in lows.values())})
    worst = [f"- {LABELS.get(p, p)}: min TTC {w['best_min_ttc_s']:.2f} s "
             f"({w['best_flag'] or 'no flag'}; {w['method']} seed {w['seed']}, simulation "
             f"{w['best_sim']}): `python -m safeil_sumo.sweep --config results/{w['toml']}`"
             for p, w in f["worst"].items()]
    text = ("`python -m safeil_sumo.results --only falsify` (docs/falsification.md): the "
            "cross-entropy method (CEM) against uniform random sampling at equal budget over "
            "leader braking (onset, deceleration, duration), cut-ins (gap, speed), recorded "
            "NGSIM leader windows, the track's radius and sensor noise; a batch is one SUMO "
            "simulation. Only scenarios that braking at 6 m/s² from the start avoids count; a "
            "failure is a flag (TTC ≤ 1 s, lane departure, collision) in one of them. Columns: "
            "simulations to the first failure and to the first avoidable run reaching TTC 0, "
            "median over seeds (in order of draw); the failures each search found; the lowest min "
            "TTC found, CEM / random. Per search: `falsify.csv`; every simulation: "
            "`runs/results_work/falsify/*/evaluations.csv` (not committed), where a rerun reads "
            "the finished searches back: the section's own wall time below is such a rerun's; "
            "the searches took about 50 min on 2 shared cores, two at a time. Every planner runs "
            "with the loop's brake guard, as shipped (docs/brake_guard.md; `--no-brake-guard` "
            "searches the planners alone: docs/falsification.md).")
    return ["## Falsification: searching for failures", "", text, "",
            md_table(rows, {"planner": "planner", "budget": "simulations per search",
                            "cem": "CEM: to 1st failure", "random": "random: to 1st failure",
                            "cem0": "CEM: to TTC 0", "random0": "random: to TTC 0",
                            "found": "failures found CEM / random (median)",
                            "low": "lowest min TTC [s] CEM / random"}),
            "", "Worst avoidable case per planner (one command reruns each):", "", *worst, "",
            "![falsification curves](falsify.png)", ""]
