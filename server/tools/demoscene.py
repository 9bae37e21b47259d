"""``drape demo --stage crossing``: two characters of two game clients walk past each other, and
their capes brush (protocol 1.7 scenes: cloths of one scene collide with each other).

Alice's client founds the scene ``crossing`` with her cape, lets anyone in, and moves the scene's
colliders every tick: both walkers' bodies (torso, legs, head), sent once for the whole scene, so
that each cape keeps out of both bodies. Bob's client submits his cape into her scene. Each
client pins its cape around its own walker's shoulders every tick; the walkers come towards each
other along parallel lines 0.6 m apart, their capes (flared cones around their backs, dragged
out behind by the air) meeting at the sides as they pass. The server is ``drape serve`` as in
the three-cloth stage (server/tools/demo.py; the cape, its wearer's body and texture are
demowearer.py's); frames and ``drape-crossing.gif`` go to ``--out``.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from .demorun import TICK_HZ, Recording, render_chunk, run_stage, save_recording
from .demowearer import CAPE_COLS, CAPE_OPTIONS, CAPE_ROWS, SHOULDER_Y, body_parts, cape_mesh, cape_texture, grid_uv

log = logging.getLogger(__name__)

SCENE = "crossing"
WALKERS = ("alice", "bob")
#: Each walker's line (z), start (x) and direction along x; they pass at x = 0 after PASS_AT s.
LANE, SPEED, PASS_AT = 0.3, 1.3, 1.6
#: The capes' contact distance (1.7: ``thickness``, each vertex kept this far from the other cape's).
THICKNESS = 0.03
BOUNDS = ((-3.2, 0.0, -2.0), (3.2, 2.4, 2.0))
EYE, TARGET, FOV = (1.0, 3.3, 4.2), (0.0, 0.85, 0.0), 38.0


def walker(name: str, t: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A walker's feet, frame (right, up, behind) and stride phase at time t: alice along +x on
    z = +LANE, bob along -x on z = -LANE, level at x = 0 at PASS_AT."""
    d = 1.0 if name == "alice" else -1.0
    pos = np.array([d * SPEED * (t - PASS_AT), 0.0, d * LANE])
    phase = SPEED / 0.75 * math.pi * t + (0.0 if d > 0 else 1.3)  # a stride of 0.75 m
    pos[1] = 0.035 * abs(math.sin(phase))
    heading, up = np.array([d, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    return pos, np.stack([np.cross(heading, up), up, -heading], 1), phase


def _body(name: str, t: float) -> tuple[list[list[Any]], list[dict[str, Any]]]:
    return body_parts(*walker(name, t))


def run_client(name: str, endpoint: str, seconds: float, fps: float, out: str, ready: Any, go: Any) -> None:
    """One game client and its walker: submit the cape (alice: founding the scene, members "*"),
    then, once both capes are in (``go``), steer it every tick and record states at ``fps``."""
    logging.basicConfig(level=logging.WARNING)
    from drape.client import DrapeClient

    every = max(1, int(round(TICK_HZ / fps)))
    frames, ticks, props = [], [], []
    seen: set[int] = set()
    local, tris = cape_mesh()
    pins = list(range(CAPE_COLS))

    def shoulders(t: float) -> tuple[np.ndarray, np.ndarray]:
        pos, frame, _ = walker(name, t)
        return pos + (local[:CAPE_COLS] + [0, SHOULDER_Y, 0]) @ frame.T, pos + (local + [0, SHOULDER_Y, 0]) @ frame.T

    def bodies(t: float) -> list[dict[str, Any]]:
        return [c for w in WALKERS for c in _body(w, t)[1]]

    with DrapeClient(endpoint, timeout=120.0, client_id=name) as client:  # a loaded machine starts slowly
        top, v = shoulders(0.0)
        cloth = client.submit_mesh(
            v,
            tris,
            pinned=pins,
            **{**CAPE_OPTIONS, "material": {**CAPE_OPTIONS["material"], "thickness": THICKNESS}},
            scene=SCENE,
        )
        if name == "alice":
            client.set_scene(SCENE, colliders=bodies(0.0), members=["*"])
        cloth.move_pins(pins, top)
        ready.set()
        go.wait()
        cloth.clear()
        start, first = time.monotonic(), None
        sender = ThreadPoolExecutor(1)
        moving: Future | None = None
        for state in cloth.states(timeout=10.0):
            if state.tick in seen:
                continue
            seen.add(state.tick)
            first = state.tick if first is None else first
            t = (state.tick - first + 1) / TICK_HZ
            top, _ = shoulders(t)
            cloth.move_pins(pins, top, wait=False)
            if name == "alice" and (moving is None or moving.done()):  # both bodies, once for the scene
                moving = sender.submit(client.set_scene, SCENE, colliders=bodies(t))  # a request: not in the loop
            if state.tick % every == 0:
                frames.append(np.array(state.positions, np.float32))
                ticks.append(state.tick)
                props.append(_body(name, t)[0])
            if time.monotonic() - start > seconds:
                break
        sender.shutdown()
        save_recording(out, name, ticks, frames, cloth.triangles, props, seen)


def _bob_texture(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bob's cape: deep green with a silver border, lined in ochre (alice's is demowearer.py's blue)."""
    from .rendermath import linear

    u, v = uv[:, 0], uv[:, 1]
    front = np.broadcast_to(linear((28, 104, 64)), (len(u), 3)).copy()
    front[(u < 0.035) | (u > 0.965) | (v > 0.955)] = linear((200, 204, 210))
    return front, np.broadcast_to(linear((190, 140, 50)), (len(u), 3)).copy()


TEXTURES = {"alice": cape_texture, "bob": _bob_texture}


def render_frame(recs: list[Recording], index: dict[str, dict[int, int]], tick: int, size: tuple[int, int]) -> Any:
    from .drawmeshes import capsule_mesh, cloth_mesh
    from .render import Camera, draw_scene

    meshes, props = [], []
    for r in recs:
        i = index[r.kind][tick]
        m = cloth_mesh(r.positions[i], r.triangles, (128, 128, 128))
        m.uv, m.texture, m.sheen = grid_uv(CAPE_ROWS, CAPE_COLS), TEXTURES[r.kind], 0.2
        meshes.append(m)
        props += r.props[i]
    for p0, p1, radius, colour in props:
        meshes.append(capsule_mesh(p0, p1, radius, colour, segments=20 if radius > 0.02 else 8))
    cam = Camera.look_at(EYE, TARGET, FOV, size)
    caption = "Drape: two clients' capes in one scene, over Zenoh" if size[0] >= 480 else ""
    return draw_scene(
        size,
        meshes,
        cam,
        bounds=BOUNDS,
        fade_floor=True,
        supersample=1.5,
        shadow_region=True,
        caption=f"{caption}   tick {tick}",
    )


def _render_chunk(args: tuple[Path, list[int], tuple[int, int], int]) -> list[Path]:
    return render_chunk(*args, WALKERS, render_frame, "crossing")


def run(args: argparse.Namespace) -> int:
    """Alice first (her cape founds the scene and lets bob in), then bob; both go together."""
    return run_stage(args, WALKERS, run_client, _render_chunk, "drape-crossing.gif", one_by_one=True)
