"""The mesh pass's kernel alone, two versions A/B on the same inputs (issue 22: its cost with
contacts): meshbench's scene (N capes of 32 x 32 against the back of their bodies, ``--into`` M
metres into them), run 30 frames, then one frame's inputs for the mesh pass (each free vertex's
next inertial motion, pushed ``--push`` metres further back, toward the body) restored before
every launch; kernels/meshcollide.cl against another copy of it (``--old FILE``, a kernel file
name in kernels/, e.g. one written by ``git show REV:kernels/meshcollide.cl > kernels/old.cl``),
launched in interleaved rounds in one process. Remove that copy afterwards (every file in kernels/
belongs to a program: tests/sim/test_kernel_sources.py).

    python -m drape.server.tools.meshab --old old.cl [--cloths 32] [--into 0.08] [--cell 0.05]
                                        [--rounds 15] [--push 0.003] [--json FILE]

Prints the medians and minima of wall and process CPU time per launch (ms; the CPU time is
steadier on a shared machine), the vertices the pass moved and the largest difference between
the two versions' outputs (m: 0 when a change keeps the results).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import pyopencl as cl

from ..sim.bodymesh import body_mesh
from ..sim.fabric import cook_grid
from ..sim.meshes import pose_matrix
from ..sim.opencl.clworld import CLWorld
from ..sim.params import ClothParams, LinkOptions, Material
from .bench import DT, make

N = 32


def mesh_ab(cloths: int, into: float, cell: float, rounds: int, old: str, push: float, device: str | None) -> dict:
    fab = cook_grid(N, N, 0.5, 0.9, LinkOptions(bending=True), [0, N - 1], "vertical", (-0.25, 1.45, -0.15))
    p = ClothParams(iterations=10, material=Material(thickness=0.005))
    w = make("workgroup", device)
    assert isinstance(w, CLWorld)
    body = body_mesh(cell)
    side = int(np.ceil(np.sqrt(cloths)))
    for i in range(cloths):
        off = np.array([1.0 * (i % side), 0.0, 1.0 * (i // side)])
        h = w.add(fab, p, positions=fab.rest_positions + off)
        w.set_mesh(h, body, pose_matrix(off - (0.0, 0.0, into)))
    for _ in range(30):
        w.step(DT)
    w.sync()
    mc, mem, q = w.mesh_collision, w.mem, w.dev.queue
    mc.save()  # the step's start: the positions now
    pos = np.empty((mem.pos.capacity, 4), np.float32)
    vel = np.empty((mem.vel.capacity, 4), np.float32)
    cl.enqueue_copy(q, pos, mem.pos.buf)
    cl.enqueue_copy(q, vel, mem.vel.buf)
    q.finish()
    moved = pos.copy()
    moved[:, :3] += vel[:, :3] * DT
    moved[:, 2] += push
    pinned = pos[:, 3] <= 0
    moved[pinned, :3] = pos[pinned, :3]
    kernels = {
        "new": mc.kernels()["mc_collide"],
        "old": cl.Kernel(w.dev.program(mc.options, source=old), "mc_collide"),
    }

    def launch(k: cl.Kernel) -> tuple[float, float, np.ndarray]:
        cl.enqueue_copy(q, mem.pos.buf, moved)
        cl.enqueue_copy(q, mem.vel.buf, vel)
        q.finish()
        t0, c0 = time.perf_counter(), time.process_time()
        mc.enqueue(DT, k)
        q.finish()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        out = np.empty_like(pos)
        cl.enqueue_copy(q, out, mem.pos.buf)
        q.finish()
        return wall * 1e3, cpu * 1e3, out

    wall: dict[str, list[float]] = {"old": [], "new": []}
    cpu: dict[str, list[float]] = {"old": [], "new": []}
    outs: dict[str, np.ndarray] = {}
    for _ in range(rounds):
        for name, k in kernels.items():
            tw, tc, outs[name] = launch(k)
            wall[name].append(tw)
            cpu[name].append(tc)
    w.close()
    res: dict = {
        "device": w.device_name,
        "cloths": cloths,
        "into": into,
        "push": push,
        "triangles": body.n_triangles,
        "rounds": rounds,
        "old": old,
        "moved_vertices": int(np.sum(np.any(outs["old"][:, :3] != moved[:, :3], axis=1))),
        "max_abs_diff_m": float(np.abs(outs["new"][:, :3] - outs["old"][:, :3]).max()),
    }
    for name in ("old", "new"):
        for label, t in (("wall", wall[name]), ("cpu", cpu[name])):
            res[f"{name}_{label}_ms_median"] = round(statistics.median(t), 3)
            res[f"{name}_{label}_ms_min"] = round(min(t), 3)
    for label in ("wall", "cpu"):
        res[f"new_vs_old_{label}"] = round(res[f"new_{label}_ms_median"] / res[f"old_{label}_ms_median"], 3)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", required=True, help="the other kernel file, in kernels/")
    ap.add_argument("--cloths", type=int, default=32)
    ap.add_argument("--into", type=float, default=0.08, help="the bodies this far (m) into the capes")
    ap.add_argument("--cell", type=float, default=0.05, help="the body's tessellation (0.05: 5,972 triangles)")
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--push", type=float, default=0.003, help="the motion's push (m) toward the body")
    ap.add_argument("--device", default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    res = mesh_ab(args.cloths, args.into, args.cell, args.rounds, args.old, args.push, args.device)
    print(json.dumps(res))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
