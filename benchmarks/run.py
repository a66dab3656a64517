"""The benchmark suite: every benchmark in one run, one summary table, JSON and a plot.

Runs, each with its own `--quick` (or `--smoke`) and in this order: `bound.py` (this machine's
FLOP/s and bandwidth), `dlt.py` (DLT + decomposition against NumPy and OpenCV), `refine.py`
(against SciPy least_squares), `triangulate.py` (against NumPy and OpenCV), `detect.py` (against
OpenCV's blob detector), `fisheye.py` (the fisheye lens against `cv2.fisheye`: projection,
unprojection, planar calibration, pose refinement), `planar.py` (Zhang's planar calibration of
one pinhole camera against `cv2.calibrateCamera`, 10-80 views), `startup.py` (compile times,
the demo's cold start) and `first_call.py` (fresh processes to the first answer against
OpenCV's loop, the break-even), then prints one table of every path of the headline settings:
time per camera / point / image, the peers' time over mvcalib's, accuracy at the same
settings, compile time, peak memory and the distance from the physical bound. Every number
comes from this run; each script also writes its own JSON to `benchmarks/results/`, the suite
adds `summary.json` and `summary.png`.

Run from the repository root:

    python -m benchmarks [--quick | --smoke] [--results DIR] [--only dlt,triangulate]
    python benchmarks/run.py [--quick]

`--quick` is the short version (a few DLT cells, short rounds, slow peers on a subset of the
cameras); the wall and CPU time of every part are printed at the end (mvcalib's compilations
and the demo's cold start take most of it). `--smoke` is a tiny run (bound, DLT and
triangulation at toy sizes) for the test that the suite works.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import sys
import time
import traceback
from pathlib import Path

PARTS = (
    "bound",
    "dlt",
    "refine",
    "triangulate",
    "detect",
    "fisheye",
    "planar",
    "startup",
    "first_call",
)
SMOKE_PARTS = ("bound", "dlt", "triangulate")


def _flags(name: str, mode: str) -> list[str]:
    flags = {"quick": ["--quick"], "smoke": ["--smoke"], "full": []}[mode]
    if name == "bound":
        flags = [*flags, "--no-xla"]  # dlt.py and triangulate.py report XLA's costs themselves
    if name == "startup" and mode == "quick":
        # The entry points compile in dlt.py, refine.py and triangulate.py already; a quick run
        # takes their compile times from there instead of compiling them all again.
        flags = [*flags, "--entry-points", ""]
    return flags


def compile_rows(payloads) -> list[dict]:
    """Compile times: startup.py's, and (quick) those measured by refine.py / triangulate.py."""
    rows = list(payloads.get("startup", {}).get("compile", []))
    measured = {r["entry_point"] for r in rows}
    if "dlt" in payloads:
        cell = next(
            c
            for c in payloads["dlt"]["results"]
            if [c["n_cameras"], c["n_points"]] == payloads["dlt"]["settings"]["headline"]
        )
        setting = f"{cell['n_cameras']} cameras x {cell['n_points']} points (dlt.py)"
        found = {p["path"]: p for p in cell["paths"]}
        for entry, path in (
            ("mc.calibrate", "calibrate()"),
            ("mc.dlt + Camera.from_projection (one jit)", "mvcalib"),
        ):
            if entry not in measured and path in found:
                p = found[path]
                rows.append(
                    {
                        "entry_point": entry,
                        "setting": setting,
                        "first_call_s": p["first_call_s"],
                        "warm_call_s": p["warm_call_s"],
                        "compile_s": p["compile_s"],
                    }
                )
        decomposition = payloads["dlt"].get("decomposition")
        if "mc.Camera.from_projection" not in measured and decomposition:
            rows.append(
                {
                    "entry_point": "mc.Camera.from_projection",
                    "setting": f"{decomposition['n_cameras']} cameras (dlt.py)",
                    "first_call_s": None,
                    "warm_call_s": None,
                    "compile_s": decomposition["mvcalib_compile_s"],
                }
            )
    if "mc.refine" not in measured and "refine" in payloads:
        r = payloads["refine"]["results"][-1]
        first = r["mvcalib_first_call_s"]
        rows.append(
            {
                "entry_point": "mc.refine",
                "setting": f"{r['n_cameras']} cameras x {r['n_points']} points (refine.py)",
                "first_call_s": first,
                "warm_call_s": first - r["mvcalib_compile_s"],
                "compile_s": r["mvcalib_compile_s"],
            }
        )
    if "mc.triangulate" not in measured and "triangulate" in payloads:
        r = payloads["triangulate"]["results"][0]
        rows.append(
            {
                "entry_point": "mc.triangulate",
                "setting": f"{r['points_timed']} points x {r['views']} views (triangulate.py)",
                "first_call_s": None,
                "warm_call_s": None,
                "compile_s": r["compile_s"],
            }
        )
    return rows


