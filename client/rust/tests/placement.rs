//! Protocol 1.4 against real `drape serve` processes (see tests/common): placement by load
//! (PROTOCOL.md 11.3) over two servers and the failover's choice of a server by the same rule
//! (11.1), and `moves` blocks (5.1.1) whose pins reach the states, from Rust and the C ABI.
mod common;

use drape::client::{Client, Cloth, Event, LossReason};
use drape::wire::reader::Reader;
use drape::wire::{Control, ErrorCode, Grid, Orientation, SceneRequest, Submit};
use std::collections::HashMap;
use std::time::{Duration, Instant};

/// An 8 x 4 vertical grid pinned at both ends of its top row (vertices 0 and 7).
fn cape(client: &Client) -> Cloth {
    let grid = Grid { cols: 8, rows: 4, width: 1.4, height: 0.6, orientation: Orientation::Vertical, origin: [0.0, 2.0, 0.0] };
    let sub = Submit { pinned: vec![0, 7], ..Submit::new("", drape::wire::Shape::Grid(Grid::new(1, 1))) };
    client.submit_grid(grid, sub).expect("submit")
}

/// Targets of pins 0 and 7 for cloth `j`: distinct per cloth and per `round`.
fn targets(j: usize, round: usize) -> [f32; 6] {
    let (x, y) = (j as f32 * 0.1, 2.5 + round as f32 * 0.1);
    [x, y, 0.2, x + 1.5, y, 0.2]
}

/// Reads `c`'s states until the one of `tick` (or later): its pins 0 and 7 are at `want` (to
/// within 1 float32 ulp per coordinate, PROTOCOL.md section 5).
fn pins_reach(c: &Cloth, tick: u64, want: &[f32; 6]) {
    let mut pos = vec![0f32; 96];
    let t0 = Instant::now();
    loop {
        let st = c.wait_state(&mut pos, None, common::WAIT).expect("read").expect("a state");
        if st.tick >= tick {
            let got = [pos[0], pos[1], pos[2], pos[21], pos[22], pos[23]];
            assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() <= 1e-6), "cloth {}: pins at {got:?}, want {want:?}", c.handle());
            return;
        }
        assert!(t0.elapsed() < common::WAIT, "cloth {}: no state of tick {tick}", c.handle());
    }
}

