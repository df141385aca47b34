"""What every section of ``python -m safeil_sumo.results`` shares: the repository's paths (the
shipped SafeIL and its synthetic tuples), the planners compared with their labels and colours, a
sweep run with one line of progress per section, an atomic CSV write and the Markdown table and
percentage formats of ``results/README.md`` and ``results/studies.md``. It writes no file of
its own."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from safeil_sumo.experiments.sweep_executor import DEFAULT_BATCH, run_sweep
from safeil_sumo.scenarios.spec import Task

REPO = Path(__file__).resolve().parents[2]
SHIPPED_DATA = REPO / "data" / "synthetic" / "tuples.parquet"
SHIPPED_SAFEIL = REPO / "safeil_sumo" / "models" / "safeil.json"
POLICIES = ("safeil", "safeil_openloop", "safeil_paper", "bc", "analytic", "idm")
LABELS = {"safeil": "SafeIL (closed loop + driver style)",
          "safeil_openloop": "SafeIL open loop (exact lane bound)",
          "safeil_paper": "SafeIL (paper barrier)",
          "bc": "BC", "analytic": "analytic", "idm": "IDM (calibrated)",
          "recorded": "recorded human path (the replay's floor)",
          "constant_speed": "constant speed (naive baseline)",
          "safeil_population": "SafeIL, driver population",
          "idm_population": "IDM (calibrated), driver population (its T drawn)"}
COLORS = {"safeil": "tab:green", "safeil_openloop": "tab:cyan", "safeil_paper": "tab:olive",
          "bc": "tab:red",
          "analytic": "tab:gray", "idm": "tab:blue", "safeil_population": "tab:purple",
          "idm_population": "tab:orange"}


def section_sweep(specs: list[Task], work: Path, name: str, workers: int) -> pd.DataFrame:
    print(f"[{name}] {len(specs)} tasks", flush=True)
    df = run_sweep(specs, work / name, workers=workers, progress=True, batch=DEFAULT_BATCH)
    failed = df[df["status"] != "ok"] if "status" in df else df.iloc[:0]
    if len(failed):
        print(f"[{name}] {len(failed)} task(s) failed, e.g. {failed['error'].iloc[0]}")
    return df


def save_csv(df: pd.DataFrame, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    df.to_csv(tmp, index=False, float_format="%.6g")
    tmp.replace(path)


def md_table(rows: list[dict], columns: dict[str, str]) -> str:
    """A Markdown table of ``rows`` with ``columns`` {key: header} (floats to 3 significant)."""

    def fmt(v: object) -> str:
        if isinstance(v, float):
            if math.isnan(v):
                return "–"
            return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"
        return "–" if v in (None, "") else str(v)

    head = "| " + " | ".join(columns.values()) + " |"
    sep = "|" + "---|" * len(columns)
    body = ["| " + " | ".join(fmt(r.get(k)) for k in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body])


def pct(rate: float | None, low: float | None = None, high: float | None = None) -> str:
    if rate is None or (isinstance(rate, float) and math.isnan(rate)):
        return "–"
    text = f"{100 * rate:.0f} %"
    # 3 significant digits: 1,000/1,000 has the interval [99.6, 100], not "[100, 100]"
    if low is None or high is None:
        return text
    return text + f" [{100 * low:.3g}, {100 * high:.3g}]"
