"""An N74/N715-like highway (paper Section IV-A), generated procedurally from a seed.

The paper's data came from a human driving 29.2 km of "highway-like" road "with low curvature and
clear lane markers" in ~30 min. We do not have that road; this module builds a road of the same
length and character for SUMO:

- a REFERENCE LINE 29.2 km long (the carriageway's median): straights, and curves made of a
  clothoid (curvature changing linearly with arc length), a circular arc of radius
  >= :data:`MIN_DESIGN_RADIUS_M` and a clothoid back; the heading is steered back towards the
  start heading so the road does not wind up. Starts at the world origin heading east.
- direction A (the ego's): 2 lanes x 3.5 m to the RIGHT of the reference line (SUMO
  ``spreadType="right"``: the edge shape is the left edge of the carriageway, so a lane gained on
  the right leaves the two main lanes where they are); lane 0 = right, lane 1 = left.
- :data:`N_RAMPS` on-ramps on direction A: a 1-lane ramp edge ends at the start of a 3-lane
  ``merge<k>`` edge whose rightmost lane (index 0) is an acceleration lane of
  :data:`ACC_LANE_M`; that lane has no successor, so SUMO's vehicles must merge left before its
  end (the usual SUMO model of an acceleration lane).
- direction B: the reversed reference line, 2 lanes, no ramps (it costs two edges per piece and
  gives the GUI a realistic look; the recorder does not load its traffic).

Edges of direction A in driving order: ``main0, merge1, main1, ..., merge5, main5``; the opposite
edges are ``opp_<id>``, the ramps ``ramp<k>``. Shapes are sampled as chords whose sagitta is at
most :data:`SHAPE_SAGITTA_M` (lean shapes keep ``moveToXY`` fast); the dense analytic geometry is
kept in :class:`N74Geometry` for sensors and tests.

Files (``sumo_scenarios/n74/``): ``n74.nod.xml``, ``n74.edg.xml``, ``n74.con.xml`` (netconvert
input), ``n74.net.xml``, ``n74.rou.xml`` (vTypes + direction-A flows on the main road and ramps),
``n74.opposite.rou.xml`` (direction-B flow), ``n74.sumocfg`` (``sumo-gui -c n74.sumocfg``) and
``n74.json`` (layout: edges with their start/end arc length, ramps, seed).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from safeil_sumo.roads.road import Road

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.roads.network import run_netconvert

NAME = "n74"
COMMITTED_DIR = Path(__file__).resolve().parents[2] / "sumo_scenarios" / NAME  # a checkout's
ROAD_LENGTH_M = 29_200.0  # [m] paper, Fig. 2 caption
LANE_WIDTH_M = 3.5  # [m]
MAIN_LANES = 2  # [-] per direction
MIN_DESIGN_RADIUS_M = 800.0  # [m] reference-line arcs; inner lanes stay above 750 m
MAX_DESIGN_RADIUS_M = 3000.0  # [m]
N_RAMPS = 5  # [-] on-ramps on direction A
ACC_LANE_M = 250.0  # [m] acceleration lane (merge edge) length
RAMP_LENGTH_M = 300.0  # [m] ramp edge length (along the reference line)
RAMP_START_OFFSET_M = 35.0  # [m] how far right of the acceleration lane the ramp starts
SPEED_LIMIT_MPS = 120.0 / 3.6  # [m/s] main road
RAMP_SPEED_MPS = 80.0 / 3.6  # [m/s]
SHAPE_SAGITTA_M = 0.03  # [m] largest chord sagitta of the SUMO shapes
MAX_CHORD_M = 250.0  # [m] longest shape segment on straights
DENSE_STEP_M = 1.0  # [m] spacing of the dense reference geometry
DEFAULT_SEED = 74
MAIN_FLOW_VPH = 1200.0  # [veh/h] entering direction A at its start
RAMP_FLOW_VPH = 120.0  # [veh/h] per ramp (direction A ends at 1200 + 5 x 120 = 1800 veh/h)
OPPOSITE_FLOW_VPH = 1500.0  # [veh/h] direction B
TRUCK_SHARE = 0.1  # [-]
GENERATOR_VERSION = 1
MIN_STRETCH_M = 100.0  # [m] shortest --from-km/--to-km stretch


@dataclass(frozen=True)
class CurvaturePiece:
    """A piece of the reference line whose curvature changes linearly from start to end."""

    length_m: float  # [m]
    kappa_start: float  # [1/m], positive = turning left
    kappa_end: float  # [1/m]


@dataclass(frozen=True)
class N74Geometry:
    """The dense analytic geometry of the reference line and the layout of edges and ramps.

    ``s`` (N,), ``xy`` (N, 2), ``heading`` (N,) [rad] and ``kappa`` (N,) [1/m] sample the
    reference line every :data:`DENSE_STEP_M`. ``edges``: direction-A edge ids with their
    ``(s_start, s_end)`` [m]; ``ramps``: arc length [m] where each acceleration lane starts.
    """

    seed: int
    pieces: tuple[CurvaturePiece, ...]
    s: np.ndarray
    xy: np.ndarray
    heading: np.ndarray
    kappa: np.ndarray
    edges: tuple[tuple[str, float, float], ...]
    ramps: tuple[float, ...]

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def frenet_to_xy(self, s: np.ndarray | float, d: np.ndarray | float) -> np.ndarray:
        """World points ``(..., 2)`` at arc length ``s`` and left offset ``d`` [m] (interpolated)."""
        s_arr = np.asarray(s, dtype=float)
        x = np.interp(s_arr, self.s, self.xy[:, 0])
        y = np.interp(s_arr, self.s, self.xy[:, 1])
        h = np.interp(s_arr, self.s, self.heading)
        d_arr = np.asarray(d, dtype=float)
        return np.stack([x - d_arr * np.sin(h), y + d_arr * np.cos(h)], axis=-1)

    def heading_at(self, s: np.ndarray | float) -> np.ndarray:
        return np.interp(s, self.s, self.heading)

    def kappa_at(self, s: np.ndarray | float) -> np.ndarray:
        return np.interp(s, self.s, self.kappa)

    def reference(self, s_start: float, s_end: float, step_m: float = 5.0) -> Polyline:
        """The reference line between two arc lengths as a polyline every ``step_m`` [m]."""
        n = max(math.ceil((s_end - s_start) / step_m), 1)
        return Polyline(self.frenet_to_xy(np.linspace(s_start, s_end, n + 1), 0.0))


def lane_centre_offset(lane: int, lanes: int = MAIN_LANES) -> float:
    """Left offset [m] of lane ``lane`` (0 = rightmost) from the reference line (spread right)."""
    return -(lanes - lane - 0.5) * LANE_WIDTH_M


def curvature_pieces(seed: int = DEFAULT_SEED, length_m: float = ROAD_LENGTH_M
                     ) -> tuple[CurvaturePiece, ...]:
    """The seeded curvature profile: straight, (clothoid, arc, clothoid), straight, ...

    Lengths are whole metres; the last straight takes up exactly the remaining length.
    """
    rng = np.random.default_rng(seed)
    pieces: list[CurvaturePiece] = []
    total, heading = 0.0, 0.0
    while True:
        straight = float(np.round(rng.uniform(600.0, 2200.0)))
        radius = float(np.round(rng.uniform(MIN_DESIGN_RADIUS_M, MAX_DESIGN_RADIUS_M)))
        # steer back towards the start heading once it has drifted, else turn either way
        sign = -np.sign(heading) if abs(heading) > 0.3 else float(rng.choice([-1.0, 1.0]))
        kappa = float(sign) / radius
        transition = float(np.round(rng.uniform(150.0, 300.0)))  # clothoid length [m]
        arc = float(np.round(rng.uniform(200.0, 1200.0)))
        if total + straight + 2 * transition + arc > length_m - 300.0:
            break  # no room for another curve and a closing straight
        pieces += [CurvaturePiece(straight, 0.0, 0.0), CurvaturePiece(transition, 0.0, kappa),
                   CurvaturePiece(arc, kappa, kappa), CurvaturePiece(transition, kappa, 0.0)]
        total += straight + 2 * transition + arc
        heading += kappa * (transition + arc)
    pieces.append(CurvaturePiece(length_m - total, 0.0, 0.0))
    return tuple(pieces)


def _integrate(pieces: tuple[CurvaturePiece, ...], step: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dense ``s, xy, heading, kappa`` of a curvature profile (trapezoid heading, midpoint xy)."""
    knots_s = np.concatenate([[0.0], np.cumsum([p.length_m for p in pieces])])
    n = round(knots_s[-1] / step)
    s = np.linspace(0.0, knots_s[-1], n + 1)
    idx = np.clip(np.searchsorted(knots_s, s, side="right") - 1, 0, len(pieces) - 1)
    k0 = np.array([p.kappa_start for p in pieces])[idx]
    k1 = np.array([p.kappa_end for p in pieces])[idx]
    frac = (s - knots_s[idx]) / np.array([p.length_m for p in pieces])[idx]
    kappa = k0 + (k1 - k0) * frac
    ds = np.diff(s)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    mid = 0.5 * (heading[1:] + heading[:-1])
    xy = np.zeros((len(s), 2))
    xy[1:, 0] = np.cumsum(np.cos(mid) * ds)
    xy[1:, 1] = np.cumsum(np.sin(mid) * ds)
    return s, xy, heading, kappa


