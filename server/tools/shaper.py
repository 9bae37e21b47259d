"""A user-space link shaper: a TCP proxy that gives each direction of every connection through it
a home link's rate, one-way delay and queue, so that a player's Zenoh session can be measured
behind a 20 Mbit/s, 20 ms link on one machine (issue 21; docs/codec.md).

    shaper = Shaper(("127.0.0.1", 7447), rate_bps=20e6, delay_s=0.020, queue_bytes=256 << 10)
    shaper.start()          # listens on shaper.endpoint: tcp/127.0.0.1:<port>
    ...                     # a client session connects there (client mode: only through it)
    shaper.stop()

Each direction is a bottleneck: bytes leave at ``rate_bps`` (a byte's turn comes when the ones
before it have left) and are delivered ``delay_s`` after they left; at most ``queue_bytes`` wait
to leave (when the queue is full the proxy stops reading, so the sender's TCP send buffer fills
up, as behind a real one). The proxy's own sockets keep small kernel buffers (``SOCKET_BUFFER``
each way, and its readers at most one chunk), so that bytes wait in the link's queue or in the
sender's, never megabytes in the proxy's receive buffer, which a real link does not have (the
kernel grows a receive buffer to several MB while the proxy does not read). ``rate_bps`` 0: no
limit. The proxy
runs on its own asyncio loop in a thread; it counts the bytes each way and keeps the last chunks'
schedule (``Direction.chunks``: when each was read, left at the rate, was due and was delivered).
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

CHUNK = 16 << 10  # bytes read at a time
SOCKET_BUFFER = 64 << 10  # SO_RCVBUF of the proxy's sockets (the kernel doubles it)


CHUNKS_KEPT = 1024  # chunks whose schedule a Direction keeps


@dataclass
class Chunk:
    """One chunk through a direction (monotonic seconds): read from the sender, its turn on the
    link (``start``: when the bytes before it have left), ``left`` (sent at the rate), ``due``
    (``left`` + the delay) and ``delivered`` (written to the receiver: ``due`` or later)."""

    n: int
    read: float
    start: float
    left: float
    due: float
    delivered: float = 0.0


@dataclass
class Direction:
    """One direction's shape, and what went through it."""

    rate_bps: float = 0.0
    delay_s: float = 0.0
    queue_bytes: int = 256 << 10
    bytes: int = 0  # delivered
    peak_queue: int = 0
    # the last chunks' schedule, oldest first: what the shaper decided, whatever the machine's pace
    chunks: deque[Chunk] = field(default_factory=lambda: deque(maxlen=CHUNKS_KEPT))


