"""The authenticated deployment of ``drape chaos --auth`` (issue 26) and of its ``acl-placement``
scenario: the documented deployment (docs/reliability.md 3) on loopback. A Zenoh router in a
child process of its own, configured as ``drape acl`` generates it (``deploy/zenoh-router.json5``,
user/password authentication, the access control of a users file, TLS with a CA made by openssl
or plain TCP), servers behind it in client mode with ``--identity keys``, and every client
(good clients, abusers, the stats watch) in client mode as its own user.

:class:`AuthRouter` starts the router for a list of users and hands out what each party needs:
``drape serve`` arguments, a Zenoh session, the SDK's keyword arguments.
"""

from __future__ import annotations

import json
import logging
import secrets
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from drape.client import protocol as P

from . import acl
from .procs import free_port

log = logging.getLogger(__name__)

TEMPLATE = Path(__file__).resolve().parents[2] / "deploy" / "zenoh-router.json5"
ROUTER_MAIN = "import sys, time, zenoh; s = zenoh.open(zenoh.Config.from_file(sys.argv[1])); time.sleep(1e9)"
WATCHER = "chaos-watch"  # the client user the stats watches subscribe as


def make_certs(d: Path, parties: Iterable[str] = ()) -> dict[str, str]:
    """A CA, a router certificate for localhost and one client certificate per party
    (CN = name.drape.test, for mutual TLS), as deploy/certs/README.md makes them, in ``d``."""

    def ossl(*a: str) -> None:
        subprocess.run(["openssl", *a], cwd=d, check=True, capture_output=True)

    ossl(
        *("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=drape-test-ca"),
        *("-keyout", "ca-key.pem", "-out", "ca.pem"),
    )
    ossl(
        *("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost"),
        *("-keyout", "router-key.pem", "-out", "router.csr"),
    )
    (d / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    signed = ("-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial", "-days", "2")
    ossl("x509", "-req", "-in", "router.csr", *signed, "-extfile", "san.ext", "-out", "router.pem")
    (d / "client.ext").write_text("extendedKeyUsage=clientAuth\n")
    for name in parties:
        ossl(
            *("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={name}.drape.test"),
            *("-keyout", f"{name}-key.pem", "-out", f"{name}.csr"),
        )
        ossl("x509", "-req", "-in", f"{name}.csr", *signed, "-extfile", "client.ext", "-out", f"{name}.pem")
    return {"ca": str(d / "ca.pem"), "key": str(d / "router-key.pem"), "cert": str(d / "router.pem")}


class AuthRouter:
    """A router process for ``servers`` (server users, id = name) and ``clients`` (client users,
    id = name), each with a random password; ``transport``: ``tls`` or ``tcp``."""

    def __init__(self, out: Path, servers: Sequence[str], clients: Sequence[str], transport: str = "tls") -> None:
        if transport not in ("tls", "tcp"):
            raise ValueError(f"transport must be tls or tcp, not {transport!r}")
        self.dir = out / f"router-{secrets.token_hex(4)}"
        self.dir.mkdir(parents=True)
        self.watcher = WATCHER
        self.passwords = {u: secrets.token_hex(8) for u in [*servers, *clients, WATCHER]}
        roles = {**{s: "server" for s in servers}, **{c: "client" for c in [*clients, WATCHER]}}
        users = "".join(
            f'[[user]]\nname = "{u}"\nrole = "{roles[u]}"\nid = "{u}"\npassword = "{p}"\n'
            for u, p in self.passwords.items()
        )
        (self.dir / "users.toml").write_text(f'namespace = "{P.DEFAULT_NAMESPACE}"\n{users}')
        port = free_port()
        self.tls = make_certs(self.dir) if transport == "tls" else None
        self.endpoint = f"tls/localhost:{port}" if self.tls else f"tcp/127.0.0.1:{port}"
        cfg = acl.listening_router(TEMPLATE, acl.load_users(self.dir / "users.toml"), self.endpoint, self.dir / "dict")
        if self.tls:
            cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(self.tls["ca"]))
            cfg.insert_json5("transport/link/tls/listen_private_key", json.dumps(self.tls["key"]))
            cfg.insert_json5("transport/link/tls/listen_certificate", json.dumps(self.tls["cert"]))
        (self.dir / "router.json5").write_text(str(cfg))
        self._log = open(self.dir / "router.log", "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", ROUTER_MAIN, str(self.dir / "router.json5")],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self._wait_listening()

    def _wait_listening(self, timeout: float = 30.0) -> None:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the router exited with {self.proc.returncode}: {self.dir / 'router.log'}")
            try:
                self.session(WATCHER).close()
                return
            except Exception:
                time.sleep(0.2)
        raise RuntimeError(f"the router did not take a session in {timeout:.0f} s: {self.dir / 'router.log'}")

    def config(self, user: str) -> dict[str, Any]:
        """A client-mode Zenoh configuration of ``user`` (what a deployment ships to it)."""
        link: dict[str, Any] = {"tls": {"root_ca_certificate": self.tls["ca"]}} if self.tls else {}
        return {
            "mode": "client",
            "connect": {"endpoints": [self.endpoint]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {
                "auth": {"usrpwd": {"user": user, "password": self.passwords[user]}},
                "shared_memory": {"enabled": False},  # remote clients cannot use it (chaos_harness.zenoh_session)
                **({"link": link} if link else {}),
            },
        }

    def config_file(self, user: str) -> str:
        """``config(user)`` written to a JSON5 file; its path."""
        path = self.dir / f"{user}.json5"
        path.write_text(json.dumps(self.config(user)))
        return str(path)

    def session(self, user: str) -> zenoh.Session:
        return zenoh.open(zenoh.Config.from_json5(json.dumps(self.config(user))))

    def serve_args(self, server_id: str) -> tuple[str, ...]:
        """``drape serve`` arguments of server user ``server_id`` behind this router."""
        return (
            *("--mode", "client", "--connect", self.endpoint),
            *("--zenoh-config", self.config_file(server_id), "--identity", "keys"),
        )

    def sdk(self, user: str) -> dict[str, Any]:
        """``DrapeClient`` keyword arguments of client user ``user`` (its first argument: ``endpoint``)."""
        return {"mode": "client", "client_id": user, "zenoh_config_file": self.config_file(user)}

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
