"""What a new user waits for: a fresh Python process to the first answer, compile included.

What is measured
----------------
Each row is one fresh child process (`subprocess.run([sys.executable, "-c", code])`) with JAX's
persistent compilation cache off (`JAX_ENABLE_COMPILATION_CACHE=false`,
`MVCALIB_COMPILATION_CACHE=0`, no `JAX_COMPILATION_CACHE_DIR`), float64
(`jax.config.update("jax_enable_x64", True)`, as the other benchmarks). The child stamps
`time.perf_counter()` (CLOCK_MONOTONIC on Linux, one clock for every process, so the parent's
launch stamp and the child's stamps subtract) after its imports, after loading its data and after
the answer, and prints them as JSON; the parent also records the process's wall time to its exit.

- **import**: from launching the process to `import jax, numpy, mvcalib` done (interpreter
  start-up included) and JAX's CPU backend started (`jax.devices()`, which the first JAX
  operation would do anyway: so that no row's data step starts it).
- **data**: loading the problem from an `.npz` file as NumPy arrays (not counted: a user's data
  is there already). The parent makes it once with `mc.synthetic.random_rig(jax.random.key(0),
  n_cameras=C, noise=0.3)` (the 19-dot target, 1000 x 1100 px images) and writes it to a
  temporary directory.
- **call**: the entry point called eagerly as a user would, ended by `jax.block_until_ready`:
  validation, tracing, XLA compilation and one run.
  - `calibrate`: `mc.calibrate(world, pixels, mask)` for C = 4, 64, 4096 cameras.
  - `refine`: `mc.calibrate(world, pixels, mask, refine=True)` (DLT seed, then least squares
    over alpha_u alpha_v u0 v0, rotation, translation, k1 k2 p1 p2; zero skew) for the same C.
  - `triangulate`: `mc.triangulate(cameras, pixels)`, 1000 points uniform in [0, 160]^3 mm seen
    by the 4 true cameras of the C = 4 rig (as `startup.py` builds it; the data step builds the
    `mc.Camera` from the file's arrays).
- **first answer** = import + call. After it, not counted, the child calls the entry point a
  second time (**warm**: the run without the compile).
- **the peer, OpenCV**: a fresh process that imports numpy and cv2, loads the same data and
  loops `cv2.calibrateCamera` over the cameras, each from its visible points (float32, what it
  accepts), with `CALIB_USE_INTRINSIC_GUESS` from the *true* camera's K (no DLT of its own to
  pay for: in OpenCV's favour) and `CALIB_FIX_K3`: the model k1 k2 p1 p2 with zero skew that
  `refine=True` fits (as `tests/test_refine.py` checks them against each other), OpenCV's
  default termination criteria. The loop runs on the first `--opencv-cameras` cameras at most
  (default: all of them; `--quick`: 512) and its call time is scaled linearly to C (marked
  `*`; one camera's cost does not depend on the others).

The ratio is OpenCV's first answer over mvcalib's (above 1: mvcalib first). Break-even: a line
t = a + b C is put through each side's first answers at the two neighbouring C between which
the two change order (refine and OpenCV run at C = 4, 64, 1024, 2048, 4096; where they do not
change order, the two largest C, extrapolated: `measured` in the JSON says which), and
mvcalib's fresh-process `calibrate(..., refine=True)` finishes first from C* = (a_mv - a_cv) /
(b_cv - b_mv) cameras on, when b_cv > b_mv (it never does otherwise). The two-point slope of
mvcalib also holds the difference between two compilations, which need not grow with C (it can
be negative); so a second C* takes mvcalib's slope from its warm call at the largest C instead
(b = warm / C, a = first answer - b C there). Before the timed rows, one untimed child imports
everything, so that every row starts with the same warm OS file cache.

Each row is one process, once: on the shared 2-core machine, with others compiling (load average
4-5), one row took from 14 to 26 s between runs and an import from 2 to 5 s; the JSON keeps
each row's load average at launch. The figures hold to tens of per cent, the break-even (a
difference of slopes) to a factor of a few.

`--quick` (about 2-3 minutes against 4-5 for the full run, under that load) runs calibrate at
C = 4096 only, refine and OpenCV at C = 64 and 4096 (the break-even's two) and times OpenCV on
512 cameras at most. `--cameras 4,8` and `--opencv-cameras N` override the sizes (the smoke
test). `--only calibrate,refine,triangulate` picks the tasks (OpenCV runs for calibrate and
refine). Results are printed and written to `benchmarks/results/first_call.json`.

Run from the repository root: `python benchmarks/first_call.py [--quick] [--only refine]`.
"""

