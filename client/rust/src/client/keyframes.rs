//! 1.5 keyframe queries of one client, at most one per query key in a while (PROTOCOL.md 9.2;
//! the Python SDK's `client/keyframes.py`). A predictive stream that cannot decode a state asks
//! the server for a keyframe with a query on the key its states come on. For a bundle that key
//! is the bundle's, and one query keyframes every stream in it: when a bundle's state is lost,
//! all of its cloths notice at once, and each asking would send the server one query per cloth
//! (a 64-cloth bundle: 64 queries for one keyframe; a load of 4096 such cloths flooded the
//! server's request queue). So the limit is kept per query key, for the whole client.
use super::Client;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};
use zenoh::{Session, Wait};

/// The least time between two keyframe queries on one key (the Python SDK's 0.1 s).
pub(crate) const KEYFRAME_QUERY_INTERVAL: Duration = Duration::from_millis(100);

/// Keys noted before those no longer limiting anything are dropped (cloths removed, rates left).
const MAX_KEYS: usize = 4096;

/// The keyframe queries a client sends: when each key was last asked, and how many went out.
#[derive(Default)]
pub(crate) struct KeyframeQueries {
    /// Query key -> time of its last query (a leaf lock: nothing is locked while it is held).
    asked: Mutex<HashMap<String, Instant>>,
    sent: AtomicU64,
}

impl KeyframeQueries {
    /// Whether a query on `key` may go out now: not asked less than `min_interval` ago (by any
    /// cloth of this client; `Duration::ZERO`: asked regardless, as a switch of rate does). If
    /// so, the time is noted and the query counted as sent ([`send`] sends it).
    pub(crate) fn may_ask(&self, key: &str, min_interval: Duration) -> bool {
        let now = Instant::now();
        let mut asked = self.asked.lock().unwrap();
        if asked.get(key).is_some_and(|&t| now.duration_since(t) < min_interval) {
            return false;
        }
        if asked.len() >= MAX_KEYS {
            asked.retain(|_, t| now.duration_since(*t) < KEYFRAME_QUERY_INTERVAL); // the others limit nothing
        }
        asked.insert(key.to_string(), now);
        self.sent.fetch_add(1, Ordering::Relaxed);
        true
    }

    /// [`Self::may_ask`], then the query [`send`]s: whether it went out.
    pub(crate) fn ask(&self, session: &Session, key: &str, min_interval: Duration) -> bool {
        self.may_ask(key, min_interval) && send(session, key)
    }

    /// Keyframe queries this client sent.
    pub(crate) fn sent(&self) -> u64 {
        self.sent.load(Ordering::Relaxed)
    }
}

impl Client {
    /// 1.5: keyframe queries this client sent (one per key at most every 100 ms, whichever of
    /// its cloths noticed the gap, and one on each switch of rate).
    pub fn keyframe_queries(&self) -> u64 {
        self.inner.keyframes.sent()
    }
}

/// Ask the server for a keyframe of the streams on `key` (a cloth's state key or its client's
/// bundle key): a query without payload, its reply ignored (the keyframe comes as the stream's
/// next state). Never waits for the reply.
pub(crate) fn send(session: &Session, key: &str) -> bool {
    session.get(key).callback(|_| {}).timeout(Duration::from_secs(1)).wait().is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_query_per_key_in_an_interval_unless_forced() {
        let q = KeyframeQueries::default();
        assert!(q.may_ask("drape/bundle/a", KEYFRAME_QUERY_INTERVAL));
        assert!(!q.may_ask("drape/bundle/a", KEYFRAME_QUERY_INTERVAL), "asked a moment ago");
        assert!(q.may_ask("drape/bundle/a/every/2", KEYFRAME_QUERY_INTERVAL), "another key");
        assert!(q.may_ask("drape/bundle/a", Duration::ZERO), "asked regardless");
        std::thread::sleep(KEYFRAME_QUERY_INTERVAL);
        assert!(q.may_ask("drape/bundle/a", KEYFRAME_QUERY_INTERVAL), "the interval passed");
        assert_eq!(q.sent(), 4);
    }
}