@dataclass
class Shaper:
    target: tuple[str, int]
    rate_bps: float = 20e6  # down (target -> client); up gets ``up_rate_bps`` (None: the same)
    delay_s: float = 0.020  # one way, each direction
    queue_bytes: int = 256 << 10
    up_rate_bps: float | None = None
    host: str = "127.0.0.1"
    port: int = 0  # 0: a free one
    down: Direction = field(init=False)
    up: Direction = field(init=False)

    def __post_init__(self) -> None:
        if self.rate_bps < 0 or self.delay_s < 0 or self.queue_bytes < CHUNK:
            raise ValueError(f"rate and delay must be >= 0 and the queue at least {CHUNK} bytes")
        self.down = Direction(self.rate_bps, self.delay_s, self.queue_bytes)
        up = self.rate_bps if self.up_rate_bps is None else self.up_rate_bps
        self.up = Direction(up, self.delay_s, self.queue_bytes)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: asyncio.AbstractServer | None = None
        self._ready = threading.Event()
        self._tasks: set[asyncio.Task] = set()

    @property
    def endpoint(self) -> str:
        return f"tcp/{self.host}:{self.port}"

    def start(self) -> Shaper:
        self._thread = threading.Thread(target=self._run, name="drape-shaper", daemon=True)
        self._thread.start()
        if not self._ready.wait(10.0):
            raise RuntimeError("the shaper did not start")
        return self

    def stop(self) -> None:
        loop = self._loop
        if loop is not None and loop.is_running():
            loop.call_soon_threadsafe(self._close)
        if self._thread is not None:
            self._thread.join(10.0)

    def __enter__(self) -> Shaper:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- the loop's side ----------------------------------------------------------------------
    def _run(self) -> None:
        self._loop = loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._serve())
        finally:
            loop.close()

    async def _serve(self) -> None:
        lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        lsock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)  # inherited by accepted ones
        lsock.bind((self.host, self.port))
        self._server = await asyncio.start_server(self._accept, sock=lsock, limit=CHUNK)
        self.port = self._server.sockets[0].getsockname()[1]
        self._stopped = asyncio.Event()
        self._ready.set()
        await self._stopped.wait()
        self._server.close()
        tasks = list(self._tasks)
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)  # every connection closed before the loop
        await self._server.wait_closed()

    def _close(self) -> None:
        self._stopped.set()

    async def _accept(self, creader: asyncio.StreamReader, cwriter: asyncio.StreamWriter) -> None:
        try:
            ssock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            ssock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)  # before connect: the window
            ssock.setblocking(False)
            try:
                await asyncio.get_running_loop().sock_connect(ssock, self.target)
            except OSError:
                ssock.close()
                raise
            sreader, swriter = await asyncio.open_connection(sock=ssock, limit=CHUNK)
        except OSError as e:
            log.warning("shaper: cannot reach %s:%d: %s", *self.target, e)
            cwriter.close()
            return
        pumps = [
            asyncio.ensure_future(self._pump(sreader, cwriter, self.down)),
            asyncio.ensure_future(self._pump(creader, swriter, self.up)),
        ]
        me = asyncio.current_task()
        if me is not None:
            self._tasks.add(me)
        self._tasks.update(pumps)
        try:
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        except asyncio.CancelledError:
            pass  # the shaper stopping: close this connection below, and end quietly
        finally:
            for t in pumps:
                t.cancel()
            await asyncio.gather(*pumps, return_exceptions=True)
            self._tasks.difference_update(pumps)
            if me is not None:
                self._tasks.discard(me)
            for w in (cwriter, swriter):
                w.close()

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, d: Direction) -> None:
        """Read while the link's backlog (bytes not yet sent at its rate) leaves room in its
        queue; a second task delivers each chunk once it has been sent and its delay has passed."""
        queue: deque[tuple[Chunk, bytes]] = deque()  # in order
        more = asyncio.Event()
        free_at = 0.0  # when the link has sent everything read so far
        done = False

        async def deliver() -> None:
            while True:
                while not queue:
                    if done:
                        return
                    more.clear()
                    await more.wait()
                chunk, data = queue[0]
                wait = chunk.due - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
                queue.popleft()
                chunk.delivered = time.monotonic()
                d.chunks.append(chunk)  # before the receiver can see it
                writer.write(data)
                await writer.drain()
                d.bytes += len(data)

        sender = asyncio.ensure_future(deliver())
        try:
            while True:
                if d.rate_bps > 0:  # the bottleneck's queue: full, stop reading (the sender's buffer fills)
                    backlog = (free_at - time.monotonic()) * d.rate_bps / 8
                    d.peak_queue = max(d.peak_queue, int(backlog))
                    over = backlog - (d.queue_bytes - CHUNK)
                    if over > 0:
                        await asyncio.sleep(over * 8 / d.rate_bps)
                        continue
                data = await reader.read(CHUNK)
                if not data:
                    break
                read = time.monotonic()
                start = max(read, free_at)
                free_at = start + (len(data) * 8 / d.rate_bps if d.rate_bps > 0 else 0.0)
                queue.append((Chunk(len(data), read, start, free_at, free_at + d.delay_s), data))
                more.set()
        finally:
            done = True
            more.set()
            try:
                await sender
            except Exception:
                pass
