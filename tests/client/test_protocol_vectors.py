"""The committed test vectors, both ways (bytes -> meaning, meaning -> identical bytes), the frozen
1.0 and 1.1 vectors still read, and the hex dumps of PROTOCOL.md."""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from drape.client import protocol as P

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
sys.path.insert(0, str(VECTORS))
from generate import json_to_wire  # noqa: E402
from generate import vectors as fresh_vectors  # noqa: E402


def load(group: str) -> list[dict]:
    return json.loads((VECTORS / f"{group}.json").read_text())


# ---------------------------------------------------------------------------------------------
# Test vectors, both ways

REENCODE = {
    "submit": (P.decode_submit, P.encode_submit, P.submit_from_map),
    "control": (P.decode_control, P.encode_control, P.control_from_map),
    "remove": (P.decode_remove, P.encode_remove, P.remove_from_map),
    "info": (P.decode_info, P.encode_info, None),
    "scene": (P.decode_scene, P.encode_scene, P.scene_from_map),
}


def _reply_encoders(kind: str, m: dict) -> bytes:
    if kind == "reply_submit":
        return P.encode_submit_reply(P.submit_reply_from_map(m))
    if kind == "reply_control":
        return P.encode_control_reply(P.control_reply_from_map(m))
    if kind == "reply_remove":
        return P.encode_remove_reply(P.RemoveReply(P.tick_reply_from_map(m), m["rid"]))
    if kind == "reply_control_batch":
        return P.encode_control_batch_reply(P.control_batch_reply_from_map(m))
    if kind == "reply_scene":
        return P.encode_scene_reply(P.scene_reply_from_map(m))
    if kind == "reply_info":
        return P.encode_ok(m["rid"], **{k: v for k, v in m.items() if k not in ("v", "rid", "ok")})
    if kind == "stats":
        return P.encode_stats({k: v for k, v in m.items() if k not in ("v", "rid")})
    err = P.decode_error_map(m)
    return P.encode_error(err.code, err.message, err.rid)


def _batch_request(d: P.DecodedControlBatch) -> P.ControlBatchRequest:
    assert all(isinstance(it, P.ControlRequest) for it in d.items), d.items
    return P.ControlBatchRequest(d.client, list(d.items), d.rid, d.moves)  # type: ignore[arg-type]


REENCODE["control_batch"] = (
    lambda data: _batch_request(P.decode_control_batch(data)),
    P.encode_control_batch,
    lambda m: _batch_request(P.control_batch_from_map(m)),
)


@pytest.mark.parametrize(
    "vec",
    load("submit") + load("control") + load("misc") + [v for v in load("meshes") if "error" not in v],
    ids=lambda v: v["name"],
)
def test_message_vectors(vec):
    data = bytes.fromhex(vec["hex"])
    wire = json_to_wire(vec["value"])
    # bytes -> meaning
    assert msgpack.unpackb(data, raw=False) == wire
    # meaning -> identical bytes (float fields as float64, smallest ints, bin for arrays, key order)
    assert msgpack.packb(wire, use_bin_type=True) == data
    kind = vec["message"]
    if kind in REENCODE:
        decode, encode, from_map = REENCODE[kind]
        typed = decode(data)
        assert encode(typed) == data
        if from_map is not None:
            assert encode(from_map(wire)) == data
        assert typed.rid == wire.get("rid", 0)
    else:
        if kind == "error":
            with pytest.raises(P.DrapeError) as e:
                P.decode_reply(data)
            assert e.value.code == wire["error"]["code"] and e.value.message == wire["error"]["message"]
            m = P.unpack_message(data)
        elif kind == "stats":
            m = P.decode_stats(data)
        else:
            m = P.decode_reply(data)
        assert _reply_encoders(kind, m) == data


