//! Failover (PROTOCOL.md section 11.1, protocol 1.3), opt-in with `ClientOptions::failover`.
//!
//! Detection: a server's liveliness token vanishes (every cloth on it is lost), or a cloth was
//! reclaimed while this client was paused or cut off: its states stalled and a probe (an empty
//! control) is answered `not_found`, or a control of the game is answered `not_found`.
//!
//! Recovery, on this module's one worker thread: if the cloth's own server is live again, the
//! cloth is probed there first and kept when it still exists; otherwise it is resubmitted, from
//! the client's copy of its submission plus `resume` (the positions of its last received state
//! and the velocities of its last two), to the live server the placement ranks first
//! (PROTOCOL.md 11.3, `placement.rs`: by the servers' stats, this client's submissions not yet in
//! them counted, so a burst of resubmissions spreads by load), under the same handle. A refusal
//! another server may not give (`overloaded`, `busy`, `limit_exceeded`, no reply) tries the next
//! server; any other error means the request itself is wrong and the cloth is lost with it. The last pin targets and colliders the game sent are
//! sent again right after, and an [`Event::ClothResubmitted`] reports it.
//!
//! Scenes (1.7, PROTOCOL.md 5.3's SDK note, `scenes.rs`): a scene's lost cloths go to one server
//! (that of this client's cloths of it still live, else the placement's choice); its owner's
//! first cloth founds it there and the scene's last state (members, colliders, mesh) is sent again
//! before its next; a member waits up to `SCENE_WAIT` for a live server holding the scene and
//! retries on `forbidden` until the owner admitted it again.
//!
//! Per state nothing is copied or decoded for this: a cloth keeps references to its last two
//! received payloads (the buffers Zenoh delivered); they are decoded only when a failover needs
//! them.
use super::cloth::{ClothInner, Status};
use super::recv::Latest;
use super::{Event, Inner, LossReason};
use crate::wire::error::{Error, ErrorCode};
use crate::wire::msg::{Control, Pins, Resume};
use crate::wire::placement::PLACE_ELSEWHERE;
use crate::wire::decode_state_into;
use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// The tick rate assumed when the lost server's stats and info never said (Hz).
pub(crate) const DEFAULT_TICK_RATE: f64 = 60.0;
/// The bound of resumed velocities (PROTOCOL.md 4.1: `max_acceleration`, m/s).
const MAX_VELOCITY: f64 = 1e4;

struct LostCloth {
    cloth: Arc<ClothInner>,
    server: String,
    reason: LossReason,
    since: Instant,
}

/// The failover state of one client.
pub(crate) struct Failover {
    pub(crate) stall_timeout: Duration,
    pub(crate) give_up_after: Duration,
    lost: Mutex<HashMap<u64, LostCloth>>,
    cv: Condvar,
}

impl Failover {
    pub(crate) fn new(stall_timeout: Duration, give_up_after: Duration) -> Failover {
        Failover {
            stall_timeout,
            give_up_after,
            lost: Mutex::new(HashMap::new()),
            cv: Condvar::new(),
        }
    }

    pub(crate) fn wake(&self) {
        let _g = self.lost.lock().unwrap();
        self.cv.notify_all();
    }

    pub(crate) fn close(&self) {
        self.lost.lock().unwrap().clear();
        self.cv.notify_all();
    }
}

/// Start the worker thread (the servers' stats come through the placement's subscription).
pub(crate) fn start(inner: &Arc<Inner>) -> crate::wire::Result<()> {
    if inner.fo.is_none() {
        return Ok(());
    }
    let weak = Arc::downgrade(inner);
    std::thread::Builder::new()
        .name("drape-failover".into())
        .spawn(move || loop {
            let Some(inner) = weak.upgrade() else { break };
            if inner.closed.load(std::sync::atomic::Ordering::SeqCst) {
                break;
            }
            let fo = inner.fo.as_ref().expect("failover state");
            let todo: Vec<(u64, Arc<ClothInner>, String, LossReason, Instant)> = {
                let g = fo.lost.lock().unwrap();
                let (g, _) = fo.cv.wait_timeout(g, Duration::from_millis(100)).unwrap();
                g.iter().map(|(h, l)| (*h, l.cloth.clone(), l.server.clone(), l.reason, l.since)).collect()
            };
            if inner.closed.load(std::sync::atomic::Ordering::SeqCst) {
                break;
            }
            if !todo.is_empty() {
                recover(&inner, todo);
            }
            watch(&inner);
        })
        .map_err(|e| Error::new(ErrorCode::Internal, format!("cannot start the failover thread: {e}")))?;
    Ok(())
}

