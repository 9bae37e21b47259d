//! A submitted cloth: its handle (stable across failover), its newest state read into caller
//! buffers, its controls (waited for or not), batch controls and removal.
use super::predictive::Pred;
use super::recv::{Buf, Latest};
use super::{Event, Inner};
use crate::wire::error::{Error, ErrorCode, Result};
use crate::wire::msg::{ControlBatch, Pins, Submit};
use crate::wire::replies::{tick_of, Applied, BatchReply};
use crate::smoothing::{sample_into, Frame, ServerClock, MAX_AHEAD};
use crate::wire::{decode_state_into, parse_state, Collider, Control, Encoding, MeshCollider};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::{Arc, Condvar, Mutex, Weak};
use std::time::{Duration, Instant};
use zenoh::pubsub::Subscriber;

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Status {
    Pending,
    Live,
    Resubmitting,
    Lost(Error),
    Removed,
}

pub(crate) struct Slot {
    pub(crate) status: Status,
    pub(crate) server: String,
    pub(crate) id: String,
    pub(crate) token: String,
    pub(crate) key: String,
    pub(crate) bundle_key: Option<String>,
    pub(crate) first_tick: u64,
    pub(crate) sub: Option<Subscriber<()>>,
    pub(crate) latest: Option<Latest>,
    /// The state received before `latest` from the same placement (failover velocities; a
    /// reference to the received payload, nothing copied).
    pub(crate) prev: Option<Latest>,
    /// When the last state arrived (or the cloth was placed), and when it was last probed
    /// (failover's stall detection).
    pub(crate) last_receipt: Instant,
    pub(crate) last_probe: Instant,
    /// States received and not read yet, oldest first (at most `ClothInner::queue_size`; the
    /// newest of them is `latest`). References to the received payloads, nothing copied.
    pub(crate) unread: VecDeque<Latest>,
    pub(crate) counters: Counters,
    /// The tick of the newest state received from the current placement (0: none yet).
    pub(crate) last_tick: u64,
    /// 1.2: the feature set the newest control reply reported, with that reply's tick.
    pub(crate) features: Option<(u64, Vec<String>)>,
    /// Render times (client clock) as server times ([`Cloth::sample`]), from the states received.
    pub(crate) clock: ServerClock,
    /// 1.8: the rate its states come at (a bundled cloth: its bundle's) and its governor.
    pub(crate) rate: super::rates::SubRate,
}

/// What the game last sent by controls that a failover sends again (PROTOCOL.md 11.1): the last
/// target of each pinned vertex moved, and the last collider list.
#[derive(Default)]
pub(crate) struct Sent {
    pub(crate) pins: HashMap<u32, [f32; 3]>,
    pub(crate) colliders: Option<Vec<Collider>>,
    /// 1.8: the whole mesh collider last sent by a control at its last pose, or its removal.
    pub(crate) mesh: Option<MeshCollider>,
}

/// What became of the states of a cloth (cumulative over its placements). Every tick from the
/// first state received on a placement to the last is accounted for exactly once:
/// `read + replaced + missed + unread + undecodable == ticks`
/// (`received == read + replaced + unread + undecodable`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Counters {
    /// States received (in tick order; stale and invalid ones not counted).
    pub received: u64,
    /// States decoded by a read (`read_state`, `wait_state`, `latest_state`).
    pub read: u64,
    /// States received but dropped unread: a newer one replaced them (queue full, or a
    /// `latest_state` read skipped them).
    pub replaced: u64,
    /// Ticks of which no state arrived (gaps in the tick numbers between received states;
    /// 1.8: at every k-th state, the stream's states that did not arrive, a switch of rate
    /// rounded up).
    pub missed: u64,
    /// States received and waiting to be read now.
    pub unread: u64,
    /// Ticks spanned: from the first state received on each placement to the newest (1.8: at
    /// every k-th state, the stream's states spanned).
    pub ticks: u64,
    /// Payloads that were not valid states.
    pub invalid: u64,
    /// States older than one already received (out of order), ignored.
    pub stale: u64,
    /// Tick of the newest state received (current placement), 0 before any.
    pub last_tick: u64,
    /// 1.5, the predictive encoding: states decoded on delivery (keyframes among them).
    pub decoded: u64,
    /// 1.5: keyframes (intra-coded states) among `decoded`.
    pub keyframes: u64,
    /// 1.5: states received but predicted from one this client lacks (a state lost, a late
    /// join): not shown (the last state stays) while the cloth waits for a keyframe.
    pub undecodable: u64,
    /// 1.5: keyframe queries sent for it (one per query key at most every 100 ms for the whole
    /// client: of a bundle's cloths missing one state, one asks; `Client::keyframe_queries`:
    /// all of them).
    pub keyframe_requests: u64,
}

