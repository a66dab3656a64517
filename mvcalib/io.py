"""Saving and loading rigs (versioned JSON, OpenCV YAML, ROS camera_info, COLMAP, Kalibr,
aniposelib and caliscope TOML), correspondences (CSV, JSON) and a rig's observations of a moving
target (CSV, caliscope's xy.csv).

A rig file holds one entry per camera (name, intrinsics, `R`, `t`, distortion in OpenCV's order,
and optionally its calibration status and reprojection RMS). Cameras that failed have `null`
parameters, loaded back as NaN. Files are written to a temporary file beside the target and
renamed over it, so an interrupted write never leaves a half-written rig.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import operator
import os
import pathlib
import re
import stat
import tempfile
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _validate
from ._camera import LENSES, Camera

__all__ = [
    "save_json", "load_json", "save_opencv", "load_opencv", "opencv_name", "save_colmap",
    "load_colmap", "write_atomic", "save_aniposelib", "load_aniposelib", "Correspondences",
    "save_correspondences", "load_correspondences", "Observations", "save_observations",
    "load_observations", "load_caliscope", "load_caliscope_cameras", "load_openptv_clicks",
    "load_clicks", "load_openptv_calibration", "save_kalibr", "load_kalibr", "save_ros",
    "load_ros",
]  # fmt: skip

FORMAT = "mvcalib.rig"
VERSION = 1
_SCALARS = ("alpha_u", "alpha_v", "u0", "v0", "skew")


# Data files are read as UTF-8 with its byte-order mark dropped if there is one (a spreadsheet's
# "CSV UTF-8" starts with it: "\ufeffcamera" was an unknown column), not in the locale's encoding.
ENCODING = "utf-8-sig"


def write_atomic(path, data: str | bytes) -> pathlib.Path:
    """Write `data` to `path` through a temporary file and a rename: all or nothing."""
    path = pathlib.Path(path)
    mode = "wb" if isinstance(data, bytes) else "w"
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as error:
        raise _cannot_write(path, error) from error
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
    except BaseException as error:
        pathlib.Path(tmp).unlink(missing_ok=True)
        if isinstance(error, OSError):  # named by the file asked for, not the temporary one
            raise _cannot_write(path, error) from error
        raise
    return path


def _cannot_write(path, error: OSError) -> OSError:
    """`error` saying which file could not be written (of the same class: the same errno)."""
    if error.errno is None:
        return OSError(f"cannot write {path}: {error}")
    return OSError(error.errno, f"cannot write {path}: {error.strerror}")


def _plain(x):
    """Nested lists of floats with None for NaN/inf (JSON has no NaN)."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        return float(x) if math.isfinite(x) else None
    return [_plain(v) for v in x]


def _names(names, n: int, default: str) -> list[str]:
    """A rig file's camera names: `names` as strings, one per camera, or `default.format(i)`."""
    names = [default.format(i) for i in range(n)] if names is None else [str(s) for s in names]
    if len(names) != n:
        raise ValueError(f"{len(names)} names for {n} cameras.")
    return names


def _array(x, shape):
    a = np.array(x if x is not None else np.full(shape, np.nan), dtype=object)
    a = np.where(a == None, np.nan, a).astype(float)  # noqa: E711 (elementwise on objects)
    if a.shape != shape:
        raise ValueError(f"expected shape {shape}; got {a.shape}")
    return a


def _one_axis(cameras: Camera) -> Camera:
    """The rig in NumPy (no program per index) with one camera axis: a camera gets one; a rig
    of more axes is refused."""
    rig = jax.tree_util.tree_map(lambda a: np.asarray(a, dtype=float), cameras)
    rig = jax.tree_util.tree_map(lambda a: a[None], rig) if rig.batch_shape == () else rig
    if len(rig.batch_shape) != 1:
        raise ValueError(f"save one camera axis; got a rig of shape {rig.batch_shape}.")
    return rig


def _check_cameras(cameras, function: str) -> None:
    """Refuse anything but a `Camera` (a calibration's result is a common slip), saying what to
    pass instead; and a Camera that no reader would load: traced (inside `jax.jit` or `grad`),
    or with an `R` that is not a rotation (a `Camera`-shaped gradient or update, which JAX code
    makes easily, was written and then refused by `load_json`: a user's trial)."""
    if isinstance(cameras, Camera):
        if not _validate.is_concrete(*jax.tree_util.tree_leaves(cameras)):
            raise TypeError(
                f"{function} writes arrays to a file: it needs concrete cameras, outside "
                "jax.jit, grad and vmap."
            )
        names = list(range(math.prod(cameras.batch_shape)))
        _check_rotations(function, cameras.R, names)
        return
    name = type(cameras).__name__
    fields = [f for f in ("cameras", "camera") if isinstance(getattr(cameras, f, None), Camera)]
    field = fields[0] if fields else None
    hint = f": pass its cameras, `result.{field}`" if field else ""
    raise TypeError(f"{function} saves an mvcalib.Camera; got {name}{hint}.")


def _reads_rig(load):
    """A rig reader that warns where JAX's default float32 holds what it read (x64 off): the
    file's values rounded to ~7 digits, which a save writes back as they are (a round trip
    changed `u0 = 639.3` to `639.2999877929688`, silently)."""

    @functools.wraps(load)
    def read(*args, **kwargs):
        out = load(*args, **kwargs)
        if not jax.config.jax_enable_x64:
            warnings.warn(
                f"{load.__name__}: the rig is held in float32 (JAX's default), its values rounded "
                "to ~7 digits, and saving it writes them so; "
                'jax.config.update("jax_enable_x64", True) before loading keeps the file\'s.',
                stacklevel=2,
            )
        return out

    return read


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
    _check_cameras(cameras, "save_json")
    rig = _one_axis(cameras)
    n = rig.batch_shape[0]
    names = _names(names, n, "cam_{}")
    entries = []
    for i in range(n):
        entry = {"name": names[i]}
        entry.update({k: _plain(getattr(rig, k)[i]) for k in _SCALARS})
        entry.update(R=_plain(rig.R[i]), t=_plain(rig.t[i]), dist=_plain(rig.dist[i]))
        entry["lens"] = rig.lens
        if status is not None:
            entry["status"] = int(np.asarray(status).reshape(-1)[i])
        if rms is not None:
            entry["rms"] = _plain(np.asarray(rms).reshape(-1)[i])
        entries.append(entry)
    document = {"format": FORMAT, "version": VERSION, "cameras": entries}
    if meta:
        document["meta"] = meta
    return write_atomic(path, json.dumps(document, indent=1, allow_nan=False) + "\n")


@_reads_rig
def load_json(path, *, record: bool = False):
    """Load a rig saved by `save_json`: `(cameras, names)`; `ValueError` if it is not one.

    With `record=True`, `(cameras, names, record)`, where `record` holds what `save_json`
    stored for the record: `"status"` (`(C,)` ints, `mvcalib.Status`) and `"rms"` (`(C,)`
    pixels, NaN where not stored), each None where the file has none, and `"meta"` (a dict).
    A rig read without it and saved again loses them.

    ```python
    >>> import jax, tempfile, pathlib, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 2).cameras
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "rig.json"
    >>> _ = mc.io.save_json(path, rig, status=[0, 6], rms=[0.3, 41.0], meta={"by": "me"})
    >>> cameras, names, record = mc.io.load_json(path, record=True)
    >>> [mc.Status(s).name for s in record["status"]], record["rms"].tolist(), record["meta"]
    (['OK', 'POOR_FIT'], [0.3, 41.0], {'by': 'me'})

    ```
    """
    path = pathlib.Path(path)
    try:
        document = json.loads(path.read_text(encoding=ENCODING))
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
    lenses = []
    try:
        for entry in cameras:
            lens = entry.get("lens", "pinhole")  # (files before the fisheye have no "lens")
            if lens not in LENSES:
                raise ValueError(f"lens {lens!r} is not one of {tuple(LENSES)}")
            n_dist = len(LENSES[lens])
            for k in _SCALARS:
                fields[k].append(_array(entry[k], ()))
            fields["R"].append(_array(entry["R"], (3, 3)))
            fields["t"].append(_array(entry["t"], (3,)))
            fields["dist"].append(_array(entry.get("dist", [0.0] * n_dist), (n_dist,)))
            lenses.append(lens)
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        where = f"{path}: camera entry {len(fields['R'])}"
        raise ValueError(f"{where} is malformed ({error}).") from None
    names = [str(e.get("name", f"cam_{i}")) for i, e in enumerate(cameras)]
    lens = _one_lens(path, lenses, names)
    _check_rotations(path, fields["R"], names)
    # (put on the device from NumPy: `jnp.asarray` of float64 with x64 off compiles a program)
    stacked = {k: jax.device_put(np.stack(v)) for k, v in fields.items()}
    if not record:
        return Camera(**stacked, lens=lens), names
    try:
        stored = {
            key: np.array([kind(np.nan if e.get(key) is None else e[key]) for e in cameras])
            if any(key in e for e in cameras) else None
            for key, kind in (("status", int), ("rms", float))
        }  # fmt: skip
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: a camera's status or rms is malformed ({error}).") from None
    meta = document.get("meta") or {}
    meta = meta if isinstance(meta, dict) else {"meta": meta}
    return Camera(**stacked, lens=lens), names, {**stored, "meta": meta}


def _one_lens(path, lenses, names) -> str:
    """The lens of a rig read from a file: every camera's must be the same (a rig is one
    batched `Camera`; load a mixed set as separate rigs)."""
    if len(set(lenses)) > 1:
        by = {
            lens: [n for n, x in zip(names, lenses) if x == lens] for lens in dict.fromkeys(lenses)
        }
        listed = "; ".join(f"{lens}: {', '.join(map(str, n))}" for lens, n in by.items())
        raise ValueError(
            f"{path}: cameras of different lenses ({listed}); an mvcalib rig has one lens "
            "model. Split the file into one rig per lens."
        )
    return lenses[0] if lenses else "pinhole"


