"""Fabric cooking, pure numpy: topology in, immutable solver-ready fabric out.

A fabric is what many cloth instances share: rest pose, links (structural, shear, bending)
greedily graph-coloured into independent batches and sorted by colour, triangles, the
vertex adjacency the Jacobi solver gathers over (vertices packed by degree), per-vertex
area (mass share) and tether anchors. It never changes after cooking, so cloths made from
the same mesh, link options and pins share one fabric and its device buffers.

Grid geometry and OBJ parsing are the wire protocol's (drape.client.protocol.geometry): one
implementation, here kept in float64. Tether anchors (each free vertex's nearest pinned vertex)
are found in bounded memory, and only for fabrics cooked with ``tethers=True`` or when first
asked for (Fabric.tethers), so a cloth without tethers never pays for them.
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

from .params import LINK_BENDING, LINK_SHEAR, LINK_STRUCTURAL, LinkOptions

log = logging.getLogger(__name__)

MAX_VERTICES = 1 << 20  # per cloth; a hard sanity cap against hostile submissions
MIN_REST_LENGTH = 0.0  # zero-length links are kept and handled by the solvers (a weld)
TETHER_PAIRS_PER_CHUNK = 1 << 21  # (free vertex, pin) distances held at once by the tether set-up (~16 MB each array)
TETHER_GROUP = 256  # neighbouring free vertices that share one candidate-pin search


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
    # tether anchors, computed once on demand (see tethers()); a list so the frozen fabric can fill it
    _tethers: list = field(default_factory=list, repr=False)
    _tether_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def tethers(self) -> tuple[np.ndarray, np.ndarray]:
        """(anchor, length): each free vertex's nearest pinned vertex (int32, -1 for pinned
        vertices or when nothing is pinned) and its rest distance to it (float64). Computed on
        the first call (thread-safe), in bounded memory."""
        with self._tether_lock:
            if not self._tethers:
                anchor, length = tether_anchors(self.rest_positions, self.pinned)
                anchor.setflags(write=False)
                length.setflags(write=False)
                self._tethers.extend((anchor, length))
            return self._tethers[0], self._tethers[1]

    @property
    def tethers_ready(self) -> bool:
        """Whether the tether anchors have been computed (cooked with tethers=True, or asked for)."""
        return bool(self._tethers)

    @property
    def tether_anchor(self) -> np.ndarray:  # (n,) int32: nearest pinned vertex, -1 for pinned or none
        return self.tethers()[0]

    @property
    def tether_length(self) -> np.ndarray:  # (n,) float64: rest distance to that anchor
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
# Links


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2) of a triangle list, lower index first, in first-seen order."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return _unique_pairs(e)


def bending_pairs(triangles: np.ndarray) -> np.ndarray:
    """For every interior edge shared by exactly two triangles, the two opposite vertices."""
    if len(triangles) == 0:
        return np.zeros((0, 2), np.int32)
    t = triangles.astype(np.int64)
    half = np.concatenate([t[:, [0, 1, 2]], t[:, [1, 2, 0]], t[:, [2, 0, 1]]])  # (a, b, opposite)
    lo = np.minimum(half[:, 0], half[:, 1])
    hi = np.maximum(half[:, 0], half[:, 1])
    key = lo * (t.max() + 1) + hi
    order = np.argsort(key, kind="stable")
    ks = key[order]
    same = ks[1:] == ks[:-1]
    # an edge with exactly two incident triangles: pair i, i+1 equal and not part of a longer run
    run_start = np.r_[True, ~same]
    run_len = np.diff(np.r_[np.flatnonzero(run_start), len(ks)])
    starts = np.flatnonzero(run_start)[run_len == 2]
    opp = np.stack([half[order[starts], 2], half[order[starts + 1], 2]], 1)
    opp = opp[opp[:, 0] != opp[:, 1]]
    return _unique_pairs(opp)


def grid_links(cols: int, rows: int, options: LinkOptions) -> tuple[np.ndarray, np.ndarray]:
    """Links of a regular grid: structural = row and column neighbours, shear = both cell
    diagonals, bending = neighbours two apart along rows and columns."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    parts: list[np.ndarray] = []
    types: list[tuple[int, int]] = []  # (link type, number of links) of each part

    def add(a: np.ndarray, b: np.ndarray, t: int) -> None:
        if a.size:
            parts.append(np.stack([a.ravel(), b.ravel()], 1))
            types.append((t, a.size))

    if options.structural:
        add(idx[:, :-1], idx[:, 1:], LINK_STRUCTURAL)
        add(idx[:-1, :], idx[1:, :], LINK_STRUCTURAL)
    if options.shear:
        add(idx[:-1, :-1], idx[1:, 1:], LINK_SHEAR)
        add(idx[:-1, 1:], idx[1:, :-1], LINK_SHEAR)
    if options.bending:
        add(idx[:, :-2], idx[:, 2:], LINK_BENDING)
        add(idx[:-2, :], idx[2:, :], LINK_BENDING)
    if not parts:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.int8)
    links = np.concatenate(parts).astype(np.int32)
    ltype = np.concatenate([np.full(n, t, np.int8) for t, n in types])
    return links, ltype


