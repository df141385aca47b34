"""Road geometry read once from a SUMO ``.net.xml``: lane centre lines and boundaries as polylines.

The closed loop never asks SUMO for geometry per step: sensors and monitors use this object.
A road is one SUMO edge (a closed test track is one edge; see DESIGN.md). Lane index 0 is the
rightmost lane, as in SUMO. A sidecar ``<net stem>.track.json`` written by the network generator
marks the test path (where the measured part of the scenario starts and ends on the ego lane).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from safeil_sumo.geometry import Polyline


class NetworkError(ValueError):
    """A road network that is missing, malformed, or unusable for a scenario."""


@dataclass(frozen=True)
class Lane:
    """One lane: SUMO id and index (0 = rightmost), width [m], centre and boundary polylines."""

    lane_id: str
    index: int
    width: float
    sumo_length: float  # SUMO's lane length [m]; positions scale by sumo_length / centre.length
    centre: Polyline
    left_boundary: Polyline
    right_boundary: Polyline


@dataclass(frozen=True)
class Road:
    """The lanes of one edge and the test path on the ego lane.

    ``path_start_s`` / ``path_end_s`` [m]: arc lengths along ``lanes[ego_lane].centre`` between
    which the scenario's "path completed" is measured.
    """

    net_path: Path
    edge_id: str
    lanes: tuple[Lane, ...]
    ego_lane: int
    path_start_s: float
    path_end_s: float
    meta: dict

    @property
    def path_length(self) -> float:
        return self.path_end_s - self.path_start_s

    def lane(self, index: int) -> Lane:
        if not 0 <= index < len(self.lanes):
            raise NetworkError(
                f"{self.net_path}: lane index {index} does not exist (edge {self.edge_id!r} "
                f"has {len(self.lanes)} lanes)"
            )
        return self.lanes[index]


def _parse_shape(text: str) -> np.ndarray:
    pts = [tuple(float(v) for v in p.split(",")[:2]) for p in text.split()]
    arr = np.array(pts, dtype=float)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(arr, axis=0), axis=1) > 1e-6])
    return arr[keep]


def load_road(
    net_path: str | Path, edge_id: str | None = None, ego_lane: int | None = None
) -> Road:
    """Read the lanes of ``edge_id`` (default: the net's only non-internal edge).

    Raises :class:`NetworkError` with a one-line reason for a missing file, malformed XML, an
    unknown edge, or a net with several edges and no ``edge_id``.
    """
    net_path = Path(net_path)
    if not net_path.is_file():
        raise NetworkError(f"network file not found: {net_path}")
    try:
        root = ET.parse(net_path).getroot()
    except ET.ParseError as exc:
        raise NetworkError(f"{net_path}: malformed XML ({exc})") from exc
    if root.tag != "net":
        raise NetworkError(f"{net_path}: not a SUMO network (root element <{root.tag}>)")
    edges = [e for e in root.iter("edge") if e.get("function") != "internal"]
    if edge_id is None:
        if len(edges) != 1:
            names = ", ".join(e.get("id", "?") for e in edges[:10])
            raise NetworkError(
                f"{net_path}: expected exactly one road edge, found {len(edges)} ({names}); "
                "the closed loop drives single-edge roads only (multi-edge routes are not "
                "supported yet): use a network with one road edge, e.g. curved500, straight or "
                "curved<R>"
            )
        edge = edges[0]
    else:
        matches = [e for e in edges if e.get("id") == edge_id]
        if not matches:
            raise NetworkError(f"{net_path}: no edge {edge_id!r}")
        edge = matches[0]

    lanes = []
    for el in edge.iter("lane"):
        try:
            shape = _parse_shape(el.get("shape", ""))
            centre = Polyline(shape)
            width = float(el.get("width", 3.2))  # SUMO's default lane width [m]
        except (ValueError, TypeError) as exc:
            raise NetworkError(
                f"{net_path}: lane {el.get('id')!r} has a bad shape ({exc})"
            ) from exc
        lanes.append(
            Lane(
                lane_id=el.get("id", ""),
                index=int(el.get("index", len(lanes))),
                width=width,
                sumo_length=float(el.get("length", centre.length)),
                centre=centre,
                left_boundary=centre.offset(0.5 * width),
                right_boundary=centre.offset(-0.5 * width),
            )
        )
    if not lanes:
        raise NetworkError(f"{net_path}: edge {edge.get('id')!r} has no lanes")
    lanes.sort(key=lambda lane: lane.index)

    sidecar = net_path.with_name(net_path.name.removesuffix(".net.xml") + ".track.json")
    try:
        meta: dict = json.loads(sidecar.read_text()) if sidecar.is_file() else {}
    except (OSError, ValueError) as exc:
        raise NetworkError(f"{sidecar}: unreadable track sidecar ({exc})") from exc
    if not isinstance(meta, dict):
        raise NetworkError(f"{sidecar}: track sidecar is not a JSON object")
    if ego_lane is None:
        ego_lane = int(meta.get("ego_lane", len(lanes) // 2))
    if not 0 <= ego_lane < len(lanes):
        raise NetworkError(
            f"{net_path}: the scenario needs lane index {ego_lane} but edge "
            f"{edge.get('id')!r} has {len(lanes)} lane(s)"
        )
    ego_len = lanes[ego_lane].centre.length
    start = float(meta.get("path_start_s", 0.0))
    end = float(meta.get("path_end_s", ego_len))
    if "generator_version" in meta and edge_id in (None, meta.get("edge_id")):
        lanes, start, end = _exact_lanes(meta, lanes, ego_lane)
    return Road(net_path, edge.get("id", ""), tuple(lanes), ego_lane, start, end, meta)


def _exact_lanes(meta: dict, lanes: list[Lane], ego_lane: int) -> tuple[list[Lane], float, float]:
    """Lanes of a generated track rebuilt from its spec at a fine sagitta (see network.py).

    The SUMO net approximates arcs coarsely to keep ``moveToXY`` cheap; sensors and monitors
    measure against the intended geometry instead. Returns lanes and the test path's ends.
    """
    from dataclasses import fields

    from safeil_sumo.scenarios import network

    spec = network.TrackSpec(**{f.name: meta[f.name] for f in fields(network.TrackSpec)})
    if spec.lanes != len(lanes):
        raise NetworkError(f"{meta.get('name')}: track.json says {spec.lanes} lanes, the net has "
                           f"{len(lanes)}")
    road_centre = Polyline(network.road_centre_line(spec, network.GEOMETRY_SAGITTA_M))
    exact = []
    for lane in lanes:
        offset = (lane.index - (spec.lanes - 1) / 2) * spec.lane_width_m
        centre = road_centre.offset(offset)
        exact.append(Lane(lane.lane_id, lane.index, lane.width, lane.sumo_length, centre,
                          centre.offset(0.5 * lane.width), centre.offset(-0.5 * lane.width)))
    s, _ = exact[ego_lane].centre.project(network.ego_path_ends(spec))
    return exact, float(s[0]), float(s[1])
