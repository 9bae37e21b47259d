"""The predictive state encoding (for protocol 1.5; docs/codec.md): each vertex predicted from the
last two states the decoder holds, the residual quantised with a step the client chose, made
smaller by its neighbour's, and bit-packed in blocks of 32 values.

Everything is integer arithmetic on a grid of the step, so that an encoder on a GPU, this numpy
reference and a decoder in any language agree to the bit and no error accumulates (closed loop):

- ``q = clamp(rint(x * inv_step), -Q_LIMIT, Q_LIMIT)`` per coordinate, with ``x`` and
  ``inv_step = float32(1 / step)`` float32 and the product rounded to float32 (IEEE; an OpenCL
  ``*`` is exact in that sense), ``rint`` ties to even. The decoder rebuilds ``q`` exactly, and
  shows ``x' = float32(float64(q) * float64(step))``: ``|x - x'| <= step / 2`` (plus float32
  rounding, a few ulps of ``x``), at every state, forever.
- The prediction of order 0 (intra, a keyframe) is 0, of order 1 the previous state ``q1``, of
  order 2 the linear extrapolation ``2 q1 - q2`` (int32; ``Q_LIMIT`` keeps every sum in range).
- The residual ``r = q - p``, per axis, minus the previous vertex's (vertex order: rows of a grid
  follow each other): ``d[i] = r[i] - r[i - 1]``, ``d[0] = r[0]``; zig-zagged to unsigned
  ``z = (d << 1) ^ (d >> 31)``.
- The symbols are laid out axis by axis (all x, then y, then z), in blocks of 32 (the last block
  of an axis padded with zeros). A block's width ``w`` is the bit length of its largest symbol
  (0..32); the block takes ``w`` little-endian u32 words, symbol ``j`` at bits ``j*w .. j*w+w-1``
  of the block's bit string (bit ``k`` of the string is bit ``k % 32`` of word ``k / 32``).
- The packed data: ``3 * ceil(n / 32)`` width bytes, zero-padded to a multiple of 4, then every
  block's words in order. Its length is ``4 * ceil(3 * nb / 4) + 4 * sum(w)`` bytes.

``encode_residuals`` / ``decode_residuals`` are this file's two halves; ``PredictiveStream``
keeps an encoder's history of one stream, ``StreamDecoder`` a decoder's (the states it rebuilt).
A bundle's states decode together: :func:`unpack_blocks` (every value's bits in a few whole-array
passes) then, for like cloths, :func:`blocks_unsymbols` (stream.decode_predictive_many).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

#: Values per block.
BLOCK = 32
#: Grid values are clamped to +-Q_LIMIT steps (134 km at 1 mm): then 2 q1 - q2, q - p and the
#: neighbour difference all fit int32.
Q_LIMIT = (1 << 27) - 1
#: Predictor orders.
ORDER_INTRA, ORDER_PREVIOUS, ORDER_LINEAR = 0, 1, 2
#: The default step, metres (max error 0.5 mm).
DEFAULT_STEP = 0.001
#: The steps a client may choose, metres.
STEP_RANGE = (1e-5, 0.1)


def inverse_step(step: float) -> np.float32:
    """``float32(1 / step)``, computed in float64 and rounded once."""
    return np.float32(1.0 / float(np.float32(step)))


def quantise(positions: np.ndarray, step: float | np.ndarray) -> np.ndarray:
    """(n, 3) float32 positions on the step's grid: int32 ``clamp(rint(x * inv_step))``. ``step``
    may be one per row ((n, 1): many cloths' vertices at once)."""
    x = np.asarray(positions, np.float32)
    if isinstance(step, np.ndarray):  # float32(1 / step) per row, each rounded once
        inv: np.float32 | np.ndarray = (1.0 / step.astype(np.float32).astype(np.float64)).astype(np.float32)
    else:
        inv = inverse_step(step)
    q = np.rint(x * inv)  # float32 product, rounded once; rint ties to even
    np.clip(q, -(1 << 27), 1 << 27, out=q)  # exact in float32; then the int range
    return np.clip(q.astype(np.int32), -Q_LIMIT, Q_LIMIT)


def dequantise(q: np.ndarray, step: float | np.ndarray) -> np.ndarray:
    """Positions of grid values: ``float32(float64(q) * float64(step))``, ``step`` float32 (one
    per row: many cloths at once)."""
    s = np.asarray(step, np.float32).astype(np.float64)
    return (np.asarray(q, np.float64) * s).astype(np.float32)


def prediction(order: int, q1: np.ndarray | None, q2: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """The prediction of ``order`` from the last two states ``q1`` (newest) and ``q2``."""
    if order not in (ORDER_INTRA, ORDER_PREVIOUS, ORDER_LINEAR):
        raise ValueError(f"unknown predictor order {order}")
    if order == ORDER_INTRA:
        return np.zeros(shape, np.int32)
    if q1 is None:
        raise ValueError(f"order {order} needs the previous state")
    if order == ORDER_PREVIOUS:
        return q1
    if q2 is None:
        raise ValueError("order 2 needs the last two states")
    return 2 * q1 - q2


def symbols(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(3, n) uint32 zig-zagged neighbour differences of the residual ``q - p`` ((n, 3) int32):
    one cloth's :func:`frame_symbols`, axis by axis."""
    return np.ascontiguousarray(frame_symbols(q, p, np.array([len(q)], np.int64)).T)


def unsymbols(z: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The inverse of :func:`symbols`: (n, 3) int32 grid values from the symbols and prediction."""
    z = np.asarray(z, np.uint32)
    return frame_unsymbols(np.ascontiguousarray(z.T), p, np.array([z.shape[1]], np.int64))


def _widths(blocks: np.ndarray) -> np.ndarray:
    """Bit length of each block's largest value, (m,) uint8: frexp's exponent (exact: a uint32
    is a float64 exactly; 0 gives 0)."""
    top = blocks.max(axis=1) if blocks.size else np.zeros(0, np.uint32)
    return np.frexp(top.astype(np.float64))[1].astype(np.uint8)


def packed_size(n: int, widths: np.ndarray | list[int]) -> int:
    """Bytes of the packed data of n vertices whose blocks have these widths."""
    nb = -(-n // BLOCK)
    return 4 * (-(-3 * nb // 4)) + 4 * int(np.asarray(widths, np.int64).sum())


def encode_residuals(z: np.ndarray) -> bytes:
    """The packed data of (3, n) uint32 symbols (one cloth: :func:`pack_frame`)."""
    out, _ = pack_frame(np.ascontiguousarray(np.asarray(z, np.uint32).T), np.array([z.shape[1]], np.int64))
    return out.tobytes()


def frame_symbols(q: np.ndarray, p: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """:func:`symbols` of many cloths at once, back to back: ``q`` and ``p`` (N, 3) int32, cloth
    ``i`` in ``counts[i]`` consecutive rows; (N, 3) uint32 (each cloth's first vertex is not
    differenced with the cloth before it)."""
    r = q - p
    d = r.copy()
    d[1:] -= r[:-1]
    starts = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    starts = starts[np.asarray(counts) > 0]
    d[starts] = r[starts]
    return ((d << 1) ^ (d >> 31)).view(np.uint32)


def _frame_blocks(counts: np.ndarray) -> tuple[np.ndarray, ...]:
    """Where each cloth's blocks are: (blocks per axis nb, first block B, width-byte head size,
    for every vertex row and axis (N, 3) its block, each row's place in its block). Kept for the
    last few cloth layouts (a server's frames repeat one until cloths come or go)."""
    counts = np.asarray(counts, np.int64)
    key = counts.tobytes()
    hit = _LAYOUTS.get(key)
    if hit is None:
        hit = _LAYOUTS[key] = _frame_blocks_of(counts)
        while len(_LAYOUTS) > 8:
            del _LAYOUTS[next(iter(_LAYOUTS))]
    return hit


_LAYOUTS: dict[bytes, tuple[np.ndarray, ...]] = {}


def _frame_blocks_of(counts: np.ndarray) -> tuple[np.ndarray, ...]:
    nb = -(-counts // BLOCK)
    first = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(3 * nb, out=first[1:])
    head = 4 * (-(-3 * nb // 4))
    cloth = np.repeat(np.arange(len(counts)), counts)
    starts = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    local = np.arange(int(counts.sum())) - starts[cloth]
    block = (first[cloth] + local // BLOCK)[:, None] + nb[cloth][:, None] * np.arange(3)[None, :]
    return nb, first, head, block, (local % BLOCK)[:, None]


def pack_frame(z: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The packed data of many cloths at once: ``z`` (N, 3) uint32 symbols back to back (cloth
    ``i`` in ``counts[i]`` rows); (bytes as uint8, offsets (k + 1,)): cloth ``i``'s packed data
    is ``out[offsets[i]:offsets[i + 1]]``, byte for byte :func:`encode_residuals`' (every size a
    multiple of 4). Whole arrays throughout, as a GPU would: no loop over cloths."""
    counts = np.asarray(counts, np.int64)
    nb, first, head, block, j = _frame_blocks(counts)
    blocks = np.zeros((int(first[-1]), BLOCK), np.uint32)
    blocks[block, j] = z
    widths = _widths(blocks)
    wsum = np.zeros(len(widths) + 1, np.int64)
    np.cumsum(widths, out=wsum[1:])
    words = wsum[first[1:]] - wsum[first[:-1]]  # per cloth
    sizes = head + 4 * words
    offsets = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(sizes, out=offsets[1:])
    total = int(offsets[-1])
    n_words = total // 4 + 2  # + 2: a value of a block at the end may reach one word further
    out = np.zeros(4 * n_words, np.uint8)
    if len(widths):
        bcloth = np.repeat(np.arange(len(counts)), 3 * nb)  # each block's cloth
        out[offsets[bcloth] + np.arange(len(widths)) - first[bcloth]] = widths
        # each block's first word in the whole output; each value's first bit
        wbase = (offsets[bcloth] + head[bcloth]) // 4 + wsum[:-1] - wsum[first[bcloth]]
        w = widths.astype(np.int64)[:, None]
        bit = (wbase[:, None] << 5) + np.arange(BLOCK)[None, :] * w
        word, shift = (bit >> 5).ravel(), (bit & 31).ravel()
        spread = blocks.astype(np.uint64).ravel() << shift.astype(np.uint64)
        # the bits of different values never overlap: a sum is an or (exact in float64: < 2^53)
        lo = np.bincount(word, (spread & np.uint64(0xFFFFFFFF)).astype(np.float64), n_words)
        hi = np.bincount(word + 1, (spread >> np.uint64(32)).astype(np.float64), n_words)
        out.view("<u4")[:] |= (lo + hi).astype(np.uint64).astype(np.uint32)  # the width bytes' words get 0
    return out[:total], offsets


def decode_residuals(data: bytes | bytearray | memoryview, n: int, at: int = 0) -> tuple[np.ndarray, int]:
    """(3, n) uint32 symbols of the packed data at ``at`` of ``data``, and its length in bytes.
    ValueError if the data is shorter than its widths say or a width is over 32."""
    z, sizes = unpack_frame(data, np.array([at], np.int64), np.array([n], np.int64))
    return np.ascontiguousarray(z.T), int(sizes[0])


def _bit_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block width ``w`` (0..32), for each of a block's 32 values: the word of the block its
    bits start in ``(j * w) >> 5`` and the shift in it ``(j * w) & 31`` (uint8 both), and the
    width's mask (uint32)."""
    w = np.arange(BLOCK + 1, dtype=np.int64)[:, None]
    at = np.arange(BLOCK, dtype=np.int64)[None, :] * w
    mask = ((np.uint64(1) << np.arange(BLOCK + 1, dtype=np.uint64)) - np.uint64(1)).astype(np.uint32)
    return (at >> 5).astype(np.uint8), (at & 31).astype(np.uint8), mask


_WORD_OF, _SHIFT_OF, _MASK_OF = _bit_tables()


class _Scratch(threading.local):
    """Work arrays reused from one decode to the next (per thread): a fresh array of a few MB a
    call costs page faults (glibc gives large blocks back to the system when they are freed)."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        size = int(np.prod(shape))
        a = self.arrays.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            a = self.arrays[name] = np.empty(size + size // 4, dtype)
        return a[:size].reshape(shape)


_SCRATCH = _Scratch()


def unpack_blocks(
    data: bytes | bytearray | memoryview, starts: np.ndarray, counts: np.ndarray, scratch: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The symbols of many cloths' packed data in block order: ((B, 32) uint32, each cloth's
    packed size), cloth ``i``'s at byte ``starts[i]`` (a multiple of 4), of ``counts[i]``
    vertices; its ``3 * ceil(counts[i] / 32)`` blocks (all x, then y, then z; the padding values
    0) follow the cloth before's. One pass per step over all values: each value's 64-bit window
    (two words, paired once) gathered, shifted by its block width's precomputed shift, masked.
    ``scratch``: the symbols are this thread's work array, valid until its next call. ValueError
    if a cloth's data runs past the end or a width is over 32."""
    buf = memoryview(data).cast("B")
    starts = np.asarray(starts, np.int64)
    counts = np.asarray(counts, np.int64)
    if (starts % 4).any():
        raise ValueError("predictive data must start at a multiple of 4 bytes")
    nb, first, head = _frame_heads(counts)
    if len(buf) < int((starts + head).max(initial=0)):
        raise ValueError("predictive data is shorter than its width bytes")
    raw = np.frombuffer(buf, np.uint8)
    n_blocks = int(first[-1])
    if len(counts) and (nb == nb[0]).all():  # like cloths (a bundle's): no per-block gather of the cloth
        widths = raw[(starts[:, None] + np.arange(3 * int(nb[0]))[None, :]).ravel()]
    else:
        bcloth = np.repeat(np.arange(len(counts)), 3 * nb)
        widths = raw[starts[bcloth] + np.arange(n_blocks) - first[bcloth]]
    if widths.size and widths.max() > 32:
        raise ValueError(f"a block width of {int(widths.max())} bits (at most 32)")
    wsum = np.zeros(n_blocks + 1, np.int64)
    np.cumsum(widths, out=wsum[1:])
    sizes = head + 4 * (wsum[first[1:]] - wsum[first[:-1]])
    if len(buf) < int((starts + sizes).max(initial=0)):
        raise ValueError("predictive data is shorter than its widths say")
    sc = _SCRATCH
    n_words = len(buf) // 4
    words = sc.get("words", (n_words + 2,), np.uint64)  # a value of a block at the end may read one word further
    words[:n_words] = np.frombuffer(buf, "<u4", n_words)
    words[n_words:] = 0
    pairs = sc.get("pairs", (n_words + 1,), np.uint64)
    np.left_shift(words[1:], np.uint64(32), out=pairs)
    pairs |= words[:-1]  # every 64-bit window, once
    # each block's first word in the whole data
    base = np.repeat((starts + head) // 4 - wsum[first[:-1]], 3 * nb) + wsum[:-1]
    shape = (n_blocks, BLOCK)
    small = np.take(_WORD_OF, widths, axis=0, out=sc.get("small", shape, np.uint8))
    at = np.add(base[:, None], small, out=sc.get("at", shape, np.int64))
    window = np.take(pairs, at, out=sc.get("window", shape, np.uint64))
    np.take(_SHIFT_OF, widths, axis=0, out=small)
    z = sc.get("z", shape, np.uint32) if scratch else np.empty(shape, np.uint32)
    np.right_shift(window, small, out=z, casting="unsafe")
    z &= _MASK_OF[widths][:, None]
    return z, sizes


def _frame_heads(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blocks per axis, each cloth's first block (and the total), width-byte head size."""
    nb = -(-counts // BLOCK)
    first = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(3 * nb, out=first[1:])
    return nb, first, 4 * (-(-3 * nb // 4))


def unpack_frame(
    data: bytes | bytearray | memoryview, starts: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`pack_frame` for packed data anywhere in ``data``: cloth ``i``'s at
    byte ``starts[i]`` (a multiple of 4), of ``counts[i]`` vertices. ((N, 3) uint32 symbols back
    to back, each cloth's packed size). ValueError if a cloth's data runs past the end or a width
    is over 32. Whole arrays: :func:`unpack_blocks`, then each value to its vertex row."""
    counts = np.asarray(counts, np.int64)
    blocks, sizes = unpack_blocks(data, starts, counts)
    _, _, _, block, j = _frame_blocks(counts)
    return blocks[block, j], sizes


def blocks_unsymbols(blocks: np.ndarray, n: int, p: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Grid values of C like cloths of ``n`` vertices from their symbols in block order
    (:func:`unpack_blocks`, (C * 3 * nb, 32), changed in place) and their predictions ``p``
    ((C, n, 3) int32): (C, n, 3) int32 (into ``out`` when given, which may not be ``p``). The
    zig-zag undone in place, the neighbour differences summed along each axis's row straight into
    the vertex-major result, the predictions added."""
    u = blocks.reshape(len(p), 3, -1)
    sign = (u & 1).view(np.int32)
    np.negative(sign, out=sign)
    u >>= 1
    d = u.view(np.int32)
    d ^= sign
    q = np.empty(p.shape, np.int32) if out is None else out
    np.cumsum(d[:, :, :n], axis=2, out=q.transpose(0, 2, 1))  # the sums land in vertex order
    q += p
    return q


def frame_unsymbols(z: np.ndarray, p: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The inverse of :func:`frame_symbols`: (N, 3) int32 grid values of many cloths."""
    d = (z >> 1).view(np.int32) ^ -(z & 1).view(np.int32)
    r = np.cumsum(d, axis=0, dtype=np.int32)
    starts = np.zeros(len(counts), np.int64)
    np.cumsum(np.asarray(counts[:-1], np.int64), out=starts[1:])
    keep = np.asarray(counts) > 0
    before = np.zeros((len(counts), 3), np.int32)  # the running sum up to each cloth's start
    before[1:] = r[starts[1:] - 1] if len(counts) > 1 else before[1:]
    r -= np.repeat(before[keep], np.asarray(counts)[keep], axis=0)
    return r + p


@dataclass
class History:
    """The last two states of a stream, as the decoder rebuilt them: grid values and ticks."""

    q1: np.ndarray | None = None
    tick1: int = 0
    q2: np.ndarray | None = None
    tick2: int = 0

    def order(self) -> int:
        """The highest order these states allow."""
        return ORDER_LINEAR if self.q2 is not None else ORDER_PREVIOUS if self.q1 is not None else ORDER_INTRA

    def push(self, q: np.ndarray, tick: int) -> None:
        self.q2, self.tick2 = self.q1, self.tick1
        self.q1, self.tick1 = q, tick

    def clear(self) -> None:
        self.q1 = self.q2 = None
        self.tick1 = self.tick2 = 0


def encode_step(
    positions: np.ndarray, step: float, history: History, tick: int, keyframe: bool = False
) -> tuple[bytes, int, int, int]:
    """Encode one state of a stream and advance its history: (packed data, order, ref tick,
    ref2 tick). ``keyframe``: intra-coded whatever the history holds; a keyframe starts the
    stream's history afresh (the next state is of order 1, from the keyframe alone)."""
    q = quantise(np.asarray(positions, np.float32).reshape(-1, 3), step)
    if keyframe:
        history.clear()
    order = history.order()
    p = prediction(order, history.q1, history.q2, q.shape)
    refs = (history.tick1 if order >= 1 else 0, history.tick2 if order >= 2 else 0)
    data = encode_residuals(symbols(q, p))
    history.push(q, tick)
    return data, order, refs[0], refs[1]


def decode_step(
    data: bytes | bytearray | memoryview, n: int, step: float, order: int, history: History, tick: int, at: int = 0
) -> tuple[np.ndarray, int]:
    """Decode one state against ``history`` (the caller checked its ticks; an intra state
    starts it afresh) and advance it: ((n, 3) float32 positions, bytes read)."""
    z, size = decode_residuals(data, n, at)
    if order == ORDER_INTRA:
        history.clear()
    p = prediction(order, history.q1, history.q2, (n, 3))
    q = unsymbols(z, p)
    history.push(q, tick)
    return dequantise(q, step), size
