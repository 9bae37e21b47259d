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
    /// The last two states' grid values, axis-major with each axis padded to whole blocks
    /// (`q[axis * np + v]`, `np` = 32 x blocks: as the packed data holds them), newest first.
    q1: Vec<i32>,
    q2: Vec<i32>,
    tick1: Option<u64>,
    tick2: Option<u64>,
    step: f32,
    scratch: Vec<i32>,
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
        if !self.advance(data, &h)? {
            return Ok(None);
        }
        let mut cells = positions[..3 * n].chunks_exact_mut(3);
        to_positions(&self.q1, n, h.step, |xyz| {
            if let Some(c) = cells.next() {
                c.copy_from_slice(&xyz);
            }
        });
        if let (Some(out), true) = (normals, h.has_normals()) {
            let at = h.header_size as usize + h.data_size as usize;
            let snorm = &data[at..at + 6 * n];
            for (x, c) in out[..3 * n].iter_mut().zip(snorm.chunks_exact(2)) {
                *x = (i16::from_le_bytes([c[0], c[1]]) as f64 / 32767.0) as f32;
            }
        }
        Ok(Some(h))
    }

    /// Decode the state `h` of `data` into the stream (its grid values become `q1`): false
    /// (nothing changed but `undecodable`) when it is predicted from a state the stream lacks.
    fn advance(&mut self, data: &[u8], h: &PredictiveHeader) -> Result<bool> {
        let n = h.vertex_count as usize;
        let holds = match h.order {
            0 => true,
            1 => h.step == self.step && self.tick1 == Some(h.ref_tick) && self.q1.len() == 3 * padded(n),
            _ => {
                h.step == self.step
                    && self.tick1 == Some(h.ref_tick)
                    && self.tick2 == Some(h.ref2_tick)
                    && self.q1.len() == 3 * padded(n)
                    && self.q2.len() == 3 * padded(n)
            }
        };
        if !holds {
            self.undecodable += 1;
            return Ok(false);
        }
        let at = h.header_size as usize;
        let packed = &data[at..at + h.data_size as usize];
        // the new state: residual sums on top of the prediction, written where q2 was (every
        // value is written by unpack: no clearing needed)
        let mut q = std::mem::take(&mut self.scratch);
        q.resize(3 * padded(n), 0);
        let r = match h.order {
            0 => unpack::<0>(packed, n, &mut q, &[], &[]),
            1 => unpack::<1>(packed, n, &mut q, &self.q1, &[]),
            _ => unpack::<2>(packed, n, &mut q, &self.q1, &self.q2),
        };
        if let Err(e) = r {
            self.tick1 = None;
            self.tick2 = None;
            self.scratch = q;
            return Err(e);
        }
        // the stream moves on: q -> q1 -> q2 (a keyframe starts it afresh)
        if h.order == 0 {
            self.keyframes += 1;
            self.tick2 = None;
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
        Ok(true)
    }
}

/// Values per axis of `n` vertices padded to whole blocks.
fn padded(n: usize) -> usize {
    n.div_ceil(BLOCK) * BLOCK
}

/// The positions `x = float32(float64(q) float64(step))` of `n` vertices of the axis-major grid
/// values `q` (each axis padded, [`padded`]), handed to `put([x, y, z])` in vertex order.
#[inline(always)]
fn to_positions(q: &[i32], n: usize, step: f32, mut put: impl FnMut([f32; 3])) {
    let step = step as f64;
    let np = padded(n);
    let (qx, qy, qz) = (&q[..n], &q[np..np + n], &q[2 * np..2 * np + n]);
    for ((x, y), z) in qx.iter().zip(qy).zip(qz) {
        put([(*x as f64 * step) as f32, (*y as f64 * step) as f32, (*z as f64 * step) as f32]);
    }
}