pub(crate) struct ClothInner {
    pub(crate) handle: u64,
    /// States kept unread (1: only the newest, the default).
    pub(crate) queue_size: usize,
    /// An asynchronous submission was cancelled (removed before its reply).
    pub(crate) cancelled: std::sync::atomic::AtomicBool,
    /// The client's copy of the submission (resubmitted as is on failover).
    pub(crate) submit: Submit,
    pub(crate) rest: Vec<f32>,
    pub(crate) triangles: Vec<u32>,
    pub(crate) n_vertices: u32,
    pub(crate) slot: Mutex<Slot>,
    /// 1.5: the predictive stream its states are decoded by on delivery (when both are held,
    /// `slot` is locked first).
    pub(crate) pred: Mutex<Pred>,
    pub(crate) cv: Condvar,
    pub(crate) sent: Mutex<Sent>,
    /// [`Cloth::sample`]'s last two states decoded (each decoded once, however many frames
    /// sample between them).
    pub(crate) smooth: Mutex<Smooth>,
}

/// A state decoded for [`Cloth::sample`]: which one (tick, server and receive times) and its
/// positions.
#[derive(Default)]
pub(crate) struct Decoded {
    key: Option<(u64, u64, u64)>,
    server_time_ns: u64,
    positions: Vec<f32>,
}

/// The two states [`Cloth::sample`] blends: `prev` and `last` as last decoded.
#[derive(Default)]
pub(crate) struct Smooth {
    prev: Decoded,
    last: Decoded,
    /// The cloth's clock offset when they were taken.
    offset: Option<i64>,
}

impl Smooth {
    /// Make `last` (and `prev`, if given) hold those states, decoding only what they do not
    /// hold yet (the newest state of one frame is the older one of a later frame: swapped).
    fn hold(&mut self, prev: Option<&Latest>, last: &Latest, n: usize) -> Result<()> {
        let key = |l: &Latest| l.buf.with(|d| parse_state(&d[l.off..l.off + l.len]).map(|h| (h.tick, h.server_time_ns, l.receive_time_ns)));
        let (kl, kp) = (Some(key(last)?), prev.map(key).transpose()?);
        if self.last.key != kl {
            if self.prev.key == kl || (kp.is_some() && self.last.key == kp) {
                std::mem::swap(&mut self.prev, &mut self.last);
            }
            if self.last.key != kl {
                self.last.fill(last, n)?;
            }
        }
        if let (Some(p), true) = (prev, kp.is_some() && self.prev.key != kp) {
            self.prev.fill(p, n)?;
        }
        Ok(())
    }
}

impl Decoded {
    fn fill(&mut self, l: &Latest, n: usize) -> Result<()> {
        self.key = None;
        self.positions.resize(3 * n, 0.0);
        let info = decode(l, &mut self.positions, None)?;
        self.key = Some((info.tick, info.server_time_ns, info.receive_time_ns));
        self.server_time_ns = info.server_time_ns;
        Ok(())
    }

    fn frame(&self) -> Frame<'_> {
        Frame { server_time_ns: self.server_time_ns, positions: &self.positions }
    }
}