def _read_toml(path: pathlib.Path) -> dict:
    """A TOML calibration file's contents; `ValueError` naming the file if it cannot be read."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        raise ValueError("reading TOML calibration files needs Python >= 3.11.") from None
    try:
        return tomllib.loads(path.read_text(encoding=ENCODING))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
        raise ValueError(f"{path}: not a readable TOML calibration ({error})") from None


@_reads_rig
def load_aniposelib(path) -> tuple[Camera, list[str]]:
    """Load an aniposelib / anipose calibration file (TOML): `(cameras, names)`.

    Each `[cam_i]` table holds `matrix` (K), `distortions` (OpenCV's k1 k2 p1 p2 k3),
    `rotation` (a Rodrigues vector, world to camera) and `translation`; the cameras come back in
    the file's order of `cam_0, cam_1, ...`. Cameras with `fisheye = true` (aniposelib's
    `FisheyeCamera`: `cv2.fisheye`'s k1 k2 k3 k4) come back as `lens="fisheye"`; a file mixing
    both is refused (ValueError), as a rig has one lens. aniposelib's own `CameraGroup.load`
    orders the tables as strings (`cam_10` before `cam_2`): in a rig of more than ten cameras
    its camera order is not this one, so match arrays to cameras by the names returned (the
    mouse rig's tracks follow the numeric order; `save_aniposelib` pads the numbers, so that
    both orders agree). A `matrix` with a skew entry (K[0,1])
    is read as aniposelib projects it, without (a warning says so). Needs Python >= 3.11
    (`tomllib`).
    """
    from ._rotation import rodrigues

    path = pathlib.Path(path)
    document = _read_toml(path)
    keys = sorted((k for k in document if re.fullmatch(r"cam_\d+", k)), key=lambda k: int(k[4:]))
    if not keys:
        raise ValueError(f"{path}: no [cam_N] tables.")
    # its 4 distortion terms of a fisheye are Kannala-Brandt's, not Brown-Conrady's
    lenses = ["fisheye" if document[k].get("fisheye", False) else "pinhole" for k in keys]
    lens = _one_lens(path, lenses, keys)
    n_dist = len(LENSES[lens])
    try:
        K = np.array([document[k]["matrix"] for k in keys], dtype=float)
        dist = [np.ravel(document[k].get("distortions", [0.0] * n_dist)) for k in keys]
        if any(len(d) > n_dist for d in dist):
            raise ValueError(f"more than {n_dist} distortion terms for a {lens} lens")
        dist = np.array([np.pad(np.asarray(d, float), (0, n_dist - len(d))) for d in dist])
        rvec = np.array([document[k]["rotation"] for k in keys], dtype=float)
        t = np.array([document[k]["translation"] for k in keys], dtype=float)
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: a camera table is malformed ({error}).") from None
    names = [str(document[k].get("name", k)) for k in keys]
    skewed = [n for n, k in zip(names, K) if k[0, 1] != 0]
    if skewed:  # aniposelib projects with cv2.projectPoints (or cv2.fisheye's, without alpha)
        warnings.warn(
            f"{path}: K[0,1] (skew) is not zero for {', '.join(skewed)}; aniposelib's "
            "projections ignore it, and so does this reading (zero skew).",
            stacklevel=2,
        )
        K[:, 0, 1] = 0.0
    return Camera.from_matrices(K, rodrigues(jnp.asarray(rvec)), t, dist, lens=lens), names


def save_aniposelib(path, cameras: Camera, image_size, *, names=None) -> pathlib.Path:
    """Save a rig as an aniposelib / anipose calibration file (TOML), atomically: what
    `aniposelib.cameras.CameraGroup.load` reads, and `load_aniposelib`.

    **Arguments:**

    - `path`: the file to write (replaced whole, or not at all).
    - `cameras`: the rig, a `Camera` with one camera axis.
    - `image_size`: `(width, height)` in pixels, for every camera or `(C, 2)`: aniposelib's
      cameras need theirs (`size`).
    - `names`: a name per camera (default `0`, `1`, ...), aniposelib's `name`.

    Each camera is a table of `name`, `size`, `matrix` (K), `distortions` (k1 k2 p1 p2 k3; a
    fisheye's k1 k2 k3 k4, with `fisheye = true`), `rotation` (a Rodrigues vector, world to
    camera) and `translation`, and an empty `[metadata]` table follows. The tables are named
    `cam_00`, `cam_01`, ... with as many digits as the last needs: aniposelib orders them as
    strings (`cam_10` before `cam_2`), which permuted the cameras of rigs of more than ten; so
    padded, its order is theirs. A camera with skew is refused (ValueError): aniposelib projects
    with `cv2.projectPoints`, which ignores K[0,1]. Numbers are written with Python's shortest
    exact representation (rotations as vectors: to ~1e-16).

    **Example:**

    ```python
    >>> import jax, tempfile, pathlib, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3).cameras
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "calibration.toml"
    >>> _ = mc.io.save_aniposelib(path, rig, (1000, 1100), names=["A", "B", "C"])
    >>> back, names = mc.io.load_aniposelib(path)
    >>> world = mc.targets.box_corner().points
    >>> names, bool(np.allclose(back.project(world), rig.project(world), rtol=0, atol=1e-9))
    (['A', 'B', 'C'], True)

    ```
    """
    _check_cameras(cameras, "save_aniposelib")
    rig = jax.tree_util.tree_map(np.asarray, cameras)
    if len(rig.batch_shape) != 1:
        raise ValueError(f"save a rig with one camera axis; got the shape {rig.batch_shape}.")
    n = rig.batch_shape[0]
    if np.any(rig.skew != 0):
        raise ValueError(
            "aniposelib's cameras have no skew (cv2.projectPoints ignores K[0,1]); refine "
            "with skew=False (refine's default) first."
        )
    if not np.all(np.isfinite(rig.K)):
        raise ValueError("the rig has cameras that are not calibrated (NaN); leave them out.")
    size = np.broadcast_to(np.asarray(image_size), (n, 2)) if np.ndim(image_size) else None
    if size is None or not np.all(size > 0) or not np.all(size == np.round(size)):
        raise ValueError(f"`image_size` must be (width, height) or ({n}, 2) of positive ints.")
    names = _names(names, n, "{}")
    rvec = [_rotation_vector(r) for r in rig.R]

    def toml(x):  # a TOML value: arrays of floats, ints or a string
        if isinstance(x, str):
            return json.dumps(x, ensure_ascii=False)  # (JSON's escapes are TOML's)
        if np.ndim(x):
            return "[ " + ", ".join(toml(v) for v in x) + ",]"
        return str(int(x)) if isinstance(x, (int, np.integer)) else repr(float(x))

    digits = len(str(n - 1))
    lines = []
    for i in range(n):
        lines += [
            f"[cam_{i:0{digits}d}]",
            f"name = {toml(names[i])}",
            f"size = {toml([int(v) for v in size[i]])}",
            f"matrix = {toml(rig.K[i])}",
            f"distortions = {toml(rig.dist[i])}",
            f"rotation = {toml(rvec[i])}",
            f"translation = {toml(rig.t[i])}",
            *(["fisheye = true"] if rig.lens == "fisheye" else []),
            "",
        ]
    return write_atomic(path, "\n".join([*lines, "[metadata]", ""]))


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


# The lens's tag in FileStorage YAML: ROS camera_info's names (`distortion_model`).
_OPENCV_MODEL = {"pinhole": "plumb_bob", "fisheye": "equidistant"}
_OPENCV_LENS = {"plumb_bob": "pinhole", "rational_polynomial": "pinhole",
                "equidistant": "fisheye", "fisheye": "fisheye"}  # fmt: skip


def _opencv_camera(camera: Camera, indent: str, image_size) -> list[str]:
    lines = []
    if image_size is not None:
        width, height = (int(v) for v in image_size)
        lines += [f"{indent}image_width: {width}", f"{indent}image_height: {height}"]
    lines += _opencv_matrix("camera_matrix", camera.K, indent)
    if camera.lens == "fisheye" and float(camera.skew) != 0.0:
        # cv2.fisheye ignores K's skew entry and takes `alpha = skew / fx` as an argument: read
        # without it, the file's K and D put points 1.4 px off where a 1.5 px skew was
        lines.append(f"{indent}alpha: {float(camera.skew) / float(camera.alpha_u)!r}")
    lines.append(f"{indent}distortion_model: {_OPENCV_MODEL[camera.lens]}")
    lines += _opencv_matrix("distortion_coefficients", np.asarray(camera.dist)[None], indent)
    lines += _opencv_matrix("R", camera.R, indent)
    lines += _opencv_matrix("T", np.asarray(camera.t)[:, None], indent)
    return lines


def _refuse_pinhole_skew(cameras: Camera, model: str) -> None:
    """`ValueError` for pinhole cameras with skew, which OpenCV's model (ROS's too) has not:
    `cv2.projectPoints` ignores K[0,1], so the file would put points `skew * y` off."""
    if cameras.lens == "pinhole" and np.any(np.asarray(cameras.skew) != 0):
        raise ValueError(
            f"{model} has no skew (cv2.projectPoints ignores K[0,1]: the file would put points "
            "skew * y off); calibrate with skew=False (`calibrate` estimates the DLT's skew by "
            "default) or refine with skew=False (refine's default) first."
        )


def opencv_name(name: str) -> str:
    """`name` as OpenCV's FileStorage keys allow (letters, digits and '_', not starting with a
    digit), as the command line writes camera names to OpenCV's YAML.

    ```python
    >>> import mvcalib as mc
    >>> mc.io.opencv_name("cal/cam1.tif"), mc.io.opencv_name("10")
    ('cal_cam1_tif', 'cam_10')

    ```
    """
    name = re.sub(r"\W", "_", str(name))
    return name if name[:1].isalpha() or name[:1] == "_" else f"cam_{name}"


def save_opencv(path, cameras: Camera, *, names=None, image_size=None) -> pathlib.Path:
    """Save cameras as OpenCV FileStorage YAML, readable by `cv2.FileStorage`, atomically.

    One camera is written at the top level with OpenCV's usual keys: `camera_matrix` (K),
    `distortion_model` (ROS's tag: `plumb_bob` for a pinhole, `equidistant` for a fisheye),
    `distortion_coefficients` (1 x 5: k1 k2 p1 p2 k3; a fisheye's 1 x 4: k1 k2 k3 k4, as
    `cv2.fisheye` takes them), `R` (world to camera) and `T` (3 x 1), with
    `image_width`/`image_height` if `image_size=(width, height)` is given. A fisheye with skew
    also gets `alpha` (skew / fx): `cv2.fisheye`'s functions ignore K's skew entry and take
    it as their `alpha` argument (`cv2.fisheye.projectPoints(X, rvec, tvec, K, D, alpha)`). A
    pinhole with skew is refused (ValueError): OpenCV's pinhole functions have no skew and ignore
    K's entry. A rig (or a camera given `names`) is written as one map per camera (`cam_0`, ...
    or `names`) holding those keys, and `cameras` listing the names. Numbers are written with
    Python's shortest exact representation, so reading back (with `load_opencv` or
    `cv2.FileStorage`) gives the same doubles.

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
    _check_cameras(cameras, "save_opencv")
    _refuse_pinhole_skew(cameras, "OpenCV's pinhole model")
    if cameras.batch_shape == () and names is not None:  # a named camera: a rig of one
        cameras = jax.tree_util.tree_map(lambda a: np.asarray(a)[None], cameras)
    if cameras.batch_shape == ():
        lines += _opencv_camera(cameras, "", image_size)
    else:
        if len(cameras.batch_shape) != 1:
            raise ValueError(f"save one camera axis; got a rig of shape {cameras.batch_shape}.")
        n = cameras.batch_shape[0]
        names = _names(names, n, "cam_{}")
        wrong = [s for s in names if not s.isidentifier()]
        if wrong:
            spelled = ", ".join(f"{s!r} as {opencv_name(s)!r}" for s in wrong[:3])
            raise ValueError(
                f"OpenCV's YAML keys are letters, digits and '_', not starting with a digit: "
                f"{', '.join(map(repr, wrong[:3]))}{' ...' if len(wrong) > 3 else ''} "
                f"cannot name a camera. Name them so (`names=[mc.io.opencv_name(n) for n in "
                f"names]`: {spelled}, as the command line writes them)."
            )
        if "cameras" in names:
            raise ValueError("a camera may not be named 'cameras': the key that lists them.")
        lines.append("cameras: [ " + ", ".join(f'"{s}"' for s in names) + " ]")
        for i, name in enumerate(names):
            lines.append(f"{name}:")
            lines += _opencv_camera(cameras[i], "   ", image_size)
    return write_atomic(path, "\n".join(lines) + "\n")


@_reads_rig
def load_opencv(path) -> tuple[Camera, list[str]]:
    """Load a file written by `save_opencv` (or any FileStorage YAML with `camera_matrix`,
    `distortion_coefficients`, `R`, `T`, at the top level or in per-camera maps listed by
    `cameras`): `(cameras, names)`; a single camera comes back with no camera axis. The lens is
    `distortion_model`'s (`equidistant` or `fisheye`: a fisheye; none, `plumb_bob` or
    `rational_polynomial`: a pinhole, whose coefficients beyond k3 must be zero). `R` may be a
    rotation vector (3 x 1, Rodrigues', as OpenCV's `rvecs`); `cameras` a flow (`[ a, b ]`) or
    block (`- a` lines) sequence, as `cv2.FileStorage` writes it. A camera with neither `R` nor
    `T` (the intrinsics alone, as OpenCV's calibration samples save them) has a NaN pose: its
    intrinsics start `calibrate_rig(..., cameras=..., fix=("intrinsics", "distortion"))`,
    which takes the poses from the frames."""
    from ._rotation import rodrigues

    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding=ENCODING)
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: cannot be read ({error})") from None
    head = text.lstrip()[:1]
    if head in ("<", "{"):
        kind = "XML" if head == "<" else "JSON"
        raise ValueError(
            f"{path}: a FileStorage {kind} file; mvcalib reads OpenCV's YAML (cv2.FileStorage "
            "reads this one and writes it again as YAML under a .yml name)."
        )
    tree = _parse_opencv_yaml(text, path)
    if "cameras" in tree:
        names = tree["cameras"]
        maps = [tree.get(n) for n in names]
    else:
        names, maps = ["camera"], [tree]
    if isinstance(tree.get("camera_matrix"), dict):
        raise ValueError(f"{path}: a ROS camera_info file; read it with mc.io.load_ros(path).")
    fields, lenses = [], []
    for name, node in zip(names, maps):
        if isinstance(node, dict) and "R" not in node and "T" not in node:
            # the intrinsics alone (OpenCV's calibration samples save no pose): the pose unknown
            node = {**node, "R": np.full((3, 3), np.nan), "T": np.full(3, np.nan)}
        try:
            K, dist, R, T = (
                node[k] for k in ("camera_matrix", "distortion_coefficients", "R", "T")
            )
            if np.size(R) == 3:  # a rotation vector, as cv2.calibrateCamera's rvecs
                R = np.asarray(rodrigues(jnp.asarray(R.reshape(3), dtype=float)))
            fields.append((K.reshape(3, 3), dist.reshape(-1), R.reshape(3, 3), T.reshape(3)))
        except (KeyError, TypeError, ValueError, AttributeError):
            missing = [k for k in ("camera_matrix", "distortion_coefficients", "R", "T")
                       if not isinstance(node, dict) or k not in node]  # fmt: skip
            raise ValueError(
                f"{path}: camera {name!r} "
                + (f"lacks {', '.join(missing)}" if missing else "has a matrix of a wrong size")
                + " (camera_matrix 3x3, distortion_coefficients 1x5 or 1x4, R 3x3 or 3x1, T 3x1)."
            ) from None
        model = node.get("distortion_model", "plumb_bob")
        if "distortion_model" not in node and np.size(dist) == 4 and np.any(dist):
            # (OpenCV's files do not say which: a cv2.fisheye calibration saved by hand read
            # as a pinhole projects wide angles wrongly; an OpenCV user's trial)
            warnings.warn(
                f"{path}: camera {name!r} has four distortion coefficients and no "
                "distortion_model: read as a pinhole's k1 k2 p1 p2 (OpenCV's plumb_bob, k3 "
                "zero); a cv2.fisheye calibration's four need `distortion_model: fisheye`.",
                stacklevel=2,
            )
        lenses.append(_model_lens(path, name, model))
    lens = _one_lens(path, lenses, names)
    dists = _coefficients(path, names, [f[1] for f in fields], lens)
    fields = [(K, d, R, T) for (K, _, R, T), d in zip(fields, dists)]
    K, dist, R, T = (np.stack(f) for f in zip(*fields))
    _check_rotations(path, R, names)
    cameras = Camera.from_matrices(
        jnp.asarray(K), jnp.asarray(R), jnp.asarray(T), jnp.asarray(dist), lens=lens
    )
    if "cameras" not in tree:
        cameras = cameras[0]
    return cameras, list(names)


