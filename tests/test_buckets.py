"""Shape buckets: rigs of other sizes reuse one compiled program, and padding changes nothing."""

import functools
import logging
from unittest import mock

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mvcalib as mc
from mvcalib import _buckets, _dlt, demo


def test_bucket_sizes():
    for n in range(1, 5000):
        b = _buckets.size(n)
        assert b >= n and _buckets.size(b) == b
        assert b == n if n <= 32 else b <= 1.0625 * n
        assert _buckets.size(n + 1) >= b
    assert _buckets.size(3, 64) == 64 and _buckets.size(100, 64) == 100
    assert _buckets.size(101) == 104 and _buckets.size(100_000) == 102_400
    assert _buckets.cameras_and_points(3, 15) == (64, 64)
    assert _buckets.cameras_and_points(33, 40) == (64, 64)
    assert _buckets.cameras_and_points(4096, 19) == (4096, 19)
    frames = [_buckets.size(n, 32, bits=2) for n in (1, 32, 33, 48, 49, 65, 100, 1000)]
    assert frames == [32, 32, 48, 48, 64, 96, 128, 1024]


def _rig(seed, n_cameras, n_points, noise=0.3, hidden=0.1):
    """A rig of random cameras seeing `n_points` random points, some hidden."""
    rng = np.random.default_rng(seed)
    cameras = mc.synthetic.random_rig(jax.random.key(seed), n_cameras=n_cameras).cameras
    world = rng.uniform(0.0, 160.0, (n_points, 3))
    pixels = np.asarray(cameras.project(world)) + noise * rng.standard_normal(
        (n_cameras, n_points, 2)
    )
    mask = rng.uniform(size=(n_cameras, n_points)) > hidden
    return world, pixels, mask


