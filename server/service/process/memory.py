"""Giving memory back: the server releases kernel programs no cloth uses any more and returns
freed heap to the operating system, so that its RSS comes back after an abuse (issue 11's
"RSS back within 10 %").

Measured on PoCL (CPU, Debian PoCL 3.1 / LLVM 15; docs/reliability.md): each feature
combination's program holds about 1.5 MB of compiler state for as long as it is built (31
combinations: +46 MB), and glibc keeps what is freed in its heap: releasing every program left
RSS where it was, ``malloc_trim(0)`` after the release gave all of it back (197 -> 154 MB, 3-7 ms),
and ``malloc_trim`` alone (programs kept) gave back nothing. So :class:`MemoryKeeper`, run by the
cook thread about once a second, releases the programs unused for ``program_idle_s``
(``Device.release_idle``; built again from the driver's disk cache when a cloth needs one, about
25 ms on the cook thread) and trims the heap after a release, or when RSS grew by more than
``growth_mb`` (``TRIM_GROWTH_MB`` at first) since the last trim (fragments of large requests).

A trim whose pages are back within one period was wasted, and not free: under a steady load
(4096 cloths on the H100, RSS 600-700 MB, the payload copies of every tick) RSS grows 4 MB
again within a second, and each ``malloc_trim`` held the arenas' locks while it gave back pages
the next ticks faulted in again; the ticks stalled about 80 ms every 1.5-2 s (5 missed ticks
each, docs/loadtest.md, session 12). So a wasted growth trim multiplies the growth that
triggers the next one by ``TRIM_BACKOFF`` (up to ``TRIM_GROWTH_MAX_MB``), and a trim that
stays given back divides it again: a loaded server stops trimming after a few tries. When the
load goes away (the server's vertices fall by ``LOAD_DROP`` or more since the threshold was
last raised) the threshold is back at ``TRIM_GROWTH_MB``, so the memory of a load that left is
given back at the next run.

Python's cyclic garbage collector is kept off the tick the same way. Its full collections scan
every tracked object while holding the GIL: under 4096 cloths on the H100 one ran every ~2 s
and took 15-22 ms (up to 82 ms), a missed tick each time (docs/loadtest.md, session 12). What
is alive when the cloths' layout changes lives long (the modules, the records, the rosters), so
:func:`freeze_long_lived` collects the young generations (cyclic garbage of the last moments,
a fuzz's exceptions) and moves the rest out of the collector's scans (``gc.freeze``; it is
still freed by reference counting), at most once every ``FREEZE_MIN_INTERVAL_S``, and the
collections that remain scan only what came since;
:class:`MemoryKeeper` collects everything once every ``FULL_COLLECT_PERIOD_S`` (cyclic garbage
among the frozen objects is found then, at one pause per period).

``drape serve`` fixes glibc's thresholds and puts every thread on one malloc arena
(:func:`configure_heap`): a thread's own arena keeps its freed top for good under the fixed trim
threshold, out of ``malloc_trim``'s reach: after a fuzz of large messages, Zenoh's receiving
threads' arenas held most of the RSS that was not given back.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

PERIOD_S = 1.0  # how often the cook thread runs MemoryKeeper.maintain
TRIM_GROWTH_MB = 4.0  # trim without a release once RSS grew this much since the last trim (at first)
TRIM_GROWTH_MAX_MB = 1024.0  # the most that wasted trims raise that growth to
TRIM_BACKOFF = 4.0  # a wasted trim multiplies the growth that triggers the next one by this
TRIM_WASTED_SHARE = 0.75  # a trim is wasted when this share of what it gave back is back one period on
LOAD_DROP = 0.25  # the load fell by this share since the threshold was raised: back to TRIM_GROWTH_MB
FREEZE_MIN_INTERVAL_S = 5.0  # freeze_long_lived() freezes at most this often (layouts churn under a flood)

FULL_COLLECT_PERIOD_S = 600.0  # the frozen objects are unfrozen and everything collected this often
freezes = 0  # freeze_long_lived() calls in this process

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


_last_freeze = -FREEZE_MIN_INTERVAL_S


def freeze_long_lived() -> bool:
    """Collect the young generations, then move every object the collector tracks to its
    permanent generation, out of future scans (``gc.freeze``: a list splice); at most once every
    ``FREEZE_MIN_INTERVAL_S`` (False when skipped)."""
    global freezes, _last_freeze
    now = time.monotonic()
    if now - _last_freeze < FREEZE_MIN_INTERVAL_S:
        return False
    _last_freeze = now
    gc.collect(1)
    gc.freeze()
    freezes += 1
    return True


def collect_all() -> int:
    """Unfreeze, collect every generation, freeze again; returns the objects collected."""
    gc.unfreeze()
    try:
        return gc.collect()
    finally:
        gc.freeze()


def _libc(name: str, argtypes: list[Any]) -> Callable[..., int] | None:
    """The C library's function ``name`` (returning int), or None where it has none (musl, macOS)."""
    try:
        fn = getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = argtypes, ctypes.c_int
    return fn


