#!/usr/bin/env bash
# Builds, here (no GPU needed), everything bench/gpu/check.sh runs on a GPU machine that has the
# NVIDIA driver, CUDA 13 and PyTorch but no Rust toolchain and no network, and lays it out in
# target/gpu-check/ (git-ignored) for carrying over:
#   payload.tar.xz           bin/vlem, the binary with the candle models and `cuda`;
#                            bin/tests/*, the candle backends' golden tests (VLEM_TEST_DEVICE=cuda);
#                            bin/examples/*, the model benchmarks and the maps' device-table
#                            benchmark (VLEM_BENCH_DEVICE=cuda); bin/tests/maps_device_table,
#                            the device table against the host table (VLEM_TEST_DEVICE=cuda);
#                            py/, the reference packages the GPU machine may lack (timm,
#                            segment_anything, mobile_sam, and open_clip for the BPE vocabulary
#                            the dinov3 tokenizer tests read, from bench/.venv-torch; Meta's
#                            dinov3 from $DINOV3_SRC)
#   data/icl-livingroom1     the shared sequence of the end-to-end run
#   BUILD                    the compute capability, commit and repository path of the build
#
# Each binary holds ~50 MB of candle's CUDA kernels (most of it the quantised MoE kernels it links
# whole), 650 MB in all; one xz stream with a dictionary larger than a binary stores the shared part
# once: ~17 MB (4 min), under the 64 MiB the device tool carries.
#
#   CUDA_COMPUTE_CAP=90 bench/gpu/build.sh      # 90: H100/H200; 89: RTX 4090/4070 ...
#
# The packages for py/ (pure Python; without them their rows are skipped there):
#   python3 -m venv bench/.venv-torch && bench/.venv-torch/bin/pip install --no-deps timm \
#       segment-anything mobilesam-mirror open_clip_torch==3.3.0
#
# The first build compiles candle's CUDA kernels with nvcc (~5 min) and the release build of the
# models (~15 min on 2 cores); it uses its own target folder, target/gpu-build, so the CPU builds
# are not rebuilt. It prints the size of target/gpu-check (the device tool carries at most 64 MiB).
set -euo pipefail
cd "$(dirname "$0")/../.."
# shellcheck source=cuda-toolchain.sh
source bench/gpu/cuda-toolchain.sh --link
export CARGO_TARGET_DIR=target/gpu-build
export CARGO_PROFILE_RELEASE_DEBUG=false
export CARGO_PROFILE_RELEASE_STRIP=symbols
models=clip,sam,dinov3,naradio,label-text,cuda
cargo build --release --features "$models"
# The benchmarks and the golden tests in one invocation: one resolution of the features, so
# candle's kernels are compiled once for both.
tests=$(cargo build --release -p vlem-backends --features "$models" \
    --example clip_bench --example dinov3_bench --example naradio_bench --example sam_bench \
    --example minilm_bench --example attention_bench --test clip --test dinov3 --test naradio \
    --test sam --test label_text --test tf32 --test fused_attention \
    --message-format=json |
    python3 -c 'import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["kind"] == ["test"]:
        print(m["target"]["name"], m["executable"])')

# The maps' device table: its tests (against the host table) and its benchmark.
maps=$(cargo build --release -p vlem-maps --features cuda --bench device_table --test device_table \
    --message-format=json |
    python3 -c 'import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable"):
        print(m["target"]["kind"][0], m["target"]["name"], m["executable"])')

out=target/gpu-check
stage=target/gpu-check-stage
rm -rf "$out" "$stage"
mkdir -p "$stage/bin/tests" "$stage/bin/examples" "$stage/py" "$out/data"
cp "$CARGO_TARGET_DIR/release/vlem" "$stage/bin/"
for e in clip_bench dinov3_bench naradio_bench sam_bench minilm_bench attention_bench; do
    cp "$CARGO_TARGET_DIR/release/examples/$e" "$stage/bin/examples/"
done
while read -r name path; do
    cp "$path" "$stage/bin/tests/$name"
done <<<"$tests"
while read -r kind name path; do
    if [ "$kind" = bench ]; then
        cp "$path" "$stage/bin/examples/maps_$name"
    else
        cp "$path" "$stage/bin/tests/maps_$name"
    fi
done <<<"$maps"
site=$(ls -d bench/.venv-torch/lib/python3*/site-packages 2>/dev/null | head -n 1 || true)
for pkg in timm segment_anything mobile_sam open_clip; do
    if [ -n "$site" ] && [ -d "$site/$pkg" ]; then
        cp -R "$site/$pkg" "$stage/py/"
    else
        echo "build.sh: $pkg not in bench/.venv-torch; its reference rows are skipped there" >&2
    fi
done
if [ -n "${DINOV3_SRC:-}" ] && [ -d "$DINOV3_SRC/dinov3" ]; then
    cp -R "$DINOV3_SRC/dinov3" "$stage/py/"
else
    echo "build.sh: DINOV3_SRC unset; the dino.txt reference row is skipped there" >&2
fi
find "$stage/py" -name __pycache__ -type d -prune -exec rm -rf {} +
echo "build.sh: compressing $(du -sh "$stage" | cut -f1) of binaries and packages ..." >&2
tar -C "$stage" -cf - bin py | xz -6 --lzma2=dict=256MiB -T1 >"$out/payload.tar.xz"
rm -rf "$stage"
cp -R ../shared/data/icl-livingroom1 "$out/data/"
{
    echo "CUDA_COMPUTE_CAP=$CUDA_COMPUTE_CAP"
    echo "commit=$(git rev-parse --short HEAD)$(git diff --quiet HEAD || echo +changes)"
    echo "root=$PWD"
} >"$out/BUILD"
du -sh "$out" "$out"/*
size=$(du -sm "$out" | cut -f1)
[ "$size" -le 64 ] || echo "build.sh: $size MiB is more than the 64 MiB the device tool carries" >&2
