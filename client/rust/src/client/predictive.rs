//! Predictive states (protocol 1.5, PROTOCOL.md 9.2) on the client's delivery path: each
//! cloth's stream decodes its predictive states in order as they arrive (a state depends on the
//! two before it, so it cannot wait for a read that may skip states), into a float32 state
//! payload that the queue, the reads and failover's velocities then use as any other state. A
//! state predicted from one this client lacks (a state lost, a late join) is not shown: the
//! cloth keeps its last state, counts the gap and asks the server for a keyframe with a Zenoh
//! query on the key its states come on (what the Python SDK's `ClothHandle.ask_keyframe` sends;
//! the server's `publish/keyframes.py` answers it), at most one per key in a while for the whole
//! client (`keyframes.rs`: a bundle's cloths share its key and one query).
use super::recv::{Buf, Latest};
use crate::wire::PredictiveStream;
use std::sync::Arc;

/// One cloth's predictive stream as this client rebuilt it (reset with each placement).
#[derive(Default)]
pub(crate) struct Pred {
    stream: PredictiveStream,
    /// The tick of the newest state decoded (0: none yet).
    last_tick: u64,
}

/// What became of a delivered predictive state.
pub(crate) enum Outcome {
    /// Decoded: the state as a float32 payload, and whether it was a keyframe.
    Decoded(Latest, bool),
    /// Not newer than the last one decoded: left to the delivery's stale check.
    Stale,
    /// Predicted from a state this stream lacks: not shown; ask for a keyframe.
    Gap,
    /// Not a valid predictive state.
    Invalid,
}

impl Pred {
    /// A new placement's stream: nothing held (its first state must be a keyframe).
    pub(crate) fn reset(&mut self) {
        *self = Pred::default();
    }

    /// Drop the states held, keeping the newest tick (a later state is not stale): the next
    /// predicted state is a gap.
    pub(crate) fn forget(&mut self) {
        self.stream = PredictiveStream::new();
    }

