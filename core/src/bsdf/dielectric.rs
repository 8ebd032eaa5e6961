//! Mitsuba's `dielectric` (smooth), `roughdielectric` (Walter et al. 2007) and
//! `thindielectric`. `eta` = int_ior / ext_ior; the normal points to the exterior.
//!
//! Radiance transport: light refracted into a denser medium is compressed into a smaller solid
//! angle, so transmitted radiance scales by 1 / eta_rel^2 (Veach 1997, ch. 5); the scale is part
//! of `eval` and of the sampled weight, as in Mitsuba's radiance mode.
//!
//! Everything is computed in the frame flipped to the side of `wo` (wo.z > 0), where the
//! relative index is `eta` outside and `1 / eta` inside.

use glam::{Vec2, Vec3};

use super::conductor::Roughness;
use super::microfacet::{fresnel_dielectric, reflect, refract};
use super::BsdfSample;
use crate::math::Rgb;
use crate::texture::{TexCoord, Texture};

#[derive(Clone, Debug)]
pub struct Dielectric {
    pub eta: f32,
    pub specular_reflectance: Texture,
    pub specular_transmittance: Texture,
    /// `None`: the smooth `dielectric`.
    pub rough: Option<Roughness>,
    /// `thindielectric`: a thin slab, transmission straight through.
    pub thin: bool,
}

#[inline]
fn flip(v: Vec3, s: f32) -> Vec3 {
    Vec3::new(v.x, v.y, v.z * s)
}

impl Dielectric {
    /// The delta mirror reflection of `wo`, chosen with probability `prob`.
    #[inline]
    fn mirror(&self, uv: TexCoord, wo: Vec3, prob: f32) -> BsdfSample {
        BsdfSample {
            wi: Vec3::new(-wo.x, -wo.y, wo.z),
            weight: self.specular_reflectance.eval(uv),
            pdf: prob,
            delta: true,
            eta: 1.0,
        }
    }

    /// Relative index seen from wo's side, and the side's sign.
    #[inline]
    fn side(&self, wo: Vec3) -> (f32, f32) {
        if wo.z >= 0.0 {
            (self.eta, 1.0)
        } else {
            (1.0 / self.eta, -1.0)
        }
    }

    /// The microfacet normal (in the flipped frame) joining wo and wi, and whether it is a
    /// reflection; `None` when the configuration is impossible.
    #[inline]
    fn half_vector(wo: Vec3, wi: Vec3, eta: f32) -> Option<(Vec3, bool)> {
        let reflect = wi.z > 0.0;
        let h = if reflect { wo + wi } else { wo + wi * eta };
        let mut m = h.normalize_or_zero();
        if m == Vec3::ZERO {
            return None;
        }
        if m.z < 0.0 {
            m = -m;
        }
        // wo must see the front of m; wi must lie on m's correct side.
        if wo.dot(m) <= 0.0 || (wi.dot(m) > 0.0) != reflect {
            return None;
        }
        Some((m, reflect))
    }

