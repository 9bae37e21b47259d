//! Placement (PROTOCOL.md 11.3, protocol 1.4): the servers' loads as this client sees them, and
//! its choice of a server for a new cloth or a failover resubmission.
//!
//! The client subscribes to `{ns}/server/*/stats` at open. Per server it keeps the last stats
//! publication (its `vertices` and `phases.tick.mean_ms`, and the map for [`super::Client::stats`])
//! and this client's own submissions there that those stats do not count yet: in flight, or
//! answered after the stats arrived (dropped when the server's next stats arrive). The live
//! servers are ranked by `wire::placement::rank`. A server whose liveliness token goes is ranked
//! as one without stats until it publishes again (a restart starts empty). With several
//! candidates and some without stats, a first choice waits up to `stats_wait` for them.
use super::cloth::ClothInner;
use super::Inner;
use crate::wire::error::{Error, ErrorCode, Result};
use crate::wire::placement::{rank, ServerLoad, PLACE_ELSEWHERE};
use crate::wire::reader::{unpack_message, Map, Reader};
use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// How long a first choice waits for the stats of candidates that have not published (the
/// Python SDK's 1.5 s; at most the client's timeout).
pub(crate) const STATS_WAIT: Duration = Duration::from_millis(1500);

struct Known {
    map: Map,
    /// Its server's token went since: ranked as without stats (its map stays readable).
    stale: bool,
}

struct Placed {
    server: String,
    vertices: u64,
    /// When its reply came (None: in flight).
    replied: Option<Instant>,
}

#[derive(Default)]
struct State {
    stats: HashMap<String, Known>,
    placed: HashMap<u64, Placed>,
    next: u64,
}

pub(crate) struct Placement {
    client_id: String,
    stats_wait: Duration,
    st: Mutex<State>,
    cv: Condvar,
}

impl Placement {
    pub(crate) fn new(client_id: &str, stats_wait: Duration) -> Placement {
        Placement { client_id: client_id.to_string(), stats_wait, st: Mutex::new(State::default()), cv: Condvar::new() }
    }

    /// A stats publication arrived on `key`: the server it is of (None: not a stats message).
    /// Placements answered before it are counted in it from now on.
    pub(crate) fn on_stats(&self, key: &str, payload: &[u8]) -> Option<(String, Map)> {
        let m = unpack_message(payload).ok()?;
        let from_key = key.rsplit('/').nth(1).unwrap_or_default();
        let server = Reader::new(&m, "").str("server", false).ok().flatten().unwrap_or(from_key).to_string();
        if server.is_empty() {
            return None;
        }
        let now = Instant::now();
        let mut st = self.st.lock().unwrap();
        st.stats.insert(server.clone(), Known { map: m.clone(), stale: false });
        st.placed.retain(|_, p| p.server != server || p.replied.is_none_or(|t| t > now));
        drop(st);
        self.cv.notify_all();
        Some((server, m))
    }

    /// Its liveliness token went: no longer ranked by its old load, its pending placements dropped.
    pub(crate) fn server_gone(&self, server: &str) {
        let mut st = self.st.lock().unwrap();
        if let Some(k) = st.stats.get_mut(server) {
            k.stale = true;
        }
        st.placed.retain(|_, p| p.server != server);
    }

    /// A submission of `vertices` is sent to `server`: counted there from now on (a ticket for
    /// [`Placement::placed`]).
    pub(crate) fn placing(&self, server: &str, vertices: u64) -> u64 {
        let mut st = self.st.lock().unwrap();
        st.next += 1;
        let ticket = st.next;
        st.placed.insert(ticket, Placed { server: server.to_string(), vertices, replied: None });
        ticket
    }

    /// Its reply came: accepted (counted until the server's next stats) or refused (not).
    pub(crate) fn placed(&self, ticket: u64, ok: bool) {
        let mut st = self.st.lock().unwrap();
        if !ok {
            st.placed.remove(&ticket);
        } else if let Some(p) = st.placed.get_mut(&ticket) {
            p.replied = Some(Instant::now());
        }
    }

