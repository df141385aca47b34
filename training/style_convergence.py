"""A plot of the (s0, T) style estimate converging over one recorded drive.

    python training/style_convergence.py --source zalazone --maneuver "handling_part26_f4#0" \
        --out docs/style_convergence.png

Runs :func:`safeil_sumo.learn.style_estimator.estimate_drive` over the maneuver's rows (10 Hz,
the population prior) and plots s0 and T with their +-1 sd bands against time, the steady rows
shaded and the whole drive's least-squares line over its steady samples dashed
(:func:`~safeil_sumo.learn.style_estimator.plot_convergence`). Prints the estimate after 2, 10,
30 and 60 s and at the end.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def convergence(source: str, maneuver: str, out: Path) -> list[str]:
    """Write the plot of ``maneuver`` of ``source`` to ``out``; the printed lines."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source
    from safeil_sumo.learn.style_estimator import (
        estimate_drive,
        least_squares_style,
        plot_convergence,
    )

    rows = process_drive(load_source(source), PipelineConfig(rate_hz=10.0))[0]
    rows = rows[rows["maneuver_id"] == maneuver].sort_values("time")
    if rows.empty:
        raise SystemExit(f"error: no maneuver {maneuver!r} in {source}")
    t, gap, v, vl = (rows[c].to_numpy(float) for c in ("time", "lead_x", "v_x", "v_lead"))
    final, traj = estimate_drive(t, gap, v, vl)
    hindsight = least_squares_style(gap[traj.steady], v[traj.steady])
    out.parent.mkdir(parents=True, exist_ok=True)
    plot_convergence(traj, out, hindsight,
                     title=f"{source} {maneuver}: (s0, T) estimated as the drive is watched")
    lines = []
    rel = t - t[0]
    for seen in (2.0, 10.0, 30.0, 60.0, rel[-1]):
        i = int((rel <= seen).sum()) - 1
        lines.append(f"after {rel[i]:6.1f} s: s0 {traj.s0_m[i]:6.2f} ± {traj.sd_s0_m[i]:.2f} m, "
                     f"T {traj.time_gap_s[i]:.3f} ± {traj.sd_time_gap_s[i]:.3f} s "
                     f"({int(traj.steady[:i + 1].sum())} steady rows)")
    lines.append(f"whole-drive least squares: s0 {hindsight[0]:.2f} m, T {hindsight[1]:.3f} s; "
                 f"final estimate's gap at the mean speed {final.mean_speed_mps:.1f} m/s: "
                 f"{final.gap_m(final.mean_speed_mps):.1f} m")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--source", default="zalazone",
                   help="openacc, zalazone, ngsim or a drive file")
    p.add_argument("--maneuver", default="handling_part26_f4#0", help="a maneuver id")
    p.add_argument("--out", type=Path, default=Path("docs/style_convergence.png"))
    args = p.parse_args(argv)
    for line in convergence(args.source, args.maneuver, args.out):
        print(line)
    print(f"plot: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
