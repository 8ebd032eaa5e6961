#!/usr/bin/env bash
# A profile-guided build of furnace (issue 15): the binary to ship to workers and artists.
#
#   deploy/build-pgo.sh [OUT]        (default OUT: target/pgo/furnace)
#
# Both builds use Cargo.toml's `dist` profile (release with fat LTO and one codegen unit).
#
# 1. builds furnace instrumented (-Cprofile-generate) into target/pgo/gen;
# 2. renders the training scenes with it (below: shipped scenes that the benchmarks do not
#    use, so that the gains measured on the benchmark scenes are on scenes it was not trained
#    on), which writes the branch and call counts;
# 3. merges them with llvm-profdata (rustup's llvm-tools component, added if missing) and
#    builds furnace again with them (-Cprofile-use) into target/pgo/use;
# 4. checks that this binary renders the same bytes as a plain `cargo build --release` on
#    the five test scenes (the profile changes code layout, inlining and branch order, never
#    the floating-point operations, so a farm of PGO workers still gives furnace render's
#    bytes), and only then copies it to OUT.
#
# Two dist builds and a release build (the plain one is cargo's usual, reused when it is up
# to date): about 8 minutes on 2 cores, 12 when the plain one is built too. Exit 0: OUT is built and checked. Measured in docs/BENCHMARKS.md
# ("Issue 15, tenth step"). The profile flags go to the target's crates only (--target), not
# to build scripts and procedural macros. RUSTFLAGS, if set, is added to them; otherwise the
# x86-64 rustflags of .cargo/config.toml are (cargo ignores the config when flags come from
# the environment), so that the profile-guided binary is built as the plain one is.
set -euo pipefail
out=$(realpath -m "${1:-$(dirname "$0")/../target/pgo/furnace}")
cd "$(dirname "$0")/.."
step() { echo "build-pgo: $*"; }
fail() { echo "build-pgo: FAILED: $*" >&2; exit 1; }

[ -z "${CARGO_ENCODED_RUSTFLAGS:-}" ] || fail "CARGO_ENCODED_RUSTFLAGS is set: pass extra flags in RUSTFLAGS"
sysroot=$(rustc --print sysroot)
host=$(rustc -vV | sed -n 's/^host: //p')
profdata="$sysroot/lib/rustlib/$host/bin/llvm-profdata"
if [ ! -x "$profdata" ]; then
    step "adding rustup's llvm-tools (for llvm-profdata)"
    rustup component add llvm-tools || fail "rustup component add llvm-tools"
fi
[ -x "$profdata" ] || fail "no llvm-profdata at $profdata"

# The flags that .cargo/config.toml gives x86-64 builds (x86-64-v2): cargo ignores the
# config's rustflags when flags come from the environment, as they do here, so they are added.
cpu=()
case "$host" in
x86_64-*)
    words=$(python3 -c 'import tomllib
config = tomllib.load(open(".cargo/config.toml", "rb"))
print("\n".join(config["target"]["cfg(target_arch = \"x86_64\")"]["rustflags"]))') \
        || fail "no x86-64 rustflags in .cargo/config.toml"
    mapfile -t cpu <<<"$words"
    ;;
esac

# RUSTFLAGS' words (or, where RUSTFLAGS is not set at all, the config's) and one more flag,
# as cargo's unit-separated list (paths may hold spaces).
flags() {
    local words=() joined
    if [ -n "${RUSTFLAGS+set}" ]; then
        read -ra words <<<"$RUSTFLAGS"
    else
        words=(${cpu[@]+"${cpu[@]}"})
    fi
    words+=("$1")
    joined=$(printf '%s\x1f' "${words[@]}")
    printf '%s' "${joined%$'\x1f'}"
}
build() { # TARGET_DIR FLAG
    env -u RUSTFLAGS CARGO_ENCODED_RUSTFLAGS="$(flags "$2")" \
        cargo build --profile dist --locked --quiet --bin furnace --target "$host" --target-dir "$1"
}

mkdir -p target/pgo
data=$(realpath -m target/pgo/data)
rm -rf "$data"
step "1/4 instrumented build"
build target/pgo/gen "-Cprofile-generate=$data"
gen=$(realpath "target/pgo/gen/$host/dist/furnace")

# The training set: every feature the renderer has (triangles, spheres, fibres, instances,
# textures, the environment map and a sun, every material, the thin lens), none of the
# scenes that bench/vs-mitsuba.sh and bench/ab.sh measure.
train=(
    examples/materials.xml:16 examples/depth-of-field.xml:16 tests/scenes/checker.xml:16
    tests/scenes/fibre.xml:16 tests/scenes/instances.xml:8 tests/scenes/lights.xml:16
    tests/scenes/roughplastic.xml:16 tests/scenes/sun.xml:16
)
step "2/4 training on ${#train[@]} scenes"
for entry in "${train[@]}"; do
    scene=${entry%:*}; spp=${entry##*:}
    "$gen" render "$scene" --spp "$spp" --threads 2 -o target/pgo/train.exr >target/pgo/train.log 2>&1 \
        || { cat target/pgo/train.log; fail "training render of $scene"; }
done
ls "$data"/*.profraw >/dev/null 2>&1 || fail "the training renders wrote no profile to $data"
"$profdata" merge -o target/pgo/merged.profdata "$data" || fail "llvm-profdata merge"
# Named by its contents: cargo sees a new profile as new flags and builds every crate again
# with it (it does not look inside the file a flag names).
profile=$(realpath "target/pgo/furnace-$(sha256sum target/pgo/merged.profdata | cut -c1-16).profdata")
rm -f target/pgo/furnace-*.profdata
mv target/pgo/merged.profdata "$profile"

# The profile holds counts for the renderer's loop: the training reached it.
"$profdata" show --function=render_region "$profile" | grep -q 'furnace_core6render13render_region' \
    || fail "the profile holds no counts for furnace_core::render::render_region"

step "3/4 optimised build with the profile"
build target/pgo/use "-Cprofile-use=$profile"
pgo=$(realpath "target/pgo/use/$host/dist/furnace")

step "4/4 the same bytes as a plain release build"
# cargo's own release build, wherever its target directory is (CARGO_TARGET_DIR, config).
plain=$(cargo build --release --locked --bin furnace --message-format=json \
    | python3 -c 'import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable"):
        print(m["executable"])') || fail "the plain release build"
[ -x "$plain" ] || fail "no plain release binary (cargo said: '$plain')"
check_render() { # BINARY SCENE OUT
    rm -f "$3"
    "$1" render "tests/scenes/$2.xml" --spp 4 --threads 2 -o "$3" >target/pgo/check.log 2>&1 \
        || { cat target/pgo/check.log; fail "render of $2 with $1"; }
}
for scene in cbox textured envmap thinlens hair; do
    check_render "$plain" "$scene" target/pgo/check-plain.exr
    check_render "$pgo" "$scene" target/pgo/check-pgo.exr
    cmp -s target/pgo/check-plain.exr target/pgo/check-pgo.exr \
        || fail "$scene: $pgo renders other bytes than $plain"
done
mkdir -p "$(dirname "$out")"
cp "$pgo" "$out.tmp" && mv -f "$out.tmp" "$out"   # a running worker's binary is replaced, not overwritten
step "$out: built with the profile, renders the plain build's bytes (cbox, textured, envmap, thinlens, hair)"
