//! The hair BSDF of Chiang, Bitterli, Tappan and Burley 2016 ("A Practical and Controllable
//! Hair and Fur Model for Production Path Tracing"), written from the paper and the PBR book's
//! description of it.
//!
//! Local frame: x along the fibre, z the surface normal, y = z x x. Longitudinal angle theta
//! from the normal plane (sin theta = w.x), azimuth phi = atan2(w.z, w.y). `h` in [-1, 1] is
//! the offset across the fibre where the ray hit it: gamma_o = asin(h).
//!
//! f cos = sum_p Mp(theta_i, theta_o) Ap(theta_o, h) Np(phi), p = R, TT, TRT, plus a residual
//! lobe (p = 3) for all longer paths with an isotropic azimuth:
//! - Mp: d'Eon et al. 2011's longitudinal term, in log form (for every v) so that neither
//!   sinh(1/v) nor I0 overflows; the cuticle tilt rotates theta_o per lobe. The four lobes'
//!   Mp and Np are computed together, a lobe a lane ([`crate::simd::F4`]).
//! - Ap: Fresnel and the absorption T = exp(-sigma_a 2 cos gamma_t / cos theta_t).
//! - Np: a logistic in phi - Phi(p, h), trimmed to [-pi, pi].
//!
//! Sampling picks a lobe by Ap, then samples Mp and Np exactly, so pdf and sampling agree.

use glam::{Vec2, Vec3};

use super::microfacet::fresnel_dielectric;
use super::BsdfSample;
use crate::math::{fast_atan2, luminance, safe_asin, safe_sqrt, Rgb, PI};
use crate::simd::F4;

const P_MAX: usize = 3;

#[derive(Clone, Debug)]
pub struct Hair {
    pub sigma_a: Rgb,
    /// Relative index of refraction of the fibre.
    pub eta: f32,
    /// Longitudinal variance per lobe (the paper's roughness map, eq. 3 of the seed document).
    v: [f32; P_MAX + 1],
    /// Azimuthal logistic scale (eq. 4 with sqrt(pi / 8)).
    s: f32,
    /// Per lobe, what Mp needs of v alone (see [`mp4`]): 1 / v, and
    /// K = -ln v - ln(1 - e^(-2 / v)).
    inv_v: F4,
    mp_k: F4,
    /// e^(-2 / v) per lobe, for sampling Mp.
    exp_m2_over_v: [f32; P_MAX + 1],
    /// The cuticle tilt of each lobe's theta_o as two coefficient lanes (the residual lobe
    /// untilted): sin = sin_o a + cos_o b, cos = |cos_o a - sin_o b|.
    tilt_a: F4,
    tilt_b: F4,
    /// The trimmed logistic's constants for `s` (see [`Trim`]).
    trim: Trim,
}

/// The logistic's CDF at -pi, and its mass on [-pi, pi], for one scale.
#[derive(Clone, Copy, Debug)]
struct Trim {
    cdf_neg_pi: f32,
    mass: f32,
}

impl Trim {
    fn new(s: f32) -> Trim {
        Trim { cdf_neg_pi: logistic_cdf(-PI, s), mass: logistic_cdf(PI, s) - logistic_cdf(-PI, s) }
    }
}

impl Hair {
    /// `beta_m`, `beta_n`: longitudinal and azimuthal roughness in [0, 1]; `alpha_deg`: tilt.
    pub fn new(sigma_a: Rgb, eta: f32, beta_m: f32, beta_n: f32, alpha_deg: f32) -> Hair {
        let bm = beta_m.clamp(1e-3, 1.0);
        let bn = beta_n.clamp(1e-3, 1.0);
        let v0 = (0.726 * bm + 0.812 * bm * bm + 3.7 * bm.powi(20)).powi(2);
        let v = [v0, 0.25 * v0, 4.0 * v0, 4.0 * v0];
        let s = (PI / 8.0).sqrt() * (0.265 * bn + 1.194 * bn * bn + 5.372 * bn.powi(22));
        let mut sin2k = [0.0; 3];
        let mut cos2k = [0.0; 3];
        sin2k[0] = alpha_deg.to_radians().sin();
        cos2k[0] = safe_sqrt(1.0 - sin2k[0] * sin2k[0]);
        for i in 1..3 {
            sin2k[i] = 2.0 * cos2k[i - 1] * sin2k[i - 1];
            cos2k[i] = cos2k[i - 1] * cos2k[i - 1] - sin2k[i - 1] * sin2k[i - 1];
        }
        Hair {
            sigma_a,
            eta,
            v,
            s,
            inv_v: F4::new(v.map(|v| 1.0 / v)),
            mp_k: F4::new(v.map(mp_k)),
            exp_m2_over_v: v.map(|v| (-2.0 / v).exp()),
            tilt_a: F4::new([cos2k[1], cos2k[0], cos2k[2], 1.0]),
            tilt_b: F4::new([-sin2k[1], sin2k[0], sin2k[2], 0.0]),
            trim: Trim::new(s),
        }
    }

