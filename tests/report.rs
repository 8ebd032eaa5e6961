//! `furnace report`: error against a reference versus time, per sample count and technique.

mod common;

use std::process::Command;

use common::*;

fn furnace() -> Command {
    Command::new(env!("CARGO_BIN_EXE_furnace"))
}

struct Row {
    technique: String,
    spp: f64,
    rel_mse: f64,
    p90: f64,
    rel_mse_mean: f64,
    seeds: f64,
}

fn read_csv(path: &std::path::Path) -> Vec<Row> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next().unwrap(),
        "technique,spp,seconds,rel_mse,rmse,rel_err_p50,rel_err_p90,rel_err_p99,estimated_rel_mse,rel_mse_mean,seeds"
    );
    lines
        .map(|l| {
            let (name, rest) = l.strip_prefix('"').unwrap().split_once("\",").unwrap();
            let f: Vec<f64> = rest.split(',').map(|v| v.parse().unwrap()).collect();
            assert_eq!(f.len(), 10, "{l}");
            // The estimate needs 2 samples per pixel.
            assert!(f[..7].iter().chain(&f[8..]).all(|v| v.is_finite() && *v >= 0.0), "{l}");
            assert_eq!(f[7].is_finite(), f[0] >= 2.0, "{l}");
            assert!(f[4] <= f[5] && f[5] <= f[6], "percentiles out of order: {l}");
            Row {
                technique: name.to_string(),
                spp: f[0],
                rel_mse: f[2],
                p90: f[5],
                rel_mse_mean: f[8],
                seeds: f[9],
            }
        })
        .collect()
}

fn slope(rows: &[&Row]) -> f64 {
    let p: Vec<(f64, f64)> = rows.iter().map(|r| (r.spp.ln(), r.rel_mse.ln())).collect();
    let n = p.len() as f64;
    let (mx, my) = (p.iter().map(|q| q.0).sum::<f64>() / n, p.iter().map(|q| q.1).sum::<f64>() / n);
    let sxy: f64 = p.iter().map(|q| (q.0 - mx) * (q.1 - my)).sum();
    let sxx: f64 = p.iter().map(|q| (q.0 - mx).powi(2)).sum();
    sxy / sxx
}

/// cbox (diffuse) against Mitsuba's reference: the path tracer's relMSE falls as 1/N (slope
/// within -1.2 to -0.8 on the log-log plot), max_depth 2 converges to the wrong answer (its
/// error levels off far above), the MIS ablations behave as they must, and the CSV, SVG and
/// PNG are written.
#[test]
fn path_tracer_error_falls_as_one_over_n_and_a_low_max_depth_levels_off() {
    let dir = scratch("report-cbox");
    let o = furnace()
        .arg("report")
        .arg(scenes().join("cbox.xml"))
        .arg("--reference")
        .arg(scenes().join("refs/cbox.exr"))
        .args(["--max-spp", "16", "--threads", "2", "-o"])
        .arg(&dir)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("refs/cbox.exr") && out.contains("levels off"), "{out}");
    let rows = read_csv(&dir.join("report.csv"));
    let main: Vec<&Row> = rows.iter().filter(|r| r.technique.starts_with("path tracer")).collect();
    assert_eq!(main.iter().map(|r| r.spp).collect::<Vec<_>>(), [1.0, 2.0, 4.0, 8.0, 16.0]);
    let s = slope(&main);
    assert!((-1.2..=-0.8).contains(&s), "path tracer slope {s}");
    let shallow: Vec<&Row> = rows.iter().filter(|r| r.technique == "max_depth 2").collect();
    assert_eq!(shallow.len(), 5);
    let s2 = slope(&shallow);
    assert!(s2 > -0.3, "max_depth 2 should level off, slope {s2}");
    let last = |v: &[&Row]| v.last().unwrap().rel_mse;
    assert!(last(&shallow) > 3.0 * last(&main), "bias of max_depth 2 not visible");
    // MIS ablations: light sampling alone is as good as MIS on this small diffuse-lit box;
    // BSDF sampling alone rarely finds the small light: far noisier, but still falling as 1/N.
    let by = |name: &str| -> Vec<&Row> { rows.iter().filter(|r| r.technique == name).collect() };
    let (light, bsdf) = (by("light sampling only"), by("BSDF sampling only"));
    assert_eq!((light.len(), bsdf.len()), (5, 5));
    assert!(
        (last(&light) / last(&main) - 1.0).abs() < 0.05,
        "light only {} vs MIS {}",
        last(&light),
        last(&main)
    );
    assert!(last(&bsdf) > 10.0 * last(&main), "BSDF only {} vs MIS {}", last(&bsdf), last(&main));
    let s3 = slope(&bsdf);
    assert!((-1.3..=-0.7).contains(&s3), "BSDF-only slope {s3}");
    let svg = std::fs::read_to_string(dir.join("report.svg")).unwrap();
    assert!(svg.contains("<svg") && svg.contains("ideal 1/N") && svg.contains("max_depth 2"));
    let png = image::open(dir.join("report.png")).unwrap();
    assert_eq!((png.width(), png.height()), (960, 640));
    std::fs::remove_dir_all(&dir).ok();
}

