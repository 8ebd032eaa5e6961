//! The coordinator under load, on loopback: how many lease-and-upload round trips per second it
//! serves to many small simulated workers, and how many MB/s of partials it stores and merges.
//!
//!   cargo bench --bench farm_load [-- --workers 1,4,16,64] [--data DIR]
//!   cargo bench --bench farm_load -- --soak SECONDS [--workers 200] [--keep]
//!
//! `--soak`: one coordinator (`furnace serve` in a process of its own), job after job (cbox,
//! 16x16-pixel chunks x 1 sample x 8 passes, 2048 chunks) driven by that many simulated
//! workers for that long; every finished job's result.exr must equal the merge of its partials
//! (nothing lost, nothing merged twice); then it is deleted (`--keep`: kept), and the
//! coordinator process's resident memory is printed.
//!
//! The simulated workers render nothing while timed: every chunk's partial is rendered and
//! encoded beforehand, so the numbers are the coordinator's (HTTP, decode, checks, fsync of
//! the partial, merge, checkpoints) plus the clients' loopback HTTP on the same cores. The
//! coordinator stores its data in a fresh folder under --data (default: the temp folder).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use furnace_coordinator::{AppState, Coordinator};
use furnace_core::Scene;
use furnace_proto::{chunk_plan, encode_partial, Bundle, JobSettings, JobSpec, JobState, Lease};

struct Server {
    url: String,
    coord: Arc<Mutex<Coordinator>>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(s) = self.stop.take() {
            s.send(()).ok();
        }
        if let Some(t) = self.thread.take() {
            t.join().ok();
        }
    }
}

fn serve(data: &Path) -> Server {
    let coord = Arc::new(Mutex::new(Coordinator::open(data).expect("open coordinator")));
    let state = AppState::new(coord.clone(), None);
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let (addr_tx, addr_rx) = std::sync::mpsc::channel();
    let thread = std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().expect("runtime");
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
            addr_tx.send(listener.local_addr().expect("address")).ok();
            furnace_coordinator::run(listener, state, async {
                rx.await.ok();
            })
            .await
            .expect("serve");
        });
    });
    let addr = addr_rx.recv().expect("coordinator address");
    Server { url: format!("http://{addr}"), coord, stop: Some(tx), thread: Some(thread) }
}

/// Stores the scene's files in the coordinator's data folder and submits the job directly.
fn submit(server: &Server, scene_path: &Path, scene: &Scene, settings: &JobSettings) -> String {
    let store = server.coord.lock().expect("lock").store();
    let (bundle, files) = Bundle::of_scene(scene_path, scene).expect("bundle");
    for (rel, path) in files {
        store.put_file(&bundle.files[&rel], &std::fs::read(path).expect("read file")).expect("store file");
    }
    let spec = JobSpec::new(bundle, settings.clone());
    furnace_coordinator::state::submit(&server.coord, spec, None, None).expect("submit").0
}

/// Runs `workers` threads of lease + upload until the job has no chunks left. Returns
/// (round trips, bytes uploaded, seconds).
fn drive(url: &str, workers: usize, partials: &Arc<Vec<Vec<u8>>>) -> (u64, u64, f64) {
    let trips = Arc::new(AtomicU64::new(0));
    let bytes = Arc::new(AtomicU64::new(0));
    let t = Instant::now();
    let handles: Vec<_> = (0..workers)
        .map(|i| {
            let (url, partials, trips, bytes) =
                (url.to_string(), partials.clone(), trips.clone(), bytes.clone());
            std::thread::spawn(move || {
                let http = reqwest::blocking::Client::builder()
                    .timeout(Duration::from_secs(60))
                    .build()
                    .expect("client");
                let name = format!("sim-{i}");
                loop {
                    let r = http
                        .post(format!("{url}/v1/leases"))
                        .json(&serde_json::json!({"worker": name}))
                        .send()
                        .expect("lease");
                    if r.status() == 204 {
                        break;
                    }
                    let l: Lease = r.json().expect("lease JSON");
                    let body = partials[l.chunk.id as usize].clone();
                    let n = body.len() as u64;
                    let r = http
                        .put(format!(
                            "{url}/v1/jobs/{}/chunks/{}/result?epoch={}",
                            l.job, l.chunk.id, l.epoch
                        ))
                        .body(body)
                        .send()
                        .expect("upload");
                    assert_eq!(r.status(), 204, "upload refused: {:?}", r.text());
                    trips.fetch_add(1, Ordering::Relaxed);
                    bytes.fetch_add(n, Ordering::Relaxed);
                }
            })
        })
        .collect();
    for h in handles {
        h.join().expect("simulated worker");
    }
    (trips.load(Ordering::Relaxed), bytes.load(Ordering::Relaxed), t.elapsed().as_secs_f64())
}

