"""run and sweep declare their scenario options once (cli_args.add_scenario_options, made from
the ScenarioSpec fields): the same flags give the same task in both, every task field has its
option, and every option's default is its dataclass field's."""

from __future__ import annotations

from dataclasses import fields

import pytest

from safeil_sumo.cli_args import loop_config, scenario_fields, task
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.run import parse_args as run_args
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.sweep import build_parser, build_tasks
from safeil_sumo.sweep import parse_args as sweep_args

FLAGS = ["--scenarios", "3", "--seed", "7", "--leader", "braking",
         "--leader-speed-range-mps", "20", "24", "--brake-time-s", "2", "--brake-decel-mps2", "4.5",
         "--brake-to-mps", "5", "--ego-speed-mps", "26",
         "--time-gap-s", "1.4", "--gap-range-m", "30", "40", "--lane-noise-m", "0.05",
         "--radar-noise-m", "0.3", "--plan-rate-hz", "5", "--max-time-s", "12", "--stop-on-flag",
         "--no-brake-guard"]


def test_run_and_sweep_read_the_same_scenario_options():
    run, sweep = run_args(["--policy", "idm", *FLAGS]), sweep_args(["--policy", "idm", *FLAGS])
    assert task(run, "straight", 0, "idm") == task(sweep, "straight", 0, "idm")
    got = task(run, "straight", 0, "idm")
    assert got.scenario.brake_decel_mps2 == 4.5 and got.scenario.initial_gap_m == (30.0, 40.0)
    assert got.loop.brake_guard is None and got.loop.stop_on_flag is True
    assert got.loop.plan_rate_hz == 5.0 and got.planner == PlannerRef("idm", time_gap_s=1.4)


def test_every_task_field_has_an_option():
    """Every ScenarioSpec field but the net and index is an option made from the field; the
    loop's task settings and the planner's time gap have theirs (a new field needs one)."""
    given = set(scenario_fields(sweep_args([])))
    assert given == {f.name for f in fields(ScenarioSpec)} - {"net", "index"}
    dests = {a.dest for a in build_parser()._actions}
    assert {"plan_rate_hz", "stop_on_flag", "brake_guard", "time_gap_s", "safety_filter",
            "policy", "net", "scenarios"} <= dests


def test_option_defaults_are_the_dataclasses_defaults():
    """No option writes its own default: a task made from no options is the dataclasses' (the
    shipped brake guard on); the help shows the field's default."""
    assert task(sweep_args([]), "curved500", 0, "analytic") == Task.of(policy="analytic")
    assert task(run_args([]), "curved500", 3, "bc") == Task.of(index=3, policy="bc")
    helps = {a.dest: a.help for a in build_parser()._actions}
    assert helps["brake_time_s"].endswith(f"(default {ScenarioSpec.brake_time_s:g})")
    assert helps["leader_speed_range_mps"].endswith("(default 25 32)")


def test_sweep_tasks_carry_every_option():
    tasks = build_tasks(sweep_args(["--policy", "idm", "--net", "straight", *FLAGS]))
    assert len(tasks) == 3 and [t.scenario.index for t in tasks] == [0, 1, 2]
    args = sweep_args(FLAGS)
    expected = Task(ScenarioSpec(net="straight", index=0, **scenario_fields(args)),
                    PlannerRef("idm", time_gap_s=1.4), loop_config(args))
    assert tasks[0] == expected


def test_run_reports_the_spec_rules_as_usage_errors(capsys):
    with pytest.raises(SystemExit) as exc:
        run_args(["--plan-rate-hz", "200"])
    assert exc.value.code == 2
    assert "plan rate must be in (0, 100] Hz" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run_args(["--net", "n74", "--route", "main0"])
    assert "--route needs a .net.xml path" in capsys.readouterr().err
