"""``drape demo``: a server and three game clients on loopback, drawn from what they received.

The server runs as its own process (``drape serve``, Zenoh peer mode on 127.0.0.1, the default
OpenCL device: PoCL's CPU device when there is no GPU). Three client processes submit a cloth
each through the client SDK and steer it every tick, as a game would:

- a flag on a pole, pinned along its left edge, in gusting wind (wind feature);
- a curtain held at its top edge, a ball swinging through it (colliders);
- a cape whose pinned top edge follows a character walking a circle, its body a capsule
  (colliders and tethers).

Each client keeps the states it received over Zenoh; the demo then renders them into PNG
frames and an animated GIF in ``--out`` and prints where they are.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import multiprocessing as mp
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .procs import ServerExited, ServerProcess, require_extra

log = logging.getLogger(__name__)

TICK_HZ = 60.0
BOUNDS = ((-0.4, 0.0, -1.3), (4.6, 2.4, 1.3))
KINDS = ("flag", "curtain", "cape")
COLOURS = {"flag": (200, 60, 50), "curtain": (70, 110, 200), "cape": (120, 60, 160)}


@dataclass
class Recording:
    kind: str
    ticks: np.ndarray  # (F,)
    positions: np.ndarray  # (F, n, 3)
    triangles: np.ndarray
    spheres: list  # per frame: list of (centre, radius)
    capsules: list  # per frame: list of (p0, p1, radius)
    received: int
    missing: int
    duplicates: int


# ------------------------------------------------------------------------------------------------
# Client processes


def _ball(t: float) -> tuple[tuple[float, float, float], float]:
    """The ball swinging through the curtain: a pendulum in the z direction."""
    swing = 0.6 * math.sin(1.6 * t)
    return (2.4, 1.0 + 0.25 * (1 - math.cos(1.6 * t)), swing), 0.28


def _walker(t: float) -> tuple[np.ndarray, np.ndarray]:
    """The cape wearer at time t: shoulder centre and body rotation. They start where the cape
    was cooked, facing -z, and walk a circle (turning left), bobbing a little."""
    r, w = 0.5, 1.1
    a = w * t
    start = np.array([3.75, 1.75, 0.0])
    pos = start + np.array([r * (1 - math.cos(a)), 0.05 * abs(math.sin(4 * a)), -r * math.sin(a)])
    c, s = math.cos(-a), math.sin(-a)  # rotation about y taking the facing -z to the heading
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return pos, rot


def run_client(kind: str, endpoint: str, seconds: float, fps: float, out: str, ready: Any, go: Any) -> None:
    """One game client: submit, then (once every client has its cloth: ``go``) steer every tick
    and record states at ``fps`` for ``seconds``."""
    logging.basicConfig(level=logging.WARNING)
    from drape.client import DrapeClient

    every = max(1, int(round(TICK_HZ / fps)))
    frames, ticks, spheres, capsules = [], [], [], []
    seen: set[int] = set()
    dup = 0
    with DrapeClient(endpoint, timeout=30.0) as client:
        if kind == "flag":
            cols, rows = 24, 16
            cloth = client.submit_grid(
                cols,
                rows,
                1.2,
                0.8,
                orientation="vertical",
                origin=(0.0, 2.1, 0.0),
                pinned=[r * cols for r in range(rows)],
                features=["wind", "xpbd"],
                material={"drag": 1.2, "lift": 0.6, "mass": 0.3, "compliance": (1e-5, 1e-4, 1e-2)},
                wind=(5.0, 0.0, 1.0),
                iterations=10,
                substeps=2,
            )
        elif kind == "curtain":
            cols, rows = 28, 26
            cloth = client.submit_grid(
                cols,
                rows,
                1.3,
                1.6,
                orientation="vertical",
                origin=(1.75, 2.15, 0.0),
                pinned=list(range(cols)),
                features=["colliders"],
                links={"bending": True},
                material={"mass": 0.8, "friction": 0.3, "damping": 0.01},
                iterations=12,
            )
        else:
            cols, rows = 16, 20
            cloth = client.submit_grid(
                cols,
                rows,
                0.6,
                0.9,
                orientation="vertical",
                origin=(3.45, 1.75, 0.0),
                pinned=list(range(cols)),
                features=["colliders", "tethers"],
                links={"bending": True},
                material={"mass": 0.6, "friction": 0.4, "tether_limit": 1.05, "damping": 0.01},
                iterations=10,
                substeps=2,
            )
        ready.set()
        go.wait()
        cloth.clear()  # the recordings start together: states queued while others submitted go
        assert cloth.rest_positions is not None, "the SDK keeps a submitted cloth's rest positions"
        rest_top = np.asarray(cloth.rest_positions[:cols], np.float64)
        start = time.monotonic()
        first_tick = None
        for state in cloth.states(timeout=10.0):
            if state.tick in seen:
                dup += 1
                continue
            seen.add(state.tick)
            first_tick = state.tick if first_tick is None else first_tick
            t = (state.tick - first_tick + 1) / TICK_HZ
            sph, cap = [], []
            if kind == "flag" and state.tick % 15 == 0:
                gust = 5.0 + 3.0 * math.sin(0.9 * t) + 1.5 * math.sin(2.3 * t)
                cloth.set(wind=(gust, 0.0, 1.5 * math.sin(0.5 * t)), wait=False)
            elif kind == "curtain":
                c, r = _ball(t)
                cloth.set_colliders([{"type": "sphere", "center": c, "radius": r}], wait=False)
                sph.append([list(c), r])
            elif kind == "cape":
                pos, rot = _walker(t)
                offsets = rest_top - rest_top.mean(0)  # the shoulder line, along x at rest
                chest = pos + rot @ np.array([0.0, 0.0, -0.17])  # the body is in front of the cape
                p0, p1 = chest + [0, -0.05, 0], chest + [0, -0.9, 0]
                body = [{"type": "capsule", "p0": tuple(p0), "p1": tuple(p1), "radius": 0.16}]
                # one message per tick, not waited for: what a game loop does
                cloth.move_pins(list(range(cols)), pos + offsets @ rot.T, colliders=body, wait=False)
                cap.append([p0.tolist(), p1.tolist(), 0.16])
            if state.tick % every == 0:
                frames.append(np.array(state.positions, np.float32))
                ticks.append(state.tick)
                spheres.append(sph)
                capsules.append(cap)
            if time.monotonic() - start > seconds:
                break
        span = (max(seen) - min(seen) + 1) if seen else 0
        np.savez_compressed(
            Path(out) / f"{kind}.npz",
            ticks=np.asarray(ticks, np.int64),
            positions=np.asarray(frames, np.float32).reshape(len(frames), -1, 3),
            triangles=np.asarray(cloth.triangles, np.int32),
            received=len(seen),
            missing=span - len(seen),
            duplicates=dup,
        )
        (Path(out) / f"{kind}-colliders.json").write_text(json.dumps({"spheres": spheres, "capsules": capsules}))


def load_recording(out: Path, kind: str) -> Recording:
    d = np.load(out / f"{kind}.npz")
    coll = json.loads((out / f"{kind}-colliders.json").read_text())
    spheres, capsules = coll["spheres"], coll["capsules"]
    return Recording(
        kind,
        d["ticks"],
        d["positions"],
        d["triangles"],
        list(spheres),
        list(capsules),
        int(d["received"]),
        int(d["missing"]),
        int(d["duplicates"]),
    )


# ------------------------------------------------------------------------------------------------
# Rendering


def render(recs: list[Recording], out: Path, size: tuple[int, int], fps: float) -> tuple[list[Path], Path]:
    from .render import render_scene, write_gif, write_png

    common = sorted(set.intersection(*(set(r.ticks.tolist()) for r in recs))) if recs else []
    index = {r.kind: {int(t): i for i, t in enumerate(r.ticks)} for r in recs}
    frames, paths = [], []
    for k, tick in enumerate(common):
        cloths, spheres = [], []
        capsules = [[[0.0, 0.0, 0.0], [0.0, 2.2, 0.0], 0.03]]  # the flag's pole (drawn only)
        for r in recs:
            i = index[r.kind][tick]
            cloths.append((r.positions[i], r.triangles, COLOURS[r.kind]))
            spheres += r.spheres[i]
            capsules += r.capsules[i]
        img = render_scene(
            size,
            cloths,
            view="iso",
            bounds=BOUNDS,
            spheres=spheres,
            capsules=capsules,
            title=f"Drape demo  tick {tick}",
        )
        p = out / f"frame_{k:04d}.png"
        write_png(p, img)
        paths.append(p)
        frames.append(img)
    gif = out / "drape-demo.gif"
    write_gif(gif, frames, fps=fps)
    return paths, gif


# ------------------------------------------------------------------------------------------------
# Command


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("server", "demo")
    require_extra("tools", "demo")
    parser.add_argument("--seconds", type=float, default=5.0, help="how long the clients run")
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="where frames and the GIF go")
    parser.add_argument("--fps", type=float, default=15.0, help="frames per second recorded and in the GIF")
    parser.add_argument("--size", default="640x400", help="frame size WxH")
    parser.add_argument("--port", type=int, default=0, help="server port on 127.0.0.1 (0: a free one)")
    parser.add_argument("--solver", default=None, help="server solver (default: the server's)")
    parser.add_argument("--device", default=None, help="OpenCL device for the server")


class ClientFailed(RuntimeError):
    """A demo client process failed or did not get going (its server alive)."""


def _run_clients(server: ServerProcess, args: argparse.Namespace, out: Path) -> None:
    """The three client processes against ``server``: started, waited on until each has its
    cloth accepted, told to go together, joined. The server is polled all along: when it exits,
    :class:`ServerExited` says so at once (with its last log lines) rather than a client's
    timeout blaming the client."""
    ctx = mp.get_context("spawn")
    procs = []
    go = ctx.Event()
    try:
        for kind in KINDS:
            ready = ctx.Event()
            p = ctx.Process(
                target=run_client,
                args=(kind, server.endpoint, args.seconds, args.fps, str(out), ready, go),
                name=f"demo-{kind}",
            )
            p.start()
            procs.append((p, ready))
        deadline = time.monotonic() + 60
        for p, ready in procs:
            while not ready.wait(0.2):
                server.check("the demo clients' cloths were accepted")
                if not p.is_alive():
                    raise ClientFailed(f"{p.name} failed before its cloth was accepted (exit code {p.exitcode})")
                if time.monotonic() > deadline:
                    raise ClientFailed(f"{p.name} did not get its cloth accepted in 60 s")
        go.set()
        log.info("clients running for %.1f s", args.seconds)
        deadline = time.monotonic() + args.seconds + 60
        for p, _ in procs:
            while p.is_alive() and time.monotonic() < deadline:
                p.join(0.2)
                if p.is_alive():
                    server.check(f"the demo clients finished their {args.seconds:g} s")
            if p.exitcode != 0:
                server.check(f"the demo clients finished their {args.seconds:g} s")
                raise ClientFailed(f"{p.name} failed (exit code {p.exitcode})")
    finally:
        for p, _ in procs:
            if p.is_alive():
                p.terminate()
                p.join(5)


def run(args: argparse.Namespace) -> int:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    # three small cloths: admission control (which refuses cloths while a busy machine stretches
    # the ticks) would only make the demo fail on a loaded machine
    serve_args = ["--tick-rate", str(TICK_HZ), "--no-admission"]
    if args.solver:
        serve_args += ["--solver", args.solver]
    if args.device:
        serve_args += ["--device", args.device]
    server = ServerProcess(serve_args, server_id="demo", port=args.port)
    try:
        _run_clients(server, args, out)
    except (ServerExited, ClientFailed) as e:
        print(f"drape demo: {e}", file=sys.stderr)
        return 1
    finally:
        server.stop(grace=15)
    recs = [load_recording(out, k) for k in KINDS]
    for r in recs:
        print(f"{r.kind:8s} received {r.received} states over Zenoh, {r.missing} missing, {r.duplicates} duplicated")
        if len(r.positions) and not np.isfinite(r.positions).all():
            raise RuntimeError(f"{r.kind}: non-finite positions received")
    w, h = (int(v) for v in args.size.lower().split("x"))
    log.info("rendering %d frames", min(len(r.ticks) for r in recs))
    paths, gif = render(recs, out, (w, h), args.fps)
    if not paths:
        raise RuntimeError("no frames: the clients received no common ticks")
    print(f"wrote {len(paths)} PNG frames: {paths[0]} .. {paths[-1]}")
    print(f"wrote {gif}")
    return 0
