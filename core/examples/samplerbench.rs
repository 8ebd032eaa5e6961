//! Cost of one 4-D sample set: `cargo run --release -p furnace-core --example samplerbench`.
use furnace_core::sampler::PixelSeeds;
use std::time::Instant;
fn main() {
    let n = 1_000_000u64;
    let t = Instant::now();
    let mut acc = 0.0f32;
    for i in 0..n {
        let mut p = PixelSeeds::new(1, (i % 256) as u32, (i / 256) as u32);
        let mut s = p.stream(i % 64);
        for _ in 0..8 {
            let v = s.next_4d();
            acc += v[0] + v[3];
        }
    }
    let dt = t.elapsed().as_secs_f64();
    println!("{:.1} ns per 4-D set ({acc})", dt / (n * 8) as f64 * 1e9);
}
