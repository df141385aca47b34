"""The ARCH-COMP AINNCS benchmark "ACC" proven with the project's own verifier.

``python -m safeil_sumo.learn.arch_acc BENCHMARK_DIR`` reads the benchmark's ReLU controller
(:mod:`polar`), builds the closed loop of its README (6 states, friction ``u v^2``, a lead car
braking at 2 m/s^2, control period 0.1 s) and proves with :mod:`reach` (CROWN bounds of
:mod:`bounds`, exact linear flow, drag remainder, continuous time) that
``x_lead - x_ego >= D_default + T_gap v_ego`` at every time of the 5 s horizon, from every state
of the initial box. The benchmark's files are read where they lie, never copied.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from safeil_sumo.learn.bounds import Layer
from safeil_sumo.learn.polar import read_polar
from safeil_sumo.learn.reach import Loop, Plant, Verdict, prove, simulate

CONTROLLER_FILE = "controller_5_20_relu.polar"
MU = 1e-4  # friction coefficient [1/m]
A_LEAD = -2.0  # the lead car's commanded acceleration [m/s^2]
V_SET, T_GAP, D_DEFAULT = 30.0, 1.4, 10.0  # [m/s], [s], [m]
PERIOD, PERIODS = 0.1, 50  # [s], control periods of the 5 s horizon
# state (x_lead, v_lead, g_lead, x_ego, v_ego, g_ego) [m, m/s, m/s^2]
INITIAL_LO = np.array([90.0, 32.0, 0.0, 10.0, 30.0, 0.0])
INITIAL_HI = np.array([110.0, 32.2, 0.0, 11.0, 30.2, 0.0])


def acc_plant(mu: float = MU, a_lead: float = A_LEAD) -> Plant:
    """Both cars ``x' = v, v' = g, g' = -2 g + 2 a - mu v^2``; the ego's ``a`` is the input."""
    a = np.zeros((6, 6))
    for car in (0, 3):
        a[car, car + 1] = a[car + 1, car + 2] = 1.0
        a[car + 2, car + 2] = -2.0
    b = np.zeros((6, 1))
    b[5, 0] = 2.0
    c = np.zeros(6)
    c[2] = 2.0 * a_lead
    e = np.zeros((6, 2))
    e[2, 0] = e[5, 1] = 1.0
    return Plant(a, b, c, e, np.array([1, 4]), np.array([mu, mu]))


def acc_loop(layers: list[Layer], d_default: float = D_DEFAULT, substeps: int = 10) -> Loop:
    """The closed loop: network input ``(v_set, T_gap, v_ego, x_lead - x_ego, v_lead - v_ego)``,
    property ``x_lead - x_ego - T_gap v_ego - d_default >= 0``."""
    in_map = np.zeros((5, 6))
    in_map[2, 4] = 1.0
    in_map[3, 0], in_map[3, 3] = 1.0, -1.0
    in_map[4, 1], in_map[4, 4] = 1.0, -1.0
    in_offset = np.array([V_SET, T_GAP, 0.0, 0.0, 0.0])
    prop = np.array([[1.0, 0.0, 0.0, -1.0, -T_GAP, 0.0]])
    return Loop(acc_plant(), layers, in_map, in_offset, PERIOD, prop, np.array([-d_default]),
                substeps)


def simulated_margin(loop: Loop, n: int = 200, seed: int = 0, steps: int = 100) -> float:
    """The smallest property value over ``n`` seeded random initial states and the initial
    box's 16 corners of its non-degenerate coordinates, RK4 at ``PERIOD / steps``."""
    rng = np.random.default_rng(seed)
    x0 = INITIAL_LO + (INITIAL_HI - INITIAL_LO) * rng.random((n, 6))
    bits = (np.arange(16)[:, None] >> np.arange(4)) & 1
    corners = np.tile(INITIAL_LO, (16, 1))
    corners[:, [0, 1, 3, 4]] += bits * (INITIAL_HI - INITIAL_LO)[[0, 1, 3, 4]]
    return float(simulate(loop, np.concatenate([x0, corners]), PERIODS, steps)[0].min())


def verify(layers: list[Layer], d_default: float = D_DEFAULT, periods: int = PERIODS,
           max_sets: int = 4096) -> Verdict:
    """:func:`reach.prove` of the benchmark's property over ``periods`` from the initial box."""
    loop = acc_loop(layers, d_default)
    return prove(loop, INITIAL_LO, INITIAL_HI, periods, max_sets=max_sets)


def main(argv: list[str] | None = None) -> int:
    """Command line: the verdict, wall time, sets, and the minimal margins."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("benchmark_dir", type=Path)
    ap.add_argument("--d-default", type=float, default=D_DEFAULT)
    ap.add_argument("--max-sets", type=int, default=4096)
    args = ap.parse_args(argv)
    layers = read_polar(args.benchmark_dir / CONTROLLER_FILE)
    t0 = time.perf_counter()
    verdict = verify(layers, args.d_default, max_sets=args.max_sets)
    seconds = time.perf_counter() - t0
    sim = simulated_margin(acc_loop(layers, args.d_default))
    print(f"ACC, D_default {args.d_default:g} m, 5 s continuous: {verdict.status.upper()}")
    print(f"time {seconds:.2f} s; sets analysed {verdict.sets}, proven leaves {verdict.proven}")
    print(f"minimal margin: bound {verdict.min_lower:.4f} m, simulation {sim:.4f} m "
          "(216 trajectories, RK4 at 1 ms)")
    return 0 if verdict.status == "verified" else 1


if __name__ == "__main__":
    raise SystemExit(main())
