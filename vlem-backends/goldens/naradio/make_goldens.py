"""Goldens for vlem's `naradio` encoder, from the reference code itself.

Builds a tiny random RADIOv2.5-like checkpoint in the torch.hub layout (`{"args", "state_dict"}`,
`base_model.*`, `input_conditioner.*`, `_heads.siglip.*`, `_feature_projections.siglip.*`) whose
`siglip` teacher is a tiny open_clip SigLIP-style text tower (custom text, no causal mask, last-token
pool, projection with bias) with a tiny SentencePiece-style (Unigram) tokenizer; loads it with RADIO's
own `hubconf.radio_model`; wraps it in RayFronts' own `NARadioEncoder` (torch.hub.load redirected to
the tiny model); and records:
  - the plain RADIO trunk (summary, patch features) before the NACLIP change,
  - NARADIO outputs (patch features with the NACLIP last block, language-aligned patch grid and global
    vector) for a 64x64 and a 48x80 image, with RayFronts' Gaussian-prior layout and with NACLIP's,
  - the Gaussian prior matrices themselves,
  - token ids and text embeddings (open_clip tokenizer + text tower) and RayFronts' encode_labels.
The model folder vlem reads is written by convert_radio.export() into tiny/ (so the converter is
exercised too), and the converted text tower is cross-checked against transformers' SiglipTextModel.

Run: RADIO_SRC=/path/to/NVlabs/RADIO RAYFRONTS_SRC=/path/to/RayFronts python make_goldens.py
(torch 2.15, timm 1.0.31, einops, open_clip_torch 3.3.0, transformers 5.24, tokenizers, safetensors).
"""

import argparse
import json
import os
import sys
import tempfile

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
RADIO_SRC = os.environ.get("RADIO_SRC", "/tmp/radio_src")
RAYFRONTS_SRC = os.environ.get("RAYFRONTS_SRC", "/tmp/rayfronts_src")
sys.path.insert(0, RADIO_SRC)
sys.path.insert(0, RAYFRONTS_SRC)
sys.path.insert(0, HERE)

import open_clip  # noqa: E402
import hubconf  # noqa: E402  (RADIO's)
from radio.radio_model import create_model_from_args  # noqa: E402
from radio.adaptor_mlp import MLP2  # noqa: E402
import convert_radio  # noqa: E402

EMBED, DEPTH, HEADS = 48, 3, 3
GRID = 8  # position table 8x8 (cpe_max_size 128)
ADAPTOR_HIDDEN = 64
TEXT_WIDTH, TEXT_HEADS, TEXT_LAYERS, CONTEXT = 40, 4, 2, 16
GAUSS_STD = 1.5
SIZES = [(64, 64), (48, 80)]
PROMPTS = ["a photo of a chair.", "The_Red SOFA!!", "  two   lamps , on a TABLE ", "x " * 30]
LABELS = ["chair", "red sofa"]


def pixels(h, w):
    """x[c, y, x] = 0.5 + 0.45 sin(0.7 c + 0.31 y + 0.17 x + 0.013 x y), in [0, 1]."""
    c = torch.arange(3, dtype=torch.float64).view(3, 1, 1)
    y = torch.arange(h, dtype=torch.float64).view(1, h, 1)
    x = torch.arange(w, dtype=torch.float64).view(1, 1, w)
    return (0.5 + 0.45 * torch.sin(0.7 * c + 0.31 * y + 0.17 * x + 0.013 * x * y)).float().unsqueeze(0)


def randomise(module, gen):
    """Every parameter random at a scale where activations stay O(1)."""
    with torch.no_grad():
        for name, p in module.named_parameters():
            if p.ndim == 1 and name.endswith("weight"):
                p.copy_(1.0 + 0.2 * torch.randn(p.shape, generator=gen))
            elif p.ndim == 1:
                p.copy_(0.2 * torch.randn(p.shape, generator=gen))
            elif p.ndim == 2 and "embedding" not in name and "pos" not in name and "token" not in name:
                p.copy_(torch.randn(p.shape, generator=gen) / p.shape[1] ** 0.5)
            else:
                p.copy_(0.5 * torch.randn(p.shape, generator=gen))


