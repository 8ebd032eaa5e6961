//! Small numeric helpers shared by the whole renderer: guarded inverse trig, frames, warps,
//! floating-point error bounds (pbrt 3rd ed., section 3.9) and colour conversion.

pub use glam::{Mat3, Mat4, Vec2, Vec3, Vec4};

/// Linear Rec.709 RGB radiance.
pub type Rgb = Vec3;

pub const PI: f32 = std::f32::consts::PI;
pub const INV_PI: f32 = std::f32::consts::FRAC_1_PI;
pub const INV_TWO_PI: f32 = 0.5 * std::f32::consts::FRAC_1_PI;
pub const INV_FOUR_PI: f32 = 0.25 * std::f32::consts::FRAC_1_PI;

/// `sqrt` that returns 0 for (slightly) negative arguments produced by rounding.
#[inline]
pub fn safe_sqrt(x: f32) -> f32 {
    x.max(0.0).sqrt()
}

/// `acos` with its argument clamped to [-1, 1].
#[inline]
pub fn safe_acos(x: f32) -> f32 {
    x.clamp(-1.0, 1.0).acos()
}

/// `asin` with its argument clamped to [-1, 1].
#[inline]
pub fn safe_asin(x: f32) -> f32 {
    x.clamp(-1.0, 1.0).asin()
}

/// [`fast_atan2`]'s polynomial in (y / x)^2, constant term first.
pub(crate) const ATAN_C: [f32; 8] = [
    0.999_999_9,
    -0.333_319_9,
    0.199_696_91,
    -0.140_192_63,
    0.099_136_17,
    -0.059_475_78,
    0.024_244_2,
    -0.004_690_802,
];

/// `y.atan2(x)` to within about 4e-7 rad (2 ulp of a result near pi), without a library call: the
/// octant's ratio min/max in [0, 1], atan of it by an odd polynomial of degree 15 (fitted for
/// least maximum relative error on [0, 1]), and the octant's reflections. Signed zeros and
/// NaN follow libm (`atan2(+-0, -0) = +-pi`, NaN in gives NaN); both infinite gives NaN (libm:
/// a multiple of pi/4), which unit directions never are. The environment map's and the hair
/// BSDF's angles spend this on every lookup.
#[inline]
pub fn fast_atan2(y: f32, x: f32) -> f32 {
    const C: [f32; 8] = ATAN_C;
    let (ax, ay) = (x.abs(), y.abs());
    let steep = ay > ax;
    let (num, den) = if steep { (ax, ay) } else { (ay, ax) };
    let a = if den == 0.0 { 0.0 * num } else { num / den }; // 0 * NaN keeps a NaN
    let z = a * a;
    let mut p = C[7];
    for &c in C[..7].iter().rev() {
        p = p * z + c;
    }
    let mut r = a * p;
    if steep {
        r = std::f32::consts::FRAC_PI_2 - r;
    }
    if x.is_sign_negative() {
        r = PI - r;
    }
    r.copysign(y)
}

/// `if c { a } else { b }` by masks: the hot warps choose on the sample's own bits, which a
/// branch would mispredict half the time.
#[inline]
fn select(c: bool, a: f32, b: f32) -> f32 {
    let m = (c as u32).wrapping_neg();
    f32::from_bits((a.to_bits() & m) | (b.to_bits() & !m))
}

/// `(b, a)` if `c`, else `(a, b)`, by masks (see [`select`]).
#[inline]
fn swap_if(c: bool, a: f32, b: f32) -> (f32, f32) {
    let x = (a.to_bits() ^ b.to_bits()) & (c as u32).wrapping_neg();
    (f32::from_bits(a.to_bits() ^ x), f32::from_bits(b.to_bits() ^ x))
}

/// `x.floor()`, bit for bit (signed zeros too; NaN gives NaN), without the library call that baseline
/// x86-64 (no SSE4.1 `roundss`) makes of it: truncate natively, step down where that rounded
/// up. From 2^23 on every f32 is whole. Texture and environment lookups, the film's filter
/// footprint and the azimuth warps spend this on every sample.
#[inline]
pub fn floor(x: f32) -> f32 {
    if x.abs() < 8_388_608.0 {
        let t = x as i32 as f32;
        (t - select(t > x, 1.0, 0.0)).copysign(x)
    } else {
        x
    }
}

