"""``safeil-train`` (safeil_sumo/train.py, learn/recipe.py, learn/stages.py, data/by_path.py):
a tiny recipe on tiny recordings written here (the OpenACC and NGSIM layouts of
tests/fixtures_data.py) trains end to end, deterministically, resumes after an interrupt, and
refuses bad recipes and data in one line; the shipped recipe states the shipped settings."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fixtures_data import (
    NGSIM_PAIRS,
    OPENACC_DIR,
    require_file,
    write_tiny_recordings,
)
from fixtures_data import (
    TINY_RECIPE as TINY,
)
from scripts import load_training_script

from safeil_sumo.data.by_path import DataSpec, parse_data_option
from safeil_sumo.learn.certificate import load_certificate
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.learn.recipe import load_recipe
from safeil_sumo.learn.stages import prepare
from safeil_sumo.learn.torch_required import TORCH_MISSING
from safeil_sumo.planners import registry as planner_registry
from safeil_sumo.train import main

REPO = Path(__file__).resolve().parents[1]
STAGE_FILES = ("openloop", "closed_loop", "lateral_refit")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with the tiny recordings and recipe, and one uninterrupted run in ``out``."""
    folder = tmp_path_factory.mktemp("tiny")
    write_tiny_recordings(folder)
    (folder / "tiny.toml").write_text(TINY.format(iters=2))
    assert _train(folder, "out") == 0
    return folder


def _train(folder: Path, out: str, *extra: str) -> int:
    return main(["--recipe", str(folder / "tiny.toml"), "--out", str(folder / out),
                 "--no-progress", *extra])


def _summary(folder: Path, out: str) -> dict:
    return json.loads((folder / out / "summary.json").read_text())


def _weights(folder: Path, out: str) -> dict[str, bytes]:
    files = {s: folder / out / "stages" / f"{s}.safetensors" for s in STAGE_FILES}
    files["final"] = folder / out / "tiny.safetensors"
    return {k: p.read_bytes() for k, p in files.items()}


def test_tiny_recipe_trains_end_to_end(tiny: Path, capsys: pytest.CaptureFixture[str]):
    out = tiny / "out"
    summary = _summary(tiny, "out")
    assert summary["seconds"] < 60.0
    assert [summary["stages"][s]["status"] for s in STAGE_FILES] == ["ran"] * 3
    assert summary["data"]["openacc"]["maneuvers"] == 8 and summary["data"]["ngsim"]["tuples"]
    assert summary["split"]["by"] == "driver" and summary["split"]["held_out_drivers"]
    assert summary["stages"]["openloop"]["losses"]["epochs_run"] == 3
    assert set(summary["certificate"]["certified"]) == {"leader", "lane"}
    assert "Held out (by driver)" in (out / "summary.md").read_text()
    # the checkpoint is what --policy PATH loads, and its certificate is valid for it
    policy = planner_registry.load(str(out / "tiny.safetensors"))
    assert isinstance(policy, MLPPolicy) and policy.name == "tiny"
    features = np.array([[1.75, 0.0, 0.0, -1.75, 0.0, 0.0, 25.0, 25.0, 40.0]])
    assert np.isfinite(policy.plan(features)).all()
    assert load_certificate(out / "tiny.safetensors").valid
    # the sidecar names the recordings (where the report card finds the held-out maneuvers)
    named = json.loads((out / "tiny.json").read_text())["training_data"]
    assert [DataSpec.from_json(d) for d in named] == list(load_recipe(tiny / "tiny.toml").data)
    # the IDM calibrated on the same training maneuvers, beside it: the report card's baseline
    fit = summary["idm"]
    assert fit["status"] == "ran" and fit["path"] == str(out / "tiny.idm.json")
    assert fit["fit_maneuvers"] + fit["held_out_maneuvers"] == sum(
        c["maneuvers"] for c in summary["data"].values())
    assert fit["held_out_maneuvers"] == len(summary["split"]["held_out_maneuvers"])
    doc = json.loads((out / "tiny.idm.json").read_text())
    assert doc["held_out_from"] == ["tiny.json"] and doc["default"] == "training"
    assert not set(doc["fits"]["training"]["maneuver_ids"]) & set(
        summary["split"]["held_out_maneuvers"])
    assert planner_registry.load(str(out / "tiny.idm.json")).name == "idm"
    assert "IDM baseline" in (out / "summary.md").read_text()


