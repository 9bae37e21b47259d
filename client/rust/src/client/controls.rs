//! Controls of one cloth: checked against the server's version, sent waited for or not, and
//! asynchronous ones whose outcome is an event.
use super::*;

impl Inner {
    /// Refuse a control that uses 1.2 fields (`features_add` / `features_remove`) toward a
    /// server older than 1.2, which would ignore them silently (PROTOCOL.md section 5.2), and
    /// likewise 1.5's predictive options and 1.8's `mesh_collider`.
    pub(crate) fn check_version(&self, server: &str, ctl: &Control) -> Result<()> {
        self.check_mesh_version(server, ctl.mesh_collider.as_ref())?;
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

    pub(crate) fn send_control(self: &Arc<Self>, c: &Arc<cloth::ClothInner>, ctl: Control, request: u64, server: &str, n: u32) -> Result<()> {
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
