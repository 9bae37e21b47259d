//! Rates per subscriber (protocol 1.8, PROTOCOL.md 9.3) against a real `drape serve` on loopback
//! (tests/common; `--no-device-encode`: decimated predictive streams are coded on the host path)
//! : with the client's rate at every 2nd state a predictive cloth receives a 30 Hz stream, even
//! ticks only, each state within step / 2 of a float32 twin's (taken at full rate) at the same
//! age; `Cloth::set_rate` switches it to every 3rd (make before break, a keyframe on the new
//! key); the bundle the same with `Client::set_bundle_rate`; and the C ABI's rate functions (1.9:
//! `DRAPE_RATE_TWELFTH`, two states 12 ticks apart).
mod common;

use drape::client::{Client, Cloth, Rate};
use drape::wire::{grid_geometry, Encoding, Grid, Orientation, Shape, StateOptions, Submit};
use common::twin::{last_age, max_diff, n_by_age, to_age};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn shared() -> Option<&'static common::Server> {
    static S: OnceLock<Option<common::Server>> = OnceLock::new();
    S.get_or_init(|| common::drape_bin().map(|b| common::start(&b, &["--no-device-encode", "--keyframe-interval", "30"])))
        .as_ref()
}

const STEP: f64 = 0.002;
const COLS: u32 = 10;
const N: usize = 3 * (COLS * COLS) as usize;

fn submit(client: &Client, state: StateOptions) -> Cloth {
    let g = Grid { cols: COLS, rows: COLS, width: 1.0, height: 1.0, orientation: Orientation::Vertical, origin: [0.0, 2.0, 0.0] };
    let (rest, tris) = grid_geometry(g.cols, g.rows, g.width, g.height, g.orientation, g.origin).unwrap();
    let sub = Submit { pinned: vec![0, COLS - 1], state: Some(state), ..Submit::new("", Shape::Grid(g)) };
    client.submit_queued(sub, rest, tris, 1024).unwrap()
}

fn predictive(bundle: bool) -> StateOptions {
    StateOptions { encoding: Some(Encoding::Predictive), step: Some(STEP), bundle: bundle.then_some(true), ..Default::default() }
}

fn bound() -> f32 {
    (STEP / 2.0) as f32 * 1.001 + 1e-6
}

/// The states read after a switch to `k`: once the first of the new key's arrived, every tick a
/// multiple of `k`; within half a step of the twin.
fn check_switched(cloth: &Cloth, twin: &Cloth, k: u64, what: &str) {
    let t0 = Instant::now();
    let before = cloth.state_counters();
    loop {
        let c = cloth.state_counters();
        if c.keyframes > before.keyframes && c.decoded > before.decoded + 3 {
            break;
        }
        assert!(t0.elapsed() < common::WAIT, "{what}: no keyframe on the new key: {c:?}");
        let _ = cloth.wait_state(&mut vec![0f32; N], None, Duration::from_millis(20));
    }
    let _ = cloth.latest_state(&mut vec![0f32; N], None); // drop what came before the switch
    let got = n_by_age(cloth, 12); // counted states, whatever the machine's pace
    let twin_states = to_age(twin, last_age(&got).unwrap()); // as far as the states compared
    assert!(got.values().all(|(t, _)| t % k == 0), "{what}: ticks {:?}", got.values().map(|v| v.0).collect::<Vec<_>>());
    let (worst, n) = max_diff(&got, &twin_states);
    eprintln!("{what}: max {worst} m from the float32 twin over {n} states");
    assert!(n >= 5 && worst <= bound(), "{what}: {worst} m over {n} states");
}

#[test]
fn a_30_hz_stream_within_half_a_step_and_switches() {
    let Some(server) = shared() else { return };
    let client = common::connect(&[server], Some(&server.id), false);
    let twin = submit(&client, StateOptions::default()); // full rate: every age
    client.set_rate(Rate::Every(2)).unwrap(); // later submissions and the bundle: every 2nd state
    let pred = submit(&client, predictive(false));
    let bundled = submit(&client, predictive(true));
    assert_eq!((pred.rate_counters().rate, twin.rate_counters().rate, client.bundle_rate_counters().rate), (2, 1, 2));

    // 30 Hz, even ticks only, each within step / 2 of the twin at the same age
    let a = n_by_age(&pred, 40); // counted states, whatever the machine's pace
    let (c, b) = (to_age(&bundled, last_age(&a).unwrap()), to_age(&twin, last_age(&a).unwrap())); // as far as `a`
    assert!(a.values().all(|(t, _)| t % 2 == 0) && c.values().all(|(t, _)| t % 2 == 0), "even ticks only");
    let (worst, n) = max_diff(&a, &b);
    eprintln!("every 2nd predictive state vs float32 twin: max {worst} m over {n} states (step {STEP})");
    assert!(n >= 20 && worst <= bound(), "{worst} m apart over {n} states");
    let (worst, n) = max_diff(&c, &b);
    assert!(n >= 3 && worst <= bound(), "bundled: {worst} m over {n} states");
    let k = pred.state_counters();
    assert_eq!(k.read + k.replaced + k.missed + k.unread + k.undecodable, k.ticks, "{k:?}");
    assert!(k.missed * 4 <= k.ticks, "counted at 30 Hz, not as every other tick missed: {k:?}");

    // switched by hand: every 3rd state, the new key's stream from a keyframe
    pred.set_rate(3).unwrap();
    assert_eq!(pred.rate_counters().rate, 3);
    check_switched(&pred, &twin, 3, "own key at every 3rd");
    client.set_bundle_rate(3).unwrap();
    check_switched(&bundled, &twin, 3, "bundle at every 3rd");
    assert!(bundled.set_rate(2).is_err(), "a bundled cloth takes its bundle's rate");
    assert!(pred.set_rate(4).is_err());
    pred.set_rate(1).unwrap();
    check_switched(&pred, &twin, 1, "own key back at every state");
    client.close(true);
}

