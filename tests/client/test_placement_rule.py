"""drape.client.placement: the rule that chooses a server for a new cloth (PROTOCOL.md 11.3), on
real stats publications (the protocol's stats test vector, re-encoded with other loads, decoded
by the protocol): fewest vertices counting this client's own placements not yet in the stats,
then the lowest mean tick, servers without stats last, ties broken per client by a hash; a burst
from one client spreads; a refused placement does not count; a vanished server is ranked as
unknown. No network: the stats bytes are fed to the Placement as its subscriber would."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from drape.client import protocol as P
from drape.client.placement import Placement, load_from_stats, rank, spread

VECTORS = Path(__file__).resolve().parents[1] / "vectors"


def stats_vector() -> dict[str, Any]:
    vec = next(v for v in json.loads((VECTORS / "misc.json").read_text()) if v["name"] == "stats")
    return P.decode_stats(bytes.fromhex(vec["hex"]))


def stats_bytes(server: str, vertices: int, tick_ms: float = 1.5) -> bytes:
    """A stats publication of ``server`` as a server sends it (the vector's map, another load)."""
    st = stats_vector()
    st.update(server=server, vertices=vertices, cloths=vertices // 256)
    st["phases"]["tick"]["mean_ms"] = tick_ms
    return P.encode_stats(st)


def placement(servers: list[str], client: str = "game-1") -> Placement:
    live = list(servers)
    return Placement(client, lambda: live, stats_wait=0.05)


def place(pl: Placement, n: int, vertices: int = 256) -> list[str]:
    """``n`` submissions, each placed where the rule says and accepted."""
    out = []
    for _ in range(n):
        s = pl.choose()
        assert s is not None
        pl.placed(pl.placing(s, vertices), True)
        out.append(s)
    return out


def test_load_from_the_stats_vector():
    ld = load_from_stats("s1", stats_vector())
    assert (ld.known, ld.vertices, ld.tick_ms, ld.pending) == (True, 2048, 1.5, 0)
    assert not load_from_stats("s2", None).known


def test_fewest_vertices_then_lowest_tick_then_unknown_last():
    pl = placement(["a", "b", "c", "d"])
    assert pl.on_stats(stats_bytes("a", 4096, 1.0), "drape/server/a/stats") == "a"
    pl.on_stats(stats_bytes("b", 1024, 9.0), "drape/server/b/stats")
    pl.on_stats(stats_bytes("c", 1024, 2.0), "drape/server/c/stats")
    assert pl.ranked() == ["c", "b", "a", "d"]  # d: no stats yet
    assert pl.choose(exclude={"c"}) == "b"
    assert pl.choose(exclude={"a", "b", "c", "d"}) is None


def test_a_burst_from_one_client_spreads_by_load():
    pl = placement(["a", "b"])
    pl.on_stats(stats_bytes("a", 1024), "drape/server/a/stats")
    pl.on_stats(stats_bytes("b", 0), "drape/server/b/stats")
    got = place(pl, 12)
    # b is 1024 vertices (4 cloths) lighter: it takes the first 4, then they alternate
    assert got[:4] == ["b"] * 4
    assert got.count("a") == 4 and got.count("b") == 8
    assert spread([1024 + 256 * got.count("a"), 256 * got.count("b")]) == 0.0


def test_placements_count_until_the_servers_next_stats_include_them():
    pl = placement(["a", "b"])
    pl.on_stats(stats_bytes("a", 0), "", now=0.0)
    pl.on_stats(stats_bytes("b", 0), "", now=0.0)
    t1 = pl.placing("a", 300)
    pl.placed(t1, True, now=1.0)  # answered at 1.0
    t2 = pl.placing("a", 50)  # still in flight
    assert {ld.server: ld.total for ld in pl.loads(["a", "b"])} == {"a": 350, "b": 0}
    pl.on_stats(stats_bytes("a", 300), "", now=2.0)  # a's stats now count the first
    assert {ld.server: ld.total for ld in pl.loads(["a", "b"])} == {"a": 350, "b": 0}
    pl.placed(t2, True, now=3.0)
    pl.on_stats(stats_bytes("a", 350), "", now=2.5)  # published before the second was answered
    assert pl.loads(["a"])[0].total == 400  # 350 in the stats + the second (50) still counted
    pl.on_stats(stats_bytes("a", 350), "", now=4.0)
    assert pl.loads(["a"])[0].total == 350


def test_a_refused_placement_does_not_count():
    pl = placement(["a", "b"])
    pl.on_stats(stats_bytes("a", 0), "")
    pl.on_stats(stats_bytes("b", 100), "")
    pl.placed(pl.placing("a", 1000), False)  # overloaded
    assert pl.choose() == "a"


def test_ties_are_broken_per_client_not_alphabetically():
    firsts = []
    for i in range(200):
        pl = placement(["a", "b"], client=f"client-{i}")
        pl.on_stats(stats_bytes("a", 512), "")
        pl.on_stats(stats_bytes("b", 512), "")
        firsts.append(pl.choose())
        assert pl.choose() == firsts[-1]  # stable for one client
    assert 60 <= firsts.count("a") <= 140, firsts.count("a")


def test_a_vanished_server_is_unknown_until_it_publishes_again():
    pl = placement(["a", "b"])
    pl.on_stats(stats_bytes("a", 0), "")
    pl.on_stats(stats_bytes("b", 5000), "")
    pl.placed(pl.placing("a", 256), True)
    pl.server_gone("a")  # killed; restarted under the same id, it starts empty
    assert pl.ranked() == ["b", "a"]
    assert (pl.stats("a") or {}).get("tick_rate") == 60.0  # a failover still reads its tick rate
    pl.on_stats(stats_bytes("a", 0), "")
    assert pl.ranked() == ["a", "b"] and pl.loads(["a"])[0].pending == 0


def test_not_a_stats_message_is_ignored():
    pl = placement(["a"])
    assert pl.on_stats(b"\x00garbage", "drape/server/a/stats") is None
    assert pl.stats("a") is None


@pytest.mark.parametrize("counts, want", [([4, 4], 0.0), ([5, 3], 0.25), ([8, 0], 1.0), ([], 0.0), ([0, 0], 0.0)])
def test_spread_is_max_over_mean_minus_one(counts, want):
    assert spread(counts) == pytest.approx(want)


def test_rank_alone():
    loads = [load_from_stats("x", {"vertices": 10}), load_from_stats("y", {"vertices": 10}, pending=1)]
    assert rank(loads, "c") == ["x", "y"]


def test_the_tiebreak_is_the_documented_hash():
    """PROTOCOL.md 11.3 gives the tie-break's hash and one value of it, so every SDK ranks alike."""
    from drape.client.placement import tiebreak

    assert tiebreak("alice", "s1") == 14233298460419450548
    assert tiebreak("alice", "s2") != tiebreak("alice", "s1")
