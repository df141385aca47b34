"""``python -m safeil_sumo.results``: regenerate ``results/`` — the paper's figures and beyond.

Sections (``--only`` picks some; every sweep is resumable, its task files live in ``--work``):

- ``safety``: the paper's Fig. "Safety Performance" — curved500, 10 scenarios, leader at a
  constant random speed in [25, 32] m/s — for the shipped planners, beside the paper's bars;
- ``large``: the same test with many scenarios, Wilson 95 % intervals, with/without the filter;
- ``grids``: radius, braking leaders, sensor noise and initial-gap grids;
- ``replay``: human-likeness replays (OpenACC, NGSIM, a held-out synthetic maneuver);
- ``efficiency``: SafeIL vs BC trained on growing subsets of maneuvers (several seeds);
- ``leader``: the static leader probe and the leader-response suite for every planner;
- ``humanlike``: every 11 s window (every 20 s) of the held-out OpenACC and NGSIM maneuvers
  replayed with every planner: gap-RMSE distributions with bootstrap intervals;
- ``whole``: the same held-out maneuvers replayed whole (start to end), beside the
  ``constant_speed`` baseline: gap RMSE median, mean and worst, spacing RMSPE, time-gap error,
  per planner and per driver;
- ``unseen``: every whole ZalaZone maneuver (24 drivers never used in training or calibration)
  replayed with the same planners in the longitudinal instrument mode (``--lateral lane``);
- ``lodo``: ``training/leave_one_driver_out.py``: the shipped recipe trained without each
  OpenACC driver (and a quarter of the NGSIM drivers), the left-out drivers replayed whole;
- ``ablation``: ``training/leader_following_ablation.py`` (one lever at a time);
- ``instrument``: the replay's own error: the ``recorded`` pseudo-planner (the human's path)
  over every whole maneuver of OpenACC, NGSIM and the synthetic drives;
- ``falsify``: the falsification study (``experiments/falsification_search.py``): CEM against
  random sampling at equal budget per planner, the curves and each planner's worst avoidable
  case;
- ``card``: the shipped ``safeil``'s report card (``safeil-evaluate safeil``, full budgets);
- and ``results/README.md`` (the paper's safety test and replay beside ours, then the report
  card) and ``results/studies.md`` (every other section).

Only small outputs (PNG, CSV, Markdown) go to ``results/``; logs stay in the work folder.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pandas as pd

from safeil_sumo.cli_args import CommandParser, interruptible, positive_int
from safeil_sumo.experiments import outputs
from safeil_sumo.studies.falsification import falsify, falsify_readme
from safeil_sumo.studies.held_out_windows import humanlike, humanlike_readme
from safeil_sumo.studies.leader_response import leader, leader_readme
from safeil_sumo.studies.n74_traffic import n74, n74_readme
from safeil_sumo.studies.open_loop_errors import openloop, openloop_readme
from safeil_sumo.studies.paper_replay import replay, replay_readme
from safeil_sumo.studies.paper_safety import safety, safety_readme
from safeil_sumo.studies.replay_floor import instrument, instrument_readme
from safeil_sumo.studies.safety_grids import grids, grids_readme, large, large_readme
from safeil_sumo.studies.sample_efficiency import efficiency, efficiency_readme
from safeil_sumo.studies.shared import REPO
from safeil_sumo.studies.shipped_card import CARD, card, card_readme
from safeil_sumo.studies.training_scripts import ablation, ablation_readme, lodo, lodo_readme
from safeil_sumo.studies.whole_maneuvers import unseen, unseen_readme, whole, whole_readme

SECTIONS = ("safety", "large", "grids", "replay", "openloop", "efficiency", "leader",
            "humanlike", "whole", "unseen", "lodo", "ablation", "instrument", "n74", "falsify",
            "card")


def front_page(out: Path, facts: dict) -> list[str]:
    """``results/README.md``: the shipped ``safeil``'s report card (:func:`card`), after the
    paper's two figures beside ours."""
    commit = facts.get("section_git_commit", {}).get("card", facts.get("git_commit", "?"))
    lines = ["# Results: the shipped `safeil`", "",
             ("`python -m safeil_sumo.results --only card safety replay` writes this page: the "
              "paper's safety test and replay beside ours, then the report card of the shipped "
              "`safeil`, `safeil-evaluate safeil` at its full budgets (its files in "
              f"[`{CARD}/`]({CARD}/report.md)). Every other study (grids, many planners, "
              "whole-drive human-likeness, unseen drivers, leave one driver out, n74, "
              "falsification, sample efficiency) is in [studies.md](studies.md)."), "",
             f"- the card's git commit: `{commit}`", ""]
    lines += safety_readme(facts) if "safety" in facts else []
    lines += replay_readme(facts) if facts.get("replay") else []
    return lines + card_readme(out)


