"""The command lines as a new user meets them (issue 39, "The command lines, tried as a new
user would"): one vocabulary across every command, usage naming the command as invoked,
one-line errors, TOML errors naming the file and key, and Ctrl-C as one line and exit 130."""

from __future__ import annotations

import argparse
import importlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from safeil_sumo import cli_args

REPO = Path(__file__).resolve().parents[1]
COMMANDS = ("run", "sweep", "replay", "probe", "gap_probe", "certify", "falsify", "results",
            "bench", "animate", "evaluate", "train")
# where a quantity has a unit, the option's name ends in it
UNIT_SUFFIXES = {"s": "-s", "m/s": "-mps", "m": "-m", "Hz": "-hz", "m/s^2": "-mps2", "km": "-km"}
# words naming a time, speed, distance or rate: such an option carries a unit suffix
QUANTITY_WORDS = ("time", "speed", "gap", "duration", "stride", "timeout", "rate", "decel",
                  "noise", "start", "end", "budget", "distance", "length", "horizon")
# options with such a word and no unit, each for a reason
UNITLESS = {
    "--speedup": "animate: a playback factor (simulated seconds per video second), no unit",
    "--budget-sims": "falsify, evaluate: counted in simulations",
    "--speed-unit": "train, evaluate, replay: names the unit a CSV's speeds are in (m/s, km/h)",
}


NUMBERS = (float, int, cli_args.finite_float, cli_args.nonnegative_int)


def parser_of(command: str) -> cli_args.CommandParser:
    return importlib.import_module(f"safeil_sumo.{command}").build_parser()


def long_options(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.Action]]:
    return [(s, a) for a in parser._actions for s in a.option_strings if s.startswith("--")]


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch) -> None:
    """A command that runs after all writes its default runs/ folder here, not into the repo."""
    monkeypatch.chdir(tmp_path)


def run_main(command: str, argv: list[str]) -> int:
    """A command's ``main`` in-process; argparse's SystemExit becomes its code."""
    try:
        return importlib.import_module(f"safeil_sumo.{command}").main(argv)
    except SystemExit as exc:
        return int(exc.code)


# ------------------------------------------------------------------------- the vocabulary


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_follows_the_vocabulary(command: str) -> None:
    """A number's unit in its help (``[s]``) is its name's suffix; a name with a quantity word has a unit
    suffix (or a reason); planners are chosen with ``--policy``; no switch is ``on|off``."""
    parser = parser_of(command)
    assert isinstance(parser, cli_args.CommandParser)
    for flag, action in long_options(parser):
        assert flag != "--policies", f"{command}: planners are chosen with --policy"
        # (sweep's --safety-filter off|on|both is a grid axis of three values, not a switch)
        assert not (action.choices and set(action.choices) <= {"on", "off"}), (
            f"{command} {flag}: a switch is --x/--no-x, not on|off")
        if flag.startswith("--no-") or flag == "--help":
            continue
        unit = re.search(r"\[(s|m/s|m|Hz|m/s\^2|km)\]", action.help or "")
        if unit and action.type in NUMBERS:  # a number whose help names its unit
            assert flag.endswith(UNIT_SUFFIXES[unit.group(1)]), (
                f"{command} {flag}: its unit [{unit.group(1)}] is not its suffix")
        words = flag[2:].split("-")
        if any(w in QUANTITY_WORDS for w in words) and flag not in UNITLESS:
            assert words[-1] in {s[1:] for s in UNIT_SUFFIXES.values()}, (
                f"{command} {flag}: a time, speed, distance or rate needs its unit suffix")


@pytest.mark.parametrize("command", ["run", "sweep", "replay", "probe", "gap_probe", "certify",
                                     "falsify", "bench", "animate"])
def test_planners_are_chosen_with_policy_one_or_more(command: str) -> None:
    actions = dict(long_options(parser_of(command)))
    assert actions["--policy"].nargs == "+"


def test_a_range_and_a_setting_have_different_names() -> None:
    run, certify = dict(long_options(parser_of("run"))), dict(long_options(parser_of("certify")))
    assert run["--time-gap-s"].nargs is None  # one setting
    assert certify["--time-gap-range-s"].nargs == 2  # LO HI
    assert certify["--time-gap-s"].nargs is None  # certify --closed-loop's one setting
    assert "--time-gap-range-s" not in run


