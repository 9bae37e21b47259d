"""The client's cost of a state bundle, per state: decoding per entry against the whole bundle at
once, and the SDK's whole receive-to-delivery path.

``python -m drape.server.tools.decodebench`` builds bundles of K states (default 256) of S x S
vertices (default 32: draped grids, each somewhere else) with the real encoder
(``encode_state`` + ``encode_bundle``), for each encoding with and without normals, and times in
this process, median microseconds per state over ``--repeat`` bundles after a warm-up (CPU time
of the calling thread; the wall times go to the JSON too):

- ``per-state``: ``parse_bundle`` then ``Bundle.state(i)`` for every entry (decode_state each);
- ``whole``: ``parse_bundle`` then ``Bundle.decode()`` (every entry at once); both keep their
  last two results alive, as the SDK's handles keep their last two states (a result dropped at
  once lets glibc hand its pages back and take page faults for the next: not a client's case);
- ``sdk old``: the SDK's dispatch as it was before the whole-bundle decode (``Bundle.state(i)``
  then ``ClothHandle.deliver`` per entry);
- ``sdk``: what the SDK does with a bundle sample: ``ZBytes.to_bytes()`` then
  :meth:`drape.client.bundles.BundleReceiver.receive` (decode once, deliver to every handle).

The SDK paths run a real :class:`DrapeClient` (a Zenoh session listening on its own loopback port,
no server needed) with K real bundled ClothHandles, ``queue_size=4`` and one ``on_state``
callback each (as ``drape loadtest``'s clients have); the queues are drained between bundles,
outside the timing. Every configuration first checks that the whole-bundle states equal the
per-entry ones bit for bit. ``--json`` writes the figures (docs/results/decodebench-cpu.json).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import socket
import statistics
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from drape.client import DrapeClient
from drape.client import protocol as P
from drape.client.handle import ClothHandle

log = logging.getLogger(__name__)


def make_bundle(rng: np.random.Generator, k: int, side: int, encoding: str, normals: bool) -> bytes:
    """A bundle of ``k`` draped ``side`` x ``side`` grids (each somewhere else), as a server sends it."""
    u = np.linspace(0.0, 1.0, side, dtype=np.float32)
    gx, gz = np.meshgrid(u, u)
    grid = np.stack([gx.ravel(), np.zeros(side * side, np.float32), gz.ravel()], 1)
    states = []
    for i in range(k):
        pos = (grid + rng.normal(0, 0.05, grid.shape) + rng.uniform(-50, 50, 3)).astype(np.float32)
        nrm = None
        if normals:
            m = rng.normal(0, 1, grid.shape)
            nrm = (m / np.linalg.norm(m, axis=1, keepdims=True)).astype(np.float32)
        states.append((f"{i:016x}", P.encode_state(1000, 2000, pos, nrm, encoding)))
    return bytes(P.encode_bundle(1000, 2000, states))


def same_states(a: P.ClothState, b: P.ClothState) -> bool:
    """Every field equal, every array equal bit for bit (dtype, shape and bytes)."""
    for name, x in vars(a).items():
        y = getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (
                isinstance(x, np.ndarray)
                and isinstance(y, np.ndarray)
                and x.dtype == y.dtype
                and x.shape == y.shape
                and x.tobytes() == y.tobytes()
            ):
                return False
        elif x != y:
            return False
    return True


def _medians_us(
    paths: Mapping[str, Callable[[], object]], after: Callable[[], object], repeat: int, warmup: int, k: int
) -> dict[str, float]:
    """Median microseconds per state of each path: the calling thread's CPU time (what the path
    costs a client's cores; waiting for a core on this shared machine is not counted) and, as
    ``<path>_wall``, the wall time (and ``<path>_min``, the fastest of the repeats: what a quiet
    machine gives). Each path runs in two blocks of ``warmup`` + ``repeat / 2`` calls, the paths'
    blocks taking turns (ABCD ABCD: a burst of load falls on all alike, and within a block a path
    is in its steady state: the SDK paths free the states their handles held from their own
    earlier bundles, as a client does); ``after`` runs after each call, untimed."""
    ts: dict[str, list[float]] = {}
    for block in (repeat - repeat // 2, repeat // 2):
        for name, fn in paths.items():
            for r in range(warmup + block):
                w0, c0 = time.perf_counter(), time.thread_time()
                fn()
                c1, w1 = time.thread_time(), time.perf_counter()
                after()
                if r >= warmup:
                    ts.setdefault(name, []).append(c1 - c0)
                    ts.setdefault(name + "_wall", []).append(w1 - w0)
    out = {name: statistics.median(t) * 1e6 / k for name, t in ts.items()}
    out.update({name.replace("_us", "_min_us"): min(t) * 1e6 / k for name, t in ts.items() if "wall" not in name})
    return out


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def ticks_of(ticks: list[int]) -> Callable[[P.ClothState], None]:
    """An on_state callback recording the ticks (what drape loadtest's clients do per state)."""
    return lambda st: ticks.append(st.tick)


def open_client(k: int) -> tuple[DrapeClient, list[ClothHandle], list[list[int]]]:
    """A real client (listening on its own port, no server) with ``k`` bundled handles registered
    as a submission registers them, each with one recording callback."""
    ep = _free_endpoint()
    client = DrapeClient(ep, listen=[ep], timeout=1.0, queue_size=4)
    handles, seen = [], []
    for i in range(k):
        rep = P.SubmitReply(f"{i:016x}", "0" * 32, f"drape/cloth/{i:016x}/state", 0, 0, bundle_key=client.bundle_key)
        h = ClothHandle(client, rep, queue_size=4, server_id="bench")
        ticks: list[int] = []
        h.on_state(ticks_of(ticks))
        with client.cloths.lock:
            client.cloths.add(h)
        handles.append(h)
        seen.append(ticks)
    return client, handles, seen


def run(
    client: DrapeClient,
    handles: list[ClothHandle],
    seen: list[list[int]],
    data: bytes,
    repeat: int,
    warmup: int,
) -> dict[str, Any]:
    """Time the four paths on one bundle payload; per-state medians in microseconds."""
    k = len(handles)
    b = P.parse_bundle(data)
    whole = b.decode(7)
    same = len(whole) == k and all(
        isinstance(s, P.ClothState) and same_states(s, b.state(i, 7)) for i, s in enumerate(whole)
    )
    zb = zenoh.ZBytes(data)
    by_id = {h.id: h for h in handles}

    def drain() -> None:
        for h, ticks in zip(handles, seen, strict=True):
            h.clear()
            ticks.clear()

    held: list[object] = [None, None]  # the decode-only paths hold their last two results, as handles do

    def hold(states: object) -> None:
        held[0], held[1] = held[1], states

    def per_state() -> None:
        bb = P.parse_bundle(data)
        hold([bb.state(i, 7) for i in range(len(bb.entries))])

    def whole_() -> None:
        hold(P.parse_bundle(data).decode(7))

    def sdk_old() -> None:  # the SDK's dispatch before Bundle.decode: a decode and a delivery per entry
        now = time.time_ns()
        bb = P.parse_bundle(zb.to_bytes())
        for i, e in enumerate(bb.entries):
            by_id[e.cloth].deliver(bb.state(i, now))

    def sdk() -> None:
        client.bundles.receive(zb.to_bytes(), time.time_ns())

    before = sum(h.received for h in handles)
    paths = {
        "per_state_us": per_state,
        "whole_us": whole_,
        "sdk_old_us": sdk_old,
        "sdk_us": sdk,
    }
    out: dict[str, Any] = {"bundle_kb": len(data) / 1024, **_medians_us(paths, drain, repeat, warmup, k)}
    out["same"] = bool(same)
    delivered = sum(h.received for h in handles) - before
    if delivered != 2 * (repeat + 2 * warmup) * k:
        raise RuntimeError(f"{delivered} states delivered, {2 * (repeat + 2 * warmup) * k} expected")
    return out


def machine() -> dict[str, Any]:
    return {
        "cpu": platform.processor() or platform.machine(),
        "cpu_model": next(
            (
                line.split(":", 1)[1].strip()
                for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")
            ),
            "",
        )
        if Path("/proc/cpuinfo").exists()
        else "",
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drape.server.tools.decodebench", description=__doc__.splitlines()[0])
    ap.add_argument("--states", type=int, default=256, help="states per bundle (default 256)")
    ap.add_argument("--side", type=int, default=32, help="grid side: side x side vertices per state (default 32)")
    ap.add_argument("--encoding", nargs="+", default=list(P.STATELESS_ENCODINGS), choices=P.STATELESS_ENCODINGS)
    ap.add_argument("--normals", choices=["both", "no", "yes"], default="both", help="states with normals")
    ap.add_argument("--repeat", type=int, default=30, help="timed bundles per path (median)")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None, help="write the figures here (e.g. docs/results/...)")
    args = ap.parse_args(argv)
    if args.repeat < 1 or args.states < 1 or args.side < 1 or args.warmup < 0:
        ap.error("--states, --side and --repeat must be at least 1, --warmup at least 0")
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rng = np.random.default_rng(args.seed)
    k, side = args.states, args.side
    normals = {"both": (False, True), "no": (False,), "yes": (True,)}[args.normals]
    print(
        f"{k} states of {side}x{side} vertices per bundle; median CPU us per state over {args.repeat} bundles "
        f"(sdk: to_bytes + BundleReceiver.receive, {k} handles with a callback each)"
    )
    print(
        f"{'encoding':9} {'normals':7} {'KB':>7} | {'per-state':>9} {'whole':>7} {'ratio':>6} | "
        f"{'sdk old':>8} {'sdk':>7} {'ratio':>6} | same"
    )
    rows = []
    client, handles, seen = open_client(k)
    try:
        for enc in args.encoding:
            for nrm in normals:
                r = run(client, handles, seen, make_bundle(rng, k, side, enc, nrm), args.repeat, args.warmup)
                r.update(encoding=enc, normals=nrm)
                rows.append(r)
                print(
                    f"{enc:9} {'yes' if nrm else 'no':7} {r['bundle_kb']:7.1f} | {r['per_state_us']:9.2f} "
                    f"{r['whole_us']:7.2f} {r['per_state_us'] / r['whole_us']:5.1f}x | {r['sdk_old_us']:8.2f} "
                    f"{r['sdk_us']:7.2f} {r['sdk_old_us'] / r['sdk_us']:5.1f}x | {'yes' if r['same'] else 'NO'}",
                    flush=True,
                )
    finally:
        client.close(remove=False)
    if args.json is not None:
        doc = {
            "command": "python -m drape.server.tools.decodebench " + " ".join(sys.argv[1:] if argv is None else argv),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": machine(),
            "states": k,
            "side": side,
            "repeat": args.repeat,
            "unit": "microseconds per state, median over the repeats: CPU time of the calling thread "
            "(*_wall: wall time)",
            "results": rows,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0 if all(r["same"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
