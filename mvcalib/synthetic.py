"""Synthetic rigs with ground truth, for tests, demos and benchmarks. Deterministic given a key
and a dtype: JAX draws random numbers per dtype, so the same key gives another rig in float32
(x64 off, JAX's default) than in float64; to compare the two, make the rig once (`dtype=`) and
cast it."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from . import _buckets
from ._camera import Camera
from ._registration import RigidTransform
from ._render import dot_normals as dot_normals
from ._render import ellipse_centres as ellipse_centres
from ._render import render as render
from ._render import true_centres as true_centres
from ._render import visible_dots as visible_dots
from .targets import Target, box_corner

__all__ = [
    "SyntheticRig", "random_cameras", "random_rig", "observe", "look_at",
    "PaperScene", "paper_scene", "BoardRig", "board", "board_rig",
    "render", "visible_dots", "true_centres", "ellipse_centres", "dot_normals",
]  # fmt: skip


class SyntheticRig(eqx.Module):
    """Cameras with known parameters looking at a target, and what they observe.

    - `cameras`: the true cameras, batch `(C,)`.
    - `world`: target points `(N, 3)` (shared by all cameras).
    - `pixels_true`: exact projections `(C, N, 2)`; `pixels`: with Gaussian noise added.
    - `mask`: `(C, N)`, True where the point is in front of the camera and inside the image.
    """

    cameras: Camera
    world: Float[Array, "N 3"]
    pixels_true: Float[Array, "C N 2"]
    pixels: Float[Array, "C N 2"]
    mask: Bool[Array, "C N"]
    image_size: tuple[int, int] = eqx.field(static=True)


def look_at(center, target, up, roll=0.0):
    """World-to-camera `(R, t)` of a camera at `center` looking at `target` (x right, y down)."""
    forward = target - center
    z = forward / jnp.linalg.norm(forward, axis=-1, keepdims=True)
    x = jnp.cross(z, up)
    x = x / jnp.linalg.norm(x, axis=-1, keepdims=True)
    y = jnp.cross(z, x)
    c, s = jnp.cos(roll)[..., None], jnp.sin(roll)[..., None]
    x, y = c * x + s * y, -s * x + c * y
    R = jnp.stack([x, y, z], axis=-2)
    t = -jnp.einsum("...ij,...j->...i", R, center)
    return R, t


def _default_dtype(dtype):
    return jnp.result_type(float) if dtype is None else jnp.dtype(dtype)


def random_cameras(
    key,
    n_cameras: int,
    target: Target | None = None,
    *,
    image_size: tuple[int, int] = (1000, 1100),
    focal: tuple[float, float] = (800.0, 2000.0),
    max_angle: float = 30.0,
    fill: tuple[float, float] = (0.45, 0.8),
    dtype=None,
) -> Camera:
    """Realistic random cameras around `target` (default: `targets.box_corner()`).

    Each camera looks at the target's centroid (jittered by 5 % of its size) from a direction
    within `max_angle` degrees of the diagonal `(1, 1, 1)` of the box corner, with a random roll
    of up to 15 degrees, focal length in `focal` (pixels), aspect ratio within 2 %, principal point
    within 30 px of the image centre, and a distance such that the target fills the fraction
    `fill` of the image's smaller side.
    """
    target = box_corner() if target is None else target
    return _random_cameras(
        key,
        jnp.asarray(target.points, _default_dtype(dtype)),
        n_cameras,
        image_size=tuple(image_size),
        focal=tuple(focal),
        max_angle=float(max_angle),
        fill=tuple(fill),
        quick=n_cameras * len(target.points) <= _buckets.COMPACT,  # (`_buckets.jit`)
    )


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _random_cameras(key, pts, n_cameras, *, image_size, focal, max_angle, fill) -> Camera:
    dtype = pts.dtype
    width, height = image_size
    keys = jax.random.split(key, 8)
    C = n_cameras
    uniform = lambda k, lo, hi, shape=(C,): jax.random.uniform(k, shape, dtype, lo, hi)  # noqa: E731

    centre = pts.mean(0)
    radius = jnp.max(jnp.linalg.norm(pts - centre, axis=-1))
    diag = jnp.ones(3, dtype) / jnp.sqrt(3.0)
    # A direction within max_angle of the diagonal: tilt it about a random perpendicular axis.
    axis = jax.random.normal(keys[0], (C, 3), dtype)
    axis = axis - (axis @ diag)[:, None] * diag
    axis = axis / jnp.linalg.norm(axis, axis=-1, keepdims=True)
    tilt = jnp.deg2rad(max_angle) * jnp.sqrt(uniform(keys[1], 0.0, 1.0))
    direction = jnp.cos(tilt)[:, None] * diag + jnp.sin(tilt)[:, None] * jnp.cross(axis, diag)

    f = uniform(keys[2], *focal)
    aspect = uniform(keys[3], 0.98, 1.02)
    frac = uniform(keys[4], *fill)
    distance = radius * f / (frac * min(width, height) / 2.0)
    look = centre + 0.05 * radius * jax.random.normal(keys[5], (C, 3), dtype)
    up = jnp.array([0.0, 0.0, 1.0], dtype)
    roll = jnp.deg2rad(uniform(keys[6], -15.0, 15.0))
    R, t = look_at(centre + distance[:, None] * direction, look, up, roll)
    pp = uniform(keys[7], -30.0, 30.0, (C, 2))
    return Camera(f, f * aspect, width / 2.0 + pp[:, 0], height / 2.0 + pp[:, 1], R, t)


def observe(key, cameras: Camera, world, noise: float, image_size) -> tuple:
    """Project `world` with `cameras`, add Gaussian pixel noise; return (true, noisy, mask)."""
    true = cameras.project(world)
    noisy = true + noise * jax.random.normal(key, true.shape, true.dtype)
    width, height = image_size
    inside = (
        (true[..., 0] >= 0)
        & (true[..., 0] <= width - 1)
        & (true[..., 1] >= 0)
        & (true[..., 1] <= height - 1)
    )
    mask = inside & (cameras.depth(world) > 0)
    return true, noisy, mask


@_buckets.eager
def _split(key):
    """`jax.random.split(key)` as two keys: one program where called eagerly (the split and
    the unpacking would compile one each)."""
    first, second = jax.random.split(key)
    return first, second


def random_rig(
    key,
    n_cameras: int = 4,
    target: Target | None = None,
    *,
    noise: float = 0.0,
    image_size: tuple[int, int] = (1000, 1100),
    dtype=None,
    **camera_options,
) -> SyntheticRig:
    """A rig of `n_cameras` random cameras (see `random_cameras`) observing `target`.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=8, noise=0.5)
    >>> rig.pixels.shape, bool(rig.mask.all())
    ((8, 19, 2), True)

    ```
    """
    target = box_corner() if target is None else target
    k_cam, k_noise = _split(key)
    cameras = random_cameras(
        k_cam, n_cameras, target, image_size=image_size, dtype=dtype, **camera_options
    )
    world = jnp.asarray(target.points, cameras.R.dtype)
    quick = n_cameras * len(world) <= _buckets.COMPACT  # (`_buckets.jit`)
    return _observe_rig(k_noise, cameras, world, noise, tuple(image_size), quick=quick)


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _observe_rig(key, cameras, world, noise, image_size) -> SyntheticRig:
    true, noisy, mask = observe(key, cameras, world, noise, image_size)
    return SyntheticRig(cameras, world, true, noisy, mask, image_size)


class PaperScene(eqx.Module):
    """The paper's experiment: one camera, four snapshots of the target in four placements.

    The camera stays where it is in the room (global frame); the target is put down in four
    placements, so each snapshot sees it from another position and orientation, and each
    calibration is expressed in that snapshot's local (target) frame. Registering every local
    frame into the global one must give back the same camera, so that a fixed room point lands
    on one pixel from all four (the paper's Section IV.2).

    - `camera`: the true camera in the global frame.
    - `local_cameras`: the same camera in each snapshot's local frame, batch `(4,)`.
    - `placements`: local-to-global transforms of the target, batch `(4,)`.
    - `world`: target dots in the local frame `(19, 3)`.
    - `world_global`: measured global coordinates of the `registration_ids` dots `(4, 18, 3)`.
    - `pixels`, `pixels_true`, `mask`: observations `(4, 19, 2)` and visibility `(4, 19)`.
    - `calibration_ids`: the 8 dots used for the DLT; `registration_ids`: the 18 measured in both
      frames.
    - `fixed_point`: a room point (global frame) in the working volume where the target stood,
      placed on the ray of a whole pixel, so that any estimate within half a pixel rounds to it.
    """

    camera: Camera
    local_cameras: Camera
    placements: RigidTransform
    world: Float[Array, "19 3"]
    world_global: Float[Array, "4 18 3"]
    pixels_true: Float[Array, "4 19 2"]
    pixels: Float[Array, "4 19 2"]
    mask: Bool[Array, "4 19"]
    calibration_ids: tuple[int, ...] = eqx.field(static=True)
    registration_ids: tuple[int, ...] = eqx.field(static=True)
    fixed_point: Float[Array, 3]
    image_size: tuple[int, int] = eqx.field(static=True)


def paper_scene(
    key=None, *, noise: float = 0.3, global_noise: float = 0.0, dtype=None
) -> PaperScene:
    """The synthetic version of the paper's experiment (see `PaperScene`).

    1000 x 1100 images (width x height), the 19-dot box-corner target, 8 dots per snapshot for
    calibration (spread over the three faces), 18 for registration, Gaussian pixel noise `noise`
    and global-coordinate measurement noise `global_noise` (in the target's units).

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> scene = mc.synthetic.paper_scene(noise=0.0)
    >>> scene.pixels.shape, len(scene.calibration_ids), scene.world_global.shape
    ((4, 19, 2), 8, (4, 18, 3))

    ```
    """
    key = jax.random.key(2010) if key is None else key
    target = box_corner()
    world = jnp.asarray(target.points, _default_dtype(dtype))
    ids = tuple(int(i) for i in target.global_ids)
    return _paper_scene(key, world, ids, noise, global_noise, quick=True)


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _paper_scene(key, world, registration_ids, noise, global_noise) -> PaperScene:
    dtype = world.dtype
    image_size = (1000, 1100)
    k_views, k_noise, k_global = jax.random.split(key, 3)
    # Four views of the target by one camera: same intrinsics, four poses relative to the target.
    views = _random_cameras(
        k_views,
        world,
        4,
        image_size=image_size,
        focal=(1400.0, 1400.0),
        max_angle=30.0,
        fill=(0.45, 0.8),
    )
    intrinsics = dict(alpha_u=1400.0, alpha_v=1392.0, u0=512.0, v0=541.0)
    local = Camera(R=views.R, t=views.t, **intrinsics)
    # The camera in the room: 2.5 m up and back from the room origin, looking at it.
    R_g, t_g = look_at(
        jnp.array([-1500.0, -1800.0, 1600.0], dtype),
        jnp.zeros(3, dtype),
        jnp.array([0.0, 0.0, 1.0], dtype),
    )
    camera = Camera(R=R_g, t=t_g, **intrinsics)
    # local -> global = (global -> camera)^-1 o (local -> camera)
    placements = RigidTransform(R_g, t_g).inverse() @ RigidTransform(local.R, local.t)

    true, noisy, mask = observe(k_noise, local, world, noise, image_size)
    exact_global = placements.apply(world[np.asarray(registration_ids)])
    world_global = exact_global + global_noise * jax.random.normal(
        k_global, exact_global.shape, dtype
    )
    # The fixed room point: in the middle of the target's four placements, moved onto the ray of
    # the nearest whole pixel.
    middle = placements.apply(world).mean(axis=(0, 1))
    pixel = jnp.round(camera.project(middle[None])[0])
    ray = jnp.linalg.solve(camera.K, jnp.array([pixel[0], pixel[1], 1.0], dtype))
    depth = camera.depth(middle[None])[0]
    fixed_point = RigidTransform(R_g, t_g).inverse().apply((depth * ray / ray[2])[None])[0]
    return PaperScene(
        camera=camera,
        local_cameras=local,
        placements=placements,
        world=world,
        world_global=world_global,
        pixels_true=true,
        pixels=noisy,
        mask=mask,
        calibration_ids=(0, 2, 4, 7, 9, 11, 13, 16),
        registration_ids=registration_ids,
        fixed_point=fixed_point,
        image_size=image_size,
    )


# ------------------------------------------------------------------------------ moving target
class BoardRig(eqx.Module):
    """A rig of cameras around a volume through which a target is moved: the ground truth of
    `mvcalib.calibrate_rig`.

    - `cameras`: the true cameras `(C,)`, in the world frame.
    - `target`: the target's points `(N, 3)` in its own frame (a board has z = 0).
    - `poses`: the target's pose in each frame, target to world, a `RigidTransform` `(F,)`.
    - `pixels_true`: exact projections `(C, F, N, 2)`; `pixels`: with Gaussian noise added.
    - `mask`: `(C, F, N)`: True where camera c saw point n in frame f.
    """

    cameras: Camera
    target: Float[Array, "N 3"]
    poses: RigidTransform
    pixels_true: Float[Array, "C F N 2"]
    pixels: Float[Array, "C F N 2"]
    mask: Bool[Array, "C F N"]
    image_size: tuple[int, int] = eqx.field(static=True)


def board(rows: int = 9, cols: int = 12, spacing: float = 0.06) -> np.ndarray:
    """The `rows x cols` inner corners of a chessboard (or a dot grid) of `spacing`, `(N, 3)`,
    z = 0, row by row."""
    y, x = np.mgrid[:rows, :cols]
    return np.c_[x.ravel() * spacing, y.ravel() * spacing, np.zeros(rows * cols)]


def board_rig(
    key,
    n_cameras: int = 8,
    n_frames: int = 100,
    target: np.ndarray | str = "board",
    *,
    noise: float = 0.0,
    distortion: bool = True,
    dropped: tuple[float, float] | None = None,
    radius: float = 1.6,
    volume: float = 1.2,
    image_size: tuple[int, int] = (1280, 800),
    dtype=None,
) -> BoardRig:
    """Cameras in a ring around a volume through which a target moves (metres).

    The cameras stand on a circle of `radius` around the origin, evenly spaced with 10 degrees
    of jitter, 0-0.4 m up or down, looking at the origin (jittered by 0.1 m) with focal lengths
    of 900-1300 px, the principal point within 20 px of the image centre and, with
    `distortion`, k1 in [-0.25, 0.05] and k2 in [-0.05, 0.1]. In each frame the target is
    somewhere in the cube of side `volume` around the origin. A board (`target="board"`, 9 x 12
    corners 6 cm apart, or any planar `(N, 3)` array with z = 0) faces a randomly chosen camera
    within 40 degrees and is seen by the cameras in front of it (within 70 degrees of its
    normal); a 3-D target (`"object"`: the three faces of a 30 cm box corner, 48 points, or any
    array) takes any orientation and is seen from everywhere. Each camera also misses a random
    fraction of its frames, drawn from `dropped` per camera (default 0-30 % for a board, 40-75 %
    for an object), and the points outside its image.

    A board shows its -z side to the cameras that see it, where `render` prints a planar
    target's dots on its +z side (`dot_normals`): to render a camera's photo of frame `f`, pose
    the camera on the board (`R_c R_f`, `R_c t_f + t_c`) and pass
    `normals=np.tile([0.0, 0.0, -1.0], (len(points), 1))`, or the photo is blank.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> rig = mc.synthetic.board_rig(jax.random.key(0), n_cameras=4, n_frames=10, noise=0.3)
    >>> rig.pixels.shape, rig.target.shape
    ((4, 10, 108, 2), (108, 3))

    ```
    """
    dtype = _default_dtype(dtype)
    if isinstance(target, str):
        if target == "board":
            target = board()
        elif target == "object":
            g = (np.arange(4) + 0.5) * 0.3 / 4
            u, v = (x.ravel() for x in np.meshgrid(g, g))
            z = np.zeros_like(u)
            target = np.concatenate([np.c_[u, v, z], np.c_[u, z, v], np.c_[z, u, v]])
        else:
            raise ValueError(f"`target` is 'board', 'object' or an (N, 3) array; got {target!r}.")
    target = np.asarray(target, dtype=float)
    planar = bool(np.all(target[:, 2] == 0))
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel())
    C, F = n_cameras, n_frames

    # the cameras
    azimuth = 2 * np.pi * np.arange(C) / C + np.deg2rad(rng.uniform(-10, 10, C))
    centers = np.c_[radius * np.cos(azimuth), radius * np.sin(azimuth), rng.uniform(-0.4, 0.4, C)]
    R, t = look_at(
        jnp.asarray(centers), jnp.asarray(rng.uniform(-0.1, 0.1, (C, 3))), jnp.array([0, 0, -1.0])
    )
    f = rng.uniform(900, 1300, C)
    width, height = image_size
    dist = np.zeros((C, 5))
    if distortion:
        dist[:, 0], dist[:, 1] = rng.uniform(-0.25, 0.05, C), rng.uniform(-0.05, 0.1, C)
    cameras = Camera(
        f, f * rng.uniform(0.99, 1.01, C),
        (width - 1) / 2 + rng.uniform(-20, 20, C), (height - 1) / 2 + rng.uniform(-20, 20, C),
        np.asarray(R), np.asarray(t), dist=dist,
    )  # fmt: skip

    # the target's poses: a board's normal (its z, away from the cameras it faces) points away
    # from a chosen camera, within 40 degrees
    positions = rng.uniform(-volume / 2, volume / 2, (F, 3))
    if planar:
        toward = centers[rng.integers(0, C, F)] - positions
        z = -toward / np.linalg.norm(toward, axis=1, keepdims=True)
        tilt = _random_rotation(rng, F, np.deg2rad(40.0))
        z = np.einsum("fij,fj->fi", tilt, z)
        x = np.cross(z, rng.normal(size=(F, 3)))
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        rotations = np.stack([x, np.cross(z, x), z], axis=-1)  # columns: the target's axes
    else:
        rotations = _random_rotation(rng, F, np.pi)
    # the target's centre at the chosen position
    center = target.mean(0)
    translations = positions - np.einsum("fij,j->fi", rotations, center)
    poses = RigidTransform(jnp.asarray(rotations, dtype), jnp.asarray(translations, dtype))

    world = np.einsum("fij,nj->fni", rotations, target) + translations[:, None]  # (F, N, 3)
    cams = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype)[:, None], cameras)  # (C, 1)
    true = np.asarray(cams.project(jnp.asarray(world, dtype)[None]))  # (C, F, N, 2)
    depth = np.asarray(cams.depth(jnp.asarray(world, dtype)[None]))
    inside = (true[..., 0] >= 0) & (true[..., 0] <= width - 1)
    inside &= (true[..., 1] >= 0) & (true[..., 1] <= height - 1)
    seen = np.ones((C, F), bool)
    if planar:
        to_camera = centers[:, None] - positions[None]  # (C, F, 3)
        to_camera /= np.linalg.norm(to_camera, axis=-1, keepdims=True)
        seen &= np.einsum("cfi,fi->cf", to_camera, rotations[:, :, 2]) < -np.cos(np.deg2rad(70))
    dropped = ((0.0, 0.3) if planar else (0.4, 0.75)) if dropped is None else dropped
    seen &= rng.uniform(size=(C, F)) >= rng.uniform(*dropped, C)[:, None]
    mask = seen[..., None] & inside & (depth > 0)
    noisy = true + noise * rng.normal(size=true.shape)
    cameras = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), cameras)
    return BoardRig(
        cameras, jnp.asarray(target, dtype), poses, jnp.asarray(true, dtype),
        jnp.asarray(noisy, dtype), jnp.asarray(mask), tuple(image_size),
    )  # fmt: skip


def _random_rotation(rng, n: int, max_angle: float) -> np.ndarray:
    """`n` rotations about uniformly random axes by angles uniform in [0, max_angle]."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(0, max_angle, n)
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K -= K.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)
