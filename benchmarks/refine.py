"""Benchmark: vmapped nonlinear refinement in mvcalib against a Python loop of SciPy least_squares.

What is measured
----------------
One rig of 256 cameras (`mvcalib.synthetic.random_rig`, seed 0, `fill=(0.8, 0.95)`) sees the
108-dot target `mvcalib.targets.box_corner_grid(6)`. The true cameras get Brown–Conrady
distortion k1 = -0.2, k2 = 0.1, p1 = p2 = 1e-3, k3 = 0 and observe the target with 0.3 px
Gaussian noise (float64). Every camera is seeded by the closed-form DLT (`mvcalib.calibrate`)
with the skew set to zero, and then refined to the least-squares minimum of its reprojection
error over 14 parameters (alpha_u, alpha_v, u0, v0, rotation, translation, k1, k2, p1, p2; zero
skew and k3 = 0 held fixed). The problems of C = 16 and 64 cameras are the first C of the rig.

- **mvcalib**: the public `mvcalib.refine(seed, world, pixels, mask)` with its defaults
  (`mvcalib.SecantLM` driven by `optimistix.least_squares`, steps down to 1e-5 standard errors,
  one problem per camera, on one CPU device in 32 slots side by side, each given the next camera
  as its own converges (`mvcalib._refine.solve_each`), vmapped across the rig elsewhere), wrapped
  in one `jax.jit`
  so that validation, solve and report are one compiled call (whose memory XLA can analyse). It
  is compiled once per rig size by a warm-up call, whose wall time is reported separately ("1st
  call": trace + compile + one run; compile = 1st call - warm call). Every timed call ends
  with `jax.block_until_ready` on the returned `Refinement`.
  Besides the optimum, each call also computes the per-camera covariance of the parameters and
  the reprojection report, which the SciPy loop does not.
- **mvcalib, from Python** (`mvcalib_eager` in the JSON): the same `mvcalib.refine` called as a
  user calls it outside a `jax.jit` of their own: its programs compiled by mvcalib (LLVM
  without optimisation below `mvcalib._buckets.COMPACT` camera-points, which 256 x 108 is:
  there one camera after another, `mvcalib._refine.slots`), the rig run in equal pieces, one
  per core, side by side (`mvcalib._buckets.pieces`). Its cameras are compared with the jitted
  call's.
- **scipy lm / scipy trf**: a Python loop over the cameras calling
  `scipy.optimize.least_squares` (`method="lm"`, MINPACK; `method="trf"`) with
  `x_scale="jac"` and `ftol = xtol = gtol = 1e-12` on the same parametrisation and seed:
  x = [fx, fy, cx, cy, rvec (3), tvec (3), k1, k2, p1, p2], `rvec = cv2.Rodrigues(seed.R)`.
  Residuals are `cv2.projectPoints(world, rvec, tvec, K, dist) - pixels` over the visible points
  (OpenCV's implementation of the same camera model, independent of mvcalib's), and the
  Jacobian is the analytic one that `cv2.projectPoints` returns (checked against central finite
  differences once per run). The per-camera inputs (visible points, seed vector) are extracted
  to NumPy once, outside the timed region.

Both run on the CPU as installed: XLA may spread the batch over both cores, the SciPy loop uses
one.

Each time is the median of the per-call wall times (`time.perf_counter`) of all calls. The
implementations are timed in interleaved blocks (7 rounds, each running every implementation
back to back for at least 0.2 s, at least once), so that drifts of the machine's speed hit all of
them alike. Times are reported per camera and per call; the ratio is scipy loop / mvcalib
(above 1: mvcalib is faster). The JSON also holds the quartiles.

Equal final RMS: the per-camera reprojection RMS (sqrt(sum of squared residuals / visible
points)) at the end of each method should be the same minimum; the table gives the largest
relative difference over the cameras between mvcalib and each SciPy method, and the JSON holds
the per-camera RMS, iterations and statuses of the 256-camera rig. Iterations: mvcalib's LM steps
(`Refinement.iterations`); SciPy's Jacobian evaluations (`njev`, one per accepted step for "lm").
On one CPU device mvcalib solves one camera after another, each for its own steps (under `vmap`,
on an accelerator, a batch runs until its slowest camera has converged): the third table sets the
camera-steps mvcalib pays (the sum of its steps; the batch's size x its max steps under `vmap`)
against the loop's (the sum of `njev`), and gives the time per camera-step of each.

Peak memory: XLA's memory analysis of mvcalib's compiled call (arguments + outputs +
temporaries); `tracemalloc`'s peak during a SciPy loop over 16 cameras (the loop's peak is one
camera's; NumPy buffers and Python objects).

`--quick` times the 256-camera rig only: mvcalib and SciPy's lm in three interleaved rounds (the
median of three warm calls each: one call alone moved by up to 1.5x between runs on the shared
machine), SciPy's trf, the slowest, in one call.

Results are printed as tables and written to `benchmarks/results/refine.json`.

Run from the repository root: `python benchmarks/refine.py [--quick]`.
"""