def make_tokenizer(tok_dir):
    """A tiny Unigram (SentencePiece-style) tokenizer: Metaspace, `</s>` appended, pad = `</s>`."""
    from tokenizers import Tokenizer, models, pre_tokenizers, decoders, processors, trainers
    from transformers import PreTrainedTokenizerFast

    tok = Tokenizer(models.Unigram())
    tok.pre_tokenizer = pre_tokenizers.Metaspace()
    tok.decoder = decoders.Metaspace()
    corpus = [
        "a photo of a chair", "the red sofa", "two lamps on a table", "a bad photo of the",
        "a sculpture of many", "a rendering of graffiti", "a drawing of my toy", "the origami plastic",
        "x x x x", "a cropped photo of a hard to see", "a video game", "a tattoo doodle sketch",
    ] * 20
    trainer = trainers.UnigramTrainer(vocab_size=90, special_tokens=["<pad>", "</s>", "<unk>"],
                                      unk_token="<unk>")
    tok.train_from_iterator(corpus, trainer)
    eos = tok.token_to_id("</s>")
    tok.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", eos)])
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, eos_token="</s>", pad_token="</s>",
                                   unk_token="<unk>")
    fast.save_pretrained(tok_dir)
    return tok.get_vocab_size()


def make_text_model(work):
    tok_dir = os.path.join(work, "tok")
    vocab = make_tokenizer(tok_dir)
    cfg = {
        "embed_dim": TEXT_WIDTH,
        "init_logit_bias": -10,
        "custom_text": True,
        "vision_cfg": {"image_size": 32, "patch_size": 16, "width": 32, "layers": 1, "head_width": 16},
        "text_cfg": {
            "context_length": CONTEXT, "vocab_size": vocab, "hf_tokenizer_name": tok_dir,
            "tokenizer_kwargs": {"clean": "canonicalize"}, "width": TEXT_WIDTH, "heads": TEXT_HEADS,
            "layers": TEXT_LAYERS, "mlp_ratio": 3.7362, "no_causal_mask": True, "proj_bias": True,
            "pool_type": "last", "norm_kwargs": {"eps": 1e-6},
        },
    }
    cfg_dir = os.path.join(work, "oc_cfg")
    os.makedirs(cfg_dir, exist_ok=True)
    with open(os.path.join(cfg_dir, "tiny-siglip.json"), "w") as f:
        json.dump(cfg, f)
    open_clip.add_model_config(cfg_dir)
    model = open_clip.create_model("tiny-siglip")
    randomise(model, torch.Generator().manual_seed(7))
    ckpt = os.path.join(work, "tiny_siglip.pt")
    torch.save(model.state_dict(), ckpt)
    return ckpt


def make_radio_checkpoint(work, text_ckpt):
    teachers = [
        {"name": "clip", "type": "open_clip", "use_summary": True},
        {"name": "siglip", "type": "open_clip", "model": "tiny-siglip", "pretrained": text_ckpt,
         "use_summary": True},
        {"name": "dino_v2", "type": "dino_v2", "use_summary": True},
        {"name": "sam", "type": "sam", "use_summary": False},
    ]
    args = argparse.Namespace(
        model="vit_base_patch16_224", model_kwargs={"embed_dim": EMBED, "depth": DEPTH, "num_heads": HEADS},
        in_chans=None, input_size=None, pretrained=False, num_classes=0, drop=0.0, drop_path=None,
        drop_block=None, gp=None, bn_momentum=None, bn_eps=None, torchscript=False,
        initial_checkpoint="", model_norm=True, cpe_max_size=GRID * 16, teachers=teachers,
        cls_token_per_teacher=True, register_multiple=8, spectral_reparam=False, damp=None,
        mlp_version="v2", dtype=torch.float32,
    )
    mod = create_model_from_args(argparse.Namespace(**{**vars(args), "model_kwargs": dict(args.model_kwargs)}))
    gen = torch.Generator().manual_seed(3)
    randomise(mod, gen)
    sd = {"base_model." + k: v for k, v in mod.state_dict().items()}
    sd["input_conditioner.norm_mean"] = torch.tensor([0.48145466, 0.4578275, 0.40821073]).view(3, 1, 1)
    sd["input_conditioner.norm_std"] = torch.tensor([0.26862954, 0.26130258, 0.27577711]).view(3, 1, 1)
    for tidx, t in enumerate(teachers):
        for kind, prefix in (("summary", "_heads."), ("feature", "_feature_projections.")):
            mlp = MLP2(EMBED, ADAPTOR_HIDDEN, TEXT_WIDTH, num_inner=1)
            randomise(mlp, gen)
            for k, v in mlp.state_dict().items():
                sd[f"{prefix}{t['name']}.{k}"] = v
    path = os.path.join(work, "tiny-radio.pth.tar")
    torch.save({"args": args, "state_dict": sd}, path)
    return path


def flat(t):
    return [round(float(v), 7) for v in t.detach().flatten().tolist()]