def test_the_cost_is_printed_before_training(tiny: Path, capsys: pytest.CaptureFixture[str]):
    shutil.rmtree(tiny / "dry", ignore_errors=True)
    assert _train(tiny, "dry", "--dry-run") == 0
    text = capsys.readouterr().out
    assert "stage openloop: up to 3 epochs" in text and "estimated: ~" in text
    assert "closed_loop: 2 iterations x 4 episodes of 10 s" in text
    assert not (tiny / "dry" / "stages").exists()


def test_the_same_seed_gives_bit_identical_checkpoints(tiny: Path):
    assert _train(tiny, "again") == 0
    assert _weights(tiny, "again") == _weights(tiny, "out")


def test_an_interrupt_after_stage_one_resumes_and_equals_the_uninterrupted_run(
        tiny: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]):
    import safeil_sumo.learn.finetune as finetune_module

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(finetune_module, "finetune", interrupt)
        assert _train(tiny, "resumed") == 130
    assert capsys.readouterr().err.splitlines()[-1] == "interrupted"
    stages = tiny / "resumed" / "stages"
    assert (stages / "openloop.done.json").is_file()
    assert not (stages / "closed_loop.done.json").exists()
    first = json.loads((stages / "openloop.done.json").read_text())
    assert _train(tiny, "resumed") == 0
    report = _summary(tiny, "resumed")["stages"]
    assert [report[s]["status"] for s in STAGE_FILES] == ["resumed", "ran", "ran"]
    assert report["openloop"]["finished_unix_s"] == first["finished_unix_s"]
    assert _weights(tiny, "resumed") == _weights(tiny, "out")


def test_a_changed_stage_reruns_from_it(tiny: Path):
    """The digest chains the stages: a changed closed-loop setting keeps the open loop."""
    shutil.copytree(tiny / "out", tiny / "changed")
    (tiny / "tiny.toml").write_text(TINY.format(iters=3))
    try:
        assert _train(tiny, "changed") == 0
    finally:
        (tiny / "tiny.toml").write_text(TINY.format(iters=2))
    report = _summary(tiny, "changed")["stages"]
    assert [report[s]["status"] for s in STAGE_FILES] == ["resumed", "ran", "ran"]


def test_a_renamed_recipe_retrains_nothing(tiny: Path):
    shutil.copytree(tiny / "out", tiny / "renamed")
    recipe = tiny / "renamed.toml"
    recipe.write_text(TINY.format(iters=2).replace('name = "tiny"', 'name = "other"'))
    for folder in ("openacc", "pairs.parquet"):  # the data beside the recipe, as for tiny.toml
        assert (tiny / folder).exists()
    assert main(["--recipe", str(recipe), "--out", str(tiny / "renamed"), "--no-progress"]) == 0
    report = _summary(tiny, "renamed")["stages"]
    assert [report[s]["status"] for s in STAGE_FILES] == ["resumed"] * 3
    other = tiny / "renamed" / "other.safetensors"
    assert other.read_bytes() == (tiny / "out" / "tiny.safetensors").read_bytes()
    assert planner_registry.load(str(other)).name == "other"


def test_the_open_loop_off_starts_from_init(tiny: Path):
    """From the open loop's checkpoint as ``init``: the same closed loop and refit."""
    init = tiny / "out" / "stages" / "openloop.safetensors"
    recipe = tiny / "from_init.toml"
    recipe.write_text(f'init = "{init}"\n'
                      + TINY.format(iters=2).replace("[openloop]\n", "[openloop]\nenabled = false\n"))
    assert main(["--recipe", str(recipe), "--out", str(tiny / "from_init"), "--no-progress"]) == 0
    report = _summary(tiny, "from_init")["stages"]
    assert [report[s]["status"] for s in STAGE_FILES] == ["off", "ran", "ran"]
    assert ((tiny / "from_init" / "tiny.safetensors").read_bytes()
            == (tiny / "out" / "tiny.safetensors").read_bytes())


