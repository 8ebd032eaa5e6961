//! `furnace`: the one binary. It parses arguments and calls the libraries.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use furnace::local::LocalLink;
use furnace_coordinator::Coordinator;
use furnace_core::{Image, Scene, Stats};
use furnace_proto::{JobSettings, JobState};
use furnace_worker::WorkerConfig;

mod farm;
mod generate;
mod plot;
mod report;

#[derive(Parser)]
#[command(name = "furnace", version, about = "Furnace: a physically based renderer and its render farm")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Render a Mitsuba 3 scene on this machine: EXR plus a tonemapped PNG beside it.
    Render(RenderArgs),
    /// Compare an EXR against a reference EXR: RMSE, relMSE, mean luminance.
    Compare { image: PathBuf, reference: PathBuf },
    /// Run the farm's coordinator (HTTP API under /v1).
    Serve(farm::ServeArgs),
    /// Render chunks for a coordinator.
    Worker(farm::WorkerArgs),
    /// Submit a scene to a coordinator.
    Submit(farm::SubmitArgs),
    /// Show jobs on a coordinator.
    Status(farm::StatusArgs),
    /// Error against a reference versus render time, per sample count and technique.
    Report(report::ReportArgs),
    /// Health check: a URL answers 2xx, or a worker's health file is fresh.
    Probe(farm::ProbeArgs),
    /// Write a scene of the seed's class (furry creature, props, sun/sky, thin lens) of any size.
    Generate(generate::GenerateArgs),
    /// Print every scene plugin Furnace reads, with its parameters (Markdown; the table of
    /// docs/SCENES.md).
    Plugins,
}

#[derive(Args)]
struct RenderArgs {
    /// Scene file (Mitsuba 3 XML).
    scene: PathBuf,
    /// Samples per pixel (default: the scene's sample_count).
    #[arg(long)]
    spp: Option<u32>,
    /// Set a scene parameter, as Mitsuba's -D: `-D spp=16`.
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    define: Vec<String>,
    /// Output EXR (default: the scene's name with .exr, in the current folder).
    #[arg(short, long)]
    output: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Chunks rendered at once on those threads, 1 to 256 (default: one a thread, 4 to 16).
    /// Does not change the image.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=256))]
    slots: Option<u32>,
    /// Sample seed (default: the scene sampler's seed).
    #[arg(long)]
    seed: Option<u64>,
    /// Print the render plan and exit.
    #[arg(long)]
    plan: bool,
    /// With --plan: print it as JSON.
    #[arg(long, requires = "plan")]
    json: bool,
    /// Tile size in pixels (does not change the image, except where a target error stops each
    /// tile). The default is `furnace submit`'s; on 16 threads it rendered up to about 12%
    /// faster than 32 (docs/BENCHMARKS.md, "Third run").
    #[arg(long, default_value_t = 64)]
    tile: u32,
    /// Stop each tile once its estimated relative error is at most this (--spp is then the
    /// cap). The image depends on --tile and --spp-per-chunk, not on threads.
    #[arg(long)]
    target_rel_error: Option<f64>,
    /// Samples per pixel of one chunk (with --target-rel-error: how often a tile is judged).
    #[arg(long, default_value_t = 64)]
    spp_per_chunk: u64,
    /// Exposure of the PNG preview, in stops.
    #[arg(long, default_value_t = 0.0, value_parser = finite_stops, allow_hyphen_values = true)]
    exposure: f32,
}

/// Exposure in stops: a finite number, within +-64 (2^64 overflows nothing a PNG can show).
fn finite_stops(s: &str) -> Result<f32, String> {
    let v: f32 = s.trim().parse().map_err(|_| format!("expected a number of stops, found '{s}'"))?;
    if !(v.abs() <= 64.0) {
        return Err(format!("exposure must be a finite number of stops within -64..64, found '{s}'"));
    }
    Ok(v)
}

fn main() {
    // Before anything else: a build for x86-64-v2 (.cargo/config.toml) would otherwise stop
    // with an illegal instruction on a CPU without those. The rest is a function of its own,
    // so that none of its code (compiled with those instructions) is scheduled before this.
    if !furnace_core::cpu::supported() {
        furnace_core::cpu::refuse();
    }
    main_checked();
}

