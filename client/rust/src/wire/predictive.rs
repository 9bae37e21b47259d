//! The predictive state encoding of protocol 1.5 (PROTOCOL.md 9.2), the decoder's side: a
//! cloth's [`Stream`] decodes each predictive state against the last two states it rebuilt, into
//! a caller-provided `f32` slice, without allocating once its history exists. A cloth asks for
//! the encoding with `StateOptions { encoding: Some(Encoding::Predictive), step, .. }` (a 1.5
//! server); the client decodes its states here on delivery, in order (`client::recv`).
//! `client/protocol/predictive.py` is the reference; `tests/predictive.rs` checks this decoder against `tests/vectors/predictive.json`.
use super::error::{invalid, malformed, Result};
use super::layout::state as L;
use super::state::STATE_HEADER_SIZE;
use super::{FLAG_NORMALS, PROTOCOL_MAJOR};

/// The encoding's id in the state header.
pub const ENCODING_PREDICTIVE: u8 = 3;
/// A predictive state's header size: the common 64 bytes and 32 more.
pub const PREDICTIVE_HEADER_SIZE: usize = 96;
/// Values per block.
pub const BLOCK: usize = 32;

/// The common header's fields this decoder needs, and the 1.5 fields after them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PredictiveHeader {
    pub header_size: u16,
    pub flags: u16,
    pub vertex_count: u32,
    pub tick: u64,
    pub server_time_ns: u64,
    pub step: f32,
    /// 0 intra-coded (a keyframe), 1 predicted from the previous state, 2 from the last two.
    pub order: u8,
    pub stride: u16,
    pub ref_tick: u64,
    pub ref2_tick: u64,
    pub data_size: u32,
}

impl PredictiveHeader {
    pub fn has_normals(&self) -> bool {
        self.flags & FLAG_NORMALS != 0
    }
}

/// Whether `data` is a predictive state (its header's encoding byte).
pub fn is_predictive(data: &[u8]) -> bool {
    data.len() >= STATE_HEADER_SIZE && L::ENCODING.u8(data) == ENCODING_PREDICTIVE
}

/// Parse and check a predictive state's header by the reading rules.
pub fn parse_predictive(data: &[u8]) -> Result<PredictiveHeader> {
    if data.len() < PREDICTIVE_HEADER_SIZE {
        return Err(malformed(format!(
            "predictive state of {} bytes is shorter than its 96-byte header",
            data.len()
        )));
    }
    if L::MAGIC.get(data) != b"DRPS" || L::MAJOR.u8(data) != PROTOCOL_MAJOR {
        return Err(malformed("not a state payload of major version 1"));
    }
    if L::ENCODING.u8(data) != ENCODING_PREDICTIVE {
        return Err(invalid(format!(
            "state encoding {} is not predictive",
            L::ENCODING.u8(data)
        )));
    }
    let header_size = L::HEADER_SIZE.u16(data);
    if (header_size as usize) < PREDICTIVE_HEADER_SIZE {
        return Err(malformed(format!(
            "predictive state header_size {header_size} is below 96"
        )));
    }
    let le32 = |at: usize| u32::from_le_bytes(data[at..at + 4].try_into().unwrap());
    let le64 = |at: usize| u64::from_le_bytes(data[at..at + 8].try_into().unwrap());
    let h = PredictiveHeader {
        header_size,
        flags: L::FLAGS.u16(data),
        vertex_count: L::VERTEX_COUNT.u32(data),
        tick: L::TICK.u64(data),
        server_time_ns: L::SERVER_TIME_NS.u64(data),
        step: f32::from_le_bytes(data[64..68].try_into().unwrap()),
        order: data[68],
        stride: u16::from_le_bytes(data[70..72].try_into().unwrap()),
        ref_tick: le64(72),
        ref2_tick: le64(80),
        data_size: le32(88),
    };
    if h.order > 2 {
        return Err(invalid(format!("unknown predictor order {}", h.order)));
    }
    if !(h.step.is_finite() && h.step > 0.0) {
        return Err(invalid(format!(
            "predictive step {} is not a positive number",
            h.step
        )));
    }
    // the packed positions hold at least their width bytes (3 per 32 vertices, padded to 4):
    // a vertex count beyond what `data_size` can hold is malformed (and allocates nothing)
    let widths = 4 * (3 * (h.vertex_count as usize).div_ceil(BLOCK)).div_ceil(4);
    if (h.data_size as usize) < widths || h.data_size % 4 != 0 {
        return Err(malformed(format!(
            "predictive data_size {} cannot hold the width bytes of {} vertices",
            h.data_size, h.vertex_count
        )));
    }
    let normals = if h.has_normals() {
        6 * h.vertex_count as usize
    } else {
        0
    };
    let need = header_size as usize + h.data_size as usize + normals;
    if data.len() < need {
        return Err(malformed(format!(
            "predictive state of {} bytes is shorter than the {need} its header announces",
            data.len()
        )));
    }
    Ok(h)
}

