"""One load-test client process: it behaves like a game client with many cloths.

It submits its cloths, SUBMITS_IN_FLIGHT at a time (counting refused submits by error code: a
server past its knee answers ``overloaded``). All of a client's cloths share one origin, so the
server cooks their fabric once and shares it, as it does any identical request. Once told to go,
it moves every cloth's pins once per tick (with bundles one batch control per tick carrying one
1.4 ``moves`` block, built from one (n, 2, 3) array with no loop over the cloths; one control
per cloth without) and records every state it receives: tick, latency (server timestamp ->
receipt, one host so one clock) and the time from the payload's arrival to the state's delivery
(the SDK's decode cost). With ``decode_sample`` N > 1 (bundles) it decodes fully only one cloth
in N and counts the others' states from their headers (tick, server time: received, lost, late
and latency as for the decoded ones), so that the clients' cores measure the server's capacity
rather than the SDK's decode. The parent tells it which server ticks the measured window covers; only
states of those ticks count. Behind a home link (``ClientSpec.link_endpoint``, loadlink.py) it
connects in client mode to its shaper only, shared memory off, at its rate (1.8), and reports its
states per cloth and longest gap apart.

Runs in a ``spawn``-ed process: everything it needs comes through its arguments.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

SUBMITS_IN_FLIGHT = 16  # a client's submits awaiting their reply at once
OVERLOADED_RETRIES = 3  # tries again of a submit refused ``overloaded`` (ClientSpec.retries)
RETRY_AFTER_S = 0.5  # the pause before each
TURN_STATS_WAIT_S = 10.0  # at most this long for stats that count the clients placed before
SAMPLED_DECODE = 16  # Workload.decode_one_in's auto: one cloth in this many decoded fully...
AUTO_SAMPLE_ABOVE = 2048  # ...for predictive loads over this many cloths
log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class Workload:
    """What every cloth of a load is and how its states travel: the settings a whole load
    (loadrun.LoadSpec) and each of its client processes (ClientSpec) share."""

    size: int = 32  # n x n vertices per cloth
    features: tuple[str, ...] = ()
    iterations: int = 10
    substeps: int = 1
    bending: bool = True
    encoding: str = "float32"
    tick_rate: float = 60.0
    bundle: bool = True
    servers: int = 1  # servers the load is spread over; a client waits for them, then places by load
    # with bundles, each client decodes fully one cloth in ``decode_sample`` (1: all); the others'
    # states are counted from their headers (BundleReceiver.count_only). 0: auto (decode_one_in)
    decode_sample: int = 0

    def decode_one_in(self, cloths: int) -> int:
        """The ``decode_sample`` a load of ``cloths`` runs with: as set, else (auto) one cloth in
        SAMPLED_DECODE for predictive loads over AUTO_SAMPLE_ABOVE cloths with bundles (their
        decode, ~1 ms of a core per 64-cloth bundle, would take the cores the server needs), all
        cloths otherwise."""
        if not self.bundle:
            return 1
        if self.decode_sample:
            return self.decode_sample
        return SAMPLED_DECODE if self.encoding == "predictive" and cloths > AUTO_SAMPLE_ABOVE else 1

    def workload(self) -> dict[str, Any]:
        """These settings as keyword arguments (for a ClientSpec of this load)."""
        return {f.name: getattr(self, f.name) for f in fields(Workload)}


@dataclass(frozen=True, kw_only=True)
class ClientSpec(Workload):
    """What one client process does: ``offered`` cloths of ``size`` x ``size`` vertices."""

    index: int
    offered: int
    # submits refused ``overloaded`` are tried again this many times (the error says "retry later";
    # a game loading a level does): 0 when the load is offered past the nominal on purpose
    retries: int = 0
    link_endpoint: str = ""  # behind a home link: its shaper's endpoint (loadlink.py); "": none
    client_rate: str = "1"  # 1.8: the rate it takes (1, 2, 3; 1.9: 6, 12; or auto)


@dataclass
class ClientResult:
    """What one client saw in the measured window (server ticks ``lo + 1 .. hi``)."""

    index: int
    offered: int
    admitted: int
    refused: dict[str, int]  # refused submits by error code
    received: int  # states of window ticks
    expected: int  # admitted cloths x window ticks
    lost: int  # window ticks some admitted cloth never received
    duplicated: int
    out_of_order: int
    latencies_ms: np.ndarray  # per received state
    decode_us_per_state: float  # mean of (per payload: arrival -> last state delivered) / states in it
    decode_us_per_payload: float  # mean arrival -> last state delivered, per payload (bundle or state)
    decode_s: float  # total decode time in the window
    payloads: int  # bundles (or single states) received in the window
    bytes: int  # received states x their encoding's size (predictive: its largest; reports take the servers')
    send_errors: int
    cpu_s: float  # the process's CPU time over the window
    extra: dict[str, Any] = field(default_factory=dict)


class _Recorder:
    """Per cloth: the states' ticks, latencies, arrival times and delivery delays, as lists
    (appends are the cheapest thing a Zenoh callback can do)."""

    def __init__(self) -> None:
        self.ticks: list[int] = []
        self.lat_ns: list[int] = []
        self.rx_ns: list[int] = []
        self.delay_ns: list[int] = []

    def __call__(self, st: Any) -> None:
        now = time.time_ns()
        self.ticks.append(st.tick)
        self.lat_ns.append(st.receive_time_ns - st.server_time_ns)
        self.rx_ns.append(st.receive_time_ns)
        self.delay_ns.append(now - st.receive_time_ns)


def window_counts(ticks: np.ndarray, lo: int, hi: int) -> tuple[int, int, int, int]:
    """Received, lost, duplicated and out-of-order states of one cloth over ticks ``lo+1 .. hi``
    (``ticks`` in arrival order)."""
    inside = ticks[(ticks > lo) & (ticks <= hi)]
    uniq = np.unique(inside)
    ooo = int(np.count_nonzero(np.diff(inside) < 0))
    return len(inside), (hi - lo) - len(uniq), len(inside) - len(uniq), ooo


def decode_cost(rx_ns: np.ndarray, delay_ns: np.ndarray) -> tuple[float, float, float, int]:
    """Decode cost from each state's payload arrival time and delivery delay: states sharing an
    arrival time came in one payload (a bundle); a payload's cost is its largest delay (arrival
    to its last state delivered). Returns mean microseconds per state and per payload, total
    seconds and the number of payloads."""
    if not len(rx_ns):
        return float("nan"), float("nan"), 0.0, 0
    _, inverse, counts = np.unique(rx_ns, return_inverse=True, return_counts=True)
    per_payload = np.zeros(len(counts), np.float64)
    np.maximum.at(per_payload, inverse, delay_ns.astype(np.float64))
    total = float(per_payload.sum())
    return total / len(rx_ns) / 1e3, float(per_payload.mean()) / 1e3, total / 1e9, len(counts)


def _wait_turn(client: Any, shared: dict[str, Any], placing: bool) -> None:
    """Wait for this client's turn to place its cloths (``shared["turn"]``, set by the parent once
    the clients before it are admitted), then, when it places by load, until the servers' stats
    it sees count at least ``shared["expect"]`` vertices (what those clients were admitted), so
    that it ranks the servers by their load with them (stats come every stats period)."""
    while not shared["turn"].wait(0.1):
        if shared["stop"].is_set():
            return
    if not placing:
        return
    want, t_end = int(shared["expect"].value), time.monotonic() + TURN_STATS_WAIT_S
    while sum(s.vertices for s in client.placement.loads(client.live_servers())) < want:
        if time.monotonic() > t_end:
            log.warning("placing by stats that count fewer vertices than the %d admitted so far", want)
            return
        time.sleep(0.02)


def _open(make: Any, endpoint: str | list[str], server_id: str | None, rate: int | str, link: dict[str, Any]) -> Any:
    """The client's DrapeClient; behind a link (client mode, which fails at once while the server
    does not listen yet, where a peer waits) tried again for up to a minute."""
    deadline = time.monotonic() + 60.0
    while True:
        try:
            return make(endpoint, server_id=server_id, timeout=60.0, queue_size=4, rate=rate, **link)
        except ConnectionError:
            if not link or time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def client_main(
    spec: ClientSpec,
    endpoint: str | list[str],
    server_id: str | None,
    shared: dict[str, Any],
    results: Any,
    cpus: frozenset[int] | None = None,
) -> None:
    """The process body. ``shared``: events ``turn``, ``ready``, ``go``, ``stop`` and values
    ``expect`` (see :func:`_wait_turn`), ``admitted``,
    ``receiving`` (1 once every admitted cloth got a state), ``progress`` (states so far) and the
    window ``lo``, ``hi`` (server ticks, -1 until the parent knows them); ``server`` (bytes, when
    present) gets the server this client placed its cloths on.

    Without ``server_id`` the client waits until it sees ``spec.servers`` live servers, takes the
    one the SDK's placement ranks first by their published load (client/placement.py) and puts
    all its cloths there (the window is counted in that server's ticks)."""
    logging.basicConfig(level=logging.WARNING)
    if cpus:  # before Zenoh starts its threads: they inherit it
        os.sched_setaffinity(0, cpus)
    from drape.client import DrapeClient
    from drape.client import protocol as P

    from .loadlink import NO_SHM, longest_gap_ms

    link: dict[str, Any] = {}
    if spec.link_endpoint:  # a home link: client mode through the shaper only, no shared memory
        zc = tempfile.NamedTemporaryFile("w", suffix=".json5", delete=False)
        zc.write(NO_SHM)
        zc.close()
        endpoint = spec.link_endpoint
        link = {"mode": "client", "zenoh_config_file": zc.name}
    rate: int | str = spec.client_rate if spec.client_rate == "auto" else int(spec.client_rate)
    n = spec.size
    pins = [0, n - 1]
    handles: list[Any] = []
    recs: list[_Recorder] = []
    refused: Counter[str] = Counter()
    try:
        with _open(DrapeClient, endpoint, server_id, rate, link) as client:
            t_end = time.monotonic() + 60.0
            while server_id is None and len(client.live_servers()) < spec.servers and time.monotonic() < t_end:
                time.sleep(0.05)
            shared["connected"].set()  # the parent lets the clients submit once all are up
            _wait_turn(client, shared, server_id is None)
            home = client.server_id  # the one given, or the least loaded live one
            if "server" in shared:
                shared["server"].value = home.encode()

            def submit_one(_j: int) -> Any:
                tries = 0
                while True:
                    try:
                        return submit_grid()
                    except P.Overloaded:
                        if tries == spec.retries or shared["stop"].is_set():
                            raise
                        tries += 1
                        time.sleep(RETRY_AFTER_S)

            def submit_grid() -> Any:
                return client.submit_grid(
                    n,
                    n,
                    1.0,
                    1.0,
                    origin=(0.0, 1.0, 2.0 * spec.index),  # one origin a client: cooked once (FabricStore)
                    pinned=pins,
                    links={"structural": True, "shear": True, "bending": spec.bending},
                    features=list(spec.features),
                    iterations=spec.iterations,
                    substeps=spec.substeps,
                    encoding=spec.encoding,
                    bundle=spec.bundle,
                    server=home,
                )

            # SUBMITS_IN_FLIGHT submits at a time, as a game loading a level would: the server adds
            # every cloth that arrived in a tick at once, rather than one cloth a client per tick
            with ThreadPoolExecutor(SUBMITS_IN_FLIGHT, thread_name_prefix="submit") as pool:
                futures = [pool.submit(submit_one, j) for j in range(spec.offered)]
                for fut in futures:  # in submission order
                    try:
                        h = fut.result()
                    except P.DrapeError as e:
                        refused[e.code] += 1
                        continue
                    handles.append(h)
                    recs.append(_Recorder())
            if spec.bundle and handles and not all(h.bundled for h in handles):
                raise RuntimeError("the server does not bundle states (protocol 1.0?)")
            rest = np.stack([np.asarray(h.rest_positions[pins], np.float32) for h in handles]) if handles else None
            sway = np.arange(len(handles), dtype=np.float64)  # each cloth's phase
            moved = np.empty((len(handles), len(pins), 3), np.float32)
            shared["admitted"].value = len(handles)
            shared["ready"].set()
            shared["go"].wait()
            sample = max(spec.decode_sample, 1) if spec.bundle else 1
            decoded = [h for j, h in enumerate(handles) if j % sample == 0]
            cancels = [h.on_state(recs[j]) for j, h in enumerate(handles) if j % sample == 0]
            if sample > 1:  # the others: counted from their headers (tick, cloth), not decoded
                counting = [True]
                by_id = {h.id: recs[j] for j, h in enumerate(handles) if j % sample}

                def on_headers(cloths: list[str], ticks: np.ndarray, server_ns: np.ndarray, rx: int) -> None:
                    if not counting[0]:
                        return
                    now = time.time_ns()
                    for c, t, s in zip(cloths, ticks.tolist(), server_ns.tolist(), strict=True):
                        rec = by_id.get(c)
                        if rec is not None:
                            rec.ticks.append(t)
                            rec.lat_ns.append(rx - s)
                            rec.rx_ns.append(rx)
                            rec.delay_ns.append(now - rx)

                client.bundles.count_only(by_id, on_headers)
                cancels.append(lambda: counting.__setitem__(0, False))
            cpu0, err0, opened = time.process_time(), client.send_errors, False
            period = 1.0 / spec.tick_rate
            t0 = next_t = time.monotonic()
            while not shared["stop"].is_set():
                t = time.monotonic() - t0
                # like a game: every cloth's pins follow its character, once per tick
                if handles:
                    assert rest is not None
                    np.copyto(moved, rest)
                    moved[:, :, 0] += (0.1 * np.sin(2.0 * t + sway))[:, None]
                    moved[:, :, 1] += 0.05 * math.sin(3.0 * t)
                if spec.bundle and handles:  # one message per tick: a moves block (1.4), else a batch
                    client.move_pins_many(handles, pins, moved)
                else:
                    for j, h in enumerate(handles):
                        h.move_pins(pins, moved[j], wait=False)
                got = sum(len(r.ticks) for r in recs)
                shared["progress"].value = got
                if not shared["receiving"].value and all(r.ticks for r in recs):
                    shared["receiving"].value = 1
                if not opened and shared["lo"].value >= 0:
                    cpu0, err0, opened = time.process_time(), client.send_errors, True
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    next_t = time.monotonic()
            cpu_s = time.process_time() - cpu0
            send_errors = client.send_errors - err0
            steps = client.bundles.step_downs + sum(h.step_downs for h in handles if not h.bundled)
            rate_at_end = max([client.bundles.rate] + [h.rate for h in handles if not h.bundled])
            per_state = P.state_size(n * n, spec.encoding)
            lo, hi = int(shared["lo"].value), int(shared["hi"].value)
            for cancel in cancels:  # stop recording before the client closes
                cancel()
            # controls still in flight meet the cloths' removal on close: not_found, not worth a warning
            logging.getLogger("drape.client.sdk").setLevel(logging.ERROR)
            snapshot = [
                (
                    np.asarray(r.ticks, np.int64),
                    np.asarray(r.lat_ns, np.int64),
                    np.asarray(r.rx_ns, np.int64),
                    np.asarray(r.delay_ns, np.int64),
                )
                for r in recs
            ]
    except BaseException as e:  # report, don't hang the parent
        results.put(("error", spec.index, repr(e)))
        if isinstance(e, P.DrapeError):  # the server's answer (or its absence): one line, no traceback
            log.error("load client %d: %s", spec.index, e)
            raise SystemExit(1) from None
        raise
    received = lost = dup = ooo = 0
    lat, rx, dl = [], [], []
    per_cloth: list[int] = []
    gap = float("nan")
    for ticks, lat_ns, rx_ns, delay_ns in snapshot:
        k = min(len(ticks), len(lat_ns), len(rx_ns), len(delay_ns))  # the callback may have raced the copy
        ticks, lat_ns, rx_ns, delay_ns = ticks[:k], lat_ns[:k], rx_ns[:k], delay_ns[:k]
        r, lo_, d, o = window_counts(ticks, lo, hi)
        received, lost, dup, ooo = received + r, lost + lo_, dup + d, ooo + o
        inside = (ticks > lo) & (ticks <= hi)
        per_cloth.append(r)
        g = longest_gap_ms(rx_ns[inside])
        gap = g if math.isnan(gap) else max(gap, g)
        lat.append(lat_ns[inside])
        rx.append(rx_ns[inside])
        dl.append(delay_ns[inside])
    lat_ms = (np.concatenate(lat) / 1e6).astype(np.float32) if lat else np.zeros(0, np.float32)
    per_s, per_p, dec_s, payloads = decode_cost(
        np.concatenate(rx) if rx else np.zeros(0, np.int64), np.concatenate(dl) if dl else np.zeros(0, np.int64)
    )
    results.put(
        (
            "ok",
            ClientResult(
                index=spec.index,
                offered=spec.offered,
                admitted=len(handles),
                refused=dict(refused),
                received=received,
                expected=len(handles) * max(hi - lo, 0),
                lost=lost,
                duplicated=dup,
                out_of_order=ooo,
                latencies_ms=lat_ms,
                decode_us_per_state=per_s,
                decode_us_per_payload=per_p,
                decode_s=dec_s,
                payloads=payloads,
                bytes=received * per_state,
                send_errors=send_errors,
                cpu_s=cpu_s,
                extra={
                    "shaped": bool(spec.link_endpoint),
                    "per_cloth_states": per_cloth,
                    "longest_gap_ms": gap,
                    "step_downs": steps,
                    "rate_at_end": rate_at_end,
                    "decoded_cloths": len(decoded),
                    "decode_sample": sample,
                },
            ),
        )
    )
