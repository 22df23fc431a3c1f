#!/bin/bash
# SAM's automatic mask generator on one 640x480 frame, vlem (example `sam_bench`) against the
# reference package (segment-anything 1.0 for ViT-B, mobile_sam for MobileSAM) in the same run,
# full-size networks with random weights, one JSON line per variant with both times and the ratio.
#
#   python3 -m venv bench/.venv-torch     # the reference only; PyTorch stays out of CI
#   bench/.venv-torch/bin/pip install torch torchvision segment-anything timm
#   bench/.venv-torch/bin/pip install --no-deps mobilesam-mirror
#   bench/sam/side_by_side.sh [--threads N] [--points-per-side N] [--points-per-batch N]
#       [--repeat N] [--device cuda] [--dtype f16] [VARIANT...]
#   (--repeat: the best of N generator calls on each side, default 1: on a CPU a call is seconds,
#   on a GPU the first one pays for its kernels' first launch and should not be the one compared)
#   (default variants: mobile-sam vit-b). With VLEM_EXAMPLES=DIR it runs DIR/sam_bench instead of
#   building it (bench/gpu/check.sh, where there is no Rust toolchain).
set -euo pipefail
cd "$(dirname "$0")/../.."
THREADS=2
SIDE=16
BATCH=32
REPEAT=1
DEVICE=cpu
DTYPE=f32
VARIANTS=()
while [ $# -gt 0 ]; do
  case "$1" in
    --threads) THREADS=$2; shift 2 ;;
    --points-per-side) SIDE=$2; shift 2 ;;
    --points-per-batch) BATCH=$2; shift 2 ;;
    --repeat) REPEAT=$2; shift 2 ;;
    --device) DEVICE=$2; shift 2 ;;
    --dtype) DTYPE=$2; shift 2 ;;
    *) VARIANTS+=("$1"); shift ;;
  esac
done
[ ${#VARIANTS[@]} -gt 0 ] || VARIANTS=(mobile-sam vit-b)
PY=${PYTHON:-bench/.venv-torch/bin/python}
EXAMPLES=${VLEM_EXAMPLES:-}
if [ -z "$EXAMPLES" ]; then
  cargo build --release -q -p vlem-backends --features sam --example sam_bench
  EXAMPLES=target/release/examples
fi
for v in "${VARIANTS[@]}"; do
  ours=$(RAYON_NUM_THREADS=$THREADS VLEM_BENCH_DEVICE=$DEVICE VLEM_BENCH_DTYPE=$DTYPE \
    "$EXAMPLES/sam_bench" --variant "$v" \
    --points-per-side "$SIDE" --points-per-batch "$BATCH" --refine off,on --repeat "$REPEAT")
  ref=$("$PY" -W ignore bench/sam/reference_bench.py --variant "$v" --points-per-side "$SIDE" \
    --points-per-batch "$BATCH" --repeat "$REPEAT" \
    --threads "$THREADS" --device "$DEVICE" --dtype "$DTYPE" 2>/dev/null | tail -1)
  OURS="$ours" "$PY" - "$v" "$SIDE" "$THREADS" "$ref" "$DEVICE" "$DTYPE" "$BATCH" <<'PY'
import json, os, re, sys
variant, side, threads, ref = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), json.loads(sys.argv[4])
device, dtype, batch = sys.argv[5], sys.argv[6], int(sys.argv[7])
text = os.environ["OURS"]
enc = float(re.search(r"image encoder ([\d.]+) ms", text).group(1)) / 1e3
dec = float(re.search(r"mask decoder ([\d.]+) ms per prompt", text).group(1))
rows = {m.group(1): float(m.group(2)) / 1e3 for m in re.finditer(r"\| \w+ \| \d+ \| (on|off) \| ([\d.]+) \|", text)}
print(json.dumps({
    "variant": variant, "points_per_side": side, "points_per_batch": batch, "threads": threads,
    "device": device, "dtype": dtype,
    "vlem_image_encoder_s": enc, "vlem_decoder_ms_per_prompt": dec,
    "vlem_generator_s": rows["off"], "vlem_generator_refine_s": rows["on"],
    "reference": ref["impl"], "reference_image_encoder_s": ref["image_encoder_s"],
    "reference_generator_s": ref["generator_s"],
    "ratio_reference_over_vlem": round(ref["generator_s"] / rows["off"], 2),
}))
PY
done
