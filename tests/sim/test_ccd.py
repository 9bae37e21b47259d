"""No tunnelling (issue 22): spheres and capsules collide continuously along each vertex's motion
in a substep (kernels/colliders.cl, reference.collide), on every solver against the float64
reference, and the penetration scenarios (drape.server.tools.penetration, small sizes) leave
nothing behind a collider and nothing passed through one at the end of every tick."""

from __future__ import annotations

import numpy as np
import pytest

from drape.server.sim import reference
from drape.server.sim.fabric import cook_grid
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.params import CCD_SLOP, CCD_STEPS, Features, LinkOptions, Sphere, pack_colliders
from drape.server.sim.world import ReferenceWorld
from drape.server.tools import penetration as pen

OPENCL = ["workgroup", "coloured", "jacobi"]
SMALL = pen.SIZES["small"]


def test_ccd_options_come_with_colliders_only():
    """A cloth without colliders builds as before; colliders bring the continuous test's two
    options (always on with colliders: its cost is in docs/collision.md)."""
    assert not any("CCD" in o for o in Features(wind=True, tethers=True).build_options())
    on = Features(colliders=True).build_options()
    assert f"-DCCD_STEPS={CCD_STEPS}" in on and f"-DCCD_SLOP={CCD_SLOP!r}f" in on


def positions(world, name: str, ticks: int) -> np.ndarray:
    return np.stack([t.x[0].astype(np.float64) for t in pen.SCENARIOS[name](world, SMALL, ticks=ticks)])


@pytest.mark.parametrize("solver", OPENCL)
def test_capsule_at_10_m_s_follows_the_reference(device, solver):
    """The capsule crossing the cloth at 10 m/s (a substep's motion is its diameter): the device
    carries the cloth along with the float64 reference (the mode that mirrors each solver)."""
    mode = {"jacobi": "jacobi", "coloured": "batches"}.get(solver, "coloured")
    got = positions(CLWorld(solver, device=device), "capsule_hit", 4)
    ref = positions(ReferenceWorld(mode), "capsule_hit", 4)
    f32 = positions(ReferenceWorld(mode, np.float32), "capsule_hit", 4)
    atol = 1e-4 + 2 * float(np.abs(f32 - ref).max())  # measured on PoCL: 7e-7 (float32 alone: as much)
    np.testing.assert_allclose(got, ref, atol=atol, rtol=0)
    # and the cloth is carried: its middle rows are in front of the capsule (z beyond it)
    assert float(got[-1][:, 2].max()) > 0.25


def sphere_through(world, ticks: int = 4) -> np.ndarray:
    """A 12 cm sphere flying through the middle of a hanging 9 x 9 cloth at 10 m/s, at an angle."""
    fab = cook_grid(SMALL, SMALL, 0.5, 0.5, LinkOptions(bending=True), [0, SMALL - 1], "vertical", (-0.25, 1.0, 0.0))
    h = world.add(fab, pen.params(pen.BASE, 0.2))
    out = []
    for k in range(ticks + 1):
        c = np.array([0.02, 0.75 + 0.01 * k, -0.25]) + np.array([0.0, 0.0, 1.0]) * pen.CAPSULE_SPEED * pen.DT * k
        world.set_colliders(h, pack_colliders([Sphere(tuple(c), 0.12)]))
        if k:
            world.step(pen.DT)
            out.append(world.positions(h).astype(np.float64))
    return np.stack(out)


@pytest.mark.parametrize("solver", OPENCL)
def test_sphere_at_10_m_s_follows_the_reference(device, solver):
    mode = {"jacobi": "jacobi", "coloured": "batches"}.get(solver, "coloured")
    got = sphere_through(CLWorld(solver, device=device))
    ref = sphere_through(ReferenceWorld(mode))
    f32 = sphere_through(ReferenceWorld(mode, np.float32))
    np.testing.assert_allclose(got, ref, atol=1e-4 + 2 * float(np.abs(f32 - ref).max()), rtol=0)
    assert float(got[-1][:, 2].max()) > 0.2  # carried in front of the sphere


@pytest.mark.parametrize("name", list(pen.SCENARIOS))
@pytest.mark.parametrize("solver", [*OPENCL, "reference"])
def test_scenarios_leave_nothing_behind_a_collider(device, solver, name):
    """At the end of every tick: no vertex behind a collider's surface, none passed through one;
    the work-group solver and the reference also keep every pair of a cloth apart (the coloured
    and Jacobi solvers' self-collision is a launch of its own: there a pair may be left)."""
    world = ReferenceWorld() if solver == "reference" else CLWorld(solver, device=device)
    records = pen.run(name, world, SMALL)
    assert all(r.behind == 0 for r in records), [r for r in records if r.behind][:3]
    assert all(r.crossed == 0 for r in records), [r for r in records if r.crossed][:3]
    if solver in ("workgroup", "reference"):
        assert all(r.pairs == 0 for r in records), [r for r in records if r.pairs][:3]


def test_a_test_at_the_end_of_each_substep_alone_lets_the_capsule_through(monkeypatch):
    """Without the continuous test the same capsule passes through the cloth: the scenario and
    its ``crossed`` count see what the continuous test prevents."""
    monkeypatch.setattr(reference, "_continuous", lambda *a, **k: None)
    records = pen.run("capsule_hit", ReferenceWorld(), SMALL)
    assert max(r.crossed for r in records) > 0
