//! A sample the film cannot take (NaN, infinite, radiance above 2^40) is dropped and counted,
//! never fatal: the chunk's sample count covers it, the tallies travel with the partial, the
//! job finishes, and the same bytes and counts come out on any number of workers.

mod common;

use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::*;
use furnace::local::LocalLink;
use furnace_coordinator::Coordinator;
use furnace_core::{Dropped, Scene};
use furnace_proto::{decode_partial, encode_partial, JobSettings, JobState, JobStatus};
use furnace_worker::WorkerConfig;

/// A diffuse floor lit by a tiny sphere light of enormous radiance: light sampling finds it
/// with finite contributions, but the few camera and BSDF paths that hit it directly carry
/// radiance above 2^40.
fn tiny_blazing_sun(radiance: &str) -> Scene {
    load_str(&format!(
        r#"<scene version="3.0.0">
        <sensor type="perspective">
            <float name="fov" value="50"/>
            <transform name="to_world"><lookat origin="0, 1.2, 3" target="0, 0.2, 0"/></transform>
            <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="16"/>
                <rfilter type="box"/></film>
        </sensor>
        <shape type="rectangle">
            <transform name="to_world"><scale value="4"/><rotate x="1" angle="-90"/></transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf>
        </shape>
        <shape type="sphere">
            <point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.05"/>
            <emitter type="area"><rgb name="radiance" value="{radiance}"/></emitter>
        </shape>
    </scene>"#
    ))
    .unwrap()
}

/// Renders `scene` as a job on an in-memory coordinator with `workers` in-process workers of
/// one thread each; returns the finished job's status and image.
fn farm(scene: Scene, settings: JobSettings, workers: usize) -> (JobStatus, furnace_core::Image) {
    let coord = Arc::new(Mutex::new(Coordinator::ephemeral().unwrap()));
    let job = coord.lock().unwrap().submit_scene(Arc::new(scene), settings).unwrap();
    let handles: Vec<_> = (0..workers)
        .map(|k| {
            let cfg = WorkerConfig {
                link: Arc::new(LocalLink::new(coord.clone())),
                threads: 1,
                slots: 2,
                name: format!("w{k}"),
                poll: Duration::from_millis(5),
                stop: Arc::new(AtomicBool::new(false)),
                exit_when_idle: true,
            };
            std::thread::spawn(move || furnace_worker::run(cfg).unwrap())
        })
        .collect();
    for h in handles {
        h.join().unwrap();
    }
    let c = coord.lock().unwrap();
    (c.status(&job).unwrap(), c.image(&job).unwrap())
}

fn settings(spp: u64, tile: u32, spp_per_chunk: u64) -> JobSettings {
    JobSettings { width: 24, height: 16, spp, tile_size: tile, spp_per_chunk, seed: 3, ..Default::default() }
}

#[test]
fn too_bright_samples_are_dropped_counted_and_the_job_finishes_with_the_same_bytes_anywhere() {
    let (one, img_one) = farm(tiny_blazing_sun("2e12"), settings(32, 8, 8), 1);
    assert_eq!(one.state, JobState::Done, "{:?}", one.errors);
    assert_eq!(one.samples_done, 24 * 16 * 32, "dropped samples count as rendered");
    let d = one.dropped_samples;
    assert!(d.too_bright > 0 && d.nan == 0 && d.infinite == 0, "{d:?}");
    assert!(d.too_bright < one.samples_done / 10, "only the paths that hit the sun: {d:?}");
    assert!(one.errors.is_empty(), "{:?}", one.errors);
    assert!(img_one.data.iter().all(|p| p.is_finite()));
    // Three workers, other chunks: the same bits and the same tallies.
    let (three, img_three) = farm(tiny_blazing_sun("2e12"), settings(32, 8, 8), 3);
    assert_eq!(three.dropped_samples, d);
    assert!(img_one.data == img_three.data, "images differ between 1 and 3 workers");
    // Below 2^40 nothing is dropped.
    let (dim, _) = farm(tiny_blazing_sun("1e9"), settings(8, 8, 8), 1);
    assert_eq!((dim.state, dim.dropped_samples), (JobState::Done, Dropped::default()));
}

#[test]
fn infinite_samples_are_dropped_and_counted_as_infinite() {
    // 3.4e38 survives parsing (it is a float) but overflows when light sampling divides by
    // the pdf of a large light.
    let big_light = common::load("overflowing_light.xml", &[("width", "24")]);
    let (st, img) = farm(big_light, settings(8, 16, 4), 2);
    assert_eq!(st.state, JobState::Done, "{:?}", st.errors);
    assert!(st.dropped_samples.infinite > 0, "{:?}", st.dropped_samples);
    assert!(img.data.iter().all(|p| p.is_finite()));
}

#[test]
fn dropped_tallies_travel_with_the_partial_and_are_checked() {
    let scene = tiny_blazing_sun("2e12");
    let region = furnace_core::Region { x0: 0, y0: 0, x1: 24, y1: 16, s0: 0, s1: 16 };
    let (acc, st) = furnace_core::render_region(&scene, &region, 3);
    assert!(acc.dropped.too_bright > 0);
    assert_eq!(acc.sample_count(), st.samples);
    let back = decode_partial(&encode_partial(&acc), 1 << 24).unwrap();
    assert_eq!(back.dropped, acc.dropped);
    assert!(back == acc);
    // More dropped than generated is refused.
    let mut lie = acc.clone();
    lie.dropped.nan = st.samples;
    let e = decode_partial(&encode_partial(&lie), 1 << 24).unwrap_err();
    assert!(e.to_string().contains("'dropped'"), "{e}");
}

/// A bug that panics while a chunk renders (planted here: a shape naming a BSDF that does not
/// exist) fails that chunk with the panic's message; the worker lives on, and after its three
/// failures on the job it stops taking that job's chunks.
#[test]
fn a_panic_while_rendering_fails_the_chunk_and_the_worker_lives_on() {
    let mut scene = tiny_blazing_sun("5");
    scene.shapes[0].bsdf = 9999;
    let (st, _) = farm(scene, settings(4, 8, 4), 1);
    assert_ne!(st.state, JobState::Done);
    assert!(
        st.errors.iter().any(|e| e.contains("render panicked") && e.contains("index out of bounds")),
        "{:?}",
        st.errors
    );
    assert!(st.errors.iter().any(|e| e.contains("gets no more of this job")), "{:?}", st.errors);
}
