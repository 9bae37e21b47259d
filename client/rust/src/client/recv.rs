//! State reception: the registry of this client's cloths, the per-cloth subscription, the
//! bundle dispatcher and the one-slot "latest state" each cloth keeps. A received payload is
//! kept as Zenoh delivered it (no copy when contiguous) and decoded only when the caller reads
//! it into its own buffers; a predictive one (1.5) is decoded on delivery, in order, by the
//! cloth's stream (`predictive.rs`) and kept as the float32 state it gave.
use super::cloth::{ClothInner, Status};
use super::keyframes::{send, KeyframeQueries, KEYFRAME_QUERY_INTERVAL};
use super::predictive::Outcome;
use super::Inner;
use crate::wire::error::Result;
use crate::wire::replies::SubmitReply;
use crate::wire::{parse_bundle, parse_state, Encoding};
use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::Arc;
use zenoh::bytes::ZBytes;

const MAX_ORPHANS: usize = 256;

/// A received payload: Zenoh's buffer when contiguous, else one contiguous copy; or the
/// float32 state a predictive one decoded to (`D`).
#[derive(Clone)]
pub(crate) enum Buf {
    Z(ZBytes),
    V(Arc<Vec<u8>>),
    D(Arc<Vec<u8>>),
}

impl Buf {
    pub(crate) fn new(z: ZBytes) -> Buf {
        let owned = match z.to_bytes() {
            Cow::Borrowed(_) => None,
            Cow::Owned(v) => Some(v),
        };
        owned.map_or(Buf::Z(z), |v| Buf::V(Arc::new(v)))
    }
    pub(crate) fn with<R>(&self, f: impl FnOnce(&[u8]) -> R) -> R {
        match self {
            Buf::Z(z) => f(&z.to_bytes()),
            Buf::V(v) | Buf::D(v) => f(v),
        }
    }
}

/// The newest state of a cloth: where its payload lies in a received buffer.
#[derive(Clone)]
pub(crate) struct Latest {
    pub(crate) buf: Buf,
    pub(crate) off: usize,
    pub(crate) len: usize,
    pub(crate) receive_time_ns: u64,
}

#[derive(Default)]
pub(crate) struct Registry {
    pub(crate) by_handle: HashMap<u64, Arc<ClothInner>>,
    pub(crate) by_id: HashMap<String, Arc<ClothInner>>,
    /// Bundle entries of cloths whose submit reply has not been handled yet.
    pub(crate) orphans: HashMap<String, Latest>,
    pub(crate) pending_bundled: usize,
}

impl Registry {
    pub(crate) fn clear(&mut self) {
        self.by_handle.clear();
        self.by_id.clear();
        self.orphans.clear();
    }
}

pub(crate) fn now_ns() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}

/// Keep `l` as the cloth's newest state (checking its header first) and count it: a state
/// older than the newest is ignored (stale), a gap in tick numbers is counted as missed, and an
/// unread state pushed out of a full queue as replaced. A predictive state is decoded here, in
/// order; one predicted from a state this client lacks is counted (`undecodable`) and not
/// shown: then the key to ask a keyframe on is returned, unless `keyframes` says it was asked
/// lately, by this cloth or another of its bundle ([`deliver_and_ask`] asks).
pub(crate) fn deliver(c: &ClothInner, keyframes: &KeyframeQueries, l: Latest) -> Option<String> {
    let head = l.buf.with(|d| parse_state(&d[l.off..l.off + l.len]).map(|h| (h.tick, h.encoding, h.server_time_ns)));
    // (state, decoded from a predictive one: whether a keyframe, a gap)
    let (l, decoded, gap) = match head {
        Ok((tick, Encoding::Predictive, _)) => match c.pred.lock().unwrap().decode(&l, tick) {
            Outcome::Decoded(d, keyframe) => (d, Some(keyframe), false),
            Outcome::Stale => (l, None, false), // counted as stale below
            Outcome::Gap => (l, None, true),
            Outcome::Invalid => {
                c.slot.lock().unwrap().counters.invalid += 1;
                return None;
            }
        },
        _ => (l, None, false),
    };
    let mut s = c.slot.lock().unwrap();
    let Ok((tick, _, server_time_ns)) = head else {
        s.counters.invalid += 1;
        return None;
    };
    if s.status != Status::Live {
        return None;
    }
    if s.last_tick != 0 && tick <= s.last_tick {
        s.counters.stale += 1;
        return None;
    }
    // 1.8: at every k-th state, the states the stream had between (a switch: rounded up)
    let steps = if s.last_tick == 0 { 1 } else { (tick - s.last_tick).div_ceil(s.rate.rate.max(1) as u64) };
    s.counters.ticks += steps;
    s.counters.missed += steps - 1;
    s.last_tick = tick;
    if gap {
        s.counters.received += 1;
        s.counters.undecodable += 1;
        let base = s.bundle_key.as_ref().unwrap_or(&s.key);
        let key = crate::rates::every_key(base, s.rate.rate)?; // the key its states come on
        if !keyframes.may_ask(&key, KEYFRAME_QUERY_INTERVAL) {
            return None;
        }
        s.counters.keyframe_requests += 1;
        return Some(key);
    }
    if let Some(keyframe) = decoded {
        s.counters.decoded += 1;
        s.counters.keyframes += keyframe as u64;
    }
    if s.unread.len() >= c.queue_size {
        s.unread.pop_front();
        s.counters.replaced += 1; // never read
    }
    s.clock.observe(l.receive_time_ns, server_time_ns);
    let receive_time_ns = l.receive_time_ns;
    s.rate.observe(tick, server_time_ns, receive_time_ns); // 1.8, rate = auto (a bundled cloth: none)
    s.unread.push_back(l.clone());
    s.prev = s.latest.replace(l); // the last two states: references, nothing copied
    s.last_receipt = std::time::Instant::now();
    s.counters.received += 1;
    drop(s);
    c.cv.notify_all();
    None
}

