"""Dot detection with sub-pixel centroids: the paper's Section IV.1, with scikit-image.

The paper binarises the photograph, inverts it, extracts and subtracts the background, labels the
connected components and keeps the dots. Those steps find the dots; the *position* of a dot comes
from its grey levels: the centroid of the background-subtracted darkness in a window shaped as
the dot (a blurred ellipse with the second moments of its image), re-centred until it balances.
Any centrally symmetric window gives the centre of a centrally symmetric dot image, whatever the
blur; one the size of the dot leaves out the pixels that hold only noise. On rendered views
(blur 1 px, noise 3 grey levels) it is within 0.013 px RMS of the dots' ellipse centres (the
centroid of the thresholded blob is off by 0.07 px), and within 0.025 / 0.047 px on 2-3 px dots
at blur 0.5 / 1 px (the plain centroid over the blob grown by 3 px: 0.113 / 0.134 px).
"""

from __future__ import annotations

import contextvars
import dataclasses
import os
import warnings

import numpy as np
from scipy import ndimage
from scipy.special import i0e, i1e  # SciPy comes with scikit-image
from skimage import color, filters, measure, morphology

__all__ = ["Detection", "detect_dots"]


@dataclasses.dataclass(frozen=True)
class Detection:
    """Dots found in one image.

    **Fields:**

    - `centroids`: `(K, 2)` float64 sub-pixel centres `(x = column, y = row)`, origin at the
      centre of the top-left pixel (the convention of `mvcalib.Camera`).
    - `area`: `(K,)` pixels in each thresholded blob.
    - `eccentricity`: `(K,)` of the blob's moment ellipse (0 for a circle; a dot seen
      obliquely is an ellipse, so this measures foreshortening, not quality).
    - `major`, `minor`: `(K,)` axis lengths of the blob's moment ellipse, in pixels. The major
      axis is the dot's diameter over its distance, little changed by obliquity: how
      `mvcalib.label_dots` tells large fiducial dots from the others.
    - `contrast`: `(K,)` peak darkness of the dot relative to the local background (dark dots:
      `1 - dot / paper`, in [0, 1]; bright dots: the grey-level step, image units in [0, 1]).
    - `bbox`: `(K, 4)` int `(min_row, min_col, max_row, max_col)` of each blob, half-open.
    - `stages`: with `return_stages=True`, the intermediate images of the paper's Fig. 3 as a
      dict (`'binary'`, `'inverted'`, `'background'`, `'subtracted'`, `'detected'`), else None.
    - `image_shape`: `(height, width)` of the image searched (the principal point's default
      guess in `mvcalib.match_dots` is its centre).
    """

    centroids: np.ndarray
    area: np.ndarray
    eccentricity: np.ndarray
    contrast: np.ndarray
    bbox: np.ndarray
    major: np.ndarray
    minor: np.ndarray
    stages: dict | None = None
    image_shape: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.centroids)


# ---------------------------------------------------------------------------- input validation
# The least blob area kept when dots are large (and the most the adaptive default asks for).
_MIN_AREA = 12


def _typical_area(areas: np.ndarray) -> float:
    """The area of the blob that a segmented pixel typically belongs to, from the blobs' `areas`:
    their median weighted by area. Specks of noise or tracer particles, however many, hold few
    of the pixels, and the dots most of them (OpenPTV's cavity photos: hundreds of particles of
    2-10 pixels, 73 dots of ~80)."""
    areas = np.sort(areas)
    areas = areas[areas > 0]
    if len(areas) == 0:
        return 4.0 * _MIN_AREA
    mass = np.cumsum(areas)
    return float(areas[np.searchsorted(mass, 0.5 * mass[-1])])


