"""A World's mesh colliders (issue 22): which cloth and which scene has which mesh at which pose,
the poses' start and end over a step, and the attachments (cloth, mesh) each back end collides.

A cloth has at most one mesh of its own and its scene at most one (set once, then moved by a pose
per tick, or re-posed with new vertices). A mesh object given to several cloths or a scene's
mesh is one copy (its grid is built once, and the device holds it once). Like colliders, a pose
not moved again before the next step stays where it is.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .meshes import CollisionMesh, MeshGrid, build_grid, pose_matrix


@dataclass
class MeshCollider:
    mesh: CollisionMesh
    grid: MeshGrid
    pose: np.ndarray  # (3, 4): mesh frame to world at the end of the next step
    pose_prev: np.ndarray  # at its start
    fresh: bool = True  # set or re-posed since the last step: its deep vertices are put out (meshes.py)


def as_pose(pose: np.ndarray | None) -> np.ndarray:
    """A checked (3, 4) rigid pose (None: the identity)."""
    if pose is None:
        return pose_matrix()
    p = np.asarray(pose, np.float64)
    if p.shape != (3, 4) or not np.all(np.isfinite(p)):
        raise ValueError(f"a mesh pose is a finite 3 x 4 matrix [R | t], got shape {p.shape}")
    if not np.allclose(p[:, :3] @ p[:, :3].T, np.eye(3), atol=1e-4):
        raise ValueError("a mesh pose's rotation must be orthonormal (a rigid motion)")
    return p


class MeshColliders:
    """The mesh colliders of one World: ``own[handle]`` and ``scene[name]``. ``version`` changes
    whenever a mesh is set, re-posed or dropped (a back end then rebuilds its tables);
    ``moved``: a pose changed since the last step."""

    def __init__(self) -> None:
        self.own: dict[int, MeshCollider] = {}
        self.scene: dict[str, MeshCollider] = {}
        self.version = 0
        self.moved = False
        self._grids: dict[int, tuple[CollisionMesh, MeshGrid]] = {}

    def _grid(self, mesh: CollisionMesh) -> MeshGrid:
        """The mesh's grid, built once per mesh object while some collider uses it."""
        held = self._grids.get(id(mesh))
        if held is not None and held[0] is mesh:
            return held[1]
        used = {id(mc.mesh) for mc in (*self.own.values(), *self.scene.values())}
        self._grids = {k: v for k, v in self._grids.items() if k in used}
        grid = build_grid(mesh)
        self._grids[id(mesh)] = (mesh, grid)
        return grid

    def _set(self, table: dict, key, mesh: CollisionMesh | None, pose: np.ndarray | None) -> None:
        if mesh is None:
            if table.pop(key, None) is not None:
                self.version += 1
                used = {id(mc.mesh) for mc in (*self.own.values(), *self.scene.values())}
                self._grids = {k: v for k, v in self._grids.items() if k in used}  # its grid given back
            return
        p = as_pose(pose)
        was = table.get(key)
        # a re-pose (the same triangles) keeps the pose it moves from; a new mesh starts still
        keep = was is not None and np.array_equal(was.mesh.triangles, mesh.triangles)
        table[key] = MeshCollider(mesh, self._grid(mesh), p, was.pose_prev if keep and was else p.copy())
        self.version += 1
        self.moved = True

    def set_cloth(self, handle: int, mesh: CollisionMesh | None, pose: np.ndarray | None = None) -> None:
        self._set(self.own, handle, mesh, pose)

    def set_scene(self, scene: str, mesh: CollisionMesh | None, pose: np.ndarray | None = None) -> None:
        self._set(self.scene, scene, mesh, pose)

    def move(self, mc: MeshCollider, pose: np.ndarray) -> None:
        mc.pose = as_pose(pose)
        self.moved = True

    def stepped(self) -> None:
        """After a step: every pose's end becomes the next step's start; no mesh is fresh."""
        for mc in (*self.own.values(), *self.scene.values()):
            mc.fresh = False
        if self.moved:
            for mc in (*self.own.values(), *self.scene.values()):
                mc.pose_prev = mc.pose
            self.moved = False

    def drop_cloth(self, handle: int) -> None:
        self.set_cloth(handle, None)

    def drop_scene(self, scene: str) -> None:
        self.set_scene(scene, None)

    def __bool__(self) -> bool:
        return bool(self.own or self.scene)

    def layers(self, scenes: Mapping[str, object]) -> list[list[tuple[int, MeshCollider]]]:
        """The attachments, in two layers collided one after the other: every cloth's own mesh,
        then its scene's (``scenes``: name -> an object with ``handles``)."""
        own = sorted(self.own.items())
        of_scenes = [
            (h, mc)
            for name, mc in sorted(self.scene.items())
            if name in scenes
            for h in scenes[name].handles  # type: ignore[attr-defined]
        ]
        return [layer for layer in (own, of_scenes) if layer]
