"""Checkpoints: weights in ``safetensors`` + a JSON sidecar; never unpickled.

``<prefix>.safetensors`` holds the float32 tensors of :class:`~safeil_sumo.learn.model.PlannerMLP`
(``net.<k>.weight``/``bias`` and the scaling buffers). ``<prefix>.json`` holds the format and
version, architecture, feature/output scaling (readable copy), horizon, training config, data
fingerprint, metrics, training summary and the sha256 of the weights file. Loading checks all of
it, so a truncated file, a file of another format renamed, a pickle, or weights of another
architecture raise :class:`CheckpointError` with a clear message.

Loading the arrays needs only numpy + safetensors (:func:`load_checkpoint`); :func:`load_model`
rebuilds the torch module.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.core.features import FEATURE_NAMES, N_FEATURES
from safeil_sumo.learn.towers import weight_across_towers

if TYPE_CHECKING:
    from safeil_sumo.data.tuples import Tuples
    from safeil_sumo.learn.model import PlannerMLP

FORMAT = "safeil-checkpoint"
FORMAT_VERSION = 1
WEIGHTS_SUFFIX = ".safetensors"
SIDECAR_SUFFIX = ".json"
BUFFERS = ("feature_mean", "feature_std", "output_mean", "output_std")


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt, of another format, or of another architecture."""


def checkpoint_paths(path: str | Path) -> tuple[Path, Path]:
    """``(weights, sidecar)`` paths for a prefix or either file's path."""
    path = Path(path)
    if path.suffix in (WEIGHTS_SUFFIX, SIDECAR_SUFFIX):
        path = path.with_suffix("")
    return path.with_name(path.name + WEIGHTS_SUFFIX), path.with_name(path.name + SIDECAR_SUFFIX)


def tuples_fingerprint(tuples: Tuples) -> str:
    """sha256 (hex) of the tuples' arrays (float64, C order), maneuver ids, times and horizon."""
    h = hashlib.sha256()
    for arr in (tuples.features, tuples.control_points, tuples.future, tuples.t):
        a = np.ascontiguousarray(arr, dtype="<f8")
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    h.update("\x00".join(map(str, tuples.maneuver_id)).encode())
    h.update(f"{float(tuples.horizon)!r},{float(tuples.rate_hz)!r}".encode())
    return h.hexdigest()


def expected_shapes(architecture: dict) -> dict[str, tuple[int, ...]]:
    """Tensor names and shapes of a :class:`PlannerMLP` with this ``architecture`` dict."""
    try:
        widths = [int(architecture["n_features"]), *map(int, architecture["hidden"]),
                  int(architecture["n_outputs"])]
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"malformed architecture in sidecar: {architecture!r}") from exc
    shapes: dict[str, tuple[int, ...]] = {}
    for j in range(len(widths) - 1):
        # nn.Sequential index: Linear layers at 0, 2, 4, ... (activations in between)
        shapes[f"net.{2 * j}.weight"] = (widths[j + 1], widths[j])
        shapes[f"net.{2 * j}.bias"] = (widths[j + 1],)
    shapes["feature_mean"] = shapes["feature_std"] = (widths[0],)
    shapes["output_mean"] = shapes["output_std"] = (widths[-1],)
    return shapes


def _jsonable(value: Any) -> Any:
    """Plain JSON values: tuples -> lists, numpy scalars -> floats, non-finite floats -> None."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _jsonable(dataclasses.asdict(value))
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def canonical_safetensors(blob: bytes) -> bytes:
    """``blob`` (a safetensors file) with its JSON header's keys sorted, padded with spaces to
    its length: safetensors writes its ``__metadata__`` map in hash order, which differs from
    process to process, so the same weights would get a different file (and sha256) each time.
    The tensors' offsets are relative to the data after the header, so they stay valid."""
    n = int.from_bytes(blob[:8], "little")
    header = json.loads(blob[8 : 8 + n])
    text = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    if len(text) > n:  # cannot happen for the same keys and values; keep the original then
        return blob
    return blob[:8] + text + b" " * (n - len(text)) + blob[8 + n :]


