//! Entry points for fuzzing: each takes arbitrary bytes, runs one parser or loader of input a
//! user controls, and must return (an error is fine) without panicking, hanging or allocating
//! without bound. The `cargo fuzz` targets in `fuzz/` call these, and `tests/fuzz_corpus.rs`
//! replays the kept corpus through them on stable in every test run.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use furnace_core::geometry::curves::parse_curve_file;
use furnace_core::geometry::Mesh;
use furnace_core::scene::{build, xml};
use furnace_core::texture::Bitmap;

/// Texel limit for fuzzed images (the loader's real limit is larger; the mechanism is the same).
const FUZZ_MAX_TEXELS: u64 = 1 << 20;

/// A folder holding the assets fuzzed scenes may name, at the paths the test scenes use:
/// `assets/checker.png`, `assets/envmap_sun.exr`, `assets/quad.obj`, `assets/quad.ply`,
/// `assets/fibre_straight.txt`. Made once per process.
pub fn asset_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("furnace-fuzz-assets-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("assets")).expect("temporary folder");
        let files: [(&str, &[u8]); 5] = [
            ("checker.png", include_bytes!("../../tests/scenes/assets/checker.png")),
            ("envmap_sun.exr", include_bytes!("../../tests/scenes/assets/envmap_sun.exr")),
            ("quad.obj", include_bytes!("../../tests/scenes/assets/quad.obj")),
            ("quad.ply", include_bytes!("../../tests/scenes/assets/quad.ply")),
            ("fibre_straight.txt", include_bytes!("../../tests/scenes/assets/fibre_straight.txt")),
        ];
        for (name, bytes) in files {
            std::fs::write(dir.join("assets").join(name), bytes).expect("temporary folder");
        }
        dir
    })
}

/// Scene XML through the parser and the scene builder (the BVH build included).
pub fn scene_xml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let path = asset_dir().join("scene.xml");
    if let Ok(doc) = xml::parse_str(text, &path, &[]) {
        let _ = build::build(&doc, &Default::default());
    }
}

pub fn obj(data: &[u8]) {
    let _ = Mesh::parse_obj(&mut std::io::Cursor::new(data), true).and_then(Mesh::validate);
}

pub fn ply(data: &[u8]) {
    let _ = Mesh::parse_ply(&mut std::io::Cursor::new(data)).and_then(Mesh::validate);
}

pub fn curves(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(c) = parse_curve_file(text, 4) {
        let _ = furnace_core::geometry::curves::Curves::bspline(&c, 4);
        let _ = furnace_core::geometry::curves::Curves::linear(&c);
    }
}

/// An image texture: the first byte picks EXR (odd) or the formats told by their bytes (PNG,
/// JPEG, HDR), and raw or sRGB decoding.
pub fn image(data: &[u8]) {
    let Some((&mode, bytes)) = data.split_first() else { return };
    let _ = Bitmap::decode(bytes, mode & 1 == 1, mode & 2 == 2, FUZZ_MAX_TEXELS);
}

/// A chunk's partial upload, decoded with the coordinator's limit on its size. The first byte
/// picks the bytes as they come (even) or an EXR that is compressed first (odd), so that the
/// fuzzer mutates the EXR itself, not only the zstd frame around it.
pub fn partial(data: &[u8]) {
    let Some((&mode, bytes)) = data.split_first() else { return };
    match mode & 1 {
        0 => drop(crate::decode_partial(bytes, 1 << 24)),
        _ => drop(crate::decode_partial(&zstd::bulk::compress(bytes, 1).expect("in memory"), 1 << 24)),
    }
}

/// A hostile upload: a valid 1 x 1 partial whose header declares a `width` x `height` data
/// window, with an offset table to match (so an EXR reader trusting it allocates the whole
/// image); a few hundred bytes once compressed.
pub fn partial_declaring(width: i32, height: i32) -> Vec<u8> {
    fn field(bytes: &mut [u8], key: &[u8]) -> usize {
        bytes.windows(key.len()).position(|w| w == key).expect("the attribute is written") + key.len() + 4
    }
    let one = furnace_core::Accum::new(0, 0, 1, 1);
    let exr = zstd::bulk::decompress(&crate::encode_partial(&one), 1 << 20).expect("just encoded");
    let block = 8 + crate::WORDS * 4; // line number, byte count, one pixel
    let mut out = exr[..exr.len() - 8 - block].to_vec(); // the header alone
    let at = field(&mut out, b"dataWindow\0box2i\0");
    out[at + 8..at + 12].copy_from_slice(&(width - 1).to_le_bytes());
    out[at + 12..at + 16].copy_from_slice(&(height - 1).to_le_bytes());
    let at = field(&mut out, b"chunkCount\0int\0");
    out[at..at + 4].copy_from_slice(&height.to_le_bytes());
    let first_block = (out.len() + 8 * height as usize) as u64;
    for _ in 0..height {
        out.extend_from_slice(&first_block.to_le_bytes());
    }
    out.extend_from_slice(&exr[exr.len() - block..]);
    zstd::bulk::compress(&out, 19).expect("in memory")
}

/// A job submission's JSON: parsed, its bundle checked and hashed.
pub fn job_spec(data: &[u8]) {
    if let Ok(spec) = serde_json::from_slice::<crate::JobSpec>(data) {
        if spec.bundle.validate().is_ok() {
            let _ = spec.bundle.hash();
            let _ = spec.settings.tiles();
        }
    }
}

/// Every target by name, for the corpus replay.
pub const TARGETS: [(&str, fn(&[u8])); 7] = [
    ("scene_xml", scene_xml),
    ("obj", obj),
    ("ply", ply),
    ("curves", curves),
    ("image", image),
    ("partial", partial),
    ("job_spec", job_spec),
];
