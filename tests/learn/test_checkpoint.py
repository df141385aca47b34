"""Checkpoints: round trip, refusal of bad files, and numpy inference == torch."""

from __future__ import annotations

import json
import pickle
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_training import make_tuples

from safeil_sumo.core.policy import Policy
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import (
    CheckpointError,
    checkpoint_paths,
    load_checkpoint,
    load_model,
    save_checkpoint,
    tuples_fingerprint,
)
from safeil_sumo.learn.inference import MLPPolicy, load_policy
from safeil_sumo.learn.model import PlannerMLP
from safeil_sumo.learn.trainer import TrainConfig, split_by_maneuver, train


@pytest.fixture(scope="module")
def data() -> Tuples:
    return make_tuples(n_maneuvers=6, per_maneuver=20, seed=3)


@pytest.fixture(scope="module")
def trained(data: Tuples) -> tuple[PlannerMLP, TrainConfig, object]:
    tr, va = split_by_maneuver(data, 0.3, seed=0)
    cfg = TrainConfig(max_epochs=15, batch_size=64, lr=3e-3)
    model, hist = train(tr, va, cfg, progress=False)
    return model, cfg, hist


@pytest.fixture()
def ckpt(tmp_path: Path, data: Tuples, trained) -> Path:
    model, cfg, hist = trained
    prefix = tmp_path / "safeil"
    save_checkpoint(prefix, model, name="safeil", horizon=data.horizon, train_config=cfg,
                    data_fingerprint=tuples_fingerprint(data), metrics={"x": 1.5, "nan": np.nan},
                    history=hist)
    return prefix


def test_round_trip(ckpt: Path, data: Tuples, trained) -> None:
    model = trained[0]
    loaded, meta = load_model(ckpt)
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k
    f = torch.as_tensor(data.features, dtype=torch.float32)
    assert torch.equal(model(f), loaded(f))
    assert meta["name"] == "safeil" and meta["horizon_s"] == data.horizon
    assert meta["architecture"] == model.architecture
    assert TrainConfig.from_dict(meta["train_config"]) == trained[1]
    assert meta["data_fingerprint"] == tuples_fingerprint(data)
    assert meta["metrics"] == {"x": 1.5, "nan": None}
    assert len(meta["history"]) == meta["training"]["epochs_run"]
    # any of the three spellings of the path works
    for p in (ckpt, ckpt.with_name("safeil.safetensors"), ckpt.with_name("safeil.json")):
        arrays, _ = load_checkpoint(p)
        assert arrays["net.0.weight"].shape == (64, 9)


def test_fingerprint_sees_any_change(data: Tuples) -> None:
    f0 = tuples_fingerprint(data)
    assert f0 == tuples_fingerprint(data.subset(np.arange(len(data))))
    changed = data.subset(np.arange(len(data)))
    changed.future[0, 0, 0] += 1e-9
    assert tuples_fingerprint(changed) != f0


def test_truncated_weights(ckpt: Path) -> None:
    weights, _ = checkpoint_paths(ckpt)
    weights.write_bytes(weights.read_bytes()[:-100])
    with pytest.raises(CheckpointError, match="truncated|sha256"):
        load_checkpoint(ckpt)
    weights.write_bytes(b"")
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(ckpt)


def test_pickle_renamed_to_safetensors_is_never_unpickled(ckpt: Path, tmp_path: Path) -> None:
    weights, _ = checkpoint_paths(ckpt)
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            return (marker.touch, ())

    weights.write_bytes(pickle.dumps(Evil()))
    with pytest.raises(CheckpointError, match="pickle"):
        load_checkpoint(ckpt)
    assert not marker.exists()


def test_other_formats_renamed(ckpt: Path, tmp_path: Path, data: Tuples) -> None:
    weights, sidecar = checkpoint_paths(ckpt)
    data.save(tmp_path / "t.parquet")
    weights.write_bytes((tmp_path / "t.parquet").read_bytes())
    with pytest.raises(CheckpointError, match="Parquet"):
        load_checkpoint(ckpt)
    weights.write_bytes(b"PK\x03\x04" + b"\x00" * 100)  # a torch.save zip
    with pytest.raises(CheckpointError, match="zip"):
        load_checkpoint(ckpt)
    # a sidecar that is not ours
    sidecar.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(CheckpointError, match="sidecar"):
        load_checkpoint(ckpt)
    sidecar.write_bytes(b"\x80\x04garbage")
    with pytest.raises(CheckpointError, match="JSON"):
        load_checkpoint(ckpt)


def test_missing_files(tmp_path: Path, ckpt: Path) -> None:
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nothing")
    checkpoint_paths(ckpt)[0].unlink()
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(ckpt)


