"""Home links in ``drape loadtest`` (issue 21): some or all client processes reach the server
through a :class:`~.shaper.Shaper` each (a rate, a one-way delay and a queue per direction), in
Zenoh client mode with shared memory off (so every byte crosses the link, as
:mod:`.homelink`'s player does), optionally taking every k-th state (protocol 1.8: ``--link-client-rate``
1, 2, 3 or ``auto``). Their states per second per cloth, latency p50 / p99 and longest gap
between two states of one cloth are reported apart from the unshaped clients' (``Report.links``);
the report's own states, losses and latency are then the unshaped clients' (the server's figures,
whether the load is held), since a shaped client's link, not the server, decides its states.

    drape loadtest --clients 4 --cloths 16 --link-rate 5 --link-delay 40 --link-share 0.5
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from drape.client import protocol as P

from .shaper import Shaper

#: A shaped client's Zenoh configuration: no shared memory (on one host Zenoh would hand the
#: states over in it, past the link).
NO_SHM = "{transport: {shared_memory: {enabled: false}}}"


@dataclass(frozen=True)
class LinkSpec:
    """The home link of the shaped clients: ``rate_mbit`` each way (0: no shaping), ``delay_ms``
    one way, ``queue_kib`` queued each way, ``share`` of the clients behind it (the last ones),
    ``client_rate`` the rate they take (1.8)."""

    rate_mbit: float = 0.0
    delay_ms: float = 0.0
    queue_kib: int = 256
    share: float = 1.0
    client_rate: str = "1"

    @property
    def on(self) -> bool:
        return self.rate_mbit > 0 or self.delay_ms > 0

    def shaped(self, clients: int) -> list[bool]:
        """Which of ``clients`` client processes are behind the link (the last ones; one at least)."""
        if not self.on:
            return [False] * clients
        n = min(clients, max(1, math.ceil(self.share * clients)))
        return [i >= clients - n for i in range(clients)]

    def shapers(self, endpoint: str | Sequence[str], shaped: list[bool]) -> list[Shaper | None]:
        """One started shaper per shaped client, in front of the first of ``endpoint`` (tcp/host:port)."""
        first = endpoint if isinstance(endpoint, str) else endpoint[0]
        host, _, port = first.split("/", 1)[1].rpartition(":")
        return [
            Shaper(
                (host, int(port)),
                rate_bps=self.rate_mbit * 1e6,
                delay_s=self.delay_ms / 1e3,
                queue_bytes=self.queue_kib << 10,
            ).start()
            if s
            else None
            for s in shaped
        ]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("home links (issue 21: clients behind a link shaper)")
    g.add_argument("--link-rate", type=float, default=0.0, help="Mbit/s each way of the shaped clients' link (0: none)")
    g.add_argument("--link-delay", type=float, default=0.0, help="ms one way of the shaped clients' link")
    g.add_argument("--link-queue", type=int, default=256, help="KiB each direction of the link queues")
    g.add_argument("--link-share", type=float, default=1.0, help="share of the clients behind the link (the last ones)")
    g.add_argument(
        "--link-client-rate",
        default="1",
        choices=[*map(str, P.RATES), "auto"],
        help="1.8 (1.9: 6, 12): the rate shaped clients take",
    )


def link_spec(args: argparse.Namespace) -> LinkSpec:
    return LinkSpec(args.link_rate, args.link_delay, args.link_queue, args.link_share, args.link_client_rate)


def longest_gap_ms(rx_ns: np.ndarray) -> float:
    """The longest time between two states of one cloth received (in receive order)."""
    if len(rx_ns) < 2:
        return float("nan")
    return float(np.diff(np.sort(rx_ns)).max()) / 1e6


def group_summary(results: Sequence[Any], seconds: float) -> dict[str, Any]:
    """States per second per cloth (mean and least), latency p50 / p99 / max and the longest gap
    of a group of clients' results (ClientResult, whose ``extra`` carries ``per_cloth_states``
    and ``longest_gap_ms``)."""
    per_cloth = [n for r in results for n in r.extra.get("per_cloth_states", [])]
    lat = np.concatenate([r.latencies_ms for r in results]) if results else np.zeros(0)
    gaps = [r.extra.get("longest_gap_ms", float("nan")) for r in results]
    rate = np.array(per_cloth, np.float64) / max(seconds, 1e-9)
    p50, p99, mx = np.percentile(lat, [50, 99, 100]) if len(lat) else (float("nan"),) * 3
    return {
        "clients": len(results),
        "cloths": len(per_cloth),
        "states_per_s_per_cloth_mean": round(float(rate.mean()), 2) if len(rate) else float("nan"),
        "states_per_s_per_cloth_min": round(float(rate.min()), 2) if len(rate) else float("nan"),
        "latency_ms": {"p50": round(float(p50), 2), "p99": round(float(p99), 2), "max": round(float(mx), 2)},
        "longest_gap_ms": round(float(np.nanmax(gaps)), 1) if gaps and not np.isnan(gaps).all() else float("nan"),
        "step_downs": sum(int(r.extra.get("step_downs", 0)) for r in results),
        "rate_at_end": sorted({int(r.extra.get("rate_at_end", 1)) for r in results}),
    }


def links_report(results: Sequence[Any], seconds: float, link: LinkSpec) -> dict[str, Any]:
    """``Report.links``: the shaped and unshaped clients' figures apart (empty without a link)."""
    if not link.on:
        return {}
    shaped = [r for r in results if r.extra.get("shaped")]
    plain = [r for r in results if not r.extra.get("shaped")]
    return {
        "link": {
            "rate_mbit": link.rate_mbit,
            "delay_ms": link.delay_ms,
            "queue_kib": link.queue_kib,
            "client_rate": link.client_rate,
        },
        "shaped": group_summary(shaped, seconds),
        "unshaped": group_summary(plain, seconds),
    }


def print_links(links: dict[str, Any]) -> None:
    if not links:
        return
    lk = links["link"]
    print(
        f"  home link {lk['rate_mbit']:g} Mbit/s, {lk['delay_ms']:g} ms, queue {lk['queue_kib']} KiB, "
        f"client rate {lk['client_rate']}:"
    )
    for name in ("shaped", "unshaped"):
        g = links[name]
        if not g["clients"]:
            continue
        lat = g["latency_ms"]
        print(
            f"    {name:9s} {g['clients']} clients, {g['cloths']} cloths: {g['states_per_s_per_cloth_mean']:.1f} "
            f"states/s per cloth (least {g['states_per_s_per_cloth_min']:.1f}), latency p50 {lat['p50']:.1f} / "
            f"p99 {lat['p99']:.1f} ms, longest gap {g['longest_gap_ms']:.0f} ms, step-downs {g['step_downs']}, "
            f"every {g['rate_at_end']} at the end"
        )


__all__ = ["NO_SHM", "LinkSpec", "add_arguments", "group_summary", "link_spec", "links_report", "print_links"]
