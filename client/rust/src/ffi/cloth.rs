//! C ABI of submissions, cloths (state reads into caller buffers, controls, removal) and
//! batch controls. See `mod.rs` for the conventions and thread safety.
use super::control::{DrapeCollider, DrapeMaterial};
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
    pub(crate) batch: Batch,
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
    /// State encoding: DRAPE_ENCODING_* (0 float32, 1 float16, 2 quant16, 3 predictive: 1.5,
    /// its step set by `drape_client_set_predictive_step`).
    pub encoding: i32,
    /// Publish normals too.
    pub normals: bool,
    /// 1.1: receive the state inside the client's bundle.
    pub bundle: bool,
    /// Quality preset ("fast", "balanced", "accurate", "exact") or NULL.
    pub quality: *const c_char,
    /// Gravity in m/s² or NULL for the server default.
    pub gravity: *const f64,
    /// Wind velocity in m/s (3 doubles) or NULL for none (PROTOCOL.md 4; needs the wind feature).
    pub wind: *const f64,
    /// Material fields (those named in `material->fields`) or NULL for the server's defaults.
    pub material: *const DrapeMaterial,
    /// Colliders (may be NULL when `collider_count` is 0).
    pub colliders: *const DrapeCollider,
    pub collider_count: usize,
    /// The feature set (DRAPE_FEATURE_* mask) or 0 for the server's default set.
    pub features: u32,
    /// Solver iterations and substeps per tick (0: the server's default).
    pub iterations: u32,
    pub substeps: u32,
    /// States kept unread for this cloth (0 or 1: only the newest; N: reads take the oldest of
    /// up to N first, so a loop reading once per frame misses none while it keeps up).
    pub queue_size: u32,
    /// `drape_submit_*_async`: how long a refusal that may pass (overloaded, busy,
    /// limit_exceeded) or no reply is retried in the background, in ms (0: not retried).
    pub retry_ms: u32,
}