def _model_lens(path, name, model: str) -> str:
    """The lens of a camera whose file names its `distortion_model` (ROS's tags)."""
    if model not in _OPENCV_LENS:
        raise ValueError(
            f"{path}: camera {name!r} has distortion_model {model!r}; mvcalib reads "
            f"{', '.join(_OPENCV_LENS)}."
        )
    return _OPENCV_LENS[model]


def _coefficients(path, names, dists, lens: str) -> list[np.ndarray]:
    """Each camera's distortion coefficients as `lens` takes them: fewer padded with zeros (an
    OpenCV pinhole's four: k3 zero), more refused unless zero (a rational model's k4-k6)."""
    n = len(LENSES[lens])
    for name, dist in zip(names, dists):
        if len(dist) > n and np.any(dist[n:]):
            raise ValueError(
                f"{path}: camera {name!r} has {len(dist)} distortion coefficients; a {lens} "
                f"lens has {n} ({', '.join(LENSES[lens])}), and the others are not zero."
            )
    return [np.pad(d, (0, max(0, n - len(d))))[:n] for d in dists]


# A rig file's R may be off a rotation by its rounding (a file written by hand with five or
# more digits), not by more: any 3 x 3 matrix was taken, and projected as given.
_ROTATION_TOLERANCE = 1e-4


def _check_rotations(path, R, names) -> None:
    """`ValueError` naming the first camera whose `R` is not a rotation (NaN ones, a failed
    camera's, pass): `|R^T R - I|` beyond `_ROTATION_TOLERANCE`, or a reflection."""
    for name, r in zip(names, np.asarray(R, dtype=float).reshape(-1, 3, 3)):
        if not np.all(np.isfinite(r)):
            continue
        off = np.abs(r.T @ r - np.eye(3)).max()
        if off > _ROTATION_TOLERANCE or np.linalg.det(r) < 0:
            what = f"R^T R is {off:.2g} off the identity" if off > _ROTATION_TOLERANCE else (
                "its determinant is -1: a reflection")  # fmt: skip
            raise ValueError(f"{path}: camera {name!r}: R is not a rotation ({what}).")


def _parse_opencv_yaml(text: str, path) -> dict:
    """The small YAML subset FileStorage (and ROS's camera_info) writes: maps by indentation,
    `!!opencv-matrix` nodes, scalars, and sequences of scalars in brackets (`[ a, b ]`, over one
    or several lines) or one item a line (`- a`, indented or not); comments (`# ...`) dropped."""
    lines = []
    for ln in text.splitlines():
        if ln.startswith(("%", "---")):
            continue
        ln = _uncommented(ln)
        if not ln.strip():
            continue
        if lines and lines[-1].count("[") > lines[-1].count("]"):  # a flow sequence goes on
            lines[-1] += " " + ln.strip()
        else:
            lines.append(ln)
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
        item = line.strip() == "-" or line.strip().startswith("- ")
        while indent < stack[-1][0] or (
            indent == stack[-1][0]
            and not (item and (isinstance(stack[-1][1], list) or stack[-1][1] == {}))
        ):  # (a sequence's items may be indented as its key is)
            stack.pop()
        parent = stack[-1][1]
        if item:  # an item of a block sequence
            if not isinstance(parent, list):  # (opened as a map: it is a sequence)
                if parent or len(stack) < 2:
                    raise ValueError(f"{path}: a '-' item outside a sequence: {line.strip()!r}.")
                outer, name = stack[-2][1], next(k for k, v in stack[-2][1].items() if v is parent)
                outer[name] = parent = []
                stack[-1] = (stack[-1][0], parent)
            parent.append(line.strip()[1:].strip().strip("\"'"))
            continue
        key, _, value = line.strip().partition(":")
        value = value.strip()
        if value.startswith("!!opencv-matrix"):
            matrix = {"indent": indent, "parent": parent, "key": key, "fields": {}, "last": None}
        elif value == "":
            parent[key] = {}
            stack.append((indent, parent[key]))
        elif value.startswith("["):
            items = value.strip("[] ").split(",")
            parent[key] = [v.strip().strip("\"'") for v in items if v.strip()]
        else:
            parent[key] = value.strip("\"'")
    if matrix is not None:
        _finish_matrix(matrix, path)
    return root


