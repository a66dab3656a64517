"""From photographs of the target to a calibrated rig: detect, label, calibrate."""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _buckets, _label, _validate
from ._detect import Detection
from ._label import Labels, label_dots
from ._match import match_dots
from ._photos import _grid_labels, _in_workers, _read_and_detect, polarity_hint, read_image
from ._pipeline import Calibration, CalibrationError, calibrate, mirror_note
from ._render import ellipse_centres, true_centres
from ._report import format_table
from ._second_look import _gate, _rms
from ._second_look import second_look as _second_look
from ._status import Status
from ._triangulate import triangulate
from .targets import Target, _grid_turns, _layout, box_corner, check_target

__all__ = ["ImageCalibration", "calibrate_images", "read_image"]


# A refined lens's distortion is called unknown at the photo's corners where its standard error
# there exceeds this (pixels).
_CORNER_STD = 1.0


# What a target without its dots' radius leaves undone.
_RADIUS_UNKNOWN = (
    "the target's dot radius is unknown (mc.targets.from_file(path, dot_radius=...); "
    "--dot-radius on the command line), so the dots' perspective bias is not removed: a tilted "
    "dot's image is an ellipse whose centroid is not its centre's image (rendered photos of a "
    "3-D target: camera centres 0.3-1 mm off against 0.03-0.13 mm with the radius)."
)


