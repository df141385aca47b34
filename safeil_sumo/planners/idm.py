"""The Intelligent Driver Model (Treiber, Hennecke, Helbing 2000) as a planner and as a calibrated
car-following baseline: what every car-following paper compares a data-driven model against.

- :func:`idm_acceleration`: the model, vectorised, pure numpy.
- :func:`simulate_follower`: the follower driven by the IDM behind a RECORDED leader (closed
  trajectory: the simulated gap feeds back, as in the calibration literature, e.g. Punzo et al.
  2021, "Calibration of car-following models with single- and multi-step approaches").
- :func:`fit_idm`: bounded least squares of the simulated spacing against the recorded one over
  whole maneuvers, from several seeded starts.
- :class:`IDMPlanner`: the :class:`~safeil_sumo.core.policy.Policy` — the IDM simulated over the
  horizon with the leader at its current speed, fitted to the same cubic B-spline as every planner,
  lateral as the analytic planner (lane centre).
- A JSON model file (``format: safeil-idm-1``, no pickle): fits per source and per driver, and
  which fit the planner uses by default.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from safeil_sumo.planners.analytic import lane_following_plan

FORMAT = "safeil-idm-1"
MIN_GAP_M = 0.1  # [m] the gap in the interaction term is floored here (the model diverges at 0)
# fitted parameters and their bounds (v0, T, s0, a, b); delta stays 4 as in the original paper
FIT_FIELDS = ("v0_mps", "time_gap_s", "s0_m", "a_max_mps2", "b_mps2")
LOWER = (10.0, 0.3, 0.5, 0.2, 0.3)
UPPER = (50.0, 3.5, 10.0, 5.0, 6.0)


class IDMError(ValueError):
    """A bad IDM model file or parameter set."""


@dataclass(frozen=True)
class IDMParams:
    """IDM parameters (SI units)."""

    v0_mps: float = 33.0  # desired speed [m/s]
    time_gap_s: float = 1.5  # safe time gap T [s]
    s0_m: float = 2.0  # standstill gap [m]
    a_max_mps2: float = 1.0  # maximum acceleration a [m/s^2]
    b_mps2: float = 1.5  # comfortable deceleration b [m/s^2]
    delta: float = 4.0  # acceleration exponent [-]

    def __post_init__(self) -> None:
        for f in fields(self):
            v = float(getattr(self, f.name))
            if not (math.isfinite(v) and v > 0):
                raise IDMError(f"IDM parameter {f.name} must be finite and > 0, got {v}")
            object.__setattr__(self, f.name, v)

    @staticmethod
    def from_vector(x: np.ndarray, delta: float = 4.0) -> IDMParams:
        return IDMParams(**dict(zip(FIT_FIELDS, map(float, x), strict=True)), delta=delta)

    def vector(self) -> np.ndarray:
        return np.array([getattr(self, name) for name in FIT_FIELDS])


def idm_acceleration(v, v_lead, gap, p: IDMParams):
    """IDM acceleration [m/s^2] for ego speed ``v``, leader speed ``v_lead`` [m/s] and bumper gap
    ``gap`` [m] (arrays broadcast): ``a [1 - (v/v0)^delta - (s*/s)^2]`` with
    ``s* = s0 + max(0, v T + v (v - v_lead) / (2 sqrt(a b)))``."""
    v = np.asarray(v, dtype=float)
    dv = v - np.asarray(v_lead, dtype=float)
    s_star = p.s0_m + np.maximum(0.0, v * p.time_gap_s + v * dv / (2.0 * math.sqrt(p.a_max_mps2
                                                                                 * p.b_mps2)))
    s = np.maximum(np.asarray(gap, dtype=float), MIN_GAP_M)
    return p.a_max_mps2 * (1.0 - (v / p.v0_mps) ** p.delta - (s_star / s) ** 2)


def equilibrium_gap(v, p: IDMParams):
    """The IDM's steady-state bumper gap [m] behind a leader at the ego's speed ``v`` [m/s]
    (zero acceleration, ``v_lead = v``): ``(s0 + v T) / sqrt(1 - (v/v0)^delta)``; inf at or
    above ``v0``. Below ``v0`` it exceeds the low-speed approximation ``s0 + v T``."""
    v = np.asarray(v, dtype=float)
    free = 1.0 - (v / p.v0_mps) ** p.delta
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(free > 0.0, (p.s0_m + v * p.time_gap_s) / np.sqrt(free), np.inf)


def simulate_follower(times: np.ndarray, v_lead: np.ndarray, v0: float, gap0: float,
                      p: IDMParams) -> tuple[np.ndarray, np.ndarray]:
    """The IDM follower behind a recorded leader: ``(gap (N,), speed (N,))`` at ``times (N,)`` [s].

    The leader's position is integrated from its recorded speed (trapezoid); the follower starts
    at speed ``v0`` [m/s] and bumper gap ``gap0`` [m] and moves ballistically with the IDM
    acceleration held over each step; speeds never go negative. (:func:`simulate_stacked` for
    one maneuver.)
    """
    t = np.asarray(times, dtype=float)
    n = len(t)
    start = Maneuver("", t, np.full(n, float(v0)), np.full(n, float(gap0)),
                     np.asarray(v_lead, dtype=float))
    gaps, speeds = simulate_stacked(_stacked([start]), p)
    return gaps[0], speeds[0]


@dataclass(frozen=True)
class Maneuver:
    """One recorded car-following maneuver at a common rate: ``times, v, gap, v_lead`` (N,)."""

    maneuver_id: str
    times: np.ndarray  # [s]
    v: np.ndarray  # follower speed [m/s]
    gap: np.ndarray  # bumper gap [m]
    v_lead: np.ndarray  # leader speed [m/s]


def maneuvers_from_rows(rows) -> list[Maneuver]:
    """:class:`Maneuver` list from the pipeline's maneuver rows (``maneuver_id, time, v_x,
    lead_x, v_lead`` columns, e.g. ``process_drive(drive, PipelineConfig(rate_hz=10))``)."""
    out = []
    for mid, g in rows.groupby("maneuver_id", sort=True):
        g = g.sort_values("time")
        out.append(Maneuver(str(mid), g["time"].to_numpy(float), g["v_x"].to_numpy(float),
                            g["lead_x"].to_numpy(float), g["v_lead"].to_numpy(float)))
    return out


def maneuvers_from_tuples(tuples) -> list[Maneuver]:
    """:class:`Maneuver` list from training tuples (:class:`safeil_sumo.data.tuples.Tuples`;
    ``features`` ``v_x, v_lead, d_lead`` and ``t`` per sample), in maneuver-id order. A tuple needs a horizon of future, so each maneuver ends one
    horizon before the recording's rows do."""
    from safeil_sumo.core.features import FEATURE_NAMES

    iv, il, ig = (FEATURE_NAMES.index(k) for k in ("v_x", "v_lead", "d_lead"))
    ids = np.asarray(tuples.maneuver_id).astype(str)
    out = []
    for mid in np.unique(ids):
        rows = np.flatnonzero(ids == mid)
        rows = rows[np.argsort(np.asarray(tuples.t)[rows], kind="stable")]
        f = tuples.features[rows]
        out.append(Maneuver(str(mid), np.asarray(tuples.t, float)[rows], f[:, iv].astype(float),
                            f[:, ig].astype(float), f[:, il].astype(float)))
    return out


