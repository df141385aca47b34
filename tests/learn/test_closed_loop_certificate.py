"""The closed-loop certificate (safeil_sumo.learn.closed_loop_certificate): the shipped safeil's
check fails and its file says so, counted again from the floor file's arrays; a file never says
proven of a failing check; a vacuous pass has no share; the file round-trips."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil

import numpy as np
import pytest
from safetensors import safe_open
from safetensors.numpy import load_file, save_file

from safeil_sumo.learn import closed_loop_certificate as clc
from safeil_sumo.learn import loop_barrier as lb
from safeil_sumo.learn import loop_invariant as li
from safeil_sumo.learn.checkpoint import checkpoint_paths
from safeil_sumo.planners import registry as pol

COARSE = (7.5, 2.5, 2.5, 3.0)  # 20 x 20 x 16 x 4 cells: about a second


@pytest.fixture(scope="module")
def safeil():
    return pol.load("safeil")


@pytest.fixture(scope="module")
def settings() -> clc.ClosedLoopSettings:
    return clc.ClosedLoopSettings((1.5, 1.5), True, clc.grid_with_widths(COARSE))


@pytest.fixture(scope="module")
def shipped_result(safeil, settings) -> clc.ClosedLoopResult:
    return clc.run(safeil, settings)


def _copy_checkpoint(name: str, folder) -> str:
    weights, sidecar = checkpoint_paths(pol.shipped_checkpoint(name))
    shutil.copy(weights, folder / weights.name)
    shutil.copy(sidecar, folder / sidecar.name)
    return str(folder / weights.name)


def test_the_verdict_by_hand() -> None:
    assert clc.verdict_of(1, 5) == clc.verdict_of(7, 0) == clc.NOT_PROVEN == "not proven"
    assert clc.verdict_of(0, 3) == clc.PROVEN
    assert clc.verdict_of(0, 0) == clc.PROVEN_EMPTY


def test_the_shipped_safeil_is_not_proven(shipped_result, settings) -> None:
    """As docs/certification.md measures on the fine grid: most columns fail, h falling below
    0 the reason; no share is claimed."""
    r = shipped_result
    assert r.verdict == clc.NOT_PROVEN and r.proven is False
    assert (r.share, r.share_stderr) == (0.0, 0.0) and "share" not in r.seconds
    assert r.columns == 20 * 16 * 4 and 0.5 * r.columns < r.failing_columns < r.columns
    assert sum(r.failing_by_reason.values()) == r.failing_columns
    assert r.failing_by_reason.get(lb.REASONS[lb.INCREMENT], 0) > 0.5 * r.failing_columns
    assert 0.0 < r.deficit_median_m <= r.deficit_max_m
    # the worst cells: failing, largest first, each a cell of the grid
    deficits = [c["deficit_m"] for c in r.worst]
    assert len(r.worst) == clc.WORST_KEPT and deficits == sorted(deficits, reverse=True)
    assert deficits[0] == r.deficit_max_m and min(deficits) > 0.0
    axes = settings.grid.axes()
    for c in r.worst:
        assert lb.REASONS[c["reason"]] == c["reason_text"] and c["reason"] != lb.OK
        for dim, edges in zip(clc.DIMS, axes, strict=True):
            lo, hi = c[dim]
            i = int(np.flatnonzero(np.isclose(edges, lo))[0])
            assert hi == pytest.approx(edges[i + 1])
    assert r.floor["source"] == "recoverable boundary"
    base = lb.recoverable_floor(settings.grid, settings.assumptions, settings.parts)
    assert np.array_equal(r.arrays["floor"], base)


def test_the_file_says_not_proven_counted_again_from_its_arrays(shipped_result,
                                                                tmp_path) -> None:
    path = _copy_checkpoint("safeil", tmp_path)
    written = clc.write(shipped_result, path)
    assert written == tmp_path / "safeil.closed_loop_certificate.json"
    body = clc.read(written)
    assert body["verdict"] == "not proven" and body["proven"] is False
    assert body["share_of_recoverable_envelope"] == 0.0
    arrays = clc.read_arrays(tmp_path / body["floor"]["file"])
    deficit = arrays["deficit"]
    assert body["failing_columns"] == int(np.sum(deficit > 0.0)) > 0
    assert body["columns_with_states"] == int(np.sum(deficit > -np.inf))
    finite = deficit[(deficit > 0) & np.isfinite(deficit)]
    assert body["deficit_max_m"] == pytest.approx(float(finite.max()))
    assert body["deficit_median_m"] == pytest.approx(float(np.median(finite)))
    blob = (tmp_path / body["floor"]["file"]).read_bytes()
    assert body["floor"]["file_sha256"] == hashlib.sha256(blob).hexdigest()
    assert body["floor"]["sha256"] == hashlib.sha256(arrays["floor"].tobytes()).hexdigest()


@pytest.mark.parametrize("change", [
    {"proven": True},
    {"verdict": clc.PROVEN},
    {"verdict": clc.PROVEN, "proven": True},
    {"share_of_recoverable_envelope": 0.4},
    {"failing_columns": 0},  # proven False but nothing fails: the verdict must say proven
])
def test_a_file_never_says_proven_of_a_failing_check(shipped_result, tmp_path, change) -> None:
    """``build`` refuses a result whose verdict, count and share disagree, and ``read`` a file
    so edited; ``load`` reports such a file invalid and not proven."""
    path = _copy_checkpoint("safeil", tmp_path)
    written = clc.write(shipped_result, path)
    body = json.loads(written.read_text())
    written.write_text(json.dumps({**body, **change}))
    with pytest.raises(clc.ClosedLoopError, match=f"^{written}: inconsistent verdict"):
        clc.read(written)
    status = clc.load(path)
    assert not status.valid and not status.proven and "inconsistent verdict" in status.reason
    with pytest.raises(clc.ClosedLoopError, match="^x: inconsistent verdict"):
        clc.consistent({**clc.build(shipped_result, path, None), **change}, "x")
    bad = dataclasses.replace(shipped_result, share=0.4)  # a share claimed without a proof
    with pytest.raises(clc.ClosedLoopError, match="^the result: inconsistent verdict"):
        clc.build(bad, path, None)


def test_a_floor_at_the_ceiling_passes_vacuously_with_no_share(safeil, settings) -> None:
    """Every node above the top gap: S is empty, the check passes with no column holding a
    state of S; proven, vacuously, and S's share of the envelope is 0."""
    ceiling = float(settings.grid.axes()[0][-1]) + 1.0
    shape = tuple(len(e) for e in lb.lattice_axes(settings.grid))
    r = clc.run(safeil, settings, floor=np.full(shape, ceiling))
    assert r.proven and r.failing_columns == 0 and r.columns_with_states == 0
    assert r.verdict == clc.PROVEN_EMPTY and r.worst == []
    assert r.share == 0.0 and "share" in r.seconds  # measured, and 0
    assert r.floor["source"] == "given" and r.floor["nodes_above_top_gap"] == int(np.prod(shape))
    clc.consistent(clc.build(r, pol.shipped_checkpoint("safeil"), None), "vacuous")


