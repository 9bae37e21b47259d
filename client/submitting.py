"""Submissions of the Python SDK: the SubmitRequest of a grid or a triangle mesh and the SDK's
friendly options (:func:`submit_request`, its options ``cloth_options``; pure), and the
:class:`Submitter`, which sends one (``submit``) to the server the placement ranks first
(PROTOCOL.md 11.3, the next one on a refusal another server may not give) and registers the new
handle with the client (``place``, also the failover's resubmission) before any state of its
bundle reaches it. A cloth naming a ``scene`` (1.7) without ``server`` goes where the scene is:
the server of this client's cloths of it, else the live server that holds it (another client
founded it there), else the placement's choice (it founds the scene there); whether this client
owns the scene is asked once after its first cloth of it (client/scenes.py).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from . import protocol as P
from .bundles import BundleReceiver
from .connection import Session
from .controls import collider, links_of, mesh_collider, vec3
from .handle import ClothHandle, HandleOwner
from .placement import PLACE_ELSEWHERE, Placement
from .protocol import DrapeError
from .rates import fit_rate
from .registry import Cloths
from .scenes import SceneBook

log = logging.getLogger("drape.client.sdk")

# Options every submit_* method takes, for documentation and for tools wrapping the SDK.
cloth_options = (
    "pinned",
    "links",
    "material",
    "features",
    "gravity",
    "wind",
    "iterations",
    "substeps",
    "chebyshev_rho",
    "colliders",
    "normals",
    "encoding",
    "step",
    "bundle",
    "quality",
    "scene",
    "mesh_collider",
    "mesh_position",
    "mesh_rotation",
    "timeout",
    "queue_size",
    "server",
)


def grid_spec(
    cols: int,
    rows: int,
    width: float = 1.0,
    height: float = 1.0,
    orientation: str = "horizontal",
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> P.GridSpec:
    """A regular grid's spec, checked (columns, rows, orientation, origin) without building it."""
    cols, rows = int(cols), int(rows)
    # the geometry's own checks (columns, rows, orientation, origin) on a grid of at most 1x1
    P.grid_positions(min(cols, 1), min(rows, 1), width, height, orientation, origin)
    return P.GridSpec(
        cols,
        rows,
        float(width),
        float(height),
        orientation,
        tuple(float(v) for v in origin),  # type: ignore[arg-type]
    )


def mesh_spec(vertices: np.ndarray | Sequence, triangles: np.ndarray | Sequence) -> P.MeshSpec:
    """A triangle mesh's spec: vertices (n, 3) metres, triangles (m, 3) vertex indices, checked."""
    v = np.ascontiguousarray(np.asarray(vertices, np.float32).reshape(-1, 3))
    t = np.asarray(triangles, np.int64).reshape(-1, 3)
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError("triangle index out of range")
    return P.MeshSpec(v, t.astype(np.uint32))