    /// Absorption from pigment concentrations (RGB fits of eumelanin and pheomelanin).
    pub fn sigma_a_from_melanin(eumelanin: f32, pheomelanin: f32) -> Rgb {
        Rgb::new(0.419, 0.697, 1.37) * eumelanin + Rgb::new(0.187, 0.4, 1.05) * pheomelanin
    }

    /// The paper's map from a perceived colour to sigma_a, given azimuthal roughness beta_n.
    pub fn sigma_a_from_reflectance(c: Rgb, beta_n: f32) -> Rgb {
        let b = beta_n;
        let d = 5.969 - 0.215 * b + 2.532 * b * b - 10.73 * b.powi(3) + 5.574 * b.powi(4) + 0.245 * b.powi(5);
        let f = |x: f32| (x.max(1e-4).ln() / d).powi(2);
        Rgb::new(f(c.x), f(c.y), f(c.z))
    }

    /// theta_o rotated by the cuticle tilt for lobe p: (sin, |cos|). Lobe 0 (R) tilts by
    /// -2 alpha, 1 (TT) by alpha, 2 (TRT) by 4 alpha, the residual not at all.
    #[inline]
    fn tilt(&self, p: usize, sin_o: f32, cos_o: f32) -> (f32, f32) {
        let (a, b) = (self.tilt_a.to_array()[p], self.tilt_b.to_array()[p]);
        (sin_o * a + cos_o * b, (cos_o * a - sin_o * b).abs())
    }

    /// Attenuations A_p (R, TT, TRT, residual) and gamma_o, gamma_t for this wo and h.
    fn attenuation(&self, sin_o: f32, cos_o: f32, h: f32) -> ([Rgb; P_MAX + 1], f32, f32) {
        let sin_t = sin_o / self.eta;
        let cos_t = safe_sqrt(1.0 - sin_t * sin_t);
        let etap = safe_sqrt(self.eta * self.eta - sin_o * sin_o) / cos_o.max(1e-8);
        let sin_gt = (h / etap).clamp(-1.0, 1.0);
        let cos_gt = safe_sqrt(1.0 - sin_gt * sin_gt);
        let gamma_t = safe_asin(sin_gt);
        let gamma_o = safe_asin(h);
        let k = -2.0 * cos_gt / cos_t.max(1e-8);
        let sa = self.sigma_a;
        let [tr, tg, tb, _] = F4::new([sa.x * k, sa.y * k, sa.z * k, 0.0]).exp().to_array();
        let t = Rgb::new(tr, tg, tb);
        let cos_gamma_o = safe_sqrt(1.0 - h * h);
        let f = fresnel_dielectric(cos_o * cos_gamma_o, self.eta).0;
        let mut a = [Rgb::ZERO; P_MAX + 1];
        a[0] = Rgb::splat(f);
        a[1] = t * ((1.0 - f) * (1.0 - f));
        for p in 2..P_MAX {
            a[p] = a[p - 1] * t * f;
        }
        let denom = Rgb::ONE - t * f;
        a[P_MAX] = a[P_MAX - 1] * t * f / denom.max(Rgb::splat(1e-12));
        (a, gamma_o, gamma_t)
    }

    /// Lobe selection probabilities, proportional to the luminance of A_p.
    fn lobe_pdf(a: &[Rgb; P_MAX + 1]) -> [f32; P_MAX + 1] {
        let mut w = [0.0; P_MAX + 1];
        let mut sum = 0.0;
        for p in 0..=P_MAX {
            w[p] = luminance(a[p]).max(0.0);
            sum += w[p];
        }
        if sum > 0.0 {
            w.iter_mut().for_each(|x| *x /= sum);
        } else {
            w = [0.25; P_MAX + 1];
        }
        w
    }

