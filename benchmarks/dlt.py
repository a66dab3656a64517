"""Benchmark: batched DLT + closed-form decomposition in mvcalib against NumPy and OpenCV peers.

What is measured
----------------
For rigs of C in {1, 16, 256, 4096, 65536} cameras seeing N in {8, 19, 100, 1000} points
(float64, 0.3 px Gaussian pixel noise), the time to go from 3-D/2-D correspondences to
calibrated cameras (alpha_u, alpha_v, u0, v0, skew, R, t). The cameras are
`mvcalib.synthetic.random_cameras` around the box-corner target; the points are the target's 19
dots for N = 19 and otherwise N random points in the target's bounding box (shared by all
cameras, as a calibration object is); pixels outside the image are masked out (every path
skips them).

- **mvcalib**: one `jax.jit`-compiled function, `mc.dlt` followed by `mc.Camera.from_projection`,
  for all cameras at once, whatever the library's kernels are at the time of the run.
- **calibrate()**: the public one-call API `mc.calibrate` called eagerly (validation, DLT,
  decomposition, reprojection report), at C = 4096, N = 19 (every cell in the full run).
- **numpy batched**: `np.linalg.svd` on the whole `(C, 2N, 12)` stack of normalised DLT
  systems and the decomposition vectorised over cameras (chunks of at most 2^20 / N cameras,
  to bound its memory).
- **numpy loop**: the same math per camera (`np.linalg.svd` of one 2N x 12 matrix at a time).
- **cv2 decompose**: the NumPy DLT per camera, then `cv2.decomposeProjectionMatrix` on its P.
- **mc.solve_pnp**: `mc.solve_pnp` with the *true* cameras' K (pose only: its closed form and
  Levenberg-Marquardt on the pose), the one-call API called eagerly, at the headline cell (C =
  4096, N = 19) of the quick run and every cell of the full run.
- **cv2 solvePnP**: `cv2.solvePnP` (iterative) per camera with the *true* K: pose only, a
  smaller problem than the others solve.
- **cv2 calibrateCamera**: per camera, with `CALIB_USE_INTRINSIC_GUESS` (OpenCV needs an
  initial K for non-planar points) from the *true* K, distortion fixed at zero, no skew;
  float32 points (what it accepts); an iterative reprojection-error minimisation.

The loops (numpy loop and the three OpenCV ones) are timed on the first cameras only when C is
large (64 with `--quick`, 4096 in the full run) and reported per camera; the table marks them.
Everything runs on this machine's CPU as installed: XLA and OpenBLAS may use both cores, the
loops use one.

Times are medians of per-call wall times, the paths interleaved in rounds (`_common.measure`),
per camera. "peer/mvcalib" is a peer's time over mvcalib's (above 1: mvcalib faster).
Accuracy: each path's cameras reproject the points; the table gives the median RMS
reprojection error (px) and the largest |RMS - RMS of numpy batched SVD| over the cameras
both computed. Compile: mvcalib's first call minus a warm call (trace + compile). Peak memory:
XLA's memory analysis of the compiled function (arguments + outputs + temporaries) for mvcalib,
`tracemalloc`'s peak during one call for the NumPy/OpenCV paths (NumPy buffers and Python
objects; not OpenCV's internal C++ allocations). "x bound": the time over the physical bound of
`bound.py` (this machine's measured FLOP/s and bandwidth against the textbook FLOP count);
"x min": over the bound of the minimal count.

`--quick`: the headline cell (4096, 19) only, five rounds of 0.1 s per path (every cell compiles
mvcalib anew, which cost a quick run ~11 s per cell; the full run has the grid). `--smoke`: one
tiny cell, for the test that the suite runs.

Results are printed and written to `benchmarks/results/dlt.json`.

Run from the repository root: `python benchmarks/dlt.py [--quick]`.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import cv2  # noqa: E402
import numpy as np  # noqa: E402

try:
    from . import bound
    from ._common import (
        first_and_warm,
        machine_info,
        measure,
        results_path,
        tracemalloc_peak_mb,
        write_results,
        xla_peak_mb,
    )
except ImportError:  # run as a script
    import bound
    from _common import (
        first_and_warm,
        machine_info,
        measure,
        results_path,
        tracemalloc_peak_mb,
        write_results,
        xla_peak_mb,
    )

import mvcalib as mc  # noqa: E402

N_CAMERAS = (1, 16, 256, 4096, 65536)
N_POINTS = (8, 19, 100, 1000)
QUICK_CELLS = ((4096, 19),)
SMOKE_CELLS = ((16, 19),)
HEADLINE = (4096, 19)
MAX_CAMERA_POINTS = 2**23  # cells with more camera-points are skipped (memory of the stacks)
LOOP_SUBSET = {"smoke": 8, "quick": 64, "full": 4096}
NOISE = 0.3  # pixels
IMAGE_SIZE = (1000, 1100)
SEED = 0
LOOPS = ("numpy loop", "cv2 decompose", "cv2 solvePnP", "cv2 calibrateCamera")
# other problems: no DLT bound for them
NOT_DLT = ("mc.solve_pnp", "cv2 solvePnP", "cv2 calibrateCamera")


# ---------------------------------------------------------------------------------- data
def make_cameras(C):
    """C random cameras around the box corner, and their K, R, t as NumPy arrays."""
    return mc.synthetic.random_cameras(jax.random.key(SEED), C, image_size=IMAGE_SIZE)


def make_problem(cameras, N, C):
    """The first C cameras observe N points: (world (N, 3), pixels (C, N, 2), mask (C, N))."""
    if N == 19:
        world = np.asarray(mc.targets.box_corner().points, np.float64)
    else:
        box = np.asarray(mc.targets.box_corner().points).max(0)
        world = np.random.default_rng(N).uniform(0.0, 1.0, (N, 3)) * box
    P = np.asarray(cameras.projection_matrix())[:C]
    x = np.einsum("cij,nj->cni", P, np.concatenate([world, np.ones((N, 1))], 1))
    depth = x[..., 2]
    true = x[..., :2] / depth[..., None]
    pixels = true + NOISE * np.random.default_rng(SEED + 1).standard_normal(true.shape)
    width, height = IMAGE_SIZE
    inside = (true[..., 0] >= 0) & (true[..., 0] <= width - 1)
    inside &= (true[..., 1] >= 0) & (true[..., 1] <= height - 1)
    return world, pixels, inside & (depth > 0)


# ---------------------------------------------------------------------------------- mvcalib
@jax.jit
def mvcalib_calibrate(world, pixels, mask):
    """Batched DLT and closed-form decomposition, one compiled function."""
    return mc.Camera.from_projection(mc.dlt(world, pixels, mask))


@jax.jit
def mvcalib_decompose(P):
    return mc.Camera.from_projection(P)


def camera_krt(cams):
    """(K, R, t) of an mvcalib Camera as NumPy arrays."""
    return np.asarray(cams.K), np.asarray(cams.R), np.asarray(cams.t)


# ---------------------------------------------------------------------------------- NumPy
def hartley(points):
    """Similarity `T` moving `points` (n, d) to centroid 0 and RMS distance sqrt(d)."""
    d = points.shape[1]
    centroid = points.mean(axis=0)
    rms = np.sqrt(np.mean(np.sum((points - centroid) ** 2, axis=1)))
    s = np.sqrt(d) / rms
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * centroid
    return T


def dlt_numpy(world, pixels):
    """Normalised DLT of one camera: (n, 3), (n, 2) -> P (3, 4), ||m3|| = 1, points in front."""
    n = len(world)
    T3, T2 = hartley(world), hartley(pixels)
    X = np.hstack([world, np.ones((n, 1))]) @ T3.T  # normalised homogeneous world points
    x = np.hstack([pixels, np.ones((n, 1))]) @ T2.T  # normalised homogeneous pixels
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = X
    A[0::2, 8:12] = -x[:, :1] * X
    A[1::2, 4:8] = X
    A[1::2, 8:12] = -x[:, 1:2] * X
    _, _, vt = np.linalg.svd(A, full_matrices=False)
    P = np.linalg.inv(T2) @ vt[-1].reshape(3, 4) @ T3
    P /= np.linalg.norm(P[2, :3])
    if np.sum(world @ P[2, :3] + P[2, 3]) < 0:
        P = -P
    return P


def decompose_numpy(P):
    """Closed-form `P = K [R | t]` with skew; `R` re-orthogonalised to the nearest rotation."""
    m1, m2, m3 = P[:, :3]
    m14, m24, m34 = P[:, 3]
    u0, v0 = m1 @ m3, m2 @ m3
    q2 = m2 - v0 * m3
    alpha_v = np.linalg.norm(q2)
    r2 = q2 / alpha_v
    q1 = m1 - u0 * m3
    skew = q1 @ r2
    q1 = q1 - skew * r2
    alpha_u = np.linalg.norm(q1)
    r1 = q1 / alpha_u
    tz = m34
    ty = (m24 - v0 * tz) / alpha_v
    tx = (m14 - u0 * tz - skew * ty) / alpha_u
    U, _, Vt = np.linalg.svd(np.stack([r1, r2, m3]))
    if np.linalg.det(U @ Vt) < 0:
        U[:, 2] = -U[:, 2]
    K = np.array([[alpha_u, skew, u0], [0.0, alpha_v, v0], [0.0, 0.0, 1.0]])
    return K, U @ Vt, np.array([tx, ty, tz])


def numpy_loop(world, pixels, mask):
    """Per-camera loop: (n, 3), (C, n, 2), (C, n) -> stacked K, R, t."""
    out = [decompose_numpy(dlt_numpy(world[m], p[m])) for p, m in zip(pixels, mask)]
    return tuple(np.array(v) for v in zip(*out))


def _hartley_batched(points, w):
    """Weighted Hartley normalisation of (C, n, d) points: normalised points, scale, centroid."""
    d = points.shape[-1]
    count = np.maximum(w.sum(1), 1.0)
    c = np.einsum("cn,cnd->cd", w, points) / count[:, None]
    centred = points - c[:, None]
    ms = np.einsum("cn,cn->c", w, np.sum(centred**2, -1)) / count
    s = np.sqrt(d / np.where(ms > 0, ms, 1.0))
    return centred * s[:, None, None], s, c


def _dlt_numpy_batched(world, pixels, mask):
    """Normalised DLT of C cameras at once: one `np.linalg.svd` of the (C, 2N, 12) stack."""
    C, n = mask.shape
    w = mask.astype(np.float64)
    Xn, s3, c3 = _hartley_batched(np.broadcast_to(world, (C, n, 3)), w)
    xn, s2, c2 = _hartley_batched(pixels, w)
    Xh = np.concatenate([Xn, np.ones((C, n, 1))], -1) * w[..., None]  # hidden rows are zero
    A = np.zeros((C, n, 2, 12))
    A[:, :, 0, 0:4] = Xh
    A[:, :, 0, 8:12] = -xn[..., :1] * Xh
    A[:, :, 1, 4:8] = Xh
    A[:, :, 1, 8:12] = -xn[..., 1:] * Xh
    _, _, vt = np.linalg.svd(A.reshape(C, 2 * n, 12), full_matrices=False)
    V = vt[:, -1].reshape(C, 3, 4)
    # De-normalise: P = T2^-1 V T3 with T = [s I, -s c; 0, 1].
    T3 = np.zeros((C, 4, 4))
    T3[:, :3, :3] = s3[:, None, None] * np.eye(3)
    T3[:, :3, 3] = -s3[:, None] * c3
    T3[:, 3, 3] = 1.0
    T2i = np.zeros((C, 3, 3))
    T2i[:, :2, :2] = np.eye(2) / s2[:, None, None]
    T2i[:, :2, 2] = c2
    T2i[:, 2, 2] = 1.0
    P = T2i @ V @ T3
    P /= np.linalg.norm(P[:, 2, :3], axis=-1)[:, None, None]
    depth = world @ np.swapaxes(P[:, 2:, :3], -1, -2) + P[:, 2:, 3:]  # (C, n, 1)
    sign = np.where(np.sum(depth[..., 0] * w, 1) < 0, -1.0, 1.0)
    return P * sign[:, None, None]


def decompose_numpy_batched(P):
    """`decompose_numpy` vectorised over (C, 3, 4) -> K, R, t."""
    M = P[:, :, :3]
    scale = np.where(np.linalg.det(M) < 0, -1.0, 1.0) / np.linalg.norm(M[:, 2], axis=-1)
    P = P * scale[:, None, None]
    m1, m2, m3 = P[:, 0, :3], P[:, 1, :3], P[:, 2, :3]
    dot = lambda a, b: np.einsum("ci,ci->c", a, b)  # noqa: E731
    u0, v0 = dot(m1, m3), dot(m2, m3)
    q2 = m2 - v0[:, None] * m3
    alpha_v = np.linalg.norm(q2, axis=-1)
    r2 = q2 / alpha_v[:, None]
    q1 = m1 - u0[:, None] * m3
    skew = dot(q1, r2)
    q1 = q1 - skew[:, None] * r2
    alpha_u = np.linalg.norm(q1, axis=-1)
    r1 = q1 / alpha_u[:, None]
    tz = P[:, 2, 3]
    ty = (P[:, 1, 3] - v0 * tz) / alpha_v
    tx = (P[:, 0, 3] - u0 * tz - skew * ty) / alpha_u
    U, _, Vt = np.linalg.svd(np.stack([r1, r2, m3], 1))
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, 2] *= -1
    K = np.zeros((len(P), 3, 3))
    K[:, 0, 0], K[:, 0, 1], K[:, 0, 2] = alpha_u, skew, u0
    K[:, 1, 1], K[:, 1, 2], K[:, 2, 2] = alpha_v, v0, 1.0
    return K, U @ Vt, np.stack([tx, ty, tz], -1)


def numpy_batched(world, pixels, mask):
    """Batched DLT + decomposition, in chunks of at most 2^20 / N cameras."""
    chunk = max(1, 2**20 // mask.shape[1])
    parts = []
    for i in range(0, len(mask), chunk):
        P = _dlt_numpy_batched(world, pixels[i : i + chunk], mask[i : i + chunk])
        parts.append(decompose_numpy_batched(P))
    return tuple(np.concatenate(v) for v in zip(*parts))


# ---------------------------------------------------------------------------------- OpenCV
def cv2_decompose_loop(world, pixels, mask):
    """NumPy DLT per camera, then `cv2.decomposeProjectionMatrix` (RQ) on its P."""
    Ks, Rs, ts = [], [], []
    for p, m in zip(pixels, mask):
        K, R, centre = cv2.decomposeProjectionMatrix(dlt_numpy(world[m], p[m]))[:3]
        Ks.append(K)
        Rs.append(R)
        ts.append(-R @ (centre[:3, 0] / centre[3, 0]))
    return np.array(Ks), np.array(Rs), np.array(ts)


def cv2_solvepnp_loop(world, pixels, mask, K_true):
    """Pose only: `cv2.solvePnP` (iterative) per camera with its true K."""
    Rs, ts = [], []
    for p, m, K in zip(pixels, mask, K_true):
        _, rvec, tvec = cv2.solvePnP(world[m], p[m], K, None)
        Rs.append(cv2.Rodrigues(rvec)[0])
        ts.append(tvec[:, 0])
    return K_true, np.array(Rs), np.array(ts)


CALIBRATE_FLAGS = (
    cv2.CALIB_USE_INTRINSIC_GUESS
    | cv2.CALIB_FIX_K1
    | cv2.CALIB_FIX_K2
    | cv2.CALIB_FIX_K3
    | cv2.CALIB_ZERO_TANGENT_DIST
)


def cv2_calibrate_loop(world32, pixels32, mask, K_true):
    """`cv2.calibrateCamera` per camera from the true K as its initial guess, no distortion."""
    Ks, Rs, ts = [], [], []
    for p, m, K in zip(pixels32, mask, K_true):
        _, K_out, _, rvecs, tvecs = cv2.calibrateCamera(
            [world32[m]], [p[m]], IMAGE_SIZE, K.copy(), np.zeros(5), flags=CALIBRATE_FLAGS
        )
        Ks.append(K_out)
        Rs.append(cv2.Rodrigues(rvecs[0])[0])
        ts.append(tvecs[0][:, 0])
    return np.array(Ks), np.array(Rs), np.array(ts)


# ---------------------------------------------------------------------------------- accuracy
def reprojection_rms(world, pixels, mask, K, R, t):
    """Per-camera RMS (px) of |K (R X + t) projected - pixel| over the visible points."""
    x = np.einsum("cij,cjk,nk->cni", K, R, world) + np.einsum("cij,cj->ci", K, t)[:, None]
    err2 = np.sum((x[..., :2] / x[..., 2:] - pixels) ** 2, -1)
    return np.sqrt(np.sum(np.where(mask, err2, 0.0), 1) / np.maximum(mask.sum(1), 1))


# ---------------------------------------------------------------------------------- timing
def bench_cell(cameras, C, N, *, mode, limits, with_calibrate):
    """Warm up, time and compare every path on C cameras and N points."""
    world, pixels, mask = make_problem(cameras, N, C)
    K_true = np.asarray(cameras.K)[:C]
    C_loop = min(C, LOOP_SUBSET[mode])
    sub = (world, pixels[:C_loop], mask[:C_loop])
    world32, pixels32 = world.astype(np.float32), pixels[:C_loop].astype(np.float32)
    jworld, jpixels, jmask = (jax.numpy.asarray(a) for a in (world, pixels, mask))

    fns = {"mvcalib": lambda: jax.block_until_ready(mvcalib_calibrate(jworld, jpixels, jmask))}
    if with_calibrate:
        fns["calibrate()"] = lambda: jax.block_until_ready(mc.calibrate(jworld, jpixels, jmask))
        # the general case, world points given per camera (PIV plates, bundle data)
        jworld_c = jax.numpy.asarray(np.broadcast_to(world, (C, N, 3)))
        fns["mvcalib, world (C,N,3)"] = lambda: jax.block_until_ready(
            mvcalib_calibrate(jworld_c, jpixels, jmask)
        )
        # pose only from the true K, as the solvePnP loop: closed form and Levenberg-Marquardt
        truth = cameras[:C]
        fns["mc.solve_pnp"] = lambda: jax.block_until_ready(
            mc.solve_pnp(truth, world, jpixels, jmask)
        )
    fns["numpy batched"] = lambda: numpy_batched(world, pixels, mask)
    fns["numpy loop"] = lambda: numpy_loop(*sub)
    fns["cv2 decompose"] = lambda: cv2_decompose_loop(*sub)
    fns["cv2 solvePnP"] = lambda: cv2_solvepnp_loop(*sub, K_true[:C_loop])
    fns["cv2 calibrateCamera"] = lambda: cv2_calibrate_loop(
        world32, pixels32, mask[:C_loop], K_true[:C_loop]
    )
    cameras_timed = {name: C_loop if name in LOOPS else C for name in fns}

    # First call of each (mvcalib compiles: first - warm is its compile time) and its output.
    first, warm, outputs = {}, {}, {}
    for name, fn in fns.items():
        first[name], warm[name], outputs[name] = first_and_warm(
            fn, warm_calls=1 if name in LOOPS or mode != "full" else 3
        )
    min_time, rounds = {"smoke": (0.02, 1), "quick": (0.5, 5), "full": (2.0, 5)}[mode]
    stats = measure(fns, min_time=min_time, rounds=rounds)

    # Accuracy: every path's cameras reproject the points; the reference is numpy batched SVD.
    krt = dict(outputs)
    krt["mvcalib"] = camera_krt(outputs["mvcalib"])
    if with_calibrate:
        krt["calibrate()"] = camera_krt(outputs["calibrate()"].cameras)
        krt["mvcalib, world (C,N,3)"] = camera_krt(outputs["mvcalib, world (C,N,3)"])
        krt["mc.solve_pnp"] = camera_krt(outputs["mc.solve_pnp"].cameras)
    rms = {
        name: reprojection_rms(world, pixels[: len(v[0])], mask[: len(v[0])], *v)
        for name, v in krt.items()
    }
    reference = rms["numpy batched"]

    # Peak memory: XLA's analysis for mvcalib's compiled function, tracemalloc for the rest.
    peak = {"mvcalib": xla_peak_mb(mvcalib_calibrate, jworld, jpixels, jmask)}
    for name, fn in fns.items():
        if name not in peak and name not in ("calibrate()", "mc.solve_pnp"):
            peak[name] = tracemalloc_peak_mb(fn)
    flops = bound.dlt_decomposition_flops(N)
    n_bytes = bound.dlt_bytes(N, n_cameras=C)
    bound_us = 1e6 * bound.bound_seconds(flops, n_bytes, limits)
    minimal = bound.dlt_decomposition_flops(N, minimal=True)
    bound_min_us = 1e6 * bound.bound_seconds(minimal, n_bytes, limits)

    us = {name: 1e6 * st["median"] / cameras_timed[name] for name, st in stats.items()}
    jitted = ("mvcalib", "calibrate()", "mc.solve_pnp")
    paths = []
    for name, st in stats.items():
        n = len(rms[name])
        diff = np.abs(rms[name] - reference[:n])
        paths.append(
            {
                "path": name,
                "cameras_timed": cameras_timed[name],
                "us_per_camera": us[name],
                "us_per_camera_q1_q3": [1e6 * st[q] / cameras_timed[name] for q in ("q1", "q3")],
                "repeats": st["repeats"],
                "peer_over_mvcalib": us[name] / us["mvcalib"],
                "rms_median_px": float(np.nanmedian(rms[name])),
                "rms_max_abs_diff_vs_numpy_svd_px": float(np.nanmax(diff)) if n else None,
                "cameras_failed": int(np.sum(~np.isfinite(rms[name]))),
                "first_call_s": first[name],
                "warm_call_s": warm[name],
                "compile_s": first[name] - warm[name] if name in jitted else None,
                "peak_mb": peak.get(name),
                "peak_kind": {"mvcalib": "xla"}.get(name, "tracemalloc" if name in peak else None),
                "x_bound": None if name in NOT_DLT else us[name] / bound_us,
                "x_bound_minimal": None if name in NOT_DLT else us[name] / bound_min_us,
            }
        )
    return {
        "n_cameras": C,
        "n_points": N,
        "visible_fraction": float(mask.mean()),
        "min_visible": int(mask.sum(1).min()),
        "bound_us_per_camera": bound_us,
        "bound_minimal_us_per_camera": bound_min_us,
        "flops_per_camera": flops,
        "bytes_per_camera": n_bytes,
        "paths": paths,
    }, (jworld, jpixels, jmask)


def bench_decomposition(cameras, C, N, *, mode):
    """Decomposition alone, on the P of the numpy batched DLT: mvcalib, NumPy, OpenCV."""
    world, pixels, mask = make_problem(cameras, N, C)
    chunk = max(1, 2**20 // N)
    P = np.concatenate(
        [
            _dlt_numpy_batched(world, pixels[i : i + chunk], mask[i : i + chunk])
            for i in range(0, C, chunk)
        ]
    )
    jP = jax.numpy.asarray(P)
    C_loop = min(C, LOOP_SUBSET[mode])
    fns = {
        "mvcalib": lambda: jax.block_until_ready(mvcalib_decompose(jP)),
        "numpy batched": lambda: decompose_numpy_batched(P),
        "cv2 decomposeProjectionMatrix": lambda: [
            cv2.decomposeProjectionMatrix(p) for p in P[:C_loop]
        ],
    }
    first, warm, out = first_and_warm(fns["mvcalib"])
    for fn in list(fns.values())[1:]:
        fn()
    min_time, rounds = {"smoke": (0.02, 1), "quick": (0.2, 3), "full": (1.0, 5)}[mode]
    stats = measure(fns, min_time=min_time, rounds=rounds)
    per = {"mvcalib": C, "numpy batched": C, "cv2 decomposeProjectionMatrix": C_loop}
    us = {name: 1e6 * st["median"] / per[name] for name, st in stats.items()}
    ref = decompose_numpy_batched(P)[0][:, 0, 0]
    limits = bound.machine_limits(quick=mode == "quick", smoke=mode == "smoke")
    bound_us = 1e6 * bound.bound_seconds(bound.decomposition_flops(), 8 * (12 + 17), limits)
    return {
        "n_cameras": C,
        "bound_us_per_camera": bound_us,
        "paths": [
            {
                "path": name,
                "cameras_timed": per[name],
                "us_per_camera": us[name],
                "peer_over_mvcalib": us[name] / us["mvcalib"],
                "x_bound": us[name] / bound_us,
            }
            for name in stats
        ],
        "mvcalib_compile_s": first - warm,
        "alpha_u_max_abs_diff_mvcalib_vs_numpy": float(
            np.max(np.abs(np.asarray(out.alpha_u) - ref))
        ),
    }


def xla_cost_row(cell, args):
    """XLA's cost analysis of mvcalib's compiled function, per camera, beside our counts."""
    cost = bound.xla_cost(mvcalib_calibrate, *args)
    C = cell["n_cameras"]
    return {
        "setting": f"C={C}, N={cell['n_points']}",
        "xla_flops_per_camera": None if cost is None else cost["flops"] / C,
        "xla_bytes_per_camera": None if cost is None else cost["bytes"] / C,
        "our_flops_per_camera": cell["flops_per_camera"],
        "our_bytes_per_camera": cell["bytes_per_camera"],
    }


# ---------------------------------------------------------------------------------- report
def _fmt(x, spec, width):
    return f"{'—':>{width}}" if x is None else f"{x:>{width}{spec}}"


def print_cell(cell):
    C, N = cell["n_cameras"], cell["n_points"]
    print(
        f"C = {C}, N = {N} (visible {100 * cell['visible_fraction']:.0f} %, at least "
        f"{cell['min_visible']} points a camera); bound {cell['bound_us_per_camera']:.3f} "
        f"µs/camera (minimal count {cell['bound_minimal_us_per_camera']:.3f})"
    )
    header = (
        f"  {'path':<21}{'µs/camera':>11}{'peer/':>8}{'RMS px':>8}{'max|ΔRMS|':>11}"
        f"{'compile':>9}{'peak MB':>9}{'x bound':>9}{'x min':>8}"
    )
    print(header)
    print(f"  {'':<21}{'':>11}{'mvcalib':>8}{'median':>8}{'vs svd px':>11}{'s':>9}")
    for p in cell["paths"]:
        mark = "*" if p["cameras_timed"] < C else " "
        peak = None if p["peak_mb"] is None else p["peak_mb"]
        kind = {"xla": "x", "tracemalloc": "t", None: " "}[p["peak_kind"]]
        print(
            f"  {p['path']:<21}{p['us_per_camera']:>10.2f}{mark}{p['peer_over_mvcalib']:>8.2f}"
            f"{p['rms_median_px']:>8.3f}{_fmt(p['rms_max_abs_diff_vs_numpy_svd_px'], '.1e', 11)}"
            f"{_fmt(p['compile_s'], '.2f', 9)}{_fmt(peak, '.1f', 8)}{kind}"
            f"{_fmt(p['x_bound'], '.1f', 9)}{_fmt(p['x_bound_minimal'], '.1f', 8)}"
        )
        if p["cameras_failed"]:
            print(f"    note: {p['cameras_failed']} cameras failed (NaN) in {p['path']}")
    print()


def print_legend(mode):
    subset = LOOP_SUBSET[mode]
    print(f"*         loop timed on the first {subset} cameras only, reported per camera.")
    print("peer/mvcalib: a path's time over mvcalib's (> 1: mvcalib faster).")
    print("RMS:       reprojection RMS per camera, median over cameras; max|ΔRMS|: largest")
    print("           |RMS - RMS of numpy batched SVD| over the cameras both computed.")
    print("compile:   first call - warm call (trace + compile), jitted paths only.")
    print("peak MB:   x = XLA memory analysis (args + outputs + temporaries); t = tracemalloc peak")
    print("           of one call (NumPy buffers + Python objects, not OpenCV's C++ internals).")
    print("x bound:   time / physical bound (bound.py: measured FLOP/s and bandwidth, textbook")
    print("           FLOP count); x min: against the minimal count. None for pose/refinement")
    print("           peers (solvePnP with the true K, calibrateCamera from the true K).")


def summary_rows(cell) -> list[dict]:
    """The suite's summary: every path of one cell, time per camera, ratio, accuracy..."""
    C, N = cell["n_cameras"], cell["n_points"]
    out = []
    for p in cell["paths"]:
        diff = p["rms_max_abs_diff_vs_numpy_svd_px"]
        subset = f" ({p['cameras_timed']} timed)" if p["cameras_timed"] < C else ""
        out.append(
            {
                "benchmark": "DLT + decomposition",
                "setting": f"C={C}, N={N}",
                "path": p["path"] + subset,
                "unit": "camera",
                "us": p["us_per_camera"],
                "peer_over_mvcalib": p["peer_over_mvcalib"],
                "accuracy": f"RMS {p['rms_median_px']:.3f} px, max|dRMS| {diff:.0e}",
                "compile_s": p["compile_s"],
                "peak_mb": p["peak_mb"],
                "peak_kind": p["peak_kind"],
                "x_bound": p["x_bound"],
            }
        )
    return out


