//! Client-side checks of requests before they are sent, with the codes the server would
//! answer (PROTOCOL.md sections 3-5, 8, 13): bad input fails fast with a clear message instead
//! of a round trip. Quotas that depend on the server's load (`limit_exceeded`) stay server-side.
use super::error::{invalid, Error, ErrorCode, Result};
use super::keys::{valid_id, valid_token};
use super::msg::{Collider, Control, ControlBatch, Material, Resume, Shape, StateOptions, Submit};
use super::{STEP_MAX, STEP_MIN};
use super::{FEATURE_NAMES, MAX_BATCH_ITEMS, MAX_COLLIDERS, MAX_FEATURES, MAX_PIN_UPDATES, MIN_MASS, QUALITY_PRESETS};

/// Per-server limits a client checks against (PROTOCOL.md section 13 defaults, or `info`'s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    pub max_vertices_per_cloth: u64,
    pub max_pin_updates: usize,
    pub max_batch_items: usize,
    pub max_iterations: u64,
    pub max_substeps: u64,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            max_vertices_per_cloth: 65_536,
            max_pin_updates: MAX_PIN_UPDATES,
            max_batch_items: MAX_BATCH_ITEMS,
            max_iterations: 100,
            max_substeps: 100,
        }
    }
}

const COORD: f64 = 1e5;
const ACCEL: f64 = 1e4;
const UPPER: f64 = 1e6;

fn err(code: ErrorCode, msg: String) -> Error {
    Error::new(code, msg)
}

fn finite(name: &str, x: f64, lo: f64, hi: f64) -> Result<()> {
    if !x.is_finite() || x < lo || x > hi {
        return Err(invalid(format!("'{name}' = {x} must be finite within [{lo}, {hi}]")));
    }
    Ok(())
}

fn vec3(name: &str, v: Option<[f64; 3]>, bound: f64) -> Result<()> {
    for (i, x) in v.unwrap_or_default().iter().enumerate() {
        finite(&format!("{name}[{i}]"), *x, -bound, bound)?;
    }
    Ok(())
}

/// 1.5: `state.step` within [`STEP_MIN`, `STEP_MAX`] metres.
fn state_options(o: Option<&StateOptions>) -> Result<()> {
    match o.and_then(|o| o.step) {
        Some(x) => finite("state.step", x, STEP_MIN, STEP_MAX),
        None => Ok(()),
    }
}

fn material(m: &Material) -> Result<()> {
    if let Some(x) = m.mass {
        if !(MIN_MASS..=UPPER).contains(&x) {
            return Err(invalid(format!("'material.mass' = {x} must be within [{MIN_MASS}, {UPPER}] kg")));
        }
    }
    for (name, v, hi) in [("stiffness", m.stiffness, 1.0), ("compliance", m.compliance, UPPER)] {
        vec3(&format!("material.{name}"), v, hi)?;
        if v.unwrap_or_default().iter().any(|x| *x < 0.0) {
            return Err(invalid(format!("'material.{name}' must be >= 0")));
        }
    }
    let scalars = [("damping", m.damping, 0.0, 1.0), ("friction", m.friction, 0.0, UPPER), ("drag", m.drag, 0.0, UPPER),
        ("lift", m.lift, 0.0, UPPER), ("air_density", m.air_density, 0.0, UPPER), ("tether_limit", m.tether_limit, 1.0, UPPER),
        ("thickness", m.thickness, 0.0, 1.0), ("contact_stiffness", m.contact_stiffness, 0.0, 1.0)];
    for (name, v, lo, hi) in scalars {
        if let Some(x) = v {
            finite(&format!("material.{name}"), x, lo, hi)?;
        }
    }
    Ok(())
}

