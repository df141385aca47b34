"""What the command lines share: their parser (:class:`CommandParser`: usage names the command
as invoked, an error is one line, a renamed option names its new name), Ctrl-C as one line
(:func:`interruptible`), argparse types (a bad number is one clear usage error, exit 2, not a
traceback or a run on NaN/inf) and the options several commands declare once.

The vocabulary: ``--policy`` chooses planners (one or more where a command compares them), a
quantity's unit is the suffix of its name (``--max-time-s``, ``--ego-speed-mps``,
``--plan-rate-hz``), a range is ``--<name>-range-<unit> LO HI``, and a switch is
``--x/--no-x``."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

if TYPE_CHECKING:
    from safeil_sumo.data.by_path import DataSpec
    from safeil_sumo.scenarios.spec import Task
    from safeil_sumo.sim.loop_types import LoopConfig

INTERRUPTED = 130  # exit code of a command ended by Ctrl-C (128 + SIGINT), as shells report it


def console_scripts(module: str) -> list[str]:
    """The console commands (``[project.scripts]``) that run ``module``'s ``main``."""
    from importlib.metadata import entry_points

    return [ep.name for ep in entry_points(group="console_scripts")
            if ep.value.split(":")[0] == module]


def command_name(module: str) -> str:
    """How the user invoked ``module``'s command line: its console command's name (``safeil-run``)
    when run as one, else ``python -m <module>``."""
    script = Path(sys.argv[0]).name.removesuffix(".exe") if sys.argv and sys.argv[0] else ""
    # a module run with -m has its file as argv[0]; only a script name is looked up
    if script and not script.endswith(".py") and script in console_scripts(module):
        return script
    return f"python -m {module}"