@dataclasses.dataclass(frozen=True)
class ImageCalibration:
    """The result of `calibrate_images`: one camera per image.

    **Fields:**

    - `calibration`: the `mvcalib.Calibration` of all images at once (cameras, report, status).
      Images that could not be read or labelled have `Status.NOT_LABELLED` and NaN cameras.
    - `labels`: one `mvcalib.Labels` per image (pixels and mask of every target dot).
    - `detections`: one `mvcalib.Detection` per image, None where the image could not be read or
      searched.
    - `names`: a name per image (its path, or `image i`).
    - `messages`: per image, what happened: the labelling summary or why it failed.
    - `misplaced`: the dots whose position in the target file the images contradict, by id,
      each with its position triangulated from the images (target coordinates). They stay
      labelled (`labels`, `mask`) and are left out of `calibration`.
    - `bias_removed`: whether the dots' perspective bias was removed (`bias_iterations`): not
      for a target whose dot radius is unknown (`targets.from_file` without `dot_radius`).
    """

    calibration: Calibration
    labels: list[Labels]
    detections: list[Detection | None]
    names: list[str]
    messages: list[str]
    misplaced: dict = dataclasses.field(default_factory=dict)
    bias_removed: bool = True

    @property
    def cameras(self):
        return self.calibration.cameras

    @property
    def ok(self) -> np.ndarray:
        return np.asarray(self.calibration.ok)

    @property
    def pixels(self) -> np.ndarray:
        return np.stack([lab.pixels for lab in self.labels])

    @property
    def mask(self) -> np.ndarray:
        return _mask_of(self.labels)

    def raise_if_failed(self) -> ImageCalibration:
        """Raise `CalibrationError` naming every image that did not give a camera."""
        bad = np.flatnonzero(~self.ok)
        if bad.size:
            status = np.asarray(self.calibration.status)
            lines = [f"{self.names[i]}: {self._why(i, status[i])}" for i in bad]
            raise CalibrationError(
                f"{bad.size} of {len(self.names)} images gave no camera:\n" + "\n".join(lines)
            )
        return self

    def _why(self, i: int, status) -> str:
        return self.messages[i] if status == Status.NOT_LABELLED else Status(int(status)).message

    def __str__(self) -> str:
        status = np.asarray(self.calibration.status)
        width = max(len(n) for n in self.names)
        lines = [f"{'image':<{width}}  blobs  dots  result"]
        for i, name in enumerate(self.names):
            detection = self.detections[i]
            blobs = "-" if detection is None else str(len(detection))
            dots = int(self.labels[i].mask.sum())
            result = "calibrated" if status[i] == Status.OK else self._why(i, status[i])
            lines.append(f"{name:<{width}}  {blobs:>5}  {dots:>4}  {result}")
        for i, point in self.misplaced.items():
            where = ", ".join(f"{x:.3f}" for x in point)
            lines.append(
                f"dot {i}: the images put it at ({where}), not where the target says; "
                "left out of the calibration"
            )
        files = [os.path.basename(n) for n in self.names]  # the table's camera, by its image
        names = files if len(set(files)) == len(files) else self.names
        table = format_table(
            self.calibration.report,
            status=[Status(int(s)).name.lower() for s in status],
            names=names,
        )
        why = "a photo transposed or flipped, or a target in a left-handed frame"
        notes = [
            mirror_note(self.calibration, names, why),
            self._loose_lens_note(names),
            self._outside_note(names),
            "" if self.bias_removed else f"note: {_RADIUS_UNKNOWN}",
        ]
        return "\n".join([*lines, "", table, *filter(None, notes)])

    def _outside_note(self, shown) -> str:
        """A note naming the calibrated cameras whose principal point lies outside their photo:
        the dots did not fix it (a flat or distant target fills a narrow field of view; a window
        or water between the camera and the target bends the rays, which a pinhole model then
        absorbs in odd intrinsics). OpenPTV's cavity photos: three of four, one 1600 px outside.
        (Printed by the command line alone until a photographer's trial missed it in Python.)"""
        outside = []
        for i, detection in enumerate(self.detections):
            if detection is None or not self.ok[i]:
                continue
            height, width = detection.image_shape
            u0, v0 = float(self.cameras.u0[i]), float(self.cameras.v0[i])
            if not (0 <= u0 <= width and 0 <= v0 <= height):
                outside.append(f"{shown[i]} ({u0:.0f}, {v0:.0f}) of {width} x {height}")
        if not outside:
            return ""
        return (
            f"note: principal points outside the photo: {'; '.join(outside)} px. The dots do not "
            "fix these cameras' intrinsics (a target that fills a narrow field of view, or rays "
            "bent by a window or water, which the pinhole model absorbs): their poses and "
            "triangulation within the target's volume hold, extrapolation beyond it does not."
        )

    def _loose_lens_note(self, shown) -> str:
        """A line naming the calibrated cameras whose refined distortion the dots leave unknown
        at the photo's corners (its standard error there, propagated from the refinement's
        covariance, above `_CORNER_STD` px): dots in a small part of the photo fit any
        distortion beyond them (a user's trial: a plate in the middle fifth of the photos,
        every camera OK at 0.03 px, k2 -35 against a true 0.08, ~17 of standard error)."""
        refinement = self.calibration.refinement
        if refinement is None or self.cameras.lens != "pinhole":
            return ""
        parameters = list(refinement.parameter_names)
        coefficients = [k for k in ("k1", "k2", "k3", "p1", "p2") if k in parameters]
        which = [parameters.index(k) for k in coefficients]
        if not which:
            return ""
        cameras, cov = self.cameras, np.asarray(refinement.covariance)
        loose = []
        for i, detection in enumerate(self.detections):
            if detection is None or not self.ok[i] or detection.image_shape is None:
                continue
            height, width = detection.image_shape
            au, av = float(cameras.alpha_u[i]), float(cameras.alpha_v[i])
            x = (np.array([0.0, width - 1]) - float(cameras.u0[i])) / au
            y = (np.array([0.0, height - 1]) - float(cameras.v0[i])) / av
            x, y = (a.ravel() for a in np.meshgrid(x, y))
            r2 = x * x + y * y
            columns = {  # the displacement's derivatives, in pixels, by coefficient
                "k1": (x * r2, y * r2), "k2": (x * r2**2, y * r2**2),
                "k3": (x * r2**3, y * r2**3), "p1": (2 * x * y, r2 + 2 * y * y),
                "p2": (r2 + 2 * x * x, 2 * x * y),
            }  # fmt: skip
            Ju = au * np.stack([columns[k][0] for k in coefficients], -1)
            Jv = av * np.stack([columns[k][1] for k in coefficients], -1)
            C = cov[i][np.ix_(which, which)]
            var = np.einsum("ca,ab,cb->c", Ju, C, Ju) + np.einsum("ca,ab,cb->c", Jv, C, Jv)
            std = float(np.sqrt(np.max(var)))
            if not std <= _CORNER_STD:
                loose.append(f"{std:.3g} px in {shown[i]}")
        if not loose:
            return ""
        return (
            "note: the dots leave the lens's distortion at the photo's corners unknown, to a "
            f"standard error of {'; '.join(loose)}: they cover too little of the photo. Points "
            "beyond them are extrapolated: fix the distortion (`distortion=('k1',)` or none; "
            "`--distortion k1`), or photograph the target filling the view."
        )