pub(crate) fn colliders(c: &Option<Vec<Collider>>) -> Result<()> {
    let Some(c) = c else { return Ok(()) };
    if c.len() > MAX_COLLIDERS {
        return Err(err(ErrorCode::TooLarge, format!("{} colliders, at most {MAX_COLLIDERS}", c.len())));
    }
    for (i, x) in c.iter().enumerate() {
        let n = format!("colliders[{i}]");
        match *x {
            Collider::Sphere { center, radius } => {
                vec3(&format!("{n}.center"), Some(center), COORD)?;
                finite(&format!("{n}.radius"), radius, 0.0, COORD)?;
            }
            Collider::Capsule { p0, p1, radius } => {
                vec3(&format!("{n}.p0"), Some(p0), COORD)?;
                vec3(&format!("{n}.p1"), Some(p1), COORD)?;
                finite(&format!("{n}.radius"), radius, 0.0, COORD)?;
            }
            Collider::Plane { normal, offset } => {
                vec3(&format!("{n}.normal"), Some(normal), COORD)?;
                if normal == [0.0; 3] {
                    return Err(invalid(format!("'{n}.normal' must be non-zero")));
                }
                finite(&format!("{n}.offset"), offset, -COORD, COORD)?;
            }
        }
    }
    Ok(())
}

/// A feature list (`features`, and 1.2's `features_add` / `features_remove`): at most
/// `MAX_FEATURES` known names.
fn feature_list(key: &str, features: Option<&[String]>) -> Result<()> {
    let features = features.unwrap_or_default();
    if features.len() > MAX_FEATURES {
        return Err(err(ErrorCode::TooLarge, format!("'{key}' has {} entries, at most {MAX_FEATURES}", features.len())));
    }
    if let Some(f) = features.iter().find(|f| !FEATURE_NAMES.contains(&f.as_str())) {
        return Err(invalid(format!("unknown feature {f:?} in '{key}'; known: {FEATURE_NAMES:?}")));
    }
    Ok(())
}

fn options(features: Option<&[String]>, quality: Option<&str>, iters: Option<u32>, substeps: Option<u32>,
           rho: Option<f64>, lim: &Limits) -> Result<()> {
    feature_list("features", features)?;
    if let Some(q) = quality.filter(|q| !QUALITY_PRESETS.contains(q)) {
        return Err(invalid(format!("unknown quality {q:?}; known: {QUALITY_PRESETS:?}")));
    }
    if iters.is_some_and(|i| i as u64 > lim.max_iterations) {
        return Err(invalid(format!("'iterations' must be within 0..{}", lim.max_iterations)));
    }
    if substeps.is_some_and(|s| s == 0 || s as u64 > lim.max_substeps) {
        return Err(invalid(format!("'substeps' must be within 1..{}", lim.max_substeps)));
    }
    if let Some(r) = rho {
        if !(0.0..1.0).contains(&r) {
            return Err(invalid(format!("'chebyshev_rho' = {r} must be within [0, 1)")));
        }
    }
    Ok(())
}

impl Submit {
    /// The vertex count of the cloth this submits (0 for a malformed mesh).
    pub fn vertex_count(&self) -> u64 {
        match &self.shape {
            Shape::Grid(g) => g.cols as u64 * g.rows as u64,
            Shape::Mesh(m) => (m.vertices.len() / 3) as u64,
        }
    }

