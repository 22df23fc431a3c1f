#!/usr/bin/env python3
"""Every model stage per 640x480 frame in vlem and in its reference implementation, in one run:
one JSON line per model with both times and the ratio (reference / vlem: above 1 is vlem ahead).

Full-size architectures with random weights (speed does not depend on the values), same inputs on
both sides, best of REPEAT calls after a warm-up. Run through `bench/models/side_by_side.sh`,
which builds the vlem side; the reference side runs in the virtualenv of PYTHON.

`--device cuda` times both sides on a GPU (vlem built with feature `cuda`); `--dtype f16` (or
`bf16`) both in that half precision (vlem's `dtype` key; PyTorch's model in it, SDPA on, or under
autocast for SAM, whose package feeds f32 inputs); `--examples DIR` runs the vlem benchmarks from
DIR instead of target/release/examples (bench/gpu/check.sh). MiniLM has no half rows: vlem's
label-text runs in f32 only.

Models (default: all but the slow SAM rows, which `bench/sam/side_by_side.sh` also gives):
  clip-1, clip-32   CLIP ViT-B/16 image tower, one crop / a batch of 32 crops (transformers)
  clip-text-1, -80  its text tower, one 16-token text / 80 (a query through 80 templates)
  minilm-1, -80     all-MiniLM-L6-v2 (label-text), 1 / 80 short texts (sentence-transformers)
  dinov3            ViT-L/16 + dino.txt vision head at short side 448 (transformers + Meta's head)
  naradio-b, -l     RADIOv2.5 B/16, L/16 trunk + NACLIP + adaptor in vlem; timm's trunk in PyTorch
  sam-mobile, sam-vit-b  the automatic mask generator at 16² points (mobile_sam, segment-anything)
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
EXAMPLES = os.path.join(ROOT, "target", "release", "examples")
DEVICE = "cpu"
DTYPE = "f32"
# The reference interpreter's folder, first on every command's PATH: vlem finds the pip packages
# it reads (the MiniLM model, open_clip's vocabulary) through `python3`, which is then the
# reference virtualenv's, with the packages installed there.
REFERENCE_BIN = None


def run(cmd, threads, env=None):
    e = dict(os.environ, RAYON_NUM_THREADS=str(threads), VLEM_BENCH_DEVICE=DEVICE,
             VLEM_BENCH_DTYPE=DTYPE, **(env or {}))
    if REFERENCE_BIN:
        e["PATH"] = REFERENCE_BIN + os.pathsep + e.get("PATH", "")
    out = subprocess.run(cmd, cwd=ROOT, env=e, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{out.stdout}\n{out.stderr}")
    return out.stdout


def find(pattern, text, what):
    m = re.search(pattern, text)
    if not m:
        sys.exit(f"no {what} in:\n{text}")
    return float(m.group(1))


def clip(py, threads, repeat, batch):
    model = "/tmp/clip-vit-b16-random"
    if not os.path.exists(os.path.join(model, "model.safetensors")):
        run([py, "bench/clip/make_random_b16.py", model], threads)
    ours = run([os.path.join(EXAMPLES, "clip_bench"), model, "--batch", str(batch),
                "--repeat", str(repeat)], threads)
    ref = run([py, "bench/clip/torch_bench.py", model, "--threads", str(threads), "--batch",
               str(batch), "--repeat", str(repeat), "--device", DEVICE, "--dtype", DTYPE],
              threads)
    pat = rf"batch={batch}: best ([\d.]+) ms/call"
    return find(pat, ours, "vlem time"), "transformers CLIPModel", find(pat, ref, "torch time")


def clip_text(py, threads, repeat, n):
    model = "/tmp/clip-vit-b16-random"
    if not os.path.exists(os.path.join(model, "model.safetensors")):
        run([py, "bench/clip/make_random_b16.py", model], threads)
    ours = run([os.path.join(EXAMPLES, "clip_bench"), model, "--text", str(n), "--repeat",
                str(repeat)], threads)
    ref = run([py, "bench/clip/torch_bench.py", model, "--threads", str(threads), "--batch",
               "--text", str(n), "--repeat", str(repeat), "--device", DEVICE, "--dtype", DTYPE],
              threads)
    pat = rf"text={n}x16: best ([\d.]+) ms/call"
    return find(pat, ours, "vlem time"), "transformers CLIPModel", find(pat, ref, "torch time")


def minilm(py, threads, repeat, n):
    if DTYPE != "f32":
        sys.exit("minilm: vlem's label-text runs in f32 only (candle's BERT makes NaN in half)")
    ours = run([os.path.join(EXAMPLES, "minilm_bench"), "--texts", str(n), "--repeat",
                str(repeat)], threads)
    ref = run([py, "bench/minilm/torch_bench.py", "--threads", str(threads), "--texts", str(n),
               "--repeat", str(repeat), "--device", DEVICE], threads)
    pat = rf"texts={n}: best ([\d.]+) ms/call"
    return find(pat, ours, "vlem time"), "sentence-transformers", find(pat, ref, "torch time")


def dinov3(py, threads, repeat):
    ours = run([os.path.join(EXAMPLES, "dinov3_bench"), "448", str(repeat)], threads)
    ref = run([py, "bench/dinov3/torch_bench.py", "--threads", str(threads), "--repeat",
               str(repeat), "--device", DEVICE, "--dtype", DTYPE], threads)
    return (find(r"best ([\d.]+) ms/frame", ours, "vlem time"),
            "transformers DINOv3ViTModel + dino.txt head",
            find(r"best ([\d.]+) ms/frame", ref, "torch time"))


def naradio(py, threads, repeat, size):
    ours = run([os.path.join(EXAMPLES, "naradio_bench"), size, str(repeat)], threads)
    ref = run([py, "bench/naradio/torch_bench.py", "--threads", str(threads), "--model", size,
               "--repeat", str(repeat), "--device", DEVICE, "--dtype", DTYPE], threads)
    return (find(r"best ([\d.]+) ms/frame", ours, "vlem time"), "timm ViT trunk (no NACLIP, no adaptor)",
            find(r"best ([\d.]+) ms/frame", ref, "torch time"))


def sam(py, threads, repeat, variant):
    out = run(["bench/sam/side_by_side.sh", "--threads", str(threads), "--device", DEVICE,
               "--dtype", DTYPE, "--repeat", str(repeat), variant], threads,
              env={"PYTHON": py, "VLEM_EXAMPLES": EXAMPLES})
    row = json.loads(out.strip().splitlines()[-1])
    return row["vlem_generator_s"] * 1e3, row["reference"], row["reference_generator_s"] * 1e3


MODELS = {
    "clip-1": lambda py, t, r: clip(py, t, r, 1),
    "clip-32": lambda py, t, r: clip(py, t, r, 32),
    "clip-text-1": lambda py, t, r: clip_text(py, t, r, 1),
    "clip-text-80": lambda py, t, r: clip_text(py, t, r, 80),
    "minilm-1": lambda py, t, r: minilm(py, t, r, 1),
    "minilm-80": lambda py, t, r: minilm(py, t, r, 80),
    "dinov3": dinov3,
    "naradio-b": lambda py, t, r: naradio(py, t, r, "b"),
    "naradio-l": lambda py, t, r: naradio(py, t, r, "l"),
    "sam-mobile": lambda py, t, r: sam(py, t, r, "mobile-sam"),
    "sam-vit-b": lambda py, t, r: sam(py, t, r, "vit-b"),
}


def main():
    global DEVICE, DTYPE, EXAMPLES, REFERENCE_BIN
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N, for both sides")
    ap.add_argument("--dtype", default="f32", choices=["f32", "f16", "bf16"],
                    help="both sides' type: f32, or half precision")
    ap.add_argument("--examples", default=EXAMPLES, help="folder of the vlem benchmarks")
    ap.add_argument("models", nargs="*", default=["clip-1", "clip-32", "clip-text-1",
                                                  "clip-text-80", "minilm-1", "minilm-80",
                                                  "dinov3", "naradio-b",
                                                  "naradio-l"])
    a = ap.parse_args()
    DEVICE, DTYPE, EXAMPLES = a.device, a.dtype, os.path.abspath(a.examples)
    py = os.environ.get("PYTHON", os.path.join(ROOT, "bench", ".venv-torch", "bin", "python"))
    REFERENCE_BIN = os.path.dirname(os.path.abspath(shutil.which(py) or py))
    for name in a.models:
        if name not in MODELS:
            sys.exit(f"unknown model {name}; known: {', '.join(MODELS)}")
        for t in a.threads:
            ours, ref_name, ref = MODELS[name](py, t, a.repeat)
            print(json.dumps({"model": name, "device": DEVICE, "dtype": DTYPE, "threads": t,
                              "fused_attention": os.environ.get("VLEM_FUSED_ATTENTION") == "1",
                              "vlem_ms": round(ours, 1), "reference": ref_name,
                              "reference_ms": round(ref, 1),
                              "ratio_reference_over_vlem": round(ref / ours, 2)}), flush=True)


if __name__ == "__main__":
    main()
