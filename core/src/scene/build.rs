//! Turns the parsed XML tree into a [`Scene`], with Mitsuba's plugin names, parameters and
//! defaults. Anything the builder does not consume is reported by `Doc::check_all_used`.

use std::collections::HashMap;
use std::sync::Arc;

use glam::{Mat3, Mat4, Vec3};

use super::plugins::{self, Make};
use super::xml::{Doc, Pos, MAX_COORD};
use super::{FilmSettings, PathSettings, Scene, SceneError};
use crate::bsdf::conductor::{conductor_preset, CONDUCTOR_PRESETS};
use crate::bsdf::{Bsdf, Distribution, Roughness};
use crate::camera::Camera;
use crate::film::Filter;
use crate::geometry::{Accel, Geometry, Instance, Shape};
use crate::light::Light;
use crate::math::Rgb;
use crate::plan::Techniques;
use crate::texture::{Bitmap, Image, Texture, MAX_TEXELS};

pub(crate) type R<T> = Result<T, SceneError>;

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
// bytes per byte of XML; a 4096 x 4096 PNG decoded to f32 at 27 bytes a texel (`TEXEL_LOAD`;
// one that keeps its bytes: `texture::bitmap::byte_texel_load`); OBJ at 7.1 and curve files at
// 3.5 bytes per byte of file (PLY: see `ply_load_estimate`); the BVH's build at 344 bytes a
// primitive, keeping 54 (triangles) or 16 (curve segments).
/// What a load holds whatever the scene.
const BASE: u64 = 1 << 20;
/// What the XML parser holds per byte of the scene file (the text, the tree, positions), and
/// keeps while the scene is built.
pub(crate) const XML_PER_BYTE: u64 = 20;
/// What a texel keeps: linear RGB (a pyramid's levels above the image are charged by their
/// own sizes, `texture::bitmap::from_scene`).
const TEXEL_KEPT: u64 = std::mem::size_of::<Rgb>() as u64;
/// What the OBJ loader holds per byte of its file while parsing.
pub(crate) const PARSE_PER_BYTE: u64 = 12;
/// What parsing a curve file holds per point (a line), and per curve, besides its text.
pub(crate) const CURVE_POINT_PARSE: u64 = 32;
pub(crate) const CURVE_PARSE: u64 = 96;
/// What building the BVH holds at its peak per primitive the builder takes in one batch
/// (obvhs' scratch; a piece of fibre is one, `Accel::build_units`), what it holds per such
/// primitive of the scene on top of what it keeps (the Morton order of a batched build), and
/// what it keeps per primitive.
const BVH_BUILD_PER_UNIT: u64 = 384;
const BVH_ORDER_PER_UNIT: u64 = 28;
const BVH_KEPT_PER_PRIM: u64 = 64;
/// The decoded copy of a small scene's tree per primitive (256 bytes a node; hair.xml has
/// 0.14 nodes a primitive, 36 bytes), up to `geometry::bvh::FLAT_BYTES` in all.
const FLAT_PER_PRIM: u64 = 48;

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
pub(crate) fn count_lines(path: &std::path::Path) -> std::io::Result<u64> {
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
pub(crate) fn file_size(path: &std::path::Path) -> u64 {
    std::fs::metadata(path).map(|m| m.len()).unwrap_or(0)
}

/// What building a scene holds: the document, the memory budget, and the parts built so far.
/// Plugin constructors (see `plugins`) read their parameters through it.
pub(crate) struct Builder<'d> {
    pub(crate) doc: &'d Doc,
    pub(crate) budget: Budget,
    bsdf_ids: HashMap<usize, u32>,
    /// Each BSDF object's value, once built.
    bsdf_values: HashMap<usize, Bsdf>,
    /// BSDFs being built, one inside another.
    bsdf_depth: usize,
    textures: HashMap<usize, Texture>,
    bitmaps: HashMap<(std::path::PathBuf, bool), Image>,
    bsdfs: Vec<Bsdf>,
    shapes: Vec<Shape>,
    lights: Vec<Light>,
    /// Every file the scene reads.
    pub(crate) assets: Vec<std::path::PathBuf>,
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
    if let Some(cache) = &budget.limits.assets {
        cache.begin_load();
    }
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
    // A sphere computes uv and tangents at a hit only for a BSDF or emitter that reads them.
    for shape in &mut b.shapes {
        if let Geometry::Sphere(s) = &mut shape.geometry {
            let emitter = shape.light.is_some_and(|l| b.lights[l as usize].reads_surface());
            s.tangents = b.bsdfs[shape.bsdf as usize].reads_surface() || emitter;
        }
    }
    let prims: u64 = b.shapes.iter().map(|s| s.prim_count() as u64).sum();
    let (units, most) = Accel::build_units(&b.shapes, &b.groups);
    let flat = prims.saturating_mul(FLAT_PER_PRIM).min(crate::geometry::bvh::FLAT_BYTES as u64);
    b.budget
        .charge(
            &format!("the BVH of {prims} primitives"),
            (most.min(crate::geometry::bvh::BATCH) as u64)
                .saturating_mul(BVH_BUILD_PER_UNIT)
                .saturating_add((units as u64).saturating_mul(BVH_ORDER_PER_UNIT))
                .saturating_add(prims.saturating_mul(BVH_KEPT_PER_PRIM))
                .saturating_add(flat),
            prims.saturating_mul(BVH_KEPT_PER_PRIM).saturating_add(flat),
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
        bsdf_traits: b.bsdfs.iter().map(Bsdf::traits).collect(),
        bsdfs: b.bsdfs,
        lights: b.lights,
        infinite_lights,
        sampled_lights: Vec::new(),
        accel,
        techniques: Techniques::default(),
        assets: b.assets,
        load_estimate: b.budget.peak,
    };
    scene.sampled_lights = super::sampled_lights(&scene.lights);
    scene.derive_techniques(b.budget.limits.accel);
    Ok(scene)
}

