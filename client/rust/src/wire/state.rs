//! The binary state payload `DRPS` (PROTOCOL.md section 9): header parsing with the reading
//! rules, decoding into caller-provided `f32` buffers (no allocation), and encoding.
use super::error::{invalid, malformed, Error, ErrorCode, Result};
use super::half::{f16_to_f32, f32_to_f16, quant_scale, quantize, snorm, FLOAT16_MAX, QUANT_MAX, SNORM_MAX};
use super::layout::state as L;
use super::msg::Encoding;
use super::{FLAG_NORMALS, PROTOCOL_MAJOR, PROTOCOL_MINOR};

pub const STATE_MAGIC: &[u8; 4] = b"DRPS";
pub const STATE_HEADER_SIZE: usize = L::SIZE;

/// Every header field of a state payload.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StateHeader {
    pub major: u8,
    pub minor: u8,
    pub header_size: u16,
    pub encoding: Encoding,
    pub flags: u16,
    pub vertex_count: u32,
    pub tick: u64,
    pub server_time_ns: u64,
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
}

impl StateHeader {
    pub fn has_normals(&self) -> bool {
        self.flags & FLAG_NORMALS != 0
    }
    pub fn is_reset(&self) -> bool {
        self.flags & super::FLAG_RESET != 0
    }
    /// Floats of the positions (and of the normals): `3 * vertex_count`.
    pub fn floats(&self) -> usize {
        3 * self.vertex_count as usize
    }
    /// Bytes the payload needs: `header_size + 3n·s·(1 + normals)`; of a predictive state the
    /// least (`header_size` and its normals: its packed positions' size is in its 1.5 header,
    /// [`super::parse_predictive`]).
    pub fn needed_size(&self) -> usize {
        if self.encoding == Encoding::Predictive {
            return self.header_size as usize + if self.has_normals() { 6 * self.vertex_count as usize } else { 0 };
        }
        self.header_size as usize + self.block() * if self.has_normals() { 2 } else { 1 }
    }
    fn block(&self) -> usize {
        self.floats() * self.encoding.element_size()
    }
}

/// Bytes of an encoded state.
pub fn state_size(vertices: usize, encoding: Encoding, normals: bool) -> usize {
    STATE_HEADER_SIZE + vertices * 3 * encoding.element_size() * if normals { 2 } else { 1 }
}

/// Parse and check a state header by the reading rules: bad magic, unknown major, header_size
/// below 64, unknown encoding or a payload shorter than announced are errors; a longer header,
/// unknown flags and trailing bytes are accepted.
pub fn parse_state(data: &[u8]) -> Result<StateHeader> {
    if data.len() < STATE_HEADER_SIZE {
        return Err(malformed(format!("state payload of {} bytes is shorter than the 64-byte header", data.len())));
    }
    if L::MAGIC.get(data) != STATE_MAGIC {
        return Err(malformed(format!("state payload magic {:?} is not \"DRPS\"", String::from_utf8_lossy(L::MAGIC.get(data)))));
    }
    let (major, minor) = (L::MAJOR.u8(data), L::MINOR.u8(data));
    if major != PROTOCOL_MAJOR {
        return Err(Error::new(
            ErrorCode::UnsupportedVersion,
            format!("state version {major}.{minor} is not supported; this side speaks {PROTOCOL_MAJOR}.{PROTOCOL_MINOR}"),
        ));
    }
    let header_size = L::HEADER_SIZE.u16(data);
    if (header_size as usize) < STATE_HEADER_SIZE {
        return Err(malformed(format!("state header_size {header_size} is below 64")));
    }
    let enc = L::ENCODING.u8(data);
    let encoding = Encoding::from_id(enc).ok_or_else(|| invalid(format!("unknown state encoding {enc}")))?;
    let h = StateHeader {
        major,
        minor,
        header_size,
        encoding,
        flags: L::FLAGS.u16(data),
        vertex_count: L::VERTEX_COUNT.u32(data),
        tick: L::TICK.u64(data),
        server_time_ns: L::SERVER_TIME_NS.u64(data),
        bounds_min: L::BOUNDS_MIN.f32x3(data),
        bounds_max: L::BOUNDS_MAX.f32x3(data),
    };
    if encoding == Encoding::Predictive {
        super::predictive::parse_predictive(data)?; // its 1.5 header and the size it announces
    } else if data.len() < h.needed_size() {
        return Err(malformed(format!(
            "state payload of {} bytes is shorter than the {} bytes its header announces ({} vertices, {}{})",
            data.len(),
            h.needed_size(),
            h.vertex_count,
            encoding.name(),
            if h.has_normals() { ", normals" } else { "" }
        )));
    }
    Ok(h)
}

