"""The runtime install has no torch (issue 40, "A lean install"): every planner, the main job,
the evaluation command lines and the Gymnasium envs run with torch hidden, and a training command
line says in one line what to install.

torch is hidden in fresh Python processes by a ``sitecustomize`` on ``PYTHONPATH`` whose
``sys.meta_path`` finder raises ``ModuleNotFoundError`` for ``torch`` and its submodules, as an
install without it does; the processes a command line spawns (sweep workers) inherit it.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from fixtures_training import HIDE_TORCH

from safeil_sumo.data.sources import DEFAULT_DATA_DIR
from safeil_sumo.learn.torch_required import TORCH_MISSING

pytest.importorskip("libsumo")

REPO = Path(__file__).resolve().parents[1]
HAS_DATA = all((DEFAULT_DATA_DIR / d).is_dir() for d in ("ngsim_i80", "openacc_vicolungo"))


@pytest.fixture(scope="module")
def no_torch(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """The environment of a Python process without torch (this repository's package first)."""
    site = tmp_path_factory.mktemp("no_torch")
    (site / "sitecustomize.py").write_text(HIDE_TORCH)
    paths = [str(site), str(REPO), os.environ.get("PYTHONPATH", "")]
    return dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in paths if p))


def _python(env: dict[str, str], *args: str, timeout: float = 300.0
            ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *args], env=env, cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, check=False)


def _ok(proc: subprocess.CompletedProcess[str]) -> str:
    assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout[-2000:]}{proc.stderr}"
    return proc.stdout


def _need_data() -> None:
    if not HAS_DATA:
        if os.environ.get("CI"):
            pytest.fail(f"the shared data is missing ({DEFAULT_DATA_DIR})")
        pytest.skip(f"needs the shared data ({DEFAULT_DATA_DIR})")


def test_the_hidden_torch_cannot_be_imported(no_torch):
    proc = _python(no_torch, "-c", "import torch.nn")
    assert proc.returncode == 1 and "ModuleNotFoundError: No module named 'torch" in proc.stderr


PLAN_EVERY_PLANNER = '''\
import sys

import numpy as np

from safeil_sumo.planners import registry as reg
from safeil_sumo.core.features import planner_features

f = planner_features([1.75, 0.0, 1e-3], [-1.75, 0.0, 1e-3], 30.0, 27.0, 45.0)
for name in reg.NAMES:
    policy = reg.load(name)
    if reg.has_time_gap(policy):
        policy = reg.with_time_gap(policy, 2.0)
    plan = np.asarray(policy.plan(f), float)
    assert plan.size and np.all(np.isfinite(plan)), (name, plan)
    print(name, "planned")
print("torch imported:", "torch" in sys.modules)
'''


def test_every_shipped_planner_loads_and_plans_without_torch(no_torch):
    from safeil_sumo.planners.registry import NAMES, SHIPPED

    out = _ok(_python(no_torch, "-c", PLAN_EVERY_PLANNER))
    assert [line.split()[0] for line in out.splitlines()[:-1]] == list(NAMES)
    assert set(SHIPPED) <= set(NAMES) and "safeil" in NAMES
    assert out.splitlines()[-1] == "torch imported: False"


@pytest.mark.sumo
def test_the_main_job_runs_in_sumo_without_torch(no_torch, tmp_path):
    """``python -m safeil_sumo.run --net curved500`` (the shipped safeil), 2 scenarios of 5 s."""
    out = _ok(_python(no_torch, "-m", "safeil_sumo.run", "--net", "curved500", "--scenarios",
                      "2", "--max-time-s", "5", "--no-plots", "--out", str(tmp_path)))
    assert re.search(r"^safeil: \d/2 scenarios completed without a flag", out, re.MULTILINE)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert [(s["scenario"], s["policy"], s["error"]) for s in summary] == [
        ("s0000", "safeil", ""), ("s0001", "safeil", "")]
    assert (tmp_path / "steps.parquet").stat().st_size > 0


@pytest.mark.sumo
@pytest.mark.parametrize("argv", [
    ("safeil_sumo.sweep", "--policy", "safeil", "bc", "--scenarios", "2", "--max-time-s", "3",
     "--workers", "2"),
    ("safeil_sumo.falsify", "--policy", "safeil", "--budget-sims", "2", "--batch", "2",
     "--max-time-s", "3", "--no-progress"),
    ("safeil_sumo.certify", "--policy", "safeil", "--budget-s", "2", "--no-progress"),
    ("safeil_sumo.replay", "--source", "openacc", "--policy", "safeil", "safeil_paper",
     "--duration-s", "5", "--workers", "1"),
], ids=lambda argv: argv[0].removeprefix("safeil_sumo."))
def test_the_evaluation_command_lines_run_without_torch(no_torch, tmp_path, argv):
    if argv[0] == "safeil_sumo.replay":
        _need_data()
    out = _ok(_python(no_torch, "-m", *argv, "--out", str(tmp_path)))
    assert str(tmp_path) in out


STEP_EVERY_ENV = '''\
import sys

import gymnasium as gym

import safeil_sumo.envs as envs

skip = set(envs.DATA_IDS) if sys.argv[1] == "no-data" else set()
for env_id in envs.IDS:
    if env_id in skip:
        continue
    env = gym.make(env_id, max_time_s=3.0)
    env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(3):
        env.step(env.action_space.sample())
    env.close()
    print(env_id, "stepped")
venv = gym.make_vec("safeil_sumo/Curved500-v0", num_envs=2,
                    vectorization_mode="vector_entry_point", max_time_s=3.0)
venv.reset(seed=0)
venv.action_space.seed(0)
for _ in range(3):
    venv.step(venv.action_space.sample())
venv.close()
print("vector env stepped")
print("torch imported:", "torch" in sys.modules)
'''


@pytest.mark.sumo
def test_every_gymnasium_env_steps_without_torch(no_torch):
    from safeil_sumo import envs

    if not HAS_DATA and os.environ.get("CI"):
        _need_data()  # fails: CI has the data; elsewhere the data's envs are left out
    out = _ok(_python(no_torch, "-c", STEP_EVERY_ENV, "data" if HAS_DATA else "no-data"))
    stepped = [line.split()[0] for line in out.splitlines() if line.endswith(" stepped")]
    expected = [i for i in envs.IDS if HAS_DATA or i not in envs.DATA_IDS]
    assert stepped == [*expected, "vector"]
    assert out.splitlines()[-1] == "torch imported: False"


@pytest.mark.parametrize("script", ["train", "closed_loop_finetune", "refit_lateral",
                                    "train_shipped_models", "leave_one_driver_out"])
def test_a_training_command_line_without_torch_says_so_in_one_line(no_torch, script):
    proc = _python(no_torch, str(REPO / "training" / f"{script}.py"), "--help")
    assert proc.returncode == 1
    assert proc.stderr == TORCH_MISSING + "\n" and proc.stdout == ""


def test_training_imports_turns_only_a_missing_torch_into_the_one_line_exit():
    from safeil_sumo.learn.torch_required import training_imports

    with pytest.raises(SystemExit) as exit_, training_imports():
        raise ModuleNotFoundError("No module named 'torch.nn'", name="torch.nn")
    assert exit_.value.code == TORCH_MISSING
    with pytest.raises(ModuleNotFoundError, match="torchvision"), training_imports():
        raise ModuleNotFoundError("No module named 'torchvision'", name="torchvision")
