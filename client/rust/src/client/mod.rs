//! The Zenoh client: a session with this client's liveliness token, server discovery by
//! liveliness, requests (waited for or not), submissions, state reception (single keys and
//! bundles), placement by load (PROTOCOL.md 11.3, protocol 1.4), 1.4 `moves` blocks and, opt-in,
//! the failover of PROTOCOL.md section 11.1 (protocol 1.3): lost or reclaimed cloths resumed on
//! the least loaded live server from their last received states.
//!
//! This file is the facade (options, events, the client's shared state and its open and close);
//! the parts are `session` (servers, their info, waited requests), `sending` (requests not waited
//! for), `submit`, `controls`, `cloth`, `recv` (states), `predictive`, `rates` (1.8: every k-th
//! state, `rate = auto`), `meshes` (1.8's mesh colliders, 1.7's scene requests), `moves`, `placement`, `scenes` (1.7: a scene kept on one server, founded again by its owner) and `failover`.
mod cloth;
mod controls;
mod failover;
mod keyframes;
mod meshes;
mod moves;
mod placement;
mod predictive;
mod rates;
mod recv;
mod scenes;
mod sending;
mod session;
mod submit;

pub use cloth::{Batch, Cloth, ClothStatus, Counters, StateInfo};
pub use rates::RateCounters;
pub use crate::rates::Rate;
use sending::{SendJob, Sends};
use session::reply_result;

use crate::wire::error::{Error, ErrorCode, Result};
use crate::wire::msg::{encode_info, Control, Grid, Mesh, Resume, Shape, Submit};
use crate::wire::reader::{Map, Reader};
use crate::wire::replies::{decode_reply, Applied, SubmitReply};
use crate::wire::{grid_geometry, parse_obj, valid_id, valid_namespace, Keys, Limits, CLIENT_REQUESTS, DEFAULT_ENDPOINT, DEFAULT_NAMESPACE};
use std::collections::{BTreeSet, HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::sample::SampleKind;
use zenoh::{Session, Wait};

/// How to connect. `Default` connects to `tcp/127.0.0.1:7447` in peer mode.
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// Endpoints of the server(s) or of a router.
    pub connect: Vec<String>,
    pub namespace: String,
    /// The server to use for every submission; None places each new cloth on the least loaded
    /// live server by the servers' stats (PROTOCOL.md 11.3).
    pub server_id: Option<String>,
    /// This client's id (its liveliness token, and in its 1.4 request keys); None: the
    /// deployment's ([`deployment_client_id_for`]: `$DRAPE_CLIENT_ID`, else the
    /// `.client_id` sidecar of `zenoh_config_file`), else random. Behind a router
    /// that binds identities (PROTOCOL.md 11.2) it must be the id the router binds to the user.
    pub client_id: Option<String>,
    /// Timeout of waited-for requests and of server discovery.
    pub timeout: Duration,
    /// Zenoh mode: "peer" (default) or "client".
    pub mode: String,
    /// A Zenoh configuration file (JSON5: user/password authentication, TLS, ...), loaded with
    /// zenoh's `Config::from_file`; `mode`, the connect endpoints, the listen endpoints (none, in
    /// peer mode) and multicast scouting (off) are then set over it, as the Python SDK's
    /// `zenoh_config_file` does. Its sidecar `<file>.client_id` gives the client id when neither
    /// `client_id` nor `$DRAPE_CLIENT_ID` does ([`deployment_client_id_for`]).
    pub zenoh_config_file: Option<std::path::PathBuf>,
    /// Failover (PROTOCOL.md 11.1, README.md "Failover"; default true): a cloth lost with its
    /// server, or reclaimed while this client was away, is resubmitted with `resume` (its last
    /// received state) to the least loaded live server, under the same handle. false: a cloth
    /// lost with its server is lost (`Event::ClothLost`).
    pub failover: bool,
    /// Failover: a cloth without a state for this long is probed (an empty control); `not_found`
    /// means it was reclaimed. Default 0.5 s.
    pub stall_timeout: Duration,
    /// Failover: how long a lost cloth waits for a live server before it is given up
    /// (`Event::ClothLost`). Default 60 s.
    pub failover_give_up: Duration,
    /// [`Client::open`] waits up to `timeout` for a server's liveliness token (the given
    /// `server_id`'s, else any) and fails with `unavailable` when none appears, instead of
    /// returning a client whose first request then waits the whole timeout. Default false in
    /// Rust; the C ABI sets it unless `DrapeClientOptions.lazy`.
    pub require_server: bool,
    /// 1.8 (PROTOCOL.md 9.3): take every k-th state of each cloth and of the bundle
    /// (`Rate::Every(2)`, `Rate::Every(3)`: 30 and 20 Hz at the default tick; 1.9:
    /// `Rate::Every(6)`, `Rate::Every(12)`: 10 and 5 Hz), each on its own key, or `Rate::Auto`:
    /// full rate, stepped down by itself while states arrive late (and back up after a quiet
    /// period; `crate::rates::Governor`). Default `Rate::Full`. Cloths on a server older than
    /// 1.8 come at full rate, on a 1.8 server at every 3rd state at most. [`Cloth::set_rate`], [`Client::set_bundle_rate`].
    pub rate: Rate,
}

