"""The host encoder: one tick's states of many cloths encoded at once on the CPU (the reference
World's frames, and an OpenCL World's when its states are not encoded on the device).

A frame holds every cloth's positions back to back in one contiguous float32 array
(``positions``, with ``offsets[i]:offsets[i + 1]`` the vertices of cloth ``i``).
:class:`FrameEncoder` then works per frame, not per cloth (wire.HostWire drives it on the
publisher's thread):

- bounds of every cloth in two calls (``np.minimum.reduceat`` / ``np.maximum.reduceat``);
- float16 and quant16 vertex blocks computed for all the cloths that use them in one pass;
- per cloth only the 64-byte header (``struct.pack_into``) and one ``memcpy`` of its block into
  an output buffer that the caller reuses from tick to tick (Zenoh copies a ``bytearray`` when
  it is put, so a buffer may be rewritten as soon as ``put`` returns).

Predictive states (protocol 1.5) are coded per stream against the last two states its decoders
rebuilt (:class:`PredictiveStreams`): a keyframe when a stream starts, every
``keyframe_interval`` ticks, after a reset, a new step or a tick the stream was not encoded
(nobody watched it), and when a subscriber asks (:meth:`PredictiveStreams.request`). The
streams are the service's state, not the World's: they live as long as the service publishes
(across Worlds), keyframe queries reach them from the network's threads, and which streams were
encoded depends on who subscribes; so the encoder takes them as an argument.

The bytes are exactly those of :func:`drape.client.protocol.encode_state` and
:func:`drape.client.protocol.encode_bundle` (tests/service/test_bundles.py checks that for every encoding):
every layout number, size and the float16 / quant16 / snorm16 arithmetic come from the protocol
package (``drape.client.protocol.state`` and ``.bundle``); only the batching over cloths is here.
"""

from __future__ import annotations

import threading
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drape.client import protocol as P

_ENTRY_PAD = bytes(P.BUNDLE_ALIGN)


def state_bytes(n: int, encoding: int, normals: bool) -> int:
    """Size of one encoded state of ``n`` vertices (protocol.state_size)."""
    return P.state_size(n, encoding, normals)


def bundle_bytes(entries: list[tuple[str, int]]) -> int:
    """Size of a bundle of (cloth id, state size) entries."""
    return P.BUNDLE_HEADER_SIZE + sum(P.bundle_entry_header_size(c) + P.align8(n) for c, n in entries)


#: A requested keyframe waits until this many ticks have passed since the stream's last one
#: (requests from many subscribers, or a hostile one asking every tick, cost one keyframe).
MIN_REQUESTED_GAP = 6


def keyframe_rule(
    tick: Any, key_tick: Any, step: Any, old_step: Any, reset: Any, requested: Any, interval: int
) -> tuple[Any, Any]:
    """The one copy of the keyframe rules (the host's streams and the device encoder's, one
    cloth's scalars or a whole frame's arrays alike): (keyframe due, request kept for a later
    tick). A keyframe when a stream starts (its ``key_tick`` far in the past, its ``old_step``
    0), every ``interval`` ticks, after a reset, on a new step and when a subscriber asked
    (at most one every :data:`MIN_REQUESTED_GAP` ticks: an earlier request is kept)."""
    since = tick - key_tick
    granted = requested & (since >= MIN_REQUESTED_GAP)
    return granted | reset | (step != old_step) | (since >= interval), requested ^ granted


def stream_phase(cloth: str, interval: int) -> int:
    """Ticks a new stream's periodic keyframes are shifted by (its key tick is set this much in
    the past): cloths added together do not all send theirs in one tick (16 capes' keyframes at
    once queued 110 ms on a 20 Mbit/s link)."""
    return zlib.crc32(cloth.encode()) % interval


@dataclass(eq=False)
class _Stream:
    """One predictive stream: the decoders' last two states, its step and its last keyframe."""

    history: P.History = field(default_factory=P.History)
    step: float = 0.0
    key_tick: int = -(1 << 62)


