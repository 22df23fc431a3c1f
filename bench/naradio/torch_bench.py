#!/usr/bin/env python3
"""Milliseconds per 640x480 frame of a RADIOv2.5-sized ViT trunk in PyTorch (timm), f32 or half.

The reference for vlem-backends/examples/naradio_bench.rs: timm's VisionTransformer in the
RADIOv2.5 B/16 or L/16 shape (RADIO's trunk is this timm model) with 8 prefix tokens (timm: 1
class + 7 register tokens; RADIOv2.5: 4 class + 4 registers), on a 480x640 input (40x30 patches,
as RayFronts feeds frames), random weights, inference mode. This times the trunk only: NACLIP's
last-block attention costs the same as the attention it replaces, and the adaptor MLP on 1200
tokens is small beside 12 or 24 blocks, so it is the bulk of what naradio_bench times.

    python3 bench/naradio/torch_bench.py --threads 2 --model b l --repeat 2
"""

import argparse
import time

import timm
import torch

def synchronize(device: str) -> None:
    """Waits for the GPU's queued work, so that a timer reads the work done, not the launch."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


SHAPES = {"b": "vit_base_patch16_224", "l": "vit_large_patch16_224"}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--model", nargs="+", default=["b", "l"], choices=sorted(SHAPES))
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--dtype", default="f32", choices=["f32", "f16", "bf16"],
                   help="the model's and the input's type (half: .half() / bfloat16, as vlem's)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    dtype = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}[args.dtype]
    x = torch.randn(1, 3, 480, 640, generator=torch.Generator().manual_seed(0))
    x = x.to(args.device, dtype)
    for name in args.model:
        model = timm.create_model(
            SHAPES[name], pretrained=False, num_classes=0, dynamic_img_size=True,
            reg_tokens=7, global_pool="",
        ).eval().to(args.device, dtype)
        times = []
        with torch.inference_mode():
            for i in range(args.repeat + 1):
                t = time.perf_counter()
                model.forward_features(x)
                synchronize(args.device)
                if i > 0:
                    times.append(time.perf_counter() - t)
        print(
            f"torch threads={args.threads} {name.upper()}/16 640x480 (40x30 patches): best "
            f"{min(times) * 1e3:.1f} ms/frame, mean {sum(times) / len(times) * 1e3:.1f} ms/frame"
        )


if __name__ == "__main__":
    main()
