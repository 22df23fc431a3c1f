#!/usr/bin/env python3
"""Writes two tiny random-weight CLIP models in the Hugging Face layout, and clip_goldens.json.

The Rust CLIP towers (vlem-backends, feature `clip`) must reproduce the goldens to 1e-4 (tests in
vlem-backends/tests/clip.rs). No pretrained CLIP weights can be downloaded where this project is
built, so the reference is `transformers`' own CLIPModel with random weights, saved exactly as a
Hugging Face model folder is laid out:

    tiny-quick-gelu/  hidden_act "quick_gelu" in both towers and the legacy text config
                      eos_token_id = 2, whose pooling takes the position of the largest token id
                      (the openai/clip-vit-base-patch16 setup); with preprocessor_config.json
                      holding CLIP's mean/std
    tiny-gelu/        hidden_act "gelu" (exact, erf) and the real eos_token_id, whose pooling
                      takes the first position of that id; preprocessor_config.json with mean and
                      std 0.5, so that a test can see that the file is read

Each folder has config.json, model.safetensors and tokenizer.json. The tokenizer is a small
CLIP-style byte-level BPE (vocabulary: the 256 byte symbols, the same with "</w>", the merges
learnt from a small corpus, then <|startoftext|> and <|endoftext|>, so that the end token has
the largest id as in CLIP), wrapped by transformers' CLIPTokenizer, which builds the CLIP
normaliser, pre-tokeniser and template; its ids are checked against the `tokenizers` library
reading the saved tokenizer.json.

Requirements (development machine only, never in CI: torch is large):
    pip install torch transformers tokenizers safetensors
Run from anywhere:
    python3 vlem-backends/goldens/clip/make_clip_goldens.py
"""

import json
import math
import shutil
from pathlib import Path

import tokenizers
import torch
import transformers
from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, trainers, Regex
from transformers import CLIPConfig, CLIPModel, CLIPTokenizer

HERE = Path(__file__).resolve().parent

# Text positions of the tiny models: short, so that the long text below is truncated.
MAX_POSITIONS = 24

CORPUS = [
    "a photo of a chair next to a table in a living room",
    "a photo of a red sofa and a white wall",
    "the lamp stands on the desk beside the bookshelf",
    "a bed with two pillows under a window",
    "a picture hangs on the wall above the television",
    "there is a cabinet, a dresser and a night stand in the bedroom",
    "books on a shelf, a box on the floor, a whiteboard on the wall",
    "something to sit on, something to sleep on",
    "a door, a window and the ceiling of the room",
    "it's a photo of the kitchen; they're cooking and we've eaten",
]

TEXTS = [
    "a photo of a chair.",
    "A Red SOFA next to the White Wall",
    "",
    "something to sit on",
    "it's 3 o'clock: room #42, we've (maybe) 2 lamps!",
    "  spaces   and\ttabs\nand newlines  ",
    # Unicode: accents (NFC-composed and decomposed), CJK, an emoji; unseen bytes become byte
    # symbols, never the unknown token.
    "Café crème, nai\u0308ve façade — 椅子 と テーブル 🪑",
    # Longer than MAX_POSITIONS tokens: truncated, the end token kept.
    "a very long description of a cluttered living room with a sofa, a lamp, a table, four chairs, "
    "a bookshelf full of books and a television on a cabinet next to the window",
]

