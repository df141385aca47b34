"""Certify a planner network's margins over its operating envelope (issue 23, part 1).

For each margin (the leader margin and the lane margin, :mod:`safeil_sumo.learn.certify_margins`)
a branch and bound over the envelope's boxes: boxes are taken largest share of the envelope
first (ties by creation order), bounded in batches (IBP + CROWN), searched for counterexamples
where unproven (the bound's minimising corner, the centre and seeded random points, each
evaluated with :class:`MLPPolicy` and the numpy reference margins) and split in half along the
dimension whose split promises the most (:func:`safeil_sumo.learn.bounds.split_scores`), until
every box is proven, or the budget (time or boxes, shared equally by the margins) runs out.

The result is the certified fraction of the envelope's volume per margin (a lower bound: boxes
cut by the recoverable condition count by a lower Riemann sum of their recoverable volume, the
envelope's by an upper one), the volume holding a confirmed counterexample, the rest (unknown),
where the unproven volume lies, and the worst counterexamples.
"""

from __future__ import annotations

import heapq
import time
from dataclasses import dataclass, field

import numpy as np

from safeil_sumo.learn.certify_margins import (
    DV,
    FLOAT_MARGIN_M,
    GAP,
    MARGIN_ROWS,
    MARGINS,
    ROW_NAMES,
    BoxBounds,
    CertEnvelope,
    CertifyError,
    Properties,
    V,
    bound_boxes,
    box_shares,
    envelope_volume,
    planner_layers,
    reference_margins,
)
from safeil_sumo.learn.inference import MLPPolicy

__all__ = ["Budget", "CertEnvelope", "CertifyError", "CertifyResult", "MarginResult",
           "Properties", "certify"]
PARTS = ("leader", "free")


@dataclass(frozen=True)
class Budget:
    """When branch and bound stops (whichever comes first), shared equally by the margins."""

    seconds: float = 600.0  # wall time for all margins [s]
    boxes: int | None = None  # boxes bounded for all margins [-]; None: no limit (set it for a
    # reproducible run: the time limit depends on the machine)
    batch: int = 512  # boxes bounded together [-]
    cex_min_share: float = 1e-10  # a box holding a counterexample is split further only
    # while its share of the envelope exceeds this [-] (its other parts may be provable)
    cex_priority: float = 0.1  # a box holding a counterexample is taken as if its share
    # were this times smaller: boxes not yet refuted are refined first [-]
    n_random: int = 4  # random points per unproven box tried as counterexamples [-]
    seed: int = 0  # seeds the random points [-]

    def __post_init__(self) -> None:
        if not self.seconds > 0:
            raise CertifyError(f"the time budget must be > 0 s, got {self.seconds}")
        if self.boxes is not None and self.boxes < 1:
            raise CertifyError(f"the box budget must be >= 1, got {self.boxes}")
        if self.batch < 1 or self.n_random < 0 or not 0 < self.cex_priority <= 1:
            raise CertifyError("batch must be >= 1, n_random >= 0 and cex_priority in (0, 1]")


@dataclass(frozen=True)
class MarginResult:
    """One margin's outcome; shares of the envelope's volume, mass-weighted over its leader and
    no-leader parts (``certified`` is a lower bound)."""

    margin: str
    certified: float  # certified share of the envelope [-]
    certified_by_part: dict  # per part ("leader", "free") [-]
    with_counterexample: float  # share in final boxes holding a confirmed violation [-]
    unknown: float  # the rest: neither proven nor refuted within the budget [-]
    boxes_bounded: int  # [-]
    proven_boxes: int  # boxes on which the margin was proven (the certificate's leaves) [-]
    counterexample_boxes: int  # unproven boxes holding a confirmed violation [-]
    open_boxes: int  # unproven boxes left [-]
    seconds: float  # wall time of this margin's branch and bound [s]
    stopped_by: str  # "proven", "seconds", "boxes" or "small" (only counterexample boxes left)
    unproven_by_dim: dict  # per dimension: share of the unproven volume in each quarter of its
    # range (the gap's in log d) [-]
    counterexamples: list  # the worst confirmed violations (dicts, worst first)
    unproven_boxes: list  # the largest unproven boxes (dicts)
    proven_summary: dict  # proven boxes: count, smallest and median share, depth range
    boxes: dict = field(default_factory=dict, repr=False)  # arrays (not written to JSON):
    # proven_lo, proven_hi (K, n_z), proven_part (K,); open_lo, open_hi, open_part, open_cex_z


