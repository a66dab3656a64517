"""Benchmark: photos of a moving dot grid, labelled, against OpenCV's `findCirclesGrid`.

What is measured
----------------
OpenCV's own calibration target, its asymmetric circles grid (11 rows of 4 dots, 40 mm apart:
`mc.targets.dot_grid(11, 4, 40.0, asymmetric=True)`), photographed as a board moved through a
rig's volume: N rendered views of 1280 x 960 (`mc.synthetic.render`: blur 1 px, noise 3 grey
levels, an illumination gradient), each tilted 0-45 degrees, at any roll, the grid spanning
about half the image. Two sweeps of the same views:

- **clean**: every dot drawn, nothing else;
- **clutter**: 5 % of the dots hidden and 10 clutter blobs (streaks, specks, smudges, blots,
  rectangles) drawn beside and across the grid.

Each photo is labelled by
- **mvcalib**: `mc.detect_dots` then `mc.label_grid(..., asymmetric=True)` (what `observe_grid`
  does per photo), in this process;
- **OpenCV**: `cv2.findCirclesGrid(image, (4, 11), flags=cv2.CALIB_CB_ASYMMETRIC_GRID)` with its
  default blob detector.

A photo is *right* if every labelled dot lies within 1.5 px of its own dot's image (mvcalib:
its id; OpenCV, whose order is the grid's mirror image for these cameras, on the grid's +z
side as mvcalib's, as in tests/test_match.py: the nearest dot, each dot once), *flagged* if
the labeller returned nothing (`ok` False, or `findCirclesGrid` not found), *wrong*
otherwise. Accuracy: the RMS distance of the labelled centres from the exact centroids of the
dots' images (`mc.synthetic.ellipse_centres`), over the right photos. Times are per photo,
each photo timed once, the two labellers interleaved photo by photo.

Then the clutter sweep's photos through `mc.observe_grid` as one camera's recording, with
`workers=1` and with a worker a core (`os.cpu_count()`), wall time from the call to the
observations (worker start-up included).

`--quick` uses 12 views, `--smoke` 3.

Run from the repository root: `python benchmarks/grid_photos.py [--quick]`; results go to
`benchmarks/results/grid_photos.json`.
"""

from __future__ import annotations

import os
import time

import numpy as np

try:
    from ._common import opencv_run, results_path, write_results
except ImportError:  # run as a script
    from _common import opencv_run, results_path, write_results

import mvcalib as mc

ROWS, COLS, SPACING = 11, 4, 40.0
IMAGE_SIZE = (1280, 960)
K = (1100.0, 1100.0, 640.0, 480.0)  # alpha_u, alpha_v, u0, v0
MAX_TILT, RIGHT_PX = 45.0, 1.5