/// Without --reference the report renders its own, says so, and keeps it.
#[test]
fn without_a_reference_the_report_renders_its_own() {
    let dir = scratch("report-own");
    let o = furnace()
        .arg("report")
        .arg(scenes().join("small.xml"))
        .args(["--max-spp", "2", "--ref-spp", "8", "-D", "width=16", "-o"])
        .arg(&dir)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("our own render at 8 spp"), "{out}");
    assert!(dir.join("reference.exr").exists());
    assert!(read_csv(&dir.join("report.csv")).len() >= 2);
    std::fs::remove_dir_all(&dir).ok();
}

/// The error a render estimates from its own sums (what noise-target jobs steer by) tracks the
/// error measured against Mitsuba's reference on cbox.
#[test]
fn estimated_error_tracks_the_measured_error() {
    let scene = load("cbox.xml", &[]);
    let reference = reference("cbox.exr");
    for spp in [4, 16, 64] {
        let acc = render(&scene, spp, 0).0;
        let measured = acc.develop().compare(&reference).unwrap().rel_mse;
        let estimated = acc.estimated_rel_mse();
        let ratio = estimated / measured;
        eprintln!("cbox {spp} spp: estimated {estimated:.3e}, measured {measured:.3e}, ratio {ratio:.3}");
        assert!((0.5..=2.0).contains(&ratio), "{spp} spp: estimate {estimated} vs measured {measured}");
    }
}

/// Runs `furnace report` on a test scene against its Mitsuba reference; returns the CSV rows.
fn report_rows(scene: &str, max_spp: &str) -> Vec<Row> {
    let dir = scratch(&format!("report-{scene}"));
    let o = furnace()
        .arg("report")
        .arg(scenes().join(format!("{scene}.xml")))
        .arg("--reference")
        .arg(scenes().join(format!("refs/{scene}.exr")))
        .args(["--max-spp", max_spp, "-o"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let rows = read_csv(&dir.join("report.csv"));
    std::fs::remove_dir_all(&dir).ok();
    rows
}

/// The last (highest-spp) row of a technique.
fn last<'a>(rows: &'a [Row], technique: &str) -> &'a Row {
    rows.iter().rfind(|r| r.technique == technique).unwrap_or_else(|| panic!("no rows for {technique}"))
}

/// Texture filter ablations edit the parsed scene: bilinear (what textured.xml says) gives the
/// very same renders as the scene itself, nearest lookups are biased (higher error at the same
/// spp), and the mip-mapped filters run.
#[test]
fn texture_filter_ablations_edit_the_scene() {
    let rows = report_rows("textured", "8");
    let err = |t: &str| last(&rows, t).rel_mse;
    assert_eq!(err("texture filter bilinear"), err("path tracer (as the scene says)"));
    assert!(err("texture filter nearest") > 1.5 * err("texture filter bilinear"));
    assert!(err("texture filter trilinear").is_finite() && err("texture filter ewa").is_finite());
}

/// Environment importance sampling against uniform sampling of the same map: uniform sampling
/// of a map with a small bright sun leaves several times the error (90th percentile of the
/// per-pixel relative error, which fireflies do not dominate) at the same spp.
#[test]
fn environment_importance_sampling_beats_uniform_sampling() {
    let rows = report_rows("envmap", "4");
    let (is, uniform) = (
        last(&rows, "path tracer (as the scene says)").p90,
        last(&rows, "environment sampled uniformly").p90,
    );
    assert!(uniform > 2.0 * is, "p90 uniform {uniform} vs importance sampled {is}");
}

