"""A second look at the image where a calibrated camera predicts the dots `detect_dots` missed.

`detect_dots` segments the whole image at one level and keeps the blobs shaped like a dot. Real
photographs lose dots to that: a saturated speck or streak attached to a dot makes its blob no
ellipse, a dot on glare or in a bright stripe merges with it, a dim half-lit disc falls apart at
the level. Once the matched dots have given a camera, each missed dot's position is known to a
pixel or so, and the question is no longer "is there a dot somewhere" but "is this dot here, and
exactly where":

1. **Template.** The dot's image is modelled on the images of the matched dots nearest it on the
   target (which share its size, obliquity and lighting): the median of their windows, each
   resampled around its `detect_dots` centroid less a plane fitted to a ring around it. The
   median keeps their specks and streaks out; the template carries the centroid's own definition
   of a dot's centre, so the dots found here agree with those found before, whatever the dots'
   look (OpenPTV's cavity dots are a dim disc with a saturated crescent on one side, which a
   uniform ellipse does not describe).
2. **Fit.** In a window around the prediction: the background (a grey opening of the image, as
   `detect_dots` removes it, which follows glare and stripes wider than a dot, plus a plane) plus
   an amplitude times the template shifted to the dot's centre, clipped at the saturation level
   (a saturated pixel says only that the image is at least that bright). A robust (soft-L1) loss
   lets specks, streaks and glare pixels fall out of the fit.
3. **Accept** only a fit that looks like its neighbours: amplitude between `amplitude` times the
   template's, the fit's robust misfit over the dot's footprint at most `max_misfit` of its
   contrast with at least half the footprint within 15 % of it, contrast at least `min_snr`
   noise sigmas, and the centre within `gate` pixels of the prediction. A dot hidden behind
   something fits with an amplitude near zero; a blob beside the prediction lies outside the
   gate.
4. **Centre** (`centre_by`). `"template"` (the default for bright dots): the fitted template's
   centre, which is right where the neighbours look like the dot, whatever its shape.
   `"centroid"` (the default for dark dots): the template, stretched by an affine map to the
   dot's shape, says which pixels are specks or streaks; they are replaced by the model and
   `detect_dots`' own matched-window centroid is taken on the cleaned window, which is right
   for any centrally symmetric dot image, even where the neighbours look different (a box's
   other face). Dark dots are measured as ink coverage, `(paper - I) / paper`, as
   `detect_dots` weighs them. On the cavity's asymmetric bright dots the centroid depends on
   the blob's outline (new dots' leave-one-out residuals up to 0.8 px; the template's: 0.6);
   on rendered box corners the template of dots on two faces is up to 0.6 px off and the
   centroid 0.01-0.02 px.

On OpenPTV's cavity photographs this finds 5 / 3 / 2 / 5 more dots of the four cameras (all the
visible ones but the dot under a glare cloud, a dot swollen by a glare halo, a faint half-cut dot,
a dot on the edge of a stripe and a dot that the target file misplaces by 0.13 mm, which
`calibrate_images` takes with `beyond_gate` and reports), whose
leave-one-out residuals (0.03-0.90 px) lie within those of the matched dots (up to 0.8 / 1.2 /
1.6 / 0.9 px). Fitted to the matched dots themselves (the template of their neighbours), the
centres predict the dots better than the centroids do: cross-validated (each dot against a DLT
camera calibrated without it, 8 folds), 0.308 / 0.365 / 0.551 / 0.429 px with the centroids and
0.178 / 0.322 / 0.445 / 0.397 px with the fits. `refit="auto"` (the default) makes that
comparison for each image and keeps the better centres: here the fits, refined RMS 0.147 / 0.190
/ 0.413 / 0.332 px (`calibrate_images`, dot 68 left out as misplaced), where the matched
centroids alone gave 0.255 / 0.279 / 0.521 / 0.344.
"""

from __future__ import annotations

import numpy as np

from . import _label
from ._camera import Camera
from ._detect import Detection, _as_grey, flag
from ._label import Labels
from .targets import Target

__all__ = ["second_look"]

