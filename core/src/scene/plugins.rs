//! Every plugin the loader knows, in one table: its XML tag and name, what it reads (for
//! `docs/SCENES.md`) and the constructor that builds it from its parameters, which lives beside
//! its model (`bsdf::plastic::from_scene`, `geometry::mesh::file_from`, ...). The loader
//! dispatches through [`PLUGINS`]; the "supported" lists of its errors and the plugin table of
//! `docs/SCENES.md` ([`markdown`], printed by `furnace plugins`) are generated from it.

use glam::Mat4;

use super::build::{Builder, R};
use super::xml::Pos;
use super::FilmSettings;
use crate::bsdf::Bsdf;
use crate::camera::Camera;
use crate::film::Filter;
use crate::geometry::Geometry;
use crate::light::Light;
use crate::texture::Texture;

/// How a plugin is built: one kind of constructor per XML tag.
#[derive(Clone, Copy)]
pub(crate) enum Make {
    /// A sensor, for its film.
    Sensor(fn(&mut Builder, usize, &FilmSettings) -> R<Camera>),
    Film(fn(&mut Builder, usize) -> R<FilmSettings>),
    Filter(fn(&mut Builder, usize) -> R<Filter>),
    /// Samples per pixel and seed.
    Sampler(fn(&mut Builder, usize) -> R<(u32, u64)>),
    Integrator(fn(&mut Builder, usize) -> R<super::PathSettings>),
    Bsdf(fn(&mut Builder, usize) -> R<Bsdf>),
    Texture(fn(&mut Builder, usize) -> R<Texture>),
    /// A shape's geometry, placed by its `to_world`.
    Shape(fn(&mut Builder, usize, &Mat4) -> R<Geometry>),
    /// A shape that structures the scene (`shapegroup`, `instance`): it adds itself.
    Structure(fn(&mut Builder, usize) -> R<()>),
    Emitter(fn(&mut Builder, usize, Pos) -> R<Light>),
    /// An emitter made with the shape it is nested in: its radiance.
    Area(fn(&mut Builder, usize) -> R<Texture>),
}

/// One plugin.
pub struct Plugin {
    /// Its XML element: `sensor`, `film`, `rfilter`, `sampler`, `integrator`, `bsdf`,
    /// `texture`, `shape` or `emitter`.
    pub tag: &'static str,
    /// Its `type`.
    pub name: &'static str,
    /// What it reads, with defaults, and where Furnace goes beyond Mitsuba 3.
    pub reads: &'static str,
    pub(crate) make: Make,
}

const fn p(tag: &'static str, name: &'static str, reads: &'static str, make: Make) -> Plugin {
    Plugin { tag, name, reads, make }
}

