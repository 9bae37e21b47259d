"""The publisher thread: everything sent for one tick, in order: the replies of the commands
applied before it, the states (encoded by drape.server.service.statecodec straight from the
frame's contiguous positions, each cloth on its own key or, for cloths submitted with
``state.bundle``, one bundle per client), the undeclarations of removed cloths' publishers, the
replies sent after it (removes) and the periodic stats.

Per tick it works per *publication* (a state or a bundle), never per live cloth: the
:class:`Roster` (ids, keys, encodings, normals, singles and bundle groups as arrays in the
frame's order) is built by the tick thread only when cloths come, go or change how they are
published. A device-encoded frame (``Job.encoded``, config ``device_encode``) is already bytes:
each publication's slice is put with one ``bytes`` copy (zenoh's ZBytes takes no memoryview;
copying each slice is cheaper than one copy of the whole frame sliced again). States or bundles
whose key has no subscriber are not encoded or copied (counted
``unwatched``). A frame the publisher had not taken when the next one was ready is dropped and
its replies carried over (counted ``skipped_frames`` by the tick thread): the tick thread never
waits for the network.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import zenoh

from drape.client import protocol as P

from ..sim.world import Frame

if TYPE_CHECKING:
    from ..sim.opencl.encode import EncodedFrame
from .config import ServerConfig
from .process.memory import freeze_long_lived
from .process.telemetry import PhaseTimer
from .registry import Registry
from .replies import Replier, Reply, send, undeclare
from .statecodec import FrameEncoder

log = logging.getLogger(__name__)


@dataclass(eq=False)
class Roster:
    """How each cloth of a frame layout is published (frame order)."""

    version: tuple[int, int]  # (layout version, publication changes)
    ids: list[str]
    keys: list[str]
    encodings: list[int]  # protocol ids
    normals: np.ndarray  # (k,) bool
    singles: np.ndarray  # frame indices published on their own key
    bundles: list[tuple[str, np.ndarray]]  # (bundle key, frame indices)
    steps: list[float] = field(default_factory=list)  # 1.5, predictive cloths' grid steps (metres)
    _pubs: list[tuple[str, str, list[int], bool]] | None = None

    @property
    def predictive(self) -> bool:
        """Whether a cloth of this roster is published with the predictive encoding (1.5):
        its frames are encoded on the host (the device encoder does not code them yet)."""
        return P.ENC_PREDICTIVE in self.encodings

    def publications(self) -> list[tuple[str, str, list[int], bool]]:
        """(publisher ident: cloth id or bundle key, key, frame indices, bundle) per payload:
        the singles, then the bundles (the device-encoded frame's publication order)."""
        if self._pubs is None:
            self._pubs = [(self.ids[i], self.keys[i], [i], False) for i in self.singles.tolist()] + [
                (k, k, idx.tolist(), True) for k, idx in self.bundles
            ]
        return self._pubs


@dataclass(eq=False)
class Job:
    tick: int = 0
    time_ns: int = 0
    frame: Frame | None = None  # held until published (or dropped)
    roster: Roster | None = None
    flags: np.ndarray | None = None  # (k,) per cloth state flags (FLAG_RESET)
    encoded: EncodedFrame | None = None  # device-encoded payloads (device_encode), held until published
    on_device: bool = False  # the frame was encoded on the device (else the publisher encodes it)
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
        if (
            older.flags is not None
            and self.flags is not None
            and older.roster is not None
            and self.roster is not None
            and older.roster.version == self.roster.version
        ):
            self.flags |= older.flags  # a reset flag is not lost with its frame
            if self.encoded is not None and older.flags.any():  # already encoded: into its bytes
                bad = np.flatnonzero(older.flags & P.FLAG_RESET)
                if len(bad):
                    self.encoded.add_flags(bad.tolist(), P.FLAG_RESET)
        older.release()

    def release(self) -> None:
        """Let the World and the encoder reuse this job's host buffers."""
        if self.frame is not None:
            self.frame.release()
            self.frame = None
        if self.encoded is not None:
            self.encoded.release()
            self.encoded = None


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
        self._buffers: dict[str, bytearray] = {}  # payload buffers reused per key
        self._encoder = FrameEncoder(config.keyframe_interval)
        self._roster_version: tuple[int, int] | None = None
        self.last_cost_s = 0.0  # encode + put of the last frame (the tick's cost model adds it)
        self.replier: Replier | None = None  # the run thread's (replies never wait in the publisher)
        self.last_tick = 0  # the last tick published (keyframe queries are told the next one)

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
        return pub

    def _buffer(self, key: str, size: int) -> bytearray:
        buf = self._buffers.get(key)
        if buf is None or len(buf) != size:
            buf = self._buffers[key] = bytearray(size)
        return buf

    def request_keyframes(self, cloths: list[str]) -> int:
        """1.5, any thread (a keyframe query): the next state of these cloths' predictive streams
        is intra-coded. Returns the tick it will be at the earliest."""
        self._encoder.streams.request(cloths)
        return self.last_tick + 1

    def publish(self, job: Job) -> None:
        reply = self.replier.put if self.replier is not None else send
        self.last_tick = max(self.last_tick, job.tick)
        for r in job.before:
            reply(r)
        if job.encoded is not None and job.roster is not None and job.roster.ids:
            self._publish_encoded(job)
        elif job.frame is not None and job.roster is not None and job.roster.ids:
            self._publish_states(job)
        for cid in job.removed:
            have = self._pubs.pop(cid, None)
            if have is not None:
                self._buffers.pop(str(have[0].key_expr), None)  # its state key: 1.0 or client-scoped (1.4)
                undeclare(have[0])
        if job.roster is not None and job.roster.version != self._roster_version:
            self._roster_version = job.roster.version
            self._encoder.streams.keep_only(set(job.roster.ids))
            freeze_long_lived()  # the new layout's records and rosters: out of the collector's scans
            live = {k for k, _ in job.roster.bundles}
            for bkey in [k for k in self._bundle_pubs if k not in live]:  # the client has no bundled cloth left
                undeclare(self._bundle_pubs.pop(bkey)[0])
                self._buffers.pop(bkey, None)
        for r in job.after:
            reply(r)
        if job.stats is not None and self.stats_pub is not None:
            self.stats_pub.put(job.stats)

    def _publish_states(self, job: Job) -> None:
        t0 = time.perf_counter()
        enc, ro, frame = self._encoder, job.roster, job.frame
        assert ro is not None and frame is not None and job.flags is not None
        off = frame.offsets
        nxyz = frame.nxyz
        flags = job.flags.tolist()

        def normals(i: int) -> np.ndarray | None:
            return nxyz[off[i] : off[i + 1]] if nxyz is not None and ro.normals[i] else None

        enc.begin(job.tick, job.time_ns, frame.xyz, off)
        singles: list[tuple[int, zenoh.Publisher, int]] = []
        unwatched = errors = 0
        for i in ro.singles.tolist():
            try:
                size = enc.state_size(i, ro.encodings[i], bool(ro.normals[i]))
                pub = self._publisher(self._pubs, ro.ids[i], ro.keys[i], size)
                if pub.matching_status.matching:  # type: ignore[attr-defined]  # the stub says bool: a MatchingStatus
                    singles.append((i, pub, size))
                else:  # nobody subscribed: skip the work
                    unwatched += 1
            except Exception as e:
                errors += 1
                log.warning("publishing cloth %s at tick %d failed: %s", ro.ids[i], job.tick, e)
        bundles: list[tuple[str, list[int], zenoh.Publisher, int]] = []
        for bkey, idx_arr in ro.bundles:
            idx = idx_arr.tolist()
            try:
                size = enc.bundle_size([(ro.ids[i], i, ro.encodings[i], bool(ro.normals[i])) for i in idx])
                pub = self._publisher(self._bundle_pubs, bkey, bkey, size)
                if pub.matching_status.matching:  # type: ignore[attr-defined]  # the stub says bool: a MatchingStatus
                    bundles.append((bkey, idx, pub, size))
                else:
                    unwatched += len(idx)
            except Exception as e:
                errors += len(idx)
                log.warning("publishing bundle %s at tick %d failed: %s", bkey, job.tick, e)
        selected = [i for i, _, _ in singles] + [i for _, idx, _, _ in bundles for i in idx]
        enc.prepare(selected, ro.encodings)
        if ro.predictive:  # 1.5: each predictive cloth coded against its stream; sizes now exact
            keyframes = enc.streams.keyframes
            enc.prepare_predictive(selected, ro.ids, ro.encodings, ro.steps, flags)
            self.registry.count("keyframes", enc.streams.keyframes - keyframes)
            watched = set(selected)
            enc.streams.forget(
                [ro.ids[i] for i, e in enumerate(ro.encodings) if e == P.ENC_PREDICTIVE and i not in watched]
            )
            singles = [(i, pub, enc.state_size(i, ro.encodings[i], bool(ro.normals[i]))) for i, pub, _ in singles]
            bundles = [
                (bkey, idx, pub, enc.bundle_size([(ro.ids[i], i, ro.encodings[i], bool(ro.normals[i])) for i in idx]))
                for bkey, idx, pub, _ in bundles
            ]
        enc_t, pub_t = time.perf_counter() - t0, 0.0
        published = n_bundles = 0
        for i, pub, size in singles:
            try:
                a = time.perf_counter()
                buf = self._buffer(ro.keys[i], size)
                enc.write_state(buf, 0, i, ro.encodings[i], flags[i], normals(i))
                b = time.perf_counter()
                pub.put(buf)
                enc_t += b - a
                pub_t += time.perf_counter() - b
                published += 1
            except Exception as e:
                errors += 1
                log.warning("publishing cloth %s at tick %d failed: %s", ro.ids[i], job.tick, e)
        for bkey, idx, pub, size in bundles:
            try:
                a = time.perf_counter()
                buf = self._buffer(bkey, size)
                enc.write_bundle(buf, [(ro.ids[i], i, ro.encodings[i], flags[i], normals(i)) for i in idx])
                b = time.perf_counter()
                pub.put(buf)
                enc_t += b - a
                pub_t += time.perf_counter() - b
                published += len(idx)
                n_bundles += 1
            except Exception as e:
                errors += len(idx)
                log.warning("publishing bundle %s at tick %d failed: %s", bkey, job.tick, e)
        self.timers["encode"].add(enc_t)
        self.timers["publish"].add(pub_t)
        self.last_cost_s = enc_t + pub_t
        self.registry.count_many(published=published, unwatched=unwatched, publish_errors=errors, bundles=n_bundles)

    def _publish_encoded(self, job: Job) -> None:
        """Put each publication's slice of the device-encoded frame (one ``bytes`` copy each:
        zenoh's ZBytes takes no memoryview; the cheapest correct way, see issue 10's figures).
        Measured against it on the H100 (docs/loadtest.md, session 12): copying into a
        ``bytearray`` kept per key doubled the copy and put phases (3.5 -> 6.1 and 9.8 -> 17.4
        ms a tick at 2048 float32), and putting from 4 threads ran 24.8 Hz instead of 56.7 at
        4096 quant16 (every put gives the GIL back and waits to take it again)."""
        ro, enc = job.roster, job.encoded
        assert ro is not None and enc is not None
        copy_t = pub_t = 0.0
        published = unwatched = errors = n_bundles = 0
        for (ident, key, idx, bundle), view in zip(ro.publications(), enc.views, strict=True):
            try:
                pub = self._publisher(self._bundle_pubs if bundle else self._pubs, ident, key, len(view))
                # nobody subscribed: skip the copy and the put (zenoh's stub types matching_status as bool)
                if not pub.matching_status.matching:  # type: ignore[attr-defined]
                    unwatched += len(idx)
                    continue
                a = time.perf_counter()
                payload = bytes(view)
                b = time.perf_counter()
                pub.put(payload)
                copy_t += b - a
                pub_t += time.perf_counter() - b
                published += len(idx)
                n_bundles += bundle
            except Exception as e:
                errors += len(idx)
                log.warning("publishing %s at tick %d failed: %s", ident, job.tick, e)
        self.timers["encode"].add(copy_t)
        self.timers["publish"].add(pub_t)
        self.last_cost_s = copy_t + pub_t
        self.registry.count_many(published=published, unwatched=unwatched, publish_errors=errors, bundles=n_bundles)
