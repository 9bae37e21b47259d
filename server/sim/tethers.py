"""Tether anchors, pure numpy: each free vertex's nearest pinned vertex and its rest distance,
found in bounded memory (groups of neighbouring vertices in Morton order, each searching only
the pins that can be nearest, in blocks of a bounded number of (vertex, pin) pairs) whatever the
cloth's size and pin count. Fabric.tethers (fabric.py) computes them once, on demand."""

from __future__ import annotations

import numpy as np

TETHER_PAIRS_PER_CHUNK = 1 << 21  # (free vertex, pin) distances held at once by the tether set-up (~16 MB each array)
TETHER_GROUP = 256  # neighbouring free vertices that share one candidate-pin search


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
