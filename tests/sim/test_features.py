"""Scene features: XPBD, tethers, pins, colliders, wind, normals, each on every solver."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import random_grid_fabric

from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import Capsule, ClothParams, Features, LinkOptions, Material, Plane, Sphere, pack_colliders
from drape.server.sim.world import ReferenceWorld, make_world

DT = 1 / 60
OPENCL = ["workgroup", "coloured", "jacobi"]


def hanging(n: int, **kw):
    """1 m x 1 m, flat at 1 m, two corners of one edge pinned."""
    return cook_grid(n, n, 1.0, 1.0, pinned=[0, n - 1], origin=(0, 1, 0), **kw)


FEATURE_SETS = [
    Features(xpbd=True),
    Features(tethers=True),
    Features(colliders=True),
    Features(wind=True, normals=True),
    Features(xpbd=True, tethers=True, colliders=True, wind=True, normals=True),
]


@pytest.mark.parametrize("solver", OPENCL)
@pytest.mark.parametrize("features", FEATURE_SETS, ids=lambda f: "+".join(f.names()))
@pytest.mark.parametrize("local_size", [1, 64], ids=["serial", "parallel"])
def test_every_feature_on_every_solver_agrees_with_reference(device, rng, solver, features, local_size):
    fab = random_grid_fabric(rng, LinkOptions(bending=True), n_pins=2)
    params = ClothParams(
        features=features,
        material=Material(compliance=(1e-7, 1e-6, 1e-4), friction=0.3, drag=0.8, lift=0.4, tether_limit=1.05),
        wind=tuple(float(x) for x in rng.normal(0, 4, 3)),
        iterations=6,
        substeps=2,
    )
    lo, hi = fab.rest_positions.min(0), fab.rest_positions.max(0)
    centre = (lo + hi) / 2
    colliders = [
        Sphere(tuple(centre - [0, 0.3, 0]), 0.25),
        Capsule(tuple(centre + [-0.5, -0.6, 0]), tuple(centre + [0.5, -0.6, 0.1]), 0.1),
        Plane((0.0, 1.0, 0.0), float(lo[1] - 0.4)),
    ]
    w = CLWorld(solver, device=device, local_size=local_size, chunk=48)  # cloths span several chunks
    ref = ReferenceWorld("jacobi" if solver == "jacobi" else "coloured")
    h, r = w.add(fab, params), ref.add(fab, params)
    for step in range(10):
        moved = pack_colliders(colliders) + np.float32(0.02 * step) * np.array([1, 0, 0, 0], np.float32)
        moved[:, 1, 3] = pack_colliders(colliders)[:, 1, 3]
        w.set_colliders(h, moved)
        ref.set_colliders(r, moved)
        w.step(DT)
        ref.step(DT)
    fw, fr = w.fetch(), ref.fetch()
    a, b = fw.positions[h], fr.positions[r]
    assert np.all(np.isfinite(a))
    np.testing.assert_allclose(a, b, atol=3e-4 * max(1.0, np.abs(b).max()))
    if features.normals:
        np.testing.assert_allclose(fw.normals[h], fr.normals[r], atol=2e-3)


def steady_sag(solver: str, xpbd: bool, iterations: int, device, n: int = 16) -> float:
    fab = hanging(n)
    # a soft cloth either way: PBD stiffness 0.1 per iteration, or XPBD compliance 0.05 m/N
    mat = Material(stiffness=(0.1, 0.1, 0.1), compliance=(0.05, 0.05, 0.05), damping=0.05)
    params = ClothParams(material=mat, features=Features(xpbd=xpbd), iterations=iterations)
    w = make_world(solver, device=device) if solver != "reference" else make_world("reference")
    h = w.add(fab, params)
    for _ in range(300):
        w.step(DT)
    return float(1.0 - w.positions(h)[:, 1].mean())


def test_xpbd_sag_does_not_depend_on_iteration_count(device):
    pbd = [steady_sag("workgroup", False, it, device) for it in (10, 40)]
    xpbd = [steady_sag("workgroup", True, it, device) for it in (10, 40)]
    pbd_change = abs(pbd[0] - pbd[1]) / pbd[1]
    xpbd_change = abs(xpbd[0] - xpbd[1]) / xpbd[1]
    print(f"sag PBD 10/40 it: {pbd}, change {pbd_change:.3f}; XPBD: {xpbd}, change {xpbd_change:.3f}")
    assert pbd_change > 0.20  # PBD stiffness depends on the iteration count (measured ~0.47)
    assert xpbd_change < 0.05 * pbd_change  # XPBD does not (measured ~0.001)


def max_structural_strain(x, fab):
    s = fab.link_type == 0
    a, b = fab.links[s, 0], fab.links[s, 1]
    length = np.linalg.norm(x[b] - x[a], axis=1)
    return float((np.abs(length - fab.rest_length[s]) / fab.rest_length[s]).max())


@pytest.mark.parametrize("solver", OPENCL)
def test_tethers_bound_the_stretch(device, solver):
    fab = hanging(24)
    base = ClothParams(iterations=2, material=Material(tether_limit=1.02, damping=0.05))
    results = {}
    for tethers in (False, True):
        w = CLWorld(solver, device=device)
        h = w.add(fab, base.with_(features=Features(tethers=tethers)))
        for _ in range(300):  # 5 s: hanging at rest
            w.step(DT)
        x = w.positions(h)
        results[tethers] = max_structural_strain(x, fab)
        if tethers:
            free = fab.tether_anchor >= 0
            d = np.linalg.norm(x[free] - x[fab.tether_anchor[free]], axis=1)
            assert np.all(d <= fab.tether_length[free] * 1.02 * (1 + 1e-5) + 1e-6)
    # measured at 2 iterations: max strain 3.8 without tethers, 0.78 with them
    assert results[True] < 0.3 * results[False], results


@pytest.mark.parametrize("solver", OPENCL)
def test_pinned_vertices_follow_their_targets_exactly(device, solver, rng):
    fab = hanging(10)
    pins = np.flatnonzero(fab.pinned)
    w = CLWorld(solver, device=device)
    h = w.add(fab, ClothParams(substeps=3))
    for _ in range(5):
        tgt = fab.rest_positions[pins] + rng.normal(0, 0.3, (len(pins), 3))
        w.set_pin_targets(h, pins, tgt)
        w.step(DT)
        np.testing.assert_allclose(w.positions(h)[pins], tgt, atol=1e-6)
    with pytest.raises(ValueError, match="pinned"):
        w.set_pin_targets(h, [5], [[0, 0, 0]])


def _inside(x, collider) -> np.ndarray:
    if isinstance(collider, Plane):
        n = np.asarray(collider.normal) / np.linalg.norm(collider.normal)
        return x @ n - collider.offset < -1e-5
    if isinstance(collider, Sphere):
        return np.linalg.norm(x - collider.center, axis=1) < collider.radius * (1 - 1e-5)
    p0, p1 = np.asarray(collider.p0), np.asarray(collider.p1)
    ax = p1 - p0
    t = np.clip((x - p0) @ ax / (ax @ ax), 0, 1)
    return np.linalg.norm(x - (p0 + t[:, None] * ax), axis=1) < collider.radius * (1 - 1e-5)


@pytest.mark.parametrize("solver", OPENCL)
@pytest.mark.parametrize("kind", ["sphere", "capsule", "plane"])
def test_no_vertex_ends_inside_a_collider_even_a_fast_one(device, solver, kind):
    fab = hanging(20)
    w = CLWorld(solver, device=device)
    h = w.add(fab, ClothParams(features=Features(colliders=True), material=Material(friction=0.5), substeps=2))
    for step in range(40):
        # the collider sweeps up through the cloth at 30 m/s (0.5 m per step), then sits in it
        y = min(-1.0 + 0.5 * step, 0.9)
        if kind == "sphere":
            c = Sphere((0.5, y, 0.5), 0.3)
        elif kind == "capsule":
            c = Capsule((0.1, y, 0.5), (0.9, y, 0.4), 0.15)
        else:
            c = Plane((0.2, 1.0, 0.0), y)
        w.set_colliders(h, pack_colliders([c]))
        w.step(DT)
        x = w.positions(h)
        free = ~fab.pinned
        assert not np.any(_inside(x[free], c)), f"step {step}: vertices inside the {kind}"
        assert np.all(np.isfinite(x))


@pytest.mark.parametrize("solver", OPENCL)
def test_wind_pushes_the_cloth_downwind(device, solver):
    fab = cook_grid(12, 12, 1.0, 1.0, pinned=list(range(12)), orientation="vertical", origin=(0, 2, 0))
    xs = {}
    for wind in (0.0, 8.0):
        w = CLWorld(solver, device=device)
        h = w.add(fab, ClothParams(features=Features(wind=True), wind=(0.0, 0.0, wind),
                                   material=Material(drag=1.0, lift=0.5)))
        for _ in range(60):
            w.step(DT)
        xs[wind] = w.positions(h)[:, 2].mean()
    assert xs[8.0] > xs[0.0] + 0.05, xs


@pytest.mark.parametrize("solver", OPENCL)
def test_normals_are_unit_and_agree_with_triangles(device, solver, rng):
    fab = random_grid_fabric(rng)
    w = CLWorld(solver, device=device)
    h = w.add(fab, ClothParams(features=Features(normals=True)))
    for _ in range(10):
        w.step(DT)
    frame = w.fetch()
    x, n = frame.positions[h], frame.normals[h]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)
    t = fab.triangles
    fn = np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])
    for k in range(3):
        assert np.all(np.einsum("ij,ij->i", n[t[:, k]], fn) > 0)


def test_features_off_compile_to_the_bare_kernel(device):
    """A cloth without features builds with every FEATURE_* = 0; cloths with different
    feature sets still share one step (one launch per feature set)."""
    fab = hanging(8)
    w = CLWorld("workgroup", device=device)
    w.add(fab, ClothParams())
    w.add(fab, ClothParams(features=Features(wind=True)))
    w.add(fab, ClothParams())
    assert len(w.groups) == 2
    bare = next(g for g in w.groups.values() if not g.features.names())
    assert all(o.endswith("=0") for o in bare.features.build_options())
    w.step(DT)
