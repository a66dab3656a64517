"""Shape buckets: one compiled program for many sizes of rig.

JAX compiles a program for every new input shape, and mvcalib's programs take seconds to compile
and micro- to milliseconds to run. A call from Python with concrete arrays (not inside the
user's `jax.jit`, `vmap` or `grad`) therefore pads the camera and point axes up to a *bucket*
before the compiled call and cuts the answer back afterwards:

- a length `n` goes up to the next `k 2^e` with `16 <= k < 32`: at most 6.25 % more work, and
  sixteen sizes per doubling (`size`);
- a program covers at least `WORK` camera-points (64 cameras of 64 points), so every rig up to
  that size shares one program (`cameras_and_points`).

Padding changes nothing that is returned but rounding. A padded point is hidden (`mask` False,
zeros in `world` and `pixels`), and hidden points have no influence at all; longer sums may round
in another order, and a solver that stops at a tolerance (`refine`: steps of 1e-5 standard errors)
may then stop a step apart: in a trial, the same refinement eager (padded) and inside the user's
`jax.jit` (not) differed by up to 7e-7 (relative) and one step. A padded camera is a copy of the
last camera, whose answer does not depend on the others in its batch (inverse iteration goes on
while any camera does, the others keeping their vectors); refinement sees it as a camera without a
seed, whose problem ends at once. `calibrate_rig` pads its frames and cameras and
`calibrate_planar` its views, in coarser buckets (a recording's length changes with every
recording), with frames or views nobody saw and cameras that see nothing, and `refine_rig` its
cameras and points, with cameras that see nothing and points nobody sees,
which their solves hold still: these joint solves round differently, so the answer is the same to
the solves' tolerance (steps of 1e-5 standard errors), not to the last digit. The padding is done
on the host in NumPy (on a CPU that is the arrays' own memory), so that a new shape compiles
nothing but the bucket's program. Inside the user's traced code, shapes are theirs: padding would
only add work to the program they compile anyway.

Programs are compiled by `jit` (in a build that compiles quickly when small) and, where a call
runs several one after the other, on other threads at the same time (`ahead`). A batch of
independent problems (the refinement's cameras) is run in equal pieces, one per core, each on a
thread of its own (`jit.across`, `pieces`): one program for them all, compiled for a piece.
"""

from __future__ import annotations

import concurrent.futures
import contextvars
import functools
import importlib.machinery
import importlib.util
import math
import os
import sys
import warnings

import equinox as eqx
import jax
import numpy as np

from . import _validate
from ._gc import collector_paused

# The least camera-points a program covers: below it, running costs next to nothing (the DLT of
# 64 cameras of 64 points takes ~0.2 ms) against the seconds a new program takes to compile.
WORK = 64 * 64
MIN_CAMERAS = 64


