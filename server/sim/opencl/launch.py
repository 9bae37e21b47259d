"""The OpenCL world's launch groups: build options, kernel set-up and launches (a part the CLWorld owns).

A *group* is the cloths that share one kernel build (feature set, substeps, local-memory fit,
CPU packs). ``_options_for`` is a group's build options (a GPU's never include the CPU pack's).
``_build_group`` sizes its launches (work-group size, chunks of the coloured and Jacobi solvers,
per-colour link prefix sums, the CPU packs) when its cloths change; the coloured and Jacobi
solvers' per-substep vertex phases and iterations, the CPU pack launch and the work-group
solver's single launch are enqueued here (:meth:`GroupLaunches.step`).

CPU pack solver (kernels/pack.cl): on a CPU device with one work-item per cloth (the default
there), the work-group solver's cloths that share a fabric, iterations and substeps are stepped
``Device.info.pack_lanes`` at a time (16 where the device check found the compiler builds them)
by one work-item, the link solve vectorised across them (docs/cpu-solver.md).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyopencl as cl

from ..params import Features
from ..shared import JACOBI_OMEGA
from ..world import Cloth
from .buffers import ClothSlot, DeviceMemory
from .device import Device

MF = cl.mem_flags


# Measured on the H100 (docs/benchmarks.md): the local path is fastest without unrolling
# (157 vs 146 G link-it/s at 4), the global path with 4 (1.31 vs 1.87 ms for the seed cloth).
LINK_UNROLL_LOCAL = 1
LINK_UNROLL_GLOBAL = 4
# Extra build options of the CPU pack kernel (never a GPU build's): measured in docs/cpu-solver.md.
CPU_BUILD_OPTIONS: list[str] = ["-cl-denorms-are-zero"]


def _next_pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def pack_lanes(keys: list[tuple], slots: list[int], lanes: int, compute_units: int) -> np.ndarray:
    """Cloth slots into packs of at most ``lanes`` cloths that share a key (fabric, iterations,
    substeps), as an (n_packs, lanes) int32 table padded with -1. A key's cloths are spread
    evenly over its packs, and over a multiple of ``compute_units`` packs where that does not add
    a round: a pack costs about the same however many lanes it fills, so 20 cloths on 2 cores
    run as 10 + 10, not 16 + 4."""
    by_key: dict[tuple, list[int]] = {}
    for key, s in zip(keys, slots, strict=True):
        by_key.setdefault(key, []).append(s)
    rows: list[list[int]] = []
    for members in by_key.values():
        n = len(members)
        k = -(-n // lanes)
        even = -(-k // compute_units) * compute_units
        k = min(n, even)
        for i in range(k):
            part = members[i * n // k : (i + 1) * n // k]
            rows.append(part + [-1] * (lanes - len(part)))
    return np.array(rows, np.int32).reshape(-1, lanes)


@dataclass
class Group:
    """Cloths stepped by one kernel build (feature set, substeps or local-memory fit, CPU packs)."""

    key: tuple
    features: Features
    use_local: bool
    handles: set[int] = field(default_factory=set)
    dirty: bool = True
    slots: np.ndarray | None = None
    cloths_buf: cl.Buffer | None = None
    prefix_buf: cl.Buffer | None = None
    chunks_buf: cl.Buffer | None = None  # (cloth slot, first vertex) per vertex-phase work-group
    n_chunks: int = 0
    colour_totals: list[int] = field(default_factory=list)
    max_iters: int = 0
    max_colours: int = 0
    max_vertices: int = 0
    substeps: int = 1
    local_size: int = 64
    pack: int = 0  # CPU pack solver: lanes per pack (0: wg_step); see launch.py
    packs_buf: cl.Buffer | None = None  # PACK_LANES cloth slots per pack, -1 = unused lane
    n_packs: int = 0
    pack_local_bytes: int = 0  # the largest pack's local memory


class GroupLaunches:
    """Sets up and enqueues each group's launches over ``mem``; ``rec`` and ``cloths`` are the
    world's (by handle), read when a group is rebuilt."""

    def __init__(
        self,
        dev: Device,
        mem: DeviceMemory,
        rec: dict[int, ClothSlot],
        cloths: dict[int, Cloth],
        solver: str,
        chunk: int,
        link_group_size: int,
        max_local_size: int,
        max_global_path_size: int,
    ) -> None:
        self.dev, self.mem, self.rec, self.cloths, self.solver = dev, mem, rec, cloths, solver
        self.chunk, self.link_group_size = chunk, link_group_size
        self.max_local_size, self.max_global_path_size = max_local_size, max_global_path_size
        # by handle: (table row, fabric arena base, iterations, substeps), set by ``note``
        self._cols = np.zeros((64, 4), np.int64)

    def options(self, g: Group, local: bool | None = None) -> list[str]:
        return self.options_for(g.features, g.use_local if local is None else local, g.pack)

    def options_for(self, features: Features, use_local: bool, pack: int = 0) -> list[str]:
        if pack:  # CPU only: the pack kernel keeps the lanes in local memory itself
            return [*features.build_options(), "-DUSE_LOCAL=0", f"-DPACK_LANES={pack}", *CPU_BUILD_OPTIONS]
        g_features = features
        env_unroll = os.environ.get("DRAPE_LINK_UNROLL_LOCAL" if use_local else "DRAPE_LINK_UNROLL_GLOBAL")
        unroll = int(env_unroll) if env_unroll else (LINK_UNROLL_LOCAL if use_local else LINK_UNROLL_GLOBAL)
        opts = [
            *g_features.build_options(),
            f"-DUSE_LOCAL={int(use_local)}",
            f"-DJACOBI_OMEGA={JACOBI_OMEGA}f",
            f"-DLINK_UNROLL={unroll}",
        ]
        regs = os.environ.get("DRAPE_NV_MAXRREG", "64")
        if not use_local and self.dev.info.is_nvidia and regs != "0":
            # cap registers so a global-path work-group may have 1024 work-items
            opts.append(f"-cl-nv-maxrregcount={regs}")
        return opts

    def kernel_limit(self, g: Group) -> int:
        name = "pack_step" if g.pack else "wg_step" if self.solver == "workgroup" else "cl_predict"
        k = self.dev.kernel(self.options(g), name)
        return int(k.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self.dev.device))

    def note(self, handle: int, slot: int, fabric_base: int, iterations: int, substeps: int) -> None:
        """A cloth's figures its group is built from (its table row, its fabric's place in the
        arena, which tells fabrics apart, iterations, substeps): set as it joins or changes."""
        if handle >= len(self._cols):
            grown = np.zeros((max(handle + 1, 2 * len(self._cols)), 4), np.int64)
            grown[: len(self._cols)] = self._cols
            self._cols = grown
        self._cols[handle] = (slot, fabric_base, iterations, substeps)

    def build_group(self, g: Group) -> None:
        """A group's launches sized for its cloths now: once per tick whose commands changed it,
        from the cloths' columns (``note``) in a few vectorised gathers, and one pass per
        *fabric* (a group of thousands of cloths mostly shares a few), not a pass over the
        cloths in Python (but for the CPU packs' table)."""
        handles = np.fromiter(g.handles, np.int64, len(g.handles))
        handles.sort()
        cols = self._cols[handles]
        slots, bases, iters, subs = cols[:, 0], cols[:, 1], cols[:, 2], cols[:, 3]
        _, first, fab_of = np.unique(bases, return_index=True, return_inverse=True)
        fabrics = [self.cloths[int(handles[i])].fabric for i in first.tolist()]  # by fabric index
        nv = np.array([f.n_vertices for f in fabrics], np.int64)
        g.slots = slots.astype(np.int32)
        g.cloths_buf = cl.Buffer(self.dev.ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=g.slots)
        g.max_iters = int(iters.max())
        g.max_colours = max(f.n_colours for f in fabrics)
        g.max_vertices = int(nv.max())
        g.substeps = int(subs[0])
        if g.pack:
            keys = list(zip(fab_of.tolist(), iters.tolist(), subs.tolist(), strict=True))
            table = pack_lanes(keys, g.slots.tolist(), g.pack, self.dev.info.compute_units)
            g.n_packs = len(table)
            g.packs_buf = cl.Buffer(self.dev.ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=table)
            # local memory of the largest pack: positions, then (XPBD) multipliers, per lane
            xpbd = g.features.xpbd
            g.pack_local_bytes = 4 * g.pack * max(4 * f.n_vertices + (f.n_links if xpbd else 0) for f in fabrics)
            g.local_size = 1
            g.dirty = False
            return
        widest = max(
            g.max_vertices,
            max((int(np.diff(f.colour_offsets).max()) if f.n_colours else 1) for f in fabrics),
        )
        if self.solver == "workgroup":
            cap = self.max_local_size if g.use_local else self.max_global_path_size
        else:
            cap = self.max_local_size
            widest = min(widest, self.chunk)
            # (cloth slot, first vertex) per chunk of each cloth, cloth by cloth
            per = (-(-nv // self.chunk))[fab_of]
            first_chunk = np.repeat(np.cumsum(per) - per, per)
            chunks = np.empty((int(per.sum()), 2), np.int32)
            chunks[:, 0] = np.repeat(slots, per)
            chunks[:, 1] = (np.arange(len(chunks)) - first_chunk) * self.chunk
            g.n_chunks = len(chunks)
            g.chunks_buf = cl.Buffer(self.dev.ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=chunks)
        g.local_size = int(min(cap, max(min(32, cap), _next_pow2(widest))))
        g.local_size = min(g.local_size, self.kernel_limit(g))
        if self.solver == "coloured" and g.max_colours == 0:  # cloths without links (1 vertex)
            g.colour_totals, g.prefix_buf = [], None
        elif self.solver == "coloured":
            sizes = np.zeros((len(fabrics), g.max_colours), np.int32)  # links per colour, by fabric
            for i, f in enumerate(fabrics):
                sizes[i, : f.n_colours] = np.diff(f.colour_offsets)
            counts = np.zeros((g.max_colours, len(handles) + 1), np.int32)
            counts[:, 1:] = sizes[fab_of].T
            prefix = np.cumsum(counts, axis=1, dtype=np.int64)
            if prefix.size and prefix.max() >= 2**31:
                raise RuntimeError("too many links in one colour batch")
            prefix = prefix.astype(np.int32)
            g.colour_totals = [int(t) for t in prefix[:, -1]]
            g.prefix_buf = cl.Buffer(
                self.dev.ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(prefix)
            )
        g.dirty = False

    def _vertex_phase_step(self, g: Group, dt32, opts) -> None:
        """Coloured or Jacobi: per substep normals (wind), predict, iterations, finish."""
        q = self.dev.queue
        ls = g.local_size
        gsize = (g.n_chunks * ls,)
        ch = np.int32(self.chunk)
        predict = self.dev.kernel(opts, "cl_predict")
        finish = self.dev.kernel(opts, "cl_finish")
        normals = self.dev.kernel(opts, "cl_normals")
        cloth_args = (ch, g.chunks_buf, self.mem.ci.buf, self.mem.cf.buf, self.mem.fab.buf, self.mem.pos.buf)
        normal_args = (*cloth_args, self.mem.nrm.buf)
        vertex_args = (*cloth_args, self.mem.vel.buf, self.mem.prev.buf)  # predict and finish, after dt and substep
        for s in range(g.substeps):
            si = np.int32(s)
            if g.features.wind:
                normals(q, gsize, (ls,), *normal_args)
            predict(q, gsize, (ls,), dt32, si, *vertex_args, self.mem.target.buf, self.mem.nrm.buf, self.mem.lam.buf)
            if self.solver == "coloured":
                self._coloured_iterations(g, dt32, opts)
            else:
                self._jacobi_iterations(g, dt32, opts, gsize, ls)
            finish(q, gsize, (ls,), dt32, si, *vertex_args, self.mem.coll.buf)
            if g.features.self_collision:  # after the colliders: one work-group per cloth (kernels/selfcollide.cl)
                mem = self.mem
                bufs = (mem.ci, mem.cf, mem.fab, mem.pos, mem.vel, mem.nrm, mem.prev, mem.coll)
                collide = self.dev.kernel(opts, "cl_self_collide")
                collide(q, (len(g.handles) * ls,), (ls,), dt32, si, g.cloths_buf, *(b.buf for b in bufs))
        if g.features.normals:
            normals(q, gsize, (ls,), *normal_args)

    def _coloured_iterations(self, g: Group, dt32, opts) -> None:
        k = self.dev.kernel(opts, "cl_links")
        q = self.dev.queue
        lg = self.link_group_size
        assert g.slots is not None  # set by _build_group
        ngc = np.int32(len(g.slots))
        # arguments set once; per dispatch only the colour and the iteration change
        k.set_args(
            dt32,
            np.int32(0),
            np.int32(0),
            ngc,
            g.prefix_buf,
            g.cloths_buf,
            self.mem.ci.buf,
            self.mem.cf.buf,
            self.mem.fab.buf,
            self.mem.pos.buf,
            self.mem.lam.buf,
        )
        sizes = [((-(-total // lg) * lg,), c) for c, total in enumerate(g.colour_totals) if total]
        for it in range(g.max_iters):
            k.set_arg(2, np.int32(it))
            for gsize, c in sizes:
                k.set_arg(1, np.int32(c))
                cl.enqueue_nd_range_kernel(q, k, gsize, (lg,))

    def _jacobi_iterations(self, g: Group, dt32, opts, gsize, ls) -> None:
        k = self.dev.kernel(opts, "jacobi_iter")
        q = self.dev.queue
        pos2 = self.mem.pos2
        assert pos2 is not None  # the Jacobi solver's world has it
        bufs = [self.mem.pos.buf, pos2.buf]
        ch = np.int32(self.chunk)
        k.set_args(
            dt32,
            np.int32(0),
            ch,
            g.chunks_buf,
            self.mem.ci.buf,
            self.mem.cf.buf,
            self.mem.fab.buf,
            bufs[0],
            bufs[1],
            self.mem.lam.buf,
        )
        for it in range(g.max_iters):
            k.set_arg(1, np.int32(it))
            k.set_arg(7, bufs[it & 1])
            k.set_arg(8, bufs[(it + 1) & 1])
            cl.enqueue_nd_range_kernel(q, k, gsize, (ls,))
        if g.max_iters & 1:
            self.dev.kernel(opts, "copy_positions")(
                q, gsize, (ls,), ch, g.chunks_buf, self.mem.ci.buf, pos2.buf, self.mem.pos.buf
            )

    def _pack_step(self, g: Group, dt32, opts) -> None:
        """CPU: one launch of pack_step, one work-item per pack, the lanes in local memory."""
        # Any: pyopencl's stub of Kernel.__call__ leaves out LocalMemory
        args: list[Any] = [dt32, g.packs_buf, *self.mem.step_buffers(), cl.LocalMemory(max(64, g.pack_local_bytes))]
        self.dev.kernel(opts, "pack_step")(self.dev.queue, (g.n_packs,), (1,), *args)

    def step(self, groups: Iterable[Group], dt: float) -> None:
        """Enqueue one step of every group (each built since its cloths last changed)."""
        q = self.dev.queue
        dt32 = np.float32(dt)
        for g in groups:
            opts = self.options(g)
            if self.solver != "workgroup":
                self._vertex_phase_step(g, dt32, opts)
                continue
            if g.pack:
                self._pack_step(g, dt32, opts)
                continue
            # kernel arguments (Any: pyopencl's stub of Kernel.__call__ leaves out LocalMemory)
            args: list[Any] = [dt32, g.cloths_buf, *self.mem.step_buffers(), self.mem.lam.buf]
            if g.use_local:
                args.append(cl.LocalMemory(16 * g.max_vertices))
            ls = g.local_size
            assert g.slots is not None  # set by build_group
            self.dev.kernel(opts, "wg_step")(q, (len(g.slots) * ls,), (ls,), *args)
