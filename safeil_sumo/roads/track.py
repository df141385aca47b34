"""The geometry of the generated test tracks: :class:`TrackSpec` and its centre line.

Pure numpy, no SUMO: :mod:`safeil_sumo.roads.network` writes a spec's SUMO files, and
:mod:`safeil_sumo.roads.road` rebuilds a generated track's exact lanes from the spec stored
beside its net (the net itself holds a coarser polygon). Both import it from here.

A track is a straight run-in, a circular arc turning LEFT (counter-clockwise), and a straight
run-out, each piece tangent to the next, starting at the world origin heading east (+x). The
road centre line is the SUMO edge shape; lane ``i`` (0 = rightmost) runs at
``(i - (lanes - 1) / 2) * lane_width`` to the left of it. ``TrackSpec.radius_m`` is the radius of
the EGO lane centre, so the road centre line is drawn at ``radius_m + ego_left_offset``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

# Run-in [m]: room to insert the ego with its FRONT bumper (SUMO's position) at the arc start;
# the car is 4.54 m long, so 30 m leaves margin for a vehicle behind or a later start.
DEFAULT_RUN_IN_M = 30.0
# Run-out [m]: the leader starts 50-100 m ahead of the ego at the arc start and drives at up to
# 32 m/s. It must still be on the road when the ego leaves the arc: with a 1 km arc driven at an
# average >= 20 m/s (<= 50 s), the leader covers <= 100 + 32 * 50 = 1700 m, i.e. up to 700 m past
# the arc end. 800 m keeps 100 m margin; a straight costs only 2 shape points.
DEFAULT_RUN_OUT_M = 800.0
# Largest chord sagitta [m] of the arc in the SUMO net (on the outermost lane boundary): ~20 m
# chords at R = 500 m (54 shape points for 1 km). moveToXY cost grows steeply with shape points:
# measured here, moveToXY + simulationStep took 90 us at 116 points (2 cm sagitta), 32 us at 54
# points, 8 us on a straight. SUMO only needs the net for the leader's motion, collisions and SSM;
# our sensors and monitors use the exact arc (road.py rebuilds it at GEOMETRY_SAGITTA_M from the
# track.json), so the 10 cm polygon costs no accuracy where we measure.
MAX_SAGITTA_M = 0.10
# Chord sagitta [m] of the exact geometry used by sensors and monitors (~4 m chords at R = 500 m).
GEOMETRY_SAGITTA_M = 0.002

_NAME_RE = re.compile(r"^[A-Za-z0-9_-]+$")
_FLOAT_FIELDS = (
    "radius_m",
    "arc_length_m",
    "lane_width_m",
    "run_in_m",
    "run_out_m",
    "speed_limit_mps",
)


@dataclass(frozen=True)
class TrackSpec:
    """A one-edge test track: straight run-in, left-turning arc (or straight), straight run-out."""

    name: str
    """File stem and scenario name; letters, digits, ``_`` and ``-`` only."""
    radius_m: float
    """Radius [m] of the EGO lane's centre line on the arc; ``math.inf`` = straight."""
    arc_length_m: float
    """Length [m] of the test path (the arc) along the ego lane centre."""
    lanes: int = 3
    """Number of lanes [-]."""
    lane_width_m: float = 3.5
    """Width of every lane [m]."""
    ego_lane: int = 1
    """SUMO lane index of the ego lane [-] (0 = rightmost; 1 = middle of 3)."""
    run_in_m: float = DEFAULT_RUN_IN_M
    """Straight [m] before the arc, tangent to it."""
    run_out_m: float = DEFAULT_RUN_OUT_M
    """Straight [m] after the arc, tangent to it (where the leader drives on)."""
    speed_limit_mps: float = 36.1
    """Speed limit of the edge [m/s] (36.1 m/s = 130 km/h)."""

    def __post_init__(self) -> None:
        for field_name in _FLOAT_FIELDS:  # 500 -> 500.0: one JSON form for equal specs
            try:
                object.__setattr__(self, field_name, float(getattr(self, field_name)))
            except (TypeError, ValueError):
                raise ValueError(
                    f"{field_name} must be a number, got {getattr(self, field_name)!r}"
                ) from None
        if not isinstance(self.name, str) or not _NAME_RE.match(self.name):
            raise ValueError(f"track name {self.name!r} must be letters, digits, '_' or '-'")
        if math.isnan(self.radius_m) or self.radius_m <= 0:
            raise ValueError(
                f"radius_m must be positive (math.inf = straight), got {self.radius_m}"
            )
        for field_name in ("arc_length_m", "lane_width_m", "speed_limit_mps"):
            value = getattr(self, field_name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{field_name} must be positive and finite, got {value}")
        for field_name in ("run_in_m", "run_out_m"):
            value = getattr(self, field_name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{field_name} must be >= 0 and finite, got {value}")
        if isinstance(self.lanes, bool) or not isinstance(self.lanes, int) or self.lanes < 1:
            raise ValueError(f"lanes must be an integer >= 1, got {self.lanes!r}")
        if not isinstance(self.ego_lane, int) or not 0 <= self.ego_lane < self.lanes:
            raise ValueError(
                f"ego_lane must be a lane index in [0, {self.lanes - 1}], got {self.ego_lane!r}"
            )
        reach = self.farthest_boundary_m
        if self.radius_m <= reach:
            raise ValueError(
                f"radius_m {self.radius_m} m is not larger than the {reach} m from the ego lane "
                "centre to the farthest lane boundary"
            )
        if self.is_curved and self.arc_angle_rad >= 2.0 * math.pi:
            raise ValueError(
                f"an arc of {self.arc_length_m} m at radius {self.radius_m} m turns a full circle "
                "or more and would overlap itself"
            )

    @property
    def is_curved(self) -> bool:
        return math.isfinite(self.radius_m)

    @property
    def ego_offset_m(self) -> float:
        """Lateral offset [m] of the ego lane centre from the road centre line (+ = left)."""
        return (self.ego_lane - 0.5 * (self.lanes - 1)) * self.lane_width_m

    @property
    def farthest_boundary_m(self) -> float:
        """Distance [m] from the ego lane centre to the farthest outer lane boundary."""
        right = (self.ego_lane + 0.5) * self.lane_width_m
        left = (self.lanes - self.ego_lane - 0.5) * self.lane_width_m
        return max(left, right)

    @property
    def arc_angle_rad(self) -> float:
        """Heading change [rad] over the arc (0 for a straight track)."""
        return self.arc_length_m / self.radius_m if self.is_curved else 0.0

    @property
    def road_radius_m(self) -> float:
        """Radius [m] of the road centre line (the edge shape) on the arc; inf if straight."""
        return self.radius_m + self.ego_offset_m


def road_centre_line(spec: TrackSpec, max_sagitta_m: float = MAX_SAGITTA_M) -> np.ndarray:
    """The edge shape ``(N, 2)`` [m]: run-in (2 points), sampled arc, run-out (2 points).

    ``max_sagitta_m``: chord sagitta bound on the outermost boundary; the SUMO net uses
    :data:`MAX_SAGITTA_M`, the exact geometry of sensors and monitors a much finer one.
    """
    x0 = spec.run_in_m
    if not spec.is_curved:
        xs = [0.0, x0, x0 + spec.arc_length_m, x0 + spec.arc_length_m + spec.run_out_m]
        pts = np.array([[x, 0.0] for x in xs])
    else:
        r = spec.road_radius_m
        r_out = r + 0.5 * spec.lanes * spec.lane_width_m  # outermost boundary: largest sagitta
        max_step = 2.0 * math.acos(1.0 - max_sagitta_m / r_out)
        n = max(1, math.ceil(spec.arc_angle_rad / max_step))
        theta = np.linspace(0.0, spec.arc_angle_rad, n + 1)
        # centre of the circle at (x0, r): the road turns left (counter-clockwise)
        arc = np.stack([x0 + r * np.sin(theta), r - r * np.cos(theta)], axis=1)
        phi = spec.arc_angle_rad
        out_end = arc[-1] + spec.run_out_m * np.array([math.cos(phi), math.sin(phi)])
        pts = np.vstack([[0.0, 0.0], arc, out_end])
    # a zero-length run-in or run-out would repeat a vertex
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6])
    return pts[keep]


def ego_path_ends(spec: TrackSpec) -> np.ndarray:
    """World points ``(2, 2)`` [m] of the arc's start and end on the ego lane centre."""
    d = spec.ego_offset_m
    start = [spec.run_in_m, d]
    if not spec.is_curved:
        return np.array([start, [spec.run_in_m + spec.arc_length_m, d]])
    phi, r = spec.arc_angle_rad, spec.radius_m
    end = [spec.run_in_m + r * math.sin(phi), spec.road_radius_m - r * math.cos(phi)]
    return np.array([start, end])
