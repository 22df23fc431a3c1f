#!/usr/bin/env bash
# An nvcc for `cargo check --features cuda`, set as NVCC: candle's own kernels get empty outputs,
# every other call goes to the real nvcc on PATH (vlem's kernel, `--version`, ...).
#
#   source bench/gpu/cuda-toolchain.sh
#   CARGO_TARGET_DIR="$PWD/target/cuda-check" NVCC="$PWD/bench/gpu/nvcc-for-check.sh" \
#       cargo check -p vlem-backends --features clip,cuda
#
# Why: candle-kernels' build script compiles its 26 .cu files with nvcc whenever the `cuda` feature
# is on, `cargo check` included: PTX for its element-wise kernels and a static library of
# quantized-matmul and mixture-of-experts kernels that vlem never calls. That is ~10 minutes on two
# cores, nine tenths of CI's `cuda` step before this script, and a check reads none of it (the PTX
# goes into `include_str!`, the library is never linked). candle is pinned by Cargo.lock and the
# compiler by cuda-toolchain.sh, so those kernels compile the same on every run; they are compiled
# for real by every build that links (bench/gpu/build.sh, `cargo build --features cuda`). vlem's own
# kernel (vlem-backends/src/fused_attention.cu) is not candle's: it goes to the real nvcc here, so
# an error in it still fails the check.
#
# Only with a target folder of its own (CARGO_TARGET_DIR, absolute): the empty kernels stay in that
# folder's build-script outputs, and candle's build script keeps outputs it finds, so a build that
# links in the same folder would get them. It refuses to stand in for candle's kernels otherwise.
# Never use it for a build that links or runs.
set -euo pipefail

real_nvcc() {
    local self candidate
    self=$(realpath "${BASH_SOURCE[0]}")
    # The first nvcc on PATH that is not this script.
    while IFS= read -r candidate; do
        if [ "$(realpath "$candidate")" != "$self" ]; then
            exec "$candidate" "$@"
        fi
    done < <(type -ap nvcc)
    echo "nvcc-for-check: no nvcc on PATH (source bench/gpu/cuda-toolchain.sh first)" >&2
    exit 127
}

args=("$@")
inputs=() output="" output_dir="" mode=""
while [ $# -gt 0 ]; do
    arg=$1
    shift
    case $arg in
        --ptx) mode=ptx ;;
        -c) mode=object ;;
        --lib) mode=lib ;;
        -o) output=${1:-} ;;
        --output-directory) output_dir=${1:-} ;;
        *.cu) inputs+=("$arg") ;;
    esac
done

# Candle's calls run inside its build script, whose OUT_DIR must lie in the folder of its own.
check_target_dir() {
    if [[ ${CARGO_TARGET_DIR:-} != /* || ${OUT_DIR:-} != "${CARGO_TARGET_DIR%/}"/* ]]; then
        echo "nvcc-for-check: candle's kernels get empty outputs only in a target folder of its own;" \
            "set CARGO_TARGET_DIR to an absolute folder used for nothing but checks" \
            "(CARGO_TARGET_DIR='${CARGO_TARGET_DIR:-}', OUT_DIR='${OUT_DIR:-}')" >&2
        exit 2
    fi
}

# candle's calls come from its build script, which runs in its package directory (the registry's
# candle-kernels-X.Y.Z); of those, only its three shapes of compilation get empty outputs. Anything
# else (vlem's kernel, --version, --list-gpu-code) goes to the real nvcc with its arguments.
stand_in=""
if [[ $PWD == */candle-kernels-[0-9]* ]]; then
    case $mode in
        lib) [[ $output == */libmoe.a ]] && stand_in=lib ;;
        ptx) [ -n "$output_dir" ] && [ ${#inputs[@]} -eq 1 ] && stand_in=ptx ;;
        object) [ -n "$output" ] && [ ${#inputs[@]} -eq 1 ] && stand_in=object ;;
    esac
fi
[ -n "$stand_in" ] || real_nvcc "${args[@]}"

check_target_dir
case $stand_in in
    # An empty archive: the static library of the quantized and expert kernels.
    lib) printf '!<arch>\n' >"$output" ;;
    ptx)
        name=$(basename "${inputs[0]}" .cu)
        printf '// %s: not compiled (bench/gpu/nvcc-for-check.sh, for cargo check only)\n' \
            "$name" >"$output_dir/$name.ptx"
        ;;
    object) : >"$output" ;;
esac