def _compiles(caplog, name):
    return sum(f"Compiling jit({name})" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("lens", ["pinhole", "fisheye"])
def test_eager_lens_inverses_compile_once(caplog, lens):
    """`undistort_points` and `Camera.rays` called eagerly, again and again (a user's loop over
    frames): one program each, compiled at the first call (each call compiled anew, 0.13 s
    for three pixels: a JAX user's trial)."""
    dist = [-0.2, 0.05, 0.0, 0.0, 0.0] if lens == "pinhole" else [0.05, -0.01, 0.0, 0.0]
    camera = mc.Camera(800.0, 800.0, 320.0, 240.0, np.eye(3), [0.0, 0.0, 4.0], dist=dist,
                       lens=lens)  # fmt: skip
    frames = np.random.default_rng(0).uniform(0.0, 600.0, (4, 3, 2))
    on_device = jnp.asarray(frames[3])
    for inverse in (lambda p: mc.undistort_points(camera, p), lambda p: camera.rays(p)):
        first = inverse(frames[0])
        with caplog.at_level(logging.WARNING), jax.log_compiles():
            caplog.clear()
            later = [inverse(p) for p in (frames[0], *frames[1:], on_device)]
        assert not [r for r in caplog.records if "Compiling" in r.getMessage()]
        np.testing.assert_array_equal(later[0], first)
        traced = jax.jit(inverse)(frames[2])  # (in a user's program: the same)
        np.testing.assert_allclose(later[2], traced, rtol=1e-12, atol=1e-9)


def test_a_loss_of_another_scale_compiles_nothing(caplog):
    """A robust loss's scale is data: an annealing loop over scales (a JAX user's trial) reuses
    the program, and each scale acts (the points set aside change with it)."""
    world, pixels, mask = _rig(1, 3, 19, noise=0.5)
    pixels[:, 0] += 6.0  # one wild point in every camera
    seed = mc.calibrate(world, pixels, mask).cameras
    refine = lambda loss: mc.refine(seed, world, pixels, mask, distortion=(), loss=loss)  # noqa: E731
    refine(mc.Huber(1.0))
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        caplog.clear()
        out = {s: refine(mc.Huber(s)) for s in (0.25, 2.0, 20.0)}
    assert not [r for r in caplog.records if "Compiling" in r.getMessage()]
    inliers = {s: int(o.inliers.sum()) for s, o in out.items()}
    assert inliers[0.25] < inliers[2.0] < inliers[20.0] == int(np.sum(mask))
    assert repr(mc.Huber(2.0)) == "Huber(2)" and float(mc.Cauchy(0.5).scale) == 0.5
    with pytest.raises(ValueError, match="positive"):
        mc.Cauchy(0.0)


def test_a_users_jit_compiles_quickly_with_the_quick_options():
    """`mc.quick_compiler_options()`: options this XLA takes (an unknown one is an error at
    compile time), and a user's program compiled with them answers as mvcalib's calls do."""
    options = mc.quick_compiler_options()
    assert set(options) <= set(_buckets._QUICK) and (jax.default_backend() != "cpu" or options)
    world, pixels, mask = _rig(3, 5, 19)
    mine = jax.jit(lambda p: mc.calibrate(world, p, mask).cameras.alpha_u, compiler_options=options)
    np.testing.assert_allclose(mine(pixels), mc.calibrate(world, pixels, mask).cameras.alpha_u,
                               rtol=1e-9)  # fmt: skip


# The script of issue 39: rigs of 3 to 33 cameras, 15 to 40 points.
RIGS = ((3, 15), (5, 22), (7, 40), (12, 19), (20, 31), (33, 27))


def test_rigs_of_many_sizes_compile_calibrate_at_most_twice(caplog):
    rigs = [_rig(i, c, n) for i, (c, n) in enumerate(RIGS)]
    jax.clear_caches()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        results = [mc.calibrate(*rig) for rig in rigs]
    assert _compiles(caplog, "_calibrate") <= 2
    for (world, pixels, mask), result in zip(rigs, results):
        assert result.P.shape == (len(pixels), 3, 4) and result.ok.all()
        # the same as the rig's own shape, traced (no padding)
        alone = jax.jit(mc.calibrate)(world, pixels, mask)
        np.testing.assert_array_equal(result.status, alone.status)
        scale = np.abs(np.asarray(alone.P)).max(axis=(-2, -1), keepdims=True)
        assert np.max(np.abs(result.P - alone.P) / scale) < 1e-12


def test_padding_keeps_batch_shapes_and_single_cameras():
    world, pixels, mask = _rig(0, 6, 19)
    grid = mc.calibrate(world, pixels.reshape(2, 3, 19, 2), mask.reshape(2, 3, 19))
    assert grid.P.shape == (2, 3, 3, 4) and grid.report.rms.shape == (2, 3)
    assert grid.report.residuals.shape == (2, 3, 19, 2) and grid.report.mask.shape == (2, 3, 19)
    one = mc.calibrate(world, pixels[4], mask[4])
    assert one.P.shape == (3, 4) and one.cameras.batch_shape == ()
    np.testing.assert_allclose(one.P, grid.P[1, 1], rtol=0, atol=1e-12 * np.abs(one.P).max())
    refined = mc.calibrate(world, pixels[:2], mask[:2], refine=True)
    assert refined.refinement.inliers.shape == (2, 19)
    assert refined.report.residuals.shape == refined.refinement.report.residuals.shape == (2, 19, 2)
    np.testing.assert_array_equal(refined.refinement.inliers, mask[:2])
    np.testing.assert_array_equal(refined.report.mask, mask[:2])
    by_hand = mc.refine(refined.cameras, world, pixels[:2], mask[:2])
    assert by_hand.inliers.shape == by_hand.report.mask.shape == (2, 19)
    assert by_hand.report.residuals.shape == (2, 19, 2) and by_hand.covariance.shape == (2, 14, 14)
    points = mc.triangulate(refined.cameras, pixels[:2, :7], mask[:2, :7])
    assert points.points.shape == (7, 3) and points.ok.shape == (7,)


def test_refined_calibration_is_the_same_padded_or_not():
    world, pixels, mask = _rig(1, 5, 30)
    padded = mc.calibrate(world, pixels, mask, refine=True)
    alone = jax.jit(functools.partial(mc.calibrate, refine=True))(world, pixels, mask)
    np.testing.assert_array_equal(padded.status, alone.status)
    np.testing.assert_array_equal(padded.refinement.result, alone.refinement.result)
    # the solver stops at steps of 1e-5 standard errors: its answer is that close, not closer
    np.testing.assert_allclose(padded.report.rms, alone.report.rms, rtol=1e-9)


@pytest.mark.parametrize("noise", [0.0, 0.5, 5.0])
def test_compact_dlt_equals_the_written_out_one(noise):
    """Small programs take LAPACK's eigenvectors and sorted medians (`_dlt.compact`); they give
    the written-out inverse iteration's cameras and statuses."""
    world, pixels, mask = _rig(2, 40, 24, noise=noise)
    mask[3, 6:] = False  # six points: the least there is
    mask[4, 5:] = False  # too few
    world_far = world + 1e4  # the target far from the world's origin (each camera's own moments)
    for w in (world, world_far):
        args = (jnp.asarray(w), jnp.asarray(pixels), jnp.asarray(mask), 1.5e-8, 0.05)
        P, status, condition, mirrored = jax.jit(functools.partial(_dlt._solve, compact=True))(
            *args
        )
        P0, status0, condition0, mirrored0 = jax.jit(_dlt._solve)(*args)
        np.testing.assert_array_equal(status, status0)
        np.testing.assert_array_equal(mirrored, mirrored0)
        ok = np.asarray(status0) == 0
        scale = np.abs(np.asarray(P0)[ok]).max(axis=(-2, -1), keepdims=True)
        assert np.max(np.abs(np.asarray(P)[ok] - np.asarray(P0)[ok]) / scale) < 1e-12
        # the written-out form estimates s_11 from above, LAPACK's is exact: the condition
        # number from below (here within 11 %; 16 % noise-free with the target far from the
        # origin, in this test alone in one process, at 18378f3 too), exact
        assert np.all(np.asarray(condition)[ok] >= np.asarray(condition0)[ok] * (1 - 1e-9))
        assert np.all(np.asarray(condition)[ok] <= np.asarray(condition0)[ok] * 1.25)


# ------------------------------------------------------------------------------ compiling ahead
def _compiled_on(caplog, name):
    """The threads on which XLA compiled the program `name`, one entry per compile (at DEBUG
    level off the main thread: `jax.log_compiles()` holds for the thread that enters it)."""
    done = f"Finished XLA compilation of jit({name})"
    return [r.threadName for r in caplog.records if done in r.getMessage()]


@pytest.mark.parametrize(
    "cameras, points, to",
    [(6, 25, np.asarray), (64, 64, np.asarray), (64, 64, jnp.asarray)],
    ids=["padded", "bucket-shaped-numpy", "bucket-shaped-jax"],
)
def test_refinement_compiles_once_on_a_second_thread(caplog, cameras, points, to):
    """`calibrate(..., refine=True)` has XLA compile the refinement while it compiles and runs
    the DLT: once, on another thread, and the answer is the traced call's. So does a rig already
    of its bucket's shape, which is not padded (64 cameras of 64 points)."""
    world, pixels, mask = map(to, _rig(3, cameras, points))
    assert _buckets.cameras_and_points(cameras, points) == (cameras, points) or cameras == 6
    jax.clear_caches()
    with caplog.at_level(logging.DEBUG), jax.log_compiles():
        result = mc.calibrate(world, pixels, mask, refine=True)
        again = mc.calibrate(world, pixels, mask, refine=True)
    assert _compiled_on(caplog, "_calibrate") == ["MainThread"]
    for name in ("_refine_all", "_checked"):  # the check of the refined cameras too
        threads = _compiled_on(caplog, name)
        assert len(threads) == 1 and threads[0].startswith("mvcalib-compile"), (name, threads)
    np.testing.assert_array_equal(result.cameras.R, again.cameras.R)
    alone = jax.jit(functools.partial(mc.calibrate, refine=True))(world, pixels, mask)
    np.testing.assert_allclose(result.report.rms, alone.report.rms, rtol=1e-9)


def _board_rig():
    rig = mc.synthetic.board_rig(jax.random.key(0), n_cameras=4, n_frames=30, noise=0.3)
    return mc.calibrate_rig(rig.target, rig.pixels, rig.mask)


def _planar_views():
    from test_planar import WORLD, observe

    return mc.calibrate_planar(WORLD, *observe(noise=0.3))


def _photos():
    target = mc.targets.box_corner()
    rig = mc.synthetic.random_rig(jax.random.key(0), 3)
    photos = [mc.synthetic.render(rig.cameras[i], target, key=i) for i in range(3)]
    seeds = [rig.cameras[i] for i in range(3)]  # (seeded: a second look, judged by triangulating)
    return mc.calibrate_images(photos, target, seeds=seeds, refine=True).calibration


@pytest.mark.parametrize(
    "call, programs",
    [
        (_board_rig, ("_start_pairs", "_start_own", "_start_rig", "_calibrate_rig")),
        (_planar_views, ("_closed_form", "_refine_views", "_finish")),
        (_photos, ("_calibrate", "_refine_all", "_triangulate")),
        (lambda: demo.run().calibration, ("_paper_scene", "_pipeline")),
    ],
)
def test_programs_compile_once_on_other_threads(caplog, call, programs):
    """A call that runs several programs one after the other has them all compiled at once, on
    other threads, each once; the answer is that of the programs compiled on the spot."""
    jax.clear_caches()
    with caplog.at_level(logging.DEBUG), jax.log_compiles():
        result = call()
        again = call()
    for name in programs:
        threads = _compiled_on(caplog, name)
        assert len(threads) == 1 and threads[0].startswith("mvcalib-compile"), (name, threads)
    assert bool(np.all(np.asarray(result.ok)))
    jax.tree_util.tree_map(np.testing.assert_array_equal, result, again)
    jax.clear_caches()
    with mock.patch.object(_buckets, "ahead", lambda *args, **kwargs: None):
        alone = call()  # compiled on the spot, on this thread
    jax.tree_util.tree_map(np.testing.assert_array_equal, result, alone)


def test_ahead_is_only_a_hint():
    calls = []

    @functools.partial(_buckets.jit, static_argnames="k")
    def scaled(x, k):
        calls.append(k)  # (at each trace)
        return x * k

    def checked(x, k):
        if k < 0:
            raise ValueError("negative")
        return scaled(x, k=k)

    x = np.arange(3.0)
    _buckets.ahead(checked, x, -1)  # fails before its program: nothing, no error
    assert calls == [] and not scaled._compiling
    jax.jit(lambda x: _buckets.ahead(checked, x, 2) or x)(x)  # inside a trace: nothing
    assert calls == []
    stand_in = _buckets.ahead(checked, x, 2)  # traced here, compiled on another thread
    assert calls == [2] and len(scaled._compiling) == 1
    # what it returns stands in for the program's outputs (NaN of their shape and type), so
    # that the programs that take them can be compiled ahead too
    assert isinstance(stand_in, np.ndarray) and stand_in.shape == (3,) and np.isnan(stand_in).all()
    np.testing.assert_array_equal(checked(x, 2), 2 * x)  # waits for it: no second trace
    assert calls == [2] and not scaled._compiling
    # compiled already (ahead, or by a call): nothing to do but stand in for the outputs
    assert np.isnan(_buckets.ahead(checked, x, 2)).all()
    y = np.arange(4.0)
    np.testing.assert_array_equal(checked(y, 2), 2 * y)
    assert _buckets.ahead(checked, y, 2).shape == (4,)
    assert calls == [2, 2] and not scaled._compiling


# --------------------------------------------------------------------------------- side by side
def test_a_batch_is_cut_into_equal_pieces_one_per_core():
    with mock.patch.object(_buckets, "_cores", lambda: 2):
        assert [_buckets.pieces(n) for n in (64, 32, 31, 33, 100, 1)] == [2, 2, 1, 1, 2, 1]
    with mock.patch.object(_buckets, "_cores", lambda: 8):
        assert [_buckets.pieces(n) for n in (1024, 64, 48, 96)] == [8, 4, 2, 4]
    with mock.patch.object(_buckets, "_cores", lambda: 1):
        assert _buckets.pieces(1024) == 1


def test_a_refinement_in_pieces_is_the_whole_to_the_last_bit(caplog):
    """`refine` and `calibrate(..., refine=True)` called from Python run a rig's cameras in
    equal pieces side by side, one per core (here four pieces of 25 cameras, whatever this
    machine's cores): one program compiled for all the pieces, and every camera's answer that of
    the rig solved in one piece, bit for bit (each camera's problem is solved on its own); the
    reports' RMS to rounding (a sum vectorised across the cameras: 1 ulp apart in four pieces)."""
    world, pixels, mask = _rig(5, 100, 30)
    seed = mc.calibrate(world, pixels, mask).cameras
    options = dict(distortion=("k1",), loss=mc.Huber(1.0))
    with mock.patch.object(_buckets, "_cores", lambda: 1):
        whole = mc.refine(seed, world, pixels, mask, **options)
        whole_pipeline = mc.calibrate(world, pixels, mask, refine=True)
    jax.clear_caches()
    with mock.patch.object(_buckets, "_cores", lambda: 4):
        assert _buckets.pieces(100) == 4
        with caplog.at_level(logging.DEBUG), jax.log_compiles():
            pieces = mc.refine(seed, world, pixels, mask, **options)
        assert len(_compiled_on(caplog, "_refine_all")) == 1
        pieces_pipeline = mc.calibrate(world, pixels, mask, refine=True)
    assert bool(np.asarray(whole.ok).all())
    same = functools.partial(np.testing.assert_allclose, rtol=1e-15, atol=0)
    for a, b in ((pieces, whole), (pieces_pipeline, whole_pipeline)):
        jax.tree_util.tree_map(same, a, b)
        jax.tree_util.tree_map(np.testing.assert_array_equal, a.cameras, b.cameras)
    np.testing.assert_array_equal(pieces.covariance, whole.covariance)
    # under a setting of the caller's thread alone, the pieces run there (in float32 here)
    with jax.enable_x64(False), mock.patch.object(_buckets, "_cores", lambda: 4):
        single = mc.refine(seed, world, pixels, mask, distortion=("k1",))
    with jax.enable_x64(False), mock.patch.object(_buckets, "_cores", lambda: 1):
        single_whole = mc.refine(seed, world, pixels, mask, distortion=("k1",))
    assert single.cameras.alpha_u.dtype == np.float32
    jax.tree_util.tree_map(np.testing.assert_array_equal, single.cameras, single_whole.cameras)


def test_recordings_of_other_lengths_reuse_the_rig_s_programs(caplog):
    """`calibrate_rig` pads a concrete rig's frames up to a bucket (32, 48, 64, 96, ...) with
    frames nobody saw: recordings of 40 and 45 frames, and the second from another reference
    camera, compile each of its programs once; other options (loss, free parameters) compile
    again only the programs of the solves, on other threads. The answer is the unpadded
    program's to its solves' tolerance (they stop at steps of 1e-5 standard errors); measured:
    the same steps, centres 1.3e-6 standard errors apart."""
    import mvcalib._rig

    rig = mc.synthetic.board_rig(jax.random.key(0), n_cameras=4, n_frames=45, noise=0.3)
    jax.clear_caches()
    with caplog.at_level(logging.DEBUG), jax.log_compiles():
        short = mc.calibrate_rig(rig.target, rig.pixels[:, :40], rig.mask[:, :40])
        full = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
        # another reference camera is an argument of the same programs (it was a constant)
        other = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, reference=2)
        for name in ("_start_pairs", "_start_own", "_start_rig", "_calibrate_rig"):
            assert len(_compiled_on(caplog, name)) == 1, name
        robust = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, loss=mc.Huber(1.0),
                                  fix="distortion")  # fmt: skip
    for name in ("_start_pairs", "_start_rig"):
        assert len(_compiled_on(caplog, name)) == 1, name
    for name in ("_start_own", "_calibrate_rig"):  # (the first program's a stand-in all the same)
        threads = _compiled_on(caplog, name)
        assert len(threads) == 2 and threads[1] != "MainThread", (name, threads)
    assert bool(robust.ok.all()) and "k1" not in robust.parameter_names
    assert bool(other.ok.all()) and np.allclose(other.cameras.center[2], 0.0)
    np.testing.assert_allclose(other.rms, full.rms, rtol=1e-7)
    N = rig.target.shape[0]
    assert short.target_poses.t.shape == (40, 3) and short.residuals.shape == (4, 40, N, 2)
    assert full.frame_rms.shape == (45,) and full.used.shape == (4, 45, N)
    with mock.patch.object(mvcalib._rig, "FRAME_BITS", 30):  # (no padding)
        alone = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    np.testing.assert_array_equal(full.status, alone.status)
    assert int(full.iterations) == int(alone.iterations)
    off = np.linalg.norm(np.asarray(full.cameras.center - alone.cameras.center), axis=-1)[1:]
    assert np.all(off < 1e-5 * np.linalg.norm(np.asarray(alone.position_std), axis=-1)[1:])
    np.testing.assert_allclose(full.rms, alone.rms, rtol=1e-9)
    np.testing.assert_array_equal(np.isnan(full.frame_rms), np.isnan(alone.frame_rms))


