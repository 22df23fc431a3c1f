"""The paper's point-cloud fusion step in numpy + scipy (cKDTree): the reference that
`cargo bench -p vlem-maps --bench fusion` is compared with (see BENCHMARKS.md).

Same workload as the Rust bench: a map of N points on the surfaces frame 0 sees (jittered by up to
3 mm) with random unit 512-d embeddings; frame 1 with 300 segments (32x32-pixel blocks) of random
unit embeddings; map points in view take their nearest new point within 2 cm, are fused with
w = 0.5 and renormalised, unmatched new points are appended. No downsampling.

    pip install numpy scipy pillow
    python3 bench/fusion_numpy.py [N ...]
"""
import json
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial import cKDTree

DIM = 512
DATA = Path(__file__).resolve().parent.parent / "data" / "living-room"


def load_poses(path):
    rows = [l.split() for l in path.read_text().splitlines() if l.strip()]
    return [np.array(rows[i + 1:i + 5], dtype=np.float64) for i in range(0, len(rows), 5)]


def back_project(depth_png, k, pose):
    d = np.asarray(Image.open(depth_png), dtype=np.float32) / 1000.0
    h, w = d.shape
    v, u = np.mgrid[0:h, 0:w]
    valid = d > 0
    z = d[valid]
    pts = np.stack([(u[valid] - k["cx"]) * z / k["fx"], (v[valid] - k["cy"]) * z / k["fy"], z], 1)
    world = pts @ pose[:3, :3].T.astype(np.float32) + pose[:3, 3].astype(np.float32)
    return world.astype(np.float32), (v[valid] * w + u[valid])


def unit_rows(rng, n):
    e = rng.uniform(-1, 1, size=(n, DIM)).astype(np.float32)
    return e / np.linalg.norm(e, axis=1, keepdims=True)


def fuse(map_pos, map_emb, new_pos, new_emb, pose, k, w=0.5, radius=0.02):
    inv = np.linalg.inv(pose)
    cam = map_pos @ inv[:3, :3].T.astype(np.float32) + inv[:3, 3].astype(np.float32)
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = k["fx"] * cam[:, 0] / z + k["cx"]
        v = k["fy"] * cam[:, 1] / z + k["cy"]
    in_view = (z > 0) & (u >= -0.5) & (v >= -0.5) & (u < k["w"] - 0.5) & (v < k["h"] - 0.5)
    idx_view = np.nonzero(in_view)[0]
    tree = cKDTree(new_pos)
    dist, nn = tree.query(map_pos[idx_view], k=1, distance_upper_bound=radius, workers=-1)
    ok = np.isfinite(dist)
    q, p = idx_view[ok], nn[ok]
    fused = (1 - w) * new_emb[p] + w * map_emb[q]
    map_emb[q] = fused / np.linalg.norm(fused, axis=1, keepdims=True)
    chosen = np.zeros(len(new_pos), bool)
    chosen[p] = True
    map_pos = np.concatenate([map_pos, new_pos[~chosen]])
    map_emb = np.concatenate([map_emb, new_emb[~chosen]])
    return map_pos, map_emb, len(q), int((~chosen).sum())


def main():
    sizes = [int(a) for a in sys.argv[1:]] or [100_000, 1_000_000]
    intr = json.loads((DATA / "intrinsics.json").read_text())
    m = intr["intrinsic_matrix"]
    k = dict(fx=m[0], fy=m[4], cx=m[6], cy=m[7], w=intr["width"], h=intr["height"])
    poses = load_poses(DATA / "trajectory.log")
    rng = np.random.default_rng(7)
    surface, _ = back_project(DATA / "depth" / "00000.png", k, poses[0])
    new_pos, pixels = back_project(DATA / "depth" / "00001.png", k, poses[1])
    seg = (pixels % k["w"]) // 32 + (pixels // k["w"]) // 32 * ((k["w"] + 31) // 32)
    table = unit_rows(rng, int(seg.max()) + 1)
    print("| map points | median ms | min ms | fused | inserted |")
    print("|---:|---:|---:|---:|---:|")
    for n in sizes:
        pos = surface[rng.integers(0, len(surface), n)] + rng.uniform(-0.003, 0.003, (n, 3)).astype(np.float32)
        emb = unit_rows(rng, n)
        times = []
        for _ in range(3):
            p, e = pos.copy(), emb.copy()
            t = time.perf_counter()
            new_emb = table[seg]  # the dense per-point embeddings of the frame
            _, _, fused, inserted = fuse(p, e, new_pos, new_emb, poses[1], k)
            times.append((time.perf_counter() - t) * 1e3)
        times.sort()
        print(f"| {n} | {times[1]:.0f} | {times[0]:.0f} | {fused} | {inserted} |")


if __name__ == "__main__":
    main()
