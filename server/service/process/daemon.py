"""``drape serve``: run the cloth server until SIGINT or SIGTERM.

Configuration: defaults < TOML file (``--config`` or $DRAPE_CONFIG) < DRAPE_* environment
variables < flags; see drape.server.service.config. On a signal the server stops publishing, answers
what is still queued with ``busy``, undeclares everything and closes its Zenoh session; the
exit status is 0 after a clean stop, 1 when the tick loop failed, 2 for a bad configuration.

``--workers N`` (``workers`` in the TOML file, DRAPE_WORKERS) with N > 1: this process becomes a
supervisor of N such servers sharing the device, each its own server id and port
(drape.server.service.process.workers); 1 (the default) serves in this process.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import signal
import sys
import threading
from types import FrameType

from ..config import ServerConfig, add_arguments, from_args
from .memory import configure_heap

log = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    add_arguments(parser)
    parser.add_argument("--print-config", action="store_true", help="print the effective configuration and exit")


def run(args: argparse.Namespace) -> int:
    try:
        config = from_args(args)
    except (OSError, ValueError) as e:
        log.error("bad configuration: %s", e)
        return 2
    if getattr(args, "print_config", False):
        for k, v in dataclasses.asdict(config).items():
            print(f"{k} = {v!r}")
        return 0
    if config.workers > 1:
        from .workers import supervise

        return supervise(config)
    return leave(serve(config))


def leave(code: int) -> int:
    """End the serving process with ``code`` once the server has stopped, without the
    interpreter's finalization. The server's session is closed by then, but Zenoh's runtime
    threads (Rust) may still enter Python for a last drop callback: CPython 3.11-3.13 ends a
    thread that wants the GIL during finalization with pthread_exit, and its forced unwind
    through Rust frames makes glibc abort the process ("FATAL: exception not rethrown", status
    -6 after a clean stop; python/cpython#87135). Logs and stdio are flushed first."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def start_ops(server, config: ServerConfig):
    """The operator endpoints (/metrics, /healthz, /readyz) and systemd notifications of a
    started server (drape.server.service.process.ops); stop them before the server."""
    from . import ops

    return ops.start(server, config)


def serve(config: ServerConfig) -> int:
    """Run a server in this process until SIGINT/SIGTERM (main thread only)."""
    from ..server import Server  # Zenoh and OpenCL only when actually serving

    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        log.info("received %s", signal.Signals(signum).name)
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    # The whole process is the server's: its threads hand the GIL over sooner (docs/loadtest.md:
    # 0.5 ms instead of 5 took 1024 cloths on the H100 from 28.8 to 48.6 Hz).
    sys.setswitchinterval(config.gil_switch_ms / 1000.0)
    # large requests' buffers mapped apart and unmapped when freed, one malloc arena whose free
    # pages the memory upkeep gives back (drape.server.service.process.memory)
    configure_heap(config.malloc_mmap_threshold)
    if config.build_in_child != "off" and config.solver != "reference":
        # the warm-up's kernels built and run in a child first: this process then loads them from
        # the driver's disk cache instead of keeping the compiler's memory (drape.server.service.cook.buildhelper)
        from ..cook.buildhelper import warm_up_in_child

        warm_up_in_child(config)
    server = Server(config)
    operator = None
    profile = os.environ.get("DRAPE_PROFILE")
    sampler = None
    try:
        server.start()
        operator = start_ops(server, config)
        if profile:
            from .sampler import ThreadSampler

            sampler = ThreadSampler().start()
        while not stop.wait(0.25):
            if server.failure is not None:
                log.error("tick loop failed: %s", server.failure)
                break
    except Exception as e:  # no device, endpoint in use, bad Zenoh configuration...
        log.error("server failed: %s", e)
        log.debug("details", exc_info=True)
        server.failure = server.failure or e
    finally:
        if operator is not None:
            operator.stop()
        if sampler is not None:
            sampler.stop()
        server.stop()
        if sampler is not None and profile:
            sampler.write(profile)
        for s, h in previous.items():
            signal.signal(s, h)
    return 1 if server.failure is not None else 0
