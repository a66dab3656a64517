"""Validation at the Python boundary.

Shapes and dtypes are checked statically, so every check also works on tracers (inside a user's
`jax.jit` or `jax.grad`); values (NaN/inf, visible-point counts) are checked only on concrete
arrays. Kernels below this layer assume valid input and report per-camera problems as statuses.
"""

from __future__ import annotations

import os
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np

MIN_POINTS = 6  # a 3x4 projection matrix has 11 degrees of freedom; each point gives 2 equations


try:  # (JAX's own test of being inside a trace; without it, tracers alone tell)
    from jax._src.core import trace_state_clean as _outside_traces
except ImportError:  # pragma: no cover

    def _outside_traces() -> bool:
        return True


def is_concrete(*arrays) -> bool:
    """Whether `arrays` hold values here: none is a tracer and no trace is under way. Arrays that
    a user's jitted function closes over are concrete, but what is computed from them there is
    traced: `jax.jit(lambda x: mc.calibrate(W, P, M).cameras.alpha_u * x)` with W, P, M JAX
    arrays took the eager path and failed on a traced result."""
    return _outside_traces() and not any(isinstance(a, jax.core.Tracer) for a in arrays)


def static_options(function: str, **options) -> None:
    """Refuse options (`skew=`, `rcond=`, ...) that arrive traced, from the arguments of a
    `jax.jit`-ed call of `mc.<function>`, saying how to keep them static; they reached the code
    as tracers and failed there in JAX's words ("Non-hashable static arguments",
    ConcretizationTypeError)."""
    for name, value in options.items():
        if isinstance(value, jax.core.Tracer):
            owner, _, method = function.rpartition(".")  # ("Camera", "rays") for a method
            if owner:
                this = owner.lower()
                how = f"a Python value in your function, jax.jit(lambda {this}, pixels: {this}."
                how += f"{method}(pixels, {name}=...))"
            else:
                how = f"jax.jit(functools.partial(mc.{function}, {name}=...)) or jax.jit("
                how += f"mc.{function}, static_argnames='{name}')"
            raise TypeError(
                f"`{name}` of mc.{function} is an option, not data, and it is traced here (an "
                f"argument of a jax.jit-ed call): make it static, {how}."
            )


def derived(fn, *arrays):
    """`fn(xp, *arrays)` for a small quantity derived from a result's arrays: in NumPy, put on
    the device, when they are concrete and on one device (each eager `jnp` operation compiles a
    program of its own for every new shape, 10-30 ms each); in `jnp` inside a trace or for
    arrays split over devices."""
    one = lambda a: not isinstance(a, jax.Array) or len(a.sharding.device_set) == 1  # noqa: E731
    if is_concrete(*arrays) and all(one(a) for a in arrays):
        return jax.device_put(fn(np, *(np.asarray(a) for a in arrays)))
    return fn(jnp, *arrays)


def result_dtype(*dtypes) -> np.dtype:
    """The floating dtype arrays of `dtypes` are computed in: their NumPy promotion, as JAX holds
    it (float32 unless the user enabled x64). `jnp.result_type` gives the same, but warns about
    each float64 (e.g. a NumPy array's) that x64 is off."""
    return jax.dtypes.canonicalize_dtype(np.result_type(*dtypes))