impl Builder<'_> {
    /// Loads an image within the budget: refused from its header when its texels (at
    /// [`crate::texture::TEXEL_LOAD`] bytes each while decoding) do not fit; each then keeps
    /// [`TEXEL_KEPT`] bytes, and `extra` more.
    pub(crate) fn bitmap(
        &mut self,
        path: &std::path::Path,
        raw: bool,
        extra: u64,
    ) -> Result<Arc<Bitmap>, String> {
        let kept = TEXEL_KEPT + extra;
        self.decoded(
            path,
            &format!("image raw={raw}"),
            |room| Bitmap::load_in(path, raw, room, kept).map(|(b, held)| (Arc::new(b), held)),
            |(b, held)| (*held, (b.width * b.height) as u64 * kept),
        )
        .map(|b| b.0.clone())
    }

    /// A texture's image, as [`Builder::bitmap`] loads it, but an 8-bit file of more than
    /// [`crate::texture::KEEP_BYTES_ABOVE`] texels keeps its bytes (3 a texel, not 12), and
    /// takes a fraction of [`crate::texture::TEXEL_LOAD`] to read (`Image::load_in`).
    fn image(&mut self, path: &std::path::Path, raw: bool) -> Result<Arc<(Image, u64)>, String> {
        let read = |room| Image::load_in(path, raw, room);
        let what = format!("texture raw={raw}");
        self.decoded(path, &what, read, |(i, held)| {
            (*held, (i.width() * i.height()) as u64 * i.texel_bytes())
        })
    }

    /// What `read` (given the bytes left for it besides the file) decodes from the image at
    /// `path`, charged to the budget as `size` says: the bytes its reading held besides the
    /// file, and the bytes it keeps.
    fn decoded<T: Send + Sync + 'static>(
        &mut self,
        path: &std::path::Path,
        what: &str,
        read: impl FnOnce(u64) -> Result<T, crate::texture::BitmapError>,
        size: impl Fn(&T) -> (u64, u64),
    ) -> Result<Arc<T>, String> {
        self.budget.in_time()?;
        let file = file_size(path);
        // The file is read whole: refused before it is, if it alone does not fit.
        self.budget.charge("an image file", file, 0)?;
        let room = self.budget.room().saturating_sub(file);
        let image = self.cached(path, what, || read(room)).map_err(|e| match e {
            crate::texture::BitmapError::TooLarge { width, height, limit } if limit < MAX_TEXELS => format!(
                "a {width} x {height} image does not fit in what is left of the {:.1} MiB a scene may take to load (--max-scene-memory-mb)",
                self.budget.limits.max_bytes as f64 / (1u64 << 20) as f64
            ),
            e => e.to_string(),
        })?;
        let (held, kept) = size(&image);
        self.budget.charge("an image", file.saturating_add(held), kept)?;
        Ok(image)
    }

    pub(crate) fn err(&self, pos: Pos, msg: impl Into<String>) -> SceneError {
        self.doc.err(pos, msg)
    }

    /// A texture's image, read once however many textures use it (by path and `raw`).
    pub(crate) fn shared_image(&mut self, path: &std::path::Path, raw: bool) -> Result<Image, String> {
        let key = (path.to_path_buf(), raw);
        if let Some(b) = self.bitmaps.get(&key) {
            return Ok(b.clone());
        }
        let b = self.image(path, raw)?.0.clone();
        self.assets.push(path.to_path_buf());
        self.bitmaps.insert(key, b.clone());
        Ok(b)
    }

    /// What `load` makes of the file at `path`, from the load's asset cache when it has one
    /// (see `assets`); `what` names the parser and its settings.
    pub(crate) fn cached<T: Send + Sync + 'static, E>(
        &self,
        path: &std::path::Path,
        what: &str,
        load: impl FnOnce() -> Result<T, E>,
    ) -> Result<Arc<T>, E> {
        match &self.budget.limits.assets {
            Some(cache) => cache.get(path, what, load),
            None => load().map(Arc::new),
        }
    }

    /// How object `i`'s plugin is built, from the table; a plugin the table does not list is
    /// refused, naming those its element may be.
    fn make(&self, i: usize) -> R<Make> {
        let o = self.doc.obj(i);
        plugins::find(&o.tag, &o.plugin).map(|p| p.make).ok_or_else(|| {
            self.err(
                o.pos,
                format!(
                    "unsupported {} plugin '{}' (supported: {})",
                    o.tag,
                    o.plugin,
                    plugins::supported(&o.tag).join(", ")
                ),
            )
        })
    }

    /// An error for a table entry built the wrong way (a bug in the table, which a test
    /// rules out).
    fn miswired(&self, i: usize) -> SceneError {
        let o = self.doc.obj(i);
        self.err(o.pos, format!("internal: plugin '{}' is listed under the wrong element", o.plugin))
    }

    pub(crate) fn make_filter(&mut self, i: usize) -> R<Filter> {
        match self.make(i)? {
            Make::Filter(f) => f(self, i),
            _ => Err(self.miswired(i)),
        }
    }

    pub(crate) fn positive_int(&self, i: usize, name: &str, default: i64) -> R<u32> {
        let v = self.doc.int_or(i, name, default)?;
        if v <= 0 || v > u32::MAX as i64 {
            return Err(self.err(
                self.doc.pos_of(i, name),
                format!("'{name}' of {} must be a positive integer, found {v}", self.doc.describe(i)),
            ));
        }
        Ok(v as u32)
    }

    pub(crate) fn nonneg_float(&self, i: usize, name: &str, default: f32) -> R<f32> {
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
        let Make::Sensor(camera) = self.make(i)? else { return Err(self.miswired(i)) };
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
            [(_, f, _)] => match self.make(*f)? {
                Make::Film(film) => film(self, *f)?,
                _ => return Err(self.miswired(*f)),
            },
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "more than one <film> in the sensor")),
        };
        let (spp, seed, sampler_type) = match doc.children(i, "sampler").as_slice() {
            [] => (4, 0, "independent".to_string()),
            [(_, s, _)] => match self.make(*s)? {
                Make::Sampler(sampler) => {
                    let (spp, seed) = sampler(self, *s)?;
                    (spp, seed, doc.obj(*s).plugin.clone())
                }
                _ => return Err(self.miswired(*s)),
            },
            [_, (_, _, pos), ..] => return Err(self.err(*pos, "more than one <sampler> in the sensor")),
        };
        let camera = camera(self, i, &film)?;
        Ok((camera, film, spp, seed, sampler_type))
    }

    fn integrator(&mut self, i: usize) -> R<PathSettings> {
        match self.make(i)? {
            Make::Integrator(f) => f(self, i),
            _ => Err(self.miswired(i)),
        }
    }

    /// A colour parameter: `<rgb>`/`<float>`, or a nested/referenced `<texture>`.
    pub(crate) fn color(&mut self, i: usize, name: &str, default: Rgb) -> R<Texture> {
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
        let tex = match self.make(i)? {
            Make::Texture(f) => f(self, i)?,
            _ => return Err(self.miswired(i)),
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
    pub(crate) fn side(&mut self, i: usize) -> R<Box<Bsdf>> {
        Ok(Box::new(match self.bsdf_value(i)? {
            Bsdf::TwoSided { front, .. } => *front,
            b => b,
        }))
    }

    fn bsdf_made(&mut self, i: usize) -> R<Bsdf> {
        match self.make(i)? {
            Make::Bsdf(f) => f(self, i),
            _ => Err(self.miswired(i)),
        }
    }

    /// The rough interfaces (roughdielectric, roughplastic) need a real interface: with equal
    /// indices of refraction their microfacet terms divide by zero (Mitsuba refuses them too).
    pub(crate) fn distinct_iors(&self, i: usize, int_ior: f32, ext_ior: f32) -> R<()> {
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
    pub(crate) fn choice<T: Copy>(&self, i: usize, name: &str, default: T, choices: &[(&str, T)]) -> R<T> {
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
    pub(crate) fn const_color(&mut self, i: usize, name: &str, default: Rgb) -> R<Rgb> {
        match self.color(i, name, default)? {
            Texture::Const(c) => Ok(c),
            _ => Err(self.err(
                self.doc.pos_of(i, name),
                format!("'{name}' of {} must be a colour, not a texture", self.doc.describe(i)),
            )),
        }
    }

    /// The rotation part of `to_world`; refuses scaling and shearing.
    pub(crate) fn rotation(&mut self, i: usize) -> R<Mat3> {
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
    pub(crate) fn float_texture(&mut self, i: usize, name: &str, default: f32) -> R<Texture> {
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
    pub(crate) fn roughness(&mut self, i: usize) -> R<Option<Roughness>> {
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
    pub(crate) fn conductor_ior(&mut self, i: usize) -> R<(Rgb, Rgb)> {
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
    pub(crate) fn ior(&mut self, i: usize, name: &str, default: &str) -> R<f32> {
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
            _ => {}
        }
        let make = match self.make(i)? {
            Make::Structure(f) => return f(self, i),
            Make::Shape(f) => f,
            _ => return Err(self.miswired(i)),
        };
        let to_world = doc.transform(i, "to_world")?.unwrap_or(Mat4::IDENTITY);
        let flip_normals = doc.boolean_or(i, "flip_normals", false)?;
        let geometry = make(self, i, &to_world)?;
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
                let Make::Area(radiance) = self.make(*e)? else {
                    return Err(self.err(
                        doc.obj(*e).pos,
                        format!(
                            "emitter '{}' cannot be attached to a shape (only 'area')",
                            doc.obj(*e).plugin
                        ),
                    ));
                };
                let radiance = radiance(self, *e)?;
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
        let light = match self.make(i)? {
            Make::Emitter(f) => f(self, i, pos)?,
            Make::Area(_) => return Err(self.err(pos, "an 'area' emitter must be nested inside a <shape>")),
            _ => return Err(self.miswired(i)),
        };
        self.lights.push(light);
        Ok(())
    }
}

/// `shapegroup` (see `plugins`): built once, drawn only through instances.
pub(crate) fn shape_group_from(b: &mut Builder, i: usize) -> R<()> {
    b.shape_group(i).map(|_| ())
}

/// `instance` (see `plugins`): a shapegroup placed by `to_world`.
pub(crate) fn instance_from(b: &mut Builder, i: usize) -> R<()> {
    b.instance(i)
}

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
