//! Rendering regions (a rectangle of pixels x a range of sample indices) into exact partial
//! accumulations, and whole images from many regions in parallel.

use std::sync::Mutex;

use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::film::{Accum, Filter, PixelSum};
use crate::geometry::bvh::{Candidates, PACKET};
use crate::geometry::{Ray, RayDifferentials};
use crate::integrator::path::{self, First};
use crate::integrator::Stats;
use crate::math::Rgb;
use crate::sampler::PixelSeeds;
use crate::scene::Scene;

/// Offset of the ray differentials, in pixels.
pub const FOOTPRINT_PIXELS: f32 = 0.25;

/// Pixels `[x0, x1) x [y0, y1)` of the output (cropped) image, samples `[s0, s1)` of each.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct Region {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
    pub s0: u64,
    pub s1: u64,
}

impl Region {
    pub fn samples(&self) -> u64 {
        (self.x1 - self.x0) as u64 * (self.y1 - self.y0) as u64 * (self.s1 - self.s0)
    }
}

/// Every `tile` x `tile` tile crossed with every sample range of `spp_per_chunk` samples, pass
/// by pass: all tiles of the first range before any tile of the second. A pure function.
pub fn plan_regions(width: u32, height: u32, spp: u64, tile: u32, spp_per_chunk: u64) -> Vec<Region> {
    let tile = tile.max(1);
    let spp_per_chunk = spp_per_chunk.max(1);
    let mut out = Vec::new();
    let mut s0 = 0;
    while s0 < spp {
        let s1 = s0.saturating_add(spp_per_chunk).min(spp);
        for y0 in (0..height).step_by(tile as usize) {
            for x0 in (0..width).step_by(tile as usize) {
                out.push(Region {
                    x0,
                    y0,
                    x1: x0.saturating_add(tile).min(width),
                    y1: y0.saturating_add(tile).min(height),
                    s0,
                    s1,
                });
            }
        }
        s0 = s1;
    }
    out
}

/// The accumulation rectangle of a region: the region grown by the filter's margin, clipped to
/// the image.
pub fn accum_rect(scene: &Scene, r: &Region) -> (u32, u32, u32, u32) {
    let m = scene.film.filter.margin();
    let (w, h) = (scene.film.crop_width, scene.film.crop_height);
    let x0 = r.x0.saturating_sub(m);
    let y0 = r.y0.saturating_sub(m);
    let x1 = (r.x1 + m).min(w);
    let y1 = (r.y1 + m).min(h);
    (x0, y0, x1 - x0, y1 - y0)
}

/// A preview of the scene: the luminance of a grid of 16 x 16 of its (output) pixels, 4
/// samples each, rendered as [`render_region`] renders them with the scene's techniques as
/// they are, averaged over the samples by their filter weights (0 where that is not finite),
/// and the shadow rays those samples traced. What the light-sample cutoff derives from
/// ([`Scene::derive_techniques`]). A pure function of the scene: 1,024 samples, on the calling
/// thread, numbered from [`PREVIEW_SAMPLES`] (seed 0), past any render's.
pub fn preview(scene: &Scene) -> (f64, u64) {
    const GRID: u64 = 16;
    let (w, h) = (scene.film.crop_width as u64, scene.film.crop_height as u64);
    let (mut sum, mut weight, mut shadow_rays) = (0.0f64, 0.0f64, 0);
    for j in 0..GRID {
        for i in 0..GRID {
            let (x, y) = (((2 * i + 1) * w / (2 * GRID)) as u32, ((2 * j + 1) * h / (2 * GRID)) as u32);
            let r =
                Region { x0: x, y0: y, x1: x + 1, y1: y + 1, s0: PREVIEW_SAMPLES, s1: PREVIEW_SAMPLES + 4 };
            let (acc, st) = render_region(scene, &r, 0);
            for p in &acc.pixels {
                let [r, g, b] = p.rgb.map(|c| crate::film::to_f64(c) as f32);
                sum += crate::math::luminance_f64(Rgb::new(r, g, b));
                weight += crate::film::to_f64(p.weight);
            }
            shadow_rays += st.shadow_rays;
        }
    }
    let b = sum / weight;
    (if b.is_finite() && b > 0.0 { b } else { 0.0 }, shadow_rays)
}

