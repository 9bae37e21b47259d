"""Shared fixtures of the access-control tests (test_acl.py, test_identity.py): a users file, a real
Zenoh router with user/password authentication and the generated ACL (over TCP and TLS with a CA
made by openssl), client-mode sessions of a user, an inbox of samples, ``drape serve`` behind the
router. Helpers are offered as the ``acl_kit`` fixture (no test imports another test); the load
tests' run of a load against a ``drape serve`` started for it as ``load_on_server``.

Being a second ``conftest`` module, this one is what ``from conftest import ...`` finds in the tools
tests: it re-exports the shared service helpers of tests/conftest.py under the same names.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import zenoh

from drape.server.tools import acl, chaos_router

REPO = Path(__file__).resolve().parents[2]


def _root_conftest() -> Any:
    """tests/conftest.py as a module of its own name (``conftest`` names this file here)."""
    spec = importlib.util.spec_from_file_location("drape_tests_root_conftest", REPO / "tests" / "conftest.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_root = _root_conftest()
# Every plain helper and constant of tests/conftest.py, under the same names: once this module is
# imported as ``conftest``, ``from conftest import ...`` finds it from any test directory (which
# one depends on the collection order), so it must offer all of them. Fixtures stay the root's
# (pytest finds those by itself; defining them here again would make second instances).
for _name, _value in vars(_root).items():
    if _name.startswith(("_", "pytest_")) or _name in globals() or type(_value).__name__ == "FixtureFunctionDefinition":
        continue
    globals()[_name] = _value
make_config, connect, collect = _root.make_config, _root.connect, _root.collect
free_port, endpoint, wait_until = _root.free_port, _root.endpoint, _root.wait_until
TIMEOUT, GRACE, WAIT = _root.TIMEOUT, _root.GRACE, _root.WAIT
EXAMPLE = REPO / "deploy" / "users.example.toml"
SERVER_WAIT = 90.0  # a drape serve starting (OpenCL warm-up) on a loaded CI machine

USERS = """
namespace = "drape"
[[user]]
name = "eu-1"
role = "server"
id = "eu-1"
password = "pw-server"
[[user]]
name = "alice"
role = "client"
id = "alice"
password = "pw-alice"
[[user]]
name = "bob"
role = "client"
id = "bob"
password = "pw-bob"
"""
PASSWORDS = {"eu-1": "pw-server", "alice": "pw-alice", "bob": "pw-bob"}


def session(
    endpoint: str, user: str | None, password: str | None, tls: dict[str, str] | None, cert: str | None = None
) -> zenoh.Session:
    """A client-mode session; ``cert``: present that certificate (``{cert}.pem``, mutual TLS)."""
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    if tls:
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls["ca"]))
    if tls and cert:
        d = Path(tls["ca"]).parent
        c.insert_json5("transport/link/tls/enable_mtls", "true")  # the connecting side must say so too
        c.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(d / f"{cert}-key.pem")))
        c.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(d / f"{cert}.pem")))
    if user:
        c.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        c.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(c)


def make_certs(d: Path) -> dict[str, str]:
    """A CA, a router certificate for localhost and one client certificate per party of
    ``PASSWORDS`` (CN = name.drape.test), as deploy/certs/README.md makes them."""
    return chaos_router.make_certs(d, PASSWORDS)


class Inbox:
    """Samples received on a subscriber (or liveliness subscriber), with an event per key."""

    def __init__(self) -> None:
        self.keys: list[str] = []
        self.payloads: list[bytes] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self.keys.append(str(sample.key_expr))
                self.payloads.append(sample.payload.to_bytes())
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[Inbox], bool], timeout: float = WAIT) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self), timeout)


def user_file(d: Path, user: str, password: str) -> str:
    """A client-mode Zenoh JSON5 file with the user's name and password (what a deployment ships)."""
    p = d / f"{user}.json5"
    auth = {"usrpwd": {"user": user, "password": password}}
    p.write_text(json.dumps({"mode": "client", "transport": {"auth": auth}}))
    return str(p)


def router_config(tmp_path: Path, endpoint: str, users_text: str = USERS) -> tuple[zenoh.Config, acl.UsersFile]:
    """deploy/zenoh-router.json5 listening on ``endpoint`` with the users' dictionary and ACL."""
    users_file = tmp_path / "users.toml"
    users_file.write_text(users_text)
    users = acl.load_users(users_file)
    c = acl.listening_router(REPO / "deploy/zenoh-router.json5", users, endpoint, tmp_path / "dict.txt")
    return c, users


