"""Encoders and validating decoders of every request: submit (with 1.3 resume), control, batch
control (1.1, with 1.4 moves), remove, info (PROTOCOL.md sections 4-8). The fields a control and a
submission share are read by iterating over the field table (requestfields.CONTROL_FIELDS), one
reader per kind. The requests' maps (wiremaps.py) and the replies' codec (submit, control,
batch, remove, ok, errors, stats; replies.py) are re-exported here, so ``codec`` names the codec
of every msgpack message."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from .errors import (
    ERR_INDEX_OUT_OF_RANGE,
    ERR_INVALID_TYPE,
    ERR_INVALID_VALUE,
    ERR_MISSING_FIELD,
    ERR_TOO_LARGE,
    ProtocolError,
)
from .keys import ID_RE, SCENE_ANYONE, TOKEN_RE
from .messages import (
    ControlBatchRequest,
    ControlRequest,
    DecodedControlBatch,
    InfoRequest,
    RemoveRequest,
    SceneRequest,
    SubmitRequest,
)
from .moves import check_items_with_moves, read_moves
from .replies import (  # noqa: F401  re-exported: codec names every message's codec
    control_batch_reply_from_map,
    control_reply_from_map,
    decode_error,
    decode_error_map,
    decode_reply,
    decode_stats,
    encode_control_batch_reply,
    encode_control_reply,
    encode_error,
    encode_ok,
    encode_remove_reply,
    encode_scene_reply,
    encode_stats,
    encode_submit_reply,
    scene_reply_from_map,
    submit_reply_from_map,
    tick_reply_from_map,
)
from .requestfields import CONTROL_WIRE_ORDER, SUBMIT_FIELDS, RequestField
from .validate import (
    _check_finite_array,
    _check_num,
    _header,
    _peek_rid,
    _read_colliders,
    _read_features,
    _read_material,
    _read_rho,
    _read_state_options,
    _Reader,
    _rid,
    _tname,
    pack,
    pinned_out_of_range,
    too_many_vertices,
    unpack_message,
)
from .vocabulary import (
    DEFAULT_LIMITS,
    MAX_SCENE_COLLIDERS,
    MAX_SCENE_MEMBERS,
    MESH_MAX_TRIANGLES,
    MESH_MAX_VERTICES,
    ORIENTATIONS,
    QUALITY_PRESETS,
    GridSpec,
    Limits,
    LinkSpec,
    MeshCollider,
    MeshSpec,
    PinUpdate,
    ResumeState,
    _empty_u32,
    mesh_problem,
)
from .wiremaps import (  # noqa: F401  re-exported: codec names every message's codec
    control_batch_to_map,
    control_item_to_map,
    control_to_map,
    resume_to_map,
    scene_to_map,
    submit_to_map,
)

_ID_WHAT = "1-64 characters of [A-Za-z0-9_.-]"  # what keys.ID_RE accepts, for error messages


def _read_resume(r: _Reader, n: int, limits: Limits) -> ResumeState | None:
    """1.3 ``resume``: positions (and velocities) of exactly ``n`` vertices, finite, positions
    within max_coordinate and velocities within max_acceleration (m/s)."""
    rr = r.sub("resume")
    if rr is None:
        return None
    pos = rr.blob("positions", "f4", 3, limits.max_vertices, True)
    vel = rr.blob("velocities", "f4", 3, limits.max_vertices)
    assert pos is not None
    for name, arr in (("positions", pos), ("velocities", vel)):
        if arr is not None and len(arr) != n:
            raise r.fail(ERR_INVALID_VALUE, f"'resume.{name}' has {len(arr)} vertices but the cloth has {n}")
    _check_finite_array(r, "resume.positions", pos, limits.max_coordinate)
    if vel is not None:
        _check_finite_array(r, "resume.velocities", vel, limits.max_acceleration)
    return ResumeState(
        pos,
        vel,
        rr.int_("tick", 0, (1 << 64) - 1),
        rr.str_("from_server", pattern=ID_RE, what=_ID_WHAT),
        rr.str_("cloth", pattern=ID_RE, what=_ID_WHAT),
    )


def encode_submit(req: SubmitRequest) -> bytes:
    return pack(submit_to_map(req))


def decode_submit(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> SubmitRequest:
    return submit_from_map(unpack_message(data, limits), limits)


def submit_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS) -> SubmitRequest:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    rid = _rid(r)
    client = r.str_("client", True, pattern=ID_RE, what=_ID_WHAT)
    bound = limits.max_coordinate
    gr, mr = r.sub("grid"), r.sub("mesh")
    if (gr is None) == (mr is None):
        if gr is None:
            raise r.fail(ERR_MISSING_FIELD, "one of 'grid' or 'mesh' is required")
        raise r.fail(ERR_INVALID_VALUE, "give exactly one of 'grid' or 'mesh', not both")
    grid = mesh = None
    if gr is not None:
        cols = gr.int_("cols", 1, limits.max_vertices, True, over=ERR_TOO_LARGE)
        rows = gr.int_("rows", 1, limits.max_vertices, True, over=ERR_TOO_LARGE)
        assert cols is not None and rows is not None
        if cols * rows > limits.max_vertices:  # before anything is built for it
            raise r.fail(ERR_TOO_LARGE, too_many_vertices(cols * rows, limits.max_vertices, (cols, rows)))
        width = gr.num("width", 0.0, bound, lo_inclusive=False)
        height = gr.num("height", 0.0, bound, lo_inclusive=False)
        grid = GridSpec(
            cols,
            rows,
            1.0 if width is None else width,
            1.0 if height is None else height,
            gr.str_("orientation", choices=ORIENTATIONS) or "horizontal",
            gr.vec3("origin", bound) or (0.0, 0.0, 0.0),
        )
        n = cols * rows
    else:
        assert mr is not None
        verts = mr.blob("vertices", "f4", 3, limits.max_vertices, True)
        tris = mr.blob("triangles", "u4", 3, limits.max_triangles, True)
        assert verts is not None and tris is not None
        n = len(verts)
        if n == 0:
            raise r.fail(ERR_INVALID_VALUE, "'mesh.vertices' must hold at least one vertex")
        _check_finite_array(r, "mesh.vertices", verts, bound)
        if tris.size:
            mx = int(tris.max())
            if mx >= n:
                raise r.fail(
                    ERR_INDEX_OUT_OF_RANGE, f"'mesh.triangles' refers to vertex {mx} but the mesh has {n} vertices"
                )
            if np.any((tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])):
                raise r.fail(ERR_INVALID_VALUE, "'mesh.triangles' has a triangle with a repeated vertex")
        mesh = MeshSpec(verts, tris)
    pinned = r.blob("pinned", "u4", 1, limits.max_vertices)
    if pinned is None:
        pinned = _empty_u32()
    if pinned.size and int(pinned.max()) >= n:
        first = int(pinned[pinned >= n][0])
        shape = (grid.cols, grid.rows) if grid is not None else None
        raise r.fail(ERR_INDEX_OUT_OF_RANGE, pinned_out_of_range(first, n, shape))
    lr = r.sub("links")
    links = None
    if lr is not None:
        d = LinkSpec()
        s, sh, b = lr.bool_("structural"), lr.bool_("shear"), lr.bool_("bending")
        links = LinkSpec(d.structural if s is None else s, d.shear if sh is None else sh, d.bending if b is None else b)
    shared = _read_fields(r, SUBMIT_FIELDS, True)
    return SubmitRequest(
        client=client,  # type: ignore[arg-type]
        grid=grid,
        mesh=mesh,
        pinned=pinned,
        links=links,
        rid=rid,
        resume=_read_resume(r, n, limits),
        scene=r.str_("scene", pattern=ID_RE, what=f"a scene id ({_ID_WHAT})"),  # 1.7
        **shared,
    )


# ---------------------------------------------------------------------------------------------
# Scene (1.7)


def encode_scene(req: SceneRequest) -> bytes:
    return pack(scene_to_map(req))


def decode_scene(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> SceneRequest:
    return scene_from_map(unpack_message(data, limits), limits)


def scene_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS) -> SceneRequest:
    """1.7: a scene request: ``client`` and ``scene`` ids, at most MAX_SCENE_COLLIDERS colliders,
    at most MAX_SCENE_MEMBERS members, each a client id or ``"*"``."""
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    rid = _rid(r)
    client = r.str_("client", True, pattern=ID_RE, what=_ID_WHAT)
    scene = r.str_("scene", True, pattern=ID_RE, what=f"a scene id ({_ID_WHAT})")
    colliders = _read_colliders(r)
    if colliders is not None and len(colliders) > MAX_SCENE_COLLIDERS:
        raise r.fail(
            ERR_TOO_LARGE, f"'colliders' has {len(colliders)} colliders; a scene has at most {MAX_SCENE_COLLIDERS}"
        )
    members = None
    raw = r.raw("members", False)
    if raw is not None:
        if not isinstance(raw, list):
            raise r.fail(ERR_INVALID_TYPE, f"'members' must be an array of client ids, got {_tname(raw)}")
        if len(raw) > MAX_SCENE_MEMBERS:
            raise r.fail(ERR_TOO_LARGE, f"'members' has {len(raw)} entries; at most {MAX_SCENE_MEMBERS}")
        for i, x in enumerate(raw):
            if not isinstance(x, str):
                raise r.fail(ERR_INVALID_TYPE, f"'members[{i}]' must be a string, got {_tname(x)}")
            if x != SCENE_ANYONE and not ID_RE.match(x):
                raise r.fail(ERR_INVALID_VALUE, f"'members[{i}]' must be a client id ({_ID_WHAT}) or '*', got {x!r}")
        members = tuple(raw)
    mesh = _read_mesh_collider(r, "mesh_collider", False)  # 1.8
    return SceneRequest(client, scene, colliders, members, rid, mesh)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# The fields a control and a submission share (requestfields.CONTROL_FIELDS)


def _read_pins(r: _Reader, key: str, n_vertices: int | None) -> PinUpdate | None:
    """A control's ``pins``: as many targets as indices; with ``n_vertices``, indices in range."""
    limits = r.limits
    pr = r.sub(key)
    if pr is None:
        return None
    idx = pr.blob("indices", "u4", 1, limits.max_pin_updates, True)
    tgt = pr.blob("targets", "f4", 3, limits.max_pin_updates, True)
    assert idx is not None and tgt is not None
    if len(idx) != len(tgt):
        raise r.fail(ERR_INVALID_VALUE, f"'{r.name(key)}' has {len(idx)} indices but {len(tgt)} targets")
    if n_vertices is not None and idx.size and int(idx.max()) >= n_vertices:
        raise r.fail(
            ERR_INDEX_OUT_OF_RANGE,
            f"'{pr.name('indices')}' refers to vertex {int(idx.max())} but the cloth has {n_vertices} vertices",
        )
    _check_finite_array(r, pr.name("targets"), tgt, limits.max_coordinate)
    return PinUpdate(idx, tgt)