def test_the_share_is_measured_only_for_a_passing_check(settings) -> None:
    """The same floor (the recoverable boundary: S is the whole envelope) with a planted check:
    failing, no share; passing (every column's deficit made <= 0: a synthetic check, not the
    loop's), the share is envelope_share's, just under 1."""
    phi = lb.recoverable_floor(settings.grid, settings.assumptions, settings.parts)
    n = tuple(s - 1 for s in phi.shape)
    deficit = np.full(n, -0.5)
    deficit[0, 0, 0] = 0.25
    failing = lb.BarrierCheck(deficit, np.full(n, lb.OK, np.int8), np.zeros(n, np.int16),
                              np.zeros(n, bool))
    failing.reason[0, 0, 0] = lb.INCREMENT
    got = clc.summarize("planted", settings, phi, failing, {}, None, {})
    assert got.verdict == clc.NOT_PROVEN and got.share == 0.0 and got.failing_columns == 1
    passing = dataclasses.replace(failing, deficit=np.minimum(deficit, 0.0))
    got = clc.summarize("planted", settings, phi, passing, {}, None, {})
    assert got.verdict == clc.PROVEN and got.columns_with_states == deficit.size
    # (the interpolated floor lies a little above the exact boundary between the nodes)
    assert 0.99 < got.share <= 1.0


