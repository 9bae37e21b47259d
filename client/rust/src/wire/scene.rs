//! Protocol 1.7's scene request and its reply (PROTOCOL.md 5.3): the owner of a scene replaces
//! its colliders and members and (1.8, 5.4) sets, re-poses, moves or removes its mesh collider,
//! once per tick for every cloth of the scene. Encoded to the reference's exact bytes and decoded
//! back; checked client-side with the server's codes.
use super::error::{invalid, Error, ErrorCode, Result};
use super::keys::valid_id;
use super::meshcollider::MeshCollider;
use super::msg::{collider_value, strings, Collider};
use super::msg_decode::{read_colliders, read_strings};
use super::reader::{header, pack, s, unpack_message, Reader, Value};
use super::replies::ok_header;
use super::validate::colliders;

/// The most colliders of a scene (each cloth holds its own and the scene's, 32 together).
pub const MAX_SCENE_COLLIDERS: usize = 16;
/// The most members a scene request lists.
pub const MAX_SCENE_MEMBERS: usize = 64;

/// A scene request: `None` leaves a field as it is (a request with none is a probe).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SceneRequest {
    pub rid: u64,
    pub client: String,
    pub scene: String,
    /// Replaces the scene's colliders (`Some(vec![])` clears them).
    pub colliders: Option<Vec<Collider>>,
    /// Replaces the clients besides the owner that may submit into the scene (`"*"`: anyone).
    pub members: Option<Vec<String>>,
    /// 1.8: the scene's mesh collider, for every cloth of it beside their own.
    pub mesh_collider: Option<MeshCollider>,
}

impl SceneRequest {
    pub fn new(client: &str, scene: &str) -> SceneRequest {
        SceneRequest { client: client.to_string(), scene: scene.to_string(), ..Default::default() }
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut m = header(self.rid);
        m.push((s("client"), s(&self.client)));
        m.push((s("scene"), s(&self.scene)));
        if let Some(c) = &self.colliders {
            m.push((s("colliders"), Value::Array(c.iter().map(collider_value).collect())));
        }
        if let Some(x) = &self.members {
            m.push((s("members"), strings(x)));
        }
        if let Some(mc) = &self.mesh_collider {
            m.push((s("mesh_collider"), mc.to_value()));
        }
        pack(&Value::Map(m))
    }

    pub fn decode(data: &[u8]) -> Result<SceneRequest> {
        let m = unpack_message(data)?;
        let r = Reader::new(&m, "");
        Ok(SceneRequest {
            rid: r.u64("rid", false)?.unwrap_or(0),
            client: r.str("client", true)?.unwrap().to_string(),
            scene: r.str("scene", true)?.unwrap().to_string(),
            colliders: read_colliders(&r)?,
            members: read_strings(&r, "members")?,
            mesh_collider: MeshCollider::from_reader(&r, "mesh_collider")?,
        })
    }

    /// The server's checks but for ownership: ids well formed, at most 16 colliders and 64
    /// members (client ids or `"*"`), the mesh collider's checks.
    pub fn validate(&self) -> Result<()> {
        if !valid_id(&self.client) {
            return Err(invalid(format!("invalid client id {:?}", self.client)));
        }
        if !valid_id(&self.scene) {
            return Err(invalid(format!("'scene' must be 1-64 characters of [A-Za-z0-9_.-], got {:?}", self.scene)));
        }
        if self.colliders.as_ref().is_some_and(|c| c.len() > MAX_SCENE_COLLIDERS) {
            return Err(invalid(format!("a scene holds at most {MAX_SCENE_COLLIDERS} colliders")));
        }
        colliders(&self.colliders)?;
        if let Some(ms) = &self.members {
            if ms.len() > MAX_SCENE_MEMBERS {
                return Err(Error::new(ErrorCode::TooLarge, format!("'members' has {} entries, at most {MAX_SCENE_MEMBERS}", ms.len())));
            }
            if let Some(x) = ms.iter().find(|x| x.as_str() != "*" && !valid_id(x)) {
                return Err(invalid(format!("'members' holds {x:?}: a client id or \"*\"")));
            }
        }
        match &self.mesh_collider {
            Some(mc) => mc.validate("mesh_collider", false),
            None => Ok(()),
        }
    }
}

/// A scene request's reply: `tick`, the first tick whose states reflect the change; the scene's
/// owner, its cloths on this server and its members after the change.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneReply {
    pub rid: u64,
    pub tick: u64,
    pub owner: String,
    pub cloths: u32,
    pub members: Vec<String>,
}

impl SceneReply {
    pub fn from_map(m: &[(Value, Value)]) -> Result<SceneReply> {
        let r = Reader::new(m, "");
        let cloths = r.u64("cloths", true)?.unwrap();
        Ok(SceneReply {
            rid: r.u64("rid", false)?.unwrap_or(0),
            tick: r.u64("tick", true)?.unwrap(),
            owner: r.str("owner", true)?.unwrap().to_string(),
            cloths: u32::try_from(cloths).map_err(|_| invalid(format!("scene reply: {cloths} cloths")))?,
            members: read_strings(&r, "members")?.unwrap_or_default(),
        })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut m = ok_header(self.rid);
        m.push((s("tick"), Value::from(self.tick)));
        m.push((s("owner"), s(&self.owner)));
        m.push((s("cloths"), Value::from(self.cloths)));
        m.push((s("members"), strings(&self.members)));
        pack(&Value::Map(m))
    }
}
