"""A calibrated pair of cameras as a stereo rig: epipolar geometry and rectification; and the
undistorted image of any camera (`undistorted`, `undistortion_maps`: OpenCV's new camera matrix
and `initUndistortRectifyMap`).

`stereo_rectify` is OpenCV's `stereoRectify` (Bouguet's method: each camera turned by half the
rotation between them, then both about the baseline until their image rows, or columns, are
epipolar lines; for fisheyes `cv2.fisheye.stereoRectify`), `StereoRectification.maps` its
`initUndistortRectifyMap`, and
`essential_matrix` / `fundamental_matrix` those of `stereoCalibrate`. They take the pair as a rig
of two cameras in any common world frame (`calibrate_rig`'s, `Camera.stack` of two), and return
the rectified cameras in that frame too: `triangulate` and `project` work with them as with any.
Written in JAX: differentiable, and usable inside the caller's `jit`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _buckets, _validate
from ._camera import Camera, flat_rig, undistort_points
from ._rotation import hat, nearest_rotation, rodrigues

__all__ = [
    "StereoRectification", "essential_matrix", "fundamental_matrix", "stereo_rectify",
    "undistorted", "undistortion_maps",
]  # fmt: skip


def _pair(cameras: Camera, what: str) -> Camera:
    if not isinstance(cameras, Camera):
        raise TypeError(f"`{what}` takes a pair of cameras: a Camera rig of two; got {cameras!r}.")
    if cameras.batch_shape != (2,):
        raise ValueError(
            f"`{what}` takes a pair of cameras: a Camera rig of two (`rig[[0, 1]]`, "
            f"`Camera.stack([a, b])`); got batch shape {cameras.batch_shape}."
        )
    return cameras


def _relative(cameras: Camera):
    """OpenCV's `R`, `T` of the pair: camera 1's coordinates from camera 0's, `x1 = R x0 + T`."""
    R = cameras.R[1] @ cameras.R[0].T
    return R, cameras.t[1] - R @ cameras.t[0]


def essential_matrix(cameras: Camera) -> Float[Array, "3 3"]:
    """The essential matrix `E = [T]x R` of a pair of cameras (`R`, `T`: camera 1's coordinates
    from camera 0's, as OpenCV's `stereoCalibrate` returns them): `y1^T E y0 = 0` for the
    normalised, undistorted image coordinates `y = (x / z, y / z, 1)` of one point in the two
    cameras.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> left = mc.Camera(800.0, 805.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3))
    >>> turned = mc.rodrigues(jnp.array([0.01, -0.05, 0.02]))
    >>> right = mc.Camera(810.0, 808.0, 630.0, 355.0, turned, jnp.array([-0.12, 0.003, 0.01]))
    >>> pair = mc.Camera.stack([left, right])  # (or two cameras of a calibrated rig)
    >>> world = jnp.array([[0.1, -0.2, 2.0], [-0.3, 0.1, 3.5], [0.4, 0.3, 2.5]])
    >>> E = mc.essential_matrix(pair)
    >>> y = pair.to_camera(world)
    >>> y = y / y[..., 2:]  # (x / z, y / z, 1) in each camera
    >>> float(jnp.abs(jnp.einsum("ni,ij,nj->n", y[1], E, y[0])).max()) < 1e-6
    True

    ```
    """
    return _essential(_pair(cameras, "essential_matrix"))


@_buckets.eager
def _essential(cameras):
    R, T = _relative(cameras)
    return hat(T) @ R