impl Default for ClientOptions {
    fn default() -> Self {
        ClientOptions {
            connect: vec![DEFAULT_ENDPOINT.to_string()],
            namespace: DEFAULT_NAMESPACE.to_string(),
            server_id: None,
            client_id: None,
            timeout: Duration::from_secs(5),
            mode: "peer".to_string(),
            zenoh_config_file: None,
            failover: true,
            stall_timeout: Duration::from_millis(500),
            failover_give_up: Duration::from_secs(60),
            require_server: false,
            rate: Rate::Full,
        }
    }
}

/// Something the caller should know about, queued until [`Client::poll_event`] takes it.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// A server's liveliness token appeared.
    ServerFound { server: String },
    /// A server's liveliness token vanished: it is gone with every cloth it held.
    ServerLost { server: String },
    /// A cloth was lost with its server (no failover, or failover gave up: `error`).
    ClothLost { handle: u64, cloth: String, server: String, error: Error },
    /// Failover (PROTOCOL.md 11.1): the cloth (lost for `reason`) lives on under the same
    /// handle as `cloth` on `server`. `resumed_tick`: the tick (on `old_server`) of the state it
    /// continued from, `None` when it restarted from its rest pose (no state received). `kept`:
    /// its own server still held it (`cloth == old_cloth`, nothing resubmitted).
    ClothResubmitted {
        handle: u64,
        reason: LossReason,
        old_cloth: String,
        old_server: String,
        cloth: String,
        server: String,
        resumed_tick: Option<u64>,
        kept: bool,
    },
    /// A request sent without waiting failed (an error reply, a refused batch item, no reply).
    /// `cloth`: the id of the cloth it was about (empty when none, e.g. a whole batch);
    /// `request`: the number [`Cloth::control_async`] returned (0 for other requests).
    RequestFailed { handle: Option<u64>, cloth: String, request: u64, error: Error },
    /// A control sent with [`Cloth::control_async`] was applied: from `tick` on, with the
    /// cloth's resulting feature set when a 1.2 server reported it.
    RequestDone { request: u64, handle: u64, cloth: String, tick: u64, features: Option<Vec<String>> },
    /// A cloth submitted with [`Client::submit_async`] is live on `server` as `cloth`.
    Submitted { handle: u64, cloth: String, server: String },
    /// A cloth submitted with [`Client::submit_async`] was refused (by every live server,
    /// retries included) or not answered: the handle is lost (`error`).
    SubmitFailed { handle: u64, error: Error },
}

/// Why a cloth failed over.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LossReason {
    /// Its server's liveliness token vanished.
    ServerLost,
    /// Its server no longer has it (`not_found` to a probe after its states stalled, or to a
    /// control): reclaimed while this client was paused or cut off, or the server restarted.
    Reclaimed,
}

