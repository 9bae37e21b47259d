//! C ABI of every control option (PROTOCOL.md section 5, as the Python SDK's `ClothHandle.set`):
//! colliders, wind, material, gravity, features, iterations, substeps, quality, state options,
//! reset, pins; waited for, or asynchronous with a completion event. See `mod.rs` for the
//! conventions.
use super::cloth::{names_of, mask_of, slice, DrapeBatch, DrapeCloth};
use super::{bad, fail, guard, opt_str, DRAPE_FEATURES_UNKNOWN, DRAPE_OK};
use crate::wire::{Collider, Control, Encoding, Material, Pins, StateOptions};

/// Collider kinds (`DrapeCollider.kind`).
pub const DRAPE_COLLIDER_SPHERE: i32 = 0;
pub const DRAPE_COLLIDER_CAPSULE: i32 = 1;
pub const DRAPE_COLLIDER_PLANE: i32 = 2;

/// A collider (PROTOCOL.md section 4): a sphere (`a` its centre, `radius`), a capsule (`a`, `b`
/// the ends of its axis, `radius`) or a plane (`a` its normal, `offset`: the half space
/// `normal . x >= offset` is outside). Fields a kind does not use are ignored.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct DrapeCollider {
    /// DRAPE_COLLIDER_*.
    pub kind: i32,
    pub a: [f64; 3],
    pub b: [f64; 3],
    pub radius: f64,
    pub offset: f64,
}

/// Material field bits (`DrapeMaterial.fields`): only the fields named there are sent.
pub const DRAPE_MATERIAL_MASS: u32 = 1;
pub const DRAPE_MATERIAL_STIFFNESS: u32 = 2;
pub const DRAPE_MATERIAL_COMPLIANCE: u32 = 4;
pub const DRAPE_MATERIAL_DAMPING: u32 = 8;
pub const DRAPE_MATERIAL_FRICTION: u32 = 16;
pub const DRAPE_MATERIAL_DRAG: u32 = 32;
pub const DRAPE_MATERIAL_LIFT: u32 = 64;
pub const DRAPE_MATERIAL_AIR_DENSITY: u32 = 128;
pub const DRAPE_MATERIAL_TETHER_LIMIT: u32 = 256;

/// Material (PROTOCOL.md section 4): the fields whose DRAPE_MATERIAL_* bit is in `fields` are
/// sent (at submit: the others take the server's defaults; in a control: the others are kept).
#[repr(C)]
#[derive(Clone, Copy)]
pub struct DrapeMaterial {
    pub fields: u32,
    /// Total mass in kg.
    pub mass: f64,
    /// Structural, shear, bending.
    pub stiffness: [f64; 3],
    pub compliance: [f64; 3],
    pub damping: f64,
    pub friction: f64,
    pub drag: f64,
    pub lift: f64,
    pub air_density: f64,
    pub tether_limit: f64,
}

/// A control (PROTOCOL.md section 5): zero-initialise it and set what changes. Pointers NULL
/// and numbers 0 leave the setting as it is.
#[repr(C)]
pub struct DrapeControl {
    /// Gravity (3 doubles, m/s²) or NULL.
    pub gravity: *const f64,
    /// Wind velocity (3 doubles, m/s) or NULL.
    pub wind: *const f64,
    /// Material fields to change or NULL.
    pub material: *const DrapeMaterial,
    /// The new collider list (replacing the old one) when `set_colliders`; `collider_count` 0
    /// with `set_colliders` removes every collider.
    pub colliders: *const DrapeCollider,
    pub collider_count: usize,
    pub set_colliders: bool,
    /// Features switched on and off (DRAPE_FEATURE_* masks, protocol 1.2; a bit in both is
    /// INVALID_VALUE).
    pub features_add: u32,
    pub features_remove: u32,
    /// Solver iterations and substeps per tick (0: unchanged).
    pub iterations: u32,
    pub substeps: u32,
    /// Quality preset ("fast", "balanced", "accurate", "exact") or NULL.
    pub quality: *const c_char,
    /// When `set_state`: the state encoding (DRAPE_ENCODING_*: 0 float32, 1 float16, 2 quant16,
    /// 3 predictive on the step the cloth has, else the server's default: see
    /// `drape_cloth_set_predictive`) and normals.
    pub set_state: bool,
    pub encoding: i32,
    pub normals: bool,
    /// Back to the rest pose with zero velocity.
    pub reset: bool,
    /// Pinned vertices `pin_indices[i]` move to `pin_targets[3i..3i+3]` (`pin_count` 0: none).
    pub pin_indices: *const u32,
    pub pin_count: usize,
    pub pin_targets: *const f32,
}