@dataclass(frozen=True)
class CertifyResult:
    """What :func:`certify` measured; :mod:`safeil_sumo.learn.certificate` writes it out."""

    policy: str
    envelope: CertEnvelope
    properties: Properties
    style: dict  # the style setting certified (a range with --time-gap-range-s), {} without style
    margins: dict  # margin name -> MarginResult
    seconds: float  # [s]
    budget: Budget
    volumes: dict  # part -> (lower, upper) bound of its volume in the envelope's coordinates
    float_margin_m: float = FLOAT_MARGIN_M  # [m]


def _style_setting(policy: MLPPolicy, env: CertEnvelope) -> tuple[bool, dict]:
    if env.time_gap_s is not None:
        if "time_gap_s" not in policy.style_names:
            raise CertifyError(f"{policy.name} has no style input: --time-gap-range-s applies "
                               "only to "
                               "style-conditioned checkpoints")
        return True, {"time_gap_s": [float(v) for v in env.time_gap_s]}
    return False, {k: float(v) for k, v in policy.style.items()}


@dataclass
class _Tree:
    """Boxes by id for one margin: bounds, part, shares, proof, counterexample."""

    n_z: int
    cap: int = 4096
    n: int = 0
    FIELDS = (("lo", "z"), ("hi", "z"), ("part", np.int8), ("share_lo", float),
              ("share_hi", float), ("proven", bool), ("cex_val", float), ("cex_z", "z"),
              ("depth", np.int32), ("lower", float))

    def __post_init__(self) -> None:
        for name, kind in self.FIELDS:
            shape = (self.cap, self.n_z) if kind == "z" else (self.cap,)
            setattr(self, name, np.empty(shape, float if kind == "z" else kind))

    def add(self, **cols) -> np.ndarray:
        k = len(cols["lo"])
        if self.n + k > self.cap:
            cap = max(self.n + k, 2 * self.cap)
            for name, _ in self.FIELDS:
                old = getattr(self, name)
                new = np.empty((cap, *old.shape[1:]), old.dtype)
                new[: self.n] = old[: self.n]
                setattr(self, name, new)
            self.cap = cap
        ids = np.arange(self.n, self.n + k)
        for name, value in cols.items():
            getattr(self, name)[ids] = value
        self.lower[ids] = -np.inf
        self.n += k
        return ids


def _candidates(env: CertEnvelope, lo, hi, part, coef, rng, n_random):
    """Points ``(N, K, n_z)`` to try as counterexamples and whether each is in the envelope:
    the corner minimising the bound's linear part, the centre, random points; a leader state
    below the recoverable gap is lifted onto it (if still inside the box)."""
    n, d = lo.shape
    vertex = np.where(coef > 0, lo, hi)
    pts = np.concatenate([vertex[:, None], 0.5 * (lo + hi)[:, None],
                          lo[:, None] + rng.uniform(size=(n, n_random, d)) * (hi - lo)[:, None]],
                         axis=1)
    lead = (part == 0)[:, None]
    closing = np.clip(np.minimum(-pts[..., DV], pts[..., V]), 0.0, None)
    floor = closing * closing / (2.0 * env.brake_mps2)
    lift = lead & (pts[..., GAP] <= floor)
    pts[..., GAP] = np.where(lift, floor * (1 + 1e-9) + 1e-9, pts[..., GAP])
    ok = (~lead | env.recoverable(pts)) & (pts[..., GAP] <= hi[:, None, GAP])
    return pts, ok