pub(crate) struct Inner {
    pub(crate) session: Session,
    pub(crate) keys: Keys,
    pub(crate) client_id: String,
    pub(crate) timeout: Duration,
    /// The failover state (`ClientOptions::failover`).
    pub(crate) fo: Option<failover::Failover>,
    /// The servers' loads and this client's choice of a server (PROTOCOL.md 11.3).
    pub(crate) placement: placement::Placement,
    /// 1.7: the scenes' owners and last requests (a scene kept on one server, founded again by its owner).
    pub(crate) scenes: scenes::SceneBook,
    /// `ClientOptions::server_id` was given: every submission goes there.
    pub(crate) server_given: bool,
    stats_sub: Mutex<Option<Subscriber<()>>>,
    rid: AtomicU64,
    next_handle: AtomicU64,
    pub(crate) servers: Mutex<Servers>,
    pub(crate) servers_cv: Condvar,
    pub(crate) reg: Mutex<recv::Registry>,
    events: Mutex<VecDeque<Event>>,
    events_cv: Condvar,
    pub(crate) closed: AtomicBool,
    pub(crate) bundle_sub: Mutex<Option<Subscriber<()>>>,
    /// 1.8: the rate later submissions start at, and the bundle subscription's rate.
    pub(crate) rate: Mutex<crate::rates::Rate>,
    pub(crate) bundle_rate: Mutex<rates::SubRate>,
    /// 1.5: the keyframe queries sent, one per key in a while for all its cloths.
    pub(crate) keyframes: keyframes::KeyframeQueries,
    /// Requests not waited for are handed to this client's sender thread, which gives them to
    /// Zenoh: the caller (a game thread) never waits on Zenoh's locks or transmission queue.
    sender: std::sync::mpsc::Sender<SendJob>,
    sends: Arc<Sends>,
    watch: Mutex<Option<Subscriber<()>>>,
    token: Mutex<Option<LivelinessToken>>,
}

#[derive(Default)]
pub(crate) struct Servers {
    pub(crate) live: BTreeSet<String>,
    pub(crate) current: Option<String>,
    /// Per server: protocol version and limits from its info reply.
    pub(crate) info: HashMap<String, ((u8, u8), Limits)>,
    /// Per server: its tick rate (Hz) from its info or stats (kept after it is lost: a failover
    /// computes velocities from it).
    pub(crate) rates: HashMap<String, f64>,
}

/// A Drape client. Cheap to share: `Client` is `Send + Sync`; every method may be called from
/// any thread.
#[derive(Clone)]
pub struct Client {
    pub(crate) inner: Arc<Inner>,
}

fn zerr(what: &str, e: impl std::fmt::Display) -> Error {
    Error::new(ErrorCode::Unavailable, scrub(&format!("{what}: {e}")))
}

/// `msg` without the source locations Zenoh's errors carry (`at /home/.../src/x.rs:12.`, the
/// build machine's paths, meaningless to a game and a leak of its layout).
pub fn scrub(msg: &str) -> String {
    let words: Vec<&str> = msg.split(' ').collect();
    let is_loc = |w: &str| {
        let w = w.trim_matches(|c: char| matches!(c, '(' | ')' | '[' | ']' | ',' | '.' | ';' | '"' | '\''));
        w.contains('/') && (w.contains(".rs:") || w.ends_with(".rs"))
    };
    let mut out: Vec<&str> = Vec::with_capacity(words.len());
    for (i, w) in words.iter().enumerate() {
        if is_loc(w) {
            if out.last() == Some(&"at") {
                out.pop();
            }
            continue;
        }
        if *w == "at" && words.get(i + 1).is_some_and(|n| is_loc(n)) {
            continue;
        }
        out.push(w);
    }
    out.join(" ").trim_end().to_string()
}

