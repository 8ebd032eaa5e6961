//! Mitsuba's `envmap`: a lat-long environment, u = atan2(d.x, -d.z) / 2pi, v = acos(d.y) / pi
//! in the emitter's frame (row 0 = +y), bilinear lookup with texel centres at
//! ((i + 0.5) / W, (j + 0.5) / H), periodic in u, clamped in v.
//!
//! Importance sampling follows the lookup. With bilinear lookup, radiance (and so its
//! luminance) is bilinear between texel centres. On a grid of W x 2H cells whose vertices lie
//! at the texel centres in u (the grid starts half a texel in) and, in v, at the texel centres
//! and half-way between them (half-height cells, so that the clamped half texels at the poles
//! are cells too), the lookup's luminance is exactly piecewise bilinear. The sampling density
//! over (u, v) is that grid with each vertex value multiplied by sin(theta) at the vertex: the
//! solid-angle Jacobian 2 pi^2 sin(theta), up to its linear interpolation across half a texel.
//! So a sample's weight L / pdf is the map's luminance integral, to within that interpolation
//! (under 0.5% away from the poles on a 1024 x 512 map), wherever the map is not black: a
//! three-texel sun is sampled where, and as much as, the lookup makes it shine. With nearest
//! lookup each texel's luminance is constant over its two cells, times sin(theta) interpolated
//! between the cells' edges. Maps shorter than 16 texels get more rows of cells per texel (a
//! power of two), so that sin(theta) is still followed (a 1 x 1 map has 32).
//!
//! The density is sampled by hierarchical warping (a tree of cell sums with 4 x 4 children a
//! node, over sums of 2 x 2 cells): the sample descends from the root, choosing in each block
//! first the column, then the row, by their sums, and rescales itself to stay uniform; last
//! it chooses among the 2 x 2 cells the same way; inside the cell it inverts the bilinear
//! patch, its marginal (linear in v) and then its conditional (linear in u). The pdf of any
//! direction is the bilinear value at its (u, v) over the grid's integral: no tree walk, and
//! exact for every direction.
//!
//! MIS compensation (Karlik et al. 2019): where a map is lit no more than its average, BSDF
//! sampling already does well, so light sampling can leave those directions to it. The
//! compensated density subtracts the map's mean luminance (over solid angle) from every
//! vertex's luminance, clamped at zero; if nothing is left (a constant map), light sampling
//! leaves the whole map to BSDF sampling, as it does a `constant` emitter (its density is
//! empty: no samples, pdf 0). It is only unbiased beside BSDF sampling with MIS (every non-delta BSDF
//! samples all directions it reflects into), so the integrator's light-sampling-only ablation
//! builds the map without it.

use std::f64::consts::PI as PI64;
use std::sync::Arc;

use glam::{Mat3, Vec2, Vec3};

use crate::math::{square_to_uniform_sphere, Rgb, INV_FOUR_PI, PI};
use crate::simd::F4;
use crate::texture::{Bitmap, FilterType};

/// The largest f64 below 1: where a rescaled sample number must stay.
const ONE_BELOW: f64 = 1.0 - f64::EPSILON / 2.0;

#[derive(Clone, Debug)]
pub struct EnvMap {
    /// The map's texels, bordered for the lookup ([`Bordered`]).
    texels: Bordered,
    scale: f32,
    /// World -> emitter frame (a rotation) and back.
    to_local: Mat3,
    to_world: Mat3,
    filter: FilterType,
    /// The sampling density (see the module notes).
    warp: Warp,
    /// Where the grid's first cell starts in u: half a texel with bilinear lookup, 0 with
    /// nearest.
    u_shift: f32,
    /// The map's luminance integral over the sphere (texel by texel, exact solid angles).
    integral: f64,
    /// Whether `warp` is MIS-compensated.
    compensated: bool,
    /// Sample directions uniformly over the sphere instead of by the map's luminance: only
    /// as an ablation (`furnace report`), to show what importance sampling buys.
    pub uniform: bool,
}

impl EnvMap {
    /// `compensate`: MIS compensation (module notes); only for integrators that combine light
    /// sampling with BSDF sampling by MIS.
    pub fn new(
        bitmap: Arc<Bitmap>,
        scale: f32,
        to_world: Mat3,
        filter: FilterType,
        compensate: bool,
    ) -> EnvMap {
        let (w, h) = (bitmap.width, bitmap.height);
        // Luminance in f64 (finite texels times a large scale may overflow f32), and the map's
        // integral from the texels' exact solid angles.
        let texel_lum = |t: &Rgb| (crate::math::luminance_f64(*t) * scale as f64).max(0.0);
        let max = bitmap.texels.iter().map(texel_lum).fold(0.0, f64::max);
        let integral: f64 = (0..h)
            .map(|j| {
                let (t0, t1) = (PI64 * j as f64 / h as f64, PI64 * (j + 1) as f64 / h as f64);
                let row: f64 = bitmap.texels[j * w..(j + 1) * w].iter().map(texel_lum).sum();
                row * (t0.cos() - t1.cos()) * 2.0 * PI64 / w as f64
            })
            .sum();
        // The tables hold luminance over the brightest texel's, in [0, 1]: their f32 sums
        // (at most 4 per texel) cannot overflow. The density does not depend on the unit.
        let unit = if max > 0.0 && max.is_finite() { 1.0 / max } else { 0.0 };
        let lum: Vec<f32> = bitmap.texels.iter().map(|t| (texel_lum(t) * unit) as f32).collect();
        let r = rows_per_texel(h);
        let (nu, nv) = (w, r * h);
        let u_shift = if filter == FilterType::Nearest { 0.0 } else { 0.5 / w as f32 };
        // Luminance at the grid's vertices (bilinear lookup: exact, as the lookup is linear in
        // v between texel centres, which are vertices) or per texel (nearest).
        let grid_lum: Vec<f32> = match filter {
            FilterType::Nearest => lum,
            _ => {
                let lum = lum; // dropped once the vertices are made
                (0..=nv)
                    .flat_map(|k| {
                        let py = (k as f64 / r as f64 - 0.5).max(0.0);
                        let r0 = (py as usize).min(h - 1);
                        let r1 = (r0 + 1).min(h - 1);
                        let t = (py - r0 as f64).min(1.0) as f32;
                        let lum = &lum;
                        (0..=nu).map(move |i| {
                            let c = i % w;
                            lum[r0 * w + c] * (1.0 - t) + lum[r1 * w + c] * t
                        })
                    })
                    .collect()
            }
        };
        let build = |sub: f32| -> Warp {
            let sin: Vec<f32> = (0..=nv).map(|k| (PI64 * k as f64 / nv as f64).sin() as f32).collect();
            let corners = match filter {
                FilterType::Nearest => Corners::Cells {
                    value: grid_lum.iter().map(|&l| (l - sub).max(0.0)).collect(),
                    rows_per_texel: r,
                    sin_edge: sin,
                },
                _ => Corners::Vertices(
                    grid_lum
                        .iter()
                        .enumerate()
                        .map(|(n, &l)| (l - sub).max(0.0) * sin[n / (nu + 1)])
                        .collect(),
                ),
            };
            Warp::new(nu, nv, corners)
        };
        // What the grid's total would be without compensation (its integral over du dv, times
        // nu nv).
        let full_total = integral * unit * (nu * nv) as f64 / (2.0 * PI64 * PI64);
        let (warp, compensated) =
            match (compensate && integral > 0.0).then(|| build((integral / (4.0 * PI64) * unit) as f32)) {
                Some(c) if c.total > 1e-6 * full_total => (c, true),
                // Nothing left but rounding (a constant map): an empty density, all of the map
                // left to BSDF sampling.
                Some(mut c) => {
                    c.total = 0.0;
                    (c, true)
                }
                None => (build(0.0), false),
            };
        EnvMap {
            texels: Bordered::new(&bitmap),
            scale,
            to_local: to_world.transpose(),
            to_world,
            filter,
            warp,
            u_shift,
            integral,
            compensated,
            uniform: false,
        }
    }

    /// Bytes the bordered texels and the sampling tables of a `w` x `h` map hold while they
    /// are built (at their peak) and keep, for the scene's memory budget.
    pub fn table_bytes(w: usize, h: usize, filter: FilterType) -> (u64, u64) {
        let (w, h) = (w as u64, h as u64);
        let (nu, nv) = (w, rows_per_texel(h as usize) as u64 * h);
        let mut levels = 0;
        let (mut lw, mut lh) = (nu.div_ceil(2), nv.div_ceil(2));
        loop {
            levels += 64 * lw.div_ceil(4) * lh.div_ceil(4);
            if lw == 1 && lh == 1 {
                break;
            }
            (lw, lh) = (lw.div_ceil(4), lh.div_ceil(4));
        }
        let (grid, corners) = match filter {
            FilterType::Nearest => (4 * w * h, 4 * w * h + 4 * (nv + 1)),
            _ => (4 * (nu + 1) * (nv + 1), 4 * (nu + 1) * (nv + 1)),
        };
        // The bordered texels, texel luminance (while the grid is made), the grid, the corners
        // being built, and the levels (counted half again: a level and the one made from it
        // are held together), then the guide.
        let bordered = 12 * ((w + 2) * (h + 2) + 1);
        let guide = (GUIDE * GUIDE * std::mem::size_of::<Guide>()) as u64;
        (
            bordered + 4 * w * h + grid + corners + levels + levels / 2 + guide,
            bordered + corners + levels + guide,
        )
    }

    /// The same map with MIS compensation on or off.
    pub fn with_compensation(&self, on: bool) -> EnvMap {
        let bitmap = Arc::new(self.texels.bitmap());
        let mut e = EnvMap::new(bitmap, self.scale, self.to_world, self.filter, on);
        e.uniform = self.uniform;
        e
    }

    /// Whether light sampling uses the MIS-compensated density.
    pub fn compensated(&self) -> bool {
        self.compensated
    }

    /// Whether light sampling has anything to sample: not a black map, nor a constant one
    /// under MIS compensation (both are left to BSDF sampling).
    pub fn is_sampled(&self) -> bool {
        self.warp.total > 0.0
    }

    /// The map's luminance integral over the sphere, texel by texel with their exact solid
    /// angles (the bilinear lookup's differs by its half-texel blur at the poles).
    pub fn luminance_integral(&self) -> f64 {
        self.integral
    }

