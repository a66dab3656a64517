"""Nonlinear refinement of reprojection error: Levenberg–Marquardt (an optimistix solver), one
problem per camera, batched across the rig (`solve_each`); distortion, robust losses, covariance,
implicit derivatives."""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int, PyTree

from . import _buckets, _sharding, _small, _validate
from ._camera import (
    LENSES,
    Camera,
    _fisheye_polynomial,
    flat_rig,
    lens_of,
    unit_camera,
    usable_rig,
)
from ._report import ReprojectionReport, masked_rms, residual_report, residual_rms
from ._rotation import exp_and_left_jacobian


def parameter_names(lens: str = "pinhole") -> tuple[str, ...]:
    """The names of a camera's packed parameters, in order: intrinsics, axis-angle rotation
    increment, translation, and the lens's distortion coefficients (`Camera`)."""
    head = ("alpha_u", "alpha_v", "u0", "v0", "skew", "rx", "ry", "rz", "tx", "ty", "tz")
    return head + LENSES[lens]


PARAMETERS = parameter_names("pinhole")
# What `refine` estimates of each lens's distortion by default: OpenCV's defaults (cv2 without
# k3, which overfits; cv2.fisheye all four).
DEFAULT_DISTORTION = {"pinhole": ("k1", "k2", "p1", "p2"), "fisheye": ("k1", "k2", "k3", "k4")}
GROUPS = {
    "focal": ("alpha_u", "alpha_v"),
    "principal_point": ("u0", "v0"),
    "intrinsics": ("alpha_u", "alpha_v", "u0", "v0"),
    "rotation": ("rx", "ry", "rz"),
    "translation": ("tx", "ty", "tz"),
    "pose": ("rx", "ry", "rz", "tx", "ty", "tz"),
    "distortion": LENSES["pinhole"],  # (a fisheye's: its own, `_free_parameters`)
}
DISTORTION = LENSES["pinhole"]
# `fix`'s constraint rather than parameters: alpha_u / alpha_v held at the seed's ratio
# (OpenCV's CALIB_FIX_ASPECT_RATIO), the focal length estimated (`Free`)
CONSTRAINTS = ("aspect_ratio",)
# Where the pose sits in the packed parameters (the same for either lens; the rest are the
# intrinsics with the distortion).
POSE_INDICES = tuple(PARAMETERS.index(n) for n in GROUPS["pose"])


# ------------------------------------------------------------------------------ robust losses
def _scale(scale):
    """A loss's `scale` as data, not a constant of the programs it enters: a Python number as a
    weakly typed JAX scalar (it takes the dtype of the residuals), an array or tracer as it is.
    As a float, every new value compiled every program again (`refine(..., loss=Huber(s))`: 0.8
    s a value, against 9 ms warm; a JAX user's trial of an annealing loop)."""
    if isinstance(scale, (int, float, np.integer, np.floating)) and not isinstance(scale, bool):
        if not float(scale) > 0:
            raise ValueError(f"a robust loss's `scale` is a positive number (pixels); got {scale}.")
        return jnp.asarray(float(scale))
    return scale


class _Loss(eqx.Module):
    scale: Float[Array, ""] = eqx.field(default=1.0, converter=_scale)

    def __repr__(self) -> str:
        try:
            return f"{type(self).__name__}({float(self.scale):g})"
        except (TypeError, jax.errors.ConcretizationTypeError):  # (traced)
            return f"{type(self).__name__}(scale={self.scale!r})"


class Huber(_Loss):
    """Huber loss on the length `r` of a point's residual: `r^2` up to `scale` pixels, linear
    beyond (`2 scale r - scale^2`). The scale may be traced (a program takes any value)."""

    def rho(self, s):
        c2 = self.scale**2
        return jnp.where(s <= c2, s, 2.0 * self.scale * jnp.sqrt(jnp.maximum(s, c2)) - c2)


class Cauchy(_Loss):
    """Cauchy (Lorentzian) loss: `scale^2 log(1 + r^2 / scale^2)`; far outliers count ~ log r.
    The scale may be traced (a program takes any value)."""

    def rho(self, s):
        c2 = self.scale**2
        return c2 * jnp.log1p(s / c2)


def check_loss(loss) -> None:
    """Refuse a `loss` that is not None, `Huber` or `Cauchy`, saying what is."""
    if loss is not None and not isinstance(loss, (Huber, Cauchy)):
        raise TypeError(
            "`loss` is None (least squares), `mc.Huber(scale)` or `mc.Cauchy(scale)`, scale in "
            f"pixels; got {loss!r}."
        )


def _robust_weights(loss, s):
    """sqrt(rho(s) / s), so that a point's weighted residual has squared length rho(s)."""
    if loss is None:
        return jnp.ones_like(s)
    tiny = s < 1e-12 * loss.scale**2
    safe = jnp.where(tiny, 1.0, s)
    return jnp.where(tiny, 1.0, jnp.sqrt(loss.rho(safe) / safe))


# ------------------------------------------------------------------------------ the solver
class _SecantLMState(eqx.Module):
    residual: Array  # at the current point, flattened
    jacobian: Array  # (n, m): transposed, one row per parameter
    normal: Array  # (n, n): jacobian @ jacobian.T
    gradient: Array  # jacobian @ residual
    curvature: Array  # (n, n): the secant estimate of sum_i r_i Hess(r_i)
    augmented: Array  # whether the next step's model adds `curvature` (else Gauss–Newton)
    cost: Array  # |residual|^2
    damping: Array
    growth: Array  # the factor of the damping's next increase
    aux: PyTree
    step: Array  # the next trial's step from the current point (zero before the first)
    done: Array
    fresh: Array  # whether no step was taken yet (the fields above are placeholders then)


