//! Ray-query throughput on a scene's BVH: `cargo run --release -p furnace-core --example raybench SCENE.xml`.
use furnace_core::geometry::bvh::SpawnedFrom;
use furnace_core::geometry::Ray;
use furnace_core::math::{square_to_uniform_sphere, Vec2, Vec3};
use std::time::Instant;

fn main() {
    let path = std::env::args().nth(1).expect("usage: raybench SCENE.xml");
    let scene = furnace_core::Scene::load(std::path::Path::new(&path), &[]).unwrap_or_else(|e| panic!("{e}"));
    let n = 2_000_000;
    // Rays from surface points (first hits of random rays from the centre), in random directions.
    let mut rays = Vec::with_capacity(n);
    let mut i = 0u32;
    while rays.len() < n {
        i += 1;
        let u = Vec2::new((i as f32 * 0.618_034) % 1.0, (i as f32 * 0.754_877_7) % 1.0);
        let v = Vec2::new((i as f32 * 0.569_840_3) % 1.0, (i as f32 * 0.324_717_9) % 1.0);
        if let Some(it) = scene.intersect(&Ray::new(Vec3::new(0.1, 0.2, 0.3), square_to_uniform_sphere(u))) {
            let mut d = square_to_uniform_sphere(v);
            if d.dot(it.ng) < 0.0 {
                d = -d;
            }
            // With the fibre piece it leaves, as the integrator traces it.
            rays.push((it.spawn_ray(d), it.leaving()));
        }
    }
    let t = Instant::now();
    let hits = rays
        .iter()
        .filter(|(r, l)| scene.accel.closest(&scene.shapes, r, SpawnedFrom::piece(*l)).is_some())
        .count();
    let dt = t.elapsed().as_secs_f64();
    println!("closest hit: {:.2} Mrays/s ({hits} hits)", n as f64 / dt / 1e6);
    let t = Instant::now();
    let occ = rays.iter().filter(|(r, l)| scene.occluded_from(r, SpawnedFrom::piece(*l))).count();
    let dt = t.elapsed().as_secs_f64();
    println!("any hit:     {:.2} Mrays/s ({occ} occluded)", n as f64 / dt / 1e6);
}