def test_rigs_of_five_and_six_cameras_share_the_rig_s_programs(caplog):
    """`calibrate_rig` pads a concrete rig's cameras up to a bucket (1-4 as they are, then 6, 8,
    12, 16, ...) with cameras that see nothing: a rig of 5 cameras and one of 6 compile each of
    its programs once. The 5 cameras' answer is the unpadded one's to the solves' tolerance,
    the same statuses and steps."""
    import mvcalib._rig

    rig = mc.synthetic.board_rig(jax.random.key(0), n_cameras=6, n_frames=40, noise=0.3)
    jax.clear_caches()
    with caplog.at_level(logging.DEBUG), jax.log_compiles():
        five = mc.calibrate_rig(rig.target, rig.pixels[:5], rig.mask[:5])
        six = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    for name in ("_start_pairs", "_start_own", "_start_rig", "_calibrate_rig"):
        assert len(_compiled_on(caplog, name)) == 1, name
    assert bool(six.ok.all()) and six.cameras.batch_shape == (6,)
    assert five.residuals.shape[0] == five.covariance.shape[0] == five.alone_rms.shape[0] == 5
    with mock.patch.object(mvcalib._rig, "CAMERA_BITS", 30):  # (no padding)
        alone = mc.calibrate_rig(rig.target, rig.pixels[:5], rig.mask[:5])
    np.testing.assert_array_equal(five.status, alone.status)
    assert int(five.iterations) == int(alone.iterations)
    off = np.linalg.norm(np.asarray(five.cameras.center - alone.cameras.center), axis=-1)[1:]
    assert np.all(off < 1e-5 * np.linalg.norm(np.asarray(alone.position_std), axis=-1)[1:])
    np.testing.assert_allclose(five.rms, alone.rms, rtol=1e-9)


