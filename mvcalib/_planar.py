"""Calibration of one camera from several views of a planar target (Zhang 1998/2000): per-view
homographies, the closed-form intrinsics, the poses, then a joint refinement with distortion."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _buckets, _status, _validate
from ._camera import LENSES, Camera, check_lens, lens_of, placeholder
from ._dlt import (
    DEFAULT_MAX_RELATIVE_RMS,
    REFITS,
    _design_matrix,
    _masked_median,
    _null_vector,
    _similarity,
    check_relative_rms,
    near,
    poor_fit,
)
from ._pipeline import CalibrationError
from ._refine import (
    _RESULT_MESSAGES,
    GROUPS,
    Cauchy,
    Free,
    Huber,
    _free_parameters,
    _ratio,
    _robust_model,
    _robust_residuals,
    check_loss,
    default_solver,
    parameter_names,
    takes_model,
)
from ._registration import RigidTransform
from ._report import ReprojectionReport, compute_report, format_table
from ._rotation import hat, nearest_rotation, rodrigues
from ._status import Status

MIN_PLANE_POINTS = 4  # a homography has 8 degrees of freedom; each point gives 2 equations
# What the refinement estimates of each lens's distortion by default: Zhang's radial model; all
# of cv2.fisheye's four.
DEFAULT_DISTORTION = {"pinhole": ("k1", "k2"), "fisheye": LENSES["fisheye"]}
# A concrete call's views are padded with unseen ones up to `_buckets.size(V, MIN_VIEWS,
# bits=VIEW_BITS)` (16, 24, 32, 48, 64, ...: at most half as many again), so that another number
# of photos reuses the programs compiled. One camera, 15, 20, 25, 30 and 40 views of a 9 x 12
# board in turn from a fresh process: 1.2-1.4 s each; with the buckets 1.4-1.9 s a new bucket,
# and 0.1 s for 30 views (25's bucket); warm 17-37 ms against 15-28.
MIN_VIEWS, VIEW_BITS = 16, 2
POSE = GROUPS["pose"]  # one per view; the other parameters have one value for every view

_MESSAGES = {
    Status.OK: "calibrated",
    Status.TOO_FEW_POINTS: "fewer than 4 visible points: the view's homography is not determined",
    Status.DEGENERATE: (
        "degenerate: the view's visible points are collinear, but for one at most, or repeated (no "
        "homography), or the views together do not determine the intrinsics (e.g. every view "
        "parallel to the others)"
    ),
    Status.NON_FINITE: "NaN or inf among the visible points",
    Status.POOR_FIT: (
        "poor fit: the refined view's RMS exceeds `max_relative_rms` (default 5 %) of its pixels' "
        "spread and 3 times the median view's (its pose in another minimum, or wrong points); "
        "left out, the camera calibrated from the other views"
    ),
}


class PlanarCalibration(eqx.Module):
    """The result of `calibrate_planar`: one camera seen in several views of a plane.

    - `camera`: a rig of `V` views, `(V,)`: the same intrinsics and distortion in every view
      (`K` and `dist` below), the target's pose per view. Views that failed are NaN.
    - `closed_form`: the same rig from the closed form, before refinement (Zhang's, or one
      focal length where that reprojects the views better; pinhole, no distortion); equal to
      `camera` when `refine=False`.
    - `homographies`: `(V, 3, 3)`, unit Frobenius norm, mapping the target's plane coordinates
      `(x, y, 1)` (in the frame `plane`) to pixels.
    - `plane`: the rigid transform from world coordinates to the plane's frame, in which the
      target is `z = 0` (the identity when the points already lie in `z = 0`).
    - `report`: reprojection errors per view (Table I; `report.rms` is `view_rms`).
    - `rms`: the reprojection RMS over every visible point of the views that succeeded.
    - `status`: a `Status` per view; `ok` is `status == Status.OK`; `messages()` says why.
    - `condition`: condition number of the normalised linear system `V b = 0` for the
      intrinsics (largest over second-smallest singular value): large means the views barely
      constrain the intrinsics (too similar orientations).
    - `iterations`: Levenberg–Marquardt steps of the refinement (0 with `refine=False`).
    - `result`: its outcome, the integer index of an `optx.RESULTS` member (0 = successful, also
      with `refine=False`); `converged` is `result == 0`, `result_message()` spells it out.
    - `covariance` `(P, P)`, `standard_errors` `(P,)` (and `std(name)`): of the refined
      intrinsics and distortion `parameter_names` (those estimated, shared by every view), the
      views' poses' uncertainty included, `sigma^2` from the residuals (as OpenCV's
      `calibrateCameraExtended`'s `stdDeviationsIntrinsics`); NaN with `refine=False` or a
      `solver` of your own. Large ones say the views do not fix a parameter: a lens's
      distortion fitted from views of a narrow field, extrapolated beyond it.
    """

    camera: Camera
    closed_form: Camera
    homographies: Float[Array, "V 3 3"]
    plane: RigidTransform
    report: ReprojectionReport
    rms: Float[Array, ""]
    status: Int[Array, " V"]
    condition: Float[Array, ""]
    iterations: Int[Array, ""]
    result: Int[Array, ""]
    covariance: Float[Array, "P P"]
    parameter_names: tuple[str, ...] = eqx.field(static=True)

    @property
    def standard_errors(self) -> Float[Array, " P"]:
        return _validate.derived(
            lambda xp, c: xp.sqrt(xp.diagonal(c, axis1=-2, axis2=-1)), self.covariance
        )

    def std(self, name: str) -> Float[Array, ""]:
        """The standard error of one parameter, by name (one of `parameter_names`)."""
        if name not in self.parameter_names:
            raise ValueError(
                f"{name!r} is not among the parameters estimated: {self.parameter_names}."
            )
        return self.standard_errors[..., self.parameter_names.index(name)]

    @property
    def K(self) -> Float[Array, "3 3"]:
        """The intrinsic matrix shared by every view (the first calibrated view's: the views
        that failed are NaN)."""
        return self._shared(self.camera.K)

    @property
    def dist(self) -> Float[Array, " K"]:
        """The distortion shared by every view: `(k1, k2, p1, p2, k3)`, a fisheye's `(k1, k2,
        k3, k4)`."""
        return self._shared(self.camera.dist)

    def _shared(self, per_view):
        """`per_view` `(..., V, ...)` at each calibration's first calibrated view (also for a
        batch of calibrations, e.g. from `jax.vmap`: it took the first calibration's)."""

        def first_ok(xp, x, s):
            axis = s.ndim - 1  # the views'
            i = xp.argmax(s == Status.OK, axis=-1)
            i = i.reshape(i.shape + (1,) * (x.ndim - axis))
            return xp.take_along_axis(x, i, axis=axis).squeeze(axis)

        return _validate.derived(first_ok, per_view, self.status)

    @property
    def view_rms(self) -> Float[Array, " V"]:
        return self.report.rms

    @property
    def ok(self) -> Bool[Array, " V"]:
        return self.status == Status.OK

    @property
    def converged(self) -> Bool[Array, ""]:
        return self.result == 0

    def result_message(self) -> str:
        return _RESULT_MESSAGES[int(self.result)]

    def messages(self) -> list[str]:
        """One line per view, saying whether and why it failed."""
        return [_MESSAGES[Status(int(s))] for s in np.asarray(self.status).reshape(-1)]

    def raise_if_failed(self) -> PlanarCalibration:
        """Raise `CalibrationError` naming every view that failed, or saying why the refinement
        did not converge; return self otherwise."""
        status = np.asarray(self.status).reshape(-1)
        bad = np.flatnonzero(status != Status.OK)
        lines = [f"view {i}: {_MESSAGES[Status(int(status[i]))]}" for i in bad]
        if int(self.result) != 0:
            lines.append(f"refinement: {self.result_message()}")
        if lines:
            raise CalibrationError(
                f"planar calibration failed ({bad.size} of {status.size} views):\n"
                + "\n".join(lines)
            )
        return self

    def __str__(self) -> str:
        if not _validate.is_concrete(self.status):
            return repr(self)
        names = [Status(int(s)).name.lower() for s in np.asarray(self.status).reshape(-1)]
        table = format_table(self.report, status=names)
        table = table.replace("per camera", "per view").replace("camera", "  view", 1)
        # which lens model was fitted: OpenCV's calibrateCamera fits five coefficients by
        # default, this two (an OpenCV user's trial compared them unawares)
        held = [c for c in LENSES[self.camera.lens] if c not in self.parameter_names]
        return (
            f"{table}\none camera from {sum(n == 'ok' for n in names)} of {len(names)} views: RMS "
            f"{float(self.rms):.4f} px; estimated {' '.join(self.parameter_names)}"
            + (f"; held {' '.join(held)}" if held else "")
        )


# ------------------------------------------------------------------------------ kernels
def _smallest_right_singular(A):
    """The null vector of `A` and its singular values, padding rows so that SVD returns it."""
    rows, cols = A.shape
    if rows < cols:
        A = jnp.concatenate([A, jnp.zeros((cols - rows, cols), A.dtype)])
    return _null_vector(A)


# A view's homography is fitted again without the points far off the last fit
# (`_homography_kernel`, `_dlt.near`). One wild point in a view (1 % of a 6 x 8 board's corners
# moved by 50 px; `board_rig` key 1, camera 0) turned its closed-form pose by up to 118 degrees:
# the refinement left such views in another minimum, the focal length 1.4 % off against 0.1 %
# without the wild points. A gate of 5 (not `_dlt.GATE`'s 10) cut the corners of views with strong
# barrel distortion (k1 = -0.25, whose homographies fit their corners worst) and moved the start
# of `tests/test_planar.py`'s views.


def _fit_homography(plane, pixels, used):
    """The homography of the plane points (N, 2) to the pixels (N, 2) used (N,), by the normalised
    DLT (Hartley's normalisation of both point sets, SVD), and the singular values."""
    w = used.astype(plane.dtype)
    T1, _, _ = _similarity(plane, w)
    T2, s2, c2 = _similarity(pixels, w)
    a = plane @ T1[:2, :2].T + T1[:2, 2]
    b = pixels @ T2[:2, :2].T + T2[:2, 2]
    v, sv = _smallest_right_singular(_design_matrix(a, b, used))
    T2_inv = jnp.array([[1 / s2, 0, c2[0]], [0, 1 / s2, c2[1]], [0, 0, 1]], dtype=plane.dtype)
    H = T2_inv @ v.reshape(3, 3) @ T1
    return H / jnp.linalg.norm(H), sv


def _homography_kernel(plane, pixels, mask, rcond):
    """One view: plane points (N, 2), pixels (N, 2), mask (N,) -> H (3, 3), status. Fitted to
    every visible point, then again without those far off the fit (`_dlt.near`)."""
    finite = jnp.all(jnp.isfinite(plane), -1) & jnp.all(jnp.isfinite(pixels), -1)
    all_finite = jnp.all(finite | ~mask)
    visible = mask & finite
    # Hidden points are replaced before any arithmetic (as in the DLT): no influence at all.
    plane = jnp.where(visible[:, None], plane, 0.0)
    pixels = jnp.where(visible[:, None], pixels, 0.0)
    H, sv = _fit_homography(plane, pixels, visible)
    used = visible
    for _ in range(REFITS):
        p = plane @ H[:, :2].T + H[:, 2]
        kept = near(jnp.linalg.norm(p[:, :2] / p[:, 2:] - pixels, axis=-1), visible)
        again = (jnp.sum(kept) >= MIN_PLANE_POINTS) & (jnp.sum(kept) < jnp.sum(visible))
        H_kept, sv_kept = _fit_homography(plane, pixels, kept)
        H, sv = jnp.where(again, H_kept, H), jnp.where(again, sv_kept, sv)
        used = jnp.where(again, kept, used)
    degenerate = ~(sv[-2] > rcond * sv[0]) | ~_general_position(plane, used)
    status = jnp.select(
        [~all_finite, jnp.sum(visible) < MIN_PLANE_POINTS, degenerate],
        [Status.NON_FINITE, Status.TOO_FEW_POINTS, Status.DEGENERATE],
        Status.OK,
    ).astype(jnp.int32)
    return H, status


def _general_position(plane, used, tolerance=1e-3):
    """Whether four of the `used` plane points `(N, 2)` have no three on a line, as a homography
    needs: else all of them but one at most lie on a line (within `tolerance` of their spread),
    and the pixels' noise alone decides the homography. (A board seen along one row and one
    more corner: `board_rig` key 0, 5 cameras x 41 frames, camera 1 in frame 7. Its pose came
    out 105 degrees off, and the joint solve with the cameras' intrinsics given ended there
    after 100 steps, that frame at 16 px and the rig at 0.83 px RMS against 0.42.)

    Each point is left out in turn; the rest's scatter must have two comparable axes."""
    w = used.astype(plane.dtype)
    n = jnp.sum(w)
    centred = plane - jnp.sum(w[:, None] * plane, 0) / jnp.maximum(n, 1.0)
    outer = centred[:, :, None] * centred[:, None, :]  # (N, 2, 2)
    total = jnp.einsum("n,nij->ij", w, outer)
    first = jnp.einsum("n,ni->i", w, centred)
    # the scatter of the others about their mean, for every point left out
    rest = jnp.maximum(n - w, 1.0)[:, None, None]
    mean = (first - w[:, None] * centred)[:, :, None] / rest
    scatter = (total - w[:, None, None] * outer) / rest - mean * jnp.swapaxes(mean, 1, 2)
    trace = scatter[:, 0, 0] + scatter[:, 1, 1]
    det = scatter[:, 0, 0] * scatter[:, 1, 1] - scatter[:, 0, 1] ** 2
    # the smaller axis over the larger, squared: det / larger^2 (no cancellation in the root)
    larger = trace / 2 + jnp.sqrt(jnp.maximum(trace**2 / 4 - det, 0.0))
    flat = det <= tolerance**2 * larger**2
    return (n >= 4) & ~jnp.any(used & flat)


def _v(H, i, j):
    """Zhang's v_ij (eq. 8): h_i^T B h_j = v_ij^T b, b = (B11, B12, B22, B13, B23, B33)."""
    hi, hj = H[:, i], H[:, j]
    return jnp.stack(
        [
            hi[0] * hj[0],
            hi[0] * hj[1] + hi[1] * hj[0],
            hi[1] * hj[1],
            hi[2] * hj[0] + hi[0] * hj[2],
            hi[2] * hj[1] + hi[1] * hj[2],
            hi[2] * hj[2],
        ]
    )


def _intrinsics(H, ok, T, skew, rcond):
    """Zhang's closed form: K from the homographies H (V, 3, 3) of the views with `ok`.

    The homographies are first expressed in normalised pixels (`T`, a similarity), so that the
    unknowns of B = K^-T K^-1 have comparable sizes; K = T^-1 K' keeps the triangular form.
    `skew` is a traced boolean, so both models share one compiled function.
    """
    Hn = T @ H
    Hn = Hn / jnp.linalg.norm(Hn, axis=(-2, -1), keepdims=True)
    # eq. 9: the two constraints per view, r1 . r2 = 0 and |r1| = |r2|
    rows = jax.vmap(lambda h: jnp.stack([_v(h, 0, 1), _v(h, 0, 0) - _v(h, 1, 1)]))(Hn)
    rows = jnp.where(ok[:, None, None], rows, 0.0).reshape(-1, 6)
    # Zero skew is B12 = -gamma / (alpha^2 beta) = 0: B12's column is removed from the data and
    # replaced by one row c e2 with c >= every singular value of the rest, so the smallest
    # singular vector is exactly the 5-unknown solution with B12 = 0.
    e2 = jnp.zeros(6, rows.dtype).at[1].set(1.0)
    rows = jnp.where(skew, rows, rows * (1.0 - e2))
    rows = jnp.concatenate([rows, jnp.where(skew, 0.0, jnp.linalg.norm(rows)) * e2[None]])
    b, sv = _smallest_right_singular(rows)
    b = b * jnp.where(skew, 1.0, 1.0 - e2)  # exactly 0, not 1e-17
    B = jnp.array([[b[0], b[1], b[3]], [b[1], b[2], b[4]], [b[3], b[4], b[5]]])
    B = B * jnp.sign(B[0, 0])  # B is positive definite up to the SVD's sign
    # B = K^-T K^-1 = L L^T (Cholesky) with K^-1 = L^T upper triangular; NaN unless B > 0.
    K_inv = jnp.linalg.cholesky(B).T
    Kn = jnp.linalg.inv(K_inv)
    Kn = Kn / Kn[2, 2]
    s, c = T[0, 0], -T[:2, 2] / T[0, 0]  # T^-1 of the similarity, explicitly: exact zeros stay
    T_inv = jnp.array([[1 / s, 0, c[0]], [0, 1 / s, c[1]], [0, 0, 1]], dtype=T.dtype)
    K = T_inv @ Kn
    condition = sv[0] / sv[-2]
    determined = (sv[-2] > rcond * sv[0]) & jnp.all(jnp.isfinite(K))
    return K, condition, determined


def _focal_lengths(H, ok, pixels, seen):
    """Each camera's starting intrinsics from its homographies: the principal point `c` fixed
    (the centre of the box around the pixels seen, as OpenCV's `initIntrinsicParams2D` takes
    the image's), zero skew, and one focal length from each frame by Zhang's two constraints
    (least squares in `1 / f^2`), the median over the frames that give one; found where there
    is one.

    The start before 2026-12-05, one least squares in `1 / fx^2`, `1 / fy^2` over all frames at
    once (OpenCV's in outline, without its normalisation of each constraint), was pulled far off
    by a few frames: 16 cameras x 250 frames of a 6 x 8 board (key 7), camera 10 at 10.1 times
    its focal length, from where its own solve and the rig's wandered off (every camera
    POOR_FIT); 20 such rigs of 16 and 64 cameras x 100 and 250 frames, up to 9.1 times (the
    median camera 8 % off). The median: at most 25 % off on the same rigs (the median camera
    5 %). OpenCV's own (`cv2.initCameraMatrix2D`, the image's centre) on key 7's frames: 1.05,
    1.12 and 1.49 times for cameras 10, 13 and 2; the median 1.10, 1.07 and 1.14."""
    big = jnp.finfo(pixels.dtype).max
    seen = seen.reshape(-1)
    lo = jnp.min(jnp.where(seen[:, None], pixels.reshape(-1, 2), big), 0)
    hi = jnp.max(jnp.where(seen[:, None], pixels.reshape(-1, 2), -big), 0)
    c = 0.5 * (lo + hi)
    scale = jnp.maximum(hi[0] - lo[0], hi[1] - lo[1])  # pixels in units of the box: conditioning
    T = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, scale]], pixels.dtype)
    T = T.at[0, 2].set(-c[0]).at[1, 2].set(-c[1])
    Hc = jnp.einsum("ij,fjk->fik", T, H)
    h1, h2 = Hc[:, :, 0], Hc[:, :, 1]
    # h1' w h2 = 0 and h1' w h1 = h2' w h2, with w = diag(1 / f^2, 1 / f^2, 1)
    a = jnp.stack(
        [
            h1[:, 0] * h2[:, 0] + h1[:, 1] * h2[:, 1],
            h1[:, 0] ** 2 - h2[:, 0] ** 2 + h1[:, 1] ** 2 - h2[:, 1] ** 2,
        ],
        -1,
    )
    b = -jnp.stack([h1[:, 2] * h2[:, 2], h1[:, 2] ** 2 - h2[:, 2] ** 2], -1)
    x = jnp.sum(a * b, -1) / jnp.sum(a * a, -1)  # 1 / f^2 per frame
    gives = ok & (x > 0) & jnp.isfinite(x)
    f = scale / jnp.sqrt(_masked_median(x, gives, sort=True))
    found = jnp.isfinite(f)
    f = jnp.where(found, f, 1.0)
    zero, one = jnp.zeros_like(c[0]), jnp.ones_like(c[0])
    K = jnp.array([[f, zero, c[0]], [zero, f, c[1]], [zero, zero, one]])
    return K, found


def _pose(K, H, plane, mask):
    """Zhang's eq. 10: r1 = l K^-1 h1, r2 = l K^-1 h2, t = l K^-1 h3, R orthonormalised."""
    M = jnp.linalg.solve(K, H)
    lam = 2.0 / (jnp.linalg.norm(M[:, 0]) + jnp.linalg.norm(M[:, 1]))
    # H's sign is the SVD's: pick the one that puts the visible points in front of the camera.
    depth = plane @ M[2, :2] + M[2, 2]
    lam = lam * jnp.where(jnp.sum(jnp.where(mask, depth, 0.0)) < 0, -1.0, 1.0)
    r1, r2, t = lam * M[:, 0], lam * M[:, 1], lam * M[:, 2]
    R = nearest_rotation(jnp.stack([r1, r2, jnp.cross(r1, r2)], -1))
    return R, t


def _posed(K, H, plane, pixels, mask, seen):
    """Each view's pose from its homography and `K` (`_pose`, the sign from the points `mask`),
    and the RMS distance of the pixels `seen` of every view from the plane's points through
    them (no distortion; NaN for a NaN `K`)."""
    R, t = jax.vmap(_pose, (None, 0, None, 0))(K, H, plane, mask)
    x = jnp.einsum("vij,nj->vni", R[..., :2], plane) + t[:, None]
    uv = jnp.einsum("ij,vnj->vni", K, x)
    square = jnp.sum((uv[..., :2] / uv[..., 2:] - pixels) ** 2, -1)
    rms = jnp.sqrt(jnp.sum(jnp.where(seen, square, 0.0)) / jnp.maximum(jnp.sum(seen), 1))
    return R, t, rms


@functools.partial(_buckets.jit, static_argnames="rcond")
def _closed_form(world, plane, pixels, mask, skew, rcond: float):
    """Homographies, intrinsics and poses for validated input, in one compiled call."""
    # Hidden points are replaced before any arithmetic, so their values (even NaN) never count.
    pixels = jnp.where(mask[..., None], pixels, 0.0)
    plane_xy = jnp.where(jnp.any(mask, 0)[:, None], plane.apply(world)[:, :2], 0.0)
    H, status = jax.vmap(functools.partial(_homography_kernel, rcond=rcond), (None, 0, 0))(
        plane_xy, pixels, mask
    )
    ok = status == Status.OK
    seen = mask & ok[:, None]
    T, _, _ = _similarity(pixels.reshape(-1, 2), seen.reshape(-1).astype(pixels.dtype))
    K, condition, determined = _intrinsics(H, ok, T, skew, rcond)
    # Zhang's K against one focal length, the median of the views' own (`_focal_lengths`): the
    # one whose poses reproject the views better. One view of a few points, its homography
    # poorly determined, can leave Zhang's B indefinite (no K) or far off
    median, found = _focal_lengths(H, ok, pixels, seen)
    Rz, tz, rms_zhang = _posed(K, H, plane_xy, pixels, mask, seen)
    Rm, tm, rms_median = _posed(median, H, plane_xy, pixels, mask, seen)
    zhang = determined & ~(rms_median < rms_zhang)
    K, R, t = (jnp.where(zhang, a, b) for a, b in ((K, median), (Rz, Rm), (tz, tm)))
    status = jnp.where(ok & ~(zhang | found), Status.DEGENERATE, status).astype(jnp.int32)
    # back from the plane's frame to the world's: x_cam = R (A X + b) + t
    R, t = R @ plane.R, jnp.einsum("vij,j->vi", R, plane.t) + t
    V = pixels.shape[0]
    camera = Camera.from_matrices(jnp.broadcast_to(K, (V, 3, 3)), R, t)
    return H, camera, status, condition


# ------------------------------------------------------------------------------ fisheye seed
def _equidistant_rays(pixels, centre, focal):
    """Unit rays `(..., 3)` of pixels through the ideal equidistant lens (`r = f theta`, no
    distortion) with its principal point at `centre`."""
    offset = pixels - centre
    r = np.linalg.norm(offset, axis=-1, keepdims=True)
    theta = r / focal
    unit = np.where(r > 0, offset / np.where(r > 0, r, 1.0), 0.0)
    return np.concatenate([np.sin(theta) * unit, np.cos(theta)], -1)


def _ray_homographies(a, d, seen):
    """For every view, the homography `H` with `d ~ H (a, 1)` for the plane points `a (N, 2)` and
    the unit rays `d (V, N, 3)` of the points `seen (V, N)` (a ray's sign is free: rays beyond 90
    degrees fit as well): the null vector of the three rows of `d x H a` per point, from the 9 x 9
    normal matrix of each view (all views in one batched `eigh`). Returns `H (V, 3, 3)`, the rows
    `(V, N, 3, 9)` (zero where not seen) and the sine of each point's angle from its fitted ray
    `(V, N)` (zero where not seen)."""
    n = len(a)
    ah = np.concatenate([a, np.ones((n, 1))], 1)
    kron = np.einsum("ij,nk->nijk", np.eye(3), ah).reshape(n, 3, 9)  # H ah = kron @ vec(H)
    rows = (hat(d, xp=np) @ kron) * seen[..., None, None]  # (V, N, 3, 9)
    flat = rows.reshape(len(rows), -1, 9)
    normal = flat.transpose(0, 2, 1) @ flat
    H = np.linalg.eigh(normal)[1][..., 0].reshape(-1, 3, 3)
    fitted = ah @ H.transpose(0, 2, 1)
    fitted /= np.linalg.norm(fitted, axis=-1, keepdims=True)
    sine = np.linalg.norm(np.cross(d, fitted), axis=-1) * seen
    return H, rows, sine


def _fisheye_seed(world, plane, pixels, mask, image_size, rcond):
    """The fisheye's closed-form seed, in NumPy: the principal point at the image centre, no
    distortion (the ideal equidistant lens), the focal length that lets every view's rays fit a
    homography best (a scan of 40 values from 3 to 1/20 radians per `r_max` pixels, then a golden
    section on its logarithm, to 1e-6), and each view's pose from its homography (Zhang's eq. 10
    with `K = I`: the rays are already normalised)."""
    width, height = (float(v) for v in image_size)
    centre = np.array([(width - 1.0) / 2.0, (height - 1.0) / 2.0])
    xy = np.asarray(plane.apply(world))[:, :2]
    pixels, mask = np.asarray(pixels, float), np.asarray(mask)
    T = np.asarray(_similarity(jnp.asarray(xy), jnp.asarray(mask.any(0), xy.dtype))[0])
    a = xy @ T[:2, :2].T + T[:2, 2]  # Hartley's normalisation of the plane points

    seen_pixels = np.where(mask[..., None], pixels, centre)  # (hidden ones: any finite pixel)

    def fit(focal):
        return _ray_homographies(a, _equidistant_rays(seen_pixels, centre, focal), mask)

    def cost(log_focal):  # the angles as pixels of the lens: sum of squares
        focal = np.exp(log_focal)
        return float(np.sum((focal * fit(focal)[2]) ** 2))

    r_max = max(float(np.max(np.linalg.norm(pixels[mask] - centre, axis=-1))), 1.0)
    grid = np.log(np.geomspace(r_max / 3.0, 20.0 * r_max, 40))
    best = int(np.argmin([cost(g) for g in grid]))
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    # a golden section, one new cost a step: the bracket (two grid steps, 0.21 in the log) down
    # to 1e-6 of the focal length in 25 steps; the refinement takes it from there
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    m1, m2 = hi - golden * (hi - lo), lo + golden * (hi - lo)
    c1, c2 = cost(m1), cost(m2)
    for _ in range(25):
        if c1 < c2:
            hi, m2, c2 = m2, m1, c1
            m1 = hi - golden * (hi - lo)
            c1 = cost(m1)
        else:
            lo, m1, c1 = m1, m2, c2
            m2 = lo + golden * (hi - lo)
            c2 = cost(m2)
    focal = float(np.exp((lo + hi) / 2.0))

    H, R, t, status, condition = [], [], [], [], []
    for Hn, rows, view, seen in zip(*fit(focal)[:2], pixels, mask):
        sv = np.linalg.svd(rows.reshape(-1, 9), compute_uv=False)  # (squares lose the small ones)
        M = Hn @ T  # plane coordinates to rays
        lam = 2.0 / (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1]))
        d = _equidistant_rays(view[seen], centre, focal)
        fitted = np.concatenate([xy[seen], np.ones((seen.sum(), 1))], 1) @ M.T
        lam *= -1.0 if np.sum(d * fitted) < 0 else 1.0  # the rays' side of the camera
        r1, r2 = lam * M[:, 0], lam * M[:, 1]
        R.append(
            np.asarray(nearest_rotation(jnp.asarray(np.stack([r1, r2, np.cross(r1, r2)], -1))))
        )
        t.append(lam * M[:, 2])
        H.append(M / np.linalg.norm(M))
        good = sv[-2] > rcond * sv[0]
        few = seen.sum() < MIN_PLANE_POINTS
        status.append(Status.TOO_FEW_POINTS if few else Status.OK if good else Status.DEGENERATE)
        condition.append(0.0 if few else sv[0] / sv[-2])  # (a view without a homography)
    R, t = np.stack(R), np.stack(t)
    R, t = R @ np.asarray(plane.R), np.einsum("vij,j->vi", R, np.asarray(plane.t)) + t
    V = len(pixels)
    camera = Camera(np.full(V, focal), np.full(V, focal), np.full(V, centre[0]),
                    np.full(V, centre[1]), R, t, lens="fisheye")  # fmt: skip
    status = jnp.asarray(np.asarray(status, np.int32))
    return jnp.asarray(np.stack(H)), camera, status, jnp.asarray(max(condition))


def _without_a_camera(status, camera: Camera):
    """`status` with its OK views DEGENERATE where the calibrated views' camera is none (a focal
    length not finite and positive): the views together do not determine one (a fisheye user's
    trial: pixels given as normalised coordinates came back OK with alpha_v < 0, the refinement
    unconverged). The views' cameras share one lens, a pose each."""
    ok = (np.asarray(status) == Status.OK).reshape(-1)
    focal = np.asarray([camera.alpha_u, camera.alpha_v]).reshape(2, -1)[:, ok]
    if (np.isfinite(focal) & (focal > 0)).all():
        return status
    return jnp.asarray(np.where(ok.reshape(np.shape(status)), Status.DEGENERATE, status), jnp.int32)


def _nan_where(failed, camera: Camera) -> Camera:
    expand = lambda x: failed.reshape(failed.shape + (1,) * (x.ndim - failed.ndim))  # noqa: E731
    return jax.tree_util.tree_map(lambda x: jnp.where(expand(x), jnp.nan, x), camera)


# ------------------------------------------------------------------------------ refinement
# One least-squares problem over the shared intrinsics and distortion and every view's pose,
# like `refine_rig(..., shared_intrinsics=True)` but compiled as one function in which the
# choice of free parameters is data (a 0/1 mask on the increments), not shape: Zhang's model with
# skew and OpenCV's without, any `distortion` or `fix`, share one compilation.
def _planar_unknowns(y, args):
    p0, R0, t0, scale, distance, free_shared, free_pose, tie = args[:8]
    p = p0 + y["shared"] * scale * free_shared
    p = p.at[0].add(tie * (_ratio(p0) * p[1] - p[0]))  # alpha_u following alpha_v (`Free`)
    w = y["views"][:, :3] * free_pose[:3]  # axis-angle increments on the seed's rotations
    dt = y["views"][:, 3:] * free_pose[3:] * distance[:, None]
    R, t = rodrigues(w) @ R0, t0 + dt
    return Camera(p[0], p[1], p[2], p[3], R, t, skew=p[4], dist=p[5:], lens=lens_of(p[5:]))


def _planar_residuals(y, args):
    return _robust_residuals(_planar_unweighted(y, args), args[-1])


def _planar_model(y, args):
    """Gauss–Newton's model of the robust cost (`_refine._robust_model`)."""
    return _robust_model(_planar_unweighted(y, args), args[-1])


def _planar_unweighted(y, args):
    world, pixels, mask, _ = args[8:]
    r = _planar_unknowns(y, args).project(world) - pixels
    return jnp.where(mask[..., None], r, 0.0)


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _refine_views(camera, ok, world, pixels, mask, free_shared, free_pose, tied, loss, solver,
                  max_steps):  # fmt: skip
    """Refine the closed-form rig. Views that failed (`~ok`) get a harmless seed and no points
    (`_finish` puts NaN in their place). (Until 2026-12-05 a redescending loss, `Cauchy`,
    started from the answer of `Huber` of its scale; with Ceres' model of the steps it needs no
    such start: 40 views of 8 board cameras, 10-14 steps against 15-187, the same K.)"""
    eye = jnp.broadcast_to(jnp.eye(3, dtype=camera.R.dtype), camera.R.shape)
    camera = eqx.tree_at(
        lambda c: (c.R, c.t),
        camera,
        (jnp.where(ok[:, None, None], camera.R, eye), jnp.where(ok[:, None], camera.t, 1.0)),
    )
    mask = mask & ok[:, None]
    if solver is None:  # the default: the views' poses eliminated from every step
        return _refine_as_rig(camera, ok, world, pixels, mask, free_shared, tied, loss, max_steps)
    P = len(parameter_names(camera.lens))
    unknown = jnp.full((P, P), jnp.nan, camera.R.dtype)  # (a user's solver: no covariance)
    first = camera[0]  # the intrinsics are every view's
    p0 = jnp.concatenate(
        [jnp.stack([first.alpha_u, first.alpha_v, first.u0, first.v0, first.skew]), first.dist]
    )
    # natural units: pixels of focal length for the intrinsics, the view's distance for t
    f = jnp.abs(p0[0])
    scale = jnp.concatenate([jnp.full(5, f), jnp.ones(len(p0) - 5, p0.dtype)])
    distance = jnp.linalg.norm(camera.t, axis=-1)
    pixels = jnp.where(mask[..., None], pixels, 0.0)
    tie = jnp.asarray(float(tied), p0.dtype)
    args = (p0, camera.R, camera.t, scale, distance, free_shared, free_pose, tie,
            world, pixels, mask, loss)  # fmt: skip
    y0 = {"shared": jnp.zeros_like(p0), "views": jnp.zeros((len(distance), 6), p0.dtype)}
    # The fixed parameters are zero columns of the Jacobian, so the implicit derivative's linear
    # system is singular along them: a least-squares (SVD) solve gives them zero derivative. It
    # drops what lies below `eps` of the largest singular value, not Lineax's `2 eps n`, which
    # in float32 dropped the distortion's directions too (as `_refine._adjoint` says): with a
    # user's solver (optimistix's LM at 1e-5), a gradient 89 % off float64's (a user's trial),
    # now 11 % (no smaller threshold does better: the rest is that solver's stopping point).
    adjoint = optx.ImplicitAdjoint(linear_solver=lx.SVD(rcond=-1.0))
    # (with a robust loss, the step's model is Ceres': `_irls`)
    options = {"model": _planar_model} if loss is not None and takes_model(solver) else {}
    sol = optx.least_squares(
        _planar_residuals, solver, y0, args, options=options, max_steps=max_steps,
        adjoint=adjoint, throw=False,
    )  # fmt: skip
    steps = sol.stats["num_steps"]
    return _planar_unknowns(sol.value, args), steps, sol.result._value, unknown  # noqa: SLF001


def _refine_as_rig(camera, ok, world, pixels, mask, free_shared, tied, loss, max_steps):
    """`_refine_views` by `calibrate_rig`'s solver (`_rig._refine`): the camera at the origin and
    its views the frames of a rig of one camera, whose poses every step eliminates (Schur
    complement), so that a step costs in proportion to the views rather than to their square.

    The whole-problem step (optimistix's, the Jacobian of every view's pose materialised) took
    32, 134, 589 and 1,804 ms warm for 10, 20, 40 and 80 views of a 9 x 12 board, against
    OpenCV's `calibrateCamera` 8, 15, 30 and 62 ms; this one 8, 16, 23 and 47 ms, to the same
    answers (K within 1e-9 of the focal length)."""
    from . import _rig  # (which builds on this module)

    dtype = pixels.dtype
    names = parameter_names(camera.lens)
    # every parameter (`movable` says which move), alpha_u following alpha_v where `tied`
    free = Free(range(len(names)), tied=tied)
    shared = np.flatnonzero([n not in POSE for n in names])
    movable = jnp.zeros(len(names), dtype).at[shared].set(free_shared)[None]
    eye = jnp.eye(3, dtype=dtype)
    origin = eqx.tree_at(lambda c: (c.R, c.t), camera[0], (eye, jnp.zeros(3, dtype)))
    distance = _masked_median(jnp.linalg.norm(camera.t, axis=-1), ok, sort=True)
    views = RigidTransform(
        jnp.where(ok[:, None, None], camera.R, eye),
        jnp.where(ok[:, None], camera.t, jnp.array([0.0, 0.0, 1.0], dtype) * distance),
    )
    y, steps, result, args, used, normal = _rig._refine(  # noqa: SLF001
        jax.tree_util.tree_map(lambda x: x[None], origin), views, ok[None], ok, distance, world,
        pixels[None], mask[None], movable, free, loss, max_steps, nielsen=False,
    )  # fmt: skip
    cameras, poses = _rig._cameras_and_frames(y, args, free)  # noqa: SLF001
    V = ok.shape[0]
    every = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x[0], (V,) + x.shape[1:]), cameras)
    every = eqx.tree_at(lambda c: (c.R, c.t), every, (poses.R, poses.t))
    # the covariance of the camera's parameters, the views' poses' uncertainty in it (the
    # reduced camera system's inverse: `calibrate_rig`'s `_uncertainty`)
    residuals = jnp.where(used[0][..., None], every.project(world[None]) - pixels, 0.0)
    cov = _rig._uncertainty(  # noqa: SLF001
        *jax.lax.stop_gradient((y, args, normal, residuals[None])), free=free, loss=loss
    )[0][0]
    return every, steps, result, cov


def _free_masks(distortion, fix, skew, dtype, lens="pinhole"):
    """0/1 masks of the free shared parameters and pose parameters, and whether alpha_u follows
    alpha_v (`Free.tied`; alpha_u's mask is then 0)."""
    names = parameter_names(lens)
    free = _free_parameters(distortion, fix, skew, lens)
    tied, free = free.tied, {names[i] for i in free}
    mask = lambda names: np.asarray([n in free for n in names], dtype)  # noqa: E731
    return mask(tuple(n for n in names if n not in POSE)), mask(POSE), tied


def _forgets_its_start(free_shared, free_pose, tied: bool, skew: bool) -> bool:
    """Whether the refinement keeps nothing of the closed form's values: every parameter it
    holds is a constant of the closed form (the distortion coefficients, zero; the skew, exactly
    zero without `skew`), none held at the closed form's value (intrinsics or poses named in
    `fix`, the aspect ratio, an estimated skew). The refined camera is then the optimum's
    alone, and under `grad` the closed form's derivatives need not go through the solve only to
    cancel (`_pipeline._seed_is_forgotten`, for `calibrate`'s DLT seed). Four views of a 7 x 5
    grid, fresh processes: the first `jax.grad` 19.8 against 22.8 s, in `jax.jit` 15.2 against
    22.4 s; the gradient within 1e-12."""
    shared = [n for n in parameter_names("pinhole") if n not in POSE]
    held = {n for n, free in zip(shared, free_shared) if not free}
    constant = set(LENSES["pinhole"]) | (set() if skew else {"skew"})
    return not tied and bool(np.all(free_pose)) and held <= constant


# A view is left out (POOR_FIT) where its RMS exceeds `max_relative_rms` of its pixels' spread and
# this many times the median view's: 40 views of a 6 x 8 board (`board_rig` key 0, camera 3), one
# of 5 points whose pose the solve left in another minimum at 42.8 px, which pulled k1 from -0.003
# to -0.156 and the focal length 28 % off (the other views at 0.4 px). The spread alone flags
# good views of a target small in the image (a fisheye's: 0.43 px, as the others).
_FAR_WORSE = 3.0


def _median_rms(square, mask):
    """The RMS that the median of the squared distances `square` over `mask` implies for 2-D
    Gaussian noise, `sqrt(median / ln 2)` (the squared distance's median is `2 ln 2 sigma^2`,
    the RMS distance `sqrt(2) sigma`): a few wild points do not move it, a fit that misses every
    point does."""
    return jnp.sqrt(_masked_median(square, mask, sort=True) / math.log(2.0))


def _out_of_proportion(rms, pixels, used, among, max_relative_rms):
    """Where `rms` (a view's, or a rig's (camera, frame) pair's) exceeds both
    `max_relative_rms` of the spread of its `pixels` `used` (`poor_fit`) and `_FAR_WORSE` times
    the median `rms` over `among`."""
    typical = _masked_median(rms.reshape(-1), among.reshape(-1), sort=True)
    return poor_fit(rms, pixels, used, max_relative_rms, sort=True) & (rms > _FAR_WORSE * typical)


@_buckets.jit
def _finish(closed, camera, world, pixels, mask, ok, max_relative_rms, loss):
    """NaN for the views that failed; the report per view, the pooled RMS of the others, and
    the views `ok` that fit out of all proportion both to their image of the target
    (`poor_fit`) and to the other views (`_FAR_WORSE` times their median RMS).

    With a robust `loss`, a view's RMS is estimated from its median squared distance
    (`_median_rms`): one wild point is the loss's business, a view
    whose pose lies in another minimum is not. (Until 2026-12-05 the RMS over the points the
    loss kept, within 3 of its scales: a view of 5 or 7 points left at 70-78 px kept none, an
    RMS of 0, and pulled the focal length 1.4-1.8 % off; 16 x 250 `board_rig` keys 0 and 3,
    40 views of a camera with 1 % of the corners moved by 50 px.)"""
    closed, camera = _nan_where(~ok, closed), _nan_where(~ok, camera)
    report = compute_report(camera, world, pixels, mask & ok[:, None])
    n = jnp.sum(report.n_points)
    rms = jnp.sqrt(jnp.sum(report.residuals**2) / jnp.maximum(n, 1))
    if loss is None:
        view_rms = report.rms
    else:
        view_rms = _median_rms(jnp.sum(report.residuals**2, -1), report.mask)
    poor = _out_of_proportion(view_rms, pixels, report.mask, ok, max_relative_rms)
    return closed, camera, report, rms, ok & poor


# ------------------------------------------------------------------------------ validation
def _plane_frame(world: np.ndarray, used: np.ndarray, dtype) -> RigidTransform:
    """The world-to-plane transform, after checking that the used points are planar and not
    collinear (concrete input only)."""
    pts = world[used]
    if len(pts) < MIN_PLANE_POINTS:
        raise ValueError(f"the views see {len(pts)} distinct target points; at least 4 needed.")
    c = pts.mean(0)
    _, s, vt = np.linalg.svd(pts - c, full_matrices=False)
    extent = s[0] / np.sqrt(len(pts))  # RMS spread along the widest direction
    tol = 1e-6 if np.dtype(dtype) == np.float64 else 1e-4
    if s[1] <= tol * s[0]:
        raise ValueError(
            "the target points are collinear (or all the same point): a plane is not determined."
        )
    height = np.abs((pts - c) @ vt[2])
    if height.max() > tol * extent:
        raise ValueError(
            f"`world` is not planar: points lie up to {height.max():.3g} from their best-fitting "
            f"plane, against a spread of {extent:.3g} (tolerance {tol:g} of it). "
            "calibrate_planar needs a flat target; use mvcalib.calibrate for 3-D targets."
        )
    if np.all(np.abs(pts[:, 2]) <= tol * extent):  # already z = 0: keep the user's x, y
        return RigidTransform.identity(dtype)
    A = vt.copy()
    A[2] = np.cross(A[0], A[1])  # a proper rotation
    return RigidTransform(*jax.device_put((A.astype(dtype), (-A @ c).astype(dtype))))


def _traced_plane_frame(world, used) -> RigidTransform:
    """`_plane_frame` of a traced `world` (unchecked): the identity where the used points lie in
    z = 0, else the frame of their best-fitting plane. It carries no derivative: the closed form
    drops the points' z in it, and only their moves within the plane mean anything to a planar
    method. (Taken as the identity, a tilted board's closed form was silently off under the
    user's `jax.jit`: focal length 796.7 against 800 px with exact pixels, a JAX user's trial.)"""
    X, w = jax.lax.stop_gradient(world), used.astype(world.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    c = (w @ X) / n
    d = (X - c) * w[:, None]
    s, v = jnp.linalg.eigh(d.T @ d)  # ascending: v[:, 2] the widest direction, v[:, 0] the normal
    A = jnp.stack([v[:, 2], v[:, 1], jnp.cross(v[:, 2], v[:, 1])])
    tol = 1e-6 if X.dtype == jnp.float64 else 1e-4
    extent = jnp.sqrt(s[2] / n)  # RMS spread along the widest direction
    flat = jnp.all(jnp.where(used, jnp.abs(X[:, 2]), 0.0) <= tol * extent)
    R = jnp.where(flat, jnp.eye(3, dtype=X.dtype), A)
    return RigidTransform(R, jnp.where(flat, 0.0, -A @ c))


def _check_views(pixels, mask, skew: bool):
    V = pixels.shape[0]
    need = 3 if skew else 2
    if V < need:
        raise ValueError(
            f"{need} views at least are needed to determine the intrinsics "
            f"({'5 unknowns with skew' if skew else '4 unknowns with zero skew'}, 2 equations "
            f"per view); got {V}." + (" Use skew=False to calibrate from 2 views." if skew else "")
        )
    if _validate.is_concrete(mask):
        # a view with fewer points is TOO_FEW_POINTS (a fisheye's board near the edge of the
        # field keeps three corners in view: it stopped the whole calibration); too few such
        # views leave nothing to calibrate
        counts = np.asarray(mask).sum(-1)
        few = np.flatnonzero(counts < MIN_PLANE_POINTS)
        if V - few.size < need:
            raise ValueError(
                f"{V - few.size} views have {MIN_PLANE_POINTS} or more visible points (a "
                f"homography's least); {need} are needed (views {few.tolist()} have fewer)."
            )


# ------------------------------------------------------------------------------ public
def calibrate_planar(
    world: Float[Array, "N 2"] | Float[Array, "N 3"],
    pixels: Float[Array, "V N 2"],
    mask: Bool[Array, "V N"] | None = None,
    *,
    skew: bool = False,
    distortion: Sequence[str] | str | None = None,
    refine: bool = True,
    fix: Sequence[str] | str = (),
    loss: Huber | Cauchy | None = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    rcond: float | None = None,
    lens: str = "pinhole",
    image_size: tuple[int, int] | None = None,
    max_relative_rms: float = DEFAULT_MAX_RELATIVE_RMS,
) -> PlanarCalibration:
    """Calibrate one camera from several views of a planar target, by Zhang's method.

    1. A homography per view by the normalised DLT (Hartley's normalisation, SVD), all views in
       one vmapped call; masks as for `mvcalib.dlt`.
    2. The intrinsics in closed form: each homography gives two linear equations in the
       symmetric `B = K^-T K^-1` (Zhang's eqs. 8–9), solved by SVD; K from the Cholesky factor
       of B. Against it, one focal length, the median of each view's own (the principal point
       at the centre of the pixels seen, zero skew): the camera starts from the one whose
       poses (step 3) reproject the views better. (One view of a few points, its homography
       poorly determined, can leave B indefinite, or K far off.)
    3. Each view's pose from `K^-1 H` (eq. 10), the rotation made orthonormal by
       `mvcalib.nearest_rotation`.
    4. With `refine=True` (default), one Levenberg–Marquardt problem over the shared intrinsics,
       the distortion and every view's pose, starting from zero distortion: `calibrate_rig`'s
       solver for a rig of one camera, the views its frames, whose poses every step eliminates
       (a step's cost grows with the views, not their square; 40 views of a 9 x 12 board in
       23 ms warm, OpenCV's `calibrateCamera` 30 ms), compiled once for any choice of free
       parameters.
       Outside a trace, a view whose refined fit is out of all proportion (RMS above
       `max_relative_rms` of its pixels' spread and 3 times the median view's; with a robust
       `loss`, the RMS that its median distance implies: a pose left in another minimum, or
       wrong points) is
       `Status.POOR_FIT`, left out, and the rest solved again, the worst view first, until none
       is left.

    The model is `Camera.project`: distortion `(k1, k2, p1, p2, k3)` in normalised coordinates
    before `K`, so Zhang's radial model `x (1 + k1 r^2 + k2 r^4)` is `distortion=("k1", "k2")`,
    the default.

    **Arguments:**

    - `world`: the target's points, shared by every view: `(N, 2)` plane coordinates, or
      `(N, 3)` points on one plane (any plane; the poses are returned in this frame; a
      `world` traced by `jax.jit` is not checked for being planar).
    - `pixels`: `(V, N, 2)` observations, `(x = column, y = row)`.
    - `mask`: `(V, N)` visibility; hidden points (even NaN) have no influence.
    - `skew`: estimate the skew `K[0, 1]` (Zhang's gamma) — then at least 3 views are needed;
      without it (default, like OpenCV) the zero-skew constraint makes 2 views enough. (From a
      single view only two intrinsics are determined; that case is not supported.)
    - `distortion`: which of the lens's coefficients the refinement estimates; `()` for none.
      By default `("k1", "k2")` of a pinhole's `(k1, k2, p1, p2, k3)` (Zhang's radial model),
      all four of a fisheye's `(k1, k2, k3, k4)` (as `cv2.fisheye.calibrate`). `refine` and
      `calibrate_rig` take OpenCV's `(k1, k2, p1, p2)` by default, and `cv2.calibrateCamera`
      `(k1, k2, p1, p2, k3)`: name them to compare like with like.
    - `refine`: run step 4; without it the result is the closed form (no distortion).
    - `fix`, `loss`, `max_steps`: as for `mvcalib.refine` (e.g. `fix="principal_point"`,
      `loss=mc.Huber(1.0)`); `fix` names from `("alpha_u", "alpha_v", "u0", "v0", "skew",
      "k1", "k2", "p1", "p2", "k3")` and `"rotation"`, `"translation"`, `"pose"` (for every
      view) or their groups. A fixed parameter is held at the closed form's value (a
      fisheye's principal point: the image centre). `"aspect_ratio"` holds `alpha_u / alpha_v`
      at the closed form's ratio (`closed_form.alpha_u / closed_form.alpha_v`: Zhang's K's, or
      1 where the camera starts from one focal length, as a fisheye always does) and estimates
      the focal length: OpenCV's `CALIB_FIX_ASPECT_RATIO` with `CALIB_USE_INTRINSIC_GUESS` from
      the closed form's K, to 2e-10. The closed form neglects the distortion, and its ratio
      carries that error (the tests' barrel lens, `k1 = -0.25`: 1.6 % off, 0.62 px RMS against
      the free focal lengths' 0.42). Without a guess OpenCV holds its own start's ratio, 1.
      To start from known intrinsics, or hold them (or their ratio, e.g. 1, with
      `fix="aspect_ratio"`) at given values (OpenCV's `CALIB_USE_INTRINSIC_GUESS` with
      `CALIB_FIX_*`), calibrate a rig of this one camera: `mc.calibrate_rig(world,
      pixels[None], mask[None], cameras=camera_with_a_camera_axis, fix="principal_point")` (a
      fisheye's principal point held at a given value: its focal lengths within 0.1 % of the
      truth, as here; a ratio of 1 held: OpenCV's `CALIB_FIX_ASPECT_RATIO` without a guess).
    - `solver`: an optimistix least-squares solver for step 4, which then solves the problem
      whole (its Jacobian of every view's pose materialised: 0.6 s for 40 views); default
      step 4's own (also where a view's pose is held by `fix`).
    - `rcond`: relative singular-value threshold below which a homography or the intrinsics'
      system counts as degenerate; default sqrt(machine epsilon).
    - `lens`: `"pinhole"` (Zhang's method as above) or `"fisheye"` (Kannala–Brandt, see
      `Camera`). A fisheye's closed form replaces steps 1-3: the principal point at the centre
      of the image (`image_size=(width, height)`, required), no distortion (the ideal
      equidistant lens `r = f theta`), the focal length whose rays let every view's points fit
      a homography best (a one-dimensional search), and each view's pose from its homography of
      rays; then step 4 as for a pinhole. Rays beyond 90 degrees off axis count as any other
      (`cv2.fisheye.calibrate` cannot take them). `homographies` then map the plane to the
      closed form's rays, and `condition` is the largest of the views' homographies' condition
      numbers (largest over second-smallest singular value).
    - `max_relative_rms`: step 4's bar for a view's RMS, as a fraction of its pixels' spread
      (as for `mvcalib.calibrate`); default 0.05, `inf` turns the check off.

    **Returns:** a `PlanarCalibration`.

    Raises `ValueError` for malformed input: fewer than 3 views with `skew=True` (2 without) of 4
    visible points or more, points that are not on one plane, or collinear. A view with fewer
    points gets `Status.TOO_FEW_POINTS` and takes no part.

    **Example:** three views of a 7 x 5 grid by a pinhole camera; the closed form alone
    (`refine=False`) is exact on noise-free data. (The default `refine=True` adds the
    distortion `k1, k2` and the maximum-likelihood fit.)

    ```python
    >>> import jax.numpy as jnp, numpy as np, mvcalib as mc
    >>> grid = np.stack(np.meshgrid(np.arange(7.0), np.arange(5.0)), -1).reshape(-1, 2) * 30
    >>> R = mc.rodrigues(jnp.array([[0.3, 0.1, 0.0], [-0.2, 0.3, 0.1], [0.1, -0.3, -0.1]]))
    >>> t = jnp.array([[-90.0, -60.0, 500.0], [-100.0, -50.0, 550.0], [-80.0, -70.0, 450.0]])
    >>> truth = mc.Camera(800.0, 790.0, 320.0, 240.0, R, t)
    >>> pixels = truth.project(jnp.pad(grid, ((0, 0), (0, 1))))  # the grid at z = 0
    >>> out = mc.calibrate_planar(grid, pixels, refine=False)
    >>> np.round(np.asarray(out.K), 1).tolist(), bool(out.ok.all())
    ([[800.0, 0.0, 320.0], [0.0, 790.0, 240.0], [0.0, 0.0, 1.0]], True)

    ```
    """
    # concrete arrays are checked in NumPy (an eager `jnp` operation compiles a program a shape)
    xp = np if _validate.is_concrete(world, pixels, mask) else jnp
    world = _validate.floating("world", world, xp=xp)
    if world.ndim != 2 or world.shape[-1] not in (2, 3):
        raise ValueError(
            "`world` holds the planar target's points shared by every view, shape (N, 2) or "
            f"(N, 3); got {tuple(world.shape)}."
        )
    if world.shape[-1] == 2:
        world = xp.concatenate([world, xp.zeros_like(world[:, :1])], -1)
    pixels = _validate.floating("pixels", pixels, (None, 2), xp=xp)
    if pixels.ndim != 3:
        raise ValueError(
            f"`pixels` must be (V, N, 2): the target's N points in each of V views; got "
            f"{tuple(pixels.shape)}."
        )
    world, pixels, mask = _validate.correspondences(
        world, pixels, mask, min_points=MIN_PLANE_POINTS, xp=xp
    )
    _check_views(pixels, mask, skew)
    check_lens(lens)
    if image_size is not None:
        _validate.in_image(pixels, mask, image_size)
    if lens == "fisheye":
        if image_size is None:
            raise ValueError(
                "a fisheye's closed form puts the principal point at the image centre: give "
                "`image_size=(width, height)`."
            )
        if not _validate.is_concrete(world, pixels, mask):
            raise ValueError("calibrate_planar(lens='fisheye') needs concrete arrays (not traced).")
    dtype = world.dtype
    if _validate.is_concrete(world, mask):
        used = np.asarray(mask).any(0)
        plane = _plane_frame(np.asarray(world), used, dtype)
    else:
        plane = _traced_plane_frame(world, jnp.any(mask, 0))
    rcond = float(jnp.finfo(dtype).eps) ** 0.5 if rcond is None else float(rcond)
    distortion = DEFAULT_DISTORTION[lens] if distortion is None else distortion
    free_shared, free_pose, tied = _free_masks(distortion, fix, skew, dtype, lens)  # checks names
    names = parameter_names(lens)  # the reported: the free ones shared by every view
    shared = [n for n in names if n not in POSE]
    reported = tuple(n for n, f in zip(shared, free_shared) if f or (n == "alpha_u" and tied))
    at = np.ix_(*[[names.index(n) for n in reported]] * 2)
    check_loss(loss)
    skew = np.asarray(bool(skew))
    V = pixels.shape[0]
    if xp is np:  # another number of views reuses its bucket's programs: padded views are unseen
        pixels, mask = (_buckets.pad(x, 0, _buckets.size(V, MIN_VIEWS, bits=VIEW_BITS), fill=fill)
                        for x, fill in ((pixels, 0.0), (mask, False)))  # fmt: skip
    quick = math.prod(mask.shape) <= _buckets.COMPACT  # a small program compiles quickly
    if solver is None and not np.all(free_pose):  # (poses held: the dense step's mask)
        solver = default_solver(dtype)
    refine_options = (free_shared, free_pose, tied, loss, solver, int(max_steps))
    closed_form = functools.partial(_closed_form, world, plane, pixels, skew=skew, rcond=rcond,
                                    quick=quick)  # fmt: skip
    max_relative_rms = check_relative_rms(max_relative_rms)
    if xp is np:  # concrete: the programs compile on other threads, the later ones traced meanwhile
        views = placeholder(mask.shape[:1], dtype, lens)
        some = np.zeros(mask.shape[:1], bool)
        if lens != "fisheye":
            _buckets.ahead(closed_form, mask)
        if refine:
            _buckets.ahead(_refine_views, views, some, world, pixels, mask, *refine_options,
                           quick=quick)  # fmt: skip
        _buckets.ahead(_finish, views, views, world, pixels, mask, some, max_relative_rms, loss,
                       quick=quick)  # fmt: skip

    def solve(mask):
        if lens == "fisheye":  # (in NumPy, from the views given; the padded ones unseen)
            H, seed, status, condition = _fisheye_seed(
                world, plane, pixels[:V], mask[:V], image_size, rcond
            )
            grow = lambda x, fill=None: _buckets.pad(x, 0, len(mask), fill=fill)  # noqa: E731
            H, status = grow(H), grow(status, Status.TOO_FEW_POINTS)
            seed = jax.tree_util.tree_map(lambda x: jnp.asarray(grow(x), dtype), seed)
        else:
            H, seed, status, condition = closed_form(mask)
        ok = _status.ok(status)
        if refine:
            start = seed  # (the closed form's answer keeps its derivatives: `closed_form`)
            if xp is not np and _forgets_its_start(free_shared, free_pose, tied, bool(skew)):
                start = jax.lax.stop_gradient(seed)
            camera, iterations, result, cov = _refine_views(
                start, ok, world, pixels, mask, *refine_options, quick=quick
            )
        else:
            camera, iterations, result = seed, np.zeros((), np.int32), np.zeros((), np.int32)
            cov = np.full((len(names), len(names)), np.nan)
        finished = _finish(
            seed, camera, world, pixels, mask, ok, max_relative_rms, loss, quick=quick
        )
        return H, status, condition, iterations, result, cov, *finished

    H, status, condition, iterations, result, cov, closed, camera, report, rms, poor = solve(mask)
    # Outside a trace, a refined view that fits out of all proportion (its pose in another
    # minimum, or its points wrong) pulled the intrinsics: the worst such view is left out and
    # the rest solved again, by the same programs, until none is left (one at a time: the
    # views it pulled may fit once it is gone); where nothing would be left, the first answer
    # stays. (The closed form's poses are no fit: a view of a few points reprojects poorly from
    # its homography's pose alone.)
    dropped = np.zeros(mask.shape[:1], bool)
    while xp is np and refine and np.asarray(poor).any():
        new = np.arange(len(dropped)) == np.argmax(np.where(poor, report.rms, -np.inf))
        dropped |= new
        again = solve(mask & ~dropped[:, None])
        if not np.asarray(_status.ok(again[1])).any():
            break
        # (the homographies are each view's own: the first solve's stay, the dropped views' too)
        _, status, condition, iterations, result, cov, closed, camera, report, rms, poor = again
    if dropped.any():
        status = np.where(dropped, Status.POOR_FIT, np.asarray(status)).astype(np.int32)
    if _validate.is_concrete(status, camera.alpha_u, camera.alpha_v):  # (called eagerly)
        status = _without_a_camera(status, camera)
    if len(mask) != V:  # the padded views cut off
        H, status, camera, closed, report = (
            _buckets.first(x, V, axis=0) for x in (H, status, camera, closed, report)
        )
    return PlanarCalibration(
        camera=camera,
        closed_form=closed,
        homographies=H,
        plane=plane,
        report=report,
        rms=rms,
        status=status,
        condition=condition,
        iterations=_validate.derived(lambda xp, i: i.astype(xp.int32), iterations),
        result=_validate.derived(lambda xp, r: r.astype(xp.int32), result),
        covariance=_validate.derived(lambda xp, c: c[at], cov),
        parameter_names=reported,
    )
