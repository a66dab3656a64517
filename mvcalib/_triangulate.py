"""N-view triangulation: one world point from its pixels in several calibrated views."""

from __future__ import annotations

import functools
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _buckets, _sharding, _small, _validate
from ._camera import Camera, _distort, undistort_points, unit_camera, usable_rig

__all__ = ["Triangulation", "triangulate", "reproject"]


# `triangulate`'s `max_rms` by default: a point that reprojects worse is not ok. Its `ok` was
# geometric only (in front, rays apart), and swapped (row, col) pixels, -1 for unseen views or
# wrong correspondences came out ok at 50-538 px (3-D errors of metres; two users' trials).
MAX_RMS = 10.0


class Triangulation(eqx.Module):
    """The result of `triangulate`, per point.

    - `points`: `(..., N, 3)` in the cameras' (global) frame; NaN where fewer than 2 views.
    - `views`: `(..., N)` int, the number of views used.
    - `rms`: `(..., N)` reprojection RMS over the views used, in pixels (distortion included);
      NaN, like `angle`, for a point seen by fewer than two views.
    - `angle`: `(..., N)` the widest angle between two of the point's rays, in degrees: small
      angles mean depth poorly determined.
    - `in_front`: `(..., N)` bool: in front of every camera that sees it (a fisheye's: on the
      side its ray points to); False for fewer than 2 views. Every point behind its cameras
      means a mirrored world (the cameras' `calibrate` says `mirrored`: a world frame of the
      other handedness).
    - `ok`: `(..., N)` bool: at least 2 views, `in_front`, an angle of at least `min_angle`,
      and an `rms` of at most `max_rms` (10 px by default: wrong matches, swapped (row,
      column) pixels or the wrong rig reproject tens to hundreds of pixels off).
    """

    points: Float[Array, "*batch N 3"]
    views: Int[Array, "*batch N"]
    rms: Float[Array, "*batch N"]
    angle: Float[Array, "*batch N"]
    in_front: Bool[Array, "*batch N"]
    ok: Bool[Array, "*batch N"]


# The distinct entries (i, j), i <= j, of a symmetric 4 x 4 matrix.
_PAIRS = [(i, j) for i in range(4) for j in range(i, 4)]
# `_SYM @ vec(O)` is the distinct entries of `O + O^T` for a 4 x 4 `O`: one small product, where
# a stack of the 10 entries, each two slices, grows tenfold in nested derivatives (`jax.grad` of
# `jax.jacfwd` of a point: 5k of its program's 15k lines).
_SYM = np.zeros((len(_PAIRS), 16))
_SYM[np.arange(len(_PAIRS)), [4 * i + j for i, j in _PAIRS]] += 1.0
_SYM[np.arange(len(_PAIRS)), [4 * j + i for i, j in _PAIRS]] += 1.0


def _normal_coefficients(P):
    """`B (4, 10, C)`: the distinct entries of the 4 x 4 normal matrix of a point's rows are
    `sum_q B[q] @ f[q]`, with `f (4, C)` its per-view features `m (x^2 + y^2), m x, m y, m`
    (mask m, normalised pixel x, y).

    A view adds `(x P3 - P1)(x P3 - P1)^T + (y P3 - P2)(y P3 - P2)^T` to the normal matrix:
    expanded, four camera-only matrices weighted by the four features. So the normal matrices of
    all points are one matrix product, where building each point's 2C x 4 rows moved ~20 kB per
    point through memory.
    """
    P1, P2, P3 = P[:, 0], P[:, 1], P[:, 2]  # (C, 4)
    squares = (_sym(P1, P1) + _sym(P2, P2)) / 2
    return jnp.stack([_sym(P3, P3) / 2, -_sym(P3, P1), -_sym(P3, P2), squares])


def _sym(a, b):
    """The distinct entries of `a b^T + b a^T`, `(10, C)`, for rows `a, b (C, 4)`: one product
    with a constant."""
    return jnp.asarray(_SYM, a.dtype) @ (a[:, :, None] * b[:, None, :]).reshape(-1, 16).T


