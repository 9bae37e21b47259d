//! The predictive state encoding (protocol 1.5) against the repository's vectors
//! (`tests/vectors/predictive.json`): a stream decoded in order gives each state's positions,
//! normals and header fields exactly; a state whose reference the stream lacks is not decoded
//! (counted), and the next keyframe resyncs it.
use drape::wire::{is_predictive, parse_predictive, PredictiveStream};
use serde_json::Value as Json;
use std::path::PathBuf;

fn vectors() -> Vec<Json> {
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/vectors/predictive.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str::<Json>(&text)
        .unwrap()
        .as_array()
        .unwrap()
        .iter()
        .filter(|v| v["message"] == "state")
        .cloned()
        .collect()
}

fn unhex(v: &Json) -> Vec<u8> {
    let s = v["hex"].as_str().unwrap();
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
        .collect()
}

fn floats(v: &Json) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .flat_map(|row| {
            row.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as f32)
        })
        .collect()
}

#[test]
fn a_stream_decodes_the_vectors_in_order() {
    let vs = vectors();
    assert_eq!(vs.len(), 5);
    let mut stream = PredictiveStream::new();
    for v in &vs {
        let data = unhex(v);
        let want = &v["value"];
        assert!(is_predictive(&data));
        let n = want["vertex_count"].as_u64().unwrap() as usize;
        let (mut pos, mut nrm) = (vec![0f32; 3 * n], vec![0f32; 3 * n]);
        let h = stream
            .decode(&data, &mut pos, Some(&mut nrm))
            .unwrap()
            .expect("decodable in order");
        assert_eq!(pos, floats(&want["positions"]), "{}", v["name"]);
        if !want["normals"].is_null() {
            assert_eq!(nrm, floats(&want["normals"]), "{}", v["name"]);
        }
        assert_eq!(
            (
                h.order as u64,
                h.ref_tick,
                h.ref2_tick,
                h.data_size as u64,
                h.tick
            ),
            (
                want["order"].as_u64().unwrap(),
                want["ref_tick"].as_u64().unwrap(),
                want["ref2_tick"].as_u64().unwrap(),
                want["data_size"].as_u64().unwrap(),
                want["tick"].as_u64().unwrap()
            ),
            "{}",
            v["name"]
        );
    }
    assert_eq!(
        (stream.decoded, stream.keyframes, stream.undecodable),
        (5, 2, 0)
    );
}

#[test]
fn a_late_joiner_waits_for_a_keyframe() {
    let vs = vectors();
    let mut stream = PredictiveStream::new();
    let mut pos = vec![0f32; 9];
    for v in &vs[1..4] {
        // predicted from states this stream never received
        assert!(stream.decode(&unhex(v), &mut pos, None).unwrap().is_none());
    }
    assert_eq!(stream.undecodable, 3);
    let h = stream
        .decode(&unhex(&vs[4]), &mut pos, None)
        .unwrap()
        .unwrap();
    assert_eq!(h.order, 0);
    assert_eq!(pos, floats(&vs[4]["value"]["positions"]));
}

#[test]
fn malformed_predictive_states_are_refused() {
    let data = unhex(&vectors()[2]);
    assert!(parse_predictive(&data[..95]).is_err());
    let mut short = data.clone();
    short.truncate(data.len() - 1);
    assert!(parse_predictive(&short).is_err());
    let mut bad = data.clone();
    bad[68] = 7; // order
    assert!(parse_predictive(&bad).is_err());
    let mut stream = PredictiveStream::new();
    let mut wide = unhex(&vectors()[0]);
    wide[96] = 33; // a width over 32
    assert!(stream.decode(&wide, &mut [0f32; 9], None).is_err());
    // a vertex count its data cannot hold: refused before anything is allocated
    let mut huge = unhex(&vectors()[0]);
    huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(parse_predictive(&huge).is_err());
    assert!(stream.decode_to_float32(&huge).is_err());
}