    fn angles(w: Vec3) -> (f32, f32, f32) {
        let sin = w.x.clamp(-1.0, 1.0);
        (sin, safe_sqrt(1.0 - sin * sin), fast_atan2(w.z, w.y))
    }

    /// Np of the four lobes at azimuth difference `phi`, each lobe's centre `phi_p`
    /// ([`HairAt::phi_p`]): R, TT and TRT the trimmed logistic around it, the residual 1 / (2 pi).
    #[inline(always)]
    fn np4(&self, phi: f32, phi_p: F4) -> F4 {
        let s = F4::splat;
        // phi - Phi(p) wrapped to [-pi, pi) (as rem_euclid, by floor).
        let d = s(phi) - phi_p + s(PI);
        let d = d - s(2.0 * PI) * (d * s(1.0 / (2.0 * PI))).floor() - s(PI);
        let e = (-(d.abs() / s(self.s))).exp();
        let n = e * s(1.0 / (self.s * self.trim.mass)) / ((s(1.0) + e) * (s(1.0) + e));
        let mut n = n.to_array();
        n[P_MAX] = 1.0 / (2.0 * PI);
        F4::new(n)
    }

    /// The offset across the fibre implied by `wo` and the normal: for a round fibre the
    /// normal at the hit makes the angle gamma_o = asin(h) with wo's projection across it.
    pub fn h_from(wo: Vec3) -> f32 {
        let len = (wo.y * wo.y + wo.z * wo.z).sqrt();
        if len > 0.0 {
            (-wo.y / len).clamp(-1.0, 1.0)
        } else {
            0.0
        }
    }

    /// The fibre seen from `wo` at offset `h`: what every evaluation and sample for this wo
    /// shares, computed once (a path vertex's light sample and BSDF sample both use it).
    /// (Not inlined, nor are [`HairAt`]'s two methods: inlined into the integrator's loop they
    /// crowded out what other BSDFs' paths inline there.)
    #[inline(never)]
    pub fn at(&self, wo: Vec3, h: f32) -> HairAt<'_> {
        let (sin_o, cos_o, phi_o) = Self::angles(wo);
        let (a, gamma_o, gamma_t) = self.attenuation(sin_o, cos_o, h);
        let (so4, co4) = (F4::splat(sin_o), F4::splat(cos_o));
        let s = F4::splat;
        let p = F4::new([0.0, 1.0, 2.0, 3.0]);
        HairAt {
            hair: self,
            sin_o,
            cos_o,
            phi_o,
            w: Self::lobe_pdf(&a),
            a,
            gamma_o,
            gamma_t,
            so: so4 * self.tilt_a + co4 * self.tilt_b,
            co: (co4 * self.tilt_a - so4 * self.tilt_b).abs(),
            phi_p: s(2.0) * p * s(gamma_t) - s(2.0 * gamma_o) + p * s(PI),
        }
    }

    /// f |cos| and the pdf of `wi`, computed together (they share every costly term).
    pub fn eval_pdf(&self, wo: Vec3, wi: Vec3, h: f32) -> (Rgb, f32) {
        self.at(wo, h).eval_pdf(wi)
    }

    pub fn eval(&self, wo: Vec3, wi: Vec3, h: f32) -> Rgb {
        self.eval_pdf(wo, wi, h).0
    }

    pub fn pdf(&self, wo: Vec3, wi: Vec3, h: f32) -> f32 {
        self.eval_pdf(wo, wi, h).1
    }

    /// Picks a lobe with `u1` (its remainder then samples the azimuth) and samples Mp with `u2`.
    pub fn sample(&self, wo: Vec3, h: f32, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        self.at(wo, h).sample(u1, u2)
    }
}

/// A fibre seen from one `wo` ([`Hair::at`]): wo's angles, the lobes' attenuations A_p and
/// selection probabilities, gamma_o and gamma_t, each lobe's tilted theta_o and its azimuthal
/// centre Phi(p, h).
#[derive(Clone, Copy, Debug)]
pub struct HairAt<'a> {
    hair: &'a Hair,
    sin_o: f32,
    cos_o: f32,
    phi_o: f32,
    a: [Rgb; P_MAX + 1],
    w: [f32; P_MAX + 1],
    gamma_o: f32,
    gamma_t: f32,
    /// theta_o tilted for each lobe: sin and |cos| ([`Hair::tilt`], a lobe a lane).
    so: F4,
    co: F4,
    /// Phi(p, h) = 2 p gamma_t - 2 gamma_o + p pi, a lobe a lane.
    phi_p: F4,
}