def ramp_positions(seed: int, length_m: float = ROAD_LENGTH_M, n: int = N_RAMPS
                   ) -> tuple[float, ...]:
    """Arc lengths [m] where the acceleration lanes start: evenly spread, jittered by the seed."""
    rng = np.random.default_rng(seed + 1)
    spacing = length_m / (n + 1)
    jitter = rng.uniform(-0.2, 0.2, size=n) * spacing
    return tuple(float(np.round((k + 1) * spacing + jitter[k])) for k in range(n))


def n74_geometry(seed: int = DEFAULT_SEED) -> N74Geometry:
    """The road's dense geometry and edge layout for ``seed``."""
    pieces = curvature_pieces(seed)
    s, xy, heading, kappa = _integrate(pieces, DENSE_STEP_M)
    ramps = ramp_positions(seed, float(s[-1]))
    edges: list[tuple[str, float, float]] = []
    start = 0.0
    for k, s_r in enumerate(ramps, start=1):
        edges.append((f"main{k - 1}", start, s_r))
        edges.append((f"merge{k}", s_r, s_r + ACC_LANE_M))
        start = s_r + ACC_LANE_M
    edges.append((f"main{len(ramps)}", start, float(s[-1])))
    return N74Geometry(seed, pieces, s, xy, heading, kappa, tuple(edges), ramps)


