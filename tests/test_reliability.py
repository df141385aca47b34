"""Reliability and security (issue 7): every bad input and fault of docs/reliability.md, tried.

Bad input gives one clear error line (no traceback), a non-zero exit and no results folder;
faults end a run with a recorded reason and keep what was finished; every writer is atomic;
the same seed gives the same numbers; nothing is unpickled and nothing escapes the results folder.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from fixtures_data import straight_drive

from safeil_sumo.data import importers
from safeil_sumo.data.schema import SchemaError, load_drive, save_drive
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.experiments import outputs
from safeil_sumo.experiments.sweep_executor import run_sweep, task_id
from safeil_sumo.learn.checkpoint import CheckpointError, load_checkpoint
from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.planners.registry import MODELS_DIR, PolicyError
from safeil_sumo.planners.registry import load as load_policy
from safeil_sumo.roads.recorded_road import safe_name
from safeil_sumo.scenarios.spec import Task
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim.leaders import ProfileError, constant, from_file
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.runner import run_scenario
from safeil_sumo.sim.sumo_setup import EGO_ID, LEADER_ID

REPO = Path(__file__).resolve().parents[1]
TRAIN = REPO / "training" / "train.py"


def cli(module_or_script: str, *args: str, cwd: Path | None = None, timeout: float = 300):
    """Run a CLI as a subprocess: ``(returncode, stdout, stderr)``."""
    cmd = ([sys.executable, module_or_script] if module_or_script.endswith(".py")
           else [sys.executable, "-m", module_or_script])
    proc = subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=timeout,
                          check=False, cwd=cwd)
    return proc.returncode, proc.stdout, proc.stderr


def assert_one_line_error(code: int, err: str, expected_code: int = 2) -> str:
    assert code == expected_code, err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(("error:", "python -m", "train.py: error")), err
    return last


def call_main(main, argv) -> int:
    """A CLI ``main`` in-process; argparse's SystemExit becomes its code."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


# -- bad recordings ------------------------------------------------------------------------------

def _drive() -> pd.DataFrame:
    return straight_drive(duration=6.0)


def _write(df: pd.DataFrame, path: Path) -> Path:
    (df.to_csv(path, index=False) if path.suffix == ".csv" else df.to_parquet(path, index=False))
    return path


def _with(col: str, row: int, value) -> pd.DataFrame:
    df = _drive()
    df.loc[row, col] = value
    return df


