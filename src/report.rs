//! `furnace report`: what accuracy costs in time. Renders a scene at 1, 2, 4, ... samples per
//! pixel, times each render, measures its error against a reference, and writes a table, a CSV
//! and a log-log plot of error against time with the ideal 1/N slope; the same for ablations of
//! the techniques the scene's render plan uses.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use furnace_core::bsdf::Bsdf;
use furnace_core::light::{Light, LightKind};
use furnace_core::scene::xml::{Doc, Prop, Value};
use furnace_core::texture::{FilterType, Texture};
use furnace_core::{Image, Scene};
use furnace_proto::JobSettings;

#[derive(Args)]
pub struct ReportArgs {
    /// Scene file (Mitsuba 3 XML).
    pub scene: PathBuf,
    /// Reference image (EXR) to measure error against; default: our own render at --ref-spp.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Output folder for report.csv, report.svg and report.png.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Largest sample count of each series (a power of two is reached first).
    #[arg(long, default_value_t = 256)]
    pub max_spp: u64,
    /// Time budget of each series in seconds: it stops at the first render past the budget.
    #[arg(long, default_value_t = 120.0)]
    pub budget: f64,
    /// Samples per pixel of our own reference, when none is given (default: 16 x --max-spp).
    #[arg(long)]
    pub ref_spp: Option<u64>,
    /// Render threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Render every sample count with this many seeds and report the median of each error
    /// measure (and the mean relMSE beside it): under a small bright sun one seed's relMSE is
    /// a lottery of fireflies, for every renderer.
    #[arg(long, default_value_t = 1)]
    pub seeds: u64,
    /// Set a scene parameter, as Mitsuba's -D.
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub define: Vec<String>,
}

/// One render of a series.
#[derive(Clone, Debug)]
pub struct Row {
    pub technique: String,
    pub spp: u64,
    pub seconds: f64,
    /// relMSE; with several seeds their median (as every error measure here).
    pub rel_mse: f64,
    /// Mean relMSE over the seeds.
    pub rel_mse_mean: f64,
    pub seeds: u64,
    pub rmse: f64,
    pub p50: f64,
    pub p90: f64,
    pub p99: f64,
    /// relMSE estimated from the render's own variance, without the reference.
    pub estimated: f64,
}

/// A variant of the scene to measure: the scene as it is, or it with one technique its render
/// plan uses taken away or changed. Which ablations a scene gets is decided from what it holds
/// (its techniques, lights, BSDFs and textures), never from the plan's text.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Ablation {
    AsScene,
    BsdfSamplingOnly,
    LightSamplingOnly,
    NoMisCompensation,
    UniformEnvironment,
    DiffuseInsteadOfHair,
    NoLightCutoff,
    NoEarlyRoulette,
    TextureFilter(FilterType),
    MaxDepth(u32),
}

impl Ablation {
    /// The scene as it is, then an ablation for each effect it uses that has one.
    fn for_scene(scene: &Scene) -> Vec<Ablation> {
        let t = &scene.techniques;
        let mut all = vec![Ablation::AsScene];
        // Whether light sampling could run with MIS if it sampled every light (without MIS
        // compensation, a constant sky alone is light-sampled too).
        let mis_possible =
            scene.bsdfs.iter().any(Bsdf::is_smooth) && scene.lights.iter().any(|l| l.kind().is_hit_by_rays());
        if t.light_sampling {
            all.push(Ablation::BsdfSamplingOnly);
        }
        if mis_possible {
            all.push(Ablation::LightSamplingOnly);
            if scene.lights.iter().any(Light::is_compensated) {
                all.push(Ablation::NoMisCompensation);
            }
        }
        if t.light_sampling && t.light_cutoff > 0.0 {
            all.push(Ablation::NoLightCutoff);
        }
        // (The roulette acts from depth 2, and from rr_depth on: where a path can get there.)
        let i = &scene.integrator;
        if t.early_roulette > 0.0 && (i.max_depth > 2 || i.rr_depth < i.max_depth) {
            all.push(Ablation::NoEarlyRoulette);
        }
        if scene.has_light(LightKind::Envmap) {
            all.push(Ablation::UniformEnvironment);
        }
        if scene.bsdfs.iter().any(|b| b.any(&|b| matches!(b, Bsdf::Hair(_)))) {
            all.push(Ablation::DiffuseInsteadOfHair);
        }
        if scene
            .bsdfs
            .iter()
            .flat_map(|b| b.textures())
            .any(|t| matches!(t, Texture::Bitmap(_) | Texture::Bytes(_)))
        {
            all.extend(FilterType::ALL.map(Ablation::TextureFilter));
        }
        // max_depth counts path vertices (Mitsuba: -1 unbounded); 2 is direct light only.
        let depth = scene.integrator.max_depth;
        all.extend([2u32, 3].into_iter().filter(|&d| depth > d).map(Ablation::MaxDepth));
        all
    }

