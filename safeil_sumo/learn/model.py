"""The planner network: a shallow MLP from the 9 features to the 3 free B-spline control points.

``features (N, 9) -> normalise -> Linear/act ... -> Linear -> (N, 6) normalised -> de-normalise ->
control points (N, 3, 2) [m]``. The normalisation statistics (feature mean/std, control-point
mean/std from the training data) are buffers, so they travel with the weights in the checkpoint.

Activation: ``tanh`` by default. The plan is then a smooth (C-infinity) function of the features,
so small sensor changes give small plan changes in the closed loop; ReLU is available.
Output order of the 6 outputs: ``(x1, y1, x2, y2, x3, y3)``, i.e. ``control_points.reshape(N, 6)``.

Output modes: ``absolute`` (the paper: the network's de-normalised outputs are the control points)
and ``residual`` (beyond the paper): the network predicts the control points MINUS constant-speed
motion, ``x_i - v_x t_i`` with ``t_i = i T_h / 3`` (y unchanged). The x control points are
~``v t`` (up to ~170 m) while the leader response is a few metres on top; in absolute mode that
response is a tiny share of the output variance the MSE sees, in residual mode it is most of it.
The constant-speed part is added back inside ``forward``, so callers always get control points.

Towers (``towers=True``, beyond the paper): each hidden layer is split in two halves, a
longitudinal tower and a lateral one, by fixed zero masks on the weights. The longitudinal tower
reads the ego speed, the leader and the style inputs, never the lane lines, and alone feeds the
x control points; the lateral tower reads everything and alone feeds the y control points. So
how far the plan goes (speed and gap keeping) cannot depend on the lane's curvature or on where
the ego sits in the lane, by construction. Still one plain MLP to everything downstream (numpy
inference, bounds, checkpoints): the masked weights are stored as zeros. :func:`split_towers`
builds one from a dense model (docs/human_likeness.md: why).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from safeil_sumo.core.features import N_FEATURES
from safeil_sumo.core.policy import PLAN_HORIZON_S
from safeil_sumo.learn import spline
from safeil_sumo.learn.style import STYLE_NAMES
from safeil_sumo.learn.towers import N_OUTPUTS, tower_masks, tower_rows

ACTIVATIONS = ("tanh", "relu")
OUTPUT_MODES = ("absolute", "residual")
LATERAL_MODES = ("absolute", "lane")
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

    def __init__(
        self, hidden: Sequence[int] = (64, 64), activation: str = "tanh",
        output_mode: str = "absolute", horizon: float = PLAN_HORIZON_S,
        n_features: int = N_FEATURES, towers: bool = False, lateral_mode: str = "absolute",
        lane_keep_m: float = 0.0,
    ) -> None:
        super().__init__()
        if output_mode not in OUTPUT_MODES:
            raise ValueError(f"output_mode must be one of {OUTPUT_MODES}, got {output_mode!r}")
        if lateral_mode not in LATERAL_MODES:
            raise ValueError(f"lateral_mode must be one of {LATERAL_MODES}, got {lateral_mode!r}")
        # "absolute": the y outputs are the y control points [m] (the paper's); "lane": they
        # are z, the plan follows the lane centre with bounded offsets h tanh(z)
        # (bspline.lane_following_y; h: the half width less lane_keep_m [m])
        self.lateral_mode = lateral_mode
        self.lane_keep_m = float(lane_keep_m)
        self.hidden = tuple(int(h) for h in hidden)
        self.activation = activation
        self.output_mode = output_mode
        self.horizon = float(horizon)  # T_h [s]: times of the control points in residual mode
        # the paper's 9 features, then the style inputs (safeil_sumo.learn.style) if any
        if n_features not in (N_FEATURES, N_FEATURES + len(STYLE_NAMES)):
            raise ValueError(f"n_features must be {N_FEATURES} or {N_FEATURES + len(STYLE_NAMES)}"
                             f" (with the style inputs {STYLE_NAMES}), got {n_features}")
        self.n_features = int(n_features)
        self.towers = bool(towers)
        if self.towers and any(h % 2 for h in self.hidden):
            raise ValueError(f"towers split every hidden layer in halves: widths must be even, "
                             f"got {self.hidden}")
        layers: list[nn.Module] = []
        width = self.n_features
        for h in self.hidden:
            layers += [nn.Linear(width, h), _activation(activation)]
            width = h
        last = nn.Linear(width, N_OUTPUTS)
        # Start from the mean plan: zero last layer -> normalised output 0 -> control-point mean.
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        layers.append(last)
        self.net = nn.Sequential(*layers)
        self.register_buffer("feature_mean", torch.zeros(self.n_features))
        self.register_buffer("feature_std", torch.ones(self.n_features))
        self.register_buffer("output_mean", torch.zeros(N_OUTPUTS))
        self.register_buffer("output_std", torch.ones(N_OUTPUTS))
        if self.towers:
            for j, mask in enumerate(tower_masks(self.n_features, self.hidden)):
                # not persistent: the checkpoint stores the (zeroed) weights only
                self.register_buffer(f"mask_{j}", torch.as_tensor(mask), persistent=False)
                with torch.no_grad():  # masked weights start (and, gradient-free, stay) zero
                    self.net[2 * j].weight.mul_(getattr(self, f"mask_{j}"))

    def set_scaling(self, features: np.ndarray, control_points: np.ndarray) -> None:
        """Set the buffers from training data: ``features (N, 9)``, ``control_points (N, 3, 2)``."""
        f_mean, f_std = scaling_stats(features)
        targets = np.asarray(control_points, dtype=float)
        if self.output_mode == "residual":
            targets = targets - constant_speed_points(np.asarray(features)[:, V_X], self.horizon)
        o_mean, o_std = scaling_stats(targets.reshape(-1, N_OUTPUTS))
        dtype = self.feature_mean.dtype
        for name, value in (
            ("feature_mean", f_mean), ("feature_std", f_std),
            ("output_mean", o_mean), ("output_std", o_std),
        ):
            getattr(self, name).copy_(torch.as_tensor(value, dtype=dtype))

    def forward_normalised(self, features: torch.Tensor) -> torch.Tensor:
        """Normalised outputs ``(N, 6)`` for ``features (N, 9)``."""
        h = (features - self.feature_mean) / self.feature_std
        if not self.towers:
            return self.net(h)
        for j, module in enumerate(self.net):
            if j % 2:
                h = module(h)
            else:  # masked linear layer: the masked weights get no gradient
                h = F.linear(h, module.weight * getattr(self, f"mask_{j // 2}"), module.bias)
        return h

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Control points ``(N, 3, 2)`` [m] for ``features (N, n_features)``."""
        out = self.forward_normalised(features) * self.output_std + self.output_mean
        out = out.reshape(out.shape[:-1] + (3, 2))
        if self.output_mode == "residual":
            times = torch.as_tensor(control_times(self.horizon), dtype=out.dtype)
            x = out[..., 0] + features[..., V_X, None] * times
            out = torch.stack([x, out[..., 1]], dim=-1)
        if self.lateral_mode == "lane":
            y = spline.lane_following_y(features[..., :6], out[..., 0], out[..., 1],
                                        self.lane_keep_m)
            out = torch.stack([out[..., 0], y], dim=-1)
        return out

    @property
    def architecture(self) -> dict:
        """What is needed to rebuild the module (stored in the checkpoint sidecar)."""
        arch = {
            "type": "mlp",
            "n_features": self.n_features,
            "hidden": list(self.hidden),
            "activation": self.activation,
            "n_outputs": N_OUTPUTS,
            "output_mode": self.output_mode,
            "horizon_s": self.horizon,
        }
        if self.n_features > N_FEATURES:
            arch["style_names"] = list(STYLE_NAMES)
        if self.towers:
            arch["towers"] = True
        if self.lateral_mode != "absolute":
            arch["lateral_mode"] = self.lateral_mode
            arch["lane_keep_m"] = self.lane_keep_m
        return arch