def _search(policy, env, props, tree, ids, bb, margin, rng, n_random) -> None:
    """Counterexample search in the boxes ``ids``: records the worst violation found per box."""
    rows = bb.lower.argmin(axis=1)
    coef = bb.coef[np.arange(len(ids)), rows]
    pts, ok = _candidates(env, tree.lo[ids], tree.hi[ids], tree.part[ids], coef, rng, n_random)
    n, k, d = pts.shape
    m = reference_margins(policy, env.features(pts.reshape(-1, d)), props).reshape(n, k, 15)
    worst = np.where(ok, m[..., MARGIN_ROWS[margin]].min(axis=2), np.inf)  # (N, K)
    best = worst.argmin(axis=1)
    val = worst[np.arange(n), best]
    hit = (val < 0.0) & (val < tree.cex_val[ids])
    tree.cex_val[ids[hit]] = val[hit]
    tree.cex_z[ids[hit]] = pts[np.arange(n), best][hit]


def _split(env, tree, ids, dims, weights) -> np.ndarray:
    """Split each box in two along ``dims`` (the gap at its geometric mean); returns the new
    ids (children with no recoverable state are dropped). A counterexample stays with the
    child holding it."""
    lo, hi = tree.lo[ids], tree.hi[ids]
    r = np.arange(len(ids))
    cut = 0.5 * (lo[r, dims] + hi[r, dims])
    gap = dims == GAP
    cut[gap] = np.sqrt(lo[r, dims][gap] * hi[r, dims][gap])
    hi_a, lo_b = hi.copy(), lo.copy()
    hi_a[r, dims] = cut
    lo_b[r, dims] = cut
    c_lo, c_hi = np.concatenate([lo, lo_b]), np.concatenate([hi_a, hi])
    parent = np.concatenate([ids, ids])
    part = tree.part[parent]
    s_lo, s_hi = np.empty(len(parent)), np.empty(len(parent))
    for p, name in enumerate(PARTS):
        sel = part == p
        if sel.any():
            a, b = box_shares(env, c_lo[sel], c_hi[sel], name)
            s_lo[sel], s_hi[sel] = a / weights[name][1], b / weights[name][1]
    keep = s_hi > 0
    cz = tree.cex_z[parent]
    inside = np.all((cz >= c_lo) & (cz <= c_hi), axis=1)
    return tree.add(lo=c_lo[keep], hi=c_hi[keep], part=part[keep], share_lo=s_lo[keep],
                    share_hi=s_hi[keep], proven=False,
                    cex_val=np.where(inside, tree.cex_val[parent], np.inf)[keep],
                    cex_z=np.where(inside[:, None], cz, np.nan)[keep],
                    depth=tree.depth[parent][keep] + 1)


def _roots(env: CertEnvelope, tree: _Tree, weights: dict, heap: list) -> None:
    for p, (name, (lo, hi)) in enumerate(env.root_boxes().items()):
        if weights[name][0] <= 0:
            continue
        s_lo, s_hi = box_shares(env, lo[None], hi[None], name)
        (i,) = tree.add(lo=lo[None], hi=hi[None], part=p, share_lo=s_lo / weights[name][1],
                        share_hi=s_hi / weights[name][1], proven=False, cex_val=np.inf,
                        cex_z=np.nan, depth=0)
        heapq.heappush(heap, (-weights[name][0] * tree.share_hi[i], int(i)))


