"""`solve_pnp`: the pose of a known target from calibrated cameras, against the truth and
OpenCV's `solvePnP`."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mvcalib as mc

BOARD = np.asarray(mc.targets.dot_grid(6, 8, 30.0).points)  # mm, z = 0
OBJECT = np.random.default_rng(7).uniform(-100.0, 100.0, (20, 3))  # a 3-D target
LENSES = {
    "pinhole": [-0.2, 0.05, 1e-3, -5e-4, 0.01],
    "fisheye": [0.05, -0.01, 0.002, 0.0],
}


def _views(seed: int, batch: tuple[int, ...], lens: str = "pinhole") -> mc.Camera:
    """Cameras of one set of intrinsics and distortion, looking at the origin from 400-700 mm
    in random poses, of batch shape `batch`."""
    rng = np.random.default_rng(seed)
    R = jax.vmap(mc.rodrigues)(jnp.asarray(rng.normal(0.0, 0.3, (*batch, 3)).reshape(-1, 3)))
    xy = rng.uniform(-80.0, 80.0, (*batch, 2)) - [75.0, 105.0]
    t = np.concatenate([xy, rng.uniform(400.0, 700.0, (*batch, 1))], -1)
    full = lambda x: np.full(batch, x)  # noqa: E731
    return mc.Camera(full(800.0), full(810.0), full(320.0), full(240.0),
                     R.reshape(*batch, 3, 3), t, dist=np.broadcast_to(LENSES[lens], (*batch,
                     len(LENSES[lens]))), lens=lens)  # fmt: skip


@pytest.mark.parametrize("lens", ["pinhole", "fisheye"])
@pytest.mark.parametrize("target", [BOARD, OBJECT], ids=["board", "object"])
def test_the_pose_of_every_view_is_exact_without_noise(target, lens):
    truth = _views(0, (12,), lens)
    out = mc.solve_pnp(truth, target, truth.project(target))
    assert bool(out.ok.all())
    np.testing.assert_allclose(out.cameras.R, truth.R, atol=1e-12)
    np.testing.assert_allclose(out.cameras.t, truth.t, rtol=0, atol=1e-9)  # mm, at 400-700
    assert float(out.rms_after.max()) < 1e-9


@pytest.mark.parametrize("target", [BOARD, OBJECT], ids=["board", "object"])
def test_the_pose_is_opencvs_solvepnp(target):
    truth = _views(1, (8,))
    pixels = np.asarray(truth.project(target))
    pixels = pixels + np.random.default_rng(2).normal(0.0, 0.5, pixels.shape)
    out = mc.solve_pnp(truth, target, pixels)
    assert bool(out.ok.all())
    stop = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-14)
    for v in range(8):
        K, D = np.asarray(truth.K[v]), np.asarray(truth.dist[v])
        _, rvec, tvec = cv2.solvePnP(target, pixels[v], K, D, flags=cv2.SOLVEPNP_ITERATIVE)
        rvec, tvec = cv2.solvePnPRefineLM(target, pixels[v], K, D, rvec, tvec, criteria=stop)
        # (the two stop at their own tolerances: refine's at steps of 1e-5 standard errors)
        np.testing.assert_allclose(out.cameras.R[v], cv2.Rodrigues(rvec)[0], atol=1e-7)
        np.testing.assert_allclose(out.cameras.t[v], tvec.ravel(), atol=1e-5)  # mm
        # and the standard errors are those of the 0.5 px noise: the truth within 5 of them
        error = np.abs(np.asarray(out.cameras.t[v] - truth.t[v]))
        assert (error < 5 * np.asarray(out.standard_errors[v, 3:])).all()


def test_cameras_broadcast_against_the_views_as_arrays_do():
    rig = _views(3, (3,))
    frames = _views(4, (3, 5))
    posed = mc.Camera(rig.alpha_u[:, None], rig.alpha_v[:, None], rig.u0[:, None],
                      rig.v0[:, None], frames.R, frames.t, dist=rig.dist[:, None])  # fmt: skip
    pixels = posed.project(BOARD)  # (3, 5, 48, 2)
    out = mc.solve_pnp(rig[:, None], BOARD, pixels)  # each camera's five frames
    assert out.cameras.batch_shape == (3, 5) and bool(out.ok.all())
    np.testing.assert_allclose(out.cameras.t, frames.t, atol=1e-9)
    one = mc.solve_pnp(rig[1], BOARD, pixels[1])  # one camera, five views
    np.testing.assert_allclose(one.cameras.t, out.cameras.t[1], atol=1e-9)
    single = mc.solve_pnp(rig[2], BOARD, pixels[2, 3])  # one view
    assert single.cameras.batch_shape == ()
    np.testing.assert_allclose(single.cameras.t, frames.t[2, 3], atol=1e-9)
    with pytest.raises(ValueError, match=r"cameras\[:, None\]"):
        mc.solve_pnp(rig, BOARD, pixels)


def test_a_view_without_a_closed_form_is_flagged_and_the_others_solved():
    truth = _views(5, (4,))
    pixels = np.array(truth.project(OBJECT))
    mask = np.ones((4, len(OBJECT)), bool)
    mask[1, 5:] = False  # five points of a 3-D target: no DLT
    pixels[2, 3] += 300.0  # a wrong correspondence: the DLT does not fit
    out = mc.solve_pnp(truth, OBJECT, pixels, mask)
    assert out.result.tolist() == [0, -1, -2, 0]
    assert bool(jnp.isnan(out.cameras.t[1:3]).all())
    assert "6 of a 3-D target" in out.messages()[1] and "closed-form" in out.messages()[2]
    np.testing.assert_allclose(np.asarray(out.cameras.t - truth.t)[[0, 3]], 0.0, atol=1e-9)
    # a point 10 px off keeps the closed form; a robust loss then sets it aside
    pixels[2, 3] -= 290.0
    robust = mc.solve_pnp(truth, OBJECT, pixels, mask, loss=mc.Cauchy(1.0))
    assert robust.result.tolist() == [0, -1, 0, 0]
    assert not bool(robust.inliers[2, 3]) and int(robust.inliers[2].sum()) == len(OBJECT) - 1
    plain = mc.solve_pnp(truth, OBJECT, pixels, mask)
    off = [float(jnp.linalg.norm(r.cameras.t[2] - truth.t[2])) for r in (robust, plain)]
    assert off[0] < 0.02 and 50 * off[0] < off[1]  # mm, at 660 (0.009 against 1.6)


def test_a_pose_that_fits_its_points_poorly_is_flagged():
    """A board's homography sets a wrong corner aside, so the closed form survives it; the pose
    that fits the corner (a robotics user's trial: a corner 400 px off, "successful", 52.8 px
    RMS and the pose 60 mm off) is flagged, as `calibrate` flags such a camera."""
    truth = _views(10, (3,))
    pixels = np.array(truth.project(BOARD))
    pixels[1, 10] += [400.0, 0.0]
    out = mc.solve_pnp(truth, BOARD, pixels)
    assert out.result.tolist() == [0, -3, 0] and "wrong correspondence" in out.messages()[1]
    assert bool(jnp.isnan(out.cameras.t[1]).all())
    robust = mc.solve_pnp(truth, BOARD, pixels, loss=mc.Huber(1.0))  # the corner set aside
    assert bool(robust.ok.all()) and not bool(robust.inliers[1, 10])
    np.testing.assert_allclose(robust.cameras.t, truth.t, atol=0.05)  # mm: Huber's pull, 0.03


def test_bad_input_says_what_is_wrong():
    camera = _views(6, ())
    pixels = camera.project(BOARD)
    with pytest.raises(ValueError, match="mvcalib.Camera"):
        mc.solve_pnp(np.eye(3), BOARD, pixels)
    with pytest.raises(ValueError, match="collinear"):
        mc.solve_pnp(camera, BOARD[:8], pixels[:8])  # the first row of the grid
    with pytest.raises(ValueError, match="points"):
        mc.solve_pnp(camera, BOARD, pixels[:40])
    with pytest.raises(ValueError, match="no closed-form pose"):
        mc.solve_pnp(camera, OBJECT, camera.project(OBJECT)[:20], np.arange(20) < 5)
    lost = mc.Camera(np.nan, 800.0, 320.0, 240.0, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="not finite"):
        mc.solve_pnp(lost, BOARD, pixels)
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda target: mc.solve_pnp(camera, target, pixels).cameras.t)(BOARD)


def test_derivatives_are_those_of_the_optimum():
    camera = _views(8, ())
    pixels = np.asarray(camera.project(OBJECT))
    pixels = pixels + np.random.default_rng(9).normal(0.0, 0.5, pixels.shape)

    def depth(pixels, focal, k1):  # the target's distance along the optical axis
        held = eqx.tree_at(lambda c: (c.alpha_u, c.dist), camera,
                           (jnp.asarray(focal), camera.dist.at[0].set(k1)))  # fmt: skip
        return mc.solve_pnp(held, OBJECT, pixels).cameras.t[2]

    point = (pixels, camera.alpha_u, camera.dist[0])
    value, gradient = jax.value_and_grad(depth, argnums=(0, 1, 2))(*point)  # traced: not padded
    np.testing.assert_allclose(value, depth(*point), rtol=1e-9)
    by_pixels = np.asarray(gradient[0])
    h = 1e-2  # px: the solves stop at steps of 1e-5 standard errors
    for n, k in [(0, 0), (7, 1), (13, 0), (19, 1)]:
        step = np.zeros_like(pixels)
        step[n, k] = h
        moved = [float(depth(pixels + sign * step, *point[1:])) for sign in (1, -1)]
        central = (moved[0] - moved[1]) / (2 * h)
        assert abs(by_pixels[n, k] - central) < 1e-6 * np.abs(by_pixels).max(), (n, k)
    # the held intrinsics and distortion move the pose: implicit derivatives through the optimum
    for i, h in ((1, 1e-2), (2, 1e-5)):
        up, down = list(point), list(point)
        up[i], down[i] = point[i] + h, point[i] - h
        central = (float(depth(*up)) - float(depth(*down))) / (2 * h)
        assert abs(float(gradient[i]) - central) < 1e-4 * abs(central), i