def test_the_certificate_round_trips(shipped_result, settings, tmp_path) -> None:
    path = _copy_checkpoint("safeil", tmp_path)
    written = clc.write(shipped_result, path, tmp_path / "a" / "b")
    assert written == tmp_path / "a" / "b" / "safeil.closed_loop_certificate.json"
    text = written.read_text()
    body = clc.read(written)
    assert text == json.dumps(body, indent=1) + "\n"
    assert clc.settings_of(body) == settings
    assumed = body["assumptions"]
    assert set(assumed["loop"]) == {f.name for f in dataclasses.fields(li.LoopAssumptions)}
    assert assumed["grid"]["shape"] == list(settings.grid.shape)
    assert assumed["time_gap_s"] == [1.5, 1.5] and assumed["brake_guard"] is True
    assert assumed["guard_settings"]["reaction_s"] == 0.3
    for key in ("failing_columns", "columns", "deficit_median_m", "deficit_max_m",
                "failing_by_reason", "worst_cells"):
        assert body[key] == getattr(shipped_result, {"worst_cells": "worst"}.get(key, key))
    arrays = clc.read_arrays(written.with_name(body["floor"]["file"]))
    for k, v in shipped_result.arrays.items():
        assert np.array_equal(arrays[k], v) and arrays[k].dtype == v.dtype
    assert arrays["reason"].dtype == np.int8 and arrays["floor"].dtype == np.float64
    with safe_open(written.with_name(body["floor"]["file"]), framework="numpy") as f:
        assert f.metadata() == {"format": clc.FORMAT + "-floor",
                                "format_version": str(clc.FORMAT_VERSION)}
    assert body["checkpoint"]["weights_sha256"] == json.loads(
        (tmp_path / "safeil.json").read_text())["weights_sha256"]
    assert body["versions"]["safeil_sumo"] and body["seconds"]["total"] > 0
    # valid for this checkpoint; not for one whose sidecar changed
    assert clc.load(path, written).valid and clc.load(path, written).reason == "ok"
    assert not clc.load(path).valid  # none beside the checkpoint
    sidecar = tmp_path / "safeil.json"
    meta = json.loads(sidecar.read_text())
    sidecar.write_text(json.dumps({**meta, "style_default": {"time_gap_s": 2.5}}))
    status = clc.load(path, written)
    assert not status.valid and not status.proven
    assert status.reason == ("sha256 mismatch: the checkpoint's sidecar changed since it was "
                             "checked")
    assert status.path == written and status.certificate == body
    sidecar.write_text(json.dumps(meta))
    weights = tmp_path / "safeil.safetensors"
    tensors = load_file(weights)  # another network, its sidecar updated
    first = next(iter(tensors))
    save_file({**tensors, first: tensors[first] + 1e-3}, weights)
    sidecar.write_text(json.dumps(
        {**meta, "weights_sha256": hashlib.sha256(weights.read_bytes()).hexdigest()}))
    status = clc.load(path, written)
    assert status.reason == ("sha256 mismatch: the checkpoint's weights changed since it was "
                             "checked")
    assert status.path == written and status.certificate == body
    weights.write_bytes(b"")
    status = clc.load(path, written)
    assert not status.valid and status.reason.startswith("checkpoint unreadable: ")
    assert status.path == written and status.certificate == body


def test_settings_grids_and_files_refuse_what_they_cannot_do(tmp_path) -> None:
    assert clc.grid_with_widths((1.5, 0.5, 0.5, 1.5)) == li.Grid()
    for widths, message in (((7.0, 1, 1, 1), "not a whole number of cells"),
                            ((0.0, 1, 1, 1), "must be > 0")):
        with pytest.raises(clc.ClosedLoopError, match=message):
            clc.grid_with_widths(widths)
    for gaps in ((2.0, 1.0), (0.0, 1.0)):
        with pytest.raises(clc.ClosedLoopError, match="0 < LO <= HI"):
            clc.ClosedLoopSettings(gaps)
    with pytest.raises(clc.ClosedLoopError, match="not a whole number of cells"):
        clc.ClosedLoopSettings((1.0, 1.0), grid=li.Grid(gap_m=(1.0, 10.0, 2.0)))
    with pytest.raises(clc.ClosedLoopError, match=">= 0 s"):
        clc.ClosedLoopSettings((1.0, 1.0), search_s=-1.0)
    path = tmp_path / "c.json"
    for text, message in (("{no json", "unreadable closed-loop certificate"),
                          ("[1]", "not a safeil-closed-loop-certificate file"),
                          ('{"format": "safeil-certificate"}', "not a safeil-closed-loop"),
                          ('{"format": "safeil-closed-loop-certificate", "format_version": 9}',
                           "format version 9, this code reads 1"),
                          ('{"format": "safeil-closed-loop-certificate", "format_version": 1}',
                           "incomplete closed-loop certificate")):
        path.write_text(text)
        with pytest.raises(clc.ClosedLoopError, match=message):
            clc.read(path)
    with pytest.raises(clc.ClosedLoopError, match="no closed-loop certificate"):
        clc.read(tmp_path / "none.json")


