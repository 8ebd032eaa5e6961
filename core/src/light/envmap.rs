//! Mitsuba's `envmap`: a lat-long environment, u = atan2(d.x, -d.z) / 2pi, v = acos(d.y) / pi
//! in the emitter's frame (row 0 = +y), bilinear lookup with texel centres at
//! ((i + 0.5) / W, (j + 0.5) / H), periodic in u.
//!
//! Importance sampling: a texel is chosen with probability proportional to its sampling
//! luminance s times its solid angle, (2 pi / W) (cos theta_top - cos theta_bottom), through
//! f64 CDFs (a marginal over rows, a conditional within the row); the direction is then uniform
//! in solid angle inside the texel (uniform phi, uniform cos theta). The density is constant
//! per texel, pdf(w) = s(texel) / sum(s Omega), and evaluating it needs no approximation.
//!
//! With nearest lookup s is the texel's luminance, so every sample's weight L / pdf has the
//! map's luminance integral as luminance. With bilinear lookup a texel also shows its
//! neighbours' radiance (the edge of a small sun), so s is the largest luminance of its 3 x 3
//! neighbourhood: the density then covers everything the lookup can return and L / pdf stays
//! bounded by sum(s Omega).

use std::sync::Arc;

use glam::{Mat3, Vec2, Vec3};

use crate::math::{luminance, square_to_uniform_sphere, Rgb, INV_FOUR_PI, PI};
use crate::texture::{Bitmap, FilterType};

#[derive(Clone, Debug)]
pub struct EnvMap {
    bitmap: Arc<Bitmap>,
    scale: f32,
    /// World -> emitter frame (a rotation) and back.
    to_local: Mat3,
    to_world: Mat3,
    filter: FilterType,
    /// Sampling luminance per texel (see the module notes), row-major.
    sample_lum: Vec<f32>,
    /// Marginal CDF over rows, length H + 1, normalised.
    row_cdf: Vec<f64>,
    /// Conditional CDF within each row, H x (W + 1), each normalised.
    col_cdf: Vec<f64>,
    /// Sum over texels of luminance x solid angle (the map's luminance integral).
    total: f64,
    /// Sample directions uniformly over the sphere instead of by the map's luminance: only
    /// as an ablation (`furnace report`), to show what importance sampling buys.
    pub uniform: bool,
}

impl EnvMap {
    pub fn new(bitmap: Arc<Bitmap>, scale: f32, to_world: Mat3, filter: FilterType) -> EnvMap {
        let (w, h) = (bitmap.width, bitmap.height);
        let lum: Vec<f32> = bitmap.texels.iter().map(|t| (luminance(*t) * scale).max(0.0)).collect();
        let sample_lum: Vec<f32> = match filter {
            FilterType::Nearest => lum,
            _ => (0..w * h)
                .map(|k| {
                    let (i, j) = ((k % w) as i64, (k / w) as i64);
                    let mut m = 0.0f32;
                    for dj in -1..=1 {
                        let jj = (j + dj).clamp(0, h as i64 - 1) as usize;
                        for di in -1..=1 {
                            let ii = (i + di).rem_euclid(w as i64) as usize;
                            m = m.max(lum[jj * w + ii]);
                        }
                    }
                    m
                })
                .collect(),
        };
        let mut row_cdf = vec![0.0f64; h + 1];
        let mut col_cdf = vec![0.0f64; h * (w + 1)];
        for j in 0..h {
            let omega = Self::texel_solid_angle(j, w, h);
            let row = &mut col_cdf[j * (w + 1)..(j + 1) * (w + 1)];
            for i in 0..w {
                row[i + 1] = row[i] + sample_lum[j * w + i] as f64 * omega;
            }
            let row_sum = row[w];
            if row_sum > 0.0 {
                row.iter_mut().for_each(|c| *c /= row_sum);
            }
            row_cdf[j + 1] = row_cdf[j] + row_sum;
        }
        let total = row_cdf[h];
        if total > 0.0 {
            row_cdf.iter_mut().for_each(|c| *c /= total);
        }
        EnvMap {
            bitmap,
            scale,
            to_local: to_world.transpose(),
            to_world,
            filter,
            sample_lum,
            row_cdf,
            col_cdf,
            total,
            uniform: false,
        }
    }

    fn texel_solid_angle(j: usize, w: usize, h: usize) -> f64 {
        let t0 = std::f64::consts::PI * j as f64 / h as f64;
        let t1 = std::f64::consts::PI * (j + 1) as f64 / h as f64;
        2.0 * std::f64::consts::PI / w as f64 * (t0.cos() - t1.cos())
    }

