"""The link shaper (server/tools/shaper.py): its rate and its one-way delay are what they are set
to, within 5 % (measured over a whole transfer and as the median of round trips, the best of
three tries: a busy machine's scheduling only ever makes a measurement late, never early, so a
shaper off by more than 5 % fails all three), and a full queue stops reading."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from drape.server.tools.shaper import Shaper


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


def test_the_delay_is_the_setting_each_way(echo):
    medians = []
    for _ in range(3):
        with Shaper(echo, rate_bps=20e6, delay_s=0.020) as sh, _connect(sh.port) as c:
            rtts = []
            for _ in range(15):
                t = time.perf_counter()
                c.sendall(b"PING" + bytes(12))
                assert c.recv(100).startswith(b"PING")
                rtts.append(time.perf_counter() - t)
            medians.append(sorted(rtts)[len(rtts) // 2])
        if medians[-1] <= 0.040 * 1.05:
            break
    assert 0.040 <= min(medians) <= 0.040 * 1.05, medians  # two ways of 20 ms (and 16 bytes at 20 Mbit/s)


def test_the_rate_is_the_setting(echo):
    n = 1_250_000  # 0.5 s at 20 Mbit/s
    rates = []
    for _ in range(3):
        with Shaper(echo, rate_bps=20e6, delay_s=0.005) as sh, _connect(sh.port) as c:
            t = time.perf_counter()
            c.sendall(bytes(n))
            deadline = time.monotonic() + 10
            while sh.up.bytes < n and time.monotonic() < deadline:
                time.sleep(0.002)
            took = time.perf_counter() - t - 0.005  # less the one-way delay of the last byte
            assert sh.up.bytes == n
            rates.append(n * 8 / took)
        if 20e6 * 0.95 <= rates[-1] <= 20e6 * 1.05:
            break
    assert 20e6 * 0.95 <= max(rates) <= 20e6 * 1.05, rates


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