    fn name(&self) -> String {
        match self {
            Ablation::AsScene => "path tracer (as the scene says)".into(),
            Ablation::BsdfSamplingOnly => "BSDF sampling only".into(),
            Ablation::LightSamplingOnly => "light sampling only".into(),
            Ablation::NoMisCompensation => "no MIS compensation".into(),
            Ablation::UniformEnvironment => "environment sampled uniformly".into(),
            Ablation::DiffuseInsteadOfHair => "diffuse instead of hair".into(),
            Ablation::NoLightCutoff => "every light sample's shadow ray traced (no cutoff)".into(),
            Ablation::NoEarlyRoulette => "Mitsuba's Russian roulette (from rr_depth, on throughput)".into(),
            Ablation::TextureFilter(f) => format!("texture filter {}", f.name()),
            Ablation::MaxDepth(d) => format!("max_depth {d}"),
        }
    }

    /// Changes to the parsed document, before the scene is built.
    fn edit(&self, doc: &mut Doc) {
        match *self {
            // The same fibres with a diffuse BSDF (reflectance 0.5): what the hair model costs.
            Ablation::DiffuseInsteadOfHair => doc.edit("bsdf", "hair", |o| {
                o.plugin = "diffuse".into();
                o.props.clear();
                o.children.clear();
            }),
            Ablation::TextureFilter(f) => doc.edit("texture", "bitmap", |o| {
                let pos = o.pos;
                o.props.retain(|p| p.name != "filter_type");
                o.props.push(Prop::new("filter_type", Value::Str(f.name().into()), pos));
            }),
            _ => {}
        }
    }

    /// Changes to the loaded scene.
    fn apply(&self, s: &mut Scene) {
        match *self {
            Ablation::BsdfSamplingOnly => {
                s.techniques.light_sampling = false;
                s.techniques.mis = false;
            }
            // Light sampling alone must sample every direction: no MIS compensation.
            Ablation::LightSamplingOnly => {
                s.disable_mis_compensation();
                s.techniques.mis = false;
            }
            Ablation::NoMisCompensation => s.disable_mis_compensation(),
            Ablation::NoLightCutoff => s.techniques.light_cutoff = 0.0,
            Ablation::NoEarlyRoulette => s.techniques.early_roulette = 0.0,
            Ablation::UniformEnvironment => {
                for l in &mut s.lights {
                    if let Light::Envmap(e) = l {
                        Arc::make_mut(e).uniform = true;
                    }
                }
            }
            Ablation::MaxDepth(d) => s.integrator.max_depth = d,
            _ => {}
        }
    }

    fn load(&self, path: &std::path::Path, defines: &[(String, String)]) -> Result<Scene> {
        let mut scene = Scene::load_edited(path, defines, &|doc| self.edit(doc))?;
        self.apply(&mut scene);
        Ok(scene)
    }
}

