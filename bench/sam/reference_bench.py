#!/usr/bin/env python3
"""Times segment-anything's automatic mask generator on one 640x480 frame: the reference side of
`bench/sam/side_by_side.sh`.

Same frame as vlem's `sam_bench` example (gradients, a red rectangle, a blue disc), full-size
network with PyTorch's default random initialisation (speed does not depend on the values; random
weights predict low IoUs, so few masks pass the filters on either side), the generator's
parameters set to vlem's defaults but for the points per side; the generator's time is the best of
--repeat calls (default 1). Prints one JSON line.

    bench/.venv-torch/bin/python bench/sam/reference_bench.py --variant vit-b --points-per-side 16 --threads 2
"""

import argparse
import json
import time

import numpy as np
import torch


def frame():
    h, w = 480, 640
    y, x = np.mgrid[0:h, 0:w]
    img = np.stack([(x // 3), (y // 2), ((x + y) // 5)], axis=-1).astype(np.uint8)
    rect = (x >= 120) & (x < 320) & (y >= 100) & (y < 380)
    disc = (x - 480.0) ** 2 + (y - 240.0) ** 2 < 90.0**2
    img[disc & ~rect] = [30, 60, 210]
    img[rect] = [200, 40, 40]
    return img


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--variant", choices=["vit-b", "mobile-sam"], default="vit-b")
    ap.add_argument("--points-per-side", type=int, default=16)
    ap.add_argument("--points-per-batch", type=int, default=32)
    ap.add_argument("--repeat", type=int, default=1,
                    help="generator calls; the best is reported (a GPU's first call pays for "
                         "its kernels' first launch)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    ap.add_argument("--dtype", default="f32", choices=["f32", "f16", "bf16"],
                    help="half: the network under torch.autocast in that type (the package feeds "
                         "f32 images and prompts, so .half() alone does not run)")
    a = ap.parse_args()
    half = {"f32": None, "f16": torch.float16, "bf16": torch.bfloat16}[a.dtype]
    torch.set_num_threads(a.threads)
    if a.variant == "vit-b":
        from segment_anything import SamAutomaticMaskGenerator, sam_model_registry

        sam = sam_model_registry["vit_b"](checkpoint=None)
        package = "segment-anything"
    else:
        from mobile_sam import SamAutomaticMaskGenerator, sam_model_registry

        sam = sam_model_registry["vit_t"](checkpoint=None)
        package = "mobile_sam (mobilesam-mirror)"
    sam.eval().to(a.device)
    gen = SamAutomaticMaskGenerator(
        sam,
        points_per_side=a.points_per_side,
        points_per_batch=a.points_per_batch,
        pred_iou_thresh=0.88,
        stability_score_thresh=0.95,
        stability_score_offset=1.0,
        box_nms_thresh=0.7,
        min_mask_region_area=0,
    )
    image = frame()
    autocast = torch.autocast(a.device.split(":")[0], dtype=half, enabled=half is not None)
    with torch.inference_mode(), autocast:
        t = time.perf_counter()
        gen.predictor.set_image(image)
        if a.device.startswith("cuda"):
            torch.cuda.synchronize()
        encoder = time.perf_counter() - t
        total = float("inf")
        for _ in range(max(1, a.repeat)):
            t = time.perf_counter()
            masks = gen.generate(image)
            total = min(total, time.perf_counter() - t)
    print(json.dumps({
        "impl": package, "torch": torch.__version__, "variant": a.variant,
        "points_per_side": a.points_per_side, "threads": a.threads, "device": a.device,
        "dtype": a.dtype,
        "repeat": max(1, a.repeat),
        "image_encoder_s": round(encoder, 4), "generator_s": round(total, 4), "masks": len(masks),
    }))


if __name__ == "__main__":
    main()
