"""The frame encoded on the device: one packed buffer of every publication's bytes per tick.

:class:`FramePlan` (frameplan.py, re-exported here) lays a frame out once (when the set of
published cloths, their encodings, normals or bundling changes): every publication (a single
state, or a client's section 9.1 bundle) at an 8-byte aligned offset of one buffer, every
cloth's state at a known offset, and its static words (magics, versions, header sizes,
encodings, vertex counts, bundle entry tables and cloth ids with their padding), built with
:mod:`drape.client.protocol`'s own structs. :class:`DeviceEncoder` puts those words once into
the device output buffer (kernels/static.cl; no zero fill: a buffer kept across plans is used as
it is); per tick one launch of ``encode_frame`` (kernels/encode.cl: one work-group per cloth)
writes the dynamic bytes (flags, tick, time, bounds, vertex data, normals) and every state's
padding straight from the world's float4 position and normal buffers, and one copy brings the
whole frame into pinned host memory. :meth:`DeviceEncoder.slices` then gives each publication's
bytes as a memoryview of that memory, without copying. No per-cloth Python runs per tick.

Use (the service's tick path; no per-cloth Python per tick)::

    plan = FramePlan.build([ClothEntry(id, vbase, n, encoding, normals), ...],
                           [Publication(key, (i,)), Publication(bundle_key, (j, k), bundle=True), ...])
    encoder = DeviceEncoder(device)             # once
    encoder.set_plan(plan)                      # when cloths, encodings, normals or bundles change
    encoder.encode(queue, world_pos_buf, world_nrm_buf, tick, time_ns, flags)  # every tick
    for i in encoder.nonfinite(): ...           # reset those cloths, encode the frame again
    for pub, payload in zip(plan.publications, encoder.slices()): publisher.put(bytes(payload))

(eclipse-zenoh 1.10's ``ZBytes`` takes ``bytes``/``bytearray``, not a memoryview, so publishing
costs one copy per payload: 1024 payloads of 12 KB, 0.7 ms; zenoh-python issue 730 asks for a
zero-copy path.)

``vbase`` is the cloth's first vertex in the world's float4 vertex buffers (``stride=4``), or its
first row in a packed xyz buffer (``stride=3``). A frame's views stay valid until
``host_buffers`` (2) more frames have been encoded, or while held across a new plan;
:meth:`DeviceEncoder.hold` keeps a frame from reuse until it is released (the service's
publisher holds the frame it publishes while the next ones are encoded): the pinned host frames
and the held frame are hostframes.py's.

Predictive states (protocol 1.5) are coded against the history the encoder keeps on the device
(one buffer of :data:`HISTORY` slots of grid values per position-buffer vertex (or per vertex
of the rows' own history bases, ``ClothEntry.hbase``: a decimated streams' encoder), each slot
one encoded tick's: the tick being coded, the frame before it whose fate the publisher has not
told yet, and the two states the decoders hold before that, so that a frame the publisher drops
is forgotten (:meth:`DeviceEncoder.forget`) and the next coded again against the states sent,
as the host path does), with the order and reference ticks devstreams.DeviceStreams decides
per tick (``encode(predictive=...)``); each row's slots follow from its own reference ticks
(uploaded with them), so streams referring to different ticks share one launch.
Their size varies, so each is written into a slot of its largest size (the plan's layout stays
fixed) and compact.py's :class:`~.compact.Compactor` (kernels/compact.cl, two more launches on
the same queue) writes the frame's wire bytes back to back into a second buffer: the host copies
only those and a small index, and each publication is a slice of them. The bytes equal
statecodec.FrameEncoder's (the host path's) for the same streams.

The bytes equal :func:`drape.client.protocol.encode_state` / :func:`~drape.client.protocol.encode_bundle`
(tests/sim/test_device_encode.py), with two documented exceptions:

- a zero bound whose axis holds both +0.0 and -0.0 may carry either sign (numpy's min/max pick
  one by evaluation order; the value is the same);
- on a device without ``cl_khr_fp64`` quant16 positions and snorm16 normals are evaluated in
  float and may differ from the float64 reference by :data:`QUANT16_FP32_TOLERANCE` (1 unit).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import pyopencl as cl

from drape.client import protocol as P

from . import reuse
from .compact import Compactor
from .device import Device
from .frameplan import (  # noqa: F401 (the plan's names, re-exported: encode.py is the entry point)
    HEADER_OFFSETS,
    SOURCE,
    STATIC_SOURCE,
    ClothEntry,
    FramePlan,
    Publication,
    encode_layout,
    state_size,
    take_bytes,
)
from .hostframes import EncodedFrame, HostFrame, HostFrames

log = logging.getLogger(__name__)

HISTORY = 4  # grid-value slots: the tick coded, the frame before (its fate not yet told), the two sent
_PRED_WORDS = encode_layout()["ENC_PRED_WORDS"]  # per plan cloth: order, ref ticks, history slots
_SLOT_BITS = encode_layout()["ENC_SLOT_BITS"]

MF = cl.mem_flags

#: quant16 / snorm16 units a device without fp64 may differ from the float64 reference by.
QUANT16_FP32_TOLERANCE = 1


def history_end(plan: FramePlan) -> int:
    """One past the last history vertex a predictive row of ``plan`` refers to (0: none)."""
    W = encode_layout()
    rows = plan.rows[plan.rows[:, W["ENC_ROW_ENC"]] == P.ENC_PREDICTIVE] if len(plan.rows) else plan.rows
    ends = rows[:, W["ENC_ROW_HIST"]].astype(np.int64) + rows[:, W["ENC_ROW_N"]]
    return int(ends.max(initial=0))


class DeviceEncoder:
    """Encode whole frames on ``dev`` with a :class:`FramePlan`.

    ``stride``: floats per vertex of the position and normal buffers, 4 for the world's float4
    buffers (a cloth's ``vbase`` is its first vertex there), 3 for packed xyz rows (``vbase`` its
    first row). ``fp64`` (default: whether the device has cl_khr_fp64) evaluates quant16 in
    double, exactly as the reference; ``host_buffers`` pinned host copies are used in turn, so the views of a
    frame stay valid until that many more frames have been encoded."""

    def __init__(
        self,
        dev: Device,
        local_size: int | None = None,
        fp64: bool | None = None,
        host_buffers: int = 2,
        stride: int = 4,
        soft_half: bool | None = None,
    ) -> None:
        if not dev.device.endian_little:
            raise RuntimeError(f"{dev.info.name} is big-endian; the wire format is little-endian")
        if stride not in (3, 4):
            raise ValueError(f"stride {stride}: vertices are float4 (4) or packed xyz (3)")
        self.stride = stride
        # float16 by integer SIMD (bit-exact with numpy) on CPUs, vstore_half_rte (hardware) on GPUs
        self.soft_half = (not dev.info.is_gpu) if soft_half is None else bool(soft_half)
        self.dev = dev
        has64 = "cl_khr_fp64" in dev.device.extensions
        if fp64 and not has64:
            raise ValueError(f"{dev.info.name} has no cl_khr_fp64")
        self.fp64 = has64 if fp64 is None else bool(fp64)
        if not self.fp64:
            log.warning(
                "%s: quant16 evaluated in float, may differ from the reference by %d",
                dev.info.name,
                QUANT16_FP32_TOLERANCE,
            )
        self._local_size = local_size
        self.hosts = HostFrames(dev, host_buffers)  # the pinned host copies, used in turn (hostframes.py)
        self.plan: FramePlan | None = None
        self._kernel: cl.Kernel | None = None
        self._wg = 1
        self._out: cl.Buffer | None = None
        self._out_reused = reuse.ReusedBuffer(dev.ctx, MF.READ_WRITE)  # the frame's slots, kept across plans
        self._static_event: cl.Event | None = None  # the plan's static bytes put in (the next encode waits)
        self._static_bufs: tuple[cl.Buffer, ...] = ()  # what that launch reads, kept until it is done
        self._table: cl.Buffer | None = None
        self._flags_buf: cl.Buffer | None = None
        self._flags = np.zeros(0, np.uint16)
        # 1.5 predictive: per plan cloth (order, ref tick, ref2 tick) of this tick, and the grid
        # values of the last HISTORY encoded ticks per position-buffer vertex (3 int32 each)
        self._pred_buf: cl.Buffer | None = None
        self._pred = np.zeros((0, 4), np.uint64)
        self._hist: cl.Buffer | None = None  # HISTORY slots of _hist_cap vertices (encode.cl's hist)
        self._hist_cap = 0  # vertices
        self._hist_of: dict[int, int] = {}  # tick -> the history buffer holding its grid values
        self._last: HostFrame | None = None
        self.kernel_event: cl.Event | None = None  # the last launch (profiling on a profiling queue)
        self.compactor = Compactor(dev)  # plans with predictive states: compacted on the device
        self._uploads: list[cl.Event] = []  # this frame's uploads (flags, predictive decisions)
        self._compact = False

    # -- plan ------------------------------------------------------------------------------

    def _pick_wg(self, max_n: int) -> int:
        limit = self.dev.info.max_work_group
        # CPU (PoCL): one work-item per cloth, no barrier bookkeeping, as the world's solvers
        want = self._local_size or (256 if self.dev.info.is_gpu else 1)
        want = min(want, limit, 1 << max(0, int(max(max_n, 1) - 1).bit_length()))
        wg = 1
        while wg * 2 <= want:
            wg *= 2
        return wg

    def _options(self, wg: int) -> list[str]:
        return [
            f"-DENC_WG={wg}",
            f"-DENC_FP64={int(self.fp64)}",
            f"-DENC_STRIDE={self.stride}",
            f"-DENC_SOFT_HALF={int(self.soft_half)}",
            *(f"-D{k}={v}" for k, v in HEADER_OFFSETS.items()),
        ]

    def build_all(self) -> int:
        """Build the program for every work-group size a plan may pick (one on a CPU, the
        powers of two up to the cap on a GPU), so that no later ``set_plan`` compiles (the
        service's tick thread never compiles). Returns how many were built."""
        wg, top = 1, self._pick_wg(2**31)
        while wg <= top:
            self.dev.program(self._options(wg), source=SOURCE)
            wg *= 2
        self.compactor.build()
        self.dev.program([], source=STATIC_SOURCE)
        return top.bit_length()

    def set_plan(self, plan: FramePlan) -> None:
        """Use ``plan`` from the next frame on: build the kernel, upload its table, size the
        output and pinned host buffers and put the plan's static bytes in (enqueued behind the
        last frame; the next encode waits for it). The output, compaction and pinned host
        buffers are kept from plan to plan while they fit (reuse.py: no allocation when cloths
        come or go within the capacity); the kernel and the tables are made before any buffer
        is touched, so a failure there leaves the previous plan in use. Frames held
        (:meth:`hold`) keep their bytes: their pinned memory is used again only once released."""
        ctx = self.dev.ctx
        wg = self._pick_wg(plan.max_n)
        kernel = cl.Kernel(self.dev.program(self._options(wg), source=SOURCE), "encode_frame")
        size = max(plan.size, 8)
        rows = np.ascontiguousarray(plan.rows, np.uint32)
        if not rows.size:
            rows = np.zeros(1, np.uint32)
        table = cl.Buffer(ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=rows)
        flags = np.zeros(max(len(plan.cloths), 1), np.uint16)
        flags_buf = cl.Buffer(ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=flags)
        pred_buf = cl.Buffer(ctx, MF.READ_ONLY, 8 * _PRED_WORDS * max(len(plan.cloths), 1))
        self._grow_history(history_end(plan))
        # the last frame's commands (in flight, perhaps on another queue) come before the
        # buffers they use are filled for this plan
        behind = [e for e in (self._last.event if self._last else None, self._static_event) if e is not None]
        out = self._out_reused.get(size)
        if plan.size:
            self._static_event = self._put_static(out, plan, behind)
        compact = bool(plan.predictive.any())
        if compact:
            self.compactor.set_plan(plan, out)
        self._compact = compact
        self.hosts.bind(plan, self.compactor if compact else None)
        self._last = None
        self._pred_buf, self._pred = pred_buf, np.zeros((0, _PRED_WORDS), np.uint64)
        self._kernel, self._wg, self._out, self._table = kernel, wg, out, table
        self._flags, self._flags_buf = flags, flags_buf
        self.plan = plan
        log.debug(
            "frame plan: %d publications, %d cloths, %d bytes, work-group %d",
            len(plan.publications),
            len(plan.rows),
            plan.size,
            wg,
        )

    def wait_static(self) -> None:
        """Wait for the plan's static bytes (set_plan enqueues them behind the last frame and
        the next encode waits for them): device work, which tools time apart."""
        if self._static_event is not None:
            self._static_event.wait()

    @property
    def buffers_made(self) -> int:
        """Frame-sized buffers allocated so far (the output, the compacted frame, the pinned host
        frames and their indices): a plan change within their capacity makes none."""
        return self._out_reused.made + self.compactor.buffers_made + self.hosts.made

    def _put_static(self, out: cl.Buffer, plan: FramePlan, behind: list[cl.Event]) -> cl.Event:
        """The plan's static words put into ``out`` by kernels/static.cl, enqueued behind the
        events ``behind`` (not waited for: the next encode waits for the returned event): a
        plan's words, not its whole template, cross to the device. No zero fill: encode.cl
        writes every other byte of every state it codes (padding included), so whatever a kept
        buffer held before is overwritten or never sent (a predictive slot past its state)."""
        q = self.dev.queue
        ev = cl.enqueue_marker(q, wait_for=behind or None)
        n = len(plan.static_at)
        if n:
            ro = MF.READ_ONLY | MF.COPY_HOST_PTR
            at = cl.Buffer(self.dev.ctx, ro, hostbuf=np.ascontiguousarray(plan.static_at, np.uint32))
            words = cl.Buffer(self.dev.ctx, ro, hostbuf=np.ascontiguousarray(plan.static_words, np.uint64))
            kernel = cl.Kernel(self.dev.program([], source=STATIC_SOURCE), "put_static")
            kernel.set_args(np.uint32(n), at, words, out)
            ev = cl.enqueue_nd_range_kernel(q, kernel, (n,), None, wait_for=[ev])
            self._static_bufs = (at, words)
        q.flush()
        return ev

    def _grow_history(self, vertices: int) -> None:
        """The predictive history buffers hold ``vertices`` position-buffer vertices (grown,
        their contents kept: the streams go on across plans)."""
        if self._hist is not None and vertices <= self._hist_cap:
            return
        cap = max(vertices, 2 * self._hist_cap, 1)
        new = cl.Buffer(self.dev.ctx, MF.READ_WRITE, 12 * cap * HISTORY)
        if self._hist is not None:
            old = 12 * self._hist_cap
            for slot in range(HISTORY):
                cl.enqueue_copy(
                    self.dev.queue, new, self._hist, byte_count=old, src_offset=slot * old, dst_offset=slot * 12 * cap
                )
        self.dev.queue.finish()
        self._hist, self._hist_cap = new, cap

    # -- per tick ----------------------------------------------------------------------------

    def encode(
        self,
        queue: cl.CommandQueue,
        positions: cl.Buffer,
        normals: cl.Buffer | None,
        tick: int,
        time_ns: int,
        flags: np.ndarray | None = None,
        wait_for: Sequence[cl.Event] | None = None,
        predictive: np.ndarray | None = None,
    ) -> cl.Event:
        """Enqueue this tick's frame: one launch, one copy into the next pinned host buffer.
        ``predictive`` (plan cloths, 3) uint64: each predictive cloth's (order, ref tick, ref2
        tick) this tick (devstreams.DeviceStreams decides them); required when the plan has
        predictive cloths. Encoding the same tick again (after resets) codes it against the same
        history; a new tick makes the last one's grid values the decoders' newest state.
        ``positions`` / ``normals``: device buffers (``stride`` floats per vertex) holding every
        plan cloth's range;
        ``flags`` (plan cloths,) state flags (FLAG_RESET...; FLAG_NORMALS is set per the plan),
        None for all zero. Returns the copy's event; :meth:`read` waits for it."""
        plan = self.plan
        if plan is None or self._kernel is None or self._out is None or self._flags_buf is None:
            raise RuntimeError("DeviceEncoder.encode before set_plan")
        need = plan.vertex_end * self.stride * 4
        if positions.size < need:
            raise ValueError(f"positions buffer of {positions.size} bytes; the plan reads {need}")
        if plan.normals:
            if normals is None:
                raise ValueError("the plan has cloths with normals but no normals buffer was given")
            if normals.size < need:
                raise ValueError(f"normals buffer of {normals.size} bytes; the plan reads {need}")
        if not 0 <= tick < 2**64 or not 0 <= time_ns < 2**64:
            raise ValueError(f"tick {tick} and time {time_ns} must be unsigned 64-bit")
        k = len(plan.cloths)
        events = list(wait_for or [])
        if flags is not None:
            f = np.asarray(flags)
            if f.shape != (k,):
                raise ValueError(f"flags of shape {f.shape}; the plan has {k} cloths")
            if f.size and (f.min() < 0 or f.max() > 0xFFFF):
                raise ValueError("flags must fit 16 bits")
            f = f.astype(np.uint16)
        else:
            f = np.zeros(k, np.uint16)
        if k and not np.array_equal(f, self._flags[:k]):
            self._flags = f.copy()  # a new array: the previous upload may still read the old one
            events.append(cl.enqueue_copy(queue, self._flags_buf, self._flags, is_blocking=False))
        if self._last is not None and self._last.event is not None:
            events.append(self._last.event)  # frames in order even when callers use several queues
        if plan.predictive.any():
            assert self._pred_buf is not None
            if predictive is None:
                raise ValueError("the plan has predictive cloths: give each its order and reference ticks")
            given = np.asarray(predictive, np.uint64)
            if given.shape != (k, 3):
                raise ValueError(f"predictive of shape {given.shape}; the plan has {k} cloths")
            pr = np.zeros((k, _PRED_WORDS), np.uint64)
            pr[:, :3] = given
            pr[:, 3] = self._slots(tick, given)
            self._pred = pr  # kept: the upload may still read it
            events.append(cl.enqueue_copy(queue, self._pred_buf, pr, is_blocking=False))
        if self._static_event is not None:
            events.append(self._static_event)  # the plan's static bytes (set_plan) are in
            self._static_event = None
        host = self.hosts.next_free(plan, self.compactor if self._compact else None)
        if host.event is not None:
            host.event.wait()  # its last copy (normally long done)
        n_rows = len(plan.rows)
        if n_rows:
            nb = normals if normals is not None else positions
            self._kernel.set_args(
                positions,
                nb,
                self._table,
                self._flags_buf,
                np.uint64(tick),
                np.uint64(time_ns),
                self._out,
                self._pred_buf,
                self._hist,
                np.uint32(self._hist_cap),
            )
            ev = cl.enqueue_nd_range_kernel(
                queue, self._kernel, (n_rows * self._wg,), (self._wg,), wait_for=events or None
            )
            self._uploads = events  # kept: pyopencl's event of a host-memory copy waits when dropped
            events = [ev]
            self.kernel_event = ev
        last = self._last
        if last is not None and last.index is not None and last.where is None:
            self._finish(last)  # its bytes must leave the compacted buffer before it is reused
        if self._compact:
            assert host.index is not None
            host.where = None
            if not plan.size:
                host.index[:] = 0  # nothing published: no launch, an empty frame
        if self._compact and plan.size:
            assert host.index is not None
            host.event, host.copied = self.compactor.enqueue(queue, host.data, host.index, plan.size, events)
        elif plan.size:
            host.event = cl.enqueue_copy(
                queue, host.data[: plan.size], self._out, is_blocking=False, wait_for=events or None
            )
        else:
            host.event = cl.enqueue_marker(queue, wait_for=events or None)
        self._last = host
        return host.event

    def _slots(self, tick: int, pred: np.ndarray) -> np.ndarray:
        """Each plan cloth's history slots for the decisions ``pred`` (k, 3): this tick's (the
        one it had when coded again, else a free one, else the oldest tick's that no row refers
        to) and those of its two reference ticks (per row: streams may refer to different
        ticks), packed as encode.cl's ``ENC_SLOT_BITS`` fields."""
        order = pred[:, 0]
        r1, r2 = order >= 1, order >= 2
        want = set(np.unique(pred[r1, 1]).tolist()) | set(np.unique(pred[r2, 2]).tolist())
        missing = sorted(t for t in want if t not in self._hist_of)
        if missing:
            raise ValueError(f"ticks {missing} are not in the encoder's history {sorted(self._hist_of)}")
        cur = self._hist_of.get(tick)
        if cur is None:
            free = sorted(set(range(HISTORY)) - set(self._hist_of.values()))
            if not free:
                oldest = min((t for t in self._hist_of if t not in want), default=None)
                if oldest is None:
                    raise ValueError(f"{HISTORY} history slots, all referred to: {sorted(want)}")
                free = [self._hist_of.pop(oldest)]
            cur = self._hist_of[tick] = free[0]
        ticks = np.array(sorted(self._hist_of), np.uint64)
        slot_of = np.array([self._hist_of[t] for t in ticks.tolist()], np.uint64)
        s1 = np.where(r1, slot_of[np.searchsorted(ticks, pred[:, 1]).clip(0, len(ticks) - 1)], cur)
        s2 = np.where(r2, slot_of[np.searchsorted(ticks, pred[:, 2]).clip(0, len(ticks) - 1)], cur)
        bits = np.uint64(_SLOT_BITS)
        return np.uint64(cur) | (s1.astype(np.uint64) << bits) | (s2.astype(np.uint64) << (bits + bits))

    def forget(self, tick: int) -> None:
        """The frame of ``tick`` was dropped (its states never went out): its history buffer is
        free, and no later state refers to it."""
        self._hist_of.pop(tick, None)

    def hold(self) -> EncodedFrame:
        """The frame last encoded (waits for it), kept from reuse until its ``release()``."""
        return EncodedFrame(self._frame())

    def _frame(self) -> HostFrame:
        if self._last is None:
            raise RuntimeError("no frame encoded yet")
        if self._last.event is not None:
            self._last.event.wait()
        if self._last.index is not None and self._last.where is None:
            self._finish(self._last)
        return self._last

    def _finish(self, host: HostFrame) -> None:
        """A compacted frame's index read, and its bytes past the first copy's guess copied."""
        assert host.index is not None
        if host.event is not None:
            host.event.wait()
        host.where = self.compactor.finish(host.data, host.index, host.copied)

    def read(self) -> memoryview:
        """The whole packed frame last encoded (waits for it), a view of pinned host memory."""
        assert self.plan is not None
        host = self._frame()
        size = host.where.size if host.where is not None else self.plan.size
        return memoryview(host.data).cast("B")[:size]  # type: ignore[arg-type]

    def slices(self) -> list[memoryview]:
        """Publication index -> its payload, views of the frame last encoded (waits for it)."""
        host = self._frame()
        return host.where.views(host.data) if host.where is not None else list(host.views)

    def bounds(self) -> np.ndarray:
        """(rows, 2, 3) float32: the bounds min and max in each encoded cloth's header, in
        :attr:`FramePlan.encoded` order (waits for the frame)."""
        assert self.plan is not None
        host = self._frame()
        data = host.data
        at = host.state_at()[self.plan.encoded] + HEADER_OFFSETS["ST_MIN"]
        return take_bytes(data, at, 24).view("<f4").reshape(-1, 2, 3)

    def nonfinite(self) -> np.ndarray:
        """Plan cloth indices whose positions held a NaN or an infinity this frame (their header
        bounds are non-finite): the service resets them and encodes them again."""
        assert self.plan is not None
        b = self.bounds().reshape(-1, 6)
        return self.plan.encoded[~np.isfinite(b).all(axis=1)]

    def close(self) -> None:
        """Drop the pinned host frames (a view still held elsewhere keeps its memory alive)."""
        self.hosts.clear()
        self._last = None
        self.plan = None
