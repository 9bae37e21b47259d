"""Encoding cost per frame: the host path against the frame encoded on the device.

``python -m drape.server.tools.encodebench --cloths 4096`` builds N cloths of S x S vertices in
one float4 device buffer (as the world holds them) and, for each encoding, times per frame:

- host: read the float4 positions back (one copy), gather every cloth's xyz back to back (what
  the tick loop hands the publisher), then :class:`drape.server.sim.statecodec.FrameEncoder`
  writes every publication into its own reused ``bytearray``;
- device: :class:`drape.server.sim.opencl.encode.DeviceEncoder`: one launch and one copy of the
  packed frame into pinned host memory, then one ``bytes`` per publication (as the service's
  publisher puts them).

Medians over ``--repeat`` frames after a warm-up; the first frame of both paths is compared byte
for byte. ``--bundle B`` puts B cloths in each bundle (0: every cloth on its own key).

``--encoding predictive`` (protocol 1.5, ``--step`` metres): the cloths sway (a smooth motion, a
new position upload before each frame, not timed) and both paths code every frame against their
streams: the host's FrameEncoder with its PredictiveStreams, the device's encoder with
devstreams.DeviceStreams' decisions (a keyframe every ``--keyframe-interval`` frames) and the
frame compacted on the device (kernels/compact.cl) before its copy. Every warm-up frame and the
first timed one are compared byte for byte; ``wire MB`` is what goes out, ``read MB`` what the
device path copies to the host.

The device path's columns: ``device`` its wall time per frame (everything below), of which
``wait`` waiting for the device (on a GPU: the kernels and the copy, which overlap nothing here);
``host`` its host share without the payloads' copies (the streams' decisions, the enqueues, the
frame's index and sizes), ``bytes`` one ``bytes`` per publication; ``kernel``, ``compact`` (the
two compaction launches) and ``copy`` (the copy to the host) from the queue's profiling.
``--no-host`` skips the host path (and the byte comparison). The process's heap is set as
``drape serve`` sets it (``malloc_mmap_threshold``: a tick's payload copies are not given back to
the OS and faulted in again every frame).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time

import numpy as np
import pyopencl as cl

from drape.client import protocol as P

from ..service.config import ServerConfig
from ..service.process.memory import configure_heap
from ..sim.opencl.buffers import map_pinned
from ..sim.opencl.device import Device
from ..sim.opencl.devstreams import DeviceStreams
from ..sim.opencl.encode import ClothEntry, DeviceEncoder, FramePlan, Publication
from ..sim.statecodec import FrameEncoder, PredictiveStreams

log = logging.getLogger(__name__)

ENCODINGS = {
    "float32": P.ENC_FLOAT32,
    "float16": P.ENC_FLOAT16,
    "quant16": P.ENC_QUANT16,
    "predictive": P.ENC_PREDICTIVE,
}


def _sway(pos: np.ndarray, frame: int) -> np.ndarray:
    """The world's positions at ``frame``: every vertex swaying smoothly (up to 5 cm a frame,
    with a phase along the cloth), as a cape on a running character moves."""
    out = pos.copy()
    t = 0.1 * frame
    phase = np.arange(len(pos), dtype=np.float32) * np.float32(0.01)
    out[:, 0] += np.float32(0.5) * np.sin(t + phase)
    out[:, 1] += np.float32(0.2) * np.sin(0.7 * t + 2 * phase)
    return out


def _world(rng: np.random.Generator, cloths: int, side: int) -> tuple[np.ndarray, np.ndarray]:
    """float4 positions (draped grids, each somewhere else) and unit normals of every cloth."""
    u = np.linspace(0.0, 1.0, side, dtype=np.float32)
    gx, gz = np.meshgrid(u, u)
    grid = np.stack([gx.ravel(), np.zeros(side * side, np.float32), gz.ravel()], 1)
    pos = np.zeros((cloths * side * side, 4), np.float32)
    for c in range(cloths):
        sl = slice(c * side * side, (c + 1) * side * side)
        pos[sl, :3] = grid + rng.normal(0, 0.05, grid.shape) + rng.uniform(-50, 50, 3)
    pos[:, 3] = 1.0
    nrm = np.zeros_like(pos)
    m = rng.normal(0, 1, (len(pos), 3))
    nrm[:, :3] = m / np.linalg.norm(m, axis=1, keepdims=True)
    return pos, nrm


def _publications(n: int, bundle: int) -> list[Publication]:
    if bundle <= 0:
        return [Publication(f"drape/cloth/c{i}/state", (i,)) for i in range(n)]
    return [
        Publication(f"drape/client/k{j}/states", tuple(range(s, min(n, s + bundle))), bundle=True)
        for j, s in enumerate(range(0, n, bundle))
    ]


class HostPath:
    """What the service does today: readback, gather, FrameEncoder into per-key bytearrays."""

    def __init__(
        self,
        dev: Device,
        pos_buf: cl.Buffer,
        plan: FramePlan,
        side: int,
        nrm_host: np.ndarray | None,
        keyframe_interval: int = 60,
    ):
        self.dev, self.pos_buf, self.plan = dev, pos_buf, plan
        self.k, self.nv = len(plan.cloths), side * side
        # pinned host memory, as the world reads frames back into
        self._pinned, self.host = map_pinned(dev, (self.k * self.nv, 4), np.float32)
        self.offsets = np.arange(self.k + 1, dtype=np.int64) * self.nv
        self.encoder = FrameEncoder(streams=PredictiveStreams(keyframe_interval))
        self.ids = [c.cloth for c in plan.cloths]
        self.steps = [c.step for c in plan.cloths]
        self.bufs = [bytearray(int(s)) for s in plan.pub_size.tolist()]
        self.nrm = [
            None if nrm_host is None else nrm_host[i * self.nv : (i + 1) * self.nv, :3].copy() for i in range(self.k)
        ]
        self.encs = [c.encoding for c in plan.cloths]
        self.parts: dict[str, list[float]] = {"readback": [], "gather": [], "encode": []}

    def frame(self, tick: int, time_ns: int) -> list[bytearray]:
        t0 = time.perf_counter()
        cl.enqueue_copy(self.dev.queue, self.host, self.pos_buf, is_blocking=True)
        t1 = time.perf_counter()
        pos = np.concatenate([self.host[i * self.nv : (i + 1) * self.nv, :3] for i in range(self.k)], axis=0)
        t2 = time.perf_counter()
        enc = self.encoder
        enc.begin(tick, time_ns, pos, self.offsets)
        every = list(range(self.k))
        enc.prepare(every, self.encs)
        pred = P.ENC_PREDICTIVE in self.encs
        if pred:  # coded against the streams; sizes then exact (the service's KeyBuffers resize)
            enc.prepare_predictive(every, self.ids, self.encs, self.steps, [0] * self.k)
        for j, pub in enumerate(self.plan.publications):
            buf = self.bufs[j]
            if pub.bundle:
                entries = [(self.plan.cloths[i].cloth, i, self.encs[i], 0, self.nrm[i]) for i in pub.cloths]
                if pred:
                    size = enc.bundle_size([(c, i, e, n is not None) for c, i, e, _, n in entries])
                    if len(buf) != size:
                        buf = self.bufs[j] = bytearray(size)
                enc.write_bundle(buf, entries)
            else:
                i = pub.cloths[0]
                if pred:
                    size = enc.state_size(i, self.encs[i], self.nrm[i] is not None)
                    if len(buf) != size:
                        buf = self.bufs[j] = bytearray(size)
                enc.write_state(buf, 0, i, self.encs[i], 0, self.nrm[i])
        t3 = time.perf_counter()
        for name, dt in zip(self.parts, (t1 - t0, t2 - t1, t3 - t2), strict=True):
            self.parts[name].append(dt)
        return self.bufs


def run(
    encoding: str,
    cloths: int,
    side: int,
    bundle: int,
    normals: bool,
    repeat: int,
    warmup: int,
    dev: Device,
    seed: int = 1,
    local_size: int | None = None,
    step: float = P.DEFAULT_STEP,
    keyframe_interval: int = 60,
    with_host: bool = True,
) -> dict[str, float | bool | None]:
    rng = np.random.default_rng(seed)
    nv = side * side
    pos, nrm = _world(rng, cloths, side)
    pos_buf = cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=pos)
    nrm_buf = cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=nrm)
    encs = [ENCODINGS[encoding]] * cloths if encoding != "mixed" else [i % 3 for i in range(cloths)]
    entries = [ClothEntry(f"c{i:05d}", i * nv, nv, encs[i], normals, step) for i in range(cloths)]
    plan = FramePlan.build(entries, _publications(cloths, bundle))
    predictive = bool(plan.predictive.any())
    host = HostPath(dev, pos_buf, plan, side, nrm if normals else None, keyframe_interval) if with_host else None
    pq = cl.CommandQueue(dev.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
    denc = DeviceEncoder(dev, local_size=local_size)
    denc.set_plan(plan)
    streams = DeviceStreams(keyframe_interval)
    streams.follow(plan)
    every = list(range(len(plan.publications)))
    flags = np.zeros(cloths, np.uint16)
    host_t: list[float] = []
    dev_t: list[float] = []
    wait_t: list[float] = []
    share_t: list[float] = []
    bytes_t: list[float] = []
    compact_t: list[float] = []
    read: list[int] = []
    kern_t: list[float] = []
    copy_t: list[float] = []
    wire: list[int] = []
    same = True
    for f in range(warmup + repeat):
        if predictive:  # a motion to predict: new positions (not timed)
            cl.enqueue_copy(dev.queue, pos_buf, _sway(pos, f), is_blocking=True)
        t0 = time.perf_counter()
        hb = host.frame(f, 1000 + f) if host is not None else None
        t1 = time.perf_counter()
        pred = streams.decide(f, flags)[0] if predictive else None
        copy_ev = denc.encode(pq, pos_buf, nrm_buf if normals else None, f, 1000 + f, flags, predictive=pred)
        ta = time.perf_counter()
        copy_ev.wait()
        tb = time.perf_counter()
        frame = denc.hold()  # a compacted frame's index read (and the rest of its bytes, if any)
        frame.sizes()  # what the publisher asks first
        tc = time.perf_counter()
        views: list = [b for _, b in frame.payloads(every)]
        frame.release()
        if predictive:  # every state put, as the publisher tells the streams (else they keyframe on)
            streams.put(plan, np.flatnonzero(plan.predictive), f)
        t2 = time.perf_counter()
        if f <= (warmup if predictive else 0) and hb is not None:
            differ = sum(bytes(a) != bytes(b) for a, b in zip(hb, views, strict=True))
            same = same and differ == 0
            if differ:
                log.warning("%s: %d of %d publications differ between host and device", encoding, differ, len(hb))
        wire.append(sum(len(v) for v in views))
        read.append(denc.compactor.copied if predictive else plan.size)
        if f >= warmup:
            host_t.append(t1 - t0)
            dev_t.append(t2 - t1)
            wait_t.append(tb - ta)
            share_t.append((ta - t1) + (tc - tb))
            bytes_t.append(t2 - tc)
            k = denc.kernel_event
            if k is not None:
                kern_t.append((k.profile.end - k.profile.start) * 1e-9)
            c = denc.compactor
            if predictive and c.scan_event is not None and c.copy_event is not None:
                compact_t.append((c.copy_event.profile.end - c.scan_event.profile.start) * 1e-9)
            copy_t.append((copy_ev.profile.end - copy_ev.profile.start) * 1e-9)
    denc.close()
    med = lambda xs: statistics.median(xs) * 1e3 if xs else float("nan")  # noqa: E731
    parts = host.parts if host is not None else {"readback": [], "gather": [], "encode": []}
    return {
        "host_ms": med(host_t) if host is not None else float("nan"),
        "readback_ms": med(parts["readback"][warmup:]),
        "gather_ms": med(parts["gather"][warmup:]),
        "encode_ms": med(parts["encode"][warmup:]),
        "device_ms": med(dev_t),
        "wait_ms": med(wait_t),
        "share_ms": med(share_t),
        "bytes_ms": med(bytes_t),
        "kernel_ms": med(kern_t),
        "compact_ms": med(compact_t),
        "copy_ms": med(copy_t),
        "frame_mb": plan.size / 1e6,
        "read_mb": statistics.median(read[warmup:] or read) / 1e6,
        "wire_mb": statistics.median(wire[warmup:] or wire) / 1e6,
        "same": bool(same) if host is not None else None,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drape.server.tools.encodebench", description=__doc__.splitlines()[0])
    ap.add_argument("--cloths", type=int, nargs="+", default=[64, 256, 1024], help="cloth counts (default 64 256 1024)")
    ap.add_argument("--side", type=int, default=32, help="grid side: side x side vertices per cloth (default 32)")
    ap.add_argument(
        "--encoding",
        nargs="+",
        default=["float32", "float16", "quant16"],
        choices=[*ENCODINGS, "mixed"],
        help="encodings to time (mixed: a third of each)",
    )
    ap.add_argument("--bundle", type=int, default=0, help="cloths per bundle; 0 = each cloth on its own key")
    ap.add_argument("--normals", action="store_true", help="normals in every state")
    ap.add_argument("--repeat", type=int, default=20, help="timed frames (median)")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--step", type=float, default=P.DEFAULT_STEP, help="predictive: grid step, metres")
    ap.add_argument("--keyframe-interval", type=int, default=60, help="predictive: frames between keyframes")
    ap.add_argument("--local-size", type=int, default=None, help="encoder work-group size (default: per device)")
    ap.add_argument("--device", default=None, help="DRAPE_DEVICE: auto, gpu, cpu or part of a name")
    ap.add_argument("--no-host", action="store_true", help="time the device path only (no host path, no comparison)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    configure_heap(ServerConfig().malloc_mmap_threshold)  # as drape serve's (the payloads' copies)
    dev = Device(args.device)
    print(
        f"device: {dev.info.name}; {args.side}x{args.side} vertices per cloth, "
        f"{'bundles of ' + str(args.bundle) if args.bundle > 0 else 'singles'}{', normals' if args.normals else ''}; "
        f"median ms per frame over {args.repeat} frames"
    )
    print(
        f"{'encoding':10} {'cloths':>6} {'MB':>7} {'read MB':>7} {'wire MB':>7} | "
        f"{'host':>8} {'readback':>8} {'gather':>7} {'encode':>7} | "
        f"{'device':>7} {'wait':>7} {'host':>6} {'bytes':>6} | {'kernel':>7} {'compact':>7} {'copy':>6} | same"
    )
    for n in args.cloths:
        for e in args.encoding:
            r = run(
                e,
                n,
                args.side,
                args.bundle,
                args.normals,
                args.repeat,
                args.warmup,
                dev,
                local_size=args.local_size,
                step=args.step,
                keyframe_interval=args.keyframe_interval,
                with_host=not args.no_host,
            )
            same = {True: "yes", False: "NO", None: "-"}[r["same"]]  # type: ignore[index]
            print(
                f"{e:10} {n:6d} {r['frame_mb']:7.2f} {r['read_mb']:7.2f} {r['wire_mb']:7.2f} | "
                f"{r['host_ms']:8.2f} {r['readback_ms']:8.2f} {r['gather_ms']:7.2f} {r['encode_ms']:7.2f} | "
                f"{r['device_ms']:7.2f} {r['wait_ms']:7.2f} {r['share_ms']:6.2f} {r['bytes_ms']:6.2f} | "
                f"{r['kernel_ms']:7.2f} {r['compact_ms']:7.2f} {r['copy_ms']:6.2f} | {same}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
