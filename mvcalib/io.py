"""Saving and loading rigs (versioned JSON, OpenCV YAML, COLMAP) and correspondences (CSV, JSON).

A rig file holds one entry per camera (name, intrinsics, `R`, `t`, distortion in OpenCV's order,
and optionally its calibration status and reprojection RMS). Cameras that failed have `null`
parameters, loaded back as NaN. Files are written to a temporary file beside the target and
renamed over it, so an interrupted write never leaves a half-written rig.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import re
import stat
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera

__all__ = [
    "save_json", "load_json", "save_opencv", "load_opencv", "save_colmap", "load_colmap",
    "write_atomic", "load_aniposelib", "Correspondences", "save_correspondences",
    "load_correspondences",
]  # fmt: skip

FORMAT = "mvcalib.rig"
VERSION = 1
_SCALARS = ("alpha_u", "alpha_v", "u0", "v0", "skew")


def write_atomic(path, data: str | bytes) -> pathlib.Path:
    """Write `data` to `path` through a temporary file and a rename: all or nothing."""
    path = pathlib.Path(path)
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as f:
            # mkstemp makes the file private (0600); give it the permissions a plain open()
            # would: those of the file it replaces, or 0666 less the umask.
            try:
                permissions = stat.S_IMODE(os.stat(path).st_mode)
            except OSError:
                umask = os.umask(0o022)
                os.umask(umask)
                permissions = 0o666 & ~umask
            os.chmod(tmp, permissions)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _plain(x):
    """Nested lists of floats with None for NaN/inf (JSON has no NaN)."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        return float(x) if math.isfinite(x) else None
    return [_plain(v) for v in x]


def _array(x, shape):
    a = np.array(x if x is not None else np.full(shape, np.nan), dtype=object)
    a = np.where(a == None, np.nan, a).astype(float)  # noqa: E711 (elementwise on objects)
    if a.shape != shape:
        raise ValueError(f"expected shape {shape}; got {a.shape}")
    return a


def save_json(path, cameras: Camera, *, names=None, status=None, rms=None, meta=None):
    """Save a rig (a `Camera` with a camera axis, or one camera) as versioned JSON, atomically.

    **Arguments:**

    - `path`: the file to write (replaced whole, or not at all).
    - `cameras`: the rig.
    - `names`: a name per camera (default `cam_0`, `cam_1`, ...).
    - `status`, `rms`: optional per-camera calibration status (ints or `mvcalib.Status`) and
      reprojection RMS in pixels, stored for the record.
    - `meta`: an optional JSON-serialisable dict stored as is (e.g. the target's name).

    **Example:**

    ```python
    >>> import jax, tempfile, pathlib, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3).cameras
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "rig.json"
    >>> _ = mc.io.save_json(path, rig)
    >>> back, names = mc.io.load_json(path)
    >>> bool(jax.numpy.all(back.K == rig.K)), names
    (True, ['cam_0', 'cam_1', 'cam_2'])

    ```
    """
    rig = (
        jax.tree_util.tree_map(lambda a: a[None], cameras) if cameras.batch_shape == () else cameras
    )
    if len(rig.batch_shape) != 1:
        raise ValueError(f"save one camera axis; got a rig of shape {rig.batch_shape}.")
    n = rig.batch_shape[0]
    names = [f"cam_{i}" for i in range(n)] if names is None else [str(s) for s in names]
    if len(names) != n:
        raise ValueError(f"{len(names)} names for {n} cameras.")
    entries = []
    for i in range(n):
        entry = {"name": names[i]}
        entry.update({k: _plain(getattr(rig, k)[i]) for k in _SCALARS})
        entry.update(R=_plain(rig.R[i]), t=_plain(rig.t[i]), dist=_plain(rig.dist[i]))
        if status is not None:
            entry["status"] = int(np.asarray(status).reshape(-1)[i])
        if rms is not None:
            entry["rms"] = _plain(np.asarray(rms).reshape(-1)[i])
        entries.append(entry)
    document = {"format": FORMAT, "version": VERSION, "cameras": entries}
    if meta:
        document["meta"] = meta
    return write_atomic(path, json.dumps(document, indent=1, allow_nan=False) + "\n")


