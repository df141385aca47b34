"""Certificates: what :func:`safeil_sumo.learn.branch_and_bound.certify` proved, tied to one
checkpoint.

A certificate is a JSON file (``<checkpoint name>.certificate.json``) holding the envelope, the
margins' settings, the bounds method, the budget, per margin the certified share of the
envelope, the proven boxes' summary, where the unproven volume lies, the worst counterexamples,
and two hashes of the checkpoint:

- ``weights_sha256``: sha256 of the ``.safetensors`` file (as its sidecar records it);
- ``function_sha256``: sha256 of the weights hash and the sidecar fields that change the certified
  function or its margins (architecture, horizon, style default, training config), so editing the
  style default in the sidecar voids the certificate too, while adding metrics does not.

:func:`load_certificate` reports whether a checkpoint has a valid certificate: both hashes must
match the checkpoint as it is now.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.learn.branch_and_bound import CertifyResult
from safeil_sumo.learn.certify_margins import DIM_NAMES, FLOAT_MARGIN_M
from safeil_sumo.learn.checkpoint import CheckpointError, checkpoint_paths, load_checkpoint

FORMAT = "safeil-certificate"
FORMAT_VERSION = 1
SUFFIX = ".certificate.json"
BOUNDS_METHOD = {
    "network": "interval bound propagation, then CROWN back-substitution (every layer's "
               "pre-activation interval from CROWN over the layers below, intersected with IBP); "
               "tanh relaxed by chord / tangent lines (across 0: the tangent from the interval's "
               "end), ReLU by the chord and an adaptive lower line (safeil_sumo.learn.bounds)",
    "inputs": "envelope coordinates -> features by an affine layer with a ReLU on the leader "
              "speed; features carried through the hidden layers as identity units; the "
              "residual output mode's v_x t_i folded into the output layer",
    "leader_margin": "linear in the output: CROWN on it directly",
    "lane_margin": "Bernstein coefficients: products c1 x and c2 x_i x_j enclosed by McCormick "
                   "planes over the outputs' CROWN intervals (interval arithmetic kept linear), "
                   "then CROWN; a lane-following head's rows in closed form (its offsets' room "
                   "less the centre fit's allowance: >= the start's and the clearance's shares "
                   "wherever the room is positive, checked from the x control points' bounds)",
    "float": f"explicit margin: a margin is proven where its lower bound is >= {FLOAT_MARGIN_M} m;"
             " relaxation lines and intermediate intervals loosened by 1e-12 relative",
    "branching": "largest envelope share first; split the dimension with the largest estimated "
                 "gain (|coef| width + relaxation gaps shared by sensitivity)",
    "volume": "certified share: the larger of the proven boxes' smallest volume and one less "
              "the open boxes' largest (the leaves partition the envelope)",
}


class CertificateError(ValueError):
    """A certificate file that is missing, unreadable or of another format."""


def function_sha256(meta: dict, weights_sha256: str) -> str:
    """sha256 of the weights hash and the sidecar fields the certified margins depend on."""
    tc = meta.get("train_config") or {}
    relevant = {"weights_sha256": weights_sha256, "architecture": meta.get("architecture"),
                "horizon_s": meta.get("horizon_s"), "style_default": meta.get("style_default"),
                "track": tc.get("track"), "gap_min": tc.get("gap_min"),
                "time_gap": tc.get("time_gap")}
    return hashlib.sha256(json.dumps(relevant, sort_keys=True).encode()).hexdigest()


def _checkpoint_hashes(checkpoint: str | Path) -> tuple[str, str, dict]:
    """``(weights_sha256, function_sha256, metadata)``; the weights file is hashed as it is
    now (a mismatch with its sidecar raises :class:`CheckpointError`)."""
    _, meta = load_checkpoint(checkpoint)
    weights, _ = checkpoint_paths(checkpoint)
    digest = hashlib.sha256(weights.read_bytes()).hexdigest()
    return digest, function_sha256(meta, digest), meta


def certificate_path(checkpoint: str | Path, out_dir: str | Path | None = None) -> Path:
    """``<checkpoint prefix>.certificate.json``, in ``out_dir`` if given."""
    weights, _ = checkpoint_paths(checkpoint)
    name = weights.name.removesuffix(".safetensors") + SUFFIX
    return (Path(out_dir) / name) if out_dir is not None else weights.with_name(name)


def build_certificate(result: CertifyResult, checkpoint: str | Path) -> dict:
    """The certificate's JSON content for ``result`` of the checkpoint at ``checkpoint``."""
    weights_sha, func_sha, meta = _checkpoint_hashes(checkpoint)
    margins = {}
    for name, m in result.margins.items():
        d = {f.name: getattr(m, f.name) for f in fields(m) if f.name != "boxes"}
        d["complete"] = m.stopped_by == "proven"
        margins[name] = d
    env = asdict(result.envelope)
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "checkpoint": {"name": meta.get("name"), "weights_file": checkpoint_paths(checkpoint)[0]
                       .name, "weights_sha256": weights_sha, "function_sha256": func_sha},
        "policy": result.policy,
        "style": result.style,
        "envelope": env,
        "coordinates": list(result.envelope.dims),
        "parts": {"leader": "leader states: every coordinate over its range, recoverable only",
                  "free": "no-leader states: relative speed 0, gap at the radar range"},
        "volume_measure": "product of the coordinates' widths, log width for the gap (the "
                          "sampler's measure: uniform, gap log-uniform); parts weighted by "
                          "no_leader_share",
        "envelope_volume": {p: list(v) for p, v in result.volumes.items()},
        "properties": asdict(result.properties),
        "bounds_method": BOUNDS_METHOD,
        "float_margin_m": result.float_margin_m,
        "budget": asdict(result.budget),
        "seconds": result.seconds,
        "margins": margins,
        "complete": all(m["complete"] for m in margins.values()),
        "covers": "one plan, open loop, exact features: every plan the network outputs on the "
                  "certified boxes keeps the margin; not the closed loop, not sensing errors, "
                  "not tracking errors",
        "created_unix_s": time.time(),
    }


