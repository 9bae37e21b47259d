"""Scenes end to end (protocol 1.7) over Zenoh on loopback: who may put a cloth into a scene and
move its colliders (the owner, the members it admits; PROTOCOL.md 5.3), and two clients' cloths in
one scene kept apart in the states they receive, where without the scene one falls through the
other."""

from __future__ import annotations

import pytest
from conftest import collect, connect, make_config

from drape.client import protocol as P
from drape.server.service.server import Server
from drape.server.sim.scenes import scene_penetration

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

N = 9
THICKNESS = 0.03
BALL = P.Sphere((5.0, 0.0, 0.0), 0.1)


@pytest.fixture(scope="module")
def server():
    with Server(make_config()) as srv:
        yield srv


def test_only_the_owner_moves_a_scene_and_admits_others(server):
    alice, bob = connect(server, client_id="alice"), connect(server, client_id="bob")
    try:
        alice.submit_grid(2, 2, scene="hall")  # founds the scene: alice owns it
        with pytest.raises(P.Forbidden):
            bob.submit_grid(2, 2, scene="hall")  # not a member yet
        with pytest.raises(P.Forbidden):
            bob.set_scene("hall", colliders=[BALL])  # a non-owner moves its collider: refused
        with pytest.raises(P.NotFound):
            alice.set_scene("no-such-scene", colliders=[BALL])
        rep = alice.set_scene("hall", colliders=[BALL], members=["bob"])
        assert rep.owner == "alice" and rep.members == ("bob",) and rep.cloths == 1 and rep.tick > 0
        bob.submit_grid(2, 2, scene="hall")  # a member now
        with pytest.raises(P.Forbidden):
            bob.set_scene("hall", colliders=[])  # still not the owner
        assert alice.set_scene("hall").cloths == 2  # a probe changes nothing
    finally:
        alice.close()
        bob.close()


def drop(server, scene: str | None) -> list[int]:
    """Bob's cloth dropped from 5 mm above the thickness onto alice's, held by its four corners; both in ``scene``
    (or in none): the pairs closer than the thickness at each tick both clients received."""
    alice, bob = connect(server, client_id=f"alice-{scene}"), connect(server, client_id=f"bob-{scene}")
    try:
        opts = dict(material={"thickness": THICKNESS}, substeps=2, scene=scene)
        a = alice.submit_grid(N, N, 0.25, 0.25, origin=(0, 1.0, 0), pinned=[0, N - 1, N * N - N, N * N - 1], **opts)
        if scene is not None:
            alice.set_scene(scene, members=[f"bob-{scene}"])
        b = bob.submit_grid(N, N, 0.25, 0.25, origin=(0, 1.035, 0), **opts)
        sa = {s.tick: s.positions for s in collect(a, 60)}
        sb = {s.tick: s.positions for s in collect(b, 40)}
        ticks = sorted(set(sa) & set(sb))
        assert len(ticks) >= 30
        return [scene_penetration([sa[t], sb[t]], [THICKNESS, THICKNESS]).pairs for t in ticks]
    finally:
        alice.close()
        bob.close()


def test_two_clients_cloths_collide_in_a_scene(server):
    """In one scene bob's cloth lands on alice's and stays 3 cm above it at every tick; without
    the scene it falls through."""
    got = drop(server, "yard")
    assert max(got) == 0, str(got)
    assert max(drop(server, None)) > 0
