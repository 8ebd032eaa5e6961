//! Microfacet distributions: GGX (Trowbridge-Reitz) and Beckmann, anisotropic, with the
//! separable Smith masking term, as Mitsuba uses them (Walter et al. 2007; Heitz 2014).
//!
//! Both sample the distribution of visible normals, D_wo(m) = G1(wo, m) max(0, wo.m) D(m) / wo.z:
//! GGX with Heitz 2018 ("Sampling the GGX Distribution of Visible Normals"), Beckmann with the
//! visible-slope method of Heitz and d'Eon 2014 (the slope across the view plane is Gaussian;
//! the slope along it has a CDF inverted numerically). Sample weights stay bounded at grazing
//! incidence. Smith's Lambda is exact for both (Beckmann through erf).

use glam::{Vec2, Vec3};

use crate::math::{safe_sqrt, PI};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Distribution {
    Beckmann,
    Ggx,
}

/// Smallest alpha used: below it the distribution is numerically a delta, and D overflows f32.
pub const MIN_ALPHA: f32 = 1e-4;

#[derive(Clone, Copy, Debug)]
pub struct Microfacet {
    pub kind: Distribution,
    pub ax: f32,
    pub ay: f32,
}

impl Microfacet {
    pub fn new(kind: Distribution, ax: f32, ay: f32) -> Microfacet {
        Microfacet { kind, ax: ax.max(MIN_ALPHA), ay: ay.max(MIN_ALPHA) }
    }

    /// Normal distribution D(m) (per unit projected area: integrates cos theta_m D to 1).
    #[inline]
    pub fn d(&self, m: Vec3) -> f32 {
        if m.z <= 0.0 {
            return 0.0;
        }
        let (x, y, z2) = (m.x / self.ax, m.y / self.ay, m.z * m.z);
        let r = match self.kind {
            Distribution::Ggx => {
                let t = x * x + y * y + z2;
                1.0 / (PI * self.ax * self.ay * t * t)
            }
            Distribution::Beckmann => (-(x * x + y * y) / z2).exp() / (PI * self.ax * self.ay * z2 * z2),
        };
        if r.is_finite() {
            r
        } else {
            0.0
        }
    }

    /// Smith Lambda(w) for the distribution.
    #[inline]
    fn lambda(&self, w: Vec3) -> f32 {
        let xy2 = (w.x * self.ax).powi(2) + (w.y * self.ay).powi(2);
        let z2 = w.z * w.z;
        if xy2 == 0.0 {
            return 0.0;
        }
        match self.kind {
            Distribution::Ggx => 0.5 * (-1.0 + (1.0 + xy2 / z2).sqrt()),
            Distribution::Beckmann => {
                // a = 1 / (alpha tan theta): Lambda = (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi)).
                let a = (z2 as f64 / xy2 as f64).sqrt();
                let l = 0.5 * (erf(a) - 1.0) + (-a * a).exp() / (2.0 * a * std::f64::consts::PI.sqrt());
                l.max(0.0) as f32
            }
        }
    }

    /// Smith masking G1(w, m), 0 when w sees the back of m.
    #[inline]
    pub fn g1(&self, w: Vec3, m: Vec3) -> f32 {
        if w.dot(m) * w.z <= 0.0 {
            return 0.0;
        }
        1.0 / (1.0 + self.lambda(w))
    }

    /// Samples a microfacet normal seen from `wo` (wo.z > 0), of density G1(wo, m) max(0,
    /// wo.m) D(m) / wo.z ([`Microfacet::terms`]' third). The density is not returned: the
    /// BSDFs evaluate the value and pdf of the direction the normal leads to (`eval_pdf`), so
    /// it (a division and a root) would be thrown away.
    #[inline]
    pub fn sample_normal(&self, wo: Vec3, u: Vec2) -> Vec3 {
        match self.kind {
            Distribution::Ggx => self.sample_ggx_visible(wo, u),
            Distribution::Beckmann => self.sample_beckmann_visible(wo, u),
        }
    }