def fundamental_matrix(cameras: Camera) -> Float[Array, "3 3"]:
    """The fundamental matrix of a pair of cameras, `F = K1^-T E K0^-1` scaled to `F[2, 2] = 1`
    (where it is not ~0; as OpenCV's `stereoCalibrate`): `p1^T F p0 = 0` for the undistorted
    pixels `p = (u, v, 1)` of one point (`undistort_points`; a camera's lens distortion bends the
    epipolar lines of the pixels it sees). Pinhole cameras.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> left = mc.Camera(800.0, 805.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3))
    >>> turned = mc.rodrigues(jnp.array([0.01, -0.05, 0.02]))
    >>> right = mc.Camera(810.0, 808.0, 630.0, 355.0, turned, jnp.array([-0.12, 0.003, 0.01]))
    >>> pair = mc.Camera.stack([left, right])  # (or two cameras of a calibrated rig)
    >>> world = jnp.array([[0.1, -0.2, 2.0], [-0.3, 0.1, 3.5], [0.4, 0.3, 2.5]])
    >>> F = mc.fundamental_matrix(pair)
    >>> p = jnp.concatenate([pair.project(world), jnp.ones((2, 3, 1))], -1)  # (u, v, 1)
    >>> line = p[0] @ F.T  # each point's epipolar line in camera 1: its pixel is on it
    >>> distance = jnp.abs(jnp.sum(line * p[1], -1)) / jnp.hypot(line[:, 0], line[:, 1])
    >>> float(distance.max()) < 1e-3
    True

    ```
    """
    cameras = _pair(cameras, "fundamental_matrix")
    if cameras.lens != "pinhole":
        raise ValueError(
            "`fundamental_matrix` relates pinhole pixels; a fisheye's epipolar curves have no F "
            "(use `essential_matrix` with `Camera.rays`)."
        )
    return _fundamental(cameras)


@_buckets.eager
def _fundamental(cameras):
    F = jnp.linalg.inv(cameras.K[1]).T @ _essential(cameras) @ jnp.linalg.inv(cameras.K[0])
    scale = jnp.where(jnp.abs(F[2, 2]) > jnp.finfo(F.dtype).eps, F[2, 2], 1.0)
    return F / scale


class StereoRectification(eqx.Module):
    """A pair of cameras rectified (`stereo_rectify`): what OpenCV's `stereoRectify` returns, and
    the rectified cameras themselves.

    - `cameras`: the rectified pair, a rig of two pinhole cameras without distortion in the
      original cameras' world frame, their image rows (columns where `vertical`) epipolar lines:
      a point's rectified pixels differ only along the baseline (the disparity). `project` and
      `triangulate` take them as any cameras.
    - `original`: the cameras rectified (their lenses are needed to resample images, `maps`).
    - `R`: `(2, 3, 3)`, OpenCV's `R1`, `R2`: each camera's coordinates turned into its rectified
      camera's (`cameras.R[i] = R[i] @ original.R[i]`).
    - `P`: `(2, 3, 4)`, OpenCV's `P1`, `P2`: the rectified cameras' projections in rectified
      camera 0's coordinates, `P[1][idx, 3] = f * baseline` (`idx` 0 horizontal, 1 vertical).
    - `Q`: `(4, 4)` disparity-to-depth matrix: `Q @ (u, v, d, 1)` is the point, homogeneous, in
      rectified camera 0's coordinates, for rectified pixel `(u, v)` of camera 0 and disparity
      `d = u0 - u1` (`v0 - v1` where `vertical`); OpenCV's `reprojectImageTo3D` takes it.
    - `roi`: `(2, 4)` integers, `x, y, width, height` of each rectified image's part where every
      pixel comes from inside the original image (OpenCV's `validPixROI1`, `validPixROI2`; for
      fisheyes, which OpenCV gives none, the same rule).
    - `vertical`: whether the cameras are one above the other (the baseline more vertical than
      horizontal in the cameras' rectified frame): then columns are the epipolar lines.
    - `image_size`: `(width, height)` of the images, original and rectified.
    """

    cameras: Camera
    original: Camera
    R: Float[Array, "2 3 3"]
    P: Float[Array, "2 3 4"]
    Q: Float[Array, "4 4"]
    roi: Int[Array, "2 4"]
    vertical: Bool[Array, ""]
    image_size: tuple[int, int] = eqx.field(static=True)

    def maps(self) -> tuple[Float[Array, "2 H W"], Float[Array, "2 H W"]]:
        """`(map_x, map_y)`, each `(2, height, width)` float32: for every pixel of each rectified
        image, where it lies in the original image (OpenCV's `initUndistortRectifyMap` with
        `CV_32FC1`, `cv2.fisheye`'s for fisheyes). Resample an image `i` with
        `cv2.remap(image, map_x[i], map_y[i], cv2.INTER_LINEAR)`, or with scikit-image,
        `skimage.transform.warp(image, np.stack([map_y[i], map_x[i]]), order=1)`.

        **Example:**

        ```python
        >>> import jax.numpy as jnp, mvcalib as mc
        >>> left = mc.Camera(800.0, 805.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3))
        >>> right = mc.Camera(810.0, 808.0, 630.0, 355.0, jnp.eye(3), jnp.array([-0.12, 0, 0]))
        >>> rect = mc.stereo_rectify(mc.Camera.stack([left, right]), (1280, 720), alpha=0)
        >>> map_x, map_y = rect.maps()
        >>> map_x.shape, map_x.dtype
        ((2, 720, 1280), dtype('float32'))

        ```
        """
        return undistortion_maps(self.original, self.cameras, self.image_size)