def lean_stations(geo: N74Geometry, s_start: float, s_end: float,
                  sagitta: float = SHAPE_SAGITTA_M) -> np.ndarray:
    """Arc lengths of shape points between two stations: chords with sagitta <= ``sagitta``."""
    out = [s_start]
    s = s_start
    while s < s_end - 1e-6:
        window = (geo.s >= s) & (geo.s <= min(s + MAX_CHORD_M, s_end))
        k_max = float(np.max(np.abs(geo.kappa[window]))) if window.any() else 0.0
        # sagitta of a chord c on radius R: c^2 / (8 R)  ->  c = sqrt(8 R sagitta)
        chord = MAX_CHORD_M if k_max < 1e-9 else min(MAX_CHORD_M, math.sqrt(8 * sagitta / k_max))
        s = min(s + chord, s_end)
        if s_end - s < 0.3 * chord:  # no sliver at the end
            s = s_end
        out.append(s)
    return np.array(out)


def _fmt(points: np.ndarray) -> str:
    return " ".join(f"{x:.3f},{y:.3f}" for x, y in points)


def ramp_shape(geo: N74Geometry, s_merge: float) -> np.ndarray:
    """Shape (left edge of the ramp lane, spread right) from its start to the merge point."""
    s = np.linspace(s_merge - RAMP_LENGTH_M, s_merge, 16)
    u = (s - s[0]) / RAMP_LENGTH_M
    blend = 0.5 * (1.0 + np.cos(np.pi * u))  # 1 -> 0, tangent to the acceleration lane at the end
    acc_left_edge = lane_centre_offset(0, MAIN_LANES + 1) + 0.5 * LANE_WIDTH_M
    return geo.frenet_to_xy(s, acc_left_edge - RAMP_START_OFFSET_M * blend)


def _node_ids(geo: N74Geometry) -> list[tuple[str, float]]:
    ids = [("n_start", 0.0)]
    for k, s_r in enumerate(geo.ramps, start=1):
        ids += [(f"m{k}_a", s_r), (f"m{k}_b", s_r + ACC_LANE_M)]
    ids.append(("n_end", geo.length))
    return ids


def nodes_xml(geo: N74Geometry) -> str:
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<nodes>"]
    for nid, s in _node_ids(geo):
        x, y = geo.frenet_to_xy(s, 0.0)
        lines.append(f'    <node id="{nid}" x="{x:.3f}" y="{y:.3f}" type="priority"/>')
    for k, s_r in enumerate(geo.ramps, start=1):
        x, y = ramp_shape(geo, s_r)[0]
        lines.append(f'    <node id="ramp{k}_in" x="{x:.3f}" y="{y:.3f}" type="priority"/>')
    lines.append("</nodes>")
    return "\n".join(lines) + "\n"


