"""The camera model: intrinsics with skew, a rigid pose and a lens: a pinhole with Brown–Conrady
distortion, or a fisheye with Kannala–Brandt's (equidistant) model."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from . import _buckets, _small, _validate
from ._rotation import nearest_rotation

# The lens models and their distortion coefficients, in OpenCV's order (`cv2` and `cv2.fisheye`).
LENSES = {"pinhole": ("k1", "k2", "p1", "p2", "k3"), "fisheye": ("k1", "k2", "k3", "k4")}


def _projection(camera: Camera, world):
    """`Camera.project` of validated `world`."""
    xd, yd = _lens(camera._camera_coordinates(world), camera.dist[..., None, :])  # noqa: SLF001
    u = camera.alpha_u[..., None] * xd + camera.skew[..., None] * yd + camera.u0[..., None]
    v = camera.alpha_v[..., None] * yd + camera.v0[..., None]
    return jnp.stack([u, v], -1)


# Called on concrete arrays, the projection's dozen operations would run one by one, each
# compiled at its first shape (~0.5 s for the first call); as one program it compiles once
# (~0.1 s) and runs ~8x faster; a small one (`_buckets.COMPACT` points) in the quick build.
_compiled_projection = _buckets.jit(_projection, jit=eqx.filter_jit)


def _eagerly(kernel, name: str, camera: Camera, pixels, iterations: int):
    """`kernel(camera, pixels, iterations)` (a lens's inverse) of checked pixels: one compiled
    program where the arrays are concrete, as `project` is (run operation by operation, the
    Newton steps' `scan`, a closure made anew at each call, compiled again at every call of
    `undistort_points`: 0.13 s each for three pixels, a JAX user's trial); part of the caller's
    program where traced."""
    _validate.static_options(name, iterations=iterations)
    xp = jnp if isinstance(pixels, jax.Array) else np  # (NumPy data: converted by the jit)
    px = _validate.floating("pixels", pixels, (None, 2), xp=xp)
    if _buckets.applies(camera, px):
        size = math.prod(np.broadcast_shapes(camera.batch_shape, px.shape[:-2])) * px.shape[-2]
        return _compiled_inverse(kernel, camera, px, iterations, quick=size <= _buckets.COMPACT)
    return kernel(camera, px, iterations)


@functools.partial(_buckets.jit, static_argnums=(0, 3))
def _compiled_inverse(kernel, camera, px, iterations):
    return kernel(camera, px, iterations)


def check_lens(lens) -> None:
    """Refuse a `lens` that is not one of `LENSES`, naming them."""
    if lens not in LENSES:
        raise ValueError(f"`lens` is one of {tuple(LENSES)}; got {lens!r}.")


def flat_rig(camera: Camera) -> Camera:
    """`camera` with its batch axes as one leading camera axis (a single camera: a rig of one)."""
    batch = camera.batch_shape
    return jax.tree_util.tree_map(lambda x: x.reshape(-1, *x.shape[len(batch) :]), camera)


def lens_of(dist) -> str:
    """The lens of a camera with these distortion coefficients `(..., 5)` or `(..., 4)`: inside
    the library's kernels, where cameras are rebuilt from packed parameter vectors, the number
    of coefficients carries the (static) lens."""
    return "fisheye" if dist.shape[-1] == len(LENSES["fisheye"]) else "pinhole"


# Camera's derived arrays, each one compiled program where called eagerly (`_buckets.eager`)
@_buckets.eager
def _intrinsic_matrix(alpha_u, alpha_v, u0, v0, skew):
    zero, one = jnp.zeros_like(u0), jnp.ones_like(u0)
    rows = [
        jnp.stack([alpha_u, skew, u0], -1),
        jnp.stack([zero, alpha_v, v0], -1),
        jnp.stack([zero, zero, one], -1),
    ]
    return jnp.stack(rows, -2)


@_buckets.eager
def _center(R, t):
    return -jnp.einsum("...ji,...j->...i", R, t)


@_buckets.eager
def _projection_matrix(K, R, t):
    return K @ jnp.concatenate([R, t[..., None]], axis=-1)


class Camera(eqx.Module):
    """A camera; a rig is one `Camera` whose fields carry a leading camera axis.

    A world point `X` maps to camera coordinates `x_cam = R @ X + t`, through the lens to
    distorted normalised coordinates `(x_d, y_d)`, and to pixels
    `u = alpha_u * x_d + skew * y_d + u0`, `v = alpha_v * y_d + v0`. Pixels are `(x = column,
    y = row)` with the origin at the centre of the top-left pixel (OpenCV's convention).

    The lens is a static choice, so that a rig of one model is one batched pytree (a rig holds
    one lens: `calibrate_rig` and `triangulate` take one rig, so cameras of both kinds are not
    yet calibrated or triangulated together):

    - `"pinhole"` (default): `(x, y) = x_cam[:2] / x_cam[2]` with Brown–Conrady distortion
      `dist = (k1, k2, p1, p2, k3)`, OpenCV's `cv2.projectPoints` (see `distort`).
    - `"fisheye"`: Kannala–Brandt's equidistant model of `cv2.fisheye`, `dist = (k1, k2, k3, k4)`:
      `theta` is the angle between the ray and the optical axis,
      `theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`, and
      `(x_d, y_d) = theta_d (x_cam[0], x_cam[1]) / |(x_cam[0], x_cam[1])|`. `theta` is the ray's
      own angle, `atan2(|(x_cam[0], x_cam[1])|, x_cam[2])`, so points beside or behind the image
      plane (up to 180 degrees off axis) project where the lens puts them; OpenCV takes
      `atan(r)` of `x_cam[:2] / x_cam[2]` and mirrors points beyond 90 degrees. (OpenCV's skew
      `alpha` is `skew / alpha_u` here.)

    **Arguments:**

    - `alpha_u`, `alpha_v`: focal lengths in pixels along x and y, `(*batch,)`.
    - `u0`, `v0`: principal point in pixels, `(*batch,)`.
    - `R`: world-to-camera rotation `(*batch, 3, 3)`; `t`: translation `(*batch, 3)`.
    - `skew`: the K[0, 1] entry, `(*batch,)`; zero by default (the paper's model).
    - `dist`: the lens's distortion coefficients in OpenCV's order, `(*batch, 5)` Brown–Conrady
      `(k1, k2, p1, p2, k3)` for a pinhole, `(*batch, 4)` `(k1, k2, k3, k4)` for a fisheye; zeros
      by default (the paper neglects distortion; a fisheye with zeros is the ideal equidistant
      lens, `r = f theta`).
    - `lens`: `"pinhole"` or `"fisheye"` (see above); a static field.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> cam = mc.Camera(alpha_u=800.0, alpha_v=800.0, u0=320.0, v0=240.0,
    ...                 R=jnp.eye(3), t=jnp.array([0.0, 0.0, 5.0]))
    >>> cam.project(jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])).tolist()
    [[320.0, 240.0], [480.0, 240.0]]

    ```
    """

    alpha_u: Float[Array, "*batch"]
    alpha_v: Float[Array, "*batch"]
    u0: Float[Array, "*batch"]
    v0: Float[Array, "*batch"]
    skew: Float[Array, "*batch"]
    R: Float[Array, "*batch 3 3"]
    t: Float[Array, "*batch 3"]
    dist: Float[Array, "*batch K"]
    lens: str = eqx.field(static=True, default="pinhole")

    def __init__(self, alpha_u, alpha_v, u0, v0, R, t, skew=None, dist=None, lens="pinhole"):
        check_lens(lens)
        names = LENSES[lens]
        alpha_u, alpha_v, u0, v0 = (jnp.asarray(a) for a in (alpha_u, alpha_v, u0, v0))
        R, t = jnp.asarray(R), jnp.asarray(t)
        if R.shape[-2:] != (3, 3):
            hint = (
                ": a rotation vector? `mc.rodrigues` makes the matrix"
                if R.shape[-1:] == (3,)
                else ""
            )
            raise ValueError(f"`R` holds 3 x 3 rotation matrices, shape (..., 3, 3); got "
                             f"{tuple(R.shape)}{hint}.")  # fmt: skip
        if t.shape[-1:] != (3,):
            hint = ": OpenCV's (3, 1) tvec? pass `t.reshape(-1)`" if t.shape[-2:] == (3, 1) else ""
            raise ValueError(f"`t` holds translations, shape (..., 3); got {tuple(t.shape)}{hint}.")
        batch = jnp.broadcast_shapes(
            alpha_u.shape, alpha_v.shape, u0.shape, v0.shape, R.shape[:-2], t.shape[:-1]
        )
        dtype = jnp.result_type(alpha_u, alpha_v, u0, v0, R, t, float)
        if skew is None:
            skew = jnp.zeros(batch, dtype)
        if dist is None:
            dist = jnp.zeros((*batch, len(names)), dtype)
        dist = jnp.asarray(dist, dtype)
        column = dist.ndim == 2 and dist.shape[-1] == 1 and dist.shape[0] > 1
        if dist.shape[-1:] != (len(names),):
            other = [k for k, v in LENSES.items() if dist.shape[-1:] == (len(v),)]
            hint = f" (the coefficients of lens={other[0]!r}?)" if other else ""
            if lens == "pinhole" and dist.shape[-1] == 4:
                hint = (
                    " (OpenCV's k1 k2 p1 p2? append a zero k3: `np.r_[dist, 0.0]`; cv2.fisheye's "
                    "four are a `lens='fisheye'` camera's)"
                )
            elif lens == "pinhole" and dist.shape[-1] in (8, 12, 14):
                hint = (
                    f" (OpenCV's {dist.shape[-1]}-coefficient model? its first five, `dist[:5]`, "
                    "are these; k4 and beyond have no counterpart here)"
                )
            if column:
                hint = f": OpenCV's ({dist.shape[0]}, 1) column? pass `dist.reshape(-1)`"
            raise ValueError(
                f"`dist` of a {lens} camera holds ({', '.join(names)}), shape (..., "
                f"{len(names)}); got {tuple(dist.shape)}{hint}."
            )
        if jnp.broadcast_shapes(dist.shape[:-1], batch) != batch:
            hint = f": OpenCV's (1, {len(names)}) row? pass `dist.reshape(-1)`" if (
                dist.shape[:-1] == (1,)) else ""  # fmt: skip
            raise ValueError(f"`dist` {tuple(dist.shape)} has more cameras than the other "
                             f"parameters (batch shape {batch}){hint}.")  # fmt: skip

        def cast(x, shape):
            return jnp.broadcast_to(jnp.asarray(x, dtype), shape)

        self.alpha_u = cast(alpha_u, batch)
        self.alpha_v = cast(alpha_v, batch)
        self.u0 = cast(u0, batch)
        self.v0 = cast(v0, batch)
        self.skew = cast(skew, batch)
        self.R = cast(R, (*batch, 3, 3))
        self.t = cast(t, (*batch, 3))
        self.dist = cast(dist, (*batch, len(names)))
        self.lens = lens

    # ------------------------------------------------------------------ derived quantities
    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.alpha_u.shape)

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError("a single Camera has no length; a rig has a leading camera axis.")
        return self.batch_shape[0]

    def __getitem__(self, index) -> Camera:
        """Select cameras of a rig: `rig[0]`, `rig[1:3]`, `rig[ok]`."""
        if not self.batch_shape:
            raise TypeError("a single Camera cannot be indexed; a rig has a leading camera axis.")
        return _buckets.take(self, index)

    @property
    def K(self) -> Float[Array, "*batch 3 3"]:
        """The intrinsic matrix `[[alpha_u, skew, u0], [0, alpha_v, v0], [0, 0, 1]]`."""
        return _intrinsic_matrix(self.alpha_u, self.alpha_v, self.u0, self.v0, self.skew)

    @property
    def center(self) -> Float[Array, "*batch 3"]:
        """The optical centre in world coordinates, `-R^T t`."""
        return _center(self.R, self.t)

    def projection_matrix(self) -> Float[Array, "*batch 3 4"]:
        """`P = K [R | t]` (distortion is not part of `P`)."""
        return _projection_matrix(self.K, self.R, self.t)

    def _camera_coordinates(self, world):
        """`R X + t` as three arrays `(*batch, N)`, one per coordinate: entry by entry rather than
        a product with 3 x 3 matrices, so that XLA runs each as one elementwise loop over the
        points (arrays with a trailing axis of 3 are slow loops on a CPU)."""
        X = [world[..., j] for j in range(3)]
        R, t = self.R[..., None], self.t[..., None]
        return [sum(R[..., i, j, :] * X[j] for j in range(3)) + t[..., i, :] for i in range(3)]

    def to_camera(self, world) -> Float[Array, "*batch N 3"]:
        """World points `(..., N, 3)` in camera coordinates, `R X + t`."""
        return jnp.stack(self._camera_coordinates(jnp.asarray(world)), -1)

    def depth(self, world) -> Float[Array, "*batch N"]:
        """Depth of world points along the optical axis (positive in front of the camera)."""
        return self._camera_coordinates(jnp.asarray(world))[2]

    def project(self, world) -> Float[Array, "*batch N 2"]:
        """Pixels of world points `(..., N, 3)`; leading axes broadcast against the rig's.

        One target seen by a rig of C cameras: `world` `(N, 3)` gives pixels `(C, N, 2)`.
        """
        xp = jnp if isinstance(world, jax.Array) else np  # (NumPy data: converted by the jit)
        world = _validate.floating("world", world, (None, 3), xp=xp)
        try:
            batch = np.broadcast_shapes(self.batch_shape, world.shape[:-2])
        except ValueError:
            raise ValueError(
                f"`project`: the world points' leading axes {world.shape[:-2]} do not broadcast "
                f"with the rig's batch shape {self.batch_shape}; e.g. one set of points per "
                "frame for every camera: `world[:, None]`, (F, 1, N, 3)."
            ) from None
        if _buckets.applies(self, world):  # concrete arrays: one compiled program
            quick = math.prod(batch) * world.shape[-2] <= _buckets.COMPACT
            return _compiled_projection(self, world, quick=quick)
        return _projection(self, world)  # (traced: part of the caller's program)

    def rays(self, pixels, *, iterations: int = 20) -> Float[Array, "*batch N 3"]:
        """Unit directions in camera coordinates of the rays through `pixels` `(..., N, 2)`: the
        inverse of `project` up to depth, for any angle the lens takes in (a fisheye's beyond 90
        degrees too: `z < 0`, which `undistort_points` cannot express). The lens is inverted by
        Newton's method (as in `undistort_points`); differentiable. NaN for a pixel no ray of
        the lens reaches: outside a fisheye's image circle, beyond the fold of a pinhole's
        radial distortion (`undistort_points`).

        **Example:**

        ```python
        >>> import jax.numpy as jnp, numpy as np, mvcalib as mc
        >>> cam = mc.Camera(300.0, 300.0, 640.0, 480.0, jnp.eye(3), jnp.zeros(3), lens="fisheye")
        >>> ray = cam.rays(cam.project(jnp.array([[1.0, 0.0, -0.2]])))
        >>> np.round(np.asarray(ray) * np.hypot(1.0, 0.2), 6).tolist()  # 101 degrees off axis
        [[1.0, 0.0, -0.2]]

        ```
        """
        return _eagerly(Camera._rays, "Camera.rays", self, pixels, iterations)

    def _rays(self, px, iterations: int):
        """`rays` of validated pixels."""
        xd, yd = self._distorted_normalised(px)
        dist = jnp.broadcast_to(self.dist[..., None, :], (*xd.shape, self.dist.shape[-1]))
        if self.lens == "fisheye":
            # the radius with a derivative on the axis too (the square root's is infinite at 0,
            # and 0 * inf made the ray's gradient NaN at the principal point: a user's trial);
            # there theta ~ theta_d, and sin(theta) / theta_d -> 1, whose derivative is 0
            r2 = xd * xd + yd * yd
            positive = r2 > 0
            theta_d = jnp.where(positive, jnp.sqrt(jnp.where(positive, r2, 1.0)), 0.0)
            theta = _fisheye_inverse(theta_d, dist, self.dist, iterations)
            scale = jnp.where(positive, jnp.sin(theta) / jnp.where(positive, theta_d, 1.0), 1.0)
            return jnp.stack([xd * scale, yd * scale, jnp.cos(theta)], -1)
        xy, valid = _undistorted(jnp.stack([xd, yd], -1), dist, iterations)
        ray = jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], -1)
        return jnp.where(
            valid[..., None], ray / jnp.linalg.norm(ray, axis=-1, keepdims=True), jnp.nan
        )

    def _in_image_circle(self, u, v) -> Bool[Array, "*batch N"]:
        """Whether the pixels `(u, v)` (each `(..., N)`) of a fisheye lie inside its image
        circle, the radius its polynomial's principal branch reaches: where `rays` is finite
        (`_fisheye_angle`'s test, without the rays' Newton steps)."""
        yd = (v - self.v0[..., None]) / self.alpha_v[..., None]
        xd = (u - self.u0[..., None] - self.skew[..., None] * yd) / self.alpha_u[..., None]
        limit = _fisheye_limit(self.dist)[..., None]
        reach = _fisheye_polynomial(limit, self.dist[..., None, :])[0]
        return xd * xd + yd * yd <= reach * reach

    def _distorted_normalised(self, px):
        """`K^-1` of pixels `(..., N, 2)`: the distorted normalised coordinates `(x_d, y_d)`."""
        yd = (px[..., 1] - self.v0[..., None]) / self.alpha_v[..., None]
        xd = (px[..., 0] - self.u0[..., None] - self.skew[..., None] * yd) / self.alpha_u[..., None]
        return xd, yd

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_matrices(cls, K, R, t, dist=None, lens="pinhole") -> Camera:
        """A camera from `K` (upper triangular, `K[2, 2] = 1`), `R` and `t` as arrays."""
        K = jnp.asarray(K)
        K = K / K[..., 2:3, 2:3]
        return cls(
            alpha_u=K[..., 0, 0],
            alpha_v=K[..., 1, 1],
            u0=K[..., 0, 2],
            v0=K[..., 1, 2],
            skew=K[..., 0, 1],
            R=R,
            t=t,
            dist=dist,
            lens=lens,
        )

    @classmethod
    def stack(cls, cameras) -> Camera:
        """A rig from cameras (or rigs, of one lens), stacked along a new leading camera axis:
        say, two cameras calibrated one by one (`calibrate_planar`'s, OpenCV's) as the start of
        a stereo pair's `calibrate_rig(..., cameras=rig, fix=("intrinsics", "distortion"))`
        (OpenCV's `stereoCalibrate(..., CALIB_FIX_INTRINSIC)`; `fix="intrinsics"` estimates
        the distortion again).

        ```python
        >>> import numpy as np, mvcalib as mc
        >>> left = mc.Camera(800.0, 800.0, 640.0, 400.0, np.eye(3), [0.0, 0, 0])
        >>> right = mc.Camera(810.0, 810.0, 630.0, 410.0, np.eye(3), [-120.0, 0, 0])
        >>> mc.Camera.stack([left, right]).alpha_u.tolist()
        [800.0, 810.0]

        ```
        """
        cameras = list(cameras)
        if not cameras or not all(isinstance(c, Camera) for c in cameras):
            raise TypeError("`Camera.stack` takes a sequence of one or more `Camera`s.")
        lenses = {c.lens for c in cameras}
        if len(lenses) > 1:
            raise ValueError(f"a rig has one lens; got cameras of {sorted(lenses)}.")
        shapes = {c.batch_shape for c in cameras}
        if len(shapes) > 1:
            raise ValueError(f"cameras of one batch shape stack; got {sorted(shapes)}.")
        return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cameras)

    @classmethod
    def from_projection(cls, P, *, skew: bool = True) -> Camera:
        """Decompose `P ~ K [R | t]` in closed form (the paper's eqs. 16–23).

        `P` is scaled so that `||m3|| = 1` with the sign that makes `det(M) > 0` (M = P[:, :3]);
        for a camera in a right-handed world frame that is the sign that puts the points it sees
        in front of it (`mvcalib.dlt` fixes the sign from the points themselves; in a mirrored,
        left-handed world frame the points end up at negative depth, and every pixel is still
        right). Then `r3 = m3`, `Tz = m34`,
        `u0 = m1·m3`, `v0 = m2·m3` and

        - `skew=True` (default): `alpha_v = ||m2 - v0 m3||`, `r2 = (m2 - v0 m3) / alpha_v`,
          `skew = (m1 - u0 m3)·r2`, `alpha_u = ||m1 - u0 m3 - skew r2||`. This is the paper's
          eqs. 19–23 extended by one Gram–Schmidt step; with zero skew it is exactly them.
        - `skew=False`: the paper's eqs. 19–21 as printed, `alpha_u = sqrt(m1·m1 - u0^2)`,
          `r1 = (m1 - u0 m3) / alpha_u`, with the skew forced to zero.

        With the skew, `R` is orthonormal by construction (one Gram–Schmidt pass); the paper's
        `R` is re-orthogonalised to `U V^T` (its nearest rotation), with a derivative that exists
        at orthogonal `R` (see `nearest_rotation`). Batched over leading axes of `P`;
        differentiable.

        **Example:**

        ```python
        >>> import jax.numpy as jnp, mvcalib as mc
        >>> cam = mc.Camera(900.0, 880.0, 300.0, 200.0, jnp.eye(3), jnp.array([0.1, 0.2, 4.0]))
        >>> back = mc.Camera.from_projection(3.0 * cam.projection_matrix())
        >>> [round(float(x), 2) for x in (back.alpha_u, back.alpha_v, back.u0, back.t[2])]
        [900.0, 880.0, 300.0, 4.0]

        ```
        """
        P = _validate.floating("P", P, (3, 4))
        alpha_u, alpha_v, u0, v0, s, R, t = _decompose(P, skew=skew)
        return cls(alpha_u=alpha_u, alpha_v=alpha_v, u0=u0, v0=v0, skew=s, R=R, t=t)


def finite_cameras(cameras: Camera) -> Bool[Array, " C"]:
    """Per camera of a rig `(C,)`: whether all its parameters are finite (in NumPy where they
    are concrete: `_validate.derived`)."""
    return _validate.derived(
        lambda xp, *leaves: xp.stack(
            [xp.isfinite(x).reshape(x.shape[0], -1).all(-1) for x in leaves]
        ).all(0),
        *jax.tree_util.tree_leaves(cameras),
    )


def where_cameras(keep: Bool[Array, " C"], cameras: Camera, other: Camera) -> Camera:
    """Camera by camera, `cameras` where `keep`, else `other` (one camera, or a rig)."""
    pick = lambda x, y: jnp.where(keep.reshape(-1, *(1,) * (x.ndim - 1)), x, y)  # noqa: E731
    return jax.tree_util.tree_map(pick, cameras, other)


def usable_rig(cameras: Camera, mask: Bool[Array, "*batch C N"], stand_in: Camera | None = None):
    """`(cameras, mask, usable)`: a camera of the rig `(C,)` with a non-finite parameter (one that
    `calibrate` could not solve is NaN) hidden in `mask` and replaced by `stand_in`, so that its
    NaN reaches nothing, even where it is multiplied by a zero weight.

    `stand_in` is by default the first usable camera, for problems whose units come from the
    rig's cameras; finding it moves data between devices when the rig is split over several.
    Problems of one camera at a time (`refine`, the views of `triangulate`) take a finite camera
    of no consequence, `unit_camera`, and stay split.
    """
    usable = finite_cameras(cameras)
    stand_in = cameras[jnp.argmax(usable)] if stand_in is None else stand_in
    return where_cameras(usable, cameras, stand_in), mask & usable[:, None], usable


def placeholder(batch: tuple[int, ...], dtype, lens: str = "pinhole", fill=0.0) -> Camera:
    """Cameras of shape `batch` whose every parameter is `fill` (NumPy arrays), of the type of
    every `Camera` computed in `dtype` with this lens: what a program is compiled for before the
    cameras it will take are known (`_buckets.ahead`)."""
    shapes = _camera_shapes(np.dtype(dtype), lens)
    return jax.tree_util.tree_map(lambda x: np.full(batch + x.shape, fill, x.dtype), shapes)


@functools.cache
def _camera_shapes(dtype, lens: str):
    return jax.eval_shape(functools.partial(unit_camera, dtype, lens))


def unit_camera(dtype, lens: str = "pinhole") -> Camera:
    """A finite camera: unit focal lengths, at the origin, looking along z from z = -1."""
    one, zero = jnp.ones((), dtype), jnp.zeros((), dtype)
    t = jnp.array([0.0, 0.0, 1.0], dtype)
    return Camera(one, one, zero, zero, jnp.eye(3, dtype=dtype), t, lens=lens)


@functools.partial(jax.jit, static_argnames="skew")
def _decompose(P, skew: bool):
    kernel = _decompose_skew if skew else _decompose_paper
    return jnp.vectorize(kernel, signature="(3,4)->(),(),(),(),(),(3,3),(3)")(P)


# The decomposition's 3-vector products are written out (`_small.dot3`, `_small.triple`): under
# `vmap`, `@`, `jnp.linalg.norm` and `jnp.linalg.det` (an LU factorisation) each became a batched
# library call or a reduction over a short axis; written out, the decomposition of 4096 cameras
# took 0.074-0.092 against 0.104 µs per camera.
_dot = _small.dot3


def _norm(a):
    return jnp.sqrt(_dot(a, a))


def _normalise_projection(P):
    det = _small.triple(P[0, :3], P[1, :3], P[2, :3])
    return P * (jnp.where(det < 0, -1.0, 1.0) / _norm(P[2, :3]))


def _decompose_skew(P):
    P = _normalise_projection(P)
    m1, m2, m3 = P[0, :3], P[1, :3], P[2, :3]
    m14, m24, m34 = P[0, 3], P[1, 3], P[2, 3]
    u0, v0 = _dot(m1, m3), _dot(m2, m3)  # eq. 17
    q2 = m2 - v0 * m3
    alpha_v = _norm(q2)  # eq. 19 (|| m2 - v0 m3 || = sqrt(m2.m2 - v0^2))
    r2 = q2 / alpha_v  # eq. 21
    q1 = m1 - u0 * m3
    s = _dot(q1, r2)  # zero for the paper's skew-free camera
    q1 = q1 - s * r2
    alpha_u = _norm(q1)  # eq. 19 with the skew removed
    r1 = q1 / alpha_u  # eq. 20
    tz = m34  # eq. 16
    ty = (m24 - v0 * tz) / alpha_v  # eq. 23
    tx = (m14 - u0 * tz - s * ty) / alpha_u  # eq. 22 with the skew term
    # Gram–Schmidt of (m3, m2, m1): r1, r2, r3 are orthonormal by construction (to rounding),
    # and right-handed since det(M) = alpha_u alpha_v det(R) > 0; nothing to re-orthogonalise.
    R = jnp.stack([r1, r2, m3])
    return alpha_u, alpha_v, u0, v0, s, R, jnp.stack([tx, ty, tz])


def _decompose_paper(P):
    P = _normalise_projection(P)
    m1, m2, m3 = P[0, :3], P[1, :3], P[2, :3]
    m14, m24, m34 = P[0, 3], P[1, 3], P[2, 3]
    u0, v0 = _dot(m1, m3), _dot(m2, m3)  # eq. 17-18
    alpha_u = jnp.sqrt(_dot(m1, m1) - u0**2)  # eq. 19
    alpha_v = jnp.sqrt(_dot(m2, m2) - v0**2)
    r1 = (m1 - u0 * m3) / alpha_u  # eq. 20
    r2 = (m2 - v0 * m3) / alpha_v  # eq. 21
    tz = m34  # eq. 16
    tx = (m14 - u0 * tz) / alpha_u  # eq. 22
    ty = (m24 - v0 * tz) / alpha_v  # eq. 23
    R = nearest_rotation(jnp.stack([r1, r2, m3]))  # "R = U V^T"
    return alpha_u, alpha_v, u0, v0, jnp.zeros_like(u0), R, jnp.stack([tx, ty, tz])


def distort(xy, dist):
    """Brown–Conrady distortion of normalised coordinates `(..., 2)`, OpenCV's model and order.

    `dist = (k1, k2, p1, p2, k3)`, broadcast against `xy[..., 0]`. (A fisheye's image of a ray
    is `Camera(..., lens="fisheye").project`: its distortion acts on the ray's angle, not on
    normalised coordinates.)

    **Example:**

    ```python
    >>> import jax.numpy as jnp, mvcalib as mc
    >>> mc.distort(jnp.array([0.5, 0.0]), jnp.array([-0.25, 0.0, 0.0, 0.0, 0.0])).tolist()
    [0.46875, 0.0]

    ```
    """
    shape = tuple(jnp.shape(dist))
    if shape[-1:] != (5,):
        hint = " (a fisheye's four? `Camera(..., lens='fisheye').project`)" if shape[-1:] == (
            4,) else ""  # fmt: skip
        raise ValueError(f"`dist` holds (k1, k2, p1, p2, k3), shape (..., 5); got {shape}{hint}.")
    return jnp.stack(_distort(xy[..., 0], xy[..., 1], dist), -1)


def _distort(x, y, dist):
    """`distort` by components: `(x_d, y_d)` from `x` and `y`."""
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def _lens(xc, dist):
    """Camera coordinates `[X, Y, Z]` (arrays) to distorted normalised `(x_d, y_d)` through the
    lens that `dist`'s number of coefficients names (`lens_of`)."""
    if lens_of(dist) == "fisheye":
        return _fisheye(*xc, dist)
    return _distort(xc[0] / xc[2], xc[1] / xc[2], dist)


def _fisheye_polynomial(theta, dist):
    """`theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)` and its derivative
    in `theta`."""
    k1, k2, k3, k4 = (dist[..., i] for i in range(4))
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    slope = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    return theta_d, slope


def _fisheye(X, Y, Z, dist):
    """Kannala–Brandt: `(x_d, y_d) = theta_d (X, Y) / rho`, `theta = atan2(rho, Z)`, `rho` the
    distance from the optical axis. On the axis `theta_d / rho` is its limit `1 / Z` in front of
    the camera; straight behind it (180 degrees) the direction in the image is undefined: NaN
    (it was the principal point, as straight ahead). The `where`s keep the derivative finite."""
    r2 = X * X + Y * Y
    on_axis = r2 == 0
    rho = jnp.sqrt(jnp.where(on_axis, 1.0, r2))
    theta_d, _ = _fisheye_polynomial(jnp.arctan2(rho, Z), dist)
    scale = jnp.where(
        on_axis, jnp.where(Z > 0, 1.0 / jnp.where(Z > 0, Z, 1.0), jnp.nan), theta_d / rho
    )
    return X * scale, Y * scale


def _fisheye_limit(dist, samples: int = 64, halvings: int = 40):
    """The end `(...)` of the lens's principal branch, for coefficients `dist (..., 4)`: the first
    angle in `(0, pi]` at which `theta_d` stops increasing (a zero of its slope, to ~1e-12 rad),
    or pi. Beyond it the polynomial folds back, and an image radius has a second angle (or none):
    the slope is sampled every pi / `samples` and its first sign change bisected."""
    theta = jnp.pi * jnp.arange(1, samples + 1, dtype=dist.dtype) / samples
    falling = _fisheye_polynomial(theta, dist[..., None, :])[1] <= 0  # (..., samples)
    folds = jnp.any(falling, -1)
    first = jnp.argmax(falling, -1)
    lo = jnp.where(first > 0, theta[jnp.maximum(first - 1, 0)], 0.0)
    hi = theta[first]

    def halve(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        down = _fisheye_polynomial(mid, dist)[1] <= 0
        return jnp.where(down, lo, mid), jnp.where(down, mid, hi)

    lo, _ = jax.lax.fori_loop(0, halvings, halve, (lo, hi))
    return jnp.where(folds, lo, jnp.pi)


@functools.partial(jax.jit, static_argnames="iterations")
def _fisheye_inverse(theta_d, dist, lens, iterations):
    """`_fisheye_angle` of the radii `theta_d (..., N)` on the principal branch of each camera's
    lens `lens (..., 4)` (`dist`, its coefficients per radius): one compiled program, whose two
    loops compiled apart, called eagerly, doubled a first call of `undistort_points`."""
    return _fisheye_angle(theta_d, dist, _fisheye_limit(lens)[..., None], iterations)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _fisheye_angle(theta_d, dist, limit, iterations):
    """The ray's angle `theta` in `[0, limit]` (the lens's principal branch, `_fisheye_limit`)
    with `_fisheye_polynomial(theta) = theta_d`, NaN where the branch does not reach `theta_d`
    (outside the lens's image circle). Newton's method from `theta_d`, at most `iterations`
    steps, kept inside a bracket of the root that each step narrows (a step that would leave it,
    or shrink less than by half, halves it instead): unguarded Newton steps overshot beyond the
    fold of a wide lens's polynomial and answered with its other angle, or with none (a lens
    monotone to 105 degrees: a ray 93 degrees off axis came back at 105.25, 39 px away when
    projected). The steps stop once every angle is at its root to rounding (each then held, so
    that an angle does not depend on the others in the batch): a million rays 80 degrees off
    axis at most, ~5 steps. The derivative is the exact inverse's (implicit), as for
    `_undistort`."""
    limit = jax.lax.stop_gradient(limit)
    tolerance = 4 * jnp.finfo(theta_d.dtype).eps * theta_d

    def newton(carry):
        k, theta, lo, hi, last, done = carry
        value, slope = _fisheye_polynomial(theta, dist)
        miss = value - theta_d
        lo, hi = jnp.where(miss > 0, lo, theta), jnp.where(miss > 0, theta, hi)
        step = theta - miss / slope
        # Newton's step where it stays in the bracket and is at most half the last step (as
        # Numerical Recipes' rtsafe): else, as where Newton went back and forth across a wide
        # bracket, bisection (False where the slope is zero)
        newton = (step >= lo) & (step <= hi) & (2 * jnp.abs(miss) <= jnp.abs(last * slope))
        # at the root to rounding, stay: XLA may round `value` differently where it recomputes
        # it for `step`, which then lands a rounding outside the bracket (and would halve it)
        there = done | (jnp.abs(miss) <= tolerance)
        new = jnp.where(there, theta, jnp.where(newton, step, 0.5 * (lo + hi)))
        return k + 1, new, lo, hi, new - theta, there

    def more(carry):
        k, *_, done = carry
        return (k < iterations) & ~jnp.all(done)

    limit = jnp.broadcast_to(limit, theta_d.shape)
    reached = theta_d <= _fisheye_polynomial(limit, dist)[0]  # (False for NaN)
    zero = jnp.zeros_like(theta_d)
    start = (0, jnp.clip(theta_d, 0.0, limit), zero, limit, limit, ~reached)
    theta = jax.lax.while_loop(more, newton, start)[1]
    return jnp.where(reached, theta, jnp.nan)


@_fisheye_angle.defjvp
def _fisheye_angle_jvp(iterations, primals, tangents):
    (theta_d, dist, limit), (d_theta_d, d_dist, _) = primals, tangents
    theta = _fisheye_angle(theta_d, dist, limit, iterations)
    value = lambda dist: _fisheye_polynomial(theta, dist)[0]  # noqa: E731
    by_dist = jax.jvp(value, (dist,), (d_dist,))[1]
    return theta, (d_theta_d - by_dist) / _fisheye_polynomial(theta, dist)[1]


def _distortion_jacobian(x, y, dist):
    """The 2 x 2 Jacobian `[[a, b], [b, d]]` of `_distort` at `(x, y)` (it is symmetric), in
    closed form: elementwise work, not a batched LAPACK solve per point (30x faster on CPU)."""
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)  # d radial / d r2
    a = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, d


def _solve_jacobian(x, y, dist, r):
    """`J^-1 r` for the distortion Jacobian `J` at `(x, y)` and `r (..., 2)`, by Cramer's rule."""
    a, b, d = _distortion_jacobian(x, y, dist)
    det = a * d - b * b
    return (
        jnp.stack([d * r[..., 0] - b * r[..., 1], a * r[..., 1] - b * r[..., 0]], -1)
        / det[..., None]
    )


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _undistort(target, dist, iterations):
    """The normalised `xy (..., 2)` with `distort(xy, dist) = target`: Newton's method from the
    distorted point, a fixed number of steps (a step to a non-finite point is not taken, so that
    `xy` stays finite: `_undistorted` judges it). Its derivative is that of the exact inverse
    (implicit differentiation: `J dxy = dtarget - d distort / d dist`), not of the steps, so
    nested derivatives do not go through the loop."""

    def newton(xy, _):
        x, y = xy[..., 0], xy[..., 1]
        step = xy - _solve_jacobian(x, y, dist, distort(xy, dist) - target)
        return jnp.where(jnp.isfinite(step), step, xy), None

    return jax.lax.scan(newton, target, None, length=iterations)[0]


def _undistorted(target, dist, iterations):
    """`_undistort`, and where its answer is the lens's ray: `(xy, valid)`, `valid` False where
    Newton's method found no root (a distorted point beyond the farthest the lens reaches) or
    a root beyond the fold of the radial distortion, where `r (1 + k1 r^2 + k2 r^4 + k3 r^6)`
    has stopped increasing (a second ray through the pixel, the mirror image of none). Both
    came back as answers: an OpenCV user's trial, k1 -0.19 fitted on a 1280 x 720 camera, put
    the corner pixel (2, 2) in the opposite corner (2554, 1441), which projects back to (2, 2)
    exactly. `xy` is finite where the input is; `valid` carries no derivative."""
    xy = _undistort(target, dist, iterations)
    x, y, d, t = jax.lax.stop_gradient((xy[..., 0], xy[..., 1], dist, target))
    miss = jnp.stack(_distort(x, y, d), -1) - t
    solved = jnp.all(jnp.abs(miss) <= jnp.sqrt(jnp.finfo(t.dtype).eps) * (1.0 + jnp.abs(t)), -1)
    return xy, solved & _before_fold(x * x + y * y, d)


def _before_fold(s, dist):
    """Whether the radial distortion's slope `1 + 3 k1 s' + 5 k2 s'^2 + 7 k3 s'^3` (in `r`, with
    `s' = r^2`) is positive on all of `[0, s]`: its least value there is at `s` or at a zero in
    `(0, s)` of its derivative in `s'` (a quadratic), so that exactly these are tried."""
    k1, k2, k3 = dist[..., 0], dist[..., 1], dist[..., 4]
    slope = lambda s: 1.0 + s * (3.0 * k1 + s * (5.0 * k2 + s * 7.0 * k3))  # noqa: E731
    # the zeros of 3 k1 + 10 k2 s + 21 k3 s^2 (one, where k3 is zero)
    a, b, c = 21.0 * k3, 10.0 * k2, 3.0 * k1
    disc = b * b - 4.0 * a * c
    root = jnp.sqrt(jnp.maximum(disc, 0.0))
    quadratic = a != 0
    safe_a = jnp.where(quadratic, a, 1.0)
    linear = jnp.where(b != 0, -c / jnp.where(b != 0, b, 1.0), -1.0)
    stations = [
        jnp.where(quadratic, (-b - root) / (2.0 * safe_a), linear),
        jnp.where(quadratic, (-b + root) / (2.0 * safe_a), -1.0),
    ]
    positive = slope(s) > 0
    for z in stations:
        inside = (~quadratic | (disc >= 0)) & (z > 0) & (z < s)
        positive &= ~inside | (slope(z) > 0)
    return positive


@_undistort.defjvp
def _undistort_jvp(iterations, primals, tangents):
    (target, dist), (d_target, d_dist) = primals, tangents
    xy = _undistort(target, dist, iterations)
    by_dist = jax.jvp(lambda dist: distort(xy, dist), (dist,), (d_dist,))[1]
    return xy, _solve_jacobian(xy[..., 0], xy[..., 1], dist, d_target - by_dist)


def undistort_points(camera: Camera, pixels, *, iterations: int = 20):
    """Remove `camera`'s lens distortion from observed pixels (the inverse of `distort`).

    Returns the pixels an ideal pinhole camera with the same `K` would have seen, like
    `cv2.undistortPoints(pixels, K, dist, P=K)` (`cv2.fisheye.undistortPoints` for a fisheye).
    Solved per point by Newton's method on the 2 x 2 distortion Jacobian (a fisheye's: on the
    ray's angle), starting from the distorted point, for a fixed number of iterations (static
    shapes); `pixels` is `(..., N, 2)` and broadcasts against the camera's batch shape.
    Differentiable: the derivative is that of the exact inverse (implicit, from the Jacobian at
    the answer), not of the iterations. A fisheye's rays at 90 degrees or more off axis have no
    pinhole pixel: NaN (`Camera.rays` gives every ray). So is a pixel beyond the fold of a
    pinhole's radial distortion (where `r (1 + k1 r^2 + k2 r^4 + k3 r^6)` stops increasing:
    its points are the mirror image of rays inside it, or of none), and one Newton's method
    leaves unsolved; `cv2.undistortPoints` answers there with a wrong point.

    **Example:**

    ```python
    >>> import jax.numpy as jnp, numpy as np, mvcalib as mc
    >>> cam = mc.Camera(800.0, 800.0, 320.0, 240.0, jnp.eye(3), jnp.array([0.0, 0.0, 4.0]),
    ...                 dist=jnp.array([-0.2, 0.05, 0.0, 0.0, 0.0]))
    >>> world = jnp.array([[1.0, 0.5, 0.0]])
    >>> np.round(np.asarray(mc.undistort_points(cam, cam.project(world))), 3).tolist()
    [[520.0, 340.0]]

    ```
    """
    return _eagerly(_undistortion, "undistort_points", camera, pixels, iterations)


def _undistortion(camera: Camera, px, iterations: int):
    """`undistort_points` of validated pixels."""
    if camera.lens == "fisheye":
        ray = camera._rays(px, iterations)  # noqa: SLF001
        valid = ray[..., 2] > 0  # beside or behind the image plane: no pinhole pixel
        xy = (
            jnp.where(valid[..., None], ray[..., :2], 0.0)
            / jnp.where(valid, ray[..., 2], 1.0)[..., None]
        )
    else:
        target = jnp.stack(camera._distorted_normalised(px), -1)
        dist = jnp.broadcast_to(camera.dist[..., None, :], (*target.shape[:-1], 5))
        xy, valid = _undistorted(target, dist, iterations)
    # (NaN put in last: a NaN times the focal length made its derivative NaN for every pixel)
    u = camera.alpha_u[..., None] * xy[..., 0] + camera.skew[..., None] * xy[..., 1]
    v = camera.alpha_v[..., None] * xy[..., 1] + camera.v0[..., None]
    return jnp.where(valid[..., None], jnp.stack([u + camera.u0[..., None], v], -1), jnp.nan)


def image_to_pixel(image_xy, pixel_size, *, image_size=None, center=None, sx: float = 1.0):
    """Tsai's conversion from image-plane coordinates to pixels (the paper's Section IV.2).

    `Xf = Sx dx^-1 Xd + Cx`, `Yf = dy^-1 Yd + Cy`, where `(dx, dy) = pixel_size` is the centre
    to centre distance of sensor elements (e.g. mm) and `(Cx, Cy)` the image centre, by default
    the midpoint of the pixel array `(width / 2, height / 2)` as the paper takes it (it has a
    1000 x 1100 image and centre (500, 550)). Give either `image_size=(width, height)` or `center`.
    (With mvcalib's pixels, whose integer coordinates are pixel centres, the array's geometric
    centre is half a pixel less, `((width - 1) / 2, (height - 1) / 2)`, where OpenPTV's files put
    it (`mvcalib.io.load_openptv_calibration`): pass it as `center` to match them.)

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> mc.image_to_pixel([0.0, 0.0], (0.01, 0.01), image_size=(1000, 1100)).tolist()
    [500.0, 550.0]

    ```
    """
    center = _image_center(image_size, center)
    xy = _validate.floating("image_xy", image_xy)
    dx, dy = (jnp.asarray(p, xy.dtype) for p in pixel_size)
    return jnp.stack([sx * xy[..., 0] / dx + center[0], xy[..., 1] / dy + center[1]], -1)


def pixel_to_image(pixels, pixel_size, *, image_size=None, center=None, sx: float = 1.0):
    """Inverse of `image_to_pixel`: pixels to image-plane coordinates in the units of `pixel_size`.

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> mc.pixel_to_image([600.0, 550.0], (0.01, 0.01), image_size=(1000, 1100)).tolist()
    [1.0, 0.0]

    ```
    """
    center = _image_center(image_size, center)
    px = _validate.floating("pixels", pixels)
    dx, dy = (jnp.asarray(p, px.dtype) for p in pixel_size)
    return jnp.stack([(px[..., 0] - center[0]) * dx / sx, (px[..., 1] - center[1]) * dy], -1)


def _image_center(image_size, center):
    if (image_size is None) == (center is None):
        raise ValueError("give exactly one of `image_size=(width, height)` or `center=(cx, cy)`.")
    if center is None:
        width, height = image_size
        return (width / 2.0, height / 2.0)
    return tuple(np.asarray(center, dtype=float).tolist())
