"""Saving and loading rigs: versioned JSON, written atomically.

A rig file holds one entry per camera (name, intrinsics, `R`, `t`, distortion in OpenCV's order,
and optionally its calibration status and reprojection RMS). Cameras that failed have `null`
parameters, loaded back as NaN. Files are written to a temporary file beside the target and
renamed over it, so an interrupted write never leaves a half-written rig.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import tempfile

import jax.numpy as jnp
import numpy as np

from ._camera import Camera

__all__ = ["save_json", "load_json", "write_atomic", "load_aniposelib"]

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
    single = cameras.batch_shape == ()
    rig = cameras if not single else Camera(
        *(jnp.asarray(getattr(cameras, k))[None] for k in ("alpha_u", "alpha_v", "u0", "v0")),
        R=cameras.R[None], t=cameras.t[None], skew=cameras.skew[None], dist=cameras.dist[None],
    )  # fmt: skip
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
    keys = sorted((k for k in document if k.startswith("cam_")), key=lambda k: int(k[4:]))
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