use std::ffi::c_char;

impl Default for DrapeControl {
    fn default() -> Self {
        // every pointer NULL, every number 0, every flag false: a control that changes nothing
        unsafe { std::mem::zeroed() }
    }
}

pub(crate) unsafe fn vec3(p: *const f64) -> Option<[f64; 3]> {
    (!p.is_null()).then(|| [*p, *p.add(1), *p.add(2)])
}

pub(crate) unsafe fn material_of(m: *const DrapeMaterial) -> Result<Material, i32> {
    let Some(m) = m.as_ref() else { return Ok(Material::default()) };
    if m.fields >> 9 != 0 {
        return Err(bad(&format!("unknown material field bits 0x{:x} (DRAPE_MATERIAL_* are 0x1..0x100)", m.fields)));
    }
    let on = |bit: u32| m.fields & bit != 0;
    Ok(Material {
        mass: on(DRAPE_MATERIAL_MASS).then_some(m.mass),
        stiffness: on(DRAPE_MATERIAL_STIFFNESS).then_some(m.stiffness),
        compliance: on(DRAPE_MATERIAL_COMPLIANCE).then_some(m.compliance),
        damping: on(DRAPE_MATERIAL_DAMPING).then_some(m.damping),
        friction: on(DRAPE_MATERIAL_FRICTION).then_some(m.friction),
        drag: on(DRAPE_MATERIAL_DRAG).then_some(m.drag),
        lift: on(DRAPE_MATERIAL_LIFT).then_some(m.lift),
        air_density: on(DRAPE_MATERIAL_AIR_DENSITY).then_some(m.air_density),
        tether_limit: on(DRAPE_MATERIAL_TETHER_LIMIT).then_some(m.tether_limit),
        // 1.6 self-collision fields: not in the C struct yet (its layout is the ABI)
        thickness: None,
        contact_stiffness: None,
    })
}

pub(crate) unsafe fn colliders_of(p: *const DrapeCollider, n: usize) -> Result<Vec<Collider>, i32> {
    let list = slice(p, n).ok_or_else(|| bad("colliders is NULL"))?;
    list.iter()
        .map(|c| match c.kind {
            DRAPE_COLLIDER_SPHERE => Ok(Collider::Sphere { center: c.a, radius: c.radius }),
            DRAPE_COLLIDER_CAPSULE => Ok(Collider::Capsule { p0: c.a, p1: c.b, radius: c.radius }),
            DRAPE_COLLIDER_PLANE => Ok(Collider::Plane { normal: c.a, offset: c.offset }),
            k => Err(bad(&format!("unknown collider kind {k} (DRAPE_COLLIDER_SPHERE, _CAPSULE, _PLANE)"))),
        })
        .collect()
}

