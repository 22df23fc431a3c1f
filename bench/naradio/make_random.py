#!/usr/bin/env python3
"""Writes a NARADIO model folder of the full size with random weights, for speed measurements.

The folder is the one vlem-backends/goldens/naradio/convert_radio.py writes from RADIO's own loader
(config.json, radio.safetensors, text/), with RADIOv2.5's shapes: the B/16 or L/16 trunk (4 summary
tokens, 4 registers, a 128x128 position grid), the `siglip` adaptor (MLP v2, 1536 hidden, 1152 out)
and the text tower of SigLIP SO400M-14-384 (1152 wide, 27 layers, 16 heads, 64 positions). Speed
does not depend on the values, and no pretrained weights can be downloaded where vlem is built. The
tokenizer is the tiny one of the goldens: its ids fit the vocabulary, which is all a speed
measurement needs. Do not commit the output (~0.5 GB for B/16).

    pip install numpy safetensors
    python3 bench/naradio/make_random.py --size b OUT_DIR     # or --size l
"""

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
from safetensors.numpy import save_file

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "vlem-backends" / "goldens" / "naradio" / "tiny"
TRUNKS = {"b": (768, 12, 12, 3072), "l": (1024, 24, 16, 4096)}


def random(rng, shape, fan_in=None):
    std = (1.0 / (fan_in or shape[-1])) ** 0.5 if len(shape) > 1 else 0.02
    return (rng.standard_normal(shape, dtype=np.float32) * std).astype(np.float32)


def trunk(rng, size):
    e, depth, heads, hidden = TRUNKS[size]
    t = {
        "patch_generator.embedder.weight": random(rng, (e, 3 * 16 * 16)),
        "patch_generator.pos_embed": random(rng, (1, 128 * 128, e)),
        "patch_generator.cls_token.token": random(rng, (4 + 4, e)),
        "norm.weight": np.ones(e, np.float32),
        "norm.bias": np.zeros(e, np.float32),
    }
    for i in range(depth):
        b = f"blocks.{i}"
        t.update({
            f"{b}.norm1.weight": np.ones(e, np.float32), f"{b}.norm1.bias": np.zeros(e, np.float32),
            f"{b}.attn.qkv.weight": random(rng, (3 * e, e)), f"{b}.attn.qkv.bias": random(rng, (3 * e,)),
            f"{b}.attn.proj.weight": random(rng, (e, e)), f"{b}.attn.proj.bias": random(rng, (e,)),
            f"{b}.norm2.weight": np.ones(e, np.float32), f"{b}.norm2.bias": np.zeros(e, np.float32),
            f"{b}.mlp.fc1.weight": random(rng, (hidden, e)), f"{b}.mlp.fc1.bias": random(rng, (hidden,)),
            f"{b}.mlp.fc2.weight": random(rng, (e, hidden)), f"{b}.mlp.fc2.bias": random(rng, (e,)),
        })
    ah, ao = 1536, 1152
    t.update({
        "adaptor.fc1.weight": random(rng, (ah, e)), "adaptor.fc1.bias": random(rng, (ah,)),
        "adaptor.blocks.0.0.weight": np.ones(ah, np.float32),
        "adaptor.blocks.0.0.bias": np.zeros(ah, np.float32),
        "adaptor.blocks.0.2.weight": random(rng, (ah, ah)), "adaptor.blocks.0.2.bias": random(rng, (ah,)),
        "adaptor.final.0.weight": np.ones(ah, np.float32),
        "adaptor.final.0.bias": np.zeros(ah, np.float32),
        "adaptor.final.2.weight": random(rng, (ao, ah)), "adaptor.final.2.bias": random(rng, (ao,)),
    })
    config = json.loads((TINY / "config.json").read_text())
    config.update({
        "embed_dim": e, "depth": depth, "num_heads": heads, "mlp_hidden": hidden,
        "layer_scale": False, "pos_grid": [128, 128], "num_cls_tokens": 4, "num_registers": 4,
        "summary_idxs": [0, 1, 2], "adaptor_token_slot": 1, "adaptor_mlp": "v2",
        "feature_normalizer": False,
    })
    return t, config


def text_tower(rng):
    w, layers, hidden, vocab, positions = 1152, 27, 4304, 32000, 64
    p = "text_model."
    t = {
        p + "embeddings.token_embedding.weight": random(rng, (vocab, w)),
        p + "embeddings.position_embedding.weight": random(rng, (positions, w)),
        p + "final_layer_norm.weight": np.ones(w, np.float32),
        p + "final_layer_norm.bias": np.zeros(w, np.float32),
        p + "head.weight": random(rng, (w, w)),
        p + "head.bias": random(rng, (w,)),
    }
    for i in range(layers):
        q = f"{p}encoder.layers.{i}."
        for name in ("q_proj", "k_proj", "v_proj", "out_proj"):
            t[q + f"self_attn.{name}.weight"] = random(rng, (w, w))
            t[q + f"self_attn.{name}.bias"] = random(rng, (w,))
        for n in ("layer_norm1", "layer_norm2"):
            t[q + f"{n}.weight"] = np.ones(w, np.float32)
            t[q + f"{n}.bias"] = np.zeros(w, np.float32)
        t[q + "mlp.fc1.weight"] = random(rng, (hidden, w))
        t[q + "mlp.fc1.bias"] = random(rng, (hidden,))
        t[q + "mlp.fc2.weight"] = random(rng, (w, hidden))
        t[q + "mlp.fc2.bias"] = random(rng, (w,))
    config = json.loads((TINY / "text" / "config.json").read_text())
    config.update({
        "vocab_size": vocab, "hidden_size": w, "intermediate_size": hidden,
        "num_hidden_layers": layers, "num_attention_heads": 16,
        "max_position_embeddings": positions, "projection_size": w, "context_length": positions,
    })
    return t, config


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--size", choices=sorted(TRUNKS), default="b")
    a = ap.parse_args()
    out = Path(a.out)
    (out / "text").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    tensors, config = trunk(rng, a.size)
    save_file(tensors, str(out / "radio.safetensors"))
    (out / "config.json").write_text(json.dumps(config, indent=1))
    tensors, config = text_tower(rng)
    save_file(tensors, str(out / "text" / "model.safetensors"))
    (out / "text" / "config.json").write_text(json.dumps(config, indent=1))
    for name in ("tokenizer.json", "tokenizer_config.json"):
        shutil.copy(TINY / "text" / name, out / "text" / name)
    print(f"wrote a random RADIOv2.5-{a.size.upper()}/16 NARADIO folder to {out}")


if __name__ == "__main__":
    main()