def load_json(path) -> tuple[Camera, list[str]]:
    """Load a rig saved by `save_json`: `(cameras, names)`; `ValueError` if it is not one."""
    path = pathlib.Path(path)
    try:
        document = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable JSON rig file ({error})") from None
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise ValueError(f'{path}: not an mvcalib rig file (no "format": "{FORMAT}").')
    if document.get("version") != VERSION:
        raise ValueError(
            f"{path}: rig file version {document.get('version')}; this mvcalib reads {VERSION}."
        )
    cameras = document.get("cameras")
    if not isinstance(cameras, list) or not cameras:
        raise ValueError(f"{path}: the rig file lists no cameras.")
    fields = {k: [] for k in (*_SCALARS, "R", "t", "dist")}
    try:
        for entry in cameras:
            for k in _SCALARS:
                fields[k].append(_array(entry[k], ()))
            fields["R"].append(_array(entry["R"], (3, 3)))
            fields["t"].append(_array(entry["t"], (3,)))
            fields["dist"].append(_array(entry.get("dist", [0.0] * 5), (5,)))
    except (KeyError, TypeError, ValueError) as error:
        where = f"{path}: camera entry {len(fields['R'])}"
        raise ValueError(f"{where} is malformed ({error}).") from None
    stacked = {k: jnp.asarray(np.stack(v)) for k, v in fields.items()}
    names = [str(e.get("name", f"cam_{i}")) for i, e in enumerate(cameras)]
    return Camera(**stacked), names


def load_aniposelib(path) -> tuple[Camera, list[str]]:
    """Load an aniposelib / anipose calibration file (TOML): `(cameras, names)`.

    Each `[cam_i]` table holds `matrix` (K), `distortions` (OpenCV's k1 k2 p1 p2 k3),
    `rotation` (a Rodrigues vector, world to camera) and `translation`; the cameras come back in
    the file's order of `cam_0, cam_1, ...`. Needs Python >= 3.11 (`tomllib`).
    """
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        raise ValueError("reading TOML calibration files needs Python >= 3.11.") from None
    from ._rotation import rodrigues

    path = pathlib.Path(path)
    try:
        document = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
        raise ValueError(f"{path}: not a readable TOML calibration ({error})") from None
    keys = sorted((k for k in document if re.fullmatch(r"cam_\d+", k)), key=lambda k: int(k[4:]))
    if not keys:
        raise ValueError(f"{path}: no [cam_N] tables.")
    try:
        K = np.array([document[k]["matrix"] for k in keys], dtype=float)
        dist = np.array([document[k].get("distortions", [0.0] * 5) for k in keys], dtype=float)
        rvec = np.array([document[k]["rotation"] for k in keys], dtype=float)
        t = np.array([document[k]["translation"] for k in keys], dtype=float)
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: a camera table is malformed ({error}).") from None
    dist = np.pad(dist, ((0, 0), (0, 5 - dist.shape[1])))
    names = [str(document[k].get("name", k)) for k in keys]
    return Camera.from_matrices(K, rodrigues(jnp.asarray(rvec)), t, dist), names


# ---------------------------------------------------------------------------- OpenCV YAML
def _opencv_matrix(name: str, a, indent: str) -> list[str]:
    a = np.atleast_2d(np.asarray(a, dtype=float))
    values = ", ".join(repr(float(v)) for v in a.ravel())  # repr: shortest exact round trip
    return [
        f"{indent}{name}: !!opencv-matrix",
        f"{indent}   rows: {a.shape[0]}",
        f"{indent}   cols: {a.shape[1]}",
        f"{indent}   dt: d",
        f"{indent}   data: [ {values} ]",
    ]


def _opencv_camera(camera: Camera, indent: str, image_size) -> list[str]:
    lines = []
    if image_size is not None:
        width, height = (int(v) for v in image_size)
        lines += [f"{indent}image_width: {width}", f"{indent}image_height: {height}"]
    lines += _opencv_matrix("camera_matrix", camera.K, indent)
    lines += _opencv_matrix("distortion_coefficients", np.asarray(camera.dist)[None], indent)
    lines += _opencv_matrix("R", camera.R, indent)
    lines += _opencv_matrix("T", np.asarray(camera.t)[:, None], indent)
    return lines