def _branch_and_bound(policy, env, props, layers, margin, seconds, max_boxes, budget,
                      volumes, progress) -> MarginResult:
    """One margin's branch and bound (``volumes``: each part's volume bounds); see the module
    docstring."""
    from tqdm import tqdm

    weights = {name: (w, volumes[name][1]) for name, w in env.part_weights().items()}
    w_part = np.array([weights[p][0] for p in PARTS])
    tree, heap = _Tree(len(env.dims)), []
    _roots(env, tree, weights, heap)
    proven_mass, finished = np.zeros(len(PARTS)), []
    start, bounded, it, stopped_by = time.perf_counter(), 0, 0, "proven"
    bar = tqdm(desc=f"{policy.name} {margin}", unit="box", disable=not progress or None,
               total=max_boxes)
    while heap:
        if time.perf_counter() - start > seconds:
            stopped_by = "seconds"
            break
        if max_boxes is not None and bounded >= max_boxes:
            stopped_by = "boxes"
            break
        take = budget.batch if max_boxes is None else min(budget.batch, max_boxes - bounded)
        ids = np.array([heapq.heappop(heap)[1] for _ in range(min(take, len(heap)))])
        bounded += len(ids)
        bb = bound_boxes(layers, props, tree.lo[ids], tree.hi[ids], margin)
        lower = bb.lower.min(axis=1)
        tree.lower[ids] = lower
        proven = lower >= FLOAT_MARGIN_M
        tree.proven[ids] = proven
        np.add.at(proven_mass, tree.part[ids[proven]],
                  tree.share_lo[ids[proven]] * w_part[tree.part[ids[proven]]])
        todo = ~proven
        if todo.any():
            rng = np.random.default_rng([budget.seed, MARGINS.index(margin), it])
            sub = BoxBounds(bb.lower[todo], bb.coef[todo], bb.score[todo])
            _search(policy, env, props, tree, ids[todo], sub, margin, rng, budget.n_random)
            small = w_part[tree.part[ids]] * tree.share_hi[ids] <= budget.cex_min_share
            final = todo & small & np.isfinite(tree.cex_val[ids])
            finished.extend(ids[final].tolist())
            split = todo & ~final
            if split.any():
                width = tree.hi[ids[split]] - tree.lo[ids[split]]
                score = bb.score[split][np.arange(split.sum()), bb.lower[split].argmin(axis=1)]
                dims = np.where(width > 0, score + 1e-12 * width, -1.0).argmax(axis=1)
                for c in _split(env, tree, ids[split], dims, weights):
                    rank = w_part[tree.part[c]] * tree.share_hi[c]
                    if np.isfinite(tree.cex_val[c]):
                        rank *= budget.cex_priority
                    heapq.heappush(heap, (-rank, int(c)))
        it += 1
        bar.update(len(ids))
        bar.set_postfix(certified=f"{proven_mass.sum():.4f}", refresh=False)
    else:
        stopped_by = "proven" if not finished else "small"
    bar.close()
    open_ids = np.array(finished + [i for _, i in heap], dtype=int)
    return _margin_result(policy, env, props, tree, margin, open_ids, proven_mass, w_part,
                          volumes, (bounded, time.perf_counter() - start, stopped_by))


def certify(policy: MLPPolicy, env: CertEnvelope | None = None,
            props: Properties | None = None, budget: Budget | None = None,
            margins: tuple[str, ...] = MARGINS, progress: bool = True) -> CertifyResult:
    """Certify ``policy`` (at its current style, or over ``env.time_gap_s``) on ``env``
    (default :class:`CertEnvelope`): one branch and bound per margin, each with an equal share
    of ``budget`` (default :class:`Budget`); ``props`` default from the checkpoint's
    metadata."""
    from threadpoolctl import threadpool_limits

    env = env or CertEnvelope()
    budget = budget or Budget()

    unknown = set(margins) - set(MARGINS)
    if unknown or not margins:
        raise CertifyError(f"margins must be among {MARGINS}, got {list(margins)}")
    style_range, style = _style_setting(policy, env)
    props = props or Properties.from_metadata(policy.metadata, env.brake_mps2)
    if (policy.lateral_mode == "lane") != (props.lane_keep_m is not None):
        raise CertifyError(f"{policy.name}: lateral mode {policy.lateral_mode!r} but the "
                           f"properties' lane_keep_m is {props.lane_keep_m}: the lane margin "
                           "would be bounded for the other head")
    layers = planner_layers(policy, style_range)
    volumes = {p: envelope_volume(env, p) for p in PARTS}
    start = time.perf_counter()
    share = 1.0 / len(margins)
    results = {}
    with threadpool_limits(limits=1, user_api="blas"):
        for m in margins:
            results[m] = _branch_and_bound(
                policy, env, props, layers, m, budget.seconds * share,
                None if budget.boxes is None else max(1, int(budget.boxes * share)), budget,
                volumes, progress)
    return CertifyResult(policy.name, env, props, style, results, time.perf_counter() - start,
                         budget, volumes)


