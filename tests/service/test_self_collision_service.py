"""Self-collision end to end (protocol 1.6): a client asks for it over Zenoh on loopback with the
feature and the material's thickness, and the states it receives of a cloth folding onto itself
leave nothing inside the thickness; the same cloth without the feature passes through itself."""

from __future__ import annotations

import pytest
from conftest import collect, connect, make_config

from drape.server.service.server import Server
from drape.server.sim.collision import penetration

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

N = 17
THICKNESS = 0.01


@pytest.fixture(scope="module")
def server():
    with Server(make_config()) as srv:
        yield srv


def test_a_folding_cloth_keeps_its_thickness_over_the_wire(server):
    c = connect(server)
    try:
        opts = dict(
            pinned=[(N // 2) * N + col for col in range(N)],  # hung by its middle row: the halves swing together
            links={"bending": True},
            material={"thickness": THICKNESS, "contact_stiffness": 1.0},
            substeps=2,
        )
        on = c.submit_grid(N, N, 0.5, 0.5, origin=(0, 1, 0), features=["self_collision"], **opts)
        off = c.submit_grid(N, N, 0.5, 0.5, origin=(0, 1, 0), **opts)
        assert on.rest_positions is not None
        rest = on.rest_positions
        pen_on = [penetration(s.positions, rest, THICKNESS).pairs for s in collect(on, 45)]
        pen_off = [penetration(s.positions, rest, THICKNESS).pairs for s in collect(off, 45)]
        assert pen_on == [0] * len(pen_on)
        assert max(pen_off) > 0
    finally:
        c.close()
