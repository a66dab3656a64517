"""Sharding across devices: split inputs give the single-device results, and stay split.

The 2-device checks run in a fresh process (tests/_sharding_check.py): the number of host devices
is fixed when JAX initialises. They compare each public function compiled for unsharded inputs
with the same function compiled for inputs split over 2 devices.

Why not bitwise everywhere: the program XLA compiles for a split input passes through the SPMD
partitioner, and the per-device program it leaves is fused differently from the single-device
one (a product moved into another fusion, for instance), so a few roundings land elsewhere.
Integer and boolean results (statuses, visible counts, iterations) must be identical; floating
results agree to rounding, and more loosely where the quantity itself amplifies rounding (an
inverse normal matrix, a mean of residuals that nearly cancel).
"""

import contextlib
import io
import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import default_codegen_env
from jax.sharding import Mesh, NamedSharding

import mvcalib as mc

ROOT = pathlib.Path(__file__).resolve().parents[1]
CAMERA = ("alpha_u", "alpha_v", "u0", "v0", "skew", "R", "t", "dist")


@pytest.fixture(scope="module")
def two_devices():
    # Backend optimisation off: the split is decided on the HLO, before LLVM, and LLVM's
    # optimisation of the unrolled DLT is most of the compile time (62 -> 35 s CPU for the ten
    # programs). Both sides of every comparison are compiled alike.
    # The comparisons are to the last bits: compiled as users' programs are (XLA's default CPU
    # emitters, not the older ones the other tests use).
    env = default_codegen_env()
    flags = env["XLA_FLAGS"] + (
        " --xla_force_host_platform_device_count=2 --xla_backend_optimization_level=0"
    )
    env = dict(
        env,
        XLA_FLAGS=flags.strip(),
        JAX_ENABLE_X64="1",
        JAX_PLATFORMS="cpu",
        PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    )
    script = ROOT / "tests" / "_sharding_check.py"
    proc = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=900
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def assert_close(compare: dict, rtol: float, *, where: str):
    assert compare["same_nan"], f"{where}: NaN in different places"
    assert compare["relative"] <= rtol, f"{where}: {compare}"


def assert_split(layout: dict, shard_shape: list[int], spec=("batch",), *, where: str):
    assert layout["devices"] == 2, where
    assert tuple(layout["spec"]) == tuple(spec), f"{where}: {layout}"
    assert layout["shard_shapes"] == [shard_shape, shard_shape], f"{where}: {layout}"


def assert_no_collectives(hlo: dict, *, allow_all_reduce: int = 0, where: str):
    counts = dict(hlo["collectives"])
    assert counts.pop("all-reduce") <= allow_all_reduce, f"{where}: {hlo}"
    assert not any(counts.values()), f"{where}: {hlo}"


# ----------------------------------------------------------------------------- 2 devices
def test_the_check_runs_on_two_devices_and_can_see_a_collective(two_devices):
    assert len(two_devices["devices"]) == 2
    # A sum over the split axis needs an all-reduce: the detector behind "no collectives" works.
    assert two_devices["detector"]["all-reduce"] >= 1


def test_sharded_calibration_equals_the_unsharded_one(two_devices):
    out = two_devices["calibrate"]
    S = mc.Status
    expected = [S.OK] * 64
    expected[5], expected[12] = S.TOO_FEW_POINTS, S.DEGENERATE
    assert out["status"] == [int(s) for s in expected]
    # Against the truth too, so that "equal" cannot mean "equally wrong" (0.3 px of noise).
    assert out["rms"] < 1.0 and out["alpha_u_error"] < 0.05
    compare = out["compare"]
    for name in (".status", ".mirrored", ".report.n_points", ".report.mask"):
        assert compare[name]["bitwise"], name
    for name in (".P", *(f".cameras.{f}" for f in CAMERA)):
        # skew is ~0: relative to its own largest value it shows the rounding of alpha_u.
        assert_close(compare[name], 1e-12 if name != ".cameras.skew" else 1e-11, where=name)
    for name in (".report.residuals", ".report.rms", ".report.max", ".report.mean_x"):
        assert compare[name]["absolute"] <= 1e-10, (name, compare[name])  # pixels
    # Compared on the calibrated cameras: a degenerate camera's s_11 is rounding noise, and so
    # is its condition number s_1 / s_11. s_11 is estimated from an iterate that is not yet an
    # eigenvector (within 2.6 %), so it moves to first order with that iterate's rounding, which
    # the solves scale by ~(||L||_F / s_11)^2 (~60) twice; the sharded program, with an
    # all-reduce in its loop, rounds differently: 1.7e-12 seen.
    assert_close(compare[".condition"], 1e-11, where="condition")


