"""The registry: which cloths exist, whose they are, quotas and the service's counters.

Lock-protected; used by the Zenoh callbacks (reserve, ownership), the cook worker and the tick
thread. It does NOT hold cloth parameters: the World is their one owner (``world.cloths[h]
.params``, tick thread only). A record carries what the service needs around the World: ids,
keys, token, the fabric (immutable, for validating pin indices), the handle once added, the
state encoding and the quality presets asked for and in force. Scenes (protocol 1.7,
PROTOCOL.md 5.3): each one's owner (the client of its first cloth), members and cloths; a scene
ends with its last cloth.
"""

from __future__ import annotations

import hmac
import logging
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field

from drape.client import protocol as P

from ..sim.fabric import Fabric
from .config import ServerConfig

log = logging.getLogger(__name__)

TOMBSTONES = 1024  # reasons kept for cloths the server removed on its own


@dataclass(eq=False)
class ClothRecord:
    """One cloth as the service knows it. Created (reserved) when a submission is accepted;
    ``handle`` is set by the tick thread once the cloth is in the World."""

    id: str
    client: str
    token: str
    key: str
    n_vertices: int
    encoding: str = "float32"
    step: float = P.STEP_DEFAULT  # 1.5, predictive: the grid step in metres
    fabric: Fabric | None = None
    handle: int | None = None
    removed: bool = False
    bundle_key: str | None = None  # published inside this client's bundle on this key (1.1), not on ``key``
    quality_wanted: str | None = None  # the preset the client asked for (1.1)
    quality: str | None = None  # the preset in force: lower than wanted while the server is overloaded
    scene: str | None = None  # 1.7: the scene it collides in
    priced: object | None = None  # what admission priced it at (requests/admission.py: Priced; request thread)


@dataclass(eq=False)
class SceneRecord:
    """A scene (1.7): its owner, who else may put cloths in it (``*``: anyone), its cloths."""

    owner: str
    members: tuple[str, ...] = ()
    cloths: set[str] = field(default_factory=set)

    def admits(self, client: str) -> bool:
        return client == self.owner or client in self.members or P.SCENE_ANYONE in self.members