    /// The sampling normalisation, sum over texels of sampling luminance x solid angle (with
    /// nearest lookup: the map's luminance integral over the sphere).
    pub fn luminance_integral(&self) -> f64 {
        self.total
    }

    /// (u, v) of world direction `d`.
    #[inline]
    fn uv(&self, d: Vec3) -> Vec2 {
        let l = self.to_local * d;
        let mut u = l.x.atan2(-l.z) * (0.5 / PI);
        if u < 0.0 {
            u += 1.0;
        }
        Vec2::new(u, crate::math::safe_acos(l.y) / PI)
    }

    /// The texel containing world direction `d`.
    #[inline]
    fn texel_of(&self, d: Vec3) -> (usize, usize) {
        let uv = self.uv(d);
        let (w, h) = (self.bitmap.width, self.bitmap.height);
        (((uv.x * w as f32) as usize).min(w - 1), ((uv.y * h as f32) as usize).min(h - 1))
    }

    /// Radiance arriving from world direction `d` (pointing away from the scene).
    pub fn eval(&self, d: Vec3) -> Rgb {
        let (w, h) = (self.bitmap.width, self.bitmap.height);
        let c = match self.filter {
            FilterType::Nearest => {
                let (i, j) = self.texel_of(d);
                self.bitmap.texel(i, j)
            }
            _ => {
                let uv = self.uv(d);
                let px = uv.x * w as f32 - 0.5;
                let py = uv.y * h as f32 - 0.5;
                let (fx, fy) = (px.floor(), py.floor());
                let (tx, ty) = (px - fx, py - fy);
                let x0 = (fx as i64).rem_euclid(w as i64) as usize;
                let x1 = (x0 + 1) % w;
                let y0 = (fy as i64).clamp(0, h as i64 - 1) as usize;
                let y1 = (fy as i64 + 1).clamp(0, h as i64 - 1) as usize;
                let b = &self.bitmap;
                (b.texel(x0, y0) * (1.0 - tx) + b.texel(x1, y0) * tx) * (1.0 - ty)
                    + (b.texel(x0, y1) * (1.0 - tx) + b.texel(x1, y1) * tx) * ty
            }
        };
        c * self.scale
    }

    /// Solid-angle density of [`EnvMap::sample`] at world direction `d`.
    pub fn pdf(&self, d: Vec3) -> f32 {
        if self.total <= 0.0 {
            return 0.0;
        }
        if self.uniform {
            return INV_FOUR_PI;
        }
        let (i, j) = self.texel_of(d);
        (self.sample_lum[j * self.bitmap.width + i] as f64 / self.total) as f32
    }

    /// A world direction towards the environment, and its solid-angle pdf.
    pub fn sample(&self, u: Vec2) -> Option<(Vec3, f32)> {
        if self.total <= 0.0 {
            return None;
        }
        if self.uniform {
            return Some((square_to_uniform_sphere(u), INV_FOUR_PI));
        }
        let (w, h) = (self.bitmap.width, self.bitmap.height);
        let (j, fv) = pick(&self.row_cdf, u.y as f64);
        let (i, fu) = pick(&self.col_cdf[j * (w + 1)..(j + 1) * (w + 1)], u.x as f64);
        // Uniform in solid angle within the texel: phi linear, cos theta linear.
        let phi = 2.0 * std::f64::consts::PI * (i as f64 + fu) / w as f64;
        let c0 = (std::f64::consts::PI * j as f64 / h as f64).cos();
        let c1 = (std::f64::consts::PI * (j + 1) as f64 / h as f64).cos();
        let cos_t = c0 + (c1 - c0) * fv;
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        let l = Vec3::new((sin_t * phi.sin()) as f32, cos_t as f32, (-sin_t * phi.cos()) as f32);
        let d = (self.to_world * l).normalize();
        let pdf = self.pdf(d);
        (pdf > 0.0).then_some((d, pdf))
    }
}

