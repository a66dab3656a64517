"""Normalised direct linear transformation, solved by SVD, batched over cameras."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from . import _validate
from ._status import Status

# The largest reprojection RMS of a camera, as a fraction of its pixels' spread, that is still
# called a fit (else `Status.POOR_FIT`). The DLT of synthetic cameras with strong radial
# distortion (k1 = -0.5, k2 = 0.3, the target filling the image) reaches 0.02; one pixel off by
# half the spread among the 19 of the box-corner target gives more than 0.05 (docs/reliability.md).
DEFAULT_MAX_RELATIVE_RMS = 0.05


def _similarity(points, w):
    """Hartley's normalisation `T` (centroid to 0, RMS distance sqrt(d)) over the weighted points.

    RMS rather than mean distance: the same conditioning, and a derivative that exists when a
    point sits on the centroid.
    """
    d = points.shape[-1]
    n = jnp.maximum(w.sum(), 1.0)
    c = (w[:, None] * points).sum(0) / n
    ms = (w * jnp.sum((points - c) ** 2, axis=-1)).sum() / n
    s = jnp.sqrt(d / jnp.where(ms > 0, ms, 1.0))
    T = jnp.eye(d + 1, dtype=points.dtype) * s
    T = T.at[:d, d].set(-s * c).at[d, d].set(1.0)
    return T, s, c


@jax.custom_jvp
def _null_vector(A):
    """The unit right singular vector of `A` for its smallest singular value, and all of them.

    The singular values are diagnostics and carry no derivative.
    """
    _, s, vt = jnp.linalg.svd(A, full_matrices=False)
    return vt[-1], s


@_null_vector.defjvp
def _null_vector_jvp(primals, tangents):
    # JAX's SVD derivative also differentiates U, dividing by the smallest singular value, which is
    # zero for noise-free data. First-order perturbation of the smallest eigenvector v of
    # G = A^T A needs only the gap to the next eigenvalue, which is what makes the DLT solution
    # unique anyway: (G - l I) dv = -(I - v v^T) dG v with v^T dv = 0. Adding c v v^T makes the
    # matrix invertible without changing that solution (B v = c v, and the right-hand side is
    # orthogonal to v). Written with v from this function itself and a linear solve, not the
    # other singular vectors, it is differentiable again: second derivatives stay finite where
    # other singular values repeat (a symmetric target), where JAX's SVD rule gives NaN.
    (A,), (dA,) = primals, tangents
    v, s = _null_vector(A)
    G = A.T @ A
    lam = v @ G @ v
    c = jnp.trace(G) / G.shape[-1] + 1.0  # any c > 0; this one is of G's scale
    B = G - lam * jnp.eye(G.shape[-1], dtype=G.dtype) + c * jnp.outer(v, v)
    dG_v = dA.T @ (A @ v) + A.T @ (dA @ v)
    rhs = dG_v - v * (v @ dG_v)
    dv = -jnp.linalg.solve(B, rhs)
    return (v, s), (dv, jnp.zeros_like(s))


def _design_matrix(world, pixels, visible):
    """The 2N x 12 matrix L of eq. 11 (two rows per point; rows of hidden points are zero).

    For 2-D points of a plane, `world (N, 2)`, the same rows make the 2N x 9 system of a
    homography (`mvcalib.calibrate_planar`)."""
    Xh = jnp.concatenate([world, jnp.ones_like(world[:, :1])], axis=-1)
    zero = jnp.zeros_like(Xh)
    rows_u = jnp.concatenate([Xh, zero, -pixels[:, :1] * Xh], axis=-1)  # eq. 9
    rows_v = jnp.concatenate([zero, Xh, -pixels[:, 1:] * Xh], axis=-1)  # eq. 10
    L = jnp.stack([rows_u, rows_v], axis=1).reshape(-1, 3 * Xh.shape[-1])
    return jnp.where(jnp.repeat(visible, 2)[:, None], L, 0.0)


def poor_fit(rms, pixels, visible, max_relative_rms):
    """True where a camera's reprojection RMS over its visible points exceeds `max_relative_rms`
    times the pixels' spread (the median distance of the visible pixels from their median).

    A check of an answer, not part of it: no derivative flows through it. Both sides are
    invariant to similarities of the world and pixel frames, like the DLT itself; the median
    keeps one wild pixel from inflating the spread that it is measured against.
    """
    rms, pixels = jax.lax.stop_gradient((rms, pixels))
    hidden = jnp.where(visible[..., None], pixels, jnp.nan)
    middle = jnp.nanmedian(hidden, axis=-2, keepdims=True)
    spread = jnp.nanmedian(jnp.linalg.norm(hidden - middle, axis=-1), axis=-1)
    return ~(rms <= max_relative_rms * spread)


def _rms(P, world, pixels, visible):
    """The reprojection RMS of `P (3, 4)` over the visible points."""
    h = world @ P[:, :3].T + P[:, 3]
    depth = jnp.where(visible, h[:, 2], 1.0)
    err2 = jnp.where(visible, jnp.sum((h[:, :2] / depth[:, None] - pixels) ** 2, axis=-1), 0.0)
    return jnp.sqrt(jnp.sum(err2) / jnp.maximum(jnp.sum(visible), 1))


def _dlt_kernel(world, pixels, mask, rcond, max_relative_rms):
    """One camera: (N, 3), (N, 2), (N,) -> P (3, 4), status, condition number, mirrored."""
    dtype = world.dtype
    finite = jnp.all(jnp.isfinite(world), -1) & jnp.all(jnp.isfinite(pixels), -1)
    all_finite = jnp.all(finite | ~mask)
    visible = mask & finite
    # Hidden points are replaced before any arithmetic, so neither their values nor NaN/inf in
    # them can reach the result or its derivative.
    world = jnp.where(visible[:, None], world, 0.0)
    pixels = jnp.where(visible[:, None], pixels, 0.0)
    w = visible.astype(dtype)

    T3, _, _ = _similarity(world, w)
    T2, s2, c2 = _similarity(pixels, w)
    world_n = world @ T3[:3, :3].T + T3[:3, 3]
    pixels_n = pixels @ T2[:2, :2].T + T2[:2, 2]

    v, sv = _null_vector(_design_matrix(world_n, pixels_n, visible))
    T2_inv = jnp.array([[1 / s2, 0, c2[0]], [0, 1 / s2, c2[1]], [0, 0, 1]], dtype=dtype)
    P = T2_inv @ v.reshape(3, 4) @ T3

    # ||m3|| = 1 (Faugeras–Toscani), with the sign that puts the visible points in front.
    P = P / jnp.linalg.norm(P[2, :3])
    depth = world @ P[2, :3] + P[2, 3]
    P = jnp.where(jnp.sum(jnp.where(visible, depth, 0.0)) < 0, -P, P)
    depth = world @ P[2, :3] + P[2, 3]

    condition = sv[0] / sv[-2]
    n_visible = jnp.sum(visible)
    status = jnp.select(
        [
            ~all_finite,
            n_visible < _validate.MIN_POINTS,
            ~(sv[-2] > rcond * sv[0]),
            jnp.any(visible & (depth <= 0)),
            poor_fit(_rms(P, world, pixels, visible), pixels, visible, max_relative_rms),
        ],
        [
            Status.NON_FINITE,
            Status.TOO_FEW_POINTS,
            Status.DEGENERATE,
            Status.POINTS_BEHIND,
            Status.POOR_FIT,
        ],
        Status.OK,
    ).astype(jnp.int32)
    P = jnp.where(status == Status.OK, P, jnp.nan)
    # With the points in front, det(M) < 0 means the world frame is mirrored relative to the
    # camera: left-handed world coordinates (the Oxford VGG sets are) or pixels with y up.
    mirrored = jnp.linalg.det(P[:, :3]) < 0
    return P, status, condition, mirrored


@functools.partial(jax.jit, static_argnames=("rcond", "max_relative_rms"))
def solve_validated(world, pixels, mask, rcond, max_relative_rms=DEFAULT_MAX_RELATIVE_RMS):
    """The DLT of every camera for inputs that passed `_validate.correspondences`."""
    kernel = functools.partial(_dlt_kernel, rcond=rcond, max_relative_rms=max_relative_rms)
    return jnp.vectorize(kernel, signature="(n,3),(n,2),(n)->(3,4),(),(),()")(world, pixels, mask)


def check_relative_rms(value) -> float:
    """`max_relative_rms` as a float, or a ValueError saying what it must be."""
    value = float(value)
    if not value > 0:
        raise ValueError(
            f"`max_relative_rms` must be positive (or inf to turn the check off); got {value}."
        )
    return value


def default_rcond(dtype) -> float:
    """sqrt(machine epsilon): 1.5e-8 in float64, 3.5e-4 in float32."""
    return float(jnp.finfo(dtype).eps) ** 0.5


def solve(
    world,
    pixels,
    mask=None,
    *,
    rcond: float | None = None,
    max_relative_rms: float = DEFAULT_MAX_RELATIVE_RMS,
):
    """Validated DLT returning `(P, status, condition, mirrored)`; see `dlt`."""
    world, pixels, mask = _validate.correspondences(world, pixels, mask)
    rcond = default_rcond(world.dtype) if rcond is None else float(rcond)
    return solve_validated(world, pixels, mask, rcond, check_relative_rms(max_relative_rms))


def dlt(
    world: Float[Array, "*batch N 3"],
    pixels: Float[Array, "*batch N 2"],
    mask: Bool[Array, "*batch N"] | None = None,
    *,
    max_relative_rms: float = DEFAULT_MAX_RELATIVE_RMS,
) -> Float[Array, "*batch 3 4"]:
    """Projection matrices from 3-D/2-D correspondences by the normalised DLT (paper, eqs. 6–11).

    For each camera, the world points and pixels are first normalised (Hartley: centroid to the
    origin, RMS distance sqrt(3) and sqrt(2)), the 2N x 12 system `L a = 0` is solved by SVD (the
    right singular vector of the smallest singular value), and the result is de-normalised and
    scaled so that `||m3|| = 1` with the sign that puts the visible points in front of the camera.
    All cameras are solved in one jit-compiled, vectorised call.

    **Arguments:**

    - `world`: world points `(..., N, 3)`, N >= 6. Leading axes broadcast against those of
      `pixels`, so one target seen by C cameras is `(N, 3)` against `(C, N, 2)`.
    - `pixels`: observed pixels `(..., N, 2)` as `(x = column, y = row)`.
    - `mask`: visibility `(..., N)`, boolean. Hidden points have no influence at all: their values,
      even NaN, never reach the result or its gradient.
    - `max_relative_rms`: the largest reprojection RMS of an answer, as a fraction of the spread
      of its pixels (median distance from their median), that counts as a fit; default 0.05.
      `inf` turns the check off.

    **Returns:** `P` of shape `(..., 3, 4)`. A camera whose P is not determined (fewer than 6
    visible points, coplanar or collinear points, NaN in traced input, points on both sides of the
    camera) or does not fit its points (`max_relative_rms`: a wild correspondence) gets a P full
    of NaN instead of a plausible wrong answer; `mvcalib.calibrate` says why.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=3)
    >>> P = mc.dlt(rig.world, rig.pixels)
    >>> P.shape
    (3, 3, 4)

    ```
    """
    return solve(world, pixels, mask, max_relative_rms=max_relative_rms)[0]