def _as_list(images) -> list:
    if isinstance(images, (str, os.PathLike)):
        return [images]
    if isinstance(images, np.ndarray):
        if images.ndim == 2 or (images.ndim == 3 and images.shape[-1] in (3, 4)):
            raise ValueError(
                f"`images` looks like one image (shape {images.shape}); pass a list: [image]."
            )
        if images.ndim not in (3, 4):
            raise ValueError(
                "`images` must be a list of images or paths, or a stack (C, height, width[, 3]);"
                f" got an array of shape {images.shape}."
            )
        return list(images)
    try:
        images = list(images)
    except TypeError:
        raise ValueError(
            f"`images` must be a list of images or image paths; got {type(images).__name__}."
        ) from None
    if not images:
        raise ValueError("`images` is empty: pass at least one image.")
    return images


# A dot's position on the target is doubted when a free 3-D point explains its pixels so much
# better: the drop in the squared reprojection errors over the images, each in units of its
# image's RMS squared, beyond chi-square with 3 degrees of freedom at p = 1e-4.
_MISPLACED_CHI2 = 21.1


def _beyond_gate(labels: Labels, first: Labels, camera, world, look: dict) -> np.ndarray:
    """The dots the second look added to `first` beyond the gate of `camera`'s predictions."""
    predicted = np.asarray(camera.project(world), np.float64)
    gate = look.get("gate") or _gate(_rms(predicted, first.pixels, first.mask))
    added = labels.mask & ~first.mask
    return added & (np.linalg.norm(np.nan_to_num(labels.pixels) - predicted, axis=-1) > gate)


def _misplaced(world, labels, far, calibrated):
    """The dots whose target position the images contradict: `(off (M,), the dots triangulated
    from the images (M, 3), calibrated(labels, far | off))`, the last the calibration without
    them and without `far` (also after `far & ~off` are dropped from the labels: the same dots).

    Each dot labelled in three or more images is triangulated from them (`far` dots included);
    it is off when that point reprojects within every image's gate (3.5 times the image's RMS,
    at least 0.5 px) and explains the dot's pixels better than the target's position by more
    than `_MISPLACED_CHI2`. The worst dot first, then the rig calibrated again without it, and
    so on (at most a tenth of the dots).
    """
    mask = _mask_of(labels)
    off = np.zeros(mask.shape[1], bool)
    while True:
        last = calibrated(labels, far | off)
        pixels, used, calibration = last
        cameras, ok = calibration.cameras, np.asarray(calibration.ok)
        seen, used = mask & ok[:, None], used & ok[:, None]
        points = np.asarray(triangulate(cameras, pixels, seen).points)
        predicted = np.asarray(cameras.project(world))
        nominal = np.linalg.norm(predicted - pixels, axis=-1)
        free = np.linalg.norm(np.asarray(cameras.project(points)) - pixels, axis=-1)
        rms = _rms(predicted, pixels, used)
        gate = _gate(rms)[:, None]
        scale = np.maximum(rms, 1e-9)[:, None] ** 2
        drop = np.sum(np.where(seen, (nominal**2 - free**2) / scale, 0.0), 0)
        explained = np.all(~seen | (free <= gate), 0) & (seen.sum(0) >= 3) & ~off
        score = np.where(explained, drop, -np.inf)
        k = int(np.argmax(score))
        if not score[k] > _MISPLACED_CHI2 or off.sum() >= len(off) // 10:
            return off, points, last
        off[k] = True


