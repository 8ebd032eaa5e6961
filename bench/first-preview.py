#!/usr/bin/env python3
"""Time to the first preview, and to the result, of one job through a farm on this machine.

usage: bench/first-preview.py SCENE.xml [--workers 1] [--worker-threads 0] [--processes]
                               [SUBMIT ARGS ...]

Starts `furnace serve` on a fresh data folder with --local-workers (each with
--worker-threads threads, 0: all cores), or with --processes that many `furnace worker`
processes beside it (each with its own cache folder), then `furnace submit SCENE --wait` with the submit
arguments given (--spp, --target-rel-error, --tile, --spp-per-chunk, ...), and polls the
job: the time from submit to the job's creation (the client has loaded the scene and
uploaded its files), to its first merged chunk with `preview.png` served, and to the result
on disk. Then renders the same job with `furnace render` (same arguments) and says whether
the two EXRs are byte-identical. Prints one line per event and a RESULT line. Only the
standard library: no venv needed. FURNACE=path picks the binary (default target/release).
"""
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FURNACE = os.environ.get("FURNACE", os.path.join(ROOT, "target", "release", "furnace"))


def hwm(pid):
    """Peak resident memory of a live process, in GB (Linux /proc), or 0."""
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1e6
    except OSError:
        pass
    return 0.0


def get(url):
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.read()


def main():
    args = sys.argv[1:]
    if not args or args[0].startswith("-"):
        sys.exit(__doc__)
    scene, rest = args[0], args[1:]
    workers, threads, processes = "1", "0", False
    submit_args = []
    i = 0
    while i < len(rest):
        if rest[i] == "--workers":
            workers = rest[i + 1]
            i += 2
        elif rest[i] == "--worker-threads":
            threads = rest[i + 1]
            i += 2
        elif rest[i] == "--processes":
            processes = True
            i += 1
        else:
            submit_args.append(rest[i])
            i += 1
    if "--tile" not in submit_args:
        submit_args += ["--tile", "64"]  # both commands' default; tiles decide a target's stops
    tmp = tempfile.mkdtemp(prefix="first-preview-")
    serve_cmd = [FURNACE, "serve", "--data-dir", os.path.join(tmp, "data"), "--bind", "127.0.0.1:0",
                 "--local-workers", "0" if processes else workers]
    if threads != "0" and not processes:
        serve_cmd += ["--worker-threads", threads]
    serve_out = open(os.path.join(tmp, "serve.out"), "w")
    serve = subprocess.Popen(serve_cmd, stdout=serve_out, stderr=subprocess.STDOUT)
    procs = []
    try:
        url = None
        while url is None:
            time.sleep(0.05)
            for line in open(os.path.join(tmp, "serve.out")):
                if "listening on " in line:
                    url = line.split("listening on ", 1)[1].split()[0]
        for w in range(int(workers) if processes else 0):
            cmd = [FURNACE, "worker", "--coordinator", url, "--name", f"w{w}", "--cache", os.path.join(tmp, f"cache{w}")]
            if threads != "0":
                cmd += ["--threads", threads]
            procs.append(subprocess.Popen(cmd, stdout=subprocess.DEVNULL,
                                          stderr=open(os.path.join(tmp, f"worker{w}.err"), "w")))
        farm = os.path.join(tmp, "farm.exr")
        t0 = time.time()
        sub = subprocess.Popen([FURNACE, "submit", scene, "--coordinator", url, "--wait", "-o", farm] + submit_args,
                               stdout=subprocess.DEVNULL, stderr=open(os.path.join(tmp, "submit.err"), "w"))
        created = first = None
        job = None
        peaks = {}
        while sub.poll() is None:
            time.sleep(0.25)
            for name, p in [("coordinator", serve), ("client", sub)] + [(f"worker{w}", p) for w, p in enumerate(procs)]:
                peaks[name] = max(peaks.get(name, 0.0), hwm(p.pid))
            try:
                jobs = json.loads(get(url + "/v1/jobs"))
            except OSError:
                continue
            if not jobs:
                continue
            job = jobs[0]
            if created is None:
                created = time.time() - t0
                print(f"job {job['id']} created after {created:.1f} s ({job['chunks_total']} chunks)", flush=True)
            if first is None and job["chunks_done"] >= 1:
                try:
                    png = get(f"{url}/v1/jobs/{job['id']}/preview.png")
                except OSError:
                    continue
                first = time.time() - t0
                open(os.path.join(tmp, "first-preview.png"), "wb").write(png)
                print(f"first preview after {first:.1f} s ({len(png)} bytes, "
                      f"{job['samples_done']} samples merged)", flush=True)
        done = time.time() - t0
        if sub.returncode != 0:
            sys.exit(f"submit failed: {open(os.path.join(tmp, 'submit.err')).read()[-2000:]}")
        status = json.loads(get(f"{url}/v1/jobs/{job['id']}"))
        print(f"result after {done:.1f} s: {status['chunks_done'] - status['chunks_skipped']} chunks rendered, "
              f"{status['chunks_skipped']} skipped at the target, {status['samples_done']} samples", flush=True)
        print("peak resident memory: " + ", ".join(f"{k} {v:.2f} GB" for k, v in peaks.items()), flush=True)
    finally:
        for p in procs + [serve]:
            p.terminate()
            p.wait()
    local = os.path.join(tmp, "local.exr")
    render_args = list(submit_args)
    t1 = time.time()
    subprocess.run([FURNACE, "render", scene, "-o", local] + render_args, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    local_s = time.time() - t1
    same = open(farm, "rb").read() == open(local, "rb").read()
    print(f"furnace render of the same job: {local_s:.1f} s; results "
          f"{'byte-identical' if same else 'DIFFERENT'}")
    print(f"RESULT created={created:.2f} first_preview={first:.2f} result={done:.2f} "
          f"render={local_s:.2f} identical={same} dir={tmp}")


if __name__ == "__main__":
    main()