impl Stream {
    /// Decode a predictive state as [`Stream::decode`] does, into a float32 state payload
    /// (`DRPS`, encoding 0, header 64 bytes: the state's common header as received, tick, times,
    /// bounds and flags; its normals as float32 when it has them), what a client keeps and reads
    /// like any other state (`decode_state_into`): the payload is the one allocation, written
    /// once. `Ok(None)`: not decodable (see `decode`).
    pub fn decode_to_float32(&mut self, data: &[u8]) -> Result<Option<(Vec<u8>, PredictiveHeader)>> {
        let h = parse_predictive(data)?;
        if !self.advance(data, &h)? {
            return Ok(None);
        }
        let n = h.vertex_count as usize;
        let normals = if h.has_normals() { 3 * n } else { 0 };
        let mut out = vec![0u8; STATE_HEADER_SIZE + 4 * (3 * n + normals)];
        out[..STATE_HEADER_SIZE].copy_from_slice(&data[..STATE_HEADER_SIZE]);
        L::HEADER_SIZE.put(&mut out, 0, &(STATE_HEADER_SIZE as u16).to_le_bytes());
        L::ENCODING.put(&mut out, 0, &[0]); // float32
        let (pos, nrm) = out[STATE_HEADER_SIZE..].split_at_mut(12 * n);
        let mut cells = pos.chunks_exact_mut(12);
        to_positions(&self.q1, n, h.step, |xyz| {
            if let Some(c) = cells.next() {
                c[0..4].copy_from_slice(&xyz[0].to_le_bytes());
                c[4..8].copy_from_slice(&xyz[1].to_le_bytes());
                c[8..12].copy_from_slice(&xyz[2].to_le_bytes());
            }
        });
        if normals > 0 {
            let at = h.header_size as usize + h.data_size as usize;
            for (o, c) in nrm.chunks_exact_mut(4).zip(data[at..at + 6 * n].chunks_exact(2)) {
                let x = (i16::from_le_bytes([c[0], c[1]]) as f64 / 32767.0) as f32;
                o.copy_from_slice(&x.to_le_bytes());
            }
        }
        Ok(Some((out, h)))
    }
}

/// One block's 32 symbols of width `W` from its `W` words (`words[W]` is 0): constant shifts
/// and masks once the loop is unrolled for each width, no branch and no bounds check.
#[inline(always)]
fn symbols<const W: usize>(words: &[u32; BLOCK + 1], out: &mut [u32; BLOCK]) {
    let mask = if W == 32 { u32::MAX as u64 } else { (1u64 << W) - 1 };
    for (j, o) in out.iter_mut().enumerate() {
        let bit = j * W;
        let k = bit >> 5;
        *o = (((words[k] as u64 | ((words[(k + 1).min(BLOCK)] as u64) << 32)) >> (bit & 31)) & mask) as u32;
    }
}

/// [`symbols`] of one width (unsafe: the AVX2 ones need a CPU that has AVX2).
type Symbols = unsafe fn(&[u32; BLOCK + 1], &mut [u32; BLOCK]);

macro_rules! by_width {
    ($f:ident; $($w:literal)*) => { [$($f::<$w> as Symbols),*] };
}

/// [`symbols`] for each width 0..=32.
static SYMBOLS: [Symbols; 33] = by_width!(symbols; 0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 23 24 25 26 27 28 29 30 31 32);

/// [`symbols`] compiled for AVX2 (per-lane shifts: 8 symbols an instruction), chosen at run
/// time where the CPU has it.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Symbols, BLOCK};

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn symbols<const W: usize>(words: &[u32; BLOCK + 1], out: &mut [u32; BLOCK]) {
        super::symbols::<W>(words, out)
    }

    pub(super) static SYMBOLS: [Symbols; 33] = by_width!(symbols; 0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 23 24 25 26 27 28 29 30 31 32);
}

/// The [`symbols`] table for this CPU.
fn symbols_table() -> &'static [Symbols; 33] {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        return &avx2::SYMBOLS;
    }
    &SYMBOLS
}

