"""The shipped training recipes (``training/train_shipped_models.py``) are configs turned into
command lines in one place (``option_argv``). A dry check, no training: the commands built from
the configs parse into exactly what the command-line lists they replaced parsed into, so the
shipped weights (deterministic for the same options) are unchanged."""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path

import pytest

from safeil_sumo.learn.closed_loop import FinetuneConfig
from safeil_sumo.learn.trainer import TrainConfig

REPO = Path(__file__).resolve().parents[1]


def _load_script(name: str):
    """A training script (``training/<name>.py``, not a package module) as a module."""
    spec = importlib.util.spec_from_file_location(name, REPO / "training" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


shipped = _load_script("train_shipped_models")
train_cli = _load_script("train")
finetune_cli = _load_script("closed_loop_finetune")

# the recipes as they were before they became configs (verbatim)
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
                   "--seed", "0"]
DATA = ["synthetic.parquet", "openacc.parquet", "ngsim.parquet"]


def old_train_command(extra: list[str], out: Path, stored_name: str) -> list[str]:
    """``_train_all``'s command before the recipes were configs."""
    return [sys.executable, str(REPO / "training" / "train.py"), "--data", *DATA,
            "--seed", "0", "--name", stored_name, "--out", str(out), "--no-progress", *extra]


def old_finetune_command(init: Path, out: Path) -> list[str]:
    return [sys.executable, str(REPO / "training" / "closed_loop_finetune.py"),
            "--init", str(init), "--data", *DATA, "--out", str(out), "--no-progress",
            *OLD_CLOSED_LOOP]


@pytest.mark.parametrize("name", sorted(OLD_OPEN_LOOP))
def test_open_loop_recipes_give_the_commands_they_replaced(name):
    """The same script, and every option (config, data, name, output) parsed equal."""
    config = {**shipped.SAFEIL_CANDIDATES, **shipped.OTHERS}[name]
    new = shipped.train_command(config, DATA, Path("work") / name, "safeil")
    old = old_train_command(OLD_OPEN_LOOP[name], Path("work") / name, "safeil")
    assert new[:2] == old[:2]
    assert vars(train_cli.parse_args(new[2:])) == vars(train_cli.parse_args(old[2:]))
    assert train_cli.config_of(train_cli.parse_args(new[2:])) == config


def test_closed_loop_recipe_gives_the_command_it_replaced():
    new = shipped.finetune_command(shipped.CLOSED_LOOP, Path("init.safetensors"), DATA,
                                   Path("work/safeil"))
    old = old_finetune_command(Path("init.safetensors"), Path("work/safeil"))
    assert new[:2] == old[:2]
    parser = finetune_cli.build_parser()
    assert vars(parser.parse_args(new[2:])) == vars(parser.parse_args(old[2:]))


@pytest.mark.parametrize("config", [
    TrainConfig(method="bc", hidden=(32, 16), activation="relu", lr=1 / 3, weight_decay=0.01,
                batch_size=0, max_epochs=7, patience=3, seed=5, barrier_k=10.0, track=1.9,
                gap_min=2.0, time_gap=0.1 + 0.2, barrier_samples=4,
                barrier_control_points=False, num_threads=2, barrier_lateral="bernstein",
                output_mode="residual", longitudinal_only_sources=("openacc", "ngsim"),
                lateral_only_sources=("synthetic",), envelope_weight=0.1, envelope_batch=32,
                monotone_weight=3.0, monotone_margin_m=0.002),
    FinetuneConfig(window=8.0, stride=4.0, iters=2, batch=4, lr=1e-5 / 3, speed_weight=0.5,
                   lateral_weight=1.0, anchor_envelope=False, lane_weight=0.5,
                   leader_weight=0.25,
                   equilibrium_weight=1.0, perturb=0.5, settle_weight=1.0,
                   settle_after=2.0, style=True, seed=7),
], ids=["train", "finetune"])
def test_option_argv_round_trips_every_field(config):
    """Every field changed from its default (bools off and on, tuples of ints and of strings,
    floats with no short decimal form) comes back bit for bit through the script's parser."""
    default = type(config)()
    for f in dataclasses.fields(config):
        assert getattr(config, f.name) != getattr(default, f.name), f.name  # all covered
    if isinstance(config, TrainConfig):
        argv = ["--data", "x", "--out", "o", *shipped.option_argv(config)]
        assert train_cli.config_of(train_cli.parse_args(argv)) == config
    else:
        argv = ["--data", "x", "--out", "o", *shipped.option_argv(config)]
        args = finetune_cli.build_parser().parse_args(argv)
        assert FinetuneConfig(**{f.name: getattr(args, f.name)
                                 for f in dataclasses.fields(FinetuneConfig)}) == config
    assert shipped.option_argv(default) == []  # a default config needs no option


def test_finetune_refuses_settling_without_style(capsys):
    """The config's rule is the command line's usage error (exit 2), before any data is read."""
    with pytest.raises(SystemExit) as exc:
        finetune_cli.main(["--data", "x", "--out", "o", "--settle-weight", "1"])
    assert exc.value.code == 2
    assert "needs style" in capsys.readouterr().err
