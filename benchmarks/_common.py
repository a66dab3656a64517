"""What every benchmark script shares: interleaved timing and a record of the machine."""

from __future__ import annotations

import datetime
import importlib.metadata
import json
import os
import platform
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

# Where every script writes its JSON; `run.py --results DIR` (and the smoke test) move it.
RESULTS_DIR = Path(__file__).resolve().parent / "results"

# A script run as `python benchmarks/x.py` has benchmarks/ first on `sys.path`, and `import
# mvcalib` found the installed package: an editable install of another checkout, so that an A/B
# of two worktrees measured one checkout's code twice (2026-12-07). The scripts import this
# module before mvcalib: the repository's own root goes first.
_ROOT = str(Path(__file__).resolve().parents[1])
if __name__ == "_common" and _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)


def results_path(name: str) -> Path:
    """`RESULTS_DIR / name`, looked up at call time so that the suite can redirect it."""
    return RESULTS_DIR / name


def measure(fns, *, min_time, rounds, warmup=0.03):
    """Time warm (already compiled) callables in interleaved blocks of back-to-back calls.

    In each of `rounds` rounds every callable runs for at least `min_time / rounds` seconds (at
    least one call), so each gets at least `rounds` calls lasting `min_time` in all. Interleaving
    makes slow drifts of the machine's speed (common on shared or virtual CPUs) hit every
    implementation alike instead of whichever ran last. Each block starts with untimed calls for
    `warmup` seconds (at least one call if `warmup > 0`), so that the timed calls run with warm
    caches and worker threads: after the other paths' blocks, mvcalib's DLT of 4096 cameras
    (~7 ms a call) took up to 3x its time for its first few calls (5.1, 3.5, 3.0, 2.6, then 1.6
    µs per camera), which moved its median by a fifth, and its refinement of 256 cameras took
    72-95 ms on the first call after SciPy's loop against 60-75 for the next ones. Returns, per
    name, the median and quartiles of the per-call times (seconds) and the calls.
    """
    times = {name: [] for name in fns}
    block = min_time / rounds
    for _ in range(rounds):
        for name, fn in fns.items():
            start = time.perf_counter()
            while time.perf_counter() - start < warmup:
                fn()
            start = time.perf_counter()
            while True:
                t0 = time.perf_counter()
                fn()
                t1 = time.perf_counter()
                times[name].append(t1 - t0)
                if t1 - start >= block:
                    break
    stats = {}
    for name, ts in times.items():
        q1, median, q3 = np.percentile(ts, [25, 50, 75])
        stats[name] = {"median": median, "q1": q1, "q3": q3, "repeats": len(ts)}
    return stats


def machine_info(*packages: str) -> dict:
    """Platform, CPUs, JAX backend and devices, and the versions of `packages` (+ jax, mvcalib)."""
    import jax

    def version(name):
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            return None

    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        **{name: version(name) for name in ("jax", "jaxlib", "mvcalib", "numpy", *packages)},
        "mvcalib_path": str(Path(sys.modules["mvcalib"].__file__).parent)
        if "mvcalib" in sys.modules
        else None,  # (which checkout was measured)
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        # The machine is shared: how busy it was when the run started (1, 5, 15 min averages).
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def opencv_run(doc: str, argv, smoke: str) -> tuple[str, dict]:
    """A comparison with OpenCV's command line and machine record: the mode (`"full"`, or
    `"quick"` / `"smoke"` from `argv`; `smoke` says what `--smoke` does) and `machine_info` with
    OpenCV's version and JAX's compilation cache (a cached first call is no compile)."""
    import argparse

    import cv2
    import jax

    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="short timing rounds")
    group.add_argument("--smoke", action="store_true", help=smoke)
    args = parser.parse_args(argv)
    info = machine_info("opencv-python-headless", "optimistix")
    info["opencv"] = cv2.__version__
    info["jax_compilation_cache_dir"] = jax.config.jax_compilation_cache_dir
    return "smoke" if args.smoke else "quick" if args.quick else "full", info


def first_and_warm(fn, *, warm_calls: int = 3):
    """(first call's wall time, median of `warm_calls` further calls, first call's output).

    For a jit-compiled `fn` at a new shape, first - warm is the trace + compile time.
    """
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    warm = []
    for _ in range(warm_calls):
        t0 = time.perf_counter()
        fn()
        warm.append(time.perf_counter() - t0)
    return first, float(np.median(warm)) if warm else float("nan"), out


def tracemalloc_peak_mb(fn) -> float:
    """Peak of the memory traced by `tracemalloc` during one call of `fn`, in MB.

    Python objects and NumPy arrays (NumPy reports its data buffers to tracemalloc; OpenCV
    returns NumPy arrays); not memory that C/C++ libraries allocate for their own work.
    """
    tracemalloc.start()
    try:
        fn()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return peak / 2**20


def xla_peak_mb(jitted, *args) -> float:
    """XLA's own memory analysis of `jitted` compiled for `args`, in MB: arguments + outputs +
    temporaries (`peak_memory_in_bytes` where the backend reports it)."""
    stats = jitted.lower(*args).compile().memory_analysis()
    if stats is None:
        return float("nan")
    peak = getattr(stats, "peak_memory_in_bytes", 0) or (
        stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes
    )
    return peak / 2**20


def write_results(path, benchmark: str, *, quick: bool, machine: dict, **sections) -> dict:
    """Write one run's results as JSON: which benchmark, when, quick or full, on what machine,
    then the script's own `sections` (settings, wall time, results...)."""
    payload = {
        "benchmark": benchmark,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "mode": "quick" if quick else "full",
        "machine": machine,
        **sections,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"results written to {path}")
    return payload
