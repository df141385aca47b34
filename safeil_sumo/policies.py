"""Name -> Policy: ``analytic``, the shipped ``safeil`` / ``bc`` checkpoints, or a checkpoint path."""

from __future__ import annotations

from pathlib import Path

from safeil_sumo.analytic import AnalyticPlanner
from safeil_sumo.policy import Policy

MODELS_DIR = Path(__file__).resolve().parent / "models"
SHIPPED = ("safeil", "safeil_paper", "bc")


class PolicyError(ValueError):
    """A policy name or checkpoint that cannot be loaded."""


def shipped_checkpoint(name: str) -> Path:
    """Path of a shipped model's weights (``models/<name>.safetensors``)."""
    return MODELS_DIR / f"{name}.safetensors"


def default_policy_name() -> str:
    """``safeil`` when the shipped model is present, else the analytic planner."""
    return "safeil" if shipped_checkpoint("safeil").is_file() else "analytic"


def load(name_or_path: str) -> Policy:
    """Resolve ``analytic``, a shipped model (``safeil``, ``safeil_paper``, ``bc``) or a path to a
    ``.safetensors`` checkpoint."""
    if name_or_path == "analytic":
        return AnalyticPlanner()
    if name_or_path in SHIPPED:
        path = shipped_checkpoint(name_or_path)
        if not path.is_file():
            raise PolicyError(f"the shipped {name_or_path!r} model is missing ({path})")
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise PolicyError(
                f"unknown policy {name_or_path!r}: use analytic, safeil, bc or a checkpoint path"
            )
    from safeil_sumo.learn.inference import load_policy  # torch-free numpy inference

    try:
        return load_policy(path)
    except Exception as exc:  # CheckpointError and friends: one clear line for the CLI
        raise PolicyError(f"cannot load policy from {path}: {exc}") from exc
