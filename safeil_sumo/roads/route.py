"""A route of SUMO edges as one :class:`~safeil_sumo.roads.road.Road`: the ego's lane is
followed across each junction through SUMO's ``<connection>`` (its ``via`` internal lane bridges
the junction), and each lane of the road is ONE polyline: edge lane + internal lane + next edge
lane + ... . Sensors, monitors and ``path completed`` then work on it as on a single edge.

- Lane ``i`` of the road is lane ``i`` of the FIRST edge (SUMO index, 0 = rightmost); the ego
  lane must continue to the end of the route, else the route is refused (one-line
  :class:`NetworkError` naming the edge and lane).
- A neighbour continues across a junction only where SUMO connects it to the lane at the same
  offset from the ego's next lane (a lane gained or lost on the right shifts SUMO's indices, not
  ours) and its width stays the same. A neighbour that ends is cut at its edge's end and stops
  being offered there (``Lane.ends_at_s``); so are the lanes beyond it.
- Boundaries are the concatenated centre offset by +-width/2, as for a single edge.
- The test path is the whole ego lane (no sidecar: a generated track's ``.track.json`` describes
  one edge).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path

import numpy as np

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.roads.road import (
    Lane,
    NetworkError,
    Road,
    RoutePiece,
    _parse_shape,
    load_road,
    read_net,
)

# Vertices closer than this [m] are merged where lane shapes are joined: a millimetre stub
# between an edge lane's end and its internal lane's start (coordinates are rounded to 1 mm)
# would have an arbitrary direction and kink the offset boundaries.
MIN_VERTEX_SPACING_M = 0.05
WIDTH_TOLERANCE_M = 0.01  # a lane "keeps its width" across a junction within this [m]
DEFAULT_LANE_WIDTH_M = 3.2  # SUMO's default lane width [m]


@dataclass(frozen=True)
class _SumoLane:
    lane_id: str
    edge_id: str
    index: int
    shape: np.ndarray  # (N, 2) [m]
    length: float  # SUMO's length [m]
    width: float  # [m]


@dataclass(frozen=True)
class _Connection:
    to_edge: str
    to_lane: int
    via: str  # internal lane id, "" when the net has no internal links


class _Net:
    """Lanes and connections of a ``.net.xml``, indexed for following lanes."""

    def __init__(self, net_path: Path, root: ET.Element) -> None:
        self.path = net_path
        self.lanes: dict[str, _SumoLane] = {}
        self.edge_lanes: dict[str, list[_SumoLane]] = {}  # road edges only, by lane index
        for edge in root.iter("edge"):
            eid = edge.get("id", "")
            lanes: list[_SumoLane] = []
            for el in edge.iter("lane"):
                lid = el.get("id", "")
                try:
                    shape = _parse_shape(el.get("shape", ""))
                    Polyline(shape)  # validates: >= 2 distinct points
                    lane = _SumoLane(lid, eid, int(el.get("index", len(lanes))), shape,
                                     float(el.get("length", "nan")),
                                     float(el.get("width", DEFAULT_LANE_WIDTH_M)))
                except (ValueError, TypeError) as exc:
                    raise NetworkError(f"{net_path}: lane {lid!r} has a bad shape ({exc})"
                                       ) from exc
                if not math.isfinite(lane.length):  # netconvert always writes it
                    lane = _SumoLane(lid, eid, lane.index, shape, Polyline(shape).length,
                                     lane.width)
                self.lanes[lid] = lane
                lanes.append(lane)
            if edge.get("function") != "internal":
                self.edge_lanes[eid] = sorted(lanes, key=lambda ln: ln.index)
        self.connections: dict[tuple[str, int], list[_Connection]] = {}
        for c in root.iter("connection"):
            try:
                key = (c.get("from", ""), int(c.get("fromLane", "")))
                conn = _Connection(c.get("to", ""), int(c.get("toLane", "")), c.get("via", ""))
            except ValueError as exc:
                raise NetworkError(f"{net_path}: bad <connection> ({exc})") from exc
            self.connections.setdefault(key, []).append(conn)

    def lane(self, edge_id: str, index: int) -> _SumoLane | None:
        lanes = self.edge_lanes[edge_id]
        return lanes[index] if 0 <= index < len(lanes) else None

    def cross(self, lane: _SumoLane, to_edge: str) -> tuple[list[_SumoLane], int] | None:
        """The internal lanes and the lane index on ``to_edge`` that ``lane`` continues into,
        or None if SUMO does not connect it to ``to_edge``. With several connections, the one
        that keeps the lane index wins, else the rightmost."""
        conns = sorted((c for c in self.connections.get((lane.edge_id, lane.index), ())
                        if c.to_edge == to_edge), key=lambda c: (c.to_lane != lane.index, c.to_lane))
        if not conns:
            return None
        conn = conns[0]
        internal: list[_SumoLane] = []
        via = conn.via
        # an internal lane may continue through another one (internal junctions): follow the
        # chain of vias from the internal lanes until it reaches the next edge
        while via:
            if via not in self.lanes or len(internal) > 8:
                raise NetworkError(f"{self.path}: connection {lane.lane_id} -> {to_edge} goes "
                                   f"via {via!r}, which is not a lane of the net")
            step = self.lanes[via]
            internal.append(step)
            nxt = [c for c in self.connections.get((step.edge_id, step.index), ())
                   if c.to_edge == to_edge and c.to_lane == conn.to_lane]
            via = nxt[0].via if nxt else ""
        return internal, conn.to_lane


def _join(shapes: list[np.ndarray]) -> np.ndarray:
    """Concatenate lane shapes ``(N_i, 2)``, merging vertices closer than
    :data:`MIN_VERTEX_SPACING_M` (the last vertex of the whole line is kept)."""
    pts = np.vstack(shapes)
    keep = [0]
    for i in range(1, len(pts)):
        if np.linalg.norm(pts[i] - pts[keep[-1]]) >= MIN_VERTEX_SPACING_M:
            keep.append(i)
    if keep[-1] != len(pts) - 1:  # the end point wins over a close predecessor
        keep[-1] = len(pts) - 1
    if len(keep) < 2:
        raise NetworkError("a route lane is shorter than "
                           f"{MIN_VERTEX_SPACING_M} m")
    return pts[keep]


def load_route(net_path: str | Path, edges: Sequence[str], ego_lane: int | None = None) -> Road:
    """The road along ``edges`` (SUMO edge ids in driving order), ego in lane ``ego_lane`` of the
    first edge (SUMO index; default: the middle lane).

    One edge gives exactly :func:`~safeil_sumo.roads.road.load_road`. Raises
    :class:`NetworkError` (one line) for an unknown edge, consecutive edges that SUMO does not
    connect, or an ego lane that does not continue across a junction: a route ends where the
    ego's lane ends.
    """
    net_path = Path(net_path)
    edges = [str(e) for e in edges]
    if not edges:
        raise NetworkError("a route needs at least one edge")
    if len(edges) == 1:
        return load_road(net_path, edges[0], ego_lane)
    net = _Net(net_path, read_net(net_path))
    ego_lane = _checked_ego_lane(net, edges, ego_lane)
    ego_index, ego_pieces = _follow_ego_lane(net, edges, ego_lane)
    # where the ego lane leaves each edge (a neighbour ending there is cut at this arc length)
    edge_end_s = [max(p.s1 for p in ego_pieces if p.route_index == k and not p.internal)
                  for k in range(len(edges))]
    lanes = [_route_lane(net, edges, lane0, ego_index, i - ego_lane, edge_end_s)
             for i, lane0 in enumerate(net.edge_lanes[edges[0]])]
    lanes = _end_with_inner_lanes(lanes, ego_lane)
    length = lanes[ego_lane].centre.length
    return Road(net_path, edges[0], tuple(lanes), ego_lane, 0.0, length,
                {"route_edges": list(edges)}, tuple(edges), tuple(ego_pieces))


def _checked_ego_lane(net: _Net, edges: list[str], ego_lane: int | None) -> int:
    """The ego's SUMO lane index on the first edge (default: the middle lane), after checking
    that every edge exists with lanes and that the first edge has that lane."""
    for eid in edges:
        if eid not in net.edge_lanes:
            names = ", ".join(list(net.edge_lanes)[:10])
            raise NetworkError(f"{net.path}: route edge {eid!r} does not exist (edges: {names}"
                               f"{', ...' if len(net.edge_lanes) > 10 else ''})")
        if not net.edge_lanes[eid]:
            raise NetworkError(f"{net.path}: edge {eid!r} has no lanes")
    first = net.edge_lanes[edges[0]]
    if ego_lane is None:
        return len(first) // 2
    if not 0 <= ego_lane < len(first):
        later = next((e for e in edges[1:] if ego_lane < len(net.edge_lanes[e])), None)
        hint = (f"; lane {ego_lane} appears only on the later edge {later!r} (e.g. an "
                f"acceleration lane): start the route there (--route {later} ...) to drive it"
                if later is not None and ego_lane >= 0 else "")
        raise NetworkError(f"{net.path}: the scenario needs lane index {ego_lane} but edge "
                           f"{edges[0]!r} has {len(first)} lane(s) (the route's first edge; "
                           f"indices 0..{len(first) - 1}, 0 = rightmost){hint}")
    return ego_lane


def _follow_ego_lane(net: _Net, edges: list[str], ego_lane: int
                     ) -> tuple[list[int], list[RoutePiece]]:
    """The ego lane followed across the junctions: its SUMO lane index on each edge, and its
    pieces (edge and internal lanes) with their arc lengths [m] along the route. A lane that
    does not continue onto the next edge is a :class:`NetworkError` saying which lanes do."""
    ego_index = [ego_lane]
    pieces: list[tuple[_SumoLane, int]] = [(net.edge_lanes[edges[0]][ego_lane], 0)]
    for k, (a, b) in enumerate(pairwise(edges)):
        lane = net.lane(a, ego_index[-1])
        if lane is None:  # a connection of the net leads to a lane its edge does not have
            raise NetworkError(f"{net.path}: edge {a!r} has no lane index {ego_index[-1]}, "
                               "which a connection of the net leads to")
        crossed = net.cross(lane, b)
        if crossed is None:
            reached = sorted({c.to_edge for (e, _), cs in net.connections.items() if e == a
                              for c in cs})
            if b not in reached:
                raise NetworkError(
                    f"{net.path}: route edge {a!r} does not connect to {b!r} (it leads to: "
                    f"{', '.join(reached) or 'nothing'}); list the edges in driving order")
            from_lanes = sorted({i for (e, i), cs in net.connections.items() if e == a
                                 and any(c.to_edge == b for c in cs)})
            raise NetworkError(
                f"{net.path}: the ego lane {lane.lane_id} does not continue from edge {a!r} onto "
                f"{b!r} (only lanes {', '.join(map(str, from_lanes))} of {a!r} do): end the "
                f"route at {a!r} or start in a lane that continues")
        internal, to_lane = crossed
        pieces += [(ln, k) for ln in internal] + [(net.edge_lanes[b][to_lane], k + 1)]
        ego_index.append(to_lane)
    ego_pieces, s = [], 0.0
    for ln, k in pieces:
        length = Polyline(ln.shape).length
        ego_pieces.append(RoutePiece(ln.lane_id, ln.edge_id, ln.index, k, ln.edge_id not in
                                     net.edge_lanes, s, s + length, ln.length))
        s += length
    return ego_index, ego_pieces


def _route_lane(net: _Net, edges: list[str], lane0: _SumoLane, ego_index: list[int],
                offset: int, edge_end_s: list[float]) -> Lane:
    """Lane ``lane0`` of the first edge, ``offset`` lanes left of the ego's, as one polyline
    across the junctions while SUMO connects it to the lane at the same offset from the ego's
    and its width stays the same; where it stops, it ends at the ego lane's arc length
    ``edge_end_s`` [m] of that edge (``ends_at_s``; inf if it runs to the route's end)."""
    shapes, sumo_length, lane, end_k = [lane0.shape], lane0.length, lane0, len(edges) - 1
    for k, b in enumerate(edges[1:]):
        crossed = net.cross(lane, b)
        nxt = None if crossed is None else net.lane(b, crossed[1])
        if crossed is None or nxt is None or crossed[1] != ego_index[k + 1] + offset:
            end_k = k
            break
        if abs(nxt.width - lane0.width) > WIDTH_TOLERANCE_M:
            if offset == 0:  # the ego lane was followed before; only its width can differ
                raise NetworkError(
                    f"{net.path}: the ego lane changes width from {lane0.width:g} m "
                    f"({lane0.lane_id}) to {nxt.width:g} m ({nxt.lane_id}); routes need "
                    "one lane width")
            end_k = k
            break
        shapes += [ln.shape for ln in crossed[0]] + [nxt.shape]
        sumo_length += sum(ln.length for ln in crossed[0]) + nxt.length
        lane = nxt
    centre = Polyline(_join(shapes))
    ends = math.inf if end_k == len(edges) - 1 else edge_end_s[end_k]
    return Lane(
        lane_id=lane0.lane_id, index=lane0.index, width=lane0.width, sumo_length=sumo_length,
        centre=centre, left_boundary=centre.offset(0.5 * lane0.width),
        right_boundary=centre.offset(-0.5 * lane0.width), ends_at_s=ends)


def _end_with_inner_lanes(lanes: list[Lane], ego_lane: int) -> list[Lane]:
    """The lanes, each ending no later than the lanes between it and the ego lane: a lane is
    offered only while every lane between it and the ego lane is."""
    lanes = list(lanes)
    for i in (*range(ego_lane + 1, len(lanes)), *range(ego_lane - 1, -1, -1)):
        inner = lanes[i - 1] if i > ego_lane else lanes[i + 1]
        if inner.ends_at_s < lanes[i].ends_at_s:
            lanes[i] = replace(lanes[i], ends_at_s=inner.ends_at_s)
    return lanes