class SecantLM(optx.AbstractLeastSquaresSolver):
    """Levenberg–Marquardt on the Gauss–Newton model augmented by a structured secant estimate
    `S` of the residuals' own curvature `sum_i r_i Hess(r_i)` (Dennis, Gay & Welsch 1981, the
    augmented model of NL2SOL), for small dense problems; an optimistix solver.

    Gauss–Newton drops `S`. Where the data pin a parameter down only weakly (a camera's k1 seen
    near the image centre), `S` is not small against `J^T J` in that direction and Gauss–Newton
    (and optimistix's `LevenbergMarquardt`) converges only linearly there: on the refine
    benchmark's 256 cameras, up to 85 steps at a rate of 0.85, against at most 20 with `S`.
    Each step solves `(J^T J + S + lambda diag(J^T J)) dy = -J^T r` by Cholesky (Marquardt's
    scaling, so the damping does not depend on the parameters' units); a trial that does not
    lower the cost, or whose matrix is not positive definite, is rejected and the damping
    raised. After an accepted step, `S` takes the secant condition
    `(J+^T J+ + S+) dy = J+^T r+ - J^T r+`, sized down where it overshoots (NL2SOL's sizing).
    As in NL2SOL, each step uses whichever model, Gauss–Newton or augmented, predicted the
    previous trial's change of cost better: far from the optimum a secant `S` built from a few
    long steps is often wrong, and Gauss–Newton is kept there (on the refine benchmark: 8.5
    steps per camera on average instead of 10.4 with `S` always, at the same tolerance).

    Converged when an accepted step is shorter than `rtol` standard errors of the parameters,
    `dy^T J^T J dy <= rtol^2 cost / (m - n)` with `m` residuals and `n` parameters (noise-scaled,
    so it means the same for every camera), or than `atol` in every entry of `y`; or when a trial
    is rejected although the model predicted a decrease of the cost below that tolerance
    `rtol^2 cost / (m - n)` and the cost changed by less (MINPACK's test of the relative
    reduction): the trial lost to rounding, which scales with the terms of the residuals (pixel
    coordinates of ~1000) rather than with the cost, and raising the damping until a trial wins
    took up to 8 more steps a camera; or when a trial changes the cost by no more than its
    rounding (an exact fit; with noise, ~1e-7 standard errors from the optimum). `y` and the
    residuals may be any pytrees of arrays; the Jacobian comes from forward-mode autodiff, or,
    for a 1-D `y`, from `options={"jacobian_transpose": jac}` with `jac(y, args)` the
    `(len(y), residuals)` matrix of the flattened residuals' derivatives, one row per parameter
    (the transpose of SciPy's `jac=`: the solver's products then run along contiguous rows).

    A robust cost `sum rho(|r_i|^2)` is given as `fn` with residuals whose squares sum to it
    (`r sqrt(rho / |r|^2)`: the objective, for the implicit derivatives) and
    `options={"model": model}`, `model(y, args) -> (residuals, cost)`, the residuals of the
    steps' Gauss–Newton model and the cost, as Ceres builds them (`_irls`: each point's residual
    and rows scaled by `sqrt(rho')`; a `jacobian_transpose` is then that of the model's
    residuals). The derivatives of `fn`'s residuals model the cost badly where `rho` is linear
    (Huber beyond its scale): their minimum lies twice as far as the cost's, and the damping
    creeps (planar views without wild points: 25 steps against least squares' 6; 7 with the
    model).

    Each step evaluates the trial its predecessor solved for and solves for the next; the first
    evaluates the start (a trial of length zero, always accepted), as optimistix's own solvers
    do. A next trial already shorter than the tolerance after an accepted one is taken without
    being evaluated, and ends the solve (the final state's residuals and Jacobian are then those
    of the point it left, within `rtol` standard errors). `optx.least_squares` counts the steps,
    one evaluation each.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, optimistix as optx, mvcalib as mc
    >>> t = jnp.linspace(0.0, 2.0, 20)
    >>> fn = lambda y, data: y[0] * jnp.exp(-y[1] * t) - data
    >>> sol = optx.least_squares(fn, mc.SecantLM(), jnp.array([1.0, 0.5]), 3.0 * jnp.exp(-2 * t))
    >>> sol.value.round(6).tolist()
    [3.0, 2.0]

    ```
    """

    rtol: float = 1e-5
    atol: float = 1e-12
    norm: Callable = optx.max_norm
    initial_damping: float = 1e-5

    def _evaluate(self, fn, y, args, options, unravel):
        """Residuals and transposed Jacobian `(n, m)` at the flat point `y`, the residuals
        flattened (any pytrees in `fn`), the cost and `fn`'s aux; those of `options["model"]`
        where given (see the class notes)."""
        model = options.get("model")

        def flat_fn(y_flat):
            if model is None:
                out, aux = fn(y_flat, args)
                return ravel_pytree(out)[0], (None, aux)
            out, cost = model(unravel(y_flat), args)
            return ravel_pytree(out)[0], (cost, None)

        residual, (cost, aux) = flat_fn(y)
        cost = residual @ residual if cost is None else cost
        jacobian = options.get("jacobian_transpose")
        if jacobian is None:  # forward mode, one row per parameter (jacfwd's pushforwards)
            pushforward = lambda v: jax.jvp(lambda y: flat_fn(y)[0], (y,), (v,))[1]  # noqa: E731
            jacobian_t = jax.vmap(pushforward)(jnp.eye(y.shape[0], dtype=y.dtype))
        else:
            jacobian_t = jacobian(y, args)
        return residual, jacobian_t, cost, aux

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, tags
        # placeholders of the residuals, Jacobian and aux that `_evaluate` returns: the first
        # step evaluates the start (`step`)
        model = options.get("model")
        if model is not None:  # the model's residuals, and no aux
            f_struct, aux_struct = jax.eval_shape(model, y, args)[0], None
        zeros = lambda x: jnp.zeros(x.shape, x.dtype)  # noqa: E731
        r = ravel_pytree(jax.tree_util.tree_map(zeros, f_struct))[0]
        y_flat = ravel_pytree(y)[0]
        n = y_flat.shape[0]
        return _SecantLMState(
            residual=r,
            jacobian=jnp.zeros((n, r.shape[0]), r.dtype),
            normal=jnp.zeros((n, n), r.dtype),
            gradient=jnp.zeros(n, r.dtype),
            curvature=jnp.zeros((n, n), y_flat.dtype),
            augmented=jnp.asarray(False),
            cost=jnp.asarray(jnp.inf, r.dtype),
            damping=jnp.asarray(self.initial_damping, y_flat.dtype),
            growth=jnp.asarray(10.0, y_flat.dtype),
            aux=jax.tree_util.tree_map(zeros, aux_struct),
            step=jnp.zeros_like(y_flat),
            done=jnp.asarray(False),
            fresh=jnp.asarray(True),
        )

    def step(self, fn, y, args, options, state, tags):
        del tags
        y, unravel = ravel_pytree(y)
        fn = _tree_fn(fn, unravel)
        r, Jt, H, g = state.residual, state.jacobian, state.normal, state.gradient
        S, cost, dy, fresh = state.curvature, state.cost, state.step, state.fresh
        # Each step evaluates the trial its predecessor solved for, then solves for the next one.
        # The first evaluates the start (a trial of length zero, always accepted), as
        # optimistix's own solvers do: the compiled program holds one copy of the residuals and
        # their Jacobian, not two (`refine` of 1024 cameras of 19 points compiled in 0.38-0.43
        # against 0.64 s). A trial that is already short is taken unevaluated (below): as many
        # evaluations and steps as with the start evaluated by `init` (6/8/16 on the refine
        # benchmark; 7/9/17 when the first step spent one on the start and every step solved
        # before it evaluated).
        r_new, Jt_new, cost_new, aux_new = self._evaluate(fn, y + dy, args, options, unravel)
        cost_new = jnp.where(jnp.isnan(cost_new), jnp.inf, cost_new)  # not definite, or NaN
        accept = (cost_new < cost) | fresh
        # the decrease of the cost each model predicted for this step, and the actual one
        gauss_newton = -2.0 * (dy @ g) - dy @ H @ dy
        augmented = gauss_newton - dy @ S @ dy
        actual = cost - cost_new
        good = actual > 0.25 * jnp.where(state.augmented, augmented, gauss_newton)

        # the structured secant update of S (Dennis, Gay & Welsch), with NL2SOL's sizing
        g_new = Jt_new @ r_new
        y_sharp = g_new - Jt @ r_new
        y_full = g_new - g
        ys = y_full @ dy
        Ss = S @ dy
        sizing = jnp.minimum(1.0, jnp.abs(dy @ y_sharp) / jnp.maximum(jnp.abs(dy @ Ss), _TINY))
        w = y_sharp - sizing * Ss
        safe = jnp.where(jnp.abs(ys) > _TINY, ys, 1.0)
        S_new = sizing * S + (jnp.outer(w, y_full) + jnp.outer(y_full, w)) / safe
        S_new = S_new - (w @ dy) * jnp.outer(y_full, y_full) / safe**2
        S_new = jnp.where(jnp.abs(ys) > _TINY, S_new, sizing * S)

        dof = jnp.maximum(r.shape[0] - y.shape[0], 1)
        short = lambda dy, H, cost: (  # noqa: E731
            (dy @ H @ dy <= self.rtol**2 * cost / dof) | (self.norm(dy) <= self.atol)
        )
        tolerance = self.rtol**2 * cost_new / dof
        exact = ~accept & (jnp.abs(cost_new - cost) <= 64 * jnp.finfo(y.dtype).eps * cost)
        predicted = jnp.where(state.augmented, augmented, gauss_newton)
        stalled = ~accept & (jnp.maximum(predicted, jnp.abs(actual)) <= tolerance)
        done = jnp.where(
            fresh, cost_new == 0, (accept & short(dy, H, cost_new)) | exact | stalled | (cost == 0)
        )
        damping = jnp.where(
            accept,
            jnp.where(good, jnp.maximum(0.1 * state.damping, _MIN_DAMPING), state.damping),
            state.damping * state.growth,
        )
        damping = jnp.where(fresh, state.damping, damping)
        keep = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        Jt, r, g, cost = keep(Jt_new, Jt), keep(r_new, r), keep(g_new, g), keep(cost_new, cost)
        H, S = keep(Jt_new @ Jt_new.T, H), jnp.where(accept & ~fresh, S_new, S)
        model = ~fresh & (jnp.abs(actual - augmented) < jnp.abs(actual - gauss_newton))

        # the next trial, `(J^T J [+ S] + damping diag(J^T J)) dy = -J^T r`; one already short
        # after an accepted trial is taken without being evaluated, and the last (after a
        # rejection, the raised damping shortens it)
        diag = jnp.diagonal(H)
        diag = jnp.maximum(diag, jnp.finfo(y.dtype).eps * jnp.max(diag))
        A = jnp.where(model, H + S, H) + damping * jnp.diag(diag)
        dy_next = -_definite_solve(A, g[:, None])[:, 0]
        last = accept & short(dy_next, H, cost)
        state = _SecantLMState(
            residual=r,
            jacobian=Jt,
            normal=H,
            gradient=g,
            curvature=S,
            augmented=model,
            cost=cost,
            damping=damping,
            growth=jnp.where(accept, 10.0, 2.0 * state.growth),
            aux=jax.tree_util.tree_map(keep, aux_new, state.aux),
            step=dy_next,
            done=done | last,
            fresh=jnp.asarray(False),
        )
        return unravel(keep(y + dy, y) + jnp.where(last, dy_next, 0.0)), state, state.aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        return state.done, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, state, tags, result
        return y, aux, {}


class _RoundingTrustRegion(optx.ClassicalTrustRegion):
    """optimistix's trust region, which also accepts a trial that changed the loss by no more
    than its rounding (as `SecantLM`'s "exact" test). Its step size starts in the parameters'
    dtype: optimistix's starts as `jnp.array(1.0)`, float64 where x64 is on, and the damped
    system of a float32 problem then failed to solve (a float64 damping row)."""

    def init(self, y, f_info_struct):
        state = super().init(y, f_info_struct)
        dtype = jnp.result_type(*jax.tree_util.tree_leaves(y))
        return eqx.tree_at(lambda s: s.step_size, state, state.step_size.astype(dtype))

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, state = super().step(
            first_step, y, y_eval, f_info, f_eval_info, state
        )
        f, f_eval = f_info.as_min(), f_eval_info.as_min()
        rounding = jnp.abs(f_eval - f) <= 64 * jnp.finfo(f.dtype).eps * f
        return step_size, accept | rounding, result, state


class LevenbergMarquardt(optx.LevenbergMarquardt):
    """`optx.LevenbergMarquardt`, which also accepts a trial that changed the loss by its
    rounding only.

    At the optimum, trials win or lose by rounding alone, and optimistix's LM tests convergence
    on accepted steps only: it shrank the step until a trial happened to win. In a vmapped
    solve the slowest member sets the pace, so that cost every member: triangulating 1200
    points in 8 views with `refine=True` took 62 against 47 ms; a joint rig of 12 cameras, one
    hidden, 13 steps (7 lost to rounding) against 6.

    It takes `options={"model": model}` as `SecantLM` does (`_modelled`): with a robust loss its
    steps then linearise Ceres' model of the cost rather than the weighted residuals. Anchored
    rigs of 12 and 24 cameras with wild dots (`refine_rig`, matrix-free), `Huber(1.0)` 29 and 25
    steps against 31 and 36, `Cauchy(1.0)` 27 and 51 against 38 and 106, the same cameras;
    `calibrate_planar` in float32, 16 cameras of 40 views, 1 % wild: Huber 663 steps against
    875, Cauchy 805 against 1184.
    """

    def __init__(self, rtol, atol, linear_solver=None):
        linear_solver = lx.QR() if linear_solver is None else linear_solver
        super().__init__(rtol=rtol, atol=atol, linear_solver=linear_solver)
        self.search = _RoundingTrustRegion()

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return super().init(_modelled(fn, options), y, args, options, f_struct, aux_struct, tags)

    def step(self, fn, y, args, options, state, tags):
        return super().step(_modelled(fn, options), y, args, options, state, tags)


def takes_model(solver) -> bool:
    """Whether `solver` takes `options={"model": model}`: its steps then linearise Gauss–Newton's
    model of a robust cost (`_irls`) rather than `fn`, which stays the objective."""
    return isinstance(solver, (SecantLM, LevenbergMarquardt))


