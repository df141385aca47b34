"""The planner seam: one Policy protocol for SafeIL, BC and analytic planners.

A policy maps the 9 planner features (see :mod:`safeil_sumo.features`) to the three free control
points ``(3, 2)`` [m, ego frame] of the cubic B-spline plan over the horizon ``horizon`` [s].
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Policy(Protocol):
    """Anything with a ``name``, a ``horizon`` [s] and ``plan(features (..., 9)) -> (..., 3, 2)``."""

    name: str
    horizon: float

    def plan(self, features: np.ndarray) -> np.ndarray: ...
