#!/usr/bin/env bash
# The README's Docker section, run for real (issue 19): a Docker engine, a base image made with
# debootstrap where no registry is reachable, the coordinator and worker images built from
# deploy/docker/Dockerfile around a binary built on this host, and the Compose project
# (deploy/compose/compose.host.yaml) up with a coordinator, two workers and a token, every
# container on the host's network, the coordinator on loopback: no traffic leaves this
# machine. Then, from the host:
#   - `furnace submit --wait` gives the bytes `furnace render` gives;
#   - every container's HEALTHCHECK reports healthy;
#   - a worker stopped with `docker stop` finishes and uploads its chunk before it exits;
#   - the coordinator restarted with `docker restart` keeps its job (the named volume), and
#     that job's result is furnace render's too;
#   - the monitoring profile runs only if its images are here (no registry to pull them from).
# Prints the images' sizes and the start-up times.
#
#   deploy/docker/compose-test.sh [FURNACE_BINARY]     (default: target/release/furnace)
#
# Exit 0: passed. Exit 77: skipped, the reason printed (no Docker engine can be started here,
# or the disk has too little room for the images).
# Anything else: failed. Needs root to start dockerd and to run debootstrap.
set -euo pipefail
shopt -s inherit_errexit
cd "$(dirname "$0")/../.."
bin=$(realpath "${1:-target/release/furnace}")
work=$(realpath -m target/compose-test)
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
project=furnace-test
token=compose-test-token
api=http://127.0.0.1:8640

skip() { echo "compose-test: SKIPPED: $*"; exit 77; }
fail() { echo "compose-test: FAILED: $*"; exit 1; }
step() { echo "compose-test: $*"; }
since() { awk -v a="$1" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }'; }

[ -x "$bin" ] || fail "no furnace binary at $bin (cargo build --release)"
# Debian's docker.io (20.10) brings its own CLI, which builds with BuildKit without the buildx
# plugin that newer CLIs want; prefer it.
docker=$(command -v /usr/bin/docker || command -v docker || true)
[ -n "$docker" ] || skip "no docker command (apt-get install docker.io)"
if [ -x /usr/bin/docker-compose ]; then compose_cmd=(/usr/bin/docker-compose)
elif "$docker" compose version >/dev/null 2>&1; then compose_cmd=("$docker" compose)
else skip "no docker-compose (apt-get install docker-compose)"; fi
mkdir -p "$work"

compose() { FURNACE_TOKEN=$token "${compose_cmd[@]}" -p "$project" -f deploy/compose/compose.host.yaml "$@"; }
started_dockerd=""
brought_up=""
copied=""
root=""
cleanup() {
    if [ -n "$brought_up" ]; then compose down -v --remove-orphans >/dev/null 2>&1 || true; fi
    # What this run made and no later run reuses: its copy of the binary, a half-made base image.
    if [ -n "$copied" ]; then rm -f target/docker/furnace || true; fi
    if [ -n "$root" ]; then rm -rf "$root" || true; fi
    if [ -n "$started_dockerd" ]; then kill "$started_dockerd" 2>/dev/null || true; wait "$started_dockerd" 2>/dev/null || true; fi
}
trap cleanup EXIT
if curl -s -o /dev/null "$api/readyz"; then
    fail "something already answers on $api: the coordinator's container would not get the port (stop it first)"
fi

# The engine: the one running, or one started here (no bridge, no iptables: the containers use
# the host's network).
if ! "$docker" info >/dev/null 2>&1; then
    command -v dockerd >/dev/null || skip "no Docker engine running and no dockerd (apt-get install docker.io)"
    [ "$(id -u)" = 0 ] || skip "no Docker engine running, and starting dockerd needs root"
    # A pid file left by an engine that died would stop a new one from starting.
    if [ -f /var/run/docker.pid ] && ! kill -0 "$(cat /var/run/docker.pid)" 2>/dev/null; then
        rm -f /var/run/docker.pid
    fi
    step "starting dockerd (log: $work/dockerd.log)"
    dockerd --bridge=none --iptables=false >"$work/dockerd.log" 2>&1 &
    started_dockerd=$!
    for _ in $(seq 60); do "$docker" info >/dev/null 2>&1 && break; sleep 0.5; done
    "$docker" info >/dev/null 2>&1 || skip "dockerd did not start: $(tail -n 3 "$work/dockerd.log" | tr '\n' ' ')"
fi