/// [`deliver`], then the keyframe query it asks for, if any.
pub(crate) fn deliver_and_ask(inner: &Arc<Inner>, c: &Arc<ClothInner>, l: Latest) {
    if let Some(key) = deliver(c, &inner.keyframes, l) {
        send(&inner.session, &key);
    }
    super::rates::after_delivery(inner, c);
}

/// The cloth entered the simulation on `server`: record the reply, subscribe to its key (or
/// rely on the bundle), register it and hand it the bundle states that came before the reply.
pub(crate) fn attach(inner: &Arc<Inner>, c: &Arc<ClothInner>, server: &str, rep: SubmitReply) -> Result<()> {
    // 1.8: every k-th state on its own key (full rate on a server older than 1.8)
    let k = super::rates::placed(inner, c, server, rep.bundle_key.is_some());
    let sub = if rep.bundle_key.is_none() { Some(super::rates::cloth_subscriber(inner, c, &rep.key, k)?) } else { None };
    let old_id = {
        let mut s = c.slot.lock().unwrap();
        let old = std::mem::replace(&mut s.id, rep.cloth.clone());
        s.server = server.to_string();
        s.token = rep.token;
        s.key = rep.key;
        s.bundle_key = rep.bundle_key;
        s.first_tick = rep.tick;
        s.status = Status::Live;
        s.latest = None;
        s.prev = None; // velocities never span two placements (tick numbers differ)
        s.last_receipt = std::time::Instant::now();
        s.counters.replaced += s.unread.len() as u64; // of the old placement, never read
        s.unread.clear();
        s.last_tick = 0; // tick numbers are the new server's
        s.features = None; // a new placement: nothing reported by its server yet
        s.sub = sub;
        c.pred.lock().unwrap().reset(); // the new placement's stream starts with a keyframe
        old
    };
    let early = {
        let mut reg = inner.reg.lock().unwrap();
        if !old_id.is_empty() {
            reg.by_id.remove(&old_id);
        }
        reg.by_handle.insert(c.handle, c.clone());
        reg.by_id.insert(rep.cloth.clone(), c.clone());
        reg.orphans.remove(&rep.cloth)
    };
    if let Some(l) = early {
        deliver_and_ask(inner, c, l);
    }
    Ok(())
}

