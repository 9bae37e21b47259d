//! C ABI of submissions, cloths (state reads into caller buffers, controls, removal) and
//! batch controls. See `mod.rs` for the conventions and thread safety.
use super::{bad, fail, guard, new_cloth, opt_str, DrapeClient, DRAPE_NO_DATA, DRAPE_OK};
use crate::client::{Batch, Cloth, StateInfo};
use crate::wire::{Control, Encoding, Grid, Orientation, Shape, StateOptions, Submit, FEATURE_NAMES};
use std::ffi::c_char;
use std::time::Duration;

/// A submitted cloth (opaque). Free with `drape_cloth_free` (after `drape_cloth_remove`, or not:
/// freeing does not remove it from the server).
pub struct DrapeCloth {
    pub(crate) cloth: Cloth,
}

/// Controls of many cloths sent as one batch control (opaque; not synchronized).
pub struct DrapeBatch {
    batch: Batch,
}

/// A regular grid (PROTOCOL.md section 4): vertex (r, c) is r * cols + c.
#[repr(C)]
pub struct DrapeGrid {
    pub cols: u32,
    pub rows: u32,
    /// Metres (0: 1.0).
    pub width: f64,
    pub height: f64,
    /// false: horizontal (XZ plane), true: vertical (XY plane, rows going down).
    pub vertical: bool,
    /// Position of vertex 0.
    pub origin: [f64; 3],
}

/// Submission options; zero-initialise for the defaults.
#[repr(C)]
pub struct DrapeClothOptions {
    /// Pinned vertex indices (may be NULL when `pinned_count` is 0).
    pub pinned: *const u32,
    pub pinned_count: usize,
    /// State encoding: 0 float32, 1 float16, 2 quant16.
    pub encoding: i32,
    /// Publish normals too.
    pub normals: bool,
    /// 1.1: receive the state inside the client's bundle.
    pub bundle: bool,
    /// Quality preset ("fast", "balanced", "accurate", "exact") or NULL.
    pub quality: *const c_char,
    /// Gravity in m/s² or NULL for the server default.
    pub gravity: *const f64,
}

/// A state read by `drape_cloth_read_state` / `drape_cloth_wait_state`.
#[repr(C)]
pub struct DrapeStateInfo {
    pub tick: u64,
    /// Server wall clock (Unix ns) of the tick, and this client's receive time.
    pub server_time_ns: u64,
    pub receive_time_ns: u64,
    pub vertex_count: u32,
    pub flags: u16,
    /// 0 float32, 1 float16, 2 quant16.
    pub encoding: u8,
    pub has_normals: bool,
    /// This state is the rest pose (after a reset control or a non-finite step).
    pub reset: bool,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
}

pub(crate) unsafe fn slice<'a, T>(p: *const T, n: usize) -> Option<&'a [T]> {
    if n == 0 {
        Some(&[])
    } else if p.is_null() {
        None
    } else {
        Some(std::slice::from_raw_parts(p, n))
    }
}

unsafe fn submit_of(opts: *const DrapeClothOptions) -> Result<Submit, i32> {
    let mut s = Submit::new("", Shape::Grid(Grid::new(1, 1)));
    let Some(o) = opts.as_ref() else { return Ok(s) };
    s.pinned = slice(o.pinned, o.pinned_count).ok_or_else(|| bad("pinned is NULL"))?.to_vec();
    let encoding = Encoding::from_id(u8::try_from(o.encoding).unwrap_or(255)).ok_or_else(|| bad("encoding must be 0, 1 or 2"))?;
    if encoding != Encoding::Float32 || o.normals || o.bundle {
        s.state = Some(StateOptions { normals: Some(o.normals), encoding: Some(encoding), bundle: o.bundle.then_some(true) });
    }
    s.quality = opt_str(o.quality, "quality")?.map(str::to_string);
    if !o.gravity.is_null() {
        s.gravity = Some([*o.gravity, *o.gravity.add(1), *o.gravity.add(2)]);
    }
    Ok(s)
}

