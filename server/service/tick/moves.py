"""Protocol 1.4 ``moves`` (PROTOCOL.md 5.1.1) in the tick: the blocks of pin moves the request
thread checked (drape.server.service.requests.moves) applied by the tick thread after the tick's
controls, each block one vectorised ``World.set_pin_targets_block``; moves of cloths removed
meanwhile are refused ``not_found``, moves of cloths reset in the same tick are dropped (the reset
wins, as over pins given with it), and the request is answered once its block (and its items) are
settled.
"""

from __future__ import annotations

import logging

import numpy as np

from drape.client import protocol as P

from ...sim.world import World
from ..commands import MoveBlock
from ..registry import Registry
from ..replies import Reply

log = logging.getLogger(__name__)


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
