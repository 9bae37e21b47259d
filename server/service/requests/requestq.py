"""The bounded request queue between Zenoh's queryable callbacks and the request thread.

A Zenoh queryable callback does the least it can: :meth:`RequestQueue.offer` queues the query
and returns. When ``max_pending_requests`` requests, or ``max_pending_request_bytes`` bytes of
their payloads, already wait (or the server is stopping), the query is answered ``busy`` at once
on the callback's thread, without decoding (PROTOCOL.md: "the server's request queue is full";
its ``rid`` is 0, as for a message too broken to read one from). One request thread takes the
queued queries in arrival order and runs each one's handler (decode, validate, check, hand on or
reply: handlers.py), so requests keep the order in which Zenoh delivered them.

Why: the handlers' Python work (decoding, validation, sending the reply) holds the GIL, and on
Zenoh's several callback threads a flood of requests took it from the tick thread as many times
over (docs/reliability.md, "Fuzz: where the missed ticks go"). Queued, the flood costs one thread's
worth of GIL at most, the queue's bound caps the memory a flood can pin (Zenoh no longer holds the
requests back in its own threads), and whatever the bound turns away costs one small reply.

With ``request_yield`` (default on) the request thread also keeps out of the tick's way: it
starts a request only while the tick thread sleeps between ticks (:class:`TickGate`). A tick's
Python work hands the GIL back at every OpenCL call and queues behind a busy request thread for
up to one switch interval each time it takes it again; gated, only the one request under way when
a tick begins competes with it. Measured under a 100,000-message fuzz (docs/reliability.md,
"Fuzz: requests off Zenoh's threads"): fewer missed ticks and about one lost state instead of
tens. A lower OS priority for the request thread (``os.setpriority``) was tried and showed no
difference above the machine's noise, so it is not kept.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

log = logging.getLogger(__name__)


class TickGate:
    """Open while the tick thread sleeps between ticks: the request thread starts a request only
    then, so the tick's own work does not queue behind requests for the GIL (each GIL hand-back
    to a thread busy in Python costs the tick thread up to one switch interval). It waits at most
    ``max_wait_s`` for the gate; having waited that long in vain (ticks back to back), it works
    unhindered for as long again, so requests still get about half the time of an overrunning server."""

    def __init__(self, max_wait_s: float) -> None:
        self.max_wait_s = max_wait_s
        self._open = threading.Event()
        self._open.set()
        self._free_until = 0.0
        self.waits = 0  # requests that waited for the tick thread (cumulative)
        self.timeouts = 0  # waits that ended without the gate opening

    def tick_sleeps(self, sleeping: bool) -> None:
        """The tick thread: True as it goes to sleep, False as it wakes."""
        if sleeping:
            self._open.set()
        else:
            self._open.clear()

    def enter(self) -> None:
        """The request thread, before each request."""
        if self._open.is_set() or time.monotonic() < self._free_until:
            return
        self.waits += 1
        if not self._open.wait(self.max_wait_s):
            self.timeouts += 1
            self._free_until = time.monotonic() + self.max_wait_s


@dataclass(eq=False)
class Pending:
    """One queued query and the handler that will answer it."""

    name: str  # the queryable's name (submit, control, ...)
    handle: Callable[[zenoh.Query], None]
    query: zenoh.Query
    size: int  # payload bytes, counted against the byte bound while queued


class RequestQueue:
    """Bounded FIFO of queries and the one thread that handles them.

    ``refuse(name, query, reason)`` answers a query the queue turns away (full or closed); it runs
    on the offering thread, or on the request thread for what is still queued at :meth:`close`.
    ``gate``: the request thread starts each request only once the gate lets it (:class:`TickGate`).
    """

    def __init__(
        self,
        max_pending: int,
        max_bytes: int,
        refuse: Callable[[str, zenoh.Query, str], None],
        name: str = "drape-requests",
        gate: TickGate | None = None,
    ) -> None:
        self.max_pending, self.max_bytes, self.gate = max_pending, max_bytes, gate
        self._refuse = refuse
        self._items: deque[Pending] = deque()
        self._bytes = 0
        self._cond = threading.Condition()
        self._closed = False
        self.accepted = 0  # queries queued (cumulative)
        self.refused = 0  # queries answered at once because the queue was full or closed
        self.handled = 0  # queries the request thread ran the handler of
        self.high_water = 0  # most queries waiting at once
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> RequestQueue:
        self._thread.start()
        return self

    # --- Zenoh's threads ---------------------------------------------------------------------------
    def callback(self, name: str, handle: Callable[[zenoh.Query], None]) -> Callable[[zenoh.Query], None]:
        """The queryable callback that queues its queries for ``handle``."""

        def on_query(query: zenoh.Query) -> None:
            self.offer(name, handle, query)

        return on_query

    def offer(self, name: str, handle: Callable[[zenoh.Query], None], query: zenoh.Query) -> bool:
        """Queue ``query`` for ``handle``; when full or closed, answer it through ``refuse`` now
        (False). One request is always taken when nothing waits, however large its payload."""
        payload = query.payload
        size = len(payload) if payload is not None else 0
        with self._cond:
            closed = self._closed
            fits = not closed and (
                not self._items or (len(self._items) < self.max_pending and self._bytes + size <= self.max_bytes)
            )
            if fits:
                self._items.append(Pending(name, handle, query, size))
                self._bytes += size
                self.accepted += 1
                self.high_water = max(self.high_water, len(self._items))
                self._cond.notify()
                return True
            self.refused += 1
            waiting, held = len(self._items), self._bytes
        reason = (
            "server is shutting down"
            if closed
            else f"server request queue is full ({waiting} requests, {held} bytes waiting), retry later"
        )
        self._refuse(name, query, reason)
        return False

    # --- the request thread ------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self._closed:
                    self._cond.wait()
                if not self._items:
                    return
            if self.gate is not None and not self._closed:
                self.gate.enter()
            with self._cond:
                item = self._items.popleft()
                self._bytes -= item.size
                closed = self._closed
            if closed:  # stopping: what is still queued is answered, not handled
                self._refuse(item.name, item.query, "server is shutting down")
                continue
            try:
                item.handle(item.query)
            except Exception:  # the handlers answer their own errors; never let one end this thread
                log.exception("request thread: handling a %s request failed", item.name)
            self.handled += 1
            del item  # the query and its payload go now, not when the next request comes

    @property
    def closed(self) -> bool:
        return self._closed

    def waiting(self) -> tuple[int, int]:
        """(queries, payload bytes) waiting now."""
        with self._cond:
            return len(self._items), self._bytes

    def close(self, timeout: float = 5.0) -> None:
        """Take no more queries (later offers are refused); answer what waits ``busy``; stop."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("the request thread did not stop in %.1f s", timeout)