/// Submit a grid cloth; `*out` receives its handle.
#[no_mangle]
pub unsafe extern "C" fn drape_submit_grid(client: *const DrapeClient, grid: *const DrapeGrid,
                                           options: *const DrapeClothOptions, out: *mut *mut DrapeCloth) -> i32 {
    guard(|| {
        let (Some(c), Some(g)) = (client.as_ref(), grid.as_ref()) else { return bad("client or grid is NULL") };
        if out.is_null() {
            return bad("out is NULL");
        }
        let sub = match submit_of(options) {
            Ok(s) => s,
            Err(code) => return code,
        };
        let or1 = |x: f64| if x == 0.0 { 1.0 } else { x };
        let orientation = if g.vertical { Orientation::Vertical } else { Orientation::Horizontal };
        let grid = Grid { cols: g.cols, rows: g.rows, width: or1(g.width), height: or1(g.height), orientation, origin: g.origin };
        new_cloth(c.client.submit_grid(grid, sub), out)
    })
}

/// Submit a triangle mesh: `vertices` 3 floats per vertex, `triangles` 3 indices per triangle.
#[no_mangle]
pub unsafe extern "C" fn drape_submit_mesh(client: *const DrapeClient, vertices: *const f32, vertex_count: usize,
                                           triangles: *const u32, triangle_count: usize,
                                           options: *const DrapeClothOptions, out: *mut *mut DrapeCloth) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        let (Some(v), Some(t)) = (slice(vertices, 3 * vertex_count), slice(triangles, 3 * triangle_count)) else {
            return bad("vertices or triangles is NULL");
        };
        if out.is_null() {
            return bad("out is NULL");
        }
        match submit_of(options) {
            Ok(sub) => new_cloth(c.client.submit_mesh(v.to_vec(), t.to_vec(), sub), out),
            Err(code) => code,
        }
    })
}

/// Submit a cloth from a Wavefront OBJ file (faces fan-triangulated).
#[no_mangle]
pub unsafe extern "C" fn drape_submit_obj(client: *const DrapeClient, path: *const c_char,
                                          options: *const DrapeClothOptions, out: *mut *mut DrapeCloth) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        let path = match opt_str(path, "path") {
            Ok(Some(p)) => p,
            Ok(None) => return bad("path is NULL"),
            Err(code) => return code,
        };
        let text = match std::fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) => return bad(&format!("cannot read {path}: {e}")),
        };
        match submit_of(options) {
            Ok(sub) if !out.is_null() => new_cloth(c.client.submit_obj(&text, sub), out),
            Ok(_) => bad("out is NULL"),
            Err(code) => code,
        }
    })
}

/// Free a cloth handle (does not remove the cloth: call `drape_cloth_remove` first for that).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_free(cloth: *mut DrapeCloth) {
    if !cloth.is_null() {
        drop(Box::from_raw(cloth));
    }
}

/// Vertex count (positions and normals buffers need 3 floats per vertex).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_vertex_count(cloth: *const DrapeCloth) -> u32 {
    cloth.as_ref().map_or(0, |c| c.cloth.vertex_count())
}

/// Triangle count of the cloth's rest mesh.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_triangle_count(cloth: *const DrapeCloth) -> u32 {
    cloth.as_ref().map_or(0, |c| (c.cloth.triangles().len() / 3) as u32)
}

/// This client's handle number of the cloth (stable across failover; events name it).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_handle(cloth: *const DrapeCloth) -> u64 {
    cloth.as_ref().map_or(0, |c| c.cloth.handle())
}

/// The server's cloth id (changes when failover resubmits it).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_id(cloth: *const DrapeCloth, buf: *mut c_char, len: usize) -> i32 {
    guard(|| cloth.as_ref().map_or_else(|| bad("cloth is NULL"), |c| super::copy_out(&c.cloth.id(), buf, len)))
}

/// The server the cloth lives on (placed by load when the client names no server; changes when
/// failover resubmits it).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_server(cloth: *const DrapeCloth, buf: *mut c_char, len: usize) -> i32 {
    guard(|| cloth.as_ref().map_or_else(|| bad("cloth is NULL"), |c| super::copy_out(&c.cloth.server(), buf, len)))
}

