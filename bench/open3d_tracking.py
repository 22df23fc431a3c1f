#!/usr/bin/env python3
"""Open3D 0.19 tracking anchors on the shared icl-livingroom1 frames.

(a) frame-to-frame RGB-D odometry: o3d.t.pipelines.odometry.rgbd_odometry_multi_scale,
    Method.Hybrid, criteria [10, 5, 3] (Open3D orders the list COARSEST level first),
    depth_scale 1000, depth_max 3.0, default OdometryLossParams, init = identity.
    source = frame i-1, target = frame i (as Open3D's t_reconstruction_system/rgbd_odometry.py),
    so T_{i<-i-1} = result.transformation and pose_i = pose_{i-1} @ inv(T) (camera-to-world),
    chained from frame 0's pseudo-GT pose. --odometry-order cur-to-prev swaps source and target.
(b) frame-to-model: o3d.t.pipelines.slam.Model exactly as Open3D's
    examples/python/t_reconstruction_system/dense_slam.py (voxel 3/512 m, block resolution 16,
    40000 blocks, trunc_voxel_multiplier 8, depth_min 0.1, depth_max 3, odometry distance
    threshold 0.07, track_frame_to_model's default method PointToPlane and criteria [6, 3, 1]).

Image loading is timed separately (all frames are read into memory first). Trajectories are written
as TUM (timestamp = frame index, camera-to-world) and compared with the pseudo ground truth
(trajectory_open3d_estimate.log): RPE over consecutive frames (RMSE of translation [m/frame] and
rotation [deg/frame]) and ATE (RMSE of positions after a rigid Umeyama alignment, no scale).

Usage:  bench/.venv/bin/python bench/open3d_tracking.py [SEQUENCE_DIR] [--out out/bench]
        [--frames N] [--threads 2] [--only odometry|frame-to-model]
"""
import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SEQ = (REPO / ".." / "shared" / "data" / "icl-livingroom1").resolve()


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequence", nargs="?", default=str(DEFAULT_SEQ),
                   help="dir with color/, depth/, intrinsics.json, trajectory_open3d_estimate.log")
    p.add_argument("--out", default=str(REPO / "out" / "bench"), help="output directory")
    p.add_argument("--frames", type=int, default=150, help="number of frames to use (from frame 0)")
    p.add_argument("--threads", type=int, default=2,
                   help="OMP_NUM_THREADS for Open3D (set before import; ignored if already in the environment)")
    p.add_argument("--only", choices=["odometry", "frame-to-model"], default=None)
    p.add_argument("--repeats", type=int, default=1,
                   help="run each loop this many times and keep, per frame, the MINIMUM time (robust to "
                        "other jobs on the shared cores); metrics come from the first run")
    p.add_argument("--odometry-order", choices=["cur-to-prev", "prev-to-cur"], default="prev-to-cur",
                   help="prev-to-cur (default, as Open3D's t_reconstruction_system/rgbd_odometry.py and the "
                        "anchor): source=frame i-1, target=frame i, pose_i = pose_{i-1} @ inv(T); "
                        "cur-to-prev: source=frame i, target=frame i-1, pose_i = pose_{i-1} @ T")
    return p.parse_args()


ARGS = parse_args()
# Open3D's CPU kernels use OpenMP (utility::EstimateMaxThreads() = omp_get_max_threads()); the TBB
# hash map used by slam.Model follows the machine's cores. Must be set before `import open3d`.
os.environ.setdefault("OMP_NUM_THREADS", str(ARGS.threads))

import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402
import open3d.core as o3c  # noqa: E402

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

# ---------------------------------------------------------------- parameters (anchor table)
DEPTH_SCALE = 1000.0
DEPTH_MAX = 3.0
ODO_CRITERIA = [10, 5, 3]            # coarsest (1/4 res) .. finest (full res)
VOXEL_SIZE = 3.0 / 512.0
BLOCK_RESOLUTION = 16
BLOCK_COUNT = 40000
TRUNC_VOXEL_MULTIPLIER = 8.0
DEPTH_MIN = 0.1                      # dense_slam.py default_config.yml
ODOMETRY_DISTANCE_THR = 0.07


