//! End-to-end tests against real `drape serve` processes on loopback (see tests/common): real
//! Zenoh, a real server, no mocks. Submissions of grids, meshes and OBJ text, states on single
//! keys and in bundles, controls waited for or not, batch control, errors, removal, and a
//! server killed under its cloths (reported, and resumed elsewhere with failover, on by default).
mod common;

use drape::client::{Client, Cloth, Event, LossReason};
use drape::wire::{Collider, Control, Encoding, ErrorCode, Grid, Orientation, StateOptions, Submit};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn shared() -> Option<&'static common::Server> {
    static S: OnceLock<Option<common::Server>> = OnceLock::new();
    S.get_or_init(|| common::drape_bin().map(|b| common::start(&b, &[]))).as_ref()
}

fn connect(servers: &[&common::Server], server_id: Option<&str>, failover: bool) -> Client {
    common::connect(servers, server_id, failover)
}

fn opts() -> Submit {
    Submit::new("", drape::wire::Shape::Grid(Grid::new(1, 1)))
}

fn wait(c: &Cloth, pos: &mut [f32]) -> drape::client::StateInfo {
    c.wait_state(pos, None, common::WAIT).expect("read").expect("no state within common::WAIT")
}

#[test]
fn grid_states_and_pins() {
    let Some(s) = shared() else { return };
    let client = connect(&[s], Some(&s.id), false);
    let grid = Grid { cols: 8, rows: 4, width: 1.4, height: 0.6, orientation: Orientation::Vertical, origin: [0.0, 2.0, 0.0] };
    let cloth = client.submit_grid(grid, Submit { pinned: vec![0, 7], ..opts() }).unwrap();
    assert_eq!(cloth.vertex_count(), 32);
    let mut pos = vec![0f32; 96];
    let first = wait(&cloth, &mut pos);
    assert!(first.tick >= cloth.first_tick() && first.vertex_count == 32);
    assert_eq!(&pos[0..3], &cloth.rest_positions()[0..3], "a pinned vertex stays at rest");
    let mut last = first.tick;
    for _ in 0..5 {
        let st = wait(&cloth, &mut pos);
        assert!(st.tick > last, "ticks increase");
        assert!(st.receive_time_ns >= st.server_time_ns / 2);
        last = st.tick;
    }
    assert!(pos[5 * 3 + 1] < 2.0, "an unpinned vertex falls");
    let targets = [0.1f32, 2.5, 0.2, 1.5, 2.5, 0.2];
    let tick = cloth.move_pins(&[0, 7], &targets, true).unwrap().unwrap();
    loop {
        let st = wait(&cloth, &mut pos);
        if st.tick >= tick {
            assert_eq!(&pos[0..3], &targets[0..3]);
            assert_eq!(&pos[21..24], &targets[3..6]);
            break;
        }
    }
    // Controls without waiting: nothing comes back but states, and the last target wins.
    for k in 0..10 {
        cloth.move_pins(&[0], &[0.0, 2.5 + k as f32 * 0.01, 0.0], false).unwrap();
    }
    let t0 = Instant::now();
    // (a pin reaches its target to within 1 float32 ulp per coordinate, PROTOCOL.md section 12)
    while pos[0..3].iter().zip([0.0f32, 2.59, 0.0]).any(|(p, t)| (p - t).abs() > 1e-6) {
        assert!(t0.elapsed() < common::WAIT, "the unwaited pin moves are not applied: {:?}", &pos[0..3]);
        wait(&cloth, &mut pos);
    }
    let last_tick = cloth.remove().unwrap();
    assert!(last_tick >= tick);
    assert_eq!(cloth.read_state(&mut pos, None).unwrap_err().code, ErrorCode::Closed);
    std::thread::sleep(Duration::from_millis(200));
    while let Some(e) = client.poll_event(Duration::ZERO) {
        assert!(!matches!(e, Event::RequestFailed { .. }), "{e:?}");
    }
    client.close(true);
}