def flag(name: str, value) -> bool:
    """`value` as a bool, or a TypeError: a string such as "no" is true to Python, and would
    silently do the opposite of what was meant."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"`{name}` is True or False; got {value!r}.")
    return bool(value)


def _as_grey(image) -> np.ndarray:
    """The image as float32 grey levels in [0, 1], or a ValueError saying what is wrong."""
    if isinstance(image, (str, os.PathLike)):
        raise ValueError(
            f"`image` is the photograph's grey levels, an array; got the path {str(image)!r}: "
            "read the file with `mc.read_image(path)`."
        )
    try:
        array = np.asarray(image)
    except Exception as error:  # ragged nested lists and the like
        raise ValueError(f"`image` must be an array of grey levels; got {type(image)}.") from error
    kind = array.dtype.kind
    if kind == "b":
        raise ValueError(
            "`image` is boolean; pass the grey-level photograph (uint8, uint16 or float), "
            "not a mask: the sub-pixel centroids need the grey levels."
        )
    if kind == "c":
        raise ValueError("`image` is complex; pass real grey levels (e.g. `np.abs(image)`).")
    if kind not in "uif":
        raise ValueError(f"`image` must hold numbers (uint8, uint16 or float); got {array.dtype}.")
    if array.size == 0:
        raise ValueError(f"`image` is empty (shape {array.shape}).")
    if array.ndim == 3 and array.shape[-1] in (3, 4):
        # Colour: drop alpha and take the luminance (ITU-R 709 weights, skimage's rgb2gray).
        array = color.rgb2gray(_unit_range(array[..., :3]))
    elif array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    elif array.ndim != 2:
        raise ValueError(
            "`image` must be 2-D (height, width) or colour (height, width, 3 or 4); "
            f"got shape {array.shape}."
        )
    if min(array.shape) < 16:
        raise ValueError(f"`image` is too small to hold dots: {array.shape}, need >= 16 x 16.")
    grey = _unit_range(array)
    if not np.ptp(grey) > 0:
        raise ValueError("the image is constant: it has no contrast, so there are no dots to find.")
    # float32 for the whole-image filters (twice as fast; 24 bits hold uint16 exactly); the
    # per-dot centroid sums are done in float64.
    return grey.astype(np.float32)


def _unit_range(array: np.ndarray) -> np.ndarray:
    if array.dtype in (np.uint8, np.uint16):  # a photo's own range: black 0, white 255 or 65535
        return array.astype(np.float64) / np.iinfo(array.dtype).max
    if array.dtype.kind in "ui":
        # Other integers are mostly 8- or 16-bit photos in a wider array (Pillow reads 16-bit
        # PNGs as int32): the range of 8 or 16 bits that holds the values, else their own.
        lo, hi = int(array.min()), int(array.max())
        if lo >= 0 and hi <= 65535:
            return array.astype(np.float64) / (255.0 if hi <= 255 else 65535.0)
    array = array.astype(np.float64)
    if not np.isfinite(array).all():
        raise ValueError("`image` has NaN or infinite values; mask or fill them first.")
    lo, hi = array.min(), array.max()
    if lo < 0.0 or hi > 1.0:  # floats are taken as [0, 1]; any other range is rescaled to it
        array = (array - lo) / (hi - lo) if hi > lo else np.zeros_like(array)
    return array


def _otsu(image: np.ndarray) -> float:
    # Otsu's threshold from every other row and column: the histogram is what matters, and a
    # quarter of a megapixel image describes it as well as all of it, in a quarter of the time.
    return float(filters.threshold_otsu(image[::2, ::2]))


# ---------------------------------------------------------------------------- shape tests
def _moments(labels: np.ndarray):
    """Area and central second moments (rows, columns, cross; over pixel centres) of every
    component of `labels`, at once: bincounts over the foreground pixels, the coordinates taken
    about each component's mean first (no cancellation in large images).

    Computed for every component of a photograph in one pass; regionprops, one object per
    component, costs ~30 us each and a real photograph has thousands of specks.
    """
    n = int(labels.max())
    flat = np.flatnonzero(labels)
    index = labels.ravel()[flat]
    row, col = np.divmod(flat, labels.shape[1])
    count = lambda w=None: np.bincount(index, w, minlength=n + 1)[1:]  # noqa: E731
    area = count()
    safe = np.maximum(area, 1)
    row = row - (count(row) / safe)[index - 1]
    col = col - (count(col) / safe)[index - 1]
    return area, count(row * row) / safe, count(col * col) / safe, count(row * col) / safe


def _axes(vrr, vcc, vrc):
    """The eigenvalues of the covariance `[[vrr, vrc], [vrc, vcc]]`, larger first: the squared
    semi-axes of the moment ellipse over 4."""
    half_trace, root = (vrr + vcc) / 2, np.sqrt(((vrr - vcc) / 2) ** 2 + vrc**2)
    return half_trace + root, np.maximum(half_trace - root, 0.0)


def _ellipse_error(subtracted, region, level) -> float:
    """How far a blob's outline is from an ellipse: its RMS distance from the best-fit ellipse,
    in pixels.

    The outline is the sub-pixel iso-line of the subtracted image at the detection level
    (marching squares over the blob and a one-pixel rim around it, so it interpolates true grey
    levels). Every dot, seen from any angle, is an ellipse, so this is the shape test that
    survives perspective where circularity does not.
    """
    r0, c0, r1, c1 = region.bbox
    height, width = subtracted.shape
    own = np.pad(region.image, 2)
    window = np.zeros(own.shape)
    # The blob's bounding box grown by 2 px, clipped to the image.
    R0, C0, R1, C1 = max(r0 - 2, 0), max(c0 - 2, 0), min(r1 + 2, height), min(c1 + 2, width)
    window[R0 - r0 + 2 : R1 - r0 + 2, C0 - c0 + 2 : C1 - c0 + 2] = subtracted[R0:R1, C0:C1]
    # Other blobs do not count: only the blob grown by a pixel (a dilation by `disk(1)`, the
    # 3 x 3 cross, written out: 9x faster on a blob's box)
    grown = own.copy()
    grown[1:] |= own[:-1]
    grown[:-1] |= own[1:]
    grown[:, 1:] |= own[:, :-1]
    grown[:, :-1] |= own[:, 1:]
    window[~grown] = 0.0
    contours = measure.find_contours(window, level)
    outline = max(contours, key=len) if contours else np.zeros((0, 2))
    if len(outline) < 6:
        return np.inf
    # Algebraic conic fit on normalised coordinates (centred, unit RMS radius, for conditioning);
    # the residual is the Sampson distance, the first-order geometric distance to the conic.
    y, x = outline[:, 0], outline[:, 1]
    scale = np.sqrt(((x - x.mean()) ** 2 + (y - y.mean()) ** 2).mean())
    u, v = (x - x.mean()) / scale, (y - y.mean()) / scale
    design = np.stack([u * u, u * v, v * v, u, v, np.ones_like(u)], axis=1)
    a, b, c, d, e, f = np.linalg.svd(design, full_matrices=False)[2][-1]
    if b * b - 4 * a * c >= 0:  # the best conic is not an ellipse
        return np.inf
    q = design @ np.array([a, b, c, d, e, f])
    gradient = np.hypot(2 * a * u + b * v + d, b * u + 2 * c * v + e)
    return float(scale * np.sqrt(np.mean((q / np.maximum(gradient, 1e-12)) ** 2)))


def _candidates(moments, min_area, max_area, max_aspect) -> tuple[np.ndarray, np.ndarray]:
    """Labels of the components with a dot's size and elongation, and their minor axes (of the
    moment ellipse, each pixel counted as a square: + 1/12 px^2 about its centre)."""
    area, vrr, vcc, vrc = moments
    major, minor = (4 * np.sqrt(v) for v in _axes(vrr + 1 / 12, vcc + 1 / 12, vrc))
    ok = (area >= min_area) & (area <= max_area) & (major <= max_aspect * np.maximum(minor, 1.0))
    return np.flatnonzero(ok) + 1, minor[ok]


@dataclasses.dataclass(frozen=True)
class _Blob:
    """A component of the labelled image, measured as skimage's `regionprops` measures it."""

    label: int
    bbox: tuple[int, int, int, int]
    image: np.ndarray  # its pixels in its bounding box
    area: int
    axis_major_length: float
    axis_minor_length: float
    eccentricity: float

    def solid(self, least: float) -> bool:
        """Whether its solidity (area over the pixels whose centres lie in the convex hull of its
        pixels' centres) is at least `least`. The hull's pixels lie within the blob's octagon (its
        box cut by its extremes along both diagonals), so where the octagon passes the hull is
        not needed: a disc's area is 95 % of its octagon's. (skimage's `regionprops` takes the
        hull of the pixels' corners, which a small disc fills only to its radius over its radius
        plus one: 5 of 2200 dots 5 px wide, centred on a pixel, were dropped at 0.78, a
        photographer's trial; with the centres' hull a convex blob is 1 at any size.)"""
        rows, cols = np.nonzero(self.image)
        grid_r, grid_c = np.ogrid[: self.image.shape[0], : self.image.shape[1]]
        octagon = np.count_nonzero(
            ((grid_r + grid_c) >= (rows + cols).min())
            & ((grid_r + grid_c) <= (rows + cols).max())
            & ((grid_r - grid_c) >= (rows - cols).min())
            & ((grid_r - grid_c) <= (rows - cols).max())
        )
        if self.area >= least * octagon:
            return True
        hull = morphology.convex_hull_image(self.image, offset_coordinates=False)
        return self.area >= least * int(np.sum(hull))


