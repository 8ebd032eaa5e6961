use furnace_core::geometry::Ray;
use furnace_core::math::{square_to_uniform_sphere, Vec2, Vec3};
use std::time::Instant;
fn main() {
    let path = std::env::args().nth(1).unwrap();
    let scene = furnace_core::Scene::load(std::path::Path::new(&path), &[]).unwrap();
    let n = 2_000_000;
    let rays: Vec<Ray> = (0..n)
        .map(|i| {
            let u = Vec2::new((i as f32 * 0.618034) % 1.0, (i as f32 * 0.7548776) % 1.0);
            Ray::new(Vec3::new(0.1, 0.2, 0.3), square_to_uniform_sphere(u))
        })
        .collect();
    let t = Instant::now();
    let mut hits = 0;
    for r in &rays {
        if scene.intersect(r).is_some() {
            hits += 1;
        }
    }
    let dt = t.elapsed().as_secs_f64();
    println!(
        "intersect: {:.1} Mrays/s ({hits} hits)",
        n as f64 / dt / 1e6
    );
    let t = Instant::now();
    let mut occ = 0;
    for r in &rays {
        if scene.occluded(r) {
            occ += 1;
        }
    }
    let dt = t.elapsed().as_secs_f64();
    println!("occluded: {:.1} Mrays/s ({occ})", n as f64 / dt / 1e6);
}