def _stacked(maneuvers: list[Maneuver]) -> dict[str, np.ndarray]:
    """Maneuvers padded to one (M, N) array each, for a simulation vectorised over maneuvers."""
    n = max(len(m.times) for m in maneuvers)
    m_count = len(maneuvers)
    out = {k: np.zeros((m_count, n)) for k in ("dt", "vl", "gap", "v")}
    out["mask"] = np.zeros((m_count, n), dtype=bool)
    for i, m in enumerate(maneuvers):
        k = len(m.times)
        out["dt"][i, 1:k] = np.diff(m.times)
        out["vl"][i, :k], out["gap"][i, :k], out["v"][i, :k] = m.v_lead, m.gap, m.v
        out["vl"][i, k:] = m.v_lead[-1]
        out["mask"][i, :k] = True
    return out


def simulate_stacked(data: dict[str, np.ndarray], p: IDMParams) -> tuple[np.ndarray, np.ndarray]:
    """:func:`simulate_follower` for all maneuvers at once: ``(gap (M, N), speed (M, N))``."""
    dt, vl = data["dt"], data["vl"]
    m_count, n = dt.shape
    gaps = np.empty((m_count, n))
    speeds = np.empty((m_count, n))
    gap = data["gap"][:, 0].copy()
    v = data["v"][:, 0].copy()
    gaps[:, 0], speeds[:, 0] = gap, v
    root_ab = 2.0 * math.sqrt(p.a_max_mps2 * p.b_mps2)
    for k in range(1, n):
        d, vlk = dt[:, k], vl[:, k - 1]
        s_star = p.s0_m + np.maximum(0.0, v * p.time_gap_s + v * (v - vlk) / root_ab)
        a = p.a_max_mps2 * (1.0 - (v / p.v0_mps) ** p.delta
                            - (s_star / np.maximum(gap, MIN_GAP_M)) ** 2)
        v_new = np.maximum(v + a * d, 0.0)
        gap = gap + 0.5 * (vlk + vl[:, k]) * d - 0.5 * (v + v_new) * d
        v = v_new
        gaps[:, k], speeds[:, k] = gap, v
    return gaps, speeds


