//! Mitsuba's `conductor` (smooth mirror) and `roughconductor` (Walter et al. 2007 microfacet
//! reflection: f = F(wo.m) D(m) G(wo, wi) / (4 cos_o cos_i)), with exact complex Fresnel.

use glam::{Vec2, Vec3};

use super::microfacet::{fresnel_conductor, reflect, Distribution, Microfacet};
use super::BsdfSample;
use crate::math::Rgb;
use crate::texture::{TexCoord, Texture};

/// Roughness of a microfacet BSDF; `alpha_u`/`alpha_v` are float textures (red channel).
#[derive(Clone, Debug)]
pub struct Roughness {
    pub dist: Distribution,
    pub alpha_u: Texture,
    pub alpha_v: Texture,
}

impl Roughness {
    #[inline]
    pub fn at(&self, uv: TexCoord) -> Microfacet {
        Microfacet::new(self.dist, self.alpha_u.eval(uv).x, self.alpha_v.eval(uv).x)
    }
}

#[derive(Clone, Debug)]
pub struct Conductor {
    pub eta: Rgb,
    pub k: Rgb,
    pub specular_reflectance: Texture,
    /// `None`: the smooth `conductor`.
    pub rough: Option<Roughness>,
}

impl Conductor {
    /// The value (f |cos|) and the pdf of `wi`, computed together: they share the half
    /// vector, the roughness lookup, D and G1(wo).
    #[inline]
    pub fn eval_pdf(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> (Rgb, f32) {
        let Some(r) = &self.rough else { return (Rgb::ZERO, 0.0) };
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return (Rgb::ZERO, 0.0);
        }
        let m = (wo + wi).normalize();
        let mf = r.at(uv);
        let (d, g, pdf_m) = mf.terms(wo, wi, m);
        let f = fresnel_conductor(wo.dot(m), self.eta, self.k);
        let v = d * g / (4.0 * wo.z);
        (self.specular_reflectance.eval(uv) * f * v, pdf_m / (4.0 * wo.dot(m)))
    }

    #[inline]
    pub fn sample(&self, uv: TexCoord, wo: Vec3, u: Vec2) -> Option<BsdfSample> {
        if wo.z <= 0.0 {
            return None;
        }
        let Some(r) = &self.rough else {
            let wi = Vec3::new(-wo.x, -wo.y, wo.z);
            let f = fresnel_conductor(wo.z, self.eta, self.k);
            return Some(BsdfSample {
                wi,
                weight: self.specular_reflectance.eval(uv) * f,
                pdf: 1.0,
                delta: true,
                eta: 1.0,
            });
        };
        let m = r.at(uv).sample_normal(wo, u);
        let wi = reflect(wo, m);
        // (A normal of pdf 0 leads to a direction of pdf 0 below: from wo.m <= 0, wi lies
        // below the surface or its half vector is -m, where D is 0.)
        if wi.z <= 0.0 {
            return None;
        }
        // pdf and value from wi, exactly as `eval_pdf` computes them for light sampling, so
        // that MIS sees the same numbers whichever strategy produced the direction.
        let (value, pdf) = self.eval_pdf(uv, wo, wi);
        if !(pdf > 0.0) {
            return None;
        }
        let weight = value / pdf;
        weight.is_finite().then_some(BsdfSample { wi, weight, pdf, delta: false, eta: 1.0 })
    }
}

/// Complex refractive index (eta, k) in linear RGB of Mitsuba's `material` names that Furnace
/// knows. "none" is a perfect mirror.
pub fn conductor_preset(name: &str) -> Option<(Rgb, Rgb)> {
    Some(match name {
        "none" => (Rgb::ZERO, Rgb::ONE),
        "Au" => (Rgb::new(0.143119, 0.374957, 1.44248), Rgb::new(3.98316, 2.38572, 1.60322)),
        "Ag" => (Rgb::new(0.155265, 0.116723, 0.138342), Rgb::new(4.82835, 3.12225, 2.14696)),
        "Cu" => (Rgb::new(0.200438, 0.924033, 1.10221), Rgb::new(3.91295, 2.45285, 2.14219)),
        "Al" => (Rgb::new(1.65746, 0.880369, 0.521229), Rgb::new(9.22387, 6.26952, 4.837)),
        _ => return None,
    })
}

pub const CONDUCTOR_PRESETS: &[&str] = &["none", "Au", "Ag", "Cu", "Al"];

/// Scene loading: `conductor` and `roughconductor` (`material` preset or `eta` + `k`,
/// `specular_reflectance`; the rough one's distribution and alpha).
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<super::Bsdf> {
    let (eta, k) = b.conductor_ior(i)?;
    Ok(super::Bsdf::Conductor(Conductor {
        eta,
        k,
        specular_reflectance: b.color(i, "specular_reflectance", Rgb::ONE)?,
        rough: b.roughness(i)?,
    }))
}