pub fn report(a: ReportArgs, defines: &[(String, String)]) -> Result<()> {
    if a.max_spp == 0 {
        bail!("--max-spp must be at least 1");
    }
    if a.seeds == 0 {
        bail!("--seeds must be at least 1");
    }
    let base = Scene::load(&a.scene, defines)?;
    let seed = base.seed;
    let threads = a.threads.unwrap_or(0);
    let dir = a.output.clone().unwrap_or_else(|| {
        let stem = a.scene.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
        PathBuf::from(format!("report-{stem}"))
    });
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let techs = Ablation::for_scene(&base);
    drop(base);
    let reference = match &a.reference {
        Some(p) => {
            println!("reference: {}", p.display());
            Image::read_exr(p)?
        }
        None => {
            let spp = a.ref_spp.unwrap_or(16 * a.max_spp);
            // The first seed the series do not use.
            let ref_seed = seed + a.seeds;
            println!("reference: our own render at {spp} spp, seed {ref_seed} (no --reference given)");
            let scene = Arc::new(Scene::load(&a.scene, defines)?);
            let t = Instant::now();
            let settings = JobSettings { spp, seed: ref_seed, ..crate::local_settings() };
            let img = crate::render_local(scene, settings, threads, 0, &|_, _| {})?.0;
            println!("  rendered in {:.1} s", t.elapsed().as_secs_f64());
            img.write_exr(&dir.join("reference.exr"))?;
            img
        }
    };
    if a.seeds > 1 {
        println!(
            "seeds {seed}..{}: each error is the median over the seeds; seconds the mean",
            seed + a.seeds - 1
        );
    }
    println!(
        "{:<34} {:>6} {:>9} {:>10} {:>10} {:>10} {:>8} {:>8} {:>8} {:>10}",
        "technique", "spp", "seconds", "relMSE", "mean relMSE", "RMSE", "p50", "p90", "p99", "estimated"
    );
    let mut rows = Vec::new();
    for tech in &techs {
        let scene = Arc::new(tech.load(&a.scene, defines)?);
        let mut spent = 0.0;
        let mut spp = 1;
        while spp <= a.max_spp && spent <= a.budget {
            let mut runs: Vec<[f64; 7]> = Vec::new();
            for s in 0..a.seeds {
                let t = Instant::now();
                let settings = JobSettings { spp, seed: seed + s, ..crate::local_settings() };
                let (img, _, estimated, _) =
                    crate::render_local(scene.clone(), settings, threads, 0, &|_, _| {})?;
                let seconds = t.elapsed().as_secs_f64();
                spent += seconds;
                let c = img.compare(&reference).with_context(|| {
                    format!(
                        "reference is {}x{}, the scene renders {}x{}",
                        reference.width, reference.height, img.width, img.height
                    )
                })?;
                let [p50, p90, p99] = c.rel_err_percentiles;
                runs.push([seconds, c.rel_mse, c.rmse, p50, p90, p99, estimated.unwrap_or(f64::NAN)]);
            }
            let median = |k: usize| median(runs.iter().map(|r| r[k]).collect());
            let row = Row {
                technique: tech.name(),
                spp,
                seconds: runs.iter().map(|r| r[0]).sum::<f64>() / runs.len() as f64,
                rel_mse: median(1),
                rel_mse_mean: runs.iter().map(|r| r[1]).sum::<f64>() / runs.len() as f64,
                seeds: a.seeds,
                rmse: median(2),
                p50: median(3),
                p90: median(4),
                p99: median(5),
                estimated: median(6),
            };
            println!(
                "{:<34} {:>6} {:>9.3} {:>10.3e} {:>10.3e} {:>10.3e} {:>8.4} {:>8.4} {:>8.4} {:>10.3e}",
                row.technique,
                spp,
                row.seconds,
                row.rel_mse,
                row.rel_mse_mean,
                row.rmse,
                row.p50,
                row.p90,
                row.p99,
                row.estimated
            );
            rows.push(row);
            spp *= 2;
        }
    }
    summary(&rows, &techs[0].name());
    std::fs::write(dir.join("report.csv"), csv(&rows)).context("cannot write report.csv")?;
    crate::plot::error_vs_time(&rows, &dir.join("report.svg"), &dir.join("report.png"))?;
    println!(
        "wrote {}",
        ["report.csv", "report.svg", "report.png"].map(|f| dir.join(f).display().to_string()).join(", ")
    );
    Ok(())
}