def _dtype(cameras: Camera):
    return np.result_type(cameras.alpha_u.dtype, np.float32)


def undistortion_maps(
    camera: Camera, new: Camera, image_size: tuple[int, int]
) -> tuple[Float[Array, "*batch H W"], Float[Array, "*batch H W"]]:
    """`(map_x, map_y)`, float32 `(*batch, height, width)`: for every pixel of the image `new`
    sees, where it lies in `camera`'s image (OpenCV's `initUndistortRectifyMap(K, D, R, P)` with
    `CV_32FC1`, `cv2.fisheye`'s for a fisheye; `R` the turn from `camera` to `new`, `P` `new.K`).
    `new` is a pinhole without distortion at `camera`'s centre: `undistorted(camera, ...)`, or a
    rectified camera (`StereoRectification.maps`). Resample with `cv2.remap(image, map_x,
    map_y, cv2.INTER_LINEAR)`, or `skimage.transform.warp(image, np.stack([map_y, map_x]),
    order=1)`.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> cam = mc.Camera(800.0, 805.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3),
    ...                 dist=jnp.array([-0.2, 0.05, 0.0, 0.0, 0.0]))
    >>> new = mc.undistorted(cam, (1280, 720))
    >>> map_x, map_y = mc.undistortion_maps(cam, new, (1280, 720))
    >>> map_x.shape, map_x.dtype
    ((720, 1280), dtype('float32'))

    ```
    """
    width, height = _image_size(image_size, "undistortion_maps")
    v, u = np.mgrid[0:height, 0:width].astype(_dtype(new))
    grid = np.stack([u.ravel(), v.ravel()], -1)
    xy = np.asarray(_maps(flat_rig(camera), flat_rig(new), grid), np.float32)
    xy = xy.reshape(*camera.batch_shape, height, width, 2)
    return xy[..., 0], xy[..., 1]


