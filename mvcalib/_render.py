"""Synthetic photographs of a dot target: what a camera of known parameters would record.

The renderer is exact where it matters for testing sub-pixel dot detection: each dot is a disc on
its face plane and is drawn as the camera sees it (through the plane-to-image homography and the
lens distortion), so the image of a dot is the true perspective ellipse, not a circle around the
projected centre. Anti-aliasing is by supersampling, then optical blur, an illumination gradient
and sensor noise. NumPy throughout: it is a test fixture, not a differentiable kernel.
"""

from __future__ import annotations

import numpy as np

from ._camera import Camera, _fisheye_polynomial
from .targets import Target

__all__ = ["render", "true_centres", "ellipse_centres", "visible_dots", "dot_normals"]


# ---------------------------------------------------------------------------- geometry helpers
# The most levels a plate's dots lie on (`dot_normals`)
_MAX_LEVELS = 16


def dot_normals(target: Target) -> np.ndarray:
    """The unit normal of the face each dot lies on, pointing to the side it is seen from.

    For the box corner (and any target whose dots lie on the coordinate planes through its local
    origin) the face follows from which coordinate is zero, checked in the order z, y, x: the
    floor `z = 0`, the wall `y = 0`, the wall `x = 0`. A dot on several faces (the corner dot at
    the origin) is taken to be on the floor. The dots of a plate of several levels (at most 16
    values of one coordinate, one of them zero) face as its level at zero does. The normals
    point into the positive octant, where the cameras of `mvcalib.synthetic.random_rig` stand.

    **Arguments:**

    - `target`: a `mvcalib.targets.Target`.

    **Returns:**

    An `(M, 3)` array of unit normals.

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> mc.synthetic.dot_normals(mc.targets.box_corner())[[0, 6, 12, 18]].tolist()
    [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]

    ```
    """
    points = np.asarray(target.points, dtype=float)
    scale = max(float(np.abs(points).max()), 1.0)
    on_plane = np.abs(points) <= 1e-9 * scale
    normals = np.zeros_like(points)
    for axis in (2, 1, 0):  # floor first, so the corner dot belongs to the floor
        pick = on_plane[:, axis] & ~normals.any(axis=1)
        normals[pick, axis] = 1.0
    # A plate of several levels (`mvcalib.targets.plate`, a PIV plate from a file): its dots
    # lie on a few planes parallel to one face, and those off that face look as it does (they
    # failed `calibrate_images`' perspective-bias step, and `render`)
    for axis in (2, 1, 0):
        levels = np.unique(np.round(points[:, axis] / scale, 9))
        if len(levels) <= _MAX_LEVELS and normals[:, axis].any():
            normals[~normals.any(axis=1), axis] = 1.0
    if not normals.any(axis=1).all():
        bad = np.flatnonzero(~normals.any(axis=1)).tolist()
        shown = ", ".join(map(str, bad[:8])) + (f", ... ({len(bad)} dots)" if len(bad) > 8 else "")
        raise ValueError(
            f"cannot tell which face dots {shown} lie on: no coordinate is zero. Pass `normals=` "
            "(one unit normal per dot) to render such a target."
        )
    return normals


def _plane_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two in-plane unit vectors per normal, completing a right-handed frame."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(normals, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(normals, e1)


def _camera_arrays(camera: Camera) -> dict[str, np.ndarray]:
    if camera.batch_shape != ():
        raise ValueError(
            f"render one camera at a time: got a rig of shape {camera.batch_shape}; "
            "select one with `rig.cameras[i]`."
        )
    return {
        "K": np.asarray(camera.K, dtype=float),
        "R": np.asarray(camera.R, dtype=float),
        "t": np.asarray(camera.t, dtype=float),
        "dist": np.asarray(camera.dist, dtype=float),
        "center": np.asarray(camera.center, dtype=float),
        "lens": camera.lens,
    }