from __future__ import annotations

import argparse
import functools
import time

import jax

jax.config.update("jax_enable_x64", True)

import cv2  # noqa: E402
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

try:
    from ._common import (
        machine_info,
        measure,
        results_path,
        tracemalloc_peak_mb,
        write_results,
        xla_peak_mb,
    )
except ImportError:  # run as a script
    from _common import (
        machine_info,
        measure,
        results_path,
        tracemalloc_peak_mb,
        write_results,
        xla_peak_mb,
    )

import mvcalib as mc  # noqa: E402

N_CAMERAS = (16, 64, 256)
GRID = 6  # box_corner_grid(6): 108 dots
NOISE = 0.3  # pixels
IMAGE_SIZE = (1000, 1100)
FILL = (0.8, 0.95)
DISTORTION = (-0.2, 0.1, 1e-3, 1e-3, 0.0)  # k1, k2, p1, p2, k3 of the true cameras
SCIPY_TOL = 1e-12
SCIPY_METHODS = ("lm", "trf")


# ---------------------------------------------------------------------------------- problem
@functools.partial(jax.jit, static_argnums=0)
def make_problem(C):
    """The distorted rig, its noisy observations and the zero-skew DLT seed, for C cameras.

    One compiled program: generated call by call (each call compiling its own program) it took
    14 s, half of a quick run of this script; as one, 10 s."""
    target = mc.targets.box_corner_grid(GRID)
    rig = mc.synthetic.random_rig(
        jax.random.key(0), n_cameras=C, target=target, noise=0.0, fill=FILL
    )
    dist = jnp.broadcast_to(jnp.asarray(DISTORTION, rig.world.dtype), (C, 5))
    cams = eqx.tree_at(lambda c: c.dist, rig.cameras, dist)
    _, pixels, mask = mc.synthetic.observe(jax.random.key(1), cams, rig.world, NOISE, IMAGE_SIZE)
    seed = mc.calibrate(rig.world, pixels, mask).cameras
    seed = eqx.tree_at(lambda c: c.skew, seed, jnp.zeros(C, seed.skew.dtype))
    return rig.world, pixels, mask, seed


def subset(problem, C):
    world, pixels, mask, seed = problem
    return world, pixels[:C], mask[:C], seed[:C]


# ---------------------------------------------------------------------------------- mvcalib
@jax.jit
def _refine_jit(seed, world, pixels, mask):
    return mc.refine(seed, world, pixels, mask)


def mvcalib_refine(seed, world, pixels, mask):
    """The public API with its defaults, blocked until the whole result is computed."""
    return jax.block_until_ready(_refine_jit(seed, world, pixels, mask))


def mvcalib_refine_eager(seed, world, pixels, mask):
    """The same call from Python, as a user makes it outside a `jax.jit` of their own."""
    return jax.block_until_ready(mc.refine(seed, world, pixels, mask))


