"""One cloth's stream of states as a client receives them (PROTOCOL.md 9.2, 1.5): states of the
stateless encodings decode alone; a predictive state decodes against the last two states this
stream rebuilt, when they are the ones it names (``ref_tick``, ``ref2_tick``). A state predicted
from one the stream lacks (a lost state, a late joiner) cannot be decoded: it is counted, the
stream says it needs a keyframe, and :meth:`StateStream.extrapolate` gives the last state
carried forward at its velocity instead: never garbage."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import ERR_INVALID_VALUE, ERR_MALFORMED, ProtocolError
from .predictive import ORDER_INTRA, ORDER_LINEAR, History, dequantise, frame_unsymbols, prediction, unpack_frame
from .state import (
    FLAG_NORMALS,
    ClothState,
    PredictiveHeader,
    decode_state,
    read_predictive_header,
    read_state_header,
    snorm16_decode_many,
)
from .vocabulary import ENC_PREDICTIVE


@dataclass
class StateStream:
    """Decodes one cloth's states in the order they arrive; counts what it could not show."""

    cloth: str = ""
    history: History = field(default_factory=History)
    step: float = 0.0  # the predictive states' step (a new step needs a keyframe)
    decoded: int = 0  # states decoded
    undecodable: int = 0  # predictive states whose reference this stream lacked
    keyframes: int = 0  # intra-coded states decoded
    needs_keyframe: bool = False  # since the last undecodable state, until a keyframe
    last: ClothState | None = None  # the last two states decoded (extrapolate's velocity)
    before_last: ClothState | None = None

    def decode(self, data: bytes | bytearray | memoryview, receive_time_ns: int = 0) -> ClothState | None:
        """The state of ``data`` (the stream moves on), or None when it is predicted from a state
        this stream does not hold (``needs_keyframe`` is then set). ProtocolError as
        :func:`decode_state` raises it."""
        buf = data if isinstance(data, (bytes, bytearray)) else memoryview(data).cast("B")
        hsize, enc, flags, n, tick, t_ns, *b = read_state_header(buf, len(buf))
        if enc != ENC_PREDICTIVE:
            return self._keep(decode_state(buf, self.cloth, receive_time_ns))
        return decode_predictive_many(buf, [0], [self], receive_time_ns)[0]  # one code path for one or many

    def holds_references(self, ph: PredictiveHeader) -> bool:
        """Whether this stream holds the states a predictive state of header ``ph`` is predicted
        from (a keyframe needs none); else it counts the state as undecodable."""
        h = self.history
        have = ph.order == ORDER_INTRA or (
            ph.step == self.step
            and h.q1 is not None
            and h.tick1 == ph.ref_tick
            and (ph.order < ORDER_LINEAR or (h.q2 is not None and h.tick2 == ph.ref2_tick))
        )
        if not have:
            self.undecodable += 1
            self.needs_keyframe = True
        return have

    def _keep(self, st: ClothState) -> ClothState:
        self.decoded += 1
        self.before_last, self.last = self.last, st
        return st

    def extrapolate(self, tick: int, server_time_ns: int = 0, receive_time_ns: int = 0) -> ClothState | None:
        """The last state decoded carried to ``tick`` at the velocity of the last two (the last
        state itself when there is one only; None before any): what to show for a state that
        could not be decoded. Marked ``extrapolated``."""
        last, prev = self.last, self.before_last
        if last is None:
            return None
        pos = last.positions
        if prev is not None and last.tick > prev.tick and tick > last.tick:
            rate = (tick - last.tick) / (last.tick - prev.tick)
            pos = (last.positions + (last.positions - prev.positions) * np.float32(rate)).astype(np.float32)
        return replace(
            last,
            tick=tick,
            server_time_ns=server_time_ns or last.server_time_ns,
            positions=pos,
            receive_time_ns=receive_time_ns,
            extrapolated=True,
        )


def decode_predictive_many(
    data: bytes | bytearray | memoryview,
    offsets: list[int],
    streams: list[StateStream],
    receive_time_ns: int = 0,
) -> list[ClothState | None]:
    """Many predictive states at once (a bundle's): the state at ``offsets[i]`` of ``data``
    (a multiple of 4) decoded by ``streams[i]`` exactly as :meth:`StateStream.decode` would, but
    with one :func:`~.predictive.unpack_frame` over all of them. None for a state whose stream
    lacks its reference (counted, as decode counts it); ProtocolError when a header is invalid."""
    buf = data if isinstance(data, (bytes, bytearray)) else memoryview(data).cast("B")
    out: list[ClothState | None] = [None] * len(offsets)
    go: list[tuple[int, int, int, int, int, int, tuple, PredictiveHeader]] = []
    for k, (at, st) in enumerate(zip(offsets, streams, strict=True)):
        hsize, enc, flags, n, tick, t_ns, *b = read_state_header(buf, len(buf) - at, at)
        if enc != ENC_PREDICTIVE:
            raise ProtocolError(ERR_INVALID_VALUE, f"state {k} is not predictive")
        ph = read_predictive_header(buf, at)
        if not st.holds_references(ph):
            continue
        go.append((k, at + hsize, n, flags, tick, t_ns, tuple(b), ph))
    if not go:
        return out
    counts = np.array([g[2] for g in go], np.int64)
    try:
        z, sizes = unpack_frame(buf, np.array([g[1] for g in go], np.int64), counts)
    except ValueError as e:
        for g in go:
            streams[g[0]].history.clear()
            streams[g[0]].needs_keyframe = True
        raise ProtocolError(ERR_MALFORMED, f"predictive states: {e}") from None
    parts = [prediction(g[7].order, streams[g[0]].history.q1, streams[g[0]].history.q2, (g[2], 3)) for g in go]
    q = frame_unsymbols(z, np.concatenate(parts) if len(parts) > 1 else parts[0], counts)
    x = dequantise(q, np.repeat(np.array([g[7].step for g in go], np.float32), counts)[:, None])
    rows = 0
    for (k, data_at, n, flags, tick, t_ns, bb, ph), size in zip(go, sizes.tolist(), strict=True):
        st = streams[k]
        qi = q[rows : rows + n]
        if ph.order == ORDER_INTRA:
            st.history.clear()
            st.keyframes += 1
            st.needs_keyframe = False
        st.history.push(qi, tick)
        st.step = ph.step
        normals = None
        if flags & FLAG_NORMALS:
            normals = snorm16_decode_many(np.frombuffer(buf, "<i2", n * 3, data_at + size).reshape(n, 3))
        bounds = ((bb[0], bb[1], bb[2]), (bb[3], bb[4], bb[5]))
        state = ClothState(
            tick, t_ns, x[rows : rows + n], normals, receive_time_ns, "predictive", flags, bounds, st.cloth
        )
        out[k] = st._keep(state)
        rows += n
    return out