fn prerender(scene: &Scene, settings: &JobSettings) -> (Arc<Vec<Vec<u8>>>, u64) {
    let plan = chunk_plan(settings);
    let mut raw = 0;
    let parts = plan
        .iter()
        .map(|c| {
            let acc = furnace_worker::render_chunk(scene, c, settings.seed).0;
            raw += acc.width as u64 * acc.height as u64 * 22 * 4;
            encode_partial(&acc)
        })
        .collect();
    (Arc::new(parts), raw)
}

fn run_case(
    label: &str,
    base: &Path,
    scene_path: &Path,
    scene: &Scene,
    settings: &JobSettings,
    workers: usize,
) -> (f64, f64, f64) {
    let (partials, raw) = prerender(scene, settings);
    let data = base.join(format!("{label}-{workers}"));
    std::fs::remove_dir_all(&data).ok();
    let server = serve(&data);
    let job = submit(&server, scene_path, scene, settings);
    let (trips, bytes, secs) = drive(&server.url, workers, &partials);
    let state = server.coord.lock().expect("lock").status(&job).expect("status").state;
    assert_eq!(state, JobState::Done, "{label}: job not done after every chunk was uploaded");
    drop(server);
    std::fs::remove_dir_all(&data).ok();
    (trips as f64 / secs, bytes as f64 / secs / 1e6, raw as f64 / secs / 1e6)
}

/// Resident memory of process `pid`, in MB (Linux).
fn rss_mb(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let kb = status.lines().find_map(|l| l.strip_prefix("VmRSS:")).and_then(|v| v.split_whitespace().next());
    kb.and_then(|k| k.parse::<f64>().ok()).unwrap_or(0.0) / 1024.0
}

/// `furnace serve` in a process of its own, so that its resident memory is the coordinator's
/// alone (not the simulated workers' threads and clients). Killed on drop.
struct ServeProcess(std::process::Child);

impl Drop for ServeProcess {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

fn serve_process(data: &Path) -> (ServeProcess, String) {
    use std::io::BufRead;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_furnace"))
        .args(["serve", "--bind", "127.0.0.1:0", "--data-dir"])
        .arg(data)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("start furnace serve");
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("stdout")).read_line(&mut line).expect("address");
    let url = line.trim().strip_prefix("listening on ").expect("listening on ...").to_string();
    (ServeProcess(child), url)
}

/// Uploads the scene's files (those not stored yet) and submits the job, as `furnace submit`.
fn submit_http(
    http: &reqwest::blocking::Client,
    url: &str,
    path: &Path,
    scene: &Scene,
    s: &JobSettings,
) -> String {
    let (bundle, files) = Bundle::of_scene(path, scene).expect("bundle");
    for (rel, file) in files {
        let h = &bundle.files[&rel];
        if http.head(format!("{url}/v1/files/{h}")).send().expect("HEAD").status() != 200 {
            let r = http.put(format!("{url}/v1/files/{h}")).body(std::fs::read(file).expect("read")).send();
            assert!(r.expect("PUT").status().is_success());
        }
    }
    let r = http.post(format!("{url}/v1/jobs")).json(&JobSpec::new(bundle, s.clone())).send();
    r.expect("POST").json::<furnace_proto::Submitted>().expect("job id").id
}

