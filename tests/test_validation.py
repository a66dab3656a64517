import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mvcalib as mc


@pytest.fixture(scope="module")
def rig():
    return mc.synthetic.random_rig(jax.random.key(40), n_cameras=2, noise=0.3)


@pytest.mark.parametrize("fn", [mc.dlt, mc.calibrate])
def test_mismatched_point_counts(rig, fn):
    with pytest.raises(ValueError, match="19 points but `pixels` has 18"):
        fn(rig.world, rig.pixels[:, :18])


def test_wrong_trailing_shapes(rig):
    with pytest.raises(ValueError, match=r"`world` must have shape \(\.\.\., N, 3\)"):
        mc.dlt(rig.world[:, :2], rig.pixels)
    with pytest.raises(ValueError, match=r"`pixels` must have shape \(\.\.\., N, 2\)"):
        mc.dlt(rig.world, jnp.concatenate([rig.pixels, rig.pixels[..., :1]], -1))


def test_non_broadcasting_camera_axes(rig):
    with pytest.raises(ValueError, match="do not broadcast"):
        mc.dlt(jnp.broadcast_to(rig.world, (3, 19, 3)), rig.pixels)


def test_fewer_than_six_points(rig):
    with pytest.raises(ValueError, match="at least 6 points"):
        mc.calibrate(rig.world[:5], rig.pixels[:, :5])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_visible_entries(rig, bad):
    pixels = np.array(rig.pixels)
    pixels[1, 7, 1] = bad
    with pytest.raises(ValueError, match=r"`pixels` has 1 non-finite .* index \(1, 7\)"):
        mc.dlt(rig.world, pixels)
    mask = np.ones((2, 19), bool)
    mask[1, 7] = False
    assert np.all(np.isfinite(np.asarray(mc.dlt(rig.world, pixels, mask))))


@pytest.mark.parametrize("dtype", [np.complex128, np.bool_, np.float16, object, jnp.bfloat16])
def test_wrong_dtypes(rig, dtype):
    with pytest.raises(ValueError, match="`pixels`") as error:
        mc.dlt(rig.world, np.asarray(rig.pixels).astype(dtype))
    if dtype in (np.float16, jnp.bfloat16):  # floating point, but too coarse: said so
        assert "too coarse for calibration" in str(error.value)


def test_strings_are_refused(rig):
    with pytest.raises(ValueError, match="`world`"):
        mc.dlt(np.asarray(rig.world).astype(str), rig.pixels)


def test_lists_and_integers_are_accepted(rig):
    world = np.asarray(rig.world)
    pixels = np.rint(np.asarray(rig.pixels[0])).astype(int)
    P = mc.dlt(world.tolist(), pixels.tolist())
    np.testing.assert_allclose(P, mc.dlt(world, pixels.astype(float)), rtol=1e-12, atol=1e-15)


def test_mask_dtype_and_shape(rig):
    with pytest.raises(ValueError, match="boolean"):
        mc.dlt(rig.world, rig.pixels, np.ones((2, 19), int))
    with pytest.raises(ValueError, match="does not broadcast"):
        mc.dlt(rig.world, rig.pixels, np.ones((2, 18), bool))


def test_ragged_lists():
    with pytest.raises(ValueError, match="rectangular"):
        mc.dlt([[0, 0, 0], [1, 2]] * 4, [[0, 0]] * 8)


