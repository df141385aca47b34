"""Two array namespaces for the closed loop's stage functions: one function, floats or arrays.

A stage (the plant step, the tracker, the monitors) is written once against a namespace ``xp``:
:data:`FLOATS` runs it on Python floats (the one-scenario loop: ``math`` functions and
comparisons, about 20x cheaper per operation than numpy on one number), :data:`ARRAYS` on numpy
arrays ``(N,)`` (a batch of N scenarios, one numpy call per operation for all of them).

Branches become ``xp.where(condition, a, b)``, which evaluates both sides: stages keep every
expression finite on both sides (e.g. a divisor floored at a tiny number where the branch that
uses it is not taken). ``+ - * /`` and ``sqrt`` round identically in both namespaces;
``cos``/``sin``/``exp``/``atan``... may differ by an ulp between libm and numpy, which is why a
batched run equals a scalar run to ~1e-12 m rather than bit for bit.

The loop itself (:class:`.stepper.ClosedLoop`) is written against a namespace too: its values
are per running scenario, one float each with :data:`FLOATS` (N = 1) or arrays ``(n,)`` with
:data:`ARRAYS`, and what is per scenario by nature (SUMO's calls, the radar) goes through
Python lists of the rows: ``rows(value)`` is such a list, ``from_rows(list)`` the value again,
``full(n, value)`` a constant, ``nonzero(mask)`` the rows where a flag is set, ``select``
numpy's ``select`` and ``any`` whether any row is set. ``each(*values)`` iterates over the
rows of several values at once (a tuple per row: ``rows`` of each, zipped; one call at N = 1)
and ``from_each(tuples)`` is its inverse (the values of per-row tuples).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from types import SimpleNamespace
from typing import Any, TypeAlias, TypeVar

import numpy as np

# The types the stages are annotated with. A per-scenario value is a Python float with FLOATS (N
# = 1) and an array (N,) with ARRAYS; the namespaces' functions are untyped (mypy sees them as
# Any), so a stage's signature says which values are per scenario, not which namespace runs.
FloatOrArray: TypeAlias = float | np.ndarray
BoolOrArray: TypeAlias = bool | np.ndarray  # a per-scenario flag
Namespace: TypeAlias = SimpleNamespace  # FLOATS or ARRAYS

T = TypeVar("T")


def _where(condition: object, a: T, b: T) -> T:
    return a if condition else b


# minimum, maximum and clip on floats: the builtins min and max, whose argument parsing costs
# ~4x a Python comparison on two floats, written out as the builtins decide (the first argument
# unless the second is strictly smaller / larger): the same object, NaN and -0.0 included
def minimum(a: float, b: float) -> float:
    """``min(a, b)``."""
    return b if b < a else a  # noqa: FURB136


def maximum(a: float, b: float) -> float:
    """``max(a, b)``."""
    return b if b > a else a  # noqa: FURB136


def clip(value: float, lo: float, hi: float) -> float:
    """``min(max(value, lo), hi)``."""
    value = lo if lo > value else value  # noqa: FURB136
    return hi if hi < value else value  # noqa: FURB136


def _or(a: bool, b: bool) -> bool:
    return a or b


def _and(a: bool, b: bool) -> bool:
    return a and b


def _each(*values: T) -> tuple[tuple[T, ...]]:
    return (values,)  # the one row: the values themselves


def _from_each(rows: Sequence[tuple[T, ...]]) -> tuple[T, ...]:
    return rows[0]


def _each_arrays(*values: np.ndarray) -> Iterator[tuple[Any, ...]]:
    return zip(*(value.tolist() for value in values), strict=True)


def _from_each_arrays(rows: Sequence[tuple[Any, ...]]) -> tuple[np.ndarray, ...]:
    return tuple(np.array(col) for col in zip(*rows, strict=True))


def _select(conditions: Sequence[object], choices: Sequence[T], default: T) -> T:
    for condition, choice in zip(conditions, choices, strict=True):
        if condition:
            return choice
    return default


FLOATS = SimpleNamespace(
    where=_where, minimum=minimum, maximum=maximum, clip=clip, abs=abs,
    logical_or=_or, logical_and=_and, isnan=math.isnan, isfinite=math.isfinite,
    cos=math.cos, sin=math.sin, tan=math.tan, atan=math.atan, atan2=math.atan2,
    sqrt=math.sqrt, hypot=math.hypot, exp=math.exp,
    # the loop's rows (one scenario)
    rows=lambda value: [value], from_rows=lambda values: values[0],
    full=lambda n, value: value, nonzero=lambda mask: [0] if mask else [],
    select=_select, any=bool, each=_each, from_each=_from_each,
)

def _clip_arrays(value: np.ndarray, lo: FloatOrArray, hi: FloatOrArray) -> np.ndarray:
    return np.minimum(np.maximum(value, lo), hi)  # np.clip's overhead is ~10x on small arrays


ARRAYS = SimpleNamespace(
    where=np.where, minimum=np.minimum, maximum=np.maximum, clip=_clip_arrays, abs=np.abs,
    logical_or=np.logical_or, logical_and=np.logical_and, isnan=np.isnan, isfinite=np.isfinite,
    cos=np.cos, sin=np.sin, tan=np.tan, atan=np.arctan, atan2=np.arctan2,
    sqrt=np.sqrt, hypot=np.hypot, exp=np.exp,
    # the loop's rows (n scenarios)
    rows=np.ndarray.tolist, from_rows=np.array,
    full=lambda n, value: np.full(n, value, dtype=float), nonzero=np.flatnonzero,
    select=np.select, any=np.any, each=_each_arrays,
    from_each=_from_each_arrays,
)
