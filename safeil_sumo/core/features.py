"""The planner's inputs: one feature function shared by training data and the closed loop.

The paper's 9 features, in this order (all in the ego frame, SI units):
``c0l, c1l, c2l`` left lane line, ``c0r, c1r, c2r`` right lane line (``y = c0 + c1 x + c2 x^2``,
y left, [m], [-], [1/m]), ``v_x`` ego speed [m/s], ``v_lead`` leader speed [m/s],
``d_lead`` bumper-to-bumper distance to the leader [m].
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

FEATURE_NAMES = ("c0l", "c1l", "c2l", "c0r", "c1r", "c2r", "v_x", "v_lead", "d_lead")
N_FEATURES = len(FEATURE_NAMES)


def planner_features(
    left_line: np.ndarray | Sequence[float],
    right_line: np.ndarray | Sequence[float],
    v_x: np.ndarray | float,
    v_lead: np.ndarray | float,
    d_lead: np.ndarray | float,
) -> np.ndarray:
    """Stack the features ``(..., 9)``.

    ``left_line`` / ``right_line``: polynomial coefficients ``(..., k)`` with k >= 3 in increasing
    order (c0, c1, c2[, c3]); only c0..c2 are used, as in the paper.
    """
    left = np.asarray(left_line, dtype=float)[..., :3]
    right = np.asarray(right_line, dtype=float)[..., :3]
    if (left.ndim == 1 and right.ndim == 1 and isinstance(v_x, float)
            and isinstance(v_lead, float) and isinstance(d_lead, float)):
        # one car (the one-scenario loop): the same 9 values without the stacking's overhead
        out = np.empty(9)
        out[:3], out[3:6], out[6:] = left, right, (v_x, v_lead, d_lead)
        return out
    scalars = np.stack(np.broadcast_arrays(v_x, v_lead, d_lead), axis=-1).astype(float)
    return np.concatenate([left, right, scalars], axis=-1)