def test_the_file_has_every_field_a_reader_needs(safeil, settings, tmp_path) -> None:
    """The file's schema, field by field, and the floor's summary recomputed from its array:
    readers of the certificate rely on these names (its own run: the test that runs the
    check is the one a mutation tool credits)."""
    path = _copy_checkpoint("safeil", tmp_path)
    body = clc.read(clc.write(clc.run(safeil, settings), path))
    assert set(body) == {
        "format", "format_version", "checkpoint", "policy", "covers", "assumptions", "verdict",
        "proven", "share_of_recoverable_envelope", "share_stderr", "share_measure", "columns",
        "failing_columns", "columns_with_states", "speed_exit_columns", "deficit_median_m",
        "deficit_max_m", "unbounded_deficits", "failing_by_reason", "reasons", "worst_cells",
        "floor", "search", "seconds", "versions", "created_unix_s"}
    assert body["policy"] == "safeil" and body["covers"] == clc.COVERS
    assert body["share_measure"].startswith(f"envelope_share: {clc.SHARE_SAMPLES} draws")
    assert body["checkpoint"]["name"] == "safeil"
    assert set(body["checkpoint"]) == {"name", "weights_file", "weights_sha256",
                                       "function_sha256"}
    assert body["checkpoint"]["weights_file"] == "safeil.safetensors"
    assert set(body["versions"]) == {"safeil_sumo", "numpy", "python"}
    assert body["versions"]["numpy"] == np.__version__
    assert body["assumptions"]["float_margin"] == li.FLOAT_MARGIN
    assert body["reasons"] == {str(k): t for k, t in enumerate(lb.REASONS)}
    floor = body["floor"]
    phi = clc.read_arrays(tmp_path / floor["file"])["floor"]
    top = settings.grid.axes()[0][-1]
    assert floor["node_axes"] == ["speed_mps", "leader_speed_mps", "force_mps2"]
    assert floor["nodes"] == list(phi.shape)
    assert (floor["min_m"], floor["median_m"], floor["max_m"]) == (
        float(phi.min()), float(np.median(phi)), float(phi.max()))
    assert floor["nodes_above_top_gap"] == int(np.sum(phi > top))
    lifted = np.full_like(phi, 100.0)  # by hand: one node above the top gap (151 m)
    lifted[3, 2, 1] = top + 1.0
    assert clc.floor_summary(lifted, settings.grid, settings, "x")["nodes_above_top_gap"] == 1
    assert floor["sha256"] == hashlib.sha256(phi.astype(np.float64).tobytes()).hexdigest()
    assert set(body["seconds"]) >= {"increments", "check", "total"}


def test_a_searched_floor_is_the_one_checked(safeil, settings) -> None:
    """With a search budget the floor checked is the search's last, its rounds recorded; the
    verdict stays the check's."""
    searched = dataclasses.replace(settings, search_s=1.0)
    r = clc.run(safeil, searched)
    assert r.verdict == clc.NOT_PROVEN
    assert r.search["budget_s"] == 1.0 and r.search["stopped_by"] in ("budget", "rounds")
    rounds = r.search["rounds"]
    assert rounds and all(set(x) == {"failing_columns", "max_finite_deficit_m", "seconds"}
                          for x in rounds)
    assert rounds[-1]["failing_columns"] == r.failing_columns
    assert r.floor["source"] == f"synthesize: last of {len(rounds)} checks"
    base = lb.recoverable_floor(settings.grid, settings.assumptions, settings.parts)
    assert np.all(r.arrays["floor"] >= base) and not np.array_equal(r.arrays["floor"], base)
    assert 0.0 < r.seconds["search"] <= r.seconds["total"]
    body = clc.build(r, pol.shipped_checkpoint("safeil"), None)
    assert clc.settings_of(body) == searched and body["search"]["budget_s"] == 1.0
