"""The cook worker: turns accepted submissions into what the tick thread adds, off the tick
path. For each submission: the fabric (from the one fabric cache, :class:`.fabrics.FabricStore`,
cooked when new), the cloth parameters and colliders, and the kernels the cloth needs, built now
(``World.prepare``) so that the first cloth with a new feature combination does not compile on
the tick path. With ``build_in_child = "always"`` the first cloth of each feature combination is
first built and run by a child process (:class:`.buildhelper.BuildHelper`), so that this process
loads its kernels from the driver's disk cache: no compiler high-water mark here, no first-launch
JIT on the tick (``"start"`` does that for every combination once before ``drape serve`` starts
serving). About once a second the same thread gives memory back
(:class:`..process.memory.MemoryKeeper`: programs of feature combinations no cloth has used for
``program_idle_s`` released, the heap trimmed).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

import numpy as np

from drape.client import protocol as P

from ...sim.fabric import Fabric
from ...sim.params import ClothParams, LinkOptions
from ...sim.world import World
from ..commands import Add, Intake, Prepare
from ..config import ServerConfig
from ..process.memory import PERIOD_S, MemoryKeeper
from ..registry import Registry
from ..replies import Replies, send
from ..worldparams import pack, params_from_submit, with_preset
from .buildhelper import COOK_IN_CHILD_VERTICES, BuildHelper, BuildMemoryExceeded, cook_in_child
from .fabrics import FabricStore, cook_fabric

log = logging.getLogger(__name__)


def warmed_keys(world: World) -> set:
    """The kernel groups (``World.build_key``) this process's warm-up ran: the default set's small
    cloth. (The start-up child's sets are not assumed: it may not have finished, e.g. on a cold
    cache; the helper then runs each new group's first cloth, as it did per new feature set.)"""
    from ...sim.fabric import cook_grid

    return {world.build_key(cook_grid(8, 8, pinned=[0, 7]), ClothParams())}


class CookWorker:
    """The cook thread: ``queue`` holds (record, request, query) of accepted submissions."""

    def __init__(
        self,
        config: ServerConfig,
        registry: Registry,
        replies: Replies,
        intake: Intake,
        fabrics: FabricStore,
        world: Callable[[], World | None],
        stopping: Callable[[], bool],
    ) -> None:
        self.config, self.registry, self.replies, self.intake = config, registry, replies, intake
        self.queue: queue.Queue = queue.Queue(config.max_pending_requests)
        self.fabrics = fabrics
        self._world, self._stopping = world, stopping
        self._asked: set = set()  # feature keys whose kernels were asked for (controls)
        self._asked_lock = threading.Lock()
        self.memory = MemoryKeeper(config.program_idle_s, self._device, lambda: self.registry.vertices)
        self.helper: BuildHelper | None = None  # set in run() when build_in_child applies
        # kernel groups (World.build_key) the helper built and ran, or a warm-up did (cook thread only)
        self._warmed: set = set()

    def _device(self):
        """The World's OpenCL Device (None for the reference solver or before the World)."""
        return getattr(self._world(), "dev", None)

    def _build(self, world: World, fabric: Fabric, params) -> None:
        """The kernels of a cloth of ``fabric`` and ``params``: first built and run by the helper
        process when its feature combination is new here, then built in this process (from the
        driver's cache)."""
        # once per group of kernels (World.build_key: the feature combination and, on the OpenCL
        # solvers, local memory and pack lanes: a 32k-vertex mesh needs another program than the
        # small cloths of its features), not world.ready(): a program built here is still compiled
        # again at its first launch (PoCL, 0.47 s on the tick for that mesh), and a released one is
        # rebuilt from the cache the helper filled; the warm-up's key ran already (run())
        key = world.build_key(fabric, params)
        if self.helper is not None and key not in self._warmed:
            try:
                warmed = self.helper.warm(fabric, params)
            except BuildMemoryExceeded as e:  # not built here either: it would take that memory here
                raise P.ProtocolError(P.ERR_TOO_LARGE, f"cannot build this cloth's kernels: {e}") from e
            if warmed:
                self._warmed.add(key)
        world.prepare(fabric, params)

    def run(self) -> None:
        dev = self._device()
        if dev is not None:  # the server warmed up before this thread started: keep its kernels
            dev.pin()
            world = self._world()
            if world is not None:  # what the warm-up ran in this process
                self._warmed = warmed_keys(world)
            if self.config.build_in_child == "always":
                self.helper = BuildHelper(self.config.solver, self.config.device, memory_mb=self.config.build_memory_mb)
        try:
            self._loop()
        finally:
            if self.helper is not None:
                self.helper.close()

    def _loop(self) -> None:
        while True:
            try:
                item = self.queue.get(timeout=PERIOD_S)
            except queue.Empty:
                item = False
            if item is None:
                break
            if isinstance(item, Prepare):
                self._prepare(item)
            elif item is not False:
                self._one(*item)
            if self.memory.due():
                self._maintain()
        while True:  # drain what is left
            try:
                item = self.queue.get_nowait()
            except queue.Empty:
                break
            if item is not None and not isinstance(item, Prepare):
                rec, req, query = item
                self.registry.unreserve(rec)
                self.replies.send_error(query, P.ERR_BUSY, "server is shutting down", req.rid)

    def _maintain(self) -> None:
        try:
            before = self.memory.released
            self.memory.maintain()
        except Exception:  # never the cook thread's end
            log.exception("giving memory back failed")
            return
        if self.memory.released != before:
            with self._asked_lock:  # a released program is built again when a control asks
                self._asked.clear()

    def request_prepare(self, fabric: Fabric, params) -> bool:
        """Ask for a cloth's kernels to be built (tick thread; never blocks). False when the
        queue is full: the tick thread asks again next tick."""
        key = (params.features.key(), fabric.key)
        with self._asked_lock:
            if key in self._asked:
                return True
            if len(self._asked) > 4096:
                self._asked.clear()
            self._asked.add(key)
        try:
            self.queue.put_nowait(Prepare(fabric, params))
            return True
        except queue.Full:
            with self._asked_lock:
                self._asked.discard(key)
            return False

    def _prepare(self, item: Prepare) -> None:
        world = self._world()
        try:
            if world is not None:
                self._build(world, item.fabric, item.params)
        except Exception:
            with self._asked_lock:
                self._asked.discard((item.params.features.key(), item.fabric.key))
            log.exception("building kernels for a control failed")  # the tick thread builds them then

    def _cook(self, req: P.SubmitRequest, links: LinkOptions, pinned: np.ndarray) -> Fabric:
        """The cloth's fabric: a big one (``COOK_IN_CHILD_VERTICES``) cooked in a child where
        builds go to one (``build_in_child``), falling back to this thread when the child fails."""
        if self.config.build_in_child == "off" or req.n_vertices < COOK_IN_CHILD_VERTICES:
            return cook_fabric(req, links, pinned)
        try:
            return cook_in_child(req, links, pinned, self.config.build_memory_mb)
        except (ValueError, BuildMemoryExceeded):
            raise
        except Exception as e:
            log.warning("cooking in a child failed (%s): cooking in the server", e)
            return cook_fabric(req, links, pinned)

    def _one(self, rec, req: P.SubmitRequest, query) -> None:
        if self._stopping():
            self.registry.unreserve(rec)
            self.replies.send_error(query, P.ERR_BUSY, "server is shutting down", req.rid)
            return
        try:
            links = LinkOptions(**vars(req.links)) if req.links is not None else LinkOptions()
            pinned = np.unique(req.pinned.astype(np.int64))
            digest = FabricStore.digest(req, links, pinned)
            fabric = self.fabrics.acquire(digest, lambda: self._cook(req, links, pinned))
        except BuildMemoryExceeded as e:
            self.registry.unreserve(rec)
            log.warning("cloth %s of client %s refused: %s", rec.id, rec.client, e)
            self.replies.send_error(query, P.ERR_TOO_LARGE, f"cannot cook this cloth: {e}", req.rid)
            return
        except ValueError as e:
            self.registry.unreserve(rec)
            self.replies.send_error(query, P.ERR_INVALID_VALUE, f"cannot build the cloth: {e}", req.rid)
            return
        except Exception as e:
            log.exception("cooking failed")
            self.registry.unreserve(rec)
            self.replies.send_error(query, P.ERR_INTERNAL, f"cooking failed: {type(e).__name__}", req.rid)
            return
        try:
            params = params_from_submit(req)
            if req.quality is not None:
                params = with_preset(self.config, params, req.quality, req.rid)
                rec.quality_wanted = rec.quality = req.quality
            packed = pack(req.colliders, req.rid) if req.colliders else None
            world = self._world()
            if world is not None:
                self._build(world, fabric, params)  # kernels built here, not on the tick path
            add = Add(rec, params, packed, query, req.rid, mesh=getattr(req, "mesh_collider", None))
            rs = getattr(req, "resume", None)
            if rs is not None:  # 1.3: the tick thread adds the cloth at this state
                add.positions, add.velocities = rs.positions, rs.velocities
                log.info(
                    "cloth %s of client %s resumes %s of server %s at tick %s",
                    rec.id,
                    rec.client,
                    rs.cloth or "a cloth",
                    rs.from_server or "?",
                    rs.tick,
                )
            rec.fabric = fabric
            self.intake.put(add, req.rid)
        except P.DrapeError as e:
            rec.fabric = None
            self.fabrics.release(fabric)
            self.registry.unreserve(rec)
            send(self.replies.error(query, e.code, e.message, req.rid))
            if e.code == P.ERR_TOO_LARGE:
                log.warning("cloth %s of client %s refused: %s", rec.id, rec.client, e.message)
        except Exception as e:
            log.exception("preparing cloth %s failed", rec.id)
            rec.fabric = None
            self.fabrics.release(fabric)
            self.registry.unreserve(rec)
            self.replies.send_error(query, P.ERR_INTERNAL, f"preparing the cloth failed: {type(e).__name__}", req.rid)
