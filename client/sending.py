"""The SDK's one sending path for controls (:class:`ControlSender`): every control of a cloth,
alone or with many others, reaches its server here, in the wire form the *target* server's
version allows (its info, asked once per server by the :class:`~.connection.Session`):

- one cloth's control: a ``control`` request (:meth:`ControlSender.control`);
- many cloths' controls (:meth:`ControlSender.controls`): grouped by the server each cloth lives
  on; pins-only items sharing one index list as one 1.4 ``moves`` block; the rest as batch
  control requests of at most the server's ``max_batch_items`` (1.1), or one control each to a
  1.0 server; replies folded back into one outcome per item (its first tick or its DrapeError);
- many cloths' pins to shared indices (:meth:`ControlSender.moves`, ``move_pins_many``): one
  ``moves`` block per server (and per ``max_batch_moves`` cloths) with no Python loop over the
  cloths, batch items to a server older than 1.4.

``features_add`` / ``features_remove`` need a 1.2 server (an older one ignores unknown keys, so
the change would be silently lost): refused before anything is sent. A ``not_found`` answer is
handed to ``lost`` (the client's failover).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any, Protocol

import numpy as np

from . import protocol as P
from .connection import ErrorCallback, ServerInfo, Session
from .controls import BatchError, features_delta, item_outcomes
from .moves import MoveBook, Moved
from .protocol import DrapeError

log = logging.getLogger(__name__)


class Target(Moved, Protocol):
    """What the sending path needs of a cloth handle (:class:`~drape.client.handle.ClothHandle`)."""

    def removal_outcome(self, err: DrapeError) -> bool: ...  # a not_found this client caused


Items = Sequence[tuple[Target, P.ControlRequest]]
Outcomes = list[int | DrapeError]


class ControlSender:
    """Controls of one client's cloths to their servers (module docstring). ``lost(handle)``: a
    control of ``handle`` was answered ``not_found``."""

    def __init__(self, session: Session, moves: MoveBook, lost: Callable[[Target], None]) -> None:
        self.session = session
        self.book = moves
        self.lost = lost

    # --- what the target server takes -------------------------------------------------------------
    def server_info(self, server: str | None, reqs: Sequence[P.ControlRequest] = ()) -> ServerInfo:
        """``server``'s info (None: the default server), after checking that it takes ``reqs``."""
        info = self.session.info_of(server)
        if features_delta(reqs) and info.version < (1, 2):
            raise P.ProtocolError(
                P.ERR_INVALID_VALUE,
                "features_add / features_remove need a protocol 1.2 server; "
                f"this one speaks {info.version[0]}.{info.version[1]}: send the "
                "whole set with features= instead",
            )
        if info.version < (1, 8) and any(r.mesh_collider is not None for r in reqs):
            raise P.ProtocolError(
                P.ERR_INVALID_VALUE,
                f"mesh_collider needs a protocol 1.8 server; this one speaks {info.version[0]}.{info.version[1]}",
            )
        return info

    def _on_error(self, h: Target, on_error: ErrorCallback | None) -> ErrorCallback:
        """``on_error`` (default: a warning) after handing a ``not_found`` of ``h`` to ``lost``."""

        def cb(err: DrapeError) -> None:
            if isinstance(err, P.NotFound):
                self.lost(h)
            if on_error is not None:
                on_error(err)
            else:
                log.warning("request failed: %s", err)

        return cb

    # --- one cloth --------------------------------------------------------------------------------
    def control(
        self, h: Target, req: P.ControlRequest, wait: bool, timeout: float | None = None, checked: bool = False
    ) -> P.ControlReply | None:
        """``req`` to ``h``'s server; ``wait``: its reply (raising its DrapeError), else None (an
        error goes to the log and ``send_errors``). ``checked``: the caller checked that the server
        takes it (``server_info``)."""
        if not checked:
            self.server_info(h.server_id or None, (req,))
        if not wait:
            self.session.send(
                "control",
                P.encode_control(req),
                self._on_error(h, None),
                timeout,
                server=h.server_id or None,
                excused=h.removal_outcome,
            )
            return None
        try:
            m = self.session.request("control", P.encode_control(req), timeout, server=h.server_id or None)
        except P.NotFound:
            self.lost(h)
            raise
        return P.control_reply_from_map(m)

    # --- many cloths ------------------------------------------------------------------------------
    def controls(
        self, items: Items, wait: bool, on_error: ErrorCallback | None, timeout: float | None
    ) -> Outcomes | None:
        """Send ``items`` (handle, control). ``wait``: returns each item's first tick or
        DrapeError, in order; otherwise None (errors go to ``on_error``)."""
        if not items:
            return [] if wait else None
        servers = {h.server_id for h, _ in items}
        if len(servers) > 1:  # after a failover a client's cloths may live on several servers
            order: dict[str, list[int]] = {}
            for i, (h, _) in enumerate(items):
                order.setdefault(h.server_id, []).append(i)
            merged: list[int | DrapeError | None] = [None] * len(items)
            for idx in order.values():
                part = self.controls([items[i] for i in idx], wait, on_error, timeout)
                for i, r in zip(idx, part or (), strict=False):
                    merged[i] = r
            return merged if wait else None  # type: ignore[return-value]
        server = items[0][0].server_id or None
        info = self.server_info(server, [r for _, r in items])
        limit = info.batch_limit
        if len(items) > 1 and limit and info.version >= (1, 4):  # pins-only items sharing one index list
            pos, block = self.book.split(items)
            if block is not None:
                moved = self._block(block, [items[i][0] for i in pos], wait, on_error, timeout, server)
                rest = set(pos)
                others = self.controls([it for i, it in enumerate(items) if i not in rest], wait, on_error, timeout)
                if not wait:
                    return None
                it_moved, it_others = iter(moved or ()), iter(others or ())
                return [next(it_moved) if i in rest else next(it_others) for i in range(len(items))]
        if not limit:  # a 1.0 server: one control per item
            log.debug("server speaks %s: batch sent as %d controls", info.version, len(items))
            out: Outcomes = []
            for h, req in items:
                if wait:
                    try:
                        out.append(
                            P.tick_reply_from_map(
                                self.session.request("control", P.encode_control(req), timeout, server=server)
                            )
                        )
                    except DrapeError as e:
                        if isinstance(e, P.NotFound):
                            self.lost(h)
                        out.append(e)
                else:
                    self.session.send(
                        "control",
                        P.encode_control(req),
                        self._on_error(h, on_error),
                        timeout,
                        server=server,
                        excused=h.removal_outcome,
                    )
            return out if wait else None
        results: Outcomes = []
        for start in range(0, len(items), limit):
            chunk = items[start : start + limit]
            rid = self.session.next_rid()
            payload = P.encode_control_batch(P.ControlBatchRequest(self.session.client_id, [r for _, r in chunk], rid))
            if wait:
                rep = P.control_batch_reply_from_map(self.session.request("control_batch", payload, timeout, server))
                outcomes = item_outcomes([h.id for h, _ in chunk], rep, rid)
                for (h, _), r in zip(chunk, outcomes, strict=True):
                    if isinstance(r, P.NotFound):
                        self.lost(h)
                results.extend(outcomes)
            else:
                self.session.send(
                    "control_batch",
                    payload,
                    on_error,
                    timeout,
                    on_ok=partial(self._batch_replied, chunk, rid=rid, on_error=on_error),
                    server=server,
                )
        return results if wait else None

    def _batch_replied(self, chunk: Items, m: dict[str, Any], rid: int, on_error: ErrorCallback | None) -> None:
        rep = P.control_batch_reply_from_map(m)
        if rep.failed:
            for (h, _), r in zip(chunk, item_outcomes([h.id for h, _ in chunk], rep, rid), strict=True):
                if isinstance(r, DrapeError):
                    if isinstance(r, P.NotFound):
                        self.lost(h)
                    self.session.failed(r, on_error, h.removal_outcome)

    # --- moves blocks (1.4) ------------------------------------------------------------------------
    def moves(
        self,
        handles: Sequence[Target],
        indices: np.ndarray,
        targets: np.ndarray,
        wait: bool,
        on_error: ErrorCallback | None,
        timeout: float | None = None,
    ) -> Outcomes | None:
        """Move pins ``indices`` of every cloth of ``handles`` to ``targets`` ((n, k, 3)): one
        request per server (and per max_batch_moves cloths); batch items to a server older than
        1.4 (it would ignore the field). ``wait``: BatchError (with every outcome) if any was
        refused."""
        idx = np.asarray(indices, np.int64).reshape(-1)
        n = len(handles)
        tgt = np.array(targets, np.float32, copy=True).reshape(n, len(idx), 3)  # the record keeps it
        if not n:
            return [] if wait else None
        if len(idx) and idx.min() < 0:
            raise ValueError("pin indices must be >= 0")
        g = self.book.group(handles)
        self.book.record(g, idx, tgt)
        idx32 = idx.astype(np.uint32)
        out: list[int | DrapeError | None] | None = [None] * n if wait else None
        for server, pos, ids, tokens in g.parts:
            if self.session.info_of(server).version < (1, 4):  # a 1.3 server ignores moves: batch items
                items = [
                    (handles[p], P.ControlRequest(ids[p], tokens[p], pins=P.PinUpdate(idx32, tgt[p])))
                    for p in pos.tolist()
                ]
                got = self.controls(items, wait, on_error, timeout)
                if got is not None and any(isinstance(r, DrapeError) for r in got):
                    raise BatchError(got)
                if out is not None and got is not None:
                    for p, r in zip(pos.tolist(), got, strict=True):
                        out[p] = r
                continue
            step = P.DEFAULT_LIMITS.max_batch_moves
            part_tgt = tgt if len(pos) == n else tgt[pos]
            for s in range(0, len(pos), step):
                mv = P.PinMoves(ids[s : s + step], tokens[s : s + step], idx32, part_tgt[s : s + step])
                got = self._block(mv, [handles[p] for p in pos[s : s + step].tolist()], wait, on_error, timeout, server)
                if out is not None and got is not None:
                    for p, r in zip(pos[s : s + step].tolist(), got, strict=True):
                        out[p] = r
        if out is not None and any(isinstance(r, DrapeError) for r in out):
            raise BatchError(out)  # type: ignore[arg-type]
        return out  # type: ignore[return-value]

    def _block(
        self,
        mv: P.PinMoves,
        handles: list[Target],
        wait: bool,
        on_error: ErrorCallback | None,
        timeout: float | None,
        server: str | None,
    ) -> Outcomes | None:
        """One batch control carrying ``mv`` alone; ``wait``: each move's tick or error."""
        rid = self.session.next_rid()
        payload = P.encode_control_batch(P.ControlBatchRequest(self.session.client_id, [], rid, mv))
        if not wait:
            self.session.send(
                "control_batch",
                payload,
                on_error,
                timeout,
                on_ok=lambda m: self._moves_replied(handles, m, rid, on_error),
                server=server,
            )
            return None
        rep = P.control_batch_reply_from_map(self.session.request("control_batch", payload, timeout, server=server))
        tick = rep.tick if rep.moves_tick is None else rep.moves_tick
        out: Outcomes = [tick] * len(handles)
        for p, err in self._moves_errors(handles, rep, rid):
            out[p] = err
        return out

    def _moves_errors(self, handles: list[Target], rep: P.ControlBatchReply, rid: int) -> list[tuple[int, DrapeError]]:
        if rep.moves_failed is None:
            raise DrapeError(P.ERR_INTERNAL, "the server answered moves without moves_failed (not 1.4)", rid)
        out = []
        for p, code, msg in rep.moves_failed:
            if not 0 <= p < len(handles):
                raise DrapeError(P.ERR_INTERNAL, f"moves_failed names position {p} of {len(handles)}", rid)
            err = P.error_for(code, f"cloth {handles[p].id}: {msg}", rid)
            if isinstance(err, P.NotFound):
                self.lost(handles[p])
            out.append((p, err))
        return out

    def _moves_replied(
        self, handles: list[Target], m: dict[str, Any], rid: int, on_error: ErrorCallback | None
    ) -> None:
        rep = P.control_batch_reply_from_map(m)
        if rep.moves_failed:
            for p, err in self._moves_errors(handles, rep, rid):
                self.session.failed(err, on_error, handles[p].removal_outcome)


__all__ = ["ControlSender", "Target"]
