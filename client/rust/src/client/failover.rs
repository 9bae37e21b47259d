//! Lost servers: when a server's liveliness token vanishes its cloths are marked lost and
//! reported; with the opt-in failover a worker thread resubmits each of them, from the
//! client's own copy of its submission, to another live server under the same handle.
use super::cloth::Status;
use super::{Event, Inner};
use crate::wire::error::{Error, ErrorCode};
use std::sync::{mpsc, Arc};

pub(crate) fn start_worker(inner: &Arc<Inner>) {
    let (tx, rx) = mpsc::channel::<String>();
    *inner.worker.lock().unwrap() = Some(tx);
    let weak = Arc::downgrade(inner);
    std::thread::Builder::new()
        .name("drape-failover".into())
        .spawn(move || {
            while let Ok(lost) = rx.recv() {
                let Some(inner) = weak.upgrade() else { break };
                resubmit_all(&inner, &lost);
            }
        })
        .expect("cannot start the failover thread");
}

/// Called on the Zenoh thread when `server`'s token vanished.
pub(crate) fn server_lost(inner: &Arc<Inner>, server: &str) {
    let failover = inner.failover && inner.worker.lock().unwrap().is_some();
    if failover {
        let mut s = inner.servers.lock().unwrap();
        if s.current.as_deref() == Some(server) {
            s.current = None;
        }
    }
    let cloths: Vec<_> = inner.reg.lock().unwrap().by_handle.values().cloned().collect();
    let lost_error = Error::new(ErrorCode::ServerLost, format!("server {server} lost its liveliness (it is gone, with its cloths)"));
    for c in cloths {
        let mut s = c.slot.lock().unwrap();
        if s.server != server || s.status != Status::Live {
            continue;
        }
        s.status = if failover { Status::Resubmitting } else { Status::Lost(lost_error.clone()) };
        let id = s.id.clone();
        drop(s);
        c.cv.notify_all();
        if !failover {
            inner.push_event(Event::ClothLost { handle: c.handle, cloth: id, server: server.to_string(), error: lost_error.clone() });
        }
    }
    if failover {
        if let Some(tx) = inner.worker.lock().unwrap().as_ref() {
            let _ = tx.send(server.to_string());
        }
    }
}

fn resubmit_all(inner: &Arc<Inner>, lost: &str) {
    let target = {
        let s = inner.servers.lock().unwrap();
        let (mut s, _) = inner.servers_cv.wait_timeout_while(s, inner.timeout, |s| s.live.iter().all(|x| x == lost)).unwrap();
        let t = s.live.iter().find(|x| *x != lost).cloned();
        if s.current.is_none() {
            s.current = t.clone();
        }
        t
    };
    let cloths: Vec<_> = inner.reg.lock().unwrap().by_handle.values().cloned().collect();
    for c in cloths {
        let (old_id, old_sub) = {
            let mut s = c.slot.lock().unwrap();
            if s.server != lost || s.status != Status::Resubmitting {
                continue;
            }
            (s.id.clone(), s.sub.take())
        };
        drop(old_sub);
        let res = match &target {
            Some(t) => inner.place(&c, t),
            None => Err(Error::new(ErrorCode::Unavailable, format!("no live server to resubmit to after {lost} was lost"))),
        };
        match res {
            Ok(rep) => inner.push_event(Event::ClothResubmitted {
                handle: c.handle,
                old_cloth: old_id,
                cloth: rep.cloth,
                server: target.clone().unwrap_or_default(),
            }),
            Err(error) => {
                c.slot.lock().unwrap().status = Status::Lost(error.clone());
                c.cv.notify_all();
                inner.push_event(Event::ClothLost { handle: c.handle, cloth: old_id, server: lost.to_string(), error });
            }
        }
    }
}
