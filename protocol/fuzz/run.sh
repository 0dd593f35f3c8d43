#!/usr/bin/env bash
# Fuzzes every target (or the ones named) for SECONDS each, starting from the checked-in seeds.
#
#     protocol/fuzz/run.sh SECONDS [TARGET...]
#
# Each target runs on a temporary copy of fuzz/seeds/<target>/ (the seeds stay untouched), with
# debug assertions and overflow checks on (-a). Prints one line per target:
#     <target>  runs=<executions>  corpus=<files>  ok|CRASH
# and exits non-zero if any target crashed (its artifact path and log are printed). An input
# that runs longer than FUZZ_TIMEOUT seconds (default 30) counts as a crash: a hang (libFuzzer's
# own default is 20 minutes, and -max_total_time does not interrupt a running input). Set
# FUZZ_KEEP_CORPUS=1 to keep the grown corpora (their paths are printed).
set -uo pipefail

if [[ $# -lt 1 || ! $1 =~ ^[0-9]+$ ]]; then
    echo "usage: $0 SECONDS [TARGET...]" >&2
    exit 2
fi
seconds=$1
shift

fuzz_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
cd "$fuzz_dir/.." # protocol/: cargo fuzz finds fuzz/ from here

targets=("$@")
if [[ ${#targets[@]} -eq 0 ]]; then
    targets=(decode_raw roundtrip link controller)
fi

# Build first (same flags as the runs below, so they do not rebuild), showing errors.
for t in "${targets[@]}"; do
    if ! build_log=$(cargo +nightly fuzz build -a "$t" 2>&1); then
        echo "$build_log" | tail -40 >&2
        echo "$t: build failed" >&2
        exit 2
    fi
done

failed=0
for t in "${targets[@]}"; do
    work=$(mktemp -d "${TMPDIR:-/tmp}/lightrig-fuzz-$t.XXXXXX")
    corpus="$work/corpus"
    mkdir -p "$corpus"
    if [[ -d "$fuzz_dir/seeds/$t" ]]; then
        cp "$fuzz_dir/seeds/$t/"* "$corpus/" 2>/dev/null
    fi
    log="$work/fuzz.log"
    cargo +nightly fuzz run -a "$t" "$corpus" -- \
        -max_total_time="$seconds" -timeout="${FUZZ_TIMEOUT:-30}" -rss_limit_mb=2048 \
        -print_final_stats=1 >"$log" 2>&1
    rc=$?
    runs=$(grep -oE 'stat::number_of_executed_units: *[0-9]+' "$log" | grep -oE '[0-9]+$' | tail -1)
    if [[ -z $runs ]]; then
        runs=$(grep -oE '#[0-9]+' "$log" | tail -1 | tr -d '#')
    fi
    size=$(find "$corpus" -type f | wc -l)
    if [[ $rc -eq 0 ]]; then
        verdict=ok
    else
        verdict=CRASH
        failed=1
    fi
    printf '%-11s runs=%-10s corpus=%-6s %s\n' "$t" "${runs:-?}" "$size" "$verdict"
    if [[ $rc -ne 0 ]]; then
        artifact=$(grep -oE 'Test unit written to [^ ]+' "$log" | tail -1 | sed 's/Test unit written to //')
        echo "  exit code $rc; artifact: ${artifact:-none}; log: $log"
        echo "  reproduce: (cd $(pwd) && cargo +nightly fuzz run -a $t ${artifact:-<artifact>})"
        grep -m1 -E "panicked at|ERROR: |SUMMARY: " "$log" | sed 's/^/  /'
    elif [[ ${FUZZ_KEEP_CORPUS:-0} == 1 ]]; then
        echo "  corpus kept: $corpus"
    else
        rm -rf "$work"
    fi
done
exit "$failed"
