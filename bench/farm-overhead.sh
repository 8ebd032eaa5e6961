#!/usr/bin/env bash
# The farm's overhead: one job through a coordinator and 2 workers of 1 thread each, against
# `furnace render --threads 2` of the same job, wall time from submit to result on disk.
#
#   bench/farm-overhead.sh [SCENE=tests/scenes/cbox.xml] [SPP=64] [TILE=64] [CHUNK_SPP=64]
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
SCENE="${1:-$ROOT/tests/scenes/cbox.xml}"; SPP="${2:-64}"; TILE="${3:-64}"; CHUNK="${4:-64}"
cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml"
F="$ROOT/target/release/furnace"
TMP="$(mktemp -d)"
PIDS=()
trap 'kill "${PIDS[@]}" 2>/dev/null; rm -rf "$TMP"' EXIT
"$F" serve --data-dir "$TMP/data" --bind 127.0.0.1:0 > "$TMP/serve.out" 2>/dev/null &
PIDS+=($!)
until grep -q listening "$TMP/serve.out"; do sleep 0.05; done
URL="$(sed -n 's/listening on //p' "$TMP/serve.out")"
for i in 1 2; do "$F" worker --coordinator "$URL" --threads 1 --name "w$i" --cache "$TMP/c$i" 2>/dev/null & PIDS+=($!); done
t0=$(date +%s.%N)
"$F" submit "$SCENE" --coordinator "$URL" --spp "$SPP" --tile "$TILE" --spp-per-chunk "$CHUNK" --wait -o "$TMP/farm.exr" > /dev/null 2>&1
t1=$(date +%s.%N)
"$F" render "$SCENE" --spp "$SPP" --threads 2 -o "$TMP/local.exr" > /dev/null 2>&1
t2=$(date +%s.%N)
cmp -s "$TMP/farm.exr" "$TMP/local.exr" && same=identical || same=DIFFERENT
awk -v f="$(echo "$t1 - $t0" | bc)" -v l="$(echo "$t2 - $t1" | bc)" -v s="$same" \
  'BEGIN { printf "farm %.2f s, furnace render %.2f s, overhead %+.1f%%, results %s\n", f, l, (f / l - 1) * 100, s }'
