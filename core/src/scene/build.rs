//! Turns the parsed XML tree into a [`Scene`], with Mitsuba's plugin names, parameters and
//! defaults. Anything the builder does not consume is reported by `Doc::check_all_used`.

use std::collections::HashMap;
use std::sync::Arc;

use glam::{Mat3, Mat4, Vec3};

use super::xml::{Doc, Pos, MAX_COORD};
use super::{FilmSettings, PathSettings, Scene, SceneError};
use crate::bsdf::conductor::{conductor_preset, CONDUCTOR_PRESETS};
use crate::bsdf::microfacet::fresnel_diffuse_reflectance;
use crate::bsdf::{Bsdf, Conductor, Dielectric, Distribution, Plastic, RoughCoating, Roughness};
use crate::camera::{tan_half_fov, Camera, ThinLens};
use crate::film::Filter;
use crate::geometry::{Accel, Disk, Geometry, Instance, Mesh, Shape, Sphere};
use crate::light::{EnvMap, Light};
use crate::math::Rgb;
use crate::plan::Techniques;
use crate::texture::{
    to_uv_rows, Bitmap, BitmapTexture, Checkerboard, FilterType, MipMap, Texture, WrapMode,
};

type R<T> = Result<T, SceneError>;

/// How many times an instance may shrink its group along a direction (see `Builder::instance`).
pub const MAX_INSTANCE_SHRINK: f32 = 1e9;

/// The largest film side, in pixels.
pub const MAX_FILM_SIDE: u32 = 65535;
/// The most pixels a film may have (8K UHD is 2^24.98): a job's accumulation takes 96 bytes a
/// pixel, 3.2 GB at this limit.
pub const MAX_FILM_PIXELS: u64 = 1 << 25;

/// Checks a film's (or a job's image's) size against [`MAX_FILM_SIDE`] and
/// [`MAX_FILM_PIXELS`]; the error names both.
pub fn check_film_size(width: u32, height: u32) -> Result<(), String> {
    if width > MAX_FILM_SIDE || height > MAX_FILM_SIDE || width as u64 * height as u64 > MAX_FILM_PIXELS {
        return Err(format!(
            "a {width} x {height} film is too large: at most {MAX_FILM_SIDE} pixels a side and {MAX_FILM_PIXELS} (2^25) in all"
        ));
    }
    Ok(())
}

// What a load holds, estimated before each part is read. Measured with a counting allocator
// (docs/BENCHMARKS.md, "Scene loading: memory"): a 7.3 MB scene of 40,000 spheres peaks at 16
// bytes per byte of XML; a 4096 x 4096 PNG at 27 bytes a texel; OBJ at 7.1 and curve files at
// 3.5 bytes per byte of file (PLY: see `ply_load_estimate`); the BVH's build at 344 bytes a
// primitive, keeping 54 (triangles) or 16 (curve segments).
/// What a load holds whatever the scene.
const BASE: u64 = 1 << 20;
/// What the XML parser holds per byte of the scene file (the text, the tree, positions), and
/// keeps while the scene is built.
pub(crate) const XML_PER_BYTE: u64 = 20;
/// What a texel costs while its image is read and decoded, besides the file: the decoder's
/// buffer (up to 16 bytes for float RGBA), the float copy and the linear texels.
const TEXEL_LOAD: u64 = 40;
/// What a texel keeps: linear RGB, and the pyramid's levels when a filter reads them.
const TEXEL_KEPT: u64 = std::mem::size_of::<Rgb>() as u64;
const MIP_TEXEL: u64 = TEXEL_KEPT * 4 / 3;
/// What the OBJ loader holds per byte of its file while parsing.
const PARSE_PER_BYTE: u64 = 12;
/// What parsing a curve file holds per point (a line), and per curve, besides its text.
const CURVE_POINT_PARSE: u64 = 32;
const CURVE_PARSE: u64 = 96;
/// What building the BVH holds at its peak per primitive of one batch (obvhs' scratch), what
/// it holds per primitive of the scene on top of what it keeps (the Morton order of a batched
/// build), and what it keeps.
const BVH_BUILD_PER_PRIM: u64 = 384;
const BVH_ORDER_PER_PRIM: u64 = 20;
const BVH_KEPT_PER_PRIM: u64 = 64;

/// A scene's load within its [`LoadLimits`](super::LoadLimits): the memory counted so far and
/// the deadline.
pub(crate) struct Budget {
    limits: super::LoadLimits,
    kept: u64,
    /// The most the load has been estimated to hold at once.
    peak: u64,
}

impl Budget {
    pub(crate) fn new(limits: &super::LoadLimits) -> Budget {
        // What any scene holds besides its parts (the builder, its maps, the plan).
        Budget { limits: limits.clone(), kept: BASE, peak: BASE }
    }

    /// Makes room for a part of the scene that holds `transient` bytes while it loads and
    /// keeps `kept` after (counted from then on); refused past the deadline or the memory.
    pub(crate) fn charge(&mut self, what: &str, transient: u64, kept: u64) -> Result<(), String> {
        self.in_time()?;
        let need = self.kept.saturating_add(transient.max(kept));
        if need > self.limits.max_bytes {
            let mib = |b: u64| format!("{:.1} MiB", b as f64 / (1u64 << 20) as f64);
            return Err(format!(
                "{what} needs about {} to load, and with the {} loaded before it that is over the {} a scene may take (--max-scene-memory-mb)",
                mib(transient.max(kept)),
                mib(self.kept),
                mib(self.limits.max_bytes)
            ));
        }
        self.peak = self.peak.max(need);
        self.kept += kept;
        Ok(())
    }

    /// The most bytes a part may still hold.
    fn room(&self) -> u64 {
        self.limits.max_bytes.saturating_sub(self.kept)
    }

    fn in_time(&self) -> Result<(), String> {
        match self.limits.deadline {
            Some(d) if std::time::Instant::now() > d => {
                Err("the scene took longer to load than its time allows".into())
            }
            _ => Ok(()),
        }
    }
}

