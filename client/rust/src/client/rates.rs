//! Rates per subscriber on the client's side (protocol 1.8, PROTOCOL.md 9.3): which key a
//! cloth's or the bundle's subscription takes (every k-th state, `crate::rates::every_key`), the
//! switch from one rate to another (make before break, as the Python SDK: the new key subscribed
//! before the old one is dropped, its stream started afresh and a keyframe asked for on it), and
//! `rate = auto`'s [`Governor`] fed with each state's (or bundle's) times; a change it calls for
//! is made off the Zenoh thread, along the rates the subscription's server serves
//! (`crate::rates::served_rates`): a cloth on a server older than 1.8 stays on the full-rate key,
//! one on a 1.8 server takes at most every 3rd state (1.9 adds every 6th and 12th).
use super::cloth::{Cloth, ClothInner, Status};
use super::recv::{self, now_ns, Buf, Latest};
use super::{zerr, Client, Inner};
use crate::rates::{every_key, fit_rate, served_rates, Governor, Rate, RATES};
use crate::wire::error::{Error, ErrorCode, Result};
use std::sync::Arc;
use std::time::Duration;
use zenoh::pubsub::Subscriber;
use zenoh::Wait;

/// A subscription's rate (a cloth's own key, or the client's bundle).
#[derive(Debug, Clone)]
pub(crate) struct SubRate {
    /// Every `rate`-th state is taken, on the key's `every/{rate}` twin (1: the key itself).
    pub(crate) rate: u8,
    /// The rates its server (every server of the bundle's cloths) serves: `[1]` before 1.8,
    /// `[1, 2, 3]` on 1.8, all of `RATES` from 1.9.
    pub(crate) served: Vec<u8>,
    /// `Rate::Auto`: steps the rate (a bundled cloth has none: its bundle's steps).
    pub(crate) governor: Option<Governor>,
    /// A change the governor called for on delivery, made off the Zenoh thread.
    pub(crate) pending: Option<u8>,
}

impl SubRate {
    pub(crate) fn new(rate: Rate) -> SubRate {
        let (k, auto) = rate.start();
        SubRate { rate: k, served: RATES.to_vec(), governor: auto.then(|| Governor::new(k)), pending: None }
    }

    /// Its server serves the rates `served`: the rate the served one at or below its own (the
    /// full-rate key, the governor idle, on a server older than 1.8), the governor's ladder those.
    fn limit(&mut self, served: &[u8]) {
        self.served = served.to_vec();
        self.rate = fit_rate(self.rate, served);
        self.pending = self.pending.filter(|k| served.contains(k));
        if let Some(g) = self.governor.as_mut() {
            g.limit(served);
        }
    }

    /// A state of `tick` arrived: the governor's verdict kept in `pending`.
    pub(crate) fn observe(&mut self, tick: u64, server_ns: u64, receive_ns: u64) {
        if self.served.len() < 2 {
            return;
        }
        if let Some(new) = self.governor.as_mut().and_then(|g| g.observe(tick, server_ns, receive_ns)) {
            self.pending = Some(new);
        }
    }

    pub(crate) fn counters(&self) -> RateCounters {
        let g = self.governor.as_ref();
        RateCounters {
            rate: self.rate,
            auto: g.is_some(),
            step_downs: g.map_or(0, |g| g.step_downs),
            step_ups: g.map_or(0, |g| g.step_ups),
        }
    }
}

/// A subscription's rate and what `rate = auto` did to it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RateCounters {
    /// Every `rate`-th state is taken now (one of `RATES`: 1, 2, 3, 6, 12).
    pub rate: u8,
    /// A governor steps it (`Rate::Auto`).
    pub auto: bool,
    /// Times the governor stepped it down, and up.
    pub step_downs: u64,
    pub step_ups: u64,
}

fn check_k(k: u8) -> Result<()> {
    if RATES.contains(&k) {
        Ok(())
    } else {
        Err(Error::new(ErrorCode::InvalidValue, format!("rate {k}: one of {RATES:?}")))
    }
}

/// The rates `server` (its info asked once) serves; the full rate only when unknown.
pub(crate) fn server_served(inner: &Inner, server: &str) -> Vec<u8> {
    served_rates(inner.server_info(server).map(|(v, _)| v).ok())
}

