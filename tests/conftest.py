import functools
import os
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

# The tests check what is computed, not how fast: XLA is asked not to spend time optimising the
# compiled code (LLVM at -O0, no expensive passes), which cuts the suite's compile time by a
# quarter to a third. The benchmarks run fully optimised code; JAX_DISABLE_MOST_OPTIMIZATIONS=0
# runs the tests on it too.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
OPTIMISE = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] != "1"
jax.config.update("jax_disable_most_optimizations", not OPTIMISE)

# XLA's CPU backend generates each fusion's code with its newer MLIR emitters, which take two to
# three times as long to compile as the older ones (a DLT program at -O0: 2.1 s against 0.85 s;
# pytest in a clean clone: 598 s against 956-977 s before, with a smaller change to triangulate).
# The tests ask for the older ones, where this XLA still has them: an XLA that does not know a
# flag in XLA_FLAGS aborts, so a child process tries it first (once; the xdist workers and
# notebook kernels inherit the answer). The two generate the same operations but may round
# differently, and differently at different batch sizes; tests that compare programs to the
# last bits, or rest on rounding, are marked `default_codegen` and run in a child process
# compiled as programs in users' own `jit` are (`default_codegen_env`; mvcalib's calls from
# Python ask for the older emitters themselves: `mvcalib/_buckets.py`).
LEGACY_EMITTERS = "--xla_cpu_use_fusion_emitters=false"


def _xla_flags() -> list[str]:
    return os.environ.get("XLA_FLAGS", "").split()


def _ask_for_legacy_emitters():
    if OPTIMISE or os.environ.get("MVCALIB_TEST_XLA_PROBED"):
        return
    os.environ["MVCALIB_TEST_XLA_PROBED"] = "1"
    flags = " ".join([*_xla_flags(), LEGACY_EMITTERS])
    probe = [sys.executable, "-c", "import jax; jax.devices()"]
    env = {**os.environ, "XLA_FLAGS": flags}
    try:
        known = subprocess.run(probe, env=env, capture_output=True, timeout=120).returncode == 0
    except subprocess.TimeoutExpired:  # a machine that slow gets the default, not an error
        known = False
    if known:
        os.environ["XLA_FLAGS"] = flags


_ask_for_legacy_emitters()
LEGACY = LEGACY_EMITTERS in _xla_flags()

# No persistent compilation cache for the run. It was taken out when XLA crashed in a worker
# while serialising a program into it or loading one from it; the crashes went on without it,
# and their cause was a worker out of memory mappings (`_let_go_of_programs`, below), not the
# cache. The suite has not been run with the cache since. Each process compiles its own
# programs (no `jax_compilation_cache_dir` here, none passed to the child processes); the
# command line's own cache, which its tests turn on or off, is theirs.


def default_codegen_env() -> dict:
    """The environment of a child process that compiles as users' programs are compiled (XLA's
    default CPU emitters)."""
    flags = " ".join(f for f in _xla_flags() if f != LEGACY_EMITTERS)
    return {**os.environ, "XLA_FLAGS": flags, "MVCALIB_TEST_XLA_PROBED": "1"}


def pytest_pyfunc_call(pyfuncitem):
    """A `default_codegen` test, in a process that uses the older emitters, runs in a child
    pytest compiled as users' programs are; its failure is this test's failure."""
    if not LEGACY or pyfuncitem.get_closest_marker("default_codegen") is None:
        return None
    command = [sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider"]
    proc = subprocess.run(
        [*command, pyfuncitem.nodeid],
        cwd=pyfuncitem.config.rootpath,
        env=default_codegen_env(),
        capture_output=True,
        text=True,
        timeout=900,
    )
    if proc.returncode != 0:
        tail = proc.stdout[-6000:]
        pytest.fail(f"in a child process with XLA's default emitters:\n{tail}", pytrace=False)
    return True


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "optimised: compile this test's programs fully optimised (its time is spent running "
        "them, e.g. a bundle adjustment of real data, not compiling them)",
    )
    config.addinivalue_line(
        "markers",
        "default_codegen: the test compares results to rounding, which depends on how XLA "
        "generates code; it runs with XLA's default CPU emitters, as users' programs do",
    )


@pytest.fixture(autouse=True)
def _xla_optimisation(request):
    if OPTIMISE or request.node.get_closest_marker("optimised") is None:
        yield
        return
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", True)


