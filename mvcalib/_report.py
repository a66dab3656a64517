"""Back-projection errors per camera: the paper's Table I, plus RMS and maximum."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _validate
from ._camera import Camera


class ReprojectionReport(eqx.Module):
    """Reprojection errors per camera (error = reprojected - observed, in pixels).

    `mean_x`, `mean_y` are the paper's Table I (mean signed error in x and y); `rms` is the
    root-mean-square length of the error vectors; `max` the largest; `n_points` how many visible
    points were used. All have the rig's batch shape; `residuals` `(..., N, 2)` are zero where
    hidden. Printing a report gives a table.
    """

    mean_x: Float[Array, "*batch"]
    mean_y: Float[Array, "*batch"]
    rms: Float[Array, "*batch"]
    max: Float[Array, "*batch"]
    n_points: Int[Array, "*batch"]
    residuals: Float[Array, "*batch N 2"]
    mask: Bool[Array, "*batch N"]

    def __str__(self) -> str:
        return format_table(self)


def reprojection_report(
    cameras: Camera,
    world: Float[Array, "*batch N 3"],
    pixels: Float[Array, "*batch N 2"],
    mask: Bool[Array, "*batch N"] | None = None,
) -> ReprojectionReport:
    """The paper's Table I for every camera: mean signed error in x and y, plus RMS and max.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=2, noise=0.5)
    >>> report = mc.reprojection_report(rig.cameras, rig.world, rig.pixels)
    >>> report.rms.shape
    (2,)

    ```
    """
    world, pixels, mask = _validate.correspondences(world, pixels, mask, min_points=1)
    return compute_report(cameras, world, pixels, mask)


def masked_rms(cameras, world, pixels, mask):
    """Reprojection RMS per camera over the visible points (inputs validated already)."""
    return residual_rms(cameras.project(world) - pixels, mask)


def residual_rms(residuals, mask):
    """The RMS per camera of `residuals (..., N, 2)` over `mask (..., N)` (zero elsewhere)."""
    r = jnp.where(mask[..., None], residuals, 0.0)
    return jnp.sqrt(jnp.sum(r * r, axis=(-1, -2)) / jnp.maximum(jnp.sum(mask, -1), 1))


def compute_report(cameras, world, pixels, mask) -> ReprojectionReport:
    """`reprojection_report` on inputs that were validated already."""
    shape = jnp.broadcast_shapes(mask.shape, cameras.batch_shape + mask.shape[-1:])
    mask = jnp.broadcast_to(mask, shape)
    return residual_report(cameras.project(world) - pixels, mask)


def residual_report(residuals, mask) -> ReprojectionReport:
    """Table I of the residuals `(..., N, 2)` (projected minus measured) over `mask (..., N)`."""
    residuals = jnp.where(mask[..., None], residuals, 0.0)
    n = jnp.sum(mask, axis=-1)
    denom = jnp.maximum(n, 1).astype(residuals.dtype)
    mean = jnp.sum(residuals, axis=-2) / denom[..., None]
    sq = jnp.sum(residuals**2, axis=-1)
    rms = jnp.sqrt(jnp.sum(sq, axis=-1) / denom)
    # (XLA's max need not carry a NaN through: a camera with NaN parameters gets NaN from its RMS)
    largest = jnp.where(jnp.isnan(rms), jnp.nan, jnp.sqrt(jnp.max(sq, axis=-1)))
    nan = jnp.where(n > 0, 1.0, jnp.nan).astype(residuals.dtype)
    return ReprojectionReport(
        mean_x=mean[..., 0] * nan,
        mean_y=mean[..., 1] * nan,
        rms=rms * nan,
        max=largest * nan,
        n_points=n.astype(jnp.int32),
        residuals=residuals,
        mask=mask,
    )


def index_names(batch: tuple[int, ...]) -> list[str]:
    """Each camera's index in a batch of shape `batch`, as text: `"3"` along one axis, `"1, 2"`
    along two (a calibration under `vmap`: numbered 0 to 5, a (2, 3) batch lost its shape)."""
    return [", ".join(map(str, i)) for i in np.ndindex(*(batch or (1,)))]


def format_table(report: ReprojectionReport, status=None, names=None) -> str:
    """Table I as text, one row per camera (flattened over batch axes), each named by `names`
    or by its index (`index_names`: as `report.rms[i]`, or `report.rms[i, j]` for a batch of
    two axes); with `status`, a word per camera after its row."""
    if not _validate.is_concrete(report.rms):
        return repr(report)
    cols = [
        np.atleast_1d(np.asarray(getattr(report, k))).reshape(-1)
        for k in ("mean_x", "mean_y", "rms", "max", "n_points")
    ]
    names = [str(n) for n in (index_names(np.shape(report.rms)) if names is None else names)]
    width = max(6, *map(len, names))
    header = (
        f"{'camera':<{width}} {'mean err x':>11} {'mean err y':>11} {'RMS':>9} {'max':>9} "
        f"{'points':>6}" + ("  status" if status is not None else "")
    )
    lines = ["Table I: back-projection error per camera (pixels; reprojected - observed)", header]
    for i, (mx, my, rms, mxx, n) in enumerate(zip(*cols)):
        line = f"{names[i]:<{width}} {mx:>11.4f} {my:>11.4f} {rms:>9.4f} {mxx:>9.4f} {int(n):>6}"
        if status is not None:
            line = f"{line}  {status[i]}".rstrip()
        lines.append(line)
    return "\n".join(lines)
