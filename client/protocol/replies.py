"""Encoders and validating decoders of every reply: submit, control, batch control (1.1), remove,
info (``encode_ok``), error replies and stats (PROTOCOL.md sections 4-8, 10). The requests' are
in codec.py, which re-exports these."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .errors import ERR_INVALID_TYPE, ERR_MALFORMED, ERROR_CODES, ProtocolError
from .keys import ID_RE, TOKEN_RE
from .messages import (
    BatchItemResult,
    ControlBatchReply,
    ControlReply,
    ErrorReply,
    RemoveReply,
    SceneReply,
    SubmitReply,
    feature_list,
)
from .moves import moves_failed_to_wire, moves_reply_from_map
from .validate import _header, _peek_rid, _Reader, _rid, _tname, pack, unpack_message
from .vocabulary import DEFAULT_LIMITS, Limits


def encode_control_batch_reply(rep: ControlBatchReply) -> bytes:
    m = _header(rep.rid)
    results: list[dict[str, Any]] = []
    for res in rep.results:
        if res.ok:
            item: dict[str, Any] = {"ok": True, "tick": int(rep.tick if res.tick is None else res.tick)}
            if res.features is not None:
                item["features"] = list(feature_list(res.features))
            results.append(item)
        else:
            if res.code not in ERROR_CODES:
                raise ValueError(f"unknown error code {res.code!r}")
            results.append({"ok": False, "error": {"code": res.code, "message": str(res.message)}})
    m.update(ok=True, tick=int(rep.tick), failed=sum(1 for x in rep.results if not x.ok), results=results)
    if rep.moves_tick is not None:  # 1.4: the request had moves
        m["moves_tick"] = int(rep.moves_tick)
        m["moves_failed"] = moves_failed_to_wire(rep.moves_failed or ())
    return pack(m)


def control_batch_reply_from_map(m: Mapping[str, Any]) -> ControlBatchReply:
    """A batch reply's map (as decode_reply returns it) as a ControlBatchReply."""
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    tick = r.int_("tick", 0, (1 << 64) - 1, True)
    raw_results = r.raw("results", True)
    if not isinstance(raw_results, list):
        raise r.fail(ERR_INVALID_TYPE, f"'results' must be an array, got {_tname(raw_results)}")
    results: list[BatchItemResult] = []
    for i, x in enumerate(raw_results):
        if not isinstance(x, dict):
            raise r.fail(ERR_INVALID_TYPE, f"'results[{i}]' must be a map, got {_tname(x)}")
        xr = _Reader(x, f"results[{i}]", r.rid, DEFAULT_LIMITS)
        if xr.bool_("ok", True):
            results.append(BatchItemResult(tick=xr.int_("tick", 0, (1 << 64) - 1, True), features=_reply_features(xr)))
        else:
            er = xr.sub("error", True)
            assert er is not None
            results.append(BatchItemResult(None, er.str_("code", True) or "", er.str_("message") or ""))
    moves_tick, moves_failed = moves_reply_from_map(m, r)
    return ControlBatchReply(tick, results, _rid(r), moves_tick, moves_failed)  # type: ignore[arg-type]


def encode_submit_reply(rep: SubmitReply) -> bytes:
    m = _header(rep.rid)
    m.update(ok=True, cloth=rep.cloth, token=rep.token, key=rep.key, vertices=int(rep.vertices), tick=int(rep.tick))
    if rep.bundle_key is not None:
        m["bundle_key"] = rep.bundle_key
    return pack(m)


def encode_control_reply(rep: ControlReply) -> bytes:
    m = _header(rep.rid)
    m.update(ok=True, tick=int(rep.tick))
    if rep.features is not None:  # 1.2
        m["features"] = list(feature_list(rep.features))
    return pack(m)


def control_reply_from_map(m: Mapping[str, Any]) -> ControlReply:
    """A control reply's map (as decode_reply returns it): ``features`` is None from a server
    older than 1.2."""
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    return ControlReply(r.int_("tick", 0, (1 << 64) - 1, True), _rid(r), _reply_features(r))  # type: ignore[arg-type]


