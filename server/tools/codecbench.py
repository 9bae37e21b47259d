"""Bits per vertex of the predictive state encoding (protocol 1.5) over recorded cloth motions.

    python -m drape.server.tools.codecbench [--record] [--steps 0.25,0.5,1,2,4] [--out docs/results]
    python -m drape.server.tools.codecbench --decode-only --out /tmp   # the client's decode cost

The motions are kept in ``tests/data/motions/*.npz`` (float32 positions, (states, n, 3), 60 Hz):
a cape whose character runs, turns and stops; a flag in gusting wind; a curtain pushed by a
capsule; a cloth at rest. ``--record`` simulates them anew with the OpenCL world (the solver
the server runs; 32x32 grids, bending, tethers, 10 iterations). Each motion is then coded as one
stream: a keyframe, then states predicted from the last two the decoder rebuilt (the codec's
own decoder runs, so the figures are of what a client decodes), for each step (millimetres).
Printed and written: mean bits per vertex per state (predicted states, keyframes and all), the
largest error against the float32 positions (never above half a step), keyframes' size, and a
plot of bits against step (``codec-bits.png``). Also the order-0 entropy of the symbols, the
bound a better entropy coder could approach.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from drape.client.protocol import predictive as P

log = logging.getLogger(__name__)

MOTIONS_DIR = Path(__file__).resolve().parents[2] / "tests" / "data" / "motions"
MOTIONS = ("cape_run", "flag_gust", "curtain_push", "rest")
STATES = 240  # 4 s at 60 Hz
HZ = 60.0
KEYFRAME_INTERVAL = 60  # the server's default: one intra-coded state a second


def _record(name: str, device: str | None = None) -> np.ndarray:
    """Simulate one motion: (STATES, 1024, 3) float32."""
    from ..sim import make_world
    from ..sim.fabric import cook_grid
    from ..sim.params import Capsule, ClothParams, Features, LinkOptions, pack_colliders

    cols = rows = 32
    world = make_world("workgroup", device=device)
    dt = 1.0 / HZ
    opts = LinkOptions(bending=True)
    out = np.empty((STATES, cols * rows, 3), np.float32)
    if name == "cape_run":
        w, h = 0.6, 1.0
        pins = list(range(cols))  # the whole top edge, on the shoulders
        fab = cook_grid(cols, rows, w, h, opts, pins, orientation="vertical", origin=(-w / 2, 1.5, 0.0))
        hd = world.add(fab, ClothParams(features=Features(tethers=True)))
        top = fab.rest_positions[pins]
        pos, heading, speed = np.zeros(3), 0.0, 0.0
        warm = 60
        for t in range(warm + STATES):
            s = (t - warm) * dt
            if s < 1.5:  # run up to 5 m/s
                speed = min(5.0, speed + 6.0 * dt)
            elif s < 3.0:  # turn left at speed
                heading += 1.6 * dt
            else:  # stop
                speed = max(0.0, speed - 8.0 * dt)
            if t >= warm:
                pos += speed * dt * np.array([math.sin(heading), 0.0, math.cos(heading)])
            c, sn = math.cos(heading), math.sin(heading)
            rot = np.array([[c, 0, sn], [0, 1, 0], [-sn, 0, c]])
            bob = 0.03 * math.sin(2 * math.pi * 2.5 * s) * (speed / 5.0) if t >= warm else 0.0
            tgt = top @ rot.T + pos + np.array([0.0, bob, 0.0])
            world.set_pin_targets(hd, np.array(pins), tgt)
            world.step(dt)
            if t >= warm:
                out[t - warm] = world.fetch().xyz
    elif name == "flag_gust":
        w, h = 1.2, 0.8
        pins = [r * cols for r in range(rows)]  # the left edge, on the pole
        fab = cook_grid(cols, rows, w, h, opts, pins, orientation="vertical", origin=(0.0, 2.0, 0.0))
        rng = np.random.default_rng(7)
        params = ClothParams(features=Features(tethers=True, wind=True))
        hd = world.add(fab, params)
        gust = 0.0
        for t in range(60 + STATES):
            gust = 0.97 * gust + 0.03 * rng.uniform(0, 2)
            wind = (6.0 + 8.0 * gust, 0.0, 2.0 * math.sin(t * dt * 1.3))
            world.set_params(hd, params.with_(wind=wind))
            world.step(dt)
            if t >= 60:
                out[t - 60] = world.fetch().xyz
    elif name == "curtain_push":
        w, h = 1.5, 1.5
        pins = list(range(cols))
        fab = cook_grid(cols, rows, w, h, opts, pins, orientation="vertical", origin=(-w / 2, 2.0, 0.0))
        hd = world.add(fab, ClothParams(features=Features(tethers=True, colliders=True)))
        for t in range(60 + STATES):
            s = max(0.0, (t - 60) * dt)
            x = -1.2 + 1.0 * s if s < 2.4 else 1.2 - 1.0 * (s - 2.4)  # across and back at 1 m/s
            z = 0.25 * math.sin(s * 1.1)  # through the curtain's plane, in and out
            world.set_colliders(hd, pack_colliders([Capsule((x, 0.3, z), (x, 1.5, z), 0.15)]))
            world.step(dt)
            if t >= 60:
                out[t - 60] = world.fetch().xyz
    elif name == "rest":
        w, h = 1.0, 1.0
        pins = [0, cols - 1]
        fab = cook_grid(cols, rows, w, h, opts, pins, orientation="vertical", origin=(-w / 2, 2.0, 0.0))
        hd = world.add(fab, ClothParams(features=Features(tethers=True)))
        for t in range(240 + STATES):  # 4 s to settle, then recorded
            world.step(dt)
            if t >= 240:
                out[t - 240] = world.fetch().xyz
    else:
        raise ValueError(f"unknown motion {name!r}; choose from {MOTIONS}")
    world.close()
    if not np.isfinite(out).all():
        raise RuntimeError(f"motion {name}: non-finite positions")
    return out


def record(device: str | None = None) -> None:
    MOTIONS_DIR.mkdir(parents=True, exist_ok=True)
    for name in MOTIONS:
        t0 = time.perf_counter()
        x = _record(name, device)
        np.savez_compressed(MOTIONS_DIR / f"{name}.npz", positions=x, hz=HZ)
        log.info("recorded %s: %d states of %d vertices in %.1f s", name, len(x), x.shape[1], time.perf_counter() - t0)


def load(name: str) -> np.ndarray:
    with np.load(MOTIONS_DIR / f"{name}.npz") as z:
        return np.asarray(z["positions"], np.float32)


def _entropy_bits(z: np.ndarray) -> float:
    """Order-0 entropy of the symbols, bits in all."""
    _, counts = np.unique(z, return_counts=True)
    p = counts / counts.sum()
    return float(-(counts * np.log2(p)).sum())


def code_motion(x: np.ndarray, step: float, keyframe_interval: int = KEYFRAME_INTERVAL) -> dict:
    """Code one motion as a stream; figures of what the decoder rebuilt."""
    enc, dec = P.History(), P.History()
    n = x.shape[1]
    total = key_bytes = keys = 0
    entropy = 0.0
    max_err = 0.0
    for t, pos in enumerate(x):
        keyframe = t % keyframe_interval == 0
        q = P.quantise(pos, step)
        order = P.ORDER_INTRA if keyframe else enc.order()
        entropy += _entropy_bits(P.symbols(q, P.prediction(order, enc.q1, enc.q2, q.shape)))
        data, order, _, _ = P.encode_step(pos, step, enc, t, keyframe)
        got, size = P.decode_step(data, n, step, order, dec, t)
        assert size == len(data)
        max_err = max(max_err, float(np.abs(got - pos).max()))
        total += len(data)
        if keyframe:
            key_bytes += len(data)
            keys += 1
    states = len(x)
    return {
        "step_mm": step * 1e3,
        "bits_per_vertex": 8 * total / (states * n),
        "bits_per_vertex_predicted": 8 * (total - key_bytes) / ((states - keys) * n),
        "keyframe_bits_per_vertex": 8 * key_bytes / (keys * n),
        "entropy_bits_per_vertex": entropy / (states * n),
        "max_error_mm": max_err * 1e3,
        "states": states,
        "vertices": n,
    }


def write_stream(x: np.ndarray, step: float, path: Path) -> None:
    """One stream's predictive states as a server publishes them (a keyframe a second), each
    prefixed by its length (u32, little-endian)."""
    import struct

    from drape.client import protocol as Q

    h = P.History()
    with open(path, "wb") as f:
        for t, pos in enumerate(x):
            st = bytes(Q.encode_predictive_state(t + 1, 0, pos, step, h, t % KEYFRAME_INTERVAL == 0))
            f.write(struct.pack("<I", len(st)) + st)


def decode_speed(x: np.ndarray, step: float, cloths: int = 64, rounds: int = 30) -> dict:
    """Client decode cost of a bundle of ``cloths`` predictive 32x32 states (the cape motion, each
    cloth at another phase, a keyframe a second), ns per vertex, two ways: ``codec``, through
    protocol.decode_predictive_many as the SDK's bundle receiver runs it, and ``sdk``, the SDK's
    whole receive path (:meth:`drape.client.bundles.BundleReceiver.receive` of a real client with
    ``cloths`` bundled handles, one recording callback each, as ``drape loadtest``'s clients).
    CPU time of the calling thread (waiting for a core on a shared machine is not counted):
    median and min over ``rounds`` bundles, after a warm-up."""
    from drape.client import protocol as Q

    from .decodebench import open_client

    n = x.shape[1]
    enc = [P.History() for _ in range(cloths)]
    dec = [Q.StateStream(f"{i:016x}") for i in range(cloths)]
    warm = 3
    bundles = []
    for t in range(2 * (rounds + warm)):
        states = [
            (
                f"{i:016x}",
                Q.encode_predictive_state(t, 0, x[(t + 7 * i) % len(x)], step, enc[i], t % KEYFRAME_INTERVAL == 0),
            )
            for i in range(cloths)
        ]
        bundles.append(bytes(Q.encode_bundle(t, 0, states)))
    times: dict[str, list[float]] = {"codec": [], "sdk": []}
    for t, data in enumerate(bundles[: rounds + warm]):
        b = Q.parse_bundle(data)
        offsets = [e.offset for e in b.entries]
        t0 = time.thread_time()
        got = Q.decode_predictive_many(data, offsets, dec)
        dt = time.thread_time() - t0
        assert all(g is not None for g in got)
        if t >= warm:
            times["codec"].append(dt)
    client, handles, seen = open_client(cloths)
    try:
        for t, data in enumerate(bundles):  # the same bundles from the start: the handles' streams are fresh
            t0 = time.thread_time()
            client.bundles.receive(data, time.time_ns())
            dt = time.thread_time() - t0
            if t >= warm and t < rounds + warm:
                times["sdk"].append(dt)
            for h, s in zip(handles, seen, strict=True):
                h.clear()
                s.clear()
        assert all(h.stream.undecodable == 0 and h.received == len(bundles) for h in handles)
    finally:
        client.close(remove=False)
    per = cloths * n / 1e9
    out: dict = {"cloths": cloths, "vertices": n, "step_mm": step * 1e3, "rounds": rounds, "clock": "thread CPU time"}
    for name, ts in times.items():
        out[f"{name}_ns_per_vertex"] = float(np.median(ts)) / per
        out[f"{name}_ns_per_vertex_min"] = float(np.min(ts)) / per
    out["ns_per_vertex"] = out["codec_ns_per_vertex"]
    return out


def _decode_report() -> dict:
    """Time the decode (:func:`decode_speed`), print it, return it with the machine's load."""
    d = decode_speed(load("cape_run"), 0.002)
    la = os.getloadavg()[0]
    for name, what in (("codec", "decode_predictive_many"), ("sdk", "BundleReceiver.receive")):
        print(
            f"decode of a {d['cloths']}-cloth bundle of {d['vertices']} vertices, {what}: "
            f"{d[name + '_ns_per_vertex']:.1f} ns per vertex (median; min {d[name + '_ns_per_vertex_min']:.1f}; "
            f"CPU time; load average {la:.1f} on {os.cpu_count()} cores)"
        )
    return {**d, "load_average": la}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--record", action="store_true", help="simulate the motions anew (OpenCL world)")
    ap.add_argument("--device", default=None, help="OpenCL device for --record (env DRAPE_DEVICE)")
    ap.add_argument("--steps", default="0.25,0.5,1,2,4", help="steps in millimetres, comma separated")
    ap.add_argument("--out", default="docs/results", help="folder for codec-bits.json and codec-bits.png")
    ap.add_argument(
        "--decode",
        action="store_true",
        help="also time the client's decode of a 64-cloth bundle (the codec, the SDK's receive path)",
    )
    ap.add_argument(
        "--decode-only",
        action="store_true",
        help="time only the decode (no bits over the motions); writes codec-decode.json to --out",
    )
    ap.add_argument(
        "--stream",
        default=None,
        help="write the cape motion's predictive states (step 2 mm) to FILE, each "
        "prefixed by its u32 length (client/rust/examples/predictive_bench.rs reads it), and stop",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.stream:
        write_stream(load("cape_run"), 0.002, Path(args.stream))
        return 0
    if args.decode_only:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        doc = {
            "command": "python -m drape.server.tools.codecbench "
            + " ".join(argv if argv is not None else sys.argv[1:]),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "cores": os.cpu_count(),
            **_decode_report(),
        }
        (out / "codec-decode.json").write_text(json.dumps(doc, indent=1) + "\n")
        return 0
    if args.record or not all((MOTIONS_DIR / f"{m}.npz").exists() for m in MOTIONS):
        record(args.device)
    steps = [float(s) / 1e3 for s in args.steps.split(",")]
    rows = []
    for name in MOTIONS:
        x = load(name)
        for step in steps:
            r = {"motion": name, **code_motion(x, step)}
            rows.append(r)
            print(
                f"{name:13s} step {r['step_mm']:5.2f} mm: {r['bits_per_vertex']:5.2f} bits/vertex "
                f"(predicted {r['bits_per_vertex_predicted']:5.2f}, keyframes {r['keyframe_bits_per_vertex']:5.2f}, "
                f"entropy {r['entropy_bits_per_vertex']:5.2f}), max error {r['max_error_mm']:.3f} mm"
            )
    print("mean over the motions:")
    summary = []
    for step in steps:
        sel = [r for r in rows if abs(r["step_mm"] - step * 1e3) < 1e-9]
        s = {
            "step_mm": step * 1e3,
            "max_error_mm": max(r["max_error_mm"] for r in sel),
            **{k: float(np.mean([r[k] for r in sel])) for k in ("bits_per_vertex", "entropy_bits_per_vertex")},
        }
        summary.append(s)
        print(
            f"  step {s['step_mm']:5.2f} mm: {s['bits_per_vertex']:5.2f} bits/vertex "
            f"(entropy {s['entropy_bits_per_vertex']:5.2f}), max error {s['max_error_mm']:.3f} mm"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"keyframe_interval": KEYFRAME_INTERVAL, "motions": rows, "mean": summary}
    if args.decode:
        report["decode"] = _decode_report()
    (out / "codec-bits.json").write_text(json.dumps(report, indent=1) + "\n")
    _plot(rows, summary, out / "codec-bits.png")
    return 0


def _plot(rows: list[dict], summary: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    for name in MOTIONS:
        sel = [r for r in rows if r["motion"] == name]
        ax.plot([r["step_mm"] for r in sel], [r["bits_per_vertex"] for r in sel], "o-", lw=1.2, label=name)
    ax.plot(
        [s["step_mm"] for s in summary], [s["bits_per_vertex"] for s in summary], "k-", lw=2.5, label="mean (packed)"
    )
    ax.plot(
        [s["step_mm"] for s in summary],
        [s["entropy_bits_per_vertex"] for s in summary],
        "k--",
        lw=1.2,
        label="mean, order-0 entropy",
    )
    from matplotlib.ticker import FixedLocator, ScalarFormatter

    ax.axhline(10, color="tab:red", lw=0.8, ls=":")
    ax.text(2.05, 10.4, "target: 10 bits at 1 mm error", color="tab:red", fontsize=8, ha="right")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log", base=2)
    ax.set_ylim(0.7, 20)
    for axis, ticks in ((ax.xaxis, [0.25, 0.5, 1, 2, 4]), (ax.yaxis, [1, 2, 4, 6, 8, 10, 16])):
        axis.set_major_locator(FixedLocator(ticks))
        axis.set_major_formatter(ScalarFormatter())
        axis.set_minor_locator(FixedLocator([]))
    ax.set_xlabel("step (mm); largest error = step / 2")
    ax.set_ylabel("bits per vertex per state (quant16: 48)")
    ax.set_title("Predictive states over recorded motions\n32x32 at 60 Hz, a keyframe a second", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="center right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
