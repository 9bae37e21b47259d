"""Shared fixtures: fresh random inputs every run (the seed is printed so a failure can be replayed),
one OpenCL device per test session (PoCL's CPU device on CI), random fabrics, and the service
tests' helpers (a server configuration on its own port, connect, collect, wait_until).

Markers (pyproject.toml): a test that opens OpenCL is marked ``opencl`` (its module's
``pytestmark``, or here when it uses the ``device`` fixture), one that opens Zenoh ``zenoh``; every
other test is marked ``unit`` here, and ``pytest -m unit`` runs those alone. A unit test that opens
OpenCL (lists its platforms, makes a context) or Zenoh (opens a session), itself or in a Python
child process (tests/unitguard/sitecustomize.py), fails at once, naming the marker its module
lacks: the markers stay true without anyone remembering them."""

from __future__ import annotations

import contextlib
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np
import pytest

from drape.server.sim.fabric import cook, cook_grid, grid_links, grid_mesh, mesh_links
from drape.server.sim.params import LinkOptions

# `drape serve` children of the tests build kernels in-process (quick; the default, built in a child,
# adds a start-up warm of every feature set): test_build_offtick.py tests the default
os.environ.setdefault("DRAPE_BUILD_IN_CHILD", "off")

if TYPE_CHECKING:
    from drape.server.service.config import ServerConfig

# Imported lazily by the helpers below: the client SDK and the service config (no OpenCL, no Zenoh
# session at import time).


# ---------------------------------------------------------------------------------------------
# Markers: unit tests need neither OpenCL nor Zenoh, and cannot open them

#: marker -> what a test so marked opens
NEEDS = {"opencl": "OpenCL", "zenoh": "Zenoh"}
#: fixtures that open OpenCL or Zenoh -> the markers of a test that uses one
FIXTURE_MARKS = {"device": ("opencl",), "server_pair": ("opencl", "zenoh")}
UNIT_GUARD = Path(__file__).resolve().parent / "unitguard"


@pytest.hookimpl(tryfirst=True)  # before ``-m`` selects by the markers
def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        for fixture, marks in FIXTURE_MARKS.items():
            if fixture in item.fixturenames:
                for mark in marks:
                    item.add_marker(mark)
        if not any(item.get_closest_marker(mark) for mark in NEEDS):
            item.add_marker("unit")


def _refuse(what: str, mark: str, name: str):
    def refuse(*args, **kwargs):
        pytest.fail(f"a unit test opened {what} ({name}): mark its module pytestmark = pytest.mark.{mark}")

    return refuse


@contextlib.contextmanager
def _unit_guard(item) -> Iterator[None]:
    """Around a unit test's setup, call and teardown: opening OpenCL or Zenoh fails the test."""
    if item.get_closest_marker("unit") is None:
        yield
        return
    with pytest.MonkeyPatch.context() as mp:
        # its Python children load tests/unitguard/sitecustomize.py, which refuses the same calls
        mp.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(UNIT_GUARD), os.environ.get("PYTHONPATH")])))
        with contextlib.suppress(ImportError):
            import zenoh

            mp.setattr(zenoh, "open", _refuse("Zenoh", "zenoh", "zenoh.open"))
        with contextlib.suppress(ImportError):
            import pyopencl

            for name in ("get_platforms", "Context", "create_some_context"):
                mp.setattr(pyopencl, name, _refuse("OpenCL", "opencl", f"pyopencl.{name}"))
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    with _unit_guard(item):
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    with _unit_guard(item):
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item):
    with _unit_guard(item):
        yield


@pytest.fixture
def rng(request) -> np.random.Generator:
    seed = int(os.environ.get("DRAPE_TEST_SEED", np.random.SeedSequence().entropy % 2**32))
    print(f"[{request.node.name}] DRAPE_TEST_SEED={seed}")
    return np.random.default_rng(seed)


@pytest.fixture(scope="session")
def device():
    from drape.server.sim.opencl.device import Device

    return Device(os.environ.get("DRAPE_DEVICE"))