def edges_xml(geo: N74Geometry) -> str:
    nodes = [nid for nid, _ in _node_ids(geo)]
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<edges>"]
    for i, (eid, s0, s1) in enumerate(geo.edges):
        shape = geo.frenet_to_xy(lean_stations(geo, s0, s1), 0.0)
        lanes = MAIN_LANES + 1 if eid.startswith("merge") else MAIN_LANES
        common = f'priority="3" speed="{SPEED_LIMIT_MPS:.2f}" width="{LANE_WIDTH_M}"'
        lines.append(f'    <edge id="{eid}" from="{nodes[i]}" to="{nodes[i + 1]}" '
                     f'numLanes="{lanes}" {common} spreadType="right" shape="{_fmt(shape)}"/>')
        lines.append(f'    <edge id="opp_{eid}" from="{nodes[i + 1]}" to="{nodes[i]}" '
                     f'numLanes="{MAIN_LANES}" {common} spreadType="right" '
                     f'shape="{_fmt(shape[::-1])}"/>')
    for k, s_r in enumerate(geo.ramps, start=1):
        lines.append(f'    <edge id="ramp{k}" from="ramp{k}_in" to="m{k}_a" numLanes="1" '
                     f'priority="1" speed="{RAMP_SPEED_MPS:.2f}" width="{LANE_WIDTH_M}" '
                     f'spreadType="right" shape="{_fmt(ramp_shape(geo, s_r))}"/>')
    lines.append("</edges>")
    return "\n".join(lines) + "\n"


def connections_xml(geo: N74Geometry) -> str:
    """Explicit lane connections at the ramp junctions (the acceleration lane has no successor)."""
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<connections>"]
    ids = [e[0] for e in geo.edges]
    for i in range(len(ids) - 1):
        a, b = ids[i], ids[i + 1]
        if b.startswith("merge"):  # main -> merge: the main lanes keep their place (shift by 1)
            pairs = [(0, 1), (1, 2)]
            k = b.removeprefix("merge")
            lines.append(f'    <connection from="ramp{k}" to="{b}" fromLane="0" toLane="0"/>')
        else:  # merge -> main: lane 0 (acceleration lane) ends
            pairs = [(1, 0), (2, 1)]
        for fl, tl in pairs:
            lines.append(f'    <connection from="{a}" to="{b}" fromLane="{fl}" toLane="{tl}"/>')
        for lane in range(MAIN_LANES):
            lines.append(f'    <connection from="opp_{b}" to="opp_{a}" fromLane="{lane}" '
                         f'toLane="{lane}"/>')
    lines.append("</connections>")
    return "\n".join(lines) + "\n"


def main_route(geo: N74Geometry) -> list[str]:
    """Direction-A edges in driving order."""
    return [e[0] for e in geo.edges]


def routes_xml(geo: N74Geometry) -> str:
    """vTypes (cars with a speed deviation, trucks) and direction-A flows."""
    route = main_route(geo)
    car_share = 1.0 - TRUCK_SHARE
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<routes>",
        "    <!-- background traffic on direction A; vehicle speeds spread by speedFactor -->",
        '    <vTypeDistribution id="traffic">',
        (f'        <vType id="car" vClass="passenger" length="4.6" width="1.8" maxSpeed="50" '
        f'accel="2.6" decel="4.5" sigma="0.5" tau="1.2" speedFactor="normc(1.0,0.1,0.75,1.25)" '
        f'probability="{car_share:.2f}"/>'),
        (f'        <vType id="truck" vClass="truck" length="12.0" width="2.5" maxSpeed="25.0" '
        f'accel="1.0" decel="4.0" sigma="0.5" tau="1.5" speedFactor="normc(1.0,0.05,0.9,1.1)" '
        f'probability="{TRUCK_SHARE:.2f}"/>'),
        "    </vTypeDistribution>",
        '    <vType id="ego" vClass="passenger" length="4.54" width="1.76" color="1,0,0"/>',
        f'    <route id="main" edges="{" ".join(route)}"/>',
    ]
    for k in range(1, len(geo.ramps) + 1):
        i = route.index(f"merge{k}")
        lines.append(f'    <route id="ramp{k}" edges="ramp{k} {" ".join(route[i:])}"/>')
    lines.append(f'    <flow id="main" route="main" type="traffic" begin="0" end="86400" '
                 f'vehsPerHour="{MAIN_FLOW_VPH:g}" departLane="random" departSpeed="desired"/>')
    for k in range(1, len(geo.ramps) + 1):
        lines.append(f'    <flow id="ramp{k}" route="ramp{k}" type="traffic" begin="0" '
                     f'end="86400" vehsPerHour="{RAMP_FLOW_VPH:g}" departLane="0" '
                     f'departSpeed="desired"/>')
    lines.append("</routes>")
    return "\n".join(lines) + "\n"


