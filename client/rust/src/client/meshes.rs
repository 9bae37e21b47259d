//! Protocol 1.8's mesh colliders (PROTOCOL.md 5.4) and 1.7's scene requests (5.3) on the
//! client: a cloth's own mesh set, re-posed, moved and removed by controls
//! ([`Cloth::set_mesh_collider`], [`Cloth::move_mesh_collider`]), a scene's colliders, members
//! and mesh sent by its owner ([`Client::set_scene`]), and the version each needs of the server
//! (a 1.7 server would ignore a `mesh_collider`: refused here, nothing sent; placement and
//! failover pass over such a server for a cloth with its own mesh).
use super::*;
use crate::wire::meshcollider::MeshCollider;
use crate::wire::scene::{SceneReply, SceneRequest};

impl Inner {
    /// `what` needs a server of version `want` or later: `invalid_value` from an older `server`.
    pub(crate) fn require_version(&self, server: &str, want: (u8, u8), what: &str) -> Result<()> {
        let ((ma, mi), _) = self.server_info(server)?;
        if (ma, mi) < want {
            return Err(Error::new(
                ErrorCode::InvalidValue,
                format!("{what} needs a protocol {}.{} server; server {server} speaks {ma}.{mi}", want.0, want.1),
            ));
        }
        Ok(())
    }

    /// A `mesh_collider` (a submission's or a control's) needs a 1.8 server.
    pub(crate) fn check_mesh_version(&self, server: &str, mesh: Option<&MeshCollider>) -> Result<()> {
        match mesh {
            Some(_) => self.require_version(server, (1, 8), "mesh_collider"),
            None => Ok(()),
        }
    }
}

impl Client {
    /// 1.7 (PROTOCOL.md 5.3): the owner's change of a scene on `server` (None: the server of
    /// this client's cloths of the scene, else the default server, [`Client::server_id`]): its colliders (they act on every cloth of the
    /// scene beside its own; `Some(vec![])` clears them), its members (client ids, `"*"`:
    /// anyone) and (1.8) its mesh collider, one for every cloth of the scene; `None` fields are
    /// left as they are. `req.client` and `req.rid` are set here. Waited for: the reply's tick
    /// is the first whose states reflect it. `forbidden` for another client's scene,
    /// `not_found` for a scene without cloths on that server. What it set is remembered: a
    /// failover founds the scene again with it (`scenes`).
    pub fn set_scene(&self, mut req: SceneRequest, server: Option<&str>) -> Result<SceneReply> {
        req.client = self.inner.client_id.clone();
        req.rid = self.inner.next_rid();
        req.validate()?;
        let server = match server.map(str::to_string).or_else(|| self.inner.scene_server(&req.scene, u64::MAX)) {
            Some(s) => s,
            None => self.server_id()?,
        };
        self.inner.require_version(&server, (1, 7), "a scene request")?;
        self.inner.check_mesh_version(&server, req.mesh_collider.as_ref())?;
        let rep = SceneReply::from_map(&self.inner.request(&server, "scene", req.encode())?)?;
        self.inner.scenes.sent(&req, &rep, &self.inner.client_id); // what a failover founds it again with
        Ok(rep)
    }

    /// 1.8: the per-tick rigid move of `scene`'s mesh collider (its owner's; about 80 bytes).
    pub fn move_scene_mesh(&self, scene: &str, position: [f64; 3], rotation: [f64; 4], server: Option<&str>) -> Result<SceneReply> {
        let req = SceneRequest { mesh_collider: Some(MeshCollider::pose(position, rotation)), ..SceneRequest::new("", scene) };
        self.set_scene(req, server)
    }
}

impl Cloth {
    /// 1.8 (PROTOCOL.md 5.4): set ([`MeshCollider::mesh`]), re-pose ([`MeshCollider::repose`]),
    /// move ([`MeshCollider::pose`]) or remove ([`MeshCollider::removal`]) the cloth's own mesh
    /// collider. Checked here as the server's decoder does (the offending triangle or value
    /// named); needs a 1.8 server (`invalid_value` otherwise, nothing sent). `wait`: the tick it
    /// applies from; otherwise return at once (failures become events). The mesh last set, at
    /// its last pose, is sent again after a failover.
    pub fn set_mesh_collider(&self, mesh: MeshCollider, wait: bool) -> Result<Option<u64>> {
        self.control(Control { mesh_collider: Some(mesh), ..Default::default() }, wait)
    }

    /// 1.8: the per-tick rigid move of the cloth's mesh collider to `position` and `rotation`
    /// (`[w, x, y, z]`), reached at the end of the next tick.
    pub fn move_mesh_collider(&self, position: [f64; 3], rotation: [f64; 4], wait: bool) -> Result<Option<u64>> {
        self.set_mesh_collider(MeshCollider::pose(position, rotation), wait)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a failover sends again: the submission's mesh moved is that mesh at the new pose; a
    /// re-pose keeps its triangles; a removal is a removal.
    #[test]
    fn the_mesh_last_sent_is_kept_whole_for_a_failover() {
        let v = vec![0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5];
        let t = vec![0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];
        let sub = Submit { mesh_collider: Some(MeshCollider::mesh(v.clone(), t.clone())), ..Submit::new("c", Shape::Grid(Grid::new(2, 2))) };
        let c = cloth::ClothInner::new(1, sub, vec![0.0; 12], vec![], 1);
        let mv = |mc: MeshCollider| c.note_sent(&Control { mesh_collider: Some(mc), ..Default::default() });
        mv(MeshCollider::pose([1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]));
        let last = c.sent.lock().unwrap().mesh.clone().unwrap();
        assert_eq!((last.vertices.as_ref(), last.triangles.as_ref(), last.position), (Some(&v), Some(&t), [1.0, 0.0, 0.0]));
        mv(MeshCollider::repose(vec![1.0; 12]).at([2.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]));
        let last = c.sent.lock().unwrap().mesh.clone().unwrap();
        assert_eq!((last.vertices.unwrap()[0], last.triangles.as_ref(), last.position), (1.0, Some(&t), [2.0, 0.0, 0.0]));
        mv(MeshCollider::removal());
        assert_eq!(c.sent.lock().unwrap().mesh, Some(MeshCollider::removal()));
    }
}
