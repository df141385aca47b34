"""The closed-loop certificate: :mod:`.loop_barrier`'s check of a gap floor on one checkpoint,
its verdict and what it measured, written next to the checkpoint (``certify --closed-loop``).

:func:`run` computes every grid cell's one-period increments (:func:`.loop_barrier.increments`)
and checks a floor: the recoverable envelope's lower boundary
(:func:`.loop_barrier.recoverable_floor`), or with a search budget the last floor of
:func:`.loop_barrier.synthesize`. :class:`ClosedLoopResult` holds the verdict and its
evidence: the failing columns, their deficits, the worst cells as states with the reason the
check gives, S's share of the recoverable envelope (:func:`.loop_barrier.envelope_share`,
measured only where the check passes: a floor that fails proves nothing, so its share is 0).

The certificate is a JSON file ``<checkpoint name>.closed_loop_certificate.json``: the
checkpoint's two hashes (as :mod:`.certificate` makes them), every assumption of the bound
(:class:`.loop_invariant.LoopAssumptions`, the :class:`.loop_invariant.Grid`, the time-gap
range, the guard and the loop parts' settings), the verdict and the numbers above, the floor's
summary, versions and time; beside it the floor and each column's deficit and reason as
``<checkpoint name>.closed_loop_floor.safetensors`` (its sha256 in the JSON). The verdict is
derived from the failing-column count and :func:`build` and :func:`read` refuse a body whose
verdict, count and share disagree, so no file says "proven" of a check that failed.
"""

from __future__ import annotations

import hashlib
import json
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from safeil_sumo import __version__
from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.learn import certificate as cert
from safeil_sumo.learn import loop_barrier as lb
from safeil_sumo.learn import loop_invariant as li
from safeil_sumo.learn.checkpoint import CheckpointError, checkpoint_paths
from safeil_sumo.learn.inference import MLPPolicy

FORMAT = "safeil-closed-loop-certificate"
FORMAT_VERSION = 1
SUFFIX = ".closed_loop_certificate.json"
FLOOR_SUFFIX = ".closed_loop_floor.safetensors"
NOT_PROVEN, PROVEN, PROVEN_EMPTY = "not proven", "proven", "proven, vacuously: S is empty"
SHARE_SAMPLES, SHARE_SEED = 200_000, 0  # envelope_share's draws
WORST_KEPT = 20  # worst failing cells the certificate lists
DIMS = ("gap_m", "speed_mps", "leader_speed_mps", "force_mps2")
COVERS = ("the longitudinal closed loop (planner network, PI tracker, brake guard if on, "
          "plant), one decision period bounded from every grid cell; if the check passes, "
          "S = {floor(v, v_l, f) <= gap <= the grid's top gap} is forward invariant for every "
          "leader, sensing error, PI integral and guard estimate the assumptions state, until "
          "the gap passes the grid's top or the ego's speed the grid's top; not the lateral "
          "loop, not curved lanes, not lane changes")


class ClosedLoopError(ValueError):
    """A closed-loop certificate that cannot be made or read (one line, naming why)."""


@dataclass(frozen=True)
class ClosedLoopSettings:
    """What :func:`run` certifies: the time-gap setting's range [s], the guard, the grid, the
    assumptions, and a search budget [s] (0: check the recoverable floor)."""

    time_gap_s: tuple[float, float]
    guard: bool = True
    grid: li.Grid = field(default_factory=li.Grid)
    assumptions: li.LoopAssumptions = field(default_factory=li.LoopAssumptions)
    search_s: float = 0.0

    def __post_init__(self) -> None:
        lo, hi = self.time_gap_s
        if not 0.0 < lo <= hi:
            raise ClosedLoopError(f"the time-gap range must be 0 < LO <= HI, got {lo:g} {hi:g}")
        if not self.search_s >= 0.0:
            raise ClosedLoopError(f"the search budget must be >= 0 s, got {self.search_s:g}")
        try:
            self.grid.axes()
        except ValueError as exc:
            raise ClosedLoopError(str(exc)) from None

    @property
    def parts(self) -> li.LoopParts:
        return li.LoopParts() if self.guard else li.LoopParts(guard=None)