/// With --seeds, each error is the median over the seeds: here the relMSE of three seeds
/// rendered one by one with `furnace render --seed` and compared with `furnace compare`.
/// The envmap scene also gets the MIS-compensation ablation, which must not beat the
/// compensated default at the same spp.
#[test]
fn several_seeds_report_the_median_error() {
    let dir = scratch("report-seeds");
    let scene = scenes().join("envmap.xml");
    let reference = scenes().join("refs/envmap.exr");
    let o = furnace()
        .arg("report")
        .arg(&scene)
        .arg("--reference")
        .arg(&reference)
        .args(["--max-spp", "4", "--seeds", "3", "-D", "max_depth=3", "-o"])
        .arg(&dir)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("median over the seeds"), "{out}");
    let rows = read_csv(&dir.join("report.csv"));
    assert!(rows.iter().all(|r| r.seeds == 3.0));
    let main = rows.iter().find(|r| r.technique.starts_with("path tracer") && r.spp == 4.0).unwrap();
    let mut errs: Vec<f64> = (0..3)
        .map(|seed| {
            let img = dir.join(format!("s{seed}.exr"));
            let r = furnace()
                .args(["render", "--spp", "4", "-D", "max_depth=3", "--seed", &seed.to_string(), "-o"])
                .arg(&img)
                .arg(&scene)
                .output()
                .unwrap();
            assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
            furnace_core::Image::read_exr(&img)
                .unwrap()
                .compare(&furnace_core::Image::read_exr(&reference).unwrap())
                .unwrap()
                .rel_mse
        })
        .collect();
    let mean = errs.iter().sum::<f64>() / 3.0;
    errs.sort_by(f64::total_cmp);
    assert!((main.rel_mse / errs[1] - 1.0).abs() < 1e-5, "median {} vs {errs:?}", main.rel_mse);
    assert!((main.rel_mse_mean / mean - 1.0).abs() < 1e-5, "mean {} vs {mean}", main.rel_mse_mean);
    let plain = rows.iter().find(|r| r.technique == "no MIS compensation" && r.spp == 4.0).unwrap();
    assert!(plain.p90 >= main.p90, "p90 without compensation {} vs {}", plain.p90, main.p90);
    std::fs::remove_dir_all(&dir).ok();
}

/// A noise-target render (the farm in one process) stops each tile at its target: the result
/// meets the target against Mitsuba's reference, uses a small part of the sample cap, and is
/// the same bits on 1 and 2 threads.
#[test]
fn a_noise_target_render_stops_at_its_target_and_meets_it() {
    let dir = scratch("target");
    let run = |threads: &str| {
        let out = dir.join(format!("t{threads}.exr"));
        let o = furnace()
            .args(["render", "--spp", "1024", "--spp-per-chunk", "8", "--target-rel-error", "0.1"])
            .args(["--threads", threads, "-o"])
            .arg(&out)
            .arg(scenes().join("cbox.xml"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(o.status.success(), "{err}");
        let samples: u64 = err
            .split("samples (")
            .next()
            .and_then(|s| s.trim_end().rsplit(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no sample count in {err}"));
        (std::fs::read(&out).unwrap(), samples)
    };
    let (two, samples) = run("2");
    let cap = 256 * 256 * 1024;
    assert!(samples < cap / 10, "{samples} samples of a cap of {cap}: the target did not stop it");
    let img = furnace_core::Image::read_exr(&dir.join("t2.exr")).unwrap();
    let measured = img.compare(&reference("cbox.exr")).unwrap().rel_mse;
    assert!(measured <= 0.1 * 0.1, "measured relMSE {measured} above the target 0.01");
    assert!(measured > 0.1 * 0.1 / 4.0, "measured relMSE {measured}: far more samples than the target needs");
    let (one, samples1) = run("1");
    assert_eq!(samples, samples1);
    assert!(one == two, "noise-target render differs between 1 and 2 threads");
    std::fs::remove_dir_all(&dir).ok();
}
