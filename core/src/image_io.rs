//! Images: EXR (RGB f32) and tonemapped sRGB PNG output, EXR input, and error metrics
//! against a reference (the same definitions as `peers/compare.py`).

use std::path::Path;

use crate::math::{linear_to_srgb, luminance, Rgb};

#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    #[error("{path}: {err}")]
    Exr { path: String, err: exr::error::Error },
    #[error("{path}: {err}")]
    Png { path: String, err: image::ImageError },
    #[error("{path}: {err}")]
    Io { path: String, err: std::io::Error },
}

/// A linear RGB image, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub data: Vec<Rgb>,
}

impl Image {
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> Rgb {
        self.data[(y * self.width + x) as usize]
    }

    /// The image as an RGB f32 EXR file's bytes. Never spawns threads.
    pub fn exr_bytes(&self) -> Result<Vec<u8>, exr::error::Error> {
        let mut out = std::io::Cursor::new(Vec::new());
        self.write_exr_to(&mut out)?;
        Ok(out.into_inner())
    }

    /// Writes RGB f32 EXR into `out` (a buffered file, say), reading the pixels as it goes.
    pub fn write_exr_to(&self, out: impl std::io::Write + std::io::Seek) -> Result<(), exr::error::Error> {
        use exr::prelude::*;
        let w = self.width as usize;
        let channels = SpecificChannels::rgb(|pos: Vec2<usize>| {
            let c = self.data[pos.y() * w + pos.x()];
            (c.x, c.y, c.z)
        });
        Image::from_channels((w, self.height as usize), channels).write().non_parallel().to_buffered(out)
    }

    /// Writes RGB f32 EXR, atomically (temporary file, then rename). Never spawns threads.
    pub fn write_exr(&self, path: &Path) -> Result<(), ImageIoError> {
        use exr::prelude::*;
        let w = self.width as usize;
        let channels = SpecificChannels::rgb(|pos: Vec2<usize>| {
            let c = self.data[pos.y() * w + pos.x()];
            (c.x, c.y, c.z)
        });
        write_atomically(path, |tmp| {
            Image::from_channels((w, self.height as usize), channels)
                .write()
                .non_parallel()
                .to_file(tmp)
                .map_err(|err| ImageIoError::Exr { path: path.display().to_string(), err })
        })
    }

    /// Writes an 8-bit sRGB PNG: radiance x 2^exposure, clamped to [0, 1], sRGB-encoded.
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<(), ImageIoError> {
        let bytes = self
            .png_bytes(exposure)
            .map_err(|err| ImageIoError::Png { path: path.display().to_string(), err })?;
        write_atomically(path, |tmp| {
            std::fs::write(tmp, &bytes)
                .map_err(|err| ImageIoError::Io { path: path.display().to_string(), err })
        })
    }

    /// The image as PNG file bytes, tonemapped as [`Image::write_png`] does.
    pub fn png_bytes(&self, exposure: f32) -> Result<Vec<u8>, image::ImageError> {
        use image::ImageEncoder;
        let scale = exposure.exp2();
        let mut buf = Vec::with_capacity(self.data.len() * 3);
        for c in &self.data {
            for v in [c.x, c.y, c.z] {
                let v = if v.is_finite() { (v * scale).clamp(0.0, 1.0) } else { 0.0 };
                buf.push((linear_to_srgb(v) * 255.0 + 0.5) as u8);
            }
        }
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out).write_image(
            &buf,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
        )?;
        Ok(out)
    }

    /// Reads the first RGB(A) layer of an EXR.
    pub fn read_exr(path: &Path) -> Result<Image, ImageIoError> {
        use exr::prelude::*;
        let img = read_first_rgba_layer_from_file(
            path,
            |res, _| crate::image_io::Image {
                width: res.width() as u32,
                height: res.height() as u32,
                data: vec![Rgb::ZERO; res.width() * res.height()],
            },
            |im: &mut crate::image_io::Image, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                let w = im.width as usize;
                im.data[pos.y() * w + pos.x()] = Rgb::new(r, g, b);
            },
        )
        .map_err(|err| ImageIoError::Exr { path: path.display().to_string(), err })?;
        Ok(img.layer_data.channel_data.pixels)
    }

    /// Mean Rec.709 luminance over finite pixels.
    pub fn mean_luminance(&self) -> f64 {
        let (s, n) = self
            .data
            .iter()
            .filter(|c| c.is_finite())
            .fold((0.0f64, 0usize), |(s, n), c| (s + luminance(*c) as f64, n + 1));
        s / n.max(1) as f64
    }

    /// Error against `reference` (same size): relMSE = mean((a - b)^2 / (b^2 + 1e-2)) and
    /// RMSE over all channels of pixels finite in both; per-pixel relative error (the root of
    /// that pixel's relMSE over its channels) at the 50th, 90th and 99th percentiles.
    pub fn compare(&self, reference: &Image) -> Option<Comparison> {
        if self.width != reference.width || self.height != reference.height {
            return None;
        }
        let (mut se, mut rel, mut n) = (0.0f64, 0.0f64, 0usize);
        let mut per_pixel = Vec::with_capacity(self.data.len());
        for (a, b) in self.data.iter().zip(&reference.data) {
            if !a.is_finite() || !b.is_finite() {
                continue;
            }
            let mut pixel = 0.0;
            for c in 0..3 {
                let d = (a[c] - b[c]) as f64;
                se += d * d;
                pixel += d * d / ((b[c] as f64).powi(2) + 1e-2);
                n += 1;
            }
            rel += pixel;
            per_pixel.push((pixel / 3.0).sqrt());
        }
        per_pixel.sort_by(f64::total_cmp);
        let pct = |p: f64| match per_pixel.len() {
            0 => 0.0,
            len => per_pixel[((len - 1) as f64 * p).round() as usize],
        };
        let n = n.max(1) as f64;
        Some(Comparison {
            rmse: (se / n).sqrt(),
            rel_mse: rel / n,
            rel_err_percentiles: [pct(0.5), pct(0.9), pct(0.99)],
            mean_lum: self.mean_luminance(),
            ref_mean_lum: reference.mean_luminance(),
        })
    }
}

#[derive(Clone, Copy, Debug)]
pub struct Comparison {
    pub rmse: f64,
    pub rel_mse: f64,
    /// Per-pixel relative error at the 50th, 90th and 99th percentiles.
    pub rel_err_percentiles: [f64; 3],
    pub mean_lum: f64,
    pub ref_mean_lum: f64,
}

/// Writes through `write` into a temporary file beside `path`, then renames it into place, so
/// that a reader never sees a half-written image.
fn write_atomically(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), ImageIoError>,
) -> Result<(), ImageIoError> {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(format!(".tmp{}", std::process::id()));
    let tmp = path.with_file_name(name);
    if let Err(e) = write(&tmp) {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, path).map_err(|err| ImageIoError::Io { path: path.display().to_string(), err })
}