#[test]
fn mesh_obj_encodings_and_errors() {
    let Some(s) = shared() else { return };
    let client = connect(&[s], Some(&s.id), false);
    let obj = "v 0 2 0\nv 1 2 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";
    let state = StateOptions { normals: Some(true), encoding: Some(Encoding::Quant16), bundle: None, step: None };
    let cloth = client.submit_obj(obj, Submit { pinned: vec![0, 1], state: Some(state), ..opts() }).unwrap();
    assert_eq!((cloth.vertex_count(), cloth.triangles()), (4, &[0u32, 1, 2, 0, 2, 3][..]));
    let (mut pos, mut nrm) = (vec![0f32; 12], vec![0f32; 12]);
    let st = cloth.wait_state(&mut pos, Some(&mut nrm), common::WAIT).unwrap().unwrap();
    assert!(st.has_normals && st.encoding == Encoding::Quant16);
    assert!((nrm[2].abs() - 1.0).abs() < 0.05, "a flat XY quad's normal is along z: {nrm:?}");
    // Client-side checks fail fast with the protocol's codes.
    let e = client.submit_obj(obj, Submit { pinned: vec![4], ..opts() }).unwrap_err();
    assert_eq!(e.code, ErrorCode::IndexOutOfRange, "{e}");
    assert_eq!(client.submit_obj("v 0 0\n", opts()).unwrap_err().code, ErrorCode::InvalidValue);
    let e = cloth.control(Control { gravity: Some([0.0, f64::NAN, 0.0]), ..Default::default() }, true).unwrap_err();
    assert_eq!(e.code, ErrorCode::InvalidValue);
    // Server-side errors come back with their code: vertex 2 is not pinned.
    let e = cloth.move_pins(&[2], &[0.0, 0.0, 0.0], true).unwrap_err();
    assert_eq!(e.code, ErrorCode::InvalidValue, "{e}");
    assert!(e.message.contains("pinned"), "{e}");
    // ... and, when not waited for, as events.
    cloth.move_pins(&[2], &[0.0, 0.0, 0.0], false).unwrap();
    let t0 = Instant::now();
    let mut ev = None;
    while t0.elapsed() < common::WAIT && !matches!(ev, Some(Event::RequestFailed { .. })) {
        ev = client.poll_event(Duration::from_millis(100));
    }
    assert!(matches!(&ev, Some(Event::RequestFailed { handle: Some(h), error, .. }) if *h == cloth.handle() && error.code == ErrorCode::InvalidValue), "{ev:?}");
    let tick = cloth.control(Control { colliders: Some(vec![Collider::Plane { normal: [0.0, 1.0, 0.0], offset: 0.5 }]), reset: true, ..Default::default() }, true);
    assert!(tick.unwrap().is_some());
    let info = client.info().unwrap();
    assert!(drape::wire::reader::Reader::new(&info, "").str("version", true).unwrap().unwrap().starts_with("1."));
    client.close(true);
}

#[test]
fn bundles_and_batch_control() {
    let Some(s) = shared() else { return };
    let client = connect(&[s], Some(&s.id), false);
    let encodings = [Encoding::Float32, Encoding::Float16, Encoding::Quant16];
    let cloths: Vec<Cloth> = encodings.iter().map(|e| {
        let state = StateOptions { encoding: Some(*e), bundle: Some(true), normals: None, step: None };
        client.submit_grid(Grid::new(6, 6), Submit { pinned: vec![0, 5], state: Some(state), ..opts() }).unwrap()
    }).collect();
    let mut pos = vec![0f32; 108];
    for c in &cloths {
        assert!(c.bundled());
        wait(c, &mut pos);
    }
    let mut batch = client.batch();
    for (k, c) in cloths.iter().enumerate() {
        batch.move_pins(c, &[0, 5], &[0.0, 1.0, k as f32, 1.0, 1.0, k as f32]);
    }
    batch.add(&cloths[0], Control { pins: Some(drape::wire::Pins { indices: vec![3], targets: vec![0.0; 3] }), ..Default::default() });
    let results = client.send_batch(batch, true).unwrap().unwrap();
    assert!(results[..3].iter().all(|r| r.is_ok()), "{results:?}");
    assert_eq!(results[3].as_ref().unwrap_err().code, ErrorCode::InvalidValue, "vertex 3 is not pinned: refused alone");
    let tick = *results[0].as_ref().unwrap();
    for (k, c) in cloths.iter().enumerate() {
        loop {
            let st = wait(c, &mut pos);
            if st.tick >= tick {
                let tol = if k == 0 { 0.0 } else { 2e-3 };
                assert!((pos[2] - k as f32).abs() <= tol && (pos[1] - 1.0).abs() <= tol, "cloth {k}: {:?}", &pos[..3]);
                break;
            }
        }
    }
    let mut batch = client.batch();
    for c in &cloths {
        batch.move_pins(c, &[0], &[0.0, 1.5, 0.0]);
    }
    assert!(client.send_batch(batch, false).unwrap().is_none());
    for c in &cloths {
        c.remove().unwrap();
    }
    client.close(true);
}

