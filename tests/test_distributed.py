"""Several processes: arrays that span two processes give the single-process results.

The test starts two Python processes on this machine, connected by `jax.distributed` (CPU
collectives by gloo, the coordinator on a free localhost port), one CPU device each. Both build
the same synthetic rig; each then

- calibrates it with `jax.jit(calibrate)` over arrays split by camera across the two processes
  (4 cameras each), once from each process's own cameras
  (`jax.make_array_from_process_local_data`) and once from the whole rig held by both
  (`mc.shard` over the two processes' mesh);
- triangulates the rig's points with `mc.triangulate`, the point axis split across the two
  processes (24 points each) and the cameras replicated;
- gathers the results (`multihost_utils.process_allgather`) and compares them with the same
  calls on its own unsharded arrays, in the same process: the single-process answer.

Each process prints one JSON line with the comparisons; the tests below read both. As on several
devices of one process (tests/test_sharding.py), the partitioned program is fused differently
from the single-device one, so floating results agree to rounding rather than bitwise, and
integer results (statuses, counts, masks) are identical.
"""

import json
import os
import pathlib
import socket
import subprocess
import sys
import time

import pytest

import mvcalib as mc

ROOT = pathlib.Path(__file__).resolve().parents[1]
CAMERA = ("alpha_u", "alpha_v", "u0", "v0", "skew", "R", "t", "dist")
REPORT = ("residuals", "rms", "max", "mean_x", "mean_y")  # pixels
TIMEOUT = 300  # seconds for both processes, start to finish (~20 s on 2 cores)