def grid_with_widths(widths: tuple[float, float, float, float]) -> li.Grid:
    """The default grid's domain cut into cells of these widths (gap [m], ego speed [m/s],
    leader speed [m/s], force [m/s^2]); :class:`ClosedLoopError` where one does not divide
    its axis."""
    base = li.Grid()
    axes = (base.gap_m, base.speed_mps, base.leader_speed_mps, base.force_mps2)
    if any(not w > 0.0 for w in widths):
        raise ClosedLoopError(f"cell widths must be > 0, got {list(widths)}")
    grid = li.Grid(*((lo, hi, float(w)) for (lo, hi, _), w in zip(axes, widths, strict=True)))
    try:
        grid.axes()
    except ValueError as exc:
        raise ClosedLoopError(f"{exc}: choose widths that divide the axes "
                              f"{[(lo, hi) for lo, hi, _ in axes]}") from None
    return grid


@dataclass
class ClosedLoopResult:
    """:func:`run`'s verdict and evidence (SI units; deficits [m], times [s])."""

    policy: str
    settings: ClosedLoopSettings
    columns: int  # (v, v_l, f) columns of the grid
    failing_columns: int
    columns_with_states: int  # columns holding states of S (the rest are vacuous)
    speed_exit_columns: int  # columns where a state of S can pass the speed axis' top
    deficit_median_m: float | None  # over the failing columns with a finite deficit
    deficit_max_m: float | None
    unbounded_deficits: int  # failing columns whose hull is too long to bound (inf)
    failing_by_reason: dict[str, int]
    worst: list[dict]
    share: float  # S's share of the recoverable envelope; 0 unless proven
    share_stderr: float
    floor: dict  # summary of the floor checked
    search: dict | None  # the synthesis's rounds, with --search-s
    seconds: dict[str, float]
    arrays: dict[str, np.ndarray] = field(repr=False, default_factory=dict)

    @property
    def proven(self) -> bool:
        return self.failing_columns == 0

    @property
    def verdict(self) -> str:
        return verdict_of(self.failing_columns, self.columns_with_states)


def verdict_of(failing_columns: int, columns_with_states: int) -> str:
    """The verdict a check's counts allow: proven only where no column fails."""
    if failing_columns > 0:
        return NOT_PROVEN
    return PROVEN if columns_with_states > 0 else PROVEN_EMPTY


def worst_cells(check: lb.BarrierCheck, grid: li.Grid, n: int = WORST_KEPT) -> list[dict]:
    """The ``n`` failing columns with the largest deficits, each as its worst cell's state
    box (gap row from the check) with the deficit [m] (None: unbounded) and the reason."""
    eg, ev, el, ef = grid.axes()
    fails = np.argwhere(check.deficit > 0.0)
    order = np.argsort(-check.deficit[tuple(fails.T)], kind="stable")[:n]
    out = []
    for iv, il, jf in fails[order]:
        row = int(check.row[iv, il, jf])
        deficit = float(check.deficit[iv, il, jf])
        code = int(check.reason[iv, il, jf])
        boxes = ((eg[row], eg[row + 1]), (ev[iv], ev[iv + 1]), (el[il], el[il + 1]),
                 (ef[jf], ef[jf + 1]))
        out.append({**{d: [float(lo), float(hi)] for d, (lo, hi) in zip(DIMS, boxes,
                                                                          strict=True)},
                    "deficit_m": deficit if np.isfinite(deficit) else None,
                    "reason": code, "reason_text": lb.REASONS[code]})
    return out


def floor_summary(phi: np.ndarray, grid: li.Grid, settings: ClosedLoopSettings,
                  source: str) -> dict:
    """What the floor is, in numbers: its nodes' range, its lift above the recoverable
    boundary, the nodes at the ceiling (S empty there), and the sha256 of its float64 bytes."""
    base = lb.recoverable_floor(grid, settings.assumptions, settings.parts)
    lift = phi - base
    top = float(grid.axes()[0][-1])
    return {"source": source, "nodes": list(phi.shape),
            "node_axes": ["speed_mps", "leader_speed_mps", "force_mps2"],
            "min_m": float(phi.min()), "median_m": float(np.median(phi)),
            "max_m": float(phi.max()), "lift_above_recoverable_max_m": float(lift.max()),
            "lift_above_recoverable_mean_m": float(lift.mean()),
            "nodes_above_top_gap": int(np.sum(phi > top)),
            "sha256": hashlib.sha256(np.ascontiguousarray(phi, np.float64).tobytes())
            .hexdigest()}


