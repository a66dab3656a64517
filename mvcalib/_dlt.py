"""Normalised direct linear transformation, batched over cameras.

The DLT's answer is the right singular vector of the 2N x 12 system L for its smallest singular
value (paper, eq. 11). LAPACK's SVD of each camera's small L costs ~20 µs on CPU, one camera
after another; the same vector, as the smallest eigenvector of `L^T L`, comes from 40 sums over
the points (for a target the cameras share, one matrix product for all of them) and inverse
iteration on a 12 x 12 matrix whose structure reduces every solve to 4 x 4 ones, written out
entry by entry so that XLA runs all cameras through a few fused loops.
Hartley's normalisation keeps `L^T L` well conditioned (`(s_1 / s_11)^2` ~17 for the box-corner
target), so squaring L costs no accuracy worth the name: the cameras equal the SVD's to ~1e-13.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from . import _buckets, _sharding, _small, _validate
from ._status import Status

# The largest reprojection RMS of a camera, as a fraction of its pixels' spread, that is still
# called a fit (else `Status.POOR_FIT`). The DLT of synthetic cameras with strong radial
# distortion (k1 = -0.5, k2 = 0.3, the target filling the image) reaches 0.02; one pixel off by
# half the spread among the 19 of the box-corner target gives more than 0.05 (docs/reliability.md).
DEFAULT_MAX_RELATIVE_RMS = 0.05


def _similarity(points, w):
    """Hartley's normalisation `T` (centroid to 0, RMS distance sqrt(d)) over the weighted points,
    with its scale and centroid (`_frame`)."""
    d = points.shape[-1]
    s, c = _frame(points, w)
    T = jnp.eye(d + 1, dtype=points.dtype) * s
    T = T.at[:d, d].set(-s * c).at[d, d].set(1.0)
    return T, s, c


def _frame(points, w):
    """The scale `s (...)` and centroid `c (..., d)` of Hartley's normalisation `s (x - c)` of the
    points `(..., N, d)` weighted by `w (..., N)`: centroid to 0, RMS distance sqrt(d).

    RMS rather than mean distance: the same conditioning, and a derivative that exists when a
    point sits on the centroid. One array per coordinate: XLA's CPU backend sums over a short
    trailing axis slowly.
    """
    d = points.shape[-1]
    n = jnp.maximum(w.sum(-1), 1.0)
    x = [points[..., k] for k in range(d)]
    c = [jnp.sum(w * xk, -1) / n for xk in x]
    ms = jnp.sum(w * sum((xk - ck[..., None]) ** 2 for xk, ck in zip(x, c)), -1) / n
    return jnp.sqrt(d / jnp.where(ms > 0, ms, 1.0)), jnp.stack(c, -1)


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
    # zero for noise-free data; the eigenvector rule of G = A^T A needs only the gap above it.
    (A,), (dA,) = primals, tangents
    v, s = _null_vector(A)
    dv = _small.eigenvector_tangent(A.T @ A, v, dA.T @ (A @ v) + A.T @ (dA @ v))
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


# Index of entry (i, j) of a symmetric 4 x 4 matrix among its 10 distinct entries.
_PAIRS = [(i, j) for i in range(4) for j in range(i + 1)]
_ENTRY = {**{p: k for k, p in enumerate(_PAIRS)}, **{p[::-1]: k for k, p in enumerate(_PAIRS)}}


def _moments(world, pixels, mask):
    """The distinct entries `(4, 10, C)` of the four 4 x 4 blocks of each camera's `L^T L` (L of
    eq. 11, of its normalised points), the points it used (`visible (C, N)`: in the mask and
    finite), `||L||_F`, and the normalisations: `s3 (C,)`, `c3 (C, 3)` of the world points and
    `s2 (C,)`, `c2 (C, 2)` of the pixels; for `pixels (C, N, 2)`, `mask (C, N)` of visible points
    and `world (N, 3)` shared by the cameras or `(C, N, 3)`.

    With X the homogeneous world point and (u, v) its pixel, a point adds to `L^T L` the blocks
    `X X^T` (twice, for the rows of P1 and P2), `-u X X^T`, `-v X X^T` and `(u^2 + v^2) X X^T`:
    the whole matrix is four weighted moment matrices of the points, 40 sums over the points.

    Formed from each camera's normalised world points (`_own_moments`), that takes the products
    of every camera's points, one small matrix product per camera. For a target the cameras
    share, its ten products are formed once, in the coordinates given, and the moments of all
    cameras are one matrix product with their pixel weights (half the time, 4096 cameras of 19
    points); each camera's normalisation of its visible world points is a similarity of those
    coordinates, under which the moments transform by a congruence (`_renormalised`). Its
    rounding is ~eps s^2 |c|^2: the distance of the visible points' centroid from the origin in
    units of their spread, squared (~3 for the box corner). A camera for which that exceeds
    `_FAR` (a target far from the world's origin, a small part of a large one) gets the moments
    of its own normalised points, as world points given per camera and float32 always do. No
    frame is computed from the points: hidden values cannot change a bit of any camera's result.
    """
    dtype = pixels.dtype
    finite_world = jnp.all(jnp.isfinite(world), -1)
    visible = mask & finite_world & jnp.all(jnp.isfinite(pixels), -1)
    w = visible.astype(dtype)
    # hidden points are replaced before any arithmetic: neither their values nor NaN in them can
    # reach the result or its derivative
    pixels = jnp.where(visible[..., None], pixels, 0.0)
    s2, c2 = _frame(pixels, w)
    u, v = (s2[:, None] * (pixels[..., k] - c2[:, k, None]) for k in range(2))
    weights = jnp.stack([w, w * u, w * v, w * (u * u + v * v)])  # (4, C, N)
    # (in float32 the congruence's rounding, ~3 eps on the box corner, made P ~4x as far from the
    # SVD's as the cameras' own moments do: there, as for world points per camera, those)
    if world.ndim == 3 or dtype != jnp.float64:
        S, s3, c3 = _own_moments(world, visible, weights)
    else:
        S, s3, c3 = _shared_moments(world, finite_world, visible, weights)
    return S, visible, _frobenius(S), s3, c3, s2, c2


def _shared_moments(world, finite_world, visible, weights):
    """`_moments` of a target `world (N, 3)` shared by the cameras: one matrix product in its own
    coordinates, then each camera's normalisation by `_renormalised`; a camera too far from the
    origin for that (`_FAR`), or that sees a point whose products overflow, by `_own_moments`."""
    products = _products(jnp.where(finite_world[:, None], world, 0.0))
    fits = jnp.all(jnp.isfinite(products), -1)  # (a point beyond sqrt of the largest float)
    products = jnp.where(fits[:, None], products, 0.0)
    S, s, c = _renormalised(jnp.einsum("np,mcn->mpc", products, weights))
    # (written so that NaN counts as far)
    far = ~(s * s * jnp.sum(c * c, -1) <= _FAR) | jnp.any(visible & ~fits, -1)

    def own(shared):  # only where there is such a camera
        (S, s, c), (S_own, s_own, c_own) = shared, _own_moments(world, visible, weights)
        return jnp.where(far, S_own, S), jnp.where(far, s_own, s), jnp.where(far[:, None], c_own, c)

    return jax.lax.cond(jnp.any(far), own, lambda shared: shared, (S, s, c))


def _own_moments(world, visible, weights):
    """The moments `(4, 10, C)` of each camera's own normalised visible world points, and the
    normalisation `s (C,)`, `c (C, 3)` (`_frame`), from the pixel weights `(4, C, N)`."""
    world = jnp.where(visible[..., None], world, 0.0)  # (C, N, 3)
    s, c = _frame(world, visible.astype(world.dtype))
    X = jnp.where(visible[..., None], s[:, None, None] * (world - c[:, None, :]), 0.0)
    return jnp.einsum("cnp,mcn->mpc", _products(X), weights), s, c


# The largest s^2 |c|^2 of a camera's normalisation of the shared target's coordinates whose
# moments come from the target's (`_moments`): P then within ~5e-14 (relative) of the SVD's; a
# camera that sees a tenth of the target's extent (s^2 |c|^2 ~ 200) had 3e-12, a hundredth
# (~15000) 5e-10.
_FAR = 16.0


def _products(X):
    """The ten distinct products `(..., N, 10)` of the homogeneous points `X (..., N, 3)`."""
    X = [X[..., 0], X[..., 1], X[..., 2], jnp.ones_like(X[..., 0])]
    return jnp.stack([X[i] * X[j] for i, j in _PAIRS], -1)


def _renormalised(S):
    """The moments `S (4, 10, C)` of the world points `x` to those of each camera's normalised
    world points `s (x - c)`, with `s (C,)` and `c (C, 3)` the camera's normalisation (`_frame`
    over its visible points), which the moments give.

    Each block `M = [[A, b], [b^T, d]]` goes to `T M T^T` with `T = [[s I, -s c], [0, 1]]`:
    `[[s^2 (A - b c^T - c b^T + d c c^T), s (b - d c)], [., d]]`. The first block's `d` is the
    count of visible points, its `b` their sum, its trace their sum of squares.
    """
    at = lambda i, j: S[:, _ENTRY[i, j]]  # noqa: E731 (of the four blocks at once: (4, C))
    n = jnp.maximum(at(3, 3)[0], 1.0)
    c = [at(k, 3)[0] / n for k in range(3)]
    ms = sum(at(k, k)[0] / n - c[k] * c[k] for k in range(3))
    s = jnp.sqrt(3.0 / jnp.where(ms > 0, ms, 1.0))
    d = at(3, 3)
    b = [at(k, 3) - d * c[k] for k in range(3)]  # b - d c
    # entry by entry, each of the four blocks at once: 10 operations rather than 40 (XLA made each
    # its own kernel; 0.95 of the time of the DLT + decomposition)
    S = jnp.stack([
        (d if j == 3 else s * b[j]) if i == 3  # the last row
        else s * s * (at(i, j) - b[i] * c[j] - c[i] * at(j, 3))  # A - (b - d c) c^T - c b^T
        for i, j in _PAIRS
    ], 1)  # fmt: skip
    return S, s, jnp.stack(c, -1)


def _blocks(S):
    """The four symmetric blocks S0, Su, Sv, Sq `(4, 4, *batch)` from the moments
    `S (4, 10, *batch)`."""
    return [jnp.stack([jnp.stack([S[m, _ENTRY[i, j]] for j in range(4)]) for i in range(4)])
            for m in range(4)]  # fmt: skip


def _normal_map():
    """`L^T L = [[S0, 0, -Su], [0, S0, -Sv], [-Su, -Sv, Sq]]` as a linear map `(12, 12, 4, 10)` of
    the moments: every entry is +-1 times one of them, so that a product with it is exact."""
    # (moment, first row, first column, sign) of each block
    blocks = [(0, 0, 0, 1), (0, 4, 4, 1), (1, 0, 8, -1), (1, 8, 0, -1), (2, 4, 8, -1),
              (2, 8, 4, -1), (3, 8, 8, 1)]  # fmt: skip
    M = np.zeros((12, 12, 4, 10))
    for m, row, col, sign in blocks:
        for (i, j), k in _ENTRY.items():
            M[row + i, col + j, m, k] = sign
    return M


_NORMAL = _normal_map()


def _normal_matrix(S):
    """The 12 x 12 `L^T L` from its moments `S (4, 10)`: one product with a constant, and so are
    its derivatives. (Built from the blocks' entries, every slice and stack of them was an
    operation of its own, forward and transposed: notebook 04's `jax.grad` of `jax.jacfwd` of
    the DLT compiled in 33.1 s, now 23.1 s.)"""
    return jnp.tensordot(
        jnp.asarray(_NORMAL, S.dtype), S, axes=2, precision=jax.lax.Precision.HIGHEST
    )


@jax.custom_jvp
def _eigen(S):
    """The unit eigenvector `(12, *batch)` of `G = L^T L` for its smallest eigenvalue, and an
    estimate of `s_11`, L's second smallest singular value (the square root of G's second smallest
    eigenvalue), from the moments `S (4, 10, *batch)`: the cameras are the last axes, so that
    every entry below is one contiguous array over them.

    Inverse iteration, each step one solve with G through its block structure: with `K_u = S0^-1
    Su`, `K_v = S0^-1 Sv` and the Schur complement `R = Sq - Su K_u - Sv K_v`, two 4 x 4 Cholesky
    factorisations solve any `G x = b`. The first step starts from `P3 = (0, 0, 0, 1)`: the last
    entry of the normalised camera's depth row is the depth of the points' centroid, which is
    positive, so the start is never orthogonal to the answer. Noise-free points need that one
    step; each further step multiplies the error by the ratio of the two smallest eigenvalues
    (<= 3e-5 with 0.5 pixel of noise on the benchmark's rig, 0.03 at 10 pixels). A camera stops
    after `_MIN_STEPS` (3) once its next change would be below rounding. One that has not goes on
    with v and z as a block turned by Rayleigh-Ritz after each solve, which converges at the
    ratio of the smallest eigenvalue to the third (for the minimal six points at 10 pixels the
    two smallest come within a ratio of 0.66, where v alone was still 35 % off after 8 steps),
    until its change is below rounding or `_MAX_STEPS` (16); nearly degenerate points go on with
    v alone, for at most `_PLAIN_STEPS` (8). The loop runs while any camera goes on, the others
    keeping their vectors, so that each camera's answer is the same in any batch: its vector to
    rounding. (Its `s_11`, where the block went on, to the estimate's accuracy: the block stops
    at the step where v stops changing in its last bits, which the rounding of the compiled
    program can move by one, and its Ritz value moves ~1e-3 a step where s_11 and s_10 are
    close.)

    `s_11` comes from a second vector z, iterated in the same solves as v for its first
    `_MIN_STEPS`, then alone up to `_Z_STEPS` (5: a fixed number, so that the estimate does not
    depend on when v stops), kept orthogonal to v, and a Rayleigh-Ritz step on its last two
    iterates, whose products with G the steps themselves give: from above, exact where it matters
    (for nearly degenerate points the next eigenvalue is far below the others and the steps
    converge at once); on 1000 random cameras of the box corner's 19 points within 2.6 % (median
    0.1 %) from 0 to 10 pixels of noise, within 2e-7 for six of them (the test asks 5 %). Where
    the block went on, the larger Ritz value of its last step is also from above (interlacing),
    and the smaller of the two is kept.
    """
    S0, Su, Sv, Sq = _blocks(S)
    trace = sum(2 * S0[i, i] + Sq[i, i] for i in range(4))  # of G
    floor = jnp.finfo(S.dtype).eps * trace / 12
    # A 4 x 4 block's rows are vectors of several right-hand sides at once: fewer, wider
    # operations than entry by entry.
    L0 = _small.cholesky(S0, floor)
    # (into memory, and sliced where used: else XLA recomputed each half of K from the solve's
    # inputs for the loop below, which takes them as operands)
    K = _small.materialised(jnp.stack(_small.cho_solve(L0, list(jnp.concatenate([Su, Sv], 1)))))
    R = Sq - _times(Su, K[:, :4]) - _times(Sv, K[:, 4:])
    LR = _small.cholesky(R, floor)

    def solve(X):
        """`G^-1 X` for `X (12, m, *batch)`."""
        m = X.shape[1]
        Y = _small.materialised(
            jnp.stack(_small.cho_solve(L0, list(jnp.concatenate([X[:4], X[4:8]], 1))))
        )
        y1, y2 = Y[:, :m], Y[:, m:]
        x3 = _small.materialised(
            jnp.stack(_small.cho_solve(LR, list(X[8:] + _times(Su, y1) + _times(Sv, y2))))
        )
        return jnp.concatenate([y1 + _times(K[:, :4], x3), y2 + _times(K[:, 4:], x3), x3])

    def along(u, x):
        """The components of `x` along `u`, per camera."""
        return _small.leading_sum(u * x)

    def next_v(v, Y_v, squared=None):
        """The next iterate of v from `Y_v = G^-1 v` (`squared`, its squared length, if known),
        and G times it (`v / length`)."""
        length = jnp.sqrt(along(Y_v, Y_v) if squared is None else squared)
        return Y_v / length, v / length

    def next_z(z, Y_z, v, G_v, first=None):
        """The next iterate of z from `Y_z = G^-1 z`, off v (`first`, its component along v, if
        known), and G times it.

        ("twice is enough": where v dominates G^-1 z, one projection leaves rounding of v's size,
        which the second removes; one normalisation after both, as the length between them only
        sets a scale. The second component and the length come from one sum over the entries:
        `|w - c v|^2 = |w|^2 - c^2` for the unit v and `c = v . w`, and c is at most of the
        order of the result, so that nothing cancels.)
        """
        first = along(v, Y_z) if first is None else first
        w = Y_z - first * v
        second, squared = _small.leading_sum(jnp.stack([v, w], 1) * w[:, None])
        w = w - second * v
        length = jnp.sqrt(squared - second * second)
        return w / length, (z - (first + second) * G_v) / length

    def change(new, old):
        # (G is positive definite: a step never flips v's sign) (a maximum over 12 arrays, not a
        # reduction, which XLA hands to XNNPACK at ~20x the cost)
        return functools.reduce(jnp.maximum, list(jnp.abs(new - old)))

    start = jnp.asarray([[float(i == 11), x] for i, x in enumerate(_START)], S.dtype)  # (12, 2)
    start = jnp.broadcast_to(start.reshape((12, 2) + (1,) * (S.ndim - 2)), (12, 2) + S.shape[2:])
    one = jnp.ones(S.shape[2:], S.dtype)
    # v and z side by side, then z alone; the iterates of z and G times them (unrolled: no
    # copies of the carry between steps)
    v, z, before, last, zs = start[:, 0], start[:, 1], one, one, []
    for _ in range(_MIN_STEPS):
        Y = solve(jnp.stack([v, z], 1))
        # |Y_v|^2 and Y_v . Y_z in one sum
        squared, product = _small.leading_sum(Y[:, :1] * Y)
        new, G_v = next_v(v, Y[:, 0], squared)
        before, last = last, change(new, v)
        v = new
        zs.append((z, *next_z(z, Y[:, 1], v, G_v, first=product / jnp.sqrt(squared))))
        z = zs[-1][1]
    for _ in range(_Z_STEPS - _MIN_STEPS):
        zs.append((z, *next_z(z, solve(z[:, None])[:, 0], v, G_v)))
        z = zs[-1][1]
    (previous, z, G_z), (_, _, G_previous) = zs[-1], zs[-2]

    # The error shrinks by a constant factor per step, so the next change of v is about
    # change^2 / previous change: a camera stops once that is below rounding, and keeps its
    # vector from then on, so that its answer does not depend on the other cameras in the batch.
    def converged(last, before):
        return last * last <= 8 * jnp.finfo(S.dtype).eps * before

    def ritz(v, G_v, z, G_z):
        """Rayleigh-Ritz of G on the span of the orthonormal v and z: the vector of the smaller
        Ritz value (turned towards v) and that of the larger, G times each, and the larger value.

        The smaller's eigenvector of [[a, b], [b, c]] = (v, z)^T G (v, z) is (h + r, -b) or
        (-b, r - h), h = (c - a) / 2, r = sqrt(h^2 + b^2): whichever does not cancel."""
        a, b, c = along(v, G_v), along(v, G_z), along(z, G_z)
        half = 0.5 * (c - a)
        root = jnp.sqrt(half * half + b * b)
        x = jnp.where(half >= 0, root + half, -b)
        y = jnp.where(half >= 0, -b, root - half)
        x, y = jnp.where(x < 0, -x, x), jnp.where(x < 0, -y, y)
        length = jnp.sqrt(x * x + y * y)
        some = length > 0  # (G is a multiple of the identity on the span: keep v and z)
        cos = jnp.where(some, x / jnp.where(some, length, 1.0), 1.0)
        sin = jnp.where(some, y / jnp.where(some, length, 1.0), 0.0)
        turn = lambda p, q: (cos * p + sin * q, cos * q - sin * p)  # noqa: E731
        (v, z), (G_v, G_z) = turn(v, z), turn(G_v, G_z)
        return v, G_v, z, G_z, 0.5 * (a + c) + root

    # A camera whose v has not converged by then goes on with v and z as a block, the pair
    # turned by Rayleigh-Ritz after each solve: v then converges at the rate s_12^2 / s_10^2, not
    # s_12^2 / s_11^2, which comes close to 1 where the two smallest singular values do (six
    # points at 10 px: up to 0.66, where 8 steps of v alone left P 35 % off the SVD's). The
    # larger Ritz value is then its s_11^2, from above. Nearly degenerate points (z's Rayleigh
    # quotient below 1e6 eps of the trace: in float64 condition numbers beyond ~7e4, points on a
    # plane; in float32 every camera) go on with v alone, as before, for at most `_PLAIN_STEPS`:
    # there the Ritz values are rounding, and `Status.DEGENERATE` takes their estimate as it was.
    def step(state):
        k, v, G_v, z, G_z, ritz_11, last, done, settled, plain, answer = state
        Y = solve(jnp.stack([v, z], 1))
        squared, product = _small.leading_sum(Y[:, :1] * Y)
        w, G_w = next_v(v, Y[:, 0], squared)  # v alone
        y, G_y = next_z(z, Y[:, 1], w, G_w, first=product / jnp.sqrt(squared))
        u, G_u, y, G_y, value = ritz(w, G_w, y, G_y)  # the block
        w, G_w = (jnp.where(plain, p, q) for p, q in ((w, u), (G_w, G_u)))
        new = change(w, v)
        keep = lambda old, new: jnp.where(done, old, new)  # noqa: E731
        # The first block step turns v by Rayleigh-Ritz, a change of another kind than the
        # steps after it: the test of the rate waits for two changes of the block's own.
        first = ~plain & (k == _MIN_STEPS)
        settled_now = settled | (~done & ~first & converged(new, last))
        done_now = settled_now | done | (plain & (k + 1 >= _PLAIN_STEPS)) | (k + 1 >= _MAX_STEPS)
        new_state = (w, G_w, y, G_y, value, jnp.where(first, 0.0, new))
        old_state = (v, G_v, z, G_z, ritz_11, last)
        # A camera that stops at a limit without settling answers with LAPACK's eigenvector
        # (`_exact`); the loop keeps its own v for the estimate of s_11 below.
        answer = keep(answer, w)
        unsettled = done_now & ~done & ~settled_now
        at_limit = (k + 1 == _PLAIN_STEPS) | (k + 1 == _MAX_STEPS)
        answer = jax.lax.cond(at_limit, lambda a: _exact(S, a, unsettled), lambda a: a, answer)
        return k + 1, *map(keep, old_state, new_state), done_now, settled_now, plain, answer

    def more(state):
        k, *_, done, _, _, _ = state
        return (k < _MAX_STEPS) & ~jnp.all(done)

    early = converged(last, before)
    plain = along(z, G_z) <= 1e6 * jnp.finfo(S.dtype).eps * trace  # (float32: every camera)
    start = (_MIN_STEPS, v, G_v, z, G_z, jnp.full_like(one, jnp.inf), last, early, early, plain, v)
    _, v, G_v, _, _, ritz_11, _, _, settled, _, answer = jax.lax.while_loop(more, step, start)

    # Rayleigh-Ritz on the last two iterates of z: the smaller eigenvalue of the 2 x 2 matrix
    # [[a, b], [b, c]] = (z, y)^T G (z, y), from above, with z the last iterate and y the one
    # before, both off v (which may have moved on since) and orthonormal, in the form that does
    # not cancel when z is already close (a << c). The products with G are those the steps
    # made known (`next_v`, `next_z`), not computed. Where the two iterates agree to sqrt(eps),
    # z's Rayleigh quotient a is already exact to rounding, and y would be mostly rounding.
    def off_v(x, G_x):
        c = along(v, x)
        return x - c * v, G_x - c * G_v

    z, G_z = off_v(z, G_z)
    length = jnp.sqrt(along(z, z))
    z, G_z = z / length, G_z / length
    y, G_y = off_v(previous, G_previous)
    m = along(z, y)
    y, G_y = y - m * z, G_y - m * G_z
    length = jnp.sqrt(along(y, y))
    distinct = length > jnp.sqrt(jnp.finfo(S.dtype).eps)
    scale = jnp.where(distinct, length, 1.0)
    y, G_y = y / scale, G_y / scale
    a, b, c = (along(p, q) for p, q in ((z, G_z), (z, G_y), (y, G_y)))
    half = 0.5 * (c - a)
    root = jnp.sqrt(half * half + b * b)
    usable = distinct & (root + half > 0)
    lowering = jnp.where(usable, b * b / jnp.where(usable, root + half, 1.0), 0.0)
    estimate = a - lowering
    # where the block went on and converged, both values are from above: the smaller is closer
    estimate = jnp.where(early | plain | ~settled, estimate, jnp.minimum(estimate, ritz_11))
    return answer, jnp.sqrt(jnp.maximum(estimate, 0.0))


def _exact(S, v, where):
    """`v (12, *batch)` with LAPACK's eigenvector of G for its smallest eigenvalue `where`: for a
    camera whose inverse iteration stopped at a limit without settling, i.e. nearly coplanar
    points with noise, whose L has three or four small singular values close together (v alone
    and the block of two then converge at a rate near 1: flatness 1e-4 and 0.1 px left P up to
    25 % off the SVD's). It runs only in a loop step at such a limit (never on the benchmark's
    rig); not on several CPU devices, where a batch of LAPACK calls can hang
    (`_sharding.batched_lapack_may_hang`)."""
    if _sharding.batched_lapack_may_hang():
        return v
    per_camera = jnp.moveaxis(S, (0, 1), (-2, -1))
    G = jnp.vectorize(_normal_matrix, signature="(4,10)->(12,12)")(per_camera)
    w = jnp.moveaxis(jnp.linalg.eigh(G)[1][..., 0], -1, 0)
    w = w * jnp.where(_small.leading_sum(w * v) < 0, -1.0, 1.0)
    return jnp.where(where, w, v)


@jax.custom_jvp
def _eigen_lapack(S):
    """`_eigen` by LAPACK: the eigenvectors of each camera's 12 x 12 `G` (`jnp.linalg.eigh`), its
    smallest and `s_11` exactly, for the compact form of small programs (`compact`), where
    compiling the written-out iteration would take seconds and running it microseconds."""
    per_camera = jnp.moveaxis(S, (0, 1), (-2, -1))
    G = jnp.vectorize(_normal_matrix, signature="(4,10)->(12,12)")(per_camera)
    values, vectors = jnp.linalg.eigh(G)
    return jnp.moveaxis(vectors[..., 0], -1, 0), jnp.sqrt(jnp.maximum(values[..., 1], 0.0))


def compact(n_cameras: int, n_points: int) -> bool:
    """Whether a program of `n_cameras` of `n_points` takes the compact form: LAPACK's
    eigenvectors (`_eigen_lapack`) and medians by sorting, a fraction of the written-out form's
    compile time (`_buckets.COMPACT`); not where a batch of LAPACK calls can hang."""
    return n_cameras * n_points <= _buckets.COMPACT and not _sharding.batched_lapack_may_hang()


def _times(A, x):
    """`A x` for a 4 x 4 block `A (4, 4, *batch)` and `x (4, *batch)` or `x (4, m, *batch)`."""
    if x.ndim == A.ndim - 1:
        return sum(A[:, k] * x[k] for k in range(4))
    return sum(A[:, k, None] * x[k] for k in range(4))


def _frobenius(S):
    """`||L||_F = sqrt(trace(L^T L))` from the moments."""
    return jnp.sqrt(sum(2 * S[0, _ENTRY[i, i]] + S[3, _ENTRY[i, i]] for i in range(4)))


# Inverse iteration stops after _MIN_STEPS once v has converged for every camera, else goes on
# (as a block with the second vector) up to _MAX_STEPS; the second vector, for s_11, takes
# _Z_STEPS first (docs of `_eigen`).
_MIN_STEPS, _MAX_STEPS, _Z_STEPS = 3, 16, 5
_PLAIN_STEPS = 8  # nearly degenerate points: v alone, at most this many steps
# A start for the other eigenvector with no structure that the normal matrix could share.
_START = (0.93, -0.27, 0.51, 0.12, -0.66, 0.38, 0.84, -0.45, 0.19, 0.71, -0.58, 0.33)


def _eigen_jvp(eigen, primals, tangents):
    # The singular value is a diagnostic and carries no derivative.
    (S,), (dS,) = primals, tangents
    v, s = eigen(S)

    def tangent(S, dS, v, s):
        # A camera whose vector is not unique (it sees nothing, too few points or a plane: no
        # gap above the smallest eigenvalue) is failed and NaN, and gets a zero derivative: its
        # system replaced before the solve, whose transpose would otherwise carry 0 * inf = NaN
        # into every camera's shared world points under `jax.grad` (a JAX user's trial: one
        # failed camera made the whole world gradient NaN; forward mode was right).
        G = _normal_matrix(S)
        scale = jnp.sqrt(jnp.abs(jnp.trace(G)))
        count = S[0, _ENTRY[3, 3]]  # (the first block's last entry: the points it saw)
        unique = (count >= _validate.MIN_POINTS) & jnp.all(jnp.isfinite(v))
        unique &= s > 64 * jnp.finfo(G.dtype).eps * scale
        G = jnp.where(unique, G, jnp.eye(12, dtype=G.dtype))
        v = jnp.where(unique, v, jnp.eye(12, dtype=G.dtype)[0])
        dG_v = jnp.where(unique, _normal_matrix(dS) @ v, 0.0)
        return _small.eigenvector_tangent(G, v, dG_v)

    first = functools.partial(jnp.moveaxis, source=(0, 1), destination=(-2, -1))
    dv = jnp.vectorize(tangent, signature="(4,10),(4,10),(12),()->(12)")(
        first(S), first(dS), jnp.moveaxis(v, 0, -1), s
    )
    return (v, s), (jnp.moveaxis(dv, -1, 0), jnp.zeros_like(s))


_eigen.defjvp(functools.partial(_eigen_jvp, _eigen))
_eigen_lapack.defjvp(functools.partial(_eigen_jvp, _eigen_lapack))


def poor_fit(rms, pixels, visible, max_relative_rms, sort=False):
    """True where a camera's reprojection RMS over its visible points exceeds `max_relative_rms`
    times the pixels' spread: the median distance of the visible pixels from their centre, the
    mean of the half of them nearest their mean.

    A check of an answer, not part of it: no derivative flows through it. Both sides are
    invariant to similarities of the world and pixel frames, like the DLT itself (the per-axis
    medians that were once the centre were not: a rotation of the pixel frame changed the
    spread by 16 % on a camera of tests/test_properties.py). The medians keep one wild pixel
    from inflating the spread that it is measured against: it is not among the nearer half, and
    its own distance is one of N. (With the plain mean as the centre, a pixel 1000 spreads off
    moved it by 50 and 2 cameras of 1000 came out OK. From 2026-12-04 to 12-07 the centre was
    the geometric median, by four Weiszfeld steps: their square roots and divisions took 0.25
    us a camera, a fifth of the DLT of 4096 cameras of 19 points.)

    The sums, as the medians, go point by point over the batch where the points are few
    (`_masked_median`'s network): XLA's CPU backend adds up a short last axis slowly.
    """
    rms, pixels = jax.lax.stop_gradient((rms, pixels))
    n = pixels.shape[-2]
    if _by_network(n, sort):
        total = lambda x: sum(x[..., i] for i in range(n))  # noqa: E731
    else:
        total = functools.partial(jnp.sum, axis=-1)
    median = functools.partial(_masked_median, sort=sort)
    u, v = jnp.where(visible, pixels[..., 0], 0.0), jnp.where(visible, pixels[..., 1], 0.0)

    def squared_distances(used):
        """From the mean of the `used` pixels."""
        count = jnp.maximum(total(used.astype(pixels.dtype)), 1.0)
        cu, cv = total(jnp.where(used, u, 0.0)) / count, total(jnp.where(used, v, 0.0)) / count
        return (u - cu[..., None]) ** 2 + (v - cv[..., None]) ** 2

    d2 = squared_distances(visible)
    d2 = squared_distances(visible & (d2 <= median(d2, visible)[..., None]))
    spread = median(jnp.sqrt(d2), visible)
    return ~(rms <= max_relative_rms * spread)


def _masked_median(x, mask, sort=False):
    """The median of `x (..., N)` over its entries where `mask` (NaN if none), as `np.median`.

    Up to `_NETWORK_POINTS` points (unless `sort`: a small program, compiled quickly) by a sorting
    network (Batcher's odd-even merge sort, cut down to the comparators that the middle ranks
    depend on: 83 for 19 points), elementwise minima and maxima over the batch; beyond, by
    sorting (`_ordered`). The hidden entries go below and above
    the visible ones, half each (-inf, then +inf), so that the visible median always sits at the
    same two ranks of all N. On CPU, 4096 cameras of 19 points, the three medians of `poor_fit`:
    0.09 against 0.25 µs per camera by counting (N^2 comparisons) and 0.5 by sorting.
    """
    n = x.shape[-1]
    count = jnp.sum(mask, axis=-1)
    if not _by_network(n, sort):
        ordered = _ordered(jnp.where(mask, x, jnp.inf))  # hidden entries rank last

        def pick(k):
            return jnp.take_along_axis(ordered, jnp.clip(k, 0, n - 1)[..., None], -1)[..., 0]

        middle = 0.5 * (pick((count - 1) // 2) + pick(count // 2))
        return jnp.where(count > 0, middle, jnp.nan)

    low = (n - count) // 2  # hidden entries that go below
    wires, below = [], jnp.zeros_like(count)
    for i in range(n):
        hidden = jnp.where(below < low, -jnp.inf, jnp.inf).astype(x.dtype)
        wires.append(jnp.where(mask[..., i], x[..., i], hidden))
        below = below + ~mask[..., i]
    for i, j in _median_network(n):
        wires[i], wires[j] = jnp.minimum(wires[i], wires[j]), jnp.maximum(wires[i], wires[j])
    first, second, single = _middle_ranks(n)
    odd = count % 2 == 1
    first, second = (jnp.where(odd, wires[single], wires[k]) for k in (first, second))
    return jnp.where(count > 0, 0.5 * (first + second), jnp.nan)


_NETWORK_POINTS = 32


def _by_network(n: int, sort: bool) -> bool:
    """Whether `n` points go one by one, elementwise over the batch (a sorting network for a
    median): up to `_NETWORK_POINTS`, unless `sort` (a small program, compiled quickly)."""
    return not sort and n <= _NETWORK_POINTS


def _middle_ranks(n):
    """The ranks among all `n` entries (the hidden ones placed as in `_masked_median`) of the
    two middle visible entries for an even count, and of the middle one for an odd count."""
    if n % 2:
        return max((n - 3) // 2, 0), (n - 1) // 2, (n - 1) // 2
    return n // 2 - 1, n // 2, n // 2 - 1


@functools.cache
def _median_network(n):
    """The comparators `(i, j)`, `i < j`, of Batcher's odd-even merge sort of `n` entries (its
    iterative form, for any n) that the middle ranks depend on."""
    pairs, p = [], 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    needed, kept = set(_middle_ranks(n)), []
    for i, j in reversed(pairs):
        if i in needed or j in needed:
            kept.append((i, j))
            needed |= {i, j}
    return tuple(reversed(kept))


def _ordered(x):
    """`x (..., N)` sorted along its last axis, as the integers whose order is the floats' (their
    bits, with those of negative numbers flipped but the sign): XLA's CPU backend sorts these
    4-5x faster than the floats themselves (its float comparison orders NaN and -0 as well)."""
    itype = jnp.int32 if x.dtype == jnp.float32 else jnp.int64
    flip = lambda b: jnp.where(b < 0, b ^ jnp.iinfo(itype).max, b)  # noqa: E731 (its own inverse)
    keys = jnp.sort(flip(jax.lax.bitcast_convert_type(x, itype)), axis=-1)
    return jax.lax.bitcast_convert_type(flip(keys), x.dtype)


_dot3 = _small.dot3


def _apply(row, world):
    """`row (4,)` of a projection matrix applied to the points `world (N, 3)`."""
    return _dot3(row, world.T) + row[3]


def _rms(P, world, pixels, visible, depth):
    """The reprojection RMS of `P (3, 4)` over the visible points, at their `depth`."""
    depth = jnp.where(visible, depth, 1.0)
    du = _apply(P[0], world) / depth - pixels[:, 0]
    dv = _apply(P[1], world) / depth - pixels[:, 1]
    err2 = jnp.where(visible, du * du + dv * dv, 0.0)
    return jnp.sqrt(jnp.sum(err2) / jnp.maximum(jnp.sum(visible), 1))


# The least focal length, in units of the pixels' spread, of a DLT camera that is not degenerate
# (`_camera`): 1e-3, a field of view of 179.9 degrees.
_MIN_FOCAL = 1e-3


def _camera(
    world, pixels, mask, visible, v, s_11, norm, s3, c3, s2, c2, rcond, max_relative_rms, compact
):
    """One camera from its eigenvector `v (12,)` and the points `_moments` used (`visible`): P
    (3, 4), status, condition number, mirrored."""
    # hidden points replaced by 0 before any arithmetic, so that neither their values nor NaN/inf
    # in them can reach the result or its derivative
    world = jnp.where(visible[:, None], world, 0.0)
    pixels = jnp.where(visible[:, None], pixels, 0.0)
    all_finite = jnp.all(visible | ~mask)  # (visible = mask & finite)
    # A camera that has no solution (too few points; no unique vector: s_11 NaN or 0) is NaN
    # whatever its vector; that vector is replaced by a harmless one before any arithmetic, so
    # that the camera's zero derivative stays zero. Its vector was inverse iteration's start
    # (0, ..., 0, 1), whose ||m3|| = 0 put 0 * inf into the normalisations' cotangents, and
    # through them into every camera's shared world points under `jax.grad` (a JAX user's trial:
    # one camera that saw nothing made the whole world gradient NaN; forward mode was right).
    solvable = (jnp.sum(visible) >= _validate.MIN_POINTS) & (s_11 > 0)
    v = jnp.where(solvable, v, jnp.eye(3, 4, dtype=v.dtype).ravel() / jnp.sqrt(3.0))
    # De-normalised, P = T2^-1 V T3 with T = [[s I, -s c], [0, 1]], written out.
    V = v.reshape(3, 4)
    V = jnp.concatenate([s3 * V[:, :3], V[:, 3:] - s3 * _dot3(V[:, :3].T, c3)[:, None]], axis=1)
    P = jnp.concatenate([V[:2] / s2 + c2[:, None] * V[2:], V[2:]])

    # ||m3|| = 1 (Faugeras–Toscani), with the sign that puts the visible points in front.
    P = P / jnp.sqrt(_dot3(P[2], P[2]))
    depth = _apply(P[2], world)
    behind = jnp.sum(jnp.where(visible, depth, 0.0)) < 0
    P, depth = jnp.where(behind, -P, P), jnp.where(behind, -depth, depth)

    # (a diagnostic, without a derivative: where s_11 is NaN, a failed camera's, its partial
    # 1 / s_11 carried 0 * NaN into the world points' cotangent under `jax.grad`)
    condition = jax.lax.stop_gradient(norm / s_11)
    n_visible = jnp.sum(visible)
    # A camera whose focal lengths are negligible against its pixels' spread (`1 / s2`) sees
    # them over ~180 degrees: no camera. With all but one point on a plane a one-parameter family
    # of P fits them, and the DLT may take a near-singular member: with noise or lens distortion
    # `s_11` clears its threshold, and half of such cameras came out OK with focal length ~0
    # (0.01-0.3 px of noise; the box corner's floor dots and one more). With ||m3|| = 1,
    # det M = alpha_u alpha_v whatever the principal point.
    det = _small.triple(P[0], P[1], P[2])
    focal_zero = ~(jnp.abs(det) * s2 * s2 > _MIN_FOCAL**2)
    # the checks computed into memory first: else XLA computes them inside `jnp.select`'s
    # reduction, camera by camera (the checks and the decomposition of 4096 cameras: 0.31 against
    # 0.24 µs per camera)
    nonfinite, few, singular, behind, poor, focal_zero = _small.materialised(jnp.stack([
        ~all_finite,
        n_visible < _validate.MIN_POINTS,
        ~(s_11 > rcond * norm),
        jnp.any(visible & (depth <= 0)),
        poor_fit(
            _rms(P, world, pixels, visible, depth), pixels, visible, max_relative_rms, compact
        ),
        focal_zero,
    ]))  # fmt: skip
    # (a wild pixel may also give a focal length ~0: said POINTS_BEHIND or POOR_FIT, as before)
    checks = [nonfinite, few, singular | (focal_zero & ~poor), behind, poor]
    status = jnp.select(
        checks,
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
    mirrored = (det < 0) & (status == Status.OK)
    return P, status, condition, mirrored


# Camera-points (cameras times points per camera) solved side by side on one CPU device: 4096
# cameras of up to 20 points.
CHUNK = 4096 * 20


def _chunk_size(n_cameras: int, n_points: int) -> int | None:
    """Cameras solved side by side in one loop step (`_sharding.cpu_chunk`): on one CPU device,
    at most `CHUNK // n_points` (and at least 64) at a time; else all."""
    return _sharding.cpu_chunk(n_cameras, max(CHUNK // n_points, 64))


# A fit is made again without the points far off it (`near`), `REFITS` times: beyond `GATE` times
# the noise level that the median distance gives (a 2-D Gaussian's median distance is
# `RAYLEIGH_MEDIAN` of its standard deviation), where Gaussian noise puts no point (probability
# exp(-50)). A planar view's homography (`_planar`), and the DLT that seeds a refinement with a
# robust loss (`refit_near`).
GATE = 10.0
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
REFITS = 2


def near(distance, visible):
    """The `visible` points whose `distance` (N,) from a fit is within `GATE` times the noise
    level that the median distance implies."""
    noise = _masked_median(distance, visible, sort=True) / RAYLEIGH_MEDIAN
    return visible & (distance <= GATE * noise)


def refit_near(world, pixels, mask, fit, rcond, max_relative_rms):
    """`fit`, `solve_validated`'s answer, fitted again without the points far off it (`near`),
    `REFITS` times; a camera keeps its fit where fewer than `MIN_POINTS` would remain."""

    def refit(_, fit):
        P = fit[0]
        ones = jnp.ones(world.shape[:-1] + (1,), world.dtype)
        p = jnp.concatenate([world, ones], -1) @ jnp.swapaxes(P, -1, -2)  # (..., N, 3)
        distance = jnp.linalg.norm(p[..., :2] / p[..., 2:] - pixels, axis=-1)
        kept = jnp.vectorize(near, signature="(n),(n)->(n)")(jnp.where(mask, distance, 0.0), mask)
        n = jnp.sum(kept, -1)
        again = (n >= _validate.MIN_POINTS) & (n < jnp.sum(mask, -1))
        new = solve_validated(world, pixels, kept, rcond, max_relative_rms)
        where = lambda a: again.reshape(again.shape + (1,) * (a.ndim - again.ndim))  # noqa: E731
        return jax.tree_util.tree_map(lambda a, b: jnp.where(where(a), a, b), new, fit)

    return jax.lax.fori_loop(0, REFITS, refit, fit)


@_buckets.jit
def solve_validated(world, pixels, mask, rcond, max_relative_rms=DEFAULT_MAX_RELATIVE_RMS):
    """The DLT of every camera for inputs that passed `_validate.correspondences`, by `_solve`.

    On one CPU device, large rigs go through `_solve` in a loop over equal chunks of cameras
    (`_chunk_size`), whose arrays stay in cache. Measured per camera, calibrating with the
    decomposition, against one batch: 65,536 cameras of 19 points 3.5 µs against 12.0-12.2 (16
    chunks of 4096); 4096 cameras of 100 points 13.6 against 20.1 (six chunks of 683). Smaller
    chunks were slower at 19 points (three of 1366 cameras: 4.2 against 3.9 µs) and faster at 100
    (chunks of 316: 9.4 µs). Each camera's answer does not depend on the others in its batch
    (`_eigen`), so chunks change it by rounding at most (~1e-15 of P).
    """
    batch = jnp.broadcast_shapes(world.shape[:-2], pixels.shape[:-2], mask.shape[:-1])
    solve = functools.partial(
        _solve,
        rcond=rcond,
        max_relative_rms=max_relative_rms,
        compact=compact(math.prod(batch), pixels.shape[-2]),
    )
    # every batched input flattened to (cameras, ...), as `_refine._refine_batched` does
    flat = lambda x, tail: jnp.broadcast_to(x, batch + tail).reshape((-1,) + tail)  # noqa: E731
    n = pixels.shape[-2]
    inputs = (flat(pixels, (n, 2)), flat(mask, (n,)))
    if world.ndim == 2:  # one target seen by every camera stays one
        run = functools.partial(solve, world)
    else:
        run, inputs = solve, (flat(world, (n, 3)), *inputs)
    out = _sharding.chunked_map(run, inputs, _chunk_size(math.prod(batch), n))
    return jax.tree_util.tree_map(lambda x: x.reshape(batch + x.shape[1:]), out)


def _solve(world, pixels, mask, rcond, max_relative_rms, compact=False):
    """For `pixels (C, N, 2)`, `mask (C, N)` and `world (N, 3)` or `(C, N, 3)`: the moments of all
    cameras, their eigenvectors with the cameras as the last axis, then per camera the
    de-normalised P and its checks (in the `compact` form for a small program)."""
    # (the scopes name the stages in profiles: benchmarks/profile_dlt.py)
    with jax.named_scope("moments"):
        S, visible, *normalisation = _moments(world, pixels, mask)
    with jax.named_scope("eigen"):
        v, s_11 = (_eigen_lapack if compact else _eigen)(S)
    camera = functools.partial(
        _camera, rcond=rcond, max_relative_rms=max_relative_rms, compact=compact
    )
    with jax.named_scope("cameras"):
        return jnp.vectorize(
            camera, signature="(n,3),(n,2),(n),(n),(12),(),(),(),(3),(),(2)->(3,4),(),(),()"
        )(world, pixels, mask, visible, jnp.moveaxis(v, 0, -1), s_11, *normalisation)


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
    batch = jnp.broadcast_shapes(world.shape[:-2], pixels.shape[:-2], mask.shape[:-1])
    quick = compact(math.prod(batch), pixels.shape[-2])  # a small program, compiled quickly
    return solve_validated(
        world, pixels, mask, rcond, check_relative_rms(max_relative_rms), quick=quick
    )


def dlt(
    world: Float[Array, "*batch N 3"],
    pixels: Float[Array, "*batch N 2"],
    mask: Bool[Array, "*batch N"] | None = None,
    *,
    max_relative_rms: float = DEFAULT_MAX_RELATIVE_RMS,
) -> Float[Array, "*batch 3 4"]:
    """Projection matrices from 3-D/2-D correspondences by the normalised DLT (paper, eqs. 6–11).

    For each camera, the world points and pixels are first normalised (Hartley: centroid to the
    origin, RMS distance sqrt(3) and sqrt(2)), the 2N x 12 system `L a = 0` is solved in the
    least-squares sense (the right singular vector of the smallest singular value, by inverse
    iteration on `L^T L`; equal to an SVD's to ~1e-13), and the result is de-normalised and
    scaled so that `||m3|| = 1` with the sign that puts the visible points in front of the camera.
    All cameras are solved in one jit-compiled, vectorised call.

    **Arguments:**

    - `world`: world points `(..., N, 3)`, N >= 6. Leading axes broadcast against those of
      `pixels`, so one target seen by C cameras is `(N, 3)` against `(C, N, 2)`.
    - `pixels`: observed pixels `(..., N, 2)` as `(x = column, y = row)`.
    - `mask`: visibility `(..., N)`, boolean. Hidden points have no influence at all: their values,
      even NaN, never reach the result or its gradient.
    - `max_relative_rms`: the largest reprojection RMS of an answer, as a fraction of the spread
      of its pixels (median distance from their centre), that counts as a fit; default
      0.05. `inf` turns the check off.

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