def _reply_features(r: _Reader) -> tuple[str, ...] | None:
    """A reply's ``features`` (1.2): a list of strings; names this side does not know are kept."""
    v = r.raw("features", False)
    if v is None:
        return None
    if not (isinstance(v, list) and all(isinstance(x, str) for x in v)):
        raise r.fail(ERR_INVALID_TYPE, f"'{r.name('features')}' must be an array of strings, got {_tname(v)}")
    return tuple(v)


def encode_scene_reply(rep: SceneReply) -> bytes:
    """1.7: a scene request's reply (PROTOCOL.md 5.3)."""
    m = _header(rep.rid)
    m.update(ok=True, tick=int(rep.tick), owner=rep.owner, cloths=int(rep.cloths), members=list(rep.members))
    return pack(m)


def scene_reply_from_map(m: Mapping[str, Any]) -> SceneReply:
    """A scene reply's map (as decode_reply returns it) as a SceneReply."""
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    tick = r.int_("tick", 0, (1 << 64) - 1, True)
    owner = r.str_("owner", True, pattern=ID_RE)
    cloths = r.int_("cloths", 0, (1 << 32) - 1, True)
    members = r.raw("members", False) or []
    if not (isinstance(members, list) and all(isinstance(x, str) for x in members)):
        raise r.fail(ERR_INVALID_TYPE, f"'members' must be an array of strings, got {_tname(members)}")
    return SceneReply(tick, owner, cloths, tuple(members), _rid(r))  # type: ignore[arg-type]


def encode_remove_reply(rep: RemoveReply) -> bytes:
    m = _header(rep.rid)
    m.update(ok=True, tick=int(rep.tick))
    return pack(m)


def encode_ok(rid: int = 0, **body: Any) -> bytes:
    """A success reply with arbitrary body fields (info)."""
    m = _header(rid)
    m["ok"] = True
    m.update(body)
    return pack(m)


def encode_error(code: str, message: str, rid: int = 0) -> bytes:
    if code not in ERROR_CODES:
        raise ValueError(f"unknown error code {code!r}")
    m = _header(rid)
    m.update(ok=False, error={"code": code, "message": str(message)})
    return pack(m)


def decode_reply(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> dict[str, Any]:
    """A reply's map if ``ok`` is true; raises the matching DrapeError when it is an error reply,
    ProtocolError when the reply itself is malformed."""
    m = unpack_message(data, limits)
    ok = m.get("ok")
    if ok is True:
        return m
    if ok is False:
        err = decode_error_map(m)
        raise err.exception()
    raise ProtocolError(ERR_MALFORMED, f"reply must have boolean 'ok', got {_tname(ok)}", _peek_rid(m))


def decode_error_map(m: Mapping[str, Any]) -> ErrorReply:
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    er = r.sub("error", True)
    assert er is not None
    code = er.str_("code", True)
    msg = er.str_("message") or ""
    return ErrorReply(code, msg, _rid(r))  # type: ignore[arg-type]


def decode_error(data: bytes | bytearray) -> ErrorReply:
    return decode_error_map(unpack_message(data))


def submit_reply_from_map(m: Mapping[str, Any]) -> SubmitReply:
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    return SubmitReply(
        cloth=r.str_("cloth", True, pattern=ID_RE),  # type: ignore[arg-type]
        token=r.str_("token", True, pattern=TOKEN_RE),  # type: ignore[arg-type]
        key=r.str_("key", True),  # type: ignore[arg-type]
        vertices=r.int_("vertices", 1, 1 << 32, True),  # type: ignore[arg-type]
        tick=r.int_("tick", 0, (1 << 64) - 1, True),  # type: ignore[arg-type]
        rid=_rid(r),
        bundle_key=r.str_("bundle_key"),
    )


def tick_reply_from_map(m: Mapping[str, Any]) -> int:
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    return r.int_("tick", 0, (1 << 64) - 1, True)  # type: ignore[return-value]


def encode_stats(stats: Mapping[str, Any]) -> bytes:
    m = _header(0)
    m.update(stats)
    return pack(m)


def decode_stats(data: bytes | bytearray) -> dict[str, Any]:
    return unpack_message(data)