def opposite_routes_xml(geo: N74Geometry) -> str:
    """Direction-B flow (uses the vTypes of ``n74.rou.xml``)."""
    route = " ".join(f"opp_{e}" for e in reversed(main_route(geo)))
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n<routes>\n'
        f'    <route id="opposite" edges="{route}"/>\n'
        f'    <flow id="opposite" route="opposite" type="traffic" begin="0" end="86400" '
        f'vehsPerHour="{OPPOSITE_FLOW_VPH:g}" departLane="random" departSpeed="desired"/>\n'
        "</routes>\n"
    )


def sumocfg_xml() -> str:
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        "<configuration>\n"
        "    <input>\n"
        f'        <net-file value="{NAME}.net.xml"/>\n'
        f'        <route-files value="{NAME}.rou.xml,{NAME}.opposite.rou.xml"/>\n'
        "    </input>\n"
        "    <time>\n"
        '        <step-length value="0.1"/>\n'
        "    </time>\n"
        "    <processing>\n"
        '        <collision.action value="warn"/>\n'
        '        <collision.mingap-factor value="0"/>\n'
        "    </processing>\n"
        "</configuration>\n"
    )


def layout_json(geo: N74Geometry, version: str) -> dict:
    radii = [1.0 / abs(p.kappa_start) for p in geo.pieces
             if p.kappa_start == p.kappa_end and p.kappa_start != 0.0]
    return {
        "name": NAME,
        "seed": geo.seed,
        "generator_version": GENERATOR_VERSION,
        "netconvert_version": version,
        "length_m": round(geo.length, 3),
        "lane_width_m": LANE_WIDTH_M,
        "main_lanes": MAIN_LANES,
        "min_arc_radius_m": round(min(radii), 1) if radii else None,
        "arcs": len(radii),
        "edges": [{"id": e, "s_start": round(a, 3), "s_end": round(b, 3)} for e, a, b in geo.edges],
        "ramps": [{"id": f"ramp{k}", "merge_edge": f"merge{k}", "s_merge": s}
                  for k, s in enumerate(geo.ramps, start=1)],
        "flows_vph": {"main": MAIN_FLOW_VPH, "per_ramp": RAMP_FLOW_VPH,
                      "opposite": OPPOSITE_FLOW_VPH, "truck_share": TRUCK_SHARE},
        "pieces": [[p.length_m, p.kappa_start, p.kappa_end] for p in geo.pieces],
    }