def undistorted(
    camera: Camera, image_size: tuple[int, int], *, alpha: float = 0.0, fov_scale: float = 1.0
) -> Camera:
    """The pinhole camera without distortion, at `camera`'s pose, whose image shows what
    `camera`'s does undistorted (resample it with `undistortion_maps`): OpenCV's new camera
    matrix, `getOptimalNewCameraMatrix(K, D, size, alpha)` for a pinhole (`alpha` 0: every pixel
    from inside the image, no black border; 1: every original pixel kept; between, a mix), and
    `cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(K, D, size, I, balance=alpha,
    fov_scale=fov_scale)` for a fisheye. `camera` may be a rig. OpenCV undistorts the image's
    border with five fixed-point steps, which with strong distortion stop short (an OpenCV
    user's trial, k1 -0.3: its focal length at `alpha=1` 0.14 px off this one, which its own
    algorithm run to convergence reproduces); with mild distortion they agree to rounding.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> cam = mc.Camera(800.0, 805.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3),
    ...                 dist=jnp.array([-0.2, 0.05, 0.0, 0.0, 0.0]))
    >>> new = mc.undistorted(cam, (1280, 720))  # alpha=0: no black border
    >>> new.lens, bool(new.dist.any()), new.K.shape
    ('pinhole', False, (3, 3))

    ```
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"`undistorted` takes a Camera; got {camera!r}.")
    size = _image_size(image_size, "undistorted")
    dtype = _dtype(camera)
    scaling, fov = _scalings(alpha, fov_scale, dtype, optional=False, function="undistorted")
    K = _new_K(flat_rig(camera), np.asarray(size, dtype), scaling, fov)
    K = K.reshape(*camera.batch_shape, 3, 3)
    return Camera(
        alpha_u=K[..., 0, 0], alpha_v=K[..., 1, 1], u0=K[..., 0, 2], v0=K[..., 1, 2],
        skew=jnp.zeros_like(K[..., 0, 0]), R=camera.R, t=camera.t,
    )  # fmt: skip


@_buckets.eager
def _new_K(cameras, size, alpha, fov_scale):
    """`undistorted`'s `K` `(n, 3, 3)` of the cameras `(n,)`."""
    n = cameras.alpha_u.shape[0]
    dtype = cameras.R.dtype
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (n, 3, 3))
    if cameras.lens == "fisheye":
        focal, c = _fisheye_intrinsics(cameras, eye, size, alpha, fov_scale)
    else:
        # OpenCV's getOptimalNewCameraMatrix: the largest rectangle inside and the smallest
        # outside the undistorted image (9 x 9 points of the border, in normalised coordinates)
        # each mapped onto the image, mixed by alpha
        last = size - 1
        steps = jnp.linspace(0.0, 1.0, 9, dtype=dtype)
        v, u = jnp.meshgrid(steps * last[1], steps * last[0], indexing="ij")
        border = jnp.stack([u.ravel(), v.ravel()], -1)
        xy = _through(cameras, eye, border, 1.0, jnp.zeros((n, 2), dtype)).reshape(n, 9, 9, 2)
        inner, outer = _rectangles(xy)
        fit = lambda r: (last / (r[:, 2:] - r[:, :2]), -(last / (r[:, 2:] - r[:, :2])) * r[:, :2])  # noqa: E731
        (f0, c0), (f1, c1) = fit(inner), fit(outer)
        focal, c = f0 * (1 - alpha) + f1 * alpha, c0 * (1 - alpha) + c1 * alpha
    zero, one = jnp.zeros((n,), dtype), jnp.ones((n,), dtype)
    return jnp.stack(
        [
            jnp.stack([focal[:, 0], zero, c[:, 0]], -1),
            jnp.stack([zero, focal[:, 1], c[:, 1]], -1),
            jnp.stack([zero, zero, one], -1),
        ],
        1,
    )


def _scalings(alpha, fov_scale, dtype, *, optional: bool, function: str):
    """`alpha` (in [0, 1]; where `optional`, None too: -1, OpenCV's "no scaling") and
    `fov_scale` (positive) of `mc.<function>` checked, as arrays of `dtype`."""
    _validate.static_options(function, alpha=alpha, fov_scale=fov_scale)
    if not (optional and alpha is None):
        number = isinstance(alpha, (int, float, np.floating)) and not isinstance(alpha, bool)
        if not number or not 0.0 <= float(alpha) <= 1.0:
            what = "None or a number" if optional else "a number"
            raise ValueError(f"`alpha` is {what} in [0, 1]; got {alpha!r}.")
    if not (isinstance(fov_scale, (int, float, np.floating)) and fov_scale > 0):
        raise ValueError(f"`fov_scale` is a positive number; got {fov_scale!r}.")
    scaling = -1.0 if alpha is None else alpha
    return np.asarray(scaling, dtype), np.asarray(fov_scale, dtype)


def _image_size(image_size, function: str) -> tuple[int, int]:
    """`image_size` of `mc.<function>` checked: two positive Python ints."""
    try:
        size = tuple(image_size)
    except TypeError:
        size = ()
    for n in size:
        _validate.static_options(function, image_size=n)
    if len(size) != 2 or not all(
        isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n > 0 for n in size
    ):
        raise ValueError(f"`image_size` is (width, height) in pixels; got {image_size!r}.")
    return int(size[0]), int(size[1])


