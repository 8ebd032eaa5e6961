#!/usr/bin/env bash
# Multi-core scaling of one furnace binary: `furnace render` at 1, 2, 4, ... threads on each
# scene (Msamples/s, speed-up over the first thread count given, efficiency), then the farm: one coordinator and
# W workers of 1 thread each (and one worker of all threads), wall time from submit to the
# result on disk, against `furnace render` with as many threads, and whether the bytes agree.
#
#   bench/scaling.sh BINARY [THREADS="1 2 4 8 16"] [REPEATS=2]
#   bench/scaling.sh target/release/furnace "1 2" 1     # a quick look on a small machine
#
# Scenes and sample counts: SCENES="SCENE.xml:SPP ..." (default below: 5 to 10 s a scene at
# 1 thread; SCENES="" measures the farm alone, as bench/farm-overhead.sh does). Farm job: FARM="SCENE.xml:SPP:TILE:CHUNK_SPP". docs/BENCHMARKS.md, "Multi-core
# scaling", has 16-core runs.
# MITSUBA="scalar_rgb llvm_ad_rgb" adds Mitsuba 3 beside each row (one run each, after Furnace's;
# llvm gets one untimed warm-up a scene at the most threads), through bench/peers/py.sh or
# MITSUBA_PY (a python3 whose PYTHONPATH holds mitsuba: bench/peers/pack-offline.sh packs one
# for a machine without a network).
set -euo pipefail
F="$(realpath "$1")"; THREADS="${2:-1 2 4 8 16}"; REPS="${3:-2}"
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
SCENES="${SCENES-tests/scenes/cbox.xml:96 tests/scenes/textured.xml:384 tests/scenes/envmap.xml:384 tests/scenes/hair.xml:32 examples/whimsical.xml:24}"
FARM="${FARM:-tests/scenes/cbox.xml:256:32:64}"
TMP="$(mktemp -d)"; PIDS=()
trap 'kill ${PIDS[@]+"${PIDS[@]}"} 2>/dev/null || true; rm -rf "$TMP"' EXIT
cd "$ROOT"
echo "cpu: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'), $(nproc) cores"
"$F" render tests/scenes/cbox.xml --spp 1 --threads 1 -o "$TMP/x.exr" 2>&1 | grep -m1 -o 'built for.*' || true

rate() { sed -n 's/.*: \([0-9.]*\) Msamples\/s.*/\1/p'; }
MITSUBA="${MITSUBA:-}"; MPY="${MITSUBA_PY:-$ROOT/bench/peers/py.sh}"
mrate() {  # VARIANT SCENE SPP THREADS: Msamples/s of one Mitsuba render, or nothing
    timeout 900 "$MPY" bench/peers/render.py "$2" --variant "$1" --spp "$3" --threads "$4" --out "$TMP/m.exr" 2>/dev/null \
        | sed -n 's/.* samples_per_s=\([0-9.]*\) .*/\1/p' | awk '{printf "%.3f", $1 / 1e6}' || true
}
best() { sort -g | tail -1; }   # best of REPS: the least disturbed run
most="$(printf '%s\n' $THREADS | sort -n | tail -1)"   # llvm's warm-up thread count

[ -z "$SCENES" ] || echo
[ -z "$SCENES" ] || echo "## furnace render: Msamples/s (best of $REPS), speed-up over ${THREADS%% *} thread(s), efficiency"
for entry in $SCENES; do
    scene="${entry%:*}"; spp="${entry##*:}"; base=""
    case " $MITSUBA " in *" llvm_ad_rgb "*) mrate llvm_ad_rgb "$scene" "$spp" "$most" > /dev/null;; esac
    for t in $THREADS; do
        r="$(for _ in $(seq "$REPS"); do
            "$F" render "$scene" --spp "$spp" --threads "$t" -o "$TMP/out.exr" 2>&1 | rate
        done | best)"
        [ -z "$base" ] && base="$r"
        awk -v s="$(basename "$scene" .xml)" -v n="$spp" -v t="$t" -v r="$r" -v b="$base" -v t0="${THREADS%% *}" \
            'BEGIN { printf "%-10s %4d spp %3d threads %8.3f Ms/s  x%5.2f  %5.1f%%", s, n, t, r, r / b, 100 * r / b * t0 / t }'
        for v in $MITSUBA; do
            m="$(mrate "$v" "$scene" "$spp" "$t")"
            awk -v v="$v" -v m="$m" -v r="$r" 'BEGIN { if (m > 0) printf "  %s %.3f (F/M %.2f)", v, m, r / m; else printf "  %s failed", v }'
        done
        echo
    done
done

IFS=: read -r scene spp tile chunk <<< "$FARM"
echo
echo "## farm: $(basename "$scene" .xml) $spp spp, tile $tile, $chunk spp a chunk; wall seconds from submit to result"
"$F" serve --data-dir "$TMP/data" --bind 127.0.0.1:0 > "$TMP/serve.out" 2>/dev/null &
PIDS+=($!)
for _ in $(seq 600); do
    grep -q listening "$TMP/serve.out" && break
    kill -0 "${PIDS[-1]}" 2>/dev/null || { echo "furnace serve exited before listening" >&2; exit 1; }
    sleep 0.05
done
grep -q listening "$TMP/serve.out" || { echo "furnace serve did not listen within 30 s" >&2; exit 1; }
URL="$(sed -n 's/listening on //p' "$TMP/serve.out")"
farm() {  # farm WORKERS THREADS_EACH
    local wp=()
    for i in $(seq "$1"); do
        "$F" worker --coordinator "$URL" --threads "$2" --name "w$i" --cache "$TMP/c$i" 2>/dev/null &
        wp+=($!); PIDS+=($!)
    done
    local t0 t1 t2 t3; t0=$(date +%s.%N)
    "$F" submit "$scene" --coordinator "$URL" --spp "$spp" --tile "$tile" --spp-per-chunk "$chunk" --wait -o "$TMP/farm.exr" > /dev/null 2>&1
    t1=$(date +%s.%N)
    kill "${wp[@]}" 2>/dev/null || true; wait "${wp[@]}" 2>/dev/null || true
    local n=$(($1 * $2)); t2=$(date +%s.%N)
    "$F" render "$scene" --spp "$spp" --threads "$n" -o "$TMP/local.exr" > /dev/null 2>&1
    t3=$(date +%s.%N)
    cmp -s "$TMP/farm.exr" "$TMP/local.exr" && same=identical || same=DIFFERENT
    awk -v w="$1" -v e="$2" -v f="$t1" -v f0="$t0" -v l="$t3" -v l0="$t2" -v s="$same" \
        'BEGIN { f -= f0; l -= l0; printf "%2d workers x %2d threads: farm %7.2f s, furnace render --threads %2d %7.2f s, farm/render %.2f, bytes %s\n", w, e, f, w * e, l, f / l, s }'
}
for w in $THREADS; do farm "$w" 1; done
[ "$most" -gt 1 ] && farm 1 "$most"
exit 0