def save_opencv(path, cameras: Camera, *, names=None, image_size=None) -> pathlib.Path:
    """Save cameras as OpenCV FileStorage YAML, readable by `cv2.FileStorage`, atomically.

    One camera is written at the top level with OpenCV's usual keys: `camera_matrix` (K),
    `distortion_coefficients` (1 x 5: k1 k2 p1 p2 k3), `R` (world to camera) and `T` (3 x 1),
    with `image_width`/`image_height` if `image_size=(width, height)` is given. A rig is
    written as one map per camera (`cam_0`, ... or `names`) holding those keys, and `cameras`
    listing the names. Numbers are written with Python's shortest exact representation, so
    reading back (with `load_opencv` or `cv2.FileStorage`) gives the same doubles.

    **Example:**

    ```python
    >>> import jax, tempfile, pathlib, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 2).cameras
    >>> path = mc.io.save_opencv(pathlib.Path(tempfile.mkdtemp()) / "rig.yml", rig)
    >>> back, names = mc.io.load_opencv(path)
    >>> bool(np.array_equal(back.K, rig.K)), names
    (True, ['cam_0', 'cam_1'])

    ```
    """
    lines = ["%YAML:1.0", "---"]
    if cameras.batch_shape == ():
        lines += _opencv_camera(cameras, "", image_size)
    else:
        if len(cameras.batch_shape) != 1:
            raise ValueError(f"save one camera axis; got a rig of shape {cameras.batch_shape}.")
        n = cameras.batch_shape[0]
        names = [f"cam_{i}" for i in range(n)] if names is None else [str(s) for s in names]
        if len(names) != n or any(not s.isidentifier() for s in names):
            raise ValueError(f"need {n} names made of letters, digits and '_'; got {names}.")
        lines.append("cameras: [ " + ", ".join(f'"{s}"' for s in names) + " ]")
        for i, name in enumerate(names):
            lines.append(f"{name}:")
            lines += _opencv_camera(cameras[i], "   ", image_size)
    return write_atomic(path, "\n".join(lines) + "\n")


def load_opencv(path) -> tuple[Camera, list[str]]:
    """Load a file written by `save_opencv` (or any FileStorage YAML with `camera_matrix`,
    `distortion_coefficients`, `R`, `T`, at the top level or in per-camera maps listed by
    `cameras`): `(cameras, names)`; a single camera comes back with no camera axis."""
    path = pathlib.Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: cannot be read ({error})") from None
    tree = _parse_opencv_yaml(text, path)
    if "cameras" in tree:
        names = tree["cameras"]
        maps = [tree.get(n) for n in names]
    else:
        names, maps = ["camera"], [tree]
    fields = []
    for name, node in zip(names, maps):
        try:
            K, dist, R, T = (
                node[k] for k in ("camera_matrix", "distortion_coefficients", "R", "T")
            )
            fields.append((K.reshape(3, 3), dist.reshape(-1), R.reshape(3, 3), T.reshape(3)))
        except (KeyError, TypeError, ValueError, AttributeError):
            raise ValueError(
                f"{path}: camera {name!r} lacks camera_matrix, "
                "distortion_coefficients, R or T (3x3, 1x5, 3x3, 3x1)."
            ) from None
    K, dist, R, T = (np.stack(f) for f in zip(*fields))
    dist = np.pad(dist, ((0, 0), (0, max(0, 5 - dist.shape[1]))))[:, :5]
    cameras = Camera.from_matrices(
        jnp.asarray(K), jnp.asarray(R), jnp.asarray(T), jnp.asarray(dist)
    )
    if "cameras" not in tree:
        cameras = cameras[0]
    return cameras, list(names)


def _parse_opencv_yaml(text: str, path) -> dict:
    """The small YAML subset FileStorage writes: maps by indentation, `!!opencv-matrix` nodes
    (whose `data` may run over several lines), scalars and one-line sequences."""
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith(("%", "---"))]
    root: dict = {}
    stack = [(-1, root)]
    matrix = None  # the open matrix: {"indent", "parent", "key", "fields"}
    for line in lines:
        indent = len(line) - len(line.lstrip())
        if matrix is not None and indent > matrix["indent"]:
            if ":" in line:
                key, _, value = line.strip().partition(":")
                matrix["fields"][key] = value.strip()
                matrix["last"] = key
            else:  # a continuation of the data list
                matrix["fields"][matrix["last"]] += " " + line.strip()
            continue
        if matrix is not None:
            _finish_matrix(matrix, path)
            matrix = None
        key, _, value = line.strip().partition(":")
        value = value.strip()
        while indent <= stack[-1][0]:
            stack.pop()
        parent = stack[-1][1]
        if value.startswith("!!opencv-matrix"):
            matrix = {"indent": indent, "parent": parent, "key": key, "fields": {}, "last": None}
        elif value == "":
            parent[key] = {}
            stack.append((indent, parent[key]))
        elif value.startswith("["):
            parent[key] = [v.strip().strip('"') for v in value.strip("[] ").split(",") if v.strip()]
        else:
            parent[key] = value.strip('"')
    if matrix is not None:
        _finish_matrix(matrix, path)
    return root


