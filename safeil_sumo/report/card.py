"""The report card of ``safeil-evaluate`` (:mod:`safeil_sumo.evaluate`): its sections, their
checks and verdicts, rendered as Markdown (``report.md``) and JSON (``report.json``).

Pure: no SUMO, no files. A :class:`Section` holds its numbers (a flat ``name -> value`` map,
the unit in the name's suffix: ``min_ttc_s``, ``gap_rmse_median_m``, a rate as a fraction),
its :class:`Check` s (a key number, the stated criterion and whether it was met), the commands
that reproduce it and its figures. ``report.md`` and ``report.json`` are written from the same
section objects, and each number is shown in ``report.md`` by :func:`format_value`, so the two
cannot disagree.
"""

from __future__ import annotations

import math
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from safeil_sumo.experiments.stats import wilson_interval

PASS, FAIL, NOT_APPLICABLE, ERROR, NOT_RUN = "PASS", "FAIL", "n/a", "ERROR", "not run"
Number = bool | int | float | str | None


@dataclass(frozen=True)
class Check:
    """One judged quantity: ``key`` the key number as shown (``"10/10 completed"``),
    ``criterion`` the pass rule as stated, ``passed`` whether it holds (None: not
    applicable to this planner)."""

    name: str
    key: str
    criterion: str
    passed: bool | None

    @property
    def verdict(self) -> str:
        return verdict_of(self.passed)


@dataclass(frozen=True)
class Section:
    """One section of the report card (``key``: its id, e.g. ``safety``)."""

    key: str
    title: str
    measures: str  # what the section measures, one paragraph
    numbers: Mapping[str, Number] = field(default_factory=dict)
    checks: tuple[Check, ...] = ()
    commands: tuple[str, ...] = ()  # the console commands that reproduce it
    figures: tuple[str, ...] = ()  # paths relative to the report's folder
    notes: tuple[str, ...] = ()  # extra Markdown lines (caveats, what was read or skipped)
    error: str = ""  # why the section could not run ("" : it ran)
    seconds: float = math.nan  # wall time [s]
    status: str = "done"  # "done", "error" or "not run"


def verdict_of(passed: bool | None) -> str:
    """PASS / FAIL, or n/a for None."""
    return NOT_APPLICABLE if passed is None else PASS if passed else FAIL


def section_verdicts(section: Section) -> list[str]:
    """The verdict of each check; ERROR / not run for a section without results."""
    if section.status == "error":
        return [ERROR]
    if section.status != "done":
        return [NOT_RUN]
    return [c.verdict for c in section.checks]


def overall(sections: Sequence[Section]) -> str:
    """FAIL when a check failed; else INCOMPLETE when a section errored or did not run; else
    PASS (a check that does not apply counts neither way)."""
    verdicts = [v for s in sections for v in section_verdicts(s)]
    if FAIL in verdicts:
        return FAIL
    if ERROR in verdicts or NOT_RUN in verdicts:
        return "INCOMPLETE"
    return PASS


# ----------------------------------------------------------------------- the rules, by hand


def rate_text(k: int, n: int) -> str:
    """``k/n`` with its rate and Wilson 95 % interval, in percent: ``"0/30 (0.0 %, 95 % CI
    0.0-11.4 %)"``."""
    if n <= 0:
        return f"{k}/{n}"
    lo, hi = wilson_interval(k, n)
    return f"{k}/{n} ({100 * k / n:.1f} %, 95 % CI {100 * lo:.1f}-{100 * hi:.1f} %)"


def rate_numbers(name: str, k: int, n: int) -> dict[str, Number]:
    """``<name>``, ``<name>_rate`` [-] and its Wilson 95 % bounds ``<name>_ci_low/_high`` [-]."""
    lo, hi = wilson_interval(k, n) if n > 0 else (math.nan, math.nan)
    return {name: k, f"{name}_rate": k / n if n > 0 else math.nan,
            f"{name}_ci_low": lo, f"{name}_ci_high": hi}


def all_completed(completed: int, n: int) -> bool:
    """The paper's safety test: every scenario completed without a flag (and there were some)."""
    return n > 0 and completed == n


def none_of(*counts: int) -> bool:
    """No event of any kind counted (collisions, lane departures, avoidable flags, failures)."""
    return all(int(c) == 0 for c in counts)


def certificate_passes(valid: bool, certified: dict[str, float]) -> bool:
    """A valid certificate proving every margin on the whole envelope (100 %)."""
    return bool(valid) and bool(certified) and all(v >= 1.0 for v in certified.values())


