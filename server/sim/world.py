"""A world of many cloths stepped together: the interface the tick loop drives.

``drape.server.sim.make_world(solver)`` returns a ``ReferenceWorld`` (here: numpy, float64, the
tests' ground truth) or a ``CLWorld`` (drape.server.sim.opencl.clworld: OpenCL work-group,
coloured or Jacobi solver). Both keep the same bookkeeping: cloths are added and removed between
steps without touching the others, each with its own parameters, pin targets and colliders.
The World is the one owner of every cloth's parameters (``world.cloths[h].params``).

A tick's output is ``fetch_async(roster, tick)``: a pending :class:`~.wire.Wire` of wire-ready
bytes, one payload per publication of the :class:`~.roster.Roster` (host-encoded here by
statecodec.py; an OpenCL World may encode them on the device). Underneath, a step's result is a
:class:`Frame` (``frame_async`` / ``fetch``): every cloth's positions back to back in ONE contiguous
(N, 3) float32 host array (cloth ``i`` of the frame in rows ``offsets[i]:offsets[i + 1]``, in
the order of ``handles``), read back in one copy into a host buffer the World reuses (frame.py).
Frames are valid until their buffer is reused: the World keeps at least the last two fetched
frames intact; a consumer that needs one longer ``hold()``s it and ``release()``s it when done.
"""

from __future__ import annotations

import functools
import itertools
import logging
from abc import ABC, abstractmethod
from collections.abc import Hashable
from dataclasses import dataclass, field

import numpy as np

from . import reference
from .fabric import Fabric, vertex_masses
from .frame import Frame, FramePool, HostBuffer, Layout, PendingFrame  # noqa: F401  re-exported
from .meshcolliders import MeshColliders
from .meshes import CollisionMesh, collide_mesh
from .params import MAX_COLLIDERS_PER_CLOTH, ClothParams
from .roster import Roster
from .scenes import MAX_SCENE_CLOTHS, MAX_SCENE_COLLIDERS, Scene, SceneCloth, inter_collide
from .wire import HostWire, KeyBuffers, PendingWire

log = logging.getLogger(__name__)


@dataclass
class Cloth:
    handle: int
    fabric: Fabric
    params: ClothParams
    colliders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 4), np.float32))  # own + scene's
    scene: str | None = None  # 1.7: the scene it collides in with the scene's other cloths
    own_colliders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 4), np.float32))


