"""``python -m drape.server.tools.putbench``: what the publisher's puts cost under each heap setting.

The publisher copies each publication out of the pinned frame (``bytes(view)``) and puts it; at
4096 quant16 cloths that is 16 bundles of about 1.5 MB a tick. Whether those copies reuse heap
pages or fault in fresh ones every tick is decided by glibc's mmap and trim thresholds, which
``drape serve`` sets (``malloc_mmap_threshold``, drape.server.service.process.memory). This benchmark puts
``--messages`` payloads of ``--mb`` MB per tick at ``--rate`` Hz over real Zenoh on loopback to a
subscriber process, once per setting, each in a fresh process (mallopt cannot be undone), and
prints the median and mean put time per tick (``--copies-only``: the ``bytes(view)`` copies alone,
no Zenoh: the allocator's share):

- ``glibc``: glibc's own dynamic thresholds;
- ``mmap``: the mmap threshold fixed at 4 MiB alone (which pins the trim threshold at 128 KiB);
- ``drape``: what ``drape serve`` sets (memory.set_mmap_threshold: both thresholds).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SETTINGS = ("glibc", "mmap", "drape")


def _subscriber(endpoint: str, seconds: float) -> None:
    import zenoh

    from drape.client.session import zenoh_config

    got = [0]
    with zenoh.open(zenoh_config("peer", connect=[endpoint])) as s:
        s.declare_subscriber("putbench/**", lambda smp: got.__setitem__(0, got[0] + len(smp.payload.to_bytes())))
        time.sleep(seconds)
    print(json.dumps({"received_mb": got[0] / 1e6}), flush=True)
    os._exit(0)  # the session's threads need not be joined


def _publisher(setting: str, endpoint: str, args: argparse.Namespace) -> dict[str, float]:
    import zenoh

    from drape.client.session import zenoh_config
    from drape.server.service.process.memory import M_MMAP_THRESHOLD, mallopt, set_mmap_threshold

    if setting == "mmap":
        mallopt(M_MMAP_THRESHOLD, 4 << 20)  # alone: the trim threshold pinned
    elif setting == "drape":
        set_mmap_threshold(4 << 20)
    size = int(args.mb * 1e6)
    frame = np.random.default_rng(0).integers(0, 255, args.messages * size, np.uint8)
    if args.copies_only:
        ticks: list[float] = []
        keep: list[bytes] = []
        for _ in range(int(args.seconds * args.rate)):
            t = time.perf_counter()
            view = memoryview(frame)
            copies = [bytes(view[i * size : (i + 1) * size]) for i in range(args.messages)]
            keep.append(bytes(64))  # something small allocated after them, as a tick does
            del copies
            ticks.append(time.perf_counter() - t)
        cms = np.asarray(ticks) * 1e3
        return {"median_ms": float(np.median(cms)), "mean_ms": float(cms.mean()), "ticks": len(cms)}
    with zenoh.open(zenoh_config("peer", listen=[endpoint])) as s:
        pubs = [s.declare_publisher(f"putbench/{i}") for i in range(args.messages)]
        sub = subprocess.Popen(
            [sys.executable, "-m", __spec__.name, "--subscriber", endpoint, "--seconds", str(args.seconds + 3)]
        )
        time.sleep(2.0)  # the subscriber connected
        per_tick: list[float] = []
        period, t_end = 1.0 / args.rate, time.monotonic() + args.seconds
        while time.monotonic() < t_end:
            t = time.perf_counter()
            view = memoryview(frame)
            for i, pub in enumerate(pubs):
                pub.put(bytes(view[i * size : (i + 1) * size]))  # as the publisher does
            per_tick.append(time.perf_counter() - t)
            time.sleep(max(0.0, period - per_tick[-1]))
        sub.wait()
    ms = np.asarray(per_tick) * 1e3
    return {"median_ms": float(np.median(ms)), "mean_ms": float(ms.mean()), "ticks": len(ms)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=16, help="puts per tick (default 16: one per client)")
    ap.add_argument("--mb", type=float, default=1.5, help="MB per put (default 1.5: 256 quant16 32x32 states)")
    ap.add_argument("--rate", type=float, default=60.0)
    ap.add_argument("--seconds", type=float, default=5.0, help="per setting and round")
    ap.add_argument("--rounds", type=int, default=2, help="every setting this many times, interleaved")
    ap.add_argument("--copies-only", action="store_true", help="time the payload copies alone (no Zenoh)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--subscriber", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--setting", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.subscriber:
        _subscriber(args.subscriber, args.seconds)
    from .procs import free_port

    if args.setting:  # one setting in this fresh process
        print(json.dumps(_publisher(args.setting, f"tcp/127.0.0.1:{free_port()}", args)), flush=True)
        os._exit(0)
    results: dict[str, list[dict[str, float]]] = {s: [] for s in SETTINGS}
    for _ in range(args.rounds):
        for setting in SETTINGS:
            cmd = [sys.executable, "-m", __spec__.name, "--setting", setting]
            cmd += ["--messages", str(args.messages), "--mb", str(args.mb), "--rate", str(args.rate)]
            cmd += ["--copies-only"] if args.copies_only else []
            out = subprocess.run([*cmd, "--seconds", str(args.seconds)], capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            results[setting].append(r)
            what = "copies" if args.copies_only else "puts"
            print(f"{setting:6s} {what} per tick: median {r['median_ms']:.2f} ms, mean {r['mean_ms']:.2f} ms")
    base = float(np.median([r["median_ms"] for r in results["glibc"]]))
    for setting in SETTINGS:
        med = float(np.median([r["median_ms"] for r in results[setting]]))
        print(
            f"{setting:6s} median of rounds {med:.2f} ms per tick of {args.messages} x {args.mb:g} MB "
            f"({med / base:.2f}x glibc)"
        )
    if args.json:
        run_args = {k: v for k, v in vars(args).items() if k not in ("json", "subscriber", "setting")}
        args.json.write_text(json.dumps({"args": run_args, "results": results}, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
