#!/usr/bin/env python3
"""Writes two tiny random-weight DINOv3 ViT backbones in the Hugging Face layout, and
dinov3_goldens.json.

The Rust DINOv3 backbone (vlem-backends, feature `dinov3`) must reproduce the goldens to 1e-4
(tests in vlem-backends/tests/dinov3.rs). No pretrained DINOv3 weights can be downloaded where
this project is built, so the reference is `transformers`' own DINOv3ViTModel with random
weights, saved with `save_pretrained`, which writes the tensor names of the checkpoints on the
Hugging Face hub (`layer.N.*`, not the `model.layer.N.*` of the module tree):

    tiny/        the ViT-S/B/L shape: plain GELU MLP, 4 register tokens
    tiny-gated/  the ViT-S+/L+/H+ shape: gated SiLU MLP (SwiGLU), 2 register tokens

Both have hidden size 32, 2 heads (head dimension 16: four RoPE frequencies per axis), 2 layers,
patch 16. Every parameter (biases, layer scales, CLS, register and mask tokens included) is drawn
at random, so that no term of the forward pass is hidden behind a zero or a one.

The input is a fixed function of the pixel position (no file), so that the Rust test can compute
the same tensor: x[c, y, x] = 2 sin(0.7 c + 0.31 y + 0.17 x + 0.013 x y), in float64, then cast
to float32. Each model runs at 64x64 (a square 4x4 grid) and 48x80 (a 3x5 grid: RoPE normalises
each axis by its own patch count, which a square grid cannot show). The goldens hold
`last_hidden_state` (final layer norm applied to every token) of each case.

dino.txt (key "dinotxt" of the goldens): Meta's own code (github.com/facebookresearch/dinov3,
`dinov3/eval/text/`, the code behind the hub entry `dinov3_vitl16_dinotxt_tet1280d20h24l`) runs
with the `tiny` backbone, converted to the names of Meta's DinoVisionTransformer (the script
checks that both backbones agree to 1e-5), under a random 2-block vision head (SwiGLU, layer
scales) and a random 2-layer causal text tower (vocabulary 520, 16 positions, width 24, 3 heads,
projection to 64 = 2 x 32). The head and text weights are saved as Meta saves the released
`dinov3_vitl16_dinotxt_vision_head_and_text_encoder-*.pth`: torch.save of the state dict without
the backbone (`tiny-dinotxt.pth`). Goldens: image embeddings and head patch tokens for both
sizes, text embeddings for three id sequences (one longer than the context, cut as Meta's
tokenizer cuts it).

The `dinov3` encoder (key "encoder"): a CLIP BPE merge list of six merges, gzipped as the
released `bpe_simple_vocab_16e6.txt.gz` is (`tiny-bpe.txt.gz`; 512 byte symbols + 6 merges + 2
special tokens = the 520 ids of the tiny text tower), tokenised with Meta's own tokenizer
(`dinov3/eval/text/tokenizer.py`); for three prompts, the ids and the normalised second half of
the text embedding (what the encoder gives for a query); and for one 64x48 RGB image that needs
no resizing (input pixel (x, y) = (37x + 11y, 3x + 71y + 5, 13xy + 7) mod 256), the head patch
tokens after ImageNet normalisation, each L2-normalised (the encoder's patch grid).

Requirements (development machine only, never in CI: torch is large):
    pip install torch transformers safetensors
    a checkout of facebookresearch/dinov3 (its `dinov3` package imports with torch alone)
Run from anywhere:
    DINOV3_SRC=/path/to/dinov3 python3 vlem-backends/goldens/dinov3/make_dinov3_goldens.py
"""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import torch
import transformers
from transformers import DINOv3ViTConfig, DINOv3ViTModel

HERE = Path(__file__).resolve().parent

MODELS = {
    "tiny": dict(
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=2,
        num_attention_heads=2,
        num_register_tokens=4,
        image_size=64,
        patch_size=16,
        hidden_act="gelu",
        use_gated_mlp=False,
    ),
    "tiny-gated": dict(
        hidden_size=32,
        intermediate_size=48,
        num_hidden_layers=2,
        num_attention_heads=2,
        num_register_tokens=2,
        image_size=64,
        patch_size=16,
        hidden_act="silu",
        use_gated_mlp=True,
        layer_norm_eps=1e-6,
        rope_theta=50.0,
    ),
}

SIZES = [(64, 64), (48, 80)]


def pixels(height: int, width: int) -> torch.Tensor:
    c, y, x = np.meshgrid(
        np.arange(3, dtype=np.float64),
        np.arange(height, dtype=np.float64),
        np.arange(width, dtype=np.float64),
        indexing="ij",
    )
    values = 2.0 * np.sin(0.7 * c + 0.31 * y + 0.17 * x + 0.013 * x * y)
    return torch.from_numpy(values.astype(np.float32)).unsqueeze(0)


