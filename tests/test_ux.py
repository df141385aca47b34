"""Things a new user trips on: --gui without a display, workers outliving a killed sweep, the
multi-edge network message."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import psutil
import pytest

from safeil_sumo import run as run_cli
from safeil_sumo.roads.road import NetworkError, load_road
from safeil_sumo.sim import sumo_api


def test_gui_without_a_display_fails_fast_with_one_line(monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)

    def no_sumo(*args, **kwargs):
        raise AssertionError("SUMO was started: the display check must come first")

    # fast means before any SUMO starts (no wall-clock bound: a loaded machine is slower)
    monkeypatch.setattr(sumo_api, "start", no_sumo)
    with pytest.raises(SystemExit) as exc:
        run_cli.main(["--gui", "--scenarios", "1", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    assert "error: --gui needs a display" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.sumo
def test_workers_die_with_a_killed_sweep(tmp_path) -> None:
    cmd = [sys.executable, "-m", "safeil_sumo.sweep", "--net", "straight", "--policy",
           "analytic", "--scenarios", "40", "--workers", "2", "--no-progress", "--out",
           str(tmp_path / "sw")]
    parent = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    proc = psutil.Process(parent.pid)
    workers: list[psutil.Process] = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(workers) < 2:
        workers = proc.children(recursive=True)
        time.sleep(0.2)
    assert len(workers) >= 2, "the sweep did not start its workers"
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    _, alive = psutil.wait_procs(workers, timeout=10)
    assert not alive, f"workers outlived their sweep: {[p.pid for p in alive]}"


def test_a_multi_edge_network_names_no_option_that_does_not_exist() -> None:
    from pathlib import Path

    n74 = Path(__file__).resolve().parents[1] / "sumo_scenarios" / "n74" / "n74.net.xml"
    with pytest.raises(NetworkError) as exc:
        load_road(n74)
    msg = str(exc.value)
    assert "single-edge" in msg and "name the edge" not in msg
    assert "--route EDGE [EDGE ...]" in msg  # an option that exists (run and sweep)


def test_a_toml_sweep_equals_the_same_sweep_from_flags(tmp_path, capsys) -> None:
    from safeil_sumo import sweep as cli

    study = tmp_path / "study.toml"
    study.write_text('net = ["straight", "curved500"]\npolicy = ["analytic"]\nscenarios = 3\n'
                     'seed = 4\nleader = "braking"\ngap_range_m = [20, 60]\nstop_on_flag = true\n')
    flags = ["--net", "straight", "curved500", "--policy", "analytic", "--scenarios", "3",
             "--seed", "4", "--leader", "braking", "--gap-range-m", "20", "60", "--stop-on-flag"]
    a = cli.build_tasks(cli.parse_args(["--config", str(study)]))
    b = cli.build_tasks(cli.parse_args(flags))
    assert a == b and len(a) == 6
    # flags on the command line override the file
    c = cli.build_tasks(cli.parse_args(["--config", str(study), "--scenarios", "1"]))
    assert len(c) == 2
    # the shipped study files parse
    from pathlib import Path

    for f in sorted((Path(__file__).resolve().parents[1] / "sumo_scenarios" / "studies")
                    .glob("*.toml")):
        assert cli.build_tasks(cli.parse_args(["--config", str(f)]))
    # a bad file: one error line, exit 2
    bad = tmp_path / "bad.toml"
    bad.write_text("scenarios = \n")
    with pytest.raises(SystemExit) as exc:
        cli.parse_args(["--config", str(bad)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"python -m safeil_sumo.sweep: error: {bad}: ") and err.count("\n") == 1
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("nope = 1\n")
    with pytest.raises(SystemExit) as exc:
        cli.parse_args(["--config", str(unknown)])
    assert exc.value.code == 2 and f"{unknown}: unknown key 'nope'" in capsys.readouterr().err


def test_api_rejects_what_is_no_policy() -> None:
    from safeil_sumo import api

    with pytest.raises(TypeError, match="no Policy"):
        api.load_policy(object())
