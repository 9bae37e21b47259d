"""The SDK's record of protocol 1.4 ``moves`` blocks (PROTOCOL.md 5.1.1): many cloths' pin moves
as one columnar block per request, for a game loop that moves every cloth's pins every tick. No
I/O: the sending path (:mod:`.sending`) sends what this builds.

- :meth:`MoveBook.group`: the handles' ids and tokens, cached per handle tuple (a
  :class:`MoveGroup`, rebuilt only when a handle of the client is rebound by a failover or
  closed), so a tick costs O(1) Python per request: no loop over cloths. :meth:`MoveBook.record`
  keeps each handle's last targets as the group's last block (one copy of the targets), folded
  into the handle's own record (``ClothHandle.record_pins``) only when the handle needs it
  (:meth:`MoveBook.fold`): before its own next control, or to re-send after a failover.
- :meth:`MoveBook.split` finds a batch's pins-only items that share one index list, to send
  them as a block instead of one item each.
"""

from __future__ import annotations

import itertools
import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from operator import attrgetter
from typing import Protocol

import numpy as np

from . import protocol as P
from .controls import pins_only

GROUPS = 16  # handle tuples whose ids and tokens are cached
_ID, _TOKEN, _SERVER = attrgetter("id"), attrgetter("token"), attrgetter("server_id")


class Moved(Protocol):
    """What a moves block needs of a cloth handle (:class:`~drape.client.handle.Moved`)."""

    @property
    def id(self) -> str: ...
    @property
    def token(self) -> str: ...
    @property
    def server_id(self) -> str: ...
    @property
    def client(self) -> object: ...  # its owner (a DrapeClient)
    def check_open(self) -> None: ...
    def record_pins(self, indices: list[int], targets: np.ndarray) -> None: ...  # the last targets sent


@dataclass(eq=False)
class MoveGroup:
    """One tuple of handles as the wire needs it, per server (after a failover a client's
    cloths may live on several): (server, positions in the tuple, ids, tokens)."""

    handles: tuple[Moved, ...]
    epoch: int
    parts: list[tuple[str | None, np.ndarray, list[str], list[str]]]
    last: tuple[int, np.ndarray, np.ndarray] | None = None  # (seq, indices, targets (n, k, 3)) last sent
    _index: dict[Moved, int] | None = None

    def row(self, handle: Moved) -> int | None:
        if self._index is None:
            self._index = dict(zip(self.handles, range(len(self.handles)), strict=True))
        return self._index.get(handle)


class MoveBook:
    """One client's moves blocks: the handle groups and the last targets sent (module docstring).
    ``owner``: the client whose handles it takes."""

    def __init__(self, owner: object) -> None:
        self.owner = owner
        self._lock = threading.Lock()
        self._groups: dict[tuple[Moved, ...], MoveGroup] = {}
        self._epoch = 0
        self._seq = itertools.count(1)
        self._folded: weakref.WeakKeyDictionary[Moved, int] = weakref.WeakKeyDictionary()  # its last fold's seq

    # --- handles -------------------------------------------------------------------------------
    def changed(self) -> None:
        """A handle was rebound (failover) or closed: cached ids and tokens are stale."""
        with self._lock:
            self._epoch += 1

    def group(self, handles: Sequence[Moved]) -> MoveGroup:
        """The cached group of ``handles`` (each checked open when it is (re)built)."""
        key = tuple(handles)
        with self._lock:
            g = self._groups.get(key)
            if g is not None and g.epoch == self._epoch:
                return g
            epoch = self._epoch
        for h in key:
            if h.client is not self.owner:
                raise ValueError(f"cloth {h.id} belongs to another DrapeClient")
            h.check_open()
        servers = list(map(_SERVER, key))
        ids, tokens = list(map(_ID, key)), list(map(_TOKEN, key))
        if len(set(servers)) == 1:
            parts = [(servers[0], np.arange(len(key)), ids, tokens)]
        else:
            parts = []
            for s in dict.fromkeys(servers):
                pos = np.flatnonzero(np.array([x == s for x in servers]))
                parts.append((s, pos, [ids[p] for p in pos], [tokens[p] for p in pos]))
        new = MoveGroup(key, epoch, parts)
        with self._lock:
            old = self._groups.pop(key, None)
            if old is not None and old.last is not None:
                new.last = old.last
            if len(self._groups) >= GROUPS:
                self._fold_out(self._groups.pop(next(iter(self._groups))))
            self._groups[key] = new
        return new

    def record(self, g: MoveGroup, indices: np.ndarray, targets: np.ndarray) -> None:
        """``targets`` ((n, k, 3), kept as is) of pins ``indices`` are sent to ``g``'s cloths."""
        with self._lock:
            g.last = (next(self._seq), indices, targets)

    def _fold_out(self, g: MoveGroup) -> None:
        """An evicted group's last block, into each of its handles' own record."""
        for h in g.handles:
            self.fold(h, g)

    def fold(self, handle: Moved, only: MoveGroup | None = None) -> None:
        """Hand ``handle`` (``record_pins``) the targets of the blocks sent since its last fold, in
        the order they were sent: called before the handle records a control of its own and
        before a failover re-sends its last targets."""
        with self._lock:
            groups = [only] if only is not None else list(self._groups.values())
            since = self._folded.get(handle, 0)
            rows = []
            for g in groups:
                if g.last is not None and g.last[0] > since and (j := g.row(handle)) is not None:
                    rows.append((g.last[0], g.last[1], g.last[2][j]))
            self._folded[handle] = next(self._seq)
        for _, idx, tgt in sorted(rows, key=lambda r: r[0]):
            handle.record_pins(idx.tolist(), tgt)

    # --- batches --------------------------------------------------------------------------------
    @staticmethod
    def split(items: Sequence[tuple[Moved, P.ControlRequest]]) -> tuple[list[int], P.PinMoves | None]:
        """The positions of the largest set (two or more) of pins-only items, one per cloth not
        otherwise in ``items``, that share one index list, and their block; ([], None) if none."""
        seen: dict[str, int] = {}
        for h, _ in items:
            seen[h.id] = seen.get(h.id, 0) + 1
        groups: dict[bytes, list[int]] = {}
        for i, (h, r) in enumerate(items):
            if seen[h.id] == 1 and pins_only(r):
                assert r.pins is not None
                groups.setdefault(np.asarray(r.pins.indices, np.uint32).tobytes(), []).append(i)
        if not groups:
            return [], None
        key, pos = max(groups.items(), key=lambda kv: len(kv[1]))
        if len(pos) < 2:
            return [], None
        pos = pos[: P.DEFAULT_LIMITS.max_batch_moves]
        reqs = [items[i][1] for i in pos]
        idx = np.frombuffer(key, np.uint32)
        tgt = np.stack([np.asarray(r.pins.targets, np.float32).reshape(len(idx), 3) for r in reqs])  # type: ignore[union-attr]
        return pos, P.PinMoves([r.cloth for r in reqs], [r.token for r in reqs], idx, tgt)


__all__ = ["GROUPS", "MoveBook", "MoveGroup", "Moved"]
