//! Mip-map pyramids and footprint-filtered lookups: `trilinear` (isotropic, two levels blended)
//! and `ewa` (Heckbert 1989: an elliptical Gaussian over the footprint ellipse, on the level
//! where the ellipse's minor axis spans a few texels, blended across two levels). The
//! footprint comes from ray differentials: the uv derivatives along the screen's x and y.

use glam::Vec2;

use super::bitmap::{Bitmap, Bitmap8, WrapMode};
use crate::math::Rgb;

/// Largest ratio of the footprint ellipse's major to minor axis; longer ellipses are fattened
/// (bounded cost per lookup, slight extra blur along the minor axis).
pub const MAX_ANISOTROPY: f32 = 8.0;

/// A bitmap's texels: a texture's own image (f32 texels, or the bytes a large 8-bit image
/// keeps, read as the same values), which is also its pyramid's level 0; the levels above are
/// [`Bitmap`]s.
pub trait Texels {
    fn width(&self) -> usize;
    fn height(&self) -> usize;
    fn texel(&self, x: usize, y: usize) -> Rgb;
    fn nearest(&self, uv: Vec2, wrap: WrapMode) -> Rgb;
    fn bilinear(&self, uv: Vec2, wrap: WrapMode) -> Rgb;
}

/// [`Texels`] by the type's own methods of the same names.
macro_rules! texels_by_own_methods {
    ($($t:ty),*) => {$(
        impl Texels for $t {
            fn width(&self) -> usize {
                self.width
            }
            fn height(&self) -> usize {
                self.height
            }
            #[inline]
            fn texel(&self, x: usize, y: usize) -> Rgb {
                <$t>::texel(self, x, y)
            }
            #[inline]
            fn nearest(&self, uv: Vec2, wrap: WrapMode) -> Rgb {
                <$t>::nearest(self, uv, wrap)
            }
            #[inline]
            fn bilinear(&self, uv: Vec2, wrap: WrapMode) -> Rgb {
                <$t>::bilinear(self, uv, wrap)
            }
        }
    )*};
}

texels_by_own_methods!(Bitmap, Bitmap8);

/// The levels above a texture's image: each halves the one below (box filter, rounding up),
/// down to 1 x 1. Level 0, the image itself, is not copied: each lookup is given it.
#[derive(Debug)]
pub struct MipMap {
    /// Levels 1, 2, ...
    pub upper: Vec<Bitmap>,
}

/// The texel count of each level above a `width` x `height` image, for [`MipMap::build`].
pub fn upper_level_sizes(width: usize, height: usize) -> impl Iterator<Item = (usize, usize)> {
    std::iter::successors(Some((width, height)), |&(w, h)| {
        (w > 1 || h > 1).then(|| (w.div_ceil(2), h.div_ceil(2)))
    })
    .skip(1)
}

impl MipMap {
    pub fn build(base: &impl Texels) -> MipMap {
        let mut upper: Vec<Bitmap> = Vec::new();
        for (w, h) in upper_level_sizes(base.width(), base.height()) {
            let level = match upper.last() {
                None => halve(base, w, h),
                Some(prev) => halve(prev, w, h),
            };
            upper.push(level);
        }
        MipMap { upper }
    }

    /// From explicit levels above `base` (tests: a distinct colour per level shows which is
    /// used).
    pub fn from_levels(upper: Vec<Bitmap>) -> MipMap {
        MipMap { upper }
    }

    fn level_f(&self, width_texels0: f32) -> f32 {
        let max = self.upper.len() as f32;
        if !(width_texels0 > 1.0) {
            return 0.0;
        }
        width_texels0.log2().clamp(0.0, max)
    }

    /// The (fractional) level a footprint of `width` in uv units selects on the pyramid over
    /// `base`: where it spans one texel.
    pub fn level_for(&self, base: &impl Texels, width: f32) -> f32 {
        self.level_f(width * base.width().max(base.height()) as f32)
    }

    /// Bilinear lookup on level `l` (0: `base`).
    #[inline]
    fn bilinear_at(&self, base: &impl Texels, l: usize, uv: Vec2, wrap: WrapMode) -> Rgb {
        if l == 0 {
            base.bilinear(uv, wrap)
        } else {
            self.upper[l - 1].bilinear(uv, wrap)
        }
    }

    /// Isotropic lookup: the footprint's larger axis picks two levels, blended linearly.
    pub fn trilinear(&self, base: &impl Texels, uv: Vec2, dx: Vec2, dy: Vec2, wrap: WrapMode) -> Rgb {
        let width = dx.abs().max(dy.abs()).max_element();
        let l = self.level_for(base, width);
        let l0 = crate::math::floor(l) as usize;
        let t = l - l0 as f32;
        let a = self.bilinear_at(base, l0, uv, wrap);
        if t == 0.0 || l0 + 1 > self.upper.len() {
            return a;
        }
        a * (1.0 - t) + self.bilinear_at(base, l0 + 1, uv, wrap) * t
    }

