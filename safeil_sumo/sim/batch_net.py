"""A SUMO net holding ``n`` copies of tracks, for running ``n`` scenarios in one simulation.

Copy ``i`` renames every edge, lane and junction id with the prefix ``c{i}_`` (internal ids
``:J_0`` become ``:c{i}_J_0``) and moves every shape by its shift along x (:func:`batch_net`:
``n`` copies of one net, ``i * offset_m`` apart; :func:`mixed_batch_net`: copy ``i`` of
``net_paths[i]``, neighbours at least a spacing apart). With shift 0 all copies lie on top of
each other, bit for bit at the original coordinates. SUMO detects collisions, and
``getLeader`` looks for leaders, per lane, never geometrically across edges, so the copies
cannot interact; a copy's geometry is its net's moved by a whole number of metres, so positions
read from SUMO, moved back, equal a one-scenario run's (tests/sim/test_batch.py compares them).
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import math
import os
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

from safeil_sumo.core.atomic import atomic_path

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
            if shape := node.get(key):
                node.set(key, _shift_shape(shape, dx))
        if node.tag == "junction" and (x := node.get("x")) is not None:
            node.set("x", f"{float(x) + dx:.3f}")


def _bounds(root: ET.Element) -> list[float]:
    """``[x0, y0, x1, y1]`` [m] of a net's ``<location convBoundary>``; a ``ValueError`` for a
    net without one."""
    loc = root.find("location")
    boundary = None if loc is None else loc.get("convBoundary")
    if boundary is None:
        raise ValueError("the net has no <location convBoundary>")
    return [float(v) for v in boundary.split(",")]


def copy_offset_m(net_path: Path, spacing_m: float) -> float:
    """x offset [m] between neighbouring copies: the net's width plus ``spacing_m``."""
    x0, _, x1, _ = _bounds(ET.parse(net_path).getroot())
    return math.ceil(x1 - x0 + spacing_m)


def copy_shifts_m(net_paths: Sequence[Path], spacing_m: float) -> list[float]:
    """x shift [m] of each copy when copy ``i`` is of ``net_paths[i]``: cumulative, so copy
    ``i + 1`` starts at least ``spacing_m`` past copy ``i``'s end (convBoundary). For ``n``
    copies of one net: ``i * copy_offset_m(net, spacing_m)``."""
    bounds = [_bounds(ET.parse(p).getroot()) for p in net_paths]
    shifts = [0.0]
    for (_, _, x1, _), (x0, _, _, _) in itertools.pairwise(bounds):
        shifts.append(shifts[-1] + math.ceil(x1 - x0 + spacing_m))
    return shifts[:len(bounds)]


def _rename(elem: ET.Element, i: int) -> None:
    for node in elem.iter():
        if node.tag in ("param", "phase", "request"):  # keys/values and indices, not ids
            continue
        for key in _ID_ATTRS:
            if key in node.attrib:
                node.set(key, prefixed(i, node.attrib[key]))
        for key in _LIST_ATTRS:
            if ids := node.get(key):
                node.set(key, " ".join(prefixed(i, s) for s in ids.split()))


def copies_xml(net_path: Path, n: int, offset_m: float = 0.0) -> bytes:
    """The text of a .net.xml with ``n`` renamed copies of ``net_path``'s net, copy ``i``
    moved by ``i * offset_m`` [m] along x (0: coincident copies)."""
    return mixed_copies_xml([net_path] * n, [i * offset_m for i in range(n)])


def mixed_copies_xml(net_paths: Sequence[Path], shifts_m: Sequence[float]) -> bytes:
    """The text of a .net.xml whose copy ``i`` is ``net_paths[i]``'s net renamed with the
    prefix ``c{i}_`` and moved by ``shifts_m[i]`` [m] along x.

    What a net holds once (``<location>``, ``<type>``, ...) appears once: the first net's, with
    the elements of the others added by (tag, id); the location's convBoundary is the union of
    the shifted copies. Raises ValueError when two nets define the same element (e.g. a
    ``<type>`` id) differently, or differ in the ``<net>`` attributes.
    """
    if len(net_paths) != len(shifts_m):
        raise ValueError(f"{len(net_paths)} nets but {len(shifts_m)} shifts")
    parsed: dict[Path, ET.Element] = {}  # one parse per distinct net
    for p in net_paths:
        if Path(p) not in parsed:
            parsed[Path(p)] = ET.parse(p).getroot()
    roots = [parsed[Path(p)] for p in net_paths]
    out = ET.Element(roots[0].tag, roots[0].attrib)
    out.extend(_shared_elements(net_paths, roots))
    loc = out.find("location")
    shifted = any(shifts_m)
    if loc is not None and shifted and len(roots) > 1:
        # SUMO sizes its spatial grid by this boundary: the union of the shifted copies
        moved = [(_bounds(r), dx) for r, dx in zip(roots, shifts_m, strict=True)]
        b = [min(q[0] + dx for q, dx in moved), min(q[1] for q, _ in moved),
             max(q[2] + dx for q, dx in moved), max(q[3] for q, _ in moved)]
        loc.set("convBoundary", ",".join(f"{v:.3f}" for v in b))
    for i, (root, dx) in enumerate(zip(roots, shifts_m, strict=True)):
        for e in root:
            if e.tag not in _COPIED:
                continue
            c = copy.deepcopy(e)
            _rename(c, i)
            if shifted:  # every copy (also copy 0): shapes written in the nets' precision
                _shift(c, dx)
            out.append(c)
    return ET.tostring(out, encoding="utf-8", xml_declaration=True)


