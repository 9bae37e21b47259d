"""1.4: the ``moves`` block of a batch control (PROTOCOL.md 5.1.1), the pin moves of many cloths
in one columnar map, and its reply fields (``moves_tick``, ``moves_failed``).

The decoder validates the block on the bytes alone and without a per-move loop: the ids and the
tokens are each checked by one regular expression over their joined text, the targets by one
min/max over the whole block (NaN and infinities fail the same comparison); only when something
is wrong does it look for the first culprit to name it."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .errors import ERR_INVALID_TYPE, ERR_INVALID_VALUE, ERR_MISSING_FIELD, ERR_TOO_LARGE, ProtocolError
from .keys import ID_RE, TOKEN_RE
from .validate import _blob, _Reader, _tname
from .vocabulary import Limits, PinMoves

#: Ids and tokens joined by "\n" (a character neither may hold): one match checks them all.
_IDS_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}(?:\n[A-Za-z0-9_.\-]{1,64})*")
_TOKENS_RE = re.compile(r"[0-9a-f]{32}(?:\n[0-9a-f]{32})*")


def moves_to_map(mv: PinMoves) -> dict[str, Any]:
    """The ``moves`` map of a batch control."""
    n = len(mv.cloths)
    if len(mv.tokens) != n:
        raise ValueError(f"{n} cloths but {len(mv.tokens)} tokens")
    idx = np.asarray(mv.indices).reshape(-1)
    tgt = np.asarray(mv.targets)
    if tgt.size != n * len(idx) * 3:
        raise ValueError(f"targets hold {tgt.size} values, expected {n} cloths x {len(idx)} pins x 3")
    return {
        "cloths": [str(c) for c in mv.cloths],
        "tokens": [str(t) for t in mv.tokens],
        "indices": _blob(idx, "u4"),
        "targets": _blob(tgt.reshape(-1), "f4"),
    }


def _strings(r: _Reader, key: str, n_max: int, joined_re: re.Pattern[str], one_re: re.Pattern[str], what: str) -> list:
    v = r.raw(key, True)
    if not isinstance(v, list):
        raise r.fail(ERR_INVALID_TYPE, f"'{r.name(key)}' must be an array of strings, got {_tname(v)}")
    if len(v) > n_max:
        raise r.fail(ERR_TOO_LARGE, f"'{r.name(key)}' has {len(v)} entries, more than the limit of {n_max}")
    try:
        joined = "\n".join(v)
        ok = joined_re.fullmatch(joined) is not None and joined.count("\n") == len(v) - 1
    except TypeError:  # not every entry is a string
        ok = False
    if not ok:
        for i, x in enumerate(v):
            if not isinstance(x, str):
                raise r.fail(ERR_INVALID_TYPE, f"'{r.name(key)}[{i}]' must be a string, got {_tname(x)}")
            if not one_re.fullmatch(x):
                raise r.fail(ERR_INVALID_VALUE, f"'{r.name(key)}[{i}]' must be {what}, got {x[:70]!r}")
    return v


def read_moves(r: _Reader, limits: Limits) -> PinMoves | None:
    """The ``moves`` block of a batch control, validated as a whole (any fault refuses the
    request): ``cloths`` and ``tokens`` arrays of equal length 1..max_batch_moves of valid ids and
    tokens; ``indices`` 1..max_pin_updates distinct u32; ``targets`` exactly n * k * 3 finite f32
    within +-max_coordinate. Ownership, ranges and pinned-ness are the server's to check."""
    mr = r.sub("moves")
    if mr is None:
        return None
    cap = limits.max_batch_moves
    cloths = _strings(mr, "cloths", cap, _IDS_RE, ID_RE, "a cloth id (1-64 characters of [A-Za-z0-9_.-])")
    tokens = _strings(mr, "tokens", cap, _TOKENS_RE, TOKEN_RE, "32 lowercase hex digits")
    n = len(cloths)
    if not n:
        raise r.fail(ERR_INVALID_VALUE, f"'{mr.name('cloths')}' must name at least one cloth")
    if len(tokens) != n:
        raise r.fail(ERR_INVALID_VALUE, f"'{mr.name('tokens')}' has {len(tokens)} entries but 'cloths' has {n}")
    idx = mr.blob("indices", "u4", 1, limits.max_pin_updates, True)
    assert idx is not None
    k = len(idx)
    if not k:
        raise r.fail(ERR_INVALID_VALUE, f"'{mr.name('indices')}' must hold at least one vertex index")
    if k > 1 and len(np.unique(idx)) != k:
        raise r.fail(ERR_INVALID_VALUE, f"'{mr.name('indices')}' repeats a vertex index")
    raw = mr.raw("targets", True)
    if not isinstance(raw, (bytes, bytearray)):
        raise r.fail(
            ERR_INVALID_TYPE,
            f"'{mr.name('targets')}' must be binary (msgpack bin) of little-endian f4, got {_tname(raw)}",
        )
    if len(raw) != n * k * 12:
        raise r.fail(
            ERR_INVALID_VALUE,
            f"'{mr.name('targets')}' has {len(raw)} bytes, expected {n} cloths x {k} pins x 3 x 4 = {n * k * 12}",
        )
    tgt = np.frombuffer(bytes(raw), np.dtype("<f4")).reshape(n, k, 3)
    bound = limits.max_coordinate
    if not (float(tgt.min()) >= -bound and float(tgt.max()) <= bound):  # NaN fails both comparisons
        flat = tgt.reshape(-1)
        bad = int(np.flatnonzero(~(np.abs(flat) <= bound))[0])
        what = "finite" if not np.isfinite(flat[bad]) else f"within +-{bound:g}"
        raise r.fail(
            ERR_INVALID_VALUE,
            f"'{mr.name('targets')}' values must be {what}: value {bad} (cloth {bad // (3 * k)}) is {flat[bad]}",
        )
    return PinMoves(cloths, tokens, idx, tgt)


