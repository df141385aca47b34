"""The package as a user installs it: a wheel built from this tree, installed (not editable)
into a fresh venv, run from a folder outside the checkout. It trains a tiny recipe on tiny
recordings and evaluates the result (issue 40's end-to-end target). The venv reuses this
environment's dependencies through a path file (installing torch and SUMO again would take
minutes); the package itself, its data files and its console scripts come from the wheel."""

from __future__ import annotations

import json
import os
import site
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures_data import (
    CSV_COLUMNS,
    TINY_RECIPE,
    write_car_following_csv,
    write_tiny_recordings,
)

# every test here runs SUMO (tests/conftest.py: the sumo marker)
pytestmark = pytest.mark.sumo

REPO = Path(__file__).resolve().parents[1]



@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, str]]:
    """(the venv's bin folder, a working folder outside the checkout, the environment)."""
    root = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "--no-build-isolation", "-w", str(root / "dist"), str(REPO)], check=True)
    (wheel,) = (root / "dist").glob("safeil_sumo-*.whl")
    subprocess.run([sys.executable, "-m", "venv", str(root / "venv")], check=True)
    py = root / "venv" / "bin" / "python"
    # without PYTHONPATH: a checkout on it (with the egg-info the build leaves there) would make
    # pip take the package as installed already and skip the wheel
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", str(wheel)], check=True,
                   env=env)
    inner = subprocess.run([str(py), "-c", "import site; print(site.getsitepackages()[0])"],
                           check=True, capture_output=True, text=True).stdout.strip()
    (Path(inner) / "outer_dependencies.pth").write_text("\n".join(site.getsitepackages()))
    work = root / "work"
    write_tiny_recordings(work)
    write_car_following_csv(work / "my_log.csv", duration_s=40.0)
    (work / "no_data").mkdir()
    (work / "tiny.toml").write_text(TINY_RECIPE.format(iters=2))
    env["SAFEIL_SUMO_CACHE"] = str(root / "cache")
    return root / "venv" / "bin", work, env


def _run(bin_: Path, work: Path, env: dict[str, str], *cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(bin_ / cmd[0]), *cmd[1:]], check=False, cwd=work, env=env,
                          capture_output=True, text=True, timeout=600)


def test_the_wheel_trains_and_evaluates_outside_the_checkout(installed) -> None:
    bin_, work, env = installed
    where = _run(bin_, work, env, "python", "-c", "import safeil_sumo; print(safeil_sumo.__file__)")
    assert "site-packages" in where.stdout and str(REPO) not in where.stdout, where
    trained = _run(bin_, work, env, "safeil-train", "--recipe", "tiny.toml", "--out", "tr",
                   "--no-progress")
    assert trained.returncode == 0, trained.stderr[-2000:]
    model = work / "tr" / "tiny.safetensors"
    assert model.is_file() and (work / "tr" / "summary.json").is_file()
    assert (work / "tr" / "tiny.idm.json").is_file()  # the IDM calibrated beside it
    card = _run(bin_, work, env, "safeil-evaluate", str(model), "--quick", "--scenarios", "2",
                "--speeds-mps", "25", "--only", "safety", "gap_probe", "replay", "certificate",
                "--data", "csv:my_log.csv", "--map", CSV_COLUMNS, "--speed-unit", "km/h",
                "--data-dir", "no_data", "--out", "card")  # no OpenACC / NGSIM folder
    assert card.returncode in (0, 1), card.stderr[-2000:]  # 1: a check failed, not a crash
    report = json.loads((work / "card" / "report.json").read_text())
    ran = {s["key"]: s for s in report["sections"] if s["status"] != "not run"}
    assert set(ran) == {"safety", "gap_probe", "replay", "certificate"}, report["sections"]
    for key, section in ran.items():
        assert not section["error"] and section["numbers"] and section["commands"], key
    assert (work / "card" / "report.md").read_text().count("safeil-") >= 4
    # the user's recording, replayed beside the IDM trained with the model
    replay = ran["replay"]["numbers"]
    # the model's held-out maneuvers, found in the recordings it names (--quick: 2 per source)
    own = replay["openacc_openacc_maneuvers"] + replay["ngsim_pairs_maneuvers"]
    assert own >= 1 and replay["csv_my_log_maneuvers"] == 1
    assert replay["maneuvers"] == own + 1 and replay["failed_to_run"] == 0
    assert replay["model_gap_rmse_median_m"] >= 0 and replay["idm_gap_rmse_median_m"] >= 0
    assert any("tiny.idm.json" in note for note in ran["replay"]["notes"])
    assert any("--source csv:my_log.csv --map" in c for c in ran["replay"]["commands"])
