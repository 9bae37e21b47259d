//! msgpack plumbing: packing a [`Value`] the way the reference encoder does (keys in the given
//! order, floats as float64, integers in their smallest form), unpacking a message with the
//! envelope rules of PROTOCOL.md section 3, and a typed field reader whose errors carry the
//! protocol's codes and the field path.
use super::error::{malformed, Error, ErrorCode, Result};
use super::{MAX_ARRAY_LENGTH, MAX_MAP_KEYS, MAX_NESTING, MAX_STRING_BYTES, MAX_VALUES, PROTOCOL_MAJOR, PROTOCOL_MINOR};
pub use rmpv::Value;

pub type Map = Vec<(Value, Value)>;

/// A msgpack string value.
pub fn s(x: &str) -> Value {
    Value::String(x.into())
}
/// The `v` and `rid` header every message starts with.
pub fn header(rid: u64) -> Map {
    vec![
        (s("v"), Value::Array(vec![Value::from(PROTOCOL_MAJOR), Value::from(PROTOCOL_MINOR)])),
        (s("rid"), Value::from(rid)),
    ]
}
pub fn vec3(v: [f64; 3]) -> Value {
    Value::Array(v.iter().map(|x| Value::F64(*x)).collect())
}
pub fn bin_u32(v: &[u32]) -> Value {
    Value::Binary(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}
pub fn bin_f32(v: &[f32]) -> Value {
    Value::Binary(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}

/// Serialize a value (a map for every message).
pub fn pack(v: &Value) -> Vec<u8> {
    let mut out = Vec::with_capacity(128);
    rmpv::encode::write_value(&mut out, v).expect("writing to a Vec cannot fail");
    out
}

/// Unpack one message: a msgpack map with string keys and nothing after it, within the 1.2
/// decoding caps (see [`scan`]), whose `v` is `[1, minor]`. Errors: `malformed`, `too_large`
/// (more than `MAX_VALUES` values), `missing_field` (no `v`), `invalid_type`,
/// `unsupported_version` (another major).
pub fn unpack_message(data: &[u8]) -> Result<Map> {
    if data.is_empty() {
        return Err(malformed("empty message"));
    }
    scan(data)?;
    let mut rest = data;
    let v = rmpv::decode::read_value(&mut rest).map_err(|e| malformed(format!("not msgpack: {e}")))?;
    if !rest.is_empty() {
        return Err(malformed(format!("{} trailing bytes after the message", rest.len())));
    }
    let Value::Map(m) = v else {
        return Err(malformed(format!("a message must be a map, got {}", type_name(&v))));
    };
    check_keys(&m)?;
    let rid = m.iter().find(|(k, _)| k.as_str() == Some("rid")).and_then(|(_, v)| v.as_u64()).unwrap_or(0);
    let r = Reader::new(&m, "");
    let ver = r.req("v").map_err(|e| e.with_rid(rid))?;
    let pair = match ver {
        Value::Array(a) if a.len() == 2 => (a[0].as_u64(), a[1].as_u64()),
        _ => (None, None),
    };
    match pair {
        (Some(major), Some(minor)) if major <= 255 && minor <= 255 => {
            if major != PROTOCOL_MAJOR as u64 {
                return Err(Error::new(
                    ErrorCode::UnsupportedVersion,
                    format!("version {major}.{minor} is not supported; this side speaks {PROTOCOL_MAJOR}.{PROTOCOL_MINOR}"),
                )
                .with_rid(rid));
            }
        }
        _ => return Err(Error::new(ErrorCode::InvalidType, "'v' must be [major, minor]").with_rid(rid)),
    }
    Ok(m)
}

/// One open container while scanning: items still to read, and for a map whether the next one
/// is a key.
struct Frame {
    left: u64,
    map: bool,
    key_next: bool,
}

/// Check one msgpack value in `data` against the protocol's decoding caps (PROTOCOL.md sections
/// 3, 8 and 13) before anything is built from it, without recursion and in one pass over the
/// bytes: maps and arrays nested deeper than `MAX_NESTING` (the outer map is level 1), a map of
/// more than `MAX_MAP_KEYS` keys, an array of more than `MAX_ARRAY_LENGTH` elements, a string
/// of more than `MAX_STRING_BYTES` bytes or not UTF-8, a non-string map key, an extension type,
/// the reserved byte 0xc1, a value running past the end or bytes after the value are
/// `malformed`; more than `MAX_VALUES` values (map keys count, containers count) is `too_large`.
/// Hostile lengths never allocate: every length is checked against the bytes left.
pub fn scan(data: &[u8]) -> Result<()> {
    let mut pos = 0usize;
    let mut values = 0usize;
    let mut stack: Vec<Frame> = Vec::new();
    let short = |what: &str| malformed(format!("truncated msgpack: {what} runs past the end of the {} bytes", data.len()));
    loop {
        let depth = stack.len() + 1;
        let is_key = stack.last().is_some_and(|f| f.map && f.key_next);
        let b = *data.get(pos).ok_or_else(|| short("a value"))?;
        pos += 1;
        values += 1;
        if values > MAX_VALUES {
            return Err(Error::new(ErrorCode::TooLarge, format!("message holds more than {MAX_VALUES} values")));
        }
        let take = |pos: &mut usize, n: usize| -> Result<u64> {
            let end = pos.checked_add(n).filter(|e| *e <= data.len()).ok_or_else(|| short("a length"))?;
            let v = data[*pos..end].iter().fold(0u64, |acc, x| (acc << 8) | *x as u64);
            *pos = end;
            Ok(v)
        };
        let is_str = matches!(b, 0xa0..=0xbf | 0xd9..=0xdb);
        if is_key && !is_str {
            return Err(malformed(format!("a map key at byte {} is not a string", pos - 1)));
        }
        // (container: map?, count) or a scalar already skipped
        let mut container: Option<(bool, u64)> = None;
        match b {
            0x00..=0x7f | 0xe0..=0xff | 0xc0 | 0xc2 | 0xc3 => {}
            0x80..=0x8f => container = Some((true, (b & 0x0f) as u64)),
            0x90..=0x9f => container = Some((false, (b & 0x0f) as u64)),
            0xde => container = Some((true, take(&mut pos, 2)?)),
            0xdf => container = Some((true, take(&mut pos, 4)?)),
            0xdc => container = Some((false, take(&mut pos, 2)?)),
            0xdd => container = Some((false, take(&mut pos, 4)?)),
            0xa0..=0xbf | 0xd9..=0xdb => {
                let n = match b {
                    0xd9 => take(&mut pos, 1)?,
                    0xda => take(&mut pos, 2)?,
                    0xdb => take(&mut pos, 4)?,
                    _ => (b & 0x1f) as u64,
                } as usize;
                if n > MAX_STRING_BYTES {
                    return Err(malformed(format!("a string of {n} bytes exceeds the cap of {MAX_STRING_BYTES}")));
                }
                let end = pos.checked_add(n).filter(|e| *e <= data.len()).ok_or_else(|| short("a string"))?;
                if std::str::from_utf8(&data[pos..end]).is_err() {
                    return Err(malformed(format!("a string at byte {pos} is not valid UTF-8")));
                }
                pos = end;
            }
            0xc4..=0xc6 => {
                let n = take(&mut pos, 1 << (b - 0xc4))? as usize;
                pos = pos.checked_add(n).filter(|e| *e <= data.len()).ok_or_else(|| short("a bin"))?;
            }
            0xca..=0xd3 => {
                let n = match b {
                    0xca => 4,
                    0xcb => 8,
                    0xcc..=0xcf => 1 << (b - 0xcc),
                    _ => 1 << (b - 0xd0),
                };
                take(&mut pos, n)?;
            }
            0xc7..=0xc9 | 0xd4..=0xd8 => return Err(malformed("msgpack extension types are not part of the protocol")),
            0xc1 => return Err(malformed("byte 0xc1 is not msgpack")),
        }
        if let Some(f) = stack.last_mut() {
            f.left -= 1;
            f.key_next = !f.key_next;
        }
        if let Some((map, n)) = container {
            if depth > MAX_NESTING {
                return Err(malformed(format!("maps and arrays nested deeper than {MAX_NESTING} levels")));
            }
            if map && n > MAX_MAP_KEYS as u64 {
                return Err(malformed(format!("a map of {n} keys exceeds the cap of {MAX_MAP_KEYS}")));
            }
            if !map && n > MAX_ARRAY_LENGTH as u64 {
                return Err(malformed(format!("an array of {n} elements exceeds the cap of {MAX_ARRAY_LENGTH}")));
            }
            if n > 0 {
                stack.push(Frame { left: if map { 2 * n } else { n }, map, key_next: true });
            }
        }
        while stack.last().is_some_and(|f| f.left == 0) {
            stack.pop();
        }
        if stack.is_empty() {
            break;
        }
    }
    if pos != data.len() {
        return Err(malformed(format!("{} trailing bytes after the message", data.len() - pos)));
    }
    Ok(())
}

fn check_keys(m: &Map) -> Result<()> {
    for (k, v) in m {
        if k.as_str().is_none() {
            return Err(malformed("map keys must be UTF-8 strings"));
        }
        match v {
            Value::Map(inner) => check_keys(inner)?,
            Value::Array(a) => {
                for x in a {
                    if let Value::Map(inner) = x {
                        check_keys(inner)?;
                    }
                }
            }
            _ => {}
        }
    }
    Ok(())
}

pub fn type_name(v: &Value) -> &'static str {
    match v {
        Value::Nil => "nil",
        Value::Boolean(_) => "bool",
        Value::Integer(_) => "int",
        Value::F32(_) | Value::F64(_) => "float",
        Value::String(_) => "string",
        Value::Binary(_) => "bin",
        Value::Array(_) => "array",
        Value::Map(_) => "map",
        Value::Ext(..) => "ext",
    }
}

/// Typed access to a map's fields; absent and `nil` are the same. `path` prefixes field names
/// in messages (`grid.cols`).
pub struct Reader<'a> {
    pub m: &'a [(Value, Value)],
    pub path: String,
}