from __future__ import annotations

import argparse
import json
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
    from ._common import machine_info, results_path, write_results
except ImportError:  # run as a script
    from _common import machine_info, results_path, write_results

import mvcalib as mc  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

# C per task ("opencv": the peer's rows); the break-even needs refine and opencv at two C, and
# is measured (not extrapolated) where the two cross between two of them
CROSSING = (4, 64, 1024, 2048, 4096)
N_CAMERAS = {
    "full": {"calibrate": (4, 64, 4096), "refine": CROSSING, "opencv": CROSSING},
    "quick": {"calibrate": (4096,), "refine": (64, 4096), "opencv": (64, 4096)},
}
OPENCV_CAMERAS = {"full": None, "quick": 512}  # None: time the loop on every camera
TASKS = ("calibrate", "refine", "triangulate")
NOISE = 0.3  # pixels
IMAGE_SIZE = (1000, 1100)  # width, height: random_rig's default
N_TRIANGULATE = 1000
CAMERA_FIELDS = ("alpha_u", "alpha_v", "u0", "v0", "R", "t", "skew", "dist")

# ---------------------------------------------------------------------------------- children
# Each child prints one line of JSON last: its perf_counter stamps, then what it computed (read
# after the last stamp) so that the parent can check the answer.
MVCALIB_CHILD = """\
import time
t_start = time.perf_counter()
import json
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import mvcalib as mc
jax.devices()
t_import = time.perf_counter()
data = np.load({path!r})
{data}
t_data = time.perf_counter()
out = jax.block_until_ready({call})
t_call = time.perf_counter()
jax.block_until_ready({call})
t_warm = time.perf_counter()
print(json.dumps(dict(
    t_start=t_start, t_import=t_import, t_data=t_data, t_call=t_call, t_warm=t_warm,
    mvcalib=mc.__file__,
    cache_enabled=bool(jax.config.jax_enable_compilation_cache),
    cache_dir=jax.config.jax_compilation_cache_dir,
    {check},
)))
"""

CALIBRATE_DATA = """\
world, pixels, mask = data["world_{C}"], data["pixels_{C}"], data["mask_{C}"]"""
CALIBRATE_CHECK = (
    "ok=int(np.sum(out.ok)), median_rms_px=float(np.nanmedian(np.asarray(out.report.rms)))"
)
TRIANGULATE_DATA = """\
cameras = mc.Camera(**{k[4:]: data[k] for k in data.files if k.startswith("cam_")})
pixels = data["tri_pixels"]"""
TRIANGULATE_CHECK = (
    "ok=int(np.sum(out.ok)), "
    "max_error_mm=float(np.max(np.abs(np.asarray(out.points) - data['tri_points'])))"
)

