"""Self-collision (issue 22, protocol 1.6): the work-group solver against the float64 reference,
the penetration metric, a cloth folded onto itself, and the features-off build unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from drape.server.sim.collision import contact_pairs, penetration, self_collide
from drape.server.sim.fabric import cook_grid
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.params import Capsule, ClothParams, Features, LinkOptions, Material, Plane, Sphere, pack_colliders
from drape.server.sim.world import ReferenceWorld

DT = 1 / 60
N = 17  # vertices a side of the folding cloth: 0.5 m, 31 mm between neighbours
THICKNESS = 0.01
# the build options of every kernel of protocol 1.5 for a cloth without features (before 1.6)
TODAYS_BARE_OPTIONS = [
    "-DFEATURE_XPBD=0",
    "-DFEATURE_TETHERS=0",
    "-DFEATURE_COLLIDERS=0",
    "-DFEATURE_WIND=0",
    "-DFEATURE_NORMALS=0",
]


def folding_cloth():
    """A 0.5 m cloth held flat at 1 m by its middle row of pins: both halves swing down and
    through each other beneath it (13 ticks of contact without self-collision)."""
    return cook_grid(
        N, N, 0.5, 0.5, LinkOptions(bending=True), pinned=[(N // 2) * N + c for c in range(N)], origin=(0, 1, 0)
    )


def draped_cloth():
    """The same cloth dropped from 2 cm over a thin bar (a 1 cm capsule under its middle)."""
    fab = cook_grid(N, N, 0.5, 0.5, LinkOptions(bending=True), origin=(-0.25, 1.02, -0.25))
    return fab, pack_colliders([Capsule((-0.5, 1.0, 0.0), (0.5, 1.0, 0.0), 0.01)])


def fold_params(self_collision: bool, colliders: bool = False) -> ClothParams:
    return ClothParams(
        features=Features(self_collision=self_collision, colliders=colliders),
        material=Material(thickness=THICKNESS, friction=1.0),
        iterations=10,
        substeps=2,
    )


def run(world, fab, params, ticks: int, colliders=None):
    """Each tick's positions (float64) of one cloth stepped ``ticks`` times."""
    h = world.add(fab, params)
    if colliders is not None:
        world.set_colliders(h, colliders)
    out = []
    for _ in range(ticks):
        world.step(DT)
        out.append(world.fetch().positions[h].astype(np.float64))
    return out


def test_features_off_build_todays_options(device):
    """A cloth without self-collision builds the kernel of protocol 1.5 with its very options
    (the same program and program-cache entry); the feature adds its own two options only."""
    assert Features().build_options() == TODAYS_BARE_OPTIONS
    assert Features(wind=True).build_options() == [o.replace("WIND=0", "WIND=1") for o in TODAYS_BARE_OPTIONS]
    on = Features(self_collision=True).build_options()
    assert on[:5] == TODAYS_BARE_OPTIONS and on[5] == "-DFEATURE_SELF_COLLISION=1"
    w = CLWorld("workgroup", device=device, pack_lanes=0)
    w.add(folding_cloth(), ClothParams())
    w.add(folding_cloth(), fold_params(True))
    bare = next(g for g in w.groups.values() if not g.features.names())
    assert w.launches.options(bare)[:5] == TODAYS_BARE_OPTIONS
    assert not any("SELF_COLLISION" in o for o in w.launches.options(bare))


@pytest.mark.parametrize(
    ("solver", "options"),
    [
        ("workgroup", {}),  # on a CPU: the pack solver (16 lanes, one used)
        ("workgroup", {"pack_lanes": 0}),  # wg_step, one work-item
        ("workgroup", {"local_size": 32, "use_local": True}),
        ("workgroup", {"local_size": 32, "use_local": False}),
        ("coloured", {}),
        ("coloured", {"local_size": 32}),
        ("jacobi", {}),
    ],
    ids=lambda v: v if isinstance(v, str) else ",".join(f"{k}={x}" for k, x in v.items()) or "default",
)
def test_opencl_matches_reference(device, solver, options):
    """The device's self-collision against the float64 reference's (the mode that mirrors the
    solver), through the halves' contact (work-group solver: the CPU's packs, local and global
    memory; one and many work-items): within 3e-4 m plus twice the float32 reference's own
    distance from the float64 one (contact amplifies rounding)."""
    fab, params = folding_cloth(), fold_params(True)
    ticks = 30
    mode = {"jacobi": "jacobi", "coloured": "batches"}.get(solver, "coloured")
    world = CLWorld(solver, device=device, **options)
    dev = run(world, fab, params, ticks)
    ref = run(ReferenceWorld(mode), fab, params, ticks)
    f32 = run(ReferenceWorld(mode, dtype=np.float32), fab, params, ticks)
    for t in range(ticks):
        spread = float(np.abs(f32[t] - ref[t]).max())
        assert np.abs(dev[t] - ref[t]).max() <= 3e-4 + 2 * spread, t
    # and the contact happened: without the feature the states part by more than the thickness
    off = run(ReferenceWorld(mode), fab, fold_params(False), ticks)
    assert max(float(np.abs(a - b).max()) for a, b in zip(off, ref, strict=True)) > THICKNESS


