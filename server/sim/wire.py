"""A tick's output as wire-ready bytes: what ``World.fetch_async(roster, tick)`` gives.

``World.fetch_async`` returns a :class:`PendingWire` at once (the step and its readback, or
its device encoding, still in flight); ``wait()`` gives a :class:`Wire`: one payload per
publication of the :class:`~drape.server.sim.roster.Roster` (a state or a bundle, in
``Roster.publications()`` order), exactly the bytes :mod:`drape.client.protocol` encodes, and
what the tick thread needs before they go out: the cloths whose state is not finite
(:meth:`Wire.nonfinite`), put back at rest in the frame with the reset flag by
:meth:`Wire.reset` once the World has reset them.

Two kinds, picked by the World (the caller never branches):

- :class:`HostWire` (here): the frame's positions read back to the host and encoded by
  :mod:`.statecodec` when the publisher asks for the payloads (on its thread, only those
  someone subscribes to);
- ``DeviceWire`` (opencl/devencode.py): every payload encoded on the device right behind the
  step and read back once into pinned memory (an OpenCL World built with ``device_encode``).

The payloads' bytes are valid until the next ``payloads`` of the same World (host buffers per
key are reused) or until :meth:`Wire.release`.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping

import numpy as np

from drape.client import protocol as P

from .fabric import Fabric
from .frame import Frame, PendingFrame
from .roster import Roster
from .shared import vertex_normals
from .statecodec import FrameEncoder, PredictiveStreams, bundle_bytes, state_bytes

log = logging.getLogger(__name__)

Payload = bytes | bytearray | None  # a publication's bytes as they are put (None: it failed)


class Wire(ABC):
    """One tick's publications of ``roster`` (``frame``: its layout; rows on the host path only)."""

    def __init__(self, frame: Frame, roster: Roster, tick: int) -> None:
        self.frame, self.roster, self.tick = frame, roster, tick
        self.time_ns = 0
        self.flags = np.zeros(len(roster.ids), np.int64)  # per cloth state flags (FLAG_RESET)

    def set_time(self, time_ns: int) -> None:
        """The server time of every header (PROTOCOL.md: when the tick was read back)."""
        self.time_ns = int(time_ns)

    def add_flags(self, cloths: np.ndarray, flag: int) -> None:
        """OR ``flag`` into the states of frame cloths ``cloths``."""
        self.flags[cloths] |= flag

    def carry_flags(self, older: Wire) -> None:
        """A dropped older frame's reset flags, not lost with it (same roster only)."""
        if older.roster.version == self.roster.version:
            bad = np.flatnonzero(older.flags & P.FLAG_RESET)
            if len(bad):
                self.add_flags(bad, P.FLAG_RESET)

    def after_dropped(self, older: Wire) -> None:
        """On the tick thread, once this frame is back and before the next step: ``older``, the
        frame before it, was dropped whole (the publisher never took it). Its reset flags are
        carried; a device-encoded frame codes its predictive states again against the last
        states sent (the host path codes them only when they are taken)."""
        self.carry_flags(older)

    @abstractmethod
    def nonfinite(self) -> np.ndarray:
        """Frame indices of the cloths whose state is not finite."""

    @abstractmethod
    def reset(self, cloths: list[tuple[int, Fabric]]) -> None:
        """These (frame index, fabric) cloths at their rest pose, with the reset flag (the World
        has reset those it keeps)."""

    @abstractmethod
    def sizes(self) -> list[int]:
        """Each publication's payload size (for a predictive state, the most it can take)."""

    @abstractmethod
    def payloads(self, watched: list[int], streams: PredictiveStreams) -> Iterator[tuple[int, Payload]]:
        """(publication index, payload) of the ``watched`` publications, in order, encoded as
        they are taken; None for one that failed (logged). ``streams``: the service's predictive
        streams (statecodec's docstring says why the World does not keep them)."""

    def rate_payloads(
        self, every: int, watched: list[int], streams: PredictiveStreams
    ) -> Iterator[tuple[int, Payload]]:
        """1.8: (publication index, payload) of the ``watched`` publications' rate-``every``
        keys this tick (``streams``: that rate's own predictive streams); a publication it cannot
        serve this tick is left out. The host path codes them as the full rate's."""
        return self.payloads(watched, streams)

    def watch_rates(self, watching: Callable[[], Mapping[int, Mapping[str, int]]]) -> None:
        """1.8: where the publications watched per rate are read (a device-encoded World plans
        their decimated streams from it); the host path needs nothing."""
        return None

    def hold(self) -> Wire:
        """Keep this tick's host memory from reuse until :meth:`release`."""
        self.frame.hold()
        return self

    def release(self) -> None:
        self.frame.release()