def view(seed: int, grid) -> mc.Camera:
    """A camera on the grid's +z side (its printed side for mvcalib), tilted up to `MAX_TILT`
    from its normal, at any roll, at a distance at which the grid spans about half the image."""
    rng = np.random.default_rng(seed)
    centre = grid.points.mean(0)
    tilt, azimuth, roll = np.radians(rng.uniform(0, MAX_TILT)), *rng.uniform(0, 2 * np.pi, 2)
    direction = np.array(
        [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
    )
    extent = np.ptp(grid.points[:, :2], axis=0).max()
    position = centre + direction * K[0] * extent / (0.5 * IMAGE_SIZE[1]) * rng.uniform(0.9, 1.1)
    z = (centre - position) / np.linalg.norm(centre - position)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    turn = np.array(
        [[np.cos(roll), -np.sin(roll), 0.0], [np.sin(roll), np.cos(roll), 0.0], [0, 0, 1.0]]
    )
    R = turn @ np.stack([x, y, z])
    return mc.Camera(*K, R, -R @ position)


def photos(n: int, grid, clutter: bool) -> list:
    """`(image, camera, hidden ids)` of the `n` views, with clutter or clean."""
    out = []
    for seed in range(n):
        camera = view(seed, grid)
        hidden = ()
        if clutter:
            rng = np.random.default_rng(1000 + seed)
            hidden = rng.choice(len(grid.points), int(0.05 * len(grid.points)), replace=False)
        image = mc.synthetic.render(camera, grid, IMAGE_SIZE, key=seed,
                                    clutter=10 if clutter else 0, hidden=hidden)  # fmt: skip
        out.append((image, camera, np.asarray(hidden, int)))
    return out


def score(centres, truth, seen):
    """`(verdict, squared errors)` of labelled `centres (M, 2)` (NaN where not labelled) against
    the dots' image centroids `truth (M, 2)`, of the dots `seen`."""
    error = np.linalg.norm(centres - truth, axis=1)
    labelled = np.isfinite(error)
    if not labelled.any():
        return "flagged", []
    right = np.all(error[labelled] < RIGHT_PX) and np.all(seen[labelled])
    return ("right" if right else "wrong"), list(error[labelled] ** 2)


def ours(image):
    labels = mc.label_grid(mc.detect_dots(image), ROWS, COLS, asymmetric=True)
    return np.where(labels.mask[:, None], labels.pixels, np.nan) if labels.ok else None


def opencv(image, truth):
    """findCirclesGrid's centres, each put at its nearest dot (its order is the grid's mirror
    image), or None."""
    import cv2

    found, centres = cv2.findCirclesGrid(image, (COLS, ROWS), flags=cv2.CALIB_CB_ASYMMETRIC_GRID)
    if not found:
        return None
    centres = centres.reshape(-1, 2).astype(np.float64)
    nearest = np.argmin(np.linalg.norm(centres[:, None] - truth[None], axis=-1), axis=1)
    out = np.full_like(truth, np.nan)
    out[nearest] = centres
    if len(set(nearest.tolist())) < len(centres):  # two centres at one dot: not a labelling
        out[:] = 1e9
    return out


def main(argv=None):
    mode, info = opencv_run(__doc__, argv, "3 views")
    n = 3 if mode == "smoke" else 12 if mode == "quick" else 60
    grid = mc.targets.dot_grid(ROWS, COLS, SPACING, asymmetric=True)
    wall = time.perf_counter()
    print(
        f"grid photos benchmark ({mode}): {n} views {IMAGE_SIZE[0]} x {IMAGE_SIZE[1]} of OpenCV's "
        f"asymmetric circles grid ({ROWS} x {COLS}), tilt 0-{MAX_TILT:g} deg; "
        f"OpenCV {info['opencv']}, {info['cpu_count']} CPUs\n"
    )
    ours(photos(1, grid, False)[0][0])  # (nothing compiles; imports and caches warm)
    results, sweeps = [], {}
    for clutter in (False, True):
        sweep = "clutter" if clutter else "clean"
        sweeps[sweep] = shots = photos(n, grid, clutter)
        stats = {name: dict(times=[], squares=[], right=0, flagged=0, wrong=0)
                 for name in ("mvcalib", "OpenCV")}  # fmt: skip
        for image, camera, hidden in shots:
            truth = mc.synthetic.ellipse_centres(camera, grid)
            seen = np.ones(len(truth), bool)
            seen[hidden] = False
            for name in stats:
                start = time.perf_counter()
                centres = ours(image) if name == "mvcalib" else opencv(image, truth)
                stats[name]["times"].append(time.perf_counter() - start)
                verdict, squares = score(
                    np.full_like(truth, np.nan) if centres is None else centres, truth, seen
                )
                stats[name][verdict] += 1
                stats[name]["squares"] += squares if verdict == "right" else []
        for name, s in stats.items():
            results.append(
                {
                    "sweep": sweep,
                    "labeller": name,
                    "ms_per_photo_median": 1e3 * float(np.median(s["times"])),
                    "right": s["right"],
                    "flagged": s["flagged"],
                    "wrong": s["wrong"],
                    "rms_px_right_views": float(np.sqrt(np.mean(s["squares"])))
                    if s["squares"]
                    else None,
                }
            )
    print(f"{'sweep':8} {'labeller':8} {'ms/photo':>9} {'right':>6} {'flagged':>8} {'wrong':>6} "
          f"{'RMS px':>7}")  # fmt: skip
    for r in results:
        rms = "-" if r["rms_px_right_views"] is None else f"{r['rms_px_right_views']:.3f}"
        print(f"{r['sweep']:8} {r['labeller']:8} {r['ms_per_photo_median']:9.1f} {r['right']:6d} "
              f"{r['flagged']:8d} {r['wrong']:6d} {rms:>7}")  # fmt: skip
    ms = {(r["sweep"], r["labeller"]): r["ms_per_photo_median"] for r in results}
    ratio = {sweep: ms[sweep, "OpenCV"] / ms[sweep, "mvcalib"] for sweep in sweeps}
    print(f"\nOpenCV's time over mvcalib's: {', '.join(f'{k} {v:.2f}x' for k, v in ratio.items())}")

    recording = [[image for image, _, _ in sweeps["clutter"]]]
    observed = {}
    for workers in sorted({1, os.cpu_count() or 1}):
        start = time.perf_counter()
        obs = mc.observe_grid(recording, grid, workers=workers, progress=False)
        observed[str(workers)] = {
            "seconds": time.perf_counter() - start,
            "photos_labelled": int(obs.mask.any(-1).sum()),
        }
        print(f"observe_grid of the {n} clutter photos, workers={workers}: "
              f"{observed[str(workers)]['seconds']:.2f} s")  # fmt: skip
    return write_results(
        results_path("grid_photos.json"),
        "grid_photos",
        quick=mode != "full",
        machine=info,
        settings={
            "n_views": n,
            "grid": [ROWS, COLS, SPACING],
            "image_size": list(IMAGE_SIZE),
            "max_tilt_deg": MAX_TILT,
            "right_px": RIGHT_PX,
        },
        wall_time_s=time.perf_counter() - wall,
        results=results,
        opencv_over_mvcalib_time=ratio,
        observe_grid_workers=observed,
    )


if __name__ == "__main__":
    main()
