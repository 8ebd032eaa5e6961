#!/usr/bin/env bash
# Pack Mitsuba 3 (scalar_rgb and llvm_ad_rgb only) and the libLLVM it needs for a machine with no
# network and a size limit on what reaches it (the lent 16-core machine takes 64 MiB a call):
#
#   bench/peers/pack-offline.sh OUTDIR [PYTHON_VERSION=3.12]
#
# OUTDIR/mitsuba-slim.tar.xz (about 24 MB): the mitsuba and drjit packages for that CPython,
# without the cuda, mono, spectral and polarized variants, and with only the plugins our scenes
# use (a scene with another plugin fails to load, saying which). OUTDIR/libllvm.tar.xz (about
# 34 MB): this machine's libLLVM 19 and the libraries it links that are not glibc's (llvm_ad_rgb
# dlopen()s it; bench/peers/setup.sh installs it). There, with xz or Python's lzma:
#
#   mkdir -p /tmp/mi /tmp/llvm
#   python3 -c "import lzma,shutil,sys; shutil.copyfileobj(lzma.open(sys.argv[1]), sys.stdout.buffer)" \
#       mitsuba-slim.tar.xz | tar -C /tmp/mi -xf -          # likewise libllvm.tar.xz into /tmp/llvm
#   export PYTHONPATH=/tmp/mi DRJIT_LIBLLVM_PATH=/tmp/llvm/libLLVM.so.19.1 LD_LIBRARY_PATH=/tmp/llvm
#   MITSUBA_PY=python3 MITSUBA="scalar_rgb llvm_ad_rgb" bench/scaling.sh ./furnace
#
# The target's python3 needs numpy. What a device call carries is counted with the repository,
# which counts about 32 MiB there (5,000 small files by their disk blocks, it seems: 59 MiB of
# bytes in all was refused), against 64 MiB a call. So send the archives and a furnace binary
# (compressed by xz: 4 MB) in two or three calls to the same warm machine (`split`
# libllvm.tar.xz, cat its parts there), unpacking each into /tmp.
# docs/BENCHMARKS.md, "Multi-core scaling", fifth run, lists the calls that did this.
set -euo pipefail
OUT="$(mkdir -p "$1" && cd "$1" && pwd)"; PYV="${2:-3.12}"
ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
TMP="$(mktemp -d)"; trap 'rm -rf "$TMP"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PYV" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$TMP/whl" mitsuba==3.9.1 drjit==1.5.0
python3 -m pip install -q --no-deps --only-binary=:all: --python-version "$PYV" --implementation cp \
    --platform manylinux_2_28_x86_64 --target "$TMP/site" "$TMP"/whl/*.whl
MI="$TMP/site/mitsuba"
rm -rf "$MI"/cuda_* "$MI"/*spectral* "$MI"/llvm_ad_mono* "$MI"/include "$MI"/cmake "$MI"/mitsuba_stubs \
    "$MI"/pkgconfig "$MI"/data/sunsky "$TMP/site/bin"   # (data/srgb.coeff stays: the hair plugin reads it)
find "$TMP/site" -name __pycache__ -prune -exec rm -rf {} +
# The plugins that SCENES name (default: every scene in tests/scenes and examples), and those
# Mitsuba instantiates by default (merge joins shapes; the rest make RGB spectra). For the six
# benchmark scenes: SCENES="$(echo tests/scenes/{cbox,textured,envmap,thinlens,hair}.xml
# examples/whimsical.xml)".
SCENES="${SCENES:-$(ls "$ROOT"/tests/scenes/*.xml "$ROOT"/examples/*.xml)}"
KEEP=" merge srgb uniform d65 rawconstant regular irregular $(cat $SCENES | grep -o 'type="[a-z_0-9]*"' \
    | sed 's/type="\(.*\)"/\1/' | sort -u | tr '\n' ' ')"
for f in "$MI"/plugins/*.so; do
    n="$(basename "$f" .so)"; case "$KEEP" in *[[:space:]]"$n"[[:space:]]*) ;; *) rm "$f";; esac
done
tar -C "$TMP/site" -cf - . | xz -9 -T0 > "$OUT/mitsuba-slim.tar.xz"
if [ ! -s "$OUT/libllvm.tar.xz" ]; then   # (3 minutes of xz: kept from an earlier run into OUTDIR)
    llvm="$(ldconfig -p | awk '{print $NF}' | grep -m1 'libLLVM.so.19')" \
        || { echo "no libLLVM 19 here: bench/peers/setup.sh installs it" >&2; exit 1; }
    mkdir "$TMP/llvm"; cp -L "$llvm" "$TMP/llvm/"
    ldd "$llvm" | awk '/=>/ {print $3}' | grep -vE '/(libc|libm|libstdc\+\+|libgcc_s|libz|libzstd|liblzma)\.so' \
        | xargs -r cp -L -t "$TMP/llvm/"
    # ICU's data library (31 MB) only as a stub that defines its one symbol: libLLVM needs
    # libxml2, which needs ICU, but only converting text encodings reads the data, and drjit
    # never does (llvm_ad_rgb rendered every benchmark scene with the stub). Saves 7.5 MB of xz.
    for icu in "$TMP"/llvm/libicudata.so.*; do
        [ -e "$icu" ] || continue
        sym="$(nm -D "$TMP"/llvm/libicuuc.so.* | awk '/ U icudt[0-9]*_dat$/ {print $2}')"
        echo "const char $sym[32] = {0};" > "$TMP/stub.c"
        cc -shared -fPIC -o "$icu" -Wl,-soname,"$(basename "$icu")" "$TMP/stub.c"
    done
    tar -C "$TMP/llvm" -cf - . | xz -9 -T0 > "$OUT/libllvm.tar.xz"
fi
ls -l "$OUT"/mitsuba-slim.tar.xz "$OUT"/libllvm.tar.xz