    /// Elliptically weighted average over the footprint ellipse with axes `dx` and `dy`.
    pub fn ewa(&self, base: &impl Texels, uv: Vec2, mut dx: Vec2, mut dy: Vec2, wrap: WrapMode) -> Rgb {
        if dx.length_squared() < dy.length_squared() {
            std::mem::swap(&mut dx, &mut dy);
        }
        let (major, mut minor) = (dx.length(), dy.length());
        if minor == 0.0 || !minor.is_finite() || !major.is_finite() {
            return base.bilinear(uv, wrap);
        }
        if minor * MAX_ANISOTROPY < major {
            dy *= major / (minor * MAX_ANISOTROPY);
            minor = major / MAX_ANISOTROPY;
        }
        let l = self.level_for(base, minor);
        let l0 = crate::math::floor(l) as usize;
        let t = l - l0 as f32;
        let level = |l: usize| {
            if l == 0 {
                ewa_level(base, uv, dx, dy, wrap)
            } else {
                ewa_level(&self.upper[l - 1], uv, dx, dy, wrap)
            }
        };
        let a = level(l0);
        if t == 0.0 || l0 + 1 > self.upper.len() {
            return a;
        }
        a * (1.0 - t) + level(l0 + 1) * t
    }
}

/// The `w` x `h` level above `prev`: the mean of each 2 x 2 block (of what lies inside).
fn halve(prev: &impl Texels, w: usize, h: usize) -> Bitmap {
    let mut texels = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let mut sum = Rgb::ZERO;
            let mut n = 0.0;
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (sx, sy) = (2 * x + dx, 2 * y + dy);
                if sx < prev.width() && sy < prev.height() {
                    sum += prev.texel(sx, sy);
                    n += 1.0;
                }
            }
            texels.push(sum / n);
        }
    }
    Bitmap { width: w, height: h, texels }
}