def mesh_links(triangles: np.ndarray, options: LinkOptions) -> tuple[np.ndarray, np.ndarray]:
    """Links of a triangle mesh: structural = edges, bending = across interior edges.
    A general mesh has no shear diagonals; the shear option only applies to grids."""
    parts, types = [], []
    if options.structural:
        e = mesh_edges(triangles)
        parts.append(e)
        types.append(np.full(len(e), LINK_STRUCTURAL, np.int8))
    if options.bending:
        b = bending_pairs(triangles)
        parts.append(b)
        types.append(np.full(len(b), LINK_BENDING, np.int8))
    if not parts:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.int8)
    return np.concatenate(parts).astype(np.int32), np.concatenate(types)


def dedupe_links(links: np.ndarray, ltype: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop self-links and repeated pairs (the first occurrence, i.e. the stronger type, wins)."""
    if len(links) == 0:
        return links.reshape(0, 2).astype(np.int32), ltype
    keep = links[:, 0] != links[:, 1]
    links, ltype = links[keep], ltype[keep]
    lo = np.minimum(links[:, 0], links[:, 1]).astype(np.int64)
    hi = np.maximum(links[:, 0], links[:, 1]).astype(np.int64)
    _, first = np.unique(lo * (int(hi.max(initial=0)) + 1) + hi, return_index=True)
    first.sort()
    return links[first].astype(np.int32), ltype[first]


def greedy_colour(links: np.ndarray, n_vertices: int) -> np.ndarray:
    """Greedy edge colouring: each link, in order, takes the lowest colour unused at both of its
    vertices. No two links of one colour share a vertex."""
    colours = np.empty(len(links), np.int32)
    used = [0] * n_vertices  # bitmask of colours already at each vertex (python ints: unbounded)
    for i, (a, b) in enumerate(links.tolist()):
        m = used[a] | used[b]
        c = (~m & (m + 1)).bit_length() - 1  # lowest clear bit
        colours[i] = c
        bit = 1 << c
        used[a] |= bit
        used[b] |= bit
    return colours


def _unique_pairs(pairs: np.ndarray) -> np.ndarray:
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int32)
    p = np.sort(pairs.astype(np.int64), axis=1)
    key = p[:, 0] * (int(p.max()) + 1) + p[:, 1]
    _, first = np.unique(key, return_index=True)
    first.sort()
    return p[first].astype(np.int32)


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


def tether_anchors(
    v: np.ndarray, pinned: np.ndarray, pairs_per_chunk: int = TETHER_PAIRS_PER_CHUNK
) -> tuple[np.ndarray, np.ndarray]:
    """Each free vertex's nearest pinned vertex (int32, -1 for pinned vertices or when none is
    pinned; the lowest index among equally near ones) and the rest distance to it (float64).

    Free vertices are taken in groups of TETHER_GROUP neighbours (Morton order); a group only
    looks at the pins that can be nearest to one of its vertices (within d0 + 2r of the group's
    centre, d0 the centre's nearest pin and r the group's radius), in blocks of at most
    ``pairs_per_chunk`` (vertex, pin) pairs (see _nearest_pins). Memory is a few arrays of
    ``pairs_per_chunk`` values plus one distance per pin, whatever the cloth's size and pin count."""
    n = len(v)
    anchor = np.full(n, -1, np.int32)
    length = np.zeros(n)
    pinned = np.asarray(pinned, bool)
    pins = np.flatnonzero(pinned)
    free = np.flatnonzero(~pinned)
    if len(pins) == 0 or len(free) == 0:
        return anchor, length
    v = np.asarray(v, np.float64)
    pv = np.ascontiguousarray(v[pins])
    free = free[np.argsort(_morton(v[free]), kind="stable")]
    for g in range(0, len(free), TETHER_GROUP):
        idx = free[g : g + TETHER_GROUP]
        x = v[idx]
        centre = 0.5 * (x.min(axis=0) + x.max(axis=0))
        radius = float(np.sqrt(((x - centre) ** 2).sum(axis=1).max()))
        dc = np.sqrt(((pv - centre) ** 2).sum(axis=1))
        reach = float(dc.min()) + 2.0 * radius
        reach += 1e-9 * (reach + float(np.abs(centre).max()) + 1.0)  # far above the rounding of dc
        sel = np.flatnonzero(dc <= reach)  # ascending: ties still go to the lowest pin index
        rows = max(1, int(pairs_per_chunk) // len(sel))
        for s in range(0, len(idx), rows):
            a, d = _nearest_pins(x[s : s + rows], pv[sel])
            anchor[idx[s : s + rows]] = pins[sel[a]]
            length[idx[s : s + rows]] = d
    return anchor, length


def _nearest_pins(x: np.ndarray, pv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row of ``x``, the index into ``pv`` of its nearest point (lowest index on ties)
    and the distance |x - p|. Squared distances come from one matrix product
    (|p|^2 - 2 x.p, the same |x|^2 missing from every pin of a row); the points within that
    formula's rounding of the nearest are then compared by their exact distance."""
    p2 = np.einsum("ij,ij->i", pv, pv)
    x2 = np.einsum("ij,ij->i", x, x)
    d2 = x @ (-2.0 * pv.T)  # -2: exact
    d2 += p2[None, :]
    near = d2.min(axis=1)
    tol = 64.0 * np.finfo(np.float64).eps * (x2 + float(p2.max())) + np.finfo(np.float64).tiny
    rr, cc = np.nonzero(d2 <= (near + tol)[:, None])
    del d2
    exact = np.linalg.norm(x[rr] - pv[cc], axis=1)
    order = np.lexsort((cc, exact, rr))  # by row, then distance, then pin index
    first = order[np.r_[True, rr[order][1:] != rr[order][:-1]]]  # rr is sorted: one per row, in row order
    return cc[first], exact[first]


def _morton(x: np.ndarray) -> np.ndarray:
    """Morton (Z-order) codes of points on a 1024^3 grid over their bounding box: nearby codes
    are nearby points, so consecutive points in code order form compact groups."""
    lo, hi = x.min(axis=0), x.max(axis=0)
    q = ((x - lo) / np.where(hi > lo, hi - lo, 1.0) * 1023.0).astype(np.int64)
    code = np.zeros(len(x), np.int64)
    for axis in range(3):
        b = q[:, axis] & 0x3FF
        b = (b | (b << 16)) & 0x030000FF
        b = (b | (b << 8)) & 0x0300F00F
        b = (b | (b << 4)) & 0x030C30C3
        b = (b | (b << 2)) & 0x09249249
        code |= b << axis
    return code


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
