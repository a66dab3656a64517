import os
import pathlib

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

# One persistent compilation cache for the whole run, shared by the xdist workers and the
# processes they start (notebook kernels), so that a program is compiled once, not once per
# worker: most of the suite's time is XLA compiling (the written-out DLT, refine's solver).
# Only compilations over half a second are stored; a hit runs the same compiled code.
CACHE = pathlib.Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax"
jax.config.update("jax_compilation_cache_dir", str(CACHE))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(CACHE))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

# The tests check what is computed, not how fast: XLA is asked not to spend time optimising the
# compiled code (LLVM at -O0, no expensive passes), which cuts the suite's compile time by a
# quarter to a third. The benchmarks run fully optimised code; JAX_DISABLE_MOST_OPTIMIZATIONS=0
# runs the tests on it too.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
OPTIMISE = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] != "1"
jax.config.update("jax_disable_most_optimizations", not OPTIMISE)


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "optimised: compile this test's programs fully optimised (its time is spent running "
        "them, e.g. a bundle adjustment of real data, not compiling them)",
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