def _modelled(fn, options):
    """`fn`, or with `options={"model": model}` (as `SecantLM` takes it) the residuals whose
    linearisation is `model`'s and whose squares sum to its cost: `model`'s residuals, and one
    more held out of every derivative, `sqrt(cost - |residuals|^2)` (>= 0 for a concave loss,
    `rho(s) >= rho'(s) s`), an entry "rest" of a dict of residuals (`refine_rig`'s)."""
    model = options.get("model")
    if model is None:
        return fn

    def modelled(y, args):
        residuals, cost = model(y, args)
        rest = cost - sum(jnp.sum(r * r) for r in jax.tree_util.tree_leaves(residuals))
        rest = jax.lax.stop_gradient(jnp.sqrt(jnp.maximum(rest, 0.0)))
        if isinstance(residuals, dict):
            return {**residuals, "rest": rest}, None
        return (residuals, rest), None

    return modelled


def _eliminate(M, B, tol):
    """`(X, definite)`: `M X = B` for a square `M (n, n)` and `B (n, m)`, by Gauss–Jordan
    elimination without pivoting (which a definite matrix does not need), a loop of `n` rank-one
    updates of `[M | B]`, not LAPACK: under `vmap` jaxlib runs a batch of LAPACK factorisations
    through XLA's CPU thread pool, and a rig split over host devices deadlocked there
    (`docs/scaling.md`): each device's program held a worker and waited for sub-tasks queued
    behind the others'.

    A pivot no larger than `tol` in magnitude is dropped: its unknown is 0 and its row takes no
    part. In a positive semidefinite `M` that is where the matrix is singular to within `tol`
    (a pivot, the `D` of `M`'s `L D L^T`, is at least `M`'s smallest eigenvalue, and a zero
    pivot's row is zero), so that a singular system gets one of its solutions, finite, rather
    than `inf`. `definite`: whether every pivot was positive and none was dropped.
    """
    n = M.shape[-1]

    def eliminate(k, carry):
        A, definite = carry
        e = jax.nn.one_hot(k, n, dtype=A.dtype)
        row = e @ A
        pivot = row[:n] @ e
        kept = jnp.abs(pivot) > tol
        row = jnp.where(kept, row / jnp.where(kept, pivot, 1.0), 0.0)
        A = jnp.where(e[:, None] > 0, row, A - jnp.outer(A[:, :n] @ e, row))
        return A, definite & kept & (pivot > 0)

    A, definite = jax.lax.fori_loop(
        0, n, eliminate, (jnp.concatenate([M, B], axis=-1), jnp.asarray(True))
    )
    return A[:, n:], definite


def _spd_solve(M, B):
    """`M^-1 B` for a symmetric `M (n, n)` and `B (n, m)`; NaN unless `M` is positive definite
    (every pivot positive), by `_eliminate`."""
    X, definite = _eliminate(M, B, 0.0)
    return jnp.where(definite, X, jnp.nan)


class _Elimination(lx.AbstractLinearSolver):
    """Lineax's solver interface to `_eliminate`, for implicit derivatives where a batch of LAPACK
    calls can hang (`_adjoint`): pivots below `eps` times the largest diagonal entry are dropped,
    so that the singular system of a camera that sees nothing (a zero matrix) or of a point seen
    once gets a finite solution, where LU's is NaN, and the derivative through that problem's
    result, which is NaN, is zero. The matrices are small (one camera's parameters, or a point's
    three coordinates), materialised."""

    def init(self, operator, options):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("`_Elimination` solves square systems only")
        return operator.as_matrix()

    def compute(self, state, vector, options):
        del options
        flat, unravel = ravel_pytree(vector)
        tol = jnp.finfo(state.dtype).eps * jnp.max(jnp.abs(jnp.diagonal(state)))
        x = _eliminate(state, flat[:, None], tol)[0][:, 0]
        return unravel(x.astype(flat.dtype)), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        return state.T, options

    def conj(self, state, options):
        return state.conj(), options

    def assume_full_rank(self):
        return False


def _definite_solve(M, B):
    """`M^-1 B` for a symmetric `M (n, n)` and `B (n, m)`, NaN unless `M` is positive definite:
    by LAPACK's Cholesky, or by `_spd_solve` where a batch of LAPACK calls can deadlock (several
    CPU devices), at the price of a slower solve there."""
    if _sharding.batched_lapack_may_hang():
        return _spd_solve(M, B)
    return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(M), True), B)


def _tree_fn(fn, unravel):
    """`fn` of a flat vector, for a `fn` of the pytree that `unravel` rebuilds."""
    return lambda y_flat, args: fn(unravel(y_flat), args)


_TINY = 1e-300
_MIN_DAMPING = 1e-12  # relative to diag(J^T J); below it the damping is lost in rounding


# ------------------------------------------------------------------------------ result
class Refinement(eqx.Module):
    """The result of `refine`.

    - `cameras`: the refined cameras (with distortion).
    - `rms_before`, `rms_after`: reprojection RMS per camera (pixels) of the seed and the result,
      over the visible points.
    - `report`: Table I of the refined cameras.
    - `iterations`: Levenberg–Marquardt steps per camera.
    - `result`: optimistix's outcome per camera, as the integer index of an `optx.RESULTS` member
      (0 = successful), or -1 where the camera has too few visible points for the free
      parameters, -2 where its seed is not finite (e.g. a camera `calibrate` could not solve),
      -3 where `solve_pnp` found the pose fitting poorly; its camera is then NaN. `ok` is
      `result == 0`, `messages()` spells them out.
    - `inliers`: `(..., N)` visible points whose final residual is within 3 `loss.scale` (all
      visible points without a robust loss).
    - `covariance`: `(..., P, P)` covariance of the parameters named in `parameter_names` (the
      free ones, and alpha_u where `fix="aspect_ratio"` ties it to alpha_v: alpha_v's row and
      column times the ratio, so that the matrix is singular), from the Jacobian at the optimum
      scaled by the residual variance (with a
      robust loss, Huber's M-estimate of it, which the wild points' bounded pull enters and
      their size does not: `residual_variance`).
    - `standard_errors`: `(..., P)` square roots of its diagonal; `std(name)` picks one.
    """

    cameras: Camera
    rms_before: Float[Array, "*batch"]
    rms_after: Float[Array, "*batch"]
    report: ReprojectionReport
    iterations: Int[Array, "*batch"]
    result: Int[Array, "*batch"]
    inliers: Bool[Array, "*batch N"]
    covariance: Float[Array, "*batch P P"]
    standard_errors: Float[Array, "*batch P"]
    parameter_names: tuple[str, ...] = eqx.field(static=True)

    @property
    def ok(self) -> Bool[Array, "*batch"]:
        return self.result == 0

    def std(self, name: str) -> Float[Array, "*batch"]:
        """The standard error of one parameter (e.g. `"alpha_u"`, `"k1"`, `"rx"` in radians)."""
        if name not in self.parameter_names:
            raise KeyError(f"{name!r} was not refined; refined: {self.parameter_names}")
        return self.standard_errors[..., self.parameter_names.index(name)]

    def messages(self) -> list[str]:
        return [_RESULT_MESSAGES[int(r)] for r in np.asarray(self.result).reshape(-1)]


TOO_FEW_POINTS = -1
NOT_FINITE_SEED = -2
POOR_FIT = -3  # (`solve_pnp`'s check of its poses)


def _result_messages() -> dict[int, str]:
    items = optx.RESULTS._name_to_item  # noqa: SLF001 (the enumeration's public view is by member)
    messages = {int(item._value): optx.RESULTS[item] or "successful" for item in items.values()}  # noqa: SLF001
    # optimistix speaks of root-finds; the likely cause here is a camera the points do not pin
    # down, whose parameters drift along a flat valley of the reprojection error
    for name in ("max_steps_reached", "nonlinear_max_steps_reached"):
        messages[int(getattr(optx.RESULTS, name)._value)] = (  # noqa: SLF001
            "not converged within `max_steps`: the points may not determine the free parameters "
            "(e.g. one view of a plane with free intrinsics: large standard errors tell; hold "
            "some with `fix=`, or add views), else raise `max_steps`"
        )
    messages[TOO_FEW_POINTS] = (
        "too few visible points for the free parameters (`solve_pnp`: for the closed form, 4 of "
        "a plane, 6 of a 3-D target): not refined"
    )
    messages[POOR_FIT] = (
        "the pose fits its points (those a robust loss keeps) with an RMS above "
        "`max_relative_rms` of their spread: a wrong correspondence (a robust loss sets it "
        "aside), or the wrong camera"
    )
    messages[NOT_FINITE_SEED] = (
        "the seed has a non-finite parameter (a camera `calibrate` could not solve is NaN; in "
        "`solve_pnp`, a view whose points gave no closed-form pose): not refined"
    )
    return messages


_RESULT_MESSAGES = _result_messages()


# ------------------------------------------------------------------------------ the kernel
def _pack(cam: Camera):
    zero = jnp.zeros(3, cam.t.dtype)
    head = jnp.stack([cam.alpha_u, cam.alpha_v, cam.u0, cam.v0, cam.skew])
    return jnp.concatenate([head, zero, cam.t, cam.dist])


def _unpack(p, R0) -> Camera:
    # The rotation is a small axis-angle increment applied to the seed's R: minimal (3 numbers),
    # well away from the singularities of any global parametrisation, and exactly R0 at 0.
    R = jnp.stack([jnp.stack(row, -1) for row in exp_and_left_jacobian(p[5:8], R0)[0]], -2)
    return Camera(p[0], p[1], p[2], p[3], R, p[8:11], skew=p[4], dist=p[11:], lens=lens_of(p[11:]))


@jax.custom_jvp
def _pixels(p, R0, world):
    """`_unpack(p, R0).project(world)` for one camera, `(N, 2)`, with the derivative in `p` written
    out (`_pixel_jacobian`): forward-mode autodiff through `project` costs about twice as much,
    and the solver needs that Jacobian at every step."""
    return _unpack(p, R0).project(world)


