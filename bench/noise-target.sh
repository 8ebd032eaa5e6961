#!/usr/bin/env bash
# Error against time for renders to a target error (`--target-rel-error`) and at fixed sample
# counts, over many seeds: under a small bright sun one seed's relMSE is a lottery of
# fireflies, so the table gives the mean (the expected error) beside the median and the worst.
#
#   bench/noise-target.sh SCENE.xml "ENTRY ..." [SEEDS=12] [BINARY...]
#   bench/noise-target.sh tests/scenes/envmap.xml "t=0.06 t=0.08 spp=32 spp=48" 12 target/release/furnace
#
# ENTRY: t=E renders with `--target-rel-error E --spp CAP --spp-per-chunk 8 --tile 32`
# (CAP=256 unless set in the environment); spp=N renders N samples per pixel as usual.
# 2 threads. Error: relMSE against tests/scenes/refs/NAME.exr (`furnace compare`). Seconds:
# the render's own time (as `furnace render` logs it; scene loading excluded). Seeds SEED0 to
# SEED0 + SEEDS - 1 (SEED0=0 unless set in the environment). The trimmed mean leaves out the
# worst tenth of the seeds (the firefly lottery's largest draws).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
scene=$1; entries=$2; seeds=${3:-12}; shift $(( $# < 3 ? $# : 3 ))
BINS=("$@")
[ ${#BINS[@]} -gt 0 ] || BINS=("$ROOT/target/release/furnace")
CAP=${CAP:-256}
SEED0=${SEED0:-0}
ref="$ROOT/tests/scenes/refs/$(basename "$scene" .xml).exr"
[ -f "$ref" ] || { echo "no reference $ref" >&2; exit 1; }
TMP="$(mktemp -d)"; trap 'rm -rf "$TMP"' EXIT

echo "| binary | entry | mean spp | median s | mean relMSE | median relMSE | worst | seeds | trimmed mean |"
echo "|---|---|---|---|---|---|---|---|---|"
for bin in "${BINS[@]}"; do
    for entry in $entries; do
        case "$entry" in
            t=*) args=(--spp "$CAP" --target-rel-error "${entry#t=}" --spp-per-chunk 8 --tile 32) ;;
            spp=*) args=(--spp "${entry#spp=}") ;;
            *) echo "entry $entry: expected t=E or spp=N" >&2; exit 1 ;;
        esac
        : > "$TMP/rows"
        for seed in $(seq "$SEED0" $((SEED0 + seeds - 1))); do
            log="$("$bin" render "$scene" "${args[@]}" --seed "$seed" --threads 2 -o "$TMP/x.exr" 2>&1)"
            secs="$(sed -n 's/.* (\([0-9.]*\) spp of at most.* in \([0-9.]*\)s on .*/\1 \2/p' <<< "$log")"
            err="$("$bin" compare "$TMP/x.exr" "$ref" | awk '/relMSE/ {print $2}')"
            echo "$secs $err" >> "$TMP/rows"
        done
        python3 - "$bin" "$entry" "$TMP/rows" <<'EOF'
import statistics as st, sys
rows = [list(map(float, l.split())) for l in open(sys.argv[3]) if l.strip()]
spp, secs, err = zip(*rows)
kept = sorted(err)[:max(1, len(err) - len(err) // 10)]
print(f"| {sys.argv[1]} | {sys.argv[2]} | {st.mean(spp):.1f} | {st.median(secs):.3f} | "
      f"{st.mean(err):.5f} | {st.median(err):.5f} | {max(err):.4f} | {len(rows)} | {st.mean(kept):.5f} |")
EOF
    done
done