class PendingWire:
    """A tick's output still in flight: ``wait()`` gives its :class:`Wire` (once made, the same)."""

    def __init__(self, pending: PendingFrame, make: Callable[[Frame], Wire]) -> None:
        self._pending, self._make = pending, make
        self._wire: Wire | None = None

    def wait(self) -> Wire:
        if self._wire is None:
            self._wire = self._make(self._pending.wait())
        return self._wire

    @property
    def device_s(self) -> float | None:
        """Device time from the start of the step to the end of the readback (after wait)."""
        return self._pending.device_s


class KeyBuffers:
    """The host path's payload buffers, one per key, reused from tick to tick (Zenoh copies a
    ``bytearray`` when it is put); those of keys no longer published are dropped when the
    roster changes."""

    def __init__(self) -> None:
        self._buffers: dict[str, bytearray] = {}
        self._version: tuple[int, int] | None = None

    def follow(self, roster: Roster) -> None:
        if roster.version == self._version:
            return
        self._version = roster.version
        live = {key for _, key, _, _ in roster.publications()}
        for key in [k for k in self._buffers if k not in live]:
            del self._buffers[key]

    def get(self, key: str, size: int) -> bytearray:
        buf = self._buffers.get(key)
        if buf is None or len(buf) != size:
            buf = self._buffers[key] = bytearray(size)
        return buf


class HostWire(Wire):
    """A frame read back to the host, encoded by statecodec.FrameEncoder when taken."""

    def __init__(self, frame: Frame, roster: Roster, tick: int, buffers: KeyBuffers) -> None:
        super().__init__(frame, roster, tick)
        self._buffers = buffers

    def nonfinite(self) -> np.ndarray:
        return self.frame.nonfinite()

    def reset(self, cloths: list[tuple[int, Fabric]]) -> None:
        frame = self.frame
        off = frame.offsets
        for i, fabric in cloths:
            sl = slice(int(off[i]), int(off[i + 1]))
            frame.xyz[sl] = fabric.rest_positions
            if frame.nxyz is not None and frame.layout.normals[i]:
                frame.nxyz[sl] = vertex_normals(fabric.rest_positions, fabric)[0]
            self.flags[i] |= P.FLAG_RESET

    def sizes(self) -> list[int]:
        ro = self.roster
        counts = np.diff(self.frame.offsets).tolist()
        nrm = ro.normals.tolist()
        return [
            bundle_bytes([(ro.ids[i], state_bytes(counts[i], ro.encodings[i], nrm[i])) for i in idx])
            if bundle
            else state_bytes(counts[idx[0]], ro.encodings[idx[0]], nrm[idx[0]])
            for _, _, idx, bundle in ro.publications()
        ]

    def payloads(self, watched: list[int], streams: PredictiveStreams) -> Iterator[tuple[int, Payload]]:
        ro, frame = self.roster, self.frame
        pubs = ro.publications()
        self._buffers.follow(ro)
        enc = FrameEncoder(streams=streams)
        enc.begin(self.tick, self.time_ns, frame.xyz, frame.offsets)
        flags = self.flags.tolist()
        off, nxyz = frame.offsets, frame.nxyz

        def normals(i: int) -> np.ndarray | None:
            return nxyz[off[i] : off[i + 1]] if nxyz is not None and ro.normals[i] else None

        selected = [i for j in watched for i in pubs[j][2]]
        enc.prepare(selected, ro.encodings)
        if ro.predictive:  # 1.5: each predictive cloth coded against its stream
            enc.prepare_predictive(selected, ro.ids, ro.encodings, ro.steps, flags)
            chosen = set(selected)
            streams.forget([ro.ids[i] for i, e in enumerate(ro.encodings) if e == P.ENC_PREDICTIVE and i not in chosen])
        for j in watched:
            _, key, idx, bundle = pubs[j]
            try:
                if bundle:
                    buf = self._buffers.get(
                        key, enc.bundle_size([(ro.ids[i], i, ro.encodings[i], bool(ro.normals[i])) for i in idx])
                    )
                    enc.write_bundle(buf, [(ro.ids[i], i, ro.encodings[i], flags[i], normals(i)) for i in idx])
                else:
                    i = idx[0]
                    buf = self._buffers.get(key, enc.state_size(i, ro.encodings[i], bool(ro.normals[i])))
                    enc.write_state(buf, 0, i, ro.encodings[i], flags[i], normals(i))
            except Exception as e:
                log.warning("encoding %s at tick %d failed: %s", key, self.tick, e)
                yield j, None
                continue
            yield j, buf
