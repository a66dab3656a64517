"""Benchmark: mvcalib's fisheye lens (Kannala–Brandt) against OpenCV's `cv2.fisheye`.

What is measured
----------------
Everything in float64, in one run; every ratio is OpenCV's time over mvcalib's from that run
(above 1: mvcalib faster). Warm times are medians of interleaved repeats (`_common.measure`);
"compile" is the first call's wall time minus a warm call's (trace + XLA compile, in this
process, with no persistent compilation cache unless JAX is configured with one: the JSON
records `jax_compilation_cache_dir`).

1. **Projection and unprojection by one camera** (fx 410, fy 405, centre (655, 482), zero skew,
   k = (-0.03, 0.004, -6e-4, 3e-5), a rotated and shifted pose), 1M points (`--smoke`: 2000):
   - projection of points up to 85 degrees off the optical axis, at 0.5-5 m:
     `jax.jit(lambda camera, world: camera.project(world))` (the camera an argument, not a
     constant) against `cv2.fisheye.projectPoints(world, rvec, tvec, K, D)`;
     max |difference| of the pixels.
   - unprojection of the pixels of points up to 80 degrees off axis back to ideal pinhole
     pixels: `jax.jit(lambda camera, p: mc.undistort_points(camera, p))` (20 Newton
     iterations, its default) against `cv2.fisheye.undistortPoints(pixels, K, D, P=K)` with
     its default criteria (10 iterations, eps 1e-8) and with tight ones ("tight": 50
     iterations, eps 1e-15); max |difference| from mvcalib's and from the exact ideal pixels
     (K applied to x/z, y/z).
   Peak memory: XLA's memory analysis of the compiled call, `tracemalloc`'s peak of one OpenCV
   call.
2. **Planar calibration**: 20 views (`--smoke`: 6) of a 9 x 12 board of 3 cm squares, 0.25-0.5
   m away, its centre up to 70 degrees off axis, seen by a 190 degree lens (fx 300, fy 301,
   centre (641.3, 478.2), k = (-0.02, 0.003, -4e-4, 2e-5), 1280 x 960 px) within 88 degrees of
   the axis (`cv2.fisheye` cannot take rays beyond 90) and inside the image, 0.3 px noise (the
   setting of tests/test_fisheye.py::test_planar_fisheye_calibration_equals_opencv_fisheye).
   - mvcalib: `mc.calibrate_planar(board, pixels, mask, lens="fisheye", image_size=(1280,
     960))`, from the image size alone; its first call in this process (fresh compile) and
     warm. Also (not in `--smoke`) its closed-form start alone, `refine=False`, whose share of
     the warm time shows where that time goes.
   - OpenCV: `cv2.fisheye.calibrate` with the true K as the intrinsic guess and D = 0,
     `CALIB_USE_INTRINSIC_GUESS | CALIB_RECOMPUTE_EXTRINSIC | CALIB_FIX_SKEW`, criteria 200
     iterations / 1e-12. Both RMS, and the largest differences of K and D.
   - OpenCV without the guess (its own start, f = max(w, h) / pi): its RMS, or its error.
3. **Refinement of many fisheye cameras**: 256 cameras (`--smoke`: 8), each with its own
   intrinsics (f 280-320 px, centre within 10 px of (640, 480), k = (-0.03, 0.004, -6e-4, 3e-5)
   scaled by 0.5-1.5) and pose, each seeing its own cloud of 100 3-D points up to 85 degrees off
   its axis at 0.5-5 m, 0.3 px noise. `cv2.fisheye.calibrate` cannot refine one camera from one
   view of a 3-D cloud: it initialises the pose from a homography (a plane), and on these
   clouds, from the 2 % focal seed below, it raises (InitExtrinsics) or ends at an RMS of
   hundreds of pixels for most cameras (one full run: 120 of 256 raised, 12 reached mvcalib's
   RMS; counted in the JSON, `cv2_fisheye_calibrate_on_3d_cloud`). So the timed comparison is
   **pose only**, the intrinsics known (the true K and D):
   - mvcalib: `mc.refine(seed, world, pixels, fix="intrinsics", distortion=())` for all
     cameras in one call (`jax.jit`), seed = true intrinsics, pose turned by ~0.01 rad per axis
     and shifted by ~1 cm.
   - OpenCV: a Python loop of `cv2.fisheye.solvePnP(world, pixels, K, D, rvec0, tvec0,
     useExtrinsicGuess=True, SOLVEPNP_ITERATIVE)` per camera from the same pose seed. It
     undistorts the pixels and minimises the error on the normalised image plane, not in
     pixels: its RMS (from `cv2.fisheye.projectPoints` of its pose) can only be >= mvcalib's
     pixel least squares; the table gives the relative difference.
   - mvcalib alone (no OpenCV peer): the full refinement, `mc.refine(seed, world, pixels)` of
     all 14 parameters (focal, centre, pose, k1-k4) from a seed with focal lengths 2 % off,
     zero distortion and the same pose error.
   Times per camera; RMS = sqrt(sum of squared residuals / points) per camera.

`--quick`: the same sizes, short timing rounds, the 3-D-cloud check of cv2.fisheye.calibrate on
32 cameras (under a minute). `--smoke`: toy sizes, one round (the test that the script works).

Run from the repository root: `python -m benchmarks.fisheye [--quick | --smoke]` (or
`python benchmarks/fisheye.py`); results go to `benchmarks/results/fisheye.json`.
"""