def _ray_coefficients(P):
    """`B (7, 10, C)` as `_normal_coefficients`, for the features `m, m dx^2, m dy^2, m dz^2,
    m dx dy, m dx dz, m dy dz` of unit rays `d` (a fisheye's, up to 180 degrees off axis): a view
    adds `P^T (I - d d^T) P`, the squared distance of the point from its ray, whose three rows
    (`d x P X`) stay of full rank where the pinhole's two, `x P3 - P1` and `y P3 - P2` with
    `(x, y) = (dx, dy) / dz`, lose one at 90 degrees."""
    P1, P2, P3 = P[:, 0], P[:, 1], P[:, 2]
    squares = [_sym(a, a) / 2 for a in (P1, P2, P3)]
    cross = [-_sym(P1, P2), -_sym(P1, P3), -_sym(P2, P3)]
    return jnp.stack([sum(squares)] + [-q for q in squares] + cross)


def _congruence(G, s, d):
    """`T^T G T` for `T = [[s I, d], [0, 1]]`, entry by entry (`G` as rows of entries): the normal
    matrix of the point `X = s X' + d` in terms of `X'`."""
    H = [[s * G[a][b] for b in range(3)] + [G[a][3] + sum(G[a][b] * d[b] for b in range(3))]
         for a in range(4)]  # fmt: skip
    return [[s * H[a][c] for c in range(4)] for a in range(3)] + [
        [H[3][c] + sum(d[b] * H[b][c] for b in range(3)) for c in range(4)]
    ]


_STEPS = 6
# Up to this many views, the widest ray angle compares every pair written out (120 at 16 views).
_PAIRED_VIEWS = 16


@jax.custom_jvp
def _null_vector(G):
    """The unit eigenvector `(4, *batch)` of the symmetric 4 x 4 `G (4, 4, *batch)` for its
    smallest eigenvalue, by inverse iteration written out entry by entry: batched over points
    (the trailing axes) it is a few fused elementwise loops, where `eigh` runs LAPACK on one tiny
    matrix after another.

    Each step multiplies by the adjugate `adj(G) = det(G) G^-1` (`_small.adjugate`: products and
    sums of G's entries, no division), so that XLA computes the matrix in one loop and each step
    in one more. A Cholesky factor's solves, whose divisions and square roots XLA keeps in
    kernels of their own, made ~80 kernels per chunk of points: 100k points of 8 views took
    0.46 µs/point, now 0.41 (in-process A/B), and noise-free points come out closer to the
    truth (RMS 6.7e-14 against 2.7e-13 mm; float32 5.9e-5 against 1.2e-4). `G` gets eps times its
    trace on the diagonal, so that the adjugate of a matrix of rank below 3 (a point whose
    views' rays all coincide) is not zero.

    The start is the homogeneous coordinate `(0, 0, 0, 1)`; its first step is the inhomogeneous
    least-squares point. In the normalised frame the point is within a few spreads of the
    origin, so the start is far from orthogonal to the answer, and each step multiplies the
    error by the ratio of the two smallest eigenvalues (noise over the rays' angle squared:
    1e-4 for 0.3 px and rays 5 degrees apart on a 1000 px focal length).
    """
    floor = jnp.finfo(G.dtype).eps * (G[0, 0] + G[1, 1] + G[2, 2] + G[3, 3])
    rows = [[G[i, j] + floor if i == j else G[i, j] for j in range(4)] for i in range(4)]
    A = _small.materialised(jnp.stack([jnp.stack(row) for row in _small.adjugate(rows)]))
    v = A[:, 3]  # the first step, from (0, 0, 0, 1)
    for step in range(_STEPS):
        if step:
            v = _small.materialised(sum(A[:, j] * v[j] for j in range(4)))
        v = v * jax.lax.rsqrt(sum(v[i] * v[i] for i in range(4)))
    return v


@_null_vector.defjvp
def _null_vector_jvp(primals, tangents):
    (G,), (dG,) = primals, tangents
    v = _null_vector(G)
    batch = lambda a: jnp.moveaxis(a.reshape(a.shape[: a.ndim - v.ndim + 1] + (-1,)), -1, 0)  # noqa: E731
    dv = jax.vmap(lambda G, v, dG: _small.eigenvector_tangent(G, v, dG @ v))(
        batch(G), batch(v), batch(dG)
    )
    return v, jnp.moveaxis(dv, 0, -1).reshape(v.shape)


