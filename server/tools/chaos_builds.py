"""The build and preparation scenarios of ``drape chaos`` (issue 26; see :mod:`drape.server.tools.chaos`):
work a cloth brings before its first step (kernel builds, a big mesh's cook and tables) must not
take the ticks of the cloths already served, and what it held must be given back when it goes.
Each judged by the good client (:func:`~.chaos_faults.judge`) and by the server's longest
tick-thread tick in the window (``tick_max_ms``, from its stats' tick phase):

- ``cold-burst``: a server started on an empty kernel cache (``DRAPE_CACHE_DIR``: Drape's PoCL
  cache too) gets the first cloth of every feature set at once, not one after the other
  (``new-features`` in :mod:`.chaos_faults`); also judged by counted events from the server's
  ``/metrics`` (``kernel_builds``: none on the tick thread; ``build_child``: none failed);
- ``big-mesh``: a 32k-vertex triangle mesh beside the good client, then removed: refused
  (``overloaded``) or served with no tick over the budget, and the server's RSS back within the
  suite's 10 % after the memory upkeep ran. With the defaults admission refuses it on a CPU (trust
  is for small cloths, and its one work-group takes about 50 ms a step there);
  ``--serve-args=--no-admission`` serves it, to measure its preparation and its memory.

Bounded in messages and seconds; talks only to 127.0.0.1.
"""

from __future__ import annotations

import itertools
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from drape.client import protocol as P

from .chaos_faults import RETRY_LATER, TICK_HZ, Context, Stage, grid_request, judge
from .chaos_harness import WAIT
from .chaos_window import Window

MESH_SIDE = 181  # big-mesh: 181 x 181 = 32,761 vertices, 64,800 triangles
STALL_BUDGET_MS = 1000.0 / TICK_HZ  # a tick-thread tick over one period is a stall


def mesh_request(client: str, side: int = MESH_SIDE, size: float = 1.0) -> P.SubmitRequest:
    """A ``side`` x ``side`` vertex sheet as a triangle mesh (not a grid spec: the mesh path's
    cook and topology), hanging from its two top corners."""
    u = np.linspace(0.0, size, side, dtype=np.float32)
    x, y = np.meshgrid(u, u)
    vertices = np.stack([x.ravel(), 1.5 - y.ravel(), np.zeros(side * side, np.float32)], axis=1)
    i = np.arange(side - 1)
    a = (i[None, :] + side * i[:, None]).ravel()  # each cell's top-left vertex
    tris = np.concatenate([np.stack([a, a + side, a + 1], 1), np.stack([a + 1, a + side, a + side + 1], 1)])
    mesh = P.MeshSpec(vertices.astype(np.float32), tris.astype(np.uint32))
    return P.SubmitRequest(client=client, mesh=mesh, pinned=np.array([0, side - 1], np.uint32))


def _stall(m: dict[str, Any]) -> list[str]:
    """A tick-thread tick over one period in a stats period without other load (the suite's rule,
    :meth:`.chaos_window.Window.attribute`; the raw longest is ``tick_max_ms``)."""
    if m.get("tick_max_own_ms", 0.0) > STALL_BUDGET_MS:
        return [f"a tick-thread tick took {m['tick_max_own_ms']} ms > {STALL_BUDGET_MS:.1f} without other load"]
    return []


def cold_burst(ctx: Context) -> dict[str, Any]:
    """The first cloth of every feature set at once, on a server started with a cold kernel cache."""
    combos = [c for n in range(len(P.FEATURE_NAMES) + 1) for c in itertools.combinations(P.FEATURE_NAMES, n)]
    cache = Path(tempfile.mkdtemp(prefix="cold-cache-", dir=ctx.out))
    t0 = time.monotonic()
    env = {"DRAPE_CACHE_DIR": str(cache), "POCL_CACHE_DIR": None}
    with Stage(ctx, "cold-burst", env=env, metrics=True) as st:
        startup_s = time.monotonic() - t0
        st.declare_alive("burst")
        base = st.baseline()
        built = st.server.build_counts()
        w = Window.open(st.server)
        t1 = time.monotonic()
        boxes = [st.submit_async(grid_request("burst", 16, features=combo)) for combo in combos]
        for box in boxes:
            box["done"].wait(max(0.0, WAIT - (time.monotonic() - t1)))
        replied_s = time.monotonic() - t1
        time.sleep(1.0)  # the admitted cloths' first ticks
        m = w.close([st.good] if st.good else [])
        after = st.server.build_counts()
        for box in boxes:
            st.remove(box.get("reply", {}))
    outcomes = Counter(str(box.get("outcome", "no reply")) for box in boxes)
    m.update(
        baseline=base,
        startup_s=round(startup_s, 1),
        combinations=len(combos),
        accepted=outcomes["ok"],
        submit_outcomes=dict(outcomes),
        replies_s=round(replied_s, 2),
        # counted: the server's kernel builds during the burst by thread, its build child's cloths
        kernel_builds={t: n - built["kernel_builds"].get(t, 0) for t, n in after["kernel_builds"].items()},
        build_child={o: n - built["build_child"].get(o, 0) for o, n in after["build_child"].items()},
    )
    fails = judge(m, rss=False) + _stall(m)
    if m["kernel_builds"].get("tick", 0):
        fails.append(f"{m['kernel_builds']['tick']} kernel builds on the tick thread")
    if m["build_child"].get("failed", 0) or m["build_child"].get("memory_killed", 0):
        fails.append(f"the build child did not build every new set: {m['build_child']}")
    odd = {o: n for o, n in outcomes.items() if o != "ok" and o not in RETRY_LATER}
    if odd:
        fails.append(f"submits answered {odd}")
    return {**m, "fails": fails}


def big_mesh(ctx: Context) -> dict[str, Any]:
    """A 32k-vertex mesh beside the good client, then removed: no stalled tick, memory given back."""
    req = mesh_request("mesh")
    with Stage(ctx, "big-mesh") as st:
        st.declare_alive(req.client)  # its cook may take longer than the grace period
        base = st.baseline()
        w = Window.open(st.server)
        t0 = time.monotonic()
        box = st.submit_async(req)
        box["done"].wait(WAIT)
        replied_s = time.monotonic() - t0
        time.sleep(ctx.seconds)
        m = w.close([st.good] if st.good else [])
        rss_with = round(st.server.rss_mb(), 1)
        removed = st.remove(box.get("reply", {})) if st.server.alive() else "server gone"
        # the memory upkeep releases programs unused for program_idle_s and trims the heap about
        # once a second: measure after both
        time.sleep(ctx.program_idle_s + 3.0)
        m["rss_after_mb"] = round(st.server.rss_mb(), 1)
    m.update(
        baseline=base,
        vertices=len(req.mesh.vertices) if req.mesh is not None else 0,
        submit_outcome=box.get("outcome", "no reply yet"),
        submit_reply_s=round(replied_s, 2),
        rss_with_mesh_mb=rss_with,
        removed=removed,
    )
    fails = judge(m) + _stall(m)
    if m["submit_outcome"] not in ("ok", "overloaded"):
        fails.append(f"the mesh's submit got {m['submit_outcome']}")
    return {**m, "fails": fails}