/// The wire control of a `DrapeControl` (cloth and token are filled in when it is sent).
pub(crate) unsafe fn control_of(c: *const DrapeControl) -> Result<Control, i32> {
    let c = c.as_ref().ok_or_else(|| bad("control is NULL"))?;
    let mut ctl = Control {
        gravity: vec3(c.gravity),
        wind: vec3(c.wind),
        material: material_of(c.material)?,
        features_add: names_of(c.features_add)?,
        features_remove: names_of(c.features_remove)?,
        iterations: (c.iterations > 0).then_some(c.iterations),
        substeps: (c.substeps > 0).then_some(c.substeps),
        quality: opt_str(c.quality, "quality")?.map(str::to_string),
        reset: c.reset,
        ..Default::default()
    };
    if c.set_colliders {
        ctl.colliders = Some(colliders_of(c.colliders, c.collider_count)?);
    }
    if c.set_state {
        let e = Encoding::from_id(u8::try_from(c.encoding).unwrap_or(255)).ok_or_else(|| bad("encoding must be 0, 1, 2 or 3 (DRAPE_ENCODING_*)"))?;
        ctl.state = Some(StateOptions { normals: Some(c.normals), encoding: Some(e), bundle: None, step: None });
    }
    if c.pin_count > 0 {
        let (Some(i), Some(t)) = (slice(c.pin_indices, c.pin_count), slice(c.pin_targets, 3 * c.pin_count)) else {
            return Err(bad("pin_indices or pin_targets is NULL"));
        };
        ctl.pins = Some(Pins { indices: i.to_vec(), targets: t.to_vec() });
    }
    Ok(ctl)
}

/// Send a control and wait for the reply (blocks up to the timeout: for a game thread use
/// `drape_cloth_control_async`). `*tick` (may be NULL) gets the first tick showing it and
/// `*features` (may be NULL) the cloth's resulting feature mask (DRAPE_FEATURES_UNKNOWN when
/// the server did not report it). Feature changes need a 1.2 server (INVALID_VALUE otherwise).
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_control(cloth: *const DrapeCloth, control: *const DrapeControl, tick: *mut u64,
                                             features: *mut u32) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        let ctl = match control_of(control) {
            Ok(x) => x,
            Err(code) => return code,
        };
        match c.cloth.apply(ctl) {
            Ok(a) => {
                if !tick.is_null() {
                    *tick = a.tick;
                }
                if !features.is_null() {
                    *features = a.features.as_deref().map_or(DRAPE_FEATURES_UNKNOWN, mask_of);
                }
                DRAPE_OK
            }
            Err(e) => fail(e),
        }
    })
}

/// Send a control without waiting: returns at once with `*request` (may be NULL) a number
/// naming it; its outcome comes as an event carrying that number: DRAPE_EVENT_REQUEST_DONE
/// (`tick`, `features`) or DRAPE_EVENT_REQUEST_FAILED (`code`, `message`, `cloth`). Never waits
/// on the network. Bad input, or a cloth not live (pending: DRAPE_E_UNAVAILABLE), fails here.
#[no_mangle]
pub unsafe extern "C" fn drape_cloth_control_async(cloth: *const DrapeCloth, control: *const DrapeControl,
                                                   request: *mut u64) -> i32 {
    guard(|| {
        let Some(c) = cloth.as_ref() else { return bad("cloth is NULL") };
        let ctl = match control_of(control) {
            Ok(x) => x,
            Err(code) => return code,
        };
        match c.cloth.control_async(ctl) {
            Ok(r) => {
                if !request.is_null() {
                    *request = r;
                }
                DRAPE_OK
            }
            Err(e) => fail(e),
        }
    })
}

/// Add a control of `cloth` to the batch (any fields, as `drape_cloth_control`).
#[no_mangle]
pub unsafe extern "C" fn drape_batch_control(batch: *mut DrapeBatch, cloth: *const DrapeCloth,
                                             control: *const DrapeControl) -> i32 {
    guard(|| {
        let (Some(b), Some(c)) = (batch.as_mut(), cloth.as_ref()) else { return bad("batch or cloth is NULL") };
        match control_of(control) {
            Ok(ctl) => {
                b.batch.add(&c.cloth, ctl);
                DRAPE_OK
            }
            Err(code) => code,
        }
    })
}
