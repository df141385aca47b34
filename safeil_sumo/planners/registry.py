"""Name -> Policy: ``analytic``, ``idm`` (the calibrated IDM baseline), the shipped ``safeil`` /
``safeil_paper`` / ``bc`` checkpoints, a checkpoint path, or an IDM model file (``*.json`` with
``"type": "idm"``, written by ``training/fit_idm.py``). Replays also know two kinematic
pseudo-planners (:func:`load_for_replay`): ``recorded``, the human's own path
(:mod:`safeil_sumo.sim.recorded_ego`), and ``constant_speed``, the ego keeping its initial speed
on its lane centre (:mod:`safeil_sumo.sim.constant_speed_ego`), and the adaptation variants
(:data:`ADAPTATION_VARIANTS`): a shipped planner under another name, adapted another way by
``replay --adapt-first-s`` (:func:`safeil_sumo.experiments.window_replays.adapt_planners`), so a
replay can show them as extra rows."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Protocol, cast

from safeil_sumo.core.policy import Policy
from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.sim.constant_speed_ego import CONSTANT_SPEED_NAME, ConstantSpeedPath
from safeil_sumo.sim.recorded_ego import RECORDED_NAME, RecordedPath

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
SHIPPED = ("safeil", "safeil_openloop", "safeil_paper", "bc")
NAMES = ("analytic", "idm", *SHIPPED)
REPLAY_ONLY = (RECORDED_NAME, CONSTANT_SPEED_NAME)  # kinematic pseudo-planners of a replay
# name -> (the planner it loads, how ``replay --adapt-first-s`` adapts it); a planner's own name
# is adapted by the (s0, T) style estimator (``ESTIMATOR``). Replay only (load_for_replay).
ESTIMATOR = "estimator"
ADAPTATION_VARIANTS = {
    # the IDM's five parameters refitted on the first seconds (the old adapted baseline)
    "idm_refit5": ("idm", "refit5"),
    # the planner as shipped, left unadapted beside the adapted ones (the same scored seconds)
    "idm_unadapted": ("idm", "unadapted"),
    "safeil_unadapted": ("safeil", "unadapted"),
    # the time-gap setting from the shrunk median of gap / speed (learn.style.adapted_time_gap)
    "safeil_median": ("safeil", "median"),
    # one setting from the (s0, T) estimate: the line's time gap at the speed seen
    "safeil_one_setting": ("safeil", "one_setting"),
}


class PolicyError(ValueError):
    """A policy name or checkpoint that cannot be loaded."""


@dataclass(frozen=True)
class PlannerRef:
    """A planner by reference, JSON-able: the planner part of a closed-loop task
    (:class:`safeil_sumo.scenarios.spec.Task`)."""

    policy: str = "analytic"  # a name of NAMES or a checkpoint/IDM path
    safety_filter: bool = False  # wrapped in the inference-time safety filter
    # the planner's preferred time gap [s] (an ACC's distance setting, :func:`with_time_gap`);
    # None: its default
    time_gap_s: float | None = None
    # with it, the driver's standstill distance [m]: the style is the steady gap's line
    # s0 + T v (:func:`with_time_gap`); None: the planner's own (0 for a checkpoint)
    standstill_m: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "policy", str(self.policy))
        object.__setattr__(self, "safety_filter", bool(self.safety_filter))
        if self.time_gap_s is not None:
            object.__setattr__(self, "time_gap_s", float(self.time_gap_s))
            if not (math.isfinite(self.time_gap_s) and 0 < self.time_gap_s <= 10):
                raise ValueError(f"time gap must be in (0, 10] s, got {self.time_gap_s}")
        if self.standstill_m is not None:
            if self.time_gap_s is None:
                raise ValueError("a standstill distance needs a time gap (the style is the "
                                 "line s0 + T v)")
            object.__setattr__(self, "standstill_m", float(self.standstill_m))
            if not math.isfinite(self.standstill_m):
                raise ValueError(f"standstill distance must be finite, got {self.standstill_m}")

    def load(self) -> Policy:
        """The planner: loaded fresh (no state shared with another load), set to the time gap,
        wrapped in the safety filter."""
        return self.wrap(self.load_unfiltered())

    def load_unfiltered(self) -> Policy:
        """The planner set to the time gap, without the safety filter (stateless: a batch of
        tasks may share it)."""
        policy = load(self.policy)
        return policy if self.time_gap_s is None else with_time_gap(policy, self.time_gap_s,
                                                                    self.standstill_m)

    def wrap(self, policy: Policy) -> Policy:
        """``policy`` in the safety filter if this reference asks for it (a new wrapper: its
        intervention counters are this task's)."""
        if not self.safety_filter:
            return policy
        from safeil_sumo.planners.safety_filter import SafetyFiltered

        return SafetyFiltered(policy)

    def to_json(self) -> dict[str, object]:
        """The fields, ``time_gap_s`` and ``standstill_m`` only when set."""
        out = asdict(self)
        for key in ("time_gap_s", "standstill_m"):
            if out[key] is None:
                del out[key]
        return out


def shipped_checkpoint(name: str) -> Path:
    """Path of a shipped model's weights (``models/<name>.safetensors``)."""
    return MODELS_DIR / f"{name}.safetensors"


def policy_file(name_or_path: str) -> Path:
    """The file a policy is loaded from: a shipped model's weights, the shipped IDM's model file
    for ``idm``, else the path given (which may not exist, or name no file at all)."""
    name_or_path = ADAPTATION_VARIANTS.get(name_or_path, (name_or_path,))[0]
    if name_or_path in SHIPPED:
        return shipped_checkpoint(name_or_path)
    return MODELS_DIR / "idm.json" if name_or_path == "idm" else Path(name_or_path)


def fingerprint(name_or_path: str) -> str:
    """What a cached result of this policy depends on, for sweep and replay task ids: the sha256
    of the weights of a shipped or given checkpoint (as its sidecar records it), of an IDM model
    file's bytes; the name itself for a planner without a file (or a file that does not exist:
    loading it fails later, with its own error). A retrained model so never reuses the cached
    results of the model before."""
    path = policy_file(name_or_path)
    try:
        if not path.is_file():
            return name_or_path
        stat = path.stat()
    except (OSError, ValueError):
        return name_or_path
    return _file_fingerprint(str(path.resolve()), stat.st_mtime_ns, stat.st_size)


@lru_cache(maxsize=64)
def _file_fingerprint(path: str, mtime_ns: int, size: int) -> str:
    """(``mtime_ns`` and ``size`` key the cache: a rewritten file is read again.)"""
    p = Path(path)
    if p.suffix == ".safetensors":
        try:
            return str(json.loads(p.with_suffix(".json").read_text())["weights_sha256"])
        except (OSError, ValueError, KeyError, TypeError):
            pass  # no readable sidecar: hash the weights themselves
    return hashlib.sha256(p.read_bytes()).hexdigest()


def default_policy_name() -> str:
    """``safeil`` when the shipped model is present, else the analytic planner."""
    return "safeil" if shipped_checkpoint("safeil").is_file() else "analytic"


def load(name_or_path: str) -> Policy:
    """Resolve ``analytic``, ``idm``, a shipped model (``safeil``, ``safeil_paper``, ``bc``), a
    path to a ``.safetensors`` checkpoint or to an IDM model file."""
    from safeil_sumo.planners import idm

    if name_or_path == RECORDED_NAME:
        raise PolicyError("the 'recorded' pseudo-planner drives a recorded maneuver's own path: "
                          "use it with python -m safeil_sumo.replay")
    if name_or_path == CONSTANT_SPEED_NAME:
        raise PolicyError("the 'constant_speed' baseline keeps a recorded maneuver's initial "
                          "speed: use it with python -m safeil_sumo.replay")
    if name_or_path in ADAPTATION_VARIANTS:
        raise PolicyError(f"{name_or_path!r} is a way of adapting "
                          f"{ADAPTATION_VARIANTS[name_or_path][0]!r} to a driver: use it with "
                          "python -m safeil_sumo.replay --adapt-first-s")
    if name_or_path == "analytic":
        return AnalyticPlanner()
    if name_or_path == "idm" or (name_or_path.endswith(".json")
                                 and idm.is_model_file(name_or_path)):
        try:
            return idm.load_planner(policy_file(name_or_path))
        except idm.IDMError as exc:
            raise PolicyError(f"cannot load the IDM planner: {exc}") from exc
    path = policy_file(name_or_path)
    if not path.is_file():
        if name_or_path in SHIPPED:
            raise PolicyError(f"the shipped {name_or_path!r} model is missing ({path})")
        if _looks_like_path(name_or_path):  # meant as a file: say that it is not there
            what = "is a folder, not a file" if path.is_dir() else "does not exist"
            raise PolicyError(f"policy file {name_or_path} {what} (a checkpoint .safetensors "
                              "or an IDM model .json)")
        raise PolicyError(
            f"unknown policy {name_or_path!r}: use one of {', '.join(NAMES)}, a checkpoint "
            "path (.safetensors) or an IDM model file (.json)"
        )
    from safeil_sumo.learn.inference import load_policy  # torch-free numpy inference

    try:
        return load_policy(path)
    except Exception as exc:  # CheckpointError and friends: one clear line for the CLI
        raise PolicyError(f"cannot load policy from {path}: {exc}") from exc


def _looks_like_path(name: str) -> bool:
    """A policy argument meant as a file: it has a folder or a model file's suffix."""
    return "/" in name or "\\" in name or name.endswith((".safetensors", ".json"))


def load_for_replay(name_or_path: str) -> Policy:
    """:func:`load`, plus ``recorded`` (an unbound :class:`RecordedPath`) and ``constant_speed``
    (an unbound :class:`ConstantSpeedPath`), which the replay binds to the maneuver it
    rebuilds, and the :data:`ADAPTATION_VARIANTS` (their planner; an IDM named as the
    variant)."""
    if name_or_path == RECORDED_NAME:
        return RecordedPath()
    if name_or_path == CONSTANT_SPEED_NAME:
        return ConstantSpeedPath()
    if name_or_path in ADAPTATION_VARIANTS:
        from dataclasses import replace

        from safeil_sumo.planners import idm

        policy = load(ADAPTATION_VARIANTS[name_or_path][0])
        return replace(policy, name=name_or_path) if isinstance(policy, idm.IDMPlanner) else policy
    return load(name_or_path)


def adaptation_of(label: str) -> str:
    """How ``replay --adapt-first-s`` adapts the planner of ``label`` (a name it was loaded
    by): its :data:`ADAPTATION_VARIANTS` entry, else :data:`ESTIMATOR`."""
    return ADAPTATION_VARIANTS.get(label, (label, ESTIMATOR))[1]


def has_time_gap(policy: Policy) -> bool:
    """Whether ``policy`` has a time-gap setting (:func:`with_time_gap`): a style-conditioned
    checkpoint or the IDM."""
    from safeil_sumo.planners import idm

    styled = "time_gap_s" in getattr(policy, "style_names", ())
    return styled or isinstance(policy, idm.IDMPlanner)


class _Styled(Protocol):
    """A style-conditioned checkpoint's planner (:class:`~safeil_sumo.learn.inference.
    MLPPolicy` with ``style_names``): its style inputs are set in place."""

    def set_style(self, **style: float) -> None: ...


def with_time_gap(policy: Policy, time_gap_s: float, standstill_m: float | None = None
                  ) -> Policy:
    """``policy`` set to keep a preferred time gap ``time_gap_s`` [s] (an ACC's distance
    setting): a style-conditioned checkpoint's style input (:mod:`safeil_sumo.learn.style`,
    clipped to its trained range), or the IDM's time gap T. With ``standstill_m`` [m] the style
    is a driver's steady-gap line ``s0 + T v``: the checkpoint's setting follows the speed
    (:meth:`~safeil_sumo.learn.inference.MLPPolicy.set_style`), the IDM's s0 is set (inside its
    calibration bounds). Other planners have no such setting, and a value out of range is
    refused: :class:`PolicyError`."""
    from dataclasses import replace

    from safeil_sumo.planners import idm

    if not (time_gap_s > 0):
        raise PolicyError(f"a time gap must be > 0 s, got {time_gap_s}")
    if isinstance(policy, idm.IDMPlanner):
        params = replace(policy.params, time_gap_s=float(time_gap_s))
        if standstill_m is not None:
            k = idm.FIT_FIELDS.index("s0_m")
            if not idm.LOWER[k] <= standstill_m <= idm.UPPER[k]:
                raise PolicyError(f"the IDM's standstill distance must be in [{idm.LOWER[k]:g}, "
                                  f"{idm.UPPER[k]:g}] m, got {standstill_m}")
            params = replace(params, s0_m=float(standstill_m))
        return replace(policy, params=params)
    if "time_gap_s" in getattr(policy, "style_names", ()):  # a style-conditioned checkpoint
        style = {"time_gap_s": float(time_gap_s)}
        if standstill_m is not None:
            style["standstill_m"] = float(standstill_m)
        try:
            cast(_Styled, policy).set_style(**style)
        except ValueError as e:
            raise PolicyError(str(e)) from None
        return policy
    raise PolicyError(f"{policy.name} has no time-gap setting (style-conditioned checkpoints "
                      "and the IDM have one)")