def floating(name: str, x, last_dims: tuple[int, ...] | None = None, *, xp=jnp):
    """`x` as a floating JAX array (a NumPy array with `xp=np`); integers are promoted, everything
    else is refused."""
    if isinstance(x, (list, tuple)):
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(x)):
            # (jax.jit made every number of a Python list an argument of its own)
            raise TypeError(
                f"`{name}` is a Python list of traced numbers: pass an array (`jnp.asarray` of "
                "the list outside the transformed function) to `jax.jit`, `grad` or `vmap`."
            )
        try:
            x = np.asarray(x)
        except ValueError:  # ragged nested lists
            lengths = sorted({len(v) for v in x if hasattr(v, "__len__")})
            raise ValueError(
                f"`{name}` must be a rectangular array of numbers; got a list of arrays of "
                f"lengths {lengths[:6]}{'...' if len(lengths) > 6 else ''}. Detections of some "
                "of the points (OpenCV's per-view lists)? Give every view all of the target's "
                "points in its order, NaN where one was not found, and `mask` False there."
            ) from None
    if not hasattr(x, "dtype"):
        x = np.asarray(x)
    dtype = np.dtype(x.dtype)
    coarse = dtype.kind == "f" and dtype.itemsize < 4 or dtype.name == "bfloat16"
    if dtype.kind in "iu":
        x = xp.asarray(x, dtype=jnp.result_type(float))
    elif coarse:
        raise ValueError(
            f"`{name}` has dtype {dtype}, which is too coarse for calibration "
            "(pixel coordinates above 2048 cannot even be represented exactly); "
            "use float32 or float64."
        )
    elif dtype.kind != "f":
        raise ValueError(
            f"`{name}` must hold real floating-point numbers; got dtype {dtype}. "
            "Convert it with `.astype(float)` (complex, boolean and object arrays are refused)."
        )
    x = xp.asarray(x)
    if last_dims is not None:
        k = len(last_dims)
        if x.ndim < k or tuple(x.shape[x.ndim - k :]) != tuple(
            d if d is not None else x.shape[x.ndim - k + i] for i, d in enumerate(last_dims)
        ):
            free = iter("CN" if last_dims.count(None) == 2 else "N" * len(last_dims))
            want = ", ".join(next(free) if d is None else str(d) for d in last_dims)
            raise ValueError(f"`{name}` must have shape (..., {want}); got {tuple(x.shape)}.")
    return x


def boolean_mask(name: str, mask, shape: tuple[int, ...], *, xp=jnp):
    """A boolean visibility mask that broadcasts to `shape` (a NumPy array with `xp=np`)."""
    if mask is None:
        return xp.ones(shape, dtype=bool)
    if not hasattr(mask, "dtype"):  # lists, tuples, Python bools
        mask = np.asarray(mask)
    dtype = np.dtype(mask.dtype)
    if dtype != np.bool_:
        raise ValueError(
            f"`{name}` must be a boolean array (True = visible); got dtype {dtype}. "
            "Use `mask.astype(bool)` if it holds 0/1."
        )
    mask = xp.asarray(mask)
    try:
        np.broadcast_shapes(tuple(mask.shape), shape)
    except ValueError:
        raise ValueError(
            f"`{name}` of shape {tuple(mask.shape)} does not broadcast to the points' "
            f"shape {shape}."
        ) from None
    return xp.broadcast_to(mask, np.broadcast_shapes(tuple(mask.shape), shape))


def correspondences(world, pixels, mask, *, min_points: int = MIN_POINTS, xp=jnp):
    """Check a (world, pixels, mask) triple; return them as arrays of one floating dtype.

    `world` is `(..., N, 3)` and `pixels` `(..., N, 2)`; their leading axes broadcast (one target
    seen by a whole rig is `world` of shape `(N, 3)` with `pixels` of shape `(C, N, 2)`). With
    `xp=np`, concrete arrays are checked and returned as NumPy arrays, compiling nothing.
    """
    world = floating("world", world, (None, 3), xp=xp)
    pixels = floating("pixels", pixels, (None, 2), xp=xp)
    if world.shape[-2] != pixels.shape[-2]:
        raise ValueError(
            f"`world` has {world.shape[-2]} points but `pixels` has {pixels.shape[-2]} "
            f"(shapes {tuple(world.shape)} and {tuple(pixels.shape)}); "
            "row i of both must be the same point."
        )
    try:
        batch = np.broadcast_shapes(tuple(world.shape[:-2]), tuple(pixels.shape[:-2]))
    except ValueError:
        raise ValueError(
            f"the leading (camera) axes of `world` {tuple(world.shape[:-2])} and `pixels` "
            f"{tuple(pixels.shape[:-2])} do not broadcast."
        ) from None
    n = world.shape[-2]
    if n < min_points:
        raise ValueError(
            f"at least {min_points} points are needed; got {n}. A projection matrix has 11 "
            "degrees of freedom and each point gives two equations."
        )
    if 0 in batch:
        raise ValueError(f"the camera axes are empty (batch shape {batch}).")
    dtype = result_dtype(world.dtype, pixels.dtype)
    world, pixels = world.astype(dtype), pixels.astype(dtype)
    mask = boolean_mask("mask", mask, (*batch, n), xp=xp)
    if is_concrete(world, pixels, mask):
        _check_finite(world, pixels, mask)
        check_placeholders(pixels, mask)
    if isinstance(world, np.ndarray) and world.dtype == np.float32:
        _check_precision(world, mask)
    return world, pixels, mask