impl ClothInner {
    pub(crate) fn new(handle: u64, submit: Submit, rest: Vec<f32>, triangles: Vec<u32>, queue_size: usize) -> Arc<ClothInner> {
        let n_vertices = submit.vertex_count() as u32;
        let slot = Slot {
            status: Status::Pending,
            server: String::new(),
            id: String::new(),
            token: String::new(),
            key: String::new(),
            bundle_key: None,
            first_tick: 0,
            sub: None,
            latest: None,
            prev: None,
            last_receipt: Instant::now(),
            last_probe: Instant::now(),
            unread: VecDeque::new(),
            counters: Counters::default(),
            last_tick: 0,
            features: None,
            clock: ServerClock::default(),
            rate: super::rates::SubRate::new(crate::rates::Rate::Full),
        };
        Arc::new(ClothInner {
            handle,
            queue_size: queue_size.max(1),
            cancelled: std::sync::atomic::AtomicBool::new(false),
            submit,
            rest,
            triangles,
            n_vertices,
            slot: Mutex::new(slot),
            pred: Mutex::new(Pred::default()),
            cv: Condvar::new(),
            sent: Mutex::new(Sent::default()),
            smooth: Mutex::new(Smooth::default()),
        })
    }

    /// Remember the pin targets, colliders and (1.8) mesh collider of a control about to be sent
    /// (a failover sends the last ones again); a reset drops the pin targets, as the server does. No allocation
    /// once each pinned vertex has been seen.
    pub(crate) fn note_sent(&self, ctl: &Control) {
        if ctl.pins.is_none() && ctl.colliders.is_none() && !ctl.reset && ctl.mesh_collider.is_none() {
            return;
        }
        if let Some(p) = &ctl.pins {
            self.note_pins(&p.indices, &p.targets);
        }
        let mut sent = self.sent.lock().unwrap();
        if let Some(c) = &ctl.colliders {
            sent.colliders = Some(c.clone());
        }
        if let Some(mc) = &ctl.mesh_collider {
            let last = sent.mesh.take().or_else(|| self.submit.mesh_collider.clone());
            sent.mesh = Some(mc.applied_to(last.as_ref()));
        }
        if ctl.reset {
            sent.pins.clear();
        }
    }

    /// Remember pin targets about to be sent (a control's or a 1.4 moves block's).
    pub(crate) fn note_pins(&self, indices: &[u32], targets: &[f32]) {
        let mut sent = self.sent.lock().unwrap();
        for (i, t) in indices.iter().zip(targets.chunks_exact(3)) {
            sent.pins.insert(*i, [t[0], t[1], t[2]]);
        }
    }

    /// Keep the feature set a control reply reported (replies may arrive out of order: the
    /// one applied at the latest tick wins).
    pub(crate) fn note_applied(&self, a: &Applied) {
        if let Some(f) = &a.features {
            let mut s = self.slot.lock().unwrap();
            if s.features.as_ref().is_none_or(|(t, _)| *t <= a.tick) {
                s.features = Some((a.tick, f.clone()));
            }
        }
    }

    /// (server, cloth id, token, vertex count) of a live cloth, else why it is not live.
    pub(crate) fn owner(&self) -> Result<(String, String, String, u32)> {
        let s = self.slot.lock().unwrap();
        match &s.status {
            Status::Live => Ok((s.server.clone(), s.id.clone(), s.token.clone(), self.n_vertices)),
            Status::Lost(e) => Err(e.clone()),
            Status::Resubmitting => Err(Error::new(ErrorCode::Unavailable, "the cloth is being resubmitted to another server")),
            Status::Removed => Err(Error::new(ErrorCode::Closed, "the cloth was removed")),
            Status::Pending => Err(Error::new(ErrorCode::Unavailable, "the cloth is not submitted yet")),
        }
    }
}

/// The lock if it is free within a short spin, else None (never parks the thread).
fn lock_briefly<T>(m: &Mutex<T>) -> Option<std::sync::MutexGuard<'_, T>> {
    for _ in 0..200 {
        match m.try_lock() {
            Ok(g) => return Some(g),
            Err(std::sync::TryLockError::Poisoned(p)) => return Some(p.into_inner()),
            Err(std::sync::TryLockError::WouldBlock) => std::hint::spin_loop(),
        }
    }
    None
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Read {
    Next,
    Latest,
}

fn decode(l: &Latest, positions: &mut [f32], normals: Option<&mut [f32]>) -> Result<StateInfo> {
    let h = l.buf.with(|d| decode_state_into(&d[l.off..l.off + l.len], positions, normals))?;
    // a predictive state, decoded on delivery, is kept as float32: say what it was
    let encoding = if matches!(l.buf, Buf::D(_)) { Encoding::Predictive } else { h.encoding };
    Ok(StateInfo {
        tick: h.tick,
        server_time_ns: h.server_time_ns,
        receive_time_ns: l.receive_time_ns,
        vertex_count: h.vertex_count,
        flags: h.flags,
        encoding,
        has_normals: h.has_normals(),
        reset: h.is_reset(),
        bounds_min: h.bounds_min,
        bounds_max: h.bounds_max,
    })
}

