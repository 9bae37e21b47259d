//! Request messages (PROTOCOL.md sections 4-7): submit, control, batch control, remove, info.
//! Each encodes to the reference's exact bytes (field order of the tables, float64 floats,
//! smallest integers) and decodes back, so the test vectors check both ways.
use super::error::{invalid, Error, ErrorCode, Result};
use super::msg_decode::{read_colliders, read_material, read_state, read_strings, u32v};
use super::meshcollider::MeshCollider;
use super::reader::{bin_f32, bin_u32, header, pack, s, unpack_message, vec3, Map, Reader, Value};

/// State encodings (the state header's `encoding` byte).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Encoding {
    Float32 = 0,
    Float16 = 1,
    Quant16 = 2,
    /// 1.5 (PROTOCOL.md 9.2): each state coded against the stream's last two on a grid of
    /// `StateOptions::step`; decoded in order ([`super::PredictiveStream`]; the client does it
    /// on delivery). Ask for it only from a server of version >= 1.5.
    Predictive = 3,
}

impl Encoding {
    /// Every encoding, by id.
    pub const ALL: [Encoding; 4] = [Self::Float32, Self::Float16, Self::Quant16, Self::Predictive];

    pub fn from_id(id: u8) -> Option<Encoding> {
        Self::ALL.get(id as usize).copied()
    }
    pub fn name(self) -> &'static str {
        ["float32", "float16", "quant16", "predictive"][self as usize]
    }
    pub fn from_name(name: &str) -> Option<Encoding> {
        Self::ALL.into_iter().find(|e| e.name() == name)
    }
    /// Bytes per coordinate: 4 for float32, 2 for float16 and quant16, 0 for predictive (its
    /// packed positions are of variable length: their size is in its 1.5 header).
    pub fn element_size(self) -> usize {
        match self {
            Self::Float32 => 4,
            Self::Float16 | Self::Quant16 => 2,
            Self::Predictive => 0,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Orientation {
    #[default]
    Horizontal,
    Vertical,
}

impl Orientation {
    pub fn name(self) -> &'static str {
        if self == Self::Horizontal { "horizontal" } else { "vertical" }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    pub cols: u32,
    pub rows: u32,
    pub width: f64,
    pub height: f64,
    pub orientation: Orientation,
    pub origin: [f64; 3],
}

impl Grid {
    pub fn new(cols: u32, rows: u32) -> Grid {
        Grid { cols, rows, width: 1.0, height: 1.0, orientation: Orientation::Horizontal, origin: [0.0; 3] }
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// Rest positions, xyz interleaved.
    pub vertices: Vec<f32>,
    /// Vertex indices, three per triangle.
    pub triangles: Vec<u32>,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    Grid(Grid),
    Mesh(Mesh),
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Collider {
    Sphere { center: [f64; 3], radius: f64 },
    Capsule { p0: [f64; 3], p1: [f64; 3], radius: f64 },
    /// The half space `normal . x >= offset` is outside.
    Plane { normal: [f64; 3], offset: f64 },
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Links {
    pub structural: bool,
    pub shear: bool,
    pub bending: bool,
}

/// Material fields; `None` = server default (submit) or unchanged (control).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Material {
    pub mass: Option<f64>,
    pub stiffness: Option<[f64; 3]>,
    pub compliance: Option<[f64; 3]>,
    pub damping: Option<f64>,
    pub friction: Option<f64>,
    pub drag: Option<f64>,
    pub lift: Option<f64>,
    pub air_density: Option<f64>,
    pub tether_limit: Option<f64>,
    /// 1.6, self_collision: metres kept between non-neighbouring vertices of the cloth.
    pub thickness: Option<f64>,
    /// 1.6, self_collision: the share of a contact corrected per pass (0..1).
    pub contact_stiffness: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StateOptions {
    pub normals: Option<bool>,
    pub encoding: Option<Encoding>,
    pub bundle: Option<bool>,
    /// 1.5: the predictive encoding's grid, metres ([`super::STEP_MIN`]..[`super::STEP_MAX`];
    /// the server's default [`super::STEP_DEFAULT`]); a decoded position is within `step / 2`
    /// of the simulated one. A control changing it makes the next predictive state a keyframe.
    pub step: Option<f64>,
}

impl StateOptions {
    /// Whether these options need a protocol 1.5 server (the predictive encoding or a step; a
    /// 1.4 server refuses them with `invalid_value`).
    pub fn needs_1_5(&self) -> bool {
        self.encoding == Some(Encoding::Predictive) || self.step.is_some()
    }
}

/// Pin updates: `targets[3i..3i+3]` is where pinned vertex `indices[i]` goes.
#[derive(Debug, Clone, PartialEq)]
pub struct Pins {
    pub indices: Vec<u32>,
    pub targets: Vec<f32>,
}

/// 1.3: the state a resubmitted cloth continues from (PROTOCOL.md section 4.1): positions
/// (and velocities, m/s) of every vertex, xyz interleaved; the other fields are informational.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Resume {
    pub positions: Vec<f32>,
    /// Absent = zero velocities.
    pub velocities: Option<Vec<f32>>,
    /// The tick of the state resumed from, on the server it came from.
    pub tick: Option<u64>,
    pub from_server: Option<String>,
    /// The cloth's id on that server.
    pub cloth: Option<String>,
}

impl Resume {
    pub fn to_value(&self) -> Value {
        let mut m = vec![(s("positions"), bin_f32(&self.positions))];
        if let Some(v) = &self.velocities {
            m.push((s("velocities"), bin_f32(v)));
        }
        if let Some(t) = self.tick {
            m.push((s("tick"), Value::from(t)));
        }
        if let Some(x) = &self.from_server {
            m.push((s("from_server"), s(x)));
        }
        if let Some(x) = &self.cloth {
            m.push((s("cloth"), s(x)));
        }
        Value::Map(m)
    }

    /// Read a `resume` map (types only; [`Submit::validate`] checks counts and bounds).
    pub fn from_reader(r: &Reader<'_>) -> Result<Resume> {
        Ok(Resume {
            positions: r.f32s("positions", true)?.unwrap(),
            velocities: r.f32s("velocities", false)?,
            tick: r.u64("tick", false)?,
            from_server: r.str("from_server", false)?.map(str::to_string),
            cloth: r.str("cloth", false)?.map(str::to_string),
        })
    }
}

/// A submit request (section 4).
#[derive(Debug, Clone, PartialEq)]
pub struct Submit {
    pub rid: u64,
    pub client: String,
    pub shape: Shape,
    pub pinned: Vec<u32>,
    pub links: Option<Links>,
    pub material: Material,
    pub features: Vec<String>,
    pub gravity: Option<[f64; 3]>,
    pub wind: Option<[f64; 3]>,
    pub iterations: Option<u32>,
    pub substeps: Option<u32>,
    pub chebyshev_rho: Option<f64>,
    pub colliders: Option<Vec<Collider>>,
    pub state: Option<StateOptions>,
    pub quality: Option<String>,
    /// 1.3: continue from this state instead of the rest pose (a 1.2 server ignores it).
    pub resume: Option<Resume>,
    /// 1.7: the scene the cloth collides in (a 1.6 server ignores it: the cloth is alone).
    pub scene: Option<String>,
    /// 1.8: the cloth's own mesh collider, a new mesh at its pose (PROTOCOL.md 5.4; a 1.7 server
    /// ignores it: refused client-side toward one).
    pub mesh_collider: Option<MeshCollider>,
}

impl Submit {
    pub fn new(client: &str, shape: Shape) -> Submit {
        Submit {
            rid: 0,
            client: client.to_string(),
            shape,
            pinned: Vec::new(),
            links: None,
            material: Material::default(),
            features: Vec::new(),
            gravity: None,
            wind: None,
            iterations: None,
            substeps: None,
            chebyshev_rho: None,
            colliders: None,
            state: None,
            quality: None,
            resume: None,
            scene: None,
            mesh_collider: None,
        }
    }
}

/// A control (section 5), also one item of a batch control.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Control {
    pub cloth: String,
    pub token: String,
    pub pins: Option<Pins>,
    pub colliders: Option<Vec<Collider>>,
    pub gravity: Option<[f64; 3]>,
    pub wind: Option<[f64; 3]>,
    pub material: Material,
    /// Replaces the whole feature set (1.0 meaning; prefer `features_add` / `features_remove`).
    pub features: Option<Vec<String>>,
    /// 1.2: features switched on, the others kept (send only to a server of version >= 1.2).
    pub features_add: Option<Vec<String>>,
    /// 1.2: features switched off, the others kept; a name in both lists is `invalid_value`.
    pub features_remove: Option<Vec<String>>,
    pub iterations: Option<u32>,
    pub substeps: Option<u32>,
    pub chebyshev_rho: Option<f64>,
    pub state: Option<StateOptions>,
    pub quality: Option<String>,
    pub reset: bool,
    /// 1.8: sets, re-poses, moves or removes the cloth's own mesh collider (PROTOCOL.md 5.4).
    pub mesh_collider: Option<MeshCollider>,
}

/// A batch control (section 5.1).
#[derive(Debug, Clone, PartialEq)]
pub struct ControlBatch {
    pub rid: u64,
    pub client: String,
    pub items: Vec<Control>,
}

pub(crate) fn collider_value(c: &Collider) -> Value {
    Value::Map(match *c {
        Collider::Sphere { center, radius } => {
            vec![(s("type"), s("sphere")), (s("center"), vec3(center)), (s("radius"), Value::F64(radius))]
        }
        Collider::Capsule { p0, p1, radius } => vec![
            (s("type"), s("capsule")),
            (s("p0"), vec3(p0)),
            (s("p1"), vec3(p1)),
            (s("radius"), Value::F64(radius)),
        ],
        Collider::Plane { normal, offset } => {
            vec![(s("type"), s("plane")), (s("normal"), vec3(normal)), (s("offset"), Value::F64(offset))]
        }
    })
}

fn material_map(m: &Material) -> Map {
    let mut out = Map::new();
    let scalars = [("mass", m.mass)];
    let push = |out: &mut Map, k: &str, v: Option<f64>| {
        if let Some(v) = v {
            out.push((s(k), Value::F64(v)));
        }
    };
    for (k, v) in scalars {
        push(&mut out, k, v);
    }
    for (k, v) in [("stiffness", m.stiffness), ("compliance", m.compliance)] {
        if let Some(v) = v {
            out.push((s(k), vec3(v)));
        }
    }
    for (k, v) in [("damping", m.damping), ("friction", m.friction), ("drag", m.drag), ("lift", m.lift)] {
        push(&mut out, k, v);
    }
    push(&mut out, "air_density", m.air_density);
    push(&mut out, "tether_limit", m.tether_limit);
    push(&mut out, "thickness", m.thickness);
    push(&mut out, "contact_stiffness", m.contact_stiffness);
    out
}

fn state_map(o: &StateOptions) -> Value {
    let mut m = Map::new();
    if let Some(n) = o.normals {
        m.push((s("normals"), Value::Boolean(n)));
    }
    if let Some(e) = o.encoding {
        m.push((s("encoding"), s(e.name())));
    }
    if let Some(b) = o.bundle {
        m.push((s("bundle"), Value::Boolean(b)));
    }
    if let Some(x) = o.step {
        m.push((s("step"), Value::F64(x)));
    }
    Value::Map(m)
}

pub(crate) fn strings(v: &[String]) -> Value {
    Value::Array(v.iter().map(|x| s(x)).collect())
}

impl Submit {
    pub fn to_value(&self) -> Value {
        let mut m = header(self.rid);
        m.push((s("client"), s(&self.client)));
        match &self.shape {
            Shape::Grid(g) => m.push((
                s("grid"),
                Value::Map(vec![
                    (s("cols"), Value::from(g.cols)),
                    (s("rows"), Value::from(g.rows)),
                    (s("width"), Value::F64(g.width)),
                    (s("height"), Value::F64(g.height)),
                    (s("orientation"), s(g.orientation.name())),
                    (s("origin"), vec3(g.origin)),
                ]),
            )),
            Shape::Mesh(x) => m.push((
                s("mesh"),
                Value::Map(vec![(s("vertices"), bin_f32(&x.vertices)), (s("triangles"), bin_u32(&x.triangles))]),
            )),
        }
        if !self.pinned.is_empty() {
            m.push((s("pinned"), bin_u32(&self.pinned)));
        }
        if let Some(l) = self.links {
            let b = Value::Boolean;
            m.push((
                s("links"),
                Value::Map(vec![(s("structural"), b(l.structural)), (s("shear"), b(l.shear)), (s("bending"), b(l.bending))]),
            ));
        }
        let mat = material_map(&self.material);
        if !mat.is_empty() {
            m.push((s("material"), Value::Map(mat)));
        }
        if !self.features.is_empty() {
            m.push((s("features"), strings(&self.features)));
        }
        common_tail(&mut m, self.gravity, self.wind, self.iterations, self.substeps, self.chebyshev_rho);
        if let Some(c) = &self.colliders {
            m.push((s("colliders"), Value::Array(c.iter().map(collider_value).collect())));
        }
        if let Some(st) = &self.state {
            m.push((s("state"), state_map(st)));
        }
        if let Some(q) = &self.quality {
            m.push((s("quality"), s(q)));
        }
        if let Some(mc) = &self.mesh_collider {
            m.push((s("mesh_collider"), mc.to_value()));
        }
        if let Some(r) = &self.resume {
            m.push((s("resume"), r.to_value()));
        }
        if let Some(sc) = &self.scene {
            m.push((s("scene"), s(sc)));
        }
        Value::Map(m)
    }

    pub fn encode(&self) -> Vec<u8> {
        pack(&self.to_value())
    }

    /// Decode a submit request (shape and types; the server checks ranges and limits).
    pub fn decode(data: &[u8]) -> Result<Submit> {
        let m = unpack_message(data)?;
        let r = Reader::new(&m, "");
        let rid = r.u64("rid", false)?.unwrap_or(0);
        let shape = match (r.sub("grid", false)?, r.sub("mesh", false)?) {
            (Some(g), None) => Shape::Grid(Grid {
                cols: u32v(&g, "cols", true)?.unwrap(),
                rows: u32v(&g, "rows", true)?.unwrap(),
                width: g.f64("width", false)?.unwrap_or(1.0),
                height: g.f64("height", false)?.unwrap_or(1.0),
                orientation: match g.str("orientation", false)? {
                    None | Some("horizontal") => Orientation::Horizontal,
                    Some("vertical") => Orientation::Vertical,
                    Some(o) => return Err(invalid(format!("unknown orientation {o:?}"))),
                },
                origin: g.vec3("origin", false)?.unwrap_or([0.0; 3]),
            }),
            (None, Some(x)) => Shape::Mesh(Mesh {
                vertices: x.f32s("vertices", true)?.unwrap(),
                triangles: x.u32s("triangles", true)?.unwrap(),
            }),
            (None, None) => return Err(Error::new(ErrorCode::MissingField, "one of 'grid' and 'mesh' is required")),
            _ => return Err(invalid("'grid' and 'mesh' are both given")),
        };
        let links = match r.sub("links", false)? {
            None => None,
            Some(l) => Some(Links {
                structural: l.bool("structural", false)?.unwrap_or(true),
                shear: l.bool("shear", false)?.unwrap_or(true),
                bending: l.bool("bending", false)?.unwrap_or(false),
            }),
        };
        Ok(Submit {
            rid,
            client: r.str("client", true)?.unwrap().to_string(),
            shape,
            pinned: r.u32s("pinned", false)?.unwrap_or_default(),
            links,
            material: read_material(&r)?,
            features: read_strings(&r, "features")?.unwrap_or_default(),
            gravity: r.vec3("gravity", false)?,
            wind: r.vec3("wind", false)?,
            iterations: u32v(&r, "iterations", false)?,
            substeps: u32v(&r, "substeps", false)?,
            chebyshev_rho: r.f64("chebyshev_rho", false)?,
            colliders: read_colliders(&r)?,
            state: read_state(&r)?,
            quality: r.str("quality", false)?.map(str::to_string),
            resume: match r.sub("resume", false)? {
                None => None,
                Some(x) => Some(Resume::from_reader(&x)?),
            },
            scene: r.str("scene", false)?.map(str::to_string),
            mesh_collider: MeshCollider::from_reader(&r, "mesh_collider")?,
        })
    }
}

fn common_tail(m: &mut Map, gravity: Option<[f64; 3]>, wind: Option<[f64; 3]>, iterations: Option<u32>, substeps: Option<u32>, rho: Option<f64>) {
    if let Some(g) = gravity {
        m.push((s("gravity"), vec3(g)));
    }
    if let Some(w) = wind {
        m.push((s("wind"), vec3(w)));
    }
    if let Some(i) = iterations {
        m.push((s("iterations"), Value::from(i)));
    }
    if let Some(i) = substeps {
        m.push((s("substeps"), Value::from(i)));
    }
    if let Some(x) = rho {
        m.push((s("chebyshev_rho"), Value::F64(x)));
    }
}

impl Control {
    /// A control of `cloth` owned by `token` that changes nothing yet.
    pub fn new(cloth: &str, token: &str) -> Control {
        Control { cloth: cloth.to_string(), token: token.to_string(), ..Default::default() }
    }

    /// The item map (no `v`, no `rid`): one item of a batch control.
    pub fn item_map(&self) -> Map {
        let mut m = vec![(s("cloth"), s(&self.cloth)), (s("token"), s(&self.token))];
        if let Some(p) = &self.pins {
            m.push((s("pins"), Value::Map(vec![(s("indices"), bin_u32(&p.indices)), (s("targets"), bin_f32(&p.targets))])));
        }
        if let Some(c) = &self.colliders {
            m.push((s("colliders"), Value::Array(c.iter().map(collider_value).collect())));
        }
        if let Some(g) = self.gravity {
            m.push((s("gravity"), vec3(g)));
        }
        if let Some(w) = self.wind {
            m.push((s("wind"), vec3(w)));
        }
        let mat = material_map(&self.material);
        if !mat.is_empty() {
            m.push((s("material"), Value::Map(mat)));
        }
        if let Some(f) = &self.features {
            m.push((s("features"), strings(f)));
        }
        if let Some(f) = &self.features_add {
            m.push((s("features_add"), strings(f)));
        }
        if let Some(f) = &self.features_remove {
            m.push((s("features_remove"), strings(f)));
        }
        common_tail(&mut m, None, None, self.iterations, self.substeps, self.chebyshev_rho);
        if let Some(st) = &self.state {
            m.push((s("state"), state_map(st)));
        }
        if let Some(q) = &self.quality {
            m.push((s("quality"), s(q)));
        }
        if self.reset {
            m.push((s("reset"), Value::Boolean(true)));
        }
        if let Some(mc) = &self.mesh_collider {
            m.push((s("mesh_collider"), mc.to_value()));
        }
        m
    }

    pub fn encode(&self, rid: u64) -> Vec<u8> {
        let mut m = header(rid);
        m.extend(self.item_map());
        pack(&Value::Map(m))
    }

    /// Read a control's fields from a map (a control message or a batch item).
    pub fn from_reader(r: &Reader<'_>) -> Result<Control> {
        let pins = match r.sub("pins", false)? {
            None => None,
            Some(p) => Some(Pins { indices: p.u32s("indices", true)?.unwrap(), targets: p.f32s("targets", true)?.unwrap() }),
        };
        Ok(Control {
            cloth: r.str("cloth", true)?.unwrap().to_string(),
            token: r.str("token", true)?.unwrap().to_string(),
            pins,
            colliders: read_colliders(r)?,
            gravity: r.vec3("gravity", false)?,
            wind: r.vec3("wind", false)?,
            material: read_material(r)?,
            features: read_strings(r, "features")?,
            features_add: read_strings(r, "features_add")?,
            features_remove: read_strings(r, "features_remove")?,
            iterations: u32v(r, "iterations", false)?,
            substeps: u32v(r, "substeps", false)?,
            chebyshev_rho: r.f64("chebyshev_rho", false)?,
            state: read_state(r)?,
            quality: r.str("quality", false)?.map(str::to_string),
            reset: r.bool("reset", false)?.unwrap_or(false),
            mesh_collider: MeshCollider::from_reader(r, "mesh_collider")?,
        })
    }

    /// Decode a control message; returns the control and its rid.
    pub fn decode(data: &[u8]) -> Result<(Control, u64)> {
        let m = unpack_message(data)?;
        let r = Reader::new(&m, "");
        Ok((Control::from_reader(&r)?, r.u64("rid", false)?.unwrap_or(0)))
    }
}

impl ControlBatch {
    /// The batch control (1.4: see also [`ControlBatch::encode_with_moves`]).
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with_moves(None)
    }

    pub fn decode(data: &[u8]) -> Result<ControlBatch> {
        let m = unpack_message(data)?;
        let r = Reader::new(&m, "");
        let mut items = Vec::new();
        for (i, it) in r.array("items", true)?.unwrap().iter().enumerate() {
            let Value::Map(im) = it else { return Err(invalid(format!("items[{i}] is not a map"))) };
            items.push(Control::from_reader(&Reader::new(im, &format!("items[{i}]")))?);
        }
        Ok(ControlBatch { rid: r.u64("rid", false)?.unwrap_or(0), client: r.str("client", true)?.unwrap().to_string(), items })
    }
}

/// `{v, rid, cloth, token}`.
pub fn encode_remove(cloth: &str, token: &str, rid: u64) -> Vec<u8> {
    let mut m = header(rid);
    m.push((s("cloth"), s(cloth)));
    m.push((s("token"), s(token)));
    pack(&Value::Map(m))
}

/// `{v, rid}`.
pub fn encode_info(rid: u64) -> Vec<u8> {
    pack(&Value::Map(header(rid)))
}

