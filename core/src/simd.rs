//! Four f32 lanes ([`F4`]) and four i32 lanes ([`I4`]): SSE2 on x86-64 (every x86-64 CPU has
//! it, so no dispatch), plain arrays elsewhere. Only the operations the renderer's four-lane
//! code needs; each lane computes exactly what the scalar IEEE operation computes, so both
//! paths give the same bits. [`F4::exp`] and [`F4::ln`] are written once, on these operations.

use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Sub};

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// Four f32 lanes.
#[derive(Clone, Copy, Debug)]
pub struct F4(#[cfg(target_arch = "x86_64")] __m128, #[cfg(not(target_arch = "x86_64"))] [f32; 4]);

/// Four i32 lanes; also a lane mask (all ones or all zeros) from [`F4`]'s comparisons.
#[derive(Clone, Copy, Debug)]
pub struct I4(#[cfg(target_arch = "x86_64")] __m128i, #[cfg(not(target_arch = "x86_64"))] [i32; 4]);

#[cfg(target_arch = "x86_64")]
// SAFETY (every `unsafe` below): SSE and SSE2 are part of x86-64 itself, so every x86-64 CPU
// runs these intrinsics; the compiler asks for `unsafe` only because they carry
// `#[target_feature]`.
mod imp {
    use super::*;

    impl F4 {
        #[inline(always)]
        pub fn new(a: [f32; 4]) -> F4 {
            F4(unsafe { _mm_setr_ps(a[0], a[1], a[2], a[3]) })
        }
        #[inline(always)]
        pub fn splat(x: f32) -> F4 {
            F4(unsafe { _mm_set1_ps(x) })
        }
        #[inline(always)]
        pub fn to_array(self) -> [f32; 4] {
            let mut a = [0.0; 4];
            // `a` holds four f32.
            unsafe { _mm_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        pub fn sqrt(self) -> F4 {
            F4(unsafe { _mm_sqrt_ps(self.0) })
        }
        /// `a < b ? a : b` per lane (a NaN in either gives `b`).
        #[inline(always)]
        pub fn min(self, b: F4) -> F4 {
            F4(unsafe { _mm_min_ps(self.0, b.0) })
        }
        /// `a > b ? a : b` per lane (a NaN in either gives `b`).
        #[inline(always)]
        pub fn max(self, b: F4) -> F4 {
            F4(unsafe { _mm_max_ps(self.0, b.0) })
        }
        #[inline(always)]
        pub fn lt(self, b: F4) -> I4 {
            I4(unsafe { _mm_castps_si128(_mm_cmplt_ps(self.0, b.0)) })
        }
        #[inline(always)]
        pub fn le(self, b: F4) -> I4 {
            I4(unsafe { _mm_castps_si128(_mm_cmple_ps(self.0, b.0)) })
        }
        #[inline(always)]
        pub fn eq(self, b: F4) -> I4 {
            I4(unsafe { _mm_castps_si128(_mm_cmpeq_ps(self.0, b.0)) })
        }
        /// The lanes' bits.
        #[inline(always)]
        pub fn bits(self) -> I4 {
            I4(unsafe { _mm_castps_si128(self.0) })
        }
        /// Truncated toward zero (lanes past i32's range give i32::MIN).
        #[inline(always)]
        pub fn trunc_i4(self) -> I4 {
            I4(unsafe { _mm_cvttps_epi32(self.0) })
        }
    }

    impl I4 {
        #[inline(always)]
        pub fn splat(x: i32) -> I4 {
            I4(unsafe { _mm_set1_epi32(x) })
        }
        #[inline(always)]
        pub fn from_bits(self) -> F4 {
            F4(unsafe { _mm_castsi128_ps(self.0) })
        }
        #[inline(always)]
        pub fn to_f4(self) -> F4 {
            F4(unsafe { _mm_cvtepi32_ps(self.0) })
        }
        #[inline(always)]
        pub fn shl<const N: i32>(self) -> I4 {
            I4(unsafe { _mm_slli_epi32::<N>(self.0) })
        }
        #[inline(always)]
        pub fn shr<const N: i32>(self) -> I4 {
            I4(unsafe { _mm_srli_epi32::<N>(self.0) })
        }
        /// Per lane, `a` where the mask `self` is set, else `b`.
        #[inline(always)]
        pub fn select(self, a: F4, b: F4) -> F4 {
            unsafe {
                let m = _mm_castsi128_ps(self.0);
                F4(_mm_or_ps(_mm_and_ps(m, a.0), _mm_andnot_ps(m, b.0)))
            }
        }
    }

    macro_rules! op {
        ($s:ident, $t:ident, $f:ident, $i:ident) => {
            impl $t for $s {
                type Output = $s;
                #[inline(always)]
                fn $f(self, b: $s) -> $s {
                    $s(unsafe { $i(self.0, b.0) })
                }
            }
        };
    }
    op!(F4, Add, add, _mm_add_ps);
    op!(F4, Sub, sub, _mm_sub_ps);
    op!(F4, Mul, mul, _mm_mul_ps);
    op!(F4, Div, div, _mm_div_ps);
    op!(I4, Add, add, _mm_add_epi32);
    op!(I4, Sub, sub, _mm_sub_epi32);
    op!(I4, BitAnd, bitand, _mm_and_si128);
    op!(I4, BitOr, bitor, _mm_or_si128);
    op!(I4, BitXor, bitxor, _mm_xor_si128);
}

#[cfg(not(target_arch = "x86_64"))]
mod imp {
    use super::*;

    impl F4 {
        #[inline(always)]
        pub fn new(a: [f32; 4]) -> F4 {
            F4(a)
        }
        #[inline(always)]
        pub fn splat(x: f32) -> F4 {
            F4([x; 4])
        }
        #[inline(always)]
        pub fn to_array(self) -> [f32; 4] {
            self.0
        }
        #[inline(always)]
        pub fn sqrt(self) -> F4 {
            F4(self.0.map(f32::sqrt))
        }
        #[inline(always)]
        pub fn min(self, b: F4) -> F4 {
            F4(std::array::from_fn(|i| if self.0[i] < b.0[i] { self.0[i] } else { b.0[i] }))
        }
        #[inline(always)]
        pub fn max(self, b: F4) -> F4 {
            F4(std::array::from_fn(|i| if self.0[i] > b.0[i] { self.0[i] } else { b.0[i] }))
        }
        #[inline(always)]
        pub fn lt(self, b: F4) -> I4 {
            I4(std::array::from_fn(|i| -((self.0[i] < b.0[i]) as i32)))
        }
        #[inline(always)]
        pub fn le(self, b: F4) -> I4 {
            I4(std::array::from_fn(|i| -((self.0[i] <= b.0[i]) as i32)))
        }
        #[inline(always)]
        pub fn eq(self, b: F4) -> I4 {
            I4(std::array::from_fn(|i| -((self.0[i] == b.0[i]) as i32)))
        }
        #[inline(always)]
        pub fn bits(self) -> I4 {
            I4(self.0.map(|x| x.to_bits() as i32))
        }
        #[inline(always)]
        pub fn trunc_i4(self) -> I4 {
            I4(self.0.map(|x| if x.abs() < 2_147_483_648.0 { x as i32 } else { i32::MIN }))
        }
    }

    impl I4 {
        #[inline(always)]
        pub fn splat(x: i32) -> I4 {
            I4([x; 4])
        }
        #[inline(always)]
        pub fn from_bits(self) -> F4 {
            F4(self.0.map(|x| f32::from_bits(x as u32)))
        }
        #[inline(always)]
        pub fn to_f4(self) -> F4 {
            F4(self.0.map(|x| x as f32))
        }
        #[inline(always)]
        pub fn shl<const N: i32>(self) -> I4 {
            I4(self.0.map(|x| (x as u32).checked_shl(N as u32).unwrap_or(0) as i32))
        }
        #[inline(always)]
        pub fn shr<const N: i32>(self) -> I4 {
            I4(self.0.map(|x| (x as u32).checked_shr(N as u32).unwrap_or(0) as i32))
        }
        #[inline(always)]
        pub fn select(self, a: F4, b: F4) -> F4 {
            F4(std::array::from_fn(|i| if self.0[i] != 0 { a.0[i] } else { b.0[i] }))
        }
    }

    macro_rules! op {
        ($s:ident, $e:ty, $t:ident, $f:ident, $g:expr) => {
            impl $t for $s {
                type Output = $s;
                #[inline(always)]
                fn $f(self, b: $s) -> $s {
                    let g: fn($e, $e) -> $e = $g;
                    $s(std::array::from_fn(|i| g(self.0[i], b.0[i])))
                }
            }
        };
    }
    op!(F4, f32, Add, add, |a, b| a + b);
    op!(F4, f32, Sub, sub, |a, b| a - b);
    op!(F4, f32, Mul, mul, |a, b| a * b);
    op!(F4, f32, Div, div, |a, b| a / b);
    op!(I4, i32, Add, add, |a, b| a.wrapping_add(b));
    op!(I4, i32, Sub, sub, |a, b| a.wrapping_sub(b));
    op!(I4, i32, BitAnd, bitand, |a, b| a & b);
    op!(I4, i32, BitOr, bitor, |a, b| a | b);
    op!(I4, i32, BitXor, bitxor, |a, b| a ^ b);
}

impl Neg for F4 {
    type Output = F4;
    #[inline(always)]
    fn neg(self) -> F4 {
        (self.bits() ^ I4::splat(i32::MIN)).from_bits()
    }
}

impl F4 {
    /// |x| per lane.
    #[inline(always)]
    pub fn abs(self) -> F4 {
        (self.bits() & I4::splat(i32::MAX)).from_bits()
    }

    /// Rounded down, per lane, as [`crate::math::floor`] (the sign of a zero kept; from 2^23
    /// on every f32 is whole and is kept).
    #[inline(always)]
    pub fn floor(self) -> F4 {
        let t = self.trunc_i4().to_f4();
        let down = self.lt(t).select(t - F4::splat(1.0), t);
        let down = (down.abs().bits() | (self.bits() & I4::splat(i32::MIN))).from_bits();
        self.abs().lt(F4::splat(8_388_608.0)).select(down, self)
    }

    /// [`crate::math::fast_atan2`] per lane, bit for bit (the same operations in the same
    /// order, both quotients computed and one kept).
    #[inline(always)]
    pub fn atan2(y: F4, x: F4) -> F4 {
        let s = F4::splat;
        let (ax, ay) = (x.abs(), y.abs());
        let steep = ax.lt(ay);
        let (num, den) = (steep.select(ax, ay), steep.select(ay, ax));
        let a = den.eq(s(0.0)).select(s(0.0) * num, num / den);
        let z = a * a;
        let mut p = s(crate::math::ATAN_C[7]);
        for &c in crate::math::ATAN_C[..7].iter().rev() {
            p = p * z + s(c);
        }
        let r = a * p;
        let r = steep.select(s(std::f32::consts::FRAC_PI_2) - r, r);
        // x's sign bit spread over its lane (`is_sign_negative`).
        let negative_x = I4::splat(0) - x.bits().shr::<31>();
        let r = negative_x.select(s(std::f32::consts::PI) - r, r);
        ((r.bits() & I4::splat(i32::MAX)) | (y.bits() & I4::splat(i32::MIN))).from_bits()
    }

    /// [`crate::math::sin_cos_2pi`] per lane, bit for bit (the same operations in the same
    /// order), for |u| < 2^29 (where the quarter turn fits an i32 both ways): `(sin, cos)` of
    /// 2 pi u. One call gives the environment map's two angles together.
    #[inline(always)]
    pub fn sin_cos_2pi(u: F4) -> (F4, F4) {
        let s = F4::splat;
        let t = s(4.0) * u;
        let q = t.floor();
        let f = t - q;
        let a = f.min(s(1.0) - f) * s(std::f32::consts::FRAC_PI_2);
        let z = a * a;
        let mut ps = s(1.0 / 362_880.0);
        for c in [-1.0 / 5040.0, 1.0 / 120.0, -1.0 / 6.0, 1.0] {
            ps = ps * z + s(c);
        }
        let sin = a * ps;
        let mut pc = s(-1.0 / 3_628_800.0);
        for c in [1.0 / 40_320.0, -1.0 / 720.0, 1.0 / 24.0, -0.5, 1.0] {
            pc = pc * z + s(c);
        }
        let q = q.trunc_i4();
        // Swap where exactly one of "upper half of the quarter" and "odd quarter" holds.
        let odd = I4::splat(0) - (q & I4::splat(1));
        let swap = s(0.5).lt(f) ^ odd;
        let x = (sin.bits() ^ pc.bits()) & swap;
        let (sin, cos) = ((sin.bits() ^ x), (pc.bits() ^ x));
        // Quarter turns 2 and 3 negate the sine, 1 and 2 the cosine.
        let sign = |v: I4, q: I4| (v ^ (q & I4::splat(2)).shl::<30>()).from_bits();
        (sign(sin, q), sign(cos, q + I4::splat(1)))
    }

    /// e^x per lane, within 1e-7 relative (`exp_and_ln_are_the_librarys`): e^x = 2^n e^r with n =
    /// x log2(e) rounded (by the 1.5 * 2^23 trick, exact in this range) and r = x - n ln 2 in
    /// two parts (Cody and Waite), e^r by a degree-7 minimax polynomial on |r| <= ln(2) / 2, and
    /// 2^n built in the exponent bits. Below -87 (f32 turns subnormal below -87.34) it gives 0, above
    /// 88 e^88 (1.65e38) rather than infinity; NaN gives NaN.
    #[inline(always)]
    pub fn exp(self) -> F4 {
        let s = F4::splat;
        let round = s(12_582_912.0); // 1.5 * 2^23
        let x = self.max(s(-87.0)).min(s(88.0)); // a NaN becomes a number here; restored below
        let n = (x * s(std::f32::consts::LOG2_E) + round) - round;
        let r = (x - n * s(0.693_359_4)) - n * s(-2.121_944_4e-4);
        let mut p = s(1.987_569_1e-4);
        for c in [1.398_199_9e-3, 8.333_452e-3, 4.166_579_6e-2, 0.166_666_65, 0.5] {
            p = p * r + s(c);
        }
        let e = p * (r * r) + r + s(1.0);
        let scale = (n.trunc_i4() + I4::splat(127)).shl::<23>().from_bits();
        let v = self.lt(s(-87.0)).select(s(0.0), e * scale);
        self.eq(self).select(v, self)
    }

    /// ln x per lane, within 1e-7 (relative, or absolute near x = 1) for positive normal x:
    /// x = 2^e m with m in [sqrt(1/2), sqrt(2)), ln m = f - f^2 / 2 + f^3 P(f) for f = m - 1 (a
    /// degree-8 minimax polynomial), and e ln 2 added in two parts. 0 gives -infinity, a
    /// negative number or NaN gives NaN, infinity gives infinity; subnormals are not handled
    /// (they read as about 2^-127 times their mantissa).
    #[inline(always)]
    pub fn ln(self) -> F4 {
        let s = F4::splat;
        let bits = self.bits();
        let m = ((bits & I4::splat(0x007f_ffff)) | I4::splat(0x3f80_0000)).from_bits();
        let e = (bits.shr::<23>() & I4::splat(0xff)).to_f4() - s(127.0);
        let big = s(std::f32::consts::SQRT_2).lt(m);
        let m = big.select(m * s(0.5), m);
        let e = big.select(e + s(1.0), e);
        let f = m - s(1.0);
        let z = f * f;
        let mut p = s(7.037_683_6e-2);
        for c in [
            -0.115_146_1,
            0.116_769_98,
            -0.124_201_41,
            0.142_493_23,
            -0.166_680_58,
            0.200_007_15,
            -0.249_999_94,
            0.333_333_3,
        ] {
            p = p * f + s(c);
        }
        let y = f * z * p + e * s(-2.121_944_4e-4) - s(0.5) * z;
        let v = f + y + e * s(0.693_359_4);
        let v = self.eq(s(f32::INFINITY)).select(self, v);
        let v = s(0.0).lt(self).select(v, s(f32::NAN));
        self.eq(s(0.0)).select(s(f32::NEG_INFINITY), v)
    }
}

/// [`F4::atan2`] on eight lanes (AVX): the same operations in the same order, so each lane is
/// [`crate::math::fast_atan2`] bit for bit.
///
/// # Safety
/// The CPU must run AVX.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub unsafe fn atan2_avx(y: __m256, x: __m256) -> __m256 {
    use _mm256_set1_ps as s;
    let sign = s(-0.0);
    let (ax, ay) = (_mm256_andnot_ps(sign, x), _mm256_andnot_ps(sign, y));
    let steep = _mm256_cmp_ps::<_CMP_LT_OQ>(ax, ay);
    let (num, den) = (_mm256_blendv_ps(ay, ax, steep), _mm256_blendv_ps(ax, ay, steep));
    let zero_den = _mm256_cmp_ps::<_CMP_EQ_OQ>(den, s(0.0));
    let a = _mm256_blendv_ps(_mm256_div_ps(num, den), _mm256_mul_ps(s(0.0), num), zero_den);
    let z = _mm256_mul_ps(a, a);
    let mut p = s(crate::math::ATAN_C[7]);
    for &c in crate::math::ATAN_C[..7].iter().rev() {
        p = _mm256_add_ps(_mm256_mul_ps(p, z), s(c));
    }
    let r = _mm256_mul_ps(a, p);
    let r = _mm256_blendv_ps(r, _mm256_sub_ps(s(std::f32::consts::FRAC_PI_2), r), steep);
    // Where x's sign bit is set (the blend reads only that bit).
    let r = _mm256_blendv_ps(r, _mm256_sub_ps(s(std::f32::consts::PI), r), x);
    _mm256_or_ps(_mm256_andnot_ps(sign, r), _mm256_and_ps(sign, y))
}

/// [`crate::math::square_to_uniform_disk_concentric`] of eight points (`ux`, `uy`) of the unit
/// square (AVX): the same operations in the same order (its sine and cosine are
/// `math::sin_cos_octant`'s polynomials), so each lane is the scalar map's bit for bit.
///
/// # Safety
/// The CPU must run AVX.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub unsafe fn disk_concentric_avx(ux: __m256, uy: __m256) -> [__m256; 2] {
    use _mm256_add_ps as add;
    use _mm256_mul_ps as mul;
    use _mm256_set1_ps as s;
    use _mm256_sub_ps as sub;
    let zero = _mm256_setzero_ps();
    let x = sub(mul(s(2.0), ux), s(1.0));
    let y = sub(mul(s(2.0), uy), s(1.0));
    let centre = _mm256_and_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(x, zero), _mm256_cmp_ps::<_CMP_EQ_OQ>(y, zero));
    let sign = s(-0.0);
    let steep = _mm256_cmp_ps::<_CMP_LE_OQ>(_mm256_andnot_ps(sign, x), _mm256_andnot_ps(sign, y));
    let (num, r) = (_mm256_blendv_ps(y, x, steep), _mm256_blendv_ps(x, y, steep));
    let a = mul(s(std::f32::consts::FRAC_PI_4), _mm256_div_ps(num, r));
    let z = mul(a, a);
    let sin = add(s(-1.0 / 5040.0), mul(z, s(1.0 / 362_880.0)));
    let sin = add(s(1.0 / 120.0), mul(z, sin));
    let sin = add(s(-1.0 / 6.0), mul(z, sin));
    let sin = mul(a, add(s(1.0), mul(z, sin)));
    let cos = add(s(1.0 / 40_320.0), mul(z, s(-1.0 / 3_628_800.0)));
    let cos = add(s(-1.0 / 720.0), mul(z, cos));
    let cos = add(s(1.0 / 24.0), mul(z, cos));
    let cos = add(s(-0.5), mul(z, cos));
    let cos = add(s(1.0), mul(z, cos));
    let (sin, cos) = (_mm256_blendv_ps(sin, cos, steep), _mm256_blendv_ps(cos, sin, steep));
    // The centre maps to (0, 0), as the scalar map returns early there.
    [_mm256_blendv_ps(mul(r, cos), zero, centre), _mm256_blendv_ps(mul(r, sin), zero, centre)]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// sin_cos_2pi's lanes are the scalar function's bits: on a fine grid over [0, 1), the
    /// quarter-turn and octant edges, random numbers up to 2^20, and negative ones.
    #[test]
    fn sin_cos_2pi_lanes_are_the_scalar_function() {
        let mut us: Vec<f32> = (0..1 << 16).map(|k| k as f32 / 65_536.0).collect();
        for k in 0..=8 {
            let e = k as f32 / 8.0;
            us.extend([e, f32::from_bits(e.to_bits() + 1), f32::from_bits(e.to_bits().max(1) - 1), -e]);
        }
        us.push(1.0 - f32::EPSILON / 2.0);
        let mut h = 0x2545_f491u32;
        for _ in 0..100_000 {
            h ^= h << 13;
            h ^= h >> 17;
            h ^= h << 5;
            let x = (h >> 8) as f32 / (1u32 << 24) as f32;
            us.extend([x, x * 1024.0, -x * 3.0, x * 1_048_576.0]);
        }
        for u in us.chunks(4) {
            let mut lanes = [0.0; 4];
            lanes[..u.len()].copy_from_slice(u);
            let (s, c) = F4::sin_cos_2pi(F4::new(lanes));
            for j in 0..u.len() {
                let (ws, wc) = crate::math::sin_cos_2pi(u[j]);
                let (gs, gc) = (s.to_array()[j], c.to_array()[j]);
                assert!(
                    gs.to_bits() == ws.to_bits() && gc.to_bits() == wc.to_bits(),
                    "u = {:e}: lanes ({gs:e}, {gc:e}), scalar ({ws:e}, {wc:e})",
                    u[j]
                );
            }
        }
    }

    /// exp and ln against f64's, over their whole range: within 1e-7 (8.1e-8 and 7.9e-8
    /// measured), and their edge values, in every lane.
    #[test]
    fn exp_and_ln_are_the_librarys() {
        let exp = |x: f32| F4::new([x, 0.0, x, 1.0]).exp().to_array()[2];
        let ln = |x: f32| F4::new([1.0, x, 2.0, x]).ln().to_array()[3];
        let mut worst = (0.0f64, 0.0f64);
        let mut x = -87.0f32;
        while x < 88.0 {
            worst.0 = worst.0.max((exp(x) as f64 / (x as f64).exp() - 1.0).abs());
            x += 0.000_37;
        }
        let mut x = f32::MIN_POSITIVE;
        while x < 1e38 {
            let (got, want) = (ln(x) as f64, (x as f64).ln());
            worst.1 = worst.1.max((got - want).abs() / want.abs().max(1.0));
            x *= 1.000_173;
        }
        for k in 0..100_000 {
            let x = 0.5 + k as f32 * 1e-5; // around 1, where ln is near 0
            let (got, want) = (ln(x) as f64, (x as f64).ln());
            worst.1 = worst.1.max((got - want).abs() / want.abs().max(x as f64 * 1e-7));
        }
        assert!(worst.0 < 1e-7 && worst.1 < 1e-7, "exp {:e}, ln {:e}", worst.0, worst.1);
        let all = |v: F4, f: fn(f32) -> bool| v.to_array().into_iter().all(f);
        assert!(all(F4::splat(0.0).exp(), |v| v == 1.0));
        assert!(all(F4::splat(-100.0).exp(), |v| v == 0.0));
        assert!(all(F4::splat(100.0).exp(), |v| v.is_finite() && v > 1e38));
        assert!(all(F4::splat(f32::NAN).exp(), f32::is_nan));
        assert!(all(F4::splat(1.0).ln(), |v| v == 0.0));
        assert!(all(F4::splat(0.0).ln(), |v| v == f32::NEG_INFINITY));
        assert!(all(F4::splat(-1.0).ln(), f32::is_nan));
        assert!(all(F4::splat(f32::NAN).ln(), f32::is_nan));
        assert!(all(F4::splat(f32::INFINITY).ln(), |v| v == f32::INFINITY));
    }

    /// floor, abs, min, max, select and negation lane by lane against the scalar operations.
    #[test]
    fn lanes_follow_the_scalar_operations() {
        let xs = [-2.5f32, -0.0, 0.3, 1.0, -1.0, 7.9, -8_388_609.0, 1e30, -1e-40, 3.5e6];
        for w in xs.windows(4) {
            let (a, b) = (F4::new([w[0], w[1], w[2], w[3]]), F4::new([w[3], w[2], w[1], w[0]]));
            let (fa, fb) = (a.to_array(), b.to_array());
            for i in 0..4 {
                assert_eq!(a.floor().to_array()[i].to_bits(), crate::math::floor(fa[i]).to_bits());
                assert_eq!(a.abs().to_array()[i], fa[i].abs());
                assert_eq!((-a).to_array()[i].to_bits(), (-fa[i]).to_bits());
                assert_eq!(a.min(b).to_array()[i], if fa[i] < fb[i] { fa[i] } else { fb[i] });
                assert_eq!(a.max(b).to_array()[i], if fa[i] > fb[i] { fa[i] } else { fb[i] });
                let sel = a.le(b).select(a, b).to_array()[i];
                assert_eq!(sel, if fa[i] <= fb[i] { fa[i] } else { fb[i] });
            }
        }
    }

    /// atan2 lane by lane against `fast_atan2`, bit for bit: signed zeros, infinities, NaN,
    /// equal magnitudes and a spread of random pairs.
    #[test]
    fn atan2_lanes_are_fast_atan2() {
        let special = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            0.5,
            -3.0,
            1e-40,
            -1e-40,
            1e30,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let mut pairs: Vec<(f32, f32)> =
            special.iter().flat_map(|&y| special.iter().map(move |&x| (y, x))).collect();
        let mut rng = crate::testing::Pcg::new(11);
        pairs.extend((0..100_000).map(|_| (rng.next_f32() * 4.0 - 2.0, rng.next_f32() * 4.0 - 2.0)));
        for c in pairs.chunks(4) {
            let lane = |k: usize| c.get(k).copied().unwrap_or((1.0, 1.0));
            let y = F4::new(std::array::from_fn(|k| lane(k).0));
            let x = F4::new(std::array::from_fn(|k| lane(k).1));
            let got = F4::atan2(y, x).to_array();
            for (k, g) in got.iter().enumerate() {
                let (yk, xk) = lane(k);
                assert_eq!(g.to_bits(), crate::math::fast_atan2(yk, xk).to_bits(), "atan2({yk}, {xk})");
            }
        }
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx") {
            for c in pairs.chunks(8) {
                let lane = |k: usize| c.get(k).copied().unwrap_or((1.0, 1.0));
                let (y, x): ([f32; 8], [f32; 8]) =
                    (std::array::from_fn(|k| lane(k).0), std::array::from_fn(|k| lane(k).1));
                let mut got = [0.0f32; 8];
                // SAFETY: the CPU runs AVX (checked above); the arrays hold eight floats.
                unsafe { avx_atan2_into(&y, &x, &mut got) };
                for (k, g) in got.iter().enumerate() {
                    let (yk, xk) = lane(k);
                    assert_eq!(
                        g.to_bits(),
                        crate::math::fast_atan2(yk, xk).to_bits(),
                        "AVX atan2({yk}, {xk})"
                    );
                }
            }
        }
    }

    /// The 8-lane concentric map is the scalar one bit for bit: a 33 x 33 grid (its centre,
    /// both diagonals, where the map switches sides, and the square's edges) and random points.
    #[test]
    fn disk_concentric_lanes_are_the_scalar_map() {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx") {
            let mut pts: Vec<(f32, f32)> =
                (0..=32).flat_map(|i| (0..=32).map(move |j| (i as f32 / 32.0, j as f32 / 32.0))).collect();
            let mut rng = crate::testing::Pcg::new(13);
            pts.extend((0..20_000).map(|_| (rng.next_f32(), rng.next_f32())));
            for c in pts.chunks(8) {
                let lane = |k: usize| c.get(k).copied().unwrap_or((0.5, 0.5));
                let (u, v): ([f32; 8], [f32; 8]) =
                    (std::array::from_fn(|k| lane(k).0), std::array::from_fn(|k| lane(k).1));
                let (mut x, mut y) = ([0.0f32; 8], [0.0f32; 8]);
                // SAFETY: the CPU runs AVX (checked above); the arrays hold eight floats.
                unsafe { avx_disk_into(&u, &v, &mut x, &mut y) };
                for k in 0..c.len() {
                    let want = crate::math::square_to_uniform_disk_concentric(glam::Vec2::new(u[k], v[k]));
                    assert_eq!(
                        (x[k].to_bits(), y[k].to_bits()),
                        (want.x.to_bits(), want.y.to_bits()),
                        "{:?}",
                        c[k]
                    );
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn avx_disk_into(u: &[f32; 8], v: &[f32; 8], x: &mut [f32; 8], y: &mut [f32; 8]) {
        let [dx, dy] = super::disk_concentric_avx(_mm256_loadu_ps(u.as_ptr()), _mm256_loadu_ps(v.as_ptr()));
        _mm256_storeu_ps(x.as_mut_ptr(), dx);
        _mm256_storeu_ps(y.as_mut_ptr(), dy);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn avx_atan2_into(y: &[f32; 8], x: &[f32; 8], out: &mut [f32; 8]) {
        let r = super::atan2_avx(_mm256_loadu_ps(y.as_ptr()), _mm256_loadu_ps(x.as_ptr()));
        _mm256_storeu_ps(out.as_mut_ptr(), r);
    }
}