OPENCV_CHILD = """\
import time
t_start = time.perf_counter()
import json
import numpy as np
import cv2
t_import = time.perf_counter()
data = np.load({path!r})
world = data["world_{C}"].astype(np.float32)
pixels = data["pixels_{C}"][:{n}].astype(np.float32)
mask = data["mask_{C}"][:{n}]
K_true = data["K_{C}"][:{n}]
flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
t_data = time.perf_counter()
rms = []
for p, m, K in zip(pixels, mask, K_true):
    err, K_out, dist, rvecs, tvecs = cv2.calibrateCamera(
        [world[m]], [p[m]], {image_size!r}, K.copy(), np.zeros(5), flags=flags
    )
    rms.append(err)
t_call = time.perf_counter()
print(json.dumps(dict(
    t_start=t_start, t_import=t_import, t_data=t_data, t_call=t_call,
    ok=len(rms), median_rms_px=float(np.median(rms)),
)))
"""


def child_env() -> dict:
    """This process's environment with every persistent compilation cache off."""
    env = dict(os.environ, JAX_ENABLE_COMPILATION_CACHE="false", MVCALIB_COMPILATION_CACHE="0")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    return env


def run_child(code: str) -> dict:
    """Launch `python -c code`; its stamps relative to the launch, and its wall time to exit."""
    load = os.getloadavg()[0]
    launch = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=child_env(), capture_output=True, text=True
    )
    exit_s = time.perf_counter() - launch
    if proc.returncode != 0:
        raise RuntimeError(f"child process failed:\n{code}\n{proc.stderr[-3000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    stamps = {k: out.pop(k) for k in ("t_start", "t_import", "t_data", "t_call")}
    return {
        "startup_s": stamps["t_start"] - launch,
        "import_s": stamps["t_import"] - launch,
        "data_s": stamps["t_data"] - stamps["t_import"],
        "call_s": stamps["t_call"] - stamps["t_data"],
        **({"warm_call_s": out.pop("t_warm") - stamps["t_call"]} if "t_warm" in out else {}),
        "exit_s": exit_s,
        "load_average_1min_at_launch": load,
        **out,
    }


def mvcalib_row(task: str, C: int, path: str) -> dict:
    if task == "triangulate":
        data, call, check = TRIANGULATE_DATA, "mc.triangulate(cameras, pixels)", TRIANGULATE_CHECK
    else:
        data, check = CALIBRATE_DATA.format(C=C), CALIBRATE_CHECK
        refine = ", refine=True" if task == "refine" else ""
        call = f"mc.calibrate(world, pixels, mask{refine})"
    code = MVCALIB_CHILD.format(path=path, data=data, call=call, check=check)
    r = run_child(code)
    if r["cache_enabled"]:
        raise RuntimeError(f"{task}: the child's persistent compilation cache is on")
    return {
        "task": task,
        "call": call,
        "n_cameras": C,
        **r,
        "first_answer_s": r["import_s"] + r["call_s"],
        "compile_s": r["call_s"] - r["warm_call_s"],
    }


def opencv_row(C: int, path: str, at_most: int | None) -> dict:
    n = C if at_most is None else min(C, at_most)
    r = run_child(OPENCV_CHILD.format(path=path, C=C, n=n, image_size=IMAGE_SIZE))
    call = r["call_s"] * C / n
    return {
        "task": "opencv",
        "call": "loop of cv2.calibrateCamera (USE_INTRINSIC_GUESS from the true K, FIX_K3)",
        "n_cameras": C,
        "cameras_timed": n,
        **r,
        "call_timed_s": r["call_s"],
        "call_s": call,
        "first_answer_s": r["import_s"] + call,
    }


# ---------------------------------------------------------------------------------- data
def write_data(path: Path, sizes) -> dict:
    """The rigs of every C and the triangulation problem, as NumPy arrays in one .npz."""
    arrays = {}
    for C in sizes:
        rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=C, noise=NOISE)
        arrays[f"world_{C}"] = np.asarray(rig.world)
        arrays[f"pixels_{C}"] = np.asarray(rig.pixels)
        arrays[f"mask_{C}"] = np.asarray(rig.mask)
        arrays[f"K_{C}"] = np.asarray(rig.cameras.K)
    # triangulation as startup.py builds it: 1000 points seen by the 4 cameras of a C = 4 rig
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4, noise=NOISE)
    points = np.random.default_rng(0).uniform(0.0, 160.0, (N_TRIANGULATE, 3))
    arrays["tri_points"] = points
    arrays["tri_pixels"] = np.asarray(rig.cameras.project(points))
    for name in CAMERA_FIELDS:
        arrays[f"cam_{name}"] = np.asarray(getattr(rig.cameras, name))
    np.savez(path, **arrays)
    return {"visible_fraction": {C: float(np.mean(arrays[f"mask_{C}"])) for C in sizes}}


