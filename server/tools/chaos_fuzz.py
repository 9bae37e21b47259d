"""``drape chaos fuzz``: malformed and hostile requests on every queryable of a server.

:func:`messages` generates, deterministically from a seed, ``(queryable, kind, payload)`` triples:
random bytes, truncated msgpack, nesting 1,000 deep (bare and inside a field), huge maps and arrays
up to ``max_message_bytes``, extension types, invalid UTF-8, non-string keys, trailing bytes, and
for every field of valid submit / control / control_batch / remove / info requests (built with
``drape.client.protocol``) each wrong-typed value, a deletion and an out-of-range value.

:func:`send_all` sends them with a bounded number of queries in flight and counts the outcomes:
every reply's error code (``internal`` is a server bug), replies that are not Drape error maps, and
queries that got no reply at all (timeouts).
"""

from __future__ import annotations

import copy
import logging
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import zenoh

from drape.client import protocol as P

from .chaos_harness import reply_outcome

log = logging.getLogger(__name__)

QUERYABLES = ("submit", "control", "control_batch", "remove", "info")
DEPTH = 1000  # nesting depth of the deep messages

#: Values of every msgpack type, put in place of a field's value.
WRONG_VALUES: tuple[Any, ...] = (
    None,
    True,
    False,
    0,
    -1,
    2**64 - 1,
    -(2**63),
    1.5,
    float("nan"),
    float("inf"),
    -float("inf"),
    1e308,
    "",
    "x" * 300,
    "\u00e9\u4e2d",
    b"",
    b"\x00" * 7,
    b"\xff" * 4096,
    [],
    [1, 2, 3],
    [None] * 100,
    {},
    {"a": 1},
    {"x": {"y": {"z": []}}},
    msgpack.ExtType(5, b"abc"),
)


@dataclass
class Base:
    """A valid request of one queryable, as the map it encodes to."""

    queryable: str
    name: str
    message: dict[str, Any]


def valid_requests(client: str, cloth: str = "0123456789abcdef", token: str = "0" * 32) -> list[Base]:
    """Valid requests of every queryable, with every optional field filled in (so each is mutated)."""
    verts, tris = P.grid_geometry(4, 4)
    sphere = P.Sphere((0.0, 0.5, 0.0), 0.2)
    capsule, plane = P.Capsule((0, 0, 0), (1, 0, 0), 0.1), P.Plane((0, 1, 0), -1)
    grid = P.SubmitRequest(
        client=client,
        grid=P.GridSpec(8, 8, 1.0, 1.0, "horizontal", (0.0, 1.0, 0.0)),
        pinned=np.array([0, 7], np.uint32),
        links=P.LinkSpec(True, True, True),
        material={"mass": 1.0, "stiffness": (1.0, 0.9, 0.5), "damping": 0.01, "drag": 0.1, "tether_limit": 1.1},
        features=("tethers", "wind"),
        gravity=(0.0, -9.81, 0.0),
        wind=(1.0, 0.0, 0.0),
        iterations=4,
        substeps=1,
        chebyshev_rho=0.0,
        colliders=(sphere, capsule, plane),
        state=P.StateOptions(False, "float16", False),
        rid=7,
    )
    mesh = P.SubmitRequest(
        client=client,
        mesh=P.MeshSpec(verts.astype(np.float32), tris.astype(np.uint32)),
        pinned=np.array([0, 3], np.uint32),
        quality="fast",
        rid=8,
    )
    pins = P.PinUpdate(np.array([0, 7], np.uint32), np.array([[0, 1, 0], [1, 1, 0]], np.float32))
    control = P.ControlRequest(
        cloth,
        token,
        pins=pins,
        colliders=(sphere,),
        gravity=(0, -9.81, 0),
        wind=(0, 0, 1),
        material={"damping": 0.02},
        features=("tethers",),
        iterations=5,
        substeps=1,
        state=P.StateOptions(True, "quant16"),
        reset=False,
        rid=9,
    )
    batch = P.ControlBatchRequest(client, [control, P.ControlRequest(cloth, token, reset=True)], rid=10)
    return [
        Base("submit", "grid", P.submit_to_map(grid)),
        Base("submit", "mesh", P.submit_to_map(mesh)),
        Base("control", "control", P.control_to_map(control)),
        Base("control_batch", "batch", P.control_batch_to_map(batch)),
        Base("remove", "remove", P.remove_to_map(P.RemoveRequest(cloth, token, rid=11))),
        Base("info", "info", msgpack.unpackb(P.encode_info(P.InfoRequest(rid=12)))),
    ]


