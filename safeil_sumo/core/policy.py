"""The planner seam: one Policy protocol for SafeIL, BC and analytic planners.

A policy maps the 9 planner features (see :mod:`safeil_sumo.core.features`) to the three free control
points ``(3, 2)`` [m, ego frame] of the cubic B-spline plan over the horizon ``horizon`` [s].
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

# The planner's defaults, each declared here only (tests/test_defaults.py): every module, command
# and environment takes its default from these names
PLAN_RATE_HZ = 10.0  # [Hz] how often the loop asks for a new plan
PLAN_HORIZON_S = 5.0  # [s] a plan's horizon T_h: the time its last control point is reached
DEFAULT_TIME_GAP_S = 1.5  # [s] a planner's preferred time gap to its leader unless one is set


@runtime_checkable
class Policy(Protocol):
    """Anything with a ``name``, a ``horizon`` [s] and ``plan(features (..., 9)) -> (..., 3, 2)``."""

    # read-only: the planners are frozen dataclasses or set them once at construction
    @property
    def name(self) -> str: ...

    @property
    def horizon(self) -> float: ...

    def plan(self, features: np.ndarray) -> np.ndarray: ...