def main() -> None:
    goldens = {
        "transformers": transformers.__version__,
        "torch": torch.__version__,
        "input": "x[c,y,x] = 2 sin(0.7 c + 0.31 y + 0.17 x + 0.013 x y), f64 then f32",
        "models": {},
    }
    for index, (name, values) in enumerate(MODELS.items()):
        torch.manual_seed(1000 + index)
        config = DINOv3ViTConfig(**values)
        model = DINOv3ViTModel(config).eval()
        with torch.no_grad():
            for param_name, param in model.named_parameters():
                if param_name.endswith("lambda1"):
                    # Layer scales near one keep the residual stream readable after 2 layers.
                    param.copy_(1.0 + 0.3 * torch.randn_like(param))
                elif param_name.startswith("norm.") or ".norm" in param_name:
                    base = 1.0 if param_name.endswith("weight") else 0.0
                    param.copy_(base + 0.2 * torch.randn_like(param))
                else:
                    param.copy_(0.2 * torch.randn_like(param))
        folder = HERE / name
        shutil.rmtree(folder, ignore_errors=True)
        model.save_pretrained(folder)
        cases = []
        for height, width in SIZES:
            with torch.no_grad():
                out = model(pixel_values=pixels(height, width)).last_hidden_state
            cases.append(
                {
                    "height": height,
                    "width": width,
                    "shape": list(out.shape),
                    "last_hidden_state": [float(v) for v in out.flatten()],
                }
            )
        goldens["models"][name] = {
            "num_register_tokens": values["num_register_tokens"],
            "hidden_size": values["hidden_size"],
            "cases": cases,
        }
    goldens["dinotxt"] = make_dinotxt_goldens()
    path = HERE / "dinov3_goldens.json"
    path.write_text(json.dumps(goldens, indent=1) + "\n")
    print(f"wrote {path}")


