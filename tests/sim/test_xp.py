"""The float namespace's helpers against the builtins they replace (issue 21's N = 1 loop)."""

import itertools
import math

from safeil_sumo.sim.xp import FLOATS, clip, maximum, minimum

VALUES = [math.nan, -math.inf, -2.5, -1, -0.0, 0.0, 0, 1e-300, 1, 2.5, math.inf]


def test_minimum_maximum_and_clip_return_what_min_and_max_return():
    """The same object as ``min``/``max`` for every pair and triple of floats and ints: NaN on
    either side, -0.0 against 0.0 (the first argument unless the other is strictly smaller or
    larger), infinities."""
    for a, b in itertools.product(VALUES, repeat=2):
        assert minimum(a, b) is min(a, b), (a, b)
        assert maximum(a, b) is max(a, b), (a, b)
    for value, lo, hi in itertools.product(VALUES, repeat=3):
        assert clip(value, lo, hi) is min(max(value, lo), hi), (value, lo, hi)
    assert (FLOATS.minimum, FLOATS.maximum, FLOATS.clip) == (minimum, maximum, clip)
