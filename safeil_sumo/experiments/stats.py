"""Sweep statistics: completion rates with Wilson intervals, and where each policy fails.

With 10 scenarios per cell (the paper's protocol) a completion rate of 7/10 has a 95 % interval
of about 0.40-0.89: the breakdown shows the interval next to every rate so that differences
within the noise are not read as results.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import pandas as pd

DEFAULT_BY = ("net", "policy", "safety_filter")


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval ``(low, high)`` of a binomial proportion ``successes / n``.

    ``z``: normal quantile (1.96 -> 95 %). ``n = 0`` gives the uninformative ``(0, 1)``.
    """
    if n < 0 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, got {successes} of {n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2.0 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n)) / denom
    # clamp rounding only: the interval lies in [0, 1] mathematically
    return max(0.0, centre - half), min(1.0, centre + half)


def _flag_counts(flags: pd.Series) -> str:
    counts = flags.fillna("").replace("", "none").value_counts()
    return " ".join(f"{k}:{v}" for k, v in sorted(counts.items()) if k != "none") or "-"


def breakdown(
    summary: pd.DataFrame, by: Sequence[str] = DEFAULT_BY, z: float = 1.96
) -> pd.DataFrame:
    """One row per group of ``by``: how many scenarios ran, completed, and why the rest failed.

    Columns: ``n`` (tasks), ``failed`` (tasks with ``status="failed"``: no valid result, not
    counted below), ``ok``, ``completed``, ``completion_rate`` and its Wilson interval
    ``ci_low`` / ``ci_high`` (over ``ok``), ``mean_path_completed`` [-], ``min_ttc_s`` (lowest
    over the group) [s], ``flags`` (first-flag reasons with counts) and ``flag_<reason>`` counts.
    """
    by = [c for c in by if c in summary.columns]
    if summary.empty or not by:
        raise ValueError(f"breakdown needs a non-empty summary with columns {list(by)}")
    df = summary.copy()
    if "status" not in df.columns:
        df["status"] = "ok"
    for col, default in (("completed", False), ("path_completed", math.nan),
                         ("flag", ""), ("min_ttc_s", math.nan)):
        if col not in df.columns:
            df[col] = default
    reasons = sorted({f for f in df.loc[df["status"] == "ok", "flag"].fillna("") if f})
    rows = []
    for key, group in df.groupby(by, sort=False, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        ok = group[group["status"] == "ok"]
        done = int(ok["completed"].fillna(False).astype(bool).sum())
        n_ok = len(ok)
        low, high = wilson_interval(done, n_ok, z)
        row = dict(zip(by, key, strict=True))
        row.update({
            "n": len(group),
            "failed": len(group) - n_ok,
            "ok": n_ok,
            "completed": done,
            "completion_rate": done / n_ok if n_ok else math.nan,
            "ci_low": low if n_ok else math.nan,
            "ci_high": high if n_ok else math.nan,
            "mean_path_completed": float(ok["path_completed"].mean()) if n_ok else math.nan,
            "min_ttc_s": float(ok["min_ttc_s"].min()) if n_ok else math.nan,
            "flags": _flag_counts(ok["flag"]) if n_ok else "-",
        })
        for reason in reasons:
            row[f"flag_{reason}"] = int((ok["flag"] == reason).sum())
        rows.append(row)
    return pd.DataFrame(rows)


def format_breakdown(table: pd.DataFrame) -> str:
    """The breakdown as a short text table: rate [%] with its 95 % interval, mean path [%]."""
    shown = table.copy()
    shown["completed"] = [f"{c}/{k}" for c, k in zip(shown["completed"], shown["ok"], strict=True)]
    shown["rate [95% CI]"] = [
        "-" if math.isnan(r) else f"{100 * r:.0f}% [{100 * lo:.0f}, {100 * hi:.0f}]"
        for r, lo, hi in zip(shown["completion_rate"], shown["ci_low"], shown["ci_high"], strict=True)
    ]
    shown["path[%]"] = (100 * shown["mean_path_completed"]).round(1)
    keys = list(table.columns[: list(table.columns).index("n")])  # the group-by columns
    cols = [*keys, "completed", "rate [95% CI]", "path[%]", "min_ttc_s", "flags", "failed"]
    return shown[cols].to_string(index=False, float_format=lambda v: f"{v:.2f}")