/// Decode a state into caller-owned buffers: `positions` gets `3n` floats (xyz interleaved),
/// `normals` (if given and the state has normals) `3n` more. A buffer shorter than `3n` is an
/// `invalid_value` error; a longer one is left untouched past `3n`. No allocation. A predictive
/// state (1.5) is an `invalid_value` error here: it decodes only against its stream's previous
/// states ([`super::PredictiveStream`]; the client does that on delivery).
pub fn decode_state_into(data: &[u8], positions: &mut [f32], normals: Option<&mut [f32]>) -> Result<StateHeader> {
    let h = parse_state(data)?;
    if h.encoding == Encoding::Predictive {
        return Err(invalid("a predictive state decodes only in order, against its stream's previous states (PredictiveStream)"));
    }
    let k = h.floats();
    if positions.len() < k {
        return Err(invalid(format!("positions buffer holds {} floats, the state has {k}", positions.len())));
    }
    let at = h.header_size as usize;
    let block = h.block();
    let (lo, hi) = (h.bounds_min, h.bounds_max);
    match h.encoding {
        Encoding::Float32 => decode_f32(&data[at..at + block], &mut positions[..k]),
        Encoding::Float16 => decode_f16(&data[at..at + block], &mut positions[..k]),
        Encoding::Predictive => unreachable!("refused above"),
        Encoding::Quant16 => {
            let lo64 = [lo[0] as f64, lo[1] as f64, lo[2] as f64];
            let step = [0, 1, 2].map(|i| (hi[i] as f64 - lo64[i]) / QUANT_MAX);
            for (out, q) in positions[..k].chunks_exact_mut(3).zip(data[at..at + block].chunks_exact(6)) {
                for i in 0..3 {
                    out[i] = (lo64[i] + u16::from_le_bytes([q[2 * i], q[2 * i + 1]]) as f64 * step[i]) as f32;
                }
            }
        }
    }
    if let (Some(nrm), true) = (normals, h.has_normals()) {
        if nrm.len() < k {
            return Err(invalid(format!("normals buffer holds {} floats, the state has {k}", nrm.len())));
        }
        let src = &data[at + block..at + 2 * block];
        match h.encoding {
            Encoding::Float32 => decode_f32(src, &mut nrm[..k]),
            Encoding::Float16 => decode_f16(src, &mut nrm[..k]),
            Encoding::Predictive => unreachable!("refused above"),
            Encoding::Quant16 => {
                for (out, q) in nrm[..k].iter_mut().zip(src.chunks_exact(2)) {
                    *out = (i16::from_le_bytes([q[0], q[1]]) as f64 / SNORM_MAX) as f32;
                }
            }
        }
    }
    Ok(h)
}

#[inline]
fn decode_f32(src: &[u8], out: &mut [f32]) {
    for (o, b) in out.iter_mut().zip(src.chunks_exact(4)) {
        *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    }
}

#[inline]
fn decode_f16(src: &[u8], out: &mut [f32]) {
    for (o, b) in out.iter_mut().zip(src.chunks_exact(2)) {
        *o = f16_to_f32(u16::from_le_bytes([b[0], b[1]]));
    }
}