def warm_file_cache():
    """One untimed child that imports everything, so that every timed row finds the same warm
    OS file cache (the parent imported jax and mvcalib already, not cv2)."""
    code = "import jax, numpy, cv2, mvcalib; jax.devices()"
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=child_env(), check=True)


# ---------------------------------------------------------------------------------- analysis
def line_through(rows, sizes) -> dict:
    """t = a + b C through the first answers at the two C of `sizes`."""
    (C0, t0), (C1, t1) = ((C, rows[C]["first_answer_s"]) for C in sizes)
    b = (t1 - t0) / (C1 - C0)
    return {"a_s": t0 - b * C0, "b_s_per_camera": b, "through": list(sizes)}


def break_even(rows) -> dict | None:
    """Where mvcalib's fresh-process refine (compile included) finishes before OpenCV's loop."""
    refine = {r["n_cameras"]: r for r in rows if r["task"] == "refine"}
    opencv = {r["n_cameras"]: r for r in rows if r["task"] == "opencv"}
    common = sorted(set(refine) & set(opencv))
    if len(common) < 2:
        return None
    # the two neighbouring C between which the first answers change order (the crossing is
    # measured, between them), else the two largest (extrapolated)
    ahead = [refine[C]["first_answer_s"] < opencv[C]["first_answer_s"] for C in common]
    pairs = [i for i in range(len(common) - 1) if ahead[i] != ahead[i + 1]]
    i = pairs[0] if pairs else len(common) - 2
    sizes = common[i : i + 2]
    mv, cv = line_through(refine, sizes), line_through(opencv, sizes)
    out = {"mvcalib_refine": mv, "opencv": cv, "C_star": crossing(mv, cv)}
    out["measured"] = bool(pairs)  # between two measured C, not extrapolated
    # The same from mvcalib's largest row with its slope from that process's warm second call
    # (the run without the compile): the two-point line's slope also holds the difference of
    # two compilations, which need not grow with C.
    big = refine[sizes[-1]]
    b = big["warm_call_s"] / sizes[-1]
    warm = {"a_s": big["first_answer_s"] - b * sizes[-1], "b_s_per_camera": b}
    out["mvcalib_refine_warm_slope"] = warm | {"through": [sizes[-1]]}
    out["C_star_warm_slope"] = crossing(warm, cv)
    return out


def crossing(mv, cv) -> float | None:
    """C* = (a_mv - a_cv) / (b_cv - b_mv) where b_cv > b_mv, else None (no break-even)."""
    if cv["b_s_per_camera"] <= mv["b_s_per_camera"]:
        return None
    return (mv["a_s"] - cv["a_s"]) / (cv["b_s_per_camera"] - mv["b_s_per_camera"])


# ---------------------------------------------------------------------------------- report
LABELS = {
    "calibrate": "mc.calibrate",
    "refine": "mc.calibrate(refine=True)",
    "triangulate": "mc.triangulate (1000 x 4 views)",
    "opencv": "cv2.calibrateCamera loop",
}


def progress(r):
    print(
        f"  {LABELS[r['task']]}, C = {r['n_cameras']}: import {r['import_s']:.2f} s, call "
        f"{r['call_s']:.2f} s, first answer {r['first_answer_s']:.2f} s (load average "
        f"{r['load_average_1min_at_launch']:.1f})",
        flush=True,
    )


