"""Nonlinear refinement of reprojection error: optimistix Levenberg–Marquardt, one problem per
camera, vmapped across the rig; distortion, robust losses, covariance, implicit derivatives."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _validate
from ._camera import Camera
from ._report import ReprojectionReport, compute_report, masked_rms
from ._rotation import rodrigues

PARAMETERS = (
    "alpha_u", "alpha_v", "u0", "v0", "skew",
    "rx", "ry", "rz", "tx", "ty", "tz",
    "k1", "k2", "p1", "p2", "k3",
)  # fmt: skip
GROUPS = {
    "focal": ("alpha_u", "alpha_v"),
    "principal_point": ("u0", "v0"),
    "intrinsics": ("alpha_u", "alpha_v", "u0", "v0"),
    "rotation": ("rx", "ry", "rz"),
    "translation": ("tx", "ty", "tz"),
    "pose": ("rx", "ry", "rz", "tx", "ty", "tz"),
    "distortion": ("k1", "k2", "p1", "p2", "k3"),
}
DISTORTION = ("k1", "k2", "p1", "p2", "k3")


# ------------------------------------------------------------------------------ robust losses
class Huber(eqx.Module):
    """Huber loss on the length `r` of a point's residual: `r^2` up to `scale` pixels, linear
    beyond (`2 scale r - scale^2`)."""

    scale: float = 1.0

    def rho(self, s):
        c2 = self.scale**2
        return jnp.where(s <= c2, s, 2.0 * self.scale * jnp.sqrt(jnp.maximum(s, c2)) - c2)


class Cauchy(eqx.Module):
    """Cauchy (Lorentzian) loss: `scale^2 log(1 + r^2 / scale^2)`; far outliers count ~ log r."""

    scale: float = 1.0

    def rho(self, s):
        c2 = self.scale**2
        return c2 * jnp.log1p(s / c2)


def _robust_weights(loss, s):
    """sqrt(rho(s) / s), so that a point's weighted residual has squared length rho(s)."""
    if loss is None:
        return jnp.ones_like(s)
    tiny = s < 1e-12 * loss.scale**2
    safe = jnp.where(tiny, 1.0, s)
    return jnp.where(tiny, 1.0, jnp.sqrt(loss.rho(safe) / safe))


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
      parameters (its cameras are then NaN); `ok` is `result == 0`, `messages()` spells them out.
    - `inliers`: `(..., N)` visible points whose final residual is within 3 `loss.scale` (all
      visible points without a robust loss).
    - `covariance`: `(..., P, P)` covariance of the parameters named in `parameter_names` (the
      free ones), from the Jacobian at the optimum scaled by the residual variance.
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


def _result_messages() -> dict[int, str]:
    items = optx.RESULTS._name_to_item  # noqa: SLF001 (the enumeration's public view is by member)
    messages = {int(item._value): optx.RESULTS[item] or "successful" for item in items.values()}  # noqa: SLF001
    messages[TOO_FEW_POINTS] = "too few visible points for the free parameters: not refined"
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
    return Camera(p[0], p[1], p[2], p[3], rodrigues(p[5:8]) @ R0, p[8:11], skew=p[4], dist=p[11:])


def _scales(p0):
    """Natural units per parameter, so that Levenberg–Marquardt sees a well-scaled problem:
    pixels of focal length for the intrinsics, radians, the camera's distance, unit distortion."""
    f = jnp.abs(p0[0])
    d = jnp.linalg.norm(p0[8:11])
    one = jnp.ones((), p0.dtype)
    return jnp.stack([f] * 5 + [one] * 3 + [d] * 3 + [one] * 5)


def _residuals(y, args):
    p0, R0, scale, free, world, pixels, mask, loss = args
    p = p0.at[free].add(y * scale[free])
    r = _unpack(p, R0).project(world) - pixels
    r = jnp.where(mask[:, None], r, 0.0)
    return r * _robust_weights(loss, jnp.sum(r * r, axis=-1))[:, None]


