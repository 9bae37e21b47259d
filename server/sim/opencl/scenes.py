"""The OpenCL world's inter-cloth collision (a part the CLWorld owns; protocol 1.7 scenes): once per
step, after every launch group's solve, the cloths of each scene are kept apart from each other
on the device by kernels/intercollide.cl (the broad phase over the cloths' boxes, a spatial hash
keyed by scene over every vertex of the cloths whose box meets another of their scene, each
vertex's candidates listed once a round, then the round's Jacobi passes over them, each
putting the vertices it moved back out of their cloth's colliders; the later rounds of a step walk
the hash again only for the vertices that moved further than INTER_COLLISION_SKIN since their
list was found, listed by ic_insert a work-group at a time on a GPU (IC_CG, IC_KEPT: dense,
ordered warps, each cloth's vertices numbered in Morton order there: IC_MORTON), the others
keeping their list's unmoved entries and gaining the moved vertices that find them), the float64
twin being
drape.server.sim.scenes.inter_collide.

Nothing is built or launched while no scene holds two cloths: a World without scenes pays
nothing, and the solvers' programs keep their build options. The tables (which vertex rows,
which cloth, which scene, thickness and stiffness) are rebuilt on the host only when a cloth
joins or leaves a scene or a scene cloth's material changes (``changed``), never per tick; the
kernels' arguments are set then (and when the World's buffers grow), so a step is the same
INTER_COLLISION_ROUNDS x (INTER_COLLISION_PASSES / INTER_COLLISION_ROUNDS + 4) launches and one
ic_rewalk per later round (each round's candidates' find runs its first pass) whatever the
number of scenes and cloths, with no Python per scene or cloth.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyopencl as cl

from ..fabric import Fabric
from ..scenes import (
    INTER_COLLISION_MARGIN,
    INTER_COLLISION_PASSES,
    INTER_COLLISION_REACH,
    INTER_COLLISION_ROUNDS,
    INTER_COLLISION_SHOCK,
    INTER_COLLISION_SKIN,
    Scene,
)
from ..tethers import morton
from ..world import Cloth
from .buffers import ClothSlot, DevArray, DeviceMemory
from .device import Device
from .phase import WorldPhase

SOURCE = "intercollide.cl"
KERNELS = ("ic_bounds", "ic_active", "ic_clear", "ic_insert", "ic_find", "ic_refind", "ic_pass", "ic_finish")
#: Candidates listed per vertex (-DIC_LIST); a vertex with more walks the hash in every pass instead.
IC_LIST = 16
#: ic_insert's work-group (-DIC_CG) on a GPU and on a CPU: the later rounds' lists of the vertices
#: that walk the hash again and of the others are appended with one atomic per group (a scan of the
#: group's flags in local memory), each group's vertices in their order; 1: one atomic a vertex
#: (PoCL: the scan's barriers made ic_insert's later launches 2x slower than the atomics).
IC_CG = {"gpu": 256, "cpu": 1}
#: Whether ic_refind runs over a list of the vertices that did not move (-DIC_KEPT; else over every
#: vertex, those that moved idle): dense warps on a GPU; on PoCL the list made it 2x slower.
IC_KEPT = {"gpu": True, "cpu": False}
#: Whether the scene numbers a cloth's vertices in its fabric's Morton order (_order; else in the
#: fabric's): a GPU's warps walk compact patches; on PoCL the scattered rows made ic_finish 3x slower.
IC_MORTON = {"gpu": True, "cpu": False}


def _pow2_at_least(n: int) -> int:
    return 1 << max(6, (max(n, 1) - 1).bit_length())


class SceneCollision(WorldPhase):
    """Inter-cloth collision of a World's scenes, given the World's memory, slots, cloths and scenes."""

    SOURCE, KERNELS = SOURCE, KERNELS  # the module's names, the phase's program
    # ic_pass from xa into xb and from xb into xa, ic_insert of the first round and of the later
    # ones, each with its arguments set once
    ALIASES = {"ic_pass_ba": "ic_pass", "ic_insert_later": "ic_insert", "ic_rewalk": "ic_refind"}

    def __init__(
        self,
        dev: Device,
        mem: DeviceMemory,
        rec: Mapping[int, ClothSlot],
        cloths: Mapping[int, Cloth],
        scenes: Mapping[str, Scene],
    ) -> None:
        kind = "gpu" if dev.info.is_gpu else "cpu"
        self.cg, self.kept, self.morton = IC_CG[kind], IC_KEPT[kind], IC_MORTON[kind]  # before the build options
        super().__init__(dev, mem, rec, cloths, scenes)
        self.n_cloths = 0  # scene cloths taking part (scenes of two cloths or more)
        self.n_vertices = 0
        self._vidx = DevArray(dev, np.int32, 1)
        self._vcl = DevArray(dev, np.int32, 1)
        self._cinfo = DevArray(dev, np.int32, 8)
        self._cpar = DevArray(dev, np.float32, 2)
        self._cslot = DevArray(dev, np.int32, 1)  # each cloth's row of the int table (colliders), -1: none
        self._box = DevArray(dev, np.float32, 8)
        self._active = DevArray(dev, np.int32, 1)
        self._next = DevArray(dev, np.int32, 1)
        self._count = DevArray(dev, np.int32, 1)
        self._nbr = DevArray(dev, np.int32, IC_LIST)
        self._xs0 = DevArray(dev, np.float32, 4)
        self._xa = DevArray(dev, np.float32, 4)
        self._xb = DevArray(dev, np.float32, 4)
        self._heads = DevArray(dev, np.int32, 1)
        # the later rounds': the first round's skin lists and positions, which vertex moved, their hash
        self._xs1 = DevArray(dev, np.float32, 4)
        self._mv = DevArray(dev, np.int32, 1)
        self._xnbr = DevArray(dev, np.int32, IC_LIST)  # an unmoved vertex's moved candidates
        self._xcount = DevArray(dev, np.int32, 1)
        self._moved = DevArray(dev, np.int32, 1)  # the vertices that moved, then their number
        self._nmoved = DevArray(dev, np.int32, 1)  # how many moved, how many did not (ic_refind's)
        self._nb = 64
        self._orders: dict[int, tuple[Fabric, np.ndarray]] = {}  # each fabric's vertex order (_order)
        self._inv = 1.0
        self._dmax = 0.0
        self._bound: tuple[object, ...] | None = None  # the buffers the kernels' arguments were set for
        self._dt = 0.0
        self._launches: list[tuple[cl.Kernel, tuple[int], tuple[int] | None]] = []
        self._finish: cl.Kernel | None = None

    def build_options(self) -> list[str]:
        return [
            f"-DIC_LS={self.ls}",
            f"-DINTER_COLLISION_PASSES={INTER_COLLISION_PASSES}",
            f"-DIC_REACH={INTER_COLLISION_REACH!r}f",
            f"-DIC_LIST={IC_LIST}",
            f"-DIC_CG={self.cg}",
            f"-DIC_KEPT={int(self.kept)}",
            f"-DIC_SHOCK={INTER_COLLISION_SHOCK!r}f",
        ]

    def _order(self, fab: Fabric, orders: dict[int, tuple[Fabric, np.ndarray]]) -> np.ndarray:
        """A cloth's vertices in the order the scene numbers them on a GPU (IC_MORTON): the Morton
        order of the fabric's rest positions, so that a GPU's warp of consecutive scene vertices
        is a compact patch of the cloth (its lanes walk and read the same few buckets), not a row
        across it. Computed once per fabric in use (kept in ``orders``, from the tables before)."""
        got = orders.get(id(fab)) or self._orders.get(id(fab))
        if got is None or got[0] is not fab:
            got = (fab, np.argsort(morton(fab.rest_positions), kind="stable").astype(np.int32))
        orders[id(fab)] = got
        return got[1]

    def _rebuild(self) -> None:
        vidx: list[np.ndarray] = []
        vcl: list[np.ndarray] = []
        cinfo: list[list[int]] = []
        cpar: list[list[float]] = []
        cslot: list[int] = []
        nt = 0  # scene vertices numbered so far
        orders: dict[int, tuple[Fabric, np.ndarray]] = {}  # the fabrics' orders in use
        for si, sc in enumerate(self.scenes.values()):
            if len(sc.handles) < 2:
                continue
            first, t0 = len(cinfo), nt  # the scene's first cloth and vertex
            t1 = t0 + sum(self.cloths[h].fabric.n_vertices for h in sc.handles)
            for h in sc.handles:
                k, slot, m = len(cinfo), self.rec[h], self.cloths[h].params.material
                n = self.cloths[h].fabric.n_vertices
                cinfo.append([slot.vbase, n, si, first, len(sc.handles), t0, t1, nt])
                nt += n
                cpar.append([m.thickness * INTER_COLLISION_MARGIN, m.contact_stiffness])
                cslot.append(slot.slot if self.cloths[h].params.features.colliders else -1)
                order = self._order(self.cloths[h].fabric, orders) if self.morton else np.arange(n, dtype=np.int32)
                vidx.append(slot.vbase + order)
                vcl.append(np.full(n, k, np.int32))
        self._orders = orders
        self._dirty = False
        self._bound = None
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
            (self._cslot, np.asarray(cslot, np.int32)),
        ):
            if arr.capacity < len(host):
                arr.resize(_pow2_at_least(len(host)))
            arr.write(0, host)
        per_vertex: tuple[DevArray, ...] = (self._next, self._count, self._nbr, self._xs0, self._xa, self._xb)
        per_vertex += (self._xs1, self._mv, self._moved, self._xnbr, self._xcount)  # the later rounds'

        for arr, n in ((self._box, self.n_cloths), (self._active, self.n_cloths), *((a, nv) for a in per_vertex)):
            if arr.capacity < n:
                arr.resize(_pow2_at_least(n))
        self._nb = _pow2_at_least(2 * nv)
        if self._heads.capacity < self._nb:
            self._heads.resize(self._nb)
        self._dmax = dmax = float(np.max(np.asarray(cpar)[:, 0]))
        self._inv = 0.5 / (dmax * INTER_COLLISION_REACH) if dmax > 0 else 0.0
        self._nmoved.write(0, np.zeros(2, np.int32))  # then ic_finish sets them back to 0
        self._xcount.write(0, np.zeros(nv, np.int32))  # then ic_refind sets them back to 0
        if self._inv > 0.0:  # every head -1 before the first step's inserts (then ic_finish clears them)
            clear = self.kernels()["ic_clear"]
            clear(self.dev.queue, (self._nb,), None, self._heads.buf, np.int32(self._nb))

    def _bind(self, dt: float) -> None:
        """The kernels' arguments, set once per table rebuild or buffer growth, and the launches."""
        k = self.kernels()
        mem = self.mem
        pos, vel, ci, coll, cslot = mem.pos.buf, mem.vel.buf, mem.ci.buf, mem.coll.buf, self._cslot.buf
        ncl, nv, nb = np.int32(self.n_cloths), np.int32(self.n_vertices), np.int32(self._nb)
        inv, mask = np.float32(self._inv), np.uint32(self._nb - 1)
        dmax, sk = np.float32(self._dmax), np.float32(self._dmax * INTER_COLLISION_SKIN)
        vidx, vcl, cinfo, cpar = self._vidx.buf, self._vcl.buf, self._cinfo.buf, self._cpar.buf
        box, active, heads, nxt = self._box.buf, self._active.buf, self._heads.buf, self._next.buf
        nbr, count, xs0, xa, xb = self._nbr.buf, self._count.buf, self._xs0.buf, self._xa.buf, self._xb.buf
        xs1, mv, moved, nmoved = self._xs1.buf, self._mv.buf, self._moved.buf, self._nmoved.buf
        k["ic_bounds"].set_args(pos, cinfo, cpar, box)
        k["ic_active"].set_args(cinfo, box, active, ncl)
        insert = (
            pos,
            vidx,
            vcl,
            cinfo,
            active,
            heads,
            nxt,
            xs0,
            nv,
            inv,
            mask,
            count,
            xs1,
            mv,
            moved,
            nmoved,
            sk,
        )
        k["ic_insert"].set_args(*insert, np.int32(0))
        k["ic_insert_later"].set_args(*insert, np.int32(1))
        find = (xs0, vcl, cinfo, cpar, active, heads, nxt, nbr, count, xb, cslot, ci, coll, nv, inv, mask, dmax, xs1)
        k["ic_find"].set_args(*find)
        xnbr, xcount = self._xnbr.buf, self._xcount.buf
        k["ic_refind"].set_args(*find, mv, xnbr, xcount, moved, nmoved, np.int32(0))
        k["ic_rewalk"].set_args(*find, mv, xnbr, xcount, moved, nmoved, np.int32(1))
        pass_args = (vcl, cinfo, cpar, heads, nxt, nbr, count, cslot, ci, coll, nv, inv, mask, dmax)
        k["ic_pass"].set_args(xs0, xa, xb, *pass_args)
        k["ic_pass_ba"].set_args(xs0, xb, xa, *pass_args)
        passes = INTER_COLLISION_PASSES // INTER_COLLISION_ROUNDS  # each round's
        last = xa if passes % 2 == 0 else xb
        k["ic_finish"].set_args(pos, vel, vidx, xs0, last, heads, nmoved, nv, nb, np.float32(1.0 / dt))
        self._dt = dt
        per_vertex = (self.n_vertices,)
        cg = self.cg
        inserts = (-(-self.n_vertices // cg) * cg,)  # ic_insert's groups: whole ones
        insert_group = (cg,) if cg > 1 else None

        def one_round(later: bool) -> list[tuple[cl.Kernel, tuple[int], tuple[int] | None]]:
            return [
                (k["ic_bounds"], (self.n_cloths * self.ls,), (self.ls,)),
                (k["ic_active"], (self.n_cloths,), None),
                (k["ic_insert_later" if later else "ic_insert"], inserts, insert_group),
                *([(k["ic_rewalk"], per_vertex, None)] if later else []),
                (k["ic_refind" if later else "ic_find"], per_vertex, None),
                # ic_find ran the first pass (into xb); then xb into xa, xa into xb, ...
                *((k["ic_pass" if p % 2 == 0 else "ic_pass_ba"], per_vertex, None) for p in range(1, passes)),
                (k["ic_finish"], per_vertex, None),
            ]

        # the candidates found again each round: by the later rounds from the first's skin lists
        self._launches = one_round(False) + one_round(True) * (INTER_COLLISION_ROUNDS - 1)
        self._finish = k["ic_finish"]
        self._bound = (pos, vel, ci, coll)

    def step(self, dt: float) -> None:
        """The scenes' inter-cloth collision, after the solvers' launches of a step."""
        if self._dirty:
            self._rebuild()
        if self.n_cloths < 2 or self._inv <= 0.0:
            return
        mem = self.mem
        if self._bound is None or any(
            a is not b for a, b in zip(self._bound, (mem.pos.buf, mem.vel.buf, mem.ci.buf, mem.coll.buf), strict=True)
        ):
            self._bind(dt)
        elif dt != self._dt:
            assert self._finish is not None
            self._finish.set_arg(9, np.float32(1.0 / dt))
            self._dt = dt
        q = self.dev.queue
        for kernel, gsize, lsize in self._launches:
            cl.enqueue_nd_range_kernel(q, kernel, gsize, lsize)