/// `x.ceil()`, bit for bit, as `-floor(-x)`.
#[inline]
pub fn ceil(x: f32) -> f32 {
    -floor(-x)
}

/// sin and cos of `a` in [-pi/4, pi/4], by their Taylor series through a^9 and a^10: the first
/// terms left out are below 2e-9 and 1.2e-10 there, far under f32's rounding.
#[inline]
fn sin_cos_octant(a: f32) -> (f32, f32) {
    let z = a * a;
    let s = a * (1.0 + z * (-1.0 / 6.0 + z * (1.0 / 120.0 + z * (-1.0 / 5040.0 + z * (1.0 / 362_880.0)))));
    let c = 1.0
        + z * (-0.5
            + z * (1.0 / 24.0 + z * (-1.0 / 720.0 + z * (1.0 / 40_320.0 + z * (-1.0 / 3_628_800.0)))));
    (s, c)
}

/// `(sin, cos)` of 2 pi `u`, within about 1.5e-7 of the exact values, without a library call
/// and without branches on `u`: the quarter turn is 4u's whole part and the angle within it
/// its fraction (both exact for u >= 0), folded to [0, pi/4]; the folds and quarter turns swap and
/// negate. The warps that turn a uniform number into an azimuth spend this on every sample.
#[inline]
pub fn sin_cos_2pi(u: f32) -> (f32, f32) {
    let t = 4.0 * u;
    let q = floor(t);
    let f = t - q;
    let (s, c) = sin_cos_octant(f.min(1.0 - f) * std::f32::consts::FRAC_PI_2);
    // An odd quarter turn swaps the pair, as does the upper half of a quarter: swap when
    // exactly one of them holds.
    let q = q as i32 as u32;
    let (s, c) = swap_if((f > 0.5) != (q & 1 != 0), s, c);
    // sin < 0 in the third and fourth quarters, cos < 0 in the second and third.
    let sign = |v: f32, bit: u32| f32::from_bits(v.to_bits() ^ ((bit & 2) << 30));
    (sign(s, q), sign(c, q.wrapping_add(1)))
}

/// Rec.709 luminance of a linear RGB colour.
#[inline]
pub fn luminance(c: Rgb) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// [`luminance`] in f64: finite texels near f32's limit, or scaled up, do not overflow.
#[inline]
pub fn luminance_f64(c: Rgb) -> f64 {
    0.2126 * c.x as f64 + 0.7152 * c.y as f64 + 0.0722 * c.z as f64
}

/// Conservative bound on the relative rounding error of `n` chained f32 operations
/// (pbrt 3rd ed., eq. 3.9: gamma_n = n eps / (1 - n eps), eps = 2^-24).
#[inline]
pub const fn gamma(n: i32) -> f32 {
    let e = f32::EPSILON * 0.5;
    (n as f32 * e) / (1.0 - n as f32 * e)
}

/// The next representable f32 above `v` (towards +inf).
#[inline]
pub fn next_float_up(v: f32) -> f32 {
    if v.is_infinite() && v > 0.0 {
        return v;
    }
    let v = if v == -0.0 { 0.0 } else { v };
    let bits = v.to_bits();
    let bits = if v >= 0.0 { bits + 1 } else { bits - 1 };
    f32::from_bits(bits)
}

/// The next representable f32 below `v` (towards -inf).
#[inline]
pub fn next_float_down(v: f32) -> f32 {
    if v.is_infinite() && v < 0.0 {
        return v;
    }
    let v = if v == 0.0 { -0.0 } else { v };
    let bits = v.to_bits();
    let bits = if v > 0.0 { bits - 1 } else { bits + 1 };
    f32::from_bits(bits)
}

