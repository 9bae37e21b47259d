"""Replies to queries: sending them (never raising: the querier may be gone) and building error
replies, each counted by error code in the registry's stats."""

from __future__ import annotations

import logging
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