/// A subscriber of `c`'s state `key` at rate `k` whose states count only while `k` is the
/// cloth's rate.
pub(crate) fn cloth_subscriber(inner: &Arc<Inner>, c: &Arc<ClothInner>, key: &str, k: u8) -> Result<Subscriber<()>> {
    let weak = Arc::downgrade(c);
    let client = Arc::downgrade(inner);
    let key = every_key(key, k).ok_or_else(|| check_k(k).unwrap_err())?;
    inner
        .session
        .declare_subscriber(key)
        .callback(move |s| {
            if let (Some(c), Some(inner)) = (weak.upgrade(), client.upgrade()) {
                if c.slot.lock().unwrap().rate.rate != k {
                    return; // the old key's, during a switch
                }
                let buf = Buf::new(s.payload().clone());
                let len = buf.with(|d| d.len());
                recv::deliver_and_ask(&inner, &c, Latest { buf, off: 0, len, receive_time_ns: now_ns() });
            }
        })
        .wait()
        .map_err(|e| zerr("state subscriber", e))
}

/// A subscriber of this client's bundle key at rate `k` whose bundles count only while `k` is
/// the bundle's rate.
pub(crate) fn bundle_subscriber(inner: &Arc<Inner>, k: u8) -> Result<Subscriber<()>> {
    let weak = Arc::downgrade(inner);
    let key = every_key(&inner.keys.bundle(&inner.client_id), k).ok_or_else(|| check_k(k).unwrap_err())?;
    inner
        .session
        .declare_subscriber(key)
        .callback(move |s| {
            if let Some(inner) = weak.upgrade() {
                if inner.bundle_rate.lock().unwrap().rate == k {
                    recv::on_bundle(&inner, s.payload().clone());
                }
            }
        })
        .wait()
        .map_err(|e| zerr("bundle subscriber", e))
}

/// A change the governor of `c` (or of the bundle) called for: made on a thread of its own
/// (a subscriber is not undeclared from its own callback).
pub(crate) fn after_delivery(inner: &Arc<Inner>, c: &Arc<ClothInner>) {
    let pending = c.slot.lock().unwrap().rate.pending.take();
    if let Some(k) = pending {
        let (inner, c) = (inner.clone(), c.clone());
        let _ = std::thread::Builder::new().name("drape-rate".into()).spawn(move || {
            let _ = switch_cloth(&inner, &c, k, false);
        });
    }
}

/// A bundle of `tick` arrived: fed to the bundle's governor; a change made off this thread.
pub(crate) fn observe_bundle(inner: &Arc<Inner>, tick: u64, server_ns: u64, receive_ns: u64) {
    let pending = {
        let mut b = inner.bundle_rate.lock().unwrap();
        b.observe(tick, server_ns, receive_ns);
        b.pending.take()
    };
    if let Some(k) = pending {
        let inner = inner.clone();
        let _ = std::thread::Builder::new().name("drape-rate".into()).spawn(move || {
            let _ = switch_bundle(&inner, k, false);
        });
    }
}

/// The rate `c` takes on its new placement on `server` (attach): its own, or the one below it
/// that `server` serves (1 on a server older than 1.8, at most 3 on a 1.8 one); a bundled
/// cloth's is the bundle's.
pub(crate) fn placed(inner: &Inner, c: &ClothInner, server: &str, bundled: bool) -> u8 {
    let served = server_served(inner, server);
    let bundle = bundled.then(|| inner.bundle_rate.lock().unwrap().rate);
    let mut s = c.slot.lock().unwrap();
    s.rate.limit(&served);
    if let Some(k) = bundle {
        s.rate.rate = k;
        s.rate.governor = None;
    }
    s.rate.rate
}

/// Before a bundled cloth is placed on `server`: the bundle keeps to the rates every server of
/// its cloths serves, for good (a server older than 1.8: the full-rate key; a 1.8 one: at most
/// every 3rd bundle), switched now when its rate is not among them.
pub(crate) fn bundle_placing(inner: &Arc<Inner>, server: &str) -> Result<()> {
    let served = server_served(inner, server);
    let (k, to) = {
        let mut b = inner.bundle_rate.lock().unwrap();
        let k = b.rate;
        let both: Vec<u8> = b.served.iter().copied().filter(|r| served.contains(r)).collect();
        b.limit(&both);
        let to = b.rate;
        b.rate = k; // switched below
        (k, to)
    };
    if to != k {
        switch_bundle(inner, to, false)?;
    }
    Ok(())
}