def _shared_elements(net_paths: Sequence[Path], roots: list[ET.Element]) -> list[ET.Element]:
    """Copies of what the nets hold once (``<location>``, ``<type>``, ...): the first net's
    all, another net's those not in an earlier one. ValueError when two nets define the same
    element differently, or differ in the ``<net>`` attributes."""
    first = roots[0]
    shared: list[ET.Element] = []
    # (tag, id) -> the texts of the elements kept
    kept: dict[tuple[str, str | None], list[bytes]] = {}
    for k, (path, root) in enumerate(zip(net_paths, roots, strict=True)):
        if root.attrib != first.attrib:
            raise ValueError(f"batch net: {path} has <net> attributes {root.attrib}, "
                             f"{net_paths[0]} has {first.attrib}")
        if any(root is r for r in roots[:k]):  # a repeat adds nothing once
            continue
        for e in root:
            if e.tag in _COPIED:
                continue
            key, text = (e.tag, e.get("id")), ET.tostring(e)
            seen = kept.get(key)
            if k and seen is not None and text not in seen and e.tag != "location":
                raise ValueError(f"batch net: <{e.tag} id={e.get('id')!r}> of {path} differs "
                                 f"from an earlier net's: {text.decode().strip()!r} vs "
                                 f"{seen[0].decode().strip()!r}")
            if k == 0 or seen is None:
                kept.setdefault(key, []).append(text)
                shared.append(copy.deepcopy(e))
    return shared


def batch_net(net_path: Path, n: int, cache_dir: Path | None = None,
              offset_m: float = 0.0) -> Path:
    """Path of a cached .net.xml with ``n`` copies of ``net_path`` (built on first use).

    The cache key is the original net's bytes, ``n``, ``offset_m`` and the copy format version.
    """
    data = Path(net_path).read_bytes()
    key = hashlib.sha256(data + f"|{n}|{offset_m}|{_VERSION}".encode()).hexdigest()[:16]
    out = _cache_folder(cache_dir) / (f"{Path(net_path).name.removesuffix('.net.xml')}_x{n}_"
                                      f"{key}.net.xml")
    if not out.is_file():
        _write(out, copies_xml(Path(net_path), n, offset_m))
    return out


def _cache_folder(cache_dir: Path | None) -> Path:
    return Path(cache_dir) if cache_dir is not None else Path(
        os.environ.get("SAFEIL_BATCH_NET_CACHE", Path(tempfile.gettempdir()) / "safeil_batch_nets"))


def _write(out: Path, data: bytes) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        tmp.write_bytes(data)


def mixed_batch_net(net_paths: Sequence[Path], spacing_m: float,
                    cache_dir: Path | None = None) -> tuple[Path, list[float]]:
    """``(path, shifts)``: a cached .net.xml whose copy ``i`` is ``net_paths[i]``'s net, and
    each copy's x shift [m] (:func:`copy_shifts_m`, neighbours ``spacing_m`` apart).

    Copies of one net are :func:`batch_net`'s file (same text and cache entry). The cache key
    of a mix is every net's bytes, the shifts and the copy format version.
    """
    paths = [Path(p) for p in net_paths]
    if len(set(paths)) == 1:
        offset = copy_offset_m(paths[0], spacing_m)
        n = len(paths)
        return batch_net(paths[0], n, cache_dir, offset), [i * offset for i in range(n)]
    shifts = copy_shifts_m(paths, spacing_m)
    digest = hashlib.sha256()
    for p, dx in zip(paths, shifts, strict=True):
        digest.update(p.read_bytes() + f"|{dx}|".encode())
    digest.update(f"{_VERSION}".encode())
    out = _cache_folder(cache_dir) / (f"{paths[0].name.removesuffix('.net.xml')}_mix"
                                      f"{len(paths)}_{digest.hexdigest()[:16]}.net.xml")
    if not out.is_file():
        _write(out, mixed_copies_xml(paths, shifts))
    return out, shifts
