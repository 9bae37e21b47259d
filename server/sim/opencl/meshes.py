"""The OpenCL world's mesh colliders (a part the CLWorld owns; issue 22, protocol 1.8): once per
step, after every launch group's solve and the scenes' inter-cloth collision, each cloth with a
mesh (its own, then its scene's) is kept out of it on the device by kernels/meshcollide.cl, the
float64 twin being drape.server.sim.meshes.collide_mesh.

Nothing is built or launched while no cloth has a mesh: a World without meshes pays nothing, and
the solvers' programs keep their build options. The meshes (triangles, grid) are uploaded once
per distinct mesh whenever one is set or re-posed; the attachments' table when a mesh or a scene's
membership changes; the poses (start inverted, end inverted, end) when one moved.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pyopencl as cl

from ..meshcolliders import MeshCollider, MeshColliders
from ..meshes import (
    MESH_DEEP_TIE,
    MESH_EDGE_TOLERANCE,
    MESH_GUARD_BACKOFF,
    MESH_MAX_QUERY_CELLS,
    MESH_PASSES,
    MESH_SLIDES,
    invert_pose,
    mesh_thickness,
)
from ..scenes import Scene
from ..world import Cloth
from .buffers import ClothSlot, DevArray, DeviceMemory
from .device import Device
from .phase import WorldPhase

SOURCE = "meshcollide.cl"
KERNELS = ("mc_save", "mc_collide")
PAR_ROWS = 10  # float4 rows per attachment (kernels/meshcollide.cl's apar)


def _upload(arr: DevArray, host: np.ndarray) -> None:
    """``host`` into ``arr``, grown to fit; a buffer four times larger than it needs is given
    back (a removed mesh's memory)."""
    want = 1 << max(6, (len(host) - 1).bit_length()) if len(host) else 64
    if arr.capacity < len(host) or arr.capacity > 4 * want:
        arr.resize(want)
    arr.write(0, host)


class MeshCollision(WorldPhase):
    """Mesh collision of a World's cloths, given the World's memory, slots, cloths, scenes and meshes."""

    SOURCE, KERNELS = SOURCE, KERNELS  # the module's names, the phase's program

    def __init__(
        self,
        dev: Device,
        mem: DeviceMemory,
        rec: Mapping[int, ClothSlot],
        cloths: Mapping[int, Cloth],
        scenes: Mapping[str, Scene],
        meshes: MeshColliders,
    ) -> None:
        super().__init__(dev, mem, rec, cloths, scenes)
        self.meshes = meshes
        self._version = -1
        self._layers: list[tuple[int, int]] = []  # (first attachment, attachments) per layer
        self._att_mc: list[MeshCollider] = []
        self._att_h: list[int] = []
        self._poses_stale = True  # the poses' table differs from the meshes' poses
        self._mtri = DevArray(dev, np.float32, 4)
        self._mcell = DevArray(dev, np.int32, 1)
        self._mlist = DevArray(dev, np.int32, 1)
        self._minfo = DevArray(dev, np.int32, 8)
        self._mgeom = DevArray(dev, np.float32, 4)
        self._att = DevArray(dev, np.int32, 4)
        self._apar = DevArray(dev, np.float32, 4 * PAR_ROWS)
        self._start = DevArray(dev, np.float32, 4)
        self.n_attachments = 0

    def build_options(self) -> list[str]:
        return [
            f"-DMC_LS={self.ls}",
            f"-DMESH_PASSES={MESH_PASSES}",
            f"-DMESH_SLIDES={MESH_SLIDES}",
            f"-DMESH_EDGE_TOLERANCE={MESH_EDGE_TOLERANCE!r}f",
            f"-DMESH_GUARD_BACKOFF={MESH_GUARD_BACKOFF!r}f",
            f"-DMESH_MAX_QUERY_CELLS={MESH_MAX_QUERY_CELLS}",
            f"-DMESH_DEEP_TIE={MESH_DEEP_TIE!r}f",
        ]

    def _upload_meshes(self) -> dict[int, int]:
        """Every distinct mesh in use on the device; its index by id(mesh)."""
        index: dict[int, int] = {}
        tris: list[np.ndarray] = []
        cells: list[np.ndarray] = []
        lists: list[np.ndarray] = []
        info: list[list[int]] = []
        geom: list[list[float]] = []
        nt = nc = nl = 0
        for mc in (*self.meshes.own.values(), *self.meshes.scene.values()):
            if id(mc.mesh) in index:
                continue
            index[id(mc.mesh)] = len(info)
            m, g = mc.mesh, mc.grid
            t = m.vertices[m.triangles]
            e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
            n = np.cross(e1, e2)
            n /= np.linalg.norm(n, axis=1)[:, None]
            rows = np.zeros((len(t), 4, 4), np.float32)
            rows[:, 0, :3], rows[:, 1, :3], rows[:, 2, :3], rows[:, 3, :3] = t[:, 0], e1, e2, n
            tris.append(rows.reshape(-1, 4))
            cells.append(g.start)
            lists.append(g.tris)
            info.append([nt, len(t), nc, nl, *g.dims.tolist(), 0])
            geom.append([*g.origin.tolist(), 1.0 / g.cell])
            nt, nc, nl = nt + len(t), nc + len(g.start), nl + len(g.tris)
        if info:
            _upload(self._mtri, np.concatenate(tris))
            _upload(self._mcell, np.concatenate(cells))
            _upload(self._mlist, np.concatenate(lists))
            _upload(self._minfo, np.asarray(info, np.int32))
            _upload(self._mgeom, np.asarray(geom, np.float32))
        else:  # the last mesh went: its memory given back
            for arr in (self._mtri, self._mcell, self._mlist, self._minfo, self._mgeom):
                _upload(arr, np.zeros((0, arr.width), arr.dtype))
        return index

    def _rebuild(self) -> None:
        index = self._upload_meshes()
        att: list[list[int]] = []
        self._att_mc, self._att_h, self._layers = [], [], []
        s = 0
        for layer in self.meshes.layers(self.scenes):
            self._layers.append((len(att), len(layer)))
            for h, mc in layer:
                n = self.cloths[h].fabric.n_vertices
                att.append([self.rec[h].vbase, n, index[id(mc.mesh)], s])
                self._att_mc.append(mc)
                self._att_h.append(h)
                s += n
        self.n_attachments = len(att)
        if att:
            _upload(self._att, np.asarray(att, np.int32))
            if self._start.capacity < s:
                self._start.resize(1 << max(6, (s - 1).bit_length()))
        self._version, self._dirty, self._poses_stale = self.meshes.version, False, True

    def _upload_poses(self) -> None:
        blocks: dict[int, np.ndarray] = {}
        rows = np.zeros((self.n_attachments, PAR_ROWS, 4), np.float32)
        for k, (h, mc) in enumerate(zip(self._att_h, self._att_mc, strict=True)):
            b = blocks.get(id(mc))
            if b is None:
                b = blocks[id(mc)] = np.concatenate([invert_pose(mc.pose_prev), invert_pose(mc.pose), mc.pose])
            rows[k, :9] = b
            m = self.cloths[h].params.material
            rows[k, 9, :3] = mesh_thickness(m.thickness), m.friction, float(mc.fresh)
        _upload(self._apar, rows.reshape(len(rows), -1))

    def save(self) -> None:
        """Before a step's solve: the positions it starts from."""
        if self._dirty or self._version != self.meshes.version:
            self._rebuild()
        if not self.n_attachments:
            return
        k = self.kernels()
        k["mc_save"](
            self.dev.queue,
            (self.n_attachments * self.ls,),
            (self.ls,),
            self.mem.pos.buf,
            self._att.buf,
            self._start.buf,
        )

    def step(self, dt: float) -> None:
        """The mesh collision, after the solvers' launches and the scenes' of a step."""
        moved = self.meshes.moved
        if self.n_attachments:
            if moved or self._poses_stale:
                self._upload_poses()
            self.enqueue(dt)
        # a pose moved this step becomes the next step's start: the table changes once more
        self._poses_stale = moved
        self.meshes.stepped()

    def enqueue(self, dt: float, kernel: cl.Kernel | None = None) -> None:
        """``mc_collide`` over every layer of attachments, as uploaded; ``kernel``: another build
        of it with the same arguments (meshab's A/B of two versions)."""
        k = kernel if kernel is not None else self.kernels()["mc_collide"]
        q, mem = self.dev.queue, self.mem
        for first, n in self._layers:
            k(
                q,
                (n * self.ls,),
                (self.ls,),
                mem.pos.buf,
                mem.vel.buf,
                self._start.buf,
                self._att.buf,
                self._apar.buf,
                self._mtri.buf,
                self._mcell.buf,
                self._mlist.buf,
                self._minfo.buf,
                self._mgeom.buf,
                np.float32(1.0 / dt),
                np.int32(first),
            )
