"""``python -m safeil_sumo.certify --closed-loop`` end to end on a coarse grid: the verdict it
prints and the file it writes for the shipped safeil (not proven), where the file goes, its
``--check``, and the one-line errors of options and checkpoints it cannot take."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest

from safeil_sumo import certify as cli
from safeil_sumo.learn import closed_loop_certificate as clc
from safeil_sumo.learn.checkpoint import checkpoint_paths
from safeil_sumo.planners import registry as pol

COARSE = ["--cells", "7.5", "2.5", "2.5", "3", "--no-progress"]


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch) -> None:
    """A shipped model's default runs/ folder is made here, not in the repo."""
    monkeypatch.chdir(tmp_path)


def _copy_checkpoint(name: str, folder) -> str:
    weights, sidecar = checkpoint_paths(pol.shipped_checkpoint(name))
    shutil.copy(weights, folder / weights.name)
    shutil.copy(sidecar, folder / sidecar.name)
    return str(folder / weights.name)


def _main(argv: list[str]) -> int:
    try:
        return cli.main(argv)
    except SystemExit as exc:
        return int(exc.code)


def test_the_command_writes_a_not_proven_certificate_beside_the_checkpoint(tmp_path,
                                                                           capsys) -> None:
    path = _copy_checkpoint("safeil", tmp_path)
    assert _main(["--policy", path, "--closed-loop", "--time-gap-s", "1.5", *COARSE]) == 0
    out = capsys.readouterr().out
    assert "time gap 1.5 s, brake guard on, 20 x 20 x 16 x 4 cells" in out
    assert "verdict: NOT PROVEN: " in out and "columns fail; median / max deficit" in out
    assert "S's share of the recoverable envelope: 0.0000% (0: only a passing check" in out
    assert "worst failing cells (where the proof fails):" in out and "reason 1: " in out
    body = clc.read(tmp_path / "safeil.closed_loop_certificate.json")
    assert (tmp_path / "safeil.closed_loop_floor.safetensors").is_file()
    assert body["verdict"] == "not proven" and body["proven"] is False
    assert f"verdict: NOT PROVEN: {body['failing_columns']:,} of {body['columns']:,}" in out
    assert body["assumptions"]["time_gap_s"] == [1.5, 1.5] and body["search"] is None
    assert body["assumptions"]["grid"]["gap_m"] == [1.0, 151.0, 7.5]
    # --check: valid, but it proves nothing, so the check fails (exit 1)
    assert _main(["--policy", path, "--closed-loop", "--check"]) == 1
    line = capsys.readouterr().out
    assert line.startswith(f"{tmp_path / 'safeil.closed_loop_certificate.json'}: valid (ok); "
                           "not proven: ")
    # the one-plan certificate is another file: its check does not read this one
    assert _main(["--policy", path, "--check"]) == 1
    assert "no certificate" in capsys.readouterr().out


def test_a_shipped_model_goes_to_runs_and_the_options_reach_the_file(tmp_path,
                                                                    capsys) -> None:
    """Without the guard, a time-gap range and a short search (one check: the budget is spent
    by then), into runs/certify_safeil/ as the one-plan certificate."""
    assert _main(["--policy", "safeil", "--closed-loop", "--no-brake-guard",
                  "--time-gap-range-s", "1.4", "1.6", "--search-s", "0.001", *COARSE]) == 0
    out = capsys.readouterr().out
    assert "time gap 1.4-1.6 s, brake guard off" in out and "verdict: NOT PROVEN" in out
    written = tmp_path / "runs" / "certify_safeil" / "safeil.closed_loop_certificate.json"
    body = clc.read(written)
    a = body["assumptions"]
    assert a["brake_guard"] is False and a["guard_settings"] is None
    assert a["time_gap_s"] == [1.4, 1.6] and body["proven"] is False
    assert body["search"]["stopped_by"] == "budget" and len(body["search"]["rounds"]) == 1
    assert body["floor"]["source"] == "synthesize: last of 1 checks"
    assert _main(["--policy", "safeil", "--closed-loop", "--check"]) == 1
    assert capsys.readouterr().out.startswith(
        "runs/certify_safeil/safeil.closed_loop_certificate.json: valid (ok); not proven: ")
    # at the checkpoint's own setting by default
    assert _main(["--policy", "safeil", "--closed-loop", *COARSE]) == 0
    setting = pol.load("safeil").style["time_gap_s"]
    assert json.loads(written.read_text())["assumptions"]["time_gap_s"] == [setting, setting]


@pytest.mark.parametrize("argv, message", [
    (["--margins", "leader"], "--margins certifies one plan: not with --closed-loop"),
    (["--budget-s", "5", "--seed", "1"], "--budget-s, --seed certify one plan: not with"),
    (["--time-gap-s", "1", "--time-gap-range-s", "1", "2"], "use either --time-gap-s"),
    (["--search-s", "-1"], "--search-s must be >= 0 s, got -1"),
    (["--brake-guard", "off"], "use --no-brake-guard"),
])
def test_options_that_make_no_sense_with_closed_loop_are_one_line(argv, message,
                                                                   capsys) -> None:
    assert _main(["--closed-loop", *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "usage:" not in err and message in err, err


@pytest.mark.parametrize("argv", [["--cells", "1", "1", "1", "1"], ["--search-s", "5"],
                                  ["--no-brake-guard"], ["--time-gap-s", "1.5"]])
def test_closed_loop_options_need_closed_loop(argv, capsys) -> None:
    assert _main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "only with --closed-loop" in err


@pytest.mark.parametrize("argv, message", [
    (["--policy", "nope/model.safetensors"], "does not exist"),
    (["--policy", "analytic"], "not a network checkpoint"),
    (["--policy", "bc"], "bc has no time-gap input"),
    (["--policy", "safeil", "--cells", "7", "1", "1", "1"], "is not a whole number of cells"),
    (["--policy", "safeil", "--time-gap-range-s", "2", "1"], "0 < LO <= HI"),
])
def test_a_checkpoint_it_cannot_check_is_a_one_line_error(argv, message, capsys) -> None:
    assert _main(["--closed-loop", *argv, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err


def test_a_missing_checkpoint_as_a_process_is_one_line(tmp_path) -> None:
    proc = subprocess.run([sys.executable, "-m", "safeil_sumo.certify", "--closed-loop",
                           "--policy", str(tmp_path / "x.safetensors")], capture_output=True,
                          text=True, timeout=300, check=False)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "does not exist" in proc.stderr
    assert proc.stdout == ""
