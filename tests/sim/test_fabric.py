"""Fabric cooking: link sets, colouring independence, degenerate input, sharing, OBJ parsing (the
protocol's), tether anchors (exact, bounded in memory, not computed for cloths without tethers)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from conftest import random_grid_fabric, random_mesh_fabric

from drape.server.sim.fabric import (
    bending_pairs,
    cook,
    cook_grid,
    cook_mesh,
    greedy_colour,
    mesh_edges,
    parse_obj,
    tether_anchors,
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


def _nearest_pin_float64(v: np.ndarray, pinned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The definition, in float64: every (free vertex, pin) distance at once, first minimum."""
    anchor, length = np.full(len(v), -1, np.int32), np.zeros(len(v))
    pins, free = np.flatnonzero(pinned), np.flatnonzero(~pinned)
    if len(pins) and len(free):
        d = np.linalg.norm(v[free, None, :] - v[pins][None, :, :], axis=2)
        j = np.argmin(d, axis=1)
        anchor[free], length[free] = pins[j], d[np.arange(len(free)), j]
    return anchor, length


@pytest.mark.parametrize("chunk", [1, 7, 1 << 21])
def test_tether_anchors_are_the_nearest_pin_in_any_chunking(rng, chunk):
    for _ in range(10):
        f = random_grid_fabric(rng, n_pins=int(rng.integers(0, 10)))  # grids have at least 9 vertices
        v = np.asarray(f.rest_positions) + rng.normal(0, 1e-3, f.rest_positions.shape) * rng.integers(0, 2)
        v += rng.uniform(-1e3, 1e3, 3)  # far from the origin: the fast formula's rounding is largest
        anchor, length = tether_anchors(v, f.pinned, chunk)
        want_a, want_l = _nearest_pin_float64(v, f.pinned)
        np.testing.assert_array_equal(anchor, want_a)  # ties: the lowest pin index, as the definition
        np.testing.assert_array_equal(length, want_l)


def test_tethers_are_not_set_up_for_a_cloth_without_tethers():
    """256 x 256 with every other vertex pinned (32 768 pins): cooking without tethers does not
    look for anchors at all (it took 65 s and 9.6 GB when it did); asking later computes them."""
    f = cook_grid(256, 256, pinned=np.arange(0, 256 * 256, 2), tethers=False)
    assert not f.tethers_ready
    small = cook_grid(4, 4, pinned=[0], tethers=False)
    assert not small.tethers_ready
    assert small.tether_anchor[15] == 0 and small.tethers_ready  # computed on first use
    assert cook_grid(4, 4, pinned=[0]).tethers_ready  # the default computes them while cooking


def test_tether_set_up_memory_is_bounded_by_its_chunk():
    """2 048 free vertices x 2 048 pins: all pairs at once would hold 4 M distances (32 MB per
    array, 100 MB for the difference vectors); in chunks of 64 K pairs the set-up's peak stays
    near a few chunks, counted by tracemalloc (numpy reports its buffers to it)."""
    v = np.random.default_rng(0).uniform(-1, 1, (4096, 3))
    pinned = np.zeros(4096, bool)
    pinned[::2] = True
    chunk = 1 << 16
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        anchor, _ = tether_anchors(v, pinned, chunk)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 * chunk * 8, peak  # 8 MB: a handful of chunk-sized float64 arrays
    assert (anchor[~pinned] >= 0).all() and (anchor[pinned] == -1).all()


def test_tiny_cloths_cook():
    for cols, rows in [(1, 1), (2, 1), (3, 1), (1, 3)]:
        f = cook_grid(cols, rows, options=LinkOptions(bending=True))
        assert f.n_vertices == cols * rows
        m = vertex_masses(f, 1.0)
        assert np.isclose(m.sum(), 1.0) and np.all(m > 0)


def test_tethers_point_at_the_nearest_pin():
    f = cook_grid(5, 5, width=1, height=1, pinned=[0, 4])
    assert f.tether_anchor[0] == -1 and f.tether_anchor[4] == -1
    assert f.tether_anchor[1] == 0 and f.tether_anchor[3] == 4
    assert np.isclose(f.tether_length[24], 1.0)  # (4,4) to pin (0,4) is 1 m


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
