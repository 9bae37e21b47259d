"""The receiving side of a client's state bundle (protocol 1.1, PROTOCOL.md 9.1): each bundle is
parsed and decoded once, whole (:meth:`drape.client.protocol.Bundle.decode`: a few numpy operations
per group of like states, not a decode per cloth), then its states are handed to their
ClothHandles in one pass on the receiving thread.

A handle's guarantees hold as with states on a cloth's own key: its queue, ``received`` /
``dropped`` / ``invalid`` counts, and its callbacks in order on the receiving thread. States of a
cloth whose submit reply has not been handled yet (the bundle can overtake the reply) are kept for
it as orphans while a bundled submission is on its way, and delivered first when its handle is
registered (:meth:`drape.client.submitting.Submitter.place`).

1.8: the bundle is taken at one rate for all its cloths (every k-th bundle on its own key,
:meth:`BundleReceiver.set_rate`; with ``rate="auto"`` a rates.RateGovernor steps it down when
bundles arrive late), at the rates every server its cloths live on serves (``served``: none but the
full rate on a 1.7 server, down to every 3rd on a 1.8 one, every 12th on a 1.9 one).

:meth:`BundleReceiver.count_only`: some cloths' states are only counted from their headers (tick,
server time), not decoded: for a client that measures the server (``drape loadtest``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh

from . import protocol as P
from .protocol import ClothState, DrapeError
from .rates import RateGovernor, fit_rate

if TYPE_CHECKING:
    from .handle import ClothHandle

log = logging.getLogger("drape.client.sdk")

MAX_ORPHAN_CLOTHS = 256  # bundle entries of cloths whose submit reply is still on its way, kept per id

#: BundleReceiver.count_only's callback: (cloth ids, their states' ticks, server times (int64
#: arrays), the bundle's receive time ns).
HeadersCallback = Callable[[list[str], np.ndarray, np.ndarray, int], None]


class BundleReceiver:
    """Delivers the states of this client's bundles to its handles.

    ``handles``: the client's handles by cloth id (read here without the lock, changed only under
    it); ``lock``: the client's lock (guards the handles, the orphans and the submission count);
    ``queue_size``: states kept per orphan cloth; ``key``: the bundle key (for the logs)."""

    def __init__(
        self,
        handles: dict[str, ClothHandle],
        lock: threading.Lock,
        queue_size: int = 64,
        key: str = "",
        rate: int = 1,
        governed: bool = False,
    ) -> None:
        self._handles = handles
        self._lock = lock
        self.queue_size = queue_size
        self.key = key
        self.bundles = 0  # bundle payloads received
        self.invalid = 0  # bundle payloads that could not be parsed
        self._submits = 0  # bundled submissions waiting for their reply
        self._orphans: dict[str, list[ClothState]] = {}  # their states that arrived before the reply
        self._sub: Any = None
        self._session: zenoh.Session | None = None
        self.rate = rate  # 1.8: every rate-th bundle, on its own key
        # the rates every server of its cloths serves (protocol.served_rates; a 1.7 one among
        # them: the full-rate key only, a 1.8 one: down to every 3rd)
        self.served: tuple[int, ...] = P.RATES
        self.governor = RateGovernor(rate=rate) if governed else None
        self.undecoded: frozenset[str] = frozenset()  # count_only's cloths
        self.counted = 0  # their states seen (headers read, nothing decoded)
        self._on_headers: HeadersCallback | None = None

    @property
    def step_downs(self) -> int:
        return self.governor.step_downs if self.governor is not None else 0

    @property
    def step_ups(self) -> int:
        return self.governor.step_ups if self.governor is not None else 0

    def set_rate(self, rate: int) -> None:
        """1.8: take every ``rate``-th bundle from now on (its own key, its own streams): each
        bundled handle's stream starts afresh and one keyframe is asked for on the new key."""
        if rate not in P.RATES:
            raise ValueError(f"rate {rate!r}: one of {P.RATES}")
        with self._lock:
            rate = fit_rate(rate, self.served)
            if rate == self.rate:
                return
            if self._session is None:  # not subscribed yet: subscribe() takes this rate
                self.rate = rate
                return
            self.rate = rate  # from now on the old key's bundles are ignored
            handles = [h for h in self._handles.values() if h.bundle_key is not None]
            session = self._session
        for h in handles:
            with h._cond:
                h.rate = rate
                h.stream = P.StateStream(h.id)
        new = self._subscribe(session, rate)  # before the old one goes (make before break)
        with self._lock:
            old, self._sub = self._sub, new
        if old is not None:
            try:
                old.undeclare()
            except Exception:
                pass
        if handles:
            handles[0].ask_keyframe(0.0)  # one query on the bundle's key: every stream of it

    def limit(self, served: tuple[int, ...]) -> None:
        """A cloth of the bundle lives on a server serving the rates ``served``: the bundle keeps
        to the rates every server of its cloths serves (stepping to the one below when its rate
        is not among them; the governor's ladder too)."""
        with self._lock:
            self.served = tuple(k for k in self.served if k in served)
            if self.governor is not None:
                self.governor.limit(self.served)
        self.set_rate(self.rate)  # fit to what is served (nothing when it is)

    def count_only(self, cloths: Iterable[str], callback: HeadersCallback | None = None) -> None:
        """Neither decode nor deliver the bundled states of ``cloths`` (ids) from now on: read
        only their headers' tick and server time, all at once, and hand them to ``callback`` (on
        the receiving thread; None: only ``counted``). For a client that counts states rather
        than shows them (``drape loadtest``'s, which measure the server, not this SDK). Their
        handles get no states, and their predictive streams stop (a cloth put back to decoding
        needs a keyframe: it asks, as after a loss). An empty set decodes every cloth again."""
        with self._lock:
            self.undecoded = frozenset(cloths)
            self._on_headers = callback

    def _count(self, bundle: P.Bundle, cols: P.BundleEntries, entries: np.ndarray, receive_time_ns: int) -> None:
        """count_only's states of a bundle: their ticks and server times, read at once."""
        entries = entries[cols.sizes[entries] >= P.STATE_HEADER_SIZE]
        raw = np.frombuffer(bundle.data, np.uint8)
        fields = raw[cols.offsets[entries][:, None] + np.arange(16, 32)].view("<i8")  # tick, server time
        self.counted += len(entries)
        cloths = [cols.cloths[i] for i in entries.tolist()]
        # their states arrive: the cloths are alive (failover probes a cloth whose states stall,
        # and took these, which get no states delivered, for stalled ones)
        now, handles = time.monotonic(), self._handles
        for c in cloths:
            h = handles.get(c)
            if h is not None:
                h.last_receipt = now
        cb = self._on_headers
        if cb is not None and cloths:
            cb(cloths, fields[:, 0], fields[:, 1], receive_time_ns)

    def subscribe(self, session: zenoh.Session) -> None:
        """Subscribe to the bundle key once, before the first bundled submission, so the
        subscription is in place when the cloth's first state is published."""
        with self._lock:
            self._session = session
            if self._sub is None:
                self._sub = self._subscribe(session, self.rate)

    def _subscribe(self, session: zenoh.Session, rate: int) -> Any:
        """A subscriber of the bundle key at ``rate`` whose bundles count only while it is the rate."""

        def on_sample(sample: zenoh.Sample) -> None:
            if rate == self.rate:
                self.on_sample(sample)

        return session.declare_subscriber(P.every_key(self.key, rate), on_sample)

    def close(self) -> None:
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except Exception:
                pass

    def on_sample(self, sample: zenoh.Sample) -> None:
        """The bundle subscriber's callback (on the Zenoh thread)."""
        now = time.time_ns()
        self.receive(sample.payload.to_bytes(), now)

    def observe(self, tick: int, server_ns: int, receive_ns: int) -> None:
        """1.8, ``rate="auto"``: a bundle of ``tick`` arrived; the rate stepped when it calls for it
        (the subscription switched off the receiving thread)."""
        gov = self.governor
        if gov is None or len(self.served) == 1:
            return
        new = gov.observe(tick, server_ns, receive_ns)
        if new is not None:
            log.info("bundle %s: every %d ticks from now", self.key, new)
            threading.Thread(target=self.set_rate, args=(new,), name="drape-rate", daemon=True).start()

    def receive(self, data: bytes | bytearray | memoryview, receive_time_ns: int = 0) -> None:
        """Decode one bundle payload and deliver each state to its handle (on the calling thread)."""
        self.bundles += 1
        try:
            bundle = P.parse_bundle(data)
        except DrapeError as e:
            self.invalid += 1
            log.warning("invalid bundle payload on %s: %s", self.key, e)
            return
        self.observe(bundle.tick, bundle.server_time_ns, receive_time_ns)
        cols = P.BundleEntries.of(bundle.entries)
        entries: list[int] | range = range(len(cols))
        if self.undecoded:  # count_only: those entries' headers only
            skip = np.fromiter((c in self.undecoded for c in cols.cloths), bool, len(cols))
            if skip.any():
                self._count(bundle, cols, np.flatnonzero(skip), receive_time_ns)
                entries = np.flatnonzero(~skip).tolist()
        # 1.5: predictive states are each their stream's (decoded together below); the others
        # whole-bundle as before
        raw = np.frombuffer(bundle.data, np.uint8)
        pred = (cols.sizes > 8) & (raw[np.minimum(cols.offsets + 8, len(raw) - 1)] == P.ENC_PREDICTIVE)
        states: list[ClothState | P.ProtocolError | None] = [None] * len(cols)
        plain = [i for i in entries if not pred[i]] if not pred.all() else []
        if plain:
            decoded = P.decode_states(
                bundle.data, cols.offsets[plain], cols.sizes[plain], [cols.cloths[i] for i in plain], receive_time_ns
            )
            for i, one in zip(plain, decoded, strict=True):
                states[i] = one
        now = time.monotonic()
        handles = self._handles
        predicted = self._predictive(bundle, cols, [i for i in entries if pred[i]], receive_time_ns)
        for i in entries:
            cloth, st = cols.cloths[i], states[i]
            h = handles.get(cloth)
            if h is None:
                h = self._orphan(cloth, st)
                if h is None:
                    continue
            if h.bundle_key is None:  # an unbundled cloth of that id: its states come on its own key
                continue
            if pred[i]:
                got = predicted.get(i)
                if isinstance(got, DrapeError):
                    h.invalid += 1
                    log.warning("cloth %s: invalid state in bundle: %s", h.id, got)
                    continue
                if got is None:  # predicted from a state this client lacks (or a handle just registered)
                    got = h.missing(bundle.payload(i), receive_time_ns)
                if got is not None:
                    h.deliver(got, now)
            elif st.__class__ is ClothState:
                h.deliver(st, now)  # type: ignore[arg-type]
            else:
                h.invalid += 1
                log.warning("cloth %s: invalid state in bundle: %s", h.id, st)

    def _predictive(
        self, bundle: P.Bundle, cols: P.BundleEntries, entries: list[int], receive_time_ns: int
    ) -> dict[int, ClothState | DrapeError | None]:
        """1.5: the bundle's predictive ``entries`` of this client's handles, decoded all at once
        through their streams (protocol.decode_predictive_many), by entry index."""
        handles = self._handles
        mine = [(i, handles[cols.cloths[i]]) for i in entries if cols.cloths[i] in handles]
        out: dict[int, ClothState | DrapeError | None] = {}
        if not mine:
            return out
        try:
            got = P.decode_predictive_many(
                bundle.data, [int(cols.offsets[i]) for i, _ in mine], [h.stream for _, h in mine], receive_time_ns
            )
            out.update((i, st) for (i, _), st in zip(mine, got, strict=True))
        except DrapeError:  # a bad one among them: each alone, so that only it is lost
            for i, h in mine:
                try:
                    out[i] = h.stream.decode(bundle.payload(i), receive_time_ns)
                except DrapeError as err:
                    out[i] = err
        return out

    def _orphan(self, cloth: str, st: ClothState | P.ProtocolError | None) -> ClothHandle | None:
        """A cloth without a handle: its handle if it was registered meanwhile, else None, and its
        state kept for it while a bundled submission (maybe its) waits for the reply."""
        with self._lock:
            h = self._handles.get(cloth)
            if h is None and self._submits and isinstance(st, ClothState):
                if cloth in self._orphans or len(self._orphans) < MAX_ORPHAN_CLOTHS:
                    q = self._orphans.setdefault(cloth, [])
                    q.append(st)
                    del q[: -self.queue_size]
            return h

    # --- bundled submissions (Submitter.place) -------------------------------------------------
    def submitting(self) -> None:
        """A bundled submission is on its way: keep states of cloths without a handle."""
        with self._lock:
            self._submits += 1

    def submitted(self) -> None:
        """A bundled submission was answered (or failed); the last one forgets every orphan."""
        with self._lock:
            self._submits -= 1
            if not self._submits:
                self._orphans.clear()

    def early_states(self, cloth: str) -> list[ClothState]:
        """The states kept for ``cloth`` before its handle existed (call with the client's lock held,
        while registering the handle)."""
        return self._orphans.pop(cloth, [])


__all__ = ["MAX_ORPHAN_CLOTHS", "BundleReceiver", "HeadersCallback"]
