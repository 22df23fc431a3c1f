#!/usr/bin/env python3
"""numpy re-implementation of ONE Gauss-Newton step of Open3D 0.19's tensor RGB-D odometry
(Hybrid and PointToPlane), checked against Open3D's own kernels
(o3d.t.pipelines.odometry.compute_odometry_result_hybrid / _point_to_plane) and image ops.

It documents, executably, what vlem's Rust odometry has to do to match Open3D:
  * preprocessing: depth/scale, <=0 or >=depth_max -> NaN; gray = round(.299R+.587G+.114B) as u8, /255
  * Sobel 3x3 (unnormalised, dx = right-left, dy = down-up, replicate border; NaN spreads), x 0.125
  * nearest-pixel projective association (roundf), target-side gradients/normals
  * "Huber": H = sum J^T J (UNWEIGHTED); b = sum J^T psi(r) with Open3D's psi(r) = r for |r| < delta,
    else delta * Sign((int)r) -- Sign takes an int, so for |r| < 1 (always, here) psi = 0 beyond delta
  * delta = solve(H, -b) (float64); pose vector (a, b, g, tx, ty, tz) -> R = Rz(g) Ry(b) Rx(a)
  * T <- dT @ T

Usage: bench/.venv/bin/python bench/open3d_odometry_reference.py [SEQUENCE_DIR] [--src 10 --tgt 11]
Prints the Open3D and numpy increments and their difference; exits non-zero if they disagree.
"""
import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402
import open3d.core as o3c  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
ap = argparse.ArgumentParser()
ap.add_argument("sequence", nargs="?", default=str((REPO / ".." / "shared" / "data" / "icl-livingroom1").resolve()))
ap.add_argument("--src", type=int, default=10)
ap.add_argument("--tgt", type=int, default=11)
args = ap.parse_args()
seq = Path(args.sequence)

K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
DEPTH_SCALE, DEPTH_MAX = 1000.0, 3.0
TRUNC, HUB_D, HUB_I = 0.07, 0.05, 0.1
SQRT_LAMBDA = np.float32(0.707)
SOBEL_SCALE = np.float32(0.125)


def load(i):
    d = o3d.t.io.read_image(str(seq / "depth" / f"{i:05d}.png"))
    c = o3d.t.io.read_image(str(seq / "color" / f"{i:05d}.jpg"))
    return d, c


# ------------------------------------------------------------------ numpy preprocessing
def np_depth(d_u16):
    d = d_u16.astype(np.float32) / np.float32(DEPTH_SCALE)
    d[(d <= 0) | (d >= DEPTH_MAX)] = np.nan
    return d


def np_gray(rgb_u8):
    c = rgb_u8.astype(np.float64)
    g = np.floor(0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2] + 0.5)  # IPP: ~99.95% exact
    return (g / 255.0).astype(np.float32)


def np_sobel(img):
    P = np.pad(img, 1, mode="edge")
    H, W = img.shape

    def s(oy, ox):
        return P[1 + oy:1 + oy + H, 1 + ox:1 + ox + W]

    dx = (s(-1, 1) + 2 * s(0, 1) + s(1, 1)) - (s(-1, -1) + 2 * s(0, -1) + s(1, -1))
    dy = (s(1, -1) + 2 * s(1, 0) + s(1, 1)) - (s(-1, -1) + 2 * s(-1, 0) + s(-1, 1))
    return dx.astype(np.float32), dy.astype(np.float32)


def vertex_map(d):
    H, W = d.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return np.stack([(u - cx) * d / fx, (v - cy) * d / fy, d], -1).astype(np.float32)


def roundf(x):  # C roundf: half away from zero
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def huber_deriv_open3d(r, delta):
    # abs(r) < delta ? r : delta * Sign(int(r))  -- Sign(int) in GeometryMacros.h
    return np.where(np.abs(r) < delta, r, delta * np.sign(np.trunc(r)))


def huber_deriv_textbook(r, delta):
    return np.where(np.abs(r) < delta, r, delta * np.sign(r))


def associate(vs, T, Dt):
    H, W = Dt.shape
    p = vs.reshape(-1, 3)
    ok = ~np.isnan(p[:, 0])
    q = (p @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)).astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = roundf(fx * q[:, 0] / q[:, 2] + cx)
        v = roundf(fy * q[:, 1] / q[:, 2] + cy)
    ok &= (q[:, 2] >= 0) & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
    ui = np.where(ok, u, 0).astype(np.int64)
    vi = np.where(ok, v, 0).astype(np.int64)
    return q, ui, vi, ok