@functools.partial(_pixels.defjvp, symbolic_zeros=True)
def _pixels_jvp(primals, tangents):
    p, R0, world = primals
    dp, dR0, dworld = tangents
    out = _pixels(p, R0, world)
    zero = jax.custom_derivatives.SymbolicZero
    d = jnp.zeros_like(out) if type(dp) is zero else _pixel_jacobian(p, R0, world) @ dp
    if type(dR0) is not zero or type(dworld) is not zero:  # the data's tangents, by autodiff
        dR0, dworld = (jnp.zeros(t.shape, t.dtype) if type(t) is zero else t for t in (dR0, dworld))
        project = lambda R0, world: _unpack(p, R0).project(world)  # noqa: E731
        d = d + jax.jvp(project, (R0, world), (dR0, dworld))[1]
    return out, d


def _pixel_jacobian(p, R0, world):
    """`d _pixels / d p`, `(N, 2, 16)`."""
    return jnp.stack([jnp.stack(c, -1) for c in _pixel_columns(p, R0, world)[0]], -1)


def _pixel_columns(p, R0, world, mask=None):
    """`d _pixels / d p` as 16 columns (15 for a fisheye) `(du / dp_k, dv / dp_k)`, each `(N,)`:
    the chain rule of `Camera.project`, entry by entry, through the lens (`_pinhole_columns`,
    `_fisheye_columns`); and `d _pixels / d world` as rows `[du / dX_j]`, `[dv / dX_j]` (unused
    entries cost nothing: XLA drops them). With a `mask`, hidden points are taken on the optical
    axis, so that whatever their coordinates, nothing is NaN."""
    au, av, s = p[0], p[1], p[4]
    R, J = exp_and_left_jacobian(p[5:8], R0)
    X = [world[:, i] for i in range(3)]
    m = [R[i][0] * X[0] + R[i][1] * X[1] + R[i][2] * X[2] for i in range(3)]  # R X
    xc = [m[i] + p[8 + i] for i in range(3)]
    if mask is not None:
        xc = [jnp.where(mask, c, float(i == 2)) for i, c in enumerate(xc)]
    if lens_of(p[11:]) == "fisheye":
        xd, yd, dxy_dc, dxd, dyd = _fisheye_columns(xc, p[11:])
        duv_dc = [[au * a + s * b for a, b in zip(*dxy_dc)], [av * b for b in dxy_dc[1]]]
    else:
        xd, yd, duv_dc, dxd, dyd = _pinhole_columns(xc, p[11:], au, av, s)
    zero, one = jnp.zeros_like(xd), jnp.ones_like(xd)
    columns = [(xd, zero), (zero, yd), (one, zero), (zero, one), (yd, zero)]
    # rotation increments: d(u, v) / d w_k = g . ((J e_k) x m) = (J e_k) . (m x g), g a row of
    # duv_dc (XLA computes each m x g once)
    J = [[row[k] for row in J] for k in range(3)]  # its columns
    columns += [tuple(_small.triple(J[k], m, g) for g in duv_dc) for k in range(3)]
    columns += [(duv_dc[0][k], duv_dc[1][k]) for k in range(3)]  # translation
    columns += [(au * a + s * b, av * b) for a, b in zip(dxd, dyd)]  # distortion
    world_rows = [[sum(g[i] * R[i][j] for i in range(3)) for j in range(3)] for g in duv_dc]
    return columns, world_rows


def _pinhole_columns(xc, dist, au, av, s):
    """The pinhole lens in `_pixel_columns`: `(x_d, y_d)`, `d(u, v) / d(camera coordinates)` and
    `d(x_d, y_d) / d(k1, k2, p1, p2, k3)`."""
    k1, k2, p1, p2, k3 = (dist[i] for i in range(5))
    x, y = xc[0] / xc[2], xc[1] / xc[2]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    xy2 = 2.0 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
    # d(xd, yd) / d(x, y), then d(u, v) / d(x, y) and d(u, v) / d(camera coordinates)
    cross = xy2 * dradial + 2.0 * (p1 * x + p2 * y)
    dxd_dx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    dyd_dy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    duv_dxy = [[au * dxd_dx + s * cross, au * cross + s * dyd_dy], [av * cross, av * dyd_dy]]
    # Divisions, not products with 1 / z: XLA fuses cheap operations into every consumer,
    # recomputing them per column, but computes an expensive one (a division) once, to memory.
    duv_dc = [[a / xc[2], b / xc[2], -(a * x + b * y) / xc[2]] for a, b in duv_dxy]
    r4 = r2 * r2
    dxd = [x * r2, x * r4, 2.0 * x * y, r2 + 2.0 * x * x, x * r4 * r2]  # d xd / d(k1..k3)
    dyd = [y * r2, y * r4, r2 + 2.0 * y * y, 2.0 * x * y, y * r4 * r2]
    return xd, yd, duv_dc, dxd, dyd


def _fisheye_columns(xc, dist):
    """The fisheye lens in `_pixel_columns`: `(x_d, y_d)`, `d(x_d, y_d) / d(X, Y, Z)` (two rows of
    three) and `d(x_d, y_d) / d(k1, k2, k3, k4)`. With `s = theta_d / rho`, `x_d = s X`:
    `d s / d Z = -theta_d' / |x_cam|^2` and `(d s / d rho) / rho` (its limit on the axis,
    `2 (k1 - 1/3) / Z^3`, from the series of `theta_d / rho`)."""
    X, Y, Z = xc
    r2 = X * X + Y * Y
    on_axis = r2 == 0
    rho = jnp.sqrt(jnp.where(on_axis, 1.0, r2))
    theta = jnp.arctan2(rho, Z)
    theta_d, slope = _fisheye_polynomial(theta, dist)
    q2 = r2 + Z * Z
    scale = jnp.where(on_axis, 1.0 / Z, theta_d / rho)
    by_rho = jnp.where(
        on_axis, 2.0 * (dist[0] - 1.0 / 3.0) / Z**3, (slope * Z * rho / q2 - theta_d) / (rho * r2)
    )
    by_z = -slope / q2
    xy = X * Y * by_rho
    dxy_dc = [[scale + X * X * by_rho, xy, X * by_z], [xy, scale + Y * Y * by_rho, Y * by_z]]
    t2 = theta * theta
    powers = [theta * t2]
    for _ in range(3):
        powers.append(powers[-1] * t2)
    unit_x, unit_y = X / rho, Y / rho  # zero on the axis, where every power is zero too
    return X * scale, Y * scale, dxy_dc, [unit_x * q for q in powers], [unit_y * q for q in powers]


def residual_variance(r, mask, loss, n_parameters):
    """The variance `sigma^2` of a fit with `loss`, for its covariance `sigma^2 A^-1` (A the
    Hessian of its cost as Gauss–Newton models it, `sum_i rho'(s_i) J_i^T J_i`).

    For least squares `sum |r_i|^2 / (2 n - p)`. For a robust loss, Huber's M-estimate (Robust
    Statistics, 1981, eq. 7.6.9) in that form: `sum |psi_i|^2 / (2 n - p) * mean(w) /
    mean(psi')^2`, with `psi_i = rho'(s_i) r_i` a point's pull on the fit, `w_i = rho'(s_i)` its
    weight in A and `psi'_i = rho'(s_i) + s_i rho''(s_i)` the mean slope of its pull (zero for
    a point beyond Huber's scale, whose pull is constant). The cost over `2 n - p`, as before,
    counted a wild point's `rho` (Huber: 2 scale |r|): standard errors 2-3 times the errors
    with 5-10 % wild points (focal lengths of 200 cameras: std of the z-scores 0.3-0.4).

    `r (..., N, 2)` the points' residuals, `mask (..., N)` those fitted."""
    s = jnp.where(mask, jnp.sum(r * r, -1), 0.0)
    if loss is None:
        return jnp.sum(s) / jnp.maximum(2 * jnp.sum(mask) - n_parameters, 1)
    flat = s.reshape(-1)
    w = jax.vmap(jax.grad(loss.rho))(flat).reshape(s.shape)
    slope = w + s * jax.vmap(jax.grad(jax.grad(loss.rho)))(flat).reshape(s.shape)
    n = jnp.maximum(jnp.sum(mask), 1)
    mean = lambda x: jnp.sum(jnp.where(mask, x, 0.0)) / n  # noqa: E731
    pull = jnp.sum(jnp.where(mask, w * w * s, 0.0))
    return pull / jnp.maximum(2 * n - n_parameters, 1) * mean(w) / mean(slope) ** 2


def _irls(loss, s):
    """`(sqrt(rho'(s)), rho(s))` for squared residual lengths `s`: Gauss–Newton's model of a
    robust cost, as Ceres builds it for losses whose `rho'' <= 0` (Huber's, Cauchy's). A point's
    rows and residual are scaled by `sqrt(rho')`, which gives the cost's gradient, and its
    Hessian without the `rho''` term; the cost itself is `rho`."""
    drho = jax.vmap(jax.grad(loss.rho))(s.reshape(-1)).reshape(s.shape)
    return jnp.sqrt(drho), loss.rho(s)


def _robust_residuals(r, loss):
    """Points' residuals `r (..., 2)` weighted so that their squares sum to the robust cost
    (`_robust_weights`): the objective, as least squares sees it."""
    return r * _robust_weights(loss, jnp.sum(r * r, axis=-1))[..., None]


def _robust_model(r, loss):
    """Points' residuals `r (..., 2)` for `SecantLM`'s `options["model"]`: scaled by `sqrt(rho')`
    (`_irls`), held out of their derivative; and the cost."""
    w, rho = _irls(loss, jnp.sum(r * r, axis=-1))
    return r * jax.lax.stop_gradient(w)[..., None], jnp.sum(rho)


def _robust_rows(rows, r, loss):
    """The rows `(d r_u, d r_v)` of `w(|r|^2) r` from those of `r (N, 2)`, point by point:
    `d (w r) = w dr + r w'(|r|^2) 2 r^T dr`."""
    if loss is None:
        return rows
    s = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1]
    w = _robust_weights(loss, s)
    dw = jax.vmap(jax.grad(lambda s: _robust_weights(loss, s)))(s)
    return [[w * d + 2.0 * dw * r[:, c] * (r[:, 0] * du + r[:, 1] * dv)
             for c, d in enumerate((du, dv))] for du, dv in rows]  # fmt: skip


