"""Benchmark: batched N-view triangulation against NumPy (per point and batched) and OpenCV.

What is measured
----------------
A synthetic rig of 8 cameras (`mvcalib.synthetic.random_cameras`, pinhole, float64) looking at
100k random points in the box-corner volume, 0.3 px Gaussian pixel noise, every point seen by
every camera.

- **mvcalib**: `mc.triangulate(cameras, pixels)` for all points, wrapped in one `jax.jit`
  (normalised linear triangulation per point, plus diagnostics: views, reprojection RMS, ray
  angle, ok flag). Timed warm; compile = first call - warm call.
- **numpy loop**: the same linear triangulation written the way one would in an afternoon: for
  each point, stack the 2V x 4 rows `x P3 - P1, y P3 - P2` from the projection matrices and take
  the last right singular vector (`np.linalg.svd`). Timed on the first 2000 points (it is
  per-point work) and reported per point.
- **numpy batched**: the same rows for all points at once and one `np.linalg.svd` of the
  `(points, 2V, 4)` stack.
- **cv2 2 views**: `cv2.triangulatePoints` (it takes two views) on cameras 0 and 1, all points
  in one call, against mvcalib on the same two views (**mvcalib 2 views**).

Accuracy: RMS 3-D error against the true points, for each method on the same noisy pixels.
Times are medians of interleaved repeats (`_common.measure`); ratios are from this one run.
Peak memory: XLA's memory analysis of the compiled call (mvcalib), `tracemalloc`'s peak of one
call (NumPy, OpenCV's returned arrays). "x bound": time over the physical bound of `bound.py`
(linear triangulation only: mvcalib also computes its diagnostics).

`--quick`: shorter rounds, 2 of at least 0.5 s (same 100k points; the suite's `--quick` must stay
under 2 minutes, and took 115-120 s on the shared machine with 1 s rounds). `--smoke`: 2000
points, one round, no 2-view paths.

Run from the repository root: `python benchmarks/triangulate.py [--quick]`; results go to
`benchmarks/results/triangulate.json`.
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

N_VIEWS, NOISE, LOOP_POINTS = 8, 0.3, 2000
N_POINTS = {"smoke": 2000, "quick": 100_000, "full": 100_000}
TIMING = {"smoke": (0.05, 1), "quick": (0.5, 2), "full": (20.0, 4)}  # (min_time s, rounds)


@jax.jit
def mvcalib_triangulate(cameras, pixels):
    return mc.triangulate(cameras, pixels)


@jax.jit
def mvcalib_refined(cameras, pixels):
    return mc.triangulate(cameras, pixels, refine=True)


def numpy_gauss_newton(P, pixels, X, steps=5):
    """`steps` Gauss–Newton steps of every point's reprojection error from `X`, batched (a
    user's afternoon: a benchmark trial's 15 lines), for cameras without distortion."""
    for _ in range(steps):
        h = np.einsum("cij,nj->cni", P[:, :, :3], X) + P[:, None, :, 3]
        uv = h[..., :2] / h[..., 2:]
        J = (P[:, None, :2, :3] - uv[..., None] * P[:, None, 2:3, :3]) / h[..., 2:, None]
        JtJ = np.einsum("cnki,cnkj->nij", J, J)
        Jtr = np.einsum("cnki,cnk->ni", J, uv - pixels)
        X = X - np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
    return X


def rows_of(P, pixels):
    """The (points, 2V, 4) stack of rows x P3 - P1, y P3 - P2 of the linear triangulation."""
    x, y = pixels[..., :1], pixels[..., 1:]  # (V, points, 1)
    rows = np.concatenate([x * P[:, None, 2] - P[:, None, 0], y * P[:, None, 2] - P[:, None, 1]])
    return np.swapaxes(rows, 0, 1)


def numpy_loop(P, pixels):
    out = np.empty((pixels.shape[1], 3))
    for n in range(pixels.shape[1]):
        x = pixels[:, n]
        A = np.concatenate([x[:, :1] * P[:, 2] - P[:, 0], x[:, 1:] * P[:, 2] - P[:, 1]])
        v = np.linalg.svd(A)[2][-1]
        out[n] = v[:3] / v[3]
    return out


def numpy_batched(P, pixels):
    v = np.linalg.svd(rows_of(P, pixels))[2][:, -1]
    return v[:, :3] / v[:, 3:]


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter rounds")
    parser.add_argument("--smoke", action="store_true", help="2000 points, one round")
    args = parser.parse_args(argv)
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    n_points = N_POINTS[mode]
    loop_points = min(LOOP_POINTS, n_points)
    wall = time.perf_counter()
    limits = bound.machine_limits(quick=mode == "quick", smoke=mode == "smoke")

    cameras = mc.synthetic.random_cameras(jax.random.key(0), N_VIEWS)
    world = np.random.default_rng(0).uniform(0.0, 160.0, (n_points, 3))
    true_px = np.asarray(cameras.project(world))
    pixels = true_px + NOISE * np.random.default_rng(1).standard_normal(true_px.shape)
    P = np.asarray(cameras.projection_matrix())
    jpixels = jax.numpy.asarray(pixels)
    pair, jpair = cameras[:2], jpixels[:2]
    loop_px = pixels[:, :loop_points]

    fns = {
        "mvcalib": lambda: jax.block_until_ready(mvcalib_triangulate(cameras, jpixels)),
        "numpy loop": lambda: numpy_loop(P, loop_px),
        "numpy batched": lambda: numpy_batched(P, pixels),
    }
    if mode != "smoke":  # (more compilations)
        fns["mvcalib 2 views"] = lambda: jax.block_until_ready(mvcalib_triangulate(pair, jpair))
        fns["cv2 2 views"] = lambda: cv2.triangulatePoints(P[0], P[1], pixels[0].T, pixels[1].T)
        # the points polished: refine=True against a batched NumPy Gauss–Newton from the same
        # linear points (the cameras have no distortion, which the NumPy version leaves out)
        linear = numpy_batched(P, pixels)
        fns["mvcalib refine"] = lambda: jax.block_until_ready(mvcalib_refined(cameras, jpixels))
        fns["numpy GN"] = lambda: numpy_gauss_newton(P, pixels, linear)
    first, warm, outputs = {}, {}, {}
    for name, fn in fns.items():  # a warm call only where first - warm is a compile time
        first[name], warm[name], outputs[name] = first_and_warm(
            fn, warm_calls=1 if name.startswith("mvcalib") else 0
        )
    min_time, rounds = TIMING[mode]
    stats = measure(fns, min_time=min_time, rounds=rounds)
    count = {name: loop_points if name == "numpy loop" else n_points for name in fns}
    per_point = {name: stats[name]["median"] / count[name] for name in fns}

    def rms(X):
        return float(np.sqrt(np.mean(np.sum((X - world[: len(X)]) ** 2, -1))))

    points = {
        "mvcalib": np.asarray(outputs["mvcalib"].points),
        "numpy loop": outputs["numpy loop"],
        "numpy batched": outputs["numpy batched"],
    }
    peak = {"mvcalib": xla_peak_mb(mvcalib_triangulate, cameras, jpixels)}
    if "cv2 2 views" in fns:
        X_cv = outputs["cv2 2 views"]
        points["mvcalib 2 views"] = np.asarray(outputs["mvcalib 2 views"].points)
        points["cv2 2 views"] = (X_cv[:3] / X_cv[3]).T
        peak["mvcalib 2 views"] = xla_peak_mb(mvcalib_triangulate, pair, jpair)
        points["mvcalib refine"] = np.asarray(outputs["mvcalib refine"].points)
        points["numpy GN"] = outputs["numpy GN"]
        peak["mvcalib refine"] = xla_peak_mb(mvcalib_refined, cameras, jpixels)
    for name in fns:
        if not name.startswith("mvcalib"):
            peak[name] = tracemalloc_peak_mb(fns[name])
    views = {name: 2 if "2 views" in name else N_VIEWS for name in fns}
    reference = {"mvcalib": "mvcalib", "numpy loop": "mvcalib", "numpy batched": "mvcalib"}
    reference |= {"mvcalib 2 views": "mvcalib 2 views", "cv2 2 views": "mvcalib 2 views"}
    reference |= {"mvcalib refine": "mvcalib refine", "numpy GN": "mvcalib refine"}
    rows = []
    for name in fns:
        b = bound.bound_seconds(
            bound.triangulation_flops(views[name]), bound.triangulation_bytes(views[name]), limits
        )
        jitted = name.startswith("mvcalib")
        rows.append(
            {
                "path": name,
                "views": views[name],
                "points_timed": count[name],
                "points_per_s": 1.0 / per_point[name],
                "us_per_point": 1e6 * per_point[name],
                "peer_over_mvcalib": per_point[name] / per_point[reference[name]],
                "rms_3d_mm": rms(points[name]),
                "max_abs_diff_vs_mvcalib_mm": float(
                    np.max(np.abs(points[name] - points[reference[name]][: len(points[name])]))
                ),
                "repeats": stats[name]["repeats"],
                "compile_s": first[name] - warm[name] if jitted else None,
                "peak_mb": peak[name],
                "peak_kind": "xla" if jitted else "tracemalloc",
                "bound_us_per_point": 1e6 * b,
                "x_bound": per_point[name] / b,
            }
        )
    xla = bound.xla_cost(mvcalib_triangulate, cameras, jpixels)

    print(
        f"triangulation benchmark ({mode}): {n_points} points, {N_VIEWS} views, {NOISE} px "
        f"noise, float64; bound from {limits['flop_per_s'] / 1e9:.1f} GFLOP/s, "
        f"{limits['bandwidth_bytes_per_s'] / 1e9:.1f} GB/s\n"
    )
    header = (
        f"{'method':<17}{'points/s':>12}{'µs/point':>10}{'peer/':>9}{'3-D RMS':>9}"
        f"{'max|ΔX|':>9}{'compile':>9}{'peak MB':>9}{'x bound':>9}"
    )
    print(header)
    print(f"{'':<17}{'':>12}{'':>10}{'mvcalib':>9}{'mm':>9}{'mm':>9}{'s':>9}")
    print("-" * len(header))
    for r in rows:
        mark = "*" if r["points_timed"] < n_points else " "
        comp = "—" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
        kind = "x" if r["peak_kind"] == "xla" else "t"
        print(
            f"{r['path']:<17}{r['points_per_s']:>12,.0f}{r['us_per_point']:>9.3f}{mark}"
            f"{r['peer_over_mvcalib']:>9.2f}{r['rms_3d_mm']:>9.4f}"
            f"{r['max_abs_diff_vs_mvcalib_mm']:>9.1e}{comp:>9}{r['peak_mb']:>8.1f}{kind}"
            f"{r['x_bound']:>9.0f}"
        )
    print(
        f"\n* timed on the first {loop_points} points, reported per point. peer/mvcalib: time "
        "over mvcalib's on as many views (> 1: mvcalib faster);\n  max|ΔX|: largest coordinate "
        "difference from mvcalib's points. peak MB: x = XLA memory analysis, t = tracemalloc.\n"
        "  x bound: time / physical bound of the linear triangulation (mvcalib also computes "
        "its diagnostics)."
    )
    if xla:
        print(
            f"XLA cost analysis of mvcalib, per point: {xla['flops'] / n_points:.0f} flops, "
            f"{xla['bytes'] / n_points:.0f} bytes accessed (ours: "
            f"{bound.triangulation_flops(N_VIEWS)} flops, {bound.triangulation_bytes(N_VIEWS):.0f}"
            " bytes; XLA does not count LAPACK calls)"
        )
    ratios = {
        "mvcalib_vs_numpy_loop": per_point["numpy loop"] / per_point["mvcalib"],
        "mvcalib_vs_numpy_batched": per_point["numpy batched"] / per_point["mvcalib"],
    }
    print(
        f"\nmvcalib is {ratios['mvcalib_vs_numpy_loop']:.0f}x the NumPy loop and "
        f"{ratios['mvcalib_vs_numpy_batched']:.1f}x batched NumPy ({N_VIEWS} views) in speed"
    )
    if "cv2 2 views" in fns:
        ratios["mvcalib_vs_cv2_2_views"] = per_point["cv2 2 views"] / per_point["mvcalib 2 views"]
        print(f"and {ratios['mvcalib_vs_cv2_2_views']:.2f}x cv2.triangulatePoints on 2 views")
        ratios["refine_vs_numpy_gauss_newton"] = per_point["numpy GN"] / per_point["mvcalib refine"]
        print(
            f"refine=True is {ratios['refine_vs_numpy_gauss_newton']:.2f}x a batched NumPy "
            "Gauss-Newton of 5 steps"
        )
    wall = time.perf_counter() - wall
    print(f"total wall time {wall:.1f} s")
    summary = [
        {
            "benchmark": "triangulation",
            "setting": f"{n_points} points, V={r['views']}",
            "path": r["path"],
            "unit": "point",
            "us": r["us_per_point"],
            "peer_over_mvcalib": r["peer_over_mvcalib"],
            "accuracy": f"3-D RMS {r['rms_3d_mm']:.4f} mm",
            "compile_s": r["compile_s"],
            "peak_mb": r["peak_mb"],
            "peak_kind": r["peak_kind"],
            "x_bound": r["x_bound"],
        }
        for r in rows
    ]
    return write_results(
        results_path("triangulate.json"),
        "triangulate",
        quick=mode != "full",
        machine=machine_info("opencv-python-headless"),
        settings={
            "mode": mode,
            "n_points": n_points,
            "n_views": N_VIEWS,
            "noise_px": NOISE,
            "numpy_loop_points": loop_points,
        },
        limits=limits,
        xla_cost_analysis_per_point=None
        if xla is None
        else {"flops": xla["flops"] / n_points, "bytes": xla["bytes"] / n_points},
        ratios=ratios,
        wall_time_s=wall,
        results=rows,
        summary=summary,
    )


if __name__ == "__main__":
    main()
