"""States across the operating envelope, for the barrier where there are no demonstrations.

The barrier term needs no target trajectory, only the features. Recorded car following rarely
contains a fast approach to a much slower car, a leader braking hard or a cut-in at 10 m, so a
network trained on the recorded tuples alone is shaped by the barrier only where the data are
(and plans straight through a slow leader elsewhere). Drawing states from the whole envelope and
adding their barrier to the loss (beyond the paper) teaches the network to stay behind the leader
and inside the lane where no human showed how.

Each state: a lane (width, the ego's lateral offset and heading error, curvature) and a leader
(ego speed, leader speed relative to it, bumper gap; a share of "no leader" states as the radar
reports them: at its range, at the ego's speed). Only *recoverable* leader states are kept
(braking at ``brake_mps2`` keeps the ego behind a constant-speed leader): where a collision
cannot be avoided, no plan is safe, and the barrier would only distort the network.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo.core.features import N_FEATURES


@dataclass(frozen=True)
class EnvelopeConfig:
    """Ranges of the sampled states (uniform unless said otherwise)."""

    ego_speed_mps: tuple[float, float] = (0.0, 40.0)  # [m/s]
    relative_speed_mps: tuple[float, float] = (-15.0, 5.0)  # v_lead - v_x [m/s]
    gap_m: tuple[float, float] = (3.0, 150.0)  # bumper gap, log-uniform [m]
    no_leader_share: float = 0.1  # share of states with the radar's "no leader" [-]
    radar_range_m: float = 150.0  # "no leader": leader at this gap, at the ego's speed [m]
    lane_width_m: tuple[float, float] = (3.3, 3.8)  # [m]
    lateral_offset_m: tuple[float, float] = (-0.6, 0.6)  # ego front bumper from lane centre [m]
    heading_error: tuple[float, float] = (-0.03, 0.03)  # lane slope c1 in the ego frame [-]
    curvature_1pm: tuple[float, float] = (-1.0 / 250.0, 1.0 / 250.0)  # lane curvature [1/m]
    brake_mps2: float = 6.0  # recoverable: braking this hard avoids the leader [m/s^2]


def sample_states(n: int, rng: np.random.Generator, cfg: EnvelopeConfig = EnvelopeConfig()
                  ) -> np.ndarray:
    """``n`` recoverable envelope states as planner features ``(n, 9)``."""
    out = np.empty((0, N_FEATURES))
    while len(out) < n:
        m = 2 * (n - len(out)) + 8
        feats = _draw(m, rng, cfg)
        v, v_lead, gap = feats[:, 6], feats[:, 7], feats[:, 8]
        closing = np.maximum(v - v_lead, 0.0)
        ok = gap > closing * closing / (2.0 * cfg.brake_mps2)
        out = np.concatenate([out, feats[ok]])
    return out[:n]


def _draw(m: int, rng: np.random.Generator, cfg: EnvelopeConfig) -> np.ndarray:
    u = rng.uniform
    width = u(*cfg.lane_width_m, m)
    offset = u(*cfg.lateral_offset_m, m)
    c1 = u(*cfg.heading_error, m)
    c2 = 0.5 * u(*cfg.curvature_1pm, m)
    v = u(*cfg.ego_speed_mps, m)
    v_lead = np.clip(v + u(*cfg.relative_speed_mps, m), 0.0, None)
    gap = np.exp(u(np.log(cfg.gap_m[0]), np.log(cfg.gap_m[1]), m))
    free = u(0.0, 1.0, m) < cfg.no_leader_share
    v_lead = np.where(free, v, v_lead)
    gap = np.where(free, cfg.radar_range_m, gap)
    # lines in the ego frame: the ego sits `offset` left of the centre, so the lines move right
    c0l, c0r = 0.5 * width - offset, -0.5 * width - offset
    return np.stack([c0l, c1, c2, c0r, c1, c2, v, v_lead, gap], axis=1)
