"""One client's open cloths (:class:`Cloths`): its handles by cloth id, and the lock that guards
them, shared with the bundle receiver (client/bundles.py), which reads the map without it; and
where this client's cloths of a scene live (placement and failover keep a scene on one server)."""

from __future__ import annotations

import threading

from .handle import ClothHandle


class Cloths:
    """The handles of one client's open cloths, by cloth id (changed only under ``lock``)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.by_id: dict[str, ClothHandle] = {}

    def add(self, h: ClothHandle, old_id: str | None = None) -> None:
        """Register ``h`` under its id (call with ``lock`` held); ``old_id``: the id it had before
        a failover, forgotten."""
        if old_id is not None and self.by_id.get(old_id) is h:
            del self.by_id[old_id]
        self.by_id[h.id] = h

    def forget(self, h: ClothHandle) -> None:
        """``h`` closed."""
        with self.lock:
            if self.by_id.get(h.id) is h:
                del self.by_id[h.id]

    def on(self, server: str) -> list[ClothHandle]:
        """The handles of cloths living on ``server``."""
        with self.lock:
            return [h for h in self.by_id.values() if h.server_id == server]

    def scene_server(self, scene: str) -> str | None:
        """The server holding this client's cloths of ``scene`` (open and not being failed over;
        None: it has none): where its next cloth of the scene goes (PROTOCOL.md 5.3)."""
        with self.lock:
            for h in self.by_id.values():
                if h.request is not None and h.request.scene == scene and not h.lost and not h.closed:
                    return h.server_id
        return None

    def all(self) -> list[ClothHandle]:
        with self.lock:
            return list(self.by_id.values())


__all__ = ["Cloths"]