def size(n: int, minimum: int = 1, *, bits: int = 5) -> int:
    """The bucket of a length: the least `k 2^e >= max(n, minimum)` with `2^(bits-1) <= k <
    2^bits` (lengths up to `2^bits` are their own bucket): by default sixteen sizes per
    doubling, at most 6.25 % more work; `bits=2`, two (48, 64, 96, ...), at most 50 %."""
    n = max(int(n), int(minimum), 1)
    step = 1 << max((n - 1).bit_length() - bits, 0)
    return -(-n // step) * step


def cameras_and_points(n_cameras: int, n_points: int) -> tuple[int, int]:
    """The bucket `(C, N)` of a rig of `n_cameras` seeing `n_points` points each."""
    cameras = size(n_cameras, MIN_CAMERAS)
    return cameras, size(n_points, math.ceil(WORK / cameras))


def applies(*trees) -> bool:
    """Whether a call with these arguments may pad: every array concrete (`is_concrete`: also
    no trace under way), and none split over several devices (whose layout the caller chose;
    `mvcalib.shard`)."""
    leaves = jax.tree_util.tree_leaves(trees)
    if not _validate.is_concrete(*leaves):
        return False
    return not any(isinstance(x, jax.Array) and len(x.sharding.device_set) > 1 for x in leaves)


def pads(world, pixels, mask) -> bool:
    """Whether a call with these correspondences pads (`applies`), i.e. is not already of its
    bucket's shape with one camera axis: a rig that is goes to the compiled program as it is,
    without a copy through NumPy."""
    if not applies(world, pixels, mask):
        return False
    try:
        n = np.shape(pixels)[-2]
        batch = np.broadcast_shapes(np.shape(world)[:-2], np.shape(pixels)[:-2])
        if mask is not None:
            batch = np.broadcast_shapes(batch, np.shape(mask)[:-1])
    except (ValueError, IndexError):  # bad shapes: validation says what is wrong
        return True
    return len(batch) != 1 or cameras_and_points(batch[0], n) != (batch[0], n)


def take(tree, index):
    """`tree`'s arrays indexed along their leading axes (`rig[0]`, `rig[1:3]`, `rig[ok]`):
    inside a trace or split over devices as JAX does; concrete, in NumPy (an eager slice of a JAX
    array compiles a program per shape and leaf)."""
    if not applies(tree, index):
        return jax.tree_util.tree_map(lambda x: x[index], tree)
    if isinstance(index, jax.Array):
        index = np.asarray(index)

    def one(x):
        return x[index] if isinstance(x, np.ndarray) else jax.device_put(np.asarray(x)[index])

    return jax.tree_util.tree_map(one, tree)


def pad(x, axis: int, length: int, *, fill=None):
    """`x` (as a NumPy array) padded along `axis` to `length`: with `fill`, or with copies of its
    last entry along that axis when `fill` is None."""
    x = np.asarray(x)
    missing = length - x.shape[axis]
    if missing <= 0:
        return x
    if fill is None:
        extra = np.repeat(np.take(x, [-1], axis=axis), missing, axis=axis)
    else:
        shape = list(x.shape)
        shape[axis] = missing
        extra = np.full(shape, fill, dtype=x.dtype)
    return np.concatenate([x, extra], axis=axis)


def correspondences(world, pixels, mask):
    """Validated NumPy `world`, `pixels`, `mask` of any batch shape, flattened to one camera axis
    and padded to their bucket: `(world, pixels, mask), batch`, with `world (N, 3)` kept shared
    by the cameras (else `(C, N, 3)`) and `batch` the cameras' shape to restore (`cut`)."""
    n = pixels.shape[-2]
    batch = np.broadcast_shapes(world.shape[:-2], pixels.shape[:-2], mask.shape[:-1])
    flat = lambda x, tail: np.broadcast_to(x, batch + tail).reshape((-1,) + tail)  # noqa: E731
    n_cameras, n_points = cameras_and_points(math.prod(batch), n)
    pixels = pad(pad(flat(pixels, (n, 2)), 0, n_cameras), 1, n_points, fill=0)
    mask = pad(pad(flat(mask, (n,)), 0, n_cameras), 1, n_points, fill=False)
    if world.ndim == 2:
        world = pad(world, 0, n_points, fill=0)
    else:
        world = pad(pad(flat(world, (n, 3)), 0, n_cameras), 1, n_points, fill=0)
    return (world, pixels, mask), batch


def cut(tree, batch: tuple[int, ...]):
    """Every array of `tree` (outputs of a padded call) with its camera axis, the first, cut to
    the real cameras and shaped `batch`, as a JAX array.

    (In NumPy, and back by `jax.device_put`: an eager slice of a JAX array, and `jnp.asarray` of
    a NumPy one, compile a program of their own for every new shape, 10-50 ms each.)"""
    n = math.prod(batch)

    def one(x):
        if not isinstance(x, (jax.Array, np.ndarray)) or np.ndim(x) == 0:
            return x
        x = np.asarray(x)
        return jax.device_put(x[:n].reshape(batch + x.shape[1:]))

    return jax.tree_util.tree_map(one, tree)


def cut_points(tree, where, n: int, axis: int):
    """`tree` with its arrays `where(tree)` (a tuple: those with a point axis) cut to the first
    `n` points along `axis` (`first`)."""
    return eqx.tree_at(where, tree, tuple(first(x, n, axis) for x in where(tree)))


def first(tree, n: int, axis: int = -1):
    """Every array of `tree` cut to its first `n` entries along `axis` (a padded point axis cut
    back), as a JAX array (in NumPy, as `cut`)."""

    def one(x):
        x = np.asarray(x)
        return jax.device_put(x[(slice(None),) * (axis % x.ndim) + (slice(0, n),)])

    return jax.tree_util.tree_map(one, tree)


# Camera-points up to which a program takes a compact form (`_dlt.compact`) and is compiled
# quickly (`jit`): 16 programs' worth of the smallest (256 cameras of 64 points, 862 of 19).
COMPACT = 16 * WORK

# XLA's CPU backend: its older fusion emitters. They compile in 55-70 % of the newer MLIR
# emitters' time and run about as fast: on this project's 2-core machine (interleaved in one
# process), `calibrate` of 4096 cameras of 19 points compiled in 2.4-2.8 s against 3.7-4.5 s and
# ran 8-11 % slower (4.0 against 3.7 ms), `refine` of 256 cameras of 108 points compiled in 2.4
# s against 2.9 s and ran 5 % faster, `triangulate` of 100,000 points in 1.0 s against 1.9 s and
# 3 % faster. (docs/performance.md has the figures, and the other way round on a Xeon.)
_OPTIMISED = {"xla_cpu_use_fusion_emitters": False}

# Compiling quickly, for small programs: LLVM without optimisation too. The compact DLT of 64
# cameras of 64 points compiled in 0.55 s against 4.95 s fully optimised, and ran in the same
# 2.3 ms. And in one piece: XLA splits a module into up to 32 for LLVM to compile in parallel,
# which without optimisation costs more than it saves (2 cores, fresh processes, interleaved:
# the first `calibrate` of 4 cameras 0.73-0.81 s against 0.79-0.88, with `refine=True`
# 1.32-1.45 against 1.39-1.52, of 1024 cameras 1.68-1.83 against 1.77-1.98; test_rig.py 532
# against 578 s; a program's code in 604 memory mappings against 790, `tests/conftest.py`).
# An optimised build keeps the split: the DLT of 4096 cameras compiled in 4.0 s in one piece
# against 2.9 s.
_QUICK = {
    **_OPTIMISED,
    "xla_backend_optimization_level": 0,
    "xla_cpu_parallel_codegen_split_count": 1,
}


def optimised_options() -> dict:
    """The options of `_OPTIMISED` that this XLA knows, on a CPU; none elsewhere."""
    return {k: v for k, v in _OPTIMISED.items() if k in _known()}


def quick_options() -> dict:
    """The options of `_QUICK` that this XLA knows, on a CPU; none elsewhere."""
    return {k: v for k, v in _QUICK.items() if k in _known()}


def quick_compiler_options() -> dict:
    """XLA's options for a program whose compiling is most of the wait: pass them to your own
    `jax.jit` around mvcalib's calls, `jax.jit(f, compiler_options=mc.quick_compiler_options())`
    (`eqx.filter_jit` takes them too).

    Inside your `jit` (or `grad`) mvcalib's calls are part of your program, compiled with your
    options: fully optimised by default, which for a whole calibration takes far longer than it
    runs. These are the options mvcalib's own small programs are compiled with (LLVM without
    optimisation, the module in one piece, XLA's older CPU emitters), those this XLA knows, on a
    CPU; none elsewhere. Measured (2 cores, float64, fresh processes): `jax.jit(jax.grad(...))`
    through `calibrate(..., refine=True)` of 4 cameras, first call 5.5-5.6 s against 9.75 s, warm
    2.9-3.1 against 1.34 ms; through `calibrate_rig` of 4 cameras and 40 frames, 11.6-12.4 s
    against 19.9 s, warm 2.1-2.2 against 1.06 s.
    Where the program runs many times (an optimisation loop of thousands of steps), the
    default's faster code may repay its compile.

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=3, noise=0.3)
    >>> focal = jax.jit(lambda pixels: mc.calibrate(rig.world, pixels).cameras.alpha_u,
    ...                 compiler_options=mc.quick_compiler_options())
    >>> focal(rig.pixels).shape
    (3,)

    ```
    """
    return quick_options()


@functools.cache
def _known() -> frozenset:
    """The names in `_QUICK` (which holds `_OPTIMISED`'s too) that this XLA knows as compiler
    options, on a CPU; none elsewhere. An option it does not know is an error at compile time:
    all are tried in one small program, and one by one only if that fails."""
    if jax.default_backend() != "cpu":
        return frozenset()

    def compiles(options):
        try:
            jax.jit(lambda x: x + 1, compiler_options=options).lower(1.0).compile()
        except Exception:  # noqa: BLE001 (XLA's error for an unknown option has no type of its own)
            return False
        return True

    if compiles(_QUICK):
        return frozenset(_QUICK)
    return frozenset(name for name, value in _QUICK.items() if compiles({name: value}))


# jaxlib's CPU backend calls LAPACK's routines through SciPy: at its first lowering of a linear
# algebra operation (an SVD, a Cholesky factor) it imports `scipy.linalg.cython_blas` and
# `scipy.linalg.cython_lapack` for their function pointers, and with them all of `scipy.linalg`
# (its `__init__`: 70 ms on this project's machine, on the main thread, inside every first call).
_LAPACK_MODULES = ("cython_blas", "cython_lapack")


@functools.cache
def _lapack_from_scipy() -> None:
    """Hand jaxlib SciPy's LAPACK without the rest of `scipy.linalg`: the two Cython modules are
    loaded on their own (9 ms), jaxlib takes its pointers from them, and they leave
    `sys.modules` again, so that the user's `import scipy.linalg` later is as it would have
    been. Where anything differs from that (`scipy.linalg` imported already, another jaxlib or
    SciPy, not a CPU), nothing is done, and jaxlib imports them itself at its first lowering."""
    if "scipy.linalg" in sys.modules or jax.default_backend() != "cpu":
        return
    loaded = []
    try:
        import scipy  # (the package's own set-up first: its libraries' search path on Windows)
        from jaxlib.cpu import _lapack

        folder = [str(next(iter(scipy.__path__))) + "/linalg"]
        for name in _LAPACK_MODULES:
            spec = importlib.machinery.PathFinder.find_spec(name, folder)
            spec.name = f"scipy.linalg.{name}"
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            sys.modules[spec.name] = module
            loaded.append(spec.name)
        _lapack.initialize()
    except Exception:  # noqa: BLE001 (any surprise: jaxlib's own import, 70 ms later, will do)
        pass
    finally:
        for name in loaded:
            sys.modules.pop(name, None)


class jit:  # noqa: N801 (used as `jax.jit` is)
    """`jit(fun, **kwargs)` (`jax.jit`, or `eqx.filter_jit` as `jit`) in two builds for calls from
    Python: optimised (`optimised_options`), and, called with `quick=True`, compiled quickly
    (`quick_options`), for programs small enough (`COMPACT`) that their compile time is all the
    user waits for. Inside the user's traced code it is `jit(fun, **kwargs)`: the caller
    compiles the whole program, with the caller's options. Under `ahead`, a call lowers its
    program and has it compiled on a second thread; a later call waits for that compile rather
    than compiling the program again."""

    def __init__(self, fun, *, jit=jax.jit, **kwargs):
        self._fun, self._jit, self._kwargs = fun, jit, kwargs
        self.traced = jit(fun, **kwargs)
        self._compiling: list[concurrent.futures.Future] = []
        self._seen: set = set()  # the signatures of the calls from Python so far
        self._shapes: dict = {}  # their outputs' shapes and types (`ahead`'s stand-ins)
        functools.update_wrapper(self, fun)

    @functools.cached_property
    def optimised(self):
        return self._jit(self._fun, compiler_options=optimised_options(), **self._kwargs)

    @functools.cached_property
    def quick(self):
        return self._jit(self._fun, compiler_options=quick_options(), **self._kwargs)

    def __call__(self, *args, quick: bool = False, _compile_only: bool = False, **kwargs):
        if not _top_level():
            return self.traced(*args, **kwargs)
        signature = _signature(quick, args, kwargs)
        with collector_paused():
            _lapack_from_scipy()
            build = self.quick if quick else self.optimised
            compiled = signature in self._seen and _holds_programs(build)
            if _AHEAD.get():
                if compiled:  # (a stand-in all the same, for the programs that follow)
                    raise _Lowered(_filled(self._shapes.get(signature)))
                lowered = build.lower(*args, **kwargs)
                self._compiling.append(_compiler().submit(lowered.compile))
                self._seen.add(signature)
                self._shapes[signature] = _stand_in(lowered)
                raise _Lowered(_filled(self._shapes[signature]))
            self._wait()
            if _compile_only:
                out = None if compiled else build.lower(*args, **kwargs).compile()
            else:
                out = build(*args, **kwargs)
                if signature not in self._shapes:
                    self._shapes[signature] = _shapes(out)
        self._seen.add(signature)
        return out

    def across(self, parts: list, *, quick: bool = False, **kwargs) -> list:
        """The program called on each of `parts` (tuples of positional arguments of equal shapes
        and types: a batch of independent problems cut into equal pieces, `pieces`), each piece
        on a thread of its own (`side_by_side`), one program compiled for them all. Every output
        array has the piece's batch as its leading axis: under `ahead`, the stand-in is the
        whole batch's. Called from Python with concrete arrays only."""
        if len(parts) == 1:
            return [self(*parts[0], quick=quick, **kwargs)]
        try:
            self(*parts[0], quick=quick, _compile_only=True, **kwargs)
        except _Lowered as lowered:  # (under `ahead`)
            whole = lowered.stand_in
            if whole is not None:
                whole = jax.tree_util.tree_map(lambda x: np.concatenate([x] * len(parts)), whole)
            raise _Lowered(whole) from None
        build = self.quick if quick else self.optimised
        run = lambda args: jax.block_until_ready(build(*args, **kwargs))  # noqa: E731
        caller = _settings()

        def beside(args):  # (not under settings this thread does not share, e.g. the caller's
            return run(args) if _settings() == caller else None  # `jax.enable_x64(...)`)

        others = [side_by_side().submit(beside, args) for args in parts[1:]]
        outs = [run(parts[0])] + [future.result() for future in others]
        return [run(args) if out is None else out for out, args in zip(outs, parts)]

    def _wait(self):
        """Wait for the compiles `ahead` started (JAX keeps what they compiled: the call that
        follows finds it; one that failed is compiled again by that call, which reports why)."""
        if self._compiling:
            concurrent.futures.wait(self._compiling)
            self._compiling.clear()

    def clear_cache(self):
        """Forget every build's compiled programs (`jax.jit`'s `clear_cache`)."""
        self._wait()
        self._seen.clear()
        self._shapes.clear()
        for build in ("traced", "optimised", "quick"):
            if build in self.__dict__:
                getattr(self.__dict__[build], "clear_cache", lambda: None)()


def eager(fun):
    """`fun` as one program compiled quickly (`jit`) where it is called with concrete arrays
    from Python, and as it is where it is traced (inlined into the caller's program): for the
    small array functions a user calls eagerly (`Camera.K`, `procrustes`, ...), where `jnp`
    would compile a program per operation and shape."""
    compiled = jit(fun)

    @functools.wraps(fun)
    def call(*args):
        return compiled(*args, quick=True) if applies(*args) else fun(*args)

    return call


def _signature(*tree):
    """What tells compiled programs apart, roughly: the tree's structure, its arrays' shapes and
    types, its other leaves (hashable or not: by identity). Equal signatures can still need two
    programs (say, arrays on other devices): a signature serves only to skip work (`ahead`)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)

    def key(x):
        if isinstance(x, (np.ndarray, jax.Array, np.generic)):
            return (x.shape, x.dtype, getattr(x, "weak_type", False))
        try:
            hash(x)
        except TypeError:
            return id(x)
        return x

    return treedef, tuple(map(key, leaves))


def _holds_programs(build) -> bool:
    """Whether a `jax.jit` (or `eqx.filter_jit`) holds compiled programs: none after
    `jax.clear_caches()`. JAX's cache size is private; where it is missing, assume it does."""
    size = getattr(getattr(build, "_cached", build), "_cache_size", None)
    return size is None or size() > 0


# ------------------------------------------------------------------------------ compiling ahead
# XLA compiles without holding Python's lock, on one core: a program that a call will need can
# be compiled on a second thread while Python traces the next one (or XLA compiles it).
_AHEAD = contextvars.ContextVar("mvcalib_ahead", default=False)


class _Lowered(BaseException):
    """Raised by a `jit` called under `ahead`, once its program is lowered (a `BaseException`,
    which no `except Exception` on the way out stops), with a stand-in of its outputs."""

    def __init__(self, stand_in):
        super().__init__()
        self.stand_in = stand_in


def _stand_in(lowered):
    """The shapes and types of a lowered program's outputs (`jax.jit`'s or `eqx.filter_jit`'s),
    as `jax.ShapeDtypeStruct`s in the outputs' tree. (A weakly typed output, which JAX's
    `out_info` does not show and NumPy cannot stand in for, would have the program that takes it
    compiled for the wrong type: mvcalib's programs return none, which the tests that count
    compiles check.)"""
    inner = getattr(lowered, "lowered", None)  # `eqx.filter_jit`'s: JAX's, and its outputs' rebuild
    if inner is None:
        return _shapes(lowered.out_info)
    return lowered.postprocess(_shapes(inner.out_info))


def _shapes(tree):
    """`tree` with its arrays (or their descriptions) replaced by `jax.ShapeDtypeStruct`s."""
    is_array = lambda x: hasattr(x, "shape") and hasattr(x, "dtype")  # noqa: E731
    return jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype) if is_array(x) else x, tree
    )


