//! The farm across machines, as near as one machine comes: the coordinator and two workers each
//! in a network namespace of their own (their own network stack, addresses and routes). The
//! client reaches the coordinator over a veth pair; each worker over a cable with 20 ms of
//! delay each way (a delay line: a TUN device in each namespace and a thread of this test that
//! passes each packet across 20 ms after it was sent, since this kernel has no `netem`), a slow
//! link (tbf rate limits) and random packet loss where `nft` is installed. One worker is cut off
//! while its uploads crawl over its slow link (its link goes down: nothing passes, what was
//! queued is lost), long enough for its leases to expire; then the partition heals and it
//! works on. The result must be byte-identical to `furnace render`.
//!
//! It needs root (`ip netns`, `/dev/net/tun`); where namespaces cannot be made it says so and
//! passes without running.

mod common;

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::io::AsRawFd;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{scenes, scratch};

const BIN: &str = env!("CARGO_BIN_EXE_furnace");
const TOKEN: &str = "netns-test-token";
const PORT: u16 = 8640;

/// Kills its process when dropped.
struct Proc(Child);
impl Drop for Proc {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// Runs a shell command (in namespace `ns`, if given); Err with its output when it fails.
fn run(ns: Option<&str>, cmd: &str) -> Result<(), String> {
    let out = match ns {
        Some(ns) => Command::new("ip").args(["netns", "exec", ns, "sh", "-c", cmd]).output(),
        None => Command::new("sh").args(["-c", cmd]).output(),
    }
    .map_err(|e| format!("{cmd}: {e}"))?;
    if !out.status.success() {
        return Err(format!("{cmd}: {}", String::from_utf8_lossy(&out.stderr).trim()));
    }
    Ok(())
}

/// One-way delay of each worker's cable.
const DELAY: Duration = Duration::from_millis(20);

/// A TUN device named `name` (in this namespace until moved), read and written as IP packets.
fn tun(name: &str) -> Result<std::fs::File, String> {
    const TUNSETIFF: libc::c_ulong = 0x4004_54ca;
    const IFF_TUN: u16 = 0x0001;
    const IFF_NO_PI: u16 = 0x1000;
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open("/dev/net/tun")
        .map_err(|e| format!("/dev/net/tun: {e}"))?;
    // struct ifreq: the name, then the flags.
    let mut req = [0u8; 40];
    req[..name.len()].copy_from_slice(name.as_bytes());
    req[16..18].copy_from_slice(&(IFF_TUN | IFF_NO_PI).to_ne_bytes());
    // SAFETY: TUNSETIFF reads and writes a struct ifreq, which `req` is large enough to hold.
    if unsafe { libc::ioctl(f.as_raw_fd(), TUNSETIFF, req.as_mut_ptr()) } < 0 {
        return Err(format!("TUNSETIFF {name}: {}", std::io::Error::last_os_error()));
    }
    Ok(f)
}

/// A cable with a delay between two TUN devices: each packet read from one is written to the
/// other `DELAY` after it was read (in order). A packet that cannot be written (its side is
/// down) is lost, as on a cut cable.
struct DelayLine {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl DelayLine {
    fn new(ends: [std::fs::File; 2]) -> DelayLine {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut ends = ends;
            // In flight towards end k: when due, and the packet.
            let mut queues: [VecDeque<(Instant, Vec<u8>)>; 2] = [VecDeque::new(), VecDeque::new()];
            let mut buf = vec![0u8; 65536];
            while !flag.load(Ordering::Relaxed) {
                let now = Instant::now();
                let next = queues.iter().filter_map(|q| q.front().map(|p| p.0)).min();
                let wait = next.map_or(50, |t| t.saturating_duration_since(now).as_millis().min(50) as i32);
                let mut fds = ends.each_ref().map(|f| libc::pollfd {
                    fd: f.as_raw_fd(),
                    events: libc::POLLIN,
                    revents: 0,
                });
                // SAFETY: `fds` is an array of two initialised pollfd.
                unsafe { libc::poll(fds.as_mut_ptr(), 2, wait) };
                for k in 0..2 {
                    if fds[k].revents & libc::POLLIN != 0 {
                        if let Ok(n) = ends[k].read(&mut buf) {
                            queues[1 - k].push_back((Instant::now() + DELAY, buf[..n].to_vec()));
                        }
                    }
                }
                let now = Instant::now();
                for k in 0..2 {
                    while queues[k].front().is_some_and(|p| p.0 <= now) {
                        let (_, p) = queues[k].pop_front().unwrap();
                        ends[k].write(&p).ok();
                    }
                }
            }
        });
        DelayLine { stop, thread: Some(thread) }
    }
}