/// Called on a Zenoh thread when `server`'s liveliness token vanished.
pub(crate) fn server_lost(inner: &Arc<Inner>, server: &str) {
    {
        let mut s = inner.servers.lock().unwrap();
        if inner.fo.is_some() && s.current.as_deref() == Some(server) {
            s.current = None;
        }
    }
    let cloths: Vec<_> = inner.reg.lock().unwrap().by_handle.values().cloned().collect();
    let lost_error = Error::new(ErrorCode::ServerLost, format!("server {server} lost its liveliness (it is gone, with its cloths)"));
    for c in cloths {
        if inner.fo.is_some() {
            let on_it = { c.slot.lock().unwrap().server == server };
            if on_it {
                cloth_lost(inner, &c, LossReason::ServerLost);
            }
            continue;
        }
        let mut s = c.slot.lock().unwrap();
        if s.server != server || s.status != Status::Live {
            continue;
        }
        s.status = Status::Lost(lost_error.clone());
        let id = s.id.clone();
        drop(s);
        c.cv.notify_all();
        inner.push_event(Event::ClothLost { handle: c.handle, cloth: id, server: server.to_string(), error: lost_error.clone() });
    }
}

/// A request about cloth `id` was answered `not_found`: when `id` is still the cloth's current
/// id, it was reclaimed (or its server restarted) and fails over.
pub(crate) fn cloth_not_found(inner: &Arc<Inner>, c: &Arc<ClothInner>, id: &str) {
    if inner.fo.is_none() {
        return;
    }
    let current = { c.slot.lock().unwrap().id == id };
    if current {
        cloth_lost(inner, c, LossReason::Reclaimed);
    }
}

/// Mark a live cloth lost and hand it to the worker.
fn cloth_lost(inner: &Arc<Inner>, c: &Arc<ClothInner>, reason: LossReason) {
    let Some(fo) = inner.fo.as_ref() else { return };
    let server = {
        let mut s = c.slot.lock().unwrap();
        if s.status != Status::Live {
            return;
        }
        s.status = Status::Resubmitting;
        s.server.clone()
    };
    c.cv.notify_all();
    let mut lost = fo.lost.lock().unwrap();
    lost.entry(c.handle).or_insert(LostCloth { cloth: c.clone(), server, reason, since: Instant::now() });
    fo.cv.notify_all();
}

fn done(inner: &Inner, handle: u64) {
    if let Some(fo) = inner.fo.as_ref() {
        fo.lost.lock().unwrap().remove(&handle);
    }
}

type Lost = (Arc<ClothInner>, String, String, LossReason, Instant); // cloth, old server, old id, reason, since

fn recover(inner: &Arc<Inner>, todo: Vec<(u64, Arc<ClothInner>, String, LossReason, Instant)>) {
    let mut scenes: Vec<(String, Vec<Lost>)> = Vec::new(); // 1.7: each scene's lost cloths, in order
    for (handle, c, old_server, reason, since) in todo {
        let (status, old_id, token) = {
            let s = c.slot.lock().unwrap();
            (s.status.clone(), s.id.clone(), s.token.clone())
        };
        if status != Status::Resubmitting || inner.closed.load(std::sync::atomic::Ordering::SeqCst) {
            done(inner, handle); // removed meanwhile
            continue;
        }
        let live = inner.servers.lock().unwrap().live.contains(&old_server);
        if live && probe(inner, &old_server, &old_id, &token).is_ok() {
            // Its server is back (or this client's link was), and the cloth with it.
            {
                let mut s = c.slot.lock().unwrap();
                if s.status == Status::Resubmitting {
                    s.status = Status::Live;
                    s.last_receipt = Instant::now();
                }
            }
            c.cv.notify_all();
            done(inner, handle);
            inner.push_event(Event::ClothResubmitted {
                handle,
                reason,
                old_cloth: old_id.clone(),
                old_server: old_server.clone(),
                cloth: old_id,
                server: old_server,
                resumed_tick: None,
                kept: true,
            });
            continue;
        }
        match c.submit.scene.clone() {
            None => {
                resubmit(inner, &c, &old_server, &old_id, reason, since, None, false);
            }
            Some(scene) => {
                let item = (c, old_server, old_id, reason, since);
                match scenes.iter_mut().find(|(s, _)| *s == scene) {
                    Some((_, items)) => items.push(item),
                    None => scenes.push((scene, vec![item])),
                }
            }
        }
    }
    for (scene, items) in scenes {
        recover_scene(inner, &scene, items);
    }
}

