//! The protocol test vectors of the repository (`../../tests/vectors/*.json`, PROTOCOL.md
//! section 16) checked both ways: bytes -> meaning, and meaning -> identical bytes (1.4's
//! `moves` blocks and batch replies included). The frozen 1.0 to 1.3 vectors (`v1.0/` ...
//! `v1.3/`) must still be read as they mean, and written back they differ only in the version.
//! Of the later versions' files: 1.5's `predictive.json`, 1.7's scene requests of `misc.json` and
//! 1.8's `meshes.json`, each written back but for the version this crate writes.
use drape::wire::msg::{encode_info, encode_remove};
use drape::wire::reader::{pack, unpack_message, Reader, Value};
use drape::wire::replies::{decode_reply, encode_tick_reply, tick_of};
use drape::wire::*;
use serde_json::{json, Value as Json};
use std::path::PathBuf;

fn dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/vectors")
}

fn load(name: &str) -> Vec<Json> {
    let path = dir().join(name);
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    serde_json::from_str::<Json>(&text).unwrap().as_array().unwrap().clone()
}

fn unhex(v: &Json) -> Vec<u8> {
    let s = v["hex"].as_str().unwrap();
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect()
}

/// A decoded msgpack value as the vectors write it: bin fields as {"u32": [...]} / {"f32": [...]}.
fn to_json(v: &Value, key: &str) -> Json {
    match v {
        Value::Nil => Json::Null,
        Value::Boolean(b) => json!(b),
        Value::Integer(i) => i.as_u64().map(|u| json!(u)).unwrap_or_else(|| json!(i.as_i64().unwrap())),
        Value::F32(x) => json!(*x as f64),
        Value::F64(x) => json!(x),
        Value::String(s) => json!(s.as_str().unwrap()),
        Value::Binary(b) => {
            let four = b.chunks_exact(4).map(|c| c.try_into().unwrap());
            match key {
                "vertices" | "targets" | "positions" | "velocities" => json!({"f32": four.map(|c: [u8; 4]| f32::from_le_bytes(c) as f64).collect::<Vec<_>>()}),
                _ => json!({"u32": four.map(u32::from_le_bytes).collect::<Vec<_>>()}),
            }
        }
        Value::Array(a) => Json::Array(a.iter().map(|x| to_json(x, key)).collect()),
        Value::Map(m) => Json::Object(m.iter().map(|(k, x)| (k.as_str().unwrap().to_string(), to_json(x, k.as_str().unwrap()))).collect()),
        Value::Ext(..) => panic!("no ext values in the protocol"),
    }
}

/// Every vector set: its directory, the version its messages carry. This crate speaks 1.4 (the
/// frozen `v1.4/` set; of the top-level set it checks 1.5's predictive vectors, in
/// `predictive_vectors`); the 1.0 to 1.3 sets are frozen and must be read as they mean
/// (PROTOCOL.md section 15).
const SETS: [(&str, u64); 5] =
    [("v1.4/", PROTOCOL_MINOR as u64), ("v1.3/", 3), ("v1.2/", 2), ("v1.1/", 1), ("v1.0/", 0)];

fn load_set(dir_prefix: &str, name: &str) -> Vec<Json> {
    if dir().join(dir_prefix).join(name).exists() { load(&format!("{dir_prefix}{name}")) } else { Vec::new() }
}

/// `v` printed and parsed again: serde_json's parser (without its `float_roundtrip` feature) may
/// miss a float by an ulp (0.9238795325112867 reads as ...68), so the decoded value meets the
/// vector's text through the same parser.
fn reparsed(v: Json) -> Json {
    serde_json::from_str(&v.to_string()).unwrap()
}