MODELS = {
    "tiny-quick-gelu": {
        "hidden_act": "quick_gelu",
        "legacy_eos": True,
        "preprocessor": {
            "image_mean": [0.48145466, 0.4578275, 0.40821073],
            "image_std": [0.26862954, 0.26130258, 0.27577711],
        },
        "seed": 0,
        "layers": 2,
    },
    "tiny-gelu": {
        "hidden_act": "gelu",
        "legacy_eos": False,
        "preprocessor": {"image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]},
        "seed": 1,
        "layers": 1,
    },
}

IMAGE_SIZE = 32
PATCH_SIZE = 8
IMAGES = 3


def bytes_to_unicode() -> list[str]:
    """CLIP's (and GPT-2's) printable stand-in of each byte, in CLIP's vocabulary order."""
    printable = (
        list(range(ord("!"), ord("~") + 1))
        + list(range(ord("¡"), ord("¬") + 1))
        + list(range(ord("®"), ord("ÿ") + 1))
    )
    codes = printable[:]
    extra = 0
    for b in range(256):
        if b not in printable:
            printable.append(b)
            codes.append(256 + extra)
            extra += 1
    return [chr(c) for c in codes]


def learn_merges() -> list[tuple[str, str]]:
    """BPE merges learnt on CORPUS with CLIP's normaliser and pre-tokeniser."""
    trainee = Tokenizer(models.BPE(continuing_subword_prefix="", end_of_word_suffix="</w>"))
    trainee.normalizer = normalizers.Sequence(
        [normalizers.NFC(), normalizers.Replace(Regex(r"\s+"), " "), normalizers.Lowercase()]
    )
    trainee.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(
                Regex(
                    r"""<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"""
                ),
                behavior="removed",
                invert=True,
            ),
            pre_tokenizers.ByteLevel(add_prefix_space=False),
        ]
    )
    trainer = trainers.BpeTrainer(
        vocab_size=700,
        min_frequency=2,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        end_of_word_suffix="</w>",
        show_progress=False,
    )
    trainee.train_from_iterator(CORPUS * 4, trainer)
    merges = json.loads(trainee.to_str())["model"]["merges"]
    return [tuple(m) if isinstance(m, list) else tuple(m.split(" ")) for m in merges]


def make_tokenizer(folder: Path, merges: list[tuple[str, str]]) -> CLIPTokenizer:
    symbols = bytes_to_unicode()
    vocab: dict[str, int] = {}
    for token in symbols + [s + "</w>" for s in symbols] + ["".join(m) for m in merges]:
        vocab.setdefault(token, len(vocab))
    vocab["<|startoftext|>"] = len(vocab)
    vocab["<|endoftext|>"] = len(vocab)
    tok = CLIPTokenizer(
        vocab=vocab, merges=merges, model_max_length=MAX_POSITIONS
    )
    tok.save_pretrained(str(folder))
    # Only tokenizer.json is part of the layout the Rust side reads; the rest is transformers'.
    for extra in ["tokenizer_config.json", "special_tokens_map.json", "vocab.json", "merges.txt"]:
        (folder / extra).unlink(missing_ok=True)
    return tok


def pixels() -> torch.Tensor:
    """IMAGES x 3 x IMAGE_SIZE x IMAGE_SIZE normalised pixels, from a formula the Rust test
    evaluates too (f64, then rounded to f32)."""
    values = [
        math.sin(0.37 * (y + 1) * (c + 1) + 0.11 * x * (b + 1) + b) * 1.5 + 0.1 * c
        for b in range(IMAGES)
        for c in range(3)
        for y in range(IMAGE_SIZE)
        for x in range(IMAGE_SIZE)
    ]
    return torch.tensor(values, dtype=torch.float32).reshape(IMAGES, 3, IMAGE_SIZE, IMAGE_SIZE)


def randomise(model: CLIPModel) -> None:
    """Replaces transformers' small initialisation with larger random values so that every weight
    matters to the outputs (a wrong layout or activation shows as an error far above 1e-4)."""
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "layer_norm" in name or "layrnorm" in name or "layernorm" in name:
                if name.endswith("weight"):
                    p.copy_(1.0 + 0.2 * torch.randn_like(p))
                else:
                    p.copy_(0.1 * torch.randn_like(p))
            elif name == "logit_scale":
                continue
            else:
                fan_in = p.shape[-1] if p.dim() > 1 else 1
                if p.dim() == 4:  # patch embedding: in_channels * k * k
                    fan_in = p.shape[1] * p.shape[2] * p.shape[3]
                std = 1.0 / math.sqrt(fan_in) if p.dim() > 1 else 0.5
                p.copy_(std * torch.randn_like(p))


