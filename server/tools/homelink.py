"""A player on a home link: how many states per second each of its capes gets, how late, and the
longest gap, with the server's states crossing a link shaper (issue 21's player target).

    python -m drape.server.tools.homelink [--rate 20 --delay 20 --capes 16 --encodings quant16,predictive]
        [--client-rate 1|2|3|6|12|auto] [--server-flags="--no-device-encode"]

A ``drape serve`` process (peer, loopback, admission off) and, in this process, a game client in
Zenoh client mode connected to the server only through a :class:`~.shaper.Shaper` (``--rate``
Mbit/s down and up, ``--delay`` ms one way, ``--queue`` KiB): it submits ``--capes`` bundled
32x32 capes with tethers and moves their pins every tick (one moves block, as a game loop does),
for each encoding in turn. Over ``--seconds`` it counts per cape the states received, the latency
of each (receive time minus the server's time: one host clock) and the longest gap between two
received states. Printed and written (``--json``) per encoding, with the link's measured bytes.
``--client-rate`` (protocol 1.8; 1.9: 6 and 12): the player takes every k-th state, or steps
down by itself (``auto``: the rate it ended at and its steps are reported); the server's device
encoder and its host path (``--server-flags=--no-device-encode``) both serve decimated streams.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from .procs import free_port
from .shaper import Shaper

log = logging.getLogger(__name__)


def _serve(port: int, flags: list[str]) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "drape.server.cli", "--log-level", "warning", "serve"]
    cmd += ["--listen", f"tcp/127.0.0.1:{port}", "--server-id", "homelink", "--no-admission", *flags]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL)


def run_one(
    port: int, shaper: Shaper, encoding: str, capes: int, seconds: float, step: float, rate: int | str = 1
) -> dict:
    extra = {"step": step} if encoding == "predictive" else {}
    with tempfile.NamedTemporaryFile("w", suffix=".json5") as zc:
        # no shared memory: on one host Zenoh would hand the states over in it, past the link
        zc.write("{transport: {shared_memory: {enabled: false}}}")
        zc.flush()
        return _measure(shaper, encoding, capes, seconds, extra, zc.name, rate)


def _measure(
    shaper: Shaper, encoding: str, capes: int, seconds: float, extra: dict, zconf: str, rate: int | str = 1
) -> dict:
    from drape.client import DrapeClient

    with DrapeClient(
        shaper.endpoint, mode="client", server_id="homelink", timeout=30.0, zenoh_config_file=zconf, rate=rate
    ) as c:
        handles = [
            c.submit_grid(
                32, 32, 0.6, 1.0, pinned=[0, 31], features=["tethers"], encoding=encoding, bundle=True, **extra
            )
            for _ in range(capes)
        ]
        for h in handles:
            h.next_state(timeout=30.0)
        seen: list[list[tuple[int, int, int]]] = [[] for _ in handles]  # (tick, server ns, receive ns)
        lock = threading.Lock()

        def recorder(i: int):
            def on_state(st):
                if not st.extrapolated:
                    with lock:
                        seen[i].append((st.tick, st.server_time_ns, st.receive_time_ns))

            return on_state

        cancels = [h.on_state(recorder(i)) for i, h in enumerate(handles)]
        rest = np.stack([np.asarray(h.rest_positions, np.float32)[[0, 31]] for h in handles])
        bytes0 = shaper.down.bytes
        t0 = time.monotonic()
        next_t = t0
        while time.monotonic() - t0 < seconds:
            t = time.monotonic() - t0
            moved = rest.copy()
            moved[:, :, 0] += np.float32(0.3 * math.sin(2.0 * t))  # the character runs to and fro
            c.move_pins_many(handles, [0, 31], moved)
            next_t += 1 / 60
            time.sleep(max(0.0, next_t - time.monotonic()))
        elapsed = time.monotonic() - t0
        for cancel in cancels:
            cancel()
        down = shaper.down.bytes - bytes0
        gaps = [h.gaps for h in handles]
        ended_at, steps = c.bundles.rate, (c.bundles.step_downs, c.bundles.step_ups)
    rates, lat, longest, late_end = [], [], [], []
    t_end = max((x[2] for s in seen for x in s), default=0)
    for s in seen:
        ticks = [x for x in s if x[2] - x[1] >= 0]
        rates.append(len(ticks) / elapsed)
        lat += [(r - sv) / 1e6 for _, sv, r in ticks]
        late_end += [(r - sv) / 1e6 for _, sv, r in ticks if r >= t_end - 2e9]  # the last 2 s
        rx = sorted(r for _, _, r in ticks)
        longest.append(max((b - a) / 1e6 for a, b in zip(rx, rx[1:], strict=False)) if len(rx) > 1 else float("inf"))
    a = np.array(lat) if lat else np.array([float("nan")])
    return {
        "encoding": encoding,
        "capes": capes,
        "seconds": round(elapsed, 2),
        "states_per_s_per_cape_min": float(min(rates)),
        "states_per_s_per_cape_mean": float(np.mean(rates)),
        "latency_p50_ms": float(np.percentile(a, 50)),
        "latency_p99_ms": float(np.percentile(a, 99)),
        "latency_p50_last_2s_ms": float(np.percentile(late_end, 50)) if late_end else float("nan"),
        "latency_p99_last_2s_ms": float(np.percentile(late_end, 99)) if late_end else float("nan"),
        "link_peak_queue_kib": shaper.down.peak_queue / 1024,
        "longest_gap_ms": float(max(longest)),
        "down_mbit_per_s": down * 8 / elapsed / 1e6,
        "undecodable_states": int(sum(gaps)),
        "client_rate": rate,  # 1.8: what the player asked for
        "rate_at_end": ended_at,  # every k-th state at the end (auto: where it stepped to)
        "step_downs": steps[0],
        "step_ups": steps[1],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=20.0, help="Mbit/s each way")
    ap.add_argument("--delay", type=float, default=20.0, help="ms one way")
    ap.add_argument("--queue", type=int, default=256, help="KiB the link's queue holds")
    ap.add_argument("--capes", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--step", type=float, default=2.0, help="predictive step, mm")
    ap.add_argument("--encodings", default="quant16,predictive")
    ap.add_argument(
        "--client-rate", default="1", help="1.8: every k-th state (1, 2, 3; 1.9: 6, 12) or auto (steps down by itself)"
    )
    ap.add_argument("--server-flags", default="", help="more drape serve flags, space-separated (--no-device-encode)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rate: int | str = args.client_rate if args.client_rate == "auto" else int(args.client_rate)
    logging.basicConfig(level=logging.WARNING)
    port = free_port()
    server = _serve(port, args.server_flags.split())
    out = []
    try:
        deadline = time.monotonic() + 240.0  # a cold kernel build on a loaded 2-core CPU takes minutes
        while True:  # the server listens once it is up (its kernels warmed)
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                break
            except OSError:
                if server.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("the server did not start") from None
                time.sleep(0.2)
        time.sleep(1.0)
        for enc in [e for e in args.encodings.split(",") if e]:
            with Shaper(
                ("127.0.0.1", port), rate_bps=args.rate * 1e6, delay_s=args.delay / 1e3, queue_bytes=args.queue << 10
            ) as shaper:
                r = run_one(port, shaper, enc, args.capes, args.seconds, args.step / 1e3, rate)
            r.update(rate_mbit=args.rate, delay_ms=args.delay, queue_kib=args.queue, load_average=os.getloadavg()[0])
            out.append(r)
            print(
                f"{args.rate:g} Mbit/s, {args.delay:g} ms, {args.capes} capes, {enc:10s}: "
                f"{r['states_per_s_per_cape_min']:5.1f} states/s per cape (least), latency p50 "
                f"{r['latency_p50_ms']:.0f} / p99 {r['latency_p99_ms']:.0f} ms, "
                f"longest gap {r['longest_gap_ms']:.0f} ms, link {r['down_mbit_per_s']:.2f} Mbit/s down, "
                f"rate {rate} (every {r['rate_at_end']} at the end, {r['step_downs']} down / {r['step_ups']} up)"
            )
    finally:
        server.terminate()
        server.wait(30)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
