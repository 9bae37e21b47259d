"""Write the protocol test vectors (tests/vectors/*.json) from drape.client.protocol.

    .venv/bin/python tests/vectors/generate.py

The vectors are committed; tests/test_protocol.py checks them both ways (bytes -> meaning and
meaning -> identical bytes), so regenerating them is only needed when the protocol changes on
purpose (and then PROTOCOL.md's version rules apply). Format: see PROTOCOL.md, "Test vectors".

tests/vectors/v1.0/ and tests/vectors/v1.1/ hold the vectors of protocols 1.0 and 1.1 as they were
committed, frozen: this script never rewrites them, and the tests check that this implementation
still reads every one the same way.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from drape.client import protocol as P

HERE = Path(__file__).resolve().parent

#: bin fields and the little-endian element type of their contents
BIN_TYPES = {
    "pinned": "u32",
    "vertices": "f32",
    "triangles": "u32",
    "indices": "u32",
    "targets": "f32",
    "positions": "f32",
    "velocities": "f32",
}  # 1.3: resume
INVALID_NOTE = (
    "Validation only: the verdicts are the decoder's, on the bytes alone. A server then also checks that "
    "each cloth exists and that the token owns it (not_found, forbidden), which these vectors do not "
    "exercise: their cloth ids and tokens are placeholders."
)
DTYPES = {"u32": "<u4", "f32": "<f4"}


def wire_to_json(obj: Any, key: str | None = None) -> Any:
    """A decoded msgpack value as JSON: bin fields become {"u32": [...]} / {"f32": [...]}."""
    if isinstance(obj, dict):
        return {k: wire_to_json(v, k) for k, v in obj.items()}
    if isinstance(obj, list):
        return [wire_to_json(v, key) for v in obj]
    if isinstance(obj, (bytes, bytearray)):
        t = BIN_TYPES[key]  # type: ignore[index]
        return {t: np.frombuffer(obj, DTYPES[t]).tolist()}
    return obj


def json_to_wire(obj: Any) -> Any:
    """The inverse of wire_to_json."""
    if isinstance(obj, dict):
        if len(obj) == 1 and next(iter(obj)) in DTYPES:
            t, values = next(iter(obj.items()))
            return np.asarray(values, DTYPES[t]).tobytes()
        return {k: json_to_wire(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [json_to_wire(v) for v in obj]
    return obj


TOKEN = "0123456789abcdef0123456789abcdef"
CLOTH = "5ba88a14c526242f"
TOKEN2 = "fedcba9876543210fedcba9876543210"
CLOTH2 = "0f1e2d3c4b5a6978"


def msg_vector(name: str, message: str, description: str, data: bytes) -> dict[str, Any]:
    return {
        "name": name,
        "message": message,
        "description": description,
        "hex": data.hex(),
        "value": wire_to_json(msgpack.unpackb(data, raw=False)),
    }


def state_vector(
    name: str, description: str, tick: int, t_ns: int, positions, normals, encoding: str, flags: int = 0
) -> dict[str, Any]:
    pos = np.asarray(positions, np.float32)
    nrm = None if normals is None else np.asarray(normals, np.float32)
    data = bytes(P.encode_state(tick, t_ns, pos, nrm, encoding, flags))
    st = P.decode_state(data)
    return {
        "name": name,
        "message": "state",
        "description": description,
        "hex": data.hex(),
        "input": {"positions": pos.tolist(), "normals": None if nrm is None else nrm.tolist(), "flags": flags},
        "value": state_value(st, data),
    }


def state_value(st: P.ClothState, data: bytes | memoryview) -> dict[str, Any]:
    return {
        "magic": "DRPS",
        "major": data[4],
        "minor": data[5],
        "header_size": int.from_bytes(bytes(data[6:8]), "little"),
        "encoding": st.encoding,
        "flags": st.flags,
        "vertex_count": st.n_vertices,
        "tick": st.tick,
        "server_time_ns": st.server_time_ns,
        "bounds_min": list(st.bounds[0]),
        "bounds_max": list(st.bounds[1]),
        "positions": st.positions.tolist(),
        "normals": None if st.normals is None else st.normals.tolist(),
    }


def rates_vectors() -> list[dict[str, Any]]:
    """1.8 (PROTOCOL.md 9.3; 1.9's k = 6, 12): the decimated keys of a state key and a bundle key, and a stream of
    every 2nd state (ticks 100, 102, 104 of the motion of ``predictive_vectors``' first three
    frames, sampled at 30 Hz), each predicted from the key's own states (ref ticks T - 2, T - 4)."""
    keys = P.Keys()
    out: list[dict[str, Any]] = [
        {
            "name": f"rate_key_{kind}_{k}",
            "message": "key",
            "description": f"{'.'.join(map(str, P.RATE_SINCE[k]))}: the key of every {k}-th state of a {kind} key.",
            "input": {"key": base, "every": k},
            "value": {"key": P.every_key(base, k)},
        }
        for kind, base in (("state", keys.client_state("alice", "cape-1")), ("bundle", keys.bundle("alice")))
        for k in P.RATES[1:]
    ]
    step = 0.002
    frames = [
        [[0.0, 2.0, 0.0], [1.0, 1.5, -0.25], [0.5, 1.0, 0.75]],
        [[0.021, 2.001, 0.0], [1.023, 1.481, -0.249], [0.499, 0.985, 0.771]],
        [[0.04, 2.0, 0.002], [1.046, 1.46, -0.251], [0.497, 0.97, 0.79]],
    ]
    enc, dec = P.History(), P.StateStream("c")
    for i, pos in enumerate(frames):
        tick, t_ns = 100 + 2 * i, 1_700_000_000_000_000_000 + 2 * i * 16_666_667
        x = np.asarray(pos, np.float32)
        data = bytes(P.encode_predictive_state(tick, t_ns, x, step, enc, keyframe=i == 0))
        st = dec.decode(data)
        assert st is not None
        ph = P.read_predictive_header(data)
        assert (ph.ref_tick, ph.ref2_tick) == ((tick - 2 if i else 0), (tick - 4 if i > 1 else 0))
        out.append(
            {
                "name": f"every_2_predictive_{i}",
                "message": "state",
                "description": f"1.8: state {i} of a stream of every 2nd state (order {ph.order}), step 2 mm, "
                "on {key}/every/2: predicted from the key's own states.",
                "hex": data.hex(),
                "input": {"positions": x.tolist(), "keyframe": i == 0, "step": step},
                "value": {
                    **state_value(st, data),
                    "order": ph.order,
                    "ref_tick": ph.ref_tick,
                    "ref2_tick": ph.ref2_tick,
                },
            }
        )
    return out + governor_vectors()


#: The governor traces' clock: ticks of 60 Hz, the client's clock this far ahead of the server's
#: (not lateness), and the link's own delay.
GOVERNOR_TICK_NS = 16_666_667
GOVERNOR_OFFSET_NS = 123_456_789_000
GOVERNOR_LINK_NS = 20_000_000


def governor_vectors() -> list[dict[str, Any]]:
    """1.8: ``rate="auto"``'s rule (client/rates.py's RateGovernor with its defaults) as data, so
    that every SDK steps at the same states with the same numbers: its constants, and traces of
    states arriving (tick, server time ``tick * tick_ns``, receive time server time + offset +
    link delay + ``late_us``) with the rate changes the Python governor made at each (the index
    of the state, the new rate). The traces cover a growing backlog (two steps down, two up after
    the quiet period), a link far too slow (one jump to the lowest rate), lost states, and step
    ups that do not hold (the quiet period doubled). Each trace's ``input.rates`` is the ladder of
    the rates its server serves (protocol.served_rates: 1.9's 1, 2, 3, 6, 12, or a 1.8 server's
    1, 2, 3, where ``auto`` stops at 3), the governor's ``rates``."""
    from drape.client.rates import RateGovernor

    base = RateGovernor()
    constants = {
        "rates": list(base.rates),
        "window_s": base.window_s,
        "late_s": base.late_s,
        "jump_s": base.jump_s,
        "lost_share": base.lost_share,
        "quiet_s": base.quiet_s,
        "max_quiet_s": base.max_quiet_s,
        "baseline_windows": base._base_window,
        "late_percentile": 90,
        "settle_windows": 1.5,
        "failed_up_windows": 3,
    }

    def trace(
        name: str,
        note: str,
        ticks: range,
        late_ms: Any,
        drop: Any = lambda gov, t: False,
        version: tuple[int, int] = P.PROTOCOL_VERSION,
    ) -> dict[str, Any]:
        gov = RateGovernor(rates=P.served_rates(version))
        fed: list[int] = []
        late_us: list[int] = []
        changes: list[list[int]] = []
        for t in ticks:
            if t % gov.rate or drop(gov, t):
                continue
            lus = int(round(late_ms(gov, t) * 1000))
            server = t * GOVERNOR_TICK_NS
            new = gov.observe(t, server, server + GOVERNOR_OFFSET_NS + GOVERNOR_LINK_NS + lus * 1000)
            if new is not None:
                changes.append([len(fed), new])
            fed.append(t)
            late_us.append(lus)
        return {
            "name": f"governor_{name}",
            "message": "governor",
            "description": f"rate=auto facing a {version[0]}.{version[1]} server: {note}",
            "input": {
                "constants": constants,
                "rates": list(gov.rates),
                "tick_ns": GOVERNOR_TICK_NS,
                "offset_ns": GOVERNOR_OFFSET_NS,
                "link_ns": GOVERNOR_LINK_NS,
                "ticks": fed,
                "late_us": late_us,
            },
            "value": {
                "changes": [c for pair in changes for c in pair],
                "rate": gov.rate,
                "step_downs": gov.step_downs,
                "step_ups": gov.step_ups,
                "quiet_s": gov._quiet,
            },
        }

    return [
        trace("on_time", "states on time keep the full rate (30 s).", range(1, 60 * 30), lambda g, t: 0.0),
        trace(
            "backlog",
            "a backlog growing at 60 and 30 Hz steps down twice, then on time it steps back up twice, "
            "each after the quiet period (30 s).",
            range(1, 60 * 30),
            lambda g, t: 0.0 if g.rate == 3 or t >= 600 else (t % 600) * 0.5,
        ),
        trace(
            "ladder",
            "a backlog growing at every rate down to 5 Hz steps down one rate at a time (2, 3, 6, 12), "
            "then on time it steps back up one at a time, each after the quiet period (50 s).",
            range(1, 60 * 50),
            lambda g, t: 0.0 if g.rate == 12 or t >= 800 else (t % 300) * 0.5,
        ),
        trace(
            "jump",
            "lateness past jump_s goes straight to the lowest rate, every 12th state (3 s).",
            range(1, 180),
            lambda g, t: 0.0 if g.rate == 12 else t * 5.0,
        ),
        trace(
            "jump_1_8",
            "the same link far too slow facing a 1.8 server: straight to its lowest rate, every 3rd "
            "state, and no lower (6 s).",
            range(1, 360),
            lambda g, t: t * 5.0,
            version=(1, 8),
        ),
        trace(
            "lost",
            "half the states never come: a step down (4 s).",
            range(1, 240),
            lambda g, t: 0.0,
            lambda g, t: t % 2 == 1,
        ),
        trace(
            "failed_up",
            "the full rate never fits: step ups that do not hold double the quiet period (20 s).",
            range(1, 60 * 20),
            lambda g, t: (t % 120) * 2.0 if g.rate == 1 else 0.0,
        ),
    ]


def mesh_vectors() -> list[dict[str, Any]]:
    """1.8 (PROTOCOL.md 5.4): a mesh collider (a tetrahedron, counter-clockwise seen from outside)
    sent with a submission, moved, re-posed and removed by controls and a batch item, set and
    moved by a scene's owner; then what a decoder refuses (``error``)."""
    verts = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], np.float32)
    tris = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.uint32)
    quarter = (0.9238795325112867, 0.0, 0.3826834323650898, 0.0)  # 45 degrees about +y
    tok = "0123456789abcdef0123456789abcdef"
    mesh = P.MeshCollider(verts, tris, (0.0, 1.0, 0.0))
    move = P.MeshCollider.pose((0.1, 1.0, 0.0), quarter)
    out = [
        msg_vector(
            "submit_mesh_collider",
            "submit",
            "1.8: a 4x4 cape with its own mesh collider, a tetrahedron 1 m up.",
            P.encode_submit(
                P.SubmitRequest(
                    client="game-7",
                    grid=P.GridSpec(4, 4),
                    pinned=np.array([0, 3], np.uint32),
                    mesh_collider=mesh,
                    rid=30,
                )
            ),
        ),
        msg_vector(
            "control_mesh_move",
            "control",
            "1.8: the per-tick rigid move of the cloth's mesh: 0.1 m along x, turned 45 degrees about y.",
            P.encode_control(P.ControlRequest("cape-1", tok, mesh_collider=move, rid=31)),
        ),
        msg_vector(
            "control_mesh_repose",
            "control",
            "1.8: a re-pose: new positions of the mesh's 4 vertices, the same triangles, at the same pose.",
            P.encode_control(
                P.ControlRequest(
                    "cape-1", tok, mesh_collider=P.MeshCollider(verts * 1.1, None, (0.0, 1.0, 0.0)), rid=32
                )
            ),
        ),
        msg_vector(
            "control_mesh_remove",
            "control",
            "1.8: the cloth's mesh collider removed.",
            P.encode_control(P.ControlRequest("cape-1", tok, mesh_collider=P.MeshCollider.removal(), rid=33)),
        ),
        msg_vector(
            "control_batch_mesh_move",
            "control_batch",
            "1.8: a batch item moving one cloth's mesh beside another's pin move.",
            P.encode_control_batch(
                P.ControlBatchRequest(
                    "game-7",
                    [
                        P.ControlRequest("cape-1", tok, mesh_collider=move),
                        P.ControlRequest(
                            "cape-2",
                            tok,
                            pins=P.PinUpdate(np.array([0], np.uint32), np.array([[0.0, 2.0, 0.0]], np.float32)),
                        ),
                    ],
                    rid=34,
                )
            ),
        ),
        msg_vector(
            "scene_mesh_set",
            "scene",
            "1.8: the owner of scene arena-1 gives it a mesh collider, for every cloth of it.",
            P.encode_scene(P.SceneRequest("c1", "arena-1", rid=35, mesh_collider=mesh)),
        ),
        msg_vector(
            "scene_mesh_move",
            "scene",
            "1.8: the owner of scene arena-1 moves the scene's mesh (the per-tick change).",
            P.encode_scene(P.SceneRequest("c1", "arena-1", rid=36, mesh_collider=move)),
        ),
    ]

    def control(mc: dict[str, Any]) -> bytes:
        return msgpack.packb({"v": [1, 8], "rid": 40, "cloth": "cape-1", "token": tok, "mesh_collider": mc})

    f4, u4 = verts.astype("<f4").tobytes(), tris.astype("<u4").tobytes()
    bad = [
        (
            "mesh_degenerate",
            {"vertices": f4, "triangles": np.array([[0, 1, 1]], "<u4").tobytes()},
            "invalid_value",
            "a triangle with a repeated index (area 0)",
        ),
        (
            "mesh_index_out_of_range",
            {"vertices": f4, "triangles": np.array([[0, 1, 4]], "<u4").tobytes()},
            "invalid_value",
            "a triangle naming vertex 4 of 4",
        ),
        (
            "mesh_not_finite",
            {
                "vertices": np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0]], "<f4").tobytes(),
                "triangles": np.array([[0, 1, 2]], "<u4").tobytes(),
            },
            "invalid_value",
            "a NaN vertex",
        ),
        ("mesh_triangles_without_vertices", {"triangles": u4}, "missing_field", "triangles without vertices"),
        (
            "mesh_remove_and_more",
            {"remove": True, "position": [0.0, 0.0, 0.0]},
            "invalid_value",
            "remove with another key",
        ),
        ("mesh_zero_rotation", {"rotation": [0.0, 0.0, 0.0, 0.0]}, "invalid_value", "a zero quaternion"),
        ("mesh_unknown_key", {"scale": 2.0}, "invalid_value", "an unknown key"),
    ]
    out += [
        {
            "name": n,
            "message": "control",
            "description": f"1.8, refused: {why}.",
            "hex": control(mc).hex(),
            "error": code,
        }
        for n, mc, code, why in bad
    ]
    return out


