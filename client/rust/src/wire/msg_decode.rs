//! Decoders of the request messages' typed fields (materials, colliders, state options...),
//! used by `Submit::decode`, `Control::from_reader` and `ControlBatch::decode`.
use super::error::{invalid, Error, ErrorCode, Result};
use super::msg::{Collider, Encoding, Material, StateOptions};
use super::reader::{Reader, Value};

pub(crate) fn u32v(r: &Reader<'_>, key: &str, required: bool) -> Result<Option<u32>> {
    match r.u64(key, required)? {
        None => Ok(None),
        Some(v) => u32::try_from(v).map(Some).map_err(|_| Error::new(ErrorCode::TooLarge, format!("'{}' = {v} is too large", r.name(key)))),
    }
}

pub(crate) fn read_strings(r: &Reader<'_>, key: &str) -> Result<Option<Vec<String>>> {
    let Some(a) = r.array(key, false)? else { return Ok(None) };
    a.iter()
        .enumerate()
        .map(|(i, v)| {
            v.as_str().map(str::to_string).ok_or_else(|| {
                Error::new(ErrorCode::InvalidType, format!("'{}[{i}]' must be a string", r.name(key)))
            })
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
}

pub(crate) fn read_material(r: &Reader<'_>) -> Result<Material> {
    let Some(m) = r.sub("material", false)? else { return Ok(Material::default()) };
    Ok(Material {
        mass: m.f64("mass", false)?,
        stiffness: m.vec3("stiffness", false)?,
        compliance: m.vec3("compliance", false)?,
        damping: m.f64("damping", false)?,
        friction: m.f64("friction", false)?,
        drag: m.f64("drag", false)?,
        lift: m.f64("lift", false)?,
        air_density: m.f64("air_density", false)?,
        tether_limit: m.f64("tether_limit", false)?,
        thickness: m.f64("thickness", false)?,
        contact_stiffness: m.f64("contact_stiffness", false)?,
    })
}

pub(crate) fn read_colliders(r: &Reader<'_>) -> Result<Option<Vec<Collider>>> {
    let Some(a) = r.array("colliders", false)? else { return Ok(None) };
    let mut out = Vec::with_capacity(a.len());
    for (i, v) in a.iter().enumerate() {
        let Value::Map(cm) = v else { return Err(invalid(format!("colliders[{i}] is not a map"))) };
        let c = Reader::new(cm, &format!("colliders[{i}]"));
        out.push(match c.str("type", true)?.unwrap() {
            "sphere" => Collider::Sphere { center: c.vec3("center", true)?.unwrap(), radius: c.f64("radius", true)?.unwrap() },
            "capsule" => Collider::Capsule {
                p0: c.vec3("p0", true)?.unwrap(),
                p1: c.vec3("p1", true)?.unwrap(),
                radius: c.f64("radius", true)?.unwrap(),
            },
            "plane" => Collider::Plane { normal: c.vec3("normal", true)?.unwrap(), offset: c.f64("offset", true)?.unwrap() },
            t => return Err(invalid(format!("unknown collider type {t:?}"))),
        });
    }
    Ok(Some(out))
}

pub(crate) fn read_state(r: &Reader<'_>) -> Result<Option<StateOptions>> {
    let Some(st) = r.sub("state", false)? else { return Ok(None) };
    let encoding = match st.str("encoding", false)? {
        None => None,
        Some(e) => Some(Encoding::from_name(e).ok_or_else(|| invalid(format!("unknown encoding {e:?}")))?),
    };
    Ok(Some(StateOptions {
        normals: st.bool("normals", false)?,
        encoding,
        bundle: st.bool("bundle", false)?,
        step: st.f64("step", false)?,
    }))
}
