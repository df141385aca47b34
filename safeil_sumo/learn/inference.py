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
        self._schedule: tuple[float, float] | None = None  # (T [s], s0 [m]) when s0 != 0
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
        trained range is clipped to it. A policy without style inputs raises ValueError.

        A time-gap input also takes a driver's standstill distance, ``standstill_m`` [m] in
        :data:`~safeil_sumo.learn.style.STANDSTILL_RANGE_M`: the style is then the line
        ``gap = s0 + T v`` and every plan gets the setting ``T + s0 / v`` at its ego speed
        (:func:`~safeil_sumo.learn.style.scheduled_time_gap`, inside the trained range);
        ``standstill_m=0`` is the one-number style."""
        from safeil_sumo.learn import style as st

        # the schedule replaces the one style input's bias row (_schedule_bias)
        extra = {st.STANDSTILL_NAME} if self.style_names == ("time_gap_s",) else set()
        if not set(self.style_names) <= set(style) <= set(self.style_names) | extra:
            raise ValueError(f"{self.name}: style inputs are {list(self.style_names) or 'none'}"
                             f"{' (and ' + st.STANDSTILL_NAME + ')' if extra else ''}"
                             f", got {sorted(style)}")
        s0 = float(style.get(st.STANDSTILL_NAME, 0.0))
        lo, hi = st.STANDSTILL_RANGE_M
        if not lo <= s0 <= hi:
            raise ValueError(f"{self.name}: {st.STANDSTILL_NAME} must be in [{lo:g}, {hi:g}] m,"
                             f" got {s0}")
        if s0 == 0.0:
            self._schedule = None
            self.style = {n: st.clip_time_gap(style[n]) for n in self.style_names}
        else:  # the setting follows the ego speed: the bias is made per plan
            time_gap = float(style["time_gap_s"])
            if not 0.0 < time_gap <= 10.0:
                raise ValueError(f"{self.name}: time_gap_s must be in (0, 10] s, got {time_gap}")
            self._schedule = (time_gap, s0)
            self.style = {"time_gap_s": time_gap, st.STANDSTILL_NAME: s0}
            return
        values = np.array([self.style[n] for n in self.style_names])
        self._b[0][:] = self._bias0 + values @ self._style_rows

    def _schedule_bias(self, speed_mps: float) -> None:
        """The first layer's bias at the scheduled setting for ego speed ``speed_mps``."""
        from safeil_sumo.learn.style import scheduled_time_gap

        assert self._schedule is not None
        setting = float(scheduled_time_gap(*self._schedule, speed_mps))
        np.multiply(self._style_rows[0], setting, out=self._b[0])
        self._b[0] += self._bias0

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
        the 9 features (bias without them); else the current style is folded into its bias
        (a style with a standstill distance has no one bias: ValueError)."""
        if self._schedule is not None and not style_input:
            raise ValueError(f"{self.name}: a standstill distance makes the setting depend on "
                             "the speed; take the style as an input (style_input=True)")
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
        if self._schedule is not None:
            self._schedule_bias(f[6])
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
        for j, (wt, b) in enumerate(zip(self._wt[:-1], self._b[:-1], strict=True)):
            h = h @ wt
            if j == 0 and self._schedule is not None:  # each row's own setting
                from safeil_sumo.learn.style import scheduled_time_gap

                setting = scheduled_time_gap(*self._schedule, f.reshape(-1, N_FEATURES)[:, 6])
                h += setting[:, None] * self._style_rows[0] + self._bias0  # as _schedule_bias
            else:
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
