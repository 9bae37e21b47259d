"""Failover that loses nothing (protocol 1.3 ``resume``): the sim starts a resumed cloth from the
given positions and velocities on every back end; a server killed with SIGKILL has its cloths
resubmitted by the SDK to another live server under the same handles, continuing from their last
state; a client whose cloths were reclaimed while it was away gets them back when it returns.
Real Zenoh sessions on loopback, real ``drape serve`` processes, PoCL's CPU OpenCL."""
from __future__ import annotations

import numpy as np
import pytest

from drape.server.sim import make_world
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import ClothParams

DT = 1.0 / 60.0


@pytest.mark.parametrize("solver", ["reference", "workgroup", "coloured", "jacobi"])
def test_resumed_cloth_moves_by_its_velocity(solver, device, rng):
    """A free cloth (no pins) resumed with velocity v moves by v*dt + g*dt^2 in its first step
    (semi-implicit Euler: v += g dt, x += v dt); its links are at rest length, so the solver has
    nothing to correct. Checked against the float64 formula; NaN never passes."""
    fab = cook_grid(6, 5, 0.5, 0.4, pinned=[])
    params = ClothParams()
    x0 = fab.rest_positions + np.array([0.3, 1.0, -0.2])
    vel = rng.uniform(-2.0, 2.0, 3)
    velocities = np.broadcast_to(vel, x0.shape).copy()
    world = make_world(solver) if solver == "reference" else make_world(solver, device=device)
    h = world.add(fab, params, x0, velocities)
    world.step(DT)
    got = world.fetch().positions[h].astype(np.float64)
    g = np.asarray(params.gravity, np.float64)
    want = x0 + (vel + g * DT) * DT
    err = np.abs(got - want).max()
    assert np.isfinite(got).all() and err < 1e-4, f"{solver}: max error {err} m"
    # and the velocity was not ignored: a cloth resumed at rest ends elsewhere by |v| dt
    assert np.abs(got - (x0 + g * DT * DT)).max() > 0.5 * np.abs(vel).max() * DT


@pytest.mark.parametrize("solver", ["reference", "workgroup"])
def test_resumed_pinned_vertices_stay_put(solver, device):
    """Pinned vertices start where ``positions`` puts them, with their targets there and no velocity."""
    fab = cook_grid(4, 4, pinned=[0, 3])
    x0 = fab.rest_positions + np.array([1.0, 2.0, 3.0])
    world = make_world(solver) if solver == "reference" else make_world(solver, device=device)
    h = world.add(fab, ClothParams(), x0, np.full(x0.shape, 5.0))
    world.step(DT)
    got = world.fetch().positions[h]
    assert np.allclose(got[[0, 3]], x0[[0, 3]], atol=1e-5)


def test_staged_state_applies_to_its_params_only(device):
    """The service's cook thread stages a resumed cloth's state for the params object it made; the
    tick thread's add with exactly that object starts there, any other add from the rest pose."""
    fab = cook_grid(3, 3, pinned=[])
    world = make_world("reference")
    p1, p2 = ClothParams(), ClothParams()
    x0 = fab.rest_positions + 7.0
    world.stage_initial_state(p1, x0, np.zeros_like(x0))
    h2 = world.add(fab, p2)
    h1 = world.add(fab, p1)
    h3 = world.add(fab, p1)  # consumed once
    assert np.allclose(world.state(h1).x, x0)
    assert np.allclose(world.state(h2).x, fab.rest_positions) and np.allclose(world.state(h3).x, fab.rest_positions)