WORKER = r'''
"""One of the two processes (argv: coordinator port, process id); prints one JSON line."""

import json
import sys
import time

import jax

jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.config.update("jax_enable_x64", True)
port, me = int(sys.argv[1]), int(sys.argv[2])
start = time.perf_counter()
jax.distributed.initialize(
    coordinator_address=f"127.0.0.1:{port}",
    num_processes=2,
    process_id=me,
    coordinator_bind_address=f"127.0.0.1:{port}",  # the address whose port was found free
    cluster_detection_method="deactivate",  # nothing from SLURM, MPI, ... variables around CI
    initialization_timeout=120,
)
seconds = {"initialize": time.perf_counter() - start}

import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import mvcalib as mc


def compare(ref, out, where=None) -> dict:
    """Bitwise equality, and the largest difference, absolute and relative to the largest
    |ref| (NaN in the same places counts as equal); over the entries `where` only, if given."""
    a, b = np.asarray(ref), np.asarray(out)
    if where is not None:
        a, b = a[np.asarray(where)], b[np.asarray(where)]
    floating = a.dtype.kind == "f"
    finite = np.isfinite(a) & np.isfinite(b) if floating else np.ones(a.shape, bool)
    x, y = a[finite].astype(float), b[finite].astype(float)
    scale = float(np.max(np.abs(x), initial=0.0))
    diff = float(np.max(np.abs(x - y), initial=0.0))
    return {
        "bitwise": bool(np.array_equal(a, b, equal_nan=floating)),
        "same_nan": bool(np.array_equal(np.isnan(a), np.isnan(b))) if floating else True,
        "absolute": diff,
        "relative": diff / scale if scale > 0 else diff,
    }


def compare_trees(ref, out) -> dict:
    leaves = jax.tree_util.tree_leaves_with_path(ref)
    return {
        jax.tree_util.keystr(path): compare(a, b)
        for (path, a), b in zip(leaves, jax.tree_util.tree_leaves(out), strict=True)
    }


def gathered(tree):
    """Every process's part of every array, on every process (NumPy)."""
    return multihost_utils.process_allgather(tree, tiled=True)


def local_shapes(x) -> list:
    return [list(s.data.shape) for s in x.addressable_shards]


report = {
    "process": jax.process_index(),
    "processes": jax.process_count(),
    "devices": [d.process_index for d in jax.devices()],
    "local_devices": jax.local_device_count(),
}
mesh = Mesh(np.array(jax.devices()), ("batch",))  # both processes' devices
by_camera = NamedSharding(mesh, PartitionSpec("batch"))
by_point = NamedSharding(mesh, PartitionSpec(None, "batch"))
lap = time.perf_counter()

# The same rig in both processes: 8 cameras of a 48-point target, 0.3 px of noise.
rig = mc.synthetic.random_rig(
    jax.random.key(0), n_cameras=8, target=mc.targets.box_corner_grid(4), noise=0.3
)
world, cameras = np.asarray(rig.world), rig.cameras
pixels, mask = np.array(rig.pixels), np.array(rig.mask)
multihost_utils.assert_equal((pixels, mask), "the two processes made different rigs")
# Camera 1 sees 5 points (too few); hidden pixels are NaN, as in a correspondences file; camera
# 6 has a NaN among its visible points (under jit: Status.NON_FINITE, not an error).
mask[1, 5:] = False
pixels[~mask] = np.nan
pixels[6, 3] = np.nan

calibrate = jax.jit(lambda p, m: mc.calibrate(world, p, m))
cams = slice(4 * me, 4 * me + 4)  # this process's cameras
alone = calibrate(pixels, mask)  # this process alone, unsharded
split = calibrate(
    jax.make_array_from_process_local_data(by_camera, pixels[cams]),
    jax.make_array_from_process_local_data(by_camera, mask[cams]),
)
report["calibrate"] = {
    "status": np.asarray(alone.status).tolist(),
    "local_shapes": local_shapes(split.P),
    "compare": compare_trees(alone, gathered(split)),
    "rms": float(np.nanmax(np.asarray(alone.report.rms))),
    "alpha_u_error": float(
        np.nanmax(np.abs(np.asarray(alone.cameras.alpha_u) / np.asarray(cameras.alpha_u) - 1))
    ),
}

# The whole rig held by both processes, split by mc.shard over the same mesh, NaN where
# unseen and the visible NaN of camera 6 included (jax.device_put's same-on-every-process check
# fails on NaN; mc.shard builds each process's slices itself).
alone = calibrate(pixels, mask)
split = calibrate(*mc.shard((pixels, mask), mesh))
report["shard"] = {
    "status": np.asarray(alone.status).tolist(),
    "local_shapes": local_shapes(split.P),
    "compare": compare_trees(alone, gathered(split)),
}
seconds["calibrate"], lap = time.perf_counter() - lap, time.perf_counter()

# Triangulation of the 48 points by the true cameras, the points split: point 7 (in process 0's
# half) is seen by nobody, point 33 (in process 1's) by one camera.
tpixels, tmask = np.array(rig.pixels), np.array(rig.mask)
tmask[:, 7] = False
tmask[1:, 33] = False
points = slice(24 * me, 24 * me + 24)  # this process's points
alone = mc.triangulate(cameras, tpixels, tmask)
split = mc.triangulate(
    mc.shard(cameras, mesh, axis=None),
    jax.make_array_from_process_local_data(by_point, tpixels[:, points]),
    jax.make_array_from_process_local_data(by_point, tmask[:, points]),
)
out = gathered(split)
seen = np.asarray(alone.views) >= 2  # rms and angle are undefined (0 or NaN) for the others
report["triangulate"] = {
    "views": np.asarray(alone.views).tolist(),
    "local_shapes": local_shapes(split.points),
    "compare": {
        **compare_trees(alone, out),
        ".rms": compare(alone.rms, out.rms, seen),
        ".angle": compare(alone.angle, out.angle, seen),
    },
    "error_median": float(np.nanmedian(np.linalg.norm(np.asarray(alone.points) - world, axis=-1))),
}
seconds["triangulate"] = time.perf_counter() - lap
report["seconds"] = {name: round(s, 2) for name, s in seconds.items()}
print(json.dumps(report), flush=True)
'''


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _child_env() -> dict:
    """This process's environment, without what could confuse a `jax.distributed` process:
    pytest's and xdist's variables, proxies (JAX warns that they can hang `initialize`),
    another coordinator, forced host devices. mvcalib comes from this repository; programs are
    compiled as this process compiles them (conftest's XLA flags), with no persistent
    compilation cache (they are compiled nowhere else)."""
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("PYTEST_", "JAX_COORDINATOR", "JAX_LOCAL_DEVICE_IDS"))
        and "_proxy" not in k.lower()
    }
    flags = env.get("XLA_FLAGS", "").split()
    paths = [str(ROOT), *filter(None, env.get("PYTHONPATH", "").split(os.pathsep))]
    env.update(
        XLA_FLAGS=" ".join(f for f in flags if "xla_force_host_platform_device_count" not in f),
        JAX_PLATFORMS="cpu",
        JAX_ENABLE_COMPILATION_CACHE="false",
        PYTHONPATH=os.pathsep.join(paths),
    )
    return env


def _traceback(stderr: str, size: int = 6000) -> str:
    text = stderr[stderr.find("Traceback") :] if "Traceback" in stderr else stderr
    return text if len(text) <= size else f"{text[: size // 2]}\n[...]\n{text[-size // 2 :]}"


def _run_pair(script: pathlib.Path, logs: pathlib.Path) -> tuple[list[dict], bool]:
    """Both processes' outputs (`code`: None if killed, `out`, `err`), and whether the timeout
    was reached. A process still running at the timeout, or after the other failed, is killed."""
    port = _free_port()
    env, procs = _child_env(), []
    deadline = time.monotonic() + TIMEOUT
    try:
        for i in range(2):
            with open(logs / f"{i}.out", "w") as out, open(logs / f"{i}.err", "w") as err:
                command = [sys.executable, str(script), str(port), str(i)]
                procs.append(subprocess.Popen(command, stdout=out, stderr=err, cwd=ROOT, env=env))
        while time.monotonic() < deadline:
            codes = [p.poll() for p in procs]
            if all(c == 0 for c in codes) or any(c not in (None, 0) for c in codes):
                break
            time.sleep(0.1)
    finally:
        codes = [p.poll() for p in procs]
        for p in procs:
            if p.poll() is None:
                p.kill()
        for p in procs:
            p.wait()
    text = [{kind: (logs / f"{i}.{kind}").read_text() for kind in ("out", "err")} for i in range(2)]
    runs = [{"code": code, **text[i]} for i, code in enumerate(codes)]
    return runs, time.monotonic() >= deadline


