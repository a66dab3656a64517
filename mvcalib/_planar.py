"""Calibration of one camera from several views of a planar target (Zhang 1998/2000): per-view
homographies, the closed-form intrinsics, the poses, then a joint refinement with distortion."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _validate
from ._bundle import RigRefinement, refine_rig
from ._camera import Camera
from ._pipeline import CalibrationError
from ._refine import Cauchy, Huber
from ._registration import RigidTransform
from ._report import ReprojectionReport, compute_report, format_table
from ._rotation import nearest_rotation
from ._status import Status

MIN_PLANE_POINTS = 4  # a homography has 8 degrees of freedom; each point gives 2 equations

_MESSAGES = {
    Status.OK: "calibrated",
    Status.TOO_FEW_POINTS: "fewer than 4 visible points: the view's homography is not determined",
    Status.DEGENERATE: (
        "degenerate: the view's visible points are collinear or repeated (no homography), or the "
        "views together do not determine the intrinsics (e.g. every view parallel to the others)"
    ),
    Status.NON_FINITE: "NaN or inf among the visible points",
}


class PlanarCalibration(eqx.Module):
    """The result of `calibrate_planar`: one camera seen in several views of a plane.

    - `camera`: a rig of `V` views, `(V,)`: the same intrinsics and distortion in every view
      (`camera.K[0]`, `camera.dist[0]`; also `K` and `dist` below), the target's pose per view.
      Views that failed are NaN.
    - `closed_form`: the same rig from Zhang's closed-form solution, before refinement (pinhole,
      no distortion); equal to `camera` when `refine=False`.
    - `homographies`: `(V, 3, 3)`, unit Frobenius norm, mapping the target's plane coordinates
      `(x, y, 1)` (in the frame `plane`) to pixels.
    - `plane`: the rigid transform from world coordinates to the plane's frame, in which the
      target is `z = 0` (the identity when the points already lie in `z = 0`).
    - `report`: reprojection errors per view (Table I; `report.rms` is `view_rms`).
    - `rms`: the reprojection RMS over every visible point of the views that succeeded.
    - `status`: a `Status` per view; `ok` is `status == Status.OK`; `messages()` says why.
    - `condition`: condition number of the linear system for the intrinsics (`s_1 / s_{p-1}`
      of the normalised `V b = 0`, p = 6 unknowns with skew, 5 without): large means the views
      barely constrain the intrinsics (too similar orientations).
    - `refinement`: the `RigRefinement` of the joint Levenberg–Marquardt step (its `result` and
      `iterations`), or None with `refine=False`.
    """

    camera: Camera
    closed_form: Camera
    homographies: Float[Array, "V 3 3"]
    plane: RigidTransform
    report: ReprojectionReport
    rms: Float[Array, ""]
    status: Int[Array, " V"]
    condition: Float[Array, ""]
    refinement: RigRefinement | None = None

    @property
    def K(self) -> Float[Array, "3 3"]:
        """The intrinsic matrix shared by every view."""
        return self.camera.K[0]

    @property
    def dist(self) -> Float[Array, " 5"]:
        """The distortion `(k1, k2, p1, p2, k3)` shared by every view."""
        return self.camera.dist[0]

    @property
    def view_rms(self) -> Float[Array, " V"]:
        return self.report.rms

    @property
    def ok(self) -> Bool[Array, " V"]:
        return self.status == Status.OK

    def messages(self) -> list[str]:
        """One line per view, saying whether and why it failed."""
        return [_MESSAGES[Status(int(s))] for s in np.asarray(self.status).reshape(-1)]

    def raise_if_failed(self) -> PlanarCalibration:
        """Raise `CalibrationError` naming every view that failed; return self otherwise."""
        status = np.asarray(self.status).reshape(-1)
        bad = np.flatnonzero(status != Status.OK)
        if bad.size:
            lines = [f"view {i}: {_MESSAGES[Status(int(status[i]))]}" for i in bad]
            raise CalibrationError(
                f"{bad.size} of {status.size} views failed:\n" + "\n".join(lines)
            )
        return self

    def __str__(self) -> str:
        if not _validate.is_concrete(self.status):
            return repr(self)
        names = [Status(int(s)).name.lower() for s in np.asarray(self.status).reshape(-1)]
        table = format_table(self.report, status=names)
        return table.replace("per camera", "per view").replace("camera", "  view", 1)


# ------------------------------------------------------------------------------ kernels
# (The two helpers below are the DLT's, kept here so that planar calibration does not depend on
# the private internals of `_dlt`, which solves its 12 x 12 problem differently.)
def _similarity(points, w):
    """Hartley's normalisation `T` (centroid to 0, RMS distance sqrt 2) of weighted 2-D points."""
    n = jnp.maximum(w.sum(), 1.0)
    c = (w[:, None] * points).sum(0) / n
    ms = (w * jnp.sum((points - c) ** 2, axis=-1)).sum() / n
    s = jnp.sqrt(2.0 / jnp.where(ms > 0, ms, 1.0))
    T = jnp.eye(3, dtype=points.dtype) * s
    T = T.at[:2, 2].set(-s * c).at[2, 2].set(1.0)
    return T, s, c