def _uncommented(line: str) -> str:
    """`line` without its YAML comment: from a `#` outside quotes that starts the line or follows
    a blank (`distortion_model: plumb_bob  # 5 coefficients` was read as that whole model)."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[:i].rstrip()
    return line


def _finish_matrix(matrix, path):
    fields, key = matrix["fields"], matrix["key"]
    try:
        data = [float(v) for v in fields["data"].strip("[] ").split(",") if v.strip()]
        matrix["parent"][key] = np.array(data).reshape(int(fields["rows"]), int(fields["cols"]))
    except (KeyError, ValueError) as error:
        raise ValueError(f"{path}: opencv-matrix {key!r} is malformed ({error}).") from None


def _in_metres(rig: Camera, metres_per_unit, writer: str, whose: str, far: float) -> Camera:
    """`rig` (NumPy, one camera axis) with its translations in metres, for a file whose units
    are metres; a warning where its cameras then stand more than `far` metres apart (a rig in
    millimetres, unscaled: a 2 m rig 2 km wide, a 12 cm baseline 120 m)."""
    if not (np.isfinite(metres_per_unit) and metres_per_unit > 0):
        raise ValueError(f"`metres_per_unit` is positive; got {metres_per_unit!r}.")
    rig = eqx.tree_at(lambda c: c.t, rig, np.asarray(rig.t) * float(metres_per_unit))
    centres = np.einsum("cji,cj->ci", rig.R, -rig.t)
    span = float(np.max(np.linalg.norm(centres - centres[0], axis=-1)))
    if span > far:
        warnings.warn(
            f"{writer}: the cameras stand {span:.4g} m apart, read as {whose} metres: is the "
            "rig in millimetres? (metres_per_unit=0.001)",
            stacklevel=3,
        )
    return rig


# ---------------------------------------------------------------------------- ROS camera_info
# The matrices of a camera_info file and their shapes.
_ROS_MATRICES = {"camera_matrix": (3, 3), "distortion_coefficients": (-1,),
                 "rectification_matrix": (3, 3), "projection_matrix": (3, 4)}  # fmt: skip


def _ros_matrix(name: str, a) -> list[str]:
    a = np.atleast_2d(np.asarray(a, dtype=float))
    values = ", ".join(repr(float(v)) for v in a.ravel())  # repr: shortest exact round trip
    return [f"{name}:", f"  rows: {a.shape[0]}", f"  cols: {a.shape[1]}", f"  data: [{values}]"]


def save_ros(
    paths, cameras: Camera, image_size, *, names=None, alpha: float = 0.0, metres_per_unit=1.0
):
    """Save one camera, or a stereo pair, as ROS camera_info YAML (the format of
    `camera_calibration_parsers`, which `camera_info_manager` loads and ROS's calibrator
    writes): one file per camera, atomically. Returns the paths written.

    Each file holds `image_width`, `image_height`, `camera_name`, `camera_matrix` (K),
    `distortion_model` (`plumb_bob` for a pinhole, k1 k2 p1 p2 k3; `equidistant` for a fisheye,
    k1 k2 k3 k4), `distortion_coefficients`, `rectification_matrix` and `projection_matrix`. One
    camera (`paths` one path): the rectification is the identity and the projection `[K' | 0]`,
    K' the camera matrix of its undistorted image (`mvcalib.undistorted(camera, image_size,
    alpha=alpha).K`, OpenCV's `getOptimalNewCameraMatrix`, as ROS's calibrator writes it). A
    stereo pair (`cameras` a rig of two, `paths` two, the left camera first): `R` and `P` of
    `mvcalib.stereo_rectify(cameras, image_size, alpha=alpha)` (OpenCV's R1, R2, P1, P2), so
    that ROS's `stereo_image_proc` rectifies the images as mvcalib does and `load_ros` reads the
    pair's relative pose back. A pinhole with skew is refused, as `save_opencv` refuses it.

    ROS's baseline (P2's fourth column, `-f' B`) is in metres, and a rig is in its target's
    units: give `metres_per_unit` (0.001 for a board measured in millimetres); a pair whose
    cameras then stand more than 10 m apart is written with a warning. ROS takes the left
    camera first: a pair whose second camera stands to the left of the first (a positive
    `Tx`, which ROS would read as a disparity of the wrong sign) is refused, with the order to
    pass.

    **Example:**

    ```python
    >>> import tempfile, pathlib, numpy as np, mvcalib as mc
    >>> R = np.stack([np.eye(3), np.asarray(mc.rodrigues(np.array([0.0, 0.1, 0.0])))])
    >>> pair = mc.Camera([800.0, 810.0], [800.0, 810.0], [640.0, 630.0], [400.0, 410.0], R,
    ...                  [[0.0, 0.0, 0.0], [-0.1, 0.0, 0.0]], dist=[[-0.1, 0.01, 0, 0, 0]] * 2)
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> paths = mc.io.save_ros([folder / "left.yaml", folder / "right.yaml"], pair, (1280, 800))
    >>> back, names = mc.io.load_ros(*paths)  # the right camera in the left one's frame
    >>> names, bool(np.allclose(back.center, pair.center)), bool(np.allclose(back.K, pair.K))
    (['left', 'right'], True, True)

    ```
    """
    from ._stereo import _image_size, stereo_rectify, undistorted

    _check_cameras(cameras, "save_ros")
    _refuse_pinhole_skew(cameras, "ROS's pinhole model (OpenCV's)")
    size = _image_size(image_size, "io.save_ros")
    paths = [pathlib.Path(paths)] if isinstance(paths, (str, os.PathLike)) else list(paths)
    shape = cameras.batch_shape
    if not (len(paths) == 1 and shape in ((), (1,)) or len(paths) == 2 and shape == (2,)):
        raise ValueError(
            f"save_ros writes one camera to one path or a stereo pair to two; got {len(paths)} "
            f"path(s) for cameras of batch shape {shape}."
        )
    names = _names(names, len(paths), "") if names is not None else [p.stem for p in paths]
    rig = jax.tree_util.tree_map(lambda a: np.asarray(a, dtype=float).reshape(
        (len(paths),) + np.shape(a)[len(shape):]), cameras)  # fmt: skip
    if len(paths) == 2:
        rig = _in_metres(rig, metres_per_unit, "save_ros", "ROS's", 10.0)
        rect = stereo_rectify(rig, size, alpha=alpha)
        R, P = np.asarray(rect.R), np.asarray(rect.P)
        if not bool(rect.vertical) and P[1, 0, 3] > 0:
            raise ValueError(
                "the pair's second camera stands to the left of the first; ROS's stereo pair "
                "is the left camera first: pass `cameras[::-1]` (and the names, paths, in that "
                "order)."
            )
    else:
        K = np.asarray(undistorted(rig, size, alpha=alpha).K)
        R, P = np.eye(3)[None], np.concatenate([K, np.zeros((1, 3, 1))], -1)
    written = []
    for i, path in enumerate(paths):
        camera = rig[i]
        lines = [
            f"image_width: {size[0]}",
            f"image_height: {size[1]}",
            f"camera_name: {names[i]}",
            *_ros_matrix("camera_matrix", camera.K),
            f"distortion_model: {_OPENCV_MODEL[rig.lens]}",
            *_ros_matrix("distortion_coefficients", np.asarray(camera.dist)[None]),
            *_ros_matrix("rectification_matrix", R[i]),
            *_ros_matrix("projection_matrix", P[i]),
        ]
        written.append(write_atomic(path, "\n".join(lines) + "\n"))
    return written


@_reads_rig
def load_ros(*paths) -> tuple[Camera, list[str]]:
    """Read ROS camera_info YAML files (`save_ros`'s, ROS's calibrator's, `camera_info_manager`'s):
    `(cameras, names)`, the names from `camera_name` (else the file's name). One file gives one
    camera (no camera axis) with a NaN pose: a camera_info holds no pose. Two files of a stereo
    pair, the left first, give a rig of two in the left camera's frame, their relative pose from
    the rectification (`rectification_matrix` R1, R2 and the right camera's
    `projection_matrix`, whose fourth column holds f' times the baseline): `x_right = R2^T (R1
    x_left + b)`. Any other files (or two that are not a rectified pair) give cameras with NaN
    poses. The lens is `distortion_model`'s, as `load_opencv` reads it.

    The intrinsics start `calibrate_rig(..., cameras=..., fix=("intrinsics", "distortion"))`,
    which takes the poses from the frames where they are NaN."""
    if not paths:
        raise ValueError("load_ros takes the paths of one or more camera_info files.")
    paths = [pathlib.Path(p) for p in paths]
    names, fields, lenses, rectification = [], [], [], []
    for path in paths:
        try:
            text = path.read_text(encoding=ENCODING)
        except (OSError, UnicodeDecodeError) as error:
            raise ValueError(f"{path}: cannot be read ({error})") from None
        tree = _parse_opencv_yaml(text, path)
        name = str(tree.get("camera_name") or path.stem)
        matrices = {}
        for key, shape in _ROS_MATRICES.items():
            node = tree.get(key)
            if node is None and key == "rectification_matrix":  # (optional in ROS's files)
                matrices[key] = matrices["projection_matrix"] = None
                break
            try:
                matrices[key] = np.array([float(v) for v in node["data"]]).reshape(shape)
            except (TypeError, KeyError, ValueError):
                raise ValueError(
                    f"{path}: {key} is missing or malformed (a map of rows, cols and data, "
                    f"{'x'.join(map(str, shape)) if len(shape) == 2 else 'a row'}): is this a "
                    "ROS camera_info file?"
                ) from None
        names.append(name)
        lenses.append(_model_lens(path, name, str(tree.get("distortion_model", "plumb_bob"))))
        fields.append((matrices["camera_matrix"], matrices["distortion_coefficients"]))
        rectification.append((matrices["rectification_matrix"], matrices["projection_matrix"]))
    lens = _one_lens(paths[0], lenses, names)
    dists = _coefficients(paths[0], names, [d for _, d in fields], lens)
    K = np.stack([k for k, _ in fields])
    R, t = _ros_poses(paths, rectification)
    cameras = Camera.from_matrices(
        jnp.asarray(K), jnp.asarray(R), jnp.asarray(t), jnp.asarray(np.stack(dists)), lens=lens
    )
    return (cameras[0] if len(paths) == 1 else cameras), names


def _ros_poses(paths, rectification) -> tuple[np.ndarray, np.ndarray]:
    """Each camera's pose `(R, t)`: a rectified stereo pair's in the left camera's frame, NaN
    for anything else."""
    n = len(paths)
    R, t = np.full((n, 3, 3), np.nan), np.full((n, 3), np.nan)
    if n != 2 or any(r is None for r, _ in rectification):
        return R, t
    (R1, P1), (R2, P2) = rectification
    b = np.array([P2[0, 3] / P2[0, 0], P2[1, 3] / P2[1, 1], 0.0])  # P2 = K' [I | b]
    if not np.any(b) or np.any(P1[:, 3]) or not np.allclose(P1[:, :3], P2[:, :3]):
        return R, t  # not a rectified pair: P1 = [K' | 0], P2 = [K' | K' b] with b != 0
    _check_rotations(paths[0], np.stack([R1, R2]), ["left", "right"])
    R[0], t[0] = np.eye(3), 0.0
    R[1], t[1] = R2.T @ R1, R2.T @ b
    return R, t


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


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector (Rodrigues', OpenCV's `rvec`) of a rotation matrix, by its
    quaternion: accurate at every angle, 180 degrees too."""
    q = _quaternion(R)
    w, v = q[0], q[1:]
    s = np.linalg.norm(v)
    return 2.0 * v / w if s == 0.0 else 2.0 * math.atan2(s, w) * v / s


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
    `FULL_OPENCV` when k3 is not zero; a fisheye `OPENCV_FISHEYE`: fx fy cx cy k1 k2 k3 k4) and
    one image (`names`, default `cam_i.png`) with its
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
    _check_cameras(cameras, "save_colmap")
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rig = _one_axis(cameras)
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
        params = [rig.alpha_u[i], rig.alpha_v[i], rig.u0[i] + 0.5, rig.v0[i] + 0.5]
        if rig.lens == "fisheye":
            model, params = "OPENCV_FISHEYE", [*params, *rig.dist[i]]
        else:
            k1, k2, p1, p2, k3 = rig.dist[i]
            model, params = "OPENCV", [*params, k1, k2, p1, p2]
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


# COLMAP's camera models that mvcalib's lenses hold: the lens, and the parameters in COLMAP's
# order, named as mvcalib's (COLMAP's fisheye models are Kannala-Brandt's, cv2.fisheye's, with
# as many terms as they name; `SIMPLE_FISHEYE` and `FISHEYE` are equidistant, without).
_COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("pinhole", "f cx cy"),
    "PINHOLE": ("pinhole", "fx fy cx cy"),
    "SIMPLE_RADIAL": ("pinhole", "f cx cy k1"),
    "RADIAL": ("pinhole", "f cx cy k1 k2"),
    "OPENCV": ("pinhole", "fx fy cx cy k1 k2 p1 p2"),
    "FULL_OPENCV": ("pinhole", "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6"),
    "SIMPLE_FISHEYE": ("fisheye", "f cx cy"),
    "FISHEYE": ("fisheye", "fx fy cx cy"),
    "SIMPLE_RADIAL_FISHEYE": ("fisheye", "f cx cy k1"),
    "RADIAL_FISHEYE": ("fisheye", "f cx cy k1 k2"),
    "OPENCV_FISHEYE": ("fisheye", "fx fy cx cy k1 k2 k3 k4"),
}


@_reads_rig
def load_colmap(folder) -> tuple[Camera, list[str]]:
    """Read a COLMAP text model's cameras and images: one mvcalib camera per image, `(cameras,
    image names)`, in the order of `images.txt`. The camera models read are those a lens of
    mvcalib's holds: `SIMPLE_PINHOLE`, `PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`, `OPENCV`,
    `FULL_OPENCV` (k4-k6 zero) as pinholes; `SIMPLE_FISHEYE`, `FISHEYE`,
    `SIMPLE_RADIAL_FISHEYE`, `RADIAL_FISHEYE`, `OPENCV_FISHEYE` as fisheyes (a rig is one lens).
    A binary model (`cameras.bin`) is not read: COLMAP's `model_converter --output_type TXT`
    writes the text one."""
    folder = pathlib.Path(folder)
    try:
        cam_lines = _data_lines(folder / "cameras.txt")
        img_lines = _data_lines(folder / "images.txt")
    except OSError as error:
        binary = (folder / "cameras.bin").exists()
        hint = "; a binary model: `colmap model_converter --output_type TXT` writes the text one"
        raise ValueError(
            f"{folder}: not a COLMAP text model ({error}){hint if binary else ''}"
        ) from None
    intrinsics = {}
    for line in cam_lines:
        f = line.split()
        try:
            model, p = f[1], [float(v) for v in f[4:]]
            if model not in _COLMAP_MODELS:
                raise KeyError(model)
            lens, names = _COLMAP_MODELS[model]
            if len(f) < 4 or len(p) != len(names.split()):
                raise ValueError(f"{model} has {len(names.split())} parameters, not {len(p)}")
        except KeyError:
            raise ValueError(
                f"{folder}: camera model {model} is not supported (mvcalib reads "
                f"{', '.join(_COLMAP_MODELS)})."
            ) from None
        except (IndexError, ValueError) as error:
            raise ValueError(
                f"{folder / 'cameras.txt'}: malformed line {line!r} ({error})"
            ) from None
        value = dict(zip(names.split(), p))
        if any(value.pop(k, 0.0) for k in ("k4", "k5", "k6") if lens == "pinhole"):
            raise ValueError(f"{folder}: camera {f[0]} uses k4-k6, which mvcalib lacks.")
        fx, fy = value.get("fx", value.get("f")), value.get("fy", value.get("f"))
        dist = [value.get(k, 0.0) for k in LENSES[lens]]
        intrinsics[f[0]] = (fx, fy, value["cx"] - 0.5, value["cy"] - 0.5, dist, lens)
    fields, names, lenses = [], [], []
    for line in img_lines[::2]:  # every image has a second line of 2-D points
        f = line.split()
        if len(f) < 10 or f[8] not in intrinsics:
            raise ValueError(f"{folder}: malformed images.txt line: {line!r}")
        fx, fy, cx, cy, dist, lens = intrinsics[f[8]]
        lenses.append(lens)
        try:
            q, t = [float(v) for v in f[1:5]], [float(v) for v in f[5:8]]
        except ValueError as error:
            where = folder / "images.txt"
            raise ValueError(f"{where}: malformed line {line!r} ({error})") from None
        fields.append((fx, fy, cx, cy, _rotation(q), t, dist))
        names.append(f[9])
    if not fields:
        raise ValueError(f"{folder}: images.txt lists no images.")
    lens = _one_lens(folder / "cameras.txt", lenses, names)
    fx, fy, cx, cy, R, t, dist = (np.asarray(v, dtype=float) for v in zip(*fields))
    return Camera(fx, fy, cx, cy, R, t, dist=dist, lens=lens), names


def _data_lines(path: pathlib.Path) -> list[str]:
    lines = path.read_text(encoding=ENCODING).splitlines()
    if path.name == "images.txt":  # keep empty 2-D point lines: they pair with image lines
        return [ln for ln in lines if not ln.startswith("#")]
    return [ln for ln in lines if ln.strip() and not ln.startswith("#")]


# ---------------------------------------------------------------------------- Kalibr camchain
# Kalibr's lens models for mvcalib's: the projection, and the distortion with its coefficients
# in mvcalib's order (radtan: k1 k2 r1 r2 = OpenCV's k1 k2 p1 p2; equidistant: cv2.fisheye's).
_KALIBR_MODEL = {"pinhole": "radtan", "fisheye": "equidistant"}
_KALIBR_LENS = {"radtan": "pinhole", "equidistant": "fisheye", "none": "pinhole"}


def _kalibr_list(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def save_kalibr(
    path, cameras: Camera, image_size, *, topics=None, metres_per_unit: float = 1.0
) -> pathlib.Path:
    """Save a rig as Kalibr's camera chain (`camchain.yaml`), the file robotics tools read for a
    multi-camera rig (Kalibr, OpenVINS, VINS-Fusion, ORB-SLAM3's converters), atomically.

    Camera `i` is the map `cam{i}`: `camera_model: pinhole`, `intrinsics: [fu, fv, pu, pv]`,
    `distortion_model` (`radtan`: k1 k2 p1 p2 for a pinhole, whose k3 must be zero;
    `equidistant`: k1 k2 k3 k4 for a fisheye, as `cv2.fisheye`), `distortion_coeffs`,
    `resolution: [width, height]` (`image_size`), `rostopic` (`topics[i]`, default
    `/cam{i}/image_raw`), and from the second camera on `T_cn_cnm1`, the 4 x 4 transform from
    the previous camera's frame to this one's (`x_cn = T x_cnm1`). Pixels are OpenCV's (the
    first pixel's centre at 0, 0), as mvcalib's. Kalibr has no skew and no world frame: a camera
    with skew is refused, and the rig's pose in the world is not written (`load_kalibr` puts
    `cam0` at the origin). A camera with no calibration (NaN) is refused: the chain would break
    there; keep the calibrated ones (`cameras[ok]`). Numbers are Python's shortest exact
    representation: reading back gives the same doubles.

    Kalibr's translations are metres; a rig is in its target's units: give `metres_per_unit`
    (0.001 for a target in millimetres). A rig whose cameras stand more than 100 m apart once so
    scaled is written with a warning (a target in millimetres, unscaled, puts a 2 m rig 2 km
    wide).

    **Example:**

    ```python
    >>> import jax, tempfile, pathlib, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), 3).cameras  # (millimetres)
    >>> path = mc.io.save_kalibr(pathlib.Path(tempfile.mkdtemp()) / "camchain.yaml", rig,
    ...                          (1000, 1100), metres_per_unit=0.001)
    >>> print(path.read_text().splitlines()[1])
      camera_model: pinhole
    >>> back, names = mc.io.load_kalibr(path)  # (reading needs PyYAML)
    >>> names, bool(np.allclose(back.K, rig.K))
    (['cam0', 'cam1', 'cam2'], True)

    ```
    """
    _check_cameras(cameras, "save_kalibr")
    rig = _one_axis(cameras)
    n = rig.batch_shape[0]
    failed = [i for i in range(n) if not all(np.isfinite(x[i]).all() for x in _fields(rig))]
    if failed:
        raise ValueError(
            f"camera(s) {failed} have no calibration (NaN): Kalibr's chain of relative poses "
            "would break there; save the calibrated ones (`cameras[ok]`)."
        )
    if np.any(rig.skew != 0):
        raise ValueError("Kalibr's camera models have no skew; refine with skew=False first.")
    if rig.lens == "pinhole" and np.any(rig.dist[:, 4] != 0):
        k3 = ", ".join(f"{i}: {rig.dist[i, 4]:.3g}" for i in np.flatnonzero(rig.dist[:, 4]))
        raise ValueError(
            f"Kalibr's radtan distortion has k1 k2 p1 p2, not k3 (camera {k3}). Calibrate with "
            "distortion=('k1', 'k2', 'p1', 'p2') (refine's default) from a start without k3 (a "
            "starting rig's k3, e.g. caliscope's or OpenCV's, is kept where not estimated); or "
            "save as OpenCV's YAML or COLMAP's FULL_OPENCV, which hold k3."
        )
    rig = _in_metres(rig, metres_per_unit, "save_kalibr", "Kalibr's", 100.0)
    width, height = (int(v) for v in image_size)
    topics = [f"/cam{i}/image_raw" for i in range(n)] if topics is None else list(topics)
    if len(topics) != n:
        raise ValueError(f"{len(topics)} topics for {n} cameras.")
    lines = []
    for i in range(n):
        lines.append(f"cam{i}:")
        if i > 0:  # x_i = R_i R_{i-1}^T (x_{i-1} - t_{i-1}) + t_i
            R = rig.R[i] @ rig.R[i - 1].T
            T = np.block([[R, (rig.t[i] - R @ rig.t[i - 1])[:, None]], [np.eye(4)[3]]])
            lines += ["  T_cn_cnm1:"] + [f"  - {_kalibr_list(row)}" for row in T]
        intrinsics = [rig.alpha_u[i], rig.alpha_v[i], rig.u0[i], rig.v0[i]]
        coeffs = rig.dist[i] if rig.lens == "fisheye" else rig.dist[i, :4]
        lines += [
            "  camera_model: pinhole",
            f"  intrinsics: {_kalibr_list(intrinsics)}",
            f"  distortion_model: {_KALIBR_MODEL[rig.lens]}",
            f"  distortion_coeffs: {_kalibr_list(coeffs)}",
            f"  resolution: [{width}, {height}]",
            f"  rostopic: {topics[i]}",
        ]
    return write_atomic(path, "\n".join(lines) + "\n")


def _fields(camera: Camera):
    return (camera.alpha_u, camera.alpha_v, camera.u0, camera.v0, camera.R, camera.t, camera.dist)


@_reads_rig
def load_kalibr(path) -> tuple[Camera, list[str]]:
    """Read Kalibr's camera chain (`camchain.yaml`, or `camchain-imucam.yaml`, whose IMU terms
    are left out): `(cameras, names)`, the cameras `cam0, cam1, ...` in the frame of `cam0`,
    each placed by its `T_cn_cnm1`. Read: `camera_model: pinhole` with `distortion_model`
    `radtan` (a pinhole lens; k3 zero), `equidistant` (a fisheye) or `none` (a pinhole without
    distortion). Kalibr's other models (omni, ds, eucm; fov) have no mvcalib lens and are
    refused, as is a rig mixing pinhole and fisheye lenses. Needs PyYAML (`pip install
    pyyaml`): Kalibr's files are written by it, in its flow or block style."""
    try:
        import yaml
    except ImportError:
        raise ImportError("reading Kalibr's YAML needs PyYAML: `pip install pyyaml`.") from None
    path = pathlib.Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding=ENCODING))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        raise ValueError(f"{path}: cannot be read as YAML ({error})") from None
    names = sorted(
        (k for k in (data if isinstance(data, dict) else {}) if re.fullmatch(r"cam\d+", str(k))),
        key=lambda k: int(k[3:]),
    )
    if not names or names != [f"cam{i}" for i in range(len(names))]:
        raise ValueError(f"{path}: not a Kalibr camera chain (maps cam0, cam1, ...); got {names}.")
    fields, lenses = [], []
    R, t = np.eye(3), np.zeros(3)
    for i, name in enumerate(names):
        cam = data[name]
        where = f"{path}: {name}"
        try:
            projection, model = cam["camera_model"], cam.get("distortion_model", "none")
            fu, fv, pu, pv = (float(v) for v in cam["intrinsics"])
            coeffs = [float(v) for v in cam.get("distortion_coeffs", [])]
            T = np.asarray(cam["T_cn_cnm1"], dtype=float) if i > 0 else np.eye(4)
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"{where} is malformed ({type(error).__name__}: {error}).") from None
        if projection != "pinhole" or model not in _KALIBR_LENS:
            raise ValueError(
                f"{where}: camera_model {projection!r} with distortion_model {model!r}; mvcalib "
                "reads pinhole with radtan, equidistant or none."
            )
        lens = _KALIBR_LENS[model]
        expected = {"radtan": 4, "equidistant": 4, "none": 0}[model]
        if len(coeffs) != expected or T.shape != (4, 4):
            raise ValueError(
                f"{where}: {model} has {expected} distortion_coeffs and T_cn_cnm1 is 4 x 4; "
                f"got {len(coeffs)} and {T.shape}."
            )
        _check_rotations(path, T[None, :3, :3], [name])
        R, t = T[:3, :3] @ R, T[:3, :3] @ t + T[:3, 3]
        dist = coeffs if lens == "fisheye" else [*coeffs, 0.0] if coeffs else [0.0] * 5
        fields.append((fu, fv, pu, pv, R, t, dist))
        lenses.append(lens)
    lens = _one_lens(path, lenses, names)
    fu, fv, pu, pv, R, t, dist = (np.asarray(v, dtype=float) for v in zip(*fields))
    return Camera(fu, fv, pu, pv, R, t, dist=dist, lens=lens), names


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
        text = path.read_text(encoding=ENCODING)
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
    if any(s.startswith("#") for s in cameras):  # (a CSV line so written would be a comment)
        raise ValueError("camera names must not start with '#'.")
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
                         " (world_* columns optional, point optional with world_*)"
                         f"{_header_hint(lines[0][1], _COLUMNS)}.")  # fmt: skip
    if "point" not in header and not has_world:
        raise ValueError(f"{path}: a file without world_* columns needs a 'point' column.")
    column = {h: k for k, h in enumerate(header)}
    body = list(rows)
    plain = _plain_columns(column, body, has_world)
    if plain is not None:
        return plain
    cameras, points, world, seen, unlabelled = {}, {}, {}, {}, {}
    for (line, _), row in zip(lines[1:], body):
        where = f"{path}:{line}"
        if len(row) != len(header):
            raise ValueError(f"{where}: {len(row)} fields; the header has {len(header)}.")
        field = {h: row[k].strip() for h, k in column.items()}

        def numbers(names, where=where, field=field):
            return _parse_numbers(where, names, [field[h] for h in names])

        camera = field["camera"]
        xyz = numbers(_WORLD) if has_world else None
        # (blank or NaN pixels: the camera did not see the point)
        xy = None if _unseen([field[h] for h in _PIXEL]) else numbers(_PIXEL)
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
            continue  # a camera that did not see the point, or saw nothing
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


def _plain_columns(column, body, has_world) -> Correspondences | None:
    """`_from_csv`'s answer for a file of plain rows, column by column in NumPy: every row a
    camera, a point and its pixel (or NaN pixels: unseen), no camera seeing a point twice, the
    world coordinates a point's own in every row; None for anything else, which the reader then
    takes row by row (and names the line that is wrong). A million rows read in ~1 s, not ~10."""
    n = len(column)
    if "point" not in column or not body or any(len(row) != n for row in body):
        return None
    fields = [list(map(operator.itemgetter(k), body)) for k in range(n)]  # (zip(*body): 20x)
    names = [[v.strip() for v in fields[column[h]]] for h in ("camera", "point")]
    if not all(map(all, names)):  # (a blank camera or point: an unlabelled detection, or wrong)
        return None
    try:
        xy = np.array([fields[column[h]] for h in _PIXEL], dtype=float).T
        xyz = np.array([fields[column[h]] for h in _WORLD], dtype=float).T if has_world else None
    except ValueError:  # (a blank or a word)
        return None
    unseen = np.isnan(xy).all(-1)
    if not (np.isfinite(xy) | unseen[:, None]).all() or (has_world and not np.isfinite(xyz).all()):
        return None
    indices = []
    for row_names in names:
        order = {name: i for i, name in enumerate(dict.fromkeys(row_names))}
        indices.append((list(order), np.fromiter(map(order.get, row_names), int, len(row_names))))
    (cameras, c), (points, p) = indices
    seen = ~unseen
    pairs = np.sort(c[seen] * len(points) + p[seen])
    if (pairs[1:] == pairs[:-1]).any():  # a camera saw a point twice
        return None
    world = None
    if has_world:
        world = xyz[np.unique(p, return_index=True)[1]]  # (each point's first row)
        if not np.array_equal(xyz, world[p]):
            return None
    pixels = np.full((len(cameras), len(points), 2), np.nan)
    mask = np.zeros((len(cameras), len(points)), bool)
    pixels[c[seen], p[seen]] = xy[seen]
    mask[c[seen], p[seen]] = True
    return Correspondences(
        world=world,
        pixels=pixels,
        mask=mask,
        cameras=cameras,
        points=points,
        unlabelled=[np.zeros((0, 2)) for _ in cameras],
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


# ---------------------------------------------------------------------------- observations
_TARGET = ("target_x", "target_y", "target_z")
_OBSERVATION_COLUMNS = ("camera", "frame", "point", *_TARGET, *_PIXEL)


@dataclasses.dataclass(frozen=True)
class Observations:
    """A rig of cameras watching a target that moves over frames: what an observations file
    (`save_observations`, `load_observations`) and caliscope's `xy.csv` (`load_caliscope`) hold.

    **Fields:**

    - `target`: `(N, 3)` the target's points in its own frame (a planar board has `z = 0`).
    - `pixels`: `(C, F, N, 2)` where camera c saw point n in frame f, `(x = column, y = row)`
      with the origin at the centre of the top-left pixel; NaN where unseen.
    - `mask`: `(C, F, N)` bool: which camera saw which point in which frame.
    - `cameras`: the C camera names; `frames`: `(F,)` int frame ids, ascending; `points`: `(N,)`
      int ids of the target's points, ascending.

    The target's pose in each frame is unknown, and not part of it. `target`, `pixels[c]`,
    `mask[c]` are camera c's views of the target, what `mvcalib.calibrate_planar` takes.

    **Example:**

    ```python
    >>> import numpy as np, mvcalib as mc
    >>> board = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    >>> pixels = np.full((2, 1, 3, 2), np.nan)  # 2 cameras, 1 frame, 3 points
    >>> pixels[0, 0] = [[10.0, 20.0], [30.0, 20.0], [10.0, 40.0]]
    >>> pixels[1, 0, :2] = [[15.0, 25.0], [35.0, 25.0]]  # camera b missed point 2
    >>> o = mc.io.Observations(board, pixels, np.isfinite(pixels[..., 0]), ["a", "b"],
    ...                        frames=np.array([7]), points=np.array([0, 1, 2]))
    >>> int(o.mask.sum()), o.pixels.shape
    (5, (2, 1, 3, 2))

    ```
    """

    target: np.ndarray
    pixels: np.ndarray
    mask: np.ndarray
    cameras: list[str]
    frames: np.ndarray
    points: np.ndarray


def _ids(what: str, ids) -> np.ndarray:
    ids = np.asarray(ids)
    if ids.ndim != 1 or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
        raise ValueError(
            f"`{what}` must be a 1-D array of integer ids; got {ids.dtype} {ids.shape}."
        )
    ids = ids.astype(np.int64)
    if np.any(np.diff(ids) <= 0):
        raise ValueError(f"`{what}` must be strictly ascending (sorted, no repeats).")
    return ids


def _checked_observations(o: Observations) -> Observations:
    frames, points = _ids("frames", o.frames), _ids("points", o.points)
    F, N = len(frames), len(points)
    target = np.array(o.target, dtype=float)
    if target.shape != (N, 3) or not np.all(np.isfinite(target)):
        raise ValueError(
            f"`target` must be finite, of shape (N, 3) = ({N}, 3); got {target.shape}."
        )
    cameras = [str(s) for s in o.cameras]
    C = len(cameras)
    pixels = np.array(o.pixels, dtype=float)
    if pixels.shape != (C, F, N, 2):
        raise ValueError(f"`pixels` must be (C, F, N, 2) = ({C}, {F}, {N}, 2); got {pixels.shape}.")
    mask = np.asarray(o.mask)
    if mask.dtype != bool or mask.shape != (C, F, N):
        raise ValueError(
            f"`mask` must be bool of shape ({C}, {F}, {N}); got {mask.dtype} {mask.shape}."
        )
    if not np.all(np.isfinite(pixels[mask])):
        raise ValueError("`pixels` has NaN or inf entries where `mask` is True.")
    if not C or len(set(cameras)) != C or any(s != s.strip() or not s for s in cameras):
        raise ValueError(f"need one or more different camera names, not blank and not starting "
                         f"or ending with a space; got {cameras}.")  # fmt: skip
    if any("\n" in s or "\r" in s or s.startswith("#") for s in cameras):
        raise ValueError("camera names must not contain line breaks nor start with '#'.")
    pixels = np.where(mask[..., None], pixels, np.nan)
    return Observations(target, pixels, mask, cameras, frames, points)


def save_observations(path, observations: Observations) -> pathlib.Path:
    """Save a rig's observations of a moving target as a CSV file, atomically.

    **Arguments:**

    - `path`: the file to write (replaced whole, or not at all).
    - `observations`: an `Observations`.

    The CSV has the header `camera,frame,point,target_x,target_y,target_z,pixel_x,pixel_y` and
    one row per observation: the camera's name, the frame's id, the point's id, the point's
    coordinates on the target (the same in every row of that point) and the pixel. Rows with
    empty fields name what no observation would: `,,point,x,y,z,,` a point of the target that
    nobody saw, `,frame,,,,,,` a frame in which nobody saw anything (these come first), and
    `camera,,,,,,,` a camera that saw nothing (in its place among the cameras), so that
    reading back gives the same arrays, names and ids. Numbers are written with Python's
    shortest exact representation: reading back gives the same doubles.

    **Example:**

    ```python
    >>> import tempfile, pathlib, numpy as np, mvcalib as mc
    >>> board = np.array([[0.0, 0.0, 0.0], [0.054, 0.0, 0.0]])
    >>> pixels = np.array([[[[10.0, 20.0], [np.nan, np.nan]]], [[[11.5, 21.0], [40.0, 22.0]]]])
    >>> o = mc.io.Observations(board, pixels, np.isfinite(pixels[..., 0]), ["cam_0", "cam_1"],
    ...                        frames=np.array([416]), points=np.array([0, 1]))
    >>> path = mc.io.save_observations(pathlib.Path(tempfile.mkdtemp()) / "obs.csv", o)
    >>> print(path.read_text(), end="")
    camera,frame,point,target_x,target_y,target_z,pixel_x,pixel_y
    cam_0,416,0,0.0,0.0,0.0,10.0,20.0
    cam_1,416,0,0.0,0.0,0.0,11.5,21.0
    cam_1,416,1,0.054,0.0,0.0,40.0,22.0
    >>> back = mc.io.load_observations(path)
    >>> bool(np.array_equal(back.pixels, o.pixels, equal_nan=True)), back.cameras
    (True, ['cam_0', 'cam_1'])

    ```
    """
    import csv
    import io as _io

    o = _checked_observations(observations)
    buffer = _io.StringIO()
    out = csv.writer(buffer, lineterminator="\n")
    out.writerow(_OBSERVATION_COLUMNS)
    target = [[_number(v) for v in row] for row in o.target]
    for n in np.flatnonzero(~o.mask.any((0, 1))):  # points nobody saw
        out.writerow(["", "", int(o.points[n]), *target[n], "", ""])
    for f in np.flatnonzero(~o.mask.any((0, 2))):  # frames in which nobody saw anything
        out.writerow(["", int(o.frames[f]), "", "", "", "", "", ""])
    for c, camera in enumerate(o.cameras):
        frames, points = np.nonzero(o.mask[c])
        for f, n in zip(frames, points):
            xy = map(_number, o.pixels[c, f, n])
            out.writerow([camera, int(o.frames[f]), int(o.points[n]), *target[n], *xy])
        if not frames.size:
            out.writerow([camera, "", "", "", "", "", "", ""])  # a camera that saw nothing
    return write_atomic(path, buffer.getvalue())


def _csv_table(path, required, optional=(), *, strict=True):
    """`(column index by name, [(line number, fields)])` of a CSV file, blank lines and (with
    `strict`) `#` comments skipped; `ValueError` naming the file and line for a missing column,
    or (with `strict`) an unknown or repeated one, or a row with another number of fields."""
    import csv

    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding=ENCODING)
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: cannot be read ({error})") from None
    lines = [(n, ln) for n, ln in enumerate(text.splitlines(), 1) if ln.strip()]
    if strict:
        lines = [(n, ln) for n, ln in lines if not ln.startswith("#")]
    if not lines:
        raise ValueError(f"{path}: empty; expected the header {','.join(required)}.")
    rows = csv.reader([ln for _, ln in lines])
    header = [h.strip() for h in next(rows)]
    known = (*required, *optional)
    unknown = [h for h in header if h not in known] if strict else []
    missing = [h for h in required if h not in header]
    if unknown or missing or len(set(header)) != len(header):
        problem = f"unknown column {unknown[0]!r}" if unknown else (
            f"no {missing[0]!r} column" if missing else "a repeated column")  # fmt: skip
        raise ValueError(f"{path}:{lines[0][0]}: {problem}; the header is {','.join(required)}"
                         f"{_header_hint(lines[0][1], known)}.")  # fmt: skip
    table = []
    for (line, _), row in zip(lines[1:], rows):
        if len(row) != len(header):
            raise ValueError(f"{path}:{line}: {len(row)} fields; the header has {len(header)}.")
        table.append((line, [v.strip() for v in row]))
    return {h: k for k, h in enumerate(header)}, table


def _header_hint(line: str, columns) -> str:
    """What a header line that is not one looks like it is: another separator (a spreadsheet's
    export in a locale whose decimal mark is a comma writes `;`), or no header at all."""
    for separator, name in ((";", "semicolons"), ("\t", "tabs")):
        if separator in line and "," not in line:
            return (f": the fields are separated by {name}; mvcalib reads comma-separated values "
                    "with '.' as the decimal mark")  # fmt: skip
    fields = [field.strip().lower() for field in line.split(",")]
    if not any(field in columns for field in fields) and any(map(_is_number, fields)):
        return ": the file's first line must be that header"  # (it is data)
    return ""


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _unseen(values) -> bool:
    """Whether pixel fields say "not seen": all blank, or all NaN (as NumPy and pandas write it)."""
    return all(not v or v.lower() == "nan" for v in values)


def _parse_numbers(where, names, values, *, blank_ok=True):
    """The floats of `values` (named `names`), None if all are blank; `ValueError` if some are
    not numbers, or NaN or inf."""
    if blank_ok and not any(values):
        return None
    try:
        xs = tuple(float(v) for v in values)
    except ValueError:
        shown = ", ".join(repr(v) for v in values)
        raise ValueError(f"{where}: {', '.join(names)} = {shown} are not all numbers.") from None
    if not all(math.isfinite(x) for x in xs):
        raise ValueError(f"{where}: NaN or inf in {', '.join(names)}.")
    return xs


def _parse_id(where, name, value, *, lenient=False):
    """An integer id, None if blank; `lenient` also takes integral floats such as `416.0`."""
    if not value:
        return None
    try:
        number = int(value)
    except ValueError:
        try:
            x = float(value) if lenient else math.nan
        except ValueError:
            x = math.nan
        if not x.is_integer():
            raise ValueError(f"{where}: {name} {value!r} is not an integer.") from None
        number = int(x)
    if not -(2**63) <= number < 2**63:
        raise ValueError(f"{where}: {name} {value!r} is out of range (64-bit integers).")
    return number


def _observations(target, seen, cameras, frames, points) -> Observations:
    """Arrays from `target` {point: xyz} and `seen` {(camera, frame, point): (line, xy)}."""
    frames = np.array(sorted(frames), dtype=np.int64)
    points = np.array(sorted(points), dtype=np.int64)
    camera_index = {c: i for i, c in enumerate(cameras)}
    pixels = np.full((len(cameras), len(frames), len(points), 2), np.nan)
    if seen:
        keys = list(seen)
        c = np.array([camera_index[k[0]] for k in keys])
        f = np.searchsorted(frames, [k[1] for k in keys])
        n = np.searchsorted(points, [k[2] for k in keys])
        pixels[c, f, n] = [xy for _, xy in seen.values()]
    xyz = np.array([target[p] for p in points.tolist()], dtype=float).reshape(-1, 3)
    mask = ~np.isnan(pixels[..., 0])
    return Observations(xyz, pixels, mask, [str(s) for s in cameras], frames, points)


def load_observations(path) -> Observations:
    """Read a file written by `save_observations` (or by hand, in the same format).

    Columns may come in any order; blank lines and lines starting with `#` are skipped. Cameras
    come back in the order they first appear; frames and points sorted by id. Raises
    `ValueError` naming the file and line for anything malformed: a missing or unknown column,
    a number that is not one, an id that is not an integer, a point whose target coordinates
    differ from an earlier row's, a camera that saw the same point in the same frame twice,
    NaN or inf where a camera saw a point, a row that is neither an observation nor one of the
    rows that name a point, a frame or a camera alone.

    **Example:**

    ```python
    >>> import tempfile, pathlib, mvcalib as mc
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "obs.csv"
    >>> _ = path.write_text(
    ...     "camera,frame,point,target_x,target_y,target_z,pixel_x,pixel_y\\n"
    ...     ",,2,0.1,0.1,0,,\\n"  # point 2 of the target, seen by nobody
    ...     "left,5,0,0,0,0,100.5,200\\n"
    ...     "right,3,1,0.1,0,0,110,210.25\\n"
    ...     "idle,,,,,,,\\n")  # a camera that saw nothing
    >>> o = mc.io.load_observations(path)
    >>> o.cameras, o.frames.tolist(), o.points.tolist(), o.mask.shape, int(o.mask.sum())
    (['left', 'right', 'idle'], [3, 5], [0, 1, 2], (3, 2, 3), 2)

    ```
    """
    path = pathlib.Path(path)
    column, table = _csv_table(path, _OBSERVATION_COLUMNS)
    cameras, frames, target, seen = {}, set(), {}, {}
    for line, row in table:
        where = f"{path}:{line}"
        field = {h: row[k] for h, k in column.items()}
        camera = field["camera"]
        # (integral floats too: pandas writes an integer column with gaps as 109.0)
        frame = _parse_id(where, "frame", field["frame"], lenient=True)
        point = _parse_id(where, "point", field["point"], lenient=True)
        xyz = _parse_numbers(where, _TARGET, [field[h] for h in _TARGET])
        xy = _parse_numbers(where, _PIXEL, [field[h] for h in _PIXEL])
        if (point is None) != (xyz is None):
            raise ValueError(f"{where}: a point needs its target coordinates, and they a point.")
        if point is not None:
            first = target.setdefault(point, (line, xyz))
            if first[1] != xyz:
                raise ValueError(f"{where}: point {point} has other target coordinates than on "
                                 f"line {first[0]}.")  # fmt: skip
        if frame is not None:
            frames.add(frame)
        if not camera:
            if xy is not None or (frame is None and point is None):
                raise ValueError(f"{where}: a pixel (or an empty row) without a camera.")
            continue  # a point or a frame named without an observation
        cameras.setdefault(camera, len(cameras))
        if frame is None and point is None and xy is None:
            continue  # a camera that saw nothing
        if frame is None or point is None or xy is None:
            raise ValueError(f"{where}: camera {camera!r} without a frame, a point and a pixel.")
        first = seen.setdefault((camera, frame, point), (line, xy))
        if first[0] != line:
            raise ValueError(f"{where}: camera {camera!r} saw point {point} in frame {frame} on "
                             f"line {first[0]} too.")  # fmt: skip
    if not cameras:
        raise ValueError(f"{path}: no cameras.")
    target = {p: xyz for p, (_, xyz) in target.items()}
    return _observations(target, seen, list(cameras), frames, target)


# ---------------------------------------------------------------------------- caliscope
_CALISCOPE = ("sync_index", "cam_id", "keypoint_id", "img_loc_x", "img_loc_y", "obj_loc_x",
              "obj_loc_y")  # fmt: skip
# The names caliscope's recorder gives two of them (its `XYSchema`), read as the same columns.
_CALISCOPE_ALIASES = {"cam_id": "port", "keypoint_id": "point_id"}


def load_caliscope(xy_csv) -> Observations:
    """Read caliscope's `xy.csv`: a rig's detections of a ChArUco board over frames.

    Each row is one board corner (`keypoint_id`) seen by one camera (`cam_id`) in one
    synchronised frame (`sync_index`): its pixel (`img_loc_x`, `img_loc_y`) and its place on the
    board (`obj_loc_x`, `obj_loc_y`, and `obj_loc_z` if there is one; else the board is the
    plane z = 0). Other columns (`frame_index`, `frame_time`, `object_id`) are not used, but a
    file with more than one `object_id` is refused. `port` and `point_id`, the names caliscope's
    recorder writes, are read as `cam_id` and `keypoint_id`. The cameras are named `cam_<id>` in
    ascending id order, as `load_caliscope_cameras` names them; frames are the `sync_index`es
    and points the `keypoint_id`s. Raises `ValueError` naming the file and line for a missing
    column, a number or id that is not one, NaN or inf, a corner whose board coordinates are not
    exactly those of an earlier row, or a camera seeing a corner twice in one frame.

    **Example:**

    ```python
    >>> import tempfile, pathlib, mvcalib as mc
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "xy.csv"
    >>> _ = path.write_text(
    ...     "sync_index,cam_id,frame_index,frame_time,object_id,keypoint_id,"
    ...     "img_loc_x,img_loc_y,obj_loc_x,obj_loc_y\\n"
    ...     "416,1,413,48033.0,0,0,710.9,507.4,0.054,0.054\\n"
    ...     "416,0,410,48033.0,0,3,671.8,505.3,0.054,0.108\\n"
    ...     "417,1,414,48033.1,0,3,672.0,505.0,0.054,0.108\\n")
    >>> o = mc.io.load_caliscope(path)
    >>> o.cameras, o.frames.tolist(), o.points.tolist(), o.target.tolist()
    (['cam_0', 'cam_1'], [416, 417], [0, 3], [[0.054, 0.054, 0.0], [0.054, 0.108, 0.0]])
    >>> o.pixels[1, 0].tolist()  # camera 1 in frame 416
    [[710.9, 507.4], [nan, nan]]

    ```
    """
    path = pathlib.Path(xy_csv)
    try:
        header = {h.strip() for h in path.read_text(encoding=ENCODING).lstrip().split("\n")[0]
                  .split(",")}  # fmt: skip
    except (OSError, UnicodeDecodeError):
        header = set()  # (`_csv_table` says why)
    aliased = {ours: theirs for ours, theirs in _CALISCOPE_ALIASES.items()
               if ours not in header and theirs in header}  # fmt: skip
    column, table = _csv_table(path, tuple(aliased.get(h, h) for h in _CALISCOPE), strict=False)
    column.update({ours: column[theirs] for ours, theirs in aliased.items()})
    has_z, objects = "obj_loc_z" in column, {}
    target, seen, cameras, frames = {}, {}, set(), set()
    for line, row in table:
        where = f"{path}:{line}"

        def integer(name, where=where, row=row):
            value = _parse_id(where, name, row[column[name]], lenient=True)
            if value is None:
                raise ValueError(f"{where}: no {name}.")
            return value

        frame, camera, point = (integer(h) for h in ("sync_index", "cam_id", "keypoint_id"))
        if "object_id" in column:
            first = objects.setdefault(row[column["object_id"]], line)
            if len(objects) > 1:
                raise ValueError(f"{where}: another object_id than on line {first}; "
                                 "one board at a time.")  # fmt: skip
        names = ("obj_loc_x", "obj_loc_y", *(("obj_loc_z",) if has_z else ()))
        xyz = _parse_numbers(where, names, [row[column[h]] for h in names], blank_ok=False)
        xyz = xyz if has_z else (*xyz, 0.0)
        xy = _parse_numbers(where, _CALISCOPE[3:5], [row[column[h]] for h in _CALISCOPE[3:5]],
                            blank_ok=False)  # fmt: skip
        first = target.setdefault(point, (line, xyz))
        if first[1] != xyz:
            raise ValueError(f"{where}: keypoint {point} is at other board coordinates than on "
                             f"line {first[0]}.")  # fmt: skip
        first = seen.setdefault((camera, frame, point), (line, xy))
        if first[0] != line:
            raise ValueError(f"{where}: camera {camera} saw keypoint {point} in frame {frame} on "
                             f"line {first[0]} too.")  # fmt: skip
        cameras.add(camera)
        frames.add(frame)
    if not seen:
        raise ValueError(f"{path}: no observations.")
    order = sorted(cameras)
    seen = {(f"cam_{c}", f, n): v for (c, f, n), v in seen.items()}
    target = {p: xyz for p, (_, xyz) in target.items()}
    return _observations(target, seen, [f"cam_{c}" for c in order], frames, target)


@_reads_rig
def load_caliscope_cameras(camera_array_toml) -> tuple[Camera, list[str]]:
    """Load caliscope's `camera_array.toml`: `(cameras, names)`.

    Each `[cameras.<id>]` table holds `matrix` (K), `distortions` (OpenCV's k1 k2 p1 p2 k3),
    `rotation` (world to camera: a 3 x 3 matrix, or a Rodrigues vector as older caliscope
    wrote it) and `translation` (`x_cam = R X + t`). The cameras come back in ascending id
    order, named `cam_<id>` as `load_caliscope` names them; every table is loaded, including
    those caliscope marks `ignore`. A camera not yet calibrated (no `matrix`, `rotation` or
    `translation`) has NaN for what it lacks. Cameras with `fisheye = true` (`cv2.fisheye`'s
    k1 k2 k3 k4) come back as `lens="fisheye"`; a file mixing both lenses is refused. Needs
    Python >= 3.11 (`tomllib`).

    **Example:**

    ```python
    >>> import tempfile, pathlib, numpy as np, mvcalib as mc
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "camera_array.toml"
    >>> _ = path.write_text(
    ...     "[cameras.0]\\nmatrix = [[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]]\\n"
    ...     "distortions = [-0.3, 0.1, 0.0, 0.0, 0.0]\\n"
    ...     "rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\\n"
    ...     "translation = [0.0, 0.0, 1.5]\\n")
    >>> cameras, names = mc.io.load_caliscope_cameras(path)
    >>> names, cameras.project(np.zeros((1, 3))).tolist()
    (['cam_0'], [[[640.0, 360.0]]])

    ```
    """
    from ._rotation import rodrigues

    path = pathlib.Path(camera_array_toml)
    document = _read_toml(path)
    tables = document.get("cameras")
    keys = [k for k in tables if re.fullmatch(r"\d+", k)] if isinstance(tables, dict) else []
    if not keys:
        raise ValueError(f"{path}: no [cameras.<id>] tables.")
    keys.sort(key=int)

    def given(value):  # caliscope writes a missing value as absent, or as "null"
        return value is not None and not (isinstance(value, str) and value == "null")

    lenses = [
        "fisheye" if isinstance(tables[k], dict) and tables[k].get("fisheye") is True else "pinhole"
        for k in keys
    ]
    lens = _one_lens(path, lenses, [f"cam_{k}" for k in keys])
    n_dist = len(LENSES[lens])
    fields = []
    for key in keys:
        table = tables[key]
        try:
            K = table.get("matrix")
            K = np.array(K, dtype=float) if given(K) else np.full((3, 3), np.nan)
            dist = table.get("distortions")
            dist = np.array(dist, dtype=float) if given(dist) else np.zeros(n_dist)
            R = table.get("rotation")
            R = np.array(R, dtype=float) if given(R) else np.full((3, 3), np.nan)
            if R.shape == (3,):
                R = np.asarray(rodrigues(jnp.asarray(R)))
            t = table.get("translation")
            t = np.array(t, dtype=float) if given(t) else np.full(3, np.nan)
            if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
                raise ValueError(f"matrix {K.shape}, rotation {R.shape}, translation {t.shape}")
            if dist.ndim != 1 or len(dist) > n_dist:
                raise ValueError(
                    f"{dist.size} distortions; a {lens} lens has {' '.join(LENSES[lens])}"
                )
        except (AttributeError, TypeError, ValueError) as error:
            raise ValueError(f"{path}: [cameras.{key}] is malformed ({error}).") from None
        fields.append((K, R, t, np.pad(dist, (0, n_dist - len(dist)))))
    K, R, t, dist = (np.stack(f) for f in zip(*fields))
    return Camera.from_matrices(K, R, t, dist, lens=lens), [f"cam_{k}" for k in keys]


def load_clicks(path, images, target) -> list:
    """Clicked seeds from a CSV file with the header `image,dot_id,pixel_x,pixel_y` (other
    columns ignored): `image` names one of `images` (its path as given, its file name, or its
    position from 0), `dot_id` a dot of `target` (`target.ids`). Returns one seed per image for
    `mvcalib.calibrate_images` / `mvcalib.match_dots`: `(pixels (k, 2), dot_ids (k,))`, or None
    for an image without clicks. Rows naming other photos are passed over (one file of clicks
    serves any of its photos), unless no row names one of `images`. `ValueError` naming the file
    and line for an unknown dot, a position beyond `images`, or a field that is not a number.

    `path` may also be OpenPTV's `man_ori.par`, with its `man_ori.dat` beside it
    (`load_openptv_clicks`): four clicks per camera, the cameras in the order of `images`.

    **Example:**

    ```python
    >>> import pathlib, tempfile, mvcalib as mc
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "clicks.csv"
    >>> _ = path.write_text("image,dot_id,pixel_x,pixel_y\\nb.png,3,10.5,20\\n")
    >>> seeds = mc.io.load_clicks(path, ["a.png", "b.png"], mc.targets.box_corner())
    >>> seeds[0], seeds[1][0].tolist(), seeds[1][1].tolist()
    (None, [[10.5, 20.0]], [3])

    ```
    """
    if pathlib.Path(path).suffix == ".par":
        return _openptv_seeds(pathlib.Path(path), images, target)
    columns, table = _csv_table(path, ("image", "dot_id", "pixel_x", "pixel_y"), strict=False)
    images = [str(p) for p in images]
    names = [pathlib.Path(p).name for p in images]
    clicked: dict[int, list] = {}
    others = []  # (line, name) of rows naming photos not given
    for line, fields in table:
        where = f"{path}, line {line}"
        image = fields[columns["image"]]
        if image in images or image in names:
            i = images.index(image) if image in images else names.index(image)
        elif image.isdigit():
            if int(image) >= len(images):
                raise ValueError(f"{where}: no image {image!r} among the images given")
            i = int(image)
        else:
            others.append((line, image))
            continue
        dot = _parse_id(where, "dot_id", fields[columns["dot_id"]])
        xy = _parse_numbers(
            where, ("pixel_x", "pixel_y"),
            (fields[columns["pixel_x"]], fields[columns["pixel_y"]]), blank_ok=False,
        )  # fmt: skip
        if dot is None or dot not in target.ids:
            raise ValueError(f"{where}: the target has no dot {dot}")
        clicked.setdefault(i, []).append((xy, dot))
    if others and not clicked:
        line, image = others[0]
        raise ValueError(f"{path}, line {line}: no image {image!r} among the images given")
    seeds = [None] * len(images)
    for i, rows in clicked.items():
        seeds[i] = (np.array([xy for xy, _ in rows]), np.array([dot for _, dot in rows]))
    return seeds


def _openptv_seeds(par: pathlib.Path, images, target) -> list:
    """`load_clicks` of OpenPTV's `man_ori.par` and the `man_ori.dat` beside it."""
    dat = par.with_suffix(".dat")
    if not dat.is_file():
        raise ValueError(f"{par}: OpenPTV's clicked pixels, {dat.name}, are not beside it.")
    ids, pixels = load_openptv_clicks(par, dat)
    if len(ids) != len(images):
        raise ValueError(
            f"{par}: clicks for {len(ids)} cameras, and {len(images)} images given; give every "
            "camera's image, in OpenPTV's order."
        )
    unknown = ~np.isin(ids, target.ids)
    if unknown.any():
        c, k = np.argwhere(unknown)[0]
        raise ValueError(f"{par}, line {4 * c + k + 1}: the target has no dot {ids[c, k]}")
    return list(zip(pixels, ids))


def load_openptv_clicks(man_ori_par, man_ori_dat) -> tuple[np.ndarray, np.ndarray]:
    """OpenPTV's clicked seeds: `man_ori.par` (the target ids of the dots clicked, one per
    line, four per camera: OpenPTV's manual orientation) and `man_ori.dat` (their pixels `x y`, one
    per line, cameras in order), as `(dot_ids (C, k), pixels (C, k, 2))` for
    `mvcalib.match_dots`. The pixels are moved to mvcalib's convention (origin at the centre of
    the top-left pixel; OpenPTV's is its corner: -0.5 px in x and y).

    **Example:**

    ```python
    >>> import pathlib, tempfile, mvcalib as mc
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "man_ori.par").write_text("2\\n3\\n71\\n73\\n")
    >>> _ = (d / "man_ori.dat").write_text("1009 608\\n979 335\\n246 620\\n235 344\\n")
    >>> ids, pixels = mc.io.load_openptv_clicks(d / "man_ori.par", d / "man_ori.dat")
    >>> ids.tolist(), pixels[0, 0].tolist()
    ([[2, 3, 71, 73]], [1008.5, 607.5])

    ```
    """
    par, dat = pathlib.Path(man_ori_par), pathlib.Path(man_ori_dat)
    try:
        ids = np.loadtxt(par, ndmin=1)
        pixels = np.loadtxt(dat, ndmin=2)
    except ValueError as error:
        raise ValueError(f"cannot read OpenPTV clicks {par} / {dat}: {error}") from None
    if ids.ndim != 1 or len(ids) == 0 or not np.all(ids == np.round(ids)):
        raise ValueError(f"{par}: expected one integer dot id per line.")
    if pixels.shape != (len(ids), 2) or not np.all(np.isfinite(pixels)):
        raise ValueError(
            f"{dat}: expected {len(ids)} lines of `x y` (one per id in {par.name}); got "
            f"{pixels.shape[0]} lines of {pixels.shape[1] if pixels.ndim == 2 else '?'} numbers."
        )
    per_camera = 4  # OpenPTV's manual orientation: four points per camera
    if len(ids) % per_camera:
        raise ValueError(f"{par}: {len(ids)} ids is not {per_camera} per camera.")
    C = len(ids) // per_camera
    return ids.astype(int).reshape(C, per_camera), pixels.reshape(C, per_camera, 2) - 0.5


# --------------------------------------------------------------------------------- OpenPTV
_OPENPTV_ADDPAR_DEFAULT = (0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)  # OpenPTV's, when there is no file


def _openptv_numbers(path: pathlib.Path, what: str, count: int) -> np.ndarray:
    """The whitespace-separated numbers of an OpenPTV text file, exactly `count` of them."""
    try:
        tokens = path.read_text(encoding=ENCODING).split()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"cannot read OpenPTV {what} {path}: {error}") from None
    try:
        numbers = np.array([float(token) for token in tokens])
    except ValueError as error:
        raise ValueError(f"{path}: not an OpenPTV {what} ({error}).") from None
    if len(numbers) != count or not np.all(np.isfinite(numbers)):
        raise ValueError(
            f"{path}: an OpenPTV {what} holds {count} finite numbers; got {len(numbers)}"
            + ("." if len(numbers) != count else " with NaN or inf.")
        )
    return numbers


