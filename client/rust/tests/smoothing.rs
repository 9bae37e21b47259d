//! Rendering between states (`drape::smoothing`), on the inputs of the Python SDK's
//! `tests/client/test_smoothing.py` with the same expected numbers: interpolation a tick behind
//! the newest state, extrapolation past it, the render clock mapped onto the server's, and a
//! 144 Hz renderer that moves the cloth in every frame where the raw states would repeat.
use drape::smoothing::{sample_into, Frame, ServerClock, MAX_AHEAD};

const TICK: u64 = 16_666_667; // ns at 60 Hz

/// A state as the Python test's `_state`: two vertices at x, its server and receive times.
struct St {
    server: u64,
    receive: u64,
    pos: [f32; 6],
}

fn state(tick: u64, x: f32, latency_ns: u64) -> St {
    let offset_ns = 123_456_789;
    let server = 1_000_000_000_000 + tick * TICK;
    St { server, receive: server + offset_ns + latency_ns, pos: [x, 0.0, 0.0, x, 1.0, 0.0] }
}

fn frame(s: &St) -> Frame<'_> {
    Frame { server_time_ns: s.server, positions: &s.pos }
}

/// The x of both vertices sampled at `at` (None before any state).
fn xs(prev: Option<&St>, last: Option<&St>, at: u64, delay: Option<i64>, extrapolate: bool) -> Option<[f32; 2]> {
    let mut out = [f32::NAN; 6];
    sample_into(prev.map(frame), last.map(frame), at as i64, delay, extrapolate, MAX_AHEAD, &mut out).then_some([out[0], out[3]])
}

fn close(got: Option<[f32; 2]>, want: f32, atol: f32) {
    let got = got.expect("a state");
    for g in got {
        assert!((g - want).abs() <= atol + 1e-7 * want.abs(), "{got:?} != {want}");
    }
}

#[test]
fn interpolation_runs_one_tick_behind_and_holds_at_the_ends() {
    let (a, b) = (state(10, 1.0, 5_000_000), state(11, 2.0, 5_000_000));
    let at = b.server; // a render time at the newest state: shows a, one tick behind
    close(xs(Some(&a), Some(&b), at, None, false), 1.0, 0.0);
    close(xs(Some(&a), Some(&b), at + TICK / 2, None, false), 1.5, 1e-6);
    close(xs(Some(&a), Some(&b), at + 5 * TICK, None, false), 2.0, 0.0); // held: no state past b yet
    close(xs(Some(&a), Some(&b), at - 5 * TICK, None, false), 1.0, 0.0);
    close(xs(Some(&a), Some(&b), at, Some(0), false), 2.0, 0.0);
    assert_eq!(xs(None, None, at, None, false), None);
    let mut out = [0f32; 6];
    assert!(sample_into(None, Some(frame(&b)), at as i64, None, false, MAX_AHEAD, &mut out));
    assert_eq!(out, b.pos);
}

#[test]
fn extrapolation_carries_the_velocity_past_the_newest_state_up_to_a_cap() {
    let (a, b) = (state(10, 1.0, 5_000_000), state(11, 2.0, 5_000_000));
    close(xs(Some(&a), Some(&b), b.server + TICK / 2, None, true), 2.5, 1e-6);
    close(xs(Some(&a), Some(&b), b.server + 10 * TICK, None, true), 3.0, 0.0);
}

#[test]
fn the_server_clock_is_the_smallest_offset_seen_lately() {
    let mut clock = ServerClock::new(4);
    assert_eq!(clock.to_server(5), None);
    for (t, lat) in [9_000_000, 5_000_000, 7_000_000].into_iter().enumerate() {
        let s = state(t as u64, 0.0, lat);
        clock.observe(s.receive, s.server);
    }
    assert_eq!(clock.offset_ns(), Some(123_456_789 + 5_000_000));
    for t in 3..7 {
        // the fast one leaves the window
        let s = state(t, 0.0, 8_000_000);
        clock.observe(s.receive, s.server);
    }
    assert_eq!(clock.offset_ns(), Some(123_456_789 + 8_000_000));
    assert_eq!(clock.to_server(clock.offset_ns().unwrap() as u64 + 42), Some(42));
}

#[test]
fn a_144_hz_renderer_moves_the_cloth_every_frame() {
    // states at 60 Hz, frames at 144 Hz: drawn raw, most frames repeat the newest state; drawn
    // with sample_into, every frame differs from the one before
    let states: Vec<St> = (0..60).map(|t| state(t, 0.01 * t as f32, 5_000_000)).collect();
    let mut clock = ServerClock::default();
    let frame_ns = 1_000_000_000 / 144;
    let start = states[2].receive;
    let (mut raw, mut smooth) = (Vec::new(), Vec::new());
    let mut k = 0;
    for f in 0..120 {
        // 0.83 s: within the states' second
        let now = start + f * frame_ns;
        while k + 1 < states.len() && states[k + 1].receive <= now {
            k += 1;
            clock.observe(states[k].receive, states[k].server);
        }
        raw.push(states[k].pos[0]);
        let at = clock.to_server(now).unwrap();
        let mut out = [0f32; 6];
        assert!(sample_into(Some(frame(&states[k - 1])), Some(frame(&states[k])), at, None, false, MAX_AHEAD, &mut out));
        smooth.push(out[0]);
    }
    let still = |v: &[f32]| v.windows(2).filter(|w| w[0] == w[1]).count();
    assert!(still(&raw) > 60, "144 / 60: more than half of the frames repeat a state");
    assert_eq!(still(&smooth), 0);
    assert!(smooth.windows(2).all(|w| w[1] >= w[0]), "never backwards");
}
