"""Placement (PROTOCOL.md 11.3): which live Drape server a new cloth goes to, chosen by load.

A :class:`DrapeClient` created without ``server_id`` places every submission on its own, and its
failover (:mod:`.failover`) places every resubmission the same way: both ask the one
:class:`Placement` of the client. It keeps each server's last stats publication
(``{ns}/server/*/stats``, PROTOCOL.md 10) and what this client placed on each server since then,
and ranks the live servers (those whose liveliness token the client sees) by:

1. servers with stats first (a server that has not published yet comes last);
2. the fewest **vertices**: the last stats' ``vertices`` plus the vertices of this client's
   placements not yet in them (submits in flight, and those answered after that server's last
   stats arrived), so a burst of submits from one client spreads at once instead of landing on
   the server that looked emptiest before it;
3. the lowest mean tick (``phases.tick.mean_ms`` of the last stats window);
4. a hash of (client id, server id): clients that see the same loads (many clients starting at
   once) prefer different servers instead of all taking the alphabetically first.

A server that refuses (``overloaded``, ``busy``, ``limit_exceeded``, no reply) is skipped for
that cloth and the next one in the ranking is tried (:data:`PLACE_ELSEWHERE`). With several
live servers and some of them without stats yet, a first choice waits up to ``stats_wait``
seconds for their first publication. Pure rule (:func:`rank`) and state (:class:`Placement`) are
separate so the rule can be checked on decoded stats messages without a network.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import zenoh

from . import protocol as P

log = logging.getLogger(__name__)

#: Error codes of a submit that another server may accept: try the next one in the ranking.
PLACE_ELSEWHERE = frozenset({P.ERR_OVERLOADED, P.ERR_BUSY, P.ERR_LIMIT_EXCEEDED, P.ERR_UNAVAILABLE})


@dataclass(frozen=True)
class ServerLoad:
    """One server as the rule sees it: ``known`` (stats received), its stats' ``vertices`` and
    ``tick_ms``, and ``pending``: this client's vertices placed there and not yet in its stats."""

    server: str
    known: bool
    vertices: int
    tick_ms: float
    pending: int = 0

    @property
    def total(self) -> int:
        return self.vertices + self.pending


def load_from_stats(server: str, stats: Mapping[str, Any] | None, pending: int = 0) -> ServerLoad:
    """A server's load from its decoded stats publication (None: none received yet)."""
    if stats is None:
        return ServerLoad(server, False, 0, 0.0, pending)
    tick = ((stats.get("phases") or {}).get("tick") or {}).get("mean_ms") or 0.0
    return ServerLoad(server, True, int(stats.get("vertices") or 0), float(tick), pending)


def tiebreak(client_id: str, server: str) -> int:
    """A stable per-(client, server) number: the last key of the ranking."""
    return int.from_bytes(hashlib.blake2b(f"{client_id}\0{server}".encode(), digest_size=8).digest(), "big")


def rank(loads: Iterable[ServerLoad], client_id: str) -> list[str]:
    """Server ids best first by the module's rule."""
    return [
        s.server for s in sorted(loads, key=lambda s: (not s.known, s.total, s.tick_ms, tiebreak(client_id, s.server)))
    ]


def spread(counts: Iterable[int]) -> float:
    """How uneven a placement is: max / mean - 1 of the per-server counts (0: even)."""
    c = list(counts)
    mean = sum(c) / len(c) if c else 0.0
    return max(c) / mean - 1.0 if mean > 0 else 0.0


@dataclass
class _Placed:
    server: str
    vertices: int
    replied: float | None = None  # time.monotonic() of the reply; None while in flight


