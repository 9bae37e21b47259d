"""1.5 keyframe queries of one client, at most one per query key in a while.

A predictive stream that cannot decode a state asks the server for a keyframe with a query on the
key its states come on (PROTOCOL.md 9.2). For a bundle that key is the bundle's, and one query
keyframes every stream in it: when a bundle's state is lost, all of its cloths notice at once, and
each asking would send the server one query per cloth (a 64-cloth bundle: 64 queries for one
keyframe; a load of 4096 such cloths flooded the server's request queue). So the limit is kept
per query key, for the whole client, not per cloth.
"""

from __future__ import annotations

import logging
import threading
import time

import zenoh

log = logging.getLogger(__name__)


def _ignore_reply(_reply: zenoh.Reply) -> None:
    """A keyframe query's answer: the keyframe itself comes as the stream's next state."""


class KeyframeQueries:
    """The keyframe queries a client sends, one per key at most every ``min_interval_s``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._asked: dict[str, float] = {}  # query key -> monotonic time of its last query
        self.sent = 0  # queries sent

    def ask(self, session: zenoh.Session, key: str, min_interval_s: float = 0.1) -> bool:
        """Query ``key`` for a keyframe (not waited for) unless it was asked less than
        ``min_interval_s`` ago, by any cloth of this client. Whether a query went out."""
        now = time.monotonic()
        with self._lock:
            if now - self._asked.get(key, -1e18) < min_interval_s:
                return False
            self._asked[key] = now
            self.sent += 1
        try:
            session.get(key, _ignore_reply, timeout=1.0)
        except Exception as e:  # the session closing
            log.debug("keyframe query on %s failed: %s", key, e)
            return False
        return True