    /// Check the request as the server would (but for quotas).
    pub fn validate(&self, lim: &Limits) -> Result<()> {
        if !valid_id(&self.client) {
            return Err(invalid(format!("invalid client id {:?}", self.client)));
        }
        let n = self.vertex_count();
        match &self.shape {
            Shape::Grid(g) => {
                if g.cols < 1 || g.rows < 1 {
                    return Err(invalid("'grid.cols' and 'grid.rows' must be >= 1"));
                }
                finite("grid.width", g.width, f64::MIN_POSITIVE, UPPER)?;
                finite("grid.height", g.height, f64::MIN_POSITIVE, UPPER)?;
                vec3("grid.origin", Some(g.origin), COORD)?;
            }
            Shape::Mesh(m) => {
                if m.vertices.len() % 3 != 0 || m.triangles.len() % 3 != 0 {
                    return Err(invalid("mesh vertices and triangles must hold 3 values each"));
                }
                if n == 0 {
                    return Err(invalid("a mesh needs at least one vertex"));
                }
                if let Some(x) = m.vertices.iter().find(|x| !x.is_finite() || x.abs() > COORD as f32) {
                    return Err(invalid(format!("'mesh.vertices' holds {x}: coordinates must be finite within ±1e5")));
                }
                if m.triangles.len() as u64 / 3 > 4 * lim.max_vertices_per_cloth {
                    return Err(err(ErrorCode::TooLarge, format!("{} triangles, at most {}", m.triangles.len() / 3, 4 * lim.max_vertices_per_cloth)));
                }
                for (t, tri) in m.triangles.chunks_exact(3).enumerate() {
                    if let Some(i) = tri.iter().find(|i| **i as u64 >= n) {
                        return Err(err(ErrorCode::IndexOutOfRange, format!("triangle {t} refers to vertex {i} but the mesh has {n} vertices")));
                    }
                    if tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2] {
                        return Err(invalid(format!("triangle {t} repeats a vertex")));
                    }
                }
            }
        }
        if n > lim.max_vertices_per_cloth {
            return Err(err(ErrorCode::TooLarge, format!("{n} vertices, at most {}", lim.max_vertices_per_cloth)));
        }
        if let Some(i) = self.pinned.iter().find(|i| **i as u64 >= n) {
            return Err(err(ErrorCode::IndexOutOfRange, format!("'pinned' refers to vertex {i} but the cloth has {n} vertices")));
        }
        vec3("gravity", self.gravity, ACCEL)?;
        vec3("wind", self.wind, ACCEL)?;
        material(&self.material)?;
        colliders(&self.colliders)?;
        state_options(self.state.as_ref())?;
        options(Some(&self.features), self.quality.as_deref(), self.iterations, self.substeps, self.chebyshev_rho, lim)?;
        if let Some(mc) = &self.mesh_collider {
            mc.validate("mesh_collider", true)?;
        }
        if let Some(sc) = &self.scene {
            if !valid_id(sc) {
                return Err(invalid(format!("'scene' must be 1-64 characters of [A-Za-z0-9_.-], got {sc:?}")));
            }
        }
        match &self.resume {
            Some(r) => r.validate(n, lim),
            None => Ok(()),
        }
    }
}

impl Resume {
    /// 1.3 (PROTOCOL.md section 4.1): positions and velocities of exactly `n` vertices, finite,
    /// positions within ±1e5 m and velocities within ±1e4 m/s; ids well formed.
    pub fn validate(&self, n: u64, lim: &Limits) -> Result<()> {
        for (name, v, bound) in [("positions", Some(&self.positions), COORD), ("velocities", self.velocities.as_ref(), ACCEL)] {
            let Some(v) = v else { continue };
            if v.len() % 3 != 0 {
                return Err(invalid(format!("'resume.{name}' must hold 3 floats per vertex")));
            }
            let count = (v.len() / 3) as u64;
            if count > lim.max_vertices_per_cloth {
                return Err(err(ErrorCode::TooLarge, format!("'resume.{name}' has {count} vertices, at most {}", lim.max_vertices_per_cloth)));
            }
            if count != n {
                return Err(invalid(format!("'resume.{name}' has {count} vertices but the cloth has {n}")));
            }
            if let Some(x) = v.iter().find(|x| !x.is_finite()) {
                return Err(invalid(format!("'resume.{name}' must be finite (holds {x})")));
            }
            if let Some(x) = v.iter().find(|x| x.abs() as f64 > bound) {
                return Err(invalid(format!("'resume.{name}' values must be within ±{bound}, got {x}")));
            }
        }
        for (name, id) in [("from_server", &self.from_server), ("cloth", &self.cloth)] {
            if let Some(id) = id.as_deref().filter(|id| !valid_id(id)) {
                return Err(invalid(format!("'resume.{name}' = {id:?} is not a valid id")));
            }
        }
        Ok(())
    }
}

