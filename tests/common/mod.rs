//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use furnace_core::{render_image, Accum, Image, Scene, Stats};

pub fn scenes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scenes")
}

pub fn load(name: &str, defines: &[(&str, &str)]) -> Scene {
    let defs: Vec<(String, String)> = defines.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
    Scene::load(&scenes().join(name), &defs).unwrap_or_else(|e| panic!("{e}"))
}

/// Loads scene XML text as if it were a file in tests/scenes (assets resolve there).
pub fn load_str(xml: &str) -> Result<Scene, furnace_core::SceneError> {
    Scene::load_str(xml, &scenes().join("inline.xml"), &[])
}

pub fn render(scene: &Scene, spp: u64, seed: u64) -> (Accum, Stats) {
    render_image(scene, spp, seed, 32, 64, &|_| {})
}

pub fn reference(name: &str) -> Image {
    Image::read_exr(&scenes().join("refs").join(name)).unwrap_or_else(|e| panic!("{e}"))
}

/// A scratch directory unique to this test process and `tag`.
pub fn scratch(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("furnace-test-{}-{tag}", std::process::id()));
    std::fs::create_dir_all(&d).expect("create scratch dir");
    d
}
