"""The shipped training recipes (``training/train_shipped_models.py``) are configs trained
in-process: :func:`safeil_sumo.learn.trainer.train_checkpoint` and
:func:`safeil_sumo.learn.finetune.finetune`, whose command lines are ``training/train.py`` and
``training/closed_loop_finetune.py``.

- The recipes are the configs the command lines they replaced built (dry, no training), so the
  shipped weights (deterministic for the same config) are unchanged.
- A function and its command line give the same checkpoint for a tiny config: the weights bit
  for bit, every metadata field equal but the timings (and so does the recipes' process pool).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file
from scripts import load_training_script

from safeil_sumo.cli_args import dataclass_from_args
from safeil_sumo.learn.checkpoint import save_checkpoint
from safeil_sumo.learn.closed_loop import FinetuneConfig
from safeil_sumo.learn.finetune import finetune
from safeil_sumo.learn.model import PlannerMLP
from safeil_sumo.learn.trainer import TrainConfig, train_checkpoint

REPO = Path(__file__).resolve().parents[1]




shipped = load_training_script("train_shipped_models")
train_cli = load_training_script("train")
finetune_cli = load_training_script("closed_loop_finetune")

# the recipes as command lines, before they became configs (verbatim)
OLD_MIXED = ["--longitudinal-only-sources", "openacc"]
OLD_SAFEIL = [*OLD_MIXED, "--method", "safeil", "--barrier-lateral", "bernstein", "--output-mode",
              "residual", "--envelope-weight", "0.01", "--monotone-weight", "10000",
              "--monotone-margin", "0.002"]
OLD_OPEN_LOOP = {
    "safeil_margin0": [*OLD_SAFEIL],
    "safeil_margin2m": [*OLD_SAFEIL, "--gap-min", "2"],
    "safeil_paper": [*OLD_MIXED, "--method", "safeil", "--barrier-lateral", "control_points"],
    "bc": [*OLD_MIXED, "--method", "bc", "--output-mode", "residual"],
}
OLD_CLOSED_LOOP = ["--window", "60", "--iters", "400", "--style", "--equilibrium-weight", "1",
                   "--perturb", "0.5", "--settle-weight", "3", "--settle-after", "20",
                   "--lane-weight", "1", "--leader-weight", "1", "--towers", "--seed", "0"]
DATA = ["synthetic.parquet", "openacc.parquet", "ngsim.parquet"]


@pytest.mark.parametrize("name", sorted(OLD_OPEN_LOOP))
def test_open_loop_recipes_are_the_command_lines_they_replaced(name):
    config = {**shipped.SAFEIL_CANDIDATES, **shipped.OTHERS}[name]
    old = ["--data", *DATA, "--seed", "0", "--out", "o", *OLD_OPEN_LOOP[name]]
    assert train_cli.config_of(train_cli.parse_args(old)) == config


def test_closed_loop_recipe_is_the_command_line_it_replaced():
    args = finetune_cli.build_parser().parse_args(["--data", *DATA, "--out", "o",
                                                   *OLD_CLOSED_LOOP])
    assert dataclass_from_args(FinetuneConfig, args) == shipped.CLOSED_LOOP


def test_finetune_cli_parses_every_field_under_its_own_name():
    """Every field changed from its default (bools off and on, floats with no short decimal
    form) comes back bit for bit through the script's parser."""
    config = FinetuneConfig(window=8.0, stride=4.0, iters=2, batch=4, lr=1e-5 / 3,
                            speed_weight=0.5, lateral_weight=1.0, anchor_envelope=False,
                            lane_weight=0.5, leader_weight=0.25, equilibrium_weight=1.0,
                            perturb=0.5, settle_weight=1.0, settle_after=2.0, style=True,
                            towers=True, seed=7)
    default = FinetuneConfig()
    for f in dataclasses.fields(config):
        assert getattr(config, f.name) != getattr(default, f.name), f.name  # all covered
    argv = ["--data", "x", "--out", "o", "--window", "8.0", "--stride", "4.0", "--iters", "2",
            "--batch", "4", "--lr", repr(1e-5 / 3), "--speed-weight", "0.5",
            "--lateral-weight", "1.0", "--no-anchor-envelope", "--lane-weight", "0.5",
            "--leader-weight", "0.25", "--equilibrium-weight", "1.0", "--perturb", "0.5",
            "--settle-weight", "1.0", "--settle-after", "2.0", "--style", "--towers", "--seed",
            "7"]
    args = finetune_cli.build_parser().parse_args(argv)
    assert dataclass_from_args(FinetuneConfig, args) == config
    assert dataclass_from_args(FinetuneConfig, finetune_cli.build_parser().parse_args(
        ["--data", "x", "--out", "o"])) == default


