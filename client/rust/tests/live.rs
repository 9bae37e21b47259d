//! End-to-end tests against real `drape serve` processes on loopback (see tests/common): real
//! Zenoh, a real server, no mocks. Submissions of grids, meshes and OBJ text, states on single
//! keys and in bundles, controls waited for or not, batch control, errors, removal, and a
//! server killed under its cloths (reported, and resubmitted with the opt-in failover).
mod common;

use drape::client::{Client, ClientOptions, Cloth, Event};
use drape::wire::{Collider, Control, Encoding, ErrorCode, Grid, Orientation, StateOptions, Submit};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn shared() -> Option<&'static common::Server> {
    static S: OnceLock<Option<common::Server>> = OnceLock::new();
    S.get_or_init(|| common::drape_bin().map(|b| common::start(&b, &[]))).as_ref()
}

fn connect(servers: &[&common::Server], server_id: Option<&str>, failover: bool) -> Client {
    let opts = ClientOptions {
        connect: servers.iter().map(|s| s.endpoint.clone()).collect(),
        server_id: server_id.map(str::to_string),
        timeout: Duration::from_secs(10),
        failover,
        ..Default::default()
    };
    let client = Client::open(opts).expect("open");
    let t0 = Instant::now();
    for s in servers {
        while !client.servers(Duration::from_millis(500)).unwrap().contains(&s.id) {
            assert!(t0.elapsed() < common::START_TIMEOUT, "server {} not up; its log:\n{}", s.id, s.log_text());
            std::thread::sleep(Duration::from_millis(200));
        }
    }
    client
}

fn opts() -> Submit {
    Submit::new("", drape::wire::Shape::Grid(Grid::new(1, 1)))
}

fn wait(c: &Cloth, pos: &mut [f32]) -> drape::client::StateInfo {
    c.wait_state(pos, None, Duration::from_secs(5)).expect("read").expect("no state within 5 s")
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
    // Controls without waiting: nothing comes back but states.
    for k in 0..10 {
        cloth.move_pins(&[0], &[0.0, 2.5 + k as f32 * 0.01, 0.0], false).unwrap();
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
    let state = StateOptions { normals: Some(true), encoding: Some(Encoding::Quant16), bundle: None };
    let cloth = client.submit_obj(obj, Submit { pinned: vec![0, 1], state: Some(state), ..opts() }).unwrap();
    assert_eq!((cloth.vertex_count(), cloth.triangles()), (4, &[0u32, 1, 2, 0, 2, 3][..]));
    let (mut pos, mut nrm) = (vec![0f32; 12], vec![0f32; 12]);
    let st = cloth.wait_state(&mut pos, Some(&mut nrm), Duration::from_secs(5)).unwrap().unwrap();
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
    while t0.elapsed() < Duration::from_secs(5) && !matches!(ev, Some(Event::RequestFailed { .. })) {
        ev = client.poll_event(Duration::from_millis(100));
    }
    assert!(matches!(&ev, Some(Event::RequestFailed { handle: Some(h), error }) if *h == cloth.handle() && error.code == ErrorCode::InvalidValue), "{ev:?}");
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
        let state = StateOptions { encoding: Some(*e), bundle: Some(true), normals: None };
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

#[test]
fn lost_server_is_reported_and_failover_resubmits() {
    let Some(bin) = common::drape_bin() else { return };
    let (a, b) = (common::start(&bin, &[]), common::start(&bin, &[]));
    let plain = connect(&[&a], Some(&a.id), false);
    let fo = connect(&[&a, &b], Some(&a.id), true);
    let sub = || Submit { pinned: vec![0, 3], ..opts() };
    let lost = plain.submit_grid(Grid::new(4, 4), sub()).unwrap();
    let moved = fo.submit_grid(Grid::new(4, 4), sub()).unwrap();
    let bundled = fo.submit_grid(Grid::new(4, 4), Submit { state: Some(StateOptions { bundle: Some(true), ..Default::default() }), ..sub() }).unwrap();
    let mut pos = vec![0f32; 48];
    for c in [&lost, &moved, &bundled] {
        wait(c, &mut pos);
        assert_eq!(c.server(), a.id);
    }
    let (old, handle) = (moved.id(), moved.handle());
    a.kill();
    let until = |client: &Client, f: &dyn Fn(&Event) -> bool| {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(15) {
            if let Some(e) = client.poll_event(Duration::from_millis(200)) {
                if f(&e) {
                    return e;
                }
            }
        }
        panic!("event not seen within 15 s");
    };
    until(&plain, &|e| matches!(e, Event::ServerLost { server } if *server == a.id));
    until(&plain, &|e| matches!(e, Event::ClothLost { handle, .. } if *handle == lost.handle()));
    assert_eq!(lost.read_state(&mut pos, None).unwrap_err().code, ErrorCode::ServerLost);
    assert_eq!(lost.move_pins(&[0], &[0.0; 3], true).unwrap_err().code, ErrorCode::ServerLost);
    let mut pending = vec![moved.handle(), bundled.handle()]; // resubmitted in any order
    while !pending.is_empty() {
        let e = until(&fo, &|e| matches!(e, Event::ClothResubmitted { handle, .. } if pending.contains(handle)));
        let Event::ClothResubmitted { handle, server, .. } = e else { unreachable!() };
        assert_eq!(server, b.id);
        pending.retain(|h| *h != handle);
    }
    assert_eq!((moved.handle(), moved.server()), (handle, b.id.clone()));
    assert_ne!(moved.id(), old);
    for c in [&moved, &bundled] {
        let st = wait(c, &mut pos);
        assert!(st.tick >= c.first_tick(), "states come from the new server");
        assert!(c.move_pins(&[0], &[0.0, 0.5, 0.0], true).unwrap().is_some());
    }
    assert_eq!(fo.server_id().unwrap(), b.id, "new submissions go to the live server");
    lost.remove().unwrap();
    fo.close(true);
    plain.close(true);
}
