//! Issue 14: a scene's load has a memory budget (`LoadLimits`, `--max-scene-memory-mb`),
//! estimated before each part is read. These tests hold the estimate to what the load really
//! allocates (counted by this binary's allocator) for every kind of part, and hold a load to
//! its budget and its deadline.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};

use furnace_core::{LoadLimits, PlanDescription, Scene, Techniques};

/// Counts the bytes allocated now and the most at once since the last reset.
struct Counting;
static NOW: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grew(by: usize) {
    PEAK.fetch_max(NOW.fetch_add(by, Relaxed) + by, Relaxed);
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        grew(l.size());
        unsafe { System.alloc(l) }
    }
    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        grew(l.size());
        unsafe { System.alloc_zeroed(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        NOW.fetch_sub(l.size(), Relaxed);
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        if new > l.size() {
            grew(new - l.size());
        } else {
            NOW.fetch_sub(l.size() - new, Relaxed);
        }
        unsafe { System.realloc(p, l, new) }
    }
}

#[global_allocator]
static COUNTING: Counting = Counting;

/// Held by each test: the counts are the whole process's, so one test's allocations must not
/// land in another's peak.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn alone() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

const HEAD: &str = r#"<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="40"/>
<film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>"#;

/// Writes the scene `body` (and its files, made by `files`) into its own folder.
fn scene(dir: &Path, name: &str, body: &str, files: impl FnOnce(&Path)) -> PathBuf {
    let d = dir.join(name);
    std::fs::create_dir_all(&d).unwrap();
    files(&d);
    let path = d.join("scene.xml");
    std::fs::write(&path, format!("{HEAD}{body}</scene>")).unwrap();
    path
}

/// An n x n grid of vertices, two triangles a cell.
fn grid(n: u32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let v = (0..n * n).map(|k| [(k % n) as f32 / n as f32, (k / n) as f32 / n as f32, 0.0]).collect();
    let mut t = Vec::new();
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = j * n + i;
            t.push([a, a + 1, a + n]);
            t.push([a + 1, a + n + 1, a + n]);
        }
    }
    (v, t)
}

fn ply(path: &Path, binary: bool, n: u32) {
    let (v, t) = grid(n);
    let format = if binary { "binary_little_endian" } else { "ascii" };
    let mut out = format!(
        "ply\nformat {format} 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        v.len(),
        t.len()
    )
    .into_bytes();
    for p in &v {
        if binary {
            p.iter().for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
        } else {
            out.extend_from_slice(format!("{} {} {}\n", p[0], p[1], p[2]).as_bytes());
        }
    }
    for f in &t {
        if binary {
            out.push(3);
            f.iter().for_each(|i| out.extend_from_slice(&(*i as i32).to_le_bytes()));
        } else {
            out.extend_from_slice(format!("3 {} {} {}\n", f[0], f[1], f[2]).as_bytes());
        }
    }
    std::fs::write(path, out).unwrap();
}

fn obj(path: &Path, n: u32) {
    let (v, t) = grid(n);
    let mut out = String::new();
    v.iter().for_each(|p| out.push_str(&format!("v {} {} {}\n", p[0], p[1], p[2])));
    t.iter().for_each(|f| out.push_str(&format!("f {} {} {}\n", f[0] + 1, f[1] + 1, f[2] + 1)));
    std::fs::write(path, out).unwrap();
}

fn curves(path: &Path, count: u32) {
    let mut out = String::new();
    for c in 0..count {
        for p in 0..10 {
            out.push_str(&format!(
                "{} {} {} 0.001\n",
                (c % 100) as f32 * 0.01,
                (c / 100) as f32 * 0.01,
                p as f32 * 0.01
            ));
        }
        out.push('\n');
    }
    std::fs::write(path, out).unwrap();
}

fn exr(path: &Path, w: u32, h: u32) {
    let data = (0..w * h).map(|k| glam::Vec3::new((k % 7) as f32, 0.5, (k % 3) as f32)).collect();
    furnace_core::Image { width: w, height: h, data }.write_exr(path).unwrap();
}