# Room for the base image (a minimal Debian, 198 MB, held twice while it is imported), the
# binary (once in the context, once in the images) and the containers' volumes: a whole run
# took at most 325 MB more than before it (df, once a second). With less free, the test
# cannot run here at all: say so, as for a missing engine, instead of failing half-way with
# "No space left on device".
need_mb=600
docker_root=$("$docker" info -f '{{.DockerRootDir}}' 2>/dev/null || echo /var/lib/docker)
for dir in "$work" "$docker_root"; do
    d=$dir; while [ ! -e "$d" ]; do d=$(dirname "$d"); done
    free_mb=$(df -Pm "$d" 2>/dev/null | awk 'NR == 2 { print $4 }') || true
    [ "${free_mb:-0}" -ge "$need_mb" ] || skip "only ${free_mb} MB free on the disk holding $dir; the images and containers need about $need_mb MB"
done

# The base image, made from Debian's packages where no registry is reachable.
if ! "$docker" image inspect debian:bookworm-slim >/dev/null 2>&1; then
    command -v debootstrap >/dev/null || skip "no debian:bookworm-slim image and no debootstrap to make one (apt-get install debootstrap)"
    step "making debian:bookworm-slim with debootstrap from $mirror"
    root="$work/bookworm-root"
    rm -rf "$root"
    debootstrap --variant=minbase bookworm "$root" "$mirror" >"$work/debootstrap.log" 2>&1 \
        || fail "debootstrap failed: $(tail -n 3 "$work/debootstrap.log" | tr '\n' ' ')"
    tar -C "$root" -c . | "$docker" import - debian:bookworm-slim >/dev/null
    rm -rf "$root"
    root=""
fi

# The images, around the binary built on this host.
step "building furnace-coordinator:local and furnace-worker:local from $bin"
mkdir -p target/docker
# Without its debug information: a debug build's binary is 280 MB, 21 MB without (the images'
# layers, BuildKit's cache of the build context and this copy each hold it once). A CI run
# once failed here with the disk full. A binary given as target/docker/furnace itself (the
# README's place for one) is taken as it is, and left there.
if [ "$bin" != "$(realpath -m target/docker/furnace)" ]; then
    copied=1
    if command -v objcopy >/dev/null; then
        objcopy --strip-debug "$bin" target/docker/furnace || fail "objcopy --strip-debug $bin"
    else
        cp "$bin" target/docker/furnace
    fi
    chmod 755 target/docker/furnace   # whatever the umask: the images run it as uid 10001
fi
for target in coordinator worker; do
    t0=$(date +%s.%N)
    DOCKER_BUILDKIT=1 "$docker" build -q -f deploy/docker/Dockerfile --target "$target" \
        --build-arg FURNACE_BINARY_FROM=prebuilt --network host -t "furnace-$target:local" . >/dev/null \
        || fail "docker build --target $target failed"
    size=$("$docker" image inspect -f '{{.Size}}' "furnace-$target:local")
    step "image furnace-$target:local: $((size / 1000000)) MB, built in $(since "$t0") s"
done

t0=$(date +%s.%N)
version=$("$docker" run --rm --network none furnace-worker:local --version) || fail "the worker image does not run furnace"
step "a container of furnace-worker:local ran '$version' in $(since "$t0") s (start to exit)"

health() { "$docker" inspect -f '{{if .State.Health}}{{.State.Health.Status}}{{else}}none{{end}}' "$1"; }
wait_healthy() { # CONTAINER... ; prints the seconds it took
    local t0 c ok
    t0=$(date +%s.%N)
    for _ in $(seq 240); do
        ok=1
        for c in "$@"; do [ "$(health "$c")" = healthy ] || ok=0; done
        if [ $ok = 1 ]; then since "$t0"; return 0; fi
        sleep 0.5
    done
    for c in "$@"; do echo "$c: $(health "$c")" >&2; "$docker" logs --tail 5 "$c" >&2 2>&1; done
    return 1
}
get() { curl -fsS -H "Authorization: Bearer $token" "$api$1"; }
field() { python3 -c "import json, sys; print(json.load(sys.stdin)$1)"; }