# ---------------------------------------------------------------------------------- report
def _cell(x, spec, width):
    return f"{'—':>{width}}" if x is None else f"{x:>{width}{spec}}"


def print_summary(rows, payloads, wall, mode, parts):
    limits = payloads["bound"]["limits"] if "bound" in payloads else None
    print("\n" + "=" * 118)
    print(f"SUMMARY ({mode} run; every figure from this run)")
    if limits:
        machine = payloads["bound"]["machine"]
        load = machine.get("load_average")
        print(
            f"machine: {machine['processor']}, {machine['cpu_count']} CPUs, measured "
            f"{limits['flop_per_s'] / 1e9:.1f} GFLOP/s (float64 matmul) and "
            f"{limits['bandwidth_bytes_per_s'] / 1e9:.1f} GB/s (copy, read + write)"
            + (f"; load average at start {load[0]:.1f}" if load else "")
        )
    header = (
        f"{'benchmark':<21}{'setting':<22}{'path':<34}{'time':>10}{'':<7}{'peer/':>8}"
        f"{'compile':>8}{'peak MB':>9}{'x bound':>8}  accuracy"
    )
    print(header)
    print(f"{'':<21}{'':<22}{'':<34}{'':>10}{'':<7}{'mvcalib':>8}{'s':>8}")
    print("-" * 118)
    previous = None
    for r in rows:
        same = (r["benchmark"], r["setting"]) == previous
        previous = (r["benchmark"], r["setting"])
        unit = {"camera": "µs/cam", "point": "µs/pt", "image": "ms/img"}[r["unit"]]
        value = r["us"] / 1e3 if r["unit"] == "image" else r["us"]
        kind = {"xla": "x", "tracemalloc": "t"}.get(r["peak_kind"], " ")
        print(
            f"{'' if same else r['benchmark']:<21}{'' if same else r['setting']:<22}"
            f"{r['path'][:33]:<34}{value:>10.4g} {unit:<6}{r['peer_over_mvcalib']:>8.2f}"
            f"{_cell(r['compile_s'], '.2f', 8)}{_cell(r['peak_mb'], '.3g', 8)}{kind}"
            f"{_cell(r['x_bound'], '.0f', 8)}  {r['accuracy']}"
        )
    print("-" * 118)
    print("peer/mvcalib: the path's time over mvcalib's at the same setting (> 1: mvcalib faster;")
    print("  triangulation's 2-view paths against mvcalib on 2 views, numpy GN against mvcalib")
    print("  refine). compile: first call - warm call. peak MB: x = XLA memory analysis of the")
    print("  compiled call (arguments + outputs +")
    print("  temporaries), t = tracemalloc peak of one call (NumPy buffers + Python objects).")
    print("  x bound: time / (max(FLOPs / FLOP/s, bytes / bandwidth)) of bound.py's counts.")
    print("  '(n timed)': a per-camera loop timed on its first n cameras, reported per camera.")
    if "dlt" in payloads:
        grid = payloads["dlt"]["results"]
        print("\nDLT + decomposition grid, mvcalib µs/camera (peer/mvcalib: numpy batched, loop):")
        for cell in grid:
            p = {x["path"]: x for x in cell["paths"]}
            print(
                f"  C={cell['n_cameras']:<6} N={cell['n_points']:<5} "
                f"{p['mvcalib']['us_per_camera']:>9.3f} µs  "
                f"batched {p['numpy batched']['peer_over_mvcalib']:>6.2f}  "
                f"loop {p['numpy loop']['peer_over_mvcalib']:>7.1f}  "
                f"x bound {p['mvcalib']['x_bound']:>6.1f}  "
                f"max|ΔRMS| vs SVD {p['mvcalib']['rms_max_abs_diff_vs_numpy_svd_px']:.1e} px"
            )
    compiles = compile_rows(payloads)
    if compiles:
        print("\njit compile time (first call - warm call):")
        for r in compiles:
            print(f"  {r['entry_point']:<27}{r['compile_s']:>7.2f} s  ({r['setting']})")
    if "startup" in payloads:
        for r in payloads["startup"]["cold_start"]:
            print(
                f"cold start `python -m mvcalib demo`, cache {r['cache']}: {r['exit_s']:.1f} s "
                f"to exit ({r['first_output_s']:.1f} s to first output)"
            )
    if "first_call" in payloads:
        print_first_call(payloads["first_call"])
    print(f"\nsuite wall time {wall:.1f} s ({mode}); per part, wall / CPU (user + sys, this")
    print("process and its children; CPU > wall: both cores; wall > CPU: waiting for a busy CPU):")
    print(
        "  "
        + ", ".join(f"{n} {t['wall_time_s']:.0f} / {t['cpu_s']:.0f} s" for n, t in parts.items())
    )