/// A counter of the server's stats (PROTOCOL.md 10), waiting up to `common::WAIT` for one >= `least`.
fn stat_reaches(client: &Client, server: &str, key: &str, least: u64) -> u64 {
    let t0 = Instant::now();
    loop {
        let v = client.stats(server).and_then(|m| Reader::new(&m, "").u64(key, false).ok().flatten()).unwrap_or(0);
        if v >= least || t0.elapsed() > common::WAIT {
            return v;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Placement (11.3): a client with no server id spreads 8 cloths over two servers by their
/// load; after a `kill -9` of one, the failover (11.1) brings every cloth of it back on the
/// survivor, with the pin targets last sent by a moves block.
#[test]
fn placement_spreads_and_failover_gathers() {
    let Some(bin) = common::drape_bin() else { return };
    let (a, b) = (common::start(&bin, &[]), common::start(&bin, &[]));
    let client = common::connect(&[&a, &b], None, true);
    // Both servers' first stats publications (a placement waits 1.5 s at most for missing ones,
    // then ranks a server without stats last: a slow start must not decide this test).
    let t0 = Instant::now();
    while client.stats(&a.id).is_none() || client.stats(&b.id).is_none() {
        assert!(t0.elapsed() < common::START_TIMEOUT, "no stats from {} or {}", a.id, b.id);
        std::thread::sleep(Duration::from_millis(100));
    }
    let cloths: Vec<Cloth> = (0..8).map(|_| cape(&client)).collect();
    let mut per_server: HashMap<String, usize> = HashMap::new();
    for c in &cloths {
        *per_server.entry(c.server()).or_default() += 1;
    }
    let (on_a, on_b) = (per_server.get(&a.id).copied().unwrap_or(0), per_server.get(&b.id).copied().unwrap_or(0));
    assert_eq!(on_a + on_b, 8, "{per_server:?}");
    // each submission counts where it went until that server's stats do (a stats publication
    // racing a reply may shift one cloth)
    assert!(on_a >= 3 && on_b >= 3, "8 cloths not spread by load over {} and {}: {per_server:?}", a.id, b.id);
    // one moves block per server, waited for
    let all: Vec<f32> = (0..8).flat_map(|j| targets(j, 0)).collect();
    let ticks = client.move_pins_many(&cloths, &[0, 7], &all, true).unwrap().unwrap();
    for (j, (c, t)) in cloths.iter().zip(&ticks).enumerate() {
        pins_reach(c, *t.as_ref().unwrap_or_else(|e| panic!("cloth {j}: {e}")), &targets(j, 0));
    }
    let gone: Vec<u64> = cloths.iter().filter(|c| c.server() == a.id).map(Cloth::handle).collect();
    a.kill();
    let mut pending = gone.clone();
    let t0 = Instant::now();
    while !pending.is_empty() {
        assert!(t0.elapsed() < common::WAIT, "cloths {pending:?} not resubmitted");
        if let Some(Event::ClothResubmitted { handle, server, old_server, reason, kept, .. }) = client.poll_event(Duration::from_millis(200)) {
            assert_eq!((&server, &old_server, reason, kept), (&b.id, &a.id, LossReason::ServerLost, false));
            pending.retain(|h| *h != handle);
        }
    }
    for (j, c) in cloths.iter().enumerate() {
        assert_eq!(c.server(), b.id, "cloth {j} is on the survivor");
        // the resubmitted ones start there with the targets of the last moves block re-sent
        let tick = c.control(Control::default(), true).unwrap().unwrap();
        pins_reach(c, tick, &targets(j, 0));
    }
    assert_eq!(client.server_id().unwrap(), b.id);
    client.close(true);
}

/// Moves blocks (5.1.1) to a 1.4 server: `move_pins_many` (waited for and not), a batch whose
/// pins-only items go as a block, refused moves reported per cloth, and the server's stats
/// counting the moves it received in blocks.
#[test]
fn moves_blocks_reach_the_states() {
    let Some(bin) = common::drape_bin() else { return };
    let s = common::start(&bin, &[]);
    let client = common::connect(&[&s], None, false);
    let cloths: Vec<Cloth> = (0..3).map(|_| cape(&client)).collect();
    assert!(cloths.iter().all(|c| c.server() == s.id), "the one live server is placed on");
    let before = stat_reaches(&client, &s.id, "batch_moves", 0);
    let all: Vec<f32> = (0..3).flat_map(|j| targets(j, 1)).collect();
    let ticks = client.move_pins_many(&cloths, &[0, 7], &all, true).unwrap().unwrap();
    for (j, c) in cloths.iter().enumerate() {
        pins_reach(c, *ticks[j].as_ref().unwrap(), &targets(j, 1));
    }
    // a batch: the pins-only items sharing [0, 7] of cloths 1 and 2 go as one block; cloth 0's,
    // which has another item (gravity) in the batch, goes as an item with it
    let mut batch = client.batch();
    for (j, c) in cloths.iter().enumerate() {
        batch.move_pins(c, &[0, 7], &targets(j, 2));
    }
    batch.add(&cloths[0], Control { gravity: Some([0.0, -9.0, 0.0]), ..Default::default() });
    let results = client.send_batch(batch, true).unwrap().unwrap();
    assert!(results.iter().all(Result::is_ok), "{results:?}");
    for (j, c) in cloths.iter().enumerate() {
        pins_reach(c, *results[j].as_ref().unwrap(), &targets(j, 2));
    }
    // vertex 3 is not pinned: each move refused alone by the server (moves_failed)
    let refused = client.move_pins_many(&cloths, &[3], &[0.0, 1.0, 0.0].repeat(3), true).unwrap().unwrap();
    assert!(refused.iter().all(|r| r.as_ref().is_err_and(|e| e.code == ErrorCode::InvalidValue)), "{refused:?}");
    // bad input is refused before anything is sent
    let e = client.move_pins_many(&cloths, &[0, 0], &[0.0; 18], true).unwrap_err();
    assert_eq!(e.code, ErrorCode::InvalidValue, "{e}");
    for (idx, tgt) in [(&[0u32][..], vec![0.0f32; 3]), (&[][..], vec![]), (&[0][..], vec![f32::NAN; 9])] {
        let e = client.move_pins_many(&cloths, idx, &tgt, false).unwrap_err();
        assert_eq!(e.code, ErrorCode::InvalidValue, "{idx:?}: {e}");
    }
    let e = client.move_pins_many(&cloths[..1], &[40], &[0.0; 3], false).unwrap_err();
    assert_eq!(e.code, ErrorCode::IndexOutOfRange, "{e}");
    // not waited for: the states show it
    let all: Vec<f32> = (0..3).flat_map(|j| targets(j, 3)).collect();
    assert!(client.move_pins_many(&cloths, &[0, 7], &all, false).unwrap().is_none());
    let tick = cloths[2].control(Control::default(), true).unwrap().unwrap();
    for (j, c) in cloths.iter().enumerate() {
        pins_reach(c, tick, &targets(j, 3));
    }
    // 3 + 2 + 3 + 3 moves reached the server in blocks (the batch's two among them)
    let got = stat_reaches(&client, &s.id, "batch_moves", before + 11);
    assert_eq!(got, before + 11, "moves the server received in blocks");
    std::thread::sleep(Duration::from_millis(200));
    while let Some(e) = client.poll_event(Duration::ZERO) {
        assert!(!matches!(e, Event::RequestFailed { .. }), "{e:?}");
    }
    c_abi_moves(&s);
    client.close(true);
}

/// `drape_move_pins_many` and `drape_cloth_server` through the C ABI, placed by load (no server id).
fn c_abi_moves(s: &common::Server) {
    use drape::ffi::*;
    let connect = std::ffi::CString::new(s.endpoint.clone()).unwrap();
    let opts = common::c_client_options(&connect, None, None, 10_000, true);
    let pins = [0u32, 7];
    let grid = DrapeGrid { cols: 8, rows: 4, width: 1.4, height: 0.6, vertical: true, origin: [0.0, 2.0, 0.0] };
    let o = common::c_cloth_options(&pins, false);
    unsafe {
        let mut client = std::ptr::null_mut();
        assert_eq!(drape_client_open(&opts, &mut client), DRAPE_OK);
        let mut cloths = [std::ptr::null_mut(); 2];
        for c in cloths.iter_mut() {
            assert_eq!(drape_submit_grid(client, &grid, &o, c), DRAPE_OK);
        }
        let mut buf = [0 as std::ffi::c_char; 72];
        assert_eq!(drape_cloth_server(cloths[0], buf.as_mut_ptr(), buf.len()), DRAPE_OK);
        assert_eq!(std::ffi::CStr::from_ptr(buf.as_ptr()).to_str().unwrap(), s.id);
        let all: Vec<f32> = (0..2).flat_map(|j| targets(j, 4)).collect();
        let ptrs: Vec<*const DrapeCloth> = cloths.iter().map(|c| *c as *const DrapeCloth).collect();
        let (mut codes, mut ticks) = ([-1i32; 2], [0u64; 2]);
        assert_eq!(drape_move_pins_many(client, ptrs.as_ptr(), 2, pins.as_ptr(), 2, all.as_ptr(), true,
                                        codes.as_mut_ptr(), ticks.as_mut_ptr()), DRAPE_OK);
        assert_eq!(codes, [DRAPE_OK; 2]);
        let mut pos = vec![0f32; 96];
        for (j, c) in cloths.iter().enumerate() {
            loop {
                let mut info: DrapeStateInfo = std::mem::zeroed();
                assert_eq!(drape_cloth_wait_state(*c, pos.as_mut_ptr(), 96, std::ptr::null_mut(), 0, common::WAIT.as_millis() as u32, &mut info), DRAPE_OK);
                if info.tick >= ticks[j] {
                    let want = targets(j, 4);
                    assert!([pos[0], pos[1], pos[2], pos[21], pos[22], pos[23]].iter().zip(want).all(|(g, w)| (g - w).abs() <= 1e-6));
                    break;
                }
            }
        }
        // a refused move is reported per cloth; bad input fails the call
        let bad = [0.0f32, 1.0, 0.0, 0.0, 1.0, 0.0];
        assert_eq!(drape_move_pins_many(client, ptrs.as_ptr(), 2, [3u32].as_ptr(), 1, bad.as_ptr(), true,
                                        codes.as_mut_ptr(), std::ptr::null_mut()), DRAPE_OK);
        assert_eq!(codes, [DRAPE_E_INVALID_VALUE; 2]);
        assert_eq!(drape_move_pins_many(client, ptrs.as_ptr(), 2, pins.as_ptr(), 2, std::ptr::null(), true,
                                        std::ptr::null_mut(), std::ptr::null_mut()), DRAPE_E_INVALID_VALUE);
        for c in cloths {
            drape_cloth_free(c);
        }
        drape_client_close(client, true);
    }
}

/// A grid of `scene` (1.7): small, pinned at one corner.
fn scene_cloth(client: &Client, scene: Option<&str>) -> Cloth {
    let sub = Submit { pinned: vec![0], scene: scene.map(str::to_string), ..Submit::new("", drape::wire::Shape::Grid(Grid::new(1, 1))) };
    client.submit_grid(Grid::new(4, 4), sub).expect("submit")
}

/// Scenes (PROTOCOL.md 5.3's SDK note): a host's cloths of a scene, and then a guest's, all on one
/// server while cloths without a scene spread; after a `kill -9` of that server the whole scene is
/// on the survivor, founded again by the host (its members back: the guest's cloths got in, and a
/// guest's scene request is still `forbidden`).
#[test]
fn a_scene_stays_on_one_server_and_keeps_its_owner() {
    let Some(bin) = common::drape_bin() else { return };
    let (a, b) = (common::start(&bin, &[]), common::start(&bin, &[]));
    let host = common::connect(&[&a, &b], None, true);
    let guest = common::connect(&[&a, &b], None, true);
    let t0 = Instant::now();
    while [&host, &guest].iter().any(|c| c.stats(&a.id).is_none() || c.stats(&b.id).is_none()) {
        assert!(t0.elapsed() < common::START_TIMEOUT, "no stats from {} or {}", a.id, b.id);
        std::thread::sleep(Duration::from_millis(100));
    }
    let free: Vec<Cloth> = (0..4).map(|_| scene_cloth(&host, None)).collect();
    assert!(free.iter().any(|c| c.server() == a.id) && free.iter().any(|c| c.server() == b.id), "not spread");
    let mine: Vec<Cloth> = (0..3).map(|_| scene_cloth(&host, Some("m"))).collect();
    let members = SceneRequest { members: Some(vec![guest.client_id().to_string()]), ..SceneRequest::new("", "m") };
    assert_eq!(host.set_scene(members, None).unwrap().cloths, 3);
    let theirs: Vec<Cloth> = (0..2).map(|_| scene_cloth(&guest, Some("m"))).collect();
    let home = mine[0].server();
    assert!(mine.iter().chain(&theirs).all(|c| c.server() == home), "the scene is split");
    let (dead, alive) = if home == a.id { (&a, &b) } else { (&b, &a) };
    dead.kill();
    let t0 = Instant::now();
    while !mine.iter().chain(&theirs).all(|c| c.server() == alive.id) {
        assert!(t0.elapsed() < common::WAIT, "the scene's cloths not all on {}", alive.id);
        std::thread::sleep(Duration::from_millis(100));
    }
    let err = guest.set_scene(SceneRequest { colliders: Some(vec![]), ..SceneRequest::new("", "m") }, None).unwrap_err();
    assert_eq!(err.code, ErrorCode::Forbidden);
    let rep = host.set_scene(SceneRequest::new("", "m"), None).unwrap();
    assert_eq!((rep.owner.as_str(), rep.cloths, rep.members), (host.client_id(), 5, vec![guest.client_id().to_string()]));
    guest.close(true);
    host.close(true);
}
