"""Generated SUMO test tracks: geometry of the real netconvert output, catalogue, errors, libsumo."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from safeil_sumo.roads import network
from safeil_sumo.roads.catalogue import (
    COMMITTED_DIR,
    default_cache_dir,
    resolve_net,
    spec_for,
)
from safeil_sumo.roads.network import build_network
from safeil_sumo.roads.road import NetworkError, Road, _parse_shape, load_road
from safeil_sumo.roads.track import TrackSpec


def fit_circle(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) least-squares circle: x² + y² + D x + E y + F = 0 -> centre, radius."""
    x, y = points[:, 0], points[:, 1]
    a = np.stack([x, y, np.ones_like(x)], axis=1)
    (d, e, f), *_ = np.linalg.lstsq(a, -(x**2 + y**2), rcond=None)
    centre = np.array([-d / 2.0, -e / 2.0])
    return centre, float(np.sqrt(centre @ centre - f))


def arc_points(road: Road, lane: int) -> np.ndarray:
    """Vertices of ``lane`` whose projection on the ego lane lies within the test path."""
    pts = road.lane(lane).centre.points
    s, _ = road.lane(road.ego_lane).centre.project(pts)
    inside = (s >= road.path_start_s - 1e-6) & (s <= road.path_end_s + 1e-6)
    return pts[inside]


@pytest.fixture(scope="module")
def curved500() -> Road:
    return load_road(resolve_net("curved500"))


def test_curved500_is_the_committed_file():
    assert resolve_net("curved500") == COMMITTED_DIR / "curved500" / "curved500.net.xml"


def test_curved500_geometry(curved500: Road):
    road = curved500
    assert road.edge_id == "road"
    assert len(road.lanes) == 3 and road.ego_lane == 1
    assert all(lane.width == pytest.approx(3.5) for lane in road.lanes)
    pts = arc_points(road, road.ego_lane)
    assert len(pts) > 40
    _, radius = fit_circle(pts)
    assert radius == pytest.approx(500.0, abs=0.5)
    assert road.path_length == pytest.approx(1000.0, abs=1.0)
    assert road.path_start_s == pytest.approx(30.0, abs=1e-6)
    # left turn: the left lane (index 2) is inside the curve
    _, r_right = fit_circle(arc_points(road, 0))
    _, r_left = fit_circle(arc_points(road, 2))
    assert r_right - radius == pytest.approx(3.5, abs=0.05)
    assert radius - r_left == pytest.approx(3.5, abs=0.05)
    # lean SUMO geometry (moveToXY cost grows with shape points), exact geometry for measuring
    sumo_shape = _parse_shape(
        next(el for el in ET.parse(road.net_path).getroot().iter("lane")
             if el.get("id") == "road_1").get("shape"))
    assert len(sumo_shape) < 60
    assert len(road.lane(1).centre.points) > 300
    _centre, r_sumo = fit_circle(sumo_shape[2:-1])  # the arc vertices lie on the circle
    assert r_sumo == pytest.approx(500.0, abs=0.01)
    seg = np.diff(pts, axis=0)
    assert np.max(np.linalg.norm(seg, axis=1)) ** 2 / (8 * 500.0) < 0.021
    # the run-out is long enough for the leader (see track.DEFAULT_RUN_OUT_M)
    assert road.lane(1).centre.length - road.path_end_s >= 600.0


def test_curved500_sidecar_matches_spec():
    meta = json.loads((COMMITTED_DIR / "curved500" / "curved500.track.json").read_text())
    spec = spec_for("curved500")
    for key in ("name", "radius_m", "arc_length_m", "lanes", "lane_width_m", "ego_lane"):
        assert meta[key] == getattr(spec, key)
    assert meta["path_end_s"] - meta["path_start_s"] == pytest.approx(1000.0, abs=1.0)


def test_committed_files_match_the_generator(tmp_path: Path):
    for name in ("curved500", "straight"):
        build_network(spec_for(name), tmp_path / name)
        for committed in sorted((COMMITTED_DIR / name).iterdir()):
            fresh = tmp_path / name / committed.name
            assert fresh.read_bytes() == committed.read_bytes(), (
                f"{committed} is stale: run python training/build_networks.py"
            )


def test_straight_geometry():
    road = load_road(resolve_net("straight"))
    ego = road.lane(road.ego_lane).centre
    assert ego.length == pytest.approx(2000.0, abs=0.01)
    pts = ego.points
    slope, intercept = np.polyfit(pts[:, 0], pts[:, 1], 1)
    assert np.max(np.abs(pts[:, 1] - (slope * pts[:, 0] + intercept))) < 0.01
    assert road.path_start_s == pytest.approx(30.0)
    assert road.path_end_s == pytest.approx(2000.0 - 800.0)
    assert math.isinf(road.meta["radius_m"])


def test_generated_variant_curved300(tmp_path: Path):
    net = resolve_net("curved300", cache_dir=tmp_path)
    assert net == tmp_path / "curved300" / "curved300.net.xml"
    road = load_road(net)
    _, radius = fit_circle(arc_points(road, road.ego_lane))
    assert radius == pytest.approx(300.0, abs=0.5)
    assert road.path_length == pytest.approx(1000.0, abs=1.0)
    # reused while the spec matches: not rebuilt
    mtime = net.stat().st_mtime_ns
    assert resolve_net("curved300", cache_dir=tmp_path) == net
    assert net.stat().st_mtime_ns == mtime


