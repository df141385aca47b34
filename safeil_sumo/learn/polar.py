"""Reader of the POLAR tool's text format of feed-forward networks into :class:`bounds.Layer` s.

Layout (whitespace-separated numbers and names, as the ARCH-COMP AINNCS benchmarks ship it):
``n_inputs n_outputs n_hidden``, the ``n_hidden`` hidden layer sizes, one activation name per
layer (hidden layers, then the output layer), then for each layer in order and for each of its
units in order that unit's incoming weights followed by its bias; finally an output offset and
an output scale. The network's output is ``(y - offset) * scale`` (POLAR's convention; the
ARCH-COMP files carry 0 and 1), folded into the last layer here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from safeil_sumo.learn.bounds import Layer

# POLAR's activation names -> bounds.py's; sigmoid has no sound relaxation in bounds.py
POLAR_ACTIVATIONS = {"Affine": "identity", "ReLU": "relu", "tanh": "tanh"}


def parse_polar(text: str) -> list[Layer]:
    """The network written in POLAR ``text`` as a list of :class:`Layer` (float64)."""
    tokens = text.split()
    pos = 0

    def take(n: int) -> list[str]:
        nonlocal pos
        if pos + n > len(tokens):
            raise ValueError(f"POLAR text ends early: wanted {n} more tokens at {pos}")
        out = tokens[pos:pos + n]
        pos += n
        return out

    n_in, n_out, n_hidden = (int(t) for t in take(3))
    sizes = [int(t) for t in take(n_hidden)] + [n_out]
    names = take(n_hidden + 1)
    unknown = [a for a in names if a not in POLAR_ACTIVATIONS]
    if unknown:
        raise ValueError(f"unsupported POLAR activations {unknown}; known: "
                         f"{sorted(POLAR_ACTIVATIONS)}")
    layers = []
    width = n_in
    for size, name in zip(sizes, names, strict=True):
        # per unit: its `width` incoming weights, then its bias
        block = np.array(take(size * (width + 1)), float).reshape(size, width + 1)
        layers.append(Layer.dense(block[:, :width], block[:, width], POLAR_ACTIVATIONS[name]))
        width = size
    offset, scale = (float(t) for t in take(2))
    if pos != len(tokens):
        raise ValueError(f"POLAR text has {len(tokens) - pos} tokens after the output scale")
    last = layers[-1]
    if names[-1] != "Affine" and (offset != 0.0 or scale != 1.0):
        raise ValueError("an output offset/scale after a non-affine output layer is not a Layer")
    # (W x + b - offset) * scale, exact for the ARCH-COMP files' 0 and 1
    layers[-1] = Layer(last.weight * scale, (last.bias - offset) * scale, last.activation)
    return layers


def read_polar(path: str | Path) -> list[Layer]:
    """:func:`parse_polar` of the file at ``path``."""
    return parse_polar(Path(path).read_text())
