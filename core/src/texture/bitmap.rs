//! Linear-RGB texel grids loaded from image files, with Mitsuba's wrap modes.

use std::path::Path;

use glam::Vec2;

use crate::math::{srgb_to_linear, Rgb};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FilterType {
    Nearest,
    Bilinear,
    /// Furnace's own: mip-mapped, isotropic footprint (Mitsuba has no equivalent).
    Trilinear,
    /// Furnace's own: mip-mapped elliptically weighted average (Mitsuba has no equivalent).
    Ewa,
}

impl FilterType {
    pub const ALL: [FilterType; 4] =
        [FilterType::Nearest, FilterType::Bilinear, FilterType::Trilinear, FilterType::Ewa];

    /// The `filter_type` value that names it in a scene.
    pub fn name(self) -> &'static str {
        match self {
            FilterType::Nearest => "nearest",
            FilterType::Bilinear => "bilinear",
            FilterType::Trilinear => "trilinear",
            FilterType::Ewa => "ewa",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WrapMode {
    Repeat,
    Mirror,
    Clamp,
}

impl WrapMode {
    /// Index `i` of a row or column of `n` texels, wrapped.
    #[inline]
    pub fn apply(self, i: i64, n: i64) -> usize {
        match self {
            WrapMode::Repeat => rem(i, n) as usize,
            WrapMode::Clamp => i.clamp(0, n - 1) as usize,
            WrapMode::Mirror => mirror(rem(i, 2 * n), n),
        }
    }

    /// `[self.apply(i, n), self.apply(i + 1, n)]` with at most one division, and none where
    /// `n` is a power of two.
    #[inline(always)]
    pub fn apply_pair(self, i: i64, n: i64) -> [usize; 2] {
        // The period's remainder once; the next index's is one more, or 0 past the period.
        let next = |k: i64, m: i64| if k + 1 == m { 0 } else { k + 1 };
        match self {
            // (Saturating: a coordinate past i64's range arrives as i64::MAX.)
            WrapMode::Clamp => [i.clamp(0, n - 1) as usize, i.saturating_add(1).clamp(0, n - 1) as usize],
            WrapMode::Repeat => {
                let k = rem(i, n);
                [k as usize, next(k, n) as usize]
            }
            WrapMode::Mirror => {
                let k = rem(i, 2 * n);
                [mirror(k, n), mirror(next(k, 2 * n), n)]
            }
        }
    }
}

/// `i.rem_euclid(n)`, as a mask where `n` is a power of two (right for negative `i` too).
#[inline]
fn rem(i: i64, n: i64) -> i64 {
    if n & (n - 1) == 0 {
        i & (n - 1)
    } else {
        i.rem_euclid(n)
    }
}

/// A position `k` in [0, 2n) of a mirrored period, folded to [0, n).
#[inline]
fn mirror(k: i64, n: i64) -> usize {
    (if k >= n { 2 * n - 1 - k } else { k }) as usize
}

#[derive(Debug, thiserror::Error)]
pub enum BitmapError {
    #[error("cannot read image: {0}")]
    Image(#[from] image::ImageError),
    #[error("cannot read EXR: {0}")]
    Exr(#[from] exr::error::Error),
    #[error("image is empty")]
    Empty,
    #[error("image has {0} non-finite texels")]
    NonFinite(usize),
    #[error("image declares {width} x {height} texels, more than the limit of {limit}")]
    TooLarge { width: u64, height: u64, limit: u64 },
}

/// The most texels one image may have (a 16k x 8k environment map; 1.6 GB of linear RGB).
pub const MAX_TEXELS: u64 = 1 << 27;

/// Decoder limits: what the decoder may allocate itself (the image crate allocates the
/// decoded image outside them).
fn limits_of(max_alloc: u64) -> image::Limits {
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(max_alloc);
    limits
}

/// What the PNG decoder may allocate itself, and is charged for: its chunks' metadata (a
/// compressed colour profile inflates to whatever it declares) and a line buffer.
const PNG_DECODER_BYTES: u64 = 8 << 20;

/// Linear RGB texels, row 0 at the top.
#[derive(Clone, Debug)]
pub struct Bitmap {
    pub width: usize,
    pub height: usize,
    pub texels: Vec<Rgb>,
}

impl Bitmap {
    /// Loads PNG, JPEG, HDR or EXR. Integer formats are sRGB-decoded unless `raw`.
    pub fn load(path: &Path, raw: bool) -> Result<Bitmap, BitmapError> {
        Ok(Bitmap::load_in(path, raw, u64::MAX, TEXEL_LOAD)?.0)
    }

    /// [`Bitmap::load`] within `room` bytes besides the file, at `per_texel` bytes a texel
    /// (at least [`TEXEL_LOAD`]): refused from its header where it would not fit. With the
    /// image, the bytes its reading held besides the file (at most).
    pub fn load_in(path: &Path, raw: bool, room: u64, per_texel: u64) -> Result<(Bitmap, u64), BitmapError> {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        let bytes = std::fs::read(path).map_err(image::ImageError::IoError)?;
        let (image, held) =
            decode_image(&bytes, ext == "exr", raw, MAX_TEXELS, room, per_texel.max(TEXEL_LOAD), u64::MAX)?;
        Ok((image.into_f32(), held))
    }

    /// Decodes an image held in memory (EXR when `exr`, else whatever format its bytes say),
    /// refusing one that declares more than `max_texels` before allocating it.
    pub fn decode(bytes: &[u8], exr: bool, raw: bool, max_texels: u64) -> Result<Bitmap, BitmapError> {
        Ok(decode_image(bytes, exr, raw, max_texels, u64::MAX, TEXEL_LOAD, u64::MAX)?.0.into_f32())
    }

    fn decode_exr(bytes: &[u8]) -> Result<Bitmap, BitmapError> {
        use exr::prelude::*;
        let img = read()
            .no_deep_data()
            .largest_resolution_level()
            .rgba_channels(
                |res, _| Bitmap {
                    width: res.width(),
                    height: res.height(),
                    texels: vec![Rgb::ZERO; res.width() * res.height()],
                },
                |b: &mut Bitmap, pos, (r, g, bl, _a): (f32, f32, f32, f32)| {
                    let w = b.width;
                    b.texels[pos.y() * w + pos.x()] = Rgb::new(r, g, bl);
                },
            )
            .first_valid_layer()
            .all_attributes()
            .from_buffered(std::io::Cursor::new(bytes))?;
        Ok(img.layer_data.channel_data.pixels)
    }

    #[inline]
    pub fn texel(&self, x: usize, y: usize) -> Rgb {
        self.texels[y * self.width + x]
    }

    #[inline]
    pub fn nearest(&self, uv: Vec2, wrap: WrapMode) -> Rgb {
        self.texels[nearest_index(self.width, self.height, uv, wrap)]
    }

    #[inline]
    pub fn bilinear(&self, uv: Vec2, wrap: WrapMode) -> Rgb {
        self.bilinear_wrapped(uv, wrap, wrap)
    }

    /// [`Bitmap::bilinear`] with its own wrap along each axis (an environment map repeats
    /// around and clamps at the poles). Always inlined, so that wraps known at the call fold.
    #[inline(always)]
    pub fn bilinear_wrapped(&self, uv: Vec2, wrap_x: WrapMode, wrap_y: WrapMode) -> Rgb {
        let (i, tx, ty) = bilinear_taps(self.width, self.height, uv, wrap_x, wrap_y);
        blend(&self.texels, i, tx, ty)
    }

    pub fn mean(&self) -> Rgb {
        let s = self.texels.iter().fold(glam::DVec3::ZERO, |a, t| a + t.as_dvec3());
        (s / self.texels.len() as f64).as_vec3()
    }
}

/// An 8-bit texture of more texels than this (48 MiB as f32 RGB) keeps its bytes, whatever
/// its filter (a pyramid's levels above it are f32): 3 a texel, a quarter of the memory, and
/// faster where the f32 texels would not fit the caches. Smaller ones are faster as f32, whose lookups read a texel
/// without a table (docs/BENCHMARKS.md, "Issue 15, twenty-eighth step": 512 x 512 as bytes
/// -12%, 2048 x 2048 -6%; 4096 x 4096 +12%).
pub const KEEP_BYTES_ABOVE: u64 = 1 << 22;

/// What a texel costs while its image is read and decoded to f32, besides the file: the
/// decoder's buffer (up to 16 bytes for float RGBA), the float copy and the linear texels.
pub const TEXEL_LOAD: u64 = 40;

/// What a texel of an 8-bit PNG that keeps its bytes holds while it is read, besides the
/// file: the decoder's `channels` bytes, and the 3 kept (the same bytes, for RGB); one byte of
/// slack. Measured at 4096 x 4096: RGB 2.95, RGBA 6.8, grey 3.8 bytes a texel; interlaced
/// the same (docs/BENCHMARKS.md, "Scene loading: memory"). A JPEG keeps its bytes too, but is
/// charged [`TEXEL_LOAD`]: what its decoder holds depends on what the header alone does not
/// bound simply (progressive scans, four components, sampling factors; up to 21 bytes a texel
/// were measured).
fn byte_texel_load(channels: u64) -> u64 {
    channels + if channels == 3 { 0 } else { 3 } + 1
}

/// [`Bitmap::decode`], keeping an 8-bit image of more than `bytes_above` texels as its bytes.
/// Refused from its header where it has more than `max_texels` texels or would hold more than
/// `room` bytes while it is read (besides the file): `per_texel` a texel decoded to f32,
/// [`byte_texel_load`] a texel of a PNG kept as bytes, and what its decoder holds whatever its
/// size (a PNG's [`PNG_DECODER_BYTES`], a JPEG's copy of the file). With the image, the bytes
/// its reading held besides the file (at most).
fn decode_image(
    bytes: &[u8],
    exr: bool,
    raw: bool,
    max_texels: u64,
    room: u64,
    per_texel: u64,
    bytes_above: u64,
) -> Result<(Image, u64), BitmapError> {
    let too_large_for = |width: u64, height: u64, limit: u64| {
        (width.saturating_mul(height) > limit).then_some(BitmapError::TooLarge { width, height, limit })
    };
    let fits = |room: u64, per_texel: u64| (room / per_texel).min(max_texels);
    let too_large = |width: u64, height: u64| too_large_for(width, height, fits(room, per_texel));
    // The image, and what reading it held besides the file.
    let (bmp, held) = if exr {
        let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(bytes), false)?;
        // Every layer counts (the reader may decode them all to find the RGBA one).
        let mut texels = 0u64;
        for h in &meta.headers {
            let (w, h) = (h.layer_size.width() as u64, h.layer_size.height() as u64);
            texels = texels.saturating_add(w.saturating_mul(h));
            if let Some(e) = too_large(w, h).or_else(|| too_large(texels, 1)) {
                return Err(e);
            }
        }
        let bmp = Bitmap::decode_exr(bytes)?;
        let held = (bmp.width * bmp.height) as u64 * per_texel;
        (bmp, held)
    } else {
        use image::ImageDecoder;
        let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(image::ImageError::IoError)?;
        // What the decoder holds whatever the image's size: a PNG decoder's own allocations
        // (capped at what is charged for them), a JPEG decoder's copy of the file.
        let (png, jpeg) = (
            reader.format() == Some(image::ImageFormat::Png),
            reader.format() == Some(image::ImageFormat::Jpeg),
        );
        let fixed = if png {
            PNG_DECODER_BYTES
        } else if jpeg {
            bytes.len() as u64
        } else {
            0
        };
        let room = room.saturating_sub(fixed);
        reader.limits(limits_of(if png {
            PNG_DECODER_BYTES
        } else {
            fits(room, per_texel).saturating_mul(16)
        }));
        // The header says the size and the texels' type, and so whether the image keeps its
        // bytes and what reading it holds, before anything is decoded.
        let decoder = reader.into_decoder()?;
        let (w, h) = decoder.dimensions();
        use image::ColorType::{La8, Rgb8, Rgba8, L8};
        let color = [L8, La8, Rgb8, Rgba8].iter().position(|&c| c == decoder.color_type());
        let keep_bytes = color.is_some() && w as u64 * h as u64 > bytes_above;
        let load = match color {
            Some(c) if keep_bytes && !jpeg => byte_texel_load(c as u64 + 1),
            _ => per_texel,
        };
        if let Some(e) = too_large_for(w as u64, h as u64, fits(room, load)) {
            return Err(e);
        }
        let held = fixed + w as u64 * h as u64 * load;
        let img = image::DynamicImage::from_decoder(decoder)?;
        if let (true, Some(color)) = (keep_bytes, color) {
            let (width, height) = (img.width() as usize, img.height() as usize);
            if width == 0 || height == 0 {
                return Err(BitmapError::Empty);
            }
            let table = &BYTE_TABLES[color][!raw as usize];
            let bytes = img.into_rgb8().into_raw();
            return Ok((Image::Bytes(std::sync::Arc::new(Bitmap8 { width, height, bytes, table })), held));
        }
        let is_float = matches!(img.color(), image::ColorType::Rgb32F | image::ColorType::Rgba32F);
        let rgb = img.to_rgb32f(); // normalises integers to [0, 1]; no linearisation
        let decode = !is_float && !raw;
        let texels = rgb
            .pixels()
            .map(|p| {
                let c = Rgb::new(p[0], p[1], p[2]);
                if decode {
                    Rgb::new(srgb_byte_or_any(c.x), srgb_byte_or_any(c.y), srgb_byte_or_any(c.z))
                } else {
                    c
                }
            })
            .collect();
        (Bitmap { width: rgb.width() as usize, height: rgb.height() as usize, texels }, held)
    };
    if bmp.width == 0 || bmp.height == 0 {
        return Err(BitmapError::Empty);
    }
    let bad = bmp.texels.iter().filter(|t| !t.is_finite()).count();
    if bad > 0 {
        return Err(BitmapError::NonFinite(bad));
    }
    Ok((Image::F32(std::sync::Arc::new(bmp)), held))
}

/// The texel (index `y * width + x`) that a nearest lookup at `uv` reads.
#[inline(always)]
fn nearest_index(width: usize, height: usize, uv: Vec2, wrap: WrapMode) -> usize {
    let x = wrap.apply(crate::math::floor(uv.x * width as f32) as i64, width as i64);
    let y = wrap.apply(crate::math::floor(uv.y * height as f32) as i64, height as i64);
    y * width + x
}

/// The four texels (indices `y * width + x`: top left, top right, bottom left, bottom right)
/// a bilinear lookup at `uv` blends, and its weights along x and y.
#[inline(always)]
fn bilinear_taps(
    width: usize,
    height: usize,
    uv: Vec2,
    wrap_x: WrapMode,
    wrap_y: WrapMode,
) -> ([usize; 4], f32, f32) {
    // (Through i64: the same f32 as from usize, in one instruction instead of several.)
    let px = uv.x * width as i64 as f32 - 0.5;
    let py = uv.y * height as i64 as f32 - 0.5;
    let (x0, y0, fx0, fy0) = if px.abs() < 8_388_608.0 && py.abs() < 8_388_608.0 {
        // floor as crate::math::floor takes it below 2^23 (the truncation, less one where
        // it rounded up), in integers: the same value.
        // SAFETY: |px|, |py| < 2^23, within i32.
        let (tx, ty) = unsafe { (px.to_int_unchecked::<i32>(), py.to_int_unchecked::<i32>()) };
        let (x0, y0) = (tx - (px < tx as f32) as i32, ty - (py < ty as f32) as i32);
        (x0 as i64, y0 as i64, x0 as f32, y0 as f32)
    } else {
        let (fx0, fy0) = (crate::math::floor(px), crate::math::floor(py));
        (fx0 as i64, fy0 as i64, fx0, fy0)
    };
    let (tx, ty) = (px - fx0, py - fy0);
    let (w, h) = (width as i64, height as i64);
    let x = wrap_x.apply_pair(x0, w);
    let y = wrap_y.apply_pair(y0, h);
    let (r0, r1) = (y[0] * width, y[1] * width);
    ([r0 + x[0], r0 + x[1], r1 + x[0], r1 + x[1]], tx, ty)
}

/// An image as a texture keeps it: linear f32 texels, or an 8-bit image's bytes.
#[derive(Clone, Debug)]
pub enum Image {
    F32(std::sync::Arc<Bitmap>),
    Bytes(std::sync::Arc<Bitmap8>),
}

/// An 8-bit image kept as its bytes: 3 a texel, a quarter of [`Bitmap`]'s 12. Each byte is
/// read through a table of the 256 values that [`Bitmap::decode`] makes of it, so lookups
/// read the same f32 texels, bit for bit, and blend them the same way.
#[derive(Clone, Debug)]
pub struct Bitmap8 {
    pub width: usize,
    pub height: usize,
    /// RGB, row 0 at the top.
    bytes: Vec<u8>,
    table: &'static ByteTable,
}

/// What [`Bitmap::decode`] makes of each byte value of each channel, by the image's colour
/// type (L8, La8, Rgb8, Rgba8) and `[raw, sRGB-decoded]`. Taken from the image crate's own
/// conversion of the 256 values (the one `decode` uses: it does not take every byte `k` to
/// `k / 255` exactly, and not the same way for every colour type), so equal by construction.
type ByteTable = [[f32; 256]; 3];
static BYTE_TABLES: std::sync::LazyLock<[[ByteTable; 2]; 4]> = std::sync::LazyLock::new(|| {
    use image::DynamicImage as D;
    let k = |x: u32| x as u8;
    let images = [
        D::ImageLuma8(image::ImageBuffer::from_fn(256, 1, |x, _| image::Luma([k(x)]))),
        D::ImageLumaA8(image::ImageBuffer::from_fn(256, 1, |x, _| image::LumaA([k(x), k(x)]))),
        D::ImageRgb8(image::ImageBuffer::from_fn(256, 1, |x, _| image::Rgb([k(x); 3]))),
        D::ImageRgba8(image::ImageBuffer::from_fn(256, 1, |x, _| image::Rgba([k(x); 4]))),
    ];
    images.map(|img| {
        let f = img.to_rgb32f();
        let raw: ByteTable = std::array::from_fn(|c| std::array::from_fn(|x| f.get_pixel(x as u32, 0)[c]));
        [raw, raw.map(|t| t.map(srgb_byte_or_any))]
    })
});

impl Bitmap8 {
    /// Texel `k` (`y * width + x`).
    #[inline(always)]
    fn at(&self, k: usize) -> Rgb {
        let b = &self.bytes[3 * k..3 * k + 3];
        let t = self.table;
        Rgb::new(t[0][b[0] as usize], t[1][b[1] as usize], t[2][b[2] as usize])
    }

    pub fn texel(&self, x: usize, y: usize) -> Rgb {
        self.at(y * self.width + x)
    }

    #[inline]
    pub fn nearest(&self, uv: Vec2, wrap: WrapMode) -> Rgb {
        self.at(nearest_index(self.width, self.height, uv, wrap))
    }

    /// [`Bitmap::bilinear`]: the same texels, blended the same way.
    #[inline]
    pub fn bilinear(&self, uv: Vec2, wrap: WrapMode) -> Rgb {
        let (i, tx, ty) = bilinear_taps(self.width, self.height, uv, wrap, wrap);
        // `blend`'s operations, in its order, on texels made in registers (not stored for its
        // 16-byte loads, which would wait on the stores).
        let top = self.at(i[0]) * (1.0 - tx) + self.at(i[1]) * tx;
        let bottom = self.at(i[2]) * (1.0 - tx) + self.at(i[3]) * tx;
        top * (1.0 - ty) + bottom * ty
    }

    /// [`Bitmap::mean`]: the same sums in the same order.
    pub fn mean(&self) -> Rgb {
        let n = self.width * self.height;
        let s = (0..n).fold(glam::DVec3::ZERO, |a, k| a + self.at(k).as_dvec3());
        (s / n as f64).as_vec3()
    }

    /// The linear f32 image (what [`Bitmap::decode`] makes of the same file).
    pub fn to_f32(&self) -> Bitmap {
        Bitmap {
            width: self.width,
            height: self.height,
            texels: (0..self.width * self.height).map(|k| self.at(k)).collect(),
        }
    }
}

impl Image {
    /// Loads as [`Bitmap::load_in`] does (at [`TEXEL_LOAD`] a texel), but an 8-bit PNG or
    /// JPEG of more than [`KEEP_BYTES_ABOVE`] texels keeps its bytes (and a PNG's reading holds
    /// a fraction of that: [`byte_texel_load`]). With the image, the bytes its reading held
    /// besides the file (at most).
    pub fn load_in(path: &Path, raw: bool, room: u64) -> Result<(Image, u64), BitmapError> {
        Image::read(path, raw, KEEP_BYTES_ABOVE, room)
    }

    /// [`Image::load_in`], keeping the bytes of an 8-bit image of more than `above` texels.
    fn read(path: &Path, raw: bool, above: u64, room: u64) -> Result<(Image, u64), BitmapError> {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        let bytes = std::fs::read(path).map_err(image::ImageError::IoError)?;
        decode_image(&bytes, ext == "exr", raw, MAX_TEXELS, room, TEXEL_LOAD, above)
    }

    pub fn width(&self) -> usize {
        match self {
            Image::F32(b) => b.width,
            Image::Bytes(b) => b.width,
        }
    }

    pub fn height(&self) -> usize {
        match self {
            Image::F32(b) => b.height,
            Image::Bytes(b) => b.height,
        }
    }

    /// Bytes kept a texel.
    pub fn texel_bytes(&self) -> u64 {
        match self {
            Image::F32(_) => std::mem::size_of::<Rgb>() as u64,
            Image::Bytes(_) => 3,
        }
    }

    fn into_f32(self) -> Bitmap {
        match self {
            Image::F32(b) => std::sync::Arc::unwrap_or_clone(b),
            Image::Bytes(b) => b.to_f32(),
        }
    }
}

/// The bilinear blend of `texels[i]` (top left, top right, bottom left, bottom right) with
/// weights `tx` and `ty`: the same operations, in the same order, as a blend of `Rgb`s; on
/// x86-64 in SSE lanes ([`blend_unchecked`]) where every texel's 16-byte load stays inside
/// `texels`.
#[inline(always)]
pub(crate) fn blend(texels: &[Rgb], i: [usize; 4], tx: f32, ty: f32) -> Rgb {
    #[cfg(target_arch = "x86_64")]
    if i.iter().all(|&k| k + 1 < texels.len()) {
        // SAFETY: just checked.
        return unsafe { blend_unchecked(texels, i, tx, ty) };
    }
    let top = texels[i[0]] * (1.0 - tx) + texels[i[1]] * tx;
    let bottom = texels[i[2]] * (1.0 - tx) + texels[i[3]] * tx;
    top * (1.0 - ty) + bottom * ty
}

/// [`blend`] in SSE lanes without its check: 16-byte loads of 12-byte texels, the same
/// operations in the same order.
///
/// # Safety
/// Texel `k + 1` exists for every index `k` in `i` (so the 16 bytes from texel k's first float
/// lie in `texels`).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) unsafe fn blend_unchecked(texels: &[Rgb], i: [usize; 4], tx: f32, ty: f32) -> Rgb {
    use std::arch::x86_64::*;
    debug_assert!(i.iter().all(|&k| k + 1 < texels.len()));
    let ld = |k: usize| _mm_loadu_ps(texels.as_ptr().add(k) as *const f32);
    let (x0, x1) = (_mm_set1_ps(1.0 - tx), _mm_set1_ps(tx));
    let top = _mm_add_ps(_mm_mul_ps(ld(i[0]), x0), _mm_mul_ps(ld(i[1]), x1));
    let bottom = _mm_add_ps(_mm_mul_ps(ld(i[2]), x0), _mm_mul_ps(ld(i[3]), x1));
    let c = _mm_add_ps(_mm_mul_ps(top, _mm_set1_ps(1.0 - ty)), _mm_mul_ps(bottom, _mm_set1_ps(ty)));
    let mut out = [0.0f32; 4];
    _mm_storeu_ps(out.as_mut_ptr(), c);
    Rgb::new(out[0], out[1], out[2])
}

/// Scene loading: `bitmap` (`filename`, `filter_type`, `wrap_mode`, `raw`, `to_uv`). An image
/// used by several textures is read once; the pyramid is built only for the filters that read
/// it.
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<super::Texture> {
    use std::sync::Arc;
    let doc = b.doc;
    let rel = doc.string(i, "filename")?.ok_or_else(|| b.err(doc.obj(i).pos, "bitmap needs a 'filename'"))?;
    let fpos = doc.pos_of(i, "filename");
    let path = doc.resolve_path(fpos, &rel)?;
    let raw = doc.boolean_or(i, "raw", false)?;
    let filter = b.choice(i, "filter_type", FilterType::Bilinear, &FilterType::ALL.map(|f| (f.name(), f)))?;
    let wrap = b.choice(
        i,
        "wrap_mode",
        WrapMode::Repeat,
        &[("repeat", WrapMode::Repeat), ("mirror", WrapMode::Mirror), ("clamp", WrapMode::Clamp)],
    )?;
    let to_uv = super::to_uv_rows(&doc.transform(i, "to_uv")?.unwrap_or(glam::Mat4::IDENTITY));
    let mip = matches!(filter, FilterType::Trilinear | FilterType::Ewa);
    let image =
        b.shared_image(&path, raw).map_err(|e| b.err(fpos, format!("cannot load texture '{rel}': {e}")))?;
    // The pyramid filters' levels above the image (the image itself is their level 0).
    let (w, h) = (image.width(), image.height());
    if mip {
        let texels: u64 = super::mipmap::upper_level_sizes(w, h).map(|(w, h)| (w * h) as u64).sum();
        let cost = texels.saturating_mul(std::mem::size_of::<Rgb>() as u64);
        b.budget.charge(&format!("the mipmap of texture '{rel}'"), cost, cost).map_err(|e| b.err(fpos, e))?;
    }
    Ok(match image {
        // A large 8-bit image's bytes, looked up as they are.
        Image::Bytes(bitmap) => {
            let mip = mip.then(|| super::MipMap::build(&*bitmap));
            super::Texture::Bytes(Arc::new(super::BytesTexture { bitmap, filter, wrap, to_uv, mip }))
        }
        Image::F32(bitmap) => {
            let mip = mip.then(|| super::MipMap::build(&*bitmap));
            super::Texture::Bitmap(Arc::new(super::BitmapTexture { bitmap, filter, wrap, to_uv, mip }))
        }
    })
}

/// [`srgb_to_linear`] of `v`, bit for bit, from a table when `v` is an 8-bit value `k / 255`
/// (what an 8-bit image normalises to; `powf` for every channel of every texel was most of
/// loading a large 8-bit texture).
#[inline]
fn srgb_byte_or_any(v: f32) -> f32 {
    static TABLE: std::sync::LazyLock<[f32; 256]> =
        std::sync::LazyLock::new(|| std::array::from_fn(|k| srgb_to_linear(k as f32 / 255.0)));
    let k = (v * 255.0).round();
    // (`k as usize` first: -0.0 is not the table's +0.)
    if (0.0..=255.0).contains(&k) && ((k as usize) as f32 / 255.0).to_bits() == v.to_bits() {
        return TABLE[k as usize];
    }
    srgb_to_linear(v)
}

#[cfg(test)]
mod load_tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn srgb_table_is_the_transfer_function() {
        for k in 0..=255u32 {
            let v = k as f32 / 255.0;
            for x in [v, f32::from_bits(v.to_bits() + 1), f32::from_bits(v.to_bits().saturating_sub(1))] {
                assert_eq!(srgb_byte_or_any(x).to_bits(), srgb_to_linear(x).to_bits(), "{x}");
            }
        }
        for x in [-0.0f32, -1.0, 1.5, 1e-30, f32::NAN] {
            assert_eq!(srgb_byte_or_any(x).to_bits(), srgb_to_linear(x).to_bits(), "{x}");
        }
    }

    #[test]
    fn wrap_modes() {
        assert_eq!(WrapMode::Repeat.apply(-1, 4), 3);
        assert_eq!(WrapMode::Clamp.apply(-1, 4), 0);
        assert_eq!(WrapMode::Mirror.apply(-1, 4), 0);
        assert_eq!(WrapMode::Mirror.apply(4, 4), 3);
        assert_eq!(WrapMode::Mirror.apply(9, 4), 1);
    }

    /// The pair is `apply` at i and i + 1, for every mode, sizes that are and are not powers
    /// of two, and indices far out on both sides (as `to_uv` scales put them).
    #[test]
    fn wrap_pairs_are_two_applies() {
        for mode in [WrapMode::Repeat, WrapMode::Mirror, WrapMode::Clamp] {
            for n in [1i64, 2, 3, 4, 5, 7, 8, 512, 600, 1 << 20] {
                let far = [i64::MIN / 4, -(1 << 40) - 3, 1 << 40, i64::MAX / 4];
                for i in (-3 * n - 2..=3 * n + 2).chain(far) {
                    assert_eq!(
                        mode.apply_pair(i, n),
                        [mode.apply(i, n), mode.apply(i + 1, n)],
                        "{mode:?} {i} {n}"
                    );
                    // apply's masks for powers of two, against the remainders themselves.
                    if mode == WrapMode::Repeat {
                        assert_eq!(mode.apply(i, n), i.rem_euclid(n) as usize, "{i} {n}");
                    }
                    if mode == WrapMode::Mirror {
                        let k = i.rem_euclid(2 * n);
                        assert_eq!(
                            mode.apply(i, n),
                            (if k >= n { 2 * n - 1 - k } else { k }) as usize,
                            "{i} {n}"
                        );
                    }
                }
            }
        }
    }

    /// The lookup bit for bit against the plain one it replaced (floor, both indices wrapped,
    /// four `Rgb` blends): every wrap mode on each axis, odd and power-of-two sizes, random
    /// points near and far (past 2^23 texels, where floor keeps the value), texel centres and
    /// edges, and NaN.
    #[test]
    fn bilinear_is_the_plain_lookup_bit_for_bit() {
        fn plain(b: &Bitmap, uv: Vec2, wx: WrapMode, wy: WrapMode) -> Rgb {
            let px = uv.x * b.width as f32 - 0.5;
            let py = uv.y * b.height as f32 - 0.5;
            let (fx0, fy0) = (crate::math::floor(px), crate::math::floor(py));
            let (tx, ty) = (px - fx0, py - fy0);
            let x = wx.apply_pair(fx0 as i64, b.width as i64);
            let y = wy.apply_pair(fy0 as i64, b.height as i64);
            let top = b.texel(x[0], y[0]) * (1.0 - tx) + b.texel(x[1], y[0]) * tx;
            let bottom = b.texel(x[0], y[1]) * (1.0 - tx) + b.texel(x[1], y[1]) * tx;
            top * (1.0 - ty) + bottom * ty
        }
        let mut rng = crate::testing::Pcg::new(5);
        let modes = [WrapMode::Repeat, WrapMode::Mirror, WrapMode::Clamp];
        for (w, h) in [(1, 1), (3, 2), (4, 4), (7, 5), (64, 32)] {
            let texels =
                (0..w * h).map(|_| Rgb::new(rng.next_f32(), rng.next_f32() * 10.0, rng.next_f32())).collect();
            let b = Bitmap { width: w, height: h, texels };
            let mut uvs: Vec<Vec2> = (0..4000)
                .map(|k| {
                    let scale = [1.0, 10.0, 1e4, 1e7][k % 4];
                    Vec2::new((rng.next_f32() * 2.0 - 1.0) * scale, (rng.next_f32() * 2.0 - 1.0) * scale)
                })
                .collect();
            for i in 0..=2 * w {
                for j in 0..=2 * h {
                    uvs.push(Vec2::new(i as f32 / (2 * w) as f32, j as f32 / (2 * h) as f32));
                }
            }
            uvs.extend(
                [(f32::NAN, 0.5), (0.5, f32::NAN), (1e30, -1e30), (-0.0, 0.0)].map(|(u, v)| Vec2::new(u, v)),
            );
            for uv in uvs {
                for wx in modes {
                    for wy in modes {
                        let (got, want) = (b.bilinear_wrapped(uv, wx, wy), plain(&b, uv, wx, wy));
                        assert_eq!(
                            got.to_array().map(f32::to_bits),
                            want.to_array().map(f32::to_bits),
                            "{w}x{h} {wx:?} {wy:?} at {uv}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn bilinear_hits_texel_centres_exactly() {
        let b = Bitmap { width: 2, height: 1, texels: vec![Rgb::splat(0.0), Rgb::splat(1.0)] };
        assert_eq!(b.bilinear(Vec2::new(0.25, 0.5), WrapMode::Clamp), Rgb::splat(0.0));
        assert_eq!(b.bilinear(Vec2::new(0.75, 0.5), WrapMode::Clamp), Rgb::splat(1.0));
        assert!((b.bilinear(Vec2::new(0.5, 0.5), WrapMode::Clamp).x - 0.5).abs() < 1e-6);
    }

    #[test]
    fn loads_hdr_linear_and_png_srgb() {
        let dir = std::env::temp_dir().join(format!("furnace-bitmap-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // Radiance HDR: floats, no transfer function.
        let hdr = dir.join("t.hdr");
        let px = [image::Rgb([0.25f32, 2.0, 1000.0]), image::Rgb([0.0, 0.5, 1.0])];
        let f = std::fs::File::create(&hdr).unwrap();
        image::codecs::hdr::HdrEncoder::new(f).encode(&px, 2, 1).unwrap();
        let b = Bitmap::load(&hdr, false).unwrap();
        assert_eq!((b.width, b.height), (2, 1));
        for (got, want) in b.texels.iter().zip([Rgb::new(0.25, 2.0, 1000.0), Rgb::new(0.0, 0.5, 1.0)]) {
            assert!((*got - want).abs().max_element() <= 0.01 * want.max_element(), "{got} vs {want}");
        }
        // 8-bit PNG: sRGB-decoded unless raw.
        let png = dir.join("t.png");
        image::save_buffer(&png, &[188u8, 188, 188], 1, 1, image::ExtendedColorType::Rgb8).unwrap();
        let srgb = Bitmap::load(&png, false).unwrap().texels[0].x;
        let raw = Bitmap::load(&png, true).unwrap().texels[0].x;
        assert!((srgb - srgb_to_linear(188.0 / 255.0)).abs() < 1e-6 && (raw - 188.0 / 255.0).abs() < 1e-6);
        std::fs::remove_dir_all(&dir).ok();
    }

    /// An 8-bit image kept as its bytes reads, through its table, the texels that the f32
    /// decode of the same file holds, bit for bit: every texel, nearest and bilinear lookups
    /// (each wrap mode, points near and far), and the mean; sRGB-decoded and raw; RGB, RGBA,
    /// grey and grey-alpha PNGs and a JPEG. A 16-bit PNG stays f32.
    #[test]
    fn bytes_kept_read_the_f32_texels_bit_for_bit() {
        let dir = std::env::temp_dir().join(format!("furnace-bytes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (37u32, 23u32);
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let bytes: Vec<u8> = (0..w * h * 4).map(|_| next() as u8).collect();
        let rgb: Vec<u8> = bytes.chunks(4).flat_map(|c| [c[0], c[1], c[2]]).collect();
        let grey: Vec<u8> = bytes.iter().step_by(4).copied().collect();
        let grey_alpha: Vec<u8> = bytes.chunks(4).flat_map(|c| [c[0], c[3]]).collect();
        use image::ExtendedColorType as C;
        let files = [
            ("rgb.png", &rgb[..], C::Rgb8),
            ("rgba.png", &bytes[..], C::Rgba8),
            ("grey.png", &grey[..], C::L8),
            ("grey-alpha.png", &grey_alpha[..], C::La8),
            ("rgb.jpg", &rgb[..], C::Rgb8),
        ];
        for (name, data, color) in files {
            let path = dir.join(name);
            image::save_buffer(&path, data, w, h, color).unwrap();
            for raw in [false, true] {
                let f32s = Bitmap::load(&path, raw).unwrap();
                // Small: f32, unless bytes are asked for whatever the size.
                assert!(matches!(Image::load_in(&path, raw, u64::MAX).unwrap().0, Image::F32(_)));
                let kept = Image::read(&path, raw, 0, u64::MAX).unwrap().0;
                let Image::Bytes(b) = &kept else { panic!("{name}: not kept as bytes") };
                assert_eq!((b.width, b.height, kept.texel_bytes()), (w as usize, h as usize, 3));
                for y in 0..h as usize {
                    for x in 0..w as usize {
                        assert_eq!(
                            b.texel(x, y).to_array().map(f32::to_bits),
                            f32s.texel(x, y).to_array().map(f32::to_bits),
                            "{name} raw {raw} {x} {y} {:?}",
                            &b.bytes[3 * (y * b.width + x)..][..3]
                        );
                    }
                }
                assert_eq!(b.to_f32().texels, f32s.texels);
                assert_eq!(b.mean().to_array().map(f32::to_bits), f32s.mean().to_array().map(f32::to_bits));
                for mode in [WrapMode::Repeat, WrapMode::Mirror, WrapMode::Clamp] {
                    for k in 0..2000 {
                        let r = |s: u64| ((s >> 11) as f32 / (1u64 << 53) as f32) * 6.0 - 3.0;
                        let mut uv = Vec2::new(r(next()), r(next()));
                        if k % 100 == 0 {
                            uv *= 1e7; // past 2^23 texels
                        }
                        let bits = |c: Rgb| c.to_array().map(f32::to_bits);
                        assert_eq!(
                            bits(b.bilinear(uv, mode)),
                            bits(f32s.bilinear(uv, mode)),
                            "{name} {uv} {mode:?}"
                        );
                        assert_eq!(
                            bits(b.nearest(uv, mode)),
                            bits(f32s.nearest(uv, mode)),
                            "{name} {uv} {mode:?}"
                        );
                    }
                }
            }
        }
        // Not 8-bit: f32, as before.
        let path = dir.join("deep.png");
        let deep: Vec<u8> = rgb.iter().flat_map(|&c| [c, c ^ 0x5a]).collect();
        image::save_buffer(&path, &deep, w, h, C::Rgb16).unwrap();
        let kept = Image::read(&path, false, 0, u64::MAX).unwrap().0;
        assert_eq!(kept.texel_bytes(), 12);
        let Image::F32(f) = &kept else { panic!("a 16-bit image kept as bytes") };
        assert_eq!(f.texels, Bitmap::load(&path, false).unwrap().texels);
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A scene of `shapes` seen by a 4 x 4 perspective camera.
    fn scene_of(shapes: &str) -> String {
        format!(
            r#"<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="40"/>
            <film type="hdrfilm"><integer name="width" value="4"/><integer name="height" value="4"/></film>
            </sensor>{shapes}</scene>"#
        )
    }

    /// An RGB PNG of `w` x `h` texels of hashed bytes.
    fn noise_png(path: &Path, w: u32, h: u32) {
        let px: Vec<u8> = (0..w * h * 3).map(|k| (k.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
        image::save_buffer(path, &px, w, h, image::ExtendedColorType::Rgb8).unwrap();
    }

    /// One file read by textures of several filters is read once: a small image's f32 texels
    /// are one allocation for all of them, a large 8-bit image's bytes likewise (its pyramid
    /// textures' level 0). An image of exactly [`KEEP_BYTES_ABOVE`] texels stays f32.
    #[test]
    fn an_image_used_by_several_filters_is_read_once() {
        use crate::texture::Texture;
        let dir = std::env::temp_dir().join(format!("furnace-shared-image-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        noise_png(&dir.join("small.png"), 37, 23);
        noise_png(&dir.join("edge.png"), 2048, 2048);
        noise_png(&dir.join("big.png"), 2049, 2048);
        assert_eq!(2048 * 2048, KEEP_BYTES_ABOVE);
        for (file, large) in [("small.png", false), ("edge.png", false), ("big.png", true)] {
            let shape = |filter: &str| {
                format!(
                    r#"<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">
                    <string name="filename" value="{file}"/><string name="filter_type" value="{filter}"/>
                    </texture></bsdf></shape>"#
                )
            };
            let xml = scene_of(&["bilinear", "nearest", "ewa", "trilinear"].map(shape).concat());
            let scene = crate::scene::Scene::load_str(&xml, &dir.join("s.xml"), &[]).unwrap();
            assert_eq!(scene.assets.iter().filter(|p| p.ends_with(file)).count(), 1, "{file}");
            let tex: Vec<Texture> = scene.bsdfs.iter().map(|b| b.textures()[0].clone()).collect();
            match (&tex[0], &tex[1], &tex[2], &tex[3], large) {
                (Texture::Bitmap(a), Texture::Bitmap(b), Texture::Bitmap(c), Texture::Bitmap(d), false) => {
                    assert!(Arc::ptr_eq(&a.bitmap, &b.bitmap) && Arc::ptr_eq(&a.bitmap, &c.bitmap), "{file}");
                    assert!(Arc::ptr_eq(&c.bitmap, &d.bitmap) && c.mip.is_some() && d.mip.is_some());
                }
                (Texture::Bytes(a), Texture::Bytes(b), Texture::Bytes(c), Texture::Bytes(d), true) => {
                    assert!(Arc::ptr_eq(&a.bitmap, &b.bitmap) && Arc::ptr_eq(&a.bitmap, &c.bitmap), "{file}");
                    assert!(Arc::ptr_eq(&c.bitmap, &d.bitmap) && c.mip.is_some() && d.mip.is_some());
                    assert!(a.mip.is_none() && b.mip.is_none());
                }
                _ => panic!("{file}: {tex:?}"),
            }
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A scene's 8-bit texture of more than [`KEEP_BYTES_ABOVE`] texels keeps its bytes, and
    /// looks up, through `to_uv` and each filter and wrap, the values of the same texture kept
    /// as f32, bit for bit: point lookups, and the pyramid filters' lookups with footprints
    /// from a texel's width to the whole image (levels 0 to the top, blended).
    #[test]
    fn a_large_8bit_texture_keeps_its_bytes_and_its_values() {
        use crate::texture::{BitmapTexture, TexCoord, Texture};
        let dir = std::env::temp_dir().join(format!("furnace-large-bytes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let png = dir.join("big.png");
        noise_png(&png, 2049, 2048);
        let f32s = Arc::new(Bitmap::load(&png, false).unwrap());
        for (filter, wrap) in [
            ("nearest", "repeat"),
            ("bilinear", "mirror"),
            ("bilinear", "clamp"),
            ("trilinear", "repeat"),
            ("ewa", "mirror"),
            ("ewa", "clamp"),
        ] {
            let xml = scene_of(&format!(
                r#"<shape type="rectangle"><bsdf type="diffuse">
                <texture type="bitmap" name="reflectance"><string name="filename" value="big.png"/>
                <string name="filter_type" value="{filter}"/><string name="wrap_mode" value="{wrap}"/>
                <transform name="to_uv"><scale x="3" y="-2"/><translate x="0.25"/></transform>
                </texture></bsdf></shape>"#
            ));
            let scene = crate::scene::Scene::load_str(&xml, &dir.join("s.xml"), &[]).unwrap();
            let tex = scene.bsdfs[0].textures()[0].clone();
            let Texture::Bytes(b) = &tex else { panic!("{filter}: not kept as bytes") };
            let pyramid = matches!(b.filter, FilterType::Trilinear | FilterType::Ewa);
            assert_eq!(b.mip.is_some(), pyramid, "{filter}");
            let as_f32 = Texture::Bitmap(Arc::new(BitmapTexture {
                bitmap: f32s.clone(),
                filter: b.filter,
                wrap: b.wrap,
                to_uv: b.to_uv,
                mip: pyramid.then(|| crate::texture::MipMap::build(&*f32s)),
            }));
            let bits = |c: Rgb| c.to_array().map(f32::to_bits);
            for k in 0..5000u32 {
                let uv = Vec2::new((k % 71) as f32 / 23.0 - 1.0, (k / 71) as f32 / 29.0 - 1.0);
                // Footprints of about 2^-12 to 2^1 of the map (a texel to all of it), skewed.
                let size = (2.0f32).powf((k % 14) as f32 - 12.0);
                let dx = Vec2::new(size, size * ((k % 5) as f32 - 2.0) * 0.3);
                let dy = Vec2::new(-size * 0.2, size * (1.0 + (k % 3) as f32));
                for tc in [TexCoord::from(uv), TexCoord { uv, dx, dy }] {
                    assert_eq!(bits(tex.eval(tc)), bits(as_f32.eval(tc)), "{filter} {uv} {dx} {dy}");
                }
            }
            assert_eq!(tex.mean().to_array().map(f32::to_bits), f32s.mean().to_array().map(f32::to_bits));
            let plan = scene.describe().to_string();
            let line = match b.filter {
                FilterType::Trilinear => "mip-mapped trilinear, footprint from ray differentials".to_string(),
                FilterType::Ewa => "mip-mapped EWA, footprint from ray differentials".to_string(),
                _ => format!("{filter} lookup, no footprint"),
            };
            assert!(plan.contains(&format!("texture: bitmap 2049x2048 {line}, 8-bit texels")), "{plan}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Writes `w` and `h` over the data window of an EXR, as a hostile file would.
    fn exr_declaring(w: i32, h: i32) -> Vec<u8> {
        use exr::prelude::*;
        let mut exr = Vec::new();
        let ch = SpecificChannels::rgb(|_: Vec2<usize>| (1.0f32, 1.0, 1.0));
        Image::from_channels((1, 1), ch)
            .write()
            .non_parallel()
            .to_buffered(std::io::Cursor::new(&mut exr))
            .unwrap();
        let key = b"dataWindow\0box2i\0";
        let at = exr.windows(key.len()).position(|k| k == key).unwrap() + key.len() + 4;
        exr[at + 8..at + 12].copy_from_slice(&(w - 1).to_le_bytes());
        exr[at + 12..at + 16].copy_from_slice(&(h - 1).to_le_bytes());
        exr
    }

    /// A 1 x 1 PNG whose header (CRC fixed up) declares `w` x `h`.
    fn png_declaring(w: u32, h: u32) -> Vec<u8> {
        let mut png = Vec::new();
        image::write_buffer_with_format(
            &mut std::io::Cursor::new(&mut png),
            &[1u8, 2, 3],
            1,
            1,
            image::ExtendedColorType::Rgb8,
            image::ImageFormat::Png,
        )
        .unwrap();
        // Signature (8), IHDR length (4), "IHDR" (4), width, height, 5 more bytes, CRC.
        png[16..20].copy_from_slice(&w.to_be_bytes());
        png[20..24].copy_from_slice(&h.to_be_bytes());
        let crc = png[12..29].iter().fold(!0u32, |mut c, &b| {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 == 1 { (c >> 1) ^ 0xEDB8_8320 } else { c >> 1 };
            }
            c
        });
        png[29..33].copy_from_slice(&(!crc).to_be_bytes());
        png
    }

    /// Issue 14: a 480 KB EXR whose header declares 60000 x 60000 (43 GB decoded) aborted the
    /// coordinator. Sizes are checked from the header, before decoding.
    #[test]
    fn textures_declaring_huge_sizes_are_refused_from_the_header() {
        for (bytes, exr) in [(exr_declaring(60_000, 60_000), true), (png_declaring(60_000, 60_000), false)] {
            match Bitmap::decode(&bytes, exr, false, MAX_TEXELS) {
                Err(BitmapError::TooLarge { width: 60_000, height: 60_000, .. }) => {}
                other => panic!("{:?}", other.map(|b| (b.width, b.height))),
            }
        }
        // The same files, honest: they load.
        assert_eq!(Bitmap::decode(&exr_declaring(1, 1), true, false, MAX_TEXELS).unwrap().width, 1);
        assert_eq!(Bitmap::decode(&png_declaring(1, 1), false, false, MAX_TEXELS).unwrap().width, 1);
    }
}