def _memory_maps() -> int:
    """How many memory mappings this process holds (Linux; 0 elsewhere)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


def _map_limit() -> int:
    """The kernel's limit on a process's memory mappings (`vm.max_map_count`, 65530 by
    default)."""
    try:
        return int(pathlib.Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return 65530


# Each program XLA compiles for the CPU takes four to six memory mappings (its code and data)
# until JAX lets it go, and a test worker compiles thousands: one that had run test_rig.py and
# three more files held 65,341 mappings, the kernel's limit, when XLA's next compile could not
# map its code and crashed the worker (a segfault; CI at ea868b0 and five fresh-clone runs
# since). Past a third of the limit, the compiled programs are let go after a test (JAX's
# `clear_caches`, which frees most of them; tests that need theirs compile them again).
_MAPS_CLEARED_AT = _map_limit() // 3


@pytest.fixture(autouse=True)
def _let_go_of_programs():
    yield
    if _memory_maps() > _MAPS_CLEARED_AT:
        jax.clear_caches()


DATA = pathlib.Path(
    os.environ.get(
        "MVCALIB_DATA", pathlib.Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
    )
).resolve()


def data_dir(name: str) -> pathlib.Path:
    path = DATA / name
    if not path.is_dir():
        pytest.skip(f"real data set {name!r} not found under MVCALIB_DATA={DATA}")
    return path


# OpenPTV's cavity photographs: the focal guess its clicks need, principal distance 70 mm over
# 12 um pixels (ptv.par, cam*.ori).
CAVITY_FOCAL = 70.0 / 0.012


@functools.cache
def cavity(**detect):
    """OpenPTV's cavity: `(target, views)` with, per camera, `(image, detection, labels)`: the
    photo's dots (`detect_dots` with `detect`'s options) matched from OpenPTV's own clicked
    points (`man_ori`). Skips without the data, or without `imagecodecs` for its TIFFs."""
    import mvcalib as mc

    skimage_io = pytest.importorskip("skimage.io")
    root = data_dir("openptv_cavity")
    target = mc.targets.from_file(root / "cal" / "target_on_a_side.txt")
    ids, clicks = mc.io.load_openptv_clicks(
        root / "parameters" / "man_ori.par", root / "parameters" / "man_ori.dat"
    )
    views = []
    for c in range(4):
        try:
            image = skimage_io.imread(root / "cal" / f"cam{c + 1}.tif")
        except ValueError as error:  # LZW-compressed TIFF without imagecodecs
            pytest.skip(f"cannot read cam{c + 1}.tif: {error}")
        detection = mc.detect_dots(image, dark_dots=False, **detect)
        labels = mc.match_dots(detection, target, (clicks[c], ids[c]), focal=CAVITY_FOCAL)
        views.append((image, detection, labels))
    return target, views


def box_corners_with_wild_dots(n_cameras: int, key: int = 0):
    """`random_rig` of `n_cameras` box-corner cameras (`key`, 0.3 px of noise) with two of each
    camera's dots moved by 50 px: `(rig, world, pixels, mask, clean)`, `clean` the mask without
    the moved dots."""
    import mvcalib as mc

    rig = mc.synthetic.random_rig(
        jax.random.key(key), n_cameras, mc.targets.box_corner_grid(4), noise=0.3
    )
    world, pixels, mask = (np.asarray(a) for a in (rig.world, rig.pixels, rig.mask))
    pixels, clean, rng = pixels.copy(), mask.copy(), np.random.default_rng(key)
    for c in range(n_cameras):
        wild = rng.choice(np.flatnonzero(mask[c]), 2, replace=False)
        angle = rng.uniform(0, 2 * np.pi, 2)
        pixels[c, wild] += 50 * np.c_[np.cos(angle), np.sin(angle)]
        clean[c, wild] = False
    return rig, world, pixels, mask, clean


def central_difference_check(f, x, *, eps=1e-6, rtol=1e-5, atol=1e-8, seed=0):
    """Compare jax.jvp of scalar-or-array `f` at `x` along a random direction with central
    differences (float64)."""
    rng = np.random.default_rng(seed)
    v = rng.standard_normal(np.shape(x))
    _, jvp = jax.jvp(f, (x,), (jax.numpy.asarray(v, x.dtype),))
    fd = (np.asarray(f(x + eps * v)) - np.asarray(f(x - eps * v))) / (2 * eps)
    np.testing.assert_allclose(np.asarray(jvp), fd, rtol=rtol, atol=atol)
    assert np.all(np.isfinite(np.asarray(jvp)))
    return np.asarray(jvp)