    /// What a microfacet BSDF's value and pdf need, each term computed once: D(m), the
    /// separable masking-shadowing G(wo, wi, m) = G1(wo, m) G1(wi, m), and the density
    /// of m that [`Microfacet::sample_normal`] draws (which shares D and G1(wo)).
    #[inline]
    pub fn terms(&self, wo: Vec3, wi: Vec3, m: Vec3) -> (f32, f32, f32) {
        let (d, g1o) = (self.d(m), self.g1(wo, m));
        let pdf = if wo.z <= 0.0 { 0.0 } else { Self::pdf_of(wo, m, d, g1o) };
        (d, g1o * self.g1(wi, m), pdf)
    }

    /// [`Microfacet::sample_normal`]'s density of m for wo.z > 0, from D(m) and G1(wo, m).
    #[inline]
    fn pdf_of(wo: Vec3, m: Vec3, d: f32, g1o: f32) -> f32 {
        g1o * wo.dot(m).max(0.0) * d / wo.z
    }

    /// Heitz 2018: stretch the view direction to the unit-roughness configuration, sample the
    /// projected hemisphere, unstretch.
    fn sample_ggx_visible(&self, wo: Vec3, u: Vec2) -> Vec3 {
        let vh = Vec3::new(self.ax * wo.x, self.ay * wo.y, wo.z).normalize();
        let len2 = vh.x * vh.x + vh.y * vh.y;
        let t1 = if len2 > 0.0 { Vec3::new(-vh.y, vh.x, 0.0) / len2.sqrt() } else { Vec3::X };
        let t2 = vh.cross(t1);
        let r = u.x.sqrt();
        let (s, c) = crate::math::sin_cos_2pi(u.y);
        let p1 = r * c;
        let mut p2 = r * s;
        let h = 0.5 * (1.0 + vh.z);
        p2 = (1.0 - h) * safe_sqrt(1.0 - p1 * p1) + h * p2;
        let nh = t1 * p1 + t2 * p2 + vh * safe_sqrt(1.0 - p1 * p1 - p2 * p2);
        Vec3::new(self.ax * nh.x, self.ay * nh.y, nh.z.max(1e-7)).normalize()
    }

    /// Beckmann visible normals (Heitz and d'Eon 2014): stretch wo to unit roughness, sample
    /// the slope (x, y) of a visible microfacet for that incidence, rotate and unstretch.
    fn sample_beckmann_visible(&self, wo: Vec3, u: Vec2) -> Vec3 {
        let ws = Vec3::new(self.ax * wo.x, self.ay * wo.y, wo.z).normalize();
        let sin_t = (ws.x * ws.x + ws.y * ws.y).sqrt() as f64;
        let cos_t = ws.z as f64;
        let (sx, sy) = beckmann_visible_slopes(cos_t, sin_t, u.x as f64, u.y as f64);
        // Rotate from the view plane back to the azimuth of ws, then unstretch.
        let (cp, sp) = if sin_t > 0.0 { (ws.x as f64 / sin_t, ws.y as f64 / sin_t) } else { (1.0, 0.0) };
        let (x, y) = (cp * sx - sp * sy, sp * sx + cp * sy);
        Vec3::new(-(self.ax as f64 * x) as f32, -(self.ay as f64 * y) as f32, 1.0).normalize()
    }
}

/// Slopes of a visible microfacet of the unit-roughness Beckmann distribution seen at angle
/// theta in the xz-plane. Along the view plane the density is proportional to
/// exp(-x^2) (cos theta - x sin theta) for x < cot theta, whose CDF
/// (sqrt(pi) / 2) cos theta (1 + erf x) + (sin theta / 2) exp(-x^2) is inverted by safeguarded
/// Newton iteration; across it the slope is Gaussian, y = erfinv(2 u2 - 1).
fn beckmann_visible_slopes(cos_t: f64, sin_t: f64, u1: f64, u2: f64) -> (f64, f64) {
    let sqrt_pi = std::f64::consts::PI.sqrt();
    let cdf = |x: f64| 0.5 * sqrt_pi * cos_t * (1.0 + erf(x)) + 0.5 * sin_t * (-x * x).exp();
    let hi = if sin_t > 1e-12 { cos_t / sin_t } else { 10.0 }.min(10.0);
    let target = u1.clamp(1e-12, 1.0 - 1e-12) * cdf(hi);
    let (mut lo_b, mut hi_b) = (-10.0f64, hi);
    let mut x = 0.0f64.min(hi);
    for _ in 0..60 {
        let f = cdf(x) - target;
        if f > 0.0 {
            hi_b = x;
        } else {
            lo_b = x;
        }
        let d = (-x * x).exp() * (cos_t - x * sin_t);
        let mut nx = if d > 1e-300 { x - f / d } else { 0.5 * (lo_b + hi_b) };
        if !(nx > lo_b && nx < hi_b) {
            nx = 0.5 * (lo_b + hi_b);
        }
        if (nx - x).abs() < 1e-12 {
            x = nx;
            break;
        }
        x = nx;
    }
    (x, erfinv(2.0 * u2.clamp(1e-12, 1.0 - 1e-12) - 1.0))
}

