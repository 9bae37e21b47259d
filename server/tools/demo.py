"""``drape demo``: a server and three game clients on loopback, drawn from what they received.

The server runs as its own process (``drape serve``, Zenoh peer mode on 127.0.0.1, the default
OpenCL device: PoCL's CPU device when there is no GPU). Three client processes submit a cloth
each through the client SDK and steer it every tick, as a game would:

- a banner on a pole, pinned along its hoist, in gusting wind (wind feature);
- a pleated stage curtain hanging from a rod, brushed by a ball swinging on a rope across its
  front (colliders; the pleats are the submitted mesh's rest shape);
- a flared cape pinned around a character's shoulders: the character walks a circle, its torso
  and legs are the cape's capsules, the air drags the cape out behind (colliders, tethers, wind).

Each client keeps the states it received over Zenoh, with the poses of what it steered; the
stages' shared run (server/tools/demorun.py) then renders them (server/tools/render.py: depth
buffer, smooth per-pixel shading, shadows, a perspective camera) into PNG frames and an animated
GIF in ``--out`` and prints where they are.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from .demorun import TICK_HZ, Recording, render_chunk, run_stage, save_recording
from .demowearer import CAPE_COLS, CAPE_OPTIONS, CAPE_ROWS, SHOULDER_Y, body_parts, cape_mesh, cape_texture, grid_uv

log = logging.getLogger(__name__)

KINDS = ("flag", "curtain", "cape")
#: The floor's extent (x-z) under the three, for the renderer's floor and shadows.
BOUNDS = ((-1.2, 0.0, -2.2), (6.6, 3.0, 2.6))
#: The camera: a little above eye height, in front of the stage, looking at its middle.
EYE, TARGET, FOV = (2.85, 2.2, 8.6), (2.85, 1.1, -0.1), 31.0

# the banner: its hoist along the pole at x = 0
FLAG_COLS, FLAG_ROWS, FLAG_W, FLAG_H, FLAG_TOP = 26, 16, 1.5, 0.92, 2.55
POLE = ((0.0, 0.0, -0.6), (0.0, 2.62, -0.6))
# the curtain: a rod at CURTAIN_TOP, the ball's pivot above the rod in front of it
CURTAIN_COLS, CURTAIN_ROWS, CURTAIN_W, CURTAIN_H = 34, 30, 1.7, 2.05
CURTAIN_X, CURTAIN_Z, CURTAIN_TOP = 1.85, -1.0, 2.3
PLEAT_DEPTH, PLEAT_COLUMNS = 0.045, 6
PIVOT, ROPE, BALL_R, SWING = (2.7, 3.35, -0.8), 2.1, 0.24, math.radians(32.0)
# the cape's wearer (demowearer.py) walks a circle
WALK_CENTRE, WALK_R, WALK_W = (4.75, 0.0, 0.2), 0.85, 1.5  # metres, metres, rad/s


# ------------------------------------------------------------------------------------------------
# The scene: rest shapes and what each client steers, as functions of time


def flag_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The banner: a vertical grid, its hoist (column 0) on the pole."""
    from drape.client import protocol as P

    x0, _, z0 = POLE[0]
    v, t = P.grid_positions(FLAG_COLS, FLAG_ROWS, FLAG_W, FLAG_H, "vertical", (x0 + 0.03, FLAG_TOP, z0))
    return v, t


def curtain_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The curtain's rest shape: a grid folded into pleats (a sine along x in z), so that it hangs
    pleated from its first tick and its bending links keep the pleats."""
    from drape.client import protocol as P

    v, t = P.grid_positions(CURTAIN_COLS, CURTAIN_ROWS, CURTAIN_W, CURTAIN_H, "vertical", (0, CURTAIN_TOP, 0))
    col = np.arange(len(v)) % CURTAIN_COLS
    v[:, 0] += CURTAIN_X
    v[:, 2] = CURTAIN_Z + PLEAT_DEPTH * np.sin(2 * math.pi * col / PLEAT_COLUMNS)
    return v, t


def ball_pose(t: float) -> tuple[np.ndarray, np.ndarray]:
    """The ball on its rope at time t: a pendulum swinging along x from its highest point, in
    front of the curtain. Returns (pivot, centre)."""
    g = 9.81
    theta = SWING * math.cos(math.sqrt(g / ROPE) * t)
    pivot = np.array(PIVOT)
    return pivot, pivot + ROPE * np.array([math.sin(theta), -math.cos(theta), 0.0])


def walker_pose(t: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The cape wearer at time t: feet position, the body's frame (columns: right, up, behind)
    and the walk's phase (radians). They walk a circle anticlockwise seen from above, bobbing."""
    a = WALK_W * t + math.radians(200.0)
    c = np.array(WALK_CENTRE)
    pos = c + WALK_R * np.array([math.cos(a), 0.0, -math.sin(a)])
    heading = np.array([-math.sin(a), 0.0, -math.cos(a)])  # d pos / da
    phase = (WALK_W * WALK_R / 0.75) * math.pi * t  # a stride of 0.75 m
    pos[1] = 0.035 * abs(math.sin(phase))
    up = np.array([0.0, 1.0, 0.0])
    right = np.cross(heading, up)
    return pos, np.stack([right, up, -heading], 1), phase