/// Offsets a ray origin `p` with absolute error bound `p_err` along the geometric normal `n`,
/// to the side of `w`, far enough that the new origin cannot re-intersect the surface it lies on
/// (pbrt 3rd ed., section 3.9.5), then rounds each component away from the surface.
#[inline]
pub fn offset_ray_origin(p: Vec3, p_err: Vec3, n: Vec3, w: Vec3) -> Vec3 {
    // Vec3A: lane for lane Vec3's operations (the same bits) in fewer instructions.
    let (p, p_err, n, w) = (lanes(p), lanes(p_err), lanes(n), glam::Vec3A::from(w));
    let d = n.abs().dot(p_err);
    let mut offset = n * d;
    if w.dot(n) < 0.0 {
        offset = -offset;
    }
    round_away(p + offset, offset)
}

/// `v` read a coordinate at a time. The compiler would otherwise read a vector that has just
/// been stored in pieces with one wide load across the pieces (a hit record's 16-byte `p`
/// across two 16-byte stores of the record's copy; a sample's 12-byte radiance with an
/// 8-byte load at its second coordinate): such a load cannot take its value from the stores
/// in flight and waits for them to complete (a failed store forward), which cost a third of
/// the integrator's time on textured.xml and a fifth of `render_region`'s on envmap.xml. The
/// empty `asm` hands the three numbers over in registers, so the loads stay apart (as the
/// compiler builds it today: nothing obliges it not to load wide and shuffle, so a timing
/// regression there is the first thing to look for).
#[inline(always)]
pub fn apart(v: Vec3) -> Vec3 {
    #[cfg(target_arch = "x86_64")]
    {
        let (mut x, mut y, mut z) = (v.x, v.y, v.z);
        // SAFETY: an empty instruction sequence; it reads and writes only these registers.
        unsafe {
            std::arch::asm!("/* {0} {1} {2} */", inout(xmm_reg) x, inout(xmm_reg) y, inout(xmm_reg) z,
                options(pure, nomem, nostack, preserves_flags));
        }
        Vec3::new(x, y, z)
    }
    #[cfg(not(target_arch = "x86_64"))]
    v
}

/// `*v` loaded a coordinate at a time, for a vector that may have just been stored in pieces
/// (a ray made a moment before): [`apart`] keeps the coordinates apart once loaded, but the
/// compiler may still load two of them with one 8-byte read, which waits for both stores to
/// complete. Three separate 4-byte reads (volatile, so that they are not merged) each take
/// their value from the store in flight.
#[inline(always)]
pub fn load_apart(v: &Vec3) -> Vec3 {
    // SAFETY: reads of three f32 fields of a live, aligned reference.
    unsafe {
        Vec3::new(std::ptr::read_volatile(&v.x), std::ptr::read_volatile(&v.y), std::ptr::read_volatile(&v.z))
    }
}

/// [`apart`] for a `Vec2`: its two coordinates read one at a time.
#[inline(always)]
pub fn apart2(v: Vec2) -> Vec2 {
    #[cfg(target_arch = "x86_64")]
    {
        let (mut x, mut y) = (v.x, v.y);
        // SAFETY: an empty instruction sequence; it reads and writes only these registers.
        unsafe {
            std::arch::asm!("/* {0} {1} */", inout(xmm_reg) x, inout(xmm_reg) y,
                options(pure, nomem, nostack, preserves_flags));
        }
        Vec2::new(x, y)
    }
    #[cfg(not(target_arch = "x86_64"))]
    v
}

/// [`apart`], in a register's lanes.
#[inline(always)]
fn lanes(v: Vec3) -> glam::Vec3A {
    glam::Vec3A::from(apart(v))
}

