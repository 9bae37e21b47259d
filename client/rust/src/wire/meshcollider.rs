//! Protocol 1.8's mesh collider (PROTOCOL.md 5.4): a cloth's or a scene's triangle mesh, sent
//! once and then moved by a pose per tick. One type for the four changes of the `mesh_collider`
//! map (a new mesh, a re-pose, a rigid move, a removal), its msgpack map both ways (the
//! reference's exact bytes) and the checks the server's decoder makes, with its codes and the
//! offending triangle or value in the message.
use super::error::{invalid, Error, ErrorCode, Result};
use super::reader::{bin_f32, bin_u32, number, s, vec3, Map, Reader, Value};

/// The most vertices and triangles of a mesh collider (fixed, PROTOCOL.md 13).
pub const MESH_MAX_VERTICES: usize = 65_536;
pub const MESH_MAX_TRIANGLES: usize = 65_536;
/// A triangle of a smaller area (m²) is degenerate (repeated indices included).
pub const MESH_MIN_AREA: f64 = 1e-10;
/// The keys of a `mesh_collider` map; any other is `invalid_value`.
pub const MESH_KEYS: [&str; 5] = ["vertices", "triangles", "position", "rotation", "remove"];
/// The identity rotation, a quaternion `[w, x, y, z]`.
pub const IDENTITY: [f64; 4] = [1.0, 0.0, 0.0, 0.0];

const COORD: f64 = 1e5;
/// The bound of a rotation component (the server normalises the quaternion).
const ROTATION_BOUND: f64 = 1e3;

/// A change of a mesh collider, by the fields given:
///
/// - `vertices` and `triangles`: a new mesh (xyz interleaved, f32, in its own frame; three
///   indices per triangle, counter-clockwise seen from outside) at the pose ([`MeshCollider::mesh`]);
/// - `vertices` alone: a re-pose of the current mesh, the same vertex count ([`MeshCollider::repose`]);
/// - neither: a rigid move of the current mesh to the pose, the per-tick change ([`MeshCollider::pose`]);
/// - `remove`: the mesh dropped ([`MeshCollider::removal`]), nothing else.
///
/// The pose: `position` (metres) and `rotation` (`[w, x, y, z]`, normalised by the server),
/// mesh frame to world.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshCollider {
    pub vertices: Option<Vec<f32>>,
    pub triangles: Option<Vec<u32>>,
    pub position: [f64; 3],
    pub rotation: [f64; 4],
    pub remove: bool,
}

impl MeshCollider {
    /// A new mesh at the identity pose (place it with [`MeshCollider::at`]).
    pub fn mesh(vertices: Vec<f32>, triangles: Vec<u32>) -> MeshCollider {
        MeshCollider { vertices: Some(vertices), triangles: Some(triangles), position: [0.0; 3], rotation: IDENTITY, remove: false }
    }

    /// New vertices of the current mesh (a skinned body's next pose), at the identity pose.
    pub fn repose(vertices: Vec<f32>) -> MeshCollider {
        MeshCollider { vertices: Some(vertices), triangles: None, position: [0.0; 3], rotation: IDENTITY, remove: false }
    }

    /// A rigid move of the current mesh (the cheap per-tick change: about 80 bytes).
    pub fn pose(position: [f64; 3], rotation: [f64; 4]) -> MeshCollider {
        MeshCollider { vertices: None, triangles: None, position, rotation, remove: false }
    }

    /// The mesh removed, with its server memory.
    pub fn removal() -> MeshCollider {
        MeshCollider { vertices: None, triangles: None, position: [0.0; 3], rotation: IDENTITY, remove: true }
    }

    /// The same change at another pose.
    pub fn at(mut self, position: [f64; 3], rotation: [f64; 4]) -> MeshCollider {
        self.position = position;
        self.rotation = rotation;
        self
    }

    /// Whether this is a new mesh (vertices and triangles).
    pub fn is_new_mesh(&self) -> bool {
        !self.remove && self.vertices.is_some() && self.triangles.is_some()
    }

    /// `last` (the whole mesh last set, or a removal) after this change: a re-pose or a move of
    /// it is that mesh at the new pose (what a failover sends again); a new mesh or a removal
    /// replaces it.
    pub fn applied_to(&self, last: Option<&MeshCollider>) -> MeshCollider {
        match last {
            Some(l) if !self.remove && self.triangles.is_none() && l.is_new_mesh() => MeshCollider {
                vertices: self.vertices.clone().or_else(|| l.vertices.clone()),
                triangles: l.triangles.clone(),
                position: self.position,
                rotation: self.rotation,
                remove: false,
            },
            _ => self.clone(),
        }
    }