def _openptv_ptv_par(path: pathlib.Path) -> tuple[tuple[int, int], tuple[float, float]]:
    """`(image_size, pixel_size)` from OpenPTV's `ptv.par`, read as OpenPTV reads it: the
    number of cameras, an image name and a calibration image name per camera, then hp_flag,
    allCam_flag, tiff_flag, imx, imy, pix_x, pix_y, chfield, n1, n2, n3, d."""
    try:
        tokens = path.read_text(encoding=ENCODING).split()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"cannot read OpenPTV parameters {path}: {error}") from None
    try:
        n = int(tokens[0])
        if n < 1:
            raise ValueError(f"{n} cameras")
        names, numbers = tokens[1 : 1 + 2 * n], [float(v) for v in tokens[1 + 2 * n :]]
    except (IndexError, ValueError) as error:
        raise ValueError(f"{path}: not an OpenPTV ptv.par ({error}).") from None
    if len(names) != 2 * n or len(numbers) != 12 or not np.all(np.isfinite(numbers)):
        raise ValueError(
            f"{path}: an OpenPTV ptv.par holds the number of cameras, two file names per camera "
            f"and 12 numbers (hp_flag allCam_flag tiff_flag imx imy pix_x pix_y chfield n1 n2 n3 "
            f"d); got {len(tokens)} entries for {n} cameras."
        )
    imx, imy, pix_x, pix_y, chfield = numbers[3:8]
    if imx != round(imx) or imy != round(imy):
        raise ValueError(f"{path}: the image size {imx} x {imy} is not whole pixels.")
    if chfield != 0:
        raise ValueError(
            f"{path}: chfield = {chfield:g} (interlaced fields); only full frames (0) are read."
        )
    return (int(imx), int(imy)), (pix_x, pix_y)


