#!/usr/bin/env bash
# Set up the Mitsuba 3 reference renderer used by the side-by-side harness.
#   peers/setup.sh            (root for the apt step; SKIP_APT=1 to skip it)
# Creates the venv OUTSIDE the repo: $PEERS_VENV, default <repo>/../peers-venv.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
VENV="${PEERS_VENV:-$(cd "$HERE/../../.." && pwd)/peers-venv}"

MITSUBA_VERSION=3.9.1   # pulls drjit 1.5.0
DRJIT_VERSION=1.5.0
NUMPY_VERSION=2.4.6

# 1. libLLVM for the llvm_ad_* variants.  Dr.Jit dlopen()s libLLVM at runtime
#    (override with DRJIT_LIBLLVM_PATH).  Debian 12's default LLVM 15 is too
#    old for drjit 1.5 (aborts: "LLVM ERROR: Cannot select: fminimum"); the
#    libllvm19 package from bookworm main works.  scalar_* variants need none.
if [ "${SKIP_APT:-0}" != 1 ] && ! ldconfig -p 2>/dev/null | grep -q 'libLLVM[-.]\(so\.\)\?19'; then
    if [ "$(id -u)" = 0 ]; then
        apt-get update
        apt-get install -y --no-install-recommends libllvm19
    else
        echo "note: run 'sudo apt-get install libllvm19' for the llvm_ad_* variants" >&2
    fi
fi

# 2. venv + pinned wheels (mi.Bitmap reads/writes EXR itself: no OpenEXR pkg needed)
[ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet \
    "mitsuba==$MITSUBA_VERSION" "drjit==$DRJIT_VERSION" "numpy==$NUMPY_VERSION"
"$VENV/bin/python" -m pip freeze | grep -Ei '^(mitsuba|drjit|numpy)=='

# 3. Which variants actually render here (cuda_* fails without a GPU).
PEERS_VENV="$VENV" "$HERE/py.sh" "$HERE/check_variants.py" || true