def _mask_of(labels) -> np.ndarray:
    """The labelled dots of every image: `(C, M)`."""
    return np.stack([lab.mask for lab in labels])


def _report_misplaced(labels: list, target: Target, off: np.ndarray, points) -> dict:
    """`{dot id: its triangulated position}` of the dots `off`, each named in the messages of
    the images that labelled it (`labels` amended in place)."""
    misplaced, labelled = {}, _mask_of(labels)
    for k in np.flatnonzero(off):
        dot = int(np.asarray(target.ids)[k])
        misplaced[dot] = points[k]
        offset = np.linalg.norm(points[k] - np.asarray(target.points[k]))
        note = (
            f"; dot {dot} left out of the calibration: the images put it {offset:.3g} "
            f"{target.units} from where the target has it"
        )
        for i in np.flatnonzero(labelled[:, k]):
            labels[i] = dataclasses.replace(labels[i], message=labels[i].message + note)
    return misplaced


def _without(labels: Labels, drop: np.ndarray, target: Target) -> Labels:
    """`labels` less the dots `drop`, beyond the gate in this image only."""
    ids = ", ".join(str(int(i)) for i in np.asarray(target.ids)[drop])
    mask = labels.mask & ~drop
    return dataclasses.replace(
        labels,
        pixels=np.where(mask[:, None], labels.pixels, np.nan),
        mask=mask,
        index=np.where(mask, labels.index, -1),
        message=labels.message + f"; dropped (ids {ids}): beyond the gate here only",
    )


def _spare_blobs(labels: Labels, detection, camera, world, far):
    """`(labels, taken)`: the dots `labels` lacks, and those it has `far` (beyond the gate),
    given the blob that no dot took nearest their prediction, within `_match._FIRST_GATE` of
    the dots' spacing, nearer it than any other dot's, with no other blob nearly as near
    (`_match._mutual`) and no unlabelled dot's image close by (one blob for two,
    `_label.unlabelled_pairs`): candidates for `_misplaced` to judge across the images, which
    drops them unless the target file misplaces the dot. Such a dot, off by more than the second
    look's fit reaches (0.6 dot radii), was matched in no image and dropped without a word (a
    user's trial: 0.5-1 mm, 3-6 px), or fitted at the edge of that reach; its blob is there in
    each image, and measures it."""
    taken = np.zeros(len(world), bool)
    candidates = ~labels.mask | far
    if detection is None or not labels.ok or not len(labels.spurious) or not candidates.any():
        return labels, taken
    from ._match import _FIRST_GATE, _mutual, _spacing

    predicted = np.asarray(camera.project(world), np.float64)
    seen = np.all(np.isfinite(predicted), axis=1)
    every = np.asarray(detection.centroids, np.float64)
    spare = np.asarray(labels.spurious)
    nearest = _mutual(predicted, every, _FIRST_GATE * _spacing(predicted[seen]))
    pair = _label.unlabelled_pairs(predicted, _label.crowd_reach(detection.major), labels.mask)
    taken = candidates & ~pair & (nearest >= 0) & np.isin(nearest, spare)
    if not taken.any():
        return labels, taken
    return dataclasses.replace(
        labels,
        pixels=np.where(taken[:, None], every[nearest], labels.pixels),
        mask=labels.mask | taken,
        index=np.where(taken, nearest, labels.index),
        spurious=np.setdiff1d(spare, nearest[taken]),
    ), taken


