"""Benchmark: mvcalib's dot detector against OpenCV's SimpleBlobDetector on rendered views.

What is measured
----------------
N random views of the 19-dot box-corner target (`mvcalib.synthetic.random_rig`, cameras 0..N-1
of one rig), rendered by `mvcalib._render.render` at 1000 x 1100 pixels with 1 px Gaussian blur,
3 grey levels of sensor noise and a 30 % illumination gradient: dark dots on a white sheet,
drawn as the exact perspective images of discs (4 x 4 supersampling, 16 x 16 on dot rims).

- **mvcalib**: `detect_dots(image)` with its defaults: the paper's binarise / invert /
  background / subtract / label pipeline, shape filter, and grey-level-weighted centroids.
- **OpenCV**: `cv2.SimpleBlobDetector` configured for dark dots of this size and shape: dark
  blobs (`blobColor=0`), area 12 px to 2 % of the image (as mvcalib), circularity >= 0.2,
  inertia ratio >= 0.05 and convexity >= 0.8 (dots seen up to ~85 degrees off their normal are
  ellipses up to ~11:1, so the defaults of 0.8 circularity and 0.1 inertia would drop them),
  thresholds 10..220 in steps of 10. Its keypoints are the mean over thresholds of binary
  contour centroids.

Per image, each detector is timed once (`time.perf_counter`, the two interleaved image by
image); the table gives the median and the quartiles. Accuracy: every detection is matched to
the nearest true dot within 3 px. Dots whose images touch another's (closer than 3 px) are left
out of the counts since no blob detector can split them. Reported: centroid RMS (2-D, px) and
median error against the ellipse centres (the centroid of each dot's image, the right reference
for a centroid detector), RMS against the projected true centres (which differ from the former
by the perspective bias, also reported), and found / missed / spurious counts. OpenCV's RMS is
dominated by outliers (elongated dots split over thresholds), hence the median beside it.

The labelling of the detected dots (`mc.label_dots`: which blob is which dot id) is timed
after mvcalib's detector, and checked against the dot ids known from the rendering.

First call: mvcalib's warm-up call (on a view not timed; nothing is jit-compiled). Peak
memory: `tracemalloc`'s peak during one detection of the first view, per detector (NumPy
buffers and Python objects; not OpenCV's internal C++ allocations).

`--quick` uses 3 views instead of 100; `--smoke` 2.

Results are printed as a table and written to `benchmarks/results/detect.json`.

Run from the repository root: `python benchmarks/detect.py [--quick]`.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

try:
    from ._common import machine_info, results_path, tracemalloc_peak_mb, write_results
except ImportError:  # run as a script
    from _common import machine_info, results_path, tracemalloc_peak_mb, write_results

import mvcalib as mc  # noqa: E402
from mvcalib import detect_dots  # noqa: E402
from mvcalib.synthetic import ellipse_centres, render, true_centres, visible_dots  # noqa: E402

IMAGE_SIZE = (1000, 1100)  # width, height
RENDER = dict(blur_sigma=1.0, noise_sigma=3.0, gradient=0.3)
SEED = 0
MATCH_PX = 3.0
MIN_GAP_PX = 3.0


def opencv_detector():
    import cv2

    params = cv2.SimpleBlobDetector_Params()
    params.filterByColor, params.blobColor = True, 0
    params.minThreshold, params.maxThreshold, params.thresholdStep = 10, 220, 10
    params.filterByArea = True
    params.minArea, params.maxArea = 12, 0.02 * IMAGE_SIZE[0] * IMAGE_SIZE[1]
    params.filterByCircularity, params.minCircularity = True, 0.2
    params.filterByInertia, params.minInertiaRatio = True, 0.05
    params.filterByConvexity, params.minConvexity = True, 0.8
    detector = cv2.SimpleBlobDetector_create(params)

    def detect(image):
        points = detector.detect(image)
        return np.array([p.pt for p in points], dtype=float).reshape(-1, 2)

    return detect, cv2.__version__


def score(found, ellipse, true, drawn, apart):
    """Matches, errors and counts of one view for one detector."""
    d = np.linalg.norm(ellipse[:, None] - found[None], axis=-1) if len(found) else None
    errors_e, errors_t = [], []
    n_found = n_missed = 0
    for i in np.flatnonzero(apart):
        j = int(d[i].argmin()) if d is not None else -1
        if j >= 0 and d[i, j] < MATCH_PX:
            n_found += 1
            errors_e.append(found[j] - ellipse[i])
            errors_t.append(found[j] - true[i])
        else:
            n_missed += 1
    # Spurious: detections that are no dot. A blob of two touching dots has its centroid between
    # them, so anything within 30 px of a touching dot counts as neither found nor spurious.
    n_spurious = 0
    if d is not None:
        near = (d[apart] < MATCH_PX).any(0) | (d[drawn & ~apart] < 30).any(0)
        n_spurious = int((~near).sum())
    return errors_e, errors_t, n_found, n_missed, n_spurious


def summarise(name, times, errors_e, errors_t, found, missed, spurious):
    rms = lambda e: float(np.sqrt(np.mean(np.sum(np.square(e), axis=1)))) if e else float("nan")  # noqa: E731
    q1, median, q3 = np.percentile(np.asarray(times) * 1e3, [25, 50, 75])
    return {
        "detector": name,
        "ms_per_image_median": float(median),
        "ms_per_image_quartiles": [float(q1), float(q3)],
        "rms_vs_ellipse_px": rms(errors_e),
        "rms_vs_true_px": rms(errors_t),
        "median_error_vs_ellipse_px": float(np.median(np.linalg.norm(errors_e, axis=1)))
        if errors_e
        else float("nan"),
        "max_error_vs_ellipse_px": float(np.max(np.linalg.norm(errors_e, axis=1)))
        if errors_e
        else float("nan"),
        "found": int(found),
        "missed": int(missed),
        "spurious": int(spurious),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 views instead of 100")
    parser.add_argument("--smoke", action="store_true", help="2 views")
    args = parser.parse_args(argv)
    n_views = 2 if args.smoke else 3 if args.quick else 100

    wall = time.perf_counter()
    target = mc.targets.box_corner()
    opencv, cv2_version = opencv_detector()
    info = machine_info("scikit-image") | {"opencv": cv2_version}
    print(
        f"dot detection benchmark ({'quick' if args.quick else 'full'}): {n_views} views "
        f"{IMAGE_SIZE[0]} x {IMAGE_SIZE[1]}, blur 1 px, noise 3 grey levels, gradient 0.3; "
        f"scikit-image {info['scikit-image']}, OpenCV {cv2_version}, {info['cpu_count']} CPUs\n"
    )
    rig = mc.synthetic.random_rig(jax.random.key(SEED), n_views, image_size=IMAGE_SIZE)
    last = {}

    def ours(image):
        last["detection"] = detect_dots(image)
        return last["detection"].centroids

    detectors = {"mvcalib detect_dots": ours}
    labelling = dict(times=[], correct=0, flagged=0, wrong=0)
    detectors["OpenCV SimpleBlobDetector"] = opencv
    stats = {name: dict(times=[], e=[], t=[], found=0, missed=0, spurious=0) for name in detectors}
    bias, touching = [], 0
    warm_image = render(rig.cameras[0], target, IMAGE_SIZE, key=0, **RENDER)
    start = time.perf_counter()
    detect_dots(warm_image)  # warm-up
    first_call = time.perf_counter() - start
    peak = {name: tracemalloc_peak_mb(lambda d=d: d(warm_image)) for name, d in detectors.items()}
    for i in range(n_views):
        camera = rig.cameras[i]
        image = render(camera, target, IMAGE_SIZE, key=SEED * 1000 + i, **RENDER)
        ellipse, true = ellipse_centres(camera, target), true_centres(camera, target)
        drawn = visible_dots(camera, target, IMAGE_SIZE)
        apart = visible_dots(camera, target, IMAGE_SIZE, min_gap=MIN_GAP_PX)
        touching += int(apart.sum() < drawn.sum())
        bias.append(np.linalg.norm(ellipse[apart] - true[apart], axis=1))
        for name, detect in detectors.items():
            start = time.perf_counter()
            found = detect(image)
            stats[name]["times"].append(time.perf_counter() - start)
            e, t, n_found, n_missed, n_spurious = score(found, ellipse, true, drawn, apart)
            s = stats[name]
            s["e"] += e
            s["t"] += t
            s["found"] += n_found
            s["missed"] += n_missed
            s["spurious"] += n_spurious
            if detect is ours:  # then label the dots: which blob is which dot id
                start = time.perf_counter()
                labels = mc.label_dots(last["detection"], target)
                labelling["times"].append(time.perf_counter() - start)
                d = np.linalg.norm(ellipse[:, None] - last["detection"].centroids[None], axis=-1)
                truth = np.where(d.min(1) < MATCH_PX, d.argmin(1), -1)
                if not labels.ok:
                    labelling["flagged"] += 1
                elif (labels.index[labels.mask] == truth[labels.mask]).all():
                    labelling["correct"] += 1
                else:
                    labelling["wrong"] += 1

    rows = [
        summarise(name, s["times"], s["e"], s["t"], s["found"], s["missed"], s["spurious"])
        for name, s in stats.items()
    ]
    bias = np.concatenate(bias)
    header = (
        f"{'detector':<28}{'ms/image':>10}{'RMS vs ellipse':>16}{'median':>8}{'RMS vs true':>13}"
        f"{'found':>7}{'missed':>8}{'spurious':>10}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r['detector']:<28}{r['ms_per_image_median']:>10.1f}{r['rms_vs_ellipse_px']:>16.4f}"
            f"{r['median_error_vs_ellipse_px']:>8.4f}{r['rms_vs_true_px']:>13.4f}{r['found']:>7}{r['missed']:>8}{r['spurious']:>10}"
        )
    print(
        f"\nperspective bias |ellipse centre - projected centre| over {len(bias)} dots: RMS "
        f"{np.sqrt(np.mean(bias**2)):.4f} px, median {np.median(bias):.4f}, max {bias.max():.4f}"
    )
    print(f"{touching} of {n_views} views have touching dot images (those dots not counted)")
    label_ms = 1e3 * np.percentile(labelling["times"], [25, 50, 75])
    print(
        f"labelling (mc.label_dots after detect_dots): {label_ms[1]:.0f} ms/image median "
        f"(quartiles {label_ms[0]:.0f}-{label_ms[2]:.0f}); views labelled correctly "
        f"{labelling['correct']}, flagged {labelling['flagged']}, wrong {labelling['wrong']}"
    )
    print(
        f"first call (warm-up) {first_call:.2f} s; peak (tracemalloc, one detection): "
        + ", ".join(f"{name} {mb:.0f} MB" for name, mb in peak.items())
    )
    wall = time.perf_counter() - wall
    print(f"total wall time {wall:.1f} s")

    mine, cv = rows
    summary = [
        {
            "benchmark": "detection",
            "setting": f"{n_views} views {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}",
            "path": r["detector"],
            "unit": "image",
            "us": 1e3 * r["ms_per_image_median"],
            "peer_over_mvcalib": r["ms_per_image_median"] / mine["ms_per_image_median"],
            "accuracy": f"RMS {r['rms_vs_ellipse_px']:.3f} px, missed {r['missed']}, "
            f"spurious {r['spurious']}",
            "compile_s": None,  # nothing is jit-compiled: the first call is in the JSON
            "peak_mb": peak[r["detector"]],
            "peak_kind": "tracemalloc",
            "x_bound": None,
        }
        for r in (mine, cv)
    ]
    return write_results(
        results_path("detect.json"),
        "detect",
        quick=args.quick,
        machine=info,
        settings={
            "n_views": n_views,
            "image_size": list(IMAGE_SIZE),
            "seed": SEED,
            "match_px": MATCH_PX,
            "min_gap_px": MIN_GAP_PX,
            **RENDER,
        },
        perspective_bias_px={
            "rms": float(np.sqrt(np.mean(bias**2))),
            "median": float(np.median(bias)),
            "max": float(bias.max()),
        },
        views_with_touching_dots=touching,
        labelling={
            "ms_per_image_median": float(label_ms[1]),
            "views_correct": labelling["correct"],
            "views_flagged": labelling["flagged"],
            "views_wrong": labelling["wrong"],
        },
        wall_time_s=wall,
        first_call_s=first_call,
        peak_mb_tracemalloc=peak,
        results=rows,
        summary=summary,
    )


if __name__ == "__main__":
    main()
