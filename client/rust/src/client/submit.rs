//! Submissions: the client's submit calls (waited for, queued, asynchronous with retries), a
//! cloth placed on a server (its submit request, its state subscription, the client's bundle
//! subscription).
use super::*;

impl Client {
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
        c.slot.lock().unwrap().rate = rates::SubRate::new(*self.inner.rate.lock().unwrap());
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
        c.slot.lock().unwrap().rate = rates::SubRate::new(*self.inner.rate.lock().unwrap());
        let (inner, c2) = (self.inner.clone(), c.clone());
        std::thread::Builder::new()
            .name("drape-submit".into())
            .spawn(move || inner.submit_in_background(c2, retry_for))
            .map_err(|e| Error::new(ErrorCode::Internal, format!("cannot start a submit thread: {e}")))?;
        Ok(Cloth { inner: c, client: self.inner.clone() })
    }
}

impl Inner {
    /// [`Client::submit_async`]'s thread.
    pub(crate) fn submit_in_background(self: Arc<Self>, c: Arc<cloth::ClothInner>, retry_for: Duration) {
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

    /// Submit `c`'s stored request to `server` and start receiving its states.
    /// `resume` (1.3, failover): the state it continues from.
    pub(crate) fn place(self: &Arc<Self>, c: &Arc<cloth::ClothInner>, server: &str, resume: Option<Resume>) -> Result<SubmitReply> {
        self.check_open()?;
        self.check_mesh_version(server, c.submit.mesh_collider.as_ref())?; // 1.8: an older server would ignore it
        let bundled = c.submit.state.and_then(|s| s.bundle).unwrap_or(false);
        if bundled {
            rates::bundle_placing(self, server)?; // 1.8: an older server's bundles come on the full-rate key
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

    pub(crate) fn ensure_bundle_sub(self: &Arc<Self>) -> Result<()> {
        let mut b = self.bundle_sub.lock().unwrap();
        if b.is_none() {
            let k = self.bundle_rate.lock().unwrap().rate; // 1.8: every k-th bundle, on its own key
            *b = Some(rates::bundle_subscriber(self, k)?);
        }
        Ok(())
    }
}