def _polish(cameras: Camera, X0, pixels, m, max_steps):
    """The points `X0 (N, 3)` moved to minimise their reprojection error in the views `m (C, N)`
    (pixels `(C, N, 2)`): Levenberg–Marquardt on every point at once, as `(N,)` arrays, each
    point's 3 x 3 step solved entry by entry (`_small.cholesky`), its damping its own; the loop
    ends when every point's step is below `_POLISH_TOL` of it, or after `max_steps`.
    Derivatives are implicit (`_polished_jvp`): those of the minimum, not of the steps.

    (Optimistix's solver vmapped over the points, which this replaced, ran one point's while
    loop under `vmap`: 26-39 µs a point for 100k points of 4 views, against 7 for a user's
    NumPy Gauss–Newton, a benchmark trial.)"""
    X = _polished(cameras, X0, pixels, m, max_steps)
    return jnp.where(jnp.all(jnp.isfinite(X), -1, keepdims=True), X, X0)


# A point is polished when its Gauss–Newton step is below this, relative to it.
_POLISH_TOL = 1e-10


def _point_residuals(cameras: Camera, X, pixels, m):
    """`(C, N, 2)`: each view's reprojection error of each point, zero where hidden."""
    return jnp.where(m[..., None], cameras.project(X) - pixels, 0.0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(4,))
def _polished(cameras: Camera, X0, pixels, m, max_steps):
    dtype = X0.dtype
    tol = max(_POLISH_TOL, 4 * float(jnp.finfo(dtype).eps))
    residuals = functools.partial(_point_residuals, cameras, pixels=pixels, m=m)
    eye = jnp.eye(3, dtype=dtype)

    def cost(r):
        return 0.5 * jnp.sum(r * r, axis=(0, 2))

    def step(state):
        X, lam, f, done, k = state
        r = residuals(X)
        J = jax.vmap(lambda e: jax.jvp(residuals, (X,), (jnp.broadcast_to(e, X.shape),))[1])(eye)
        H = [[jnp.sum(J[a] * J[b], axis=(0, 2)) for b in range(3)] for a in range(3)]
        g = [jnp.sum(J[a] * r, axis=(0, 2)) for a in range(3)]
        A = [[H[a][b] * (1.0 + lam) if a == b else H[a][b] for b in range(3)] for a in range(3)]
        L = _definite_factor(A, H)
        delta = jnp.stack(_small.cho_solve(L, [-x for x in g]), -1)  # (N, 3)
        trial = X + delta
        f_trial = cost(residuals(trial))
        # Near the minimum a step's gain is below the cost's rounding, where the gradient still
        # says where to go: a step whose predicted gain is that small is taken
        predicted = -sum(g[a] * delta[:, a] for a in range(3)) - 0.5 * sum(
            H[a][b] * delta[:, a] * delta[:, b] for a in range(3) for b in range(3)
        )
        rounding = 64 * jnp.finfo(dtype).eps * f
        better = ((f_trial <= f) | (predicted <= rounding)) & ~done
        small = jnp.max(jnp.abs(delta), -1) <= tol * (jnp.max(jnp.abs(X), -1) + tol)
        X = jnp.where(better[:, None], trial, X)
        lam = jnp.where(better, jnp.maximum(lam * 0.3, 1e-12), lam * 10.0)
        # (a step damped small is no sign of the minimum: only a small step taken is)
        done = done | (better & small) | (lam > 1e12) | (f == 0)
        return X, lam, jnp.where(better, f_trial, f), done, k + 1

    def going(state):
        return (state[4] < max_steps) & ~jnp.all(state[3])

    n = X0.shape[0]
    start = (X0, jnp.full(n, 1e-3, dtype), cost(residuals(X0)), jnp.zeros(n, bool), 0)
    X, _, f, _, k = jax.lax.while_loop(going, step, start)
    # one more Gauss–Newton step for every point: from a step of 1e-10 of the point it takes
    # the gradient of a test's 4-view points (0.5 px of noise) from 9e-7 to 1e-8, where a
    # tolerance of 1e-12 needed up to 50 steps for all points (the last few at rounding)
    return step((X, jnp.zeros(n, dtype), f, jnp.zeros(n, bool), k))[0]


def _definite_factor(rows, undamped):
    """`_small.cholesky` of the symmetric 3 x 3 `rows` (entries `(N,)`), its pivots raised to
    `eps` of the trace of `undamped` (the same matrix before damping): the factor of a nearby
    definite matrix where a point's is singular."""
    trace = undamped[0][0] + undamped[1][1] + undamped[2][2]
    return _small.cholesky(rows, jnp.finfo(trace.dtype).eps * trace + jnp.finfo(trace.dtype).tiny)