def _atomic_write(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def save_checkpoint(
    path: str | Path,
    model: PlannerMLP,
    *,
    name: str,
    horizon: float,
    train_config: Any = None,
    data_fingerprint: str | None = None,
    metrics: dict | None = None,
    history: Any = None,
    style_default: dict | None = None,
) -> tuple[Path, Path]:
    """Write ``<prefix>.safetensors`` and ``<prefix>.json``; returns both paths.

    ``name``: policy name (e.g. "safeil" or "bc"); ``horizon`` [s] of the plans;
    ``train_config``: a TrainConfig (or dict); ``history``: a TrainHistory, stored as a summary
    plus the per-epoch logs; ``style_default``: the style inputs' default settings of a
    style-conditioned model (e.g. ``{"time_gap_s": 1.4}``, the humans' median).
    """
    import torch
    from safetensors.numpy import save as st_save

    weights_path, sidecar_path = checkpoint_paths(path)
    weights_path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {
        k: v.detach().to(torch.float32).contiguous().numpy()
        for k, v in model.state_dict().items()
    }
    blob = canonical_safetensors(
        st_save(arrays, metadata={"format": FORMAT, "format_version": str(FORMAT_VERSION)}))
    meta: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "name": name,
        "architecture": model.architecture,
        "feature_names": list(FEATURE_NAMES) + list(model.architecture.get("style_names", [])),
        "scaling": {k: arrays[k].tolist() for k in BUFFERS},
        "horizon_s": float(horizon),
        "train_config": _jsonable(train_config),
        "data_fingerprint": data_fingerprint,
        "metrics": _jsonable(metrics or {}),
        "weights_file": weights_path.name,
        "weights_sha256": hashlib.sha256(blob).hexdigest(),
        "torch_version": torch.__version__,
        "created_unix_s": time.time(),
    }
    if style_default is not None:
        meta["style_default"] = _jsonable(style_default)
    if history is not None:
        h = _jsonable(history)
        meta["training"] = {k: v for k, v in h.items() if k != "epochs"}
        meta["training"]["epochs_run"] = len(h["epochs"])
        meta["history"] = h["epochs"]
    _atomic_write(weights_path, blob)
    _atomic_write(sidecar_path, (json.dumps(meta, indent=1) + "\n").encode())
    return weights_path, sidecar_path


def _looks_like_safetensors(blob: bytes) -> bool:
    """8-byte little-endian header length, then a JSON header that fits in the file."""
    if len(blob) < 10:
        return False
    n = int.from_bytes(blob[:8], "little")
    return blob[8:9] == b"{" and 8 + n <= len(blob)


def _sniff(blob: bytes) -> str | None:
    """Name a well-known non-safetensors format from the first bytes, else None."""
    if _looks_like_safetensors(blob):
        return None
    if blob[:1] == b"\x80" or blob[:2] in (b"(d", b"(l", b"]q", b"}q", b"cc"):
        return "a Python pickle (refusing to unpickle)"
    if blob[:4] == b"PK\x03\x04":
        return "a zip archive (e.g. torch.save output; refusing to unpickle)"
    if blob[:4] == b"PAR1":
        return "a Parquet file"
    if blob[:6] == b"\x93NUMPY":
        return "a .npy file"
    if blob[:1] in (b"{", b"["):
        return "a JSON/text file"
    if len(blob) < 10 or blob[8:9] == b"{":
        return "a truncated or empty file"
    return None