def keep_only_tower_gradients(model: PlannerMLP, tower: str = "longitudinal") -> None:
    """Zero every gradient of ``model`` (a towers model, after ``backward``) outside ``tower``
    (``"longitudinal"``: its units and the x outputs; ``"lateral"``: its units and the y
    outputs), so an optimiser step (Adam, SGD: a parameter whose gradient is always zero never
    moves) leaves the other tower's plan exactly as it was."""
    if not model.towers:
        raise ValueError("only a towers model has towers")
    for j, rows in enumerate(tower_rows(model.hidden, tower)):
        layer = model.net[2 * j]
        keep = torch.as_tensor(rows, dtype=layer.weight.dtype)
        for p in (layer.weight, layer.bias):
            if p.grad is not None:
                p.grad.mul_(keep.reshape(-1, *([1] * (p.dim() - 1))))


def split_towers(model: PlannerMLP) -> PlannerMLP:
    """A towers model (every hidden layer twice as wide) from a dense ``model``: both towers
    start as copies of it, the longitudinal one with its lane-line inputs cut. So the y control
    points are exactly ``model``'s, and the x control points are ``model``'s for lane lines at
    their training mean (a straight lane, the ego centred) whatever lanes it is given."""
    if model.towers:
        raise ValueError("the model already has towers")
    out = PlannerMLP([2 * h for h in model.hidden], model.activation, model.output_mode,
                     model.horizon, model.n_features, towers=True)
    old = model.state_dict()
    state = {k: v.clone() for k, v in old.items() if not k.startswith("net.")}
    n_linear = len(model.hidden) + 1
    for j in range(n_linear):
        w, b = old[f"net.{2 * j}.weight"], old[f"net.{2 * j}.bias"]
        if j == 0:
            w_new = torch.cat([w, w])
        elif j < n_linear - 1:
            w_new = torch.block_diag(w, w)
        else:
            w_new = torch.cat([w, w], dim=1)
        state[f"net.{2 * j}.weight"] = w_new * getattr(out, f"mask_{j}")
        state[f"net.{2 * j}.bias"] = torch.cat([b, b]) if j < n_linear - 1 else b.clone()
    out.load_state_dict(state)
    return out


