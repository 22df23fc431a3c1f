#!/usr/bin/env python3
"""Writes a dinov3 model folder of the full size with random weights, for speed measurements.

What vlem's `dinov3` encoder reads: the DINOv3 ViT-L/16 backbone in the Hugging Face layout
(`facebook/dinov3-vitl16-pretrain-lvd1689m`'s shapes: 1024 wide, 24 layers, 16 heads, 4 registers;
config.json + model.safetensors, written by transformers) and the dino.txt checkpoint in Meta's
layout (vision head: 2 blocks with SwiGLU; text tower: 1280 wide, 24 layers, 77 positions, 2048-d
projection), all random: speed does not depend on the values, and no pretrained weights can be
downloaded where vlem is built. The BPE vocabulary is not written: vlem finds open_clip's copy
(`python3 -m pip install --no-deps open_clip_torch`). Do not commit the output (~1.8 GB).

    pip install torch transformers
    python3 bench/dinov3/make_random.py OUT_DIR
"""

import sys
from pathlib import Path

import torch
from transformers import DINOv3ViTConfig, DINOv3ViTModel

DINOTXT = "dinov3_vitl16_dinotxt_vision_head_and_text_encoder-random.pth"


def linear(t, name, inputs, outputs, bias=True):
    t[f"{name}.weight"] = torch.randn(outputs, inputs) * inputs ** -0.5
    if bias:
        t[f"{name}.bias"] = torch.zeros(outputs)


def norm(t, name, width):
    t[f"{name}.weight"] = torch.ones(width)
    t[f"{name}.bias"] = torch.zeros(width)


def dinotxt(vocab=49408):
    t = {}
    w, hidden = 1024, 2752
    for i in range(2):
        b = f"visual_model.head.blocks.{i}"
        norm(t, f"{b}.norm1", w)
        linear(t, f"{b}.attn.qkv", w, 3 * w, bias=False)
        linear(t, f"{b}.attn.proj", w, w)
        t[f"{b}.ls1.gamma"] = torch.full((w,), 1e-5)
        norm(t, f"{b}.norm2", w)
        linear(t, f"{b}.mlp.w1", w, hidden)
        linear(t, f"{b}.mlp.w2", w, hidden)
        linear(t, f"{b}.mlp.w3", hidden, w)
        t[f"{b}.ls2.gamma"] = torch.full((w,), 1e-5)
    norm(t, "visual_model.head.ln_final", w)
    d, tb = 1280, "text_model.backbone"
    t[f"{tb}.token_embedding.weight"] = torch.randn(vocab, d) * 0.02
    t[f"{tb}.positional_embedding"] = torch.randn(77, d) * 0.01
    for i in range(24):
        b = f"{tb}.blocks.{i}"
        norm(t, f"{b}.attention_norm", d)
        linear(t, f"{b}.attention.qkv", d, 3 * d, bias=False)
        linear(t, f"{b}.attention.proj", d, d)
        norm(t, f"{b}.ffn_norm", d)
        linear(t, f"{b}.feed_forward.fc1", d, 4 * d)
        linear(t, f"{b}.feed_forward.fc2", 4 * d, d)
    norm(t, f"{tb}.ln_final", d)
    linear(t, "text_model.head.linear_projection", d, 2048, bias=False)
    return t


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/dinov3-vitl16-random")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    config = DINOv3ViTConfig(
        hidden_size=1024, intermediate_size=4096, num_hidden_layers=24, num_attention_heads=16,
        num_register_tokens=4, patch_size=16, layer_norm_eps=1e-5, rope_theta=100.0,
    )
    DINOv3ViTModel(config).eval().save_pretrained(out)
    torch.save(dinotxt(), out / DINOTXT)
    print(f"wrote a random DINOv3 ViT-L/16 + dino.txt folder to {out}")


if __name__ == "__main__":
    main()