def write_readme(out: Path, facts: dict) -> None:
    """``results/README.md`` (:func:`front_page`) and ``results/studies.md``: our numbers beside
    the paper's, from ``facts.json``; a section appears once its facts exist."""
    args = facts.get("args", {})
    lines = _head_readme(facts, args)
    lines += large_readme(facts, args) if "large" in facts else []
    lines += grids_readme(facts, args) if "grids" in facts else []
    lines += humanlike_readme(facts) if facts.get("humanlike") else []
    lines += whole_readme(facts["whole"]) if facts.get("whole") else []
    lines += unseen_readme(facts["unseen"]) if facts.get("unseen") else []
    lines += instrument_readme(facts) if facts.get("instrument") else []
    lines += leader_readme(facts) if facts.get("leader") else []
    lines += lodo_readme(out) if facts.get("lodo") else []
    lines += ablation_readme(out) if facts.get("ablation") else []
    lines += falsify_readme(facts["falsify"]) if facts.get("falsify") else []
    lines += openloop_readme(facts) if facts.get("openloop") else []
    lines += efficiency_readme(facts) if facts.get("efficiency") else []
    lines += n74_readme(facts["n74"]) if facts.get("n74") else []
    lines += _walls_readme(facts)
    for name, text in (("studies.md", lines), ("README.md", front_page(out, facts))):
        tmp = out / f".{name}.tmp"
        tmp.write_text("\n".join(text))
        tmp.replace(out / name)


def _head_readme(facts: dict, args: dict) -> list[str]:
    """The title, how the results were made, the commit and versions."""
    return [
        "# Studies",
        "",
        "The shipped `safeil`'s report card and the paper's figures beside ours are on the "
        "[front page](README.md). Regenerated by `python -m safeil_sumo.results` (sections: `--only " + " ".join(SECTIONS)
        + "`; sweeps resume from `runs/results_work/`). Everything here was measured by that "
        "command; the paper's numbers come from its figures.",
        "",
        f"- git commit: `{facts.get('git_commit', '?')}`; versions: "
        + ", ".join(f"{k} {v}" for k, v in facts.get("versions", {}).items()
                    if k in ("eclipse-sumo", "torch", "numpy", "python")),
        (f"- master seed {args.get('seed', 0)}; planners: the shipped checkpoints in "
        "`safeil_sumo/models/` (trained by `python training/train_shipped_models.py` on "
        "OpenACC (longitudinal only), NGSIM and the default synthetic dataset, seed 0; the IDM "
        "fitted by `python training/fit_idm.py` on the same human maneuvers). The open-loop and "
        "sample-efficiency sections train the paper's recipe (no envelope states) per dataset."),
        *_stale_readme(facts),
        "",
    ]


def _stale_readme(facts: dict) -> list[str]:
    """A warning naming the sections last run before the shipped models last changed."""
    stale = outputs.sections_before("safeil_sumo/models", facts.get("section_git_commit", {}))
    if not stale:
        return []
    return [(f"- **Run with earlier shipped models than these:** {', '.join(stale)} (each ran "
             "at a commit before `safeil_sumo/models/` last changed; `--only "
             f"{' '.join(stale)}` reruns them).")]


def _walls_readme(facts: dict) -> list[str]:
    """The wall time per section, and the commit each section last ran at."""
    walls = facts.get("section_wall_s", {})
    commits = facts.get("section_git_commit", {})

    def at(k: str) -> str:  # a section last run at another commit than the whole
        c = commits.get(k)
        return f" (commit `{c[:10]}`)" if c and c != facts.get("git_commit") else ""

    return ["Wall time per section on 2 cores (the last time each ran; a resumed sweep is "
            "faster): " + ", ".join(f"{k} {v:.0f} s{at(k)}" for k, v in walls.items()) + ".",
            ""]