def check_items_with_moves(r: _Reader, raw_items: Any, has_moves: bool, max_items: int) -> list:
    """``items`` of a batch control: 1..max_batch_items maps; with ``moves`` (1.4) absent or empty too."""
    if raw_items is None:
        if has_moves:
            return []
        raise r.fail(ERR_MISSING_FIELD, "field 'items' is required (unless 'moves' is given, 1.4)")
    if not isinstance(raw_items, list):
        raise r.fail(ERR_INVALID_TYPE, f"'items' must be an array of control maps, got {_tname(raw_items)}")
    if not raw_items and not has_moves:
        raise r.fail(ERR_INVALID_VALUE, "'items' must hold at least one control (or give 'moves', 1.4)")
    if len(raw_items) > max_items:
        raise r.fail(ERR_TOO_LARGE, f"'items' has {len(raw_items)} controls, more than the limit of {max_items}")
    return raw_items


def moves_failed_to_wire(failed: Sequence[tuple[int, str, str]]) -> list[list[Any]]:
    return [[int(p), str(c), str(m)] for p, c, m in failed]


def moves_reply_from_map(m: Mapping[str, Any], r: _Reader) -> tuple[int | None, list[tuple[int, str, str]] | None]:
    """``moves_tick`` and ``moves_failed`` of a batch reply (both None from a server older than 1.4)."""
    tick = r.int_("moves_tick", 0, (1 << 64) - 1)
    raw = m.get("moves_failed")
    if raw is None:
        return tick, None
    if not isinstance(raw, list):
        raise r.fail(ERR_INVALID_TYPE, f"'moves_failed' must be an array, got {_tname(raw)}")
    out: list[tuple[int, str, str]] = []
    for i, x in enumerate(raw):
        if not (
            isinstance(x, list)
            and len(x) == 3
            and isinstance(x[0], int)
            and not isinstance(x[0], bool)
            and isinstance(x[1], str)
            and isinstance(x[2], str)
        ):
            raise ProtocolError(
                ERR_INVALID_TYPE, f"'moves_failed[{i}]' must be [position, code, message], got {_tname(x)}", r.rid
            )
        out.append((x[0], x[1], x[2]))
    return tick, out
