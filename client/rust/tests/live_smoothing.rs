//! Rendering between states against a real `drape serve` on loopback (tests/common): a 144 Hz
//! renderer whose cloth's pins are moved every frame draws with `Cloth::sample` (Rust) and
//! `drape_cloth_sample` (C ABI), and the cloth moves in every frame, where the newest state read
//! raw repeats in most frames. The render times are given (`now_ns`), not read from the machine's
//! clock: a 144 Hz grid on the server's clock, each frame drawn once the state it lies after has
//! arrived (a wait for an event), so a busy machine's pace changes nothing that is judged.
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
const PERIOD_NS: i64 = 1_000_000_000 / 144;

/// The pins' targets at time `t` (s): a circle of 0.3 m radius, once per 2 s.
fn targets(t: f64) -> [f32; 6] {
    let (s, c) = ((t * std::f64::consts::PI).sin() as f32 * 0.3, (t * std::f64::consts::PI).cos() as f32 * 0.3);
    [s, 2.0 + c, 0.0, 1.0 + s, 2.0 + c, 0.0]
}

/// A cloth as the frame loop drives it: `next` waits (up to `common::WAIT`, an event that must
/// come) for the next state read in order, giving its (tick, server time); `offset` is the
/// cloth's clock offset; `frame(t, now_ns)` moves the pins to `targets(t)`, samples at render
/// time `now_ns` and reads the newest state raw, giving (sampled, raw positions, the raw one's tick).
struct Driven<N, O, F> {
    next: N,
    offset: O,
    frame: F,
}

/// Run a 144 Hz frame loop for `FRAMES` frames on given render times: for each state read that
/// follows its predecessor (tick + 1, so the pair that `sample` interpolates is known), the
/// frames of the grid whose render time lies in the state's interval `[server, server + span)`
/// (the default delay, one span, puts them between the two states) are drawn at once, at
/// `now_ns` = render time + clock offset. A frame drawn after a newer state came (the pair moved
/// on: the raw tick tells) is not counted. Returns the counted frames (of those after the first)
/// where the sampled positions and the raw newest state stood still.
fn render<N, O, F>(mut d: Driven<N, O, F>) -> (usize, usize)
where
    N: FnMut() -> (u64, u64),
    O: FnMut() -> i64,
    F: FnMut(f64, u64) -> (Vec<f32>, Vec<f32>, u64),
{
    let (mut frames, mut prev, mut states) = (Vec::new(), None::<(u64, u64)>, 0usize);
    let (mut r0, mut r) = (None::<i64>, 0i64); // the grid's origin and next render time (server ns)
    while frames.len() < FRAMES {
        states += 1;
        assert!(states < 20 * FRAMES, "{} of {FRAMES} frames counted in {states} states", frames.len());
        let (tick, server) = (d.next)();
        let Some((ptick, pserver)) = prev.replace((tick, server)) else { continue };
        if tick != ptick + 1 {
            continue; // a state missed: the pair sampled is not known
        }
        let (server, span) = (server as i64, server as i64 - pserver as i64);
        if r0.is_none() {
            (r0, r) = (Some(server), server);
        }
        let origin = r0.unwrap();
        if r < server {
            r += PERIOD_NS * ((server - r + PERIOD_NS - 1) / PERIOD_NS); // the grid's next time in it
        }
        let offset = (d.offset)();
        while r < server + span && frames.len() < FRAMES {
            let (smooth, raw, now_tick) = (d.frame)((r - origin) as f64 / 1e9, (r + offset) as u64);
            if now_tick != tick {
                break; // a newer state came meanwhile: this frame sampled another pair
            }
            frames.push((smooth, raw));
            r += PERIOD_NS;
        }
    }
    let still = |k: usize| frames.windows(2).filter(|w| if k == 0 { w[0].0 == w[1].0 } else { w[0].1 == w[1].1 }).count();
    (still(0), still(1))
}

/// The sampled frames never stand still (the whole cloth compared): each render time lies
/// inside its state's interval, at its own fraction of it; the raw newest state repeats in the
/// frames of an interval after the first (144 / 60: most of them).
fn check(what: &str, (smooth, raw): (usize, usize)) {
    eprintln!("{what}: {FRAMES} frames at 144 Hz: sampled still in {smooth}, raw newest state still in {raw}");
    assert!(raw > FRAMES / 3, "{what}: 144 / 60: most raw frames repeat a state ({raw})");
    assert_eq!(smooth, 0, "{what}: a sampled frame moves (still in {smooth} of {FRAMES}; raw {raw})");
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
        assert!(t0.elapsed() < common::WAIT, "no state");
    }
    let mut buf = vec![0f32; n];
    let counted = render(Driven {
        next: || {
            let st = cloth.wait_state(&mut buf, None, common::WAIT).unwrap().expect("a state");
            (st.tick, st.server_time_ns)
        },
        offset: || cloth.clock_offset_ns().unwrap(),
        frame: |t, now_ns| {
            cloth.move_pins(&PINS, &targets(t), false).unwrap();
            assert!(cloth.sample(Some(now_ns), None, false, &mut pos).unwrap());
            let st = common::latest(&cloth, &mut raw);
            (pos.clone(), raw.clone(), st.tick)
        },
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
            assert!(t0.elapsed() < common::WAIT, "no state");
        }
        assert_eq!(drape_cloth_sample(cloth, 0, -1, false, pos.as_mut_ptr(), n - 1), DRAPE_E_INVALID_VALUE, "a short buffer");
        let mut buf = vec![0f32; n];
        let counted = render(Driven {
            next: || {
                let mut info: DrapeStateInfo = std::mem::zeroed();
                let wait = common::WAIT.as_millis() as u32;
                let rc = drape_cloth_wait_state(cloth, buf.as_mut_ptr(), n, std::ptr::null_mut(), 0, wait, &mut info);
                assert_eq!(rc, DRAPE_OK, "a state");
                (info.tick, info.server_time_ns)
            },
            offset: || {
                let mut offset = 0i64;
                assert_eq!(drape_cloth_clock_offset(cloth, &mut offset), DRAPE_OK);
                offset
            },
            frame: |t, now_ns| {
                mv(t);
                assert_eq!(drape_cloth_sample(cloth, now_ns, -1, false, pos.as_mut_ptr(), n), DRAPE_OK);
                let mut info: DrapeStateInfo = std::mem::zeroed();
                common::c_latest(cloth, &mut raw, &mut info);
                (pos.clone(), raw.clone(), info.tick)
            },
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
