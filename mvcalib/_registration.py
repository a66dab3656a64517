"""Local-to-global registration: rigid transforms, Procrustes, and cameras in the global frame."""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import _buckets, _validate
from ._camera import Camera
from ._rotation import nearest_rotation


class RigidTransform(eqx.Module):
    """The map `Y = R X + t` (the paper's eq. 24); batched over leading axes like `Camera`.

    Compose with `@`: `(a @ b).apply(x) == a.apply(b.apply(x))`.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> T = mc.RigidTransform(jnp.eye(3), jnp.array([1.0, 2.0, 3.0]))
    >>> (T.inverse() @ T).apply(jnp.array([[4.0, 5.0, 6.0]])).tolist()
    [[4.0, 5.0, 6.0]]

    ```
    """

    R: Float[Array, "*batch 3 3"]
    t: Float[Array, "*batch 3"]

    def __init__(self, R, t):
        self.R = jnp.asarray(R)
        self.t = jnp.asarray(t)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.t.shape[:-1])

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("a single RigidTransform has no length; a batch has leading axes.")
        return self.batch_shape[0]

    def __getitem__(self, index) -> RigidTransform:
        """Select transforms of a batch: `poses[3]`, `poses[1:3]`, `poses[ok]`."""
        if not self.batch_shape:
            raise TypeError("a single RigidTransform cannot be indexed; a batch has leading axes.")
        return _buckets.take(self, index)

    @classmethod
    def identity(cls, dtype=float) -> RigidTransform:
        # (put from NumPy: `jnp.eye`, `jnp.zeros` and `jnp.asarray` of a NumPy array, called
        # eagerly, compile a small program each)
        dtype = jax.dtypes.canonicalize_dtype(dtype)
        return cls(*jax.device_put((np.eye(3, dtype=dtype), np.zeros(3, dtype=dtype))))

    def apply(self, points: Float[Array, "*batch N 3"]) -> Float[Array, "*batch N 3"]:
        """`R X + t` for points `(..., N, 3)`."""
        points = points if isinstance(points, (np.ndarray, jax.Array)) else np.asarray(points)
        return _apply(self.R, self.t, points)

    def inverse(self) -> RigidTransform:
        """`X = R^T (Y - t)`; assumes `R` is a rotation (as everything `procrustes` returns)."""
        return RigidTransform(*_inverse(self.R, self.t))

    def __matmul__(self, other: RigidTransform) -> RigidTransform:
        return RigidTransform(*_compose(self.R, self.t, other.R, other.t))

    def as_matrix(self) -> Float[Array, "*batch 4 4"]:
        """The 4 x 4 homogeneous matrix."""
        return _as_matrix(self.R, self.t)


# RigidTransform's arithmetic, each one compiled program where called eagerly (`_buckets.eager`)
@_buckets.eager
def _apply(R, t, points):
    return points @ jnp.swapaxes(R, -1, -2) + t[..., None, :]


@_buckets.eager
def _inverse(R, t):
    Rt = jnp.swapaxes(R, -1, -2)
    return Rt, -jnp.einsum("...ij,...j->...i", Rt, t)


@_buckets.eager
def _compose(R1, t1, R2, t2):
    return R1 @ R2, jnp.einsum("...ij,...j->...i", R1, t2) + t1


