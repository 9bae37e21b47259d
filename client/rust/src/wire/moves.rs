//! Protocol 1.4 `moves` (PROTOCOL.md 5.1.1): the pin moves of many cloths as one columnar block
//! in a batch control ([`Moves`]), a batch control decoded with its block ([`DecodedBatch`]),
//! and the batch reply's `moves_tick` / `moves_failed` ([`MovesReply`]).
use super::error::{invalid, malformed, Error, ErrorCode, Result};
use super::keys::{valid_id, valid_token};
use super::msg::{Control, ControlBatch};
use super::reader::{bin_f32, bin_u32, header, pack, s, type_name, unpack_message, Map, Reader, Value};
use super::replies::BatchReply;
use super::validate::Limits;
use super::MAX_BATCH_MOVES;

/// The largest coordinate of a pin target (PROTOCOL.md section 5).
const COORD: f32 = 1e5;

/// A `moves` block: cloth `j` (`cloths[j]`, owned by `tokens[j]`) moves its pinned vertex
/// `indices[i]` to `targets[3(j k + i) .. 3(j k + i) + 3]` (`k = indices.len()`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Moves {
    pub cloths: Vec<String>,
    pub tokens: Vec<String>,
    pub indices: Vec<u32>,
    pub targets: Vec<f32>,
}

impl Moves {
    /// The `moves` map of a batch control.
    pub fn to_value(&self) -> Value {
        Value::Map(vec![
            (s("cloths"), Value::Array(self.cloths.iter().map(|c| s(c)).collect())),
            (s("tokens"), Value::Array(self.tokens.iter().map(|t| s(t)).collect())),
            (s("indices"), bin_u32(&self.indices)),
            (s("targets"), bin_f32(&self.targets)),
        ])
    }

    /// Check the block whole, as the server does on the bytes alone (PROTOCOL.md 5.1.1):
    /// 1..`MAX_BATCH_MOVES` well-formed cloth ids with as many tokens, 1..`max_pin_updates`
    /// distinct indices, exactly `n * k * 3` targets, finite within ±1e5. Ownership, index
    /// ranges and pinned-ness are the server's (per move).
    pub fn validate(&self, lim: &Limits) -> Result<()> {
        let n = self.cloths.len();
        for (key, len) in [("cloths", n), ("tokens", self.tokens.len())] {
            if len > MAX_BATCH_MOVES {
                return Err(Error::new(ErrorCode::TooLarge, format!("'moves.{key}' has {len} entries, at most {MAX_BATCH_MOVES}")));
            }
        }
        if let Some((j, c)) = self.cloths.iter().enumerate().find(|(_, c)| !valid_id(c)) {
            return Err(invalid(format!("'moves.cloths[{j}]' = {c:?} is not a cloth id")));
        }
        if let Some(j) = self.tokens.iter().position(|t| !valid_token(t)) {
            return Err(invalid(format!("'moves.tokens[{j}]' must be 32 lowercase hex digits")));
        }
        if self.tokens.len() != n {
            return Err(invalid(format!("'moves.tokens' has {} entries but 'cloths' has {n}", self.tokens.len())));
        }
        check_block(n, &self.indices, &self.targets, lim)
    }

