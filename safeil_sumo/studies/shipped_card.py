"""The ``card`` section of ``python -m safeil_sumo.results``: the shipped ``safeil``'s report
card, ``safeil-evaluate safeil`` at its full budgets, its report, figures and tables copied into
``report_card/``, and the card's part of ``results/README.md`` (:func:`card_readme`)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

CARD = "report_card"  # results/report_card/: the shipped safeil's report card


def card(out: Path, work: Path, workers: int, seed: int) -> dict:
    """The shipped ``safeil``'s report card: ``safeil-evaluate safeil`` at its full budgets
    (resumable in ``work/report_card``), its report, figures and tables copied into
    ``out/report_card``. Facts: its overall verdict and wall time."""
    from safeil_sumo import evaluate
    from safeil_sumo.report.sections import shown_path

    folder = work / CARD
    evaluate.main(["safeil", "--workers", str(workers), "--seed", str(seed), "--out",
                   shown_path(folder)])
    target = out / CARD
    target.mkdir(parents=True, exist_ok=True)
    for name in ("report.md", "report.json"):
        shutil.copyfile(folder / name, target / name)
    for sub in ("figures", "data"):
        shutil.rmtree(target / sub, ignore_errors=True)
        shutil.copytree(folder / sub, target / sub)
    report = json.loads((target / "report.json").read_text())
    return {"overall": report["overall"], "seconds": report.get("seconds_total")}


def card_readme(out: Path) -> list[str]:
    """The card's part of ``results/README.md``: its ``report.md`` under our heading, its
    figures linked from ``results/`` (nothing before the card has run)."""
    report = out / CARD / "report.md"
    if not report.is_file():
        return []
    body = report.read_text().split("\n", 1)[1]  # its own title replaced by ours
    body = body.replace("](figures/", f"]({CARD}/figures/").replace("\n## ", "\n### ")
    return ["## The report card", "", body.strip(), ""]