def predictive_vectors() -> list[dict[str, Any]]:
    """1.5: one stream of predictive states (PROTOCOL.md 9.2), in order: a keyframe, a state of
    order 1, two of order 2 (the last with normals), then a keyframe again; and a submit asking
    for the encoding with its step. Each state's ``value`` is what a decoder that received the
    stream's states before it rebuilds; ``input`` the float32 positions the encoder was given."""
    step = 0.002
    frames = [
        [[0.0, 2.0, 0.0], [1.0, 1.5, -0.25], [0.5, 1.0, 0.75]],
        [[0.01, 2.0, 0.0], [1.012, 1.49, -0.25], [0.5, 0.993, 0.76]],
        [[0.021, 2.001, 0.0], [1.023, 1.481, -0.249], [0.499, 0.985, 0.771]],
        [[0.03, 2.002, 0.001], [1.035, 1.47, -0.25], [0.498, 0.978, 0.78]],
        [[0.04, 2.0, 0.002], [1.046, 1.46, -0.251], [0.497, 0.97, 0.79]],
    ]
    nrm = [[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]]
    enc, dec = P.History(), P.StateStream("c")
    out: list[dict[str, Any]] = []
    notes = ["a keyframe (order 0)", "order 1", "order 2", "order 2, with normals", "a keyframe again"]
    for i, (pos, note) in enumerate(zip(frames, notes, strict=True)):
        tick, t_ns = 100 + i, 1_700_000_000_000_000_000 + i * 16_666_667
        normals = np.asarray(nrm, np.float32) if i == 3 else None
        x = np.asarray(pos, np.float32)
        data = bytes(P.encode_predictive_state(tick, t_ns, x, step, enc, keyframe=i in (0, 4), normals=normals))
        st = dec.decode(data)
        assert st is not None
        ph = P.read_predictive_header(data)
        out.append(
            {
                "name": f"predictive_{i}",
                "message": "state",
                "description": f"State {i} of one predictive stream of three vertices, step 2 mm: {note}.",
                "hex": data.hex(),
                "input": {
                    "positions": x.tolist(),
                    "normals": None if normals is None else normals.tolist(),
                    "keyframe": i in (0, 4),
                    "step": step,
                },
                "value": {
                    **state_value(st, data),
                    "step": ph.step,
                    "order": ph.order,
                    "stride": ph.stride,
                    "ref_tick": ph.ref_tick,
                    "ref2_tick": ph.ref2_tick,
                    "data_size": ph.data_size,
                },
            }
        )
    sub = P.SubmitRequest(
        client="c1", grid=P.GridSpec(2, 2), state=P.StateOptions(encoding="predictive", step=0.002), rid=1
    )
    out.append(
        msg_vector(
            "submit_predictive",
            "submit",
            "1.5: a 2x2 grid published with the predictive encoding, step 2 mm.",
            P.encode_submit(sub),
        )
    )
    return out