/// The median (the mean of the middle two for an even count); NaN stays last.
fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Least-squares slope of log(relMSE) against log(x).
pub fn log_slope(points: impl Iterator<Item = (f64, f64)>) -> f64 {
    let p: Vec<(f64, f64)> = points.map(|(x, y)| (x.ln(), y.ln())).collect();
    let n = p.len() as f64;
    let (mx, my) = (p.iter().map(|q| q.0).sum::<f64>() / n, p.iter().map(|q| q.1).sum::<f64>() / n);
    let sxy: f64 = p.iter().map(|q| (q.0 - mx) * (q.1 - my)).sum();
    let sxx: f64 = p.iter().map(|q| (q.0 - mx).powi(2)).sum();
    sxy / sxx
}

/// Time each technique needs to reach the main technique's last relMSE (log-log interpolation),
/// its slope, and the error it levels off at: what it costs and what bias it keeps.
fn summary(rows: &[Row], main: &str) {
    let Some(target) = rows.iter().rfind(|r| r.technique == main).map(|r| r.rel_mse) else { return };
    println!("\ntime to reach relMSE {target:.3e} (the first technique's last render), slope of relMSE against time:");
    for name in technique_names(rows) {
        let s: Vec<&Row> = rows.iter().filter(|r| r.technique == name).collect();
        let slope = if s.len() > 1 { log_slope(s.iter().map(|r| (r.seconds, r.rel_mse))) } else { f64::NAN };
        let reach = s.windows(2).find(|w| w[1].rel_mse <= target).map(|w| {
            let f = (target.ln() - w[0].rel_mse.ln()) / (w[1].rel_mse.ln() - w[0].rel_mse.ln());
            (w[0].seconds.ln() + f.clamp(0.0, 1.0) * (w[1].seconds.ln() - w[0].seconds.ln())).exp()
        });
        // Not reached: still falling (the last doubling's slope below -0.5) means slow, and
        // the time is extrapolated at that slope; levelling off means bias.
        // The last doubling's slope, unless the whole series falls steadily and only the last
        // step is noise (fireflies): then the whole series' slope.
        let tail = s.len().checked_sub(2).map(|i| log_slope(s[i..].iter().map(|r| (r.seconds, r.rel_mse))));
        let tail = tail.map(|k| if slope < -0.8 { k.min(slope) } else { k });
        let reach = match (reach, s.first(), s.last(), tail) {
            (Some(t), ..) => format!("{t:.2} s"),
            (None, Some(first), ..) if first.rel_mse <= target * 1.001 => format!("{:.2} s", first.seconds),
            (None, _, Some(last), Some(k)) if k < -0.5 => {
                let t = last.seconds * (last.rel_mse / target).powf(-1.0 / k);
                format!("about {t:.1} s (extrapolated at slope {k:.2})")
            }
            (None, _, Some(last), _) if last.rel_mse <= target * 1.001 => format!("{:.2} s", last.seconds),
            (None, _, Some(last), _) => format!("not reached: levels off near {:.3e} (bias)", last.rel_mse),
            _ => String::new(),
        };
        println!("  {name:<34} slope {slope:>6.2}   {reach}");
    }
}

/// The techniques of `rows`, in order of first appearance.
pub fn technique_names(rows: &[Row]) -> Vec<&str> {
    let mut names: Vec<&str> = Vec::new();
    for r in rows {
        if !names.contains(&r.technique.as_str()) {
            names.push(&r.technique);
        }
    }
    names
}

