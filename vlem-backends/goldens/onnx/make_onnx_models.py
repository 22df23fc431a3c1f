#!/usr/bin/env python3
"""Builds the tiny ONNX test models of the `onnx` encoder and their goldens, computed by torch.

The Rust encoder (vlem-backends, feature `onnx`, tests in vlem-backends/tests/onnx.rs) must
reproduce the outputs of the TORCH modules below (the reference), run through ONNX Runtime, to
1e-4. The models are random-weight stand-ins in CLIP's shape, small enough to commit:

- image_global.onnx: a ViT image tower giving one embedding per image (CLS token, layer norm,
  projection), input `pixel_values` N x 3 x 32 x 32, output `image_embeds` N x 8;
- image_patches.onnx: a ViT giving one embedding per token, input `pixel_values`
  N x 3 x 32 x 48 (height 32, width 48, so that width and height cannot be swapped unnoticed),
  patches of 8 pixels, a CLS and a register token first: output `tokens` N x (2 + 4*6) x 8;
- image_patches_nhwc.onnx: the same tower, output `grid` N x 4 x 6 x 8 (no leading tokens);
- text.onnx: a text tower over `input_ids` and `attention_mask` (both int64 N x L, L <= 8),
  masked mean pooling and a projection, output `text_embeds` N x 8;
- tokenizer.json: a word-level tokenizer ([BOS] words [EOS]) built with the `tokenizers` library.

goldens.json holds, for fixed inputs:
- the RGB images (bytes, row-major, interleaved) and the preprocessed input tensors
  ((x / 255 - mean) / std, N x 3 x H x W);
- the torch outputs of each image tower for the whole batch and for each image alone;
- the token ids of every prompt, the torch text embedding of each prompt alone (no padding),
  and the template-averaged embedding of every text (mean of the unit-norm prompt embeddings,
  L2-normalised), which is what `Encoder::encode_text` must return.

Requirements (development machine only, never in CI: torch is large):
    python3 -m pip install torch onnx tokenizers
Run from anywhere:
    python3 vlem-backends/goldens/onnx/make_onnx_models.py
"""

import json
from pathlib import Path

import numpy as np
import torch
from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors
from torch import nn

OUT = Path(__file__).resolve().parent
SEED = 20261123
OPSET = 17
DIM = 8
WIDTH = 16  # transformer width
MEAN = [0.48145466, 0.4578275, 0.40821073]
STD = [0.26862954, 0.26130258, 0.27577711]
MAX_LENGTH = 8

WORDS = (
    "a an the photo picture of red green blue white chair table cat dog sofa lamp wall floor "
    "next to on in with sitting very long tail big small room"
).split()

TEMPLATES = ["a photo of a {}", "{}"]
TEXTS = [
    "red chair",
    "Cat",
    # Unknown words become [UNK]; long enough to be truncated to MAX_LENGTH tokens.
    "a very big green sofa next to the white wall in the small room",
    "",
]


