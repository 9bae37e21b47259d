"""The cost of mesh colliders (issue 22: "a 5,000-triangle body collider per cloth at <= 2x the
solver time without it"): N capes of 32 x 32 (0.5 x 0.9 m, pinned at the shoulders, 10
iterations) each hanging against the back of its own body mesh (the procedural humanoid of
drape.server.sim.bodymesh, one mesh object shared by every cloth: one copy on the device, each
cloth its own pose), on the work-group solver, against the same cloths without meshes.

    python -m drape.server.tools.meshbench [--cloths N] [--cells 0.05,0.035] [--into M] [--frames F]
                                           [--rounds R] [--json FILE]

``--cells``: the body's tessellation (0.05: 5,972 triangles, 0.035: 12,220). The cases' Worlds
are built first, then timed in ``--rounds`` interleaved rounds. Each row: the median ms per
frame (step + wait, drape bench's timing), ``vs_none`` and the mesh's cost per cloth
(microseconds) and per cloth and triangle (nanoseconds). The capes hang 3 cm behind the back:
no vertex touches it, the cost of the queries alone. ``--into M`` places each body M metres
further back, into its cape: at 0.08 about 80 of a cape's 1,024 vertices lean on it every frame
(the cost of contacts: pushes, the guard).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..sim.bodymesh import body_mesh
from ..sim.fabric import cook_grid
from ..sim.meshes import pose_matrix
from ..sim.opencl.device import Device
from ..sim.params import ClothParams, LinkOptions, Material
from .bench import FrameTimes, Record, _record, make, time_frames

N = 32


def bench_mesh(
    cloths: int,
    cells: list[float],
    frames: int,
    max_seconds: float,
    device: str | None,
    rounds: int = 3,
    into: float = 0.0,
) -> list[Record]:
    """Every case's World built first, then ``rounds`` rounds of ``frames`` frames each, case after
    case (a load that comes and goes on a shared machine falls on every case alike)."""
    fab = cook_grid(N, N, 0.5, 0.9, LinkOptions(bending=True), [0, N - 1], "vertical", (-0.25, 1.45, -0.15))
    p = ClothParams(iterations=10, material=Material(thickness=0.005))
    side = int(np.ceil(np.sqrt(cloths)))
    offsets = [np.array([1.0 * (i % side), 0.0, 1.0 * (i // side)]) for i in range(cloths)]
    cases = []
    for cell in [None, *cells]:
        w = make("workgroup", device)
        body = body_mesh(cell) if cell is not None else None
        for off in offsets:
            h = w.add(fab, p, positions=fab.rest_positions + off)
            if body is not None:
                w.set_mesh(h, body, pose_matrix(off - (0.0, 0.0, into)))
        time_frames(w, warmup=30, frames=0, max_seconds=max_seconds)
        cases.append((w, body, FrameTimes()))
    for _ in range(rounds):
        for w, _, times in cases:
            t = time_frames(w, warmup=1, frames=frames, max_seconds=max_seconds / rounds)
            times += t
            times.host_ms = [*getattr(times, "host_ms", []), *t.host_ms]
    out = []
    for w, body, times in cases:
        extra = {
            "features": "none" if body is None else "mesh",
            "triangles": body.n_triangles if body else 0,
            "into": into,
        }
        out.append(_record("mesh", "workgroup", w, [(fab, p)] * cloths, times, extra))
        out[-1].extra["rounds"] = rounds
        w.close()
    none = out[0].ms_per_frame
    for r in out:
        r.extra["vs_none"] = round(r.ms_per_frame / none, 3)
        extra_ms = r.ms_per_frame - none
        r.extra["us_per_cloth"] = round(1e3 * extra_ms / cloths, 3)
        tris = r.extra["triangles"]
        r.extra["ns_per_cloth_triangle"] = round(1e6 * extra_ms / (cloths * tris), 4) if tris else None
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cloths", type=int, default=None, help="default 4096 on a GPU, 128 on a CPU")
    ap.add_argument("--cells", default="0.05,0.035", help="the body's tessellation cells (m), a comma list")
    ap.add_argument("--into", type=float, default=0.0, help="the bodies this far (m) into the capes: contacts")
    ap.add_argument("--frames", type=int, default=10, help="timed frames per case and round")
    ap.add_argument("--rounds", type=int, default=3, help="rounds over the cases (interleaved)")
    ap.add_argument("--max-seconds", type=float, default=20.0)
    ap.add_argument("--device", default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    cloths = args.cloths or (4096 if Device(args.device).info.is_gpu else 128)
    cells = [float(c) for c in args.cells.split(",")]
    records = bench_mesh(cloths, cells, args.frames, args.max_seconds, args.device, args.rounds, args.into)
    for r in records:
        e = r.extra
        print(
            f"{r.device[:40]:40s} {r.cloths:5d} cloths  {e['features']:5s} {e['triangles']:6d} triangles  "
            f"{r.ms_per_frame:9.3f} ms (min {r.ms_min:.3f})  vs_none {e['vs_none']:.3f}  "
            f"{e['us_per_cloth']:.3f} us/cloth  {e['ns_per_cloth_triangle']} ns/cloth/triangle"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps([asdict(r) for r in records], indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