@_polished.defjvp
def _polished_jvp(max_steps, primals, tangents):
    """The implicit derivative of each point's minimum: `dX = -H^-1 d(grad)`, with `H` the
    Hessian of its cost (3 x 3, exact: second-order terms included) and `d(grad)` its
    gradient's change with the cameras and pixels; zero for a point seen by fewer than 2 views
    (whose result is not a point)."""
    cameras, X0, pixels, m = primals
    d_cameras, _, d_pixels, _ = tangents
    X = _polished(cameras, X0, pixels, m, max_steps)

    def gradient(X, cameras, pixels, m):  # of one point's cost, X (3,), pixels (C, 2), m (C,)
        def cost(X):
            r = _point_residuals(cameras, X[None], pixels[:, None], m[:, None])
            return 0.5 * jnp.sum(r * r)

        return jax.grad(cost)(X)

    H = jax.vmap(jax.jacfwd(gradient), in_axes=(0, None, 1, 1))(X, cameras, pixels, m)
    d_gradient = jax.vmap(
        lambda X, p, dp, m: jax.jvp(
            lambda c, p: gradient(X, c, p, m), (cameras, p), (d_cameras, dp)
        )[1],
        in_axes=(0, 1, 1, 1),
    )(X, pixels, d_pixels, m)
    rows = [[H[:, a, b] for b in range(3)] for a in range(3)]
    L = _definite_factor(rows, rows)
    inverse = jnp.stack([jnp.stack(_small.cho_solve(L, list(e)), -1) for e in jnp.eye(3)], -1)
    seen = jnp.sum(m, 0) >= 2
    inverse = jnp.where(seen[:, None, None], inverse, 0.0)  # (N, 3, 3)
    return X, -jnp.einsum("nab,nb->na", inverse, d_gradient)


def _diagnostics(cameras: Camera, X, u, v, m, observed=None):
    """Views, reprojection RMS, widest ray angle and in-front flag of the points `X (N, 3)`: in
    front of every view that sees it, at positive depth; or, given the `observed` unit rays
    `(3, C, N)` (a fisheye's), on the side of each camera its ray points to.

    Computed as `(C, N)` arrays over all views at once, summed over the views by a product with
    ones: XLA's reductions over a leading axis, and over short trailing ones, are slow on a CPU.
    """
    w = m.astype(X.dtype)
    views = jnp.ones(w.shape[0], w.dtype)
    n = views @ w
    q = cameras.project(X)
    err2 = (q[..., 0] - u) ** 2 + (q[..., 1] - v) ** 2
    rms = jnp.sqrt(views @ (w * err2) / jnp.maximum(n, 1.0))
    # Unit rays from the centres, by component (C, N); the widest angle is the smallest cosine
    # between the rays of two views that see the point.
    rays = [X[:, k] - cameras.center[:, k, None] for k in range(3)]
    # (into memory, not recomputed per pair; by one reciprocal square root rather than a square
    # root and three divisions: 0.32-0.34 against 0.35-0.37 µs/point, in-process A/B)
    scale = jax.lax.rsqrt(sum(r * r for r in rays))
    rays = jax.lax.optimization_barrier([r * scale for r in rays])

    def cosines(a, b):  # of view a with view (or views) b
        return jnp.where(m[a] & m[b], sum(r[a] * r[b] for r in rays), 1.0)

    C = w.shape[0]
    if C <= _PAIRED_VIEWS:
        # every pair written out, one elementwise loop over the points (100k points of 8 views:
        # 0.37-0.39 against 0.40-0.42 µs/point with the loop below and its minimum over views)
        pairs = [cosines(a, b) for a in range(C) for b in range(a + 1, C)]
        cos = functools.reduce(jnp.minimum, pairs)
    else:  # one view at a time against all (a view with itself gives 1)
        every = slice(None)
        smallest = lambda a, cos: jnp.minimum(cos, cosines(a, every))  # noqa: E731
        cos = jnp.min(jax.lax.fori_loop(1, C, smallest, cosines(0, every)), 0)
    # (a point seen once has cosine 1, where arccos' slope is infinite: kept off it)
    cos = jnp.where(n >= 2, jnp.clip(cos, -1.0, 1.0), 0.0)
    # arccos(c) = 2 atan(sqrt((1 - c) / (1 + c))): XLA's CPU backend runs arctan as a vectorised
    # loop and arccos (as arctan2) element by element, 2.2 against 9 ns a point (within 2.5 ulp
    # of arccos, 5e-14 degrees); 1 - c is exact where c is near 1, and c = -1 gives atan(inf)
    angle = jnp.degrees(2.0 * jnp.arctan(jnp.sqrt((1.0 - cos) / (1.0 + cos))))
    if observed is None:
        behind = cameras.depth(X) <= 0
    else:
        xc = cameras._camera_coordinates(X)  # noqa: SLF001
        behind = sum(r * c for r, c in zip(observed, xc)) <= 0
    in_front = views @ (w * behind) == 0
    # A point seen by fewer than two views has no position: its diagnostics are NaN, not
    # whatever the rounding of its stand-in happened to give.
    rms, angle = (jnp.where(n >= 2, x, jnp.nan) for x in (rms, angle))
    return n, rms, angle, in_front


