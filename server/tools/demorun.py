"""The ``drape demo`` stages' shared run: their client processes started against the stage's
server and told to go together, the server stopped, each client's recording (the states it
received over Zenoh, with what it steered) saved, loaded and checked, and every common tick
drawn into PNG frames (in two processes) and a GIF.

A stage (demo.py, demoscene.py) gives its client names, its client function
``client(name, endpoint, seconds, fps, out, ready, go)`` (which records with
:func:`save_recording`) and its render chunk (a module-level function, for the spawned pool,
that calls :func:`render_chunk` with its own ``render_frame``); :func:`run_stage` does the rest.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .procs import ServerExited, ServerProcess, demo_server

log = logging.getLogger(__name__)

TICK_HZ = 60.0  #: the stages' server's tick rate
#: a stage's render chunk: (out, ticks, size, first frame's number) -> the PNGs written
Chunk = Callable[[tuple[Path, list[int], tuple[int, int], int]], list[Path]]


@dataclass
class Recording:
    kind: str
    ticks: np.ndarray  # (F,)
    positions: np.ndarray  # (F, n, 3)
    triangles: np.ndarray
    props: list  # per frame: the steered things, [(p0, p1, radius, colour)] (capsules; spheres p0 == p1)
    received: int
    missing: int
    duplicates: int


class ClientFailed(RuntimeError):
    """A demo client process failed or did not get going (its server alive)."""


def save_recording(
    out: str | Path,
    kind: str,
    ticks: list[int],
    frames: list[np.ndarray],
    triangles: np.ndarray | None,
    props: list,
    seen: set[int],
    duplicates: int = 0,
) -> None:
    """A client's recording: the frames it kept (at their ticks), its cloth's triangles, what it
    steered per frame, and the count of states received (``seen``: their ticks), missing and
    duplicated."""
    span = (max(seen) - min(seen) + 1) if seen else 0
    np.savez_compressed(
        Path(out) / f"{kind}.npz",
        ticks=np.asarray(ticks, np.int64),
        positions=np.asarray(frames, np.float32).reshape(len(frames), -1, 3),
        triangles=np.asarray(triangles, np.int32),
        received=len(seen),
        missing=span - len(seen),
        duplicates=duplicates,
    )
    (Path(out) / f"{kind}-props.json").write_text(json.dumps(props))


def load_recording(out: Path, kind: str) -> Recording:
    d = np.load(out / f"{kind}.npz")
    props = json.loads((out / f"{kind}-props.json").read_text())
    return Recording(
        kind,
        d["ticks"],
        d["positions"],
        d["triangles"],
        list(props),
        int(d["received"]),
        int(d["missing"]),
        int(d["duplicates"]),
    )


def run_clients(
    server: ServerProcess,
    args: argparse.Namespace,
    out: Path,
    names: Sequence[str],
    client: Callable[..., None],
    one_by_one: bool = False,
) -> None:
    """The stage's client processes against ``server``: started (``one_by_one``: each after the
    one before has its cloth accepted, as a scene's founder comes before its guests), waited on
    until each has its cloth accepted, told to go together, joined. The server is polled all
    along: when it exits, :class:`ServerExited` says so at once (with its last log lines) rather
    than a client's timeout blaming the client."""
    ctx = mp.get_context("spawn")
    procs: list[tuple[Any, Any]] = []
    go = ctx.Event()

    def accepted(p: Any, ready: Any, deadline: float) -> None:
        while not ready.wait(0.2):
            server.check("the demo clients' cloths were accepted")
            if not p.is_alive():
                raise ClientFailed(f"{p.name} failed before its cloth was accepted (exit code {p.exitcode})")
            if time.monotonic() > deadline:
                raise ClientFailed(f"{p.name} did not get its cloth accepted in time")

    try:
        deadline = time.monotonic() + 150  # a loaded machine starts slowly
        for name in names:
            ready = ctx.Event()
            p = ctx.Process(
                target=client, args=(name, server.endpoint, args.seconds, args.fps, str(out), ready, go), name=name
            )
            p.start()
            procs.append((p, ready))
            if one_by_one:
                accepted(p, ready, deadline)
        for p, ready in procs:
            accepted(p, ready, deadline)
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


