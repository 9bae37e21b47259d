//! C ABI of protocol 1.5's predictive encoding (PROTOCOL.md 9.2): the encoding ids, the grid
//! step at submit (a client-wide setting: `DrapeClothOptions` has no field for it and its
//! layout is fixed) and by control, and the per-cloth counters of the stream's decoding. The
//! library decodes a predictive cloth's states on delivery; reads give float32 positions as for
//! any other encoding (`DrapeStateInfo.encoding` says DRAPE_ENCODING_PREDICTIVE).
use super::cloth::{control, DrapeCloth};
use super::{bad, guard, DrapeClient, DRAPE_OK};
use crate::wire::{Control, Encoding, StateOptions, STEP_MAX, STEP_MIN};
use std::sync::atomic::Ordering;

/// State encodings (`DrapeClothOptions.encoding`, `DrapeControl.encoding`,
/// `DrapeStateInfo.encoding`).
pub const DRAPE_ENCODING_FLOAT32: i32 = 0;
pub const DRAPE_ENCODING_FLOAT16: i32 = 1;
pub const DRAPE_ENCODING_QUANT16: i32 = 2;
/// Protocol 1.5: a few bits per vertex, each state coded against the two before it on a grid of
/// `step` metres (a position is within step / 2 of the simulated one). Needs a 1.5 server.
pub const DRAPE_ENCODING_PREDICTIVE: i32 = 3;
/// The range of the predictive grid step, metres, and the server's default.
/// (Literals, for cbindgen; a unit test checks they are `wire::STEP_*`.)
pub const DRAPE_STEP_MIN: f64 = 1e-5;
pub const DRAPE_STEP_MAX: f64 = 0.1;
pub const DRAPE_STEP_DEFAULT: f64 = 0.001;

/// The predictive grid step (metres, DRAPE_STEP_MIN..DRAPE_STEP_MAX; 0: the server's default)
/// that this client's later submissions with DRAPE_ENCODING_PREDICTIVE ask for.
#[no_mangle]
pub unsafe extern "C" fn drape_client_set_predictive_step(client: *const DrapeClient, step: f64) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        if step != 0.0 && !(STEP_MIN..=STEP_MAX).contains(&step) {
            return bad(&format!("step {step} must be 0 or within [{STEP_MIN}, {STEP_MAX}] metres"));
        }
        c.step.store(step.to_bits(), Ordering::Relaxed);
        DRAPE_OK
    })
}

/// The step of a submission's options, when they ask for the predictive encoding.
pub(crate) fn submit_step(c: &DrapeClient, state: &mut Option<StateOptions>) {
    let step = f64::from_bits(c.step.load(Ordering::Relaxed));
    if let Some(s) = state.as_mut().filter(|s| s.encoding == Some(Encoding::Predictive) && step != 0.0) {
        s.step = Some(step);
    }
}

/// A control switching the cloth to the predictive encoding on a grid of `step` metres
/// (DRAPE_STEP_MIN..DRAPE_STEP_MAX; or changing the step of a predictive cloth): the next state
/// is a keyframe. Needs a 1.5 server (INVALID_VALUE otherwise, nothing sent). `wait` and `tick`
/// as in `drape_cloth_set_gravity`.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_set_predictive(cloth: *const DrapeCloth, step: f64, wait: bool, tick: *mut u64) -> i32 {
    guard(|| {
        let state = StateOptions { encoding: Some(Encoding::Predictive), step: Some(step), ..Default::default() };
        control(cloth, Control { state: Some(state), ..Default::default() }, wait, tick)
    })
}

/// How a predictive cloth's states were decoded (`drape_cloth_predictive_counters`; all 0 for
/// the other encodings). Cumulative over the cloth's placements.
#[repr(C)]
#[derive(Default, Debug, Clone, Copy)]
pub struct DrapePredictiveCounters {
    /// States decoded on delivery (keyframes among them).
    pub decoded: u64,
    /// Keyframes (intra-coded states) among `decoded`.
    pub keyframes: u64,
    /// States received but predicted from one this client lacks (a state lost, a late join):
    /// not shown (reads keep giving the last state) while the cloth waits for a keyframe.
    /// `drape_cloth_counters`' `received` counts them; with them,
    /// `read + replaced + missed + unread + undecodable == ticks`.
    pub undecodable: u64,
    /// Keyframe queries this client sent for the cloth (one per query key at most every 100 ms
    /// for the whole client: of a bundle's cloths missing one state, one asks).
    pub keyframe_requests: u64,
}

/// Fill `*out` with the cloth's predictive counters. Never blocks.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_predictive_counters(cloth: *const DrapeCloth, out: *mut DrapePredictiveCounters) -> i32 {
    guard(|| {
        let (Some(c), Some(o)) = (cloth.as_ref(), out.as_mut()) else { return bad("cloth or out is NULL") };
        let k = c.cloth.state_counters();
        *o = DrapePredictiveCounters {
            decoded: k.decoded,
            keyframes: k.keyframes,
            undecodable: k.undecodable,
            keyframe_requests: k.keyframe_requests,
        };
        DRAPE_OK
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn constants_are_the_wire_ones() {
        use crate::wire::{Encoding, STEP_DEFAULT, STEP_MAX, STEP_MIN};
        assert_eq!((super::DRAPE_STEP_MIN, super::DRAPE_STEP_MAX, super::DRAPE_STEP_DEFAULT), (STEP_MIN, STEP_MAX, STEP_DEFAULT));
        let ids = [super::DRAPE_ENCODING_FLOAT32, super::DRAPE_ENCODING_FLOAT16, super::DRAPE_ENCODING_QUANT16, super::DRAPE_ENCODING_PREDICTIVE];
        assert_eq!(ids.map(|i| Encoding::from_id(i as u8)), Encoding::ALL.map(Some));
    }
}