impl Client {
    /// Open a Zenoh session, declare this client's liveliness token and start watching the
    /// servers' tokens.
    pub fn open(opts: ClientOptions) -> Result<Client> {
        let file = opts.zenoh_config_file.as_deref();
        let client_id = opts.client_id.clone().or_else(|| deployment_client_id_for(file)).unwrap_or_else(random_id);
        if !valid_id(&client_id) {
            return Err(Error::new(ErrorCode::InvalidValue, format!("invalid client id {client_id:?}")));
        }
        if let Some(s) = opts.server_id.as_deref().filter(|s| !valid_id(s)) {
            return Err(Error::new(ErrorCode::InvalidValue, format!("invalid server id {s:?}")));
        }
        if !valid_namespace(&opts.namespace) {
            return Err(Error::new(ErrorCode::InvalidValue, format!("invalid namespace {:?}", opts.namespace)));
        }
        if opts.mode != "peer" && opts.mode != "client" {
            return Err(Error::new(ErrorCode::InvalidValue, format!("mode must be peer or client, not {:?}", opts.mode)));
        }
        let mut cfg = match file {
            Some(path) => zenoh::Config::from_file(path)
                .map_err(|e| Error::new(ErrorCode::InvalidValue, format!("zenoh config file {}: {e}", path.display())))?,
            None => zenoh::Config::default(),
        };
        let json = |v: &[String]| format!("[{}]", v.iter().map(|e| format!("{e:?}")).collect::<Vec<_>>().join(","));
        let set = |cfg: &mut zenoh::Config, k: &str, v: &str| cfg.insert_json5(k, v).map_err(|e| Error::new(ErrorCode::InvalidValue, format!("zenoh config {k} = {v}: {e}")));
        set(&mut cfg, "mode", &format!("{:?}", opts.mode))?;
        set(&mut cfg, "connect/endpoints", &json(&opts.connect))?;
        if opts.mode == "peer" {
            set(&mut cfg, "listen/endpoints", "[]")?;
        }
        set(&mut cfg, "scouting/multicast/enabled", "false")?;
        let session = zenoh::open(cfg).wait().map_err(|e| zerr("cannot open the Zenoh session", e))?;
        let keys = Keys::new(&opts.namespace);
        let placement = placement::Placement::new(&client_id, opts.timeout.min(placement::STATS_WAIT));
        let (sender, jobs) = std::sync::mpsc::channel::<SendJob>();
        let sends = Arc::new(Sends::default());
        let counted = sends.clone();
        std::thread::Builder::new()
            .name("drape-send".into())
            .spawn(move || {
                for job in jobs {
                    // a job that panicked (a bug) must not stop the thread: waited requests count on it
                    let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(job));
                    *counted.sent.lock().unwrap() += 1;
                    counted.cv.notify_all();
                }
            })
            .map_err(|e| Error::new(ErrorCode::Internal, format!("cannot start the sender thread: {e}")))?;
        let inner = Arc::new(Inner {
            session,
            keys,
            client_id,
            timeout: opts.timeout,
            fo: opts.failover.then(|| failover::Failover::new(opts.stall_timeout, opts.failover_give_up)),
            placement,
            scenes: scenes::SceneBook::default(),
            server_given: opts.server_id.is_some(),
            stats_sub: Mutex::new(None),
            rid: AtomicU64::new(1),
            next_handle: AtomicU64::new(1),
            servers: Mutex::new(Servers { current: opts.server_id.clone(), ..Default::default() }),
            servers_cv: Condvar::new(),
            reg: Mutex::new(recv::Registry::default()),
            events: Mutex::new(VecDeque::new()),
            events_cv: Condvar::new(),
            closed: AtomicBool::new(false),
            bundle_sub: Mutex::new(None),
            rate: Mutex::new(opts.rate),
            bundle_rate: Mutex::new(rates::SubRate::new(opts.rate)),
            keyframes: keyframes::KeyframeQueries::default(),
            sender,
            sends,
            watch: Mutex::new(None),
            token: Mutex::new(None),
        });
        placement::subscribe(&inner)?;
        let weak = Arc::downgrade(&inner);
        let watch = inner
            .session
            .liveliness()
            .declare_subscriber(inner.keys.all_servers_alive())
            .history(true)
            .callback(move |s| {
                if let Some(inner) = weak.upgrade() {
                    let id = Keys::last_chunk(s.key_expr().as_str()).to_string();
                    inner.on_server(id, s.kind() == SampleKind::Put);
                }
            })
            .wait()
            .map_err(|e| zerr("liveliness subscriber", e))?;
        *inner.watch.lock().unwrap() = Some(watch);
        let token = inner
            .session
            .liveliness()
            .declare_token(inner.keys.alive_client(&inner.client_id))
            .wait()
            .map_err(|e| zerr("liveliness token", e))?;
        *inner.token.lock().unwrap() = Some(token);
        failover::start(&inner)?;
        let client = Client { inner };
        if opts.require_server {
            let want = opts.server_id.clone();
            let seen = {
                let s = client.inner.servers.lock().unwrap();
                let (s, _) = client.inner.servers_cv
                    .wait_timeout_while(s, opts.timeout, |s| match &want {
                        Some(w) => !s.live.contains(w),
                        None => s.live.is_empty(),
                    })
                    .unwrap();
                match &want {
                    Some(w) => s.live.contains(w),
                    None => !s.live.is_empty(),
                }
            };
            if !seen {
                client.close(false);
                let who = want.map_or("no Drape server".to_string(), |w| format!("server {w:?} not"));
                return Err(Error::new(ErrorCode::Unavailable, format!(
                    "{who} seen (liveliness {}) through {} within {:?}: is `drape serve` running there?",
                    client.inner.keys.all_servers_alive(), opts.connect.join(","), opts.timeout)));
            }
        }
        Ok(client)
    }

    pub fn client_id(&self) -> &str {
        &self.inner.client_id
    }

    /// The server given in the options, or else this client's default server for requests that
    /// name none (`info`): the placement's first choice among the live ones, kept while it is
    /// live (waiting up to the timeout for one). Submissions are placed one by one
    /// (PROTOCOL.md 11.3): see [`Cloth::server`].
    pub fn server_id(&self) -> Result<String> {
        self.inner.server_id()
    }

    /// The last stats publication of `server` (PROTOCOL.md section 10: load, counters, phases;
    /// informational, fields may be added in any minor version), as received on
    /// `{ns}/server/{server}/stats`; None before the first one.
    pub fn stats(&self, server: &str) -> Option<Map> {
        self.inner.placement.stats(server)
    }

    /// Ids of the servers whose liveliness tokens are visible now (a liveliness get).
    pub fn servers(&self, timeout: Duration) -> Result<Vec<String>> {
        let replies = self.inner.session.liveliness().get(self.inner.keys.all_servers_alive()).timeout(timeout).wait()
            .map_err(|e| zerr("liveliness get", e))?;
        let mut out = BTreeSet::new();
        while let Ok(r) = replies.recv() {
            if let Ok(s) = r.result() {
                out.insert(Keys::last_chunk(s.key_expr().as_str()).to_string());
            }
        }
        Ok(out.into_iter().collect())
    }

    /// The next event (server lost, cloth resubmitted or lost, a failed request), if any;
    /// waits up to `timeout` (zero: no wait).
    pub fn poll_event(&self, timeout: Duration) -> Option<Event> {
        let q = self.inner.events.lock().unwrap();
        let (mut q, _) = self.inner.events_cv.wait_timeout_while(q, timeout, |q| q.is_empty()).unwrap();
        q.pop_front()
    }

    /// `server`'s `info` map (asks it: waits up to the timeout).
    pub fn info_of(&self, server: &str) -> Result<Map> {
        self.inner.request(server, "info", encode_info(self.inner.next_rid()))
    }

    /// A server this client knows without asking anyone: the given or current default server,
    /// else the first live one; None before any server was seen. Never blocks.
    pub fn known_server(&self) -> Option<String> {
        let s = self.inner.servers.lock().unwrap();
        s.current.clone().or_else(|| s.live.iter().next().cloned())
    }

    /// The server's `info` map (version, limits, counts...).
    pub fn info(&self) -> Result<Map> {
        let server = self.server_id()?;
        self.inner.request(&server, "info", encode_info(self.inner.next_rid()))
    }

    /// An empty batch of controls (sent with [`Client::send_batch`]).
    pub fn batch(&self) -> Batch {
        Batch::default()
    }

    /// Send a batch control (one request per server and per `max_batch_items`; one control
    /// per item to a 1.0 server). `wait`: return each item's first tick or its error;
    /// otherwise return at once and report failures as [`Event::RequestFailed`].
    pub fn send_batch(&self, batch: Batch, wait: bool) -> Result<Option<Vec<Result<u64>>>> {
        let out = cloth::send_batch(&self.inner, batch, wait)?;
        Ok(out.map(|v| v.into_iter().map(|r| r.map(|a| a.tick)).collect()))
    }

    /// Send a batch control and wait: each item's [`Applied`] (the tick it applies from and,
    /// from a 1.2 server, the cloth's feature set after it) or its error.
    pub fn send_batch_applied(&self, batch: Batch) -> Result<Vec<Result<Applied>>> {
        Ok(cloth::send_batch(&self.inner, batch, true)?.unwrap_or_default())
    }

    /// Remove this client's cloths (if `remove`), withdraw its liveliness token and close the
    /// session. Handles stay valid objects but every call on them fails with `closed`.
    pub fn close(&self, remove: bool) {
        if self.inner.closed.load(Ordering::SeqCst) {
            return;
        }
        if remove {
            let all: Vec<_> = self.inner.reg.lock().unwrap().by_handle.values().cloned().collect();
            for c in all {
                let _ = Cloth { inner: c, client: self.inner.clone() }.remove();
            }
        }
        self.inner.closed.store(true, Ordering::SeqCst);
        if let Some(fo) = self.inner.fo.as_ref() {
            fo.close();
        }
        self.inner.stats_sub.lock().unwrap().take();
        self.inner.reg.lock().unwrap().clear();
        self.inner.bundle_sub.lock().unwrap().take();
        self.inner.watch.lock().unwrap().take();
        self.inner.token.lock().unwrap().take();
        let _ = self.inner.session.close().wait();
    }
}

