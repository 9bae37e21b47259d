"""Protocol 1.4 ``moves`` (PROTOCOL.md 5.1.1) on arrival: a batch control's columnar block of pin
moves checked by the request thread, with Python work per message, not per move (the tick
thread applies the accepted blocks: drape.server.service.tick.moves).

:class:`MoveChecker`, run by the batch control's handler: ownership of every move with set and map
operations that run in C (the client's cloth set covers the block's ids, one constant-time
comparison of the joined tokens, every cloth in the World); pinned-ness of the shared indices
once per fabric (a bounded cache keyed by fabric and index bytes). Only when one of those fails
does a per-move loop find and name the refused moves (``not_found``, ``forbidden``,
``index_out_of_range``, ``invalid_value``); a cloth listed twice keeps its last position.
"""

from __future__ import annotations

import hmac
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from operator import attrgetter
from typing import Any

import numpy as np

from drape.client import protocol as P

from ..commands import BatchControl, MoveBlock
from ..registry import ClothRecord, Registry

log = logging.getLogger(__name__)

VERDICTS = 4096  # (fabric, index block) verdicts kept; past it the cache starts over
_HANDLE = attrgetter("handle")
_TOKEN = attrgetter("token")
_FABRIC_KEY = attrgetter("fabric.key")
CLIENTS_SEEN = 4096  # clients whose last accepted block is remembered; past it the memo starts over


@dataclass(eq=False)
class _Accepted:
    """A client's last block accepted whole: the next one moving the same cloths (the game loop's
    every tick) is checked by comparing with it instead of against the registry again."""

    ids: list[str]
    tokens: str  # joined
    idx_bytes: bytes
    generation: int  # the registry's then: a cloth removed since (a handle reused) voids it
    handles_arr: np.ndarray  # the same array object every time: the intake coalesces by it
    positions: np.ndarray


class MoveChecker:
    """Checks a decoded ``moves`` block against the registry (thread-safe)."""

    def __init__(self, registry: Registry) -> None:
        self.registry = registry
        self._verdicts: dict[tuple[str, bytes], tuple[str, str] | None] = {}
        self._accepted: dict[str, _Accepted] = {}

    def check(self, mv: P.PinMoves, client: str, waiter: BatchControl) -> MoveBlock | None:
        """The block of the moves that may be applied, or None when none may; the refused ones
        go to ``waiter.moves_failed`` as (position, code, message)."""
        ids, n = mv.cloths, len(mv.cloths)
        idx_bytes = np.ascontiguousarray(mv.indices, np.uint32).tobytes()
        tokens = "".join(mv.tokens)
        last = self._accepted.get(client)
        if (
            last is not None
            and last.idx_bytes == idx_bytes
            and last.ids == ids
            and last.generation == self.registry.generation  # no cloth has gone since
            and hmac.compare_digest(last.tokens, tokens)
        ):
            waiter.moves_failed = []
            return self._block(last.handles_arr, last.positions, mv, waiter)
        reg = self.registry
        uniq = set(ids)
        with reg.lock:
            generation = reg.generation
            mine = reg.by_client.get(client)
            fast = mine is not None and len(uniq) == n and uniq <= mine
            recs: list[ClothRecord | None] = list(map(reg.cloths.__getitem__ if fast else reg.cloths.get, ids))
        failed: list[tuple[int, str, str]] = []
        waiter.moves_failed = failed
        if fast:
            handles = list(map(_HANDLE, recs))
            if (
                None not in handles
                and hmac.compare_digest("".join(map(_TOKEN, recs)), tokens)
                and all(self._verdict(r, mv.indices, idx_bytes) is None for r in self._by_fabric(recs))
            ):
                pos = np.arange(n, dtype=np.int64)
                arr = np.array(handles, np.int64)
                if len(self._accepted) >= CLIENTS_SEEN:
                    self._accepted.clear()
                self._accepted[client] = _Accepted(list(ids), tokens, idx_bytes, generation, arr, pos)
                return self._block(arr, pos, mv, waiter)
        keep: dict[str, int] = {}  # cloth -> its last acceptable position
        for p, (rec, tok) in enumerate(zip(recs, mv.tokens, strict=True)):
            err = self._refusal(rec, ids[p], tok, client, mv.indices, idx_bytes)
            if err is None:
                keep[ids[p]] = p
            else:
                failed.append((p, *err))
        if not keep:
            return None
        pos = np.fromiter(keep.values(), np.int64, len(keep))
        handles_arr = np.fromiter((recs[p].handle for p in pos.tolist()), np.int64, len(pos))  # type: ignore[union-attr]
        return self._block(handles_arr, pos, mv, waiter)

    @staticmethod
    def _block(handles: np.ndarray, pos: np.ndarray, mv: P.PinMoves, waiter: BatchControl) -> MoveBlock:
        tgt = np.asarray(mv.targets, np.float32).reshape(len(mv.cloths), len(mv.indices), 3)
        if len(pos) != len(tgt):
            tgt = tgt[pos]
        return MoveBlock(handles, pos, mv.cloths, np.asarray(mv.indices, np.int64), tgt, waiter)

    @staticmethod
    def _by_fabric(recs: Iterable[Any]) -> Iterable[ClothRecord]:
        """One record per distinct fabric."""
        return dict(zip(map(_FABRIC_KEY, recs), recs, strict=False)).values()

    def _refusal(
        self, rec: ClothRecord | None, cloth: str, token: str, client: str, idx: np.ndarray, idx_bytes: bytes
    ) -> tuple[str, str] | None:
        """Why one move is refused (the order of a single control's checks), or None."""
        if rec is None or rec.removed or rec.fabric is None or rec.handle is None:
            reg = self.registry
            with reg.lock:
                reason = reg.tombstones.get(cloth)
            where = f"no cloth {cloth!r} on server {reg.config.server_id!r}"
            return P.ERR_NOT_FOUND, f"{where}: {reason}" if reason else where
        if not hmac.compare_digest(rec.token, token):
            return P.ERR_FORBIDDEN, f"the token does not own cloth {cloth!r}"
        if rec.client != client:
            return P.ERR_FORBIDDEN, f"cloth {cloth!r} is not a cloth of client {client!r}"
        return self._verdict(rec, idx, idx_bytes)

    def _verdict(self, rec: ClothRecord, idx: np.ndarray, idx_bytes: bytes) -> tuple[str, str] | None:
        """Whether the block's indices are pinned vertices of ``rec``'s fabric (cached per fabric)."""
        f = rec.fabric
        assert f is not None
        key = (f.key, idx_bytes)
        try:
            return self._verdicts[key]
        except KeyError:
            pass
        top = int(idx.max())
        verdict: tuple[str, str] | None = None
        if top >= f.n_vertices:
            verdict = (
                P.ERR_INDEX_OUT_OF_RANGE,
                f"'moves.indices' refers to vertex {top} but the cloth has {f.n_vertices} vertices",
            )
        else:
            free = idx[~f.pinned[idx]]
            if len(free):
                verdict = (
                    P.ERR_INVALID_VALUE,
                    f"vertex {int(free[0])} of the cloth is not pinned; only pinned vertices take targets",
                )
        if len(self._verdicts) >= VERDICTS:
            self._verdicts.clear()
        self._verdicts[key] = verdict
        return verdict


def refused_counts(failed: list[tuple[int, str, str]]) -> dict[str, int]:
    """Refused moves by error code."""
    out: dict[str, int] = {}
    for _, code, _ in failed:
        out[code] = out.get(code, 0) + 1
    return out