fn check_message(v: &Json) {
    let name = v["name"].as_str().unwrap();
    let data = unhex(v);
    let m = unpack_message(&data).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(reparsed(to_json(&Value::Map(m.clone()), "")), v["value"], "{name}: decoded value");
    let rid = Reader::new(&m, "").u64("rid", false).unwrap().unwrap_or(0);
    let again = match v["message"].as_str().unwrap() {
        "submit" => {
            let s = Submit::decode(&data).unwrap();
            s.validate(&Limits::default()).unwrap();
            s.encode()
        }
        "control" => {
            let (c, rid) = Control::decode(&data).unwrap();
            c.validate(&Limits::default(), None).unwrap();
            c.encode(rid)
        }
        "control_batch" => {
            let d = DecodedBatch::decode(&data, &Limits::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(d.moves.is_some(), !v["value"]["moves"].is_null(), "{name}: moves");
            let items: Vec<Control> = d.items.into_iter().map(|r| r.unwrap_or_else(|e| panic!("{name}: {e}"))).collect();
            let batch = ControlBatch { rid, client: d.client, items };
            if d.moves.is_none() {
                assert_eq!(batch.encode(), data, "{name}: re-encoded without moves");
            }
            batch.encode_with_moves(d.moves.as_ref())
        }
        "remove" => {
            let r = Reader::new(&m, "");
            encode_remove(r.str("cloth", true).unwrap().unwrap(), r.str("token", true).unwrap().unwrap(), rid)
        }
        "info" => encode_info(rid),
        "scene" => {
            let s = SceneRequest::decode(&data).unwrap_or_else(|e| panic!("{name}: {e}"));
            s.validate().unwrap_or_else(|e| panic!("{name}: {e}"));
            s.encode()
        }
        "reply_scene" => SceneReply::from_map(&decode_reply(&data).unwrap()).unwrap().encode(),
        "reply_submit" => SubmitReply::from_map(&decode_reply(&data).unwrap()).unwrap().encode(),
        "reply_control" => {
            let a = Applied::from_map(&decode_reply(&data).unwrap()).unwrap();
            assert_eq!(a.features.is_some(), !v["value"]["features"].is_null(), "{name}: features");
            a.encode_reply(rid)
        }
        "reply_remove" => encode_tick_reply(tick_of(&decode_reply(&data).unwrap()).unwrap(), rid),
        "reply_control_batch" => {
            let rep = BatchReply::from_map(&decode_reply(&data).unwrap()).unwrap();
            for (r, w) in rep.results.iter().zip(v["value"]["results"].as_array().unwrap()) {
                match r {
                    Ok(a) => assert_eq!(json!(a.features), w["features"], "{name}: item features"),
                    Err(e) => assert_eq!(json!(e.code), w["error"]["code"], "{name}: item error"),
                }
            }
            let moves = MovesReply::from_map(&decode_reply(&data).unwrap()).unwrap();
            assert_eq!(moves.is_some(), !v["value"]["moves_tick"].is_null(), "{name}: moves_tick");
            if let Some(mv) = &moves {
                let failed: Vec<Json> = mv.moves_failed.iter().map(|f| json!([f.position, f.code, f.message])).collect();
                assert_eq!(Json::Array(failed), v["value"]["moves_failed"], "{name}: moves_failed");
                assert_eq!(json!(mv.moves_tick), v["value"]["moves_tick"], "{name}");
            }
            rep.encode_with_moves(moves.as_ref())
        }
        // Informational maps a client reads generically (fields may be added in any minor):
        // decoded within the caps and written back as decoded.
        "reply_info" => {
            let m = decode_reply(&data).unwrap();
            let version = Reader::new(&m, "").str("version", true).unwrap().unwrap().to_string();
            assert_eq!(json!(version), v["value"]["version"], "{name}");
            pack(&Value::Map(m))
        }
        "stats" => pack(&Value::Map(m.clone())),
        "error" => {
            let e = decode_reply(&data).unwrap_err();
            assert_eq!(e.code.as_str(), v["value"]["error"]["code"], "{name}");
            assert_ne!(e.code, ErrorCode::Unknown, "{name}: every code of this version is known");
            assert_eq!(e.rid, rid);
            ErrorReply::from_map(&m).unwrap().encode()
        }
        other => panic!("{name}: unknown message kind {other}"),
    };
    assert_eq!(again, data, "{name}: re-encoded bytes differ");
}

/// An earlier version's message with its version replaced by this one's: the `v` array
/// `[1, minor]` (0x92 0x01 minor) is the first thing of every message map.
fn as_current(v: &Json, minor: u64) -> Json {
    let data = unhex(v);
    let at = data.windows(3).position(|w| w == [0x92, 1, minor as u8]).expect("the version array");
    let mut bytes = data.clone();
    bytes[at + 2] = PROTOCOL_MINOR;
    let mut out = v.clone();
    out["hex"] = json!(bytes.iter().map(|b| format!("{b:02x}")).collect::<String>());
    out["value"]["v"] = json!([1, PROTOCOL_MINOR]);
    out
}

#[test]
fn messages_both_ways() {
    let mut seen = 0;
    for (set, minor) in SETS {
        for file in ["submit.json", "control.json", "misc.json"] {
            let vectors = load_set(set, file);
            assert!(!vectors.is_empty(), "{set}{file} is missing");
            for v in vectors {
                let name = format!("{set}{file} {}", v["name"].as_str().unwrap());
                assert_eq!(v["value"]["v"], json!([1, minor]), "{name}");
                if minor == PROTOCOL_MINOR as u64 {
                    check_message(&v);
                } else {
                    // Read as it means: the same value but for the version ...
                    let data = unhex(&v);
                    let m = unpack_message(&data).unwrap_or_else(|e| panic!("{name}: {e}"));
                    assert_eq!(to_json(&Value::Map(m), ""), v["value"], "{name}: decoded value");
                    // ... and written back differing only in the version.
                    check_message(&as_current(&v, minor));
                }
                seen += 1;
            }
        }
    }
    assert!(seen >= 80, "only {seen} message vectors");
}

/// The 1.2 messages: what a control carries and what its replies report.
#[test]
fn features_add_remove_and_overloaded() {
    let v = load("control.json").into_iter().find(|v| v["name"] == "control_features_add_remove").unwrap();
    let (c, _) = Control::decode(&unhex(&v)).unwrap();
    assert_eq!(c.features_add.as_deref(), Some(&["wind".to_string()][..]));
    assert_eq!(c.features_remove.as_deref(), Some(&["tethers".to_string()][..]));
    assert!(c.features.is_none() && c.needs_1_2());
    let misc = load("misc.json");
    let by = |n: &str| unhex(misc.iter().find(|v| v["name"] == n).unwrap());
    let a = Applied::from_map(&decode_reply(&by("reply_control_features")).unwrap()).unwrap();
    assert_eq!((a.tick, a.has("wind"), a.has("xpbd")), (1050, Some(true), Some(false)));
    let old = Applied::from_map(&decode_reply(&by("reply_control")).unwrap()).unwrap();
    assert_eq!((old.features.clone(), old.has("wind")), (None, None), "a reply without features: not reported");
    let e = decode_reply(&by("reply_error_overloaded")).unwrap_err();
    assert_eq!((e.code, e.code as i32, e.code.is_retryable(), e.code.is_bad_request()), (ErrorCode::Overloaded, 17, true, false));
    assert_eq!(ErrorCode::from_name("overloaded"), ErrorCode::Overloaded);
    assert_eq!(ErrorCode::from_name("from_a_later_version"), ErrorCode::Unknown);
}

/// The 1.3 `resume` of a submission: decoded field by field, validated against the cloth.
#[test]
fn resume_in_submit() {
    let subs = load("submit.json");
    let by = |n: &str| unhex(subs.iter().find(|v| v["name"] == n).unwrap_or_else(|| panic!("no vector {n}")));
    let s = Submit::decode(&by("submit_resume")).unwrap();
    let r = s.resume.as_ref().expect("resume");
    assert_eq!(r.positions, vec![0.0, 1.0, 0.0, 1.0, 0.75, 0.25, 0.0, 0.5, 1.0, 1.0, 0.25, 1.0]);
    assert_eq!(r.velocities.as_ref().unwrap()[3..6], [0.5, -1.0, 0.0]);
    assert_eq!((r.tick, r.from_server.as_deref(), r.cloth.as_deref()), (Some(1042), Some("s1"), Some("5ba88a14c526242f")));
    let least = Submit::decode(&by("submit_resume_positions")).unwrap();
    let r = least.resume.as_ref().unwrap();
    assert_eq!((r.positions.len(), r.velocities.is_none(), r.tick, r.from_server.is_none()), (6, true, None, true));
    // validated against the cloth's vertex count and bounds
    let lim = Limits::default();
    let mut bad = s.clone();
    bad.resume.as_mut().unwrap().positions.truncate(9);
    assert_eq!(bad.validate(&lim).unwrap_err().code, ErrorCode::InvalidValue);
    let mut bad = s.clone();
    bad.resume.as_mut().unwrap().velocities.as_mut().unwrap()[4] = 2e4;
    assert_eq!(bad.validate(&lim).unwrap_err().code, ErrorCode::InvalidValue);
    let mut bad = s.clone();
    bad.resume.as_mut().unwrap().positions[0] = f32::NAN;
    assert_eq!(bad.validate(&lim).unwrap_err().code, ErrorCode::InvalidValue);
    // an earlier version's submission has none
    assert!(load_set("v1.2/", "submit.json").iter().all(|v| Submit::decode(&unhex(v)).unwrap().resume.is_none()));
}

/// The 1.4 `moves` block of a batch control and the reply's `moves_tick` / `moves_failed`,
/// decoded field by field; the block validated as the server does.
#[test]
fn moves_block_and_reply() {
    let ctl = load("control.json");
    let by = |n: &str| unhex(ctl.iter().find(|v| v["name"] == n).unwrap_or_else(|| panic!("no vector {n}")));
    let lim = Limits::default();
    let d = DecodedBatch::decode(&by("control_batch_moves"), &lim).unwrap();
    let mv = d.moves.clone().unwrap();
    assert_eq!((d.client.as_str(), d.items.len(), d.rid), ("game-7", 0, 13));
    assert_eq!(mv.cloths, ["5ba88a14c526242f", "0f1e2d3c4b5a6978"]);
    assert_eq!((mv.indices.as_slice(), &mv.targets[9..12]), (&[0u32, 3][..], &[1.0f32, 1.5, 0.25][..]));
    let both = DecodedBatch::decode(&by("control_batch_moves_items"), &lim).unwrap();
    assert_eq!((both.items.len(), both.moves.as_ref().unwrap().indices.as_slice()), (1, &[0u32][..]));
    // what the client checks before sending: the server's verdicts on the bytes alone
    mv.validate(&lim).unwrap();
    let code = |m: &Moves| m.validate(&lim).unwrap_err().code;
    assert_eq!(code(&Moves { indices: vec![3, 3], ..mv.clone() }), ErrorCode::InvalidValue);
    assert_eq!(code(&Moves { targets: mv.targets[..9].to_vec(), ..mv.clone() }), ErrorCode::InvalidValue);
    assert_eq!(code(&Moves { tokens: mv.tokens[..1].to_vec(), ..mv.clone() }), ErrorCode::InvalidValue);
    assert_eq!(code(&Moves { indices: vec![], targets: vec![], ..mv.clone() }), ErrorCode::InvalidValue);
    let mut far = mv.clone();
    far.targets[4] = 1e6;
    assert_eq!(code(&far), ErrorCode::InvalidValue);
    let many = Moves { cloths: vec!["c".into(); MAX_BATCH_MOVES + 1], tokens: vec![mv.tokens[0].clone(); MAX_BATCH_MOVES + 1],
                       indices: vec![0], targets: vec![0.0; 3 * (MAX_BATCH_MOVES + 1)] };
    assert_eq!(code(&many), ErrorCode::TooLarge);
    // a batch control without moves still needs items
    let none = ControlBatch { rid: 1, client: "c1".into(), items: vec![] };
    assert_eq!(DecodedBatch::decode(&none.encode(), &lim).unwrap_err().code, ErrorCode::InvalidValue);
    assert_eq!(DecodedBatch::decode(&none.encode_with_moves(Some(&mv)), &lim).unwrap().moves, Some(mv));
    // the reply
    let misc = load("misc.json");
    let rep = unhex(misc.iter().find(|v| v["name"] == "reply_control_batch_moves").unwrap());
    let m = decode_reply(&rep).unwrap();
    let r = MovesReply::from_map(&m).unwrap().unwrap();
    assert_eq!((r.moves_tick, r.moves_failed.len(), r.moves_failed[0].position), (1050, 1, 1));
    assert_eq!(r.moves_failed[0].to_error(13).code, ErrorCode::Forbidden);
    let plain = unhex(misc.iter().find(|v| v["name"] == "reply_control_batch").unwrap());
    assert_eq!(MovesReply::from_map(&decode_reply(&plain).unwrap()).unwrap(), None, "no moves: no moves fields");
}

fn f32s(v: &Json) -> Vec<f32> {
    v.as_array().unwrap().iter().flat_map(|p| p.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32)).collect()
}