def print_table(rows):
    opencv = {r["n_cameras"]: r for r in rows if r["task"] == "opencv"}
    header = (
        f"{'task':<32}{'C':>6}{'import':>8}{'call':>9}{'first':>9}{'OpenCV':>9}{'ratio':>8}"
        f"{'warm':>7}{'data':>6}{'exit':>7}  check"
    )
    units = (
        f"{'':<32}{'':>6}{'s':>8}{'s':>9}{'answer s':>9}{'first s':>9}{'cv/mv':>8}"
        f"{'s':>7}{'s':>6}{'s':>7}"
    )
    print(header)
    print(units)
    print("-" * 116)
    for r in rows:
        peer = opencv.get(r["n_cameras"]) if r["task"] in ("calibrate", "refine") else None
        scaled = r["task"] == "opencv" and r["cameras_timed"] < r["n_cameras"]
        check = (
            f"max |Δpoint| {r['max_error_mm']:.1e} mm"
            if "max_error_mm" in r
            else f"median RMS {r['median_rms_px']:.4f} px"
        )
        if scaled:
            check += f" ({r['cameras_timed']} timed)"
        peer_scaled = peer is not None and peer["cameras_timed"] < r["n_cameras"]
        print(
            f"{LABELS[r['task']]:<32}{r['n_cameras']:>6}{r['import_s']:>8.2f}"
            f"{r['call_s']:>8.2f}{'*' if scaled else ' '}{r['first_answer_s']:>9.2f}"
            + (
                f"{peer['first_answer_s']:>8.2f}{'*' if peer_scaled else ' '}"
                f"{peer['first_answer_s'] / r['first_answer_s']:>8.2f}"
                if peer
                else f"{'—':>9}{'—':>8}"
            )
            + (f"{r['warm_call_s']:>7.2f}" if "warm_call_s" in r else f"{'—':>7}")
            + f"{r['data_s']:>6.2f}{r['exit_s']:>7.2f}  {check}, {r['ok']} ok"
        )
    print("-" * 116)
    print("import: launch of the fresh process to its imports done (interpreter start-up, and for")
    print("  mvcalib JAX's CPU backend started); call: the entry point's trace + compile + run (or")
    print("  the OpenCV loop); first answer = import + call; data (not counted): loading the .npz;")
    print("  warm (not counted): a second, identical call in the same process (no compile); exit:")
    print("  the process's wall time to its exit (after the warm call). ratio: OpenCV's first")
    print("  answer over mvcalib's at the same C (> 1: mvcalib answers first). *: the OpenCV loop")
    print("  timed on the first 'timed' cameras and scaled linearly to C. Persistent compilation")
    print("  caches off.")


def print_break_even(b):
    if b is None:
        return
    mv, cv = b["mvcalib_refine"], b["opencv"]
    C0, C1 = mv["through"]
    where = "between which they change order" if b["measured"] else "(extrapolated)"
    print(f"\nbreak-even, first answers fitted by t = a + b C through C = {C0} and {C1} {where}:")
    print(
        f"  mvcalib calibrate(refine=True): a = {mv['a_s']:.2f} s, "
        f"b = {1e3 * mv['b_s_per_camera']:.3f} ms/camera"
    )
    print(
        f"  OpenCV calibrateCamera loop:    a = {cv['a_s']:.2f} s, "
        f"b = {1e3 * cv['b_s_per_camera']:.3f} ms/camera"
    )
    print("  " + describe(b["C_star"]))
    if mv["b_s_per_camera"] <= 0:
        print(
            f"  (mvcalib's line falls with C: its C = {C0} process took longer than its C = {C1}"
            " one,\n  a compile-time difference, not a cost per camera.)"
        )
    w = b["mvcalib_refine_warm_slope"]
    print(
        f"with mvcalib's slope from its warm second call at C = {C1} instead "
        f"(b = {1e3 * w['b_s_per_camera']:.3f} ms/camera,\n  a = {w['a_s']:.2f} s): "
        + describe(b["C_star_warm_slope"])
    )


