"""The pose of a known target seen by calibrated cameras: OpenCV's `solvePnP`, batched.

Each view's pose comes from a closed form on its pixels with the camera's own lens distortion
removed (a planar target's homography and the camera's K, Zhang's eq. 10; a 3-D target's DLT),
as `calibrate_rig` starts its (camera, frame) pairs, and is then refined by `refine` with every
intrinsic parameter and distortion coefficient held: one compiled call for all views of either.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from . import _buckets, _dlt, _validate
from ._camera import Camera, undistort_points
from ._pipeline import poorly_fitted
from ._planar import MIN_PLANE_POINTS, _plane_frame
from ._refine import POOR_FIT, TOO_FEW_POINTS, Cauchy, Huber, Refinement, refine
from ._rig import _pair_poses_object, _pair_poses_planar
from ._status import Status

# Every parameter of the camera but its pose is held.
_HELD = ("intrinsics", "skew", "distortion")


def solve_pnp(
    cameras: Camera,
    target: Float[Array, "N 3"],
    pixels: Float[Array, "*batch N 2"],
    mask: Bool[Array, "*batch N"] | None = None,
    *,
    loss: Huber | Cauchy | None = None,
    rcond: float | None = None,
    max_relative_rms: float = _dlt.DEFAULT_MAX_RELATIVE_RMS,
    max_steps: int = 100,
) -> Refinement:
    """The pose of a known target in every view of calibrated cameras (OpenCV's `solvePnP`).

    Each view's pose starts from a closed form on its pixels with the camera's distortion
    removed (a planar target: its homography and the camera's K; a 3-D target: the DLT) and is
    refined by Levenberg–Marquardt on the reprojection error with the camera's intrinsics, skew
    and distortion held: `refine(seed, target, pixels, mask, fix=("intrinsics", "skew",
    "distortion"))`, which is what this returns. All views are solved in one compiled call.

    **Arguments:**

    - `cameras`: the calibrated cameras (pinhole or fisheye); their poses are not used. They
      broadcast against the leading axes of `pixels` as NumPy's arrays do: one camera for many
      views (`pixels (V, N, 2)`), a rig of C cameras each seeing the target once (`(C, N, 2)`),
      or, for F frames of each, `rig[:, None]` with `pixels (C, F, N, 2)`.
    - `target`: `(N, 3)` the target's points in its own frame (or `(N, 2)`, a board at z = 0): a
      plane (4 or more points) or a 3-D object (6 or more), concrete (not traced).
    - `pixels`, `mask`: where each view saw each point, and which points it saw (default: the
      finite pixels).
    - `loss`: `None` for least squares, or `Huber(scale)` / `Cauchy(scale)` in pixels, to bound
      the influence of wrong detections. (A 3-D target's detection wrong by more than about 5 %
      of the view's spread of pixels spoils its closed form, the DLT, and the view is flagged:
      leave it out in `mask`, or refine a pose from elsewhere with `refine(..., loss=...)`.)
    - `rcond`: relative cut-off of the closed form's smallest singular values (default
      `sqrt(eps)`).
    - `max_relative_rms`: a view whose pose fits its points (those the loss keeps) with an RMS
      above this fraction of their spread is flagged, as `calibrate` flags a camera.
    - `max_steps`: iteration limit per view; reaching it is reported, not raised.

    **Returns:** a `Refinement` with one entry per view: `cameras` placed so that the target's
    frame is the world's (`cameras.R`, `cameras.t` are OpenCV's `rvec` as a matrix and `tvec`:
    `x_cam = R X + t`), the reprojection RMS of the closed form (`rms_before`) and of the result
    (`rms_after`), and the standard errors of the pose (`std("rx")` in radians, `std("tx")` in
    the target's units). Each view is checked, and a failed one has a NaN pose: `result == -1`
    with fewer points than the closed form needs (4 of a plane, 6 of a 3-D target), `-2` where
    it fails (points collinear, a DLT that does not fit them), `-3` where the pose fits its
    points poorly (`max_relative_rms`: a wrong correspondence); `messages()` says which.
    Derivatives with respect to `pixels` and the cameras' intrinsics and distortion are those
    of the optimum (implicit).

    **Example:**

    ```python
    >>> import jax, jax.numpy as jnp, numpy as np, mvcalib as mc
    >>> board = mc.targets.dot_grid(6, 8, 30.0).points  # mm
    >>> camera = mc.Camera(800.0, 800.0, 320.0, 240.0, mc.rodrigues(jnp.array([0.3, -0.2, 0.1])),
    ...                    jnp.array([-100.0, -70.0, 500.0]), dist=jnp.array([-0.2, 0.05, 0, 0, 0]))
    >>> pixels = camera.project(board)
    >>> pose = mc.solve_pnp(camera, board, pixels)
    >>> np.allclose(pose.cameras.t, camera.t), float(pose.rms_after) < 1e-3  # pixels
    (True, True)
    >>> pose.cameras.R.shape, pose.std("tz").shape  # one view: no batch axes
    ((3, 3), ())

    ```
    """
    if not isinstance(cameras, Camera):
        raise ValueError(f"`cameras` must be an mvcalib.Camera; got {type(cameras).__name__}.")
    if isinstance(target, jax.core.Tracer):
        raise ValueError(
            "`target` must be concrete (not traced): whether it is a plane decides the closed "
            "form. Pass it as a constant to your `jax.jit`ed function."
        )
    target = np.asarray(target)
    if target.ndim == 2 and target.shape[-1] == 2:  # a board's x, y at z = 0
        target = np.concatenate([target, np.zeros_like(target[:, :1])], -1)
    if target.ndim != 2 or target.shape[-1] != 3:
        raise ValueError(f"`target` must have shape (N, 3) or (N, 2); got {target.shape}.")
    planar = _validate.is_planar(target)
    concrete = _buckets.applies(cameras, pixels, mask)
    xp = np if concrete else jnp
    world, pixels, mask = _validate.correspondences(target, pixels, mask, min_points=4, xp=xp)
    views = tuple(np.broadcast_shapes(pixels.shape[:-2], mask.shape[:-1]))
    try:
        fits = np.broadcast_shapes(cameras.batch_shape, views) == views
    except ValueError:
        fits = False
    if not fits:
        raise ValueError(
            f"the cameras have batch shape {cameras.batch_shape}, which does not broadcast to "
            f"the views {views} (the leading axes of `pixels`); for F frames of each of C "
            "cameras pass `cameras[:, None]` with `pixels (C, F, N, 2)`."
        )
    if concrete:
        intrinsics = [cameras.alpha_u, cameras.alpha_v, cameras.u0, cameras.v0, cameras.dist]
        if not all(np.all(np.isfinite(np.asarray(x))) for x in intrinsics):
            raise ValueError(
                "a camera's intrinsics or distortion are not finite (a camera whose calibration "
                "failed is NaN): only calibrated cameras have a pose to solve for."
            )
    plane = _plane_frame(target, np.ones(len(target), bool), world.dtype) if planar else None
    rcond = float(np.sqrt(np.finfo(world.dtype).eps)) if rcond is None else float(rcond)
    options = dict(
        loss=loss,
        max_steps=max_steps,
        max_relative_rms=_dlt.check_relative_rms(max_relative_rms),
        minimum=MIN_PLANE_POINTS if planar else _validate.MIN_POINTS,
    )
    n = pixels.shape[-2]
    if concrete:  # one flat axis of views, padded to its bucket: other numbers reuse the programs
        (world, pixels, mask), _ = _buckets.correspondences(world, pixels, mask)
        cameras = jax.tree_util.tree_map(
            lambda x: _buckets.pad(x, 0, len(pixels)), _flat(cameras, views, np)
        )
    else:  # (in the caller's program)
        pixels = jnp.broadcast_to(pixels, views + (n, 2)).reshape(-1, n, 2)
        mask = jnp.broadcast_to(mask, views + (n,)).reshape(-1, n)
        cameras = _flat(cameras, views, jnp)
    quick = math.prod(mask.shape) <= _buckets.COMPACT  # (a small program compiles quickly)
    seed = _closed_form(cameras, world, plane, pixels, mask, planar=planar, rcond=rcond,
                        quick=quick)  # fmt: skip
    if concrete and not views and not np.all(np.isfinite(np.asarray(seed.t[0]))):
        raise ValueError(
            f"the view's {int(np.sum(mask[0]))} points give no closed-form pose: too few (a "
            f"{'plane needs 4' if planar else '3-D target needs 6'}), collinear, or a DLT that "
            "does not fit them (wrong correspondences?)."
        )
    if not concrete:
        # The refinement estimates every pose (only the camera's own parameters are held): the
        # closed form's derivatives of the poses would go through its solve only to cancel (8
        # views, fresh processes: the first `jax.grad` 14.9 against 16.5 s, in `jax.jit` 12.0
        # against 15.4 s)
        seed = eqx.tree_at(lambda c: (c.R, c.t), seed, jax.lax.stop_gradient((seed.R, seed.t)))
    out = _solved(seed, world, pixels, mask, quick=quick, **options)
    if concrete:
        out = _buckets.cut(out, views)
        return _buckets.cut_points(out, _point_arrays, n, len(views))
    return jax.tree_util.tree_map(lambda x: x.reshape(views + x.shape[1:]), out)


def _point_arrays(out: Refinement) -> tuple:
    return out.inliers, out.report.residuals, out.report.mask


def _solved(seed, world, pixels, mask, *, loss, max_steps, max_relative_rms, minimum, quick):
    """`refine` of the seeded poses (`(V,)` cameras, `pixels (V, N, 2)`), each checked: too few
    points for the closed form, -1; a pose that fits the points it kept poorly, -3 (NaN)."""
    out = refine(seed, world, pixels, mask, distortion=(), fix=_HELD, loss=loss,
                 max_steps=max_steps)  # fmt: skip
    return _checked(out, pixels, mask, max_relative_rms, minimum, quick=quick)


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _checked(out: Refinement, pixels, mask, max_relative_rms, minimum) -> Refinement:
    """`out` with each view checked as `calibrate` checks a camera (`poorly_fitted`), and
    flagged with a NaN pose where it fails."""
    poor = poorly_fitted(out, pixels, mask, max_relative_rms)
    result = jnp.where((out.result == 0) & poor, POOR_FIT, out.result)
    result = jnp.where(jnp.sum(mask, -1) < minimum, TOO_FEW_POINTS, result).astype(jnp.int32)
    flagged = result != out.result
    cameras = jax.tree_util.tree_map(
        lambda x: jnp.where(flagged.reshape(flagged.shape + (1,) * (x.ndim - 1)), jnp.nan, x),
        out.cameras,
    )
    return eqx.tree_at(lambda r: (r.cameras, r.result), out, (cameras, result))


def _flat(cameras: Camera, views: tuple[int, ...], xp) -> Camera:
    """`cameras` broadcast to `views` and flattened to one axis."""
    batch = len(cameras.batch_shape)

    def one(x):
        tail = x.shape[batch:]
        return xp.broadcast_to(xp.asarray(x), views + tail).reshape((-1,) + tail)

    return jax.tree_util.tree_map(one, cameras)


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _closed_form(cameras, world, plane, pixels, mask, *, planar, rcond) -> Camera:
    """Each view's camera placed by the closed form on its undistorted pixels: `(V,)` cameras,
    `pixels (V, N, 2)`, `mask (V, N)`; NaN poses where it fails."""
    dtype = pixels.dtype
    cameras = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), cameras)
    one_frame = jax.tree_util.tree_map(lambda x: x[:, None], cameras)  # (V, 1): a rig's layout
    xy = undistort_points(one_frame, pixels[:, None])
    seen = mask[:, None] & jnp.all(jnp.isfinite(xy), -1)  # (a fisheye's beyond 90 degrees: NaN)
    xy = jnp.where(seen[..., None], xy, 0.0)
    if planar:
        board = plane.apply(world)[:, :2]
        _, _, R, t, status, _ = _pair_poses_planar(plane, board, xy, seen, cameras.K, rcond)
    else:
        _, _, R, t, status, _ = _pair_poses_object(world, xy, seen, cameras.K, rcond)
    R, t = R[:, 0], t[:, 0]
    ok = (status[:, 0] == Status.OK) & jnp.all(jnp.isfinite(R), (-2, -1))
    ok = ok & jnp.all(jnp.isfinite(t), -1)
    R = jnp.where(ok[:, None, None], R, jnp.nan)
    t = jnp.where(ok[:, None], t, jnp.nan)
    return eqx.tree_at(lambda c: (c.R, c.t), cameras, (R, t))
