"""Benchmark: batched DLT + closed-form decomposition in mvcalib against a plain NumPy loop.

What is measured
----------------
For rigs of C = 1, 64 and 4096 cameras, each seeing the 19-dot box-corner target
(`mvcalib.synthetic.random_rig`, 0.3 px Gaussian noise, float64), the time to go from 3-D/2-D
correspondences to calibrated cameras (alpha_u, alpha_v, u0, v0, skew, R, t):

- **mvcalib**: one `jax.jit`-compiled function, `mvcalib.dlt` (the normalised DLT for all
  cameras at once) followed by `Camera.from_projection`. It is compiled once per shape by a
  warm-up call, whose wall time is reported separately ("first call": trace + compile + one run).
  Every timed call ends with `jax.block_until_ready` on the returned `Camera`. mvcalib also
  computes per-camera statuses and condition numbers, which the NumPy loop does not.
- **calibrate()**: the public one-call API `mvcalib.calibrate`, called eagerly as a user would
  (input validation, DLT, decomposition and the reprojection report), for context.
- **NumPy loop**: the same math written as straightforward per-camera NumPy: Hartley
  normalisation, the 2N x 12 system, `np.linalg.svd`, de-normalisation, ||m3|| = 1 with the sign
  that puts the points in front, then the closed-form decomposition with `R` re-orthogonalised by
  `np.linalg.svd`.

Both run on the CPU as installed: XLA may spread a batch over all cores, the NumPy loop uses one.

Each time is the median of the per-call wall times (`time.perf_counter`) of at least 10 calls
lasting at least 0.5 s in all, per implementation and rig size. The implementations are timed
in interleaved blocks (10 rounds, each running every implementation back to back for 1/10 of
that time), so that drifts of the machine's speed hit all of them alike. Times are reported per
camera; the JSON also holds the quartiles. The maximum difference of the recovered alpha_u
between mvcalib and NumPy shows that both compute the same thing (they agree to rounding).

`--quick` (under a minute on two cores) takes 3 rounds over 0.05 s and times the NumPy loop on the
first 256 cameras only when C > 256, reporting the result per camera all the same.

Results are printed as a table and written to `benchmarks/results/dlt.json`.

Run from the repository root: `python benchmarks/dlt.py [--quick]`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _common import machine_info, measure, write_results  # noqa: E402

import mvcalib as mc  # noqa: E402

N_CAMERAS = (1, 64, 4096)
NOISE = 0.3  # pixels
SEED = 0
QUICK_NUMPY_SUBSET = 256
RESULTS = Path(__file__).resolve().parent / "results" / "dlt.json"


# ---------------------------------------------------------------------------------- mvcalib
@jax.jit
def mvcalib_calibrate(world, pixels, mask):
    """Batched normalised DLT and closed-form decomposition, one compiled function.

    Validation in `mvcalib.dlt` runs once, at trace time; the compiled code is the DLT kernel
    vectorised over cameras followed by the decomposition.
    """
    return mc.Camera.from_projection(mc.dlt(world, pixels, mask))


def mvcalib_calibrate_public(world, pixels, mask):
    """The public API, eagerly: validation, DLT, decomposition and the reprojection report."""
    return mc.calibrate(world, pixels, mask)


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
    R = U @ Vt
    return alpha_u, alpha_v, u0, v0, skew, R, np.array([tx, ty, tz])


def numpy_calibrate(world, pixels, mask):
    """Per-camera loop over a rig: (n, 3), (C, n, 2), (C, n) -> dict of stacked parameters."""
    names = ("alpha_u", "alpha_v", "u0", "v0", "skew", "R", "t")
    out = {name: [] for name in names}
    for pix, visible in zip(pixels, mask, strict=True):
        P = dlt_numpy(world[visible], pix[visible])
        for name, value in zip(names, decompose_numpy(P), strict=True):
            out[name].append(value)
    return {name: np.array(values) for name, values in out.items()}


# ---------------------------------------------------------------------------------- timing
def bench_one(C, *, quick):
    """Warm up, time and compare the implementations on a rig of C cameras."""
    rig = mc.synthetic.random_rig(jax.random.key(SEED), n_cameras=C, noise=NOISE)
    world, pixels, mask = rig.world, rig.pixels, rig.mask
    # NumPy works on host arrays, converted once outside the timed region.
    C_np = min(C, QUICK_NUMPY_SUBSET) if quick else C
    world_np = np.asarray(world)
    pixels_np, mask_np = np.asarray(pixels)[:C_np], np.asarray(mask)[:C_np]

    fns = {
        "mvcalib": lambda: jax.block_until_ready(mvcalib_calibrate(world, pixels, mask)),
        "calibrate": lambda: jax.block_until_ready(mvcalib_calibrate_public(world, pixels, mask)),
        "numpy": lambda: numpy_calibrate(world_np, pixels_np, mask_np),
    }
    # Warm-up: the first call of each compiles (JAX) or fills caches, and gives the results.
    first_call, outputs = {}, {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        outputs[name] = fn()
        first_call[name] = time.perf_counter() - t0
    cams, ref = outputs["mvcalib"], outputs["numpy"]
    n_ok = int(np.sum(np.asarray(outputs["calibrate"].ok)))

    min_time, rounds = (0.05, 3) if quick else (0.5, 10)
    stats = measure(fns, min_time=min_time, rounds=rounds)
    per_camera = {"mvcalib": C, "calibrate": C, "numpy": C_np}
    us = {name: 1e6 * st["median"] / per_camera[name] for name, st in stats.items()}

    alpha_u = np.asarray(cams.alpha_u)[:C_np]
    diff = np.abs(alpha_u - ref["alpha_u"])
    # Every other parameter too, for the JSON: the largest absolute difference of each.
    max_abs_diff = {
        name: float(np.max(np.abs(np.asarray(getattr(cams, name))[:C_np] - value)))
        for name, value in ref.items()
    }
    row = {
        "n_cameras": C,
        "n_points": int(world.shape[0]),
        "visible_fraction": float(np.mean(np.asarray(mask))),
        "cameras_ok": n_ok,
        "numpy_cameras_timed": C_np,
    }
    for name, st in stats.items():
        row[f"{name}_us_per_camera"] = us[name]
        row[f"{name}_us_per_camera_q1_q3"] = [1e6 * st[q] / per_camera[name] for q in ("q1", "q3")]
        row[f"{name}_repeats"] = st["repeats"]
        row[f"{name}_first_call_s"] = first_call[name]
    row.update(
        {
            "speedup_numpy_over_mvcalib": us["numpy"] / us["mvcalib"],
            "alpha_u_max_abs_diff": float(diff.max()),
            "alpha_u_max_rel_diff": float(np.max(diff / np.abs(ref["alpha_u"]))),
            "max_abs_diff_by_parameter": max_abs_diff,
        }
    )
    return row


# ---------------------------------------------------------------------------------- report
def print_table(rows, quick):
    header = (
        f"{'C':>5} {'N':>3} {'mvcalib':>11} {'numpy':>11} {'numpy/':>8} {'calibrate()':>12} "
        f"{'max|Δα_u|':>10} {'max rel':>8} {'1st call':>9}"
    )
    units = (
        f"{'':>5} {'':>3} {'µs/cam':>11} {'µs/cam':>11} {'mvcalib':>8} {'µs/cam':>12} "
        f"{'px':>10} {'':>8} {'s':>9}"
    )
    print(header)
    print(units)
    print("-" * len(header))
    for r in rows:
        mark = "*" if r["numpy_cameras_timed"] < r["n_cameras"] else " "
        print(
            f"{r['n_cameras']:>5} {r['n_points']:>3} {r['mvcalib_us_per_camera']:>11.2f} "
            f"{r['numpy_us_per_camera']:>10.2f}{mark} {r['speedup_numpy_over_mvcalib']:>8.1f} "
            f"{r['calibrate_us_per_camera']:>12.2f} {r['alpha_u_max_abs_diff']:>10.1e} "
            f"{r['alpha_u_max_rel_diff']:>8.0e} {r['mvcalib_first_call_s']:>9.2f}"
        )
    print()
    print("mvcalib:     jitted batched DLT + Camera.from_projection, median per call / C.")
    print("numpy:       per-camera NumPy loop doing the same math, median per call / cameras.")
    print("calibrate(): mvcalib.calibrate called eagerly (validation + DLT + decomposition +")
    print("             reprojection report), for context.")
    print("1st call:    wall time of mvcalib's first call per shape (trace + compile + run).")
    print("max|Δα_u|:   largest difference of alpha_u between mvcalib and NumPy (alpha_u is")
    print("             800-2000 px); max rel: the same relative to alpha_u.")
    if quick and any(r["numpy_cameras_timed"] < r["n_cameras"] for r in rows):
        print("*            --quick: NumPy loop timed (and compared) on the first")
        print(f"             {QUICK_NUMPY_SUBSET} cameras only; reported per camera.")
    for r in rows:
        if r["cameras_ok"] < r["n_cameras"]:
            print(
                f"note: C = {r['n_cameras']}: only {r['cameras_ok']} cameras calibrated; "
                "the failed ones are NaN in mvcalib and make the differences NaN."
            )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="3 short rounds, NumPy loop on 256 cameras at most; < 1 min",
    )
    args = parser.parse_args(argv)

    wall = time.perf_counter()
    info = machine_info()
    print(
        f"mvcalib DLT benchmark ({'quick' if args.quick else 'full'}): jax {info['jax']} on "
        f"{info['jax_backend']}, numpy {info['numpy']}, {info['cpu_count']} CPUs, float64\n"
    )
    rows = [bench_one(C, quick=args.quick) for C in N_CAMERAS]
    print_table(rows, args.quick)
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")

    write_results(
        RESULTS,
        "dlt",
        quick=args.quick,
        machine=info,
        settings={"noise_px": NOISE, "seed": SEED, "dtype": "float64"},
        wall_time_s=wall,
        results=rows,
    )


if __name__ == "__main__":
    main()