/// Samples a normalised CDF: the bin `k` with cdf[k] <= u < cdf[k + 1] and where u falls in
/// it, in [0, 1). Empty bins are never chosen.
fn pick(cdf: &[f64], u: f64) -> (usize, f64) {
    let n = cdf.len() - 1;
    let k = cdf.partition_point(|&c| c <= u).saturating_sub(1).min(n - 1);
    let width = cdf[k + 1] - cdf[k];
    let f = if width > 0.0 { ((u - cdf[k]) / width).clamp(0.0, 1.0 - 1e-12) } else { 0.5 };
    (k, f)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{chi2_test, Grid, Pcg};

    fn sky_with_sun(w: usize, h: usize, sun: (usize, usize), radiance: f32) -> Bitmap {
        let mut texels: Vec<Rgb> = (0..w * h)
            .map(|k| {
                let v = (k / w) as f32 / h as f32;
                Rgb::new(0.1 + 0.3 * v, 0.2, 0.3 - 0.2 * v)
            })
            .collect();
        texels[sun.1 * w + sun.0] = Rgb::splat(radiance);
        Bitmap { width: w, height: h, texels }
    }

    /// A 1e6-radiance sun in one texel of a 1024 x 512 map, nearest lookup: every light sample's
    /// weight L / pdf has the map's luminance integral as luminance.
    #[test]
    fn sun_texel_weights_equal_the_map_integral() {
        let bmp = Arc::new(sky_with_sun(1024, 512, (700, 150), 1e6));
        let rot = Mat3::from_rotation_y(0.7);
        let env = EnvMap::new(bmp.clone(), 1.0, rot, FilterType::Nearest);
        // The integral, summed independently in f64.
        let mut integral = 0.0f64;
        for j in 0..512 {
            let omega = EnvMap::texel_solid_angle(j, 1024, 512);
            for i in 0..1024 {
                integral += luminance(bmp.texel(i, j)) as f64 * omega;
            }
        }
        // Same terms, summed in another order.
        assert!(
            (env.luminance_integral() / integral - 1.0).abs() < 1e-9,
            "{} vs {integral}",
            env.luminance_integral()
        );
        let mut rng = Pcg::new(9);
        let mut sun_hits = 0;
        for _ in 0..20_000 {
            let (d, pdf) = env.sample(rng.next_2d()).expect("sample");
            let weight = env.eval(d) / pdf;
            let lum = luminance(weight) as f64;
            assert!((lum / integral - 1.0).abs() < 1e-3, "weight {lum} vs integral {integral}");
            if env.eval(d).x > 1e5 {
                sun_hits += 1;
            }
        }
        // The sun holds most of the power: most samples go there.
        assert!(sun_hits > 15_000, "{sun_hits}");
    }

    #[test]
    fn sampled_directions_follow_the_pdf() {
        for filter in [FilterType::Nearest, FilterType::Bilinear] {
            let bmp = Arc::new(sky_with_sun(64, 32, (40, 10), 300.0));
            let env = EnvMap::new(bmp, 2.0, Mat3::from_rotation_x(0.3), filter);
            let r = chi2_test(
                200_000,
                Grid::uniform(16, 32),
                4,
                |rng| env.sample(rng.next_2d()).map(|(d, _)| d),
                |d| env.pdf(d) as f64,
                |_| true,
            );
            assert!(r.p_value > 1e-3, "{filter:?}: {r:?}");
            // Quadrature of a pdf that is discontinuous at every texel edge: accurate to ~0.5%.
            assert!((r.pdf_integral - 1.0).abs() < 5e-3, "{filter:?}: {r:?}");
            // The discrete distribution itself is normalised exactly.
            assert_eq!(*env.row_cdf.last().unwrap(), 1.0);
        }
    }

    #[test]
    fn lookup_follows_mitsubas_orientation() {
        // Row 0 is +y; u = 0 is -z, u = 0.25 is +x.
        let (w, h) = (8, 4);
        let mut texels = vec![Rgb::ZERO; w * h];
        texels[0] = Rgb::X; // top row, u in [0, 1/8): up and towards -z
        texels[3 * w + 2] = Rgb::Y; // bottom row, u in [0.25, 0.375): down and towards +x
        let env = EnvMap::new(
            Arc::new(Bitmap { width: w, height: h, texels }),
            1.0,
            Mat3::IDENTITY,
            FilterType::Nearest,
        );
        let d = |u: f32, v: f32| {
            let (phi, theta) = (2.0 * PI * u, PI * v);
            Vec3::new(theta.sin() * phi.sin(), theta.cos(), -theta.sin() * phi.cos())
        };
        assert_eq!(env.eval(d(0.06, 0.1)), Rgb::X);
        assert_eq!(env.eval(d(0.3, 0.9)), Rgb::Y);
        assert!((d(0.25, 0.5) - Vec3::X).length() < 1e-6);
    }
}