#[test]
fn c_abi_rates() {
    use drape::ffi::*;
    let Some(s) = shared() else { return };
    unsafe {
        let client = common::c_open(s, None);
        assert_eq!(drape_client_set_rate(client, 7), DRAPE_E_INVALID_VALUE);
        assert_eq!(drape_client_set_rate(client, DRAPE_RATE_HALF), DRAPE_OK);
        let grid = DrapeGrid { cols: 8, rows: 8, width: 0.0, height: 0.0, vertical: true, origin: [0.0, 2.0, 0.0] };
        let pins = [0u32, 7];
        let copts = DrapeClothOptions { queue_size: 64, ..common::c_cloth_options(&pins, false) };
        let mut cloth = std::ptr::null_mut();
        assert_eq!(drape_submit_grid(client, &grid, &copts, &mut cloth), DRAPE_OK);
        let mut pos = vec![0f32; 192];
        let mut info: DrapeStateInfo = std::mem::zeroed();
        for _ in 0..10 {
            assert_eq!(drape_cloth_wait_state(cloth, pos.as_mut_ptr(), 192, std::ptr::null_mut(), 0, common::WAIT.as_millis() as u32, &mut info), DRAPE_OK);
            assert_eq!(info.tick % 2, 0, "every 2nd state");
        }
        let mut k = DrapeRateCounters::default();
        assert_eq!(drape_cloth_rate_counters(cloth, &mut k), DRAPE_OK);
        assert_eq!((k.rate, k.auto_), (DRAPE_RATE_HALF, false));
        assert_eq!(drape_cloth_set_rate(cloth, DRAPE_RATE_AUTO), DRAPE_E_INVALID_VALUE, "auto is a client-wide option");
        assert_eq!(drape_cloth_set_rate(cloth, DRAPE_RATE_THIRD), DRAPE_OK);
        let t0 = Instant::now();
        loop {
            assert_eq!(drape_cloth_wait_state(cloth, pos.as_mut_ptr(), 192, std::ptr::null_mut(), 0, common::WAIT.as_millis() as u32, &mut info), DRAPE_OK);
            if info.tick % 3 == 0 && info.tick % 2 != 0 {
                break; // a state of the new key only
            }
            assert!(t0.elapsed() < common::WAIT, "no state of every 3rd");
        }
        // 1.9: every 12th state (5 Hz), two in a row 12 ticks apart
        assert_eq!(drape_cloth_set_rate(cloth, DRAPE_RATE_TWELFTH), DRAPE_OK);
        let (t0, mut last) = (Instant::now(), 0);
        loop {
            assert_eq!(drape_cloth_wait_state(cloth, pos.as_mut_ptr(), 192, std::ptr::null_mut(), 0, common::WAIT.as_millis() as u32, &mut info), DRAPE_OK);
            if info.tick % 12 == 0 && last != 0 && info.tick == last + 12 {
                break;
            }
            last = info.tick;
            assert!(t0.elapsed() < common::WAIT, "no two states of every 12th");
        }
        assert_eq!(drape_cloth_rate_counters(cloth, &mut k), DRAPE_OK);
        assert_eq!(k.rate, DRAPE_RATE_TWELFTH);
        assert_eq!(drape_client_set_rate(client, DRAPE_RATE_AUTO), DRAPE_OK);
        assert_eq!(drape_client_bundle_rate_counters(client, &mut k), DRAPE_OK);
        assert!(k.auto_ && k.rate == DRAPE_RATE_FULL, "{k:?}");
        assert_eq!(drape_cloth_remove(cloth, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(cloth);
        drape_client_close(client, true);
    }
}
