//! The protocol test vectors of the repository (`../../tests/vectors/*.json`, PROTOCOL.md
//! section 16) checked both ways: bytes -> meaning, and meaning -> identical bytes. The frozen
//! 1.0 vectors (`v1.0/`) must still be read as they mean.
use drape::wire::msg::{encode_info, encode_remove};
use drape::wire::reader::{unpack_message, Reader, Value};
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
                "vertices" | "targets" => json!({"f32": four.map(|c: [u8; 4]| f32::from_le_bytes(c) as f64).collect::<Vec<_>>()}),
                _ => json!({"u32": four.map(u32::from_le_bytes).collect::<Vec<_>>()}),
            }
        }
        Value::Array(a) => Json::Array(a.iter().map(|x| to_json(x, key)).collect()),
        Value::Map(m) => Json::Object(m.iter().map(|(k, x)| (k.as_str().unwrap().to_string(), to_json(x, k.as_str().unwrap()))).collect()),
        Value::Ext(..) => panic!("no ext values in the protocol"),
    }
}

fn check_message(v: &Json) {
    let name = v["name"].as_str().unwrap();
    let data = unhex(v);
    let m = unpack_message(&data).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(to_json(&Value::Map(m.clone()), ""), v["value"], "{name}: decoded value");
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
        "control_batch" => ControlBatch::decode(&data).unwrap().encode(),
        "remove" => {
            let r = Reader::new(&m, "");
            encode_remove(r.str("cloth", true).unwrap().unwrap(), r.str("token", true).unwrap().unwrap(), rid)
        }
        "info" => encode_info(rid),
        "reply_submit" => SubmitReply::from_map(&decode_reply(&data).unwrap()).unwrap().encode(),
        "reply_control" | "reply_remove" => encode_tick_reply(tick_of(&decode_reply(&data).unwrap()).unwrap(), rid),
        "reply_control_batch" => BatchReply::from_map(&decode_reply(&data).unwrap()).unwrap().encode(),
        "error" => {
            let e = decode_reply(&data).unwrap_err();
            assert_eq!(e.code.as_str(), v["value"]["error"]["code"], "{name}");
            assert_eq!(e.rid, rid);
            ErrorReply::from_map(&m).unwrap().encode()
        }
        other => panic!("{name}: unknown message kind {other}"),
    };
    assert_eq!(again, data, "{name}: re-encoded bytes differ");
}

#[test]
fn messages_both_ways() {
    for file in ["submit.json", "control.json", "misc.json", "v1.0/submit.json", "v1.0/control.json", "v1.0/misc.json"] {
        for v in load(file) {
            if file.starts_with("v1.0") {
                // 1.0 vectors: read as they mean; written back they differ only in the version.
                let data = unhex(&v);
                let m = unpack_message(&data).unwrap();
                let mut want = v["value"].clone();
                assert_eq!(want["v"], json!([1, 0]));
                want["v"] = json!([1, 1]);
                let mut got = to_json(&Value::Map(m), "");
                got["v"] = json!([1, 1]);
                assert_eq!(got, want, "{file} {}", v["name"]);
                let mut v11 = v.clone();
                let mut bytes = data.clone();
                let at = bytes.windows(3).position(|w| w == [0x92, 1, 0]).unwrap();
                bytes[at + 2] = 1;
                v11["hex"] = json!(bytes.iter().map(|b| format!("{b:02x}")).collect::<String>());
                v11["value"] = want;
                check_message(&v11);
            } else {
                check_message(&v);
            }
        }
    }
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
    for file in ["state.json", "v1.0/state.json"] {
        for v in load(file) {
            let name = format!("{file} {}", v["name"].as_str().unwrap());
            let data = unhex(&v);
            let want = &v["value"];
            check_state(&name, &data, want);
            let input = &v["input"];
            let normals = if input["normals"].is_null() { None } else { Some(f32s(&input["normals"])) };
            let enc = Encoding::from_name(want["encoding"].as_str().unwrap()).unwrap();
            let mut again = encode_state(want["tick"].as_u64().unwrap(), want["server_time_ns"].as_u64().unwrap(),
                &f32s(&input["positions"]), normals.as_deref(), enc, input["flags"].as_u64().unwrap() as u16).unwrap();
            again[5] = data[5]; // a 1.0 vector differs only in the minor version byte
            assert_eq!(again, data, "{name}: re-encoded bytes differ");
        }
    }
}

#[test]
fn bundles_both_ways() {
    for v in load("bundle.json") {
        let name = v["name"].as_str().unwrap();
        let data = unhex(&v);
        let want = &v["value"];
        let b = parse_bundle(&data).unwrap();
        assert_eq!((b.major as u64, b.minor as u64, b.header_size as u64), (1, 1, 32));
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
        assert_eq!(encode_bundle(b.tick, b.server_time_ns, &refs, 0).unwrap(), data, "{name}: re-encoded");
    }
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
            "remove" => unpack_message(&data).and_then(|m| {
                let r = Reader::new(&m, "");
                validate::validate_owner(r.str("cloth", true)?.unwrap(), r.str("token", true)?.unwrap())
            }),
            "control_batch" => match ControlBatch::decode_items(&data, &lim) {
                Err(e) => Err(e),
                Ok((_, items)) => {
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
    let one = unhex(&load("bundle.json")[1]);
    let b1 = parse_bundle(&one).unwrap();
    assert_eq!((b.minor, b.flags, b.entries.len()), (7, 1 << 31, 1));
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