def test_procrustes_inputs():
    with pytest.raises(ValueError, match="same points"):
        mc.procrustes(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="at least 3"):
        mc.procrustes(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="non-negative"):
        mc.procrustes(np.eye(3), np.eye(3), weights=np.array([1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="NaN"):
        mc.procrustes(np.eye(3), np.full((3, 3), np.nan))


def test_validation_accepts_tracers(rig):
    # shape checks are static, value checks are skipped: grad and jit go through the boundary
    g = jax.grad(lambda px: jnp.sum(mc.dlt(rig.world, px, rig.mask)[..., 0, 0]))(rig.pixels)
    assert np.all(np.isfinite(np.asarray(g)))
    with pytest.raises(ValueError, match="at least 6 points"):
        jax.jit(lambda px: mc.dlt(rig.world[:5], px))(rig.pixels[:, :5])


def test_camera_dist_shape():
    with pytest.raises(ValueError, match=r"\(k1, k2, p1, p2, k3\)"):
        mc.Camera(1.0, 1.0, 0.0, 0.0, np.eye(3), np.zeros(3), dist=np.zeros(4))


NUMPY_IN_FLOAT32 = """
import warnings
warnings.simplefilter("error")  # any warning fails the run
import jax, numpy as np
import mvcalib as mc
rig = mc.synthetic.random_rig(jax.random.key(0), 3)
world, pixels = (np.asarray(x, np.float64) for x in (rig.world, rig.pixels))
mask = np.asarray(rig.mask)
fit = mc.calibrate(world, pixels, mask, refine=True)
mc.refine(fit.cameras, world, pixels, mask)
mc.triangulate(fit.cameras, np.asarray(fit.cameras.project(world), np.float64))
mc.procrustes(world, world + 1.0)
mc.rodrigues(np.array([0.1, 0.2, 0.3]))
board = mc.synthetic.board_rig(jax.random.key(0), 3, 20, noise=0.3)
target, views, seen = (np.asarray(x) for x in (board.target, board.pixels, board.mask))
mc.calibrate_rig(target.astype(np.float64), views.astype(np.float64), seen)
use = seen[0].sum(1) >= 4
mc.calibrate_planar(target.astype(np.float64), views[0][use].astype(np.float64), seen[0][use])
dots = mc.targets.box_corner()
photos = [mc.synthetic.render(rig.cameras[i], dots, key=i) for i in range(3)]
mc.calibrate_images(photos, dots, seeds=[rig.cameras[i] for i in range(3)])
print(fit.cameras.R.dtype)
"""


def test_numpy_float64_input_without_x64_gives_no_warning():
    """JAX's default (x64 off) with NumPy float64 data, the common case: computed in float32
    without a warning (`jnp.result_type` of a float64 dtype warns; the library promotes in NumPy).
    In a fresh process: the tests run with x64 on."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-c", NUMPY_IN_FLOAT32], capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["float32"]


def test_float32_world_far_from_the_origin_warns(rig):
    """UTM-like coordinates of a 16 cm target in float32 (x64 off, or float32 data) are rounded
    to 0.12 units: the cameras came out at 0.8 px RMS against 0.35 px, with no word. A warning
    now says so; a float32 world near the origin, or in float64, gives none."""
    world, pixels = (np.asarray(x, np.float32) for x in (rig.world, rig.pixels))
    far = world + np.float32([5e5, 4e6, 0])
    with pytest.warns(UserWarning, match="float32 rounds it by up to 0.12") as caught:
        cameras = mc.calibrate(far, pixels, rig.mask).cameras
        mc.refine(cameras, far, pixels, rig.mask)
    assert len(caught) == 2 and all(w.filename == __file__ for w in caught)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mc.calibrate(world, pixels, rig.mask)
        mc.calibrate(far.astype(np.float64), pixels.astype(np.float64), rig.mask)
    # triangulation, whose frame is the cameras' (a benchmark trial: 0.16 m off in UTM, all ok)
    near = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32), rig.cameras)
    t = near.t - np.einsum("cij,j->ci", near.R, np.float32([5e5, 4e6, 0]))
    moved = mc.Camera(near.alpha_u, near.alpha_v, near.u0, near.v0, near.R, t)
    with pytest.warns(UserWarning, match="the rig is float32 and lies up to") as caught:
        mc.triangulate(moved, pixels, rig.mask)
    assert len(caught) == 1 and caught[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mc.triangulate(near, pixels, rig.mask)


def _misuses(rig):
    """Plausible slips (from a trial of the API), each with the words its error must say."""
    W, P, M = rig.world, rig.pixels, rig.mask
    cameras = mc.calibrate(W, P, M).cameras
    board = mc.synthetic.board_rig(jax.random.key(0), n_cameras=3, n_frames=10)
    T, BP, BM = board.target, board.pixels, board.mask
    return [
        (lambda: mc.calibrate(W, P, M, refine="yes"), TypeError, "got 'yes'"),
        (lambda: jax.jit(mc.calibrate)(W, P, M, refine=True), TypeError, "make it static"),
        (lambda: mc.refine(cameras, W, P, M, loss="huber"), TypeError, r"mc.Huber\(scale\)"),
        (lambda: mc.refine(cameras, W, P, M, distortion=True), TypeError, "got True"),
        (lambda: mc.refine(cameras, W, P, M, distortion="k9"), ValueError,
         r"use any of \('k1', 'k2', 'p1', 'p2', 'k3'\) or the groups \('distortion',\)"),
        (lambda: mc.calibrate_rig(T, BP, BM, lens="fish-eye"), ValueError, "`lens` is one of"),
        (lambda: mc.calibrate_rig(T, BP, BM, cameras=[board.cameras[0]]), TypeError, "got list"),
        (lambda: mc.calibrate_rig(T, BP, BM, loss="huber"), TypeError, r"mc.Cauchy\(scale\)"),
        (lambda: jax.jit(mc.calibrate_rig)(T, BP, BM), ValueError, "close over it"),
        (lambda: mc.refine(cameras, W, P[0], M[0]), ValueError,
         r"cameras of shape \(2,\) but the correspondences are of \(\)"),
        (lambda: mc.refine(cameras[np.array([0, 1, 0])], W, P, M), ValueError, "its own pixels"),
        (lambda: mc.calibrate_images([np.zeros((64, 64))], "box_corner"), TypeError,
         r"mc.targets.box_corner\(\) or mc.targets.from_file\(path\); got str"),
        (lambda: mc.detect_dots("cam0.png"), ValueError, r"mc.read_image\(path\)"),
        (lambda: mc.calibrate_planar(T, _seen(BP, BM)[0][..., ::-1], _seen(BP, BM)[1],
                                     image_size=board.image_size), ValueError,
         r"visible pixels lie outside the image of `image_size` \(1280, 800\).*\(x = column"),
        (lambda: mc.calibrate_planar(T, *_seen(BP, BM), image_size=1280), ValueError,
         r"`image_size` is \(width, height\) in pixels; got 1280"),
        (lambda: mc.triangulate(cameras, P[:, 0]), ValueError,
         r"`pixels` must have shape \(\.\.\., C, N, 2\); got \(2, 2\)"),
        (lambda: mc.label_grid(np.zeros((64, 64)), 4, 5), TypeError,
         r"takes the dots `mc.detect_dots\(image\)` found, a Detection; got ndarray"),
        (lambda: mc.label_dots(_detection(), mc.targets.box_corner().points), TypeError,
         "label_dots's `target` is an mvcalib.targets.Target"),
        (lambda: mc.match_dots(np.zeros((64, 64)), mc.targets.box_corner(), cameras[0]),
         TypeError, "match_dots takes the dots"),
        (lambda: mc.observe_grid([[np.zeros((64, 64))]], np.zeros((20, 3))), TypeError,
         r"`grid` is an mvcalib.targets.Target"),
        (lambda: mc.detect_dots(np.zeros((64, 64)), dark_dots="no"), TypeError,
         "`dark_dots` is True or False; got 'no'"),
        (lambda: jax.jit(mc.calibrate)(W, P, M, skew=False), TypeError,
         r"`skew` of mc.calibrate is an option.*static_argnames='skew'"),
        (lambda: jax.jit(mc.calibrate)(W, P, M, max_relative_rms=0.1), TypeError,
         "`max_relative_rms` of mc.calibrate is an option"),
        (lambda: jax.jit(mc.triangulate)(cameras, P, M, min_angle=2.0), TypeError,
         "`min_angle` of mc.triangulate is an option"),
        (lambda: jax.jit(mc.refine)(cameras, W, P, M, max_steps=20), TypeError,
         "`max_steps` of mc.refine is an option"),
        (lambda: jax.jit(lambda a: mc.stereo_rectify(cameras, (1280, 720), alpha=a).P)(0.5),
         TypeError, "`alpha` of mc.stereo_rectify is an option"),
        (lambda: jax.jit(lambda w: mc.undistorted(cameras[0], (w, 720)).K)(1280), TypeError,
         "`image_size` of mc.undistorted is an option"),
        (lambda: mc.solve_pnp(board.cameras, T, BP), ValueError, r"pass `cameras\[:, None\]`"),
        (lambda: mc.calibrate_images([np.zeros((64, 64))], mc.targets.dot_grid(6, 8, 20.0)),
         ValueError, r"is flat: one photo of a plane.*mc.label_grid.*mc.calibrate_planar"),
        (lambda: jax.jit(lambda n: mc.undistort_points(cameras, P, iterations=n))(20), TypeError,
         "`iterations` of mc.undistort_points is an option"),
        (lambda: jax.jit(lambda n: cameras.rays(P, iterations=n))(20), TypeError,
         r"`iterations` of mc.Camera.rays is an option.*jax.jit\(lambda camera, pixels: "
         r"camera.rays\(pixels, iterations=\.\.\.\)\)\."),
    ]  # fmt: skip


def _seen(pixels, mask):
    """Camera 0's views of the board with enough corners for a homography."""
    keep = np.asarray(mask)[0].sum(-1) >= 4
    return np.asarray(pixels)[0][keep], np.asarray(mask)[0][keep]


def _detection():
    camera = mc.synthetic.random_rig(jax.random.key(1), 1).cameras[0]
    return mc.detect_dots(mc.synthetic.render(camera, mc.targets.box_corner(), key=1))


def test_misused_arguments_say_what_they_take(rig):
    for call, error, words in _misuses(rig):
        with pytest.raises(error, match=words):
            call()


def test_python_lists_under_jit_are_refused_with_the_fix():
    """A JAX user's trial: `jax.jit(mc.calibrate)` of Python lists (each number a traced
    argument) failed with JAX's TracerArrayConversionError, naming nothing; eagerly, lists work."""
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=3)
    lists = [np.asarray(x).tolist() for x in (rig.world, rig.pixels, rig.mask)]
    assert bool(mc.calibrate(*lists).ok.all())
    with pytest.raises(TypeError, match="`world` is a Python list of traced numbers"):
        jax.jit(mc.calibrate)(*lists)