/// One block's values on top of its prediction: the 32 symbols `sym` un-zig-zagged and summed
/// from `run` (the axis's running sum, carried to the next block), plus the prediction of order
/// `ORDER` from the last two states' block values `q1`, `q2` (`2 q1 - q2`, `q1`, or none).
#[inline(always)]
fn finish<const ORDER: u8>(sym: &[u32; BLOCK], run: &mut i32, q1: &[i32], q2: &[i32], out: &mut [i32; BLOCK]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        let (q1, q2): (&[i32; BLOCK], &[i32; BLOCK]) = match ORDER {
            0 => (&[0; BLOCK], &[0; BLOCK]),
            1 => (q1.try_into().unwrap(), &[0; BLOCK]),
            _ => (q1.try_into().unwrap(), q2.try_into().unwrap()),
        };
        // SAFETY: SSE2 is part of x86_64; every load and store is of 4 values at 4 g < 32 of a
        // 32-value array
        unsafe {
            let one = _mm_set1_epi32(1);
            let mut carry = _mm_set1_epi32(*run);
            for g in 0..BLOCK / 4 {
                let z = _mm_loadu_si128(sym.as_ptr().add(4 * g) as *const __m128i);
                let d = _mm_xor_si128(_mm_srli_epi32::<1>(z), _mm_sub_epi32(_mm_setzero_si128(), _mm_and_si128(z, one)));
                let x = _mm_add_epi32(d, _mm_slli_si128::<4>(d));
                let x = _mm_add_epi32(_mm_add_epi32(x, _mm_slli_si128::<8>(x)), carry);
                carry = _mm_shuffle_epi32::<0xFF>(x);
                let p = match ORDER {
                    0 => _mm_setzero_si128(),
                    1 => _mm_loadu_si128(q1.as_ptr().add(4 * g) as *const __m128i),
                    _ => {
                        let a = _mm_loadu_si128(q1.as_ptr().add(4 * g) as *const __m128i);
                        let b = _mm_loadu_si128(q2.as_ptr().add(4 * g) as *const __m128i);
                        _mm_sub_epi32(_mm_add_epi32(a, a), b)
                    }
                };
                _mm_storeu_si128(out.as_mut_ptr().add(4 * g) as *mut __m128i, _mm_add_epi32(x, p));
            }
            *run = _mm_cvtsi128_si32(carry);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    for (j, (o, &z)) in out.iter_mut().zip(sym).enumerate() {
        *run = run.wrapping_add(((z >> 1) as i32) ^ -((z & 1) as i32));
        let p = match ORDER {
            0 => 0,
            1 => q1[j],
            _ => q1[j].wrapping_mul(2).wrapping_sub(q2[j]),
        };
        *o = run.wrapping_add(p);
    }
}

/// The grid values of `n` vertices from the packed data and the prediction of order `ORDER`
/// from `q1`, `q2` (the last two states, as `out`): symbols by blocks, un-zig-zagged, summed along
/// each axis and added to the prediction, written axis-major and padded (`out[axis * np + v]`,
/// `out` of `3 np` values, [`padded`]).
fn unpack<const ORDER: u8>(packed: &[u8], n: usize, out: &mut [i32], q1: &[i32], q2: &[i32]) -> Result<()> {
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
    let np = nb * BLOCK;
    let out = &mut out[..3 * np];
    let q1 = if ORDER >= 1 { &q1[..3 * np] } else { &[][..] };
    let q2 = if ORDER >= 2 { &q2[..3 * np] } else { &[][..] };
    let mut buf = [0u32; BLOCK + 1]; // a block's words (at most 32) and a zero one past them
    let mut sym = [0u32; BLOCK];
    let mut src = words[..4 * total].chunks_exact(4);
    let table = symbols_table();
    for (axis, ws) in widths.chunks_exact(nb).enumerate() {
        let mut run: i32 = 0;
        for (b, &w) in ws.iter().enumerate() {
            let w = w as usize;
            for (slot, c) in buf[..w].iter_mut().zip(src.by_ref()) {
                *slot = u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            }
            buf[w] = 0;
            // SAFETY: the table holds AVX2 functions only where the CPU has AVX2
            unsafe { table[w](&buf, &mut sym) };
            let at = axis * np + b * BLOCK;
            let o: &mut [i32; BLOCK] = (&mut out[at..at + BLOCK]).try_into().unwrap();
            let p1 = if ORDER >= 1 { &q1[at..at + BLOCK] } else { q1 };
            let p2 = if ORDER >= 2 { &q2[at..at + BLOCK] } else { q2 };
            finish::<ORDER>(&sym, &mut run, p1, p2, o);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every width's symbols, plain and through the table this CPU uses (AVX2 where it has it),
    /// are the bits of the block's words, LSB first.
    #[test]
    fn symbols_of_every_width_are_the_packed_bits() {
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        for w in 0..=32usize {
            let mut words = [0u32; BLOCK + 1];
            for x in words[..w].iter_mut() {
                seed ^= seed << 13;
                seed ^= seed >> 7;
                seed ^= seed << 17;
                *x = seed as u32;
            }
            let bit = |i: usize| (words[i / 32] >> (i % 32)) & 1;
            let want: Vec<u32> = (0..BLOCK).map(|j| (0..w).map(|b| bit(j * w + b) << b).sum()).collect();
            for table in [&SYMBOLS, symbols_table()] {
                let mut got = [0u32; BLOCK];
                // SAFETY: symbols_table() gives AVX2 functions only where the CPU has AVX2
                unsafe { table[w](&words, &mut got) };
                assert_eq!(got.to_vec(), want, "width {w}");
            }
        }
    }
}