/// Each lane of `po` rounded one step up where `off` is positive ([`next_float_up`]) and one
/// down where it is negative ([`next_float_down`]), bit for bit; kept where `off` is 0 or NaN.
/// On x86-64 in SSE2 lanes, without the branches (their direction follows the ray's).
#[inline(always)]
fn round_away(po: glam::Vec3A, off: glam::Vec3A) -> Vec3 {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE2 is part of x86-64.
    unsafe {
        use std::arch::x86_64::*;
        let (v, o) = (__m128::from(po), __m128::from(off));
        let zero = _mm_setzero_ps();
        let is_zero = _mm_cmpeq_ps(v, zero);
        // next_float_up: a zero of either sign becomes +0, then one step away from it in the
        // direction of +inf (bits + 1 from +0 and positives, - 1 from negatives and NaN); +inf
        // stays.
        let up_from = _mm_andnot_ps(is_zero, v);
        let up_pos = _mm_castps_si128(_mm_cmpge_ps(up_from, zero)); // -1 where >= 0
        let up = _mm_sub_epi32(_mm_castps_si128(up_from), _mm_or_si128(up_pos, _mm_set1_epi32(1)));
        // (bits - (-1 | 1)): + 1 where >= 0, - 1 elsewhere.
        let up = _mm_castsi128_ps(up);
        let up = select_ps(_mm_cmpeq_ps(v, _mm_set1_ps(f32::INFINITY)), v, up);
        // next_float_down: a zero becomes -0, then bits - 1 from positives, + 1 from -0,
        // negatives and NaN; -inf stays.
        let down_from = _mm_or_ps(_mm_and_ps(is_zero, _mm_set1_ps(-0.0)), _mm_andnot_ps(is_zero, v));
        let down_pos = _mm_castps_si128(_mm_cmpgt_ps(down_from, zero)); // -1 where > 0
        let down = _mm_add_epi32(_mm_castps_si128(down_from), _mm_or_si128(down_pos, _mm_set1_epi32(1)));
        let down = _mm_castsi128_ps(down);
        let down = select_ps(_mm_cmpeq_ps(v, _mm_set1_ps(f32::NEG_INFINITY)), v, down);
        let r = select_ps(_mm_cmpgt_ps(o, zero), up, select_ps(_mm_cmplt_ps(o, zero), down, v));
        let mut a = [0.0f32; 4];
        _mm_storeu_ps(a.as_mut_ptr(), r);
        Vec3::new(a[0], a[1], a[2])
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let (mut po, off) = (po.to_array(), off.to_array());
        for i in 0..3 {
            if off[i] > 0.0 {
                po[i] = next_float_up(po[i]);
            } else if off[i] < 0.0 {
                po[i] = next_float_down(po[i]);
            }
        }
        Vec3::from_array(po)
    }
}

/// Per lane, `a` where the mask `m` is set, else `b`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn select_ps(
    m: std::arch::x86_64::__m128,
    a: std::arch::x86_64::__m128,
    b: std::arch::x86_64::__m128,
) -> std::arch::x86_64::__m128 {
    use std::arch::x86_64::*;
    _mm_or_ps(_mm_and_ps(m, a), _mm_andnot_ps(m, b))
}

/// Orthonormal basis whose third axis is the shading normal; `to_local` maps world directions
/// into it, so that `cos theta = v.z`.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    /// Builds a frame around `n` (unit) without a preferred tangent (Duff et al. 2017).
    pub fn from_normal(n: Vec3) -> Frame {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Frame { s, t, n }
    }

    /// Builds a frame around `n` whose first axis follows the tangent `dpdu` (Gram-Schmidt);
    /// falls back to [`Frame::from_normal`] when `dpdu` is degenerate or parallel to `n`.
    pub fn from_normal_tangent(n: Vec3, dpdu: Vec3) -> Frame {
        let s = dpdu - n * n.dot(dpdu);
        let len2 = s.length_squared();
        if !(len2 > 1e-20) || !len2.is_finite() {
            return Frame::from_normal(n);
        }
        let s = s / len2.sqrt();
        Frame { s, t: n.cross(s), n }
    }

    /// The frame with each vector read a coordinate at a time ([`apart`]).
    #[inline(always)]
    pub fn apart(&self) -> Frame {
        Frame { s: apart(self.s), t: apart(self.t), n: apart(self.n) }
    }

    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

/// Shirley-Chiu concentric map of the unit square onto the unit disk.
#[inline]
pub fn square_to_uniform_disk_concentric(u: Vec2) -> Vec2 {
    let x = 2.0 * u.x - 1.0;
    let y = 2.0 * u.y - 1.0;
    if x == 0.0 && y == 0.0 {
        return Vec2::ZERO;
    }
    // phi = pi/4 (y / x), or pi/2 - pi/4 (x / y), whose sin and cos are the cos and sin of
    // pi/4 (x / y).
    let steep = x.abs() <= y.abs();
    let (num, r) = swap_if(steep, y, x);
    let (s, c) = sin_cos_octant(std::f32::consts::FRAC_PI_4 * (num / r));
    let (s, c) = swap_if(steep, s, c);
    Vec2::new(r * c, r * s)
}