    /// (u, v) of world direction `d`, and sin(theta): both angles' atan2 in one pass of four
    /// lanes ([`F4::atan2`], `fast_atan2` bit for bit).
    #[inline]
    fn uv(&self, d: Vec3) -> (Vec2, f32) {
        let l = self.to_local * d;
        // theta by atan2, not acos: acos(l.y) rounds to 0 within 2.4e-4 rad of the poles.
        let sin_t = (l.x * l.x + l.z * l.z).sqrt();
        let [phi, theta, _, _] =
            F4::atan2(F4::new([l.x, sin_t, 0.0, 0.0]), F4::new([-l.z, l.y, 1.0, 1.0])).to_array();
        let mut u = phi * (0.5 / PI);
        if u < 0.0 {
            u += 1.0;
        }
        (Vec2::new(u, theta / PI), sin_t)
    }

    /// The lookup at (u, v), scaled: bilinear (u repeats, v is clamped) or nearest.
    #[inline]
    fn lookup(&self, uv: Vec2) -> Rgb {
        let c = match self.filter {
            FilterType::Nearest => self.texels.nearest(uv),
            _ => self.texels.bilinear(uv),
        };
        c * self.scale
    }

    /// Solid-angle density at (u, v) with sin(theta) `sin_t`. The cell is found in f32 as
    /// [`EnvMap::lookup`] finds its texel, so that both agree on which texel (nearest) a
    /// point lies in.
    fn pdf_at(&self, uv: Vec2, sin_t: f64) -> f32 {
        self.pdf_in(uv, sin_t, Cell::NONE)
    }

    /// [`EnvMap::pdf_at`], reading the corners from `near` where (u, v) lies in that cell
    /// ([`Warp::pdf_near`]).
    fn pdf_in(&self, uv: Vec2, sin_t: f64, near: Cell) -> f32 {
        if self.warp.total <= 0.0 {
            return 0.0;
        }
        if self.uniform {
            return INV_FOUR_PI;
        }
        if !(sin_t > 0.0) {
            return 0.0;
        }
        let mut us = uv.x - self.u_shift;
        if us < 0.0 {
            us += 1.0;
        }
        (self.warp.pdf_near(us, uv.y, near) / (2.0 * PI64 * PI64 * sin_t)) as f32
    }

    // The three lookups by direction below take the direction's coordinates as three
    // numbers, which pass in registers: passed as a Vec3 it went through memory, where the
    // callee's 8-byte reads of it could straddle the caller's separate stores and wait for
    // them (store forwarding fails), which cost envmap.xml 6% of its time after an unrelated
    // change to its callers' code.

    /// Radiance arriving from world direction `d` (pointing away from the scene).
    #[inline]
    pub fn eval(&self, d: Vec3) -> Rgb {
        self.eval_at(d.x, d.y, d.z)
    }

    #[inline(never)]
    fn eval_at(&self, x: f32, y: f32, z: f32) -> Rgb {
        self.lookup(self.uv(Vec3::new(x, y, z)).0)
    }

    /// [`EnvMap::eval`] of each of `d` (at most eight) into `out`: the same values, bit for
    /// bit. Where the CPU has AVX2 the directions' angles are computed eight at once.
    ///
    /// # Panics
    /// If `d` holds more than eight directions or `out` fewer than `d`.
    pub fn eval_many(&self, d: &[Vec3], out: &mut [Rgb]) {
        assert!(d.len() <= 8 && out.len() >= d.len(), "{} directions into {}", d.len(), out.len());
        #[cfg(target_arch = "x86_64")]
        if d.len() > 1 && std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU runs AVX2 (checked).
            unsafe { self.eval_many_avx2(d, out) };
            return;
        }
        for (d, o) in d.iter().zip(out) {
            *o = self.eval(*d);
        }
    }

    /// [`EnvMap::eval_many`]: [`EnvMap::uv`] on eight lanes, the same operations in the same
    /// order, then each lane's lookup.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn eval_many_avx2(&self, d: &[Vec3], out: &mut [Rgb]) {
        use std::arch::x86_64::*;
        let n = d.len();
        // (Macros, not closures: nothing here is left to the inliner.)
        macro_rules! lane {
            ($c:ident) => {{
                let a: [f32; 8] = std::array::from_fn(|j| d[j.min(n - 1)].$c);
                _mm256_loadu_ps(a.as_ptr())
            }};
        }
        let (dx, dy, dz) = (lane!(x), lane!(y), lane!(z));
        let m = &self.to_local;
        // Component c of to_local * d, as glam's Mat3 * Vec3 sums it.
        macro_rules! row {
            ($c:ident) => {
                _mm256_add_ps(
                    _mm256_add_ps(
                        _mm256_mul_ps(_mm256_set1_ps(m.x_axis.$c), dx),
                        _mm256_mul_ps(_mm256_set1_ps(m.y_axis.$c), dy),
                    ),
                    _mm256_mul_ps(_mm256_set1_ps(m.z_axis.$c), dz),
                )
            };
        }
        let (lx, ly, lz) = (row!(x), row!(y), row!(z));
        let sin_t = _mm256_sqrt_ps(_mm256_add_ps(_mm256_mul_ps(lx, lx), _mm256_mul_ps(lz, lz)));
        let phi = crate::simd::atan2_avx(lx, _mm256_xor_ps(lz, _mm256_set1_ps(-0.0)));
        let theta = crate::simd::atan2_avx(sin_t, ly);
        let u = _mm256_mul_ps(phi, _mm256_set1_ps(0.5 / PI));
        let below = _mm256_cmp_ps::<_CMP_LT_OQ>(u, _mm256_setzero_ps());
        let u = _mm256_blendv_ps(u, _mm256_add_ps(u, _mm256_set1_ps(1.0)), below);
        let v = _mm256_div_ps(theta, _mm256_set1_ps(PI));
        let (mut us, mut vs) = ([0.0f32; 8], [0.0f32; 8]);
        _mm256_storeu_ps(us.as_mut_ptr(), u);
        _mm256_storeu_ps(vs.as_mut_ptr(), v);
        let t = &self.texels;
        if self.filter != FilterType::Nearest && t.fast {
            // `Bordered::bilinear`'s texel and weights on eight lanes, the same operations in
            // the same order, where every (u, v) lies in the unit square (as a direction's
            // does); then each lane's blend, as `Bordered::lerp` makes it.
            let one = _mm256_set1_ps(1.0);
            let inside = _mm256_and_ps(
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GE_OQ>(u, _mm256_setzero_ps()),
                    _mm256_cmp_ps::<_CMP_LE_OQ>(u, one),
                ),
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GE_OQ>(v, _mm256_setzero_ps()),
                    _mm256_cmp_ps::<_CMP_LE_OQ>(v, one),
                ),
            );
            if _mm256_movemask_ps(inside) == 0xff {
                let half = _mm256_set1_ps(0.5);
                let px = _mm256_sub_ps(_mm256_mul_ps(u, _mm256_set1_ps(t.fw)), half);
                let py = _mm256_sub_ps(_mm256_mul_ps(v, _mm256_set1_ps(t.fh)), half);
                // Truncation, less one below 0 (the mask's -1 added): floor for px >= -0.5.
                // (A macro: a closure here would not inherit the function's AVX2.)
                macro_rules! floor {
                    ($p:expr) => {
                        _mm256_add_epi32(
                            _mm256_cvttps_epi32($p),
                            _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LT_OQ>($p, _mm256_setzero_ps())),
                        )
                    };
                }
                let (x0, y0) = (floor!(px), floor!(py));
                let tx = _mm256_sub_ps(px, _mm256_cvtepi32_ps(x0));
                let ty = _mm256_sub_ps(py, _mm256_cvtepi32_ps(y0));
                let (mut xs, mut ys, mut fx, mut fy) = ([0i32; 8], [0i32; 8], [0.0f32; 8], [0.0f32; 8]);
                _mm256_storeu_si256(xs.as_mut_ptr().cast(), x0);
                _mm256_storeu_si256(ys.as_mut_ptr().cast(), y0);
                _mm256_storeu_ps(fx.as_mut_ptr(), tx);
                _mm256_storeu_ps(fy.as_mut_ptr(), ty);
                for (j, o) in out[..n].iter_mut().enumerate() {
                    // (The bordered texel (x0 + 1, y0 + 1), as `Bordered::bilinear` passes it.)
                    let (xb, yb) = ((xs[j] + 1) as usize, (ys[j] + 1) as usize);
                    *o = t.lerp(xb, yb, fx[j], fy[j]) * self.scale;
                }
                return;
            }
        }
        for (j, o) in out[..n].iter_mut().enumerate() {
            *o = self.lookup(Vec2::new(us[j], vs[j]));
        }
    }

    /// Solid-angle density of [`EnvMap::sample`] at world direction `d`.
    #[inline]
    pub fn pdf(&self, d: Vec3) -> f32 {
        self.pdf_towards(d.x, d.y, d.z)
    }

    #[inline(never)]
    fn pdf_towards(&self, x: f32, y: f32, z: f32) -> f32 {
        let (uv, sin_t) = self.uv(Vec3::new(x, y, z));
        self.pdf_at(uv, sin_t as f64)
    }

    /// [`EnvMap::eval`] and [`EnvMap::pdf`] at once.
    #[inline]
    pub fn eval_pdf(&self, d: Vec3) -> (Rgb, f32) {
        self.eval_pdf_at(d.x, d.y, d.z)
    }

    #[inline(never)]
    fn eval_pdf_at(&self, x: f32, y: f32, z: f32) -> (Rgb, f32) {
        let (uv, sin_t) = self.uv(Vec3::new(x, y, z));
        (self.lookup(uv), self.pdf_at(uv, sin_t as f64))
    }

    /// A world direction towards the environment, the radiance arriving along it and its
    /// solid-angle pdf.
    pub fn sample(&self, u: Vec2) -> Option<(Vec3, Rgb, f32)> {
        let (d, uv, pdf) = self.sample_direction(u)?;
        Some((d, self.radiance_at(uv), pdf))
    }

    /// [`EnvMap::sample`] without the radiance: the direction, the point (u, v) where
    /// [`EnvMap::radiance_at`] gives its radiance, and the pdf. Light sampling looks the
    /// radiance up only once the shadow ray is clear (or, under a light-sample cutoff,
    /// before it).
    pub fn sample_direction(&self, u: Vec2) -> Option<(Vec3, Vec2, f32)> {
        if self.warp.total <= 0.0 {
            return None;
        }
        if self.uniform {
            let d = square_to_uniform_sphere(u);
            return Some((d, self.uv(d).0, INV_FOUR_PI));
        }
        let (us, v, cell) = self.warp.sample(u.x as f64, u.y as f64)?;
        let mut uu = us + self.u_shift;
        if uu >= 1.0 {
            uu -= 1.0;
        }
        // Both angles' sines and cosines at once (`sin_cos_2pi` of each, bit for bit).
        let (sin, cos) = F4::sin_cos_2pi(F4::new([uu, 0.5 * v, 0.0, 0.0]));
        let ([sin_p, sin_t, _, _], [cos_p, cos_t, _, _]) = (sin.to_array(), cos.to_array());
        let l = Vec3::new(sin_t * sin_p, cos_t, -sin_t * cos_p);
        let d = (self.to_world * l).normalize();
        // Radiance and pdf at the same (f32) point, so that they agree on the texel; the pdf
        // reads the sampled cell's corners where the point is in that cell.
        let uv = Vec2::new(uu, v);
        let pdf = self.pdf_in(uv, sin_t as f64, cell);
        (pdf > 0.0).then_some((d, uv, pdf))
    }

    /// The radiance at (u, v) of [`EnvMap::sample_direction`].
    #[inline]
    pub fn radiance_at(&self, uv: Vec2) -> Rgb {
        self.lookup(uv)
    }
}

