//! Rates per subscriber (protocol 1.8, 1.9's every 6th and 12th; PROTOCOL.md 9.3):
//! `tests/vectors/rates.json` read by the crate's `rates` module. The decimated keys; a stream of
//! every 2nd state decoding in order, each predicted from the key's own states (ref ticks T - 2,
//! T - 4); and `rate = auto`'s rule: the Python governor's constants are this crate's, and each of
//! its traces (states arriving with injected receive times, along the ladder of the rates its
//! server serves) makes the Rust governor step at the same states to the same rates.
use drape::rates::{every_key, served_rates, split_every, Governor, GovernorConfig, RATES};
use drape::wire::*;
use serde_json::Value as Json;

fn vectors() -> Vec<Json> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/vectors/rates.json");
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {path}: {e}"));
    serde_json::from_str::<Json>(&text).unwrap().as_array().unwrap().clone()
}

fn of(kind: &str) -> Vec<Json> {
    vectors().into_iter().filter(|v| v["message"] == kind).collect()
}

#[test]
fn decimated_keys() {
    let keys = of("key");
    assert_eq!(keys.len(), 2 * (RATES.len() - 1));
    for v in keys {
        let (key, k) = (v["input"]["key"].as_str().unwrap(), v["input"]["every"].as_u64().unwrap() as u8);
        let want = v["value"]["key"].as_str().unwrap();
        assert_eq!(every_key(key, k).as_deref(), Some(want), "{}", v["name"]);
        assert_eq!(split_every(want), (key, k), "{}", v["name"]);
    }
}

#[test]
fn a_stream_of_every_2nd_state_decodes_in_order() {
    let states = of("state");
    assert_eq!(states.len(), 3);
    let mut stream = PredictiveStream::new();
    for v in states {
        let s = v["hex"].as_str().unwrap();
        let data: Vec<u8> = (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect();
        let want = &v["value"];
        let h = parse_state(&data).unwrap();
        let ph = parse_predictive(&data).unwrap();
        assert_eq!(h.tick, want["tick"].as_u64().unwrap());
        assert_eq!((ph.order as u64, ph.ref_tick, ph.ref2_tick),
                   (want["order"].as_u64().unwrap(), want["ref_tick"].as_u64().unwrap(), want["ref2_tick"].as_u64().unwrap()));
        let mut pos = vec![0f32; 3 * h.vertex_count as usize];
        stream.decode(&data, &mut pos, None).unwrap().expect("in order");
        let expect: Vec<f32> = want["positions"].as_array().unwrap().iter()
            .flat_map(|p| p.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32)).collect();
        assert_eq!(pos, expect, "{}", v["name"]);
    }
}

#[test]
fn the_governor_is_the_python_sdks() {
    let traces = of("governor");
    assert!(traces.len() >= 7);
    let ours = GovernorConfig::default();
    for v in traces {
        let (name, i, want) = (v["name"].as_str().unwrap(), &v["input"], &v["value"]);
        let c = &i["constants"];
        let f = |k: &str| c[k].as_f64().unwrap_or_else(|| panic!("{name}: constants.{k}"));
        let theirs = GovernorConfig {
            window_s: f("window_s"),
            late_s: f("late_s"),
            jump_s: f("jump_s"),
            lost_share: f("lost_share"),
            quiet_s: f("quiet_s"),
            max_quiet_s: f("max_quiet_s"),
            baseline_windows: f("baseline_windows") as usize,
            late_percentile: f("late_percentile"),
            settle_windows: f("settle_windows"),
            failed_up_windows: f("failed_up_windows"),
        };
        assert_eq!(theirs, ours, "{name}: the Python governor's numbers");
        let rates: Vec<u8> = c["rates"].as_array().unwrap().iter().map(|r| r.as_u64().unwrap() as u8).collect();
        assert_eq!(rates, RATES, "{name}");
        let u = |k: &str| i[k].as_u64().unwrap();
        let (tick_ns, offset_ns, link_ns) = (u("tick_ns"), u("offset_ns"), u("link_ns"));
        let ticks = i["ticks"].as_array().unwrap();
        let late = i["late_us"].as_array().unwrap();
        let ladder: Vec<u8> = i["rates"].as_array().unwrap().iter().map(|r| r.as_u64().unwrap() as u8).collect();
        let version = if name.ends_with("1_8") { (1, 8) } else { (1, 9) };
        assert_eq!(ladder, served_rates(Some(version)), "{name}: the ladder of a {version:?} server");
        let mut gov = Governor::new(1);
        gov.limit(&ladder);
        let mut changes = Vec::new();
        for (n, (t, l)) in ticks.iter().zip(late).enumerate() {
            let (t, l) = (t.as_u64().unwrap(), l.as_u64().unwrap());
            let server = t * tick_ns;
            if let Some(r) = gov.observe(t, server, server + offset_ns + link_ns + l * 1000) {
                changes.extend([n as u64, r as u64]);
            }
        }
        let want_changes: Vec<u64> = want["changes"].as_array().unwrap().iter().map(|x| x.as_u64().unwrap()).collect();
        assert_eq!(changes, want_changes, "{name}: (state index, new rate) of each change");
        assert_eq!((gov.rate as u64, gov.step_downs, gov.step_ups, gov.quiet_s),
                   (want["rate"].as_u64().unwrap(), want["step_downs"].as_u64().unwrap(),
                    want["step_ups"].as_u64().unwrap(), want["quiet_s"].as_f64().unwrap()), "{name}");
    }
}