/// The error function, to about 1e-15 (series below 3, continued fraction of erfc above).
pub fn erf(x: f64) -> f64 {
    let a = x.abs();
    if a == 0.0 || a.is_nan() {
        return x;
    }
    let r = if a < 3.0 {
        // erf(a) = 2/sqrt(pi) sum_n (-1)^n a^(2n+1) / (n! (2n+1))
        let mut term = a;
        let mut sum = a;
        let a2 = a * a;
        for k in 1..200 {
            let n = k as f64;
            term *= -a2 / n;
            let t = term / (2.0 * n + 1.0);
            sum += t;
            if t.abs() < 1e-17 * sum.abs() {
                break;
            }
        }
        2.0 / std::f64::consts::PI.sqrt() * sum
    } else {
        // erfc(a) = exp(-a^2)/sqrt(pi) * 1/(a + 1/2/(a + 1/(a + 3/2/(a + 2/(a + ...)))))
        let mut f = 0.0;
        for k in (1..=60).rev() {
            f = (k as f64 * 0.5) / (a + f);
        }
        1.0 - (-a * a).exp() / std::f64::consts::PI.sqrt() / (a + f)
    };
    r.copysign(x)
}

/// Inverse of [`erf`] on (-1, 1): Newton iteration from a logarithmic first guess.
pub fn erfinv(y: f64) -> f64 {
    let w = -((1.0 - y) * (1.0 + y)).ln();
    let mut x = (w.max(0.0) * 0.5).sqrt().copysign(y) * 0.9;
    for _ in 0..40 {
        let f = erf(x) - y;
        let d = 2.0 / std::f64::consts::PI.sqrt() * (-x * x).exp();
        if d < 1e-300 {
            break;
        }
        let step = f / d;
        x -= step;
        if step.abs() < 1e-13 * x.abs().max(1e-13) {
            break;
        }
    }
    x
}

/// Exact unpolarised Fresnel reflectance of a dielectric interface. `cos_i` is the cosine
/// with the normal on the incident side (negative: arriving from below), `eta` = n_below /
/// n_above. Returns `(F, cos_t)` with cos_t >= 0 (0 under total internal reflection).
#[inline]
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> (f32, f32) {
    let (cos_i, eta) = if cos_i < 0.0 { (-cos_i, 1.0 / eta) } else { (cos_i, eta) };
    let sin2_t = (1.0 - cos_i * cos_i).max(0.0) / (eta * eta);
    if sin2_t >= 1.0 {
        return (1.0, 0.0);
    }
    let cos_t = safe_sqrt(1.0 - sin2_t);
    let rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    let rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    (0.5 * (rs * rs + rp * rp), cos_t)
}

/// Exact unpolarised Fresnel reflectance of a conductor with complex index eta + i k,
/// per channel, for cos_i in [0, 1]. Where the CPU has AVX, the three channels at once (the
/// same operations on f64 lanes, so the same bits for finite indices, which are all a scene
/// can give: `conductor_lanes_are_the_scalar_fresnel`; from an infinite or NaN index both
/// give NaN, whose sign and payload may differ).
pub fn fresnel_conductor(cos_i: f32, eta: Vec3, k: Vec3) -> Vec3 {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU runs AVX (checked).
        return unsafe { fresnel_conductor_avx(cos_i, eta, k) };
    }
    fresnel_conductor_scalar(cos_i, eta, k)
}

