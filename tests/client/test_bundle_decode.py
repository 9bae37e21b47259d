"""The whole-bundle reader (Bundle.decode, decode_states, parse_bundle's entry table) against
the per-entry reference (decode_state, PROTOCOL.md 9.1's reading rules) on fresh random bundles:
every field equal, every array equal bit for bit, an invalid state reported for its own entry only;
and the SDK's bundle receiver (client/bundles.py) delivering them to real ClothHandles of a real
client, over real Zenoh on loopback (own port, no server)."""

from __future__ import annotations

import struct
import threading

import numpy as np
import pytest
from conftest import endpoint, wait_until

from drape.client import DrapeClient
from drape.client import protocol as P
from drape.client.handle import ClothHandle

pytestmark = pytest.mark.zenoh  # not unit (tests/conftest.py)

ID_CHARS = np.frombuffer(b"abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-", np.uint8)
SIZES = (0, 1, 3, 16, 63, 64, 65, 100, 1024)


def random_id(rng: np.random.Generator) -> str:
    return bytes(rng.choice(ID_CHARS, int(rng.integers(1, 65)))).decode()


def random_state(
    rng: np.random.Generator, n: int, encoding: str, normals: bool, raw: bool = False, tick: int = 7
) -> bytearray:
    """An encoded state; ``raw``: then its bounds and values overwritten with random bits (NaNs,
    infinities, subnormals: whatever a hostile or broken writer sends)."""
    scale = float(rng.choice([1e-3, 1.0, 100.0, 1e5]))
    pos = (rng.normal(0, 1, (n, 3)) * scale + rng.uniform(-scale, scale, 3)).astype(np.float32)
    if n and rng.random() < 0.3:
        pos[:, int(rng.integers(3))] = np.float32(rng.normal())  # a flat axis: quant16's max == min
    nrm = rng.normal(0, 1, (n, 3)).astype(np.float32) * 1.2 if normals else None
    flags = int(rng.choice([0, P.FLAG_RESET, 0x8000 | P.FLAG_RESET, 0x4000]))
    data = P.encode_state(tick, 10**18 + tick, pos, nrm, encoding, flags)
    if raw:
        data[32:56] = rng.integers(0, 256, 24, np.uint8).tobytes()
        data[64:] = rng.integers(0, 256, len(data) - 64, np.uint8).tobytes()
    return data


def assert_same(got: P.ClothState | P.ProtocolError, ref: P.ClothState | P.ProtocolError) -> None:
    """Equal in every field, every array equal in dtype, shape, bits and writability."""
    assert type(got) is type(ref)
    if isinstance(ref, P.ProtocolError):
        assert (got.code, got.message) == (ref.code, ref.message)
        return
    assert vars(got).keys() == vars(ref).keys()
    for name, r in vars(ref).items():
        g = getattr(got, name)
        if isinstance(r, np.ndarray):
            assert isinstance(g, np.ndarray), name
            assert (g.dtype, g.shape, g.flags.writeable) == (r.dtype, r.shape, r.flags.writeable), name
            assert g.flags.c_contiguous, name
            assert g.tobytes() == r.tobytes(), f"{name} differs in {np.count_nonzero(g != r)} values"
        elif name == "bounds":
            assert np.array(g, np.float64).tobytes() == np.array(r, np.float64).tobytes()
        else:
            assert g == r and type(g) is type(r), name


def reference(b: P.Bundle, i: int, t: int) -> P.ClothState | P.ProtocolError:
    try:
        return b.state(i, t)
    except P.ProtocolError as e:
        return e


def check_bundle(data: bytes | bytearray, t: int = 5) -> list[P.ClothState | P.ProtocolError]:
    b = P.parse_bundle(data)
    got = b.decode(t)
    assert len(got) == len(b.entries)
    for i, g in enumerate(got):
        assert_same(g, reference(b, i, t))
    return got


# ---------------------------------------------------------------------------------------------
# Bit for bit what decode_state gives


@pytest.mark.parametrize("encoding", P.STATELESS_ENCODINGS)
@pytest.mark.parametrize("normals", [False, True])
def test_a_bundle_of_equal_states_decodes_bit_for_bit(rng, encoding, normals):
    n = int(rng.choice([16, 64, 100, 1024]))
    k = int(rng.integers(2, 40))
    states = [(f"{i:016x}", random_state(rng, n, encoding, normals)) for i in range(k)]
    data = bytes(P.encode_bundle(7, 10**18 + 7, states))
    got = check_bundle(data)
    assert all(s.cloth == c for s, (c, _) in zip(got, states, strict=True))
    if encoding == "float32":  # views of the payload, as decode_state's
        assert all(not s.positions.flags.writeable and s.positions.base is not None for s in got)


