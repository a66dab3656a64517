"""One call from 3-D/2-D correspondences to calibrated cameras, with a report and statuses."""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _buckets, _dlt, _status, _validate
from ._camera import Camera, placeholder
from ._gc import collector_paused
from ._report import ReprojectionReport, compute_report, format_table, index_names, residual_rms
from ._status import Status

if TYPE_CHECKING:
    from . import _refine


def _refiner():
    """`mvcalib._refine`, imported at the first refinement (with Optimistix and Lineax, which
    nothing else needs) with the garbage collector paused, as `mvcalib`'s own names are
    (`_gc`): a fresh process's first `calibrate(..., refine=True)` walked the heap for cycles
    while the two made their classes."""
    with collector_paused():
        from . import _refine
    return _refine


class CalibrationError(ValueError):
    """Raised by `Calibration.raise_if_failed` (and `calibrate(..., strict=True)`)."""


class Calibration(eqx.Module):
    """The result of `calibrate`.

    - `cameras`: the decomposed cameras (NaN for cameras that failed).
    - `P`: the projection matrices with `||m3|| = 1`, `(..., 3, 4)`.
    - `report`: Table I and RMS/max per camera, on the points used for calibration.
    - `status`: a `Status` code per camera (`int32`); `ok` is `status == Status.OK`.
    - `condition`: the DLT's condition number `||L||_F / s_11` after normalisation (Frobenius
      norm over the second smallest singular value; large means nearly degenerate geometry).
      Exact for rigs of up to `_buckets.COMPACT` camera-points (LAPACK's eigenvalues); larger
      rigs estimate `s_11` from above in their inverse iteration, which gives the condition
      number from below, within ~15 %. `status` flags it only where the points give no camera
      (DEGENERATE); well before that, the camera is poorly determined while its points still
      fit it (a benchmark trial, 100 points on a 1 x 1 patch with 0.3 px of noise: depth spread
      0.3, condition 13, focal length 1.3 % off; 0.03, 123, 12 %; 0.003, 1340, 93 %, all OK).
      Check it (above ~100 asks for a deeper target), or the refinement's `standard_errors`.
    - `mirrored`: True where the world frame is mirrored relative to the camera (det M < 0 with
      the points in front): left-handed world coordinates, as in the Oxford VGG data, or pixels
      with y pointing up. `P` is right either way; `cameras` then has a proper rotation and
      the points at negative depth, and still projects every point correctly.
    - `refinement`: with `calibrate(..., refine=...)`, the `mvcalib.Refinement` whose cameras and
      report replaced the closed-form ones (`P` stays the DLT's); otherwise None.
    """

    cameras: Camera
    P: Float[Array, "*batch 3 4"]
    report: ReprojectionReport
    status: Int[Array, "*batch"]
    condition: Float[Array, "*batch"]
    mirrored: Bool[Array, "*batch"]
    refinement: _refine.Refinement | None = None

    @property
    def ok(self) -> Bool[Array, "*batch"]:
        return _status.ok(self.status)

    def messages(self) -> list[str]:
        """One line per camera (flattened), saying whether and why it failed, and where a
        calibrated camera's points barely fix it (`condition` above `WEAK_CONDITION`)."""
        status = np.asarray(self.status).reshape(-1)
        condition = np.broadcast_to(np.asarray(self.condition), np.shape(self.status)).reshape(-1)
        return [
            Status(int(s)).message + (_weak(c) if s == Status.OK and c > WEAK_CONDITION else "")
            for s, c in zip(status, condition)
        ]

    def raise_if_failed(self) -> Calibration:
        """Raise `CalibrationError` naming every camera that failed; return self otherwise."""
        status = np.asarray(self.status).reshape(-1)
        bad = np.flatnonzero(status != Status.OK)
        if bad.size:
            lines = [f"camera {i}: {Status(int(status[i])).message}" for i in bad]
            raise CalibrationError(
                f"{bad.size} of {status.size} cameras failed to calibrate:\n" + "\n".join(lines)
            )
        return self

    def __str__(self) -> str:
        if not _validate.is_concrete(self.status):
            return repr(self)
        names = [Status(int(s)).name.lower() for s in np.asarray(self.status).reshape(-1)]
        return "\n".join(filter(None, [format_table(self.report, status=names),
                                        mirror_note(self)]))  # fmt: skip


# A calibrated camera is said to be poorly determined by its points above this condition number:
# a benchmark trial's 100 points on a 1 x 1 patch, 0.3 px of noise, depth spread 0.03: condition
# 123, focal length 12 % off, status OK (0.3: 13, 1.3 %; the box corner's: 7-8).
WEAK_CONDITION = 100.0


