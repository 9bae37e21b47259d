"""``drape demo --stage crossing``: two characters of two game clients walk past each other, and
their capes brush (protocol 1.7 scenes: cloths of one scene collide with each other).

Alice's client founds the scene ``crossing`` with her cape, lets anyone in, and moves the scene's
colliders every tick: both walkers' bodies (torso, legs, head), sent once for the whole scene, so
that each cape keeps out of both bodies. Bob's client submits his cape into her scene. Each
client pins its cape around its own walker's shoulders every tick; the walkers come towards each
other along parallel lines 0.6 m apart, their capes (flared cones around their backs, dragged
out behind by the air) meeting at the sides as they pass. The server is ``drape serve`` as in
the three-cloth stage (server/tools/demo.py, whose cape, walker body, textures and renderer this
stage reuses); frames and ``drape-crossing.gif`` go to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import multiprocessing as mp
import sys
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from .demo import (
    CAPE_COLS,
    CAPE_ROWS,
    SHOULDER_Y,
    TICK_HZ,
    ClientFailed,
    Recording,
    _cape_texture,
    _uv,
    body_parts,
    cape_mesh,
    load_recording,
    render,
)
from .procs import ServerExited, ServerProcess, demo_server

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
            features=["colliders", "tethers", "wind"],
            links={"bending": True},
            material={
                "mass": 0.6,
                "stiffness": (1.0, 0.8, 0.15),
                "friction": 0.3,
                "tether_limit": 1.05,
                "damping": 0.01,
                "drag": 1.0,
                "lift": 0.0,
                "thickness": THICKNESS,
            },
            wind=(0.0, 0.0, 0.0),
            iterations=10,
            substeps=2,
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
        span = (max(seen) - min(seen) + 1) if seen else 0
        np.savez_compressed(
            Path(out) / f"{name}.npz",
            ticks=np.asarray(ticks, np.int64),
            positions=np.asarray(frames, np.float32).reshape(len(frames), -1, 3),
            triangles=np.asarray(cloth.triangles, np.int32),
            received=len(seen),
            missing=span - len(seen),
            duplicates=0,
        )
        (Path(out) / f"{name}-props.json").write_text(json.dumps(props))


def _bob_texture(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bob's cape: deep green with a silver border, lined in ochre (alice's is demo.py's blue)."""
    from .render import _linear

    u, v = uv[:, 0], uv[:, 1]
    front = np.broadcast_to(_linear((28, 104, 64)), (len(u), 3)).copy()
    front[(u < 0.035) | (u > 0.965) | (v > 0.955)] = _linear((200, 204, 210))
    return front, np.broadcast_to(_linear((190, 140, 50)), (len(u), 3)).copy()


TEXTURES = {"alice": _cape_texture, "bob": _bob_texture}


def render_frame(recs: list[Recording], index: dict[str, dict[int, int]], tick: int, size: tuple[int, int]) -> Any:
    from .render import Camera, capsule_mesh, cloth_mesh, draw_scene

    meshes, props = [], []
    for r in recs:
        i = index[r.kind][tick]
        m = cloth_mesh(r.positions[i], r.triangles, (128, 128, 128))
        m.uv, m.texture, m.sheen = _uv(CAPE_ROWS, CAPE_COLS), TEXTURES[r.kind], 0.2
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
    out, ticks, size, first = args
    from .render import write_png

    recs = [load_recording(out, k) for k in WALKERS]
    index = {r.kind: {int(t): i for i, t in enumerate(r.ticks)} for r in recs}
    return [
        write_png(out / f"crossing_{first + k:04d}.png", render_frame(recs, index, tick, size))
        for k, tick in enumerate(ticks)
    ]


def _run_clients(server: ServerProcess, args: argparse.Namespace, out: Path) -> None:
    """Alice first (her cape founds the scene and lets bob in), then bob; both go together."""
    ctx = mp.get_context("spawn")
    go, procs = ctx.Event(), []
    try:
        for name in WALKERS:
            ready = ctx.Event()
            p = ctx.Process(
                target=run_client, args=(name, server.endpoint, args.seconds, args.fps, str(out), ready, go), name=name
            )
            p.start()
            procs.append(p)
            deadline = time.monotonic() + 150
            while not ready.wait(0.2):
                server.check("the demo clients' capes were accepted")
                if not p.is_alive() or time.monotonic() > deadline:
                    raise ClientFailed(f"{name}'s cape was not accepted (exit code {p.exitcode})")
        go.set()
        deadline = time.monotonic() + args.seconds + 60
        for p in procs:
            while p.is_alive() and time.monotonic() < deadline:
                p.join(0.2)
            if p.exitcode != 0:
                server.check("the demo clients finished")
                raise ClientFailed(f"{p.name} failed (exit code {p.exitcode})")
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
                p.join(5)


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    server = demo_server(args, TICK_HZ)
    try:
        _run_clients(server, args, out)
    except (ServerExited, ClientFailed) as e:
        print(f"drape demo: {e}", file=sys.stderr)
        return 1
    finally:
        server.stop(grace=15)
    recs = [load_recording(out, k) for k in WALKERS]
    for r in recs:
        print(f"{r.kind:6s} received {r.received} states over Zenoh, {r.missing} missing")
        if len(r.positions) and not np.isfinite(r.positions).all():
            raise RuntimeError(f"{r.kind}: non-finite positions received")
    w, h = (int(v) for v in args.size.lower().split("x"))
    paths, gif = render(recs, out, (w, h), args.fps, chunk=_render_chunk, name="drape-crossing.gif")
    if not paths:
        raise RuntimeError("no frames: the clients received no common ticks")
    print(f"wrote {len(paths)} PNG frames: {paths[0]} .. {paths[-1]}")
    print(f"wrote {gif}")
    return 0