    /// The `mesh_collider` map: `{remove: true}` alone, or the vertices and triangles given and
    /// the pose (always written, as the reference does).
    pub fn to_value(&self) -> Value {
        if self.remove {
            return Value::Map(vec![(s("remove"), Value::Boolean(true))]);
        }
        let mut m = Map::new();
        if let Some(v) = &self.vertices {
            m.push((s("vertices"), bin_f32(v)));
        }
        if let Some(t) = &self.triangles {
            m.push((s("triangles"), bin_u32(t)));
        }
        m.push((s("position"), vec3(self.position)));
        m.push((s("rotation"), Value::Array(self.rotation.iter().map(|x| Value::F64(*x)).collect())));
        Value::Map(m)
    }

    /// Read the map at `key` of `r` (types and shape: unknown keys, `remove` with another key,
    /// `triangles` without `vertices`, a rotation not of 4 numbers); [`MeshCollider::validate`]
    /// checks the values.
    pub fn from_reader(r: &Reader<'_>, key: &str) -> Result<Option<MeshCollider>> {
        let Some(mr) = r.sub(key, false)? else { return Ok(None) };
        let name = r.name(key);
        if let Some((k, _)) = mr.m.iter().find(|(k, _)| !k.as_str().is_some_and(|k| MESH_KEYS.contains(&k))) {
            return Err(invalid(format!("'{name}' has an unknown key {k}; known: {MESH_KEYS:?}")));
        }
        if mr.bool("remove", false)? == Some(true) {
            if mr.m.len() > 1 {
                return Err(invalid(format!("'{name}' with 'remove' must have no other key")));
            }
            return Ok(Some(MeshCollider::removal()));
        }
        let vertices = mr.f32s("vertices", false)?;
        let triangles = mr.u32s("triangles", false)?;
        if triangles.is_some() && vertices.is_none() {
            return Err(Error::new(ErrorCode::MissingField, format!("'{}' is required with '{}'", mr.name("vertices"), mr.name("triangles"))));
        }
        let rotation = match mr.get("rotation") {
            None => IDENTITY,
            Some(Value::Array(a)) if a.len() == 4 => {
                let mut q = [0.0; 4];
                for (i, x) in a.iter().enumerate() {
                    q[i] = number(x).ok_or_else(|| {
                        Error::new(ErrorCode::InvalidType, format!("'{}[{i}]' must be a number", mr.name("rotation")))
                    })?;
                }
                q
            }
            Some(_) => {
                return Err(Error::new(ErrorCode::InvalidType, format!("'{}' must be 4 numbers (w, x, y, z)", mr.name("rotation"))));
            }
        };
        Ok(Some(MeshCollider { vertices, triangles, position: mr.vec3("position", false)?.unwrap_or([0.0; 3]), rotation, remove: false }))
    }

    /// The server decoder's checks, named `name` in messages: a submission's is a new mesh;
    /// `remove` stands alone; a mesh of 1 to 65 536 finite vertices within ±1e5 m and 1 to
    /// 65 536 triangles whose indices are in range and whose areas are at least
    /// [`MESH_MIN_AREA`] (the first bad triangle named); a finite position within ±1e5 m and a
    /// non-zero rotation of components within ±1e3.
    pub fn validate(&self, name: &str, submit: bool) -> Result<()> {
        if self.remove {
            if self.vertices.is_some() || self.triangles.is_some() {
                return Err(invalid(format!("'{name}' with 'remove' must have no other key")));
            }
            if submit {
                return Err(invalid(format!("'{name}' of a submission cannot remove a mesh")));
            }
            return Ok(());
        }
        if submit && !self.is_new_mesh() {
            return Err(Error::new(ErrorCode::MissingField, format!("'{name}' of a submission is a new mesh: vertices and triangles")));
        }
        if self.triangles.is_some() && self.vertices.is_none() {
            return Err(Error::new(ErrorCode::MissingField, format!("'{name}.vertices' is required with '{name}.triangles'")));
        }
        if let Some(v) = &self.vertices {
            mesh_problem(v, self.triangles.as_deref()).map_err(|e| Error::new(e.code, format!("'{name}': {}", e.message)))?;
            if let Some(x) = v.iter().find(|x| x.abs() as f64 > COORD) {
                return Err(invalid(format!("'{name}.vertices' holds {x}: coordinates must be within ±1e5")));
            }
        }
        for (i, x) in self.position.iter().enumerate() {
            if !x.is_finite() || x.abs() > COORD {
                return Err(invalid(format!("'{name}.position[{i}]' = {x} must be finite within ±1e5")));
            }
        }
        for (i, x) in self.rotation.iter().enumerate() {
            if !x.is_finite() || x.abs() > ROTATION_BOUND {
                return Err(invalid(format!("'{name}.rotation[{i}]' = {x} must be finite within ±1e3")));
            }
        }
        if !(self.rotation.iter().map(|x| x * x).sum::<f64>() > 1e-12) {
            return Err(invalid(format!("'{name}.rotation' must be a non-zero quaternion (w, x, y, z)")));
        }
        Ok(())
    }
}

