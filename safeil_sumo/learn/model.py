"""The planner network: a shallow MLP from the 9 features to the 3 free B-spline control points.

``features (N, 9) -> normalise -> Linear/act ... -> Linear -> (N, 6) normalised -> de-normalise ->
control points (N, 3, 2) [m]``. The normalisation statistics (feature mean/std, control-point
mean/std from the training data) are buffers, so they travel with the weights in the checkpoint.

Activation: ``tanh`` by default. The plan is then a smooth (C-infinity) function of the features,
so small sensor changes give small plan changes in the closed loop; ReLU is available.
Output order of the 6 outputs: ``(x1, y1, x2, y2, x3, y3)``, i.e. ``control_points.reshape(N, 6)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from safeil_sumo.features import N_FEATURES

N_OUTPUTS = 6
ACTIVATIONS = ("tanh", "relu")
# A feature that is (nearly) constant in the training data keeps std 1 instead of exploding.
MIN_STD = 1e-6


def _activation(name: str) -> nn.Module:
    if name == "tanh":
        return nn.Tanh()
    if name == "relu":
        return nn.ReLU()
    raise ValueError(f"activation must be one of {ACTIVATIONS}, got {name!r}")


def scaling_stats(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column mean and std ``(D,)`` of ``values (N, D)``; std below ``MIN_STD`` becomes 1."""
    values = np.asarray(values, dtype=float)
    mean = values.mean(axis=0)
    std = values.std(axis=0)
    return mean, np.where(std < MIN_STD, 1.0, std)


class PlannerMLP(nn.Module):
    """MLP ``9 -> hidden... -> 6`` with input/output scaling buffers; outputs metres ``(N, 3, 2)``."""

    def __init__(self, hidden: Sequence[int] = (64, 64), activation: str = "tanh") -> None:
        super().__init__()
        self.hidden = tuple(int(h) for h in hidden)
        self.activation = activation
        layers: list[nn.Module] = []
        width = N_FEATURES
        for h in self.hidden:
            layers += [nn.Linear(width, h), _activation(activation)]
            width = h
        last = nn.Linear(width, N_OUTPUTS)
        # Start from the mean plan: zero last layer -> normalised output 0 -> control-point mean.
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        layers.append(last)
        self.net = nn.Sequential(*layers)
        self.register_buffer("feature_mean", torch.zeros(N_FEATURES))
        self.register_buffer("feature_std", torch.ones(N_FEATURES))
        self.register_buffer("output_mean", torch.zeros(N_OUTPUTS))
        self.register_buffer("output_std", torch.ones(N_OUTPUTS))

    def set_scaling(self, features: np.ndarray, control_points: np.ndarray) -> None:
        """Set the buffers from training data: ``features (N, 9)``, ``control_points (N, 3, 2)``."""
        f_mean, f_std = scaling_stats(features)
        o_mean, o_std = scaling_stats(np.asarray(control_points).reshape(-1, N_OUTPUTS))
        dtype = self.feature_mean.dtype
        for name, value in (
            ("feature_mean", f_mean), ("feature_std", f_std),
            ("output_mean", o_mean), ("output_std", o_std),
        ):
            getattr(self, name).copy_(torch.as_tensor(value, dtype=dtype))

    def forward_normalised(self, features: torch.Tensor) -> torch.Tensor:
        """Normalised outputs ``(N, 6)`` for ``features (N, 9)``."""
        return self.net((features - self.feature_mean) / self.feature_std)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Control points ``(N, 3, 2)`` [m] for ``features (N, 9)``."""
        out = self.forward_normalised(features) * self.output_std + self.output_mean
        return out.reshape(out.shape[:-1] + (3, 2))

    @property
    def architecture(self) -> dict:
        """What is needed to rebuild the module (stored in the checkpoint sidecar)."""
        return {
            "type": "mlp",
            "n_features": N_FEATURES,
            "hidden": list(self.hidden),
            "activation": self.activation,
            "n_outputs": N_OUTPUTS,
        }
