"""Replies to queries: sending them (never raising: the querier may be gone) and building error
replies, each counted by error code in the registry's stats."""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from drape.client import protocol as P

from .registry import Registry

log = logging.getLogger(__name__)


@dataclass(eq=False)
class Reply:
    """A reply to send; ``payload`` may be a function making it, so that the tick thread only
    builds the reply and the publisher thread encodes it."""

    query: zenoh.Query
    payload: bytes | Callable[[], bytes]
    error: bool = False


def send(reply: Reply) -> None:
    """Answer a query and let it go."""
    try:
        payload = reply.payload() if callable(reply.payload) else reply.payload
        if reply.error:
            reply.query.reply_err(payload)
        else:
            reply.query.reply(reply.query.key_expr, payload)
    except Exception as e:
        log.debug("reply failed: %s", e)
    finally:
        try:
            reply.query.drop()
        except Exception:
            pass


class Replier:
    """Sends replies on a thread of its own, in the order they were handed over, so that the
    publisher never waits for a querier's link: zenoh's ``Query.reply``/``drop`` block until the
    transport takes the reply (on the H100 at 256 cloths the publisher spent 88-97 % of its time
    there, and the frames it could not publish meanwhile were dropped). Bounded: past
    ``capacity`` waiting replies, ``put`` waits (the publisher slows down rather than memory
    growing)."""

    def __init__(self, name: str, capacity: int = 65536) -> None:
        self._queue: queue.Queue[Reply | None] = queue.Queue(capacity)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, reply: Reply) -> None:
        self._queue.put(reply)

    def _run(self) -> None:
        while (reply := self._queue.get()) is not None:
            send(reply)

    def close(self, timeout: float = 5.0) -> None:
        """Send what is queued, then stop."""
        self._queue.put(None)
        self._thread.join(timeout)


def undeclare(obj: Any) -> None:
    try:
        obj.undeclare()
    except Exception as e:
        log.debug("undeclare failed: %s", e)


class Replies:
    """Error replies, counted by code."""

    def __init__(self, registry: Registry) -> None:
        self.registry = registry

    def error(self, query: zenoh.Query, code: str, message: str, rid: int | None = 0) -> Reply:
        self.registry.error(code)
        log.debug("request %s refused: [%s] %s", query.key_expr, code, message)
        return Reply(query, P.encode_error(code, message, rid or 0), True)

    def send_error(self, query: zenoh.Query, code: str, message: str, rid: int | None = 0) -> None:
        send(self.error(query, code, message, rid))