impl Control {
    /// Check a control (or batch item) as the server would, but for what needs the cloth
    /// (whether an index is pinned, the vertex count): `n_vertices` if known.
    pub fn validate(&self, lim: &Limits, n_vertices: Option<u32>) -> Result<()> {
        if !valid_id(&self.cloth) {
            return Err(invalid(format!("invalid cloth id {:?}", self.cloth)));
        }
        if !valid_token(&self.token) {
            return Err(invalid("'token' must be 32 lowercase hex digits"));
        }
        if let Some(p) = &self.pins {
            if p.targets.len() != 3 * p.indices.len() {
                return Err(invalid(format!("{} pin indices but {} target floats (3 per pin)", p.indices.len(), p.targets.len())));
            }
            if p.indices.len() > lim.max_pin_updates {
                return Err(err(ErrorCode::TooLarge, format!("{} pin updates, at most {}", p.indices.len(), lim.max_pin_updates)));
            }
            if let Some(x) = p.targets.iter().find(|x| !x.is_finite() || x.abs() > COORD as f32) {
                return Err(invalid(format!("'pins.targets' holds {x}: targets must be finite within ±1e5")));
            }
            if let (Some(n), Some(i)) = (n_vertices, p.indices.iter().max()) {
                if *i >= n {
                    return Err(err(ErrorCode::IndexOutOfRange, format!("pin index {i} but the cloth has {n} vertices")));
                }
            }
        }
        if self.state.is_some_and(|s| s.bundle.is_some()) {
            return Err(invalid("'state.bundle' is chosen at submission only"));
        }
        vec3("gravity", self.gravity, ACCEL)?;
        vec3("wind", self.wind, ACCEL)?;
        material(&self.material)?;
        colliders(&self.colliders)?;
        state_options(self.state.as_ref())?;
        options(self.features.as_deref(), self.quality.as_deref(), self.iterations, self.substeps, self.chebyshev_rho, lim)?;
        feature_list("features_add", self.features_add.as_deref())?;
        feature_list("features_remove", self.features_remove.as_deref())?;
        let add = self.features_add.as_deref().unwrap_or_default();
        if let Some(f) = self.features_remove.as_deref().unwrap_or_default().iter().find(|f| add.contains(f)) {
            return Err(invalid(format!("feature {f:?} is in both 'features_add' and 'features_remove'")));
        }
        match &self.mesh_collider {
            Some(mc) => mc.validate("mesh_collider", false),
            None => Ok(()),
        }
    }

    /// Whether the control uses a field a 1.1 server would silently ignore (1.2's
    /// `features_add` / `features_remove`).
    pub fn needs_1_2(&self) -> bool {
        self.features_add.is_some() || self.features_remove.is_some()
    }
}

impl ControlBatch {
    /// Check the envelope: a valid client and 1..max_batch_items items.
    pub fn validate_envelope(&self, lim: &Limits) -> Result<()> {
        check_envelope(&self.client, self.items.len(), lim)
    }

    /// Decode a batch control the way the server reads it: the envelope all or nothing, then
    /// each item standing alone (decoded and validated, or its error). 1.4: a `moves` block is
    /// validated with the envelope; [`super::moves::DecodedBatch`] returns it too.
    pub fn decode_items(data: &[u8], lim: &Limits) -> Result<(String, Vec<Result<Control>>)> {
        super::moves::DecodedBatch::decode(data, lim).map(|d| (d.client, d.items))
    }
}

fn check_envelope(client: &str, n: usize, lim: &Limits) -> Result<()> {
    if !valid_id(client) {
        return Err(invalid(format!("invalid client id {client:?}")));
    }
    if n == 0 {
        return Err(invalid("'items' is empty"));
    }
    if n > lim.max_batch_items {
        return Err(err(ErrorCode::TooLarge, format!("{n} items, at most {}", lim.max_batch_items)));
    }
    Ok(())
}

/// Check a remove request's owner fields.
pub fn validate_owner(cloth: &str, token: &str) -> Result<()> {
    if !valid_id(cloth) {
        return Err(invalid(format!("invalid cloth id {cloth:?}")));
    }
    if !valid_token(token) {
        return Err(invalid("'token' must be 32 lowercase hex digits"));
    }
    Ok(())
}