/// What is wrong with a mesh collider's vertices (xyz interleaved) and triangles (`None`: the
/// vertices alone, a re-pose), as the protocol's checks say (`vocabulary.mesh_problem` of the
/// reference): `too_large` past the caps, else `invalid_value` for a count not of threes, no
/// vertex or triangle, a non-finite vertex, an index out of range or a degenerate triangle (area,
/// in float64, under [`MESH_MIN_AREA`]); the message names the first bad triangle.
pub fn mesh_problem(vertices: &[f32], triangles: Option<&[u32]>) -> Result<()> {
    if vertices.len() % 3 != 0 || vertices.is_empty() {
        return Err(invalid(format!("mesh vertices must be (n, 3) with n >= 1, got {} floats", vertices.len())));
    }
    let n = vertices.len() / 3;
    if n > MESH_MAX_VERTICES {
        return Err(Error::new(ErrorCode::TooLarge, format!("mesh has {n} vertices: at most {MESH_MAX_VERTICES}")));
    }
    if vertices.iter().any(|x| !x.is_finite()) {
        return Err(invalid("mesh vertices must be finite"));
    }
    let Some(t) = triangles else { return Ok(()) };
    if t.len() % 3 != 0 || t.is_empty() {
        return Err(invalid(format!("mesh triangles must be (m, 3) with m >= 1, got {} indices", t.len())));
    }
    let m = t.len() / 3;
    if m > MESH_MAX_TRIANGLES {
        return Err(Error::new(ErrorCode::TooLarge, format!("mesh has {m} triangles: at most {MESH_MAX_TRIANGLES}")));
    }
    if let Some(bad) = t.chunks_exact(3).position(|tri| tri.iter().any(|i| *i as usize >= n)) {
        return Err(invalid(format!("mesh triangle {bad} has an index out of range (vertices: {n})")));
    }
    let p = |i: u32| -> [f64; 3] {
        let i = 3 * i as usize;
        [vertices[i] as f64, vertices[i + 1] as f64, vertices[i + 2] as f64]
    };
    let area = |tri: &[u32]| -> f64 {
        let (a, b, c) = (p(tri[0]), p(tri[1]), p(tri[2]));
        let (u, v) = ([b[0] - a[0], b[1] - a[1], b[2] - a[2]], [c[0] - a[0], c[1] - a[1], c[2] - a[2]]);
        let x = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
        0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
    };
    let mut bad = t.chunks_exact(3).enumerate().filter(|(_, tri)| !(area(tri) >= MESH_MIN_AREA));
    if let Some((first, tri)) = bad.next() {
        let count = 1 + bad.count();
        return Err(invalid(format!(
            "mesh triangle {first} is degenerate (area {:.3e} m^2 < {MESH_MIN_AREA:e}); {count} such",
            area(tri)
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetra() -> MeshCollider {
        let v = vec![0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.5];
        MeshCollider::mesh(v, vec![0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3])
    }

    #[test]
    fn checks_name_the_offending_triangle_or_value() {
        assert!(tetra().validate("m", true).is_ok());
        let mut m = tetra();
        m.triangles.as_mut().unwrap()[7] = 9;
        let e = m.validate("m", false).unwrap_err();
        assert_eq!(e.code, ErrorCode::InvalidValue);
        assert!(e.message.contains("triangle 2"), "{}", e.message);
        let mut m = tetra();
        m.triangles.as_mut().unwrap()[10] = 1; // triangle 3: 1, 1, 3
        let e = m.validate("m", false).unwrap_err();
        assert!(e.message.contains("triangle 3 is degenerate"), "{}", e.message);
        let mut m = tetra();
        m.vertices.as_mut().unwrap()[4] = f32::NAN;
        assert_eq!(m.validate("m", false).unwrap_err().code, ErrorCode::InvalidValue);
        assert_eq!(MeshCollider::pose([0.0; 3], [0.0; 4]).validate("m", false).unwrap_err().code, ErrorCode::InvalidValue);
        assert_eq!(MeshCollider::pose([0.0; 3], IDENTITY).validate("m", true).unwrap_err().code, ErrorCode::MissingField);
        assert_eq!(MeshCollider::removal().validate("m", true).unwrap_err().code, ErrorCode::InvalidValue);
        let big = MeshCollider::repose(vec![0.0; 3 * (MESH_MAX_VERTICES + 1)]);
        assert_eq!(big.validate("m", false).unwrap_err().code, ErrorCode::TooLarge);
    }

    #[test]
    fn a_move_or_repose_of_the_last_mesh_is_that_mesh_at_its_new_pose() {
        let last = tetra();
        let moved = MeshCollider::pose([1.0, 2.0, 3.0], IDENTITY).applied_to(Some(&last));
        assert_eq!((moved.triangles.as_ref(), moved.position), (last.triangles.as_ref(), [1.0, 2.0, 3.0]));
        let reposed = MeshCollider::repose(vec![1.0; 12]).applied_to(Some(&moved));
        assert_eq!((reposed.vertices.unwrap()[0], reposed.triangles, reposed.position), (1.0, last.triangles.clone(), [0.0; 3]));
        assert!(MeshCollider::removal().applied_to(Some(&last)).remove);
    }
}
