#!/usr/bin/env bash
# Runs every fuzz target at once for SECONDS each, FORK processes per target, starting from
# CORPUS/TARGET and growing OUT/corpus/TARGET; crashes, timeouts and out-of-memory inputs go to
# OUT/artifacts. Built targets in BIN (cargo +nightly fuzz build -a; see fuzz/README.md).
#   fuzz/run-all.sh BIN CORPUS OUT [SECONDS=600] [FORK=2]
set -euo pipefail
bin=$1 corpus=$2 out=$3 secs=${4:-600} fork=${5:-2}
mkdir -p "$out/artifacts"
for t in scene_xml obj ply curves image partial job_spec; do
    mkdir -p "$out/corpus/$t"
    cp -r "$corpus/$t/." "$out/corpus/$t/"
    "$bin/$t" "$out/corpus/$t" -fork="$fork" -ignore_crashes=1 -ignore_ooms=1 -ignore_timeouts=1 \
        -max_total_time="$secs" -rss_limit_mb=2048 -timeout=10 -max_len=16384 \
        -artifact_prefix="$out/artifacts/$t-" > "$out/$t.log" 2>&1 &
done
wait
for t in scene_xml obj ply curves image partial job_spec; do
    runs=$(grep -ao 'exec/s: [0-9]*' "$out/$t.log" | tail -1)
    echo "$t: $(ls "$out/corpus/$t" | wc -l) inputs, $(grep -ac 'crash-\|timeout-\|oom-\|leak-' "$out/$t.log" || true) artifact lines, $(grep -a 'INFO: fuzzed for' "$out/$t.log" | tail -1) $runs"
done
ls -la "$out/artifacts"