    /// Decode the predictive state `l` (of tick `tick`) against this stream.
    pub(crate) fn decode(&mut self, l: &Latest, tick: u64) -> Outcome {
        if self.last_tick != 0 && tick <= self.last_tick {
            return Outcome::Stale;
        }
        let r = l.buf.with(|d| self.stream.decode_to_float32(&d[l.off..l.off + l.len]));
        match r {
            Ok(Some((out, h))) => {
                self.last_tick = tick;
                let len = out.len();
                Outcome::Decoded(Latest { buf: Buf::D(Arc::new(out)), off: 0, len, receive_time_ns: l.receive_time_ns }, h.order == 0)
            }
            Ok(None) => Outcome::Gap,
            Err(_) => Outcome::Invalid,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::cloth::{ClothInner, Status};
    use super::super::keyframes::{KeyframeQueries, KEYFRAME_QUERY_INTERVAL};
    use super::super::recv::deliver;
    use super::*;
    use crate::wire::{decode_state_into, Grid, Shape, Submit};

    /// The five states of `tests/vectors/predictive.json` (ticks 100-104: a keyframe, orders
    /// 1, 2, 2 with normals, a keyframe) and each one's decoded positions.
    fn vectors() -> Vec<(Vec<u8>, Vec<f32>)> {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/vectors/predictive.json");
        let all: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let unhex = |s: &str| (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap()).collect();
        all.as_array().unwrap().iter().filter(|v| v["message"] == "state").map(|v| {
            let pos = v["value"]["positions"].as_array().unwrap().iter()
                .flat_map(|p| p.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32)).collect();
            (unhex(v["hex"].as_str().unwrap()), pos)
        }).collect()
    }

    fn latest(data: &[u8]) -> Latest {
        Latest { buf: Buf::V(Arc::new(data.to_vec())), off: 0, len: data.len(), receive_time_ns: 0 }
    }

    fn cloth() -> Arc<ClothInner> {
        let c = ClothInner::new(1, Submit::new("c", Shape::Grid(Grid::new(3, 1))), vec![0.0; 9], vec![], 8);
        let mut s = c.slot.lock().unwrap();
        s.status = Status::Live;
        s.key = "drape/cloth/x/state".into();
        drop(s);
        c
    }

    /// The unread states' ticks and positions (float32 payloads), oldest first.
    fn unread(c: &ClothInner) -> Vec<(u64, Vec<f32>)> {
        c.slot.lock().unwrap().unread.drain(..).map(|l| {
            let mut p = vec![0f32; 9];
            let h = l.buf.with(|d| decode_state_into(&d[l.off..l.off + l.len], &mut p, None)).unwrap();
            assert!(matches!(l.buf, Buf::D(_)));
            (h.tick, p)
        }).collect()
    }

    #[test]
    fn states_decode_in_order_on_delivery() {
        let vs = vectors();
        let c = cloth();
        let q = KeyframeQueries::default();
        for (data, _) in &vs {
            assert_eq!(deliver(&c, &q, latest(data)), None);
        }
        let got = unread(&c);
        assert_eq!(got.iter().map(|x| x.0).collect::<Vec<_>>(), vec![100, 101, 102, 103, 104]);
        for ((_, p), (_, want)) in got.iter().zip(&vs) {
            assert_eq!(p, want);
        }
        let k = c.slot.lock().unwrap().counters;
        assert_eq!((k.received, k.decoded, k.keyframes, k.undecodable, k.keyframe_requests), (5, 5, 2, 0, 0));
        // delivered again: stale, counted once
        deliver(&c, &q, latest(&vs[3].0));
        assert_eq!(c.slot.lock().unwrap().counters.stale, 1);
    }

    #[test]
    fn a_gap_waits_for_a_keyframe_and_asks_once() {
        let vs = vectors();
        let c = cloth();
        let q = KeyframeQueries::default();
        deliver(&c, &q, latest(&vs[0].0));
        // 101 lost: 102 and 103 cannot be decoded; a keyframe is asked once (rate limit)
        assert_eq!(deliver(&c, &q, latest(&vs[2].0)).as_deref(), Some("drape/cloth/x/state"));
        assert_eq!(deliver(&c, &q, latest(&vs[3].0)), None);
        deliver(&c, &q, latest(&vs[4].0));
        let got = unread(&c);
        assert_eq!(got.iter().map(|x| x.0).collect::<Vec<_>>(), vec![100, 104], "nothing shown between");
        assert_eq!(got[1].1, vs[4].1);
        let k = c.slot.lock().unwrap().counters;
        assert_eq!((k.received, k.decoded, k.keyframes, k.undecodable, k.keyframe_requests), (4, 2, 2, 2, 1), "{k:?}");
        assert_eq!((k.ticks, k.missed), (5, 1), "{k:?}");
        assert_eq!(k.read + k.replaced + k.missed + 2 + k.undecodable, k.ticks);
        // a late joiner (nothing held): asks again once the interval has passed
        let late = cloth();
        std::thread::sleep(KEYFRAME_QUERY_INTERVAL);
        assert!(deliver(&late, &q, latest(&vs[1].0)).is_some());
        assert!(unread(&late).is_empty());
        assert_eq!(q.sent(), 2);
    }

    #[test]
    fn a_bundle_whose_cloths_all_miss_a_state_asks_one_keyframe() {
        // every cloth of a bundle that lost a state notices at once; one query on the bundle's
        // key answers them all, so one is sent, not one per cloth
        let vs = vectors();
        let q = KeyframeQueries::default();
        let bundle: Vec<_> = (0..8).map(|_| cloth()).collect();
        for c in &bundle {
            c.slot.lock().unwrap().bundle_key = Some("drape/bundle/x".into());
            deliver(c, &q, latest(&vs[0].0));
        }
        // 101 lost: 102 is a gap for each of them
        let asked: Vec<_> = bundle.iter().filter_map(|c| deliver(c, &q, latest(&vs[2].0))).collect();
        assert_eq!(asked, vec!["drape/bundle/x".to_string()]);
        assert_eq!(q.sent(), 1);
        let ks: Vec<_> = bundle.iter().map(|c| c.slot.lock().unwrap().counters).collect();
        assert!(ks.iter().all(|k| k.undecodable == 1), "{ks:?}");
        assert_eq!(ks.iter().map(|k| k.keyframe_requests).sum::<u64>(), 1);
        // a cloth on its own key asks for its own stream; a switch of rate asks regardless
        let own = cloth();
        assert!(deliver(&own, &q, latest(&vs[1].0)).is_some());
        assert!(q.may_ask("drape/bundle/x", std::time::Duration::ZERO));
        assert_eq!(q.sent(), 3);
    }
}
