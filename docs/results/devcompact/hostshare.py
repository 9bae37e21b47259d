"""The device path's host share per frame, part by part, on the tree PYTHONPATH picks (the API
the trees before and after the device compaction share): one frame of N swaying 32x32
predictive cloths encoded, then each host part timed 25 times (min and median, ms): the
streams' decisions, the headers' edits the tick thread makes (nonfinite, set_time), and what
the publisher does with a frame (hold it, its sizes, one ``bytes`` per publication, release).
Deterministic host work: the min is what a quiet core takes.

    python docs/results/devcompact/hostshare.py 4096 0    # N, cloths per bundle (0: singles)
"""

import statistics
import sys
import time

import numpy as np
import pyopencl as cl

from drape.client import protocol as P
from drape.server.sim.opencl.device import Device
from drape.server.sim.opencl.devstreams import DeviceStreams
from drape.server.sim.opencl.encode import ClothEntry, DeviceEncoder, FramePlan
from drape.server.tools.encodebench import _publications, _sway, _world

try:  # the heap as drape serve sets it (the payloads' copies), where the tree does
    from drape.server.service.config import ServerConfig
    from drape.server.service.process.memory import configure_heap

    configure_heap(ServerConfig().malloc_mmap_threshold)
except ImportError:
    pass
n, bundle = int(sys.argv[1]), int(sys.argv[2])
dev = Device(None)
nv = 32 * 32
pos, _ = _world(np.random.default_rng(1), n, 32)
pos_buf = cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=pos)
plan = FramePlan.build(
    [ClothEntry(f"c{i:05d}", i * nv, nv, P.ENC_PREDICTIVE, False) for i in range(n)], _publications(n, bundle)
)
enc = DeviceEncoder(dev)
enc.set_plan(plan)
streams = DeviceStreams(60)
streams.follow(plan)
every = list(range(len(plan.publications)))
for f in range(4):
    cl.enqueue_copy(dev.queue, pos_buf, _sway(pos, f), is_blocking=True)
    enc.encode(dev.queue, pos_buf, None, f, f, None, predictive=streams.decide(f, None)[0]).wait()
    enc.hold().release()
new = hasattr(enc, "compactor")


def publish() -> int:
    if new:
        enc._last.where = None  # the frame's index read again, as each new frame's is
    frame = enc.hold()
    sizes = frame.sizes() if new else [len(v) for v in frame.views]
    out = [b for _, b in frame.payloads(every)]
    frame.release()
    return len(sizes) + len(out)


tick = iter(range(100, 10**6))
parts = {
    "decide": lambda: streams.decide(next(tick), None),
    "nonfinite": enc.nonfinite,
    "set_time": lambda: (lambda fr: (fr.set_time(12345), fr.release()))(enc.hold()),
    "publish": publish,
}
row = []
for name, fn in parts.items():
    ts = []
    for _ in range(25):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    row.append(f"{name} {min(ts) * 1e3:.2f}/{statistics.median(ts) * 1e3:.2f}")
tree = "after" if new else "before"
print(f"{tree:6} {n} {'singles' if bundle <= 0 else f'bundles of {bundle}'}: " + ", ".join(row) + " (ms min/median)")