def print_first_call(payload):
    """first_call.py's rows at their largest C, and its break-even."""
    rows = payload["results"]
    largest = {r["task"]: r for r in sorted(rows, key=lambda r: r["n_cameras"])}
    print("fresh process to first answer (import + compile + run, caches off):")
    for task, r in largest.items():
        timed = r.get("cameras_timed", r["n_cameras"])
        print(
            f"  {task:<12} C={r['n_cameras']:<5} {r['first_answer_s']:>6.1f} s "
            f"(import {r['import_s']:.1f} s)"
            + (f", {timed} cameras timed" if timed < r["n_cameras"] else "")
        )
    even = payload.get("break_even")
    if even:
        C0, C1 = even["opencv"]["through"]
        star = lambda c: "none" if c is None else f"{c:.0f} cameras"  # noqa: E731
        print(
            f"  break-even of refine=True against the OpenCV loop: C* = {star(even['C_star'])} "
            f"(lines through C = {C0}, {C1}, "
            f"{'measured' if even.get('measured') else 'extrapolated'}); "
            f"{star(even['C_star_warm_slope'])} with mvcalib's "
            "warm slope"
        )


def plot(payloads, path):
    """summary.png: DLT time per camera against C (N = 19) beside the bound, and every peer's
    time over mvcalib's at the headline settings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5.5))
    if "dlt" in payloads:
        cells = [c for c in payloads["dlt"]["results"] if c["n_points"] == 19]
        if not cells:
            n = payloads["dlt"]["results"][0]["n_points"]
            cells = [c for c in payloads["dlt"]["results"] if c["n_points"] == n]
        n_points = cells[0]["n_points"]
        Cs = [c["n_cameras"] for c in cells]
        for name in [p["path"] for p in cells[0]["paths"]]:
            xs, ys = [], []
            for c in cells:
                for p in c["paths"]:
                    if p["path"] == name:
                        xs.append(c["n_cameras"])
                        ys.append(p["us_per_camera"])
            style = "o-" if name == "mvcalib" else ".--"
            left.loglog(xs, ys, style, label=name, lw=2.5 if name == "mvcalib" else 1)
        bounds = [c["bound_us_per_camera"] for c in cells]
        left.loglog(Cs, bounds, "k*:", label="physical bound (bound.py)")
        left.set_xticks(Cs, [str(C) for C in Cs])
        left.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        left.set_xlabel("cameras C")
        left.set_ylabel("µs per camera")
        left.set_title(f"DLT + decomposition, N = {n_points} points")
        left.legend(fontsize=8)
        left.grid(True, which="both", alpha=0.3)
    labels, ratios = [], []
    for name in ("dlt", "refine", "triangulate", "detect", "fisheye", "planar"):
        for r in payloads.get(name, {}).get("summary", []):
            if not r["path"].startswith("mvcalib") and r["path"] != "calibrate()":
                labels.append(f"{r['benchmark']} ({r['setting']}): {r['path']}")
                ratios.append(r["peer_over_mvcalib"])
    if ratios:
        y = range(len(ratios))
        colours = ["tab:green" if v >= 1 else "tab:red" for v in ratios]
        right.barh(list(y), ratios, color=colours)
        for i, v in zip(y, ratios):
            right.annotate(
                f"{v:.3g}x",
                (v, i),
                xytext=(3, 0),
                textcoords="offset points",
                va="center",
                fontsize=7,
            )
        right.set_yticks(list(y))
        right.set_yticklabels(labels, fontsize=7)
        right.set_xscale("log")
        right.axvline(1.0, color="k", lw=1)
        right.invert_yaxis()
        right.set_xlabel("peer time / mvcalib time (> 1: mvcalib faster)")
        right.set_title("mvcalib against each peer")
        right.grid(True, axis="x", which="both", alpha=0.3)
    first = next(iter(payloads.values()), {})
    machine = first.get("machine") or {}
    load = machine.get("load_average")
    fig.suptitle(
        f"python -m benchmarks ({first.get('mode', '?')}), {first.get('date', '')}, "
        f"{machine.get('cpu_count')} CPUs, jax {machine.get('jax')}"
        + (f", load average {load[0]:.1f} at the start" if load else "")
        + "; figures from this one run",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"plot written to {path}")


# ---------------------------------------------------------------------------------- main
def replot(common) -> int:
    """The summary table and plot again, from the JSON files of the last run."""
    summary = json.loads(common.results_path("summary.json").read_text())
    payloads = {
        name: json.loads(common.results_path(f"{name}.json").read_text())
        for name in summary["parts"]
        if name not in summary.get("failed", {})
    }
    print_summary(
        summary["summary"], payloads, summary["wall_time_s"], summary["mode"], summary["parts"]
    )
    plot(payloads, common.results_path(summary["plot"]))
    return 0


def _cpu_seconds() -> float:
    """User + system CPU time of this process and its finished children."""
    own, children = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="every benchmark's --quick")
    group.add_argument("--smoke", action="store_true", help="tiny sizes (the smoke test)")
    parser.add_argument("--results", type=Path, help="directory for the JSON and the plot")
    parser.add_argument("--only", help=f"comma-separated subset of {','.join(PARTS)}")
    parser.add_argument(
        "--replot",
        action="store_true",
        help="run nothing: print the summary table and redraw summary.png from the JSON of the "
        "last run in the results directory",
    )
    args = parser.parse_args(argv)
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    parts = SMOKE_PARTS if args.smoke else PARTS
    if args.only:
        parts = tuple(p for p in PARTS if p in args.only.split(","))

    common = importlib.import_module("benchmarks._common")
    if args.results:
        common.RESULTS_DIR = args.results.resolve()
    common.RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    if args.replot:
        return replot(common)

    wall = time.perf_counter()
    payloads, part_times, failed = {}, {}, {}
    for name in parts:
        print(f"\n{'#' * 30} {name} {' '.join(_flags(name, mode))} {'#' * 30}\n", flush=True)
        start, cpu = time.perf_counter(), _cpu_seconds()
        try:
            module = importlib.import_module(f"benchmarks.{name}")
            payloads[name] = module.main(_flags(name, mode))
        except Exception:  # report it, run the other parts, fail at the end
            traceback.print_exc()
            failed[name] = traceback.format_exc(limit=-3)
        part_times[name] = {
            "wall_time_s": time.perf_counter() - start,
            "cpu_s": _cpu_seconds() - cpu,
        }
        sys.stdout.flush()

    rows = [
        r
        for name in ("dlt", "refine", "triangulate", "detect", "fisheye", "planar")
        for r in payloads.get(name, {}).get("summary", [])
    ]
    wall = time.perf_counter() - wall
    print_summary(rows, payloads, wall, mode, part_times)
    plot_path = common.results_path("summary.png")
    plot(payloads, plot_path)
    summary = {
        "benchmark": "suite",
        "mode": mode,
        "command": "python -m benchmarks" + {"full": "", "quick": " --quick"}.get(mode, " --smoke"),
        "machine": next(iter(payloads.values()), {}).get("machine"),
        "limits": payloads.get("bound", {}).get("limits"),
        "parts": part_times,
        "skipped": [p for p in PARTS if p not in parts],
        "failed": failed,
        "summary": rows,
        "dlt_grid": payloads.get("dlt", {}).get("results"),
        "compile": compile_rows(payloads),
        "cold_start": payloads.get("startup", {}).get("cold_start"),
        "first_call": payloads.get("first_call", {}).get("break_even"),
        "plot": plot_path.name,
        "wall_time_s": wall,
    }
    path = common.results_path("summary.json")
    path.write_text(json.dumps(summary, indent=2) + "\n")
    print(f"summary written to {path}")
    if failed:
        print(f"FAILED: {', '.join(failed)} (tracebacks above and in summary.json)")
    return 1 if failed else 0


if __name__ == "__main__" and not __package__:
    # `python benchmarks/run.py`: run the package's module, so that the scripts import as
    # `benchmarks.*` exactly as under `python -m benchmarks`.
    sys.path[0] = os.fspath(Path(__file__).resolve().parents[1])
    sys.exit(importlib.import_module("benchmarks.run").main())
