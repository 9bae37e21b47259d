//! The session's side of the client: the servers seen by liveliness, their info (versions and
//! limits, asked once per server), the request keys by server version, and waited requests with
//! their replies.
use super::*;

impl Inner {
    pub(crate) fn on_server(self: &Arc<Self>, id: String, alive: bool) {
        let mut s = self.servers.lock().unwrap();
        if alive {
            if s.live.insert(id.clone()) {
                drop(s);
                self.servers_cv.notify_all();
                self.push_event(Event::ServerFound { server: id });
                if let Some(fo) = self.fo.as_ref() {
                    fo.wake(); // lost cloths may go there
                }
            }
            return;
        }
        s.live.remove(&id);
        s.info.remove(&id);
        drop(s);
        self.placement.server_gone(&id);
        self.push_event(Event::ServerLost { server: id.clone() });
        failover::server_lost(self, &id);
    }

    /// The server's limits (asked once with info; defaults if it does not answer).
    pub(crate) fn limits(&self, server: &str) -> Limits {
        self.server_info(server).map(|(_, l)| l).unwrap_or_default()
    }

    pub(crate) fn server_info(&self, server: &str) -> Result<((u8, u8), Limits)> {
        self.server_info_within(server, self.timeout)
    }

    /// The server's version and limits, asked with info once per server (kept until its
    /// liveliness token vanishes; an unanswered info is not remembered).
    pub(crate) fn server_info_within(&self, server: &str, timeout: Duration) -> Result<((u8, u8), Limits)> {
        if let Some(i) = self.servers.lock().unwrap().info.get(server) {
            return Ok(*i);
        }
        let m = self.request_within(server, "info", encode_info(self.next_rid()), timeout)?;
        let r = Reader::new(&m, "");
        let version = r.str("version", false)?.unwrap_or("1.0");
        let (ma, mi) = version.split_once('.').unwrap_or((version, "0"));
        let v = (ma.parse().unwrap_or(1), mi.parse().unwrap_or(0));
        let mut lim = Limits::default();
        if let Some(rate) = r.f64("tick_rate", false).ok().flatten().filter(|x| *x > 0.0 && x.is_finite()) {
            self.servers.lock().unwrap().rates.insert(server.to_string(), rate);
        }
        if let Some(l) = r.sub("limits", false)? {
            let get = |k: &str| l.u64(k, false).ok().flatten();
            lim.max_vertices_per_cloth = get("max_vertices_per_cloth").unwrap_or(lim.max_vertices_per_cloth);
            lim.max_pin_updates = get("max_pin_updates").map_or(lim.max_pin_updates, |x| x as usize);
            lim.max_batch_items = get("max_batch_items").map_or(if v < (1, 1) { 0 } else { lim.max_batch_items }, |x| x as usize);
            lim.max_iterations = get("max_iterations").unwrap_or(lim.max_iterations);
            lim.max_substeps = get("max_substeps").unwrap_or(lim.max_substeps);
        }
        self.servers.lock().unwrap().info.insert(server.to_string(), (v, lim));
        Ok((v, lim))
    }

    /// The key of a `kind` request to `server` (PROTOCOL.md 11.2): this client's own key
    /// `{ns}/server/{server}/client/{client}/{kind}` when the server speaks 1.4 or later (its
    /// `info.version`, asked once per server), else the server-wide key of 1.0-1.3 (always for
    /// info). A 1.3 server has no client-scoped queryable and a server run with
    /// `identity = "keys"` has no server-wide one, so the version decides.
    pub(crate) fn request_key(&self, server: &str, kind: &str, timeout: Duration) -> String {
        if CLIENT_REQUESTS.contains(&kind) && self.client_scoped(server, timeout) {
            return self.keys.client_request(server, &self.client_id, kind);
        }
        self.keys.query(server, kind)
    }

    /// Whether `server` speaks 1.4 (client-scoped request keys); false when its info is not
    /// answered (not remembered: asked again by the next request).
    pub(crate) fn client_scoped(&self, server: &str, timeout: Duration) -> bool {
        self.server_info_within(server, timeout).map(|(v, _)| v >= (1, 4)).unwrap_or(false)
    }

    /// Whether `server`'s info (version) is known.
    pub(crate) fn info_known(&self, server: &str) -> bool {
        self.servers.lock().unwrap().info.contains_key(server)
    }

    /// A waited-for request: the success map, the server's error, or `unavailable`.
    pub(crate) fn request(&self, server: &str, kind: &str, payload: Vec<u8>) -> Result<Map> {
        self.request_within(server, kind, payload, self.timeout)
    }

    /// A waited-for request with its own timeout.
    pub(crate) fn request_within(&self, server: &str, kind: &str, payload: Vec<u8>, timeout: Duration) -> Result<Map> {
        self.check_open()?;
        self.sends.wait_for(self.sends.queued.load(Ordering::SeqCst)); // earlier unwaited requests leave first
        let deadline = Instant::now() + timeout;
        let mut key = self.request_key(server, kind, timeout);
        loop {
            let left = deadline.saturating_duration_since(Instant::now()).max(Duration::from_millis(10));
            let started = Instant::now();
            let replies = self.session.get(&key).payload(payload.clone()).timeout(left).wait().map_err(|e| zerr(&key, e))?;
            if let Ok(r) = replies.recv() {
                return reply_result(&key, r);
            }
            // No reply at all: the queryable is not known yet (connecting) -> retry until the deadline.
            if Instant::now() + Duration::from_millis(50) < deadline && started.elapsed() < left / 2 {
                std::thread::sleep(Duration::from_millis(50));
                if CLIENT_REQUESTS.contains(&kind) && !self.info_known(server) {
                    // its info went unanswered too: ask again which keys it has
                    key = self.request_key(server, kind, deadline.saturating_duration_since(Instant::now()).max(Duration::from_millis(10)));
                }
                continue;
            }
            return Err(Error::new(ErrorCode::Unavailable, format!("no reply from {key} within {timeout:?}")));
        }
    }
}

/// A reply's outcome: an `ok` map, the server's error, or `unavailable` for Zenoh's own errors.
pub(crate) fn reply_result(key: &str, r: zenoh::query::Reply) -> Result<Map> {
    match r.result() {
        Ok(sample) => decode_reply(&sample.payload().to_bytes()),
        Err(e) => {
            let data = e.payload().to_bytes();
            match decode_reply(&data) {
                Err(err) if err.code != ErrorCode::Malformed => Err(err),
                Ok(_) => Err(Error::new(ErrorCode::Unavailable, format!("{key}: error reply without an error"))),
                Err(_) => Err(Error::new(ErrorCode::Unavailable, format!("{key}: {}", String::from_utf8_lossy(&data[..data.len().min(80)])))),
            }
        }
    }
}