/// Cosine-weighted hemisphere around +z (Malley's method); pdf = cos(theta) / pi.
#[inline]
pub fn square_to_cosine_hemisphere(u: Vec2) -> Vec3 {
    let d = square_to_uniform_disk_concentric(u);
    let z = safe_sqrt(1.0 - d.length_squared());
    Vec3::new(d.x, d.y, z)
}

/// Uniform direction on the unit sphere; pdf = 1 / (4 pi).
#[inline]
pub fn square_to_uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.y;
    let r = safe_sqrt(1.0 - z * z);
    let (s, c) = sin_cos_2pi(u.x);
    Vec3::new(r * c, r * s, z)
}

/// Uniform direction inside the cone of half-angle acos(`cos_max`) around +z;
/// pdf = 1 / (2 pi (1 - cos_max)).
#[inline]
pub fn square_to_uniform_cone(u: Vec2, cos_max: f32) -> Vec3 {
    let cos_t = (1.0 - u.y) + u.y * cos_max;
    let sin_t = safe_sqrt(1.0 - cos_t * cos_t);
    let (s, c) = sin_cos_2pi(u.x);
    Vec3::new(sin_t * c, sin_t * s, cos_t)
}

/// Uniform point on a triangle as barycentrics (b0, b1); b2 = 1 - b0 - b1.
#[inline]
pub fn square_to_uniform_triangle(u: Vec2) -> Vec2 {
    let su0 = safe_sqrt(u.x);
    Vec2::new(1.0 - su0, u.y * su0)
}

/// Power heuristic with exponent 2 (Veach 1997, eq. 9.13), written to stay finite when a pdf is
/// infinite or both are 0.
#[inline]
pub fn mis_power(a: f32, b: f32) -> f32 {
    let a2 = a * a;
    let b2 = b * b;
    let w = a2 / (a2 + b2);
    if w.is_finite() {
        w
    } else if a2.is_infinite() {
        1.0
    } else {
        0.0
    }
}

