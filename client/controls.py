"""Pure control building of the Python SDK (no I/O, no session): the conversions of the SDK's
friendly arguments (pins, settings, colliders, links, vectors) into protocol values, what a
"pins only" control is (the one a 1.4 ``moves`` block carries), a batch reply folded into one
outcome per item, and the error of a refused batch (:class:`BatchError`)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import fields, is_dataclass
from typing import Any, TypedDict

import numpy as np

from . import protocol as P
from .protocol import DrapeError


class BatchError(DrapeError):
    """Raised by a waited-for batch (``client.batch(wait=True)``) when some of its items were
    refused: ``results`` holds, per item in order, the tick it applies from or its DrapeError."""

    def __init__(self, results: list[int | DrapeError]) -> None:
        errors = [r for r in results if isinstance(r, DrapeError)]
        first = errors[0]
        super().__init__(
            first.code, f"{len(errors)} of {len(results)} batch items refused; first: {first.message}", first.rid
        )
        self.results = results


def item_outcomes(cloths: Sequence[str], rep: P.ControlBatchReply, rid: int) -> list[int | DrapeError]:
    """A batch reply to items of ``cloths`` (their ids, in order) as one outcome per item: the tick
    it applies from, or its DrapeError."""
    if len(rep.results) != len(cloths):
        raise DrapeError(P.ERR_INTERNAL, f"batch reply has {len(rep.results)} results for {len(cloths)} items", rid)
    out: list[int | DrapeError] = []
    for cloth, r in zip(cloths, rep.results, strict=True):
        if r.ok:
            out.append(rep.tick if r.tick is None else r.tick)
        else:
            out.append(P.error_for(r.code, f"cloth {cloth}: {r.message}", rid))
    return out


def pins_only(r: P.ControlRequest) -> bool:
    """A control with pin targets (distinct indices) and nothing else: what a moves block carries
    (the fields' table says which are pins: :func:`drape.client.protocol.requestfields.pins_only`)."""
    if not P.pins_only(r) or r.pins is None or not len(r.pins.indices):
        return False
    return len(np.unique(r.pins.indices)) == len(r.pins.indices)


def features_delta(reqs: Iterable[P.ControlRequest]) -> bool:
    """Whether any of ``reqs`` switches single features (features_add / features_remove: 1.2)."""
    return any(r.features_add is not None or r.features_remove is not None for r in reqs)


def pin_changes(
    indices: Sequence[int] | np.ndarray,
    targets: Sequence[Sequence[float]] | np.ndarray,
    colliders: Sequence[Any] | None,
) -> dict[str, Any]:
    idx = np.asarray(indices, np.int64).reshape(-1)
    tgt = np.asarray(targets, np.float32).reshape(-1, 3)
    if len(idx) != len(tgt):
        raise ValueError(f"{len(idx)} indices but {len(tgt)} targets")
    if idx.size and idx.min() < 0:
        raise ValueError("pin indices must be >= 0")
    out: dict[str, Any] = {"pins": P.PinUpdate(idx.astype(np.uint32), tgt)}
    if colliders is not None:
        out["colliders"] = tuple(collider(c) for c in colliders)
    return out


def feature_names(names: Iterable[str] | None) -> tuple[str, ...] | None:
    if names is None:
        return None
    out = (names,) if isinstance(names, str) else tuple(names)
    bad = [n for n in out if n not in P.FEATURE_NAMES]
    if bad:
        raise ValueError(f"unknown feature(s) {bad}; known: {list(P.FEATURE_NAMES)}")
    return out


def vec3(v: Sequence[float] | None) -> P.Vec3 | None:
    if v is None:
        return None
    t = tuple(float(x) for x in v)
    if len(t) != 3:
        raise ValueError(f"expected 3 numbers, got {len(t)}")
    return t  # type: ignore[return-value]


def mesh_collider(
    m: Any, position: Sequence[float] | None = None, rotation: Sequence[float] | None = None
) -> P.MeshCollider | None:
    """1.8: ``m`` as a protocol MeshCollider: one already (a :meth:`~P.MeshCollider.pose` move
    included), ``False`` (remove the mesh), a ``(vertices, triangles)`` pair or an object with
    ``vertices`` and ``triangles`` (a new mesh, e.g. ``drape.server.sim.bodymesh.body_mesh()``),
    placed at ``position`` and ``rotation`` (w, x, y, z) when given. None: unchanged."""
    if m is None:
        return None
    if m is False:
        return P.MeshCollider.removal()
    if isinstance(m, P.MeshCollider):
        mc = m
    else:
        v, t = (m.vertices, m.triangles) if hasattr(m, "vertices") else m
        mc = P.MeshCollider(np.asarray(v, np.float32).reshape(-1, 3), np.asarray(t, np.uint32).reshape(-1, 3))
    if position is not None or rotation is not None:
        mc = P.MeshCollider(
            mc.vertices,
            mc.triangles,
            vec3(position) if position is not None else mc.position,  # type: ignore[arg-type]
            tuple(float(x) for x in rotation) if rotation is not None else mc.rotation,  # type: ignore[arg-type]
        )
    return mc


class SetOptions(TypedDict, total=False):
    """The keyword arguments of :meth:`ClothHandle.set <drape.client.handle.ClothHandle.set>` and
    :meth:`ControlBatch.set <drape.client.batching.ControlBatch.set>`: every control field of
    ``protocol.CONTROL_FIELDS`` but pins and colliders (their own methods), with the state's
    options (``protocol.StateOptions`` but ``bundle``) flat. None (or absent) = unchanged.
    tests/client/test_sdk_session.py checks it against the table."""

    gravity: Sequence[float] | None
    wind: Sequence[float] | None
    material: Mapping[str, Any] | Any
    features: Iterable[str] | None
    iterations: int | None
    substeps: int | None
    chebyshev_rho: float | None
    quality: str | None
    features_add: Iterable[str] | None
    features_remove: Iterable[str] | None
    reset: bool
    mesh_collider: Any  # 1.8: P.MeshCollider (P.MeshCollider.pose(...): the per-tick move), a mesh, or False
    normals: bool | None
    encoding: str | None
    step: float | None


def _material(m: Any) -> dict[str, Any]:
    return P.material_to_map(m) if m is not None else {}


def _same(v: Any) -> Any:
    return v


#: How a ``set`` argument of each field kind becomes its protocol value (kinds: requestfields.FIELD_KINDS).
CONVERT_KIND: dict[str, Callable[[Any], Any]] = {
    "vec3": vec3,
    "material": _material,
    "features": feature_names,
    "int": _same,
    "fraction": _same,
    "quality": _same,
    "flag": bool,
    "mesh": mesh_collider,
}
#: The control fields ``set`` takes as they are (pins, colliders and state have their own shapes).
SET_FIELDS = tuple(f for f in P.CONTROL_FIELDS if f.kind in CONVERT_KIND)
#: The state options ``set`` takes flat (a submission's ``bundle`` cannot change).
STATE_OPTIONS = tuple(f.name for f in fields(P.StateOptions) if f.name != "bundle")


def set_changes(**options: Any) -> dict[str, Any]:
    """``set``'s keyword arguments (:class:`SetOptions`) as the fields of a ControlRequest."""
    unknown = options.keys() - SetOptions.__annotations__.keys()
    if unknown:
        raise TypeError(f"set() got unexpected keyword argument(s) {sorted(unknown)}")
    out = {f.name: CONVERT_KIND[f.kind](options.get(f.name)) for f in SET_FIELDS}
    state = {k: options.get(k) for k in STATE_OPTIONS}
    out["state"] = P.StateOptions(**state) if any(v is not None for v in state.values()) else None
    add, remove = out["features_add"], out["features_remove"]
    if add and remove and set(add) & set(remove):
        raise ValueError(f"feature(s) {sorted(set(add) & set(remove))} both added and removed")
    return out


def links_of(links: Any) -> P.LinkSpec | None:
    if links is None or isinstance(links, P.LinkSpec):
        return links
    if isinstance(links, Mapping):
        return P.LinkSpec(**links)
    if is_dataclass(links):
        return P.LinkSpec(**{f.name: bool(getattr(links, f.name)) for f in fields(links)})
    raise TypeError(f"links must be a LinkSpec, a mapping or a dataclass, got {type(links).__name__}")


def collider(c: Any) -> P.Collider:
    """``c`` as a protocol collider (one already, a wire map or an object with a shape's fields):
    the shapes' table decides (:func:`drape.client.protocol.as_collider`)."""
    return P.as_collider(c)


__all__ = [
    "BatchError",
    "collider",
    "CONVERT_KIND",
    "SET_FIELDS",
    "STATE_OPTIONS",
    "SetOptions",
    "feature_names",
    "features_delta",
    "item_outcomes",
    "links_of",
    "mesh_collider",
    "pin_changes",
    "pins_only",
    "set_changes",
    "vec3",
]
