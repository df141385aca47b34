"""Atomic file writes: write a temporary sibling, then rename it onto the target.

A crash or an exception half-way leaves the old target (or none) and no temporary file, never a
half-written target.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` (``os.replace``).

    The temporary name ends with the target's name, so writers that infer the format from the
    suffix (``.csv``, ``.parquet``, ``.csv.gz``) still do.
    """
    path = Path(path)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