impl HairAt<'_> {
    /// f |cos| summed over lobes and the pdf of `wi`: the four lobes' Mp and Np are computed
    /// together, a lobe a lane, and once for both.
    #[inline(never)]
    pub fn eval_pdf(&self, wi: Vec3) -> (Rgb, f32) {
        let hair = self.hair;
        let (sin_i, cos_i, phi_i) = Hair::angles(wi);
        let m = mp4(cos_i, sin_i, self.co, self.so, hair.inv_v, hair.mp_k);
        let mn = (m * hair.np4(phi_i - self.phi_o, self.phi_p)).to_array();
        let (mut f, mut pdf) = (Rgb::ZERO, 0.0f32);
        for p in 0..=P_MAX {
            f = f + self.a[p] * mn[p];
            pdf += self.w[p] * mn[p];
        }
        (
            if f.is_finite() { f.max(Rgb::ZERO) } else { Rgb::ZERO },
            if pdf.is_finite() { pdf.max(0.0) } else { 0.0 },
        )
    }

    /// [`Hair::sample`].
    #[inline(never)]
    pub fn sample(&self, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        let hair = self.hair;
        let (sin_o, cos_o, phi_o) = (self.sin_o, self.cos_o, self.phi_o);
        let lp = &self.w;
        let mut p = P_MAX;
        let mut u = u1;
        for (k, &w) in lp.iter().enumerate().take(P_MAX) {
            if u < w {
                p = k;
                break;
            }
            u -= w;
        }
        let u_phi = if p < P_MAX {
            (u / lp[p]).clamp(0.0, 1.0 - f32::EPSILON)
        } else {
            (u / lp[P_MAX].max(1e-12)).clamp(0.0, 1.0 - f32::EPSILON)
        };
        let (so, co) = hair.tilt(p, sin_o, cos_o);
        // Sample Mp (d'Eon et al. 2011): cos theta = 1 + v log(u + (1 - u) e^(-2/v)).
        let v = hair.v[p];
        let u0 = u2.x.max(1e-5);
        let cos_t = 1.0 + v * F4::splat(u0 + (1.0 - u0) * hair.exp_m2_over_v[p]).ln().to_array()[0];
        let sin_t = safe_sqrt(1.0 - cos_t * cos_t);
        let cos_phi = crate::math::sin_cos_2pi(u2.y).1;
        let sin_i = (-cos_t * so + sin_t * cos_phi * co).clamp(-1.0, 1.0);
        let cos_i = safe_sqrt(1.0 - sin_i * sin_i);
        let dphi = if p < P_MAX {
            phi_fn(p, self.gamma_o, self.gamma_t) + sample_trimmed_logistic(u_phi, hair.s, &hair.trim)
        } else {
            2.0 * PI * u_phi
        };
        let phi_i = phi_o + dphi;
        let wi = Vec3::new(sin_i, cos_i * phi_i.cos(), cos_i * phi_i.sin());
        if !wi.is_finite() {
            return None;
        }
        let (f, pdf) = self.eval_pdf(wi);
        if !(pdf > 0.0) {
            return None;
        }
        let weight = f / pdf;
        weight.is_finite().then_some(BsdfSample { wi, weight, pdf, delta: false, eta: 1.0 })
    }
}

/// Abramowitz and Stegun 9.8.1: I0(x) for |x| <= 3.75 as a polynomial in t = (x / 3.75)^2
/// (within 1.6e-7).
const I0_SMALL: [f32; 7] =
    [1.0, 3.515_622_9, 3.089_942_4, 1.206_749_2, 0.265_973_2, 0.036_076_8, 0.004_581_3];
/// Abramowitz and Stegun 9.8.2: sqrt(x) e^-x I0(x) for x >= 3.75 as a polynomial in t = 3.75 / x
/// (within 1.9e-7).
const I0_LARGE: [f32; 9] = [
    0.398_942_28,
    0.013_285_92,
    0.002_253_19,
    -0.001_575_65,
    0.009_162_81,
    -0.020_577_06,
    0.026_355_37,
    -0.016_476_33,
    0.003_923_77,
];