def _refine_one(cam, world, pixels, mask, *, free, loss, solver, max_steps):
    dtype = world.dtype
    # Hidden points: replaced before any arithmetic, so NaN there reaches neither result nor grad.
    world = jnp.where(mask[:, None], world, 0.0)
    pixels = jnp.where(mask[:, None], pixels, 0.0)
    p0 = _pack(cam)
    scale = _scales(p0)
    free = jnp.asarray(free)
    args = (p0, cam.R, scale, free, world, pixels, mask, loss)
    y0 = jnp.zeros(len(free), dtype)
    sol = optx.least_squares(
        _residuals,
        solver,
        y0,
        args,
        max_steps=max_steps,
        throw=False,
    )
    y = sol.value
    refined = _unpack(p0.at[free].add(y * scale[free]), cam.R)

    # Covariance of the free parameters: sigma^2 (J^T J)^-1 with J the Jacobian of the
    # (robustly weighted) residuals at the optimum, in the parameters' own units.
    r = _residuals(y, args).reshape(-1)
    J = jax.jacfwd(lambda y: _residuals(y, args).reshape(-1))(y) / scale[free]  # dr/dp
    n_obs = 2 * jnp.sum(mask)
    dof = jnp.maximum(n_obs - len(free), 1)
    sigma2 = jnp.sum(r * r) / dof
    cov = sigma2 * jnp.linalg.inv(J.T @ J)

    rms = lambda c: masked_rms(c, world, pixels, mask)  # noqa: E731
    residual_length = jnp.linalg.norm(
        jnp.where(mask[:, None], refined.project(world) - pixels, 0.0), axis=-1
    )
    threshold = jnp.inf if loss is None else 3.0 * loss.scale
    inliers = mask & (residual_length <= threshold)
    enough = n_obs > len(free)
    refined = jax.tree_util.tree_map(lambda x: jnp.where(enough, x, jnp.nan), refined)
    result = jnp.where(enough, sol.result._value, TOO_FEW_POINTS)  # noqa: SLF001
    return (
        refined, rms(cam), rms(refined), sol.stats["num_steps"], result,
        inliers, cov, jnp.sqrt(jnp.diagonal(cov)),
    )  # fmt: skip


@eqx.filter_jit
def _refine_batched(cameras, world, pixels, mask, free, loss, solver, max_steps):
    batch = cameras.batch_shape
    n = world.shape[-2]
    flat = lambda x, tail: jnp.broadcast_to(x, (*batch, *tail)).reshape(-1, *tail)  # noqa: E731
    cams = jax.tree_util.tree_map(lambda x: x.reshape(-1, *x.shape[len(batch) :]), cameras)
    kernel = functools.partial(
        _refine_one, free=free, loss=loss, solver=solver, max_steps=max_steps
    )
    out = jax.vmap(kernel)(cams, flat(world, (n, 3)), flat(pixels, (n, 2)), flat(mask, (n,)))
    return jax.tree_util.tree_map(lambda x: x.reshape(*batch, *x.shape[1:]), out)


def _free_parameters(distortion, fix, skew) -> tuple[int, ...]:
    def expand(names, what):
        if isinstance(names, str):
            names = (names,)
        out = []
        for name in names:
            if name in GROUPS:
                out.extend(GROUPS[name])
            elif name in PARAMETERS:
                out.append(name)
            else:
                raise ValueError(
                    f"unknown parameter {name!r} in `{what}`; use any of {PARAMETERS} or the "
                    f"groups {tuple(GROUPS)}."
                )
        return set(out)

    estimated = expand(distortion, "distortion")
    if not estimated <= set(DISTORTION):
        raise ValueError(f"`distortion` takes coefficients of {DISTORTION}; got {distortion!r}.")
    fixed = expand(fix, "fix") | (set() if skew else {"skew"})
    fixed |= set(DISTORTION) - estimated
    return tuple(i for i, name in enumerate(PARAMETERS) if name not in fixed)