def hybrid_step(Ds, Dt, Is, It, T, psi):
    dDx, dDy = np_sobel(Dt)
    dIx, dIy = np_sobel(It)
    vs = vertex_map(Ds)
    q, ui, vi, ok = associate(vs, T, Dt)
    dt = Dt[vi, ui]
    diffD = dt - q[:, 2]
    with np.errstate(invalid="ignore"):
        ok &= ~np.isnan(dt) & ~(np.abs(diffD) > TRUNC)
    gDx, gDy = SOBEL_SCALE * dDx[vi, ui], SOBEL_SCALE * dDy[vi, ui]
    ok &= ~np.isnan(gDx) & ~np.isnan(gDy)
    q, diffD, gDx, gDy, ui, vi = q[ok], diffD[ok], gDx[ok], gDy[ok], ui[ok], vi[ok]
    diffI = It[vi, ui] - Is.reshape(-1)[ok]
    gIx, gIy = SOBEL_SCALE * dIx[vi, ui], SOBEL_SCALE * dIy[vi, ui]
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    invz = 1 / z
    c0, c1 = gIx * fx * invz, gIy * fy * invz
    c2 = -(c0 * x + c1 * y) * invz
    d0, d1 = gDx * fx * invz, gDy * fy * invz
    d2 = -(d0 * x + d1 * y) * invz
    JI = SQRT_LAMBDA * np.stack([-z * c1 + y * c2, z * c0 - x * c2, -y * c0 + x * c1, c0, c1, c2], 1)
    JD = SQRT_LAMBDA * np.stack([(-z * d1 + y * d2) - y, (z * d0 - x * d2) + x, -y * d0 + x * d1,
                                 d0, d1, d2 - 1.0], 1)
    rI, rD = SQRT_LAMBDA * diffI, SQRT_LAMBDA * diffD
    JI, JD = JI.astype(np.float64), JD.astype(np.float64)
    Hm = JI.T @ JI + JD.T @ JD
    b = JI.T @ psi(rI.astype(np.float64), HUB_I) + JD.T @ psi(rD.astype(np.float64), HUB_D)
    return np.linalg.solve(Hm, -b), int(ok.sum())


def np_bilateral(d, value_sigma=5.0, dist_sigma=10.0):
    """IPP FilterBilateral as Open3D calls it: CIRCULAR window radius kernel//2 = 2 (13 taps),
    w = exp(-(dv^2)/(2 vs^2) - (dx^2+dy^2)/(2 ds^2)), replicate border, any NaN in the window -> NaN."""
    H, W = d.shape
    P = np.pad(d.astype(np.float64), 2, mode="edge")
    num, den = np.zeros((H, W)), np.zeros((H, W))
    for oy in range(-2, 3):
        for ox in range(-2, 3):
            if ox * ox + oy * oy > 4:
                continue
            v = P[2 + oy:2 + oy + H, 2 + ox:2 + ox + W]
            w = np.exp(-(v - d) ** 2 / (2 * value_sigma ** 2) - (ox * ox + oy * oy) / (2 * dist_sigma ** 2))
            num += w * v
            den += w
    return (num / den).astype(np.float32)


def np_normals(V):
    """CreateNormalMap: n = normalize((V[y+1,x]-V) x (V[y,x+1]-V)); last row/col and NaN neighbours -> NaN."""
    N = np.full_like(V, np.nan)
    a = V[1:, :-1] - V[:-1, :-1]
    b = V[:-1, 1:] - V[:-1, :-1]
    n = np.cross(a, b)
    N[:-1, :-1] = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-5)
    return N


def p2plane_step(Ds, Dt, Nt, T, psi):
    vs = vertex_map(Ds)
    Vt = vertex_map(Dt)
    q, ui, vi, ok = associate(vs, T, Dt)
    vt, nt = Vt[vi, ui], Nt[vi, ui]
    ok &= ~np.isnan(vt[:, 0]) & ~np.isnan(nt[:, 0])
    with np.errstate(invalid="ignore"):
        r = np.sum((q - vt) * nt, 1)
        ok &= ~(np.abs(r) > TRUNC)
    q, nt, r = q[ok], nt[ok], r[ok]
    J = np.concatenate([np.cross(q, nt), nt], 1).astype(np.float64)
    return np.linalg.solve(J.T @ J, -(J.T @ psi(r.astype(np.float64), HUB_D))), int(ok.sum())