def write_certificate(result: CertifyResult, checkpoint: str | Path,
                      out_dir: str | Path | None = None) -> Path:
    """Write the certificate next to the checkpoint (or into ``out_dir``); returns its path."""
    path = certificate_path(checkpoint, out_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    body = json.dumps(build_certificate(result, checkpoint), indent=1, allow_nan=False) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(body)
    return path


@dataclass(frozen=True)
class CertificateStatus:
    """Whether a checkpoint has a valid certificate, and what it certifies."""

    valid: bool
    reason: str  # why not, or "ok"
    path: Path
    certified: dict  # margin -> certified share of the envelope [-] (empty if unreadable)
    complete: bool  # every margin proven on the whole envelope
    certificate: dict | None


def read_certificate(path: str | Path) -> dict:
    """A certificate's JSON (format checked); :class:`CertificateError` naming the file."""
    path = Path(path)
    try:
        cert = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise CertificateError(f"{path}: no certificate") from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CertificateError(f"{path}: unreadable certificate ({exc})") from exc
    if not isinstance(cert, dict) or cert.get("format") != FORMAT:
        raise CertificateError(f"{path}: not a {FORMAT} file")
    if cert.get("format_version") != FORMAT_VERSION:
        raise CertificateError(f"{path}: format version {cert.get('format_version')!r}, this "
                               f"code reads {FORMAT_VERSION}")
    if list(cert.get("coordinates", []))[: len(DIM_NAMES)] != list(DIM_NAMES):
        raise CertificateError(f"{path}: envelope coordinates {cert.get('coordinates')} are "
                               "not this code's")
    return cert


def load_certificate(checkpoint: str | Path, certificate: str | Path | None = None
                     ) -> CertificateStatus:
    """Whether ``checkpoint`` has a valid certificate (``certificate``: its path, default next
    to the checkpoint): readable, and both hashes match the checkpoint as it is now."""
    path = Path(certificate) if certificate is not None else certificate_path(checkpoint)
    try:
        cert = read_certificate(path)
    except CertificateError as exc:
        return CertificateStatus(False, str(exc), path, {}, False, None)
    certified = {m: float(r["certified"]) for m, r in (cert.get("margins") or {}).items()}
    complete = bool(cert.get("complete"))
    try:
        weights_sha, func_sha, _ = _checkpoint_hashes(checkpoint)
    except CheckpointError as exc:
        return CertificateStatus(False, f"checkpoint unreadable: {exc}", path, certified,
                                 complete, cert)
    recorded = cert.get("checkpoint") or {}
    if recorded.get("weights_sha256") != weights_sha:
        return CertificateStatus(False, "sha256 mismatch: the checkpoint's weights are not the "
                                 "certified ones", path, certified, complete, cert)
    if recorded.get("function_sha256") != func_sha:
        return CertificateStatus(False, "sha256 mismatch: the checkpoint's sidecar (style "
                                 "default, horizon, architecture or margins) changed", path,
                                 certified, complete, cert)
    return CertificateStatus(True, "ok", path, certified, complete, cert)
