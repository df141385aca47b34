"""The Python API: run a planner in SUMO and get the log as a DataFrame, in a few lines.

    from safeil_sumo import api

    result = api.run("curved500", policy="safeil", scenarios=2)
    result.summary          # one row per scenario (flags, path completed, min TTC, ...)
    result.log              # the per-step log of every scenario (column ``scenario``)

``policy`` is a shipped name (``safeil``, ``safeil_paper``, ``bc``, ``analytic``, ``idm``), a
checkpoint or IDM model path, or ANY object with the :class:`~safeil_sumo.policy.Policy` protocol
(``name``, ``horizon`` [s], ``plan(features (..., 9)) -> (..., 3, 2)``), so your own planner plugs
in. Scenarios are those of ``python -m safeil_sumo.run`` / ``sweep`` (the same seeds give the same
runs); :func:`sweep` and :func:`replay` wrap the sweep engine and the replay of many windows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from safeil_sumo import policies
from safeil_sumo.experiments.sweep import ScenarioSpec, build_scenario, run_sweep
from safeil_sumo.policy import Policy
from safeil_sumo.sim.runner import LoopConfig, Scenario, run_scenario


@dataclass(frozen=True)
class RunResult:
    """``summary``: one row per scenario; ``log``: every step of every scenario."""

    summary: pd.DataFrame
    log: pd.DataFrame


def load_policy(policy: str | Policy) -> Policy:
    """A shipped name, a checkpoint / IDM model path, or a Policy object (returned as it is)."""
    if isinstance(policy, str):
        return policies.load(policy)
    if not isinstance(policy, Policy):
        raise TypeError(f"{policy!r} is no Policy: it needs name, horizon and plan(features)")
    return policy


def scenario(net: str = "curved500", index: int = 0, seed: int = 0, **spec: object) -> Scenario:
    """Scenario ``index`` of master ``seed`` on ``net``; ``spec`` takes any
    :class:`~safeil_sumo.experiments.sweep.ScenarioSpec` field (``leader_kind="recorded"``,
    ``leader_profile="ngsim"``, ``leader_speed_range_mps=(20, 25)``, ``initial_gap_m=30``, ...)."""
    from safeil_sumo.experiments.sweep import _road

    s = ScenarioSpec(net=net, index=index, master_seed=seed, **spec)
    return build_scenario(s, _road(s.net))


def run(net: str = "curved500", policy: str | Policy = "safeil", scenarios: int = 10,
        seed: int = 0, loop: LoopConfig | None = None, **spec: object) -> RunResult:
    """Run ``scenarios`` scenarios (indices 0..n-1 of master ``seed``) closed loop in libsumo."""
    planner = load_policy(policy)
    loop = loop or LoopConfig()
    rows, logs = [], []
    for i in range(scenarios):
        sc = scenario(net, i, seed, **spec)
        rollout = run_scenario(sc, planner, loop)
        rows.append(rollout.summary)
        logs.append(rollout.log.assign(scenario=sc.name))
    return RunResult(pd.DataFrame(rows), pd.concat(logs, ignore_index=True))


def sweep(policies_: Sequence[str], out: str | Path, scenarios: int = 10, nets: Sequence[str] =
          ("curved500",), seed: int = 0, workers: int = 1, **spec: object) -> pd.DataFrame:
    """A resumable sweep (nets x policies x scenarios; ``spec``: ScenarioSpec fields) written to
    ``out``; returns its summary (one row per task). Policies are names or paths (they travel to
    worker processes)."""
    specs = [ScenarioSpec(net=n, index=i, master_seed=seed, policy=p, **spec)
             for n in nets for p in policies_ for i in range(scenarios)]
    return run_sweep(specs, out, workers=workers, progress=False)


def replay(source: str, policies_: Sequence[str], out: str | Path, maneuvers: str | list[str] =
           "all", windows: str = "sliding", workers: int = 1) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Replay every window of ``maneuvers`` of ``source`` (``openacc``, ``ngsim`` or a drive file)
    with each policy: ``(per-window table, per-policy aggregate)``, both also written to ``out``."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.experiments import replay_all as ra
    from safeil_sumo.replay import load_source

    rows, _ = process_drive(load_source(source), PipelineConfig(rate_hz=10.0))
    only = None if maneuvers == "all" else list(maneuvers)
    wins = ra.windows(rows, windows, only=only)
    records = ra.replay_all(rows, wins, list(policies_), Path(out), workers=workers,
                            progress=False)
    return ra.write(Path(out), records, {"source": source, "policies": list(policies_)},
                    title=str(source))