@jax.custom_jvp
def _null_vector(A):
    """The unit right singular vector of `A` for its smallest singular value, and all of them."""
    _, s, vt = jnp.linalg.svd(A, full_matrices=False)
    return vt[-1], s


@_null_vector.defjvp
def _null_vector_jvp(primals, tangents):
    # JAX's SVD derivative divides by the smallest singular value, zero for noise-free data;
    # first-order perturbation of the smallest eigenvector of A^T A needs only the gap to the
    # next one, which is what makes the solution unique anyway.
    (A,), (dA,) = primals, tangents
    _, s, vt = jnp.linalg.svd(A, full_matrices=False)
    v, others = vt[-1], vt[:-1]
    dG_v = dA.T @ (A @ v) + A.T @ (dA @ v)
    dv = -others.T @ ((others @ dG_v) / (s[:-1] ** 2 - s[-1] ** 2))
    return (v, s), (dv, jnp.zeros_like(s))


def _smallest_right_singular(A):
    """The null vector of `A` and its singular values, padding rows so that SVD returns it."""
    rows, cols = A.shape
    if rows < cols:
        A = jnp.concatenate([A, jnp.zeros((cols - rows, cols), A.dtype)])
    return _null_vector(A)


def _homography_kernel(plane, pixels, mask, rcond):
    """One view: plane points (N, 2), pixels (N, 2), mask (N,) -> H (3, 3), status."""
    dtype = plane.dtype
    finite = jnp.all(jnp.isfinite(plane), -1) & jnp.all(jnp.isfinite(pixels), -1)
    all_finite = jnp.all(finite | ~mask)
    visible = mask & finite
    # Hidden points are replaced before any arithmetic (as in the DLT): no influence at all.
    plane = jnp.where(visible[:, None], plane, 0.0)
    pixels = jnp.where(visible[:, None], pixels, 0.0)
    w = visible.astype(dtype)
    # Hartley's normalisation of both point sets, as for the DLT.
    T1, _, _ = _similarity(plane, w)
    T2, s2, c2 = _similarity(pixels, w)
    a = plane @ T1[:2, :2].T + T1[:2, 2]
    b = pixels @ T2[:2, :2].T + T2[:2, 2]
    ah = jnp.concatenate([a, jnp.ones_like(a[:, :1])], -1)
    zero = jnp.zeros_like(ah)
    rows_u = jnp.concatenate([ah, zero, -b[:, :1] * ah], -1)
    rows_v = jnp.concatenate([zero, ah, -b[:, 1:] * ah], -1)
    L = jnp.stack([rows_u, rows_v], 1).reshape(-1, 9)
    L = jnp.where(jnp.repeat(visible, 2)[:, None], L, 0.0)
    v, sv = _smallest_right_singular(L)
    T2_inv = jnp.array([[1 / s2, 0, c2[0]], [0, 1 / s2, c2[1]], [0, 0, 1]], dtype=dtype)
    H = T2_inv @ v.reshape(3, 3) @ T1
    H = H / jnp.linalg.norm(H)
    status = jnp.select(
        [~all_finite, jnp.sum(visible) < MIN_PLANE_POINTS, ~(sv[-2] > rcond * sv[0])],
        [Status.NON_FINITE, Status.TOO_FEW_POINTS, Status.DEGENERATE],
        Status.OK,
    ).astype(jnp.int32)
    return H, status


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


def _intrinsics(H, ok, T, skew: bool, rcond):
    """Zhang's closed form: K from the homographies H (V, 3, 3) of the views with `ok`.

    The homographies are first expressed in normalised pixels (`T`, a similarity), so that the
    unknowns of B = K^-T K^-1 have comparable sizes; K = T^-1 K' keeps the triangular form.
    """
    Hn = T @ H
    Hn = Hn / jnp.linalg.norm(Hn, axis=(-2, -1), keepdims=True)
    # eq. 9: the two constraints per view, r1 . r2 = 0 and |r1| = |r2|
    rows = jax.vmap(lambda h: jnp.stack([_v(h, 0, 1), _v(h, 0, 0) - _v(h, 1, 1)]))(Hn)
    rows = jnp.where(ok[:, None, None], rows, 0.0).reshape(-1, 6)
    if not skew:  # B12 = -gamma / (alpha^2 beta) = 0: drop its column
        rows = rows[:, jnp.array([0, 2, 3, 4, 5])]
    b, sv = _smallest_right_singular(rows)
    if not skew:
        b = jnp.concatenate([b[:1], jnp.zeros_like(b[:1]), b[1:]])
    B = jnp.array([[b[0], b[1], b[3]], [b[1], b[2], b[4]], [b[3], b[4], b[5]]])
    B = B * jnp.sign(B[0, 0])  # B is positive definite up to the SVD's sign
    # B = K^-T K^-1 = L L^T (Cholesky) with K^-1 = L^T upper triangular; NaN unless B > 0.
    K_inv = jnp.linalg.cholesky(B).T
    Kn = jnp.linalg.inv(K_inv)
    Kn = Kn / Kn[2, 2]
    K = jnp.linalg.solve(T, Kn)
    condition = sv[0] / sv[-2]
    determined = (sv[-2] > rcond * sv[0]) & jnp.all(jnp.isfinite(K))
    return K, condition, determined


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