@pytest.mark.parametrize("command, argv, new", [
    ("sweep", ["--policies", "idm"], "--policy"),
    ("replay", ["--policies=idm"], "--policy"),
    ("probe", ["--policies", "idm"], "--policy"),
    ("gap_probe", ["--policies", "idm"], "--policy"),
    # --max-time would otherwise be taken as an abbreviation of --max-time-s
    ("run", ["--max-time", "3"], "--max-time-s"),
    ("sweep", ["--max-time", "3"], "--max-time-s"),
    ("run", ["--leader-speed", "20", "25"], "--leader-speed-range-mps"),
    ("sweep", ["--gap", "40"], "--gap-m"),
    ("sweep", ["--task-timeout", "9"], "--task-timeout-s"),
    ("replay", ["--time-gap", "1.2"], "--time-gap-s"),
    ("replay", ["--duration", "5"], "--duration-s"),
    ("certify", ["--time-gap", "1", "2"], "--time-gap-range-s"),
    ("falsify", ["--budget", "10"], "--budget-sims"),
    ("gap_probe", ["--speeds", "20"], "--speeds-mps"),
    ("animate", ["runs/x", "--speed", "2"], "--speedup"),
])
def test_an_old_spelling_fails_with_one_line_naming_the_new(command, argv, new, capsys) -> None:
    assert run_main(command, argv) == 2
    err = capsys.readouterr().err
    old = argv[0].split("=")[0] if argv[0].startswith("--") else argv[1]
    assert err == f"python -m safeil_sumo.{command}: error: {old} was renamed {new}\n"