/// Every plugin, by tag in the order a scene is described, then by name.
pub static PLUGINS: &[Plugin] = &[
    p("integrator", "path", "`max_depth` (-1 = unlimited), `rr_depth` (5), `hide_emitters` (false). Default when absent.", Make::Integrator(crate::integrator::path::from_scene)),
    p("sensor", "perspective", "`fov` (degrees, required), `fov_axis` (`x` default, `y`, `diagonal`, `smaller`, `larger`), `near_clip` (0.01), `far_clip` (10000), `to_world` (no scaling). One sensor per scene.", Make::Sensor(crate::camera::from_scene)),
    p("sensor", "thinlens", "as `perspective`, and `aperture_radius` (required; 0 renders as a pinhole), `focus_distance` (default `far_clip`, as Mitsuba's code does).", Make::Sensor(crate::camera::from_scene)),
    p("film", "hdrfilm", "`width` (768), `height` (576), `crop_offset_x/y`, `crop_width/height`, `pixel_format` (`rgb`), `component_format` (`float16`/`float32`; Furnace writes float32).", Make::Film(crate::film::hdrfilm_from)),
    p("rfilter", "box", "`radius` (0.5).", Make::Filter(crate::film::box_from)),
    p("rfilter", "gaussian", "`stddev` (0.5; radius 4 stddev). Default when absent, as in Mitsuba.", Make::Filter(crate::film::gaussian_from)),
    p("sampler", "independent", "`sample_count` (4), `seed` (0). Every sampler renders with Furnace's Owen-scrambled Sobol sequence.", Make::Sampler(crate::sampler::from_scene)),
    p("sampler", "stratified", "as `independent`.", Make::Sampler(crate::sampler::from_scene)),
    p("sampler", "multijitter", "as `independent`.", Make::Sampler(crate::sampler::from_scene)),
    p("sampler", "orthogonal", "as `independent`.", Make::Sampler(crate::sampler::from_scene)),
    p("sampler", "ldsampler", "as `independent`.", Make::Sampler(crate::sampler::from_scene)),
    p("shape", "obj", "`filename`, `face_normals`, `flip_tex_coords` (true). Every shape but curves takes `to_world`, `flip_normals`, one `bsdf` and one `area` emitter.", Make::Shape(crate::geometry::mesh::file_from)),
    p("shape", "ply", "`filename`, `face_normals`.", Make::Shape(crate::geometry::mesh::file_from)),
    p("shape", "rectangle", "[-1, 1]^2 in the xy-plane, facing +z.", Make::Shape(crate::geometry::mesh::builtin_from)),
    p("shape", "cube", "[-1, 1]^3, Mitsuba's vertex order and uv.", Make::Shape(crate::geometry::mesh::builtin_from)),
    p("shape", "sphere", "`center`, `radius`; `to_world` must scale uniformly.", Make::Shape(crate::geometry::shapes::sphere_from)),
    p("shape", "disk", "the unit disk in the xy-plane, facing +z.", Make::Shape(crate::geometry::shapes::disk_from)),
    p("shape", "linearcurve", "`filename`: `x y z radius` per line, a blank line between curves; `to_world` moves points, not radii. A `bsdf`, no emitter.", Make::Shape(crate::geometry::curves::from_scene)),
    p("shape", "bsplinecurve", "as `linearcurve`, a uniform cubic B-spline through at least 4 points a curve.", Make::Shape(crate::geometry::curves::from_scene)),
    p("shape", "shapegroup", "an `id` and shapes of the kinds above, without emitters, drawn only through instances; no `to_world`. Its shapes and BVH exist once however many instances place it.", Make::Structure(super::build::shape_group_from)),
    p("shape", "instance", "one `<ref>` to a shapegroup (or, beyond Mitsuba, the shapegroup written inside it) and `to_world`, which may shrink the group at most 1e9 times along any direction; no `bsdf`, emitter or `flip_normals`.", Make::Structure(super::build::instance_from)),
    p("bsdf", "diffuse", "`reflectance` (0.5).", Make::Bsdf(crate::bsdf::diffuse_from)),
    p("bsdf", "twosided", "one nested BSDF for both sides, or two (front, back).", Make::Bsdf(crate::bsdf::twosided_from)),
    p("bsdf", "conductor", "`material` preset (default `none`, a perfect mirror) or `eta` + `k`; `specular_reflectance`.", Make::Bsdf(crate::bsdf::conductor::from_scene)),
    p("bsdf", "roughconductor", "as `conductor`, and the roughness: `distribution` (`beckmann` default, `ggx`), `alpha` (0.1) or `alpha_u` + `alpha_v` (each a number or a texture); `sample_visible` must stay true.", Make::Bsdf(crate::bsdf::conductor::from_scene)),
    p("bsdf", "dielectric", "`int_ior` (`bk7`), `ext_ior` (`air`), numbers or names; `specular_reflectance`, `specular_transmittance`.", Make::Bsdf(crate::bsdf::dielectric::from_scene)),
    p("bsdf", "roughdielectric", "as `dielectric` with the roughness of `roughconductor`; the two indices must differ.", Make::Bsdf(crate::bsdf::dielectric::from_scene)),
    p("bsdf", "thindielectric", "as `dielectric`.", Make::Bsdf(crate::bsdf::dielectric::from_scene)),
    p("bsdf", "plastic", "`diffuse_reflectance` (0.5), `specular_reflectance`, `int_ior` (`polypropylene`), `ext_ior`, `nonlinear`.", Make::Bsdf(crate::bsdf::plastic::from_scene)),
    p("bsdf", "roughplastic", "as `plastic` with `distribution` and one constant `alpha` (its tables are built for one roughness; no `alpha_u`/`alpha_v`); the two indices must differ.", Make::Bsdf(crate::bsdf::plastic::from_scene)),
    p("bsdf", "hair", "`eumelanin` (1.3) and `pheomelanin` (0.2), or `sigma_a` with `scale`, or Furnace's own `reflectance`; `int_ior` (`amber`), `ext_ior`, `longitudinal_roughness` (0.3), `azimuthal_roughness` (0.3), `scale_tilt` (2 degrees).", Make::Bsdf(crate::bsdf::hair::from_scene)),
    p("texture", "bitmap", "`filename` (PNG, JPEG, HDR, EXR), `filter_type` (`bilinear` default, `nearest`; Furnace's own `trilinear` and `ewa`), `wrap_mode` (`repeat`, `mirror`, `clamp`), `raw`, `to_uv`. Any colour or float parameter of a BSDF or an area emitter takes a texture, except the roughness of `roughplastic` and conductor `eta`/`k`.", Make::Texture(crate::texture::bitmap::from_scene)),
    p("texture", "checkerboard", "`color0` (0.4), `color1` (0.2), `to_uv`.", Make::Texture(crate::texture::checkerboard_from)),
    p("emitter", "point", "`intensity`, `position` or `to_world`.", Make::Emitter(crate::light::point_from)),
    p("emitter", "spot", "`intensity`, `cutoff_angle` (20), `beam_width` (3/4 of the cutoff), `to_world`.", Make::Emitter(crate::light::spot_from)),
    p("emitter", "directional", "`irradiance`, `direction` or `to_world`.", Make::Emitter(crate::light::directional_from)),
    p("emitter", "constant", "`radiance`. Light sampling leaves it to BSDF sampling (MIS compensation, Furnace's own: always on; `furnace report` measures it off).", Make::Emitter(crate::light::constant_from)),
    p("emitter", "envmap", "`filename` (EXR, HDR, PNG), `scale`, `to_world` (a rotation), `mis_compensation` (Furnace's default: true), Furnace's own `filter_type` (`bilinear`, `nearest`).", Make::Emitter(crate::light::envmap::from_scene)),
    p("emitter", "area", "inside a shape (not curves): `radiance`, a colour or a texture.", Make::Area(crate::light::area_radiance_from)),
];