/// A scene's lost cloths to one server (PROTOCOL.md 5.3's SDK note): the server of this client's
/// cloths of it still live, else, for its owner, the placement's choice, its first cloth founding
/// the scene there and the scene's last state sent again before the next; a member waits (up to
/// `SCENE_WAIT`) for a live server that holds the scene, retrying on `forbidden`.
fn recover_scene(inner: &Arc<Inner>, scene: &str, items: Vec<Lost>) {
    let owner = inner.scenes.owner(scene) == Some(true);
    for (c, old_server, old_id, reason, since) in items {
        let mut target = inner.scene_server(scene, c.handle);
        let founds = target.is_none();
        if target.is_none() && !owner {
            target = inner.locate_scene(scene);
            if target.is_none() && since.elapsed() < super::scenes::SCENE_WAIT {
                return; // its owner has not founded it again yet: the next pass
            }
        }
        if !resubmit(inner, &c, &old_server, &old_id, reason, since, target.as_deref(), !owner) {
            return; // stays lost (or was given up): the scene's next cloths wait too
        }
        if founds && owner {
            let server = c.slot.lock().unwrap().server.clone();
            inner.replay_scene(scene, &server);
        }
    }
}

/// An empty control (PROTOCOL.md 11.1's probe), waited for: `Ok` while the cloth exists.
fn probe(inner: &Inner, server: &str, id: &str, token: &str) -> crate::wire::Result<()> {
    let payload = Control::new(id, token).encode(inner.next_rid());
    inner.request_within(server, "control", payload, inner.timeout.min(Duration::from_secs(2))).map(|_| ())
}

/// The `resume` of a resubmission from the cloth's last two received states (PROTOCOL.md 4.1):
/// the newer one's positions; velocities `(x_k - x_{k-1}) / (dt (t_k - t_{k-1}))` when both
/// exist, are finite and in tick order. `None` when no finite state was received.
pub(crate) fn resume_from(prev: Option<&Latest>, last: Option<&Latest>, n: usize, tick_rate: f64,
                          from_server: &str, cloth: &str) -> Option<Resume> {
    let last = last?;
    let mut positions = vec![0f32; 3 * n];
    let h = last.buf.with(|d| decode_state_into(&d[last.off..last.off + last.len], &mut positions, None)).ok()?;
    if positions.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let mut velocities = None;
    if let Some(p) = prev {
        let mut before = vec![0f32; 3 * n];
        if let Ok(hp) = p.buf.with(|d| decode_state_into(&d[p.off..p.off + p.len], &mut before, None)) {
            if hp.tick < h.tick && before.iter().all(|x| x.is_finite()) {
                let dt = (h.tick - hp.tick) as f64 / tick_rate;
                for (b, x) in before.iter_mut().zip(&positions) {
                    *b = ((*x as f64 - *b as f64) / dt).clamp(-MAX_VELOCITY, MAX_VELOCITY) as f32;
                }
                velocities = Some(before);
            }
        }
    }
    Some(Resume {
        positions,
        velocities,
        tick: Some(h.tick),
        from_server: crate::wire::valid_id(from_server).then(|| from_server.to_string()),
        cloth: crate::wire::valid_id(cloth).then(|| cloth.to_string()),
    })
}

