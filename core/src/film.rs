//! Reconstruction filters and exact, order-independent accumulation of samples.
//!
//! Each sample adds its filter-weighted radiance and its weight to every pixel within the
//! filter's radius. Sums are kept in fixed point: every term is rounded once to a multiple of
//! 2^-40 (squared luminance: 2^-24) and added as an `i128` with wrapping arithmetic, which is
//! exact, associative and commutative, so any split of the work (tiles, sample ranges,
//! machines, arrival order) produces exactly the same bits.
//!
//! Range: a sample may carry radiance up to [`MAX_RADIANCE`] = 2^40 (1.1e12; a sample above it
//! is dropped and counted, like a NaN). A pixel then holds 2^47 such samples before its
//! radiance sum leaves i128, and 2^23 before its squared-luminance sum does. The resolution,
//! 9e-13, is far below the f32 precision of any visible radiance.

use crate::math::{luminance, Rgb};

/// Fractional bits of the radiance and weight sums.
pub const FIXED_BITS: i32 = 40;
/// Fractional bits of the squared-luminance sums.
pub const FIXED_BITS_LUM2: i32 = 24;
/// How many times its region's mean a pixel's mean may be before
/// [`Accum::estimated_rel_mse_for_stopping`] takes it for a firefly's.
pub const FIREFLY_MEAN: f64 = 8.0;
/// The largest radiance (per channel) a single sample may carry.
pub const MAX_RADIANCE: f32 = 1_099_511_627_776.0; // 2^40

#[inline]
pub fn to_fixed(v: f64) -> i128 {
    round_to_i128(v * (FIXED_BITS as f64).exp2())
}

/// `x.round_ties_even() as i128` (halves to even; NaN gives 0, beyond range saturates),
/// without the library calls that baseline x86-64 needs for both: below 2^62 in magnitude
/// one conversion instruction, which rounds to nearest, ties to even (SSE2's `cvtsd2si` in
/// the default rounding mode, which nothing here changes). The film spends this on every
/// sample, four times.
#[inline]
pub fn round_to_i128(x: f64) -> i128 {
    const LIMIT: f64 = 4_611_686_018_427_387_904.0; // 2^62
    if !(x.abs() < LIMIT) {
        return x.round_ties_even() as i128;
    }
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE2 is part of x86-64.
    unsafe {
        use std::arch::x86_64::{_mm_cvtsd_si64, _mm_set_sd};
        _mm_cvtsd_si64(_mm_set_sd(x)) as i128
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        x.round_ties_even() as i64 as i128
    }
}

/// `x as f64`, bit for bit, without the library call that converting an i128 takes, below
/// 2^85 in magnitude: x = hi 2^32 + lo with hi (below 2^53) and lo (below 2^32) exact in f64,
/// hi 2^32 exact too, so their sum rounds once, to the nearest, as the conversion does.
/// (Written this way because the compiler turns a plain `x as i64 as f64` under a range check
/// back into the library call.) Developing an image and the status's error estimate spend
/// this on every pixel.
#[inline]
pub fn to_f64(x: i128) -> f64 {
    let hi = x >> 32;
    if hi.unsigned_abs() < 1 << 53 {
        hi as i64 as f64 * 4_294_967_296.0 + (x as u32) as f64
    } else {
        x as f64
    }
}

/// Why a sample was left out of the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DropReason {
    Nan,
    Infinite,
    /// Finite, but above [`MAX_RADIANCE`] in some channel.
    TooBright,
}

/// Whether a sample's radiance can be accumulated (`None`), or why not: NaN in any channel,
/// an infinite channel, or a channel above [`MAX_RADIANCE`].
#[inline]
pub fn drop_reason(l: Rgb) -> Option<DropReason> {
    if l.is_finite() && l.abs().max_element() <= MAX_RADIANCE {
        None
    } else if l.is_nan() {
        Some(DropReason::Nan)
    } else if !l.is_finite() {
        Some(DropReason::Infinite)
    } else {
        Some(DropReason::TooBright)
    }
}