def native_backbone_state(hf: DINOv3ViTModel) -> dict:
    """The HF tiny backbone's weights under the names of Meta's own DinoVisionTransformer."""
    sd = {k: v.detach().clone() for k, v in hf.state_dict().items()}
    c = hf.config
    out = {
        "cls_token": sd["embeddings.cls_token"],
        "storage_tokens": sd["embeddings.register_tokens"],
        "mask_token": sd["embeddings.mask_token"].reshape(1, -1),
        "patch_embed.proj.weight": sd["embeddings.patch_embeddings.weight"],
        "patch_embed.proj.bias": sd["embeddings.patch_embeddings.bias"],
        "norm.weight": sd["norm.weight"],
        "norm.bias": sd["norm.bias"],
    }
    head_dim = c.hidden_size // c.num_attention_heads
    out["rope_embed.periods"] = c.rope_theta ** (
        2 * torch.arange(head_dim // 4, dtype=torch.float32) / (head_dim // 2)
    )
    for i in range(c.num_hidden_layers):
        hf_p, p = f"model.layer.{i}", f"blocks.{i}"
        a = f"{hf_p}.attention"
        zeros = torch.zeros(c.hidden_size)
        out[f"{p}.attn.qkv.weight"] = torch.cat(
            [sd[f"{a}.q_proj.weight"], sd[f"{a}.k_proj.weight"], sd[f"{a}.v_proj.weight"]]
        )
        out[f"{p}.attn.qkv.bias"] = torch.cat([sd[f"{a}.q_proj.bias"], zeros, sd[f"{a}.v_proj.bias"]])
        out[f"{p}.attn.qkv.bias_mask"] = torch.cat([zeros + 1, zeros, zeros + 1])
        out[f"{p}.attn.proj.weight"] = sd[f"{a}.o_proj.weight"]
        out[f"{p}.attn.proj.bias"] = sd[f"{a}.o_proj.bias"]
        for n in ("norm1", "norm2"):
            out[f"{p}.{n}.weight"] = sd[f"{hf_p}.{n}.weight"]
            out[f"{p}.{n}.bias"] = sd[f"{hf_p}.{n}.bias"]
        out[f"{p}.ls1.gamma"] = sd[f"{hf_p}.layer_scale1.lambda1"]
        out[f"{p}.ls2.gamma"] = sd[f"{hf_p}.layer_scale2.lambda1"]
        out[f"{p}.mlp.fc1.weight"] = sd[f"{hf_p}.mlp.up_proj.weight"]
        out[f"{p}.mlp.fc1.bias"] = sd[f"{hf_p}.mlp.up_proj.bias"]
        out[f"{p}.mlp.fc2.weight"] = sd[f"{hf_p}.mlp.down_proj.weight"]
        out[f"{p}.mlp.fc2.bias"] = sd[f"{hf_p}.mlp.down_proj.bias"]
    return out


# The tiny dino.txt text tower: vocabulary of 520 ids (519 = end of text, the largest, as in
# CLIP's vocabulary; 518 = start of text), 16 positions, width 24 in 3 heads, 2 layers. The
# vocabulary is that of CLIP's tokenizer over the six merges of TINY_MERGES.
TEXT_VOCAB, TEXT_CONTEXT, TEXT_DIM, TEXT_HEADS, TEXT_LAYERS = 520, 16, 24, 3, 2
TEXT_IDS = [
    [518, 5, 17, 330, 2, 519],
    [518, 400, 519],
    [518] + [(7 * i + 3) % 511 + 1 for i in range(20)] + [519],  # longer than the context: truncated
]
TINY_MERGES = ["c h", "a i", "ch ai", "chai r</w>", "t a", "ta ble</w>"]
PROMPTS = ["chair", "a Table!", "a photo of a chair next to the table and a lamp"]


def tokenize_like_dinov3(ids: list) -> list:
    """dinov3/eval/text/tokenizer.py: truncate to the context with the end token last, pad with 0."""
    if len(ids) > TEXT_CONTEXT:
        ids = ids[:TEXT_CONTEXT]
        ids[-1] = TEXT_VOCAB - 1
    return ids + [0] * (TEXT_CONTEXT - len(ids))


def make_dinotxt_goldens() -> dict:
    """Runs Meta's own dino.txt code (facebookresearch/dinov3, its `dinov3` package on sys.path
    through the DINOV3_SRC environment variable) on the tiny backbone above, with a random head
    and text tower, and saves the head and text weights as the released checkpoint is saved: a
    torch.save'd state dict without the backbone (`tiny-dinotxt.pth`)."""
    import os
    import sys

    src = os.environ.get("DINOV3_SRC")
    if not src:
        raise SystemExit(
            "set DINOV3_SRC to a checkout of github.com/facebookresearch/dinov3 (the folder "
            "that holds the `dinov3` package)"
        )
    sys.path.insert(0, src)
    from dinov3.eval.text.dinotxt_model import DINOTxt, DINOTxtConfig
    from dinov3.eval.text.text_transformer import TextTransformer
    from dinov3.models.vision_transformer import DinoVisionTransformer

    hf = DINOv3ViTModel.from_pretrained(HERE / "tiny").eval()
    c = hf.config
    backbone = DinoVisionTransformer(
        img_size=64,
        patch_size=16,
        pos_embed_rope_base=c.rope_theta,
        pos_embed_rope_normalize_coords="separate",
        pos_embed_rope_rescale_coords=2,
        pos_embed_rope_dtype="fp32",
        embed_dim=c.hidden_size,
        depth=c.num_hidden_layers,
        num_heads=c.num_attention_heads,
        ffn_ratio=c.intermediate_size / c.hidden_size,
        qkv_bias=True,
        layerscale_init=1.0e-05,
        norm_layer="layernormbf16",
        ffn_layer="mlp",
        n_storage_tokens=c.num_register_tokens,
        mask_k_bias=True,
    )
    backbone.load_state_dict(native_backbone_state(hf), strict=True)
    backbone.eval()
    # Meta's backbone and transformers' must agree (the HF checkpoints are conversions).
    with torch.no_grad():
        x = pixels(48, 80)
        native = backbone.get_intermediate_layers(x, n=1, return_class_token=True, return_extra_tokens=True)[0]
        hf_out = hf(pixel_values=x).last_hidden_state
        native_all = torch.cat([native[1].unsqueeze(1), native[2], native[0]], dim=1)
        gap = (native_all - hf_out).abs().max().item()
        assert gap < 1e-5, f"native and HF backbones differ by {gap}"

    config = DINOTxtConfig(
        embed_dim=2 * c.hidden_size,
        vision_model_freeze_backbone=True,
        vision_model_train_img_size=64,
        vision_model_use_class_token=True,
        vision_model_use_patch_tokens=True,
        vision_model_num_head_blocks=2,
        vision_model_head_blocks_drop_path=0.3,
        vision_model_use_linear_projection=False,
        vision_model_patch_tokens_pooler_type="mean",
        vision_model_patch_token_layer=1,
        text_model_freeze_backbone=False,
        text_model_num_head_blocks=0,
        text_model_head_blocks_is_causal=False,
        text_model_head_blocks_drop_prob=0.0,
        text_model_tokens_pooler_type="argmax",
        text_model_use_linear_projection=True,
        init_logit_scale=math.log(1 / 0.07),
        init_logit_bias=None,
        freeze_logit_scale=False,
    )
    text = TextTransformer(
        context_length=TEXT_CONTEXT,
        vocab_size=TEXT_VOCAB,
        dim=TEXT_DIM,
        num_heads=TEXT_HEADS,
        num_layers=TEXT_LAYERS,
        ffn_ratio=4,
        is_causal=True,
        ls_init_value=None,
        dropout_prob=0.0,
    )
    torch.manual_seed(2000)
    model = DINOTxt(model_config=config, vision_backbone=backbone, text_backbone=text)
    model.visual_model.backbone = backbone
    with torch.no_grad():
        for name, param in model.named_parameters():
            if name.startswith("visual_model.backbone."):
                continue
            if name.endswith(".gamma"):
                param.copy_(1.0 + 0.3 * torch.randn_like(param))
            elif "norm" in name or "ln_final" in name:
                base = 1.0 if name.endswith("weight") else 0.0
                param.copy_(base + 0.2 * torch.randn_like(param))
            else:
                param.copy_(0.3 * torch.randn_like(param))
    model.eval()
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("visual_model.backbone.")}
    torch.save(state, HERE / "tiny-dinotxt.pth")

    images = []
    for height, width in SIZES:
        with torch.no_grad():
            features, patches, _ = model.encode_image_with_patch_tokens(pixels(height, width))
        images.append(
            {
                "height": height,
                "width": width,
                "image_embedding": [float(v) for v in features[0]],
                "patch_tokens_shape": list(patches.shape),
                "patch_tokens": [float(v) for v in patches.flatten()],
            }
        )
    texts = []
    for ids in TEXT_IDS:
        padded = tokenize_like_dinov3(list(ids))
        with torch.no_grad():
            emb = model.encode_text(torch.tensor([padded]))
        texts.append({"ids": ids, "padded_ids": padded, "text_embedding": [float(v) for v in emb[0]]})
    encoder = make_encoder_goldens(model, c.hidden_size)
    return {
        "encoder": encoder,
        "backbone": "tiny",
        "checkpoint": "tiny-dinotxt.pth",
        "vision_heads": c.num_attention_heads,
        "text_heads": TEXT_HEADS,
        "text_context": TEXT_CONTEXT,
        "end_token": TEXT_VOCAB - 1,
        "images": images,
        "texts": texts,
    }


