//! Predictive cloths (protocol 1.5, PROTOCOL.md 9.2) against a real `drape serve` on loopback
//! (tests/common), whose keyframes come only when a stream starts and when asked for
//! (`--keyframe-interval 100000`): a predictive cloth's states, decoded on delivery, are within
//! step / 2 of a float32 twin's at the same age; a forced gap (the stream forgotten, as a late
//! joiner's) shows nothing new until the keyframe the client asks for arrives, then decodes
//! again; the same in a bundle; a float32 cloth switched to the encoding by control; and the
//! same through the C ABI.
mod common;

use drape::client::{Client, Cloth, Counters};
use drape::wire::{grid_geometry, Control, Encoding, Grid, Orientation, Shape, StateOptions, Submit};
use common::twin::{last_age, max_diff, read_n_by_age, read_to_age, ByAge};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn shared() -> Option<&'static common::Server> {
    static S: OnceLock<Option<common::Server>> = OnceLock::new();
    S.get_or_init(|| common::drape_bin().map(|b| common::start(&b, &["--keyframe-interval", "100000"]))).as_ref()
}

const STEP: f64 = 0.002;
const COLS: u32 = 12;

fn grid() -> Grid {
    Grid { cols: COLS, rows: COLS, width: 1.0, height: 1.0, orientation: Orientation::Vertical, origin: [0.0, 2.0, 0.0] }
}

fn submit(client: &Client, state: StateOptions) -> Cloth {
    let g = grid();
    let (rest, tris) = grid_geometry(g.cols, g.rows, g.width, g.height, g.orientation, g.origin).unwrap();
    let sub = Submit { pinned: vec![0, COLS - 1], state: Some(state), ..Submit::new("", Shape::Grid(g)) };
    client.submit_queued(sub, rest, tris, 1024).unwrap()
}

fn predictive(bundle: bool) -> StateOptions {
    StateOptions { encoding: Some(Encoding::Predictive), step: Some(STEP), bundle: bundle.then_some(true), ..Default::default() }
}

fn wait_counters(cloth: &Cloth, what: &str, ok: impl Fn(&Counters) -> bool) -> Counters {
    let t0 = Instant::now();
    let mut pos = vec![0f32; 3 * (COLS * COLS) as usize];
    loop {
        let k = cloth.state_counters();
        if ok(&k) {
            return k;
        }
        assert!(t0.elapsed() < common::WAIT, "{what}: {k:?}");
        let _ = cloth.wait_state(&mut pos, None, Duration::from_millis(20));
    }
}

#[test]
fn predictive_cloths_decode_resync_and_switch() {
    let Some(server) = shared() else { return };
    let client = common::connect(&[server], Some(&server.id), false);
    let twin = submit(&client, StateOptions::default());
    let pred = submit(&client, predictive(false));
    let bundled = submit(&client, predictive(true));
    assert!(bundled.bundled());

    // Decoded in order, each within step / 2 of the float32 twin's state of the same age.
    let (mut a, mut b, mut c) = (ByAge::new(), ByAge::new(), ByAge::new());
    let enc = read_n_by_age(&pred, 40, &mut a); // counted states, whatever the machine's pace
    read_to_age(&bundled, last_age(&a).unwrap(), &mut c); // as far as the states compared
    read_to_age(&twin, last_age(&a).unwrap(), &mut b);
    assert!(!enc.is_empty() && enc.iter().all(|e| *e == Encoding::Predictive), "{enc:?}");
    let (worst, n) = max_diff(&a, &b);
    let bound = (STEP / 2.0) as f32 * 1.001 + 1e-6;
    assert!(n >= 20, "only {n} states of the same age");
    eprintln!("predictive vs float32 twin: max {worst} m over {n} states (step {STEP})");
    assert!(worst <= bound, "predictive vs float32: {worst} m apart (step {STEP})");
    let (worst, n) = max_diff(&c, &b);
    assert!(n >= 20 && worst <= bound, "bundled predictive vs float32: {worst} m over {n} states");
    let moved = a.values().next().unwrap().1.iter().zip(&a.values().last().unwrap().1).any(|(x, y)| (x - y).abs() > 0.01);
    assert!(moved, "the cloth falls");
    let k = pred.state_counters();
    assert!(k.decoded >= 20 && k.keyframes >= 1, "{k:?}");
    assert_eq!(k.read + k.replaced + k.missed + k.unread + k.undecodable, k.ticks, "{k:?}");

    // A forced gap: nothing shown until the keyframe asked for; then it decodes again.
    for cloth in [&pred, &bundled] {
        let before = cloth.state_counters();
        let sent = client.keyframe_queries();
        cloth.forget_predictive_stream();
        let k = wait_counters(cloth, "a keyframe after the gap", |k| k.keyframes > before.keyframes && k.decoded > before.decoded + 5);
        assert!(k.undecodable > before.undecodable && k.keyframe_requests > before.keyframe_requests, "{k:?}");
        assert!(client.keyframe_queries() > sent, "the client counts the queries it sent");
        eprintln!("after the gap ({}): {k:?}", if cloth.bundled() { "bundled" } else { "own key" });
        assert_eq!(k.read + k.replaced + k.missed + k.unread + k.undecodable, k.ticks, "{k:?}");
    }
    let mut a2 = ByAge::new();
    read_n_by_age(&pred, 20, &mut a2);
    read_to_age(&twin, last_age(&a2).unwrap(), &mut b);
    let (worst, n) = max_diff(&a2, &b);
    assert!(n >= 10 && worst <= bound, "after the resync: {worst} m over {n} states");

    // A float32 cloth switched to the encoding by control (on a coarser grid).
    let state = StateOptions { encoding: Some(Encoding::Predictive), step: Some(2.0 * STEP), ..Default::default() };
    let tick = twin.control(Control { state: Some(state), ..Default::default() }, true).unwrap().unwrap();
    let k = wait_counters(&twin, "the switched cloth's states", |k| k.decoded >= 10);
    assert!(k.keyframes >= 1, "{k:?}");
    let mut pos = vec![0f32; 3 * (COLS * COLS) as usize];
    let st = common::latest(&twin, &mut pos);
    assert!(st.tick >= tick && st.encoding == Encoding::Predictive && pos.iter().all(|x| x.is_finite()));
    // Out of range: refused before sending.
    let bad = StateOptions { step: Some(0.5), ..Default::default() };
    assert!(twin.control(Control { state: Some(bad), ..Default::default() }, true).is_err());
    client.close(true);
}

