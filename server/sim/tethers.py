"""Long-range attachments, pure numpy and heaps: tethers and long-range links.

**Tethers** (Kim, Chentanez, Mueller 2012; NvCloth's geodesic tether cooker): each free vertex gets
one tether to every *pin island* (pinned vertices connected by links), up to ``TETHER_SLOTS``
islands, the nearest first. A tether's anchor is the island's pin nearest along the cloth and its
rest length the geodesic distance to it, so a vertex between two pinned corners is held by both
(the middle of a hanging cloth's top edge, which a tether to the nearest pin alone cannot hold).
With fewer islands than slots, the biggest islands are split into runs of neighbouring pins, one
tether to each run (a flag on its pole: the pole's top, middle and bottom hold its sag; measured
on the float64 reference at 1 x 5: flag 37.4 % / 2.68 % -> 51.2 % / 1.80 % max / mean, cape
53.1 % / 1.09 % -> 28.4 % / 0.84 %).

Geodesic distances run over the fabric's links with their rest lengths (a multi-label Dijkstra:
each vertex settles up to TETHER_SLOTS islands), made any-angle where the cloth is flat: a
vertex reached from u may take u's own predecessor p as its predecessor when the chord p -> v
stays within ``ANY_ANGLE_SAG`` of a link length of u (the chord lies on the cloth). On a flat
convex grid the result is the straight-line distance; around a hole or across a fold it follows
the cloth. Graph paths never come out shorter than the cloth's geodesic, so a tether never pulls
a vertex closer than its rest distance; the any-angle chord may cut a curved surface by at most
about that sag.

**Long-range links**: unilateral links (they only resist stretching) from every vertex to the
vertices LONG_RANGE_STRIDES (5 and 10) structural links away along each of its structural
links' directions, on grids and meshes alike (long_range_links). Like tethers they hold at most
``tether_limit`` times their rest length. Measured on the hanging 64 x 64 (float64 reference,
XPBD 1 iteration per substep + tethers, max / mean structural stretch over 2 s): the issue's
coarse hierarchy (the vertices at every 2nd..32nd row and column linked to their next, +16 %
links) 70.4 % / 1.96 % at 1 x 5 and 41 % / 1.09 % at 1 x 8; every vertex at strides 5 and 10
(+90 % links) 23.7 % / 1.08 % at 1 x 2 and 9.2 % / 0.34 % at 1 x 6. At 1 x 2: strides 4, 8:
29.1 % / 1.33 %; 6, 12: 35.6 % / 0.98 %; 4, 8, 16 (+134 %): 27.3 % / 0.90 %; 3, 6: 25.3 % /
1.66 %; the coarse hierarchy added to strides 5, 10 changed nothing (23.7 % / 1.09 %).
"""

from __future__ import annotations

import heapq

import numpy as np

TETHER_SLOTS = 4  # tethers per vertex: one per pin island, the nearest TETHER_SLOTS islands
ANY_ANGLE_SAG = 0.5  # a chord p -> v replaces p -> u -> v when u is within this many |uv| of it
LONG_RANGE_STRIDES = (5, 10)  # long-range links: every vertex to those 5 and 10 links away


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
    island = _split_islands(island, slots, off, nb)
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


