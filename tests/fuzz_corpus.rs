//! Replays the kept fuzzing corpus (`fuzz/corpus/TARGET/*`, grown by `cargo fuzz run TARGET`,
//! see `fuzz/README.md`) through the same entry points the fuzz targets call, on stable: any
//! input that once crashed a parser or loader and was fixed stays fixed.

use std::path::Path;

use furnace_proto::fuzz::TARGETS;

#[test]
fn the_fuzzing_corpus_replays_without_a_panic() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus");
    let mut total = 0;
    for (name, run) in TARGETS {
        let dir = root.join(name);
        let mut files: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .collect();
        files.sort();
        assert!(!files.is_empty(), "no corpus for {name}");
        for f in &files {
            let bytes = std::fs::read(f).unwrap();
            let t = std::time::Instant::now();
            run(&bytes);
            let secs = t.elapsed().as_secs_f64();
            assert!(secs < 10.0, "{}: {secs:.1} s", f.display());
        }
        eprintln!("{name}: {} inputs", files.len());
        total += files.len();
    }
    assert!(total >= 50, "{total} inputs");
    // The scene target's asset folder (one per process; this test is its only user here).
    std::fs::remove_dir_all(furnace_proto::fuzz::asset_dir()).ok();
}

/// Writes the seed partials of `fuzz/corpus/partial` (run by hand with `--ignored` when the
/// partial format changes). The first byte is the target's mode: 0, the upload as it comes;
/// 1, an EXR the target compresses first.
#[test]
#[ignore]
fn write_partial_seeds() {
    use furnace_core::{Accum, Dropped};
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/partial");
    let mut a = Accum::new(3, 5, 4, 2);
    for (i, p) in a.pixels.iter_mut().enumerate() {
        p.rgb = [i as i128 * 1000, -7, 1 << 90];
        p.weight = 1 << 40;
        p.lum2 = 12345;
        p.count = 4;
    }
    a.dropped = Dropped { nan: 1, infinite: 2, too_bright: 3 };
    let seeds = [
        ("seed_tile", furnace_proto::encode_partial(&a)),
        ("seed_empty", furnace_proto::encode_partial(&Accum::new(0, 0, 1, 1))),
        ("seed_huge_window", furnace_proto::fuzz::partial_declaring(60_000, 60_000)),
        ("seed_wide_window", furnace_proto::fuzz::partial_declaring(60_000, 1)),
    ];
    for (name, zst) in seeds {
        std::fs::write(dir.join(format!("{name}.zst")), [&[0u8][..], &zst].concat()).unwrap();
        let exr = zstd::bulk::decompress(&zst, 1 << 24).unwrap();
        if exr.len() < 4096 {
            std::fs::write(dir.join(format!("{name}.exr")), [&[1u8][..], &exr].concat()).unwrap();
        }
    }
}
