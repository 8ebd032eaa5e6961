#!/usr/bin/env bash
# Furnace beside Mitsuba 3 (scalar_rgb and llvm_ad_rgb) on every scene, in one run:
# samples per second (interleaved, so that machine noise hits all three alike), their ratios,
# and the time each needs to reach Mitsuba's own 64-spp error against the scene's reference.
#
#   bench/vs-mitsuba.sh [THREADS=2] [REPEATS=3] [SCENE.xml:SPP ...]
#
# SEEDS=N (default 1): both errors are medians over seeds 0..N-1 (under a small bright sun
# one seed's relMSE is a lottery of fireflies); ERRORS=0 leaves the error columns out. FURNACE=BINARY measures that binary instead of
# building this tree; PGO=1 builds it profile-guided (deploy/build-pgo.sh, about 8 minutes, the
# binary to ship) and measures that. Default scenes: tests/scenes/{cbox,textured,envmap,
# thinlens,hair}.xml at 64 spp and examples/whimsical.xml at 16. Needs Mitsuba 3:
# bench/peers/setup.sh (venv outside the repo, $PEERS_VENV, default ../peers-venv), or MITSUBA_PY
# (a python3 whose PYTHONPATH holds mitsuba: bench/peers/pack-offline.sh packs one for a
# machine without a network).
#
# Samples/s: median over REPEATS of width * height * spp / render seconds (scene loading
# excluded for all three); llvm gets one untimed warm-up per scene to fill Dr.Jit's kernel
# cache. Error: relMSE against tests/scenes/refs/NAME.exr (scenes without one get none).
# Mitsuba's 64-spp error is measured on scalar_rgb renders (seed 0, or the median over SEEDS); llvm_ad_rgb uses the
# same independent sampler, so its 64-spp error is the same in expectation. Furnace's renders
# are deterministic: it renders 8, 12, 16, 24, 32, 48, 64, 96, 128 spp until its error is at
# most Mitsuba's, and the spp that reaches it is interpolated log-log between the last two,
# to a tenth of a sample (rounded to whole samples, as it was before issue 15's thirty-sixth
# step, it moved the time-to-error ratio by up to 1.5% near 34 spp).
# Time to error = that many samples at the measured samples/s.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
THREADS="${1:-2}"; REPEATS="${2:-3}"; SEEDS="${SEEDS:-1}"; shift $(( $# < 2 ? $# : 2 ))
SCENES=("$@")
if [ ${#SCENES[@]} -eq 0 ]; then
    for s in cbox textured envmap thinlens hair; do SCENES+=("$ROOT/tests/scenes/$s.xml:64"); done
    SCENES+=("$ROOT/examples/whimsical.xml:16")
fi
PY="${MITSUBA_PY:-$ROOT/bench/peers/py.sh}"   # or a python3 whose PYTHONPATH holds mitsuba (bench/peers/pack-offline.sh)
TMP="$(mktemp -d)"; trap 'rm -rf "$TMP"' EXIT

if [ -z "${FURNACE:-}" ] && [ -n "${PGO:-}" ]; then   # PGO=1: the profile-guided build, as shipped
    "$ROOT/deploy/build-pgo.sh" >&2
    FURNACE="$ROOT/target/pgo/furnace"
fi
if [ -z "${FURNACE:-}" ]; then   # FURNACE=path/to/furnace measures that binary instead
    (cd "$ROOT" && cargo build --release --quiet)   # in the repository, for its .cargo/config.toml
    FURNACE="$ROOT/target/release/furnace"
fi

furnace_secs() { # SCENE SPP OUT
    "$FURNACE" render "$1" --spp "$2" --threads "$THREADS" -o "$3" 2>&1 \
        | sed -n 's/.* in \([0-9.]*\)s on .*/\1/p'
}
mitsuba_secs() { # VARIANT SCENE SPP OUT; prints nothing if Mitsuba fails
    "$PY" "$ROOT/bench/peers/render.py" "$2" --variant "$1" --spp "$3" --threads "$THREADS" \
        --out "$4" 2>/dev/null | sed -n 's/.* seconds=\([0-9.]*\) .*/\1/p' || true
}
relmse() { "$FURNACE" compare "$1" "$2" 2>/dev/null | awk '/^relMSE/ {print $2}'; }
median() { sort -g | awk '{a[NR]=$1} END {if (NR) print (NR%2) ? a[(NR+1)/2] : (a[NR/2]+a[NR/2+1])/2}'; }

echo "Furnace $(git -C "$ROOT" rev-parse --short HEAD) beside Mitsuba 3, $THREADS threads, median of $REPEATS, errors over $SEEDS seed(s) ($(date -u +%F))"
echo "Furnace traces with: $("$FURNACE" render "${SCENES[0]%:*}" --spp 1 --threads 1 -o "$TMP/k.exr" 2>&1 | sed -n 's/.*tracing with an //p')"
echo
echo "| scene | spp | Furnace Ms/s | scalar_rgb | llvm_ad_rgb | F / scalar | F / llvm | Mitsuba 64-spp relMSE | Furnace spp to reach it | llvm time / Furnace time to it |"
echo "|---|---|---|---|---|---|---|---|---|---|"
for entry in "${SCENES[@]}"; do
    scene="${entry%:*}"; spp="${entry##*:}"; name="$(basename "$scene" .xml)"
    W=$(grep -o '"width" value="[0-9]*"' "$scene" | head -1 | grep -o '[0-9]*"$' | tr -d '"')
    H=$(grep -o '"height" value="[0-9]*"' "$scene" | head -1 | grep -o '[0-9]*"$' | tr -d '"')
    samples=$(( W * H * spp ))
    mitsuba_secs llvm_ad_rgb "$scene" "$spp" "$TMP/warm.exr" > /dev/null
    : > "$TMP/f"; : > "$TMP/s"; : > "$TMP/l"
    for _ in $(seq "$REPEATS"); do
        furnace_secs "$scene" "$spp" "$TMP/f.exr" >> "$TMP/f"
        mitsuba_secs scalar_rgb "$scene" "$spp" "$TMP/s.exr" >> "$TMP/s"
        mitsuba_secs llvm_ad_rgb "$scene" "$spp" "$TMP/l.exr" >> "$TMP/l"
    done
    rate() { local s; s=$(median < "$1"); [ -n "$s" ] && awk -v k="$samples" -v s="$s" 'BEGIN {printf "%.3f", k / s / 1e6}' || echo "failed"; }
    f=$(rate "$TMP/f"); sc=$(rate "$TMP/s"); ll=$(rate "$TMP/l")
    ratio() { [[ "$2" =~ ^[0-9.]+$ ]] && awk -v a="$1" -v b="$2" 'BEGIN {printf "%.2fx", a / b}' || echo "-"; }

    ref="$ROOT/tests/scenes/refs/$name.exr"
    m_err="-"; f_spp="-"; tte="-"
    if [ -f "$ref" ] && [ "${ERRORS:-1}" != 0 ]; then
        : > "$TMP/me"
        for seed in $(seq 0 $((SEEDS - 1))); do
            rm -f "$TMP/m64.exr"
            "$PY" "$ROOT/bench/peers/render.py" "$scene" --variant scalar_rgb --spp 64 --seed "$seed" \
                --threads "$THREADS" --out "$TMP/m64.exr" > /dev/null 2>&1 || true
            [ -f "$TMP/m64.exr" ] && relmse "$TMP/m64.exr" "$ref" >> "$TMP/me"
        done
        [ -s "$TMP/me" ] && m_err=$(median < "$TMP/me")
        if [ "$m_err" != "-" ]; then
            prev_s=""; prev_e=""
            for s in 8 12 16 24 32 48 64 96 128; do
                e=$(for seed in $(seq 0 $((SEEDS - 1))); do
                    "$FURNACE" render "$scene" --spp "$s" --seed "$seed" --threads "$THREADS" -o "$TMP/ladder.exr" > /dev/null 2>&1
                    relmse "$TMP/ladder.exr" "$ref"
                done | median)
                if awk -v e="$e" -v m="$m_err" 'BEGIN {exit !(e <= m)}'; then
                    f_spp=$(awk -v s1="$prev_s" -v e1="$prev_e" -v s2="$s" -v e2="$e" -v m="$m_err" \
                        'BEGIN { if (s1 == "" || e1 <= e2) {printf "%.1f", s2; exit}
                                 printf "%.1f", s1 * exp(log(e1 / m) / log(e1 / e2) * log(s2 / s1)) }')
                    break
                fi
                prev_s=$s; prev_e=$e
            done
            [ "$f_spp" = "-" ] && f_spp=">128"
            if [[ "$f_spp" =~ ^[0-9.]+$ && "$ll" =~ ^[0-9.]+$ ]]; then
                tte=$(awk -v fs="$f_spp" -v f="$f" -v l="$ll" 'BEGIN {printf "%.2fx", (64 / l) / (fs / f)}')
            fi
        fi
        rm -f "$TMP/m64.exr"
    fi
    echo "| $name (${W}x${H}) | $spp | $f | $sc | $ll | $(ratio "$f" "$sc") | $(ratio "$f" "$ll") | $m_err | $f_spp | $tte |"
done
