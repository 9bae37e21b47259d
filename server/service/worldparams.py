"""From validated protocol requests to what the World takes: cloth parameters (one helper for
submit and control), packed colliders, feature sets after a control, mesh colliders (1.8) as the
World's set_mesh / move_mesh calls."""

from __future__ import annotations

import hashlib
import weakref
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from drape.client import protocol as P
from drape.client.protocol.requestfields import CONTROL_FIELDS, any_given

from ..sim import quality
from ..sim.meshes import CollisionMesh, collision_mesh, pose_matrix
from ..sim.params import ClothParams, Features, Material, pack_colliders
from ..sim.world import World
from .config import ServerConfig


def pack(colliders: tuple[P.Collider, ...] | None, rid: int) -> np.ndarray:
    """A request's colliders as device slots (ProtocolError invalid_value when one cannot be packed)."""
    try:
        return pack_colliders(colliders or ())
    except (TypeError, ValueError) as e:
        raise P.ProtocolError(P.ERR_INVALID_VALUE, f"colliders: {e}", rid) from None


def features_after(req: P.ControlRequest, p: ClothParams) -> set[str]:
    """The cloth's feature names once ``req`` is applied (the protocol's own rule)."""
    return set(P.resolve_features(frozenset(p.features.names()), req))


#: Whether a control gives a field that always changes the cloth's parameters (by where it acts).
_gives_params = any_given(f for f in CONTROL_FIELDS if f.acts in ("param", "material", "features", "quality"))
#: The fields copied onto the ClothParams field of the same name.
_PARAM_FIELDS = tuple(f.name for f in CONTROL_FIELDS if f.acts == "param")


def changes_params(req: P.ControlRequest, p: ClothParams) -> bool:
    """Whether a control changes the cloth's parameters (the common per-tick control, pins and
    colliders of a cloth whose colliders feature is on, changes none)."""
    return bool(
        _gives_params(req)
        or (req.colliders and not p.features.colliders)
        or (req.state is not None and req.state.normals is not None and req.state.normals != p.features.normals)
    )


def params_with(
    base: ClothParams, req: P.SubmitRequest | P.ControlRequest, material: Material, features: set[str]
) -> ClothParams:
    """``base`` with the solver fields a submit or control request gives (absent ones kept)."""
    given = {k: v for k in _PARAM_FIELDS if (v := getattr(req, k)) is not None}
    return base.with_(material=material, features=Features.from_names(sorted(features)), **given)


def params_from_submit(req: P.SubmitRequest) -> ClothParams:
    feats = set(req.features)
    if req.colliders or req.scene is not None:  # 1.7: a scene's colliders act on its cloths
        feats.add("colliders")
    if req.state is not None and req.state.normals:
        feats.add("normals")
    try:
        params = params_with(ClothParams(), req, Material(**req.material), feats)
        params.validate()
    except (TypeError, ValueError) as e:
        raise P.ProtocolError(P.ERR_INVALID_VALUE, f"cloth parameters: {e}", req.rid) from None
    return params


def params_after_control(req: P.ControlRequest, p: ClothParams) -> ClothParams:
    """The parameters once ``req`` is applied (raises ValueError when they are invalid)."""
    material = replace(p.material, **req.material) if req.material else p.material
    new = params_with(p, req, material, features_after(req, p))
    new.validate()
    return new


def with_preset(config: ServerConfig, params: ClothParams, name: str, rid: int) -> ClothParams:
    """``params`` with quality preset ``name`` at this server's tick rate, within its limits."""
    out = quality.apply_preset(params, name, config.tick_rate)
    if out.substeps > config.max_substeps or out.iterations > config.max_iterations:
        raise P.LimitExceeded(
            P.ERR_LIMIT_EXCEEDED,
            f"quality {name!r} needs {out.substeps} substeps x "
            f"{out.iterations} iterations; this server allows {config.max_substeps} x "
            f"{config.max_iterations}",
            rid,
        )
    return out


#: Equal meshes sent by many clients (a crowd's one body) are one CollisionMesh, so the World
#: builds one grid and the device holds one copy; an entry goes with the last collider using it.
_MESHES: weakref.WeakValueDictionary[bytes, CollisionMesh] = weakref.WeakValueDictionary()


def _interned(vertices: np.ndarray, triangles: np.ndarray) -> CollisionMesh:
    key = hashlib.blake2b(
        np.ascontiguousarray(vertices, "<f4").tobytes() + np.ascontiguousarray(triangles, "<u4").tobytes(),
        digest_size=20,
    ).digest()
    mesh = _MESHES.get(key)
    if mesh is None:
        mesh = _MESHES[key] = collision_mesh(vertices, triangles)
    return mesh


def prepare_mesh(
    world: World, spec: P.MeshCollider, handle: int | None = None, scene: str | None = None
) -> Callable[[], None]:
    """1.8: the World call that applies ``spec`` to cloth ``handle`` or to ``scene``, checked
    before anything is applied (ValueError saying what is wrong: a move or a re-pose with no mesh
    to change, a re-pose of another vertex count, a re-pose that makes a triangle degenerate)."""
    mcs = world.mesh_colliders
    current = mcs.own.get(handle) if scene is None else mcs.scene.get(scene)  # type: ignore[arg-type]

    def set_(mesh: CollisionMesh | None, pose: np.ndarray | None) -> Callable[[], None]:
        if scene is None:
            return lambda: world.set_mesh(handle, mesh, pose)  # type: ignore[arg-type]
        return lambda: world.set_scene_mesh(scene, mesh, pose)

    if spec.remove:
        return set_(None, None)
    pose = pose_matrix(spec.position, spec.rotation)
    if spec.triangles is not None:
        assert spec.vertices is not None
        return set_(_interned(spec.vertices, spec.triangles), pose)
    what = "cloth" if scene is None else f"scene {scene!r}"
    if current is None:
        raise ValueError(f"mesh_collider: the {what} has no mesh to move or re-pose; send vertices and triangles first")
    if spec.vertices is not None:
        if len(spec.vertices) != len(current.mesh.vertices):
            raise ValueError(
                f"mesh_collider: a re-pose has {len(spec.vertices)} vertices; the {what}'s mesh has "
                f"{len(current.mesh.vertices)} (send vertices and triangles for a new mesh)"
            )
        return set_(_interned(spec.vertices, current.mesh.triangles), pose)
    return lambda: mcs.move(current, pose)