@_buckets.eager
def _as_matrix(R, t):
    top = jnp.concatenate([R, t[..., None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0, 0, 0, 1], R.dtype), (*top.shape[:-2], 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def _procrustes_kernel(src, dst, w):
    n = jnp.sum(w)
    cs = (w[:, None] * src).sum(0) / n
    cd = (w[:, None] * dst).sum(0) / n
    H = ((w[:, None] * (dst - cd)).T) @ (src - cs)  # sum w (y - ȳ)(x - x̄)^T
    R = nearest_rotation(H)  # maximises sum w (y - ȳ)·R(x - x̄)
    # The best rotation is unique only if H has rank >= 2. Collinear or coincident points (or
    # fewer than 3 with non-zero weight) leave the rotation about their line free, and the SVD
    # would return one of them as if it were the answer: NaN instead. The threshold is the DLT's
    # (sqrt(eps)): below it, rounding alone moves R by more than sqrt(eps) radians. The test
    # is False for NaN, which an all-zero weight vector gives.
    sv = jnp.linalg.svd(jax.lax.stop_gradient(H), compute_uv=False)
    determined = sv[1] > jnp.finfo(H.dtype).eps ** 0.5 * sv[0]
    R = jnp.where(determined, R, jnp.nan)
    return R, cd - R @ cs, determined


def procrustes(
    src: Float[Array, "*batch N 3"],
    dst: Float[Array, "*batch N 3"],
    weights: Float[Array, "*batch N"] | None = None,
) -> RigidTransform:
    """The rigid transform minimising `sum w ||R src + t - dst||^2` (Kabsch, orthogonal Procrustes).

    The rotation comes from the SVD of the weighted cross-covariance and is always proper
    (det +1), also when the points are nearer a reflection than a rotation. This is the library's
    answer to the paper's registration step (eqs. 24–28); `procrustes_paper` is the paper's own
    unconstrained least squares, for comparison. Differentiable in `src`, `dst` and `weights`
    (also at symmetric configurations, where the SVD's own derivative is undefined); batched over
    leading axes, which broadcast.

    **Arguments:**

    - `src`: points in the local frame `(..., N, 3)`, N >= 3 and not collinear.
    - `dst`: the same points in the global frame `(..., N, 3)`.
    - `weights`: optional non-negative weights `(..., N)`; a zero weight removes a point.

    **Returns:** a `RigidTransform` with `dst ≈ transform.apply(src)`. Points that do not
    determine the rotation (collinear or coincident, or fewer than 3 with non-zero weight, in
    `src` or in `dst`) raise `ValueError`; inside `jax.jit`, where nothing can raise, that
    transform is NaN instead of one of the many rotations that fit.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> src = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> T = mc.procrustes(src, src + jnp.array([1.0, 2.0, 3.0]))
    >>> T.t.round(6).tolist()
    [1.0, 2.0, 3.0]

    ```
    """
    # concrete arrays are checked in NumPy, and the fit is one compiled program (eager `jnp`
    # operations would compile a program each)
    xp = np if _validate.is_concrete(src, dst, weights) else jnp
    src = _validate.floating("src", src, (None, 3), xp=xp)
    dst = _validate.floating("dst", dst, (None, 3), xp=xp)
    if src.shape[-2] != dst.shape[-2]:
        raise ValueError(
            f"`src` and `dst` must hold the same points; got shapes {tuple(src.shape)} and "
            f"{tuple(dst.shape)}."
        )
    _validate.at_least("src", src, 3, "points (not collinear) to fix a rotation")
    dtype = _validate.result_dtype(src.dtype, dst.dtype)
    if weights is None:
        weights = xp.ones(src.shape[-2], dtype)
    weights = _validate.floating("weights", weights, xp=xp).astype(dtype)
    if xp is np:
        for name, x in (("src", src), ("dst", dst), ("weights", weights)):
            if not np.all(np.isfinite(x)):
                raise ValueError(f"`{name}` contains NaN or inf.")
        if np.any(weights < 0):
            raise ValueError("`weights` must be non-negative.")
    R, t, determined = _procrustes(src.astype(dtype), dst.astype(dtype), weights)
    if _validate.is_concrete(determined) and not np.all(np.asarray(determined)):
        where = np.argwhere(~np.asarray(determined))
        at = f" (at batch index {tuple(int(i) for i in where[0])})" if where.shape[1] else ""
        raise ValueError(
            f"`src` and `dst` do not determine a rotation{at}: the points with non-zero weight "
            "are collinear or coincident (in `src` or in `dst`). At least 3 non-collinear "
            "points are needed."
        )
    if xp is np:
        _check_rigid_fit(src, dst, weights, np.asarray(R), np.asarray(t))
    return RigidTransform(R, t)


# A registration whose residual exceeds this share of the points' spread is no rigid motion.
_MAX_MISFIT = 0.05


def _check_rigid_fit(src, dst, weights, R, t) -> None:
    """Warn where the fitted motion leaves the points an RMS residual above `_MAX_MISFIT` of their
    spread about their centre (in `dst`): a benchmark trial registered a target in mm to a room
    in metres (110.7 m of residual on a 0.22 m room) and a left-handed room frame (94 mm on a
    219 mm target), silently."""
    moved = np.einsum("...ij,...nj->...ni", R, src) + t[..., None, :]
    w = np.broadcast_to(weights, moved.shape[:-1])
    total = np.maximum(np.sum(w, -1), np.finfo(float).tiny)
    misfit = np.sqrt(np.sum(w * np.sum((moved - dst) ** 2, -1), -1) / total)
    centre = np.sum(w[..., None] * dst, -2) / total[..., None]
    spread = np.sqrt(np.sum(w * np.sum((dst - centre[..., None, :]) ** 2, -1), -1) / total)
    worst = np.unravel_index(np.argmax(misfit / spread), np.shape(misfit))
    if misfit[worst] > _MAX_MISFIT * spread[worst]:
        at = f" (at batch index {tuple(int(i) for i in worst)})" if worst else ""
        warnings.warn(
            f"procrustes: no rigid motion fits the points{at}: an RMS residual of "
            f"{misfit[worst]:.3g}, {misfit[worst] / spread[worst]:.0%} of their spread "
            f"({spread[worst]:.3g}). Are `src` and `dst` in the same units (mm and m?), both "
            "right-handed, and the same points in the same order?",
            stacklevel=_validate._outside_mvcalib(),  # noqa: SLF001
        )


@_buckets.eager
def _procrustes(src, dst, weights):
    """`_procrustes_kernel` over the leading axes, which broadcast."""
    kernel = jnp.vectorize(_procrustes_kernel, signature="(n,3),(n,3),(n)->(3,3),(3),()")
    return kernel(src, dst, weights)


def _paper_kernel(src, dst):
    A = src[1:] - src[0]  # eq. 25: differences to point 1
    b = dst[1:] - dst[0]
    Z = jnp.linalg.solve(A.T @ A, A.T @ b)  # minimises eq. 27, ||b - A Z||^2
    R = Z.T
    return R, dst[0] - R @ src[0]  # eq. 28


def procrustes_paper(
    src: Float[Array, "*batch N 3"], dst: Float[Array, "*batch N 3"]
) -> RigidTransform:
    """The paper's registration (eqs. 25–28): unconstrained least squares for `R`, `T = Y1 - R X1`.

    `R` is a general 3 x 3 matrix, not constrained to be a rotation, and `T` trusts point 1
    exactly, so under measurement noise `R` is not orthogonal and the residual is larger than
    `procrustes`'s. Kept for comparison with the paper.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> src = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    >>> T = mc.procrustes_paper(src, src + 2.0)
    >>> T.R.round(6).tolist() == jnp.eye(3).tolist(), T.t.round(6).tolist()
    (True, [2.0, 2.0, 2.0])

    ```
    """
    src = _validate.floating("src", src, (None, 3))
    dst = _validate.floating("dst", dst, (None, 3))
    _validate.at_least("src", src, 4, "points (3 independent differences to point 1)")
    dtype = _validate.result_dtype(src.dtype, dst.dtype)
    R, t = jnp.vectorize(_paper_kernel, signature="(n,3),(n,3)->(3,3),(3)")(
        src.astype(dtype), dst.astype(dtype)
    )
    return RigidTransform(R, t)


def to_global(cameras: Camera, transform: RigidTransform) -> Camera:
    """Express cameras calibrated in a local frame in the global frame `Y = R X + T` (§III.B).

    A camera `x_cam = R_c X + t_c` becomes `x_cam = R_c R^T Y + (t_c - R_c R^T T)`. Batched: one
    transform for the whole rig, or one per camera (leading axes broadcast).

    **Example:**

    ```python
    >>> import jax, jax.numpy as jnp, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=2)
    >>> T = mc.RigidTransform(mc.rodrigues(jnp.array([0.1, 0.2, 0.3])), jnp.array([1.0, 2, 3]))
    >>> glob = mc.to_global(rig.cameras, T)
    >>> bool(jnp.allclose(glob.project(T.apply(rig.world)), rig.cameras.project(rig.world)))
    True

    ```
    """
    rig, per = cameras.R.shape[:-2], transform.R.shape[:-2]
    try:
        np.broadcast_shapes(rig, per)
    except ValueError:
        raise ValueError(
            f"`to_global`: the transforms' batch shape {per} does not broadcast with the rig's "
            f"{rig}: pass one transform, or one per camera."
        ) from None
    return _to_global(cameras, transform)


@_buckets.eager
def _to_global(cameras: Camera, transform: RigidTransform) -> Camera:
    inv = transform.inverse()
    R = cameras.R @ inv.R
    t = jnp.einsum("...ij,...j->...i", cameras.R, inv.t) + cameras.t
    return Camera(
        cameras.alpha_u,
        cameras.alpha_v,
        cameras.u0,
        cameras.v0,
        R,
        t,
        skew=cameras.skew,
        dist=cameras.dist,
        lens=cameras.lens,
    )