def default_solver(dtype) -> optx.LevenbergMarquardt:
    """Levenberg–Marquardt stopping at steps of 1e-6 (float64) or 1e-5 (float32) in the
    parameters' natural units (`_scales`), with its steps solved by normal equations in float64.

    The tolerance is far below the noise: on 64 cameras of the refine benchmark (14 parameters)
    every parameter ends within 4e-6 of its standard error from the optimum of a 1e-12 solve,
    and the RMS within 2e-13 relative; a tolerance of 1e-10 costs 2.5 times the steps, because
    the slowest direction (k1, k2 against the focal length, condition ~1e10 of J^T J) converges
    only linearly. Normal equations (one 14 x 14 Cholesky) cost a third of the default QR of the
    augmented Jacobian; in float32 that squared condition number is beyond the precision, so
    QR stays.
    """
    if jnp.dtype(dtype) == jnp.float64:
        return optx.LevenbergMarquardt(1e-6, 1e-6, linear_solver=lx.Normal(lx.Cholesky()))
    return optx.LevenbergMarquardt(rtol=1e-5, atol=1e-5)


def refine(
    cameras: Camera,
    world: Float[Array, "*batch N 3"],
    pixels: Float[Array, "*batch N 2"],
    mask: Bool[Array, "*batch N"] | None = None,
    *,
    distortion: Sequence[str] | str = ("k1", "k2", "p1", "p2"),
    fix: Sequence[str] | str = (),
    skew: bool = False,
    loss: Huber | Cauchy | None = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
) -> Refinement:
    """Minimise the reprojection error of every camera, starting from `cameras` (e.g. the DLT).

    One independent least-squares problem per camera, all solved in one compiled call (vmapped
    across the rig) with `optimistix.LevenbergMarquardt`. The rotation is refined as a minimal
    axis-angle increment on the seed's; the model is `Camera.project` (pinhole with
    Brown–Conrady distortion in OpenCV's order). Derivatives of the result with respect to
    `world` and `pixels` (and the seed) come from implicit differentiation through the optimum.

    **Arguments:**

    - `cameras`: the seed, a `Camera` with the rig's batch shape.
    - `world`, `pixels`, `mask`: as for `mvcalib.dlt` (`world` may be shared by the rig).
    - `distortion`: which of `("k1", "k2", "p1", "p2", "k3")` to estimate; the others keep the
      seed's values (zeros for a DLT seed). `()` or `"none"`-like empty means a pinhole model.
    - `fix`: parameters held at the seed's values: names from `PARAMETERS`, or the groups
      `"focal"`, `"principal_point"`, `"intrinsics"`, `"rotation"`, `"translation"`, `"pose"`.
    - `skew`: estimate the skew (default: held at the seed's value, which is zero for the usual
      zero-skew model that OpenCV uses; `calibrate(refine=True)` seeds it with zero).
    - `loss`: `None` for least squares, or `Huber(scale)` / `Cauchy(scale)` with `scale` in
      pixels, to bound the influence of outliers.
    - `solver`: any optimistix least-squares solver; default `default_solver(dtype)`: LM with
      tolerance 1e-6 (float64) in natural units, parameters within ~1e-5 standard errors of
      the optimum.
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
    world, pixels, mask = _validate.correspondences(world, pixels, mask)
    if not isinstance(cameras, Camera):
        raise ValueError(f"`cameras` must be an mvcalib.Camera; got {type(cameras).__name__}.")
    free = _free_parameters(distortion, fix, skew)
    if _validate.is_concrete(mask) and not cameras.batch_shape:
        n_min = int(np.sum(np.asarray(mask)))
        if 2 * n_min <= len(free):
            raise ValueError(
                f"the camera has {n_min} visible points, {2 * n_min} residuals for {len(free)} "
                "free parameters; fix some parameters or add points. (In a rig, such a camera "
                "is flagged instead: `result == -1`.)"
            )
    dtype = jnp.result_type(world.dtype, cameras.R.dtype)
    cameras = jax.tree_util.tree_map(lambda x: x.astype(dtype), cameras)
    solver = default_solver(dtype) if solver is None else solver
    out = _refine_batched(
        cameras, world.astype(dtype), pixels.astype(dtype), mask, free, loss, solver, max_steps
    )
    refined, rms_before, rms_after, steps, result, inliers, cov, std = out
    report = compute_report(refined, world, pixels, mask)
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
        parameter_names=tuple(PARAMETERS[i] for i in free),
    )