# ---------------------------------------------------------------- I/O
def load_intrinsic(path):
    with open(path) as f:
        j = json.load(f)
    K = np.array(j["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T  # column-major in file
    return K, int(j["width"]), int(j["height"])


def load_log(path):
    """Redwood .log: 'i j k' line then 4 rows of a 4x4 camera-to-world matrix."""
    poses = []
    with open(path) as f:
        lines = [l for l in f.read().splitlines() if l.strip()]
    for k in range(0, len(lines), 5):
        m = np.array([[float(x) for x in lines[k + r].split()] for r in range(1, 5)])
        poses.append(m)
    return poses


def rot_to_quat(R):
    """Rotation matrix -> (qx, qy, qz, qw), qw >= 0."""
    t = np.trace(R)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        qw = 0.25 * s
        qx = (R[2, 1] - R[1, 2]) / s
        qy = (R[0, 2] - R[2, 0]) / s
        qz = (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        qw = (R[2, 1] - R[1, 2]) / s
        qx = 0.25 * s
        qy = (R[0, 1] + R[1, 0]) / s
        qz = (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        qw = (R[0, 2] - R[2, 0]) / s
        qx = (R[0, 1] + R[1, 0]) / s
        qy = 0.25 * s
        qz = (R[1, 2] + R[2, 1]) / s
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        qw = (R[1, 0] - R[0, 1]) / s
        qx = (R[0, 2] + R[2, 0]) / s
        qy = (R[1, 2] + R[2, 1]) / s
        qz = 0.25 * s
    q = np.array([qx, qy, qz, qw])
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def write_tum(path, poses):
    with open(path, "w") as f:
        f.write("# timestamp(frame index) tx ty tz qx qy qz qw  (camera-to-world)\n")
        for i, T in enumerate(poses):
            q = rot_to_quat(T[:3, :3])
            t = T[:3, 3]
            f.write(f"{i} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")


# ---------------------------------------------------------------- metrics
def rot_angle_deg(R):
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def rpe(est, gt, delta=1):
    """Relative pose error over frame pairs (i, i+delta): E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)."""
    tr, rot = [], []
    for i in range(len(est) - delta):
        j = i + delta
        dq = np.linalg.inv(gt[i]) @ gt[j]
        dp = np.linalg.inv(est[i]) @ est[j]
        E = np.linalg.inv(dq) @ dp
        tr.append(np.linalg.norm(E[:3, 3]))
        rot.append(rot_angle_deg(E[:3, :3]))
    tr, rot = np.array(tr), np.array(rot)
    return {
        "pairs": int(len(tr)),
        "trans_rmse_m": float(np.sqrt(np.mean(tr ** 2))),
        "trans_mean_m": float(np.mean(tr)),
        "trans_median_m": float(np.median(tr)),
        "trans_max_m": float(np.max(tr)),
        "rot_rmse_deg": float(np.sqrt(np.mean(rot ** 2))),
        "rot_mean_deg": float(np.mean(rot)),
        "rot_max_deg": float(np.max(rot)),
    }


def umeyama_rigid(src, dst):
    """R, t minimising sum ||R src_k + t - dst_k||^2 (no scale). src, dst: (N, 3)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    S = (dst - mu_d).T @ (src - mu_s) / len(src)
    U, _, Vt = np.linalg.svd(S)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    t = mu_d - R @ mu_s
    return R, t


def ate(est, gt):
    P = np.array([T[:3, 3] for T in est])
    Q = np.array([T[:3, 3] for T in gt])
    R, t = umeyama_rigid(P, Q)
    err = np.linalg.norm((P @ R.T + t) - Q, axis=1)
    err_raw = np.linalg.norm(P - Q, axis=1)
    return {
        "ate_rmse_m": float(np.sqrt(np.mean(err ** 2))),
        "ate_mean_m": float(np.mean(err)),
        "ate_max_m": float(np.max(err)),
        "unaligned_rmse_m": float(np.sqrt(np.mean(err_raw ** 2))),
        "final_drift_m": float(err_raw[-1]),
    }


def cpu_snapshot():
    """(system busy CPU seconds from /proc/stat, this process's CPU seconds, wall time)."""
    busy = float("nan")
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        busy = (sum(v[:8]) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")  # minus idle, iowait
    except (OSError, ValueError):
        pass
    t = os.times()
    return busy, t.user + t.system, time.perf_counter()


def foreign_load(a, b):
    """Average number of cores used by OTHER processes between two snapshots (0 = machine to ourselves)."""
    return max(0.0, ((b[0] - a[0]) - (b[1] - a[1])) / max(1e-9, b[2] - a[2]))


def timing_stats(ms):
    ms = np.asarray(ms, dtype=np.float64)
    return {"n": int(len(ms)), "mean_ms": float(ms.mean()), "median_ms": float(np.median(ms)),
            "min_ms": float(ms.min()), "max_ms": float(ms.max()), "total_s": float(ms.sum() / 1e3)}


# ---------------------------------------------------------------- runs
def run_odometry(depths, colors, K, T0):
    Kt = o3c.Tensor(K)
    crit = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n) for n in ODO_CRITERIA]
    method = o3d.t.pipelines.odometry.Method.Hybrid
    params = o3d.t.pipelines.odometry.OdometryLossParams()  # defaults: 0.07 / 0.05 / 0.1
    init = o3c.Tensor(np.eye(4))
    poses = [T0.copy()]
    ms, cpu, fitness, rmse = [], [], [], []
    prev = o3d.t.geometry.RGBDImage(colors[0], depths[0])
    # warm-up call (first call pays one-off allocation / thread-pool start), not timed
    o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(prev, prev, Kt, init, DEPTH_SCALE, DEPTH_MAX,
                                                       crit, method, params)
    for i in range(1, len(depths)):
        c0 = time.process_time()
        t0 = time.perf_counter()
        cur = o3d.t.geometry.RGBDImage(colors[i], depths[i])
        if ARGS.odometry_order == "cur-to-prev":
            res = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                cur, prev, Kt, init, DEPTH_SCALE, DEPTH_MAX, crit, method, params)
            T = res.transformation.numpy()
        else:
            res = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                prev, cur, Kt, init, DEPTH_SCALE, DEPTH_MAX, crit, method, params)
            T = np.linalg.inv(res.transformation.numpy())
        ms.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
        poses.append(poses[-1] @ T)
        fitness.append(float(res.fitness))
        rmse.append(float(res.inlier_rmse))
        prev = cur
    return poses, ms, fitness, rmse, cpu


def run_frame_to_model(depths, colors, K, T0):
    device = o3c.Device("CPU:0")
    Kt = o3c.Tensor(K)
    T_frame_to_model = o3c.Tensor(T0)
    model = o3d.t.pipelines.slam.Model(VOXEL_SIZE, BLOCK_RESOLUTION, BLOCK_COUNT, T_frame_to_model, device)
    h, w = depths[0].rows, depths[0].columns
    input_frame = o3d.t.pipelines.slam.Frame(h, w, Kt, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(h, w, Kt, device)
    poses, ms, ms_track, ms_integrate, ms_raycast, fitness, rmse, cpu = [], [], [], [], [], [], [], []
    for i in range(len(depths)):
        c0 = time.process_time()
        t0 = time.perf_counter()
        input_frame.set_data_from_image("depth", depths[i])
        input_frame.set_data_from_image("color", colors[i])
        if i > 0:
            result = model.track_frame_to_model(input_frame, raycast_frame, DEPTH_SCALE, DEPTH_MAX,
                                                ODOMETRY_DISTANCE_THR)
            T_frame_to_model = T_frame_to_model @ result.transformation
            fitness.append(float(result.fitness))
            rmse.append(float(result.inlier_rmse))
        t1 = time.perf_counter()
        poses.append(T_frame_to_model.cpu().numpy())
        model.update_frame_pose(i, T_frame_to_model)
        model.integrate(input_frame, DEPTH_SCALE, DEPTH_MAX, TRUNC_VOXEL_MULTIPLIER)
        t2 = time.perf_counter()
        model.synthesize_model_frame(raycast_frame, DEPTH_SCALE, DEPTH_MIN, DEPTH_MAX,
                                     TRUNC_VOXEL_MULTIPLIER, False)
        t3 = time.perf_counter()
        ms.append((t3 - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
        if i > 0:
            ms_track.append((t1 - t0) * 1e3)
        ms_integrate.append((t2 - t1) * 1e3)
        ms_raycast.append((t3 - t2) * 1e3)
    n_blocks = int(model.get_hashmap().size())
    return poses, ms, ms_track, ms_integrate, ms_raycast, fitness, rmse, n_blocks, cpu


def main():
    load_before = os.getloadavg()
    if load_before[0] > 0.7:
        print(f"WARNING: load average {load_before[0]:.2f} before start: other jobs share the cores, "
              f"timings will be inflated", file=sys.stderr)
    seq = Path(ARGS.sequence)
    out = Path(ARGS.out)
    out.mkdir(parents=True, exist_ok=True)
    K, W, H = load_intrinsic(seq / "intrinsics.json")
    gt = load_log(seq / "trajectory_open3d_estimate.log")[: ARGS.frames]
    n = min(ARGS.frames, len(gt))
    gt = gt[:n]

    t0 = time.perf_counter()
    depths, colors = [], []
    for i in range(n):
        depths.append(o3d.t.io.read_image(str(seq / "depth" / f"{i:05d}.png")))
        colors.append(o3d.t.io.read_image(str(seq / "color" / f"{i:05d}.jpg")))
    load_s = time.perf_counter() - t0
    assert depths[0].dtype == o3c.uint16 and colors[0].dtype == o3c.uint8, (depths[0].dtype, colors[0].dtype)
    assert (depths[0].columns, depths[0].rows) == (W, H)

    report = {
        "open3d_version": o3d.__version__,
        "numpy_version": np.__version__,
        "python": platform.python_version(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "threads": {"OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS")},
        "sequence": str(seq),
        "frames": n,
        "loading": {"total_s": load_s, "ms_per_frame": load_s * 1e3 / n,
                    "what": "o3d.t.io.read_image of depth PNG + color JPG, all frames up front"},
        "ground_truth": "trajectory_open3d_estimate.log (pseudo-GT, camera-to-world)",
    }
    rows = []

    if ARGS.only in (None, "odometry"):
        snap = cpu_snapshot()
        poses, ms, fit, rm, cpu = run_odometry(depths, colors, K, gt[0])
        ms_runs, cpu_runs = [ms], [cpu]
        for _ in range(ARGS.repeats - 1):
            rr = run_odometry(depths, colors, K, gt[0])
            ms_runs.append(rr[1])
            cpu_runs.append(rr[4])
        ms = list(np.min(np.array(ms_runs), axis=0))
        cpu = list(np.min(np.array(cpu_runs), axis=0))
        odo_foreign = foreign_load(snap, cpu_snapshot())
        write_tum(out / "open3d-odometry.tum", poses)
        r = {
            "order": ARGS.odometry_order,
            "call": "o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(source, target, "
                    "K, init=I, depth_scale=1000, depth_max=3.0, criteria=[10,5,3] (coarse->fine), "
                    "Method.Hybrid, OdometryLossParams())",
            "timing_per_frame": timing_stats(ms),
            "cpu_time_per_frame": timing_stats(cpu),
            "rpe": rpe(poses, gt), "ate": ate(poses, gt),
            "fitness_mean": float(np.mean(fit)), "fitness_min": float(np.min(fit)),
            "inlier_rmse_mean": float(np.mean(rm)),
            "foreign_cores_busy": odo_foreign,
            "per_frame": {"ms": ms, "fitness": fit, "inlier_rmse": rm},
            "trajectory": str(out / "open3d-odometry.tum"),
            "anchor": {"ms_per_frame": 84, "rpe_trans_m": 0.0033, "ate_m": 0.045},
        }
        report["odometry"] = r
        rows.append(("frame-to-frame (hybrid)", r))

    if ARGS.only in (None, "frame-to-model"):
        snap = cpu_snapshot()
        poses, ms, mtr, mint, mray, fit, rm, nb, cpu = run_frame_to_model(depths, colors, K, gt[0])
        runs = [(ms, mtr, mint, mray, cpu)]
        for _ in range(ARGS.repeats - 1):
            rr = run_frame_to_model(depths, colors, K, gt[0])
            runs.append(rr[1:5] + (rr[8],))
        ms, mtr, mint, mray, cpu = (list(np.min(np.array([r[k] for r in runs]), axis=0)) for k in range(5))
        f2m_foreign = foreign_load(snap, cpu_snapshot())
        write_tum(out / "open3d-frame-to-model.tum", poses)
        r = {
            "call": "o3d.t.pipelines.slam.Model(3/512, 16, 40000, T0, CPU:0); per frame: "
                    "track_frame_to_model(input, raycast, 1000, 3.0, 0.07) [defaults: PointToPlane, criteria "
                    "[6,3,1]] -> update_frame_pose -> integrate(1000, 3.0, 8) -> "
                    "synthesize_model_frame(1000, 0.1, 3.0, 8, enable_color=False)",
            "timing_per_frame": timing_stats(ms),
            "cpu_time_per_frame": timing_stats(cpu),
            "timing_track": timing_stats(mtr),
            "timing_integrate": timing_stats(mint),
            "timing_raycast": timing_stats(mray),
            "rpe": rpe(poses, gt), "ate": ate(poses, gt),
            "fitness_mean": float(np.mean(fit)), "fitness_min": float(np.min(fit)),
            "inlier_rmse_mean": float(np.mean(rm)),
            "allocated_blocks": nb,
            "foreign_cores_busy": f2m_foreign,
            "per_frame": {"ms": ms, "fitness": fit, "inlier_rmse": rm},
            "trajectory": str(out / "open3d-frame-to-model.tum"),
            "anchor": {"ms_per_frame": 231, "rpe_trans_m": 0.0023, "ate_m": 0.008},
        }
        report["frame_to_model"] = r
        rows.append(("frame-to-model (slam.Model)", r))

    report["repeats"] = ARGS.repeats
    report["timing_note"] = ("per-frame wall time, image loading excluded; with repeats > 1 each frame's time "
                             "is the minimum over the repeats")
    report["loadavg_before"] = load_before
    report["loadavg_after"] = os.getloadavg()
    json_path = out / ("open3d-tracking.json" if ARGS.only is None else f"open3d-tracking-{ARGS.only}.json")
    with open(json_path, "w") as f:
        json.dump(report, f, indent=1)

    print(f"Open3D {o3d.__version__}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, "
          f"{os.cpu_count()} CPUs, {n} frames of {seq.name}")
    print(f"loading: {load_s:.2f} s total, {load_s * 1e3 / n:.1f} ms/frame (excluded from timings)")
    hdr = (f"{'method':30s} {'mean ms':>8s} {'med ms':>8s} {'cpu ms':>7s} {'RPE t mm':>9s} {'RPE r deg':>9s} "
           f"{'ATE cm':>7s} {'other':>6s}   anchor")
    print(hdr)
    print("-" * len(hdr) + "-" * 30)
    for name, r in rows:
        t, p, a, an = r["timing_per_frame"], r["rpe"], r["ate"], r["anchor"]
        print(f"{name:30s} {t['mean_ms']:8.1f} {t['median_ms']:8.1f} {r['cpu_time_per_frame']['mean_ms']:7.1f} "
              f"{p['trans_rmse_m'] * 1e3:9.2f} "
              f"{p['rot_rmse_deg']:9.3f} {a['ate_rmse_m'] * 1e2:7.2f} {r['foreign_cores_busy']:6.2f}   "
              f"{an['ms_per_frame']} ms, RPE {an['rpe_trans_m'] * 1e3:.1f} mm, ATE {an['ate_m'] * 1e2:.1f} cm")
    if "frame_to_model" in report:
        r = report["frame_to_model"]
        print(f"frame-to-model breakdown (mean ms): track {r['timing_track']['mean_ms']:.1f}, "
              f"integrate {r['timing_integrate']['mean_ms']:.1f}, raycast {r['timing_raycast']['mean_ms']:.1f}; "
              f"{r['allocated_blocks']} blocks")
    print(f"load average before/after (1 min): {load_before[0]:.2f} / {report['loadavg_after'][0]:.2f}; "
          f"'other' = cores kept busy by other processes during the timed loop (0 = clean timing); "
          f"'cpu ms' = process CPU time per frame (all threads; with --threads 1 it is robust to other jobs)")
    print(f"wrote {json_path}")


if __name__ == "__main__":
    main()
