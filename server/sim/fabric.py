"""Fabric cooking, pure numpy: topology in, immutable solver-ready fabric out.

A fabric is what many cloth instances share: rest pose, links (structural, shear, bending)
greedily graph-coloured into independent batches and sorted by colour, triangles, the
vertex adjacency the Jacobi solver gathers over (vertices packed by degree), per-vertex
area (mass share) and tether anchors. It never changes after cooking, so cloths made from
the same mesh, link options and pins share one fabric and its device buffers.

Grid geometry and OBJ parsing are the wire protocol's (drape.client.protocol.geometry): one
implementation, here kept in float64. The links and their colouring are links.py's; the
long-range attachments (tethers.py: each free vertex's tethers to up to TETHER_SLOTS pin islands
with geodesic rest lengths, and the unilateral long-range links from every vertex to those 5 and
10 links away, coloured like the links) are cooked only for fabrics cooked with ``tethers=True`` or when
first asked for (Fabric.tethers, Fabric.long_range), so a cloth without tethers never pays for
them.
"""

from __future__ import annotations

import hashlib
import logging
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drape.client.protocol.geometry import grid_positions, parse_obj_exact

from .links import (  # noqa: F401  bending_pairs, dedupe_links, mesh_edges: re-exported
    bending_pairs,
    dedupe_links,
    greedy_colour,
    grid_links,
    mesh_edges,
    mesh_links,
)
from .params import LINK_STRUCTURAL, LinkOptions
from .tethers import LONG_RANGE_STRIDES, TETHER_SLOTS, long_range_links, tether_anchors  # noqa: F401  re-exported

log = logging.getLogger(__name__)

MAX_VERTICES = 1 << 20  # per cloth; a hard sanity cap against hostile submissions
MIN_REST_LENGTH = 0.0  # zero-length links are kept and handled by the solvers (a weld)


