//! Rendering between states against a real `drape serve` on loopback (tests/common): a 144 Hz
//! renderer whose cloth's pins are moved every frame (the pinned vertices are where the states
//! put them) draws with `Cloth::sample` (Rust) and `drape_cloth_sample` (C ABI), and the cloth
//! moves in (nearly) every frame, where the newest state read raw repeats in most frames. Only a
//! state that arrives later than the fastest (a busy shared machine) holds a frame, so the bound
//! allows a few; the counts are printed.
mod common;

use drape::wire::{Grid, Orientation, Shape, Submit};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn shared() -> Option<&'static common::Server> {
    static S: OnceLock<Option<common::Server>> = OnceLock::new();
    S.get_or_init(|| common::drape_bin().map(|b| common::start(&b, &[]))).as_ref()
}

const COLS: u32 = 6;
const PINS: [u32; 2] = [0, COLS - 1];
const FRAMES: usize = 216; // 1.5 s at 144 Hz

/// The pins' targets at time `t` (s): a circle of 0.3 m radius, once per 2 s.
fn targets(t: f64) -> [f32; 6] {
    let (s, c) = ((t * std::f64::consts::PI).sin() as f32 * 0.3, (t * std::f64::consts::PI).cos() as f32 * 0.3);
    [s, 2.0 + c, 0.0, 1.0 + s, 2.0 + c, 0.0]
}

/// Run a 144 Hz frame loop for `FRAMES` frames: `frame(t)` moves the pins and returns (the
/// sampled first vertex, the raw newest one); returns the frames (of those after the first)
/// where each stood still.
fn render(mut frame: impl FnMut(f64) -> ([f32; 3], [f32; 3])) -> (usize, usize) {
    let period = Duration::from_nanos(1_000_000_000 / 144);
    let t0 = Instant::now();
    let (mut smooth, mut raw) = (Vec::new(), Vec::new());
    for f in 0..FRAMES {
        let due = t0 + period * f as u32;
        if let Some(d) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(d);
        }
        let (s, r) = frame(t0.elapsed().as_secs_f64());
        smooth.push(s);
        raw.push(r);
    }
    let still = |v: &[[f32; 3]]| v.windows(2).filter(|w| w[0] == w[1]).count();
    (still(&smooth), still(&raw))
}

/// The sampled frames may stand still only where a state came later than the fastest one (the
/// one-tick delay leaves no margin for it: the newest state is held until the next arrives),
/// which a busy shared machine does in bursts (0-23 of 216 frames seen on the 2-core VM).
fn check(what: &str, (smooth, raw): (usize, usize)) {
    eprintln!("{what}: {FRAMES} frames at 144 Hz: sampled still in {smooth}, raw newest state still in {raw}");
    assert!(raw > FRAMES / 3, "{what}: 144 / 60: most raw frames repeat a state ({raw})");
    assert!(smooth * 5 <= FRAMES, "{what}: a sampled frame moves (still in {smooth} of {FRAMES})");
    assert!(smooth < raw / 4, "{what}: {smooth} vs {raw}");
}

fn grid() -> Grid {
    Grid { cols: COLS, rows: COLS, width: 1.0, height: 1.0, orientation: Orientation::Vertical, origin: [0.0, 2.0, 0.0] }
}