def test_a_damaged_stage_checkpoint_is_trained_again(tiny: Path):
    shutil.copytree(tiny / "out", tiny / "damaged")
    (tiny / "damaged" / "stages" / "openloop.safetensors").write_bytes(b"half a file")
    assert _train(tiny, "damaged") == 0
    assert _summary(tiny, "damaged")["stages"]["openloop"]["status"] == "ran"
    assert _weights(tiny, "damaged") == _weights(tiny, "out")


def test_an_unknown_recipe_key_is_one_line_naming_file_and_key(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    recipe = tmp_path / "bad.toml"
    recipe.write_text('[[data]]\nformat = "ngsim"\npath = "x.parquet"\n[openloop]\nepochs = 3\n')
    with pytest.raises(SystemExit) as exc:
        main(["--recipe", str(recipe), "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    assert str(recipe) in err and "[openloop] epochs: unknown key" in err


def test_a_wrongly_typed_recipe_value_is_one_line(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]):
    recipe = tmp_path / "bad.toml"
    recipe.write_text('[closed_loop]\nstyle = "yes"\n')
    with pytest.raises(SystemExit):
        main(["--recipe", str(recipe)])
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "[closed_loop] style: expected true or false" in err


def test_an_unknown_data_format_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    with pytest.raises(SystemExit) as exc:
        main(["--data", "hdf5:x.h5", "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    assert "unknown data format 'hdf5'" in err and "openacc, ngsim, highd, csv, drive, synthetic" in err


def test_a_missing_data_path_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    with pytest.raises(SystemExit):
        main(["--data", f"ngsim:{tmp_path / 'none.parquet'}", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "does not exist" in err


def test_the_shipped_recipe_states_the_shipped_settings():
    shipped = load_training_script("train_shipped_models")
    recipe = load_recipe()
    assert recipe.name == "safeil" and recipe.seed == shipped.SEED
    assert [d.format for d in recipe.data] == ["synthetic", "openacc", "ngsim"]  # the order
    assert recipe.split.by == "maneuver" and recipe.split.fraction == 0.2
    assert recipe.openloop.config == shipped.SAFEIL_CANDIDATES["safeil_margin0"]
    assert recipe.closed_loop.config == shipped.CLOSED_LOOP
    assert recipe.closed_loop.sources == ("openacc", "ngsim")  # REAL only
    assert recipe.lateral_refit.config == shipped.LATERAL
    assert recipe.certify.time_gap_range_s == shipped.CERTIFY_TIME_GAP_S
    assert recipe.certify.max_boxes == shipped.CERTIFY_BOXES
    # the script reads these from the recipe now: its settings, written out
    ol, cl, lr = recipe.openloop.config, recipe.closed_loop.config, recipe.lateral_refit.config
    assert (ol.method, ol.barrier_lateral, ol.output_mode, ol.gap_min) == (
        "safeil", "bernstein", "residual", 0.0)
    assert (ol.envelope_weight, ol.monotone_weight, ol.monotone_margin_m) == (0.01, 1e4, 0.002)
    assert ol.longitudinal_only_sources == ("openacc",) and ol.max_epochs == 400
    assert (cl.window, cl.iters, cl.perturb, cl.settle_weight, cl.settle_after) == (
        60.0, 400, 0.5, 3.0, 20.0)
    assert cl.style and cl.towers and cl.lane_weight == cl.leader_weight == 1.0
    assert lr.lateral_mode == "lane" and lr.steps == 16000 and lr.seed == 0
    assert recipe.certify.time_gap_range_s == (0.6, 3.5) and recipe.certify.max_boxes == 400_000


def test_data_given_on_the_command_line_keep_the_stages_sources_it_has(tmp_path: Path):
    shipped = load_recipe()
    both = shipped.with_data([parse_data_option(f"ngsim:{tmp_path}"),
                              parse_data_option(f"openacc:{tmp_path}")])
    assert both.closed_loop.sources == ("openacc", "ngsim")
    one = shipped.with_data([parse_data_option(f"drive:{tmp_path}")])
    assert one.closed_loop.sources == ()  # none left: all the data


def test_a_user_recipe_inherits_the_shipped_settings(tiny: Path):
    recipe = load_recipe(tiny / "tiny.toml")
    assert recipe.openloop.config.envelope_weight == 0.01  # not set in tiny.toml
    assert recipe.closed_loop.config.towers and recipe.closed_loop.sources == ()
    assert recipe.openloop.config.max_epochs == 3


def test_the_shipped_split_of_the_real_data_is_the_shipped_models(tmp_path: Path):
    """Data by path + the recipe's split draw the held-out maneuvers the shipped checkpoint
    records for its real sources (the synthetic source is drawn last, so it cannot change
    them)."""
    require_file(NGSIM_PAIRS)
    require_file(OPENACC_DIR / "JRC-VC_280219_part2.csv.gz")
    recipe = load_recipe().with_data([parse_data_option(f"openacc:{OPENACC_DIR}"),
                                      parse_data_option(f"ngsim:{NGSIM_PAIRS}")])
    held = prepare(recipe, tmp_path, False, lambda _: None).held_out
    meta = json.loads(planner_registry.shipped_checkpoint("safeil_openloop")
                      .with_suffix(".json").read_text())
    real = {m for m in meta["metrics"]["val_maneuvers"] if not m.startswith("n74_")}
    assert set(held) == real and len(real) == 37


def test_without_torch_it_says_what_to_install(tmp_path: Path):
    from fixtures_training import HIDE_TORCH

    (tmp_path / "sitecustomize.py").write_text(HIDE_TORCH)
    env = {"PYTHONPATH": f"{tmp_path}:{REPO}", "PATH": "/usr/bin:/bin"}
    proc = subprocess.run([sys.executable, "-m", "safeil_sumo.train", "--dry-run"], env=env,
                          cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 1 and proc.stderr.strip() == TORCH_MISSING


def test_a_car_following_csv_is_data_by_path(tmp_path) -> None:
    """``--data csv:FILE`` goes through the car-following importer (default column names) and
    the paper's pipeline, like any other format."""
    from safeil_sumo.data.by_path import FORMATS, load_data, parse_data_option

    assert {"highd", "csv"} <= set(FORMATS)
    t = np.arange(0.0, 60.0, 0.1)
    v = 25.0 + np.sin(t / 5.0)
    pd.DataFrame({"time": t, "v": v, "gap": 30.0 + 2.0 * np.cos(t / 5.0),
                  "lead_v": v + 0.2}).to_csv(tmp_path / "pairs.csv", index=False)
    (drive,) = load_data([parse_data_option(f"csv:{tmp_path / 'pairs.csv'}")])
    assert len(drive) == len(t) and np.allclose(drive["v_x"], v)


def test_a_csv_column_map_and_speed_unit_from_the_recipe_or_the_command_line(tmp_path) -> None:
    """A user's CSV with its own column names and km/h speeds: mapped by the recipe's
    ``columns`` table and ``speed_unit``, or by ``--map`` / ``--speed-unit``, the same drive."""
    from fixtures_data import CSV_COLUMNS, write_car_following_csv

    from safeil_sumo.data.by_path import load_data
    from safeil_sumo.train import parse_args

    write_car_following_csv(tmp_path / "log.csv")
    cols = ", ".join(f'{k} = "{v}"' for k, v in (kv.split("=") for kv in CSV_COLUMNS.split(",")))
    (tmp_path / "r.toml").write_text(f'name = "r"\n[[data]]\nformat = "csv"\npath = "log.csv"\n'
                                     f'speed_unit = "km/h"\ncolumns = {{{cols}}}\n')
    (from_recipe,) = load_recipe(tmp_path / "r.toml").data
    _, args = parse_args(["--data", f"csv:{tmp_path / 'log.csv'}", "--map", CSV_COLUMNS,
                          "--speed-unit", "km/h"])
    (from_cli,) = args.data_specs
    assert from_recipe.columns == from_cli.columns == CSV_COLUMNS
    a, b = load_data([from_recipe, from_cli])
    raw = pd.read_csv(tmp_path / "log.csv")
    assert np.allclose(a["v_x"], raw["spd"] / 3.6) and np.allclose(b["v_x"], a["v_x"])
