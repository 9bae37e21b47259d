"""The failover scenarios of ``drape chaos`` (see :mod:`drape.server.tools.chaos`): ``kill``
(SIGKILL of servers under game clients whose cloths the SDK placed by load, repeatable with
``--kills``, each server restarted after a moment) and ``pause`` (SIGSTOP of a game client past
the server's lease and grace period). Both use game clients with the SDK's defaults (``failover=True``)
(:class:`FailoverClient`), measure how soon every cloth is served again and how far its first
state is from its last, and judge against issue 11: every cloth back within 1 s, within 1 cm.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import time
from typing import Any

import numpy as np

from drape.client.placement import spread

from .chaos_clients import GoodClient
from .chaos_faults import FAILOVER_GAP_S, Context, Stage, judge
from .chaos_harness import WAIT, ChaosServer
from .chaos_window import Window

log = logging.getLogger(__name__)


def _failover_client_main(
    endpoints: list[str],
    server_id: str | None,
    client_id: str,
    cloths: int,
    size: int,
    records: Any,
    ready: Any,
    stop: Any,
) -> None:
    """A game client process with the SDK's failover on: its states as (cloth index, tick, time),
    each failover event, and the distance of the first state after a failover to the last before."""
    logging.basicConfig(level=logging.WARNING)
    from drape.client import DrapeClient

    try:
        # the SDK's defaults (failover on): what a game using the README's first example gets
        with DrapeClient(endpoints, server_id=server_id, client_id=client_id, timeout=WAIT) as client:
            handles: list[Any] = []
            current: dict[int, tuple[str, np.ndarray]] = {}

            def on_state(st: Any, j: int) -> None:
                had = current.get(j)
                if had is not None and had[0] != st.cloth:  # the first state of the cloth's new incarnation
                    records.put(
                        ("jump", j, float(np.linalg.norm(st.positions - had[1], axis=1).max()), time.monotonic())
                    )
                current[j] = (st.cloth, st.positions)
                records.put((j, int(st.tick), time.monotonic()))

            def on_failover(ev: Any) -> None:
                j = next((k for k, h in enumerate(handles) if h is ev.handle), -1)
                records.put(
                    (
                        "failover",
                        j,
                        ev.reason,
                        ev.ok,
                        ev.kept,
                        ev.new_server,
                        ev.detected_ns / 1e9,
                        ev.done_ns / 1e9,
                        ev.resumed_tick,
                    )
                )

            client.on_failover(on_failover)
            for j in range(cloths):
                # horizontal at rest: hanging from two corners after a second or two, far from its rest pose
                h = client.submit_grid(
                    size, size, 0.5, 0.5, origin=(1.0 * j, 2.0, 0.0), pinned=[0, size - 1], material={"damping": 0.1}
                )
                h.on_state(functools.partial(on_state, j=j))
                handles.append(h)
            records.put(("ready", [h.id for h in handles], client.client_id, time.monotonic()))
            ready.set()
            stop.wait()
            records.put(("where", [h.server_id for h in handles], client_id, time.monotonic()))
            client.close(remove=False)
    except BaseException as e:  # report, never hang the parent
        records.put(("error", repr(e), client_id, time.monotonic()))


class FailoverClient(GoodClient):
    """A GoodClient whose process runs the SDK with ``failover=True``, connected to several
    servers (``server_id`` None: each cloth placed by the servers' load); ``events`` and ``jumps``
    (distance, time) as the process reported them."""

    def __init__(self, endpoints: list[str], server_id: str | None, name: str, cloths: int = 1, size: int = 8) -> None:
        self.events: list[tuple[Any, ...]] = []
        self.jumps: dict[int, list[tuple[float, float]]] = {}
        self._start(_failover_client_main, "failover", endpoints, server_id, name, cloths, size)

    def _record(self, rec: tuple[Any, ...]) -> bool:
        if rec[0] == "failover":
            self.events.append(rec[1:])
        elif rec[0] == "jump":
            self.jumps.setdefault(rec[1], []).append((rec[2], rec[3]))
        else:
            return False
        return True

    def failover_report(self, cloths: int, t_fault: float, t_from: float) -> list[dict[str, Any]]:
        """Per cloth: back (a state after ``t_from``), the gap from ``t_from`` (the liveliness
        loss, or SIGCONT) to its first state there, its failover events and the distance of its
        first state after the failover to the last before."""
        out = []
        with self._lock:
            events = list(self.events)
            jumps = {k: list(v) for k, v in self.jumps.items()}
        for j in range(cloths):
            first = self.first_receipt_after(j, t_from + 1e-3)
            evs = [e for e in events if e[0] == j]
            outage = self.outage(j, t_fault)
            out.append(
                {
                    "cloth": j,
                    "back": first is not None,
                    "gap_s": None if first is None else round(first - t_from, 3),
                    "outage_s": None if outage is None else round(outage, 3),
                    "events": [
                        {
                            "reason": e[1],
                            "ok": e[2],
                            "kept": e[3],
                            "server": e[4],
                            "detect_to_reply_s": round(e[6] - e[5], 3),
                            "resumed_tick": e[7],
                        }
                        for e in evs
                    ],
                    "first_state_jump_cm": [round(100 * x, 2) for x, _ in jumps.get(j, [])],
                }
            )
        return out


def kill(ctx: Context, cloths: int = 8) -> dict[str, Any]:
    """kill -9 of servers under placed failover clients, ``--kills`` times, each restarted after a
    moment: is every cloth served again, how soon after the liveliness loss, from where it was?

    ``ctx.kill_servers`` (2-4) servers, peers on loopback; two game clients (the SDK,
    ``failover=True``, connected to all, no server id) place their ``cloths`` by the servers'
    load. Kill k SIGKILLs server k mod N, restarts it (same id and endpoint) ``ctx.kill_gap``
    seconds later and waits until the cloths it held are back on the others before the next."""
    n = max(2, min(4, ctx.kill_servers))
    args = ("--grace-period", str(ctx.grace_period), *ctx.serve_args)
    servers: list[ChaosServer] = []
    clients: list[FailoverClient] = []
    kills: list[dict[str, Any]] = []
    logs = [0]  # tracebacks of the servers already stopped
    try:
        for k in range(n):
            servers.append(
                ChaosServer(ctx.out, f"kill-{k}", args, [s.endpoint for s in servers], rss_limit_mb=ctx.rss_limit_mb)
            )
            servers[-1].wait_ready()
        endpoints = [s.endpoint for s in servers]
        half = max(1, cloths // 2)
        clients = [FailoverClient(endpoints, None, f"game{c}", m) for c, m in enumerate((half, cloths - half)) if m]
        for c in clients:
            c.wait_ready()
        time.sleep(2.0)  # the cloths hang nearly still; every server published its load
        at_start = [int((s.stats.next(WAIT) or {}).get("cloths", 0)) for s in servers]
        for k in range(ctx.kills):
            i = k % n
            victim = servers[i]
            held = int(victim.stats.latest().get("cloths", 0))
            t_kill = time.monotonic()
            victim.kill(signal.SIGKILL)
            victim.proc.wait(10)
            logs[0] += victim.log_counts()["tracebacks"]
            victim.stop()
            time.sleep(ctx.kill_gap)
            servers[i] = ChaosServer(
                ctx.out,
                f"kill-{i}-restart{k}",
                args,
                [s.endpoint for s in servers if s is not victim],
                rss_limit_mb=ctx.rss_limit_mb,
                endpoint=victim.endpoint,
                server_id=victim.server_id,
            )
            servers[i].wait_ready()
            t_end = time.monotonic() + WAIT
            while time.monotonic() < t_end and _moved(clients, t_kill) < held:
                time.sleep(0.1)
            time.sleep(1.0)  # their first states
            kills.append(_kill_report(clients, k, victim.server_id, held, t_kill))
        time.sleep(1.0)
        t_check = time.monotonic()
        time.sleep(1.0)
    finally:
        for c in clients:
            c.close()
        for s in servers:
            logs[0] += s.log_counts()["tracebacks"] if s.alive() else 0
            s.stop()
    served = [c.last_receipt(j) >= t_check for c in clients for j in range(len(c.log.cloth_ids))]
    failed = [e for c in clients for e in c.events if not e[2]]
    gaps = [g for x in kills for g in x["gaps_s"]]
    jumps = [v for x in kills for v in x["jumps_cm"]]
    m: dict[str, Any] = {
        "servers": n,
        "kills": ctx.kills,
        "cloths": cloths,
        "cloths_per_server_at_start": at_start,
        "spread_at_start": round(spread(at_start), 3),
        "failovers": sum(x["back"] for x in kills),
        "lost": served.count(False) + len(failed),
        "back_pct": round(100.0 * sum(x["back"] for x in kills) / max(1, sum(x["held"] for x in kills)), 1),
        "per_kill": kills,
        "liveliness_lost_after_kill_s": max((x["detected_after_s"] or 0.0 for x in kills), default=None),
        "max_gap_after_liveliness_loss_s": max(gaps, default=None),
        "max_first_state_jump_cm": max(jumps, default=None),
        "tracebacks": logs[0],
    }
    # the table's columns: cloths lost, the worst gap from a liveliness loss to a cloth's first state
    m["good_lost"] = m["lost"]
    m["good_worst_gap_ms"] = None if not gaps else round(1000 * max(gaps), 1)
    fails = []
    if m["lost"]:
        fails.append(f"{m['lost']} of {cloths} cloths lost over {ctx.kills} kills")
    short = [x for x in kills if x["back"] < x["held"]]
    if short:
        fails.append(f"kill {short[0]['kill']}: {short[0]['back']} of {short[0]['held']} cloths came back")
    if gaps and max(gaps) > FAILOVER_GAP_S:
        fails.append(f"longest gap after the liveliness loss {max(gaps)} s > {FAILOVER_GAP_S} s")
    if jumps and max(jumps) > 1.0:
        fails.append(f"a first state after failover {max(jumps)} cm from the last before (> 1 cm)")
    if m["tracebacks"]:
        fails.append(f"{m['tracebacks']} tracebacks in the servers' logs")
    return {**m, "fails": fails}


def _moved(clients: list[FailoverClient], since: float) -> int:
    """Failover events (ok or not) detected after ``since``."""
    return sum(1 for c in clients for e in list(c.events) if e[5] >= since)


def _kill_report(clients: list[FailoverClient], k: int, server: str, held: int, t_kill: float) -> dict[str, Any]:
    """One kill: the cloths it hit, how many came back, each one's gap from the liveliness loss
    (the earliest detection) to its first state after, and its first state's distance to its last."""
    evs = [(c, e) for c in clients for e in list(c.events) if e[5] >= t_kill]
    t_lost = min((e[5] for _, e in evs), default=t_kill)
    gaps, jumps = [], []
    for c, e in evs:
        first = c.first_receipt_after(e[0], e[6])
        if e[2] and first is not None:
            gaps.append(round(first - t_lost, 3))
        with c._lock:
            jumps += [round(100 * d, 2) for d, t in c.jumps.get(e[0], []) if t >= t_kill]
    return {
        "kill": k,
        "server": server,
        "held": held,
        "back": sum(1 for _, e in evs if e[2]),
        "detected_after_s": round(t_lost - t_kill, 3) if evs else None,
        "gaps_s": gaps,
        "jumps_cm": jumps,
        "to": sorted({str(e[4]) for _, e in evs if e[2]}),
    }


def pause(ctx: Context, cloths: int = 2) -> dict[str, Any]:
    """SIGSTOP a failover client process (the SDK, ``failover=True``) for ``pause_s`` seconds, then
    SIGCONT: are its cloths served again within 1 s, and from where they were?"""
    with Stage(ctx, "pause") as st:
        sleeper = FailoverClient([st.server.endpoint], st.server.server_id, "sleeper", cloths)
        try:
            sleeper.wait_ready()
            time.sleep(2.0)
            w = Window.open(st.server)
            t_stop = time.monotonic()
            reclaimed0 = st.server.stats.latest().get("reclaimed", 0)
            pid = sleeper.proc.pid
            if pid is None or pid <= 0:  # never signal a process group by accident
                raise RuntimeError("the paused client has no process id")
            os.kill(pid, signal.SIGSTOP)
            time.sleep(ctx.pause_s)
            t_cont = time.monotonic()
            os.kill(pid, signal.SIGCONT)
            time.sleep(max(3.0, FAILOVER_GAP_S * 3))
            m = w.close([st.good] if st.good else [])
            # when the server gave the sleeper's cloths up: the first stats publication counting them
            gone = [t for t, s in list(st.server.stats.samples) if t > t_stop and s.get("reclaimed", 0) > reclaimed0]
            m["reclaimed_after_s"] = round(gone[0] - t_stop, 1) if gone else None
        finally:
            sleeper.close()
    back = sleeper.failover_report(cloths, t_stop, t_cont)
    for x in back:
        x["back"] = x["gap_s"] is not None and x["gap_s"] <= FAILOVER_GAP_S
    n_back = sum(x["back"] for x in back)
    jumps = [v for x in back for v in x["first_state_jump_cm"]]
    m.update(
        paused_s=ctx.pause_s,
        cloths=cloths,
        back=n_back,
        back_pct=round(100.0 * n_back / cloths, 1),
        per_cloth=back,
        max_gap_after_sigcont_s=max((x["gap_s"] for x in back if x["gap_s"] is not None), default=None),
        max_first_state_jump_cm=max(jumps, default=None),
    )
    fails = judge(m, rss=False)
    if n_back < cloths:
        fails.append(
            f"{n_back} of {cloths} cloths served within {FAILOVER_GAP_S} s of SIGCONT "
            f"(reclaimed by the server: {m.get('reclaimed', 0)})"
        )
    if jumps and max(jumps) > 1.0:
        fails.append(f"a first state after failover {max(jumps)} cm from the last before (> 1 cm)")
    return {**m, "fails": fails}
