"""n74: geometry of the generated road (committed files) and its generator."""

from __future__ import annotations

import itertools
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.roads import n74

NET = n74.n74_dir() / "n74.net.xml"


def _lanes(edge_prefix: str = "") -> dict[str, tuple[int, np.ndarray]]:
    """Lane id -> (edge's lane count, shape) of the committed net's non-internal edges."""
    root = ET.parse(NET).getroot()
    out = {}
    for e in root.iter("edge"):
        if e.get("function") == "internal" or not e.get("id", "").startswith(edge_prefix):
            continue
        lanes = list(e.iter("lane"))
        for ln in lanes:
            pts = np.array([[float(v) for v in p.split(",")[:2]] for p in ln.get("shape").split()])
            out[ln.get("id")] = (len(lanes), pts)
    return out


def circumradius(p: np.ndarray) -> np.ndarray:
    """Radius [m] of the circle through each three consecutive points (inf on straights)."""
    a, b, c = p[:-2], p[1:-1], p[2:]
    ab, bc, ca = (np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                  np.linalg.norm(a - c, axis=1))
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    with np.errstate(divide="ignore"):
        return np.where(cross > 1e-9, ab * bc * ca / (2.0 * cross), np.inf)


def test_length_is_29_2_km_along_the_reference_and_lanes():
    geo = n74.n74_geometry()
    assert geo.length == pytest.approx(29_200.0, rel=0.01)
    main = [lid for lid in _lanes() if lid.startswith(("main", "merge"))]
    for lane in (0, 1):  # the ego's lane chain (merge edges: the same lanes are 1 and 2)
        ids = [f"{e}_{lane + (1 if e.startswith('merge') else 0)}" for e, _, _ in geo.edges]
        assert set(ids) <= set(main)
        total = sum(Polyline(_lanes()[i][1]).length for i in ids)
        assert total == pytest.approx(29_200.0, rel=0.01)


def test_two_lanes_per_direction_and_acceleration_lanes():
    lanes = _lanes()
    for lid, (count, _) in lanes.items():
        if lid.startswith(("main", "opp_")):
            assert count == 2, lid
        elif lid.startswith("merge"):
            assert count == 3, lid


def test_ramps_present_and_joined_to_the_acceleration_lane():
    meta = json.loads((n74.n74_dir() / "n74.json").read_text())
    assert 4 <= len(meta["ramps"]) <= 6
    root = ET.parse(NET).getroot()
    conns = {(c.get("from"), c.get("to"), c.get("fromLane"), c.get("toLane"))
             for c in root.iter("connection")}
    for ramp in meta["ramps"]:
        assert (ramp["id"], ramp["merge_edge"], "0", "0") in conns
        # the acceleration lane (index 0) has no successor: SUMO's cars must merge left
        assert not any(c[0] == ramp["merge_edge"] and c[2] == "0" and not c[1].startswith(":")
                       for c in conns)
    routes = (n74.n74_dir() / "n74.rou.xml").read_text()
    assert routes.count("<flow ") == 1 + len(meta["ramps"])
    assert "speedFactor" in routes


def test_min_radius_at_least_750_m_on_every_main_lane_and_the_dense_centre_line():
    geo = n74.n74_geometry()
    assert 1.0 / np.max(np.abs(geo.kappa)) >= 750.0
    for lid, (_, pts) in _lanes().items():
        if lid.startswith(("main", "merge", "opp_")) and len(pts) >= 3:
            assert np.min(circumradius(pts)) >= 750.0, lid


def test_clothoid_transitions_curvature_is_continuous_and_piecewise_linear():
    geo = n74.n74_geometry()
    # curvature changes by at most (1/800 m) / 150 m per metre: no jumps
    assert np.max(np.abs(np.diff(geo.kappa))) <= (1.0 / 800.0) / 150.0 * n74.DENSE_STEP_M + 1e-12
    pieces = geo.pieces
    for a, b in itertools.pairwise(pieces):
        assert a.kappa_end == pytest.approx(b.kappa_start)


def test_generator_is_seeded_and_shapes_are_lean():
    a, b, c = n74.n74_geometry(74), n74.n74_geometry(74), n74.n74_geometry(75)
    assert np.array_equal(a.xy, b.xy)
    assert not np.array_equal(a.xy[-1], c.xy[-1])
    assert max(len(pts) for _, pts in _lanes("main").values()) < 300


def test_committed_files_match_the_generator(tmp_path):
    n74.build_n74(tmp_path / "n74")
    for name in ("n74.nod.xml", "n74.edg.xml", "n74.con.xml", "n74.net.xml", "n74.rou.xml"):
        assert (tmp_path / "n74" / name).read_text() == (n74.n74_dir() / name).read_text(), name


def test_an_installed_package_builds_n74_once_into_the_cache(tmp_path, monkeypatch):
    """Without the checkout's sumo_scenarios/ (a wheel install), the n74 files are built into
    the network cache from the same code, once, and equal the committed ones."""
    committed = n74.n74_dir()
    monkeypatch.setattr(n74, "COMMITTED_DIR", tmp_path / "no_checkout" / "n74")
    monkeypatch.setenv("SAFEIL_SUMO_CACHE", str(tmp_path / "cache"))
    built = n74.n74_dir()
    assert built == tmp_path / "cache" / "n74"
    for name in ("n74.net.xml", "n74.rou.xml", "n74.json"):
        assert (built / name).read_text() == (committed / name).read_text(), name
    stamp = (built / "n74.net.xml").stat().st_mtime_ns
    assert n74.n74_dir() == built and (built / "n74.net.xml").stat().st_mtime_ns == stamp
