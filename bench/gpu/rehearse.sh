#!/usr/bin/env bash
# Rehearses bench/gpu/check.sh here, on a machine without a GPU, so that a lent GPU's few minutes
# are not lost to a wrong path, flag or file in the check or the carried package. It runs the check
# on the package bench/gpu/build.sh made (target/gpu-check), as the device tool would, but with a
# stand-in NVIDIA driver: a small libcuda.so.1 built here whose cuInit answers "no CUDA-capable
# device" (CUDA_ERROR_NO_DEVICE), as a real driver on a machine without a GPU does. The CUDA
# libraries come from bench/.venv-cuda (`source bench/gpu/cuda-toolchain.sh --link`).
#
#   bench/gpu/rehearse.sh
#
# Every step of the check then runs: the package unpacks, the libraries are found, each binary
# starts and parses its arguments, each Python script starts, and the summary and the two hand-back
# files are written. A step is expected to fail here, but only for one of these reasons, each found
# in its log: vlem's error naming CUDA_ERROR_NO_DEVICE; a Python module the GPU machine has and this
# one may lack (torch, numpy, transformers, safetensors); the random-weight model folders that the
# check makes with torch first, missing for that reason. A log that fails for any other reason, a
# crash (a signal), a missing test binary or a missing hand-back file fails the rehearsal, with the
# log's first error lines; so does a reference row skipped for want of a package the check carries
# (timm, segment_anything, mobile_sam, open_clip, dinov3: build.sh's py/), which it would also miss
# there. NVIDIA's own link stub (lib/libcuda.so of the wheels) is not used: its cuGetErrorString
# leaves the message unset, and the binaries crash formatting the error.
#
# What it cannot show: anything after the device opens (timings, the parsing of a step's output,
# memory). Exit status 0 when every step failed only for an expected reason.
set -euo pipefail
cd "$(dirname "$0")/../.."
packed=target/gpu-check
if [ ! -f "$packed/payload.tar.xz" ]; then
    echo "rehearse.sh: no $packed/payload.tar.xz: run CUDA_COMPUTE_CAP=90 bench/gpu/build.sh first" >&2
    exit 2
fi
cuda_lib=$(ls -d bench/.venv-cuda/lib/python3*/site-packages/nvidia/cu13/lib 2>/dev/null | head -n 1)
if [ -z "$cuda_lib" ] || [ ! -e "$cuda_lib/libcublas.so.13" ]; then
    echo "rehearse.sh: no CUDA 13 libraries in bench/.venv-cuda: run 'source bench/gpu/cuda-toolchain.sh --link'" >&2
    exit 2
fi
cuda_lib=$PWD/$cuda_lib

work=$PWD/target/gpu-rehearsal
rm -rf "$work" && mkdir -p "$work/bin" "$work/driver"
tar -C "$work" -xJf "$packed/payload.tar.xz" bin

