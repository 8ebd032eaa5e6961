//! Mitsuba's `plastic`: a smooth dielectric coating (delta specular reflection, Fresnel
//! weighted) over a diffuse base, with internal reflections inside the coating accounted for
//! in the diffuse term (`nonlinear` false):
//!   f_d = (1 - F(cos_o)) (1 - F(cos_i)) R / (pi eta^2 (1 - F_dr))
//! where F_dr is the coating's hemispherical internal Fresnel reflectance.

use glam::{Vec2, Vec3};

use super::microfacet::fresnel_dielectric;
use super::BsdfSample;
use crate::math::{square_to_cosine_hemisphere, Rgb, INV_PI};
use crate::texture::{TexCoord, Texture};

#[derive(Clone, Debug)]
pub struct Plastic {
    pub eta: f32,
    pub diffuse_reflectance: Texture,
    pub specular_reflectance: Texture,
    /// Hemispherical Fresnel reflectance seen from inside the coating.
    pub fdr_int: f32,
    /// Mitsuba's `nonlinear`: the internal scattering term also darkens and saturates colour.
    pub nonlinear: bool,
    /// Prior probability of choosing the specular lobe (before Fresnel), from the mean
    /// specular and diffuse reflectances, as Mitsuba.
    pub specular_weight: f32,
}

impl Plastic {
    #[inline]
    fn probs(&self, cos_o: f32) -> (f32, f32) {
        let (f_o, _) = fresnel_dielectric(cos_o, self.eta);
        let ps = f_o * self.specular_weight;
        let pd = (1.0 - f_o) * (1.0 - self.specular_weight);
        let p_spec = ps / (ps + pd);
        (f_o, p_spec)
    }

    #[inline]
    fn diffuse_value(&self, uv: TexCoord, wi: Vec3, f_o: f32) -> Rgb {
        let (f_i, _) = fresnel_dielectric(wi.z, self.eta);
        let d = self.diffuse_reflectance.eval(uv);
        let r = if self.nonlinear { d / (Rgb::ONE - d * self.fdr_int) } else { d / (1.0 - self.fdr_int) };
        r * ((1.0 - f_o) * (1.0 - f_i) * INV_PI * wi.z / (self.eta * self.eta))
    }

    pub fn eval(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> Rgb {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return Rgb::ZERO;
        }
        let (f_o, _) = fresnel_dielectric(wo.z, self.eta);
        self.diffuse_value(uv, wi, f_o)
    }

    pub fn pdf(&self, _uv: TexCoord, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        let (_, p_spec) = self.probs(wo.z);
        (1.0 - p_spec) * wi.z * INV_PI
    }

    pub fn sample(&self, uv: TexCoord, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        if wo.z <= 0.0 {
            return None;
        }
        let (f_o, p_spec) = self.probs(wo.z);
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
