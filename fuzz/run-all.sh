#!/usr/bin/env bash
# Runs every fuzz target for SECONDS each, one after the other, on a COPY of the committed seed
# corpus (corpus/ never grows here), and prints per target and in total the executions and the
# crashes. Exits nonzero when any target crashed (a panic, an abort, a timeout, an out-of-memory)
# or failed to run; crash inputs are kept under fuzz/artifacts/<target>/.
#
#   fuzz/run-all.sh SECONDS [TARGET...]     (default: every target of fuzz/Cargo.toml)
#
# FUZZ_SANITIZER=none|address (default address) picks cargo fuzz's sanitizer: `none` builds and
# runs faster (vlem itself forbids unsafe code), `address` also catches memory errors in the unsafe
# code of dependencies (image decoders). Each has its own build dir (fuzz/target, fuzz/target-none).
#
# Installs nothing. Needs cargo-fuzz (`cargo install cargo-fuzz --locked`) and a C++ compiler (for
# libFuzzer). cargo fuzz passes nightly-only flags (-Zsanitizer, sanitizer coverage) to rustc; on a
# stable toolchain RUSTC_BOOTSTRAP=1 lets rustc accept them, so this works on stable and nightly.
set -uo pipefail
cd "$(dirname "$0")"

usage() { echo "usage: fuzz/run-all.sh SECONDS [TARGET...]" >&2; exit 2; }
[[ $# -ge 1 && $1 =~ ^[0-9]+$ && $1 -gt 0 ]] || usage
seconds=$1
shift

if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "run-all: cargo-fuzz is not installed; install it with:" >&2
    echo "    cargo install cargo-fuzz --locked" >&2
    exit 2
fi

export RUSTC_BOOTSTRAP=1
# -O: build with fuzz/Cargo.toml's release profile instead of cargo fuzz's global debug assertions,
# so overflow checks and debug assertions cover vlem's crates and not third-party decoders (whose
# release builds wrap, e.g. zune-jpeg; see the profile there).
sanitizer=${FUZZ_SANITIZER:-address}
case $sanitizer in
    address) build_dir=target ;;
    none) build_dir=target-none ;;
    *) echo "run-all: FUZZ_SANITIZER must be none or address, not $sanitizer" >&2; exit 2 ;;
esac
# The fuzz crate is its own workspace: keep its builds out of the main target dir, one build dir
# per sanitizer so that switching does not rebuild.
export CARGO_TARGET_DIR="$PWD/$build_dir"
export CARGO_TERM_COLOR=never

targets=("$@")
if [[ ${#targets[@]} -eq 0 ]]; then
    mapfile -t targets < <(cargo fuzz list)
fi

echo "== cargo fuzz build (${#targets[@]} targets, sanitizer $sanitizer)"
build_start=$SECONDS
if ! cargo fuzz build -O --sanitizer "$sanitizer"; then
    echo "run-all: the fuzz targets do not build" >&2
    exit 1
fi
echo "built in $((SECONDS - build_start)) s"

work="$PWD/work"
rm -rf "$work"
mkdir -p "$work"
total_execs=0
total_crashes=0
failed=()
summary=()
for target in "${targets[@]}"; do
    if [[ ! -d corpus/$target ]]; then
        echo "run-all: no seed corpus corpus/$target" >&2
        failed+=("$target")
        continue
    fi
    echo "== $target: ${seconds} s"
    copy="$work/corpus/$target"
    mkdir -p "$copy" "artifacts/$target"
    cp -R "corpus/$target/." "$copy/"
    log="$work/$target.log"
    marker="$work/$target.started"
    touch "$marker"
    # -timeout: one input running longer than this is a hang (reported as a crash);
    # -rss_limit_mb: the memory a target may use before it counts as an out-of-memory crash.
    # -fork=1 keeps fuzzing after a crash (each one is written to artifacts/ and counted), so one
    # bug does not hide the next.
    cargo fuzz run -O --sanitizer "$sanitizer" "$target" "$copy" -- \
        -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 -fork=1 -ignore_crashes=1 \
        -ignore_timeouts=1 -ignore_ooms=1 -print_final_stats=1 >"$log" 2>&1
    status=$?
    # With -fork, libFuzzer's last status line reads "... exec/s: N ... crashes: C ..." and the
    # final stats "stat::number_of_executed_units: N".
    execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -n 1)
    if [[ -z $execs ]]; then
        execs=$(grep -o '#[0-9]*' "$log" | tr -d '#' | sort -n | tail -n 1)
    fi
    execs=${execs:-0}
    crashes=$(find "artifacts/$target" -type f -newer "$marker" \( -name 'crash-*' -o -name 'timeout-*' -o -name 'oom-*' -o -name 'leak-*' \) | wc -l)
    if [[ $status -ne 0 && $crashes -eq 0 ]]; then
        echo "run-all: $target exited with status $status without a crash file; last lines:" >&2
        tail -n 20 "$log" >&2
        failed+=("$target")
    fi
    if [[ $crashes -gt 0 ]]; then
        echo "run-all: $target: $crashes crashing input(s) in fuzz/artifacts/$target/; first report:" >&2
        grep -m 1 -B 2 -A 25 -E '^(==[0-9]+==|thread .* panicked)' "$log" >&2 || tail -n 30 "$log" >&2
        failed+=("$target")
    fi
    summary+=("$(printf '%-20s %12s executions %4s crashes' "$target" "$execs" "$crashes")")
    total_execs=$((total_execs + execs))
    total_crashes=$((total_crashes + crashes))
done

echo "== summary (${seconds} s per target)"
printf '%s\n' "${summary[@]}"
printf '%-20s %12s executions %4s crashes\n' "total" "$total_execs" "$total_crashes"
if [[ ${#failed[@]} -gt 0 ]]; then
    echo "run-all: FAILED: ${failed[*]} (logs in fuzz/work/)" >&2
    exit 1
fi