fn ewa_level(b: &impl Texels, uv: Vec2, dx: Vec2, dy: Vec2, wrap: WrapMode) -> Rgb {
    let (w, h) = (b.width() as f32, b.height() as f32);
    // Ellipse in texel space of this level, centred on the lookup point.
    let (s, t) = (uv.x * w - 0.5, uv.y * h - 0.5);
    let (d0, d1) = (Vec2::new(dx.x * w, dx.y * h), Vec2::new(dy.x * w, dy.y * h));
    // Implicit form A x^2 + B x y + C y^2 = F of the ellipse spanned by d0 and d1, grown by
    // one texel so that it always covers some texel centres.
    let a = d0.y * d0.y + d1.y * d1.y + 1.0;
    let bb = -2.0 * (d0.x * d0.y + d1.x * d1.y);
    let c = d0.x * d0.x + d1.x * d1.x + 1.0;
    let f = a * c - 0.25 * bb * bb;
    if !(f > 0.0) {
        return b.bilinear(uv, wrap);
    }
    let (a, bb, c) = (a / f, bb / f, c / f);
    // Bounding box of the ellipse.
    let det = -bb * bb + 4.0 * a * c;
    let u_ext = 2.0 * (c / det).sqrt();
    let v_ext = 2.0 * (a / det).sqrt();
    let (x0, x1) = (crate::math::ceil(s - u_ext) as i64, crate::math::floor(s + u_ext) as i64);
    let (y0, y1) = (crate::math::ceil(t - v_ext) as i64, crate::math::floor(t + v_ext) as i64);
    let mut sum = Rgb::ZERO;
    let mut wsum = 0.0f32;
    let falloff = (-2.0f32).exp();
    for y in y0..=y1 {
        let ty = y as f32 - t;
        for x in x0..=x1 {
            let tx = x as f32 - s;
            let r2 = a * tx * tx + bb * tx * ty + c * ty * ty;
            if r2 < 1.0 {
                // Gaussian weight, 0 at the ellipse's edge.
                let wgt = (-2.0 * r2).exp() - falloff;
                let xi = wrap.apply(x, b.width() as i64);
                let yi = wrap.apply(y, b.height() as i64);
                sum += b.texel(xi, yi) * wgt;
                wsum += wgt;
            }
        }
    }
    if wsum > 0.0 {
        sum / wsum
    } else {
        b.bilinear(uv, wrap)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pyramid whose level k is a flat colour k, and its level 0: lookups reveal the level
    /// they used.
    fn levels_as_colours(size: usize) -> (Bitmap, MipMap) {
        let mut levels = Vec::new();
        let mut s = size;
        let mut k = 0.0;
        loop {
            levels.push(Bitmap { width: s, height: s, texels: vec![Rgb::splat(k); s * s] });
            if s == 1 {
                break;
            }
            s /= 2;
            k += 1.0;
        }
        let base = levels.remove(0);
        (base, MipMap::from_levels(levels))
    }

    #[test]
    fn footprint_selects_the_level_where_it_spans_one_texel() {
        let (base, m) = levels_as_colours(256);
        let m = Pyramid(&base, &m);
        for (texels, level) in
            [(1.0f32, 0.0f32), (2.0, 1.0), (8.0, 3.0), (16.0, 4.0), (256.0, 8.0), (4096.0, 8.0)]
        {
            let w = texels / 256.0;
            let tri =
                m.trilinear(Vec2::splat(0.3), Vec2::new(w, 0.0), Vec2::new(0.0, w * 0.5), WrapMode::Repeat);
            assert!(
                (tri.x - level).abs() < 1e-4,
                "trilinear: {texels} texels -> level {}, expected {level}",
                tri.x
            );
            // EWA picks by the minor axis: a circle of diameter `texels`.
            let ewa = m.ewa(Vec2::splat(0.3), Vec2::new(w, 0.0), Vec2::new(0.0, w), WrapMode::Repeat);
            assert!(
                (ewa.x - level).abs() < 1e-4,
                "ewa: {texels} texels -> level {}, expected {level}",
                ewa.x
            );
        }
        // Between levels the two neighbours blend: 2^2.5 texels -> level 2.5.
        let w = 2f32.powf(2.5) / 256.0;
        let tri = m.trilinear(Vec2::splat(0.3), Vec2::new(w, 0.0), Vec2::ZERO, WrapMode::Repeat);
        assert!((tri.x - 2.5).abs() < 1e-3);
        // A long, thin ellipse is clamped to MAX_ANISOTROPY: minor = major / 8.
        let e = m.ewa(
            Vec2::splat(0.3),
            Vec2::new(64.0 / 256.0, 0.0),
            Vec2::new(0.0, 1.0 / 256.0),
            WrapMode::Repeat,
        );
        assert!((e.x - 3.0).abs() < 1e-3, "{}", e.x);
    }

    /// A pyramid with its level 0, looked up as a texture does.
    struct Pyramid<'a>(&'a Bitmap, &'a MipMap);

    impl Pyramid<'_> {
        fn trilinear(&self, uv: Vec2, dx: Vec2, dy: Vec2, wrap: WrapMode) -> Rgb {
            self.1.trilinear(self.0, uv, dx, dy, wrap)
        }
        fn ewa(&self, uv: Vec2, dx: Vec2, dy: Vec2, wrap: WrapMode) -> Rgb {
            self.1.ewa(self.0, uv, dx, dy, wrap)
        }
    }

    #[test]
    fn pyramid_preserves_the_mean() {
        let texels: Vec<Rgb> = (0..37 * 23).map(|k| Rgb::splat((k % 7) as f32)).collect();
        let b = Bitmap { width: 37, height: 23, texels };
        let m = MipMap::build(&b);
        assert_eq!((m.upper.last().unwrap().width, m.upper.last().unwrap().height), (1, 1));
        assert_eq!(m.upper.len(), 6);
        let sizes: Vec<_> = upper_level_sizes(37, 23).collect();
        assert_eq!(sizes, m.upper.iter().map(|l| (l.width, l.height)).collect::<Vec<_>>());
        // Box filtering keeps even-sized levels' means; odd edges shift it only slightly.
        let mean0 = b.mean().x;
        let top = m.upper.last().unwrap().texels[0].x;
        assert!((top - mean0).abs() < 0.2 * mean0, "{top} vs {mean0}");
    }

    #[test]
    fn ewa_of_a_flat_texture_is_flat() {
        let b = Bitmap { width: 64, height: 64, texels: vec![Rgb::new(0.2, 0.4, 0.6); 64 * 64] };
        let m = MipMap::build(&b);
        let m = Pyramid(&b, &m);
        for (dx, dy) in
            [(Vec2::new(0.01, 0.003), Vec2::new(-0.002, 0.02)), (Vec2::new(0.5, 0.0), Vec2::new(0.0, 0.001))]
        {
            let c = m.ewa(Vec2::new(0.7, 0.1), dx, dy, WrapMode::Repeat);
            assert!((c - Rgb::new(0.2, 0.4, 0.6)).abs().max_element() < 1e-5);
        }
    }
}