def cells_for(mode):
    if mode == "smoke":
        return list(SMOKE_CELLS), []
    if mode == "quick":
        return list(QUICK_CELLS), []
    cells, skipped = [], []
    for C in N_CAMERAS:
        for N in N_POINTS:
            (cells if C * N <= MAX_CAMERA_POINTS else skipped).append((C, N))
    return cells, skipped


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the headline cell, short rounds")
    parser.add_argument("--smoke", action="store_true", help="one tiny cell (the smoke test)")
    args = parser.parse_args(argv)
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"

    wall = time.perf_counter()
    info = machine_info("opencv-python-headless")
    print(
        f"mvcalib DLT + decomposition benchmark ({mode}): jax {info['jax']} on "
        f"{info['jax_backend']}, numpy {info['numpy']}, opencv {cv2.__version__}, "
        f"{info['cpu_count']} CPUs, float64, {NOISE} px noise\n"
    )
    limits = bound.machine_limits(quick=mode == "quick", smoke=mode == "smoke")
    print(
        f"bound from this machine: {limits['flop_per_s'] / 1e9:.1f} GFLOP/s, "
        f"{limits['bandwidth_bytes_per_s'] / 1e9:.1f} GB/s (bound.py)\n"
    )
    cells, skipped = cells_for(mode)
    cameras = make_cameras(max(C for C, _ in cells))
    headline = HEADLINE if HEADLINE in cells else cells[-1]
    rows, xla = [], None
    for C, N in cells:
        with_calibrate = mode == "full" or (mode == "quick" and (C, N) == headline)
        row, args_ = bench_cell(
            cameras, C, N, mode=mode, limits=limits, with_calibrate=with_calibrate
        )
        rows.append(row)
        print_cell(row)
        if (C, N) == headline:
            xla = xla_cost_row(row, args_)
    print_legend(mode)
    if skipped:
        print(f"skipped (C x N > {MAX_CAMERA_POINTS} camera-points, memory): {skipped}")
    decomposition = None
    if mode != "smoke":  # (one more compilation)
        decomposition = bench_decomposition(cameras, *headline, mode=mode)
        print(
            f"\ndecomposition alone, C = {decomposition['n_cameras']} (P from numpy batched DLT):"
        )
        for p in decomposition["paths"]:
            mark = "*" if p["cameras_timed"] < decomposition["n_cameras"] else " "
            print(
                f"  {p['path']:<31}{p['us_per_camera']:>9.3f}{mark} µs/camera  peer/mvcalib "
                f"{p['peer_over_mvcalib']:>6.2f}  x bound {p['x_bound']:>7.1f}"
            )
        diff = decomposition["alpha_u_max_abs_diff_mvcalib_vs_numpy"]
        print(
            f"  max |Δalpha_u| mvcalib vs numpy {diff:.1e} px; "
            f"bound {decomposition['bound_us_per_camera']:.4f} µs/camera"
        )
    if xla:
        xf, xb = xla["xla_flops_per_camera"], xla["xla_bytes_per_camera"]
        print(
            f"\nXLA cost analysis of mvcalib at {xla['setting']}, per camera: "
            f"{_fmt(xf, '.0f', 0)} flops, {_fmt(xb, '.0f', 0)} bytes accessed (ours: "
            f"{xla['our_flops_per_camera']} flops, {xla['our_bytes_per_camera']:.0f} bytes; "
            "XLA does not count LAPACK calls)"
        )
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")
    return write_results(
        results_path("dlt.json"),
        "dlt",
        quick=mode != "full",
        machine=info,
        settings={
            "mode": mode,
            "noise_px": NOISE,
            "seed": SEED,
            "dtype": "float64",
            "image_size": list(IMAGE_SIZE),
            "loop_subset": LOOP_SUBSET[mode],
            "headline": list(headline),
            "skipped_cells": skipped,
        },
        limits=limits,
        wall_time_s=wall,
        results=rows,
        decomposition=decomposition,
        xla_cost_analysis=xla,
        summary=summary_rows(next(r for r in rows if (r["n_cameras"], r["n_points"]) == headline)),
    )


if __name__ == "__main__":
    main()
