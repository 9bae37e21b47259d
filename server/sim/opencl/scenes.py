"""The OpenCL world's inter-cloth collision (a part the CLWorld owns; protocol 1.7 scenes): once per
step, after every launch group's solve, the cloths of each scene are kept apart from each other
on the device by kernels/intercollide.cl (the broad phase over the cloths' boxes, then a spatial
hash keyed by scene over every vertex of the cloths whose box meets another of their scene,
INTER_COLLISION_PASSES Jacobi passes), the float64 twin being drape.server.sim.scenes.inter_collide.

Nothing is built or launched while no scene holds two cloths: a World without scenes pays
nothing, and the solvers' programs keep their build options. The tables (which vertex rows,
which cloth, which scene, thickness and stiffness) are rebuilt on the host only when a cloth
joins or leaves a scene or a scene cloth's material changes (``changed``), never per tick.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyopencl as cl

from ..scenes import INTER_COLLISION_MARGIN, INTER_COLLISION_PASSES, Scene
from ..world import Cloth
from .buffers import ClothSlot, DevArray, DeviceMemory
from .device import Device

SOURCE = "intercollide.cl"
KERNELS = ("ic_bounds", "ic_active", "ic_clear", "ic_insert", "ic_contacts", "ic_apply")


def _pow2_at_least(n: int) -> int:
    return 1 << max(6, (max(n, 1) - 1).bit_length())


class SceneCollision:
    """Inter-cloth collision of a World's scenes, given the World's memory, slots, cloths and scenes."""

    def __init__(
        self,
        dev: Device,
        mem: DeviceMemory,
        rec: Mapping[int, ClothSlot],
        cloths: Mapping[int, Cloth],
        scenes: Mapping[str, Scene],
    ) -> None:
        self.dev, self.mem, self.rec, self.cloths, self.scenes = dev, mem, rec, cloths, scenes
        self.ls = 64 if dev.info.is_gpu else 1
        self.options = [f"-DIC_LS={self.ls}", f"-DINTER_COLLISION_PASSES={INTER_COLLISION_PASSES}"]
        self._dirty = True
        self.n_cloths = 0  # scene cloths taking part (scenes of two cloths or more)
        self.n_vertices = 0
        self._kernels: dict[str, cl.Kernel] | None = None
        self._vidx = DevArray(dev, np.int32, 1)
        self._vcl = DevArray(dev, np.int32, 1)
        self._cinfo = DevArray(dev, np.int32, 8)
        self._cpar = DevArray(dev, np.float32, 2)
        self._box = DevArray(dev, np.float32, 8)
        self._active = DevArray(dev, np.int32, 1)
        self._next = DevArray(dev, np.int32, 1)
        self._delta = DevArray(dev, np.float32, 4)
        self._heads = DevArray(dev, np.int32, 1)
        self._nb = 64
        self._inv = 1.0

    def changed(self) -> None:
        """A cloth joined or left a scene, or a scene cloth's material changed: tables rebuilt
        before the next step."""
        self._dirty = True

    def kernels(self) -> dict[str, cl.Kernel]:
        if self._kernels is None:
            prg = self.dev.program(self.options, source=SOURCE)
            self._kernels = {name: cl.Kernel(prg, name) for name in KERNELS}
        return self._kernels

    def _rebuild(self) -> None:
        vidx: list[np.ndarray] = []
        vcl: list[np.ndarray] = []
        cinfo: list[list[int]] = []
        cpar: list[list[float]] = []
        for si, sc in enumerate(self.scenes.values()):
            if len(sc.handles) < 2:
                continue
            first = len(cinfo)
            for h in sc.handles:
                k, slot, m = len(cinfo), self.rec[h], self.cloths[h].params.material
                n = self.cloths[h].fabric.n_vertices
                cinfo.append([slot.vbase, n, si, first, len(sc.handles), 0, 0, 0])
                cpar.append([m.thickness * INTER_COLLISION_MARGIN, m.contact_stiffness])
                vidx.append(np.arange(slot.vbase, slot.vbase + n, dtype=np.int32))
                vcl.append(np.full(n, k, np.int32))
        self._dirty = False
        self.n_cloths = len(cinfo)
        if not cinfo:
            self.n_vertices = 0
            return
        v = np.concatenate(vidx)
        self.n_vertices = nv = len(v)
        for arr, host in (
            (self._vidx, v),
            (self._vcl, np.concatenate(vcl)),
            (self._cinfo, np.asarray(cinfo, np.int32)),
            (self._cpar, np.asarray(cpar, np.float32)),
        ):
            if arr.capacity < len(host):
                arr.resize(_pow2_at_least(len(host)))
            arr.write(0, host)
        for arr, n in ((self._box, self.n_cloths), (self._active, self.n_cloths), (self._next, nv), (self._delta, nv)):
            if arr.capacity < n:
                arr.resize(_pow2_at_least(n))
        self._nb = _pow2_at_least(2 * nv)
        if self._heads.capacity < self._nb:
            self._heads.resize(self._nb)
        dmax = float(np.max(np.asarray(cpar)[:, 0]))
        self._inv = 0.5 / dmax if dmax > 0 else 0.0

    def step(self, dt: float) -> None:
        """The scenes' inter-cloth collision, after the solvers' launches of a step."""
        if self._dirty:
            self._rebuild()
        if self.n_cloths < 2 or self._inv <= 0.0:
            return
        k = self.kernels()
        q, mem = self.dev.queue, self.mem
        pos, vel = mem.pos.buf, mem.vel.buf
        ncl, nv, nb = np.int32(self.n_cloths), np.int32(self.n_vertices), np.int32(self._nb)
        inv, mask = np.float32(self._inv), np.uint32(self._nb - 1)
        vidx, vcl, cinfo, cpar = self._vidx.buf, self._vcl.buf, self._cinfo.buf, self._cpar.buf
        box, active, heads, nxt, delta = (
            self._box.buf,
            self._active.buf,
            self._heads.buf,
            self._next.buf,
            self._delta.buf,
        )
        for _ in range(INTER_COLLISION_PASSES):
            k["ic_bounds"](q, (self.n_cloths * self.ls,), (self.ls,), pos, cinfo, cpar, box)
            k["ic_active"](q, (self.n_cloths,), None, cinfo, box, active, ncl)
            k["ic_clear"](q, (self._nb,), None, heads, nb)
            k["ic_insert"](q, (self.n_vertices,), None, pos, vidx, vcl, cinfo, active, heads, nxt, nv, inv, mask)
            k["ic_contacts"](
                q, (self.n_vertices,), None, pos, vidx, vcl, cinfo, cpar, active, heads, nxt, delta, nv, inv, mask
            )
            k["ic_apply"](q, (self.n_vertices,), None, pos, vel, vidx, delta, nv, np.float32(1.0 / dt))