def summarize(policy: str, settings: ClosedLoopSettings, phi: np.ndarray,
              check: lb.BarrierCheck, floor: dict, search: dict | None,
              seconds: dict[str, float]) -> ClosedLoopResult:
    """The result of one checked floor (the share measured only if the check passed)."""
    deficit = check.deficit
    fails = deficit > 0.0
    finite = deficit[fails & np.isfinite(deficit)]
    reasons = check.reason[fails]
    by_reason = {lb.REASONS[k]: int(np.sum(reasons == k)) for k in np.unique(reasons)}
    result = ClosedLoopResult(
        policy, settings, int(deficit.size), int(fails.sum()),
        int(np.sum(deficit > -np.inf)), int(check.speed_exits.sum()),
        float(np.median(finite)) if finite.size else None,
        float(finite.max()) if finite.size else None, int(np.sum(fails & ~np.isfinite(deficit))),
        by_reason, worst_cells(check, settings.grid), 0.0, 0.0, floor, search, dict(seconds),
        {"floor": phi, "deficit": deficit, "reason": check.reason.astype(np.int8),
         "row": check.row})
    if check.passed:  # only a passing check proves anything: measure S then
        start = time.perf_counter()
        result.share, result.share_stderr = lb.envelope_share(
            phi, settings.grid, settings.assumptions, settings.parts, SHARE_SAMPLES, SHARE_SEED)
        result.seconds["share"] = time.perf_counter() - start
    return result


def _bar(progress: bool, total: int | None, desc: str, unit: str) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=not progress or None)


def run(policy: MLPPolicy, settings: ClosedLoopSettings, progress: bool = False,
        floor: np.ndarray | None = None) -> ClosedLoopResult:
    """Increments of every cell, then the barrier check of ``floor`` (default: the recoverable
    floor, or with ``settings.search_s > 0`` :func:`.loop_barrier.synthesize`'s last floor)."""
    start = time.perf_counter()
    grid, a, parts = settings.grid, settings.assumptions, settings.parts
    with _bar(progress, grid.shape[0], f"{policy.name} closed loop: period bounds",
              "gap row") as bar:
        inc = lb.increments(policy, grid, settings.time_gap_s, a, parts, progress=bar.update)
    seconds = {"increments": inc.seconds}
    search = None
    t0 = time.perf_counter()
    if floor is not None:
        phi, source = np.asarray(floor, float), "given"
        check = lb.check(inc, phi, grid, a)
    elif settings.search_s > 0.0:
        phi, check, search = _search(policy, settings, inc, progress)
        source = f"synthesize: last of {len(search['rounds'])} checks"
    else:
        phi, source = lb.recoverable_floor(grid, a, parts), "recoverable boundary"
        check = lb.check(inc, phi, grid, a)
    seconds["check" if search is None else "search"] = time.perf_counter() - t0
    summary = floor_summary(phi, grid, settings, source)
    result = summarize(policy.name, settings, phi, check, summary, search, seconds)
    result.seconds["total"] = time.perf_counter() - start
    return result


def _search(policy: MLPPolicy, settings: ClosedLoopSettings, inc: lb.Increments,
            progress: bool) -> tuple[np.ndarray, lb.BarrierCheck, dict]:
    """:func:`.loop_barrier.synthesize` for the budget, a bar counting its checks."""
    with _bar(progress, None, f"{policy.name} closed loop: floor search", "check") as bar:
        def shown(_: int, check: lb.BarrierCheck) -> None:
            bar.set_postfix(failing=int(np.sum(check.deficit > 0.0)))
            bar.update(1)

        syn = lb.synthesize(policy, settings.grid, settings.time_gap_s, settings.assumptions,
                            settings.parts, budget_s=settings.search_s, progress=shown, inc=inc)
    stopped = ("passed" if syn.result.passed
               else "budget" if syn.rounds[-1][2] > settings.search_s else "rounds")
    rounds = [{"failing_columns": n, "max_finite_deficit_m": d, "seconds": s}
              for n, d, s in syn.rounds]
    return syn.phi, syn.result, {"budget_s": settings.search_s, "stopped_by": stopped,
                                 "rounds": rounds}


