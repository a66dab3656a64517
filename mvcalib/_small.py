"""Small symmetric linear algebra written out entry by entry.

A matrix here is a list of rows, each an array whose trailing axes are the batch (the DLT's
cameras). Batched over thousands of cameras, LAPACK runs one tiny problem after another, and XLA's
reductions over axes of length 4 are slow on CPU; written out, every entry is one array over the
batch and XLA fuses the whole solve into a few elementwise loops.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def cholesky(A, floor):
    """The lower Cholesky factor of the symmetric `A` (rows of entries; only its lower triangle is
    read), as a list of rows.

    Pivots below `floor` are raised to it, so a singular or slightly indefinite `A` (rounding of a
    semi-definite one) gets a factor of a nearby definite matrix, as inverse iteration wants.
    """
    n = len(A)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = A[j][j] - sum(L[j][k] * L[j][k] for k in range(j))
        L[j][j] = jnp.sqrt(jnp.maximum(d, floor))
        for i in range(j + 1, n):
            L[i][j] = (A[i][j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    return L


def cho_solve(L, b):
    """`x` with `L L^T x = b`."""
    n = len(L)
    y = [None] * n
    for i in range(n):
        y[i] = (b[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i]
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return x


def lower_inverse(L):
    """The rows of `L^-1` for a lower triangular `L` (rows of entries), `None` above the
    diagonal."""
    n = len(L)
    X = [[None] * n for _ in range(n)]
    for j in range(n):
        X[j][j] = 1.0 / L[j][j]
        for i in range(j + 1, n):
            X[i][j] = -sum(L[i][k] * X[k][j] for k in range(j, i)) / L[i][i]
    return X


def dot3(a, b):
    """The dot product of the first three entries along the leading axis, written out (under
    `vmap`, `@` on 3-vectors is a batched library call, `jnp.sum` a reduction over a short axis)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def triple(a, b, c):
    """`a . (b x c)`, the determinant of the 3 x 3 matrix with rows `a, b, c` (3-vectors along the
    leading axis), written out like `dot3`."""
    cross = [b[i] * c[j] - b[j] * c[i] for i, j in ((1, 2), (2, 0), (0, 1))]
    return dot3(a, cross)


def adjugate(A):
    """The adjugate `det(A) A^-1` of the 4 x 4 `A` (rows of entries), as rows of entries: its
    cofactors by Laplace expansion over the 2 x 2 minors of the first two and last two rows,
    products and sums only."""

    def minor(r, a, b):  # the 2 x 2 minor of rows r, r + 1 and columns a, b
        return A[r][a] * A[r + 1][b] - A[r + 1][a] * A[r][b]

    s = {(a, b): minor(0, a, b) for a in range(4) for b in range(a + 1, 4)}
    c = {(a, b): minor(2, a, b) for a in range(4) for b in range(a + 1, 4)}

    def cofactor(i, j):  # (-1)^(i+j) times the determinant of A without row i and column j
        minors = c if i < 2 else s  # of the other block's rows
        other = 1 - i if i < 2 else 5 - i  # the row of the 2 x 2 block that remains
        cols = [k for k in range(4) if k != j]
        # expand along the remaining row of i's block, the first row of the 3 x 3 minor for
        # i < 2 and its last for i >= 2 (the same alternating signs): each entry times the 2 x 2
        # minor of the other block's rows in the two other columns
        terms = [A[other][k] * minors[tuple(x for x in cols if x != k)] for k in cols]
        value = terms[0] - terms[1] + terms[2]
        return value if (i + j) % 2 == 0 else -value

    return [[cofactor(j, i) for j in range(4)] for i in range(4)]


def leading_sum(x):
    """The sum of `x (n, *batch)` over its leading axis, as a product with a row of ones.

    XLA's CPU backend fuses a chain of reductions and the elementwise work between them into one
    kernel (XNNPACK's, in jax 0.10) that runs several times slower than its parts: normalising
    v and keeping z orthogonal to it took ~0.1 µs per camera and step. A matrix-vector product
    ends every fusion, and the parts run as fast elementwise loops.
    """
    ones = jnp.ones(x.shape[:1], x.dtype)
    # (no reshape: merging the batch axes would make XLA gather an axis sharded over devices)
    return jnp.tensordot(ones, x, axes=1, precision=jax.lax.Precision.HIGHEST)


def eigenvector_tangent(G, v, dG_v):
    """The derivative `dv` of the unit eigenvector `v` of the smallest eigenvalue of the symmetric
    `G (n, n)`, given `dG v`.

    First-order perturbation needs only the gap to the next eigenvalue (which is what makes `v`
    unique anyway): `(G - l I) dv = -(I - v v^T) dG v` with `v^T dv = 0`. Adding `c v v^T` makes
    the matrix invertible without changing that solution (`B v = c v`, and the right-hand side
    is orthogonal to v). Written with v and a linear solve, not G's other eigenvectors, it is
    differentiable again: second derivatives stay finite where other eigenvalues repeat (a
    symmetric target), where JAX's SVD and eigh rules give NaN.
    """
    n = G.shape[-1]
    lam = v @ G @ v
    c = jnp.trace(G) / n + 1.0  # any c > 0; this one is of G's scale
    B = G - lam * jnp.eye(n, dtype=G.dtype) + c * jnp.outer(v, v)
    return -jnp.linalg.solve(B, dG_v - v * (v @ dG_v))


def materialised(x):
    """`x`, behind an optimisation barrier: XLA computes it once, into memory, instead of fusing
    its computation into every consumer, where each entry of the consumer recomputes the whole
    chain of a triangular solve (fusions of 115-143 operations in the DLT's inverse iteration).

    A product with the identity did the same (with `leading_sum`, the DLT + decomposition of 4096
    cameras went from 4.21 to 3.32 µs per camera); the barrier spares that product and the copy
    that fed it (with the DLT's step change written as an elementwise maximum: 1.58-1.71 against
    1.82-1.88 µs per camera, interleaved, 3 rounds).
    """
    return jax.lax.optimization_barrier(x)