# Points per loop step, times the number of views: on a CPU, the (C, n) arrays of a chunk of
# 2^15 / C points stay in cache (a fifth of the time moving 100k points' arrays through memory).
CHUNK = 2**15


def _chunk_size(n_cameras: int, n_points: int) -> int | None:
    """Points triangulated side by side in one loop step (`_sharding.cpu_chunk`): on one CPU
    device, at most `CHUNK // C` at a time; else all."""
    return _sharding.cpu_chunk(n_points, max(CHUNK // n_cameras, 256))


def _triangulate_set(cameras, pixels, mask, min_angle, refine, max_steps, chunk):
    run = functools.partial(
        _triangulate_points, cameras, min_angle=min_angle, refine=refine, max_steps=max_steps
    )
    # (C, N) arrays per coordinate from here on, split before the chunks: XLA's loops over
    # arrays with a trailing axis of length 2 are several times slower on a CPU, and moving the
    # chunks' (x, y) pairs into place cost 2.6 ms of 36 for 100k points of 8 views
    return _sharding.chunked_map(run, (pixels[..., 0], pixels[..., 1], mask), chunk, axis=1)


def _undistorted_at_zero(cameras: Camera, u, v):
    """`undistort_points` of the pixels `(C, N)` `u`, `v` where every coefficient is zero: the
    pixels themselves (exactly: the distortion's terms are zero), as one step `p - (distort(p)
    - p)` from them, whose derivative in the coefficients is undistortion's there."""
    y = (v - cameras.v0[:, None]) / cameras.alpha_v[:, None]
    x = (u - cameras.u0[:, None] - cameras.skew[:, None] * y) / cameras.alpha_u[:, None]
    xd, yd = _distort(x, y, cameras.dist[:, None])
    dx, dy = xd - x, yd - y
    return u - cameras.alpha_u[:, None] * dx - cameras.skew[:, None] * dy, v - cameras.alpha_v[
        :, None] * dy  # fmt: skip


def _triangulate_points(cameras, u, v, mask, min_angle, refine, max_steps):
    # Hartley's normalisation for triangulation: undistorted pixels to normalised camera
    # coordinates (K^-1 x), and the world frame moved to the cameras' centroid and scaled by
    # their spread, so that every entry of the linear system is of order one in float32 too.
    # Each view's rows are then weighted by its focal length relative to the rig's mean, so
    # that, as in pixel units, a pixel of noise counts the same in every camera.
    # Hidden pixels are replaced before any arithmetic, so that NaN in them reaches neither the
    # points nor their derivatives.
    # (a fisheye's pixel outside its image circle, beyond its polynomial's fold, has no ray:
    # hidden, as a NaN pixel is; it made the point NaN, whatever the other views saw: a fisheye
    # user's trial)
    m = mask & jnp.isfinite(u) & jnp.isfinite(v)
    fisheye = cameras.lens == "fisheye"
    if fisheye:
        m &= jax.lax.stop_gradient(cameras._in_image_circle(u, v))  # noqa: SLF001
    pu = jnp.where(m, u, cameras.u0[:, None])
    pv = jnp.where(m, v, cameras.v0[:, None])
    if fisheye:  # unit rays, beyond 90 degrees too
        rays = jnp.moveaxis(cameras.rays(jnp.stack([pu, pv], -1)), -1, 0)
    else:
        # Undistortion (Newton steps per pixel) is a third of the work; skipped for rigs without
        # distortion, where it is the identity written as one step from it, which keeps its
        # derivative in the coefficients (the plain identity had none: gradient descent on the
        # distortion through `triangulate`, from zero as usual, never moved; a JAX user's trial)
        ideal = jax.lax.cond(
            jnp.any(cameras.dist != 0),
            lambda u, v: tuple(
                jnp.moveaxis(undistort_points(cameras, jnp.stack([u, v], -1)), -1, 0)
            ),
            functools.partial(_undistorted_at_zero, cameras),
            pu,
            pv,
        )
        # (a pixel beyond the fold of its lens's radial distortion has no ray either: hidden)
        reached = jax.lax.stop_gradient(jnp.isfinite(ideal[0]))
        m &= reached
        ideal = [jnp.where(reached, p, c[:, None]) for p, c in zip(ideal, (cameras.u0, cameras.v0))]
        y = (ideal[1] - cameras.v0[:, None]) / cameras.alpha_v[:, None]
        x = (ideal[0] - cameras.u0[:, None] - cameras.skew[:, None] * y) / cameras.alpha_u[:, None]

    centres = cameras.center
    middle = jnp.mean(centres, 0)
    ms = jnp.mean(jnp.sum((centres - middle) ** 2, -1))
    # `where` before `sqrt` and division: coincident cameras have a zero spread, and the
    # derivative must stay finite (0 * inf in the backward pass would be NaN).
    spread = jnp.sqrt(jnp.where(ms > 0, ms, 1.0))
    focal = jnp.sqrt(jnp.abs(cameras.alpha_u * cameras.alpha_v))
    weight = focal / jnp.mean(focal)
    t = (cameras.R @ middle + cameras.t) / spread
    P = weight[:, None, None] * jnp.concatenate([cameras.R, t[..., None]], axis=-1)

    # The normal matrices in that rig frame are one product (`_normal_coefficients`; XLA's
    # products of small matrices are slower than one with the features stacked); each is
    # then moved to its point's own frame, the centroid and spread of just the views that see
    # the point, so that a hidden view changes nothing (the linear solution depends on the frame).
    w = m.astype(pu.dtype)
    n = jnp.ones_like(w[:, 0]) @ w  # (a sum over the leading axis is slow on a CPU)
    if fisheye:
        B = _ray_coefficients(P)
        dx, dy, dz = rays
        products = [dx * dx, dy * dy, dz * dz, dx * dy, dx * dz, dy * dz]
        features = jnp.concatenate([w] + [w * q for q in products])  # (7C, N)
    else:
        B = _normal_coefficients(P)
        features = jnp.concatenate([w * (x * x + y * y), w * x, w * y, w])  # (4C, N)
    entries = jnp.concatenate(B, -1) @ features
    G = [[None] * 4 for _ in range(4)]
    for k, (i, j) in enumerate(_PAIRS):
        G[i][j] = G[j][i] = entries[k]
    own = (centres - middle) / spread
    d = (own.T @ w) / jnp.maximum(n, 1.0)  # (3, N): the point's frame in the rig's
    ms = (jnp.sum(own * own, -1) @ w) / jnp.maximum(n, 1.0) - jnp.sum(d * d, 0)
    s = jnp.sqrt(jnp.where(ms > 0, ms, 1.0))
    G = _congruence(G, s, d)
    # A point seen by fewer than two views gets a harmless stand-in (it is flagged not ok): an
    # all-zero matrix would have no Cholesky factor, and repeated eigenvalues, where the null
    # vector's derivative (which needs the gap to the next eigenvalue) is infinite.
    G = [[jnp.where(n >= 2, G[i][j], float(4 - i) if i == j else 0.0) for j in range(4)]
         for i in range(4)]  # fmt: skip
    v = _null_vector(jnp.stack([jnp.stack(row) for row in G]))  # (4, N)
    X = middle + spread * (d + s * v[:3] / v[3]).T  # (N, 3)
    # That stand-in sits at its one camera's centre, where projections and rays divide by zero;
    # the diagnostics and the refinement see it at the middle of the rig, a spread along the
    # cameras' mean axis, instead (not refined: its views are hidden), so that its NaN results
    # leave the others' derivatives finite.
    seen = n >= 2
    away = middle + spread * jnp.mean(cameras.R[:, 2], 0)
    X = jnp.where(seen[:, None], X, away)
    if refine:
        X = _polish(cameras, X, jnp.stack([pu, pv], -1), m & seen, max_steps)
    n, rms, angle, in_front = _diagnostics(cameras, X, pu, pv, m, rays if fisheye else None)
    in_front = seen & in_front
    ok = in_front & (angle >= min_angle) & jnp.all(jnp.isfinite(X), -1)
    X = jnp.where(seen[:, None], X, jnp.nan)
    return Triangulation(
        points=X, views=n.astype(jnp.int32), rms=rms, angle=angle, in_front=in_front, ok=ok
    )


def triangulate(
    cameras: Camera,
    pixels: Float[Array, "*batch C N 2"],
    mask: Bool[Array, "*batch C N"] | None = None,
    *,
    refine: bool = False,
    min_angle: float = 1.0,
    max_rms: float = MAX_RMS,
    max_steps: int = 50,
) -> Triangulation:
    """Reconstruct world points from their pixels in several calibrated views.

    For each point: the pixels are undistorted (`undistort_points`) and taken to normalised
    camera coordinates, and the point is the null vector of the `2C x 4` linear system of its
    visible views (the DLT of the point; the smallest eigenvector of its 4 x 4 normal matrix).
    Fisheye cameras give unit rays (`Camera.rays`, up to 180 degrees off axis) and each view
    three rows, the point's offset from its ray (`d x P X`), so that rays beside or behind the
    image plane count as any other;
    with `refine=True` it is then moved to the minimum of its reprojection error (optimistix
    Levenberg–Marquardt, distortion included).
    All points (and all point sets) in one jit-compiled, vectorised call. Differentiable with
    respect to the pixels and the cameras (so `jax.jacfwd` gives the first-order covariance of
    the points).

    **Arguments:**

    - `cameras`: a rig `(C,)` in one (global) frame. A camera with a non-finite parameter (one
      that `calibrate` could not solve is NaN) sees nothing.
    - `pixels`: `(..., C, N, 2)`: point n as seen by camera c; leading axes are point sets.
    - `mask`: `(..., C, N)` visibility, or any shape that broadcasts to it (`(N,)` per point,
      `(C, 1)` per camera); default: the finite pixels. Hidden views have no
      influence, even if NaN; a NaN or inf pixel counts as hidden whatever the mask says
      (called with concrete arrays, with a warning).
    - `refine`: polish each point by minimising its reprojection error.
    - `min_angle`: the smallest ray angle (degrees) for `ok`.
    - `max_rms`: the largest reprojection RMS (pixels) for `ok`, default `MAX_RMS` (10 px;
      `np.inf` for any: `ok` then says the geometry holds, not that the pixels agree).
    - `max_steps`: Levenberg–Marquardt steps per point with `refine`.

    **Returns:** a `Triangulation` (points and per-point diagnostics).

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4)
    >>> out = mc.triangulate(rig.cameras, rig.pixels)
    >>> bool(np.allclose(out.points, rig.world, atol=1e-2)), out.views[:3].tolist()  # mm
    (True, [4, 4, 4])

    ```
    """
    _validate.static_options(
        "triangulate", refine=refine, min_angle=min_angle, max_rms=max_rms, max_steps=max_steps
    )
    if not isinstance(cameras, Camera) or len(cameras.batch_shape) != 1:
        raise ValueError("`cameras` must be a rig: one `Camera` with a camera axis (C,).")
    C = cameras.batch_shape[0]
    # Called with concrete arrays, the point sets are one set (every point is triangulated
    # alone; padding each set's points to a bucket was up to 58 times the work: 1000 frames of
    # 6 body parts took 1.2-1.6 s against 0.02 s) and the points are padded to a shape bucket
    # (hidden), so that other numbers of points reuse the compiled program; checked, flattened
    # and padded in NumPy.
    host = _buckets.applies(cameras, pixels, mask)
    xp = np if host else jnp
    pixels = _validate.floating("pixels", pixels, (None, None, 2), xp=xp)
    if pixels.shape[-3] != C:
        raise ValueError(
            f"`pixels` must be (..., C, N, 2) with C = {C} cameras; got {tuple(pixels.shape)}."
        )
    if C < 2:
        raise ValueError("triangulation needs at least 2 cameras.")
    if not max_rms > 0:
        raise ValueError(f"`max_rms` is a positive number of pixels; got {max_rms!r}.")
    given = mask is not None
    if mask is None:
        mask = _validate.finite_pixels(pixels, xp)
    mask = _validate.boolean_mask("mask", mask, pixels.shape[:-1], xp=xp)
    if host:
        _validate.check_placeholders(pixels, mask)
        if given:
            _validate.check_hidden_non_finite(pixels, mask)
        R, t = np.asarray(cameras.R), np.asarray(cameras.t)
        if t.dtype == np.float32:  # (a benchmark trial: 4 cameras 30 m apart in UTM, 0.16 m off)
            centres = -np.einsum("cji,cj->ci", R, t)
            _validate.check_float32_frame(
                centres, "the rig is", "the cameras' spread", "the points"
            )
    batch, n = pixels.shape[:-3], pixels.shape[-2]
    if host and batch:  # (C, sets x N): set b's point j is point b N + j
        pixels = np.moveaxis(pixels.reshape(-1, C, n, 2), 0, 1).reshape(C, -1, 2)
        mask = np.moveaxis(mask.reshape(-1, C, n), 0, 1).reshape(C, -1)
    total = pixels.shape[-2]
    n_points = _buckets.size(total, _buckets.WORK // max(C, 1))
    bucketed = host and n_points != total
    if bucketed:
        pixels = _buckets.pad(pixels, -2, n_points, fill=0)
        mask = _buckets.pad(mask, -1, n_points, fill=False)
    work = math.prod(pixels.shape[:-1])
    out = _triangulate(
        cameras,
        pixels,
        mask,
        min_angle=np.asarray(min_angle, pixels.dtype),
        max_rms=np.asarray(max_rms, pixels.dtype),
        refine=bool(refine),
        max_steps=int(max_steps),
        chunk=_chunk_size(C, pixels.shape[-2]),
        quick=work <= _buckets.COMPACT,
    )
    if not host:
        return out
    if bucketed:
        out = _buckets.first(out, total, axis=0)
    _check_behind(out)
    if batch:
        out = jax.tree_util.tree_map(
            lambda a: jax.device_put(np.asarray(a).reshape(*batch, n, *a.shape[1:])), out
        )
    return out


def _check_behind(out: Triangulation) -> None:
    """Warn where most points seen twice or more lie behind the cameras that see them: a
    mirrored world (a benchmark trial: the Oxford house's 672 points, accurate, all not ok,
    without a word)."""
    seen = np.asarray(out.views) >= 2
    behind = seen & ~np.asarray(out.in_front)
    if behind.sum() >= 4 and behind.sum() > 0.5 * seen.sum():
        warnings.warn(
            f"triangulate: {int(behind.sum())} of {int(seen.sum())} points lie behind the "
            "cameras that see them (not ok): the cameras see a mirrored world (`calibrate` says "
            "`mirrored`: a left-handed world frame, or pixels as (y, x)).",
            stacklevel=_validate._outside_mvcalib(),  # noqa: SLF001
        )


@functools.partial(_buckets.jit, static_argnames=("refine", "max_steps", "chunk"))
def _triangulate(cameras, pixels, mask, min_angle, max_rms, refine, max_steps, chunk):
    """`triangulate` of validated `pixels (..., C, N, 2)` and `mask (..., C, N)`."""
    out = _triangulate_sets(cameras, pixels, mask, min_angle, refine, max_steps, chunk)
    return eqx.tree_at(lambda o: o.ok, out, out.ok & (out.rms <= max_rms))


def _triangulate_sets(cameras, pixels, mask, min_angle, refine, max_steps, chunk):
    """Every point set's (the leading axes') triangulation."""
    cameras = jax.tree_util.tree_map(lambda a: jnp.asarray(a, pixels.dtype), cameras)
    # a NaN camera (not calibrated) sees nothing
    cameras, mask, _ = usable_rig(cameras, mask, unit_camera(pixels.dtype, cameras.lens))
    run = functools.partial(
        _triangulate_set,
        cameras,
        min_angle=min_angle,
        refine=refine,
        max_steps=max_steps,
        chunk=chunk,
    )
    batch = pixels.shape[:-3]
    if not batch:
        return run(pixels, mask)
    out = jax.vmap(run)(pixels.reshape(-1, *pixels.shape[-3:]), mask.reshape(-1, *mask.shape[-2:]))
    return jax.tree_util.tree_map(lambda a: a.reshape(*batch, *a.shape[1:]), out)


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
