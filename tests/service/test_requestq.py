"""The bounded request queue (server/service/requests/requestq.py) in a real Server over real Zenoh.

The request thread is held deterministically: the test wraps the server's ``on_info`` handler
before start so that the first info request waits on an event. Everything is counted: which
queries were queued, which were answered ``busy`` at once (without decoding: their payloads are
not msgpack), that every query got exactly one reply, that ticks went on while the request
thread was held, and what a stop answers for the queries still waiting.
"""

from __future__ import annotations

import threading
from collections import Counter

import msgpack
import pytest
import zenoh
from conftest import TIMEOUT, WAIT, connect, make_config, wait_until

from drape.client import protocol as P
from drape.server.service import Server
from drape.server.service.requests.requestq import TickGate

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

GARBAGE = b"\xc1" * 600  # 0xc1 is never valid msgpack: decoding it answers "malformed"


class Asker:
    """Queries sent with callbacks; each query's reply outcomes and whether it finished."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.lock = threading.Lock()
        self.outcomes: list[list[str]] = []
        self.done: list[bool] = []

    def ask(self, key: str, payload: bytes) -> int:
        with self.lock:
            i = len(self.outcomes)
            self.outcomes.append([])
            self.done.append(False)

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                outcome = "ok"
            else:
                outcome = str(msgpack.unpackb(reply.err.payload.to_bytes(), raw=False)["error"]["code"])
            with self.lock:
                self.outcomes[i].append(outcome)

        def on_done() -> None:
            with self.lock:
                self.done[i] = True

        self.session.get(key, zenoh.handlers.Callback(on_reply, on_done), payload=payload, timeout=4 * TIMEOUT)
        return i

    def replied(self, indices) -> bool:
        with self.lock:
            return all(self.outcomes[i] for i in indices)

    def finished(self) -> bool:
        with self.lock:
            return all(self.done)

    def tally(self, indices) -> Counter:
        with self.lock:
            return Counter(o for i in indices for o in self.outcomes[i])


def held_server(**config) -> tuple[Server, threading.Event, threading.Event]:
    """A started server whose first info request holds the request thread until ``release``."""
    srv = Server(make_config(**config))
    entered, release = threading.Event(), threading.Event()
    on_info = srv.handlers.on_info

    def holding(query, payload, client=None):
        if not entered.is_set():
            entered.set()
            release.wait(4 * TIMEOUT)
        on_info(query, payload, client)

    srv.handlers.on_info = holding  # type: ignore[method-assign]  # before start: endpoints() takes it
    srv.start()
    return srv, entered, release


@pytest.mark.parametrize("request_yield", [False, True], ids=["plain", "yield"])
def test_a_flood_past_the_bound_is_answered_busy_at_once_and_ticks_go_on(request_yield: bool) -> None:
    srv, entered, release = held_server(max_pending_requests=4, request_yield=request_yield)
    try:
        with connect(srv) as c:
            keys, sid = P.Keys(srv.config.namespace), srv.server_id
            asker = Asker(c.session)
            first = asker.ask(keys.info(sid), P.encode_info(P.InfoRequest(rid=1)))
            assert entered.wait(WAIT), "the request thread never ran the info handler"
            tick0 = srv.tick
            flood = [asker.ask(keys.submit(sid), GARBAGE) for _ in range(20)]
            # 4 wait in the queue; the other 16 are answered busy while the request thread is held
            assert wait_until(lambda: asker.tally(flood)["busy"] == 16), asker.tally(flood)
            assert srv.handlers.request_queue.waiting() == (4, 4 * len(GARBAGE))
            assert wait_until(lambda: srv.tick >= tick0 + 10), "the server stopped ticking"
            assert not asker.replied([first])
            release.set()
            assert wait_until(asker.finished), "a query got no end"
            assert asker.tally([first]) == Counter(ok=1)
            assert asker.tally(flood) == Counter(busy=16, malformed=4)  # the queued ones decoded in turn
            assert all(len(o) == 1 for o in asker.outcomes), "every query gets exactly one reply"
            st = srv.stats()
            assert st["errors"]["busy"] == 16 and st["errors"]["malformed"] == 4
            assert st["requests"]["submit"] == 20 and st["requests"]["info"] == 1
            q = srv.handlers.request_queue
            assert (q.accepted, q.refused, q.high_water) == (5, 16, 4)
    finally:
        release.set()
        srv.stop()
    assert srv.failure is None


def test_the_byte_bound_turns_away_what_would_not_fit() -> None:
    srv, entered, release = held_server(max_pending_request_bytes=1000)
    try:
        with connect(srv) as c:
            keys, sid = P.Keys(srv.config.namespace), srv.server_id
            asker = Asker(c.session)
            asker.ask(keys.info(sid), P.encode_info(P.InfoRequest(rid=1)))
            assert entered.wait(WAIT)
            q = srv.handlers.request_queue
            a = asker.ask(keys.control(sid), GARBAGE)  # 600 bytes: fits
            assert wait_until(lambda: q.waiting() == (1, 600))
            b = asker.ask(keys.control(sid), GARBAGE)  # 1200 > 1000: busy now
            assert wait_until(lambda: asker.replied([b]))
            small = asker.ask(keys.remove(sid), GARBAGE[:100])  # 700: fits
            assert wait_until(lambda: q.waiting() == (2, 700))
            release.set()
            assert wait_until(asker.finished)
            assert asker.tally([b]) == Counter(busy=1)
            assert asker.tally([a, small]) == Counter(malformed=2)
    finally:
        release.set()
        srv.stop()
    assert srv.failure is None


def test_queries_still_queued_at_stop_are_answered_busy() -> None:
    srv, entered, release = held_server()
    stopper = threading.Thread(target=srv.stop)
    try:
        with connect(srv) as c:
            keys, sid = P.Keys(srv.config.namespace), srv.server_id
            asker = Asker(c.session)
            first = asker.ask(keys.info(sid), P.encode_info(P.InfoRequest(rid=1)))
            assert entered.wait(WAIT)
            queued = [asker.ask(keys.info(sid), P.encode_info(P.InfoRequest(rid=2 + i))) for i in range(3)]
            q = srv.handlers.request_queue
            assert wait_until(lambda: q.waiting()[0] == 3)
            stopper.start()
            assert wait_until(lambda: q.closed)
            release.set()  # the held request finishes; the three waiting ones are refused, not handled
            assert wait_until(asker.finished)
            assert asker.tally([first]) == Counter(ok=1)
            assert asker.tally(queued) == Counter(busy=3)
            assert q.handled == 1
    finally:
        release.set()
        if stopper.ident is None:
            srv.stop()
        else:
            stopper.join(4 * TIMEOUT)
    assert srv.failure is None


def test_the_tick_gate_holds_requests_while_the_tick_thread_works() -> None:
    gate = TickGate(max_wait_s=4 * TIMEOUT)
    gate.enter()  # open at first: no wait
    assert gate.waits == 0
    gate.tick_sleeps(False)  # the tick thread woke
    t = threading.Thread(target=gate.enter)
    t.start()
    assert wait_until(lambda: gate.waits == 1)
    assert t.is_alive(), "a request started while the tick thread worked"
    gate.tick_sleeps(True)  # it sleeps again: the request goes ahead
    t.join(TIMEOUT)
    assert not t.is_alive() and gate.timeouts == 0


def test_the_tick_gate_lets_requests_through_when_ticks_never_sleep() -> None:
    gate = TickGate(max_wait_s=0.01)
    gate.tick_sleeps(False)
    gate.enter()  # nobody opens it: returns after max_wait_s, counted
    assert (gate.waits, gate.timeouts) == (1, 1)
