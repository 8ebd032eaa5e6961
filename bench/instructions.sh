#!/usr/bin/env bash
# Instructions that rendering takes (callgrind's count of `render_region`, inclusive, one
# thread): deterministic, so a change of a percent shows where this machine's 10-20% timing
# spread hides it. One column per binary, one row per scene at the spp the BENCHMARKS tables use.
#
#   bench/instructions.sh [BINARY...]     default: target/release/furnace (built if missing)
#   SCENES="tests/scenes/cbox.xml:2 ..." bench/instructions.sh OLD NEW
#
# Needs valgrind (Debian: apt-get install valgrind). It cannot run AVX-512 code; Furnace's
# kernels stop at AVX2.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
command -v valgrind >/dev/null || { echo "valgrind is not installed (apt-get install valgrind)" >&2; exit 1; }
BINS=("$@")
if [ ${#BINS[@]} -eq 0 ]; then
    (cd "$ROOT" && cargo build --release --quiet)   # in the repository, for its .cargo/config.toml
    BINS=("$ROOT/target/release/furnace")
fi
SCENES=${SCENES:-"$ROOT/tests/scenes/cbox.xml:2 $ROOT/tests/scenes/textured.xml:4 $ROOT/tests/scenes/envmap.xml:4 $ROOT/tests/scenes/thinlens.xml:4 $ROOT/tests/scenes/hair.xml:2 $ROOT/examples/whimsical.xml:1"}
TMP="$(mktemp -d)"; trap 'rm -rf "$TMP"' EXIT

count() { # BINARY SCENE SPP
    valgrind --tool=callgrind --callgrind-out-file="$TMP/cg" "$1" render "$2" --spp "$3" --threads 1 \
        -o "$TMP/x.exr" > /dev/null 2>&1
    callgrind_annotate --inclusive=yes "$TMP/cg" > "$TMP/annotated" 2>/dev/null
    awk '/render::render_region \[/ {gsub(",", "", $1); printf "%.1fM", $1 / 1e6; exit}' "$TMP/annotated"
}

header="| scene (spp) |"; rule="|---|"
for b in "${BINS[@]}"; do header="$header $b |"; rule="$rule---|"; done
echo "$header"; echo "$rule"
for entry in $SCENES; do
    scene="${entry%:*}"; spp="${entry##*:}"
    line="| $(basename "$scene" .xml) ($spp) |"
    for b in "${BINS[@]}"; do line="$line $(count "$b" "$scene" "$spp") |"; done
    echo "$line"
done