def _split_islands(island: np.ndarray, slots: int, off: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """With fewer islands than tether slots, the biggest islands split into runs of neighbouring
    pins (breadth-first along the island from its lowest pin, cut into equal parts) until there
    are ``slots`` groups or every group is one pin: a vertex then has a tether to the nearest pin
    of each run (a flag pinned along its pole: to the pole's top, middle and bottom, which hold
    its sag, where one tether to the nearest pin holds only its reach)."""
    n_isl = int(island.max()) + 1 if (island >= 0).any() else 0
    if n_isl == 0 or n_isl >= slots:
        return island
    members = [np.flatnonzero(island == i) for i in range(n_isl)]
    # how many parts each island gets: one each, the spare slots to the biggest in turn
    parts = [1] * n_isl
    for _ in range(slots - n_isl):
        sizes = [len(m) / p if len(m) > p else 0 for m, p in zip(members, parts, strict=True)]
        best = int(np.argmax(sizes))
        if sizes[best] == 0:
            break
        parts[best] += 1
    out = np.full_like(island, -1)
    gid = 0
    for m, p in zip(members, parts, strict=True):
        in_isl = set(m.tolist())
        order = [int(m.min())]  # breadth-first along the island's own links
        seen = {order[0]}
        k = 0
        while k < len(order):
            u = order[k]
            k += 1
            for w in nb[off[u] : off[u + 1]].tolist():
                if w in in_isl and w not in seen:
                    seen.add(w)
                    order.append(w)
        for j, chunk in enumerate(np.array_split(np.array(order), p)):
            out[chunk] = gid + j
        gid += p
    return out


# ---------------------------------------------------------------------------------------------
# Long-range links


def long_range_links(
    v: np.ndarray, links: np.ndarray, rest: np.ndarray, strides: tuple[int, ...] = LONG_RANGE_STRIDES
) -> tuple[np.ndarray, np.ndarray]:
    """Long-range links: from every vertex, along each of its structural links, a walk that goes
    on as straight as the cloth allows (each step the neighbour best aligned with the first
    step's direction, at most 60 degrees off; ends at a border), linking the vertex to the
    vertices ``stride`` steps away, for each stride. On a grid they are the vertices ``stride``
    apart along every row and column; on a mesh the same along its edges' directions. Rest
    length: the walk's length (the cloth between the ends: never shorter than its geodesic, so a
    link never holds the cloth shorter than its rest shape). Finest stride first; a pair reached
    twice keeps its shorter walk. (links (M, 2) int32, rest length (M,) float64.)"""
    v = np.asarray(v, np.float64)
    n = len(v)
    links = np.asarray(links, np.int64).reshape(-1, 2)
    rest = np.asarray(rest, np.float64)
    if len(links) == 0 or not strides:
        return np.zeros((0, 2), np.int32), np.zeros(0)
    off, nb, wt = _adjacency(n, links, rest)
    deg = np.diff(off)
    width = int(deg.max())
    table = np.full((n, width), -1, np.int64)  # neighbours, padded with -1
    wtab = np.zeros((n, width))
    slot = np.arange(len(nb)) - np.repeat(off[:-1], deg)
    table[np.repeat(np.arange(n), deg), slot] = nb
    wtab[np.repeat(np.arange(n), deg), slot] = wt
    start = np.repeat(np.arange(n), deg)  # every directed link (start, first step)
    cur = nb.copy()
    length = wt.copy()
    d = v[cur] - v[start]
    d /= np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
    alive = np.ones(len(start), bool)
    found: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for step in range(2, max(strides) + 1):
        cand = table[cur]  # (W, width)
        ok = cand >= 0
        e = v[np.where(ok, cand, 0)] - v[cur][:, None, :]
        el = np.linalg.norm(e, axis=2)
        align = np.where(ok & (el > 0), np.einsum("wkc,wc->wk", e, d) / np.maximum(el, 1e-300), -2.0)
        k = np.argmax(align, axis=1)
        rows = np.arange(len(k))
        alive &= align[rows, k] > 0.5  # at most 60 degrees off the walk's direction
        length = length + np.where(alive, wtab[cur, k], 0.0)
        cur = np.where(alive, cand[rows, k], cur)
        if step in strides:
            sel = alive & (cur != start)
            found[step] = (start[sel], cur[sel], length[sel])
    pairs: dict[tuple[int, int], float] = {}
    for stride in sorted(strides):
        if stride not in found:
            continue
        a, b, ln = found[stride]
        for i, j, L in zip(a.tolist(), b.tolist(), ln.tolist(), strict=True):
            key = (i, j) if i < j else (j, i)
            if key not in pairs or L < pairs[key]:
                pairs[key] = L
    if not pairs:
        return np.zeros((0, 2), np.int32), np.zeros(0)
    return np.array(list(pairs.keys()), np.int32).reshape(-1, 2), np.array(list(pairs.values()), np.float64)


def morton(x: np.ndarray) -> np.ndarray:
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