def walker_parts(t: float) -> tuple[list[list[Any]], list[dict[str, Any]]]:
    """The wearer's body at time t: capsules to draw [(p0, p1, radius, colour)] and the cape's
    colliders (torso, legs and head)."""
    return body_parts(*walker_pose(t))


# ------------------------------------------------------------------------------------------------
# Client processes


def run_client(kind: str, endpoint: str, seconds: float, fps: float, out: str, ready: Any, go: Any) -> None:
    """One game client: submit, then (once every client has its cloth: ``go``) steer every tick
    and record states at ``fps`` for ``seconds``."""
    logging.basicConfig(level=logging.WARNING)
    from drape.client import DrapeClient

    every = max(1, int(round(TICK_HZ / fps)))
    frames, ticks, props = [], [], []
    seen: set[int] = set()
    dup = 0
    with DrapeClient(endpoint, timeout=30.0) as client:
        if kind == "flag":
            v, tris = flag_mesh()
            cloth = client.submit_mesh(
                v,
                tris,
                pinned=[r * FLAG_COLS for r in range(FLAG_ROWS)],
                features=["wind", "xpbd"],
                links={"bending": True},
                material={"drag": 1.1, "lift": 0.5, "mass": 0.25, "compliance": (1e-5, 1e-4, 4e-3)},
                wind=(5.0, 0.0, 1.0),
                iterations=10,
                substeps=2,
            )
        elif kind == "curtain":
            v, tris = curtain_mesh()
            cloth = client.submit_mesh(
                v,
                tris,
                pinned=list(range(CURTAIN_COLS)),
                features=["colliders"],
                links={"bending": True},
                material={"mass": 1.2, "friction": 0.15, "damping": 0.015},
                iterations=12,
            )
            pivot, c = ball_pose(0.0)
            cloth.set_colliders([{"type": "sphere", "center": tuple(c), "radius": BALL_R + 0.02}])
        else:
            local, tris = cape_mesh()
            pos, frame, _ = walker_pose(0.0)
            top = pos + (local[:CAPE_COLS] + [0, SHOULDER_Y, 0]) @ frame.T
            v = pos + (local + [0, SHOULDER_Y, 0]) @ frame.T
            cloth = client.submit_mesh(
                v,
                tris,
                pinned=list(range(CAPE_COLS)),
                **CAPE_OPTIONS,
            )
            _, body = walker_parts(0.0)
            cloth.move_pins(list(range(CAPE_COLS)), top, colliders=body)
        ready.set()
        go.wait()
        cloth.clear()  # the recordings start together: states queued while others submitted go
        start = time.monotonic()
        first_tick = None
        for state in cloth.states(timeout=10.0):
            if state.tick in seen:
                dup += 1
                continue
            seen.add(state.tick)
            first_tick = state.tick if first_tick is None else first_tick
            t = (state.tick - first_tick + 1) / TICK_HZ
            drawn: list[list[Any]] = []
            if kind == "flag" and state.tick % 15 == 0:
                gust = 5.5 + 3.0 * math.sin(0.9 * t) + 1.5 * math.sin(2.3 * t)
                cloth.set(wind=(gust, 0.0, 0.5 + 1.0 * math.sin(0.5 * t)), wait=False)
            elif kind == "curtain":
                pivot, c = ball_pose(t)
                cloth.set_colliders([{"type": "sphere", "center": tuple(c), "radius": BALL_R + 0.02}], wait=False)
                drawn = [[c.tolist(), c.tolist(), BALL_R, BALL], [pivot.tolist(), c.tolist(), 0.012, ROPE_COLOUR]]
            elif kind == "cape":
                pos, frame, _ = walker_pose(t)
                drawn, body = walker_parts(t)
                top = pos + (local[:CAPE_COLS] + [0, SHOULDER_Y, 0]) @ frame.T
                # one message per tick, not waited for: what a game loop does
                cloth.move_pins(list(range(CAPE_COLS)), top, colliders=body, wait=False)
            if state.tick % every == 0:
                frames.append(np.array(state.positions, np.float32))
                ticks.append(state.tick)
                props.append(drawn)
            if time.monotonic() - start > seconds:
                break
        save_recording(out, kind, ticks, frames, cloth.triangles, props, seen, dup)