def _blobs(labels, keep, moments) -> list[_Blob]:
    """The components `keep` of `labels`, from their `_moments` (no object per component)."""
    area, vrr, vcc, vrc = moments
    large, small = _axes(vrr, vcc, vrc)
    boxes = ndimage.find_objects(labels)
    blobs = []
    for label in keep:
        rows, cols = boxes[label - 1]
        i = label - 1
        l1, l2 = float(large[i]), float(small[i])
        blobs.append(
            _Blob(
                label=int(label),
                bbox=(rows.start, cols.start, rows.stop, cols.stop),
                image=labels[rows, cols] == label,
                area=int(area[i]),
                axis_major_length=4 * np.sqrt(l1),
                axis_minor_length=4 * np.sqrt(l2),
                eccentricity=np.sqrt(1 - l2 / l1) if l1 > 0 else 0.0,
            )
        )
    return blobs


# ---------------------------------------------------------------------------- detection
def detect_dots(
    image,
    *,
    min_area: int | None = None,
    max_area: int | None = None,
    max_ellipse_error: tuple[float, float] = (0.4, 0.02),
    min_solidity: float = 0.8,
    max_aspect: float = 12.0,
    dark_dots: bool = True,
    dot_size: float | None = None,
    smooth: float = 1.0,
    margin: int = 3,
    exclude_border: bool = True,
    return_stages: bool = False,
) -> Detection:
    """Find the dots of a calibration target in a photograph, with sub-pixel centroids.

    The paper's steps (Section IV.1), made quantitative:

    1. **Binarise** with Otsu's threshold: the candidate dots, and so the dot size.
    2. **Invert** the grey image, so that dots are bright (with `dark_dots=True`).
    3. **Background**: a grey opening of the inverted image with a square wider than any
       candidate dot. Opening removes every bright structure the square cannot fit inside: the
       dots go, the slowly varying rest (illumination, shading) stays.
    4. **Subtract** it (a white top-hat): a flat background with the dots on top.
    5. **Threshold** the subtracted image, smoothed by a Gaussian of `smooth` pixels (Otsu's
       level, but at least 6 noise sigmas above the background), **label** its connected
       components and keep those shaped like a dot seen from some angle: of plausible size
       (`min_area`, `max_area`), not a streak (`max_aspect`), not a blot (`min_solidity`), and
       with an elliptic outline (`max_ellipse_error`).
    6. **Centroid**: per blob, a grey-level-weighted centroid in a window matched to the dot. The
       weights are `(b - I) / b` for dark dots, with `b` a plane fitted to the background in a
       ring around the blob: the plane follows the illumination gradient, and dividing by it
       makes the weights the ink coverage itself, so the centroid is that of the dot's image
       whatever the light falling on the paper (shading, vignetting). Light added on top of
       the image (glare, a veil) is not divided out: a glare a quarter to three quarters of
       the paper's brightness moved 18 px dots by 0.1-0.3 px, their `contrast` down to
       0.55-0.8 from 0.86 (a photographer's trial). Bright dots use `I - b`. The window is a
       model of the dot: a uniform ellipse with the second moments of the dot's image (less
       the blur's), enlarged by 20 % and one blur sigma to cover unevenly lit dots, blurred by
       a Gaussian of `margin / 3` pixels: flat over a large dot, a bump the size of a small
       one. It is
       re-centred (Newton's method, from the plain centroid over the blob grown by `margin`
       pixels) until the centroid in it is its centre. Any centrally symmetric window gives the
       centre of a centrally symmetric dot image, so the model need not be exact; one the size
       of the dot leaves out the pixels that hold only noise (3 grey levels of noise over a
       3 px rim moved the plain centroid of a 2-3 px dot by 0.13 px RMS; this window: 0.05).

    Colour images are converted to grey by luminance (skimage's `rgb2gray`; alpha is ignored).
    uint8 and uint16 images are scaled by their dtype's range; other integer images (a 16-bit
    PNG read by Pillow is int32) by 8 or 16 bits, whichever holds their values, else by their
    own range; float images are taken as [0, 1], and any other range is rescaled to it.

    **Arguments:**

    - `image`: `(height, width)` grey or `(height, width, 3|4)` colour; uint8, uint16 or float.
    - `min_area`, `max_area`: blob size bounds in pixels. `min_area` by default adapts to the
      image: a quarter of the typical blob's area (the area-weighted median, which specks and
      particles barely move), between 2 and 12 pixels
      (12 for dots of 48 pixels' area or more: specks of noise and dust stay out; 3 for the
      2-3 px dots of a large PIV image, which a fixed 12 would drop). `max_area` defaults to 2 %
      of the image.
    - `max_ellipse_error`: `(pixels, fraction)`: a blob's outline may stray from its best-fit
      ellipse by an RMS distance of at most `pixels + fraction * b`, `b` its minor semi-axis.
      Plain circularity would reject dots seen obliquely; every dot, from any angle, is an
      ellipse. The fixed part covers noise and pixel grid, which fray any outline by a few
      tenths of a pixel; the part growing with size lets large dots' outlines bend a little
      more. Rendered dots stay below 0.1 px, real photographed dots below ~0.5 px (highlights);
      rectangles and blots of dot size stray by 0.5 to 2 px. Loosen it for photographs whose
      dots carry a saturated highlight on one side (back-lit dots under water, as OpenPTV's
      cavity): `(2.0, 1.0)` found 42 / 41 / 70 / 69 of its dots where the default found 36 / 40
      / 69 / 66, and `mvcalib.match_dots` keeps the clutter it lets in out of the labels.
    - `min_solidity`: area over convex hull area: a quick first cut at blots and touching blobs.
    - `max_aspect`: the longest elongation (major / minor axis) a dot may have; rejects streaks.
      A dot seen 85 degrees off its normal has aspect ~11.
    - `dark_dots`: True for dark dots on a light sheet (the paper's), False for bright dots on a
      dark background.
    - `dot_size`: the widest dot in pixels (the minor axis, for an oblique dot), to size the
      background filter; by default measured from the binarised image.
    - `smooth`: sigma in pixels of the Gaussian applied before thresholding (segmentation
      only; 0 for none). It keeps noise and highlights from fraying the blob outlines.
    - `margin`: the width of the dots' blurred rim in pixels, about 3 blur sigmas: the centroid's
      window is blurred by `margin / 3` pixels and reaches `margin + 1` pixels beyond the blob,
      and the background ring lies beyond that.
    - `exclude_border`: drop blobs touching the image border (their centroids are cut).
    - `return_stages`: also return the intermediate images (see `Detection.stages`).

    **Returns:**

    A `Detection` (see there): centroids `(K, 2)` as `(x, y)` and per-blob measurements, in the
    raster order of the blobs' first pixels.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> camera = mc.synthetic.random_rig(jax.random.key(0), 1).cameras[0]
    >>> image = mc.synthetic.render(camera, mc.targets.box_corner(), key=0)
    >>> found = mc.detect_dots(image)
    >>> len(found), found.centroids.shape
    (19, (19, 2))

    ```
    """
    dark_dots, exclude_border, return_stages = (
        flag(name, value)
        for name, value in (
            ("dark_dots", dark_dots),
            ("exclude_border", exclude_border),
            ("return_stages", return_stages),
        )
    )
    # (as given: the other polarity is searched with them where few dots are found)
    given = dict(min_area=min_area, max_area=max_area, max_ellipse_error=max_ellipse_error,
                 min_solidity=min_solidity, max_aspect=max_aspect, dot_size=dot_size,
                 smooth=smooth, margin=margin, exclude_border=exclude_border)  # fmt: skip
    grey = _as_grey(image)
    height, width = grey.shape
    max_area = 0.02 * grey.size if max_area is None else max_area
    if margin < 1:
        raise ValueError(f"`margin` must be at least 1 pixel; got {margin}.")

    # 1-2. Binarise and invert: dots bright on a dark background from here on.
    inverted = 1.0 - grey if dark_dots else grey
    binary = inverted > _otsu(inverted)

    # 3. Background by opening. The square must fit inside no dot: its side is the widest
    # dot-like candidate's minor axis plus the blurred rims on either side.
    if dot_size is None:
        size_area = _MIN_AREA if min_area is None else min_area
        _, widths = _candidates(_moments(measure.label(binary)), size_area, max_area, max_aspect)
        dot_size = float(widths.max()) if len(widths) else 30.0
    half = int(np.ceil(dot_size / 2.0)) + margin + 2
    square = morphology.footprint_rectangle((2 * half + 1, 2 * half + 1), decomposition="separable")
    background = morphology.opening(inverted, square)

    # 4-5. Subtract, threshold above the noise, label, keep dot-shaped blobs. The noise is the
    # robust spread of the subtracted image (mostly background), from a subsample for speed.
    subtracted = inverted - background
    # Segment a lightly smoothed copy: it averages out pixel noise and the highlights of real
    # dots, so blob outlines (and the shape test on them) follow the dot, not the noise. The
    # centroids below use the unsmoothed grey levels.
    smoothed = filters.gaussian(subtracted, smooth) if smooth > 0 else subtracted
    sample = smoothed[::3, ::3]
    offset = np.median(sample)
    noise = 1.4826 * np.median(np.abs(sample - offset))
    level = max(_otsu(smoothed), offset + 6.0 * noise)
    labels = measure.label(smoothed > level, connectivity=2)
    moments = _moments(labels)
    if min_area is None:  # a quarter of the typical blob's area, 2 to 12 pixels
        min_area = int(np.clip(round(_typical_area(moments[0]) / 4), 2, _MIN_AREA))
    candidates, _ = _candidates(moments, min_area, max_area, max_aspect)
    kept = []
    for region in _blobs(labels, candidates, moments):
        r0, c0, r1, c1 = region.bbox
        if exclude_border and (r0 == 0 or c0 == 0 or r1 == height or c1 == width):
            continue
        if not region.solid(min_solidity):
            continue
        tolerance = max_ellipse_error[0] + max_ellipse_error[1] * region.axis_minor_length / 2
        if _ellipse_error(smoothed, region, level) <= tolerance:
            kept.append(region)

    # 6. Sub-pixel centroids on the grey levels. Background rings keep clear of every blob
    # (kept or not) and of its blurred rim.
    centroids, contrast, measured = [], [], []
    for region in kept:
        centroid, peak = _weighted_centroid(grey, labels, region, margin, smooth, dark_dots)
        if centroid is None:
            continue  # no net contrast against its own surroundings: not a dot after all
        centroids.append(centroid)
        contrast.append(peak)
        measured.append(region)
    kept = measured

    stages = None
    if return_stages:
        lookup = np.zeros(labels.max() + 1, dtype=np.int32)
        lookup[[r.label for r in kept]] = np.arange(1, len(kept) + 1)
        stages = {
            "binary": ~binary if dark_dots else binary,
            "inverted": inverted,
            "background": background,
            "subtracted": subtracted,
            "detected": lookup[labels],
        }
    if len(kept) < _FEW_DOTS and not _OTHER_POLARITY.get():
        # (bright dots searched as dark ones gave 0-5 junk blobs and no word: a photographer's
        # trial) the other polarity, searched as this image was, once
        token = _OTHER_POLARITY.set(True)
        try:
            other = detect_dots(grey, dark_dots=not dark_dots, **given)
        finally:
            _OTHER_POLARITY.reset(token)
        if len(other) >= max(_FEW_DOTS, 4 * len(kept)):
            shade, ground = ("bright", "dark") if dark_dots else ("dark", "bright")
            warnings.warn(
                f"detect_dots found {len(kept)} dots, but {len(other)} {shade} ones: "
                f"{shade} dots on a {ground} ground? dark_dots={not dark_dots}.",
                stacklevel=2,
            )
    return Detection(
        centroids=np.asarray(centroids, dtype=np.float64).reshape(-1, 2),
        area=np.asarray([r.area for r in kept], dtype=np.int64),
        eccentricity=np.asarray([r.eccentricity for r in kept], dtype=np.float64),
        contrast=np.asarray(contrast, dtype=np.float64),
        bbox=np.asarray([r.bbox for r in kept], dtype=np.int64).reshape(-1, 4),
        major=np.asarray([r.axis_major_length for r in kept], dtype=np.float64),
        minor=np.asarray([r.axis_minor_length for r in kept], dtype=np.float64),
        stages=stages,
        image_shape=(int(height), int(width)),
    )