/// An environment map's texels with a border of one texel, (w + 2) x (h + 2): u repeats, so
/// column 0 holds the last column and column w + 1 the first; v is clamped, so row 0 repeats
/// the first row and row h + 1 the last. A bilinear lookup then reads its four texels at
/// fixed offsets, with no wrapping and no clamping per texel: it is
/// [`Bitmap::bilinear_wrapped`] with `Repeat` in u and `Clamp` in v, bit for bit.
#[derive(Clone, Debug)]
struct Bordered {
    w: usize,
    h: usize,
    /// w and h as f32.
    fw: f32,
    fh: f32,
    /// Both sides below 2^23, where f32 holds every px = u w - 0.5 of the unit square within
    /// [-0.5, w - 0.5] (and py likewise): [`Bordered::bilinear`]'s fast path.
    fast: bool,
    texels: Vec<Rgb>,
}

impl Bordered {
    fn new(b: &Bitmap) -> Bordered {
        let (w, h) = (b.width, b.height);
        // One texel more than the bordered map: a 16-byte load of the last texel stays inside
        // ([`crate::texture::bitmap::blend_unchecked`]).
        // (Allocated once at its size: the scene's memory estimate counts it so.)
        let mut texels = Vec::with_capacity((w + 2) * (h + 2) + 1);
        for r in 0..h + 2 {
            let y = r.saturating_sub(1).min(h - 1);
            texels.extend((0..w + 2).map(|c| b.texel((c + w - 1) % w, y)));
        }
        texels.push(Rgb::ZERO);
        Bordered { w, h, fw: w as f32, fh: h as f32, fast: w < 1 << 23 && h < 1 << 23, texels }
    }

    /// The map without its border.
    fn bitmap(&self) -> Bitmap {
        let mut texels = Vec::with_capacity(self.w * self.h);
        for y in 0..self.h {
            texels.extend((0..self.w).map(|x| self.texel(x, y)));
        }
        Bitmap { width: self.w, height: self.h, texels }
    }

    /// Texel (x, y) of the map.
    #[inline]
    fn texel(&self, x: usize, y: usize) -> Rgb {
        self.texels[(y + 1) * (self.w + 2) + x + 1]
    }

    /// Nearest lookup at (u, v) in [0, 1]^2, as [`EnvMap::lookup`] has always done it.
    #[inline]
    fn nearest(&self, uv: Vec2) -> Rgb {
        let (w, h) = (self.w, self.h);
        self.texel(((uv.x * w as f32) as usize).min(w - 1), ((uv.y * h as f32) as usize).min(h - 1))
    }

    /// Bilinear lookup at (u, v), texel centres at ((i + 0.5) / w, (j + 0.5) / h).
    #[inline]
    fn bilinear(&self, uv: Vec2) -> Rgb {
        let px = uv.x * self.fw - 0.5;
        let py = uv.y * self.fh - 0.5;
        // (u, v) in the unit square, as every direction's is: px in [-0.5, w - 0.5] and py in
        // [-0.5, h - 0.5] (`fast`), where floor is the truncation, less one below 0; the
        // bordered column and row of floor(px) and floor(py) are then 0 to w and 0 to h.
        if !(uv.x >= 0.0 && uv.x <= 1.0 && uv.y >= 0.0 && uv.y <= 1.0 && self.fast) {
            return self.bilinear_anywhere(px, py);
        }
        // SAFETY: px and py are finite and within [-0.5, 2^23].
        let (x0, y0) = unsafe { (px.to_int_unchecked::<i32>(), py.to_int_unchecked::<i32>()) };
        let (x0, y0) = (x0 - (px < 0.0) as i32, y0 - (py < 0.0) as i32);
        self.lerp((x0 + 1) as usize, (y0 + 1) as usize, px - x0 as f32, py - y0 as f32)
    }

    /// [`Bordered::bilinear`] at any (u, v): u repeats, v is clamped.
    #[cold]
    fn bilinear_anywhere(&self, px: f32, py: f32) -> Rgb {
        let (w, h) = (self.w as i64, self.h as i64);
        let (fx0, fy0) = (crate::math::floor(px), crate::math::floor(py));
        let xb = (fx0 as i64).rem_euclid(w) as usize + 1;
        // Clamping the bordered row to [0, h] clamps both rows read as v's clamp does.
        let yb = (fy0 as i64).saturating_add(1).clamp(0, h) as usize;
        self.lerp(xb, yb, px - fx0, py - fy0)
    }

    /// The bilinear blend of the bordered texels (xb, yb) to (xb + 1, yb + 1) with weights
    /// `tx` and `ty` ([`crate::texture::bitmap::blend`], without its bounds check on x86-64).
    #[inline(always)]
    fn lerp(&self, xb: usize, yb: usize, tx: f32, ty: f32) -> Rgb {
        debug_assert!(xb <= self.w && yb <= self.h);
        let (s, i) = (self.w + 2, yb * (self.w + 2) + xb);
        let i = [i, i + 1, i + s, i + s + 1];
        #[cfg(target_arch = "x86_64")]
        // SAFETY: xb <= w and yb <= h, so i + s + 1 <= (h + 1) s + w + 1 = (h + 2) s - 1, and
        // the spare texel at the end of `texels` (index (h + 2) s) follows it.
        return unsafe { crate::texture::bitmap::blend_unchecked(&self.texels, i, tx, ty) };
        #[cfg(not(target_arch = "x86_64"))]
        crate::texture::bitmap::blend(&self.texels, i, tx, ty)
    }
}

/// How the density's cells get their corner values.
#[derive(Clone, Debug)]
enum Corners {
    /// Shared vertices, (nu + 1) x (nv + 1), row by row in v.
    Vertices(Vec<f32>),
    /// One value per texel (nu x nv / rows_per_texel) for each of its cells, times sin(theta)
    /// at the cell's top and bottom edge (nv + 1 edges).
    Cells { value: Vec<f32>, rows_per_texel: usize, sin_edge: Vec<f32> },
}

/// A piecewise-bilinear density on the unit square, nu x nv cells, sampled by hierarchical
/// warping.
#[derive(Clone, Debug)]
struct Warp {
    nu: usize,
    nv: usize,
    corners: Corners,
    /// levels[0] holds the sums of 2 x 2 blocks of cell means, levels[l + 1] the sums of 4 x 4
    /// blocks of levels[l]'s entries; the last is the root, 1 x 1. Entries past the grid's
    /// edge count zero.
    levels: Vec<Level>,
    /// Sum of the cell means (the integral over the square, times nu nv), in f64.
    total: f64,
    /// Where the descent starts for each of GUIDE x GUIDE cells of the sample square, row by
    /// row in uy ([`Warp::guide_for`]).
    guide: Vec<Guide>,
}

/// The guide's cells per side of the sample square.
const GUIDE: usize = 32;

/// A node of the warp's tree and its preimage in the sample square, [x0, x0 + 1 / sx) x
/// [y0, y0 + 1 / sy): the descent maps a point of that rectangle affinely onto the node's own
/// unit square (each step's choice and rescaling is affine in ux, and in uy for a given
/// column), so a sample in the rectangle may start at the node with (ux - x0) sx and
/// (uy - y0) sy instead of at the root.
#[derive(Clone, Copy, Debug)]
struct Guide {
    /// Steps of the descent taken (0 at the root, up to levels.len() - 1), and the node's
    /// entry (x, y) in the level those steps reached (u32: a level has fewer than 2^32
    /// entries a side, as the map has fewer texels).
    depth: u32,
    x: u32,
    y: u32,
    x0: f64,
    sx: f64,
    y0: f64,
    sy: f64,
}

/// One level of the warp's tree: its entries in blocks of 4 x 4 (padded with zeros), each
/// block the children of one entry of the level above, stored together (row by row) so that
/// a step of the descent reads one 64-byte block.
#[derive(Clone, Debug)]
struct Level {
    /// Blocks per row (a quarter of the padded width).
    bw: usize,
    blocks: Vec<Block>,
}

#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Block([f32; 16]);

impl Level {
    fn zeros(w: usize, h: usize) -> Level {
        let (bw, bh) = (w.div_ceil(4), h.div_ceil(4));
        Level { bw, blocks: vec![Block([0.0; 16]); bw * bh] }
    }

    /// The entry at (i, k).
    #[inline]
    fn at(&mut self, i: usize, k: usize) -> &mut f32 {
        &mut self.blocks[k / 4 * self.bw + i / 4].0[(k % 4) * 4 + i % 4]
    }

    /// The 4 x 4 block at (4x, 4y), row by row.
    #[inline]
    fn block(&self, x: usize, y: usize) -> &[f32; 16] {
        &self.blocks[y * self.bw + x].0
    }
}

