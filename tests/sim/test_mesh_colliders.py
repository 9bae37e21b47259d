"""Triangle-mesh colliders (issue 22): bad meshes refused with clear errors, the float64 pieces
(closest points, the grid, the inside metric), a cape kept out of a moving body mesh with nothing
behind it at any tick (the reference), the OpenCL solvers against the reference (a cloth's own
mesh with friction, a scene's, a re-pose, a fast thin plate), creases (the body's shoulders under a
10 mm cape, a groove narrower than twice the thickness), and a World without meshes building
nothing new."""

from __future__ import annotations

import numpy as np
import pytest

from drape.server.sim.bodymesh import body_mesh
from drape.server.sim.collision import penetration
from drape.server.sim.fabric import cook_grid
from drape.server.sim.meshes import (
    MESH_MAX_TRIANGLES,
    MESH_MAX_VERTICES,
    apply_pose,
    build_grid,
    closest_points,
    collision_mesh,
    depth_inside,
    pose_matrix,
)
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.opencl.meshes import SOURCE
from drape.server.sim.params import ClothParams, Features, LinkOptions, Material
from drape.server.sim.world import ReferenceWorld
from drape.server.tools import penetration as tool

DT = 1 / 60
N = 9
PINS = np.array([0, N - 1])
THICKNESS = 0.005


@pytest.fixture(scope="module")
def body():
    return body_mesh(0.06)  # a coarse body: the reference stays quick


def plate(size: float = 0.4):
    """A one-sided square in z = 0 facing +z, two triangles."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64) * size
    return collision_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def groove(gap: float = 0.008, depth: float = 0.04):
    """A closed 0.3 x 0.1 x 0.3 m block (top at y = 0.1) with a V-groove along z in its top, ``gap``
    wide at the top and ``depth`` deep: a crease narrower than twice a 5-10 mm thickness."""
    half, top = gap / 2, 0.1
    sec = np.array(
        [(-0.15, 0), (0, 0), (0.15, 0), (0.15, top), (half, top), (0, top - depth), (-half, top), (-0.15, top)]
    )
    m = len(sec)
    v = np.concatenate([np.c_[sec, np.full(m, -0.15)], np.c_[sec, np.full(m, 0.15)]])
    t = [[i, (i + 1) % m, m + (i + 1) % m] for i in range(m)] + [[i, m + (i + 1) % m, m + i] for i in range(m)]
    for poly in ([0, 1, 5, 6, 7], [1, 2, 3, 4, 5]):  # the section's two convex halves, the ends fanned
        for k in range(1, len(poly) - 1):
            t += [[m + poly[0], m + poly[k], m + poly[k + 1]], [poly[0], poly[k + 1], poly[k]]]
    return collision_mesh(v, np.array(t))


def directed_edges(mesh) -> np.ndarray:
    """Every triangle's three edges as (from, to) rows."""
    t = mesh.triangles
    return np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])


# --- checks ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "vertices, triangles, message",
    [
        (np.zeros((3, 3)), np.array([[0, 1, 2]]), "degenerate"),
        (np.eye(3), np.array([[0, 1, 3]]), "out of range"),
        (np.eye(3), np.array([[0, 1, -1]]), "out of range"),
        (np.eye(3), np.array([[0, 0, 1]]), "degenerate"),
        (np.eye(3), np.zeros((0, 3), int), "m >= 1"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), np.array([[0, 1, 2]]), "finite"),
        (np.zeros((MESH_MAX_VERTICES + 1, 3)), np.array([[0, 1, 2]]), "at most"),
        (np.eye(3), np.zeros((MESH_MAX_TRIANGLES + 1, 3), int), "at most"),
        (np.eye(3), np.array([[0.0, 1.0, 2.0]]), "integers"),
    ],
)
def test_bad_meshes_are_refused_with_clear_errors(vertices, triangles, message):
    with pytest.raises(ValueError, match=message):
        collision_mesh(vertices, triangles)


def test_the_body_has_5000_triangles_and_is_closed_outward():
    m = body_mesh()
    assert m.n_triangles >= 5000
    inside = depth_inside(np.array([[0, 1.3, 0], [0, 0.5, 0.0], [0, 1.3, 0.5], [0, 2.0, 0]]), m, pose_matrix())
    assert inside[0] > 0.1 and inside[1] == 0 and inside[2] == 0 and inside[3] == 0  # between the legs: outside


@pytest.mark.parametrize("mesh", [pytest.param(lambda: body_mesh(0.05), id="body"), pytest.param(groove, id="groove")])
def test_meshes_are_closed_and_consistently_oriented(mesh):
    """Every edge once in each direction: a closed skin whose triangles all face out. The body's
    triangles were turned by the distance's gradient at their centres, which turned 45 of 5,972
    inward at the armpits (the 10 mm crease case below: a vertex entered through their backs)."""
    e = directed_edges(mesh())
    assert len(np.unique(e, axis=0)) == len(e)
    assert len(np.unique(np.sort(e, axis=1), axis=0)) * 2 == len(e)