# ---------------------------------------------------------------------------------- SciPy
def scipy_inputs(world, pixels, mask, seed):
    """Per camera: (visible world points, their pixels, seed vector x0), as NumPy arrays."""
    world, pixels, mask = np.asarray(world), np.asarray(pixels), np.asarray(mask)
    au, av, u0, v0 = (np.asarray(getattr(seed, n)) for n in ("alpha_u", "alpha_v", "u0", "v0"))
    R, t = np.asarray(seed.R), np.asarray(seed.t)
    out = []
    for i in range(len(mask)):
        rvec, _ = cv2.Rodrigues(R[i])
        x0 = np.concatenate([[au[i], av[i], u0[i], v0[i]], rvec.ravel(), t[i], np.zeros(4)])
        w = np.ascontiguousarray(world[mask[i]])
        out.append((w, np.ascontiguousarray(pixels[i][mask[i]]).ravel(), x0))
    return out


def _unpack(x):
    K = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
    return K, x[4:7], x[7:10], x[10:14]


def residuals(x, world, pixels):
    """cv2.projectPoints(world) - pixels, flattened (u0, v0, u1, v1, ...)."""
    K, rvec, tvec, dist = _unpack(x)
    projected, _ = cv2.projectPoints(world, rvec, tvec, K, dist)
    return projected.ravel() - pixels


def jacobian(x, world, pixels):
    """Analytic d residuals / dx from cv2.projectPoints, reordered to x's order.

    OpenCV's columns are rvec (3), tvec (3), fx, fy, cx, cy, dist (4 here).
    """
    K, rvec, tvec, dist = _unpack(x)
    _, J = cv2.projectPoints(world, rvec, tvec, K, dist)
    return np.hstack([J[:, 6:10], J[:, 0:6], J[:, 10:14]])


def scipy_solve(problem, method):
    world, pixels, x0 = problem
    return least_squares(
        residuals,
        x0,
        jac=jacobian,
        args=(world, pixels),
        method=method,
        x_scale="jac",
        ftol=SCIPY_TOL,
        xtol=SCIPY_TOL,
        gtol=SCIPY_TOL,
    )


def scipy_loop(problems, method):
    return [scipy_solve(p, method) for p in problems]


def check_jacobian(problem):
    """Largest |analytic - central finite difference| relative to the largest |entry|."""
    world, pixels, x0 = problem
    J = jacobian(x0, world, pixels)
    fd = np.empty_like(J)
    for j in range(len(x0)):
        h = 1e-6 * max(1.0, abs(x0[j]))
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        fd[:, j] = (residuals(xp, world, pixels) - residuals(xm, world, pixels)) / (2 * h)
    return float(np.max(np.abs(J - fd)) / np.max(np.abs(J)))


# ---------------------------------------------------------------------------------- timing
def percentiles(x):
    """min, median, max of an integer array, as ints."""
    return [int(v) for v in np.percentile(np.asarray(x), [0, 50, 100], method="nearest")]