def test_calibration_runs_split_by_camera_without_moving_data(two_devices):
    out = two_devices["calibrate"]
    for layout in out["inputs"]:
        assert_split(layout, layout["shard_shapes"][0], where="inputs")
    for name, layout in out["layout"].items():
        if name == ".cameras.dist":  # zeros made by the decomposition: any layout will do
            continue
        shape = layout["shard_shapes"][0]
        assert shape[0] == 32, (name, layout)
        assert_split(layout, shape, where=name)
    # Two collectives, one boolean each: the DLT's inverse iteration goes on past `_MIN_STEPS`
    # while any camera has not converged, so the devices agree on that once per extra step; and
    # on whether any camera needs the moments of its own frame (`_dlt._moments`), once.
    assert_no_collectives(out["hlo"], allow_all_reduce=2, where="calibrate")
    assert set(out["hlo"]["all_reduce_shapes"]) <= {"pred[]"}
    # LAPACK calls (CPU) are partitioned along their batch axis: each device decomposes 32.
    for call in out["hlo"]["custom_calls"]:
        assert "[32," in call, call


def test_sharded_refinement_equals_the_unsharded_one(two_devices):
    out = two_devices["refine"]
    compare = out["compare"]
    for name in (".iterations", ".result", ".inliers", ".report.n_points"):
        assert compare[name]["bitwise"], name
    for name in (*(f".cameras.{f}" for f in CAMERA), ".rms_before", ".rms_after"):
        assert_close(compare[name], 1e-12, where=name)
    # (J^T J)^-1 amplifies rounding by its condition number (2e-12 measured).
    for name in (".covariance", ".standard_errors"):
        assert_close(compare[name], 1e-10, where=name)
    assert max(out["rms_after"]) < 0.6 and out["focal_error"] < 0.05  # 0.3 px noise
    for name, layout in out["layout"].items():
        assert_split(layout, [2, *layout["shard_shapes"][0][1:]], where=name)
    # The one collective: Levenberg-Marquardt's loops run until every camera has converged, so
    # the devices agree on "any camera still running" once per step (a single boolean).
    assert_no_collectives(out["hlo"], allow_all_reduce=1, where="refine")
    assert set(out["hlo"]["all_reduce_shapes"]) <= {"pred[]"}


def test_sharded_triangulation_splits_the_points(two_devices):
    out = two_devices["triangulate"]
    compare = out["compare"]
    for name in (".views", ".ok"):
        assert compare[name]["bitwise"], name
    # (rms and angle compared on the points seen at least twice: for the others they are
    # undefined, and come out 0 or NaN depending on rounding.)
    for name in (".points", ".rms", ".angle"):
        assert_close(compare[name], 1e-12, where=name)
    assert out["views"][7] == 0 and out["views"][9] == 1
    assert out["error_median"] < 1.0  # 0.5 px of noise, a 200-unit target
    # The cameras are replicated, the points split; each device triangulates 54 of the 108.
    cameras, pixels, mask = out["inputs"][:-2], out["inputs"][-2], out["inputs"][-1]
    assert all(c["spec"] == [] and c["devices"] == 2 for c in cameras)
    assert_split(pixels, [8, 54, 2], spec=(None, "batch"), where="pixels")
    assert_split(mask, [8, 54], spec=(None, "batch"), where="mask")
    assert_split(out["layout"][".points"], [54, 3], where="points")
    assert_split(out["layout"][".views"], [54], where="views")
    assert_no_collectives(out["hlo"], where="triangulate")


@pytest.mark.parametrize("name", ["reproject", "to_global"])
def test_reprojection_and_registration_keep_the_split(two_devices, name):
    out = two_devices[name]
    for path, compare in out["compare"].items():
        assert_close(compare, 1e-12, where=path)
        assert_split(out["layout"][path], [32, *out["layout"][path]["shard_shapes"][0][1:]],
                     where=path)  # fmt: skip
    assert_no_collectives(out["hlo"], where=name)


