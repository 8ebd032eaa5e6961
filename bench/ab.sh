#!/usr/bin/env bash
# Two or more furnace binaries on the same scenes, interleaved (A B A B ...), so that this
# machine's 10-20% timing noise hits them alike. Prints each binary's Msamples/s per run,
# sorted, per scene. For a decision, back a timing difference with callgrind's instruction
# counts (deterministic): several timing "gains" here did not survive one.
#
#   bench/ab.sh "SCENE.xml:SPP ..." REPEATS BINARY...
#   bench/ab.sh "tests/scenes/cbox.xml:64 tests/scenes/hair.xml:32" 3 /tmp/furnace-old target/release/furnace
set -euo pipefail
scenes=$1; reps=$2; shift 2
TMP="$(mktemp -d)"; trap 'rm -rf "$TMP"' EXIT
for entry in $scenes; do
    scene="${entry%:*}"; spp="${entry##*:}"
    for k in $(seq $#); do : > "$TMP/$k"; done
    for _ in $(seq "$reps"); do
        k=0
        for bin in "$@"; do
            k=$((k + 1))
            "$bin" render "$scene" --spp "$spp" --threads 2 -o "$TMP/out.exr" 2>&1 \
                | sed -n 's/.*: \([0-9.]*\) Msamples\/s.*/\1/p' >> "$TMP/$k"
        done
    done
    line="$(basename "$scene" .xml) $spp spp"; k=0
    for bin in "$@"; do k=$((k + 1)); line="$line | $bin: $(sort -g "$TMP/$k" | paste -sd' ')"; done
    echo "$line"
done