@pytest.mark.parametrize("vec", load("state"), ids=lambda v: v["name"])
def test_state_vectors(vec):
    data = bytes.fromhex(vec["hex"])
    val = vec["value"]
    st = P.decode_state(data)
    assert data[:4].decode() == val["magic"] and (data[4], data[5]) == (val["major"], val["minor"])
    assert struct.unpack_from("<H", data, 6)[0] == val["header_size"]
    assert st.encoding == val["encoding"] and st.flags == val["flags"] and st.n_vertices == val["vertex_count"]
    assert st.tick == val["tick"] and st.server_time_ns == val["server_time_ns"]
    assert list(st.bounds[0]) == val["bounds_min"] and list(st.bounds[1]) == val["bounds_max"]
    assert st.positions.tolist() == val["positions"]
    assert (st.normals is None and val["normals"] is None) or st.normals.tolist() == val["normals"]
    inp = vec["input"]
    normals = None if inp["normals"] is None else np.array(inp["normals"], np.float32)
    again = P.encode_state(
        val["tick"],
        val["server_time_ns"],
        np.array(inp["positions"], np.float32),
        normals,
        val["encoding"],
        inp["flags"],
    )
    assert bytes(again) == data


@pytest.mark.parametrize("vec", load("bundle"), ids=lambda v: v["name"])
def test_bundle_vectors(vec):
    data = bytes.fromhex(vec["hex"])
    val = vec["value"]
    # bytes -> meaning, read with struct as the document's offset table says
    magic, major, minor, hsize, count, flags, tick, t_ns = struct.unpack_from("<4sBBHIIQQ", data, 0)
    assert (magic.decode(), major, minor, hsize, count, flags, tick, t_ns) == (
        val["magic"],
        val["major"],
        val["minor"],
        val["header_size"],
        val["count"],
        val["flags"],
        val["tick"],
        val["server_time_ns"],
    )
    assert len(data) == val["size"] and len(data) % 8 == 0
    for e in val["entries"]:
        at = e["entry_offset"]
        h, id_len, reserved, size = struct.unpack_from("<HBBI", data, at)
        assert (h, size, reserved) == (e["entry_header_size"], e["state_size"], 0)
        assert data[at + 8 : at + 8 + id_len].decode() == e["cloth"] and not any(data[at + 8 + id_len : at + h])
        assert at % 8 == 0 and e["state_offset"] == at + h and e["state_offset"] % 8 == 0
        st = P.decode_state(data[at + h : at + h + size], e["cloth"])
        sv = e["state"]
        assert (st.tick, st.server_time_ns, st.encoding, st.flags, st.n_vertices) == (
            sv["tick"],
            sv["server_time_ns"],
            sv["encoding"],
            sv["flags"],
            sv["vertex_count"],
        )
        assert st.positions.tolist() == sv["positions"]
        assert (st.normals is None and sv["normals"] is None) or st.normals.tolist() == sv["normals"]
    # the decoder agrees
    b = P.parse_bundle(data)
    assert (b.tick, b.server_time_ns, b.flags, len(b.entries)) == (val["tick"], val["server_time_ns"], 0, val["count"])
    assert [s.cloth for s in P.decode_bundle(data, 5)] == [e["cloth"] for e in val["entries"]]
    # meaning -> identical bytes
    inp = vec["input"]
    again = P.encode_bundle(
        inp["tick"], inp["server_time_ns"], [(s["cloth"], bytes.fromhex(s["hex"])) for s in inp["states"]]
    )
    assert bytes(again) == data
    for s, e in zip(inp["states"], val["entries"], strict=True):
        assert data[e["state_offset"] : e["state_offset"] + e["state_size"]].hex() == s["hex"]


DECODERS = {
    "submit": P.decode_submit,
    "control": P.decode_control,
    "remove": P.decode_remove,
    "control_batch": P.decode_control_batch,
    "bundle": P.decode_bundle,
}