class World(ABC):
    solver: str = "?"

    def __init__(self) -> None:
        self.cloths: dict[int, Cloth] = {}
        self._handles = itertools.count(1)
        self.steps = 0
        self._layout: Layout | None = None
        self._layout_version = 0
        self._live = np.zeros(64, bool)  # by handle (handles are never reused): set_pin_targets_block
        # by handle, what the layout is made of: a layout is a few vectorised gathers, not a pass
        # over the cloths in Python (a tick that adds or removes cloths rebuilds it)
        self._rows_of = np.zeros(64, np.int64)  # vertices
        self._normals_of = np.zeros(64, bool)  # the state carries normals
        self._key_buffers = KeyBuffers()  # the host-encoded payloads' buffers (wire.HostWire)
        self.scenes: dict[str, Scene] = {}  # 1.7: a scene exists while it holds a cloth (scenes.py)
        self.mesh_colliders = MeshColliders()  # 1.8: the cloths' and scenes' meshes (meshcolliders.py)

    # --- cloth lifecycle -------------------------------------------------------------------
    def add(
        self,
        fabric: Fabric,
        params: ClothParams,
        positions: np.ndarray | None = None,
        velocities: np.ndarray | None = None,
        scene: str | None = None,
    ) -> int:
        """Add a cloth at ``positions`` (default: its rest pose) moving at ``velocities`` (m/s,
        default zero; protocol 1.3 ``resume``: a cloth continued from another server's state).
        Pinned vertices start at ``positions`` with their pin targets there, and keep zero velocity.
        ``scene`` (1.7): the cloth collides with the scene's other cloths and its colliders."""
        _validate(params)
        if scene is not None and len(self.scenes.get(scene, Scene(scene)).handles) >= MAX_SCENE_CLOTHS:
            raise ValueError(f"scene {scene!r} is full: {MAX_SCENE_CLOTHS} cloths")
        if positions is not None:
            positions = np.asarray(positions, np.float64).reshape(fabric.n_vertices, 3)
            if not np.all(np.isfinite(positions)):
                raise ValueError("positions must be finite")
        if velocities is not None:
            velocities = np.array(velocities, np.float64).reshape(fabric.n_vertices, 3)
            if not np.all(np.isfinite(velocities)):
                raise ValueError("velocities must be finite")
            velocities[fabric.pinned] = 0.0  # kinematic vertices move only with their targets
        h = next(self._handles)
        cloth = Cloth(h, fabric, params, scene=scene)
        self.cloths[h] = cloth
        try:
            self._add(cloth, positions, velocities)
        except BaseException:
            del self.cloths[h]
            raise
        if scene is not None:
            sc = self.scenes.setdefault(scene, Scene(scene))
            sc.handles.append(h)
            self._scenes_changed()
            if len(sc.colliders):
                self._apply_colliders(cloth)
        if h >= len(self._live):
            grow = max(h + 1, len(self._live))
            self._live = np.concatenate([self._live, np.zeros(grow, bool)])
            self._rows_of = np.concatenate([self._rows_of, np.zeros(grow, np.int64)])
            self._normals_of = np.concatenate([self._normals_of, np.zeros(grow, bool)])
        self._live[h] = True
        self._rows_of[h] = fabric.n_vertices
        self._normals_of[h] = params.features.normals
        self._layout = None
        return h

    def remove(self, handle: int) -> None:
        cloth = self.cloths.pop(handle)
        self._live[handle] = False
        self._remove(cloth)
        self._layout = None
        self.mesh_colliders.drop_cloth(handle)
        if cloth.scene is not None:
            sc = self.scenes[cloth.scene]
            sc.handles.remove(handle)
            if not sc.handles:
                del self.scenes[cloth.scene]
                self.mesh_colliders.drop_scene(cloth.scene)
            self._scenes_changed()

    def live(self, handles: np.ndarray) -> np.ndarray:
        """Which of ``handles`` are cloths of this World now: one bool per handle, vectorised."""
        h = np.asarray(handles, np.int64).reshape(-1)
        ok = (h >= 0) & (h < len(self._live))
        ok[ok] = self._live[h[ok]]
        return ok

    def set_params(self, handle: int, params: ClothParams) -> None:
        params.validate()
        cloth = self.cloths[handle]
        old = cloth.params
        cloth.params = params
        self._set_params(cloth, old)
        if old.features.normals != params.features.normals:
            self._normals_of[handle] = params.features.normals
            self._layout = None

    def prepare(self, fabric: Fabric, params: ClothParams) -> None:  # noqa: B027 (optional hook)
        """Build whatever a cloth of ``fabric`` and ``params`` will need (kernels) now, so that
        adding it later does not. Touches no cloth: may run on another thread than the ticks."""

    def build_key(self, fabric: Fabric, params: ClothParams) -> Hashable:
        """What a cloth of ``fabric`` and ``params`` shares its kernels by: two cloths of one key
        need the same programs (here: the feature set)."""
        return params.features.key()

    def ready(self, fabric: Fabric, params: ClothParams) -> bool:
        """Whether a cloth of ``fabric`` and ``params`` needs nothing built (see ``prepare``)."""
        return True

    def set_pin_targets(self, handle: int, indices: np.ndarray, targets: np.ndarray) -> None:
        """Where pinned vertices ``indices`` are at the end of the next step (interpolated
        over its substeps). Every index must be a pinned vertex of the cloth's fabric."""
        cloth = self.cloths[handle]
        idx = np.asarray(indices, np.int64).reshape(-1)
        tgt = np.asarray(targets, np.float64).reshape(-1, 3)
        if len(idx) != len(tgt):
            raise ValueError("one target per index")
        if idx.size and (idx.min() < 0 or idx.max() >= cloth.fabric.n_vertices):
            raise ValueError("pin index out of range")
        if idx.size and not cloth.fabric.pinned[idx].all():
            raise ValueError("only pinned vertices can be given targets")
        if not np.all(np.isfinite(tgt)):
            raise ValueError("targets must be finite")
        self._set_targets(cloth, idx, tgt)

    def set_pin_targets_many(
        self, handles: list[int], indices: list[np.ndarray], targets: list[np.ndarray], validated: bool = False
    ) -> None:
        """Pin targets of many cloths at once (one upload before the next step): cloth
        ``handles[j]`` gets ``targets[j]`` for its vertices ``indices[j]``. ``validated``: the
        caller has checked ranges, pinned vertices and finiteness (the service's handlers do)."""
        if not validated:
            for h, i, t in zip(handles, indices, targets, strict=True):
                self.set_pin_targets(h, i, t)
            return
        if handles:
            self._set_targets_many(handles, indices, targets)

    def _set_targets_many(self, handles: list[int], indices: list[np.ndarray], targets: list[np.ndarray]) -> None:
        for h, i, t in zip(handles, indices, targets, strict=True):
            self._set_targets(self.cloths[h], np.asarray(i, np.int64), np.asarray(t, np.float64).reshape(-1, 3))

    def set_pin_targets_block(
        self, handles: np.ndarray, indices: np.ndarray, targets: np.ndarray, validated: bool = False
    ) -> None:
        """Pin targets of many cloths that share one list of pinned vertices (protocol 1.4
        ``moves``): cloth ``handles[j]`` gets ``targets[j]`` ((n, k, 3)) for its vertices
        ``indices`` ((k,)), as ``set_pin_targets`` would, in one vectorised call (one upload
        before the next step). A later call of the same step wins where both set a vertex.
        ``validated``: the caller has checked that the handles are live and distinct, the
        indices distinct, in range and pinned in every cloth, the targets finite (the service's
        handlers and decoder do); otherwise they are checked here (ValueError, KeyError)."""
        h = np.asarray(handles, np.int64).reshape(-1)
        idx = np.asarray(indices, np.int64).reshape(-1)
        tgt = np.asarray(targets, np.float32).reshape(len(h), len(idx), 3)
        if not validated:
            missing = h[~self.live(h)]
            if len(missing):
                raise KeyError(int(missing[0]))
            if len(np.unique(h)) != len(h) or len(np.unique(idx)) != len(idx):
                raise ValueError("handles and indices must be distinct")
            if not np.all(np.isfinite(tgt)):
                raise ValueError("targets must be finite")
            checked: set[str] = set()
            for handle in h.tolist():
                f = self.cloths[handle].fabric
                if f.key in checked:
                    continue
                if idx.size and (idx.min() < 0 or idx.max() >= f.n_vertices):
                    raise ValueError("pin index out of range")
                if idx.size and not f.pinned[idx].all():
                    raise ValueError("only pinned vertices can be given targets")
                checked.add(f.key)
        if len(h) and len(idx):
            self._set_targets_block(h, idx, tgt)

    def _set_targets_block(self, handles: np.ndarray, idx: np.ndarray, targets: np.ndarray) -> None:
        """Back-end hook of set_pin_targets_block (checked arguments); per cloth unless overridden."""
        for j, h in enumerate(handles.tolist()):
            self._set_targets(self.cloths[h], idx, targets[j].astype(np.float64))

    def set_colliders(self, handle: int, packed: np.ndarray) -> None:
        """Collider poses (see params.pack_colliders) for the end of the next step."""
        cloth = self.cloths[handle]
        packed = np.asarray(packed, np.float32).reshape(-1, 2, 4)
        if len(packed) > MAX_COLLIDERS_PER_CLOTH:
            raise ValueError(f"at most {MAX_COLLIDERS_PER_CLOTH} colliders per cloth")
        if not np.all(np.isfinite(packed)):
            raise ValueError("collider values must be finite")
        scene = self.scenes[cloth.scene].colliders if cloth.scene is not None else packed[:0]
        if len(packed) + len(scene) > MAX_COLLIDERS_PER_CLOTH:
            raise ValueError(f"at most {MAX_COLLIDERS_PER_CLOTH} colliders per cloth, its scene's included")
        cloth.own_colliders = packed.copy()
        self._apply_colliders(cloth)

    def set_scene_colliders(self, scene: str, packed: np.ndarray) -> None:
        """A scene's collider poses for the end of the next step (1.7), for every cloth of it
        beside its own colliders (each cloth's rows are those of its own, then the scene's). A
        scene without cloths yet keeps them for its first (its founder may still be cooking)."""
        sc = self.scenes.setdefault(scene, Scene(scene))
        packed = np.asarray(packed, np.float32).reshape(-1, 2, 4)
        if len(packed) > MAX_SCENE_COLLIDERS:
            raise ValueError(f"at most {MAX_SCENE_COLLIDERS} colliders per scene")
        if not np.all(np.isfinite(packed)):
            raise ValueError("collider values must be finite")
        moved = len(packed) == len(sc.colliders) > 0  # the per-tick case: the same colliders, new poses
        if not moved and any(
            len(self.cloths[h].own_colliders) + len(packed) > MAX_COLLIDERS_PER_CLOTH for h in sc.handles
        ):
            raise ValueError(f"at most {MAX_COLLIDERS_PER_CLOTH} colliders per cloth, its scene's included")
        sc.colliders = packed.copy()
        if moved:
            k = len(packed)
            for h in sc.handles:  # each cloth's scene rows in place (they follow its own)
                self.cloths[h].colliders[-k:] = packed
            if self._move_scene_colliders(sc):
                return
        for h in sc.handles:
            self._apply_colliders(self.cloths[h])

    def _move_scene_colliders(self, sc: Scene) -> bool:
        """Back-end hook: the scene's colliders (as many as before) moved for all its cloths at
        once, ``cloth.colliders`` already updated; False: not handled (each cloth's rows set one by one)."""
        return False

    def _apply_colliders(self, cloth: Cloth) -> None:
        """A cloth's collider rows: its own, then its scene's."""
        scene = self.scenes[cloth.scene].colliders if cloth.scene is not None else None
        cloth.colliders = (
            cloth.own_colliders if scene is None or not len(scene) else np.concatenate([cloth.own_colliders, scene])
        )
        self._set_colliders(cloth)

    def set_mesh(self, handle: int, mesh: CollisionMesh | None, pose: np.ndarray | None = None) -> None:
        """A cloth's own mesh collider (meshes.py; None: none) at ``pose`` (3 x 4 ``[R | t]``,
        default the identity) from now on: a new mesh starts still, the same triangles on new
        vertices (a re-pose) move from the last pose."""
        if handle not in self.cloths:
            raise KeyError(handle)
        self.mesh_colliders.set_cloth(handle, mesh, pose)

    def move_mesh(self, handle: int, pose: np.ndarray) -> None:
        """A cloth's mesh's pose for the end of the next step (rigid: the grid is kept)."""
        self.mesh_colliders.move(self.mesh_colliders.own[handle], pose)

    def set_scene_mesh(self, scene: str, mesh: CollisionMesh | None, pose: np.ndarray | None = None) -> None:
        """A scene's mesh collider, for every cloth of it beside its own (one copy)."""
        self.mesh_colliders.set_scene(scene, mesh, pose)

    def move_scene_mesh(self, scene: str, pose: np.ndarray) -> None:
        self.mesh_colliders.move(self.mesh_colliders.scene[scene], pose)

    def _scenes_changed(self) -> None:  # noqa: B027 (optional hook)
        """A cloth joined or left a scene (an OpenCL World rebuilds its scene tables)."""

    def reset(self, handle: int, positions: np.ndarray | None = None) -> None:
        """Put a cloth back at ``positions`` (default: its rest pose) with zero velocity."""
        cloth = self.cloths[handle]
        pos = cloth.fabric.rest_positions if positions is None else np.asarray(positions, np.float64)
        self._reset(cloth, pos.reshape(-1, 3))

    # --- frames ---------------------------------------------------------------------------
    def layout(self) -> Layout:
        """Where each cloth is in the frames from now on (cached until cloths change)."""
        if self._layout is None:
            k = len(self.cloths)
            handles = np.fromiter(self.cloths, np.int64, k)  # insertion order: new cloths last
            offsets = np.zeros(k + 1, np.int64)
            np.cumsum(self._rows_of[handles], out=offsets[1:])
            normals = self._normals_of[handles]
            self._layout_version += 1
            self._layout = Layout(
                self._layout_version, handles, offsets, normals, dict(zip(handles.tolist(), range(k), strict=True))
            )
            self._layout_changed(self._layout)
        return self._layout

    def _layout_changed(self, layout: Layout) -> None:  # noqa: B027 (optional hook)
        """Back-end hook: the frame layout was rebuilt."""

    # --- stepping ------------------------------------------------------------------------
    @abstractmethod
    def step(self, dt: float) -> None:
        """Advance every cloth by dt (may return before the device has finished)."""

    def fetch_async(self, roster: Roster, tick: int) -> PendingWire:
        """The output of the last step as tick ``tick``: ``.wait()`` gives the Wire of every
        publication of ``roster`` (a roster of this World's current layout, frame order)."""
        buffers = self._key_buffers
        return PendingWire(self.frame_async(), lambda frame: HostWire(frame, roster, tick, buffers))

    def warm_wire(self) -> None:  # noqa: B027 (optional hook)
        """Build whatever ``fetch_async`` will need (kernels) now: the tick thread never compiles."""

    @abstractmethod
    def frame_async(self) -> PendingFrame:
        """Start reading back the state after the last step; ``.wait()`` gives the Frame."""

    def fetch(self) -> Frame:
        """Wait for the last step and return the frame of every cloth's state."""
        return self.frame_async().wait()

    def positions(self, handle: int) -> np.ndarray:
        return self.fetch().positions[handle].copy()

    def sync(self) -> None:  # noqa: B027 (an optional hook: a no-op for a world that steps synchronously)
        """Wait until every step asked for so far has finished (for timing)."""

    def close(self) -> None:  # noqa: B027 (an optional hook: a no-op for a world without resources)
        pass

    # --- stats ----------------------------------------------------------------------------
    @property
    def n_cloths(self) -> int:
        return len(self.cloths)

    @property
    def n_vertices(self) -> int:
        return sum(c.fabric.n_vertices for c in self.cloths.values())

    @property
    def n_links(self) -> int:
        return sum(c.fabric.n_links for c in self.cloths.values())

    # --- backend hooks --------------------------------------------------------------------
    @abstractmethod
    def _add(self, cloth: Cloth, positions: np.ndarray | None, velocities: np.ndarray | None = None) -> None: ...

    @abstractmethod
    def _remove(self, cloth: Cloth) -> None: ...

    @abstractmethod
    def _set_params(self, cloth: Cloth, old: ClothParams) -> None: ...

    @abstractmethod
    def _set_targets(self, cloth: Cloth, idx: np.ndarray, targets: np.ndarray) -> None: ...

    @abstractmethod
    def _set_colliders(self, cloth: Cloth) -> None: ...

    @abstractmethod
    def _reset(self, cloth: Cloth, positions: np.ndarray) -> None: ...


