"""Placement end to end (PROTOCOL.md 11.3): two real ``drape serve`` processes on loopback, each on
its own port; one SDK client with no ``server_id`` submitting 8 cloths spreads them over both by
their published load; a ``kill -9`` of one brings every cloth it held back on the other (failover
places through the same rule), and later submits go to the survivor; a server that refuses a
cloth sends it to the next one. Counted events only."""

from __future__ import annotations

import os
import signal
import time

import pytest
from conftest import PAIR_ARGS

from drape.client import DrapeClient
from drape.client import protocol as P
from drape.client.placement import spread
from drape.server.tools.procs import ServerProcess

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

SERVER_WAIT = 90.0  # a drape serve starting (OpenCL warm-up) on a loaded CI machine
EVENT_WAIT = 30.0
CLOTHS = 8


def test_cloths_spread_over_two_servers_and_come_back_after_a_kill(server_pair, svc):
    a, b = server_pair
    with DrapeClient([a.endpoint, b.endpoint], timeout=SERVER_WAIT, failover=True) as client:
        ids = {a.server_id, b.server_id}
        assert svc.wait_until(lambda: set(client.live_servers()) == ids, SERVER_WAIT)
        # both servers' first stats (they come every 0.25 s): the rule then sees both loads
        assert svc.wait_until(lambda: all(client.placement.stats(s) for s in ids), SERVER_WAIT)
        handles = [client.submit_grid(8, 8, 0.5, 0.5, origin=(j, 1.0, 0.0), pinned=[0, 7]) for j in range(CLOTHS)]
        on = {s: [h for h in handles if h.server_id == s] for s in ids}
        counts = [len(v) for v in on.values()]
        # equal cloths, equal servers: the rule alternates (4 / 4); at worst a stats publication
        # racing a reply shifts one cloth
        assert min(counts) >= CLOTHS // 2 - 1 and spread(counts) <= 0.25, counts
        for h in handles:
            assert h.next_state(EVENT_WAIT) is not None
        # the servers count them too
        assert svc.wait_until(
            lambda: all((client.placement.stats(s) or {}).get("cloths") == len(on[s]) for s in ids), EVENT_WAIT
        )

        victims = on[a.server_id]
        os.killpg(a.proc.pid, signal.SIGKILL)
        a.proc.wait(30)
        assert svc.wait_until(lambda: all(h.server_id == b.server_id and not h.lost for h in handles), EVENT_WAIT)
        events = client.failover_events
        assert sorted(id(e.handle) for e in events) == sorted(id(h) for h in victims)
        assert all(e.ok and e.new_server == b.server_id for e in events)
        t = time.monotonic()
        for h in handles:  # every cloth is served by b now
            st = h.next_state(EVENT_WAIT)
            while st.cloth != h.id:  # a state of its old incarnation still queued
                st = h.next_state(max(0.1, EVENT_WAIT - (time.monotonic() - t)))
        assert svc.wait_until(lambda: (client.placement.stats(b.server_id) or {}).get("cloths") == CLOTHS, EVENT_WAIT)
        late = client.submit_grid(4, 4, pinned=[0])
        assert late.server_id == b.server_id


def test_a_refusing_server_sends_the_cloth_to_the_next(svc):
    """A server at its limit answers ``limit_exceeded`` (as one past its tick budget answers
    ``overloaded``): the SDK places the cloth on the next server in the ranking instead of
    failing the submit; with every server refusing, the last refusal is raised."""
    full = ServerProcess((*PAIR_ARGS, "--max-cloths", "1"), server_id=f"pl-full-{os.getpid()}")
    room = ServerProcess((*PAIR_ARGS, "--max-cloths", "3"), server_id=f"pl-room-{os.getpid()}")
    try:
        with DrapeClient([full.endpoint, room.endpoint], timeout=SERVER_WAIT) as client:
            ids = {full.server_id, room.server_id}
            assert svc.wait_until(lambda: set(client.live_servers()) == ids, SERVER_WAIT)
            assert svc.wait_until(lambda: all(client.placement.stats(s) for s in ids), SERVER_WAIT)
            handles = [client.submit_grid(4, 4, pinned=[0]) for _ in range(4)]
            where = sorted(h.server_id for h in handles)
            assert where == sorted([full.server_id] + [room.server_id] * 3)
            with pytest.raises(P.LimitExceeded):
                client.submit_grid(4, 4, pinned=[0])
    finally:
        for s in (full, room):
            s.stop(grace=20.0)