@pytest.mark.parametrize("vec", load("invalid") + [v for v in load("meshes") if "error" in v], ids=lambda v: v["name"])
def test_invalid_vectors(vec):
    decode = DECODERS[vec["message"]]
    data = bytes.fromhex(vec["hex"])
    if vec["error"] is None:  # a batch with a valid envelope: per-item errors
        batch = decode(data)
        codes = [it.code if isinstance(it, P.ProtocolError) else None for it in batch.items]
        assert codes == vec["item_errors"]
        assert all(it.rid == batch.rid for it in batch.items if isinstance(it, P.ProtocolError))
        return
    with pytest.raises(P.ProtocolError) as e:
        decode(data)
    assert e.value.code == vec["error"]


def test_accepted_vectors():
    for vec in load("accepted"):
        data = bytes.fromhex(vec["hex"])
        val = vec["value"]
        if vec["message"] == "bundle":
            (st,) = P.decode_bundle(data)
            assert st.cloth == "c" and st.tick == 7 and st.encoding == "float16"
            b = P.parse_bundle(data)
            assert (b.minor, b.tick, b.server_time_ns, b.flags, len(b.entries)) == (
                val["minor"],
                val["tick"],
                val["server_time_ns"],
                val["flags"],
                val["count"],
            )
            assert struct.unpack_from("<H", data, 6)[0] == val["header_size"] and len(data) == val["size"]
            for e, ev in zip(b.entries, val["entries"], strict=True):
                assert (e.cloth, e.offset, e.size) == (ev["cloth"], ev["state_offset"], ev["state_size"])
                st = P.decode_state(data[e.offset : e.offset + e.size])
                assert st.positions.tolist() == ev["state"]["positions"]
            continue
        assert msgpack.unpackb(data, raw=False) == json_to_wire(val)
        req = P.decode_submit(data)
        assert req.grid == P.GridSpec(2, 2)
        known = P.submit_to_map(req)
        assert all(k not in known for k in vec["ignored"])


FROZEN = {v: VECTORS / f"v{v}" for v in ("1.0", "1.1", "1.2", "1.3", "1.4", "1.5", "1.6", "1.7", "1.8")}


def _as_current(wire: dict) -> dict:
    """An older message as this version writes it: the same map with v = [1, PROTOCOL_MINOR]."""
    return {**wire, "v": [P.PROTOCOL_MAJOR, P.PROTOCOL_MINOR]} if "v" in wire else wire


def _frozen(groups: tuple[str, ...]) -> list:
    return [
        pytest.param(ver, v, id=f"{ver}-{v['name']}")
        for ver, d in FROZEN.items()
        for g in groups
        if (d / f"{g}.json").exists()
        for v in json.loads((d / f"{g}.json").read_text())
        if v["message"] != "stats"
    ]  # stats are informational: fields may come and go in any minor


@pytest.mark.parametrize("version,vec", _frozen(("submit", "control", "misc")))
def test_frozen_message_vectors_still_read(version, vec):
    """Minor-version compatibility: every frozen 1.0 and 1.1 message means the same under this
    version; writing it again changes the version field only."""
    data = bytes.fromhex(vec["hex"])
    wire = json_to_wire(vec["value"])
    assert wire["v"] == [int(x) for x in version.split(".")]
    kind = vec["message"]
    if kind in REENCODE:
        decode, encode, _ = REENCODE[kind]
        again = encode(decode(data))
    elif kind == "error":
        err = P.decode_error_map(P.unpack_message(data))
        again = P.encode_error(err.code, err.message, err.rid)
    else:
        again = _reply_encoders(kind, P.decode_reply(data))
    assert msgpack.unpackb(again, raw=False) == _as_current(wire)


