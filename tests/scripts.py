"""The training scripts (``training/<name>.py``, not package modules) loaded by the tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

TRAINING = Path(__file__).resolve().parents[1] / "training"


def load_training_script(name: str) -> ModuleType:
    """``training/<name>.py`` as a module; ``training/`` goes on ``sys.path`` first, as when the
    script runs (some import their siblings, e.g. ``leave_one_driver_out``)."""
    if str(TRAINING) not in sys.path:
        sys.path.insert(0, str(TRAINING))
    spec = importlib.util.spec_from_file_location(name, TRAINING / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
