"""Kernel builds and big cooks in a child process: the compiler's memory, the first launch's JIT
and a big mesh's seconds of Python stay out of the server (:func:`cook_in_child`: cloths of
``COOK_IN_CHILD_VERTICES`` or more, where builds go to a child).

On PoCL (the CPU device) a program built from source for the first time costs the process that
builds it LLVM's high-water mark for good (measured: 150 -> 288 MB for the first build, not given
back by releasing the program or trimming the heap), and each kernel's work-group function is
compiled again at its first launch for each local size (300-600 ms on the tick thread per new
feature combination). Both land in PoCL's disk cache (``~/.cache/pocl``), keyed by source, options
and device. So the cook thread first has :class:`BuildHelper`'s child process build *and run* the
cloth (a scratch World of its own: add, one step, fetch, remove) the first time a feature
combination comes, then builds the program itself from the cache: measured with a cold cache,
the server's first step of 8 new combinations took 7.4 ms at worst instead of 323 ms, and its RSS
stayed where it was.

Both children run at a lower CPU priority (``NICE``): a build takes what the tick thread leaves,
and are bounded in memory (``build_memory_mb``): the parent samples a child's resident memory
every ``WATCH_S`` while it waits and kills a child past the bound. The helper then raises
:class:`BuildMemoryExceeded` (the cook thread refuses that cloth ``too_large`` instead of building
it in the server, which would take the same memory there); the start-up warm-up is reported and
skipped. (Not RLIMIT_AS: a GPU driver reserves tens of GB of address space it never touches.)

``build_in_child = "start"``: :func:`warm_up_in_child` does it once, before ``drape serve`` starts serving, for
the warm-up's kernels and one cloth of each of the 32 feature combinations (start-up 0.8 -> 2.9 s
with PoCL's cache warm, 2.6 -> 21.6 s cold, where it keeps the server at 168 MB instead of 306 MB);
the cook thread then builds from the cache. ``"always"``: the cook thread also has
:class:`BuildHelper` build and run the first cloth of each feature combination it meets (for a
driver whose cache the start did not fill); that child starts on the first request (1-2 s, which
that submit waits) and exits after ``IDLE_S`` without requests. A helper that fails or times out
is reported and the server builds in-process as before. ``"always"`` is the default (issue 26: with
``"off"``, on a cold cache the first cloth of 29 of 31 feature sets stalled ticks 208-446 ms);
``"off"``: everything is built in the server process (the test suite's servers, for speed).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
import time
from dataclasses import fields
from typing import Any

log = logging.getLogger(__name__)

IDLE_S = 30.0  # the child exits after this long without a request
TIMEOUT_S = 120.0  # longest wait for one build and run (a cold 65k-vertex build on a busy CPU)
START_TIMEOUT_S = 60.0
# the start-up warm-up of every feature set: cold, 71-78 s on this 2-core CPU under others' load
# (issue 26: killed at 60 s, it left the later first cloths to build in the server)
WARM_UP_TIMEOUT_S = 180.0
NICE = 10  # the children's CPU priority below the server's (os.nice)
WATCH_S = 0.05  # the parent samples a child's resident memory this often while it waits
COOK_IN_CHILD_VERTICES = 8192  # cloths this large are cooked in a child (a 32k-vertex mesh: 7 s of Python)


class BuildMemoryExceeded(RuntimeError):
    """A build child passed its memory bound (``build_memory_mb``) and was killed."""


def rss_mb(pid: int) -> float:
    """A process's resident memory in MB (0 where it cannot be read: gone, or not Linux)."""
    try:
        with open(f"/proc/{pid}/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def watch(proc: Any, done: Any, timeout: float, memory_mb: float, what: str) -> bool:
    """Wait up to ``timeout`` s for ``done(wait_s)`` (a pipe's poll, a process's end), sampling
    ``proc``'s resident memory every ``WATCH_S``; False on timeout. A child past ``memory_mb``
    (0: no bound) is killed and :class:`BuildMemoryExceeded` raised."""
    t_end = time.monotonic() + timeout
    while True:
        left = t_end - time.monotonic()
        if left <= 0.0:
            return False
        if done(min(WATCH_S, left)):
            return True
        rss = rss_mb(proc.pid) if memory_mb > 0 else 0.0
        if rss > memory_mb > 0:
            proc.kill()
            proc.join(5)
            raise BuildMemoryExceeded(
                f"{what} took {rss:.0f} MB, over build_memory_mb = {memory_mb:g} MB: the child was killed"
            )


def _fabric_fields(fabric: Any) -> dict[str, Any]:
    """A Fabric as its init fields (it holds a lock, which does not pickle; the child's Fabric
    computes its own tethers when asked)."""
    return {f.name: getattr(fabric, f.name) for f in fields(fabric) if f.init and not f.name.startswith("_")}


def _run_one(world: Any, fabric_kw: dict[str, Any], params: Any) -> None:
    from ...sim.fabric import Fabric

    fabric = Fabric(**fabric_kw)
    world.prepare(fabric, params)
    h = world.add(fabric, params)
    world.step(1.0 / 60.0)
    world.fetch()
    world.remove(h)
    world.fetch()


def lower_priority(nice: int = NICE) -> None:
    """This (child) process at a lower CPU priority: its builds take what the tick thread leaves."""
    try:
        os.nice(nice)
    except OSError:  # not allowed here: the build still runs, at the server's priority
        log.debug("could not lower the build child's priority", exc_info=True)


def _child_main(conn: Any, solver: str, device: str | None, idle_s: float) -> None:
    """The helper process: one scratch World; (fabric fields, params) in, ("ok" | error) out."""
    lower_priority()
    from ...sim import make_world

    try:
        world = make_world(solver, device=device)
        conn.send(("ready", None))
    except Exception as e:
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    while conn.poll(idle_s):
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg is None:
            return
        try:
            _run_one(world, *msg)
            conn.send(("ok", None))
        except Exception as e:  # the server builds it in-process then, and reports it
            conn.send(("error", f"{type(e).__name__}: {e}"))


class BuildHelper:
    """The cook thread's helper process (thread-safe; one request at a time)."""

    def __init__(self, solver: str, device: str | None, idle_s: float = IDLE_S, memory_mb: float = 0.0) -> None:
        self.solver, self.device, self.idle_s, self.memory_mb = solver, device, idle_s, memory_mb
        self.runs = 0  # cloths the child built and ran
        self.starts = 0  # child processes started
        self.failures = 0  # requests that fell back to an in-process build
        self.memory_kills = 0  # children killed past memory_mb (their cloths refused)
        self.disabled = False  # after a failure to start: the server builds in-process
        self._lock = threading.Lock()
        self._proc: Any = None
        self._conn: Any = None

    def warm(self, fabric: Any, params: Any) -> bool:
        """Build and run a cloth of ``fabric`` and ``params`` in the child (blocking the caller,
        never the tick). True when it did; False when the caller should simply build in-process;
        :class:`BuildMemoryExceeded` when the child passed ``memory_mb`` (the cloth is too large
        to build: not in the server either)."""
        if self.disabled:
            return False
        with self._lock:
            try:
                conn = self._connection()
                conn.send((_fabric_fields(fabric), params))
                if not watch(self._proc, conn.poll, TIMEOUT_S, self.memory_mb, "building and running the cloth"):
                    raise TimeoutError(f"no answer in {TIMEOUT_S:.0f} s")
                status, detail = conn.recv()
            except BuildMemoryExceeded as e:
                self.memory_kills += 1
                log.warning("kernel build helper: %s", e)
                self._stop()
                raise
            except Exception as e:
                self.failures += 1
                log.warning("kernel build helper failed (%s): building in the server process", e)
                self._stop()
                return False
            if status != "ok":
                self.failures += 1
                log.warning("kernel build helper could not run the cloth (%s): building in the server", detail)
                return False
            self.runs += 1
            return True

    def _connection(self) -> Any:
        if self._proc is not None and self._proc.is_alive():
            return self._conn
        self._stop()
        ctx = mp.get_context("spawn")  # never fork a process with Zenoh's and OpenCL's threads
        parent, child = ctx.Pipe()
        t = time.monotonic()
        proc = ctx.Process(
            target=_child_main, args=(child, self.solver, self.device, self.idle_s), daemon=True, name="drape-build"
        )
        proc.start()
        child.close()
        self._proc = proc  # so that _stop ends it, whatever happens below
        self._conn = parent
        if not watch(proc, parent.poll, START_TIMEOUT_S, self.memory_mb, "starting the build helper"):
            proc.kill()
            self.disabled = True
            raise TimeoutError(f"the helper did not start in {START_TIMEOUT_S:.0f} s")
        status, detail = parent.recv()
        if status != "ready":
            proc.join(5)
            self.disabled = True
            raise RuntimeError(detail)
        self.starts += 1
        log.debug("kernel build helper %d started in %.2f s", proc.pid, time.monotonic() - t)
        self._proc, self._conn = proc, parent
        return parent

    def _stop(self) -> None:
        if self._proc is None:
            return
        try:
            self._conn.send(None)
        except Exception:
            pass
        self._proc.join(2)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(2)
        self._conn.close()
        self._proc = self._conn = None

    def close(self) -> None:
        with self._lock:
            self._stop()


def _warm_up_main(config: Any) -> None:
    lower_priority()
    import itertools

    from drape.client.protocol import FEATURE_NAMES

    from ...sim import make_world
    from ...sim.fabric import cook_grid
    from ...sim.params import ClothParams, Features
    from .warmup import warm_up

    kw = {} if config.solver == "reference" else {"device": config.device, "device_encode": config.device_encode}
    world = make_world(config.solver, **kw)
    warm_up(world, config)  # the server's own warm-up: what it then builds from the cache
    fabric = _fabric_fields(cook_grid(8, 8, pinned=[0, 7]))
    for n in range(1, len(FEATURE_NAMES) + 1):
        for combo in itertools.combinations(FEATURE_NAMES, n):
            _run_one(world, fabric, ClothParams(features=Features.from_names(list(combo))))


def _cook_main(conn: Any, req: Any, links: Any, pinned: Any) -> None:
    """The one-shot cook child: the fabric with its tethers and long-range links, as init fields."""
    lower_priority()
    from .fabrics import cook_fabric

    try:
        fab = cook_fabric(req, links, pinned)
        fab.tethers()
        fab.long_range()
        conn.send(("ok", {f.name: getattr(fab, f.name) for f in fields(fab) if f.init and f.name != "_tether_lock"}))
    except ValueError as e:
        conn.send(("invalid", str(e)))
    except Exception as e:
        conn.send(("error", f"{type(e).__name__}: {e}"))


def cook_in_child(req: Any, links: Any, pinned: Any, memory_mb: float = 0.0, timeout: float = TIMEOUT_S) -> Any:
    """:func:`.fabrics.cook_fabric` in a child process at lower priority, bounded in memory
    (:func:`watch`) and time: a big mesh's cook is seconds of Python (a 32k-vertex mesh: 7 s,
    mostly its tethers and long-range links) that would hold the GIL against the tick thread.
    Raises ValueError (an invalid cloth, as the in-process cook does), BuildMemoryExceeded,
    TimeoutError or RuntimeError."""
    from ...sim.fabric import Fabric

    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_cook_main, args=(child, req, links, pinned), daemon=True, name="drape-cook")
    proc.start()
    child.close()
    try:
        if not watch(proc, parent.poll, timeout, memory_mb, "cooking the cloth"):
            proc.kill()
            raise TimeoutError(f"cooking the cloth took more than {timeout:.0f} s")
        status, payload = parent.recv()
    finally:
        parent.close()
        proc.join(5)
        if proc.is_alive():
            proc.kill()
    if status == "invalid":
        raise ValueError(payload)
    if status != "ok":
        raise RuntimeError(f"cooking the cloth in a child failed: {payload}")
    return Fabric(**payload)


def warm_up_in_child(config: Any, timeout: float = WARM_UP_TIMEOUT_S) -> bool:
    """Run the server's warm-up (its default kernels, the frame encoder's) and one cloth of every
    feature combination in a child process first, so that the server builds them all from the
    driver's cache, at start and whenever a cloth asks for one later. True when it ran."""
    t = time.monotonic()
    proc = mp.get_context("spawn").Process(target=_warm_up_main, args=(config,), daemon=True, name="drape-warm-up")
    proc.start()

    def ended(wait_s: float) -> bool:
        proc.join(wait_s)
        return not proc.is_alive()

    try:
        watch(proc, ended, timeout, config.build_memory_mb, "the warm-up in a child process")
    except BuildMemoryExceeded as e:
        log.warning("%s; the server builds its kernels itself", e)
        return False
    if proc.is_alive():
        proc.kill()
        proc.join(5)
        log.warning("the warm-up in a child process did not finish in %.0f s", timeout)
        return False
    if proc.exitcode != 0:
        log.warning("the warm-up in a child process failed (exit %s)", proc.exitcode)
        return False
    log.debug("warm-up in a child process took %.2f s", time.monotonic() - t)
    return True