@pytest.mark.parametrize("version,vec", _frozen(("state",)))
def test_frozen_state_vectors_still_read(version, vec):
    data = bytes.fromhex(vec["hex"])
    val = vec["value"]
    assert (data[4], data[5]) == tuple(int(x) for x in version.split("."))
    st = P.decode_state(data)
    assert st.positions.tolist() == val["positions"] and st.tick == val["tick"] and st.flags == val["flags"]
    assert (st.normals is None and val["normals"] is None) or st.normals.tolist() == val["normals"]
    inp = vec["input"]
    normals = None if inp["normals"] is None else np.array(inp["normals"], np.float32)
    again = bytes(
        P.encode_state(
            val["tick"],
            val["server_time_ns"],
            np.array(inp["positions"], np.float32),
            normals,
            val["encoding"],
            inp["flags"],
        )
    )
    assert again[:5] + again[6:] == data[:5] + data[6:] and again[5] == P.PROTOCOL_MINOR  # only the minor byte


@pytest.mark.parametrize("version,vec", _frozen(("bundle",)))
def test_frozen_bundle_vectors_still_read(version, vec):
    data = bytes.fromhex(vec["hex"])
    val = vec["value"]
    b = P.parse_bundle(data)
    assert (b.minor, b.tick, len(b.entries)) == (val["minor"], val["tick"], val["count"])
    for i, ev in enumerate(val["entries"]):
        st = b.state(i)
        assert st.cloth == ev["cloth"] and st.positions.tolist() == ev["state"]["positions"]
    inp = vec["input"]
    again = bytes(
        P.encode_bundle(
            inp["tick"], inp["server_time_ns"], [(s["cloth"], bytes.fromhex(s["hex"])) for s in inp["states"]]
        )
    )
    assert again[:5] + again[6:] == data[:5] + data[6:] and again[5] == P.PROTOCOL_MINOR  # only the minor byte


def test_committed_vectors_are_current():
    """The generator reproduces the committed files (a protocol change must update both)."""
    for group, items in fresh_vectors().items():
        assert json.loads(json.dumps(items)) == load(group), f"tests/vectors/{group}.json is stale"


# ---------------------------------------------------------------------------------------------
# The client mirrors the server's vocabulary and geometry without importing it


def test_the_document_s_hex_examples_are_the_vectors():
    """Every hex dump in PROTOCOL.md is byte for byte one of the committed vectors."""
    text = (Path(__file__).resolve().parents[2] / "PROTOCOL.md").read_text()
    known = {v["hex"] for g in ("misc", "state", "bundle", "predictive") for v in load(g)}
    dumps = []
    for block in text.split("```")[1::2]:
        data = []
        for line in block.splitlines():
            for tok in line.split():
                if len(tok) != 2 or not all(c in "0123456789abcdef" for c in tok):
                    break
                data.append(tok)
        if len(data) >= 16:
            dumps.append("".join(data))
    assert len(dumps) == 4, "the remove message, a state, a bundle and a predictive state"
    for d in dumps:
        assert d in known, d[:64]


def test_the_document_states_the_protocol_s_limits_and_codes():
    """PROTOCOL.md's limits table and error table are this package's values."""
    text = (Path(__file__).resolve().parents[2] / "PROTOCOL.md").read_text()
    assert text.startswith(f"# Drape wire protocol, version {P.VERSION_STRING}")
    lim = P.DEFAULT_LIMITS
    assert f"| `max_iterations`, `max_substeps` | {lim.max_iterations}, {lim.max_substeps} |" in text
    assert f"| `max_colliders` (colliders per cloth) | {lim.max_colliders} |" in text

    def sp(n: int) -> str:  # 65 536
        return f"{n:,}".replace(",", " ")

    assert f"| {P.MAX_NESTING}, {P.MAX_MAP_KEYS}, {sp(P.MAX_ARRAY_LENGTH)}, {sp(P.MAX_STRING_BYTES)} |" in text
    assert f"| values per message (1.2, fixed) | {sp(P.MAX_ELEMENTS)} |" in text
    for code in P.ERROR_CODES:
        if code != P.ERR_UNAVAILABLE:  # the SDK's own, never on the wire
            assert f"| `{code}` |" in text, code