@dataclass(frozen=True, eq=False)
class Fabric:
    key: str
    rest_positions: np.ndarray  # (n, 3) float64
    triangles: np.ndarray  # (m, 3) int32
    pinned: np.ndarray  # (n,) bool
    links: np.ndarray  # (L, 2) int32, sorted by colour
    link_type: np.ndarray  # (L,) int8: LINK_STRUCTURAL / LINK_SHEAR / LINK_BENDING
    rest_length: np.ndarray  # (L,) float64
    colour_offsets: np.ndarray  # (C+1,) int32: colour c is links[colour_offsets[c]:colour_offsets[c+1]]
    vertex_area: np.ndarray  # (n,) float64: a third of the area of each incident triangle
    jacobi_order: np.ndarray  # (n,) int32: vertices sorted by degree, highest first
    jacobi_offsets: np.ndarray  # (n+1,) int32: CSR over jacobi_order positions
    jacobi_adj: np.ndarray  # (2L, 2) int32: (other vertex, link index) for each incidence
    vtri_offsets: np.ndarray  # (n+1,) int32: CSR of incident triangles per vertex
    vtri: np.ndarray  # (3m,) int32
    # tether anchors and long-range links, computed once on demand (see tethers(), long_range());
    # lists so the frozen fabric can fill them
    _tethers: list = field(default_factory=list, repr=False)
    _long_range: list = field(default_factory=list, repr=False)
    _tether_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def tethers(self) -> tuple[np.ndarray, np.ndarray]:
        """(anchor, length), each (n, TETHER_SLOTS): every free vertex's tethers, one to each of
        up to TETHER_SLOTS pin islands, nearest first: the island's pin nearest along the cloth
        (int32, -1 in unused slots and for pinned vertices) and the geodesic rest distance to it
        (float64). Computed on the first call (thread-safe)."""
        with self._tether_lock:
            if not self._tethers:
                anchor, length = tether_anchors(self.rest_positions, self.pinned, self.links, self.rest_length)
                anchor.setflags(write=False)
                length.setflags(write=False)
                self._tethers.extend((anchor, length))
            return self._tethers[0], self._tethers[1]

    def long_range(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(links (M, 2) int32, rest length (M,) float64, colour offsets (C+1,) int32): the
        unilateral long-range links (tethers.py), sorted by colour (no two of a colour share a
        vertex). Computed on the first call (thread-safe)."""
        with self._tether_lock:
            if not self._long_range:
                s = self.link_type == LINK_STRUCTURAL
                lk, rest = long_range_links(self.rest_positions, self.links[s], self.rest_length[s])
                colours = greedy_colour(lk, self.n_vertices)
                # by colour, and within a colour by their first vertex: the CPU pack solver walks
                # them in this order, so its memory accesses go forward (a 64 x 64 pack's
                # long-range sweep took 10x a link sweep's time per link in colouring order)
                order = np.lexsort((lk.min(axis=1) if len(lk) else lk[:, 0], colours))
                lk, rest, colours = lk[order], rest[order], colours[order]
                n_col = int(colours.max()) + 1 if len(colours) else 0
                offsets = np.searchsorted(colours, np.arange(n_col + 1)).astype(np.int32)
                for a in (lk, rest, offsets):
                    a.setflags(write=False)
                self._long_range.extend((lk, rest, offsets))
            return self._long_range[0], self._long_range[1], self._long_range[2]

    @property
    def tethers_ready(self) -> bool:
        """Whether the tether anchors have been computed (cooked with tethers=True, or asked for)."""
        return bool(self._tethers)

    @property
    def tether_anchor(self) -> np.ndarray:  # (n, TETHER_SLOTS) int32: a pin of each island, -1 unused
        return self.tethers()[0]

    @property
    def tether_length(self) -> np.ndarray:  # (n, TETHER_SLOTS) float64: geodesic rest distance to it
        return self.tethers()[1]

    @property
    def n_vertices(self) -> int:
        return len(self.rest_positions)

    @property
    def n_links(self) -> int:
        return len(self.links)

    @property
    def n_colours(self) -> int:
        return len(self.colour_offsets) - 1

    def colour_of_links(self) -> np.ndarray:
        return np.repeat(np.arange(self.n_colours, dtype=np.int32), np.diff(self.colour_offsets))

    def count(self, link_type: int) -> int:
        return int(np.count_nonzero(self.link_type == link_type))


# ---------------------------------------------------------------------------------------------
# Meshes in


def grid_mesh(
    cols: int,
    rows: int,
    width: float = 1.0,
    height: float = 1.0,
    orientation: str = "horizontal",
    origin: Iterable[float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (rows*cols, 3) float64 and triangles (int32) of a regular grid; vertex (r, c) is
    r*cols + c. The protocol's grid geometry (drape.client.protocol.grid_positions): horizontal in
    the XZ plane (x = columns, z = rows) at the origin's height; vertical in the XY plane, row 0
    at the origin's height, rows going down (-y)."""
    if cols * rows > MAX_VERTICES:
        raise ValueError(f"grid of {cols}x{rows} exceeds {MAX_VERTICES} vertices")
    verts, tris = grid_positions(cols, rows, width, height, orientation, origin)
    return verts, tris.astype(np.int32)


def load_obj(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a Wavefront OBJ file (parse_obj)."""
    return parse_obj(Path(path).read_text())


def parse_obj(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and triangles (m, 3) int32 of OBJ text, by the protocol's rules
    (drape.client.protocol.parse_obj_exact: faces fan-triangulated, v/vt/vn and negative indices,
    out-of-range references refused)."""
    v, t = parse_obj_exact(text)
    return v, t.astype(np.int32)


# ---------------------------------------------------------------------------------------------
# Cooking


def cook(
    vertices: np.ndarray,
    triangles: np.ndarray,
    links: np.ndarray,
    link_type: np.ndarray,
    pinned: Iterable[int] = (),
    tethers: bool = True,
) -> Fabric:
    """Cook a fabric from a rest pose, triangles and candidate links (any order, duplicates
    and self-links removed). Raises ValueError on malformed input. ``tethers``: compute the tether
    anchors now (False: only if and when Fabric.tethers is first asked, e.g. by a cloth with the
    tethers feature)."""
    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError("vertices must be a non-empty (n, 3) array")
    n = len(v)
    if n > MAX_VERTICES:
        raise ValueError(f"{n} vertices exceeds the limit of {MAX_VERTICES}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices must be finite")
    t = np.asarray(triangles, np.int64).reshape(-1, 3)
    if t.size and (t.min() < 0 or t.max() >= n):
        raise ValueError("triangle index out of range")
    if t.size and np.any((t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])):
        raise ValueError("triangle with a repeated vertex")
    lk = np.asarray(links, np.int64).reshape(-1, 2)
    if lk.size and (lk.min() < 0 or lk.max() >= n):
        raise ValueError("link index out of range")
    pin_idx = np.asarray(list(pinned), np.int64).reshape(-1)
    if pin_idx.size and (pin_idx.min() < 0 or pin_idx.max() >= n):
        raise ValueError("pinned index out of range")
    pin_mask = np.zeros(n, bool)
    pin_mask[pin_idx] = True

    lk, lt = dedupe_links(lk.astype(np.int32), np.asarray(link_type, np.int8).reshape(-1))
    colours = greedy_colour(lk, n)
    order = np.argsort(colours, kind="stable")
    lk, lt, colours = lk[order], lt[order], colours[order]
    n_col = int(colours.max()) + 1 if len(colours) else 0
    colour_offsets = np.searchsorted(colours, np.arange(n_col + 1)).astype(np.int32)
    rest = np.linalg.norm(v[lk[:, 1]] - v[lk[:, 0]], axis=1) if len(lk) else np.zeros(0)

    t32 = t.astype(np.int32)
    area = _vertex_area(v, t32)
    j_order, j_off, j_adj = _jacobi_adjacency(lk, n)
    vt_off, vt = _vertex_triangles(t32, n)

    key = _fabric_key(v, t32, lk, lt, pin_mask)
    fab = Fabric(
        key=key,
        rest_positions=v,
        triangles=t32,
        pinned=pin_mask,
        links=lk,
        link_type=lt,
        rest_length=rest,
        colour_offsets=colour_offsets,
        vertex_area=area,
        jacobi_order=j_order,
        jacobi_offsets=j_off,
        jacobi_adj=j_adj,
        vtri_offsets=vt_off,
        vtri=vt,
    )
    for arr in (v, t32, pin_mask, lk, lt, rest, colour_offsets, area, j_order, j_off, j_adj, vt_off, vt):
        arr.setflags(write=False)
    if tethers:
        fab.tethers()
        fab.long_range()
    log.debug("cooked fabric %s: %d vertices, %d links, %d colours", key[:8], n, len(lk), n_col)
    return fab


def cook_grid(
    cols: int,
    rows: int,
    width: float = 1.0,
    height: float = 1.0,
    options: LinkOptions = LinkOptions(),  # noqa: B008 (frozen)
    pinned: Iterable[int] = (),
    orientation: str = "horizontal",
    origin: Iterable[float] = (0.0, 0.0, 0.0),
    tethers: bool = True,
) -> Fabric:
    verts, tris = grid_mesh(cols, rows, width, height, orientation, origin)
    links, ltype = grid_links(cols, rows, options)
    return cook(verts, tris, links, ltype, pinned, tethers)


def cook_mesh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    options: LinkOptions = LinkOptions(),  # noqa: B008 (frozen)
    pinned: Iterable[int] = (),
    tethers: bool = True,
) -> Fabric:
    t = np.asarray(triangles, np.int64).reshape(-1, 3)
    n = len(np.asarray(vertices).reshape(-1, 3))
    if t.size and (t.min() < 0 or t.max() >= n):
        raise ValueError("triangle index out of range")
    links, ltype = mesh_links(t.astype(np.int32), options)
    return cook(vertices, t, links, ltype, pinned, tethers)


