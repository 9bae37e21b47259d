"""The server gives memory back (drape.server.service.process.memory): once no cloth uses a feature
combination's program for ``program_idle_s`` the cook thread releases it and trims the heap
(counted), a cloth in use keeps its program, and a later cloth of the released combination is
served (the program built again, by the cook thread). Asserted on counted events only."""

from __future__ import annotations

import gc
import os
import platform
import re
import subprocess
import sys
import textwrap

import pytest
from conftest import TIMEOUT, collect, connect, make_config, wait_until

from drape.server.service import Server
from drape.server.service.process import memory as M
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import ClothParams, Features

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)


def test_programs_no_cloth_uses_are_released_and_the_heap_trimmed():
    with Server(make_config(program_idle_s=0.2, build_in_child="always")) as srv:
        dev = srv.call(lambda w: w.dev)
        keeper = srv.cook.memory

        def built(*features: str) -> bool:
            params = ClothParams(features=Features.from_names(list(features)))
            return srv.call(lambda w: w.ready(cook_grid(6, 6, pinned=[0, 5]), params))

        # each new feature set's submit waits for its kernels, built in a child process first: at
        # a loaded machine's pace (a CI run beside other work) that took longer than TIMEOUT
        c = connect(srv, timeout=6 * TIMEOUT)
        try:
            kept = c.submit_grid(6, 6, pinned=[0, 5], features=["tethers", "wind"])
            gone = c.submit_grid(6, 6, pinned=[0, 5], features=["xpbd"])
            collect(kept, 3)
            collect(gone, 3)
            assert built("tethers", "wind") and built("xpbd")
            helper = srv.cook.helper  # a CPU device: new kernels are built and run in a child first
            assert helper is not None and helper.runs == 2 and helper.failures == 0  # one per combination
            gone.remove()
            assert wait_until(lambda: not built("xpbd")), "the unused program was not released"
            assert keeper.released >= 1 and dev.released == keeper.released
            if M.CAN_TRIM:  # glibc: the release was followed by a trim
                assert wait_until(lambda: keeper.trims >= 1)
            assert built("tethers", "wind"), "a program in use was released"
            collect(kept, 3)

            at, runs = len(dev.builds), srv.cook.helper.runs
            again = c.submit_grid(6, 6, pinned=[0, 5], features=["xpbd"])
            collect(again, 3)
            assert len(dev.builds) > at and all(t.startswith("drape-cook") for _, t in dev.builds[at:])
            assert srv.cook.helper.runs == runs  # in the driver's cache already: no child run again
        finally:
            c.close()


def test_program_idle_zero_keeps_every_program():
    with Server(make_config(program_idle_s=0.0)) as srv:
        c = connect(srv)
        try:
            h = c.submit_grid(6, 6, pinned=[0, 5], features=["colliders"])
            collect(h, 3)
            h.remove()
            keeper = srv.cook.memory
            after = keeper.runs
            assert wait_until(lambda: keeper.runs >= after + 2)  # maintained since the cloth went
            assert keeper.released == 0 and srv.call(lambda w: w.dev.released) == 0
            params = ClothParams(features=Features.from_names(["colliders"]))
            assert srv.call(lambda w: w.ready(cook_grid(6, 6, pinned=[0, 5]), params))  # still built
        finally:
            c.close()


def test_wasted_heap_trims_back_off_and_recover(monkeypatch):
    """A growth trim whose pages are back one period on (a steady load re-faulting them) raises
    the growth that triggers the next trim, until the load's own swing no longer triggers one; a
    trim that stays given back lowers it again. Driven with a scripted RSS: no server, no clock."""
    rss = [100.0]  # a steady load swings between 50 MB (just trimmed) and 100 MB

    def trim() -> bool:
        rss[0] = 50.0
        return True

    monkeypatch.setattr(M, "rss_mb", lambda: rss[0])
    monkeypatch.setattr(M, "trim_heap", trim)
    keeper = M.MemoryKeeper(program_idle_s=0.0, device=lambda: None)
    for t in range(10):
        rss[0] = 100.0  # the pages the last trim gave back are in use again
        keeper.maintain(now=float(t))
    # two trims, both wasted: 4 -> 16 -> 64 MB, and the 50 MB swing no longer triggers one
    assert keeper.wasted == 2 and keeper.growth_mb == M.TRIM_GROWTH_MB * M.TRIM_BACKOFF**2
    assert keeper.trims == 2
    rss[0] = 500.0  # a real growth still trims ...
    keeper.maintain(now=10.0)
    assert keeper.trims == 3
    keeper.maintain(now=11.0)  # ... and its pages stay given back: the threshold comes down
    assert keeper.wasted == 2 and keeper.growth_mb == M.TRIM_GROWTH_MB * M.TRIM_BACKOFF


def test_the_trim_threshold_returns_when_the_load_goes_away(monkeypatch):
    """Trims backed off under a load trim at the first TRIM_GROWTH_MB again once the server's
    vertices fell by LOAD_DROP: the memory of a load that left is given back."""
    rss, load = [100.0], [4_000_000]

    def trim() -> bool:
        rss[0] = 50.0
        return True

    monkeypatch.setattr(M, "rss_mb", lambda: rss[0])
    monkeypatch.setattr(M, "trim_heap", trim)
    keeper = M.MemoryKeeper(program_idle_s=0.0, device=lambda: None, load=lambda: load[0])
    for t in range(5):
        rss[0] = 100.0
        keeper.maintain(now=float(t))
    assert keeper.growth_mb > M.TRIM_GROWTH_MB and keeper.trims == 2
    rss[0] = 60.0  # 10 MB over the last trim: under the raised threshold
    keeper.maintain(now=5.0)
    assert keeper.trims == 2
    load[0] = 1_000_000  # most cloths left
    keeper.maintain(now=6.0)
    assert keeper.growth_mb == M.TRIM_GROWTH_MB and keeper.trims == 3


