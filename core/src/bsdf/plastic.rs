//! Mitsuba's `plastic` and `roughplastic`: a dielectric coating over a diffuse base, with
//! internal reflections inside the coating accounted for in the diffuse term:
//!   f_d = T(cos_o) T(cos_i) R / (pi eta^2 (1 - F_dr))      (`nonlinear` false)
//! where T is the coating's transmittance (1 - Fresnel when smooth; the transmittance of the
//! rough interface, tabulated, when rough) and F_dr its hemispherical internal reflectance.
//! The smooth coating reflects as a delta lobe; the rough one as a microfacet lobe
//! F D G / (4 cos_o cos_i).

use glam::{Vec2, Vec3};

use super::conductor::Roughness;
use super::microfacet::{fresnel_dielectric, reflect, refract};
use super::BsdfSample;
use crate::math::{square_to_cosine_hemisphere, Rgb, INV_PI};
use crate::texture::{TexCoord, Texture};

#[derive(Clone, Debug)]
pub struct Plastic {
    pub eta: f32,
    pub diffuse_reflectance: Texture,
    pub specular_reflectance: Texture,
    /// Hemispherical reflectance of the coating seen from inside.
    pub fdr_int: f32,
    /// Mitsuba's `nonlinear`: the internal scattering term also darkens and saturates colour.
    pub nonlinear: bool,
    /// Prior probability of choosing the specular lobe (before Fresnel), from the mean
    /// specular and diffuse reflectances, as Mitsuba.
    pub specular_weight: f32,
    /// `roughplastic`: the coating's roughness and its tabulated transmittance.
    pub rough: Option<RoughCoating>,
}

/// A rough coating: microfacet roughness (constant: the table depends on it) and the
/// transmittance of the interface from outside, tabulated over cos theta.
#[derive(Clone, Debug)]
pub struct RoughCoating {
    pub roughness: Roughness,
    /// T(mu) at mu = (i + 0.5) / TABLE, linearly interpolated.
    pub transmittance: Vec<f32>,
}

const TABLE: usize = 64;

impl RoughCoating {
    /// Tabulates the transmittance of a rough interface of relative index `eta` seen from
    /// outside, and returns it with the hemispherical internal reflectance seen from inside,
    /// 2 int R_int(mu) mu dmu (reflected energy: a single-scattering interface also loses
    /// some), both by integrating Furnace's `roughdielectric` with stratified samples.
    pub fn new(roughness: Roughness, eta: f32) -> (RoughCoating, f32) {
        // (transmitted, reflected) energy per mu: over visible microfacets m (stratified),
        // E[(1 - F) G1(w_t, m)] and E[F G1(w_r, m)]; no lobe is sampled, Fresnel weights both.
        // Rows in parallel (each sums its own samples in order: the same values on any
        // number of threads); 1.2M samples in all took 1.66 s of a load on one core.
        use rayon::prelude::*;
        let table = |eta: f32| -> Vec<(f32, f32)> {
            (0..TABLE)
                .into_par_iter()
                .map(|i| {
                    let mu = (i as f32 + 0.5) / TABLE as f32;
                    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
                    let mf = roughness.at(TexCoord::default());
                    let k = 96;
                    let (mut t, mut r) = (0.0f64, 0.0f64);
                    for a in 0..k {
                        for b in 0..k {
                            let u = Vec2::new((a as f32 + 0.5) / k as f32, (b as f32 + 0.5) / k as f32);
                            let m = mf.sample_normal(wo, u);
                            let (f, cos_t) = fresnel_dielectric(wo.dot(m), eta);
                            let wr = reflect(wo, m);
                            if wr.z > 0.0 {
                                r += (f * mf.g1(wr, m)) as f64;
                            }
                            if f < 1.0 {
                                let wt = refract(wo, m, eta, cos_t);
                                if wt.z < 0.0 {
                                    t += ((1.0 - f) * mf.g1(wt, m)) as f64;
                                }
                            }
                        }
                    }
                    let n = (k * k) as f64;
                    ((t / n) as f32, (r / n) as f32)
                })
                .collect()
        };
        let transmittance = table(eta).into_iter().map(|(t, _)| t).collect();
        let internal: f64 = table(1.0 / eta)
            .iter()
            .enumerate()
            .map(|(i, &(_, r))| 2.0 * r as f64 * (i as f64 + 0.5) / TABLE as f64)
            .sum::<f64>()
            / TABLE as f64;
        (RoughCoating { roughness, transmittance }, internal.clamp(0.0, 1.0) as f32)
    }

    #[inline]
    fn t(&self, mu: f32) -> f32 {
        let x = (mu.clamp(0.0, 1.0) * TABLE as f32 - 0.5).clamp(0.0, (TABLE - 1) as f32);
        let i = (x as usize).min(TABLE - 2);
        let f = x - i as f32;
        self.transmittance[i] * (1.0 - f) + self.transmittance[i + 1] * f
    }
}

impl Plastic {
    /// The coating's transmittance at cos theta `mu`.
    #[inline]
    fn transmittance(&self, mu: f32) -> f32 {
        match &self.rough {
            None => 1.0 - fresnel_dielectric(mu, self.eta).0,
            Some(r) => r.t(mu),
        }
    }

    /// (1 - T(cos_o), probability of sampling the specular lobe).
    #[inline]
    fn probs(&self, cos_o: f32) -> (f32, f32) {
        let f_o = 1.0 - self.transmittance(cos_o);
        let ps = f_o * self.specular_weight;
        let pd = (1.0 - f_o) * (1.0 - self.specular_weight);
        (f_o, ps / (ps + pd))
    }