/// Samples left out of an accumulation, by reason. Each is still counted in its pixel's
/// `count` (so a chunk's count covers every sample rendered) but adds nothing else; the counts
/// travel with the partial and add up exactly when partials merge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Dropped {
    pub nan: u64,
    pub infinite: u64,
    pub too_bright: u64,
}

impl Dropped {
    pub fn total(&self) -> u64 {
        self.nan.saturating_add(self.infinite).saturating_add(self.too_bright)
    }

    pub fn add(&mut self, o: &Dropped) {
        self.nan = self.nan.saturating_add(o.nan);
        self.infinite = self.infinite.saturating_add(o.infinite);
        self.too_bright = self.too_bright.saturating_add(o.too_bright);
    }

    pub fn count(&mut self, why: DropReason) {
        match why {
            DropReason::Nan => self.nan += 1,
            DropReason::Infinite => self.infinite += 1,
            DropReason::TooBright => self.too_bright += 1,
        }
    }
}

impl std::fmt::Display for Dropped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} NaN, {} infinite, {} above 2^40", self.nan, self.infinite, self.too_bright)
    }
}

/// Mitsuba's reconstruction filters (`rfilter`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Filter {
    /// Constant weight within `radius` (default 0.5: each sample lands in its own pixel).
    Box { radius: f32 },
    /// exp(-x^2 / 2 sigma^2) - exp(-r^2 / 2 sigma^2), clamped at 0, per axis; r = 4 sigma.
    Gaussian { stddev: f32 },
}

impl Filter {
    pub fn radius(&self) -> f32 {
        match *self {
            Filter::Box { radius } => radius,
            Filter::Gaussian { stddev } => 4.0 * stddev,
        }
    }

    /// Pixels a tile must extend by on each side to catch all of its samples' splats.
    pub fn margin(&self) -> u32 {
        (self.radius() - 0.5).max(0.0).ceil() as u32
    }

    /// The pixels `lo..=hi` along one axis (of `len`) that a sample at `p` (in pixels), taken
    /// in pixel `x`, splats to: those whose centres lie within the radius, and never more than
    /// [`Filter::margin`] from `x`. Without that bound a sample at the far edge of its pixel,
    /// where `x + offset` rounds up to `x + 1`, would reach one pixel further when the radius
    /// is a whole number plus a half (a box of 1.5): a tile's accumulation, grown by the
    /// margin, would drop that splat and the whole image keep it, so a farm's image and
    /// `furnace render`'s would differ. Such a splat sits exactly at the radius.
    #[inline]
    pub fn splat_span(&self, x: u32, p: f32, len: u32) -> (i64, i64) {
        let (r, m, x) = (self.radius(), self.margin() as i64, x as i64);
        let lo = (crate::math::ceil(p - r - 0.5) as i64).max(0).max(x - m);
        let hi = (crate::math::floor(p + r - 0.5) as i64).min(len as i64 - 1).min(x + m);
        (lo, hi)
    }

    #[inline]
    pub fn eval(&self, x: f32) -> f32 {
        match *self {
            Filter::Box { radius } => {
                if x.abs() <= radius {
                    1.0
                } else {
                    0.0
                }
            }
            Filter::Gaussian { stddev } => {
                let a = -1.0 / (2.0 * stddev * stddev);
                let r = 4.0 * stddev;
                ((a * x * x).exp() - (a * r * r).exp()).max(0.0)
            }
        }
    }

    pub fn name(&self) -> String {
        match *self {
            Filter::Box { radius } => format!("box (radius {radius})"),
            Filter::Gaussian { stddev } => {
                format!("gaussian (stddev {stddev}, radius {})", 4.0 * stddev)
            }
        }
    }
}

/// Per-pixel sums of one accumulation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PixelSum {
    /// Sum of filter weight x radiance, per channel.
    pub rgb: [i128; 3],
    /// Sum of filter weights.
    pub weight: i128,
    /// Sum of squared luminance of the samples generated in this pixel.
    pub lum2: i128,
    /// Samples generated in this pixel.
    pub count: u64,
}

