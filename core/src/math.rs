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

/// `y.atan2(x)` to within about 4e-7 rad (2 ulp of a result near pi), without a library call: the
/// octant's ratio min/max in [0, 1], atan of it by an odd polynomial of degree 15 (fitted for
/// least maximum relative error on [0, 1]), and the octant's reflections. Signed zeros and
/// NaN follow libm (`atan2(+-0, -0) = +-pi`, NaN in gives NaN); both infinite gives NaN (libm:
/// a multiple of pi/4), which unit directions never are. The environment map's and the hair
/// BSDF's angles spend this on every lookup.
#[inline]
pub fn fast_atan2(y: f32, x: f32) -> f32 {
    const C: [f32; 8] = [
        0.999_999_9,
        -0.333_319_9,
        0.199_696_91,
        -0.140_192_63,
        0.099_136_17,
        -0.059_475_78,
        0.024_244_2,
        -0.004_690_802,
    ];
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
    let (p, p_err, n, w) =
        (glam::Vec3A::from(p), glam::Vec3A::from(p_err), glam::Vec3A::from(n), glam::Vec3A::from(w));
    let d = n.abs().dot(p_err);
    let mut offset = n * d;
    if w.dot(n) < 0.0 {
        offset = -offset;
    }
    let mut po = (p + offset).to_array();
    let off = offset.to_array();
    for i in 0..3 {
        if off[i] > 0.0 {
            po[i] = next_float_up(po[i]);
        } else if off[i] < 0.0 {
            po[i] = next_float_down(po[i]);
        }
    }
    Vec3::from_array(po)
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
    let (r, phi) =
        if x.abs() > y.abs() { (x, (PI / 4.0) * (y / x)) } else { (y, (PI / 2.0) - (PI / 4.0) * (x / y)) };
    let (s, c) = phi.sin_cos();
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
    let (s, c) = (2.0 * PI * u.x).sin_cos();
    Vec3::new(r * c, r * s, z)
}

/// Uniform direction inside the cone of half-angle acos(`cos_max`) around +z;
/// pdf = 1 / (2 pi (1 - cos_max)).
#[inline]
pub fn square_to_uniform_cone(u: Vec2, cos_max: f32) -> Vec3 {
    let cos_t = (1.0 - u.y) + u.y * cos_max;
    let sin_t = safe_sqrt(1.0 - cos_t * cos_t);
    let (s, c) = (2.0 * PI * u.x).sin_cos();
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

/// Hash of several words, order-sensitive.
#[inline]
pub fn hash_words(words: &[u32]) -> u32 {
    let mut h = 0x9e37_79b9u32;
    for &w in words {
        h = hash_u32(h ^ w.wrapping_add(0x9e37_79b9).wrapping_add(h << 6).wrapping_add(h >> 2));
    }
    h
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