fn fresnel_conductor_scalar(cos_i: f32, eta: Vec3, k: Vec3) -> Vec3 {
    Vec3::new(
        fresnel_complex(cos_i, eta.x, k.x),
        fresnel_complex(cos_i, eta.y, k.y),
        fresnel_complex(cos_i, eta.z, k.z),
    )
}

/// [`fresnel_complex`] of the three channels in the lanes of 256-bit f64 registers: its
/// operations in its order (each exactly rounded, lane by lane), its divisions and roots
/// taken once for all three. (Macros, not closures: a closure would not inherit AVX.)
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn fresnel_conductor_avx(cos_i: f32, eta: Vec3, k: Vec3) -> Vec3 {
    use std::arch::x86_64::*;
    macro_rules! add {
        ($a:expr, $b:expr) => {
            _mm256_add_pd($a, $b)
        };
    }
    macro_rules! sub {
        ($a:expr, $b:expr) => {
            _mm256_sub_pd($a, $b)
        };
    }
    macro_rules! mul {
        ($a:expr, $b:expr) => {
            _mm256_mul_pd($a, $b)
        };
    }
    macro_rules! cmul {
        ($a:expr, $b:expr) => {{
            let (a, b): ((__m256d, __m256d), (__m256d, __m256d)) = ($a, $b);
            (sub!(mul!(a.0, b.0), mul!(a.1, b.1)), add!(mul!(a.0, b.1), mul!(a.1, b.0)))
        }};
    }
    macro_rules! cdiv {
        ($a:expr, $b:expr) => {{
            let (a, b): ((__m256d, __m256d), (__m256d, __m256d)) = ($a, $b);
            let d = add!(mul!(b.0, b.0), mul!(b.1, b.1));
            (
                _mm256_div_pd(add!(mul!(a.0, b.0), mul!(a.1, b.1)), d),
                _mm256_div_pd(sub!(mul!(a.1, b.0), mul!(a.0, b.1)), d),
            )
        }};
    }
    let zero = _mm256_setzero_pd();
    let half = _mm256_set1_pd(0.5);
    let sign = _mm256_set1_pd(-0.0);
    // (x.max(0.0) is x where x > 0 and 0 otherwise, NaN included: maxpd(x, 0) exactly.)
    macro_rules! csqrt {
        ($a:expr) => {{
            let a: (__m256d, __m256d) = $a;
            let r = _mm256_sqrt_pd(add!(mul!(a.0, a.0), mul!(a.1, a.1)));
            let re = _mm256_sqrt_pd(_mm256_max_pd(mul!(add!(r, a.0), half), zero));
            let im = _mm256_sqrt_pd(_mm256_max_pd(mul!(sub!(r, a.0), half), zero));
            (re, _mm256_or_pd(_mm256_andnot_pd(sign, im), _mm256_and_pd(sign, a.1)))
        }};
    }
    let c = _mm256_set1_pd(cos_i.clamp(0.0, 1.0) as f64);
    let n = (
        _mm256_setr_pd(eta.x as f64, eta.y as f64, eta.z as f64, eta.z as f64),
        _mm256_setr_pd(k.x as f64, k.y as f64, k.z as f64, k.z as f64),
    );
    let one = _mm256_set1_pd(1.0);
    let sin2_i = sub!(one, mul!(c, c));
    let sin2_t = cdiv!((sin2_i, zero), cmul!(n, n));
    let cos_t = csqrt!((sub!(one, sin2_t.0), _mm256_xor_pd(sin2_t.1, sign)));
    let nc = (mul!(n.0, c), mul!(n.1, c));
    let ncos_t = cmul!(n, cos_t);
    let r_parl =
        cdiv!((sub!(nc.0, cos_t.0), sub!(nc.1, cos_t.1)), (add!(nc.0, cos_t.0), add!(nc.1, cos_t.1)));
    let r_perp = cdiv!((sub!(c, ncos_t.0), _mm256_xor_pd(ncos_t.1, sign)), (add!(c, ncos_t.0), ncos_t.1));
    let f = mul!(
        half,
        add!(
            add!(mul!(r_parl.0, r_parl.0), mul!(r_parl.1, r_parl.1)),
            add!(mul!(r_perp.0, r_perp.0), mul!(r_perp.1, r_perp.1))
        )
    );
    let mut out = [0.0f32; 4];
    _mm_storeu_ps(out.as_mut_ptr(), _mm256_cvtpd_ps(f));
    Vec3::new(out[0], out[1], out[2])
}

