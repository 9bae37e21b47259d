"""``drape demo --stage body``: a cape on a running body mesh, over Zenoh (protocol 1.8 mesh
colliders).

A game client submits a cape pinned behind the shoulders of the procedural body
(``bodymesh.body_mesh``: 12,220 triangles), sending the body once as the cape's mesh collider;
then, for every state it receives, it moves the body one tick on (the penetration tool's
``cape_body`` runner: up to 5 m/s, a turn, a stop) with the mesh's rigid pose (a control of
about 80 bytes) and the cape's pins with it, in one control. The server is ``drape serve``; the states received
are drawn as ``meshdemo`` draws the World's (one drawing: :func:`.meshdemo.draw`), the body at the
pose in force at each state's tick (the tick each waited pose control answered), and checked
with the penetration metric: the vertices inside the body at each received tick are printed.
Frames and ``drape-body.gif`` go to ``--out``.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

import numpy as np

from ..sim.bodymesh import body_mesh
from ..sim.collision import penetration
from ..sim.meshes import pose_matrix
from .demorun import wrote
from .imagefiles import write_gif, write_png
from .meshdemo import draw
from .penetration import DT, Runner
from .procs import ServerExited, demo_server

log = logging.getLogger(__name__)

N = 24  # the cape's columns and rows
SHOULDERS = np.array([0.0, 1.45, -0.12])
THICKNESS = 0.005


def drive(endpoint: str, seconds: float) -> tuple[np.ndarray, list[np.ndarray], list[int], list[np.ndarray]]:
    """The client: the cape's triangles, its received positions, their ticks, and the body's pose
    in force at each of those ticks."""
    from drape.client import DrapeClient
    from drape.client import protocol as P
    from drape.client.controls import pin_changes

    body = body_mesh()
    top = np.arange(N)
    client = DrapeClient(endpoint, server_id="demo", timeout=30.0)
    try:
        cape = client.submit_grid(
            N,
            N,
            0.5,
            0.9,
            orientation="vertical",
            origin=tuple(SHOULDERS - [0.25, 0.0, 0.0]),
            pinned=top,
            features=["tethers", "self_collision", "wind"],  # still air's drag: the cape streams behind
            material={"thickness": THICKNESS, "drag": 1.0, "lift": 0.3},
            substeps=2,
            mesh_collider=body,
        )
        assert cape.rest_positions is not None and cape.triangles is not None
        rest_top = cape.rest_positions[top]
        run = Runner()
        applied: list[tuple[int, np.ndarray]] = [(0, pose_matrix())]  # (from tick, pose)
        xs, ticks, poses = [], [], []
        for k in range(int(seconds / DT)):
            s = cape.next_state(30.0)
            while len(applied) > 1 and applied[1][0] <= s.tick:
                applied.pop(0)
            xs.append(s.positions.copy())
            ticks.append(s.tick)
            poses.append(applied[0][1])
            run.advance(k * DT)
            h = run.heading
            rotation = (math.cos(h / 2), 0.0, math.sin(h / 2), 0.0)  # about +y, as the runner turns
            pose = pose_matrix(run.pos, rotation)
            batch = client.batch(wait=True)  # the pins and the body's pose in one control: one tick
            pins = pin_changes(top, rest_top @ pose[:, :3].T + run.pos, None)
            batch.add(cape, **pins, mesh_collider=P.MeshCollider.pose(run.pos, rotation))
            tick = batch.send()[0]  # type: ignore[index]
            assert isinstance(tick, int)
            applied.append((tick, pose))
        return cape.triangles, xs, ticks, poses
    finally:
        client.close()


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    server = demo_server(args)
    try:
        tris, xs, ticks, poses = drive(server.endpoint, args.seconds)
    except ServerExited as e:
        print(f"drape demo: {e}", file=sys.stderr)
        return 1
    finally:
        server.stop(grace=15)
    body = body_mesh()
    pen = [penetration(x, x, 0.0, meshes=[(body, p)]) for x, p in zip(xs, poses, strict=True)]
    inside = [p.behind for p in pen]
    print(
        f"received {len(xs)} states over Zenoh (ticks {ticks[0]}..{ticks[-1]}); vertices inside the body: "
        f"at most {max(inside)}, in {sum(1 for n in inside if n)} states (at ticks "
        f"{[t - ticks[0] for t, n in zip(ticks, inside, strict=True) if n][:12]} of the run), "
        f"deepest {1e3 * max(p.deepest_behind for p in pen):.1f} mm"
    )
    if not all(np.isfinite(x).all() for x in xs):
        raise RuntimeError("non-finite positions received")
    w = int(args.size.lower().split("x")[1])  # square frames of the height
    every = max(1, round(60 / args.fps))
    imgs = []
    for i in range(0, len(xs), every):
        t = (ticks[i] - ticks[0]) * DT
        caption = f"t = {t:4.2f} s  Zenoh, 1.8: {body.n_triangles:,}-triangle body"
        imgs.append(draw(xs[i], tris, body, poses[i], w, caption))
    paths = [write_png(out / f"body_{i * every:03d}.png", img) for i, img in enumerate(imgs)]
    return wrote(paths, write_gif(out / "drape-body.gif", imgs, fps=60 / every))


def main(argv: list[str] | None = None) -> int:
    """``python -m drape.server.tools.demobody`` (``deploy/h100.sh tool demobody``): the stage
    alone, with ``drape demo``'s options that it reads."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--out", type=Path, default=Path("out/demo-body"))
    ap.add_argument("--fps", type=float, default=20.0)
    ap.add_argument("--size", default="400x400")
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--solver", default=None)
    ap.add_argument("--device", default=None)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