# float32 rounds a coordinate to 2^-24 of its size; beyond this fraction of the points' extent
# (~0.01 px in an image that the points fill), a float32 world loses what the pixels measure.
MAX_ROUNDING = 2e-5


def _check_precision(world: np.ndarray, mask: np.ndarray) -> None:
    """Warn where float32 rounds the visible world points by more than `MAX_ROUNDING` of their
    extent: coordinates far from the origin (e.g. UTM) of a small target."""
    if world.ndim == 2:  # one target: the points any camera sees
        seen = world[np.asarray(mask).reshape(-1, world.shape[0]).any(0)]
    else:
        seen = np.broadcast_to(world, mask.shape + (3,))[np.asarray(mask)]
    check_float32_frame(seen, "`world` is", "the points' extent", "the cameras")


def check_float32_frame(points: np.ndarray, what: str, extent_of: str, losers: str) -> None:
    """Warn where float32 rounds `points (K, 3)` by more than `MAX_ROUNDING` of their extent."""
    points = points[np.isfinite(points).all(-1)]
    if len(points) < 2:
        return
    size, extent = float(np.abs(points).max()), float(np.ptp(points, axis=0).max())
    rounding = float(np.spacing(np.float32(size))) / 2
    if extent > 0 and rounding > MAX_ROUNDING * extent:
        warnings.warn(
            f"{what} float32 and lies up to {size:.6g} from the origin, {size / extent:.0f} "
            f"times {extent_of}: float32 rounds it by up to {rounding:.2g}, "
            f"{rounding / extent:.1e} of the extent, and {losers} lose that precision. "
            "Subtract an origin near the points first, or compute in float64: "
            'jax.config.update("jax_enable_x64", True).',
            stacklevel=_outside_mvcalib(),
        )


def check_placeholders(pixels, mask) -> None:
    """Warn where visible pixels look like placeholders for unseen points: more than 1 % (and at
    least two) exactly (-1, -1) or (0, 0), which trackers write for "not found". Taken as
    detections, they gave triangulated points 13,000 px off (an animal-pose trial), silently.
    Concrete arrays only."""
    pixels, mask = np.asarray(pixels), np.broadcast_to(np.asarray(mask), np.shape(pixels)[:-1])
    visible = np.count_nonzero(mask)  # (counted in place: copying out the visible pixels of
    # 176,868 tracks x 12 cameras took 0.28 s of `triangulate`, these counts 6 ms)
    for value in (-1.0, 0.0):
        count = np.count_nonzero((pixels[..., 0] == value) & (pixels[..., 1] == value) & mask)
        if count >= 2 and count > 0.01 * visible:
            warnings.warn(
                f"{count} of the {visible} visible pixels are exactly ({value:g}, {value:g}): "
                "if they mark points not seen, pass NaN there (or a `mask`); as they are, they "
                "count as detections.",
                stacklevel=_outside_mvcalib(),
            )


def finite_pixels(pixels, xp=np):
    """Where both coordinates of `pixels (..., 2)` are finite: one test per coordinate (NumPy's
    `all` over a trailing axis of two took 7.3 ms of 600,000 pixels, this 0.2 ms)."""
    return xp.isfinite(pixels[..., 0]) & xp.isfinite(pixels[..., 1])


