//! IEEE half precision (float16) and the quant16 / snorm16 codings of state payloads, exactly as
//! PROTOCOL.md section 9 defines them (round to nearest even; quant16 computed in float64).

/// float32 -> IEEE half bits, round to nearest even (overflow gives infinity, NaN stays NaN).
pub fn f32_to_f16(x: f32) -> u16 {
    let b = x.to_bits();
    let sign = ((b >> 16) & 0x8000) as u16;
    let exp = ((b >> 23) & 0xff) as i32;
    let man = b & 0x7f_ffff;
    if exp == 0xff {
        return sign | 0x7c00 | if man != 0 { 0x200 | (man >> 13) as u16 } else { 0 };
    }
    let e = exp - 127 + 15;
    if e >= 0x1f {
        return sign | 0x7c00;
    }
    if e <= 0 {
        if e < -10 {
            return sign; // below half the smallest subnormal: zero
        }
        let m = man | 0x80_0000;
        let shift = (14 - e) as u32;
        let q = m >> shift;
        let rem = m & ((1 << shift) - 1);
        let half = 1 << (shift - 1);
        let q = if rem > half || (rem == half && q & 1 == 1) { q + 1 } else { q };
        return sign | q as u16;
    }
    let q = ((e as u32) << 10) | (man >> 13);
    let rem = man & 0x1fff;
    let q = if rem > 0x1000 || (rem == 0x1000 && q & 1 == 1) { q + 1 } else { q };
    sign | q as u16
}

/// IEEE half bits -> float32 (exact).
#[inline]
pub fn f16_to_f32(h: u16) -> f32 {
    let sign = ((h as u32) & 0x8000) << 16;
    let exp = ((h >> 10) & 0x1f) as u32;
    let man = (h & 0x3ff) as u32;
    if exp == 0 {
        let v = man as f32 * (1.0 / 16_777_216.0);
        return if sign != 0 { -v } else { v };
    }
    let bits = if exp == 31 { sign | 0x7f80_0000 | (man << 13) } else { sign | ((exp + 112) << 23) | (man << 13) };
    f32::from_bits(bits)
}

pub const FLOAT16_MAX: f32 = 65504.0;
pub const QUANT_MAX: f64 = 65535.0;
pub const SNORM_MAX: f64 = 32767.0;

/// quant16 of one coordinate against its axis bounds: `scale` is `65535 / (max - min)` in float64
/// (0 where `max == min`).
#[inline]
pub fn quantize(x: f32, lo: f64, scale: f64) -> u16 {
    ((x as f64 - lo) * scale).clamp(0.0, QUANT_MAX).round_ties_even() as u16
}

/// The quant16 scale of an axis, `65535 / (max - min)` or 0.
pub fn quant_scale(lo: f32, hi: f32) -> f64 {
    let ext = hi as f64 - lo as f64;
    if ext > 0.0 { QUANT_MAX / ext } else { 0.0 }
}

/// snorm16 of a normal component: `rint(clamp(n, -1, 1) * 32767)`.
#[inline]
pub fn snorm(n: f32) -> i16 {
    ((n as f64).clamp(-1.0, 1.0) * SNORM_MAX).round_ties_even() as i16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_every_finite_half() {
        for h in 0..=0xffffu16 {
            let x = f16_to_f32(h);
            if x.is_nan() {
                assert!(f32_to_f16(x) & 0x7c00 == 0x7c00 && f32_to_f16(x) & 0x3ff != 0);
                continue;
            }
            assert_eq!(f32_to_f16(x), h, "half {h:#06x} = {x}");
        }
    }

    #[test]
    fn rounds_to_nearest_even() {
        assert_eq!(f32_to_f16(0.1), 0x2e66);
        assert_eq!(f32_to_f16(1.3), 0x3d33);
        assert_eq!(f32_to_f16(65520.0), 0x7c00); // halfway to the next: even is infinity
        assert_eq!(f32_to_f16(65519.0), 0x7bff);
        assert_eq!(f32_to_f16(2.0f32.powi(-25)), 0); // half the smallest subnormal: even is 0
        assert_eq!(f32_to_f16(1.5 * 2.0f32.powi(-24)), 2);
    }
}