@functools.partial(jax.jit, static_argnames=("skew", "rcond"))
def _closed_form(world, plane, pixels, mask, skew: bool, rcond: float):
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
    status = jnp.where(ok & ~determined, Status.DEGENERATE, status).astype(jnp.int32)
    R, t = jax.vmap(_pose, (None, 0, None, 0))(K, H, plane_xy, mask)
    # back from the plane's frame to the world's: x_cam = R (A X + b) + t
    R, t = R @ plane.R, jnp.einsum("vij,j->vi", R, plane.t) + t
    V = pixels.shape[0]
    camera = Camera.from_matrices(jnp.broadcast_to(K, (V, 3, 3)), R, t)
    camera = _nan_where(status != Status.OK, camera)
    return H, camera, status, condition


def _nan_where(failed, camera: Camera) -> Camera:
    expand = lambda x: failed.reshape(failed.shape + (1,) * (x.ndim - failed.ndim))  # noqa: E731
    return jax.tree_util.tree_map(lambda x: jnp.where(expand(x), jnp.nan, x), camera)


@jax.jit
def _finish(camera, world, pixels, mask, status):
    """The report per view and the pooled RMS, over the views that succeeded."""
    report = compute_report(camera, world, pixels, mask & (status == Status.OK)[:, None])
    n = jnp.sum(report.n_points)
    rms = jnp.sqrt(jnp.sum(report.residuals**2) / jnp.maximum(n, 1))
    return report, rms


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
    return RigidTransform(jnp.asarray(A, dtype), jnp.asarray(-A @ c, dtype))


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
        counts = np.asarray(mask).sum(-1)
        few = np.flatnonzero(counts < MIN_PLANE_POINTS)
        if few.size:
            raise ValueError(
                f"view {int(few[0])} has {int(counts[few[0]])} visible points; a homography "
                f"needs at least {MIN_PLANE_POINTS} per view (views {few.tolist()} have fewer)."
            )