def pose_to_T(xi):
    a, b_, g = xi[:3]
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b_), 0, np.sin(b_)], [0, 1, 0], [-np.sin(b_), 0, np.cos(b_)]])
    Rz = np.array([[np.cos(g), -np.sin(g), 0], [np.sin(g), np.cos(g), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = xi[3:]
    return T


def main():
    (ds, cs), (dt, ct) = load(args.src), load(args.tgt)
    # Open3D preprocessing, as in RGBDOdometryMultiScaleHybrid (finest level only)
    Ds_o = ds.clip_transform(DEPTH_SCALE, 0.0, DEPTH_MAX, float("nan"))
    Dt_o = dt.clip_transform(DEPTH_SCALE, 0.0, DEPTH_MAX, float("nan"))
    Is_o = cs.rgb_to_gray().to(o3c.float32)
    It_o = ct.rgb_to_gray().to(o3c.float32)
    dDx_o, dDy_o = Dt_o.filter_sobel()
    dIx_o, dIy_o = It_o.filter_sobel()
    Kt = o3c.Tensor(K)
    vs_o = Ds_o.create_vertex_map(Kt, float("nan"))

    # check numpy preprocessing against Open3D's
    Ds, Dt = np_depth(ds.as_tensor().numpy()[..., 0]), np_depth(dt.as_tensor().numpy()[..., 0])
    Is, It = np_gray(cs.as_tensor().numpy()), np_gray(ct.as_tensor().numpy())
    eq = lambda a, b: np.nanmax(np.abs(a - b)) if np.isnan(a).tolist() == np.isnan(b).tolist() else float("inf")
    print("depth preprocess max|diff|:", eq(Ds, Ds_o.as_tensor().numpy()[..., 0]))
    gi = Is_o.as_tensor().numpy()[..., 0]
    print("gray (u8 round(.299R+.587G+.114B), /255): fraction within 1e-6:",
          float(np.mean(np.abs(Is - gi) < 1e-6)), " max|diff| (in 1/255 units):", float(np.abs(Is - gi).max() * 255))
    print("depth sobel dx max|diff| (NaN pattern must match):", eq(np_sobel(Dt)[0], dDx_o.as_tensor().numpy()[..., 0]))
    print("intensity sobel dy max|diff|:", eq(np_sobel(It)[1], dIy_o.as_tensor().numpy()[..., 0]))

    T0 = np.eye(4)
    for it in range(3):
        res = o3d.t.pipelines.odometry.compute_odometry_result_hybrid(
            Ds_o.as_tensor(), Dt_o.as_tensor(), Is_o.as_tensor(), It_o.as_tensor(),
            dDx_o.as_tensor(), dDy_o.as_tensor(), dIx_o.as_tensor(), dIy_o.as_tensor(),
            vs_o.as_tensor(), Kt, o3c.Tensor(T0), TRUNC, HUB_D, HUB_I)
        dT_o3d = res.transformation.numpy()
        # use Open3D's own gray for the numpy step, to isolate the solver from the 0.05% gray rounding
        Is_x, It_x = Is_o.as_tensor().numpy()[..., 0], It_o.as_tensor().numpy()[..., 0]
        xi_a, n_a = hybrid_step(Ds, Dt, Is_x, It_x, T0, huber_deriv_open3d)
        xi_b, _ = hybrid_step(Ds, Dt, Is_x, It_x, T0, huber_deriv_textbook)
        dA, dB = pose_to_T(xi_a), pose_to_T(xi_b)
        eA, eB = np.abs(dA - dT_o3d).max(), np.abs(dB - dT_o3d).max()
        print(f"iter {it}: inliers numpy {n_a}, open3d fitness*N {res.fitness * Ds.size:.0f}; "
              f"|dT_numpy(Open3D psi) - dT_open3d| = {eA:.2e}, "
              f"|dT_numpy(textbook Huber) - dT_open3d| = {eB:.2e}, |dT - I| = {np.abs(dT_o3d - np.eye(4)).max():.2e}")
        ok = eA < 0.02 * np.abs(dT_o3d - np.eye(4)).max() + 1e-7
        if not ok:
            print("MISMATCH", file=sys.stderr)
            sys.exit(1)
        T0 = dT_o3d @ T0
    print("hybrid step reproduced (Open3D's int-Sign Huber derivative)")

    # ---------------- point-to-plane (what slam.Model.track_frame_to_model uses by default)
    Bt_o = Dt_o.filter_bilateral(5, 5.0, 10.0)
    Bt = np_bilateral(Dt)
    print("bilateral(5, 5, 10) max|diff| (NaN pattern must match):", eq(Bt, Bt_o.as_tensor().numpy()[..., 0]))
    Vt_o = Dt_o.create_vertex_map(Kt, float("nan"))
    Nt_o = Bt_o.create_vertex_map(Kt, float("nan")).create_normal_map(float("nan"))
    Nt = np_normals(vertex_map(Bt))
    print("normal map max|diff|:", eq(Nt, Nt_o.as_tensor().numpy()))
    T0 = np.eye(4)
    for it in range(3):
        res = o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane(
            vs_o.as_tensor(), Vt_o.as_tensor(), Nt_o.as_tensor(), Kt, o3c.Tensor(T0), TRUNC, HUB_D)
        dT_o3d = res.transformation.numpy()
        xi, n = p2plane_step(Ds, Dt, Nt_o.as_tensor().numpy(), T0, huber_deriv_open3d)
        e = np.abs(pose_to_T(xi) - dT_o3d).max()
        print(f"p2plane iter {it}: inliers numpy {n}, open3d {res.fitness * Ds.size:.0f}; "
              f"|dT_numpy - dT_open3d| = {e:.2e}, |dT - I| = {np.abs(dT_o3d - np.eye(4)).max():.2e}")
        if not e < 0.02 * np.abs(dT_o3d - np.eye(4)).max() + 1e-7:
            print("MISMATCH", file=sys.stderr)
            sys.exit(1)
        T0 = dT_o3d @ T0
    print("point-to-plane step reproduced")


if __name__ == "__main__":
    main()