/// One cloth's stream of predictive states, as this client rebuilt them.
#[derive(Debug, Default, Clone)]
pub struct Stream {
    q1: Vec<i32>,
    q2: Vec<i32>,
    tick1: Option<u64>,
    tick2: Option<u64>,
    step: f32,
    scratch: Vec<i32>,
    /// [`Stream::decode_to_float32`]'s positions and normals.
    pos: Vec<f32>,
    nrm: Vec<f32>,
    /// States decoded, keyframes among them, and states predicted from one this stream lacked.
    pub decoded: u64,
    pub keyframes: u64,
    pub undecodable: u64,
}

impl Stream {
    pub fn new() -> Self {
        Self::default()
    }

    /// Decode a predictive state into `positions` (`3 n` floats) and, when the state carries
    /// them and `normals` is given, its normals. `Ok(None)`: the state is predicted from one this
    /// stream does not hold (a lost state, a late join): ask for a keyframe; the stream is
    /// unchanged but for its `undecodable` count.
    pub fn decode(
        &mut self,
        data: &[u8],
        positions: &mut [f32],
        normals: Option<&mut [f32]>,
    ) -> Result<Option<PredictiveHeader>> {
        let h = parse_predictive(data)?;
        let n = h.vertex_count as usize;
        if positions.len() < 3 * n {
            return Err(invalid(format!(
                "positions buffer of {} floats; the state has {}",
                positions.len(),
                3 * n
            )));
        }
        let holds = match h.order {
            0 => true,
            1 => h.step == self.step && self.tick1 == Some(h.ref_tick) && self.q1.len() == 3 * n,
            _ => {
                h.step == self.step
                    && self.tick1 == Some(h.ref_tick)
                    && self.tick2 == Some(h.ref2_tick)
                    && self.q1.len() == 3 * n
                    && self.q2.len() == 3 * n
            }
        };
        if !holds {
            self.undecodable += 1;
            return Ok(None);
        }
        let at = h.header_size as usize;
        let packed = &data[at..at + h.data_size as usize];
        // the new state: residual sums on top of the prediction, written where q2 was
        let mut q = std::mem::take(&mut self.scratch);
        q.clear();
        q.resize(3 * n, 0);
        if let Err(e) = unpack(packed, n, &mut q) {
            self.tick1 = None;
            self.tick2 = None;
            self.scratch = q;
            return Err(e);
        }
        // q holds the residuals, vertex-major (x y z per vertex): add the prediction
        match h.order {
            0 => {}
            1 => q
                .iter_mut()
                .zip(&self.q1)
                .for_each(|(r, p)| *r = r.wrapping_add(*p)),
            _ => q
                .iter_mut()
                .zip(self.q1.iter().zip(&self.q2))
                .for_each(|(r, (a, b))| *r = r.wrapping_add(a.wrapping_mul(2).wrapping_sub(*b))),
        }
        let step = h.step as f64;
        for (x, v) in positions[..3 * n].iter_mut().zip(&q) {
            *x = (*v as f64 * step) as f32;
        }
        if let (Some(out), true) = (normals, h.has_normals()) {
            let at = at + h.data_size as usize;
            for (i, x) in out.iter_mut().take(3 * n).enumerate() {
                let v = i16::from_le_bytes([data[at + 2 * i], data[at + 2 * i + 1]]);
                *x = (v as f64 / 32767.0) as f32;
            }
        }
        // the stream moves on: q -> q1 -> q2 (a keyframe starts it afresh)
        if h.order == 0 {
            self.keyframes += 1;
            self.tick2 = None;
            self.q2.clear();
        } else {
            self.tick2 = self.tick1;
        }
        let old2 = std::mem::replace(&mut self.q2, std::mem::replace(&mut self.q1, q));
        self.scratch = old2;
        if h.order == 0 {
            self.q2.clear();
        }
        self.tick1 = Some(h.tick);
        self.step = h.step;
        self.decoded += 1;
        Ok(Some(h))
    }
}