@_buckets.eager
def _maps(original, new, grid):
    """The original pixels `(n, N, 2)` of the pixels `grid` `(N, 2)` of the new cameras `(n,)`
    (at the original cameras' centres)."""
    R = new.R @ jnp.swapaxes(original.R, -1, -2)  # original camera coordinates to new ones
    K_inv = jnp.linalg.inv(new.K)  # (n, 3, 3)
    rays = jnp.concatenate([grid, jnp.ones_like(grid[:, :1])], -1)  # (N, 3)
    directions = jnp.einsum("cji,cjk,nk->cni", R, K_inv, rays)  # original camera coordinates
    unposed = eqx.tree_at(
        lambda c: (c.R, c.t),
        original,
        (jnp.broadcast_to(jnp.eye(3, dtype=R.dtype), R.shape), jnp.zeros_like(original.t)),
    )
    return unposed.project(directions)


def stereo_rectify(
    cameras: Camera,
    image_size: tuple[int, int],
    *,
    alpha: float | None = None,
    zero_disparity: bool = True,
    fov_scale: float = 1.0,
) -> StereoRectification:
    """Rectify a calibrated pair of cameras, as OpenCV's `stereoRectify` does.

    Each camera is turned by half the rotation between them, then both about the baseline until
    it lies along their rectified x axis (y where the cameras are one above the other): a point
    then has the same rectified image row in both (column), and its depth follows from the
    disparity (`Q`). Both rectified cameras get one focal length (the mean of the originals'
    vertical ones, horizontal ones for a vertical pair) and principal points that centre the
    undistorted image corners, as OpenCV computes them; `alpha` then zooms both. A fisheye pair
    is rectified as `cv2.fisheye.stereoRectify` does it (side by side only; one focal length from
    `estimateNewCameraMatrixForUndistortRectify`'s fit of the edges' midpoints, `alpha` its
    `balance`, and `fov_scale`), into pinhole cameras: a rectified pinhole image holds less than
    180 degrees, and `alpha=1` keeps what it can.

    **Arguments:**

    - `cameras`: the pair, a `Camera` rig of two (e.g. `calibrate_rig(...).cameras[[0, 1]]`,
      `Camera.stack([left, right])`), pinholes or fisheyes, in any common world frame.
    - `image_size`: `(width, height)` in pixels, of both cameras' images.
    - `alpha`: OpenCV's free scaling: `None` (OpenCV's -1) keeps the focal length above; `0`
      zooms in until every rectified pixel comes from inside the original images (no black
      borders), `1` out until every original pixel is in the rectified images; between, a mix.
      For fisheyes, OpenCV's `balance` (`None`: 0, its default).
    - `zero_disparity`: OpenCV's `CALIB_ZERO_DISPARITY` (its default): both rectified cameras
      share their principal point, so that points at infinity have zero disparity. `False` moves
      each camera's principal point along the baseline to centre its own view.
    - `fov_scale`: for fisheyes, OpenCV's: the focal length divided by it (above 1 shows more).

    **Returns:** a `StereoRectification`: the rectified cameras, OpenCV's `R1 R2 P1 P2 Q` and
    valid regions, and `maps()` to resample images. Where there is none (a fisheye that sees
    beyond 90 degrees at the middle of an image edge: a pinhole cannot hold it), a `ValueError`
    says so; inside a `jax.jit`, NaN.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> left = mc.Camera(800.0, 805.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3))
    >>> turned = mc.rodrigues(jnp.array([0.01, -0.05, 0.02]))
    >>> right = mc.Camera(810.0, 808.0, 630.0, 355.0, turned, jnp.array([-0.12, 0.003, 0.01]))
    >>> pair = mc.Camera.stack([left, right])  # (or two cameras of a calibrated rig)
    >>> world = jnp.array([[0.1, -0.2, 2.0], [-0.3, 0.1, 3.5], [0.4, 0.3, 2.5]])
    >>> rect = mc.stereo_rectify(pair, (1280, 720))
    >>> rows = rect.cameras.project(world)[..., 1]  # a point has one row in both cameras
    >>> float(jnp.abs(rows[0] - rows[1]).max()) < 1e-3
    True

    ```
    """
    cameras = _pair(cameras, "stereo_rectify")
    size = _image_size(image_size, "stereo_rectify")
    if not isinstance(zero_disparity, (bool, np.bool_)):
        raise TypeError(f"`zero_disparity` is True or False; got {zero_disparity!r}.")
    dtype = _dtype(cameras)
    scaling, fov = _scalings(alpha, fov_scale, dtype, optional=True, function="stereo_rectify")
    out = _rectify(cameras, np.asarray(size, dtype), scaling, np.asarray(zero_disparity), fov)
    rect = StereoRectification(*out, image_size=size)
    P = rect.P
    if _buckets.applies(P) and not np.isfinite(np.asarray(P)).all():
        # (called eagerly; inside the caller's trace it stays NaN, as the docstring says)
        what = (
            "a fisheye sees the middle of an image edge more than 90 degrees off the rectified "
            "axis, which a rectified pinhole image cannot hold (cv2.fisheye.stereoRectify gives "
            "focal lengths of a few tens of pixels there); rectify a crop of the images about "
            "the principal points (the cameras' u0, v0 less the crop's corner, its size as "
            "`image_size`)"
            if cameras.lens == "fisheye"
            else "are the cameras' parameters finite, and apart?"
        )
        raise ValueError(f"`stereo_rectify` found no finite rectification: {what}.")
    return rect