# Fewer dots than this, and `detect_dots` looks whether the other polarity has many (once: the
# flag is set while it looks).
_FEW_DOTS = 4
_OTHER_POLARITY = contextvars.ContextVar("mvcalib_other_polarity", default=False)


def _disc_window(r, radius, sigma):
    """The window of the matched-filter centroid for a disc of `radius` blurred by a Gaussian of
    `sigma`, and its derivative: w(r) = -M'(r) / r, with M(r) the blurred disc's radial profile,
    so that sum w(|x - c|) I(x) (x - c) = 0 is the peak of the correlation of the image with M.

    -M'(r) = (R / s^2) exp(-(r^2 + R^2) / 2 s^2) I1(r R / s^2), with I1 the modified Bessel
    function: a ring of width s on the edge of a large disc, a Gaussian of sigma ~s for a small
    one."""
    r = np.maximum(r, 1e-6)
    z, k = r * radius / sigma**2, radius / sigma**2
    # The exponentially scaled Bessel functions keep exp(-z) I(z) finite for large discs.
    edge = k * np.exp(-((r - radius) ** 2) / (2 * sigma**2))
    i0, i1 = i0e(z), i1e(z)
    window = edge * i1 / r
    slope = edge * (k * i0 / r - i1 / sigma**2 - 2 * i1 / r**2)
    return window, slope