def _filled(tree):
    """NumPy arrays of the shapes and types in `tree` (`_shapes`), NaN where they are
    floating-point, else zero; None for None."""

    def fill(x):
        if not isinstance(x, jax.ShapeDtypeStruct):
            return x
        return np.full(x.shape, np.nan if np.issubdtype(x.dtype, np.inexact) else 0, x.dtype)

    return jax.tree_util.tree_map(fill, tree)


@functools.cache
def _compiler() -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(2, thread_name_prefix="mvcalib-compile")


# ------------------------------------------------------------------------------- side by side
# XLA's CPU runtime runs a program's loop one step after another, handing the steps' small
# kernels between the cores' threads as they become ready, which costs more than it wins: the
# refinement of 1024 cameras of 19 points (a loop over the cameras) took 0.48 s on this project's
# 2 cores and 0.37-0.46 s confined to one (`taskset`). Called from two threads, two programs
# run on a core each: the rig's two halves, side by side, 0.24-0.25 s.
MIN_PIECE = 16


def _cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # (not on Linux)
        return os.cpu_count() or 1


def _settings():
    """JAX's settings that its compiled programs depend on, as this thread sees them (some can be
    set for one thread: `with jax.enable_x64(True)`); None where JAX's private record of them is
    missing."""
    settings = getattr(getattr(jax, "_src", None) and jax._src.config, "trace_context", None)
    return settings() if settings else None


