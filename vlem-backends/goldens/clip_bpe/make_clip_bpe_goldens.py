#!/usr/bin/env python3
"""Writes clip_bpe_goldens.json: the token ids that OpenAI CLIP's tokenizer, as Meta ships it for
dino.txt, gives for a set of texts.

The Rust tokenizer (vlem-backends `dinov3::clip_bpe`, feature `dinov3`) must give the same ids
(test `tokenizer_matches_the_reference` in vlem-backends/tests/dinov3.rs). The reference is
`dinov3/eval/text/tokenizer.py` of github.com/facebookresearch/dinov3 (OpenAI's
`SimpleTokenizer` with ftfy, html.unescape and the `regex` module, context 77, cut with the last
id set to end-of-text), over the released vocabulary `bpe_simple_vocab_16e6.txt.gz`. The same
file ships inside the PyPI wheel `open_clip_torch`, which is where the test finds it.

The texts cover what the reimplementation must get right: case, whitespace, apostrophe
contractions, digits (one token each), punctuation runs, accents and non-Latin scripts
(byte-level BPE), the text cleaning (curly quotes, ligatures, full-width letters, HTML entities,
control characters), the special-token strings, and a text longer than the context.

Requirements (development machine only): pip install torch ftfy regex, pip install --no-deps
open_clip_torch, a checkout of facebookresearch/dinov3. Run from anywhere:
    DINOV3_SRC=/path/to/dinov3 python3 vlem-backends/goldens/clip_bpe/make_clip_bpe_goldens.py
"""

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.environ["DINOV3_SRC"])
import open_clip  # noqa: E402  (only for the vocabulary file it ships)
from dinov3.eval.text.tokenizer import Tokenizer  # noqa: E402

VOCAB = Path(open_clip.__file__).parent / "bpe_simple_vocab_16e6.txt.gz"

TEXTS = [
    "a photo of a coffee machine.",
    "Where is the COFFEE machine?",
    "  something   to\tsit on \n",
    "the cat's toy, they're here, I'll go, we've seen, I'm, he'd, don't",
    "room 101 has 3 chairs and 12.5 m² of floor",
    "!!! ... ?!? --- (brackets) [square] {curly} #hash @at $dollar",
    "café naïve résumé Ærøskøbing straße",
    "Кофеварка на кухне",
    "咖啡机在哪里",
    "コーヒーメーカー",
    "emoji 🙂☕ cup",
    "the cat\u2019s \u201cfavourite\u201d spot",
    "\ufb01sh and \ufb02owers",
    "\uff23\uff4f\uff46\uff46\uff45\uff45\u3000\uff11\uff12",
    "salt &amp; pepper &lt;grinder&gt; &#39;x&#39; &#x41;",
    "tab\x07bell and nul\x00 here",
    "<|startoftext|>a<|endoftext|>",
    "a",
    "",
    "chair " * 100,
]


def main():
    tokenizer = Tokenizer(str(VOCAB))
    ids = tokenizer.tokenize(TEXTS, context_length=77)
    cases = []
    for text, row in zip(TEXTS, ids.tolist()):
        # Drop the zero padding: the Rust tokenizer returns the unpadded ids.
        end = len(row)
        while end > 0 and row[end - 1] == 0:
            end -= 1
        cases.append({"text": text, "ids": row[:end]})
    out = Path(__file__).with_name("clip_bpe_goldens.json")
    out.write_text(json.dumps({"context_length": 77, "cases": cases}, ensure_ascii=False, indent=1) + "\n")
    print(f"wrote {out}: {len(cases)} cases")


if __name__ == "__main__":
    main()
