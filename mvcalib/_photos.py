"""Photos read and searched for dots, here or in worker processes (`_in_workers`), for
`mvcalib.calibrate_images` and `mvcalib.observe_grid`.

This module imports no JAX (nor do `_detect`, `_label` and `_match` until they fit a camera):
a worker process started by "spawn" imports it, and so starts in ~0.4 s rather than the ~1.3 s
of mvcalib's JAX modules.
"""

from __future__ import annotations

import logging
import os
import pathlib
import sys
import warnings

import numpy as np

from ._detect import detect_dots
from ._label import Labels


def read_image(path) -> np.ndarray:
    """Read an image file as an array, or raise `ValueError` saying what is wrong with it.

    TIFF through tifffile (8/16-bit, compressed with the `imagecodecs` package), every other
    format (PNG, JPEG, BMP, GIF, ...) through Pillow: both come with scikit-image. Grey or colour.
    """
    import imageio.v3 as iio  # scikit-image's own image I/O; imported only when files are read

    path = pathlib.Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    # One named reader per format: imageio's own search would also try other installed
    # readers (OpenCV's prints its failures to stderr).
    tiff = path.suffix.lower() in (".tif", ".tiff")
    # (tifffile logs a broken file's faults to stderr before failing; the error says them)
    quiet = logging.getLogger("tifffile")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    try:
        # The first frame of an animation (GIF, APNG); a TIFF's first page.
        image = (
            iio.imread(path, plugin="tifffile", key=0)
            if tiff
            else iio.imread(path, index=0, plugin="pillow")
        )
    except Exception as error:  # every reader raises its own kind; all mean "not an image"
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        if "can not handle the given uri" in reason:  # (imageio's words for an unknown format)
            reason = "not in a format Pillow reads: PNG, JPEG, BMP, GIF, ..."
        raise ValueError(f"{path}: cannot be read as an image ({reason[:200]})") from None
    finally:
        quiet.setLevel(level)
    image = np.asarray(image)
    if image.size == 0:  # (tifffile warns about a broken file and returns nothing)
        raise ValueError(f"{path}: cannot be read as an image (no image data in the file)")
    if image.ndim == 3 and image.shape[0] in (3, 4) and image.shape[-1] not in (3, 4):
        image = np.moveaxis(image, 0, -1)  # planar (channels-first) TIFFs
    return image


# The variables that set how many threads OpenMP and the BLAS libraries under NumPy start.
_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _in_workers(fun, items: list, workers: int | None):
    """`map(fun, items)`, in order: here, or on `workers` processes (started by "spawn", which
    is safe beside JAX's threads, where "fork" is not). A photo's detection is Python, NumPy and
    scikit-image work that threads would share one core for (measured: 0.89x with two threads).
    `fun` must be a module-level function (or a `functools.partial` of one) and catch its own
    errors. Where the workers die (say, in a script that starts processes without the main
    guard), the photos they did not do are done here, with a line on stderr saying why."""
    workers = 1 if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"`workers` must be at least 1; got {workers}.")
    if workers == 1 or len(items) < 2:
        yield from map(fun, items)
        return
    import concurrent.futures
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    pool = concurrent.futures.ProcessPoolExecutor(min(workers, len(items)), mp_context=context)
    # One BLAS thread a worker: OpenBLAS's own threads, one per core in every worker, fought
    # over the cores (48 photos on 2 workers: 18.6 s, against 7.5 s with one thread each and
    # 12.1 s in one process). The workers start in `map`, with the environment of that moment.
    saved = {name: os.environ.get(name) for name in _THREADS}
    os.environ.update(dict.fromkeys(_THREADS, "1"))
    try:
        results = pool.map(fun, items)
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    done = 0
    try:
        for result in results:
            yield result
            done += 1
    except concurrent.futures.process.BrokenProcessPool:
        # Workers that died (a script without the main guard, a sandbox that allows no new
        # processes, memory): the photos not done yet are read here, with a word why.
        print(
            f"mvcalib: the worker processes stopped after {done} of {len(items)} photos; the "
            "rest are read in this process (in a script, start workers under `if __name__ == "
            '"__main__":`, or pass workers=1)',
            file=sys.stderr,
        )
        yield from map(fun, items[done:])
    finally:  # (an error here, or a caller that stops early: the photos not begun are dropped)
        pool.shutdown(cancel_futures=True)


def _read_and_detect(image, detect: dict):
    """A photo (array or path) and its dots: `(picture, detection, None)`, or `(None, None,
    why)` where it cannot be read or searched (for `_in_workers`)."""
    try:
        picture = read_image(image) if isinstance(image, (str, os.PathLike)) else image
        with warnings.catch_warnings():  # (the callers say it in their own words)
            warnings.filterwarnings("ignore", "detect_dots found")
            return picture, detect_dots(picture, **detect), None
    except ValueError as error:
        return None, None, str(error)


def _grid_labels(photo, detect: dict, layout: tuple, markers, n_points: int) -> Labels:
    """A photo's dots labelled as the grid `layout` `(rows, cols, asymmetric)`, or the failed
    `Labels` saying why (for `_in_workers`)."""
    from ._match import label_grid

    picture, detection, why = _read_and_detect(photo, detect)
    if detection is None:
        return Labels.failed(n_points, 0, why)
    rows, cols, asymmetric = layout
    try:
        return label_grid(detection, rows, cols, asymmetric=asymmetric, markers=markers)
    except ValueError as error:
        return Labels.failed(n_points, 0, str(error) + polarity_hint(detection, n_points, detect))


def polarity_hint(detection, n_points: int, detect: dict) -> str:
    """For a photo that could not be labelled: where it was searched for dark dots and few were
    found, a hint that they may be bright (a user's trial: OpenPTV's back-lit dots searched as
    dark ones, "only 0 blobs found"); else ""."""
    if len(detection) >= min(10, n_points) or not detect.get("dark_dots", True):
        return ""
    return (
        f" ({len(detection)} dark dots found: bright dots on a dark ground? "
        "detect=dict(dark_dots=False), --bright-dots)"
    )