fn fresnel_complex(cos_i: f32, eta: f32, k: f32) -> f32 {
    // Complex arithmetic in f64: (re, im).
    type C = (f64, f64);
    let mul = |a: C, b: C| (a.0 * b.0 - a.1 * b.1, a.0 * b.1 + a.1 * b.0);
    let div = |a: C, b: C| {
        let d = b.0 * b.0 + b.1 * b.1;
        ((a.0 * b.0 + a.1 * b.1) / d, (a.1 * b.0 - a.0 * b.1) / d)
    };
    let sqrt = |a: C| {
        let r = (a.0 * a.0 + a.1 * a.1).sqrt();
        let re = ((r + a.0) * 0.5).max(0.0).sqrt();
        let im = ((r - a.0) * 0.5).max(0.0).sqrt().copysign(a.1);
        (re, im)
    };
    let norm2 = |a: C| a.0 * a.0 + a.1 * a.1;
    let c = (cos_i.clamp(0.0, 1.0)) as f64;
    let n: C = (eta as f64, k as f64);
    let sin2_i = 1.0 - c * c;
    let sin2_t = div((sin2_i, 0.0), mul(n, n));
    let cos_t = sqrt((1.0 - sin2_t.0, -sin2_t.1));
    let nc = (n.0 * c, n.1 * c);
    let ncos_t = mul(n, cos_t);
    let r_parl = div((nc.0 - cos_t.0, nc.1 - cos_t.1), (nc.0 + cos_t.0, nc.1 + cos_t.1));
    let r_perp = div((c - ncos_t.0, -ncos_t.1), (c + ncos_t.0, ncos_t.1));
    (0.5 * (norm2(r_parl) + norm2(r_perp))) as f32
}

/// Hemispherical average of the dielectric Fresnel reflectance, 2 int_0^1 F(mu) mu dmu, for
/// light arriving from the side where the relative index is `eta` (numerical integration).
pub fn fresnel_diffuse_reflectance(eta: f32) -> f32 {
    let n = 4096;
    let mut sum = 0.0f64;
    for i in 0..n {
        let mu = (i as f64 + 0.5) / n as f64;
        sum += fresnel_dielectric(mu as f32, eta).0 as f64 * mu;
    }
    (2.0 * sum / n as f64) as f32
}

/// Mirror `w` about the normal `m`.
#[inline]
pub fn reflect(w: Vec3, m: Vec3) -> Vec3 {
    m * (2.0 * w.dot(m)) - w
}