def _zdict(env: CertEnvelope, z: np.ndarray) -> dict:
    return {n: float(v) for n, v in zip(env.dims, z, strict=True)}


def _unproven_by_dim(env: CertEnvelope, lo: np.ndarray, hi: np.ndarray, mass: np.ndarray,
                     bins: int = 4) -> dict:
    """Per dimension, the share of ``mass`` in each of ``bins`` equal parts of its range (the
    gap's in log d), each box's mass spread uniformly over its extent."""
    root_lo, root_hi = env.root_boxes()["leader"]
    out = {}
    total = max(float(mass.sum()), 1e-300)
    for j, name in enumerate(env.dims):
        f = np.log if j == GAP else (lambda a: a)
        a, b = f(root_lo[j]), f(root_hi[j])
        edges = a + (b - a) * np.arange(bins + 1) / bins
        x0, x1 = f(lo[:, j]), f(hi[:, j])
        width = x1 - x0
        share = np.empty((len(lo), bins))
        for q in range(bins):
            overlap = np.clip(np.minimum(x1, edges[q + 1]) - np.maximum(x0, edges[q]), 0, None)
            point = (width <= 0) & (x0 >= edges[q]) & ((x0 < edges[q + 1]) | (q == bins - 1))
            share[:, q] = np.where(width > 0, overlap / np.where(width > 0, width, 1.0), point)
        out[name] = [round(float(v), 4) for v in (mass[:, None] * share).sum(axis=0) / total]
    return out


def _diverse(env: CertEnvelope, tree: _Tree, ids: np.ndarray, k: int = 20,
             min_dist: float = 0.15) -> np.ndarray:
    """Up to ``k`` of the boxes ``ids`` (sorted worst counterexample first) whose
    counterexamples are at least ``min_dist`` apart (max-norm, each coordinate scaled to its
    range, the gap in log d): the worst violation of each region, not k copies of one."""
    lo, hi = env.root_boxes()["leader"]
    lo, hi = lo.copy(), hi.copy()
    lo[GAP], hi[GAP] = np.log(lo[GAP]), np.log(hi[GAP])
    scale = np.where(hi > lo, hi - lo, 1.0)
    picked: list[int] = []
    points: list[np.ndarray] = []
    for i in ids[: 200 * k]:
        z = tree.cex_z[i].copy()
        z[GAP] = np.log(z[GAP])
        z = (z - lo) / scale
        if all(np.max(np.abs(z - q)) >= min_dist for q in points):
            picked.append(int(i))
            points.append(z)
            if len(picked) == k:
                break
    return np.array(picked, dtype=int)


def certified_mass(proven: np.ndarray, open_: np.ndarray, weights: np.ndarray,
                   volumes: np.ndarray) -> np.ndarray:
    """Certified share of the envelope per part ``(P,)``: the larger of two sound lower bounds.

    ``proven (P,)``: the proven boxes' mass (weight times their share of the part's volume,
    shares from the boxes' smallest volume); ``open_ (P,)``: the open boxes' mass from their
    largest volume; ``weights (P,)``: each part's weight; ``volumes (P, 2)``: each part's
    ``(lower, upper)`` volume bound. Shares are of the part's UPPER volume, and the leaves
    partition the part, so the open boxes hold at most ``open_ upper / lower`` of the weight:
    what is left of the weight is proven. Rest below 1e-12 (sums that round) counts as 0.
    """
    rest = weights - volumes[:, 1] / volumes[:, 0] * open_
    return np.maximum(proven, np.where(rest > 1e-12, rest, 0.0))


