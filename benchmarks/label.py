"""Benchmark: labelling rendered views of the box corner, clean and with hidden dots + clutter.

What is measured
----------------
Two sweeps of N random views each (`mvcalib.synthetic.random_rig`, 1000 x 1100 px, blur 1 px,
noise 3 grey levels, 30 % illumination gradient):

- **clean**: every dot drawn;
- **hidden + clutter**: 2 random dots hidden (fiducials included) and 5 clutter blobs (streaks,
  specks, smudges, blots, rectangles) per view.

Each view is detected (`mc.detect_dots`) and labelled (`mc.label_dots`); the labels are checked
against the dot ids known from the rendering (a dot's blob is the detection within 3 px of the
centre of its image). A view is *correct* if every labelled dot is right, *flagged* if the
labeller said it could not be sure (`ok=False`), *wrong* otherwise. Labelling time is per image,
after the first (which compiles).

`--quick` uses 20 views per sweep instead of 200.

Run from the repository root: `python benchmarks/label.py [--quick]`; results go to
`benchmarks/results/label.json`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _common import machine_info, write_results  # noqa: E402

import mvcalib as mc  # noqa: E402
from mvcalib.synthetic import ellipse_centres, render  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "label.json"
RENDER = dict(blur_sigma=1.0, noise_sigma=3.0, gradient=0.3)


def sweep(n_views: int, seed: int, hidden: int, clutter: int) -> dict:
    target = mc.targets.box_corner()
    rig = mc.synthetic.random_rig(jax.random.key(seed), n_views)
    rng = np.random.default_rng(seed)
    counts = dict(correct=0, flagged=0, wrong=0)
    times, dots, messages = [], 0, []
    for i in range(n_views):
        camera = rig.cameras[i]
        gone = rng.choice(len(target), hidden, replace=False) if hidden else ()
        image = render(camera, target, key=seed * 1000 + i, hidden=gone, clutter=clutter, **RENDER)
        detection = mc.detect_dots(image)
        start = time.perf_counter()
        labels = mc.label_dots(detection, target)
        times.append(time.perf_counter() - start)
        ellipse = ellipse_centres(camera, target)
        d = np.linalg.norm(ellipse[:, None] - detection.centroids[None], axis=-1)
        truth = np.where(d.min(1) < 3.0, d.argmin(1), -1)
        if not labels.ok:
            counts["flagged"] += 1
            messages.append(labels.message)
        elif (labels.index[labels.mask] == truth[labels.mask]).all():
            counts["correct"] += 1
            dots += int(labels.mask.sum())
        else:
            counts["wrong"] += 1
    ms = 1e3 * np.asarray(times[1:] if len(times) > 1 else times)
    return counts | {
        "views": n_views,
        "dots_labelled": dots,
        "ms_per_image_median": float(np.median(ms)),
        "ms_per_image_max": float(ms.max()),
        "flag_messages": messages,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="20 views per sweep instead of 200")
    args = parser.parse_args(argv)
    n = 20 if args.quick else 200
    wall = time.perf_counter()
    rows = {
        "clean": sweep(n, seed=100, hidden=0, clutter=0),
        "hidden 2 + clutter 5": sweep(n, seed=200, hidden=2, clutter=5),
    }
    print(f"labelling benchmark: {n} views per sweep, 1000 x 1100 px\n")
    print(f"{'sweep':<22}{'correct':>9}{'flagged':>9}{'wrong':>7}{'dots':>7}{'ms/image':>10}")
    for name, r in rows.items():
        print(
            f"{name:<22}{r['correct']:>9}{r['flagged']:>9}{r['wrong']:>7}"
            f"{r['dots_labelled']:>7}{r['ms_per_image_median']:>10.0f}"
        )
        for message in r["flag_messages"]:
            print(f"    flagged: {message}")
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")
    write_results(
        RESULTS,
        "label",
        quick=args.quick,
        machine=machine_info("scikit-image"),
        settings={"views_per_sweep": n, **RENDER},
        wall_time_s=wall,
        results=rows,
    )


if __name__ == "__main__":
    main()