def render_chunk(
    out: Path,
    ticks: list[int],
    size: tuple[int, int],
    first: int,
    kinds: Sequence[str],
    render_frame: Callable[[list[Recording], dict[str, dict[int, int]], int, tuple[int, int]], Any],
    prefix: str,
) -> list[Path]:
    """A part of a stage's frames, ``<prefix>_<n>.png`` from ``first``, drawn by the stage's
    ``render_frame`` from the recordings of ``kinds``."""
    from .imagefiles import write_png

    recs = [load_recording(out, k) for k in kinds]
    index = {r.kind: {int(t): i for i, t in enumerate(r.ticks)} for r in recs}
    return [
        write_png(out / f"{prefix}_{first + k:04d}.png", render_frame(recs, index, tick, size))
        for k, tick in enumerate(ticks)
    ]


def render(
    recs: list[Recording], out: Path, size: tuple[int, int], fps: float, chunk: Chunk, name: str
) -> tuple[list[Path], Path]:
    """Every common tick's frame as PNG (in two processes: the demo machine may have two cores;
    ``chunk`` renders a part), then the GIF ``name``."""
    from PIL import Image

    from .imagefiles import write_gif

    common = sorted(set.intersection(*(set(r.ticks.tolist()) for r in recs))) if recs else []
    jobs = min(2, mp.cpu_count(), max(1, len(common)))
    parts = np.array_split(np.arange(len(common)), jobs)
    work = [(out, [common[i] for i in p.tolist()], size, int(p[0]) if len(p) else 0) for p in parts]
    if jobs > 1:
        with mp.get_context("spawn").Pool(jobs) as pool:
            paths = [q for part in pool.map(chunk, work) for q in part]
    else:
        paths = chunk(work[0]) if common else []
    frames = [np.asarray(Image.open(p).convert("RGB")) for p in paths]
    gif = out / name
    if frames:
        write_gif(gif, frames, fps=fps, colours=256)  # smooth shading: 128 colours band
    return paths, gif


def run_stage(
    args: argparse.Namespace,
    kinds: Sequence[str],
    client: Callable[..., None],
    chunk: Chunk,
    gif: str,
    one_by_one: bool = False,
) -> int:
    """A recorded stage from start to end: its server, its clients (:func:`run_clients`), the
    server stopped, the recordings loaded and checked (finite, counted), rendered into ``--out``
    (frames and ``gif``); 1 when the server or a client failed."""
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    server = demo_server(args, TICK_HZ)
    try:
        run_clients(server, args, out, kinds, client, one_by_one)
    except (ServerExited, ClientFailed) as e:
        print(f"drape demo: {e}", file=sys.stderr)
        return 1
    finally:
        server.stop(grace=15)
    recs = [load_recording(out, k) for k in kinds]
    width = max(len(k) for k in kinds)
    for r in recs:
        print(
            f"{r.kind:{width}s} received {r.received} states over Zenoh, {r.missing} missing, {r.duplicates} duplicated"
        )
        if len(r.positions) and not np.isfinite(r.positions).all():
            raise RuntimeError(f"{r.kind}: non-finite positions received")
    w, h = (int(v) for v in args.size.lower().split("x"))
    log.info("rendering %d frames", min(len(r.ticks) for r in recs))
    t0 = time.monotonic()
    paths, gif_path = render(recs, out, (w, h), args.fps, chunk, gif)
    log.info("rendered %d frames in %.1f s", len(paths), time.monotonic() - t0)
    return wrote(paths, gif_path)


def wrote(paths: list[Path], gif: Path) -> int:
    """What a stage wrote, said (0), or that it drew nothing (a RuntimeError)."""
    if not paths:
        raise RuntimeError("no frames: the clients received no common ticks")
    print(f"wrote {len(paths)} PNG frames: {paths[0]} .. {paths[-1]}")
    print(f"wrote {gif}")
    return 0