impl Default for DrapeClothOptions {
    fn default() -> Self {
        DrapeClothOptions {
            pinned: std::ptr::null(),
            pinned_count: 0,
            encoding: 0,
            normals: false,
            bundle: false,
            quality: std::ptr::null(),
            gravity: std::ptr::null(),
            wind: std::ptr::null(),
            material: std::ptr::null(),
            colliders: std::ptr::null(),
            collider_count: 0,
            features: 0,
            iterations: 0,
            substeps: 0,
            queue_size: 0,
            retry_ms: 0,
        }
    }
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
    /// 0 float32, 1 float16, 2 quant16, 3 predictive (1.5: decoded on delivery, read as float32).
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

/// The submission options of `opts`, its queue size and its retry time.
pub(crate) unsafe fn submit_of(opts: *const DrapeClothOptions) -> Result<(Submit, usize, Duration), i32> {
    let s = Submit::new("", Shape::Grid(Grid::new(1, 1)));
    let Some(o) = opts.as_ref() else { return Ok((s, 1, Duration::ZERO)) };
    Ok((submit_fields(o, s)?, o.queue_size.max(1) as usize, Duration::from_millis(o.retry_ms as u64)))
}

unsafe fn submit_fields(o: &DrapeClothOptions, mut s: Submit) -> Result<Submit, i32> {
    s.pinned = slice(o.pinned, o.pinned_count).ok_or_else(|| bad("pinned is NULL"))?.to_vec();
    let encoding = Encoding::from_id(u8::try_from(o.encoding).unwrap_or(255)).ok_or_else(|| bad("encoding must be 0, 1, 2 or 3 (DRAPE_ENCODING_*)"))?;
    if encoding != Encoding::Float32 || o.normals || o.bundle {
        s.state = Some(StateOptions { normals: Some(o.normals), encoding: Some(encoding), bundle: o.bundle.then_some(true), step: None });
    }
    s.quality = opt_str(o.quality, "quality")?.map(str::to_string);
    if !o.gravity.is_null() {
        s.gravity = Some([*o.gravity, *o.gravity.add(1), *o.gravity.add(2)]);
    }
    s.wind = super::control::vec3(o.wind);
    s.material = super::control::material_of(o.material)?;
    if o.collider_count > 0 || !o.colliders.is_null() {
        s.colliders = Some(super::control::colliders_of(o.colliders, o.collider_count)?);
    }
    s.features = names_of(o.features)?.unwrap_or_default();
    s.iterations = (o.iterations > 0).then_some(o.iterations);
    s.substeps = (o.substeps > 0).then_some(o.substeps);
    Ok(s)
}

pub(crate) unsafe fn grid_of(g: &DrapeGrid) -> Grid {
    let or1 = |x: f64| if x == 0.0 { 1.0 } else { x };
    let orientation = if g.vertical { Orientation::Vertical } else { Orientation::Horizontal };
    Grid { cols: g.cols, rows: g.rows, width: or1(g.width), height: or1(g.height), orientation, origin: g.origin }
}

/// Submit `sub` with its shape's rest geometry, waiting or not.
pub(crate) fn submit_any(c: &DrapeClient, sub: (Submit, usize, Duration), shape: Shape, asynchronous: bool, out: *mut *mut DrapeCloth) -> i32 {
    let (sub, queue, retry) = sub;
    let geometry = match &shape {
        Shape::Grid(g) => crate::wire::grid_geometry(g.cols, g.rows, g.width, g.height, g.orientation, g.origin),
        Shape::Mesh(m) => Ok((m.vertices.clone(), m.triangles.clone())),
    };
    let (rest, tris) = match geometry {
        Ok(x) => x,
        Err(e) => return fail(e),
    };
    let mut sub = Submit { shape, ..sub };
    super::predictive::submit_step(c, &mut sub.state);
    let r = if asynchronous {
        c.client.submit_async(sub, rest, tris, queue, retry)
    } else {
        c.client.submit_queued(sub, rest, tris, queue)
    };
    new_cloth(r, out)
}

unsafe fn submit_grid(client: *const DrapeClient, grid: *const DrapeGrid, options: *const DrapeClothOptions,
                      out: *mut *mut DrapeCloth, asynchronous: bool) -> i32 {
    guard(|| {
        let (Some(c), Some(g)) = (client.as_ref(), grid.as_ref()) else { return bad("client or grid is NULL") };
        if out.is_null() {
            return bad("out is NULL");
        }
        match submit_of(options) {
            Ok(sub) => submit_any(c, sub, Shape::Grid(grid_of(g)), asynchronous, out),
            Err(code) => code,
        }
    })
}

unsafe fn submit_mesh(client: *const DrapeClient, vertices: *const f32, vertex_count: usize, triangles: *const u32,
                      triangle_count: usize, options: *const DrapeClothOptions, out: *mut *mut DrapeCloth,
                      asynchronous: bool) -> i32 {
    guard(|| {
        let Some(c) = client.as_ref() else { return bad("client is NULL") };
        let (Some(v), Some(t)) = (slice(vertices, 3 * vertex_count), slice(triangles, 3 * triangle_count)) else {
            return bad("vertices or triangles is NULL");
        };
        if out.is_null() {
            return bad("out is NULL");
        }
        match submit_of(options) {
            Ok(sub) => {
                let mesh = crate::wire::Mesh { vertices: v.to_vec(), triangles: t.to_vec() };
                submit_any(c, sub, Shape::Mesh(mesh), asynchronous, out)
            }
            Err(code) => code,
        }
    })
}

/// Submit a grid cloth and wait for the server's reply; `*out` receives its handle. Blocks up
/// to the timeout (and longer when servers refuse and the next is tried): from a game loop use
/// `drape_submit_grid_async`.
#[no_mangle]
pub unsafe extern "C" fn drape_submit_grid(client: *const DrapeClient, grid: *const DrapeGrid,
                                           options: *const DrapeClothOptions, out: *mut *mut DrapeCloth) -> i32 {
    submit_grid(client, grid, options, out, false)
}

/// Submit a grid cloth without waiting: `*out` is its handle at once (DRAPE_CLOTH_PENDING:
/// reads return DRAPE_NO_DATA, controls DRAPE_E_UNAVAILABLE), then DRAPE_EVENT_SUBMITTED (live)
/// or DRAPE_EVENT_SUBMIT_FAILED (after `options->retry_ms` of retries). Invalid options fail
/// here; the server's limits are checked in the background. `drape_cloth_remove` before the
/// reply cancels it.
#[no_mangle]
pub unsafe extern "C" fn drape_submit_grid_async(client: *const DrapeClient, grid: *const DrapeGrid,
                                                 options: *const DrapeClothOptions, out: *mut *mut DrapeCloth) -> i32 {
    submit_grid(client, grid, options, out, true)
}

/// Submit a triangle mesh: `vertices` 3 floats per vertex, `triangles` 3 indices per triangle.
/// Blocks as `drape_submit_grid`.
#[no_mangle]
pub unsafe extern "C" fn drape_submit_mesh(client: *const DrapeClient, vertices: *const f32, vertex_count: usize,
                                           triangles: *const u32, triangle_count: usize,
                                           options: *const DrapeClothOptions, out: *mut *mut DrapeCloth) -> i32 {
    submit_mesh(client, vertices, vertex_count, triangles, triangle_count, options, out, false)
}

/// `drape_submit_mesh` without waiting, as `drape_submit_grid_async`.
#[no_mangle]
pub unsafe extern "C" fn drape_submit_mesh_async(client: *const DrapeClient, vertices: *const f32, vertex_count: usize,
                                                 triangles: *const u32, triangle_count: usize,
                                                 options: *const DrapeClothOptions, out: *mut *mut DrapeCloth) -> i32 {
    submit_mesh(client, vertices, vertex_count, triangles, triangle_count, options, out, true)
}

/// Submit a cloth from a Wavefront OBJ file (faces fan-triangulated). Blocks as
/// `drape_submit_grid`.
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
        let (v, t) = match crate::wire::parse_obj(&text) {
            Ok(x) => x,
            Err(e) => return fail(e),
        };
        match submit_of(options) {
            Ok(sub) if !out.is_null() => submit_any(c, sub, Shape::Mesh(crate::wire::Mesh { vertices: v, triangles: t }), false, out),
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

#[derive(Clone, Copy)]
enum How {
    Next,
    Wait(Duration),
    Latest,
}

unsafe fn read(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize, normals: *mut f32, normals_len: usize,
               info: *mut DrapeStateInfo, how: How) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        if positions.is_null() {
            return bad("positions is NULL");
        }
        let pos = std::slice::from_raw_parts_mut(positions, positions_len);
        let nrm = if normals.is_null() { None } else { Some(std::slice::from_raw_parts_mut(normals, normals_len)) };
        let r = match how {
            How::Wait(t) => c.cloth.wait_state(pos, nrm, t),
            How::Next => c.cloth.read_state(pos, nrm),
            How::Latest => c.cloth.latest_state(pos, nrm),
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

/// Decode the next state not read yet into `positions` (`normals` may be NULL): the oldest
/// unread one of a cloth submitted with a `queue_size` above 1, else the newest. Lengths count
/// FLOATS, not vertices or bytes: 3 per vertex (`3 * drape_cloth_vertex_count`); a shorter
/// buffer is DRAPE_E_INVALID_VALUE. Returns DRAPE_OK, DRAPE_NO_DATA (nothing new), or an error
/// (SERVER_LOST, CLOSED...). `info` may be NULL. Never blocks (not even on a lock: while a
/// Zenoh thread is storing a state for this cloth at that instant it returns DRAPE_NO_DATA and
/// the states stay queued for the next read); no allocation. Read until DRAPE_NO_DATA to take
/// every queued state; `drape_cloth_counters` accounts for all of them.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_read_state(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize,
                                                normals: *mut f32, normals_len: usize, info: *mut DrapeStateInfo) -> i32 {
    read(cloth, positions, positions_len, normals, normals_len, info, How::Next)
}

/// Like `drape_cloth_read_state`, waiting up to `timeout_ms` for a new state (blocks: not for
/// a game thread).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_wait_state(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize,
                                                normals: *mut f32, normals_len: usize, timeout_ms: u32,
                                                info: *mut DrapeStateInfo) -> i32 {
    read(cloth, positions, positions_len, normals, normals_len, info, How::Wait(Duration::from_millis(timeout_ms as u64)))
}

/// Decode the newest state received, read before or not (lengths in floats, as
/// `drape_cloth_read_state`): DRAPE_OK, or DRAPE_NO_DATA before the first state. Unread states
/// older than it are dropped (counted as `replaced`). Never blocks.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_read_latest(cloth: *const DrapeCloth, positions: *mut f32, positions_len: usize,
                                                 normals: *mut f32, normals_len: usize, info: *mut DrapeStateInfo) -> i32 {
    read(cloth, positions, positions_len, normals, normals_len, info, How::Latest)
}