@pytest.fixture
def acl_kit() -> SimpleNamespace:
    """The helpers above: USERS, PASSWORDS, EXAMPLE, REPO, WAIT, SERVER_WAIT, Inbox, session,
    make_certs, user_file, router_config, wait_until."""
    return SimpleNamespace(
        USERS=USERS,
        PASSWORDS=PASSWORDS,
        EXAMPLE=EXAMPLE,
        REPO=REPO,
        WAIT=WAIT,
        SERVER_WAIT=SERVER_WAIT,
        Inbox=Inbox,
        session=session,
        make_certs=make_certs,
        user_file=user_file,
        router_config=router_config,
        wait_until=wait_until,
    )


@pytest.fixture(params=["tcp", "tls"])
def router(request, tmp_path) -> Iterator[Callable[..., zenoh.Session]]:
    """A Zenoh router with the generated access control and user/password authentication;
    yields ``connect(user, password=None)``, a client-mode session of that user."""
    port = free_port()
    tls = None
    if request.param == "tls":
        if shutil.which("openssl") is None:
            pytest.skip("openssl not installed")
        tls = make_certs(tmp_path)
        endpoint = f"tls/localhost:{port}"
    else:
        endpoint = f"tcp/127.0.0.1:{port}"
    c, _ = router_config(tmp_path, endpoint)
    if tls:
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls["ca"]))
        c.insert_json5("transport/link/tls/listen_private_key", json.dumps(tls["key"]))
        c.insert_json5("transport/link/tls/listen_certificate", json.dumps(tls["cert"]))
    r = zenoh.open(c)
    opened: list[zenoh.Session] = []

    def connect(user: str | None, password: str | None = None) -> zenoh.Session:
        s = session(endpoint, user, PASSWORDS.get(user or "") if password is None else password, tls)
        opened.append(s)
        return s

    yield connect
    for s in reversed(opened):
        s.close()
    r.close()


@dataclass
class DrapeBehindRouter:
    """A TCP router with the generated ACL and ``drape serve`` (server eu-1, client mode) behind it."""

    endpoint: str
    tmp_path: Path
    server: subprocess.Popen[Any]

    def client_file(self, user: str) -> str:
        return user_file(self.tmp_path, user, PASSWORDS[user])

    def session(self, user: str) -> zenoh.Session:
        return session(self.endpoint, user, PASSWORDS[user], None)

    def sdk(self, user: str, timeout: float = SERVER_WAIT) -> Any:
        """The SDK as client ``user``, in client mode through the router, with its user file."""
        from drape.client import DrapeClient

        return DrapeClient(
            self.endpoint, mode="client", client_id=user, timeout=timeout, zenoh_config_file=self.client_file(user)
        )


@pytest.fixture
def drape_behind_router(tmp_path, request) -> Iterator[DrapeBehindRouter]:
    """``drape serve`` as server user eu-1 behind an ACL router; extra ``drape serve`` arguments
    from the test's ``serve_args`` marker (``@pytest.mark.serve_args("--identity", "keys")``)."""
    marker = request.node.get_closest_marker("serve_args")
    extra = list(marker.args) if marker else []
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    c, _ = router_config(tmp_path, endpoint)
    r = zenoh.open(c)
    log = open(tmp_path / "server.log", "w")
    server = subprocess.Popen(
        [
            *(sys.executable, "-m", "drape.server.cli", "serve", "--mode", "client", "--connect", endpoint),
            *("--zenoh-config", user_file(tmp_path, "eu-1", "pw-server"), "--server-id", "eu-1"),
            *("--stats-period", "0.5", "--no-admission"),  # admission: not these tests' subject
            *extra,
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    try:
        yield DrapeBehindRouter(endpoint, tmp_path, server)
    finally:
        server.terminate()
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait(10)
        log.close()
        r.close()


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "serve_args(*args): extra drape serve arguments of drape_behind_router")


def _load_on_server(spec: Any, serve_args: list[str], server_id: str) -> tuple[Any, Any, Any]:
    """``drape loadtest``'s run of ``spec`` (a LoadSpec) against a ``drape serve`` with
    ``serve_args`` started for it, its stats watched; the server stopped after (cleanly, asserted):
    (report, client results, window)."""
    from drape.server.tools import loadtest as lt
    from drape.server.tools.procs import ServerProcess

    server = ServerProcess(serve_args, server_id=server_id)
    try:
        stats = lt.StatsWatch(server.endpoint, server.server_id)
        try:
            return lt.run_load(spec, server.endpoint, server.server_id, server, stats, quiet=True)
        finally:
            stats.close()
    finally:
        assert server.stop() == 0, "drape serve did not stop cleanly"


@pytest.fixture
def load_on_server() -> Callable[[Any, list[str], str], tuple[Any, Any, Any]]:
    """:func:`_load_on_server`: (spec, serve_args, server_id) -> (report, client results, window)."""
    return _load_on_server
