"""The thread sampler behind ``DRAPE_PROFILE``: it counts the named threads' stacks (driven by
explicit samples, not a timer), attributes inclusive and self shares, writes folded stacks and a
summary; and ``drape serve`` with the knob leaves both files after a clean stop."""

from __future__ import annotations

import threading

import pytest

from drape.server.service.process.sampler import ThreadSampler

pytestmark = pytest.mark.unit


def _park(ready: threading.Event, done: threading.Event) -> None:
    ready.set()
    done.wait(10.0)


def test_samples_count_the_named_threads_stacks(tmp_path) -> None:
    ready, done = threading.Event(), threading.Event()
    t = threading.Thread(target=_park, args=(ready, done), name="drape-tick-test")
    other = threading.Thread(target=_park, args=(threading.Event(), done), name="someone-else")
    t.start()
    other.start()
    try:
        assert ready.wait(5.0)
        s = ThreadSampler(prefixes=("drape-tick",))
        for _ in range(5):
            s.sample()
    finally:
        done.set()
        t.join()
        other.join()
    assert s.samples == {"drape-tick": 5}  # the other thread is not sampled
    text = s.summary()
    assert "== drape-tick: 5 samples" in text
    # _park is on the stack of every sample: 100 % inclusive; the innermost frame is the wait
    line = next(ln for ln in text.splitlines() if ln.endswith("test_sampler._park"))
    assert float(line.split()[0]) == 100.0
    folded, summary = s.write(tmp_path / "prof")
    lines = folded.read_text().splitlines()
    assert sum(int(ln.rsplit(" ", 1)[1]) for ln in lines) == 5
    assert all(ln.startswith("drape-tick;") and "test_sampler._park" in ln for ln in lines)
    assert summary.read_text() == text


def test_a_bad_rate_is_refused() -> None:
    with pytest.raises(ValueError, match="sampling rate"):
        ThreadSampler(hz=0)