def test_closest_points_against_dense_sampling(rng):
    for _ in range(20):
        tri = rng.normal(size=(3, 3))
        p = rng.normal(size=(50, 3)) * 2
        q = closest_points(p[:, None], tri[0][None], (tri[1] - tri[0])[None], (tri[2] - tri[0])[None])[:, 0]
        u, v = np.meshgrid(np.linspace(0, 1, 200), np.linspace(0, 1, 200))
        keep = u + v <= 1
        samples = tri[0] + u[keep, None] * (tri[1] - tri[0]) + v[keep, None] * (tri[2] - tri[0])
        brute = np.linalg.norm(p[:, None] - samples[None], axis=-1).min(axis=1)
        exact = np.linalg.norm(p - q, axis=1)
        assert np.all(exact <= brute + 1e-9) and np.all(brute - exact < 0.02)


def test_the_grid_holds_every_triangle_near_a_point(body, rng):
    g = build_grid(body)
    tri = body.vertices[body.triangles]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    for p in rng.uniform(body.vertices.min(axis=0), body.vertices.max(axis=0), size=(200, 3)):
        c = np.clip(np.floor((p - g.origin) / g.cell).astype(int), 0, g.dims - 1)
        cell = c[0] + g.dims[0] * (c[1] + g.dims[1] * c[2])
        held = set(g.tris[g.start[cell] : g.start[cell + 1]].tolist())
        assert set(np.nonzero(np.all((lo <= p) & (hi >= p), axis=1))[0].tolist()) <= held


def test_pose_rotation_and_inverse():
    p = pose_matrix((1, 2, 3), (np.cos(0.4), 0.3, np.sin(0.4), 0.1))
    x = np.array([[0.5, -1, 2.0]])
    from drape.server.sim.meshes import apply_pose, invert_pose

    assert np.allclose(apply_pose(invert_pose(p), apply_pose(p, x)), x)
    with pytest.raises(ValueError, match="quaternion"):
        pose_matrix(rotation=(0, 0, 0, 0))


# --- the scenario: a cape on a body walking back into it ----------------------------------------
def cape():
    return cook_grid(
        N, N, 0.5, 0.8, LinkOptions(bending=True), orientation="vertical", pinned=PINS, origin=(-0.25, 0.75, -0.2)
    )


def body_pose(t: int) -> np.ndarray:
    """Back 0.4 m in 20 ticks (1.2 m/s) into the cape, turning about y."""
    a = 0.02 * t
    return pose_matrix((0, 0, -min(0.4, (t + 1) * 0.02)), (np.cos(a), 0, np.sin(a), 0))


def walk(world, mesh, ticks: int = 30, with_mesh: bool = True, friction: float = 0.5):
    params = ClothParams(material=Material(thickness=THICKNESS, friction=friction), iterations=10, substeps=2)
    h = world.add(cape(), params)
    if with_mesh:
        world.set_mesh(h, mesh, body_pose(-1))
    out = []
    for t in range(ticks):
        if with_mesh:
            world.move_mesh(h, body_pose(t))
        world.step(DT)
        out.append(world.fetch().positions[h].astype(np.float64))
    return out


def behind(states, mesh) -> list[int]:
    invm = np.ones(N * N)
    invm[PINS] = 0
    return [penetration(x, x, 0.0, invm=invm, meshes=[(mesh, body_pose(t))]).behind for t, x in enumerate(states)]


def test_reference_keeps_the_cape_out_of_the_body(body, references):
    """0 vertices inside the body at every tick with the mesh (friction 0.5, and 0); without it the
    body walks through; friction changes how the cape slides on it."""
    with_friction = references("coloured")[0]
    assert max(behind(with_friction, body)) == 0
    frictionless = walk(ReferenceWorld(), body, friction=0.0)
    assert max(behind(frictionless, body)) == 0
    assert max(float(np.abs(a - b).max()) for a, b in zip(with_friction, frictionless, strict=True)) > 1e-3
    assert max(behind(walk(ReferenceWorld(), body, with_mesh=False), body)) > 10


# --- the device against the reference -----------------------------------------------------------
SOLVERS = [
    pytest.param(dict(solver="workgroup", pack_lanes=0), "coloured", id="wg_step"),
    pytest.param(dict(solver="workgroup"), "coloured", id="pack"),
    pytest.param(dict(solver="coloured"), "coloured", id="coloured"),
    pytest.param(dict(solver="jacobi"), "jacobi", id="jacobi"),
]