impl PixelSum {
    /// Adds weight `w` and radiance `l`.
    #[inline]
    fn splat(&mut self, w: f32, l: Rgb) {
        let w64 = w as f64;
        self.rgb[0] = self.rgb[0].wrapping_add(to_fixed(w64 * l.x as f64));
        self.rgb[1] = self.rgb[1].wrapping_add(to_fixed(w64 * l.y as f64));
        self.rgb[2] = self.rgb[2].wrapping_add(to_fixed(w64 * l.z as f64));
        self.weight = self.weight.wrapping_add(to_fixed(w64));
    }

    /// The pixel's mean luminance and that mean's variance: the sample luminance's variance
    /// (from the squared sums and the filtered mean, with Bessel's correction) over the sample
    /// count. None for a pixel with fewer than 2 samples or no weight.
    fn mean_and_variance(&self) -> Option<(f64, f64)> {
        if self.count < 2 || self.weight == 0 {
            return None;
        }
        let w = to_f64(self.weight);
        let mean = luminance(Rgb::new(
            (to_f64(self.rgb[0]) / w) as f32,
            (to_f64(self.rgb[1]) / w) as f32,
            (to_f64(self.rgb[2]) / w) as f32,
        )) as f64;
        let c = self.count as f64;
        let second = to_f64(self.lum2) / (1u64 << FIXED_BITS_LUM2) as f64 / c;
        // Bessel's correction: the mean is estimated from the same samples.
        let var = (second - mean * mean).max(0.0) * c / (c - 1.0);
        Some((mean, var / c))
    }

    /// Counts one sample of radiance `l` generated in this pixel.
    #[inline]
    fn count_sample(&mut self, l: Rgb) {
        let lum = luminance(l) as f64;
        self.lum2 = self.lum2.wrapping_add(round_to_i128(lum * lum * (FIXED_BITS_LUM2 as f64).exp2()));
        self.count += 1;
    }

    /// Adds one sample that lands in its own pixel with weight 1 (a box filter of radius
    /// 0.5), as [`Accum::count_sample`] and [`Accum::splat`] would: a pixel's samples summed
    /// here and then added with [`Accum::add_pixel`] give the same bits.
    #[inline]
    pub fn add_own_sample(&mut self, l: Rgb) {
        self.count_sample(l);
        self.splat(1.0, l);
    }

    #[inline]
    fn add(&mut self, o: &PixelSum) {
        for c in 0..3 {
            self.rgb[c] = self.rgb[c].wrapping_add(o.rgb[c]);
        }
        self.weight = self.weight.wrapping_add(o.weight);
        self.lum2 = self.lum2.wrapping_add(o.lum2);
        self.count = self.count.wrapping_add(o.count);
    }
}

/// Accumulated samples over a rectangle of pixels `[x0, x0 + width) x [y0, y0 + height)` of the
/// output image (a tile plus its filter margin, or the whole image).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Accum {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<PixelSum>,
    /// Samples generated in these pixels but left out of the sums.
    pub dropped: Dropped,
}

impl Accum {
    pub fn new(x0: u32, y0: u32, width: u32, height: u32) -> Accum {
        let pixels = vec![PixelSum::default(); width as usize * height as usize];
        Accum { x0, y0, width, height, pixels, dropped: Dropped::default() }
    }

    #[inline]
    fn index(&self, x: u32, y: u32) -> Option<usize> {
        if x >= self.x0 && y >= self.y0 && x < self.x0 + self.width && y < self.y0 + self.height {
            Some(((y - self.y0) * self.width + (x - self.x0)) as usize)
        } else {
            None
        }
    }

    /// Adds weight `w` and radiance `l` to pixel (x, y) in image coordinates.
    #[inline]
    pub fn splat(&mut self, x: u32, y: u32, w: f32, l: Rgb) {
        if let Some(i) = self.index(x, y) {
            self.pixels[i].splat(w, l);
        }
    }

    /// Records that one sample with radiance `l` was generated in pixel (x, y).
    #[inline]
    pub fn count_sample(&mut self, x: u32, y: u32, l: Rgb) {
        if let Some(i) = self.index(x, y) {
            self.pixels[i].count_sample(l);
        }
    }