_MESH_KEYS = ("vertices", "triangles", "position", "rotation", "remove")


def _read_mesh_collider(r: _Reader, key: str, submit: bool) -> MeshCollider | None:
    """1.8: a ``mesh_collider`` map (PROTOCOL.md 5.4), checked by the protocol's one copy of the
    mesh checks (vocabulary.mesh_problem): ``{remove: true}`` alone; else vertices and triangles
    (a new mesh), vertices alone (a re-pose) or neither (a rigid move), with the pose. A
    submission's is a new mesh."""
    mr = r.sub(key)
    if mr is None:
        return None
    unknown = sorted(set(mr.m) - set(_MESH_KEYS))
    if unknown:
        raise r.fail(ERR_INVALID_VALUE, f"'{r.name(key)}' has unknown key(s) {unknown}; known: {list(_MESH_KEYS)}")
    if mr.bool_("remove"):
        if len(mr.m) > 1:
            raise r.fail(ERR_INVALID_VALUE, f"'{r.name(key)}' with 'remove' must have no other key")
        if submit:
            raise r.fail(ERR_INVALID_VALUE, f"'{r.name(key)}' of a submission cannot remove a mesh")
        return MeshCollider.removal()
    verts = mr.blob("vertices", "f4", 3, MESH_MAX_VERTICES)
    tris = mr.blob("triangles", "u4", 3, MESH_MAX_TRIANGLES)
    if tris is not None and verts is None:
        raise r.fail(ERR_MISSING_FIELD, f"'{mr.name('vertices')}' is required with '{mr.name('triangles')}'")
    if submit and tris is None:
        raise r.fail(ERR_MISSING_FIELD, f"'{r.name(key)}' of a submission is a new mesh: vertices and triangles")
    if verts is not None:
        problem = mesh_problem(verts, tris)
        if problem is not None:
            raise r.fail(problem[0], f"'{r.name(key)}': {problem[1]}")
        _check_finite_array(r, mr.name("vertices"), verts, r.limits.max_coordinate)
    position = mr.vec3("position", r.limits.max_coordinate) or (0.0, 0.0, 0.0)
    rotation: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0)
    raw = mr.raw("rotation", False)
    if raw is not None:
        if not (isinstance(raw, list) and len(raw) == 4):
            raise r.fail(ERR_INVALID_TYPE, f"'{mr.name('rotation')}' must be 4 numbers (w, x, y, z), got {_tname(raw)}")
        rotation = tuple(_check_num(mr, f"{mr.name('rotation')}[{i}]", x, -1e3, 1e3) for i, x in enumerate(raw))
        if not sum(x * x for x in rotation) > 1e-12:
            raise r.fail(ERR_INVALID_VALUE, f"'{mr.name('rotation')}' must be a non-zero quaternion (w, x, y, z)")
    return MeshCollider(verts, tris, position, rotation)  # type: ignore[arg-type]