def bundle_vector(
    name: str, description: str, tick: int, t_ns: int, cloths: list[tuple[str, Any, Any, str, int]]
) -> dict[str, Any]:
    """cloths: (id, positions, normals, encoding, flags) per entry."""
    states = []
    for cid, pos, nrm, enc, flags in cloths:
        pos = np.asarray(pos, np.float32)
        nrm = None if nrm is None else np.asarray(nrm, np.float32)
        states.append((cid, bytes(P.encode_state(tick, t_ns, pos, nrm, enc, flags))))
    data = bytes(P.encode_bundle(tick, t_ns, states))
    b = P.parse_bundle(data)
    entries = []
    at = P.BUNDLE_HEADER_SIZE
    for i, e in enumerate(b.entries):
        entries.append(
            {
                "cloth": e.cloth,
                "entry_offset": at,
                "entry_header_size": e.offset - at,
                "state_offset": e.offset,
                "state_size": e.size,
                "state": state_value(b.state(i), b.payload(i)),
            }
        )
        at = P.align8(e.offset + e.size)
    return {
        "name": name,
        "message": "bundle",
        "description": description,
        "hex": data.hex(),
        "input": {"tick": tick, "server_time_ns": t_ns, "states": [{"cloth": c, "hex": st.hex()} for c, st in states]},
        "value": {
            "magic": "DRPB",
            "major": P.PROTOCOL_MAJOR,
            "minor": P.PROTOCOL_MINOR,
            "header_size": P.BUNDLE_HEADER_SIZE,
            "count": len(entries),
            "flags": b.flags,
            "tick": tick,
            "server_time_ns": t_ns,
            "size": len(data),
            "entries": entries,
        },
    }


