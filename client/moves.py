"""The SDK's side of protocol 1.4 ``moves`` (PROTOCOL.md 5.1.1): many cloths' pin moves as one
columnar block per request, for a game loop that moves every cloth's pins every tick.

- :meth:`ClientMoves.send` is ``DrapeClient.move_pins_many``'s vectorised path: the handles'
  ids and tokens are cached per handle tuple (a :class:`MoveGroup`, rebuilt only when a handle of
  the client is rebound by a failover or closed), so a tick costs O(1) Python per request: no
  loop over cloths. Each handle's last targets are recorded as the group's last block (one
  copy of the targets), folded into the handle's own record (``ClothHandle._last_pins``) only when
  the handle needs it: before its own next control, or to re-send after a failover.
- :meth:`ClientMoves.split` lets ``ControlBatch`` send its pins-only items that share one index
  list as a block instead of one item each.

Both only to a server whose ``info.version`` is 1.4 or later (a 1.3 server would ignore the
field): otherwise the same controls go as batch items.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from operator import attrgetter
from typing import TYPE_CHECKING, Any

import numpy as np

from . import protocol as P
from .controls import BatchError
from .protocol import DrapeError

if TYPE_CHECKING:
    from .handle import ClothHandle
    from .sdk import DrapeClient

GROUPS = 16  # handle tuples whose ids and tokens are cached
_ID, _TOKEN, _SERVER = attrgetter("id"), attrgetter("token"), attrgetter("server_id")
ErrorCallback = Callable[[DrapeError], None]


@dataclass(eq=False)
class MoveGroup:
    """One tuple of handles as the wire needs it, per server (after a failover a client's
    cloths may live on several): (server, positions in the tuple, ids, tokens)."""

    handles: tuple[ClothHandle, ...]
    epoch: int
    parts: list[tuple[str | None, np.ndarray, list[str], list[str]]]
    last: tuple[int, np.ndarray, np.ndarray] | None = None  # (seq, indices, targets (n, k, 3)) last sent
    _index: dict[ClothHandle, int] | None = None

    def row(self, handle: ClothHandle) -> int | None:
        if self._index is None:
            self._index = dict(zip(self.handles, range(len(self.handles)), strict=True))
        return self._index.get(handle)


class ClientMoves:
    """One DrapeClient's moves blocks: groups, per-server versions, the last targets sent."""

    def __init__(self, client: DrapeClient) -> None:
        self.client = client
        self._lock = threading.Lock()
        self._groups: dict[tuple[ClothHandle, ...], MoveGroup] = {}
        self._epoch = 0
        self._seq = itertools.count(1)
        self._versions: dict[str, tuple[int, int]] = {}

    # --- capability ------------------------------------------------------------------------
    def speaks_moves(self, server: str | None) -> bool:
        """Whether ``server`` (None: the client's) speaks 1.4: the client's ``server_version`` for
        its own server, else asked with info once per server."""
        sid = server or self.client.server_id
        if sid == self.client.server_id:
            return self.client.server_version >= (1, 4)
        v = self._versions.get(sid)
        if v is None:
            info = self.client.request("info", P.encode_info(P.InfoRequest(self.client._next_rid())), server=sid)
            major, _, minor = str(info.get("version", "1.0")).partition(".")
            v = self._versions[sid] = (int(major), int(minor or 0))
        return v >= (1, 4)

    # --- handles -------------------------------------------------------------------------------
    def changed(self) -> None:
        """A handle was rebound (failover) or closed: cached ids and tokens are stale."""
        with self._lock:
            self._epoch += 1

    def _group(self, handles: Sequence[ClothHandle]) -> MoveGroup:
        key = tuple(handles)
        with self._lock:
            g = self._groups.get(key)
            if g is not None and g.epoch == self._epoch:
                return g
            epoch = self._epoch
        for h in key:
            if h.client is not self.client:
                raise ValueError(f"cloth {h.id} belongs to another DrapeClient")
            h._check_open()
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

    def _fold_out(self, g: MoveGroup) -> None:
        """An evicted group's last block, into each of its handles' own record."""
        for h in g.handles:
            self.fold(h, g)

    def fold(self, handle: ClothHandle, only: MoveGroup | None = None) -> None:
        """Bring ``handle._last_pins`` up to date with the blocks sent since its last fold (in
        the order they were sent): called before the handle records a control of its own and
        before a failover re-sends its last targets."""
        with self._lock:
            groups = [only] if only is not None else list(self._groups.values())
            since = getattr(handle, "_pins_seq", 0)
            rows = []
            for g in groups:
                if g.last is not None and g.last[0] > since and (j := g.row(handle)) is not None:
                    rows.append((g.last[0], g.last[1], g.last[2][j]))
            handle._pins_seq = next(self._seq)  # type: ignore[attr-defined]
        for _, idx, tgt in sorted(rows, key=lambda r: r[0]):
            handle._last_pins.update(zip(idx.tolist(), tgt, strict=True))

    # --- sending -------------------------------------------------------------------------------
    def send(
        self,
        handles: Sequence[ClothHandle],
        indices: np.ndarray,
        targets: np.ndarray,
        wait: bool,
        on_error: ErrorCallback | None,
        timeout: float | None = None,
    ) -> list[int | DrapeError] | None:
        """Move pins ``indices`` of every cloth of ``handles`` to ``targets`` ((n, k, 3)): one
        request per server (and per max_batch_moves cloths)."""
        idx = np.asarray(indices, np.int64).reshape(-1)
        n = len(handles)
        tgt = np.array(targets, np.float32, copy=True).reshape(n, len(idx), 3)  # the record keeps it
        if not n:
            return [] if wait else None
        if len(idx) and idx.min() < 0:
            raise ValueError("pin indices must be >= 0")
        g = self._group(handles)
        with self._lock:
            g.last = (next(self._seq), idx, tgt)
        idx32 = idx.astype(np.uint32)
        out: list[int | DrapeError | None] | None = [None] * n if wait else None
        for server, pos, ids, tokens in g.parts:
            if not self.speaks_moves(server):  # a 1.3 server ignores moves: batch items instead
                b = self.client.batch(wait=wait, on_error=on_error, timeout=timeout)
                for p in pos.tolist():
                    b.items.append((g.handles[p], P.ControlRequest(ids[p], tokens[p], pins=P.PinUpdate(idx32, tgt[p]))))
                got = b.send()
                if out is not None and got is not None:
                    for p, r in zip(pos.tolist(), got, strict=True):
                        out[p] = r
                continue
            step = P.DEFAULT_LIMITS.max_batch_moves
            part_tgt = tgt if len(pos) == n else tgt[pos]
            for s in range(0, len(pos), step):
                mv = P.PinMoves(ids[s : s + step], tokens[s : s + step], idx32, part_tgt[s : s + step])
                got = self.send_block(
                    mv, [g.handles[p] for p in pos[s : s + step].tolist()], wait, on_error, timeout, server
                )
                if out is not None and got is not None:
                    for p, r in zip(pos[s : s + step].tolist(), got, strict=True):
                        out[p] = r
        if out is not None and any(isinstance(r, DrapeError) for r in out):
            raise BatchError(out)  # type: ignore[arg-type]
        return out  # type: ignore[return-value]

    def send_block(
        self,
        mv: P.PinMoves,
        handles: list[ClothHandle],
        wait: bool,
        on_error: ErrorCallback | None,
        timeout: float | None,
        server: str | None,
    ) -> list[int | DrapeError] | None:
        """One batch control carrying ``mv`` alone; ``wait``: each move's tick or error."""
        c = self.client
        rid = c._next_rid()
        payload = P.encode_control_batch(P.ControlBatchRequest(c.client_id, [], rid, mv))
        if not wait:
            c.send(
                "control_batch",
                payload,
                on_error,
                timeout,
                on_ok=lambda m: self._replied(handles, m, rid, on_error),
                server=server,
            )
            return None
        rep = P.control_batch_reply_from_map(c.request("control_batch", payload, timeout, server=server))
        tick = rep.tick if rep.moves_tick is None else rep.moves_tick
        out: list[int | DrapeError] = [tick] * len(handles)
        for p, err in self._errors(handles, rep, rid):
            out[p] = err
        return out

    def _errors(self, handles: list[ClothHandle], rep: P.ControlBatchReply, rid: int) -> list[tuple[int, DrapeError]]:
        if rep.moves_failed is None:
            raise DrapeError(P.ERR_INTERNAL, "the server answered moves without moves_failed (not 1.4)", rid)
        out = []
        for p, code, msg in rep.moves_failed:
            if not 0 <= p < len(handles):
                raise DrapeError(P.ERR_INTERNAL, f"moves_failed names position {p} of {len(handles)}", rid)
            err = P.error_for(code, f"cloth {handles[p].id}: {msg}", rid)
            if isinstance(err, P.NotFound):
                self.client._cloth_not_found(handles[p])
            out.append((p, err))
        return out

    def _replied(self, handles: list[ClothHandle], m: dict[str, Any], rid: int, on_error: ErrorCallback | None) -> None:
        rep = P.control_batch_reply_from_map(m)
        if rep.moves_failed:
            for p, err in self._errors(handles, rep, rid):
                self.client._send_failed(err, on_error, handles[p])

    # --- ControlBatch ---------------------------------------------------------------------------
    @staticmethod
    def split(items: list[tuple[ClothHandle, P.ControlRequest]]) -> tuple[list[int], P.PinMoves | None]:
        """The positions of the largest set (two or more) of pins-only items, one per cloth not
        otherwise in ``items``, that share one index list, and their block; ([], None) if none."""
        seen: dict[str, int] = {}
        for h, _ in items:
            seen[h.id] = seen.get(h.id, 0) + 1
        groups: dict[bytes, list[int]] = {}
        for i, (h, r) in enumerate(items):
            if seen[h.id] == 1 and _pins_only(r):
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


def _pins_only(r: P.ControlRequest) -> bool:
    """A control with pin targets (distinct indices) and nothing else: what a moves block carries."""
    if r.pins is None or not len(r.pins.indices) or r.reset or r.material:
        return False
    others = (r.colliders, r.gravity, r.wind, r.features, r.iterations, r.substeps, r.chebyshev_rho, r.state)
    if any(x is not None for x in (*others, r.quality, r.features_add, r.features_remove)):
        return False
    return len(np.unique(r.pins.indices)) == len(r.pins.indices)


def moves_of(client: DrapeClient) -> ClientMoves:
    """The client's ClientMoves, made on first use."""
    m = client.__dict__.get("_moves_state")
    if m is None:
        with client._lock:
            m = client.__dict__.setdefault("_moves_state", ClientMoves(client))
    return m