/// Switch `c`'s own subscription to rate `k` (make before break). `by_hand`: the caller's
/// choice, told to its governor.
pub(crate) fn switch_cloth(inner: &Arc<Inner>, c: &Arc<ClothInner>, k: u8, by_hand: bool) -> Result<()> {
    check_k(k)?;
    let key = {
        let mut s = c.slot.lock().unwrap();
        if s.bundle_key.is_some() {
            return Err(Error::new(ErrorCode::InvalidValue, "a bundled cloth takes its bundle's rate (Client::set_bundle_rate)"));
        }
        if s.status != Status::Live {
            return Err(Error::new(ErrorCode::Unavailable, "the cloth is not live"));
        }
        if !s.rate.served.contains(&k) {
            let why = if s.rate.served.len() < 2 { "older than 1.8: the full rate only" } else { "1.8: every 3rd state at most" };
            return Err(Error::new(ErrorCode::InvalidValue, format!("server {} speaks a protocol {why}", s.server)));
        }
        if s.rate.rate == k {
            return Ok(());
        }
        s.rate.rate = k; // from now on the old key's states are ignored
        if let Some(g) = s.rate.governor.as_mut().filter(|_| by_hand) {
            g.set_rate(k, now_ns());
        }
        c.pred.lock().unwrap().reset(); // the new key's stream: its own states, from a keyframe
        s.key.clone()
    };
    let new = cloth_subscriber(inner, c, &key, k)?; // before the old one goes
    let old = {
        let mut s = c.slot.lock().unwrap();
        if s.key != key || s.rate.rate != k {
            return Ok(()); // placed anew or switched again meanwhile: the newer one holds
        }
        s.counters.keyframe_requests += 1;
        s.sub.replace(new)
    };
    drop(old);
    if let Some(key) = every_key(&key, k) {
        inner.keyframes.ask(&inner.session, &key, Duration::ZERO); // asked regardless
    }
    Ok(())
}

/// Switch the client's bundle subscription to rate `k` (make before break): each bundled
/// cloth's stream starts afresh and one keyframe is asked for on the new key.
pub(crate) fn switch_bundle(inner: &Arc<Inner>, k: u8, by_hand: bool) -> Result<()> {
    check_k(k)?;
    {
        let mut b = inner.bundle_rate.lock().unwrap();
        if !b.served.contains(&k) {
            return Err(Error::new(ErrorCode::InvalidValue, format!("a server of the bundle's cloths serves the rates {:?} only", b.served)));
        }
        if b.rate == k {
            return Ok(());
        }
        b.rate = k;
        if let Some(g) = b.governor.as_mut().filter(|_| by_hand) {
            g.set_rate(k, now_ns());
        }
    }
    let bundled: Vec<Arc<ClothInner>> = inner.reg.lock().unwrap().by_handle.values().cloned().collect();
    for c in bundled {
        let mut s = c.slot.lock().unwrap();
        if s.bundle_key.is_some() {
            s.rate.rate = k;
            c.pred.lock().unwrap().reset();
        }
    }
    if inner.bundle_sub.lock().unwrap().is_none() {
        return Ok(()); // subscribed at this rate with the first bundled cloth
    }
    let new = bundle_subscriber(inner, k)?;
    let old = inner.bundle_sub.lock().unwrap().replace(new);
    drop(old);
    if let Some(key) = every_key(&inner.keys.bundle(&inner.client_id), k) {
        inner.keyframes.ask(&inner.session, &key, Duration::ZERO); // asked regardless
    }
    Ok(())
}