/// [`Cloth::status`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClothStatus {
    Pending,
    Live,
    Resubmitting,
    Lost,
    Removed,
}

/// What a read state was: every header field plus the local receive time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StateInfo {
    pub tick: u64,
    pub server_time_ns: u64,
    pub receive_time_ns: u64,
    pub vertex_count: u32,
    pub flags: u16,
    pub encoding: Encoding,
    pub has_normals: bool,
    pub reset: bool,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
}

/// A submitted cloth. `Send + Sync`; clones share the same cloth.
#[derive(Clone)]
pub struct Cloth {
    pub(crate) inner: Arc<ClothInner>,
    pub(crate) client: Arc<Inner>,
}

impl std::fmt::Debug for Cloth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Cloth({}, {:?}, {} vertices)", self.inner.handle, self.id(), self.inner.n_vertices)
    }
}

impl Cloth {
    /// This client's handle number: stable for the cloth's life, failover included.
    pub fn handle(&self) -> u64 {
        self.inner.handle
    }
    /// The server's cloth id (changes when failover resubmits the cloth).
    pub fn id(&self) -> String {
        self.inner.slot.lock().unwrap().id.clone()
    }
    pub fn server(&self) -> String {
        self.inner.slot.lock().unwrap().server.clone()
    }
    /// The cloth's ownership token on its current server (PROTOCOL.md section 11: keep it
    /// secret; it changes when failover resubmits the cloth).
    pub fn token(&self) -> String {
        self.inner.slot.lock().unwrap().token.clone()
    }
    /// The cloth's state key, as its submit reply gave it (`{ns}/cloth/{cloth}/state`, or 1.4's
    /// `{ns}/client/{client}/cloth/{cloth}/state` when submitted on a client-scoped key); a
    /// bundled cloth's states arrive in the client's bundle instead.
    pub fn state_key(&self) -> String {
        self.inner.slot.lock().unwrap().key.clone()
    }
    pub fn vertex_count(&self) -> u32 {
        self.inner.n_vertices
    }
    /// Rest positions (xyz interleaved) and triangles, for rendering.
    pub fn rest_positions(&self) -> &[f32] {
        &self.inner.rest
    }
    pub fn triangles(&self) -> &[u32] {
        &self.inner.triangles
    }
    /// Whether states arrive in the client's bundle (acknowledged by the server).
    pub fn bundled(&self) -> bool {
        self.inner.slot.lock().unwrap().bundle_key.is_some()
    }
    /// The first tick whose state includes the cloth (of its current placement).
    pub fn first_tick(&self) -> u64 {
        self.inner.slot.lock().unwrap().first_tick
    }
    /// States received, states replaced before they were read, invalid payloads.
    pub fn counters(&self) -> (u64, u64, u64) {
        let s = self.inner.slot.lock().unwrap();
        (s.counters.received, s.counters.replaced, s.counters.invalid)
    }

    /// Every counter of the cloth's states ([`Counters`]: received, read, replaced, missed...).
    pub fn state_counters(&self) -> Counters {
        let s = self.inner.slot.lock().unwrap();
        Counters { unread: s.unread.len() as u64, last_tick: s.last_tick, ..s.counters }
    }

    /// 1.5: forget what the cloth's predictive stream holds, as a client that lost a state or
    /// joined late: its next predicted state is a gap (a keyframe is asked for). For tests.
    #[doc(hidden)]
    pub fn forget_predictive_stream(&self) {
        self.inner.pred.lock().unwrap().forget();
    }

    /// States kept unread per cloth (the `queue_size` it was submitted with; 1: the newest only).
    pub fn queue_size(&self) -> usize {
        self.inner.queue_size
    }

