//! Fur at scale: loading B-spline fibres and building the BVH, timed and weighed. The million-
//! fibre run is `--ignored` (about 10 s in release on 2 cores, see docs/BENCHMARKS.md); the
//! normal run checks the same memory bound on 100,000 fibres.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use common::scratch;
use furnace_core::geometry::Geometry;

/// Counts live heap bytes and their peak, so the test can weigh what a scene holds.
struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    // Zeroed and resized blocks go to the system allocator's own calls (calloc hands out
    // fresh pages untouched; the default would memset them), so the count costs no time.
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::Relaxed) + layout.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
            let now = LIVE.fetch_add(new_size, Ordering::Relaxed) + new_size;
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Writes `fibres` B-spline fibres of 4 control points (one span, so 8 segments each) growing
/// out of a unit sphere, with tapering radii, and a scene that shows them: once, or with
/// `instances` > 0 as a shapegroup placed that many times in a row along x (the first at the
/// origin).
fn write_fur(fibres: usize, tag: &str, instances: usize) -> std::path::PathBuf {
    let dir = scratch(tag);
    let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("fur.txt")).unwrap());
    let mut state = 0x853c49e6748fea9bu64;
    let mut next = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 40) as f32) / (1u64 << 24) as f32
    };
    for _ in 0..fibres {
        let z = 2.0 * next() - 1.0;
        let phi = 2.0 * std::f32::consts::PI * next();
        let r = (1.0 - z * z).max(0.0).sqrt();
        let n = [r * phi.cos(), r * phi.sin(), z];
        let bend = [next() - 0.5, next() - 0.5, next() - 0.5];
        for k in 0..4 {
            let t = k as f32 / 3.0;
            let p: Vec<f32> = (0..3).map(|i| n[i] * (1.0 + 0.3 * t) + bend[i] * 0.1 * t * t).collect();
            writeln!(f, "{} {} {} {}", p[0], p[1], p[2], 0.004 * (1.0 - 0.7 * t)).unwrap();
        }
        writeln!(f).unwrap();
    }
    f.flush().unwrap();
    let fur =
        r#"<shape type="bsplinecurve"><string name="filename" value="fur.txt"/><bsdf type="hair"/></shape>"#;
    let shapes = if instances == 0 {
        fur.to_string()
    } else {
        let mut s = format!(r#"<shape type="shapegroup" id="fur">{fur}</shape>"#);
        for k in 0..instances {
            s += &format!(
                r#"<shape type="instance"><ref id="fur"/><transform name="to_world"><rotate y="1" angle="{}"/><translate x="{}"/></transform></shape>"#,
                k * 37,
                3 * k
            );
        }
        s
    };
    std::fs::write(
        dir.join("fur.xml"),
        format!(
            r#"<scene version="3.0.0">
            <sensor type="perspective"><float name="fov" value="40"/><transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
                <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="64"/></film></sensor>
            <emitter type="constant"/>
            {shapes}
        </scene>"#
        ),
    )
    .unwrap();
    dir
}

/// Loads the fur scene; returns (segments, seconds, bytes held per segment, peak bytes per
/// segment), heap bytes counted from before the load.
fn load_fur(fibres: usize, tag: &str) -> (usize, f64, f64, f64) {
    load_fur_instanced(fibres, tag, 0)
}

/// [`load_fur`] with the fur placed by `instances` instances (0: placed as it is).
fn load_fur_instanced(fibres: usize, tag: &str, instances: usize) -> (usize, f64, f64, f64) {
    // One weighing at a time: the heap counters are process-wide.
    static ONE: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one = ONE.lock().unwrap_or_else(|e| e.into_inner());
    let dir = write_fur(fibres, tag, instances);
    let before = LIVE.load(Ordering::Relaxed);
    PEAK.store(before, Ordering::Relaxed);
    let t = Instant::now();
    let scene = furnace_core::Scene::load(&dir.join("fur.xml"), &[]).unwrap_or_else(|e| panic!("{e}"));
    let secs = t.elapsed().as_secs_f64();
    let held = LIVE.load(Ordering::Relaxed) - before;
    let peak = PEAK.load(Ordering::Relaxed) - before;
    let segments: usize = scene
        .shapes
        .iter()
        .map(|s| match &s.geometry {
            Geometry::Curves(c) => c.segments.len(),
            _ => 0,
        })
        .sum();
    assert_eq!(segments, fibres * 8);
    assert_eq!(scene.accel.group_stats(), (instances.min(1), if instances > 0 { segments } else { 0 }));
    // The scene can be intersected: rays across the sphere's middle hit fur.
    let hits = (0..64)
        .filter(|&x| {
            scene.intersect(&scene.camera.ray_pinhole(glam::Vec2::new(x as f32 + 0.5, 32.0))).is_some()
        })
        .count();
    assert!(hits > 10, "{hits} of 64 rays hit the fur");
    drop(scene);
    std::fs::remove_dir_all(&dir).ok();
    let n = segments as f64;
    eprintln!(
        "{fibres} fibres, {segments} segments: load + BVH {secs:.2} s, {:.1} bytes/segment held, {:.1} peak",
        held as f64 / n,
        peak as f64 / n
    );
    (segments, secs, held as f64 / n, peak as f64 / n)
}