def _weak(condition) -> str:
    return (
        f", but its points barely fix it (condition {condition:.3g}: nearly on one plane, or "
        "few; their noise is amplified as much; a deeper target or more points fix it)"
    )


def mirror_note(
    result: Calibration,
    names=None,
    why: str = "a left-handed world frame, or pixels given as (y, x) or with y up",
) -> str:
    """A line naming the calibrated cameras that see a mirror image of the world (`mirrored`),
    which is legitimate (a left-handed world frame) but is also what pixels given as (y, x)
    look like; "" where there are none."""
    mirrored = np.asarray(result.mirrored).reshape(-1) & np.asarray(result.ok).reshape(-1)
    if not mirrored.any():
        return ""
    names = [str(n) for n in (index_names(np.shape(result.mirrored)) if names is None else names)]
    which = ", ".join(names[i] for i in np.flatnonzero(mirrored))
    cameras = f"cameras {which} see" if mirrored.sum() > 1 else f"camera {which} sees"
    return (
        f"mirrored: {cameras} a mirror image of the world ({why}): they project correctly, "
        "with the points at negative depth; if that is not intended, check the axes."
    )


def calibrate(
    world: Float[Array, "*batch N 3"],
    pixels: Float[Array, "*batch N 2"],
    mask: Bool[Array, "*batch N"] | None = None,
    *,
    skew: bool = True,
    rcond: float | None = None,
    max_relative_rms: float = _dlt.DEFAULT_MAX_RELATIVE_RMS,
    strict: bool = False,
    refine: bool | dict = False,
) -> Calibration:
    """Calibrate every camera of a rig from 3-D/2-D correspondences in one call.

    Runs the normalised DLT (`mvcalib.dlt`), the closed-form decomposition
    (`Camera.from_projection`) and the back-projection report for all cameras at once. A camera
    whose data cannot determine it (fewer than 6 visible points, coplanar or collinear points,
    NaN in traced input, points on both sides of the camera, a reprojection error out of all
    proportion to the image of the target) gets a status
    that says so and NaN parameters; the others are exactly what they would be alone. Nothing
    raises inside `jax.jit`.

    **Arguments:**

    - `world`, `pixels`, `mask`: as for `mvcalib.dlt`.
    - `skew`: estimate the skew (default) or use the paper's skew-free eqs. 19–21.
    - `rcond`: relative threshold on the second-smallest singular value of the normalised DLT
      system (against its Frobenius norm) below which a camera is `Status.DEGENERATE`; default
      sqrt(machine epsilon).
    - `max_relative_rms`: a camera whose reprojection RMS exceeds this fraction of its
      pixels' spread (median distance from their centre) is `Status.POOR_FIT`, with NaN
      parameters; default 0.05, more than twice what the DLT leaves of strong lens distortion.
      One wild correspondence is the usual cause. With `refine`, the refined camera is checked
      instead, over the points it kept (a robust loss's inliers), so that distortion the DLT
      cannot model is refined, not rejected. `inf` turns the check off.
    - `strict`: raise `CalibrationError` if any camera failed (outside `jit` only).
    - `refine`: seed `mvcalib.refine` with the closed-form cameras and return its cameras and
      report: `True` for its defaults (zero skew, distortion k1, k2, p1, p2, least squares), or a
      dict of its keyword arguments, e.g. `dict(distortion=(), loss=mc.Huber(1.0))`. The skew is
      zeroed in the seed unless `skew=True` is among them. Failed cameras stay NaN.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(1), n_cameras=4, noise=0.3)
    >>> result = mc.calibrate(rig.world, rig.pixels, rig.mask)
    >>> bool(result.ok.all()), result.cameras.batch_shape
    (True, (4,))

    ```
    """
    _validate.static_options(
        "calibrate", skew=skew, rcond=rcond, max_relative_rms=max_relative_rms, strict=strict
    )
    # Called with concrete arrays, the rig is padded to its shape bucket (`_buckets`), so that
    # rigs of other sizes reuse the compiled program; checked and padded in NumPy. (A rig of a
    # bucket's shape, or inside the caller's trace, goes as it is.)
    bucketed = _buckets.pads(world, pixels, mask)
    # (checked in NumPy when padded, or when they are NumPy arrays already: compiling nothing)
    host = bucketed or all(isinstance(x, np.ndarray) for x in (world, pixels, mask))
    world, pixels, mask = _validate.correspondences(world, pixels, mask, xp=np if host else jnp)
    rcond = _dlt.default_rcond(world.dtype) if rcond is None else float(rcond)
    max_relative_rms = _dlt.check_relative_rms(max_relative_rms)
    if not isinstance(refine, (bool, dict)):
        traced = isinstance(refine, jax.core.Tracer)
        raise TypeError(
            "`refine` is True, False or a dict of `mvcalib.refine`'s options, e.g. "
            f"dict(distortion=('k1',)); got {'a traced value' if traced else repr(refine)}"
            + (
                ": inside jax.jit, make it static, jax.jit(functools.partial(mc.calibrate, "
                "refine=True))."
                if traced
                else "."
            )
        )
    options = None if refine is False else ({} if refine is True else dict(refine))
    # (with refinement, the fit's check waits for the refined cameras)
    settings = dict(
        skew=skew, rcond=rcond, max_relative_rms=np.inf if options is not None else max_relative_rms
    )
    if options is not None and options.get("loss") is not None:
        # a robust refinement's seed without the wild points a closed form takes at full weight:
        # 256 box-corner cameras with two dots each moved by 50 px, Huber(1.0), 2,959 steps in
        # all against 5,602 and the largest focal-length error 4.8 % against 7.8 % (the same
        # rig without the wild points: 4.3 %)
        settings["robust"] = True
    if bucketed:
        n_points = pixels.shape[-2]
        (world, pixels, mask), batch = _buckets.correspondences(world, pixels, mask)
    # A call from Python of a rig with one camera axis (padded or of its bucket's shape) compiles
    # the refinement on a second thread while the DLT is traced and compiled; the same programs
    # run in the caller's trace, one after the other.
    ahead = options is not None and (
        bucketed or (mask.ndim == 2 and _buckets.applies(world, pixels, mask))
    )
    quick = _dlt.compact(math.prod(mask.shape[:-1]), mask.shape[-1])
    if ahead:
        seed = placeholder(pixels.shape[:-2], pixels.dtype, fill=np.nan)
        refined = _buckets.ahead(_refine_padded, seed, world, pixels, mask, options)
    result = _calibrate(world, pixels, mask, quick=quick, **settings)
    if ahead:
        if refined is not None:  # and the check of its cameras
            check = (world, pixels, mask, max_relative_rms)
            _buckets.ahead(_checked, result, refined, *check, quick=quick)
        n_cameras = math.prod(batch) if bucketed else mask.shape[0]
        result = _refined_bucket(
            result, world, pixels, mask, options, max_relative_rms, n_cameras, quick
        )
    elif options is not None:
        result = _refined(result, world, pixels, mask, options, max_relative_rms, quick)
    if bucketed:
        result = _buckets.cut(result, batch)
        result = _buckets.cut_points(result, _point_arrays, n_points, len(batch))
    if strict and _validate.is_concrete(result.status):
        result.raise_if_failed()
    return result


