"""The ARCH-COMP ACC benchmark with immrax, for docs/arch_comp_acc.md — NOT run by the project.

Run with a separate venv holding immrax (PyPI) and jax, never the project's:

    python3.11 -m venv /tmp/immrax-venv && /tmp/immrax-venv/bin/pip install immrax
    /tmp/immrax-venv/bin/python tools/immrax_acc.py ../shared/benchmarks/arch_comp_acc

The controller is read from the benchmark's POLAR file by the project's own reader (numpy only,
imported from this checkout) and loaded into an immrax ``NeuralNetwork`` in a temporary
directory, so both verifiers see the same weights. The analysis follows immrax's published ACC
example (examples/ARCH-AINNCS/ACC/acc.py of the immrax repository): a mixed-monotone embedding
system with CROWN bounds of the network over the current box at every vector-field evaluation,
integrated by Tsit5 with dt = 0.05 s, the property checked on the saved steps. The installed
release's ``irx.crown`` has no ``iterated`` option, so it is called without it.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import equinox as eqx
import immrax as irx
import jax
import jax.numpy as jnp

from safeil_sumo.learn.polar import read_polar

V_SET, T_GAP, D_DEFAULT, MU, A_LEAD = 30.0, 1.4, 10.0, 1e-4, -2.0


class AccPlant(irx.System):
    """The benchmark's 6-state plant, ``u`` the ego's commanded acceleration."""

    def __init__(self) -> None:
        self.evolution = "continuous"
        self.xlen = 6

    def f(self, t, x, u, w):  # immrax's signature
        _, vl, gl, _, ve, ge = x
        return jnp.array([vl, gl, -2 * gl + 2 * A_LEAD - MU * vl**2,
                          ve, ge, -2 * ge + 2 * u[0] - MU * ve**2])


def load_network(polar: Path, workdir: Path) -> irx.NeuralNetwork:
    """An immrax network with the POLAR file's weights (ReLU hidden layers, affine output)."""
    layers = read_polar(polar)
    arch = [str(layers[0].weight.shape[1])]
    for layer in layers[:-1]:
        arch += [str(layer.weight.shape[0]), "relu"]
    arch.append(str(layers[-1].weight.shape[0]))
    (workdir / "arch.txt").write_text(" ".join(arch))
    net = irx.NeuralNetwork(workdir, load=False)
    linear = [i for i, m in enumerate(net.seq) if isinstance(m, eqx.nn.Linear)]
    seq = net.seq
    for i, layer in zip(linear, layers, strict=True):
        seq = eqx.tree_at(lambda s, i=i: s[i].weight, seq, jnp.asarray(layer.weight))
        seq = eqx.tree_at(lambda s, i=i: s[i].bias, seq, jnp.asarray(layer.bias))
    return eqx.tree_at(lambda n: n.seq, net, seq)


def run(polar: Path, repeats: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        prenet = load_network(polar, Path(tmp))

    # the input as a matrix product: the release's linbp has no rule for indexing ('slice')
    in_map = jnp.array([[0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 1, 0],
                        [1, 0, 0, -1, 0, 0], [0, 1, 0, 0, -1, 0]], dtype=float)
    in_offset = jnp.array([V_SET, T_GAP, 0.0, 0.0, 0.0])

    def net(x):
        return prenet(in_map @ x + in_offset)

    net.out_len = 1
    plant = AccPlant()
    clsys = irx.NNCSystem(plant, net)
    ix0 = irx.interval([90.0, 32.0, 0.0, 10.0, 30.0, 0.0], [110.0, 32.2, 0.0, 11.0, 30.2, 0.0])
    dt, tf = 0.05, 5.0
    n_saved = round(tf / dt) + 1

    @jax.jit
    def reach(t0, dt, tf, ix0):
        verifier = irx.crown(net)
        f_ol = irx.natif(plant.f)

        class Emb(irx.EmbeddingSystem):
            def __init__(self) -> None:
                self.sys, self.xlen, self.evolution = clsys, 12, "continuous"

            def E(self, t, x):  # immrax's name
                ix = irx.ut2i(x)
                bound = verifier(ix)
                return irx.embed(lambda t, ix: f_ol(t, ix, bound(ix), irx.izeros(1)))(
                    t, irx.i2ut(ix))

        traj = Emb().compute_trajectory(t0, tf, irx.i2ut(ix0), dt=dt, solver="tsit5")
        lead = irx.interval(traj.ys[:n_saved, 0:3], traj.ys[:n_saved, 6:9])
        ego = irx.interval(traj.ys[:n_saved, 3:6], traj.ys[:n_saved, 9:12])
        margin = lead[:, 0] - ego[:, 0] - (ego[:, 1] * T_GAP + D_DEFAULT)
        return margin.lower, traj.ts[:n_saved]

    t0 = time.perf_counter()
    jax.block_until_ready(reach(0.0, dt, tf, ix0))
    print(f"jit compile {time.perf_counter() - t0:.3f} s")
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        lows, ts = jax.block_until_ready(reach(0.0, dt, tf, ix0))
        times.append(time.perf_counter() - t0)
    bad = [(float(t), float(v)) for t, v in zip(ts, lows, strict=True) if not v >= 0.0]
    low = float(lows.min())
    status = "VERIFIED" if not bad else "UNKNOWN"
    print("margin lower bound every 0.5 s:", [round(float(v), 3) for v in lows[::10]])
    if bad:
        print(f"first saved step not proven: t = {bad[0][0]:.2f} s, bound {bad[0][1]}")
    print(f"immrax {irx.__version__ if hasattr(irx, '__version__') else ''} ACC: {status}, "
          f"lower bound of the margin {low:.4f} m on the saved steps, "
          f"time {min(times):.4f} s (min of {repeats}), first {times[0]:.4f} s, "
          f"jax {jax.__version__}, x64 {jax.config.jax_enable_x64}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("benchmark_dir", type=Path)
    ap.add_argument("--repeats", type=int, default=10)
    args = ap.parse_args()
    run(args.benchmark_dir / "controller_5_20_relu.polar", args.repeats)
