//! How much of a render's time its rays' traversals take: the bound on what faster shading
//! (issue 15's lever 4, paths shaded in SIMD lanes) can buy while rays are traced as now.
//!
//!     cargo bench -p furnace-core --features ray-log --bench traversal_share [-- THREADS SCENE.xml:SPP ...]
//!
//! Per scene: the render's rays are logged (one thread), then the render (`render_image`) and
//! a replay of the logged rays alone, each ray waiting on the one before as a path's rays do,
//! are timed on THREADS threads (default 2), best of five. Camera rays that go in packets
//! (`Accel::intersect_among_packet`) are not logged, so not replayed: their share is what
//! callgrind counts in `Accel::intersect_among_packet` and `Accel::gather`. Default scenes:
//! tests/scenes' cbox (16 spp), textured (64), envmap (64), thinlens (32), hair (8), and
//! examples/whimsical.xml (4).

use std::path::Path;
use std::time::Instant;

use furnace_core::geometry::bvh::ray_log;
use furnace_core::{render_image, Scene};
use rayon::prelude::*;

/// Seconds `f` takes.
fn seconds(f: impl FnOnce()) -> f64 {
    let t = Instant::now();
    f();
    t.elapsed().as_secs_f64()
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let threads = args.first().and_then(|t| t.parse().ok()).unwrap_or(2usize);
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut scenes: Vec<(String, u64)> = args
        .iter()
        .skip(1)
        // (Relative to the repository: cargo runs benches in the package's folder.)
        .filter_map(|a| {
            a.rsplit_once(':').and_then(|(s, n)| Some((root.join(s).display().to_string(), n.parse().ok()?)))
        })
        .collect();
    if scenes.is_empty() {
        for (s, spp) in [("cbox", 16), ("textured", 64), ("envmap", 64), ("thinlens", 32), ("hair", 8)] {
            scenes.push((root.join(format!("tests/scenes/{s}.xml")).display().to_string(), spp));
        }
        scenes.push((root.join("examples/whimsical.xml").display().to_string(), 4));
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("a thread pool");
    println!("{threads} threads, best of 5\n");
    println!("| scene | spp | rays replayed a sample | render (s) | replay (s) | replay / render |");
    println!("|---|---|---|---|---|---|");
    for (path, spp) in scenes {
        let scene = Scene::load(Path::new(&path), &[]).unwrap_or_else(|e| panic!("{e}"));
        let samples = (scene.film.crop_width * scene.film.crop_height) as f64 * spp as f64;
        let render = || {
            render_image(&scene, spp, 0, 32, spp, &|_| {});
        };
        let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("a thread pool");
        let rays = ray_log::during(|| one.install(render));
        let chunk = rays.len().div_ceil(threads * 64).max(1);
        let replay = || {
            rays.par_chunks(chunk).for_each(|c| {
                let mut last = 0.0f32;
                for (ray, from, shadow) in c {
                    let mut r = *ray;
                    // (Opaque to the compiler: the next query waits on this one's answer.)
                    r.tmin = r.tmin.max(std::hint::black_box(last) * 0.0);
                    last = if *shadow {
                        scene.accel.occluded_from(&scene.shapes, &r, *from) as u32 as f32
                    } else {
                        scene.accel.closest(&scene.shapes, &r, *from).map_or(1.0, |h| h.distance())
                    };
                }
                std::hint::black_box(last);
            })
        };
        let (mut t_render, mut t_replay) = (f64::MAX, f64::MAX);
        for _ in 0..5 {
            // Interleaved, so that the machine's drift hits both alike.
            t_render = t_render.min(seconds(|| pool.install(render)));
            t_replay = t_replay.min(seconds(|| pool.install(replay)));
        }
        let name =
            Path::new(&path).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or(path.clone());
        println!(
            "| {name} | {spp} | {:.2} | {t_render:.3} | {t_replay:.3} | {:.0}% |",
            rays.len() as f64 / samples,
            100.0 * t_replay / t_render
        );
    }
}
