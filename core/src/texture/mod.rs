//! Textures: constants, Mitsuba's `bitmap` (PNG, JPEG, EXR, HDR) and `checkerboard`.
//!
//! Bitmaps follow Mitsuba: uv (0, 0) is the top-left texel (row 0), texel centres sit at
//! ((i + 0.5) / W, (j + 0.5) / H), 8-bit and 16-bit data are decoded from sRGB to linear per texel
//! before interpolation (unless `raw`), and `to_uv` is an affine 2-D map applied first.

pub mod bitmap;
pub mod mipmap;

use std::sync::Arc;

use glam::Vec2;

use crate::math::Rgb;

pub use bitmap::{
    Bitmap, Bitmap8, BitmapError, FilterType, Image, WrapMode, KEEP_BYTES_ABOVE, MAX_TEXELS, TEXEL_LOAD,
};
pub use mipmap::MipMap;

/// Where a texture is looked up: uv, and its derivatives along the screen's x and y (zero
/// when no footprint is known: a point lookup).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TexCoord {
    pub uv: Vec2,
    pub dx: Vec2,
    pub dy: Vec2,
}

impl From<Vec2> for TexCoord {
    fn from(uv: Vec2) -> TexCoord {
        TexCoord { uv, dx: Vec2::ZERO, dy: Vec2::ZERO }
    }
}

#[derive(Clone, Debug)]
pub enum Texture {
    Const(Rgb),
    Bitmap(Arc<BitmapTexture>),
    /// A large 8-bit bitmap, kept as its bytes.
    Bytes(Arc<BytesTexture>),
    Checkerboard(Arc<Checkerboard>),
}

/// Mitsuba's `checkerboard`: `color0` where the fractional parts of u and v lie on the same
/// side of 1/2, `color1` elsewhere, after `to_uv`.
#[derive(Debug)]
pub struct Checkerboard {
    pub color0: Rgb,
    pub color1: Rgb,
    pub to_uv: [[f32; 3]; 2],
}

/// A bitmap with its lookup settings, on f32 texels ([`BitmapTexture`]) or on the bytes of an
/// 8-bit image of more than [`KEEP_BYTES_ABOVE`] texels ([`BytesTexture`], the same values).
#[derive(Debug)]
pub struct ImageTexture<B> {
    pub bitmap: Arc<B>,
    pub filter: FilterType,
    pub wrap: WrapMode,
    /// Rows of the 2x3 affine `to_uv` map.
    pub to_uv: [[f32; 3]; 2],
    /// The pyramid above the image, built only for `trilinear` and `ewa`.
    pub mip: Option<MipMap>,
}

/// A bitmap of f32 texels.
pub type BitmapTexture = ImageTexture<Bitmap>;
/// A bitmap of 8-bit texels ([`Bitmap8`]); a pyramid's levels above the image are f32.
pub type BytesTexture = ImageTexture<Bitmap8>;

impl<B: mipmap::Texels> ImageTexture<B> {
    /// The value at `tc`: the filter's lookup, or a bilinear one where a pyramid filter has no
    /// footprint.
    #[inline(always)]
    fn look_up(&self, tc: TexCoord) -> Rgb {
        let uv = apply(&self.to_uv, tc.uv);
        match (self.filter, &self.mip) {
            (FilterType::Nearest, _) => self.bitmap.nearest(uv, self.wrap),
            (filter, Some(m)) if tc.dx != Vec2::ZERO || tc.dy != Vec2::ZERO => {
                let (dx, dy) = (linear(&self.to_uv, tc.dx), linear(&self.to_uv, tc.dy));
                match filter {
                    FilterType::Ewa => m.ewa(&*self.bitmap, uv, dx, dy, self.wrap),
                    _ => m.trilinear(&*self.bitmap, uv, dx, dy, self.wrap),
                }
            }
            _ => self.bitmap.bilinear(uv, self.wrap),
        }
    }
}

impl Texture {
    /// The value at `tc`. A constant is answered inline (most of a scene's reflectances and
    /// radiances are); lookups go through [`Texture::look_up`].
    #[inline(always)]
    pub fn eval(&self, tc: TexCoord) -> Rgb {
        match self {
            Texture::Const(c) => *c,
            _ => self.look_up(tc),
        }
    }

    #[inline(never)]
    fn look_up(&self, tc: TexCoord) -> Rgb {
        match self {
            Texture::Const(c) => *c,
            Texture::Checkerboard(c) => {
                let uv = apply(&c.to_uv, tc.uv);
                if (uv.x - crate::math::floor(uv.x) > 0.5) == (uv.y - crate::math::floor(uv.y) > 0.5) {
                    c.color0
                } else {
                    c.color1
                }
            }
            Texture::Bitmap(b) => b.look_up(tc),
            Texture::Bytes(b) => b.look_up(tc),
        }
    }

    /// True when the texture is a constant (no lookup).
    pub fn is_const(&self) -> bool {
        matches!(self, Texture::Const(_))
    }

    /// True when the texture is the constant 0.
    pub fn is_black(&self) -> bool {
        matches!(self, Texture::Const(c) if *c == Rgb::ZERO)
    }

    /// Whether lookups use a footprint (a `trilinear` or `ewa` bitmap).
    pub fn wants_footprint(&self) -> bool {
        match self {
            Texture::Bitmap(b) => b.mip.is_some(),
            Texture::Bytes(b) => b.mip.is_some(),
            _ => false,
        }
    }

    /// Mean value over the texture's domain (for constants, the constant).
    pub fn mean(&self) -> Rgb {
        match self {
            Texture::Const(c) => *c,
            Texture::Bitmap(b) => b.bitmap.mean(),
            Texture::Bytes(b) => b.bitmap.mean(),
            Texture::Checkerboard(c) => (c.color0 + c.color1) * 0.5,
        }
    }
}

/// The linear part of a 2x3 uv map, for derivatives.
#[inline]
fn linear(m: &[[f32; 3]; 2], d: Vec2) -> Vec2 {
    Vec2::new(m[0][0] * d.x + m[0][1] * d.y, m[1][0] * d.x + m[1][1] * d.y)
}

/// Applies a 2x3 affine uv map (rows of Mitsuba's `to_uv`).
#[inline]
fn apply(m: &[[f32; 3]; 2], uv: Vec2) -> Vec2 {
    Vec2::new(m[0][0] * uv.x + m[0][1] * uv.y + m[0][2], m[1][0] * uv.x + m[1][1] * uv.y + m[1][2])
}

/// The 2x3 affine part of a `to_uv` transform.
pub fn to_uv_rows(m: &glam::Mat4) -> [[f32; 3]; 2] {
    [[m.x_axis.x, m.y_axis.x, m.w_axis.x], [m.x_axis.y, m.y_axis.y, m.w_axis.y]]
}

/// Scene loading: `checkerboard` (`color0` 0.4, `color1` 0.2, `to_uv`).
pub(crate) fn checkerboard_from(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<Texture> {
    Ok(Texture::Checkerboard(Arc::new(Checkerboard {
        color0: b.const_color(i, "color0", Rgb::splat(0.4))?,
        color1: b.const_color(i, "color1", Rgb::splat(0.2))?,
        to_uv: to_uv_rows(&b.doc.transform(i, "to_uv")?.unwrap_or(glam::Mat4::IDENTITY)),
    })))
}