# Template and windows, in dot radii R: the fit's window reaches 2.5 R (+2 px) from the
# prediction; a template's background ring lies 1.8-2.8 R from its dot's centroid; the
# template is sampled every half pixel.
_WINDOW, _RING, _STEP = 2.5, (1.8, 2.8), 0.5
# The fitted centre may move at most this many radii from the prediction.
_MAX_SHIFT = 0.6
# With `refit="auto"` and more than twice this many matched dots, this many are refitted first,
# and the rest only if their fits predict the dots better.
_SAMPLE = 48
# ... if the sample's held-out RMS falls by this share (the clean dots of a rendered plate:
# 0.01 %; OpenPTV's cavity dots, whose centroids the fits correct: 10-40 %)
_GAIN = 0.01


def _coords(p, xx, yy, s):
    """The template's sample coordinates (row, column) of pixels `xx, yy` for parameters `p`:
    the pixel's offset from the centre `p[:2]`, through the affine map `I + [[p6, p7], [p8, p9]]`
    (or none), on the template's grid of `_STEP` px with its centre at index `s`."""
    dx, dy = xx - p[0], yy - p[1]
    if len(p) > 6:
        dx, dy = (1 + p[6]) * dx + p[7] * dy, p[8] * dx + (1 + p[9]) * dy
    return [dy / _STEP + s, dx / _STEP + s]


def _ring_plane(image, centre, r_in, r_out):
    """A plane `(c0, cx, cy)` through the pixels between `r_in` and `r_out` of `centre` (around
    it), fitted with three rounds of trimming at 3 robust sigmas (specks in the ring)."""
    h = int(np.ceil(r_out)) + 1
    x0, y0 = int(round(centre[0])) - h, int(round(centre[1])) - h
    yy, xx = np.mgrid[y0 : y0 + 2 * h + 1, x0 : x0 + 2 * h + 1]
    inside = (xx >= 0) & (yy >= 0) & (xx < image.shape[1]) & (yy < image.shape[0])
    d = np.hypot(xx - centre[0], yy - centre[1])
    ring = (d > r_in) & (d < r_out) & inside
    if ring.sum() < 3:
        return np.zeros(3)
    A = np.c_[np.ones(ring.sum()), xx[ring] - centre[0], yy[ring] - centre[1]]
    values = image[yy[ring], xx[ring]]
    keep = np.ones(len(values), bool)
    for _ in range(3):
        coef = np.linalg.lstsq(A[keep], values[keep], rcond=None)[0]
        r = values - A @ coef
        keep = np.abs(r) <= 3 * 1.4826 * np.median(np.abs(r)) + 1e-9
    return np.linalg.lstsq(A[keep], values[keep], rcond=None)[0]


def _patches(flat, centres, radius, half):
    """Each dot's window of `flat` around `centre`, resampled every `_STEP` px over +-`half`
    px, less the plane of its background ring: `(n, 2 s + 1, 2 s + 1)`."""
    from scipy.ndimage import map_coordinates  # SciPy comes with scikit-image

    s = int(round(half / _STEP))
    grid = np.arange(-s, s + 1) * _STEP
    V, U = np.meshgrid(grid, grid, indexing="ij")
    out = np.empty((len(centres), 2 * s + 1, 2 * s + 1))
    for i, c in enumerate(centres):
        coef = _ring_plane(flat, c, _RING[0] * radius, _RING[1] * radius)
        sampled = map_coordinates(flat, [c[1] + V, c[0] + U], order=1, mode="nearest")
        out[i] = sampled - coef[0] - coef[1] * U - coef[2] * V
    return out