fn csv(rows: &[Row]) -> String {
    let mut out = String::from(
        "technique,spp,seconds,rel_mse,rmse,rel_err_p50,rel_err_p90,rel_err_p99,estimated_rel_mse,rel_mse_mean,seeds\n",
    );
    for r in rows {
        let _ = writeln!(
            out,
            "\"{}\",{},{:.6},{:.6e},{:.6e},{:.6},{:.6},{:.6},{:.6e},{:.6e},{}",
            r.technique,
            r.spp,
            r.seconds,
            r.rel_mse,
            r.rmse,
            r.p50,
            r.p90,
            r.p99,
            r.estimated,
            r.rel_mse_mean,
            r.seeds
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use furnace_core::Techniques;

    fn scene(name: &str) -> Scene {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scenes").join(name);
        Scene::load(&path, &[]).unwrap_or_else(|e| panic!("{e}"))
    }

    /// Each scene gets the ablations of what it holds, chosen from its typed techniques, lights,
    /// BSDFs and textures; each ablation changes what it names and nothing else.
    #[test]
    fn ablations_follow_what_the_scene_holds() {
        use Ablation::*;
        // cbox: one area light (MIS), no environment, no hair, no bitmap; max_depth 8.
        assert_eq!(
            Ablation::for_scene(&scene("cbox.xml")),
            [AsScene, BsdfSamplingOnly, LightSamplingOnly, NoEarlyRoulette, MaxDepth(2), MaxDepth(3)]
        );
        // hair: fibres under a compensated environment map, a light-sample cutoff.
        let hair = Ablation::for_scene(&scene("hair.xml"));
        for a in [NoMisCompensation, NoLightCutoff, UniformEnvironment, DiffuseInsteadOfHair] {
            assert!(hair.contains(&a), "{a:?} missing: {hair:?}");
        }
        assert!(!hair.iter().any(|a| matches!(a, TextureFilter(_))));
        // textured: a bitmap, so every filter.
        let textured = Ablation::for_scene(&scene("textured.xml"));
        assert!(FilterType::ALL.iter().all(|&f| textured.contains(&TextureFilter(f))), "{textured:?}");
        assert!(!textured.contains(&DiffuseInsteadOfHair));
        // Its only light is a constant, left to BSDF sampling: "BSDF sampling only" would be
        // the scene itself; without compensation the constant is light-sampled, with MIS.
        assert!(!textured.contains(&BsdfSamplingOnly), "{textured:?}");
        assert!(textured.contains(&LightSamplingOnly) && textured.contains(&NoMisCompensation));
        let mut t = scene("textured.xml");
        assert!(!t.techniques.light_sampling && !t.techniques.mis);
        NoMisCompensation.apply(&mut t);
        assert!(t.techniques.light_sampling && t.techniques.mis);
        assert!(t.describe().to_string().contains("light sampling: constant"));

        let mut s = scene("hair.xml");
        let before = s.techniques;
        BsdfSamplingOnly.apply(&mut s);
        assert_eq!(s.techniques, Techniques { light_sampling: false, mis: false, ..before });
        let mut s = scene("hair.xml");
        NoMisCompensation.apply(&mut s);
        // The same techniques, the light-sample cutoff included (the ablation changes
        // compensation alone).
        assert!(before.light_cutoff > 0.0);
        assert_eq!(s.techniques, before);
        let mut off = scene("hair.xml");
        NoLightCutoff.apply(&mut off);
        assert_eq!(off.techniques, Techniques { light_cutoff: 0.0, ..before });
        assert!(!off.describe().to_string().contains("before the shadow ray"));
        assert!(!s.describe().to_string().contains("MIS-compensated"));
        MaxDepth(2).apply(&mut s);
        assert_eq!(s.integrator.max_depth, 2);
        assert!(s.describe().to_string().contains("max_depth 2"));
        let diffuse = DiffuseInsteadOfHair.load(&s.file, &[]).unwrap();
        assert!(!diffuse.bsdfs.iter().any(|b| b.any(&|b| matches!(b, Bsdf::Hair(_)))));
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scenes/textured.xml");
        let ewa = TextureFilter(FilterType::Ewa).load(&path, &[]).unwrap();
        assert!(ewa.techniques.footprints && ewa.describe().to_string().contains("EWA"));
    }
}
