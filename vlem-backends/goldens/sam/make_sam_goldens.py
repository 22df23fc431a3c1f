#!/usr/bin/env python3
"""Goldens for the `sam` region proposer (vlem-backends/src/sam), from the reference code.

Builds two small SAM networks with the reference implementations -- `segment-anything` 1.0
(ImageEncoderViT, PromptEncoder, MaskDecoder, SamPredictor, SamAutomaticMaskGenerator) and
MobileSAM's TinyViT (`mobile_sam`, packaged on PyPI as `mobilesam-mirror`) -- fills every tensor with
the deterministic synthetic weights that vlem-backends/src/sam/synthetic.rs also computes (so no
weights are committed), runs them on a fixed synthetic image and writes small summaries:
`sam_goldens.json` (resize hash, embedding samples, low-resolution mask samples, IoU predictions,
upsampled-mask statistics, automatic-mask-generator records) and `state_dict_*.json` (the tensor
names and shapes of the two small networks and of the official ViT-B and MobileSAM
architectures, which the Rust loader must find).

Run (CPU is enough, ~1 minute):
    python3 -m pip install segment-anything torchvision pillow opencv-python-headless timm
    python3 -m pip install --no-deps mobilesam-mirror
    python3 vlem-backends/goldens/sam/make_sam_goldens.py
"""

import json
import math
import os
from functools import partial

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
MASK64 = (1 << 64) - 1


# ---------------------------------------------------------------- synthetic weights (see synthetic.rs)
def fnv1a64(data: bytes) -> int:
    h = 0xCBF29CE484222325
    for b in data:
        h ^= b
        h = (h * 0x100000001B3) & MASK64
    return h


def splitmix64_mix(z: np.ndarray) -> np.ndarray:
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def synthetic_values(name: str, shape) -> np.ndarray:
    h = fnv1a64(name.encode())
    n = int(np.prod(shape)) if len(shape) else 1
    with np.errstate(over="ignore"):
        base = np.uint64((h + 0x9E3779B97F4A7C15) & MASK64)
        z = splitmix64_mix(np.arange(n, dtype=np.uint64) + base)
    u = (z >> np.uint64(40)).astype(np.float32) * np.float32(1.0 / 8388608.0) - np.float32(1.0)
    leaf = name.rsplit(".", 1)[-1]
    if leaf == "positional_encoding_gaussian_matrix":
        scale, offset = np.float32(1.0), np.float32(0.0)
    elif len(shape) == 1:
        scale = np.float32(0.1)
        offset = np.float32(1.0) if leaf in ("weight", "running_var") else np.float32(0.0)
    else:
        fan_in = int(np.prod(shape[1:]))
        scale, offset = np.float32(1.0 / math.sqrt(max(fan_in, 1))), np.float32(0.0)
    return (scale * u + offset).astype(np.float32).reshape(shape)


def fill_synthetic(model: torch.nn.Module):
    names = []
    with torch.no_grad():
        for name, t in model.state_dict().items():
            if not t.is_floating_point():
                continue  # num_batches_tracked
            t.copy_(torch.from_numpy(synthetic_values(name, tuple(t.shape))))
            names.append([name, list(t.shape)])
    return names


# ---------------------------------------------------------------- models
def build_tiny_vit_sam():
    from segment_anything.modeling import (
        ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer)
    sam = Sam(
        image_encoder=ImageEncoderViT(
            depth=2, embed_dim=32, img_size=1024, mlp_ratio=4,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6), num_heads=2, patch_size=16,
            qkv_bias=True, use_rel_pos=True, global_attn_indexes=[1], window_size=14,
            out_chans=256),
        prompt_encoder=PromptEncoder(embed_dim=256, image_embedding_size=(64, 64),
                                     input_image_size=(1024, 1024), mask_in_chans=16),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(depth=2, embedding_dim=256, mlp_dim=2048, num_heads=8),
            transformer_dim=256, iou_head_depth=3, iou_head_hidden_dim=256),
        pixel_mean=[123.675, 116.28, 103.53], pixel_std=[58.395, 57.12, 57.375])
    names = fill_synthetic(sam)
    sam.eval()
    return sam, names