def calibrate_images(
    images,
    target: Target | None = None,
    *,
    refine: bool | dict = False,
    detect: dict | None = None,
    label: dict | None = None,
    seeds=None,
    focal=None,
    strict: bool = False,
    progress: bool | None = None,
    bias_iterations: int = 2,
    second_look: bool | dict = True,
    workers: int | None = 1,
) -> ImageCalibration:
    """Calibrate one camera per photograph of `target`: the paper's whole pipeline from images.

    For each image: detect the dots (`mvcalib.detect_dots`, the paper's morphological steps),
    label them (`mvcalib.label_dots`: which blob is which dot, from the target's fiducials); then
    all views at once: DLT, closed-form decomposition and Table I (`mvcalib.calibrate`), with the
    dots' perspective bias removed (`bias_iterations`), optionally refined. An image that
    cannot be read or labelled with certainty gives a flagged camera (`Status.NOT_LABELLED`,
    NaN parameters, a message saying why), never a wrong one, and the other images are
    calibrated as if it were not there.

    **Arguments:**

    - `images`: a list of images (arrays: grey or colour, 8/16-bit or float) and/or image paths,
      or a stack `(C, height, width[, 3])`.
    - `target`: the photographed target; default `mvcalib.targets.box_corner()`.
    - `refine`: as for `mvcalib.calibrate` (e.g. `True`, or `dict(distortion=("k1", "k2"))`).
    - `detect`, `label`: keyword arguments for `detect_dots` and `label_dots` (or
      `match_dots`, with seeds).
    - `seeds`: for targets without fiducials (any target, e.g. `mvcalib.targets.from_file`):
      one seed per image for `mvcalib.match_dots`, a rough `Camera` or clicked `(pixels (k, 2),
      dot_ids (k,))`, or None for that image (then `label_dots`); `focal`: the focal-length
      guess in pixels that four or five (or coplanar) clicks need, one for all images or one
      per image.
    - `second_look`: for images labelled from `seeds`: look again, with each calibrated camera,
      where it predicts the dots that were not matched, and add those that a template of their
      matched neighbours fits well (`mvcalib.second_look`: dots lost to an attached speck, glare,
      a stripe or uneven light), and re-centre the matched dots by that template where
      cross-validation says its centres predict the dots better; then calibrate again.
      A dict passes its options. With three or more such images, the dots that fit well beyond
      an image's gate are taken too, and judged across the images: a dot that a free 3-D point
      (triangulated from every image that has it) explains far better than its position on
      the target (by chi-square, 3 degrees of freedom, p = 1e-4; within every image's gate)
      is *misplaced*: it stays labelled, is left out of the calibration and reported (the
      result's `misplaced`, the messages, `print`); the other dots beyond the gate are dropped.
    - `strict`: raise `CalibrationError` if any image gives no camera.
    - `progress`: print one line per image to stderr; default: when there are more than 4.
    - `workers`: how many processes read the images and detect their dots (default 1: this
      one; see `observe_grid`; the labelling and calibration run here).
    - `bias_iterations`: rounds of perspective-bias correction: a dot's image is an ellipse
      whose centroid is not the projection of the dot's centre (by up to a few pixels for large
      dots seen obliquely); each round predicts that offset from the current cameras, removes
      it from the centroids and calibrates again. 0 for the raw centroids (the paper's way).

    **Returns:** an `ImageCalibration` (see there); `print` it for a per-image summary and
    Table I.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> target = mc.targets.box_corner()
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 2)
    >>> photos = [mc.synthetic.render(rig.cameras[i], target, key=i) for i in range(2)]
    >>> result = mc.calibrate_images(photos, target)
    >>> result.ok.tolist(), result.mask.sum(axis=1).tolist()
    ([True, True], [19, 19])

    ```
    """
    target = box_corner() if target is None else target
    check_target(target)
    if _validate.is_planar(np.asarray(target.points, float)):  # (every image DEGENERATE)
        raise ValueError(
            f"target {target.name!r} is flat: one photo of a plane does not determine a camera "
            "(calibrate_images calibrates a camera a photo). Label each photo of a grid with "
            "mc.label_grid and calibrate a camera from several with mc.calibrate_planar, or a "
            "rig with mc.observe_grid and mc.calibrate_rig."
        )
    images = _as_list(images)
    seeds = [None] * len(images) if seeds is None else list(seeds)
    if len(seeds) != len(images):
        raise ValueError(f"{len(seeds)} seeds for {len(images)} images: give one per image.")
    focals = list(focal) if np.ndim(focal) == 1 else [focal] * len(images)
    if len(focals) != len(images):
        raise ValueError(f"{len(focals)} focal lengths for {len(images)} images.")
    progress = len(images) > 4 if progress is None else progress
    detect, label = dict(detect or {}), dict(label or {})
    look = {} if second_look is True else (dict(second_look) if second_look else None)
    dtype = jnp.result_type(float)
    world = np.asarray(target.points, dtype)  # (NumPy in: `calibrate` pads it in NumPy anyway)
    # the calibration's programs compile on other threads while the images are read and matched
    views = (len(images), len(world))
    _buckets.ahead(calibrate, world, np.zeros((*views, 2), dtype), np.ones(views, bool),
                   refine=refine)  # fmt: skip
    names = [str(x) if isinstance(x, (str, os.PathLike)) else f"image {i}"
             for i, x in enumerate(images)]  # fmt: skip
    detections, labels, pictures = [], [], {}
    found = _in_workers(functools.partial(_read_and_detect, detect=detect), images, workers)
    for i, (picture, detection, why) in enumerate(found):
        try:
            if detection is None:
                raise ValueError(why)
            if seeds[i] is not None and look is not None:
                pictures[i] = picture  # (for the second look)
            if seeds[i] is None:
                labels.append(label_dots(detection, target, **label))
            else:
                labels.append(match_dots(detection, target, seeds[i], focal=focals[i], **label))
        except ValueError as error:
            message = str(error).removeprefix(f"{names[i]}: ")  # the name is shown beside it
            labels.append(Labels.failed(len(target.points), 0, message))
        if not labels[-1].ok and detection is not None:
            hint = polarity_hint(detection, len(target.points), detect)
            labels[-1] = dataclasses.replace(labels[-1], message=labels[-1].message + hint)
        detections.append(detection)
        if progress:
            print(f"[{i + 1}/{len(images)}] {names[i]}: {labels[-1].message}", file=sys.stderr)

    def calibrated(labels, leave_out=False):
        """The labels' pixels, the dots used (labelled, not `leave_out`) and every view
        calibrated from them."""
        mask = _mask_of(labels) & ~np.asarray(leave_out)
        pixels = np.nan_to_num(np.stack([lab.pixels for lab in labels]))  # hidden: no influence
        calibration = calibrate(world, pixels.astype(dtype), mask, refine=refine)
        return pixels, mask, calibration

    pixels, mask, calibration = calibrated(labels)
    misplaced = {}
    if pictures:  # the seeded images: look again where the cameras predict the missing dots
        # With three or more, the dots beyond an image's gate are taken and judged across the
        # images: a dot the target misplaces is off in all of them, a bad one in one.
        check = len(pictures) >= 3
        if check:  # (the triangulation that judges them compiles meanwhile)
            _buckets.ahead(triangulate, calibration.cameras, pixels, mask)
        options = dict(dark_dots=detect.get("dark_dots", True), beyond_gate=check, **look)
        cameras = jax.tree_util.tree_map(np.asarray, calibration.cameras)
        ok = np.asarray(calibration.ok)
        far = np.zeros((len(labels), len(target.points)), bool)
        for i, picture in pictures.items():
            if ok[i] and labels[i].ok:
                first = labels[i]
                try:
                    labels[i] = _second_look(
                        picture, first, target, cameras[i], detection=detections[i], **options
                    )
                except (ValueError, np.linalg.LinAlgError):  # (keep what was matched)
                    pass
                if check:  # (a blob that no dot took measures a dot better than a fit)
                    far[i] = _beyond_gate(labels[i], first, cameras[i], world, look)
                    labels[i], spare = _spare_blobs(
                        labels[i], detections[i], cameras[i], world, far[i]
                    )
                    far[i] |= spare
        if check:
            off, points, (pixels, mask, calibration) = _misplaced(world, labels, far, calibrated)
            # The dots beyond the gate that the target does not explain are dropped.
            for i in np.flatnonzero((far & ~off).any(1)):
                labels[i] = _without(labels[i], far[i] & ~off, target)
            misplaced = _report_misplaced(labels, target, off, points)
        else:
            pixels, mask, calibration = calibrated(labels)
    # (the bias is predicted from the dots' radii: a target without them keeps the centroids,
    # and says so: a photographer's trial, a 3-D target from a file, centres 0.3-1 mm off)
    known_radii = bool(np.all(np.isfinite(target.radii)))
    if bias_iterations and not known_radii:
        warnings.warn(f"calibrate_images: {_RADIUS_UNKNOWN}", stacklevel=2)
    for _ in range(int(bias_iterations) if known_radii else 0):
        # A dot's image is an ellipse whose centroid is not the image of the dot's centre
        # (perspective: the nearer half looks larger). Predict that offset per dot from the
        # current camera, remove it from the measured centroids, and calibrate again.
        bias = np.zeros_like(pixels)
        cameras = jax.tree_util.tree_map(np.asarray, calibration.cameras)
        for i in np.flatnonzero(np.asarray(calibration.ok)):
            bias[i] = ellipse_centres(cameras[i], target) - true_centres(cameras[i], target)
        corrected = np.where(mask[..., None], pixels - bias, 0.0).astype(dtype)
        calibration = calibrate(world, corrected, mask, refine=refine)
    unlabelled = np.asarray([not lab.ok for lab in labels])
    status = np.where(unlabelled, Status.NOT_LABELLED, np.asarray(calibration.status))
    status = jax.device_put(status.astype(np.int32))  # (from NumPy: no program of its own)
    calibration = eqx.tree_at(lambda c: c.status, calibration, status)
    result = ImageCalibration(
        calibration=calibration,
        labels=labels,
        detections=detections,
        names=names,
        messages=[lab.message for lab in labels],
        misplaced=misplaced,
        bias_removed=known_radii and bool(bias_iterations),
    )
    if strict:
        result.raise_if_failed()
    return result