def _point_arrays(result: Calibration) -> tuple:
    """The arrays of a `Calibration` with a point axis (after the cameras')."""
    report = (result.report.residuals, result.report.mask)
    if result.refinement is None:
        return report
    refinement = result.refinement
    return report + (refinement.inliers, refinement.report.residuals, refinement.report.mask)


def _refined(result, world, pixels, mask, options, max_relative_rms, quick) -> Calibration:
    """`result` refined (inside the caller's trace): the closed form seeds `refine`, and the
    fit's check is made on the refined cameras."""
    _refine = _refiner()
    # Failed cameras have NaN seeds, which `refine` leaves out (result -2); they stay NaN.
    # One camera goes in as a rig of one, where a failed seed is flagged rather than refused.
    seed = result.cameras  # (`refine` zeroes its skew unless it is estimated)
    if _seed_is_forgotten(options):
        seed = jax.lax.stop_gradient(seed)
    if seed.batch_shape:
        refined = _refine.refine(seed, world, pixels, mask, **options)
    else:
        one = lambda x: x[None]  # noqa: E731
        refined = _refine.refine(
            jax.tree_util.tree_map(one, seed), world, one(pixels), one(mask), **options
        )
        refined = jax.tree_util.tree_map(lambda x: x[0], refined)
    return _checked(result, refined, world, pixels, mask, max_relative_rms, quick=quick)