def build_tiny_tinyvit_sam():
    from mobile_sam.modeling import (
        MaskDecoder, PromptEncoder, Sam, TinyViT, TwoWayTransformer)
    sam = Sam(
        image_encoder=TinyViT(
            img_size=1024, in_chans=3, num_classes=1000, embed_dims=[16, 32, 64, 320],
            depths=[1, 1, 1, 1], num_heads=[1, 2, 2, 10], window_sizes=[7, 7, 14, 7],
            mlp_ratio=4.0, drop_rate=0.0, drop_path_rate=0.0, use_checkpoint=False,
            mbconv_expand_ratio=4.0, local_conv_size=3, layer_lr_decay=0.8),
        prompt_encoder=PromptEncoder(embed_dim=256, image_embedding_size=(64, 64),
                                     input_image_size=(1024, 1024), mask_in_chans=16),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(depth=2, embedding_dim=256, mlp_dim=2048, num_heads=8),
            transformer_dim=256, iou_head_depth=3, iou_head_hidden_dim=256),
        pixel_mean=[123.675, 116.28, 103.53], pixel_std=[58.395, 57.12, 57.375])
    # Fill before eval(): TinyViT's attention caches its gathered biases in eval().
    names = fill_synthetic(sam)
    sam.eval()
    return sam, names