def test_other_architecture(ckpt: Path, tmp_path: Path, data: Tuples) -> None:
    # sidecar claims 32-wide layers, the weights are 64-wide
    _, sidecar = checkpoint_paths(ckpt)
    meta = json.loads(sidecar.read_text())
    meta["architecture"]["hidden"] = [32, 32]
    sidecar.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="shape"):
        load_checkpoint(ckpt)
    # a valid checkpoint of another architecture, with a copied sidecar
    small = PlannerMLP(hidden=(16,))
    other = tmp_path / "other"
    save_checkpoint(other, small, name="x", horizon=data.horizon)
    checkpoint_paths(ckpt)[0].write_bytes(checkpoint_paths(other)[0].read_bytes())
    meta["architecture"]["hidden"] = [64, 64]
    meta["weights_sha256"] = json.loads(checkpoint_paths(other)[1].read_text())["weights_sha256"]
    sidecar.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="architecture"):
        load_checkpoint(ckpt)


def test_wrong_format_version(ckpt: Path) -> None:
    _, sidecar = checkpoint_paths(ckpt)
    meta = json.loads(sidecar.read_text())
    meta["format_version"] = 99
    sidecar.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="version"):
        load_checkpoint(ckpt)


def test_safetensors_with_header_length_looking_like_pickle(tmp_path: Path) -> None:
    """The first byte of a safetensors file is its header length: 0x80 must not read as pickle."""
    from safeil_sumo.learn.checkpoint import _sniff

    header = b"{" + b" " * 126 + b"}"
    blob = struct.pack("<Q", len(header)) + header
    assert blob[:1] == b"\x80" and _sniff(blob) is None


# ---------------------------------------------------------------- numpy inference

@pytest.mark.parametrize("activation", ["tanh", "relu"])
def test_numpy_policy_equals_torch(activation: str, data: Tuples, tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = PlannerMLP(activation=activation)
    model.set_scaling(data.features, data.control_points)
    with torch.no_grad():  # non-trivial last layer (it starts at zero)
        torch.nn.init.normal_(model.net[-1].weight, std=0.3)
    save_checkpoint(tmp_path / "m", model, name="bc", horizon=data.horizon)
    policy = load_policy(tmp_path / "m")
    assert isinstance(policy, Policy) and policy.name == "bc" and policy.horizon == data.horizon
    f = data.features
    with torch.no_grad():
        ref32 = model(torch.as_tensor(f, dtype=torch.float32)).numpy()
        ref64 = model.double()(torch.as_tensor(f)).numpy()
    out = policy.plan(f)
    assert out.shape == (len(f), 3, 2)
    np.testing.assert_allclose(out, ref64, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out, ref32, rtol=1e-5, atol=1e-5 * np.abs(ref32).max())
    # single sample, nested batch shapes, lists, float32 inputs
    np.testing.assert_allclose(policy.plan(f[3]), out[3], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(policy.plan(f[:6].reshape(2, 3, 9)), out[:6].reshape(2, 3, 3, 2),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(policy.plan(list(f[0])), out[0], rtol=1e-12, atol=1e-12)
    assert policy.plan(f[0].astype(np.float32)).shape == (3, 2)
    with pytest.raises(ValueError):
        policy.plan(np.zeros(8))


def test_single_sample_plans_are_not_overwritten(data: Tuples, tmp_path: Path) -> None:
    model = PlannerMLP()
    model.set_scaling(data.features, data.control_points)
    policy = MLPPolicy({k: v.numpy() for k, v in model.state_dict().items()},
                       model.architecture, "x", data.horizon)
    a = policy.plan(data.features[0])
    a_copy = a.copy()
    policy.plan(data.features[1] * 2)
    np.testing.assert_array_equal(a, a_copy)


def test_the_same_weights_give_the_same_file_in_every_process(tmp_path: Path) -> None:
    """safetensors writes its metadata map in hash order, which changes between processes (and
    between maps in one process): the weights file of one model, saved in fresh processes,
    must still be byte-identical (its sha256 keys caches and certificates)."""
    import subprocess
    import sys

    script = (
        "import sys, torch\n"
        "from safeil_sumo.learn.checkpoint import save_checkpoint\n"
        "from safeil_sumo.learn.model import PlannerMLP\n"
        "for k in range(4):\n"
        "    torch.manual_seed(0)\n"
        "    model = PlannerMLP(hidden=(4,))\n"
        "    save_checkpoint(f'{sys.argv[1]}_{k}', model, name='bc', horizon=5.0)\n"
    )
    for run in range(3):
        subprocess.run([sys.executable, "-c", script, str(tmp_path / f"p{run}")], check=True)
    files = sorted(tmp_path.glob("p*.safetensors"))
    assert len(files) == 12
    assert len({f.read_bytes() for f in files}) == 1
    blob = files[0].read_bytes()
    header = json.loads(blob[8 : 8 + struct.unpack("<Q", blob[:8])[0]])
    assert list(header) == sorted(header)
    load_checkpoint(files[0])  # still a valid checkpoint