    /// Where the cloth stands: pending (an asynchronous submission not answered yet), live,
    /// resubmitting (failover), lost, removed.
    pub fn status(&self) -> ClothStatus {
        match self.inner.slot.lock().unwrap().status {
            Status::Pending => ClothStatus::Pending,
            Status::Live => ClothStatus::Live,
            Status::Resubmitting => ClothStatus::Resubmitting,
            Status::Lost(_) => ClothStatus::Lost,
            Status::Removed => ClothStatus::Removed,
        }
    }

    /// Decode the next state not read yet into `positions` (and `normals` if given and the
    /// state has them): the oldest unread one (with `queue_size` 1, the newest); `Ok(None)`
    /// when nothing new arrived. Buffers need `3 * vertex_count` floats. Errors: `server_lost`
    /// (without failover), `closed` (removed).
    pub fn read_state(&self, positions: &mut [f32], normals: Option<&mut [f32]>) -> Result<Option<StateInfo>> {
        self.read(positions, normals, Duration::ZERO, Read::Next)
    }

    /// Like [`Cloth::read_state`], waiting up to `timeout` for a new state.
    pub fn wait_state(&self, positions: &mut [f32], normals: Option<&mut [f32]>, timeout: Duration) -> Result<Option<StateInfo>> {
        self.read(positions, normals, timeout, Read::Next)
    }

    /// The newest state even if it was read before (`Ok(None)` before the first one). Unread
    /// states older than it are dropped (counted as `replaced`).
    pub fn latest_state(&self, positions: &mut [f32], normals: Option<&mut [f32]>) -> Result<Option<StateInfo>> {
        self.read(positions, normals, Duration::ZERO, Read::Latest)
    }

    /// The positions to draw at render time `now_ns` (client clock, Unix ns as
    /// [`StateInfo::receive_time_ns`]; None: now), written into `positions` (`3 * vertex_count`
    /// floats): the last two states received interpolated `delay` (None: one tick, the time
    /// between them) behind the newest, mapped onto the server's clock by the cloth's
    /// [`Cloth::clock_offset_ns`], so that a renderer faster than the server moves the cloth
    /// every frame, at the cost of that delay; `extrapolate`: carried past the newest state
    /// instead (no delay; up to one state interval, overshooting where the motion turns).
    /// `Ok(false)` before the first state (nothing written); the newest state alone while there
    /// is one. Reads nothing from the queue (`read_state` and its counters are unchanged); each
    /// state is decoded once however many frames sample it. Never blocks (a state being
    /// delivered at that instant: the states held before it are sampled). Errors as
    /// [`Cloth::read_state`]. (The Python SDK's `ClothHandle.sample`, `client/smoothing.py`.)
    pub fn sample(&self, now_ns: Option<u64>, delay: Option<Duration>, extrapolate: bool, positions: &mut [f32]) -> Result<bool> {
        self.client.check_open()?;
        let c = &self.inner;
        let n = c.n_vertices as usize;
        if positions.len() < 3 * n {
            return Err(Error::new(ErrorCode::InvalidValue, format!(
                "a buffer of {} floats: {} floats (3 per vertex) needed", positions.len(), 3 * n)));
        }
        let mut smooth = c.smooth.lock().unwrap(); // the game's threads only
        // a state being delivered holds the slot: the states and clock offset held last time
        if let Some(s) = lock_briefly(&c.slot) {
            match &s.status {
                Status::Lost(e) => return Err(e.clone()),
                Status::Removed => return Err(Error::new(ErrorCode::Closed, "the cloth was removed")),
                _ => {}
            }
            let Some(last) = s.latest.clone() else { return Ok(false) };
            let (prev, offset) = (s.prev.clone(), s.clock.offset_ns());
            drop(s);
            smooth.hold(prev.as_ref(), &last, n)?;
            if prev.is_none() {
                smooth.prev.key = None;
            }
            smooth.offset = offset;
        }
        if smooth.last.key.is_none() {
            return Ok(false);
        }
        let Some(offset) = smooth.offset else {
            positions[..3 * n].copy_from_slice(&smooth.last.positions);
            return Ok(true);
        };
        let server_ns = now_ns.unwrap_or_else(super::recv::now_ns) as i64 - offset;
        let prev = smooth.prev.key.map(|_| smooth.prev.frame());
        let delay = delay.map(|d| d.as_nanos() as i64);
        Ok(sample_into(prev, Some(smooth.last.frame()), server_ns, delay, extrapolate, MAX_AHEAD, positions))
    }