impl Warp {
    fn new(nu: usize, nv: usize, corners: Corners) -> Warp {
        let mut warp = Warp { nu, nv, corners, levels: Vec::new(), total: 0.0, guide: Vec::new() };
        // The cells' 2 x 2 block sums, straight from their corners.
        let (mut w, mut h) = (nu.div_ceil(2), nv.div_ceil(2));
        let mut cur = Level::zeros(w, h);
        for k in 0..nv {
            for i in 0..nu {
                let m = warp.cell_mean(i, k);
                warp.total += m as f64;
                *cur.at(i / 2, k / 2) += m;
            }
        }
        while w > 1 || h > 1 {
            let mut next = Level::zeros(w.div_ceil(4), h.div_ceil(4));
            for k in 0..h {
                for i in 0..w {
                    let v = *cur.at(i, k);
                    *next.at(i / 4, k / 4) += v;
                }
            }
            warp.levels.push(cur);
            cur = next;
            (w, h) = (w.div_ceil(4), h.div_ceil(4));
        }
        warp.levels.push(cur);
        warp.guide = (0..GUIDE * GUIDE).map(|n| warp.guide_for(n % GUIDE, n / GUIDE)).collect();
        warp
    }

    /// The deepest node whose preimage holds all of the guide's cell (gx, gy), found by
    /// following the descent's splits of the square exactly as [`choose16`] and [`pick4`] make
    /// them (the same f32 column sums, the same f64 running sums). A margin of 1e-12 keeps a
    /// split that rounding could move to either side of the cell's edge from counting as
    /// outside it. Only splits need it: a child's lower edge with no weight before it
    /// (p[k] = 0) or upper edge with none after it (p[k + 1] = sum) is its parent's edge, which
    /// the descent keeps exactly (its tests `x >= p && sum > p`, and the clamps to [0, 1)).
    /// A child of weight 0 has an empty preimage and never holds the cell.
    fn guide_for(&self, gx: usize, gy: usize) -> Guide {
        const MARGIN: f64 = 1e-12;
        let n = GUIDE as f64;
        let (a, b) = (gx as f64 / n, (gx + 1) as f64 / n);
        let (c, d) = (gy as f64 / n, (gy + 1) as f64 / n);
        // The node reached and its preimage [x0, x1) x [y0, y1).
        let (mut depth, mut x, mut y) = (0, 0, 0);
        let (mut x0, mut x1, mut y0, mut y1) = (0.0f64, 1.0f64, 0.0f64, 1.0f64);
        // The part of [lo, hi) that weight k of `w` takes, if it holds [s, t) within the margin.
        let holding = |w: [f64; 4], lo: f64, hi: f64, s: f64, t: f64| -> Option<(usize, f64, f64)> {
            let p = [0.0, w[0], w[0] + w[1], w[0] + w[1] + w[2], w[0] + w[1] + w[2] + w[3]];
            if !(p[4] > 0.0 && p[4] <= f64::MAX) {
                return None;
            }
            (0..4).find_map(|k| {
                // (e0 is lo exactly when p[k] = 0; e1 is hi, not its rounding, when nothing
                // follows. The parent's preimage holds [s, t) at those edges.)
                let (first, last) = (p[k] == 0.0, p[k + 1] == p[4]);
                let e0 = lo + (hi - lo) * (p[k] / p[4]);
                let e1 = if last { hi } else { lo + (hi - lo) * (p[k + 1] / p[4]) };
                let holds = (first || e0 + MARGIN <= s) && (last || t <= e1 - MARGIN);
                (w[k] > 0.0 && holds).then_some((k, e0, e1))
            })
        };
        for lev in self.levels[..self.levels.len() - 1].iter().rev() {
            let blk = lev.block(x, y);
            let Some((dx, e0, e1)) = holding(column_sums(blk), x0, x1, a, b) else { break };
            let rows = std::array::from_fn(|r| blk[4 * r + dx] as f64);
            let Some((dy, f0, f1)) = holding(rows, y0, y1, c, d) else { break };
            (depth, x, y) = (depth + 1, 4 * x + dx, 4 * y + dy);
            (x0, x1, y0, y1) = (e0, e1, f0, f1);
        }
        let (depth, x, y) = (depth as u32, x as u32, y as u32);
        Guide { depth, x, y, x0, sx: 1.0 / (x1 - x0), y0, sy: 1.0 / (y1 - y0) }
    }

    /// The corner values of cell (i, k): [(u0, v0), (u1, v0), (u0, v1), (u1, v1)].
    #[inline]
    fn corners(&self, i: usize, k: usize) -> [f32; 4] {
        match &self.corners {
            Corners::Vertices(g) => {
                let s = self.nu + 1;
                let (a, b) = (k * s + i, (k + 1) * s + i);
                [g[a], g[a + 1], g[b], g[b + 1]]
            }
            Corners::Cells { value, rows_per_texel, sin_edge } => {
                let v = value[k / rows_per_texel * self.nu + i];
                let (t, b) = (v * sin_edge[k], v * sin_edge[k + 1]);
                [t, t, b, b]
            }
        }
    }

    /// [`Warp::corners`] of the 2 x 2 cells at (i, k), in the order [(0, 0), (1, 0), (0, 1), (1, 1)]; cells
    /// past the grid's edge are zero (as [`Warp::cell_mean`] counts them). Shared vertices are
    /// read once.
    #[inline]
    fn corners_2x2(&self, i: usize, k: usize) -> [[f32; 4]; 4] {
        match &self.corners {
            Corners::Vertices(g) if i + 1 < self.nu && k + 1 < self.nv => {
                let s = self.nu + 1;
                let row = |r: usize| -> [f32; 3] {
                    let a = (k + r) * s + i;
                    [g[a], g[a + 1], g[a + 2]]
                };
                let (r0, r1, r2) = (row(0), row(1), row(2));
                [
                    [r0[0], r0[1], r1[0], r1[1]],
                    [r0[1], r0[2], r1[1], r1[2]],
                    [r1[0], r1[1], r2[0], r2[1]],
                    [r1[1], r1[2], r2[1], r2[2]],
                ]
            }
            _ => [(i, k), (i + 1, k), (i, k + 1), (i + 1, k + 1)].map(|(i, k)| {
                if i < self.nu && k < self.nv {
                    self.corners(i, k)
                } else {
                    [0.0; 4]
                }
            }),
        }
    }

    fn cell_mean(&self, i: usize, k: usize) -> f32 {
        if i >= self.nu || k >= self.nv {
            return 0.0;
        }
        let c = self.corners(i, k);
        0.25 * (c[0] + c[1] + c[2] + c[3])
    }

    /// A point (u, v) of the unit square, distributed by the density, and its cell with the
    /// cell's corners.
    fn sample(&self, ux: f64, uy: f64) -> Option<(f32, f32, Cell)> {
        if !(self.total > 0.0) {
            return None;
        }
        let (ux, uy) = (ux.clamp(0.0, ONE_BELOW), uy.clamp(0.0, ONE_BELOW));
        // The descent starts where the guide's cell of (ux, uy) says: the same map as from the
        // root, without its first steps (on a map with a sun, all of them for most samples).
        let g = GUIDE as f64;
        let guide = &self.guide[(uy * g) as usize * GUIDE + (ux * g) as usize];
        self.descend(
            guide,
            ((ux - guide.x0) * guide.sx).clamp(0.0, ONE_BELOW),
            ((uy - guide.y0) * guide.sy).clamp(0.0, ONE_BELOW),
        )
    }

    /// [`Warp::sample`] from the root, without the guide (tests compare the two).
    #[cfg(test)]
    fn sample_unguided(&self, ux: f64, uy: f64) -> Option<(f32, f32, Cell)> {
        if !(self.total > 0.0) {
            return None;
        }
        let root = Guide { depth: 0, x: 0, y: 0, x0: 0.0, sx: 1.0, y0: 0.0, sy: 1.0 };
        self.descend(&root, ux.clamp(0.0, ONE_BELOW), uy.clamp(0.0, ONE_BELOW))
    }

    /// The rest of the descent from `node`, with (ux, uy) in the node's own unit square.
    #[inline(always)]
    fn descend(&self, node: &Guide, mut ux: f64, mut uy: f64) -> Option<(f32, f32, Cell)> {
        let (mut x, mut y) = (node.x as usize, node.y as usize);
        for lev in self.levels[..self.levels.len() - 1 - node.depth as usize].iter().rev() {
            let (dx, dy) = choose16(lev.block(x, y), &mut ux, &mut uy)?;
            (x, y) = (4 * x + dx, 4 * y + dy);
        }
        let (i, k) = (2 * x, 2 * y);
        let quad = self.corners_2x2(i, k);
        let (dx, dy) = choose(quad.map(|c| 0.25 * (c[0] + c[1] + c[2] + c[3])), &mut ux, &mut uy)?;
        (x, y) = (i + dx, k + dy);
        let c = quad[dx + 2 * dy].map(f64::from);
        let fy = sample_linear(uy, c[0] + c[1], c[2] + c[3]);
        let fx = sample_linear(ux, c[0] + (c[2] - c[0]) * fy, c[1] + (c[3] - c[1]) * fy);
        if !(fx.is_finite() && fy.is_finite()) {
            return None;
        }
        let corners = quad[dx + 2 * dy];
        Some((in_cell(x, fx, self.nu), in_cell(y, fy, self.nv), Cell { i: x, k: y, corners }))
    }

    /// Density at (u, v) in the unit square, with respect to du dv (what [`Warp::pdf_near`]
    /// gives with no cell).
    #[cfg(test)]
    fn pdf(&self, u: f32, v: f32) -> f64 {
        self.pdf_near(u, v, Cell::NONE)
    }

