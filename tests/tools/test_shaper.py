"""The link shaper (server/tools/shaper.py): its rate and its one-way delay are what they are set
to, and a full queue stops reading. Judged by the shaper's own schedule of every chunk (when it
was read, its turn on the link, sent at the rate, due the delay later, delivered no sooner),
which the machine's pace cannot change, and by measurements only on the side a loaded machine
cannot reach (a round trip never shorter than the two delays, a transfer never faster than the
rate): a busy machine only ever makes a delivery late."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from drape.server.tools.shaper import Direction, Shaper


@pytest.fixture
def echo():
    """A TCP server on loopback that echoes messages starting with PING and swallows the rest."""
    srv = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def handle(c: socket.socket) -> None:
        with c:
            while not stop.is_set():
                try:
                    d = c.recv(1 << 16)
                except OSError:
                    return
                if not d:
                    return
                if d.startswith(b"PING"):
                    c.sendall(d)

    def serve() -> None:
        srv.settimeout(0.2)
        while not stop.is_set():
            try:
                c, _ = srv.accept()
            except OSError:
                continue
            threading.Thread(target=handle, args=(c,), daemon=True).start()

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    yield srv.getsockname()
    stop.set()
    t.join(2)
    srv.close()


def _connect(port: int) -> socket.socket:
    c = socket.create_connection(("127.0.0.1", port), timeout=10)
    c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return c


def check_schedule(d: Direction, rate_bps: float, delay_s: float) -> None:
    """The shaper's own schedule of every chunk through ``d`` is the setting, to the float: its
    turn on the link when the bytes before it have left (or when it was read), sent at the rate,
    due the delay after it left, and never delivered before it was due (the machine's pace can
    only make a delivery late)."""
    chunks = list(d.chunks)
    assert chunks
    before = 0.0
    for c in chunks:
        assert c.start == max(c.read, before), c
        assert c.left - c.start == pytest.approx(c.n * 8 / rate_bps, rel=1e-9, abs=1e-9), c
        assert c.due - c.left == pytest.approx(delay_s, abs=1e-9) and c.delivered >= c.due, c
        before = c.left


def test_the_delay_is_the_setting_each_way(echo):
    with Shaper(echo, rate_bps=20e6, delay_s=0.020) as sh, _connect(sh.port) as c:
        rtts = []
        for _ in range(15):
            t = time.perf_counter()
            c.sendall(b"PING" + bytes(12))
            assert c.recv(100).startswith(b"PING")
            rtts.append(time.perf_counter() - t)
        assert len(sh.up.chunks) == len(sh.down.chunks) == 15  # one chunk a ping, each way
        for d in (sh.up, sh.down):
            check_schedule(d, 20e6, 0.020)
    assert min(rtts) >= 0.040, rtts  # two ways of 20 ms (and 16 bytes at 20 Mbit/s): never sooner


def test_the_rate_is_the_setting(echo):
    n = 1_250_000  # 0.5 s at 20 Mbit/s
    with Shaper(echo, rate_bps=20e6, delay_s=0.005) as sh, _connect(sh.port) as c:
        t = time.perf_counter()
        c.sendall(bytes(n))
        deadline = time.monotonic() + 30
        while sh.up.bytes < n and time.monotonic() < deadline:
            time.sleep(0.002)
        took = time.perf_counter() - t - 0.005  # less the one-way delay of the last byte
        assert sh.up.bytes == n == sum(c.n for c in sh.up.chunks)
        check_schedule(sh.up, 20e6, 0.005)
        chunks = list(sh.up.chunks)
        # the link was never idle while bytes waited: each chunk after the first read queued behind the last
        assert sum(c.start > c.read for c in chunks) >= len(chunks) // 2, "the transfer should keep the link busy"
    assert n * 8 / took <= 20e6 * 1.05, took  # never faster than the rate (a loaded machine: only slower)


def test_a_full_queue_stops_reading_and_the_setting_is_checked(echo):
    with Shaper(echo, rate_bps=1e6, delay_s=0.0, queue_bytes=64 << 10) as sh, _connect(sh.port) as c:
        c.setblocking(False)
        sent = 0
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:  # far more than a second of the link
            try:
                sent += c.send(bytes(1 << 16))
            except BlockingIOError:
                time.sleep(0.01)
        assert sh.up.peak_queue <= 64 << 10  # what waits to leave stays within the queue
        assert sh.up.bytes < sent  # the rest waits in the sockets' buffers, as behind a real link
    with pytest.raises(ValueError):
        Shaper(echo, rate_bps=-1)