@dataclass(frozen=True)
class IDMFit:
    """A calibration result: parameters, spacing/speed RMSE [m, m/s] over the fitted samples."""

    params: IDMParams
    rmse_gap_m: float
    rmse_speed_mps: float
    maneuver_ids: tuple[str, ...]
    samples: int


def evaluate_fit(maneuvers: list[Maneuver], p: IDMParams) -> tuple[float, float]:
    """Spacing and speed RMSE of the IDM simulated over whole ``maneuvers`` [m, m/s]."""
    data = _stacked(maneuvers)
    gaps, speeds = simulate_stacked(data, p)
    mask = data["mask"]
    eg = (gaps - data["gap"])[mask]
    ev = (speeds - data["v"])[mask]
    return float(np.sqrt(np.mean(eg ** 2))), float(np.sqrt(np.mean(ev ** 2)))


def fit_idm(maneuvers: list[Maneuver], seed: int = 0, starts: int = 4) -> IDMFit:
    """Calibrate the 5 IDM parameters on whole maneuvers: minimise the spacing RMSE of the
    closed-trajectory simulation (bounded trust-region least squares from ``starts`` starts: the
    default parameters and seeded uniform draws within the bounds; the best one is kept)."""
    if not maneuvers:
        raise IDMError("no maneuvers to fit the IDM on")
    data = _stacked(maneuvers)
    mask = data["mask"]
    lo, hi = np.array(LOWER), np.array(UPPER)

    def residuals(x: np.ndarray) -> np.ndarray:
        gaps, _ = simulate_stacked(data, IDMParams.from_vector(x))
        r = (gaps - data["gap"])[mask]
        return np.clip(r, -1e3, 1e3)  # a diverging trial stays finite

    rng = np.random.default_rng(seed)
    x0s = [np.clip(IDMParams().vector(), lo, hi)]
    x0s += [rng.uniform(lo, hi) for _ in range(max(starts - 1, 0))]
    fits = [least_squares(residuals, x0, bounds=(lo, hi), x_scale=hi - lo, diff_step=1e-3,
                          max_nfev=200) for x0 in x0s]
    best = min(fits, key=lambda res: res.cost)  # the first of the cheapest
    params = IDMParams.from_vector(best.x)
    rmse_gap, rmse_speed = evaluate_fit(maneuvers, params)
    return IDMFit(params, rmse_gap, rmse_speed, tuple(m.maneuver_id for m in maneuvers),
                  int(mask.sum()))


# --------------------------------------------------------------------------------- planner