/// 100,000 fibres x 8 segments: the loaded scene (segments, BVH and everything else) holds
/// under 64 bytes per segment, and the load peaks under 170 (the BVH is built in batches of
/// 2^18 segments, four here; in one build it peaked at 332).
#[test]
fn fur_holds_under_64_bytes_per_segment() {
    let (_, _, held, peak) = load_fur(100_000, "fur100k");
    assert!(held < 64.0, "{held} bytes per segment");
    assert!(peak < 170.0, "peak {peak} bytes per segment");
}

/// Instancing (issue 17): 20,000 fibres (160,000 segments) placed 200 times, 32 million
/// segments in the picture, hold what one copy holds (within 10%: the instances and the top
/// tree), and load within 10% of its time plus a second.
#[test]
fn instanced_fur_holds_one_copy() {
    let (_, secs_one, held_one, peak_one) = load_fur_instanced(20_000, "fur20k", 0);
    let (_, secs, held, peak) = load_fur_instanced(20_000, "fur20k_x200", 200);
    eprintln!("200 instances: held {held:.1} against {held_one:.1} bytes a segment, peak {peak:.1} against {peak_one:.1}, {secs:.2} s against {secs_one:.2} s");
    assert!(held < 1.1 * held_one, "held {held} bytes a segment, {held_one} for one copy");
    assert!(peak < 1.1 * peak_one, "peak {peak} bytes a segment, {peak_one} for one copy");
    assert!(secs < 1.1 * secs_one + 1.0, "{secs} s, {secs_one} s for one copy");
}

/// The issue's scale: 1,000,000 fibres x 8 segments hold under 64 bytes per segment, peak at
/// most 120, and load and build in under 10 s on 2 cores (release build: 3.7 s here, right
/// after writing the file; docs/BENCHMARKS.md). The bound, 12 s, leaves room for a noisy
/// machine.
#[test]
#[ignore]
fn a_million_fibres_load_in_about_10_seconds() {
    let (_, secs, held, peak) = load_fur(1_000_000, "fur1m");
    assert!(held < 64.0, "{held} bytes per segment");
    // Issue 17's bound: 92.7 here (the batch's scratch spread over 31 batches).
    assert!(peak <= 120.0, "peak {peak} bytes per segment");
    assert!(secs < 12.0, "{secs} s");
}

/// Issue 18, measured: the frames of an animation of the seed's kind (`furnace generate`,
/// 250,000 fibres and a 400,000-triangle body; the camera turns a degree a frame) loaded one
/// after another, with the BVH as a worker loads them and without as a submission checks them:
/// with an asset cache the body, the fur and the sky are parsed for the first frame only.
/// Prints the times; checked without the BVH, the cached frames after the first must load in
/// at most 0.8 of the time (`cargo test --release --test scale -- --ignored
/// frames_after_the_first --nocapture`; docs/BENCHMARKS.md).
#[test]
#[ignore]
fn frames_after_the_first_reuse_the_parsed_files() {
    use furnace_core::scene::assets::AssetCache;
    use furnace_core::{LoadLimits, Scene};
    use std::sync::Arc;
    let dir = scratch("frames-gen");
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_furnace"))
        .args(["generate", "--fibres", "250000", "--body-triangles", "400000"])
        .arg(&dir)
        .status()
        .unwrap();
    assert!(st.success());
    let text = std::fs::read_to_string(dir.join("scene.xml")).unwrap();
    let turning = text
        .replacen(
            "<default name=\"spp\"",
            "<default name=\"frame\" value=\"0\"/>\n    <default name=\"spp\"",
            1,
        )
        .replacen(
            "<transform name=\"to_world\"><lookat",
            "<transform name=\"to_world\"><rotate y=\"1\" angle=\"$frame\"/><lookat",
            1,
        );
    // The rotation goes after the lookat (it turns the placed camera about the y axis).
    let turning = turning.replacen(
        "<rotate y=\"1\" angle=\"$frame\"/><lookat origin=\"0.2, 1.9, 8.5\" target=\"0.2, 0.9, 0\" up=\"0, 1, 0\"/>",
        "<lookat origin=\"0.2, 1.9, 8.5\" target=\"0.2, 0.9, 0\" up=\"0, 1, 0\"/><rotate y=\"1\" angle=\"$frame\"/>",
        1,
    );
    assert!(turning.contains("angle=\"$frame\""));
    let scene = dir.join("frames.xml");
    std::fs::write(&scene, turning).unwrap();
    let frames = ["1", "2", "3"];
    let time = |limits: &LoadLimits| -> Vec<f64> {
        frames
            .iter()
            .map(|f| {
                let t = Instant::now();
                let s = Scene::load_with(&scene, &[("frame".into(), f.to_string())], limits).unwrap();
                let secs = t.elapsed().as_secs_f64();
                drop(s);
                secs
            })
            .collect()
    };
    // As a worker loads them (with the BVH), and as a submission checks them (without).
    for accel in [true, false] {
        let plain = time(&LoadLimits { accel, ..Default::default() });
        let cache = Arc::new(AssetCache::new());
        let cached = time(&LoadLimits { accel, assets: Some(cache.clone()), ..Default::default() });
        println!(
            "BVH {accel}: frame loads without a cache {plain:.2?} s, with one {cached:.2?} s (hits, misses: {:?})",
            cache.counts()
        );
        assert_eq!(
            cache.counts(),
            (8, 4),
            "the mesh, the curve file (and its line count) and the sky: parsed once"
        );
        if !accel {
            let (a, b) = (plain[1] + plain[2], cached[1] + cached[2]);
            assert!(b <= 0.8 * a, "frames 2 and 3: {b:.2} s cached against {a:.2} s");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}