def _fit(
    grey, background, predicted, template, radius, saturation, affine=True, min_amplitude=None
):
    """Fit `clip(background + plane + a * template(x - c))` around `predicted`: a dict with the
    centre and the acceptance measures, or None where the window leaves the image."""
    from scipy.ndimage import map_coordinates, spline_filter
    from scipy.optimize import least_squares

    half = int(np.ceil(_WINDOW * radius)) + 2
    x0, y0 = int(round(predicted[0])) - half, int(round(predicted[1])) - half
    height, width = grey.shape
    if x0 < 0 or y0 < 0 or x0 + 2 * half + 1 > width or y0 + 2 * half + 1 > height:
        return None
    data = grey[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1]
    base = background[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1]
    yy, xx = np.mgrid[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1].astype(np.float64)
    X, Y = (xx - predicted[0]) / half, (yy - predicted[1]) / half
    s = (template.shape[0] - 1) // 2
    Tv, Tu = np.gradient(template)
    outer = np.hypot(xx - predicted[0], yy - predicted[1]) > 1.8 * radius
    above = (data - base)[outer]
    noise = max(1.4826 * float(np.median(np.abs(above - np.median(above)))), 1e-3)

    # The cubic B-spline coefficients of the template and its gradients, once: what
    # `map_coordinates` computes on every call with its default `prefilter` (the same numbers)
    images = {"template": template, "u": Tu, "v": Tv}
    spline = {k: spline_filter(a, 3, output=np.float64, mode="constant") for k, a in images.items()}

    def sample(name, p):
        coordinates = _coords(p, xx, yy, s)
        return map_coordinates(spline[name], coordinates, order=3, mode="constant", prefilter=False)

    def model(p):
        return base + p[2] + p[3] * X + p[4] * Y + p[5] * sample("template", p)

    def residuals(p):
        return (np.clip(model(p), 0.0, saturation) - data).ravel()

    def jacobian(p):
        m = model(p)
        live = ((m > 0.0) & (m < saturation)).ravel()  # a clipped pixel does not move
        t = sample("template", p).ravel()
        gu = p[5] * sample("u", p).ravel() / _STEP  # d model / d (template x, y)
        gv = p[5] * sample("v", p).ravel() / _STEP
        columns = [None, None, np.ones_like(t), X.ravel(), Y.ravel(), t]
        A = np.eye(2) + (p[6:10].reshape(2, 2) if len(p) > 6 else 0.0)
        columns[0] = -(A[0, 0] * gu + A[1, 0] * gv)
        columns[1] = -(A[0, 1] * gu + A[1, 1] * gv)
        if len(p) > 6:
            dx, dy = (xx - p[0]).ravel(), (yy - p[1]).ravel()
            columns += [gu * dx, gu * dy, gv * dx, gv * dy]
        return np.stack(columns, axis=1) * live[:, None]

    b0 = float(np.median(above))
    if min_amplitude is not None:  # no dot at all here (hidden): the linear fit at the prediction
        t = sample("template", np.array([*predicted, 0.0, 0.0, 0.0, 1.0])).ravel()
        A = np.stack([np.ones_like(t), X.ravel(), Y.ravel(), t], axis=1)
        a = np.linalg.lstsq(A, (data - base).ravel(), rcond=None)[0][3]
        if not a >= min_amplitude:
            return dict(amplitude=float(a), shift=0.0, snr=0.0, misfit=np.inf, inliers=0.0)
    reach = _MAX_SHIFT * radius
    start = np.array([predicted[0], predicted[1], b0, 0.0, 0.0, 1.0] + [0.0] * (4 * affine))
    lower = [predicted[0] - reach, predicted[1] - reach, -1.0, -1.0, -1.0, 0.05]
    upper = [predicted[0] + reach, predicted[1] + reach, 2.0, 1.0, 1.0, 5.0]
    if affine:  # (the template stretched by up to 2/3 or squeezed to 1/2.5 along any axis)
        lower += [-0.4, -0.4, -0.4, -0.4]
        upper += [0.6, 0.4, 0.4, 0.6]
    fitted = least_squares(
        residuals, start, jac=jacobian, bounds=(lower, upper), loss="soft_l1",
        f_scale=max(3 * noise, 0.01), x_scale="jac", max_nfev=100,
    )  # fmt: skip
    p = fitted.x
    residual = residuals(p).reshape(data.shape)
    linear = map_coordinates(template, _coords(p, xx, yy, s), order=1, mode="constant")
    footprint = linear > 0.2 * template.max()
    contrast = p[5] * template.max()
    if not footprint.any() or not contrast > 0:
        return None
    return dict(
        centre=p[:2].copy(),
        amplitude=float(p[5]),
        shift=float(np.hypot(*(p[:2] - predicted))),
        snr=float(contrast / noise),
        misfit=float(np.sqrt(np.median(residual[footprint] ** 2)) / contrast),
        inliers=float(np.mean(np.abs(residual[footprint]) < 0.15 * contrast)),
        params=p,
        predicted=np.asarray(predicted, float),
        half=half,
        noise=noise,
        contrast=float(contrast),
    )