/// Where [`preview`] numbers its samples: past the farm's limit of 2^24 samples a pixel (and
/// any render's in practice), so that no render reuses the numbers its cutoff was derived from.
pub const PREVIEW_SAMPLES: u64 = 1 << 40;

/// Renders one region into a partial accumulation over the region plus the filter margin.
pub fn render_region(scene: &Scene, r: &Region, seed: u64) -> (Accum, Stats) {
    render_region_in(scene, r, seed, true)
}

/// [`render_region`]; without `together` every sample is traced alone, as before packets
/// (the reference that packets are tested against).
fn render_region_in(scene: &Scene, r: &Region, seed: u64, together: bool) -> (Accum, Stats) {
    let (ax, ay, aw, ah) = accum_rect(scene, r);
    let mut acc = Accum::new(ax, ay, aw, ah);
    let mut st = Stats::default();
    let film = &scene.film;
    let cam = &scene.camera;
    let filter = film.filter;
    let own_pixel = matches!(filter, Filter::Box { radius } if radius == 0.5);
    // Without a lens the camera's set has two numbers to spare: the first vertex's light
    // sample (`path::li`).
    let spare_lens = cam.lens.is_none();
    let (w, h) = (film.crop_width, film.crop_height);
    let mut cands = Candidates::default();
    let bundles = cam.pixel_bundles();
    for y in r.y0..r.y1 {
        for x in r.x0..r.x1 {
            let (fx_px, fy_px) = (x + film.crop_x, y + film.crop_y);
            // The leaves this pixel's camera rays may hit, gathered once for all its samples.
            scene.accel.gather(&bundles.pixel(fx_px, fy_px), &mut cands);
            let mut seeds = PixelSeeds::new(seed, fx_px, fy_px);
            // With a box filter of radius 0.5 the pixel's own sums, added once at its end.
            let mut own = PixelSum::default();
            let mut add = |l: Rgb, fx: f32, fy: f32| {
                if let Some(why) = crate::film::drop_reason(l) {
                    acc.count_dropped(x, y, why);
                    return;
                }
                if own_pixel {
                    own.add_own_sample(l);
                    return;
                }
                acc.count_sample(x, y, l);
                // Splat to every pixel whose centre lies within the filter radius.
                let (px, py) = (x as f32 + fx, y as f32 + fy);
                let (jx0, jx1) = filter.splat_span(x, px, w);
                let (jy0, jy1) = filter.splat_span(y, py, h);
                for jy in jy0..=jy1 {
                    let wy = filter.eval(py - (jy as f32 + 0.5));
                    if wy == 0.0 {
                        continue;
                    }
                    for jx in jx0..=jx1 {
                        let wx = filter.eval(px - (jx as f32 + 0.5));
                        if wx != 0.0 {
                            acc.splat(jx as u32, jy as u32, wx * wy, l);
                        }
                    }
                }
            };
            // Where the pixel's leaves were all gathered, its camera rays go in packets of
            // PACKET: their first hits are found together (and the radiance of those that hit
            // nothing), then each path goes on alone.
            let gathered = cands.len().is_some();
            // A pixel whose bundle meets no leaf (a sky pixel): every camera ray escapes, and
            // a packet needs only its rays and their lights' radiance, looked up together.
            let sky = together && cands.len() == Some(0) && path::looks_up_escaped(scene);
            let mut i = r.s0;
            while i < r.s1 {
                let want = if gathered && together { (r.s1 - i).min(PACKET as u64) as usize } else { 1 };
                let (mut streams, n) = seeds.streams::<PACKET>(i, want);
                let mut film_uv = [(0.0f32, 0.0f32); PACKET];
                let (mut pos, mut lens_u) = ([Vec2::ZERO; PACKET], [Vec2::ZERO; PACKET]);
                for j in 0..n {
                    let [fx, fy, lx, ly] = streams[j].next_4d();
                    film_uv[j] = (fx, fy);
                    pos[j] = Vec2::new(fx_px as f32 + fx, fy_px as f32 + fy);
                    lens_u[j] = Vec2::new(lx, ly);
                }
                if cam.lens.is_some() {
                    st.lens_samples += n as u64;
                }
                let mut rays = [Ray::new(Vec3::ZERO, Vec3::Z); PACKET];
                cam.rays(&pos[..n], &lens_u[..n], &mut rays[..n]);
                let mut diffs = [None; PACKET];
                let mut hits = [None; PACKET];
                // The radiance of the rays that hit nothing, looked up together (bit j: ray j's
                // is in escaped[j]).
                let (mut escaped, mut looked_up) = ([Rgb::ZERO; PACKET], 0u32);
                if sky && n > 1 {
                    // What the packet below would find for them, bit for bit (no hits, then
                    // `path::li_escaped` of all), without its per-ray bookkeeping.
                    let dirs: [Vec3; PACKET] = std::array::from_fn(|j| rays[j].d);
                    path::li_escaped(scene, &dirs[..n], &mut escaped[..n], &mut st);
                    looked_up = (1 << n) - 1;
                } else {
                    if scene.techniques.footprints {
                        // Differentials to a neighbour FOOTPRINT_PIXELS away: the pixel filter
                        // already averages many samples, so a full pixel would blur twice.
                        let (mut rx, mut ry) = ([rays[0]; PACKET], [rays[0]; PACKET]);
                        let shifted = |by: Vec2| -> [Vec2; PACKET] { std::array::from_fn(|j| pos[j] + by) };
                        cam.rays(&shifted(Vec2::new(FOOTPRINT_PIXELS, 0.0))[..n], &lens_u[..n], &mut rx[..n]);
                        cam.rays(&shifted(Vec2::new(0.0, FOOTPRINT_PIXELS))[..n], &lens_u[..n], &mut ry[..n]);
                        for j in 0..n {
                            diffs[j] = Some(RayDifferentials { rx: rx[j], ry: ry[j] });
                        }
                    }
                    if gathered {
                        scene.intersect_among_packet(&rays[..n], &cands, &mut hits[..n]);
                        let (mut dirs, mut lanes, mut m) = ([Vec3::ZERO; PACKET], [0usize; PACKET], 0);
                        for j in (0..n).filter(|&j| hits[j].is_none()) {
                            (dirs[m], lanes[m]) = (rays[j].d, j);
                            m += 1;
                        }
                        let mut out = [Rgb::ZERO; PACKET];
                        if together && m > 1 && path::li_escaped(scene, &dirs[..m], &mut out[..m], &mut st) {
                            for (&j, &l) in lanes[..m].iter().zip(&out[..m]) {
                                escaped[j] = l;
                                looked_up |= 1 << j;
                            }
                        }
                    }
                }
                for j in 0..n {
                    let first = if gathered { First::Found(hits[j]) } else { First::Trace };
                    let l = if looked_up >> j & 1 != 0 {
                        escaped[j]
                    } else {
                        let light0 = spare_lens.then(|| lens_u[j].to_array());
                        path::li(scene, rays[j], diffs[j].as_ref(), first, light0, &mut streams[j], &mut st)
                    };
                    st.samples += 1;
                    // (Read a coordinate at a time: either branch leaves `l` in memory in pieces.)
                    add(crate::math::apart(l), film_uv[j].0, film_uv[j].1);
                }
                i += n as u64;
            }
            if own_pixel {
                acc.add_pixel(x, y, &own);
            }
        }
    }
    (acc, st)
}

