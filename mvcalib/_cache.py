"""JAX's persistent compilation cache, for users who want every process after the first to skip
compiling."""

from __future__ import annotations

import os
import pathlib


def default_cache_dir() -> pathlib.Path:
    """`$XDG_CACHE_HOME/mvcalib/jax` (default `~/.cache/mvcalib/jax`)."""
    cache = pathlib.Path(os.environ.get("XDG_CACHE_HOME", pathlib.Path.home() / ".cache"))
    return cache / "mvcalib" / "jax"


def enable_compilation_cache(
    directory: str | os.PathLike | None = None, *, min_compile_time: float = 0.0
) -> pathlib.Path | None:
    """Turn on JAX's persistent compilation cache, so that a program compiled once (by this
    process or an earlier one) is read from disk instead of compiled again.

    mvcalib's programs take a second or more to compile and milliseconds to run; with the
    cache, a new process's first `calibrate` costs its import and a disk read. This is a setting
    of JAX for the whole process (`jax_compilation_cache_dir`), so mvcalib never changes it by
    itself: the command line turns it on (`MVCALIB_COMPILATION_CACHE=0` turns it off there), a
    library user calls this once, after importing JAX.

    **Arguments:**

    - `directory`: where the compiled programs go; default `$XDG_CACHE_HOME/mvcalib/jax`
      (`~/.cache/mvcalib/jax`). Any directory JAX accepts, e.g. one shared by several machines
      of the same kind.
    - `min_compile_time`: programs that compile faster than this many seconds are not stored.
      By default every one is: mvcalib's small programs are compiled quickly (`_buckets.jit`),
      but a call runs tens of them. With 0.2 s, 4 of a fisheye `calibrate_rig`'s programs were
      stored and a later process's first call took 3.3-3.4 s; with 0, 71 programs (1.1 MB) and
      2.3-2.4 s (a fisheye user's trial; 2 cameras, 30 frames; the process that fills the cache
      0.2 s slower).

    **Returns:** the directory, or None if it could not be created (a read-only home: the
    process then runs without the cache).

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> path = mc.enable_compilation_cache()  # doctest: +SKIP
    >>> path  # doctest: +SKIP
    PosixPath('/home/me/.cache/mvcalib/jax')

    ```

    (Skipped as a doctest, which would change the setting of the process running the tests;
    `tests/test_readme.py` runs the README's example in a process of its own.)
    """
    import jax

    path = default_cache_dir() if directory is None else pathlib.Path(directory)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time))
    return path