def _scales(p0):
    """Natural units per parameter, so that Levenberg–Marquardt sees a well-scaled problem:
    pixels of focal length for the intrinsics, radians, the camera's distance, unit distortion."""
    f = jnp.abs(p0[0])
    d = jnp.linalg.norm(p0[8:11])
    one = jnp.ones((), p0.dtype)
    return jnp.stack([f] * 5 + [one] * 3 + [d] * 3 + [one] * (p0.shape[0] - 11))


class Free(tuple):
    """Indices into `parameter_names(lens)` of the parameters a solve estimates (a tuple, as
    static as one), and whether alpha_u is `tied` to alpha_v at the seed's ratio
    (`fix="aspect_ratio"`, OpenCV's CALIB_FIX_ASPECT_RATIO). Tied, alpha_u is no parameter of its
    own: `_parameters` sets it to `ratio * alpha_v`, `ratio = alpha_u / alpha_v` of the seed
    `p0`, and alpha_v's Jacobian column is `d/d alpha_v + ratio d/d alpha_u` (`_tied_columns`),
    the chain rule. Untied it equals (and hashes as) its tuple; tied, only a `Free` tied alike
    (a compiled program's key)."""

    tied: bool

    def __new__(cls, indices=(), tied: bool = False):
        out = super().__new__(cls, indices)
        out.tied = bool(tied)
        return out

    def __eq__(self, other):
        if not isinstance(other, tuple):
            return NotImplemented
        return tuple(self) == tuple(other) and self.tied == getattr(other, "tied", False)

    def __ne__(self, other):
        equal = self.__eq__(other)
        return equal if equal is NotImplemented else not equal

    def __hash__(self):
        return hash((tuple(self), True)) if self.tied else hash(tuple(self))

    def __repr__(self):
        return f"Free({tuple(self)!r}, tied={self.tied})"

    def __reduce__(self):
        return Free, (tuple(self), self.tied)

    @property
    def reported(self) -> tuple[int, ...]:
        """The parameters whose covariance a result reports: the free ones, and alpha_u where it
        is tied to alpha_v (`reported_covariance`)."""
        return tuple(sorted({*self, 0})) if self.tied else tuple(self)


def _ratio(p0):
    """The seed's aspect ratio alpha_u / alpha_v of packed parameters `(..., P)`."""
    return p0[..., 0] / p0[..., 1]


def _parameters(y, p0, scale, free):
    """The packed parameters: the seed's, with the increments `y` (natural units) on the `free`
    entries (a tuple), by a one-hot product rather than a scatter (cheaper under jacfwd's vmap);
    alpha_u the seed's ratio times alpha_v where `free.tied` (`Free`)."""
    one_hot = jax.nn.one_hot(jnp.asarray(free), p0.shape[0], dtype=y.dtype)
    p = p0 + (y @ one_hot) * scale
    if getattr(free, "tied", False):
        first = jax.nn.one_hot(0, p0.shape[0], dtype=p.dtype)
        p = p + first * (_ratio(p0) * p[1] - p[0])
    return p


def _tied_columns(columns, p0, free):
    """`_pixel_columns`' columns `d(u, v) / d p_k` as the free parameters see them: where
    `free.tied`, alpha_u follows alpha_v (`Free`), so that alpha_v's column takes alpha_u's times
    the seed's ratio, and alpha_u's, which moves nothing, is zero."""
    if not getattr(free, "tied", False):
        return columns
    ratio = _ratio(p0)
    both = tuple(a + ratio * b for a, b in zip(columns[1], columns[0]))
    return [tuple(jnp.zeros_like(d) for d in columns[0]), both, *columns[2:]]


def reported_covariance(cov, free, p0):
    """The covariance `(..., R, R)` of the reported parameters (`Free.reported`) from that of the
    free ones `cov (..., P, P)`: itself, or where alpha_u is tied to alpha_v, with alpha_u's row
    and column first, alpha_v's times the seed's ratio (`p0 (..., P)`): `A cov A^T`."""
    if not getattr(free, "tied", False):
        return cov
    v = free.index(1)  # alpha_v's
    rows = [jax.nn.one_hot(v, len(free), dtype=cov.dtype)]
    rows += [jax.nn.one_hot(i, len(free), dtype=cov.dtype) for i in range(len(free))]
    A = jnp.stack(rows)
    ratio = _ratio(p0)[..., None, None]
    A = jnp.where((jnp.arange(len(rows)) == 0)[:, None], ratio * A, A)  # (..., R, P)
    return A @ cov @ jnp.swapaxes(A, -1, -2)


# (Both are traced once and called where needed: the solver evaluates them in its loop and
# optimistix for the implicit derivatives, and under `vmap` the loop's body is batched more than
# once.)
@functools.partial(jax.jit, static_argnames="free")
def _residuals(y, args, free):
    """The (robustly weighted) residuals `(2, N)`: all u, then all v (one array per coordinate,
    as the Jacobian's columns are built)."""
    p0, R0, scale, world, pixels, mask, loss = args
    p = _parameters(y, p0, scale, free)
    r = jnp.where(mask[:, None], _pixels(p, R0, world) - pixels, 0.0).T
    if loss is None:
        return r
    return r * _robust_weights(loss, r[0] * r[0] + r[1] * r[1])


@functools.partial(jax.jit, static_argnames="free")
def _model(y, args, free):
    """Gauss–Newton's model of the robust cost (`_irls`, `SecantLM`'s `options["model"]`): the
    residuals `(2, N)` scaled by `sqrt(rho')`, and the cost."""
    p0, R0, scale, world, pixels, mask, loss = args
    p = _parameters(y, p0, scale, free)
    r = jnp.where(mask[:, None], _pixels(p, R0, world) - pixels, 0.0).T
    w, rho = _irls(loss, r[0] * r[0] + r[1] * r[1])
    return r * w, jnp.sum(rho)


@functools.partial(jax.jit, static_argnames=("free", "irls"))
def _residual_jacobian_t(y, args, free, irls=False):
    """`d _residuals / d y` transposed, `(P, 2 N)`, one row per free parameter, from the
    written-out `_pixel_columns` (under `jax.jacfwd` the custom JVP would also multiply by the
    identity of the tangents); only the free rows are built, each as one array over the points.
    Rows rather than columns: the solver's `J^T J` and `J^T r` then contract contiguous rows
    (on a CPU 4.6 against 6.3 µs a camera for `J^T J`, 0.9 against 2.4 for `J^T r`). With
    `irls`, the rows of `_model`'s residuals instead (the pixels' rows scaled by `sqrt(rho')`)."""
    p0, R0, scale, world, pixels, mask, loss = args
    p = _parameters(y, p0, scale, free)
    columns = _tied_columns(_pixel_columns(p, R0, world)[0], p0, free)
    rows = [[jnp.where(mask, d, 0.0) * scale[k] for d in columns[k]] for k in free]
    if loss is not None:
        r = jnp.where(mask[:, None], _pixels(p, R0, world) - pixels, 0.0)
        if irls:
            w = _irls(loss, r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1])[0]
            rows = [[w * d for d in row] for row in rows]
        else:
            rows = _robust_rows(rows, r, loss)
    # one concatenation of (1, N) pieces, u and v of each row in turn: under vmap `jnp.stack`
    # would put the cameras second and XLA would transpose the Jacobian at every step
    return jnp.concatenate([d.reshape(1, -1) for row in rows for d in row]).reshape(len(rows), -1)


def _arguments(cam, world, pixels, mask, loss):
    """The `args` of `_residuals` and `_residual_jacobian_t` for one camera: the packed seed,
    its rotation, the parameters' scales, the points and pixels, the mask and the loss. Hidden
    points are replaced before any arithmetic, so that NaN there reaches neither result nor
    gradient."""
    world = jnp.where(mask[:, None], world, 0.0)
    pixels = jnp.where(mask[:, None], pixels, 0.0)
    p0 = _pack(cam)
    return p0, cam.R, _scales(p0), world, pixels, mask, loss


def _refine_one(cam, world, pixels, mask, y, steps, result, kept, *, free, loss, options):
    """One camera's answer from the solution `y` of its problem (`solve_each`): the refined
    camera, RMS before and after, steps, outcome, inliers, covariance, standard errors and the
    residuals."""
    args = _arguments(cam, world, pixels, mask, loss)
    p0, _, scale, world, pixels, _, _ = args
    residuals = functools.partial(_residuals, free=free)
    refined = _unpack(_parameters(y, p0, scale, free), cam.R)

    # Covariance of the free parameters: sigma^2 (J^T J)^-1 with J the Jacobian of the
    # (robustly weighted) residuals at the optimum, in the parameters' own units; sigma^2 from
    # the points' own residuals (`residual_variance`).
    model = functools.partial(_model, free=free)
    held = (lambda y, args: model(y, args)[0]) if "model" in options else residuals  # noqa: E731
    jacobian_t = functools.partial(_residual_jacobian_t, free=free, irls="model" in options)
    _, Jt = _at_optimum(held, jacobian_t, y, args, kept)
    Jt = Jt / scale[jnp.asarray(free), None]  # dr/dp, transposed
    n_obs = 2 * jnp.sum(mask)
    raw = jnp.where(mask[:, None], refined.project(world) - pixels, 0.0)
    sigma2 = residual_variance(raw, mask, loss, len(free))
    H = Jt @ Jt.T
    cov = sigma2 * _definite_solve(H, jnp.eye(H.shape[0], dtype=H.dtype))
    cov = reported_covariance(cov, free, p0)  # (alpha_u's too where it is tied)

    residual_length = jnp.linalg.norm(raw, axis=-1)
    threshold = jnp.inf if loss is None else 3.0 * loss.scale
    inliers = mask & (residual_length <= threshold)
    enough = n_obs > len(free)
    refined = jax.tree_util.tree_map(lambda x: jnp.where(enough, x, jnp.nan), refined)
    raw = jnp.where(enough, raw, jnp.nan)  # (those of the NaN camera)
    result = jnp.where(enough, result, TOO_FEW_POINTS)
    # (the refined camera's residuals, `raw`, give its RMS and, in `_refine_all`, its Table I:
    # projected once, not three times)
    return (
        refined, masked_rms(cam, world, pixels, mask), residual_rms(raw, mask), steps, result,
        inliers, cov, jnp.sqrt(jnp.diagonal(cov)), raw,
    )  # fmt: skip