impl Drop for DelayLine {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.take().map(|t| t.join());
    }
}

/// Three namespaces (c: the coordinator, w1 and w2: workers) and a link from this one to c;
/// all removed on drop (removing a namespace removes its ends of the links).
struct Net {
    c: String,
    w: [String; 2],
    /// The coordinator's address as seen from this namespace.
    client_addr: String,
    loss: bool,
    /// Whether the workers' cables have their delay (a delay line): without `/dev/net/tun`
    /// they are plain veth pairs.
    delay: bool,
    _lines: Vec<DelayLine>,
}

impl Drop for Net {
    fn drop(&mut self) {
        for ns in [&self.c, &self.w[0], &self.w[1]] {
            run(None, &format!("ip netns del {ns}")).ok();
        }
    }
}

impl Net {
    fn new() -> Result<Net, String> {
        let pid = std::process::id();
        let tag = pid % 100_000;
        let net = Net {
            c: format!("fzc{tag}"),
            w: [format!("fzw1-{tag}"), format!("fzw2-{tag}")],
            // This namespace's link to c gets a subnet of its own per test process.
            client_addr: format!("10.{}.{}.2", 100 + (pid / 250) % 100, pid % 250),
            loss: false,
            delay: true,
            _lines: Vec::new(),
        };
        for ns in [&net.c, &net.w[0], &net.w[1]] {
            run(None, &format!("ip netns add {ns}"))?;
            run(Some(ns), "ip link set lo up")?;
        }
        // This namespace <-> c.
        let host = net.client_addr.trim_end_matches(".2").to_string() + ".1";
        let (a, b) = (format!("fz{tag}h"), format!("fz{tag}c"));
        run(None, &format!("ip link add {a} type veth peer name {b} netns {}", net.c))?;
        run(None, &format!("ip addr add {host}/24 dev {a} && ip link set {a} up"))?;
        run(Some(&net.c), &format!("ip addr add {}/24 dev {b} && ip link set {b} up", net.client_addr))?;
        // c <-> each worker: 10.1.k.1 (c) and 10.1.k.2 (the worker), over a delay line.
        let mut net = net;
        for k in 0..2 {
            let (cw, wc) = (format!("fz{tag}c{k}"), format!("fz{tag}w{k}"));
            let w = net.w[k].clone();
            match tun(&cw).and_then(|c| Ok([c, tun(&wc)?])) {
                Ok(ends) => {
                    run(None, &format!("ip link set {cw} netns {} && ip link set {wc} netns {w}", net.c))?;
                    let (c_end, w_end) =
                        (format!("10.1.{k}.1 peer 10.1.{k}.2"), format!("10.1.{k}.2 peer 10.1.{k}.1"));
                    run(Some(&net.c), &format!("ip addr add {c_end} dev {cw} && ip link set {cw} up"))?;
                    run(Some(&w), &format!("ip addr add {w_end} dev {wc} && ip link set {wc} up"))?;
                    net._lines.push(DelayLine::new(ends));
                }
                Err(e) => {
                    eprintln!("no delay line ({e}): a plain veth pair, without delay");
                    net.delay = false;
                    run(
                        None,
                        &format!("ip link add {cw} netns {} type veth peer name {wc} netns {w}", net.c),
                    )?;
                    run(Some(&net.c), &format!("ip addr add 10.1.{k}.1/24 dev {cw} && ip link set {cw} up"))?;
                    run(Some(&w), &format!("ip addr add 10.1.{k}.2/24 dev {wc} && ip link set {wc} up"))?;
                }
            }
        }
        Ok(net)
    }