# ------------------------------------------------------------------ the file


def certificate_path(checkpoint: str | Path, out_dir: str | Path | None = None,
                     suffix: str = SUFFIX) -> Path:
    """``<checkpoint prefix>.closed_loop_certificate.json`` (or another ``suffix``), where the
    one-plan certificate goes (:func:`.certificate.certificate_path`)."""
    one_plan = cert.certificate_path(checkpoint, out_dir)
    return one_plan.with_name(one_plan.name.removesuffix(cert.SUFFIX) + suffix)


def checkpoint_fingerprint(checkpoint: str | Path) -> dict:
    """The checkpoint's name, weights file and two hashes, as the one-plan certificate
    records them (its own hashing, so the two certificates name a checkpoint alike)."""
    weights_sha, function_sha, meta = cert._checkpoint_hashes(checkpoint)
    weights, _ = checkpoint_paths(checkpoint)
    return {"name": meta.get("name"), "weights_file": weights.name,
            "weights_sha256": weights_sha, "function_sha256": function_sha}


def _assumptions(s: ClosedLoopSettings) -> dict:
    parts = s.parts
    return {"loop": asdict(s.assumptions), "grid": {**asdict(s.grid), "shape": list(
                s.grid.shape)},
            "time_gap_s": list(s.time_gap_s), "brake_guard": s.guard,
            "vehicle": asdict(parts.vehicle), "controller": asdict(parts.controller),
            "guard_settings": asdict(parts.guard) if parts.guard is not None else None,
            "float_margin": li.FLOAT_MARGIN}


def build(result: ClosedLoopResult, checkpoint: str | Path, floor_file: str | None) -> dict:
    """The certificate's JSON content (:class:`ClosedLoopError` if its verdict, failing
    count and share disagree)."""
    body = {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "checkpoint": checkpoint_fingerprint(checkpoint), "policy": result.policy,
        "covers": COVERS, "assumptions": _assumptions(result.settings),
        "verdict": result.verdict, "proven": result.proven,
        "share_of_recoverable_envelope": result.share, "share_stderr": result.share_stderr,
        "share_measure": f"envelope_share: {SHARE_SAMPLES} draws (seed {SHARE_SEED}) of "
                         "(v, v_l, f), the gap integrated exactly; 0 unless proven",
        "columns": result.columns, "failing_columns": result.failing_columns,
        "columns_with_states": result.columns_with_states,
        "speed_exit_columns": result.speed_exit_columns,
        "deficit_median_m": result.deficit_median_m, "deficit_max_m": result.deficit_max_m,
        "unbounded_deficits": result.unbounded_deficits,
        "failing_by_reason": result.failing_by_reason,
        "reasons": {str(k): text for k, text in enumerate(lb.REASONS)},
        "worst_cells": result.worst, "floor": {**result.floor, "file": floor_file},
        "search": result.search, "seconds": result.seconds,
        "versions": {"safeil_sumo": __version__, "numpy": np.__version__,
                     "python": platform.python_version()},
        "created_unix_s": time.time(),
    }
    consistent(body, "the result")
    return body


def consistent(body: dict, where: str) -> None:
    """:class:`ClosedLoopError` unless the verdict is the one the counts allow, ``proven``
    agrees with it, and a share is claimed only for a proof."""
    try:
        want = verdict_of(int(body["failing_columns"]), int(body["columns_with_states"]))
        share = float(body["share_of_recoverable_envelope"])
        proven, verdict = body["proven"], body["verdict"]
    except (KeyError, TypeError, ValueError) as exc:
        raise ClosedLoopError(f"{where}: incomplete closed-loop certificate ({exc})") from None
    if verdict != want or proven is not (want != NOT_PROVEN) or (not proven and share != 0.0):
        raise ClosedLoopError(
            f"{where}: inconsistent verdict {verdict!r} (proven {proven!r}, share {share:g}) "
            f"for {body['failing_columns']} failing columns")


