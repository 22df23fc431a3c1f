"""PyTorch's attention at vlem's attention_bench shapes: milliseconds per call of
torch.nn.functional.scaled_dot_product_attention (the backend PyTorch picks: flash attention in
half precision on a recent GPU) and of the unfused math (two products and a softmax), one JSON
line per shape and type with the fields of `attention_bench`'s lines.

    python3 bench/attention/sdpa_bench.py --device cuda [--iterations 20]
"""
import argparse
import json
import time

import torch

SHAPES = [
    ("clip-b16-batch32", 32, 12, 197, 64),
    ("naradio-b16-640x480", 1, 12, 1208, 64),
    ("naradio-l16-640x480", 1, 16, 1208, 64),
    ("dinov3-l16-448", 1, 16, 789, 64),
    ("tokens-4096", 1, 16, 4096, 64),
]
TYPES = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}


def per_call_ms(fn, device, iterations):
    fn()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(iterations):
        fn()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return (time.perf_counter() - start) * 1e3 / iterations


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--iterations", type=int, default=20)
    a = ap.parse_args()
    torch.manual_seed(0)
    for name, batch, heads, tokens, head_dim in SHAPES:
        q, k, v = (torch.randn(batch, heads, tokens, head_dim, device=a.device) for _ in range(3))
        for dtype_name, dtype in TYPES.items():
            qt, kt, vt = q.to(dtype), k.to(dtype), v.to(dtype)
            scale = head_dim ** -0.5
            with torch.inference_mode():
                sdpa = per_call_ms(
                    lambda: torch.nn.functional.scaled_dot_product_attention(qt, kt, vt),
                    a.device, a.iterations)
                math = per_call_ms(
                    lambda: torch.softmax((qt * scale) @ kt.transpose(-1, -2), dim=-1) @ vt,
                    a.device, a.iterations)
            print(json.dumps({
                "impl": "torch " + torch.__version__, "shape": name, "batch": batch,
                "heads": heads, "tokens": tokens, "head_dim": head_dim, "device": a.device,
                "dtype": dtype_name, "unfused_ms": round(math, 4), "fused_ms": round(sdpa, 4),
                "unfused_over_fused": round(math / sdpa, 2),
            }), flush=True)


if __name__ == "__main__":
    main()