/// The lines of the file at `path` (newlines, and one), read a buffer at a time.
fn count_lines(path: &std::path::Path) -> std::io::Result<u64> {
    use std::io::Read;
    let mut f = std::fs::File::open(path)?;
    let mut buf = vec![0u8; 1 << 20];
    let mut lines = 1;
    loop {
        match f.read(&mut buf) {
            Ok(0) => return Ok(lines),
            Ok(n) => lines += buf[..n].iter().filter(|&&c| c == b'\n').count() as u64,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// The size of the file at `path` (0 if it cannot be read: its loader says why).
fn file_size(path: &std::path::Path) -> u64 {
    std::fs::metadata(path).map(|m| m.len()).unwrap_or(0)
}

struct Builder<'d> {
    doc: &'d Doc,
    budget: Budget,
    bsdf_ids: HashMap<usize, u32>,
    /// Each BSDF object's value, once built.
    bsdf_values: HashMap<usize, Bsdf>,
    /// BSDFs being built, one inside another.
    bsdf_depth: usize,
    textures: HashMap<usize, Texture>,
    bitmaps: HashMap<(std::path::PathBuf, bool), Arc<Bitmap>>,
    bsdfs: Vec<Bsdf>,
    shapes: Vec<Shape>,
    lights: Vec<Light>,
    assets: Vec<std::path::PathBuf>,
    /// The shapes of each shape group (indices into `shapes`), in the order groups are built.
    groups: Vec<Vec<u32>>,
    /// Each shapegroup object's group and the box of its shapes (in the group's space).
    group_of: HashMap<usize, (u32, Option<(Vec3, Vec3)>)>,
    /// Whether the shapes being built belong to a group.
    in_group: bool,
}

/// The box around everything `shapes` holds; `None` if they hold no primitive.
fn bounds_of<'a>(shapes: impl Iterator<Item = &'a Shape>) -> Option<(Vec3, Vec3)> {
    let mut b: Option<(Vec3, Vec3)> = None;
    for s in shapes {
        for k in 0..s.prim_count() {
            let (lo, hi) = s.prim_bounds(k);
            b = Some(b.map_or((lo, hi), |(l, h)| (l.min(lo), h.max(hi))));
        }
    }
    b
}

/// Builds the scene of a parsed document within `limits`.
pub fn build(doc: &Doc, limits: &super::LoadLimits) -> R<Scene> {
    build_within(doc, Budget::new(limits))
}

pub(crate) fn build_within(doc: &Doc, budget: Budget) -> R<Scene> {
    let mut b = Builder {
        doc,
        budget,
        bsdf_ids: HashMap::new(),
        bsdf_values: HashMap::new(),
        bsdf_depth: 0,
        textures: HashMap::new(),
        bitmaps: HashMap::new(),
        bsdfs: Vec::new(),
        shapes: Vec::new(),
        lights: Vec::new(),
        assets: Vec::new(),
        groups: Vec::new(),
        group_of: HashMap::new(),
        in_group: false,
    };
    let root = doc.root;
    for tag in ["film", "rfilter", "sampler"] {
        if let Some((_, _, pos)) = doc.children(root, tag).first() {
            return Err(doc.err(*pos, format!("<{tag}> belongs inside a <sensor>, not at scene level")));
        }
    }
    // Top-level BSDF and texture definitions are built even if unused, so errors surface.
    for (_, i, _) in doc.children(root, "bsdf") {
        b.bsdf(i)?;
    }
    for (_, i, _) in doc.children(root, "texture") {
        b.texture(i)?;
    }
    for (_, i, _) in doc.children(root, "shape") {
        b.shape(i)?;
    }
    for (_, i, pos) in doc.children(root, "emitter") {
        b.emitter(i, pos)?;
    }
    let sensors = doc.children(root, "sensor");
    let (sensor, film, spp, seed, sampler_type) = match sensors.as_slice() {
        [] => return Err(doc.err(doc.obj(root).pos, "the scene has no <sensor>")),
        [(_, s, _)] => b.sensor(*s)?,
        [_, (_, _, pos), ..] => {
            return Err(doc.err(*pos, "more than one <sensor>: Furnace renders one camera per scene"))
        }
    };
    let integrator = match doc.children(root, "integrator").as_slice() {
        [] => PathSettings { max_depth: u32::MAX, rr_depth: 5, hide_emitters: false },
        [(_, i, _)] => b.integrator(*i)?,
        [_, (_, _, pos), ..] => return Err(doc.err(*pos, "more than one <integrator>")),
    };
    doc.check_all_used(root)?;

    let infinite_lights =
        (0..b.lights.len() as u32).filter(|&i| b.lights[i as usize].is_infinite()).collect();
    let prims: u64 = b.shapes.iter().map(|s| s.prim_count() as u64).sum();
    b.budget
        .charge(
            &format!("the BVH of {prims} primitives"),
            prims
                .min(crate::geometry::bvh::BATCH as u64)
                .saturating_mul(BVH_BUILD_PER_PRIM)
                .saturating_add(prims.saturating_mul(BVH_KEPT_PER_PRIM + BVH_ORDER_PER_PRIM)),
            prims.saturating_mul(BVH_KEPT_PER_PRIM),
        )
        .map_err(|e| SceneError::file(&doc.file, e))?;
    let accel =
        if b.budget.limits.accel { Accel::build_grouped(&b.shapes, &b.groups) } else { Accel::build(&[]) };
    let mut scene = Scene {
        file: doc.file.clone(),
        camera: sensor,
        film,
        integrator,
        spp,
        seed,
        sampler_type,
        shapes: b.shapes,
        bsdfs: b.bsdfs,
        lights: b.lights,
        infinite_lights,
        accel,
        techniques: Techniques::default(),
        assets: b.assets,
        load_estimate: b.budget.peak,
    };
    scene.techniques = Techniques::derive(&scene);
    Ok(scene)
}

impl Builder<'_> {
    /// Loads an image within the budget: refused from its header when its texels (at
    /// [`TEXEL_LOAD`] bytes each while decoding) do not fit; each then keeps
    /// [`TEXEL_KEPT`] bytes, and `extra` more.
    fn bitmap(&mut self, path: &std::path::Path, raw: bool, extra: u64) -> Result<Bitmap, String> {
        self.budget.in_time()?;
        let file = file_size(path);
        // The file is read whole: refused before it is, if it alone does not fit.
        self.budget.charge("an image file", file, 0)?;
        let room = self.budget.room().saturating_sub(file);
        let fits = room / TEXEL_LOAD.max(TEXEL_KEPT + extra);
        let bitmap = Bitmap::load_within(path, raw, fits.min(crate::texture::MAX_TEXELS)).map_err(|e| match e {
            crate::texture::BitmapError::TooLarge { width, height, .. } if fits < crate::texture::MAX_TEXELS => format!(
                "a {width} x {height} image does not fit in what is left of the {:.1} MiB a scene may take to load (--max-scene-memory-mb)",
                self.budget.limits.max_bytes as f64 / (1u64 << 20) as f64
            ),
            e => e.to_string(),
        })?;
        let texels = (bitmap.width * bitmap.height) as u64;
        let load = file.saturating_add(texels.saturating_mul(TEXEL_LOAD));
        self.budget.charge("an image", load, texels.saturating_mul(TEXEL_KEPT + extra))?;
        Ok(bitmap)
    }

    fn err(&self, pos: Pos, msg: impl Into<String>) -> SceneError {
        self.doc.err(pos, msg)
    }

    fn unsupported_plugin(&self, i: usize, supported: &[&str]) -> SceneError {
        let o = self.doc.obj(i);
        self.err(
            o.pos,
            format!("unsupported {} plugin '{}' (supported: {})", o.tag, o.plugin, supported.join(", ")),
        )
    }

    fn positive_int(&self, i: usize, name: &str, default: i64) -> R<u32> {
        let v = self.doc.int_or(i, name, default)?;
        if v <= 0 || v > u32::MAX as i64 {
            return Err(self.err(
                self.doc.pos_of(i, name),
                format!("'{name}' of {} must be a positive integer, found {v}", self.doc.describe(i)),
            ));
        }
        Ok(v as u32)
    }

    fn nonneg_float(&self, i: usize, name: &str, default: f32) -> R<f32> {
        let v = self.doc.float_or(i, name, default)?;
        if !(v >= 0.0) || !v.is_finite() {
            return Err(self.err(
                self.doc.pos_of(i, name),
                format!("'{name}' of {} must be a finite number >= 0, found {v}", self.doc.describe(i)),
            ));
        }
        Ok(v)
    }

    fn sensor(&mut self, i: usize) -> R<(Camera, FilmSettings, u32, u64, String)> {
        let doc = self.doc;
        let plugin = doc.obj(i).plugin.clone();
        if plugin != "perspective" && plugin != "thinlens" {
            return Err(self.unsupported_plugin(i, &["perspective", "thinlens"]));
        }
        let film = match doc.children(i, "film").as_slice() {
            [] => FilmSettings {
                width: 768,
                height: 576,
                crop_x: 0,
                crop_y: 0,
                crop_width: 768,
                crop_height: 576,
                filter: Filter::Gaussian { stddev: 0.5 },
            },
            [(_, f, _)] => self.film(*f)?,
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "more than one <film> in the sensor")),
        };
        let (spp, seed, sampler_type) = match doc.children(i, "sampler").as_slice() {
            [] => (4, 0, "independent".to_string()),
            [(_, s, _)] => {
                let known = ["independent", "stratified", "multijitter", "orthogonal", "ldsampler"];
                if !known.contains(&doc.obj(*s).plugin.as_str()) {
                    return Err(self.unsupported_plugin(*s, &known));
                }
                let spp = self.positive_int(*s, "sample_count", 4)?;
                let seed = doc.int_or(*s, "seed", 0)?;
                (spp, seed as u64, doc.obj(*s).plugin.clone())
            }
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "more than one <sampler> in the sensor")),
        };
        let to_world = doc.transform(i, "to_world")?.unwrap_or(Mat4::IDENTITY);
        for (k, axis) in [to_world.x_axis, to_world.y_axis, to_world.z_axis].iter().enumerate() {
            if (axis.truncate().length() - 1.0).abs() > 1e-3 {
                return Err(self.err(
                    doc.pos_of(i, "to_world"),
                    format!(
                        "the sensor's to_world must not scale (axis {k} has length {})",
                        axis.truncate().length()
                    ),
                ));
            }
        }
        let fov = doc.float(i, "fov")?.ok_or_else(|| {
            self.err(doc.obj(i).pos, format!("{} needs a 'fov' (degrees)", doc.describe(i)))
        })?;
        if !(fov > 0.0 && fov < 180.0) {
            return Err(
                self.err(doc.pos_of(i, "fov"), format!("'fov' must lie in (0, 180) degrees, found {fov}"))
            );
        }
        let axis = doc.string(i, "fov_axis")?.unwrap_or_else(|| "x".into());
        let tan_half = tan_half_fov(fov, &axis, film.width, film.height).ok_or_else(|| {
            self.err(
                doc.pos_of(i, "fov_axis"),
                format!("unknown fov_axis '{axis}' (expected x, y, diagonal, smaller or larger)"),
            )
        })?;
        let near_clip = self.nonneg_float(i, "near_clip", 0.01)?;
        if near_clip == 0.0 {
            return Err(self.err(doc.pos_of(i, "near_clip"), "'near_clip' must be greater than zero"));
        }
        let far_clip = doc.float_or(i, "far_clip", 10000.0)?;
        if !(far_clip > near_clip) {
            return Err(self.err(doc.pos_of(i, "far_clip"), "far_clip must exceed near_clip"));
        }
        let lens = if plugin == "thinlens" {
            let aperture_radius = doc
                .float(i, "aperture_radius")?
                .ok_or_else(|| self.err(doc.obj(i).pos, "thinlens needs 'aperture_radius' (world units)"))?;
            if !(aperture_radius >= 0.0) {
                return Err(self.err(doc.pos_of(i, "aperture_radius"), "'aperture_radius' must be >= 0"));
            }
            let focus_distance = doc.float_or(i, "focus_distance", far_clip)?;
            if !(focus_distance > 0.0) {
                return Err(self.err(doc.pos_of(i, "focus_distance"), "'focus_distance' must be > 0"));
            }
            // An aperture of 0 is a pinhole, rendered as one (no lens samples).
            (aperture_radius > 0.0).then_some(ThinLens { aperture_radius, focus_distance })
        } else {
            None
        };
        let camera =
            Camera { to_world, film_size: (film.width, film.height), tan_half, near_clip, far_clip, lens };
        Ok((camera, film, spp, seed, sampler_type))
    }

    fn film(&mut self, i: usize) -> R<FilmSettings> {
        let doc = self.doc;
        if doc.obj(i).plugin != "hdrfilm" {
            return Err(self.unsupported_plugin(i, &["hdrfilm"]));
        }
        let width = self.positive_int(i, "width", 768)?;
        let height = self.positive_int(i, "height", 576)?;
        check_film_size(width, height).map_err(|e| self.err(doc.obj(i).pos, e))?;
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
            return Err(self.err(
                doc.obj(i).pos,
                format!("crop window ({crop_x}, {crop_y}) size {crop_w} x {crop_h} does not fit in the {width} x {height} film"),
            ));
        }
        if let Some(pf) = doc.string(i, "pixel_format")? {
            if pf != "rgb" {
                return Err(self.err(
                    doc.pos_of(i, "pixel_format"),
                    format!("pixel_format '{pf}' is not supported: Furnace writes 'rgb'"),
                ));
            }
        }
        if let Some(cf) = doc.string(i, "component_format")? {
            if cf != "float32" && cf != "float16" {
                return Err(self.err(doc.pos_of(i, "component_format"), format!("component_format '{cf}' is not supported (float16 or float32; Furnace writes float32)")));
            }
        }
        let filter = match doc.children(i, "rfilter").as_slice() {
            [] => Filter::Gaussian { stddev: 0.5 },
            [(_, f, _)] => match doc.obj(*f).plugin.as_str() {
                "box" => {
                    let radius = doc.float_or(*f, "radius", 0.5)?;
                    if !(radius > 0.0 && radius <= 8.0) {
                        return Err(self.err(doc.pos_of(*f, "radius"), "box radius must lie in (0, 8]"));
                    }
                    Filter::Box { radius }
                }
                "gaussian" => {
                    let stddev = doc.float_or(*f, "stddev", 0.5)?;
                    if !(stddev > 0.0 && stddev <= 2.0) {
                        return Err(self.err(doc.pos_of(*f, "stddev"), "gaussian stddev must lie in (0, 2]"));
                    }
                    Filter::Gaussian { stddev }
                }
                _ => return Err(self.unsupported_plugin(*f, &["box", "gaussian"])),
            },
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "more than one <rfilter>")),
        };
        Ok(FilmSettings {
            width,
            height,
            crop_x: crop_x as u32,
            crop_y: crop_y as u32,
            crop_width: crop_w as u32,
            crop_height: crop_h as u32,
            filter,
        })
    }

    fn integrator(&mut self, i: usize) -> R<PathSettings> {
        let doc = self.doc;
        if doc.obj(i).plugin != "path" {
            return Err(self.unsupported_plugin(i, &["path"]));
        }
        let max_depth = doc.int_or(i, "max_depth", -1)?;
        if max_depth < -1 {
            return Err(self.err(doc.pos_of(i, "max_depth"), "max_depth must be -1 (unlimited) or >= 0"));
        }
        let rr_depth = doc.int_or(i, "rr_depth", 5)?;
        if rr_depth <= 0 {
            return Err(self.err(doc.pos_of(i, "rr_depth"), "rr_depth must be > 0"));
        }
        Ok(PathSettings {
            max_depth: if max_depth < 0 { u32::MAX } else { max_depth.min(u32::MAX as i64) as u32 },
            rr_depth: rr_depth.min(u32::MAX as i64) as u32,
            hide_emitters: doc.boolean_or(i, "hide_emitters", false)?,
        })
    }

    /// A colour parameter: `<rgb>`/`<float>`, or a nested/referenced `<texture>`.
    fn color(&mut self, i: usize, name: &str, default: Rgb) -> R<Texture> {
        if self.doc.has(i, name) {
            let c = self.doc.rgb(i, name)?.unwrap_or(default);
            if !c.is_finite() {
                return Err(self.err(self.doc.pos_of(i, name), format!("'{name}' must be finite")));
            }
            return Ok(Texture::Const(c));
        }
        match self.doc.named_child(i, name) {
            Some(t) if self.doc.obj(t).tag == "texture" => self.texture(t),
            Some(t) => Err(self.err(
                self.doc.obj(t).pos,
                format!(
                    "'{name}' of {} must be a colour or a texture, found a {}",
                    self.doc.describe(i),
                    self.doc.obj(t).tag
                ),
            )),
            None => Ok(Texture::Const(default)),
        }
    }

    fn texture(&mut self, i: usize) -> R<Texture> {
        if let Some(t) = self.textures.get(&i) {
            return Ok(t.clone());
        }
        let doc = self.doc;
        let o = doc.obj(i);
        let tex = match o.plugin.as_str() {
            "bitmap" => {
                let rel =
                    doc.string(i, "filename")?.ok_or_else(|| self.err(o.pos, "bitmap needs a 'filename'"))?;
                let path = doc.resolve_path(doc.pos_of(i, "filename"), &rel)?;
                let raw = doc.boolean_or(i, "raw", false)?;
                let filter = self.choice(
                    i,
                    "filter_type",
                    FilterType::Bilinear,
                    &FilterType::ALL.map(|f| (f.name(), f)),
                )?;
                let wrap = self.choice(
                    i,
                    "wrap_mode",
                    WrapMode::Repeat,
                    &[("repeat", WrapMode::Repeat), ("mirror", WrapMode::Mirror), ("clamp", WrapMode::Clamp)],
                )?;
                let to_uv = to_uv_rows(&doc.transform(i, "to_uv")?.unwrap_or(Mat4::IDENTITY));
                let key = (path.clone(), raw);
                let fpos = doc.pos_of(i, "filename");
                let bitmap = match self.bitmaps.get(&key) {
                    Some(b) => b.clone(),
                    None => {
                        let b = Arc::new(
                            self.bitmap(&path, raw, 0)
                                .map_err(|e| self.err(fpos, format!("cannot load texture '{rel}': {e}")))?,
                        );
                        self.assets.push(path.clone());
                        self.bitmaps.insert(key, b.clone());
                        b
                    }
                };
                // The pyramid is built only for the filters that read it.
                let mip = matches!(filter, FilterType::Trilinear | FilterType::Ewa);
                if mip {
                    let texels = (bitmap.width * bitmap.height) as u64;
                    let what = format!("the mipmap of texture '{rel}'");
                    let cost = texels.saturating_mul(MIP_TEXEL);
                    self.budget.charge(&what, cost, cost).map_err(|e| self.err(fpos, e))?;
                }
                let mip = mip.then(|| MipMap::build(&bitmap));
                Texture::Bitmap(Arc::new(BitmapTexture { bitmap, filter, wrap, to_uv, mip }))
            }
            "checkerboard" => Texture::Checkerboard(Arc::new(Checkerboard {
                color0: self.const_color(i, "color0", Rgb::splat(0.4))?,
                color1: self.const_color(i, "color1", Rgb::splat(0.2))?,
                to_uv: to_uv_rows(&doc.transform(i, "to_uv")?.unwrap_or(Mat4::IDENTITY)),
            })),
            _ => return Err(self.unsupported_plugin(i, &["bitmap", "checkerboard"])),
        };
        self.textures.insert(i, tex.clone());
        Ok(tex)
    }

    fn bsdf(&mut self, i: usize) -> R<u32> {
        if let Some(&id) = self.bsdf_ids.get(&i) {
            return Ok(id);
        }
        let b = self.bsdf_value(i)?;
        let id = self.bsdfs.len() as u32;
        self.bsdfs.push(b);
        self.bsdf_ids.insert(i, id);
        Ok(id)
    }

    /// A BSDF object's value, each object built once (`<ref>`s may name one many times).
    fn bsdf_value(&mut self, i: usize) -> R<Bsdf> {
        if let Some(b) = self.bsdf_values.get(&i) {
            return Ok(b.clone());
        }
        // Objects nest at most MAX_NESTING deep in the file; through <ref>s they could chain
        // on: bound that too.
        if self.bsdf_depth >= super::xml::MAX_NESTING {
            return Err(self.err(self.doc.obj(i).pos, "BSDFs nest (through <ref>s) deeper than 64 levels"));
        }
        self.bsdf_depth += 1;
        let b = self.bsdf_made(i);
        self.bsdf_depth -= 1;
        let b = b?;
        self.bsdf_values.insert(i, b.clone());
        Ok(b)
    }

    /// The side of a `twosided` BSDF: one nested inside it is only ever seen from its front
    /// (each side is flipped to the front first), so its front serves.
    fn side(&mut self, i: usize) -> R<Box<Bsdf>> {
        Ok(Box::new(match self.bsdf_value(i)? {
            Bsdf::TwoSided { front, .. } => *front,
            b => b,
        }))
    }

    fn bsdf_made(&mut self, i: usize) -> R<Bsdf> {
        let doc = self.doc;
        Ok(match doc.obj(i).plugin.as_str() {
            "diffuse" => Bsdf::Diffuse { reflectance: self.color(i, "reflectance", Rgb::splat(0.5))? },
            "twosided" => {
                let nested = doc.children(i, "bsdf");
                match nested.as_slice() {
                    [(_, f, _)] => {
                        let front = self.side(*f)?;
                        Bsdf::TwoSided { front: front.clone(), back: front }
                    }
                    [(_, f, _), (_, bk, _)] => {
                        Bsdf::TwoSided { front: self.side(*f)?, back: self.side(*bk)? }
                    }
                    _ => return Err(self.err(doc.obj(i).pos, "twosided needs one or two nested <bsdf>s")),
                }
            }
            "conductor" | "roughconductor" => {
                let (eta, k) = self.conductor_ior(i)?;
                Bsdf::Conductor(Conductor {
                    eta,
                    k,
                    specular_reflectance: self.color(i, "specular_reflectance", Rgb::ONE)?,
                    rough: self.roughness(i)?,
                })
            }
            "dielectric" | "roughdielectric" | "thindielectric" => {
                let int_ior = self.ior(i, "int_ior", "bk7")?;
                let ext_ior = self.ior(i, "ext_ior", "air")?;
                if doc.obj(i).plugin == "roughdielectric" {
                    self.distinct_iors(i, int_ior, ext_ior)?;
                }
                Bsdf::Dielectric(Dielectric {
                    eta: int_ior / ext_ior,
                    specular_reflectance: self.color(i, "specular_reflectance", Rgb::ONE)?,
                    specular_transmittance: self.color(i, "specular_transmittance", Rgb::ONE)?,
                    rough: self.roughness(i)?,
                    thin: doc.obj(i).plugin == "thindielectric",
                })
            }
            "hair" => {
                let eta = self.ior(i, "int_ior", "amber")? / self.ior(i, "ext_ior", "air")?;
                let beta_m = doc.float_or(i, "longitudinal_roughness", 0.3)?;
                let beta_n = doc.float_or(i, "azimuthal_roughness", 0.3)?;
                for (name, b) in [("longitudinal_roughness", beta_m), ("azimuthal_roughness", beta_n)] {
                    if !(b > 0.0 && b <= 1.0) {
                        return Err(
                            self.err(doc.pos_of(i, name), format!("'{name}' must lie in (0, 1], found {b}"))
                        );
                    }
                }
                let tilt = doc.float_or(i, "scale_tilt", 2.0)?;
                let pigments = doc.has(i, "eumelanin") || doc.has(i, "pheomelanin");
                let given = [doc.has(i, "sigma_a"), pigments, doc.has(i, "reflectance")];
                if given.iter().filter(|&&g| g).count() > 1 {
                    return Err(self.err(
                        doc.obj(i).pos,
                        "hair: give one of sigma_a, the pigments (eumelanin/pheomelanin) or reflectance",
                    ));
                }
                let sigma_a = if doc.has(i, "sigma_a") {
                    self.const_color(i, "sigma_a", Rgb::ZERO)? * self.nonneg_float(i, "scale", 1.0)?
                } else if doc.has(i, "reflectance") {
                    crate::bsdf::hair::Hair::sigma_a_from_reflectance(
                        self.const_color(i, "reflectance", Rgb::splat(0.5))?,
                        beta_n,
                    )
                } else {
                    crate::bsdf::hair::Hair::sigma_a_from_melanin(
                        self.nonneg_float(i, "eumelanin", 1.3)?,
                        self.nonneg_float(i, "pheomelanin", 0.2)?,
                    )
                };
                Bsdf::Hair(crate::bsdf::hair::Hair::new(sigma_a, eta, beta_m, beta_n, tilt))
            }
            "plastic" | "roughplastic" => {
                let int_ior = self.ior(i, "int_ior", "polypropylene")?;
                let ext_ior = self.ior(i, "ext_ior", "air")?;
                if doc.obj(i).plugin == "roughplastic" {
                    self.distinct_iors(i, int_ior, ext_ior)?;
                    for name in ["alpha_u", "alpha_v"] {
                        if doc.has(i, name) || doc.named_child_exists(i, name) {
                            return Err(self.err(
                                doc.pos_of(i, name),
                                "roughplastic does not support anisotropic roughness (alpha_u, alpha_v): give one 'alpha'",
                            ));
                        }
                    }
                }
                let eta = int_ior / ext_ior;
                let diffuse_reflectance = self.color(i, "diffuse_reflectance", Rgb::splat(0.5))?;
                let specular_reflectance = self.color(i, "specular_reflectance", Rgb::ONE)?;
                let d = diffuse_reflectance.mean().element_sum() / 3.0;
                let s = specular_reflectance.mean().element_sum() / 3.0;
                let (rough, fdr_int) = match self.roughness(i)? {
                    None => (None, fresnel_diffuse_reflectance(1.0 / eta)),
                    Some(r) => {
                        // The coating's transmittance is tabulated for one roughness.
                        if !matches!((&r.alpha_u, &r.alpha_v), (Texture::Const(_), Texture::Const(_))) {
                            return Err(self.err(
                                doc.obj(i).pos,
                                "roughplastic: alpha must be a constant, not a texture",
                            ));
                        }
                        let (coating, fdr) = RoughCoating::new(r, eta);
                        (Some(coating), fdr)
                    }
                };
                Bsdf::Plastic(Plastic {
                    eta,
                    fdr_int,
                    nonlinear: doc.boolean_or(i, "nonlinear", false)?,
                    specular_weight: s / (d + s),
                    diffuse_reflectance,
                    specular_reflectance,
                    rough,
                })
            }
            _ => {
                return Err(self.unsupported_plugin(
                    i,
                    &[
                        "diffuse",
                        "twosided",
                        "conductor",
                        "roughconductor",
                        "dielectric",
                        "roughdielectric",
                        "thindielectric",
                        "plastic",
                        "roughplastic",
                        "hair",
                    ],
                ))
            }
        })
    }

    /// The rough interfaces (roughdielectric, roughplastic) need a real interface: with equal
    /// indices of refraction their microfacet terms divide by zero (Mitsuba refuses them too).
    fn distinct_iors(&self, i: usize, int_ior: f32, ext_ior: f32) -> R<()> {
        if int_ior == ext_ior {
            let pos = if self.doc.has(i, "int_ior") {
                self.doc.pos_of(i, "int_ior")
            } else {
                self.doc.pos_of(i, "ext_ior")
            };
            return Err(self.err(
                pos,
                format!(
                    "{}: the interior and exterior indices of refraction must differ (both are {int_ior})",
                    self.doc.describe(i)
                ),
            ));
        }
        Ok(())
    }

    /// A string parameter naming one of `choices` (`default` when absent).
    fn choice<T: Copy>(&self, i: usize, name: &str, default: T, choices: &[(&str, T)]) -> R<T> {
        let Some(v) = self.doc.string(i, name)? else { return Ok(default) };
        choices.iter().find(|(n, _)| *n == v).map(|(_, t)| *t).ok_or_else(|| {
            let names: Vec<&str> = choices.iter().map(|(n, _)| *n).collect();
            self.err(
                self.doc.pos_of(i, name),
                format!("unknown {name} '{v}' (expected one of: {})", names.join(", ")),
            )
        })
    }

    /// A colour parameter that must be constant.
    fn const_color(&mut self, i: usize, name: &str, default: Rgb) -> R<Rgb> {
        match self.color(i, name, default)? {
            Texture::Const(c) => Ok(c),
            _ => Err(self.err(
                self.doc.pos_of(i, name),
                format!("'{name}' of {} must be a colour, not a texture", self.doc.describe(i)),
            )),
        }
    }

    /// The rotation part of `to_world`; refuses scaling and shearing.
    fn rotation(&mut self, i: usize) -> R<Mat3> {
        let m = self.doc.transform(i, "to_world")?.unwrap_or(Mat4::IDENTITY);
        let r = Mat3::from_mat4(m);
        let ortho = (r.transpose() * r - Mat3::IDENTITY).to_cols_array().iter().all(|v| v.abs() < 1e-3);
        if !ortho {
            return Err(self.err(
                self.doc.pos_of(i, "to_world"),
                format!("the to_world of {} must be a rotation", self.doc.describe(i)),
            ));
        }
        Ok(r)
    }

    /// A float parameter that may also be a texture (its red channel is used).
    fn float_texture(&mut self, i: usize, name: &str, default: f32) -> R<Texture> {
        if self.doc.has(i, name) {
            let v = self.doc.float(i, name)?.unwrap_or(default);
            if !v.is_finite() {
                return Err(self.err(self.doc.pos_of(i, name), format!("'{name}' must be finite")));
            }
            return Ok(Texture::Const(Rgb::splat(v)));
        }
        self.color(i, name, Rgb::splat(default))
    }

    /// `distribution` and `alpha` / `alpha_u` + `alpha_v` of the rough plugins; `None` for the
    /// smooth ones.
    fn roughness(&mut self, i: usize) -> R<Option<Roughness>> {
        let doc = self.doc;
        if !doc.obj(i).plugin.starts_with("rough") {
            return Ok(None);
        }
        let dist = self.choice(
            i,
            "distribution",
            Distribution::Beckmann,
            &[("beckmann", Distribution::Beckmann), ("ggx", Distribution::Ggx)],
        )?;
        if !doc.boolean_or(i, "sample_visible", true)? && dist == Distribution::Ggx {
            return Err(self.err(
                doc.pos_of(i, "sample_visible"),
                "sample_visible=false is not supported: Furnace always samples GGX's visible normals",
            ));
        }
        let has_uv = doc.has(i, "alpha_u") || doc.named_child_exists(i, "alpha_u");
        let (alpha_u, alpha_v) = if has_uv {
            if doc.has(i, "alpha") {
                return Err(
                    self.err(doc.pos_of(i, "alpha"), "give 'alpha' or 'alpha_u' and 'alpha_v', not both")
                );
            }
            (self.float_texture(i, "alpha_u", 0.1)?, self.float_texture(i, "alpha_v", 0.1)?)
        } else {
            let a = self.float_texture(i, "alpha", 0.1)?;
            (a.clone(), a)
        };
        for a in [&alpha_u, &alpha_v] {
            if let Texture::Const(c) = a {
                if !(c.x >= 0.0) {
                    return Err(self.err(doc.obj(i).pos, format!("alpha must be >= 0, found {}", c.x)));
                }
            }
        }
        Ok(Some(Roughness { dist, alpha_u, alpha_v }))
    }

    /// `material` preset or `eta` + `k` of a conductor.
    fn conductor_ior(&mut self, i: usize) -> R<(Rgb, Rgb)> {
        let doc = self.doc;
        let material = doc.string(i, "material")?;
        let has_eta_k = doc.has(i, "eta") || doc.has(i, "k");
        match (material, has_eta_k) {
            (Some(_), true) => {
                Err(self.err(doc.pos_of(i, "material"), "give 'material' or 'eta' and 'k', not both"))
            }
            (None, true) => {
                let eta = doc.rgb(i, "eta")?.unwrap_or(Rgb::ZERO);
                let k = doc.rgb(i, "k")?.unwrap_or(Rgb::ONE);
                Ok((eta, k))
            }
            (m, false) => {
                let name = m.unwrap_or_else(|| "none".into());
                conductor_preset(&name).ok_or_else(|| {
                    self.err(
                        doc.pos_of(i, "material"),
                        format!(
                            "unknown conductor material '{name}' (known: {})",
                            CONDUCTOR_PRESETS.join(", ")
                        ),
                    )
                })
            }
        }
    }

    /// An index of refraction: a number, or one of Mitsuba's named media.
    fn ior(&mut self, i: usize, name: &str, default: &str) -> R<f32> {
        let doc = self.doc;
        let pos = doc.pos_of(i, name);
        let v = if doc.has(i, name) && doc.string(i, name).is_err() {
            doc.float(i, name)?.unwrap_or(1.0)
        } else {
            let n = doc.string(i, name)?.unwrap_or_else(|| default.to_string());
            named_ior(&n).ok_or_else(|| {
                self.err(
                    pos,
                    format!(
                        "unknown index of refraction '{n}' (a number, or one of: {})",
                        IOR_NAMES.join(", ")
                    ),
                )
            })?
        };
        if !(v > 0.0) || !v.is_finite() {
            return Err(self.err(pos, format!("'{name}' must be a positive number, found {v}")));
        }
        Ok(v)
    }

    fn shape(&mut self, i: usize) -> R<()> {
        let doc = self.doc;
        let o = doc.obj(i);
        match o.plugin.as_str() {
            "shapegroup" | "instance" if self.in_group => {
                return Err(self.err(
                    o.pos,
                    format!(
                        "a shapegroup cannot hold {}: nested instancing is not supported (nor in Mitsuba 3)",
                        doc.describe(i)
                    ),
                ))
            }
            "shapegroup" => return self.shape_group(i).map(|_| ()),
            "instance" => return self.instance(i),
            _ => {}
        }
        let to_world = doc.transform(i, "to_world")?.unwrap_or(Mat4::IDENTITY);
        let flip_normals = doc.boolean_or(i, "flip_normals", false)?;
        let mesh = |m: Mesh| -> Geometry {
            let mut m = m;
            m.transform(&to_world);
            Geometry::Mesh(m)
        };
        let geometry = match o.plugin.as_str() {
            "rectangle" | "cube" => {
                let mut m = if o.plugin == "cube" { Mesh::cube() } else { Mesh::rectangle() };
                m.transform_flat(&to_world);
                Geometry::Mesh(m)
            }
            "obj" | "ply" => {
                let rel = doc
                    .string(i, "filename")?
                    .ok_or_else(|| self.err(o.pos, format!("{} needs a 'filename'", o.plugin)))?;
                let fpos = doc.pos_of(i, "filename");
                let path = doc.resolve_path(fpos, &rel)?;
                let face_normals = doc.boolean_or(i, "face_normals", false)?;
                let parse = if o.plugin == "ply" {
                    crate::geometry::mesh::ply_load_estimate(&path)
                } else {
                    file_size(&path).saturating_mul(PARSE_PER_BYTE)
                };
                self.budget.charge(&format!("mesh '{rel}'"), parse, 0).map_err(|e| self.err(fpos, e))?;
                let loaded = if o.plugin == "obj" {
                    let flip_v = doc.boolean_or(i, "flip_tex_coords", true)?;
                    Mesh::load_obj(&path, flip_v)
                } else {
                    Mesh::load_ply(&path)
                };
                let mut m = loaded
                    .and_then(Mesh::validate)
                    .map_err(|e| self.err(fpos, format!("{} '{rel}': {e}", o.plugin)))?;
                if face_normals {
                    m.normals.clear();
                    m.normals.shrink_to_fit();
                }
                let kept = std::mem::size_of_val(m.positions.as_slice())
                    + std::mem::size_of_val(m.normals.as_slice())
                    + std::mem::size_of_val(m.uvs.as_slice())
                    + std::mem::size_of_val(m.tris.as_slice());
                self.budget
                    .charge(&format!("mesh '{rel}'"), 0, kept as u64)
                    .map_err(|e| self.err(fpos, e))?;
                self.assets.push(path);
                mesh(m)
            }
            "sphere" => {
                let center = doc.point(i, "center")?.unwrap_or(Vec3::ZERO);
                let radius = doc.float_or(i, "radius", 1.0)?;
                if !(radius > 0.0 && radius <= MAX_COORD) {
                    return Err(self.err(
                        doc.pos_of(i, "radius"),
                        format!("sphere radius must be > 0 and at most {MAX_COORD:e}, found {radius:e}"),
                    ));
                }
                let m = to_world * Mat4::from_translation(center) * Mat4::from_scale(Vec3::splat(radius));
                let c = m.transform_point3(Vec3::ZERO);
                let axes = [m.x_axis.truncate(), m.y_axis.truncate(), m.z_axis.truncate()];
                let r = axes[0].length();
                if axes.iter().any(|a| (a.length() - r).abs() > 1e-4 * r) {
                    return Err(self.err(doc.pos_of(i, "to_world"), "sphere to_world must scale uniformly"));
                }
                let rot = Mat3::from_cols(axes[0] / r, axes[1] / r, axes[2] / r).transpose();
                Geometry::Sphere(Sphere { center: c, radius: r, rot })
            }
            "disk" => Geometry::Disk(Disk::new(to_world)),
            "linearcurve" | "bsplinecurve" => {
                let bspline = o.plugin == "bsplinecurve";
                let rel = doc
                    .string(i, "filename")?
                    .ok_or_else(|| self.err(o.pos, format!("{} needs a 'filename'", o.plugin)))?;
                let fpos = doc.pos_of(i, "filename");
                let path = doc.resolve_path(fpos, &rel)?;
                // The text is read a block at a time (`read_curve_file`), never whole; what
                // parsing holds follows from the file's lines, counted first in a streamed
                // pass: each a point (16 bytes, up to twice that in a grown list), and each
                // curve (at least `min` points) a list in two lists of lists (about 96 bytes).
                let size = file_size(&path);
                let cannot =
                    |e: std::io::Error| doc.err(fpos, format!("cannot read curve file '{rel}': {e}"));
                let lines = count_lines(&path).map_err(cannot)?;
                let min = if bspline { 4 } else { 2 };
                let text = size.min(2 * crate::geometry::curves::CURVE_BLOCK as u64);
                let parse = text.saturating_add(lines.saturating_mul(CURVE_POINT_PARSE + CURVE_PARSE / min));
                self.budget
                    .charge(&format!("curve file '{rel}'"), parse, 0)
                    .map_err(|e| self.err(fpos, e))?;
                let file = std::fs::File::open(&path).map_err(cannot)?;
                let mut curves = crate::geometry::curves::read_curve_file(file, min as usize)
                    .map_err(|e| self.err(fpos, format!("{} '{rel}': {e}", o.plugin)))?;
                // to_world moves the points, not the radii (as Mitsuba).
                for c in &mut curves {
                    for (p, _) in c.iter_mut() {
                        *p = to_world.transform_point3(*p);
                    }
                }
                self.assets.push(path);
                // A B-spline of n points has n - 3 spans of BSPLINE_STEPS segments; a polyline
                // n - 1 segments.
                let segments: u64 = curves
                    .iter()
                    .map(|c| if bspline { c.len().saturating_sub(3) * BSPLINE_STEPS } else { c.len().saturating_sub(1) } as u64)
                    .sum();
                let kept =
                    segments.saturating_mul(std::mem::size_of::<crate::geometry::curves::Segment>() as u64);
                // Meanwhile the parsed points are still held, and the B-spline tessellation's
                // points of the curves being worked on (a few thousand per thread).
                let points = parse - text;
                self.budget
                    .charge(&format!("curve file '{rel}'"), points.saturating_add(kept), kept)
                    .map_err(|e| self.err(fpos, e))?;
                if bspline {
                    let (c, err) = crate::geometry::curves::Curves::bspline(&curves, BSPLINE_STEPS);
                    tracing::debug!(
                        "bsplinecurve '{rel}': {} segments, chord error {err:.3e}",
                        c.segments.len()
                    );
                    Geometry::Curves(c)
                } else {
                    Geometry::Curves(crate::geometry::curves::Curves::linear(&curves))
                }
            }
            _ => {
                return Err(self.unsupported_plugin(
                    i,
                    &[
                        "obj",
                        "ply",
                        "rectangle",
                        "cube",
                        "sphere",
                        "disk",
                        "linearcurve",
                        "bsplinecurve",
                        "shapegroup",
                        "instance",
                    ],
                ))
            }
        };
        let emitters = doc.children(i, "emitter");
        let bsdf = match doc.children(i, "bsdf").as_slice() {
            [] => {
                // Mitsuba's default material: diffuse 0.5, or black on an emitter.
                let r = if emitters.is_empty() { 0.5 } else { 0.0 };
                let id = self.bsdfs.len() as u32;
                self.bsdfs.push(Bsdf::Diffuse { reflectance: Texture::Const(Rgb::splat(r)) });
                id
            }
            [(_, b, _)] => self.bsdf(*b)?,
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "a shape takes one <bsdf>")),
        };
        let shape_idx = self.shapes.len() as u32;
        self.check_extent(i, &geometry)?;
        let mut shape = Shape {
            geometry,
            bsdf,
            light: None,
            flip_normals,
            name: o.id.clone().unwrap_or_else(|| o.plugin.clone()),
        };
        match emitters.as_slice() {
            [] => {}
            [(_, e, _)] if self.in_group => {
                return Err(self.err(
                    doc.obj(*e).pos,
                    "a shape in a shapegroup cannot carry an emitter: instances of emitters are not supported (nor in Mitsuba 3)",
                ));
            }
            [(_, e, _)] => {
                if matches!(shape.geometry, Geometry::Curves(_)) {
                    return Err(self.err(doc.obj(*e).pos, "curves cannot carry an area emitter"));
                }
                if doc.obj(*e).plugin != "area" {
                    return Err(self.err(
                        doc.obj(*e).pos,
                        format!(
                            "emitter '{}' cannot be attached to a shape (only 'area')",
                            doc.obj(*e).plugin
                        ),
                    ));
                }
                let radiance = self.color(*e, "radiance", Rgb::ONE)?;
                shape.light = Some(self.lights.len() as u32);
                self.lights.push(Light::area(shape_idx, &shape, radiance));
            }
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "a shape takes one <emitter>")),
        }
        self.shapes.push(shape);
        Ok(())
    }

    /// Builds a `shapegroup` once (however many instances name it): its shapes, in its own
    /// space, are drawn only where instances place them.
    fn shape_group(&mut self, i: usize) -> R<(u32, Option<(Vec3, Vec3)>)> {
        if let Some(&g) = self.group_of.get(&i) {
            return Ok(g);
        }
        let doc = self.doc;
        if doc.has(i, "to_world") {
            return Err(self.err(
                doc.pos_of(i, "to_world"),
                "a shapegroup takes no to_world: its instances' to_world places it (and its shapes' their own)",
            ));
        }
        let first = self.shapes.len();
        self.in_group = true;
        let built = doc.children(i, "shape").into_iter().try_for_each(|(_, c, _)| self.shape(c));
        self.in_group = false;
        built?;
        let bounds = bounds_of(self.shapes[first..].iter());
        let g = (self.groups.len() as u32, bounds);
        self.groups.push((first as u32..self.shapes.len() as u32).collect());
        self.group_of.insert(i, g);
        Ok(g)
    }

    /// An `instance`: one shapegroup (a `<ref>` or the group itself), placed by `to_world`.
    fn instance(&mut self, i: usize) -> R<()> {
        let doc = self.doc;
        let o = doc.obj(i);
        for tag in ["bsdf", "emitter"] {
            if let Some((_, _, pos)) = doc.children(i, tag).first() {
                return Err(self.err(
                    *pos,
                    if tag == "bsdf" {
                        "an instance takes no <bsdf>: the shapes of its shapegroup carry their own (as in Mitsuba 3)"
                    } else {
                        "an instance takes no <emitter>: instances of emitters are not supported (nor in Mitsuba 3)"
                    },
                ));
            }
        }
        let (group, bounds) = match doc.children(i, "shape").as_slice() {
            [] => {
                return Err(self.err(
                    o.pos,
                    "an instance needs the shapegroup it places: <ref id=\"...\"/> naming a <shape type=\"shapegroup\">",
                ))
            }
            [(_, c, _)] if doc.obj(*c).plugin == "shapegroup" => self.shape_group(*c)?,
            [(_, c, pos)] => {
                return Err(self.err(*pos, format!("an instance places a shapegroup, not {}", doc.describe(*c))))
            }
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "an instance places one shapegroup")),
        };
        let to_world = doc.transform(i, "to_world")?.unwrap_or(Mat4::IDENTITY);
        // Squashed along some direction, an instance moves rays' origins far away in its
        // group's space: past about 1e10 a hit's distance is no longer resolved in f32 (a
        // panel squashed 1e-11 seen from 6 units loses pixels; below 1e-19 the direction
        // itself overflows). The parser has checked that the transform is invertible.
        let shrink =
            Mat3::from_mat4(to_world.inverse()).to_cols_array().iter().fold(0f32, |m, x| m.max(x.abs()));
        if !(shrink <= MAX_INSTANCE_SHRINK) {
            return Err(self.err(
                doc.pos_of(i, "to_world"),
                format!("an instance's to_world may shrink its group at most {MAX_INSTANCE_SHRINK:e} times along any direction; this one shrinks it about {shrink:e} times"),
            ));
        }
        let geometry = Geometry::Instance(Instance::new(group, to_world, bounds));
        self.check_extent(i, &geometry)?;
        self.shapes.push(Shape {
            geometry,
            // Never read: hits inside an instance are its group's shapes', with their BSDFs.
            bsdf: u32::MAX,
            light: None,
            flip_normals: false,
            name: o.id.clone().unwrap_or_else(|| o.plugin.clone()),
        });
        Ok(())
    }

    /// Refuses a shape that reaches beyond what f32 geometry holds once in world space (a
    /// sphere radius of 1e20, a mesh scaled by 1e30) or holds a non-finite bound.
    fn check_extent(&self, i: usize, g: &Geometry) -> R<()> {
        for k in 0..g.prim_count() {
            let (lo, hi) = g.prim_bounds(k);
            let far = lo.abs().max(hi.abs()).max_element();
            if !(far <= MAX_COORD) {
                return Err(self.err(
                    self.doc.obj(i).pos,
                    format!(
                        "{} reaches coordinate {far:e} in world space: shapes must lie within +-{MAX_COORD:e}, what 32-bit float geometry can hold",
                        self.doc.describe(i)
                    ),
                ));
            }
        }
        Ok(())
    }

    fn emitter(&mut self, i: usize, pos: Pos) -> R<()> {
        let doc = self.doc;
        let light = match doc.obj(i).plugin.as_str() {
            "point" => {
                let intensity = self.const_color(i, "intensity", Rgb::ONE)?;
                let m = doc.transform(i, "to_world")?;
                let p = doc.point(i, "position")?;
                let position = match (m, p) {
                    (Some(_), Some(_)) => {
                        return Err(self.err(pos, "point emitter: give 'position' or 'to_world', not both"))
                    }
                    (Some(m), None) => m.transform_point3(Vec3::ZERO),
                    (None, Some(p)) => p,
                    (None, None) => Vec3::ZERO,
                };
                Light::Point { position, intensity }
            }
            "constant" => Light::Constant { radiance: self.const_color(i, "radiance", Rgb::ONE)? },
            "envmap" => {
                let rel =
                    doc.string(i, "filename")?.ok_or_else(|| self.err(pos, "envmap needs a 'filename'"))?;
                let fpos = doc.pos_of(i, "filename");
                let path = doc.resolve_path(fpos, &rel)?;
                let scale = self.nonneg_float(i, "scale", 1.0)?;
                let to_world = self.rotation(i)?;
                let filter = self.choice(
                    i,
                    "filter_type",
                    FilterType::Bilinear,
                    &[("bilinear", FilterType::Bilinear), ("nearest", FilterType::Nearest)],
                )?;
                // Mitsuba's default is false; Furnace compensates unless the scene says not to.
                let compensate = doc.boolean_or(i, "mis_compensation", true)?;
                let bitmap = self
                    .bitmap(&path, false, 0)
                    .map_err(|e| self.err(fpos, format!("cannot load envmap '{rel}': {e}")))?;
                let (peak, kept) = EnvMap::table_bytes(bitmap.width, bitmap.height, filter);
                self.budget
                    .charge("the environment map's sampling tables", peak, kept)
                    .map_err(|e| self.err(fpos, format!("envmap '{rel}': {e}")))?;
                self.assets.push(path);
                Light::Envmap(Arc::new(EnvMap::new(Arc::new(bitmap), scale, to_world, filter, compensate)))
            }
            "directional" => {
                let irradiance = self.const_color(i, "irradiance", Rgb::ONE)?;
                let direction = match (doc.point(i, "direction")?, doc.transform(i, "to_world")?) {
                    (Some(_), Some(_)) => {
                        return Err(self.err(pos, "directional: give 'direction' or 'to_world', not both"))
                    }
                    (Some(d), None) => d,
                    (None, Some(m)) => m.transform_vector3(Vec3::Z),
                    (None, None) => Vec3::Z,
                };
                if direction.length_squared() == 0.0 || !direction.is_finite() {
                    return Err(self.err(pos, "directional: the direction must be a non-zero vector"));
                }
                Light::Directional { direction: direction.normalize(), irradiance }
            }
            "spot" => {
                let intensity = self.const_color(i, "intensity", Rgb::ONE)?;
                let cutoff = doc.float_or(i, "cutoff_angle", 20.0)?;
                let beam = doc.float_or(i, "beam_width", cutoff * 0.75)?;
                if !(cutoff > 0.0 && cutoff <= 180.0 && beam > 0.0 && beam <= cutoff) {
                    return Err(self.err(
                        pos,
                        format!("spot: need 0 < beam_width ({beam}) <= cutoff_angle ({cutoff}) <= 180"),
                    ));
                }
                let m = doc.transform(i, "to_world")?.unwrap_or(Mat4::IDENTITY);
                let (cutoff, beam) = (cutoff.to_radians(), beam.to_radians());
                Light::Spot {
                    position: m.transform_point3(Vec3::ZERO),
                    axis: m.transform_vector3(Vec3::Z).normalize(),
                    intensity,
                    cos_cutoff: cutoff.cos(),
                    cos_beam: beam.cos(),
                    cutoff,
                    beam,
                }
            }
            "area" => return Err(self.err(pos, "an 'area' emitter must be nested inside a <shape>")),
            _ => {
                return Err(self.unsupported_plugin(
                    i,
                    &["point", "spot", "directional", "constant", "envmap", "area (inside a shape)"],
                ))
            }
        };
        self.lights.push(light);
        Ok(())
    }
}

/// Round segments per B-spline span.
const BSPLINE_STEPS: usize = 8;

/// Indices of refraction of common media (at about 589 nm), under Mitsuba's names.
const IORS: &[(&str, f32)] = &[
    ("vacuum", 1.0),
    ("air", 1.000277),
    ("water", 1.3330),
    ("water ice", 1.31),
    ("fused quartz", 1.458),
    ("pyrex", 1.470),
    ("acrylic glass", 1.49),
    ("polypropylene", 1.49),
    ("bk7", 1.5046),
    ("amber", 1.55),
    ("diamond", 2.419),
];
const IOR_NAMES: &[&str] = &[
    "vacuum",
    "air",
    "water",
    "water ice",
    "fused quartz",
    "pyrex",
    "acrylic glass",
    "polypropylene",
    "bk7",
    "amber",
    "diamond",
];

fn named_ior(name: &str) -> Option<f32> {
    IORS.iter().find(|(n, _)| *n == name).map(|(_, v)| *v)
}
