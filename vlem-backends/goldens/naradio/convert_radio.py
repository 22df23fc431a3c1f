"""Writes the model folder vlem's `naradio` encoder reads, from RADIO's own torch.hub loader.

Usage (once, with network; needs torch, timm, einops, open_clip_torch, safetensors):

    python convert_radio.py --version radio_v2.5-b --out models/naradio-b
    python convert_radio.py --version radio_v2.5-l --out models/naradio-l   # what RayFronts uses

`--version` is a RADIO version name (downloaded by torch.hub from huggingface.co/nvidia/RADIO) or the
path of a `.pth.tar` checkpoint already on disk. The model is loaded exactly as RayFronts loads it
(`torch.hub.load("NVlabs/RADIO", "radio_model", version=..., adaptor_names=["siglip"])`, which also
fetches the SigLIP text tower `timm/ViT-SO400M-14-SigLIP-384` through open_clip), then written as:

    OUT/config.json           backbone and adaptor shape facts read off the live modules
    OUT/radio.safetensors     backbone (patch_generator.*, blocks.*, norm.*), adaptor.* (the
                              siglip summary MLP), feature_normalizer.* when the model has one
    OUT/text/config.json      SigLIP text tower config (Hugging Face SiglipTextConfig keys)
    OUT/text/model.safetensors  the text tower under Hugging Face `text_model.` names
    OUT/text/tokenizer.json   the tokenizer open_clip uses for it

`export()` is also what make_goldens.py calls on its tiny model, so the goldens exercise this file.
"""

import argparse
import json
import os

import torch
from torch import nn
from safetensors.torch import save_file


def _f32(t):
    return t.detach().to(torch.float32).contiguous().clone()


def _require(cond, what):
    if not cond:
        raise SystemExit(f"convert_radio: unsupported model: {what}")


def export(radio, adaptor_name, out_dir):
    """Writes `out_dir` from a loaded RADIOModel `radio` that holds adaptor `adaptor_name`."""
    from radio.adaptor_mlp import MLP, MLP2
    from radio.feature_normalizer import FeatureNormalizer

    os.makedirs(os.path.join(out_dir, "text"), exist_ok=True)
    vit = radio.model
    pg = getattr(vit, "patch_generator", None)
    _require(pg is not None, "no CPE patch generator (not a RADIOv2.5 ViT)")
    _require(pg.abs_pos, "no absolute position embedding")
    _require(isinstance(pg.patch_normalizer, nn.Identity), "patch normaliser")
    _require(pg.embedder.bias is None, "patch embedder with bias")
    _require(pg.cls_token.enabled, "no cls tokens")
    blocks = list(vit.blocks)
    b0 = blocks[0]
    _require(isinstance(b0.attn.q_norm, nn.Identity), "q/k norm in attention")
    _require(isinstance(b0.mlp.act, nn.GELU) and b0.mlp.act.approximate == "none", "MLP activation")
    layer_scale = not isinstance(b0.ls1, nn.Identity)
    final_norm = not isinstance(vit.norm, nn.Identity)
    adaptor = radio.adaptors[adaptor_name]
    head = adaptor.head_mlp
    if isinstance(head, MLP2):
        _require(isinstance(head.pre_norm, nn.Identity), "adaptor pre-norm")
        _require(head.upsample_factor == 1, "adaptor upsampling")
        mlp_version = "v2"
        adaptor_eps = head.final[0].eps
    elif isinstance(head, MLP):
        mlp_version = "v1"
        adaptor_eps = head.norm.eps
    else:
        raise SystemExit(f"convert_radio: unsupported adaptor head {type(head)}")
    normalizer = radio.feature_normalizer
    has_normalizer = isinstance(normalizer, FeatureNormalizer)

    summary_idxs = radio.summary_idxs.tolist() if radio.summary_idxs is not None else [0]
    config = {
        "format": "vlem-naradio-1",
        "patch_size": pg.patch_size,
        "embed_dim": vit.embed_dim,
        "depth": len(blocks),
        "num_heads": b0.attn.num_heads,
        "mlp_hidden": b0.mlp.fc1.out_features,
        "qkv_bias": b0.attn.qkv.bias is not None,
        "layer_scale": layer_scale,
        "layer_norm_eps": b0.norm1.eps,
        "final_norm": final_norm,
        "pos_grid": [pg.num_rows, pg.num_cols],
        "num_cls_tokens": pg.num_cls_tokens,
        "num_registers": pg.num_registers,
        "summary_idxs": summary_idxs,
        "adaptor": adaptor_name,
        "adaptor_token_slot": int(adaptor.head_idx),
        "adaptor_mlp": mlp_version,
        "adaptor_layer_norm_eps": adaptor_eps,
        "feature_normalizer": has_normalizer,
        "input_mean": radio.input_conditioner.norm_mean.flatten().tolist(),
        "input_std": radio.input_conditioner.norm_std.flatten().tolist(),
    }

    tensors = {}
    for k, v in vit.state_dict().items():
        if k.startswith(("patch_generator.", "blocks.")) or (final_norm and k.startswith("norm.")):
            tensors[k] = _f32(v)
    for k, v in head.state_dict().items():
        tensors["adaptor." + k] = _f32(v)
    if has_normalizer:
        tensors["feature_normalizer.mean"] = _f32(normalizer.mean)
        tensors["feature_normalizer.tx"] = _f32(normalizer.tx)
    save_file(tensors, os.path.join(out_dir, "radio.safetensors"))
    with open(os.path.join(out_dir, "config.json"), "w") as f:
        json.dump(config, f, indent=1)

    export_text(adaptor, os.path.join(out_dir, "text"))
    return config


