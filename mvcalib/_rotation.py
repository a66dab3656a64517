"""Rotations: the nearest rotation to a matrix, with derivatives that exist at orthogonal R."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def hat(w, xp=jnp):
    """The skew-symmetric matrix `[w]x` with `hat(w) @ v == cross(w, v)`; `xp=np` for NumPy
    arrays on the host."""
    z = xp.zeros_like(w[..., 0])
    return xp.stack(
        [
            xp.stack([z, -w[..., 2], w[..., 1]], -1),
            xp.stack([w[..., 2], z, -w[..., 0]], -1),
            xp.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def vee(S):
    """Inverse of `hat` on the skew part of `S`."""
    return 0.5 * jnp.stack(
        [S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]], -1
    )


@jax.custom_jvp
def _nearest_rotation(H):
    U, _, Vt = jnp.linalg.svd(H)
    d = jnp.where(jnp.linalg.det(U @ Vt) < 0, -1.0, 1.0).astype(H.dtype)
    return (U * jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d])) @ Vt


@_nearest_rotation.defjvp
def _nearest_rotation_jvp(primals, tangents):
    # JAX's SVD derivative divides by differences of singular values, which are all equal when
    # H is already a rotation (re-orthogonalising a good R) or symmetric (a cube of points), so it
    # gives NaN exactly where calibration lives. Differentiate the optimality condition instead:
    # R = argmax tr(R^T H) makes M = R^T H symmetric; keeping it symmetric under H + dH with
    # R -> R (I + [w]x) gives [w]x M + M [w]x = R^T dH - dH^T R, i.e. (tr(M) I - M) w = b.
    # That matrix is singular only when the best rotation itself is not unique.
    (H,), (dH,) = primals, tangents
    R = _nearest_rotation(H)
    M = R.T @ H
    M = 0.5 * (M + M.T)
    A = jnp.trace(M) * jnp.eye(3, dtype=H.dtype) - M
    b = 2.0 * vee(R.T @ dH)
    w = jnp.linalg.solve(A, b)
    return R, R @ hat(w)


def nearest_rotation(H):
    """The rotation `R` (det +1) maximising `tr(R^T H)`: `U diag(1, 1, det(U V^T)) V^T`.

    For a nearly orthogonal `H` this is the re-orthogonalisation `R = U V^T` of the paper; for a
    cross-covariance `H = sum w (y - ȳ)(x - x̄)^T` it is the Kabsch rotation. Batched over leading
    axes; its derivative is defined wherever the answer is unique (also at orthogonal `H`).

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> R = mc.nearest_rotation(jnp.array([[2.0, 0.1, 0], [0, 1.0, 0], [0, 0, -1.0]]))
    >>> round(float(jnp.linalg.det(R)), 6), bool(jnp.allclose(R.T @ R, jnp.eye(3), atol=1e-6))
    (1.0, True)

    ```
    """
    return jnp.vectorize(_nearest_rotation, signature="(3,3)->(3,3)")(H)


def rodrigues(rvec):
    """Rotation matrix of an axis-angle vector (OpenCV's Rodrigues), gradient-safe at zero.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> (mc.rodrigues(jnp.array([0.0, 0.0, jnp.pi / 2])) @ jnp.array([1.0, 0, 0])).round(6).tolist()
    [0.0, 1.0, 0.0]

    ```
    """
    rvec = jnp.asarray(rvec)  # (NumPy float64 without x64: float32, as JAX takes it, no warning)
    theta2 = jnp.sum(rvec * rvec, axis=-1)
    small = theta2 < 1e-12
    safe2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(safe2)
    # sin(t)/t and (1 - cos t)/t^2 with their Taylor series near 0 (jaxlie does the same); the
    # latter as (sin(t/2) / (t/2))^2 / 2, without the cancellation of 1 - cos t, which cost its
    # second derivative 2e-5 (relative) just above the switch (t ~ 1e-6).
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    half = 0.5 * theta
    b = jnp.where(small, 0.5 - theta2 / 24.0, 0.5 * (jnp.sin(half) / half) ** 2)
    K = hat(rvec)
    eye = jnp.eye(3, dtype=rvec.dtype)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def exp_and_left_jacobian(w, R0):
    """`rodrigues(w) @ R0` and the left Jacobian `J` of the exponential at `w`, with which
    `d (rodrigues(w) @ R0 @ X) / d w_k = (J e_k) x (rodrigues(w) @ R0 @ X)`: both as 3 x 3
    nested lists of scalars, entry by entry, so that XLA fuses them into the kernels over the
    points (refinement's rotation increments). (As 3 x 3 products, and `jax.jacfwd(rodrigues)`
    for the derivative, each product and stack was a kernel of its own under `vmap`: a
    refinement step of the refine benchmark ran 123 kernels, 102 now, and 6-9 % faster.)

    `J = I + b [w]x + c [w]x^2` and `rodrigues(w) = I + a [w]x + b [w]x^2` with
    `a = sin(t) / t`, `b = (1 - cos t) / t^2 = (sin(t / 2) / (t / 2))^2 / 2` (no cancellation)
    and `c = (t - sin t) / t^3`, its Taylor series below t = 0.01 (where the quotient would
    lose up to 7e-12 of its value to cancellation)."""
    w = [w[i] for i in range(3)]  # (each entry indexed once: tracing costs per operation)
    R0 = [[R0[i, j] for j in range(3)] for i in range(3)]
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    safe2 = jnp.where(t2 < 1e-12, 1.0, t2)
    t = jnp.sqrt(safe2)
    sine_half = jnp.sin(0.5 * t) / (0.5 * t)
    a = jnp.where(t2 < 1e-12, 1.0 - t2 / 6.0, sine_half * jnp.cos(0.5 * t))
    b = jnp.where(t2 < 1e-12, 0.5 - t2 / 24.0, 0.5 * sine_half * sine_half)
    c = jnp.where(t2 < 1e-4, 1.0 / 6.0 - t2 * (1.0 / 120.0 - t2 / 5040.0), (1.0 - a) / safe2)
    # [w]x (zero diagonal) and [w]x^2 = w w^T - t2 I, then I + x [w]x + y [w]x^2 entry by entry
    hat = {(0, 1): -w[2], (0, 2): w[1], (1, 0): w[2], (1, 2): -w[0], (2, 0): -w[1], (2, 1): w[0]}
    hat2 = [[w[i] * w[j] - t2 if i == j else w[i] * w[j] for j in range(3)] for i in range(3)]

    def series(x, y):
        return [
            [1.0 + y * hat2[i][j] if i == j else x * hat[i, j] + y * hat2[i][j] for j in range(3)]
            for i in range(3)
        ]

    E = series(a, b)
    R = [[E[i][0] * R0[0][j] + E[i][1] * R0[1][j] + E[i][2] * R0[2][j] for j in range(3)]
         for i in range(3)]  # fmt: skip
    J = series(b, c)
    return R, J