def _normals(target: Target, normals) -> np.ndarray:
    if normals is None:
        return dot_normals(target)
    normals = np.asarray(normals, dtype=float)
    if normals.shape != np.shape(target.points):
        raise ValueError(
            f"`normals` needs one 3-vector per dot, shape {np.shape(target.points)}; "
            f"got {normals.shape}."
        )
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _boundary(target: Target, normals: np.ndarray, n: int) -> np.ndarray:
    """`n` points on the rim of every dot, `(M, n, 3)`, counter-clockwise about the normal."""
    e1, e2 = _plane_basis(normals)
    phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rim = np.cos(phi)[None, :, None] * e1[:, None] + np.sin(phi)[None, :, None] * e2[:, None]
    return np.asarray(target.points, float)[:, None] + target.radii[:, None, None] * rim


def _project_rims(camera: Camera, target: Target, normals: np.ndarray, n: int) -> np.ndarray:
    rims = _boundary(target, normals, n)
    world = np.asarray(rims.reshape(-1, 3), dtype=np.asarray(camera.R).dtype)
    return np.asarray(camera.project(world), dtype=float).reshape(len(rims), n, 2)


def _facing(camera: Camera, target: Target, normals: np.ndarray, n: int) -> np.ndarray:
    """Dots whose face the camera sees from the front and whose whole rim (`n` points) lies in
    front of the camera (a fisheye's: within 160 degrees of its axis)."""
    cam = _camera_arrays(camera)
    points = np.asarray(target.points, float)
    facing = np.einsum("ij,ij->i", cam["center"] - points, normals) > 0
    rims = _boundary(target, normals, n) @ cam["R"].T + cam["t"]
    if cam["lens"] == "fisheye":
        cosine = rims[..., 2] / np.linalg.norm(rims, axis=-1)
        return facing & (cosine.min(axis=1) > np.cos(np.deg2rad(160.0)))
    return facing & (rims[..., 2].min(axis=1) > 0)


def visible_dots(
    camera: Camera,
    target: Target,
    image_size=(1000, 1100),
    *,
    min_gap: float = 0.0,
    normals=None,
) -> np.ndarray:
    """Which dots a camera sees whole, and apart from the others.

    A dot counts if its face is turned towards the camera, it is in front of it, its whole rim
    is inside the image, and (with `min_gap > 0`) its image keeps at least `min_gap` pixels from
    every other drawn dot's. Dots failing the last test touch another in the picture (at grazing
    views the corner dot's disc on the floor can run into a wall dot) and no blob detector can
    tell them apart; those failing the others are not drawn or cut by the image border.

    **Arguments:**

    - `camera`, `target`, `image_size`, `normals`: as for `render`.
    - `min_gap`: the clearance in pixels required between dot images.

    **Returns:**

    A boolean `(M,)` array.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> camera = mc.synthetic.random_rig(jax.random.key(0), 1).cameras[0]
    >>> int(mc.synthetic.visible_dots(camera, mc.targets.box_corner(), min_gap=2.0).sum())
    19

    ```
    """
    normals = _normals(target, normals)
    drawn = _facing(camera, target, normals, 256)
    px = _project_rims(camera, target, normals, 256)
    width, height = image_size
    inside = (
        (px[..., 0].min(1) >= 0)
        & (px[..., 1].min(1) >= 0)
        & (px[..., 0].max(1) <= width - 1)
        & (px[..., 1].max(1) <= height - 1)
    )
    apart = np.ones(len(target.points), bool)
    if min_gap > 0:
        # Rim-to-rim distance between every pair of drawn dots (256 rim points each, so good to
        # a small fraction of a pixel for dots of tens of pixels); a rim point inside the
        # other's polygon would be an overlap, which always also brings the rims together.
        ids = np.flatnonzero(drawn)
        lo, hi = px.min(1) - min_gap, px.max(1) + min_gap
        for k, i in enumerate(ids):
            for j in ids[k + 1 :]:
                if np.any(lo[i] > hi[j]) or np.any(lo[j] > hi[i]):
                    continue  # bounding boxes apart
                gap = np.linalg.norm(px[i][:, None] - px[j][None], axis=-1).min()
                if gap < min_gap:
                    apart[i] = apart[j] = False
    return drawn & inside & apart