impl Inner {
    pub(crate) fn next_rid(&self) -> u64 {
        self.rid.fetch_add(1, Ordering::Relaxed)
    }

    pub(crate) fn push_event(&self, e: Event) {
        let mut q = self.events.lock().unwrap();
        if q.len() >= 4096 {
            q.pop_front(); // a caller that never polls must not grow memory without bound
        }
        q.push_back(e);
        self.events_cv.notify_all();
    }

    pub(crate) fn check_open(&self) -> Result<()> {
        if self.closed.load(Ordering::SeqCst) {
            return Err(Error::new(ErrorCode::Closed, "the client is closed"));
        }
        Ok(())
    }

}

/// The environment variable giving this client's id (PROTOCOL.md 11.2), as the Python SDK reads it.
pub const CLIENT_ID_ENV: &str = "DRAPE_CLIENT_ID";

/// The suffix of the client id's sidecar file, appended to the Zenoh configuration file's name
/// (`zenoh-client-tls.json5.client_id`), as the Python SDK reads it.
pub const CLIENT_ID_SIDECAR: &str = ".client_id";

/// The client id the deployment gives this client without a Zenoh configuration file, or None:
/// `$DRAPE_CLIENT_ID` (trimmed, when not empty). Same as `deployment_client_id_for(None)`.
pub fn deployment_client_id() -> Option<String> {
    deployment_client_id_for(None)
}