def submit_request(
    client: str,
    rid: int,
    *,
    grid: P.GridSpec | None = None,
    mesh: P.MeshSpec | None = None,
    pinned: Iterable[int] = (),
    links: Any = None,
    material: Mapping[str, Any] | Any = None,
    features: Iterable[str] = (),
    gravity: Sequence[float] | None = None,
    wind: Sequence[float] | None = None,
    iterations: int | None = None,
    substeps: int | None = None,
    chebyshev_rho: float | None = None,
    colliders: Sequence[Any] | None = None,
    normals: bool = False,
    encoding: str = "float32",
    step: float | None = None,
    bundle: bool = False,
    quality: str | None = None,
    scene: str | None = None,
    mesh_collider: Any = None,
    mesh_position: Sequence[float] | None = None,
    mesh_rotation: Sequence[float] | None = None,
) -> P.SubmitRequest:
    """The SubmitRequest of ``client`` for a grid or a mesh with the SDK's options (``cloth_options``
    but timeout, queue_size and server, which are the sending's). 1.8: ``mesh_collider``, the
    cloth's own mesh collider (``(vertices, triangles)`` or an object with them, see
    :func:`.controls.mesh_collider`) at ``mesh_position`` and ``mesh_rotation`` (w, x, y, z)."""
    pins = np.asarray(list(pinned), np.int64).reshape(-1)
    n = grid.cols * grid.rows if grid is not None else len(mesh.vertices) if mesh is not None else 0
    bad = pins[(pins < 0) | (pins >= n)]
    if bad.size:
        shape = (grid.cols, grid.rows) if grid is not None else None
        raise ValueError(P.pinned_out_of_range(int(bad[0]), n, shape))
    return P.SubmitRequest(
        client=client,
        grid=grid,
        mesh=mesh,
        pinned=pins.astype(np.uint32),
        links=links_of(links),
        material=P.material_to_map(material) if material is not None else {},
        features=tuple(features),
        gravity=vec3(gravity),
        wind=vec3(wind),
        iterations=iterations,
        substeps=substeps,
        chebyshev_rho=chebyshev_rho,
        colliders=tuple(collider(c) for c in colliders) if colliders is not None else None,
        state=(
            P.StateOptions(bool(normals), encoding, True if bundle else None, step)
            if (normals or encoding != "float32" or bundle or step is not None)
            else None
        ),
        quality=quality,
        rid=rid,
        scene=scene,
        mesh_collider=_mesh_collider(mesh_collider, mesh_position, mesh_rotation),
    )


_mesh_collider = mesh_collider  # the option's name shadows the converter in submit_request