/// Copy the rest mesh: `positions` 3 floats per vertex, `triangles` 3 indices per triangle
/// (either may be NULL to skip it; lengths are element counts).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_rest_mesh(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize,
                                               triangles: *mut u32, triangles_len: usize) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        let (p, t) = (c.cloth.rest_positions(), c.cloth.triangles());
        if (!positions.is_null() && positions_len < p.len()) || (!triangles.is_null() && triangles_len < t.len()) {
            return bad(&format!("buffers too small: {} floats and {} indices needed", p.len(), t.len()));
        }
        if !positions.is_null() {
            std::ptr::copy_nonoverlapping(p.as_ptr(), positions, p.len());
        }
        if !triangles.is_null() {
            std::ptr::copy_nonoverlapping(t.as_ptr(), triangles, t.len());
        }
        DRAPE_OK
    })
}

unsafe fn read(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize, normals: *mut f32, normals_len: usize,
               info: *mut DrapeStateInfo, timeout: Option<Duration>) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        if positions.is_null() {
            return bad("positions is NULL");
        }
        let pos = std::slice::from_raw_parts_mut(positions, positions_len);
        let nrm = if normals.is_null() { None } else { Some(std::slice::from_raw_parts_mut(normals, normals_len)) };
        let r = match timeout {
            Some(t) => c.cloth.wait_state(pos, nrm, t),
            None => c.cloth.read_state(pos, nrm),
        };
        match r {
            Ok(Some(st)) => {
                if let Some(i) = info.as_mut() {
                    *i = info_of(&st);
                }
                DRAPE_OK
            }
            Ok(None) => DRAPE_NO_DATA,
            Err(e) => fail(e),
        }
    })
}

fn info_of(s: &StateInfo) -> DrapeStateInfo {
    DrapeStateInfo {
        tick: s.tick,
        server_time_ns: s.server_time_ns,
        receive_time_ns: s.receive_time_ns,
        vertex_count: s.vertex_count,
        flags: s.flags,
        encoding: s.encoding as u8,
        has_normals: s.has_normals,
        reset: s.reset,
        bounds_min: s.bounds_min,
        bounds_max: s.bounds_max,
    }
}

/// Decode the newest state not read yet into `positions` (3 floats per vertex; `normals` may
/// be NULL): DRAPE_OK, DRAPE_NO_DATA (nothing new), or an error (SERVER_LOST, CLOSED...).
/// `info` may be NULL. Never blocks; no allocation per vertex.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_read_state(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize,
                                                normals: *mut f32, normals_len: usize, info: *mut DrapeStateInfo) -> i32 {
    read(cloth, positions, positions_len, normals, normals_len, info, None)
}

/// Like `drape_cloth_read_state`, waiting up to `timeout_ms` for a new state.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_wait_state(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize,
                                                normals: *mut f32, normals_len: usize, timeout_ms: u32,
                                                info: *mut DrapeStateInfo) -> i32 {
    read(cloth, positions, positions_len, normals, normals_len, info, Some(Duration::from_millis(timeout_ms as u64)))
}

unsafe fn control(cloth: *const DrapeCloth, ctl: Control, wait: bool, tick: *mut u64) -> i32 {
    let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
    match c.cloth.control(ctl, wait) {
        Ok(t) => {
            if let (Some(t), false) = (t, tick.is_null()) {
                *tick = t;
            }
            DRAPE_OK
        }
        Err(e) => fail(e),
    }
}

unsafe fn pins(indices: *const u32, count: usize, targets: *const f32) -> Option<crate::wire::Pins> {
    Some(crate::wire::Pins { indices: slice(indices, count)?.to_vec(), targets: slice(targets, 3 * count)?.to_vec() })
}