@pytest.fixture(scope="module")
def two_processes(tmp_path_factory):
    """The JSON reports of process 0 and process 1."""
    directory = tmp_path_factory.mktemp("distributed")
    script = directory / "worker.py"
    script.write_text(WORKER)
    start = time.monotonic()
    for attempt in range(3):
        logs = directory / f"attempt{attempt}"
        logs.mkdir()
        runs, timed_out = _run_pair(script, logs)
        # Another program took the free port before the coordinator bound it: another port.
        if not any("Failed to add port" in run["err"] for run in runs):
            break
    failed = []
    for i, run in enumerate(runs):
        if run["code"] is None:
            why = f"killed at the {TIMEOUT} s timeout" if timed_out else "killed: the other failed"
            failed.append(f"process {i}: {why}; stderr:\n{_traceback(run['err'])}")
        elif run["code"] != 0:
            failed.append(
                f"process {i}: exit code {run['code']}; stderr:\n{_traceback(run['err'])}"
            )
    assert not failed, (
        f"jax.distributed over two CPU processes failed ({time.monotonic() - start:.0f} s):\n"
        + "\n".join(failed)
    )
    reports = []
    for i, run in enumerate(runs):
        lines = run["out"].strip().splitlines()
        assert lines and lines[-1].startswith("{"), (
            f"process {i} printed no report; stdout:\n{run['out'][-2000:]}\n"
            f"stderr:\n{_traceback(run['err'])}"
        )
        reports.append(json.loads(lines[-1]))
    return reports


def assert_calibration_agrees(compare: dict, *, where: str):
    for name in (".status", ".mirrored", ".report.n_points", ".report.mask"):
        assert compare[name]["bitwise"], (where, name)
    for name in (".P", ".condition", *(f".cameras.{f}" for f in CAMERA)):
        assert compare[name]["same_nan"], (where, name, "NaN in different places")
        # skew is ~0: relative to its own largest value it shows the rounding of alpha_u.
        rtol = 1e-11 if name == ".cameras.skew" else 1e-12
        assert compare[name]["relative"] <= rtol, (where, name, compare[name])
    for name in (f".report.{f}" for f in REPORT):
        assert compare[name]["same_nan"], (where, name, "NaN in different places")
        assert compare[name]["absolute"] <= 1e-10, (where, name, compare[name])  # pixels


def test_two_processes_of_one_cpu_device_each(two_processes):
    for i, report in enumerate(two_processes):
        assert (report["process"], report["processes"]) == (i, 2)
        assert report["devices"] == [0, 1] and report["local_devices"] == 1
    # One program on one data set: both processes gather the same results and compare them
    # with the same single-process answers.
    same = [{k: v for k, v in r.items() if k not in ("process", "seconds")} for r in two_processes]
    assert same[0] == same[1]


def test_jit_calibrate_over_two_processes_equals_one_process(two_processes):
    S = mc.Status
    expected = [S.OK] * 8
    expected[1], expected[6] = S.TOO_FEW_POINTS, S.NON_FINITE
    for report in two_processes:
        out = report["calibrate"]
        assert out["status"] == [int(s) for s in expected]
        assert out["local_shapes"] == [[4, 3, 4]]  # each process holds its own 4 cameras' P
        assert_calibration_agrees(out["compare"], where="calibrate")
        # Against the truth too, so that "equal" cannot mean "equally wrong" (0.3 px of noise).
        assert out["rms"] < 1.0 and out["alpha_u_error"] < 0.05


def test_shard_splits_a_rig_every_process_holds_over_both(two_processes):
    """NaN where unseen and among camera 6's visible pixels go through mc.shard as they are."""
    S = mc.Status
    expected = [S.OK] * 8
    expected[1], expected[6] = S.TOO_FEW_POINTS, S.NON_FINITE
    for report in two_processes:
        out = report["shard"]
        assert out["status"] == [int(s) for s in expected]
        assert out["local_shapes"] == [[4, 3, 4]]
        assert_calibration_agrees(out["compare"], where="shard")


def test_triangulate_split_by_point_over_two_processes_equals_one_process(two_processes):
    for report in two_processes:
        out = report["triangulate"]
        assert out["views"][7] == 0 and out["views"][33] == 1
        assert sum(v == 8 for v in out["views"]) == 46
        assert out["local_shapes"] == [[24, 3]]  # each process triangulates its 24 points
        compare = out["compare"]
        for name in (".views", ".ok"):
            assert compare[name]["bitwise"], name
        for name in (".points", ".rms", ".angle"):
            assert compare[name]["same_nan"], (name, "NaN in different places")
            assert compare[name]["relative"] <= 1e-12, (name, compare[name])
        assert out["error_median"] < 1.0  # 0.3 px of noise, a 167-unit target