def random_mesh_fabric(rng: np.random.Generator, options: LinkOptions = LinkOptions(bending=True), n_pins: int = 2):
    """A random triangle mesh: a jittered grid of random size, some triangles dropped, vertex
    indices shuffled, random pins."""
    cols, rows = int(rng.integers(3, 12)), int(rng.integers(3, 12))
    v, t = grid_mesh(cols, rows, width=rng.uniform(0.5, 2.0), height=rng.uniform(0.5, 2.0))
    v = v + rng.normal(0, 0.02, v.shape)
    keep = rng.random(len(t)) > 0.15
    keep[0] = True
    t = t[keep]
    perm = rng.permutation(len(v))
    inv = np.argsort(perm)
    v = v[perm]
    t = inv[t]
    used = np.unique(t)
    pins = rng.choice(used, size=min(n_pins, len(used)), replace=False) if n_pins else []
    links, ltype = mesh_links(t.astype(np.int32), options)
    return cook(v, t, links, ltype, pins)


def random_grid_fabric(rng: np.random.Generator, options: LinkOptions = LinkOptions(bending=True), n_pins: int = 2):
    cols, rows = int(rng.integers(3, 14)), int(rng.integers(3, 14))
    pins = rng.choice(cols * rows, size=n_pins, replace=False) if n_pins else []
    return cook_grid(
        cols,
        rows,
        rng.uniform(0.5, 2.0),
        rng.uniform(0.5, 2.0),
        options,
        pins,
        orientation=str(rng.choice(["horizontal", "vertical"])),
    )


# ---------------------------------------------------------------------------------------------
# The service end to end: helpers (plain functions, also offered as the ``svc`` fixture)

GRACE = 1.0  # grace period of the test servers' vanished clients
TIMEOUT = 5.0  # a test client's request timeout
# seconds to wait for a positive event (states, a tick, a counter reached): never asserted on, so
# generous; a deadline of TIMEOUT made collect(h, 60) a 12-states-per-second minimum that a loaded
# CI machine's pace could miss
WAIT = 30.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def make_config(**kw) -> ServerConfig:
    """A test server's configuration on its own free port. Admission control runs with a budget
    of 50 ticks (it never refuses on a loaded CI machine); tests of admission set their own."""
    from drape.server.service.config import ServerConfig

    ep = kw.pop("listen", None) or [endpoint()]
    base = dict(
        listen=ep,
        server_id=f"test-{ep[0].rsplit(':', 1)[1]}",
        solver="workgroup",
        tick_rate=60.0,
        grace_period=GRACE,
        stats_period=0.25,
        max_cloths_per_client=6,
        max_vertices_per_cloth=4096,
        max_total_vertices=40000,
        max_message_bytes=1 << 20,
        max_pin_updates=64,
        multicast_scouting=False,
        admission_budget=50.0,
        build_in_child="off",  # kernels built in-process: quick (test_build_offtick.py tests the default)
    )
    base.update(kw)
    return ServerConfig(**base).validate()


def connect(server, **kw):
    from drape.client import DrapeClient

    kw.setdefault("timeout", TIMEOUT)
    return DrapeClient(server.config.listen[0], server_id=server.server_id, **kw)


@pytest.fixture
def client(server):
    """A client of the test module's ``server`` fixture, closed (its cloths removed) afterwards."""
    c = connect(server)
    yield c
    c.close()


def collect(handle, n: int, timeout: float = WAIT) -> list:
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n:
        out.append(handle.next_state(max(0.0, deadline - time.monotonic())))
    return out


def wait_until(pred, timeout: float = WAIT, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


#: flags of the two ``drape serve`` processes of ``server_pair``
PAIR_ARGS = ("--device", "cpu", "--grace-period", "1", "--stats-period", "0.25", "--no-admission")


@pytest.fixture
def server_pair():
    """Two real ``drape serve`` processes on loopback, each on its own port (placement, failover)."""
    from drape.server.tools.procs import ServerProcess

    pair = [ServerProcess(PAIR_ARGS, server_id=f"pl-{k}-{os.getpid()}") for k in "ab"]
    try:
        yield pair
    finally:
        for s in pair:
            s.stop(grace=20.0)


@pytest.fixture
def svc() -> SimpleNamespace:
    """The service test helpers: make_config, connect, collect, wait_until, free_port, endpoint,
    TIMEOUT, WAIT, GRACE."""
    return SimpleNamespace(
        make_config=make_config,
        connect=connect,
        collect=collect,
        wait_until=wait_until,
        free_port=free_port,
        endpoint=endpoint,
        TIMEOUT=TIMEOUT,
        WAIT=WAIT,
        GRACE=GRACE,
    )


__all__ = [
    "random_mesh_fabric",
    "random_grid_fabric",
    "grid_links",
    "make_config",
    "connect",
    "collect",
    "wait_until",
    "free_port",
    "endpoint",
    "TIMEOUT",
    "GRACE",
]