# ---------------------------------------------------------------------------------------------
# Derived data


def _vertex_area(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    area = np.zeros(len(v))
    if len(t):
        tri_area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
        for k in range(3):
            np.add.at(area, t[:, k], tri_area / 3.0)
    return area


MIN_AREA_SHARE = 1.0e-6  # of the mean: sliver triangles never make a vertex massless


def vertex_masses(fabric: Fabric, total_mass: float) -> np.ndarray:
    """Mass of each vertex: the total spread by area share (the mean share where there is no area).

    Every share is at least MIN_AREA_SHARE of the mean (then all are renormalised), so with any
    total mass the protocol accepts (>= protocol.MIN_MASS) each vertex's mass and inverse mass are
    normal, finite float32 values whatever sliver triangles a mesh has."""
    area = fabric.vertex_area
    total = float(area.sum())
    n = fabric.n_vertices
    if not total > 0:
        return np.full(n, total_mass / n)
    floor = MIN_AREA_SHARE * total / n
    if np.all(area >= floor):
        return total_mass * area / total
    # vertices touching no triangle get the mean share, slivers the floor; then all are renormalised
    a = np.where(area > 0, np.maximum(area, floor), total / n)
    return total_mass * a / a.sum()


def _jacobi_adjacency(links: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    deg = np.bincount(links.ravel(), minlength=n) if len(links) else np.zeros(n, np.int64)
    order = np.argsort(-deg, kind="stable").astype(np.int32)
    pos = np.empty(n, np.int64)
    pos[order] = np.arange(n)
    offsets = np.zeros(n + 1, np.int32)
    offsets[1:] = np.cumsum(deg[order])
    if len(links) == 0:
        return order, offsets, np.zeros((0, 2), np.int32)
    L = len(links)
    ends = np.concatenate([links[:, 0], links[:, 1]])
    others = np.concatenate([links[:, 1], links[:, 0]])
    lid = np.concatenate([np.arange(L), np.arange(L)])
    srt = np.lexsort((lid, pos[ends]))
    adj = np.stack([others[srt], lid[srt]], 1).astype(np.int32)
    return order, offsets, adj


def _vertex_triangles(t: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    if len(t) == 0:
        return np.zeros(n + 1, np.int32), np.zeros(0, np.int32)
    v = t.ravel()
    tri = np.repeat(np.arange(len(t)), 3)
    srt = np.argsort(v, kind="stable")
    offsets = np.zeros(n + 1, np.int32)
    offsets[1:] = np.cumsum(np.bincount(v, minlength=n))
    return offsets, tri[srt].astype(np.int32)


def _fabric_key(*arrays: np.ndarray) -> str:
    h = hashlib.sha1()
    for a in arrays:
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()