def _section_runs(a: argparse.Namespace) -> dict[str, Callable[[], object]]:
    """Each section's computation (its facts, JSON-able), in the order they run."""
    def records(df: pd.DataFrame) -> list[dict]:
        return df.to_dict(orient="records")

    return {
        "safety": lambda: safety(a.out, a.work, a.workers, a.seed),
        "large": lambda: records(large(a.out, a.work, a.workers, a.seed, a.large)),
        "grids": lambda: {k: records(v) for k, v in
                          grids(a.out, a.work, a.workers, a.seed, a.grid).items()},
        "replay": lambda: records(replay(a.out, a.work, a.seed)),
        "openloop": lambda: records(openloop(a.out, a.work)),
        "efficiency": lambda: records(efficiency(a.out, a.work, a.workers, a.fractions, a.seeds,
                                                 a.efficiency_scenarios)),
        "leader": lambda: leader(a.out, a.work, a.workers, a.seed, 1 if a.quick else 3),
        "humanlike": lambda: humanlike(a.out, a.work, a.workers, a.seed),
        "whole": lambda: whole(a.out, a.work, a.workers, a.seed, a.quick),
        "unseen": lambda: unseen(a.out, a.work, a.workers, a.seed, a.quick),
        "lodo": lambda: lodo(a.out, a.workers),
        "ablation": lambda: ablation(a.out, a.workers),
        "instrument": lambda: instrument(a.out, a.work, a.workers, a.seed),
        "n74": lambda: n74(a.out, a.work, a.workers, a.seed, a.quick),
        "falsify": lambda: falsify(a.out, a.work),
        "card": lambda: card(a.out, a.work, a.workers, a.seed),
    }


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.results", description=__doc__,
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=REPO / "results")
    p.add_argument("--work", type=Path, default=REPO / "runs" / "results_work",
                   help="sweep task files and logs (resumable; not committed)")
    p.add_argument("--only", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    p.add_argument("--workers", type=positive_int, default=2)
    p.add_argument("--seed", type=int, default=0, help="master seed")
    p.add_argument("--large", type=positive_int, default=200, help="scenarios per bar in 'large'")
    p.add_argument("--grid", type=positive_int, default=20, help="scenarios per cell in 'grids'")
    p.add_argument("--fractions", type=float, nargs="+", default=[0.05, 0.15, 0.4, 1.0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--efficiency-scenarios", type=int, default=10)
    p.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test)")
    return p


@interruptible
def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    if args.quick:
        args.large, args.grid, args.fractions, args.seeds = 4, 2, [0.1, 1.0], [0]
        args.efficiency_scenarios = 2
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    facts: dict = {"versions": outputs.versions(), "git_commit": outputs.git_commit(),
                   "args": {k: (str(v) if isinstance(v, Path) else v)
                            for k, v in vars(args).items()}}
    walls: dict[str, float] = {}

    for name, run in _section_runs(args).items():  # in this order
        if name in args.only:
            t = time.perf_counter()
            facts[name] = run()
            walls[name] = round(time.perf_counter() - t, 1)
    facts["wall_time_s"] = time.perf_counter() - t0
    previous = args.out / "facts.json"
    merged = json.loads(previous.read_text()) if previous.is_file() else {}
    merged.setdefault("section_wall_s", {}).update(walls)
    merged.setdefault("section_git_commit", {}).update({k: facts["git_commit"] for k in walls})
    # a run of some sections keeps the run-wide args/commit of the full run (the other sections'
    # text reads them); its own commit is in section_git_commit
    partial = set(args.only) != set(SECTIONS) and "args" in merged
    run_wide = {"args", "git_commit", "versions", "wall_time_s"} if partial else set()
    merged.update({k: v for k, v in facts.items()
                   if k != "section_wall_s" and k not in run_wide})
    outputs.write_json(previous, merged)
    write_readme(args.out, json.loads(previous.read_text()))
    print(f"results in {args.out} ({facts['wall_time_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
