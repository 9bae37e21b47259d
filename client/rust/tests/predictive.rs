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