/// Resubmit `c` to `only` (None: the live servers by load); true once placed. `retry_forbidden`:
/// a `forbidden` (a member's cloth whose scene's owner has not admitted it again) leaves it lost
/// for the next pass.
#[allow(clippy::too_many_arguments)]
fn resubmit(inner: &Arc<Inner>, c: &Arc<ClothInner>, old_server: &str, old_id: &str, reason: LossReason, since: Instant,
            only: Option<&str>, retry_forbidden: bool) -> bool {
    let (prev, last, old_sub) = {
        let mut s = c.slot.lock().unwrap();
        (s.prev.clone(), s.latest.clone(), s.sub.take())
    };
    drop(old_sub); // outside the slot's lock: its callback takes it
    let rate = inner.servers.lock().unwrap().rates.get(old_server).copied().unwrap_or(DEFAULT_TICK_RATE);
    let resume = resume_from(prev.as_ref(), last.as_ref(), c.n_vertices as usize, rate, old_server, old_id);
    let resumed_tick = resume.as_ref().and_then(|r| r.tick);
    let mut tried = HashSet::new();
    let mut last_err = None;
    let mut wrong = false;
    // the best live server not tried yet (PROTOCOL.md 11.3; no wait for stats: a loss is urgent)
    let next = |tried: &HashSet<String>| match only {
        Some(s) => (!tried.contains(s) && inner.live_servers().iter().any(|l| l == s)).then(|| s.to_string()),
        None => inner.placement.ranked(&inner.live_servers(), tried, false).into_iter().next(),
    };
    while let Some(target) = next(&tried) {
        tried.insert(target.clone());
        // 1.8: a cloth with its own mesh only onto a server that speaks mesh colliders
        if let Err(e) = inner.check_mesh_version(&target, c.submit.mesh_collider.as_ref()) {
            last_err = Some(e);
            continue;
        }
        match inner.place(c, &target, resume.clone()) {
            Ok(rep) => {
                {
                    let mut s = inner.servers.lock().unwrap();
                    if s.current.is_none() {
                        s.current = Some(target.clone());
                    }
                }
                done(inner, c.handle);
                resend_controls(inner, c);
                inner.push_event(Event::ClothResubmitted {
                    handle: c.handle,
                    reason,
                    old_cloth: old_id.to_string(),
                    old_server: old_server.to_string(),
                    cloth: rep.cloth,
                    server: target,
                    resumed_tick,
                    kept: false,
                });
                return true;
            }
            // overloaded, busy, limit_exceeded, no reply: the next best server
            Err(e) if PLACE_ELSEWHERE.contains(&e.code) => last_err = Some(e),
            // 1.7: not admitted into the scene again yet (its owner refounds it): the next pass
            Err(e) if retry_forbidden && e.code == ErrorCode::Forbidden => {
                last_err = Some(e);
                break;
            }
            // the request itself is wrong (PROTOCOL.md 11.3): no server will take it
            Err(e) => {
                last_err = Some(e);
                wrong = true;
                break;
            }
        }
    }
    let give_up = inner.fo.as_ref().map_or(Duration::ZERO, |f| f.give_up_after);
    if wrong || since.elapsed() >= give_up {
        let error = last_err.unwrap_or_else(|| {
            Error::new(ErrorCode::Unavailable, format!("no live server to fail cloth {old_id} over to within {give_up:?}"))
        });
        done(inner, c.handle);
        c.slot.lock().unwrap().status = Status::Lost(error.clone());
        c.cv.notify_all();
        inner.push_event(Event::ClothLost { handle: c.handle, cloth: old_id.to_string(), server: old_server.to_string(), error });
    }
    // else: stays lost; tried again on the next pass (a server may appear)
    false
}

/// After a resubmission: the last pin targets, colliders and mesh collider the game sent, as one control (not
/// waited for; a failure becomes an event).
fn resend_controls(inner: &Arc<Inner>, c: &Arc<ClothInner>) {
    let ctl = {
        let sent = c.sent.lock().unwrap();
        let mut idx: Vec<u32> = sent.pins.keys().copied().collect();
        idx.sort_unstable();
        let targets: Vec<f32> = idx.iter().flat_map(|i| sent.pins[i]).collect();
        Control {
            pins: (!idx.is_empty()).then_some(Pins { indices: idx, targets }),
            colliders: sent.colliders.clone(),
            // 1.8: the mesh last set, at its last pose (or its removal)
            mesh_collider: sent.mesh.clone().filter(|m| m.remove || m.is_new_mesh()),
            ..Default::default()
        }
    };
    if ctl.pins.is_none() && ctl.colliders.is_none() && ctl.mesh_collider.is_none() {
        return;
    }
    if let Err(error) = inner.control(c, ctl, false) {
        let cloth = c.slot.lock().unwrap().id.clone();
        inner.push_event(Event::RequestFailed { handle: Some(c.handle), cloth, request: 0, error });
    }
}