#[test]
fn c_abi_predictive_cloth() {
    use drape::ffi::*;
    let Some(s) = shared() else { return };
    unsafe {
        let client = common::c_open(s, None);
        assert_eq!(drape_client_set_predictive_step(client, 0.5), DRAPE_E_INVALID_VALUE);
        assert_eq!(drape_client_set_predictive_step(client, STEP), DRAPE_OK);
        let grid = DrapeGrid { cols: 8, rows: 8, width: 0.0, height: 0.0, vertical: true, origin: [0.0, 2.0, 0.0] };
        let pins = [0u32, 7];
        let copts = DrapeClothOptions { encoding: DRAPE_ENCODING_PREDICTIVE, queue_size: 64, ..common::c_cloth_options(&pins, true) };
        let mut cloth = std::ptr::null_mut();
        assert_eq!(drape_submit_grid(client, &grid, &copts, &mut cloth), DRAPE_OK);
        let (mut pos, mut nrm) = (vec![0f32; 192], vec![0f32; 192]);
        let mut info: DrapeStateInfo = std::mem::zeroed();
        let mut first = None;
        for _ in 0..20 {
            let rc = drape_cloth_wait_state(cloth, pos.as_mut_ptr(), 192, nrm.as_mut_ptr(), 192, common::WAIT.as_millis() as u32, &mut info);
            assert_eq!(rc, DRAPE_OK);
            assert_eq!(info.encoding as i32, DRAPE_ENCODING_PREDICTIVE);
            assert!(info.has_normals && pos.iter().chain(&nrm).all(|x| x.is_finite()));
            first.get_or_insert(pos.clone());
        }
        // the cloth sags from its rest pose (by 10 mm within 20 ticks); measured from the rest pose,
        // not from the first state shown, which comes later in the motion when the subscription
        // missed the stream's first keyframe (a loaded machine: a gap, a keyframe asked for)
        let mut rest = vec![0f32; 192];
        let mut tris = vec![0u32; 6 * 49];
        assert_eq!(drape_cloth_rest_mesh(cloth, rest.as_mut_ptr(), 192, tris.as_mut_ptr(), tris.len()), DRAPE_OK);
        assert!(first.is_some() && rest.iter().zip(&pos).any(|(a, b)| (a - b).abs() > 0.005), "the cloth moves");
        let mut k = DrapePredictiveCounters::default();
        assert_eq!(drape_cloth_predictive_counters(cloth, &mut k), DRAPE_OK);
        assert!(k.decoded >= 20 && k.keyframes >= 1, "{k:?}");
        // a control re-gridding it: the next state is a keyframe
        let mut tick = 0u64;
        assert_eq!(drape_cloth_set_predictive(cloth, 2.0 * STEP, true, &mut tick), DRAPE_OK);
        assert_eq!(drape_cloth_set_predictive(cloth, 1.0, true, &mut tick), DRAPE_E_INVALID_VALUE);
        let t0 = Instant::now();
        loop {
            assert_eq!(drape_cloth_predictive_counters(cloth, &mut k), DRAPE_OK);
            if k.keyframes >= 2 {
                break;
            }
            assert!(t0.elapsed() < common::WAIT, "no keyframe after the new step: {k:?}");
            drape_cloth_wait_state(cloth, pos.as_mut_ptr(), 192, std::ptr::null_mut(), 0, 100, &mut info);
        }
        assert_eq!(drape_cloth_remove(cloth, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(cloth);
        drape_client_close(client, true);
    }
}
