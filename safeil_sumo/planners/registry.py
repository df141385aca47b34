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
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Protocol, cast

import numpy as np

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
    # a style that changes during the run: ((t_s [s], time_gap_s [s], standstill_m [m] or None),
    # ...) in increasing t_s, each set at the first decision at or after t_s of the scenario's
    # time (:class:`ScheduledStyle`); () : none (left out of the JSON)
    style_changes: tuple[StyleChange, ...] = ()

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
        object.__setattr__(self, "style_changes", checked_style_changes(self.style_changes))

    def load(self) -> Policy:
        """The planner: loaded fresh (no state shared with another load), set to the time gap,
        wrapped in the safety filter; with :attr:`style_changes` a :class:`ScheduledStyle`
        (the filter inside it). A planner without a time-gap setting refuses a style:
        :class:`PolicyError`."""
        if self.style_changes:
            return ScheduledStyle(self.load_unfiltered(), self.style_changes,
                                  self.safety_filter)
        return self.wrap(self.load_unfiltered())

    def load_unfiltered(self) -> Policy:
        """The planner set to the time gap, without the safety filter and the style changes
        (stateless: a batch of tasks may share it; :meth:`load` makes a task's own
        :class:`ScheduledStyle` of it)."""
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
        """The fields, ``time_gap_s``, ``standstill_m`` and ``style_changes`` (a list of
        ``[t_s, time_gap_s, standstill_m]``) only when set."""
        out = asdict(self)
        for key in ("time_gap_s", "standstill_m", "style_changes"):
            if out[key] in (None, ()):
                del out[key]
        if "style_changes" in out:
            out["style_changes"] = [list(change) for change in self.style_changes]
        return out


# a style change: (t_s [s], time_gap_s [s], standstill_m [m] or None: the planner's own)
StyleChange = tuple[float, float, float | None]
_TIME_TOLERANCE_S = 1e-9  # a decision this close before a change's time is at it


def checked_style_changes(changes: object) -> tuple[StyleChange, ...]:
    """``changes`` (pairs ``(t_s, time_gap_s)`` or triples ``(t_s, time_gap_s, standstill_m)``,
    e.g. read from JSON) as triples of floats (``standstill_m`` None in a pair), checked: times
    finite, >= 0 s and increasing, time gaps in (0, 10] s, standstill distances finite.
    ``ValueError`` in one line otherwise."""
    if isinstance(changes, (str, bytes)) or not hasattr(changes, "__iter__"):
        raise ValueError(f"style changes must be a sequence of (t_s, time_gap_s[, standstill_m]),"
                         f" got {changes!r}")
    out: list[StyleChange] = []
    for change in cast(Iterable[object], changes):
        if isinstance(change, (str, bytes)) or not hasattr(change, "__len__") or len(
                cast(Sequence[object], change)) not in (2, 3):
            raise ValueError(f"a style change is (t_s, time_gap_s[, standstill_m]), got "
                             f"{change!r}")
        t, gap, *rest = cast(Sequence[object], change)
        s0 = rest[0] if rest else None
        try:
            triple = (float(cast(float, t)), float(cast(float, gap)),
                      None if s0 is None else float(cast(float, s0)))
        except (TypeError, ValueError):
            raise ValueError(f"a style change holds numbers [s, s, m], got {change!r}") from None
        t_s, time_gap_s, standstill_m = triple
        if not (math.isfinite(t_s) and t_s >= 0):
            raise ValueError(f"a style change's time must be >= 0 s, got {t_s}")
        if out and not t_s > out[-1][0]:
            raise ValueError(f"style changes must be in increasing time, got {t_s} s after "
                             f"{out[-1][0]} s")
        if not (math.isfinite(time_gap_s) and 0 < time_gap_s <= 10):
            raise ValueError(f"a style change's time gap must be in (0, 10] s, got {time_gap_s}")
        if standstill_m is not None and not math.isfinite(standstill_m):
            raise ValueError(f"a style change's standstill distance must be finite, got "
                             f"{standstill_m}")
        out.append(triple)
    return tuple(out)