def test_finetune_refuses_settling_without_style(capsys):
    """The config's rule is the command line's usage error (exit 2), before any data is read."""
    with pytest.raises(SystemExit) as exc:
        finetune_cli.main(["--data", "x", "--out", "o", "--settle-weight", "1"])
    assert exc.value.code == 2
    assert "needs style" in capsys.readouterr().err


# ------------------------------------------------- the functions against their command lines

# run-to-run differences: wall times, the file's own name and creation time, and the weights
# file's hash (safetensors writes its metadata map in no fixed order; the weights are compared)
VOLATILE = {"created_unix_s", "weights_file", "weights_sha256"}


def _without_timings(meta: dict) -> dict:
    meta = {k: v for k, v in meta.items() if k not in VOLATILE}
    if "training" in meta:
        meta["training"] = {k: v for k, v in meta["training"].items()
                            if k not in ("seconds", "samples_per_s")}
        meta["history"] = [{k: v for k, v in e.items() if k != "seconds"}
                           for e in meta["history"]]
    for stage in ("closed_loop", "lateral_refit"):
        run = meta["metrics"].get(stage)
        if run is not None:
            meta["metrics"][stage] = {k: v for k, v in run.items() if k != "seconds"}
    return meta


def assert_same_checkpoint(a: Path, b: Path) -> None:
    wa, wb = load_file(a.with_suffix(".safetensors")), load_file(b.with_suffix(".safetensors"))
    assert sorted(wa) == sorted(wb)
    assert all(np.array_equal(wa[k], wb[k]) for k in wa)
    ma = json.loads(a.with_suffix(".json").read_text())
    mb = json.loads(b.with_suffix(".json").read_text())
    assert list(ma) == list(mb) and list(ma["metrics"]) == list(mb["metrics"])
    assert _without_timings(ma) == _without_timings(mb)