class CommandParser(argparse.ArgumentParser):
    """The parser of a ``safeil_sumo`` command line (``module``: e.g. ``safeil_sumo.run``).

    Usage names the command as it was invoked (:func:`command_name`). An error is one line,
    ``<prog>: error: <message>``, without the usage block (``-h`` still prints it). An option
    renamed for the shared vocabulary (:meth:`rename`) fails with one line naming its new name,
    also where argparse would take the old name as an abbreviation of the new one."""

    def __init__(self, module: str, **kwargs) -> None:
        super().__init__(prog=command_name(module), **kwargs)
        self.renamed: dict[str, str] = {}
        self.switches: set[str] = set()  # --x/--no-x switches that were --x on|off
        self.error_prefix = ""  # e.g. a TOML file's name, for the errors of its options

    def rename(self, **renamed: str) -> None:
        """Old spellings that fail naming their new name (``rename(policies="--policy")``:
        ``--policies`` -> ``--policy``; the keys with ``_`` for ``-``)."""
        self.renamed.update({"--" + old.replace("_", "-"): new for old, new in renamed.items()})

    def add_switch(self, flag: str, **kwargs) -> None:
        """``flag`` / ``--no-<flag>`` (argparse.BooleanOptionalAction); ``flag on|off``, its old
        form, fails naming them."""
        self.add_argument(flag, action=argparse.BooleanOptionalAction, **kwargs)
        self.switches.add(flag)

    def old_spelling(self, argv: Sequence[str]) -> str | None:
        """The message for the first old spelling in ``argv``, if any."""
        argv = list(argv)
        for i, token in enumerate(argv):
            if token == "--":
                break
            flag, _, value = token.partition("=")
            if flag in self.renamed:
                return f"{flag} was renamed {self.renamed[flag]}"
            if flag in self.switches:
                value = value or (argv[i + 1] if i + 1 < len(argv) else "")
                if value in ("on", "off"):
                    new = flag if value == "on" else "--no-" + flag[2:]
                    return f"{flag} on|off was replaced by {flag} / --no-{flag[2:]}: use {new}"
        return None

    # typeshed types parse_known_args as overloads on the namespace's class; this one forwards
    # whatever it is given, so it matches none of them exactly
    def parse_known_args(  # type: ignore[override]
            self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        argv = list(sys.argv[1:] if args is None else args)
        message = self.old_spelling(argv)
        if message:
            self.error(message)
        return super().parse_known_args(argv, namespace)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {self.error_prefix}{message}\n")


def interruptible(main: Callable[..., int]) -> Callable[..., int]:
    """``main`` ending on Ctrl-C with one line, ``interrupted``, and exit code 130, instead of a
    KeyboardInterrupt traceback (a command with more to say catches it itself first)."""

    @functools.wraps(main)
    def wrapper(argv: list[str] | None = None) -> int:
        try:
            return main(argv)
        except KeyboardInterrupt:
            if sys.stderr.isatty():  # end a progress bar's line first
                print(file=sys.stderr)
            print("interrupted", file=sys.stderr)
            return INTERRUPTED

    return wrapper


def add_policy_option(parser: CommandParser, default: Sequence[str] | None, what: str,
                      many: bool = True, shown: str = "the shipped model") -> None:
    """``--policy NAME [NAME ...]``: the planners a command runs (``what``: the names it takes,
    for the help; ``shown``: what a None ``default`` means). ``many=False``: the command runs
    one (:func:`one_policy` checks it)."""
    shown = shown if default is None else " ".join(default)
    parser.add_argument(
        "--policy", nargs="+", default=None if default is None else list(default),
        metavar="POLICY",
        help=f"{what} ({'one or more' if many else 'one'}; default {shown})")
    parser.rename(policies="--policy")


def one_policy(parser: CommandParser, args: argparse.Namespace, hint: str) -> str | None:
    """The one ``--policy`` of a command that runs one planner (None: not given); several are a
    usage error (``hint``: where to compare several)."""
    if args.policy is None:
        return None
    if len(args.policy) > 1:
        parser.error(f"--policy takes one planner here, got {len(args.policy)}; {hint}")
    return args.policy[0]


def finite_float(text: str) -> float:
    """A float that is not NaN or ±inf."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def _int_at_least(text: str, low: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
    return value


def positive_int(text: str) -> int:
    """An int >= 1 (worker processes, batch sizes)."""
    return _int_at_least(text, 1)


def nonnegative_int(text: str) -> int:
    """An int >= 0 (seeds, counts)."""
    return _int_at_least(text, 0)


def add_time_gap_option(parser: CommandParser, planners: str = "the planner's") -> None:
    """``--time-gap-s`` and ``--standstill-m``, shared by ``run``, ``sweep`` and ``replay``:
    the planner's style, the steady gap's line ``s0 + T v``."""
    parser.rename(time_gap="--time-gap-s", standstill="--standstill-m")
    parser.add_argument(
        "--time-gap-s", type=finite_float, default=None, metavar="S",
        help=f"{planners} preferred time gap T [s], like an ACC's distance setting: the style "
             "input of a style-conditioned checkpoint (default: the humans' median stored in "
             "it), or the IDM's T; other planners refuse it")
    parser.add_argument(
        "--standstill-m", type=finite_float, default=None, metavar="M",
        help=f"with --time-gap-s: {planners} standstill distance s0 [m], so the steady gap is "
             "s0 + T v (a checkpoint's setting follows the speed, the IDM's s0 is set; "
             "default: none)")


def check_style_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--standstill-m`` needs ``--time-gap-s``: a usage error otherwise."""
    if args.standstill_m is not None and args.time_gap_s is None:
        parser.error("--standstill-m needs --time-gap-s (the style is the line s0 + T v)")


def add_brake_guard_option(parser: CommandParser) -> None:
    """``--brake-guard/--no-brake-guard``, shared by ``run``, ``sweep`` and ``replay``."""
    parser.add_switch(
        "--brake-guard", default=True,
        help="collision-avoidance braking under the planner: brakes harder than the plan when "
             "keeping 2 m behind a leader that keeps braking to a stop needs >= 3 m/s^2 "
             "(default on; --no-brake-guard: the planner and tracker alone, the paper's loop; "
             "docs/brake_guard.md)")


def add_plan_rate_option(parser: CommandParser) -> None:
    """``--plan-rate-hz``, shared by ``run``, ``sweep`` and ``replay``."""
    from safeil_sumo.sim.loop_types import LoopConfig

    default = LoopConfig.plan_rate_hz
    parser.add_argument("--plan-rate-hz", type=finite_float, default=default, metavar="HZ",
                        help=f"re-planning rate [Hz] (default {default:g})")
    parser.rename(plan_rate="--plan-rate-hz")


def add_scheduler_option(parser: CommandParser) -> None:
    """``--scheduler``, shared by ``sweep`` and ``replay`` (their tasks on a Dask cluster); check
    it with :func:`check_scheduler`."""
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="Dask scheduler address (tcp://host:port) to run the tasks on")