V_X = 6  # column of the ego speed in the features (FEATURE_NAMES)


def control_times(horizon: float) -> np.ndarray:
    """Times ``(3,)`` [s] of the free control points (Greville abscissae ``i T_h / 3``)."""
    return np.arange(1, 4) * (float(horizon) / 3.0)


def constant_speed_points(v_x: np.ndarray, horizon: float) -> np.ndarray:
    """Control points ``(N, 3, 2)`` [m] of driving straight on at ``v_x (N,)`` [m/s]."""
    v = np.asarray(v_x, dtype=float)
    out = np.zeros(v.shape + (3, 2))
    out[..., 0] = v[..., None] * control_times(horizon)
    return out


def with_style_input(model: PlannerMLP, style_mean: float, style_std: float) -> PlannerMLP:
    """A copy of ``model`` with the style inputs appended (:data:`STYLE_NAMES`), their first-layer
    weights zero: it plans exactly as ``model`` until trained. ``style_mean`` / ``style_std``
    normalise the new input (e.g. the training maneuvers' time gaps [s])."""
    if model.n_features != N_FEATURES:
        raise ValueError("the model already has style inputs")
    out = PlannerMLP(model.hidden, model.activation, model.output_mode, model.horizon,
                     N_FEATURES + len(STYLE_NAMES), towers=model.towers)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    w0 = state["net.0.weight"]
    state["net.0.weight"] = torch.cat([w0, torch.zeros(w0.shape[0], len(STYLE_NAMES))], dim=1)
    state["feature_mean"] = torch.cat([state["feature_mean"], torch.tensor([float(style_mean)])])
    state["feature_std"] = torch.cat([state["feature_std"], torch.tensor([float(style_std)])])
    out.load_state_dict(state)
    return out