def _run_script(name: str, *args: str) -> None:
    proc = subprocess.run([sys.executable, str(REPO / "training" / f"{name}.py"), *args],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    from fixtures_training import make_tuples

    path = tmp_path_factory.mktemp("tiny") / "tuples.parquet"
    make_tuples(n_maneuvers=6, per_maneuver=30).save(path)
    return path


TINY_SAFEIL = TrainConfig(method="safeil", max_epochs=3, seed=2, barrier_lateral="bernstein",
                          output_mode="residual", envelope_weight=0.01, monotone_weight=1.0)
TINY_SAFEIL_ARGV = ["--method", "safeil", "--max-epochs", "3", "--seed", "2",
                    "--barrier-lateral", "bernstein", "--output-mode", "residual",
                    "--envelope-weight", "0.01", "--monotone-weight", "1"]
TINY_BC = TrainConfig(method="bc", max_epochs=2, seed=1)
TINY_BC_ARGV = ["--method", "bc", "--max-epochs", "2", "--seed", "1"]


def test_train_checkpoint_gives_the_command_lines_checkpoint(tiny_data, tmp_path):
    """In this process, in a fresh one (the script) and through the recipes' process pool (two
    trainings at once in spawned workers): the same checkpoints."""
    for config, argv in ((TINY_SAFEIL, TINY_SAFEIL_ARGV), (TINY_BC, TINY_BC_ARGV)):
        assert train_cli.config_of(train_cli.parse_args(
            ["--data", "x", "--out", "o", *argv])) == config
    _run_script("train", "--data", str(tiny_data), *TINY_SAFEIL_ARGV, "--name", "safeil",
                "--out", str(tmp_path / "cli_safeil"), "--no-progress")
    result = train_checkpoint(TINY_SAFEIL, [tiny_data], tmp_path / "fn_safeil", "safeil")
    assert result.prefix == tmp_path / "fn_safeil"
    assert result.metrics == json.loads((tmp_path / "fn_safeil.json").read_text())["metrics"]
    assert "6 maneuvers" in result.notes[0]
    assert_same_checkpoint(tmp_path / "fn_safeil", tmp_path / "cli_safeil")
    train_checkpoint(TINY_BC, [tiny_data], tmp_path / "fn_bc")

    pool = tmp_path / "pool"
    shipped_paths = {"WORK": pool, "SYNTHETIC": tiny_data, "REAL": ()}
    saved = {k: getattr(shipped, k) for k in shipped_paths}
    try:
        for k, v in shipped_paths.items():
            setattr(shipped, k, v)
        prefixes = shipped._train_all({"a": (TINY_SAFEIL, "safeil"), "b": (TINY_BC, "bc")}, 2)
    finally:
        for k, v in saved.items():
            setattr(shipped, k, v)
    assert prefixes == {"a": pool / "a", "b": pool / "b"}
    assert_same_checkpoint(pool / "a", tmp_path / "cli_safeil")
    assert_same_checkpoint(pool / "b", tmp_path / "fn_bc")


def test_finetune_gives_the_command_lines_checkpoint(tmp_path):
    """A tiny fine-tune (3 iterations, style, perturbed starts, settling) in this process and in
    a fresh one (the script): the same checkpoint."""
    import torch
    from fixtures_training import make_tuples

    tup = make_tuples(n_maneuvers=4, per_maneuver=60, curved=True)  # 15 s maneuvers
    data = tmp_path / "tuples.parquet"
    tup.save(data)
    torch.manual_seed(0)
    model = PlannerMLP(output_mode="residual")
    model.set_scaling(tup.features, tup.control_points)
    held = [str(np.unique(tup.maneuver_id)[0])]
    save_checkpoint(tmp_path / "init", model, name="safeil", horizon=5.0,
                    train_config=TrainConfig(envelope_weight=0.01, monotone_weight=1.0,
                                             output_mode="residual",
                                             barrier_lateral="bernstein"),
                    metrics={"val_maneuvers": held})
    config = FinetuneConfig(window=8.0, stride=4.0, iters=3, batch=4, style=True, perturb=0.5,
                            equilibrium_weight=1.0, settle_weight=1.0)
    init = tmp_path / "init.safetensors"
    _run_script("closed_loop_finetune", "--init", str(init), "--data", str(data),
                "--window", "8", "--stride", "4", "--iters", "3", "--batch", "4", "--style",
                "--perturb", "0.5", "--equilibrium-weight", "1", "--settle-weight", "1",
                "--out", str(tmp_path / "cli"), "--no-progress")
    threads = torch.get_num_threads()
    result = finetune(config, init, [data], tmp_path / "fn")
    assert torch.get_num_threads() == threads  # restored
    assert result.metrics["closed_loop"]["iters"] == 3 and "episodes" in result.notes[0]
    assert_same_checkpoint(tmp_path / "fn", tmp_path / "cli")


def test_lateral_refit_gives_the_command_lines_checkpoint(tmp_path):
    """A tiny lateral refit in this process and through ``training/refit_lateral.py`` in a fresh
    one: the same checkpoint; the recipe's config is the default one at the shipped seed."""
    from fixtures_training import towers_checkpoint

    from safeil_sumo.learn.lateral_refit import LateralRefitConfig, refit_lateral

    data = towers_checkpoint(tmp_path)
    init, ref = tmp_path / "towers.safetensors", tmp_path / "ref.safetensors"
    _run_script("refit_lateral", "--init", str(init), "--reference", str(ref), "--data",
                str(data), "--steps", "5", "--batch", "32", "--out", str(tmp_path / "cli"),
                "--no-progress")
    refit_lateral(LateralRefitConfig(steps=5, batch=32), init, ref, [data], tmp_path / "fn")
    assert_same_checkpoint(tmp_path / "fn", tmp_path / "cli")
    assert shipped.LATERAL.seed == shipped.SEED