# The stand-in driver exports every driver function the package's binaries link (they bind all
# symbols at load): cuInit fails with CUDA_ERROR_NO_DEVICE, the error strings are real, and every
# other call (never reached after a failed cuInit) answers CUDA_ERROR_NOT_INITIALIZED.
special=" cuInit cuDeviceGetCount cuGetErrorString cuGetErrorName "
{
    cat <<'C'
/* A stand-in NVIDIA driver for bench/gpu/rehearse.sh: a machine with the driver and no GPU. */
typedef int CUresult;
enum { CUDA_SUCCESS = 0, CUDA_ERROR_INVALID_VALUE = 1, CUDA_ERROR_NOT_INITIALIZED = 3,
       CUDA_ERROR_NO_DEVICE = 100 };
CUresult cuInit(unsigned flags) { (void)flags; return CUDA_ERROR_NO_DEVICE; }
CUresult cuDeviceGetCount(int *count) {
    if (count) *count = 0;
    return CUDA_ERROR_NOT_INITIALIZED;
}
CUresult cuGetErrorString(CUresult error, const char **text) {
    if (!text) return CUDA_ERROR_INVALID_VALUE;
    *text = error == CUDA_ERROR_NO_DEVICE ? "no CUDA-capable device is detected"
                                          : "initialization error";
    return CUDA_SUCCESS;
}
CUresult cuGetErrorName(CUresult error, const char **name) {
    if (!name) return CUDA_ERROR_INVALID_VALUE;
    *name = error == CUDA_ERROR_NO_DEVICE ? "CUDA_ERROR_NO_DEVICE" : "CUDA_ERROR_NOT_INITIALIZED";
    return CUDA_SUCCESS;
}
C
    find "$work/bin" -type f -print0 | xargs -0 -n 1 nm -D --undefined-only 2>/dev/null |
        awk '$1 == "U" && $2 ~ /^cu[A-Z]/ && $2 !~ /@/ { print $2 }' | sort -u |
        while read -r name; do
            [[ $special == *" $name "* ]] ||
                echo "CUresult $name(void) { return CUDA_ERROR_NOT_INITIALIZED; }"
        done
} >"$work/driver/stub.c"
cc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$work/driver/libcuda.so.1" "$work/driver/stub.c"
rm -rf "${work:?}/bin"

# The package is what is rehearsed: it says which commit it was built from (build.sh again after a
# change to the Rust code; the scripts the check runs come from the working tree).
echo "== package: $(tr '\n' ' ' <"$packed/BUILD")(HEAD is $(git rev-parse --short HEAD))"
echo "== bench/gpu/check.sh with a stand-in driver (no GPU), no time budget"
status=0
LD_LIBRARY_PATH="$work/driver:$cuda_lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" \
    VLEM_GPU_CHECK_BUDGET_S=0 bench/gpu/check.sh "$work/hand-back" >"$work/check.out" 2>&1 || status=$?
echo "   check.sh exited $status ($(tail -n 1 "$work/check.out"))"

problems=0
problem() {
    echo "   REHEARSAL: $*"
    problems=$((problems + 1))
}
for file in summary.txt logs.tar.gz; do
    [ -s "$work/hand-back/$file" ] || problem "no $file handed back"
done
grep -q '^== libraries: all found' "$work/check.out" || problem "the check did not find its libraries"
while read -r line; do
    problem "$line"
done < <(grep -E 'no test binary|Segmentation fault|Illegal instruction|Aborted|core dumped|Killed' \
    "$work/check.out" || true)

# The reference packages the package carries (build.sh's py/) must import but for torch, which the
# GPU machine has: a reference row skipped for want of one of them would be skipped there too.
while read -r line; do
    problem "$line (build.sh carries it: is it in bench/.venv-torch, or DINOV3_SRC set?)"
done < <(grep -E "skipped \(python3 -c 'import .*No module named '(timm|segment_anything|mobile_sam|open_clip|dinov3)'" \
    "$work/check.out" || true)

# A log passes with one of these: the expected failures, or a step that succeeds without a GPU (a
# test binary's summary; sam_bench writing the synthetic SAM weights, which needs no device: that
# step leaves a log only where /tmp holds no weights from an earlier run).
expected="CUDA_ERROR_NO_DEVICE|No module named '(torch|numpy|transformers|safetensors)'|model folder /tmp/[a-z0-9-]*-random \(from \[encoder\] model_dir\) lacks|^test result: ok|synthetic tensors written to /tmp/sam-vit-b-synthetic.safetensors$"
logs=0
for log in target/gpu-check-out/*.log; do
    logs=$((logs + 1))
    if ! grep -qE "$expected" "$log"; then
        problem "$(basename "$log") fails for a reason the rehearsal does not expect:"
        { grep -m 3 -iE 'error|panicked|usage|not found' "$log" || tail -n 5 "$log"; } | sed 's/^/      /'
    fi
done
echo "== $logs step logs read; $problems problem(s)"
[ "$problems" -eq 0 ]