/// The largest distance between two vertices of the same index (xyz interleaved).
fn max_dist(a: &[f32], b: &[f32]) -> f32 {
    a.chunks_exact(3).zip(b.chunks_exact(3))
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt())
        .fold(0.0, f32::max)
}

/// kill -9 of the server under the cloths. Without failover: reported, lost. With failover
/// (PROTOCOL.md 11.1): resubmitted to the other server under the same handle, resumed from the
/// last received state (within 1 cm of it, and the cloth hangs far from its rest pose, so a
/// restart from the rest pose fails this), the moved pins sent again.
#[test]
fn lost_server_is_reported_and_failover_resumes() {
    let Some(bin) = common::drape_bin() else { return };
    let (a, b) = (common::start(&bin, &[]), common::start(&bin, &[]));
    let plain = connect(&[&a], Some(&a.id), false);
    let fo = connect(&[&a, &b], Some(&a.id), true);
    // A horizontal 4x4 grid pinned at two corners of its first row: it swings down and hangs
    // (damped), far from its flat rest pose.
    let material = drape::wire::Material { damping: Some(0.05), ..Default::default() };
    let sub = || Submit { pinned: vec![0, 3], material, ..opts() };
    let lost = plain.submit_grid(Grid::new(4, 4), sub()).unwrap();
    let moved = fo.submit_grid(Grid::new(4, 4), sub()).unwrap();
    let bundled = fo.submit_grid(Grid::new(4, 4), Submit { state: Some(StateOptions { bundle: Some(true), ..Default::default() }), ..sub() }).unwrap();
    let mut pos = vec![0f32; 48];
    // the pins raised by 0.5 m: the resubmission must keep them there
    let lifted = [0.0, 0.5, 0.0, 1.0, 0.5, 0.0];
    for c in [&moved, &bundled] {
        wait(c, &mut pos);
        assert_eq!(c.server(), a.id);
        c.move_pins(&[0, 3], &lifted, true).unwrap();
    }
    wait(&lost, &mut pos);
    // The same through the C ABI: a client with failover on (DrapeClientOptions.no_failover false, the default).
    use drape::ffi::*;
    let (c_connect, c_server) = (std::ffi::CString::new(format!("{},{}", a.endpoint, b.endpoint)).unwrap(), std::ffi::CString::new(a.id.clone()).unwrap());
    let c_opts = common::c_client_options(&c_connect, Some(&c_server), None, 10_000, false);
    let (mut cclient, mut ccloth) = (std::ptr::null_mut(), std::ptr::null_mut());
    let pins = [0u32, 3];
    let grid = DrapeGrid { cols: 4, rows: 4, width: 1.0, height: 1.0, vertical: false, origin: [0.0; 3] };
    unsafe {
        assert_eq!(drape_client_open(&c_opts, &mut cclient), DRAPE_OK);
        let o = common::c_cloth_options(&pins, false);
        assert_eq!(drape_submit_grid(cclient, &grid, &o, &mut ccloth), DRAPE_OK);
        assert_eq!(drape_cloth_wait_state(ccloth, pos.as_mut_ptr(), 48, std::ptr::null_mut(), 0, common::WAIT.as_millis() as u32, std::ptr::null_mut()), DRAPE_OK);
    }
    let t0 = Instant::now();
    let mut last = [vec![0f32; 48], vec![0f32; 48]];
    loop {
        for (c, l) in [&moved, &bundled].iter().zip(last.iter_mut()) {
            c.wait_state(l, None, common::WAIT).unwrap().expect("a state");
        }
        let far = last.iter().zip([&moved, &bundled]).all(|(l, c)| max_dist(l, c.rest_positions()) > 0.5);
        if far && t0.elapsed() > Duration::from_secs(3) {
            break;
        }
        assert!(t0.elapsed() < common::WAIT, "the cloths did not swing down");
    }
    // the client's last received states, just before the kill
    for (c, l) in [&moved, &bundled].iter().zip(last.iter_mut()) {
        common::latest(c, l);
    }
    let (old, handle) = (moved.id(), moved.handle());
    a.kill();
    let until = |client: &Client, f: &dyn Fn(&Event) -> bool| {
        let t0 = Instant::now();
        while t0.elapsed() < common::WAIT {
            if let Some(e) = client.poll_event(Duration::from_millis(200)) {
                if f(&e) {
                    return e;
                }
            }
        }
        panic!("event not seen within {:?}", common::WAIT);
    };
    until(&plain, &|e| matches!(e, Event::ServerLost { server } if *server == a.id));
    until(&plain, &|e| matches!(e, Event::ClothLost { handle, .. } if *handle == lost.handle()));
    assert_eq!(lost.read_state(&mut pos, None).unwrap_err().code, ErrorCode::ServerLost);
    assert_eq!(lost.move_pins(&[0], &[0.0; 3], true).unwrap_err().code, ErrorCode::ServerLost);
    let mut pending = vec![moved.handle(), bundled.handle()]; // resubmitted in any order
    while !pending.is_empty() {
        let e = until(&fo, &|e| matches!(e, Event::ClothResubmitted { handle, .. } if pending.contains(handle)));
        let Event::ClothResubmitted { handle, server, old_server, reason, resumed_tick, kept, .. } = e else { unreachable!() };
        assert_eq!((server, old_server, reason, kept), (b.id.clone(), a.id.clone(), LossReason::ServerLost, false));
        assert!(resumed_tick.is_some(), "resumed from a received state");
        pending.retain(|h| *h != handle);
    }
    assert_eq!((moved.handle(), moved.server()), (handle, b.id.clone()));
    assert_ne!(moved.id(), old);
    for (c, l) in [&moved, &bundled].iter().zip(&last) {
        let st = wait(c, &mut pos);
        assert!(st.tick >= c.first_tick(), "states come from the new server");
        let (from_last, from_rest) = (max_dist(&pos, l), max_dist(&pos, c.rest_positions()));
        assert!(from_last < 0.01, "the first state after the failover is {from_last} m from the last one before it");
        assert!(from_rest > 0.5, "the cloth did not restart from its rest pose ({from_rest} m from it)");
        // the pins stay where the game moved them
        std::thread::sleep(Duration::from_millis(200));
        common::latest(&c, &mut pos);
        assert!(max_dist(&pos[..3], &lifted[..3]) < 1e-3 && max_dist(&pos[9..12], &lifted[3..]) < 1e-3, "pins: {:?}", &pos[..12]);
        assert!(c.move_pins(&[0], &[0.0, 0.5, 0.0], true).unwrap().is_some());
    }
    assert_eq!(fo.server_id().unwrap(), b.id, "new submissions go to the live server");
    unsafe {
        let t0 = Instant::now();
        let ev = loop {
            assert!(t0.elapsed() < common::WAIT, "C ABI: no DRAPE_EVENT_CLOTH_RESUBMITTED");
            let mut ev: DrapeEvent = std::mem::zeroed();
            if drape_client_poll_event(cclient, 200, &mut ev) == DRAPE_OK && ev.kind == DRAPE_EVENT_CLOTH_RESUBMITTED {
                break ev;
            }
        };
        let text = |b: &[std::ffi::c_char]| std::ffi::CStr::from_ptr(b.as_ptr()).to_str().unwrap().to_string();
        assert_eq!((ev.handle, ev.reason, ev.resumed, ev.kept), (drape_cloth_handle(ccloth), DRAPE_REASON_SERVER_LOST, true, false));
        assert_eq!((text(&ev.server), text(&ev.old_server)), (b.id.clone(), a.id.clone()));
        assert!(ev.resumed_tick > 0);
        // (what it resumed from is checked on the Rust cloths above: the same code)
        assert_eq!(drape_cloth_wait_state(ccloth, pos.as_mut_ptr(), 48, std::ptr::null_mut(), 0, common::WAIT.as_millis() as u32, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(ccloth);
        drape_client_close(cclient, true);
    }
    lost.remove().unwrap();
    fo.close(true);
    plain.close(true);
}

/// A reclaim (PROTOCOL.md 11.1, case 2): the server no longer has the cloth (here another
/// party removed it with its token, as the server does when it reclaims the cloths of a client
/// away past its grace period). Its states stall, the probe is answered `not_found`, and the
/// failover resubmits it to the live server (the same one) from its last received state.
#[test]
fn reclaimed_cloth_is_resumed() {
    use zenoh::Wait;
    let Some(s) = shared() else { return };
    let fo = connect(&[s], Some(&s.id), true);
    let material = drape::wire::Material { damping: Some(0.05), ..Default::default() };
    let cloth = fo.submit_grid(Grid::new(4, 4), Submit { pinned: vec![0, 3], material, ..opts() }).unwrap();
    let mut last = vec![0f32; 48];
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(2) || max_dist(&last, cloth.rest_positions()) < 0.5 {
        assert!(t0.elapsed() < common::WAIT, "the cloth did not swing down");
        wait(&cloth, &mut last);
    }
    let (old, handle) = (cloth.id(), cloth.handle());
    // Removed behind the client's back.
    let mut cfg = zenoh::Config::default();
    cfg.insert_json5("mode", "\"peer\"").unwrap();
    cfg.insert_json5("connect/endpoints", &format!("[\"{}\"]", s.endpoint)).unwrap();
    cfg.insert_json5("listen/endpoints", "[]").unwrap();
    cfg.insert_json5("scouting/multicast/enabled", "false").unwrap();
    let other = zenoh::open(cfg).wait().unwrap();
    let payload = drape::wire::msg::encode_remove(&old, &cloth.token(), 1);
    let t0 = Instant::now();
    loop {
        let replies = other.get(format!("drape/server/{}/remove", s.id)).payload(payload.clone()).timeout(Duration::from_secs(5)).wait().unwrap();
        if let Ok(r) = replies.recv() {
            assert!(r.result().is_ok(), "the remove was refused");
            break;
        }
        assert!(t0.elapsed() < common::WAIT, "no reply to the remove");
    }
    // the last state received before the removal (no state comes after it)
    std::thread::sleep(Duration::from_millis(150));
    common::latest(&cloth, &mut last);
    let t0 = Instant::now();
    let ev = loop {
        assert!(t0.elapsed() < common::WAIT, "no failover");
        if let Some(e @ Event::ClothResubmitted { .. }) = fo.poll_event(Duration::from_millis(200)) {
            break e;
        }
    };
    let Event::ClothResubmitted { handle: h, reason, old_cloth, server, resumed_tick, kept, .. } = ev else { unreachable!() };
    assert_eq!((h, reason, old_cloth, server, kept), (handle, LossReason::Reclaimed, old.clone(), s.id.clone(), false));
    assert!(resumed_tick.is_some());
    assert_ne!(cloth.id(), old);
    let mut pos = vec![0f32; 48];
    wait(&cloth, &mut pos);
    let (from_last, from_rest) = (max_dist(&pos, &last), max_dist(&pos, cloth.rest_positions()));
    assert!(from_last < 0.01, "the first state after the failover is {from_last} m from the last one before it");
    assert!(from_rest > 0.5, "restarted from the rest pose ({from_rest} m from it)");
    cloth.remove().unwrap();
    fo.close(true);
    let _ = other.close().wait();
}

fn names(v: &[&str]) -> Option<Vec<String>> {
    Some(v.iter().map(|x| x.to_string()).collect())
}

/// Protocol 1.2 feature changes against the real server: `features_add` / `features_remove`
/// switch single features and keep the others (seen in the states: the normals flag), and a
/// 1.2 server reports the resulting set in every control reply and applied batch result.
#[test]
fn feature_changes_keep_the_other_features() {
    let Some(s) = shared() else { return };
    let client = connect(&[s], Some(&s.id), false);
    let info = client.info().unwrap();
    let version = drape::wire::reader::Reader::new(&info, "").str("version", true).unwrap().unwrap().to_string();
    let (major, minor) = version.split_once('.').map(|(a, b)| (a.parse::<u32>().unwrap(), b.parse::<u32>().unwrap())).unwrap();
    assert!(major == 1 && minor >= 2, "the server speaks protocol 1.2 or later, not {version}");
    let state = StateOptions { normals: Some(true), ..Default::default() };
    let cloth = client.submit_grid(Grid::new(6, 6), Submit { pinned: vec![0, 5], state: Some(state), ..opts() }).unwrap();
    let (mut pos, mut nrm) = (vec![0f32; 108], vec![0f32; 108]);
    assert!(cloth.wait_state(&mut pos, Some(&mut nrm), common::WAIT).unwrap().unwrap().has_normals);
    assert_eq!(cloth.features(), None, "nothing reported before a control");

    // Client-side checks: a name in both lists, an unknown name.
    assert_eq!(cloth.change_features(&["wind"], &["wind"], true).unwrap_err().code, ErrorCode::InvalidValue);
    assert_eq!(cloth.change_features(&["gravity"], &[], true).unwrap_err().code, ErrorCode::InvalidValue);

    // wind on: normals (switched on by state.normals at submission) stay on.
    let on = cloth.change_features(&["wind"], &[], true).unwrap().unwrap();
    // normals off, wind kept: the states from the reply's tick on carry no normals.
    let off = cloth.change_features(&[], &["normals"], true).unwrap().unwrap();
    loop {
        let st = cloth.wait_state(&mut pos, Some(&mut nrm), common::WAIT).unwrap().expect("a state");
        if st.tick >= off.tick {
            assert!(!st.has_normals, "normals removed from tick {}: {st:?}", off.tick);
            break;
        }
        assert!(st.has_normals, "normals still on before tick {}", off.tick);
    }
    // In a batch item: xpbd on, wind off.
    let mut batch = client.batch();
    batch.change_features(&cloth, &["xpbd"], &["wind"]);
    let item = client.send_batch_applied(batch).unwrap().remove(0).unwrap();
    // Not waited for: the reply's set is kept on the cloth when it comes.
    assert!(cloth.change_features(&["tethers"], &[], false).unwrap().is_none());
    let t0 = Instant::now();
    while cloth.features().is_none_or(|f| !f.contains(&"tethers".to_string())) && t0.elapsed() < common::WAIT {
        std::thread::sleep(Duration::from_millis(20));
    }
    let later = cloth.features();
    cloth.remove().unwrap();
    client.close(true);

    // What a 1.2 server reports (PROTOCOL.md section 5: `features` in control replies and in
    // applied batch results), in the protocol's order.
    assert_eq!(on.features, names(&["wind", "normals"]), "control reply after features_add [wind]");
    assert_eq!(off.features, names(&["wind"]), "control reply after features_remove [normals]");
    assert_eq!(item.features, names(&["xpbd"]), "batch result after features_add [xpbd], features_remove [wind]");
    assert_eq!(later, names(&["xpbd", "tethers"]), "the set kept from an unwaited control's reply");
}

/// The C ABI of 1.2: feature masks, the resulting set, `overloaded` named.
#[test]
fn c_abi_feature_changes() {
    use drape::ffi::*;
    use std::ffi::CStr;
    let Some(s) = shared() else { return };
    let name = |code: i32| unsafe { CStr::from_ptr(drape_error_name(code)) }.to_str().unwrap().to_string();
    assert_eq!(name(DRAPE_E_OVERLOADED), "overloaded");
    assert_eq!(name(DRAPE_E_UNKNOWN), "unknown");
    assert!(unsafe { CStr::from_ptr(drape_version()) }.to_str().unwrap().ends_with("protocol 1.4"));
    unsafe {
        let client = common::c_open(s, None);
        let grid = DrapeGrid { cols: 4, rows: 4, width: 0.0, height: 0.0, vertical: false, origin: [0.0; 3] };
        let pins = [0u32, 3];
        let copts = common::c_cloth_options(&pins, true);
        let mut cloth = std::ptr::null_mut();
        assert_eq!(drape_submit_grid(client, &grid, &copts, &mut cloth), DRAPE_OK);
        let mut mask = 0u32;
        assert_eq!(drape_cloth_features(cloth, &mut mask), DRAPE_NO_DATA);
        assert_eq!(drape_cloth_change_features(cloth, 1 << 6, 0, true, std::ptr::null_mut(), &mut mask), DRAPE_E_INVALID_VALUE);
        let both = drape_cloth_change_features(cloth, DRAPE_FEATURE_WIND, DRAPE_FEATURE_WIND, true, std::ptr::null_mut(), &mut mask);
        assert_eq!(both, DRAPE_E_INVALID_VALUE);
        let mut tick = 0u64;
        let rc = drape_cloth_change_features(cloth, DRAPE_FEATURE_WIND, DRAPE_FEATURE_NORMALS, true, &mut tick, &mut mask);
        assert_eq!(rc, DRAPE_OK);
        assert!(tick > 0);
        let after_control = mask;
        let batch = drape_batch_new();
        assert_eq!(drape_batch_change_features(batch, cloth, DRAPE_FEATURE_XPBD, DRAPE_FEATURE_WIND), DRAPE_OK);
        assert_eq!(drape_batch_change_features(batch, cloth, 1 << 31, 0), DRAPE_E_INVALID_VALUE);
        let mut codes = [-1i32; 1];
        let mut ticks = [0u64; 1];
        assert_eq!(drape_batch_send(client, batch, true, codes.as_mut_ptr(), ticks.as_mut_ptr(), 1), DRAPE_OK);
        assert_eq!(codes[0], DRAPE_OK);
        drape_batch_free(batch);
        let mut after_batch = 0u32;
        let reported = drape_cloth_features(cloth, &mut after_batch);
        assert_eq!(drape_cloth_remove(cloth, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(cloth);
        drape_client_close(client, true);
        // a 1.2 server reports the resulting sets
        assert_eq!(after_control, DRAPE_FEATURE_WIND, "mask after wind on, normals off");
        assert_eq!((reported, after_batch), (DRAPE_OK, DRAPE_FEATURE_XPBD), "mask after the batch item");
    }
}

/// 1.2 admission control: a server that cannot fit another cloth in its tick budget answers
/// `overloaded` (code 17, retryable), in Rust and through the C ABI's code.
#[test]
fn overloaded_submissions() {
    let Some(bin) = common::drape_bin() else { return };
    // a budget of 0.01 % of a tick: the first cloth is admitted (an empty server admits), the
    // next ones are not once a tick has measured the cost per vertex
    let s = common::start(&bin, &["--admission", "--admission-budget", "0.0001"]);
    let client = connect(&[&s], Some(&s.id), false);
    let first = client.submit_grid(Grid::new(8, 8), Submit { pinned: vec![0, 7], ..opts() }).unwrap();
    let mut pos = vec![0f32; 192];
    wait(&first, &mut pos);
    wait(&first, &mut pos);
    let e = client.submit_grid(Grid::new(8, 8), Submit { pinned: vec![0, 7], ..opts() }).unwrap_err();
    assert_eq!(e.code, ErrorCode::Overloaded, "{e}");
    assert!(e.code.is_retryable() && !e.code.is_bad_request());
    assert_eq!(e.code as i32, drape::ffi::DRAPE_E_OVERLOADED);
    first.remove().unwrap();
    client.close(true);
}

/// PROTOCOL.md 11.2 (1.4): a server run with `--identity keys` declares only the client-scoped
/// request keys. The client asks its info once, sees 1.4 and sends submit, control,
/// control_batch and remove on `{ns}/server/{S}/client/{C}/...`; states come on the submit
/// reply's client-scoped key, bundles on the client's bundle key. The server-wide keys answer
/// nothing there (what a 1.3 client would get).
#[test]
fn identity_keys_server() {
    use zenoh::Wait;
    let Some(bin) = common::drape_bin() else { return };
    let s = common::start(&bin, &["--identity", "keys"]);
    let client = connect(&[&s], Some(&s.id), false);
    let info = client.info().unwrap();
    let version = drape::wire::reader::Reader::new(&info, "").str("version", true).unwrap().unwrap().to_string();
    let (major, minor) = version.split_once('.').unwrap();
    assert!((major.parse::<u32>().unwrap(), minor.parse::<u32>().unwrap()) >= (1, 4), "server version {version}");
    let me = client.client_id().to_string();
    // submit (a grid on its own state key) and states
    let grid = Grid { cols: 8, rows: 4, width: 1.4, height: 0.6, orientation: Orientation::Vertical, origin: [0.0, 2.0, 0.0] };
    let cloth = client.submit_grid(grid, Submit { pinned: vec![0, 7], ..opts() }).unwrap();
    assert_eq!(cloth.state_key(), drape::wire::Keys::new("drape").client_state(&me, &cloth.id()), "the 1.4 per-cloth state key");
    let mut pos = vec![0f32; 96];
    let first = wait(&cloth, &mut pos);
    let st = wait(&cloth, &mut pos);
    assert!(st.tick > first.tick && st.vertex_count == 32);
    // a control, waited for and not
    let tick = common::pins_follow(&cloth, &mut pos, wait);
    cloth.move_pins(&[0], &[0.0, 2.6, 0.0], false).unwrap();
    let t0 = Instant::now();
    while pos[0..3].iter().zip([0.0f32, 2.6, 0.0]).any(|(p, t)| (p - t).abs() > 1e-6) {
        assert!(t0.elapsed() < common::WAIT, "the unwaited pin move is not applied: {:?}", &pos[0..3]);
        wait(&cloth, &mut pos);
    }
    // a bundled cloth and a batch control (control_batch on the client's key)
    let state = StateOptions { bundle: Some(true), ..Default::default() };
    let bundled = client.submit_grid(Grid::new(6, 6), Submit { pinned: vec![0, 5], state: Some(state), ..opts() }).unwrap();
    assert!(bundled.bundled());
    let mut bpos = vec![0f32; 108];
    wait(&bundled, &mut bpos);
    let mut batch = client.batch();
    batch.move_pins(&bundled, &[0], &[0.0, 1.0, 0.5]).move_pins(&cloth, &[7], &[1.5, 2.0, 0.0]);
    let results = client.send_batch(batch, true).unwrap().unwrap();
    assert!(results.iter().all(|r| r.is_ok()), "{results:?}");
    // the server-wide keys answer nothing on this server (a 1.3 client's fate)
    let cfg = {
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"peer\"").unwrap();
        c.insert_json5("connect/endpoints", &format!("[{:?}]", s.endpoint)).unwrap();
        c.insert_json5("listen/endpoints", "[]").unwrap();
        c.insert_json5("scouting/multicast/enabled", "false").unwrap();
        c
    };
    let raw = zenoh::open(cfg).wait().unwrap();
    let payload = drape::wire::msg::encode_info(1);
    let count = |key: String| raw.get(key).payload(payload.clone()).timeout(Duration::from_secs(2)).wait().unwrap().iter().count();
    let t0 = Instant::now();
    let info = loop {
        // asked until answered: the routes to the server's queryables take their time to come
        let n = count(format!("drape/server/{}/info", s.id));
        if n > 0 || t0.elapsed() > common::WAIT {
            break n;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(info, 1, "info stays server-wide");
    assert_eq!(count(format!("drape/server/{}/control", s.id)), 0, "no server-wide control under identity = keys");
    raw.close().wait().unwrap();
    // remove
    assert!(cloth.remove().unwrap() >= tick);
    bundled.remove().unwrap();
    std::thread::sleep(Duration::from_millis(200));
    while let Some(e) = client.poll_event(Duration::ZERO) {
        assert!(!matches!(e, Event::RequestFailed { .. }), "{e:?}");
    }
    client.close(true);
}

/// The C ABI against an `--identity keys` server, with the client id given (as a deployment
/// whose router binds it would): submit, a state, a control, remove.
#[test]
fn c_abi_identity_keys_server() {
    use drape::ffi::*;
    let Some(bin) = common::drape_bin() else { return };
    let s = common::start(&bin, &["--identity", "keys"]);
    let me = format!("c-abi-{}", std::process::id());
    unsafe {
        let client = common::c_open(&s, Some(me.as_str()));
        let grid = DrapeGrid { cols: 4, rows: 4, width: 0.0, height: 0.0, vertical: false, origin: [0.0; 3] };
        let pins = [0u32, 3];
        let copts = common::c_cloth_options(&pins, false);
        let mut cloth = std::ptr::null_mut();
        assert_eq!(drape_submit_grid(client, &grid, &copts, &mut cloth), DRAPE_OK);
        let mut pos = [0f32; 48];
        common::c_first_state(cloth, &mut pos, common::WAIT);
        let mut tick = 0u64;
        let idx = [0u32];
        let target = [0.0f32, 1.0, 0.0];
        assert_eq!(drape_cloth_move_pins(cloth, idx.as_ptr(), 1, target.as_ptr(), true, &mut tick), DRAPE_OK);
        assert!(tick > 0);
        assert_eq!(drape_cloth_remove(cloth, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(cloth);
        drape_client_close(client, true);
    }
}