def pieces(n: int) -> int:
    """Into how many equal pieces a batch of `n` independent problems, called from Python, is cut
    to run side by side (`jit.across`): on one CPU device, the most cores (a power of two) that
    divide `n` into pieces of at least `MIN_PIECE`; elsewhere one (an accelerator runs the batch
    at once, several devices split it themselves), and where the threads could not tell the
    caller's settings from theirs (`_settings`)."""
    if jax.default_backend() != "cpu" or jax.device_count() > 1 or _settings() is None:
        return 1
    k = 1
    while 2 * k <= _cores() and n % (2 * k) == 0 and n // (2 * k) >= MIN_PIECE:
        k *= 2
    return k


def in_pieces(program: jit, args: tuple, axes: tuple, *, quick: bool = False, **kwargs):
    """`program(*args, quick=quick, **kwargs)` for a batch of independent problems, each
    argument's along its axis in `axes` (None: every problem's), called from Python with
    concrete arrays: in `pieces` equal pieces of the batch run side by side (`jit.across`), the
    outputs (each with the batch as its leading axis) joined in NumPy. Elsewhere, one call.

    Only for programs that solve each problem alone (a `lax.map` over them), whose answers do
    not depend on the batch's size: a solve vectorised over the batch rounds differently at
    another size (`triangulate`'s points, a trial: up to 2e-8 apart in four pieces), and the
    answer would depend on the machine's cores."""
    n = next(np.shape(x)[axis] for a, axis in zip(args, axes) if axis is not None
             for x in jax.tree_util.tree_leaves(a))  # fmt: skip
    k = pieces(n) if applies(*args) else 1
    if k == 1:
        return program(*args, quick=quick, **kwargs)
    size = n // k

    def piece(i):
        index = slice(i * size, (i + 1) * size)

        def cut(a, axis):
            if axis is None:
                return a
            where = (slice(None),) * axis + (index,)
            return jax.tree_util.tree_map(lambda x: np.asarray(x)[where], a)

        return tuple(map(cut, args, axes))

    out = program.across([piece(i) for i in range(k)], quick=quick, **kwargs)
    return jax.tree_util.tree_map(lambda *xs: jax.device_put(np.concatenate(xs)), *out)


