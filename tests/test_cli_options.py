"""run and sweep declare their scenario options once (cli_args.add_scenario_options): the same
flags give the same ScenarioSpec fields in both, and every spec field has its option."""

from __future__ import annotations

from dataclasses import fields

import pytest

from safeil_sumo.cli_args import scenario_fields
from safeil_sumo.run import parse_args as run_args
from safeil_sumo.scenarios.spec import ScenarioSpec
from safeil_sumo.sweep import build_specs
from safeil_sumo.sweep import parse_args as sweep_args

FLAGS = ["--scenarios", "3", "--seed", "7", "--leader", "braking",
         "--leader-speed-range-mps", "20", "24", "--brake-time-s", "2", "--brake-decel-mps2", "4.5",
         "--brake-to-mps", "5", "--ego-speed-mps", "26",
         "--time-gap-s", "1.4", "--gap-range-m", "30", "40", "--lane-noise-m", "0.05",
         "--radar-noise-m", "0.3", "--plan-rate-hz", "5", "--max-time-s", "12", "--stop-on-flag",
         "--no-brake-guard"]


def test_run_and_sweep_read_the_same_scenario_options():
    run = scenario_fields(run_args(["--policy", "idm", *FLAGS]))
    sweep = scenario_fields(sweep_args(["--policy", "idm", *FLAGS]))
    assert run == sweep
    assert run["brake_decel_mps2"] == 4.5 and run["initial_gap_m"] == (30.0, 40.0)
    assert run["brake_guard"] is False and run["stop_on_flag"] is True


def test_every_spec_field_has_an_option():
    """A new ScenarioSpec field needs an option here (or a reason to be left out)."""
    per_task = {"net", "index", "policy", "safety_filter"}  # the grid's axes, set by each CLI
    given = set(scenario_fields(sweep_args([])))
    assert given == {f.name for f in fields(ScenarioSpec)} - per_task


def test_sweep_specs_carry_every_option():
    specs = build_specs(sweep_args(["--policy", "idm", "--net", "straight", *FLAGS]))
    assert len(specs) == 3 and [s.index for s in specs] == [0, 1, 2]
    expected = ScenarioSpec(net="straight", index=0, policy="idm",
                            **scenario_fields(sweep_args(FLAGS)))
    assert specs[0] == expected


def test_run_reports_the_spec_rules_as_usage_errors(capsys):
    with pytest.raises(SystemExit) as exc:
        run_args(["--plan-rate-hz", "200"])
    assert exc.value.code == 2
    assert "plan rate must be in (0, 100] Hz" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run_args(["--net", "n74", "--route", "main0"])
    assert "--route needs a .net.xml path" in capsys.readouterr().err
