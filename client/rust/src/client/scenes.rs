//! What one client knows of its scenes (protocol 1.7, PROTOCOL.md 5.3 and its SDK note), as the
//! Python SDK's `client/scenes.py`: whether it owns each (a probe after its first cloth of it, or
//! a scene request that succeeded), what its scene requests last set (members, colliders, mesh
//! collider at its last pose: replayed when a failover founds the scene again), where this client's
//! cloths of a scene live and which live server holds a scene (a probe answered `ok` or
//! `forbidden` there, `not_found` elsewhere). Placement and failover keep a scene on one server.
use super::cloth::{ClothInner, Status};
use super::Inner;
use crate::wire::{ErrorCode, SceneReply, SceneRequest};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// At most this long for one scene probe.
const PROBE_TIMEOUT: Duration = Duration::from_secs(2);
/// A member's cloths wait this long for their scene's owner to found it again after a failover.
pub(crate) const SCENE_WAIT: Duration = Duration::from_secs(10);

/// One scene as this client last set it (`owner`: `None` while not known).
#[derive(Default, Clone)]
pub(crate) struct SceneMemo {
    pub(crate) owner: Option<bool>,
    last: SceneRequest,
}

impl SceneMemo {
    /// A scene request that succeeded: its fields are in force now.
    fn sent(&mut self, req: &SceneRequest) {
        if req.colliders.is_some() {
            self.last.colliders = req.colliders.clone();
        }
        if req.members.is_some() {
            self.last.members = req.members.clone();
        }
        match &req.mesh_collider {
            None => {}
            Some(mc) if mc.remove => self.last.mesh_collider = None,
            Some(mc) if mc.triangles.is_some() => self.last.mesh_collider = Some(mc.clone()),
            Some(mc) => {
                if let Some(cur) = &mut self.last.mesh_collider {
                    if mc.vertices.is_some() {
                        cur.vertices = mc.vertices.clone();
                    }
                    cur.position = mc.position;
                    cur.rotation = mc.rotation;
                }
            }
        }
    }

    /// The one request that sets it all again (None: nothing was ever set).
    fn replay(&self, client: &str, scene: &str) -> Option<SceneRequest> {
        let l = &self.last;
        if l.colliders.is_none() && l.members.is_none() && l.mesh_collider.is_none() {
            return None;
        }
        Some(SceneRequest { client: client.to_string(), scene: scene.to_string(), ..l.clone() })
    }
}

/// This client's scenes, by id.
#[derive(Default)]
pub(crate) struct SceneBook {
    scenes: Mutex<HashMap<String, SceneMemo>>,
}

impl SceneBook {
    pub(crate) fn owner(&self, scene: &str) -> Option<bool> {
        self.scenes.lock().unwrap().get(scene).and_then(|m| m.owner)
    }

    pub(crate) fn sent(&self, req: &SceneRequest, rep: &SceneReply, client: &str) {
        let mut s = self.scenes.lock().unwrap();
        let m = s.entry(req.scene.clone()).or_default();
        m.sent(req);
        m.owner = Some(rep.owner == client);
    }

    fn set_owner(&self, scene: &str, owner: bool) {
        self.scenes.lock().unwrap().entry(scene.to_string()).or_default().owner = Some(owner);
    }

    fn replay(&self, client: &str, scene: &str) -> Option<SceneRequest> {
        self.scenes.lock().unwrap().get(scene).and_then(|m| m.replay(client, scene))
    }
}

/// What a scene probe found on a server.
enum Probe {
    Owned(SceneReply),
    Others,
    Absent,
    NoAnswer,
}

impl Inner {
    /// The server of this client's live cloths of `scene` (other than `except`, a handle).
    pub(crate) fn scene_server(&self, scene: &str, except: u64) -> Option<String> {
        let cloths: Vec<Arc<ClothInner>> = self.reg.lock().unwrap().by_handle.values().cloned().collect();
        cloths.iter().filter(|c| c.handle != except && c.submit.scene.as_deref() == Some(scene)).find_map(|c| {
            let s = c.slot.lock().unwrap();
            (s.status == Status::Live).then(|| s.server.clone())
        })
    }