#: kind -> reader(reader, field, submission?, vertex count or None): the value, None if absent.
_READERS: dict[str, Callable[[_Reader, RequestField, bool, int | None], Any]] = {
    "pins": lambda r, f, sub, n: _read_pins(r, f.name, n),
    "colliders": lambda r, f, sub, n: _read_colliders(r, f.name),
    "vec3": lambda r, f, sub, n: r.vec3(f.name, getattr(r.limits, f.limit)),
    "material": lambda r, f, sub, n: _read_material(r, f.name),
    "features": lambda r, f, sub, n: _read_features(r, f.name),
    "int": lambda r, f, sub, n: r.int_(f.name, f.lo, getattr(r.limits, f.limit)),
    "fraction": lambda r, f, sub, n: _read_rho(r, f.name),
    "state": lambda r, f, sub, n: _read_state_options(r, f.name, submit=sub),
    "quality": lambda r, f, sub, n: r.str_(f.name, choices=QUALITY_PRESETS),
    "flag": lambda r, f, sub, n: r.bool_(f.name),
    "mesh": lambda r, f, sub, n: _read_mesh_collider(r, f.name, sub),
}


def _read_fields(
    r: _Reader, table: tuple[RequestField, ...], submit: bool, n_vertices: int | None = None
) -> dict[str, Any]:
    """The fields of ``table`` present in ``r``'s map, validated, by name (absent and nil ones
    left out: the request's defaults apply)."""
    out: dict[str, Any] = {}
    m = r.m
    for f, read in _READ_PLANS.get(id(table)) or _read_plan(table):
        if f.name in m:
            v = read(r, f, submit, n_vertices)
            if v is not None:
                out[f.name] = v
    return out


