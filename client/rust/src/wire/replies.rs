//! Replies (PROTOCOL.md sections 4-8): success maps of submit, control (1.2: with the cloth's
//! resulting `features`), batch control and remove, and error replies, decoded into types (and
//! encoded, for the test vectors).
use super::error::{malformed, Error, ErrorCode, Result};
use super::keys::{valid_id, valid_token};
use super::reader::{header, pack, s, type_name, unpack_message, Map, Reader, Value};

/// Unpack a reply: the map when `ok` is true; the server's [`Error`] when `ok` is false.
pub fn decode_reply(data: &[u8]) -> Result<Map> {
    let m = unpack_message(data)?;
    let r = Reader::new(&m, "");
    let rid = r.u64("rid", false).ok().flatten().unwrap_or(0);
    match r.get("ok") {
        Some(Value::Boolean(true)) => Ok(m),
        Some(Value::Boolean(false)) => Err(ErrorReply::from_map(&m)?.into_error()),
        other => Err(malformed(format!("reply must have boolean 'ok', got {}", other.map_or("nothing", type_name))).with_rid(rid)),
    }
}

/// `{v, rid, ok: false, error: {code, message}}`.
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorReply {
    pub rid: u64,
    /// The wire code as sent (a later minor version may send codes this crate does not know).
    pub code: String,
    pub message: String,
}

impl ErrorReply {
    pub fn from_map(m: &Map) -> Result<ErrorReply> {
        let r = Reader::new(m, "");
        let e = r.sub("error", true)?.unwrap();
        Ok(ErrorReply {
            rid: r.u64("rid", false)?.unwrap_or(0),
            code: e.str("code", true)?.unwrap().to_string(),
            message: e.str("message", false)?.unwrap_or("").to_string(),
        })
    }
    pub fn into_error(self) -> Error {
        let code = ErrorCode::from_name(&self.code);
        let message = if code == ErrorCode::Unknown { format!("{}: {}", self.code, self.message) } else { self.message };
        Error::new(code, message).with_rid(self.rid)
    }
    pub fn encode(&self) -> Vec<u8> {
        let mut m = header(self.rid);
        m.push((s("ok"), Value::Boolean(false)));
        m.push((s("error"), Value::Map(vec![(s("code"), s(&self.code)), (s("message"), s(&self.message))])));
        pack(&Value::Map(m))
    }
}

/// A submission accepted.
#[derive(Debug, Clone, PartialEq)]
pub struct SubmitReply {
    pub rid: u64,
    pub cloth: String,
    pub token: String,
    pub key: String,
    pub vertices: u32,
    pub tick: u64,
    /// 1.1: present only for a bundled cloth.
    pub bundle_key: Option<String>,
}

impl SubmitReply {
    pub fn from_map(m: &Map) -> Result<SubmitReply> {
        let r = Reader::new(m, "");
        let cloth = r.str("cloth", true)?.unwrap();
        let token = r.str("token", true)?.unwrap();
        if !valid_id(cloth) || !valid_token(token) {
            return Err(malformed("submit reply with an invalid cloth id or token"));
        }
        let vertices = r.u64("vertices", true)?.unwrap();
        Ok(SubmitReply {
            rid: r.u64("rid", false)?.unwrap_or(0),
            cloth: cloth.to_string(),
            token: token.to_string(),
            key: r.str("key", true)?.unwrap().to_string(),
            vertices: u32::try_from(vertices).map_err(|_| malformed(format!("submit reply: {vertices} vertices")))?,
            tick: r.u64("tick", true)?.unwrap(),
            bundle_key: r.str("bundle_key", false)?.map(str::to_string),
        })
    }
    pub fn encode(&self) -> Vec<u8> {
        let mut m = ok_header(self.rid);
        m.push((s("cloth"), s(&self.cloth)));
        m.push((s("token"), s(&self.token)));
        m.push((s("key"), s(&self.key)));
        m.push((s("vertices"), Value::from(self.vertices)));
        m.push((s("tick"), Value::from(self.tick)));
        if let Some(b) = &self.bundle_key {
            m.push((s("bundle_key"), s(b)));
        }
        pack(&Value::Map(m))
    }
}

pub(crate) fn ok_header(rid: u64) -> Map {
    let mut m = header(rid);
    m.push((s("ok"), Value::Boolean(true)));
    m
}

/// The `tick` of a control or remove reply.
pub fn tick_of(m: &Map) -> Result<u64> {
    Ok(Reader::new(m, "").u64("tick", true)?.unwrap())
}