def bench_one(problem, C, *, quick):
    """Warm up, time and compare the implementations on the first C cameras of the rig."""
    world, pixels, mask, seed = subset(problem, C)
    problems = scipy_inputs(world, pixels, mask, seed)
    fns = {
        "mvcalib": lambda: mvcalib_refine(seed, world, pixels, mask),
        "mvcalib_eager": lambda: mvcalib_refine_eager(seed, world, pixels, mask),
    }
    for method in SCIPY_METHODS:
        fns[f"scipy_{method}"] = lambda method=method: scipy_loop(problems, method)

    # Warm-up: the first call of each compiles (JAX) or fills caches, and gives the results.
    first_call, outputs = {}, {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        outputs[name] = fn()
        first_call[name] = time.perf_counter() - t0

    if quick:  # the ratio's two sides by the median of three calls (each after an untimed one:
        # `measure`'s warm-up); trf, the slowest, once
        timed = ("mvcalib", "mvcalib_eager", "scipy_lm")
        stats = measure({k: fns[k] for k in timed}, min_time=0.0, rounds=3)
        stats |= measure({"scipy_trf": fns["scipy_trf"]}, min_time=0.0, rounds=1)
    else:
        stats = measure(fns, min_time=1.4, rounds=7)

    out = outputs["mvcalib"]
    n_visible = np.array([len(p[0]) for p in problems])
    rms = {"mvcalib": np.asarray(out.rms_after)}
    row = {
        "n_cameras": C,
        "n_points": int(world.shape[0]),
        "visible_fraction": float(np.mean(np.asarray(mask))),
        "rms_before_median_px": float(np.median(np.asarray(out.rms_before))),
        "mvcalib_ok": int(np.sum(np.asarray(out.ok))),
        "mvcalib_iterations_min_median_max": percentiles(out.iterations),
    }
    per_camera = {"mvcalib_iterations": np.asarray(out.iterations).tolist()}
    cam = out.cameras
    for method in SCIPY_METHODS:
        results = outputs[f"scipy_{method}"]
        name = f"scipy_{method}"
        rms[name] = np.array([np.sqrt(np.sum(r.fun**2) / n) for r, n in zip(results, n_visible)])
        x = np.array([r.x for r in results])
        rel = np.abs(rms[name] - rms["mvcalib"]) / rms[name]
        row[f"{name}_converged"] = int(sum(r.status > 0 for r in results))
        row[f"{name}_njev_min_median_max"] = percentiles([r.njev for r in results])
        row[f"{name}_nfev_min_median_max"] = percentiles([r.nfev for r in results])
        row[f"{name}_rms_max_rel_diff"] = float(np.max(rel))
        row[f"{name}_rms_worst_camera"] = int(np.argmax(rel))
        # The parameters should agree too (same minimum); focal length and k1, for the JSON.
        row[f"{name}_alpha_u_max_rel_diff"] = float(
            np.max(np.abs(np.asarray(cam.alpha_u) - x[:, 0]) / x[:, 0])
        )
        row[f"{name}_k1_max_abs_diff"] = float(
            np.max(np.abs(np.asarray(cam.dist[:, 0]) - x[:, 10]))
        )
        per_camera[f"{name}_njev"] = [int(r.njev) for r in results]
        per_camera[f"{name}_status"] = [int(r.status) for r in results]
    row["rms_after_median_px"] = float(np.median(rms["mvcalib"]))
    for name, st in stats.items():
        row[f"{name}_ms_per_camera"] = 1e3 * st["median"] / C
        row[f"{name}_ms_per_camera_q1_q3"] = [1e3 * st[q] / C for q in ("q1", "q3")]
        row[f"{name}_total_s"] = st["median"]
        row[f"{name}_repeats"] = st["repeats"]
        row[f"{name}_first_call_s"] = first_call[name]
    row["mvcalib_compile_s"] = first_call["mvcalib"] - stats["mvcalib"]["median"]
    row["mvcalib_eager_compile_s"] = first_call["mvcalib_eager"] - stats["mvcalib_eager"]["median"]
    eager = outputs["mvcalib_eager"]
    row["mvcalib_eager_cameras_max_rel_diff"] = float(
        np.max(np.abs(np.asarray(eager.cameras.alpha_u) / np.asarray(cam.alpha_u) - 1))
    )
    row["mvcalib_peak_mb_xla"] = xla_peak_mb(_refine_jit, seed, world, pixels, mask)
    for method in SCIPY_METHODS:  # a loop's peak is one camera's: 16 cameras show it
        row[f"scipy_{method}_peak_mb_tracemalloc"] = tracemalloc_peak_mb(
            lambda method=method: scipy_loop(problems[:16], method)
        )
    for method in SCIPY_METHODS:
        row[f"ratio_scipy_{method}_over_mvcalib"] = (
            stats[f"scipy_{method}"]["median"] / stats["mvcalib"]["median"]
        )
    row["ratio_scipy_lm_over_mvcalib_eager"] = (
        stats["scipy_lm"]["median"] / stats["mvcalib_eager"]["median"]
    )
    # Cost per step: a vmapped solve runs every camera for the batch's largest number of steps;
    # in slots refilled as cameras converge (on one CPU device) and in the loop each camera pays
    # its own.
    steps = np.asarray(out.iterations)
    queued = mc._refine.slots(C) < C  # noqa: SLF001 (how the solve is batched)
    batched_steps = int(steps.sum()) if queued else C * int(steps.max())
    row["mvcalib_batched_camera_steps"] = batched_steps
    row["mvcalib_us_per_camera_step"] = 1e6 * stats["mvcalib"]["median"] / batched_steps
    for method in SCIPY_METHODS:
        name = f"scipy_{method}"
        total_njev = int(sum(per_camera[f"{name}_njev"]))
        row[f"{name}_total_njev"] = total_njev
        row[f"{name}_us_per_njev"] = 1e6 * stats[name]["median"] / total_njev
        row[f"steps_ratio_mvcalib_over_{name}"] = batched_steps / total_njev
    per_camera.update({f"{name}_rms_px": values.tolist() for name, values in rms.items()})
    per_camera["mvcalib_ok"] = np.asarray(out.ok).tolist()
    return row, per_camera, problems


# ---------------------------------------------------------------------------------- report
def print_table(rows, jacobian_error):
    header = (
        f"{'C':>4} {'mvcalib':>9} {'lm':>8} {'trf':>8} {'lm/':>8} {'trf/':>8} "
        f"{'mvcalib':>8} {'lm':>7} {'trf':>7} {'1st call':>9}"
    )
    units = (
        f"{'':>4} {'ms/cam':>9} {'ms/cam':>8} {'ms/cam':>8} {'mvcalib':>8} {'mvcalib':>8} "
        f"{'total s':>8} {'total s':>7} {'total s':>7} {'s':>9}"
    )
    print(header)
    print(units)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['n_cameras']:>4} {r['mvcalib_ms_per_camera']:>9.2f} "
            f"{r['scipy_lm_ms_per_camera']:>8.2f} {r['scipy_trf_ms_per_camera']:>8.2f} "
            f"{r['ratio_scipy_lm_over_mvcalib']:>8.2f} {r['ratio_scipy_trf_over_mvcalib']:>8.2f} "
            f"{r['mvcalib_total_s']:>8.3f} {r['scipy_lm_total_s']:>7.3f} "
            f"{r['scipy_trf_total_s']:>7.3f} {r['mvcalib_first_call_s']:>9.1f}"
        )
    for r in rows:
        print(
            f"{r['n_cameras']:>4} {r['mvcalib_eager_ms_per_camera']:>9.2f}  <- mc.refine called "
            f"from Python: lm/mvcalib {r['ratio_scipy_lm_over_mvcalib_eager']:.2f}, "
            f"{r['mvcalib_eager_total_s']:.3f} s, 1st call {r['mvcalib_eager_first_call_s']:.1f} s"
        )
    print()
    header = (
        f"{'C':>4} {'RMS px':>13} {'max rel ΔRMS':>19} {'iterations min/med/max':>34} "
        f"{'converged':>16}"
    )
    units = (
        f"{'':>4} {'before':>6} {'after':>6} {'lm':>9} {'trf':>9} {'mvcalib':>10} {'lm':>11} "
        f"{'trf':>11} {'mvcalib':>7} {'lm':>4} {'trf':>3}"
    )
    print(header)
    print(units)
    print("-" * len(units))
    fmt = lambda v: "/".join(str(x) for x in v)  # noqa: E731
    for r in rows:
        print(
            f"{r['n_cameras']:>4} {r['rms_before_median_px']:>6.3f} "
            f"{r['rms_after_median_px']:>6.3f} {r['scipy_lm_rms_max_rel_diff']:>9.1e} "
            f"{r['scipy_trf_rms_max_rel_diff']:>9.1e} "
            f"{fmt(r['mvcalib_iterations_min_median_max']):>10} "
            f"{fmt(r['scipy_lm_njev_min_median_max']):>11} "
            f"{fmt(r['scipy_trf_njev_min_median_max']):>11} "
            f"{r['mvcalib_ok']:>7} {r['scipy_lm_converged']:>4} {r['scipy_trf_converged']:>3}"
        )
    print()
    header = (
        f"{'C':>4} {'paid steps':>14} {'Σ njev':>13} {'steps ratio':>12} {'µs per camera step':>27}"
    )
    units = (
        f"{'':>4} {'mvcalib':>14} {'lm':>6} {'trf':>6} {'lm':>5} {'trf':>6} "
        f"{'mvcalib':>9} {'lm':>8} {'trf':>8}"
    )
    print(header)
    print(units)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['n_cameras']:>4} {r['mvcalib_batched_camera_steps']:>14} "
            f"{r['scipy_lm_total_njev']:>6} {r['scipy_trf_total_njev']:>6} "
            f"{r['steps_ratio_mvcalib_over_scipy_lm']:>5.1f} "
            f"{r['steps_ratio_mvcalib_over_scipy_trf']:>6.1f} "
            f"{r['mvcalib_us_per_camera_step']:>9.0f} {r['scipy_lm_us_per_njev']:>8.0f} "
            f"{r['scipy_trf_us_per_njev']:>8.0f}"
        )
    print()
    print("mvcalib:    mc.refine (SecantLM, a camera at a time on a CPU; also covariance, report),")
    print("            in the caller's jax.jit; median wall time a call, a camera and in total.")
    print("            <-: the same call from Python (the rig in pieces, one per core; LLVM -O0")
    print("            below mvcalib._buckets.COMPACT camera-points).")
    print("lm, trf:    Python loop of scipy.optimize.least_squares(method=..., x_scale='jac',")
    print("            tol 1e-12) on cv2.projectPoints residuals with its analytic Jacobian")
    print(f"            (max rel. error vs central differences {jacobian_error:.0e}).")
    print("lm/mvcalib: ratio of the total times (> 1: mvcalib faster).")
    print("1st call:   wall time of mvcalib's first call per rig size (trace + compile + run).")
    print("RMS:        median over cameras of the reprojection RMS of the DLT seed and of the")
    print(
        "            refined cameras; max rel ΔRMS: largest |RMS_scipy - RMS_mvcalib| / RMS_scipy."
    )
    print("iterations: mvcalib's LM steps, SciPy's Jacobian evaluations (njev), over cameras.")
    print("converged:  mvcalib `ok`; SciPy `status > 0`.")
    worst = lambda key: max(r[f"scipy_{m}_{key}"] for r in rows for m in SCIPY_METHODS)  # noqa: E731
    print(
        f"parameters: mvcalib and SciPy agree to {worst('alpha_u_max_rel_diff'):.0e} in alpha_u "
        f"(relative)\n            and {worst('k1_max_abs_diff'):.0e} in k1 (absolute), at worst."
    )
    print("steps:      mvcalib pays Σ steps (one camera per step on a CPU; under vmap the batch's")
    print("            size x its max steps); the loop pays Σ njev. Ratio:")
    print("            their quotient; µs per camera step: median total time / those counts.")
    for r in rows:
        for method in SCIPY_METHODS:
            if r[f"scipy_{method}_rms_max_rel_diff"] > 1e-6:
                print(
                    f"note: C = {r['n_cameras']}: final RMS of mvcalib and scipy {method} differ "
                    f"by {r[f'scipy_{method}_rms_max_rel_diff']:.1e} (relative) at camera "
                    f"{r[f'scipy_{method}_rms_worst_camera']}: not the same minimum."
                )
        if r["mvcalib_ok"] < r["n_cameras"]:
            print(f"note: C = {r['n_cameras']}: only {r['mvcalib_ok']} mvcalib cameras ok.")