/// Every kind of part a scene loads, each in a scene of its own.
fn scenes(dir: &Path) -> Vec<(&'static str, PathBuf)> {
    let shape = |plugin: &str, file: &str| {
        format!(r#"<shape type="{plugin}"><string name="filename" value="{file}"/></shape>"#)
    };
    let texture = |filter: &str| {
        format!(
            r#"<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">
            <string name="filename" value="t.exr"/><string name="filter_type" value="{filter}"/></texture></bsdf></shape>"#
        )
    };
    let spheres: String = (0..3000)
        .map(|k| {
            format!(
                r#"<shape type="sphere"><point name="center" x="{}" y="{}" z="0"/><float name="radius" value="0.3"/>
                <bsdf type="diffuse"><rgb name="reflectance" value="0.5, 0.2, 0.1"/></bsdf></shape>"#,
                k % 60,
                k / 60
            )
        })
        .collect();
    vec![
        ("binary PLY", scene(dir, "plyb", &shape("ply", "m.ply"), |d| ply(&d.join("m.ply"), true, 200))),
        ("text PLY", scene(dir, "plya", &shape("ply", "m.ply"), |d| ply(&d.join("m.ply"), false, 200))),
        ("OBJ", scene(dir, "obj", &shape("obj", "m.obj"), |d| obj(&d.join("m.obj"), 200))),
        (
            "linear curves",
            scene(dir, "lin", &shape("linearcurve", "c.txt"), |d| curves(&d.join("c.txt"), 4000)),
        ),
        (
            "B-spline curves",
            scene(dir, "bsp", &shape("bsplinecurve", "c.txt"), |d| curves(&d.join("c.txt"), 1000)),
        ),
        ("texture", scene(dir, "tex", &texture("bilinear"), |d| exr(&d.join("t.exr"), 512, 256))),
        ("mipmapped texture", scene(dir, "mip", &texture("ewa"), |d| exr(&d.join("t.exr"), 512, 256))),
        (
            "environment map",
            scene(
                dir,
                "env",
                r#"<emitter type="envmap"><string name="filename" value="e.exr"/></emitter>"#,
                |d| exr(&d.join("e.exr"), 512, 256),
            ),
        ),
        (
            // Short maps get more rows of cells per texel row: their tables cost more a texel.
            "short environment map",
            scene(
                dir,
                "short-env",
                r#"<emitter type="envmap"><string name="filename" value="s.exr"/></emitter>"#,
                |d| exr(&d.join("s.exr"), 4096, 2),
            ),
        ),
        ("3000 spheres", scene(dir, "spheres", &spheres, |_| {})),
        ("8-bit RGB PNG kept as bytes", large_8bit(dir, "rgb8", "t.png", image::ExtendedColorType::Rgb8)),
        ("8-bit RGBA PNG kept as bytes", large_8bit(dir, "rgba8", "t.png", image::ExtendedColorType::Rgba8)),
        ("8-bit grey PNG kept as bytes", large_8bit(dir, "l8", "t.png", image::ExtendedColorType::L8)),
    ]
}

/// Texels of [`large_8bit`]'s images: past `KEEP_BYTES_ABOVE`, so kept as bytes.
const LARGE: (u32, u32) = (2049, 2048);

/// A scene of a bilinear texture on an 8-bit image of [`LARGE`] texels of type `color`, saved as
/// `file` (PNG or JPEG by its name).
fn large_8bit(dir: &Path, name: &str, file: &str, color: image::ExtendedColorType) -> PathBuf {
    scene(dir, name, &large_8bit_body(file), |d| {
        let (w, h) = LARGE;
        let bytes = color.bits_per_pixel() as u32 / 8;
        let px: Vec<u8> = (0..w * h * bytes).map(|k| (k % 251 ^ k / 7919) as u8).collect();
        image::save_buffer(d.join(file), &px, w, h, color).unwrap();
    })
}

/// A sphere with a bilinear texture on the image `file`.
fn large_8bit_body(file: &str) -> String {
    format!(
        r#"<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">
        <string name="filename" value="{file}"/><string name="filter_type" value="bilinear"/></texture></bsdf></shape>"#
    )
}

/// The estimate bounds what each load allocates at its peak, by no more than 4 times (an
/// estimate that large would refuse scenes that fit); a budget just under it refuses the scene
/// with an error naming the setting, and a budget of it loads it.
#[test]
fn a_scenes_load_estimate_bounds_what_it_allocates_and_its_budget_holds() {
    let _alone = alone();
    let dir = common::scratch("load-budget");
    for (what, path) in scenes(&dir) {
        let before = NOW.load(Relaxed);
        PEAK.store(before, Relaxed);
        let scene = Scene::load(&path, &[]).unwrap_or_else(|e| panic!("{what}: {e}"));
        let (peak, estimate) = ((PEAK.load(Relaxed) - before) as u64, scene.load_estimate);
        drop(scene);
        println!("{what}: allocated at most {peak} bytes, estimated {estimate}");
        assert!(
            peak <= estimate,
            "{what}: the load allocated {peak} bytes, more than the {estimate} estimated"
        );
        assert!(
            estimate <= 4 * peak.max(1 << 20),
            "{what}: estimated {estimate} bytes for a {peak}-byte load"
        );
        let within =
            |max_bytes| Scene::load_with(&path, &[], &LoadLimits { max_bytes, ..Default::default() });
        let e = within(estimate - 1).err().unwrap_or_else(|| panic!("{what}: loaded under its estimate"));
        assert!(e.to_string().contains("--max-scene-memory-mb"), "{what}: {e}");
        // The file, and the line of the part over the budget (the BVH is the whole scene's).
        assert_eq!(e.file, path, "{what}");
        assert!(e.line > 0 || e.message.contains("the BVH"), "{what}: the error names no line: {e}");
        assert!(within(estimate).is_ok(), "{what}");
        if what == "texture" {
            // An image file larger than the room left is refused before it is read.
            let e = within(2 << 20).err().expect("a 1.2 MiB image in under 1 MiB of room");
            assert!(e.to_string().contains("an image file needs about 1.2 MiB"), "{e}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// The bytes `load` allocates at its peak.
fn peak_of<T>(load: impl FnOnce() -> T) -> (T, u64) {
    let before = NOW.load(Relaxed);
    PEAK.store(before, Relaxed);
    let out = load();
    (out, (PEAK.load(Relaxed) - before) as u64)
}

/// A large 8-bit PNG keeps its bytes, and its load is charged what that takes: it loads in
/// half of what decoding it to f32 would take, where a 16-bit image of the same size is
/// refused with an error naming the setting. A JPEG keeps its bytes too, but is charged as if
/// decoded to f32 (what its decoder holds is not simply bounded by its header), and its
/// estimate bounds its load. A PNG's decoder may allocate for its metadata only what is
/// charged for it: a colour profile that inflates to 64 MiB is not read.
#[test]
fn a_texture_that_keeps_its_bytes_loads_in_a_fraction_of_the_memory() {
    let _alone = alone();
    let dir = common::scratch("load-budget-bytes");
    let (w, h) = LARGE;
    let half = (w * h) as u64 * furnace_core::texture::TEXEL_LOAD / 2;
    let within =
        |path: &Path| Scene::load_with(path, &[], &LoadLimits { max_bytes: half, ..Default::default() });
    for color in [image::ExtendedColorType::Rgb8, image::ExtendedColorType::Rgba8] {
        let path = large_8bit(&dir, "kept", "t.png", color);
        let scene = within(&path).unwrap_or_else(|e| panic!("{color:?}: {e}"));
        assert!(scene.describe().to_string().contains("8-bit texels"), "{color:?}: not kept as bytes");
    }
    let path = large_8bit(&dir, "wide", "t.png", image::ExtendedColorType::Rgb16);
    let e = within(&path).err().expect("a 16-bit image decoded to f32 in half of what that takes");
    assert!(e.to_string().contains("a 2049 x 2048 image does not fit"), "{e}");
    assert!(e.to_string().contains("--max-scene-memory-mb"), "{e}");

    let path = large_8bit(&dir, "jpeg", "t.jpg", image::ExtendedColorType::Rgb8);
    let (jpeg, peak) = peak_of(|| Scene::load(&path, &[]).unwrap());
    assert!(jpeg.describe().to_string().contains("8-bit texels"), "the JPEG not kept as bytes");
    assert!(jpeg.load_estimate >= peak, "JPEG: allocated {peak}, estimated {}", jpeg.load_estimate);
    assert!(jpeg.load_estimate >= (w * h) as u64 * furnace_core::texture::TEXEL_LOAD);
    let e = within(&path).err().expect("a JPEG in half of what decoding it to f32 takes");
    assert!(e.to_string().contains("--max-scene-memory-mb"), "{e}");

    let bomb = scene(&dir, "bomb", &large_8bit_body("t.png"), |d| {
        use image::ImageEncoder;
        let mut png = image::codecs::png::PngEncoder::new(std::fs::File::create(d.join("t.png")).unwrap());
        png.set_icc_profile(vec![0; 64 << 20]).unwrap();
        png.write_image(&[128; 64 * 64 * 3], 64, 64, image::ExtendedColorType::Rgb8).unwrap();
    });
    let (loaded, peak) = peak_of(|| Scene::load(&bomb, &[]));
    assert!(peak < 32 << 20, "a PNG's 64 MiB colour profile: {peak} bytes allocated");
    if let Ok(loaded) = loaded {
        assert!(loaded.load_estimate >= peak, "allocated {peak}, estimated {}", loaded.load_estimate);
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// A load past its deadline stops with an error; without its BVH a scene is the same scene,
/// planned alike, with nothing to trace, except that its light-sample cutoff (which a preview
/// render derives) is left to the loads that render it, as its plan says.
#[test]
fn a_load_keeps_to_its_deadline_and_may_skip_the_bvh() {
    let _alone = alone();
    let path = common::scenes().join("small.xml");
    let late = LoadLimits { deadline: Some(std::time::Instant::now()), ..Default::default() };
    let e = Scene::load_with(&path, &[], &late).err().expect("a load past its deadline");
    assert!(e.to_string().contains("longer to load than its time allows"), "{e}");
    let full = Scene::load(&path, &[]).unwrap();
    let bare = Scene::load_with(&path, &[], &LoadLimits { accel: false, ..Default::default() }).unwrap();
    assert_eq!(
        (bare.film.clone(), bare.spp, bare.load_estimate),
        (full.film.clone(), full.spp, full.load_estimate)
    );
    assert!(full.techniques.light_cutoff > 0.0 && !full.techniques.light_cutoff_pending);
    assert!(bare.techniques.light_cutoff == 0.0 && bare.techniques.light_cutoff_pending);
    let pending = Techniques { light_cutoff: 0.0, light_cutoff_pending: true, ..full.techniques };
    assert_eq!(bare.techniques, pending);
    let (mut bare_plan, mut full_plan) = (bare.describe(), full.describe());
    let cutoff = |p: &mut PlanDescription, what: &str| {
        let n = p.stages.len();
        p.stages.retain(|s| !s.contains(what));
        assert_eq!(p.stages.len(), n - 1, "one stage names {what}: {:?}", p.stages);
    };
    cutoff(&mut bare_plan, "light-sample cutoff: derived from a preview where the scene is rendered");
    cutoff(&mut full_plan, "Russian roulette before the shadow ray");
    assert_eq!(bare_plan, full_plan);
    assert_eq!((bare.accel.prim_count(), full.accel.prim_count() > 0), (0, true));
}