class PredictiveStreams:
    """Every predictive cloth's stream (by cloth id), kept from frame to frame by the publisher.
    ``request`` may be called from any thread (a keyframe query); the rest from the publisher's."""

    MIN_REQUESTED_GAP = MIN_REQUESTED_GAP

    def __init__(self, keyframe_interval: int = 60) -> None:
        self.keyframe_interval = keyframe_interval
        self.streams: dict[str, _Stream] = {}
        self._requested: set[str] = set()
        self._lock = threading.Lock()
        self.keyframes = 0  # intra-coded states written (the stats' keyframes)

    def request(self, cloths: list[str]) -> None:
        """The next state of each of these cloths' streams is a keyframe."""
        with self._lock:
            self._requested.update(cloths)

    def take_requests(self) -> set[str]:
        with self._lock:
            out, self._requested = self._requested, set()
        return out

    def start(self, cloth: str, tick: int, step: float, reset: bool, requested: bool) -> tuple[_Stream, int]:
        """The stream of ``cloth`` about to code its state at ``tick``, and that state's order
        (0: a keyframe, when due (:func:`keyframe_rule`); the stream's history then starts afresh)."""
        s = self.streams.get(cloth)
        new = s is None
        if s is None:
            s = self.streams[cloth] = _Stream()
        keyframe, kept = keyframe_rule(tick, s.key_tick, step, s.step, reset, requested, self.keyframe_interval)
        if kept:
            self.request([cloth])  # kept for a later tick
        if keyframe:
            s.key_tick, s.step = tick, step
            s.history.clear()
            self.keyframes += 1
        if new:
            s.key_tick = tick - stream_phase(cloth, self.keyframe_interval)
        return s, s.history.order()

    def keep_only(self, cloths: set[str]) -> None:
        """Forget the streams of cloths that are gone."""
        for c in [c for c in self.streams if c not in cloths]:
            del self.streams[c]

    def forget(self, cloths: list[str]) -> None:
        """These streams were not encoded this tick (nobody watched): whoever subscribes next
        starts from a keyframe."""
        for c in cloths:
            self.streams.pop(c, None)


@dataclass(eq=False)
class _Group:
    """The encoded vertex blocks of the cloths of one encoding, back to back."""

    data: memoryview  # bytes
    start: dict[int, int] = field(default_factory=dict)  # cloth index -> byte offset in data