def encoder_image(height: int, width: int) -> np.ndarray:
    """The encoder golden's RGB image, uint8 (height, width, 3)."""
    y, x = np.mgrid[0:height, 0:width]
    rgb = np.stack([37 * x + 11 * y, 3 * x + 71 * y + 5, 13 * x * y + 7], axis=-1)
    return (rgb % 256).astype(np.uint8)


def make_encoder_goldens(model, width: int) -> dict:
    """What the `dinov3` encoder must give over the tiny files: prompts tokenised by Meta's
    tokenizer over the tiny merge list, their normalised second text half, and one image's
    normalised head patch tokens."""
    import gzip

    from dinov3.eval.text.tokenizer import Tokenizer

    vocab_path = HERE / "tiny-bpe.txt.gz"
    # mtime=0: the same bytes on every run. No newline after the last merge: OpenAI's reader
    # would take the empty line after it for a merge (the released file is cut long before its end).
    with gzip.GzipFile(vocab_path, "wb", mtime=0) as f:
        f.write(("#version: tiny\n" + "\n".join(TINY_MERGES)).encode())
    tokenizer = Tokenizer(str(vocab_path))
    assert len(tokenizer.encoder) == TEXT_VOCAB, len(tokenizer.encoder)
    prompts = []
    for text in PROMPTS:
        ids = tokenizer.tokenize([text], context_length=TEXT_CONTEXT)
        with torch.no_grad():
            emb = model.encode_text(ids)[0]
        half = torch.nn.functional.normalize(emb[width:], dim=-1)
        row = ids[0].tolist()
        while row and row[-1] == 0:
            row.pop()
        prompts.append({"text": text, "ids": row, "embedding": [float(v) for v in half]})

    height, image_width = 48, 64
    rgb = torch.from_numpy(encoder_image(height, image_width)).float() / 255.0
    mean = torch.tensor([0.485, 0.456, 0.406])
    std = torch.tensor([0.229, 0.224, 0.225])
    x = ((rgb - mean) / std).permute(2, 0, 1).unsqueeze(0)
    with torch.no_grad():
        _, patches, _ = model.encode_image_with_patch_tokens(x)
    grid = torch.nn.functional.normalize(patches[0], dim=-1)
    return {
        "bpe_vocab": "tiny-bpe.txt.gz",
        "prompts": prompts,
        "image": {
            "width": image_width,
            "height": height,
            "grid_width": image_width // 16,
            "grid_height": height // 16,
            "patch_grid": [float(v) for v in grid.flatten()],
        },
    }


if __name__ == "__main__":
    main()