@pytest.fixture(scope="module")
def references(body):
    """The walk in the float64 reference and in float32, per reference mode (computed once)."""
    cache: dict[str, tuple[list, list]] = {}

    def get(mode: str) -> tuple[list, list]:
        if mode not in cache:
            cache[mode] = (walk(ReferenceWorld(mode), body), walk(ReferenceWorld(mode, np.float32), body))
        return cache[mode]

    return get


@pytest.mark.parametrize("kw, mode", SOLVERS)
def test_device_follows_the_reference(device, body, references, kw, mode):
    kw = dict(kw)
    solver = kw.pop("solver")
    ref, f32 = references(mode)
    dev = walk(CLWorld(solver, device=device, **kw), body)
    own = max(float(np.abs(a - b).max()) for a, b in zip(ref, f32, strict=True))
    err = max(float(np.abs(a - b).max()) for a, b in zip(ref, dev, strict=True))
    assert err < 3e-4 + 2 * own, (err, own)
    assert max(behind(dev, body)) == 0


def test_scene_mesh_and_repose_follow_the_reference(device, body):
    """Two cloths of a scene against the scene's one mesh, re-posed (scaled up) half-way."""

    def run(world):
        params = ClothParams(material=Material(thickness=0.01), iterations=10, substeps=2)
        hs = [world.add(cape(), params, scene="s") for _ in range(2)]
        world.set_pin_targets(hs[1], PINS, cape().rest_positions[PINS] + [0, 0.05, -0.05])
        world.set_scene_mesh("s", body, body_pose(-1))
        out = []
        for t in range(24):
            if t == 12:
                world.set_scene_mesh("s", body.reposed(body.vertices * 1.05), body_pose(t))
            else:
                world.move_scene_mesh("s", body_pose(t))
            world.step(DT)
            f = world.fetch()
            out.append(np.concatenate([f.positions[h] for h in hs]).astype(np.float64))
        return out

    ref, dev = run(ReferenceWorld()), run(CLWorld("workgroup", device=device, pack_lanes=0))
    err = max(float(np.abs(a - b).max()) for a, b in zip(ref, dev, strict=True))
    assert err < 1e-3


def test_a_fast_thin_plate_never_passes_through(device):
    """A one-sided plate (no thickness of its own) swept at 20 m/s through a hanging cloth, which
    ends in front of it at every tick, on the device as in the reference."""
    mesh = plate(2.0)  # wider than the cloth: nothing goes round it

    def run(world):
        f = cook_grid(
            N, N, 0.3, 0.3, LinkOptions(bending=True), orientation="vertical", pinned=PINS, origin=(-0.15, 0.85, 0)
        )
        h = world.add(f, ClothParams(material=Material(thickness=THICKNESS), iterations=10, substeps=2))
        pose = lambda t: pose_matrix((0, 1.0, -0.3 + 20 * DT * (t + 1)))  # noqa: E731
        world.set_mesh(h, mesh, pose(-1))
        zs = []
        for t in range(12):
            world.move_mesh(h, pose(t))
            world.step(DT)
            x = world.fetch().positions[h]
            free = np.ones(N * N, bool)
            free[PINS] = False
            zs.append(float((x[free, 2] - pose(t)[2, 3]).min()))
        return zs

    for world in (ReferenceWorld(), CLWorld("workgroup", device=device, pack_lanes=0)):
        assert min(run(world)) > THICKNESS - 1e-4


def test_the_shoulder_crease_under_a_10mm_cape(device):
    """The crease case found over the wire, on the World: a 9 x 9 cape, 10 mm thick, dropped onto
    the head and shoulders of the 5,972-triangle body (0.3 m down, turned a quarter) slides down
    into the armpit crease; before the fix one vertex went 10-25 mm inside from tick 113 on."""
    body = body_mesh(0.05)
    pose = pose_matrix((0.0, -0.3, 0.0), (np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0))
    world = CLWorld("workgroup", device=device, pack_lanes=0)
    f = cook_grid(N, N, 0.6, 0.6, LinkOptions(), origin=(-0.3, 1.65, -0.3))
    h = world.add(f, ClothParams(material=Material(thickness=0.01, friction=0.3), substeps=2))
    world.set_mesh(h, body, pose)
    got = []
    for _ in range(130):
        world.step(DT)
        x = world.fetch().positions[h].astype(np.float64)
        got.append(penetration(x, x, 0.0, meshes=[(body, pose)]).behind)
    assert max(got) == 0, [(t, n) for t, n in enumerate(got) if n]
    assert x[:, 1].min() < 1.1  # it reached the armpits


