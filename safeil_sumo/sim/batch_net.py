"""A SUMO net holding ``n`` copies of a track, for running ``n`` scenarios in one simulation.

Copy ``i`` renames every edge, lane and junction id with the prefix ``c{i}_`` (internal ids
``:J_0`` become ``:c{i}_J_0``) and keeps every shape as the same text: all copies lie on top of
each other, bit for bit at the original coordinates. SUMO detects collisions, and ``getLeader``
looks for leaders, per lane, never geometrically across edges, so the copies cannot interact;
the geometry of each copy equals the original net's, so positions read from SUMO equal a
one-scenario run's exactly (tests/test_batch.py compares them).
"""

from __future__ import annotations

import copy
import hashlib
import math
import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

from safeil_sumo.atomic import atomic_path

# elements of a .net.xml that belong to one copy of the track (the rest, e.g. <location> and
# <type>, appears once)
_COPIED = ("edge", "junction", "connection", "tlLogic", "roundabout")
# attributes that hold one id / a space-separated list of ids of edges, lanes or junctions
_ID_ATTRS = ("id", "from", "to", "via", "tl", "lane")
_LIST_ATTRS = ("incLanes", "intLanes", "edges", "nodes")
# bump when the copies change, so cached nets are rebuilt
_VERSION = 1


def prefixed(i: int, ident: str) -> str:
    """Id ``ident`` of the original net in copy ``i`` (internal ids keep their leading ``:``)."""
    if ident.startswith(":"):
        return f":c{i}_{ident[1:]}"
    return f"c{i}_{ident}"


def _shift_shape(text: str, dx: float) -> str:
    """A SUMO shape ``"x,y[,z] x,y[,z] ..."`` moved by ``dx`` [m] along x (3 decimals: the
    nets' precision)."""
    out = []
    for point in text.split():
        xyz = point.split(",")
        xyz[0] = f"{float(xyz[0]) + dx:.3f}"
        out.append(",".join(xyz))
    return " ".join(out)


def _shift(elem: ET.Element, dx: float) -> None:
    for node in elem.iter():
        for key in ("shape", "customShape"):
            if node.get(key):
                node.set(key, _shift_shape(node.get(key), dx))
        if node.tag == "junction" and node.get("x") is not None:
            node.set("x", f"{float(node.get('x')) + dx:.3f}")


def copy_offset_m(net_path: Path, spacing_m: float) -> float:
    """x offset [m] between neighbouring copies: the net's width plus ``spacing_m``."""
    loc = ET.parse(net_path).getroot().find("location")
    x0, _, x1, _ = (float(v) for v in loc.get("convBoundary").split(","))
    return math.ceil(x1 - x0 + spacing_m)


def _rename(elem: ET.Element, i: int) -> None:
    for node in elem.iter():
        if node.tag in ("param", "phase", "request"):  # keys/values and indices, not ids
            continue
        for key in _ID_ATTRS:
            if key in node.attrib:
                node.set(key, prefixed(i, node.get(key)))
        for key in _LIST_ATTRS:
            if node.get(key):
                node.set(key, " ".join(prefixed(i, s) for s in node.get(key).split()))


def copies_xml(net_path: Path, n: int, offset_m: float = 0.0) -> bytes:
    """The text of a .net.xml with ``n`` renamed copies of ``net_path``'s net, copy ``i``
    moved by ``i * offset_m`` [m] along x (0: coincident copies)."""
    root = ET.parse(net_path).getroot()
    out = ET.Element(root.tag, root.attrib)
    kept = [copy.deepcopy(e) for e in root if e.tag not in _COPIED]
    copied = [e for e in root if e.tag in _COPIED]
    out.extend(kept)
    loc = out.find("location")
    if loc is not None and offset_m and n > 1:  # SUMO sizes its spatial grid by this boundary
        b = [float(v) for v in loc.get("convBoundary").split(",")]
        b[2] += (n - 1) * offset_m
        loc.set("convBoundary", ",".join(f"{v:.3f}" for v in b))
    for i in range(n):
        for e in copied:
            c = copy.deepcopy(e)
            _rename(c, i)
            if offset_m:
                _shift(c, i * offset_m)
            out.append(c)
    return ET.tostring(out, encoding="utf-8", xml_declaration=True)


def batch_net(net_path: Path, n: int, cache_dir: Path | None = None,
              offset_m: float = 0.0) -> Path:
    """Path of a cached .net.xml with ``n`` copies of ``net_path`` (built on first use).

    The cache key is the original net's bytes, ``n``, ``offset_m`` and the copy format version.
    """
    data = Path(net_path).read_bytes()
    key = hashlib.sha256(data + f"|{n}|{offset_m}|{_VERSION}".encode()).hexdigest()[:16]
    folder = Path(cache_dir) if cache_dir is not None else Path(
        os.environ.get("SAFEIL_BATCH_NET_CACHE", Path(tempfile.gettempdir()) / "safeil_batch_nets"))
    out = folder / f"{Path(net_path).name.removesuffix('.net.xml')}_x{n}_{key}.net.xml"
    if not out.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:
            tmp.write_bytes(copies_xml(Path(net_path), n, offset_m))
    return out
