"""Start-up costs: jit compile time of the main entry points, and the demo's cold start.

What is measured
----------------
- **Compile time** of `mc.calibrate`, `mc.dlt`, `mc.Camera.from_projection`, `mc.refine` and
  `mc.triangulate`, each called as a user would (eagerly; each compiles its own kernels) on a
  small problem: 4 cameras seeing the 19-dot target (triangulation: 1000 points in 4 views).
  JAX's in-memory caches are cleared (`jax.clear_caches()`) before each entry point, so that its
  first call traces and compiles as in a fresh process; compile = first call - median of 3 warm
  calls. The persistent compilation cache is not used here (this process does not enable it).
- **Cold start**: wall time from launching `python -m mvcalib demo` (a subprocess) to its first
  line of output and to its exit, with JAX's persistent compilation cache off
  (`MVCALIB_COMPILATION_CACHE=0`) and on, in a fresh temporary directory: the first run fills
  it, the second uses it. `--quick` skips the cache-off run: the run that fills an empty cache
  has no cache hits either, so it is the cold start without a cache plus the writing of it.

Run from the repository root: `python benchmarks/startup.py [--quick]`; results go to
`benchmarks/results/startup.json`.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

try:
    from ._common import first_and_warm, machine_info, results_path, write_results
except ImportError:  # run as a script
    from _common import first_and_warm, machine_info, results_path, write_results

import mvcalib as mc  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


ENTRY_POINTS = (
    "mc.calibrate",
    "mc.dlt",
    "mc.Camera.from_projection",
    "mc.refine",
    "mc.triangulate",
)


def compile_times(names=ENTRY_POINTS) -> list[dict]:
    """First call - warm call of each entry point, after clearing JAX's in-memory caches."""
    if not names:
        return []
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4, noise=0.3)
    world, pixels, mask = rig.world, rig.pixels, rig.mask
    seed = mc.calibrate(world, pixels, mask).cameras
    P = mc.dlt(world, pixels, mask)
    points = np.random.default_rng(0).uniform(0.0, 160.0, (1000, 3))
    tri_px = jax.block_until_ready(rig.cameras.project(points))
    entry_points = {
        "mc.calibrate": lambda: mc.calibrate(world, pixels, mask),
        "mc.dlt": lambda: mc.dlt(world, pixels, mask),
        "mc.Camera.from_projection": lambda: mc.Camera.from_projection(P),
        "mc.refine": lambda: mc.refine(seed, world, pixels, mask),
        "mc.triangulate": lambda: mc.triangulate(rig.cameras, tri_px),
    }
    rows = []
    for name in names:
        fn = entry_points[name]
        jax.clear_caches()
        first, warm, _ = first_and_warm(lambda fn=fn: jax.block_until_ready(fn()))
        rows.append(
            {
                "entry_point": name,
                "setting": "4 cameras x 19 points"
                if name != "mc.triangulate"
                else "1000 x 4 views",
                "first_call_s": first,
                "warm_call_s": warm,
                "compile_s": first - warm,
            }
        )
    return rows


def demo_run(cache: str) -> dict:
    """Launch `python -m mvcalib demo` with MVCALIB_COMPILATION_CACHE=cache; time it."""
    env = dict(os.environ, MVCALIB_COMPILATION_CACHE=cache)
    start = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mvcalib", "demo"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    proc.stdout.readline()
    first_output = time.perf_counter() - start
    _, stderr = proc.communicate()
    total = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"`python -m mvcalib demo` failed:\n{stderr}")
    return {"first_output_s": first_output, "exit_s": total}


def cold_start(*, quick: bool) -> list[dict]:
    rows = []
    if not quick:
        rows.append({"cache": "off"} | demo_run("0"))
    with tempfile.TemporaryDirectory(prefix="mvcalib-jax-cache-") as directory:
        rows.append({"cache": "empty (filled by this run)"} | demo_run(directory))
        n_files = sum(len(files) for _, _, files in os.walk(directory))
        rows.append({"cache": f"warm ({n_files} entries)"} | demo_run(directory))
    return rows


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="no cache-off demo run")
    parser.add_argument("--smoke", action="store_true", help="compile times only, no demo")
    parser.add_argument(
        "--entry-points",
        default=",".join(ENTRY_POINTS),
        help="comma-separated subset of the entry points to compile (the suite measures the "
        "others in their own benchmarks with --quick)",
    )
    args = parser.parse_args(argv)
    wall = time.perf_counter()
    info = machine_info()
    compiles = compile_times([n for n in ENTRY_POINTS if n in args.entry_points.split(",")])
    if compiles:
        print("jit compile time of the entry points (first call - warm call):")
    for r in compiles:
        print(
            f"  {r['entry_point']:<27}{r['compile_s']:>7.2f} s   (first {r['first_call_s']:.2f} s, "
            f"warm {1e3 * r['warm_call_s']:.2f} ms; {r['setting']})"
        )
    starts = [] if args.smoke else cold_start(quick=args.quick)
    if starts:
        print("\ncold start of `python -m mvcalib demo` (subprocess, wall clock):")
        for r in starts:
            print(
                f"  cache {r['cache']:<28} first output {r['first_output_s']:>6.1f} s, "
                f"exit {r['exit_s']:>6.1f} s"
            )
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")
    return write_results(
        results_path("startup.json"),
        "startup",
        quick=args.quick or args.smoke,
        machine=info,
        wall_time_s=wall,
        compile=compiles,
        cold_start=starts,
    )


if __name__ == "__main__":
    main()