def test_mixed_random_bundles_decode_bit_for_bit(rng):
    """Every encoding, vertex count, normals, flags and id length mixed in one bundle, in random
    order, some with random bits for values and bounds; the receive time and ids carried over."""
    for _ in range(12):
        k = int(rng.integers(1, 60))
        states = []
        for _ in range(k):
            n = int(rng.choice(SIZES))
            enc = str(rng.choice(P.STATELESS_ENCODINGS))
            states.append((random_id(rng), random_state(rng, n, enc, bool(rng.random() < 0.5), rng.random() < 0.2)))
        data = P.encode_bundle(7, 10**18 + 7, states)
        got = check_bundle(bytes(data), t=int(rng.integers(0, 2**63)))
        check_bundle(data)  # a bytearray: float32 views are writable, as decode_state's
        check_bundle(memoryview(bytes(data)))
        assert [s.cloth for s in got] == [c for c, _ in states]
        assert [s.cloth for s in P.decode_bundle(bytes(data))] == [c for c, _ in states]


def test_every_float16_and_snorm16_value_decodes_as_decode_state_does():
    """All 65536 bit patterns (NaNs, infinities, subnormals, -0) as float16 values and as quant16
    normals, through the whole-bundle reader and through decode_state."""
    n = 65536 // 3 + 1
    bits = np.resize(np.arange(65536, dtype=np.uint16), n * 3)
    states = []
    for enc in ("float16", "quant16"):
        st = P.encode_state(1, 2, np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32), enc)
        st[64:] = np.concatenate([bits, bits]).astype("<u2").tobytes()
        states += [(f"{enc}-a", st), (f"{enc}-b", st)]
    check_bundle(bytes(P.encode_bundle(1, 2, states)))


def test_states_with_a_longer_header_or_trailing_bytes_decode_as_decode_state_does(rng):
    """A later minor version's states (header_size 80, trailing sections) among 1.x states of the
    same kind: the values start at other offsets, so the group is not evenly spaced."""
    states = []
    for i in range(9):
        st = random_state(rng, 50, str(rng.choice(P.STATELESS_ENCODINGS)), bool(i % 2))
        if i % 3 == 0:
            st = bytearray(st[:64] + rng.integers(0, 256, 16, np.uint8).tobytes() + st[64:] + b"later")
            st[5] = 99
            struct.pack_into("<H", st, 6, 80)
        states.append((f"c{i}", st))
    check_bundle(bytes(P.encode_bundle(7, 8, states)))


def test_an_invalid_state_spoils_only_its_own_entry(rng):
    good = [random_state(rng, 30, enc, nrm) for enc in P.STATELESS_ENCODINGS for nrm in (False, True)]
    base = good[0]
    bad = {
        "short": base[:40],
        "truncated": base[:-1],
        "magic": b"DRPX" + base[4:],
        "major": base[:4] + b"\x02" + base[5:],
        "encoding": base[:8] + b"\x07" + base[9:],
        "header": base[:6] + struct.pack("<H", 32) + base[8:],
        "normals": base[:10] + struct.pack("<H", P.FLAG_NORMALS) + base[12:],  # announces what is not there
        "huge": base[:12] + struct.pack("<I", 2**32 - 1) + base[16:],
        "empty": b"",
    }
    for name, payload in bad.items():
        order = [("g0", good[0]), ("g1", good[3]), (name, payload), ("g2", good[1]), ("g3", good[5])]
        order = [order[j] for j in rng.permutation(len(order))]
        data = bytes(P.encode_bundle(1, 2, order))
        got = check_bundle(data)
        assert [isinstance(s, P.ProtocolError) for s in got] == [c == name for c, _ in order], name
        with pytest.raises(P.ProtocolError) as e:
            P.decode_bundle(data)
        assert e.value.message == next(s for s in got if isinstance(s, P.ProtocolError)).message