def export_text(adaptor, text_dir):
    """The open_clip SigLIP text tower of `adaptor`, under Hugging Face SiglipTextModel names."""
    oc = adaptor.oc_model
    text = getattr(oc, "text", None)
    _require(text is not None, "text tower is not a custom open_clip text tower (SigLIP)")
    _require(text.attn_mask is None, "causal text mask")
    _require(text.pool_type == "last" and text.cls_emb is None, "text pooling other than the last token")
    _require(isinstance(text.text_projection, nn.Linear), "text projection without bias")
    r0 = text.transformer.resblocks[0]
    _require(isinstance(r0.ls_1, nn.Identity), "text layer scale")
    act = r0.mlp.gelu
    _require(isinstance(act, nn.GELU), "text MLP activation")
    width = text.width
    _require(text.text_projection.out_features == width, "text projection changes the width")

    t = {}
    p = "text_model."
    t[p + "embeddings.token_embedding.weight"] = _f32(text.token_embedding.weight)
    t[p + "embeddings.position_embedding.weight"] = _f32(text.positional_embedding)
    for i, blk in enumerate(text.transformer.resblocks):
        q = f"{p}encoder.layers.{i}."
        w, b = blk.attn.in_proj_weight, blk.attn.in_proj_bias
        for j, name in enumerate(["q_proj", "k_proj", "v_proj"]):
            t[q + f"self_attn.{name}.weight"] = _f32(w[j * width:(j + 1) * width])
            t[q + f"self_attn.{name}.bias"] = _f32(b[j * width:(j + 1) * width])
        t[q + "self_attn.out_proj.weight"] = _f32(blk.attn.out_proj.weight)
        t[q + "self_attn.out_proj.bias"] = _f32(blk.attn.out_proj.bias)
        t[q + "layer_norm1.weight"] = _f32(blk.ln_1.weight)
        t[q + "layer_norm1.bias"] = _f32(blk.ln_1.bias)
        t[q + "layer_norm2.weight"] = _f32(blk.ln_2.weight)
        t[q + "layer_norm2.bias"] = _f32(blk.ln_2.bias)
        t[q + "mlp.fc1.weight"] = _f32(blk.mlp.c_fc.weight)
        t[q + "mlp.fc1.bias"] = _f32(blk.mlp.c_fc.bias)
        t[q + "mlp.fc2.weight"] = _f32(blk.mlp.c_proj.weight)
        t[q + "mlp.fc2.bias"] = _f32(blk.mlp.c_proj.bias)
    t[p + "final_layer_norm.weight"] = _f32(text.ln_final.weight)
    t[p + "final_layer_norm.bias"] = _f32(text.ln_final.bias)
    t[p + "head.weight"] = _f32(text.text_projection.weight)
    t[p + "head.bias"] = _f32(text.text_projection.bias)
    save_file(t, os.path.join(text_dir, "model.safetensors"))

    tok = adaptor.tokenizer
    hf_tok = tok.tokenizer
    hf_tok.save_pretrained(text_dir)
    _require(os.path.exists(os.path.join(text_dir, "tokenizer.json")), "tokenizer has no tokenizer.json")
    clean_name = getattr(tok.clean_fn, "__name__", "?")
    clean = next((c for c in ("canonicalize", "whitespace") if c in clean_name), None)
    _require(clean is not None, f"text cleaning {clean_name}")
    cfg = {
        "model_type": "siglip_text_model",
        "vocab_size": text.vocab_size,
        "hidden_size": width,
        "intermediate_size": r0.mlp.c_fc.out_features,
        "num_hidden_layers": len(text.transformer.resblocks),
        "num_attention_heads": text.heads,
        "max_position_embeddings": text.context_length,
        "hidden_act": "gelu" if act.approximate == "none" else "gelu_pytorch_tanh",
        "layer_norm_eps": r0.ln_1.eps,
        "projection_size": width,
        "pad_token_id": hf_tok.pad_token_id,
        "eos_token_id": hf_tok.eos_token_id,
        "bos_token_id": hf_tok.bos_token_id if hf_tok.bos_token_id is not None else hf_tok.eos_token_id,
        "context_length": tok.context_length,
        "text_clean": clean,
    }
    with open(os.path.join(text_dir, "config.json"), "w") as f:
        json.dump(cfg, f, indent=1)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--version", default="radio_v2.5-l")
    ap.add_argument("--adaptor", default="siglip")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    radio = torch.hub.load("NVlabs/RADIO", "radio_model", version=a.version, progress=True,
                           skip_validation=True, adaptor_names=[a.adaptor])
    radio.eval()
    cfg = export(radio, a.adaptor, a.out)
    print(json.dumps(cfg, indent=1))


if __name__ == "__main__":
    main()