class Registry:
    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.lock = threading.Lock()
        self.generation = 0  # bumped whenever a cloth goes: caches of "these records are live" check it
        self.cloths: dict[str, ClothRecord] = {}
        self.by_client: dict[str, set[str]] = {}
        self.vertices = 0
        self.alive: set[str] = set()
        self.gone_since: dict[str, float] = {}
        self._new_tokens = float(config.new_clients_burst)  # the new-client token bucket
        self._new_at = time.monotonic()
        self.requests: Counter[str] = Counter()
        self.errors: Counter[str] = Counter()
        self.counters: Counter[str] = Counter()
        self.tombstones: OrderedDict[str, str] = OrderedDict()  # cloths the server removed itself: why
        self.scenes: dict[str, SceneRecord] = {}  # 1.7: by scene id

    def bury(self, cloth: str, reason: str) -> None:
        """Remember why the server removed ``cloth`` (its owner's next request is told)."""
        with self.lock:
            self.tombstones[cloth] = reason
            while len(self.tombstones) > TOMBSTONES:
                self.tombstones.popitem(last=False)

    # --- counters ----------------------------------------------------------------------------
    def count(self, name: str, n: int = 1) -> None:
        with self.lock:
            self.counters[name] += n

    def count_many(self, **names: int) -> None:
        with self.lock:
            for k, n in names.items():
                self.counters[k] += n

    def error(self, code: str, n: int = 1) -> None:
        with self.lock:
            self.errors[code] += n

    # --- cloths ------------------------------------------------------------------------------
    def reserve(self, rec: ClothRecord, rid: int) -> None:
        """Take room for a submitted cloth, or raise LimitExceeded (or Overloaded: a new client over the bucket)."""
        cfg = self.config
        with self.lock:
            mine = self.by_client.get(rec.client, set())
            if len(self.cloths) >= cfg.max_cloths:
                raise P.LimitExceeded(P.ERR_LIMIT_EXCEEDED, f"server is full: {cfg.max_cloths} cloths", rid)
            if len(mine) >= cfg.max_cloths_per_client:
                raise P.LimitExceeded(
                    P.ERR_LIMIT_EXCEEDED,
                    f"client {rec.client!r} already has {len(mine)} cloths (limit {cfg.max_cloths_per_client})",
                    rid,
                )
            if self.vertices + rec.n_vertices > cfg.max_total_vertices:
                raise P.LimitExceeded(
                    P.ERR_LIMIT_EXCEEDED,
                    f"server vertex budget exhausted: {self.vertices} + {rec.n_vertices} > {cfg.max_total_vertices}",
                    rid,
                )
            scene = self.scenes.get(rec.scene) if rec.scene is not None else None
            if scene is not None and not scene.admits(rec.client):
                raise P.Forbidden(
                    P.ERR_FORBIDDEN,
                    f"scene {rec.scene!r} is client {scene.owner!r}'s, who has not made client {rec.client!r} "
                    "a member (PROTOCOL.md 5.3)",
                    rid,
                )
            if not mine and not self._take_new_client_token():
                raise P.Overloaded(
                    P.ERR_OVERLOADED,
                    f"too many new clients at once (more than {cfg.new_clients_per_s:g} a second after "
                    f"{cfg.new_clients_burst}): retry later",
                    rid,
                )
            if rec.scene is not None:
                self.scenes.setdefault(rec.scene, SceneRecord(rec.client)).cloths.add(rec.id)
            self.cloths[rec.id] = rec
            self.by_client.setdefault(rec.client, set()).add(rec.id)
            self.vertices += rec.n_vertices
            if rec.client not in self.alive:
                self.gone_since.setdefault(rec.client, time.monotonic())

    def _take_new_client_token(self) -> bool:
        """A token of the new-client bucket (under the lock; taken last, once every other limit
        passed, so a refused submit spends none): client ids are free to mint unless
        the router binds them to logins (identity = "keys"), so ids the server has no cloth of get
        ``new_clients_per_s`` a second after ``new_clients_burst`` at once, and one flood of ids
        cannot fill the server's cloths (PROTOCOL.md, "overloaded")."""
        now = time.monotonic()
        cfg = self.config
        refill = (now - self._new_at) * cfg.new_clients_per_s
        self._new_tokens = min(float(cfg.new_clients_burst), self._new_tokens + refill)
        self._new_at = now
        if self._new_tokens < 1.0:
            return False
        self._new_tokens -= 1.0
        return True

    def unreserve(self, rec: ClothRecord) -> None:
        with self.lock:
            if self.cloths.pop(rec.id, None) is not None:
                self.vertices -= rec.n_vertices
                mine = self.by_client.get(rec.client)
                if mine is not None:
                    mine.discard(rec.id)
                    if not mine:
                        del self.by_client[rec.client]
                scene = self.scenes.get(rec.scene) if rec.scene is not None else None
                if scene is not None:
                    scene.cloths.discard(rec.id)
                    if not scene.cloths:  # a scene ends with its last cloth
                        del self.scenes[rec.scene]  # type: ignore[arg-type]
            rec.removed = True
            self.generation += 1

    def get(self, cloth: str) -> ClothRecord | None:
        with self.lock:
            return self.cloths.get(cloth)

    def owned(self, cloth: str, token: str, rid: int) -> ClothRecord:
        """The record of ``cloth`` if ``token`` owns it; raises NotFound or Forbidden."""
        with self.lock:
            rec = self.cloths.get(cloth)
            reason = self.tombstones.get(cloth) if rec is None else None
        if reason is not None:
            raise P.NotFound(P.ERR_NOT_FOUND, f"no cloth {cloth!r} on server {self.config.server_id!r}: {reason}", rid)
        if rec is None or rec.removed or rec.fabric is None:
            raise P.NotFound(P.ERR_NOT_FOUND, f"no cloth {cloth!r} on server {self.config.server_id!r}", rid)
        if not hmac.compare_digest(rec.token, token):
            raise P.Forbidden(P.ERR_FORBIDDEN, f"the token does not own cloth {cloth!r}", rid)
        return rec

    def owned_scene(self, scene: str, client: str, rid: int) -> SceneRecord:
        """The record of ``scene`` if ``client`` owns it; raises NotFound or Forbidden (1.7)."""
        with self.lock:
            rec = self.scenes.get(scene)
        if rec is None:
            raise P.NotFound(P.ERR_NOT_FOUND, f"no scene {scene!r} on server {self.config.server_id!r}", rid)
        if rec.owner != client:
            raise P.Forbidden(
                P.ERR_FORBIDDEN, f"scene {scene!r} is client {rec.owner!r}'s, not {client!r}'s (PROTOCOL.md 5.3)", rid
            )
        return rec

    # --- clients -----------------------------------------------------------------------------
    def client_alive(self, client: str, alive: bool) -> None:
        with self.lock:
            if alive:
                self.alive.add(client)
                self.gone_since.pop(client, None)
            else:
                self.alive.discard(client)
                if client in self.by_client:
                    self.gone_since[client] = time.monotonic()

    def expired(self, now: float) -> tuple[list[str], list[ClothRecord]]:
        """Clients gone for longer than the grace period, and their cloths (forgotten here)."""
        if not self.gone_since:
            return [], []
        grace = self.config.grace_period
        with self.lock:
            expired = [c for c, t in self.gone_since.items() if now - t >= grace]
            victims: list[ClothRecord] = []
            for c in expired:
                del self.gone_since[c]
                victims.extend(self.cloths[i] for i in self.by_client.get(c, ()))
        return expired, victims

    def counts(self) -> dict[str, int]:
        with self.lock:
            return {"cloths": len(self.cloths), "clients": len(self.by_client), "vertices": self.vertices}