def test_corrupted_bundles_decode_entry_by_entry_as_decode_state_does(rng):
    """Random bytes changed in bundles of like and of mixed states (headers, values, bounds): the
    bundle is refused as parse_bundle refuses it, or every entry is what state(i) gives."""
    for _ in range(15):
        like = rng.random() < 0.5
        enc = str(rng.choice(P.STATELESS_ENCODINGS))
        states = [
            (
                f"c{i}",
                random_state(
                    rng,
                    16 if like else int(rng.choice(SIZES[:6])),
                    enc if like else str(rng.choice(P.STATELESS_ENCODINGS)),
                    like or bool(rng.random() < 0.5),
                ),
            )
            for i in range(int(rng.integers(1, 12)))
        ]
        data = bytes(P.encode_bundle(7, 8, states))
        for _ in range(20):
            bad = bytearray(data)
            for j in rng.integers(32, len(bad), int(rng.integers(1, 4))):
                bad[j] = int(rng.integers(0, 256))
            try:
                P.parse_bundle(bytes(bad))
            except P.ProtocolError:
                continue  # the entry table itself is broken: parse_bundle says so
            check_bundle(bytes(bad))  # decode() raises nothing: each entry a state or its error


def test_decode_states_takes_payloads_anywhere_in_a_buffer(rng):
    """decode_states on payloads laid out by hand: unaligned, out of order, the same one twice."""
    payloads = [
        bytes(random_state(rng, 20, str(rng.choice(P.STATELESS_ENCODINGS)), bool(rng.random() < 0.5))) for _ in range(6)
    ]
    buf = bytearray(b"\x01\x02\x03")
    offsets = []
    for p in payloads:
        offsets.append(len(buf))
        buf += p + b"\x05" * int(rng.integers(0, 7))
    order = [4, 1, 1, 0, 5, 3, 2]
    got = P.decode_states(bytes(buf), [offsets[j] for j in order], [len(payloads[j]) for j in order], list("abcdefg"))
    for g, j, c in zip(got, order, "abcdefg", strict=True):
        assert_same(g, P.decode_state(memoryview(bytes(buf))[offsets[j] : offsets[j] + len(payloads[j])], c))
    assert P.decode_states(b"", [], [], []) == []
    with pytest.raises(ValueError):
        P.decode_states(bytes(buf), [len(buf) - 10], [64], ["x"])


# ---------------------------------------------------------------------------------------------
# The entry table: the columns agree with PROTOCOL.md 9.1 read entry by entry


def walk(data: bytes) -> list[tuple[str, int, int]] | str:
    """PROTOCOL.md 9.1's reading rules, entry by entry: (id, state offset, state size) of each
    entry, or the error code."""
    if len(data) < 32:
        return "malformed"
    magic, major, _, hsize, count = struct.unpack_from("<4sBBHI", data)
    if magic != b"DRPB" or hsize < 32:
        return "malformed"
    if major != 1:
        return "unsupported_version"
    out, at = [], hsize
    for _ in range(count):
        if at + 8 > len(data):
            return "malformed"
        h, length, size = struct.unpack_from("<HBxI", data, at)
        if h < 8 + length or at + h + size > len(data):
            return "malformed"
        cloth = data[at + 8 : at + 8 + length].decode("latin-1")
        if not P.valid_id(cloth):
            return "malformed"
        out.append((cloth, at + h, size))
        at = (at + h + size + 7) & ~7
    return out


def test_entry_tables_agree_with_the_reading_rules_under_corruption(rng):
    """Bundles of equal entries (read with a few numpy operations) and of mixed ones (entry by
    entry), then corrupted at random: the same entries, or the same error, as the rules say."""
    for _ in range(40):
        k = int(rng.integers(1, 12))
        equal = rng.random() < 0.6
        n = int(rng.integers(0, 9))
        states = [
            (
                f"{i:04d}abcdefgh"[: int(rng.integers(1, 13))] if not equal else f"c{i:07d}",
                P.encode_state(1, 2, np.ones((n if equal else int(rng.integers(0, 9)), 3), np.float32)),
            )
            for i in range(k)
        ]
        data = bytes(P.encode_bundle(3, 4, states))
        for trial in range(30):
            bad = bytearray(data)
            if trial:
                for j in rng.integers(32, len(bad), int(rng.integers(1, 3))):
                    bad[j] = int(rng.integers(0, 256)) if rng.random() < 0.5 else bad[j] ^ 1
            expect = walk(bytes(bad))
            try:
                got = [(e.cloth, e.offset, e.size) for e in P.parse_bundle(bytes(bad)).entries]
            except P.ProtocolError as e:
                got = e.code  # type: ignore[assignment]
            assert got == expect, bytes(bad).hex()


