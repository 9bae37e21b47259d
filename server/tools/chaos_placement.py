"""``drape chaos acl-placement`` (issue 26; see :mod:`drape.server.tools.chaos`): placement behind
the generated ACL router. Two servers (``--identity keys``, client mode) behind an
:class:`~.chaos_router.AuthRouter` (TLS unless ``--auth tcp``), one SDK client with no server id
submits 8 cloths one after the other: the SDK must see every server's load (their stats on the
wildcard key ``{ns}/server/*/stats``, which the generated ACL once let through only on exact keys:
8 submits took 12.1 s and were spread blind) and place the 8 in under 1 s, on both servers.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Any

from .chaos_faults import Context, judge
from .chaos_harness import WAIT, ChaosServer
from .chaos_router import AuthRouter

CLOTHS = 8
PLACED_S = 1.0  # the 8 submits placed within this (issue 26)
SEEN_S = 20.0  # the longest wait for every server's load before the submits
PLACER = "placer"


def acl_placement(ctx: Context) -> dict[str, Any]:
    """8 cloths of one SDK client placed by load over 2 servers behind the generated ACL router."""
    from drape.client import DrapeClient, DrapeError

    names = [f"acl-placement-{k}" for k in range(2)]
    ids = [ChaosServer.id_of(n) for n in names]
    router = AuthRouter(ctx.out, ids, [PLACER], ctx.auth or "tls")
    args = ("--grace-period", str(ctx.grace_period), *ctx.serve_args)
    servers = [ChaosServer(ctx.out, n, args, rss_limit_mb=ctx.rss_limit_mb, router=router) for n in names]
    out: dict[str, Any] = {"servers": len(servers), "transport": router.endpoint.split("/")[0]}
    try:
        for s in servers:
            s.wait_ready()
        with DrapeClient(router.endpoint, timeout=WAIT, **router.sdk(PLACER)) as client:
            t0 = time.monotonic()
            while time.monotonic() - t0 < SEEN_S and not all(x.known for x in client.placement.loads(ids)):
                time.sleep(0.05)
            seen = [x.server for x in client.placement.loads(ids) if x.known]
            out["loads_seen"] = len(seen)
            out["loads_seen_s"] = round(time.monotonic() - t0, 2)
            t1 = time.monotonic()
            handles = [client.submit_grid(8, 8, origin=(1.5 * j, 1.0, 0.0), pinned=[0, 7]) for j in range(CLOTHS)]
            out["placed_s"] = round(time.monotonic() - t1, 2)
            out["placement"] = dict(Counter(h.server_id for h in handles))
            served = 0
            for h in handles:
                try:
                    h.next_state(10.0)
                    served += 1
                except (TimeoutError, DrapeError):
                    pass
            out["served"] = served
            for h in handles:
                h.remove()
        time.sleep(0.5)
        out["tracebacks"] = sum(s.log_counts()["tracebacks"] for s in servers)
        out["server_alive"] = all(s.alive() for s in servers)
    finally:
        for s in servers:
            s.stop()
        router.close()
    fails = judge(out, good=False, rss=False)
    if out.get("loads_seen") != len(ids):
        fails.append(f"the SDK saw the load of {out.get('loads_seen')} of {len(ids)} servers in {SEEN_S:.0f} s")
    if out.get("placed_s", float("inf")) > PLACED_S:
        fails.append(f"{CLOTHS} submits placed in {out.get('placed_s')} s > {PLACED_S:g}")
    if len(out.get("placement", {})) < len(ids):
        fails.append(f"placed on {out.get('placement')}: not every server used")
    if out.get("served", 0) < CLOTHS:
        fails.append(f"{out.get('served')} of {CLOTHS} cloths got a state")
    return {**out, "fails": fails}