def _at_optimum(residuals, jacobian_t, y, args, kept):
    """The flat residuals and their transposed Jacobian at the solution `y`: from `SecantLM`'s
    final state (`kept`, `_kept`), which holds them at that point or, where its last trial was
    taken unevaluated, at the point that trial left, within `rtol` standard errors (computing
    them again would put a second copy of the Jacobian into the compiled program, a third of its
    size), and differentiated as `residuals(y, args)` and `jacobian_t(y, args)` are."""
    if kept is None:
        return residuals(y, args).reshape(-1), jacobian_t(y, args)
    return _held(functools.partial(_residuals_and_jacobian, residuals, jacobian_t), y, args,
                 kept)  # fmt: skip


def _kept(y, state):
    """What `solve_each` keeps of a solver's final state for `_at_optimum`: `SecantLM`'s
    residuals and Jacobian."""
    del y
    if isinstance(state, _SecantLMState):
        return state.residual, state.jacobian
    return None


def _residuals_and_jacobian(residuals, jacobian_t, y, args):
    return residuals(y, args).reshape(-1), jacobian_t(y, args)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _held(fn, y, args, value):
    """`value`, which equals `fn(y, args)`, with the derivative of `fn(y, args)`."""
    del y, args
    return value


@_held.defjvp
def _held_jvp(fn, primals, tangents):
    y, args, value = primals
    dy, dargs, _ = tangents
    return value, jax.jvp(fn, (y, args), (dy, dargs))[1]


def _adjoint() -> optx.ImplicitAdjoint:
    """Implicit derivatives by a pseudo-inverse (SVD): a camera with too few points (none, where
    its seed is not finite) has a singular system, on which optimistix's default solve (LU)
    raised for the whole batch; its result is NaN, and its derivative zero.

    The pseudo-inverse drops singular values below `eps` of the largest (`rcond=-1`), not
    Lineax's default `2 eps n`: the system is the Hessian, whose condition is the Jacobian's
    squared, and a pinhole's distortion directions lie near `1e-6` of its largest singular value.
    In float32, `2 eps n` (3.6e-6) dropped them: the gradient of a refined camera's centre with
    respect to its pixels came out 73-78 % off float64's, signs flipped (a user's trial); with
    `eps`, 0.1-0.5 %, as LU gives.

    Where a batch of LAPACK calls can hang (several CPU devices) the batched SVD did (64 cameras
    split over 2 host devices, under `jax.grad`), and LAPACK's LU, which did not there, raised for
    a camera that saw nothing (a user's trial): the systems are solved there by `_Elimination`,
    without LAPACK, which drops the pivots of a singular system."""
    if _sharding.batched_lapack_may_hang():
        return optx.ImplicitAdjoint(linear_solver=_Elimination())
    return optx.ImplicitAdjoint(linear_solver=lx.SVD(rcond=-1.0))


SLOTS = 32  # problems stepped side by side on one CPU device (`solve_each`)


def slots(n_problems: int, alone: bool = False) -> int:
    """How many of `n_problems` independent solves `solve_each` steps side by side: on one CPU
    device `SLOTS`, each slot given the next problem as soon as its own has converged, or one
    (`alone`: the programs `refine` runs side by side, one per core, when called from Python,
    which must not batch LAPACK's calls, `_sharding.batched_lapack_may_hang`); elsewhere all of
    them at once (accelerators want the batch, and an axis split over devices must stay one)."""
    size = _sharding.cpu_chunk(n_problems, 1 if alone else SLOTS)
    return n_problems if size is None else size


def _no_aux(fn):
    return lambda y, args: (fn(y, args), None)


def solve_each(
    fn, solver, y0, args, options, *, max_steps, size, keep=None, finish=None, extra=None
):
    """`optx.least_squares(fn, solver, y0, args[i], options)` for every problem `i` of `args`
    (batched along its leading axis), as a work queue: `size` problems take a step side by side
    (vmapped; `slots`), and a slot whose problem has ended (converged, failed, or at
    `max_steps`) takes the next problem at the following step.

    A vmapped loop of solves runs every problem until the slowest has converged; one problem at
    a time runs each step's ~100 small kernels for one camera. Measured (`jax.jit(mc.refine)`,
    warm, 2026-12-07, 2 cores, the versions alternated in one process): 256 cameras of 108
    points (the refine benchmark, 2,074 steps) 31.4 ms in 32 slots against 38.3 one camera at a
    time and 37.5 in vmapped chunks of 16 (39.1 against 55.7 in a slower hour); 1024 of 19
    points 69 against 115 and 92 ms. The price: the caller's trace and compile take ~0.3 s
    longer each (the step vmapped). A problem's answer is the same to the last bit whichever
    slot it ran in, so a rig's cameras depend neither on their order nor on the rest of the
    rig.

    `fn(y, args_i)` returns the residuals of problem `i` (no aux) from `y0`, the start of every
    problem; `solver` is an optimistix least-squares solver (not a minimiser). Returns, for each
    problem, `finish(extra_i, y, steps, result, kept)` (by default that tuple without `extra_i`,
    problem `i`'s entries of `extra`, a pytree batched as `args` is):
    its solution, with the derivatives of the implicit function theorem (`implicit`: the loop
    itself is not differentiated), the number of steps (one evaluation each, as
    `optx.least_squares` counts them), the integer value of its `optx.RESULTS` outcome, and
    `keep(y, final_state)`. With `size` 1, one problem after another, each solved and finished
    in one step of a loop over them (LAPACK's calls unbatched)."""
    finish = (lambda extra_i, *out: out) if finish is None else finish
    solution = functools.partial(implicit, fn)
    n = jax.tree_util.tree_leaves(args)[0].shape[0]
    queue = size < n  # (else every slot keeps its problem: a vmapped solve)
    keep = (lambda y, state: None) if keep is None else keep
    fn = _no_aux(fn)
    tags = frozenset()
    first = jax.tree_util.tree_map(lambda x: x[0], args)
    f_struct = jax.eval_shape(fn, y0, first)[0]
    state = solver.init(fn, y0, first, options, f_struct, None, tags)
    static = eqx.partition(state, eqx.is_array)[1]
    kept = jax.tree_util.tree_map(jnp.zeros_like, keep(y0, state))  # (its shapes, as zeros)
    done_code = optx.RESULTS.successful._value  # noqa: SLF001
    at_max = optx.RESULTS.nonlinear_max_steps_reached._value  # noqa: SLF001

    def finite(y):
        return jnp.all(jnp.array([jnp.isfinite(x).all() for x in jax.tree_util.tree_leaves(y)]))

    def take(index):
        return jax.tree_util.tree_map(lambda x: x[jnp.minimum(index, n - 1)], args)

    def init(args_i):
        state = solver.init(fn, y0, args_i, options, f_struct, None, tags)
        return eqx.partition(state, eqx.is_array)[0]

    def advance(y, args_i, dynamic):  # `optx.least_squares`'s loop body
        state = eqx.combine(dynamic, static)
        y_new, state, _ = solver.step(fn, y, args_i, options, state, tags)
        stop, result = solver.terminate(fn, y, args_i, options, state, tags)
        result = optx.RESULTS.where(finite(y), result, optx.RESULTS.nonfinite)  # (y before it)
        return y_new, state, stop, result

    def answer(y, args_i, state, result):  # its `postprocess`, and what is kept of the state
        y = solver.postprocess(fn, y, None, args_i, options, state, tags, result)[0]
        return y, keep(y, state)

    def step(y, args_i, dynamic):
        y, state, stop, result = advance(y, args_i, dynamic)
        dynamic = eqx.partition(state, eqx.is_array)[0]
        return y, dynamic, stop, result._value, *answer(y, args_i, state, result)  # noqa: SLF001

    if size == 1:  # one problem after another, each its own loop

        def alone(inputs):
            args_i, extra_i = inputs
            fixed = jax.lax.stop_gradient(args_i)

            def body(carry):  # (`optx.least_squares`'s loop: the state carried once)
                y, dynamic, steps, _, _ = carry
                y, state, stop, result = advance(y, fixed, dynamic)
                stop = stop | (result != optx.RESULTS.successful)
                return y, eqx.partition(state, eqx.is_array)[0], steps + 1, stop, result

            zero = jnp.zeros((), jnp.int32)
            carry = (y0, init(fixed), zero, jnp.asarray(False), optx.RESULTS.successful)
            carry = jax.lax.while_loop(lambda c: ~c[3] & (c[2] < max_steps), body, carry)
            y, dynamic, steps, stop, result = carry
            result = optx.RESULTS.where(stop, result, optx.RESULTS.nonlinear_max_steps_reached)
            y, kept = answer(y, fixed, eqx.combine(dynamic, static), result)
            result = result._value  # noqa: SLF001
            return finish(extra_i, solution(y, args_i), steps, result, kept)

        return jax.lax.map(alone, (args, extra))

    def write(out, ended, problem, value):
        if queue:  # (an index of `n` is dropped)
            return out.at[jnp.where(ended, problem, n)].set(value, mode="drop")
        return jnp.where(ended.reshape((-1,) + (1,) * (out.ndim - 1)), value, out)

    def body(carry):
        problem, following, y, dynamic, steps, out = carry
        y, dynamic, stop, result, answer, kept = jax.vmap(step)(
            y, take(problem) if queue else args, dynamic
        )
        steps = steps + 1
        ended = (problem < n) & (stop | (result != done_code) | (steps >= max_steps))
        result = jnp.where(stop | (result != done_code), result, at_max)
        values = (answer, steps, result, kept)
        out = jax.tree_util.tree_map(lambda o, v: write(o, ended, problem, v), out, values)
        if not queue:
            return jnp.where(ended, n, problem), following, y, dynamic, steps, out
        # the ended slots take the next problems
        nxt = following + jnp.cumsum(ended) - 1
        problem = jnp.where(ended, jnp.where(nxt < n, nxt, n), problem)
        restart = lambda new, old: jnp.where(  # noqa: E731
            ended.reshape((-1,) + (1,) * (old.ndim - 1)), new, old
        )
        y = restart(jnp.broadcast_to(y0, y.shape), y)
        dynamic = jax.tree_util.tree_map(restart, jax.vmap(init)(take(problem)), dynamic)
        steps = jnp.where(ended, 0, steps)
        return problem, following + jnp.sum(ended), y, dynamic, steps, out

    args, differentiable = jax.lax.stop_gradient(args), args
    problem = jnp.arange(size)
    dynamic = jax.vmap(init)(take(problem) if queue else args)
    y = jnp.broadcast_to(y0, (size, *y0.shape))
    out = (
        jnp.zeros((n, *y0.shape), y0.dtype), jnp.zeros(n, jnp.int32), jnp.zeros(n, jnp.int32),
        jax.tree_util.tree_map(lambda x: jnp.zeros((n, *x.shape), x.dtype), kept),
    )  # fmt: skip
    carry = (problem, jnp.asarray(size), y, dynamic, jnp.zeros(size, jnp.int32), out)
    y, steps, result, kept = jax.lax.while_loop(lambda c: jnp.any(c[0] < n), body, carry)[-1]
    y = jax.vmap(solution)(y, differentiable)
    return jax.vmap(finish)(extra, y, steps, result, kept)