def _cleaned_centroid(grey, background, fit, template, radius, saturation, margin=3):
    """`detect_dots`' centroid of the fitted dot, on the image with the pixels the fit calls
    outliers (specks, streaks, glare: further from the model than 4 noise sigmas and 30 % of
    the dot's contrast) replaced by the model, and the opened background taken off. None where
    the window leaves the image."""
    from scipy.ndimage import map_coordinates
    from skimage import measure

    from ._detect import _weighted_centroid

    p, predicted, half = fit["params"], fit["predicted"], fit["half"]
    reach = int(np.ceil(1.5 * radius)) + 2 * margin + 10  # the blob, its rim and ring
    x0, y0 = int(round(p[0])) - reach, int(round(p[1])) - reach
    height, width = grey.shape
    if x0 < 0 or y0 < 0 or x0 + 2 * reach + 1 > width or y0 + 2 * reach + 1 > height:
        return None
    box = np.s_[y0 : y0 + 2 * reach + 1, x0 : x0 + 2 * reach + 1]
    data, base = grey[box], background[box]
    yy, xx = np.mgrid[box].astype(np.float64)
    s = (template.shape[0] - 1) // 2
    dot = p[5] * map_coordinates(template, _coords(p, xx, yy, s), order=3, mode="constant")
    plane = p[2] + p[3] * (xx - predicted[0]) / half + p[4] * (yy - predicted[1]) / half
    model = np.clip(base + plane + dot, 0.0, saturation)
    outlier = np.abs(data - model) > max(4 * fit["noise"], 0.3 * fit["contrast"])
    flat = np.where(outlier, model, data) - base
    blob = measure.label(dot > 0.5 * fit["contrast"])
    if blob.max() == 0:
        return None
    region = max(measure.regionprops(blob), key=lambda r: r.area)
    blob = np.where(blob == region.label, 1, 0)
    region = measure.regionprops(blob)[0]
    centre, _ = _weighted_centroid(flat, blob, region, margin, 1.0, False)
    if centre is None:
        return None
    return np.array([centre[0] + x0, centre[1] + y0])


def _radius(grey, pixels, detection, labels):
    """The dots' typical radius in pixels: half the median major axis of the matched blobs, or
    (without the detection) from the area above half contrast around the matched pixels."""
    found = np.flatnonzero(labels.mask)
    if detection is not None and len(detection):
        index = labels.index[found]
        index = index[(index >= 0) & (index < len(detection))]
        if len(index):
            return 0.5 * float(np.median(np.asarray(detection.major)[index]))
    d = np.linalg.norm(pixels[found][:, None] - pixels[found][None], axis=-1)
    np.fill_diagonal(d, np.inf)
    reach = max(3, int(0.4 * np.median(d.min(1))))
    radii = []
    for x, y in pixels[found]:
        x, y = int(round(x)), int(round(y))
        w = grey[max(y - reach, 0) : y + reach + 1, max(x - reach, 0) : x + reach + 1]
        level = 0.5 * (w.max() + np.median(w))
        radii.append(np.sqrt((w > level).sum() / np.pi))
    return float(np.median(radii))


def _rms(predicted, pixels, mask):
    """The RMS distance (px) of the dots `mask` `(..., N)` from their predictions `(..., N, 2)`,
    over the last axis of dots (0 where there is none)."""
    square = np.where(mask, np.sum((predicted - np.nan_to_num(pixels)) ** 2, -1), 0.0)
    return np.sqrt(np.sum(square, -1) / np.maximum(np.sum(mask, -1), 1))


def _gate(rms):
    """The default gate for dots `rms` px from their predictions: 3.5 times that, at least 0.5
    px (here and in `calibrate_images`' check across the images)."""
    return np.maximum(0.5, 3.5 * rms)


def _held_out_rms(world, candidates, mask, folds: int = 8, judged=None) -> list[float]:
    """For each candidate set of pixels `(N, 2)` of the dots `mask`: the RMS distance of each
    dot (of those `judged`, default all) from where a camera calibrated without it projects it
    (`folds`-fold cross-validation, the dots dealt to the folds in turn; all candidates' folds
    in one batched call). NaN where a fold's camera failed."""
    from ._pipeline import calibrate

    seen = np.flatnonzero(mask)
    fold = np.full(len(world), -1)
    fold[seen] = np.arange(len(seen)) % folds
    held = np.stack([mask & (fold != j) for j in range(folds)])  # (folds, N): the fit's dots
    pixels = np.concatenate([np.broadcast_to(c, (folds, *c.shape)) for c in candidates])
    masks = np.concatenate([held] * len(candidates))
    fit = calibrate(world, np.where(masks[..., None], pixels, 0.0), masks)
    projected = np.asarray(fit.cameras.project(world)).reshape(len(candidates), folds, -1, 2)
    counted = np.ones(len(seen), bool) if judged is None else np.asarray(judged)[seen]
    out = []
    for c, candidate in enumerate(candidates):
        predicted = projected[c, fold[seen], seen]
        error = np.sum((predicted - candidate[seen]) ** 2, -1)[counted]
        out.append(float(np.sqrt(np.mean(error))))  # (NaN if a fold's camera failed)
    return out