/// Refracts `w` (on the side `m` points to, w.m > 0) through a surface with relative index
/// `eta` = n_other / n_this, given cos_t from [`fresnel_dielectric`].
#[inline]
pub fn refract(w: Vec3, m: Vec3, eta: f32, cos_t: f32) -> Vec3 {
    let c = w.dot(m);
    m * (c / eta - cos_t) - w / eta
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The three channels in AVX lanes give `fresnel_complex`'s bits: the presets, random
    /// indices from 0 to 20 and cosines over [0, 1] (grazing and normal incidence, outside
    /// the range, NaN).
    #[test]
    fn conductor_lanes_are_the_scalar_fresnel() {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx") {
            let mut rng = crate::testing::Pcg::new(41);
            let mut cases: Vec<(Vec3, Vec3)> = super::super::conductor::CONDUCTOR_PRESETS
                .iter()
                .filter_map(|n| super::super::conductor::conductor_preset(n))
                .collect();
            cases.extend([
                (Vec3::ZERO, Vec3::ZERO),
                (Vec3::ONE, Vec3::ZERO),
                (Vec3::splat(1e-6), Vec3::splat(1e3)),
            ]);
            cases.extend((0..2000).map(|_| {
                let mut c = || rng.next_f32() * rng.next_f32() * 20.0;
                (Vec3::new(c(), c(), c()), Vec3::new(c(), c(), c()))
            }));
            let mut cosines = vec![0.0, 1.0, -0.5, 1.5, 1e-30, 1.0 - f32::EPSILON, f32::NAN];
            cosines.extend((0..64).map(|_| rng.next_f32()));
            for &(eta, k) in &cases {
                for &c in &cosines {
                    // SAFETY: the CPU runs AVX (checked).
                    let got = unsafe { fresnel_conductor_avx(c, eta, k) };
                    let want = fresnel_conductor_scalar(c, eta, k);
                    assert_eq!(
                        got.to_array().map(f32::to_bits),
                        want.to_array().map(f32::to_bits),
                        "cos {c}, eta {eta}, k {k}"
                    );
                }
            }
        }
    }

    #[test]
    fn distributions_are_normalised() {
        // int D(m) cos(theta_m) dm = 1, by midpoint quadrature over the hemisphere.
        for kind in [Distribution::Ggx, Distribution::Beckmann] {
            for (ax, ay) in [(0.1, 0.1), (0.5, 0.2), (1.0, 1.0)] {
                let mf = Microfacet::new(kind, ax, ay);
                let (nt, np) = (2000, 200);
                let mut s = 0.0f64;
                for i in 0..nt {
                    let ct = (i as f64 + 0.5) / nt as f64;
                    let st = (1.0 - ct * ct).sqrt();
                    for j in 0..np {
                        let phi = 2.0 * std::f64::consts::PI * (j as f64 + 0.5) / np as f64;
                        let m = Vec3::new((st * phi.cos()) as f32, (st * phi.sin()) as f32, ct as f32);
                        s += mf.d(m) as f64 * ct;
                    }
                }
                let integral = s * 2.0 * std::f64::consts::PI / (nt * np) as f64;
                assert!((integral - 1.0).abs() < 0.01, "{kind:?} {ax} {ay}: {integral}");
            }
        }
    }

    #[test]
    fn erf_and_its_inverse() {
        // erf(0.5) = 0.5204998778130465, erf(2) = 0.9953222650189527, erf(3.5) = 0.9999992569016276.
        assert!((erf(0.5) - 0.520_499_877_813_046_5).abs() < 1e-14);
        assert!((erf(2.0) - 0.995_322_265_018_952_7).abs() < 1e-14);
        assert!((erf(3.5) - 0.999_999_256_901_627_6).abs() < 1e-14);
        assert!((erf(-1.0) + 0.842_700_792_949_714_9).abs() < 1e-14);
        for y in [-0.999_999, -0.5, 0.0, 0.3, 0.99, 0.999_999_9] {
            assert!((erf(erfinv(y)) - y).abs() < 1e-12, "{y}");
        }
    }

    #[test]
    fn fresnel_limits() {
        let (f, _) = fresnel_dielectric(1.0, 1.5);
        assert!((f - 0.04).abs() < 1e-6);
        assert_eq!(fresnel_dielectric(0.1, 1.0 / 1.5).0, 1.0); // total internal reflection
        assert!((fresnel_dielectric(1e-7, 1.5).0 - 1.0).abs() < 1e-3);
        // A conductor with k = 0 is a dielectric.
        let c = fresnel_conductor(0.6, Vec3::splat(1.5), Vec3::ZERO).x;
        assert!((c - fresnel_dielectric(0.6, 1.5).0).abs() < 1e-6);
        // eta = 0, k = 1: a perfect mirror.
        assert!((fresnel_conductor(0.3, Vec3::ZERO, Vec3::ONE).x - 1.0).abs() < 1e-6);
    }

    #[test]
    fn refraction_obeys_snell() {
        let w = Vec3::new(0.6, 0.0, 0.8);
        let (_, cos_t) = fresnel_dielectric(w.z, 1.5);
        let t = refract(w, Vec3::Z, 1.5, cos_t);
        assert!((t.length() - 1.0).abs() < 1e-6 && t.z < 0.0);
        assert!((0.6f32 - 1.5 * t.x.abs()).abs() < 1e-6);
    }
}