@pytest.mark.parametrize("solver", ["reference", "workgroup", "coloured", "jacobi"])
def test_folded_cloth_leaves_no_penetration(device, solver):
    """The cloth folded onto itself: the metric is 0 at the end of every tick with self-collision
    and > 0 (the halves pass through each other) without."""
    fab = folding_cloth()
    for on in (False, True):
        world = ReferenceWorld() if solver == "reference" else CLWorld(solver, device=device)
        counts = [penetration(x, fab.rest_positions, THICKNESS).pairs for x in run(world, fab, fold_params(on), 45)]
        if on:
            assert counts == [0] * len(counts)
        else:
            assert max(counts) > 0


def test_draped_cloth_leaves_no_penetration(device):
    """A cloth dropped over a thin bar: its halves swing under the bar and meet; with
    self-collision nothing is left inside the thickness or inside the bar at any tick."""
    fab, bar = draped_cloth()
    for on in (False, True):
        states = run(CLWorld("workgroup", device=device), fab, fold_params(on, colliders=True), 60, bar)
        pens = [penetration(x, fab.rest_positions, THICKNESS, bar) for x in states]
        assert all(p.behind == 0 for p in pens)
        if on:
            assert all(p.total == 0 for p in pens)
        else:
            assert max(p.pairs for p in pens) > 0


def test_rest_neighbours_never_collide():
    """Vertices within the thickness at rest are the cloth's own neighbourhood: a flat cloth at
    rest whose thickness is 1.5 x its spacing does not move."""
    fab = cook_grid(9, 9, 0.4, 0.4)  # 5 cm spacing
    x = fab.rest_positions.copy()
    invm = np.ones(len(x))
    assert len(contact_pairs(x, fab.rest_positions, 0.075)[0]) == 0
    self_collide(x, invm, fab.rest_positions, 0.075, 1.0)
    np.testing.assert_array_equal(x, fab.rest_positions)


def test_self_collide_pushes_a_pair_apart_by_inverse_mass():
    """Two vertices far apart at rest, 2 mm apart now: one pass at stiffness 1 leaves them at the
    thickness, each moved by its inverse-mass share; a pinned one does not move; coincident
    vertices part along their rest direction."""
    rest = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    x = np.array([[0.0, 0, 0], [0.002, 0, 0]])
    self_collide(x, np.array([1.0, 3.0]), rest, 0.01, 1.0, passes=1)
    assert np.linalg.norm(x[1] - x[0]) == pytest.approx(0.01)
    np.testing.assert_allclose(x[0], [-0.002, 0, 0], atol=1e-12)
    x = np.array([[0.0, 0, 0], [0.002, 0, 0]])
    self_collide(x, np.array([0.0, 1.0]), rest, 0.01, 0.5, passes=1)
    np.testing.assert_allclose(x, [[0, 0, 0], [0.006, 0, 0]], atol=1e-12)
    x = np.zeros((2, 3))
    self_collide(x, np.ones(2), rest, 0.01, 1.0, passes=1)
    np.testing.assert_allclose(x, [[-0.005, 0, 0], [0.005, 0, 0]], atol=1e-12)


def test_penetration_metric():
    """Pairs closer than thickness - tolerance that are further apart at rest, once each; free
    vertices deeper than the tolerance inside a sphere, a capsule or behind a plane."""
    rest = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.005, 0, 0], [2.0, 0, 0]])
    x = np.array([[0.0, 0, 0], [0.004, 0, 0], [0.005, 0, 0], [2.0, 0, 0]])
    p = penetration(x, rest, 0.01)
    assert p.pairs == 2  # (0, 1) and (1, 2); (0, 2) are neighbours at rest
    assert p.deepest_pair == pytest.approx(0.009)
    assert penetration(x, rest, 0.01, tolerance=0.0095).pairs == 0
    assert penetration(x, rest, 0.0).total == 0
    colliders = pack_colliders(
        [Sphere((0.0, 0.0, 0.0), 0.003), Capsule((2.0, -1.0, 0.0), (2.0, 1.0, 0.0), 0.1), Plane((0, 1, 0), 0.5)]
    )
    p = penetration(rest, rest, 0.0, colliders)
    assert p.behind == 4 and p.deepest_behind == pytest.approx(0.5)
    p = penetration(rest, rest, 0.0, colliders[:2], invm=np.array([0.0, 1, 1, 1]))
    assert p.behind == 1 and p.deepest_behind == pytest.approx(0.1)
