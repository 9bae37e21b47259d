"""Protocol versions, ids and every key expression of a Drape namespace (PROTOCOL.md sections 2, 3, 15)."""

from __future__ import annotations

import re
from dataclasses import dataclass

PROTOCOL_MAJOR = 1
PROTOCOL_MINOR = 4
PROTOCOL_VERSION: tuple[int, int] = (PROTOCOL_MAJOR, PROTOCOL_MINOR)
VERSION_STRING = f"{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}"
#: The minor versions this side has vectors for (every minor of the major is accepted on the wire).
KNOWN_MINORS = (0, 1, 2, 3, 4)

DEFAULT_NAMESPACE = "drape"
DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

#: Ids (server, client, cloth) are single key-expression chunks made of these characters.
ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
NAMESPACE_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}(/[A-Za-z0-9_.\-]{1,64}){0,7}$")
TOKEN_RE = re.compile(r"^[0-9a-f]{32}$")


def valid_id(s: object) -> bool:
    return isinstance(s, str) and bool(ID_RE.match(s))


@dataclass(frozen=True)
class Keys:
    """Every key expression of one Drape namespace."""

    namespace: str = DEFAULT_NAMESPACE

    def __post_init__(self) -> None:
        if not NAMESPACE_RE.match(self.namespace):
            raise ValueError(f"invalid namespace {self.namespace!r}: chunks of [A-Za-z0-9_.-] separated by '/'")

    def submit(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/submit"

    def control(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/control"

    def control_batch(self, server: str) -> str:  # queryable (1.1)
        return f"{self.namespace}/server/{server}/control_batch"

    def remove(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/remove"

    def info(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/info"

    def stats(self, server: str) -> str:  # publication, every stats period
        return f"{self.namespace}/server/{server}/stats"

    def state(self, cloth: str) -> str:  # publication, every tick, binary
        return f"{self.namespace}/cloth/{cloth}/state"

    def bundle(self, client: str) -> str:  # publication, every tick, binary bundle (1.1)
        return f"{self.namespace}/client/{client}/states"

    def alive_server(self, server: str) -> str:  # liveliness token
        return f"{self.namespace}/alive/server/{server}"

    def alive_client(self, client: str) -> str:  # liveliness token
        return f"{self.namespace}/alive/client/{client}"

    @property
    def all_servers_alive(self) -> str:
        return f"{self.namespace}/alive/server/*"

    @property
    def all_clients_alive(self) -> str:
        return f"{self.namespace}/alive/client/*"

    def last_chunk(self, key: str) -> str:
        return str(key).rsplit("/", 1)[-1]
