//! Rendering between states (no network): a renderer that draws faster than the server ticks
//! (144 Hz against 60) shows the same state for two or three frames unless it samples the cloth
//! at its own frame time. [`sample_into`] gives the positions at a render time from the last two
//! states: interpolated (the default: the render time runs `delay` behind the newest state, so it
//! almost always lies between two received states) or extrapolated (no delay added; a guess past
//! the newest state). The same semantics and arithmetic as the Python SDK's
//! `client/smoothing.py` (`tests/smoothing.rs` checks the same inputs give the same numbers).
//!
//! The render time is on the client's clock (Unix ns, as states' receive times); the states
//! carry the server's. [`ServerClock`] maps one to the other by the smallest `receive - server`
//! time seen lately: the clock offset plus the network's shortest delay.
//!
//! The latency it adds: interpolation shows the cloth as it was `delay` before the newest state
//! arrived (default one tick, 16.7 ms at 60 Hz); extrapolation adds none but overshoots where the
//! motion turns (by up to `velocity x max_ahead` state intervals).
use std::collections::VecDeque;

/// States whose `receive - server` difference a [`ServerClock`] keeps by default (2 s at 60 Hz).
pub const CLOCK_WINDOW: usize = 120;
/// How far extrapolation goes past the newest state by default, in state intervals.
pub const MAX_AHEAD: f64 = 1.0;

/// The client's clock as the server's: `server_ns = client_ns - offset`, the offset being the
/// smallest `receive - server` difference of the last `window` states.
#[derive(Debug, Clone)]
pub struct ServerClock {
    window: usize,
    diffs: VecDeque<i64>,
    min: Option<i64>,
}

impl Default for ServerClock {
    fn default() -> Self {
        Self::new(CLOCK_WINDOW)
    }
}

impl ServerClock {
    pub fn new(window: usize) -> Self {
        let window = window.max(1);
        ServerClock { window, diffs: VecDeque::with_capacity(window), min: None }
    }

    /// A state received at `receive_time_ns` (client clock) stamped `server_time_ns`; either 0
    /// (unknown) is ignored.
    pub fn observe(&mut self, receive_time_ns: u64, server_time_ns: u64) {
        if receive_time_ns == 0 || server_time_ns == 0 {
            return;
        }
        let d = receive_time_ns as i64 - server_time_ns as i64;
        if self.diffs.len() == self.window {
            let gone = self.diffs.pop_front();
            self.diffs.push_back(d);
            if gone == self.min {
                self.min = self.diffs.iter().copied().min();
                return;
            }
        } else {
            self.diffs.push_back(d);
        }
        self.min = Some(self.min.map_or(d, |m| m.min(d)));
    }

    /// Client time - server time of the fastest recent state (None before any).
    pub fn offset_ns(&self) -> Option<i64> {
        self.min
    }

    /// A client time (Unix ns) on the server's clock (None before any state).
    pub fn to_server(&self, client_ns: u64) -> Option<i64> {
        self.min.map(|m| client_ns as i64 - m)
    }
}

/// One state as [`sample_into`] reads it: its server time and positions (`3 n` floats).
#[derive(Debug, Clone, Copy)]
pub struct Frame<'a> {
    pub server_time_ns: u64,
    pub positions: &'a [f32],
}

/// The positions at server time `server_ns` (a render time already on the server's clock) from
/// the last two states `prev` and `last`, written into `out` (at least `last`'s length):
/// interpolated at `server_ns - delay_ns` (`delay_ns` None: the time between the two states, one
/// tick) and held at the ends; `extrapolate`: at `server_ns` itself, up to `max_ahead` state
/// intervals past `last`. False (nothing written) before any state; `last`'s positions when
/// there is one state only (or two that cannot be blended: not in time order, other sizes).
/// Panics if `out` is shorter than `last.positions`.
pub fn sample_into(prev: Option<Frame>, last: Option<Frame>, server_ns: i64, delay_ns: Option<i64>,
                   extrapolate: bool, max_ahead: f64, out: &mut [f32]) -> bool {
    let Some(last) = last else { return false };
    let n = last.positions.len();
    let out = &mut out[..n];
    let prev = match prev {
        Some(p) if last.server_time_ns > p.server_time_ns && p.positions.len() == n => p,
        _ => {
            out.copy_from_slice(last.positions);
            return true;
        }
    };
    let span = (last.server_time_ns - prev.server_time_ns) as i64;
    let t = if extrapolate { server_ns } else { server_ns - delay_ns.unwrap_or(span) };
    let a = (t - prev.server_time_ns as i64) as f64 / span as f64;
    let a = if extrapolate { a.clamp(0.0, 1.0 + max_ahead) } else { a.clamp(0.0, 1.0) } as f32;
    // prev + a (last - prev) in float32, as numpy computes it (no fused multiply-add)
    for ((o, p), l) in out.iter_mut().zip(prev.positions).zip(last.positions) {
        *o = p + a * (l - p);
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clock_ignores_unknown_times() {
        let mut c = ServerClock::new(2);
        c.observe(0, 5);
        c.observe(5, 0);
        assert_eq!(c.offset_ns(), None);
        c.observe(10, 4);
        assert_eq!(c.to_server(100), Some(94));
    }

    #[test]
    fn states_out_of_order_or_of_other_sizes_show_the_last() {
        let (a, b) = ([1.0f32; 3], [2.0f32; 3]);
        let mut out = [0f32; 3];
        fn f(t: u64, p: &[f32; 3]) -> Frame<'_> {
            Frame { server_time_ns: t, positions: p }
        }
        assert!(sample_into(Some(f(20, &a)), Some(f(10, &b)), 15, None, false, MAX_AHEAD, &mut out));
        assert_eq!(out, b);
        let short = [3.0f32; 0];
        let g = Frame { server_time_ns: 5, positions: &short };
        assert!(sample_into(Some(g), Some(f(10, &a)), 15, None, false, MAX_AHEAD, &mut out));
        assert_eq!(out, a);
    }
}
