"""The OpenCL world: every live cloth merged into structure-of-arrays device buffers.

The CLWorld keeps the World's bookkeeping (cloth slots, fabrics, tables, colliders, groups) and
owns its parts, each built once in its constructor and given what it reads (none imports this
module): the device arrays (``mem``, buffers.DeviceMemory), the launch groups' set-up and
launches (``launches``, launch.GroupLaunches), the pin targets (``targets``,
targets.PinTargets), the frame readback (``readback``, frames.FrameReadback) and, with
``device_encode``, the frame encoder (``device_frames``, devencode.DeviceFrames), and the
scenes' inter-cloth collision after each step (``scene_collision``, scenes.SceneCollision, 1.7).

Layout (see kernels/layout.h):
- vertex buffers (positions with inverse mass in w, velocities, previous positions, pin
  targets, normals) hold each cloth in a contiguous range handed out by a first-fit allocator,
  so adding or removing a cloth never moves the others; an added cloth's rows are staged and
  the tick's adds written together before anything touches those buffers (one non-blocking write
  per buffer per run of adjacent ranges, ``_write_staged``), not several writes per cloth;
- one int arena holds each *fabric* once (links sorted by colour, colour offsets, tether
  anchors, Jacobi adjacency, vertex-triangle lists): cloths of one fabric share it;
- per-cloth int/float tables carry ranges and parameters; kernels read them by cloth index.

Cloths are grouped by the kernels they need (feature set, and substeps or local-memory fit):
one program per build-option set, one launch (or one batch sequence) per group (launch.py);
pin targets are gathered into one upload per step (targets.py).

A frame is read back whole: one ``pack_rows`` launch gathers every cloth's positions (xyz,
without the inverse mass) back to back in the layout's order into one device buffer, and one
non-blocking copy brings it into a host buffer mapped from ``ALLOC_HOST_PTR`` memory (pinned
where the driver does that), reused from tick to tick. ``frame_async`` returns at once; its
``wait`` waits on that copy's event only (frames.py). Built with ``device_encode``, a tick's
``fetch_async(roster, tick)`` is encoded on the device instead, straight from the float4 ``pos``
and ``nrm`` buffers (devencode.py), predictive states (1.5) included.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Hashable

import numpy as np

from ..fabric import Fabric
from ..frame import Layout, PendingFrame
from ..params import ClothParams, Features
from ..roster import Roster
from ..scenes import Scene
from ..wire import PendingWire
from ..world import Cloth, World, inverse_masses
from .buffers import ClothSlot, DeviceMemory, FabricSlot, fabric_blob
from .devencode import DeviceFrames
from .device import Device, layout
from .frames import FrameReadback
from .launch import Group, GroupLaunches
from .meshes import MeshCollision
from .scenes import SceneCollision
from .targets import PinTargets

log = logging.getLogger(__name__)

L = layout()


class CLWorld(World):
    """The World on an OpenCL device, composed of parts it owns: its device memory (``mem``),
    the launch groups (``launches``), the pending pin targets (``targets``), the frame readback
    (``readback``) and, with ``device_encode``, the frame encoder (``device_frames``)."""

    def __init__(
        self,
        strategy: str = "workgroup",
        device: str | Device | None = None,
        local_size: int | None = None,
        use_local: bool | None = None,
        link_group_size: int = 256,
        chunk: int | None = None,
        pack_lanes: int | None = None,
        device_encode: bool = False,
    ) -> None:
        super().__init__()
        if strategy not in ("workgroup", "coloured", "jacobi"):
            raise ValueError(f"unknown OpenCL strategy {strategy!r}")
        self.solver = strategy
        self.dev = device if isinstance(device, Device) else Device(device)
        self.device_name = self.dev.info.name
        env_ls = os.environ.get("DRAPE_WG_SIZE")
        # GPU: 256 work-items per cloth held in local memory; a big cloth on the global-memory
        # path takes as many as the kernel allows (it is alone on its compute unit anyway).
        # CPU (PoCL): one work-item per cloth, i.e. the talk's serial loop in colour order with
        # no barrier bookkeeping, fastest there (docs/benchmarks.md); cloths spread over cores.
        gpu = self.dev.info.is_gpu
        self.max_local_size = int(local_size or env_ls or (256 if gpu else 1))
        self.max_global_path_size = int(local_size or env_ls or (1024 if gpu else 1))
        self.use_local = use_local  # None: when the cloth fits
        # CPU with one work-item per cloth: packs of cloths of one fabric, one work-item each,
        # the link solve vectorised across the pack (launch.py, kernels/pack.cl). Never on a GPU.
        # The width: the argument, else DRAPE_PACK_LANES, else what the device check found runs.
        lanes = pack_lanes if pack_lanes is not None else self.dev.info.pack_lanes
        self.pack_lanes = lanes if (not gpu and self.max_local_size == 1 and strategy == "workgroup") else 0
        if self.pack_lanes not in (0, 2, 4, 8, 16):
            raise ValueError(f"pack_lanes must be 0, 2, 4, 8 or 16, got {self.pack_lanes}")
        self.link_group_size = link_group_size
        # vertices per work-group in the coloured/Jacobi vertex phases: big cloths spread out
        self.chunk = int(chunk or os.environ.get("DRAPE_CHUNK", "1024"))
        self.mem = mem = DeviceMemory(self.dev, jacobi=strategy == "jacobi")
        self.coll_host = np.zeros((1, L["COLLIDER_WORDS"], 4), np.float32)
        self._coll_dirty = False
        self._moved: set[int] = set()
        # the vertex ranges of the cloths added since the last flush: handle -> (vbase, float4
        # positions with inverse mass, float4 velocities or None), written together (_write_staged)
        self._staged: dict[int, tuple[int, np.ndarray, np.ndarray | None]] = {}
        self.fabrics: dict[str, FabricSlot] = {}
        self.rec: dict[int, ClothSlot] = {}
        self.ci_host = np.zeros((64, L["CI_STRIDE"]), np.int32)
        self.cf_host = np.zeros((64, L["CF_STRIDE"]), np.float32)
        self._free_slots: list[int] = list(range(63, -1, -1))
        self._tables_dirty = True
        self.groups: dict[tuple, Group] = {}
        self._group_keys: dict[tuple, tuple[tuple, bool, int]] = {}  # _group_key's, by its inputs
        base_options = [*Features().build_options(), "-DUSE_LOCAL=0"]
        self.launches = GroupLaunches(
            self.dev,
            mem,
            self.rec,
            self.cloths,
            strategy,
            self.chunk,
            link_group_size,
            self.max_local_size,
            self.max_global_path_size,
        )
        self.targets = PinTargets(self.dev, mem, self.rec, base_options)
        self.readback = FrameReadback(self.dev, mem, self.rec, base_options)
        # the ticks' bytes encoded on the device (devencode.py)
        self.device_frames = DeviceFrames(self.dev, mem, self.rec, self.readback) if device_encode else None
        # 1.7: cloths of one scene kept apart after each step (nothing built while no scene has two)
        self.scene_collision = SceneCollision(self.dev, mem, self.rec, self.cloths, self.scenes)
        # 1.8: cloths kept out of their meshes after each step (nothing built while none has one)
        self.mesh_collision = MeshCollision(self.dev, mem, self.rec, self.cloths, self.scenes, self.mesh_colliders)

    # --- a tick's output ---------------------------------------------------------------------
    def fetch_async(self, roster: Roster, tick: int) -> PendingWire:
        self._write_staged()  # a frame asked for before a step shows the adds at their start
        if self.device_frames is not None:
            pending = self.device_frames.encode(roster, tick, self.layout(), self.steps)
        else:
            pending = super().fetch_async(roster, tick)
        # the step and its read-back submitted now: a driver may hold enqueued commands until a
        # flush or a wait, and the pipelined tick waits for this frame a tick later
        self.dev.queue.flush()
        return pending

    def warm_wire(self) -> None:
        if self.device_frames is not None:  # the frame encoder's programs: the tick thread never compiles
            self.device_frames.build_all()

    # --- allocation -----------------------------------------------------------------------
    def _fabric_slot(self, f: Fabric) -> FabricSlot:
        fs = self.fabrics.get(f.key)
        if fs is None:
            blob, offsets = fabric_blob(f)
            base = self.mem.alloc(self.mem.fab_alloc, [self.mem.fab], len(blob))
            self.mem.fab.write(base, blob)
            fs = FabricSlot(base, len(blob), 0, offsets)
            self.fabrics[f.key] = fs
        fs.refs += 1
        return fs

    def _table_slot(self) -> int:
        if not self._free_slots:
            old = len(self.ci_host)
            self.ci_host = np.concatenate([self.ci_host, np.zeros_like(self.ci_host)])
            self.cf_host = np.concatenate([self.cf_host, np.zeros_like(self.cf_host)])
            self.mem.ci.resize(2 * old)
            self.mem.cf.resize(2 * old)
            self._free_slots = list(range(2 * old - 1, old - 1, -1))
        return self._free_slots.pop()

    # --- World hooks -----------------------------------------------------------------------
    def _add(self, cloth: Cloth, positions: np.ndarray | None, velocities: np.ndarray | None = None) -> None:
        f = cloth.fabric
        n = f.n_vertices
        vbase = self.mem.alloc(self.mem.vert, self.mem.vertex_arrays(), n)
        rec = ClothSlot(self._table_slot(), vbase, self._fabric_slot(f))
        self.rec[cloth.handle] = rec
        self.targets.note_vbase(cloth.handle, vbase)
        v = None
        if velocities is not None:  # protocol 1.3 resume: the velocity buffer is the state (xyz, w unused)
            v = np.zeros((n, 4), np.float32)
            v[:, :3] = velocities
        # written with the tick's other adds before anything reads or writes the vertex buffers
        self._staged[cloth.handle] = (vbase, self._vertex_rows(cloth, positions), v)
        self._write_tables(cloth, rec)
        self._regroup(cloth, rec)

    def _vertex_rows(self, cloth: Cloth, x: np.ndarray | None) -> np.ndarray:
        """A cloth's float4 rows: positions ``x`` (None: at rest), its inverse masses in w. At
        rest they are the fabric's rows for that mass, shared (read-only) by its cloths."""
        fs = self.rec[cloth.handle].fabric
        mass = cloth.params.material.mass
        rest = fs.rest_rows.get(mass)
        if rest is None:
            if len(fs.rest_rows) >= 16:  # many masses of one fabric: keep the latest few
                fs.rest_rows.clear()
            rest = np.empty((cloth.fabric.n_vertices, 4), np.float32)
            rest[:, :3] = cloth.fabric.rest_positions
            rest[:, 3] = inverse_masses(cloth.fabric, cloth.params)
            rest.flags.writeable = False
            fs.rest_rows[mass] = rest
        if x is None:
            return rest
        p = rest.copy()
        p[:, :3] = x
        return p

    def _write_vertices(self, vbase: int, p: np.ndarray, v: np.ndarray | None = None) -> None:
        """Rows ``p`` (float4, see _vertex_rows) as positions, previous positions and pin targets
        from ``vbase`` on, velocities ``v`` (zero if None), normals zero: one non-blocking write
        or fill per buffer."""
        mem = self.mem
        for arr in (mem.pos, mem.prev, mem.target, *([mem.pos2] if mem.pos2 is not None else [])):
            arr.write(vbase, p, blocking=False)
        if v is None:
            mem.vel.zero(vbase, len(p))
        else:
            mem.vel.write(vbase, v, blocking=False)
        mem.nrm.zero(vbase, len(p))

    def _write_staged(self) -> None:
        """The staged adds' vertex rows, one write per buffer per run of adjacent ranges (the
        allocator hands a tick's adds adjacent ranges while it has room): the adds of one tick
        cost a few device writes, not several per cloth. Called before anything that reads or
        writes the vertex buffers (a step, a frame, pin targets, a reset, a mass change)."""
        if not self._staged:
            return
        entries = sorted(self._staged.values(), key=lambda e: e[0])
        self._staged.clear()
        runs: list[list[tuple[int, np.ndarray, np.ndarray | None]]] = [[entries[0]]]
        for e in entries[1:]:
            last = runs[-1][-1]
            if last[0] + len(last[1]) == e[0]:
                runs[-1].append(e)
            else:
                runs.append([e])
        for run in runs:
            p = np.concatenate([e[1] for e in run]) if len(run) > 1 else run[0][1]
            v = None
            if any(e[2] is not None for e in run):
                v = np.concatenate([e[2] if e[2] is not None else np.zeros_like(e[1]) for e in run])
            self._write_vertices(run[0][0], p, v)

    def _upload_targets(self) -> None:
        """The pending pin targets scattered (after the staged adds they may target)."""
        self._write_staged()
        self.targets.upload()

    def _write_tables(self, cloth: Cloth, rec: ClothSlot) -> None:
        f, p, m = cloth.fabric, cloth.params, cloth.params.material
        if p.features.xpbd and rec.lam_size < 2 * f.n_links:
            if rec.lam_size:
                self.mem.lam_alloc.release(rec.lam_base, rec.lam_size)
            rec.lam_size = 2 * f.n_links
            rec.lam_base = self.mem.alloc(self.mem.lam_alloc, [self.mem.lam], rec.lam_size)
        ci = self.ci_host[rec.slot]
        ci[:] = 0
        ci[L["CI_VBASE"]] = rec.vbase
        ci[L["CI_NVERTS"]] = f.n_vertices
        ci[L["CI_FAB"]] = rec.fabric.base
        ci[L["CI_NLINKS"]] = f.n_links
        ci[L["CI_NCOLOURS"]] = f.n_colours
        ci[L["CI_ITERS"]] = p.iterations
        ci[L["CI_SUBSTEPS"]] = p.substeps
        ci[L["CI_COLL"]] = rec.coll_base
        ci[L["CI_NCOLL"]] = len(cloth.colliders) if p.features.colliders else 0
        ci[L["CI_NTRIS"]] = len(f.triangles)
        ci[L["CI_LAM"]] = max(rec.lam_base, 0)
        for name, off in rec.fabric.offsets.items():
            ci[L[name]] = off
        cf = self.cf_host[rec.slot]
        cf[:] = 0
        cf[L["CF_GRAVITY"] : L["CF_GRAVITY"] + 3] = p.gravity
        cf[L["CF_WIND"] : L["CF_WIND"] + 3] = p.wind
        cf[L["CF_DAMP_SUB"]] = 1.0 - (1.0 - m.damping) ** (1.0 / p.substeps)
        cf[L["CF_STIFFNESS"] : L["CF_STIFFNESS"] + 3] = m.stiffness
        # beyond float32: the largest float32, whose alpha = c / h^2 is infinite, i.e. no correction
        cf[L["CF_COMPLIANCE"] : L["CF_COMPLIANCE"] + 3] = np.minimum(m.compliance, np.finfo(np.float32).max)
        cf[L["CF_FRICTION"]] = m.friction
        cf[L["CF_DRAG"]] = m.drag
        cf[L["CF_LIFT"]] = m.lift
        cf[L["CF_RHO"]] = m.air_density
        cf[L["CF_TETHER_LIMIT"]] = m.tether_limit
        cf[L["CF_CHEB_RHO"]] = p.chebyshev_rho
        cf[L["CF_THICKNESS"]] = m.thickness
        cf[L["CF_CONTACT_STIFFNESS"]] = m.contact_stiffness
        self._tables_dirty = True

    def _group_key(self, cloth: Cloth) -> tuple[tuple, bool, int]:
        """(group key, local memory, pack lanes) of the group the cloth joins (worked out once per
        fabric, features and substeps: a tick of many adds mostly repeats a few)."""
        memo = (cloth.fabric.key, cloth.params.features, cloth.params.substeps)
        got = self._group_keys.get(memo)
        if got is None:
            if len(self._group_keys) >= 1024:
                self._group_keys.clear()
            got = self._group_keys[memo] = self._work_out_group(cloth)
        return got

    def _work_out_group(self, cloth: Cloth) -> tuple[tuple, bool, int]:
        f = cloth.params.features
        if self.solver == "workgroup":
            budget = self.dev.info.local_mem - 1024
            fits = cloth.fabric.n_vertices * 16 <= budget
            local = fits if self.use_local is None else (self.use_local and fits)
            # CPU packs: as many lanes as the cloth's lanes fit in local memory (at least 2)
            W = self.pack_lanes
            per_lane = 4 * (4 * cloth.fabric.n_vertices + (cloth.fabric.n_links if f.xpbd else 0))
            while W > 2 and W * per_lane > budget:
                W //= 2
            if W and local and W * per_lane <= budget:
                return (f.key(), "pack", W), True, W
            return (f.key(), local), local, 0
        return (f.key(), cloth.params.substeps), False, 0

    def _regroup(self, cloth: Cloth, rec: ClothSlot) -> None:
        p = cloth.params
        self.launches.note(cloth.handle, rec.slot, rec.fabric.base, p.iterations, p.substeps)
        key, local, pack = self._group_key(cloth)
        if rec.group == key:
            self.groups[key].dirty = True
            return
        if rec.group is not None:
            self._leave_group(cloth.handle, rec)
        g = self.groups.get(key)
        if g is None:
            g = self.groups[key] = Group(key, cloth.params.features, local, pack=pack)
        g.handles.add(cloth.handle)
        g.dirty = True
        rec.group = key

    def _leave_group(self, handle: int, rec: ClothSlot) -> None:
        key = rec.group
        assert key is not None  # called for a cloth in a group only
        g = self.groups[key]
        g.handles.discard(handle)
        g.dirty = True
        if not g.handles:
            del self.groups[key]
        rec.group = None

    def _remove(self, cloth: Cloth) -> None:
        if self.targets.pending:  # targets still queued for this cloth must not land in its freed range
            self._upload_targets()
        self._staged.pop(cloth.handle, None)  # added and removed before a flush: never written
        rec = self.rec.pop(cloth.handle)
        self.targets.note_vbase(cloth.handle, -1)
        self._leave_group(cloth.handle, rec)
        mem = self.mem
        mem.vert.release(rec.vbase, cloth.fabric.n_vertices)
        if rec.lam_size:
            mem.lam_alloc.release(rec.lam_base, rec.lam_size)
        if rec.coll_cap:
            mem.coll_alloc.release(rec.coll_base, rec.coll_cap)
        self._moved.discard(cloth.handle)
        fs = rec.fabric
        fs.refs -= 1
        if fs.refs == 0:
            mem.fab_alloc.release(fs.base, fs.size)
            del self.fabrics[cloth.fabric.key]
        self.ci_host[rec.slot] = 0
        self._free_slots.append(rec.slot)
        self._tables_dirty = True

    def _set_params(self, cloth: Cloth, old: ClothParams) -> None:
        rec = self.rec[cloth.handle]
        if old.material.mass != cloth.params.material.mass:
            self._write_staged()
            x = self.mem.pos.read(rec.vbase, cloth.fabric.n_vertices)
            x[:, 3] = inverse_masses(cloth.fabric, cloth.params)
            self.mem.pos.write(rec.vbase, x, blocking=False)
        self._write_tables(cloth, rec)
        self._regroup(cloth, rec)
        m, was = cloth.params.material, old.material
        if cloth.scene is not None and (m.thickness, m.contact_stiffness) != (was.thickness, was.contact_stiffness):
            self.scene_collision.changed()
        if (m.thickness, m.friction) != (was.thickness, was.friction):
            self.mesh_collision.changed()

    def _scenes_changed(self) -> None:
        self.scene_collision.changed()
        self.mesh_collision.changed()

    def _move_scene_colliders(self, sc: Scene) -> bool:
        """A scene's colliders moved (1.7, the per-tick case): the scene's rows of every cloth of it
        in the collider table at once, the previous poses becoming the step's start."""
        k = len(sc.colliders)
        starts = np.fromiter(
            (self.rec[h].coll_base + len(self.cloths[h].own_colliders) for h in sc.handles), np.int64, len(sc.handles)
        )
        rows = (starts[:, None] + np.arange(k)).reshape(-1)
        self.coll_host[rows, 0:2] = self.coll_host[rows, 2:4]
        self.coll_host[rows, 2:4] = np.broadcast_to(sc.colliders, (len(starts), k, 2, 4)).reshape(-1, 2, 4)
        self._moved.update(sc.handles)
        self._coll_dirty = True
        return True

    def _set_colliders(self, cloth: Cloth) -> None:
        rec = self.rec[cloth.handle]
        new = cloth.colliders
        n = len(new)
        W = L["COLLIDER_WORDS"]
        mem = self.mem
        if n != rec.coll_cap:
            if rec.coll_cap:
                mem.coll_alloc.release(rec.coll_base, rec.coll_cap)
            rec.coll_cap = n
            rec.coll_base = mem.alloc(mem.coll_alloc, [mem.coll], n) if n else 0
            if mem.coll_alloc.capacity > len(self.coll_host):
                grown = np.zeros((mem.coll_alloc.capacity, W, 4), np.float32)
                grown[: len(self.coll_host)] = self.coll_host
                self.coll_host = grown
            self.coll_host[rec.coll_base : rec.coll_base + n, 0:2] = new  # starts where it is
        else:
            self.coll_host[rec.coll_base : rec.coll_base + n, 0:2] = self.coll_host[
                rec.coll_base : rec.coll_base + n, 2:4
            ]
        self.coll_host[rec.coll_base : rec.coll_base + n, 2:4] = new
        self._coll_dirty = True
        self._moved.add(cloth.handle)
        self._write_tables(cloth, rec)

    def _reset(self, cloth: Cloth, positions: np.ndarray) -> None:
        staged = self._staged.get(cloth.handle)
        if staged is not None:  # added this tick: it starts at ``positions`` at rest
            self._staged[cloth.handle] = (staged[0], self._vertex_rows(cloth, positions), None)
            return
        if self.targets.pending:  # earlier pin targets first: the reset puts the pins back too
            self._upload_targets()
        self._write_vertices(self.rec[cloth.handle].vbase, self._vertex_rows(cloth, positions))

    # --- stepping ---------------------------------------------------------------------------
    def _flush(self) -> None:
        mem = self.mem
        self._write_staged()
        if self.targets.pending:
            self.targets.upload()
        if self._tables_dirty:  # copies: the writes do not wait, and the host tables change on
            n = len(self.ci_host)
            if mem.ci.capacity < n:
                mem.ci.resize(n)
                mem.cf.resize(n)
            mem.ci.write(0, self.ci_host.copy(), blocking=False)
            mem.cf.write(0, self.cf_host.copy(), blocking=False)
            self._tables_dirty = False
        if self._coll_dirty:
            coll = self.coll_host[: mem.coll.capacity].reshape(-1, 4 * L["COLLIDER_WORDS"])
            mem.coll.write(0, coll.copy(), blocking=False)
            self._coll_dirty = False
        for g in self.groups.values():
            if g.dirty:
                self.launches.build_group(g)

    def build_key(self, fabric: Fabric, params: ClothParams) -> Hashable:
        """The group such a cloth joins: its features, local or global memory, pack lanes (a big
        cloth needs another program than a small one of the same features)."""
        return self._group_key(Cloth(0, fabric, params))[0]

    def ready(self, fabric: Fabric, params: ClothParams) -> bool:
        _, local, pack = self._group_key(Cloth(0, fabric, params))
        return self.dev.built(self.launches.options_for(params.features, local, pack))

    def prepare(self, fabric: Fabric, params: ClothParams) -> None:
        """Build the kernels of the group such a cloth joins (Device.program is thread-safe and
        builds without blocking the other threads' use of built kernels)."""
        _, local, pack = self._group_key(Cloth(0, fabric, params))
        opts = self.launches.options_for(params.features, local, pack)
        if pack:
            names = ["pack_step"]
        elif self.solver == "workgroup":
            names = ["wg_step"]
        else:
            names = [
                "cl_predict",
                "cl_finish",
                "cl_normals",
                "copy_positions",
                "cl_links" if self.solver == "coloured" else "jacobi_iter",
            ]
        for name in names:
            self.dev.kernel(opts, name)

    def step(self, dt: float) -> None:
        self._flush()
        self.readback.mark_step()  # device time of the step: frames.py
        self.mesh_collision.save()
        self.launches.step(self.groups.values(), dt)
        self.scene_collision.step(dt)
        self.mesh_collision.step(dt)
        self.steps += 1
        self._after_step()

    def _after_step(self) -> None:
        """A collider not moved again before the next step stays where it is."""
        if not self._moved:
            return
        for h in self._moved:
            rec = self.rec[h]
            sl = slice(rec.coll_base, rec.coll_base + rec.coll_cap)
            self.coll_host[sl, 0:2] = self.coll_host[sl, 2:4]
        self._moved.clear()
        self._coll_dirty = True

    def sync(self) -> None:
        self.dev.queue.finish()

    def close(self) -> None:
        self.dev.queue.finish()
        if self.device_frames is not None:
            self.device_frames.close()

    # --- parts' hooks --------------------------------------------------------------------------
    def _set_targets(self, cloth: Cloth, idx: np.ndarray, targets: np.ndarray) -> None:
        self.targets.add(cloth.handle, idx, targets)

    def _set_targets_many(self, handles: list[int], indices: list[np.ndarray], targets: list[np.ndarray]) -> None:
        self.targets.add_many(handles, indices, targets)

    def _set_targets_block(self, handles: np.ndarray, idx: np.ndarray, targets: np.ndarray) -> None:
        self.targets.add_block(handles, idx, targets)

    def _layout_changed(self, layout: Layout) -> None:
        self.readback.layout_changed(layout)

    def frame_async(self) -> PendingFrame:
        self._write_staged()
        return self.readback.frame_async(self.layout(), self.steps)
