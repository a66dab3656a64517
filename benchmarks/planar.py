"""Benchmark: planar (Zhang) calibration of one pinhole camera, mvcalib against OpenCV.

What is measured
----------------
Everything in one run; every ratio is OpenCV's time over mvcalib's from that run (above 1:
mvcalib faster). Warm times are medians of interleaved repeats (`_common.measure`, mvcalib and
OpenCV in turn at each V); "compile" is mvcalib's first call's wall time minus a warm call's
(trace + XLA compile, in this process, with no persistent compilation cache unless JAX is
configured with one: the JSON records `jax_compilation_cache_dir`).

**Data**: one camera of `mc.synthetic.board_rig(jax.random.key(3), n_cameras=1,
n_frames=200, noise=0.3)` in float64 (focal lengths 1175.4 / 1165.1 px, centre (626.1, 415.8),
k1 -0.154, k2 0.058; the rig's images are 1280 x 800 px), a 9 x 12 board of 108 corners 6 cm
apart, 0.3 px of Gaussian noise. The views: the frames in which the camera sees at least 20
corners, the first V of them, for V = 10, 20, 40 and 80 (`--smoke`: V = 6). Both calibrate
from the same views and the same visible corners.

- **mvcalib**: `mc.calibrate_planar(target, pixels[views], mask[views], distortion=("k1",
  "k2", "p1", "p2"))` (float64 arrays, the hidden corners masked), `jax.block_until_ready` on
  its result: Zhang's closed form from the homographies, then Levenberg–Marquardt over the
  intrinsics, k1 k2 p1 p2 and every view's pose. Its first call for each V in this process
  (`jax.clear_caches()` before it, so that each V compiles afresh, as a new process would)
  and warm.
- **OpenCV**: per view, float32 arrays of the visible corners (`target[mask[v]]`,
  `pixels[v][mask[v]]`, what `cv2.calibrateCamera` takes), then, in the timed call, its closed
  form start `K0 = cv2.initCameraMatrix2D(objects, images, (1280, 800))` (the rig's image size)
  and `cv2.calibrateCamera(objects, images, (1280, 800), K0, None,
  flags=CALIB_USE_INTRINSIC_GUESS | CALIB_FIX_K3)` with its default criteria (30 iterations, eps
  DBL_EPSILON): the same model (k1 k2 p1 p2, zero skew). Its first call at each V is also
  timed.

Reported per V and path: the warm median (and quartiles), the first call, OpenCV's time over
mvcalib's, the RMS reprojection error over every visible corner (mvcalib's `result.rms`,
OpenCV's returned RMS; OpenCV's from float32 pixels, which moves it by a few 1e-7 px: given
the same float32-rounded pixels, mvcalib's RMS is OpenCV's to 1e-10 px at V = 10), the
relative difference of the focal lengths between the two (largest of alpha_u, alpha_v), each
one's focal-length error against the truth (relative, largest of the two) and principal-point
error (px, distance), and whether every view is OK in mvcalib (`result.ok.all()`).

`--quick`: short timing rounds (under a minute). `--smoke`: V = 6 only, one round (the test that
the script works).

Run from the repository root: `python -m benchmarks.planar [--quick | --smoke]` (or
`python benchmarks/planar.py`); results go to `benchmarks/results/planar.json`.
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import cv2  # noqa: E402
import numpy as np  # noqa: E402

try:
    from ._common import first_and_warm, measure, opencv_run, results_path, write_results
except ImportError:  # run as a script
    from _common import first_and_warm, measure, opencv_run, results_path, write_results

import mvcalib as mc  # noqa: E402

NOISE = 0.3  # px
N_FRAMES = 200
MIN_CORNERS = 20  # a view: a frame in which the camera sees at least this many corners
VIEWS = {"smoke": (6,), "quick": (10, 20, 40, 80), "full": (10, 20, 40, 80)}
# (min_time s, rounds) of `measure`, per V
TIMING = {"smoke": (0.0, 1), "quick": (1.0, 2), "full": (6.0, 6)}
DISTORTION = ("k1", "k2", "p1", "p2")
CV2_FLAGS = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3


# ---------------------------------------------------------------------------------- data
def board_views():
    """(target (N, 3), pixels (F, N, 2), mask (F, N), the frames with >= MIN_CORNERS corners,
    the true camera, the rig's image size)."""
    rig = mc.synthetic.board_rig(jax.random.key(3), n_cameras=1, n_frames=N_FRAMES, noise=NOISE)
    target = np.asarray(rig.target)
    pixels = np.asarray(rig.pixels)[0]
    mask = np.asarray(rig.mask)[0]
    frames = np.flatnonzero(mask.sum(-1) >= MIN_CORNERS)
    return target, pixels, mask, frames, rig.cameras[0], tuple(rig.image_size)


def intrinsics(K):
    """(alpha_u, alpha_v, u0, v0) of a 3 x 3 K."""
    K = np.asarray(K)
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def errors(found, truth):
    """The focal lengths' relative errors (alpha_u, alpha_v) and the principal point's distance
    (px) of `found` against `truth`, both (alpha_u, alpha_v, u0, v0)."""
    focal = (found[:2] - truth[:2]) / truth[:2]
    return focal, float(np.linalg.norm(found[2:] - truth[2:]))


def row(setting, path, st, reference, **extra):
    """One timed path at one V: its stats, the ratio to mvcalib's `reference` stats."""
    out = {
        "benchmark": "planar calibration",
        "setting": setting,
        "path": path,
        "median_s": st["median"],
        "q1_s": st["q1"],
        "q3_s": st["q3"],
        "repeats": st["repeats"],
        "peer_over_mvcalib": st["median"] / reference["median"],
    }
    return out | extra


# ---------------------------------------------------------------------------------- bench
def bench_views(n_views, data, truth, timing):
    """mvcalib's calibrate_planar and OpenCV's calibrateCamera on the first `n_views` views."""
    target, pixels, mask, frames, _, image = data
    idx = frames[:n_views]
    if len(idx) < n_views:
        raise ValueError(f"{len(idx)} frames see >= {MIN_CORNERS} corners; {n_views} needed")
    view_pixels, view_mask = pixels[idx], mask[idx]
    objects = [np.ascontiguousarray(target[m], np.float32) for m in view_mask]
    images = [np.ascontiguousarray(p[m], np.float32) for p, m in zip(view_pixels, view_mask)]

    def ours():
        return jax.block_until_ready(
            mc.calibrate_planar(target, view_pixels, view_mask, distortion=DISTORTION)
        )

    def theirs():
        K0 = cv2.initCameraMatrix2D(objects, images, image)
        return cv2.calibrateCamera(objects, images, image, K0, None, flags=CV2_FLAGS)

    jax.clear_caches()  # this V's first call compiles afresh
    first, warm, result = first_and_warm(ours, warm_calls=1)
    cv_first, _, cv_out = first_and_warm(theirs, warm_calls=0)
    stats = measure({"mvcalib": ours, "cv2": theirs}, min_time=timing[0], rounds=timing[1])

    ours_k = intrinsics(result.K)
    cv_rms, cv_K, cv_dist = float(cv_out[0]), cv_out[1], cv_out[2].ravel()
    cv_k = intrinsics(cv_K)
    ours_focal, ours_centre = errors(ours_k, truth)
    cv_focal, cv_centre = errors(cv_k, truth)
    rms = float(result.rms)
    setting = f"V={n_views} views, 9x12"
    common = {"n_views": n_views, "points": int(view_mask.sum())}
    rows = [
        row(
            setting,
            "mvcalib calibrate_planar",
            stats["mvcalib"],
            stats["mvcalib"],
            **common,
            first_call_s=first,
            warm_call_s=warm,
            compile_s=first - warm,
            rms_px=rms,
            ok=bool(np.asarray(result.ok).all()),
            converged=bool(result.converged),
            iterations=int(result.iterations),
            intrinsics=ours_k.tolist(),
            dist=np.asarray(result.dist).tolist(),
            focal_rel_error_vs_truth=ours_focal.tolist(),
            principal_point_error_vs_truth_px=ours_centre,
        ),
        row(
            setting,
            "cv2.calibrateCamera",
            stats["cv2"],
            stats["mvcalib"],
            **common,
            first_call_s=cv_first,
            compile_s=None,
            rms_px=cv_rms,
            rms_rel_diff_vs_mvcalib=(cv_rms - rms) / rms,
            focal_max_rel_diff_vs_mvcalib=float(np.max(np.abs(cv_k[:2] - ours_k[:2]) / ours_k[:2])),
            intrinsics=cv_k.tolist(),
            dist=cv_dist.tolist(),
            focal_rel_error_vs_truth=cv_focal.tolist(),
            principal_point_error_vs_truth_px=cv_centre,
        ),
    ]
    return rows


# ---------------------------------------------------------------------------------- report
def accuracy(r):
    focal = np.max(np.abs(r["focal_rel_error_vs_truth"]))
    truth = f"vs truth f {focal:.1e}, c {r['principal_point_error_vs_truth_px']:.2f} px"
    if "rms_rel_diff_vs_mvcalib" in r:
        return (
            f"RMS {r['rms_px']:.6f} px, Δf vs mvcalib {r['focal_max_rel_diff_vs_mvcalib']:.0e}; "
            + truth
        )
    return f"RMS {r['rms_px']:.6f} px{'' if r['ok'] else ' NOT all ok'}; " + truth


def short_accuracy(r):
    """`accuracy` in at most 60 characters, for the suite's table."""
    if "rms_rel_diff_vs_mvcalib" in r:
        return f"RMS {r['rms_px']:.6f} px, Δf vs mvcalib {r['focal_max_rel_diff_vs_mvcalib']:.0e}"
    focal = np.max(np.abs(r["focal_rel_error_vs_truth"]))
    return (
        f"RMS {r['rms_px']:.6f} px, vs truth f {focal:.1e} c "
        f"{r['principal_point_error_vs_truth_px']:.2f} px"
    )[:60]


def print_header():
    header = (
        f"{'V':>4}  {'path':<26}{'median':>9}{'q1-q3':>15}{'peer/':>9}{'first':>8}"
        f"{'compile':>9}  accuracy"
    )
    print(header)
    print(f"{'':>4}  {'':<26}{'ms':>9}{'ms':>15}{'mvcalib':>9}{'s':>8}{'s':>9}")
    print("-" * (len(header) + 60))


def print_rows(rows):
    for r in rows:
        comp = "—" if r.get("compile_s") is None else f"{r['compile_s']:.2f}"
        spread = f"{1e3 * r['q1_s']:.2f}-{1e3 * r['q3_s']:.2f}"
        print(
            f"{r['n_views']:>4}  {r['path'][:25]:<26}{1e3 * r['median_s']:>9.2f}{spread:>15}"
            f"{r['peer_over_mvcalib']:>9.2f}{r['first_call_s']:>8.2f}{comp:>9}  {accuracy(r)}",
            flush=True,
        )


def summary_rows(rows):
    """The suite's summary table (benchmarks/run.py): time per calibration, ratio, accuracy."""
    return [
        {
            "benchmark": r["benchmark"],
            "setting": r["setting"],
            "path": r["path"],
            "unit": "camera",
            "us": 1e6 * r["median_s"],
            "peer_over_mvcalib": r["peer_over_mvcalib"],
            "accuracy": short_accuracy(r),
            "compile_s": r.get("compile_s"),
            "peak_mb": None,
            "peak_kind": None,
            "x_bound": None,
        }
        for r in rows
    ]


def main(argv=None) -> dict:
    mode, info = opencv_run(__doc__, argv, "V = 6 only, one round")
    wall = time.perf_counter()
    print(
        f"planar benchmark ({mode}): mvcalib calibrate_planar against cv2.calibrateCamera "
        f"(OpenCV {cv2.__version__}), jax {info['jax']} on {info['jax_backend']}, "
        f"{info['cpu_count']} CPUs, float64\n"
    )
    data = board_views()
    camera, rig_image = data[4], data[5]
    truth = np.array([float(camera.alpha_u), float(camera.alpha_v), float(camera.u0),
                      float(camera.v0)])  # fmt: skip
    rows, walls = [], {}
    print_header()
    for n_views in VIEWS[mode]:
        start = time.perf_counter()
        new = bench_views(n_views, data, truth, TIMING[mode])
        walls[n_views] = time.perf_counter() - start
        print_rows(new)
        rows += new
    print(
        "\npeer/mvcalib: OpenCV's time over mvcalib's (> 1: mvcalib faster); first: the first "
        "call at this V\n  (mvcalib: after jax.clear_caches(), so trace + compile + run); "
        "Δf: largest relative difference\n  of the focal lengths; vs truth: largest relative "
        "focal-length error, principal point's distance."
    )
    ratios = {
        f"V={r['n_views']}": r["peer_over_mvcalib"]
        for r in rows
        if r["path"] == "cv2.calibrateCamera"
    }
    wall = time.perf_counter() - wall
    print(f"total wall time {wall:.1f} s")
    return write_results(
        results_path("planar.json"),
        "planar",
        quick=mode != "full",
        machine=info,
        settings={
            "mode": mode,
            "dtype": "float64 (mvcalib), float32 points (OpenCV)",
            "noise_px": NOISE,
            "data": f"mc.synthetic.board_rig(jax.random.key(3), n_cameras=1, "
            f"n_frames={N_FRAMES}, noise={NOISE}), camera 0",
            "rig_image_size": list(rig_image),
            "board": "9x12 corners, 0.06 m",
            "views": list(VIEWS[mode]),
            "view_rule": f"the first V frames with >= {MIN_CORNERS} visible corners",
            "frames_available": int(len(data[3])),
            "truth": {
                "alpha_u": truth[0],
                "alpha_v": truth[1],
                "u0": truth[2],
                "v0": truth[3],
                "dist": np.asarray(camera.dist).tolist(),
            },
            "mvcalib_call": f"calibrate_planar(target, pixels, mask, distortion={DISTORTION})",
            "cv2_call": "initCameraMatrix2D, then calibrateCamera(K0, None, "
            "flags=USE_INTRINSIC_GUESS|FIX_K3), default criteria",
            "timing_min_time_rounds": TIMING[mode],
        },
        ratios_cv2_over_mvcalib=ratios,
        wall_time_per_V_s={str(k): v for k, v in walls.items()},
        wall_time_s=wall,
        results=rows,
        summary=summary_rows(rows),
    )


if __name__ == "__main__":
    main()