class ScheduledStyle:
    """A planner whose style changes during a run: each change ``(t_s, time_gap_s,
    standstill_m)`` (:func:`checked_style_changes`; None: as :func:`with_time_gap` without one)
    is set by :func:`with_time_gap` at the first decision at or after ``t_s`` [s] of the
    scenario's time, before that decision plans. The loop tells it each decision's time
    (:meth:`at_time`, :class:`safeil_sumo.sim.stepper.PlanAndTrack`); a time earlier than the
    last one told (the object run again) starts over from the style it was built with.
    ``safety_filter``: its plans are filtered (the filter's counters are this object's:
    ``interventions``, ``calls``, ``intervention_rate``).

    Stateful, so one per scenario: scenarios that share one must be at the same time at every
    decision (a batch started together; the loop checks it). A planner without a time-gap
    setting (:func:`has_time_gap`), or a change it refuses (e.g. the IDM's s0 out of its
    bounds), raises :class:`PolicyError` here, before any simulation."""

    def __init__(self, policy: Policy, changes: Iterable[Sequence[float | None]],
                 safety_filter: bool = False) -> None:
        if not has_time_gap(policy):
            raise PolicyError(f"{policy.name} has no time-gap setting, so its style cannot "
                              "change (style-conditioned checkpoints and the IDM have one)")
        self.changes = checked_style_changes(changes)
        self._initial = _style_of(policy)
        self._planner = policy
        for _, time_gap_s, standstill_m in self.changes:  # each change refused now, not mid-run
            self._planner = with_time_gap(self._planner, time_gap_s, standstill_m)
        self._planner = with_time_gap(self._planner, *self._initial)
        self._filter = None
        if safety_filter:
            from safeil_sumo.planners.safety_filter import SafetyFiltered

            self._filter = SafetyFiltered(self._planner)
        self.name: str = (self._filter or self._planner).name
        self.horizon: float = float(policy.horizon)
        self._next = 0  # the next change to set
        self._t_last = -math.inf  # the last decision's time [s]

    @property
    def planner(self) -> Policy:
        """The planner at its current style (unfiltered)."""
        return self._planner

    def at_time(self, t_s: float) -> None:
        """The decision at the scenario's time ``t_s`` [s] plans next: set every change due."""
        planner = self._planner
        if t_s < self._t_last:  # run again from the start
            planner = with_time_gap(planner, *self._initial)
            self._next = 0
        self._t_last = t_s
        while (self._next < len(self.changes)
               and self.changes[self._next][0] <= t_s + _TIME_TOLERANCE_S):
            _, time_gap_s, standstill_m = self.changes[self._next]
            planner = with_time_gap(planner, time_gap_s, standstill_m)
            self._next += 1
        self._planner = planner
        if self._filter is not None:
            self._filter.policy = planner  # the IDM's setting is a new planner

    def plan(self, features: np.ndarray) -> np.ndarray:
        return (self._filter or self._planner).plan(features)

    @property
    def interventions(self) -> int:
        return self._filter.interventions if self._filter is not None else 0

    @property
    def calls(self) -> int:
        return self._filter.calls if self._filter is not None else 0

    @property
    def intervention_rate(self) -> float:
        return self._filter.intervention_rate if self._filter is not None else 0.0


def _style_of(policy: Policy) -> tuple[float, float | None]:
    """The time gap [s] and standstill distance [m] (None: a checkpoint's one-number style)
    ``policy`` is set to (:func:`has_time_gap`)."""
    from safeil_sumo.planners import idm

    if isinstance(policy, idm.IDMPlanner):
        return policy.params.time_gap_s, policy.params.s0_m
    style = cast(_Styled, policy).style
    s0 = style.get("standstill_m")
    return style["time_gap_s"], s0


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

    style: dict[str, float]

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
