"""Builds off the tick by default (issue 26): a ``drape serve`` with its default settings on a cold
kernel cache (DRAPE_CACHE_DIR, and so Drape's PoCL cache, in an empty directory) takes a burst of
the first cloths of new feature sets and builds none of their kernels on the tick thread. Proved
by counted events from the server's own ``/metrics``, not by the machine's pace (a build on the
tick took 208-446 ms per set, issue 26, but so can a loaded CI machine's tick): every program the
server process built, by the thread that built it (``drape_kernel_builds_total{thread}``): none on
the tick, every one since start-up on the cook thread; and each set's first cloth built and run by the build
child first (``drape_build_child_cloths_total{outcome}``: one ``ran`` a set, none fallen back to a
build in the server), which fills the driver's cache the server then builds from and runs each
kernel once, so that no first-launch compile is left for the tick either. Slow (a cold start-up
builds every feature set in a child first)."""

from __future__ import annotations

import itertools
import time

import pytest

from drape.client import protocol as P
from drape.server.tools.chaos_faults import grid_request
from drape.server.tools.chaos_harness import ChaosServer, reply_outcome, zenoh_session

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

SETS = 8  # feature sets of the burst (the first ones of every combination of FEATURE_NAMES)


def stats_where(server: ChaosServer, ok, timeout: float = 120.0) -> dict:
    """The server's first stats publication from now on for which ``ok(stats)`` holds."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        st = server.stats.next(5.0)
        if st is not None and ok(st):
            return st
    raise AssertionError(f"no stats publication as expected in {timeout:.0f} s: {server.stats.latest()}")


def test_a_burst_of_new_feature_sets_on_a_cold_kernel_cache_builds_nothing_on_the_tick(tmp_path, monkeypatch):
    monkeypatch.setenv("DRAPE_CACHE_DIR", str(tmp_path / "cache"))  # device verdicts and PoCL: cold
    monkeypatch.delenv("POCL_CACHE_DIR", raising=False)
    monkeypatch.delenv("DRAPE_BUILD_IN_CHILD", raising=False)  # the default (tests/conftest.py sets off)
    server = ChaosServer(tmp_path, "offtick", metrics=True)
    try:
        server.wait_ready(timeout=600.0)
        before = server.build_counts()
        session = zenoh_session(server.endpoint)
        keys = P.Keys()
        # held like a game's SDK: on a loaded machine a first build outlasts the grace period
        token = session.liveliness().declare_token(keys.alive_client("features"))
        combos = [c for n in range(1, 3) for c in itertools.combinations(P.FEATURE_NAMES, n)][:SETS]
        outcomes = []
        try:
            for combo in combos:  # the first cloth of each set (retried while 'overloaded': admission's word)
                req = grid_request("features", 16, features=combo)
                for _ in range(20):
                    got = [
                        reply_outcome(r)
                        for r in session.get(keys.submit(server.server_id), payload=P.encode_submit(req), timeout=120)
                    ]
                    if got != ["overloaded"]:
                        break
                    time.sleep(0.5)
                outcomes += got
            # every cloth on the server, then a later tick: each has been stepped, so built
            first = stats_where(server, lambda st: st.get("cloths") == SETS)
            stats_where(server, lambda st: st.get("tick", 0) > first.get("tick", 0))
            after = server.build_counts()
        finally:
            token.undeclare()
            session.close()
        assert outcomes == ["ok"] * len(combos), outcomes

        builds = {t: n - before["kernel_builds"].get(t, 0) for t, n in after["kernel_builds"].items()}
        assert after["kernel_builds"]["tick"] == 0, f"kernels built on the tick thread: {after}"
        # every program since start-up built by the cook thread (a set whose options are another's shares its program)
        assert builds["cook"] > 0 and sum(builds.values()) == builds["cook"], f"builds since start-up: {builds}"
        child = {o: n - before["build_child"].get(o, 0) for o, n in after["build_child"].items()}
        assert child == {"ran": SETS, "failed": 0, "memory_killed": 0}, f"the build child's first cloths: {child}"
        assert server.log_counts()["tracebacks"] == 0
    finally:
        server.stop()
