"""Scene features: XPBD, tethers, pins, colliders, wind, normals, each on every solver."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_grid_fabric

from drape.server.sim import make_world
from drape.server.sim.fabric import cook_grid
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.params import Capsule, ClothParams, Features, LinkOptions, Material, Plane, Sphere, pack_colliders
from drape.server.sim.world import ReferenceWorld

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


# The float32 ensemble that measures a scene's float32 sensitivity (see compare_with_reference):
# the float32 reference from the rest pose and from ENSEMBLE - 1 copies of it moved by at most
# one float32 ulp per coordinate; the device may stray F32_SPREAD x as far as the farthest of them.
# Measured on all features (527 seeds x workgroup, jacobi, plane out of reach): wherever that
# farthest run is over 1e-5 m (34 cases) the device is at most 1.05x as far (normals: 1.01x), and
# likewise (0.98x, normals 1.0x) for the 4 of 400 x 30 cases over the plain bound with the plane
# in reach; 2 leaves the margin.
ENSEMBLE = 8
F32_SPREAD = 2.0


def run_scene(world, fab, params, colliders, steps: int = 10, positions=None):
    """Step one cloth (from ``positions``, default its rest pose) under three colliders that slide
    along x every step (a plane's normal tilts with them); returns its handle and the final frame."""
    h = world.add(fab, params, positions=positions)
    packed = pack_colliders(colliders)
    for step in range(steps):
        moved = packed + np.float32(0.02 * step) * np.array([1, 0, 0, 0], np.float32)
        moved[:, 1, 3] = packed[:, 1, 3]
        world.set_colliders(h, moved)
        world.step(DT)
    return h, world.fetch()


def feature_scene(rng, features):
    """A random grid (random size, pins, orientation), a random wind and three colliders under it:
    a sphere and a capsule, and a plane 5 cm below the cloth's lowest vertex, which it reaches
    within the 10 steps (0.4 m below, no vertex ever touched it and dropping it went unnoticed)."""
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
        Plane((0.0, 1.0, 0.0), float(lo[1] - 0.05)),
    ]
    return fab, params, colliders


def float32_sensitivity(fab, params, colliders, mode: str, ref, ref_n=None) -> tuple[float, float]:
    """How far float32 rounding alone carries this scene from the float64 reference ``ref``
    (positions; ``ref_n`` normals): the largest distance of ENSEMBLE float32 reference runs, the
    first from the rest pose, the others from it moved by -1, 0 or +1 ulp per coordinate (fixed
    seed: the same ensemble every run). NaN when a run is not finite."""
    ulp_rng = np.random.default_rng(0)
    x0 = fab.rest_positions.astype(np.float32)
    sens = sens_n = 0.0
    for k in range(ENSEMBLE):
        start = x0 if k == 0 else x0 + ulp_rng.integers(-1, 2, x0.shape) * np.spacing(np.abs(x0))
        h, f = run_scene(ReferenceWorld(mode, np.float32), fab, params, colliders, positions=start)
        x = f.positions[h].astype(np.float64)
        if not np.all(np.isfinite(x)):
            return float("nan"), float("nan")
        sens = max(sens, float(np.abs(x - ref).max()))
        if ref_n is not None:
            sens_n = max(sens_n, float(np.abs(f.normals[h].astype(np.float64) - ref_n).max()))
    return sens, sens_n