def _given(inputs):
    """`implicit`'s primal: the solution, found already."""
    return inputs[1], None


def _stationary(root, _, inputs):
    """The gradient of `0.5 |fn(y, args)|^2` at `root`, zero at a least-squares solution (the
    condition `optx.least_squares` differentiates implicitly)."""
    fn, _, args = inputs[:3]
    return jax.grad(lambda y: 0.5 * jnp.sum(fn(y, args) ** 2))(root)


def implicit(fn, y, args):
    """The least-squares solution `y` of `fn(., args)` (one problem), with the derivatives of
    the implicit function theorem with respect to `args`, as `optx.least_squares` gives them
    (`_adjoint`)."""
    inputs = (fn, jax.lax.stop_gradient(y), args)
    return _adjoint().apply(_given, _stationary, inputs, frozenset())[0]


@eqx.filter_jit
def _refine_batched(cameras, world, pixels, mask, free, loss, solver, max_steps, slotted):
    batch = cameras.batch_shape
    n = world.shape[-2]
    flat = lambda x, tail: jnp.broadcast_to(x, (*batch, *tail)).reshape(-1, *tail)  # noqa: E731
    cams = flat_rig(cameras)
    # a camera without a finite seed sees nothing (its problem ends at once), and is flagged
    cams, mask, usable = usable_rig(cams, flat(mask, (n,)), unit_camera(world.dtype, cams.lens))
    world, pixels = flat(world, (n, 3)), flat(pixels, (n, 2))
    args = jax.vmap(_arguments, (0, 0, 0, 0, None))(cams, world, pixels, mask, loss)
    residuals = functools.partial(_residuals, free=free)
    # with a loss, Gauss–Newton's model of the robust cost, as Ceres builds it (`_irls`);
    # `residuals` stay the objective (their squares sum to it) for the implicit derivatives
    modelled = loss is not None and takes_model(solver)
    options = {}
    if isinstance(solver, SecantLM):
        options["jacobian_transpose"] = functools.partial(
            _residual_jacobian_t, free=free, irls=modelled
        )
    if modelled:
        options["model"] = functools.partial(_model, free=free)
    y0 = jnp.zeros(len(free), world.dtype)
    kernel = functools.partial(_refine_one, free=free, loss=loss, options=options)
    out = solve_each(
        residuals, solver, y0, args, options, max_steps=max_steps,
        size=slots(len(mask), alone=not slotted), keep=_kept,
        finish=lambda inputs, *solved: kernel(*inputs, *solved), extra=(cams, world, pixels, mask),
    )  # fmt: skip
    refined, rms_before, rms_after, steps, result, *rest = out
    rms_before, rms_after = (jnp.where(usable, x, jnp.nan) for x in (rms_before, rms_after))
    result = jnp.where(usable, result, NOT_FINITE_SEED)
    out = (refined, rms_before, rms_after, steps, result, *rest)
    return jax.tree_util.tree_map(lambda x: x.reshape(*batch, *x.shape[1:]), out)


def _free_parameters(distortion, fix, skew, lens: str = "pinhole") -> Free:
    """Indices into `parameter_names(lens)` of the parameters to estimate (a `Free`, tied where
    `fix` names `"aspect_ratio"` and the focal lengths are not held: either one held holds both).
    `distortion=None` is the lens's `DEFAULT_DISTORTION`."""
    names = parameter_names(lens)
    coefficients = LENSES[lens]
    groups = {**GROUPS, "distortion": coefficients}
    given, constrained = ((fix,) if isinstance(fix, str) else fix), ()
    if isinstance(given, (tuple, list, set, frozenset)):
        constrained = tuple(n for n in given if n in CONSTRAINTS)
        fix = tuple(n for n in given if n not in CONSTRAINTS)

    def expand(given, what):
        if isinstance(given, str):
            given = (given,)
        if not isinstance(given, (tuple, list, set, frozenset)) or not all(
            isinstance(n, str) for n in given
        ):
            raise TypeError(
                f"`{what}` is a parameter's name or a sequence of names, e.g. ('k1', 'k2'); "
                f"got {given!r}."
            )
        offered = (coefficients, ("distortion",)) if what == "distortion" else (names, groups)
        out = []
        for name in given:
            if name in groups:
                out.extend(groups[name])
            elif name in names:
                out.append(name)
            else:
                groups_named = tuple(offered[1]) + (CONSTRAINTS if what == "fix" else ())
                raise ValueError(
                    f"unknown parameter {name!r} in `{what}` of a {lens} camera; use any of "
                    f"{offered[0]} or the groups {groups_named}."
                )
        return set(out)

    if distortion is None:
        distortion = DEFAULT_DISTORTION[lens]
    estimated = expand(distortion, "distortion")
    if not estimated <= set(coefficients):
        raise ValueError(
            f"`distortion` of a {lens} camera takes coefficients of {coefficients}; "
            f"got {distortion!r}."
        )
    fixed = expand(fix, "fix") | (set() if skew else {"skew"})
    fixed |= set(coefficients) - estimated
    focal = set(GROUPS["focal"])
    tied = bool(constrained) and not fixed & focal
    if constrained:  # alpha_u follows alpha_v (`Free`), or both are held
        fixed |= {"alpha_u"} if tied else focal
    return Free((i for i, name in enumerate(names) if name not in fixed), tied=tied)


def warn_held_coefficients(cameras: Camera, distortion, fix) -> None:
    """Warn where given cameras carry a distortion coefficient that the default `distortion`
    (`DEFAULT_DISTORTION`: no k3) leaves out and `fix` does not name: it is held at its value
    while the others are estimated, a lens model nobody asked for. An OpenCV user's trial:
    cameras from `cv2.calibrateCamera` (k3 0.32 and -0.12) as the start of a stereo pair with
    `fix="intrinsics"` (OpenCV's CALIB_FIX_INTRINSIC, they thought): k1 k2 p1 p2 moved, k3 did
    not, and the baseline came out 0.38 mm (0.3 %) from `cv2.stereoCalibrate`'s, nothing said.
    Concrete cameras only (inside a trace, nothing is said)."""
    if distortion is not None or not _validate.is_concrete(cameras.dist):
        return
    lens = cameras.lens
    named = set((fix,) if isinstance(fix, str) else tuple(fix))
    if "distortion" in named:
        return
    coefficients = LENSES[lens]
    left = [n for n in coefficients if n not in DEFAULT_DISTORTION[lens] and n not in named]
    dist = np.asarray(cameras.dist).reshape(-1, len(coefficients))
    for name in left:
        values = dist[:, coefficients.index(name)]
        which = np.flatnonzero(np.isfinite(values) & (values != 0))
        if which.size:
            listed = ", ".join(f"camera {c}: {values[c]:.3g}" for c in which[:4])
            more = f" and {which.size - 4} more" if which.size > 4 else ""
            warnings.warn(
                f"the given cameras' {name} ({listed}{more}) is held at its value while "
                f"{', '.join(DEFAULT_DISTORTION[lens])} are estimated: a mixed lens model. "
                f"Estimate it too (distortion={(*DEFAULT_DISTORTION[lens], name)}), or hold "
                "every coefficient as given (fix=('intrinsics', 'distortion') is OpenCV's "
                "CALIB_FIX_INTRINSIC); fix=" + repr(name) + " keeps it held and says nothing.",
                stacklevel=3,  # (the caller of `refine`, `refine_rig`, `calibrate_rig`)
            )


def _skew_model(cameras: Camera, skew: bool, fix, xp=jnp) -> Camera:
    """The seed of a zero-skew model (`skew=False`, the default: OpenCV's model) has zero skew:
    a seed with another value (the DLT's, noisy) has it set to zero, not held, unless `fix` names
    `"skew"` (then the seed's value is held). With `skew=True` it is estimated from the seed's."""
    held = "skew" in ((fix,) if isinstance(fix, str) else tuple(fix))
    if skew or held:
        return cameras
    return eqx.tree_at(lambda c: c.skew, cameras, xp.zeros_like(cameras.skew))


def default_solver(dtype) -> optx.AbstractLeastSquaresSolver:
    """`SecantLM` stopping at steps of 1e-5 standard errors (float64); optimistix's
    Levenberg–Marquardt stopping at steps of 1e-5 in the parameters' natural units (float32).

    On the refine benchmark (256 cameras, 14 parameters) `SecantLM` ends within 1e-13 (relative)
    of the RMS of a 1e-12 solve in at most 20 steps; optimistix's Gauss–Newton-based
    `LevenbergMarquardt` needs up to 98 steps for that and 65 for a 1e-6 tolerance. In float32
    the normal equations' squared condition number (~1e10 for k1, k2 against the focal length)
    is beyond the precision, so there the QR of the augmented Jacobian stays.
    """
    if jnp.dtype(dtype) == jnp.float64:
        return SecantLM(rtol=1e-5)
    return LevenbergMarquardt(rtol=1e-5, atol=1e-5)