    /// The `moves` block of a batch control (None when absent), read and validated whole.
    pub fn from_reader(r: &Reader<'_>, lim: &Limits) -> Result<Option<Moves>> {
        let Some(mr) = r.sub("moves", false)? else { return Ok(None) };
        let strings = |key: &str| -> Result<Vec<String>> {
            let a = mr.array(key, true)?.unwrap();
            if a.len() > MAX_BATCH_MOVES {
                return Err(Error::new(ErrorCode::TooLarge, format!("'{}' has {} entries, at most {MAX_BATCH_MOVES}", mr.name(key), a.len())));
            }
            a.iter()
                .enumerate()
                .map(|(i, v)| {
                    v.as_str().map(str::to_string).ok_or_else(|| {
                        Error::new(ErrorCode::InvalidType, format!("'{}[{i}]' must be a string, got {}", mr.name(key), type_name(v)))
                    })
                })
                .collect()
        };
        let cloths = strings("cloths")?;
        let tokens = strings("tokens")?;
        let indices = mr.u32s("indices", true)?.unwrap();
        let targets = match mr.req("targets")? {
            Value::Binary(_) => mr.f32s("targets", true)?.unwrap(),
            v => return Err(Error::new(ErrorCode::InvalidType, format!("'moves.targets' must be bin of f32, got {}", type_name(v)))),
        };
        let m = Moves { cloths, tokens, indices, targets };
        m.validate(lim)?;
        Ok(Some(m))
    }
}

/// The part of a block's checks that needs no ids (PROTOCOL.md 5.1.1): at least one cloth
/// (`n`), 1..`max_pin_updates` distinct `indices`, exactly `n * k * 3` `targets`, each finite
/// within ±1e5. [`Moves::validate`] adds the ids, the tokens and the `MAX_BATCH_MOVES` cap.
pub fn check_block(n: usize, indices: &[u32], targets: &[f32], lim: &Limits) -> Result<()> {
    if n == 0 {
        return Err(invalid("'moves.cloths' must name at least one cloth"));
    }
    let k = indices.len();
    if k == 0 {
        return Err(invalid("'moves.indices' must hold at least one vertex index"));
    }
    if k > lim.max_pin_updates {
        return Err(Error::new(ErrorCode::TooLarge, format!("'moves.indices' has {k} entries, at most {}", lim.max_pin_updates)));
    }
    let mut sorted = indices.to_vec();
    sorted.sort_unstable();
    if sorted.windows(2).any(|w| w[0] == w[1]) {
        return Err(invalid("'moves.indices' repeats a vertex index"));
    }
    if targets.len() != n * k * 3 {
        return Err(invalid(format!("'moves.targets' has {} values, expected {n} cloths x {k} pins x 3 = {}", targets.len(), n * k * 3)));
    }
    if let Some(i) = targets.iter().position(|x| !(x.abs() <= COORD)) {
        return Err(invalid(format!("'moves.targets' values must be finite within ±1e5: value {i} (cloth {}) is {}", i / (3 * k), targets[i])));
    }
    Ok(())
}

/// A batch control as the server reads it: the envelope (and, 1.4, the `moves` block) all or
/// nothing, then each item standing alone (decoded and validated, or its error).
#[derive(Debug)]
pub struct DecodedBatch {
    pub rid: u64,
    pub client: String,
    pub items: Vec<Result<Control>>,
    pub moves: Option<Moves>,
}

impl DecodedBatch {
    pub fn decode(data: &[u8], lim: &Limits) -> Result<DecodedBatch> {
        let m = unpack_message(data)?;
        let r = Reader::new(&m, "");
        let rid = r.u64("rid", false)?.unwrap_or(0);
        let client = r.str("client", true)?.unwrap().to_string();
        if !valid_id(&client) {
            return Err(invalid(format!("invalid client id {client:?}")));
        }
        let moves = Moves::from_reader(&r, lim)?;
        let raw = match (r.array("items", false)?, &moves) {
            (None, Some(_)) => &[][..],
            (None, None) => return Err(Error::new(ErrorCode::MissingField, "'items' is required (unless 'moves' is given, 1.4)")),
            (Some(a), _) => a,
        };
        if raw.is_empty() && moves.is_none() {
            return Err(invalid("'items' is empty"));
        }
        if raw.len() > lim.max_batch_items {
            return Err(Error::new(ErrorCode::TooLarge, format!("{} items, at most {}", raw.len(), lim.max_batch_items)));
        }
        let items = raw.iter().enumerate().map(|(i, it)| {
            let Value::Map(im) = it else {
                return Err(Error::new(ErrorCode::InvalidType, format!("'items[{i}]' must be a map")));
            };
            let c = Control::from_reader(&Reader::new(im, &format!("items[{i}]")))?;
            c.validate(lim, None).map(|_| c)
        });
        Ok(DecodedBatch { rid, client, items: items.collect(), moves })
    }
}

