"""``python -m safeil_sumo.animate RUN_DIR``: a watchable animation of one scenario of a results folder.

    python -m safeil_sumo.animate runs/curved500_safeil_seed0 --scenario s0003
    python -m safeil_sumo.animate runs/replay_x --policy safeil --out safeil.gif

The frames and the file are :mod:`safeil_sumo.experiments.animation`'s: an MP4 when an ffmpeg is
found, else a GIF. Exit codes: 0 ok, 2 bad input.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from safeil_sumo.cli_args import CommandParser, add_policy_option, interruptible, one_policy
from safeil_sumo.experiments.animation import (
    DEFAULT_DPI,
    DEFAULT_FPS,
    FIGSIZE_IN,
    AnimateError,
    animate,
)


def build_parser() -> CommandParser:
    p = CommandParser(
        "safeil_sumo.animate",
        description="Animate one scenario of a results folder of safeil_sumo.run (or one policy "
                    "of a safeil_sumo.replay folder): MP4 when an ffmpeg is found, else GIF.")
    p.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="results folder")
    p.add_argument("--scenario", default=None, help="run folders: e.g. s0003 (default: the first)")
    add_policy_option(p, None, "replay folders: the policy shown", many=False,
                      shown="the first")
    p.add_argument("--out", type=Path, default=None,
                   help="output .mp4 or .gif (default RUN_DIR/animation_<scenario>.mp4, or .gif "
                        "without an ffmpeg)")
    p.add_argument("--fps", type=float, default=DEFAULT_FPS,
                   help="video frames per second (default 10)")
    p.add_argument("--speedup", type=float, default=1.0,
                   help="simulated seconds per second of video, a factor (default 1: real time)")
    p.add_argument("--start-s", type=float, default=None, metavar="S",
                   help="first frame's time [s]")
    p.add_argument("--end-s", type=float, default=None, metavar="S",
                   help="last frame's time [s]")
    p.add_argument("--dpi", type=float, default=DEFAULT_DPI,
                   help=f"pixels per inch of the {FIGSIZE_IN[0]:g} x {FIGSIZE_IN[1]:g} in "
                        f"figure (default {DEFAULT_DPI})")
    p.rename(speed="--speedup", start="--start-s", end="--end-s")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    args.policy = one_policy(p, args, "animate each policy in turn")
    for name in ("fps", "speedup", "dpi"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            p.error(f"--{name} must be > 0")
    return args


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        path = animate(args.run_dir, args.scenario, args.policy, args.out, fps=args.fps,
                       every_s=args.speedup / args.fps, start_s=args.start_s, end_s=args.end_s,
                       dpi=args.dpi)
    except AnimateError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"animation: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