/// Move pinned vertices `indices[i]` to `targets[3i..3i+3]`. `wait`: block for the reply and
/// store the first tick showing it in `*tick` (may be NULL); otherwise return at once (a
/// failure then arrives as a REQUEST_FAILED event).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_move_pins(cloth: *const DrapeCloth, indices: *const u32, count: usize,
                                               targets: *const f32, wait: bool, tick: *mut u64) -> i32 {
    guard(|| match pins(indices, count, targets) {
        Some(p) => control(cloth, Control { pins: Some(p), ..Default::default() }, wait, tick),
        None => bad("indices or targets is NULL"),
    })
}

/// Set gravity (3 doubles, m/s²).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_set_gravity(cloth: *const DrapeCloth, gravity: *const f64, wait: bool, tick: *mut u64) -> i32 {
    guard(|| match slice(gravity, 3) {
        Some(g) => control(cloth, Control { gravity: Some([g[0], g[1], g[2]]), ..Default::default() }, wait, tick),
        None => bad("gravity is NULL"),
    })
}

/// Feature names of a mask of DRAPE_FEATURE_* bits (None: unknown bits, or empty mask).
fn names_of(mask: u32) -> Result<Option<Vec<String>>, i32> {
    if mask >> FEATURE_NAMES.len() != 0 {
        return Err(bad(&format!("unknown feature bits 0x{mask:x} (DRAPE_FEATURE_* are 0x1..0x10)")));
    }
    let names: Vec<String> = FEATURE_NAMES.iter().enumerate().filter(|(i, _)| mask & (1 << i) != 0).map(|(_, n)| n.to_string()).collect();
    Ok((!names.is_empty()).then_some(names))
}

/// The DRAPE_FEATURE_* mask of a feature list (names this version does not know are left out).
fn mask_of(names: &[String]) -> u32 {
    names.iter().filter_map(|n| FEATURE_NAMES.iter().position(|f| f == n)).fold(0, |m, i| m | 1 << i)
}

/// Protocol 1.2: switch features on (`add`, a mask of DRAPE_FEATURE_* bits) and off (`remove`),
/// keeping the others; a bit in both is INVALID_VALUE. Needs a 1.2 server (INVALID_VALUE,
/// nothing sent, otherwise). `wait`: block for the reply; `*tick` (may be NULL) gets the first
/// tick showing the change and `*features` (may be NULL) the cloth's resulting feature mask
/// (DRAPE_FEATURES_UNKNOWN if the reply did not report it).
/// Not waiting: return at once; `drape_cloth_features` has the set once the reply arrived.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_change_features(cloth: *const DrapeCloth, add: u32, remove: u32, wait: bool,
                                                     tick: *mut u64, features: *mut u32) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        let (add, remove) = match (names_of(add), names_of(remove)) {
            (Ok(a), Ok(r)) => (a, r),
            (Err(code), _) | (_, Err(code)) => return code,
        };
        let ctl = Control { features_add: add, features_remove: remove, ..Default::default() };
        let r = if wait { c.cloth.apply(ctl).map(Some) } else { c.cloth.control(ctl, false).map(|_| None) };
        match r {
            Ok(Some(a)) => {
                if !tick.is_null() {
                    *tick = a.tick;
                }
                if !features.is_null() {
                    *features = a.features.as_deref().map_or(super::DRAPE_FEATURES_UNKNOWN, mask_of);
                }
                DRAPE_OK
            }
            Ok(None) => DRAPE_OK,
            Err(e) => fail(e),
        }
    })
}

/// Protocol 1.2: the cloth's feature mask (DRAPE_FEATURE_* bits) as its server last reported it
/// in a control or batch reply: DRAPE_OK with `*features` set, or DRAPE_NO_DATA when none was
/// reported yet (no control answered yet, or a server older than 1.2).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_features(cloth: *const DrapeCloth, features: *mut u32) -> i32 {
    guard(|| {
        let (Some(c), false) = (cloth.as_ref(), features.is_null()) else { return bad("cloth or features is NULL") };
        match c.cloth.features() {
            Some(f) => {
                *features = mask_of(&f);
                DRAPE_OK
            }
            None => DRAPE_NO_DATA,
        }
    })
}

