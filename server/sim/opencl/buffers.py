"""Device memory bookkeeping of the OpenCL world: a first-fit range allocator, growable device
arrays, the world's device arrays and their allocators (:class:`DeviceMemory`, one part of the
world that its other parts share), each cloth's and fabric's place in them (:class:`ClothSlot`,
:class:`FabricSlot`) and the int32 blob a fabric is uploaded as (its parts' offsets go into the
cloth tables, kernels/layout.h)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyopencl as cl

from ..fabric import Fabric
from .device import Device, layout

L = layout()
MF = cl.mem_flags


class RangeAllocator:
    """First-fit allocator of [start, start + n) ranges inside [0, capacity), coalescing frees."""

    def __init__(self) -> None:
        self.capacity = 0
        self.free: list[list[int]] = []  # sorted [start, size]

    def alloc(self, n: int) -> int | None:
        if n == 0:
            return 0
        for i, (s, size) in enumerate(self.free):
            if size >= n:
                if size == n:
                    self.free.pop(i)
                else:
                    self.free[i] = [s + n, size - n]
                return s
        return None

    def grow(self, capacity: int) -> None:
        if capacity > self.capacity:
            self.release(self.capacity, capacity - self.capacity)
            self.capacity = capacity

    def release(self, start: int, n: int) -> None:
        if n == 0:
            return
        self.free.append([start, n])
        self.free.sort()
        merged: list[list[int]] = []
        for s, size in self.free:
            if merged and merged[-1][0] + merged[-1][1] == s:
                merged[-1][1] += size
            else:
                merged.append([s, size])
        self.free = merged

    @property
    def high_water(self) -> int:
        """End of the last allocated range."""
        if self.free and self.free[-1][0] + self.free[-1][1] == self.capacity:
            return self.free[-1][0]
        return self.capacity


class DevArray:
    """A growable device buffer of ``capacity`` items of ``width`` elements of ``dtype``."""

    def __init__(self, dev: Device, dtype, width: int = 1, capacity: int = 64) -> None:
        self.dev = dev
        self.dtype = np.dtype(dtype)
        self.width = width
        self.itembytes = self.dtype.itemsize * width
        self.capacity = 0
        self._inflight: list[cl.Event] = []  # non-blocking writes not known to be done (write)
        self.buf: cl.Buffer  # set by resize below (never None after)
        self.resize(capacity)

    def resize(self, capacity: int) -> None:
        capacity = max(capacity, 1)
        new = cl.Buffer(self.dev.ctx, MF.READ_WRITE, capacity * self.itembytes)
        if self.capacity:  # capacity is 0 only before the first buffer
            n = min(self.capacity, capacity) * self.itembytes
            cl.enqueue_copy(self.dev.queue, new, self.buf, byte_count=n)
        self.buf, self.capacity = new, capacity

    def write(self, start: int, host: np.ndarray, blocking: bool = True) -> None:
        """``host`` into items ``start``...; ``blocking=False``: returns at once, never waiting
        for the commands queued before it (a blocking write waits for the whole in-order queue,
        a step included). The caller must not change ``host`` afterwards: the copy may still be
        reading it (pyopencl's transfer event keeps it alive, held here until complete)."""
        host = np.ascontiguousarray(host, self.dtype)
        if not host.size:
            return
        ev = cl.enqueue_copy(self.dev.queue, self.buf, host, dst_offset=start * self.itembytes, is_blocking=blocking)
        if not blocking:  # a dropped transfer event waits for its copy: kept until it is done
            done = cl.command_execution_status.COMPLETE
            self._inflight = [e for e in self._inflight if e.command_execution_status != done]
            self._inflight.append(ev)

    def zero(self, start: int, n: int) -> None:
        """Items ``start`` .. ``start + n`` set to zero on the device (no host array, no wait)."""
        if n:
            b = self.itembytes
            cl.enqueue_fill_buffer(self.dev.queue, self.buf, np.zeros(1, np.float32), start * b, n * b)

    def read(self, start: int, n: int) -> np.ndarray:
        out = np.empty((n, self.width), self.dtype)
        if n:
            cl.enqueue_copy(self.dev.queue, out, self.buf, src_offset=start * self.itembytes)
        return out


def map_pinned(dev: Device, shape: int | tuple[int, ...], dtype: Any) -> tuple[cl.Buffer, np.ndarray]:
    """A host array of ``shape`` and ``dtype`` in pinned memory: a buffer of ALLOC_HOST_PTR
    memory mapped once for good (the array's base keeps the mapping). A driver may copy into
    pageable memory synchronously; into this one a copy can stay non-blocking. Raises
    cl.Error where the driver has no mappable host memory (the callers fall back to numpy)."""
    dims = (shape,) if isinstance(shape, int) else tuple(shape)
    buf = cl.Buffer(
        dev.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.ALLOC_HOST_PTR, int(np.prod(dims)) * np.dtype(dtype).itemsize
    )
    # pyopencl's stub is wrong here: flags are OR-ed map_flags (an int), dtype any dtype-like,
    # and the call returns (array, event)
    arr, _ = cl.enqueue_map_buffer(  # type: ignore[misc]
        dev.queue,
        buf,
        cl.map_flags.READ | cl.map_flags.WRITE,  # type: ignore[arg-type]
        0,
        dims,
        dtype,
        is_blocking=True,
    )
    return buf, arr


def fabric_blob(f: Fabric) -> tuple[np.ndarray, dict[str, int]]:
    """Every fabric array the kernels read, as one int32 blob, and where each part starts."""
    links = np.zeros((f.n_links, L["LINK_WORDS"]), np.int32)
    links[:, :2] = f.links
    links[:, 2] = f.link_type
    links[:, 3] = f.rest_length.astype(np.float32).view(np.int32)
    slots = L["TETHER_SLOTS"]
    assert L["ANCHOR_WORDS"] == 2 * slots == 2 * f.tether_anchor.shape[1], "layout.h's TETHER_SLOTS: tethers.py's"
    anchor = np.zeros((f.n_vertices, slots, 2), np.int32)
    anchor[:, :, 0] = f.tether_anchor
    anchor[:, :, 1] = f.tether_length.astype(np.float32).view(np.int32)
    lr_links, lr_rest, lr_offsets = f.long_range()
    lr = np.zeros((len(lr_links), L["LINK_WORDS"]), np.int32)
    lr[:, :2] = lr_links
    lr[:, 3] = lr_rest.astype(np.float32).view(np.int32)
    parts = {
        "CI_OFF_LINKS": links.ravel(),
        "CI_OFF_COLOURS": f.colour_offsets.astype(np.int32),
        "CI_OFF_ANCHOR": anchor.ravel(),
        "CI_OFF_JORDER": f.jacobi_order.astype(np.int32),
        "CI_OFF_JOFF": f.jacobi_offsets.astype(np.int32),
        "CI_OFF_JADJ": f.jacobi_adj.astype(np.int32).ravel(),
        "CI_OFF_VTRIOFF": f.vtri_offsets.astype(np.int32),
        "CI_OFF_VTRI": f.vtri.astype(np.int32),
        "CI_OFF_TRIS": f.triangles.astype(np.int32).ravel(),
        "CI_OFF_LRLINKS": lr.ravel(),
        "CI_OFF_LRCOLOURS": np.concatenate([[len(lr_offsets) - 1], lr_offsets]).astype(np.int32),
        "CI_OFF_REST": f.rest_positions.astype(np.float32).view(np.int32).ravel(),
    }
    offsets, pos = {}, 0
    for name, arr in parts.items():
        offsets[name] = pos
        pos += len(arr)
    return np.concatenate(list(parts.values())).astype(np.int32), offsets


@dataclass
class FabricSlot:
    """A fabric's blob in the int arena, shared by its cloths (``refs``), and its vertex rows at
    rest (float4, inverse masses in w) by total mass, made once for all its cloths of that mass."""

    base: int
    size: int
    refs: int
    offsets: dict[str, int]
    rest_rows: dict[float, np.ndarray] = field(default_factory=dict)


@dataclass
class ClothSlot:
    """A cloth's place in the device arrays: its table row, first vertex, fabric, multipliers,
    colliders and the launch group it is stepped in."""

    slot: int  # row in the cloth tables
    vbase: int
    fabric: FabricSlot
    lam_base: int = -1
    lam_size: int = 0
    coll_base: int = 0
    coll_cap: int = 0
    group: tuple | None = None


class DeviceMemory:
    """Every device array of an OpenCL world: the vertex arrays (float4 positions with inverse
    mass in w, velocities, previous positions, pin targets, normals; a second position array for
    the Jacobi solver) with their range allocator, the fabric int arena, the XPBD multipliers,
    the colliders and the per-cloth int/float tables."""

    def __init__(self, dev: Device, jacobi: bool) -> None:
        self.vert = RangeAllocator()
        self.pos = DevArray(dev, np.float32, 4)
        self.vel = DevArray(dev, np.float32, 4)
        self.prev = DevArray(dev, np.float32, 4)
        self.target = DevArray(dev, np.float32, 4)
        self.nrm = DevArray(dev, np.float32, 4)
        self.pos2 = DevArray(dev, np.float32, 4) if jacobi else None
        self.fab_alloc = RangeAllocator()
        self.fab = DevArray(dev, np.int32, 1)
        self.lam_alloc = RangeAllocator()
        self.lam = DevArray(dev, np.float32, 1)
        self.coll_alloc = RangeAllocator()
        self.coll = DevArray(dev, np.float32, 4 * L["COLLIDER_WORDS"])
        self.ci = DevArray(dev, np.int32, L["CI_STRIDE"], 64)
        self.cf = DevArray(dev, np.float32, L["CF_STRIDE"], 64)

    def vertex_arrays(self) -> list[DevArray]:
        arrs = [self.pos, self.vel, self.prev, self.target, self.nrm]
        return arrs + ([self.pos2] if self.pos2 is not None else [])

    def alloc(self, alloc: RangeAllocator, arrays: list[DevArray], n: int) -> int:
        """A range of ``n`` items of ``alloc``, the arrays grown (doubled) when none is free."""
        start = alloc.alloc(n)
        if start is None:
            cap = max(alloc.capacity * 2, alloc.capacity + n, 64)
            for a in arrays:
                a.resize(cap)
            alloc.grow(cap)
            start = alloc.alloc(n)
        assert start is not None
        return start

    def step_buffers(self) -> list[Any]:
        """The buffers wg_step and pack_step both take after their cloth list, in their order
        (ci, cf, fab, pos, vel, prev, target, nrm, coll)."""
        bufs = (self.ci, self.cf, self.fab, self.pos, self.vel, self.prev, self.target, self.nrm, self.coll)
        return [b.buf for b in bufs]
