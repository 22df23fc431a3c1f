#!/usr/bin/env python3
"""Exports a random-weight CLIP ViT-B/16 image tower to ONNX, for the `onnx` encoder benchmark.

Real size (224 x 224 input, 16-pixel patches, 12 layers of width 768, projection to 512), random
weights (no pretrained weights can be downloaded here; speed does not depend on them). The model
is transformers' CLIPVisionModelWithProjection; the ONNX graph has input `pixel_values`
(batch x 3 x 224 x 224, dynamic batch) and output `image_embeds` (batch x 512). About 350 MB:
written to /tmp, never committed.

    python3 -m pip install torch transformers onnx onnxruntime==1.31.1
    python3 bench/onnx/export_clip_b16.py [OUT_DIR]      # default /tmp/vlem-onnx-bench

It also writes OUT_DIR/onnx.toml, an `[encoder]` config for the exported model, which
`cargo run --release -p vlem-backends --features onnx --example onnx_bench` reads.
"""

import sys
from pathlib import Path

import torch
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection


class ImageEmbeds(torch.nn.Module):
    """The tower with a plain tensor output (the ONNX exporter wants tensors, not ModelOutput)."""

    def __init__(self, model: CLIPVisionModelWithProjection) -> None:
        super().__init__()
        self.model = model

    def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
        return self.model(pixel_values=pixel_values).image_embeds


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/vlem-onnx-bench")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    config = CLIPVisionConfig(
        hidden_size=768,
        intermediate_size=3072,
        num_hidden_layers=12,
        num_attention_heads=12,
        image_size=224,
        patch_size=16,
        projection_dim=512,
    )
    config._attn_implementation = "eager"
    model = ImageEmbeds(CLIPVisionModelWithProjection(config).eval())
    x = torch.randn(1, 3, 224, 224)
    path = out / "clip-b16-image.onnx"
    torch.onnx.export(
        model,
        (x,),
        str(path),
        input_names=["pixel_values"],
        output_names=["image_embeds"],
        dynamic_axes={"pixel_values": {0: "batch"}, "image_embeds": {0: "batch"}},
        opset_version=17,
        dynamo=False,
    )
    (out / "onnx.toml").write_text(
        '[image]\nmodel = "clip-b16-image.onnx"\noutput_kind = "global"\nsize = 224\n'
    )
    print(f"{path}: {path.stat().st_size / 1e6:.0f} MB")


if __name__ == "__main__":
    main()
