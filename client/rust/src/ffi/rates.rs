//! C ABI of protocol 1.8's rates per subscriber (1.9: every 6th and 12th too; PROTOCOL.md 9.3): the rate ids, the client-wide
//! rate of later submissions and of the bundle (a function: `DrapeClientOptions`' layout is
//! fixed), a cloth's and the bundle's switch (make before break, a keyframe asked for on the new
//! key) and their counters (a new struct: `DrapeStateCounters` keeps its layout).
use super::cloth::DrapeCloth;
use super::{bad, fail, guard, DrapeClient, DRAPE_OK};
use crate::client::RateCounters;
use crate::rates::Rate;

/// `rate = auto`: the full rate, stepped down (to 30 then 20 Hz at the default tick, on a 1.9
/// server on to 10 and 5 Hz) while states arrive late or too few, back up after a quiet period
/// (the Python SDK's rule).
pub const DRAPE_RATE_AUTO: u32 = 0;
/// Every state (60 Hz at the default tick), every 2nd (30 Hz), every 3rd (20 Hz); HALF and THIRD
/// need a 1.8 server (a cloth on an older one takes every state).
pub const DRAPE_RATE_FULL: u32 = 1;
pub const DRAPE_RATE_HALF: u32 = 2;
pub const DRAPE_RATE_THIRD: u32 = 3;
/// Every 6th state (10 Hz at the default tick), every 12th (5 Hz): for links too slow even for
/// 20 Hz; they need a 1.9 server (on a 1.8 one a governed subscription stops at THIRD).
pub const DRAPE_RATE_SIXTH: u32 = 6;
pub const DRAPE_RATE_TWELFTH: u32 = 12;

/// A subscription's rate and what DRAPE_RATE_AUTO did to it (`drape_cloth_rate_counters`,
/// `drape_client_bundle_rate_counters`).
#[repr(C)]
#[derive(Default, Debug, Clone, Copy)]
pub struct DrapeRateCounters {
    /// Times the governor stepped the rate down, and up (0 without DRAPE_RATE_AUTO).
    pub step_downs: u64,
    pub step_ups: u64,
    /// Every `rate`-th state is taken now (DRAPE_RATE_FULL, _HALF, _THIRD, _SIXTH, _TWELFTH).
    pub rate: u32,
    /// A governor steps it (DRAPE_RATE_AUTO).
    pub auto_: bool,
}

fn counters(k: RateCounters) -> DrapeRateCounters {
    DrapeRateCounters { step_downs: k.step_downs, step_ups: k.step_ups, rate: k.rate as u32, auto_: k.auto }
}

/// The rate (DRAPE_RATE_*) later submissions of this client start at, and its bundle's from now
/// on (switched at once when subscribed). A rate the bundle cannot take (a bundled cloth on a
/// server older than 1.8, or 6 or 12 with one on a 1.8 server) leaves it where it is.
#[no_mangle]
pub unsafe extern "C" fn drape_client_set_rate(client: *const DrapeClient, rate: u32) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        let Some(r) = Rate::from_k(rate) else { return bad(&format!("rate {rate}: one of DRAPE_RATE_*")) };
        c.client.set_rate(r).map_or_else(fail, |_| DRAPE_OK)
    })
}

/// Take every `rate`-th bundle (DRAPE_RATE_FULL, _HALF, _THIRD, _SIXTH, _TWELFTH) from now on, for every bundled
/// cloth at once. DRAPE_E_INVALID_VALUE for a rate a server of a bundled cloth does not serve
/// (other than FULL before 1.8, SIXTH or TWELFTH on a 1.8 server).
#[no_mangle]
pub unsafe extern "C" fn drape_client_set_bundle_rate(client: *const DrapeClient, rate: u32) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        let Ok(k) = u8::try_from(rate) else { return bad(&format!("rate {rate}: one of DRAPE_RATE_FULL, _HALF, _THIRD, _SIXTH, _TWELFTH")) };
        c.client.set_bundle_rate(k).map_or_else(fail, |_| DRAPE_OK)
    })
}

/// Take every `rate`-th state of the cloth (DRAPE_RATE_FULL, _HALF, _THIRD, _SIXTH, _TWELFTH) from now on; with
/// DRAPE_RATE_AUTO its governor goes on from there. DRAPE_E_INVALID_VALUE for a bundled cloth
/// (`drape_client_set_bundle_rate`) or a rate its server does not serve (other than FULL before
/// 1.8, SIXTH or TWELFTH on a 1.8 server).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_set_rate(cloth: *const DrapeCloth, rate: u32) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        let Ok(k) = u8::try_from(rate) else { return bad(&format!("rate {rate}: one of DRAPE_RATE_FULL, _HALF, _THIRD, _SIXTH, _TWELFTH")) };
        c.cloth.set_rate(k).map_or_else(fail, |_| DRAPE_OK)
    })
}

/// Fill `*out` with the cloth's rate and its governor's steps (a bundled cloth: its bundle's
/// rate; the steps are the bundle's, `drape_client_bundle_rate_counters`). Never blocks long.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_rate_counters(cloth: *const DrapeCloth, out: *mut DrapeRateCounters) -> i32 {
    guard(|| {
        let (Some(c), Some(o)) = (cloth.as_ref(), out.as_mut()) else { return bad("cloth or out is NULL") };
        *o = counters(c.cloth.rate_counters());
        DRAPE_OK
    })
}

/// Fill `*out` with the bundle's rate and its governor's steps.
#[no_mangle]
pub unsafe extern "C" fn drape_client_bundle_rate_counters(client: *const DrapeClient, out: *mut DrapeRateCounters) -> i32 {
    guard(|| {
        let (Some(c), Some(o)) = (client.as_ref(), out.as_mut()) else { return bad("client or out is NULL") };
        *o = counters(c.client.bundle_rate_counters());
        DRAPE_OK
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn constants_are_the_rates() {
        use crate::rates::{Rate, RATES};
        let ids = [super::DRAPE_RATE_FULL, super::DRAPE_RATE_HALF, super::DRAPE_RATE_THIRD, super::DRAPE_RATE_SIXTH, super::DRAPE_RATE_TWELFTH];
        assert_eq!(ids.map(|k| k as u8), RATES);
        assert_eq!(Rate::from_k(super::DRAPE_RATE_AUTO), Some(Rate::Auto));
    }
}