@dataclass(frozen=True)
class IDMPlanner:
    """Implements :class:`safeil_sumo.core.policy.Policy`: the IDM over the horizon, leader at its
    current speed, fitted to the cubic B-spline; lateral: the analytic planner's lane following."""

    params: IDMParams = IDMParams()
    name: str = "idm"
    horizon: float = 5.0  # plan horizon T_h [s]
    samples: int = 20  # trajectory samples fitted by least squares [-]
    lateral_tau_s: float = 1.5  # lateral convergence time constant [s]

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Control points ``(..., 3, 2)`` [m] for features ``(..., 9)``."""
        f = np.asarray(features, dtype=float)
        if f.ndim > 1:
            return np.stack([self.plan(row) for row in f.reshape(-1, 9)]).reshape(
                f.shape[:-1] + (3, 2))
        v, v_lead, gap = float(f[6]), float(f[7]), float(f[8])
        p = self.params
        root_ab = 2.0 * math.sqrt(p.a_max_mps2 * p.b_mps2)
        n = self.samples
        dt = self.horizon / n
        x = [0.0] * n
        pos = 0.0
        for k in range(n):  # plain floats: ~5x cheaper than numpy scalars
            s_star = p.s0_m + max(0.0, v * p.time_gap_s + v * (v - v_lead) / root_ab)
            a = p.a_max_mps2 * (1.0 - (v / p.v0_mps) ** p.delta
                                - (s_star / max(gap, MIN_GAP_M)) ** 2)
            new_v = max(v + a * dt, 0.0)
            step = 0.5 * (v + new_v) * dt
            pos += step
            gap += v_lead * dt - step
            v = new_v
            x[k] = pos
        return lane_following_plan(f, np.array(x), dt, self.lateral_tau_s)


# ------------------------------------------------------------------------------ model file


def save_model(path: str | Path, fits: dict[str, IDMFit], default: str,
               per_driver: dict[str, IDMFit] | None = None, extra: dict | None = None) -> None:
    """Write an IDM model file (JSON, atomically)."""
    from safeil_sumo.core.atomic import atomic_path

    if default not in fits:
        raise IDMError(f"default fit {default!r} not among {sorted(fits)}")

    def fit_json(fit: IDMFit) -> dict:
        return {"params": asdict(fit.params), "rmse_gap_m": fit.rmse_gap_m,
                "rmse_speed_mps": fit.rmse_speed_mps, "samples": fit.samples,
                "maneuver_ids": list(fit.maneuver_ids)}

    doc = {"format": FORMAT, "type": "idm", "default": default, "horizon_s": 5.0,
           "fits": {k: fit_json(v) for k, v in fits.items()},
           "per_driver": {k: fit_json(v) for k, v in (per_driver or {}).items()},
           **(extra or {})}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=1) + "\n")


def baseline_path(checkpoint: str | Path) -> Path:
    """The IDM ``safeil-train`` calibrates on a checkpoint's training maneuvers, beside it:
    ``<name>.idm.json`` for ``<name>.safetensors`` (the report card's baseline)."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(f"{checkpoint.stem}.idm.json")


def is_model_file(path: str | Path) -> bool:
    """True if ``path`` is a JSON file that declares itself an IDM model."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and doc.get("type") == "idm"


def load_planner(path: str | Path, fit: str | None = None, name: str = "idm") -> IDMPlanner:
    """An :class:`IDMPlanner` from a model file (``fit``: a key of ``fits`` or ``per_driver``;
    default: the file's ``default``). Raises :class:`IDMError` naming what is wrong."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise IDMError(f"{path}: not a readable IDM model file ({exc})") from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise IDMError(f"{path}: not an IDM model file (format must be {FORMAT!r})")
    key = fit or doc.get("default")
    table = {**doc.get("per_driver", {}), **doc.get("fits", {})}
    if key not in table:
        raise IDMError(f"{path}: no fit {key!r} (has {sorted(table)})")
    raw = table[key].get("params", {})
    try:
        params = IDMParams(**{f.name: raw[f.name] for f in fields(IDMParams)})
    except (KeyError, TypeError) as exc:
        raise IDMError(f"{path}: fit {key!r} lacks parameter {exc}") from exc
    horizon = float(doc.get("horizon_s", 5.0))
    return IDMPlanner(params=params, name=name, horizon=horizon)