from __future__ import annotations

import time

import jax

jax.config.update("jax_enable_x64", True)

import cv2  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

try:
    from ._common import (
        first_and_warm,
        measure,
        opencv_run,
        results_path,
        tracemalloc_peak_mb,
        write_results,
        xla_peak_mb,
    )
except ImportError:  # run as a script
    from _common import (
        first_and_warm,
        measure,
        opencv_run,
        results_path,
        tracemalloc_peak_mb,
        write_results,
        xla_peak_mb,
    )

import mvcalib as mc  # noqa: E402

NOISE = 0.3  # px
N_POINTS = {"smoke": 2000, "quick": 1_000_000, "full": 1_000_000}
N_VIEWS = {"smoke": 6, "quick": 20, "full": 20}
N_CAMERAS = {"smoke": 8, "quick": 256, "full": 256}
CLOUD_CHECK = {"smoke": 8, "quick": 32, "full": 256}  # cameras for cv2.fisheye.calibrate on 3-D
POINTS_PER_CAMERA = 100
# (min_time s, rounds) of `measure`, per section
TIMING = {
    "smoke": {"project": (0.0, 1), "calibrate": (0.0, 1), "refine": (0.0, 1)},
    "quick": {"project": (1.0, 2), "calibrate": (1.0, 2), "refine": (1.0, 3)},
    "full": {"project": (12.0, 6), "calibrate": (6.0, 6), "refine": (7.0, 7)},
}
TIGHT = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 50, 1e-15)
CALIB_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)

# ---------------------------------------------------------------------------------- data
# (copied from tests/test_fisheye.py, not imported from the tests)
DIST = np.array([-0.03, 0.004, -0.0006, 0.00003])
IMAGE = (1280, 960)
# a 190 degree lens on a 1280 x 960 sensor: 95 degrees off axis land 481 px from the centre
LENS = dict(alpha_u=300.0, alpha_v=301.0, u0=641.3, v0=478.2, dist=[-0.02, 0.003, -4e-4, 2e-5])
BOARD = 0.03 * np.stack(np.meshgrid(np.arange(12.0), np.arange(9.0)), -1).reshape(-1, 2)
BOARD = np.concatenate([BOARD - BOARD.mean(0), np.zeros((len(BOARD), 1))], 1)  # 9 x 12, 3 cm


def directions(n, max_degrees, seed):
    """Unit rays up to `max_degrees` off the optical axis, uniform in angle and azimuth, and
    depths of 0.5-5 m."""
    rng = np.random.default_rng(seed)
    theta = np.deg2rad(rng.uniform(0.0, max_degrees, n))
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    ray = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    return ray, rng.uniform(0.5, 5.0, n)