def check_scheduler(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """A usage error for ``--scheduler`` beside ``--workers`` > 1, or not an address."""
    if args.scheduler is not None and args.workers != 1:
        parser.error("use either --workers (local processes) or --scheduler (a Dask cluster)")
    if args.scheduler is not None and "://" not in args.scheduler:
        parser.error(f"--scheduler needs an address like tcp://host:8786, got {args.scheduler!r}")


def add_task_options(parser: CommandParser) -> None:
    """``--task-timeout-s`` and ``--retry-failed``, shared by ``sweep`` and ``replay`` (the task
    engine's); check them with :func:`check_task_options`."""
    parser.add_argument("--task-timeout-s", type=finite_float, default=None, metavar="S",
                        help="local workers: kill a task after this many seconds [s]")
    parser.rename(task_timeout="--task-timeout-s")
    parser.add_argument("--retry-failed", action="store_true",
                        help="rerun tasks that failed before")


def check_task_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """A usage error for a ``--task-timeout-s`` that is not > 0."""
    if args.task_timeout_s is not None and args.task_timeout_s <= 0:
        parser.error("--task-timeout-s must be > 0")


def _flag(f: dataclasses.Field) -> str:
    return f.metadata.get("flag") or "--" + f.name.replace("_", "-")


def _dest(f: dataclasses.Field) -> str:
    return _flag(f)[2:].replace("-", "_")


def _shown(default: Any) -> str:
    """A default as the help shows it: ``25 32`` for a pair, nothing for None or ``""``."""
    if default in (None, "", ()):
        return ""
    if isinstance(default, tuple):
        return " (default " + " ".join(f"{v:g}" for v in default) + ")"
    return f" (default {default:g})" if isinstance(default, float) else f" (default {default})"


def _scenario_option_fields() -> list[dataclasses.Field]:
    """The :class:`~safeil_sumo.scenarios.spec.ScenarioSpec` fields that are options: every
    field with a help (not the net, which each command takes its way, nor the index)."""
    from safeil_sumo.scenarios.spec import ScenarioSpec

    return [f for f in dataclasses.fields(ScenarioSpec) if "help" in f.metadata]


def _add_field_option(parser: CommandParser, f: dataclasses.Field) -> None:
    """One option of a ScenarioSpec field: its flag, help and default from the field, its type
    from the field's annotation."""
    kw: dict[str, Any] = {"dest": _dest(f), "default": f.default, "choices":
                          f.metadata.get("choices"), "metavar": f.metadata.get("metavar")}
    kw["help"] = f.metadata["help"] + _shown(f.default)
    if f.type == "int":
        kw["type"] = nonnegative_int
    elif f.type == "tuple[float, float]":
        kw.update(type=finite_float, nargs=2)
    elif f.type == "tuple[str, ...]":
        kw.update(nargs="+", default=[])
    elif "float" in str(f.type):
        kw["type"] = finite_float
        kw["metavar"] = kw["metavar"] or _dest(f).rpartition("_")[2].upper()
    elif f.default == "":
        kw["default"] = None  # not given: the field's "" (checked with the net: lane_for_net)
    parser.add_argument(_flag(f), **kw)


def add_scenario_options(parser: CommandParser) -> None:
    """The scenario options of ``run`` and ``sweep``: how many scenarios, then one option per
    :class:`~safeil_sumo.scenarios.spec.ScenarioSpec` field (:func:`_scenario_option_fields`:
    the flag, help and default are the field's, so each default is written once), the
    planner's time gap and the loop's settings (their defaults :class:`PlannerRef`'s and
    :class:`LoopConfig`'s). The dataclasses' ``__post_init__`` hold the rules
    (:func:`check_scenario_options` reports them as usage errors)."""
    from safeil_sumo.sim.loop_types import LoopConfig

    p = parser
    p.add_argument("--scenarios", type=int, default=10,
                   help="scenarios (per net and policy in a sweep) (default 10)")
    for f in _scenario_option_fields():
        if f.name == "initial_gap_m":  # a fixed gap or a range: two exclusive options
            gap = p.add_mutually_exclusive_group()
            _add_field_option(gap, f)  # type: ignore[arg-type]
            gap.add_argument("--gap-range-m", type=finite_float, nargs=2, default=None,
                             metavar=("LOW", "HIGH"), help="initial gap drawn per scenario [m]")
        else:
            _add_field_option(p, f)
    add_time_gap_option(p)
    add_plan_rate_option(p)
    p.add_argument("--stop-on-flag", action="store_true", default=LoopConfig.stop_on_flag,
                   help="end a scenario at its first flag")
    p.rename(leader_speed="--leader-speed-range-mps", brake_time="--brake-time-s",
             brake_decel="--brake-decel-mps2", brake_to="--brake-to-mps",
             ego_speed="--ego-speed-mps", gap="--gap-m", gap_range="--gap-range-m",
             lane_noise="--lane-noise-m", radar_noise="--radar-noise-m",
             max_time="--max-time-s")
    add_brake_guard_option(p)


def scenario_fields(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`~safeil_sumo.scenarios.spec.ScenarioSpec` fields of
    :func:`add_scenario_options`' options (all but the net and the scenario index)."""
    out = {}
    for f in _scenario_option_fields():
        value = getattr(args, _dest(f))
        if f.type.startswith("tuple"):
            value = tuple(value)
        elif f.default == "" and value in (None, "none"):  # not given, or --traffic none
            value = ""
        out[f.name] = value
    if args.gap_range_m:
        out["initial_gap_m"] = tuple(args.gap_range_m)
    return out


def loop_config(args: argparse.Namespace, **how: Any) -> LoopConfig:
    """The :class:`LoopConfig` of :func:`add_scenario_options`' loop options; ``how``: the
    command's own loop settings (a backend, sumo-gui)."""
    from safeil_sumo.sim.brake_guard import when as brake_guard_when
    from safeil_sumo.sim.loop_types import LoopConfig

    return LoopConfig(plan_rate_hz=args.plan_rate_hz, stop_on_flag=args.stop_on_flag,
                      brake_guard=brake_guard_when(args.brake_guard), **how)


def task(args: argparse.Namespace, net: str, index: int, policy: str,
         safety_filter: bool = False) -> Task:
    """The :class:`~safeil_sumo.scenarios.spec.Task` of scenario ``index`` on ``net`` driven
    by ``policy``, with the scenario options of ``args``."""
    from safeil_sumo.planners.registry import PlannerRef
    from safeil_sumo.scenarios.spec import ScenarioSpec, Task

    return Task(ScenarioSpec(net=net, index=index, **scenario_fields(args)),
                PlannerRef(policy, safety_filter, args.time_gap_s, args.standstill_m),
                loop_config(args))


def check_scenario_options(parser: argparse.ArgumentParser, args: argparse.Namespace,
                           nets: list[str]) -> None:
    """The scenario options' rules, as usage errors: the task's, on each of ``nets``."""
    if args.scenarios < 1:
        parser.error("--scenarios must be >= 1")
    try:
        for net in nets:
            task(args, net, 0, "analytic")
    except ValueError as exc:
        parser.error(str(exc))


def int_list(text: str) -> tuple[int, ...]:
    """Comma-separated integers, e.g. layer widths ``64,64``."""
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not comma-separated integers: {text!r}") from None


def add_dataclass_options(parser: argparse.ArgumentParser, cls: type, *,
                          helps: dict[str, str] | None = None,
                          aliases: dict[str, tuple[str, ...]] | None = None,
                          choices: dict[str, tuple] | None = None,
                          names: dict[str, str] | None = None) -> None:
    """One option per field of the dataclass ``cls``, named after it (``max_epochs`` ->
    ``--max-epochs``, or ``names[name]``, which renames the field's own spelling (on a
    :class:`CommandParser`), plus any ``aliases``), defaulting to the field's default and typed
    by it:
    a float is finite, a bool is ``--x/--no-x``, a tuple of ints is comma-separated, another
    tuple takes several values. Values are checked by ``cls.__post_init__`` when the instance is
    built (:func:`dataclass_from_args`), so each rule lives in one place. Each option's help is
    ``helps[name]``, else the field's ``help`` metadata, else its name."""
    defaults = cls()
    names, choices = names or {}, choices or {}
    for f in dataclasses.fields(cls):
        default = getattr(defaults, f.name)
        flag = "--" + f.name.replace("_", "-")
        if f.name in names:
            if isinstance(parser, CommandParser):
                parser.rename(**{f.name: names[f.name]})
            flag = names[f.name]
        flags = [flag, *(aliases or {}).get(f.name, ())]
        text = (helps or {}).get(f.name, f.metadata.get("help", f.name))
        kw: dict = {"dest": f.name, "default": default, "help": f"{text} (default {default!r})"}
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
        if f.name in choices:
            kw["choices"] = choices[f.name]
        parser.add_argument(*flags, **kw)


def config_or_usage_error(parser: argparse.ArgumentParser, cls: type, args: argparse.Namespace):
    """:func:`dataclass_from_args`, its config's own check failing as a usage error (exit 2 with
    the message), as a bad option value would."""
    try:
        return dataclass_from_args(cls, args)
    except ValueError as exc:
        parser.error(str(exc))


def dataclass_from_args(cls: type, args: argparse.Namespace):
    """``cls`` built from the options :func:`add_dataclass_options` added (``ValueError`` from
    its checks)."""
    return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls)})


