"""The links of a cloth, pure numpy: structural, shear and bending pairs of a grid or a triangle
mesh, deduplicated (the stronger type wins), and their greedy colouring into independent batches
(no two links of one colour share a vertex), the order the solvers step them in. fabric.py cooks
them into a Fabric."""

from __future__ import annotations

import numpy as np

from .params import LINK_BENDING, LINK_SHEAR, LINK_STRUCTURAL, LinkOptions


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