fn check_state(name: &str, data: &[u8], want: &Json) {
    let mut pos = vec![0f32; 3 * want["vertex_count"].as_u64().unwrap() as usize];
    let mut nrm = pos.clone();
    let h = decode_state_into(data, &mut pos, Some(&mut nrm)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let got = json!({
        "magic": "DRPS", "major": h.major, "minor": h.minor, "header_size": h.header_size,
        "encoding": h.encoding.name(), "flags": h.flags, "vertex_count": h.vertex_count, "tick": h.tick,
        "server_time_ns": h.server_time_ns,
        "bounds_min": h.bounds_min.map(|x| x as f64), "bounds_max": h.bounds_max.map(|x| x as f64),
    });
    for k in got.as_object().unwrap().keys() {
        let w = if k == "major" { json!(want[k].as_u64().unwrap()) } else { want[k].clone() };
        assert_eq!(got[k], w, "{name}: {k}");
    }
    assert_eq!(pos, f32s(&want["positions"]), "{name}: positions");
    if h.has_normals() {
        assert_eq!(nrm, f32s(&want["normals"]), "{name}: normals");
    } else {
        assert!(want["normals"].is_null(), "{name}");
    }
}

#[test]
fn states_both_ways() {
    let mut seen = 0;
    for (set, minor) in SETS {
        for v in load_set(set, "state.json") {
            let name = format!("{set}state.json {}", v["name"].as_str().unwrap());
            let data = unhex(&v);
            let want = &v["value"];
            assert_eq!((data[5] as u64, want["minor"].as_u64().unwrap()), (minor, minor), "{name}");
            check_state(&name, &data, want);
            let input = &v["input"];
            let normals = if input["normals"].is_null() { None } else { Some(f32s(&input["normals"])) };
            let enc = Encoding::from_name(want["encoding"].as_str().unwrap()).unwrap();
            let mut again = encode_state(want["tick"].as_u64().unwrap(), want["server_time_ns"].as_u64().unwrap(),
                &f32s(&input["positions"]), normals.as_deref(), enc, input["flags"].as_u64().unwrap() as u16).unwrap();
            assert_eq!(again[5], PROTOCOL_MINOR);
            again[5] = data[5]; // an earlier version's vector differs only in the minor version byte
            assert_eq!(again, data, "{name}: re-encoded bytes differ");
            seen += 1;
        }
    }
    assert!(seen >= 12, "only {seen} state vectors");
}

#[test]
fn bundles_both_ways() {
    let mut seen = 0;
    for (set, minor) in SETS {
        for v in load_set(set, "bundle.json") {
            let name = format!("{set}bundle.json {}", v["name"].as_str().unwrap());
            let data = unhex(&v);
            let want = &v["value"];
            let b = parse_bundle(&data).unwrap();
            assert_eq!((b.major as u64, b.minor as u64, b.header_size as u64), (1, minor, 32), "{name}");
            assert_eq!(json!([b.entries.len(), b.flags, b.tick, b.server_time_ns, data.len()]),
                       json!([want["count"], want["flags"], want["tick"], want["server_time_ns"], want["size"]]), "{name}");
            let mut states: Vec<(String, Vec<u8>)> = Vec::new();
            for (i, (e, w)) in b.entries.iter().zip(want["entries"].as_array().unwrap()).enumerate() {
                assert_eq!(json!([e.cloth, e.entry_offset, e.state_offset - e.entry_offset, e.state_offset, e.state_size]),
                           json!([w["cloth"], w["entry_offset"], w["entry_header_size"], w["state_offset"], w["state_size"]]), "{name}");
                check_state(&format!("{name} entry {i}"), b.payload(i), &w["state"]);
                let input = &v["input"]["states"][i];
                assert_eq!(input["cloth"], json!(e.cloth));
                states.push((e.cloth.to_string(), unhex(input)));
            }
            let refs: Vec<(&str, &[u8])> = states.iter().map(|(c, s)| (c.as_str(), s.as_slice())).collect();
            let mut again = encode_bundle(b.tick, b.server_time_ns, &refs, 0).unwrap();
            assert_eq!(again[5], PROTOCOL_MINOR);
            again[5] = data[5]; // the states inside are carried as given
            assert_eq!(again, data, "{name}: re-encoded");
            seen += 1;
        }
    }
    assert!(seen >= 4, "only {seen} bundle vectors");
}

#[test]
fn invalid_payloads_are_rejected_with_their_code() {
    let lim = Limits::default();
    for v in load("invalid.json") {
        let name = v["name"].as_str().unwrap();
        let data = unhex(&v);
        let got: Result<()> = match v["message"].as_str().unwrap() {
            "bundle" => parse_bundle(&data).and_then(|b| (0..b.entries.len()).try_for_each(|i| parse_state(b.payload(i)).map(|_| ()))),
            "submit" => Submit::decode(&data).and_then(|s| s.validate(&lim)),
            "control" => Control::decode(&data).and_then(|(c, _)| c.validate(&lim, None)),
            "remove" => unpack_message(&data).and_then(|m| {
                let r = Reader::new(&m, "");
                validate::validate_owner(r.str("cloth", true)?.unwrap(), r.str("token", true)?.unwrap())
            }),
            "control_batch" => match DecodedBatch::decode(&data, &lim) {
                Err(e) => Err(e),
                Ok(DecodedBatch { items, .. }) => {
                    let codes: Vec<Json> = items.iter().map(|r| r.as_ref().err().map_or(Json::Null, |e| json!(e.code.as_str()))).collect();
                    assert_eq!(Json::Array(codes), v["item_errors"], "{name}: item errors");
                    Ok(())
                }
            },
            other => panic!("{name}: unknown message {other}"),
        };
        match (&got, v["error"].as_str()) {
            (Err(e), Some(code)) => assert_eq!(e.code.as_str(), code, "{name}: {e}"),
            (Ok(()), None) => {}
            _ => panic!("{name}: expected {:?}, got {got:?}", v["error"]),
        }
    }
}

#[test]
fn future_minor_versions_are_accepted() {
    let acc = load("accepted.json");
    let m = unpack_message(&unhex(&acc[0])).unwrap();
    assert!(Reader::new(&m, "").get("hologram").is_some());
    Submit::decode(&unhex(&acc[0])).unwrap().validate(&Limits::default()).unwrap();
    let later = unhex(&acc[1]);
    let b = parse_bundle(&later).unwrap();
    let one = unhex(&load("bundle.json")[1]); // generated with the future vector: same state bytes
    let b1 = parse_bundle(&one).unwrap();
    // the generator's "future" minor: the Python package's current one (1.9) plus one
    assert_eq!((b.minor, b.flags, b.entries.len()), (10, 1 << 31, 1));
    assert_eq!(b.payload(0), b1.payload(0));
    assert_eq!((b.tick, b.server_time_ns, b.entries[0].cloth), (b1.tick, b1.server_time_ns, "c"));
}

#[test]
fn grid_geometry_matches_the_protocol() {
    let (v, t) = grid_geometry(3, 2, 1.0, 0.5, Orientation::Vertical, [0.0, 2.0, 0.0]).unwrap();
    assert_eq!(v, vec![0.0, 2.0, 0.0, 0.5, 2.0, 0.0, 1.0, 2.0, 0.0, 0.0, 1.5, 0.0, 0.5, 1.5, 0.0, 1.0, 1.5, 0.0]);
    assert_eq!(t, vec![0, 3, 1, 1, 4, 2, 1, 3, 4, 2, 4, 5]);
    let (v, t) = grid_geometry(1, 1, 1.0, 1.0, Orientation::Horizontal, [0.0; 3]).unwrap();
    assert_eq!((v.len(), t.len()), (3, 0));
}

/// 1.5's predictive vectors (`predictive.json`): the submit asking for the encoding read and
/// written back (but for the version this crate writes), each state's header read by
/// `parse_state` (its packed positions refused by `decode_state_into`: they decode only in
/// order) and the stream decoded in order by `PredictiveStream` to the vectors' positions.
#[test]
fn predictive_vectors() {
    let vs = load("predictive.json");
    let sub = vs.iter().find(|v| v["name"] == "submit_predictive").expect("submit_predictive");
    let minor = sub["value"]["v"][1].as_u64().unwrap();
    check_message(&as_current(sub, minor));
    let s = Submit::decode(&unhex(sub)).unwrap();
    let st = s.state.unwrap();
    assert_eq!((st.encoding, st.step), (Some(Encoding::Predictive), Some(0.002)));
    assert!(st.needs_1_5());
    let (mut stream, mut as_f32) = (PredictiveStream::new(), PredictiveStream::new());
    let mut seen = 0;
    for v in vs.iter().filter(|v| v["message"] == "state") {
        let name = v["name"].as_str().unwrap();
        let (data, want) = (unhex(v), &v["value"]);
        let h = parse_state(&data).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(h.encoding, Encoding::Predictive, "{name}");
        assert_eq!(json!([h.header_size, h.flags, h.vertex_count, h.tick, h.server_time_ns]),
                   json!([want["header_size"], want["flags"], want["vertex_count"], want["tick"], want["server_time_ns"]]), "{name}");
        let mut pos = vec![0f32; 3 * h.vertex_count as usize];
        let mut nrm = pos.clone();
        assert_eq!(decode_state_into(&data, &mut pos, None).unwrap_err().code, ErrorCode::InvalidValue, "{name}");
        let p = stream.decode(&data, &mut pos, Some(&mut nrm)).unwrap().expect("in order");
        // what the client keeps: the same state as a float32 payload, read like any other
        let (f32_state, _) = as_f32.decode_to_float32(&data).unwrap().expect("in order");
        let (mut pos2, mut nrm2) = (pos.clone(), nrm.clone());
        let h2 = decode_state_into(&f32_state, &mut pos2, Some(&mut nrm2)).unwrap();
        assert_eq!((h2.encoding, h2.tick, h2.flags, h2.bounds_min, h2.bounds_max), (Encoding::Float32, h.tick, h.flags, h.bounds_min, h.bounds_max), "{name}");
        assert_eq!((&pos2, h2.has_normals().then_some(&nrm2)), (&pos, h.has_normals().then_some(&nrm)), "{name}");
        assert_eq!((p.order as u64, p.step as f64), (want["order"].as_u64().unwrap(), want["step"].as_f64().unwrap()), "{name}");
        assert_eq!(pos, f32s(&want["positions"]), "{name}: positions");
        if h.has_normals() {
            assert_eq!(nrm, f32s(&want["normals"]), "{name}: normals");
        }
        // a payload cut short of what its 1.5 header announces is malformed
        assert_eq!(parse_state(&data[..data.len() - 4]).unwrap_err().code, ErrorCode::Malformed, "{name}");
        seen += 1;
    }
    assert_eq!(seen, 5);
    assert!(encode_state(1, 0, &[0.0; 3], None, Encoding::Predictive, 0).is_err());
    // the step's range (PROTOCOL.md section 4: 1e-5 to 0.1 metres)
    for (step, ok) in [(STEP_MIN, true), (STEP_MAX, true), (STEP_DEFAULT, true), (0.5 * STEP_MIN, false), (0.2, false), (f64::NAN, false)] {
        let mut s = Submit::decode(&unhex(sub)).unwrap();
        s.state.as_mut().unwrap().step = Some(step);
        assert_eq!(s.validate(&Limits::default()).is_ok(), ok, "submit step {step}");
        let ctl = Control { state: Some(StateOptions { step: Some(step), ..Default::default() }), ..Control::new("5ba88a14c526242f", "0123456789abcdef0123456789abcdef") };
        assert_eq!(ctl.validate(&Limits::default(), None).is_ok(), ok, "control step {step}");
    }
}

/// 1.7's scene request and reply (`misc.json`) and 1.8's mesh colliders (`meshes.json`): each
/// message read and written back but for the version this crate writes (a submission's, a
/// control's, a batch item's and a scene's mesh: set, moved, re-posed, removed), then each
/// refused message with its code (the decoder's checks and [`MeshCollider::validate`]'s).
#[test]
fn scene_and_mesh_vectors() {
    let scenes: Vec<Json> = load("misc.json").into_iter().filter(|v| v["message"].as_str().unwrap().contains("scene")).collect();
    assert_eq!(scenes.len(), 3, "scene, scene_open, reply_scene");
    let (mut ok, mut refused) = (0, 0);
    for v in scenes.iter().chain(load("meshes.json").iter()) {
        let name = v["name"].as_str().unwrap();
        let data = unhex(v);
        let Some(code) = v["error"].as_str() else {
            check_message(&as_current(v, v["value"]["v"][1].as_u64().unwrap()));
            ok += 1;
            continue;
        };
        let got = match v["message"].as_str().unwrap() {
            "control" => Control::decode(&data).and_then(|(c, _)| c.validate(&Limits::default(), None)),
            "scene" => SceneRequest::decode(&data).and_then(|s| s.validate()),
            other => panic!("{name}: unexpected message {other}"),
        };
        let e = got.expect_err(name);
        assert_eq!(e.code.as_str(), code, "{name}: {e}");
        refused += 1;
    }
    assert_eq!((ok, refused), (10, 7));
    // what each change is, read back from the vectors
    let meshes = load("meshes.json");
    let get = |n: &str| unhex(meshes.iter().find(|v| v["name"] == n).unwrap());
    let sub = Submit::decode(&get("submit_mesh_collider")).unwrap();
    let mc = sub.mesh_collider.unwrap();
    assert!(mc.is_new_mesh() && mc.position == [0.0, 1.0, 0.0] && mc.rotation == [1.0, 0.0, 0.0, 0.0]);
    let (mv, _) = Control::decode(&get("control_mesh_move")).unwrap();
    let mv = mv.mesh_collider.unwrap();
    assert_eq!(mv, MeshCollider::pose(mv.position, mv.rotation));
    let (rp, _) = Control::decode(&get("control_mesh_repose")).unwrap();
    assert!(rp.mesh_collider.as_ref().is_some_and(|m| m.vertices.is_some() && m.triangles.is_none()));
    let (rm, _) = Control::decode(&get("control_mesh_remove")).unwrap();
    assert_eq!(rm.mesh_collider, Some(MeshCollider::removal()));
    // the message names the offending triangle
    let (bad, _) = Control::decode(&get("mesh_index_out_of_range")).unwrap();
    assert!(bad.validate(&Limits::default(), None).unwrap_err().message.contains("triangle 0"));
}
