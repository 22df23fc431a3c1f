#!/usr/bin/env python3
"""Images per second of an ONNX image tower on python onnxruntime: the reference for the Rust
`onnx` encoder's benchmark (vlem-backends/examples/onnx_bench.rs), same model, same settings.

For 1 and 2 intra-op threads and batches of 1 and 16 crops (224 x 224, random values), it
warms up once, then times `--runs` model calls; every measurement is taken twice and both are
printed, with the better one (the machine is shared, so the better one is the less disturbed).

    python3 bench/onnx/export_clip_b16.py                 # writes /tmp/vlem-onnx-bench/
    python3 bench/onnx/ort_python_bench.py [MODEL] [--runs N] [--threads 1,2]
"""

import argparse
import time

import numpy as np
import onnxruntime as ort


def measure(session: ort.InferenceSession, batch: int, runs: int) -> float:
    """Images per second over `runs` calls after one warm-up call."""
    name = session.get_inputs()[0].name
    size = session.get_inputs()[0].shape[2]
    x = np.random.default_rng(0).standard_normal((batch, 3, size, size), dtype=np.float32)
    session.run(None, {name: x})
    start = time.perf_counter()
    for _ in range(runs):
        session.run(None, {name: x})
    return batch * runs / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("model", nargs="?", default="/tmp/vlem-onnx-bench/clip-b16-image.onnx")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--threads", default="1,2", help="intra-op thread counts, e.g. 1,2")
    args = parser.parse_args()
    print(f"onnxruntime {ort.__version__}, {args.model}")
    print("threads  batch  img/s (1st)  img/s (2nd)  best  ms/img (best)")
    for threads in [int(t) for t in args.threads.split(",")]:
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        session = ort.InferenceSession(args.model, options, providers=["CPUExecutionProvider"])
        for batch in (1, 16):
            runs = args.runs if batch > 1 else 4 * args.runs
            first, second = measure(session, batch, runs), measure(session, batch, runs)
            best = max(first, second)
            print(f"{threads:7}  {batch:5}  {first:11.2f}  {second:11.2f}  {best:5.2f}  {1000 / best:8.0f}")


if __name__ == "__main__":
    main()