/// The positions to draw at render time `now_ns` (this client's clock: Unix ns, as
/// `DrapeStateInfo.receive_time_ns`; 0: now) into `positions` (`positions_len` FLOATS, at least
/// `3 * drape_cloth_vertex_count`): the last two states received interpolated `delay_ns` behind
/// the newest (negative: one tick, the time between the two states), so that a renderer faster
/// than the server (144 Hz against 60) moves the cloth every frame, at the cost of that delay;
/// `extrapolate`: carried past the newest state instead (no delay; up to one state interval,
/// overshooting where the motion turns). Render times are mapped onto the server's clock by
/// `drape_cloth_clock_offset`. Returns DRAPE_OK, DRAPE_NO_DATA before the first state (nothing
/// written), or an error as `drape_cloth_read_state`. The newest state alone while there is
/// one. Takes nothing from the state queue (the reads and counters are unchanged); each state is
/// decoded once however many frames sample it. Never blocks. (The Python SDK's
/// `ClothHandle.sample`.)
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_sample(cloth: *const DrapeCloth, now_ns: u64, delay_ns: i64, extrapolate: bool,
                                            positions: *mut f32, positions_len: usize) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        if positions.is_null() {
            return bad("positions is NULL");
        }
        let pos = std::slice::from_raw_parts_mut(positions, positions_len);
        let now = (now_ns != 0).then_some(now_ns);
        let delay = u64::try_from(delay_ns).ok().map(Duration::from_nanos);
        match c.cloth.sample(now, delay, extrapolate, pos) {
            Ok(true) => DRAPE_OK,
            Ok(false) => DRAPE_NO_DATA,
            Err(e) => fail(e),
        }
    })
}

