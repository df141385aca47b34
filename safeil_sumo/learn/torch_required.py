"""torch is needed to train, not to plan: the runtime install (``pip install safeil-sumo``) has
no torch, and training comes with the ``[train]`` extra.

A training command line imports its torch modules inside :func:`training_imports`, so that
without torch it exits with one line that says what to install, not a traceback.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

TORCH_MISSING = "torch is not installed: pip install 'safeil-sumo[train]'"


def is_torch_missing(exc: ModuleNotFoundError) -> bool:
    """Whether ``exc`` is torch (or one of its submodules) missing, not another module."""
    return exc.name is not None and exc.name.split(".")[0] == "torch"


def have_torch() -> bool:
    """Whether torch can be imported (importing it: a command line about to train needs it)."""
    try:
        import torch  # noqa: F401
    except ModuleNotFoundError as exc:
        if not is_torch_missing(exc):
            raise
        return False
    return True


@contextmanager
def training_imports() -> Iterator[None]:
    """Around a training command line's imports: without torch, exit (status 1) with
    :data:`TORCH_MISSING` on stderr; any other missing module raises as usual."""
    try:
        yield
    except ModuleNotFoundError as exc:
        if not is_torch_missing(exc):
            raise
        raise SystemExit(TORCH_MISSING) from None