def _margin_result(policy, env, props, tree, margin, open_ids, proven_mass, w_part, volumes,
                   run) -> MarginResult:
    bounded, seconds, stopped_by = run
    n = tree.n
    mass = w_part[tree.part[open_ids]] * tree.share_hi[open_ids]
    has = np.isfinite(tree.cex_val[open_ids])
    # two sound lower bounds, the larger wins: the proven boxes' smallest volume, and what the
    # open boxes' largest volume leaves (the leaves partition the envelope; a box cut by the
    # recoverable condition has only bounds of its volume, shares are of the part's upper one)
    open_mass = np.bincount(tree.part[open_ids], weights=mass, minlength=len(PARTS))
    proven_mass = certified_mass(proven_mass, open_mass, w_part,
                                 np.array([volumes[p] for p in PARTS]))
    certified = float(proven_mass.sum())
    cex_share = float(mass[has].sum())
    cexs = []
    order = _diverse(env, tree, open_ids[has][np.argsort(tree.cex_val[open_ids[has]],
                                                         kind="stable")])
    if len(order):
        z = tree.cex_z[order]
        again = reference_margins(policy, env.features(z), props)  # confirm each one
        sl = MARGIN_ROWS[margin]
        for k, i in enumerate(order):
            row = sl.start + int(np.argmin(again[k, sl]))
            cexs.append({"row": ROW_NAMES[row], "margin_m": float(again[k, row]),
                         "confirmed": bool(again[k, row] < 0.0), "part": PARTS[tree.part[i]],
                         "z": _zdict(env, z[k]),
                         "features": [float(v) for v in env.features(z[k])]})
    unproven = []
    for i in open_ids[np.argsort(-mass, kind="stable")][:10]:
        unproven.append({"part": PARTS[tree.part[i]],
                         "share": float(w_part[tree.part[i]] * tree.share_hi[i]),
                         "lower_bound_m": (float(tree.lower[i]) if np.isfinite(tree.lower[i])
                                           else None),
                         "counterexample_m": (float(tree.cex_val[i])
                                              if np.isfinite(tree.cex_val[i]) else None),
                         "lo": _zdict(env, tree.lo[i]), "hi": _zdict(env, tree.hi[i])})
    proven = np.flatnonzero(tree.proven[:n])
    shares = w_part[tree.part[proven]] * tree.share_lo[proven]
    summary = {"count": len(proven),
               "smallest_share": float(shares.min()) if len(proven) else None,
               "median_share": float(np.median(shares)) if len(proven) else None,
               "depth_range": ([int(tree.depth[proven].min()), int(tree.depth[proven].max())]
                               if len(proven) else None)}
    return MarginResult(
        margin, certified,
        {p: float(proven_mass[k] / w_part[k]) if w_part[k] > 0 else None
         for k, p in enumerate(PARTS)},
        cex_share, max(0.0, 1.0 - certified - cex_share), bounded, len(proven),
        int(has.sum()), len(open_ids), seconds, stopped_by,
        _unproven_by_dim(env, tree.lo[open_ids], tree.hi[open_ids], mass), cexs, unproven,
        summary, {"proven_lo": tree.lo[proven], "proven_hi": tree.hi[proven],
                  "proven_part": tree.part[proven], "open_lo": tree.lo[open_ids],
                  "open_hi": tree.hi[open_ids], "open_part": tree.part[open_ids],
                  "open_cex_z": tree.cex_z[open_ids]})