impl Stream {
    /// Decode a predictive state as [`Stream::decode`] does, into a float32 state payload
    /// (`DRPS`, encoding 0, header 64 bytes: the state's common header as received, tick, times,
    /// bounds and flags; its normals as float32 when it has them), what a client keeps and reads
    /// like any other state (`decode_state_into`). `Ok(None)`: not decodable (see `decode`).
    pub fn decode_to_float32(&mut self, data: &[u8]) -> Result<Option<(Vec<u8>, PredictiveHeader)>> {
        let h = parse_predictive(data)?;
        let k = 3 * h.vertex_count as usize;
        let (mut pos, mut nrm) = (std::mem::take(&mut self.pos), std::mem::take(&mut self.nrm));
        pos.resize(k, 0.0);
        nrm.resize(if h.has_normals() { k } else { 0 }, 0.0);
        let normals = if h.has_normals() { Some(&mut nrm[..]) } else { None };
        let r = self.decode(data, &mut pos, normals);
        let out = match r {
            Ok(Some(h)) => {
                let mut out = Vec::with_capacity(STATE_HEADER_SIZE + 4 * (pos.len() + nrm.len()));
                out.extend_from_slice(&data[..STATE_HEADER_SIZE]);
                L::HEADER_SIZE.put(&mut out, 0, &(STATE_HEADER_SIZE as u16).to_le_bytes());
                L::ENCODING.put(&mut out, 0, &[0]); // float32
                for v in pos.iter().chain(&nrm) {
                    out.extend_from_slice(&v.to_le_bytes());
                }
                Ok(Some((out, h)))
            }
            Ok(None) => Ok(None),
            Err(e) => Err(e),
        };
        (self.pos, self.nrm) = (pos, nrm);
        out
    }
}

/// The residuals of `n` vertices from the packed data: symbols by blocks, un-zig-zagged and
/// summed along each axis, written vertex-major (`out[3 v + axis]`).
fn unpack(packed: &[u8], n: usize, out: &mut [i32]) -> Result<()> {
    let nb = n.div_ceil(BLOCK);
    let head = 4 * (3 * nb).div_ceil(4);
    if packed.len() < head {
        return Err(malformed("predictive data is shorter than its width bytes"));
    }
    let widths = &packed[..3 * nb];
    let words = &packed[head..];
    let total: usize = widths.iter().map(|&w| w as usize).sum();
    if widths.iter().any(|&w| w > 32) {
        return Err(invalid("a block width over 32 bits"));
    }
    if words.len() < 4 * total {
        return Err(malformed("predictive data is shorter than its widths say"));
    }
    let mut buf = [0u64; BLOCK + 2]; // a block's words (at most 32) and a zero one past them
    let mut base = 0usize; // the current block's first word
    for axis in 0..3 {
        let mut run: i32 = 0;
        for b in 0..nb {
            let w = widths[axis * nb + b] as usize;
            let first = b * BLOCK;
            let count = BLOCK.min(n - first);
            if w == 0 {
                // every symbol 0: the running sum stays
                for v in first..first + count {
                    out[3 * v + axis] = run;
                }
                continue;
            }
            for (k, slot) in buf.iter_mut().take(w).enumerate() {
                let at = 4 * (base + k);
                *slot = u32::from_le_bytes(words[at..at + 4].try_into().unwrap()) as u64;
            }
            buf[w] = 0;
            let mask: u64 = (1u64 << w) - 1;
            for j in 0..count {
                let bit = j * w;
                let k = bit >> 5;
                let z = (((buf[k] | (buf[k + 1] << 32)) >> (bit & 31)) & mask) as u32;
                run = run.wrapping_add(((z >> 1) as i32) ^ -((z & 1) as i32));
                out[3 * (first + j) + axis] = run;
            }
            base += w;
        }
    }
    Ok(())
}
