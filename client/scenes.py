"""What one client knows of its scenes (protocol 1.7, PROTOCOL.md 5.3): whether it owns each one
(founded it: its scene probe's ``owner``, or a ``scene`` request it sent that succeeded), the last
state its ``scene`` requests set (members, colliders, mesh collider: every field the latest that
was sent, so a failover can found the scene again as it was), and where a scene lives among the
live servers (:meth:`SceneBook.locate`: a probe answered ``ok`` or ``forbidden`` means the server
holds it, ``not_found`` that it does not).

Placement (client/submitting.py) and failover (client/failover.py) use it to keep a scene's cloths
on one server and to found a scene again as its owner, with the owner's cloths first.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from . import protocol as P
from .connection import Session
from .protocol import DrapeError

log = logging.getLogger(__name__)

SCENES_SINCE = (1, 7)  # the protocol version that has scenes
PROBE_TIMEOUT = 2.0  # s, at most, for one scene probe


@dataclass
class SceneState:
    """One scene as this client last set it: ``owner`` True (this client founded it), False (it
    is a member), None (not known yet); the fields its scene requests set, None where never sent;
    the mesh collider as a whole mesh at its last pose (``mesh_removed``: the last change removed it)."""

    owner: bool | None = None
    colliders: tuple[P.Collider, ...] | None = None
    members: tuple[str, ...] | None = None
    mesh: P.MeshCollider | None = None
    mesh_removed: bool = False

    def sent(self, req: P.SceneRequest) -> None:
        """A scene request ``req`` succeeded: its fields are in force now."""
        if req.colliders is not None:
            self.colliders = req.colliders
        if req.members is not None:
            self.members = req.members
        mc = req.mesh_collider
        if mc is None:
            return
        if mc.remove:
            self.mesh, self.mesh_removed = None, True
        elif mc.triangles is not None:  # a new mesh at its pose
            self.mesh, self.mesh_removed = mc, False
        elif self.mesh is not None:  # a re-pose (new vertices) and / or a rigid move of the current one
            verts = mc.vertices if mc.vertices is not None else self.mesh.vertices
            self.mesh = P.MeshCollider(verts, self.mesh.triangles, mc.position, mc.rotation)

    def replay(self, client: str, scene: str, rid: int) -> P.SceneRequest | None:
        """The one request that sets all of it again on a server where the scene was just founded
        (None: nothing was ever set)."""
        if self.colliders is None and self.members is None and self.mesh is None:
            return None
        return P.SceneRequest(client, scene, self.colliders, self.members, rid, self.mesh)


class SceneBook:
    """This client's scenes (module docstring), by scene id; thread-safe."""

    def __init__(self, session: Session) -> None:
        self.session = session
        self._lock = threading.Lock()
        self._scenes: dict[str, SceneState] = {}

    def get(self, scene: str) -> SceneState:
        with self._lock:
            return self._scenes.setdefault(scene, SceneState())

    def owns(self, scene: str) -> bool:
        """Whether this client is known to own ``scene`` (founded it)."""
        with self._lock:
            st = self._scenes.get(scene)
            return bool(st is not None and st.owner)

    def sent(self, req: P.SceneRequest, reply: P.SceneReply) -> None:
        """``req`` was answered ``reply``: remembered for a failover, and who owns the scene."""
        with self._lock:
            st = self._scenes.setdefault(req.scene, SceneState())
            st.sent(req)
            st.owner = reply.owner == self.session.client_id

    def _speaks_scenes(self, server: str) -> bool:
        try:
            return self.session.info_of(server, PROBE_TIMEOUT).version >= SCENES_SINCE
        except DrapeError:
            return False

    def probe(self, scene: str, server: str) -> P.SceneReply | bool | None:
        """Ask ``server`` about ``scene`` with an empty scene request: the reply (this client owns
        it there), True (it exists there, another client's: ``forbidden``), False (not there, or the
        server has no scenes), None (no answer)."""
        if not self._speaks_scenes(server):
            return False
        req = P.SceneRequest(self.session.client_id, scene, rid=self.session.next_rid())
        try:
            rep = self.session.request("scene", P.encode_scene(req), PROBE_TIMEOUT, server)
        except P.Forbidden:
            return True
        except P.NotFound:
            return False
        except DrapeError as e:
            log.debug("scene probe of %s on %s: %s", scene, server, e)
            return None
        return P.scene_reply_from_map(rep)

    def learn_owner(self, scene: str, server: str) -> None:
        """After this client's first cloth of ``scene`` went to ``server``: ask who owns it there."""
        got = self.probe(scene, server)
        if got is None or got is False:
            return
        with self._lock:
            self._scenes.setdefault(scene, SceneState()).owner = not isinstance(got, bool) and (
                got.owner == self.session.client_id
            )

    def locate(self, scene: str, servers: list[str]) -> str | None:
        """The first of ``servers`` that holds ``scene`` (None: none does)."""
        for s in servers:
            got = self.probe(scene, s)
            if got is not None and got is not False:
                return s
        return None


__all__ = ["SCENES_SINCE", "SceneBook", "SceneState"]