step "compose up: a coordinator and two workers"
# What an interrupted earlier run of this test left (the port is free, so none is running).
compose down -v --remove-orphans >/dev/null 2>&1 || true
brought_up=1
t0=$(date +%s.%N)
compose up -d --no-build --scale worker=2 coordinator worker >"$work/up.log" 2>&1 || { cat "$work/up.log"; fail "compose up"; }
ready() { # seconds from $1 until the coordinator answers /readyz
    for _ in $(seq 600); do curl -fs -o /dev/null "$api/readyz" && { since "$1"; return 0; }; sleep 0.1; done
    return 1
}
# (Compose starts the workers once the coordinator's first health check, 15 s in, passes.)
step "compose up took $(since "$t0") s"
coord=$(compose ps -q coordinator)
mapfile -t workers < <(compose ps -q worker)
[ ${#workers[@]} = 2 ] || fail "expected 2 workers, got ${#workers[@]}"
took=$(wait_healthy "$coord") || fail "the coordinator is not healthy"

out="$work/out"
rm -rf "$out"
mkdir -p "$out"
scene=tests/scenes/cbox.xml
step "furnace submit --wait from the host, against furnace render"
timeout 600 "$bin" submit "$scene" --coordinator "$api" --token "$token" --spp 16 --tile 64 --spp-per-chunk 4 \
    --wait -o "$out/farm.exr" >"$out/submit-a.log" 2>&1 || { cat "$out/submit-a.log"; fail "submit --wait (or its 600 s)"; }
"$bin" render "$scene" --spp 16 -o "$out/render.exr" >"$out/render.log" 2>&1 || { cat "$out/render.log"; fail "furnace render"; }
cmp "$out/farm.exr" "$out/render.exr" || fail "the farm's EXR differs from furnace render's"
step "byte-identical to furnace render ($(stat -c %s "$out/farm.exr") bytes)"

took=$(wait_healthy "$coord" "${workers[@]}") || fail "not every container is healthy"
step "all three HEALTHCHECKs healthy"

# A longer job; once both workers hold chunks, one is stopped.
job=$("$bin" submit "$scene" --coordinator "$api" --token "$token" --spp 512 --tile 64 --spp-per-chunk 8)
for _ in $(seq 200); do
    n=$(get "/v1/jobs/$job" | field "['workers'].__len__()") || fail "cannot read job $job's status"
    [ "$n" -ge 2 ] && break
    sleep 0.1
done
[ "$n" -ge 2 ] || fail "the two workers never both held a chunk of job $job"
step "docker stop of a worker holding a chunk"
"$docker" stop -t 600 "${workers[1]}" >/dev/null
code=$("$docker" inspect -f '{{.State.ExitCode}}' "${workers[1]}")
logs=$("$docker" logs "${workers[1]}" 2>&1)
[ "$code" = 0 ] || fail "the stopped worker exited with $code"
grep -q "stopping after the chunk in hand" <<<"$logs" || fail "the worker did not see SIGTERM: $logs"
done_line=$(grep -o "worker stopped after [0-9]* chunks" <<<"$logs") || fail "the worker did not finish: $logs"
[ "$(grep -o '[0-9]*' <<<"$done_line")" -ge 1 ] || fail "the stopped worker uploaded no chunk"
expired=$(get /metrics | grep -E '^furnace_chunk_retries_total\{reason="expired"\}' | awk '{print $2}')
[ "${expired:-0}" = 0 ] || fail "$expired leases expired: the stopped worker abandoned its chunk"
step "the worker finished its chunk and exited 0 ($done_line), no lease expired"

step "docker restart of the coordinator in the middle of job $job"
before=$(get "/v1/jobs/$job" | field "['chunks_done']")
t0=$(date +%s.%N)
"$docker" restart "$coord" >/dev/null
answered=$(ready "$t0") || fail "the coordinator never answered after its restart"
took=$(wait_healthy "$coord") || fail "the coordinator is not healthy after its restart"
step "restarted coordinator answering /readyz ${answered} s after docker restart began"
state=$(get "/v1/jobs/$job" | field "['state']")
step "after the restart (healthy in ${took} s) job $job is $state with $before chunks done before it"
for _ in $(seq 600); do
    state=$(get "/v1/jobs/$job" | field "['state']")
    [ "$state" = done ] && break
    sleep 0.5
done
[ "$state" = done ] || fail "job $job did not finish after the restart: $state"
get "/v1/jobs/$job/result.exr" >"$out/restarted.exr"
"$bin" render "$scene" --spp 512 -o "$out/render512.exr" >"$out/render.log" 2>&1 || { cat "$out/render.log"; fail "furnace render"; }
cmp "$out/restarted.exr" "$out/render512.exr" || fail "job $job's result differs from furnace render's"
step "job $job kept across the restart, byte-identical to furnace render"

# The monitoring profile, only with its image here: pulling it would reach for a registry.
prom=$(awk '/image: prom\//{print $2}' deploy/compose/compose.host.yaml)
if "$docker" image inspect "$prom" >/dev/null 2>&1; then
    compose --profile monitoring up -d --no-build prometheus >/dev/null
    for _ in $(seq 120); do
        curl -fsS 'http://127.0.0.1:9090/api/v1/query?query=furnace_jobs' 2>/dev/null | grep -q '"result":\[{' && break
        sleep 1
    done
    curl -fsS 'http://127.0.0.1:9090/api/v1/query?query=furnace_jobs' | grep -q '"result":\[{' \
        || fail "Prometheus does not scrape the coordinator"
    step "monitoring profile: Prometheus scrapes the coordinator"
else
    step "monitoring profile not started: the image $prom cannot be had here (no image registry to pull it from)"
fi
step "passed"