def load_checkpoint(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays (float32, by tensor name) and sidecar metadata of a checkpoint.

    ``path``: the prefix or either file. Raises :class:`CheckpointError` on any inconsistency.
    """
    from safetensors.numpy import load as st_load

    weights_path, sidecar_path = checkpoint_paths(path)
    if not sidecar_path.is_file():
        raise CheckpointError(f"{sidecar_path}: sidecar JSON not found")
    if not weights_path.is_file():
        raise CheckpointError(f"{weights_path}: weights file not found")
    try:
        meta = json.loads(sidecar_path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{sidecar_path}: not a JSON sidecar ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"{sidecar_path}: not a {FORMAT} sidecar")
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{sidecar_path}: format version {meta.get('format_version')!r}, "
            f"this code reads {FORMAT_VERSION}"
        )

    blob = weights_path.read_bytes()
    kind = _sniff(blob)
    if kind is not None:
        raise CheckpointError(f"{weights_path}: is {kind}, not safetensors")
    if hashlib.sha256(blob).hexdigest() != meta.get("weights_sha256"):
        raise CheckpointError(
            f"{weights_path}: sha256 does not match its sidecar (truncated, corrupted or "
            "replaced by another file)"
        )
    try:
        arrays = st_load(blob)
    except Exception as exc:  # safetensors raises its own SafetensorError
        raise CheckpointError(f"{weights_path}: unreadable safetensors ({exc})") from exc

    shapes = expected_shapes(meta.get("architecture") or {})
    n_style = len(meta["architecture"].get("style_names") or ())
    if meta["architecture"].get("n_features") != N_FEATURES + n_style:
        raise CheckpointError(f"{sidecar_path}: expects {N_FEATURES} features"
                              + (f" and {n_style} style inputs" if n_style else ""))
    if set(arrays) != set(shapes):
        raise CheckpointError(
            f"{weights_path}: tensors {sorted(arrays)} do not match the architecture "
            f"{meta['architecture']} (expected {sorted(shapes)})"
        )
    for key, shape in shapes.items():
        if arrays[key].shape != shape:
            raise CheckpointError(
                f"{weights_path}: tensor {key} has shape {arrays[key].shape}, the architecture "
                f"{meta['architecture']} needs {shape}"
            )
        if not np.all(np.isfinite(arrays[key])):
            raise CheckpointError(f"{weights_path}: tensor {key} has non-finite values")
    _check_towers(arrays, meta["architecture"], weights_path)
    return arrays, meta


def _check_towers(arrays: dict[str, np.ndarray], arch: dict, weights_path: Path) -> None:
    """A towers checkpoint must store zeros across its towers: every reader (numpy inference,
    the certifier's bounds) takes the stored weights as they are."""
    if not arch.get("towers"):
        return
    n_linear = len(arch["hidden"]) + 1
    across = weight_across_towers([arrays[f"net.{2 * j}.weight"] for j in range(n_linear)],
                                  arch["n_features"], arch["hidden"])
    if across > 0:
        raise CheckpointError(f"{weights_path}: a towers checkpoint with non-zero weights "
                              f"across the towers (up to {across:.3g})")


def load_model(path: str | Path) -> tuple[PlannerMLP, dict]:
    """The torch module (eval mode, float32) and metadata of a checkpoint."""
    import torch

    from safeil_sumo.learn.model import PlannerMLP

    arrays, meta = load_checkpoint(path)
    arch = meta["architecture"]
    try:
        model = PlannerMLP(arch["hidden"], arch["activation"],
                           arch.get("output_mode", "absolute"),
                           arch.get("horizon_s", meta["horizon_s"]), int(arch["n_features"]),
                           towers=bool(arch.get("towers", False)),
                           lateral_mode=arch.get("lateral_mode", "absolute"),
                           lane_keep_m=float(arch.get("lane_keep_m", 0.0)))
    except ValueError as exc:
        raise CheckpointError(f"{path}: {exc}") from exc
    model.load_state_dict({k: torch.from_numpy(v.copy()) for k, v in arrays.items()})
    model.eval()
    return model, meta


def held_out_maneuvers(path: str | Path) -> list[str]:
    """The maneuver ids a checkpoint held out of training (its sidecar's
    ``metrics.val_maneuvers``); ``path``: the sidecar JSON (or the weights / prefix beside it).
    Raises :class:`CheckpointError` naming the file when there are none."""
    sidecar = Path(path).with_suffix(".json")
    try:
        ids = json.loads(sidecar.read_text())["metrics"]["val_maneuvers"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CheckpointError(f"{sidecar}: no held-out maneuvers (metrics.val_maneuvers): "
                              f"{exc}") from exc
    return [str(i) for i in ids]