class FrameEncoder:
    """Encode the states of one frame (call :meth:`begin`, then :meth:`prepare` with the cloths
    that will be written, then :meth:`write_state` / :meth:`write_bundle` for each)."""

    def __init__(self, keyframe_interval: int = 60, streams: PredictiveStreams | None = None) -> None:
        self.streams = streams if streams is not None else PredictiveStreams(keyframe_interval)
        self._coded: dict[int, tuple[bytes, int, int, int, float]] = {}  # predictive: frame index -> data
        self.tick = 0
        self.time_ns = 0
        self._positions = np.zeros((0, 3), np.float32)
        self._offsets = np.zeros(1, np.int64)
        self._counts: list[int] = []
        self._lo: list[list[float]] = []
        self._hi: list[list[float]] = []
        self._groups: dict[int, _Group] = {}
        self._ids: dict[str, bytes] = {}

    def begin(self, tick: int, time_ns: int, positions: np.ndarray, offsets: np.ndarray) -> None:
        """A new frame: ``positions`` (N, 3) float32 C-contiguous, ``offsets`` (k + 1,) with
        every cloth non-empty."""
        pos = np.ascontiguousarray(positions, dtype="<f4")
        self.tick, self.time_ns = int(tick), int(time_ns)
        self._positions = pos.reshape(-1, 3)
        self._offsets = np.asarray(offsets, np.int64)
        self._counts = np.diff(self._offsets).tolist()
        self._lo, self._hi = [], []
        self._groups = {}
        self._coded = {}

    def prepare(self, cloths: list[int], encodings: list[int]) -> None:
        """Compute bounds and vertex blocks for ``cloths`` (indices into the frame), whose
        encodings are ``encodings`` (protocol ids, one per cloth of the frame)."""
        pos, off = self._positions, self._offsets
        k = len(off) - 1
        if not cloths or not k:
            return
        starts = off[:-1]
        cols = np.ascontiguousarray(pos.T)  # (3, N): reduceat runs faster along contiguous rows
        lo = np.minimum.reduceat(cols, starts, axis=1).T
        hi = np.maximum.reduceat(cols, starts, axis=1).T
        self._lo, self._hi = lo.tolist(), hi.tolist()
        by_enc: dict[int, list[int]] = {}
        for i in cloths:
            by_enc.setdefault(encodings[i], []).append(i)
        for enc, idx in by_enc.items():
            if enc == P.ENC_PREDICTIVE:  # coded per stream: prepare_predictive
                continue
            idx = sorted(set(idx))
            if len(idx) == k:  # every cloth: the frame as is
                src, local = pos, off
            else:
                src = (
                    np.concatenate([pos[off[i] : off[i + 1]] for i in idx])
                    if len(idx) > 1
                    else pos[off[idx[0]] : off[idx[0] + 1]]
                )
                counts = np.array([self._counts[i] for i in idx], np.int64)
                local = np.zeros(len(idx) + 1, np.int64)
                np.cumsum(counts, out=local[1:])
            es = P.element_size(enc)
            if enc == P.ENC_FLOAT32:
                block = src
            elif enc == P.ENC_FLOAT16:
                block = P.float16_values(src)
            else:
                block = np.empty((len(src), 3), "<u2")
                _quantise(src, lo[idx], hi[idx], np.diff(local), block)
            if len(idx) == k:
                starts_b = {i: int(off[i]) * 3 * es for i in idx}
            else:
                starts_b = {i: int(local[j]) * 3 * es for j, i in enumerate(idx)}
            # numpy's stubs give ndarray __buffer__ only for Python >= 3.12 (we check as 3.11)
            self._groups[enc] = _Group(memoryview(np.ascontiguousarray(block)).cast("B"), starts_b)  # type: ignore[arg-type]

    def prepare_predictive(
        self, cloths: list[int], ids: list[str], encodings: list[int], steps: list[float], flags: list[int]
    ) -> None:
        """Code the predictive states of ``cloths`` (after :meth:`prepare`: the bounds), each
        against its stream (one per cloth id), all in one pass over the frame
        (protocol.predictive's frame functions). Sizes are then exact (:meth:`state_size`)."""
        idx = [i for i in dict.fromkeys(cloths) if encodings[i] == P.ENC_PREDICTIVE and i not in self._coded]
        if not idx:
            return
        requested = self.streams.take_requests()
        pos, off = self._positions, self._offsets
        counts = np.array([self._counts[i] for i in idx], np.int64)
        step32 = np.array([steps[i] for i in idx], np.float32)
        x = (
            np.concatenate([pos[off[i] : off[i + 1]] for i in idx])
            if len(idx) > 1
            else pos[off[idx[0]] : off[idx[0] + 1]]
        )
        q = P.quantise(x, np.repeat(step32, counts)[:, None])
        parts, meta = [], []
        for i, n in zip(idx, counts.tolist(), strict=True):
            cid = ids[i]
            s, order = self.streams.start(cid, self.tick, steps[i], bool(flags[i] & P.FLAG_RESET), cid in requested)
            h = s.history
            parts.append(P.prediction(order, h.q1, h.q2, (n, 3)))
            meta.append((s, order, h.tick1 if order >= 1 else 0, h.tick2 if order >= 2 else 0))
        p = np.concatenate(parts) if len(parts) > 1 else parts[0]
        data, offsets = P.pack_frame(P.frame_symbols(q, p, counts), counts)
        rows = np.zeros(len(idx) + 1, np.int64)
        np.cumsum(counts, out=rows[1:])
        for j, (i, (s, order, r1, r2)) in enumerate(zip(idx, meta, strict=True)):
            s.history.push(q[rows[j] : rows[j + 1]], self.tick)
            self._coded[i] = (data[offsets[j] : offsets[j + 1]].tobytes(), order, r1, r2, float(step32[j]))

    def state_size(self, i: int, encoding: int, normals: bool) -> int:
        if encoding == P.ENC_PREDICTIVE:
            coded = self._coded.get(i)
            if coded is None:  # before prepare_predictive: the most it can take
                return state_bytes(self._counts[i], encoding, normals)
            return P.PREDICTIVE_HEADER_SIZE + len(coded[0]) + self._counts[i] * 6 * normals
        return state_bytes(self._counts[i], encoding, normals)

    def write_state(
        self, out: bytearray, at: int, i: int, encoding: int, flags: int, normals: np.ndarray | None
    ) -> int:
        """Write cloth ``i``'s state payload into ``out`` at ``at``; returns where it ends."""
        n = self._counts[i]
        flags = (flags | P.FLAG_NORMALS) if normals is not None else (flags & ~P.FLAG_NORMALS)
        if encoding == P.ENC_PREDICTIVE:
            data, order, r1, r2, step = self._coded[i]
            hs = P.PREDICTIVE_HEADER_SIZE
            P.pack_state_header(out, at, encoding, flags, n, self.tick, self.time_ns, self._lo[i], self._hi[i], hs)
            P.PREDICTIVE_HEADER.pack_into(out, at + P.STATE_HEADER_SIZE, step, order, 1, r1, r2, len(data))
            end = at + hs + len(data)
            out[at + hs : end] = data
            if normals is not None:
                P.encode_normals_into(out, end, normals, encoding)
                end += n * 6
            return end
        block = n * 3 * P.element_size(encoding)
        P.pack_state_header(out, at, encoding, flags, n, self.tick, self.time_ns, self._lo[i], self._hi[i])
        g = self._groups[encoding]
        s = g.start[i]
        p0 = at + P.STATE_HEADER_SIZE
        out[p0 : p0 + block] = g.data[s : s + block]
        end = p0 + block
        if normals is not None:
            P.encode_normals_into(out, end, normals, encoding)
            end += block
        return end

    def bundle_size(self, cloths: list[tuple[str, int, int, bool]]) -> int:
        """Bytes of a bundle of (cloth id, frame index, encoding, normals) entries."""
        return bundle_bytes([(c, self.state_size(i, e, nr)) for c, i, e, nr in cloths])

    def write_bundle(self, out: bytearray, entries: list[tuple[str, int, int, int, np.ndarray | None]]) -> int:
        """Write a bundle of (cloth id, frame index, encoding, flags, normals) entries into
        ``out`` (sized with bundle_size); returns its size."""
        P.pack_bundle_header(out, self.tick, self.time_ns, len(entries))
        at = P.BUNDLE_HEADER_SIZE
        ids = self._ids
        for cloth, i, enc, flags, nrm in entries:
            cid = ids.get(cloth)
            if cid is None:
                cid = ids[cloth] = cloth.encode("ascii")
                if len(ids) > 65536:
                    ids.clear()
            h = P.bundle_entry_header_size(cloth)
            n_state = self.state_size(i, enc, nrm is not None)
            P.BUNDLE_ENTRY.pack_into(out, at, h, len(cid), n_state)
            e = at + P.BUNDLE_ENTRY_SIZE + len(cid)
            out[at + P.BUNDLE_ENTRY_SIZE : e] = cid
            out[e : at + h] = _ENTRY_PAD[: at + h - e]
            end = self.write_state(out, at + h, i, enc, flags, nrm)
            at = P.align8(end)
            out[end:at] = _ENTRY_PAD[: at - end]  # the buffer is reused: padding must be rewritten
        return at


def _quantise(src: np.ndarray, lo: np.ndarray, hi: np.ndarray, counts: np.ndarray, out: np.ndarray) -> None:
    """quant16 of consecutive cloths (``counts`` vertices each) of ``src`` into ``out``, with the
    protocol's scale (protocol.quant16_scale) and rounding (protocol.quant16_round): exactly what
    protocol.encode_state computes, for many cloths in one pass."""
    lo64, scale = P.quant16_scale(lo, hi)
    q = src.astype(np.float64)
    if (counts == counts[0]).all():  # cloths of one size: broadcast instead of repeating
        qv = q.reshape(len(counts), int(counts[0]), 3)
        qv -= lo64[:, None, :]
        qv *= scale[:, None, :]
    else:
        q -= np.repeat(lo64, counts, axis=0)
        q *= np.repeat(scale, counts, axis=0)
    out[:] = P.quant16_round(q)
