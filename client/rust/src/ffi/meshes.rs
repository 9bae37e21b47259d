//! C ABI of protocol 1.8's mesh colliders (PROTOCOL.md 5.4): one struct for the four changes
//! (a new mesh, a re-pose, a rigid move, a removal; a submission's: `submitex.rs`), a
//! cloth's mesh changed (waited for or not, or in a batch) and a scene's mesh changed by its
//! owner (1.7's scene request). New functions and a new struct: the layouts of
//! `DrapeClothOptions` and `DrapeControl` are the ABI and stay as they are.
use super::cloth::{slice, DrapeBatch, DrapeCloth};
use super::{bad, fail, guard, opt_str, DrapeClient, DRAPE_OK};
use crate::wire::meshcollider::{MeshCollider, IDENTITY};
use crate::wire::{Control, SceneRequest};

/// A mesh collider change (PROTOCOL.md 5.4), by the fields given; zero-initialise it:
/// - `vertices` and `triangles`: a new mesh (3 floats per vertex in its own frame, 3 indices per
///   triangle, counter-clockwise seen from outside: the normals' side is outside) at the pose;
/// - `vertices` alone (`triangles` NULL): a re-pose, new positions of the current mesh's
///   vertices (the same count);
/// - neither: a rigid move of the current mesh to the pose, the per-tick change;
/// - `remove`: the mesh dropped (nothing else may be set).
///
/// The pose, mesh frame to world: `position` in metres and `rotation` a quaternion
/// `{w, x, y, z}` (normalised by the server; all four 0: the identity).
#[repr(C)]
#[derive(Clone, Copy)]
pub struct DrapeMeshCollider {
    pub vertices: *const f32,
    pub vertex_count: usize,
    pub triangles: *const u32,
    pub triangle_count: usize,
    pub position: [f64; 3],
    pub rotation: [f64; 4],
    pub remove: bool,
}

/// The wire mesh collider of a `DrapeMeshCollider` (checked when it is sent).
pub(crate) unsafe fn mesh_of(m: *const DrapeMeshCollider) -> Result<MeshCollider, i32> {
    let m = m.as_ref().ok_or_else(|| bad("mesh is NULL"))?;
    if m.remove {
        if !m.vertices.is_null() || !m.triangles.is_null() {
            return Err(bad("a mesh removal has no vertices or triangles"));
        }
        return Ok(MeshCollider::removal());
    }
    let rotation = if m.rotation == [0.0; 4] { IDENTITY } else { m.rotation };
    // NULL: not given (a count of 0 with a pointer: an empty list, refused by the checks)
    let vertices = slice(m.vertices, 3 * m.vertex_count).filter(|_| !m.vertices.is_null()).map(<[f32]>::to_vec);
    let triangles = slice(m.triangles, 3 * m.triangle_count).filter(|_| !m.triangles.is_null()).map(<[u32]>::to_vec);
    Ok(MeshCollider { vertices, triangles, position: m.position, rotation, remove: false })
}

/// Set, re-pose, move or remove the cloth's own mesh collider. `wait`: block for the reply and
/// put the first tick showing it in `*tick` (may be NULL); else return at once (a failure
/// becomes DRAPE_EVENT_REQUEST_FAILED). Needs a 1.8 server (DRAPE_E_INVALID_VALUE otherwise,
/// nothing sent). The mesh last set, at its last pose, is sent again after a failover.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_set_mesh_collider(cloth: *const DrapeCloth, mesh: *const DrapeMeshCollider,
                                                       wait: bool, tick: *mut u64) -> i32 {
    guard(|| match mesh_of(mesh) {
        Ok(m) => super::cloth::control(cloth, Control { mesh_collider: Some(m), ..Default::default() }, wait, tick),
        Err(code) => code,
    })
}

/// The per-tick rigid move of the cloth's mesh collider: `position` (3 doubles) and `rotation`
/// (4 doubles, w x y z; NULL: the identity), as `drape_cloth_set_mesh_collider`.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_move_mesh_collider(cloth: *const DrapeCloth, position: *const f64,
                                                        rotation: *const f64, wait: bool, tick: *mut u64) -> i32 {
    guard(|| {
        let Some(p) = slice(position, 3) else { return bad("position is NULL") };
        let q = slice(rotation, 4).map_or(IDENTITY, |q| [q[0], q[1], q[2], q[3]]);
        let mc = MeshCollider::pose([p[0], p[1], p[2]], q);
        super::cloth::control(cloth, Control { mesh_collider: Some(mc), ..Default::default() }, wait, tick)
    })
}

/// Add a change of `cloth`'s mesh collider to the batch (sent with `drape_batch_send`).
#[no_mangle]
pub unsafe extern "C" fn drape_batch_set_mesh_collider(batch: *mut DrapeBatch, cloth: *const DrapeCloth,
                                                       mesh: *const DrapeMeshCollider) -> i32 {
    guard(|| {
        let (Some(b), Some(c)) = (batch.as_mut(), cloth.as_ref()) else { return bad("batch or cloth is NULL") };
        match mesh_of(mesh) {
            Ok(m) => {
                b.batch.add(&c.cloth, Control { mesh_collider: Some(m), ..Default::default() });
                DRAPE_OK
            }
            Err(code) => code,
        }
    })
}

/// As the owner of `scene` (the client whose cloth founded it), set, re-pose, move or remove
/// the scene's mesh collider, one for every cloth of the scene beside their own, on `server`
/// (NULL: the client's default server). Waits for the reply; `*tick` (may be NULL) gets the
/// first tick showing it. DRAPE_E_FORBIDDEN for another client's scene, DRAPE_E_NOT_FOUND for a
/// scene without cloths there; needs a 1.8 server.
#[no_mangle]
pub unsafe extern "C" fn drape_client_set_scene_mesh_collider(client: *const DrapeClient, scene: *const std::ffi::c_char,
                                                              mesh: *const DrapeMeshCollider,
                                                              server: *const std::ffi::c_char, tick: *mut u64) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        let (scene, server) = match (opt_str(scene, "scene"), opt_str(server, "server")) {
            (Ok(Some(s)), Ok(v)) => (s, v),
            (Ok(None), _) => return bad("scene is NULL"),
            (Err(code), _) | (_, Err(code)) => return code,
        };
        let mc = match mesh_of(mesh) {
            Ok(m) => m,
            Err(code) => return code,
        };
        let req = SceneRequest { mesh_collider: Some(mc), ..SceneRequest::new("", scene) };
        match c.client.set_scene(req, server) {
            Ok(rep) => {
                if !tick.is_null() {
                    *tick = rep.tick;
                }
                DRAPE_OK
            }
            Err(e) => fail(e),
        }
    })
}