    /// Adds the sums `p` to pixel (x, y) in image coordinates (nothing outside the rectangle).
    #[inline]
    pub fn add_pixel(&mut self, x: u32, y: u32, p: &PixelSum) {
        if let Some(i) = self.index(x, y) {
            self.pixels[i].add(p);
        }
    }

    /// Records that one sample generated in pixel (x, y) was dropped: it counts as generated,
    /// adds nothing to the sums, and is tallied by reason.
    #[inline]
    pub fn count_dropped(&mut self, x: u32, y: u32, why: DropReason) {
        if let Some(i) = self.index(x, y) {
            self.pixels[i].count += 1;
            self.dropped.count(why);
        }
    }

    /// Adds `other` into `self` (the overlap of the two rectangles; anything of `other` outside
    /// `self` is dropped; the dropped-sample tallies always add). Exact and commutative.
    pub fn merge(&mut self, other: &Accum) {
        self.dropped.add(&other.dropped);
        for oy in 0..other.height {
            for ox in 0..other.width {
                let (x, y) = (other.x0 + ox, other.y0 + oy);
                if let Some(i) = self.index(x, y) {
                    self.pixels[i].add(&other.pixels[(oy * other.width + ox) as usize]);
                }
            }
        }
    }

    /// The relative MSE this accumulation's image has against the converged one, estimated
    /// from its own sums: per pixel, the variance of the sample luminance (from the squared
    /// sums and the filtered mean, with Bessel's correction) over the sample count, relative
    /// to mean^2 + 0.01 (the
    /// denominator of `Image::compare`'s relMSE), averaged over pixels with samples.
    /// Pixel filters wider than a pixel average neighbours' samples too, so there it reads
    /// high; tests state the factor.
    pub fn estimated_rel_mse(&self) -> f64 {
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (mean, var) in self.pixels.iter().filter_map(PixelSum::mean_and_variance) {
            sum += var / (mean * mean + 1e-2);
            n += 1;
        }
        if n == 0 {
            return f64::INFINITY; // fewer than 2 samples per pixel: unknown
        }
        sum / n as f64
    }

    /// [`Accum::estimated_rel_mse`] with each pixel's mean, in the denominator, held to at
    /// most [`FIREFLY_MEAN`] times the mean over all the pixels, for judging when to stop
    /// sampling. A rare bright sample (a firefly) raises its pixel's mean with its variance:
    /// relative to its own mean such a pixel reads about 1 however bright the sample, while its
    /// error relative to the converged pixel is far larger. Held to a multiple k of its
    /// region's mean, it reads at least 1/k^2 of that error where the region's mean is near
    /// the converged pixel's (less where the firefly lifts the region's mean too, as in a
    /// region of few pixels): far more than 1, so its tile goes on. Pixels within that
    /// multiple read as before, bit for bit.
    pub fn estimated_rel_mse_for_stopping(&self) -> f64 {
        let judged = || self.pixels.iter().filter_map(PixelSum::mean_and_variance);
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (mean, _) in judged() {
            sum += mean;
            n += 1;
        }
        if n == 0 {
            return f64::INFINITY; // fewer than 2 samples per pixel: unknown
        }
        let region = sum / n as f64;
        let mut rel = 0.0f64;
        for (mean, var) in judged() {
            let mean = mean.min(FIREFLY_MEAN * region);
            rel += var / (mean * mean + 1e-2);
        }
        rel / n as f64
    }

    /// Total samples counted.
    pub fn sample_count(&self) -> u64 {
        self.pixels.iter().fold(0u64, |n, p| n.saturating_add(p.count))
    }

    /// The image: sum(weight x radiance) / sum(weight) per pixel (0 where nothing landed).
    pub fn develop(&self) -> crate::image_io::Image {
        let data = self
            .pixels
            .iter()
            .map(|p| {
                if p.weight == 0 {
                    return Rgb::ZERO;
                }
                let w = to_f64(p.weight);
                Rgb::new(
                    (to_f64(p.rgb[0]) / w) as f32,
                    (to_f64(p.rgb[1]) / w) as f32,
                    (to_f64(p.rgb[2]) / w) as f32,
                )
            })
            .collect();
        crate::image_io::Image { width: self.width, height: self.height, data }
    }
}