@_buckets.eager
def _rectify(cameras, size, alpha, zero_disparity, fov_scale):
    # OpenCV's pixel grid: the corner pixels' centres at 0 and size - 1
    last = size - 1
    nx, ny = last[0], last[1]
    dtype = cameras.R.dtype
    R, T = _relative(cameras)
    eye = jnp.eye(3, dtype=dtype)
    # half the rotation between the cameras: R^(1/2) is the rotation of I + R's polar
    # decomposition (I + R = R^(1/2) (R^(1/2) + R^(-1/2)), the latter symmetric positive definite
    # below 180 degrees); OpenCV's r_r = Rodrigues(-om / 2) = R^(-1/2)
    r_r = nearest_rotation(eye + R).T
    t = r_r @ T
    fisheye = cameras.lens == "fisheye"  # (static) cv2.fisheye.stereoRectify: side by side only
    vertical = jnp.asarray(False) if fisheye else jnp.abs(t[0]) <= jnp.abs(t[1])  # OpenCV's idx
    idx = vertical.astype(jnp.int32)
    # then both about the axis t x u by the angle between the baseline t and the axis u it is
    # to lie along (rectified x, or y for a vertical pair; its sign's direction)
    u = jnp.where(jnp.arange(3) == idx, jnp.sign(t[idx]) + (t[idx] == 0), 0.0).astype(dtype)
    axis = jnp.cross(t, u)
    norm = jnp.linalg.norm(axis)
    angle = jnp.arccos(jnp.clip(jnp.abs(t[idx]) / jnp.linalg.norm(t), 0.0, 1.0))
    wR = rodrigues(jnp.where(norm > 0, axis * angle / jnp.where(norm > 0, norm, 1.0), 0.0))
    rotations = jnp.stack([wR @ r_r.T, wR @ r_r])  # OpenCV's R1, R2
    t = rotations[1] @ T  # the baseline, along rectified x (y where vertical)
    baseline = jnp.where(vertical, t[1], t[0])

    if fisheye:
        focal, c = _fisheye_intrinsics(cameras, rotations, size, alpha, fov_scale)
        f = jnp.min(focal[:, 1])  # (OpenCV: the smaller vertical one, for both)
    else:
        # one focal length (OpenCV: the mean of the originals' vertical ones, horizontal for a
        # vertical pair) and the principal points that centre the undistorted image corners
        f = 0.5 * jnp.where(vertical, cameras.alpha_u.sum(), cameras.alpha_v.sum())
        corners = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
        corners = last * jnp.asarray(corners, dtype)
        seen = _through(cameras, rotations, corners, f, jnp.zeros((2, 2), dtype))
        # (a corner beyond the fold of the lens's distortion has no ray: there, the lens's
        # pinhole's, without distortion; OpenCV's steps stop short of a point there too)
        pinholes = eqx.tree_at(lambda c: c.dist, cameras, jnp.zeros_like(cameras.dist))
        seen = jnp.where(
            jnp.isfinite(seen),
            seen,
            _through(pinholes, rotations, corners, f, jnp.zeros((2, 2), dtype)),
        )
        c = last / 2 - seen.mean(1)
    mean = c.mean(0)
    c = jnp.where(
        zero_disparity,
        jnp.broadcast_to(mean, (2, 2)),
        jnp.where(vertical, c.at[:, 0].set(mean[0]), c.at[:, 1].set(mean[1])),
    )

    # OpenCV's alpha: a zoom between the largest inner and the smallest outer rectangle of the
    # undistorted image borders (9 x 9 points), about the principal points
    steps = jnp.linspace(0.0, 1.0, 9, dtype=dtype)
    v, u = jnp.meshgrid(steps * ny, steps * nx, indexing="ij")
    border = jnp.stack([u.ravel(), v.ravel()], -1)  # row-major, 9 x 9
    xy = _through(cameras, rotations, border, f, c).reshape(2, 9, 9, 2)
    inner, outer = _rectangles(xy)

    def zoom(rect, pick):
        x0, y0, x1, y1 = (rect[:, i] for i in range(4))
        cx, cy = c[:, 0], c[:, 1]
        return pick(
            jnp.stack(
                [cx / (cx - x0), cy / (cy - y0), (nx - cx) / (x1 - cx), (ny - cy) / (y1 - cy)]
            )
        )

    s0 = zoom(inner, jnp.max)
    s1 = zoom(outer, jnp.min)
    s = jnp.where(alpha >= 0, s0 * (1 - alpha) + s1 * alpha, 1.0) if not fisheye else 1.0
    f = f * s

    zeros = jnp.zeros((2,), dtype)
    K = jnp.stack(
        [
            jnp.stack([jnp.full((2,), f), zeros, c[:, 0]], -1),
            jnp.stack([zeros, jnp.full((2,), f), c[:, 1]], -1),
            jnp.stack([zeros, zeros, jnp.ones((2,), dtype)], -1),
        ],
        1,
    )  # (2, 3, 3)
    shift = jnp.zeros((2, 3), dtype).at[1, idx].set(baseline * f)
    P = jnp.concatenate([K, shift[..., None]], -1)
    disparity_shift = jnp.where(vertical, c[0, 1] - c[1, 1], c[0, 0] - c[1, 0])
    Q = jnp.array(
        [
            [1.0, 0.0, 0.0, -c[0, 0]],
            [0.0, 1.0, 0.0, -c[0, 1]],
            [0.0, 0.0, 0.0, f],
            [0.0, 0.0, -1.0 / baseline, disparity_shift / baseline],
        ],
        dtype,
    )
    # OpenCV's whole pixels inside (`cvCeil`, `cvFloor`), forgiving our rounding: at `alpha=0` a
    # border lands on a pixel by construction
    slack = 100 * jnp.finfo(dtype).eps * size.max()
    up = lambda x: jnp.ceil(x - slack)  # noqa: E731
    down = lambda x: jnp.floor(x + slack)  # noqa: E731
    roi_x = up((inner[:, 0] - c[:, 0]) * s + c[:, 0])
    roi_y = up((inner[:, 1] - c[:, 1]) * s + c[:, 1])
    roi_w = down((inner[:, 2] - inner[:, 0]) * s)
    roi_h = down((inner[:, 3] - inner[:, 1]) * s)
    # intersected with the image, as OpenCV's `Rect & Rect`
    x0, y0 = jnp.maximum(roi_x, 0), jnp.maximum(roi_y, 0)
    x1, y1 = jnp.minimum(roi_x + roi_w, size[0]), jnp.minimum(roi_y + roi_h, size[1])
    empty = ~(x1 > x0) | ~(y1 > y0)  # (or NaN)
    roi = jnp.where(empty[:, None], 0, jnp.stack([x0, y0, x1 - x0, y1 - y0], -1)).astype(jnp.int32)

    rectified = Camera(
        alpha_u=K[:, 0, 0],
        alpha_v=K[:, 1, 1],
        u0=K[:, 0, 2],
        v0=K[:, 1, 2],
        skew=jnp.zeros((2,), dtype),
        R=rotations @ cameras.R,
        t=jnp.einsum("cij,cj->ci", rotations, cameras.t),
    )
    return rectified, cameras, rotations, P, Q, roi, vertical