@pytest.mark.parametrize("command", ["run", "sweep", "replay"])
@pytest.mark.parametrize("value, new", [("off", "--no-brake-guard"), ("on", "--brake-guard")])
def test_brake_guard_on_off_names_the_switch(command, value, new, capsys) -> None:
    assert run_main(command, ["--brake-guard", value]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"use {new}" in err and "--no-brake-guard" in err


def test_brake_guard_switch_sets_the_loop() -> None:
    from safeil_sumo.run import parse_args

    assert cli_args.loop_config(parse_args([])).brake_guard is not None
    assert cli_args.loop_config(parse_args(["--no-brake-guard"])).brake_guard is None


def test_one_planner_commands_refuse_several_in_one_line(capsys) -> None:
    assert run_main("run", ["--policy", "idm", "analytic"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--policy takes one planner here, got 2" in err


# ------------------------------------------------------------------ program name and errors


def _first_line(cmd: list[str]) -> str:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()[0]


def test_usage_names_the_command_as_invoked() -> None:
    """As a console script, usage names it; as ``python -m``, the module."""
    script = Path(sys.executable).parent / "safeil-run"
    if not script.is_file():
        pytest.skip("the console scripts are not installed (pip install -e .)")
    assert _first_line([str(script), "--help"]).startswith("usage: safeil-run [-h]")
    assert _first_line([sys.executable, "-m", "safeil_sumo.run", "--help"]).startswith(
        "usage: python -m safeil_sumo.run [-h]")


def test_command_name_of_a_console_script(monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["/somewhere/bin/safeil-gap-probe"])
    assert cli_args.command_name("safeil_sumo.gap_probe") == "safeil-gap-probe"
    monkeypatch.setattr(sys, "argv", [str(REPO / "safeil_sumo" / "gap_probe.py")])
    assert cli_args.command_name("safeil_sumo.gap_probe") == "python -m safeil_sumo.gap_probe"


@pytest.mark.parametrize("command, argv, message", [
    ("run", ["--scenarios", "0"], "--scenarios must be >= 1"),
    ("run", ["--plan-rate-hz", "200"], "plan rate must be in (0, 100] Hz"),
    ("run", ["--ego-speed-mps", "nan"], "argument --ego-speed-mps: must be a finite number"),
    # positive_int: one type for every count of workers or batch size, one message
    ("sweep", ["--workers", "0"], "argument --workers: must be >= 1, got 0"),
    ("sweep", ["--batch", "0"], "argument --batch: must be >= 1, got 0"),
    ("replay", ["--workers", "0"], "argument --workers: must be >= 1, got 0"),
    ("replay", ["--batch", "-3"], "argument --batch: must be >= 1, got -3"),
    ("replay", ["--stride-s", "0"], "--stride-s must be > 0 s"),
    ("sweep", ["--bogus"], "unrecognized arguments: --bogus"),
    ("replay", ["--rate-hz", "0"], "--rate-hz and --plan-rate-hz must be in (0, 100] Hz"),
    ("gap_probe", ["--workers", "0"], "argument --workers: must be >= 1, got 0"),
    ("gap_probe", ["--workers", "two"], "argument --workers: not an integer: 'two'"),
    ("falsify", ["--budget-sims", "0"], "budget and batch must be >= 1"),
    ("animate", ["runs/x", "--fps", "0"], "--fps must be > 0"),
    ("results", ["--workers", "0"], "argument --workers: must be >= 1, got 0"),
    ("results", ["--grid", "0"], "argument --grid: must be >= 1, got 0"),
    ("evaluate", ["idm", "--workers", "0"], "argument --workers: must be >= 1, got 0"),
])
def test_a_validation_error_is_one_line_without_usage(command, argv, message, capsys) -> None:
    assert run_main(command, argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(f"python -m safeil_sumo.{command}: error: ") and message in err
    assert "usage:" not in err


def test_positive_int_by_hand() -> None:
    assert cli_args.positive_int("1") == 1 and cli_args.positive_int(" 12 ") == 12
    for text, message in (("0", "must be >= 1, got 0"), ("-1", "must be >= 1, got -1"),
                          ("1.5", "not an integer: '1.5'"), ("", "not an integer: ''")):
        with pytest.raises(argparse.ArgumentTypeError, match=re.escape(message)):
            cli_args.positive_int(text)


def test_help_still_prints_the_usage(capsys) -> None:
    assert run_main("sweep", ["--help"]) == 0
    assert capsys.readouterr().out.startswith("usage: python -m safeil_sumo.sweep")


def test_a_missing_checkpoint_is_a_missing_file(tmp_path, capsys) -> None:
    missing = tmp_path / "nope" / "model.safetensors"
    assert run_main("run", ["--policy", str(missing), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert f"policy file {missing} does not exist" in err and "unknown policy" not in err
    assert err.count("\n") == 1
    # a name that is no file stays an unknown policy, with the names to use
    assert run_main("run", ["--policy", "nosuch", "--out", str(tmp_path / "o")]) == 2
    assert "unknown policy 'nosuch': use one of" in capsys.readouterr().err


# ---------------------------------------------------------------------------- TOML files


def _sweep_error(path: Path, capsys) -> str:
    from safeil_sumo import sweep

    with pytest.raises(SystemExit) as exc:
        sweep.parse_args(["--config", str(path)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "usage:" not in err, err
    return err


def test_a_toml_error_names_the_file_and_the_key(tmp_path, capsys) -> None:
    study = tmp_path / "study.toml"
    study.write_text('policies = ["safeil"]\n')
    assert f"{study}: key 'policies' was renamed 'policy'" in _sweep_error(study, capsys)
    study.write_text('policy = ["safeil"]\nnope = 1\n')
    assert f"{study}: unknown key 'nope'" in _sweep_error(study, capsys)
    study.write_text('brake_guard = "off"\n')
    assert f"{study}: brake_guard = 'off' is now brake_guard = false" in _sweep_error(
        study, capsys)
    study.write_text('scenarios = "many"\n')
    err = _sweep_error(study, capsys)
    assert f"{study}: argument --scenarios: invalid int value: 'many'" in err


def test_a_toml_switch_is_a_boolean(tmp_path) -> None:
    from safeil_sumo import sweep

    study = tmp_path / "study.toml"
    study.write_text('policy = "idm"\nbrake_guard = false\nmax_time_s = 5\n')
    specs = sweep.build_tasks(sweep.parse_args(["--config", str(study), "--scenarios", "1"]))
    assert [(s.planner.policy, s.brake_guard, s.scenario.max_time_s) for s in specs] == [
        ("idm", False, 5.0)]


def test_the_shipped_toml_files_use_the_current_keys() -> None:
    """Studies, the falsification's worst cases and the docs' example all parse."""
    from safeil_sumo import sweep

    files = [*(REPO / "sumo_scenarios" / "studies").glob("*.toml"),
             *(REPO / "results" / "falsify").glob("*.toml"), *(REPO / "docs").glob("*.toml")]
    assert len(files) >= 8
    for f in files:
        assert sweep.build_tasks(sweep.parse_args(["--config", str(f)])), f


# ----------------------------------------------------------------------------- interrupts


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_ends_a_ctrl_c_with_one_line(command, monkeypatch, capsys) -> None:
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_args.CommandParser, "parse_known_args", interrupted)
    assert run_main(command, ["runs/x"] if command == "animate" else []) == 130
    assert capsys.readouterr().err == "interrupted\n"


def _libsumo_loaded(pid: int) -> bool:
    psutil = pytest.importorskip("psutil")
    try:
        return any("libsumo" in m.path for m in psutil.Process(pid).memory_maps())
    except psutil.Error:
        return False


@pytest.mark.sumo
def test_ctrl_c_in_a_running_scenario_is_one_line_and_130(tmp_path) -> None:
    """A real ``run`` sent SIGINT while SUMO runs its scenarios (libsumo loaded: the first
    scenario has started; 100 of them last far longer than the wait)."""
    pytest.importorskip("libsumo")
    cmd = [sys.executable, "-m", "safeil_sumo.run", "--net", "straight", "--policy", "analytic",
           "--scenarios", "100", "--no-plots", "--out", str(tmp_path / "r")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        deadline = time.monotonic() + 120
        while not _libsumo_loaded(proc.pid) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.2)
        assert _libsumo_loaded(proc.pid), "the run never started SUMO"
        time.sleep(1.0)  # well inside the scenarios
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert err.splitlines() == ["interrupted"], err
    assert not (tmp_path / "r").exists()  # nothing half-written