/// `{v, rid, ok: true, tick}`: the reply of remove (and of control from a 1.0 / 1.1 server).
pub fn encode_tick_reply(tick: u64, rid: u64) -> Vec<u8> {
    let mut m = ok_header(rid);
    m.push((s("tick"), Value::from(tick)));
    pack(&Value::Map(m))
}

/// An applied control (a control reply, or an applied item of a batch reply): the first tick
/// whose state reflects it and (1.2) the cloth's feature set after it, in the protocol's
/// order (`None` from a 1.0 or 1.1 server, which does not report it).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Applied {
    pub tick: u64,
    pub features: Option<Vec<String>>,
}

impl Applied {
    /// Read `tick` and the optional `features` of a control reply or a batch result map.
    pub fn from_map(m: &Map) -> Result<Applied> {
        Self::from_reader(&Reader::new(m, ""))
    }
    fn from_reader(r: &Reader<'_>) -> Result<Applied> {
        let features = match r.array("features", false)? {
            None => None,
            Some(a) => Some(
                a.iter()
                    .enumerate()
                    .map(|(i, v)| match v.as_str() {
                        // kept as sent, names a later minor version may add included
                        Some(f) => Ok(f.to_string()),
                        None => Err(malformed(format!("'{}[{i}]' must be a string, got {}", r.name("features"), type_name(v)))),
                    })
                    .collect::<Result<Vec<_>>>()?,
            ),
        };
        Ok(Applied { tick: r.u64("tick", true)?.unwrap(), features })
    }
    /// Whether the reported set holds `feature` (`None`: not reported, a server before 1.2).
    pub fn has(&self, feature: &str) -> Option<bool> {
        self.features.as_ref().map(|f| f.iter().any(|x| x == feature))
    }
    fn push(&self, m: &mut Map) {
        m.push((s("tick"), Value::from(self.tick)));
        if let Some(f) = &self.features {
            m.push((s("features"), Value::Array(f.iter().map(|x| s(x)).collect())));
        }
    }
    /// `{v, rid, ok: true, tick[, features]}`: a control reply.
    pub fn encode_reply(&self, rid: u64) -> Vec<u8> {
        let mut m = ok_header(rid);
        self.push(&mut m);
        pack(&Value::Map(m))
    }
}

/// One item's outcome in a batch reply: applied (its tick and, 1.2, features), or its error.
pub type BatchItem = std::result::Result<Applied, ErrorReply>;

#[derive(Debug, Clone, PartialEq)]
pub struct BatchReply {
    pub rid: u64,
    pub tick: u64,
    pub failed: u64,
    pub results: Vec<BatchItem>,
}

impl BatchReply {
    pub fn from_map(m: &Map) -> Result<BatchReply> {
        let r = Reader::new(m, "");
        let rid = r.u64("rid", false)?.unwrap_or(0);
        let mut results = Vec::new();
        for (i, x) in r.array("results", true)?.unwrap().iter().enumerate() {
            let Value::Map(xm) = x else { return Err(malformed(format!("results[{i}] is not a map"))) };
            let xr = Reader::new(xm, &format!("results[{i}]"));
            if xr.bool("ok", true)?.unwrap() {
                results.push(Ok(Applied::from_reader(&xr)?));
            } else {
                let e = xr.sub("error", true)?.unwrap();
                results.push(Err(ErrorReply {
                    rid,
                    code: e.str("code", true)?.unwrap().to_string(),
                    message: e.str("message", false)?.unwrap_or("").to_string(),
                }));
            }
        }
        Ok(BatchReply { rid, tick: r.u64("tick", true)?.unwrap(), failed: r.u64("failed", false)?.unwrap_or(0), results })
    }
    pub fn encode(&self) -> Vec<u8> {
        pack(&Value::Map(self.to_map()))
    }
    /// The reply's map (`encode` packs it; 1.4's `moves` fields go after it).
    pub(crate) fn to_map(&self) -> Map {
        let mut m = ok_header(self.rid);
        m.push((s("tick"), Value::from(self.tick)));
        m.push((s("failed"), Value::from(self.results.iter().filter(|x| x.is_err()).count() as u64)));
        let items = self.results.iter().map(|x| {
            Value::Map(match x {
                Ok(a) => {
                    let mut im = vec![(s("ok"), Value::Boolean(true))];
                    a.push(&mut im);
                    im
                }
                Err(e) => vec![
                    (s("ok"), Value::Boolean(false)),
                    (s("error"), Value::Map(vec![(s("code"), s(&e.code)), (s("message"), s(&e.message))])),
                ],
            })
        });
        m.push((s("results"), Value::Array(items.collect())));
        m
    }
}