#[inline(never)]
fn main_checked() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .init();
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.cmd {
        Cmd::Render(a) => render(a),
        Cmd::Serve(a) => farm::serve(a),
        Cmd::Worker(a) => farm::worker(a),
        Cmd::Submit(a) => farm::submit(a),
        Cmd::Status(a) => farm::status(a),
        Cmd::Probe(a) => farm::probe(a),
        Cmd::Generate(a) => generate::generate(a),
        Cmd::Plugins => {
            print!("{}", furnace_core::scene::plugins::markdown());
            Ok(())
        }
        Cmd::Report(a) => {
            let defines = parse_defines(&a.define)?;
            report::report(a, &defines)
        }
        Cmd::Compare { image, reference } => {
            let a = Image::read_exr(&image)?;
            let b = Image::read_exr(&reference)?;
            let c = a.compare(&b).with_context(|| {
                format!("sizes differ: {}x{} vs {}x{}", a.width, a.height, b.width, b.height)
            })?;
            println!("RMSE          {:.6}", c.rmse);
            println!("relMSE        {:.6}", c.rel_mse);
            println!(
                "mean lum      {:.6} / reference {:.6} (ratio {:.4})",
                c.mean_lum,
                c.ref_mean_lum,
                c.mean_lum / c.ref_mean_lum
            );
            Ok(())
        }
    }
}

pub(crate) fn parse_defines(defs: &[String]) -> Result<Vec<(String, String)>> {
    defs.iter()
        .map(|d| match d.split_once('=') {
            Some((k, v)) if !k.is_empty() => Ok((k.to_string(), v.to_string())),
            _ => bail!("-D expects NAME=VALUE, got '{d}'"),
        })
        .collect()
}

fn render(a: RenderArgs) -> Result<()> {
    let defines = parse_defines(&a.define)?;
    let t0 = Instant::now();
    let scene = Scene::load(&a.scene, &defines)?;
    let (groups, grouped) = scene.accel.group_stats();
    let instances = scene
        .shapes
        .iter()
        .filter(|s| matches!(s.geometry, furnace_core::geometry::Geometry::Instance(_)))
        .count();
    let instanced = if groups > 0 {
        format!(" ({instances} instances among them; {grouped} more in {groups} shape groups, held once)")
    } else {
        String::new()
    };
    tracing::info!(
        "loaded {} in {:.2}s: {} shapes, {} primitives{instanced}, {} lights; built for {}; Sobol sets in {}; tracing with an {}",
        a.scene.display(),
        t0.elapsed().as_secs_f64(),
        scene.shapes.len(),
        scene.accel.prim_count(),
        scene.lights.len(),
        furnace_core::cpu::build_target(),
        furnace_core::sampler::instruction_set(),
        scene.accel.describe()
    );
    let plan = scene.describe();
    if a.plan {
        if a.json {
            println!("{}", serde_json::to_string_pretty(&plan)?);
        } else {
            print!("{plan}");
        }
        return Ok(());
    }
    eprint!("{plan}");
    let spp = a.spp.unwrap_or(scene.spp) as u64;
    if spp == 0 {
        bail!("--spp must be at least 1");
    }
    let seed = a.seed.unwrap_or(scene.seed);
    let out = a.output.clone().unwrap_or_else(|| default_output(&a.scene));
    let (w, h) = (scene.film.crop_width, scene.film.crop_height);
    let total = w as u64 * h as u64 * spp;
    let bar = indicatif::ProgressBar::new(total);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:40} {percent:>3}%  {human_pos}/{human_len} samples  {per_sec}  ETA {eta}",
        )
        .expect("static progress template"),
    );
    let t1 = Instant::now();
    let threads = a.threads.unwrap_or(0);
    let settings = JobSettings {
        spp,
        tile_size: a.tile,
        spp_per_chunk: a.spp_per_chunk,
        seed,
        target_rel_error: a.target_rel_error,
        ..local_settings()
    };
    let (image, stats, estimate, dropped) =
        render_local(Arc::new(scene), settings, threads, a.slots.unwrap_or(0) as usize, &|done, total| {
            bar.set_length(total);
            bar.set_position(done)
        })?;
    bar.finish_and_clear();
    let secs = t1.elapsed().as_secs_f64();
    let threads = if threads == 0 { rayon::current_num_threads() } else { threads };
    let slots = a.slots.map_or_else(|| local_slots(threads), |k| k as usize);
    image.write_exr(&out)?;
    let png = out.with_extension("png");
    image.write_png(&png, a.exposure)?;
    tracing::info!(
        "rendered {w}x{h}: {} samples ({:.1} spp of at most {spp}) in {secs:.3}s on {threads} threads (up to {slots} chunks in flight): {:.3} Msamples/s",
        stats.samples,
        stats.samples as f64 / (w as f64 * h as f64),
        stats.samples as f64 / secs / 1e6
    );
    tracing::info!(
        "per sample: {:.2} rays, {:.2} shadow rays, {:.2} BSDF samples",
        stats.rays as f64 / stats.samples as f64,
        stats.shadow_rays as f64 / stats.samples as f64,
        stats.bsdf_samples as f64 / stats.samples as f64
    );
    if let Some(e) = estimate {
        tracing::info!("estimated relative MSE (from the render's own variance): {e:.3e}");
    }
    if dropped.total() > 0 {
        tracing::warn!(
            "{} of {} samples were dropped and never reached the image: {dropped}",
            dropped.total(),
            stats.samples
        );
    }
    println!("wrote {} and {}", out.display(), png.display());
    Ok(())
}