def _rectangles(xy):
    """OpenCV's `icvGetRectangles` of the border grids `xy (n, 9, 9, 2)` (rows of points): the
    largest rectangle inside and the smallest outside each, `(n, 4)` as `x0, y0, x1, y1`. (A
    fisheye's border points beyond 90 degrees of the axis are NaN: they bound nothing.)"""
    inner = jnp.stack(
        [
            jnp.nanmax(xy[:, :, 0, 0], 1),  # left: the first column's largest x
            jnp.nanmax(xy[:, 0, :, 1], 1),  # top
            jnp.nanmin(xy[:, :, -1, 0], 1),  # right
            jnp.nanmin(xy[:, -1, :, 1], 1),  # bottom
        ],
        -1,
    )
    outer = jnp.stack(
        [
            jnp.nanmin(xy[..., 0], (1, 2)),
            jnp.nanmin(xy[..., 1], (1, 2)),
            jnp.nanmax(xy[..., 0], (1, 2)),
            jnp.nanmax(xy[..., 1], (1, 2)),
        ],
        -1,
    )
    return inner, outer


def _through(cameras, rotations, pixels, f, c):
    """Original `pixels` `(M, 2)` of both cameras, undistorted, turned by `rotations` and seen
    by pinholes of focal length `f` and principal points `c` `(2, 2)`: `(2, M, 2)`; NaN where a
    ray (a fisheye's) turns away from the pinhole."""
    if cameras.lens == "fisheye":
        rays = cameras.rays(pixels)  # (2, M, 3)
    else:
        ideal = undistort_points(cameras, pixels)  # (2, M, 2): the pinholes' pixels, same K
        normalised = jnp.stack(cameras._distorted_normalised(ideal), -1)
        rays = jnp.concatenate([normalised, jnp.ones_like(normalised[..., :1])], -1)
    turned = jnp.einsum("cij,cmj->cmi", rotations, rays)
    ahead = turned[..., 2:] > 0
    xy = turned[..., :2] / jnp.where(ahead, turned[..., 2:], 1.0)
    return jnp.where(ahead, f * xy + c[:, None, :], jnp.nan)