/// sRGB transfer function, encoded -> linear.
#[inline]
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// sRGB transfer function, linear -> encoded.
#[inline]
pub fn linear_to_srgb(v: f32) -> f32 {
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// 32-bit integer hash (Wellons' lowbias32), used to derive decorrelated seeds.
#[inline]
pub fn hash_u32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// Hash of several words, order-sensitive: [`hash_step`] from [`HASH_START`] for each.
#[inline]
pub fn hash_words(words: &[u32]) -> u32 {
    words.iter().fold(HASH_START, |h, &w| hash_step(h, w))
}

/// [`hash_words`]' state before any word.
pub const HASH_START: u32 = 0x9e37_79b9;

/// [`hash_words`]' state `h` after one more word `w`: a hash of words that share their first
/// ones can start from the state after those (`hash_words(&[a, b]) == hash_step(hash_step(HASH_START, a), b)`).
#[inline]
pub fn hash_step(h: u32, w: u32) -> u32 {
    hash_u32(h ^ w.wrapping_add(0x9e37_79b9).wrapping_add(h << 6).wrapping_add(h >> 2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_orthonormal_for_all_normals() {
        for i in 0..1000 {
            let u = Vec2::new((i as f32 * 0.618_034) % 1.0, (i as f32 * 0.414_213) % 1.0);
            let n = square_to_uniform_sphere(u);
            let f = Frame::from_normal(n);
            assert!((f.s.length() - 1.0).abs() < 1e-5);
            assert!((f.t.length() - 1.0).abs() < 1e-5);
            assert!(f.s.dot(f.t).abs() < 1e-5 && f.s.dot(n).abs() < 1e-5);
            let v = Vec3::new(0.3, -0.5, 0.81).normalize();
            assert!((f.to_world(f.to_local(v)) - v).length() < 1e-5);
        }
    }

    #[test]
    fn next_float_moves_one_ulp() {
        assert!(next_float_up(1.0) > 1.0 && next_float_down(1.0) < 1.0);
        assert!(next_float_up(0.0) > 0.0 && next_float_down(0.0) < 0.0);
        assert!(next_float_up(-1.0) > -1.0);
    }

    /// Bit for bit the library's floor and ceil: every f32 between -2^25 and 2^25 in steps that
    /// cross every fraction pattern near the integers, random bit patterns, and the specials.
    #[test]
    fn floor_and_ceil_are_the_librarys() {
        let mut bits = 0x1234_5678u32;
        let mut xs: Vec<f32> = (0..2_000_000)
            .map(|_| {
                bits ^= bits << 13;
                bits ^= bits >> 17;
                bits ^= bits << 5;
                f32::from_bits(bits)
            })
            .collect();
        for k in -300i32..300 {
            for d in [-2i32, -1, 0, 1, 2] {
                let x = k as f32 * 0.5;
                xs.push(f32::from_bits((x.to_bits() as i32 + d) as u32));
                xs.push(f32::from_bits(((x + 8_388_608.0).to_bits() as i32 + d) as u32));
                xs.push(f32::from_bits(((x - 8_388_608.0).to_bits() as i32 + d) as u32));
            }
        }
        xs.extend([
            0.0,
            -0.0,
            1e-45,
            -1e-45,
            0.5,
            -0.5,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ]);
        xs.extend([f32::NAN, 8_388_607.5, -8_388_607.5, 2_147_483_648.0, -2_147_483_904.0]);
        for x in xs {
            if x.is_nan() {
                // NaN gives NaN; its payload bits (a signalling NaN quieted or not) are not
                // something Rust or the library promise.
                assert!(floor(x).is_nan() && ceil(x).is_nan(), "{:#x}", x.to_bits());
                continue;
            }
            assert_eq!(floor(x).to_bits(), x.floor().to_bits(), "floor {x:e} ({:#x})", x.to_bits());
            assert_eq!(ceil(x).to_bits(), x.ceil().to_bits(), "ceil {x:e} ({:#x})", x.to_bits());
        }
    }

    /// Against f64's sin and cos over a fine grid of u, at the octants' ends, outside [0, 1]
    /// and for NaN.
    #[test]
    fn sin_cos_2pi_is_sin_cos() {
        let mut worst = 0.0f64;
        let n = 1 << 20;
        let grid = (0..=n).map(|i| i as f32 / n as f32);
        let odd = [-0.0f32, 1e-30, 0.125, 0.375, 0.5, 0.625, 0.875, 1.0 - f32::EPSILON, -0.3, 2.7];
        for u in grid.chain(odd) {
            let (s, c) = sin_cos_2pi(u);
            let (es, ec) = (std::f64::consts::TAU * u as f64).sin_cos();
            worst = worst.max((s as f64 - es).abs()).max((c as f64 - ec).abs());
        }
        assert!(worst < 1.5e-7, "worst error {worst:e}");
        // Exact at the quarter turns, as the warps' symmetric points should be (in value: a
        // zero there may carry a minus sign).
        assert_eq!(sin_cos_2pi(0.0), (0.0, 1.0));
        assert_eq!(sin_cos_2pi(0.25), (1.0, 0.0));
        assert_eq!(sin_cos_2pi(0.5), (0.0, -1.0));
        assert_eq!(sin_cos_2pi(0.75), (-1.0, 0.0));
        let (s, c) = sin_cos_2pi(f32::NAN);
        assert!(s.is_nan() && c.is_nan());
    }

    #[test]
    fn concentric_disk_is_polar() {
        // Against the map written with f64 trigonometry: the same point to within 2e-7.
        let n = 512;
        // Cell centres, and the grid's own points, which lie on the lines x = 0, y = 0 and
        // x = +-y where the map changes branch.
        for (oi, oj) in [(0.5f32, 0.37f32), (0.0, 0.0)] {
            for i in 0..n {
                for j in 0..n {
                    let u = Vec2::new((i as f32 + oi) / n as f32, (j as f32 + oj) / n as f32);
                    let (x, y) = (2.0 * u.x as f64 - 1.0, 2.0 * u.y as f64 - 1.0);
                    if x == 0.0 && y == 0.0 {
                        continue; // the centre, below
                    }
                    let (r, phi) = if x.abs() > y.abs() {
                        (x, std::f64::consts::FRAC_PI_4 * (y / x))
                    } else {
                        (y, std::f64::consts::FRAC_PI_2 - std::f64::consts::FRAC_PI_4 * (x / y))
                    };
                    let d = square_to_uniform_disk_concentric(u);
                    let e = (d.x as f64 - r * phi.cos()).abs().max((d.y as f64 - r * phi.sin()).abs());
                    assert!(e < 2e-7, "{u}: {d} off by {e:e}");
                }
            }
        }
        assert_eq!(square_to_uniform_disk_concentric(Vec2::splat(0.5)), Vec2::ZERO);
    }

    /// The lanes' rounding away from the surface against the scalar steps, bit for bit: zeros
    /// of both signs, infinities, NaN, subnormals, and offsets of every sign (0 and NaN keep
    /// the lane).
    #[test]
    fn round_away_is_next_float_up_and_down() {
        let vals = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            1e-45,
            -1e-45,
            3.5,
            -7.25e10,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
        ];
        let offs = [1.0f32, -1.0, 0.0, -0.0, f32::NAN, 1e-30];
        let mut rng = crate::testing::Pcg::new(3);
        let mut cases: Vec<([f32; 3], [f32; 3])> = Vec::new();
        for &v in &vals {
            for &o in &offs {
                cases.push(([v, -v, 0.5], [o, -o, o]));
            }
        }
        for _ in 0..20_000 {
            let r = |rng: &mut crate::testing::Pcg| {
                (rng.next_f32() - 0.5) * 10f32.powi((rng.next_u32() % 20) as i32 - 10)
            };
            cases.push(([r(&mut rng), r(&mut rng), r(&mut rng)], [r(&mut rng), r(&mut rng), r(&mut rng)]));
        }
        for (p, o) in cases {
            let got = round_away(glam::Vec3A::from_array(p), glam::Vec3A::from_array(o)).to_array();
            for i in 0..3 {
                let want = if o[i] > 0.0 {
                    next_float_up(p[i])
                } else if o[i] < 0.0 {
                    next_float_down(p[i])
                } else {
                    p[i]
                };
                assert_eq!(got[i].to_bits(), want.to_bits(), "{} offset {}", p[i], o[i]);
            }
        }
    }

    /// Against f64's atan2 over every octant, near the axes and diagonals, with signed zeros
    /// and NaN as libm has them.
    #[test]
    fn fast_atan2_is_atan2() {
        let mut worst = 0.0f64;
        for i in 0..200_000 {
            let phi = (i as f64 + 0.5) / 200_000.0 * std::f64::consts::TAU - std::f64::consts::PI;
            for r in [1.0f64, 1e-20, 3e15] {
                let (y, x) = ((phi.sin() * r) as f32, (phi.cos() * r) as f32);
                let exact = (y as f64).atan2(x as f64);
                worst = worst.max((fast_atan2(y, x) as f64 - exact).abs());
            }
        }
        // The worst found by an exhaustive search over the ratios is 4.0e-7.
        assert!(worst < 4.5e-7, "worst error {worst:e}");
        for (y, x) in [
            (0.0f32, 0.0f32),
            (-0.0, 0.0),
            (0.0, -0.0),
            (-0.0, -0.0),
            (1.0, 0.0),
            (-1.0, 0.0),
            (0.0, -1.0),
            (-0.0, -1.0),
            (1e-30, 1.0),
            (1.0, 1e-30),
            (3.0, -1e-38),
        ] {
            let (f, e) = (fast_atan2(y, x), y.atan2(x));
            assert!(
                (f - e).abs() <= 4e-7 && f.is_sign_negative() == e.is_sign_negative(),
                "atan2({y}, {x}): {f} against {e}"
            );
        }
        assert!(fast_atan2(f32::NAN, 1.0).is_nan() && fast_atan2(1.0, f32::NAN).is_nan());
    }

    #[test]
    fn mis_power_is_finite() {
        assert_eq!(mis_power(0.0, 0.0), 0.0);
        assert_eq!(mis_power(f32::INFINITY, 1.0), 1.0);
        assert!((mis_power(1.0, 1.0) - 0.5).abs() < 1e-7);
    }
}