    fn probe_scene(&self, scene: &str, server: &str) -> Probe {
        if self.require_version(server, (1, 7), "a scene probe").is_err() {
            return Probe::Absent;
        }
        let req = SceneRequest { rid: self.next_rid(), ..SceneRequest::new(&self.client_id, scene) };
        match self.request_within(server, "scene", req.encode(), self.timeout.min(PROBE_TIMEOUT)).and_then(|m| SceneReply::from_map(&m)) {
            Ok(rep) => Probe::Owned(rep),
            Err(e) if e.code == ErrorCode::Forbidden => Probe::Others,
            Err(e) if e.code == ErrorCode::NotFound => Probe::Absent,
            Err(_) => Probe::NoAnswer,
        }
    }

    /// The first live server (by placement's rank) that holds `scene`.
    pub(crate) fn locate_scene(&self, scene: &str) -> Option<String> {
        let ranked = self.placement.ranked(&self.live_servers(), &Default::default(), false);
        ranked.into_iter().find(|s| matches!(self.probe_scene(scene, s), Probe::Owned(_) | Probe::Others))
    }

    /// After this client's first cloth of `scene` went to `server`: who owns it there.
    pub(crate) fn learn_scene_owner(&self, scene: &str, server: &str) {
        if self.scenes.owner(scene).is_some() {
            return;
        }
        match self.probe_scene(scene, server) {
            Probe::Owned(rep) => self.scenes.set_owner(scene, rep.owner == self.client_id),
            Probe::Others => self.scenes.set_owner(scene, false),
            Probe::Absent | Probe::NoAnswer => {}
        }
    }

    /// The scene's last state sent again to `server`, where this client just founded it again.
    /// A refusal becomes an [`super::Event::RequestFailed`].
    pub(crate) fn replay_scene(&self, scene: &str, server: &str) {
        let Some(mut req) = self.scenes.replay(&self.client_id, scene) else { return };
        req.rid = self.next_rid();
        if req.mesh_collider.is_some() && self.require_version(server, (1, 8), "mesh_collider").is_err() {
            req.mesh_collider = None;
        }
        match self.request(server, "scene", req.encode()).and_then(|m| SceneReply::from_map(&m)) {
            Ok(rep) => self.scenes.sent(&req, &rep, &self.client_id),
            Err(error) => self.push_event(super::Event::RequestFailed { handle: None, cloth: String::new(), request: 0, error }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::{Collider, MeshCollider};

    #[test]
    fn the_last_of_each_field_is_replayed() {
        let mut m = SceneMemo::default();
        assert!(m.replay("c", "s").is_none());
        let ball = Collider::Sphere { center: [1.0, 2.0, 3.0], radius: 0.1 };
        m.sent(&SceneRequest { colliders: Some(vec![ball.clone()]), members: Some(vec!["a".into()]), ..SceneRequest::new("c", "s") });
        m.sent(&SceneRequest { members: Some(vec!["b".into()]), ..SceneRequest::new("c", "s") });
        m.sent(&SceneRequest { mesh_collider: Some(MeshCollider::mesh(vec![0.0; 9], vec![0, 1, 2])), ..SceneRequest::new("c", "s") });
        m.sent(&SceneRequest { mesh_collider: Some(MeshCollider::pose([1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0])), ..SceneRequest::new("c", "s") });
        let r = m.replay("c", "s").unwrap();
        assert_eq!(r.colliders, Some(vec![ball]));
        assert_eq!(r.members, Some(vec!["b".to_string()]));
        let mc = r.mesh_collider.unwrap();
        assert_eq!(mc.triangles, Some(vec![0, 1, 2]));
        assert_eq!(mc.position, [1.0, 0.0, 0.0]);
        m.sent(&SceneRequest { mesh_collider: Some(MeshCollider::removal()), ..SceneRequest::new("c", "s") });
        assert!(m.replay("c", "s").unwrap().mesh_collider.is_none());
    }
}
