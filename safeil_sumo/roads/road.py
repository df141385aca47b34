"""Road geometry read once from a SUMO ``.net.xml``: lane centre lines and boundaries as polylines.

The closed loop never asks SUMO for geometry per step: sensors and monitors use this object.
A road is one SUMO edge (a closed test track is one edge: docs/architecture.md), or a route of edges
whose lanes are concatenated across the junctions (:mod:`safeil_sumo.roads.route`). Lane
index 0 is the rightmost lane, as in SUMO. A sidecar ``<net stem>.track.json`` written by the network generator
marks the test path (where the measured part of the scenario starts and ends on the ego lane).
"""

from __future__ import annotations

import bisect
import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.roads import track


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
    # on a route, a neighbour lane that does not continue across a junction ends there: the arc
    # length [m] along the EGO lane's centre beyond which it is no longer offered (inf: never)
    ends_at_s: float = math.inf


@dataclass(frozen=True)
class RoutePiece:
    """One SUMO lane the ego lane runs through: an edge's lane or a junction's internal lane.

    ``s0`` / ``s1`` [m]: where it lies along the ego lane's (concatenated) centre polyline;
    ``sumo_length`` [m]: SUMO's length of that lane (positions on it scale by ``scale``).
    """

    lane_id: str
    edge_id: str
    lane_index: int  # SUMO lane index on its edge (0 = rightmost)
    route_index: int  # index in ``Road.route_edges`` of its edge (internal: of the edge before)
    internal: bool  # a junction's internal lane (no vehicle can depart on it)
    s0: float
    s1: float
    sumo_length: float

    @property
    def scale(self) -> float:
        """SUMO lane position (and speed) per geometric metre [-]."""
        return self.sumo_length / (self.s1 - self.s0)