/// d'Eon et al. 2011's Mp = exp(-sin_i sin_o / v) I0(cos_i cos_o / v) / (2 v sinh(1 / v)) for
/// four lobes at once (lane p: its tilted theta_o and its v), in log form, which holds for any
/// v: with a = cos_i cos_o / v and c = cos(theta_i + theta_o) = cos_i cos_o - sin_i sin_o,
/// ln Mp = (ln I0(a) - a) - (1 - c) / v + K, K = -ln v - ln(1 - e^(-2 / v)) (per lobe, in f64).
/// a and 1 / v reach 7.6e6 at the smallest roughness, where an f32 ulp is 0.5: near the lobe's
/// peak they cancel, so their difference is never formed; 1 - c is taken as sin^2 / (1 + c)
/// of the sum, which the sines give to full precision there, at any theta_o, grazing included.
#[inline(always)]
fn mp4(cos_i: f32, sin_i: f32, cos_o: F4, sin_o: F4, inv_v: F4, k: F4) -> F4 {
    let (ci, si) = (F4::splat(cos_i), F4::splat(sin_i));
    let cc = ci * cos_o;
    let a = cc * inv_v;
    // ln I0(a) - a: the logarithm of I0(a) (A&S 9.8.1), less a, up to 3.75; above, of
    // sqrt(a) e^-a I0(a) (A&S 9.8.2) over sqrt(a): no exponential formed, finite for any a.
    let small = a.le(F4::splat(3.75));
    let t = a * F4::splat(1.0 / 3.75);
    let i0_small = poly(t * t, &I0_SMALL);
    let i0_large = poly(F4::splat(3.75) / a, &I0_LARGE) / a.sqrt();
    let ln_i0_minus_a = small.select(i0_small, i0_large).ln() - small.select(a, F4::splat(0.0));
    let c = cc - si * sin_o;
    let s = si * cos_o + ci * sin_o;
    let one = F4::splat(1.0);
    let one_minus_c = F4::splat(0.0).lt(c).select(s * s / (one + c), one - c);
    (ln_i0_minus_a - one_minus_c * inv_v + k).exp()
}

/// K = -ln v - ln(1 - e^(-2 / v)) of [`mp4`], in f64 (1 - e^(-2 / v) is near 2 / v for large v).
fn mp_k(v: f32) -> f32 {
    let v = v as f64;
    (-v.ln() - (-(-2.0 / v).exp_m1()).ln()) as f32
}

/// sum c[k] x^k, by Horner's rule, on four lanes.
#[inline(always)]
fn poly<const N: usize>(x: F4, c: &[f32; N]) -> F4 {
    let mut p = F4::splat(c[N - 1]);
    for &ck in c[..N - 1].iter().rev() {
        p = p * x + F4::splat(ck);
    }
    p
}

/// Azimuthal deflection of lobe p: 2 p gamma_t - 2 gamma_o + p pi.
fn phi_fn(p: usize, gamma_o: f32, gamma_t: f32) -> f32 {
    2.0 * p as f32 * gamma_t - 2.0 * gamma_o + p as f32 * PI
}

fn logistic_cdf(x: f32, s: f32) -> f32 {
    1.0 / (1.0 + (-x / s).exp())
}

fn sample_trimmed_logistic(u: f32, s: f32, trim: &Trim) -> f32 {
    let x = -s * (1.0 / (u * trim.mass + trim.cdf_neg_pi) - 1.0).ln();
    x.clamp(-PI, PI)
}