    /// The value (f |cos|) and the pdf of `wi`, computed together: they share the half
    /// vector, the Fresnel term, the roughness lookup, D and G1(wo).
    pub fn eval_pdf(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> (Rgb, f32) {
        let Some(r) = &self.rough else { return (Rgb::ZERO, 0.0) };
        if wo.z == 0.0 {
            return (Rgb::ZERO, 0.0);
        }
        let (eta, s) = self.side(wo);
        let (wo, wi) = (flip(wo, s), flip(wi, s));
        let Some((m, is_reflect)) = Self::half_vector(wo, wi, eta) else { return (Rgb::ZERO, 0.0) };
        let mf = r.at(uv);
        let (f, _) = fresnel_dielectric(wo.dot(m), eta);
        let (d, g, pdf_m) = mf.terms(wo, wi, m);
        let dg = d * g;
        if is_reflect {
            (self.specular_reflectance.eval(uv) * (f * dg / (4.0 * wo.z)), f * pdf_m / (4.0 * wo.dot(m)))
        } else {
            let denom = wo.dot(m) + eta * wi.dot(m);
            let v = (1.0 - f) * dg * (wo.dot(m) * wi.dot(m)).abs() / (wo.z * denom * denom);
            // Radiance mode: eta^2 of the Jacobian cancels the 1 / eta^2 radiance scale.
            let pdf = (1.0 - f) * pdf_m * eta * eta * wi.dot(m).abs() / (denom * denom);
            (self.specular_transmittance.eval(uv) * v.abs(), pdf)
        }
    }

    pub fn sample(&self, uv: TexCoord, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        if wo.z == 0.0 {
            return None;
        }
        let (eta, s) = self.side(wo);
        let wo_f = flip(wo, s);
        if self.thin {
            let (r, _) = fresnel_dielectric(wo_f.z, self.eta);
            // Inter-reflections inside the slab: R' = R + T^2 R / (1 - R^2).
            let r2 = if r < 1.0 { r + (1.0 - r) * (1.0 - r) * r / (1.0 - r * r) } else { 1.0 };
            return Some(if u1 < r2 {
                self.mirror(uv, wo, r2)
            } else {
                BsdfSample {
                    wi: -wo,
                    weight: self.specular_transmittance.eval(uv),
                    pdf: 1.0 - r2,
                    delta: true,
                    eta: 1.0,
                }
            });
        }
        let Some(r) = &self.rough else {
            let (f, cos_t) = fresnel_dielectric(wo_f.z, eta);
            return Some(if u1 < f {
                self.mirror(uv, wo, f)
            } else {
                let t = refract(wo_f, Vec3::Z, eta, cos_t);
                BsdfSample {
                    wi: flip(t, s),
                    weight: self.specular_transmittance.eval(uv) / (eta * eta),
                    pdf: 1.0 - f,
                    delta: true,
                    eta,
                }
            });
        };
        let mf = r.at(uv);
        // (Its pdf is that of the direction, from `eval_pdf` below: 0 there where m's is.)
        let m = mf.sample_normal(wo_f, u2);
        if wo_f.dot(m) <= 0.0 {
            return None;
        }
        let (f, cos_t) = fresnel_dielectric(wo_f.dot(m), eta);
        let (wi_f, is_reflect) =
            if u1 < f { (reflect(wo_f, m), true) } else { (refract(wo_f, m, eta, cos_t), false) };
        if (wi_f.z > 0.0) != is_reflect || wi_f.z == 0.0 {
            return None; // the sampled microfacet sends the ray to the wrong side
        }
        let wi = flip(wi_f, s);
        let (value, pdf) = self.eval_pdf(uv, wo, wi);
        if !(pdf > 0.0) {
            return None;
        }
        let weight = value / pdf;
        weight.is_finite().then_some(BsdfSample {
            wi,
            weight,
            pdf,
            delta: false,
            eta: if is_reflect { 1.0 } else { eta },
        })
    }
}

/// Scene loading: `dielectric`, `roughdielectric` and `thindielectric` (`int_ior`, `ext_ior`,
/// `specular_reflectance`, `specular_transmittance`; the rough one's distribution and alpha).
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<super::Bsdf> {
    let plugin = b.doc.obj(i).plugin.as_str();
    let int_ior = b.ior(i, "int_ior", "bk7")?;
    let ext_ior = b.ior(i, "ext_ior", "air")?;
    if plugin == "roughdielectric" {
        b.distinct_iors(i, int_ior, ext_ior)?;
    }
    Ok(super::Bsdf::Dielectric(Dielectric {
        eta: int_ior / ext_ior,
        specular_reflectance: b.color(i, "specular_reflectance", Rgb::ONE)?,
        specular_transmittance: b.color(i, "specular_transmittance", Rgb::ONE)?,
        rough: b.roughness(i)?,
        thin: plugin == "thindielectric",
    }))
}