@pytest.mark.parametrize("thickness", [0.01, 0.005])
def test_a_groove_narrower_than_twice_the_thickness(device, thickness):
    """A cloth dropped 0.3 m onto a block with an 8 mm wide V-groove, one column of vertices falling
    into it: a push of the thickness away from one wall would go through the other (9 vertices
    inside before the guard, in the reference as on the device); 0 at every tick, both worlds."""
    mesh = groove()

    def run(world):
        f = cook_grid(N, N, 0.2, 0.2, LinkOptions(bending=True), origin=(-0.099, 0.4 + thickness, -0.1))
        h = world.add(f, ClothParams(material=Material(thickness=thickness, friction=0.3), substeps=2))
        world.set_mesh(h, mesh)
        out = []
        for _ in range(30):
            world.step(DT)
            x = world.fetch().positions[h].astype(np.float64)
            out.append(penetration(x, x, 0.0, meshes=[(mesh, pose_matrix())]).behind)
        return out, x

    for world in (ReferenceWorld(), CLWorld("workgroup", device=device, pack_lanes=0)):
        got, x = run(world)
        assert max(got) == 0, (type(world).__name__, [(t, n) for t, n in enumerate(got) if n])
        assert x[4::N, 1].max() < 0.1 + thickness  # the column over the groove is in the crease


def test_no_mesh_builds_nothing(device):
    """A World without meshes builds no mesh program and its solvers' build options are those of
    Features alone (cloth.cl unchanged)."""
    world = CLWorld("workgroup", device=device, pack_lanes=0)
    h = world.add(cape(), ClothParams(features=Features(colliders=True)))
    for _ in range(2):
        world.step(DT)
    world.sync()
    assert world.mesh_collision.n_attachments == 0 and world.mesh_collision._kernels is None
    options = world.launches.options_for(world.cloths[h].params.features, False, 0)
    assert not any("MESH" in o or "MC_" in o for o in options)
    group = world.rec[h].group
    world.set_mesh(h, plate())
    world.step(DT)
    assert world.rec[h].group == group  # the same launch group: the same solver program
    assert world.mesh_collision._kernels is not None and any(key[0] == SOURCE for key in device._programs)
    assert world.launches.options_for(world.cloths[h].params.features, False, 0) == options
    world.set_mesh(h, None)
    world.step(DT)
    assert world.mesh_collision.n_attachments == 0


def test_penetration_scenario_cape_on_a_running_body(device):
    """The penetration tool's cape_body (small): 0 vertices inside the body at every tick of the
    run and the turn; without the mesh the cape swings into it."""
    records = tool.run("cape_body", CLWorld("workgroup", device=device, pack_lanes=0), 9, ticks=150)
    assert max(r.behind for r in records) == 0 and max(r.crossed for r in records) == 0
    world = CLWorld("workgroup", device=device, pack_lanes=0)
    world.set_mesh = world.move_mesh = lambda *a, **k: None  # type: ignore[method-assign]
    assert max(r.behind for r in tool.run("cape_body", world, 9, ticks=150)) > 0


def test_a_mesh_set_onto_an_overlapping_cape_puts_its_deep_vertices_out(device, body):
    """The body set (then re-posed) right through a hanging cape: the vertices deeper inside than
    the thickness come out in the mesh's first step, on the device as in the reference; the
    vertices far outside do not move."""
    inside_pose = pose_matrix((0, 0, -0.2))
    invm = np.ones(N * N)
    invm[PINS] = 0

    def run(world, with_mesh=True):
        params = ClothParams(material=Material(thickness=THICKNESS), iterations=10, substeps=2)
        h = world.add(cape(), params)
        world.step(DT)
        before = world.fetch().positions[h].astype(np.float64)
        if not with_mesh:
            world.step(DT)
            return before, [world.fetch().positions[h].astype(np.float64)]
        world.set_mesh(h, body, inside_pose)
        out = []
        for t in range(3):
            if t == 2:  # re-posed (the same triangles) onto the cape again, 5 % larger
                world.set_mesh(h, body.reposed(body.vertices * 1.05), inside_pose)
            world.step(DT)
            out.append(world.fetch().positions[h].astype(np.float64))
        return before, out

    (before, ref), (_, dev) = run(ReferenceWorld()), run(CLWorld("workgroup", device=device, pack_lanes=0))
    deep = depth_inside(before, body, inside_pose) > THICKNESS
    assert deep.sum() > 5  # the scene: a cape through the body
    for states in (ref, dev):
        for x in states:
            assert penetration(x, x, 0.0, invm=invm, meshes=[(body, inside_pose)]).behind == 0
    err = max(float(np.abs(a - b).max()) for a, b in zip(ref, dev, strict=True))
    assert err < 1e-3, err
    # outside and clear of the surface (the body's nearest vertex further than 5 cm): as without it
    free = run(ReferenceWorld(), with_mesh=False)[1][0]
    gap = np.linalg.norm(before[:, None] - apply_pose(inside_pose, body.vertices)[None], axis=-1).min(axis=1)
    far = (gap > 0.05) & ~(depth_inside(before, body, inside_pose) > 0)
    assert far.sum() > 5
    assert np.abs(ref[0][far] - free[far]).max() < 1e-9
