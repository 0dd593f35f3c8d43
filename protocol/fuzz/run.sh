#!/usr/bin/env bash
# Fuzzes every target (or the ones named) for SECONDS each.
#
#     protocol/fuzz/run.sh SECONDS [TARGET...]
#
# Each target's corpus grows from run to run in $LIGHTRIG_FUZZ_CORPUS/<target> (default
# ${XDG_CACHE_HOME:-~/.cache}/lightrig/fuzz-corpus/<target>), so every run starts where the
# last one on this machine stopped; the checked-in seeds (fuzz/seeds/<target>/) are read as a
# second corpus and never written. Debug assertions and overflow checks are on (-a). Prints one
# line per target:
#     <target>  runs=<executions>  corpus=<files>  ok|CRASH
# and exits non-zero if any target crashed (its artifact path and log are printed). An input
# that runs longer than FUZZ_TIMEOUT seconds (default 30) counts as a crash: a hang (libFuzzer's
# own default is 20 minutes, and -max_total_time does not interrupt a running input).
set -uo pipefail

if [[ $# -lt 1 || ! $1 =~ ^[0-9]+$ ]]; then
    echo "usage: $0 SECONDS [TARGET...]" >&2
    exit 2
fi
seconds=$1
shift

fuzz_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
cache=${LIGHTRIG_FUZZ_CORPUS:-${XDG_CACHE_HOME:-$HOME/.cache}/lightrig/fuzz-corpus}
cd "$fuzz_dir/.." # protocol/: cargo fuzz finds fuzz/ from here

targets=("$@")
if [[ ${#targets[@]} -eq 0 ]]; then
    targets=(decode_raw roundtrip link controller update)
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
    corpus="$cache/$t"
    mkdir -p "$corpus"
    seeds=()
    if [[ -d "$fuzz_dir/seeds/$t" ]]; then
        seeds=("$fuzz_dir/seeds/$t")
    fi
    log="$work/fuzz.log"
    # New inputs go to the first directory only: the kept corpus.
    cargo +nightly fuzz run -a "$t" "$corpus" "${seeds[@]}" -- \
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
    else
        rm -rf "$work"
    fi
done
exit "$failed"
