"""N-view triangulation: one world point from its pixels in several calibrated views."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _small, _validate
from ._camera import Camera, undistort_points

__all__ = ["Triangulation", "triangulate", "reproject"]


class Triangulation(eqx.Module):
    """The result of `triangulate`, per point.

    - `points`: `(..., N, 3)` in the cameras' (global) frame; NaN where fewer than 2 views.
    - `views`: `(..., N)` int, the number of views used.
    - `rms`: `(..., N)` reprojection RMS over the views used, in pixels (distortion included);
      NaN, like `angle`, for a point seen by fewer than two views.
    - `angle`: `(..., N)` the widest angle between two of the point's rays, in degrees: small
      angles mean depth poorly determined.
    - `ok`: `(..., N)` bool: at least 2 views, in front of every camera that sees it, and an
      angle of at least `min_angle`.
    """

    points: Float[Array, "*batch N 3"]
    views: Int[Array, "*batch N"]
    rms: Float[Array, "*batch N"]
    angle: Float[Array, "*batch N"]
    ok: Bool[Array, "*batch N"]


def _total(a):
    """The sum over the views (leading axis)."""
    return _small.over_leading(jnp.add, a)


def _linear_points(cameras: Camera, x, y, w):
    """The points `(3, N)` in their normalised frames, and the frames, from normalised camera
    coordinates `x, y (C, N)` and view weights `w (C, N)` (1 where seen, 0 where not).

    Hartley's normalisation for triangulation: the world frame moved to the centroid of the
    cameras that see the point and scaled by their spread, so that every entry of the linear
    system is of order one in float32 too; each view's rows weighted by its focal length
    relative to their mean, so that, as in pixel units, a pixel of noise counts the same in
    every camera. Each point is then the null vector of its 2C x 4 system `x P3 - P1 = 0,
    y P3 - P2 = 0`, found as the smallest eigenvector of the 4 x 4 normal matrix. Everything is
    written with the points as the last axis, so each step is one elementwise pass over them.
    """
    n = _total(w)
    count = jnp.maximum(n, 1.0)
    centres = cameras.center[:, :, None]  # (C, 3, 1)
    middle = _total(w[:, None] * centres) / count  # (3, N)
    # `where` before `sqrt` and division: a point seen by fewer than two views has a zero
    # spread, and its derivative must stay finite (0 * inf in the backward pass would turn the
    # gradient of every camera into NaN, even where that point's output is not used).
    ms = _total(w * sum((centres[:, k] - middle[k]) ** 2 for k in range(3))) / count
    spread = jnp.sqrt(jnp.where(ms > 0, ms, 1.0))
    focal = jnp.sqrt(jnp.abs(cameras.alpha_u * cameras.alpha_v))
    mean_focal = _total(w * focal[:, None]) / count
    per_focal = 1.0 / jnp.where(mean_focal > 0, mean_focal, 1.0)
    R, t = cameras.R, cameras.t
    pairs = [(i, j) for i in range(4) for j in range(i + 1)]

    def add_view(c, entries):
        # rows k of the normalised, weighted camera c: weight [R_k | (R_k middle + t_k) / spread]
        weight = w[c] * focal[c] * per_focal
        P = [
            [weight * R[c, k, j] for j in range(3)]
            + [weight * (sum(R[c, k, j] * middle[j] for j in range(3)) + t[c, k]) / spread]
            for k in range(3)
        ]
        rows_x = [x[c] * P[2][j] - P[0][j] for j in range(4)]
        rows_y = [y[c] * P[2][j] - P[1][j] for j in range(4)]
        return entries + jnp.stack(
            [rows_x[i] * rows_x[j] + rows_y[i] * rows_y[j] for i, j in pairs]
        )

    # One view at a time: a pass over the points per view, not (C, N) intermediates in memory.
    entries = jax.lax.fori_loop(
        0, x.shape[0], add_view, jnp.zeros((len(pairs), x.shape[1]), x.dtype)
    )
    G = [[entries[pairs.index((max(i, j), min(i, j)))] for j in range(4)] for i in range(4)]
    # A point seen by fewer than two views gets a harmless stand-in (it is flagged not ok), so
    # that no derivative meets the repeated eigenvalues of an all-zero matrix.
    seen = n >= 2
    G = jnp.stack([jnp.stack([jnp.where(seen, G[i][j], float(4 - i) * (i == j)) for j in range(4)])
                   for i in range(4)])  # fmt: skip
    v = _smallest_eigenvectors(G)
    return v[:3] / v[3], middle, spread


@jax.custom_jvp
def _smallest_eigenvectors(G):
    """The unit eigenvectors `(4, N)` of the smallest eigenvalues of the positive semi-definite
    `G (4, 4, N)`: inverse iteration written out entry by entry (`_small`), from the origin of the
    normalised frame, (0, 0, 0, 1), never orthogonal to the answer (a point's last homogeneous
    coordinate is not 0). In float64, noise-free points come back to ~1e-12 relative."""
    A = [[G[i, j] for j in range(4)] for i in range(4)]
    L = _small.cholesky(A, jnp.finfo(G.dtype).eps * sum(A[i][i] for i in range(4)) / 4)
    zero, one = jnp.zeros_like(A[0][0]), jnp.ones_like(A[0][0])
    v = _small.inverse_iteration(lambda b: _small.cho_solve(L, b), [zero] * 3 + [one], _STEPS)
    return jnp.stack(v)


_STEPS = 8


@_smallest_eigenvectors.defjvp
def _smallest_eigenvectors_jvp(primals, tangents):
    (G,), (dG,) = primals, tangents
    v = _smallest_eigenvectors(G)
    dG_v = jnp.sum(dG * v[None], axis=1)  # (4, N); only derivatives pay for this reduction
    tangent = jax.vmap(_small.eigenvector_tangent, in_axes=-1, out_axes=-1)(G, v, dG_v)
    return v, tangent


def _diagnostics(cameras: Camera, X, pixels, w):
    """Views, reprojection RMS, widest ray angle (degrees) and in front, per point `X (N, 3)`."""
    n = _total(w)
    err = cameras.project(X) - pixels  # (C, N, 2)
    rms = jnp.sqrt(_total(w * (err[..., 0] ** 2 + err[..., 1] ** 2)) / jnp.maximum(n, 1.0))
    in_front = _small.over_leading(jnp.minimum, jnp.where(w > 0, cameras.depth(X), 1.0)) > 0
    # Sums over the 3 coordinates written out: XLA on CPU reduces short axes slowly.
    rays = [X[:, k] - cameras.center[:, k, None] for k in range(3)]  # (C, N) each
    length = jnp.sqrt(sum(r * r for r in rays))
    rays = jnp.stack([r / length for r in rays])  # (3, C, N)

    def widest(i, smallest):
        cos = sum(rays[k, i][None] * rays[k] for k in range(3))  # (C, N): view i against all
        cos = jnp.where((w[i] > 0) & (w > 0), cos, 1.0)
        return jnp.minimum(smallest, _small.over_leading(jnp.minimum, cos))

    smallest = jax.lax.fori_loop(0, w.shape[0], widest, jnp.ones_like(n))
    angle = jnp.degrees(jnp.arccos(jnp.clip(smallest, -1.0, 1.0)))
    # A point seen by fewer than two views has no position: its diagnostics are NaN, not
    # whatever the rounding of its stand-in happened to give.
    rms, angle = (jnp.where(n >= 2, a, jnp.nan) for a in (rms, angle))
    return n, rms, angle, in_front


def _refine_point(cameras: Camera, X0, pixels, m, max_steps):
    def residuals(X, _):
        r = cameras.project(X[None])[:, 0] - pixels
        return jnp.where(m[:, None], r, 0.0)

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    sol = optx.least_squares(residuals, solver, X0, max_steps=max_steps, throw=False)
    return jnp.where(jnp.all(jnp.isfinite(sol.value)), sol.value, X0)


@functools.partial(jax.jit, static_argnames=("refine", "max_steps"))
def _triangulate(cameras, pixels, mask, min_angle, refine, max_steps):
    # Undistorted pixels to normalised camera coordinates (K^-1 x). Hidden pixels are replaced
    # before any arithmetic, so that NaN in them reaches neither the points nor their
    # derivatives.
    m = mask & jnp.all(jnp.isfinite(pixels), -1)
    principal = jnp.stack([cameras.u0, cameras.v0], -1)[:, None]
    pixels = jnp.where(m[..., None], pixels, principal)
    # Undistortion (Newton steps per pixel) is a third of the work; skip it for pinhole rigs.
    ideal = jax.lax.cond(
        jnp.any(cameras.dist != 0), lambda p: undistort_points(cameras, p), lambda p: p, pixels
    )  # (C, N, 2)
    y = (ideal[..., 1] - cameras.v0[:, None]) / cameras.alpha_v[:, None]
    x = (ideal[..., 0] - cameras.u0[:, None] - cameras.skew[:, None] * y) / cameras.alpha_u[:, None]
    w = m.astype(pixels.dtype)
    Xn, middle, spread = _linear_points(cameras, x, y, w)
    X = (middle + spread * Xn).T  # (N, 3)
    if refine:
        refine_one = functools.partial(_refine_point, cameras, max_steps=max_steps)
        X = jax.vmap(refine_one, in_axes=(0, 1, 1))(X, pixels, m)
    n, rms, angle, in_front = _diagnostics(cameras, X, pixels, w)
    ok = (n >= 2) & in_front & (angle >= min_angle) & jnp.all(jnp.isfinite(X), -1)
    X = jnp.where((n >= 2)[:, None], X, jnp.nan)
    return Triangulation(points=X, views=n.astype(jnp.int32), rms=rms, angle=angle, ok=ok)


def triangulate(
    cameras: Camera,
    pixels: Float[Array, "*batch C N 2"],
    mask: Bool[Array, "*batch C N"] | None = None,
    *,
    refine: bool = False,
    min_angle: float = 1.0,
    max_steps: int = 50,
) -> Triangulation:
    """Reconstruct world points from their pixels in several calibrated views.

    For each point: the pixels are undistorted (`undistort_points`) and taken to normalised
    camera coordinates, and the point is the null vector of the `2C x 4` linear system of its
    visible views (the DLT of the point: the smallest eigenvector of its 4 x 4 normal matrix, by
    inverse iteration; equal to a per-point SVD to 1e-9); with `refine=True` it is then moved to
    the minimum of its reprojection error (optimistix Levenberg–Marquardt, distortion included).
    All points (and all point sets) in one jit-compiled, vectorised call. Differentiable with
    respect to the pixels and the cameras (so `jax.jacfwd` gives the first-order covariance of
    the points).

    **Arguments:**

    - `cameras`: a rig `(C,)` in one (global) frame.
    - `pixels`: `(..., C, N, 2)`: point n as seen by camera c; leading axes are point sets.
    - `mask`: `(..., C, N)` visibility; default: the finite pixels. Hidden views have no
      influence, even if NaN.
    - `refine`: polish each point by minimising its reprojection error.
    - `min_angle`: the smallest ray angle (degrees) for `ok`.
    - `max_steps`: Levenberg–Marquardt steps per point with `refine`.

    **Returns:** a `Triangulation` (points and per-point diagnostics).

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4)
    >>> out = mc.triangulate(rig.cameras, rig.pixels)
    >>> float(np.abs(out.points - rig.world).max()) < 1e-3, out.views[:3].tolist()  # float32
    (True, [4, 4, 4])

    ```
    """
    if not isinstance(cameras, Camera) or len(cameras.batch_shape) != 1:
        raise ValueError("`cameras` must be a rig: one `Camera` with a camera axis (C,).")
    C = cameras.batch_shape[0]
    pixels = _validate.floating("pixels", pixels, (None, None, 2))
    if pixels.shape[-3] != C:
        raise ValueError(
            f"`pixels` must be (..., C, N, 2) with C = {C} cameras; got {tuple(pixels.shape)}."
        )
    if C < 2:
        raise ValueError("triangulation needs at least 2 cameras.")
    if mask is None:
        mask = jnp.all(jnp.isfinite(pixels), -1)
    mask = _validate.boolean_mask("mask", mask, pixels.shape[:-1])
    cameras = jax.tree_util.tree_map(lambda a: jnp.asarray(a, pixels.dtype), cameras)
    run = functools.partial(
        _triangulate,
        cameras,
        min_angle=jnp.asarray(min_angle, pixels.dtype),
        refine=bool(refine),
        max_steps=int(max_steps),
    )
    batch = pixels.shape[:-3]
    flat = run if not batch else jax.vmap(run)
    out = flat(pixels.reshape(-1, *pixels.shape[-3:]) if batch else pixels,
               mask.reshape(-1, *mask.shape[-2:]) if batch else mask)  # fmt: skip
    if batch:
        out = jax.tree_util.tree_map(lambda a: a.reshape(*batch, *a.shape[1:]), out)
    return out


def reproject(cameras: Camera, points) -> Float[Array, "C N 2"]:
    """Every camera's pixel of every point: the paper's "reconstruct the other points" step.

    `points` is `(N, 3)` in the cameras' frame, or a `Triangulation`. Use
    `mvcalib.reprojection_report(cameras, points, observed, mask)` for the per-camera
    disagreement with observed pixels (Table I).

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=3)
    >>> bool(np.allclose(mc.reproject(rig.cameras, rig.world), rig.pixels))
    True

    ```
    """
    if isinstance(points, Triangulation):
        points = points.points
    points = _validate.floating("points", points, (None, 3))
    return cameras.project(points)