impl ControlBatch {
    /// The batch control with a 1.4 `moves` block (after the items; `items` is left out when
    /// there are none and a block is given). `encode_with_moves(None)` is [`ControlBatch::encode`].
    pub fn encode_with_moves(&self, moves: Option<&Moves>) -> Vec<u8> {
        let mut m = header(self.rid);
        m.push((s("client"), s(&self.client)));
        if !self.items.is_empty() || moves.is_none() {
            m.push((s("items"), Value::Array(self.items.iter().map(|c| Value::Map(c.item_map())).collect())));
        }
        if let Some(mv) = moves {
            m.push((s("moves"), mv.to_value()));
        }
        pack(&Value::Map(m))
    }
}

/// One refused move of a block: its position in the block, the wire code and the message.
#[derive(Debug, Clone, PartialEq)]
pub struct MoveFailed {
    pub position: usize,
    pub code: String,
    pub message: String,
}

impl MoveFailed {
    pub fn to_error(&self, rid: u64) -> Error {
        let code = ErrorCode::from_name(&self.code);
        let message = if code == ErrorCode::Unknown { format!("{}: {}", self.code, self.message) } else { self.message.clone() };
        Error::new(code, message).with_rid(rid)
    }
}

/// 1.4: what a batch reply says of the request's `moves` block.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MovesReply {
    /// The first tick whose states reflect the applied moves.
    pub moves_tick: u64,
    /// The refused moves, in position order (empty: none).
    pub moves_failed: Vec<MoveFailed>,
}

impl MovesReply {
    /// `moves_tick` and `moves_failed` of a batch reply; None when absent (the request had no
    /// moves, or the server is older than 1.4); `malformed` when only one is there.
    pub fn from_map(m: &Map) -> Result<Option<MovesReply>> {
        let r = Reader::new(m, "");
        let (tick, failed) = (r.u64("moves_tick", false)?, r.array("moves_failed", false)?);
        let (tick, failed) = match (tick, failed) {
            (None, None) => return Ok(None),
            (Some(t), Some(f)) => (t, f),
            _ => return Err(malformed("a batch reply must have both 'moves_tick' and 'moves_failed' or neither")),
        };
        let mut out = Vec::with_capacity(failed.len());
        for (i, x) in failed.iter().enumerate() {
            match x {
                Value::Array(a) if a.len() == 3 => match (a[0].as_u64(), a[1].as_str(), a[2].as_str()) {
                    (Some(p), Some(c), Some(msg)) => {
                        out.push(MoveFailed { position: p as usize, code: c.to_string(), message: msg.to_string() })
                    }
                    _ => return Err(malformed(format!("'moves_failed[{i}]' must be [position, code, message]"))),
                },
                v => return Err(malformed(format!("'moves_failed[{i}]' must be [position, code, message], got {}", type_name(v)))),
            }
        }
        Ok(Some(MovesReply { moves_tick: tick, moves_failed: out }))
    }
}

impl BatchReply {
    /// The batch reply with 1.4's `moves_tick` and `moves_failed` (after `results`).
    /// `encode_with_moves(None)` is [`BatchReply::encode`].
    pub fn encode_with_moves(&self, moves: Option<&MovesReply>) -> Vec<u8> {
        let mut m = self.to_map();
        if let Some(mv) = moves {
            m.push((s("moves_tick"), Value::from(mv.moves_tick)));
            let failed = mv.moves_failed.iter().map(|f| Value::Array(vec![Value::from(f.position as u64), s(&f.code), s(&f.message)]));
            m.push((s("moves_failed"), Value::Array(failed.collect())));
        }
        pack(&Value::Map(m))
    }
}