def observe_grid(photos, grid: Target, *, names=None, detect: dict | None = None,
                 progress: bool | None = None, workers: int | None = 1):  # fmt: skip
    """A rig's observations of a printed dot grid moved through the volume, from its photos:
    each photo's dots detected (`detect_dots`) and labelled (`label_grid`, with the grid's
    `fiducials` as its markers, `targets.dot_grid(..., markers=)`, which give every dot the same
    id in every camera), for `mvcalib.calibrate_rig`.

    **Arguments:**

    - `photos`: per camera, its photos in frame order (paths or images; None where it took
      none): `photos[c][f]`, every camera with as many frames.
    - `grid`: a grid of dots made by `mvcalib.targets.dot_grid`, its markers as its
      `fiducials`. Without them a symmetric grid's ids are fixed only up to its half turn (its
      quarter turns if square), read from each photo's own orientation: photos that see the
      board turned by more than a quarter turn in its plane, from one camera or several, give
      its dots other ids (a warning says so for a rig); an asymmetric grid with an odd number of
      rows needs none while every camera sees the board from the same side.
    - `names`: the cameras' names; default `cam0`, `cam1`, ...
    - `detect`: options of `detect_dots` (e.g. `dark_dots=False`).
    - `progress`: a line on stderr per photo flagged or unreadable, and ten on how far it got
      (default: with more than 20 photos).
    - `workers`: how many processes read and label the photos (default 1: this one). More
      take as many cores, after ~0.4 s to start: on this project's 2-core machine, 48 photos
      of a 9 x 12 grid took 10.7 s in one process and 5.8 s in two. They are new Python
      processes, which import the main script again: in a script, call this under `if
      __name__ == "__main__":` (without it the workers stop, and the photos are read in this
      process, with a line on stderr saying so).

    **Returns:** an `mvcalib.io.Observations`; a photo that could not be read or labelled leaves
    its frame unseen by that camera, and `observations.mask.any(-1)` says which were labelled.

    **Example:** two cameras, one frame each.

    ```python
    >>> import numpy as np, mvcalib as mc
    >>> grid = mc.targets.dot_grid(6, 8, 20.0, markers=(0, 1, 2, 8))
    >>> R = np.diag([1.0, -1.0, -1.0])  # looking down at the grid's printed side
    >>> cameras = [mc.Camera(900.0, 900.0, 480.0, 360.0, R, -R @ np.array([x, 50.0, 420.0]))
    ...            for x in (40.0, 100.0)]
    >>> photos = [[mc.synthetic.render(c, grid, (960, 720), key=0)] for c in cameras]
    >>> obs = mc.observe_grid(photos, grid)
    >>> obs.pixels.shape, obs.mask.sum(-1).tolist()
    ((2, 1, 48, 2), [[48], [48]])

    ```
    """
    from .io import Observations

    check_target(grid, "`grid`", "mc.targets.dot_grid(rows, cols, spacing)")
    points = np.asarray(grid.points, float)
    if any(isinstance(camera, (str, os.PathLike, np.ndarray)) for camera in photos):
        raise ValueError(
            "`photos` holds a list of photos per camera, `photos[c][f]`; got a photo where a "
            "camera's list should be. For one camera, pass `[photos]`."
        )
    photos = [list(camera) for camera in photos]
    C, F = len(photos), max((len(camera) for camera in photos), default=0)
    if C == 0 or F == 0 or any(len(camera) != F for camera in photos):
        raise ValueError(
            "`photos` holds each camera's photos in frame order, as many for every camera "
            f"(None where one took none); got {[len(camera) for camera in photos]}."
        )
    names = [f"cam{c}" for c in range(C)] if names is None else [str(n) for n in names]
    if len(names) != C:
        raise ValueError(f"{len(names)} names for {C} cameras.")
    progress = C * F > 20 if progress is None else progress
    pixels = np.full((C, F, len(points), 2), np.nan)
    taken = [(c, f) for c, f in np.ndindex(C, F) if photos[c][f] is not None]
    missing = [(c, f) for c, f in taken if isinstance(photos[c][f], (str, os.PathLike))
               and not os.path.isfile(photos[c][f])]  # fmt: skip
    if missing:  # (a typo in a path: said before any photo is read, not as a frame unseen)
        (c, f), more = missing[0], len(missing) - 1
        raise ValueError(
            f"no such photo file: {photos[c][f]} ({names[c]}, frame {f})"
            + (f", and {more} more" if more else "")
        )
    layout = _layout(grid)
    if C > 1 and not len(grid.fiducials) and _grid_turns(*layout) > 1:
        # (a rig's photographer's trial: 864 of 2592 labels half turned, no word, and then
        # calibrate_rig blamed another camera)
        warnings.warn(
            f"observe_grid: the {layout[0]} x {layout[1]} grid has no markers, so its dots' ids "
            "are fixed only up to its half turn, from each photo's own orientation: cameras (or "
            "frames) that see the board turned by more than a quarter turn give other ids, and a "
            "rig calibrated from them fails. Print and give markers: mc.targets.dot_grid(rows, "
            f"cols, spacing, markers=(0, 1, 2, {layout[1]})).",
            stacklevel=2,
        )
    one = functools.partial(_grid_labels, detect=dict(detect or {}), layout=layout,
                            markers=grid.fiducials, n_points=len(points))  # fmt: skip
    every = max(len(taken) // 10, 1)
    found = 0
    for k, ((c, f), labels) in enumerate(
        zip(taken, _in_workers(one, [photos[c][f] for c, f in taken], workers))
    ):
        if labels.ok:
            pixels[c, f] = np.where(labels.mask[:, None], labels.pixels, np.nan)
            found += 1
        elif progress:
            print(f"{names[c]}, frame {f}: {labels.message}", file=sys.stderr)
        if progress and ((k + 1) % every == 0 or k + 1 == len(taken)):
            print(f"observe_grid: {k + 1} of {len(taken)} photos, {found} labelled",
                  file=sys.stderr)  # fmt: skip
    return Observations(points, pixels, np.isfinite(pixels[..., 0]), names, np.arange(F),
                        np.asarray(grid.ids))  # fmt: skip
