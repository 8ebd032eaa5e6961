#!/usr/bin/env bash
# Samples per second of Furnace beside Mitsuba 3 (scalar_rgb and llvm_ad_rgb) on the same
# scene, in one run, interleaved so that machine noise hits all three alike.
#
#   bench/vs-mitsuba.sh [SCENE=tests/scenes/cbox.xml] [SPP=64] [THREADS=2] [REPEATS=3]
#
# Needs Mitsuba 3: bench/peers/setup.sh (venv outside the repo, $PEERS_VENV, default
# ../peers-venv). Prints a markdown table: median seconds and samples/s over REPEATS, and the
# ratio of Furnace's samples/s to each Mitsuba variant's. Render time only (scene loading
# excluded) for all three; llvm gets one untimed warm-up run to fill Dr.Jit's kernel cache.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
SCENE="${1:-$ROOT/tests/scenes/cbox.xml}"; SPP="${2:-64}"; THREADS="${3:-2}"; REPEATS="${4:-3}"
PY="$ROOT/bench/peers/py.sh"
TMP="$(mktemp -d)"; trap 'rm -rf "$TMP"' EXIT

cargo build --release --quiet --manifest-path "$ROOT/Cargo.toml"
FURNACE="$ROOT/target/release/furnace"

furnace_secs() {
    "$FURNACE" render "$SCENE" --spp "$SPP" --threads "$THREADS" -o "$TMP/f.exr" 2>&1 \
        | sed -n 's/.* in \([0-9.]*\)s on .*/\1/p'
}
mitsuba_secs() {
    "$PY" "$ROOT/bench/peers/render.py" "$SCENE" --variant "$1" --spp "$SPP" --threads "$THREADS" \
        --out "$TMP/m.exr" | sed -n 's/.* seconds=\([0-9.]*\) .*/\1/p'
}
median() { sort -g | awk '{a[NR]=$1} END {print (NR%2) ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2}'; }

mitsuba_secs llvm_ad_rgb > /dev/null   # warm Dr.Jit's kernel cache
: > "$TMP/furnace"; : > "$TMP/scalar_rgb"; : > "$TMP/llvm_ad_rgb"
for _ in $(seq "$REPEATS"); do
    furnace_secs >> "$TMP/furnace"
    mitsuba_secs scalar_rgb >> "$TMP/scalar_rgb"
    mitsuba_secs llvm_ad_rgb >> "$TMP/llvm_ad_rgb"
done

read -r W H < <(sed -n 's/.*"width" value="\([0-9]*\)".*/\1/p; s/.*"height" value="\([0-9]*\)".*/\1/p' "$SCENE" | head -2 | paste -sd' ')
samples=$(( W * H * SPP ))
f=$(median < "$TMP/furnace")
echo "scene $(basename "$SCENE"), ${W}x${H}, $SPP spp, $THREADS threads, median of $REPEATS ($(date -u +%F))"
echo
echo "| renderer | seconds | Msamples/s | Furnace / this |"
echo "|---|---|---|---|"
for r in furnace scalar_rgb llvm_ad_rgb; do
    s=$(median < "$TMP/$r")
    name=$r; [ "$r" = furnace ] || name="Mitsuba 3 $r"
    awk -v n="$name" -v s="$s" -v f="$f" -v k="$samples" \
        'BEGIN { printf "| %s | %.3f | %.3f | %.2fx |\n", n, s, k / s / 1e6, s / f }'
done