@dataclass(frozen=True)
class Road:
    """The lanes of one edge (or route of edges) and the test path on the ego lane.

    ``path_start_s`` / ``path_end_s`` [m]: arc lengths along ``lanes[ego_lane].centre`` between
    which the scenario's "path completed" is measured. ``route_edges``: the SUMO edges the ego
    drives, in order (default: ``(edge_id,)``); ``ego_pieces``: the SUMO lanes along the ego lane
    (default: the ego lane of ``edge_id`` over its whole centre).
    """

    net_path: Path
    edge_id: str
    lanes: tuple[Lane, ...]
    ego_lane: int
    path_start_s: float
    path_end_s: float
    meta: dict
    route_edges: tuple[str, ...] = ()
    ego_pieces: tuple[RoutePiece, ...] = ()
    # the arc length [m] at which each ego piece ends: set by __post_init__
    _piece_ends: list[float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.route_edges:
            object.__setattr__(self, "route_edges", (self.edge_id,))
        if not self.ego_pieces and 0 <= self.ego_lane < len(self.lanes):
            lane = self.lanes[self.ego_lane]
            object.__setattr__(self, "ego_pieces", (RoutePiece(
                lane.lane_id, self.edge_id, lane.index, 0, False, 0.0, lane.centre.length,
                lane.sumo_length),))
        object.__setattr__(self, "_piece_ends", [p.s1 for p in self.ego_pieces])

    @property
    def path_length(self) -> float:
        return self.path_end_s - self.path_start_s

    def piece_at(self, s: float) -> RoutePiece:
        """The SUMO lane under arc length ``s`` [m] of the ego lane (clipped to the ends)."""
        return self.ego_pieces[self.piece_index_at(s)]

    def piece_index_at(self, s: float) -> int:
        """Index in ``ego_pieces`` of :meth:`piece_at`."""
        k, last = bisect.bisect_right(self._piece_ends, s), len(self.ego_pieces) - 1
        # min(k, last), without the builtin's argument parsing (~4x a comparison; every step)
        return last if k > last else k  # noqa: FURB136

    def lanes_at(self, s: float) -> tuple[int, int]:
        """Lowest and highest lane index offered at arc length ``s`` [m] of the ego lane (a
        neighbour that ended at a junction is not; see :attr:`Lane.ends_at_s`)."""
        lo = hi = self.ego_lane
        while lo > 0 and s < self.lanes[lo - 1].ends_at_s:
            lo -= 1
        while hi < len(self.lanes) - 1 and s < self.lanes[hi + 1].ends_at_s:
            hi += 1
        return lo, hi

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


def read_net(net_path: Path) -> ET.Element:
    """The ``<net>`` root of a ``.net.xml``; :class:`NetworkError` if missing or malformed."""
    if not net_path.is_file():
        raise NetworkError(f"network file not found: {net_path}")
    try:
        root = ET.parse(net_path).getroot()
    except ET.ParseError as exc:
        raise NetworkError(f"{net_path}: malformed XML ({exc})") from exc
    if root.tag != "net":
        raise NetworkError(f"{net_path}: not a SUMO network (root element <{root.tag}>)")
    return root


def load_road(
    net_path: str | Path, edge_id: str | None = None, ego_lane: int | None = None
) -> Road:
    """Read the lanes of ONE edge, ``edge_id`` (default: the net's only non-internal edge).

    ``ego_lane``: SUMO lane index of the ego (default: the sidecar's, else the middle lane).
    For a route over several edges use :func:`safeil_sumo.roads.route.load_route` (CLI:
    ``--route EDGE [EDGE ...]``).

    Raises :class:`NetworkError` with a one-line reason for a missing file, malformed XML, an
    unknown edge, or a net with several edges and no ``edge_id`` (naming ``--route``).
    """
    net_path = Path(net_path)
    root = read_net(net_path)
    edges = [e for e in root.iter("edge") if e.get("function") != "internal"]
    if edge_id is None:
        if len(edges) != 1:
            names = ", ".join(e.get("id", "?") for e in edges[:10])
            raise NetworkError(
                f"{net_path}: expected exactly one road edge, found {len(edges)} ({names}); "
                "without a route the closed loop drives single-edge roads only: give the edges "
                "to drive, in order, with --route EDGE [EDGE ...], or use a single-edge network "
                "(curved500, straight, curved<R>)"
            )
        edge = edges[0]
    else:
        matches = [e for e in edges if e.get("id") == edge_id]
        if not matches:
            raise NetworkError(f"{net_path}: no edge {edge_id!r}")
        edge = matches[0]

    lanes: list[Lane] = []
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
            f"{edge.get('id')!r} has {len(lanes)} lane(s) (indices 0..{len(lanes) - 1}, "
            "0 = rightmost)"
        )
    ego_len = lanes[ego_lane].centre.length
    start = float(meta.get("path_start_s", 0.0))
    end = float(meta.get("path_end_s", ego_len))
    if "generator_version" in meta and edge_id in (None, meta.get("edge_id")):
        lanes, start, end = _exact_lanes(meta, lanes, ego_lane)
    return Road(net_path, edge.get("id", ""), tuple(lanes), ego_lane, start, end, meta)


def _exact_lanes(meta: dict, lanes: list[Lane], ego_lane: int) -> tuple[list[Lane], float, float]:
    """Lanes of a generated track rebuilt from its spec at a fine sagitta (see track.py).

    The SUMO net approximates arcs coarsely to keep ``moveToXY`` cheap; sensors and monitors
    measure against the intended geometry instead. Returns lanes and the test path's ends.
    """
    spec = track.TrackSpec(**{f.name: meta[f.name] for f in fields(track.TrackSpec)})
    if spec.lanes != len(lanes):
        raise NetworkError(f"{meta.get('name')}: track.json says {spec.lanes} lanes, the net has "
                           f"{len(lanes)}")
    road_centre = Polyline(track.road_centre_line(spec, track.GEOMETRY_SAGITTA_M))
    exact = []
    for lane in lanes:
        offset = (lane.index - (spec.lanes - 1) / 2) * spec.lane_width_m
        centre = road_centre.offset(offset)
        exact.append(Lane(lane.lane_id, lane.index, lane.width, lane.sumo_length, centre,
                          centre.offset(0.5 * lane.width), centre.offset(-0.5 * lane.width)))
    s, _ = exact[ego_lane].centre.project(track.ego_path_ends(spec))
    return exact, float(s[0]), float(s[1])