def _finish_matrix(matrix, path):
    fields, key = matrix["fields"], matrix["key"]
    try:
        data = [float(v) for v in fields["data"].strip("[] ").split(",") if v.strip()]
        matrix["parent"][key] = np.array(data).reshape(int(fields["rows"]), int(fields["cols"]))
    except (KeyError, ValueError) as error:
        raise ValueError(f"{path}: opencv-matrix {key!r} is malformed ({error}).") from None


# ---------------------------------------------------------------------------- COLMAP text
def _quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method: the largest pivot)."""
    m = np.asarray(R, dtype=float)
    trace = np.trace(m)
    pivots = [trace, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(pivots))
    if k == 0:
        r = np.sqrt(1.0 + trace)
        q = [r / 2, (m[2, 1] - m[1, 2]) / (2 * r), (m[0, 2] - m[2, 0]) / (2 * r),
             (m[1, 0] - m[0, 1]) / (2 * r)]  # fmt: skip
    else:
        i = k - 1
        j, l = (i + 1) % 3, (i + 2) % 3
        r = np.sqrt(1.0 + m[i, i] - m[j, j] - m[l, l])
        v = np.zeros(3)
        v[i] = r / 2
        v[j] = (m[j, i] + m[i, j]) / (2 * r)
        v[l] = (m[l, i] + m[i, l]) / (2 * r)
        q = [(m[l, j] - m[j, l]) / (2 * r), *v]
    q = np.asarray(q)
    return q if q[0] >= 0 else -q


def _rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def save_colmap(folder, cameras: Camera, image_size, *, names=None) -> pathlib.Path:
    """Export a rig as a COLMAP text model: `cameras.txt`, `images.txt`, empty `points3D.txt`.

    Each camera becomes one COLMAP camera (model `OPENCV`: fx fy cx cy k1 k2 p1 p2, or
    `FULL_OPENCV` when k3 is not zero) and one image (`names`, default `cam_i.png`) with its
    pose as COLMAP's world-to-camera quaternion and translation. COLMAP puts the pixel origin at
    the corner of the first pixel, mvcalib at its centre, so `cx = u0 + 0.5`. COLMAP has no
    skew: a camera with skew is refused. Files are written atomically.

    **Example:**

    ```python
    >>> import jax, tempfile, pathlib, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 2).cameras
    >>> folder = mc.io.save_colmap(tempfile.mkdtemp(), rig, (1000, 1100))
    >>> back, names = mc.io.load_colmap(folder)
    >>> bool(np.allclose(back.R, rig.R, atol=1e-14)), names
    (True, ['cam_0.png', 'cam_1.png'])

    ```
    """
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rig = jax.tree_util.tree_map(lambda a: np.asarray(a, dtype=float), cameras)
    if rig.batch_shape == ():
        rig = jax.tree_util.tree_map(lambda a: a[None], rig)
    if len(rig.batch_shape) != 1:
        raise ValueError(f"save one camera axis; got a rig of shape {rig.batch_shape}.")
    n = rig.batch_shape[0]
    if np.any(rig.skew != 0):
        raise ValueError("COLMAP's camera models have no skew; refine with skew=False first.")
    names = [f"cam_{i}.png" for i in range(n)] if names is None else [str(s) for s in names]
    if len(names) != n or any(any(c.isspace() for c in s) or not s for s in names):
        raise ValueError(f"need {n} image names without spaces; got {names}.")
    width, height = (int(v) for v in image_size)
    cams = ["# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]  # fmt: skip
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)"]  # fmt: skip
    for i in range(n):
        k1, k2, p1, p2, k3 = rig.dist[i]
        params = [rig.alpha_u[i], rig.alpha_v[i], rig.u0[i] + 0.5, rig.v0[i] + 0.5, k1, k2, p1, p2]
        model = "OPENCV"
        if k3 != 0:
            model, params = "FULL_OPENCV", [*params, k3, 0.0, 0.0, 0.0]
        cams.append(f"{i + 1} {model} {width} {height} " + " ".join(repr(float(v)) for v in params))
        pose = [*_quaternion(rig.R[i]), *rig.t[i]]
        imgs.append(f"{i + 1} " + " ".join(repr(float(v)) for v in pose) + f" {i + 1} {names[i]}")
        imgs.append("")
    write_atomic(folder / "cameras.txt", "\n".join(cams) + "\n")
    write_atomic(folder / "images.txt", "\n".join(imgs) + "\n")
    write_atomic(folder / "points3D.txt", "# 3D point list (empty: cameras only)\n")
    return folder


def load_colmap(folder) -> tuple[Camera, list[str]]:
    """Read a COLMAP text model's cameras and images (models `PINHOLE`, `OPENCV`, `FULL_OPENCV`,
    `SIMPLE_PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`): one mvcalib camera per image, `(cameras,
    image names)`, in the order of `images.txt`."""
    folder = pathlib.Path(folder)
    try:
        cam_lines = _data_lines(folder / "cameras.txt")
        img_lines = _data_lines(folder / "images.txt")
    except OSError as error:
        raise ValueError(f"{folder}: not a COLMAP text model ({error})") from None
    intrinsics = {}
    n_params = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}
    n_params["FULL_OPENCV"] = 12
    for line in cam_lines:
        f = line.split()
        try:
            model, p = f[1], [float(v) for v in f[4:]]
            n = n_params.get(model, len(p))
            if len(f) < 4 or len(p) != n:
                raise ValueError(f"{model} has {n} parameters, not {len(p)}")
        except (IndexError, ValueError) as error:
            raise ValueError(
                f"{folder / 'cameras.txt'}: malformed line {line!r} ({error})"
            ) from None
        dist = [0.0] * 5
        if model in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
            fx, fy, cx, cy = p[:4]
            if model != "PINHOLE":
                dist[:4] = p[4:8]
            if model == "FULL_OPENCV":
                if any(p[9:12]):
                    raise ValueError(f"{folder}: camera {f[0]} uses k4-k6, which mvcalib lacks.")
                dist[4] = p[8]
        elif model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = p[0]
            cx, cy = p[1:3]
            dist[: len(p) - 3] = p[3:]
        else:
            raise ValueError(f"{folder}: camera model {model} is not supported.")
        intrinsics[f[0]] = (fx, fy, cx - 0.5, cy - 0.5, dist)
    fields, names = [], []
    for line in img_lines[::2]:  # every image has a second line of 2-D points
        f = line.split()
        if len(f) < 10 or f[8] not in intrinsics:
            raise ValueError(f"{folder}: malformed images.txt line: {line!r}")
        fx, fy, cx, cy, dist = intrinsics[f[8]]
        try:
            q, t = [float(v) for v in f[1:5]], [float(v) for v in f[5:8]]
        except ValueError as error:
            where = folder / "images.txt"
            raise ValueError(f"{where}: malformed line {line!r} ({error})") from None
        fields.append((fx, fy, cx, cy, _rotation(q), t, dist))
        names.append(f[9])
    if not fields:
        raise ValueError(f"{folder}: images.txt lists no images.")
    fx, fy, cx, cy, R, t, dist = (np.asarray(v, dtype=float) for v in zip(*fields))
    return Camera(fx, fy, cx, cy, R, t, dist=dist), names


def _data_lines(path: pathlib.Path) -> list[str]:
    lines = path.read_text().splitlines()
    if path.name == "images.txt":  # keep empty 2-D point lines: they pair with image lines
        return [ln for ln in lines if not ln.startswith("#")]
    return [ln for ln in lines if ln.strip() and not ln.startswith("#")]


# ---------------------------------------------------------------------------- correspondences
CORRESPONDENCES = "mvcalib.correspondences"
_WORLD = ("world_x", "world_y", "world_z")
_PIXEL = ("pixel_x", "pixel_y")
_COLUMNS = ("camera", "point", *_WORLD, *_PIXEL)


@dataclasses.dataclass(frozen=True)
class Correspondences:
    """Which camera saw which point where: what a correspondences file holds.

    **Fields:**

    - `world`: `(P, 3)` the points' world coordinates; None for a file of 2-D tracks only.
    - `pixels`: `(C, P, 2)` where camera c saw point p, `(x = column, y = row)` with the origin
      at the centre of the top-left pixel; NaN where unseen.
    - `mask`: `(C, P)` bool: which camera saw which point.
    - `cameras`: the C camera names; `points`: the P point names (strings).
    - `unlabelled`: per camera, `(K, 2)` pixels of detections matched to no point (the dots
      `mvcalib detect` found but could not label); usually empty.

    `world`, `pixels`, `mask` are what `mvcalib.calibrate` takes.
    """

    world: np.ndarray | None
    pixels: np.ndarray
    mask: np.ndarray
    cameras: list[str]
    points: list[str]
    unlabelled: list[np.ndarray]


def save_correspondences(
    path, world, pixels, mask=None, *, cameras=None, points=None, unlabelled=None
) -> pathlib.Path:
    """Save 3-D/2-D correspondences (or 2-D tracks) as CSV or JSON, by the suffix, atomically.

    **Arguments:**

    - `path`: a `.csv` or `.json` file (replaced whole, or not at all).
    - `world`: `(P, 3)` world points, or None for 2-D tracks without world coordinates.
    - `pixels`: `(C, P, 2)`: point p as seen by camera c.
    - `mask`: `(C, P)` bool, which camera saw which point; default: the finite pixels.
    - `cameras`, `points`: names, default `cam_0, cam_1, ...` and `0, 1, ...`.
    - `unlabelled`: optional per-camera `(K, 2)` pixels matched to no point.

    The CSV has one row per observation, with the header
    `camera,point,world_x,world_y,world_z,pixel_x,pixel_y` (no `world_*` columns for tracks).
    A row with an empty `point` is an unlabelled detection, a row with only a camera name a
    camera that saw nothing, and a row with an empty `camera` names a point without an
    observation (written first for every point when the observations alone would not give
    the points' order, or miss a point no camera saw), so that reading back gives the same
    arrays. The JSON holds the same as arrays: `cameras`,
    `points`, `world` `(P, 3)` and `pixels` `(C, P, 2)` with `null` where unseen. Numbers are
    written with Python's shortest exact representation: reading back gives the same doubles.

    **Example:**

    ```python
    >>> import jax, tempfile, pathlib, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3)
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "points.csv"
    >>> _ = mc.io.save_correspondences(path, rig.world, rig.pixels, rig.mask)
    >>> c = mc.io.load_correspondences(path)  # c.world, c.pixels, c.mask: for mc.calibrate
    >>> bool(np.array_equal(c.pixels, rig.pixels)), c.cameras, c.pixels.shape
    (True, ['cam_0', 'cam_1', 'cam_2'], (3, 19, 2))

    ```
    """
    path = pathlib.Path(path)
    kind = _correspondence_kind(path)
    c = _checked(world, pixels, mask, cameras, points, unlabelled)
    text = _to_csv(c) if kind == "csv" else _to_json(c)
    return write_atomic(path, text)


def load_correspondences(path) -> Correspondences:
    """Read a file written by `save_correspondences` (or by hand, in the same format).

    In a CSV, the `point` column may be left out when the world coordinates identify the
    points (rows with the same `world_x, world_y, world_z` are one point); a point's world
    coordinates must be the same in every row. Raises `ValueError` naming the file and line
    for anything malformed: a missing column, a number that is not one, a pixel seen twice,
    NaN or inf where a camera saw a point.
    """
    path = pathlib.Path(path)
    kind = _correspondence_kind(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: cannot be read ({error})") from None
    return _from_csv(text, path) if kind == "csv" else _from_json(text, path)


def _correspondence_kind(path: pathlib.Path) -> str:
    kind = path.suffix.lower().lstrip(".")
    if kind not in ("csv", "json"):
        raise ValueError(f"{path}: correspondences are .csv or .json files; got {path.suffix!r}.")
    return kind


def _checked(world, pixels, mask, cameras, points, unlabelled) -> Correspondences:
    pixels = np.array(pixels, dtype=float)
    if pixels.ndim != 3 or pixels.shape[-1] != 2:
        raise ValueError(f"`pixels` must be (C, P, 2); got shape {pixels.shape}.")
    C, P = pixels.shape[:2]
    if world is not None:
        world = np.array(world, dtype=float)
        if world.shape != (P, 3):
            raise ValueError(f"`world` must be (P, 3) = ({P}, 3); got shape {world.shape}.")
        if not np.all(np.isfinite(world)):
            raise ValueError("`world` has NaN or inf entries.")
    mask = np.all(np.isfinite(pixels), -1) if mask is None else np.asarray(mask)
    if mask.dtype != bool or mask.shape != (C, P):
        raise ValueError(f"`mask` must be bool of shape ({C}, {P}); got {mask.dtype} {mask.shape}.")
    if not np.all(np.isfinite(pixels[mask])):
        raise ValueError("`pixels` has NaN or inf entries where `mask` is True.")
    pixels = np.where(mask[..., None], pixels, np.nan)
    cameras = [f"cam_{i}" for i in range(C)] if cameras is None else [str(s) for s in cameras]
    points = [str(i) for i in range(P)] if points is None else [str(s) for s in points]
    for what, names, n in (("cameras", cameras, C), ("points", points, P)):
        if len(names) != n or len(set(names)) != n or "" in names:
            raise ValueError(f"need {n} different, non-empty `{what}` names; got {len(names)}.")
    if any("\n" in s or "\r" in s for s in cameras + points):
        raise ValueError("camera and point names must not contain line breaks.")
    if unlabelled is None:
        unlabelled = [np.zeros((0, 2)) for _ in range(C)]
    unlabelled = [np.array(u, dtype=float).reshape(-1, 2) for u in unlabelled]
    if len(unlabelled) != C or not all(np.all(np.isfinite(u)) for u in unlabelled):
        raise ValueError(f"`unlabelled` must be {C} finite (K, 2) arrays, one per camera.")
    return Correspondences(world, pixels, mask, cameras, points, unlabelled)


def _number(v) -> str:
    return repr(float(v))  # the shortest string that reads back as the same double


def _to_csv(c: Correspondences) -> str:
    import csv
    import io as _io

    buffer = _io.StringIO()
    out = csv.writer(buffer, lineterminator="\n")
    has_world = c.world is not None
    out.writerow(_COLUMNS if has_world else ("camera", "point", *_PIXEL))
    blank = [""] * 3 if has_world else []
    world = [[_number(v) for v in row] for row in c.world] if has_world else [[]] * len(c.points)
    # A reader orders the points as they first appear; where the observations alone would give
    # another order (or miss points that no camera saw), name every point first.
    _, first = np.unique(np.nonzero(c.mask)[1], return_index=True)
    if not np.array_equal(np.argsort(first, kind="stable"), np.arange(len(c.points))):
        for p, name in enumerate(c.points):
            out.writerow(["", name, *world[p], "", ""])
    for i, camera in enumerate(c.cameras):
        seen = np.flatnonzero(c.mask[i])
        for p in seen:
            out.writerow([camera, c.points[p], *world[p], *map(_number, c.pixels[i, p])])
        for xy in c.unlabelled[i]:
            out.writerow([camera, "", *blank, *map(_number, xy)])
        if not seen.size and not len(c.unlabelled[i]):
            out.writerow([camera, "", *blank, "", ""])  # a camera that saw nothing
    return buffer.getvalue()


def _to_json(c: Correspondences) -> str:
    document = {"format": CORRESPONDENCES, "version": VERSION, "cameras": c.cameras,
                "points": c.points}  # fmt: skip
    if c.world is not None:
        document["world"] = _plain(c.world)
    document["pixels"] = [
        [_plain(c.pixels[i, p]) if c.mask[i, p] else None for p in range(len(c.points))]
        for i in range(len(c.cameras))
    ]
    if any(len(u) for u in c.unlabelled):
        document["unlabelled"] = [_plain(u) for u in c.unlabelled]
    return json.dumps(document, allow_nan=False) + "\n"


def _from_csv(text: str, path) -> Correspondences:
    import csv

    lines = [(n, ln) for n, ln in enumerate(text.splitlines(), 1) if not ln.startswith("#")]
    lines = [(n, ln) for n, ln in lines if ln.strip()]
    if not lines:
        raise ValueError(f"{path}: empty; expected the header {','.join(_COLUMNS)}.")
    rows = csv.reader([ln for _, ln in lines])
    header = [h.strip().lower() for h in next(rows)]
    unknown = [h for h in header if h not in _COLUMNS]
    has_world = any(h in _WORLD for h in header)
    missing = [h for h in ("camera", *_PIXEL, *(_WORLD if has_world else ())) if h not in header]
    if unknown or missing or len(set(header)) != len(header):
        problem = f"unknown column {unknown[0]!r}" if unknown else (
            f"no {missing[0]!r} column" if missing else "a repeated column")  # fmt: skip
        raise ValueError(f"{path}:{lines[0][0]}: {problem}; the header is {','.join(_COLUMNS)}"
                         " (world_* columns optional, point optional with world_*).")  # fmt: skip
    if "point" not in header and not has_world:
        raise ValueError(f"{path}: a file without world_* columns needs a 'point' column.")
    column = {h: k for k, h in enumerate(header)}
    cameras, points, world, seen, unlabelled = {}, {}, {}, {}, {}
    for (line, _), row in zip(lines[1:], rows):
        where = f"{path}:{line}"
        if len(row) != len(header):
            raise ValueError(f"{where}: {len(row)} fields; the header has {len(header)}.")
        field = {h: row[k].strip() for h, k in column.items()}

        def numbers(names, where=where, field=field):
            values = [field[h] for h in names]
            if not any(values):
                return None
            try:
                xs = tuple(float(v) for v in values)
            except ValueError:
                raise ValueError(f"{where}: {', '.join(values)} are not all numbers.") from None
            if not all(math.isfinite(x) for x in xs):
                raise ValueError(f"{where}: NaN or inf in {', '.join(names)}.")
            return xs

        camera = field["camera"]
        xyz = numbers(_WORLD) if has_world else None
        xy = numbers(_PIXEL)
        name = field.get("point", "")
        if not name and "point" not in field and xyz is not None:
            name = world.get(("by position", xyz), str(len(points)))
            world.setdefault(("by position", xyz), name)
        if name:
            if has_world and xyz is None:
                raise ValueError(f"{where}: point {name!r} has no world coordinates.")
            if world.setdefault(name, xyz) != xyz:
                raise ValueError(f"{where}: point {name!r} has other world coordinates "
                                 "than in an earlier row.")  # fmt: skip
            points.setdefault(name, len(points))
        elif xyz is not None:
            raise ValueError(f"{where}: world coordinates without a point name.")
        if not camera:
            if xy is not None or not name:
                raise ValueError(f"{where}: a pixel (or an empty row) without a camera.")
            continue  # a point named without an observation
        cameras.setdefault(camera, len(cameras))
        unlabelled.setdefault(camera, [])
        if xy is None:
            if name:
                raise ValueError(f"{where}: camera {camera!r} and point {name!r} but no pixel.")
            continue  # a camera that saw nothing
        if not name:
            unlabelled[camera].append(xy)
        elif seen.setdefault((camera, name), (line, xy)) != (line, xy):
            first = seen[(camera, name)][0]
            raise ValueError(f"{where}: camera {camera!r} saw point {name!r} on line {first} too.")
    if not cameras:
        raise ValueError(f"{path}: no observations.")
    pixels = np.full((len(cameras), len(points), 2), np.nan)
    mask = np.zeros((len(cameras), len(points)), bool)
    for (camera, name), (_, xy) in seen.items():
        pixels[cameras[camera], points[name]] = xy
        mask[cameras[camera], points[name]] = True
    xyz = np.array([world[n] for n in points], dtype=float).reshape(-1, 3) if has_world else None
    return Correspondences(
        world=xyz,
        pixels=pixels,
        mask=mask,
        cameras=list(cameras),
        points=list(points),
        unlabelled=[np.array(unlabelled[c], dtype=float).reshape(-1, 2) for c in cameras],
    )


def _from_json(text: str, path) -> Correspondences:
    try:
        document = json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(document, dict) or document.get("format") != CORRESPONDENCES:
        raise ValueError(f'{path}: not a correspondences file (no "format": "{CORRESPONDENCES}").')
    if document.get("version") != VERSION:
        version = document.get("version")
        raise ValueError(f"{path}: version {version}; this mvcalib reads {VERSION}.")
    try:
        cameras, points = list(document["cameras"]), list(document["points"])
        C, P = len(cameras), len(points)
        world = document.get("world")
        world = None if world is None else _array(world, (P, 3))
        rows = document["pixels"]
        if len(rows) != C or any(len(r) != P for r in rows):
            raise ValueError(f"pixels must be {C} lists of {P} entries")
        mask = np.array([[v is not None for v in r] for r in rows], dtype=bool).reshape(C, P)
        pixels = np.full((C, P, 2), np.nan)
        for i, r in enumerate(rows):
            for p, v in enumerate(r):
                if v is not None:
                    pixels[i, p] = _array(v, (2,))
        unlabelled = document.get("unlabelled") or [[] for _ in range(C)]
        unlabelled = [np.array(u, dtype=float).reshape(-1, 2) for u in unlabelled]
        return _checked(world, pixels, mask, cameras, points, unlabelled)
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: malformed correspondences ({error}).") from None