    /// Slow links: each worker's uploads go out at `rates[k]` (tbf); with nft, 2% of each
    /// worker's packets are dropped.
    fn degrade(&mut self, rates: [&str; 2]) -> Result<(), String> {
        let tag = std::process::id() % 100_000;
        for (k, w) in self.w.clone().iter().enumerate() {
            let dev = format!("fz{tag}w{k}");
            run(
                Some(w),
                &format!("tc qdisc add dev {dev} root tbf rate {} burst 16kb latency 2s", rates[k]),
            )?;
            let nft = "nft add table inet fz && \
                 nft add chain inet fz out '{ type filter hook output priority 0; }' && \
                 nft add rule inet fz out numgen random mod 100 '<' 2 drop";
            self.loss = run(Some(w), nft).is_ok();
        }
        Ok(())
    }

    /// Bytes waiting in worker `k`'s outgoing queue (its slow link's tbf): an upload under way.
    fn backlog(&self, k: usize) -> u64 {
        let dev = format!("fz{}w{k}", std::process::id() % 100_000);
        let out = Command::new("ip")
            .args(["netns", "exec", &self.w[k], "tc", "-s", "qdisc", "show", "dev", &dev])
            .output()
            .map(|o| String::from_utf8_lossy(&o.stdout).to_string())
            .unwrap_or_default();
        let words: Vec<&str> = out.split_whitespace().collect();
        let at = words.iter().position(|w| *w == "backlog");
        at.and_then(|i| words.get(i + 1)).and_then(|b| b.trim_end_matches('b').parse().ok()).unwrap_or(0)
    }

    /// Cuts worker `k`'s cable (its link goes down: what its queue holds is dropped and
    /// nothing passes either way), or plugs it back in.
    fn partition(&self, k: usize, cut: bool) -> Result<(), String> {
        let dev = format!("fz{}w{k}", std::process::id() % 100_000);
        run(Some(&self.w[k]), &format!("ip link set {dev} {}", if cut { "down" } else { "up" }))
    }
}

fn http() -> reqwest::blocking::Client {
    reqwest::blocking::Client::builder().no_proxy().timeout(Duration::from_secs(10)).build().unwrap()
}

fn get_json(url: &str) -> serde_json::Value {
    let r = http().get(url).bearer_auth(TOKEN).send().unwrap();
    assert!(r.status().is_success(), "GET {url}: {}", r.status());
    r.json().unwrap()
}

/// Chunks a worker has handed in, as the coordinator counts them.
fn chunks_done(url: &str, worker: &str) -> u64 {
    let workers = get_json(&format!("{url}/v1/workers"));
    let w = workers.as_array().unwrap().iter().find(|w| w["name"] == worker);
    w.map_or(0, |w| w["chunks_done"].as_u64().unwrap())
}