def test_bundle_entries_read_like_a_list():
    data = bytes(P.encode_bundle(1, 2, [(c, P.encode_state(1, 2, np.zeros((2, 3), np.float32))) for c in "xyz"]))
    b = P.parse_bundle(data)
    assert len(b.entries) == 3 and b.entries[-1].cloth == "z" and [e.cloth for e in b.entries[1:]] == ["y", "z"]
    assert b.entries == list(b.entries) and b.entries[0] == P.BundleEntry("x", 48, 88)
    hand = P.Bundle(b.tick, b.server_time_ns, b.flags, list(b.entries)[::-1], data)  # a plain list works too
    assert [s.cloth for s in hand.decode()] == ["z", "y", "x"]


# ---------------------------------------------------------------------------------------------
# The SDK: one decode per bundle, then every handle's guarantees


@pytest.fixture
def client():
    ep = endpoint()
    c = DrapeClient(ep, listen=[ep], timeout=2.0, queue_size=3)
    c.endpoint = ep  # type: ignore[attr-defined]
    yield c
    c.close(remove=False)


def bundled_handle(client: DrapeClient, cloth: str, register: bool = True, bundled: bool = True) -> ClothHandle:
    """A handle as a bundled submission makes it (registered as Submitter.place does)."""
    rep = P.SubmitReply(cloth, "0" * 32, f"drape/cloth/{cloth}/state", 4, 1, bundle_key=client.bundle_key)
    if not bundled:
        rep.bundle_key = None
    h = ClothHandle(client, rep, queue_size=client.queue_size, server_id="s")
    if register:
        with client.cloths.lock:
            client.cloths.add(h)
    return h


def test_the_receiver_delivers_each_state_to_its_handle_with_its_guarantees(rng, client):
    ids = [random_id(rng) for _ in range(5)]
    handles = [bundled_handle(client, c) for c in ids[:4]]  # ids[4]: nobody's
    plain = bundled_handle(client, "plain", bundled=False)
    calls: list[tuple[str, int, int]] = []
    for h in handles:
        h.on_state(lambda st, h=h: calls.append((h.id, st.tick, threading.get_ident())))
    sent = []
    for tick in range(1, 7):
        states = [
            (c, random_state(rng, 12, str(rng.choice(P.STATELESS_ENCODINGS)), tick % 2 == 0, tick=tick)) for c in ids
        ]
        states.append(("plain", random_state(rng, 4, "float32", False, tick=tick)))
        if tick == 4:  # an invalid state: counted for its cloth, the others delivered
            states[1] = (ids[1], b"DRPX" + bytes(states[1][1][4:]))
        sent.append(states)
        client.bundles.receive(bytes(P.encode_bundle(tick, 9, states)), 1000 + tick)
    client.bundles.receive(b"not a bundle")
    assert client.bundle_invalid == 1 and plain.received == 0
    me = threading.get_ident()
    for j, h in enumerate(handles):
        ticks = [t for c, t, thread in calls if c == h.id and thread == me]  # on the receiving thread
        expect = [t for t in range(1, 7) if not (j == 1 and t == 4)]
        assert ticks == expect and h.received == len(expect) and h.invalid == (j == 1)
        assert h.dropped == len(expect) - 3  # queue_size 3: the oldest dropped, counted
        queued = [h.next_state(0) for _ in range(3)]
        assert [s.tick for s in queued] == expect[-3:]
        for s in queued:
            payload = dict(sent[s.tick - 1])[h.id]
            assert_same(s, P.decode_state(bytes(payload), h.id, 1000 + s.tick))
        older, newer = h.last_states()
        assert older is queued[-2] and newer is queued[-1] and h.latest() is newer


