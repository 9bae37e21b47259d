//! The Zenoh client: a session with this client's liveliness token, server discovery by
//! liveliness, requests (waited for or not), submissions, state reception (single keys and
//! bundles), placement by load (PROTOCOL.md 11.3, protocol 1.4), 1.4 `moves` blocks and, opt-in,
//! the failover of PROTOCOL.md section 11.1 (protocol 1.3): lost or reclaimed cloths resumed on
//! the least loaded live server from their last received states.
mod cloth;
mod failover;
mod moves;
mod placement;
mod predictive;
mod recv;

pub use cloth::{Batch, Cloth, ClothStatus, Counters, StateInfo};

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

/// A request handed to the sender thread.
type SendJob = Box<dyn FnOnce() + Send>;

/// How many requests were handed to the sender thread, and how many it has given to Zenoh: a
/// waited request first waits for the earlier unwaited ones to be sent, so that requests leave
/// in the order they were made.
#[derive(Default)]
struct Sends {
    queued: AtomicU64,
    sent: Mutex<u64>,
    cv: Condvar,
}

impl Sends {
    fn wait_for(&self, n: u64) {
        let g = self.sent.lock().unwrap();
        drop(self.cv.wait_while(g, |sent| *sent < n).unwrap());
    }
}

/// What a request sent without waiting does with its success map (on a Zenoh thread).
pub(crate) type OnOk = Box<dyn Fn(&Arc<Inner>, Map) + Send + Sync>;

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
    bundle_sub: Mutex<Option<Subscriber<()>>>,
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

    /// Submit a grid cloth (`submit` carries the options; its `client` and `rid` are set here).
    pub fn submit_grid(&self, grid: Grid, submit: Submit) -> Result<Cloth> {
        let (rest, tris) = grid_geometry(grid.cols, grid.rows, grid.width, grid.height, grid.orientation, grid.origin)?;
        self.submit(Submit { shape: Shape::Grid(grid), ..submit }, rest, tris)
    }

    /// Submit a triangle mesh cloth.
    pub fn submit_mesh(&self, vertices: Vec<f32>, triangles: Vec<u32>, submit: Submit) -> Result<Cloth> {
        let (rest, tris) = (vertices.clone(), triangles.clone());
        self.submit(Submit { shape: Shape::Mesh(Mesh { vertices, triangles }), ..submit }, rest, tris)
    }

    /// Submit a cloth from Wavefront OBJ text (faces fan-triangulated).
    pub fn submit_obj(&self, obj_text: &str, submit: Submit) -> Result<Cloth> {
        let (v, t) = parse_obj(obj_text)?;
        self.submit_mesh(v, t, submit)
    }

    /// Submit as is (shape included) and subscribe to the cloth's state. `rest`/`triangles`
    /// are kept on the handle for rendering. To the server given in the options, else to the
    /// live server the placement ranks first (PROTOCOL.md 11.3); a refusal another server may not
    /// give (`overloaded`, `busy`, `limit_exceeded`, no reply) tries the next one, and the last
    /// refusal is returned when every live server refused.
    pub fn submit(&self, submit: Submit, rest: Vec<f32>, triangles: Vec<u32>) -> Result<Cloth> {
        self.submit_queued(submit, rest, triangles, 1)
    }

    /// [`Client::submit`] keeping up to `queue_size` states unread per cloth (reads take the
    /// oldest first; 1: only the newest, as `submit`).
    pub fn submit_queued(&self, mut submit: Submit, rest: Vec<f32>, triangles: Vec<u32>, queue_size: usize) -> Result<Cloth> {
        submit.client = self.inner.client_id.clone();
        let handle = self.inner.next_handle.fetch_add(1, Ordering::Relaxed);
        let c = cloth::ClothInner::new(handle, submit, rest, triangles, queue_size);
        self.inner.submit_placed(&c)?;
        Ok(Cloth { inner: c, client: self.inner.clone() })
    }

    /// Submit without waiting: the handle comes back at once, [`ClothStatus::Pending`] until
    /// the reply (reads return nothing, controls fail with `unavailable`); then an
    /// [`Event::Submitted`] (live) or [`Event::SubmitFailed`] (the handle is lost). Placement
    /// as [`Client::submit`], on a thread of its own; a refusal that may pass
    /// ([`ErrorCode::is_retryable`]: `overloaded`, `busy`, `limit_exceeded`) or no reply is
    /// retried for up to `retry_for` (backing off from 50 ms to 1 s). Removing the handle
    /// before the reply cancels it (a cloth placed meanwhile is removed from its server).
    pub fn submit_async(&self, mut submit: Submit, rest: Vec<f32>, triangles: Vec<u32>, queue_size: usize,
                        retry_for: Duration) -> Result<Cloth> {
        self.inner.check_open()?;
        submit.client = self.inner.client_id.clone();
        let handle = self.inner.next_handle.fetch_add(1, Ordering::Relaxed);
        let c = cloth::ClothInner::new(handle, submit, rest, triangles, queue_size);
        let (inner, c2) = (self.inner.clone(), c.clone());
        std::thread::Builder::new()
            .name("drape-submit".into())
            .spawn(move || inner.submit_in_background(c2, retry_for))
            .map_err(|e| Error::new(ErrorCode::Internal, format!("cannot start a submit thread: {e}")))?;
        Ok(Cloth { inner: c, client: self.inner.clone() })
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

    /// [`Client::submit_async`]'s thread.
    fn submit_in_background(self: Arc<Self>, c: Arc<cloth::ClothInner>, retry_for: Duration) {
        let deadline = Instant::now() + retry_for;
        let mut delay = Duration::from_millis(50);
        let cancelled = |c: &cloth::ClothInner| c.cancelled.load(Ordering::SeqCst);
        loop {
            match self.submit_placed(&c) {
                Ok(()) => {
                    let cloth = Cloth { inner: c.clone(), client: self.clone() };
                    if cancelled(&c) {
                        let _ = cloth.remove();
                        return;
                    }
                    let (id, server) = (cloth.id(), cloth.server());
                    self.push_event(Event::Submitted { handle: c.handle, cloth: id, server });
                    return;
                }
                Err(e) if (e.code.is_retryable() || e.code == ErrorCode::Unavailable)
                    && Instant::now() + delay < deadline && !cancelled(&c) && self.check_open().is_ok() => {
                    std::thread::sleep(delay);
                    delay = (delay * 2).min(Duration::from_secs(1));
                }
                Err(error) => {
                    {
                        let mut s = c.slot.lock().unwrap();
                        if s.status == cloth::Status::Pending {
                            s.status = cloth::Status::Lost(error.clone());
                        }
                    }
                    c.cv.notify_all();
                    if !cancelled(&c) {
                        self.push_event(Event::SubmitFailed { handle: c.handle, error });
                    }
                    return;
                }
            }
        }
    }

    pub(crate) fn check_open(&self) -> Result<()> {
        if self.closed.load(Ordering::SeqCst) {
            return Err(Error::new(ErrorCode::Closed, "the client is closed"));
        }
        Ok(())
    }

    fn on_server(self: &Arc<Self>, id: String, alive: bool) {
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
    fn client_scoped(&self, server: &str, timeout: Duration) -> bool {
        self.server_info_within(server, timeout).map(|(v, _)| v >= (1, 4)).unwrap_or(false)
    }

    /// Whether `server`'s info (version) is known.
    fn info_known(&self, server: &str) -> bool {
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

    /// A request not waited for: failures become [`Event::RequestFailed`]; `on_ok` gets a
    /// success map (on a Zenoh thread).
    /// `watch`: the cloth (and its id then) whose `not_found` answer means it was reclaimed.
    pub(crate) fn send(self: &Arc<Self>, server: &str, kind: &str, payload: Vec<u8>, handle: Option<u64>,
                       on_ok: Option<OnOk>,
                       watch: Option<(std::sync::Weak<cloth::ClothInner>, String)>) -> Result<()> {
        self.send_request(server, kind, payload, handle, on_ok, watch, 0)
    }

    /// [`Inner::send`] with the request number of an asynchronous control (0: none), carried
    /// by its failure event.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn send_request(self: &Arc<Self>, server: &str, kind: &str, payload: Vec<u8>, handle: Option<u64>,
                       on_ok: Option<OnOk>,
                       watch: Option<(std::sync::Weak<cloth::ClothInner>, String)>, request: u64) -> Result<()> {
        self.check_open()?;
        let key = self.request_key(server, kind, self.timeout);
        struct Done {
            inner: std::sync::Weak<Inner>,
            answered: AtomicBool,
            key: String,
            handle: Option<u64>,
            cloth: String,
            request: u64,
        }
        impl Drop for Done {
            fn drop(&mut self) {
                if !self.answered.load(Ordering::SeqCst) {
                    if let Some(i) = self.inner.upgrade() {
                        let error = Error::new(ErrorCode::Unavailable, format!("no reply from {}", self.key));
                        i.push_event(Event::RequestFailed { handle: self.handle, cloth: self.cloth.clone(), request: self.request, error });
                    }
                }
            }
        }
        let cloth = watch.as_ref().map(|w| w.1.clone()).unwrap_or_default();
        let done = Done { inner: Arc::downgrade(self), answered: AtomicBool::new(false), key: key.clone(), handle, cloth, request };
        let (session, timeout) = (self.session.clone(), self.timeout);
        let job = move || {
            // an error here drops the callback unanswered: its Done reports the request failed
            let _ = session
                .get(&key)
                .payload(payload)
                .timeout(timeout)
                .callback(move |r| {
                    done.answered.store(true, Ordering::SeqCst);
                    let Some(inner) = done.inner.upgrade() else { return };
                    match reply_result(&done.key, r) {
                        Ok(m) => {
                            if let Some(f) = &on_ok {
                                f(&inner, m)
                            }
                        }
                        Err(error) => {
                            if let (ErrorCode::NotFound, Some((c, id))) = (error.code, &watch) {
                                if let Some(c) = c.upgrade() {
                                    failover::cloth_not_found(&inner, &c, id);
                                }
                            }
                            inner.push_event(Event::RequestFailed { handle: done.handle, cloth: done.cloth.clone(), request: done.request, error })
                        }
                    }
                })
                .wait();
        };
        self.sends.queued.fetch_add(1, Ordering::SeqCst);
        self.sender.send(Box::new(job)).map_err(|_| {
            self.sends.queued.fetch_sub(1, Ordering::SeqCst);
            Error::new(ErrorCode::Closed, "the client is closed")
        })
    }

    /// Submit `c`'s stored request to `server` and start receiving its states.
    /// `resume` (1.3, failover): the state it continues from.
    pub(crate) fn place(self: &Arc<Self>, c: &Arc<cloth::ClothInner>, server: &str, resume: Option<Resume>) -> Result<SubmitReply> {
        self.check_open()?;
        let bundled = c.submit.state.and_then(|s| s.bundle).unwrap_or(false);
        if bundled {
            self.ensure_bundle_sub()?;
            self.reg.lock().unwrap().pending_bundled += 1;
        }
        let mut req = c.submit.clone();
        req.rid = self.next_rid();
        req.resume = resume;
        let ticket = self.placement.placing(server, c.n_vertices as u64); // counted there until its next stats
        let res = self.request(server, "submit", req.encode()).and_then(|m| SubmitReply::from_map(&m));
        self.placement.placed(ticket, res.is_ok());
        let out = res.and_then(|rep| recv::attach(self, c, server, rep.clone()).map(|_| rep));
        if bundled {
            let mut reg = self.reg.lock().unwrap();
            reg.pending_bundled -= 1;
            if reg.pending_bundled == 0 {
                reg.orphans.clear();
            }
        }
        out
    }

    fn ensure_bundle_sub(self: &Arc<Self>) -> Result<()> {
        let mut b = self.bundle_sub.lock().unwrap();
        if b.is_none() {
            let weak = Arc::downgrade(self);
            let sub = self
                .session
                .declare_subscriber(self.keys.bundle(&self.client_id))
                .callback(move |s| {
                    if let Some(inner) = weak.upgrade() {
                        recv::on_bundle(&inner, s.payload().clone());
                    }
                })
                .wait()
                .map_err(|e| zerr("bundle subscriber", e))?;
            *b = Some(sub);
        }
        Ok(())
    }

    /// Refuse a control that uses 1.2 fields (`features_add` / `features_remove`) toward a
    /// server older than 1.2, which would ignore them silently (PROTOCOL.md section 5.2).
    pub(crate) fn check_version(&self, server: &str, ctl: &Control) -> Result<()> {
        let needs_1_5 = ctl.state.is_some_and(|s| s.needs_1_5());
        if !ctl.needs_1_2() && !needs_1_5 {
            return Ok(());
        }
        let ((ma, mi), _) = self.server_info(server)?;
        if needs_1_5 && (ma, mi) < (1, 5) {
            return Err(Error::new(
                ErrorCode::InvalidValue,
                format!("the predictive encoding and state.step need a protocol 1.5 server; server {server} speaks {ma}.{mi}"),
            ));
        }
        if !ctl.needs_1_2() {
            return Ok(());
        }
        if (ma, mi) < (1, 2) {
            return Err(Error::new(
                ErrorCode::InvalidValue,
                format!("features_add / features_remove need a protocol 1.2 server; server {server} speaks {ma}.{mi} \
                         (it would ignore them): send the whole set with `features` instead"),
            ));
        }
        Ok(())
    }

    /// A control of one cloth (waited for: the tick it applies from and, 1.2, the cloth's
    /// features). The features a reply reports are kept on the cloth, waited for or not.
    pub(crate) fn control(self: &Arc<Self>, c: &Arc<cloth::ClothInner>, mut ctl: Control, wait: bool) -> Result<Option<Applied>> {
        let (server, id, token, n) = c.owner()?;
        ctl.cloth = id;
        ctl.token = token;
        ctl.validate(&self.limits(&server), Some(n))?;
        self.check_version(&server, &ctl)?;
        let payload = ctl.encode(self.next_rid());
        c.note_sent(&ctl);
        if wait {
            let m = match self.request(&server, "control", payload) {
                Err(e) if e.code == ErrorCode::NotFound => {
                    failover::cloth_not_found(self, c, &ctl.cloth);
                    return Err(e);
                }
                r => r?,
            };
            let a = Applied::from_map(&m)?;
            c.note_applied(&a);
            return Ok(Some(a));
        }
        let weak = Arc::downgrade(c);
        let on_ok = move |_: &Arc<Inner>, m: Map| {
            if let (Some(c), Ok(a)) = (weak.upgrade(), Applied::from_map(&m)) {
                c.note_applied(&a);
            }
        };
        let watch = Some((Arc::downgrade(c), ctl.cloth.clone()));
        self.send(&server, "control", payload, Some(c.handle), Some(Box::new(on_ok)), watch)?;
        Ok(None)
    }
}

impl Inner {
    /// A control sent without waiting whose outcome is an event: [`Event::RequestDone`] or
    /// [`Event::RequestFailed`], both with `request` (returned here). Never waits on the network:
    /// when the cloth's server's info (limits, keys) is not known yet, the control is validated
    /// and sent from a thread of its own.
    pub(crate) fn control_async(self: &Arc<Self>, c: &Arc<cloth::ClothInner>, mut ctl: Control) -> Result<u64> {
        let (server, id, token, n) = c.owner()?;
        ctl.cloth = id;
        ctl.token = token;
        let request = self.next_rid();
        if self.info_known(&server) {
            self.send_control(c, ctl, request, &server, n)?;
        } else {
            let (inner, c) = (self.clone(), c.clone());
            std::thread::spawn(move || {
                let cloth = ctl.cloth.clone();
                if let Err(error) = inner.send_control(&c, ctl, request, &server, n) {
                    inner.push_event(Event::RequestFailed { handle: Some(c.handle), cloth, request, error });
                }
            });
        }
        Ok(request)
    }

    fn send_control(self: &Arc<Self>, c: &Arc<cloth::ClothInner>, ctl: Control, request: u64, server: &str, n: u32) -> Result<()> {
        ctl.validate(&self.limits(server), Some(n))?;
        self.check_version(server, &ctl)?;
        let payload = ctl.encode(request);
        c.note_sent(&ctl);
        let (weak, handle, id) = (Arc::downgrade(c), c.handle, ctl.cloth.clone());
        let on_ok = move |inner: &Arc<Inner>, m: Map| match Applied::from_map(&m) {
            Ok(a) => {
                if let Some(c) = weak.upgrade() {
                    c.note_applied(&a);
                }
                inner.push_event(Event::RequestDone { request, handle, cloth: id.clone(), tick: a.tick, features: a.features });
            }
            Err(error) => inner.push_event(Event::RequestFailed { handle: Some(handle), cloth: id.clone(), request, error }),
        };
        let watch = Some((Arc::downgrade(c), ctl.cloth.clone()));
        self.send_request(server, "control", payload, Some(handle), Some(Box::new(on_ok)), watch, request)
    }
}

/// A reply's outcome: an `ok` map, the server's error, or `unavailable` for Zenoh's own errors.
fn reply_result(key: &str, r: zenoh::query::Reply) -> Result<Map> {
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