fn wait_for(what: &str, limit: Duration, mut done: impl FnMut() -> bool) {
    let t = Instant::now();
    while !done() {
        assert!(t.elapsed() < limit, "{what}: not within {limit:?}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn workers_in_other_namespaces_through_a_partition_render_the_same_bytes() {
    let mut net = match Net::new() {
        Ok(n) => n,
        Err(e) => {
            eprintln!("skipped: network namespaces cannot be made here ({e})");
            return;
        }
    };
    net.degrade(["64kbit", "1mbit"]).unwrap();
    eprintln!(
        "links: delay line ({DELAY:?} each way): {}; tbf rate limits; 2% loss (nft): {}",
        net.delay, net.loss
    );
    let dir = scratch("netns");
    let data = dir.join("data");
    // The coordinator in c, listening on all its addresses.
    let mut serve = Command::new("ip")
        .args(["netns", "exec", &net.c, BIN, "serve", "--data-dir"])
        .arg(&data)
        .args(["--bind", &format!("0.0.0.0:{PORT}"), "--lease-seconds", "2", "--token", TOKEN])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(serve.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.starts_with("listening on"), "{line:?}");
    let _serve = Proc(serve);
    let url = format!("http://{}:{PORT}", net.client_addr);
    // The delay is there: a health check from a worker's namespace takes a connection and a
    // request, two round trips (the first one after the coordinator listens).
    let probe = |k: usize| {
        let t = Instant::now();
        let ok = Command::new("ip")
            .args(["netns", "exec", &net.w[k], BIN, "probe", &format!("http://10.1.{k}.1:{PORT}/healthz")])
            .stderr(Stdio::null())
            .status()
            .unwrap()
            .success();
        (ok, t.elapsed())
    };
    wait_for("w1 reaches the coordinator", Duration::from_secs(10), || probe(1).0);
    let (ok, took) = probe(1);
    assert!(ok, "w1 cannot reach the coordinator");
    assert!(!net.delay || took >= 4 * DELAY, "a health check over the delayed cable took {took:?}");
    eprintln!("a health check from w1's namespace: {took:?}");
    // Submitted from this namespace, over the link to c.
    let (spp, scene) = ("16384", scenes().join("small.xml"));
    let out = Command::new(BIN)
        .arg("submit")
        .arg(&scene)
        .args([
            "--coordinator",
            &url,
            "--token",
            TOKEN,
            "--spp",
            spp,
            "--tile",
            "16",
            "--spp-per-chunk",
            "512",
        ])
        .env("NO_PROXY", "*")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let job = String::from_utf8(out.stdout).unwrap().trim().to_string();
    let worker = |k: usize| {
        let log = std::fs::File::create(dir.join(format!("w{k}.log"))).unwrap();
        Proc(
            Command::new("ip")
                .args([
                    "netns",
                    "exec",
                    &net.w[k],
                    BIN,
                    "worker",
                    "--threads",
                    "1",
                    "--name",
                    &format!("w{k}"),
                ])
                .args(["--coordinator", &format!("http://10.1.{k}.1:{PORT}"), "--token", TOKEN, "--cache"])
                .arg(dir.join(format!("cache{k}")))
                .stdout(Stdio::null())
                .stderr(log)
                .spawn()
                .unwrap(),
        )
    };
    let (_w0, _w1) = (worker(0), worker(1));
    // The slow worker is cut off once it has handed in two chunks, in the middle of an upload:
    // its link's queue holds 6 KB of it, most of a second at 64 kbit (cut at the very end of
    // an upload, the coordinator would take it and only its answer would be held up). Its
    // lease expires during the cut.
    wait_for("w0 hands in 2 chunks", Duration::from_secs(60), || chunks_done(&url, "w0") >= 2);
    wait_for("w0 uploads", Duration::from_secs(30), || net.backlog(0) >= 6000);
    net.partition(0, true).unwrap();
    // A merge of an upload whose last bytes got through just before the cut may still be
    // under way.
    std::thread::sleep(Duration::from_millis(500));
    let cut = chunks_done(&url, "w0");
    std::thread::sleep(Duration::from_secs(6));
    let status = get_json(&format!("{url}/v1/jobs/{job}"));
    assert_ne!(status["state"], "done", "the job ended during the cut: make it longer");
    assert_eq!(chunks_done(&url, "w0"), cut, "a partitioned worker handed in chunks");
    net.partition(0, false).unwrap();
    // Healed: the cut-off worker works on.
    wait_for("w0 hands in chunks after the cut", Duration::from_secs(60), || chunks_done(&url, "w0") > cut);
    wait_for("the job is done", Duration::from_secs(180), || {
        get_json(&format!("{url}/v1/jobs/{job}"))["state"] == "done"
    });
    let r = http().get(format!("{url}/v1/jobs/{job}/result.exr")).bearer_auth(TOKEN).send().unwrap();
    assert!(r.status().is_success());
    let farm = r.bytes().unwrap().to_vec();
    // What the cut did to the worker in its own words: an upload that hung on the dead link
    // and failed or was refused once it healed, or a render whose lease was gone by then
    // (refused at its first heartbeat after the cut: its lease had gone to w1).
    let log = std::fs::read_to_string(dir.join("w0.log")).unwrap();
    let noticed = |l: &&str| l.contains("upload") || l.contains("unreachable") || l.contains("lease lost");
    let hit: Vec<&str> = log.lines().filter(noticed).take(3).collect();
    eprintln!("w0 after the cut: {hit:?}");
    assert!(!hit.is_empty(), "the cut worker never noticed the cut");
    let status = get_json(&format!("{url}/v1/jobs/{job}"));
    eprintln!(
        "chunks: w0 {}, w1 {}; errors: {}",
        chunks_done(&url, "w0"),
        chunks_done(&url, "w1"),
        status["errors"]
    );
    let local = dir.join("local.exr");
    let st = Command::new(BIN)
        .arg("render")
        .arg(&scene)
        .args(["--spp", spp, "--threads", "2", "-o"])
        .arg(&local)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(st.success());
    assert!(farm == std::fs::read(&local).unwrap(), "the farm's result differs from furnace render's");
    drop(net);
    std::fs::remove_dir_all(&dir).ok();
}
