"""Long-range attachments, pure numpy and heaps: tethers and long-range links.

**Tethers** (Kim, Chentanez, Mueller 2012; NvCloth's geodesic tether cooker): each free vertex gets
one tether to every *pin island* (pinned vertices connected by links), up to ``TETHER_SLOTS``
islands, the nearest first. A tether's anchor is the island's pin nearest along the cloth and its
rest length the geodesic distance to it, so a vertex between two pinned corners is held by both
(the middle of a hanging cloth's top edge, which a tether to the nearest pin alone cannot hold).

Geodesic distances run over the fabric's links with their rest lengths (a multi-label Dijkstra:
each vertex settles up to TETHER_SLOTS islands), made any-angle where the cloth is flat: a
vertex reached from u may take u's own predecessor p as its predecessor when the chord p -> v
stays within ``ANY_ANGLE_SAG`` of a link length of u (the chord lies on the cloth). On a flat
convex grid the result is the straight-line distance; around a hole or across a fold it follows
the cloth. Graph paths never come out shorter than the cloth's geodesic, so a tether never pulls
a vertex closer than its rest distance; the any-angle chord may cut a curved surface by at most
about that sag.

**Long-range links**: unilateral links (they only resist stretching) between the vertices of a
coarse hierarchy of the cloth: on a grid, the vertices at every stride-th row and column
(strides 2, 4, ... up to the grid), each linked to its next coarse neighbour along the row and
the column (+16 % links on 64 x 64); on a mesh, a greedy sample of vertices at spacing
2^k times the mean link length, each linked to the samples within 1.5 spacings along the cloth,
rest length the geodesic (graph) distance. Like tethers they hold at most ``tether_limit``
times their rest length.
"""

from __future__ import annotations

import heapq

import numpy as np

TETHER_SLOTS = 4  # tethers per vertex: one per pin island, the nearest TETHER_SLOTS islands
ANY_ANGLE_SAG = 0.5  # a chord p -> v replaces p -> u -> v when u is within this many |uv| of it
LONG_RANGE_MIN_STRIDE = 2
LONG_RANGE_REACH = 1.5  # mesh long-range links: samples within this many spacings are linked


