"""Protocol 1.4 ``moves`` (PROTOCOL.md 5.1.1): a batch control's columnar block of pin moves,
checked on arrival and applied by the tick thread, with Python work per message, not per move.

On arrival (:class:`MoveChecker`, a Zenoh callback): ownership of every move with set and map
operations that run in C (the client's cloth set covers the block's ids, one constant-time
comparison of the joined tokens, every cloth in the World); pinned-ness of the shared indices
once per fabric (a bounded cache keyed by fabric and index bytes). Only when one of those fails
does a per-move loop find and name the refused moves (``not_found``, ``forbidden``,
``index_out_of_range``, ``invalid_value``); a cloth listed twice keeps its last position.

In the tick (:func:`apply_blocks`): after the tick's controls, each block is one vectorised
``World.set_pin_targets_block``; moves of cloths removed meanwhile are refused ``not_found``, moves
of cloths reset in the same tick are dropped (the reset wins, as over pins given with it), and
the request is answered once its block (and its items) are settled.
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

from ...sim.world import World
from ..commands import BatchControl, MoveBlock
from ..registry import ClothRecord, Registry
from ..replies import Reply

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


def apply_blocks(
    world: World, blocks: list[MoveBlock], tick: int, resets: set[int], registry: Registry, before: list[Reply]
) -> None:
    """Apply this tick's moves blocks in arrival order (after the tick's controls); replies of
    the requests now settled go to ``before``."""
    reset_arr = np.fromiter(resets, np.int64, len(resets)) if resets else None
    applied = superseded = 0
    errors: dict[str, int] = {}
    for b in blocks:
        w = b.waiter
        assert w.moves_failed is not None
        try:
            live = world.live(b.handles)
            keep = live if reset_arr is None else live & ~np.isin(b.handles, reset_arr)
            if not live.all():
                for p in b.positions[~live].tolist():
                    w.moves_failed.append((p, P.ERR_NOT_FOUND, f"no cloth {b.cloths[p]!r}: removed"))
                errors[P.ERR_NOT_FOUND] = errors.get(P.ERR_NOT_FOUND, 0) + int((~live).sum())
            if keep.all():
                world.set_pin_targets_block(b.handles, b.indices, b.targets, validated=True)
            elif keep.any():
                world.set_pin_targets_block(b.handles[keep], b.indices, b.targets[keep], validated=True)
            applied += int(keep.sum())
        except Exception as e:  # one block's failure must not leave the others unanswered
            log.exception("applying a moves block failed")
            done = {p for p, _, _ in w.moves_failed}
            for p in b.positions.tolist():
                if p not in done:
                    w.moves_failed.append((p, P.ERR_INTERNAL, f"internal error: {type(e).__name__}"))
        w.moves_tick = tick
        rep = w.one_done(tick)
        if rep is not None:
            before.append(rep)
        for old in b.superseded:  # the same moves, replaced before their tick by this block's
            assert old.moves_failed is not None
            old.moves_failed.extend(w.moves_failed)
            old.moves_tick = tick
            rep = old.one_done(tick)
            if rep is not None:
                before.append(rep)
        superseded += len(b.superseded)
    registry.count_many(moves_applied=applied, move_blocks=len(blocks), move_blocks_superseded=superseded)
    for code, k in errors.items():
        registry.error(code, k)