impl Cloth {
    /// 1.8: take every `k`-th state (1, 2, 3: 60, 30, 20 Hz at the default tick; 1.9: 6, 12: 10,
    /// 5 Hz) from now on, on
    /// the state key's `every/{k}` twin: the new key is subscribed before the old one is dropped,
    /// and its stream starts with a keyframe asked for. With `Rate::Auto` the governor goes on
    /// from `k`. `invalid_value` for a bundled cloth (its bundle's rate:
    /// [`Client::set_bundle_rate`]) or a rate its server does not serve (other than 1 before 1.8,
    /// 6 or 12 on a 1.8 server).
    pub fn set_rate(&self, k: u8) -> Result<()> {
        switch_cloth(&self.client, &self.inner, k, true)
    }

    /// 1.8: the rate its states come at (a bundled cloth: its bundle's) and the governor's steps
    /// (a bundled cloth: see [`Client::bundle_rate_counters`]).
    pub fn rate_counters(&self) -> RateCounters {
        self.inner.slot.lock().unwrap().rate.counters()
    }
}

impl Client {
    /// 1.8: the rate later submissions start at (`Rate::Auto`: full rate, stepped by a
    /// governor), and the bundle's rate from now on (switched now if it is subscribed).
    pub fn set_rate(&self, rate: Rate) -> Result<()> {
        let (k, auto) = rate.start();
        check_k(k)?;
        *self.inner.rate.lock().unwrap() = rate;
        {
            let mut b = self.inner.bundle_rate.lock().unwrap();
            let mut g = auto.then(|| Governor::new(b.rate));
            if let (Some(g), Some(old)) = (g.as_mut(), b.governor.as_ref()) {
                (g.step_downs, g.step_ups) = (old.step_downs, old.step_ups);
            }
            b.governor = g;
        }
        self.set_bundle_rate(k).or_else(|e| if k != 1 && e.code == ErrorCode::InvalidValue { Ok(()) } else { Err(e) })
    }

    /// 1.8: take every `k`-th bundle (1, 2, 3; 1.9: 6, 12) of this client's bundle key from now on
    /// (every bundled cloth at once; make before break, a keyframe asked for on the new key).
    /// `invalid_value` for a rate a server of a bundled cloth does not serve (other than 1 before
    /// 1.8, 6 or 12 on a 1.8 server).
    pub fn set_bundle_rate(&self, k: u8) -> Result<()> {
        switch_bundle(&self.inner, k, true)
    }

    /// 1.8: the bundle's rate and its governor's steps.
    pub fn bundle_rate_counters(&self) -> RateCounters {
        self.inner.bundle_rate.lock().unwrap().counters()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_subscription_on_a_pre_1_8_server_takes_every_state_and_its_governor_idles() {
        let mut r = SubRate::new(Rate::Every(2));
        assert_eq!((r.rate, r.served.as_slice(), r.governor.is_none()), (2, &RATES[..], true));
        let mut auto = SubRate::new(Rate::Auto);
        auto.governor.as_mut().unwrap().rate = 3; // as after two steps down
        for s in [&mut r, &mut auto] {
            s.limit(&served_rates(Some((1, 7))));
            assert_eq!((s.rate, s.served.as_slice(), s.pending), (1, &[1u8][..], None));
        }
        assert_eq!(auto.governor.as_ref().unwrap().rate, 1);
        // late states feed nothing while the server cannot serve another rate
        for t in 1..600u64 {
            auto.observe(t, t * 16_666_667, t * 16_666_667 + t * 5_000_000);
        }
        assert_eq!((auto.pending, auto.counters().step_downs), (None, 0));
        assert!(check_k(4).is_err() && check_k(12).is_ok());
    }

    #[test]
    fn a_subscription_on_a_1_8_server_stops_at_every_3rd_state() {
        let mut auto = SubRate::new(Rate::Auto);
        auto.governor.as_mut().unwrap().rate = 12; // as after a jump on a 1.9 server
        auto.rate = 12;
        auto.limit(&served_rates(Some((1, 8))));
        assert_eq!((auto.rate, auto.governor.as_ref().unwrap().rate), (3, 3));
        // far too late at every rate: no step below 3
        for t in (3..1200u64).step_by(3) {
            auto.observe(t, t * 16_666_667, t * 16_666_667 + t * 5_000_000);
        }
        assert_eq!(auto.pending, None);
        assert_eq!(auto.governor.as_ref().unwrap().rate, 3);
    }
}
