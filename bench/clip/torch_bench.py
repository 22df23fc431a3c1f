#!/usr/bin/env python3
"""Images per second of a CLIP image tower (get_image_features) in PyTorch `transformers`, CPU.

The reference for vlem-backends/examples/clip_bench.rs: same model folder, same input size, same
batch sizes, float32, inference mode. One warm-up call, then REPEAT timed calls; prints the best
and the mean time per call and the images per second of the best.

    python3 bench/clip/torch_bench.py MODEL_DIR --threads 2 --batch 1 16 --repeat 5

`--cuda-graph` (on a GPU) also times each call captured once in a CUDA graph and replayed: the
GPU's own work without the host launching each kernel. Eager minus replay is what launching costs
a call, the question of whether vlem's models would gain from graphs (issue 38 part 4).
"""

import argparse
import time

import torch
from transformers import CLIPModel


def synchronize(device: str) -> None:
    """Waits for the GPU's queued work, so that a timer reads the work done, not the launch."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("model_dir")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--batch", type=int, nargs="*", default=[1, 16])
    p.add_argument("--text", type=int, nargs="*", default=[],
                   help="also time the text tower on this many 16-token texts (as clip_bench)")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--dtype", default="f32", choices=["f32", "f16", "bf16"],
                   help="the model's and the input's type (half: .half() / bfloat16, as vlem's)")
    p.add_argument("--cuda-graph", action="store_true",
                   help="also time replays of each call captured in a CUDA graph (GPU only)")
    args = p.parse_args()
    if args.cuda_graph and not args.device.startswith("cuda"):
        p.error("--cuda-graph needs --device cuda")
    torch.set_num_threads(args.threads)
    dtype = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}[args.dtype]
    # SDPA: PyTorch's fused attention, transformers' default where it is available.
    model = CLIPModel.from_pretrained(args.model_dir, dtype=dtype, attn_implementation="sdpa")
    model = model.eval().to(args.device)
    size = model.config.vision_config.image_size
    gen = torch.Generator().manual_seed(0)
    for batch in args.batch:
        x = torch.randn(batch, 3, size, size, generator=gen).to(args.device, dtype)
        times = timed(lambda: model.get_image_features(pixel_values=x), args)
        best = min(times)
        print(
            f"torch threads={args.threads} batch={batch}: best {best * 1e3:.1f} ms/call, "
            f"mean {sum(times) / len(times) * 1e3:.1f} ms/call, {batch / best:.2f} images/s"
        )
        if args.cuda_graph:
            graph = min(timed_graph(lambda: model.get_image_features(pixel_values=x), args))
            print(f"torch threads={args.threads} batch={batch}: graph replay best "
                  f"{graph * 1e3:.2f} ms/call (eager {best * 1e3:.2f})")
    time_text(model, args)


def timed(call, args):
    """The times of `args.repeat` calls of `call` after one warm-up, in inference mode."""
    times = []
    with torch.inference_mode():
        call()
        synchronize(args.device)
        for _ in range(args.repeat):
            t = time.perf_counter()
            call()
            synchronize(args.device)
            times.append(time.perf_counter() - t)
    return times


def timed_graph(call, args):
    """The times of `args.repeat` replays (as `timed` times calls) of `call` captured once in a
    CUDA graph, in inference mode: warmed up on a side stream first, as PyTorch's capture needs,
    the same inputs (static buffers) in every replay."""
    with torch.inference_mode():
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(3):
                call()
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            call()
    return timed(graph.replay, args)


def time_text(model, args):
    """get_text_features on N texts of 16 tokens, the ids of clip_bench's `--text`."""
    for n in args.text:
        ids = torch.tensor([[1000 + 37 * t + i for i in range(16)] for t in range(n)])
        ids = ids.to(args.device)
        times = timed(lambda: model.get_text_features(input_ids=ids), args)
        print(f"torch threads={args.threads} text={n}x16: best {min(times) * 1e3:.1f} ms/call")
        if args.cuda_graph:
            graph = min(timed_graph(lambda: model.get_text_features(input_ids=ids), args))
            print(f"torch threads={args.threads} text={n}x16: graph replay best "
                  f"{graph * 1e3:.2f} ms/call (eager {min(times) * 1e3:.2f})")


if __name__ == "__main__":
    main()
