"""Scenes kept on one server by the SDK (PROTOCOL.md 5.3, 11.3): two real ``drape serve`` processes
on loopback; one client's cloths of a scene, submitted without ``server=``, all land on one server
while its cloths without a scene spread; a second client's cloths of that scene join it there; a
``kill -9`` of that server brings the whole scene to the survivor, founded again by its owner
(first its own cloths, then its members and colliders, then the member's cloths). Counted events
only."""

from __future__ import annotations

import os
import signal

import pytest

from drape.client import DrapeClient
from drape.client import protocol as P

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

SERVER_WAIT = 90.0  # a drape serve starting (OpenCL warm-up) on a loaded CI machine
EVENT_WAIT = 30.0
BALL = P.Sphere((5.0, 0.0, 0.0), 0.1)


def _up(client: DrapeClient, servers, svc) -> None:
    ids = {s.server_id for s in servers}
    assert svc.wait_until(lambda: set(client.live_servers()) == ids, SERVER_WAIT)
    assert svc.wait_until(lambda: all(client.placement.stats(s) for s in ids), SERVER_WAIT)


def test_a_scene_stays_on_one_server_while_other_cloths_spread(server_pair, svc):
    with DrapeClient([s.endpoint for s in server_pair], timeout=SERVER_WAIT) as client:
        _up(client, server_pair, svc)
        free = [client.submit_grid(4, 4, origin=(j, 1.0, 0.0), pinned=[0]) for j in range(6)]
        scene = [client.submit_grid(4, 4, origin=(j, 2.0, 0.0), pinned=[0], scene="a") for j in range(6)]
        assert len({h.server_id for h in free}) == 2, [h.server_id for h in free]
        assert len({h.server_id for h in scene}) == 1, [h.server_id for h in scene]
        assert client.scenes.owns("a")  # its first cloth founded it
        assert client.set_scene("a").cloths == 6  # to the scene's server without server=


def test_a_killed_scene_comes_back_on_one_server_under_its_owner(server_pair, svc):
    endpoints = [s.endpoint for s in server_pair]
    host = DrapeClient(endpoints, client_id=f"host-{os.getpid()}", timeout=SERVER_WAIT)
    guest = DrapeClient(endpoints, client_id=f"guest-{os.getpid()}", timeout=SERVER_WAIT)
    try:
        _up(host, server_pair, svc)
        _up(guest, server_pair, svc)
        mine = [host.submit_grid(4, 4, origin=(j, 1.0, 0.0), pinned=[0], scene="m") for j in range(2)]
        host.set_scene("m", colliders=[BALL], members=[guest.client_id])
        theirs = [guest.submit_grid(4, 4, origin=(j, 2.0, 0.0), pinned=[0], scene="m") for j in range(2)]
        both = mine + theirs
        where = {h.server_id for h in both}
        assert len(where) == 1, [h.server_id for h in both]  # the guest found the host's scene
        assert host.scenes.owns("m") and not guest.scenes.owns("m")
        for h in both:
            assert h.next_state(EVENT_WAIT) is not None

        dead = next(s for s in server_pair if s.server_id in where)
        alive = next(s for s in server_pair if s is not dead)
        os.killpg(dead.proc.pid, signal.SIGKILL)
        dead.proc.wait(30)
        assert svc.wait_until(lambda: all(h.server_id == alive.server_id and not h.lost for h in both), EVENT_WAIT), [
            (h.server_id, h.lost, h.closed, h.close_reason) for h in both
        ]
        events = host.failover_events + guest.failover_events
        assert len(events) == 4 and all(e.ok for e in events), events
        # the host founded it again: it owns it, with its members; the guest still may not move it
        with pytest.raises(P.Forbidden):
            guest.set_scene("m", colliders=[])
        rep = host.set_scene("m")
        assert rep.owner == host.client_id and rep.members == (guest.client_id,) and rep.cloths == 4
        # a host's cloth founded it again before any of the guest's came back
        assert min(e.done_ns for e in host.failover_events) < min(e.done_ns for e in guest.failover_events)
    finally:
        guest.close()
        host.close()