/// Job after job against one coordinator process, each driven to the end by `workers`
/// simulated workers, checked (image, sample count), and deleted unless `keep`; the
/// coordinator's resident memory after each.
fn soak(
    base: &Path,
    scene_path: &Path,
    scene: &Scene,
    settings: &JobSettings,
    workers: usize,
    secs: f64,
    keep: bool,
) {
    let (partials, _) = prerender(scene, settings);
    let mut expected = furnace_core::Accum::new(0, 0, settings.width, settings.height);
    for p in partials.iter() {
        expected.merge(&furnace_proto::decode_partial(p, 1 << 30).expect("own partial"));
    }
    let expected = expected.develop();
    let data = base.join("soak");
    std::fs::remove_dir_all(&data).ok();
    let (server, url) = serve_process(&data);
    let pid = server.0.id();
    let http = reqwest::blocking::Client::builder().timeout(Duration::from_secs(60)).build().expect("client");
    let t = Instant::now();
    let (mut jobs, mut trips, mut rss) = (0u64, 0u64, Vec::new());
    let what = if keep { "kept" } else { "deleted once checked" };
    println!("soak: {workers} workers, {} chunks a job, {secs} s, finished jobs {what}", partials.len());
    println!("{:>6} {:>10} {:>14} {:>10}", "job", "seconds", "round trips/s", "RSS MB");
    let result = base.join("soak-result.exr");
    while t.elapsed().as_secs_f64() < secs {
        let job = submit_http(&http, &url, scene_path, scene, settings);
        let (n, _, s) = drive(&url, workers, &partials);
        // The last merge's checkpoint and result are written after its upload is answered.
        let st = loop {
            let st: furnace_proto::JobStatus =
                http.get(format!("{url}/v1/jobs/{job}")).send().expect("status").json().expect("status JSON");
            if st.state == JobState::Done || t.elapsed().as_secs_f64() > secs + 120.0 {
                break st;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        assert_eq!(st.state, JobState::Done, "job {jobs} not done");
        assert_eq!(st.samples_done, st.samples_total, "job {jobs}: samples lost or counted twice");
        let bytes = http.get(format!("{url}/v1/jobs/{job}/result.exr")).send().expect("result").bytes();
        std::fs::write(&result, bytes.expect("result bytes")).expect("write result");
        let image = furnace_core::Image::read_exr(&result).expect("read result");
        assert!(image.data == expected.data, "job {jobs}: image differs");
        if !keep {
            let r = http.delete(format!("{url}/v1/jobs/{job}")).send().expect("DELETE");
            assert_eq!(r.status(), 204, "job {jobs}: not deleted");
        }
        jobs += 1;
        trips += n;
        rss.push(rss_mb(pid));
        println!(
            "{jobs:>6} {:>10.1} {:>14.0} {:>10.1}",
            t.elapsed().as_secs_f64(),
            n as f64 / s,
            rss_mb(pid)
        );
    }
    let max = rss.iter().cloned().fold(0.0, f64::max);
    let half = rss.len() / 2;
    println!(
        "soak: {jobs} jobs, {trips} round trips in {:.0} s ({:.0}/s), every image exact; coordinator RSS after job 1 {:.1} MB, after job {} {:.1} MB, after the last {:.1} MB, most {max:.1} MB",
        t.elapsed().as_secs_f64(),
        trips as f64 / t.elapsed().as_secs_f64(),
        rss[0],
        half + 1,
        rss[half],
        rss[rss.len() - 1]
    );
    drop(server);
    std::fs::remove_dir_all(&data).ok();
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let mut workers = vec![1usize, 4, 16, 64];
    let mut base = std::env::temp_dir();
    let mut soak_secs: Option<f64> = None;
    let mut keep = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--workers" => {
                workers = args
                    .next()
                    .expect("--workers N,N,...")
                    .split(',')
                    .map(|n| n.parse().expect("--workers takes numbers"))
                    .collect()
            }
            "--data" => base = PathBuf::from(args.next().expect("--data DIR")),
            "--soak" => soak_secs = Some(args.next().and_then(|v| v.parse().ok()).expect("--soak SECONDS")),
            "--keep" => keep = true,
            _ => {} // cargo bench passes --bench
        }
    }
    let base = base.join(format!("furnace-farm-load-{}", std::process::id()));
    let scene_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/scenes/cbox.xml");
    let scene = Scene::load(&scene_path, &[]).expect("load cbox");
    let (w, h) = (scene.film.crop_width, scene.film.crop_height);
    let settings = |tile, spp| JobSettings {
        width: w,
        height: h,
        spp,
        tile_size: tile,
        spp_per_chunk: 1,
        seed: 0,
        priority: 0,
        target_rel_error: None,
    };
    if let Some(secs) = soak_secs {
        let n = if workers == [1, 4, 16, 64] { 200 } else { workers[0] };
        soak(&base, &scene_path, &scene, &settings(16, 8), n, secs, keep);
        std::fs::remove_dir_all(&base).ok();
        return;
    }
    // Small chunks: 8 x 8 pixels x 1 sample, 4096 of them. Round trips per second.
    println!("round trips: cbox {w}x{h}, 8x8-pixel chunks of 1 sample, 4096 chunks");
    println!("{:>8} {:>14} {:>12}", "workers", "round trips/s", "MB/s wire");
    for &n in &workers {
        let (rt, mb, _) = run_case("small", &base, &scene_path, &scene, &settings(8, 4), n);
        println!("{n:>8} {rt:>14.0} {mb:>12.2}");
    }
    // Large chunks: the whole 256 x 256 image x 1 sample, 64 of them. Merge throughput.
    println!("merge throughput: whole-image chunks of 1 sample, 64 chunks");
    println!("{:>8} {:>14} {:>12} {:>14}", "workers", "chunks/s", "MB/s wire", "MB/s decoded");
    for &n in workers.iter().filter(|&&n| n <= 16) {
        let (rt, mb, raw) = run_case("large", &base, &scene_path, &scene, &settings(256, 64), n);
        println!("{n:>8} {rt:>14.1} {mb:>12.2} {raw:>14.1}");
    }
    // A full-HD job: 510 tiles of 64 x 64 pixels x 4 passes of 1 sample; each checkpoint
    // (every 256 merges and at the end) encodes the whole 1920 x 1080 accumulation, and the
    // job ends with result.exr written.
    std::fs::create_dir_all(&base).expect("scratch folder");
    let hd_path = base.join("cbox-1080.xml");
    let xml = std::fs::read_to_string(&scene_path).expect("read cbox");
    let xml = xml
        .replace(r#"name="width" value="256""#, r#"name="width" value="1920""#)
        .replace(r#"name="height" value="256""#, r#"name="height" value="1080""#);
    std::fs::write(&hd_path, xml).expect("write 1080p cbox");
    let hd = Scene::load(&hd_path, &[]).expect("load 1080p cbox");
    let hd_settings = JobSettings { width: 1920, height: 1080, ..settings(64, 4) };
    println!("full HD: 1920x1080, 64x64-pixel chunks of 1 sample, 2040 chunks, 8 checkpoints");
    println!("{:>8} {:>14} {:>12} {:>14}", "workers", "chunks/s", "MB/s wire", "MB/s decoded");
    for &n in workers.iter().filter(|&&n| n <= 16) {
        let (rt, mb, raw) = run_case("hd", &base, &hd_path, &hd, &hd_settings, n);
        println!("{n:>8} {rt:>14.1} {mb:>12.2} {raw:>14.1}");
    }
    std::fs::remove_dir_all(&base).ok();
}
