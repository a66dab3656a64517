"""Figures of a calibrated rig: the cameras in 3-D, residuals over each image, their histograms.

matplotlib is optional (`pip install 'mvcalib[plot]'`) and imported only when a function here is
called. The functions draw on the matplotlib axes they are given, or make their own
`matplotlib.figure.Figure` without pyplot: no window opens, whatever the backend, and nothing
global changes. `report_figure` puts all three together, as `mvcalib report --plot` writes it.
"""

from __future__ import annotations

import io as _io
import math
import pathlib

import jax
import numpy as np

from ._camera import Camera

__all__ = ["plot_rig", "plot_residuals", "plot_histograms", "report_figure", "save_figure"]

_AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")


def require_matplotlib():
    """matplotlib's `Figure` class, or an `ImportError` saying how to install it."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise ImportError("mvcalib's plots need matplotlib: pip install 'mvcalib[plot]'") from None
    return Figure


def _host(cameras: Camera) -> Camera:
    rig = jax.tree_util.tree_map(lambda a: np.asarray(a, dtype=float), cameras)
    if rig.batch_shape == ():
        rig = jax.tree_util.tree_map(lambda a: a[None], rig)
    if len(rig.batch_shape) != 1:
        raise ValueError(f"plot a rig with one camera axis; got batch shape {rig.batch_shape}.")
    return rig


def _calibrated(rig: Camera) -> np.ndarray:
    """Per camera: are all its parameters finite (a failed calibration is NaN)?"""
    leaves = jax.tree_util.tree_leaves(rig)
    return np.all([np.isfinite(a).reshape(len(a), -1).all(-1) for a in leaves], axis=0)


def _image_sizes(rig: Camera, image_size, pixels=None) -> np.ndarray:
    """(C, 2) width and height: given, or guessed from the principal point (at the middle of
    most sensors), grown to hold every observed pixel."""
    if image_size is not None:
        return np.broadcast_to(np.asarray(image_size, dtype=float), (len(rig.u0), 2))
    size = np.stack([2 * rig.u0 + 1, 2 * rig.v0 + 1], -1)
    if pixels is not None:
        seen = np.where(np.isfinite(pixels), pixels, -np.inf).max(axis=1)  # -inf: none seen
        size = np.fmax(size, np.ceil(seen + 0.5))
    return np.where(np.isfinite(size), size, 1.0)


def _frustum(camera: Camera, size, depth) -> np.ndarray:
    """(5, 3) world points: the centre, then the image's four corners at `depth` (a fisheye's:
    at that distance along their rays, which may point beside or behind the camera)."""
    w, h = size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    if camera.lens == "fisheye":
        x_cam = depth * np.asarray(camera.rays(corners), dtype=float)
    else:
        K = np.array([[camera.alpha_u, camera.skew, camera.u0], [0, camera.alpha_v, camera.v0],
                      [0, 0, 1]], dtype=float)  # fmt: skip
        rays = np.linalg.solve(K, np.c_[corners, np.ones(4)].T).T
        x_cam = depth * rays / rays[:, 2:]
    R, t = np.asarray(camera.R), np.asarray(camera.t)
    world = (x_cam - t) @ R  # R^T (x - t), row by row
    return np.vstack([-(t @ R)[None], world])


def plot_rig(
    cameras: Camera,
    world=None,
    *,
    names=None,
    ax=None,
    image_size=None,
    frustum_depth: float | None = None,
    axes_length: float | None = None,
):
    """Draw the rig in 3-D: a frustum per camera, the world points, and the world frame's axes.

    **Arguments:**

    - `cameras`: the rig (a `Camera` with a camera axis, or one camera).
    - `world`: optional `(P, 3)` points to draw (the target).
    - `names`: a label per camera (default its index, `0, 1, ...`, as the tables number cameras).
    - `ax`: a 3-D matplotlib axes to draw on (default: a new figure's).
    - `image_size`: `(width, height)` for the frusta's far rectangles; default from the
      principal point.
    - `frustum_depth`: how far each frustum reaches, in world units; default a fifth of the
      median distance from the cameras to the points (or to the rig's middle). A camera that
      sees the points at negative depth (a mirrored world frame) draws it towards them.
    - `axes_length`: length of the X, Y, Z arrows at the world origin.

    **Returns:** the axes.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc, mvcalib.plot
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3, noise=0.5)
    >>> ax = mc.plot.plot_rig(rig.cameras, rig.world)
    >>> len(ax.lines)  # per camera: four rays and the far rectangle; then X, Y, Z
    18

    ```
    """
    rig = _host(cameras)
    C = len(rig.u0)
    names = [str(i) for i in range(C)] if names is None else [str(s) for s in names]
    if ax is None:
        ax = require_matplotlib()(figsize=(6, 5)).add_subplot(projection="3d")
    # NumPy rather than the Camera's JAX methods: a figure needs no compiled code.
    centres = -np.einsum("cji,cj->ci", rig.R, rig.t)
    ok = _calibrated(rig)
    world = None if world is None else np.asarray(world, dtype=float).reshape(-1, 3)
    anchor = np.median(world, 0) if world is not None else np.median(centres[ok], 0)
    if frustum_depth is None:
        distance = np.linalg.norm(centres[ok] - anchor, axis=-1)
        frustum_depth = 0.2 * float(np.median(distance)) if distance.size else 1.0
        frustum_depth = frustum_depth if frustum_depth > 0 else 1.0
    sizes = _image_sizes(rig, image_size)
    drawn = [np.zeros((1, 3))]
    colours = [f"C{i % 10}" for i in range(C)]
    for i in np.flatnonzero(ok):
        camera = rig[i]
        sign = 1.0
        if world is not None:
            depth = world @ camera.R[2] + camera.t[2]
            sign = -1.0 if np.median(depth) < 0 else 1.0
        f = _frustum(camera, sizes[i], sign * frustum_depth)
        for k in range(1, 5):
            ax.plot(*zip(f[0], f[k]), color=colours[i], lw=1)
        ax.plot(*f[[1, 2, 3, 4, 1]].T, color=colours[i], lw=1.5)
        ax.text(*f[0], f" {names[i]}", color=colours[i], fontsize=9)
        drawn.append(f)
    if world is not None:
        ax.scatter(*world.T, s=10, color="0.2", depthshade=False, label="points")
        drawn.append(world)
    everything = np.vstack(drawn)
    extent = float(np.ptp(everything, 0).max()) or 1.0
    length = 0.15 * extent if axes_length is None else float(axes_length)
    for k, (label, colour) in enumerate(zip("XYZ", _AXIS_COLOURS)):
        tip = np.zeros(3)
        tip[k] = length
        ax.plot(*zip(np.zeros(3), tip), color=colour, lw=2.5)
        ax.text(*(1.12 * tip), label, color=colour, fontsize=10, fontweight="bold")
    middle = (everything.max(0) + everything.min(0)) / 2
    half = 0.55 * extent
    ax.set(
        xlim=(middle[0] - half, middle[0] + half),
        ylim=(middle[1] - half, middle[1] + half),
        zlim=(middle[2] - half, middle[2] + half),
        xlabel="X",
        ylabel="Y",
        zlabel="Z",
    )
    ax.set_box_aspect((1, 1, 1), zoom=1.15)
    ax.tick_params(labelsize=7)
    points = "" if world is None else f", {len(world)} points"
    ax.set_title(f"{int(ok.sum())} cameras{points}", fontsize=9)
    return ax


def _residuals(rig: Camera, world, pixels, mask):
    world = np.asarray(world, dtype=float)
    pixels = np.asarray(pixels, dtype=float)
    if pixels.ndim != 3 or pixels.shape[0] != len(rig.u0):
        raise ValueError(f"`pixels` must be (C, P, 2) with C = {len(rig.u0)}; got {pixels.shape}.")
    if mask is None:
        mask = np.all(np.isfinite(pixels), -1)
    mask = np.asarray(mask, dtype=bool) & np.all(np.isfinite(pixels), -1)
    # One compiled projection (lens distortion included) rather than a string of eager ops.
    projected = np.asarray(_project(rig, np.broadcast_to(world, pixels.shape[:2] + (3,))))
    residuals = projected - pixels  # reprojected - observed, as in Table I
    mask = mask & np.all(np.isfinite(residuals), -1)
    return np.where(mask[..., None], residuals, np.nan), pixels, mask


@jax.jit
def _project(cameras: Camera, world):
    return cameras.project(world)


def _nice(x: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above x."""
    if not x > 0 or not math.isfinite(x):
        return 1.0
    k = math.floor(math.log10(x))
    return max(m * 10.0**k for m in (1, 2, 5) if m * 10.0**k <= x)


def plot_residuals(
    cameras: Camera,
    world,
    pixels,
    mask=None,
    *,
    names=None,
    axes=None,
    image_size=None,
    scale: float | None = None,
):
    """Draw each camera's residuals as arrows over its image, from observed to reprojected.

    **Arguments:**

    - `cameras`, `world`, `pixels`, `mask`: as for `mvcalib.reprojection_report`; `world`
      `(P, 3)` or `(C, P, 3)`.
    - `names`: a title per camera.
    - `axes`: one matplotlib axes per camera (default: a new figure, a panel per camera).
    - `image_size`: `(width, height)` of the images drawn; default from the principal point,
      grown to hold every observed pixel.
    - `scale`: how many times the arrows are magnified, the same for every camera (default: a
      round number that makes the 95th percentile arrow about half the points' typical spacing,
      between 2 % and 10 % of the image's width).

    **Returns:** `(axes, scale)`.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc, mvcalib.plot
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3, noise=0.5)
    >>> axes, scale = mc.plot.plot_residuals(rig.cameras, rig.world, rig.pixels)
    >>> len(axes), scale  # one round magnification for every camera
    (3, 50.0)

    ```
    """
    rig = _host(cameras)
    residuals, pixels, mask = _residuals(rig, world, pixels, mask)
    C = len(rig.u0)
    names = [str(i) for i in range(C)] if names is None else [str(s) for s in names]
    sizes = _image_sizes(rig, image_size, np.where(mask[..., None], pixels, np.nan))
    if axes is None:
        cols = min(C, 4)
        rows = -(-C // cols)
        figure = require_matplotlib()(figsize=(3.6 * cols, 3.4 * rows), layout="constrained")
        axes = list(figure.subplots(rows, cols, squeeze=False).ravel()[:C])
    if scale is None:
        # The 95th percentile arrow about half the typical spacing of the points, so that
        # arrows seldom cross, and between 2 % and 10 % of the image's width.
        lengths = np.linalg.norm(residuals[mask], axis=-1)
        typical = np.percentile(lengths, 95) if lengths.size else 0.0
        n = np.median(mask.sum(1)[mask.any(1)]) if mask.any() else 1.0
        width = float(np.max(sizes[:, 0]))
        spacing = float(np.sqrt(np.prod(np.median(sizes, 0)) / n))
        target = float(np.clip(0.5 * spacing, 0.02 * width, 0.1 * width))
        scale = _nice(target / typical) if typical > 0 else 1.0
    for i, ax in enumerate(axes):
        w, h = sizes[i]
        ax.add_patch(_rectangle(w, h))
        seen = mask[i]
        x, y = pixels[i, seen].T
        r = residuals[i, seen]
        ax.plot(x, y, ".", color="0.45", ms=2.5)
        ax.quiver(
            x,
            y,
            scale * r[:, 0],
            scale * r[:, 1],
            angles="xy",
            scale_units="xy",
            scale=1.0,
            color="tab:red",
            width=0.006,
        )
        ax.set_xlim(-0.5 - 0.02 * w, w - 0.5 + 0.02 * w)
        ax.set_ylim(h - 0.5 + 0.02 * h, -0.5 - 0.02 * h)  # rows grow downwards
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        if seen.any():
            rms = float(np.sqrt(np.mean(np.sum(r**2, -1))))
            ax.set_title(f"{names[i]}: RMS {rms:.3g} px, {int(seen.sum())} points", fontsize=9)
        else:
            ax.set_title(f"{names[i]}: no points", fontsize=9)
    return axes, float(scale)


def _rectangle(w, h):
    from matplotlib.patches import Rectangle

    return Rectangle((-0.5, -0.5), w, h, fill=False, ec="0.6", lw=1)


def plot_histograms(
    cameras: Camera, world, pixels, mask=None, *, axes=None, bins: int | None = None
):
    """Histograms of the residuals over all cameras: the x and y components, and the lengths.

    **Arguments:** as for `plot_residuals`; `axes` is a pair of matplotlib axes (default: a new
    figure's); `bins` per histogram (default twice the square root of the number of
    observations, between 10 and 40).

    **Returns:** the two axes.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc, mvcalib.plot
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3, noise=0.5)
    >>> components, lengths = mc.plot.plot_histograms(rig.cameras, rig.world, rig.pixels)
    >>> components.get_xlabel()
    'residual (px)'

    ```
    """
    rig = _host(cameras)
    residuals, _, mask = _residuals(rig, world, pixels, mask)
    r = residuals[mask]
    if axes is None:
        figure = require_matplotlib()(figsize=(8, 3), layout="constrained")
        axes = figure.subplots(1, 2)
    components, lengths = axes
    beyond = ""
    if r.size:
        length = np.linalg.norm(r, axis=-1)
        rms = float(np.sqrt(np.mean(length**2)))
        # A few outliers should not squeeze the rest into one bin: show up to 5 RMS.
        limit = min(float(length.max()), 5 * rms) or 1.0
        outside = int(np.sum(length > limit))
        beyond = f"; {outside} beyond {limit:.3g} px not shown" if outside else ""
        bins = int(np.clip(2 * np.sqrt(len(r)), 10, 40)) if bins is None else int(bins)
        edges = np.linspace(-limit, limit, bins + 1)
        components.hist(r[:, 0], edges, histtype="step", lw=1.5, label="x", color="tab:blue")
        components.hist(r[:, 1], edges, histtype="step", lw=1.5, label="y", color="tab:orange")
        components.legend(fontsize=8)
        lengths.hist(length, bins, range=(0, limit), color="0.55")
        lengths.axvline(rms, color="tab:red", lw=1.5, label=f"RMS {rms:.3g} px")
        lengths.legend(fontsize=8)
    components.set(
        xlabel="residual (px)",
        ylabel="observations",
        title=f"x and y components ({len(r)} observations)",
    )
    lengths.set(xlabel="|residual| (px)", ylabel="observations", title=f"lengths{beyond}")
    for ax in axes:
        ax.tick_params(labelsize=7)
        ax.title.set_fontsize(9)
    return components, lengths


def report_figure(
    cameras: Camera,
    world,
    pixels,
    mask=None,
    *,
    names=None,
    image_size=None,
    max_cameras: int = 12,
    title: str | None = None,
):
    """One figure: the rig in 3-D, the residual histograms, and the residuals over each image
    (the first `max_cameras` cameras). What `mvcalib report --plot` writes.

    **Returns:** a `matplotlib.figure.Figure` (save it with `save_figure` or `.savefig`).

    **Example:**

    ```python
    >>> import jax, mvcalib as mc, mvcalib.plot
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3, noise=0.5)
    >>> figure = mc.plot.report_figure(rig.cameras, rig.world, rig.pixels, rig.mask)
    >>> len(figure.axes)  # 3-D rig, two histograms, three cameras
    6

    ```
    """
    Figure = require_matplotlib()
    rig = _host(cameras)
    C = len(rig.u0)
    if names is None:
        names = [f"camera {i}" for i in range(C)]
    else:
        names = [f"{i}: {_short(str(n))}" for i, n in enumerate(names)]
    shown = min(C, max_cameras)
    cols = min(max(shown, 3), 5) if shown else 3
    rows = -(-shown // cols)
    figure = Figure(figsize=(3.2 * cols, 4.6 + 3.0 * rows), layout="constrained")
    top, bottom = figure.subfigures(2, 1, height_ratios=[4.6, 3.0 * max(rows, 0.01)])
    grid = top.add_gridspec(2, 2, width_ratios=[1.3, 1])
    rig_ax = top.add_subplot(grid[:, 0], projection="3d")
    world_points = np.asarray(world, dtype=float).reshape(-1, 3)
    numbers = [str(i) for i in range(C)]  # (as the tables number them) names would crowd it
    plot_rig(rig, np.unique(world_points, axis=0), names=numbers, ax=rig_ax, image_size=image_size)
    rig_ax.view_init(elev=25, azim=-60)
    plot_histograms(
        rig, world, pixels, mask, axes=(top.add_subplot(grid[0, 1]), top.add_subplot(grid[1, 1]))
    )
    residuals, _, seen = _residuals(rig, world, pixels, mask)
    if shown:
        panels = bottom.subplots(rows, cols, squeeze=False).ravel()
        for ax in panels[shown:]:
            ax.set_axis_off()
        _, scale = plot_residuals(
            rig[:shown],
            world if np.ndim(world) == 2 else world[:shown],
            np.asarray(pixels)[:shown],
            seen[:shown],
            names=names[:shown],
            axes=panels[:shown],
            image_size=image_size,
        )
        more = f" (first {shown} of {C} cameras)" if shown < C else ""
        bottom.suptitle(
            f"residuals over each image, arrows x {scale:g}, observed to reprojected{more}",
            fontsize=10,
        )
    r = residuals[seen]
    rms = float(np.sqrt(np.mean(np.sum(r**2, -1)))) if r.size else float("nan")
    top.suptitle(
        title or f"{C} cameras, {int(seen.sum())} observations, RMS {rms:.3g} px", fontsize=11
    )
    return figure


def _short(name: str, width: int = 24) -> str:
    """A camera's name for a panel title: a path's file name, the end of a long name."""
    name = pathlib.PurePath(name).name or name
    return name if len(name) <= width else "..." + name[-(width - 3) :]


def save_figure(figure, path, *, dpi: int = 100) -> pathlib.Path:
    """Save a matplotlib figure atomically (temporary file + rename), in the format of the
    suffix (`.png`, `.pdf`, `.svg`, ...)."""
    from .io import write_atomic

    path = pathlib.Path(path)
    buffer = _io.BytesIO()
    figure.savefig(buffer, format=path.suffix.lstrip(".").lower() or "png", dpi=dpi)
    return write_atomic(path, buffer.getvalue())