def _paths(obj: Any, prefix: tuple = ()) -> Iterator[tuple]:
    """Every path to a value inside nested maps and lists (lists: the first two entries)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj[:2]):
            yield prefix + (i,)
            yield from _paths(v, prefix + (i,))


def _set(obj: Any, path: tuple, value: Any, delete: bool = False) -> Any:
    out = copy.deepcopy(obj)
    node = out
    for p in path[:-1]:
        node = node[p]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return out


def deep(depth: int = DEPTH, kind: str = "array") -> bytes:
    """msgpack nested ``depth`` levels: fixarrays or one-key maps around a nil."""
    if kind == "array":
        return b"\x91" * depth + b"\xc0"
    return b"\x81\xa1k" * depth + b"\xc0"


def _huge_map(n: int) -> bytes:
    return msgpack.packb({f"k{i}": i for i in range(n)})


def _huge_array(n: int) -> bytes:
    return b"\xdd" + n.to_bytes(4, "big") + b"\xc0" * n


def _claims_more(n: int) -> bytes:
    """A map header claiming n entries with nothing after it (a decoder must not preallocate)."""
    return b"\xdf" + n.to_bytes(4, "big")


def messages(
    count: int, seed: int, client: str, cloth: str, token: str, max_bytes: int
) -> Iterator[tuple[str, str, bytes]]:
    """``count`` hostile (queryable, kind, payload) triples, the same for the same arguments.

    Roughly: 45 % field mutations of valid requests, 15 % truncated, 10 % random bytes, the rest
    structural (deep, huge, ext, bad UTF-8, non-string keys, trailing bytes, wrong top-level type).
    Huge payloads (each up to ``max_bytes``) are at most 1 in 50 messages."""
    rng = np.random.default_rng(seed)
    bases = valid_requests(client, cloth, token)
    mutations: list[tuple[str, str, dict[str, Any]]] = []
    for b in bases:
        for path in _paths(b.message):
            name = ".".join(map(str, path))
            mutations.append((b.queryable, f"delete {b.name}.{name}", _set(b.message, path, None, delete=True)))
            for v in WRONG_VALUES:
                mutations.append((b.queryable, f"type {b.name}.{name}={type(v).__name__}", _set(b.message, path, v)))
        for extra in (
            {"v": [2, 0]},
            {"v": [1]},
            {"v": "1.1"},
            {"v": [1, 256]},
            {"rid": -1},
            {"rid": 2**64},
            {"unknown": [1] * 10},
            {"client": "../../x"},
            {"cloth": "*"},
            {"token": "A" * 32},
        ):
            mutations.append((b.queryable, f"value {b.name}.{list(extra)[0]}", {**b.message, **extra}))
    order = rng.permutation(len(mutations))
    mi = 0
    huge_every = 50
    for i in range(count):
        q = QUERYABLES[i % len(QUERYABLES)]
        r = rng.random()
        if i % huge_every == huge_every - 1:
            kind = ["huge-map", "huge-array", "huge-bin", "claims-more", "over-limit"][(i // huge_every) % 5]
            n = int(rng.integers(1, 5)) * max(1, max_bytes // 40)
            if kind == "huge-map":
                payload = _huge_map(min(n // 12, 400_000))
            elif kind == "huge-array":
                payload = _huge_array(min(n, max_bytes - 8))
            elif kind == "huge-bin":
                mesh = {"vertices": b"\x00" * min(n, max_bytes - 100), "triangles": b""}
                payload = msgpack.packb({"v": [1, 1], "client": client, "mesh": mesh})
            elif kind == "claims-more":
                payload = _claims_more(2**32 - 1)
            else:
                payload = b"\x00" * (max_bytes + 1)
            yield q, kind, payload
        elif r < 0.45:
            q, kind, m = mutations[order[mi % len(mutations)]]
            mi += 1
            try:
                yield q, kind, msgpack.packb(m)
            except (OverflowError, ValueError, TypeError):  # e.g. 2**64 cannot be packed: send it raw
                yield q, kind + " (unpackable)", msgpack.packb({**m, "v": [1, 1]}, default=str)
        elif r < 0.60:
            b = bases[int(rng.integers(len(bases)))]
            data = msgpack.packb(b.message)
            yield b.queryable, "truncated", data[: int(rng.integers(0, len(data)))]
        elif r < 0.70:
            yield q, "random", rng.bytes(int(rng.integers(1, 2048)))
        else:
            j = int(rng.integers(9))
            base = bases[int(rng.integers(len(bases)))]
            good = msgpack.packb(base.message)
            if j == 0:
                yield q, "deep-array", deep(DEPTH, "array")
            elif j == 1:
                yield q, "deep-map", deep(DEPTH, "map")
            elif j == 2:  # a valid envelope with a deep value in a field
                yield base.queryable, "deep-field", _with_raw_field(base.message, "material", deep(DEPTH))
            elif j == 3:
                # {"v": [1, 1], "rid": timestamp ext -1 (96-bit)}
                yield q, "ext", b"\x82\xa1v\x92\x01\x01\xa3rid\xc7\x0c\xff" + b"\x00" * 12
            elif j == 4:  # a str value that is not UTF-8
                yield q, "bad-utf8", b"\x82\xa1v\x92\x01\x01\xa6client\xa4\xff\xfe\xfd\xfc"
            elif j == 5:  # {1: 2, b"v": [1, 1], nil: 0}
                yield q, "non-string-keys", b"\x83\x01\x02\xc4\x01v\x92\x01\x01\xc0\x00"
            elif j == 6:
                yield base.queryable, "trailing", good + b"\x00\x01"
            elif j == 7:
                yield q, "not-a-map", msgpack.packb([base.message, 1, "x"])
            else:
                yield q, "duplicate-keys", b"\x83\xa1v\x92\x01\x01\xa1v\x92\x02\x00\xa3rid\x05"


def _with_raw_field(m: dict[str, Any], key: str, raw: bytes) -> bytes:
    """``m`` encoded with ``key`` mapped to already-encoded msgpack ``raw`` (appended last)."""
    rest = {k: v for k, v in m.items() if k != key}
    packer = msgpack.Packer()
    n = len(rest) + 1
    header = bytes([0x80 | n]) if n < 16 else b"\xde" + n.to_bytes(2, "big")
    return header + b"".join(packer.pack(k) + packer.pack(v) for k, v in rest.items()) + packer.pack(key) + raw


@dataclass
class FuzzCounts:
    sent: int = 0
    outcomes: Counter = field(default_factory=Counter)  # reply outcome (ok / error code / unparseable)
    no_reply: int = 0  # queries answered by nobody (Zenoh timeout)
    internal_kinds: Counter = field(default_factory=Counter)  # message kinds that got `internal`
    by_kind: Counter = field(default_factory=Counter)


def send_all(
    session: zenoh.Session,
    keys: P.Keys,
    server_id: str,
    msgs: Iterator[tuple[str, str, bytes]],
    in_flight: int = 16,
    timeout: float = 30.0,
    deadline_s: float = 600.0,
) -> FuzzCounts:
    """Send every message as a query, at most ``in_flight`` unanswered at once; count the outcomes.
    Stops sending after ``deadline_s`` seconds (what was not sent is not counted as sent)."""
    counts = FuzzCounts()
    lock = threading.Lock()
    slots = threading.BoundedSemaphore(in_flight)
    t_end = time.monotonic() + deadline_s

    for q, kind, payload in msgs:
        if time.monotonic() > t_end:
            log.warning("fuzz: deadline reached after %d messages", counts.sent)
            break
        if not slots.acquire(timeout=timeout + 5):
            log.warning("fuzz: no reply slot freed in %.0f s: the server is stuck", timeout + 5)
            break
        state = {"replied": False}

        def on_reply(reply: zenoh.Reply, kind: str = kind, state: dict = state) -> None:
            outcome = reply_outcome(reply)
            with lock:
                state["replied"] = True
                counts.outcomes[outcome] += 1
                if outcome == "internal":
                    counts.internal_kinds[kind] += 1

        def on_done(state: dict = state) -> None:
            with lock:
                if not state["replied"]:
                    counts.no_reply += 1
            slots.release()

        with lock:
            counts.sent += 1
            counts.by_kind[kind.split(" ")[0]] += 1
        session.get(
            getattr(keys, q)(server_id), zenoh.handlers.Callback(on_reply, on_done), payload=payload, timeout=timeout
        )
    for _ in range(in_flight):  # wait for the last replies
        slots.acquire(timeout=timeout + 5)
    return counts