// Scene loading: `hdrfilm` and the pixel filters.
use crate::scene::build::{Builder, R};

/// `hdrfilm`: `width` (768), `height` (576), the crop window, `pixel_format` (`rgb`),
/// `component_format` (written as float32), and one `rfilter` (gaussian when absent).
pub(crate) fn hdrfilm_from(b: &mut Builder, i: usize) -> R<crate::scene::FilmSettings> {
    let doc = b.doc;
    let width = b.positive_int(i, "width", 768)?;
    let height = b.positive_int(i, "height", 576)?;
    crate::scene::build::check_film_size(width, height).map_err(|e| b.err(doc.obj(i).pos, e))?;
    let crop_x = doc.int_or(i, "crop_offset_x", 0)?;
    let crop_y = doc.int_or(i, "crop_offset_y", 0)?;
    let crop_w = doc.int_or(i, "crop_width", width as i64 - crop_x)?;
    let crop_h = doc.int_or(i, "crop_height", height as i64 - crop_y)?;
    if crop_x < 0
        || crop_y < 0
        || crop_w <= 0
        || crop_h <= 0
        || crop_x + crop_w > width as i64
        || crop_y + crop_h > height as i64
    {
        return Err(b.err(
            doc.obj(i).pos,
            format!("crop window ({crop_x}, {crop_y}) size {crop_w} x {crop_h} does not fit in the {width} x {height} film"),
        ));
    }
    if let Some(pf) = doc.string(i, "pixel_format")? {
        if pf != "rgb" {
            return Err(b.err(
                doc.pos_of(i, "pixel_format"),
                format!("pixel_format '{pf}' is not supported: Furnace writes 'rgb'"),
            ));
        }
    }
    if let Some(cf) = doc.string(i, "component_format")? {
        if cf != "float32" && cf != "float16" {
            return Err(b.err(
                doc.pos_of(i, "component_format"),
                format!(
                    "component_format '{cf}' is not supported (float16 or float32; Furnace writes float32)"
                ),
            ));
        }
    }
    let filter = match doc.children(i, "rfilter").as_slice() {
        [] => Filter::Gaussian { stddev: 0.5 },
        [(_, f, _)] => b.make_filter(*f)?,
        [_, (_, _, pos), ..] => return Err(b.err(*pos, "more than one <rfilter>")),
    };
    Ok(crate::scene::FilmSettings {
        width,
        height,
        crop_x: crop_x as u32,
        crop_y: crop_y as u32,
        crop_width: crop_w as u32,
        crop_height: crop_h as u32,
        filter,
    })
}

/// `box`: `radius` (0.5).
pub(crate) fn box_from(b: &mut Builder, i: usize) -> R<Filter> {
    let radius = b.doc.float_or(i, "radius", 0.5)?;
    if !(radius > 0.0 && radius <= 8.0) {
        return Err(b.err(b.doc.pos_of(i, "radius"), "box radius must lie in (0, 8]"));
    }
    Ok(Filter::Box { radius })
}

