"""The publisher thread: everything sent for one tick, in order: the replies of the commands
applied before it, the tick's payloads (the World's :class:`~drape.server.sim.wire.Wire`: each
cloth on its own key or, for cloths submitted with ``state.bundle``, one bundle per client), the
undeclarations of removed cloths' publishers, the replies sent after it (removes) and the
periodic stats.

Per tick it works per *publication* (a state or a bundle), never per live cloth. The bytes come
from the World as they are: encoded on the host as they are taken, or slices of a frame encoded
on the device (one ``bytes`` copy each). Publications whose key has no subscriber are not
encoded or copied (counted ``unwatched``). The predictive streams (1.5) are kept here, with the
keyframe requests of subscribers (:meth:`Publisher.request_keyframes`); the decimated keys of
1.8 (every k-th state, their own streams) in :mod:`.rates`. A frame the publisher
had not taken when the next one was read back is dropped and its replies carried over (counted
``skipped_frames`` by the tick thread, :meth:`Job.drop_older`, before it steps again: a
device-encoded frame's predictive states are then coded again against the states sent): the
tick thread never waits for the network.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import zenoh

from drape.client import protocol as P

from ...sim.statecodec import PredictiveStreams
from ...sim.wire import Wire
from ..config import ServerConfig
from ..process.memory import freeze_long_lived
from ..process.telemetry import PhaseTimer
from ..registry import Registry
from ..replies import Replier, Reply, send, undeclare
from .rates import RatePublishers

log = logging.getLogger(__name__)


@dataclass(eq=False)
class Job:
    tick: int = 0
    wire: Wire | None = None  # the tick's payloads (World.fetch_async), held until published (or dropped)
    before: list[Reply] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    after: list[Reply] = field(default_factory=list)
    stats: bytes | None = None

    def absorb(self, older: Job) -> None:
        """Coalesce: keep this job's frame, every reply and removal of the older one first."""
        self.before = older.before + self.before
        self.removed = older.removed + self.removed
        self.after = older.after + self.after
        if self.stats is None:
            self.stats = older.stats
        if self.wire is not None and older.wire is not None:
            self.wire.carry_flags(older.wire)  # a reset flag is not lost with its frame
        older.release()

    def drop_older(self, older: Job) -> None:
        """The tick thread, once this job's frame is back and before the next step: ``older``,
        which the publisher never took, is dropped now (rather than when this job is handed
        over), so that this frame's predictive states are coded again against the last states
        sent (``Wire.after_dropped``) before the world moves on."""
        if self.wire is not None and older.wire is not None:
            self.wire.after_dropped(older.wire)
            older.wire.release()
            older.wire = None
        self.absorb(older)

    def release(self) -> None:
        """Let the World reuse this job's host memory."""
        if self.wire is not None:
            self.wire.release()
            self.wire = None


