//! Requests not waited for: handed to the client's sender thread (a game thread never waits on
//! Zenoh), their failures turned into events and their successes handed to a callback.
use super::*;

/// A request handed to the sender thread.
pub(crate) type SendJob = Box<dyn FnOnce() + Send>;

/// How many requests were handed to the sender thread, and how many it has given to Zenoh: a
/// waited request first waits for the earlier unwaited ones to be sent, so that requests leave
/// in the order they were made.
#[derive(Default)]
pub(crate) struct Sends {
    pub(crate) queued: AtomicU64,
    pub(crate) sent: Mutex<u64>,
    pub(crate) cv: Condvar,
}

impl Sends {
    pub(crate) fn wait_for(&self, n: u64) {
        let g = self.sent.lock().unwrap();
        drop(self.cv.wait_while(g, |sent| *sent < n).unwrap());
    }
}

/// What a request sent without waiting does with its success map (on a Zenoh thread).
pub(crate) type OnOk = Box<dyn Fn(&Arc<Inner>, Map) + Send + Sync>;

impl Inner {
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
}