def describe(C_star) -> str:
    if C_star is None:
        return "OpenCV's time per camera is not above mvcalib's: no break-even."
    if C_star <= 0:
        return f"C* = {C_star:.0f}: mvcalib answers first at any C."
    return (
        f"C* = (a_mv - a_cv) / (b_cv - b_mv) = {C_star:.0f} cameras: from there on a fresh "
        "mvcalib\n  process (import and compile included) answers before OpenCV's loop."
    )


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rows; OpenCV on 512 cameras")
    parser.add_argument("--only", help=f"comma-separated subset of {','.join(TASKS)}")
    parser.add_argument("--cameras", help="comma-separated C for calibrate, refine and OpenCV")
    parser.add_argument(
        "--opencv-cameras", type=int, help="time the OpenCV loop on at most this many cameras"
    )
    args = parser.parse_args(argv)
    mode = "quick" if args.quick else "full"
    tasks = [t for t in TASKS if args.only is None or t in args.only.split(",")]
    if args.cameras:
        sizes = dict.fromkeys(("calibrate", "refine", "opencv"), args.cameras.split(","))
        sizes = {k: tuple(int(c) for c in v) for k, v in sizes.items()}
    else:
        sizes = dict(N_CAMERAS[mode])
    sizes["triangulate"] = (4,)
    if not {"calibrate", "refine"} & set(tasks):
        sizes["opencv"] = ()
    all_sizes = sorted({C for t in ("calibrate", "refine", "opencv") for C in sizes[t]})
    at_most = args.opencv_cameras or OPENCV_CAMERAS[mode]

    wall = time.perf_counter()
    info = machine_info("opencv-python-headless")
    print(
        f"first call from a fresh process ({mode}): jax {info['jax']} on {info['jax_backend']}, "
        f"{info['cpu_count']} CPUs, float64, persistent compilation caches off\n"
    )
    rows = []
    with tempfile.TemporaryDirectory(prefix="mvcalib-first-call-") as directory:
        path = str(Path(directory) / "data.npz")
        data = write_data(Path(path), all_sizes)
        warm_file_cache()
        for task in tasks:
            for C in sizes[task]:
                rows.append(mvcalib_row(task, C, path))
                progress(rows[-1])
        for C in sizes["opencv"]:
            rows.append(opencv_row(C, path, at_most))
            progress(rows[-1])
    print()
    print_table(rows)
    even = break_even(rows)
    print_break_even(even)
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")
    return write_results(
        results_path("first_call.json"),
        "first_call",
        quick=args.quick,
        machine=info,
        settings={
            "rig": f"mc.synthetic.random_rig(jax.random.key(0), n_cameras=C, noise={NOISE})",
            "target": "box_corner (19 dots)",
            "n_cameras": {t: list(sizes[t]) for t in (*tasks, "opencv")},
            "visible_fraction": data["visible_fraction"],
            "triangulate": f"{N_TRIANGULATE} points uniform in [0, 160]^3 mm, 4 true cameras",
            "opencv": "cv2.calibrateCamera per camera, float32 points, flags "
            "CALIB_USE_INTRINSIC_GUESS | CALIB_FIX_K3, intrinsic guess = true K, default criteria",
            "opencv_cameras_timed_at_most": at_most,
            "child_env": {
                "JAX_ENABLE_COMPILATION_CACHE": "false",
                "MVCALIB_COMPILATION_CACHE": "0",
                "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
                "JAX_DISABLE_MOST_OPTIMIZATIONS": os.environ.get(
                    "JAX_DISABLE_MOST_OPTIMIZATIONS", ""
                ),
            },
            "dtype": "float64 (mvcalib), float32 points (OpenCV)",
        },
        wall_time_s=wall,
        results=rows,
        break_even=even,
    )


if __name__ == "__main__":
    main()
