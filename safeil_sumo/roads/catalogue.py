"""Named test tracks, and ``--net`` resolution: a catalogue name or a path -> a ``.net.xml``.

Names:
- ``curved500``: the paper's safety track: a left-turning arc of radius 500 m (ego lane centre)
  and 1 km length, 3 lanes x 3.5 m, ego in the middle lane.
- ``straight``: a 2 km straight 3-lane road. Its test path is what is left of the 2 km after the
  run-in (ego insertion) and the run-out the leader needs (see ``track.DEFAULT_RUN_OUT_M``):
  2000 - 30 - 800 = 1170 m.
- ``curved<R>`` (``curved300``, ``curved1000``, ...): ``curved500`` with ego lane radius R [m].

``curved500`` and ``straight`` are committed under ``<repo>/sumo_scenarios/<name>/`` (regenerate
with ``python training/build_networks.py``); other names are generated on first use into a cache
folder (``$SAFEIL_SUMO_CACHE``, default ``~/.cache/safeil_sumo/nets``) and reused while their
``.track.json`` matches the spec.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import asdict
from pathlib import Path

from safeil_sumo.roads.network import GENERATOR_VERSION, build_network
from safeil_sumo.roads.road import NetworkError
from safeil_sumo.roads.track import DEFAULT_RUN_IN_M, DEFAULT_RUN_OUT_M, TrackSpec

PAPER_RADIUS_M = 500.0  # ego lane centre radius of the paper's safety track [m]
PAPER_ARC_LENGTH_M = 1000.0  # length of the paper's safety track [m]
STRAIGHT_TOTAL_M = 2000.0  # total length of the straight track [m]

# Names with committed files; ``curved<R>`` is a pattern on top of these.
CATALOGUE: tuple[str, ...] = ("curved500", "straight")
CURVED_PATTERN = re.compile(r"^curved([1-9][0-9]*)$")

REPO_ROOT = Path(__file__).resolve().parents[2]
COMMITTED_DIR = REPO_ROOT / "sumo_scenarios"
DEFAULT_CACHE_DIR = Path("~/.cache/safeil_sumo/nets")


def _valid_names() -> str:
    return ", ".join(CATALOGUE) + ", curved<R> (R in metres, e.g. curved300)"


def spec_for(name: str) -> TrackSpec:
    """The :class:`TrackSpec` of a catalogue name; :class:`NetworkError` if unknown or invalid."""
    if name == "straight":
        arc = STRAIGHT_TOTAL_M - DEFAULT_RUN_IN_M - DEFAULT_RUN_OUT_M
        return TrackSpec(name="straight", radius_m=math.inf, arc_length_m=arc)
    match = CURVED_PATTERN.match(name)
    if match is None:
        raise NetworkError(f"unknown track {name!r}; valid names: {_valid_names()}")
    try:
        return TrackSpec(name=name, radius_m=float(match.group(1)), arc_length_m=PAPER_ARC_LENGTH_M)
    except ValueError as exc:
        raise NetworkError(f"track {name!r} cannot be built: {exc}") from exc


def default_cache_dir() -> Path:
    """``$SAFEIL_SUMO_CACHE`` if set, else ``~/.cache/safeil_sumo/nets``."""
    return Path(os.environ.get("SAFEIL_SUMO_CACHE") or DEFAULT_CACHE_DIR).expanduser()


def _is_current(spec: TrackSpec, folder: Path) -> bool:
    """True if ``folder`` holds a complete build of exactly ``spec`` by this generator."""
    net = folder / f"{spec.name}.net.xml"
    sidecar = folder / f"{spec.name}.track.json"
    if not (net.is_file() and sidecar.is_file()):
        return False
    try:
        meta = json.loads(sidecar.read_text())
    except (OSError, ValueError):
        return False
    wanted = asdict(spec) | {"generator_version": GENERATOR_VERSION}
    return all(meta.get(key) == value for key, value in wanted.items())


def resolve_net(name_or_path: str, cache_dir: Path | None = None) -> Path:
    """A ``.net.xml`` path for a catalogue name or an existing ``.net.xml`` path.

    Raises :class:`NetworkError` for a missing file or an unknown name (listing valid names).
    """
    if name_or_path.endswith(".net.xml"):
        path = Path(name_or_path).expanduser()
        if not path.is_file():
            raise NetworkError(f"network file not found: {path}")
        return path
    spec = spec_for(name_or_path)
    if spec.name in CATALOGUE:
        committed = COMMITTED_DIR / spec.name / f"{spec.name}.net.xml"
        if committed.is_file():
            return committed
    # not shipped (a curved<R> variant, or a non-editable install): build once into the cache
    folder = Path(cache_dir if cache_dir is not None else default_cache_dir()) / spec.name
    if _is_current(spec, folder):
        return folder / f"{spec.name}.net.xml"
    return build_network(spec, folder)