def write(result: ClosedLoopResult, checkpoint: str | Path,
          out_dir: str | Path | None = None) -> Path:
    """Write the certificate and its floor file next to the checkpoint (or into
    ``out_dir``); returns the certificate's path."""
    from safetensors.numpy import save

    path = certificate_path(checkpoint, out_dir)
    floor_path = certificate_path(checkpoint, out_dir, FLOOR_SUFFIX)
    blob = save({k: np.ascontiguousarray(v) for k, v in result.arrays.items()},
                metadata={"format": FORMAT + "-floor", "format_version": str(FORMAT_VERSION)})
    body = build(result, checkpoint, floor_path.name)
    body["floor"]["file_sha256"] = hashlib.sha256(blob).hexdigest()
    text = json.dumps(body, indent=1, allow_nan=False) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(floor_path) as tmp:
        tmp.write_bytes(blob)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def read(path: str | Path) -> dict:
    """A closed-loop certificate's JSON, format and verdict checked; :class:`ClosedLoopError`
    naming the file."""
    path = Path(path)
    try:
        body = json.loads(path.read_text())
    except FileNotFoundError:
        raise ClosedLoopError(f"{path}: no closed-loop certificate") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ClosedLoopError(f"{path}: unreadable closed-loop certificate ({exc})") from None
    if not isinstance(body, dict) or body.get("format") != FORMAT:
        raise ClosedLoopError(f"{path}: not a {FORMAT} file")
    if body.get("format_version") != FORMAT_VERSION:
        raise ClosedLoopError(f"{path}: format version {body.get('format_version')!r}, this "
                              f"code reads {FORMAT_VERSION}")
    consistent(body, str(path))
    return body


def read_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """The floor file's arrays (``floor``, ``deficit``, ``reason``, ``row``)."""
    from safetensors.numpy import load

    return load(Path(path).read_bytes())


def settings_of(body: dict) -> ClosedLoopSettings:
    """The :class:`ClosedLoopSettings` a certificate records."""
    a = body["assumptions"]
    loop: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                            for k, v in a["loop"].items()}
    grid = {k: tuple(v) for k, v in a["grid"].items() if k != "shape"}
    return ClosedLoopSettings(tuple(a["time_gap_s"]), bool(a["brake_guard"]), li.Grid(**grid),
                              li.LoopAssumptions(**loop),
                              float((body.get("search") or {}).get("budget_s", 0.0)))


@dataclass(frozen=True)
class ClosedLoopStatus:
    """Whether a checkpoint has a valid closed-loop certificate, and what it says."""

    valid: bool
    reason: str  # why not, or "ok"
    path: Path
    certificate: dict | None

    @property
    def proven(self) -> bool:
        return self.valid and self.certificate is not None and self.certificate["proven"] is True


def load(checkpoint: str | Path, path: str | Path | None = None) -> ClosedLoopStatus:
    """Whether ``checkpoint`` has a valid closed-loop certificate (``path``: its file, default
    beside the checkpoint): readable, consistent, and both hashes the checkpoint's now."""
    path = Path(path) if path is not None else certificate_path(checkpoint)
    try:
        body = read(path)
    except ClosedLoopError as exc:
        return ClosedLoopStatus(False, str(exc), path, None)
    try:
        now = checkpoint_fingerprint(checkpoint)
    except CheckpointError as exc:
        return ClosedLoopStatus(False, f"checkpoint unreadable: {exc}", path, body)
    recorded = body.get("checkpoint") or {}
    for key, what in (("weights_sha256", "weights"), ("function_sha256", "sidecar")):
        if recorded.get(key) != now[key]:
            return ClosedLoopStatus(False, f"sha256 mismatch: the checkpoint's {what} changed "
                                    "since it was checked", path, body)
    return ClosedLoopStatus(True, "ok", path, body)