    /// The rough coating's microfacet reflection (times cos_i) and its pdf.
    #[inline]
    fn specular(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> (Rgb, f32) {
        let Some(r) = &self.rough else { return (Rgb::ZERO, 0.0) };
        let m = (wo + wi).normalize();
        let mf = r.roughness.at(uv);
        let f = fresnel_dielectric(wo.dot(m), self.eta).0;
        let (d, g, pdf_m) = mf.terms(wo, wi, m);
        let value = f * d * g / (4.0 * wo.z);
        (self.specular_reflectance.eval(uv) * value, pdf_m / (4.0 * wo.dot(m)))
    }

    #[inline]
    fn diffuse_value(&self, uv: TexCoord, wi: Vec3, f_o: f32) -> Rgb {
        let f_i = 1.0 - self.transmittance(wi.z);
        let d = self.diffuse_reflectance.eval(uv);
        let r = if self.nonlinear { d / (Rgb::ONE - d * self.fdr_int) } else { d / (1.0 - self.fdr_int) };
        r * ((1.0 - f_o) * (1.0 - f_i) * INV_PI * wi.z / (self.eta * self.eta))
    }

    /// The value (f |cos|) and the pdf of `wi`, computed together: they share the coating's
    /// transmittance towards `wo` and the specular lobe.
    pub fn eval_pdf(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> (Rgb, f32) {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return (Rgb::ZERO, 0.0);
        }
        let (f_o, p_spec) = self.probs(wo.z);
        let (spec, spec_pdf) = self.specular(uv, wo, wi);
        (self.diffuse_value(uv, wi, f_o) + spec, (1.0 - p_spec) * wi.z * INV_PI + p_spec * spec_pdf)
    }

    pub fn sample(&self, uv: TexCoord, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        if wo.z <= 0.0 {
            return None;
        }
        let (f_o, p_spec) = self.probs(wo.z);
        if let Some(r) = &self.rough {
            // Both lobes are non-delta: pick one to sample, weight by the full eval / pdf.
            let wi = if u1 < p_spec {
                reflect(wo, r.roughness.at(uv).sample_normal(wo, u2))
            } else {
                square_to_cosine_hemisphere(u2)
            };
            if wi.z <= 0.0 {
                return None;
            }
            let (value, pdf) = self.eval_pdf(uv, wo, wi);
            if !(pdf > 0.0) {
                return None;
            }
            let weight = value / pdf;
            return weight.is_finite().then_some(BsdfSample { wi, weight, pdf, delta: false, eta: 1.0 });
        }
        if u1 < p_spec {
            return Some(BsdfSample {
                wi: Vec3::new(-wo.x, -wo.y, wo.z),
                weight: self.specular_reflectance.eval(uv) * (f_o / p_spec),
                pdf: p_spec,
                delta: true,
                eta: 1.0,
            });
        }
        let wi = square_to_cosine_hemisphere(u2);
        let pdf = (1.0 - p_spec) * wi.z * INV_PI;
        if !(pdf > 0.0) {
            return None;
        }
        let weight = self.diffuse_value(uv, wi, f_o) / pdf;
        Some(BsdfSample { wi, weight, pdf, delta: false, eta: 1.0 })
    }
}

/// Scene loading: `plastic` and `roughplastic`. The coating's internal diffuse reflectance
/// (`fdr_int`) and the weight of sampling the specular lobe are derived here, from the
/// parameters: the mean specular reflectance over the mean of both reflectances.
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<super::Bsdf> {
    let doc = b.doc;
    let int_ior = b.ior(i, "int_ior", "polypropylene")?;
    let ext_ior = b.ior(i, "ext_ior", "air")?;
    if doc.obj(i).plugin == "roughplastic" {
        b.distinct_iors(i, int_ior, ext_ior)?;
        for name in ["alpha_u", "alpha_v"] {
            if doc.has(i, name) || doc.named_child_exists(i, name) {
                return Err(b.err(
                    doc.pos_of(i, name),
                    "roughplastic does not support anisotropic roughness (alpha_u, alpha_v): give one 'alpha'",
                ));
            }
        }
    }
    let eta = int_ior / ext_ior;
    let diffuse_reflectance = b.color(i, "diffuse_reflectance", Rgb::splat(0.5))?;
    let specular_reflectance = b.color(i, "specular_reflectance", Rgb::ONE)?;
    let d = diffuse_reflectance.mean().element_sum() / 3.0;
    let s = specular_reflectance.mean().element_sum() / 3.0;
    let (rough, fdr_int) = match b.roughness(i)? {
        None => (None, super::microfacet::fresnel_diffuse_reflectance(1.0 / eta)),
        Some(r) => {
            // The coating's transmittance is tabulated for one roughness.
            if !matches!((&r.alpha_u, &r.alpha_v), (Texture::Const(_), Texture::Const(_))) {
                return Err(b.err(doc.obj(i).pos, "roughplastic: alpha must be a constant, not a texture"));
            }
            let (coating, fdr) = RoughCoating::new(r, eta);
            (Some(coating), fdr)
        }
    };
    Ok(super::Bsdf::Plastic(Plastic {
        eta,
        fdr_int,
        nonlinear: doc.boolean_or(i, "nonlinear", false)?,
        specular_weight: s / (d + s),
        diffuse_reflectance,
        specular_reflectance,
        rough,
    }))
}
