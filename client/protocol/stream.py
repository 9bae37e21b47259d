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
from .keys import PROTOCOL_MAJOR
from .predictive import (
    ORDER_INTRA,
    ORDER_LINEAR,
    History,
    _frame_blocks,
    blocks_unsymbols,
    frame_unsymbols,
    prediction,
    unpack_blocks,
)
from .state import (
    FLAG_NORMALS,
    PREDICTIVE_HEADER_FIELDS,
    PREDICTIVE_HEADER_SIZE,
    STATE_HEADER_FIELDS,
    STATE_MAGIC,
    ClothState,
    PredictiveHeader,
    decode_state,
    header_dtype,
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
    rows: tuple[int, int] = (-1, -1)  # the rows of the frames (decode_predictive_many) q1, q2 are

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
        return self._holds(ph.order, ph.step, ph.ref_tick, ph.ref2_tick)

    def _holds(self, order: int, step: float, ref_tick: int, ref2_tick: int) -> bool:
        h = self.history
        have = order == ORDER_INTRA or (
            step == self.step
            and h.q1 is not None
            and h.tick1 == ref_tick
            and (order < ORDER_LINEAR or (h.q2 is not None and h.tick2 == ref2_tick))
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
    with one :func:`~.predictive.unpack_blocks` over all of them and, for like cloths (one vertex
    count), one numpy pass per step over the whole frame (predictions, sums, positions); each
    state's positions and each stream's history are views of the frame's arrays (no per-state
    copy). None for a state whose stream lacks its reference (counted, as decode counts it);
    ProtocolError when a header is invalid."""
    buf = data if isinstance(data, (bytes, bytearray)) else memoryview(data).cast("B")
    out: list[ClothState | None] = [None] * len(offsets)
    heads = _headers(buf, offsets)
    if heads is None:  # one breaks a reading rule: read each alone, which raises the right error
        heads = [_header(buf, at, k) for k, at in enumerate(offsets)]
    go: list[tuple] = []
    for k, (st, head) in enumerate(zip(streams, heads, strict=True)):
        if st._holds(head[6], head[7], head[8], head[9]):
            go.append((k, offsets[k] + head[0], *head[1:]))
    if not go:
        return out
    counts = np.array([g[3] for g in go], np.int64)
    try:
        blocks, sizes = unpack_blocks(buf, np.array([g[1] for g in go], np.int64), counts, scratch=True)
    except ValueError as e:
        for g in go:
            streams[g[0]].history.clear()
            streams[g[0]].needs_keyframe = True
        raise ProtocolError(ERR_MALFORMED, f"predictive states: {e}") from None
    n0 = go[0][3]
    steps = [g[8] for g in go]
    step: float | np.ndarray = steps[0] if steps.count(steps[0]) == len(steps) else np.array(steps, np.float32)
    if (counts == n0).all():  # like cloths: (C, n, 3) frames
        q = blocks_unsymbols(blocks, n0, _predictions(go, streams, n0), out=None)
        x = _positions(q, step if isinstance(step, float) else step[:, None, None])
        views = [(q[c], x[c]) for c in range(len(go))]
    else:
        layout = _frame_blocks(counts)
        z = blocks[layout[3], layout[4]]
        parts = [prediction(g[7], streams[g[0]].history.q1, streams[g[0]].history.q2, (g[3], 3)) for g in go]
        q = frame_unsymbols(z, np.concatenate(parts) if len(parts) > 1 else parts[0], counts)
        x = _positions(q, step if isinstance(step, float) else np.repeat(step, counts)[:, None])
        ends = np.cumsum(counts).tolist()
        views = [(q[e - g[3] : e], x[e - g[3] : e]) for e, g in zip(ends, go, strict=True)]
    for c, ((k, data_at, flags, n, tick, t_ns, bounds, order, step_, _, _), size, (qi, xi)) in enumerate(
        zip(go, sizes.tolist(), views, strict=True)
    ):
        st = streams[k]
        h = st.history
        if order == ORDER_INTRA:
            h.clear()
            st.keyframes += 1
            st.needs_keyframe = False
        h.q2, h.tick2, h.q1, h.tick1 = h.q1, h.tick1, qi, tick  # History.push
        st.rows = (c, st.rows[0])
        st.step = step_
        normals = None
        if flags & FLAG_NORMALS:
            normals = snorm16_decode_many(np.frombuffer(buf, "<i2", n * 3, data_at + size).reshape(n, 3))
        state = ClothState(tick, t_ns, xi, normals, receive_time_ns, "predictive", flags, bounds, st.cloth)
        st.decoded += 1  # StateStream._keep
        st.before_last, st.last = st.last, state
        out[k] = state
    return out


#: A predictive state's whole header (PROTOCOL.md 9.2): many read at once.
_PREDICTIVE_DTYPE = header_dtype(STATE_HEADER_FIELDS + PREDICTIVE_HEADER_FIELDS)


def _headers(buf: bytes | bytearray | memoryview, offsets: list[int]) -> list[tuple] | None:
    """The headers of the predictive states at ``offsets``, all read at once: per state
    (header_size, flags, n, tick, server time, bounds, order, step, ref tick, ref2 tick); None
    when one of them breaks any of the reading rules :func:`_header` checks."""
    at = np.asarray(offsets, np.int64)
    size = len(buf) - at
    if not len(at) or int(size.min()) < PREDICTIVE_HEADER_SIZE:
        return None
    raw = np.frombuffer(buf, np.uint8)
    h = raw[at[:, None] + np.arange(PREDICTIVE_HEADER_SIZE)].view(_PREDICTIVE_DTYPE)[:, 0]
    n, flags, hsize, step = h["vertex_count"], h["flags"], h["header_size"], h["step"]
    need = hsize + h["data_size"].astype(np.int64) + 6 * n.astype(np.int64) * (flags & FLAG_NORMALS)
    if not (
        (h["magic"] == STATE_MAGIC).all()
        and (h["major"] == PROTOCOL_MAJOR).all()
        and (hsize >= PREDICTIVE_HEADER_SIZE).all()
        and (h["encoding"] == ENC_PREDICTIVE).all()
        and (need <= size).all()
        and (h["order"] <= ORDER_LINEAR).all()
        and (np.isfinite(step) & (step > 0)).all()
    ):
        return None
    lo, hi = h["bounds_min"].tolist(), h["bounds_max"].tolist()
    return list(
        zip(
            hsize.tolist(),
            flags.tolist(),
            n.tolist(),
            h["tick"].tolist(),
            h["server_time_ns"].tolist(),
            [(tuple(a), tuple(b)) for a, b in zip(lo, hi, strict=True)],
            h["order"].tolist(),
            step.tolist(),
            h["ref_tick"].tolist(),
            h["ref2_tick"].tolist(),
            strict=True,
        )
    )


def _header(buf: bytes | bytearray | memoryview, at: int, k: int) -> tuple:
    """One predictive state's header as :func:`_headers` gives it, read by the reading rules
    (ProtocolError for the first it breaks)."""
    hsize, enc, flags, n, tick, t_ns, *b = read_state_header(buf, len(buf) - at, at)
    if enc != ENC_PREDICTIVE:
        raise ProtocolError(ERR_INVALID_VALUE, f"state {k} is not predictive")
    ph = read_predictive_header(buf, at)
    bounds = ((b[0], b[1], b[2]), (b[3], b[4], b[5]))
    return (hsize, flags, n, tick, t_ns, bounds, ph.order, ph.step, ph.ref_tick, ph.ref2_tick)


def _predictions(go: list, streams: list[StateStream], n: int) -> np.ndarray:
    """(C, n, 3) int32 predictions of like cloths: ``2 q1 - q2`` of the whole frame at once where
    the streams' last two states are the rows of two earlier frames in this order (a bundle's
    steady state), each other cloth's alone."""
    p = np.empty((len(go), n, 3), np.int32)
    h0 = streams[go[0][0]].history
    b1 = h0.q1.base if h0.q1 is not None else None
    b2 = h0.q2.base if h0.q2 is not None else None
    whole = False
    if b1 is not None and b2 is not None and b1.shape == b2.shape == p.shape and b1.dtype == b2.dtype == p.dtype:
        np.left_shift(b1, 1, out=p)
        p -= b2
        whole = True
    for c, g in enumerate(go):
        st = streams[g[0]]
        h = st.history
        if (
            whole
            and g[7] == ORDER_LINEAR
            and st.rows == (c, c)
            and h.q1 is not None
            and h.q1.base is b1
            and h.q2 is not None
            and h.q2.base is b2
        ):
            continue
        p[c] = prediction(g[7], h.q1, h.q2, (n, 3))
    return p


def _positions(q: np.ndarray, step: float | np.ndarray) -> np.ndarray:
    """:func:`~.predictive.dequantise` in one pass: ``float32(float64(q) * float64(step))``."""
    x = np.empty(q.shape, np.float32)
    s = np.float64(np.float32(step)) if isinstance(step, float) else np.asarray(step, np.float32).astype(np.float64)
    np.multiply(q, s, out=x, dtype=np.float64, casting="unsafe")
    return x
