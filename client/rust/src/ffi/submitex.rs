//! C ABI of the submission fields that came after `DrapeClothOptions`' layout was fixed (it is
//! the ABI and stays as it is): 1.6's `thickness` and `contact_stiffness` (self-collision, and the
//! distance kept from a mesh collider), 1.7's `scene` and 1.8's own mesh collider, in a struct of
//! their own passed to `drape_submit_grid_ex`.
use super::cloth::{grid_of, submit_any, submit_of, DrapeCloth, DrapeClothOptions, DrapeGrid};
use super::meshes::{mesh_of, DrapeMeshCollider};
use super::{bad, guard, opt_str, DrapeClient};
use crate::wire::Shape;
use std::ffi::c_char;

/// Submission fields beyond `DrapeClothOptions`; zero-initialise it (0 and NULL: not sent).
#[repr(C)]
pub struct DrapeSubmitExtras {
    /// 1.6: metres kept between non-neighbouring vertices (self_collision) and from a mesh
    /// collider (at least 0.001 there); 0: the server's default (0.01).
    pub thickness: f64,
    /// 1.6: the share of a contact corrected per pass (0..1); 0: the server's default (1).
    pub contact_stiffness: f64,
    /// 1.7: the scene the cloth collides in with the scene's other cloths (an id; NULL: none).
    /// The first cloth founds it and its client owns it; others need the owner's `members`.
    pub scene: *const c_char,
    /// 1.8: the cloth's own mesh collider, a new mesh (`vertices` and `triangles`) at its pose
    /// (NULL: none). Needs a 1.8 server (placement passes over older ones).
    pub mesh_collider: *const DrapeMeshCollider,
}

/// Submit a grid cloth with `options` and the fields of `extras` (NULL: none, as
/// `drape_submit_grid`), waiting for the reply as `drape_submit_grid` does. A bad mesh is
/// DRAPE_E_INVALID_VALUE (or TOO_LARGE past 65 536 vertices or triangles) with the triangle or
/// value named by `drape_last_error`, nothing sent.
#[no_mangle]
pub unsafe extern "C" fn drape_submit_grid_ex(client: *const DrapeClient, grid: *const DrapeGrid, options: *const DrapeClothOptions,
                                              extras: *const DrapeSubmitExtras, out: *mut *mut DrapeCloth) -> i32 {
    guard(|| {
        let (Some(c), Some(g)) = (client.as_ref(), grid.as_ref()) else { return bad("client or grid is NULL") };
        if out.is_null() {
            return bad("out is NULL");
        }
        let (mut sub, queue, retry) = match submit_of(options) {
            Ok(s) => s,
            Err(code) => return code,
        };
        if let Some(x) = extras.as_ref() {
            let positive = |v: f64| (v != 0.0).then_some(v);
            sub.material.thickness = positive(x.thickness);
            sub.material.contact_stiffness = positive(x.contact_stiffness);
            sub.scene = match opt_str(x.scene, "scene") {
                Ok(s) => s.map(str::to_string),
                Err(code) => return code,
            };
            if !x.mesh_collider.is_null() {
                match mesh_of(x.mesh_collider) {
                    Ok(m) => sub.mesh_collider = Some(m),
                    Err(code) => return code,
                }
            }
        }
        submit_any(c, (sub, queue, retry), Shape::Grid(grid_of(g)), false, out)
    })
}