def compare_with_reference(device, rng, solver, features, local_size, always_ensemble: bool = False) -> dict:
    """Run one random scene on an OpenCL solver and on the float64 reference; return both
    (positions, and normals when asked), the plain tolerances (3e-4 m scaled by the cloth's extent;
    2e-3 on normals) and, where the device exceeds them (or ``always_ensemble``), the scene's
    float32 sensitivity and the tolerances widened by it.

    Why float32 sensitivity: the device computes in float32, so it differs from the float64 ground
    truth by float32 rounding amplified through the step. Usually that stays ~1e-6 m. But when the
    cloth folds onto itself over the sphere, a bending link can shrink to a millimetre (seed
    211990349 with the plane 0.4 m down, as this test had it: 1.5 mm against its 111 mm rest
    length) and the XPBD correction along its direction d / |d| turns a 1e-6 m rounding
    difference into 1e-4 m (condition ~ rest / |d|); elsewhere float32 runs split between two
    outcomes 2e-4 m apart (seed 1048), a branch taken one way or the other. The float32 reference
    -- the same algorithm in the same order, rounded to float32 -- diverges the same way: for seed
    211990349 the device was 6.4e-4 m from the float64 reference (plain bound 4.3e-4) and the
    ENSEMBLE float32 reference runs 1.7e-4 .. 2.2e-3 m; now seed 5038 on jacobi: device 4.4e-4 m
    (plain bound 3.0e-4), farthest float32 run 4.5e-4 m (normals: 4.2e-3 against 2e-3, 4.2e-3). So
    a device result beyond the plain tolerance still passes within F32_SPREAD x the farthest
    float32 reference run (float32_sensitivity). The sensitivity comes from the reference, never from the device under
    test, so a kernel that drops or changes a term still fails: without friction, lift or the
    colliders' interpolation over substeps, 7 to 10 of 10 seeds fail (the others never touch a
    collider)."""
    fab, params, colliders = feature_scene(rng, features)
    mode = {"jacobi": "jacobi", "coloured": "batches"}.get(solver, "coloured")
    h, fw = run_scene(CLWorld(solver, device=device, local_size=local_size, chunk=48), fab, params, colliders)
    r, fr = run_scene(ReferenceWorld(mode), fab, params, colliders)
    b = fr.positions[r].astype(np.float64)
    out = dict(device=fw.positions[h].astype(np.float64), ref=b, sens=0.0, sens_n=0.0)
    out["atol"] = out["plain_atol"] = 3e-4 * max(1.0, float(np.abs(b).max()))
    out["atol_n"] = out["plain_atol_n"] = 2e-3
    exceeded = not np.abs(out["device"] - b).max() <= out["atol"]
    if features.normals:
        out.update(device_n=fw.normals[h].astype(np.float64), ref_n=fr.normals[r].astype(np.float64))
        exceeded |= not np.abs(out["device_n"] - out["ref_n"]).max() <= out["atol_n"]
    if exceeded or always_ensemble:
        out["sens"], out["sens_n"] = float32_sensitivity(fab, params, colliders, mode, b, out.get("ref_n"))
        out["atol"] += F32_SPREAD * out["sens"]
        out["atol_n"] += F32_SPREAD * out["sens_n"]
    return out


@pytest.mark.parametrize("solver", OPENCL)
@pytest.mark.parametrize("features", FEATURE_SETS, ids=lambda f: "+".join(f.names()))
@pytest.mark.parametrize("local_size", [1, 64], ids=["serial", "parallel"])
def test_every_feature_on_every_solver_agrees_with_reference(device, rng, solver, features, local_size):
    """The device within float32 reach of the float64 reference (compare_with_reference)."""
    c = compare_with_reference(device, rng, solver, features, local_size)
    assert np.all(np.isfinite(c["device"]))
    assert np.isfinite(c["atol"]) and np.isfinite(c["atol_n"]), "the float32 reference is not finite"
    np.testing.assert_allclose(c["device"], c["ref"], atol=c["atol"], rtol=0)
    if features.normals:
        assert np.all(np.isfinite(c["device_n"]))
        np.testing.assert_allclose(c["device_n"], c["ref_n"], atol=c["atol_n"], rtol=0)


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
        if tethers:  # a tether to each pin island: both corners
            a, ln = fab.tether_anchor, fab.tether_length
            free = a >= 0
            vtx = np.nonzero(free)[0]
            ratio = np.linalg.norm(x[vtx] - x[a[free]], axis=1) / (ln[free] * 1.02)
            # one pass over a vertex's tethers, nearest first, last in the substep in every
            # solver: the last (the other corner) holds exactly, the first within a few %
            far = a[:, 1] >= 0
            d1 = np.linalg.norm(x[far] - x[a[far, 1]], axis=1)
            assert np.all(d1 <= ln[far, 1] * 1.02 * (1 + 1e-5) + 1e-6), (d1 / (ln[far, 1] * 1.02)).max()
            assert ratio.max() <= 1.05, ratio.max()  # measured: 1.04
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
        h = w.add(
            fab, ClothParams(features=Features(wind=True), wind=(0.0, 0.0, wind), material=Material(drag=1.0, lift=0.5))
        )
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