/// Encode a state (what a server publishes; here for tests and tools). `positions`: `3n` finite
/// floats; `normals`: `3n` floats or None. The normals flag follows `normals`; other `flags`
/// bits are written as given. Bounds are the positions' per-axis min and max. Not predictive
/// states (they are coded against a stream's previous ones: `invalid_value`).
pub fn encode_state(
    tick: u64,
    server_time_ns: u64,
    positions: &[f32],
    normals: Option<&[f32]>,
    encoding: Encoding,
    flags: u16,
) -> Result<Vec<u8>> {
    if positions.len() % 3 != 0 {
        return Err(invalid(format!("positions hold {} floats, not a multiple of 3", positions.len())));
    }
    if encoding == Encoding::Predictive {
        return Err(invalid("predictive states are coded against their stream's previous states; encode_state writes the others"));
    }
    let n = positions.len() / 3;
    if let Some(nrm) = normals {
        if nrm.len() != positions.len() {
            return Err(invalid(format!("{} normal floats for {} position floats", nrm.len(), positions.len())));
        }
    }
    let flags = if normals.is_some() { flags | FLAG_NORMALS } else { flags & !FLAG_NORMALS };
    let (mut lo, mut hi) = ([0f32; 3], [0f32; 3]);
    if n > 0 {
        lo = [f32::INFINITY; 3];
        hi = [f32::NEG_INFINITY; 3];
        for p in positions.chunks_exact(3) {
            for i in 0..3 {
                lo[i] = lo[i].min(p[i]);
                hi[i] = hi[i].max(p[i]);
            }
        }
    }
    let mut out = Vec::with_capacity(state_size(n, encoding, normals.is_some()));
    out.resize(STATE_HEADER_SIZE, 0); // reserved fields stay 0
    L::MAGIC.put(&mut out, 0, STATE_MAGIC);
    L::MAJOR.put(&mut out, 0, &[PROTOCOL_MAJOR]);
    L::MINOR.put(&mut out, 0, &[PROTOCOL_MINOR]);
    L::HEADER_SIZE.put(&mut out, 0, &(STATE_HEADER_SIZE as u16).to_le_bytes());
    L::ENCODING.put(&mut out, 0, &[encoding as u8]);
    L::FLAGS.put(&mut out, 0, &flags.to_le_bytes());
    L::VERTEX_COUNT.put(&mut out, 0, &(n as u32).to_le_bytes());
    L::TICK.put(&mut out, 0, &tick.to_le_bytes());
    L::SERVER_TIME_NS.put(&mut out, 0, &server_time_ns.to_le_bytes());
    L::BOUNDS_MIN.put(&mut out, 0, &lo.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<_>>());
    L::BOUNDS_MAX.put(&mut out, 0, &hi.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<_>>());
    match encoding {
        Encoding::Float32 => {
            for v in positions.iter().chain(normals.unwrap_or(&[])) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        Encoding::Float16 => {
            for v in positions {
                out.extend_from_slice(&f32_to_f16(v.clamp(-FLOAT16_MAX, FLOAT16_MAX)).to_le_bytes());
            }
            for v in normals.unwrap_or(&[]) {
                out.extend_from_slice(&f32_to_f16(*v).to_le_bytes());
            }
        }
        Encoding::Predictive => unreachable!("refused above"),
        Encoding::Quant16 => {
            let scale = [0, 1, 2].map(|i| quant_scale(lo[i], hi[i]));
            for p in positions.chunks_exact(3) {
                for i in 0..3 {
                    out.extend_from_slice(&quantize(p[i], lo[i] as f64, scale[i]).to_le_bytes());
                }
            }
            for v in normals.unwrap_or(&[]) {
                out.extend_from_slice(&snorm(*v).to_le_bytes());
            }
        }
    }
    Ok(out)
}