    /// [`Warp::pdf`], reading the corners from `near` when (u, v) lies in that cell (as a
    /// sample's point does): the same value, without fetching them again.
    #[inline]
    fn pdf_near(&self, u: f32, v: f32, near: Cell) -> f64 {
        if !(self.total > 0.0) {
            return 0.0;
        }
        // (Sizes and cells through i64: the same values as through usize, in one conversion
        // each instead of several.)
        let (nu, nv) = (self.nu as i64, self.nv as i64);
        let (px, py) = (u * nu as f32, v * nv as f32);
        let i = (px.max(0.0) as i64).min(nu - 1);
        let k = (py.max(0.0) as i64).min(nv - 1);
        let fx = (px - i as f32).clamp(0.0, 1.0) as f64;
        let fy = (py - k as f32).clamp(0.0, 1.0) as f64;
        let (i, k) = (i as usize, k as usize);
        let c = if (i, k) == (near.i, near.k) { near.corners } else { self.corners(i, k) };
        let c = c.map(f64::from);
        let value = (c[0] * (1.0 - fx) + c[1] * fx) * (1.0 - fy) + (c[2] * (1.0 - fx) + c[3] * fx) * fy;
        value * (nu * nv) as f64 / self.total
    }
}

/// A cell of the warp's grid and its corner values ([`Warp::corners`]).
#[derive(Clone, Copy)]
struct Cell {
    i: usize,
    k: usize,
    corners: [f32; 4],
}

impl Cell {
    /// No cell: the corners are always fetched.
    const NONE: Cell = Cell { i: usize::MAX, k: usize::MAX, corners: [0.0; 4] };
}

/// Rows of cells per texel row: two (so that texel centres are vertices), more for maps so
/// short that sin(theta) needs them (32 in all at least), a power of two (so that nearest
/// lookup and the grid agree on rows in f32).
fn rows_per_texel(h: usize) -> usize {
    2 * (16 / h.max(1)).max(1).next_power_of_two()
}

/// (c + f) / n in f32, kept in cell c of n (rounding could carry it into the next cell, which
/// with nearest lookup may be a black texel).
fn in_cell(c: usize, f: f64, n: usize) -> f32 {
    // (Through i64: the same values as from usize, in one conversion instead of several.)
    let (ci, ni) = (c as i64, n as i64);
    let nf = ni as f32;
    let mut x = ((ci as f64 + f.clamp(0.0, 1.0)) / ni as f64) as f32;
    // One or two steps of one ulp; more only past f32's resolution (n > 2^24).
    for _ in 0..4 {
        let cell = (x * nf) as i64;
        if x > 0.0 && cell > ci {
            x = f32::from_bits(x.to_bits() - 1);
        } else if cell < ci {
            x = f32::from_bits(x.to_bits() + 1);
        } else {
            break;
        }
    }
    x
}

/// Chooses one of a 4 x 4 block (row by row): the column by the column sums with `ux`, then
/// the row within it with `uy`, each rescaled to be uniform again (see [`pick4`]). `None` if
/// the block is empty. Half the steps of a 2 x 2 descent, with the same two divisions a step:
/// the descent is a serial chain of them.
#[inline]
fn choose16(b: &[f32; 16], ux: &mut f64, uy: &mut f64) -> Option<(usize, usize)> {
    let (dx, x) = pick4(column_sums(b), *ux)?;
    let (dy, y) = pick4(std::array::from_fn(|r| b[4 * r + dx] as f64), *uy)?;
    (*ux, *uy) = (x, y);
    Some((dx, dy))
}

/// The column sums of a 4 x 4 block, in f32 (the entries are non-negative, so a column sums to
/// 0 only if it is empty): the weights of [`choose16`]'s first choice, and of the guide's
/// splits ([`Warp::guide_for`]), which must be the same numbers.
#[inline(always)]
fn column_sums(b: &[f32; 16]) -> [f64; 4] {
    std::array::from_fn(|j| ((b[j] + b[4 + j]) + (b[8 + j] + b[12 + j])) as f64)
}

/// One of four non-negative weights chosen with `u` in [0, 1): the `k` whose share of their
/// sum holds `u * sum`, and where in that share, rescaled to [0, 1). Never a weight of 0, even
/// when `u * sum` rounds up to the sum. `None` if they sum to 0 or overflow.
#[inline(always)]
fn pick4(w: [f64; 4], u: f64) -> Option<(usize, f64)> {
    // The running sums p1 to p3 and the total, left to right.
    let p1 = w[0];
    let p2 = p1 + w[1];
    let p3 = p2 + w[2];
    let sum = p3 + w[3];
    if !(sum > 0.0 && sum <= f64::MAX) {
        return None;
    }
    let x = u * sum;
    // Past boundary m only if some weight lies beyond it: the last such m has p[m] <= x and,
    // unless x rounded up to the sum, x < p[m + 1]. The three tests hold for a prefix of m
    // (the sums never decrease), so their count is that m; the share's ends are selected,
    // not indexed (an array indexed by k would go through memory).
    let (b1, b2, b3) = (x >= p1 && sum > p1, x >= p2 && sum > p2, x >= p3 && sum > p3);
    let k = b1 as usize + b2 as usize + b3 as usize;
    let lo = if b3 {
        p3
    } else if b2 {
        p2
    } else if b1 {
        p1
    } else {
        0.0
    };
    let hi = if b3 {
        sum
    } else if b2 {
        p3
    } else if b1 {
        p2
    } else {
        p1
    };
    Some((k, ((x - lo) / (hi - lo)).clamp(0.0, ONE_BELOW)))
}

/// Chooses one of a 2 x 2 block by its values [(0, 0), (1, 0), (0, 1), (1, 1)]: the column by
/// the column sums with `ux`, then the row within it with `uy`, each rescaled to be uniform
/// again. `None` if the block is empty.
///
/// In the block's own units (`ux * sum` against the left column's sum), so that each choice
/// and rescaling costs one division: the warp's levels are a serial chain of them. A side
/// whose sum is 0 is never chosen, whatever the rounding of `ux * sum`.
#[inline]
fn choose(v: [f32; 4], ux: &mut f64, uy: &mut f64) -> Option<(usize, usize)> {
    let [a, b, c, d] = v.map(f64::from);
    let (left, right) = (a + c, b + d);
    let sum = left + right;
    // (Not `is_finite()`, which compiles to a classification of the bits here.)
    if !(sum > 0.0 && sum < f64::INFINITY) {
        return None;
    }
    let x = *ux * sum;
    let dx = (x >= left && right > 0.0) as usize;
    let (top, bottom) = if dx == 0 { (a, c) } else { (b, d) };
    *ux = if dx == 0 { x / left } else { (x - left) / right };
    let y = *uy * (top + bottom);
    let dy = (y >= top && bottom > 0.0) as usize;
    *uy = if dy == 0 { y / top } else { (y - top) / bottom };
    *ux = ux.clamp(0.0, ONE_BELOW);
    *uy = uy.clamp(0.0, ONE_BELOW);
    Some((dx, dy))
}

/// Inverts the cdf of the density proportional to a (1 - x) + b x on [0, 1]: the root of
/// (b - a) x^2 / 2 + a x = u (a + b) / 2, written without cancellation.
#[inline]
fn sample_linear(u: f64, a: f64, b: f64) -> f64 {
    if a == b {
        return u;
    }
    let x = u * (a + b) / (a + (a * a + u * (b * b - a * a)).max(0.0).sqrt());
    if x.is_finite() {
        x.clamp(0.0, ONE_BELOW)
    } else {
        u
    }
}