# ------------------------------------------------------------------------------ public
def calibrate_planar(
    world: Float[Array, "N 2"] | Float[Array, "N 3"],
    pixels: Float[Array, "V N 2"],
    mask: Bool[Array, "V N"] | None = None,
    *,
    skew: bool = False,
    distortion: Sequence[str] | str = ("k1", "k2"),
    refine: bool = True,
    fix: Sequence[str] | str = (),
    loss: Huber | Cauchy | None = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    rcond: float | None = None,
) -> PlanarCalibration:
    """Calibrate one camera from several views of a planar target, by Zhang's method.

    1. A homography per view by the normalised DLT (Hartley's normalisation, SVD), all views in
       one vmapped call; masks as for `mvcalib.dlt`.
    2. The intrinsics in closed form: each homography gives two linear equations in the
       symmetric `B = K^-T K^-1` (Zhang's eqs. 8–9), solved by SVD; K from the Cholesky factor
       of B.
    3. Each view's pose from `K^-1 H` (eq. 10), the rotation made orthonormal by
       `mvcalib.nearest_rotation`.
    4. With `refine=True` (default), one Levenberg–Marquardt problem over the shared intrinsics,
       the distortion and every view's pose (`mvcalib.refine_rig` with `shared_intrinsics=True`:
       the views are the rig, the target is its fixed world), starting from zero distortion.

    The model is `Camera.project`: distortion `(k1, k2, p1, p2, k3)` in normalised coordinates
    before `K`, so Zhang's radial model `x (1 + k1 r^2 + k2 r^4)` is `distortion=("k1", "k2")`,
    the default.

    **Arguments:**

    - `world`: the target's points, shared by every view: `(N, 2)` plane coordinates, or
      `(N, 3)` points on one plane (any plane; the poses are returned in this frame).
    - `pixels`: `(V, N, 2)` observations, `(x = column, y = row)`.
    - `mask`: `(V, N)` visibility; hidden points (even NaN) have no influence.
    - `skew`: estimate the skew `K[0, 1]` (Zhang's gamma) — then at least 3 views are needed;
      without it (default, like OpenCV) the zero-skew constraint makes 2 views enough. (From a
      single view only two intrinsics are determined; that case is not supported.)
    - `distortion`: which of `("k1", "k2", "p1", "p2", "k3")` the refinement estimates;
      `()` for a pinhole camera.
    - `refine`: run step 4; without it the result is the closed form (no distortion).
    - `fix`, `loss`, `solver`, `max_steps`: passed to `refine_rig` (e.g.
      `fix="principal_point"`, `loss=mc.Huber(1.0)`).
    - `rcond`: relative singular-value threshold below which a homography or the intrinsics'
      system counts as degenerate; default sqrt(machine epsilon).

    **Returns:** a `PlanarCalibration`.

    Raises `ValueError` for malformed input: fewer than 4 visible points in a view, fewer than
    3 views with `skew=True` (2 without), points that are not on one plane, or collinear.

    **Example:**

    ```python
    >>> import numpy as np, mvcalib as mc
    >>> grid = np.stack(np.meshgrid(np.arange(7.0), np.arange(5.0)), -1).reshape(-1, 2) * 30
    >>> world = np.concatenate([grid, np.zeros((35, 1))], 1)
    >>> truth = mc.Camera(800.0, 790.0, 320.0, 240.0,
    ...                   mc.rodrigues(np.array([[0.3, 0.1, 0.0], [-0.2, 0.3, 0.1],
    ...                                          [0.1, -0.3, -0.1]])),
    ...                   np.array([[-90.0, -60.0, 500.0], [-100.0, -50.0, 550.0],
    ...                             [-80.0, -70.0, 450.0]]),
    ...                   dist=np.array([-0.2, 0.1, 0.0, 0.0, 0.0]))
    >>> out = mc.calibrate_planar(world, truth.project(world))
    >>> np.round(np.asarray(out.K), 6).tolist()
    [[800.0, 0.0, 320.0], [0.0, 790.0, 240.0], [0.0, 0.0, 1.0]]
    >>> np.round(np.asarray(out.dist), 6).tolist(), bool(out.ok.all())
    ([-0.2, 0.1, 0.0, 0.0, 0.0], True)

    ```
    """
    world = _validate.floating("world", world)
    if world.ndim != 2 or world.shape[-1] not in (2, 3):
        raise ValueError(
            "`world` holds the planar target's points shared by every view, shape (N, 2) or "
            f"(N, 3); got {tuple(world.shape)}."
        )
    if world.shape[-1] == 2:
        world = jnp.concatenate([world, jnp.zeros_like(world[:, :1])], -1)
    pixels = _validate.floating("pixels", pixels, (None, 2))
    if pixels.ndim != 3:
        raise ValueError(
            f"`pixels` must be (V, N, 2): the target's N points in each of V views; got "
            f"{tuple(pixels.shape)}."
        )
    world, pixels, mask = _validate.correspondences(
        world, pixels, mask, min_points=MIN_PLANE_POINTS
    )
    _check_views(pixels, mask, skew)
    dtype = world.dtype
    if _validate.is_concrete(world, mask):
        used = np.asarray(mask).any(0)
        plane = _plane_frame(np.asarray(world), used, dtype)
    else:
        plane = RigidTransform.identity(dtype)  # traced: the user's z = 0 plane is assumed
    rcond = float(jnp.finfo(dtype).eps) ** 0.5 if rcond is None else float(rcond)
    H, closed, status, condition = _closed_form(world, plane, pixels, mask, bool(skew), rcond)
    camera, refinement = closed, None
    if refine and _validate.is_concrete(status) and bool(jnp.any(status == Status.OK)):
        # Refine the views that succeeded; the others stay NaN.
        keep = np.flatnonzero(np.asarray(status) == Status.OK)
        every = len(keep) == pixels.shape[0]
        select = (lambda x: x) if every else (lambda x: x[keep])  # noqa: E731
        refinement = refine_rig(
            jax.tree_util.tree_map(select, closed),
            world,
            jnp.where(select(mask)[..., None], select(pixels), 0.0),
            select(mask),
            shared_intrinsics=True,
            distortion=distortion,
            fix=fix,
            skew=skew,
            loss=loss,
            solver=solver,
            max_steps=max_steps,
        )
        camera = refinement.cameras
        if not every:
            camera = jax.tree_util.tree_map(lambda c, r: c.at[keep].set(r), closed, camera)
    report, rms = _finish(camera, world, pixels, mask, status)
    return PlanarCalibration(
        camera=camera,
        closed_form=closed,
        homographies=H,
        plane=plane,
        report=report,
        rms=rms,
        status=status,
        condition=condition,
        refinement=refinement,
    )