/// A bundle arrived: hand each entry to its cloth (on the Zenoh thread; no decoding here).
pub(crate) fn on_bundle(inner: &Arc<Inner>, payload: ZBytes) {
    let receive_time_ns = now_ns();
    let buf = Buf::new(payload);
    let mut targets: Vec<(Arc<ClothInner>, Latest)> = Vec::new();
    buf.with(|d| {
        let Ok(b) = parse_bundle(d) else { return };
        super::rates::observe_bundle(inner, b.tick, b.server_time_ns, receive_time_ns); // 1.8, rate = auto
        let mut reg = inner.reg.lock().unwrap();
        for e in &b.entries {
            let l = Latest { buf: buf.clone(), off: e.state_offset, len: e.state_size, receive_time_ns };
            match reg.by_id.get(e.cloth) {
                Some(c) => targets.push((c.clone(), l)),
                None if reg.pending_bundled > 0 && (reg.orphans.len() < MAX_ORPHANS || reg.orphans.contains_key(e.cloth)) => {
                    reg.orphans.insert(e.cloth.to_string(), l);
                }
                None => {}
            }
        }
    });
    for (c, l) in targets {
        deliver_and_ask(inner, &c, l);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::client::cloth::{ClothInner, Status};
    use crate::wire::{encode_state, Encoding, Grid, Shape, Submit};

    fn cloth(queue: usize) -> Arc<ClothInner> {
        let c = ClothInner::new(1, Submit::new("c", Shape::Grid(Grid::new(2, 2))), vec![0.0; 12], vec![0, 1, 2], queue);
        c.slot.lock().unwrap().status = Status::Live;
        c
    }

    fn state(tick: u64) -> Latest {
        let data = encode_state(tick, 0, &[0.0; 12], None, Encoding::Float32, 0).unwrap();
        let len = data.len();
        Latest { buf: Buf::V(Arc::new(data)), off: 0, len, receive_time_ns: 0 }
    }

    fn counters(c: &Arc<ClothInner>) -> crate::client::Counters {
        let s = c.slot.lock().unwrap();
        crate::client::Counters { unread: s.unread.len() as u64, last_tick: s.last_tick, ..s.counters }
    }

    fn take(c: &Arc<ClothInner>) -> Option<u64> {
        let mut s = c.slot.lock().unwrap();
        let l = s.unread.pop_front()?;
        s.counters.read += 1;
        Some(l.buf.with(|d| crate::wire::parse_state(d).unwrap().tick))
    }

    #[test]
    fn every_tick_is_counted_once() {
        // ticks 10, 11, 14 (12 and 13 never arrive), 12 late (stale), 15, 16 into a queue of 2
        let c = cloth(2);
        for t in [10, 11, 14, 12, 15, 16] {
            deliver(&c, &KeyframeQueries::default(), state(t));
        }
        let k = counters(&c);
        assert_eq!((k.received, k.missed, k.stale, k.replaced, k.unread, k.ticks), (5, 2, 1, 3, 2, 7), "{k:?}");
        assert_eq!(take(&c), Some(15)); // oldest of the queue first
        assert_eq!(take(&c), Some(16));
        assert_eq!(take(&c), None);
        let k = counters(&c);
        assert_eq!(k.read + k.replaced + k.missed + k.unread, k.ticks, "{k:?}");
        assert_eq!(k.received, k.read + k.replaced + k.unread);
        // an invalid payload is counted apart and changes nothing else
        deliver(&c, &KeyframeQueries::default(), Latest { buf: Buf::V(Arc::new(vec![1, 2, 3])), off: 0, len: 3, receive_time_ns: 0 });
        assert_eq!(counters(&c).invalid, 1);
        assert_eq!(counters(&c).ticks, 7);
    }

    #[test]
    fn at_every_kth_state_the_streams_states_are_counted() {
        // 1.8, every 2nd state: ticks 2, 4, 8 (6 lost), then switched to every 3rd: 9, 12
        let c = cloth(8);
        c.slot.lock().unwrap().rate.rate = 2;
        for t in [2, 4, 8] {
            deliver(&c, &KeyframeQueries::default(), state(t));
        }
        let k = counters(&c);
        assert_eq!((k.received, k.missed, k.ticks), (3, 1, 4), "{k:?}");
        c.slot.lock().unwrap().rate.rate = 3;
        for t in [9, 12] {
            deliver(&c, &KeyframeQueries::default(), state(t));
        }
        let k = counters(&c);
        assert_eq!((k.received, k.missed, k.ticks), (5, 1, 6), "{k:?}");
        assert_eq!(k.read + k.replaced + k.missed + k.unread, k.ticks, "{k:?}");
    }

    #[test]
    fn a_queue_of_one_keeps_the_newest() {
        let c = cloth(1);
        for t in 1..=5 {
            deliver(&c, &KeyframeQueries::default(), state(t));
        }
        let k = counters(&c);
        assert_eq!((k.received, k.replaced, k.unread, k.ticks, k.missed), (5, 4, 1, 5, 0));
        assert_eq!(take(&c), Some(5));
    }
}