    /// The client clock minus the server's, as the cloth's states measure it: the smallest
    /// `receive_time_ns - server_time_ns` of its last 120 states (the clock offset plus the
    /// network's shortest delay); None before any state. [`Cloth::sample`] maps render times by it.
    pub fn clock_offset_ns(&self) -> Option<i64> {
        self.inner.slot.lock().unwrap().clock.offset_ns()
    }

    fn read(&self, positions: &mut [f32], normals: Option<&mut [f32]>, timeout: Duration, how: Read) -> Result<Option<StateInfo>> {
        self.client.check_open()?;
        let c = &self.inner;
        let need = 3 * c.n_vertices as usize;
        if positions.len() < need || normals.as_ref().is_some_and(|n| n.len() < need) {
            return Err(Error::new(ErrorCode::InvalidValue, format!(
                "buffers of {} and {} floats: {need} floats (3 per vertex) needed",
                positions.len(), normals.as_ref().map_or(0, |n| n.len()))));
        }
        let next = how == Read::Next;
        let waiting = |s: &mut Slot| next && s.unread.is_empty() && matches!(s.status, Status::Live | Status::Resubmitting);
        let mut s = if timeout.is_zero() {
            // never waits: a Zenoh thread delivering a state holds the slot for a microsecond,
            // but if it is preempted meanwhile a game thread would wait for it; then nothing
            // is read now and the state stays queued for the next read
            match lock_briefly(&c.slot) {
                Some(g) => g,
                None => return Ok(None),
            }
        } else {
            c.cv.wait_timeout_while(c.slot.lock().unwrap(), timeout, waiting).unwrap().0
        };
        match &s.status {
            Status::Lost(e) => return Err(e.clone()),
            Status::Removed => return Err(Error::new(ErrorCode::Closed, "the cloth was removed")),
            _ => {}
        }
        let l = if next {
            match s.unread.pop_front() {
                Some(l) => l,
                None => return Ok(None),
            }
        } else {
            let skipped = s.unread.len().saturating_sub(1) as u64;
            let fresh = !s.unread.is_empty();
            s.unread.clear();
            s.counters.replaced += skipped;
            let Some(l) = s.latest.clone() else { return Ok(None) };
            if !fresh {
                // read before: decoded again, not counted again
                drop(s);
                return decode(&l, positions, normals).map(Some);
            }
            l
        };
        s.counters.read += 1;
        drop(s);
        decode(&l, positions, normals).map(Some)
    }
    /// Move pinned vertices `indices` to `targets` (3 floats each). `wait`: return the tick
    /// it applies from; otherwise return at once (failures become events).
    pub fn move_pins(&self, indices: &[u32], targets: &[f32], wait: bool) -> Result<Option<u64>> {
        let ctl = Control { pins: Some(Pins { indices: indices.to_vec(), targets: targets.to_vec() }), ..Default::default() };
        self.control(ctl, wait)
    }

    /// Any control (its `cloth` and `token` are filled in here). `wait`: the tick it applies
    /// from; otherwise return at once (failures become events).
    pub fn control(&self, ctl: Control, wait: bool) -> Result<Option<u64>> {
        Ok(self.client.control(&self.inner, ctl, wait)?.map(|a| a.tick))
    }

    /// Any control, not waited for, whose outcome comes as an event carrying the number
    /// returned here: [`super::Event::RequestDone`] (tick, features) or
    /// [`super::Event::RequestFailed`]. Never waits on the network.
    pub fn control_async(&self, ctl: Control) -> Result<u64> {
        self.client.control_async(&self.inner, ctl)
    }

    /// Any control, waited for: the tick it applies from and, from a 1.2 server, the cloth's
    /// feature set after it ([`Applied::features`]).
    pub fn apply(&self, ctl: Control) -> Result<Applied> {
        Ok(self.client.control(&self.inner, ctl, true)?.expect("a waited control has a reply"))
    }