def second_look(
    image,
    labels: Labels,
    target: Target,
    camera: Camera,
    *,
    detection: Detection | None = None,
    dark_dots: bool = True,
    neighbours: int = 6,
    gate: float | None = None,
    amplitude: tuple[float, float] = (0.5, 2.0),
    max_misfit: float = 0.15,
    min_snr: float = 10.0,
    refit: bool | str = "auto",
    saturation: float = 1.0,
    centre_by: str | None = None,
    beyond_gate: bool = False,
) -> Labels:
    """Find the dots `labels` lacks where `camera` predicts them, by fitting a template of their
    matched neighbours to the image (see the module notes for the method).

    **Arguments:**

    - `image`: the photograph the labels come from (as for `mvcalib.detect_dots`).
    - `labels`: its `Labels` (e.g. from `mvcalib.match_dots`), with at least `neighbours` dots.
    - `target`: the target; `camera`: this view's calibrated camera (e.g. from
      `mvcalib.calibrate` on the labels, refined or not), which predicts the missing dots.
    - `detection`: the `Detection` the labels were matched in (the dots' size comes from its
      blobs; without it, from the image around the matched dots).
    - `dark_dots`: as for `detect_dots` (False for bright dots on a dark background).
    - `neighbours`: how many matched dots, the nearest on the target, make each dot's template.
    - `gate`: the farthest (pixels) a found dot may lie from its prediction; default 3.5 times
      the RMS distance of the matched dots from `camera`'s projections, at least 0.5 px.
    - `amplitude`: the range of the dot's brightness relative to its template's; `max_misfit`:
      the largest robust misfit over the dot, as a fraction of its contrast; `min_snr`: the
      least contrast in noise sigmas of the window's background.
    - `refit`: also replace the matched dots' centroids by their own fits (each with the
      template of its neighbours, never itself), where those fit well: `True`; `False` keeps
      them; `"auto"` (the default) keeps the fits only if they predict the dots better, by
      cross-validation: the RMS distance of each dot from where a camera calibrated without it
      (the DLT, `mvcalib.calibrate`, 8 folds) projects it, with the one set of centres
      against the other; with more than 96 matched dots, 48 of them first, and the rest only
      if those improve. (With `centre_by="centroid"`, `"auto"` keeps them: a clean dot's
      cleaned centroid is its centroid again, and the fits take ~0.5 s a dot.)
    - `centre_by`: `"template"` or `"centroid"` (see the module notes); default `"centroid"`
      for dark dots, `"template"` for bright ones.
    - `saturation`: the level (in [0, 1]) at which the dots' brightness clips (`1 - grey` for
      dark dots, whose clip is black).
    - `beyond_gate`: also take the missing dots that fit well but lie beyond `gate` (as far as
      the fit reaches, 0.6 dot radii along each axis), named apart in the message: for a
      caller that checks them otherwise. `mvcalib.calibrate_images` does, across the images:
      a dot that the target file misplaces lies beyond the gate in every image, and one bad
      measurement in one image only.

    **Returns:** the `Labels` with the dots found added (`index` -1: they are no blob of the
    detection), their ids named in the `message`. Labels that are not `ok` come back as they are.

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> target = mc.targets.box_corner_grid(4)
    >>> camera = mc.synthetic.random_rig(jax.random.key(1), 1, target).cameras[0]
    >>> image = mc.synthetic.render(camera, target, key=0)
    >>> labels = mc.match_dots(mc.detect_dots(image), target, camera)
    >>> lost = labels.mask.copy(); lost[[3, 30]] = False  # as if two dots had been missed
    >>> labels = mc.Labels(np.where(lost[:, None], labels.pixels, np.nan), lost,
    ...     np.where(lost, labels.index, -1), labels.spurious, True, labels.rms, labels.message)
    >>> found = mc.second_look(image, labels, target, camera)
    >>> int(labels.mask.sum()), int(found.mask.sum())
    (46, 48)

    ```
    """
    if len(labels.mask) != len(target.points):
        raise ValueError(
            f"`labels` are of {len(labels.mask)} dots and `target` has {len(target.points)}: "
            "give the target the labels were made for."
        )
    if not isinstance(camera, Camera) or camera.batch_shape:
        if isinstance(camera, Camera):
            got = f"cameras of shape {camera.batch_shape}"
        else:
            got = f"a {type(camera).__name__}"
        raise ValueError(f"`camera` must be one mvcalib.Camera (this view's); got {got}.")
    dark_dots = flag("dark_dots", dark_dots)
    if not labels.ok:
        return labels
    centre_by = ("centroid" if dark_dots else "template") if centre_by is None else centre_by
    if centre_by not in ("template", "centroid"):
        raise ValueError(f"`centre_by` is 'template' or 'centroid'; got {centre_by!r}.")
    grey = np.asarray(_as_grey(image), dtype=np.float64)
    if dark_dots:  # (the dots bright from here on; the clip at black becomes one at 1)
        grey = 1.0 - grey
    mask = np.asarray(labels.mask, bool).copy()
    pixels = np.asarray(labels.pixels, np.float64).copy()
    world = np.asarray(target.points, np.float64)
    matched = np.flatnonzero(mask)
    height, width = grey.shape
    outside = (pixels[matched] < 0).any(1) | (pixels[matched] >= (width, height)).any(1)
    if outside.any():
        raise ValueError(
            f"{int(outside.sum())} of the labelled dots lie outside the {width} x {height} image "
            f"(e.g. id {int(np.asarray(target.ids)[matched[outside][0]])}): is this the image "
            "the labels come from?"
        )
    neighbours = int(neighbours)
    if len(matched) < max(neighbours, 1) + 1:
        return labels
    predicted = np.asarray(camera.project(world), np.float64)
    gate = float(_gate(_rms(predicted, pixels, mask))) if gate is None else gate
    radius = _radius(grey, pixels, detection, labels)
    if not np.isfinite(radius) or radius < 1.0:
        return labels

    from skimage import morphology

    # The background without the dots: a grey opening with a square wider than a dot
    side = 2 * (int(np.ceil(2 * radius)) + 5) + 1
    background = morphology.opening(
        grey, morphology.footprint_rectangle((side, side), decomposition="separable")
    )
    if dark_dots:
        # Ink under uneven light: its contrast is in proportion to the light on the paper, so
        # the dot is measured as the ink's coverage, (paper - I) / paper (as detect_dots' weights);
        # black (the clip) is 1 whatever the light.
        paper = np.maximum(1.0 - background, 1e-3)
        grey = np.clip((grey - background) / paper, 0.0, 1.0)
        background = np.zeros_like(grey)
    patches = _patches(grey - background, pixels[matched], radius, np.ceil(_WINDOW * radius) + 4)

    def look(k, at):
        """Dot `k`'s fit at `at` with the median template of its nearest matched dots."""
        others = matched[matched != k]
        near = np.argsort(np.linalg.norm(world[others] - world[k], axis=1))[:neighbours]
        template = np.median(patches[np.searchsorted(matched, others[near])], axis=0)
        least = 0.5 * amplitude[0] if not mask[k] else None  # (a quick "nothing here")
        affine = centre_by != "template"
        fit = _fit(grey, background, at, template, radius, saturation, affine, least)
        if fit is None or "centre" not in fit:
            return fit
        if centre_by == "template":
            return fit
        fit["template_centre"] = fit["centre"]
        fit["centre"] = _cleaned_centroid(grey, background, fit, template, radius, saturation)
        if fit["centre"] is None:
            return None
        fit["shift"] = float(np.hypot(*(fit["centre"] - fit["predicted"])))
        return fit

    def verdict(fit, gate):
        """Why a fit is no dot ("" if it is one)."""
        if fit is None:
            return "window leaves the image"
        why = []
        if not amplitude[0] <= fit["amplitude"] <= amplitude[1]:
            why.append(f"amplitude {fit['amplitude']:.2f}")
        if fit["shift"] > gate:
            why.append(f"{fit['shift']:.2f} px from the prediction (gate {gate:.2f})")
        if fit["misfit"] > max_misfit or fit["inliers"] < 0.5:
            why.append(f"misfit {fit['misfit']:.2f}, inliers {fit['inliers']:.2f}")
        if fit["snr"] < min_snr:
            why.append(f"contrast {fit['snr']:.1f} noise sigmas")
        return ", ".join(why)

    if refit not in (True, False, "auto"):
        raise ValueError(f"`refit` is True, False or 'auto'; got {refit!r}.")
    if refit == "auto" and centre_by == "centroid":
        refit = False  # (the cleaned centroid of a clean dot is its centroid again)
    # Two missing dots whose images lie within a diameter and 3 px are not looked for (one blob
    # may be both, which `match_dots` leaves out), nor a matched dot with a neighbour that close
    # refitted (the other lies in its window)
    reach = _label.crowd_reach([2.0 * radius])
    a, b = _label.close_pairs(predicted, reach)
    crowded = _label.unlabelled_pairs(predicted, reach, mask)
    crowded[a[mask[a]]] = crowded[b[mask[b]]] = True
    found, far, centres = [], [], {}

    def look_at(dots):
        for k in dots:
            at = pixels[k] if mask[k] else predicted[k]
            if crowded[k] or not (
                np.all(np.isfinite(at)) and 0 <= at[0] < width and 0 <= at[1] < height
            ):
                continue
            fit = look(k, at)
            why = verdict(fit, np.inf if beyond_gate else gate)
            if mask[k]:  # refit: a matched dot keeps its centroid where the fit is not good
                if fit is not None and fit["misfit"] <= max_misfit and fit["shift"] <= gate:
                    centres[k] = fit["centre"]
            elif not why:
                found.append(k)
                centres[k] = fit["centre"]
                if fit["shift"] > gate:
                    far.append(k)

    def better_fitted(judged=None):
        """`(before, after)`: the held-out RMS with the matched dots' centroids and with their
        fits (`refit="auto"`), over the dots `judged` (default all)."""
        fitted = pixels.copy()
        for k, centre in centres.items():
            fitted[k] = centre
        kept = fitted.copy()  # (the dots found, with the matched dots' centroids)
        refitted = [k for k in centres if mask[k]]
        kept[refitted] = pixels[refitted]
        every = mask.copy()
        every[found] = True
        every[far] = False  # (not measured to the gate: no judge of the centres)
        return _held_out_rms(world, (kept, fitted), every, judged=judged)

    if refit is False:
        look_at(np.flatnonzero(~mask))
    elif refit == "auto" and len(matched) > 2 * _SAMPLE:
        # Many dots: the fits of an even sample of them judged first, and the rest fitted only
        # if those predict the dots better (a user's trial: 4 photos of 450 clean dots, where
        # the fits do not, spent 5 of 7.4 s fitting every one)
        sample = matched[np.linspace(0, len(matched) - 1, _SAMPLE).astype(int)]
        look_at(np.union1d(np.flatnonzero(~mask), sample))
        judged = np.isin(np.arange(len(world)), sample)
        before, after = better_fitted(judged) if judged[list(centres)].any() else (0, np.nan)
        if after < (1.0 - _GAIN) * before:
            look_at(np.setdiff1d(matched, sample))
        else:  # (the sample's fits set aside too: the matched dots keep their centroids)
            for k in sample:
                centres.pop(k, None)
    else:
        look_at(np.arange(len(world)))
    refitted = [k for k in centres if mask[k]]
    message, held_out = labels.message, ""
    if refit == "auto" and refitted:
        before, after = better_fitted()
        if not after < before:  # (NaN: a fold failed; keep the centroids)
            for k in refitted:
                del centres[k]
            refitted = []
        else:
            held_out = f" (held-out RMS {before:.3f} -> {after:.3f} px)"
    if not centres:
        return labels
    for k, centre in centres.items():
        pixels[k] = centre
        mask[k] = True
    index = np.where(labels.mask, labels.index, -1)
    if found:
        ids = ", ".join(str(int(i)) for i in np.asarray(target.ids)[found])
        message += f"; second look: {len(found)} more (ids {ids}"
        if far:
            message += "; beyond the gate: " + ", ".join(
                str(int(i)) for i in np.asarray(target.ids)[far]
            )
        message += ")"
    if refitted:
        message += f"; {len(refitted)} matched dots refitted{held_out}"
    return Labels(
        pixels=np.where(mask[:, None], pixels, np.nan),
        mask=mask,
        index=index,
        spurious=labels.spurious,
        ok=labels.ok,
        rms=labels.rms,
        message=message,
    )