class Placement:
    """The servers' loads as one client sees them, and its choice of a server (module docstring).

    ``live``: the ids of the servers whose liveliness tokens the client sees now. Stats come from
    :meth:`attach` (a subscriber on ``{ns}/server/*/stats``) or are fed to :meth:`on_stats`."""

    def __init__(self, client_id: str, live: Callable[[], Iterable[str]], *, stats_wait: float = 1.5) -> None:
        self.client_id = client_id
        self.live = live
        self.stats_wait = stats_wait
        self._cond = threading.Condition()
        self._stats: dict[str, dict[str, Any]] = {}
        self._arrived: dict[str, float] = {}
        self._placed: dict[int, _Placed] = {}
        self._ids = itertools.count()
        self._sub: Any = None

    # --- inputs -------------------------------------------------------------------------------
    def attach(self, session: zenoh.Session, keys: P.Keys) -> None:
        """Subscribe to every server's stats publications (once)."""
        if self._sub is None:
            self._sub = session.declare_subscriber(keys.stats("*"), self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.on_stats(sample.payload.to_bytes(), str(sample.key_expr))

    def on_stats(self, payload: bytes | bytearray, key: str = "", now: float | None = None) -> str | None:
        """A stats publication (its msgpack bytes) arrived; returns the server it is of (None:
        not a stats message). Placements answered before it are counted in it from now on."""
        try:
            st = P.decode_stats(payload)
        except Exception:
            return None
        parts = key.split("/")
        sid = str(st.get("server") or (parts[-2] if len(parts) >= 2 else ""))
        if not sid:
            return None
        now = time.monotonic() if now is None else now
        with self._cond:
            self._stats[sid] = st
            self._arrived[sid] = now
            for k in [
                k for k, p in self._placed.items() if p.server == sid and p.replied is not None and p.replied <= now
            ]:
                del self._placed[k]
            self._cond.notify_all()
        return sid

    def server_gone(self, server: str) -> None:
        """Its liveliness token went: its stats stay (a failover reads its tick rate) but no longer
        rank it by its old load if it comes back (a restart starts empty)."""
        with self._cond:
            st = self._stats.get(server)
            if st is not None:
                self._stats[server] = {"server": server, "tick_rate": st.get("tick_rate"), "stale": True}
            for k in [k for k, p in self._placed.items() if p.server == server]:
                del self._placed[k]

    def placing(self, server: str, vertices: int) -> int:
        """A submission of ``vertices`` is sent to ``server``: counted there from now on."""
        with self._cond:
            k = next(self._ids)
            self._placed[k] = _Placed(server, int(vertices))
            return k

    def placed(self, ticket: int, ok: bool, now: float | None = None) -> None:
        """Its reply came: accepted (counted until the server's next stats) or refused (not)."""
        with self._cond:
            if not ok:
                self._placed.pop(ticket, None)
            elif ticket in self._placed:
                self._placed[ticket].replied = time.monotonic() if now is None else now

    def close(self) -> None:
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except Exception:
                pass
            self._sub = None

    # --- the choice ---------------------------------------------------------------------------
    def stats(self, server: str) -> dict[str, Any] | None:
        """The server's last stats publication (decoded), or None."""
        with self._cond:
            return self._stats.get(server)

    def loads(self, servers: Iterable[str]) -> list[ServerLoad]:
        with self._cond:
            pending: dict[str, int] = {}
            for p in self._placed.values():
                pending[p.server] = pending.get(p.server, 0) + p.vertices
            return [
                load_from_stats(s, None if self._stale(s) else self._stats.get(s), pending.get(s, 0)) for s in servers
            ]

    def _stale(self, server: str) -> bool:
        st = self._stats.get(server)
        return st is None or bool(st.get("stale"))

    def ranked(self, exclude: Iterable[str] = (), wait: bool = True) -> list[str]:
        """The live servers not in ``exclude``, best first. ``wait``: when several are candidates
        and some have not published stats, wait up to ``stats_wait`` s for them."""
        skip = set(exclude)
        cands = sorted(s for s in self.live() if s not in skip)
        if wait and len(cands) > 1:
            with self._cond:
                self._cond.wait_for(lambda: not any(self._stale(s) for s in cands), self.stats_wait)
        return rank(self.loads(cands), self.client_id)

    def choose(self, exclude: Iterable[str] = (), wait: bool = True) -> str | None:
        """The best live server not in ``exclude`` (None: there is none)."""
        r = self.ranked(exclude, wait)
        return r[0] if r else None


__all__ = ["PLACE_ELSEWHERE", "Placement", "ServerLoad", "load_from_stats", "rank", "spread", "tiebreak"]
