"""Input latency: from a pin move sent to the first state that shows it, with and without the
server's pipeline (setting ``pipeline``).

    python -m drape.server.tools.latencybench [--samples 200] [--json docs/results/latency-cpu.json]

For each setting a server runs in this process (real Zenoh on loopback, the OpenCL device Drape
chooses) and a game client moves a pinned vertex of a small cloth to a new place, once every
60-110 ms (so that the moves fall at every phase of a tick), without waiting for the reply, as a
game loop does; the latency of a move is the receive time of the first state in which that
vertex stands at its new place minus the time the move was sent (one host clock). Printed and
written: p50, p90, p99 and max in milliseconds and in ticks, per setting.

With the pipeline the device steps tick N + 1 while the publisher sends tick N, so a move
applied before tick N + 1 shows in a state published a tick later; without it each tick is read
back and published in the tick that stepped it."""

from __future__ import annotations

import argparse
import json
import logging
import random
import socket
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def measure(pipeline: bool, samples: int, tick_rate: float = 60.0, device: str | None = None) -> dict:
    """Input latencies of ``samples`` moves against a server with ``pipeline`` on or off."""
    from drape.client import DrapeClient

    from ..service.config import ServerConfig
    from ..service.server import Server

    ep = f"tcp/127.0.0.1:{_port()}"
    cfg = ServerConfig(
        listen=[ep], server_id=f"latency-{int(pipeline)}", tick_rate=tick_rate, pipeline=pipeline, device=device
    ).validate()
    lat_ms: list[float] = []
    with Server(cfg) as srv, DrapeClient(ep, server_id=srv.server_id, timeout=10.0) as client:
        with client.submit_grid(8, 8, 0.5, 0.5, pinned=[0, 7]) as cape:
            for _ in range(10):
                cape.next_state(timeout=10.0)
            rng = random.Random(1)
            for k in range(samples):
                x = 1.0 + 0.001 * (k % 500)  # a new place each move: no earlier state shows it
                target = np.array([[x, 0.25, -0.1]], np.float32)
                sent = time.time_ns()
                cape.move_pins([0], target, wait=False)
                deadline = time.monotonic() + 2.0
                while time.monotonic() < deadline:
                    st = cape.next_state(timeout=2.0)
                    if np.allclose(st.positions[0], target[0], atol=1e-5):
                        lat_ms.append((st.receive_time_ns - sent) / 1e6)
                        break
                time.sleep(rng.uniform(0.06, 0.11))
    a = np.array(lat_ms)
    tick_ms = 1e3 / tick_rate
    pct = {f"p{q}_ms": float(np.percentile(a, q)) for q in (50, 90, 99)}
    return {
        "pipeline": pipeline,
        "samples": len(a),
        "tick_ms": tick_ms,
        **pct,
        "max_ms": float(a.max()),
        **{k.replace("_ms", "_ticks"): v / tick_ms for k, v in pct.items()},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=200)
    ap.add_argument("--tick-rate", type=float, default=60.0)
    ap.add_argument("--device", default=None, help="OpenCL device (env DRAPE_DEVICE)")
    ap.add_argument("--json", default=None, help="write the figures here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import os

    out = []
    for pipeline in (True, False):
        r = measure(pipeline, args.samples, args.tick_rate, args.device)
        r["load_average"] = os.getloadavg()[0]
        out.append(r)
        print(
            f"pipeline {'on ' if pipeline else 'off'}: input latency p50 {r['p50_ms']:.1f} ms "
            f"({r['p50_ticks']:.2f} ticks), p90 {r['p90_ms']:.1f}, p99 {r['p99_ms']:.1f} ms "
            f"({r['p99_ticks']:.2f} ticks), max {r['max_ms']:.1f} ms over {r['samples']} moves "
            f"(load average {r['load_average']:.1f})"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