def vectors() -> dict[str, list[dict[str, Any]]]:
    quad_v = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], np.float32)
    quad_t = np.array([[0, 3, 1], [1, 3, 2]], np.uint32)
    submit = [
        msg_vector(
            "submit_grid_full",
            "submit",
            "A vertical 8x4 grid with every optional field.",
            P.encode_submit(
                P.SubmitRequest(
                    client="game-7",
                    grid=P.GridSpec(8, 4, 1.6, 0.8, "vertical", (0.0, 2.0, 0.0)),
                    pinned=np.array([0, 7], np.uint32),
                    links=P.LinkSpec(True, True, True),
                    material={"mass": 0.5, "stiffness": (1.0, 0.9, 0.5), "damping": 0.01},
                    features=("tethers",),
                    gravity=(0.0, -9.81, 0.0),
                    wind=(1.0, 0.0, 0.0),
                    iterations=12,
                    substeps=2,
                    colliders=(P.Sphere((0.8, 1.5, 0.3), 0.25),),
                    state=P.StateOptions(True, "float32"),
                    rid=1,
                )
            ),
        ),
        msg_vector(
            "submit_bundle",
            "submit",
            "1.1: a 4x4 grid whose state goes in the client's bundle, quant16.",
            P.encode_submit(
                P.SubmitRequest(
                    client="game-7",
                    grid=P.GridSpec(4, 4),
                    pinned=np.array([0, 3], np.uint32),
                    state=P.StateOptions(None, "quant16", True),
                    rid=7,
                )
            ),
        ),
        msg_vector(
            "submit_grid_minimal",
            "submit",
            "The smallest submission: a 4x4 grid, server defaults.",
            P.encode_submit(P.SubmitRequest(client="c1", grid=P.GridSpec(4, 4))),
        ),
        msg_vector(
            "submit_mesh",
            "submit",
            "A 4-vertex, 2-triangle mesh pinned at vertex 0, quantised states.",
            P.encode_submit(
                P.SubmitRequest(
                    client="c1",
                    mesh=P.MeshSpec(quad_v, quad_t),
                    pinned=np.array([0], np.uint32),
                    state=P.StateOptions(None, "quant16"),
                    rid=2,
                )
            ),
        ),
        msg_vector(
            "submit_resume",
            "submit",
            "1.3: a 2x2 grid resubmitted after a failover, continuing from the "
            "state of tick 1042 of cloth 5ba88a14c526242f on server s1: positions and velocities of its 4 "
            "vertices (vertex 0 pinned: it starts at its given position with zero velocity).",
            P.encode_submit(
                P.SubmitRequest(
                    client="c1",
                    grid=P.GridSpec(2, 2),
                    pinned=np.array([0], np.uint32),
                    rid=9,
                    resume=P.ResumeState(
                        np.array([[0, 1, 0], [1, 0.75, 0.25], [0, 0.5, 1], [1, 0.25, 1]], np.float32),
                        np.array([[0, 0, 0], [0.5, -1, 0], [0, -1.5, 0.25], [0.5, -2, 0]], np.float32),
                        1042,
                        "s1",
                        CLOTH,
                    ),
                )
            ),
        ),
        msg_vector(
            "submit_self_collision",
            "submit",
            "1.6: an 8x8 cape pinned at two corners that keeps 5 mm between its non-neighbouring vertices "
            "(the self_collision feature with the material's thickness and contact_stiffness).",
            P.encode_submit(
                P.SubmitRequest(
                    client="c1",
                    grid=P.GridSpec(8, 8, 0.5, 0.5),
                    pinned=np.array([0, 7], np.uint32),
                    material={"thickness": 0.005, "contact_stiffness": 0.5},
                    features=("self_collision",),
                    rid=10,
                )
            ),
        ),
        msg_vector(
            "submit_scene",
            "submit",
            "1.7: a cape in scene arena-1, where it collides with the scene's other cloths (3 cm apart: "
            "the material's thickness) and the scene's colliders.",
            P.encode_submit(
                P.SubmitRequest(
                    client="c1",
                    grid=P.GridSpec(8, 8, 0.5, 0.5, "vertical"),
                    pinned=np.array([0, 7], np.uint32),
                    material={"thickness": 0.03},
                    scene="arena-1",
                    rid=13,
                )
            ),
        ),
        msg_vector(
            "submit_resume_positions",
            "submit",
            "1.3: the least resume: positions only (velocities zero).",
            P.encode_submit(
                P.SubmitRequest(
                    client="c1",
                    grid=P.GridSpec(2, 1),
                    resume=P.ResumeState(np.array([[0, 2, 0], [1, 2, 0]], np.float32)),
                )
            ),
        ),
    ]
    control = [
        msg_vector(
            "control_full",
            "control",
            "Pins, colliders, gravity, wind, material, features, iterations, substeps, state options and a reset.",
            P.encode_control(
                P.ControlRequest(
                    cloth=CLOTH,
                    token=TOKEN,
                    pins=P.PinUpdate(np.array([0, 7], np.uint32), np.array([[0, 2, 0], [1.5, 2, 0.25]], np.float32)),
                    colliders=(P.Plane((0.0, 1.0, 0.0), -1.0), P.Capsule((0, 1, 0), (1, 1, 0), 0.1)),
                    gravity=(0.0, -20.0, 0.0),
                    wind=(0.0, 0.0, 3.0),
                    material={"drag": 0.3, "lift": 0.1},
                    features=("wind", "colliders"),
                    iterations=8,
                    substeps=1,
                    state=P.StateOptions(False, "float16"),
                    reset=True,
                    rid=3,
                )
            ),
        ),
        msg_vector(
            "control_pins",
            "control",
            "Move pinned vertex 3.",
            P.encode_control(
                P.ControlRequest(
                    CLOTH,
                    TOKEN,
                    pins=P.PinUpdate(np.array([3], np.uint32), np.array([[0.5, 1.0, -0.5]], np.float32)),
                    rid=4,
                )
            ),
        ),
        msg_vector(
            "control_batch",
            "control_batch",
            "1.1: one request controlling two cloths of client game-7: "
            "pins and a collider for the first, a reset for the second.",
            P.encode_control_batch(
                P.ControlBatchRequest(
                    "game-7",
                    [
                        P.ControlRequest(
                            CLOTH,
                            TOKEN,
                            pins=P.PinUpdate(np.array([0, 3], np.uint32), np.array([[0, 1, 0], [1, 1, 0]], np.float32)),
                            colliders=(P.Sphere((0.5, 0.5, 0.0), 0.2),),
                        ),
                        P.ControlRequest(CLOTH2, TOKEN2, reset=True),
                    ],
                    rid=10,
                )
            ),
        ),
        msg_vector(
            "control_batch_moves",
            "control_batch",
            "1.4: the pins of two cloths of client game-7 moved as one block: vertices 0 and 3 of each, "
            "the first cloth's targets then the second's; no items.",
            P.encode_control_batch(
                P.ControlBatchRequest(
                    "game-7",
                    [],
                    rid=13,
                    moves=P.PinMoves(
                        [CLOTH, CLOTH2],
                        [TOKEN, TOKEN2],
                        np.array([0, 3], np.uint32),
                        np.array([[[0, 1, 0], [1, 1, 0]], [[0, 1.5, 0.25], [1, 1.5, 0.25]]], np.float32),
                    ),
                )
            ),
        ),
        msg_vector(
            "control_batch_moves_items",
            "control_batch",
            "1.4: an item (a collider for the first cloth) and a block moving vertex 0 of both cloths; "
            "the item applies first, then the block.",
            P.encode_control_batch(
                P.ControlBatchRequest(
                    "game-7",
                    [P.ControlRequest(CLOTH, TOKEN, colliders=(P.Sphere((0.5, 0.5, 0.0), 0.2),))],
                    rid=14,
                    moves=P.PinMoves(
                        [CLOTH, CLOTH2],
                        [TOKEN, TOKEN2],
                        np.array([0], np.uint32),
                        np.array([[[0, 1, 0]], [[0, 1.5, 0.25]]], np.float32),
                    ),
                )
            ),
        ),
        msg_vector(
            "control_features_add_remove",
            "control",
            "1.2: switch wind on and tethers off, keeping every "
            "other feature of the cloth (features_add / features_remove instead of replacing the set).",
            P.encode_control(
                P.ControlRequest(
                    CLOTH, TOKEN, material={"drag": 0.3}, features_add=("wind",), features_remove=("tethers",), rid=11
                )
            ),
        ),
    ]
    other = [
        msg_vector("remove", "remove", "Remove a cloth.", P.encode_remove(P.RemoveRequest(CLOTH, TOKEN, 5))),
        msg_vector(
            "info",
            "info",
            "Ask for the server's description (an empty payload is accepted too).",
            P.encode_info(P.InfoRequest(6)),
        ),
        msg_vector(
            "reply_submit",
            "reply_submit",
            "A submission accepted.",
            P.encode_submit_reply(P.SubmitReply(CLOTH, TOKEN, f"drape/cloth/{CLOTH}/state", 32, 1042, 1)),
        ),
        msg_vector(
            "reply_control",
            "reply_control",
            "A control applied from tick 1050 on.",
            P.encode_control_reply(P.ControlReply(1050, 3)),
        ),
        msg_vector(
            "reply_submit_bundle",
            "reply_submit",
            "1.1: a bundled submission accepted: its state goes in client game-7's bundle.",
            P.encode_submit_reply(
                P.SubmitReply(CLOTH, TOKEN, f"drape/cloth/{CLOTH}/state", 16, 1042, 7, "drape/client/game-7/states")
            ),
        ),
        msg_vector(
            "reply_control_batch",
            "reply_control_batch",
            "1.1: a batch of two: the first applied from tick 1050 on, the second refused (not the owner's token).",
            P.encode_control_batch_reply(
                P.ControlBatchReply(
                    1050,
                    [
                        P.BatchItemResult(1050),
                        P.BatchItemResult(None, "forbidden", f"the token does not own cloth '{CLOTH2}'"),
                    ],
                    10,
                )
            ),
        ),
        msg_vector(
            "reply_control_batch_moves",
            "reply_control_batch",
            "1.4: the reply to a block of two moves and no items: the first applied from tick 1050 on, "
            "the second (position 1) refused.",
            P.encode_control_batch_reply(
                P.ControlBatchReply(1050, [], 13, 1050, [(1, "forbidden", f"the token does not own cloth '{CLOTH2}'")])
            ),
        ),
        msg_vector(
            "scene",
            "scene",
            "1.7: the owner of scene arena-1 moves its colliders (a body's capsule and the floor) and lets "
            "clients c2 and c3 put cloths in it.",
            P.encode_scene(
                P.SceneRequest(
                    "c1",
                    "arena-1",
                    (P.Capsule((0.0, 0.2, 0.0), (0.0, 1.4, 0.0), 0.2), P.Plane((0.0, 1.0, 0.0), 0.0)),
                    ("c2", "c3"),
                    14,
                )
            ),
        ),
        msg_vector(
            "scene_open",
            "scene",
            "1.7: the owner of scene arena-1 lets every client put cloths in it and leaves its colliders as they are.",
            P.encode_scene(P.SceneRequest("c1", "arena-1", members=(P.SCENE_ANYONE,), rid=15)),
        ),
        msg_vector(
            "reply_scene",
            "reply_scene",
            "1.7: a scene request applied: its colliders are where they were sent in the state of tick 1062.",
            P.encode_scene_reply(P.SceneReply(1062, "c1", 3, ("c2", "c3"), 14)),
        ),
        msg_vector(
            "reply_remove",
            "reply_remove",
            "A cloth removed; 1061 was its last state.",
            P.encode_remove_reply(P.RemoveReply(1061, 5)),
        ),
        msg_vector(
            "reply_error",
            "error",
            "An error reply.",
            P.encode_error("index_out_of_range", "'pinned' refers to vertex 16 but the cloth has 16 vertices", 9),
        ),
        msg_vector(
            "reply_control_features",
            "reply_control",
            "1.2: a control applied from tick 1050 on; the cloth's feature set after it, in the protocol's order.",
            P.encode_control_reply(P.ControlReply(1050, 11, ("colliders", "wind", "normals"))),
        ),
        msg_vector(
            "reply_control_batch_features",
            "reply_control_batch",
            "1.2: a batch of one applied item, with the cloth's resulting feature set.",
            P.encode_control_batch_reply(
                P.ControlBatchReply(1050, [P.BatchItemResult(1050, features=("xpbd", "tethers"))], 12)
            ),
        ),
        msg_vector(
            "reply_info",
            "reply_info",
            "An info reply (1.2 server, defaults).",
            P.encode_ok(
                6,
                server="s1",
                version=P.VERSION_STRING,
                solver="workgroup",
                device="pthread-cpu",
                tick_rate=60.0,
                tick=1042,
                cloths=2,
                clients=1,
                vertices=2048,
                limits={
                    "max_cloths": 1024,
                    "max_cloths_per_client": 64,
                    "max_vertices_per_cloth": 65536,
                    "max_total_vertices": 2097152,
                    "max_message_bytes": 8 << 20,
                    "max_pin_updates": 4096,
                    "max_batch_items": 64,
                    "max_colliders": 32,
                    "max_iterations": 100,
                    "max_substeps": 100,
                },
                encodings=list(P.ENCODINGS),
                features=list(P.FEATURE_NAMES),
                grace_period_s=5.0,
                stats_period_s=1.0,
            ),
        ),
        msg_vector(
            "stats",
            "stats",
            "A stats publication (informational: fields may be added in any minor version).",
            P.encode_stats(
                {
                    "server": "s1",
                    "tick": 1042,
                    "time_ns": 1_700_000_000_123_456_789,
                    "uptime_s": 17.4,
                    "tick_rate": 60.0,
                    "cloths": 2,
                    "clients": 1,
                    "alive_clients": 1,
                    "vertices": 2048,
                    "requests": {"submit": 2, "control": 40},
                    "errors": {"forbidden": 1},
                    "ticks": 1043,
                    "missed_ticks": 0,
                    "skipped_frames": 0,
                    "nan_resets": 0,
                    "reclaimed": 0,
                    "published": 2086,
                    "unwatched": 0,
                    "publish_errors": 0,
                    "bundles": 0,
                    "batch_items": 0,
                    "phases": {"tick": {"mean_ms": 1.5, "max_ms": 3.25, "count": 60, "total_mean_ms": 1.5}},
                    "quality": {
                        "adaptive": True,
                        "presets": {"balanced": 2},
                        "degraded": 0,
                        "degraded_since_ns": None,
                        "degraded_s": 0.0,
                        "changes": 0,
                        "last_change": None,
                    },
                }
            ),
        ),
        msg_vector(
            "reply_error_overloaded",
            "error",
            "1.2: a submission refused because admitting it would break the server's tick budget.",
            P.encode_error(
                "overloaded",
                "admitting 65536 more vertices would exceed the tick budget; retry later or on another server",
                13,
            ),
        ),
    ]
    tri = [[0.0, 2.0, 0.0], [1.0, 1.5, -0.25], [0.5, 1.0, 0.75]]
    nrm = [[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]]
    state = [
        state_vector(
            "state_float32", "Three vertices, float32.", 1042, 1_700_000_000_123_456_789, tri, None, "float32"
        ),
        state_vector(
            "state_float32_normals",
            "Three vertices with normals, float32, after a reset.",
            7,
            42,
            tri,
            nrm,
            "float32",
            P.FLAG_RESET,
        ),
        state_vector(
            "state_float16",
            "Three vertices with normals, float16 (0.1 and 1.3 round).",
            8,
            43,
            [[0.1, 2.0, 0.0], [1.3, 1.5, -0.25], [0.5, 1.0, 0.75]],
            nrm,
            "float16",
        ),
        state_vector(
            "state_quant16",
            "Three vertices with normals, uint16 quantised against the bounds, normals snorm16.",
            9,
            44,
            [[0.0, 2.0, 0.0], [1.0, 1.5, -0.25], [0.3, 1.2, 0.75]],
            nrm,
            "quant16",
        ),
    ]
    bundles = [
        bundle_vector(
            "bundle_two",
            "Two cloths at tick 1042: a float32 one (16-character id) and a quant16 one "
            "with normals (6-character id, so its entry header is padded).",
            1042,
            1_700_000_000_123_456_789,
            [
                (CLOTH, tri, None, "float32", 0),
                ("cape-2", [[0.0, 2.0, 0.0], [1.0, 1.5, -0.25]], nrm[:2], "quant16", P.FLAG_RESET),
            ],
        ),
        bundle_vector("bundle_one", "A bundle of one float16 cloth.", 7, 42, [("c", tri, None, "float16", 0)]),
    ]
    one = bytes.fromhex(bundles[1]["hex"])
    bad_cases = [
        ("truncated", P.encode_submit(P.SubmitRequest(client="c1", grid=P.GridSpec(4, 4)))[:-4], "submit", "malformed"),
        ("unknown_major", msgpack.packb({"v": [2, 0], "client": "c1"}), "submit", "unsupported_version"),
        ("no_version", msgpack.packb({"client": "c1", "grid": {"cols": 2, "rows": 2}}), "submit", "missing_field"),
        (
            "cols_as_string",
            msgpack.packb({"v": [1, 0], "client": "c1", "grid": {"cols": "4", "rows": 4}}),
            "submit",
            "invalid_type",
        ),
        (
            "nan_gravity",
            msgpack.packb(
                {"v": [1, 0], "client": "c1", "grid": {"cols": 2, "rows": 2}, "gravity": [0.0, float("nan"), 0.0]}
            ),
            "submit",
            "invalid_value",
        ),
        (
            "pin_out_of_range",
            msgpack.packb(
                {"v": [1, 0], "client": "c1", "grid": {"cols": 2, "rows": 2}, "pinned": np.array([4], "<u4").tobytes()},
                use_bin_type=True,
            ),
            "submit",
            "index_out_of_range",
        ),
        (
            "grid_too_large",
            msgpack.packb({"v": [1, 0], "client": "c1", "grid": {"cols": 100000, "rows": 100000}}),
            "submit",
            "too_large",
        ),
        ("token_not_hex", msgpack.packb({"v": [1, 0], "cloth": CLOTH, "token": "secret"}), "remove", "invalid_value"),
    ]
    batch = {"v": [1, 1], "rid": 4, "client": "c1"}
    item = {"cloth": CLOTH, "token": TOKEN}
    bad_cases += [
        ("batch_no_items", msgpack.packb(batch), "control_batch", "missing_field"),
        ("batch_items_not_array", msgpack.packb({**batch, "items": item}), "control_batch", "invalid_type"),
        ("batch_empty", msgpack.packb({**batch, "items": []}), "control_batch", "invalid_value"),
        ("batch_too_many", msgpack.packb({**batch, "items": [item] * 65}), "control_batch", "too_large"),
        (
            "batch_bad_client",
            msgpack.packb({**batch, "client": "a/b", "items": [item]}),
            "control_batch",
            "invalid_value",
        ),
        ("bundle_bad_magic", b"DRPX" + one[4:], "bundle", "malformed"),
        ("bundle_major_2", one[:4] + b"\x02" + one[5:], "bundle", "unsupported_version"),
        ("bundle_truncated_header", one[:31], "bundle", "malformed"),
        ("bundle_truncated_state", one[:-9], "bundle", "malformed"),  # the state itself ends early
        ("bundle_count_too_big", one[:8] + (2).to_bytes(4, "little") + one[12:], "bundle", "malformed"),
        ("bundle_entry_header_short", one[:32] + (8).to_bytes(2, "little") + one[34:], "bundle", "malformed"),
        ("bundle_bad_id", one[:40] + b"/" + one[41:], "bundle", "malformed"),
    ]

    moves = {
        "cloths": [CLOTH, CLOTH2],
        "tokens": [TOKEN, TOKEN2],
        "indices": np.array([0, 3], "<u4").tobytes(),
        "targets": np.zeros(12, "<f4").tobytes(),
    }
    nan_targets = np.zeros(12, "<f4")
    nan_targets[7] = np.nan

    def with_moves(**changes: Any) -> bytes:  # 1.4: a batch control of a moves block (no items)
        return msgpack.packb({**batch, "v": [1, 4], "moves": {**moves, **changes}}, use_bin_type=True)

    bad_cases += [
        (
            "batch_moves_length_mismatch",
            with_moves(targets=np.zeros(9, "<f4").tobytes()),
            "control_batch",
            "invalid_value",
        ),
        ("batch_moves_nan_target", with_moves(targets=nan_targets.tobytes()), "control_batch", "invalid_value"),
        ("batch_moves_bad_token", with_moves(tokens=[TOKEN, "not-a-token"]), "control_batch", "invalid_value"),
        ("batch_moves_tokens_count", with_moves(tokens=[TOKEN]), "control_batch", "invalid_value"),
        ("batch_moves_bad_cloth", with_moves(cloths=[CLOTH, "a/b"]), "control_batch", "invalid_value"),
        (
            "batch_moves_repeated_index",
            with_moves(indices=np.array([3, 3], "<u4").tobytes()),
            "control_batch",
            "invalid_value",
        ),
        ("batch_moves_not_map", msgpack.packb({**batch, "v": [1, 4], "moves": [1]}), "control_batch", "invalid_type"),
        (
            "batch_moves_targets_not_bin",
            with_moves(targets=[0.0] * 12),
            "control_batch",
            "invalid_type",
        ),
    ]
    deep: Any = [0]
    for _ in range(999):
        deep = [deep]
    bad_cases += [
        (
            "features_add_and_remove",
            msgpack.packb(
                {"v": [1, 2], "cloth": CLOTH, "token": TOKEN, "features_add": ["wind"], "features_remove": ["wind"]}
            ),
            "control",
            "invalid_value",
        ),
        (
            "features_add_unknown",
            msgpack.packb({"v": [1, 2], "cloth": CLOTH, "token": TOKEN, "features_add": ["gravity"]}),
            "control",
            "invalid_value",
        ),
        (
            "mass_subnormal",
            msgpack.packb({"v": [1, 2], "client": "c1", "grid": {"cols": 2, "rows": 2}, "material": {"mass": 5e-324}}),
            "submit",
            "invalid_value",
        ),
        (
            "mass_below_minimum",
            msgpack.packb({"v": [1, 2], "client": "c1", "grid": {"cols": 2, "rows": 2}, "material": {"mass": 1e-10}}),
            "submit",
            "invalid_value",
        ),
        (
            "nested_1000_deep",
            msgpack.packb({"v": [1, 2], "client": "c1", "grid": {"cols": 2, "rows": 2}, "x": deep}),
            "submit",
            "malformed",
        ),
        (
            "map_too_many_keys",
            msgpack.packb(
                {
                    "v": [1, 2],
                    "client": "c1",
                    "grid": {"cols": 2, "rows": 2},
                    **{f"k{i}": 0 for i in range(P.MAX_MAP_KEYS)},
                }
            ),
            "submit",
            "malformed",
        ),
        (
            "array_too_long",
            msgpack.packb(
                {
                    "v": [1, 2],
                    "client": "c1",
                    "grid": {"cols": 2, "rows": 2},
                    "features": ["wind"] * (P.MAX_ARRAY_LENGTH + 1),
                }
            ),
            "submit",
            "malformed",
        ),
        (
            "ext_type",
            msgpack.packb({"v": [1, 2], "client": "c1", "x": msgpack.ExtType(1, b"z")}),
            "submit",
            "malformed",
        ),
    ]
    grid22 = {"v": [1, 4], "client": "c1", "grid": {"cols": 2, "rows": 2}}
    four = np.zeros((4, 3), "<f4")
    bad_cases += [
        (
            "resume_wrong_count",
            msgpack.packb({**grid22, "resume": {"positions": np.zeros((3, 3), "<f4").tobytes()}}, use_bin_type=True),
            "submit",
            "invalid_value",
        ),
        (
            "resume_velocities_wrong_count",
            msgpack.packb(
                {**grid22, "resume": {"positions": four.tobytes(), "velocities": np.zeros((5, 3), "<f4").tobytes()}},
                use_bin_type=True,
            ),
            "submit",
            "invalid_value",
        ),
        (
            "resume_nan",
            msgpack.packb(
                {
                    **grid22,
                    "resume": {
                        "positions": np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 1], [1, 0, 1]], "<f4").tobytes()
                    },
                },
                use_bin_type=True,
            ),
            "submit",
            "invalid_value",
        ),
        (
            "resume_out_of_bounds",
            msgpack.packb(
                {
                    **grid22,
                    "resume": {"positions": np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [2e5, 0, 1]], "<f4").tobytes()},
                },
                use_bin_type=True,
            ),
            "submit",
            "invalid_value",
        ),
        (
            "resume_velocity_too_fast",
            msgpack.packb(
                {
                    **grid22,
                    "resume": {"positions": four.tobytes(), "velocities": np.full((4, 3), 2e4, "<f4").tobytes()},
                },
                use_bin_type=True,
            ),
            "submit",
            "invalid_value",
        ),
        ("resume_no_positions", msgpack.packb({**grid22, "resume": {"tick": 5}}), "submit", "missing_field"),
        (
            "resume_positions_not_bin",
            msgpack.packb({**grid22, "resume": {"positions": [0.0] * 12}}),
            "submit",
            "invalid_type",
        ),
    ]
    invalid = [{"name": n, "message": m, "hex": d.hex(), "error": code} for n, d, m, code in bad_cases]
    # A batch whose envelope is valid: each item stands alone, only the bad ones are refused.
    partial = msgpack.packb(
        {
            **batch,
            "items": [
                item,
                {
                    **item,
                    "pins": {"indices": np.array([0, 1], "<u4").tobytes(), "targets": np.zeros(3, "<f4").tobytes()},
                },
                [1, 2],
                {**item, "token": "not-a-token"},
                {**item, "state": {"bundle": True}},
                {**item, "gravity": [0.0, -9.81, 0.0]},
            ],
        },
        use_bin_type=True,
    )
    invalid.append(
        {
            "name": "batch_partly_invalid",
            "message": "control_batch",
            "description": INVALID_NOTE,
            "hex": partial.hex(),
            "error": None,
            "item_errors": [None, "invalid_value", "invalid_type", "invalid_value", "invalid_value", None],
        }
    )
    # Unknown minor version and unknown keys are accepted within major 1 (a minor after this one):
    fut = P.PROTOCOL_MINOR + 1
    future = {
        "name": "submit_future_minor",
        "message": "submit",
        "description": f"Version 1.{fut} with a key this version does not know: accepted, the key ignored.",
        "hex": msgpack.packb(
            {"v": [1, fut], "rid": 0, "client": "c1", "grid": {"cols": 2, "rows": 2}, "hologram": True}
        ).hex(),
        "value": {"v": [1, fut], "rid": 0, "client": "c1", "grid": {"cols": 2, "rows": 2}, "hologram": True},
        "ignored": ["hologram"],
    }
    # A bundle of a future minor version: a longer header, an unknown flag, bytes after the last entry.
    later = bytearray(one[:32] + b"\xee" * 8 + one[32:] + b"trailing")
    later[5] = fut
    later[6:8] = (40).to_bytes(2, "little")
    later[12:16] = (1 << 31).to_bytes(4, "little")
    future_bundle = {
        "name": "bundle_future_minor",
        "message": "bundle",
        "description": f"Version 1.{fut} bundle with a "
        "40-byte header, an unknown flag and trailing bytes: read as the bundle it contains.",
        "hex": bytes(later).hex(),
        "value": {
            **bundles[1]["value"],
            "minor": fut,
            "header_size": 40,
            "flags": 1 << 31,
            "size": len(later),
            "entries": [
                {**e, "entry_offset": e["entry_offset"] + 8, "state_offset": e["state_offset"] + 8}
                for e in bundles[1]["value"]["entries"]
            ],
        },
    }
    return {
        "submit": submit,
        "control": control,
        "misc": other,
        "state": state,
        "bundle": bundles,
        "invalid": invalid,
        "accepted": [future, future_bundle],
        "predictive": predictive_vectors(),
        "rates": rates_vectors(),
        "meshes": mesh_vectors(),
    }


def dumps(items: list[dict[str, Any]]) -> str:
    """JSON with one line per scalar field and arrays of numbers kept on one line."""
    text = json.dumps(items, indent=1)
    return re.sub(
        r"\[[-+0-9.e,\s]*\]", lambda m: re.sub(r"\s+", " ", m.group(0)).replace("[ ", "[").replace(" ]", "]"), text
    )


def main() -> None:
    for group, items in vectors().items():
        path = HERE / f"{group}.json"
        path.write_text(dumps(items) + "\n")
        print(f"wrote {len(items)} vectors to {path}")


if __name__ == "__main__":
    main()
