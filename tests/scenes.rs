//! Scene loading: Mitsuba XML features, defaults and substitution, and the errors bad scenes get.

mod common;

use common::*;
use furnace_core::geometry::Geometry;
use furnace_core::math::Vec3;
use furnace_core::SceneError;

fn scene_with(body: &str) -> String {
    format!(
        r#"<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    </sensor>
{body}
</scene>"#
    )
}

/// Loads `body` inside a minimal scene and returns the error, checking that it names the file
/// and a line and column.
fn error_of(body: &str) -> SceneError {
    let e = match load_str(&scene_with(body)) {
        Ok(_) => panic!("scene loaded, but should fail:\n{body}"),
        Err(e) => e,
    };
    let text = e.to_string();
    assert!(text.starts_with(&scenes().join("inline.xml").display().to_string()), "{text}");
    assert!(e.line > 0 && e.col > 0, "no position in: {text}");
    e
}

#[test]
fn unknown_plugin_is_named_with_its_position() {
    let e = error_of(r#"    <shape type="rectangle"><bsdf type="velvet"/></shape>"#);
    assert_eq!(e.line, 6);
    assert!(e.message.contains("unsupported bsdf plugin 'velvet'"), "{e}");
    let e = error_of(r#"    <emitter type="sunsky"/>"#);
    assert!(e.message.contains("unsupported emitter plugin 'sunsky'"), "{e}");
}

#[test]
fn unsupported_parameter_is_never_ignored() {
    let e = error_of(
        r#"    <shape type="sphere">
        <bsdf type="diffuse"><float name="roughness" value="0.3"/></bsdf>
    </shape>"#,
    );
    assert_eq!((e.line, e.col), (7, 30));
    assert!(e.message.contains("unsupported parameter 'roughness'") && e.message.contains("diffuse"), "{e}");
    let e = error_of(r#"    <medium type="homogeneous"/>"#);
    assert!(e.message.contains("unsupported element <medium>"), "{e}");
}

#[test]
fn missing_file_is_reported() {
    let e = error_of(r#"    <shape type="obj"><string name="filename" value="assets/nope.obj"/></shape>"#);
    assert!(e.message.contains("cannot open file") && e.message.contains("nope.obj"), "{e}");
    let e = error_of(
        r#"    <shape type="sphere"><bsdf type="diffuse">
        <texture type="bitmap" name="reflectance"><string name="filename" value="assets/missing.png"/></texture>
    </bsdf></shape>"#,
    );
    assert!(e.message.contains("missing.png"), "{e}");
}

#[test]
fn paths_leaving_the_scene_folder_are_refused() {
    // tests/scenes/../scenes/... resolves inside the folder: allowed.
    load_str(&scene_with(
        r#"    <shape type="obj"><string name="filename" value="../scenes/assets/quad.obj"/></shape>"#,
    ))
    .unwrap();
    let e = error_of(r#"    <shape type="obj"><string name="filename" value="../render.rs"/></shape>"#);
    assert!(e.message.contains("outside the scene's folder"), "{e}");
}

#[test]
fn malformed_xml_is_reported_with_its_position() {
    let e = load_str("<scene version=\"3.0.0\">\n  <shape type=\"sphere\">\n</scene>").unwrap_err();
    assert!(e.message.contains("malformed XML"), "{e}");
    assert_eq!(e.line, 3);
    let e = load_str("<scene><sensor type=\"perspective\"/></scene>").unwrap_err();
    assert!(e.message.contains("version"), "{e}");
}

#[test]
fn bad_values_are_reported() {
    let e = load_str(
        r#"<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="40"/>
        <film type="hdrfilm"><integer name="width" value="-5"/></film></sensor></scene>"#,
    )
    .unwrap_err();
    assert!(
        e.message.contains("'width'") && e.message.contains("positive") && e.message.contains("-5"),
        "{e}"
    );
    assert_eq!(e.line, 2);
    let e = error_of(r#"    <shape type="sphere"><float name="radius" value="abc"/></shape>"#);
    assert!(e.message.contains("expected a number"), "{e}");
    let e = error_of(
        r#"    <shape type="sphere"><integer name="radius" value="1"/><float name="radius" value="2"/></shape>"#,
    );
    assert!(e.message.contains("given twice"), "{e}");
    let e = error_of(r#"    <shape type="sphere"><string name="radius" value="big"/></shape>"#);
    assert!(e.message.contains("must be a float"), "{e}");
}

#[test]
fn undefined_parameter_is_reported() {
    let e = error_of(r#"    <shape type="sphere"><float name="radius" value="$size"/></shape>"#);
    assert!(e.message.contains("'$size' is not defined"), "{e}");
}

#[test]
fn ref_to_unknown_id_is_reported() {
    let e = error_of(r#"    <shape type="sphere"><ref id="gold"/></shape>"#);
    assert!(e.message.contains("gold"), "{e}");
}

#[test]
fn defaults_and_command_line_defines() {
    let s = load("small.xml", &[]);
    assert_eq!((s.film.width, s.spp), (48, 16));
    let s = load("small.xml", &[("width", "20"), ("spp", "3")]);
    assert_eq!((s.film.width, s.spp), (20, 3));
}

#[test]
fn transforms_apply_in_document_order() {
    // translate, then scale: the centre moves to x = 1, then scales to x = 2.
    let s = load_str(&scene_with(
        r#"    <shape type="sphere"><transform name="to_world"><translate x="1"/><scale value="2"/></transform></shape>
    <shape type="sphere"><transform name="to_world"><matrix value="1 0 0 5  0 1 0 6  0 0 1 7  0 0 0 1"/></transform></shape>
    <shape type="sphere"><transform name="to_world"><rotate y="1" angle="90"/><translate x="3"/></transform>
        <point name="center" x="0" y="0" z="1"/></shape>"#,
    ))
    .unwrap();
    let centre = |i: usize| match &s.shapes[i].geometry {
        Geometry::Sphere(sp) => (sp.center, sp.radius),
        _ => unreachable!(),
    };
    assert!((centre(0).0 - Vec3::new(2.0, 0.0, 0.0)).length() < 1e-5 && (centre(0).1 - 2.0).abs() < 1e-5);
    assert!((centre(1).0 - Vec3::new(5.0, 6.0, 7.0)).length() < 1e-5);
    // centre (0,0,1) rotated 90 degrees about y -> (1,0,0), then translated -> (4,0,0).
    assert!((centre(2).0 - Vec3::new(4.0, 0.0, 0.0)).length() < 1e-5, "{:?}", centre(2));
}

#[test]
fn meshes_load_from_obj_and_ply() {
    let s = load("small.xml", &[]);
    let meshes: Vec<_> = s
        .shapes
        .iter()
        .filter_map(|sh| match &sh.geometry {
            Geometry::Mesh(m) => Some(m),
            _ => None,
        })
        .collect();
    // OBJ quad, PLY quad, cube.
    assert_eq!(meshes.iter().map(|m| m.tris.len()).collect::<Vec<_>>(), vec![2, 2, 12]);
    // OBJ texture v is flipped (flip_tex_coords defaults to true): vt 0 0 -> uv (0, 1).
    assert_eq!(meshes[0].uvs[0], furnace_core::math::Vec2::new(0.0, 1.0));
    assert_eq!(s.assets.len(), 3, "{:?}", s.assets);
}

#[test]
fn shapes_with_emitters_default_to_black() {
    let s = load("small.xml", &[]);
    let light = s.shapes.iter().find(|sh| sh.light.is_some()).unwrap();
    assert!(s.bsdfs[light.bsdf as usize].is_black());
}

#[test]
fn lookat_without_up_follows_mitsuba() {
    // Mitsuba takes the first tangent of the Duff et al. basis around the view direction.
    let s = load_str(
        r#"<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 3, 4" target="0, 0, 0"/></transform></sensor></scene>"#,
    )
    .unwrap();
    let dir = Vec3::new(0.0, -3.0, -4.0).normalize();
    let up = furnace_core::math::Frame::from_normal(dir).s;
    let m = s.camera.to_world;
    assert!((m.z_axis.truncate() - dir).length() < 1e-6);
    assert!((m.x_axis.truncate() - up.cross(dir).normalize()).length() < 1e-6);
}

#[test]
fn hair_parameters_follow_mitsuba() {
    let e = error_of(
        r#"    <shape type="sphere"><bsdf type="hair"><rgb name="sigma_a" value="1"/><float name="eumelanin" value="1"/></bsdf></shape>"#,
    );
    assert!(e.message.contains("one of sigma_a"), "{e}");
    let e = error_of(
        r#"    <shape type="sphere"><bsdf type="hair"><float name="beta_m" value="0.3"/></bsdf></shape>"#,
    );
    assert!(e.message.contains("unsupported parameter 'beta_m'"), "{e}");
    load_str(&scene_with(r#"    <shape type="sphere"><bsdf type="hair"><rgb name="reflectance" value="0.6, 0.4, 0.2"/></bsdf></shape>"#)).unwrap();
}

/// Every shipped example loads, with its assets inside `examples/` (a fresh clone renders
/// them all).
#[test]
fn every_shipped_example_loads() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap().flatten() {
        let path = e.path();
        if path.extension().is_some_and(|x| x == "xml") {
            let scene = furnace_core::Scene::load(&path, &[]).unwrap_or_else(|e| panic!("{e}"));
            for a in &scene.assets {
                assert!(
                    a.canonicalize().unwrap().starts_with(dir.canonicalize().unwrap()),
                    "{}",
                    a.display()
                );
            }
            n += 1;
        }
    }
    assert!(n >= 4, "{n} examples");
}

/// Issue 18: frames loaded one after another with one asset cache parse each file they share
/// once (frames.xml: its mesh and its texture), and render the same bits as frames loaded
/// alone. A curve file too (hair.xml, loaded twice).
#[test]
fn frames_loaded_with_an_asset_cache_parse_shared_files_once() {
    use furnace_core::scene::assets::AssetCache;
    use furnace_core::{LoadLimits, Scene};
    use std::sync::Arc;
    let cache = Arc::new(AssetCache::new());
    let limits = LoadLimits { assets: Some(cache.clone()), ..Default::default() };
    for (k, frame) in ["0", "7", "13"].into_iter().enumerate() {
        let defs = [("frame".to_string(), frame.to_string())];
        let cached = Scene::load_with(&scenes().join("frames.xml"), &defs, &limits).unwrap();
        // The first frame parses the mesh and the image; the others find both.
        assert_eq!(cache.counts(), (2 * k as u64, 2));
        let alone = load("frames.xml", &[("frame", frame)]);
        assert!(render(&cached, 2, 1).0 == render(&alone, 2, 1).0, "frame {frame}");
    }
    let cache = Arc::new(AssetCache::new());
    let limits = LoadLimits { assets: Some(cache.clone()), ..Default::default() };
    let a = Scene::load_with(&scenes().join("hair.xml"), &[], &limits).unwrap();
    let misses = cache.counts().1;
    let b = Scene::load_with(&scenes().join("hair.xml"), &[], &limits).unwrap();
    assert_eq!(cache.counts(), (misses, misses), "the second load parsed a file again");
    assert!(render(&a, 1, 0).0 == render(&b, 1, 0).0);
}
