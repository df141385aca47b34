"""`python -m safeil_sumo.run`: outputs of a real run, and one-line errors for bad input."""

import json
import subprocess
import sys

import pandas as pd
import pytest

from safeil_sumo.run import main


@pytest.mark.sumo
def test_run_writes_the_results_folder(tmp_path, capsys):
    out = tmp_path / "res"
    code = main(["--net", "curved500", "--policy", "analytic", "--scenarios", "2", "--seed", "5",
                 "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "2/2 scenarios completed" in printed and "s0001" in printed
    for name in ("steps.parquet", "summary.csv", "summary.json", "manifest.json",
                 "trajectory.png", "speed_gap.png", "ttc.png"):
        assert (out / name).is_file(), name
    steps = pd.read_parquet(out / "steps.parquet")
    assert set(steps["scenario"]) == {"s0000", "s0001"}
    summary = pd.read_csv(out / "summary.csv")
    assert list(summary["completed"]) == [True, True]
    assert summary["leader_speed_mps"].between(25, 32).all()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["versions"]["eclipse-sumo"] == "1.28.0"
    assert manifest["config"]["master_seed"] == 5 and len(manifest["seeds"]) == 2
    assert manifest["git_commit"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp leftovers


@pytest.mark.parametrize(
    "args, message",
    [
        (["--net", "nosuchnet"], "unknown"),
        (["--net", "missing/road.net.xml"], "not found"),
        (["--net", "curved2"], "radius"),
        (["--policy", "nosuchpolicy"], "unknown policy"),
        (["--leader-speed-range-mps", "-1", "5"], "error"),
    ],
)
def test_bad_input_gives_one_clear_line(tmp_path, capsys, args, message):
    out = tmp_path / "res"
    try:
        code = main([*args, "--out", str(out)])
    except SystemExit as exc:  # argparse errors
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert message in err.lower()
    assert "Traceback" not in err
    assert not out.exists()


def test_malformed_net_file(tmp_path, capsys):
    bad = tmp_path / "bad.net.xml"
    bad.write_text("<net><edge id='a'")
    assert main(["--net", str(bad), "--out", str(tmp_path / "res")]) == 2
    assert "malformed" in capsys.readouterr().err
    assert not (tmp_path / "res").exists()


@pytest.mark.sumo
def test_module_entry_point_runs_headless(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "safeil_sumo.run", "--net", "straight", "--policy", "analytic",
         "--scenarios", "1", "--no-plots", "--out", str(tmp_path / "r")],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "1/1 scenarios completed" in proc.stdout
