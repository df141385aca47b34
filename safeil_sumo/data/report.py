"""Write a pipeline report (JSON + Markdown) and a plot of one maneuver like the paper's Fig. 1.

The plot has two panels: (a) the ego frame at one state — left/right lane lines from the features,
the demonstrated future trajectory, its fitted B-spline and control points, and the leader's rear
bumper at ``d_lead``; (b) the maneuver over time — ``v_x``, ``v_lead`` and ``d_lead``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.core.bspline import evaluate
from safeil_sumo.core.features import FEATURE_NAMES
from safeil_sumo.data.pipeline import PipelineReport
from safeil_sumo.data.tuples import Tuples


def _atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def report_markdown(report: dict, title: str = "Data processing report") -> str:
    """Markdown for a :meth:`PipelineReport.to_dict` (plus optional ``import_stats``)."""
    lines = [f"# {title}: {report['source']}", ""]
    lines += ["| step | rows in | rows out | removed | events |", "|---|---:|---:|---:|---|"]
    for s in report["steps"]:
        ev = ", ".join(f"{k} {v}" for k, v in s["events"].items()) or "-"
        lines.append(f"| {s['name']} | {s['rows_in']} | {s['rows_out']} | "
                     f"{s['rows_in'] - s['rows_out'] if s['name'] != 'resample' else '(rate)'} "
                     f"| {ev} |")
    lines += [
        "",
        (f"- recordings: {report['recordings']}; maneuvers kept {report['maneuvers_kept']}, "
        f"dropped (too short) {report['maneuvers_dropped']}; tuples: {report['tuples']}"),
        f"- time: {report['elapsed_s']:.3f} s ({report['rows_per_s']:,.0f} input rows/s)",
    ]
    for s in report["steps"]:
        for k, v in s["notes"].items():
            lines.append(f"- {s['name']}: {k} = {v:.4g}" if isinstance(v, float)
                         else f"- {s['name']}: {k} = {v}")
    if "import_stats" in report:
        lines += ["", "## Import", "", "```json",
                  json.dumps(report["import_stats"], indent=1, default=str), "```"]
    cfg = report["config"]
    lines += ["", "## Settings", ""] + [f"- `{k}` = {v}" for k, v in cfg.items()]
    return "\n".join(lines) + "\n"


def write_report(report: PipelineReport, out_dir: str | Path, stem: str,
                 import_stats: dict | None = None) -> tuple[Path, Path]:
    """``<stem>_report.json`` and ``<stem>_report.md`` in ``out_dir``; returns both paths."""
    out_dir = Path(out_dir)
    d = report.to_dict()
    if import_stats is not None:
        d["import_stats"] = import_stats
    js, md = out_dir / f"{stem}_report.json", out_dir / f"{stem}_report.md"
    _atomic_write(js, json.dumps(d, indent=1, default=str) + "\n")
    _atomic_write(md, report_markdown(d))
    return js, md


def plot_maneuver(tuples: Tuples, path: str | Path, maneuver: str | None = None,
                  index_in_maneuver: int = 0) -> Path:
    """PNG of one maneuver (default: the longest) at its ``index_in_maneuver``-th state."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if len(tuples) == 0:
        raise ValueError("no tuples to plot")
    ids, counts = np.unique(tuples.maneuver_id, return_counts=True)
    man = maneuver if maneuver is not None else str(ids[np.argmax(counts)])
    rows = np.flatnonzero(tuples.maneuver_id == man)
    if len(rows) == 0:
        raise ValueError(f"no maneuver {man!r}")
    i = rows[min(index_in_maneuver, len(rows) - 1)]
    f = dict(zip(FEATURE_NAMES, tuples.features[i], strict=True))
    fut, cp = tuples.future[i], tuples.control_points[i]

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    x_max = max(float(fut[:, 0].max()), f["d_lead"] + 5.0, 10.0)
    xs = np.linspace(0.0, x_max, 100)
    for side, color in (("l", "k"), ("r", "k")):
        ys = f[f"c0{side}"] + f[f"c1{side}"] * xs + f[f"c2{side}"] * xs**2
        ax.plot(xs, ys, color=color, lw=1.5, label="lane lines" if side == "l" else None)
    ax.plot(fut[:, 0], fut[:, 1], "o", ms=3, color="tab:blue", label="demonstrated future")
    spline = evaluate(cp, np.linspace(0.0, 1.0, 100))
    ax.plot(spline[:, 0], spline[:, 1], "-", color="tab:orange", label="B-spline fit")
    allcp = np.vstack([[0.0, 0.0], cp])
    ax.plot(allcp[:, 0], allcp[:, 1], "s--", color="tab:orange", ms=5, alpha=0.6,
            label="control points")
    ax.add_patch(plt.Rectangle((f["d_lead"], -0.9), 4.5, 1.8, color="tab:red", alpha=0.5,
                               label="leader"))
    ax.plot([0.0], [0.0], "k^", ms=8, label="ego (front bumper)")
    ax.set_xlabel("x ego [m]")
    ax.set_ylabel("y ego [m] (left)")
    ax.set_title(f"{man}, t = {tuples.t[i]:.1f} s, horizon {tuples.horizon:g} s")
    ax.set_xlim(-2.0, x_max + 6.0)
    ax.set_ylim(-6.0, 6.0)
    ax.legend(fontsize=7, loc="upper right")

    t = tuples.t[rows] - tuples.t[rows[0]]
    feats = tuples.features[rows]
    j = {n: k for k, n in enumerate(FEATURE_NAMES)}
    ax2.plot(t, feats[:, j["v_x"]], label="v_x [m/s]")
    ax2.plot(t, feats[:, j["v_lead"]], label="v_lead [m/s]")
    ax2.plot(t, feats[:, j["d_lead"]], label="d_lead [m]")
    ax2.axvline(tuples.t[i] - tuples.t[rows[0]], color="gray", lw=0.8)
    ax2.set_xlabel("time in maneuver [s]")
    ax2.legend(fontsize=8)
    ax2.set_title(f"{tuples.source[i]}: {len(rows)} tuples")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
