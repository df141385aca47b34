"""Reproduce the shipped planners in ``safeil_sumo/models/`` with one command:

    python training/train_shipped_models.py

Builds the default dataset if it is missing (``training/build_synthetic_dataset.py``: 16
calibrated synthetic drivers x the 29.2 km n74 road in SUMO, then the paper's processing
pipeline -> ``data/synthetic/tuples.parquet``), then trains, each with seed 0 and the same
maneuver split (20 % of maneuvers held out for early stopping):

- ``safeil``: SafeIL with the exact Bernstein bound of the lane margin along the whole spline
  (our extension; on curves the paper's control-point barrier rejects lane-following plans);
- ``safeil_paper``: SafeIL exactly as the paper (barrier on the three control points);
- ``bc``: behavioral cloning, the paper's baseline (same network, data and loop, no barrier).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "data" / "synthetic" / "tuples.parquet"
MODELS = REPO / "safeil_sumo" / "models"
SEED = 0
MODELS_TO_TRAIN = {
    "safeil": ["--method", "safeil", "--barrier-lateral", "bernstein"],
    "safeil_paper": ["--method", "safeil", "--barrier-lateral", "control_points"],
    "bc": ["--method", "bc"],
}


def main() -> int:
    if not DATA.is_file():
        subprocess.run([sys.executable, str(REPO / "training" / "build_synthetic_dataset.py")],
                       check=True)
    MODELS.mkdir(parents=True, exist_ok=True)
    for name, extra in MODELS_TO_TRAIN.items():
        prefix = REPO / "data" / "models" / name
        prefix.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, str(REPO / "training" / "train.py"), "--data", str(DATA),
                        "--seed", str(SEED), "--name", name, "--out", str(prefix), *extra],
                       check=True)
        for suffix in (".safetensors", ".json"):
            shutil.copyfile(prefix.with_suffix(suffix), MODELS / f"{name}{suffix}")
        print(f"shipped {MODELS / name}.safetensors")
    return 0


if __name__ == "__main__":
    sys.exit(main())
