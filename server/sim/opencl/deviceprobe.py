"""The device check's child process: builds and runs on one OpenCL device every kernel the
server runs there, printing each stage before it starts it (devicecheck.py reads them, and the
last one names the kernel a crash was on).

    python -m drape.server.sim.opencl.deviceprobe PLATFORM DEVICE LANES

PLATFORM and DEVICE index ``cl.get_platforms()`` and its devices; LANES is the CPU pack width
to run (0: no packs). Prints ``passed`` and exits 0 when every stage ran.
"""

from __future__ import annotations

import os
import sys
from dataclasses import fields

import numpy as np
import pyopencl as cl

from drape.client.protocol.vocabulary import ENCODING_IDS

from ..fabric import cook_grid
from ..meshes import collision_mesh
from ..params import Capsule, ClothParams, Features, LinkOptions, Sphere, pack_colliders
from .clworld import CLWorld
from .device import Device
from .devicecheck import FAULT_ENV
from .encode import ClothEntry, DeviceEncoder, FramePlan, Publication


def _stage(name: str) -> None:
    print(f"stage {name}", flush=True)
    fault = os.environ.get(FAULT_ENV, "")
    how, _, where = fault.partition(":")
    if where and name.startswith(where):
        if how == "abort":
            sys.stderr.write(f"LLVM ERROR: injected fault at {name}\n")
            sys.stderr.flush()
            os.abort()
        raise RuntimeError(f"injected fault at {name}")


def _exercise(dev: cl.Device, lanes: int) -> None:
    """Build and run on ``dev`` every kernel the server runs there, with ``lanes`` CPU pack lanes."""
    d = Device(device=dev)
    gpu = d.info.is_gpu
    fabric = cook_grid(5, 4, options=LinkOptions(bending=True), pinned=[0, 4])
    every = Features(**{f.name: True for f in fields(Features)})
    feature_sets = {"no features": Features(), "every feature": every}
    colliders = pack_colliders([Sphere((0.5, -0.3, 0.5), 0.2), Capsule((0, -0.5, 0), (1, -0.5, 0), 0.1)])

    def run(world: CLWorld, n: int, features: Features) -> None:
        hs = [world.add(fabric, ClothParams(features=features, iterations=2, substeps=2)) for _ in range(n)]
        if features.colliders:
            world.set_colliders(hs[0], colliders)
        world.set_pin_targets(hs[0], np.array([0]), np.array([[0.0, 0.1, 0.0]]))
        for _ in range(2):
            world.step(1 / 60)
        frame = world.fetch()
        if not np.isfinite(frame.xyz).all():
            raise RuntimeError("the step gave non-finite positions")

    widths = [w for w in (lanes, lanes // 2, lanes // 4, lanes // 8) if w >= 2] if lanes else []
    for fname, features in feature_sets.items():
        for w in widths if not gpu else []:
            _stage(f"pack_step (kernels/pack.cl) at {w} lanes, {fname}")
            run(CLWorld("workgroup", device=d, pack_lanes=w), w, features)
        for local in (True, False) if gpu or not widths else (False,):
            _stage(f"wg_step (kernels/wg_step.cl) in {'local' if local else 'global'} memory, {fname}")
            run(CLWorld("workgroup", device=d, pack_lanes=0, use_local=local), 2, features)
        for solver in ("coloured", "jacobi"):
            _stage(f"{solver} solver (cl_predict, {'cl_links' if solver == 'coloured' else 'jacobi_iter'}), {fname}")
            run(CLWorld(solver, device=d), 2, features)

    _stage("inter-cloth collision (kernels/intercollide.cl)")
    world = CLWorld("workgroup", device=d, pack_lanes=lanes if not gpu else 0)
    for _ in range(2):
        world.add(fabric, ClothParams(iterations=2), scene="probe")
    world.step(1 / 60)
    if not np.isfinite(world.fetch().xyz).all():
        raise RuntimeError("inter-cloth collision gave non-finite positions")

    _stage("mesh collision (kernels/meshcollide.cl)")
    world = CLWorld("workgroup", device=d, pack_lanes=lanes if not gpu else 0)
    h = world.add(fabric, ClothParams(iterations=2))
    box = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]])
    faces = [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [3, 7, 6], [3, 6, 2], [0, 4, 7]]
    faces += [[0, 7, 3], [1, 2, 6], [1, 6, 5]]
    world.set_mesh(h, collision_mesh(0.2 * box, np.array(faces)))
    world.step(1 / 60)
    if not np.isfinite(world.fetch().xyz).all():
        raise RuntimeError("mesh collision gave non-finite positions")

    _stage("encode_frame (kernels/encode.cl)")
    world = CLWorld("workgroup", device=d, pack_lanes=lanes if not gpu else 0)
    encodings = list(ENCODING_IDS.values())  # what the device encoder writes, predictive (1.5) included
    hs = [world.add(fabric, ClothParams(features=Features(normals=True))) for _ in encodings]
    world.step(1 / 60)
    world.sync()
    cloths = [
        ClothEntry(f"c{i}", world.rec[h].vbase, fabric.n_vertices, enc, True)
        for i, (h, enc) in enumerate(zip(hs, encodings, strict=True))
    ]
    pubs = [Publication("s", (0,)), Publication("b", tuple(range(1, len(cloths))), True)]
    enc = DeviceEncoder(d)
    enc.set_plan(FramePlan.build(cloths, pubs))
    enc.encode(d.queue, world.mem.pos.buf, world.mem.nrm.buf, 1, 1, predictive=np.zeros((len(cloths), 3), np.uint64))
    if not all(len(s) for s in enc.slices()):
        raise RuntimeError("the encoder wrote an empty publication")
    enc.close()


def _child(platform: int, device: int, lanes: int) -> int:
    dev = cl.get_platforms()[platform].get_devices()[device]
    _stage("start-up")
    _exercise(dev, lanes)
    print("passed", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 3 or not all(a.isdigit() for a in args):
        print(__doc__, file=sys.stderr)
        return 2
    return _child(*map(int, args))


if __name__ == "__main__":
    sys.exit(main())