    /// 1.2: switch features on (`add`) and off (`remove`), keeping the others (PROTOCOL.md
    /// section 5.2; names from [`crate::wire::FEATURE_NAMES`], none in both lists). Needs a 1.2
    /// server (`invalid_value` otherwise, nothing sent). `wait`: the reply, with the resulting
    /// set; otherwise return at once (the set is kept for [`Cloth::features`] when it comes).
    pub fn change_features(&self, add: &[&str], remove: &[&str], wait: bool) -> Result<Option<Applied>> {
        let list = |v: &[&str]| (!v.is_empty()).then(|| v.iter().map(|x| x.to_string()).collect());
        let ctl = Control { features_add: list(add), features_remove: list(remove), ..Default::default() };
        self.client.control(&self.inner, ctl, wait)
    }

    /// 1.2: the cloth's feature set as the server last reported it in a control reply (waited
    /// for or not, batch replies included), in the protocol's order; `None` before any such
    /// reply, from a server older than 1.2, and after a failover resubmission until the next.
    pub fn features(&self) -> Option<Vec<String>> {
        self.inner.slot.lock().unwrap().features.as_ref().map(|(_, f)| f.clone())
    }

    /// Back to the rest pose with zero velocity.
    pub fn reset(&self, wait: bool) -> Result<Option<u64>> {
        self.control(Control { reset: true, ..Default::default() }, wait)
    }

    /// Remove the cloth: the last tick a state of it may have been published for. A cloth
    /// lost with its server is just forgotten (`Ok(0)`).
    pub fn remove(&self) -> Result<u64> {
        let c = &self.inner;
        let owner = c.owner();
        let tick = match owner {
            Ok((server, id, token, _)) => {
                let payload = crate::wire::msg::encode_remove(&id, &token, self.client.next_rid());
                match self.client.request(&server, "remove", payload) {
                    Ok(m) => tick_of(&m)?,
                    Err(e) if e.code == ErrorCode::NotFound => 0,
                    Err(e) => return Err(e),
                }
            }
            Err(e) if e.code == ErrorCode::ServerLost => 0,
            // an asynchronous submission not answered yet: cancelled (removed if placed meanwhile)
            Err(_) if c.slot.lock().unwrap().status == Status::Pending => {
                c.cancelled.store(true, std::sync::atomic::Ordering::SeqCst);
                0
            }
            // its asynchronous submission failed: never placed, nothing to remove
            Err(_) if c.slot.lock().unwrap().id.is_empty() => 0,
            // placed by an asynchronous submission meanwhile
            Err(_) if c.slot.lock().unwrap().status == Status::Live => return self.remove(),
            // being failed over: forgotten (the failover worker drops it)
            Err(_) if c.slot.lock().unwrap().status == Status::Resubmitting => 0,
            Err(e) => return Err(e),
        };
        let (id, sub) = {
            let mut s = c.slot.lock().unwrap();
            s.status = Status::Removed;
            (s.id.clone(), s.sub.take())
        };
        drop(sub);
        let mut reg = self.client.reg.lock().unwrap();
        reg.by_handle.remove(&c.handle);
        reg.by_id.remove(&id);
        drop(reg);
        c.cv.notify_all();
        Ok(tick)
    }
}

/// Controls of many cloths, sent as batch controls by [`super::Client::send_batch`] (to a 1.4
/// server, pins-only items of several cloths sharing one index list as one `moves` block).
#[derive(Default, Clone)]
pub struct Batch {
    pub(crate) items: Vec<(Arc<ClothInner>, Control)>,
}

impl Batch {
    pub fn add(&mut self, cloth: &Cloth, ctl: Control) -> &mut Self {
        self.items.push((cloth.inner.clone(), ctl));
        self
    }
    pub fn move_pins(&mut self, cloth: &Cloth, indices: &[u32], targets: &[f32]) -> &mut Self {
        let pins = Pins { indices: indices.to_vec(), targets: targets.to_vec() };
        self.add(cloth, Control { pins: Some(pins), ..Default::default() })
    }
    /// 1.2: an item switching features on and off (as [`Cloth::change_features`]).
    pub fn change_features(&mut self, cloth: &Cloth, add: &[&str], remove: &[&str]) -> &mut Self {
        let list = |v: &[&str]| (!v.is_empty()).then(|| v.iter().map(|x| x.to_string()).collect());
        self.add(cloth, Control { features_add: list(add), features_remove: list(remove), ..Default::default() })
    }
    pub fn len(&self) -> usize {
        self.items.len()
    }
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }
}