class Mailbox:
    """A one-slot hand-off from the tick thread to the publisher that never blocks the producer."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._job: Job | None = None
        self._closed = False

    def put(self, job: Job) -> bool:
        """Hand over a job; True when it replaced one the publisher had not taken yet."""
        with self._cond:
            coalesced = self._job is not None
            if coalesced:
                job.absorb(self._job)  # type: ignore[arg-type]
            self._job = job
            self._cond.notify()
            return coalesced

    def withdraw(self) -> Job | None:
        """The job the publisher has not taken yet, taken back (it is dropped), or None."""
        with self._cond:
            job, self._job = self._job, None
            return job

    def take(self) -> Job | None:
        with self._cond:
            while self._job is None and not self._closed:
                self._cond.wait()
            job, self._job = self._job, None
            return job

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class Publisher:
    def __init__(self, config: ServerConfig, keys: P.Keys, registry: Registry, timers: dict[str, PhaseTimer]) -> None:
        self.config, self.keys, self.registry, self.timers = config, keys, registry, timers
        self.mailbox = Mailbox()
        self.session: zenoh.Session | None = None
        self.stats_pub: zenoh.Publisher | None = None
        self._pubs: dict[str, tuple[zenoh.Publisher, bool]] = {}  # per cloth id
        self._bundle_pubs: dict[str, tuple[zenoh.Publisher, bool]] = {}  # per bundle key
        self.streams = PredictiveStreams(config.keyframe_interval)  # 1.5: the predictive streams
        self.rates = RatePublishers(config.keyframe_interval)  # 1.8: the decimated keys and their streams
        self._roster_version: tuple[int, int] | None = None
        self.last_cost_s = 0.0  # encode + put of the last frame (the tick's cost model adds it)
        self.replier: Replier | None = None  # the run thread's (replies never wait in the publisher)
        self.last_tick = 0  # the last tick published (keyframe queries are told the next one)

    def attach(self, session: zenoh.Session) -> None:
        """The Zenoh session it puts on (opened when the server starts, before the threads) and
        its stats publisher there."""
        self.session = session
        self.stats_pub = session.declare_publisher(
            self.keys.stats(self.config.server_id), congestion_control=zenoh.CongestionControl.DROP
        )

    def run(self) -> None:
        self.replier = Replier(f"{threading.current_thread().name}-replies")
        try:
            while True:
                job = self.mailbox.take()
                if job is None:
                    break
                try:
                    self.publish(job)
                except Exception:
                    log.exception("publishing tick %d failed", job.tick)
                    self.registry.count("publish_errors")
                finally:
                    job.release()
        finally:
            self.replier.close()

    def close(self) -> None:
        for pub, _ in list(self._pubs.values()) + list(self._bundle_pubs.values()):
            undeclare(pub)
        self._pubs.clear()
        self._bundle_pubs.clear()
        self.rates.close()
        if self.stats_pub is not None:
            undeclare(self.stats_pub)
            self.stats_pub = None

    def _publisher(
        self, store: dict[str, tuple[zenoh.Publisher, bool]], ident: str, key: str, size: int
    ) -> zenoh.Publisher:
        """The publisher of ``key``, re-declared when the congestion control its payload size
        calls for changes (``auto``)."""
        mode = self.config.state_congestion
        block = mode == "block" or (mode == "auto" and size > self.config.drop_max_bytes)
        have = store.get(ident)
        if have is not None and have[1] == block:
            return have[0]
        if have is not None:
            undeclare(have[0])
        assert self.session is not None
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = self.session.declare_publisher(key, congestion_control=cc)
        store[ident] = (pub, block)
        self.rates.declare(self.session, ident, key, block)  # 1.8: its decimated keys, with it
        return pub

    def request_keyframes(self, cloths: list[str], every: int = 1) -> int:
        """1.5, any thread (a keyframe query): the next state of these cloths' predictive streams
        (1.8: of their rate-``every`` streams) is intra-coded. Returns the tick it will be at the
        earliest."""
        if every == 1:
            self.streams.request(cloths)
        else:
            self.rates.request_keyframes(cloths, every)
        t = self.last_tick + 1
        return t + (-t) % every

    def publish(self, job: Job) -> None:
        reply = self.replier.put if self.replier is not None else send
        self.last_tick = max(self.last_tick, job.tick)
        for r in job.before:
            reply(r)
        wire = job.wire
        if wire is not None and wire.roster.ids:
            self._put(wire)
        for cid in job.removed:
            have = self._pubs.pop(cid, None)
            if have is not None:
                undeclare(have[0])
                self.rates.remove(cid)
        if wire is not None and wire.roster.version != self._roster_version:
            roster = wire.roster
            self._roster_version = roster.version
            self.streams.keep_only(set(roster.ids))
            freeze_long_lived()  # the new layout's records and rosters: out of the collector's scans
            live = {k for k, _ in roster.bundles}
            for bkey in [k for k in self._bundle_pubs if k not in live]:  # the client has no bundled cloth left
                undeclare(self._bundle_pubs.pop(bkey)[0])
            self.rates.keep_only(set(self._pubs) | set(self._bundle_pubs), set(roster.ids))
        for r in job.after:
            reply(r)
        if job.stats is not None and self.stats_pub is not None:
            self.stats_pub.put(job.stats)

    def _put(self, wire: Wire) -> None:
        """Put each watched publication's payload (encoded as it is taken: the host path encodes
        only what someone subscribes to; a device-encoded payload is one ``bytes`` copy)."""
        pubs = wire.roster.publications()
        targets: dict[int, zenoh.Publisher] = {}
        unwatched = errors = 0
        for j, ((ident, key, idx, bundle), size) in enumerate(zip(pubs, wire.sizes(), strict=True)):
            try:
                pub = self._publisher(self._bundle_pubs if bundle else self._pubs, ident, key, size)
                # nobody subscribed: skip the work (zenoh's stub types matching_status as bool)
                if pub.matching_status.matching:  # type: ignore[attr-defined]
                    targets[j] = pub
                else:
                    unwatched += len(idx)
            except Exception as e:
                errors += len(idx)
                log.warning("publishing %s at tick %d failed: %s", ident, wire.tick, e)
        keyframes = self.streams.keyframes
        enc_t = pub_t = 0.0
        published = n_bundles = n_bytes = 0
        a = time.perf_counter()
        for j, payload in wire.payloads(list(targets), self.streams):
            b = time.perf_counter()
            enc_t += b - a
            ident, _, idx, bundle = pubs[j]
            if payload is None:
                errors += len(idx)
            else:
                try:
                    targets[j].put(payload)
                    published += len(idx)
                    n_bytes += len(payload)
                    n_bundles += bundle
                except Exception as e:
                    errors += len(idx)
                    log.warning("publishing %s at tick %d failed: %s", ident, wire.tick, e)
            a = time.perf_counter()
            pub_t += a - b
        if self.streams.keyframes != keyframes:
            self.registry.count("keyframes", self.streams.keyframes - keyframes)
        rate_t = self._put_rates(wire)
        self.timers["encode"].add(enc_t)
        self.timers["publish"].add(pub_t + rate_t)
        self.last_cost_s = enc_t + pub_t + rate_t
        self.registry.count_many(
            published=published, published_bytes=n_bytes, unwatched=unwatched, publish_errors=errors, bundles=n_bundles
        )

    def _put_rates(self, wire: Wire) -> float:
        """1.8: the decimated keys someone subscribes to whose state is this tick's, each coded
        against its own streams (``Wire.rate_payloads``: on the host, or the device's decimated
        frames, rates.py). Returns the seconds it took."""
        wire.watch_rates(self.rates.watching)  # a device encoder plans the next frames' rates from it
        due = self.rates.due(wire.tick, wire.roster)
        if not due:
            return 0.0
        a = time.perf_counter()
        pubs = wire.roster.publications()
        published = unserved = errors = n_bytes = 0
        for k, watched in due:
            streams = self.rates.streams[k]
            keyframes = streams.keyframes
            served = 0
            for j, payload in wire.rate_payloads(k, watched, streams):
                ident, _, idx, _ = pubs[j]
                served += len(idx)
                pub = self.rates.publisher(ident, k)
                if payload is None or pub is None:
                    errors += len(idx)
                    continue
                try:
                    pub.put(payload)
                    published += len(idx)
                    n_bytes += len(payload)
                except Exception as e:
                    errors += len(idx)
                    log.warning("publishing %s every %d at tick %d failed: %s", ident, k, wire.tick, e)
            if streams.keyframes != keyframes:
                self.registry.count("keyframes", streams.keyframes - keyframes)
            unserved += sum(len(pubs[j][2]) for j in watched) - served  # watched after the frame was encoded
        self.registry.count_many(
            rate_published=published, rate_unserved=unserved, published_bytes=n_bytes, publish_errors=errors
        )
        return time.perf_counter() - a
