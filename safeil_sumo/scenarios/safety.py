"""The paper's safety scenarios: a leader at a constant random speed ahead of the ego.

Each scenario's seed and leader speed derive from the master seed and the scenario index only
(``numpy.random.SeedSequence([master, index])``), so scenario i is the same whether it runs
alone, in a sweep of 10 or of 10,000, sequentially or in parallel.
"""

from __future__ import annotations

import numpy as np

from safeil_sumo.roads.road import Road
from safeil_sumo.sim.leaders import constant
from safeil_sumo.sim.loop_types import Scenario

PAPER_LEADER_SPEED_MPS = (25.0, 32.0)  # the paper: constant random speed in [25, 32] m/s


def scenario_seed(master_seed: int, index: int) -> int:
    """A 32-bit seed for scenario ``index`` of a sweep with ``master_seed``."""
    return int(np.random.SeedSequence([master_seed, index]).generate_state(1)[0])


def safety_scenario(
    road: Road,
    index: int,
    master_seed: int = 0,
    leader_speed_range: tuple[float, float] = PAPER_LEADER_SPEED_MPS,
    ego_speed_mps: float = 30.0,
    initial_gap_m: float = 50.0,
) -> Scenario:
    """Scenario ``index``: leader speed uniform in ``leader_speed_range`` [m/s]."""
    lo, hi = leader_speed_range
    if not 0 <= lo <= hi:
        raise ValueError(f"leader speed range must satisfy 0 <= low <= high, got {lo}, {hi}")
    seed = scenario_seed(master_seed, index)
    speed = float(np.random.default_rng(seed).uniform(lo, hi))
    return Scenario(
        name=f"s{index:04d}", road=road, leader=constant(speed), ego_speed_mps=ego_speed_mps,
        initial_gap_m=initial_gap_m, seed=seed,
    )