class Submitter:
    """Sends one client's submissions and registers their handles (module docstring). ``owner``:
    the client the new handles belong to; ``queue_size``: their default state queue length."""

    def __init__(
        self,
        owner: HandleOwner,
        session: Session,
        placement: Placement,
        cloths: Cloths,
        bundles: BundleReceiver,
        queue_size: int = 64,
        rate: tuple[int, bool] = (1, False),
        scenes: SceneBook | None = None,
    ) -> None:
        self.owner = owner
        self.scenes = scenes if scenes is not None else SceneBook(session)
        self._scene_locks: dict[str, threading.Lock] = {}  # one scene's first placements, one at a time
        self._locks_lock = threading.Lock()
        self.rate = rate  # 1.8: (the rate new cloths start at, governed by rates.RateGovernor)
        self.session = session
        self.placement = placement
        self.cloths = cloths
        self.bundles = bundles
        self.queue_size = queue_size

    def submit(
        self,
        req: P.SubmitRequest,
        rest_positions: np.ndarray | None = None,
        triangles: np.ndarray | None = None,
        timeout: float | None = None,
        queue_size: int | None = None,
        server: str | None = None,
    ) -> ClothHandle:
        """``req`` as is, to ``server``, else the session's given server, else the live server the
        placement ranks first, a refusal another server may not give trying the next one (see
        DrapeClient.submit); its handle."""

        def make(target: str) -> Callable[[P.SubmitReply], ClothHandle]:
            def handle(rep: P.SubmitReply) -> ClothHandle:
                rest, tris = rest_positions, triangles
                if rest is None and req.grid is not None:  # built once the server took the cloth
                    g = req.grid
                    rest, tris = P.grid_geometry(g.cols, g.rows, g.width, g.height, g.orientation, g.origin)
                # 1.8: the client's rate, or the one below it the server serves (1.7: full rate)
                served = self._served(target)
                if rep.bundle_key is not None:
                    self.bundles.limit(served)
                rate, governed = self.rate
                rate, governed = fit_rate(rate, served), governed and len(served) > 1
                return ClothHandle(
                    self.owner, rep, rest, tris, queue_size or self.queue_size, target, req, rate, governed, served
                )

            return handle

        if server is not None or self.session.server_given:
            target = server or self.session.server_id
            h = self.place(None, req, target, timeout, make(target))
            if req.scene is not None and self.scenes.get(req.scene).owner is None:
                self.scenes.learn_owner(req.scene, target)
            return h
        if req.scene is not None:
            with self._scene_lock(req.scene):
                where = self.cloths.scene_server(req.scene) or self.scenes.locate(
                    req.scene, self.placement.ranked(wait=False)
                )
                h = self.place(None, req, where, timeout, make(where)) if where else self._by_load(req, timeout, make)
                if self.scenes.get(req.scene).owner is None:
                    self.scenes.learn_owner(req.scene, h.server_id)
                return h
        return self._by_load(req, timeout, make)

    def _scene_lock(self, scene: str) -> threading.Lock:
        with self._locks_lock:
            return self._scene_locks.setdefault(scene, threading.Lock())

    def _by_load(
        self, req: P.SubmitRequest, timeout: float | None, make: Callable[[str], Callable[[P.SubmitReply], ClothHandle]]
    ) -> ClothHandle:
        """To the live server the placement ranks first, a refusal another server may not give
        trying the next one."""
        tried: set[str] = set()
        last: DrapeError | None = None
        while True:
            choice = self.placement.choose(tried)
            if choice is None:
                if last is not None:  # every live server refused: the last refusal
                    raise last
                choice = self.session.server_id  # none live yet: wait for one (or raise unavailable)
            tried.add(choice)
            try:
                return self.place(None, req, choice, timeout, make(choice))
            except DrapeError as e:
                if e.code not in PLACE_ELSEWHERE:
                    raise
                log.info("server %s refused a cloth (%s): trying the next", choice, e.code)
                last = e

    def _served(self, server: str) -> tuple[int, ...]:
        """1.8: the rates ``server`` (its info asked already, by _check_size) serves."""
        info = self.session.known_info(server)
        return P.served_rates(None if info is None else info.version)

    def _check_size(self, req: P.SubmitRequest, server: str, timeout: float | None = None) -> None:
        """Refuse a cloth larger than ``server`` takes (its ``max_vertices_per_cloth``, from the
        info asked once per server) before sending it: ``too_large``, the server's own words."""
        try:
            limit = self.session.info_of(server, timeout).max_vertices
        except DrapeError:  # unanswered: the request itself will tell
            return
        n = req.n_vertices
        if limit is not None and n > limit:
            grid = (req.grid.cols, req.grid.rows) if req.grid is not None else None
            raise P.ProtocolError(P.ERR_TOO_LARGE, P.too_many_vertices(n, limit, grid), req.rid)

    def place(
        self,
        h: ClothHandle | None,
        req: P.SubmitRequest,
        server: str,
        timeout: float | None = None,
        make: Callable[[P.SubmitReply], ClothHandle] | None = None,
    ) -> ClothHandle:
        """Submit ``req`` to ``server``: a new handle (``make``), or, in a failover, the cloth of
        the existing handle ``h`` continued under the new reply's id."""
        bundled = bool(req.state is not None and req.state.bundle)
        if bundled:
            self.bundles.subscribe(self.session.zenoh)
            self.bundles.submitting()
        self._check_size(req, server, timeout)  # a cloth the server would refuse is not sent
        ticket = self.placement.placing(server, req.n_vertices)  # counted there until its next stats
        try:
            try:
                rep = P.submit_reply_from_map(self.session.request("submit", P.encode_submit(req), timeout, server))
            except BaseException:
                self.placement.placed(ticket, False)
                raise
            self.placement.placed(ticket, True)
            if bundled and rep.bundle_key is None:
                log.info("server %s does not bundle states (protocol 1.0): cloth %s on its own key", server, rep.cloth)
            old_id = None
            if h is None:
                assert make is not None
                h = make(rep)
            else:
                old_id = h.id
                served = self._served(server)  # a failover onto an older server: fewer rates from now on
                if rep.bundle_key is not None:
                    self.bundles.limit(served)
            with h.deliver_lock:  # states of the bundle reach the handle only after these
                if old_id is not None:
                    h.rebind(rep, server, served)
                with self.cloths.lock:
                    self.cloths.add(h, old_id)
                    early = self.bundles.early_states(h.id) if bundled else []
                for st in early:
                    h.deliver(st)
            return h
        finally:
            if bundled:
                self.bundles.submitted()


__all__ = ["Submitter", "cloth_options", "grid_spec", "mesh_spec", "submit_request"]