def test_stale_cache_is_rebuilt(tmp_path: Path):
    net = resolve_net("curved800", cache_dir=tmp_path)
    sidecar = net.with_name("curved800.track.json")
    meta = json.loads(sidecar.read_text())
    sidecar.write_text(json.dumps(meta | {"radius_m": 123.0}))
    assert resolve_net("curved800", cache_dir=tmp_path) == net
    assert json.loads(sidecar.read_text())["radius_m"] == 800.0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folders


def test_cache_dir_from_environment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("SAFEIL_SUMO_CACHE", str(tmp_path / "env-cache"))
    assert default_cache_dir() == tmp_path / "env-cache"
    net = resolve_net("curved1000")
    assert net == tmp_path / "env-cache" / "curved1000" / "curved1000.net.xml"


def test_build_is_deterministic(tmp_path: Path):
    spec = TrackSpec(name="t", radius_m=250.0, arc_length_m=400.0, lanes=2, ego_lane=0)
    a = build_network(spec, tmp_path / "a")
    b = build_network(spec, tmp_path / "b")
    assert a.read_bytes() == b.read_bytes()
    road = load_road(a)
    assert road.ego_lane == 0 and len(road.lanes) == 2
    _, radius = fit_circle(arc_points(road, 0))
    assert radius == pytest.approx(250.0, abs=0.5)


def test_path_to_net_is_returned_as_is(tmp_path: Path):
    net = resolve_net("curved500")
    assert resolve_net(str(net)) == net


@pytest.mark.parametrize("name", ["nowhere", "curved", "curved-5", "curved0500", "Straight"])
def test_unknown_name_lists_valid_names(name: str, tmp_path: Path):
    with pytest.raises(NetworkError, match="valid names: curved500, straight, curved<R>"):
        resolve_net(name, cache_dir=tmp_path)
    assert not list(tmp_path.iterdir())


def test_missing_file(tmp_path: Path):
    with pytest.raises(NetworkError, match="not found"):
        resolve_net(str(tmp_path / "missing.net.xml"))


def test_malformed_net(tmp_path: Path):
    bad = tmp_path / "bad.net.xml"
    bad.write_text("<net><edge id='road'>")
    with pytest.raises(NetworkError, match="malformed"):
        load_road(resolve_net(str(bad)))


def test_radius_smaller_than_lane_offset(tmp_path: Path):
    with pytest.raises(ValueError, match="farthest lane boundary"):
        TrackSpec(name="tiny", radius_m=2.0, arc_length_m=10.0)
    with pytest.raises(NetworkError, match="farthest lane boundary"):
        resolve_net("curved2", cache_dir=tmp_path)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"radius_m": 0.0}, "radius_m must be positive"),
        ({"radius_m": -500.0}, "radius_m must be positive"),
        ({"radius_m": math.nan}, "radius_m must be positive"),
        ({"arc_length_m": 0.0}, "arc_length_m must be positive"),
        ({"lane_width_m": -3.5}, "lane_width_m must be positive"),
        ({"lanes": 0}, "lanes must be an integer >= 1"),
        ({"ego_lane": 3}, r"ego_lane must be a lane index in \[0, 2\]"),
        ({"run_out_m": -1.0}, "run_out_m must be >= 0"),
        ({"name": "a b"}, "track name"),
        ({"radius_m": 100.0, "arc_length_m": 1000.0}, "full circle"),
    ],
)
def test_bad_specs(kwargs: dict, message: str):
    args = {"name": "t", "radius_m": 500.0, "arc_length_m": 1000.0} | kwargs
    with pytest.raises(ValueError, match=message):
        TrackSpec(**args)


def test_failing_netconvert_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    fake = tmp_path / "fake-netconvert"
    fake.write_text("#!/bin/sh\necho 'Warning: something' >&2\necho 'Error: boom' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setattr(network, "find_netconvert", lambda: str(fake))
    out = tmp_path / "nets"
    with pytest.raises(NetworkError, match="netconvert failed .*Error: boom"):
        build_network(spec_for("curved500"), out / "curved500")
    assert list(out.iterdir()) == []
    with pytest.raises(NetworkError, match="Error: boom"):
        resolve_net("curved400", cache_dir=out)
    assert list(out.iterdir()) == []


def test_sumocfg_runs_in_sumo():
    sumo = shutil.which("sumo")
    if sumo is None:
        pytest.skip("sumo binary not on PATH")
    cfg = COMMITTED_DIR / "curved500" / "curved500.sumocfg"
    proc = subprocess.run(
        [sumo, "-c", str(cfg), "--end", "1", "--no-step-log", "true"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr


def test_libsumo_vehicle_on_ego_lane(curved500: Road):
    libsumo = pytest.importorskip("libsumo")
    net = str(resolve_net("curved500"))
    libsumo.start(["sumo", "-n", net, "--no-step-log", "true"])
    try:
        libsumo.route.add("r_test", ["road"])
        libsumo.vehicle.add(
            "ego",
            "r_test",
            departLane=str(curved500.ego_lane),
            departPos=str(curved500.path_start_s),
            departSpeed="30",
        )
        for _ in range(5):
            libsumo.simulationStep()
        assert libsumo.vehicle.getLaneID("ego") == f"road_{curved500.ego_lane}"
        xy = np.array(libsumo.vehicle.getPosition("ego"))
        _, d = curved500.lane(curved500.ego_lane).centre.project(xy)
        # SUMO drives on the 10 cm-sagitta polygon, our geometry is the exact arc
        assert abs(float(d)) < 0.11
    finally:
        libsumo.close()