/// Rows of one band: the unit of work the threads share within a region.
const BAND_ROWS: u32 = 2;

/// Renders one region on `pool`: bands of [`BAND_ROWS`] rows, taken in turn by as many tasks
/// as the pool has threads and merged exactly, so the result is bit-identical to
/// [`render_region`]. Gives up (`None`) once `stop` is set: bands not begun by then are not
/// rendered (a worker whose lease was revoked stops within a band).
///
/// The calling thread (a worker's chunk thread, outside the pool) waits for the tasks; no
/// pool thread ever waits inside a region. A pool thread blocked in a fork-join (rayon's
/// `install` and `join`) runs other regions' work on top of its own while it waits, so its
/// region ends only when that work has: chunks then finished in clumps and the pool ran dry
/// between them. Here a thread that finds no band left simply takes the next task queued, the
/// next region's (docs/BENCHMARKS.md, "Issue 15, twenty-third step").
pub fn render_region_on(
    pool: &rayon::ThreadPool,
    scene: &Scene,
    r: &Region,
    seed: u64,
    stop: &std::sync::atomic::AtomicBool,
) -> Option<(Accum, Stats)> {
    use std::sync::atomic::{AtomicBool, AtomicU32, Ordering::Relaxed};
    let (ax, ay, aw, ah) = accum_rect(scene, r);
    let bands = (r.y1.saturating_sub(r.y0)).div_ceil(BAND_ROWS);
    let next = AtomicU32::new(0);
    let stopped = AtomicBool::new(false);
    let total = Mutex::new((Accum::new(ax, ay, aw, ah), Stats::default()));
    let tasks = pool.current_num_threads().min(bands as usize);
    pool.in_place_scope(|s| {
        for _ in 0..tasks {
            s.spawn(|_| loop {
                let b = next.fetch_add(1, Relaxed);
                if b >= bands {
                    return;
                }
                if stop.load(Relaxed) {
                    stopped.store(true, Relaxed);
                    return;
                }
                let y0 = r.y0 + b * BAND_ROWS;
                let band = Region { y0, y1: (y0 + BAND_ROWS).min(r.y1), ..*r };
                let (a, st) = render_region(scene, &band, seed);
                let mut t = total.lock().unwrap_or_else(|e| e.into_inner());
                t.0.merge(&a);
                t.1.merge(&st);
            });
        }
    });
    if stopped.load(Relaxed) {
        return None;
    }
    Some(total.into_inner().unwrap_or_else(|e| e.into_inner()))
}

