#!/usr/bin/env bash
# Runs the Dockerfile's runtime stages without a Docker engine: a Debian bookworm minbase root
# (debootstrap, from Debian's mirrors) stands in for debian:bookworm-slim, the runtime stage's
# RUN makes the user, and the coordinator and a worker run in it as uid 10001 with the ENV and
# CMD of their targets. A job submitted from outside must give furnace render's bytes, and
# both HEALTHCHECK commands must pass. Needs root (chroot); takes a few minutes the first time.
#   deploy/docker/try-runtime.sh [ROOTFS_DIR]
set -euo pipefail
shopt -s inherit_errexit
cd "$(dirname "$0")/../.."
root=${1:-/tmp/furnace-slimroot}
port=18650
cargo build --release --bin furnace
if [ ! -x "$root/bin/sh" ]; then
    debootstrap --variant=minbase bookworm "$root" http://deb.debian.org/debian
fi
py() { python3 -c "import sys; sys.path.insert(0, 'deploy'); import check; $1"; }
cp target/release/furnace "$root/usr/local/bin/furnace"
# The runtime stage's RUN, once.
if ! chroot "$root" id -u furnace >/dev/null 2>&1; then
    chroot "$root" sh -c "$(py "print(dict(check.dockerfile_stages()['runtime']['ops'])['RUN'])")"
fi
envs() { py "print(' '.join(f'{k}={v}' for k, v in check.stage_env(check.dockerfile_stages(), '$1').items()))"; }
cmd() { py "import json; print(' '.join(json.loads(check.resolved(check.dockerfile_stages(), '$1', 'CMD'))))"; }
health() { py "import json; h = check.resolved(check.dockerfile_stages(), '$1', 'HEALTHCHECK'); print(' '.join(json.loads(h[h.index('CMD') + 3:])))"; }
as_furnace=(chroot --userspec=10001:10001 "$root" env -i HOME=/var/lib/furnace PATH=/usr/local/bin:/usr/bin:/bin FURNACE_TOKEN=tok)
run_as() { "${as_furnace[@]}" "$@"; }
pids=()
trap 'kill "${pids[@]}" 2>/dev/null || true' EXIT
# Started directly (chroot, env and sh exec), so that $! is the furnace process itself.
# The coordinator binds 0.0.0.0:8640 in the image; here the host's network is shared, so a free port.
"${as_furnace[@]}" $(envs coordinator) FURNACE_BIND=0.0.0.0:$port \
    sh -c "cd /var/lib/furnace && exec furnace $(cmd coordinator)" &
pids+=($!)
sleep 1
"${as_furnace[@]}" $(envs worker) FURNACE_COORDINATOR=http://127.0.0.1:$port \
    sh -c "cd /var/lib/furnace && exec furnace $(cmd worker)" &
pids+=($!)
sleep 1
run_as $(health coordinator | sed "s/8640/$port/")
echo "coordinator HEALTHCHECK: ok"
FURNACE_TOKEN=tok target/release/furnace submit examples/cbox.xml --coordinator http://127.0.0.1:$port --spp 16 --wait -o /tmp/try-runtime.exr
run_as $(health worker)
echo "worker HEALTHCHECK: ok"
target/release/furnace render examples/cbox.xml --spp 16 -o /tmp/try-runtime-local.exr
cmp /tmp/try-runtime.exr /tmp/try-runtime-local.exr
echo "the job rendered in the runtime image as uid 10001 equals furnace render"