_TRIM = _libc("malloc_trim", [ctypes.c_size_t])
_MALLOPT = _libc("mallopt", [ctypes.c_int, ctypes.c_int])
CAN_TRIM = _TRIM is not None
M_MMAP_THRESHOLD = -3  # glibc mallopt parameters
M_TRIM_THRESHOLD = -1
M_ARENA_MAX = -8
#: With the mmap threshold fixed, glibc also stops raising its trim threshold (it stays at 128 KiB),
#: so a tick's freed payload copies at the top of the heap went back to the OS every tick and were
#: faulted in afresh on the next. ``python -m drape.server.tools.putbench --copies-only`` (the
#: publisher's 16 ``bytes(view)`` copies of 1.5 MB a tick, 4096 quant16 cloths' worth; this 2-core
#: VM, medians of 3 rounds): glibc's own thresholds 11.2 ms a tick, the mmap threshold alone
#: 11.8 ms, both thresholds 1.2 ms. The heap is given back on purpose instead: MemoryKeeper's
#: malloc_trim when RSS grew or programs were released.
TRIM_THRESHOLD = 128 << 20


def set_mmap_threshold(nbytes: int) -> bool:
    """Allocations of ``nbytes`` or more get their own mapping, returned to the OS when freed
    (glibc ``mallopt(M_MMAP_THRESHOLD)``, which also stops glibc raising the threshold to the
    largest block freed so far, up to 32 MB, after which such blocks stay in the heap), and the
    top of the heap is kept up to TRIM_THRESHOLD (``M_TRIM_THRESHOLD``: fixing one fixes both,
    and glibc's fixed 128 KiB trim made every tick's payload copies fault in afresh). Measured:
    eight 8 MiB requests left the server +22 MB for good with glibc's default, +3.5 MB with a
    fixed 1 MiB threshold, and the 2,000-message fuzz +28 MB against +10 MB (1 or 4 MiB alike).
    False where there is no such call (or ``nbytes`` is 0: glibc's default kept)."""
    if nbytes <= 0:
        return False
    return mallopt(M_MMAP_THRESHOLD, int(nbytes)) and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)


def configure_heap(mmap_threshold: int) -> bool:
    """``drape serve``'s heap, set before its threads start: the thresholds fixed
    (:func:`set_mmap_threshold`) and, when they are, every thread on one malloc arena
    (:func:`one_arena`), so that the memory upkeep's ``malloc_trim`` reaches every free page.
    ``mmap_threshold`` 0 leaves glibc's own behaviour (dynamic thresholds, an arena per thread up
    to 8 per core), which trims each arena's top itself. True when the thresholds were fixed."""
    if not set_mmap_threshold(mmap_threshold):
        return False
    one_arena()
    return True


def one_arena() -> bool:
    """Every thread started from now on allocates from glibc's main arena (``mallopt(M_ARENA_MAX,
    1)``), unless ``MALLOC_ARENA_MAX`` or ``GLIBC_TUNABLES``' ``glibc.malloc.arena_max`` in the
    environment chose otherwise (an operator's comparison: glibc applied it at start-up).

    Why: with the trim threshold fixed at TRIM_THRESHOLD, the top of a thread's own arena (a
    64 MB heap of its own) is never given back when freed (glibc trims a thread arena's top only
    when it exceeds the trim threshold), and ``malloc_trim`` gives back the free chunks of every
    arena but the top only of the main one. Measured (``drape chaos fuzz``, 20,000 messages, 8 MiB
    limit; glibc's malloc_info, and gdb for each thread's arena): the arenas of Zenoh's receiving
    threads ``rx-0`` and ``rx-1``, which put large messages together from their fragments, grew
    by about 9 MB each and kept it as free top for good (1.3-1.6 MB each with a 1 MiB limit), RSS
    +7 to +11 %; with one arena +2.3 % (100,000 messages: +7.8 to +10.0 %, and +2.8 %). A thread
    allocating 16 MiB in 64 KiB blocks and freeing them keeps them after ``malloc_trim(0)``, and
    gives them back with one arena (tests/service/test_memory.py). The cost: one lock for every
    thread's allocations beyond its thread cache (the Python threads share the GIL anyway; on an
    H200 host, one server at 3584 quant16 cloths published in 10.4 / 11.0 ms a tick against
    10.1 / 6.7 with glibc's arenas: not settled, docs/loadtest.md session 13). Must run before
    the threads allocate: glibc fixes its arena limit once a ninth arena is asked for, and a
    thread keeps the arena it has. False
    where there is no such call or the environment chose."""
    if "MALLOC_ARENA_MAX" in os.environ or "arena_max" in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    return mallopt(M_ARENA_MAX, 1)