# ------------------------------------------------------------------------------------------------
# Rendering

SUPERSAMPLE = 1.5  # smooth edges at a bit over half the cost of 2
BALL = (196, 150, 62)  # brass
ROPE_COLOUR = (120, 104, 84)
ROD = (150, 118, 60)
POLE_COLOUR = (88, 80, 74)


def _flag_texture(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The banner: three bands with a disc at the hoist, the same both sides."""
    from .rendermath import linear

    u, v = uv[:, 0], uv[:, 1]
    band = np.clip((v * 3).astype(int), 0, 2)
    col = linear(np.array([(24, 96, 132), (238, 232, 214), (214, 84, 56)]))[band]
    disc = (u - 0.24) ** 2 * (FLAG_W / FLAG_H) ** 2 + (v - 0.5) ** 2 < 0.2**2
    col[disc] = linear((236, 178, 48))
    return col, col


def _curtain_texture(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Red velvet with a gold band above the hem; the back a duller lining."""
    from .rendermath import linear

    v = uv[:, 1]
    front = np.broadcast_to(linear((150, 22, 34)), (len(v), 3)).copy()
    front[(v > 0.9) & (v < 0.95)] = linear((210, 160, 60))
    return front, front * 0.6


TEXTURES = {
    "flag": (_flag_texture, FLAG_ROWS, FLAG_COLS),
    "curtain": (_curtain_texture, CURTAIN_ROWS, CURTAIN_COLS),
    "cape": (cape_texture, CAPE_ROWS, CAPE_COLS),
}


def _static_props() -> list[list[Any]]:
    """What stands still: the banner's pole and finial, the curtain's rod."""
    rod_y = CURTAIN_TOP + 0.03
    top = list(POLE[1])
    return [
        [list(POLE[0]), top, 0.032, POLE_COLOUR],
        [[top[0], top[1] + 0.06, top[2]], [top[0], top[1] + 0.06, top[2]], 0.06, BALL],
        [[CURTAIN_X - 0.12, rod_y, CURTAIN_Z], [CURTAIN_X + CURTAIN_W + 0.12, rod_y, CURTAIN_Z], 0.03, ROD],
        [[CURTAIN_X - 0.16, rod_y, CURTAIN_Z], [CURTAIN_X - 0.16, rod_y, CURTAIN_Z], 0.05, ROD],
        [[CURTAIN_X + CURTAIN_W + 0.16, rod_y, CURTAIN_Z], [CURTAIN_X + CURTAIN_W + 0.16, rod_y, CURTAIN_Z], 0.05, ROD],
    ]


def render_frame(recs: list[Recording], index: dict[str, dict[int, int]], tick: int, size: tuple[int, int]) -> Any:
    """One frame: every recording's cloth at ``tick`` and the props, from the demo's camera."""
    from .drawmeshes import capsule_mesh, cloth_mesh
    from .render import Camera, draw_scene

    meshes = []
    props = _static_props()
    for r in recs:
        i = index[r.kind][tick]
        tex, rows, cols = TEXTURES[r.kind]
        m = cloth_mesh(r.positions[i], r.triangles, (128, 128, 128))
        m.uv, m.texture = grid_uv(rows, cols), tex
        m.sheen = 0.5 if r.kind == "curtain" else 0.2
        meshes.append(m)
        props += r.props[i]
    for p0, p1, radius, colour in props:
        meshes.append(capsule_mesh(p0, p1, radius, colour, segments=20 if radius > 0.02 else 8))
    cam = Camera.look_at(EYE, TARGET, FOV, size)
    return draw_scene(
        size,
        meshes,
        cam,
        bounds=BOUNDS,
        fade_floor=True,
        supersample=SUPERSAMPLE,
        shadow_region=True,
        caption=(f"Drape: three game clients' cloths over Zenoh   tick {tick}" if size[0] >= 480 else f"tick {tick}"),
    )


def _render_chunk(args: tuple[Path, list[int], tuple[int, int], int]) -> list[Path]:
    return render_chunk(*args, KINDS, render_frame, "frame")


# ------------------------------------------------------------------------------------------------
# Command


def run(args: argparse.Namespace) -> int:
    """The three-cloth stage (``drape demo``'s default, demostages.py)."""
    return run_stage(args, KINDS, run_client, _render_chunk, "drape-demo.gif")
