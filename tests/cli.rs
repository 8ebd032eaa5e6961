//! The `furnace` binary end to end.

mod common;

use std::process::Command;

use common::*;
use furnace_core::Image;

fn furnace() -> Command {
    Command::new(env!("CARGO_BIN_EXE_furnace"))
}

#[test]
fn render_writes_exr_and_png() {
    let dir = scratch("cli-render");
    let out = dir.join("small.exr");
    let o = furnace()
        .args(["render", "--spp", "4", "--threads", "2", "-D", "width=24", "-o"])
        .arg(&out)
        .arg(scenes().join("small.xml"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("thin lens") && stderr.contains("Msamples/s"), "{stderr}");
    // What the binary was compiled for is logged with the kernels chosen at run time.
    let built_for = format!("built for {}; Sobol sets in", furnace_core::cpu::build_target());
    assert!(stderr.contains(&built_for), "expected {built_for} in {stderr}");
    let img = Image::read_exr(&out).unwrap();
    assert_eq!((img.width, img.height), (24, 40));
    assert!(img.mean_luminance() > 0.05);
    let png = image::open(dir.join("small.png")).unwrap();
    assert_eq!((png.width(), png.height()), (24, 40));
    std::fs::remove_dir_all(&dir).ok();
}

/// `furnace render` runs the farm in one process (a coordinator and a worker with several
/// chunks in flight: by default one a thread, 4 to 16); neither threads, chunks in flight nor
/// tile size change a bit of the image, which equals the library's plain render loop.
#[test]
fn render_through_the_in_process_farm_equals_the_plain_render_loop() {
    let dir = scratch("cli-one-path");
    let scene = load("small.xml", &[("width", "24")]);
    let expect = render(&scene, 70, 9).0.develop();
    for (threads, slots, tile) in [
        ("1", None, "8"),
        ("2", None, "32"),
        ("3", Some("1"), "5"),
        ("2", Some("9"), "7"),
        ("6", None, "16"),
        ("20", None, "64"),
    ] {
        let out = dir.join(format!("t{threads}-{tile}.exr"));
        let mut cmd = furnace();
        cmd.args(["render", "--spp", "70", "--seed", "9", "-D", "width=24", "--threads", threads]);
        if let Some(k) = slots {
            cmd.args(["--slots", k]);
        }
        let o = cmd.args(["--tile", tile, "-o"]).arg(&out).arg(scenes().join("small.xml")).output().unwrap();
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{stderr}");
        let default = match threads {
            "6" => "6",
            "20" => "16",
            _ => "4",
        };
        let in_flight = format!("(up to {} chunks in flight)", slots.unwrap_or(default));
        assert!(stderr.contains(&in_flight), "expected {in_flight} in {stderr}");
        let img = Image::read_exr(&out).unwrap();
        assert!(
            img.data == expect.data,
            "threads {threads}, slots {slots:?}, tile {tile}: image differs from render_image"
        );
    }
    // Out of range: a clear error before anything renders.
    for bad in ["0", "257", "many"] {
        let o = furnace().args(["render", "--slots", bad]).arg(scenes().join("small.xml")).output().unwrap();
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && stderr.contains("--slots"), "--slots {bad}: {stderr}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn plan_is_printed() {
    let o = furnace().args(["render", "--plan"]).arg(scenes().join("cbox.xml")).output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success());
    assert!(out.contains("pinhole") && out.contains("area x1") && out.contains("MIS"), "{out}");
}

#[test]
fn bad_scene_fails_with_file_line_and_reason() {
    let dir = scratch("cli-bad");
    let bad = dir.join("bad.xml");
    std::fs::write(&bad, "<scene version=\"3.0.0\">\n  <shape type=\"teapot\"/>\n</scene>\n").unwrap();
    let o = furnace().arg("render").arg(&bad).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1));
    assert!(err.contains("bad.xml:2:3") && err.contains("unsupported shape plugin 'teapot'"), "{err}");
    let o = furnace().args(["render", "-D", "novalue"]).arg(&bad).output().unwrap();
    assert!(String::from_utf8_lossy(&o.stderr).contains("NAME=VALUE"));
    std::fs::remove_dir_all(&dir).ok();
}

/// Every shipped example loads and renders (the README's first command renders one).
#[test]
fn examples_render() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
    let out = scratch("examples");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("xml") {
            continue;
        }
        let o = furnace()
            .args(["render", "--spp", "1", "-D", "spp=1", "-o"])
            .arg(out.join("e.exr"))
            .arg(&path)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}: {}", path.display(), String::from_utf8_lossy(&o.stderr));
        n += 1;
    }
    assert!(n >= 3, "only {n} examples");
    std::fs::remove_dir_all(&out).ok();
}