/// This client's clock minus the server's as the cloth's states measure it (the smallest
/// `receive_time_ns - server_time_ns` of its last 120 states: the clock offset plus the
/// network's shortest delay) into `*offset_ns`: a render time `t` is server time
/// `t - offset_ns`. DRAPE_OK, or DRAPE_NO_DATA before the first state.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_clock_offset(cloth: *const DrapeCloth, offset_ns: *mut i64) -> i32 {
    guard(|| {
        let (Some(c), Some(o)) = (cloth.as_ref(), offset_ns.as_mut()) else { return bad("cloth or offset_ns is NULL") };
        match c.cloth.clock_offset_ns() {
            Some(v) => {
                *o = v;
                DRAPE_OK
            }
            None => DRAPE_NO_DATA,
        }
    })
}

/// What became of a cloth's states (`drape_cloth_counters`). Every tick from the first state
/// received (per placement) to the newest is counted once:
/// `read + replaced + missed + unread == ticks`, and `received == read + replaced + unread`.
#[repr(C)]
#[derive(Default, Debug, Clone, Copy)]
pub struct DrapeStateCounters {
    /// States received (in tick order).
    pub received: u64,
    /// States decoded by a read.
    pub read: u64,
    /// States received but dropped unread (a newer one replaced them: queue full, or
    /// `drape_cloth_read_latest` skipped them).
    pub replaced: u64,
    /// Ticks of which no state arrived (gaps in the tick numbers).
    pub missed: u64,
    /// States waiting to be read now.
    pub unread: u64,
    /// Ticks spanned from the first state received (per placement) to the newest.
    pub ticks: u64,
    /// Payloads that were not valid states.
    pub invalid: u64,
    /// States older than one already received, ignored.
    pub stale: u64,
    /// The tick of the newest state received (0: none yet).
    pub last_tick: u64,
}

/// Fill `*out` with the cloth's state counters. Never blocks.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_counters(cloth: *const DrapeCloth, out: *mut DrapeStateCounters) -> i32 {
    guard(|| {
        let (Some(c), Some(o)) = (cloth.as_ref(), out.as_mut()) else { return bad("cloth or out is NULL") };
        let k = c.cloth.state_counters();
        *o = DrapeStateCounters {
            received: k.received,
            read: k.read,
            replaced: k.replaced,
            missed: k.missed,
            unread: k.unread,
            ticks: k.ticks,
            invalid: k.invalid,
            stale: k.stale,
            last_tick: k.last_tick,
        };
        DRAPE_OK
    })
}

/// Cloth statuses (`drape_cloth_status`).
pub const DRAPE_CLOTH_PENDING: i32 = 0;
pub const DRAPE_CLOTH_LIVE: i32 = 1;
pub const DRAPE_CLOTH_RESUBMITTING: i32 = 2;
pub const DRAPE_CLOTH_LOST: i32 = 3;
pub const DRAPE_CLOTH_REMOVED: i32 = 4;

/// The cloth's status: DRAPE_CLOTH_PENDING (an asynchronous submission not answered yet),
/// _LIVE, _RESUBMITTING (failover), _LOST, _REMOVED; DRAPE_E_INVALID_VALUE for NULL.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_status(cloth: *const DrapeCloth) -> i32 {
    use crate::client::ClothStatus as S;
    match cloth.as_ref() {
        Some(c) => match c.cloth.status() {
            S::Pending => DRAPE_CLOTH_PENDING,
            S::Live => DRAPE_CLOTH_LIVE,
            S::Resubmitting => DRAPE_CLOTH_RESUBMITTING,
            S::Lost => DRAPE_CLOTH_LOST,
            S::Removed => DRAPE_CLOTH_REMOVED,
        },
        None => bad("cloth is NULL"),
    }
}

pub(crate) unsafe fn control(cloth: *const DrapeCloth, ctl: Control, wait: bool, tick: *mut u64) -> i32 {
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
pub(crate) fn names_of(mask: u32) -> Result<Option<Vec<String>>, i32> {
    if mask >> FEATURE_NAMES.len() != 0 {
        return Err(bad(&format!("unknown feature bits 0x{mask:x} (DRAPE_FEATURE_* are 0x1..0x10)")));
    }
    let names: Vec<String> = FEATURE_NAMES.iter().enumerate().filter(|(i, _)| mask & (1 << i) != 0).map(|(_, n)| n.to_string()).collect();
    Ok((!names.is_empty()).then_some(names))
}

/// The DRAPE_FEATURE_* mask of a feature list (names this version does not know are left out).
pub(crate) fn mask_of(names: &[String]) -> u32 {
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