def check_hidden_non_finite(pixels, mask) -> None:
    """Warn where the `mask` calls pixels visible that are NaN or inf, in the functions that take
    them as hidden (`triangulate`, `bundle_adjust`: NaN marks a point not seen there; `calibrate`
    raises instead): a stale mask silently gave points from fewer views (a user's trial).
    Concrete arrays only."""
    pixels, mask = np.asarray(pixels), np.broadcast_to(np.asarray(mask), np.shape(pixels)[:-1])
    bad = ~finite_pixels(pixels) & mask
    count = np.count_nonzero(bad)
    if count:
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        warnings.warn(
            f"{count} pixels that the mask calls visible are NaN or inf (the first at index "
            f"{first}): they count as hidden. Leave `mask` out to have the finite pixels taken, "
            "or correct it.",
            stacklevel=_outside_mvcalib(),
        )


def _outside_mvcalib() -> int:
    """The `stacklevel` of a warning raised here that names the first caller outside mvcalib."""
    package = os.path.dirname(__file__)
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.dirname(frame.f_code.co_filename) == package:
        frame, level = frame.f_back, level + 1
    return level


def _non_finite(world, pixels, mask, xp=jnp):
    """How many visible points have NaN/inf in `world` and in `pixels`: two integers."""
    count = lambda x: xp.sum(~xp.all(xp.isfinite(x), axis=-1) & mask)  # noqa: E731
    return count(world), count(pixels)


_count_non_finite = jax.jit(_non_finite)


def _check_finite(world, pixels, mask):
    # Counted where the data live (two integers come back to the host, not the arrays); the
    # arrays are copied to NumPy only to name the first bad entry in the error.
    if isinstance(world, np.ndarray):
        counts = _non_finite(world, pixels, mask, np)
    else:
        counts = _count_non_finite(world, pixels, mask)
    if not any(int(n) for n in counts):
        return
    mask = np.asarray(mask)
    for name, x in (("world", world), ("pixels", pixels)):
        x = np.asarray(x)
        finite = np.all(np.isfinite(x), axis=-1)
        bad = np.broadcast_to(~finite, mask.shape) & mask
        if bad.any():
            where = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(
                f"`{name}` has {int(bad.sum())} non-finite (NaN or inf) entries among the "
                f"visible points, the first at index {where}. Mask them out "
                "(mask[...] = False) or fix the data."
            )


def at_least(name: str, x, n: int, what: str):
    if x.shape[-2] < n:
        raise ValueError(f"`{name}` needs at least {n} {what}; got shape {tuple(x.shape)}.")


def in_image(pixels, mask, image_size) -> None:
    """Refuse visible pixels outside `image_size=(width, height)` by more than 1 % of its larger
    side (noise and a dot cut by the border stay inside that): pixels given as (row, column), or
    the size as (height, width), are what this usually is. Concrete arrays only."""
    bad = f"`image_size` is (width, height) in pixels; got {image_size!r}."
    try:
        width, height = (float(v) for v in image_size)
    except (TypeError, ValueError):
        raise ValueError(bad) from None
    if not (width > 0 and height > 0):
        raise ValueError(bad)
    if not is_concrete(pixels, mask):
        return
    seen = np.asarray(pixels)[np.asarray(mask, bool)]
    margin = 0.01 * max(width, height)
    low, high = -0.5 - margin, np.array([width, height]) - 0.5 + margin
    outside = ((seen < low) | (seen > high)).any(-1)
    if outside.any():
        x, y = seen[np.argmax(outside)]
        raise ValueError(
            f"{int(outside.sum())} visible pixels lie outside the image of `image_size` "
            f"({width:g}, {height:g}), e.g. ({x:.1f}, {y:.1f}): are the pixels (x = column, "
            "y = row) and the size (width, height)?"
        )


def is_planar(target: np.ndarray) -> bool:
    """Whether a target's points `(N, 3)` lie on a plane (else they must span 3-D); ValueError
    where they are collinear or fewer than 4."""
    c = target - target.mean(0)
    s = np.linalg.svd(c, compute_uv=False)
    tol = 1e-6 if target.dtype == np.float64 else 1e-4
    if len(target) < 4 or s[1] <= tol * s[0]:
        raise ValueError("the target's points are collinear or too few (at least 4 needed).")
    return bool(s[2] <= tol * s[0])