def main():
    torch.manual_seed(0)
    out = {}
    with tempfile.TemporaryDirectory() as work:
        text_ckpt = make_text_model(work)
        ckpt = make_radio_checkpoint(work, text_ckpt)
        radio = hubconf.radio_model(version=ckpt, adaptor_names=["siglip"])
        radio.eval()

        tiny = os.path.join(HERE, "tiny")
        cfg = convert_radio.export(radio, "siglip", tiny)
        out["config"] = cfg
        out["gauss_std"] = GAUSS_STD

        # 1. The plain trunk (RADIO's forward, before RayFronts touches it).
        trunk = []
        with torch.no_grad():
            for h, w in SIZES:
                y = radio(pixels(h, w))["backbone"]
                trunk.append({"height": h, "width": w, "summary": flat(y.summary),
                              "features": flat(y.features), "tokens": list(y.features.shape)})
        out["trunk"] = trunk

        # 2. RayFronts' NARadioEncoder on the same model.
        from rayfronts.image_encoders import naradio as rf
        torch.hub.load = lambda *a, **k: radio  # the only network access in NARadioEncoder
        enc = rf.NARadioEncoder(device="cpu", model_version="tiny", lang_model="siglip",
                                input_resolution=list(SIZES[0]), gauss_std=GAUSS_STD,
                                return_radio_features=True, compile=False, amp=False)
        attn = enc.model.model.blocks[-1].attn
        nar = []
        with torch.no_grad():
            for h, w in SIZES:
                enc.input_resolution = (h, w)
                x = pixels(h, w)
                feat = enc.encode_image_to_feat_map(x)  # (1, C, h', w')
                lang = enc.align_spatial_features_with_language(feat)
                vec = enc.encode_image_to_vector(x)
                glob = enc.align_global_features_with_language(vec)
                prior = attn.attn_addition[0]
                entry = {"height": h, "width": w, "features": flat(feat), "lang": flat(lang),
                         "global": flat(glob), "prior": flat(prior), "prior_dim": prior.shape[0]}
                # NACLIP's own layout (rows first), through RayFronts' helpers.
                hp, wp = h // 16, w // 16
                win = rf.GaussKernelAttn.gaussian_window(2 * hp - 1, 2 * wp - 1, std=GAUSS_STD, device="cpu")
                attn.attn_addition = rf.GaussKernelAttn.get_attention_addition(
                    hp, wp, win, attn.num_prefix_tokens).unsqueeze(0)
                feat_i = enc.encode_image_to_feat_map(x)
                entry["features_image_grid"] = flat(feat_i)
                entry["lang_image_grid"] = flat(enc.align_spatial_features_with_language(feat_i))
                entry["prior_image_grid"] = flat(attn.attn_addition[0])
                nar.append(entry)
        out["naradio"] = nar

        # 3. Text: open_clip tokenizer + text tower, RayFronts' label encoding.
        adaptor = enc.lang_adaptor
        saved = torch.load(text_ckpt)["text.token_embedding.weight"]
        assert torch.equal(adaptor.oc_model.text.token_embedding.weight, saved), "text weights not loaded"
        with torch.no_grad():
            ids = adaptor.tokenizer(PROMPTS)
            emb = adaptor.encode_text(ids)
            labels = enc.encode_labels(LABELS)
        out["text"] = {"prompts": PROMPTS, "ids": ids.tolist(), "embeddings": flat(emb),
                       "labels": LABELS, "label_embeddings": flat(labels)}

        # Cross-check: the converted text folder under transformers' SiglipTextModel.
        from transformers import SiglipTextModel, SiglipTextConfig
        tcfg = json.load(open(os.path.join(tiny, "text", "config.json")))
        keep = {k: v for k, v in tcfg.items() if k not in ("context_length", "text_clean", "model_type")}
        hf = SiglipTextModel(SiglipTextConfig(**keep))
        from safetensors.torch import load_file
        sd = load_file(os.path.join(tiny, "text", "model.safetensors"))
        sd = {k[len("text_model."):]: v for k, v in sd.items()}
        missing = hf.load_state_dict(sd, strict=True)
        hf.eval()
        with torch.no_grad():
            hf_emb = hf(input_ids=ids).pooler_output
        diff = (hf_emb - emb).abs().max().item()
        print("transformers SiglipTextModel vs open_clip:", diff, missing)
        assert diff < 1e-5, diff

    with open(os.path.join(HERE, "naradio_goldens.json"), "w") as f:
        json.dump(out, f)
    print("wrote", os.path.join(HERE, "naradio_goldens.json"))


if __name__ == "__main__":
    main()