impl<'a> Reader<'a> {
    pub fn new(m: &'a [(Value, Value)], path: &str) -> Reader<'a> {
        Reader { m, path: path.to_string() }
    }
    pub fn name(&self, key: &str) -> String {
        if self.path.is_empty() { key.to_string() } else { format!("{}.{key}", self.path) }
    }
    fn ty(&self, key: &str, want: &str, got: &Value) -> Error {
        Error::new(ErrorCode::InvalidType, format!("'{}' must be {want}, got {}", self.name(key), type_name(got)))
    }
    pub fn get(&self, key: &str) -> Option<&'a Value> {
        self.m.iter().find(|(k, _)| k.as_str() == Some(key)).map(|(_, v)| v).filter(|v| !v.is_nil())
    }
    pub fn req(&self, key: &str) -> Result<&'a Value> {
        self.get(key)
            .ok_or_else(|| Error::new(ErrorCode::MissingField, format!("'{}' is required", self.name(key))))
    }
    fn opt(&self, key: &str, required: bool) -> Result<Option<&'a Value>> {
        if required { self.req(key).map(Some) } else { Ok(self.get(key)) }
    }
    pub fn u64(&self, key: &str, required: bool) -> Result<Option<u64>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(v @ Value::Integer(i)) => {
                i.as_u64().map(Some).ok_or_else(|| Error::new(ErrorCode::InvalidValue, format!("'{}' must be >= 0, got {v}", self.name(key))))
            }
            Some(v) => Err(self.ty(key, "an int", v)),
        }
    }
    pub fn f64(&self, key: &str, required: bool) -> Result<Option<f64>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(v) => number(v).map(Some).ok_or_else(|| self.ty(key, "a number", v)),
        }
    }
    pub fn bool(&self, key: &str, required: bool) -> Result<Option<bool>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(Value::Boolean(b)) => Ok(Some(*b)),
            Some(v) => Err(self.ty(key, "a bool", v)),
        }
    }
    pub fn str(&self, key: &str, required: bool) -> Result<Option<&'a str>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(Value::String(x)) => x.as_str().map(Some).ok_or_else(|| malformed(format!("'{}' is not UTF-8", self.name(key)))),
            Some(v) => Err(self.ty(key, "a string", v)),
        }
    }
    pub fn vec3(&self, key: &str, required: bool) -> Result<Option<[f64; 3]>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(Value::Array(a)) if a.len() == 3 => {
                let mut out = [0.0; 3];
                for (i, x) in a.iter().enumerate() {
                    out[i] = number(x).ok_or_else(|| self.ty(&format!("{key}[{i}]"), "a number", x))?;
                }
                Ok(Some(out))
            }
            Some(v) => Err(self.ty(key, "an array of 3 numbers", v)),
        }
    }
    pub fn bin(&self, key: &str, width: usize, required: bool) -> Result<Option<&'a [u8]>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(Value::Binary(b)) if b.len() % width == 0 => Ok(Some(b)),
            Some(Value::Binary(b)) => Err(Error::new(
                ErrorCode::InvalidValue,
                format!("'{}' has {} bytes, not a multiple of {width}", self.name(key), b.len()),
            )),
            Some(v) => Err(self.ty(key, "bin", v)),
        }
    }
    pub fn u32s(&self, key: &str, required: bool) -> Result<Option<Vec<u32>>> {
        Ok(self.bin(key, 4, required)?.map(|b| b.chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect()))
    }
    pub fn f32s(&self, key: &str, required: bool) -> Result<Option<Vec<f32>>> {
        Ok(self.bin(key, 4, required)?.map(|b| b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()))
    }
    pub fn array(&self, key: &str, required: bool) -> Result<Option<&'a [Value]>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(Value::Array(a)) => Ok(Some(a)),
            Some(v) => Err(self.ty(key, "an array", v)),
        }
    }
    pub fn sub(&self, key: &str, required: bool) -> Result<Option<Reader<'a>>> {
        match self.opt(key, required)? {
            None => Ok(None),
            Some(Value::Map(m)) => Ok(Some(Reader::new(m, &self.name(key)))),
            Some(v) => Err(self.ty(key, "a map", v)),
        }
    }
}

/// A msgpack int or float as f64 (not a bool).
pub fn number(v: &Value) -> Option<f64> {
    match v {
        Value::Integer(i) => i.as_f64(),
        Value::F32(x) => Some(*x as f64),
        Value::F64(x) => Some(*x),
        _ => None,
    }
}