_READ_PLANS: dict[int, tuple[tuple[RequestField, Callable[..., Any]], ...]] = {}  # by id(table)


def _read_plan(table: tuple[RequestField, ...]) -> tuple[tuple[RequestField, Callable[..., Any]], ...]:
    plan = _READ_PLANS[id(table)] = tuple((f, _READERS[f.kind]) for f in table)
    return plan


# ---------------------------------------------------------------------------------------------
# Control, remove, info


def encode_control(req: ControlRequest) -> bytes:
    return pack(control_to_map(req))


def decode_control(
    data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS, n_vertices: int | None = None
) -> ControlRequest:
    """Validate a control message; with ``n_vertices`` pin indices are range-checked too."""
    return control_from_map(unpack_message(data, limits), limits, n_vertices)


def _owner_fields(r: _Reader) -> tuple[str, str]:
    cloth = r.str_("cloth", True, pattern=ID_RE, what=f"a cloth id ({_ID_WHAT})")
    token = r.str_("token", True, pattern=TOKEN_RE, what="32 lowercase hex digits")
    return cloth, token  # type: ignore[return-value]


def control_from_map(
    m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS, n_vertices: int | None = None
) -> ControlRequest:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    return _read_control(r, _rid(r), n_vertices)


def _read_control(r: _Reader, rid: int, n_vertices: int | None = None) -> ControlRequest:
    """The fields of a control (a whole message, or one batch item whose reader path names it).
    Only the fields present are read (a per-tick control carries two or three of them)."""
    cloth, token = _owner_fields(r)
    given = _read_fields(r, CONTROL_WIRE_ORDER, False, n_vertices)
    both = set(given.get("features_add", ())) & set(given.get("features_remove", ()))
    if both:
        raise r.fail(
            ERR_INVALID_VALUE,
            f"feature(s) {sorted(both)} in both '{r.name('features_add')}' and '{r.name('features_remove')}'",
        )
    return ControlRequest(cloth=cloth, token=token, rid=rid, **given)