    /// The server's last stats publication (stale ones too), if any.
    pub(crate) fn stats(&self, server: &str) -> Option<Map> {
        self.st.lock().unwrap().stats.get(server).map(|k| k.map.clone())
    }

    fn loads(st: &State, servers: &[String]) -> Vec<ServerLoad> {
        let mut pending: HashMap<&str, u64> = HashMap::new();
        for p in st.placed.values() {
            *pending.entry(p.server.as_str()).or_default() += p.vertices;
        }
        servers
            .iter()
            .map(|s| {
                let known = st.stats.get(s).filter(|k| !k.stale).map(|k| &k.map);
                ServerLoad::from_stats(s, known, pending.get(s.as_str()).copied().unwrap_or(0))
            })
            .collect()
    }

    /// The `live` servers not in `exclude`, best first. `wait`: when several are candidates and
    /// some have no stats yet, wait up to `stats_wait` for them.
    pub(crate) fn ranked(&self, live: &[String], exclude: &HashSet<String>, wait: bool) -> Vec<String> {
        let cands: Vec<String> = live.iter().filter(|s| !exclude.contains(*s)).cloned().collect();
        let unknown = |st: &State| cands.iter().any(|s| st.stats.get(s).is_none_or(|k| k.stale));
        let mut st = self.st.lock().unwrap();
        if wait && cands.len() > 1 && unknown(&st) {
            st = self.cv.wait_timeout_while(st, self.stats_wait, |st| unknown(st)).unwrap().0;
        }
        rank(&Self::loads(&st, &cands), &self.client_id)
    }
}

/// Subscribe to every server's stats publications (their loads; their tick rates for failover).
pub(crate) fn subscribe(inner: &Arc<Inner>) -> Result<()> {
    let weak = Arc::downgrade(inner);
    let sub = inner
        .session
        .declare_subscriber(inner.keys.stats("*"))
        .callback(move |s| {
            let Some(inner) = weak.upgrade() else { return };
            let Some((server, m)) = inner.placement.on_stats(s.key_expr().as_str(), &s.payload().to_bytes()) else { return };
            if let Some(rate) = Reader::new(&m, "").f64("tick_rate", false).ok().flatten().filter(|x| *x > 0.0 && x.is_finite()) {
                inner.servers.lock().unwrap().rates.insert(server, rate);
            }
        })
        .wait()
        .map_err(|e| super::zerr("stats subscriber", e))?;
    *inner.stats_sub.lock().unwrap() = Some(sub);
    Ok(())
}

impl Inner {
    /// The ids of the servers whose liveliness tokens this client sees now.
    pub(crate) fn live_servers(&self) -> Vec<String> {
        self.servers.lock().unwrap().live.iter().cloned().collect()
    }

    /// The given server, or else the default one for requests that name none: the placement's
    /// first choice among the live ones, kept while it is live (waiting up to the timeout for one).
    pub(crate) fn server_id(&self) -> Result<String> {
        let s = self.servers.lock().unwrap();
        if let Some(c) = &s.current {
            if self.server_given || s.live.contains(c) {
                return Ok(c.clone());
            }
        }
        let (s, _) = self.servers_cv.wait_timeout_while(s, self.timeout, |s| s.live.is_empty()).unwrap();
        let live: Vec<String> = s.live.iter().cloned().collect();
        drop(s);
        let chosen = self.placement.ranked(&live, &HashSet::new(), true).into_iter().next().ok_or_else(|| {
            Error::new(ErrorCode::Unavailable, format!("no Drape server seen in namespace {:?} within {:?}", self.keys.namespace, self.timeout))
        })?;
        self.servers.lock().unwrap().current = Some(chosen.clone());
        Ok(chosen)
    }