def _bad_file(kind: str, tmp: Path) -> Path:
    """A drive file with one defect (name -> file)."""
    good = _drive()
    if kind == "missing_column":
        return _write(good.drop(columns=["v_x"]), tmp / "d.parquet")
    if kind == "nan":
        return _write(_with("x", 5, np.nan), tmp / "d.parquet")
    if kind == "inf":
        return _write(_with("left_c0", 5, np.inf), tmp / "d.parquet")
    if kind == "duplicate_time":
        return _write(_with("time", 5, good.loc[4, "time"]), tmp / "d.csv")
    if kind == "decreasing_time":
        return _write(_with("time", 5, 0.1), tmp / "d.parquet")
    if kind == "kmh":
        return _write(good.assign(v_x=good["v_x"] * 3.6 + 60), tmp / "d.parquet")
    if kind == "empty_parquet":
        (tmp / "d.parquet").write_bytes(b"")
        return tmp / "d.parquet"
    if kind == "empty_csv":
        (tmp / "d.csv").write_text("")
        return tmp / "d.csv"
    if kind == "header_only_csv":
        (tmp / "d.csv").write_text(",".join(good.columns) + "\n")
        return tmp / "d.csv"
    if kind == "truncated_parquet":
        data = _write(good, tmp / "full.parquet").read_bytes()
        (tmp / "d.parquet").write_bytes(data[: len(data) // 2])
        return tmp / "d.parquet"
    if kind == "truncated_csv":
        text = _write(good, tmp / "full.csv").read_text()
        (tmp / "d.csv").write_text(text[: len(text) // 2])  # a row cut mid-way
        return tmp / "d.csv"
    if kind == "csv_named_parquet":
        (tmp / "d.parquet").write_text(good.to_csv(index=False))
        return tmp / "d.parquet"
    if kind == "parquet_named_csv":
        (tmp / "d.csv").write_bytes(_write(good, tmp / "full.parquet").read_bytes())
        return tmp / "d.csv"
    raise AssertionError(kind)


BAD_DRIVES = {
    "missing_column": "column 'v_x': missing required column",
    "nan": "column 'x', row 5: missing value (NaN) not allowed",
    "inf": "column 'left_c0', row 5: infinite value",
    "duplicate_time": "column 'time', row 5: time does not increase (0.4 -> 0.4)",
    "decreasing_time": "column 'time', row 5: time does not increase",
    "kmh": "looks like km/h",
    "empty_parquet": "not a readable Parquet file",
    "empty_csv": "empty file",
    "header_only_csv": "no rows",
    "truncated_parquet": "not a readable Parquet file",
    "truncated_csv": "does not end with a newline (truncated?)",
    "csv_named_parquet": "not a readable Parquet file",
    "parquet_named_csv": "not a readable CSV file",
}


@pytest.mark.parametrize("kind", sorted(BAD_DRIVES))
def test_load_drive_rejects_bad_recordings(kind, tmp_path):
    path = _bad_file(kind, tmp_path)
    with pytest.raises(SchemaError) as exc:
        load_drive(path)
    msg = str(exc.value)
    assert msg.startswith(str(path)) and BAD_DRIVES[kind] in msg and "\n" not in msg


@pytest.mark.parametrize("kind", sorted(BAD_DRIVES))
@pytest.mark.parametrize("reader", ["ngsim_pairs", "ngsim_csv", "openacc", "tuples"])
def test_importers_and_tuples_reject_bad_files(kind, reader, tmp_path):
    """Wrong files for every reader: a ValueError (SchemaError) naming the file, nothing else."""
    path = _bad_file(kind, tmp_path)
    fn = {"ngsim_pairs": importers.import_ngsim_pairs, "ngsim_csv": importers.import_ngsim_csv,
          "openacc": importers.import_openacc, "tuples": Tuples.load}[reader]
    with pytest.raises(ValueError) as exc:
        fn(path)
    assert str(path) in str(exc.value)


def _tuples_file(tmp: Path) -> Path:
    from fixtures_training import make_tuples

    make_tuples().save(tmp / "t.parquet")
    return tmp / "t.parquet"


@pytest.mark.parametrize("defect, message", [
    ("missing_column", "missing tuples column(s) ['cp_x2']"),
    ("nan", "column 'f_v_x', row 3: non-finite value nan"),
    ("bad_metadata", "malformed safeil tuples metadata"),
    ("zero_horizon", "must be > 0"),
    ("no_metadata", "no safeil tuples metadata"),
    ("missing_file", "no such tuples file"),
])
def test_tuples_load_rejects_bad_tuples(defect, message, tmp_path):
    path = _tuples_file(tmp_path)
    table = pq.read_table(path)
    meta = table.schema.metadata
    if defect == "missing_column":
        pq.write_table(table.drop(["cp_x2"]), path)
    elif defect == "nan":
        df = table.to_pandas()
        df.loc[3, "f_v_x"] = np.nan
        pq.write_table(pa.Table.from_pandas(df, preserve_index=False)
                       .replace_schema_metadata(meta), path)
    elif defect == "bad_metadata":
        pq.write_table(table.replace_schema_metadata({b"safeil": b"[1, 2]"}), path)
    elif defect == "zero_horizon":
        pq.write_table(table.replace_schema_metadata(
            {b"safeil": b'{"horizon_s": 0, "rate_hz": 10}'}), path)
    elif defect == "no_metadata":
        pq.write_table(table.replace_schema_metadata({}), path)
    else:
        path.unlink()
    with pytest.raises(ValueError, match=re.escape(message)):
        Tuples.load(path)


@pytest.mark.parametrize("kind", ["truncated_parquet", "kmh", "csv_named_parquet"])
def test_replay_cli_bad_source_subprocess(kind, tmp_path):
    path = _bad_file(kind, tmp_path)
    out = tmp_path / "out"
    code, _, err = cli("safeil_sumo.replay", "--source", str(path), "--out", str(out))
    last = assert_one_line_error(code, err)
    assert BAD_DRIVES[kind] in last
    assert not out.exists()


@pytest.mark.parametrize("kind", sorted(BAD_DRIVES))
def test_replay_cli_bad_source(kind, tmp_path, capsys):
    from safeil_sumo.replay import main

    path = _bad_file(kind, tmp_path)
    out = tmp_path / "out"
    assert main(["--source", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and BAD_DRIVES[kind] in err
    assert not out.exists()


# -- bad networks --------------------------------------------------------------------------------

def _bad_net(kind: str, tmp: Path) -> Path:
    src = REPO / "sumo_scenarios" / "straight"
    net = tmp / "road.net.xml"
    text = (src / "straight.net.xml").read_text()
    if kind == "missing":
        return net
    if kind == "malformed":
        net.write_text(text[: len(text) // 2])
    elif kind == "not_a_net":
        net.write_text("<routes/>")
    elif kind in ("fewer_lanes", "bad_sidecar"):
        net.write_text(re.sub(r'\s*<lane id="[^"]*_[12]"[^>]*/>', "", text))
        sidecar = (src / "straight.track.json").read_text()
        (tmp / "road.track.json").write_text(sidecar if kind == "fewer_lanes" else "{oops")
    return net


BAD_NETS = {
    "missing": "network file not found",
    "malformed": "malformed XML",
    "not_a_net": "not a SUMO network",
    "fewer_lanes": "the scenario needs lane index 1 but edge 'road' has 1 lane(s)",
    "bad_sidecar": "unreadable track sidecar",
}


@pytest.mark.parametrize("kind", sorted(BAD_NETS))
@pytest.mark.parametrize("which", ["run", "sweep"])
def test_bad_net_gives_one_line_and_no_output(kind, which, tmp_path, capsys):
    from safeil_sumo.run import main as run_main
    from safeil_sumo.sweep import main as sweep_main

    net, out = _bad_net(kind, tmp_path), tmp_path / "out"
    if which == "run":
        code = run_main(["--net", str(net), "--policy", "analytic", "--out", str(out)])
    else:
        code = sweep_main(["--net", str(net), "--policy", "analytic", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and BAD_NETS[kind] in err
    assert not out.exists()


def test_bad_net_subprocess_run_and_sweep(tmp_path):
    net = _bad_net("fewer_lanes", tmp_path)
    for module, flag in (("safeil_sumo.run", "--policy"), ("safeil_sumo.sweep", "--policy")):
        out = tmp_path / module
        code, _, err = cli(module, "--net", str(net), flag, "analytic", "--out", str(out))
        assert BAD_NETS["fewer_lanes"] in assert_one_line_error(code, err)
        assert not out.exists()


# -- leader profiles -----------------------------------------------------------------------------

@pytest.mark.parametrize("rows, message", [
    ({"time": [0.0, 0.5, 3.0], "speed": [20, 20, 20]}, "gap of 2.50 s before row 2"),
    ({"time": [0.0, 0.5, 1.0], "speed": [20, -1, 20]}, "negative speed -1.000 m/s at row 1"),
    ({"time": [0.0, 0.5, 0.5], "speed": [20, 20, 20]}, "times must increase strictly (row 2)"),
    ({"time": [0.0, np.nan, 1.0], "speed": [20, 20, 20]}, "must be finite"),
    ({"time": [0.0, 0.5], "speed": [20, np.inf]}, "must be finite"),
    ({"time": [0.0, 0.5], "speed": ["fast", 20]}, "non-numeric values"),
    ({"time": [], "speed": []}, "the profile is empty"),
    ({"t": [0.0], "speed": [20.0]}, "missing column 'time'"),
])
def test_leader_profile_errors(rows, message, tmp_path):
    path = tmp_path / "lead.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    with pytest.raises(ProfileError, match=re.escape(message)):
        from_file(path)


def test_leader_profile_unreadable_files(tmp_path):
    (tmp_path / "a.parquet").write_text("time,speed\n0,1\n")
    (tmp_path / "b.csv").write_bytes(b"\x00\xff\xfe" * 10)
    for name, message in (("a.parquet", "cannot read"), ("b.csv", "cannot read"),
                          ("c.csv", "not found")):
        with pytest.raises(ProfileError, match=message):
            from_file(tmp_path / name)


# -- CLI arguments out of range ------------------------------------------------------------------

RUN_BAD = [
    ["--scenarios", "-1"], ["--scenarios", "0"], ["--seed", "-1"], ["--ego-speed-mps", "nan"],
    ["--ego-speed-mps", "inf"], ["--ego-speed-mps", "-3"], ["--gap-m", "inf"], ["--gap-m", "0"],
    ["--leader-speed-range-mps", "0", "inf"], ["--leader-speed-range-mps", "30", "20"],
    ["--plan-rate-hz", "0"],
    ["--plan-rate-hz", "nan"], ["--plan-rate-hz", "1000"], ["--scenarios", "two"],
]
SWEEP_BAD = [
    ["--scenarios", "-1"], ["--workers", "-2"], ["--workers", "0"], ["--seed", "-1"],
    ["--plan-rate-hz", "0"], ["--ego-speed-mps", "nan"], ["--lane-noise-m", "nan"],
    ["--radar-noise-m", "inf"], ["--radar-noise-m", "-1"], ["--brake-time-s", "nan"],
    ["--leader", "braking", "--brake-decel-mps2", "inf"], ["--max-time-s", "nan"],
    ["--max-time-s", "inf"], ["--max-time-s", "-1"], ["--gap-m", "inf"],
    ["--gap-range-m", "10", "inf"], ["--gap-range-m", "50", "10"],
    ["--leader-speed-range-mps", "0", "inf"], ["--task-timeout-s", "nan"],
    ["--task-timeout-s", "0"], ["--ego-speed-mps", "1e9"], ["--scheduler", "localhost"],
]
REPLAY_BAD = [
    ["--rate-hz", "0"], ["--plan-rate-hz", "0"], ["--plan-rate-hz", "nan"], ["--duration-s", "-1"],
    ["--duration-s", "inf"], ["--start-s", "nan"], ["--seed", "-1"], ["--rate-hz", "500"],
]
TRAIN_BAD = [
    ["--epochs", "-1"], ["--patience", "0"], ["--batch-size", "-3"], ["--lr", "nan"],
    ["--lr", "0"], ["--val-fraction", "1.5"], ["--hidden", "0,a"], ["--hidden", "64,-1"],
    ["--threads", "0"], ["--seed", "-1"], ["--track", "inf"], ["--barrier-samples", "-2"],
    ["--val-maneuvers", "no_such_maneuver"],
]


@pytest.mark.parametrize("args", RUN_BAD, ids=" ".join)
def test_run_cli_rejects_out_of_range(args, tmp_path, capsys):
    from safeil_sumo.run import main

    out = tmp_path / "out"
    assert call_main(main, [*args, "--net", "straight", "--policy", "analytic",
                            "--out", str(out)]) == 2
    assert "Traceback" not in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("args", SWEEP_BAD, ids=" ".join)
def test_sweep_cli_rejects_out_of_range(args, tmp_path, capsys):
    from safeil_sumo.sweep import main

    out = tmp_path / "out"
    assert call_main(main, [*args, "--net", "straight", "--policy", "analytic",
                            "--no-progress", "--out", str(out)]) == 2
    assert "Traceback" not in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("args", REPLAY_BAD, ids=" ".join)
def test_replay_cli_rejects_out_of_range(args, tmp_path, capsys):
    from safeil_sumo.replay import main

    path = _write(_drive(), tmp_path / "d.parquet")
    out = tmp_path / "out"
    assert call_main(main, [*args, "--source", str(path), "--out", str(out)]) == 2
    assert "Traceback" not in capsys.readouterr().err and not out.exists()


@pytest.fixture(scope="module")
def tuples_path(tmp_path_factory) -> Path:
    return _tuples_file(tmp_path_factory.mktemp("tuples"))


@pytest.mark.parametrize("args", TRAIN_BAD, ids=" ".join)
def test_train_cli_rejects_out_of_range(args, tuples_path, tmp_path):
    out = tmp_path / "ck" / "m"
    code, _, err = cli(str(TRAIN), "--data", str(tuples_path), "--out", str(out), *args)
    assert_one_line_error(code, err)
    assert not out.parent.exists()


@pytest.mark.parametrize("kind", ["truncated_parquet", "kmh"])
def test_train_cli_rejects_bad_data(kind, tmp_path):
    path = _bad_file(kind, tmp_path)
    code, _, err = cli(str(TRAIN), "--data", str(path), "--out", str(tmp_path / "ck" / "m"))
    assert str(path) in assert_one_line_error(code, err)
    assert not (tmp_path / "ck").exists()


@pytest.mark.parametrize("module, args", [
    # was a traceback
    ("safeil_sumo.run", ["--leader-speed-range-mps", "0", "inf", "--policy", "analytic"]),
    ("safeil_sumo.sweep", ["--seed", "-1", "--policy", "analytic"]),  # was a traceback
    ("safeil_sumo.sweep", ["--workers", "-1"]),
    ("safeil_sumo.replay", ["--plan-rate-hz", "0"]),
])
def test_cli_argument_errors_subprocess(module, args, tmp_path):
    out = tmp_path / "out"
    code, _, err = cli(module, *args, "--out", str(out))
    assert_one_line_error(code, err)
    assert not out.exists()


# -- checkpoints ---------------------------------------------------------------------------------

class _SideEffect:
    """Unpickling this calls ``open(marker, "w")``: the file would appear."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _copy_shipped(dst: Path, name: str = "analytic_test") -> Path:
    shutil.copy(MODELS_DIR / "bc.safetensors", dst / f"{name}.safetensors")
    shutil.copy(MODELS_DIR / "bc.json", dst / f"{name}.json")
    return dst / f"{name}.safetensors"


def test_pickle_payload_is_never_unpickled(tmp_path):
    # the payload works: unpickling it here creates its marker ...
    probe = tmp_path / "probe_marker"
    pickle.loads(pickle.dumps(_SideEffect(probe))).close()
    assert probe.exists()
    # ... but as a checkpoint (weights renamed .safetensors, a valid sidecar beside it) it is
    # refused by the loader and by the run CLI, and its marker never appears
    marker = tmp_path / "pwned"
    weights = _copy_shipped(tmp_path, "evil")
    weights.write_bytes(pickle.dumps(_SideEffect(marker)))
    with pytest.raises(CheckpointError, match="pickle"):
        load_checkpoint(weights)
    with pytest.raises(PolicyError, match="refusing to unpickle"):
        load_policy(str(weights))
    out = tmp_path / "out"
    code, _, err = cli("safeil_sumo.run", "--net", "straight", "--policy", str(weights),
                       "--out", str(out))
    assert "refusing to unpickle" in assert_one_line_error(code, err)
    assert not marker.exists() and not out.exists()


def _torch_zip(path: Path) -> None:
    import torch

    torch.save({"w": torch.zeros(3)}, path)


@pytest.mark.parametrize("kind, message", [
    ("truncated", "sha256 does not match"),
    ("zip", "zip archive"),
    ("npy", ".npy file"),
    ("pickle", "Python pickle"),
    ("parquet", "Parquet file"),
    ("empty", "truncated or empty"),
    ("random", "sha256 does not match"),
])
def test_checkpoint_renamed_or_corrupt(kind, message, tmp_path):
    weights = _copy_shipped(tmp_path)
    blob = weights.read_bytes()
    if kind == "truncated":
        weights.write_bytes(blob[: len(blob) // 2])
    elif kind == "zip":
        _torch_zip(weights)
    elif kind == "npy":
        with open(weights, "wb") as f:
            np.save(f, np.zeros(3))
    elif kind == "pickle":
        weights.write_bytes(pickle.dumps({"w": [0.0] * 3}))
    elif kind == "parquet":
        weights.write_bytes(_write(_drive(), tmp_path / "x.parquet").read_bytes())
    elif kind == "empty":
        weights.write_bytes(b"")
    else:
        weights.write_bytes(np.random.default_rng(0).bytes(len(blob)))
    with pytest.raises(CheckpointError, match=re.escape(message)):
        load_checkpoint(weights)


def test_checkpoint_of_another_architecture(tmp_path):
    weights = _copy_shipped(tmp_path)
    sidecar = weights.with_suffix(".json")
    meta = json.loads(sidecar.read_text())
    meta["architecture"]["hidden"] = [32, 32]  # the weights are 64-64
    sidecar.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="do not match the architecture|needs"):
        load_checkpoint(weights)
    from safeil_sumo.run import main

    assert call_main(main, ["--policy", str(weights), "--out", str(tmp_path / "o")]) == 2


# -- faults in SUMO ------------------------------------------------------------------------------

class FaultyLibsumo:
    """libsumo with one action injected before the N-th ``simulation.step``."""

    def __init__(self, args, at_step: int, action) -> None:
        self.api = sumo_api.start(args)
        self.route, self.vehicle = self.api.route, self.api.vehicle
        self.steps, outer = 0, self

        class Simulation:
            def __getattr__(self, name):
                return getattr(outer.api.simulation, name)

            def step(self, *args):
                outer.steps += 1
                if outer.steps == at_step:
                    action(outer.api)
                return outer.api.simulation.step(*args)

        self.simulation = Simulation()

    def close(self) -> None:
        self.api.close()


def _boom(api):
    raise RuntimeError("injected SUMO failure")


def _run_with_fault(action, at_step=100):
    from safeil_sumo.roads.catalogue import resolve_net
    from safeil_sumo.roads.road import load_road

    road = load_road(resolve_net("straight"))
    sc = Scenario("fault", road, constant(28.0), 30.0, 50.0, seed=1, max_time_s=3.0)
    return run_scenario(sc, AnalyticPlanner(), LoopConfig(),
                        api_factory=lambda args: FaultyLibsumo(args, at_step, action))


@pytest.mark.sumo
def test_sumo_exception_mid_run_is_recorded_and_log_kept():
    r = _run_with_fault(_boom)
    assert r.summary["end_reason"] == "error"
    assert r.summary["error"] == "RuntimeError: injected SUMO failure"
    assert len(r.log) == 98 and np.isfinite(r.log["x"]).all()  # the first step is the setup's


@pytest.mark.sumo
def test_ego_removed_mid_run_is_an_error_with_the_log_kept():
    r = _run_with_fault(lambda api: api.vehicle.remove(EGO_ID))
    assert r.summary["end_reason"] == "error" and "'ego' is not known" in r.summary["error"]
    assert len(r.log) == 99


@pytest.mark.sumo
def test_leader_removed_mid_run_continues_as_free_road():
    r = _run_with_fault(lambda api: api.vehicle.remove(LEADER_ID))
    assert r.summary["end_reason"] == "timeout" and r.summary["error"] == ""
    lost = r.log["leader_x"].isna().to_numpy()
    assert not lost[:98].any() and lost[99:].all()  # visible in the log from that step on
    assert np.isinf(r.log["gap"].to_numpy()[99:]).all()


def test_sumo_that_cannot_start_is_exit_code_3(tmp_path, monkeypatch, capsys):
    from safeil_sumo import run as run_cli

    def fail(*args, **kwargs):
        raise sumo_api.SumoError("cannot start SUMO: injected")

    monkeypatch.setattr(sumo_api, "start", fail)
    out = tmp_path / "out"
    assert run_cli.main(["--net", "straight", "--policy", "analytic", "--out", str(out)]) == 3
    assert capsys.readouterr().err == "error: cannot start SUMO: injected\n"
    assert not out.exists()


# -- Ctrl-C of a running sweep -------------------------------------------------------------------

def _task_files(out: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in (out / "tasks").glob("*.json")}


@pytest.mark.sumo
@pytest.mark.parametrize(("workers", "batch"), [("1", "1"), ("2", "1"), ("2", "3")])
def test_sigint_keeps_finished_results_and_rerun_completes_the_rest(workers, batch, tmp_path):
    """Batched (3 per simulation), each record is saved as its scenario ends (these end
    together; tests/experiments/test_task_engine.py interrupts a batch whose scenarios end apart)."""
    out = tmp_path / "sweep"
    args = [sys.executable, "-m", "safeil_sumo.sweep", "--net", "straight", "--policy",
            "analytic", "--scenarios", "12", "--max-time-s", "4", "--workers", workers,
            "--batch", batch, "--no-progress", "--out", str(out)]
    # the sweep gets Ctrl-C's default handling even when the tests run in a background job
    # (a non-interactive shell starts those with SIGINT ignored, and children inherit that)
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            # the child only resets one handler before exec: thread-safe
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # noqa: PLW1509
    deadline = time.monotonic() + 120
    while len(list((out / "tasks").glob("*.json"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted: finished tasks are saved" in err
    finished = _task_files(out)
    assert 2 <= len(finished) < 12
    for text in finished.values():  # every saved result is whole and readable
        assert json.loads(text)["status"] == "ok"
    assert not [p for p in out.rglob("*") if p.name.startswith(".tmp")]

    code, stdout, err = cli("safeil_sumo.sweep", *args[3:])
    assert code == 0, err
    assert "12 tasks, 0 failed" in stdout
    after = _task_files(out)
    assert len(after) == 12
    assert all(after[name] == text for name, text in finished.items())  # not rerun
    assert len(pd.read_csv(out / "summary.csv")) == 12


# -- atomic writes -------------------------------------------------------------------------------

class Crash(Exception):
    pass


def _half_then_crash(real_writer, path_index: int = 0):
    """A writer that writes half of the real output to its target, then raises."""

    def writer(*args, **kwargs):
        args = list(args)
        target = Path(args[path_index])
        real_writer(*args, **kwargs)
        with open(target, "r+b") as f:  # plain file I/O: Path methods may be the patched ones
            f.truncate(os.path.getsize(target) // 2)
        raise Crash("disk full half-way")

    return writer


def _assert_untouched(folder: Path, before: dict[str, bytes]) -> None:
    now = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert now == before, "a target changed or a temporary file was left behind"


def test_crash_mid_write_leaves_old_files_intact(tmp_path, monkeypatch):
    from fixtures_training import make_tuples

    import safeil_sumo.data.schema as schema_mod
    import safeil_sumo.data.tuples as tuples_mod
    import safeil_sumo.learn.checkpoint as ckpt_mod

    drive, tuples = _drive(), make_tuples()
    save_drive(drive, tmp_path / "drive.parquet")
    tuples.save(tmp_path / "tuples.parquet")
    outputs.write_json(tmp_path / "a.json", {"old": True})
    outputs.write_tables(tmp_path, drive, drive.head(2))
    _copy_shipped(tmp_path, "ck")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    real_write_table = pq.write_table
    monkeypatch.setattr(schema_mod.pq, "write_table", _half_then_crash(real_write_table, 1))
    with pytest.raises(Crash):
        save_drive(drive.assign(x=drive["x"] + 1), tmp_path / "drive.parquet")
    with pytest.raises(Crash):
        tuples_mod.Tuples.save(tuples.subset(np.arange(5)), tmp_path / "tuples.parquet")
    monkeypatch.setattr(schema_mod.pq, "write_table", real_write_table)
    _assert_untouched(tmp_path, before)

    monkeypatch.setattr(Path, "write_text", _half_then_crash(Path.write_text))
    with pytest.raises(Crash):
        outputs.write_json(tmp_path / "a.json", {"new": list(range(100))})
    monkeypatch.undo()
    _assert_untouched(tmp_path, before)

    monkeypatch.setattr(pd.DataFrame, "to_parquet", _half_then_crash(pd.DataFrame.to_parquet, 1))
    with pytest.raises(Crash):
        outputs.write_tables(tmp_path, drive.head(3), drive.head(1))
    monkeypatch.undo()
    _assert_untouched(tmp_path, before)
    monkeypatch.setattr(pd.DataFrame, "to_csv", _half_then_crash(pd.DataFrame.to_csv, 1))
    with pytest.raises(Crash):
        outputs.write_tables(tmp_path, drive.head(3), drive.head(1))
    monkeypatch.undo()
    # files are replaced one by one: steps.parquet is the new, whole table; summary.csv the old
    assert len(pd.read_parquet(tmp_path / "steps.parquet")) == 3
    before["steps.parquet"] = (tmp_path / "steps.parquet").read_bytes()
    _assert_untouched(tmp_path, before)

    from safeil_sumo.learn.model import PlannerMLP

    monkeypatch.setattr(Path, "write_bytes", _half_then_crash(Path.write_bytes))
    with pytest.raises(Crash):
        ckpt_mod.save_checkpoint(tmp_path / "ck", PlannerMLP((8,), "tanh"), name="x",
                                 horizon=2.0)
    monkeypatch.undo()
    _assert_untouched(tmp_path, before)
    load_checkpoint(tmp_path / "ck")  # still the old, consistent pair


@pytest.mark.sumo
def test_crash_while_writing_sweep_summary_keeps_task_files(tmp_path, monkeypatch):
    specs = [Task.of(net="straight", policy="analytic", max_time_s=1.0, index=i)
             for i in range(2)]
    run_sweep(specs, tmp_path, progress=False)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    tasks = _task_files(tmp_path)
    monkeypatch.setattr(pd.DataFrame, "to_csv", _half_then_crash(pd.DataFrame.to_csv, 1))
    with pytest.raises(Crash):
        run_sweep(specs, tmp_path, progress=False)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
    assert _task_files(tmp_path) == tasks


@pytest.mark.sumo
def test_failed_run_leaves_no_results_folder(tmp_path, monkeypatch, capsys):
    """A crash while assembling a run's folder (here: the plots) leaves nothing behind."""
    from safeil_sumo import run as run_cli

    def broken_plot(*args, **kwargs):
        raise Crash("plotting failed")

    monkeypatch.setattr(run_cli.plots, "plot_speed_gap", broken_plot)
    out = tmp_path / "out"
    with pytest.raises(Crash):
        run_cli.main(["--net", "straight", "--policy", "analytic", "--scenarios", "1",
                      "--out", str(out)])
    assert list(tmp_path.iterdir()) == []


# -- determinism ---------------------------------------------------------------------------------

@pytest.mark.sumo
def test_run_cli_twice_gives_identical_steps_and_summary(tmp_path, capsys):
    from safeil_sumo.run import main

    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:
        assert main(["--net", "straight", "--policy", "safeil", "--scenarios", "2", "--seed",
                     "7", "--no-plots", "--out", str(out)]) == 0
    a, b = (pd.read_parquet(o / "steps.parquet") for o in outs)
    pd.testing.assert_frame_equal(a, b, check_exact=True)
    timing = ["wall_time_s", "steps_per_s"]
    sa, sb = (pd.read_csv(o / "summary.csv").drop(columns=timing) for o in outs)
    pd.testing.assert_frame_equal(sa, sb, check_exact=True)


# -- security ------------------------------------------------------------------------------------

UNSAFE = re.compile(
    r"\bimport pickle\b|\bfrom pickle\b|\bpickle\.loads?\(|\bcPickle\b|\bdill\b|\bjoblib\b"
    r"|\bpd\.read_pickle\b|\bread_pickle\(|allow_pickle\s*=\s*True|\bshelve\b|\bmarshal\.loads?"
    r"|\btorch\.load\((?![^)]*weights_only\s*=\s*True)"
)


def test_no_pickle_anywhere_in_the_code():
    """The package, training scripts and tools never unpickle (torch.load only weights_only)."""
    sources = [*(REPO / "safeil_sumo").rglob("*.py"), *(REPO / "training").rglob("*.py")]
    assert len(sources) > 30
    hits = []
    for path in sources:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if UNSAFE.search(line):
                hits.append(f"{path.relative_to(REPO)}:{n}: {line.strip()}")
    assert hits == []
    # the scan itself catches what it should
    for bad in ("import pickle", "np.load(f, allow_pickle=True)", "torch.load(path)",
                "pd.read_pickle(p)", "import joblib"):
        assert UNSAFE.search(bad), bad
    assert not UNSAFE.search("torch.load(path, weights_only=True)")


@pytest.mark.parametrize("name", ["../../etc/passwd", "..", "a/../../b", "/abs/path", "x\\..\\y"])
def test_names_from_config_cannot_leave_the_results_folder(name, tmp_path):
    tid = task_id(Task.of(net=name + ".net.xml", policy=name))
    assert "/" not in tid and "\\" not in tid and not tid.startswith(".")
    assert (tmp_path / "tasks" / f"{tid}.json").resolve().parent == (tmp_path / "tasks")
    stem = safe_name(name)
    assert re.fullmatch(r"[A-Za-z0-9_-]+", stem)


@pytest.mark.sumo
def test_run_default_folder_name_cannot_escape(tmp_path, monkeypatch, capsys):
    """A checkpoint's name (from its sidecar) becomes part of the default results folder."""
    from safeil_sumo import run as run_cli

    evil = AnalyticPlanner()
    object.__setattr__(evil, "name", "../../../escaped")  # frozen dataclass
    monkeypatch.setattr(run_cli.planner_registry, "load", lambda name: evil)
    work = tmp_path / "a" / "b" / "c"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    assert run_cli.main(["--net", "straight", "--scenarios", "1", "--no-plots"]) == 0
    made = [p.name for p in (work / "runs").iterdir()]
    assert made == ["straight_.._.._.._escaped_seed0"]
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_dir()) == sorted(
        ["a", "b", "c", "runs", made[0]])


@pytest.mark.sumo
def test_sweep_without_scheduler_makes_no_network_connection(tmp_path):
    """No default remote address: without --scheduler dask is not imported and no socket
    connects (sockets are patched to record any attempt)."""
    code = f"""
import socket, sys
attempts = []
real = socket.socket.connect
def connect(self, address):
    attempts.append(address)
    return real(self, address)
socket.socket.connect = connect
socket.create_connection = lambda address, *a, **k: attempts.append(address)
from safeil_sumo.sweep import main
rc = main(["--net", "straight", "--policy", "analytic", "--scenarios", "1", "--max-time-s", "1",
           "--no-progress", "--out", {str(tmp_path / "out")!r}])
print("RESULT", rc, [a for a in attempts if not isinstance(a, str)],
      any(m == "dask" or m.startswith(("dask.", "distributed")) for m in sys.modules))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, check=False,
                          env={**os.environ, "DASK_SCHEDULER_ADDRESS": ""})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "RESULT 0 [] False"
