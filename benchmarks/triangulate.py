"""Benchmark: batched N-view triangulation against a NumPy per-point loop and OpenCV.

What is measured
----------------
A synthetic rig of 8 cameras (`mvcalib.synthetic.random_cameras`, pinhole, float64) looking at
random points in the box-corner volume, 0.3 px Gaussian pixel noise, every point seen by every
camera.

- **mvcalib**: `mc.triangulate(cameras, pixels)`: one jit-compiled call for all points
  (normalised linear triangulation per point, 4 x 4 eigensolve, plus diagnostics: views,
  reprojection RMS, ray angle, ok flag). Timed warm; the first call's compile time is reported.
- **NumPy loop**: the same linear triangulation written the way one would in an afternoon: for
  each point, stack the 2C x 4 rows `x P3 - P1, y P3 - P2` from the projection matrices and take
  the last right singular vector (`np.linalg.svd`). Timed on a subset of points (it is
  per-point work) and reported per point.
- **OpenCV** (2 views only, since `cv2.triangulatePoints` takes two): all points of cameras 0
  and 1 in one call, against `mc.triangulate` on the same two views.

Accuracy: RMS 3-D error against the true points, for each method on the same noisy pixels.
Times are medians of interleaved repeats (`_common.measure`); ratios are from this one run.

`--quick`: 10k points instead of 100k (under a minute).

Run from the repository root: `python benchmarks/triangulate.py [--quick]`; results go to
`benchmarks/results/triangulate.json`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine_info, measure, write_results  # noqa: E402

import mvcalib as mc  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "triangulate.json"
N_VIEWS, NOISE, LOOP_POINTS = 8, 0.3, 2000


def numpy_loop(P, pixels):
    out = np.empty((pixels.shape[1], 3))
    for n in range(pixels.shape[1]):
        x = pixels[:, n]
        A = np.concatenate([x[:, :1] * P[:, 2] - P[:, 0], x[:, 1:] * P[:, 2] - P[:, 1]])
        v = np.linalg.svd(A)[2][-1]
        out[n] = v[:3] / v[3]
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="10k points instead of 100k")
    args = parser.parse_args(argv)
    n_points = 10_000 if args.quick else 100_000
    wall = time.perf_counter()

    key = jax.random.key(0)
    cameras = mc.synthetic.random_cameras(key, N_VIEWS)
    world = np.random.default_rng(0).uniform(0.0, 200.0, (n_points, 3))
    true_px = np.asarray(cameras.project(world))
    pixels = true_px + NOISE * np.random.default_rng(1).standard_normal(true_px.shape)
    P = np.asarray(cameras.projection_matrix())
    jpixels = jax.numpy.asarray(pixels)

    start = time.perf_counter()
    ours = mc.triangulate(cameras, jpixels)
    jax.block_until_ready(ours.points)
    compile_s = time.perf_counter() - start
    pair = cameras[:2]
    jax.block_until_ready(mc.triangulate(pair, jpixels[:2]).points)

    loop_px = pixels[:, :LOOP_POINTS]
    stats = measure(
        {
            "mvcalib": lambda: jax.block_until_ready(mc.triangulate(cameras, jpixels).points),
            "numpy loop": lambda: numpy_loop(P, loop_px),
            "mvcalib 2 views": lambda: jax.block_until_ready(
                mc.triangulate(pair, jpixels[:2]).points
            ),
            "cv2 2 views": lambda: cv2.triangulatePoints(P[0], P[1], pixels[0].T, pixels[1].T),
        },
        min_time=8.0 if args.quick else 20.0,
        rounds=4,
    )
    per_point = {
        "mvcalib": stats["mvcalib"]["median"] / n_points,
        "numpy loop": stats["numpy loop"]["median"] / LOOP_POINTS,
        "mvcalib 2 views": stats["mvcalib 2 views"]["median"] / n_points,
        "cv2 2 views": stats["cv2 2 views"]["median"] / n_points,
    }

    def rms(X):
        return float(np.sqrt(np.mean(np.sum((X - world[: len(X)]) ** 2, -1))))

    X_cv = cv2.triangulatePoints(P[0], P[1], pixels[0].T, pixels[1].T)
    accuracy = {
        "mvcalib": rms(np.asarray(ours.points)),
        "numpy loop": rms(numpy_loop(P, loop_px)),
        "mvcalib 2 views": rms(np.asarray(mc.triangulate(pair, jpixels[:2]).points)),
        "cv2 2 views": rms((X_cv[:3] / X_cv[3]).T),
    }
    rows = []
    print(
        f"triangulation benchmark ({'quick' if args.quick else 'full'}): {n_points} points, "
        f"{N_VIEWS} views, {NOISE} px noise, float64; mvcalib compile {compile_s:.1f} s\n"
    )
    print(f"{'method':<18}{'points/s':>14}{'us/point':>10}{'3-D RMS (mm)':>14}")
    for name in per_point:
        rows.append(
            {
                "method": name,
                "points_per_s": 1.0 / per_point[name],
                "us_per_point": 1e6 * per_point[name],
                "rms_3d_mm": accuracy[name],
                "repeats": stats[name]["repeats"],
            }
        )
        print(
            f"{name:<18}{1 / per_point[name]:>14,.0f}{1e6 * per_point[name]:>10.2f}"
            f"{accuracy[name]:>14.4f}"
        )
    ratios = {
        "mvcalib_vs_numpy_loop": per_point["numpy loop"] / per_point["mvcalib"],
        "mvcalib_vs_cv2_2_views": per_point["cv2 2 views"] / per_point["mvcalib 2 views"],
    }
    print(
        f"\nmvcalib is {ratios['mvcalib_vs_numpy_loop']:.0f}x the NumPy loop ({N_VIEWS} views) "
        f"and {ratios['mvcalib_vs_cv2_2_views']:.2f}x cv2.triangulatePoints (2 views) in speed"
    )
    wall = time.perf_counter() - wall
    print(f"total wall time {wall:.1f} s")
    write_results(
        RESULTS,
        "triangulate",
        quick=args.quick,
        machine=machine_info("opencv-python-headless"),
        settings={
            "n_points": n_points,
            "n_views": N_VIEWS,
            "noise_px": NOISE,
            "numpy_loop_points": LOOP_POINTS,
        },  # fmt: skip
        compile_s=compile_s,
        ratios=ratios,
        wall_time_s=wall,
        results=rows,
    )


if __name__ == "__main__":
    main()