# ---------------------------------------------------------------- inputs (same formulas in tests/sam.rs)
def test_image(w: int, h: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.int64)
    r = (x * 7 + y * 3) % 256
    g = (x * y) % 256
    b = (255 - 2 * x + 5 * y) % 256
    # A bright rectangle and a dark disc: some structure for the masks.
    rect = (x >= w // 5) & (x < w // 2) & (y >= h // 4) & (y < (3 * h) // 4)
    disc = (x - (3 * w) // 4) ** 2 + (y - h // 2) ** 2 < (h // 5) ** 2
    r = np.where(rect, 240, np.where(disc, 20, r))
    g = np.where(rect, 230, np.where(disc, 30, g))
    b = np.where(rect, 60, np.where(disc, 200, b))
    return np.stack([r, g, b], axis=-1).astype(np.uint8)


def stride_sample(a: np.ndarray, step: int):
    return [float(v) for v in a[::step, ::step].ravel()]


def mask_box(mask: np.ndarray):
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    return [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())]


def network_goldens(sam, predictor_cls, amg_cls, image, points):
    predictor = predictor_cls(sam)
    predictor.set_image(image)
    resized = predictor.transform.apply_image(image)
    emb = predictor.features[0].numpy()
    out = {
        "resized_size": [int(resized.shape[1]), int(resized.shape[0])],
        "resized_fnv1a64": f"{fnv1a64(resized.tobytes()):016x}",
        "input_sum": float(sam.preprocess(torch.as_tensor(resized).permute(2, 0, 1)[None].float())
                           .sum().item()),
        "embedding_mean": float(emb.mean()),
        "embedding_abs_mean": float(np.abs(emb).mean()),
        "embedding_max_abs": float(np.abs(emb).max()),
        # channels 0, 32, ..., 224; rows and columns 0, 8, ..., 56.
        "embedding_sample": [float(v) for v in emb[::32, ::8, ::8].ravel()],
        "points": [],
    }
    for p in points:
        masks, iou, low = predictor.predict(
            point_coords=np.array([p], dtype=np.float64), point_labels=np.array([1]),
            multimask_output=True, return_logits=True)
        entry = {"point": p, "iou": [float(v) for v in iou], "low_res": [], "upsampled": []}
        for k in range(3):
            logits = masks[k]
            hi = int((logits > 1.0).sum())
            lo = int((logits > -1.0).sum())
            entry["low_res"].append({
                "sample": stride_sample(low[k], 16),
                "mean": float(low[k].mean()),
                "max_abs": float(np.abs(low[k]).max()),
            })
            entry["upsampled"].append({
                "sample": stride_sample(logits, 8),
                "mean": float(logits.mean()),
                "stability_score": hi / lo if lo else 0.0,
                "area": int((logits > 0.0).sum()),
                "box": mask_box(logits > 0.0),
            })
        out["points"].append(entry)

    amg_runs = []
    # The synthetic weights give small, speckled mask logits (|l| < 1): a small stability offset
    # makes the score informative, and box_nms_thresh = 1 keeps every mask (their boxes are
    # nearly all the whole image), so every record is compared.
    for params in (
        dict(points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0,
             stability_score_offset=0.05, box_nms_thresh=1.0, min_mask_region_area=0),
        dict(points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0,
             stability_score_offset=0.05, box_nms_thresh=1.0, min_mask_region_area=40),
    ):
        gen = amg_cls(sam, points_per_batch=8, **params)
        records = gen.generate(image)
        amg_runs.append({
            "params": params,
            "masks": [{
                # XYWH of the inclusive box as the reference writes it.
                "bbox": [int(v) for v in r["bbox"]],
                "area": int(r["area"]),
                "predicted_iou": float(r["predicted_iou"]),
                "stability_score": float(r["stability_score"]),
                "point": [float(v) for v in r["point_coords"][0]],
            } for r in records],
        })
    out["amg"] = amg_runs
    return out


def main():
    torch.manual_seed(0)
    torch.set_num_threads(max(1, min(4, os.cpu_count() or 1)))
    from PIL import Image
    import segment_anything
    import mobile_sam

    image = test_image(96, 72)
    points = [[30.0, 36.0], [72.0, 36.0], [5.5, 60.25]]

    goldens = {
        "image": {"width": 96, "height": 72},
        "resize_only": [],
    }
    # Pillow's bilinear resize, up and down (what ResizeLongestSide.apply_image does).
    from segment_anything.utils.transforms import ResizeLongestSide
    for (w, h) in [(96, 72), (1500, 1000), (640, 480)]:
        img = test_image(w, h)
        r = ResizeLongestSide(1024).apply_image(img)
        goldens["resize_only"].append({
            "size": [w, h], "resized_size": [int(r.shape[1]), int(r.shape[0])],
            "fnv1a64": f"{fnv1a64(r.tobytes()):016x}"})

    sam, names = build_tiny_vit_sam()
    with torch.no_grad():
        goldens["vit"] = network_goldens(
            sam, segment_anything.SamPredictor, segment_anything.SamAutomaticMaskGenerator,
            image, points)
    with open(os.path.join(HERE, "state_dict_tiny_vit.json"), "w") as f:
        json.dump(names, f, indent=0)

    sam, names = build_tiny_tinyvit_sam()
    with torch.no_grad():
        goldens["tiny_vit"] = network_goldens(
            sam, mobile_sam.SamPredictor, mobile_sam.SamAutomaticMaskGenerator, image, points)
    with open(os.path.join(HERE, "state_dict_tiny_tinyvit.json"), "w") as f:
        json.dump(names, f, indent=0)

    # Tensor names and shapes of the full-size official architectures (what converted
    # checkpoints hold), for the loader's name check; no forward pass.
    for file, build in (("state_dict_vit_b.json", segment_anything.build_sam_vit_b),
                        ("state_dict_mobile_sam.json", mobile_sam.build_sam_vit_t)):
        sd = build().state_dict()
        with open(os.path.join(HERE, file), "w") as f:
            json.dump([[k, list(v.shape)] for k, v in sd.items() if v.is_floating_point()],
                      f, indent=0)

    goldens["versions"] = {
        "torch": torch.__version__,
        "segment_anything": getattr(segment_anything, "__version__", "1.0"),
        "pillow": Image.__version__,
    }
    with open(os.path.join(HERE, "sam_goldens.json"), "w") as f:
        json.dump(goldens, f, indent=1)
    print("wrote", os.path.join(HERE, "sam_goldens.json"))


if __name__ == "__main__":
    main()