def summary_rows(rows) -> list[dict]:
    """The suite's summary: per path of the largest rig, time per camera, ratio, accuracy."""
    r = rows[-1]
    out = []
    for name in ("mvcalib", *(f"scipy_{m}" for m in SCIPY_METHODS)):
        rel = None if name == "mvcalib" else r[f"{name}_rms_max_rel_diff"]
        out.append(
            {
                "benchmark": "refinement",
                "setting": f"C={r['n_cameras']}, N={r['n_points']}",
                "path": "mvcalib refine" if name == "mvcalib" else f"scipy {name[6:]} loop",
                "unit": "camera",
                "us": 1e3 * r[f"{name}_ms_per_camera"],
                "peer_over_mvcalib": r[f"{name}_total_s"] / r["mvcalib_total_s"],
                "accuracy": f"RMS {r['rms_after_median_px']:.3f} px"
                if rel is None
                else f"max rel dRMS {rel:.0e}",
                "compile_s": r["mvcalib_compile_s"] if name == "mvcalib" else None,
                "peak_mb": r["mvcalib_peak_mb_xla"]
                if name == "mvcalib"
                else r[f"{name}_peak_mb_tracemalloc"],
                "peak_kind": "xla" if name == "mvcalib" else "tracemalloc",
                "x_bound": None,
            }
        )
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="256 cameras only, one round")
    args = parser.parse_args(argv)

    wall = time.perf_counter()
    info = machine_info("optimistix", "scipy") | {"opencv": cv2.__version__}
    print(
        f"mvcalib refinement benchmark ({'quick' if args.quick else 'full'}): jax {info['jax']} "
        f"on {info['jax_backend']}, scipy {info['scipy']}, opencv {info['opencv']}, "
        f"{info['cpu_count']} CPUs, float64\n"
    )
    sizes = N_CAMERAS[-1:] if args.quick else N_CAMERAS
    problem = make_problem(max(sizes))
    rows, per_camera, jacobian_error = [], None, None
    for C in sizes:
        row, per_camera, problems = bench_one(problem, C, quick=args.quick)
        rows.append(row)
        if jacobian_error is None:
            jacobian_error = check_jacobian(problems[0])
    print_table(rows, jacobian_error)
    for r in rows:
        print(
            f"C = {r['n_cameras']}: mvcalib compile (1st call - warm) "
            f"{r['mvcalib_compile_s']:.1f} s, "
            f"peak {r['mvcalib_peak_mb_xla']:.1f} MB (XLA memory analysis); scipy loops peak "
            + ", ".join(f"{m} {r[f'scipy_{m}_peak_mb_tracemalloc']:.1f} MB" for m in SCIPY_METHODS)
            + " (tracemalloc)"
        )
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")

    payload = write_results(
        results_path("refine.json"),
        "refine",
        quick=args.quick,
        machine=info,
        settings={
            "target": f"box_corner_grid({GRID})",
            "noise_px": NOISE,
            "image_size": list(IMAGE_SIZE),
            "fill": list(FILL),
            "true_distortion_k1_k2_p1_p2_k3": list(DISTORTION),
            "seed": "mc.calibrate (DLT), skew set to 0",
            "free_parameters": "alpha_u alpha_v u0 v0 rotation(3) translation(3) k1 k2 p1 p2",
            "mvcalib": "mc.refine defaults: mc.SecantLM(rtol=1e-5) via optx.least_squares",
            "scipy": f"least_squares x_scale='jac', ftol=xtol=gtol={SCIPY_TOL}",
            "scipy_jacobian": "analytic (cv2.projectPoints jacobian)",
            "scipy_jacobian_max_rel_error_vs_fd": jacobian_error,
            "dtype": "float64",
        },
        wall_time_s=wall,
        results=rows,
        per_camera={"n_cameras": rows[-1]["n_cameras"], **per_camera},
        summary=summary_rows(rows),
    )
    return payload


if __name__ == "__main__":
    main()
