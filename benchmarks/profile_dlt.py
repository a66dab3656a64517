"""Where the batched DLT + decomposition spends its time: XLA's kernels by stage.

What is measured
----------------
The benchmark's headline call (`dlt.py`: `Camera.from_projection(dlt(...))`, 4096 cameras of
the box corner's 19 points, 0.3 px noise) runs under `jax.profiler` for `--calls` warm calls.
Every kernel XLA's CPU runtime executes (a fusion, a library call, a copy) is attributed to the
stage whose `jax.named_scope` it came from (`mvcalib/_dlt.py`: moments, eigen, cameras; the
decomposition is `_decompose`), through the `op_name` of the compiled program's instructions.
Printed per stage: kernel time per camera, kernels per call, and the largest kernels. The sum
of kernel times is compared with the wall time of the calls: XLA runs this program's kernels
one after another, so the two agree to a few per cent when the machine is quiet.

This is a tool for working on the DLT's speed, not part of the suite (`python -m benchmarks`),
and writes no results. Run from the repository root: `python benchmarks/profile_dlt.py`.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import re
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

try:
    from . import dlt
except ImportError:  # run as a script
    import dlt

STAGES = ("moments", "eigen", "cameras", "_decompose")


def stage_of(op_name: str) -> str:
    """The stage a kernel's `op_name` belongs to (its first path component that names one)."""
    for part in op_name.split("/"):
        for stage in STAGES:
            if part == stage or part == f"jit({stage})":
                return stage.lstrip("_")
    return "other"


def op_names(hlo_text: str) -> dict[str, str]:
    """Instruction name -> `op_name` of every instruction of an optimised HLO module's text."""
    names = {}
    for m in re.finditer(r"^\s+%?([\w.\-]+) = .*?op_name=\"([^\"]*)\"", hlo_text, re.M):
        names.setdefault(m.group(1), m.group(2))
    return names


def kernel_events(trace_dir: Path) -> list[dict]:
    """The complete ("X") events of the Perfetto trace that `jax.profiler` wrote."""
    (path,) = trace_dir.rglob("*.trace.json.gz")
    with gzip.open(path) as f:
        return [e for e in json.load(f)["traceEvents"] if e.get("ph") == "X"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=4096)
    parser.add_argument("--calls", type=int, default=20, help="profiled warm calls")
    args = parser.parse_args(argv)
    C, N = args.cameras, 19
    world, pixels, mask = dlt.make_problem(dlt.make_cameras(C), N, C)
    inputs = [jax.numpy.asarray(a) for a in (world, pixels, mask)]
    # the program profiled is the one whose instructions name the kernels (compiled once)
    compiled = dlt.mvcalib_calibrate.lower(*inputs).compile()
    names = op_names(compiled.as_text())

    def call():
        return jax.block_until_ready(compiled(*inputs))

    for _ in range(2 * args.calls):  # compiled, warm caches and threads
        call()
    with tempfile.TemporaryDirectory() as tmp:
        jax.profiler.start_trace(tmp, create_perfetto_trace=True)
        start = time.perf_counter()
        for _ in range(args.calls):
            call()
        wall = (time.perf_counter() - start) / args.calls
        jax.profiler.stop_trace()
        events = kernel_events(Path(tmp))

    per_stage = collections.defaultdict(float)
    count = collections.Counter()
    kernels = collections.defaultdict(float)
    for e in events:
        if e["name"] in names:
            stage = stage_of(names[e["name"]])
            per_stage[stage] += e["dur"] / args.calls
            count[stage] += 1 / args.calls
            kernels[stage, e["name"]] += e["dur"] / args.calls
    total = sum(per_stage.values())
    print(f"DLT + decomposition, {C} cameras x {N} points: {args.calls} calls profiled")
    print(f"wall {1e6 * wall / C:.3f} µs/camera under the profiler; kernels {total / C:.3f}")
    print(f"\n{'stage':<12}{'µs/camera':>10}{'share':>8}{'kernels/call':>14}   largest kernels")
    for stage, us in sorted(per_stage.items(), key=lambda kv: -kv[1]):
        top = sorted(((t, k) for (s, k), t in kernels.items() if s == stage), reverse=True)[:3]
        largest = ", ".join(f"{k} {t / C:.3f}" for t, k in top)
        print(f"{stage:<12}{us / C:>10.3f}{us / total:>8.0%}{count[stage]:>14.0f}   {largest}")


if __name__ == "__main__":
    main()
