"""A cape on a body mesh, as frames and a GIF (issue 22's demo of mesh colliders): the penetration
tool's ``cape_body`` scenario (a 32 x 32 cape pinned behind the shoulders of the 12,220-triangle
procedural body, which runs up to 5 m/s, turns and stops) stepped on a World on this machine and
drawn from behind, following the body (the camera moves with it; the body turns in view).

    python -m drape.server.tools.meshdemo [--out docs/mesh_demo] [--ticks 300] [--every 3] [--size 360]

Writes ``OUT.gif`` and a few PNG frames ``OUT_NNN.png``. The same scene over Zenoh, the body
sent as a 1.8 mesh collider and moved by a pose per tick: ``drape demo --stage body``
(:mod:`.demobody`, drawn by :func:`draw`).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..sim import make_world
from ..sim.bodymesh import body_mesh
from ..sim.meshes import CollisionMesh
from . import penetration
from .imagefiles import write_gif, write_png
from .render import render_scene

CAPE = (150, 30, 40)
CAPE_BACK = (110, 25, 35)
BODY = (190, 175, 160)
_A = np.radians(235)  # the drawing turned about y: the body seen from behind and the side
VIEW = np.array([[np.cos(_A), 0, np.sin(_A)], [0, 1, 0], [-np.sin(_A), 0, np.cos(_A)]])
BOUNDS = ((-0.9, 0.0, -0.9), (0.9, 1.9, 0.9))  # around the body, in its frame


def draw(
    cape: np.ndarray, triangles: np.ndarray, body: CollisionMesh, pose: np.ndarray, size: int, caption: str
) -> np.ndarray:
    """One frame: the cape's positions ``cape`` (world) and the body at ``pose`` (3 x 4), seen
    from behind and the side, the camera following the body (also ``drape demo --stage body``'s)."""
    shift = pose[:, 3]
    return render_scene(
        (size, size),
        [
            ((cape - shift) @ VIEW.T, triangles, CAPE, CAPE_BACK),
            (body.vertices @ (VIEW @ pose[:, :3]).T, body.triangles, BODY),
        ],
        view="iso",
        bounds=BOUNDS,
        title=caption,
    )


def frames(ticks: int, every: int, size: int, solver: str = "workgroup") -> list[np.ndarray]:
    world = make_world(solver)
    body = body_mesh()
    out = []
    base = penetration.BASE.with_(
        features=replace(penetration.BASE.features, wind=True),  # still air: the cape streams behind
        material=replace(penetration.BASE.material, drag=1.0, lift=0.3),
    )
    for t in penetration.cape_body(world, 32, ticks=ticks, base=base):
        if t.index % every:
            continue
        cloth = t.cloths[0]
        _, pose = cloth.meshes[0]
        caption = f"t = {t.index / penetration.HZ:4.2f} s   cape 32 x 32 on a {body.n_triangles:,}-triangle body"
        out.append(draw(t.x[0], cloth.fabric.triangles, body, pose, size, caption))
    world.close()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("docs/mesh_demo"))
    ap.add_argument("--ticks", type=int, default=300)
    ap.add_argument("--every", type=int, default=3, help="draw one tick in EVERY")
    ap.add_argument("--size", type=int, default=360)
    ap.add_argument("--solver", default="workgroup")
    args = ap.parse_args(argv)
    imgs = frames(args.ticks, args.every, args.size, args.solver)
    for i in np.linspace(0, len(imgs) - 1, 4).round().astype(int).tolist():
        print(write_png(args.out.parent / f"{args.out.name}_{i * args.every:03d}.png", imgs[i]))
    print(write_gif(args.out.with_suffix(".gif"), imgs, fps=60 / args.every / 1.0))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