/// Scene loading: `hair`. Its absorption comes from one of `sigma_a` (with `scale`), the
/// pigment concentrations (`eumelanin`, `pheomelanin`) or Furnace's own `reflectance`.
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<super::Bsdf> {
    let doc = b.doc;
    let eta = b.ior(i, "int_ior", "amber")? / b.ior(i, "ext_ior", "air")?;
    let beta_m = doc.float_or(i, "longitudinal_roughness", 0.3)?;
    let beta_n = doc.float_or(i, "azimuthal_roughness", 0.3)?;
    for (name, v) in [("longitudinal_roughness", beta_m), ("azimuthal_roughness", beta_n)] {
        if !(v > 0.0 && v <= 1.0) {
            return Err(b.err(doc.pos_of(i, name), format!("'{name}' must lie in (0, 1], found {v}")));
        }
    }
    let tilt = doc.float_or(i, "scale_tilt", 2.0)?;
    let pigments = doc.has(i, "eumelanin") || doc.has(i, "pheomelanin");
    let given = [doc.has(i, "sigma_a"), pigments, doc.has(i, "reflectance")];
    if given.iter().filter(|&&g| g).count() > 1 {
        return Err(b.err(
            doc.obj(i).pos,
            "hair: give one of sigma_a, the pigments (eumelanin/pheomelanin) or reflectance",
        ));
    }
    let sigma_a = if doc.has(i, "sigma_a") {
        b.const_color(i, "sigma_a", Rgb::ZERO)? * b.nonneg_float(i, "scale", 1.0)?
    } else if doc.has(i, "reflectance") {
        Hair::sigma_a_from_reflectance(b.const_color(i, "reflectance", Rgb::splat(0.5))?, beta_n)
    } else {
        Hair::sigma_a_from_melanin(
            b.nonneg_float(i, "eumelanin", 1.3)?,
            b.nonneg_float(i, "pheomelanin", 0.2)?,
        )
    };
    Ok(super::Bsdf::Hair(Hair::new(sigma_a, eta, beta_m, beta_n, tilt)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{chi2_test, sidak_alpha, Grid, Pcg};

    fn random_dir(rng: &mut Pcg) -> Vec3 {
        crate::math::square_to_uniform_sphere(rng.next_2d())
    }

    /// White furnace by evaluation: sigma_a 0, beta_m and beta_n in {0.1 .. 0.9}, random h,
    /// uniform sphere directions: the mean of f cos / pdf_uniform is 1 within 5%.
    #[test]
    fn white_furnace_by_evaluation_within_5_percent() {
        let mut rng = Pcg::new(11);
        for bm in [0.1f32, 0.3, 0.5, 0.7, 0.9] {
            for bn in [0.1f32, 0.3, 0.5, 0.7, 0.9] {
                let hair = Hair::new(Rgb::ZERO, 1.55, bm, bn, 2.0);
                let n = 300_000;
                let mut sum = 0.0f64;
                for _ in 0..n {
                    let (wo, wi) = (random_dir(&mut rng), random_dir(&mut rng));
                    let h = -1.0 + 2.0 * rng.next_f32();
                    sum += hair.eval(wo, wi, h).y as f64 * 4.0 * std::f64::consts::PI;
                }
                let mean = sum / n as f64;
                assert!((mean - 1.0).abs() < 0.05, "beta_m {bm} beta_n {bn}: {mean}");
            }
        }
    }

    /// White furnace by sampling: every weight is 1 within 1e-3 at sigma_a 0 (so the mean is
    /// 1 within 1% and far better).
    #[test]
    fn white_furnace_by_sampling_weights_are_one() {
        let mut rng = Pcg::new(12);
        for bm in [0.001f32, 0.02, 0.1, 0.3, 0.5, 0.7, 0.9] {
            for bn in [0.1f32, 0.3, 0.5, 0.7, 0.9] {
                let hair = Hair::new(Rgb::ZERO, 1.55, bm, bn, 2.0);
                let (mut sum, mut n) = (0.0f64, 0);
                for _ in 0..20_000 {
                    let wo = random_dir(&mut rng);
                    let h = -1.0 + 2.0 * rng.next_f32();
                    if let Some(s) = hair.sample(wo, h, rng.next_f32(), rng.next_2d()) {
                        for c in 0..3 {
                            assert!(
                                (s.weight[c] - 1.0).abs() < 1e-3,
                                "beta {bm}/{bn}: weight {:?}",
                                s.weight
                            );
                        }
                        sum += s.weight.y as f64;
                        n += 1;
                    }
                }
                assert!(n > 19_000 && (sum / n as f64 - 1.0).abs() < 0.01);
            }
        }
    }

    #[test]
    fn attenuations_sum_to_one_without_absorption() {
        let hair = Hair::new(Rgb::ZERO, 1.55, 0.3, 0.3, 2.0);
        for (sin_o, h) in [(0.0f32, 0.0f32), (0.5, 0.7), (-0.9, -0.99), (0.3, 1.0)] {
            let (a, _, _) = hair.attenuation(sin_o, safe_sqrt(1.0 - sin_o * sin_o), h);
            let s: Rgb = a.iter().copied().sum();
            assert!((s - Rgb::ONE).abs().max_element() < 1e-5, "{sin_o} {h}: {s}");
        }
    }

    /// With sigma_a 0.25 and tilts 0, 2 and 10 degrees, importance sampling and uniform
    /// sampling estimate the same directional albedo (within 3%).
    #[test]
    fn importance_and_uniform_estimates_agree() {
        let mut rng = Pcg::new(13);
        for alpha in [0.0f32, 2.0, 10.0] {
            let hair = Hair::new(Rgb::splat(0.25), 1.55, 0.3, 0.3, alpha);
            let wo = Vec3::new(0.3, 0.5, 0.8).normalize();
            let h = 0.3;
            let n = 400_000;
            let (mut imp, mut uni) = (0.0f64, 0.0f64);
            for _ in 0..n {
                if let Some(s) = hair.sample(wo, h, rng.next_f32(), rng.next_2d()) {
                    imp += s.weight.y as f64;
                }
                uni += hair.eval(wo, random_dir(&mut rng), h).y as f64 * 4.0 * std::f64::consts::PI;
            }
            let (imp, uni) = (imp / n as f64, uni / n as f64);
            assert!((imp / uni - 1.0).abs() < 0.03, "tilt {alpha}: importance {imp}, uniform {uni}");
        }
    }

    /// Chi-square of sampled directions against the pdf (100,000 samples, 16 x 32 grid over
    /// the sphere, Sidak-corrected 1% level over 9 cases): beta_m = beta_n in {0.1, 0.3, 0.7}
    /// (and beta_n 0.5) x incident (sin theta_o, h) in {(0, 0.2), (0.9, -0.6), (-0.99, 0.95)},
    /// sigma_a 0.2; the pdf integrates to 1 within 1%.
    #[test]
    fn sampled_directions_follow_the_pdf() {
        let cases: Vec<(f32, f32, f32, f32)> = [0.1f32, 0.3, 0.7]
            .iter()
            .flat_map(|&b| [(b, b, 0.0f32, 0.2f32), (b, b, 0.9, -0.6), (b, 0.5, -0.99, 0.95)])
            .collect();
        let alpha = sidak_alpha(cases.len());
        for (bm, bn, sin_o, h) in cases {
            let hair = Hair::new(Rgb::splat(0.2), 1.55, bm, bn, 2.0);
            let wo =
                Vec3::new(sin_o, safe_sqrt(1.0 - sin_o * sin_o) * 0.6, safe_sqrt(1.0 - sin_o * sin_o) * 0.8);
            let r = chi2_test(
                100_000,
                Grid::uniform(16, 32),
                7,
                |rng| hair.sample(wo, h, rng.next_f32(), rng.next_2d()).map(|s| s.wi),
                |w| hair.pdf(wo, w, h) as f64,
                |_| true,
            );
            assert!(r.p_value > alpha, "beta {bm}/{bn} sin_o {sin_o} h {h}: {r:?}");
            assert!((r.pdf_integral - 1.0).abs() < 0.01, "beta {bm}/{bn}: pdf integral {}", r.pdf_integral);
        }
    }

    #[test]
    fn edge_cases_stay_finite_and_non_negative() {
        let mut rng = Pcg::new(14);
        let ulp = 1.0 - f32::EPSILON / 2.0;
        for (bm, bn) in [(0.01f32, 0.01f32), (1.0, 1.0), (0.01, 1.0)] {
            let hair = Hair::new(Rgb::splat(0.5), 1.55, bm, bn, 2.0);
            for wo in [Vec3::X, -Vec3::X, Vec3::Z, Vec3::new(0.999_999, 0.0, 0.001).normalize()] {
                for h in [-1.0f32, 1.0, 0.0] {
                    for u in [0.0f32, ulp] {
                        if let Some(s) = hair.sample(wo, h, u, Vec2::new(u, u)) {
                            assert!(
                                s.weight.is_finite() && s.weight.min_element() >= 0.0 && s.wi.is_finite(),
                                "{s:?}"
                            );
                        }
                    }
                    for _ in 0..200 {
                        let wi = random_dir(&mut rng);
                        let (e, p) = (hair.eval(wo, wi, h), hair.pdf(wo, wi, h));
                        assert!(e.is_finite() && e.min_element() >= 0.0 && p.is_finite() && p >= 0.0);
                    }
                }
            }
        }
    }

    /// Mp of one lobe of variance `v` (lane 0 of [`mp4`]).
    fn mp(cos_i: f32, cos_o: f32, sin_i: f32, sin_o: f32, v: f32) -> f32 {
        let s = F4::splat;
        mp4(cos_i, sin_i, s(cos_o), s(sin_o), s(1.0 / v), s(mp_k(v))).to_array()[0]
    }

    /// ln I0(x) - x as [`mp4`] computes it: ln Mp at theta_i = theta_o = 0 (1 - c = 0), with
    /// 1 / v = x and K = 0.
    fn ln_i0_minus_x(x: f32) -> f32 {
        let s = F4::splat;
        mp4(1.0, 0.0, s(1.0), s(0.0), s(x), s(0.0)).ln().to_array()[0]
    }

    #[test]
    fn longitudinal_term_is_normalised_even_for_tiny_roughness() {
        // int Mp(theta_i) cos theta_i dtheta_i = 1 for any theta_o and v, including v = 1e-4
        // where sinh(1 / v) overflows f32.
        for v in [1.3e-7f32, 1e-6, 1e-4, 0.01, 0.1, 0.5, 2.0] {
            for sin_o in [0.0f32, 0.5, -0.9, -0.999_999_9] {
                let cos_o = safe_sqrt(1.0 - sin_o * sin_o);
                let n = 200_000;
                let mut s = 0.0f64;
                for k in 0..n {
                    let t = -PI / 2.0 + PI * (k as f32 + 0.5) / n as f32;
                    s += (mp(t.cos(), cos_o, t.sin(), sin_o, v) * t.cos()) as f64;
                }
                let integral = s * std::f64::consts::PI / n as f64;
                assert!((integral - 1.0).abs() < 0.001, "v {v} sin_o {sin_o}: {integral}");
            }
        }
    }

    #[test]
    /// ln I0 - x by the polynomial fits against the power series in f64 (summed until its
    /// terms no longer count), over the arguments Mp passes (cos cos / v: up to 1 / v, v down
    /// to about 1.3e-7 at the smallest roughness, so up to 7.6e6).
    fn bessel_i0_fits_match_the_series() {
        fn series(x: f64) -> f64 {
            let x2 = x * x * 0.25;
            let (mut sum, mut term) = (1.0f64, 1.0f64);
            for k in 1..2000 {
                term *= x2 / (k as f64 * k as f64);
                sum += term;
                if term < 1e-18 * sum {
                    break;
                }
            }
            sum
        }
        fn ln_reference(x: f64) -> f64 {
            if x <= 50.0 {
                series(x).ln()
            } else {
                // The asymptotic series, its next term below 2e-8 here.
                let y = 1.0 / x;
                x - 0.5 * (2.0 * std::f64::consts::PI * x).ln()
                    + (1.0 + y / 8.0 + 9.0 * y * y / 128.0 + 225.0 * y * y * y / 3072.0).ln()
            }
        }
        let mut worst = (0.0f64, 0.0f64);
        for k in 0..=20_000 {
            let x = k as f32 * 0.0005; // 0 to 10
            let (got, want) = ((ln_i0_minus_x(x) + x) as f64, series(x as f64).ln());
            let err = (got - want).abs() / want.abs().max(1.0);
            assert!(err < 5e-7, "ln I0({x}) = {got}, series {want}, error {err:e}");
            worst.0 = worst.0.max(err);
        }
        for k in 0..=4_000 {
            // 0 to about 1.7e7, denser near 0.
            let x = (k as f32 * 0.006).exp2() - 1.0;
            let (got, want) = (ln_i0_minus_x(x) as f64, ln_reference(x as f64) - x as f64);
            let err = (got - want).abs() / want.abs().max(1.0);
            assert!(err < 5e-7, "ln I0({x}) - {x} = {got}, series {want}, error {err:e}");
            worst.1 = worst.1.max(err);
        }
        assert_eq!(ln_i0_minus_x(0.0), 0.0);
        eprintln!("worst: ln I0 to 10 {:e}, ln I0 - x {:e}", worst.0, worst.1);
    }

    #[test]
    fn reflectance_maps_to_sigma_a_by_the_papers_polynomial() {
        // beta_n = 0.3: D = 5.969 - 0.0645 + 0.22788 - 0.28971 + 0.0451494 + 0.00059535.
        let d = 5.969 - 0.215 * 0.3 + 2.532 * 0.09 - 10.73 * 0.027 + 5.574 * 0.0081 + 0.245 * 0.00243;
        let s = Hair::sigma_a_from_reflectance(Rgb::new(0.5, 0.25, 0.1), 0.3);
        for (c, x) in [(0.5f64, s.x), (0.25, s.y), (0.1, s.z)] {
            let want = (c.ln() / d).powi(2);
            assert!((x as f64 - want).abs() < 1e-5 * want.max(1e-3), "{x} vs {want}");
        }
    }
}