/// Renders the whole image at `spp` samples per pixel on the current rayon pool, calling
/// `progress(samples_done)` as regions finish. The result does not depend on `tile`,
/// `spp_per_chunk` or the thread count.
pub fn render_image(
    scene: &Scene,
    spp: u64,
    seed: u64,
    tile: u32,
    spp_per_chunk: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> (Accum, Stats) {
    let (w, h) = (scene.film.crop_width, scene.film.crop_height);
    let regions = plan_regions(w, h, spp, tile, spp_per_chunk);
    let total = Mutex::new((Accum::new(0, 0, w, h), Stats::default(), 0u64));
    regions.par_iter().for_each(|r| {
        let (acc, st) = render_region(scene, r, seed);
        let mut g = total.lock().unwrap_or_else(|e| e.into_inner());
        g.0.merge(&acc);
        g.1.merge(&st);
        g.2 += r.samples();
        let done = g.2;
        drop(g);
        progress(done);
    });
    let (acc, st, _) = total.into_inner().unwrap_or_else(|e| e.into_inner());
    (acc, st)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    /// Camera rays in packets (first hits found together, the radiance of those that escape
    /// looked up together) render what each sample traced alone renders, bit for bit, with the
    /// same counts: on every kernel, for sample ranges that fill packets and ranges that do
    /// not, on scenes of triangles, spheres, instances, fibres, a lens, a sky and a constant
    /// emitter, hidden emitters.
    #[test]
    fn packets_render_what_each_sample_renders() {
        for (name, extra) in [
            ("cbox.xml", ""),
            ("textured.xml", ""),
            ("envmap.xml", ""),
            ("thinlens.xml", ""),
            ("instances.xml", ""),
            ("hair.xml", ""),
            ("hidden_emitter.xml", ""),
            ("envmap.xml", "hide"),
        ] {
            let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes").join(name);
            let mut scene = Scene::load(&path, &[]).unwrap_or_else(|e| panic!("{name}: {e}"));
            if extra == "hide" {
                scene.integrator.hide_emitters = true;
            }
            let (w, h) = (scene.film.crop_width, scene.film.crop_height);
            for kernel in crate::geometry::bvh::Kernel::available() {
                scene.accel.set_kernel(kernel);
                for (s0, s1) in [(0, 8), (3, 14), (5, 6)] {
                    let r = Region { x0: w / 2 - 12, y0: h / 2 - 10, x1: w / 2 + 12, y1: h / 2 + 10, s0, s1 };
                    let packed = render_region_in(&scene, &r, 11, true);
                    let alone = render_region_in(&scene, &r, 11, false);
                    assert_same(&packed, &alone, &format!("{name} {extra} {kernel:?} samples {s0}..{s1}"));
                }
            }
        }
    }

    /// The same image, bit for bit, and the same counts.
    fn assert_same(a: &(Accum, Stats), b: &(Accum, Stats), what: &str) {
        assert!(a.0 == b.0, "{what}: images differ");
        assert_eq!(a.1, b.1, "{what}: counts differ");
    }

    /// A region rendered in bands by a pool's tasks is the region rendered alone, bit for bit
    /// and count for count: for pools of 1 to 5 threads (more threads than bands, fewer, as
    /// many), regions of 0, 1, 2, 7 and 20 rows and regions at the image's edges; a box filter,
    /// a wider one (whose bands splat into each other's rows) and a crop window. A stop set
    /// before the render gives nothing (a region of no rows has nothing to stop); one set while
    /// it renders gives nothing or all of it, never a region with bands missing.
    #[test]
    fn a_region_rendered_in_bands_on_a_pool_is_the_region_rendered_alone() {
        use std::sync::atomic::AtomicBool;
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes");
        for (name, crop) in [("cbox.xml", false), ("small.xml", false), ("small.xml", true)] {
            let mut scene = Scene::load(&dir.join(name), &[]).unwrap_or_else(|e| panic!("{name}: {e}"));
            if crop {
                // A crop window: pixels are the window's, the camera's are offset.
                let f = &mut scene.film;
                (f.crop_x, f.crop_y, f.crop_width, f.crop_height) =
                    (5, 3, f.crop_width - 9, f.crop_height - 7);
            }
            let (w, h) = (scene.film.crop_width, scene.film.crop_height);
            let mut regions: Vec<Region> = [0, 1, 2, 7, 20]
                .map(|rows| Region {
                    x0: w / 2 - 9,
                    y0: h / 2 - 10,
                    x1: w / 2 + 9,
                    y1: h / 2 - 10 + rows,
                    s0: 2,
                    s1: 6,
                })
                .into();
            // At the image's edges, where the filter's margin is clipped.
            regions.push(Region { x0: 0, y0: 0, x1: w, y1: 5, s0: 0, s1: 3 });
            regions.push(Region { x0: w - 13, y0: h - 7, x1: w, y1: h, s0: 1, s1: 4 });
            for threads in 1..=5 {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
                for r in &regions {
                    let go = AtomicBool::new(false);
                    let banded = render_region_on(&pool, &scene, r, 5, &go).expect("not stopped");
                    let alone = render_region(&scene, r, 5);
                    assert_same(&banded, &alone, &format!("{name} (crop {crop}), {threads} threads, {r:?}"));
                    let stop = AtomicBool::new(true);
                    assert!(render_region_on(&pool, &scene, r, 5, &stop).is_none() || r.y1 == r.y0);
                }
            }
        }
        // A stop that comes while the bands render gives nothing or the whole region, never a
        // region with bands missing (a worker would upload it as complete). The region takes
        // tens of milliseconds, so that a stop sent at once lands during it even on a loaded
        // machine (at 32 x 32 x 2 samples a busy scheduler could start the stopping thread
        // only after the render had finished, and no render was stopped).
        let scene = Scene::load(&dir.join("cbox.xml"), &[]).expect("cbox");
        let r = Region { x0: 96, y0: 96, x1: 160, y1: 160, s0: 0, s1: 16 };
        let alone = render_region(&scene, &r, 5);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().expect("pool");
        let (mut stopped, mut whole) = (0, 0);
        for k in 0..24u64 {
            let stop = AtomicBool::new(false);
            let got = std::thread::scope(|s| {
                s.spawn(|| {
                    std::thread::sleep(std::time::Duration::from_micros(k * k * 150));
                    stop.store(true, std::sync::atomic::Ordering::Relaxed);
                });
                render_region_on(&pool, &scene, &r, 5, &stop)
            });
            match got {
                None => stopped += 1,
                Some(got) => {
                    assert_same(&got, &alone, &format!("stopped after {} us", k * k * 150));
                    whole += 1;
                }
            }
        }
        assert!(stopped > 0, "no render was stopped ({whole} whole)");
    }
}
