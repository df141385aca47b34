"""Plain-numpy inference of a trained planner: no torch needed in the closed loop.

The feature normalisation is folded into the first layer and the output de-normalisation into the
last (``W1' = W1 / std_f``, ``b1' = b1 - W1' mean_f``; ``W3' = std_o W3``, ``b3' = std_o b3 + mean_o``),
weights are stored transposed, C-contiguous float64, and the hidden activations of the single-
sample path reuse preallocated buffers. Hence an instance is not thread-safe; use one per thread.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from safeil_sumo.core.bspline import lane_following_y
from safeil_sumo.core.features import N_FEATURES
from safeil_sumo.core.policy import DEFAULT_TIME_GAP_S
from safeil_sumo.learn.checkpoint import CheckpointError, load_checkpoint

_ONE = (N_FEATURES,)
_F64 = np.dtype(np.float64)


class MLPPolicy:
    """The Policy protocol (``name``, ``horizon`` [s], ``plan``) over checkpoint arrays."""

    def __init__(
        self,
        arrays: dict[str, np.ndarray],
        architecture: dict,
        name: str,
        horizon: float,
        metadata: dict | None = None,
    ) -> None:
        self.name = name
        self.horizon = float(horizon)
        self.metadata = metadata or {}
        self.activation = architecture["activation"]
        if self.activation not in ("tanh", "relu"):
            raise CheckpointError(f"unsupported activation {self.activation!r}")
        n_layers = len(architecture["hidden"]) + 1
        w = [np.asarray(arrays[f"net.{2 * j}.weight"], np.float64) for j in range(n_layers)]
        b = [np.asarray(arrays[f"net.{2 * j}.bias"], np.float64) for j in range(n_layers)]
        f_mean, f_std = (np.asarray(arrays[k], np.float64) for k in ("feature_mean", "feature_std"))
        o_mean, o_std = (np.asarray(arrays[k], np.float64) for k in ("output_mean", "output_std"))
        w[0] = w[0] / f_std
        b[0] = b[0] - w[0] @ f_mean
        w[-1] = w[-1] * o_std[:, None]
        b[-1] = b[-1] * o_std + o_mean
        self._wt = [np.ascontiguousarray(wi.T) for wi in w]  # (in, out)
        self._b = [np.ascontiguousarray(bi) for bi in b]
        # single-sample path: (weights^T, bias, preallocated output) per hidden layer
        self._hidden = tuple(
            (wt, bi, np.empty(wt.shape[1]))
            for wt, bi in zip(self._wt[:-1], self._b[:-1], strict=True)
        )
        self._tanh = self.activation == "tanh"
        # style inputs (safeil_sumo.learn.style): constant for a policy instance, so folded
        # into the first layer's bias; the planner keeps taking the 9 features
        self.style_names = tuple(architecture.get("style_names") or ())
        self._style_rows = self._wt[0][N_FEATURES:].copy()
        self._bias0 = self._b[0].copy()
        self._wt[0] = np.ascontiguousarray(self._wt[0][:N_FEATURES])
        self._hidden = ((self._wt[0], self._b[0], self._hidden[0][2]), *self._hidden[1:]) \
            if self._hidden else ()
        self.style: dict[str, float] = {}
        if self.style_names:
            default = (self.metadata.get("style_default") or {})
            self.set_style(**{n: float(default.get(n, DEFAULT_TIME_GAP_S))  # the one style
                              for n in self.style_names})
        # residual output mode: x_i += v_x * t_i (constant-speed motion added back)
        mode = architecture.get("output_mode", "absolute")
        if mode not in ("absolute", "residual"):
            raise CheckpointError(f"unsupported output mode {mode!r}")
        self._residual_times = (
            np.arange(1, 4) * (float(architecture.get("horizon_s", horizon)) / 3.0)
            if mode == "residual" else None
        )
        # lateral mode "lane": the y outputs are z, the plan follows the lane centre with
        # bounded offsets (bspline.lane_following_y)
        self.lateral_mode = architecture.get("lateral_mode", "absolute")
        if self.lateral_mode not in ("absolute", "lane"):
            raise CheckpointError(f"unsupported lateral mode {self.lateral_mode!r}")
        self.lane_keep_m = float(architecture.get("lane_keep_m", 0.0))

    def set_style(self, **style: float) -> None:
        """Set the style inputs, e.g. ``set_style(time_gap_s=2.0)`` [s]; a value outside the
        trained range is clipped to it. A policy without style inputs raises ValueError."""
        from safeil_sumo.learn.style import clip_time_gap

        if set(style) != set(self.style_names):
            raise ValueError(f"{self.name}: style inputs are {list(self.style_names) or 'none'}"
                             f", got {sorted(style)}")
        self.style = {n: clip_time_gap(style[n]) for n in self.style_names}
        values = np.array([self.style[n] for n in self.style_names])
        self._b[0][:] = self._bias0 + values @ self._style_rows

    @property
    def residual_times(self) -> np.ndarray | None:
        """Times ``(3,)`` [s] at which the residual output mode adds ``v_x * t_i`` to the x
        control points (constant-speed motion), or None in the absolute mode."""
        return None if self._residual_times is None else self._residual_times.copy()

    def affine_layers(self, style_input: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
        """The network as ``(weight (n_out, n_in), bias (n_out,))`` float64 per layer, exactly
        the arrays :meth:`plan` uses (scaling folded in); :attr:`activation` acts between
        layers and the residual mode adds ``v_x *`` :attr:`residual_times` to the x outputs
        after the last. ``style_input``: the first layer takes the style inputs as columns after
        the 9 features (bias without them); else the current style is folded into its bias."""
        layers = [(wt.T.copy(), b.copy()) for wt, b in zip(self._wt, self._b, strict=True)]
        if style_input:
            if not self.style_names:
                raise ValueError(f"{self.name} has no style inputs")
            layers[0] = (np.concatenate([layers[0][0], self._style_rows.T], axis=1),
                         self._bias0.copy())
        return layers

    def _act(self, h: np.ndarray) -> None:
        if self._tanh:
            np.tanh(h, out=h)
        else:
            np.maximum(h, 0.0, out=h)

    def _plan_one(self, f: np.ndarray) -> np.ndarray:
        """``(9,)`` float64 -> ``(3, 2)``: ~4 numpy calls per layer, no temporaries."""
        h = f
        tanh = self._tanh
        for wt, b, buf in self._hidden:
            np.dot(h, wt, out=buf)
            buf += b
            if tanh:
                np.tanh(buf, out=buf)
            else:
                np.maximum(buf, 0.0, out=buf)
            h = buf
        out = np.dot(h, self._wt[-1])  # fresh array: the caller may keep the plan
        out += self._b[-1]
        out = out.reshape(3, 2)
        if self._residual_times is not None:
            out[:, 0] += f[6] * self._residual_times
        if self.lateral_mode == "lane":
            out[:, 1] = lane_following_y(f[:6], out[:, 0], out[:, 1], self.lane_keep_m)
        return out

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Control points ``(..., 3, 2)`` [m] for ``features (..., 9)``."""
        if type(features) is np.ndarray and features.shape == _ONE and features.dtype == _F64:
            return self._plan_one(features)  # the closed loop's hot path
        f = np.asarray(features, dtype=np.float64)
        if f.shape[-1:] != (N_FEATURES,):
            raise ValueError(f"features must be (..., {N_FEATURES}), got {f.shape}")
        if f.ndim == 1:
            return self._plan_one(f)
        h = f.reshape(-1, N_FEATURES)
        for wt, b in zip(self._wt[:-1], self._b[:-1], strict=True):
            h = h @ wt
            h += b
            self._act(h)
        out = h @ self._wt[-1]
        out += self._b[-1]
        out = out.reshape(f.shape[:-1] + (3, 2))
        if self._residual_times is not None:
            out[..., 0] += f[..., 6, None] * self._residual_times
        if self.lateral_mode == "lane":
            out[..., 1] = lane_following_y(f[..., :6], out[..., 0], out[..., 1],
                                           self.lane_keep_m)
        return out


def load_policy(path: str | Path, name: str | None = None) -> MLPPolicy:
    """An :class:`MLPPolicy` from a checkpoint (prefix, ``.safetensors`` or ``.json`` path)."""
    arrays, meta = load_checkpoint(path)
    return MLPPolicy(
        arrays, meta["architecture"], name or meta.get("name") or Path(path).stem,
        meta["horizon_s"], meta,
    )
