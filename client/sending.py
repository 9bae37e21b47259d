"""How a client's controls reach the servers (the SDK's one sending path for controls): grouped
by the server each cloth lives on; pins-only items sharing one index list as one 1.4 ``moves``
block; the rest as batch control requests of at most the server's ``max_batch_items`` (1.1), or
one control each to a 1.0 server; replies folded back into one outcome per item (its first tick
or its DrapeError), ``not_found`` reported to the failover."""

from __future__ import annotations

import logging
from functools import partial
from typing import TYPE_CHECKING, Any

from . import protocol as P
from .controls import ErrorCallback, _item_outcomes
from .protocol import DrapeError

if TYPE_CHECKING:
    from .handle import ClothHandle
    from .sdk import DrapeClient

log = logging.getLogger(__name__)


def send_controls(
    client: DrapeClient,
    items: list[tuple[ClothHandle, P.ControlRequest]],
    wait: bool,
    on_error: ErrorCallback | None,
    timeout: float | None,
) -> list[int | DrapeError] | None:
    """Send ``items`` (handle, control) of ``client``'s cloths. ``wait``: returns each item's
    first tick or DrapeError, in order; otherwise None (errors go to ``on_error``)."""
    if not items:
        return [] if wait else None
    servers = {h.server_id for h, _ in items}
    if len(servers) > 1:  # after a failover a client's cloths may live on several servers
        order: dict[str, list[int]] = {}
        for i, (h, _) in enumerate(items):
            order.setdefault(h.server_id, []).append(i)
        merged: list[int | DrapeError | None] = [None] * len(items)
        for idx in order.values():
            part = send_controls(client, [items[i] for i in idx], wait, on_error, timeout)
            for i, r in zip(idx, part or (), strict=False):
                merged[i] = r
        return merged if wait else None  # type: ignore[return-value]
    server = items[0][0].server_id or None
    client._require_features_delta(r for _, r in items)
    if len(items) > 1:  # 1.4: pins-only items sharing one index list go as one moves block
        from .moves import moves_of

        moves = moves_of(client)
        pos, block = moves.split(items)
        if block is not None and client._server_batch_limit() and moves.speaks_moves(server):
            moved = moves.send_block(block, [items[i][0] for i in pos], wait, on_error, timeout, server)
            rest = set(pos)
            others = send_controls(client, [it for i, it in enumerate(items) if i not in rest], wait, on_error, timeout)
            if not wait:
                return None
            it_moved, it_others = iter(moved or ()), iter(others or ())
            return [next(it_moved) if i in rest else next(it_others) for i in range(len(items))]
    limit = client._server_batch_limit()
    if not limit:  # a 1.0 server: one control per item
        log.debug("server speaks %s: batch sent as %d controls", client._server_version, len(items))
        out: list[int | DrapeError] = []
        for h, req in items:
            if wait:
                try:
                    out.append(
                        P.tick_reply_from_map(client.request("control", P.encode_control(req), timeout, server=server))
                    )
                except DrapeError as e:
                    if isinstance(e, P.NotFound):
                        client._cloth_not_found(h)
                    out.append(e)
            else:
                client.send(
                    "control",
                    P.encode_control(req),
                    client._watch_not_found(h, on_error),
                    timeout,
                    server=server,
                    handle=h,
                )
        return out if wait else None
    results: list[int | DrapeError] = []
    for start in range(0, len(items), limit):
        chunk = items[start : start + limit]
        rid = client._next_rid()
        payload = P.encode_control_batch(P.ControlBatchRequest(client.client_id, [r for _, r in chunk], rid))
        if wait:
            rep = P.control_batch_reply_from_map(client.request("control_batch", payload, timeout, server=server))
            outcomes = _item_outcomes(chunk, rep, rid)
            for (h, _), r in zip(chunk, outcomes, strict=True):
                if isinstance(r, P.NotFound):
                    client._cloth_not_found(h)
            results.extend(outcomes)
        else:
            client.send(
                "control_batch",
                payload,
                on_error,
                timeout,
                on_ok=partial(_batch_replied, client, chunk, rid=rid, on_error=on_error),
                server=server,
            )
    return results if wait else None


def _batch_replied(
    client: DrapeClient,
    chunk: list[tuple[ClothHandle, P.ControlRequest]],
    m: dict[str, Any],
    rid: int,
    on_error: ErrorCallback | None,
) -> None:
    rep = P.control_batch_reply_from_map(m)
    if rep.failed:
        for (h, _), r in zip(chunk, _item_outcomes(chunk, rep, rid), strict=True):
            if isinstance(r, DrapeError):
                if isinstance(r, P.NotFound):
                    client._cloth_not_found(h)
                client._send_failed(r, on_error, h)