/// The plugin a `<tag type="name">` names.
pub fn find(tag: &str, name: &str) -> Option<&'static Plugin> {
    PLUGINS.iter().find(|p| p.tag == tag && p.name == name)
}

/// The plugins of a tag, in the table's order.
pub fn supported(tag: &str) -> Vec<&'static str> {
    PLUGINS.iter().filter(|p| p.tag == tag).map(|p| p.name).collect()
}

/// The table of `docs/SCENES.md`: a row per plugin.
pub fn markdown() -> String {
    let mut s = String::from("| element | type | reads |\n|---|---|---|\n");
    for p in PLUGINS {
        s.push_str(&format!("| {} | `{}` | {} |\n", p.tag, p.name, p.reads));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each tag's plugins are built one way, and no plugin is listed twice.
    #[test]
    fn each_tag_has_one_kind_of_constructor_and_each_plugin_one_row() {
        let kind = |m: &Make| match m {
            Make::Sensor(_) => "sensor",
            Make::Film(_) => "film",
            Make::Filter(_) => "rfilter",
            Make::Sampler(_) => "sampler",
            Make::Integrator(_) => "integrator",
            Make::Bsdf(_) => "bsdf",
            Make::Texture(_) => "texture",
            Make::Shape(_) | Make::Structure(_) => "shape",
            Make::Emitter(_) | Make::Area(_) => "emitter",
        };
        for (k, p) in PLUGINS.iter().enumerate() {
            assert_eq!(kind(&p.make), p.tag, "{}", p.name);
            assert!(!PLUGINS[..k].iter().any(|q| q.tag == p.tag && q.name == p.name), "{} twice", p.name);
        }
        assert!(supported("shape").contains(&"bsplinecurve") && supported("shape").contains(&"linearcurve"));
    }

    /// docs/SCENES.md holds the table as generated (`furnace plugins`); to update it, paste
    /// that between the markers.
    #[test]
    fn the_scene_docs_list_every_plugin_as_the_table_does() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/SCENES.md");
        let doc = std::fs::read_to_string(&path).unwrap();
        let start = "<!-- plugins: generated by `furnace plugins` -->\n";
        let a = doc.find(start).expect("start marker") + start.len();
        let b = doc.find("<!-- plugins: end -->").expect("end marker");
        assert!(doc[a..b] == markdown(), "docs/SCENES.md's plugin table differs from `furnace plugins`");
    }
}