def main() -> None:
    out = {
        "generator": "vlem-backends/goldens/clip/make_clip_goldens.py",
        "transformers": transformers.__version__,
        "tokenizers": tokenizers.__version__,
        "torch": torch.__version__,
        "pixels": {
            "formula": "sin(0.37*(y+1)*(c+1) + 0.11*x*(b+1) + b)*1.5 + 0.1*c",
            "shape": [IMAGES, 3, IMAGE_SIZE, IMAGE_SIZE],
        },
        "models": {},
    }
    px = pixels()
    # Learnt once: the trainer breaks ties between equally frequent pairs in no fixed order.
    merges = learn_merges()
    for name, spec in MODELS.items():
        folder = HERE / name
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        tok = make_tokenizer(folder, merges)
        bos, eos = tok.bos_token_id, tok.eos_token_id
        assert eos == len(tok) - 1, "the end token must have the largest id, as in CLIP"
        config = CLIPConfig(
            text_config=dict(
                vocab_size=len(tok),
                hidden_size=32,
                intermediate_size=64,
                num_hidden_layers=spec["layers"],
                num_attention_heads=4,
                max_position_embeddings=MAX_POSITIONS,
                hidden_act=spec["hidden_act"],
                bos_token_id=bos,
                eos_token_id=2 if spec["legacy_eos"] else eos,
                pad_token_id=1 if spec["legacy_eos"] else eos,
            ),
            vision_config=dict(
                # Not the text width, so that a mix-up of the towers' configs cannot go unseen.
                hidden_size=40,
                intermediate_size=64,
                num_hidden_layers=spec["layers"],
                num_attention_heads=4,
                image_size=IMAGE_SIZE,
                patch_size=PATCH_SIZE,
                hidden_act=spec["hidden_act"],
            ),
            projection_dim=16,
        )
        torch.manual_seed(spec["seed"])
        model = CLIPModel(config).eval()
        randomise(model)
        model.save_pretrained(str(folder))
        (folder / "preprocessor_config.json").write_text(
            json.dumps(
                {
                    "crop_size": {"height": IMAGE_SIZE, "width": IMAGE_SIZE},
                    "do_center_crop": True,
                    "do_normalize": True,
                    "do_resize": True,
                    "image_processor_type": "CLIPImageProcessor",
                    "resample": 3,
                    "size": {"shortest_edge": IMAGE_SIZE},
                    **spec["preprocessor"],
                },
                indent=2,
            )
            + "\n"
        )

        # Token ids: transformers' tokenizer, checked against the tokenizers library alone.
        plain = Tokenizer.from_file(str(folder / "tokenizer.json"))
        plain.enable_truncation(MAX_POSITIONS)
        ids = []
        for text in TEXTS:
            a = tok(text, truncation=True, max_length=MAX_POSITIONS)["input_ids"]
            b = plain.encode(text).ids
            assert a == b, (text, a, b)
            assert a[0] == bos and a[-1] == eos, (text, a)
            assert tok.unk_token_id not in a[1:-1], (text, a)
            ids.append(a)
        assert len(ids[-1]) == MAX_POSITIONS, "the long text must be truncated"

        batch = tok(TEXTS, truncation=True, max_length=MAX_POSITIONS, padding=True, return_tensors="pt")
        with torch.no_grad():
            text_features = model.get_text_features(**batch).pooler_output
            image_features = model.get_image_features(pixel_values=px).pooler_output
            # One text alone (no padding) gives the same features: padding never reaches the
            # pooled token through the causal mask.
            alone = model.get_text_features(
                input_ids=torch.tensor([ids[0]]), attention_mask=torch.ones(1, len(ids[0]), dtype=torch.long)
            ).pooler_output
        assert torch.allclose(alone[0], text_features[0], atol=1e-5)
        out["models"][name] = {
            "hidden_act": spec["hidden_act"],
            "eos_token_id_in_config": config.text_config.eos_token_id,
            "projection_dim": config.projection_dim,
            "image_mean": spec["preprocessor"]["image_mean"],
            "image_std": spec["preprocessor"]["image_std"],
            "texts": [
                {"text": t, "ids": i, "features": [round(float(x), 7) for x in f]}
                for t, i, f in zip(TEXTS, ids, text_features)
            ],
            "images": [[round(float(x), 7) for x in f] for f in image_features],
        }
        print(f"{name}: vocab {len(tok)}, ids of the long text {len(ids[-1])}")

    path = HERE / "clip_goldens.json"
    path.write_text(json.dumps(out, ensure_ascii=False, separators=(",", ":")) + "\n")
    total = sum(f.stat().st_size for f in HERE.rglob("*") if f.is_file())
    print(f"wrote {path}; folder total {total} bytes")


if __name__ == "__main__":
    main()