def beats(value: float, baseline: float) -> bool:
    """``value`` strictly below ``baseline`` (both finite): a smaller error than the baseline's."""
    return math.isfinite(value) and math.isfinite(baseline) and value < baseline


def best_median_worst(values: Sequence[float]) -> list[tuple[str, int]]:
    """``[("best", i), ("median", j), ("worst", k)]``: the positions of the smallest, the
    median (the lower middle of an even count) and the largest finite value; labels that fall
    on a position already taken are dropped (fewer than three values)."""
    finite = [i for i, v in enumerate(values) if math.isfinite(v)]
    order = sorted(finite, key=lambda i: (values[i], i))
    if not order:
        return []
    picks = [("best", order[0]), ("median", order[(len(order) - 1) // 2]), ("worst", order[-1])]
    seen: set[int] = set()
    out = []
    for label, i in picks:
        if i not in seen:
            out.append((label, i))
            seen.add(i)
    return out


# ----------------------------------------------------------------------- rendering


def format_value(value: Number) -> str:
    """How a number is shown in report.md: booleans yes/no, integers as they are, floats to 4
    significant digits, missing values and NaN as ``-``."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def command_line(program: str, args: Sequence[object]) -> str:
    """A shell command line: ``program`` and its arguments, each quoted where needed."""
    return " ".join([program, *(shlex.quote(str(a)) for a in args)])


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def verdict_table(sections: Sequence[Section]) -> list[str]:
    """The Markdown verdict table: one row per check (one per section without results)."""
    lines = ["| # | section | check | key number | criterion | verdict |",
             "|---|---|---|---|---|---|"]
    for k, s in enumerate(sections, 1):
        if s.status != "done":
            reason = s.error if s.status == "error" else "interrupted or not selected"
            lines.append(f"| {k} | {_cell(s.title)} | - | - | {_cell(reason)} | "
                         f"{section_verdicts(s)[0]} |")
            continue
        for c in s.checks:
            lines.append(f"| {k} | {_cell(s.title)} | {_cell(c.name)} | {_cell(c.key)} | "
                         f"{_cell(c.criterion)} | **{c.verdict}** |")
    return lines


def section_markdown(k: int, s: Section) -> list[str]:
    """One section: what it measures, its checks, its numbers, figures and commands."""
    took = "" if math.isnan(s.seconds) else f" ({s.seconds:.0f} s)"
    lines = [f"## {k}. {s.title}", "", s.measures, ""]
    if s.status != "done":
        what = f"**{ERROR}**: {s.error}" if s.status == "error" else f"**{NOT_RUN}**"
        return [*lines, what, "", "Reproduce:", "", "```", *s.commands, "```", ""]
    lines += [f"- {c.name}: {c.key} - criterion: {c.criterion} - **{c.verdict}**"
              for c in s.checks]
    lines += ["", *s.notes, *([""] if s.notes else []), "| number | value |", "|---|---|"]
    lines += [f"| `{name}` | {format_value(v)} |" for name, v in s.numbers.items()]
    lines.append("")
    lines += [f"![{s.key}: {fig}]({fig})" for fig in s.figures]
    lines += ["", f"Reproduce{took}:", "", "```", *s.commands, "```", ""]
    return lines


def render_markdown(header: dict[str, Number], sections: Sequence[Section]) -> str:
    """report.md: the title, the run's settings, the verdict table, then every section."""
    budget = "quick" if header.get("quick") else "full"
    took = header.get("seconds_total")
    took = math.nan if not isinstance(took, int | float) else float(took)
    summary = (f"Overall: **{overall(sections)}**. Written by `{header.get('command')}` "
               f"({budget} budget, seed {header.get('seed')}, commit {header.get('commit')}, "
               f"{took:.0f} s).")
    lines = [f"# Report card: {header.get('model')}", "", summary, "", "## Verdict", "",
             *verdict_table(sections), ""]
    for k, s in enumerate(sections, 1):
        lines += section_markdown(k, s)
    return "\n".join(lines)


def report_json(header: dict[str, Number], sections: Sequence[Section]) -> dict:
    """report.json: the header, the overall verdict and every section with the same numbers."""
    return {**header, "overall": overall(sections), "sections": [
        {"key": s.key, "title": s.title, "status": s.status, "error": s.error,
         "seconds": s.seconds, "numbers": dict(s.numbers),
         "checks": [{"name": c.name, "key": c.key, "criterion": c.criterion,
                     "passed": c.passed, "verdict": c.verdict} for c in s.checks],
         "commands": list(s.commands), "figures": list(s.figures),
         "notes": list(s.notes)} for s in sections]}
