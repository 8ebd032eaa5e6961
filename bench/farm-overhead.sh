#!/usr/bin/env bash
# The farm's overhead: one job through a coordinator and 2 workers of 1 thread each (and one
# worker of 2 threads), against `furnace render --threads 2` of the same job, wall time from
# submit to result on disk. The farm part of bench/scaling.sh, on this tree's release build.
#
#   bench/farm-overhead.sh [SCENE=tests/scenes/cbox.xml] [SPP=64] [TILE=64] [CHUNK_SPP=64]
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
SCENE="${1:-$ROOT/tests/scenes/cbox.xml}"; SPP="${2:-64}"; TILE="${3:-64}"; CHUNK="${4:-64}"
(cd "$ROOT" && cargo build --release --quiet)   # in the repository, for its .cargo/config.toml
SCENES="" FARM="$(realpath "$SCENE"):$SPP:$TILE:$CHUNK" exec "$ROOT/bench/scaling.sh" "$ROOT/target/release/furnace" 2 1