def _adjacency(n: int, links: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR of the undirected link graph: offsets (n+1), neighbour, weight (rest length)."""
    if len(links) == 0:
        return np.zeros(n + 1, np.int64), np.zeros(0, np.int64), np.zeros(0)
    a = np.concatenate([links[:, 0], links[:, 1]]).astype(np.int64)
    b = np.concatenate([links[:, 1], links[:, 0]]).astype(np.int64)
    w = np.concatenate([rest, rest]).astype(np.float64)
    order = np.lexsort((b, a))
    off = np.zeros(n + 1, np.int64)
    off[1:] = np.cumsum(np.bincount(a, minlength=n))
    return off, b[order], w[order]


def pin_islands(n: int, pinned: np.ndarray, links: np.ndarray) -> np.ndarray:
    """Island id (0, 1, ...) of each pinned vertex, -1 for free ones: pinned vertices joined by a
    link are one island. Ids follow the lowest pinned index of each island."""
    pinned = np.asarray(pinned, bool)
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    if len(links):
        both = pinned[links[:, 0]] & pinned[links[:, 1]]
        for a, b in links[both].tolist():
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    island = np.full(n, -1, np.int64)
    ids: dict[int, int] = {}
    for p in np.flatnonzero(pinned).tolist():
        r = find(p)
        island[p] = ids.setdefault(r, len(ids))
    return island


def tether_anchors(
    v: np.ndarray, pinned: np.ndarray, links: np.ndarray, rest: np.ndarray, slots: int = TETHER_SLOTS
) -> tuple[np.ndarray, np.ndarray]:
    """(anchor (n, slots) int32, length (n, slots) float64): each free vertex's tethers, one per
    pin island, nearest island first; -1 (length 0) in unused slots and for pinned vertices.

    Multi-label Dijkstra over the link graph from every pin at once: a vertex settles each island
    the first time it is popped with it, at most ``slots`` islands; any-angle where the chord
    stays on the cloth (module docstring)."""
    v = np.asarray(v, np.float64)
    n = len(v)
    pinned = np.asarray(pinned, bool)
    anchor = np.full((n, slots), -1, np.int32)
    length = np.zeros((n, slots))
    if not pinned.any() or pinned.all():
        return anchor, length
    island = pin_islands(n, pinned, links)
    off, nb, wt = _adjacency(n, np.asarray(links, np.int64).reshape(-1, 2), np.asarray(rest, np.float64))
    offl, nbl, wtl = off.tolist(), nb.tolist(), wt.tolist()
    vl = v.tolist()
    # settled labels: per vertex {island: (dist, pin, predecessor)}
    settled: list[dict[int, tuple[float, int, int]]] = [{} for _ in range(n)]
    heap: list[tuple[float, int, int, int, int]] = []  # (dist, vertex, island, pin, predecessor)
    for p in np.flatnonzero(pinned).tolist():
        heap.append((0.0, p, int(island[p]), p, -1))
    heapq.heapify(heap)
    pin_list = pinned.tolist()
    while heap:
        d, u, isl, pin, pred = heapq.heappop(heap)
        su = settled[u]
        if isl in su or len(su) >= slots:
            continue
        su[isl] = (d, pin, pred)
        xu = vl[u]
        for k in range(offl[u], offl[u + 1]):
            w = nbl[k]
            if pin_list[w]:
                continue  # pinned vertices carry no tethers; paths do not run through other pins
            sw = settled[w]
            if isl in sw or len(sw) >= slots:
                continue
            nd, npred = d + wtl[k], u
            if pred >= 0:  # any-angle: straight from u's predecessor when the chord is on the cloth
                xp, xw = vl[pred], vl[w]
                c = (xw[0] - xp[0], xw[1] - xp[1], xw[2] - xp[2])
                cl2 = c[0] * c[0] + c[1] * c[1] + c[2] * c[2]
                if cl2 > 0.0:
                    e = (xu[0] - xp[0], xu[1] - xp[1], xu[2] - xp[2])
                    t = min(max((e[0] * c[0] + e[1] * c[1] + e[2] * c[2]) / cl2, 0.0), 1.0)
                    q = (e[0] - t * c[0], e[1] - t * c[1], e[2] - t * c[2])
                    sag2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2]
                    if sag2 <= (ANY_ANGLE_SAG * wtl[k]) ** 2:
                        cand = settled[pred][isl][0] + cl2**0.5
                        if cand < nd:
                            nd, npred = cand, pred
            heapq.heappush(heap, (nd, w, isl, pin, npred))
    for i in np.flatnonzero(~pinned).tolist():
        labels = sorted(settled[i].items(), key=lambda kv: (kv[1][0], kv[0]))[:slots]
        for s, (_, (d, pin, _)) in enumerate(labels):
            anchor[i, s] = pin
            length[i, s] = max(d, float(np.linalg.norm(v[i] - v[pin])))  # never below the straight line
    return anchor, length


# ---------------------------------------------------------------------------------------------
# Long-range links


def grid_long_range(cols: int, rows: int, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Long-range links of a (flat) grid: for strides 2, 4, ... below the grid's size, the
    vertices at every stride-th row and column, each linked to the next along its row and its
    column; coarsest stride first (the order they colour and run in: measured on the hanging
    64 x 64 at 1 x 8, max stretch 50 -> 41 %). (links (M, 2) int32, rest length (M,) float64:
    the straight distance.)"""
    idx = np.arange(rows * cols).reshape(rows, cols)
    parts = []
    s = LONG_RANGE_MIN_STRIDE
    while s < max(cols, rows):
        sub = idx[::s, ::s]
        if sub.shape[1] > 1:
            parts.append(np.stack([sub[:, :-1].ravel(), sub[:, 1:].ravel()], 1))
        if sub.shape[0] > 1:
            parts.append(np.stack([sub[:-1, :].ravel(), sub[1:, :].ravel()], 1))
        s *= 2
    if not parts:
        return np.zeros((0, 2), np.int32), np.zeros(0)
    lk = np.concatenate(parts[::-1]).astype(np.int32)  # coarsest first: they colour (and run) first
    return lk, np.linalg.norm(v[lk[:, 1]] - v[lk[:, 0]], axis=1)


def mesh_long_range(v: np.ndarray, links: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Long-range links of a mesh: at levels k = 1, 2, ..., a greedy sample of vertices (Morton
    order) no two within 2^k mean link lengths of each other along the cloth, each linked to the
    samples within LONG_RANGE_REACH spacings along the cloth (a bounded Dijkstra), rest length
    that graph distance (never shorter than the cloth's geodesic, so the link never holds the
    cloth shorter than its rest shape). Stops when a level has fewer than 2 samples."""
    v = np.asarray(v, np.float64)
    n = len(v)
    links = np.asarray(links, np.int64).reshape(-1, 2)
    if len(links) == 0 or n < 3:
        return np.zeros((0, 2), np.int32), np.zeros(0)
    off, nb, wt = _adjacency(n, links, np.asarray(rest, np.float64))
    offl, nbl, wtl = off.tolist(), nb.tolist(), wt.tolist()
    ell = float(np.mean(rest)) if len(rest) else 0.0
    if not ell > 0:
        return np.zeros((0, 2), np.int32), np.zeros(0)
    order = np.argsort(_morton(v), kind="stable").tolist()
    levels: list[dict[tuple[int, int], float]] = []
    spacing = 2.0 * ell
    extent = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    while spacing < extent:
        reach = LONG_RANGE_REACH * spacing
        near = np.full(n, False)
        samples: list[int] = []
        for i in order:  # greedy: a sample blocks the vertices within the spacing along the cloth
            if near[i]:
                continue
            samples.append(i)
            for j, _ in _bounded_dijkstra(i, spacing * 0.999, offl, nbl, wtl):
                near[j] = True
        if len(samples) < 2:
            break
        is_sample = np.zeros(n, bool)
        is_sample[samples] = True
        out: dict[tuple[int, int], float] = {}
        levels.append(out)
        for i in samples:
            for j, d in _bounded_dijkstra(i, reach, offl, nbl, wtl):
                if j > i and is_sample[j]:
                    key = (i, j)
                    if key not in out:
                        out[key] = d
        spacing *= 2.0
    merged: dict[tuple[int, int], float] = {}
    for level in levels[::-1]:  # coarsest first, as on grids
        for key, d in level.items():
            merged.setdefault(key, d)
    if not merged:
        return np.zeros((0, 2), np.int32), np.zeros(0)
    lk = np.array(list(merged.keys()), np.int32).reshape(-1, 2)
    return lk, np.array(list(merged.values()), np.float64)


def _bounded_dijkstra(src: int, limit: float, offl, nbl, wtl):
    """(vertex, graph distance) of every vertex within ``limit`` of ``src``."""
    dist = {src: 0.0}
    heap = [(0.0, src)]
    done = set()
    while heap:
        d, u = heapq.heappop(heap)
        if u in done:
            continue
        done.add(u)
        yield u, d
        for k in range(offl[u], offl[u + 1]):
            w = nbl[k]
            nd = d + wtl[k]
            if nd <= limit and nd < dist.get(w, np.inf):
                dist[w] = nd
                heapq.heappush(heap, (nd, w))


def _morton(x: np.ndarray) -> np.ndarray:
    """Morton (Z-order) codes of points on a 1024^3 grid over their bounding box: nearby codes
    are nearby points."""
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
