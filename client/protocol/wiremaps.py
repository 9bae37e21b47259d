"""Every request as its msgpack map (PROTOCOL.md sections 4, 5, 5.1, 5.3): submit (with 1.3
resume and 1.7 scene), control, batch control (with 1.4 moves), scene (1.7). The fields a
submission and a control share are written by iterating over the field table
(requestfields.CONTROL_FIELDS), one writer per kind.
The request dataclasses compare by these maps; :mod:`.codec` packs them."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import MISSING, fields
from typing import Any, TypeAlias

from .moves import moves_to_map
from .requestfields import CONTROL_WIRE_ORDER, SUBMIT_FIELDS, RequestField
from .validate import _blob, _f, _header, _state_map, _v3, collider_to_map, material_to_map
from .vocabulary import ResumeState

# The requests (messages.py) are annotated by name only: messages imports this module for its
# equality, and a module below it may not import it back (not even for annotations).
SubmitRequest: TypeAlias = Any
ControlRequest: TypeAlias = Any
ControlBatchRequest: TypeAlias = Any
SceneRequest: TypeAlias = Any

#: kind -> the wire value of a given field of that kind (requestfields.FIELD_KINDS).
WRITERS: dict[str, Callable[[Any], Any]] = {
    "pins": lambda p: {"indices": _blob(p.indices, "u4"), "targets": _blob(p.targets, "f4")},
    "colliders": lambda cs: [collider_to_map(c) for c in cs],
    "vec3": _v3,
    "material": material_to_map,
    "features": list,
    "int": int,
    "fraction": _f,
    "state": _state_map,
    "quality": str,
    "flag": lambda _: True,
    "mesh": lambda mc: mesh_collider_to_map(mc),
}


def mesh_collider_to_map(mc: Any) -> dict[str, Any]:
    """1.8: a MeshCollider's map (PROTOCOL.md 5.4): ``{remove: true}`` alone, or the vertices and
    triangles given and the pose."""
    if mc.remove:
        return {"remove": True}
    m: dict[str, Any] = {}
    if mc.vertices is not None:
        m["vertices"] = _blob(mc.vertices, "f4")
    if mc.triangles is not None:
        m["triangles"] = _blob(mc.triangles, "u4")
    m["position"] = _v3(mc.position)
    m["rotation"] = [_f(x) for x in mc.rotation]
    return m


#: (class, id of the table) -> its plan: (name, writer, whether a falsy value is unset) per field.
_PLANS: dict[tuple[type, int], tuple[tuple[str, Callable[[Any], Any], bool], ...]] = {}


def _plan(cls: type, table: tuple[RequestField, ...]) -> tuple[tuple[str, Callable[[Any], Any], bool], ...]:
    """How ``cls``'s fields of ``table`` are written: a field is unset when None or, where the
    dataclass default is not None (an empty map or list, false), when empty."""
    defaults: dict[str, Any] = {}
    for f in fields(cls):
        if f.default is not MISSING:
            defaults[f.name] = f.default
        elif callable(f.default_factory):
            defaults[f.name] = f.default_factory()
    plan = tuple((f.name, WRITERS[f.kind], defaults.get(f.name) is not None) for f in table)
    _PLANS[(cls, id(table))] = plan
    return plan


def _write_fields(m: dict[str, Any], req: Any, table: tuple[RequestField, ...]) -> None:
    """Write ``req``'s fields of ``table`` that are set (see _plan), in the table's order."""
    plan = _PLANS.get((type(req), id(table))) or _plan(type(req), table)
    for name, write, falsy_unset in plan:
        v = getattr(req, name)
        if v is None or (falsy_unset and not v):
            continue
        m[name] = write(v)


def submit_to_map(req: SubmitRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m["client"] = req.client
    if req.grid is not None:
        g = req.grid
        m["grid"] = {
            "cols": int(g.cols),
            "rows": int(g.rows),
            "width": _f(g.width),
            "height": _f(g.height),
            "orientation": g.orientation,
            "origin": _v3(g.origin),
        }
    if req.mesh is not None:
        m["mesh"] = {"vertices": _blob(req.mesh.vertices, "f4"), "triangles": _blob(req.mesh.triangles, "u4")}
    if len(req.pinned):
        m["pinned"] = _blob(req.pinned, "u4")
    if req.links is not None:
        m["links"] = {
            "structural": bool(req.links.structural),
            "shear": bool(req.links.shear),
            "bending": bool(req.links.bending),
        }
    _write_fields(m, req, SUBMIT_FIELDS)
    if req.resume is not None:
        m["resume"] = resume_to_map(req.resume)
    if req.scene is not None:  # 1.7
        m["scene"] = str(req.scene)
    return m


def scene_to_map(req: SceneRequest) -> dict[str, Any]:
    """1.7: a scene request (PROTOCOL.md 5.3)."""
    m = _header(req.rid)
    m["client"] = req.client
    m["scene"] = req.scene
    if req.colliders is not None:
        m["colliders"] = [collider_to_map(c) for c in req.colliders]
    if req.members is not None:
        m["members"] = [str(x) for x in req.members]
    if req.mesh_collider is not None:  # 1.8
        m["mesh_collider"] = mesh_collider_to_map(req.mesh_collider)
    return m


def resume_to_map(rs: ResumeState) -> dict[str, Any]:
    """1.3: the ``resume`` map of a submission (PROTOCOL.md section 4.1)."""
    m: dict[str, Any] = {"positions": _blob(rs.positions, "f4")}
    if rs.velocities is not None:
        m["velocities"] = _blob(rs.velocities, "f4")
    if rs.tick is not None:
        m["tick"] = int(rs.tick)
    if rs.from_server is not None:
        m["from_server"] = str(rs.from_server)
    if rs.cloth is not None:
        m["cloth"] = str(rs.cloth)
    return m


def control_to_map(req: ControlRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m.update(control_item_to_map(req))
    return m


def control_item_to_map(req: ControlRequest) -> dict[str, Any]:
    """A control's fields without ``v`` and ``rid``: one item of a batch control."""
    m: dict[str, Any] = {"cloth": req.cloth, "token": req.token}
    _write_fields(m, req, CONTROL_WIRE_ORDER)
    return m


def control_batch_to_map(req: ControlBatchRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m["client"] = req.client
    if req.items or req.moves is None:
        m["items"] = [control_item_to_map(it) for it in req.items]
    if req.moves is not None:  # 1.4
        m["moves"] = moves_to_map(req.moves)
    return m
