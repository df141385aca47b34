"""argparse types shared by the CLIs: a bad number is one clear usage error (exit 2), not a
traceback or a run on NaN/inf."""

from __future__ import annotations

import argparse
import dataclasses
import math

# checked by the scenario layer, re-exported for the CLIs
from safeil_sumo.scenarios.spec import N74_LANES, lane_for_net  # noqa: F401


def finite_float(text: str) -> float:
    """A float that is not NaN or ±inf."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def nonnegative_int(text: str) -> int:
    """An int >= 0 (seeds, counts)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def add_leader_options(parser: argparse.ArgumentParser, kinds: tuple[str, ...],
                       change: str) -> None:
    """``--leader`` and ``--leader-profile``, shared by ``run`` and ``sweep``; ``change`` says
    how a braking/accelerating leader changes its speed in that command."""
    parser.add_argument(
        "--leader", choices=kinds, default="constant",
        help=f"constant speed (the paper); braking or accelerating ({change}); or recorded (a "
             "human leader's speed profile, the ego starting as the recorded follower did, or "
             "behind a profile file at the leader's speed) (default constant)")
    parser.add_argument(
        "--leader-profile", default=None,
        help="with --leader recorded: ngsim (default) or openacc (from ../shared/data), or a "
             "CSV/Parquet file with columns time [s] and speed [m/s], or a folder of them")


def add_ego_speed_option(parser: argparse.ArgumentParser) -> None:
    """``--ego-speed``, shared by ``run`` and ``sweep``: default None, resolved per scenario by
    :class:`safeil_sumo.scenarios.spec.ScenarioSpec` (30 m/s, or a recorded leader's start)."""
    parser.add_argument(
        "--ego-speed", type=finite_float, default=None, metavar="MPS",
        help="ego initial speed [m/s] (default 30; with --leader recorded: as the recorded "
             "follower started (ngsim, openacc), or the profile's speed where the scenario "
             "starts in it (a file); a speed given here wins)")


def add_time_gap_option(parser: argparse.ArgumentParser) -> None:
    """``--time-gap``, shared by ``run`` and ``sweep``: the planner's preferred time gap."""
    parser.add_argument(
        "--time-gap", type=finite_float, default=None, metavar="S",
        help="the planner's preferred time gap [s], like an ACC's distance setting: the style "
             "input of a style-conditioned checkpoint (default: the humans' median stored in "
             "it), or the IDM's T; other planners refuse it")


BRAKE_GUARD_OPTIONS = {"on": True, "off": False}


def add_brake_guard_option(parser: argparse.ArgumentParser) -> None:
    """``--brake-guard on|off``, shared by ``run``, ``sweep`` and ``replay``."""
    parser.add_argument(
        "--brake-guard", choices=tuple(BRAKE_GUARD_OPTIONS), default="on",
        help="collision-avoidance braking under the planner: brakes harder than the plan when "
             "keeping 2 m behind a leader that keeps braking to a stop needs >= 3 m/s^2 "
             "(default on; off: the planner and tracker alone, the paper's loop; "
             "docs/brake_guard.md)")


def add_route_option(parser: argparse.ArgumentParser) -> None:
    """``--route EDGE [EDGE ...]``, shared by ``run`` and ``sweep``."""
    parser.add_argument(
        "--route", nargs="+", default=[], metavar="EDGE",
        help="SUMO edges the ego drives, in driving order, on a multi-edge .net.xml (its lane is "
             "followed across the junctions; the route must end where that lane ends); "
             "default: the net's one edge")


def add_n74_options(parser: argparse.ArgumentParser) -> None:
    """``--from-km/--to-km/--traffic`` for ``--net n74``, shared by ``run`` and ``sweep``."""
    from safeil_sumo.sim.traffic import DENSITIES

    parser.add_argument("--from-km", type=finite_float, default=None, metavar="KM",
                        help="with --net n74: start of the stretch driven, kilometre post of "
                             "direction A (default 0)")
    parser.add_argument("--to-km", type=finite_float, default=None, metavar="KM",
                        help="with --net n74: end of the stretch (default 29.2, the whole "
                             "carriageway)")
    parser.add_argument("--traffic", choices=("none", *DENSITIES), default="none",
                        help="with --net n74: SUMO's own traffic from "
                             "sumo_scenarios/n74/n74.rou.xml (main road + on-ramps), flows "
                             "scaled x0.5 light, x1 default, x2 dense, seeded by the scenario "
                             "seed; the ego's leader is whichever vehicle is ahead in its lane "
                             "(no scripted leader). Default none")




def add_lane_option(parser: argparse.ArgumentParser) -> None:
    """``--lane``, shared by ``run`` and ``sweep``; check it with :func:`lane_for_net`."""
    parser.add_argument(
        "--lane", default=None, metavar="LANE",
        help="the ego's lane: with --net n74 the main lane, right (default) or left; with a "
             ".net.xml path the SUMO lane index (0 = rightmost) on the first edge of --route "
             "(or of the net's one edge); default: the middle lane")


def int_list(text: str) -> tuple[int, ...]:
    """Comma-separated integers, e.g. layer widths ``64,64``."""
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not comma-separated integers: {text!r}") from None


def add_dataclass_options(parser: argparse.ArgumentParser, cls: type, *,
                          helps: dict[str, str] | None = None,
                          aliases: dict[str, tuple[str, ...]] | None = None,
                          choices: dict[str, tuple] | None = None) -> None:
    """One option per field of the dataclass ``cls``, named after it (``max_epochs`` ->
    ``--max-epochs``, plus any ``aliases``), defaulting to the field's default and typed by it:
    a float is finite, a bool is ``--x/--no-x``, a tuple of ints is comma-separated, another
    tuple takes several values. Values are checked by ``cls.__post_init__`` when the instance is
    built (:func:`dataclass_from_args`), so each rule lives in one place."""
    defaults = cls()
    for f in dataclasses.fields(cls):
        default = getattr(defaults, f.name)
        flags = ["--" + f.name.replace("_", "-"), *(aliases or {}).get(f.name, ())]
        kw: dict = {"dest": f.name, "default": default,
                    "help": f"{(helps or {}).get(f.name, f.name)} (default {default!r})"}
        if isinstance(default, bool):
            kw["action"] = argparse.BooleanOptionalAction
        elif isinstance(default, float):
            kw["type"] = finite_float
        elif isinstance(default, int):
            kw["type"] = int
        elif isinstance(default, tuple):
            if "int" in str(f.type):
                kw["type"] = int_list
            else:
                kw["nargs"] = "*"
        if f.name in (choices or {}):
            kw["choices"] = choices[f.name]
        parser.add_argument(*flags, **kw)


def dataclass_from_args(cls: type, args: argparse.Namespace):
    """``cls`` built from the options :func:`add_dataclass_options` added (``ValueError`` from
    its checks)."""
    return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls)})