def test_uneven_splits_are_refused_and_explicit_meshes_used_as_automatic(two_devices):
    message = two_devices["odd_count_error"]
    assert message and "(63, 19, 2)" in message and "multiple of 2" in message
    explicit = two_devices["explicit_mesh"]
    assert explicit["spec"] == ["cameras"] and explicit["axis_types"] == ["AxisType.Auto"]
    assert explicit["shard_shapes"] == [[32, 19, 2], [32, 19, 2]]


# ----------------------------------------------------------------------------- this process
def test_shard_places_every_array_and_keeps_the_values():
    n = jax.device_count()
    camera = mc.Camera(
        alpha_u=jnp.full(2 * n, 800.0), alpha_v=800.0, u0=320.0, v0=240.0,
        R=jnp.eye(3), t=jnp.array([0.0, 0.0, 5.0]),
    )  # fmt: skip
    pixels = np.random.default_rng(0).random((2 * n, 6, 2))
    tree = {"camera": camera, "pixels": pixels, "count": 3, "nothing": None}
    out = mc.shard(tree)
    assert out["count"] == 3 and out["nothing"] is None
    for before, after in zip(jax.tree_util.tree_leaves(tree), jax.tree_util.tree_leaves(out)):
        if isinstance(before, int):
            continue
        assert isinstance(after, jax.Array) and isinstance(after.sharding, NamedSharding)
        np.testing.assert_array_equal(after, before)
        assert after.sharding.spec[0] == "batch" and after.sharding.num_devices == n
    assert isinstance(out["camera"], mc.Camera)
    points = mc.shard(pixels, axis=1)
    assert tuple(points.sharding.spec) == (None, "batch")
    everywhere = mc.shard(camera, axis=None)
    assert all(tuple(x.sharding.spec) == () for x in jax.tree_util.tree_leaves(everywhere))
    # A user's mesh (here over this process's devices) with its own axis name.
    mesh = Mesh(np.array(jax.devices()), ("cameras",))
    assert tuple(mc.shard(pixels, mesh).sharding.spec) == ("cameras",)


@pytest.mark.parametrize("axis", [-1, 1.0, True, "cameras"])
def test_shard_refuses_axes_it_cannot_apply_alike_to_every_array(axis):
    with pytest.raises(ValueError, match="`axis` must be a non-negative int"):
        mc.shard(np.zeros((4, 3)), axis=axis)


def test_shard_refuses_what_is_not_a_mesh():
    with pytest.raises(ValueError, match="`mesh` must be a jax.sharding.Mesh"):
        mc.shard(np.zeros(4), mesh=jax.devices())