/// The client id the deployment gives this client, or None, as the Python SDK's
/// `deployment_client_id`: `$DRAPE_CLIENT_ID` (trimmed, when not empty), else the first word of
/// the sidecar file `<zenoh_config_file>.client_id` when there is one (it sits next to the Zenoh
/// file holding the user and password the router binds to that id). [`Client::open`] uses it
/// when [`ClientOptions::client_id`] is None.
pub fn deployment_client_id_for(zenoh_config_file: Option<&std::path::Path>) -> Option<String> {
    client_id_from_env(std::env::var(CLIENT_ID_ENV).ok()).or_else(|| zenoh_config_file.and_then(client_id_from_sidecar))
}

fn client_id_from_env(value: Option<String>) -> Option<String> {
    value.map(|v| v.trim().to_string()).filter(|v| !v.is_empty())
}

fn client_id_from_sidecar(zenoh_config_file: &std::path::Path) -> Option<String> {
    let mut name = zenoh_config_file.as_os_str().to_owned();
    name.push(CLIENT_ID_SIDECAR);
    let text = std::fs::read_to_string(std::path::PathBuf::from(name)).ok()?;
    text.split_whitespace().next().map(str::to_string)
}

fn random_id() -> String {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_nanos());
    h.write_u32(std::process::id());
    format!("c{:016x}", h.finish())
}

#[cfg(test)]
mod tests {
    use super::{client_id_from_env, client_id_from_sidecar};

    #[test]
    fn source_locations_are_scrubbed() {
        let m = "cannot open the Zenoh session: Can not create a new TCP listener bound to tcp/x:1: invalid port \
                 at /root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f/zenoh-link-tcp-1.10.2/src/unicast.rs:360.";
        let s = super::scrub(m);
        assert!(!s.contains(".rs") && !s.contains("/root") && !s.ends_with(" at"), "{s}");
        assert!(s.starts_with("cannot open the Zenoh session: Can not create a new TCP listener bound to tcp/x:1: invalid port"), "{s}");
        assert_eq!(super::scrub("no reply from drape/server/a/info within 5s"), "no reply from drape/server/a/info within 5s");
    }

    #[test]
    fn client_id_from_the_deployment() {
        assert_eq!(client_id_from_env(Some(" game-7\n".into())).as_deref(), Some("game-7"));
        assert_eq!(client_id_from_env(Some("  ".into())), None);
        assert_eq!(client_id_from_env(None), None);
    }

    #[test]
    fn client_id_from_the_sidecar() {
        let dir = std::env::temp_dir().join(format!("drape-sidecar-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("zenoh-client.json5");
        assert_eq!(client_id_from_sidecar(&file), None); // no sidecar
        std::fs::write(dir.join("zenoh-client.json5.client_id"), "alice\nignored\n").unwrap();
        assert_eq!(client_id_from_sidecar(&file).as_deref(), Some("alice"));
        std::fs::write(dir.join("zenoh-client.json5.client_id"), " \n").unwrap();
        assert_eq!(client_id_from_sidecar(&file), None);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
