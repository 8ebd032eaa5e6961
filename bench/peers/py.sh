#!/usr/bin/env bash
# Run python from the peers venv:  peers/py.sh peers/render.py ...  |  peers/py.sh -c '...'
# The venv lives outside the repository: $PEERS_VENV, default <repo>/../peers-venv.
# Also points Dr.Jit at the newest system libLLVM (llvm_* variants need LLVM >= 16;
# LLVM 15 aborts with "LLVM ERROR: Cannot select ... fminimum") unless
# DRJIT_LIBLLVM_PATH is already set.
HERE="$(cd "$(dirname "$0")" && pwd)"
VENV="${PEERS_VENV:-$(cd "$HERE/../../.." && pwd)/peers-venv}"
if [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
    lib="$(ldconfig -p 2>/dev/null | awk '{print $NF}' | grep 'libLLVM' \
        | sed -E 's/^(.*libLLVM[-.](so\.)?([0-9]+).*)$/\3 \1/' | sort -n | tail -1 | cut -d' ' -f2)"
    [ -n "$lib" ] && export DRJIT_LIBLLVM_PATH="$lib"
fi
exec "$VENV/bin/python" "$@"