def mallopt(param: int, value: int) -> bool:
    """glibc ``mallopt(param, value)``; False where there is no such call or it refused."""
    return _MALLOPT is not None and bool(_MALLOPT(param, value))


def rss_mb() -> float | None:
    """This process's resident set in MB (Linux /proc), None elsewhere."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE / 1e6
    except (OSError, ValueError, IndexError):
        return None


def trim_heap() -> bool:
    """Return the free pages of every malloc arena to the OS (glibc ``malloc_trim(0)``; ctypes
    releases the GIL meanwhile). False where there is no such call."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


class MemoryKeeper:
    """What the cook thread does about memory: ``maintain()`` whenever :meth:`due` (counted)."""

    def __init__(self, program_idle_s: float, device: Callable[[], Any], load: Callable[[], int] = lambda: 0) -> None:
        self.program_idle_s = program_idle_s  # 0: programs are kept for good
        self._device = device  # the World's Device, or None (the reference solver has none)
        self._load = load  # the server's live vertices
        self._raised_at_load = 0  # the load when the trim threshold was last raised
        self.runs = 0  # maintain() calls
        self.released = 0  # programs released
        self.trims = 0  # heap trims
        self.trimmed_mb = 0.0  # RSS given back by them, in all
        self.wasted = 0  # growth trims whose pages were back one period on
        self.growth_mb = TRIM_GROWTH_MB  # the RSS growth since the last trim that triggers one
        self.full_collections = 0  # collect_all() calls
        self._next = time.monotonic() + PERIOD_S
        self._next_full = time.monotonic() + FULL_COLLECT_PERIOD_S
        self._after_trim: float | None = None  # RSS after the last trim
        self._judge: tuple[float, float] | None = None  # RSS before and after the last growth trim

    def due(self, now: float | None = None) -> bool:
        return (time.monotonic() if now is None else now) >= self._next

    def maintain(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        self._next = now + PERIOD_S
        self.runs += 1
        if now >= self._next_full:
            self._next_full = now + FULL_COLLECT_PERIOD_S
            self.full_collections += 1
            log.debug("full garbage collection: %d objects collected", collect_all())
        released = 0
        dev = self._device()
        if dev is not None and self.program_idle_s > 0:
            released = dev.release_idle(self.program_idle_s, now)
            self.released += released
        before = rss_mb()
        if self._judge is not None and before is not None:
            self._judge_last_trim(before)
        raised = self._raised_at_load
        if self.growth_mb > TRIM_GROWTH_MB and raised > 0 and self._load() <= (1.0 - LOAD_DROP) * raised:
            self.growth_mb = TRIM_GROWTH_MB  # the load that made trims wasted is gone
        grew = before is not None and (self._after_trim is None or before > self._after_trim + self.growth_mb)
        if not (released or grew) or not trim_heap():
            return
        self.trims += 1
        after = rss_mb()
        self._after_trim = after
        if not released and before is not None and after is not None and before > after:
            self._judge = (before, after)
        if before is not None and after is not None:
            self.trimmed_mb += max(0.0, before - after)
            log.debug("released %d program(s), trimmed the heap: RSS %.1f -> %.1f MB", released, before, after)

    def _judge_last_trim(self, now_mb: float) -> None:
        """One period after a growth trim: back off when its pages came back, else recover."""
        assert self._judge is not None
        before, after = self._judge
        self._judge = None
        if now_mb - after >= TRIM_WASTED_SHARE * (before - after):
            self.wasted += 1
            self.growth_mb = min(TRIM_GROWTH_MAX_MB, self.growth_mb * TRIM_BACKOFF)
            self._raised_at_load = self._load()
            log.debug("wasted trim (%.1f -> %.1f -> %.1f MB): next at +%.0f MB", before, after, now_mb, self.growth_mb)
        else:
            self.growth_mb = max(TRIM_GROWTH_MB, self.growth_mb / TRIM_BACKOFF)