/// Scene loading: `envmap` (`filename`, `scale`, `to_world` rotation, Furnace's own
/// `filter_type` and `mis_compensation`, which is on unless the scene turns it off).
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
    pos: crate::scene::xml::Pos,
) -> crate::scene::build::R<super::Light> {
    let doc = b.doc;
    let rel = doc.string(i, "filename")?.ok_or_else(|| b.err(pos, "envmap needs a 'filename'"))?;
    let fpos = doc.pos_of(i, "filename");
    let path = doc.resolve_path(fpos, &rel)?;
    let scale = b.nonneg_float(i, "scale", 1.0)?;
    let to_world = b.rotation(i)?;
    let filter = b.choice(
        i,
        "filter_type",
        FilterType::Bilinear,
        &[("bilinear", FilterType::Bilinear), ("nearest", FilterType::Nearest)],
    )?;
    // Mitsuba's default is false; Furnace compensates unless the scene says not to.
    let compensate = doc.boolean_or(i, "mis_compensation", true)?;
    let bitmap =
        b.bitmap(&path, false, 0).map_err(|e| b.err(fpos, format!("cannot load envmap '{rel}': {e}")))?;
    let (peak, kept) = EnvMap::table_bytes(bitmap.width, bitmap.height, filter);
    b.budget
        .charge("the environment map's texels and sampling tables", peak, kept)
        .map_err(|e| b.err(fpos, format!("envmap '{rel}': {e}")))?;
    b.assets.push(path);
    Ok(super::Light::Envmap(Arc::new(EnvMap::new(bitmap, scale, to_world, filter, compensate))))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{luminance, Frame};
    use crate::testing::{chi2_test, Grid, Pcg};

    /// `eval_many` (eight directions' angles at once on AVX2) is `eval` bit for bit: random
    /// directions, the poles, the seam behind (u = 0 and 1), axes, unnormalised and degenerate
    /// directions, a rotated map, bilinear and nearest lookups, one to eight at a time.
    #[test]
    fn eval_many_is_eval() {
        let bmp = Arc::new(sky_with_sun(37, 19, (30, 4), 3, 500.0));
        let rot = Mat3::from_rotation_y(0.7) * Mat3::from_rotation_x(-0.3);
        let mut dirs = vec![
            Vec3::Y,
            Vec3::NEG_Y,
            Vec3::Z,
            Vec3::NEG_Z,
            Vec3::X,
            Vec3::NEG_X,
            Vec3::new(0.0, 0.3, -1.0),
            Vec3::new(-0.0, 0.3, -1.0),
            Vec3::new(1e-30, 1.0, -1e-30),
            Vec3::new(3.0, -4.0, 12.0),
            Vec3::ZERO,
            Vec3::new(f32::NAN, 0.0, 1.0),
        ];
        let mut rng = Pcg::new(5);
        dirs.extend(
            (0..4000)
                .map(|_| Vec3::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, rng.next_f32() - 0.5) * 2.0),
        );
        for filter in [FilterType::Bilinear, FilterType::Nearest] {
            for to_world in [Mat3::IDENTITY, rot] {
                let env = EnvMap::new(bmp.clone(), 1.5, to_world, filter, true);
                let mut at = 0;
                let mut size = 0;
                while at < dirs.len() {
                    size = size % 8 + 1;
                    let d = &dirs[at..(at + size).min(dirs.len())];
                    at += d.len();
                    let mut out = [Rgb::ZERO; 8];
                    env.eval_many(d, &mut out[..d.len()]);
                    for (d, got) in d.iter().zip(out) {
                        let want = env.eval(*d);
                        assert_eq!(
                            got.to_array().map(f32::to_bits),
                            want.to_array().map(f32::to_bits),
                            "{d:?}"
                        );
                    }
                }
            }
        }
    }

    /// A sky gradient with a square sun of `size` x `size` texels at `sun` (its corner).
    fn sky_with_sun(w: usize, h: usize, sun: (usize, usize), size: usize, radiance: f32) -> Bitmap {
        let mut texels: Vec<Rgb> = (0..w * h)
            .map(|k| {
                let v = (k / w) as f32 / h as f32;
                Rgb::new(0.1 + 0.3 * v, 0.2, 0.3 - 0.2 * v)
            })
            .collect();
        for j in sun.1..sun.1 + size {
            for i in sun.0..sun.0 + size {
                texels[j * w + i % w] = Rgb::splat(radiance);
            }
        }
        Bitmap { width: w, height: h, texels }
    }

    fn dir_of(u: f32, v: f32) -> Vec3 {
        let (phi, theta) = (2.0 * PI * u, PI * v);
        Vec3::new(theta.sin() * phi.sin(), theta.cos(), -theta.sin() * phi.cos())
    }

    /// The sun's share of the map's luminance integral, summed independently over texels.
    fn integral_and_sun_share(bmp: &Bitmap, sun_min: f32) -> (f64, f64) {
        let (w, h) = (bmp.width, bmp.height);
        let (mut all, mut sun) = (0.0f64, 0.0f64);
        for j in 0..h {
            let (t0, t1) = (PI64 * j as f64 / h as f64, PI64 * (j + 1) as f64 / h as f64);
            let omega = 2.0 * PI64 / w as f64 * (t0.cos() - t1.cos());
            for i in 0..w {
                let l = luminance(bmp.texel(i, j)) as f64 * omega;
                all += l;
                if bmp.texel(i, j).x >= sun_min {
                    sun += l;
                }
            }
        }
        (all, sun / all)
    }

    /// A 1e6-radiance sun of one texel (nearest) or three texels across (bilinear) in a
    /// 1024 x 512 map: the density follows the lookup, so every light sample's weight L / pdf
    /// has the map's luminance integral as luminance, to within sin(theta)'s interpolation
    /// over half a texel, and the sun gets the samples its power deserves.
    #[test]
    fn light_sample_weights_equal_the_map_integral() {
        for (filter, size) in [(FilterType::Nearest, 1), (FilterType::Bilinear, 3)] {
            let bmp = Arc::new(sky_with_sun(1024, 512, (700, 150), size, 1e6));
            let (integral, sun_share) = integral_and_sun_share(&bmp, 1e5);
            let env = EnvMap::new(bmp.clone(), 1.0, Mat3::from_rotation_y(0.7), filter, false);
            // Texel sums and the grid's sums differ only by sin(theta) per row (nearest) or
            // the half-texel blur at the map's edges (bilinear).
            assert!((env.luminance_integral() / integral - 1.0).abs() < 2e-3, "{filter:?}");
            let mut rng = Pcg::new(9);
            let (n, mut sun_hits, mut worst) = (40_000, 0, 0.0f64);
            for _ in 0..n {
                let (d, li, pdf) = env.sample(rng.next_2d()).expect("sample");
                if filter == FilterType::Bilinear {
                    // Radiance and pdf are those of the direction (up to its f32 rounding);
                    // nearest lookup jumps at texel edges, where a rounded direction may
                    // land in the neighbour.
                    let (l2, p2) = env.eval_pdf(d);
                    assert!((luminance(li) / luminance(l2) - 1.0).abs() < 1e-2, "{li} vs {l2}");
                    assert!((pdf / p2 - 1.0).abs() < 1e-2, "{pdf} vs {p2}");
                }
                let weight = luminance(li) as f64 / pdf as f64 / env.luminance_integral();
                let sin_t = (env.to_local * d).y.abs() < 0.95;
                if sin_t {
                    worst = worst.max((weight - 1.0).abs());
                }
                if li.x > 1e3 {
                    sun_hits += 1;
                }
            }
            assert!(worst < 5e-3, "{filter:?}: weights up to {worst} off the integral");
            let share = sun_hits as f64 / n as f64;
            assert!((share - sun_share).abs() < 0.01, "{filter:?}: sun share {share} vs {sun_share}");
        }
    }

    /// Away from the poles, the pdf is the lookup's luminance over its integral (times the
    /// sphere's measure), for random directions: the density is what the lookup shows.
    #[test]
    fn bilinear_density_follows_the_lookup() {
        let bmp = Arc::new(sky_with_sun(256, 128, (100, 40), 2, 5e4));
        let env = EnvMap::new(bmp, 3.0, Mat3::from_rotation_z(0.2), FilterType::Bilinear, false);
        let mut rng = Pcg::new(4);
        for _ in 0..100_000 {
            let d = square_to_uniform_sphere(rng.next_2d());
            let (li, pdf) = env.eval_pdf(d);
            if (env.to_local * d).y.abs() > 0.95 {
                continue;
            }
            let ratio = luminance(li) as f64 / pdf as f64 / env.luminance_integral();
            assert!((ratio - 1.0).abs() < 0.02, "{d}: ratio {ratio}");
        }
    }

    /// Chi-square of sampled (u, v) in `bu` x `bv` bins of the map against the pdf integrated
    /// over each bin (midpoint rule, 8 x 8 points a bin: exact enough for a density that is
    /// piecewise bilinear in cells no smaller than a bin, whatever its jumps at texel edges).
    fn chi2_uv(env: &EnvMap, bu: usize, bv: usize, what: &str) {
        let n = 300_000usize;
        let mut observed = vec![0.0f64; bu * bv];
        let mut rng = Pcg::new(8);
        for _ in 0..n {
            let u = rng.next_2d();
            let Some((d, _, _)) = env.sample(u) else { panic!("{what}: no sample for {u}") };
            let uv = env.uv(d).0;
            let (i, k) =
                (((uv.x * bu as f32) as usize).min(bu - 1), ((uv.y * bv as f32) as usize).min(bv - 1));
            observed[k * bu + i] += 1.0;
        }
        let m = 8;
        let mut expected = vec![0.0f64; bu * bv];
        let mut integral = 0.0;
        for k in 0..bv {
            for i in 0..bu {
                let mut e = 0.0;
                for b in 0..m {
                    for a in 0..m {
                        let u = (i as f64 + (a as f64 + 0.5) / m as f64) / bu as f64;
                        let v = (k as f64 + (b as f64 + 0.5) / m as f64) / bv as f64;
                        let d = env.to_world * dir_of(u as f32, v as f32);
                        e += env.pdf(d) as f64 * 2.0 * PI64 * PI64 * (PI64 * v).sin();
                    }
                }
                e /= (m * m * bu * bv) as f64;
                integral += e;
                expected[k * bu + i] = e * n as f64;
            }
        }
        assert!((integral - 1.0).abs() < 2e-3, "{what}: pdf integrates to {integral}");
        let (mut stat, mut cells, mut pool_o, mut pool_e) = (0.0, 0usize, 0.0, 0.0);
        for (o, e) in observed.iter().zip(&expected) {
            if *e < 5.0 {
                pool_o += o;
                pool_e += e;
            } else {
                stat += (o - e).powi(2) / e;
                cells += 1;
            }
        }
        if pool_e >= 5.0 {
            stat += (pool_o - pool_e).powi(2) / pool_e;
            cells += 1;
        } else {
            assert!(
                pool_o < 5.0 + 5.0 * pool_e.sqrt(),
                "{what}: {pool_o} samples where {pool_e} were expected"
            );
        }
        let dof = cells.saturating_sub(1).max(1);
        let p = crate::testing::gamma_q(dof as f64 * 0.5, stat * 0.5);
        assert!(p > 1e-4, "{what}: chi2 {stat} on {dof} dof, p = {p}");
    }

    fn chi2_of(env: &EnvMap, grid: Grid, what: &str) {
        let r = chi2_test(
            300_000,
            grid,
            4,
            |rng| env.sample(rng.next_2d()).map(|(d, _, _)| d),
            |d| env.pdf(d) as f64,
            |_| true,
        );
        assert!(r.p_value > 1e-4, "{what}: {r:?}");
        assert!((r.pdf_integral - 1.0).abs() < 5e-3, "{what}: {r:?}");
        assert_eq!(r.sampled_fraction, 1.0, "{what}: {r:?}");
    }

    /// The guide starts the descent at a node whose preimage holds the sample: the guided and
    /// the unguided warp give the same cell and the same point (to rounding) for 200 000
    /// points of the square, on a sun map (where the guide goes deep), black rows, a 1 x 1 map
    /// and a constant one. A wrong guide entry would send a 1/1024 of the square, about 200
    /// of the points, elsewhere.
    #[test]
    fn the_guide_starts_the_descent_where_the_root_would_lead() {
        let mut black_rows = sky_with_sun(48, 24, (30, 10), 1, 50.0);
        for j in [0, 1, 7, 8, 9, 23] {
            black_rows.texels[j * 48..(j + 1) * 48].fill(Rgb::ZERO);
        }
        let maps = [
            (sky_with_sun(512, 256, (300, 60), 2, 1e5), FilterType::Bilinear, true),
            (sky_with_sun(512, 256, (300, 60), 2, 1e5), FilterType::Bilinear, false),
            (sky_with_sun(128, 64, (70, 14), 4, 1e5), FilterType::Nearest, true),
            (black_rows, FilterType::Bilinear, false),
            (
                Bitmap { width: 1, height: 1, texels: vec![Rgb::new(0.3, 0.5, 0.7)] },
                FilterType::Bilinear,
                false,
            ),
            (Bitmap { width: 16, height: 8, texels: vec![Rgb::ONE; 128] }, FilterType::Nearest, false),
        ];
        for (n, (bmp, filter, compensate)) in maps.into_iter().enumerate() {
            let env = EnvMap::new(Arc::new(bmp), 1.0, Mat3::IDENTITY, filter, compensate);
            let warp = &env.warp;
            let mut depths = vec![0usize; warp.levels.len()];
            warp.guide.iter().for_each(|g| depths[g.depth as usize] += 1);
            let (mut differ, mut state) = (0, 0x9e3779b97f4a7c15u64);
            let mut next = || {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (state >> 11) as f64 / (1u64 << 53) as f64
            };
            // Random points, then the guide's cell edges and the square's, and inputs outside it.
            let edges = (0..=GUIDE).flat_map(|i| {
                let e = i as f64 / GUIDE as f64;
                [e, e - 1e-17, e + 1e-17, e.next_down(), e.next_up()]
            });
            let edges: Vec<f64> = edges.chain([-0.5, 1.5, f64::NAN, ONE_BELOW]).collect();
            let odd = edges.iter().flat_map(|&a| edges.iter().step_by(7).map(move |&b| (a, b)));
            let odd: Vec<(f64, f64)> = odd.flat_map(|(a, b)| [(a, b), (b, a)]).collect();
            for (ux, uy) in (0..200_000).map(|_| (next(), next())).chain(odd) {
                match (warp.sample(ux, uy), warp.sample_unguided(ux, uy)) {
                    (Some((u, v, c)), Some((u2, v2, c2))) => {
                        if (c.i, c.k) != (c2.i, c2.k) || (u - u2).abs() > 1e-6 || (v - v2).abs() > 1e-6 {
                            differ += 1;
                        }
                    }
                    (None, None) => {}
                    _ => differ += 1,
                }
            }
            assert!(differ <= 2, "map {n}: {differ} of 200000 samples differ; guide depths {depths:?}");
            if n == 0 {
                // On the sun map most of the square starts at the bottom, and only cells that
                // straddle one of the root's splits start at the root: at most 3 columns of
                // cells and the cells of 3 rows in each of 4 columns' ranges (fewer than 4 x 3
                // x 2 = 24, as a row split crosses one row of cells).
                assert!(depths[depths.len() - 1] * 2 > GUIDE * GUIDE, "guide depths {depths:?}");
                assert!(depths[0] <= 3 * GUIDE + 24, "guide depths {depths:?}");
            }
        }
    }

    /// Sampling follows the pdf (chi-square), and the pdf integrates to one, for a tiny sun
    /// (histogram cells concentrated around it), a 1 x 1 map, maps with black rows and a
    /// constant map (compensated, these two have nothing to sample); with and without MIS
    /// compensation, for both lookups.
    #[test]
    fn sampled_directions_follow_the_pdf() {
        let rot = Mat3::from_rotation_x(0.3);
        let sun_dir = |w: usize, h: usize, sun: (usize, usize), size: usize| {
            let (u, v) = (
                (sun.0 as f32 + size as f32 / 2.0) / w as f32,
                (sun.1 as f32 + size as f32 / 2.0) / h as f32,
            );
            rot * dir_of(u, v)
        };
        let mut black_rows = sky_with_sun(48, 24, (30, 10), 1, 50.0);
        for j in [0, 1, 7, 8, 9, 23] {
            black_rows.texels[j * 48..(j + 1) * 48].fill(Rgb::ZERO);
        }
        let one = Bitmap { width: 1, height: 1, texels: vec![Rgb::new(0.3, 0.5, 0.7)] };
        let constant = Bitmap { width: 16, height: 8, texels: vec![Rgb::ONE; 128] };
        for filter in [FilterType::Nearest, FilterType::Bilinear] {
            for compensate in [false, true] {
                let name = |m: &str| format!("{m}, {filter:?}, compensated {compensate}");
                // A 1e5 sun of 2 x 2 texels in 512 x 256 (bilinear: the lookup is continuous,
                // so the test's quadrature resolves it) or 4 x 4 in 128 x 64 (nearest: the
                // quadrature needs a box that is not too small): cells shrink towards it.
                let (w, h, at, size) = match filter {
                    FilterType::Nearest => (128, 64, (70, 14), 4),
                    _ => (512, 256, (300, 60), 2),
                };
                let sun = Arc::new(sky_with_sun(w, h, at, size, 1e5));
                let env = EnvMap::new(sun, 1.0, rot, filter, compensate);
                assert_eq!(env.compensated(), compensate);
                if filter == FilterType::Bilinear {
                    let axis = sun_dir(w, h, at, size);
                    chi2_of(&env, Grid { axis, rows: 24, cols: 16, power: 3.0 }, &name("tiny sun"));
                }
                // Bins of one texel (nearest) or around the sun's texels (bilinear).
                chi2_uv(&env, 128, 64, &name("tiny sun, (u, v) bins"));
                let env = EnvMap::new(Arc::new(black_rows.clone()), 2.0, rot, filter, compensate);
                chi2_of(&env, Grid::uniform(24, 24), &name("black rows"));
                chi2_uv(&env, 48, 24, &name("black rows, (u, v) bins"));
                // Constant maps: compensated, nothing is left to light sampling.
                let env = EnvMap::new(Arc::new(one.clone()), 1.0, rot, filter, compensate);
                assert_eq!(env.compensated(), compensate);
                assert_eq!(env.is_sampled(), !compensate);
                if compensate {
                    assert!(env.sample(Vec2::new(0.3, 0.6)).is_none() && env.pdf(Vec3::Y) == 0.0);
                } else {
                    chi2_of(&env, Grid::uniform(12, 12), &name("1 x 1"));
                    chi2_uv(&env, 16, 8, &name("1 x 1, (u, v) bins"));
                }
                let env = EnvMap::new(Arc::new(constant.clone()), 1.0, rot, filter, compensate);
                assert_eq!(env.is_sampled(), !compensate);
                if !compensate {
                    chi2_of(&env, Grid::uniform(12, 12), &name("constant"));
                }
            }
        }
    }

    /// Texels near f32's largest value, and a large scale on large texels: the tables are
    /// built relative to the brightest texel, so nothing overflows; samples stay finite and
    /// follow the pdf.
    #[test]
    fn huge_radiance_neither_overflows_nor_hangs() {
        let mut half = Bitmap { width: 32, height: 16, texels: vec![Rgb::splat(1.0); 512] };
        for j in 0..16 {
            half.texels[j * 32..j * 32 + 16].fill(Rgb::splat(1e37));
        }
        let mut one = Bitmap { width: 32, height: 8, texels: vec![Rgb::splat(0.5); 256] };
        one.texels[3 * 32 + 7] = Rgb::splat(1.5e38);
        let mut scaled = Bitmap { width: 64, height: 8, texels: vec![Rgb::splat(0.5); 512] };
        scaled.texels[2 * 64 + 40] = Rgb::splat(1e30);
        for (bmp, scale) in [(half, 1.0), (one, 1.0), (scaled, 1e9)] {
            for filter in [FilterType::Nearest, FilterType::Bilinear] {
                let (w, h) = (bmp.width, bmp.height);
                let env = EnvMap::new(Arc::new(bmp.clone()), scale, Mat3::IDENTITY, filter, true);
                assert!(env.luminance_integral().is_finite() && env.luminance_integral() > 0.0);
                let mut rng = Pcg::new(5);
                for _ in 0..2000 {
                    let (d, _, pdf) = env.sample(rng.next_2d()).expect("a sample");
                    assert!(d.is_finite() && pdf.is_finite() && pdf > 0.0, "{w}x{h} {filter:?}: {d} {pdf}");
                }
                chi2_uv(&env, w, h, &format!("{w}x{h} x{scale}, {filter:?}"));
            }
        }
    }

    /// Within 2.4e-4 rad of a pole, acos(y) rounds to 0 in f32; the pdf takes theta by atan2
    /// and agrees with the density the sample came from.
    #[test]
    fn the_pdf_holds_at_the_poles() {
        let mut bmp = Bitmap { width: 64, height: 32, texels: vec![Rgb::splat(0.1); 64 * 32] };
        bmp.texels[..64].fill(Rgb::splat(100.0));
        for filter in [FilterType::Nearest, FilterType::Bilinear] {
            let env = EnvMap::new(Arc::new(bmp.clone()), 1.0, Mat3::IDENTITY, filter, true);
            for theta in [1e-6f32, 1e-5, 1e-4, 1e-3] {
                let d = Vec3::new(theta.sin() * 0.6, theta.cos(), theta.sin() * 0.8);
                let pdf = env.pdf(d);
                assert!(pdf > 0.0, "{filter:?}: theta {theta}: pdf {pdf}");
            }
            let mut rng = Pcg::new(2);
            let mut near = 0;
            for _ in 0..200_000 {
                let (d, _, pdf) = env.sample(rng.next_2d()).expect("a sample");
                if d.y > 0.999_999 {
                    near += 1;
                    let p2 = env.pdf(d);
                    assert!((p2 / pdf - 1.0).abs() < 0.05, "{filter:?}: {d}: {pdf} vs {p2}");
                }
            }
            assert!(near > 0);
        }
    }

    /// The pdf that a sample reads from its own cell's corners (`pdf_near`) is `Warp::pdf` at
    /// its point, bit for bit, with either filter and with and without compensation.
    #[test]
    fn a_samples_pdf_is_the_pdf_of_its_point() {
        let bmp = Arc::new(sky_with_sun(37, 19, (30, 6), 2, 1000.0));
        let mut checked = 0;
        for filter in [FilterType::Bilinear, FilterType::Nearest] {
            for compensate in [false, true] {
                let env = EnvMap::new(bmp.clone(), 1.0, Mat3::IDENTITY, filter, compensate);
                let w = &env.warp;
                for i in 0..20_000 {
                    let ux = (i as f64 + 0.5) / 20_000.0;
                    let uy = (i as f64 * 0.618_033_988_749_895).fract();
                    if let Some((u, v, cell)) = w.sample(ux, uy) {
                        assert_eq!(w.pdf_near(u, v, cell).to_bits(), w.pdf(u, v).to_bits(), "{u} {v}");
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 70_000, "{checked} samples");
    }

    /// pick4 takes each weight in proportion, never one of 0 (also when u * sum rounds up to
    /// the sum), and leaves the remainder uniform in [0, 1).
    #[test]
    fn pick4_follows_the_weights_and_skips_zeros() {
        let cases: [[f64; 4]; 6] = [
            [1.0, 2.0, 3.0, 4.0],
            [0.0, 1.0, 0.0, 1.0],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 3.0],
            [1e-30, 1.0, 0.0, 1e-30],
            [0.1, 0.2, 0.3, 0.0],
        ];
        let n = 100_000;
        for w in cases {
            let sum: f64 = w.iter().sum();
            let mut count = [0usize; 4];
            let mut rest = [0.0f64; 4];
            for i in 0..=n {
                let u = if i == n { ONE_BELOW } else { (i as f64 + 0.5) / n as f64 };
                let (k, r) = pick4(w, u).unwrap();
                assert!(w[k] > 0.0, "{w:?}, u {u}: chose an empty weight");
                assert!((0.0..1.0).contains(&r), "{w:?}, u {u}: remainder {r}");
                if i < n {
                    count[k] += 1;
                    rest[k] += r;
                }
            }
            for k in 0..4 {
                let want = w[k] / sum * n as f64;
                assert!((count[k] as f64 - want).abs() <= 1.0, "{w:?}: {count:?}");
                if count[k] > 100 {
                    assert!((rest[k] / count[k] as f64 - 0.5).abs() < 1e-3, "{w:?}: remainders {rest:?}");
                }
            }
        }
        assert!(pick4([0.0; 4], 0.5).is_none());
        assert!(pick4([f64::INFINITY, 1.0, 0.0, 0.0], 0.5).is_none());
    }

    #[test]
    fn a_black_map_is_never_sampled() {
        let black = Arc::new(Bitmap { width: 8, height: 4, texels: vec![Rgb::ZERO; 32] });
        for filter in [FilterType::Nearest, FilterType::Bilinear] {
            let env = EnvMap::new(black.clone(), 1.0, Mat3::IDENTITY, filter, true);
            let mut rng = Pcg::new(1);
            for _ in 0..1000 {
                let u = rng.next_2d();
                assert!(env.sample(u).is_none());
                assert_eq!(env.pdf(square_to_uniform_sphere(u)), 0.0);
            }
            assert_eq!(env.luminance_integral(), 0.0);
        }
    }

    /// Compensation leaves the map's dim half to BSDF sampling: its density there is zero, and
    /// the sun gets more of the samples.
    #[test]
    fn compensation_drops_directions_dimmer_than_the_mean() {
        let bmp = Arc::new(sky_with_sun(256, 128, (100, 40), 2, 5e3));
        let full = EnvMap::new(bmp.clone(), 1.0, Mat3::IDENTITY, FilterType::Bilinear, false);
        let comp = full.with_compensation(true);
        assert!(comp.compensated());
        let sky = dir_of(0.8, 0.7); // a sky texel, far from the sun
        assert!(full.pdf(sky) > 0.0);
        assert_eq!(comp.pdf(sky), 0.0);
        let sun = dir_of(101.0 / 256.0, 41.0 / 128.0);
        assert!(comp.pdf(sun) > full.pdf(sun));
    }

    /// Direct light on a diffuse point, estimated as the path tracer does (one light sample and
    /// one cosine-weighted BSDF sample, power heuristic), equals the integral by quadrature,
    /// with and without MIS compensation; compensation lowers the variance. The normals look at
    /// the sun, at the sky beside it and straight down at the dark ground, where compensation
    /// leaves most directions to BSDF sampling alone.
    #[test]
    fn mis_with_compensation_is_unbiased_and_lowers_variance() {
        let (w, h) = (64, 32);
        let mut bmp = sky_with_sun(w, h, (20, 9), 2, 400.0);
        for t in &mut bmp.texels[(h / 2) * w..] {
            *t = Rgb::splat(0.02); // a dark ground
        }
        let bmp = Arc::new(bmp);
        let rot = Mat3::from_rotation_y(0.4);
        let full = EnvMap::new(bmp.clone(), 1.0, rot, FilterType::Bilinear, false);
        let comp = full.with_compensation(true);
        let sun = rot * dir_of(21.0 / w as f32, 10.0 / h as f32);
        for n in [sun, (sun + Vec3::X).normalize(), -Vec3::Y] {
            // Reference: midpoint rule on a grid 8x finer than the map, in (u, v).
            let (qu, qv) = (8 * w, 8 * h);
            let mut reference = 0.0f64;
            for k in 0..qv {
                for i in 0..qu {
                    let (u, v) = ((i as f32 + 0.5) / qu as f32, (k as f32 + 0.5) / qv as f32);
                    let l = dir_of(u, v);
                    let d = rot * l;
                    let cos = n.dot(d).max(0.0) as f64;
                    let jac = 2.0 * PI64 * PI64 * (PI64 * v as f64).sin() / (qu * qv) as f64;
                    reference += luminance(full.eval(d)) as f64 * cos / PI64 * jac;
                }
            }
            let frame = Frame::from_normal(n);
            let mut stats = Vec::new();
            for env in [&full, &comp] {
                let mut rng = Pcg::new(17);
                let m = 200_000;
                let (mut sum, mut sum2) = (0.0f64, 0.0f64);
                for _ in 0..m {
                    let mut x = 0.0f64;
                    if let Some((d, li, pl)) = env.sample(rng.next_2d()) {
                        let cos = n.dot(d).max(0.0);
                        if cos > 0.0 {
                            let pb = cos / PI;
                            x += (luminance(li) * cos / PI) as f64 * crate::math::mis_power(pl, pb) as f64
                                / pl as f64;
                        }
                    }
                    let l = crate::math::square_to_cosine_hemisphere(rng.next_2d());
                    let d = frame.to_world(l);
                    let pb = l.z / PI;
                    if pb > 0.0 {
                        let (li, pl) = env.eval_pdf(d);
                        // f cos / pb = 1 for a white Lambertian lobe.
                        x += luminance(li) as f64 * crate::math::mis_power(pb, pl) as f64;
                    }
                    sum += x;
                    sum2 += x * x;
                }
                let mean = sum / m as f64;
                let var = sum2 / m as f64 - mean * mean;
                let sigma = (var / m as f64).sqrt();
                assert!(
                    (mean - reference).abs() < 5.0 * sigma + 2e-3 * reference,
                    "n = {n}, compensated {}: {mean} vs {reference} (sigma {sigma})",
                    env.compensated()
                );
                stats.push(var);
            }
            if n.y < 0.0 {
                // Facing the dark ground only: compensation leaves it all to BSDF sampling,
                // which costs a little (1.7x a tiny variance: 3.5e-6 against 2.0e-6).
                assert!(
                    stats[1] <= stats[0] * 2.0,
                    "n = {n}: variance {} compensated vs {}",
                    stats[1],
                    stats[0]
                );
            } else {
                // Facing the sun: 1.8 to 0.014 and 1.6 to 0.023.
                assert!(
                    stats[1] <= stats[0] * 0.1,
                    "n = {n}: variance {} compensated vs {}",
                    stats[1],
                    stats[0]
                );
            }
        }
    }

    #[test]
    fn the_bordered_lookup_is_the_wrapped_one() {
        // Bit for bit, on maps of odd and power-of-two sizes (1 x 1 too), at texel centres and
        // edges, the border, and points outside the unit square (u repeats, v is clamped).
        let mut rng = Pcg::new(7);
        for (w, h) in [(1, 1), (2, 1), (5, 3), (8, 4), (33, 17)] {
            let texels = (0..w * h)
                .map(|_| Rgb::new(rng.next_f32(), rng.next_f32() * 100.0, rng.next_f32()))
                .collect();
            let bmp = Bitmap { width: w, height: h, texels };
            let b = Bordered::new(&bmp);
            let mut uvs: Vec<Vec2> = (0..20_000).map(|_| Vec2::new(rng.next_f32(), rng.next_f32())).collect();
            for i in 0..=2 * w {
                for j in 0..=2 * h {
                    uvs.push(Vec2::new(i as f32 / (2 * w) as f32, j as f32 / (2 * h) as f32));
                }
            }
            uvs.extend(
                [
                    (-0.3, 0.5),
                    (1.7, 0.2),
                    (0.5, -0.4),
                    (0.25, 1.3),
                    (-2.6, 2.2),
                    (1.0, 1.0),
                    (-0.0, 0.0),
                    (0.25, 1e20),
                    (0.25, -1e20),
                    (1e20, 0.5),
                    (0.5, f32::INFINITY),
                    (f32::NAN, 0.5),
                    (0.5, f32::NAN),
                ]
                .map(|(u, v)| Vec2::new(u, v)),
            );
            for uv in uvs {
                let want = bmp.bilinear_wrapped(
                    uv,
                    crate::texture::WrapMode::Repeat,
                    crate::texture::WrapMode::Clamp,
                );
                let got = b.bilinear(uv);
                // NaN where the wrapped lookup gives NaN (its payload is not compared), else the
                // same bits.
                let (ga, wa) = (got.to_array(), want.to_array());
                for c in 0..3 {
                    assert!(
                        if wa[c].is_nan() { ga[c].is_nan() } else { ga[c].to_bits() == wa[c].to_bits() },
                        "{w}x{h} at {uv}: {got} against {want}"
                    );
                }
            }
            for y in 0..h {
                for x in 0..w {
                    assert_eq!(b.texel(x, y), bmp.texel(x, y));
                }
            }
            assert_eq!(b.bitmap().texels, bmp.texels);
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
            true,
        );
        assert_eq!(env.eval(dir_of(0.06, 0.1)), Rgb::X);
        assert_eq!(env.eval(dir_of(0.3, 0.9)), Rgb::Y);
        assert!((dir_of(0.25, 0.5) - Vec3::X).length() < 1e-6);
    }

    #[test]
    fn linear_inversion_is_exact() {
        for (a, b) in [(1.0, 1.0), (0.0, 1.0), (1.0, 0.0), (3.0, 1e-9), (1e-30, 1e30), (2.0, 5.0)] {
            for k in 0..=20 {
                let u = k as f64 / 20.0;
                let x = sample_linear(u, a, b);
                let cdf = (a * x + (b - a) * x * x / 2.0) / ((a + b) / 2.0);
                assert!((cdf - u).abs() < 1e-9 || (u == 1.0 && x == ONE_BELOW), "{a} {b} {u}: {x} -> {cdf}");
            }
        }
    }
}
