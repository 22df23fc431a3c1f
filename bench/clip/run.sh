#!/bin/bash
# CLIP ViT-B/16 image tower, images per second: candle (vlem-backends, example clip_bench) against
# PyTorch transformers, at 1 and 2 threads, batches of 1 and 16, random weights (no pretrained
# weights are needed for speed). Two rounds: on a shared machine take the better of the two.
#
#   pip install torch transformers                       # the reference only; not needed by vlem
#   bench/clip/run.sh [MODEL_DIR]                        # default /tmp/clip-vit-b16-random
set -euo pipefail
cd "$(dirname "$0")/../.."
M=${1:-/tmp/clip-vit-b16-random}
[ -f "$M/model.safetensors" ] || python3 bench/clip/make_random_b16.py "$M"
cargo build --release -p vlem-backends --features clip --example clip_bench
BIN=target/release/examples/clip_bench
for round in 1 2; do
  for t in 1 2; do
    echo "round $round, $(uptime | sed 's/.*load/load/')"
    RAYON_NUM_THREADS=$t "$BIN" "$M" --batch 1 16 --repeat 3
    python3 bench/clip/torch_bench.py "$M" --threads "$t" --batch 1 16 --repeat 3 2>&1 | grep '^torch'
  done
done