def test_cloths_counted_only_get_their_headers_and_the_others_their_states(rng, client):
    """BundleReceiver.count_only: those cloths' states are neither decoded nor delivered, their
    ticks and server times come from the headers, once per bundle; the other cloths are as
    before, predictive streams included; an empty set decodes every cloth again."""
    ids = [random_id(rng) for _ in range(6)]
    handles = [bundled_handle(client, c) for c in ids]
    counted: list[tuple[list[str], list[int], list[int], int]] = []
    client.bundles.count_only(ids[::2], lambda c, t, s, r: counted.append((c, t.tolist(), s.tolist(), r)))
    encs = [P.History() for _ in ids]
    x = rng.uniform(-1, 1, (30, 3)).astype(np.float32)
    for tick in range(1, 5):
        states = [
            (c, P.encode_predictive_state(tick, 50 + tick, x, 0.001, e, tick == 1))
            for c, e in zip(ids, encs, strict=True)
        ]
        client.bundles.receive(bytes(P.encode_bundle(tick, 9, states)), 1000 + tick)
    assert counted == [(ids[::2], [t] * 3, [50 + t] * 3, 1000 + t) for t in range(1, 5)]
    assert client.bundles.counted == 12
    assert [h.received for h in handles] == [0, 4] * 3
    assert all(h.stream.undecodable == 0 and h.latest().tick == 4 for h in handles[1::2])
    client.bundles.count_only(())
    states = [(c, P.encode_predictive_state(5, 55, x, 0.001, e)) for c, e in zip(ids, encs, strict=True)]
    client.bundles.receive(bytes(P.encode_bundle(5, 9, states)), 1005)
    assert [h.received for h in handles] == [0, 5] * 3 and len(counted) == 4
    assert all(h.stream.undecodable == 1 for h in handles[::2])  # no references: a keyframe is asked for


def test_a_bundle_whose_cloths_all_miss_a_state_asks_one_keyframe(rng, client):
    """Every cloth of a bundle that lost a state notices at once; one keyframe query on the
    bundle's key answers them all (client/keyframes.py), so the client sends one, not one per
    cloth, and the next within the interval from any of them is held back."""
    ids = [random_id(rng) for _ in range(8)]
    handles = [bundled_handle(client, c) for c in ids]
    encs = [P.History() for _ in ids]
    x = rng.uniform(-1, 1, (30, 3)).astype(np.float32)

    def bundle(tick: int) -> bytes:
        states = [
            (c, P.encode_predictive_state(tick, 50 + tick, x, 0.001, e, tick == 1))
            for c, e in zip(ids, encs, strict=True)
        ]
        return bytes(P.encode_bundle(tick, 9, states))

    client.bundles.receive(bundle(1), 1001)
    bundle(2)  # lost: never received
    sent = client.keyframes.sent
    client.bundles.receive(bundle(3), 1003)  # predicted from tick 2, which nobody here has
    assert all(h.gaps == 1 for h in handles)
    assert client.keyframes.sent == sent + 1  # one query for the bundle's eight cloths
    assert sum(h.keyframe_queries for h in handles) == 1
    assert not handles[-1].ask_keyframe()  # asked a moment ago, by another cloth of the bundle
    assert handles[-1].ask_keyframe(0.0)  # unless asked regardless


def test_states_of_a_cloth_whose_reply_is_on_its_way_are_kept_for_it(rng, client):
    rx = client.bundles
    early = bundled_handle(client, "early", register=False)

    def bundle(tick: int) -> bytes:
        return bytes(P.encode_bundle(tick, 1, [("early", random_state(rng, 4, "quant16", False, tick=tick))]))

    rx.receive(bundle(1))  # no submission under way: nothing kept
    rx.submitting()
    for tick in range(2, 8):
        rx.receive(bundle(tick))
    with client.cloths.lock:  # what Submitter.place does once the reply is in
        client.cloths.add(early)
        kept = rx.early_states(early.id)
    for st in kept:
        early.deliver(st)
    rx.submitted()
    rx.receive(bundle(8))
    got = [early.next_state(0).tick for _ in range(3)]
    assert [s.tick for s in kept] == [5, 6, 7] and got == [6, 7, 8]  # the last queue_size kept, in order
    assert early.received == 4 and not rx._orphans


def test_bundles_over_zenoh_reach_the_handles(rng, client):
    """The real subscriber path: bundles another session puts on the client's bundle key."""
    import zenoh

    from drape.client.session import zenoh_config

    handles = [bundled_handle(client, f"z{i}") for i in range(3)]
    client.bundles.subscribe(client.session)
    states = {h.id: random_state(rng, 8, "quant16", True, tick=1) for h in handles}
    data = bytes(P.encode_bundle(1, 1, list(states.items())))
    server = zenoh.open(zenoh_config("peer", connect=[client.endpoint]))
    try:  # until the subscription has propagated
        assert wait_until(lambda: server.put(client.bundle_key, data) or all(h.received for h in handles))
    finally:
        server.close()
    for h in handles:
        st = h.latest()
        assert st is not None and h.invalid == 0
        assert_same(st, P.decode_state(bytes(states[h.id]), h.id, st.receive_time_ns))
