"""Rates per subscriber (protocol 1.8, PROTOCOL.md 9.3): every publication (a cloth's state key
or a client's bundle key) has decimated twins, ``{key}/every/{k}`` for k in ``RATES[1:]``, which
carry every k-th state (the ticks with ``tick % k == 0``), each a stream of its own: predictive
states on it are coded against its own previous states (a :class:`PredictiveStreams` per k,
keyed by cloth id like the full-rate ones, with a periodic keyframe every ``keyframe_interval``
of its own states), so a client that takes 30 Hz never needs a state it did not get.

A decimated key is encoded only while someone subscribes to it: its publisher's matching listener
(on Zenoh's threads) keeps the set of watched (publication, k), and the publisher thread looks at
that set only on the ticks of k, so the cost of rates nobody takes is one listener per key.

The World's wire codes them (``Wire.rate_payloads``): the host path against these streams, a
device-encoded frame from its own decimated frames (sim/opencl/devrates.py), planned from the
watched set read at each encode (:meth:`RatePublishers.watching`, handed to the wire); a
publication first watched after its tick's frame was encoded is served from its next tick of k
(its states meanwhile counted ``rate_unserved``).

A key that loses its last subscriber restarts its streams, so that whoever subscribes next starts
on a keyframe: the host path forgets them at the next frame put (:meth:`RatePublishers.due`), the
device encoder leaves the publication out of its next plan, or, when a subscriber came back
before the rate's next tick, restarts them from the count of such losses that
:meth:`RatePublishers.watching` gives with each watched publication.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import zenoh

from drape.client import protocol as P

from ...sim.roster import Roster
from ...sim.statecodec import PredictiveStreams
from ..replies import undeclare

log = logging.getLogger(__name__)

DECIMATED = P.RATES[1:]  # the rates with keys of their own


@dataclass(eq=False)
class _RateKey:
    """One publication's decimated key of rate ``every`` (its publisher and matching listener)."""

    pub: zenoh.Publisher
    listener: object
    block: bool


@dataclass(eq=False)
class RatePublishers:
    """The decimated publishers of one server's publications and who watches them."""

    keyframe_interval: int = 60
    streams: dict[int, PredictiveStreams] = field(default_factory=dict)
    _keys: dict[tuple[str, int], _RateKey] = field(default_factory=dict)  # (ident, k)
    # k -> idents with a subscriber -> times their key lost its last one before (as _left had it)
    _watched: dict[int, dict[str, int]] = field(default_factory=dict)
    _frozen: dict[int, Mapping[str, int]] = field(default_factory=dict)  # the same, as read by encoders
    _gone: dict[int, set[str]] = field(default_factory=dict)  # k -> idents that lost their last subscriber
    _left: dict[int, dict[str, int]] = field(default_factory=dict)  # k -> ident -> times it lost them all
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        # a periodic keyframe every keyframe_interval of the stream's own states (k x the ticks)
        self.streams = {k: PredictiveStreams(k * self.keyframe_interval) for k in DECIMATED}
        self._watched = {k: {} for k in DECIMATED}
        self._gone = {k: set() for k in DECIMATED}
        self._left = {k: {} for k in DECIMATED}

    # -- Zenoh's threads ------------------------------------------------------------------
    def _matching(self, ident: str, every: int, status: zenoh.MatchingStatus) -> None:
        with self._lock:
            if status.matching:
                self._watched[every][ident] = self._left[every].get(ident, 0)
            else:
                self._watched[every].pop(ident, None)
                self._gone[every].add(ident)  # its streams restart for whoever subscribes next
                left = self._left[every]
                left[ident] = left.get(ident, 0) + 1
            self._freeze(every)

    def _freeze(self, every: int) -> None:
        """(under the lock) the watched set of ``every`` as a new mapping (read without a lock)."""
        self._frozen = {**self._frozen, every: MappingProxyType(dict(self._watched[every]))}

    def watching(self) -> dict[int, Mapping[str, int]]:
        """Any thread: per rate, the idents of the publications watched, each with the times its
        key lost its last subscriber (a device encoder's plans: a publication watched again since
        its last plan restarts its streams); one mapping per rate until its watched set changes."""
        return self._frozen

    def request_keyframes(self, cloths: list[str], every: int) -> None:
        """1.8, any thread: the next state of these cloths' rate-``every`` streams is a keyframe."""
        self.streams[every].request(cloths)

    # -- the publisher thread -------------------------------------------------------------
    def declare(self, session: zenoh.Session, ident: str, key: str, block: bool) -> None:
        """The decimated publishers of publication ``ident`` on ``key`` (again when its congestion
        control changed)."""
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        for k in DECIMATED:
            have = self._keys.get((ident, k))
            if have is not None and have.block == block:
                continue
            if have is not None:
                self._drop(ident, k)
            pub = session.declare_publisher(P.every_key(key, k), congestion_control=cc)
            listener = pub.declare_matching_listener(
                lambda st, ident=ident, k=k: self._matching(ident, k, st)  # type: ignore[misc]
            )
            self._keys[(ident, k)] = _RateKey(pub, listener, block)
            if pub.matching_status.matching:  # type: ignore[attr-defined]
                with self._lock:
                    self._watched[k][ident] = self._left[k].get(ident, 0)
                    self._freeze(k)

    def _drop(self, ident: str, every: int) -> None:
        have = self._keys.pop((ident, every), None)
        if have is None:
            return
        try:
            have.listener.undeclare()  # type: ignore[attr-defined]
        except Exception:
            pass
        undeclare(have.pub)
        with self._lock:
            self._watched[every].pop(ident, None)
            self._freeze(every)

    def remove(self, ident: str) -> None:
        """A cloth (or bundle) no longer published."""
        for k in DECIMATED:
            self._drop(ident, k)

    def keep_only(self, idents: set[str], cloths: set[str]) -> None:
        """Forget the keys of publications gone and the streams of cloths gone."""
        for ident, k in [x for x in self._keys if x[0] not in idents]:
            self._drop(ident, k)
        for s in self.streams.values():
            s.keep_only(cloths)
        with self._lock:
            for left in self._left.values():
                for ident in [i for i in left if i not in idents]:
                    del left[ident]

    def due(self, tick: int, roster: Roster) -> list[tuple[int, list[int]]]:
        """(k, publication indices someone watches at rate k) of the rates whose state is this
        tick's (``tick % k == 0``)."""
        out = []
        pubs = roster.publications()
        for k in DECIMATED:
            with self._lock:
                gone, self._gone[k] = self._gone[k], set()
            if gone and self.streams[k].streams:
                # a key that lost its last subscriber starts its next subscriber on a keyframe, as
                # the device's decimated plans do (a publication unwatched leaves the rate's
                # plan): noticed on the next frame put, whether or not the frame of the tick it
                # left on was dropped; a rate nobody watches any more has lost them all so
                # (tests/service/test_rates.py, a key watched again, alone and beside another)
                ids = roster.ids
                self.streams[k].forget([ids[i] for p in pubs if p[0] in gone for i in p[2]])
            if tick % k:
                continue
            with self._lock:
                watched = set(self._watched[k])
            if watched:
                out.append((k, [j for j, p in enumerate(pubs) if p[0] in watched]))
        return out

    def publisher(self, ident: str, every: int) -> zenoh.Publisher | None:
        have = self._keys.get((ident, every))
        return have.pub if have is not None else None

    def close(self) -> None:
        for ident, k in list(self._keys):
            self._drop(ident, k)
