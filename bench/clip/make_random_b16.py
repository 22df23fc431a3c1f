#!/usr/bin/env python3
"""Writes a CLIP ViT-B/16 with random weights in the Hugging Face layout, for speed measurements.

The shape is openai/clip-vit-base-patch16's (image tower: 224 px, patch 16, width 768, 12 layers,
12 heads; text tower: width 512, 12 layers, 8 heads, 77 positions; 512-d projections;
quick-GELU), so the time per image is that of the real model; the weights are random because no
pretrained weights can be downloaded where vlem is built. The tokenizer is the tiny one of the
goldens (vlem-backends/goldens/clip/tiny-quick-gelu/tokenizer.json): its ids fit the vocabulary,
which is all a speed measurement of the text tower needs. Do not commit the output (~600 MB).

    pip install torch transformers
    python3 bench/clip/make_random_b16.py [OUT_DIR]     # default /tmp/clip-vit-b16-random
"""

import shutil
import sys
from pathlib import Path

import torch
from transformers import CLIPConfig, CLIPModel

REPO = Path(__file__).resolve().parents[2]


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/clip-vit-b16-random")
    out.mkdir(parents=True, exist_ok=True)
    config = CLIPConfig(
        text_config=dict(
            vocab_size=49408,
            hidden_size=512,
            intermediate_size=2048,
            num_hidden_layers=12,
            num_attention_heads=8,
            max_position_embeddings=77,
            hidden_act="quick_gelu",
            bos_token_id=0,
            eos_token_id=2,
            pad_token_id=1,
        ),
        vision_config=dict(
            hidden_size=768,
            intermediate_size=3072,
            num_hidden_layers=12,
            num_attention_heads=12,
            image_size=224,
            patch_size=16,
            hidden_act="quick_gelu",
        ),
        projection_dim=512,
    )
    torch.manual_seed(0)
    CLIPModel(config).eval().save_pretrained(str(out))
    tiny = REPO / "vlem-backends/goldens/clip/tiny-quick-gelu"
    for f in ["tokenizer.json", "preprocessor_config.json"]:
        shutil.copy(tiny / f, out / f)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