pub(crate) fn send_batch(inner: &Arc<Inner>, batch: Batch, wait: bool) -> Result<Option<Vec<Result<Applied>>>> {
    let mut results: Vec<Result<Applied>> = vec![Ok(Applied::default()); batch.items.len()];
    let mut by_server: BTreeMap<String, Vec<(usize, Arc<ClothInner>, Control)>> = BTreeMap::new();
    for (i, (c, mut ctl)) in batch.items.into_iter().enumerate() {
        match c.owner() {
            Ok((server, id, token, n)) => {
                ctl.cloth = id;
                ctl.token = token;
                match ctl.validate(&inner.limits(&server), Some(n)).and_then(|_| inner.check_version(&server, &ctl)) {
                    Ok(()) => {
                        c.note_sent(&ctl);
                        by_server.entry(server).or_default().push((i, c, ctl))
                    }
                    Err(e) => results[i] = Err(e),
                }
            }
            Err(e) => results[i] = Err(e),
        }
    }
    if !wait {
        if let Some(e) = results.iter().find_map(|r| r.as_ref().err()) {
            return Err(e.clone()); // nothing is sent when an item is invalid here
        }
    }
    for (server, mut items) in by_server {
        let (version, lim) = inner.server_info(&server)?;
        if version >= (1, 4) {
            // 1.4: pins-only items sharing one index list go as one moves block
            super::moves::take_block(inner, &server, &mut items, wait, &mut results)?;
        }
        if lim.max_batch_items == 0 {
            for (i, c, ctl) in items {
                // a 1.0 server: one control per item (validated again there, on the same data)
                match inner.control(&c, ctl, wait) {
                    Err(e) if !wait => return Err(e),
                    r => results[i] = r.map(Option::unwrap_or_default),
                }
            }
            continue;
        }
        for chunk in items.chunks(lim.max_batch_items) {
            let req = ControlBatch { rid: inner.next_rid(), client: inner.client_id.clone(), items: chunk.iter().map(|x| x.2.clone()).collect() };
            if wait {
                match inner.request(&server, "control_batch", req.encode()).and_then(|m| BatchReply::from_map(&m)) {
                    Ok(rep) => {
                        for ((i, c, ctl), r) in chunk.iter().zip(rep.results) {
                            if let Ok(a) = &r {
                                c.note_applied(a);
                            }
                            let r = r.map_err(|e| e.into_error());
                            if r.as_ref().is_err_and(|e| e.code == ErrorCode::NotFound) {
                                super::failover::cloth_not_found(inner, c, &ctl.cloth);
                            }
                            results[*i] = r;
                        }
                    }
                    Err(e) => chunk.iter().for_each(|(i, _, _)| results[*i] = Err(e.clone())),
                }
            } else {
                let cloths: Vec<(u64, Weak<ClothInner>, String)> =
                    chunk.iter().map(|x| (x.1.handle, Arc::downgrade(&x.1), x.2.cloth.clone())).collect();
                let on_ok = move |inner: &Arc<Inner>, m: crate::wire::reader::Map| match BatchReply::from_map(&m) {
                    Ok(rep) => {
                        for ((h, c, id), r) in cloths.iter().zip(rep.results) {
                            match r {
                                Ok(a) => {
                                    if let Some(c) = c.upgrade() {
                                        c.note_applied(&a);
                                    }
                                }
                                Err(e) => {
                                    let error = e.into_error();
                                    if let (ErrorCode::NotFound, Some(c)) = (error.code, c.upgrade()) {
                                        super::failover::cloth_not_found(inner, &c, id);
                                    }
                                    inner.push_event(Event::RequestFailed { handle: Some(*h), cloth: id.clone(), request: 0, error })
                                }
                            }
                        }
                    }
                    Err(error) => inner.push_event(Event::RequestFailed { handle: None, cloth: String::new(), request: 0, error }),
                };
                inner.send(&server, "control_batch", req.encode(), None, Some(Box::new(on_ok)), None)?;
            }
        }
    }
    Ok(if wait { Some(results) } else { None })
}
