#!/usr/bin/env python3
"""Milliseconds per frame of the dinov3 encoder's image side in PyTorch: `transformers`'
DINOv3ViTModel (ViT-L/16 shape) and Meta's dino.txt `VisionHead` (2 SwiGLU blocks, final norm),
random weights, float32, inference mode, CPU.

The reference for vlem-backends/examples/dinov3_bench.rs: the same input sizes (the frame's short
side resized to SHORT_SIDE, both sides multiples of 16: 640x480 at 448 is 592x448). One warm-up
call, then REPEAT timed calls; prints the best and the mean.

    DINOV3_SRC=/path/to/facebookresearch/dinov3 python3 bench/dinov3/torch_bench.py \
        --threads 2 --short-side 448 --repeat 3
"""

import argparse
import os
import sys
import time

import torch
from transformers import DINOv3ViTConfig, DINOv3ViTModel


def synchronize(device: str) -> None:
    """Waits for the GPU's queued work, so that a timer reads the work done, not the launch."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def input_size(width: int, height: int, short_side: int, patch: int = 16) -> tuple:
    """As vlem's patch_aligned_size: short side to short_side, aspect kept, rounded to patches."""
    short, long = min(width, height), max(width, height)
    new_long = max(round(long * short_side / short / patch), 1) * patch
    new_short = max(round(short_side / patch), 1) * patch
    return (new_long, new_short) if width > height else (new_short, new_long)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--short-side", type=int, nargs="+", default=[448])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--dtype", default="f32", choices=["f32", "f16", "bf16"],
                   help="the model's and the input's type (half: .half() / bfloat16, as vlem's)")
    args = p.parse_args()
    sys.path.insert(0, os.environ["DINOV3_SRC"])
    from dinov3.eval.text.vision_tower import VisionHead

    torch.set_num_threads(args.threads)
    config = DINOv3ViTConfig(
        hidden_size=1024, intermediate_size=4096, num_hidden_layers=24, num_attention_heads=16,
        num_register_tokens=4, patch_size=16, layer_norm_eps=1e-5, rope_theta=100.0,
        attn_implementation="sdpa",  # PyTorch's fused attention (transformers' default)
    )
    dtype = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}[args.dtype]
    backbone = DINOv3ViTModel(config).eval().to(args.device, dtype)
    head = VisionHead(1024, 2048, 16, 2, 0.0, True, True, False).eval().to(args.device, dtype)
    for side in args.short_side:
        width, height = input_size(640, 480, side)
        x = torch.randn(1, 3, height, width, generator=torch.Generator().manual_seed(0))
        x = x.to(args.device, dtype)
        times = []
        with torch.inference_mode():
            for i in range(args.repeat + 1):
                t = time.perf_counter()
                head(backbone(pixel_values=x).last_hidden_state)
                synchronize(args.device)
                if i > 0:
                    times.append(time.perf_counter() - t)
        print(
            f"torch threads={args.threads} short side {side}: input {width}x{height} "
            f"({width // 16 * (height // 16)} patches)  best {min(times) * 1e3:.1f} ms/frame, "
            f"mean {sum(times) / len(times) * 1e3:.1f} ms/frame"
        )


if __name__ == "__main__":
    main()