def true_centres(camera: Camera, target: Target) -> np.ndarray:
    """The projections of the dot centres, `camera.project(target.points)`, `(M, 2)` float64.

    Under perspective these are *not* the centres of the dots' images (see `ellipse_centres`).

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> camera = mc.synthetic.random_rig(jax.random.key(0), 1).cameras[0]
    >>> mc.synthetic.true_centres(camera, mc.targets.box_corner()).shape
    (19, 2)

    ```
    """
    points = np.asarray(target.points, dtype=np.asarray(camera.R).dtype)
    return np.asarray(camera.project(points), dtype=float)


def ellipse_centres(
    camera: Camera, target: Target, *, normals=None, n_boundary: int = 4096
) -> np.ndarray:
    """The centroid of each dot's image (the area centroid of the projected disc), `(M, 2)`.

    A disc seen in perspective images to an ellipse whose centre is not the image of the disc's
    centre: the nearer half of the disc looks larger. This is what an unbiased centroid detector
    measures, so it is the reference for the detector's accuracy; `true_centres` minus this is
    the perspective bias a calibration has to live with (or correct). Computed from a dense
    polygon of projected rim points (so lens distortion is included), by the shoelace formula;
    with 4096 vertices the polygon's centroid is within 1e-6 px of the curve's.

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> camera = mc.synthetic.random_rig(jax.random.key(0), 1).cameras[0]
    >>> target = mc.targets.box_corner()
    >>> ellipse = mc.synthetic.ellipse_centres(camera, target)
    >>> bias = ellipse - mc.synthetic.true_centres(camera, target)
    >>> bool(0.1 < np.linalg.norm(bias, axis=1).max() < 2)  # a pixel or so
    True

    ```
    """
    normals = _normals(target, normals)
    px = _project_rims(camera, target, normals, n_boundary)
    # Shoelace centroid, relative to the first vertex to avoid cancellation.
    p = px - px[:, :1]
    x, y = p[..., 0], p[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    area = cross.sum(1) / 2.0
    cx = ((x + xn) * cross).sum(1) / (6.0 * area)
    cy = ((y + yn) * cross).sum(1) / (6.0 * area)
    return px[:, 0] + np.stack([cx, cy], axis=1)


# ---------------------------------------------------------------------------- rasterisation
def _undistort(xd: np.ndarray, dist: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Invert Brown–Conrady distortion of normalised coordinates `(..., 2)` by fixed point."""
    k1, k2, p1, p2, k3 = dist
    x, y = xd[..., 0].copy(), xd[..., 1].copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xd[..., 0] - dx) / radial
        y = (xd[..., 1] - dy) / radial
    return np.stack([x, y], -1)


def _fisheye_rays(xd: np.ndarray, dist: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Unit rays `(..., 3)` of a fisheye's distorted normalised coordinates `(..., 2)`: the angle
    `theta` from `theta_d` by Newton's method (as `Camera.rays`, here in NumPy: rendering runs
    on the host, block by block)."""
    theta_d = np.linalg.norm(xd, axis=-1)
    theta = theta_d.copy()
    for _ in range(iterations):
        value, slope = _fisheye_polynomial(theta, dist)
        theta = np.clip(theta - (value - theta_d) / slope, 0.0, np.pi)
    scale = np.where(theta_d > 0, np.sin(theta) / np.where(theta_d > 0, theta_d, 1.0), 1.0)
    return np.concatenate([xd * scale[..., None], np.cos(theta)[..., None]], -1)


def _samples(x0: int, x1: int, y0: int, y1: int, s: int):
    """Sub-pixel sample positions of the pixel block [x0, x1) x [y0, y1), s x s per pixel."""
    offsets = (np.arange(s) + 0.5) / s - 0.5
    xs = (np.arange(x0, x1)[:, None] + offsets).ravel()
    ys = (np.arange(y0, y1)[:, None] + offsets).ravel()
    return np.meshgrid(xs, ys)


def _coverage_block(inside: np.ndarray, s: int) -> np.ndarray:
    h, w = inside.shape[0] // s, inside.shape[1] // s
    return inside.reshape(h, s, w, s).mean(axis=(1, 3))


def _draw_dots(cover, cam, target, normals, px_rims, draw, s):
    height, width = cover.shape
    Kinv = np.linalg.inv(cam["K"])
    e1, e2 = _plane_basis(normals)
    points = np.asarray(target.points, float)
    distorted = bool(np.any(cam["dist"] != 0))
    fisheye = cam["lens"] == "fisheye"
    for i in np.flatnonzero(draw):
        radius = float(target.radii[i])
        # Plane (a, b) -> normalised camera coordinates: [x, y, 1] ~ G [a, b, 1] with
        # G = [R e1, R e2, R c + t]; a sample is on the dot iff a^2 + b^2 <= r^2 (exact conic).
        G = np.stack([cam["R"] @ e1[i], cam["R"] @ e2[i], cam["R"] @ points[i] + cam["t"]], 1)
        Ginv = np.linalg.inv(G) @ Kinv  # pixel -> plane, for undistorted pixels

        def on_dot(X, Y, G=G, Ginv=Ginv, radius=radius):
            if fisheye:  # the sample's ray, through the plane: in front along the ray only
                yn = Kinv[1, 1] * Y + Kinv[1, 2]
                xn = Kinv[0, 0] * X + Kinv[0, 1] * Y + Kinv[0, 2]
                ray = _fisheye_rays(np.stack([xn, yn], -1), cam["dist"])
                a, b, w = np.moveaxis(ray @ np.linalg.inv(G).T, -1, 0)
                return (w > 0) & (a * a + b * b <= (radius * w) ** 2)
            if distorted:
                xn = Kinv[0, 0] * X + Kinv[0, 1] * Y + Kinv[0, 2]
                yn = Kinv[1, 1] * Y + Kinv[1, 2]
                xn, yn = np.moveaxis(_undistort(np.stack([xn, yn], -1), cam["dist"]), -1, 0)
                X, Y = (
                    cam["K"][0, 0] * xn + cam["K"][0, 1] * yn + cam["K"][0, 2],
                    cam["K"][1, 1] * yn + cam["K"][1, 2],
                )
            a = Ginv[0, 0] * X + Ginv[0, 1] * Y + Ginv[0, 2]
            b = Ginv[1, 0] * X + Ginv[1, 1] * Y + Ginv[1, 2]
            w = Ginv[2, 0] * X + Ginv[2, 1] * Y + Ginv[2, 2]
            return a * a + b * b <= (radius * w) ** 2

        lo = np.floor(px_rims[i].min(0)).astype(int) - 1
        hi = np.ceil(px_rims[i].max(0)).astype(int) + 2
        x0, y0 = max(lo[0], 0), max(lo[1], 0)
        x1, y1 = min(hi[0], width), min(hi[1], height)
        if x0 >= x1 or y0 >= y1:
            continue
        block = _coverage_block(on_dot(*_samples(x0, x1, y0, y1, s)), s)
        # Rim pixels again, 4x finer along each axis: the coverage of the pixels the dot's edge
        # crosses is what places its centroid, and s x s samples quantise it to 1 / s^2.
        rows, cols = np.nonzero((block > 0) & (block < 1))
        if len(rows):
            fine = 4 * s
            offsets = (np.arange(fine) + 0.5) / fine - 0.5
            X = (cols + x0)[:, None, None] + offsets[None, None, :]
            Y = (rows + y0)[:, None, None] + offsets[None, :, None]
            X, Y = np.broadcast_arrays(X, Y)
            block[rows, cols] = on_dot(X, Y).mean(axis=(1, 2))
        cover[y0:y1, x0:x1] = np.maximum(cover[y0:y1, x0:x1], block)


def _clutter_shapes(rng, n, image_size, keep_out):
    """Random spurious blobs: (centre, list of primitives, ink) each, away from `keep_out`.

    Kinds, chosen in turn so every kind appears: a thin streak (scratch, hair), a speck (dust),
    a large faint smudge, an irregular blot (overlapping discs), a rotated rectangle (printed mark)
    and a dot-like ellipse (which no shape test can tell from a dot; labelling must).
    """
    width, height = image_size
    kinds = ["streak", "speck", "smudge", "blot", "rectangle", "ellipse"]
    shapes = []
    for j in range(n):
        kind = kinds[j % len(kinds)]
        angle = rng.uniform(0, np.pi)
        if kind == "streak":
            prims = [("rect", 0.0, 0.0, rng.uniform(40, 120), rng.uniform(1.0, 2.5), angle)]
            ink, extent = rng.uniform(0.5, 1.0), 65.0
        elif kind == "speck":
            r = rng.uniform(0.8, 1.8)
            prims, ink, extent = [("ellipse", 0.0, 0.0, r, r, 0.0)], rng.uniform(0.5, 1.0), 3.0
        elif kind == "smudge":
            a = rng.uniform(90, 150)
            prims = [("ellipse", 0.0, 0.0, a, a * rng.uniform(0.6, 1.0), angle)]
            ink, extent = rng.uniform(0.15, 0.4), a + 5
        elif kind == "blot":
            # Overlapping discs (each centre inside the first disc): one irregular blob.
            r0 = rng.uniform(6, 14)
            prims = [("ellipse", 0.0, 0.0, r0, r0, 0.0)]
            for _ in range(rng.integers(1, 4)):
                r, phi = rng.uniform(0.4, 0.8) * r0, rng.uniform(0, 2 * np.pi)
                off = rng.uniform(0.7, 1.0) * r0 * np.array([np.cos(phi), np.sin(phi)])
                prims.append(("ellipse", off[0], off[1], r, r, 0.0))
            ink, extent = rng.uniform(0.6, 1.0), 2.0 * r0 + 2
        elif kind == "rectangle":
            prims = [("rect", 0.0, 0.0, rng.uniform(10, 40), rng.uniform(8, 30), angle)]
            ink, extent = rng.uniform(0.6, 1.0), 30.0
        else:
            a = rng.uniform(8, 25)
            prims = [("ellipse", 0.0, 0.0, a, a / rng.uniform(1.5, 4.0), angle)]
            ink, extent = rng.uniform(0.6, 1.0), a + 3
        for _ in range(200):
            c = rng.uniform([extent, extent], [width - extent, height - extent])
            if all(np.hypot(*(c - k[:2])) > extent + k[2] + 10 for k in keep_out):
                break
        else:
            continue  # no free place for this one; leave it out rather than cover a dot
        keep_out.append(np.array([c[0], c[1], extent]))
        shapes.append((c, prims, ink, extent))
    return shapes


def _draw_clutter(cover, shapes, s):
    height, width = cover.shape
    for c, prims, ink, extent in shapes:
        x0, y0 = max(int(c[0] - extent) - 2, 0), max(int(c[1] - extent) - 2, 0)
        x1, y1 = min(int(c[0] + extent) + 3, width), min(int(c[1] + extent) + 3, height)
        X, Y = _samples(x0, x1, y0, y1, s)
        inside = np.zeros(X.shape, bool)
        for kind, dx, dy, a, b, angle in prims:
            u, v = X - c[0] - dx, Y - c[1] - dy
            cs, sn = np.cos(angle), np.sin(angle)
            u, v = cs * u + sn * v, -sn * u + cs * v
            if kind == "ellipse":
                inside |= (u / a) ** 2 + (v / b) ** 2 <= 1.0
            else:
                inside |= (np.abs(u) <= a / 2) & (np.abs(v) <= b / 2)
        block = cover[y0:y1, x0:x1]
        cover[y0:y1, x0:x1] = np.maximum(block, ink * _coverage_block(inside, s))


def _rng(key) -> np.random.Generator:
    if key is None:
        return np.random.default_rng(0)
    if isinstance(key, (int, np.integer)):
        return np.random.default_rng(int(key))
    import jax  # only for typed PRNG keys

    data = (
        jax.random.key_data(key) if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key) else key
    )
    return np.random.default_rng(np.asarray(data, dtype=np.uint32).ravel().tolist())


def render(
    camera: Camera,
    target: Target,
    image_size: tuple[int, int] = (1000, 1100),
    *,
    blur_sigma: float = 1.0,
    noise_sigma: float = 3.0,
    gradient: float = 0.3,
    clutter: int = 0,
    hidden=(),
    key=None,
    supersample: int = 4,
    background: float = 200.0,
    dot: float = 30.0,
    normals=None,
) -> np.ndarray:
    """A greyscale photograph of `target` (white sheet, black dots) taken by `camera`.

    Every dot is a disc of radius `target.radii[i]` on its face plane and is drawn exactly as
    the camera sees it: a sub-pixel sample is dark iff it back-projects (through the lens
    distortion and the face's homography) into the disc, so perspective and distortion are in the
    picture, not approximated. Only dots on faces turned towards the camera are drawn. A dot on
    several faces (the box corner's dot 18) is drawn whole on the first (see `dot_normals`), as
    the target model has it, even where a real wall would hide part of it.

    The ink coverage of each pixel is blurred (optics), lit by the illumination ramp, and
    sensor noise is added; the result is rounded and clipped to 0..255.

    **Arguments:**

    - `camera`: one `mvcalib.Camera` (not a rig).
    - `target`: the target; dots' faces come from `dot_normals` unless `normals` is given.
    - `image_size`: `(width, height)` in pixels.
    - `blur_sigma`: Gaussian optical blur (point spread function), in pixels; 0 for none.
    - `noise_sigma`: Gaussian sensor noise, in grey levels.
    - `gradient`: relative amplitude of a linear illumination ramp across the image in a random
      direction (0.3: the light falls from 115 % to 85 % of its mean), as uneven lighting does.
    - `clutter`: how many spurious dark blobs to add away from the dots (streaks, specks,
      smudges, irregular blots, rectangles and dot-like ellipses, in turn).
    - `hidden`: indices of dots not to draw (occluded, or to test missing detections).
    - `key`: a JAX PRNG key or an int seed; `None` means seed 0. Same key, same image.
    - `supersample`: samples per pixel along each axis for anti-aliasing (4: 16 per pixel);
      pixels that a dot's rim crosses are sampled 4 times finer again along each axis, since
      their coverage is what places the dot's centroid.
    - `background`, `dot`: grey levels of the paper and of the ink under mean illumination.
    - `normals`: optional `(M, 3)` unit normals of the dots' faces, towards the visible side.

    **Returns:**

    A `uint8` array of shape `(height, width)`.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> camera = mc.synthetic.random_rig(jax.random.key(0), 1).cameras[0]
    >>> image = mc.synthetic.render(camera, mc.targets.box_corner(), key=0)
    >>> image.shape, image.dtype.name
    ((1100, 1000), 'uint8')

    ```
    """
    width, height = (int(v) for v in image_size)
    if width < 1 or height < 1:
        raise ValueError(f"`image_size` is (width, height) in pixels; got {image_size}.")
    if int(supersample) < 1:
        raise ValueError(f"`supersample` must be a positive integer; got {supersample}.")
    rng = _rng(key)
    cam = _camera_arrays(camera)
    normals = _normals(target, normals)
    draw = _facing(camera, target, normals, 64)
    draw[np.asarray(hidden, dtype=int)] = False
    px_rims = _project_rims(camera, target, normals, 64)

    cover = np.zeros((height, width))  # fraction of each pixel covered by ink
    _draw_dots(cover, cam, target, normals, px_rims, draw, int(supersample))
    if clutter:
        # Keep clutter clear of every dot, drawn or not, so a hidden dot stays hidden.
        lo, hi = px_rims.min(1), px_rims.max(1)
        keep_out = [
            np.array([*(lo[i] + hi[i]) / 2, np.hypot(*(hi[i] - lo[i])) / 2])
            for i in range(len(target.points))
        ]
        shapes = _clutter_shapes(rng, int(clutter), (width, height), keep_out)
        _draw_clutter(cover, shapes, int(supersample))

    reflectance = background - (background - dot) * cover
    if blur_sigma > 0:
        from skimage.filters import gaussian  # SciPy and scikit-image only for rendering

        reflectance = gaussian(reflectance, sigma=blur_sigma, mode="nearest", preserve_range=True)
    # Illumination: a linear ramp of relative amplitude `gradient` in a random direction.
    theta = rng.uniform(0, 2 * np.pi)
    xs, ys = np.arange(width) / max(width - 1, 1) - 0.5, np.arange(height) / max(height - 1, 1)
    ramp = np.cos(theta) * xs[None, :] + np.sin(theta) * (ys[:, None] - 0.5)
    ramp /= max(abs(np.cos(theta)) + abs(np.sin(theta)), 1e-12)  # the ramp spans [-0.5, 0.5]
    image = reflectance * (1.0 + gradient * ramp)
    if noise_sigma > 0:
        image = image + rng.normal(0.0, noise_sigma, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