def test_photos_of_other_numbers_reuse_the_planar_programs(caplog):
    """`calibrate_planar` pads a concrete call's views up to a bucket (16, 24, 32, 48, ...) with
    views nobody saw: 17 and 20 views compile each of its programs once; the answer is the
    unpadded one's to the solve's tolerance, the same statuses."""
    import mvcalib._planar

    rig = mc.synthetic.board_rig(jax.random.key(3), n_cameras=1, n_frames=60, noise=0.3)
    seen = np.flatnonzero(np.asarray(rig.mask)[0].sum(-1) >= 20)[:20]
    target, pixels, mask = (
        rig.target,
        np.asarray(rig.pixels)[0, seen],
        np.asarray(rig.mask)[0, seen],
    )
    jax.clear_caches()
    with caplog.at_level(logging.DEBUG), jax.log_compiles():
        short = mc.calibrate_planar(target, pixels[:17], mask[:17])
        full = mc.calibrate_planar(target, pixels, mask)
    for name in ("_closed_form", "_refine_views", "_finish"):
        assert len(_compiled_on(caplog, name)) == 1, name
    assert short.status.shape == (17,) and short.camera.R.shape == (17, 3, 3)
    assert (
        full.report.residuals.shape == (20, mask.shape[1], 2) and full.homographies.shape[0] == 20
    )
    with mock.patch.object(mvcalib._planar, "VIEW_BITS", 30):  # (no padding)
        alone = mc.calibrate_planar(target, pixels, mask)
    np.testing.assert_array_equal(full.status, alone.status)
    np.testing.assert_allclose(full.K, alone.K, rtol=1e-9)
    np.testing.assert_allclose(full.rms, alone.rms, rtol=1e-12)