def _run_on_two_host_devices(code: str, timeout: float) -> str:
    """The standard output of `code` run in a fresh process with 2 host devices, compiled as
    this process compiles (with XLA's older CPU emitters where conftest chose them: these checks
    are of finishing and agreeing to 1e-9, not of the last bits)."""
    flags = [*os.environ.get("XLA_FLAGS", "").split(), "--xla_force_host_platform_device_count=2"]
    env = dict(
        os.environ,
        XLA_FLAGS=" ".join(flags),
        JAX_ENABLE_X64="1",
        JAX_PLATFORMS="cpu",
        PYTHONPATH=os.pathsep.join(
            [str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")]
        ),
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=timeout
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc.stdout


def test_refinement_of_a_large_rig_split_over_host_devices_finishes():
    # 1024 cameras over 2 host devices: with LAPACK's batched kernels (the covariance's `getrf`
    # from 256 cameras, the step's `potrf`/`trsm` at 1024) both of XLA's CPU workers waited in
    # jaxlib's ParallelBatchMap for sub-tasks queued behind each other, and the call never
    # returned (docs/scaling.md); 128 cameras finished.
    code = """
import jax.numpy as jnp, mvcalib as mc
from test_refine import distorted_rig, zero_skew
_, world, pixels, mask = distorted_rig(0, 1024)
seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
out = mc.refine(*mc.shard((seed,)), world, *mc.shard((pixels, mask)))
print(len(out.ok.sharding.device_set), int(out.ok.sum()), float(jnp.max(out.rms_after)))
"""
    devices, ok, rms = _run_on_two_host_devices(code, timeout=240).split()
    assert (int(devices), int(ok)) == (2, 1024) and float(rms) < 1.0


def test_the_gradient_of_a_refinement_split_over_host_devices_finishes():
    # Implicit derivatives by a batched SVD (which spares a batch the singular system of a
    # camera that sees nothing) never returned for 64 cameras split over 2 host devices; there
    # the LU solve stays.
    code = """
import jax, jax.numpy as jnp, mvcalib as mc
from test_refine import distorted_rig, zero_skew
_, world, pixels, mask = distorted_rig(0, 64)
seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
s_seed, s_pixels, s_mask = mc.shard((seed, pixels, mask))
loss = lambda px: jnp.sum(mc.refine(s_seed, world, px, s_mask, distortion=()).rms_after)
print(bool(jnp.isfinite(jax.grad(loss)(s_pixels)).all()))
"""
    assert _run_on_two_host_devices(code, timeout=240).split() == ["True"]


def test_a_joint_rig_refinement_split_over_host_devices_finishes_and_agrees():
    # 256 anchored cameras with distortion, split over 2 host devices: the matrix-free step's
    # preconditioner factorised each camera's block by LAPACK's batched Cholesky, and the call
    # never returned (from 256 cameras of 48 points; 128 finished). It is written out there now.
    code = """
import jax, jax.numpy as jnp, equinox as eqx, numpy as np, mvcalib as mc
C = 256
rig = mc.synthetic.random_rig(jax.random.key(1), C, target=mc.targets.box_corner_grid(4),
                              noise=0.3, fill=(0.8, 0.95))
seed = mc.calibrate(rig.world, rig.pixels, rig.mask).cameras
seed = eqx.tree_at(lambda c: c.skew, seed, jnp.zeros(C))
ids = np.arange(0, 48, 5)
kw = dict(anchors=(ids, np.asarray(rig.world)[ids]), distortion=("k1", "k2"))
one = mc.refine_rig(seed, rig.world, rig.pixels, rig.mask, **kw)
s_seed, s_pixels, s_mask = mc.shard((seed, rig.pixels, rig.mask))
two = mc.refine_rig(s_seed, rig.world, s_pixels, s_mask, **kw)
rel = float(jnp.max(jnp.abs(two.rms_after - one.rms_after) / one.rms_after))
print(len(two.cameras.alpha_u.sharding.device_set), bool(one.ok), bool(two.ok), rel)
"""
    devices, ok_one, ok_two, rel = _run_on_two_host_devices(code, timeout=300).split()
    assert (int(devices), ok_one, ok_two) == (2, "True", "True")
    assert float(rel) < 1e-9


GRADIENTS_PAST_FAILURES = """
import jax, numpy as np, mvcalib as mc
rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4, noise=0.3)
few = rig.mask.at[3, 5:].set(False)  # camera 3 sees 5 points: TOO_FEW_POINTS, a NaN seed
once = rig.mask.at[1:, 2].set(False)  # point 2 is seen by camera 0 only
seed = mc.calibrate(rig.world, rig.pixels, few).cameras
refined = lambda p: mc.refine(seed, rig.world, p, few).cameras.center[0, 0]
points = lambda p: mc.triangulate(rig.cameras, p, once, refine=True).points[:2].sum()
grads = [jax.grad(f)(rig.pixels) for f in (refined, points)]
print(jax.device_count(), *(" ".join(map(repr, np.ravel(g).tolist())) for g in grads), sep="\\n")
"""


def test_gradients_split_over_host_devices_pass_over_a_failed_camera():
    # On several CPU devices the implicit derivatives are solved without LAPACK (whose batched
    # calls can hang there); LAPACK's LU, used there before, raised for the whole rig on the
    # singular system of a camera that saw too few points, and of a point seen once (a user's
    # trial). They must equal one device's (by SVD), zero through the failed camera and point.
    devices, *two = _run_on_two_host_devices(GRADIENTS_PAST_FAILURES, timeout=300).splitlines()
    with contextlib.redirect_stdout(io.StringIO()) as out:
        exec(GRADIENTS_PAST_FAILURES, {})  # here, on one device
    one_device, *one = out.getvalue().splitlines()
    assert (devices, one_device) == ("2", "1")
    (refine_1, refine_2), (points_1, points_2) = (
        (np.array(x.split(), float).reshape(4, -1, 2) for x in pair) for pair in zip(one, two)
    )
    for a, b in ((refine_1, refine_2), (points_1, points_2)):
        assert np.all(np.isfinite(b))
        assert np.abs(b - a).max() <= 1e-9 * np.abs(a).max()
    assert np.all(refine_2[3] == 0) and np.all(points_2[:, 2] == 0)
    assert np.any(refine_2[0] != 0) and np.any(points_2[:, :2] != 0)