/// Cloths whose states stalled for `stall_timeout`: probed without waiting; `not_found` means
/// reclaimed.
fn watch(inner: &Arc<Inner>) {
    let Some(fo) = inner.fo.as_ref() else { return };
    let now = Instant::now();
    let cloths: Vec<_> = inner.reg.lock().unwrap().by_handle.values().cloned().collect();
    for c in cloths {
        let (server, id, token) = {
            let mut s = c.slot.lock().unwrap();
            if s.status != Status::Live || now - s.last_receipt < fo.stall_timeout || now - s.last_probe < fo.stall_timeout {
                continue;
            }
            s.last_probe = now;
            (s.server.clone(), s.id.clone(), s.token.clone())
        };
        let payload = Control::new(&id, &token).encode(inner.next_rid());
        let weak = Arc::downgrade(inner);
        let cw = Arc::downgrade(&c);
        let key = inner.request_key(&server, "control", inner.timeout.min(Duration::from_secs(2)));
        let _ = inner
            .session
            .get(key.clone())
            .payload(payload)
            .timeout(inner.timeout.min(Duration::from_secs(2)))
            .callback(move |r| {
                let (Some(inner), Some(c)) = (weak.upgrade(), cw.upgrade()) else { return };
                if let Err(e) = super::reply_result(&key, r) {
                    if e.code == ErrorCode::NotFound {
                        cloth_not_found(&inner, &c, &id);
                    }
                }
            })
            .wait();
    }
}

#[cfg(test)]
mod tests {
    use super::super::recv::{Buf, Latest};
    use super::resume_from;
    use crate::wire::{encode_state, Encoding};
    use std::sync::Arc;

    fn state(tick: u64, positions: &[f32]) -> Latest {
        let data = encode_state(tick, 0, positions, None, Encoding::Float32, 0).unwrap();
        let len = data.len();
        Latest { buf: Buf::V(Arc::new(data)), off: 0, len, receive_time_ns: 0 }
    }

    #[test]
    fn resume_positions_and_velocities_from_the_last_two_states() {
        let (a, b) = ([0.0, 1.0, 0.0, 1.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0, 0.9, 0.2]);
        let r = resume_from(Some(&state(10, &a)), Some(&state(12, &b)), 2, 60.0, "s1", "c1").unwrap();
        assert_eq!((r.positions.as_slice(), r.tick, r.from_server.as_deref(), r.cloth.as_deref()), (&b[..], Some(12), Some("s1"), Some("c1")));
        let v = r.velocities.unwrap();
        let want = [0.0, 0.0, 0.0, 0.0, -3.0, 6.0]; // (b - a) / (2 ticks / 60 Hz)
        assert!(v.iter().zip(want).all(|(x, w)| (x - w).abs() < 1e-4), "{v:?}");
        // one state: positions only; none: no resume; out of order: no velocities
        assert!(resume_from(None, Some(&state(12, &b)), 2, 60.0, "s1", "c1").unwrap().velocities.is_none());
        assert!(resume_from(None, None, 2, 60.0, "s1", "c1").is_none());
        assert!(resume_from(Some(&state(12, &a)), Some(&state(12, &b)), 2, 60.0, "s1", "c1").unwrap().velocities.is_none());
        // velocities are clamped to the protocol's bound
        let far = [0.0, 1.0, 0.0, 1.0e3, 1.0, 0.0];
        let r = resume_from(Some(&state(1, &a)), Some(&state(2, &far)), 2, 60.0, "s1", "c1").unwrap();
        assert_eq!(r.velocities.as_ref().unwrap()[3], 1.0e4);
        r.validate(2, &Default::default()).unwrap();
    }
}