/// Back to the rest pose with zero velocity.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_reset(cloth: *const DrapeCloth, wait: bool, tick: *mut u64) -> i32 {
    guard(|| control(cloth, Control { reset: true, ..Default::default() }, wait, tick))
}

/// Remove the cloth from its server (waits for the reply); `*last_tick` (may be NULL) is the
/// last tick a state of it may have been published for. The handle must still be freed.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_remove(cloth: *const DrapeCloth, last_tick: *mut u64) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        match c.cloth.remove() {
            Ok(t) => {
                if !last_tick.is_null() {
                    *last_tick = t;
                }
                DRAPE_OK
            }
            Err(e) => fail(e),
        }
    })
}

/// A new, empty batch (free with `drape_batch_free`).
#[no_mangle]
pub extern "C" fn drape_batch_new() -> *mut DrapeBatch {
    Box::into_raw(Box::new(DrapeBatch { batch: Batch::default() }))
}

#[no_mangle]
pub unsafe extern "C" fn drape_batch_free(batch: *mut DrapeBatch) {
    if !batch.is_null() {
        drop(Box::from_raw(batch));
    }
}

/// Add a pin move of `cloth` to the batch (as `drape_cloth_move_pins`).
#[no_mangle]
pub unsafe extern "C" fn drape_batch_move_pins(batch: *mut DrapeBatch, cloth: *const DrapeCloth, indices: *const u32,
                                               count: usize, targets: *const f32) -> i32 {
    guard(|| {
        let (Some(b), Some(c)) = (batch.as_mut(), cloth.as_ref()) else { return bad("batch or cloth is NULL") };
        match pins(indices, count, targets) {
            Some(p) => {
                b.batch.add(&c.cloth, Control { pins: Some(p), ..Default::default() });
                DRAPE_OK
            }
            None => bad("indices or targets is NULL"),
        }
    })
}

/// Protocol 1.2: add an item switching features on and off (as `drape_cloth_change_features`;
/// checked when the batch is sent). The resulting set: `drape_cloth_features` after the reply.
#[no_mangle]
pub unsafe extern "C" fn drape_batch_change_features(batch: *mut DrapeBatch, cloth: *const DrapeCloth, add: u32,
                                                     remove: u32) -> i32 {
    guard(|| {
        let (Some(b), Some(c)) = (batch.as_mut(), cloth.as_ref()) else { return bad("batch or cloth is NULL") };
        match (names_of(add), names_of(remove)) {
            (Ok(features_add), Ok(features_remove)) => {
                b.batch.add(&c.cloth, Control { features_add, features_remove, ..Default::default() });
                DRAPE_OK
            }
            (Err(code), _) | (_, Err(code)) => code,
        }
    })
}

/// Send the batch (and empty it for reuse). `wait`: block for the replies; item i's status
/// goes to `codes[i]` and its first tick to `ticks[i]` (either may be NULL; `len` is their
/// length). Not waiting: failures arrive as REQUEST_FAILED events.
#[no_mangle]
pub unsafe extern "C" fn drape_batch_send(client: *const DrapeClient, batch: *mut DrapeBatch, wait: bool,
                                          codes: *mut i32, ticks: *mut u64, len: usize) -> i32 {
    guard(|| {
        let (Some(c), Some(b)) = (client.as_ref(), batch.as_mut()) else { return bad("client or batch is NULL") };
        match c.client.send_batch(std::mem::take(&mut b.batch), wait) {
            Ok(Some(results)) => {
                for (i, r) in results.iter().enumerate().take(len) {
                    if !codes.is_null() {
                        *codes.add(i) = r.as_ref().map_or_else(|e| e.code as i32, |_| DRAPE_OK);
                    }
                    if !ticks.is_null() {
                        *ticks.add(i) = *r.as_ref().unwrap_or(&0);
                    }
                }
                DRAPE_OK
            }
            Ok(None) => DRAPE_OK,
            Err(e) => fail(e),
        }
    })
}