def test_a_new_layout_is_frozen_and_frozen_cycles_are_collected_by_the_full_collection(monkeypatch):
    """The publisher freezes what is alive when the cloths' layout changes (out of the
    collector's scans); a cycle frozen that way is found only by collect_all()."""

    class Node:
        pass

    with Server(make_config()) as srv:
        c = connect(srv)
        try:
            monkeypatch.setattr(M, "_last_freeze", -1e9)  # no freeze in this process lately
            before = M.freezes
            collect(c.submit_grid(4, 4, pinned=[0]), 2)
            assert M.freezes > before
        finally:
            c.close()
    a, b = Node(), Node()
    a.other, b.other = b, a  # a reference cycle: only the collector frees it
    monkeypatch.setattr(M, "_last_freeze", -1e9)
    assert M.freeze_long_lived()
    assert not M.freeze_long_lived()  # at most once every FREEZE_MIN_INTERVAL_S
    del a, b
    gc.collect()  # the frozen cycle is not scanned
    assert M.collect_all() >= 2


#: A child process: a thread allocates 16 MiB in 64 KiB blocks (below the mmap threshold, like
#: Zenoh's fragments of a large message) and frees them; then the heap is trimmed. Prints the RSS
#: kept (MB) and, from glibc's malloc_stats on stderr, its arenas.
_THREAD_HEAP = textwrap.dedent(
    """
    import ctypes, sys, threading
    from drape.server.service.process import memory as M
    if sys.argv[1] == "configure_heap":
        assert M.configure_heap(4 << 20)
    else:
        assert M.set_mmap_threshold(4 << 20)  # the thresholds alone: each thread its own arena
    before = M.rss_mb()

    def work():
        blocks = [ctypes.create_string_buffer(64 << 10) for _ in range(256)]  # written: resident
        del blocks

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert M.trim_heap()
    print(round(M.rss_mb() - before, 1), flush=True)
    ctypes.CDLL("libc.so.6").malloc_stats()
    """
)


def _thread_heap(mode: str) -> tuple[float, list[tuple[int, int]]]:
    """(RSS kept in MB, for the log; each arena's (system bytes, in-use bytes) after the trim, as
    glibc's malloc_stats counts them: what the allocator holds from the OS, not the machine's
    noisy resident-set figure)."""
    env = {k: v for k, v in os.environ.items() if k not in ("MALLOC_ARENA_MAX", "GLIBC_TUNABLES")}
    out = subprocess.run(
        [sys.executable, "-c", _THREAD_HEAP, mode], env=env, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    arenas = re.findall(r"Arena \d+:\s*system bytes\s*=\s*(\d+)\s*in use bytes\s*=\s*(\d+)", out.stderr)
    return float(out.stdout.split()[-1]), [(int(a), int(b)) for a, b in arenas]


@pytest.mark.skipif(not M.CAN_TRIM or platform.libc_ver()[0] != "glibc", reason="glibc's malloc only")
def test_one_arena_lets_the_trim_give_back_what_a_thread_freed():
    """With drape serve's fixed trim threshold a thread's own arena keeps its freed top for good
    and malloc_trim does not reach it (the fuzz's RSS: Zenoh's receiving threads); with
    configure_heap every thread allocates from the one arena the trim gives back entirely.
    Judged by the allocator's own counts (malloc_stats), not by RSS, which varies by machine."""
    rss, arenas = _thread_heap("thresholds")
    print(f"thresholds: RSS kept {rss} MB, arenas (system, in use) {arenas}")
    assert len(arenas) == 2
    system, in_use = arenas[1]  # the thread's arena: its 16 MiB freed, and still held
    assert system >= 16 << 20 and in_use < 1 << 20
    rss, arenas = _thread_heap("configure_heap")
    print(f"configure_heap: RSS kept {rss} MB, arenas (system, in use) {arenas}")
    assert len(arenas) == 1
    system, in_use = arenas[0]
    assert system - in_use < 4 << 20  # the thread's 16 MiB given back by the trim


def test_one_arena_leaves_an_operators_arena_setting(monkeypatch):
    """MALLOC_ARENA_MAX or GLIBC_TUNABLES' arena_max in the environment (glibc applied it at
    start-up) is kept: one_arena calls no mallopt; without either it asks for one arena."""
    calls: list[tuple[int, int]] = []
    monkeypatch.setattr(M, "mallopt", lambda p, v: calls.append((p, v)) or True)
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    monkeypatch.setenv("MALLOC_ARENA_MAX", "8")
    assert not M.one_arena()
    monkeypatch.delenv("MALLOC_ARENA_MAX")
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=4")
    assert not M.one_arena()
    assert calls == []
    monkeypatch.delenv("GLIBC_TUNABLES")
    assert M.one_arena() and calls == [(M.M_ARENA_MAX, 1)]