def _disc_profile(r, radius, sigma):
    """The blurred disc's radial profile M and its window w = -M'(r) / r (`_disc_window`) at the
    evenly spaced `r` from 0 on, out to where M has vanished (a few `sigma` beyond `radius`).

    M(r) = integral of -M'(t) over t > r, by the trapezoid rule summed from the far end with
    Euler-Maclaurin's end correction, -h^2 / 12 (f'(end) - f'(r)): within 4e-8 of its exact
    value (the noncentral chi-square distribution, SciPy's `chndtr`, which took 0.13-0.7 ms a
    blob against 0.07 ms) at 1024 samples, for discs of 1 to 25 px."""
    window, slope = _disc_window(r, radius, sigma)
    f, df = window * r, window + r * slope  # -M'(r) and its derivative
    h = r[1] - r[0]
    trapezoids = 0.5 * h * (f[1:] + f[:-1])
    tail = np.append(np.cumsum(trapezoids[::-1])[::-1], 0.0)
    return window, tail - h * h / 12 * (df[-1] - df)


_PROFILE_SAMPLES = 1024


def _squared_norm(offsets, metric):
    """`x^T metric x` for each row `x` of `offsets` `(n, 2)` (4x as fast as `np.einsum`)."""
    x, y = offsets[:, 0], offsets[:, 1]
    return metric[0, 0] * x * x + (metric[0, 1] + metric[1, 0]) * x * y + metric[1, 1] * y * y