def _fisheye_intrinsics(cameras, rotations, size, balance, fov_scale):
    """Each fisheye's new pinhole focal lengths `(n, 2)` and principal point `(n, 2)`, as
    `cv2.fisheye.estimateNewCameraMatrixForUndistortRectify` makes them (the midpoints of the
    image's edges, turned by `rotations` and undistorted, fitted by a focal length between the
    one that keeps all of them, `balance` 1, and the one that fills the image, 0, over
    `fov_scale`)."""
    w, h = size[0], size[1]
    midpoints = jnp.stack(
        [
            jnp.stack([jnp.floor(w / 2), 0.0 * h]),
            jnp.stack([w, jnp.floor(h / 2)]),
            jnp.stack([jnp.floor(w / 2), h]),
            jnp.stack([0.0 * w, jnp.floor(h / 2)]),
        ]
    )
    origin = jnp.zeros((rotations.shape[0], 2), w.dtype)
    xy = _through(cameras, rotations, midpoints, 1.0, origin)  # (n, 4, 2)
    ratio = (cameras.alpha_u / cameras.alpha_v)[:, None]  # (to square pixels, and back)
    xy = xy.at[..., 1].multiply(ratio)
    centre = xy.mean(1)  # (2, 2)
    reach = jnp.stack(
        [
            w / 2 / (centre[:, 0] - xy[..., 0].min(1)),
            w / 2 / (xy[..., 0].max(1) - centre[:, 0]),
            h / 2 * ratio[:, 0] / (centre[:, 1] - xy[..., 1].min(1)),
            h / 2 * ratio[:, 0] / (xy[..., 1].max(1) - centre[:, 1]),
        ]
    )
    balance = jnp.clip(jnp.where(balance >= 0, balance, 0.0), 0.0, 1.0)
    f = balance * reach.min(0) + (1 - balance) * reach.max(0)
    f = f / jnp.where(fov_scale > 0, fov_scale, 1.0)
    n = centre.shape[0]
    c = -centre * f[:, None] + jnp.stack([jnp.full((n,), w), h * ratio[:, 0]], -1) / 2
    c = c.at[:, 1].divide(ratio[:, 0])
    return jnp.stack([f, f / ratio[:, 0]], -1), c  # (n, 2) focal lengths, (n, 2) centres
