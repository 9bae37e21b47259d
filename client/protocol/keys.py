"""Protocol versions, ids and every key expression of a Drape namespace (PROTOCOL.md sections 2, 3, 15)."""

from __future__ import annotations

import re
from dataclasses import dataclass

PROTOCOL_MAJOR = 1
PROTOCOL_MINOR = 9
PROTOCOL_VERSION: tuple[int, int] = (PROTOCOL_MAJOR, PROTOCOL_MINOR)
VERSION_STRING = f"{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}"
#: The minor versions this side has vectors for (every minor of the major is accepted on the wire).
KNOWN_MINORS = (0, 1, 2, 3, 4, 5, 6, 7, 8)

DEFAULT_NAMESPACE = "drape"
DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

#: Ids (server, client, cloth) are single key-expression chunks made of these characters.
ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
NAMESPACE_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}(/[A-Za-z0-9_.\-]{1,64}){0,7}$")
TOKEN_RE = re.compile(r"^[0-9a-f]{32}$")

#: The requests a 1.4 client sends on its own client-scoped key (info stays server-wide); 1.7 adds scene.
CLIENT_REQUESTS = ("submit", "control", "control_batch", "remove", "scene")
#: 1.7: the members entry that lets every client put cloths into a scene.
SCENE_ANYONE = "*"
#: The rates a subscriber may take a state or bundle key at: every k-th state (k = 1: the key
#: itself; 1.8: 2 and 3, 30 and 20 Hz at the default 60 Hz tick; 1.9: 6 and 12, 10 and 5 Hz), each
#: on its own key (:func:`every_key`), with the first protocol version whose servers serve it.
RATE_SINCE: dict[int, tuple[int, int]] = {1: (1, 0), 2: (1, 8), 3: (1, 8), 6: (1, 9), 12: (1, 9)}
RATES = tuple(RATE_SINCE)
#: 1.8: the chunk that names a decimated stream's key: ``{state or bundle key}/every/{k}``.
EVERY_CHUNK = "every"


def valid_id(s: object) -> bool:
    return isinstance(s, str) and bool(ID_RE.match(s))


def every_key(key: str, every: int) -> str:
    """1.8 (1.9: 6, 12): the key of every ``every``-th state published on ``key`` (a state or bundle key; a
    stream of its own, predicted against its own states); ``key`` itself for 1."""
    if every not in RATES:
        raise ValueError(f"rate every={every!r}: one of {RATES}")
    return key if every == 1 else f"{key}/{EVERY_CHUNK}/{every}"


def served_rates(version: tuple[int, int] | None) -> tuple[int, ...]:
    """The rates a server of protocol ``version`` serves (None: unknown, the full rate only)."""
    if version is None:
        return RATES[:1]
    return tuple(k for k, since in RATE_SINCE.items() if tuple(version) >= since)


def split_every(key: str) -> tuple[str, int]:
    """1.8: (the full-rate key, k) of a decimated stream's key; (``key``, 1) for any other key
    (k not in RATES: the key is taken as is, as no stream's)."""
    base, sep, last = str(key).rpartition(f"/{EVERY_CHUNK}/")
    if sep and last.isdigit() and int(last) in RATES[1:]:
        return base, int(last)
    return str(key), 1


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

    def scene(self, server: str) -> str:  # queryable (1.7)
        return f"{self.namespace}/server/{server}/scene"

    def info(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/info"

    def stats(self, server: str) -> str:  # publication, every stats period
        return f"{self.namespace}/server/{server}/stats"

    def state(self, cloth: str) -> str:  # publication, every tick, binary
        return f"{self.namespace}/cloth/{cloth}/state"

    def bundle(self, client: str) -> str:  # publication, every tick, binary bundle (1.1)
        return f"{self.namespace}/client/{client}/states"

    # --- 1.4: keys that name the client, so that a router can bind them to its user (section 11.2)
    def client_request(self, kind: str, server: str, client: str) -> str:  # queryable (1.4)
        """``{ns}/server/{server}/client/{client}/{kind}``, kind one of CLIENT_REQUESTS; the server
        takes the request's client id from this key. ``client="*"``: what a server declares."""
        if kind not in CLIENT_REQUESTS:
            raise ValueError(f"no client-scoped {kind!r} request; one of {CLIENT_REQUESTS}")
        return f"{self.namespace}/server/{server}/client/{client}/{kind}"

    def client_state(self, client: str, cloth: str) -> str:  # publication, every tick, binary (1.4)
        return f"{self.namespace}/client/{client}/cloth/{cloth}/state"

    def every(self, key: str) -> str:
        """1.8: the decimated streams of a state or bundle key expression (``key`` may hold
        wildcards): what a server declares its keyframe queryables and ACL rules on."""
        return f"{key}/{EVERY_CHUNK}/*"

    def client_all(self, client: str) -> str:
        """Everything published for one client: its bundle and its cloths' states (1.4)."""
        return f"{self.namespace}/client/{client}/**"

    def request_client(self, key: str, kind: str) -> str | None:
        """The client id of a client-scoped ``kind`` request key, or None when ``key`` is not one
        naming exactly one valid client id (a wildcard or a foreign layout)."""
        parts = str(key).split("/")
        n = self.namespace.count("/") + 1
        if (
            len(parts) != n + 5
            or "/".join(parts[:n]) != self.namespace
            or parts[n] != "server"
            or parts[n + 2] != "client"
            or parts[n + 4] != kind
        ):
            return None
        return parts[n + 3] if valid_id(parts[n + 3]) else None

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