def remove_to_map(req: RemoveRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m["cloth"] = req.cloth
    m["token"] = req.token
    return m


def encode_remove(req: RemoveRequest) -> bytes:
    return pack(remove_to_map(req))


def decode_remove(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> RemoveRequest:
    return remove_from_map(unpack_message(data, limits), limits)


def remove_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS) -> RemoveRequest:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    rid = _rid(r)
    cloth, token = _owner_fields(r)
    return RemoveRequest(cloth, token, rid)


def encode_info(req: InfoRequest) -> bytes:
    return pack(_header(req.rid))


def decode_info(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> InfoRequest:
    """An info query may carry no payload at all (then rid is 0)."""
    if not data:
        return InfoRequest()
    m = unpack_message(data, limits)
    return InfoRequest(_rid(_Reader(m, "", _peek_rid(m), limits)))


# ---------------------------------------------------------------------------------------------
# Batch control (1.1)


def encode_control_batch(req: ControlBatchRequest) -> bytes:
    return pack(control_batch_to_map(req))


def decode_control_batch(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> DecodedControlBatch:
    """Validate a batch control. The envelope (size, msgpack, version, ``client``, ``items``
    being an array of 1..max_batch_items) raises ProtocolError for the whole request; every item
    is then validated on its own: an invalid item becomes its ProtocolError in ``items`` and
    does not affect the others."""
    return control_batch_from_map(unpack_message(data, limits), limits)


def control_batch_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS) -> DecodedControlBatch:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    rid = _rid(r)
    client = r.str_("client", True, pattern=ID_RE, what=_ID_WHAT)
    moves = read_moves(r, limits)  # 1.4: validated whole, with the envelope
    raw_items = check_items_with_moves(r, r.raw("items", False), moves is not None, limits.max_batch_items)
    items: list[ControlRequest | ProtocolError] = []
    for i, it in enumerate(raw_items):
        name = f"items[{i}]"
        if not isinstance(it, dict):
            items.append(ProtocolError(ERR_INVALID_TYPE, f"'{name}' must be a map, got {_tname(it)}", rid))
            continue
        try:
            items.append(_read_control(_Reader(it, name, rid, limits), rid))
        except ProtocolError as e:
            items.append(e)
    return DecodedControlBatch(client, items, rid, moves)  # type: ignore[arg-type]
