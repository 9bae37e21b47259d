"""Fabric cooking: link sets, colouring independence, degenerate input, sharing, OBJ parsing (the
protocol's), tethers to every pin island with geodesic rest lengths and long-range links (not
computed for cloths without tethers)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_grid_fabric, random_mesh_fabric

from drape.server.sim.fabric import (
    TETHER_SLOTS,
    bending_pairs,
    cook,
    cook_grid,
    cook_mesh,
    greedy_colour,
    grid_mesh,
    mesh_edges,
    parse_obj,
    vertex_masses,
)
from drape.server.sim.params import LINK_BENDING, LINK_SHEAR, LINK_STRUCTURAL, LinkOptions


def test_grid_link_counts_match_the_talk():
    f = cook_grid(150, 150, options=LinkOptions(structural=True, shear=True))
    assert f.n_links == 89_102  # the talk's "90,000 links"
    assert f.count(LINK_STRUCTURAL) == 2 * 150 * 149
    assert f.count(LINK_SHEAR) == 2 * 149 * 149
    g = cook_grid(32, 32, options=LinkOptions(bending=True))
    assert g.n_links == 5_826
    assert g.count(LINK_BENDING) == 2 * 32 * 30


def _assert_independent(f):
    for c in range(f.n_colours):
        batch = f.links[f.colour_offsets[c] : f.colour_offsets[c + 1]]
        ends = batch.ravel()
        assert len(np.unique(ends)) == len(ends), f"colour {c} has links sharing a vertex"


@pytest.mark.parametrize("maker", [random_mesh_fabric, random_grid_fabric])
def test_colouring_is_independent_on_random_meshes(rng, maker):
    for _ in range(5):
        f = maker(rng)
        _assert_independent(f)
        # every link kept, sorted by colour, colours contiguous
        assert f.colour_offsets[0] == 0 and f.colour_offsets[-1] == f.n_links
        assert np.all(np.diff(f.colour_offsets) > 0)


def test_greedy_colour_uses_lowest_free_colour(rng):
    n = 40
    links = rng.integers(0, n, size=(300, 2))
    links = links[links[:, 0] != links[:, 1]]
    col = greedy_colour(links.astype(np.int32), n)
    for i, (a, b) in enumerate(links):
        earlier = col[:i][(links[:i] == a).any(1) | (links[:i] == b).any(1)]
        assert col[i] not in earlier
        assert all(c in earlier for c in range(col[i]))


def test_mesh_links_and_bending_pairs():
    # two triangles sharing edge (1, 2): one bending link between 0 and 3
    t = np.array([[0, 1, 2], [2, 1, 3]])
    assert sorted(map(tuple, mesh_edges(t))) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]
    assert [tuple(p) for p in bending_pairs(t)] == [(0, 3)]
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    f = cook_mesh(v, t, LinkOptions(structural=True, shear=True, bending=True), pinned=[0])
    assert f.count(LINK_STRUCTURAL) == 5 and f.count(LINK_BENDING) == 1 and f.count(LINK_SHEAR) == 0
    assert f.pinned.tolist() == [True, False, False, False]
    np.testing.assert_allclose(sorted(f.rest_length), sorted([1, 1, np.sqrt(2), 1, 1, np.sqrt(2)]))


def test_duplicate_self_and_zero_length_links_are_handled():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [2, 0, 0.0]])  # vertices 1 and 2 coincide
    links = np.array([[0, 1], [1, 0], [1, 1], [1, 2], [2, 3], [0, 1]])
    types = np.zeros(len(links), np.int8)
    f = cook(v, np.zeros((0, 3), int), links, types)
    assert f.n_links == 3  # (0,1) once, (1,2) zero-length kept, (2,3)
    assert np.isclose(f.rest_length.min(), 0.0)
    assert np.all(np.isfinite(f.rest_length))


@pytest.mark.parametrize(
    "verts,tris,links,pins,match",
    [
        (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2)), [], "non-empty"),
        (np.array([[0, 0, np.nan]]), np.zeros((0, 3)), np.zeros((0, 2)), [], "finite"),
        (np.zeros((3, 3)), np.array([[0, 1, 5]]), np.zeros((0, 2)), [], "triangle index"),
        (np.zeros((3, 3)), np.array([[0, 1, 1]]), np.zeros((0, 2)), [], "repeated"),
        (np.zeros((3, 3)), np.zeros((0, 3)), np.array([[0, 3]]), [], "link index"),
        (np.zeros((3, 3)), np.zeros((0, 3)), np.zeros((0, 2)), [7], "pinned index"),
    ],
)
def test_malformed_input_is_rejected(verts, tris, links, pins, match):
    with pytest.raises(ValueError, match=match):
        cook(verts, tris, links, np.zeros(len(links), np.int8), pins)


def test_obj_loader_fan_triangulates_and_accepts_slashes_and_negative_indices():
    text = """
    # a quad and a triangle
    v 0 0 0
    v 1 0 0
    v 1 1 0
    v 0 1 0
    vt 0 0
    f 1/1/1 2/1/1 3/1/1 4/1/1
    v 2 0 0
    f -1 2 3
    """
    v, t = parse_obj(text)
    assert v.shape == (5, 3)
    assert t.tolist() == [[0, 1, 2], [0, 2, 3], [4, 1, 2]]


@pytest.mark.parametrize("face,line", [("f 1 2 9", 4), ("f 0 1 2", 4), ("f -4 1 2", 4), ("f 1 2", 4), ("f 1 2 x", 4)])
def test_obj_loader_refuses_references_outside_the_vertices(face, line):
    """One parser for client and server (the protocol's): a face naming a vertex that does not
    exist (0, past the end, or negative before the first) is refused with the line, never
    turned into a silent out-of-range or wrapped index."""
    with pytest.raises(ValueError, match=f"line {line}"):
        parse_obj(f"v 0 0 0\nv 1 0 0\nv 0 1 0\n{face}\n")


def test_tethers_on_a_flat_grid_are_straight_lines_to_the_nearest_pin_of_every_island():
    """Hanging 16 x 16, two corner pins: every free vertex has one tether to each corner (two
    islands), nearest first, rest length the straight distance (any-angle paths over a flat
    convex grid), to float rounding."""
    n = 16
    f = cook_grid(n, n, pinned=[0, n - 1])
    a, ln = f.tether_anchor, f.tether_length
    assert a.shape == (n * n, TETHER_SLOTS)
    assert (a[[0, n - 1]] == -1).all()
    free = np.flatnonzero(~f.pinned)
    assert set(map(tuple, np.sort(a[free, :2], axis=1).tolist())) == {(0, n - 1)}
    assert (a[free, 2:] == -1).all()
    v = f.rest_positions
    straight = np.linalg.norm(v[free, None, :] - v[a[free, :2]], axis=2)
    np.testing.assert_allclose(ln[free, :2], straight, rtol=1e-9)
    assert (ln[free, 0] <= ln[free, 1]).all()  # nearest island first


def test_a_pinned_edge_is_one_island_split_into_runs_one_tether_to_each():
    """The first row of 8 x 8 pinned: one island, with 3 slots spare split into 4 runs of 2
    neighbouring pins; every free vertex has a tether to the nearest pin of each run, the first
    straight up its column."""
    n = 8
    f = cook_grid(n, n, width=1, height=1, pinned=range(n))
    free = np.flatnonzero(~f.pinned)
    a, ln = f.tether_anchor[free], f.tether_length[free]
    assert (a >= 0).all()
    assert {tuple(sorted(r)) for r in (a // 2).tolist()} == {(0, 1, 2, 3)}  # one pin of each run
    np.testing.assert_array_equal(a[:, 0], free % n)  # the nearest: straight up the column
    np.testing.assert_allclose(ln[:, 0], (free // n) / (n - 1), rtol=1e-9)
    v = f.rest_positions
    np.testing.assert_allclose(ln, np.linalg.norm(v[free][:, None] - v[a], axis=2), rtol=1e-9)  # flat: straight


def test_tether_lengths_follow_the_cloth_around_a_gap():
    """A U-shaped mesh (a grid with a slot cut from its top edge down the middle): the tether
    from across the slot runs around its end, far longer than the straight line, never shorter
    than the graph allows."""
    n = 9
    v, t = grid_mesh(n, n, 1.0, 1.0)
    c = n // 2
    # the slot: every triangle touching column c in rows 0..5
    slot = (t % n == c) & (t // n <= 5)
    f = cook_mesh(v, t[~slot.any(axis=1)], pinned=[0])  # the top-left corner
    right = 2  # a vertex of the top row right of the slot
    vtx = c + right
    assert f.tether_anchor[vtx, 0] == 0
    straight = np.linalg.norm(v[vtx] - v[0])
    around = 2 * 5 / (n - 1)  # down the slot and back up at least
    assert f.tether_length[vtx, 0] > straight + 0.8 * around


def test_tethers_hold_up_to_four_islands_the_nearest_first():
    n = 10
    pins = [0, 9, 90, 99, 44]  # four corners and one in the middle: five islands
    f = cook_grid(n, n, pinned=pins)
    a = f.tether_anchor
    free = np.flatnonzero(~f.pinned)
    assert (a[free] >= 0).all()  # every slot used
    assert a[1, 0] == 0 and 99 not in a[1]  # next to a corner: the far corner is the 5th island, left out
    assert (np.diff(f.tether_length[free], axis=1) >= 0).all()


def test_long_range_links_of_a_grid_reach_5_and_10_along_rows_and_columns():
    """64 x 64: every vertex to the vertices 5 and 10 away along its row and its column, rest
    length the straight distance; no two links of a colour share a vertex, and within a colour
    they run forward (by first vertex)."""
    n = 64
    f = cook_grid(n, n, pinned=[0, n - 1])
    lk, rest, off = f.long_range()
    assert len(lk) == sum(2 * n * (n - s) for s in (5, 10)) == 14464
    lo, hi = lk.min(axis=1), lk.max(axis=1)
    dr, dc = hi // n - lo // n, hi % n - lo % n
    assert set(zip(dr.tolist(), dc.tolist(), strict=True)) == {(0, 5), (5, 0), (0, 10), (10, 0)}
    v = f.rest_positions
    np.testing.assert_allclose(rest, np.linalg.norm(v[hi] - v[lo], axis=1), rtol=1e-12)
    for c in range(len(off) - 1):
        e = lk[off[c] : off[c + 1]]
        assert len(np.unique(e.ravel())) == e.size
        assert (np.diff(e.min(axis=1)) > 0).all()


def test_long_range_links_of_a_mesh_are_no_shorter_than_the_cloth_between_their_ends(rng):
    """A jittered 12 x 12 mesh with triangles dropped, its vertices shuffled: long-range links
    exist, none shorter than the straight line between its ends (rest: the walk's length)."""
    v, t = grid_mesh(12, 12, 1.0, 1.0)
    v = v + rng.normal(0, 0.01, v.shape)
    t = t[rng.random(len(t)) > 0.1]
    perm = rng.permutation(len(v))
    inv = np.argsort(perm)
    f = cook_mesh(v[perm], inv[t], pinned=[0])
    lk, rest, off = f.long_range()
    assert len(lk) > 0 and off[-1] == len(lk)
    v = f.rest_positions
    assert (rest >= np.linalg.norm(v[lk[:, 1]] - v[lk[:, 0]], axis=1) - 1e-12).all()
    for c in range(len(off) - 1):
        e = lk[off[c] : off[c + 1]].ravel()
        assert len(np.unique(e)) == len(e)


def test_tethers_are_not_set_up_for_a_cloth_without_tethers():
    """256 x 256 with every other vertex pinned (32 768 pins): cooking without tethers does not
    look for anchors at all; asking later computes them."""
    f = cook_grid(256, 256, pinned=np.arange(0, 256 * 256, 2), tethers=False)
    assert not f.tethers_ready
    small = cook_grid(4, 4, pinned=[0], tethers=False)
    assert not small.tethers_ready
    assert small.tether_anchor[15, 0] == 0 and small.tethers_ready  # computed on first use
    assert cook_grid(4, 4, pinned=[0]).tethers_ready  # the default computes them while cooking


def test_tiny_cloths_cook():
    for cols, rows in [(1, 1), (2, 1), (3, 1), (1, 3)]:
        f = cook_grid(cols, rows, options=LinkOptions(bending=True))
        assert f.n_vertices == cols * rows
        m = vertex_masses(f, 1.0)
        assert np.isclose(m.sum(), 1.0) and np.all(m > 0)


def test_tethers_point_at_the_nearest_pin():
    f = cook_grid(5, 5, width=1, height=1, pinned=[0, 4])
    assert f.tether_anchor[0, 0] == -1 and f.tether_anchor[4, 0] == -1
    assert f.tether_anchor[1, 0] == 0 and f.tether_anchor[3, 0] == 4
    assert f.tether_anchor[1, 1] == 4 and f.tether_anchor[3, 1] == 0  # and to the other island
    assert np.isclose(f.tether_length[24, 0], 1.0)  # (4,4) to pin (0,4) is 1 m


def test_mass_follows_area_and_pins():
    f = cook_grid(3, 3, width=2, height=2, pinned=[0])
    m = vertex_masses(f, 1.0)
    assert np.isclose(m.sum(), 1.0)
    assert m[4] > m[0]  # the centre touches more triangles than a corner


def test_identical_fabrics_share_one_device_copy(device):
    """The CL world keeps one device copy per fabric content key (the service's cook step keeps
    one host fabric per request digest: tests/service)."""
    from drape.server.sim.opencl.clworld import CLWorld
    from drape.server.sim.params import ClothParams

    a, b = cook_grid(8, 8, pinned=[0, 7]), cook_grid(8, 8, pinned=[0, 7])
    c = cook_grid(8, 8, pinned=[0])
    assert a is not b and a.key == b.key and a.key != c.key
    w = CLWorld("workgroup", device=device)
    h1, h2, h3 = w.add(a, ClothParams()), w.add(b, ClothParams()), w.add(c, ClothParams())
    assert len(w.fabrics) == 2 and w.rec[h1].fabric is w.rec[h2].fabric  # one device copy
    w.remove(h1)
    assert len(w.fabrics) == 2
    w.remove(h2)
    assert len(w.fabrics) == 1
    w.remove(h3)
    assert len(w.fabrics) == 0


def test_sliver_triangles_never_give_a_vertex_a_mass_float32_cannot_invert():
    """A mesh with a sliver (area 1e-30 of the rest) and the least total mass the protocol
    accepts: every vertex mass and inverse mass is a normal, finite float32."""
    from drape.client.protocol import MIN_MASS

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1e-30, 0]], np.float64)
    f = cook_mesh(v, np.array([[0, 1, 2], [0, 3, 1]]))
    assert f.vertex_area[3] < 1e-29  # the sliver vertex
    for total in (MIN_MASS, 1.0, 1.0e6):
        m = vertex_masses(f, total).astype(np.float32)
        assert np.isclose(float(m.astype(np.float64).sum()), total, rtol=1e-5)
        assert (m >= np.finfo(np.float32).tiny).all() and np.isfinite(np.float32(1.0) / m).all()