class Block(nn.Module):
    """One pre-norm transformer block with explicit attention (exports to plain ONNX ops)."""

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.ln1 = nn.LayerNorm(width)
        self.qkv = nn.Linear(width, 3 * width)
        self.out = nn.Linear(width, width)
        self.ln2 = nn.LayerNorm(width)
        self.mlp = nn.Sequential(nn.Linear(width, 2 * width), nn.GELU(), nn.Linear(2 * width, width))

    def forward(self, x: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        n, t, w = x.shape
        h = self.heads
        q, k, v = self.qkv(self.ln1(x)).reshape(n, t, 3, h, w // h).permute(2, 0, 3, 1, 4)
        scores = q @ k.transpose(-1, -2) / float(w // h) ** 0.5
        if bias is not None:
            scores = scores + bias
        attn = scores.softmax(-1) @ v
        x = x + self.out(attn.transpose(1, 2).reshape(n, t, w))
        return x + self.mlp(self.ln2(x))


class ImageTower(nn.Module):
    """A tiny ViT: conv patch embedding, leading tokens, position embeddings, one block."""

    def __init__(self, height: int, width: int, patch: int, leading: int, output: str) -> None:
        super().__init__()
        self.grid = (height // patch, width // patch)
        self.leading = leading
        self.output = output
        self.patch = nn.Conv2d(3, WIDTH, patch, stride=patch)
        self.tokens = nn.Parameter(torch.randn(leading, WIDTH) * 0.5)
        self.pos = nn.Parameter(torch.randn(leading + self.grid[0] * self.grid[1], WIDTH) * 0.5)
        self.block = Block(WIDTH, 2)
        self.ln = nn.LayerNorm(WIDTH)
        self.proj = nn.Linear(WIDTH, DIM, bias=False)

    def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
        x = self.patch(pixel_values).flatten(2).transpose(1, 2)  # N x (gh*gw) x WIDTH
        lead = self.tokens.unsqueeze(0).expand(x.shape[0], -1, -1)
        x = torch.cat([lead, x], 1) + self.pos
        x = self.proj(self.ln(self.block(x)))  # N x T x DIM
        if self.output == "global":
            return x[:, 0]
        if self.output == "grid":
            gh, gw = self.grid
            return x[:, self.leading :].reshape(x.shape[0], gh, gw, DIM)
        return x


class TextTower(nn.Module):
    """A tiny text encoder: token and position embeddings, one masked block, masked mean."""

    def __init__(self, vocab: int) -> None:
        super().__init__()
        self.embed = nn.Embedding(vocab, WIDTH)
        self.pos = nn.Parameter(torch.randn(MAX_LENGTH, WIDTH) * 0.5)
        self.block = Block(WIDTH, 2)
        self.ln = nn.LayerNorm(WIDTH)
        self.proj = nn.Linear(WIDTH, DIM, bias=False)

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        length = input_ids.shape[1]
        x = self.embed(input_ids) + self.pos[:length]
        mask = attention_mask.to(x.dtype)
        bias = (1.0 - mask)[:, None, None, :] * -1e4
        x = self.ln(self.block(x, bias))
        pooled = (x * mask[:, :, None]).sum(1) / mask.sum(1, keepdim=True).clamp(min=1.0)
        return self.proj(pooled)


def export(model: nn.Module, args: tuple, path: Path, inputs: list, outputs: list, axes: dict) -> None:
    torch.onnx.export(
        model,
        args,
        str(path),
        input_names=inputs,
        output_names=outputs,
        dynamic_axes=axes,
        opset_version=OPSET,
        dynamo=False,
    )


def make_tokenizer() -> Tokenizer:
    vocab = {"[PAD]": 0, "[UNK]": 1, "[BOS]": 2, "[EOS]": 3}
    for w in WORDS:
        vocab.setdefault(w, len(vocab))
    tok = Tokenizer(models.WordLevel(vocab, unk_token="[UNK]"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(
        single="[BOS] $A [EOS]", special_tokens=[("[BOS]", 2), ("[EOS]", 3)]
    )
    return tok


def preprocess(images: np.ndarray) -> np.ndarray:
    """N x H x W x 3 bytes -> N x 3 x H x W float32, as the Rust encoder computes it (in f32)."""
    x = images.astype(np.float32) / np.float32(255.0)
    x = (x - np.array(MEAN, np.float32)) / np.array(STD, np.float32)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2)).astype(np.float32)


def run(model: nn.Module, x: np.ndarray) -> dict:
    with torch.no_grad():
        batch = model(torch.from_numpy(x)).numpy()
        alone = [model(torch.from_numpy(x[i : i + 1])).numpy()[0] for i in range(len(x))]
    return {
        "shape": list(batch.shape),
        "batch": f32(batch),
        "alone": [f32(a) for a in alone],
    }


def f32(values) -> list:
    """Float32 values as the shortest decimals that read back to the same float32."""
    return [float(str(np.float32(v))) for v in np.asarray(values, np.float32).reshape(-1)]


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def main() -> None:
    torch.manual_seed(SEED)
    rng = np.random.default_rng(SEED)

    global_tower = ImageTower(32, 32, 8, 1, "global").eval()
    patch_tower = ImageTower(32, 48, 8, 2, "tokens").eval()
    grid_tower = ImageTower(32, 48, 8, 2, "grid").eval()
    grid_tower.load_state_dict(patch_tower.state_dict())
    tokenizer = make_tokenizer()
    text_tower = TextTower(tokenizer.get_vocab_size()).eval()

    square = rng.integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    wide = rng.integers(0, 256, (3, 32, 48, 3), dtype=np.uint8)
    batch = {"pixel_values": {0: "batch"}}
    export(global_tower, (torch.from_numpy(preprocess(square[:1])),), OUT / "image_global.onnx",
           ["pixel_values"], ["image_embeds"], {**batch, "image_embeds": {0: "batch"}})
    export(patch_tower, (torch.from_numpy(preprocess(wide[:1])),), OUT / "image_patches.onnx",
           ["pixel_values"], ["tokens"], {**batch, "tokens": {0: "batch"}})
    export(grid_tower, (torch.from_numpy(preprocess(wide[:1])),), OUT / "image_patches_nhwc.onnx",
           ["pixel_values"], ["grid"], {**batch, "grid": {0: "batch"}})
    ids = torch.tensor([[2, 5, 3]], dtype=torch.int64)
    export(text_tower, (ids, torch.ones_like(ids)), OUT / "text.onnx",
           ["input_ids", "attention_mask"], ["text_embeds"],
           {"input_ids": {0: "batch", 1: "length"}, "attention_mask": {0: "batch", 1: "length"},
            "text_embeds": {0: "batch"}})
    tokenizer.save(str(OUT / "tokenizer.json"))

    # Text: each prompt alone (no padding), as the reference; the encoder pads and masks.
    tokenizer.enable_truncation(MAX_LENGTH)
    prompts = []
    texts = []
    for text in TEXTS:
        unit_prompts = []
        for template in TEMPLATES:
            prompt = template.replace("{}", text)
            ids = tokenizer.encode(prompt).ids
            t = torch.tensor([ids], dtype=torch.int64)
            with torch.no_grad():
                e = text_tower(t, torch.ones_like(t)).numpy()[0]
            prompts.append({"prompt": prompt, "ids": ids, "embedding": f32(e)})
            unit_prompts.append(unit(e.astype(np.float64)))
        texts.append({"text": text, "embedding": unit(np.mean(unit_prompts, 0)).tolist()})

    goldens = {
        "mean": MEAN,
        "std": STD,
        "dim": DIM,
        "max_length": MAX_LENGTH,
        "templates": TEMPLATES,
        "global": {
            "width": 32, "height": 32,
            "images": [im.reshape(-1).tolist() for im in square],
            "input": f32(preprocess(square)),
            "output": run(global_tower, preprocess(square)),
        },
        "patches": {
            "width": 48, "height": 32, "patch_size": 8, "skip_tokens": 2,
            "images": [im.reshape(-1).tolist() for im in wide],
            "input": f32(preprocess(wide)),
            "output": run(patch_tower, preprocess(wide)),
            "grid_output": run(grid_tower, preprocess(wide)),
        },
        "prompts": prompts,
        "texts": texts,
        "versions": {"torch": torch.__version__, "numpy": np.__version__},
    }
    (OUT / "goldens.json").write_text(json.dumps(goldens, separators=(",", ":")) + "\n")
    for f in sorted(OUT.iterdir()):
        print(f"{f.name}: {f.stat().st_size} bytes")


if __name__ == "__main__":
    main()
