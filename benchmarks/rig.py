"""Benchmark: `mc.calibrate_rig` on caliscope's real 4-camera rig against aniposelib, and at scale.

What is measured
----------------
**Real data** (`caliscope_4cam`, ../shared/data/SOURCE.md section 6: 4 cameras, 48 frames of a
12-corner ChArUco board, 1725 observations; `mc.io.load_caliscope`,
`mc.io.load_caliscope_cameras`). Four calibrations from the same corners:

- **aniposelib** 0.8.0, `CameraGroup.calibrate_rows(rows, board, verbose=False, ...)` as its
  users call it: one row per (camera, frame) with the corners sorted by id,
  `board.fill_points_rows`, `CharucoBoard(4, 5, square_length=0.054, marker_length=0.0405,
  marker_bits=4, dict_size=1000)` (its corner ids are caliscope's `keypoint_id`s), image size
  1280 x 720, `np.random.seed(0)` before each call (it resamples points at random), its
  default `bundle_adjust_iter` settings:
  - *own intrinsics*: `init_intrinsics=True` (`cv2.initCameraMatrix2D`; one focal length, k1,
    the principal point at the image centre);
  - *caliscope intrinsics fixed*: the cameras built with caliscope's K and 5-term distortion,
    `init_intrinsics=False, only_extrinsics=True`.
- **mvcalib** `mc.calibrate_rig(target, pixels, mask, cameras=cams, reference=1, ...)` from
  caliscope's cameras `cams`:
  - *intrinsics fixed*: `fix=("intrinsics", "distortion")` (only the poses are fitted);
  - *free*: `fix=()` from caliscope's intrinsics (k1 k2 p1 p2; k3 held at caliscope's).

**Score**, the same for every rig, caliscope's own included (SOURCE.md's definition): cameras
held fixed, each frame's board pose fitted by least squares to every camera that saw it, RMS
of the residual lengths over all 1725 observations; for mvcalib's result that is exactly
`mc.calibrate_rig(target, pixels, mask, cameras=rig, fix=("intrinsics", "distortion",
"pose")).rms_observed`, and aniposelib's cameras are scored by the same call after
`mc.Camera.from_matrices(K, R, t, dist)` (`R` = Rodrigues of its `rvec`, `x_cam = R X + t`,
OpenCV's k1 k2 p1 p2 k3; checked: the converted cameras project the board like
`cv2.projectPoints` with aniposelib's own parameters, to the difference printed). Geometry,
independent of the world frame: each camera centre's distance from camera 1's (baseline) and
the angle of `R_i R_1^T`; "drot" is the angle between a tool's `R_i R_1^T` and caliscope's.

**Times** (wall clock, `time.perf_counter`):
- *first answer*: a fresh child process (`first_call.run_child`, JAX's persistent compilation
  cache off) that imports the tool (aniposelib: `aniposelib.boards`, `aniposelib.cameras`;
  aniposelib imports JAX inside its first call, so that is counted in its call) and makes the
  call once: import + the first call (mvcalib: trace + compile + run; aniposelib: numba's
  compile and JAX's jit of its triangulation + run). Loading the data from an `.npz` file is
  not counted.
- *first call in process*: the first call in this process (compile included, imports not; the
  second aniposelib variant finds numba's functions compiled by the first).
- *warm*: the median of `--rounds` further calls in this process, interleaved between the four
  calibrations (`_common.measure`, one call per calibration per round), so that the machine's
  drifts hit all alike. ratio = aniposelib's warm time over mvcalib's for the matching pair
  (own intrinsics / free; caliscope's fixed / fixed): above 1, mvcalib is faster.

**Scale**: synthetic rigs `mc.synthetic.board_rig(jax.random.key(0), C, F,
target=mc.synthetic.board(6, 8, 0.05), noise=0.3, **kwargs)` (N = 48 corners), C = 16 and 64
cameras, F = 250 and 1000 frames; `kwargs` = `BOARD_RIG_KWARGS` (none; see there), and in full
mode one more row, C = 16, F = 250 with the board in a smaller volume (`EXTRA_ROW`). Each
configuration runs in its own fresh child process (persistent compilation cache off): the rig
is made, then `mc.calibrate_rig(target, pixels, mask)` is called twice (first: trace + compile
+ run; warm: run). Reported: the warm time, the LM steps (`iterations`), warm time per step
(this includes the closed-form start and the per-camera refinements before the joint LM: an
upper bound of the step cost); the warm call's programs timed apart (each call wrapped in
`jax.block_until_ready`): the start (`_start`: closed form, each camera refined alone with its
own frames) and the joint solve (`_calibrate_rig`: LM, uncertainty, report), whose last call
over its steps is the joint solve's time per step; whether it converged (`result`, 0 = yes),
the RMS, the counts of calibrated cameras (`ok`) and statuses, the largest camera-centre error
against the truth (camera 0's frame), and the child's peak resident memory (`ru_maxrss`, which
includes XLA's compilation). A child that fails (out of memory, killed, over `--timeout`) is
recorded with its error and whatever it reported before. Growth of the step cost with F: warm
time per step, and the joint solve's time per step, at F = 1000 over F = 250 at the same C
(linear in F expected: the frames are eliminated).

`--quick`: the real data and the C = 16, F = 250 rig only, 3 rounds. `--only real,scale` picks
the parts, `--sizes 16x250,64x1000` the rigs. aniposelib is optional: if it cannot be imported
its rows are skipped with the install command (`ANIPOSE_INSTALL`); set `ANIPOSELIB_SITE` to a
directory it was installed into with `pip install --target`.

Results are printed and written to `benchmarks/results/rig.json`.

Run from the repository root: `python benchmarks/rig.py [--quick] [--only real,scale]`.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import inspect
import io
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
    from ._common import machine_info, measure, results_path, write_results
    from .first_call import child_env, run_child
except ImportError:  # run as a script
    from _common import machine_info, measure, results_path, write_results
    from first_call import child_env, run_child

import mvcalib as mc  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MVCALIB_DATA", ROOT / ".." / "shared" / "data")).resolve()
CALISCOPE = DATA / "caliscope_4cam"
# aniposelib installed outside the venv (`pip install --target DIR`): DIR goes on sys.path
ANIPOSE_SITE = os.environ.get("ANIPOSELIB_SITE")
ANIPOSE_INSTALL = (
    "pip install --no-deps aniposelib==0.8.0 numba llvmlite pandas toml tqdm "
    "(or with --target DIR and ANIPOSELIB_SITE=DIR; --no-deps because its requirement "
    "opencv-contrib-python would overwrite opencv-python-headless, whose cv2.aruco it uses)"
)
if ANIPOSE_SITE and ANIPOSE_SITE not in sys.path:
    sys.path.insert(0, ANIPOSE_SITE)

SQUARE = 0.054  # caliscope's charuco.toml: 4 x 5 squares of 5.4 cm, DICT_4X4_1000
IMAGE_SIZE = (1280, 720)
REFERENCE = 1  # caliscope's origin camera
FIXED = ("intrinsics", "distortion")
SCORE_FIX = ("intrinsics", "distortion", "pose")
# name: (start from caliscope's cameras, calibrate_rows keyword arguments)
ANIPOSE_VARIANTS = {
    "own intrinsics": (False, {"init_intrinsics": True, "init_extrinsics": True}),
    "caliscope intrinsics fixed": (
        True,
        {"init_intrinsics": False, "init_extrinsics": True, "only_extrinsics": True},
    ),
}
MVCALIB_VARIANTS = {"intrinsics fixed": FIXED, "free": ()}
PAIRS = (("own intrinsics", "free"), ("caliscope intrinsics fixed", "intrinsics fixed"))

SIZES = {"full": ((16, 250), (16, 1000), (64, 250), (64, 1000)), "quick": ((16, 250),)}
BOARD = (6, 8, 0.05)  # rows, columns, spacing (m): N = 48
NOISE = 0.3  # pixels
# board_rig's defaults: every camera of every size OK and converged (at 1495120). Before
# 1f56ba1 (OpenCV's focal-length start instead of Zhang's) the C = 16, F = 250 rig seeded two
# cameras at 31 % and 49 % of their focal length and ended at 104 px RMS after 100 steps, every
# camera still OK (POOR_FIT, 4458397, flags that now). The full run adds that rig with the board
# kept in a 0.8 m cube instead of 1.2 m (fewer boards cut by the image's edge): LM's steps
# depend on the rig as much as on its size.
BOARD_RIG_KWARGS: dict = {}
EXTRA_ROW = (16, 250, {"volume": 0.8})  # full mode
ROUNDS = {"full": 5, "quick": 3}
TIMEOUT = 3 * 3600  # seconds per scale configuration


# ---------------------------------------------------------------------------------- data
def load_caliscope():
    """(observations, caliscope's cameras) from xy.csv and camera_array.toml."""
    obs = mc.io.load_caliscope(CALISCOPE / "xy.csv")
    cameras, _ = mc.io.load_caliscope_cameras(CALISCOPE / "camera_array.toml")
    return obs, cameras


def as_arrays(obs, cameras) -> dict:
    """The problem as NumPy arrays (what the children load from an .npz file)."""
    arrays = {
        "target": np.asarray(obs.target),
        "pixels": np.asarray(obs.pixels),
        "mask": np.asarray(obs.mask),
        "ids": np.asarray(obs.points),
        "frames": np.asarray(obs.frames),
        "K": np.asarray(cameras.K),
        "dist": np.asarray(cameras.dist),
    }
    fields = ("alpha_u", "alpha_v", "u0", "v0", "skew", "R", "t", "dist")
    return arrays | {f"cam_{k}": np.asarray(getattr(cameras, k)) for k in fields}


# ---------------------------------------------------------------------------------- aniposelib
# These functions also run in the fresh child process (their source is copied into it), so they
# use only NumPy, the standard library and the module's constants.
def anipose_board():
    from aniposelib.boards import CharucoBoard

    return CharucoBoard(
        4, 5, square_length=SQUARE, marker_length=0.75 * SQUARE, marker_bits=4, dict_size=1000
    )


def anipose_rows(board, pixels, mask, ids, frames):
    """Per camera, one row {framenum, corners (n, 1, 2) float32, ids (n, 1) int32, filled} per
    frame it saw the board in, corners sorted by id."""
    all_rows = []
    for c in range(pixels.shape[0]):
        rows = []
        for f in range(pixels.shape[1]):
            seen = mask[c, f]
            if not seen.any():
                continue
            order = np.argsort(ids[seen])
            rows.append(
                {
                    "framenum": int(frames[f]),
                    "corners": pixels[c, f][seen][order].astype(np.float32).reshape(-1, 1, 2),
                    "ids": ids[seen][order].astype(np.int32).reshape(-1, 1),
                }
            )
        all_rows.append(board.fill_points_rows(rows))
    return all_rows


def anipose_calibrate(variant, board, rows, K, dist, seed=0):
    """One `calibrate_rows` call on new cameras and a copy of `rows` (it changes them):
    (the CameraGroup, the error it returns)."""
    from aniposelib.cameras import Camera, CameraGroup

    caliscope_start, kwargs = ANIPOSE_VARIANTS[variant]
    cameras = []
    for i in range(len(rows)):
        start = {"matrix": K[i], "dist": dist[i]} if caliscope_start else {}
        cameras.append(Camera(size=IMAGE_SIZE, name=str(i), **start))
    group = CameraGroup(cameras)
    np.random.seed(seed)  # bundle_adjust_iter resamples the points with np.random
    with contextlib.redirect_stdout(io.StringIO()):  # it prints its cameras unconditionally
        error = group.calibrate_rows(copy.deepcopy(rows), board, verbose=False, **kwargs)
    return group, float(error)


def anipose_parameters(group) -> dict:
    """aniposelib's cameras as lists: K, rvec, tvec (x_cam = R(rvec) X + t), distortion."""
    get = {
        "K": "get_camera_matrix",
        "rvec": "get_rotation",
        "t": "get_translation",
        "dist": "get_distortions",
    }
    return {
        k: [np.asarray(getattr(c, m)(), float).ravel().tolist() for c in group.cameras]
        for k, m in get.items()
    }


ANIPOSE_HELPERS = (anipose_board, anipose_rows, anipose_calibrate, anipose_parameters)


def anipose_missing() -> str | None:
    """None if aniposelib imports, else why not."""
    try:
        import aniposelib.boards  # noqa: F401
        import aniposelib.cameras  # noqa: F401
    except ImportError as error:
        return f"aniposelib not importable ({error}); install: {ANIPOSE_INSTALL}"
    return None


def anipose_to_mvcalib(parameters: dict):
    """aniposelib's cameras (`anipose_parameters`) as an mc.Camera rig, and the largest
    difference (px) between its projections of a board 1.5 m in front of each camera and
    `cv2.projectPoints` with aniposelib's own parameters."""
    import cv2

    K = np.asarray(parameters["K"]).reshape(-1, 3, 3)
    rvec, t = np.asarray(parameters["rvec"]), np.asarray(parameters["t"])
    R = np.stack([cv2.Rodrigues(r)[0] for r in rvec])
    dist = np.zeros((len(K), 5))
    for i, d in enumerate(parameters["dist"]):
        dist[i, : len(d)] = d
    rig = mc.Camera.from_matrices(K, R, t, dist)
    board = mc.synthetic.board(3, 4, SQUARE) - [0.08, 0.05, -1.5]
    worst = 0.0
    for i in range(len(K)):
        world = (board - t[i]) @ R[i]  # camera -> world: R^T (x - t)
        ours = np.asarray(rig[i].project(world))
        theirs = cv2.projectPoints(world, rvec[i], t[i], K[i], dist[i])[0].reshape(-1, 2)
        worst = max(worst, float(np.abs(ours - theirs).max()))
    return rig, worst


# ---------------------------------------------------------------------------------- scoring
def score(obs, cameras) -> dict:
    """SOURCE.md's score: `cameras` held, each frame's board pose fitted to every camera that
    saw it; the residual lengths over every observation."""
    out = mc.calibrate_rig(obs.target, obs.pixels, obs.mask, cameras=cameras, fix=SCORE_FIX)
    observed = np.asarray(out.observed)
    lengths = np.linalg.norm(np.asarray(out.residuals), axis=-1)
    e = lengths[observed]
    return {
        "rms_px": float(out.rms_observed),
        "median_px": float(np.median(e)),
        "p95_px": float(np.percentile(e, 95)),
        "max_px": float(e.max()),
        "n_observations": int(observed.sum()),
        "camera_rms_px": [
            float(np.sqrt(np.mean(lengths[c][observed[c]] ** 2))) for c in range(len(observed))
        ],
    }


def rotation_angle(R) -> np.ndarray:
    """The angle (degrees) of rotation matrices `R (..., 3, 3)`, accurate near 0 and 180."""
    sin = 0.5 * np.linalg.norm(
        np.stack(
            [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
            -1,
        ),
        axis=-1,
    )
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1)
    return np.degrees(np.arctan2(sin, cos))


def geometry(cameras, caliscope=None) -> list[dict]:
    """Per camera: its baseline to camera 1 (m) and the angle of `R_i R_1^T` (degrees); with
    `caliscope`, the differences from caliscope's."""
    centres, R = np.asarray(cameras.center), np.asarray(cameras.R)
    relative = R @ R[REFERENCE].T
    rows = []
    for i in range(len(R)):
        row = {
            "baseline_m": float(np.linalg.norm(centres[i] - centres[REFERENCE])),
            "rotation_deg": float(rotation_angle(relative[i])),
        }
        if caliscope is not None:
            theirs = geometry(caliscope)[i]
            Rc = np.asarray(caliscope.R)
            drot = rotation_angle(relative[i] @ (Rc[i] @ Rc[REFERENCE].T).T)
            row["d_baseline_m"] = row["baseline_m"] - theirs["baseline_m"]
            row["d_rotation_deg"] = float(drot)
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------------- children
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
cameras = mc.Camera(**{{k[4:]: data[k] for k in data.files if k.startswith("cam_")}})
target, pixels, mask = data["target"], data["pixels"], data["mask"]
call = lambda: mc.calibrate_rig(
    target, pixels, mask, cameras=cameras, fix={fix!r}, reference={reference}
)
t_data = time.perf_counter()
out = jax.block_until_ready(call())
t_call = time.perf_counter()
jax.block_until_ready(call())
t_warm = time.perf_counter()
print(json.dumps(dict(
    t_start=t_start, t_import=t_import, t_data=t_data, t_call=t_call, t_warm=t_warm,
    rms_observed=float(out.rms_observed), iterations=int(out.iterations), mvcalib=mc.__file__,
)))
"""

ANIPOSE_CHILD = """\
import time
t_start = time.perf_counter()
import sys
if {site!r}:
    sys.path.insert(0, {site!r})
import contextlib, copy, io, json
import numpy as np
import aniposelib.boards, aniposelib.cameras
t_import = time.perf_counter()
SQUARE, IMAGE_SIZE, ANIPOSE_VARIANTS = {square!r}, {image_size!r}, {variants!r}
{helpers}
data = np.load({path!r})
board = anipose_board()
rows = anipose_rows(board, data["pixels"], data["mask"], data["ids"], data["frames"])
t_data = time.perf_counter()
group, error = anipose_calibrate({variant!r}, board, rows, data["K"], data["dist"])
t_call = time.perf_counter()
again, _ = anipose_calibrate({variant!r}, board, rows, data["K"], data["dist"])
t_warm = time.perf_counter()
print(json.dumps(dict(
    t_start=t_start, t_import=t_import, t_data=t_data, t_call=t_call, t_warm=t_warm,
    anipose_error=error, cameras=anipose_parameters(group),
    cameras_second_call=anipose_parameters(again),
)))
"""

SCALE_CHILD = """\
import time
t_start = time.perf_counter()
import json
import resource
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import mvcalib as mc
jax.devices()
t_import = time.perf_counter()


def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def report(stage, out, **stamps):
    status = np.asarray(out.status)
    R0, t0 = np.asarray(rig.cameras.R[0]), np.asarray(rig.cameras.t[0])
    truth = np.asarray(rig.cameras.center) @ R0.T + t0  # the true centres in camera 0's frame
    error = np.linalg.norm(np.asarray(out.cameras.center) - truth, axis=1)
    print(json.dumps(dict(
        stage=stage, **stamps, peak_rss_mb=rss_mb(), mvcalib=mc.__file__,
        iterations=int(out.iterations), result=int(out.result), rms_px=float(out.rms),
        ok=int(np.sum(status == mc.Status.OK)),
        status={{mc.Status(int(s)).name: int(np.sum(status == s)) for s in np.unique(status)}},
        used=int(np.asarray(out.used).sum()), skipped_pairs=int(out.n_skipped),
        max_centre_error_m=float(np.nanmax(error)),
        worst_camera_rms_px=float(np.nanmax(np.asarray(out.camera_rms))),
    )), flush=True)


rig = mc.synthetic.board_rig(
    jax.random.key(0), {C}, {F}, target=mc.synthetic.board(*{board!r}), noise={noise!r},
    **{kwargs!r}
)
target, pixels, mask = (np.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
counts = mask.sum(-1)
print(json.dumps(dict(
    stage="data", observations=int(mask.sum()), pairs=int(np.sum(counts >= 4)),
    cameras_per_frame=float(np.mean(np.sum(counts >= 4, 0))), peak_rss_mb=rss_mb(),
)), flush=True)
t_data = time.perf_counter()
out = jax.block_until_ready(mc.calibrate_rig(target, pixels, mask))
t_call = time.perf_counter()
report("first", out, t_start=t_start, t_import=t_import, t_data=t_data, t_call=t_call)
stages = {{"_start": [], "_calibrate_rig": []}}  # the warm call's programs, each call timed


def timed(name):
    program = getattr(mc._rig, name)

    def call(*args, **kwargs):
        t = time.perf_counter()
        out = jax.block_until_ready(program(*args, **kwargs))
        stages[name].append(time.perf_counter() - t)
        return out

    return call


for name in stages:
    setattr(mc._rig, name, timed(name))
t_call = time.perf_counter()
out = jax.block_until_ready(mc.calibrate_rig(target, pixels, mask))
t_warm = time.perf_counter()
report("warm", out, t_call=t_call, t_warm=t_warm, start_s=stages["_start"],
       joint_s=stages["_calibrate_rig"])  # fmt: skip
"""


def mvcalib_first_answer(path: str, fix) -> dict:
    code = MVCALIB_CHILD.format(path=path, fix=fix, reference=REFERENCE)
    return run_child(code)


def anipose_first_answer(path: str, variant: str) -> dict:
    helpers = "\n\n".join(inspect.getsource(f) for f in ANIPOSE_HELPERS)
    code = ANIPOSE_CHILD.format(
        site=ANIPOSE_SITE or "",
        square=SQUARE,
        image_size=IMAGE_SIZE,
        variants=ANIPOSE_VARIANTS,
        helpers=helpers,
        path=path,
        variant=variant,
    )
    return run_child(code)


def scale_row(C: int, F: int, kwargs: dict, timeout: float) -> dict:
    """One configuration in a fresh process; its reports, or its failure and the error."""
    code = SCALE_CHILD.format(C=C, F=F, board=BOARD, noise=NOISE, kwargs=kwargs)
    row = {"n_cameras": C, "n_frames": F, "n_points": BOARD[0] * BOARD[1], "kwargs": kwargs}
    row["load_average_1min_at_launch"] = os.getloadavg()[0]
    launch = time.perf_counter()
    error = None
    try:
        proc = subprocess.run(
            [sys.executable, "-c", code],
            cwd=ROOT,
            env=child_env(),
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        stdout, stderr = proc.stdout, proc.stderr
        if proc.returncode != 0:
            signal = -proc.returncode if proc.returncode < 0 else None
            error = f"exit status {proc.returncode}" + (
                f" (killed by signal {signal}{': out of memory?' if signal == 9 else ''})"
                if signal
                else ""
            )
    except subprocess.TimeoutExpired as expired:
        stdout = expired.stdout.decode() if isinstance(expired.stdout, bytes) else expired.stdout
        stderr = expired.stderr.decode() if isinstance(expired.stderr, bytes) else expired.stderr
        stdout, stderr = stdout or "", stderr or ""
        error = f"timed out after {timeout:.0f} s (--timeout)"
    row["exit_s"] = time.perf_counter() - launch
    reports = {}
    for line in stdout.splitlines():
        if line.startswith("{"):
            item = json.loads(line)
            reports[item.pop("stage")] = item
    row |= reports.get("data", {})
    if "first" in reports:
        first = reports["first"]
        row["import_s"] = first["t_import"] - launch
        row["first_call_s"] = first["t_call"] - first["t_data"]
        row["first"] = {k: v for k, v in first.items() if not k.startswith("t_")}
    if "warm" in reports:
        warm = reports["warm"]
        row["warm_call_s"] = warm["t_warm"] - warm["t_call"]
        row["steps"] = warm["iterations"]
        row["warm_s_per_step"] = row["warm_call_s"] / max(warm["iterations"], 1)
        if warm.get("joint_s"):  # the last joint solve's program over its steps
            row["joint_s_per_step"] = warm["joint_s"][-1] / max(warm["iterations"], 1)
        if "first_call_s" in row:
            row["first_minus_warm_s"] = row["first_call_s"] - row["warm_call_s"]
        row |= {k: v for k, v in warm.items() if not k.startswith("t_") and k != "iterations"}
    if error:
        row["failed"] = error
        row["stderr_tail"] = stderr[-2000:]
    return row


# ---------------------------------------------------------------------------------- parts
def real_data(rounds: int, directory: str) -> dict:
    obs, caliscope = load_caliscope()
    arrays = as_arrays(obs, caliscope)
    path = str(Path(directory) / "caliscope.npz")
    np.savez(path, **arrays)
    missing = anipose_missing()
    keys = [f"mvcalib {name}" for name in MVCALIB_VARIANTS]
    keys += [f"aniposelib {name}" for name in ANIPOSE_VARIANTS] if missing is None else []
    results = {"caliscope": {}}  # scored last: its compilation is not to help the first calls

    # fresh processes: import + first call
    for key in keys:
        tool, name = key.split(" ", 1)
        if tool == "mvcalib":
            fa = mvcalib_first_answer(path, MVCALIB_VARIANTS[name])
        else:
            fa = anipose_first_answer(path, name)
        fa["first_answer_s"] = fa["import_s"] + fa["call_s"]
        results[key] = {"first_answer": fa}
        print(f"  {key}: fresh process, first answer {fa['first_answer_s']:.2f} s", flush=True)

    # this process: the first call of each (compile included), then interleaved warm calls
    calls = {}
    for name, fix in MVCALIB_VARIANTS.items():

        def call(fix=fix):
            return jax.block_until_ready(
                mc.calibrate_rig(
                    obs.target,
                    obs.pixels,
                    obs.mask,
                    cameras=caliscope,
                    fix=fix,
                    reference=REFERENCE,
                )
            )

        calls[f"mvcalib {name}"] = call
    if missing is None:
        board = anipose_board()
        rows = anipose_rows(
            board, arrays["pixels"], arrays["mask"], arrays["ids"], arrays["frames"]
        )
        used = int(sum(r["ids"].size for rr in rows for r in rr if r["ids"].size >= 8))
        for name in ANIPOSE_VARIANTS:

            def call(name=name):
                return anipose_calibrate(name, board, rows, arrays["K"], arrays["dist"])

            calls[f"aniposelib {name}"] = call
    outputs = {}
    for key, call in calls.items():
        t0 = time.perf_counter()
        outputs[key] = call()
        results[key]["first_call_in_process_s"] = time.perf_counter() - t0
        print(f"  {key}: first call in this process {time.perf_counter() - t0:.2f} s", flush=True)
    warm = measure(calls, min_time=0.0, rounds=rounds, warmup=0.0)

    for key, out in outputs.items():
        entry = results[key]
        entry["warm"] = warm[key]
        if key.startswith("mvcalib"):
            cameras = out.cameras
            entry |= {
                "rms_fit_px": float(out.rms),
                "rms_observed_px": float(out.rms_observed),
                "iterations": int(out.iterations),
                "result": int(out.result),
                "converged": bool(out.converged),
                "ok": int(np.sum(out.ok)),
                "intrinsics": {
                    k: np.asarray(getattr(cameras, k)).tolist()
                    for k in ("alpha_u", "alpha_v", "u0", "v0", "dist")
                },
            }
        else:
            # scored: the fresh process's first call, as a user's script gets it (aniposelib
            # turns jax_enable_x64 on in its first triangulation, so later calls in a process,
            # as here, compute in float64 from the start and end elsewhere)
            fa = entry["first_answer"]
            parameters = fa.pop("cameras")
            cameras, worst = anipose_to_mvcalib(parameters)
            second, _ = anipose_to_mvcalib(fa.pop("cameras_second_call"))
            here, _ = anipose_to_mvcalib(anipose_parameters(out[0]))
            entry |= {
                "anipose_error": fa["anipose_error"],
                "projection_check_max_px": worst,
                "n_observations_used": used,
                "score_second_call_fresh_process": score(obs, second),
                "score_in_this_process": score(obs, here),
                "intrinsics": {k: parameters[k] for k in ("K", "dist")},
            }
        entry["score"] = score(obs, cameras)
        entry["geometry"] = geometry(cameras, caliscope)
        print(f"  {key}: score RMS {entry['score']['rms_px']:.4f} px", flush=True)
    results["caliscope"] = {"score": score(obs, caliscope), "geometry": geometry(caliscope)}
    ratios = {}
    if missing is None:
        for a, m in PAIRS:
            ratios[f"aniposelib {a} / mvcalib {m}"] = (
                results[f"aniposelib {a}"]["warm"]["median"]
                / results[f"mvcalib {m}"]["warm"]["median"]
            )
    else:
        results["aniposelib"] = {"skipped": missing}
    return {"results": results, "ratio_warm_aniposelib_over_mvcalib": ratios}


def print_real(real: dict) -> None:
    res = real["results"]
    print(
        f"\ncaliscope_4cam: score = RMS over all {res['caliscope']['score']['n_observations']} "
        "observations, cameras held, board poses fitted"
    )
    head = f"{'calibration':<40}{'RMS px':>8}{'median':>8}{'answer s':>10}{'import':>8}"
    head += f"{'call':>8}{'in-proc':>9}{'warm s':>9}{'steps':>7}"
    print(head)
    print("-" * len(head))
    for key, r in res.items():
        if "skipped" in r:
            print(f"{key:<40}skipped: {r['skipped']}")
            continue
        s = r["score"]
        line = f"{key:<40}{s['rms_px']:>8.4f}{s['median_px']:>8.3f}"
        if "warm" in r:
            fa = r["first_answer"]
            line += (
                f"{fa['first_answer_s']:>10.2f}{fa['import_s']:>8.2f}{fa['call_s']:>8.2f}"
                f"{r['first_call_in_process_s']:>9.2f}{r['warm']['median']:>9.3f}"
                f"{r.get('iterations', '—'):>7}"
            )
        print(line)
    print("-" * len(head))
    for key, r in res.items():
        if "score_in_this_process" in r:
            print(
                f"{key}: RMS {r['score_second_call_fresh_process']['rms_px']:.4f} px from its "
                f"second call in the fresh process, {r['score_in_this_process']['rms_px']:.4f} "
                "in this one (float64 from the start)"
            )
    for name, ratio in real["ratio_warm_aniposelib_over_mvcalib"].items():
        print(f"warm time ratio {name}: {ratio:.1f}")
    print("answer s: a fresh process, import + first call (mvcalib: trace + compile + run;")
    print("  aniposelib: JAX's import, numba's compile + run), the data's loading not counted;")
    print("  import, call: its two parts. in-proc: the first call in this process (compile, no")
    print("  import). warm s: median of the interleaved calls in this process. steps: mvcalib's")
    print("  LM steps (at max_steps = 100: stopped there, not converged). RMS, median: the score")
    print("  (aniposelib: its fresh process's first call).")
    print("\ngeometry: baseline to camera 1 (m) / angle of R_i R_1^T (deg) [drot vs caliscope]")
    for key, r in res.items():
        if "geometry" not in r:
            continue
        cells = []
        for i, g in enumerate(r["geometry"]):
            if i == REFERENCE:
                continue
            cell = f"cam{i} {g['baseline_m']:.4f} / {g['rotation_deg']:7.2f}"
            if "d_rotation_deg" in g:
                cell += f" [{g['d_rotation_deg']:.2f}]"
            cells.append(cell)
        print(f"{key:<40}" + "   ".join(cells))


def print_scale(rows: list[dict]) -> None:
    print(
        f"\nscale: board_rig, {BOARD[0]} x {BOARD[1]} board, noise {NOISE} px, fresh process each"
    )
    head = f"{'C':>4}{'F':>6}{'obs':>9}{'first s':>9}{'compile':>8}{'warm s':>8}{'steps':>6}"
    head += f"{'s/step':>7}{'start s':>8}{'joint/step':>11}"
    head += f"{'result':>7}{'RMS px':>9}{'ok':>7}{'centre err m':>14}{'peak MB':>9}  kwargs"
    print(head)
    print("-" * len(head))
    for r in rows:
        line = f"{r['n_cameras']:>4}{r['n_frames']:>6}{r.get('observations', 0):>9}"
        line += f"{r['first_call_s']:>9.1f}" if "first_call_s" in r else f"{'—':>9}"
        if "warm_call_s" in r:
            line += (
                f"{r['first_minus_warm_s']:>8.1f}{r['warm_call_s']:>8.2f}{r['steps']:>6}"
                f"{r['warm_s_per_step']:>7.2f}{sum(r.get('start_s', [np.nan])):>8.2f}"
                f"{r.get('joint_s_per_step', np.nan):>11.3f}{r['result']:>7}{r['rms_px']:>9.3f}"
                f"{r['ok']:>4}/{r['n_cameras']:<2}{r['max_centre_error_m']:>14.2e}"
                f"{r['peak_rss_mb']:>9.0f}"
            )
        line += f"  {r['kwargs']}"
        if "failed" in r:
            line += f"  FAILED: {r['failed']}"
        print(line)
    print("-" * len(head))
    for C, g in step_growth(rows).items():
        F0, F1 = g["F"]
        print(
            f"C = {C}: from F = {F0} to {F1} (x{F1 / F0:.0f}) warm time x{g['warm_ratio']:.2f}, "
            f"warm time per step x{g['per_step_ratio']:.2f}, the joint solve's time per step "
            f"x{g.get('joint_per_step_ratio', np.nan):.2f}"
        )
    print("first s: the first call in the child (trace + compile + run); compile: first - warm.")
    print("warm s/step: the whole warm call (closed form, each camera refined alone, then the")
    print("  joint LM) over the joint LM's steps: an upper bound of one step's cost. start s: the")
    print("  warm call's start program(s) (closed form, each camera refined alone). joint/step:")
    print("  the last joint solve's program (LM, uncertainty, report) over its steps. centre err:")
    print("  largest distance of a camera centre from the truth (camera 0's frame). ok: cameras")
    print("  with status OK. peak MB: the child's ru_maxrss (XLA's compilation included).")


def step_growth(rows: list[dict]) -> dict:
    """Per C, the warm time and warm time per step at the largest F over the smallest (rows
    with `BOARD_RIG_KWARGS` that finished)."""
    out = {}
    for C in sorted({r["n_cameras"] for r in rows}):
        done = {
            r["n_frames"]: r
            for r in rows
            if r["n_cameras"] == C and r["kwargs"] == BOARD_RIG_KWARGS and "warm_call_s" in r
        }
        if len(done) >= 2:
            a, b = done[min(done)], done[max(done)]
            out[str(C)] = {
                "F": [min(done), max(done)],
                "warm_ratio": b["warm_call_s"] / a["warm_call_s"],
                "per_step_ratio": b["warm_s_per_step"] / a["warm_s_per_step"],
            }
            if "joint_s_per_step" in a and "joint_s_per_step" in b:
                out[str(C)]["joint_per_step_ratio"] = b["joint_s_per_step"] / a["joint_s_per_step"]
    return out


def git_state() -> dict:
    """The commit and the changed files of the working tree measured."""

    def git(*args):
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
        return out.stdout.strip() if out.returncode == 0 else None

    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": git("rev-parse", "HEAD"), "modified": status.splitlines() if status else []}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="C = 16, F = 250 only (+ real data)")
    parser.add_argument("--only", help="comma-separated subset of real,scale")
    parser.add_argument("--sizes", help="comma-separated CxF for the scale rows, e.g. 16x250")
    parser.add_argument("--rounds", type=int, help="warm calls of each real-data calibration")
    parser.add_argument(
        "--timeout", type=float, default=TIMEOUT, help="seconds per scale configuration"
    )
    args = parser.parse_args(argv)
    mode = "quick" if args.quick else "full"
    parts = ("real", "scale") if args.only is None else tuple(args.only.split(","))
    if args.sizes:
        sizes = tuple(tuple(int(x) for x in s.split("x")) for s in args.sizes.split(","))
    else:
        sizes = SIZES[mode]
    rounds = args.rounds or ROUNDS[mode]

    wall = time.perf_counter()
    info = machine_info("opencv-python-headless", "aniposelib", "numba", "scipy")
    print(
        f"calibrate_rig ({mode}): jax {info['jax']} on {info['jax_backend']}, "
        f"{info['cpu_count']} CPUs, float64; aniposelib {info['aniposelib']}\n"
    )
    sections = {}
    with tempfile.TemporaryDirectory(prefix="mvcalib-rig-") as directory:
        if "real" in parts:
            sections["real_data"] = real_data(rounds, directory)
            print_real(sections["real_data"])
    if "scale" in parts:
        configs = [(C, F, BOARD_RIG_KWARGS) for C, F in sizes]
        if mode == "full" and not args.sizes:
            configs.append(EXTRA_ROW)
        rows = []
        for C, F, kwargs in configs:
            print(f"  scale C = {C}, F = {F}, board_rig kwargs {kwargs} ...", flush=True)
            rows.append(scale_row(C, F, kwargs, args.timeout))
            print_scale(rows[-1:])
        print_scale(rows)
        sections["scale"] = {"results": rows, "step_growth_with_F": step_growth(rows)}
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")
    return write_results(
        results_path("rig.json"),
        "rig",
        quick=args.quick,
        machine=info,
        settings={
            "git": git_state(),
            "mvcalib_imported_from": mc.__file__,
            "real_data": str(CALISCOPE),
            "aniposelib_site": ANIPOSE_SITE,
            "aniposelib_variants": {k: v[1] for k, v in ANIPOSE_VARIANTS.items()},
            "mvcalib_variants": {k: list(v) for k, v in MVCALIB_VARIANTS.items()},
            "reference": REFERENCE,
            "score": f"mc.calibrate_rig(..., cameras=rig, fix={SCORE_FIX}).rms_observed",
            "warm_rounds": rounds,
            "scale_sizes": [list(s) for s in sizes] if "scale" in parts else [],
            "scale_rig": f"mc.synthetic.board_rig(jax.random.key(0), C, F, "
            f"target=mc.synthetic.board{BOARD}, noise={NOISE}, **{BOARD_RIG_KWARGS})",
            "timeout_s": args.timeout,
            "child_env": {
                "JAX_ENABLE_COMPILATION_CACHE": "false",
                "MVCALIB_COMPILATION_CACHE": "0",
            },
            "dtype": "float64",
        },
        wall_time_s=wall,
        **sections,
    )


if __name__ == "__main__":
    main()