#[test]
fn a_144_hz_sampler_moves_every_frame() {
    let Some(s) = shared() else { return };
    let client = common::connect(&[s], Some(&s.id), false);
    let cloth = client.submit_grid(grid(), Submit { pinned: PINS.to_vec(), ..Submit::new("", Shape::Grid(grid())) }).unwrap();
    let n = 3 * cloth.vertex_count() as usize;
    let (mut pos, mut raw) = (vec![0f32; n], vec![0f32; n]);
    assert!(!cloth.sample(None, None, false, &mut pos).unwrap() || cloth.clock_offset_ns().is_some());
    // the pins moving, until states flow
    let t0 = Instant::now();
    while cloth.clock_offset_ns().is_none() || t0.elapsed() < Duration::from_millis(300) {
        cloth.move_pins(&PINS, &targets(t0.elapsed().as_secs_f64()), false).unwrap();
        std::thread::sleep(Duration::from_millis(7));
        assert!(t0.elapsed() < Duration::from_secs(20), "no state");
    }
    let counted = render(|t| {
        cloth.move_pins(&PINS, &targets(t), false).unwrap();
        assert!(cloth.sample(None, None, false, &mut pos).unwrap());
        cloth.latest_state(&mut raw, None).unwrap().expect("a state");
        ([pos[0], pos[1], pos[2]], [raw[0], raw[1], raw[2]])
    });
    check("Rust", counted);
    // extrapolated: no delay, still a state's positions or beyond, finite
    assert!(cloth.sample(None, None, true, &mut pos).unwrap());
    assert!(pos.iter().all(|x| x.is_finite()));
    let offset = cloth.clock_offset_ns().unwrap();
    assert!(offset.unsigned_abs() < 60_000_000_000, "one host's clocks: {offset} ns");
}

#[test]
fn c_abi_a_144_hz_sampler_moves_every_frame() {
    use drape::ffi::*;
    use std::ffi::CString;
    let Some(s) = shared() else { return };
    let (connect, server) = (CString::new(s.endpoint.clone()).unwrap(), CString::new(s.id.clone()).unwrap());
    let opts = common::c_client_options(&connect, Some(&server), None, 60_000, true);
    let grid = DrapeGrid { cols: COLS, rows: COLS, width: 1.0, height: 1.0, vertical: true, origin: [0.0, 2.0, 0.0] };
    let n = 3 * (COLS * COLS) as usize;
    let (mut pos, mut raw) = (vec![0f32; n], vec![0f32; n]);
    unsafe {
        let (mut client, mut cloth) = (std::ptr::null_mut(), std::ptr::null_mut());
        assert_eq!(drape_client_open(&opts, &mut client), DRAPE_OK);
        let o = common::c_cloth_options(&PINS, false);
        assert_eq!(drape_submit_grid(client, &grid, &o, &mut cloth), DRAPE_OK);
        let mut offset = 0i64;
        let t0 = Instant::now();
        let mv = |t: f64| assert_eq!(drape_cloth_move_pins(cloth, PINS.as_ptr(), PINS.len(), targets(t).as_ptr(), false, std::ptr::null_mut()), DRAPE_OK);
        while drape_cloth_clock_offset(cloth, &mut offset) != DRAPE_OK || t0.elapsed() < Duration::from_millis(300) {
            mv(t0.elapsed().as_secs_f64());
            std::thread::sleep(Duration::from_millis(7));
            assert!(t0.elapsed() < Duration::from_secs(20), "no state");
        }
        assert_eq!(drape_cloth_sample(cloth, 0, -1, false, pos.as_mut_ptr(), n - 1), DRAPE_E_INVALID_VALUE, "a short buffer");
        let counted = render(|t| {
            mv(t);
            assert_eq!(drape_cloth_sample(cloth, 0, -1, false, pos.as_mut_ptr(), n), DRAPE_OK);
            assert_eq!(drape_cloth_read_latest(cloth, raw.as_mut_ptr(), n, std::ptr::null_mut(), 0, std::ptr::null_mut()), DRAPE_OK);
            ([pos[0], pos[1], pos[2]], [raw[0], raw[1], raw[2]])
        });
        check("C ABI", counted);
        // a render time given explicitly: the client's clock (Unix ns), as the receive times
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64;
        assert_eq!(drape_cloth_sample(cloth, now, 0, true, pos.as_mut_ptr(), n), DRAPE_OK);
        assert!(pos.iter().all(|x| x.is_finite()));
        assert_eq!(drape_cloth_sample(cloth, now, 16_666_667, false, pos.as_mut_ptr(), n), DRAPE_OK);
        assert!(pos.iter().all(|x| x.is_finite()));
        assert_eq!(drape_cloth_remove(cloth, std::ptr::null_mut()), DRAPE_OK);
        drape_cloth_free(cloth);
        drape_client_close(client, true);
    }
}