def refine(
    cameras: Camera,
    world: Float[Array, "*batch N 3"],
    pixels: Float[Array, "*batch N 2"],
    mask: Bool[Array, "*batch N"] | None = None,
    *,
    distortion: Sequence[str] | str | None = None,
    fix: Sequence[str] | str = (),
    skew: bool = False,
    loss: Huber | Cauchy | None = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
) -> Refinement:
    """Minimise the reprojection error of every camera, starting from `cameras` (e.g. the DLT).

    One independent least-squares problem per camera, all solved in one compiled call (vmapped
    across the rig; on one CPU device in 32 slots, each given the next camera as its own
    converges, `solve_each`; called from Python, one camera after another in equal pieces of
    the rig side by side, one per core), each as `optimistix.least_squares` solves it,
    with `SecantLM`, a Levenberg–Marquardt whose model keeps the residuals' curvature, and the
    projection's Jacobian written out. The rotation is refined as
    a minimal axis-angle increment on the seed's; the model is `Camera.project`, with the seed's
    lens (a pinhole with Brown–Conrady distortion, or a fisheye). Derivatives of the result with
    respect to `world` and `pixels` (and the seed) come from implicit differentiation through
    the optimum.

    **Arguments:**

    - `cameras`: the seed, a `Camera` with the rig's batch shape.
    - `world`, `pixels`, `mask`: as for `mvcalib.dlt` (`world` may be shared by the rig).
    - `distortion`: which of the lens's coefficients to estimate (`"distortion"` for all); the
      others keep the seed's values (zeros for a DLT seed); `()` for none. By default OpenCV's
      choice: `("k1", "k2", "p1", "p2")` of a pinhole's `(k1, k2, p1, p2, k3)`, all four
      `(k1, k2, k3, k4)` of a fisheye's. Estimate only those the lens needs: from a few points
      each one adds variance (the 19 dots of the box corner seen by a lens without distortion:
      focal lengths 0.42 % off with `()`, 0.73 % with the default, median of 200 cameras), and
      the fitted distortion holds only where the points are.
    - `fix`: parameters held at the seed's values: names from `PARAMETERS`, or the groups
      `"focal"`, `"principal_point"`, `"intrinsics"`, `"rotation"`, `"translation"`, `"pose"`;
      and `"aspect_ratio"` (OpenCV's `CALIB_FIX_ASPECT_RATIO`): `alpha_u / alpha_v` held at the
      seed's ratio, the focal length estimated (`alpha_u` follows `alpha_v`; its standard error
      is the ratio times alpha_v's, and the two are fully correlated in `covariance`). With
      either focal length held, both are. `fix=("intrinsics", "distortion")` fits the pose
      alone from a seed near it (`mvcalib.solve_pnp` finds the seed too: OpenCV's `solvePnP`).
    - `skew`: estimate the skew; by default the model has none, as OpenCV's: the seed's skew
      (e.g. the DLT's small, noisy one) is set to zero. To hold a seed's non-zero skew instead,
      name it in `fix`.
    - `loss`: `None` for least squares, or `Huber(scale)` / `Cauchy(scale)` with `scale` in
      pixels, to bound the influence of outliers.
    - `solver`: any optimistix least-squares solver; default `default_solver(dtype)`:
      `SecantLM` stopping at steps of 1e-5 standard errors (float64; the RMS then equals that of
      a 1e-12 solve within 1e-13), optimistix's `LevenbergMarquardt` in float32.
    - `max_steps`: iteration limit per camera; reaching it is reported, not raised.

    **Returns:** a `Refinement`.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=3, noise=0.3)
    >>> seed = mc.calibrate(rig.world, rig.pixels).cameras
    >>> out = mc.refine(seed, rig.world, rig.pixels, distortion=())
    >>> bool((out.rms_after <= out.rms_before + 1e-6).all()), bool(out.ok.all())
    (True, True)

    ```
    """
    if not isinstance(cameras, Camera):
        raise ValueError(f"`cameras` must be an mvcalib.Camera; got {type(cameras).__name__}.")
    check_loss(loss)
    _validate.static_options("refine", skew=skew, max_steps=max_steps)
    # Called with concrete arrays, the rig is padded to its shape bucket (`_buckets`): padded
    # cameras have NaN seeds, which end at once, padded points are hidden.
    bucketed = _buckets.applies(cameras) and _buckets.pads(world, pixels, mask)
    # (checked in NumPy when padded, or when they are NumPy arrays already: compiling nothing)
    host = bucketed or all(isinstance(x, np.ndarray) for x in (world, pixels, mask))
    world, pixels, mask = _validate.correspondences(world, pixels, mask, xp=np if host else jnp)
    views = np.broadcast_shapes(world.shape[:-2], pixels.shape[:-2], mask.shape[:-1])
    try:  # (the cameras broadcast to the correspondences' leading axes, not the other way)
        fits = np.broadcast_shapes(cameras.batch_shape, views) == tuple(views)
    except ValueError:
        fits = False
    if not fits:
        raise ValueError(
            f"the rig has cameras of shape {cameras.batch_shape} but the correspondences are of "
            f"{views} (the leading axes of `pixels`, `mask` and `world`); give each camera its "
            "own pixels."
        )
    free = _free_parameters(distortion, fix, skew, cameras.lens)
    warn_held_coefficients(cameras, distortion, fix)
    cameras = _skew_model(
        cameras, skew, fix, xp=np if bucketed or isinstance(cameras.skew, np.ndarray) else jnp
    )
    if _validate.is_concrete(mask) and not cameras.batch_shape:
        n_min = int(np.sum(np.asarray(mask)))
        if 2 * n_min <= len(free):
            raise ValueError(
                f"the camera has {n_min} visible points, {2 * n_min} residuals for {len(free)} "
                "free parameters; fix some parameters or add points. (In a rig, such a camera "
                "is flagged instead: `result == -1`.)"
            )
    leaves = jax.tree_util.tree_leaves(cameras)
    if not cameras.batch_shape and _validate.is_concrete(*leaves):
        if not all(np.all(np.isfinite(np.asarray(x))) for x in leaves):
            raise ValueError(
                "the seed camera has a non-finite parameter (a camera `calibrate` could not "
                "solve is NaN; see its status). (In a rig, such a camera is flagged instead: "
                "`result == -2`.)"
            )
    dtype = _validate.result_dtype(world.dtype, cameras.R.dtype)
    solver = default_solver(dtype) if solver is None else solver
    options = dict(free=free, loss=loss, solver=solver, max_steps=max_steps)
    if not bucketed:
        quick = math.prod(mask.shape) <= _buckets.COMPACT
        return _refine_side_by_side(cameras, world, pixels, mask, quick=quick, **options)
    n_points, rig_shape = pixels.shape[-2], cameras.batch_shape
    (world, pixels, mask), batch = _buckets.correspondences(world, pixels, mask)
    n_cameras = pixels.shape[0]

    def flat(x):  # the seed cameras as the flat, padded camera axis
        tail = np.shape(x)[len(rig_shape) :]
        x = np.broadcast_to(np.asarray(x), batch + tail).reshape((-1,) + tail)
        return _buckets.pad(x, 0, n_cameras, fill=np.nan)

    cameras = jax.tree_util.tree_map(flat, cameras)
    quick = n_cameras * pixels.shape[1] <= _buckets.COMPACT
    out = _refine_side_by_side(cameras, world, pixels, mask, quick=quick, **options)
    out = _buckets.cut(out, batch)
    point_arrays = lambda r: (r.inliers, r.report.residuals, r.report.mask)  # noqa: E731
    return _buckets.cut_points(out, point_arrays, n_points, len(batch))


def _refine_side_by_side(cameras, world, pixels, mask, *, quick, **options) -> Refinement:
    """`_refine_all`. Called from Python with concrete arrays, the program solves one camera at
    a time (`slots`), and a rig of one camera axis runs in equal pieces side by side on the
    CPU's cores (`_buckets.in_pieces`): each camera's problem is its own, so the pieces' cameras
    are the whole's to the last bit (and the reports' RMS to rounding: a sum vectorised across
    the cameras). Inside the caller's trace, one program solves the rig in `SLOTS` side by
    side."""
    concrete = _buckets.applies(cameras, world, pixels, mask)
    if mask.ndim != 2 or not concrete:
        return _refine_all(
            cameras, world, pixels, mask, quick=quick, slotted=not concrete, **options
        )
    axes = (0, None if np.ndim(world) == 2 else 0, 0, 0)
    args = (cameras, world, pixels, mask)
    return _buckets.in_pieces(_refine_all, args, axes, quick=quick, slotted=False, **options)


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _refine_all(
    cameras, world, pixels, mask, *, free, loss, solver, max_steps, slotted=True
) -> Refinement:
    """`refine` of validated arrays, in one compiled program (`slotted`: see `slots`)."""
    dtype = _validate.result_dtype(world.dtype, cameras.R.dtype)
    cameras = jax.tree_util.tree_map(lambda x: x.astype(dtype), cameras)
    out = _refine_batched(
        cameras, world.astype(dtype), pixels.astype(dtype), mask, free, loss, solver, max_steps,
        slotted,
    )  # fmt: skip
    refined, rms_before, rms_after, steps, result, inliers, cov, std, residuals = out
    report = residual_report(residuals, jnp.broadcast_to(mask, residuals.shape[:-1]))
    return Refinement(
        cameras=refined,
        rms_before=rms_before,
        rms_after=rms_after,
        report=report,
        iterations=steps,
        result=result,
        inliers=inliers,
        covariance=cov,
        standard_errors=std,
        parameter_names=tuple(parameter_names(cameras.lens)[i] for i in free.reported),
    )