@functools.cache
def side_by_side() -> concurrent.futures.ThreadPoolExecutor:
    """The threads that run the pieces of a batch beside the caller's (`jit.across`)."""
    return concurrent.futures.ThreadPoolExecutor(
        max(_cores() - 1, 1), thread_name_prefix="mvcalib-run"
    )


def ahead(fun, /, *args, **kwargs):
    """Start compiling the program that `fun(*args, **kwargs)` would call first (a `jit`'s), and
    return as soon as it is lowered: `fun` runs up to that call (its checks and padding, in
    NumPy) and no further, and XLA compiles the program on a second thread while the caller goes
    on. Call `fun` later with arguments of the same shapes and types: its call of the program
    waits for that compile instead of compiling again.

    Returns a stand-in of the program's outputs (NumPy arrays of their shapes and types, NaN or
    zero), with which the `ahead` of a program that takes them can follow (`chain`), also where
    the program is compiled already; `None` where nothing can follow. Only a hint: inside a
    trace, where the program is compiled already, or if `fun` fails before its first program,
    nothing is started (a real call would raise the same error)."""
    if not _top_level():
        return None
    token = _AHEAD.set(True)
    try:
        with warnings.catch_warnings():  # (about stand-in inputs; the real call warns of its own)
            warnings.simplefilter("ignore")
            fun(*args, **kwargs)
    except _Lowered as lowered:
        return lowered.stand_in
    except Exception:  # noqa: BLE001 (an error: the real call will raise it)
        pass
    finally:
        _AHEAD.reset(token)
    return None


def chain(first, /, *then, early: bool = True):
    """`first()`, then each of `then` called with the one before's output: the last one's. Each
    is a program (or runs up to one, as `ahead` asks); with `early`, every one of them is
    compiled on another thread before the first runs, each traced with a stand-in of the one
    before's outputs while XLA compiles that (`ahead`). Pass `early=False` for arrays whose
    layout a stand-in would not have (split over devices: `applies`)."""
    like = ahead(first) if early else None
    for stage in then:
        if like is None:
            break
        like = ahead(stage, like)
    out = first()
    for stage in then:
        out = stage(out)
    return out


def _top_level() -> bool:
    """Whether no JAX transformation is tracing: only a top-level `jax.jit` takes compiler
    options (JAX raises for a nested one). JAX has no public test of this; where its private one
    is missing, every program is compiled with JAX's defaults."""
    clean = getattr(getattr(jax, "_src", None) and jax._src.core, "trace_state_clean", None)
    return bool(clean and clean())
