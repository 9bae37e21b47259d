"""Keyframe queries (protocol 1.5, PROTOCOL.md 9.2): a subscriber that lacks a predictive
stream's last states (it joined late, or lost one) sends a Zenoh query, without payload, on the
key it subscribes to: a cloth's state key (``{ns}/cloth/{cloth}/state``, or the 1.4
client-scoped ``{ns}/client/{client}/cloth/{cloth}/state``) or a client's bundle key
(``{ns}/client/{client}/states``). The next state of each predictive stream published there is
intra-coded, for every subscriber at once (one stream for all: the server keeps no state per
subscriber), and the query is answered ``{"v": [1, 5], "tick": T, "cloths": k}``: T the
earliest tick that keyframe can carry, k the predictive cloths it covers. A server answers only
for keys of its own cloths; requests within a few ticks of a stream's last keyframe are served
by the next one allowed (``PredictiveStreams.MIN_REQUESTED_GAP``). 1.8: a query on a decimated
key (``{key}/every/{k}``) asks for a keyframe of that rate's streams only (their own, rates.py).

The callbacks run on Zenoh's threads and do no more than look the key up and mark the streams."""

from __future__ import annotations

import logging
from collections.abc import Callable

import msgpack
import zenoh

from drape.client import protocol as P

from ..registry import Registry
from .publisher import Publisher

log = logging.getLogger(__name__)


class KeyframeQueries:
    def __init__(self, keys: P.Keys, registry: Registry, publisher: Publisher) -> None:
        self.keys, self.registry, self.publisher = keys, registry, publisher

    def endpoints(self) -> list[tuple[str, Callable[[zenoh.Query], None]]]:
        """(key expression, callback) of the keyframe queryables: every state and bundle key."""
        k = self.keys
        full = (k.state("*"), k.client_state("*", "*"), k.bundle("*"))
        return [(key, self.on_query) for key in (*full, *(k.every(f) for f in full))]

    def cloths_on(self, key: str) -> list[str]:
        """The predictive cloths of this server published on ``key``."""
        reg = self.registry
        with reg.lock:
            recs = list(reg.cloths.values())
        return [
            r.id
            for r in recs
            if not r.removed and r.encoding == "predictive" and (r.bundle_key == key if r.bundle_key else r.key == key)
        ]

    def on_query(self, query: zenoh.Query) -> None:
        try:
            key = str(query.key_expr)
            base, every = P.split_every(key)
            cloths = self.cloths_on(base)
            if not cloths:
                return  # not this server's, or nothing predictive there: another server may answer
            tick = self.publisher.request_keyframes(cloths, every)
            self.registry.count("keyframe_queries")
            query.reply(key, msgpack.packb({"v": list(P.PROTOCOL_VERSION), "tick": tick, "cloths": len(cloths)}))
        except Exception:
            log.exception("keyframe query on %s failed", query.key_expr)