/// Chunks in flight for a render in this process on `threads` threads: one a thread, 4 to
/// 16 ([`furnace_worker::MAX_AUTO_SLOTS`]); a farm worker keeps half its threads
/// ([`furnace_worker::auto_slots`]), because there extra chunks in flight would be held from
/// idle workers at a job's end; here there is no other worker. On a 2-core machine the chunk
/// threads, which merge, hand over and lease between chunks, wait for a core, and with only two
/// chunks in flight the pool's threads can run out of bands: 2 threads, 64 spp, medians of 7
/// interleaved runs, 4 against 2: textured -0.5% to +3.6%, envmap +2.1% to +4.4%, thinlens
/// +2.7% to +2.8%. On 16 cores (docs/BENCHMARKS.md, "Multi-core scaling"): 8 threads, 8
/// against 4, cbox +11%, textured +3%, whimsical +3%, hair within the spread; 16 threads, 16
/// against 8, +1% (thinlens) to +14% (cbox), medians of 3 on a noisy machine ("Chunks in
/// flight, and malloc").
pub fn local_slots(threads: usize) -> usize {
    threads.clamp(4, furnace_worker::MAX_AUTO_SLOTS)
}

/// Renders on this machine through the farm in one process: a coordinator that stores nothing
/// and one worker on `threads` threads (0: all cores) with `slots` chunks in flight (0:
/// [`local_slots`]). The bytes are the farm's. Returns the image, the render statistics, the
/// estimated relative MSE and the dropped samples.
pub fn render_local(
    scene: Arc<Scene>,
    settings: JobSettings,
    threads: usize,
    slots: usize,
    progress: &dyn Fn(u64, u64),
) -> Result<(Image, Stats, Option<f64>, furnace_core::Dropped)> {
    let coord = Arc::new(Mutex::new(Coordinator::ephemeral()?));
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    let job = lock().submit_scene(scene, settings)?;
    let link = Arc::new(LocalLink::new(coord.clone()));
    let slots = match slots {
        0 => local_slots(if threads == 0 { rayon::current_num_threads() } else { threads }),
        k => k,
    };
    let cfg = WorkerConfig {
        link: link.clone(),
        threads,
        slots,
        name: "local".into(),
        poll: Duration::from_millis(10),
        stop: Arc::new(AtomicBool::new(false)),
        exit_when_idle: true,
    };
    let (done_tx, done) = std::sync::mpsc::channel();
    let worker = std::thread::spawn(move || {
        let r = furnace_worker::run(cfg);
        done_tx.send(()).ok();
        r
    });
    while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) = done.recv_timeout(Duration::from_millis(50)) {
        let (done, total) = lock().progress(&job)?;
        progress(done, total);
    }
    worker.join().map_err(|_| anyhow::anyhow!("the render worker panicked"))??;
    let status = lock().status(&job)?;
    if status.state != JobState::Done {
        let why = match status.errors.is_empty() {
            true => format!("the job is {:?} and recorded no error", status.state),
            false => status.errors.join("; "),
        };
        bail!("the render stopped unfinished: {why}");
    }
    let stats = link.stats.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let image = lock().image(&job)?;
    Ok((image, stats, status.estimated_rel_mse, status.dropped_samples))
}

/// Settings of a render on this machine: the scene's size (filled in at submission), no
/// priority, no target error.
pub fn local_settings() -> JobSettings {
    JobSettings {
        width: 0,
        height: 0,
        tile_size: 64,
        priority: 0,
        target_rel_error: None,
        ..JobSettings::default()
    }
}

fn default_output(scene: &Path) -> PathBuf {
    let stem = scene.file_stem().map(|s| s.to_os_string()).unwrap_or_else(|| "render".into());
    PathBuf::from(stem).with_extension("exr")
}