def one_camera():
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([0.1, 0.2, 0.3])
    K = np.array([[410.0, 0.0, 655.0], [0.0, 405.0, 482.0], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(rvec)[0]
    return mc.Camera.from_matrices(K, R, tvec, dist=DIST, lens="fisheye"), K, rvec, tvec


def world_of(camera, camera_points):
    """World points whose camera coordinates are `camera_points`: `R^T (x - t)`."""
    return (camera_points - np.asarray(camera.t)) @ np.asarray(camera.R)


def board_views(n_views, max_degrees, field, seed):
    """A 9 x 12 board 0.25-0.5 m away, its centre up to `max_degrees` off the optical axis,
    tilted, seen by the 190 degree lens up to `field` degrees off axis; 0.3 px of noise."""
    rng = np.random.default_rng(seed)
    pixels, masks = [], []
    while len(pixels) < n_views:
        a, phi = np.deg2rad(rng.uniform(0.0, max_degrees)), rng.uniform(0.0, 2.0 * np.pi)
        direction = np.array([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])
        z = direction @ cv2.Rodrigues(rng.normal(0.0, 0.35, 3))[0].T  # the board's normal
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        spin = cv2.Rodrigues(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))[0]
        R, t = np.stack([x, np.cross(z, x), z], 1) @ spin, direction * rng.uniform(0.25, 0.5)
        camera = mc.Camera(R=R, t=t, lens="fisheye", **LENS)
        xc = BOARD @ R.T + t
        angle = np.degrees(np.arctan2(np.linalg.norm(xc[:, :2], axis=1), xc[:, 2]))
        p = np.asarray(camera.project(BOARD))
        seen = (angle < field) & np.all((p >= 0) & (p <= np.array(IMAGE) - 1), axis=1)
        if seen.sum() >= 60:
            pixels.append(p + NOISE * rng.standard_normal(p.shape))
            masks.append(seen)
    return np.where(np.array(masks)[..., None], pixels, np.nan), np.array(masks)


def camera_clouds(n_cameras, n_points, seed=0):
    """`n_cameras` fisheye cameras with their own intrinsics and poses, each seeing its own
    `n_points` 3-D points up to 85 degrees off its axis: (true cameras, world (C, N, 3), noisy
    pixels (C, N, 2), pose seed (rotation, translation))."""
    rng = np.random.default_rng(seed)
    R = np.array([cv2.Rodrigues(r)[0] for r in rng.normal(0.0, 1.0, (n_cameras, 3))])
    t = rng.uniform(-1.0, 1.0, (n_cameras, 3))
    focal = rng.uniform(280.0, 320.0, (2, n_cameras))
    centre = np.array([640.0, 480.0])[:, None] + rng.uniform(-10.0, 10.0, (2, n_cameras))
    dist = DIST * rng.uniform(0.5, 1.5, (n_cameras, 1))
    cameras = mc.Camera(*focal, *centre, R, t, dist=dist, lens="fisheye")
    camera_points = []
    for c in range(n_cameras):
        ray, depth = directions(n_points, 85.0, seed=1000 * seed + c)
        camera_points.append(ray * depth[:, None])
    world = np.einsum("cnj,cjk->cnk", np.array(camera_points) - t[:, None], R)  # R^T (x - t)
    pixels = np.asarray(cameras.project(world))
    pixels = pixels + NOISE * rng.standard_normal(pixels.shape)
    turn = np.array([cv2.Rodrigues(r)[0] for r in rng.normal(0.0, 0.01, (n_cameras, 3))])
    pose = (R @ turn, t + rng.normal(0.0, 0.01, (n_cameras, 3)))
    return cameras, world, pixels, pose


def K_of(cameras, c):
    return np.array(
        [
            [float(cameras.alpha_u[c]), 0.0, float(cameras.u0[c])],
            [0.0, float(cameras.alpha_v[c]), float(cameras.v0[c])],
            [0.0, 0.0, 1.0],
        ]
    )


def cv2_message(error):
    """An OpenCV error's function and reason, on one line."""
    lines = [x.strip().lstrip("> ").strip() for x in str(error).strip().splitlines()]
    head = lines[0].split(" error: ")[-1]
    return (head + (" " + " ".join(lines[1:]) if len(lines) > 1 else ""))[:400]


def rms_px(residuals):
    """sqrt(sum of squared residuals / points) over the last two axes of (..., N, 2)."""
    return np.sqrt(np.sum(residuals**2, axis=(-1, -2)) / residuals.shape[-2])


def row(benchmark, setting, path, st, count, reference, **extra):
    """One timed path: per-item microseconds, the ratio to its mvcalib `reference` stats."""
    out = {
        "benchmark": benchmark,
        "setting": setting,
        "path": path,
        "median_s": st["median"],
        "q1_s": st["q1"],
        "q3_s": st["q3"],
        "repeats": st["repeats"],
        "items": count,
        "us_per_item": 1e6 * st["median"] / count,
        "peer_over_mvcalib": st["median"] / reference["median"],
    }
    return out | extra


# ---------------------------------------------------------------------------------- 1
def bench_projection(mode):
    n = N_POINTS[mode]
    camera, K, rvec, tvec = one_camera()
    ray, depth = directions(n, 85.0, seed=0)
    world = world_of(camera, ray * depth[:, None])
    cv_world = np.ascontiguousarray(world[:, None])
    jworld = jnp.asarray(world)
    # (`jax.jit(camera.project)` cannot hash the bound method of an equinox Module: the camera
    # is an argument of the compiled call, as it would be in a user's jitted function)
    project = jax.jit(lambda camera, world: camera.project(world))
    # unprojection: the pixels of points up to 80 degrees off axis, and their exact ideal pixels
    ray80, depth80 = directions(n, 80.0, seed=1)
    pixels = np.asarray(camera.project(world_of(camera, ray80 * depth80[:, None])))  # (eager)
    ideal_true = (ray80[:, :2] / ray80[:, 2:]) @ K[:2, :2].T + K[:2, 2]
    cv_pixels = np.ascontiguousarray(pixels[:, None])
    jpixels = jnp.asarray(pixels)
    undistort = jax.jit(lambda camera, p: mc.undistort_points(camera, p))

    fns = {
        "mvcalib project": lambda: jax.block_until_ready(project(camera, jworld)),
        "cv2.fisheye.projectPoints": lambda: cv2.fisheye.projectPoints(
            cv_world, rvec, tvec, K, DIST
        ),
        "mvcalib undistort_points": lambda: jax.block_until_ready(undistort(camera, jpixels)),
        "cv2.fisheye.undistortPoints": lambda: cv2.fisheye.undistortPoints(cv_pixels, K, DIST, P=K),
        "cv2.fisheye.undistortPoints tight": lambda: cv2.fisheye.undistortPoints(
            cv_pixels, K, DIST, P=K, criteria=TIGHT
        ),
    }
    first, warm, out = {}, {}, {}
    for name, fn in fns.items():
        jitted = name.startswith("mvcalib")
        first[name], warm[name], out[name] = first_and_warm(fn, warm_calls=1 if jitted else 0)
    stats = measure(fns, min_time=TIMING[mode]["project"][0], rounds=TIMING[mode]["project"][1])
    ours_px = np.asarray(out["mvcalib project"])
    cv_px = out["cv2.fisheye.projectPoints"][0][:, 0]
    ours_ideal = np.asarray(out["mvcalib undistort_points"])
    peak = {
        "mvcalib project": xla_peak_mb(project, camera, jworld),
        "mvcalib undistort_points": xla_peak_mb(undistort, camera, jpixels),
    }
    for name in fns:
        if not name.startswith("mvcalib"):
            peak[name] = tracemalloc_peak_mb(fns[name])

    setting = f"{n:,} pts"
    rows = [
        row(
            "fisheye projection",
            setting + ", <=85°",
            name,
            stats[name],
            n,
            stats["mvcalib project"],
            max_abs_diff_vs_mvcalib_px=float(np.max(np.abs(p - ours_px))),
        )
        for name, p in (("mvcalib project", ours_px), ("cv2.fisheye.projectPoints", cv_px))
    ]
    for name in [k for k in fns if "ndistort" in k]:
        ideal = ours_ideal if name.startswith("mvcalib") else out[name][:, 0]
        rows.append(
            row(
                "fisheye unprojection",
                setting + ", <=80°",
                name,
                stats[name],
                n,
                stats["mvcalib undistort_points"],
                max_abs_diff_vs_mvcalib_px=float(np.max(np.abs(ideal - ours_ideal))),
                max_abs_error_vs_exact_px=float(np.max(np.abs(ideal - ideal_true))),
            )
        )
    for r in rows:
        jitted = r["path"].startswith("mvcalib")
        r["compile_s"] = first[r["path"]] - warm[r["path"]] if jitted else None
        r["peak_mb"] = peak[r["path"]]
        r["peak_kind"] = "xla" if jitted else "tracemalloc"
    return rows, {"n_points": n, "radius_px_max": float(np.abs(pixels - K[:2, 2]).max())}


# ---------------------------------------------------------------------------------- 2
def bench_calibration(mode):
    n_views = N_VIEWS[mode]
    pixels, mask = board_views(n_views, 70.0, 88.0, seed=0)
    objects = [np.ascontiguousarray(BOARD[m][:, None]) for m in mask]
    images = [np.ascontiguousarray(p[m][:, None]) for p, m in zip(pixels, mask)]
    true_K = np.array(
        [[LENS["alpha_u"], 0.0, LENS["u0"]], [0.0, LENS["alpha_v"], LENS["v0"]], [0.0, 0.0, 1.0]]
    )
    flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW

    def ours():
        return jax.block_until_ready(
            mc.calibrate_planar(BOARD, pixels, mask, lens="fisheye", image_size=IMAGE)
        )

    def theirs():
        return cv2.fisheye.calibrate(
            objects,
            images,
            IMAGE,
            true_K.copy(),
            np.zeros(4),
            flags=flags | cv2.fisheye.CALIB_USE_INTRINSIC_GUESS,
            criteria=CALIB_CRITERIA,
        )

    def seed_only():  # the closed-form start alone: where the warm time goes
        return jax.block_until_ready(
            mc.calibrate_planar(BOARD, pixels, mask, lens="fisheye", image_size=IMAGE, refine=False)
        )

    first, warm, result = first_and_warm(ours, warm_calls=1)
    cv_first, _, cv_out = first_and_warm(theirs, warm_calls=0)
    fns = {"mvcalib": ours, "cv2": theirs}
    if mode != "smoke":
        seed_first, seed_warm, seed = first_and_warm(seed_only, warm_calls=1)
        fns["seed"] = seed_only
    stats = measure(fns, min_time=TIMING[mode]["calibrate"][0], rounds=TIMING[mode]["calibrate"][1])
    cv_rms, K, D = cv_out[0], cv_out[1], cv_out[2].ravel()
    try:  # OpenCV's own start: f = max(w, h) / pi
        no_guess = cv2.fisheye.calibrate(
            objects, images, IMAGE, np.eye(3), np.zeros(4), flags=flags, criteria=CALIB_CRITERIA
        )
        no_guess = {"rms_px": float(no_guess[0]), "K": no_guess[1].tolist(), "error": None}
    except cv2.error as e:
        no_guess = {"rms_px": None, "K": None, "error": cv2_message(e)}
    rms = float(result.rms)
    setting = f"{n_views} views, 9x12"
    timed = lambda path, key, **extra: row(  # noqa: E731
        "fisheye calibration", setting, path, stats[key], 1, stats["mvcalib"], **extra
    )
    rows = [
        timed(
            "mvcalib calibrate_planar",
            "mvcalib",
            **{
                "first_call_s": first,
                "warm_call_s": warm,
                "compile_s": first - warm,
                "peer_over_mvcalib": 1.0,
                "rms_px": rms,
                "ok": bool(np.asarray(result.ok).all()) and bool(result.converged),
                "K": np.asarray(result.K).tolist(),
                "dist": np.asarray(result.dist).tolist(),
            },
        ),
        timed(
            "cv2.fisheye.calibrate (K guess)",
            "cv2",
            **{
                "first_call_s": cv_first,
                "compile_s": None,
                "rms_px": float(cv_rms),
                "rms_rel_diff_vs_mvcalib": abs(cv_rms - rms) / cv_rms,
                "K": K.tolist(),
                "dist": D.tolist(),
                "K_max_rel_diff_vs_mvcalib": float(
                    np.max(np.abs(np.asarray(result.K) - K)[[0, 1, 0, 1], [0, 1, 2, 2]] / K[0, 0])
                ),
                "dist_max_abs_diff_vs_mvcalib": float(np.max(np.abs(np.asarray(result.dist) - D))),
            },
        ),
    ]
    if "seed" in fns:
        rows.append(
            timed(
                "mvcalib calibrate_planar seed",
                "seed",
                **{
                    "first_call_s": seed_first,
                    "warm_call_s": seed_warm,
                    "compile_s": seed_first - seed_warm,
                    # the closed-form seed's share of the full calibration, not a peer's ratio
                    "peer_over_mvcalib": None,
                    "share_of_calibrate_planar": stats["seed"]["median"]
                    / stats["mvcalib"]["median"],
                    "rms_px": float(seed.rms),
                },
            )
        )
    truth = np.array([LENS["alpha_u"], LENS["alpha_v"], LENS["u0"], LENS["v0"]])
    found = np.asarray(result.K)[[0, 1, 0, 1], [0, 1, 2, 2]]
    extra = {
        "n_views": n_views,
        "points": int(mask.sum()),
        "mvcalib_K_error_vs_truth_px": (found - truth).tolist(),
        "cv2_without_guess": no_guess,
    }
    return rows, extra


# ---------------------------------------------------------------------------------- 3
@jax.jit
def refine_pose(seed, world, pixels):
    return mc.refine(seed, world, pixels, fix="intrinsics", distortion=())


@jax.jit
def refine_all(seed, world, pixels):
    return mc.refine(seed, world, pixels)


def cv2_pose_loop(inputs):
    out = []
    for world, pixels, K, D, rvec0, tvec0 in inputs:
        _, rvec, tvec = cv2.fisheye.solvePnP(
            world, pixels, K, D, rvec0.copy(), tvec0.copy(), True, cv2.SOLVEPNP_ITERATIVE
        )
        out.append((rvec, tvec))
    return out


def normalised_cost(inputs, poses):
    """Per camera, the sum of squared errors on the normalised image plane (what
    cv2.fisheye.solvePnP minimises): the undistorted pixels against x/z, y/z of the points in the
    camera frame of each pose."""
    cost = []
    for (world, pixels, K, D, _, _), (R, t) in zip(inputs, poses):
        ideal = cv2.fisheye.undistortPoints(pixels, K, D, criteria=TIGHT)[:, 0]
        xc = world[:, 0] @ R.T + t
        cost.append(float(np.sum((xc[:, :2] / xc[:, 2:] - ideal) ** 2)))
    return np.array(cost)


def bench_refinement(mode):
    C = N_CAMERAS[mode]
    full_refine = mode != "smoke"  # (one compilation fewer in the smoke run)
    truth, world, pixels, (R0, t0) = camera_clouds(C, POINTS_PER_CAMERA)
    jworld, jpixels = jnp.asarray(world), jnp.asarray(pixels)
    dist = np.asarray(truth.dist)
    pose_seed = mc.Camera(
        truth.alpha_u, truth.alpha_v, truth.u0, truth.v0, R0, t0, dist=dist, lens="fisheye"
    )
    full_seed = mc.Camera(
        truth.alpha_u * 1.02, truth.alpha_v * 1.02, truth.u0, truth.v0, R0, t0, lens="fisheye"
    )
    inputs = [
        (
            np.ascontiguousarray(world[c][:, None]),
            np.ascontiguousarray(pixels[c][:, None]),
            K_of(truth, c),
            dist[c],
            cv2.Rodrigues(R0[c])[0],
            t0[c].reshape(3, 1).copy(),
        )
        for c in range(C)
    ]
    fns = {
        "mvcalib refine pose": lambda: jax.block_until_ready(
            refine_pose(pose_seed, jworld, jpixels)
        ),
        "cv2.fisheye.solvePnP loop": lambda: cv2_pose_loop(inputs),
    }
    if full_refine:
        fns["mvcalib refine all 14"] = lambda: jax.block_until_ready(
            refine_all(full_seed, jworld, jpixels)
        )
    first, warm, out = {}, {}, {}
    for name, fn in fns.items():
        jitted = name.startswith("mvcalib")
        first[name], warm[name], out[name] = first_and_warm(fn, warm_calls=1 if jitted else 0)
    stats = measure(fns, min_time=TIMING[mode]["refine"][0], rounds=TIMING[mode]["refine"][1])

    # RMS: mvcalib's report, and cv2's poses projected by cv2.fisheye.projectPoints
    pose = out["mvcalib refine pose"]
    rms_ours = np.asarray(pose.rms_after)
    rms_cv = np.array(
        [
            rms_px(cv2.fisheye.projectPoints(w, rv, tv, K, D)[0][:, 0] - p[:, 0])
            for (w, p, K, D, _, _), (rv, tv) in zip(inputs, out["cv2.fisheye.solvePnP loop"])
        ]
    )
    rms_check = rms_px(np.asarray(pose.cameras.project(jworld)) - pixels)
    rel = (rms_cv - rms_ours) / rms_ours
    R_cv = np.array([cv2.Rodrigues(rv)[0] for rv, _ in out["cv2.fisheye.solvePnP loop"]])
    t_cv = np.array([tv.ravel() for _, tv in out["cv2.fisheye.solvePnP loop"]])
    R_ours, t_ours = np.asarray(pose.cameras.R), np.asarray(pose.cameras.t)
    # each at its own optimum: cv2's pose has the lower cost on the normalised plane
    cost_cv = normalised_cost(inputs, zip(R_cv, t_cv))
    cost_ours = normalised_cost(inputs, zip(R_ours, t_ours))
    setting = f"C={C} x {POINTS_PER_CAMERA} pts"
    base = stats["mvcalib refine pose"]
    iterations = lambda out: [  # noqa: E731
        int(v) for v in np.percentile(np.asarray(out.iterations), [0, 50, 100], method="nearest")
    ]
    rows = [
        row(
            "fisheye refinement",
            setting + ", pose",
            "mvcalib refine pose",
            base,
            C,
            base,
            rms_median_px=float(np.median(rms_ours)),
            rms_before_median_px=float(np.median(np.asarray(pose.rms_before))),
            ok=int(np.sum(np.asarray(pose.ok))),
            iterations_min_median_max=iterations(pose),
            rms_report_vs_projection_max_abs_diff_px=float(np.max(np.abs(rms_check - rms_ours))),
        ),
        row(
            "fisheye refinement",
            setting + ", pose",
            "cv2.fisheye.solvePnP loop",
            stats["cv2.fisheye.solvePnP loop"],
            C,
            base,
            rms_median_px=float(np.median(rms_cv)),
            rms_rel_diff_vs_mvcalib_min_median_max=[
                float(v) for v in np.percentile(rel, [0, 50, 100])
            ],
            cameras_with_rms_below_mvcalib=int(np.sum(rel < -1e-9)),
            cameras_with_normalised_cost_at_most_mvcalib=int(
                np.sum(cost_cv <= cost_ours * (1 + 1e-9))
            ),
            rotation_max_diff_vs_mvcalib_rad=float(
                np.max([np.linalg.norm(cv2.Rodrigues(a @ b.T)[0]) for a, b in zip(R_cv, R_ours)])
            ),
            translation_max_diff_vs_mvcalib_m=float(np.max(np.linalg.norm(t_cv - t_ours, axis=1))),
        ),
    ]
    if full_refine:
        full = out["mvcalib refine all 14"]
        rows.append(
            row(
                "fisheye refinement",
                setting + ", all",
                "mvcalib refine all 14",
                stats["mvcalib refine all 14"],
                C,
                base,
                rms_median_px=float(np.median(np.asarray(full.rms_after))),
                rms_before_median_px=float(np.median(np.asarray(full.rms_before))),
                ok=int(np.sum(np.asarray(full.ok))),
                iterations_min_median_max=iterations(full),
                alpha_u_max_abs_error_vs_truth_px=float(
                    np.max(np.abs(np.asarray(full.cameras.alpha_u - truth.alpha_u)))
                ),
                k1_max_abs_error_vs_truth=float(
                    np.max(np.abs(np.asarray(full.cameras.dist[:, 0] - truth.dist[:, 0])))
                ),
                # no OpenCV peer: the ratio is the pose-only refinement's time over this one's
                mvcalib_pose_over_full=base["median"] / stats["mvcalib refine all 14"]["median"],
            )
        )
        rows[2]["peer_over_mvcalib"] = None
    peaks = {
        "mvcalib refine pose": (xla_peak_mb(refine_pose, pose_seed, jworld, jpixels), "xla"),
        "cv2.fisheye.solvePnP loop": (
            tracemalloc_peak_mb(fns["cv2.fisheye.solvePnP loop"]),
            "tracemalloc",
        ),
    }
    if full_refine:
        peaks["mvcalib refine all 14"] = (
            xla_peak_mb(refine_all, full_seed, jworld, jpixels),
            "xla",
        )
    for r in rows:
        jitted = r["path"].startswith("mvcalib")
        r["compile_s"] = first[r["path"]] - warm[r["path"]] if jitted else None
        r["first_call_s"] = first[r["path"]]
        r["peak_mb"], r["peak_kind"] = peaks[r["path"]]
    rms_full = np.asarray(out["mvcalib refine all 14"].rms_after) if full_refine else None
    cloud = cloud_check(inputs[: CLOUD_CHECK[mode]], full_seed, rms_full)
    return rows, {"n_cameras": C, "cv2_fisheye_calibrate_on_3d_cloud": cloud}


def cloud_check(inputs, full_seed, rms_full):
    """cv2.fisheye.calibrate on one view of a 3-D cloud per camera, from the 2 % focal seed (the
    14-parameter problem): how many raise, how many reach mvcalib's RMS (within 1 %)."""
    flags = (
        cv2.fisheye.CALIB_USE_INTRINSIC_GUESS
        | cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC
        | cv2.fisheye.CALIB_FIX_SKEW
    )
    raised, same, rms = 0, 0, []
    errors = set()
    for c, (world, pixels, *_) in enumerate(inputs):
        K = K_of(full_seed, c)
        try:
            r = cv2.fisheye.calibrate(
                [world], [pixels], IMAGE, K, np.zeros(4), flags=flags, criteria=CALIB_CRITERIA
            )[0]
        except cv2.error as e:
            raised += 1
            errors.add(cv2_message(e))
            continue
        rms.append(float(r))
        if rms_full is not None:
            same += abs(r - rms_full[c]) <= 0.01 * rms_full[c]
    return {
        "cameras": len(inputs),
        "raised": raised,
        "finished": len(rms),
        "finished_at_mvcalib_rms_within_1pct": None if rms_full is None else int(same),
        "finished_rms_median_px": float(np.median(rms)) if rms else None,
        "errors": sorted(errors),
    }


# ---------------------------------------------------------------------------------- report
def print_rows(rows):
    header = (
        f"{'path':<44}{'median':>11}{'per item':>12}{'peer/':>9}{'compile':>9}{'peak MB':>9}"
        "  accuracy"
    )
    print(header)
    print(f"{'':<44}{'ms':>11}{'µs':>12}{'mvcalib':>9}{'s':>9}")
    print("-" * (len(header) + 30))
    for r in rows:
        ratio = "—" if r["peer_over_mvcalib"] is None else f"{r['peer_over_mvcalib']:.2f}"
        comp = "—" if r.get("compile_s") is None else f"{r['compile_s']:.2f}"
        peak = r.get("peak_mb")
        peak = "—" if peak is None else f"{peak:.1f}" + ("x" if r["peak_kind"] == "xla" else "t")
        per = r.get("us_per_item", 1e6 * r["median_s"])
        print(
            f"{r['path'][:43]:<44}{1e3 * r['median_s']:>11.3f}{per:>12.4g}{ratio:>9}{comp:>9}"
            f"{peak:>9}  {accuracy(r)}"
        )


def accuracy(r):
    if "max_abs_error_vs_exact_px" in r:
        return (
            f"max|Δ| vs mvcalib {r['max_abs_diff_vs_mvcalib_px']:.1e} px, "
            f"vs exact {r['max_abs_error_vs_exact_px']:.1e} px"
        )
    if "max_abs_diff_vs_mvcalib_px" in r:
        return f"max|Δ| vs mvcalib {r['max_abs_diff_vs_mvcalib_px']:.1e} px"
    if "rms_rel_diff_vs_mvcalib_min_median_max" in r:
        lo, med, hi = r["rms_rel_diff_vs_mvcalib_min_median_max"]
        return f"RMS {r['rms_median_px']:.4f} px, rel ΔRMS {lo:.0e}/{med:.0e}/{hi:.0e}"
    if "rms_median_px" in r:
        return f"RMS {r['rms_median_px']:.4f} px (median), {r['ok']} ok"
    if "share_of_calibrate_planar" in r:
        return (
            f"RMS {r['rms_px']:.4f} px (seed); {r['share_of_calibrate_planar']:.0%} of "
            "calibrate_planar's time"
        )
    if "rms_rel_diff_vs_mvcalib" in r:
        return f"RMS {r['rms_px']:.6f} px, rel ΔRMS {r['rms_rel_diff_vs_mvcalib']:.0e}"
    return f"RMS {r['rms_px']:.6f} px"


def summary_rows(rows):
    """The suite's summary table (benchmarks/run.py): time per point / camera, ratio, accuracy."""
    out = []
    for r in rows:
        if "share_of_calibrate_planar" in r:  # a part of mvcalib's path, not a path
            continue
        pointwise = r["benchmark"] in ("fisheye projection", "fisheye unprojection")
        unit = "point" if pointwise else "camera"
        us = r.get("us_per_item", 1e6 * r["median_s"])
        out.append(
            {
                "benchmark": r["benchmark"],
                "setting": r["setting"],
                "path": r["path"],
                "unit": unit,
                "us": us,
                "peer_over_mvcalib": 1.0
                if r["peer_over_mvcalib"] is None
                else r["peer_over_mvcalib"],
                "accuracy": accuracy(r)[:60],
                "compile_s": r.get("compile_s"),
                "peak_mb": r.get("peak_mb"),
                "peak_kind": r.get("peak_kind"),
                "x_bound": None,
            }
        )
    return out


def main(argv=None) -> dict:
    mode, info = opencv_run(__doc__, argv, "toy sizes, one round")
    wall = time.perf_counter()
    print(
        f"fisheye benchmark ({mode}): mvcalib against cv2.fisheye (OpenCV {cv2.__version__}), "
        f"jax {info['jax']} on {info['jax_backend']}, {info['cpu_count']} CPUs, float64\n"
    )
    parts, extra = {}, {}
    for name, bench in (
        ("projection", bench_projection),
        ("calibration", bench_calibration),
        ("refinement", bench_refinement),
    ):
        start = time.perf_counter()
        parts[name], extra[name] = bench(mode)
        extra[name]["wall_time_s"] = time.perf_counter() - start
        print(f"== {name} ({extra[name]['wall_time_s']:.1f} s)")
        print_rows(parts[name])
        print()

    cal = parts["calibration"]
    ng = extra["calibration"]["cv2_without_guess"]
    print(
        f"calibration: mvcalib first call {cal[0]['first_call_s']:.2f} s (compile "
        f"{cal[0]['compile_s']:.2f} s), warm {1e3 * cal[0]['median_s']:.1f} ms; cv2 "
        f"{1e3 * cal[1]['median_s']:.1f} ms; K within {cal[1]['K_max_rel_diff_vs_mvcalib']:.0e} "
        f"(rel.), D within {cal[1]['dist_max_abs_diff_vs_mvcalib']:.0e}; cv2 without a guess: "
        + (f"RMS {ng['rms_px']:.4g} px" if ng["error"] is None else f"raised {ng['error']}")
    )
    ref = parts["refinement"]
    cloud = extra["refinement"]["cv2_fisheye_calibrate_on_3d_cloud"]
    pnp = ref[1]
    lo, med, hi = pnp["rms_rel_diff_vs_mvcalib_min_median_max"]
    print(
        "refinement: pose only (intrinsics known), mvcalib against cv2.fisheye.solvePnP, "
        f"{pnp['us_per_item'] / 1e3:.3f} against {ref[0]['us_per_item'] / 1e3:.3f} ms/camera; "
        f"cv2's pixel RMS above mvcalib's by {lo:.1%} / {med:.1%} / {hi:.1%} (min/median/max),\n"
        f"  {pnp['cameras_with_normalised_cost_at_most_mvcalib']} of {pnp['items']} cv2 poses "
        "at or below mvcalib's cost on the normalised plane (the objective solvePnP minimises)"
    )
    finished = cloud["finished"]
    print(
        f"  cv2.fisheye.calibrate on one view of a 3-D cloud (the 14-parameter problem): "
        f"{cloud['raised']} of {cloud['cameras']} cameras raised, {finished} finished"
        + (f" at median RMS {cloud['finished_rms_median_px']:.4g} px" if finished else "")
        + (
            ""
            if cloud["finished_at_mvcalib_rms_within_1pct"] is None
            else f", {cloud['finished_at_mvcalib_rms_within_1pct']} at mvcalib's RMS (within 1 %)"
        )
    )
    if len(ref) > 2:
        print(
            f"  mvcalib full 14-parameter refine {ref[2]['us_per_item'] / 1e3:.3f} ms/camera "
            f"(compile {ref[2]['compile_s']:.1f} s), RMS {ref[2]['rms_before_median_px']:.1f} -> "
            f"{ref[2]['rms_median_px']:.4f} px (median), {ref[2]['ok']} of {ref[2]['items']} ok"
        )
    rows = [r for name in parts for r in parts[name]]
    ratios = {
        "projection_cv2_over_mvcalib": parts["projection"][1]["peer_over_mvcalib"],
        "unprojection_cv2_default_over_mvcalib": parts["projection"][3]["peer_over_mvcalib"],
        "unprojection_cv2_tight_over_mvcalib": parts["projection"][4]["peer_over_mvcalib"],
        "calibration_cv2_over_mvcalib_warm": cal[1]["peer_over_mvcalib"],
        "calibration_cv2_over_mvcalib_first_call": cal[1]["median_s"] / cal[0]["first_call_s"],
        "pose_refinement_cv2_loop_over_mvcalib": ref[1]["peer_over_mvcalib"],
    }
    print(
        "\npeer/mvcalib: OpenCV's time over mvcalib's (> 1: mvcalib faster). "
        + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items())
    )
    wall = time.perf_counter() - wall
    print(f"total wall time {wall:.1f} s")
    return write_results(
        results_path("fisheye.json"),
        "fisheye",
        quick=mode != "full",
        machine=info,
        settings={
            "mode": mode,
            "dtype": "float64",
            "noise_px": NOISE,
            "projection": {
                "n_points": N_POINTS[mode],
                "max_degrees": 85.0,
                "unprojection_max_degrees": 80.0,
                "dist": DIST.tolist(),
            },
            "calibration": {
                "n_views": N_VIEWS[mode],
                "board": "9x12, 0.03 m",
                "lens": LENS,
                "image_size": list(IMAGE),
                "field_degrees": 88.0,
                "cv2_flags": "USE_INTRINSIC_GUESS|RECOMPUTE_EXTRINSIC|FIX_SKEW",
                "cv2_criteria": "200 iterations, eps 1e-12",
            },
            "refinement": {
                "n_cameras": N_CAMERAS[mode],
                "points_per_camera": POINTS_PER_CAMERA,
                "max_degrees": 85.0,
                "compared": "pose only: mc.refine(fix='intrinsics', distortion=()) "
                "vs cv2.fisheye.solvePnP(useExtrinsicGuess=True) loop",
                "seed": "pose turned N(0, 0.01) rad per axis, shifted N(0, 0.01) m; "
                "full refine: focal x1.02, zero distortion",
            },
            "timing_min_time_rounds": TIMING[mode],
        },
        ratios=ratios,
        details=extra,
        wall_time_s=wall,
        results=rows,
        summary=summary_rows(rows),
    )


if __name__ == "__main__":
    main()