def build_n74(out_dir: Path, seed: int = DEFAULT_SEED) -> Path:
    """Write the n74 files into ``out_dir`` (built in a temporary folder, then moved in)."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    geo = n74_geometry(seed)
    tmp = Path(tempfile.mkdtemp(prefix=f".{NAME}-build-", dir=out_dir.parent))
    names = [f"{NAME}{sfx}" for sfx in (".nod.xml", ".edg.xml", ".con.xml", ".net.xml",
                                        ".rou.xml", ".opposite.rou.xml", ".sumocfg", ".json")]
    try:
        (tmp / names[0]).write_text(nodes_xml(geo))
        (tmp / names[1]).write_text(edges_xml(geo))
        (tmp / names[2]).write_text(connections_xml(geo))
        version = run_netconvert(NAME, tmp, "safeil_sumo.roads.n74",
                                 ("--connection-files", f"{NAME}.con.xml"))
        (tmp / names[4]).write_text(routes_xml(geo))
        (tmp / names[5]).write_text(opposite_routes_xml(geo))
        (tmp / names[6]).write_text(sumocfg_xml())
        (tmp / names[7]).write_text(json.dumps(layout_json(geo, version), indent=2) + "\n")
        out_dir.mkdir(parents=True, exist_ok=True)
        for name in names:
            os.replace(tmp / name, out_dir / name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir / f"{NAME}.net.xml"


def layout(net_dir: Path | None = None) -> dict:
    """The committed ``n74.json`` (edges of direction A with their reference arc lengths)."""
    return json.loads(((net_dir or n74_dir()) / f"{NAME}.json").read_text())


def stretch_edges(from_m: float, to_m: float, net_dir: Path | None = None
                  ) -> tuple[list[str], list[tuple[float, float]]]:
    """Direction-A edges covering reference arc lengths ``[from_m, to_m]`` [m] in driving
    order, with each edge's ``(s_start, s_end)`` [m]. Raises :class:`NetworkError` (one line) for
    a stretch outside the road or an empty one."""
    from safeil_sumo.roads.road import NetworkError

    edges = layout(net_dir)["edges"]
    total = edges[-1]["s_end"]
    if not (math.isfinite(from_m) and math.isfinite(to_m)):
        raise NetworkError("--from-km/--to-km must be finite numbers")
    if from_m < 0 or to_m > total + 1e-6:
        raise NetworkError(f"the stretch {from_m / 1000:g}-{to_m / 1000:g} km is outside {NAME} "
                           f"(0-{total / 1000:g} km of direction A)")
    if to_m - from_m < MIN_STRETCH_M:
        raise NetworkError(f"the stretch {from_m / 1000:g}-{to_m / 1000:g} km is shorter than "
                           f"{MIN_STRETCH_M:g} m: --to-km must exceed --from-km")
    first = next(i for i, e in enumerate(edges) if from_m < e["s_end"])
    last = next(i for i, e in enumerate(edges) if to_m <= e["s_end"])
    chosen = edges[first:last + 1]
    return [e["id"] for e in chosen], [(e["s_start"], e["s_end"]) for e in chosen]


def stretch_road(from_km: float = 0.0, to_km: float | None = None, lane: str = "right",
                 net_dir: Path | None = None) -> Road:
    """The :class:`~safeil_sumo.roads.road.Road` of direction A between two kilometre
    posts (reference-line chainage, the ``s_start``/``s_end`` of ``n74.json``; default: the
    whole carriageway), ego in the ``right`` (default) or ``left`` main lane.

    The route is the edges covering the stretch (:func:`~safeil_sumo.roads.route.
    load_route`); the test path starts and ends at the kilometre posts, mapped onto the ego
    lane linearly within each edge (lanes of a curve are slightly longer or shorter than the
    reference line: < 0.3 % on n74), so the ego departs at ``from_km`` on the right edge.
    """
    from dataclasses import replace

    from safeil_sumo.roads.road import NetworkError
    from safeil_sumo.roads.route import load_route

    net_dir = net_dir or n74_dir()
    if lane not in ("right", "left"):
        raise NetworkError(f"lane must be 'right' or 'left', got {lane!r}")
    total = layout(net_dir)["edges"][-1]["s_end"]
    from_m = 1000.0 * float(from_km)
    to_m = total if to_km is None else 1000.0 * float(to_km)
    edges, spans = stretch_edges(from_m, to_m, net_dir)
    # main lanes are 0 (right), 1 (left) on main edges and 1, 2 on merge edges (0: acc. lane)
    main0 = 1 if edges[0].startswith("merge") else 0
    road = load_route(net_dir / f"{NAME}.net.xml", edges, main0 + (lane == "left"))

    def lane_s(k: int, s_ref: float) -> float:
        piece = next(p for p in road.ego_pieces if p.route_index == k and not p.internal)
        s0, s1 = spans[k]
        return piece.s0 + (s_ref - s0) / (s1 - s0) * (piece.s1 - piece.s0)

    s_start, s_end = lane_s(0, from_m), lane_s(len(edges) - 1, to_m)
    meta = dict(road.meta, stretch_km=[from_m / 1000.0, to_m / 1000.0], lane=lane)
    return replace(road, path_start_s=s_start, path_end_s=s_end, meta=meta)


def n74_dir() -> Path:
    """The n74 files: the committed ``sumo_scenarios/n74`` of a checkout; an installed package
    (which holds no ``sumo_scenarios/``) builds them once into the network cache
    (:func:`safeil_sumo.roads.catalogue.default_cache_dir`), from the same code."""
    if (COMMITTED_DIR / f"{NAME}.json").is_file():
        return COMMITTED_DIR
    from safeil_sumo.roads.catalogue import default_cache_dir

    folder = default_cache_dir() / NAME
    if not (folder / f"{NAME}.json").is_file():
        build_n74(folder)
    return folder


if __name__ == "__main__":
    print(build_n74(n74_dir()))