/// `gaussian`: `stddev` (0.5).
pub(crate) fn gaussian_from(b: &mut Builder, i: usize) -> R<Filter> {
    let stddev = b.doc.float_or(i, "stddev", 0.5)?;
    if !(stddev > 0.0 && stddev <= 2.0) {
        return Err(b.err(b.doc.pos_of(i, "stddev"), "gaussian stddev must lie in (0, 2]"));
    }
    Ok(Filter::Gaussian { stddev })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fast rounding is `round_ties_even() as i128` exactly: halves, near-halves, integers, both
    /// signs, around 2^52 and 2^62 and beyond, zeros, infinities and NaN.
    #[test]
    fn fast_rounding_is_exact() {
        let mut vals = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            -1.5,
            2.5,
            0.49999999999999994,
            -0.49999999999999994,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            f64::MAX,
            f64::MIN_POSITIVE,
            1e300,
            -1e300,
        ];
        for e in [0, 1, 20, 51, 52, 53, 61, 62, 63, 100, 126, 127, 128] {
            let b = 2f64.powi(e);
            for d in [-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5] {
                for x in [b + d, b - d, -(b + d), -(b - d), b * 1.25 + d] {
                    vals.extend([
                        x,
                        f64::from_bits(x.to_bits() + 1),
                        f64::from_bits(x.to_bits().saturating_sub(1)),
                    ]);
                }
            }
        }
        let mut state = 1u64;
        for _ in 0..100_000 {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let x = f64::from_bits(state >> 2 | (state & 1) << 63);
            vals.push(x);
            vals.push((state >> 11) as f64 / (1u64 << 53) as f64 * 1e7 - 5e6);
        }
        for x in vals {
            assert_eq!(round_to_i128(x), x.round_ties_even() as i128, "{x:e} ({:#x})", x.to_bits());
        }
    }

    #[test]
    fn to_f64_is_as_f64() {
        let mut s = 0x1234_5678_9abc_def0u64;
        for k in 0..100_000 {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            let x = ((s as i128) << 64 | s.rotate_left(29) as i128) >> (k % 120);
            for v in [x, -x, x >> 64, i64::MAX as i128 + (k as i128), i64::MIN as i128 - (k as i128)] {
                assert_eq!(to_f64(v).to_bits(), (v as f64).to_bits(), "{v}");
            }
        }
        // Ties and near-ties of the rounding, on both sides of the fast path's 2^85 limit.
        for e in 50..100 {
            let ulp = 1i128 << (e - 52).max(0);
            for off in [0, ulp / 2 - 1, ulp / 2, ulp / 2 + 1, ulp + ulp / 2, ulp - 1] {
                for v in [(1i128 << e) + off, (3i128 << (e - 1)) + off, -((1i128 << e) + off)] {
                    assert_eq!(to_f64(v).to_bits(), (v as f64).to_bits(), "{v}");
                }
            }
        }
    }

    #[test]
    fn merge_is_order_independent_and_exact() {
        let vals = [0.1f32, 1e6, 3.3e-7, 0.7, 42.0, 1.0 / 3.0];
        let mut a = Accum::new(0, 0, 1, 1);
        for v in vals {
            a.splat(0, 0, 0.37, Rgb::splat(v));
        }
        let mut parts: Vec<Accum> = vals
            .iter()
            .map(|&v| {
                let mut p = Accum::new(0, 0, 1, 1);
                p.splat(0, 0, 0.37, Rgb::splat(v));
                p
            })
            .collect();
        parts.reverse();
        let mut b = Accum::new(0, 0, 1, 1);
        for p in &parts {
            b.merge(p);
        }
        assert_eq!(a, b);
    }

    /// The stopping estimate reads a firefly as large as its error against the converged pixel
    /// (relative to the pixel's own, inflated mean it reads about 1, whatever its size), and
    /// reads pixels within [`FIREFLY_MEAN`] times their region's mean as the plain estimate
    /// does.
    #[test]
    fn a_firefly_counts_in_the_stopping_estimate() {
        let (w, h, spp) = (16u32, 16u32, 8);
        // Samples around 0.5, and a pixel four times as bright (within FIREFLY_MEAN).
        let value = |x: u32, y: u32, k: u32| {
            let base = if (x, y) == (3, 3) { 2.0 } else { 0.5 };
            base * (1.0 + 0.2 * (((x * 7 + y * 13 + k * 5) % 9) as f32 / 8.0 - 0.5))
        };
        let render = |firefly: Option<f32>| {
            let mut a = Accum::new(0, 0, w, h);
            for y in 0..h {
                for x in 0..w {
                    for k in 0..spp {
                        let v = match firefly {
                            Some(f) if (x, y, k) == (9, 5, 2) => f,
                            _ => value(x, y, k),
                        };
                        a.count_sample(x, y, Rgb::splat(v));
                        a.splat(x, y, 1.0, Rgb::splat(v));
                    }
                }
            }
            a
        };
        let clean = render(None);
        let (plain, stopping) = (clean.estimated_rel_mse(), clean.estimated_rel_mse_for_stopping());
        assert!(plain > 0.0 && (stopping - plain).abs() <= 1e-12 * plain, "{plain} {stopping}");
        for f in [100.0f32, 1000.0, 10_000.0] {
            let a = render(Some(f));
            // The firefly pixel's squared error against its converged value, relative to it as
            // `Image::compare` takes it, averaged over the image: what it adds to the relMSE.
            let truth = value(9, 5, 0) as f64;
            let mean = (f as f64 + (0..spp).filter(|&k| k != 2).map(|k| value(9, 5, k) as f64).sum::<f64>())
                / spp as f64;
            let adds = (mean - truth).powi(2) / (truth * truth + 1e-2) / (w * h) as f64;
            let (plain_f, stopping_f) =
                (a.estimated_rel_mse() - plain, a.estimated_rel_mse_for_stopping() - plain);
            assert!(
                plain_f < 0.01 && plain_f < adds / 200.0,
                "firefly {f}: the plain estimate adds {plain_f}"
            );
            // Held to FIREFLY_MEAN times the region's mean (which the firefly raises too), the
            // pixel's mean still reads larger than the converged value: the estimate stays below
            // the truth, but well above the plain one and above any usual target (0.1^2).
            assert!(
                stopping_f < adds && stopping_f > 8.0 * plain_f && stopping_f > 0.02,
                "firefly {f}: the stopping estimate adds {stopping_f}, the firefly {adds}, the plain estimate {plain_f}"
            );
        }
    }

    #[test]
    fn gaussian_is_zero_at_its_radius_and_margin_covers_it() {
        let g = Filter::Gaussian { stddev: 0.5 };
        assert_eq!(g.eval(2.0), 0.0);
        assert!(g.eval(0.0) > 0.99);
        assert_eq!(g.margin(), 2);
        assert_eq!(Filter::Box { radius: 0.5 }.margin(), 0);
    }

    /// A sample splats only within the margin of its own pixel, so that a tile grown by the
    /// margin catches every splat its samples make. The hard case: an offset just below 1,
    /// where `x + offset` rounds up to `x + 1`, and a radius of a whole number plus a half,
    /// where the pixel one further then lies exactly at the radius (a box filter weighs it 1).
    #[test]
    fn a_sample_splats_only_within_the_margin_of_its_pixel() {
        let below_one = 1.0 - f32::EPSILON / 2.0;
        for filter in [
            Filter::Box { radius: 0.5 },
            Filter::Box { radius: 1.5 },
            Filter::Box { radius: 2.5 },
            Filter::Box { radius: 1.7 },
            Filter::Gaussian { stddev: 0.375 },
            Filter::Gaussian { stddev: 0.5 },
        ] {
            let m = filter.margin() as i64;
            let mut rounded_up = 0;
            for x in 0..4096u32 {
                for offset in [0.0, 0.5, below_one] {
                    let p = x as f32 + offset;
                    rounded_up += (p == (x + 1) as f32) as u32;
                    let (lo, hi) = filter.splat_span(x, p, 4096);
                    assert!(
                        lo >= x as i64 - m && hi <= x as i64 + m,
                        "{filter:?}: x {x}, p {p}: {lo}..={hi}"
                    );
                    // Every pixel of the span has its centre within the radius, and every one
                    // within the margin whose centre is strictly within the radius is in it.
                    for j in (x as i64 - m).max(0)..=(x as i64 + m).min(4095) {
                        let d = (p - (j as f32 + 0.5)).abs();
                        if (lo..=hi).contains(&j) {
                            assert!(d <= filter.radius(), "{filter:?}: x {x}, p {p}: pixel {j} at {d}");
                        } else {
                            assert!(
                                d >= filter.radius(),
                                "{filter:?}: x {x}, p {p}: pixel {j} at {d} left out"
                            );
                        }
                    }
                }
            }
            // The hard case is exercised: x + offset rounds up for every x from 1 on.
            assert!(rounded_up > 4000, "{filter:?}: {rounded_up}");
        }
    }
}