    /// Submit a new cloth: to the given server (with failover: its replacement once it was
    /// lost), else, for a cloth of a scene, where the scene is (`scenes`), else by placement,
    /// trying the next server on a refusal another may not give.
    pub(crate) fn submit_placed(self: &Arc<Self>, c: &Arc<ClothInner>) -> Result<()> {
        if self.server_given {
            let server = self.server_id()?;
            self.submit_to(c, &server)?;
            if let Some(scene) = &c.submit.scene {
                self.learn_scene_owner(scene, &server);
            }
            return Ok(());
        }
        if let Some(scene) = &c.submit.scene {
            // 1.7: where the scene is (this client's cloths of it, else the live server holding it)
            let placed = match self.scene_server(scene, c.handle).or_else(|| self.locate_scene(scene)) {
                Some(server) => self.submit_to(c, &server).map(|_| server),
                None => self.submit_by_load(c).map(|_| c.slot.lock().unwrap().server.clone()),
            }?;
            self.learn_scene_owner(scene, &placed);
            return Ok(());
        }
        self.submit_by_load(c)
    }

    /// By placement, trying the next server on a refusal another may not give.
    fn submit_by_load(self: &Arc<Self>, c: &Arc<ClothInner>) -> Result<()> {
        let mut tried = HashSet::new();
        let mut last: Option<Error> = None;
        loop {
            let choice = match self.placement.ranked(&self.live_servers(), &tried, true).into_iter().next() {
                Some(s) => s,
                None => match last {
                    Some(e) => return Err(e), // every live server refused: the last refusal
                    None => self.server_id()?, // none live yet: wait for one
                },
            };
            if !tried.insert(choice.clone()) {
                return Err(last.unwrap_or_else(|| Error::new(ErrorCode::Unavailable, format!("server {choice} did not take the cloth"))));
            }
            // 1.8: a cloth with its own mesh goes to a server that speaks mesh colliders
            if let Err(e) = self.check_mesh_version(&choice, c.submit.mesh_collider.as_ref()) {
                last = Some(e);
                continue;
            }
            match self.submit_to(c, &choice) {
                Err(e) if PLACE_ELSEWHERE.contains(&e.code) => last = Some(e),
                r => return r,
            }
        }
    }

    /// Validate `c`'s submission against `server`'s limits and place it there.
    fn submit_to(self: &Arc<Self>, c: &Arc<ClothInner>, server: &str) -> Result<()> {
        c.submit.validate(&self.limits(server))?;
        self.place(c, server, None).map(|_| ())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::reader::{header, pack, s, Value};

    fn stats(server: &str, vertices: u64) -> Vec<u8> {
        let mut m = header(0);
        m.extend([(s("server"), s(server)), (s("vertices"), Value::from(vertices))]);
        pack(&Value::Map(m))
    }

    #[test]
    fn pending_placements_count_until_the_next_stats() {
        let p = Placement::new("game-7", Duration::ZERO);
        let live = vec!["s1".to_string(), "s2".to_string()];
        let none = HashSet::new();
        p.on_stats("drape/server/s1/stats", &stats("s1", 100));
        p.on_stats("drape/server/s2/stats", &stats("s2", 100));
        assert!(p.stats("s1").is_some() && p.stats("s3").is_none());
        let first = p.ranked(&live, &none, true)[0].clone();
        let other = if first == "s1" { "s2" } else { "s1" }.to_string();
        // a burst spreads: what this client placed counts at once
        let t = p.placing(&first, 50);
        assert_eq!(p.ranked(&live, &none, true)[0], other);
        p.placed(t, true);
        assert_eq!(p.ranked(&live, &none, true)[0], other, "answered, not yet in its stats");
        // its next stats count it: the pending count goes
        p.on_stats("drape/server/x/stats", &stats(&first, 100));
        assert_eq!(p.ranked(&live, &none, true)[0], first, "equal again: the hash decides");
        // a refused submission does not count
        let t = p.placing(&first, 50);
        p.placed(t, false);
        assert_eq!(p.ranked(&live, &none, true)[0], first);
        // a server whose token went ranks last until it publishes again
        p.server_gone(&first);
        assert_eq!(p.ranked(&live, &none, false), vec![other.clone(), first.clone()]);
        assert!(p.stats(&first).is_some(), "its last stats stay readable");
        let mut ex = HashSet::new();
        ex.insert(other.clone());
        assert_eq!(p.ranked(&live, &ex, true), vec![first.clone()]);
        assert!(p.on_stats("k", b"\x01").is_none(), "not a stats message");
    }
}
