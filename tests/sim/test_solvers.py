"""OpenCL solvers against the float64 CPU reference, and the solver invariants."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import random_grid_fabric, random_mesh_fabric

from drape.server.sim import reference
from drape.server.sim.fabric import cook_grid, cook_mesh, grid_mesh
from drape.server.sim.opencl.buffers import RangeAllocator
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.opencl.launch import pack_lanes
from drape.server.sim.params import ClothParams, Features, LinkOptions, Material, Sphere, pack_colliders
from drape.server.sim.world import ReferenceWorld, inverse_masses

pytestmark = pytest.mark.opencl  # not unit (tests/conftest.py)

GS_SOLVERS = ["workgroup", "coloured"]
DT = 1 / 60


def random_params(rng, features=Features()) -> ClothParams:
    return ClothParams(
        material=Material(
            mass=float(rng.uniform(0.2, 3.0)),
            stiffness=tuple(float(s) for s in rng.uniform(0.3, 1.0, 3)),
            compliance=tuple(float(c) for c in 10.0 ** rng.uniform(-8, -4, 3)),
            damping=float(rng.uniform(0, 0.05)),
        ),
        features=features,
        gravity=(float(rng.normal(0, 1)), float(rng.uniform(-15, -5)), float(rng.normal(0, 1))),
        iterations=int(rng.integers(1, 12)),
        substeps=int(rng.integers(1, 4)),
    )


def random_state(rng, fabric, scale=0.05):
    return fabric.rest_positions + rng.normal(0, scale, fabric.rest_positions.shape)


def run_pair(world, ref, fabric, params, positions, steps):
    h = world.add(fabric, params, positions)
    hr = ref.add(fabric, params, positions)
    for _ in range(steps):
        world.step(DT)
        ref.step(DT)
    return world.positions(h), ref.positions(hr)


def tol(ref_pos, steps):
    scale = max(1.0, float(np.abs(ref_pos).max()))
    return 2e-5 * scale * steps


# The float32 ensemble that measures a run's float32 sensitivity (as test_features's, for a plain
# run from given positions): the float32 reference from the start and from ENSEMBLE - 1 copies of
# it moved by at most one float32 ulp per coordinate; the device may stray F32_SPREAD x as far as
# the farthest of them.
ENSEMBLE = 8
F32_SPREAD = 2.0


def float32_sensitivity(fab, params, positions, steps: int, ref, mode: str = "coloured") -> float:
    """How far float32 rounding alone carries this run from the float64 reference's end positions
    ``ref``: the largest distance of ENSEMBLE float32 reference runs (fixed seed: the same ensemble
    every run). It comes from the reference, never from the device under test."""
    ulp_rng = np.random.default_rng(0)
    p32 = np.asarray(positions, np.float32)
    sens = 0.0
    for k in range(ENSEMBLE):
        start = p32 if k == 0 else np.nextafter(p32, ulp_rng.choice([-np.inf, np.inf], p32.shape).astype(np.float32))
        world = ReferenceWorld(mode, np.float32)
        h = world.add(fab, params, start)
        for _ in range(steps):
            world.step(DT)
        sens = max(sens, float(np.abs(world.positions(h) - ref).max()))
    return sens


def assert_within_float32_reach(a, b, fab, params, positions, steps: int, mode: str = "coloured") -> None:
    """The device's end positions ``a`` within tol of the float64 reference's ``b``, or, where the
    run amplifies float32 rounding past that, within F32_SPREAD x its float32 sensitivity more."""
    assert np.all(np.isfinite(a))
    err = float(np.abs(a - b).max())
    if err <= tol(b, steps):
        return
    sens = float32_sensitivity(fab, params, positions, steps, b, mode)
    assert err <= tol(b, steps) + F32_SPREAD * sens, f"device {err:.3g} m from float64, float32 reference {sens:.3g} m"


@pytest.mark.parametrize("solver", GS_SOLVERS)
@pytest.mark.parametrize("xpbd", [False, True])
@pytest.mark.parametrize("local_size", [1, 64], ids=["serial", "parallel"])
def test_gauss_seidel_solvers_match_reference_in_colour_order(device, rng, solver, xpbd, local_size):
    """Within tol of the float64 reference, or of its float32 reach where the run amplifies
    rounding: a random state compresses links to a third of their rest length and a mesh may buckle
    either way (seed 4084327806, PBD: every device solver 9.6e-4 m from float64 against a tol of
    1.5e-4, the float32 reference 9.3e-4 m, the device 3e-5 m from it)."""
    for maker in (random_mesh_fabric, random_grid_fabric):
        fab = maker(rng)
        params = random_params(rng, Features(xpbd=xpbd))
        pos = random_state(rng, fab)
        steps = 5
        world = CLWorld(solver, device=device, local_size=local_size)
        a, b = run_pair(world, ReferenceWorld("coloured"), fab, params, pos, steps)
        assert_within_float32_reach(a, b, fab, params, pos, steps)


def test_workgroup_global_memory_path_matches_local(device, rng):
    fab = random_grid_fabric(rng)
    params = random_params(rng)
    pos = random_state(rng, fab)
    a, _ = run_pair(
        CLWorld("workgroup", device=device, use_local=True, local_size=64), ReferenceWorld(), fab, params, pos, 3
    )
    b, r = run_pair(
        CLWorld("workgroup", device=device, use_local=False, local_size=64), ReferenceWorld(), fab, params, pos, 3
    )
    np.testing.assert_allclose(a, r, atol=tol(r, 3), rtol=0)
    np.testing.assert_allclose(b, r, atol=tol(r, 3), rtol=0)


def test_cloth_too_big_for_local_memory_takes_the_global_path(device):
    w = CLWorld("workgroup", device=device)
    n = int(np.ceil(np.sqrt(device.info.local_mem / 16))) + 2  # more vertices than local memory holds
    big = cook_grid(n, n, pinned=[0, n - 1])
    small = cook_grid(8, 8, pinned=[0, 7])
    hb, hs = w.add(big, ClothParams(iterations=2)), w.add(small, ClothParams(iterations=2))
    assert not w.groups[w.rec[hb].group].use_local and w.groups[w.rec[hs].group].use_local
    ref = ReferenceWorld()
    rb, rs = ref.add(big, ClothParams(iterations=2)), ref.add(small, ClothParams(iterations=2))
    for _ in range(2):
        w.step(DT)
        ref.step(DT)
    np.testing.assert_allclose(w.positions(hb), ref.positions(rb), atol=1e-4)
    np.testing.assert_allclose(w.positions(hs), ref.positions(rs), atol=1e-4)


def test_serial_reference_equals_colour_batched_reference(rng):
    fab = random_mesh_fabric(rng)
    for xpbd in (False, True):
        params = random_params(rng, Features(xpbd=xpbd))
        pos = random_state(rng, fab)
        s1 = reference.ClothState.initial(fab, params, positions=pos)
        s2 = reference.ClothState.initial(fab, params, positions=pos)
        for _ in range(3):
            reference.step(s1, fab, params, DT, "serial")
            reference.step(s2, fab, params, DT, "coloured")
        np.testing.assert_allclose(s1.x, s2.x, atol=1e-12)


def test_jacobi_matches_its_reference_and_reaches_the_rest_shape(device, rng):
    fab = random_grid_fabric(rng, n_pins=0)
    params = ClothParams(gravity=(0.0, 0.0, 0.0), iterations=4, material=Material(damping=0.5))
    pos = random_state(rng, fab, 0.02)
    a, b = run_pair(CLWorld("jacobi", device=device, chunk=32), ReferenceWorld("jacobi"), fab, params, pos, 3)
    np.testing.assert_allclose(a, b, atol=tol(b, 3), rtol=0)
    # relaxed long enough, Jacobi and Gauss-Seidel reach the same shape: every link at rest length
    # (Jacobi gets there more slowly: it needs several times the iterations of Gauss-Seidel)
    for solver, iterations, bound in (("jacobi", 100, 2e-3), ("workgroup", 50, 2e-3)):
        w = CLWorld(solver, device=device, local_size=32)
        h = w.add(fab, params.with_(iterations=iterations), pos)
        strains = []
        for _ in range(3):
            for _ in range(40):
                w.step(DT)
            x = w.positions(h)
            lengths = np.linalg.norm(x[fab.links[:, 1]] - x[fab.links[:, 0]], axis=1)
            strains.append(float((np.abs(lengths - fab.rest_length) / fab.rest_length).max()))
        assert strains[-1] < bound, (solver, strains)
        assert strains[-1] <= strains[0] + 1e-6, (solver, strains)


@pytest.mark.parametrize("solver", ["workgroup", "coloured", "jacobi"])
def test_pinned_vertices_never_move_and_no_nan(device, rng, solver):
    fab = random_grid_fabric(rng, n_pins=3)
    w = CLWorld(solver, device=device)
    h = w.add(fab, random_params(rng))
    pins = np.flatnonzero(fab.pinned)
    for _ in range(30):
        w.step(DT)
    x = w.positions(h)
    assert np.all(np.isfinite(x))
    np.testing.assert_array_equal(x[pins], fab.rest_positions[pins].astype(np.float32))


@pytest.mark.parametrize("solver", GS_SOLVERS)
def test_link_solve_conserves_momentum(device, rng, solver):
    fab = random_mesh_fabric(rng, n_pins=0)
    params = ClothParams(gravity=(0.0, 0.0, 0.0), iterations=8, material=Material(mass=float(rng.uniform(0.5, 2))))
    w = CLWorld(solver, device=device)
    h = w.add(fab, params, random_state(rng, fab, 0.1))
    w.step(DT)
    m = 1.0 / inverse_masses(fab, params)
    # velocity after one step from rest = link corrections / h; total momentum stays zero
    frame_v = w.mem.vel.read(w.rec[h].vbase, fab.n_vertices)[:, :3]
    p = (m[:, None] * frame_v).sum(0)
    scale = (m[:, None] * np.abs(frame_v)).sum()
    assert scale > 1e-3  # the links did move things
    assert np.abs(p).max() < 1e-4 * scale


def test_add_and_remove_between_ticks_leaves_others_untouched(device, rng):
    fa, fb = random_grid_fabric(rng), random_mesh_fabric(rng)
    pa = random_params(rng)
    alone = CLWorld("workgroup", device=device)
    busy = CLWorld("workgroup", device=device)
    ha = alone.add(fa, pa)
    hb_a = busy.add(fa, pa)
    others = []
    for step in range(12):
        if step % 3 == 0:
            others.append(busy.add(fb, random_params(rng)))
        if step % 4 == 3:
            busy.remove(others.pop(0))
        alone.step(DT)
        busy.step(DT)
        np.testing.assert_array_equal(alone.positions(ha), busy.positions(hb_a))
    # holes left by removed cloths get reused
    assert busy.mem.vert.high_water <= fa.n_vertices + 4 * fb.n_vertices


def test_per_cloth_parameters_in_one_world(device):
    fab = cook_grid(6, 6, pinned=[0, 5])
    w = CLWorld("coloured", device=device)
    ref = ReferenceWorld()
    ps = [
        ClothParams(iterations=i, gravity=(0, g, 0), material=Material(stiffness=(s, s, s)))
        for i, g, s in [(2, -9.8, 1.0), (9, -3.0, 0.5), (5, -20.0, 0.8)]
    ]
    hs = [w.add(fab, p) for p in ps]
    rs = [ref.add(fab, p) for p in ps]
    for _ in range(10):
        w.step(DT)
        ref.step(DT)
    for h, r in zip(hs, rs, strict=True):
        np.testing.assert_allclose(w.positions(h), ref.positions(r), atol=2e-4)
    assert not np.allclose(w.positions(hs[0]), w.positions(hs[1]))


def test_many_cloths_in_one_launch_match_reference(device, rng):
    fabs = [random_grid_fabric(rng) for _ in range(3)]
    # small vertex chunks: the coloured strategy's vertex phases spread one cloth over work-groups
    w = {s: CLWorld(s, device=device, local_size=32, chunk=40) for s in GS_SOLVERS}
    ref = ReferenceWorld()
    handles = []
    for i in range(24):
        fab = fabs[i % 3]
        p = random_params(rng).with_(substeps=1)
        pos = random_state(rng, fab)
        handles.append(({s: w[s].add(fab, p, pos) for s in GS_SOLVERS}, ref.add(fab, p, pos)))
    for _ in range(3):
        for s in GS_SOLVERS:
            w[s].step(DT)
        ref.step(DT)
    frames = {s: w[s].fetch() for s in GS_SOLVERS}
    rf = ref.fetch()
    for hs, hr in handles:
        for s in GS_SOLVERS:
            np.testing.assert_allclose(frames[s].positions[hs[s]], rf.positions[hr], atol=tol(rf.positions[hr], 3))


def test_range_allocator_reuses_and_coalesces():
    a = RangeAllocator()
    a.grow(100)
    x, y, z = a.alloc(10), a.alloc(20), a.alloc(30)
    assert (x, y, z) == (0, 10, 30) and a.high_water == 60
    a.release(10, 20)
    assert a.alloc(15) == 10
    a.release(0, 10)
    a.release(10, 15)
    assert a.free[0] == [0, 30]
    a.release(30, 30)
    assert a.high_water == 0 and a.free == [[0, 100]]


def test_device_choice_respects_environment(monkeypatch):
    from drape.server.sim.opencl.device import choose_device

    monkeypatch.setenv("DRAPE_DEVICE", "cpu")
    import pyopencl as cl

    assert choose_device().type & cl.device_type.CPU
    with pytest.raises(RuntimeError, match="no OpenCL device matches"):
        choose_device("no-such-device-name")


def test_device_choice_by_index():
    """gpu:N / cpu:N pick the N-th device of that type (one server per GPU); past the last is an error
    that lists what there is."""
    import pyopencl as cl

    from drape.server.sim.opencl.device import choose_device

    cpus = [d for p in cl.get_platforms() for d in p.get_devices() if d.type & cl.device_type.CPU]
    assert choose_device("cpu:0").int_ptr == choose_device("cpu").int_ptr
    with pytest.raises(RuntimeError, match=f"there are {len(cpus)} OpenCL CPU device"):
        choose_device(f"cpu:{len(cpus)}")


def test_link_options_change_links():
    f = cook_grid(4, 4, options=LinkOptions(structural=True, shear=False, bending=False))
    assert f.n_links == 2 * 4 * 3


def test_chebyshev_jacobi_matches_reference_and_converges_faster(device, rng):
    fab = random_grid_fabric(rng, n_pins=2)
    base = ClothParams(iterations=30, material=Material(damping=0.1))
    pos = random_state(rng, fab, 0.02)
    cheb = base.with_(chebyshev_rho=0.95)
    a, b = run_pair(CLWorld("jacobi", device=device, chunk=32), ReferenceWorld("jacobi"), fab, cheb, pos, 3)
    np.testing.assert_allclose(a, b, atol=tol(b, 3) * 5, rtol=0)

    def residual(fabric, start, params):
        w = ReferenceWorld("jacobi")
        h = w.add(fabric, params.with_(gravity=(0.0, 0.0, 0.0)), start)
        w.step(DT)
        x = w.positions(h)
        lengths = np.linalg.norm(x[fabric.links[:, 1]] - x[fabric.links[:, 0]], axis=1)
        return float(np.abs(lengths - fabric.rest_length).sum())

    # One step of 30 iterations from a perturbed pose, on 15 random grids. rho must suit the mesh
    # (docs/benchmarks.md): 0.95 suits a grid whose longer side has 7 vertices or more; on smaller
    # ones plain Jacobi's error falls faster than rho assumes and the schedule overshoots (ratio
    # up to 1.056 on 3 x 5 .. 4 x 6 grids, seed 418293324). Over 900 such grids the residual ratio
    # (Chebyshev / plain) was at most 0.95 and its median over 15 at most 0.78.
    ratios = []
    for _ in range(15):
        long, short = int(rng.integers(7, 14)), int(rng.integers(3, 14))
        cols, rows = (long, short) if rng.random() < 0.5 else (short, long)
        f = cook_grid(
            cols,
            rows,
            rng.uniform(0.5, 2.0),
            rng.uniform(0.5, 2.0),
            LinkOptions(bending=True),
            rng.choice(cols * rows, 2, replace=False),
            orientation=str(rng.choice(["horizontal", "vertical"])),
        )
        p0 = random_state(rng, f, 0.02)
        ratios.append(residual(f, p0, cheb) / residual(f, p0, base))
    assert np.median(ratios) < 0.9, ratios
    assert max(ratios) < 1.0, ratios


@pytest.mark.parametrize("solver", ["workgroup", "reference"])
def test_frame_is_one_contiguous_array_with_ranges_and_held_frames_survive(device, rng, solver):
    w = CLWorld("workgroup", device=device) if solver == "workgroup" else ReferenceWorld()
    fabs = [random_grid_fabric(rng) for _ in range(3)]
    hs = [w.add(f, ClothParams(features=Features(normals=(i == 1)))) for i, f in enumerate(fabs)]
    w.step(1 / 60)
    f1 = w.fetch()
    n = sum(f.n_vertices for f in fabs)
    assert f1.xyz.shape == (n, 3) and f1.xyz.dtype == np.float32 and f1.xyz.flags.c_contiguous
    assert f1.handles.tolist() == hs and f1.offsets.tolist() == [0, *np.cumsum([f.n_vertices for f in fabs])]
    for h in hs:
        np.testing.assert_array_equal(f1.positions[h], f1.xyz[f1.rows(h)])
    assert list(f1.normals) == [hs[1]] and f1.normals[hs[1]].shape == (fabs[1].n_vertices, 3)
    assert len(f1.nonfinite()) == 0
    kept = f1.xyz.copy()
    f1.hold()
    for _ in range(4):  # more fetches than there are unheld buffers
        w.step(1 / 60)
        f2 = w.fetch()
    np.testing.assert_array_equal(f1.xyz, kept)  # a held frame is never overwritten
    assert not np.array_equal(f2.xyz, kept)
    f1.release()
    assert w.layout() is f2.layout  # unchanged until cloths change
    w.reset(hs[2], np.full((fabs[2].n_vertices, 3), np.nan))
    w.step(1 / 60)
    assert w.fetch().nonfinite().tolist() == [2]
    w.remove(hs[0])
    f3 = w.fetch()
    assert f3.handles.tolist() == hs[1:] and f3.layout is not f2.layout and len(f3.xyz) == n - fabs[0].n_vertices
    w.close()


# ---------------------------------------------------------------------------------------------
# The CPU pack solver (kernels/pack.cl): cloths of one fabric stepped together, one lane each


def test_pack_table_keeps_keys_apart_and_spreads_over_compute_units():
    keys = [("a",)] * 20 + [("b",)] * 3 + [("c",)] + [("d",)] * 40
    slots = list(range(100, 100 + len(keys)))
    table = pack_lanes(keys, slots, 16, 2)
    assert table.shape[1] == 16 and table.dtype == np.int32
    used = table[table >= 0]
    assert sorted(used.tolist()) == slots  # every cloth in exactly one lane
    key_of = dict(zip(slots, keys, strict=True))
    sizes: dict[tuple, list[int]] = {}
    for row in table:
        members = row[row >= 0]
        assert np.all(row[len(members) :] == -1)  # lanes filled from the first, padded with -1
        assert len({key_of[int(m)] for m in members}) == 1  # one key (fabric, iterations, substeps)
        sizes.setdefault(key_of[int(members[0])], []).append(len(members))
    # 20 cloths: 2 packs of 10 (one per core), not 16 + 4; 40: 4 packs of 10, not 16 + 16 + 8
    assert sorted(sizes[("a",)]) == [10, 10] and sorted(sizes[("d",)]) == [10, 10, 10, 10]
    assert sorted(sizes[("b",)]) == [1, 2] and sizes[("c",)] == [1]
    assert pack_lanes([], [], 16, 2).shape == (0, 16)


def cpu_only(device):
    if device.info.is_gpu:
        pytest.skip("the pack solver runs on CPU devices only")


@pytest.mark.parametrize("lanes", [4, 16])
@pytest.mark.parametrize("xpbd", [False, True], ids=["pbd", "xpbd"])
def test_cpu_packs_of_cloths_with_their_own_parameters_match_reference(device, rng, lanes, xpbd):
    """21 cloths of two fabrics, each with its own material, mass, gravity and moving pins, in
    packs by (fabric, iterations, substeps): every lane equals the float64 reference and the
    one-cloth-per-work-item kernel (wg_step), and full and partly filled packs alike."""
    cpu_only(device)
    fabs = [random_grid_fabric(rng), random_mesh_fabric(rng)]
    packed = CLWorld("workgroup", device=device, pack_lanes=lanes)
    serial = CLWorld("workgroup", device=device, pack_lanes=0)
    assert serial.pack_lanes == 0 and packed.pack_lanes == lanes
    ref = ReferenceWorld("coloured")
    cloths = []
    for i in range(21):
        fab = fabs[i % 2]
        p = random_params(rng, Features(xpbd=xpbd)).with_(iterations=[4, 7][i % 3 == 0], substeps=1 + (i % 4 == 0))
        pos = random_state(rng, fab)
        cloths.append((fab, packed.add(fab, p, pos), serial.add(fab, p, pos), ref.add(fab, p, pos)))
    (g,) = packed.groups.values()
    steps = 5
    for step in range(steps):
        for fab, hp, hs, hr in cloths[::3]:  # some pins move every step
            pins = np.flatnonzero(fab.pinned)
            t = fab.rest_positions[pins] + 0.01 * (step + 1)
            for w, h in ((packed, hp), (serial, hs), (ref, hr)):
                w.set_pin_targets(h, pins, t)
        for w in (packed, serial, ref):
            w.step(DT)
    assert g.pack == lanes and g.n_packs >= 8  # 2 fabrics x 4 (iterations, substeps), lanes apart
    fp, fs, fr = packed.fetch(), serial.fetch(), ref.fetch()
    for _, hp, hs, hr in cloths:
        a, b = fp.positions[hp], fr.positions[hr]
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, atol=tol(b, steps), rtol=0)
        np.testing.assert_allclose(a, fs.positions[hs], atol=tol(b, steps), rtol=0)


def test_cpu_packs_carry_every_feature_per_cloth(device, rng):
    """Tethers, a collider, wind and normals differ per cloth of one pack: each lane as wg_step."""
    cpu_only(device)
    fab = cook_grid(9, 7, 1.0, 0.8, LinkOptions(bending=True), pinned=[0, 8], origin=(0, 1, 0))
    feats = Features(xpbd=True, tethers=True, colliders=True, wind=True, normals=True)
    packed = CLWorld("workgroup", device=device)
    serial = CLWorld("workgroup", device=device, pack_lanes=0)
    pairs = []
    for i in range(6):
        mat = Material(tether_limit=1.02 + 0.02 * i, friction=0.1 * i, drag=0.5 + 0.2 * i, lift=0.1 * i)
        p = ClothParams(material=mat, features=feats, wind=(1.0 + i, 0.0, 0.5 * i), iterations=6)
        sphere = pack_colliders([Sphere((0.5, 0.7 - 0.03 * i, 0.4), 0.25)])
        hp, hs = packed.add(fab, p), serial.add(fab, p)
        packed.set_colliders(hp, sphere)
        serial.set_colliders(hs, sphere)
        pairs.append((hp, hs))
    assert [g.pack for g in packed.groups.values()] == [packed.pack_lanes]
    for _ in range(10):
        packed.step(DT)
        serial.step(DT)
    fp, fs = packed.fetch(), serial.fetch()
    for hp, hs in pairs:
        assert np.all(np.isfinite(fp.positions[hp])) and np.all(np.isfinite(fp.normals[hp]))
        np.testing.assert_allclose(fp.positions[hp], fs.positions[hs], atol=1e-4, rtol=0)
        np.testing.assert_allclose(fp.normals[hp], fs.normals[hs], atol=1e-3, rtol=0)
    assert not np.allclose(fp.positions[pairs[0][0]], fp.positions[pairs[-1][0]])  # lanes differ


def test_bigger_cloths_take_fewer_lanes_and_the_biggest_the_work_group_kernel(device):
    cpu_only(device)
    w = CLWorld("workgroup", device=device)
    lanes = w.pack_lanes
    assert lanes > 2  # the default on a CPU
    # n x n vertices: 16 bytes a vertex a lane; `mid` fits half the lanes, `big` not even 2
    mid = int(np.ceil(np.sqrt(device.info.local_mem / (16 * lanes)))) + 1
    big = int(np.ceil(np.sqrt(device.info.local_mem / (16 * 2)))) + 1
    fabs = [cook_grid(n, n, pinned=[0, n - 1]) for n in (8, mid, big)]
    p = ClothParams(iterations=2)
    hs = [w.add(f, p) for f in fabs]
    packs = [w.groups[w.rec[h].group].pack for h in hs]
    assert packs == [lanes, lanes // 2, 0]
    assert w.groups[w.rec[hs[2]].group].use_local  # the biggest still fits wg_step's local memory
    assert CLWorld("workgroup", device=device, local_size=64).pack_lanes == 0  # a parallel work-group
    assert CLWorld("coloured", device=device).pack_lanes == 0
    ref = ReferenceWorld()
    rs = [ref.add(f, p) for f in fabs]
    for _ in range(2):
        w.step(DT)
        ref.step(DT)
    for h, r in zip(hs, rs, strict=True):
        np.testing.assert_allclose(w.positions(h), ref.positions(r), atol=1e-4)


def test_a_pack_group_of_unlike_cloths_fits_local_memory(device):
    """An XPBD pack holds its positions and then its multipliers in local memory: a group of one
    cloth with the most vertices and another with the most links launches in the memory of the
    larger pack, not the sum of the two maxima (which here is more than the device has)."""
    cpu_only(device)
    budget = device.info.local_mem - 1024
    na = int(np.sqrt(budget / 48)) - 1  # structural only: ~24 n^2 bytes a lane, 2 lanes
    nb = int(np.sqrt(budget / 80)) - 1  # with shear and bending: ~40 n^2 bytes a lane, 2 lanes
    fa = cook_grid(na, na, pinned=[0, na - 1], options=LinkOptions(shear=False))
    fb = cook_grid(nb, nb, pinned=[0, nb - 1], options=LinkOptions(bending=True))
    assert 2 * (16 * fa.n_vertices + 4 * fb.n_links) > budget
    p = ClothParams(features=Features(xpbd=True), iterations=1)
    w, serial = CLWorld("workgroup", device=device), CLWorld("workgroup", device=device, pack_lanes=0)
    hs = [(w.add(f, p), serial.add(f, p)) for f in (fa, fb)]
    assert w.rec[hs[0][0]].group == w.rec[hs[1][0]].group and w.groups[w.rec[hs[0][0]].group].pack == 2
    for _ in range(2):
        w.step(DT)
        serial.step(DT)
    for h, hs_ in hs:
        np.testing.assert_allclose(w.positions(h), serial.positions(hs_), atol=1e-5)


def test_a_gpu_build_never_gets_the_pack_kernel():
    """Packs are chosen by device type: a device that says it is a GPU gets the work-group
    solver's own groups and build options whatever pack_lanes asks (the H100's build is the one
    before the pack solver: features, USE_LOCAL, JACOBI_OMEGA, LINK_UNROLL)."""
    from dataclasses import replace

    from drape.server.sim.opencl.device import Device
    from drape.server.sim.opencl.launch import LINK_UNROLL_LOCAL
    from drape.server.sim.shared import JACOBI_OMEGA

    dev = Device(None)
    dev.info = replace(dev.info, is_gpu=True, is_nvidia=False)
    w = CLWorld("workgroup", device=dev, pack_lanes=16)
    h = w.add(cook_grid(8, 8, pinned=[0, 7]), ClothParams())
    g = w.groups[w.rec[h].group]
    assert w.pack_lanes == 0 and g.pack == 0 and g.use_local
    opts = w.launches.options(g)
    assert opts == [
        *Features().build_options(),
        "-DUSE_LOCAL=1",
        f"-DJACOBI_OMEGA={JACOBI_OMEGA}f",
        f"-DLINK_UNROLL={LINK_UNROLL_LOCAL}",
    ]
    assert not any("PACK" in o or "denorms" in o for o in opts)


@pytest.mark.parametrize(
    "solver", ["workgroup-parallel-local", "workgroup-parallel-global", "pack", "workgroup-serial"]
)
@pytest.mark.parametrize("compliance", [0.0, 1e-6], ids=["stiff", "compliant"])
@pytest.mark.parametrize("iterations", [1, 3])
def test_long_range_attachments_match_reference(device, rng, solver, compliance, iterations):
    """Tethers to every pin island (before and after the links) and the long-range links (by
    colour, before the links of each iteration) in wg_step with 64 work-items (its colour
    barriers: the GPU's path), on one work-item, and in the CPU pack solver (its vector phases
    where no multiplier is kept: compliance 0 or one iteration), against the float64 reference;
    random grids and meshes with 3 pins (islands)."""
    kw = {
        "workgroup-parallel-local": dict(local_size=64, use_local=True),
        "workgroup-parallel-global": dict(local_size=64, use_local=False),
        "workgroup-serial": dict(pack_lanes=0),
        "pack": {},
    }[solver]
    if solver in ("pack", "workgroup-serial"):
        cpu_only(device)
    for mesh in (False, True):
        cols, rows = (int(x) for x in rng.integers(7, 15, 2))
        pins = rng.choice(cols * rows, 3, replace=False)
        if mesh:  # a jittered grid as a triangle mesh: its long-range links walk its edges
            v, t = grid_mesh(cols, rows, 1.0, 1.0)
            fab = cook_mesh(v + rng.normal(0, 0.01, v.shape), t, pinned=pins)
        else:
            fab = cook_grid(cols, rows, 1.0, 1.0, pinned=pins)
        assert len(fab.long_range()[0]) > 0
        params = random_params(rng, Features(xpbd=True, tethers=True)).with_(iterations=iterations)
        params = params.with_(
            material=replace(params.material, compliance=(compliance,) * 3, tether_limit=float(rng.uniform(1.0, 1.1)))
        )
        pos = random_state(rng, fab, 0.1)
        steps = 5
        world = CLWorld("workgroup", device=device, **kw)
        a, b = run_pair(world, ReferenceWorld("coloured"), fab, params, pos, steps)
        if solver == "pack":
            assert [g.pack for g in world.groups.values()] == [world.pack_lanes]
        # the unilateral limits switch on and off at a threshold, where float32 rounding alone
        # may tip a vertex over: the float32 reference shows how far that carries this run
        assert_within_float32_reach(a, b, fab, params, pos, steps)
        # and the attachments matter here: without them the same run ends elsewhere
        c = run_pair(
            ReferenceWorld("coloured"),
            ReferenceWorld("coloured"),
            fab,
            params.with_(features=Features(xpbd=True)),
            pos,
            steps,
        )[0]
        assert np.abs(c - b).max() > 10 * tol(b, steps)
