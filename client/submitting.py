"""DrapeClient's submissions (a mixin of :class:`drape.client.sdk.DrapeClient`): a cloth built
from a grid, a triangle mesh or an OBJ file (``submit_grid``, ``submit_mesh``, ``submit_obj``,
their options ``cloth_options``), a SubmitRequest sent as is (``submit``) to the server the
placement ranks first (PROTOCOL.md 11.3, the next one on a refusal another server may not give),
and the new handle registered with the client (``_place``, also the failover's resubmission)
before any state of its bundle reaches it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import protocol as P
from .controls import _collider, _links, _vec3
from .handle import ClothHandle
from .placement import PLACE_ELSEWHERE
from .protocol import DrapeError

if TYPE_CHECKING:
    from .sdk import DrapeClient

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
    "timeout",
    "queue_size",
    "server",
)


class SubmittingMixin:
    """DrapeClient's submission methods (its session, servers and requests are in sdk.py). Their
    ``self`` is the DrapeClient they are mixed into: mypy wants a mixin's self type to be a
    supertype of the mixin, hence each ``type: ignore[misc]``."""

    def submit(  # type: ignore[misc]
        self: DrapeClient,
        req: P.SubmitRequest,
        rest_positions: np.ndarray | None = None,
        triangles: np.ndarray | None = None,
        timeout: float | None = None,
        queue_size: int | None = None,
        server: str | None = None,
    ) -> ClothHandle:
        """Send a SubmitRequest as is and subscribe to the new cloth's state (with
        ``req.state.bundle``: to this client's bundle, once for all its bundled cloths; a 1.0
        server ignores the option and the handle subscribes to the cloth's own key). A grid's
        ``rest_positions`` and ``triangles`` default to its geometry, built once it is accepted.

        To ``server``, else the client's ``server_id`` when one was given, else the live server
        the placement ranks first (PROTOCOL.md 11.3); a refusal another server may not give
        (``overloaded``, ``busy``, ``limit_exceeded``, no reply) tries the next one, and the last
        refusal is raised when every live server refused."""

        def make(target: str) -> Callable[[P.SubmitReply], ClothHandle]:
            def handle(rep: P.SubmitReply) -> ClothHandle:
                rest, tris = rest_positions, triangles
                if rest is None and req.grid is not None:  # built once the server took the cloth
                    g = req.grid
                    rest, tris = P.grid_geometry(g.cols, g.rows, g.width, g.height, g.orientation, g.origin)
                return ClothHandle(self, rep, rest, tris, queue_size or self.queue_size, target, req)

            return handle

        if server is not None or self._server_given:
            target = server or self.server_id
            return self._place(None, req, target, timeout, make(target))
        tried: set[str] = set()
        last: DrapeError | None = None
        while True:
            choice = self.placement.choose(tried)
            if choice is None:
                if last is not None:  # every live server refused: the last refusal
                    raise last
                choice = self.server_id  # none live yet: wait for one (or raise unavailable)
            tried.add(choice)
            try:
                return self._place(None, req, choice, timeout, make(choice))
            except DrapeError as e:
                if e.code not in PLACE_ELSEWHERE:
                    raise
                log.info("server %s refused a cloth (%s): trying the next", choice, e.code)
                last = e

    def _place(  # type: ignore[misc]
        self: DrapeClient,
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
            self._ensure_bundle_subscriber()
            self.bundles.submitting()
        self._check_size(req, server, timeout)  # a cloth the server would refuse is not sent
        ticket = self.placement.placing(server, req.n_vertices)  # counted there until its next stats
        try:
            try:
                rep = P.submit_reply_from_map(self.request("submit", P.encode_submit(req), timeout, server=server))
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
            with h._deliver_lock:  # states of the bundle reach the handle only after these
                if old_id is not None:
                    h._rebind(rep, server)
                with self._lock:
                    if old_id is not None and self._handles.get(old_id) is h:
                        del self._handles[old_id]
                    self._handles[h.id] = h
                    early = self.bundles.early_states(h.id) if bundled else []
                for st in early:
                    h._deliver(st)
            return h
        finally:
            if bundled:
                self.bundles.submitted()

    def submit_grid(  # type: ignore[misc]
        self: DrapeClient,
        cols: int,
        rows: int,
        width: float = 1.0,
        height: float = 1.0,
        *,
        orientation: str = "horizontal",
        origin: Sequence[float] = (0.0, 0.0, 0.0),
        **options: Any,
    ) -> ClothHandle:
        """A regular grid cloth; vertex (row r, column c) is r * cols + c. ``options``: see
        ``cloth_options``. Its geometry (the handle's ``rest_positions`` and ``triangles``) is
        built once the server accepted it: a grid too large is refused before anything is built."""
        cols, rows = int(cols), int(rows)
        # the geometry's own checks (columns, rows, orientation, origin) on a grid of at most 1x1
        P.grid_positions(min(cols, 1), min(rows, 1), width, height, orientation, origin)
        grid = P.GridSpec(
            cols,
            rows,
            float(width),
            float(height),
            orientation,
            tuple(float(v) for v in origin),  # type: ignore[arg-type]
        )
        return self._submit(grid=grid, **options)

    def submit_mesh(  # type: ignore[misc]
        self: DrapeClient, vertices: np.ndarray | Sequence, triangles: np.ndarray | Sequence, **options: Any
    ) -> ClothHandle:
        """A triangle mesh cloth: vertices (n, 3) metres, triangles (m, 3) vertex indices."""
        v = np.ascontiguousarray(np.asarray(vertices, np.float32).reshape(-1, 3))
        t = np.asarray(triangles, np.int64).reshape(-1, 3)
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError("triangle index out of range")
        mesh = P.MeshSpec(v, t.astype(np.uint32))
        return self._submit(mesh=mesh, rest=v, tris=mesh.triangles, **options)

    def submit_obj(self: DrapeClient, path: str | Path, **options: Any) -> ClothHandle:  # type: ignore[misc]
        """A cloth from a Wavefront OBJ file (faces fan-triangulated)."""
        v, t = P.parse_obj(Path(path).read_text())
        return self.submit_mesh(v, t, **options)

    def _submit(  # type: ignore[misc]
        self: DrapeClient,
        *,
        rest: np.ndarray | None = None,
        tris: np.ndarray | None = None,
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
        timeout: float | None = None,
        queue_size: int | None = None,
        server: str | None = None,
    ) -> ClothHandle:
        pins = np.asarray(list(pinned), np.int64).reshape(-1)
        n = grid.cols * grid.rows if grid is not None else len(mesh.vertices) if mesh is not None else 0
        bad = pins[(pins < 0) | (pins >= n)]
        if bad.size:
            shape = (grid.cols, grid.rows) if grid is not None else None
            raise ValueError(P.pinned_out_of_range(int(bad[0]), n, shape))
        req = P.SubmitRequest(
            client=self.client_id,
            grid=grid,
            mesh=mesh,
            pinned=pins.astype(np.uint32),
            links=_links(links),
            material=P.material_to_map(material) if material is not None else {},
            features=tuple(features),
            gravity=_vec3(gravity),
            wind=_vec3(wind),
            iterations=iterations,
            substeps=substeps,
            chebyshev_rho=chebyshev_rho,
            colliders=tuple(_collider(c) for c in colliders) if colliders is not None else None,
            state=(
                P.StateOptions(bool(normals), encoding, True if bundle else None, step)
                if (normals or encoding != "float32" or bundle or step is not None)
                else None
            ),
            quality=quality,
            rid=self._next_rid(),
        )
        return self.submit(req, rest, tris, timeout, queue_size, server)
