"""The two-tower masks of the planner MLP (learn/model.py ``towers=True``), in plain numpy so
the checkpoint loader can check a towers checkpoint without torch.

The first half of every hidden layer is the longitudinal tower: it reads the ego speed, the
leader and the style inputs, never the lane lines, and alone feeds the x control points. The
second half, the lateral tower, reads every input and alone feeds the y control points.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import numpy as np

LANE_FEATURES = tuple(range(6))  # c0l, c1l, c2l, c0r, c1r, c2r: never read by the x tower
X_OUTPUTS, Y_OUTPUTS = (0, 2, 4), (1, 3, 5)  # of (x1, y1, x2, y2, x3, y3)
N_OUTPUTS = 6


def tower_masks(n_features: int, hidden: Sequence[int]) -> list[np.ndarray]:
    """0/1 masks ``(n_out, n_in)`` float32 of every linear layer of a towers MLP (first half of
    each hidden layer: the longitudinal tower; the rest: the lateral tower)."""
    widths = [int(n_features), *(int(h) for h in hidden)]
    masks = []
    for j, (n_in, n_out) in enumerate(pairwise(widths)):
        m = np.ones((n_out, n_in), np.float32)
        if j == 0:
            m[: n_out // 2, list(LANE_FEATURES)] = 0.0
        else:  # two towers, no crossing
            m[: n_out // 2, n_in // 2:] = 0.0
            m[n_out // 2:, : n_in // 2] = 0.0
        masks.append(m)
    last = np.ones((N_OUTPUTS, widths[-1]), np.float32)
    last[list(X_OUTPUTS), widths[-1] // 2:] = 0.0
    last[list(Y_OUTPUTS), : widths[-1] // 2] = 0.0
    return [*masks, last]


def weight_across_towers(weights: Sequence[np.ndarray], n_features: int,
                         hidden: Sequence[int]) -> float:
    """Largest |w| of ``weights`` (one ``(n_out, n_in)`` per linear layer) where the masks are 0."""
    masks = tower_masks(n_features, hidden)
    return max(float(np.max(np.abs(np.asarray(w) * (1.0 - m)))) for w, m in
               zip(weights, masks, strict=True))


TOWERS = ("longitudinal", "lateral")


def tower_rows(hidden: Sequence[int], tower: str) -> list[np.ndarray]:
    """0/1 row masks ``(n_out,)`` of every linear layer of a towers MLP: 1 on ``tower``'s units
    and outputs (the longitudinal tower: the first half of each hidden layer and the x outputs;
    the lateral one: the rest and the y outputs), i.e. what training that tower alone moves."""
    if tower not in TOWERS:
        raise ValueError(f"tower must be one of {TOWERS}, got {tower!r}")
    rows = []
    for h in hidden:
        r = np.zeros(int(h), np.float32)
        r[: int(h) // 2] = 1.0
        rows.append(r)
    last = np.zeros(N_OUTPUTS, np.float32)
    last[list(X_OUTPUTS)] = 1.0
    rows.append(last)
    return rows if tower == "longitudinal" else [1.0 - r for r in rows]