@pytest.mark.parametrize("kind", ["anchored", "free points", "shared intrinsics"])
def test_rigs_of_other_sizes_reuse_the_joint_refinement(caplog, kind):
    """`refine_rig` pads a concrete rig up to a bucket of cameras and points (at least 4 and 64)
    with cameras that see nothing and points nobody sees: rigs of 3 and 4 cameras of 27 and 48
    points compile its solve once. The answer is the unpadded solve's to its tolerance (steps of
    1e-5 relative; measured: the same steps, RMS 1e-14 to 1e-8 apart relative)."""
    import mvcalib._bundle

    def problem(n_cameras, n):
        target = mc.targets.box_corner_grid(n)
        rig = mc.synthetic.random_rig(jax.random.key(n_cameras), n_cameras, target, noise=0.3)
        world, pixels, mask = (np.asarray(x) for x in (rig.world, rig.pixels, rig.mask))
        if kind == "shared intrinsics":  # one physical camera seen in several snapshots
            same = tuple(np.full(n_cameras, v) for v in (1400.0, 1392.0, 512.0, 541.0))
            cameras = eqx.tree_at(lambda c: (c.alpha_u, c.alpha_v, c.u0, c.v0), rig.cameras, same)
            observed = mc.synthetic.observe(jax.random.key(n), cameras, world, 0.3, rig.image_size)
            pixels, mask = (np.asarray(x) for x in observed[1:])
        seed = mc.calibrate(world, pixels, mask).cameras
        seed = jax.tree_util.tree_map(
            np.asarray, eqx.tree_at(lambda c: c.skew, seed, 0 * seed.skew)
        )
        options = dict(distortion=())
        if kind == "shared intrinsics":
            options["shared_intrinsics"] = True
        else:  # the same 9 anchors (their number is part of the program's shape)
            options.update(anchors=(np.arange(9), world[:9]), anchor_sigma=0.1)
        if kind == "free points":
            world = world + np.random.default_rng(n).normal(scale=0.5, size=world.shape)
            options.update(points="free", fix=("u0", "v0", "skew"))  # (3 cameras: else slow)
        return (seed, world, pixels, mask), options

    problems = [problem(c, n) for c, n in ((4, 3), (3, 4), (4, 4))]
    jax.clear_caches()
    with caplog.at_level(logging.DEBUG), jax.log_compiles():
        padded = [mc.refine_rig(*args, **options) for args, options in problems]
    assert len(_compiled_on(caplog, "_refine_rig")) == 1
    no_padding = {"MIN_CAMERAS": 1, "MIN_POINTS": 1, "BITS": 30}
    for (args, options), out in zip(problems, padded):
        C, N = args[2].shape[:2]
        assert out.cameras.batch_shape == (C,) and out.world.shape == (N, 3)
        assert out.rms_after.shape == out.used.shape == (C,)
        with mock.patch.multiple(mvcalib._bundle, **no_padding):
            alone = mc.refine_rig(*args, **options)
        assert bool(out.ok) and int(out.iterations) == int(alone.iterations)
        np.testing.assert_allclose(out.rms_after, alone.rms_after, rtol=1e-7)
        scale = np.abs(np.asarray(alone.cameras.center)).max()
        assert np.abs(np.asarray(out.cameras.center - alone.cameras.center)).max() < 1e-7 * scale
        np.testing.assert_allclose(
            out.world, alone.world, rtol=0, atol=1e-7 * np.abs(args[1]).max()
        )
        np.testing.assert_allclose(out.transform.t, alone.transform.t, atol=1e-7 * scale)