def _openptv_rotation(omega: float, phi: float, kappa: float) -> np.ndarray:
    """OpenPTV's `rotation_matrix`: the matrix `dm` whose columns are the camera's axes in the
    world frame (a camera point is `dm^T (X - X0)`)."""
    co, so, cp, sp, ck, sk = (f(a) for a in (omega, phi, kappa) for f in (np.cos, np.sin))
    return np.array(
        [
            [cp * ck, -cp * sk, sp],
            [co * sk + so * sp * ck, co * ck - so * sp * sk, -so * cp],
            [so * sk - co * sp * ck, so * ck + co * sp * sk, co * cp],
        ]
    )


@_reads_rig
def load_openptv_calibration(
    ori, addpar=None, *, ptv_par=None, pixel_size=None, image_size=None, scx_scales=None
) -> Camera:
    """One camera of an OpenPTV calibration (`camN.tif.ori` and `camN.tif.addpar`) as an
    mvcalib `Camera`, in mvcalib's conventions: pixels with the origin at the centre of the
    top-left pixel and y down (OpenPTV's pixel origin is the pixel's corner: mvcalib's pixel =
    OpenPTV's - 0.5 px), and `x_cam = R X + t` with `X` in the target's units (mm).

    The `.ori` file holds 21 numbers: the projection centre `X0 Y0 Z0`, the angles `omega phi
    kappa` (radians), the 3 x 3 rotation matrix, the principal point `xh yh` and principal
    distance `c` (mm on the sensor, y up) and the glass vector. The rotation is computed from
    the angles, as OpenPTV does when it reads the file; a matrix that disagrees with them (by
    more than 1e-6) is refused. The `.addpar` file holds 7: `k1 k2 k3 p1 p2 scx she` (Brown's
    radial and decentering terms in mm, scale and shear). Without `addpar`, the `.addpar` next
    to `ori` (`camN.tif.ori` -> `camN.tif.addpar`) is read if there is one; if there is none,
    the terms are OpenPTV's defaults (no distortion, `scx = 1`, `she = 0`).

    The sensor's pixel size (mm) and image size `(width, height)` in pixels come from OpenPTV's
    `ptv.par` (`ptv_par`), or from `pixel_size` (one number, or `(x, y)`) and `image_size`:
    give one or the other. Interlaced fields (`chfield` other than 0) are refused.

    The principal distance over the pixel size gives the focal lengths, and the shear `she` a
    skew. OpenPTV's versions disagree on what `scx` scales: its older C library and
    openptv-python scale x only (`x' = scx x - sin(she) y`, `y' = cos(she) y`), optv 0.3
    scales both (`x' = scx (x - sin(she) y)`, `y' = scx cos(she) y`). A file with `scx` other
    than 1 is refused unless `scx_scales` says which wrote it: `"x"` or `"xy"`.

    OpenPTV's distortion terms become OpenCV's, in normalised coordinates: `k1 c^2, k2 c^4,
    k3 c^6`, `p1 = -c p2'`, `p2 = c p1'` (OpenPTV's `p1' p2'`; y points up in OpenPTV's image
    coordinates). That is exact when the principal point is at the sensor's centre (`xh = yh =
    0`; OpenPTV's older C code differs from optv 0.3, and from this, by a term of second order
    in the distortion: its y uses the distorted x in `2 p1' x y`). Otherwise OpenPTV distorts
    about the sensor's centre, not the principal point, which Brown-Conrady about the principal
    point cannot express: non-zero distortion terms are then refused.

    Refraction is not part of it: OpenPTV models cameras looking through a flat glass wall into
    water (`ptv.par`'s refractive indices `n1 n2 n3` and glass thickness, and the `.ori`'s
    glass vector), and a pinhole `Camera` has no such model. This camera is OpenPTV's with all
    refractive indices 1; when the media differ, it does not project where OpenPTV does (in
    OpenPTV's cavity set-up, air / glass / water, by 65-113 px RMS).

    **Example:**

    ```python
    >>> import pathlib, tempfile, numpy as np, mvcalib as mc
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "cam1.tif.ori").write_text(
    ...     "0 0 500\\n0 0 0\\n1 0 0\\n0 1 0\\n0 0 1\\n0 0\\n60\\n0 0 125\\n")
    >>> _ = (d / "cam1.tif.addpar").write_text("0 0 0 0 0 1 0")
    >>> camera = mc.io.load_openptv_calibration(
    ...     d / "cam1.tif.ori", pixel_size=0.01, image_size=(1280, 1024))
    >>> [round(float(v), 6) for v in (camera.alpha_u, camera.alpha_v, camera.u0, camera.v0)]
    [6000.0, 6000.0, 639.5, 511.5]
    >>> np.round(camera.project(np.array([[10.0, 5.0, 0.0]])), 6).tolist()
    [[759.5, 451.5]]

    ```
    """
    ori = pathlib.Path(ori)
    if scx_scales not in (None, "x", "xy"):
        raise ValueError(f'`scx_scales` is None, "x" or "xy"; got {scx_scales!r}.')
    if addpar is None:
        sibling = ori.with_suffix(".addpar")
        addpar = sibling if ori.suffix == ".ori" and sibling.is_file() else None
    if ptv_par is not None:
        if pixel_size is not None or image_size is not None:
            raise ValueError("give `ptv_par`, or `pixel_size` and `image_size`; not both.")
        image_size, pixel_size = _openptv_ptv_par(pathlib.Path(ptv_par))
    elif pixel_size is None or image_size is None:
        raise ValueError(
            "the pixel size and image size are needed: give `ptv_par` (OpenPTV's ptv.par), or "
            "`pixel_size` (mm) and `image_size` ((width, height) in pixels)."
        )
    try:
        pix = np.broadcast_to(np.asarray(pixel_size, dtype=float), (2,))
    except (TypeError, ValueError):
        pix = np.full(2, np.nan)
    if not np.all(np.isfinite(pix) & (pix > 0)):
        raise ValueError(f"`pixel_size` is positive, in mm (one, or x and y); got {pixel_size!r}.")
    try:
        size = np.asarray(image_size, dtype=float)
    except (TypeError, ValueError):
        size = np.full(1, np.nan)
    if size.shape != (2,) or not np.all(np.isfinite(size) & (size > 0)):
        raise ValueError(f"`image_size` is (width, height) in pixels; got {image_size!r}.")

    numbers = _openptv_numbers(ori, "orientation (.ori)", 21)
    centre, angles, dm = numbers[0:3], numbers[3:6], numbers[6:15].reshape(3, 3)
    xh, yh, c = numbers[15:18]  # numbers[18:21]: the glass vector (refraction)
    if addpar is None:
        k1, k2, k3, p1, p2, scx, she = _OPENPTV_ADDPAR_DEFAULT
    else:
        addpar = pathlib.Path(addpar)
        k1, k2, k3, p1, p2, scx, she = _openptv_numbers(addpar, "distortion (.addpar)", 7)
    rotation = _openptv_rotation(*angles)
    if np.abs(rotation - dm).max() > 1e-6:
        raise ValueError(
            f"{ori}: the rotation matrix disagrees with the angles omega phi kappa = "
            f"{angles.tolist()} by {np.abs(rotation - dm).max():.2g}; is the file consistent?"
        )
    if not c > 0:
        raise ValueError(f"{ori}: the principal distance c = {c:g} mm is not positive.")
    if not (scx > 0 and abs(she) < np.pi / 2):
        raise ValueError(f"{addpar}: scx = {scx:g} and she = {she:g} do not map an image.")
    if scx != 1.0 and scx_scales is None:
        raise ValueError(
            f"{addpar}: scx = {scx:.8g}, and OpenPTV's versions disagree on what it scales "
            '(its older C library: x only; optv 0.3: x and y). Say which: scx_scales="x" '
            'or "xy".'
        )
    if (k1, k2, k3, p1, p2) != (0.0, 0.0, 0.0, 0.0, 0.0) and (xh, yh) != (0.0, 0.0):
        raise ValueError(
            f"{addpar}: OpenPTV's distortion (k1 k2 k3 p1 p2 = {k1:g} {k2:g} {k3:g} {p1:g} "
            f"{p2:g}) is about the sensor's centre, and the principal point of {ori} is off it "
            f"(xh, yh = {xh:g}, {yh:g} mm): mvcalib's Brown-Conrady distortion, about the "
            "principal point, cannot express it."
        )
    # OpenPTV: camera point p = dm^T (X - X0), looking down -z; image point (x, y) = -c (p_x,
    # p_y) / p_z + (xh, yh), y up. mvcalib: z forward, y down: flip y and z.
    R = np.diag([1.0, -1.0, -1.0]) @ rotation.T
    t = -R @ centre
    # The affine map after the distortion, x' = a x + b y, y' = d y, then OpenPTV's pixel
    # (origin at the corner) = (x' / pix_x + imx / 2, imy / 2 - y' / pix_y).
    scale = scx if scx_scales == "xy" else 1.0
    a, b, d = scx, -scale * np.sin(she), scale * np.cos(she)
    return Camera(
        alpha_u=a * c / pix[0],
        alpha_v=d * c / pix[1],
        u0=(a * xh + b * yh) / pix[0] + size[0] / 2 - 0.5,
        v0=size[1] / 2 - d * yh / pix[1] - 0.5,
        R=R,
        t=t,
        skew=-b * c / pix[0],
        dist=np.array([k1 * c**2, k2 * c**4, -p2 * c, p1 * c, k3 * c**6]),
    )