def add_data_options(parser: CommandParser, what: str) -> None:
    """``--data FORMAT:PATH ...`` (``what`` the data is for) and :func:`add_csv_options`;
    :func:`data_specs` parses them."""
    from safeil_sumo.data.by_path import FORMAT_HELP

    parser.add_argument("--data", nargs="+", default=None, metavar="FORMAT:PATH",
                        help=f"{what}: {FORMAT_HELP}")
    add_csv_options(parser)


def add_csv_options(parser: CommandParser) -> None:
    """``--map`` and ``--speed-unit``: how ``csv:`` data reads (docs/your_own_drives.md)."""
    from safeil_sumo.data.car_following_csv import SPEED_UNITS

    parser.add_argument("--map", default="", metavar="ROLE=COLUMN,...",
                        help="csv data: the file's column of each role (time, v, gap, lead_v, "
                             "id, driver), e.g. time=t,v=follower_speed (default: columns "
                             "named as the roles)")
    parser.add_argument("--speed-unit", choices=tuple(SPEED_UNITS), default="m/s",
                        help="csv data: the unit of its speed columns (default m/s)")


def data_specs(parser: CommandParser, args: argparse.Namespace) -> list[DataSpec] | None:
    """The :class:`~safeil_sumo.data.by_path.DataSpec` of each ``--data`` (None without it);
    a usage error in one line for a bad spec, or ``--map`` / ``--speed-unit`` without csv."""
    from safeil_sumo.data.by_path import DataError, missing_paths, parse_data_option

    try:
        specs = [parse_data_option(d, args.map, args.speed_unit) for d in args.data or ()]
    except DataError as exc:
        parser.error(str(exc))
    for spec in specs:  # before any work: a missing path is the user's typo
        missing = missing_paths(spec)
        if missing:
            parser.error(f"--data {spec.label()}: {missing[0]} does not exist")
    if (args.map or args.speed_unit != "m/s") and not any(s.format == "csv" for s in specs):
        parser.error("--map and --speed-unit read csv data: give --data csv:FILE")
    return specs if args.data is not None else None