def test_calls_inside_a_users_trace_on_arrays_it_closes_over():
    """Arrays a jitted function closes over are concrete, but what is computed from them there is
    traced: these calls took the eager path (padding, checks on the host) and raised JAX's
    TracerArrayConversionError or ConcretizationTypeError (a JAX user's trial). The answers equal
    the eager calls' (to the solvers' tolerance: the eager ones are padded)."""
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4, noise=0.3)
    W, P, M = rig.world, rig.pixels, rig.mask
    eager = mc.calibrate(W, P, M)
    alpha = jax.jit(lambda x: mc.calibrate(W, P, M).cameras.alpha_u * x)(1.0)
    np.testing.assert_allclose(alpha, eager.cameras.alpha_u, rtol=1e-12)
    refined = mc.refine(eager.cameras, W, P, M, loss=mc.Huber(1.0))
    traced = jax.jit(lambda s, c: mc.refine(s, W, P, M, loss=mc.Huber(c)).cameras.alpha_u)
    np.testing.assert_allclose(traced(eager.cameras, 1.0), refined.cameras.alpha_u, rtol=1e-5)
    board = mc.synthetic.board_rig(jax.random.key(0), n_cameras=3, n_frames=20, noise=0.3)
    T, BP, BM = board.target, board.pixels, board.mask
    start = mc.calibrate_rig(T, BP, BM)
    held = mc.calibrate_rig(T, BP, BM, cameras=start.cameras, fix="intrinsics")
    on = jax.jit(lambda c: mc.calibrate_rig(T, BP, BM, cameras=c, fix="intrinsics").cameras.t)
    np.testing.assert_allclose(on(start.cameras), held.cameras.t, rtol=1e-5, atol=1e-9)