def _seed_is_forgotten(options: dict) -> bool:
    """Whether `refine(**options)` keeps nothing of the DLT's seed: every parameter it holds is
    a constant of that seed (a zero-skew model's skew, the distortion coefficients, zero), none
    is held at the seed's value (`fix` naming intrinsics, pose or skew; the aspect ratio). The
    refined cameras are then the optimum's alone, whose derivatives do not depend on where the
    solve started, and under `grad` the seed's are not carried through the solve only to cancel
    (`jax.grad` of `calibrate(..., refine=True)` of 4 cameras, fresh processes: the first call
    16.9-17.1 s against 19.8-20.5 s; in `jax.jit` 9.75 against 16.3 s, warm 1.34 against 2.27 ms;
    the gradient within 1e-9 relative, what the cancelling left)."""
    _refine = _refiner()
    fix = options.get("fix", ())
    fix = (fix,) if isinstance(fix, str) else tuple(fix)
    try:
        free = _refine._free_parameters(options.get("distortion"), fix, options.get("skew", False))
    except (ValueError, TypeError):  # (`refine` says what is wrong)
        return False
    names = _refine.PARAMETERS
    held = {name for i, name in enumerate(names) if i not in free}
    constant = set(_refine.DISTORTION) | ({"skew"} - set(fix))
    return not getattr(free, "tied", False) and held <= constant


def _refined_bucket(
    result, world, pixels, mask, options, max_relative_rms, n_cameras, quick
) -> Calibration:
    """`_refined` of a rig of its bucket's shape (padded or not) called from Python, as the same
    compiled programs that `calibrate` and `refine` called one after the other run: the same
    cameras to the last bit. The seed is made in NumPy, the cameras after the first `n_cameras`
    (the padding's) NaN: their problems end at once."""

    def padding_nan(x):
        x = np.array(x)
        x[n_cameras:] = np.nan
        return x

    seed = jax.tree_util.tree_map(padding_nan, result.cameras)
    refined = _refine_padded(seed, world, pixels, mask, options)
    return _checked(result, refined, world, pixels, mask, max_relative_rms, quick=quick)


def _refine_padded(seed, world, pixels, mask, options):
    """`refine` of a rig already padded to its bucket."""
    return _refiner().refine(seed, world, pixels, mask, **options)


def poorly_fitted(refined, pixels, mask, max_relative_rms):
    """Where a refinement's camera fits its points poorly (`_dlt.poor_fit`): its RMS over the
    points the fit kept (a robust loss's inliers; all visible points for least squares) above
    `max_relative_rms` of their spread."""
    rms_kept = residual_rms(refined.report.residuals, refined.inliers)
    sort = _dlt.compact(math.prod(mask.shape[:-1]), mask.shape[-1])
    return _dlt.poor_fit(rms_kept, pixels, mask, max_relative_rms, sort)


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _checked(result, refined, world, pixels, mask, max_relative_rms) -> Calibration:
    """`result` with the refined cameras and report, each camera checked (`_dlt.poor_fit`) over
    the points the fit kept (a robust loss's inliers; all visible points for least squares)."""
    poor = poorly_fitted(refined, pixels, mask, max_relative_rms)
    status = jnp.where(result.ok & poor, Status.POOR_FIT, result.status).astype(jnp.int32)
    ok = status == Status.OK
    cameras = jax.tree_util.tree_map(
        lambda x: jnp.where(ok.reshape(ok.shape + (1,) * (x.ndim - ok.ndim)), x, jnp.nan),
        refined.cameras,
    )
    return eqx.tree_at(
        lambda r: (r.cameras, r.report, r.refinement, r.status),
        result,
        (cameras, refined.report, refined, status),
        is_leaf=lambda x: x is None,
    )


@functools.partial(_buckets.jit, static_argnames=("skew", "robust"))
def _calibrate(
    world, pixels, mask, skew: bool, rcond: float, max_relative_rms: float, robust: bool = False
) -> Calibration:
    """DLT, decomposition and report for validated inputs, compiled into one computation; with
    `robust` (the seed of a refinement with a robust loss), the DLT fitted again without the
    points far off it (`_dlt.refit_near`)."""
    fit = _dlt.solve_validated(world, pixels, mask, rcond, max_relative_rms)
    if robust:
        fit = _dlt.refit_near(world, pixels, mask, fit, rcond, max_relative_rms)
    P, status, condition, mirrored = fit
    cameras = Camera.from_projection(P, skew=skew)
    report = compute_report(cameras, world, pixels, mask)
    return Calibration(
        cameras=cameras, P=P, report=report, status=status, condition=condition, mirrored=mirrored
    )