/// Issue 13's first case: the shipped Cornell box with its light at radiance 2e12. Samples
/// that see the light directly are above 2^40: they are dropped and counted, the render
/// finishes, and the log says how many and why.
#[test]
fn render_with_a_blazing_light_finishes_and_reports_dropped_samples() {
    let dir = scratch("cli-dropped");
    let xml = std::fs::read_to_string(env!("CARGO_MANIFEST_DIR").to_string() + "/examples/cbox.xml").unwrap();
    let hot = xml.replace("18.387, 13.9873, 6.75357", "2e12");
    assert_ne!(hot, xml);
    std::fs::write(dir.join("cbox.xml"), hot).unwrap();
    let out = dir.join("hot.exr");
    let o = furnace()
        .args(["render", "--spp", "4", "--threads", "2", "-o"])
        .arg(&out)
        .arg(dir.join("cbox.xml"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(
        stderr.contains("were dropped and never reached the image") && stderr.contains("above 2^40"),
        "{stderr}"
    );
    assert!(Image::read_exr(&out).unwrap().data.iter().all(|p| p.is_finite()));
    // A non-finite exposure is refused up front.
    let o = furnace().args(["render", "--exposure", "nan"]).arg(dir.join("cbox.xml")).output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("exposure"));
    std::fs::remove_dir_all(&dir).ok();
}

/// A careless job is refused at once, naming the limit, instead of growing its chunk plan
/// until memory runs out (issue 14: cbox at 4096 spp in 1-pixel, 1-spp chunks is 268M chunks).
#[test]
fn a_job_beyond_the_chunk_limit_is_refused_naming_the_limit() {
    let cbox = env!("CARGO_MANIFEST_DIR").to_string() + "/examples/cbox.xml";
    let t = std::time::Instant::now();
    let o = furnace()
        .args(["render", "--spp", "4096", "--tile", "1", "--spp-per-chunk", "1", "-o", "/dev/null"])
        .arg(&cbox)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(stderr.contains("268435456 chunks, more than the limit of 1048576"), "{stderr}");
    assert!(t.elapsed().as_secs() < 10, "refused only after {:?}", t.elapsed());
}

/// `furnace generate` writes a scene of the seed's class of the size asked (body triangles,
/// 8 segments a fibre, a ground and two balls) that loads with every plugin it names and
/// renders: the fur (hair BSDF) and the ground are lit by the sun/sky map; the grass is one
/// tuft in a shapegroup, placed by an instance per tuft.
#[test]
fn generate_writes_a_seed_class_scene_that_renders() {
    let dir = scratch("generate");
    let o = furnace()
        .arg("generate")
        .arg(&dir)
        .args(["--fibres", "3000", "--body-triangles", "2000", "--grass-tufts", "40", "--blades", "30"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{stdout}{}", String::from_utf8_lossy(&o.stderr));
    let tris: u64 = stdout.split(": ").nth(1).and_then(|s| s.split(' ').next()).unwrap().parse().unwrap();
    assert!((1800..=2200).contains(&tris), "{stdout}");
    let scene = furnace_core::Scene::load(&dir.join("scene.xml"), &[]).unwrap();
    assert_eq!(scene.accel.prim_count() as u64, tris + 3000 * 8 + 2 + 2 + 40, "{stdout}");
    assert_eq!(scene.accel.group_stats(), (1, 30 * 8), "{stdout}");
    assert_eq!((scene.film.width, scene.film.height), (1920, 1080));
    assert!(
        scene.bsdfs.iter().any(|b| b.any(&|b| matches!(b, furnace_core::bsdf::Bsdf::Hair(_))))
            && scene.has_light(furnace_core::light::LightKind::Envmap)
    );
    let out = dir.join("o.exr");
    let o = furnace()
        .args(["render", "--spp", "2", "-D", "width=48", "-D", "height=27", "-o"])
        .arg(&out)
        .arg(dir.join("scene.xml"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = Image::read_exr(&out).unwrap();
    // Finite, and lit almost everywhere at 2 spp (84% here: some fur pixels' two paths end
    // dark in the fur).
    assert!(img.data.iter().all(|p| p.is_finite()));
    let lit = img.data.iter().filter(|p| p.max_element() > 0.0).count();
    assert!(lit * 10 > img.data.len() * 7, "{lit} of {} pixels lit", img.data.len());
    std::fs::remove_dir_all(&dir).ok();
}

/// `furnace plugins` prints the loader's table (as docs/SCENES.md holds it), and `--plan
/// --json` the render plan's description as JSON, the same words as the text.
#[test]
fn plugins_and_the_plan_as_json() {
    let o = furnace().arg("plugins").output().unwrap();
    assert!(o.status.success());
    let table = String::from_utf8(o.stdout).unwrap();
    assert_eq!(table, furnace_core::scene::plugins::markdown());
    assert!(table.contains("| shape | `bsplinecurve` |") && table.contains("| bsdf | `hair` |"), "{table}");
    let o = furnace().args(["render", "--plan", "--json"]).arg(scenes().join("small.xml")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let plan: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let text = load("small.xml", &[]).describe().to_string();
    assert!(plan["camera"].as_str().unwrap().starts_with("thin lens"), "{plan}");
    assert_eq!(plan["max_depth"], 6);
    for stage in plan["stages"].as_array().unwrap() {
        assert!(text.contains(stage.as_str().unwrap()), "{stage} not in {text}");
    }
    // --json goes with --plan only.
    assert!(!furnace()
        .args(["render", "--json"])
        .arg(scenes().join("small.xml"))
        .output()
        .unwrap()
        .status
        .success());
}

/// `furnace submit --frames ... --wait -o NAME` checks NAME before it uploads or submits
/// anything: a bad name found after the render would lose it. Nothing listens on the
/// coordinator's address here, so an error about the name shows that nothing was sent.
#[test]
fn submit_checks_the_frame_output_name_before_submitting() {
    let scene = scenes().join("frames.xml");
    for (out, expected) in [
        ("out.exr", "needs '#'s in the output name"),
        ("shot.####", "before the extension"),
        ("dir_##/out.exr", "not in its folder"),
    ] {
        let o = furnace()
            .arg("submit")
            .arg(&scene)
            .args(["--frames", "0-2", "--wait", "-o", out])
            .args(["--coordinator", "http://127.0.0.1:9"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{out}");
        assert!(err.contains(expected), "-o {out}: {err}");
    }
}