@functools.lru_cache(maxsize=256)
def _validated(params: ClothParams) -> bool:
    params.validate()  # raises (and so is not remembered) when invalid
    return True


def _validate(params: ClothParams) -> None:
    """``params.validate()``, remembered for the last few valid ones: a tick of many adds mostly
    repeats a few parameter sets (frozen, hashable; one with a list in it is checked every time)."""
    try:
        _validated(params)
    except TypeError:  # unhashable: a field given as a list
        params.validate()


def inverse_masses(fabric: Fabric, params: ClothParams) -> np.ndarray:
    m = vertex_masses(fabric, params.material.mass)
    return np.where(fabric.pinned, 0.0, 1.0 / m)


class ReferenceWorld(World):
    """Every cloth stepped by drape.server.sim.reference on the CPU."""

    solver = "reference"

    def __init__(self, mode: str = "coloured", dtype=np.float64) -> None:
        super().__init__()
        self.mode = mode
        self.dtype = dtype
        self.states: dict[int, reference.ClothState] = {}
        self.device_name = f"numpy {np.dtype(dtype).name} ({mode})"
        self._pool = FramePool()

    def _add(self, cloth, positions, velocities=None):
        st = reference.ClothState.initial(cloth.fabric, cloth.params, self.dtype, positions)
        if velocities is not None:
            st.v[:] = velocities
        self.states[cloth.handle] = st

    def _remove(self, cloth):
        del self.states[cloth.handle]

    def _set_params(self, cloth, old):
        if old.material.mass != cloth.params.material.mass:
            self.states[cloth.handle].invm[:] = inverse_masses(cloth.fabric, cloth.params)

    def _set_targets(self, cloth, idx, targets):
        self.states[cloth.handle].target[idx] = targets

    def _set_colliders(self, cloth):
        self.states[cloth.handle].set_colliders(cloth.colliders.astype(self.dtype))

    def _reset(self, cloth, positions):
        st = self.states[cloth.handle]
        st.x[:] = positions
        st.v[:] = 0.0
        st.target[:] = positions  # the pins put back too, as the OpenCL world does

    def step(self, dt: float) -> None:
        layers = self.mesh_colliders.layers(self.scenes)
        start = {h: self.states[h].x.copy() for layer in layers for h, _ in layer}
        for h, cloth in self.cloths.items():
            st = self.states[h]
            reference.step(st, cloth.fabric, cloth.params, dt, self.mode)
            st.colliders_prev = st.colliders  # a collider not moved again stays where it is
        for sc in self.scenes.values():  # 1.7: after every cloth's own solve (scenes.py)
            inter_collide([self._scene_cloth(h) for h in sc.handles], dt)
        for layer in layers:  # 1.8: meshes last, each cloth's own then its scene's (meshes.py)
            for h, mc in layer:
                st = self.states[h]
                m = self.cloths[h].params.material
                collide_mesh(
                    st.x, st.v, start[h], st.invm, mc.mesh, mc.pose_prev, mc.pose, m.thickness, dt, m.friction, mc.fresh
                )
        self.mesh_colliders.stepped()
        self.steps += 1

    def _scene_cloth(self, h: int) -> SceneCloth:
        st, p = self.states[h], self.cloths[h].params
        coll = st.colliders if p.features.colliders and st.colliders is not None else np.zeros((0, 2, 4))
        return SceneCloth(st.x, st.v, st.invm, p.material.thickness, p.material.contact_stiffness, coll)

    def frame_async(self) -> PendingFrame:
        lay = self.layout()
        n = lay.n_rows
        want_nrm = bool(lay.normals.any())
        buf = self._pool.acquire(n, want_nrm)
        xyz, nxyz = buf.xyz[:n], (buf.nrm[:n] if want_nrm else None)
        for i, h in enumerate(lay.handles.tolist()):  # the reference is per cloth anyway
            st, sl = self.states[h], slice(int(lay.offsets[i]), int(lay.offsets[i + 1]))
            xyz[sl] = st.x
            if nxyz is not None and lay.normals[i] and st.normals is not None:
                nxyz[sl] = st.normals
        return PendingFrame(Frame(self.steps, lay, xyz, nxyz, buf))

    def state(self, handle: int) -> reference.ClothState:
        return self.states[handle]
