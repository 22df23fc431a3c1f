#!/usr/bin/env python3
"""Converts an official SAM or MobileSAM PyTorch checkpoint to safetensors for vlem's `sam` proposer.

The tensor names stay those of the checkpoint (`image_encoder.*`, `prompt_encoder.*`,
`mask_decoder.*`), which is what vlem-backends/src/sam loads; integer buffers
(`num_batches_tracked`) are dropped and every tensor is stored as contiguous float32.

Get a checkpoint on a connected machine:
    SAM ViT-B: https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth
    MobileSAM: https://github.com/ChaoningZhang/MobileSAM/raw/master/weights/mobile_sam.pt
then:
    python3 -m pip install torch safetensors
    python3 vlem-backends/goldens/sam/convert_checkpoint.py sam_vit_b_01ec64.pth sam_vit_b.safetensors
and point `[proposer] weights = "..."` (with `variant = "vit-b"` or `"mobile-sam"`) at the result.
"""

import argparse
import sys

import torch
from safetensors.torch import save_file


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="the .pth / .pt file")
    parser.add_argument("output", help="the .safetensors file to write")
    args = parser.parse_args()

    state = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
    # Some training checkpoints wrap the weights.
    for key in ("model", "state_dict"):
        if isinstance(state, dict) and key in state and isinstance(state[key], dict):
            state = state[key]
    tensors = {}
    for name, value in state.items():
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            continue
        tensors[name] = value.detach().to(torch.float32).contiguous()
    prefixes = {n.split(".", 1)[0] for n in tensors}
    missing = {"image_encoder", "prompt_encoder", "mask_decoder"} - prefixes
    if missing:
        print(f"{args.checkpoint} is not a SAM checkpoint: no {sorted(missing)} tensors",
              file=sys.stderr)
        return 1
    save_file(tensors, args.output)
    print(f"wrote {len(tensors)} tensors to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