def _solve2(a, b):
    """`a^-1 b` for a 2 x 2 `a` by Cramer's rule (a tenth of `lstsq`'s time), or `lstsq`'s
    least-norm answer where `a` is singular to rounding."""
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    if not abs(det) > 1e-12 * np.abs(a).max() ** 2:
        return np.linalg.lstsq(a, b, rcond=None)[0]
    return np.array([a[1, 1] * b[0] - a[0, 1] * b[1], a[0, 0] * b[1] - a[1, 0] * b[0]]) / det


def _weighted_centroid(grey, labels, region, margin, smooth, dark_dots):
    ring_width = 5
    pad = 2 * margin + ring_width + 2
    r0, c0 = max(region.bbox[0] - pad, 0), max(region.bbox[1] - pad, 0)
    r1, c1 = min(region.bbox[2] + pad, grey.shape[0]), min(region.bbox[3] + pad, grey.shape[1])
    window = grey[r0:r1, c0:c1].astype(np.float64)
    rows, cols = np.mgrid[r0:r1, c0:c1]
    blobs = labels[r0:r1, c0:c1]
    # Each pixel goes to the nearest blob within the distance (Euclidean), so a grown blob
    # never takes pixels nearer to another one: `segmentation.expand_labels`, its distance
    # transform taken once for the three distances below
    distance_to, nearest = ndimage.distance_transform_edt(blobs == 0, return_indices=True)
    nearest = blobs[tuple(nearest)]
    grown = lambda distance: np.where(distance_to <= distance, nearest, 0)  # noqa: E731
    # The blob grown by `margin`: a Euclidean disc, so that the grown shape stays centrally
    # symmetric and the blur tails it cuts off cancel (the starting point, and the contrast).
    inside = grown(margin) == region.label
    rim = grown(margin + 1)
    # The pixels the matched window may weigh: one pixel further, up to the background ring.
    reach = rim == region.label
    # Background ring: beyond this blob's blurred rim and clear of every other blob's.
    around = (grown(margin + 1 + ring_width) == region.label) & (rim == 0)
    if around.sum() < 3:  # crowded: fall back on every pixel of the window not near a blob
        around = rim == 0
    if around.sum() < 3:
        around = ~inside
    # Local background: a plane through the ring, which follows any illumination gradient.
    A = np.stack([np.ones(around.sum()), cols[around], rows[around]], axis=1)
    coef = np.linalg.lstsq(A, window[around], rcond=None)[0]
    plane = coef[0] + coef[1] * cols + coef[2] * rows
    if dark_dots:
        weight = (plane - window) / np.maximum(plane, 1e-6)
    else:
        weight = window - plane
    total = weight[inside].sum()
    if not total > 0:
        return None, 0.0
    peak = float(weight[inside].max())
    # Start: the plain centroid over the grown blob.
    xy = np.stack([cols[reach], rows[reach]], axis=1).astype(np.float64)
    w = weight[reach]
    start = (weight[inside][:, None] * xy[inside[reach]]).sum(0) / total
    # The dot model: a uniform ellipse with the second moments of the dot's image (less the
    # pixel's 1/12 and the blur's sigma^2), enlarged by 20 % and by one blur sigma so that it
    # covers unevenly lit dots, blurred by a Gaussian of sigma = margin / 3 (the margin is ~3
    # blur sigmas). The window is the model's profile: flat over a large dot, a bump the size
    # of a small one. Its shape and size only set how well noise is averaged out: a centrally
    # symmetric dot image gives its centre for any centrally symmetric window.
    sigma = margin / 3.0
    offsets = xy[inside[reach]] - start
    moments = (weight[inside][:, None, None] * offsets[:, :, None] * offsets[:, None, :]).sum(0)
    variance, axes = np.linalg.eigh(moments / total)
    variance = np.maximum(variance - 1 / 12 - sigma**2, 0.05)
    semi = 1.2 * 2.0 * np.sqrt(variance) + sigma  # semi-axes of a uniform ellipse, enlarged
    radius = float(np.sqrt(semi[0] * semi[1]))
    to_circle = axes * (radius / semi)  # maps the ellipse onto the disc of that radius
    metric = to_circle @ to_circle.T

    # The blurred disc's profile M(r) and window, tabulated once a blob (evaluated at every
    # pixel in every step, they were most of the detection's time), interpolated linearly: off
    # by at most 1e-4 of their peaks, and functions of r like M, so as centrally symmetric
    reach_r = float(np.sqrt(np.max(_squared_norm(xy - start, metric))))
    table_r = np.linspace(0.0, reach_r + 2.0 * (radius + margin) + 1.0, _PROFILE_SAMPLES)
    table_w, table = _disc_profile(table_r, radius, sigma)
    centre = start
    for _ in range(20):  # Newton's method on sum M(|x - c|) I(x) (x - c) = 0; ~3 steps
        offset = xy - centre
        r = np.sqrt(_squared_norm(offset, metric))
        profile = np.interp(r, table_r, table)  # the blurred disc
        slope = np.interp(r, table_r, table_w)  # -M'(r) / r
        mw = w * profile
        if not mw.sum() > 0:
            return None, 0.0
        f = mw @ offset
        jacobian = -mw.sum() * np.eye(2) + ((w * slope)[:, None] * offset).T @ (offset @ metric)
        step = -_solve2(jacobian, f)
        if not np.all(np.abs(step) < 1.0):  # far from the balance: a plain windowed centroid
            step = f / mw.sum()
        centre = centre + step
        if np.abs(step).max() < 1e-5:
            break
    else:
        centre = start  # no convergence (never seen on dots): the plain centroid
    if np.linalg.norm(centre - start) > radius + margin:
        centre = start
    return (float(centre[0]), float(centre[1])), peak