/// Encodes 40 states of 1001 vertices (partial last block) with the Python reference
/// (`encode_predictive_state`), blocks moving at scales from none (width 0) to the grid's ends
/// (widths up to 31), keyframes at 0 and 20, normals in some states, and decodes them with the
/// reference `StateStream`; then this crate's `decode` and `decode_to_float32` must give the same
/// float32 bits. Needs the repository's venv (`DRAPE_PYTHON`, default `../../.venv/bin/python`):
/// skipped without it outside CI.
const REFERENCE_STREAM: &str = r#"
import struct, sys
import numpy as np
from drape.client.protocol.state import encode_predictive_state
from drape.client.protocol.predictive import History
from drape.client.protocol.stream import StateStream

rng = np.random.default_rng(7)
n, step = 1001, 0.001  # a partial block, and a vertex past the last group of 4
# blocks of 32 vertices moving at scales from 0 (widths 0) to a km per tick (widths near 32)
scale = np.repeat(10.0 ** rng.uniform(-5, 3, size=n // 32 + 1), 32)[:n, None]
scale[64:96] = 0.0
pos = rng.normal(size=(n, 3)) * scale
hist, dec, out = History(), StateStream("c"), bytearray()
widths = set()
for t in range(40):
    pos = pos + rng.normal(size=(n, 3)) * scale * (0.05 if t % 7 else 1.0)
    pos[128:160] = rng.choice([-1.3e5, 1.3e5], size=(32, 3))  # the grid's ends: widths up to 32
    pos = np.clip(pos, -1.3e5, 1.3e5).astype(np.float32)
    nrm = rng.uniform(-1, 1, size=(n, 3)).astype(np.float32) if t % 5 == 3 else None
    st = encode_predictive_state(100 + t, 1000 + t, pos, step, hist, keyframe=t in (0, 20), normals=nrm)
    got = dec.decode(bytes(st))
    ref = got.positions.astype("<f4").tobytes() + (got.normals.astype("<f4").tobytes() if got.normals is not None else b"")
    out += struct.pack("<II", len(st), len(ref)) + st + ref
    widths.update(st[96 : 96 + 3 * ((n + 31) // 32)])
sys.stdout.buffer.write(out)
assert max(widths) >= 31 and min(widths) == 0, sorted(widths)
"#;

#[test]
fn a_long_stream_of_every_width_decodes_as_the_reference() {
    let python = std::env::var_os("DRAPE_PYTHON").map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../.venv/bin/python"));
    if !python.exists() {
        let ci = std::env::var("CI").map(|v| v.eq_ignore_ascii_case("true") || v == "1").unwrap_or(false);
        assert!(!ci, "{} is missing", python.display());
        eprintln!("SKIPPED: {} is missing", python.display());
        return;
    }
    let run = std::process::Command::new(&python).arg("-c").arg(REFERENCE_STREAM).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let data = run.stdout;
    let (mut a, mut b) = (PredictiveStream::new(), PredictiveStream::new());
    let (mut at, mut states) = (0, 0);
    while at < data.len() {
        let le = |i: usize| u32::from_le_bytes(data[i..i + 4].try_into().unwrap()) as usize;
        let (ns, nr) = (le(at), le(at + 4));
        let (st, want) = (&data[at + 8..at + 8 + ns], &data[at + 8 + ns..at + 8 + ns + nr]);
        at += 8 + ns + nr;
        let h = parse_predictive(st).unwrap();
        let k = 3 * h.vertex_count as usize;
        let (mut pos, mut nrm) = (vec![0f32; k], vec![0f32; k]);
        a.decode(st, &mut pos, Some(&mut nrm)).unwrap().expect("in order");
        let mut got: Vec<u8> = pos.iter().flat_map(|x| x.to_le_bytes()).collect();
        if h.has_normals() {
            got.extend(nrm.iter().flat_map(|x| x.to_le_bytes()));
        }
        assert!(got == want, "state {states}: decode differs from the reference");
        let (kept, _) = b.decode_to_float32(st).unwrap().expect("in order");
        assert!(kept[64..] == *want, "state {states}: decode_to_float32 differs from the reference");
        states += 1;
    }
    assert_eq!(states, 40);
}
