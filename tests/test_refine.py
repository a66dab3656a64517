import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from conftest import box_corners_with_wild_dots
from scipy.optimize import least_squares

import mvcalib as mc

DIST = np.array([-0.2, 0.1, 1e-3, 1e-3, 0.0])  # k1, k2, p1, p2, k3 (OpenCV order)
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3")
NOISE = 0.3
IMAGE = (1000, 1100)


def distorted_rig(seed, n_cameras, noise=NOISE):
    """Cameras with lens distortion filling most of the image with a 108-dot box corner."""
    target = mc.targets.box_corner_grid(6)
    rig = mc.synthetic.random_rig(
        jax.random.key(seed), n_cameras=n_cameras, target=target, fill=(0.8, 0.95)
    )
    cams = eqx.tree_at(lambda c: c.dist, rig.cameras, jnp.broadcast_to(DIST, (n_cameras, 5)))
    _, pixels, mask = mc.synthetic.observe(
        jax.random.key(seed + 1000), cams, rig.world, noise, IMAGE
    )
    return cams, rig.world, pixels, mask


def zero_skew(cameras):
    return eqx.tree_at(lambda c: c.skew, cameras, jnp.zeros_like(cameras.skew))


@pytest.fixture(scope="module")
def rig32():
    cams, world, pixels, mask = distorted_rig(0, 32)
    dlt = mc.calibrate(world, pixels, mask)
    refined = mc.refine(zero_skew(dlt.cameras), world, pixels, mask)
    return cams, world, pixels, mask, dlt, refined


def test_refined_rms_reaches_the_noise_floor_where_the_dlt_does_not(rig32):
    cams, world, pixels, mask, dlt, refined = rig32
    n = np.asarray(mask.sum(-1))
    p = len(refined.parameter_names)  # 4 intrinsics + 6 pose + 4 distortion
    # E[sum |r|^2] = sigma^2 (2N - p) at the least-squares optimum
    floor = NOISE * np.sqrt((2 * n - p) / n)
    pooled = lambda rms: np.sqrt(np.sum(np.asarray(rms) ** 2 * n) / np.sum(floor**2 * n))  # noqa: E731
    print(f"refined RMS / floor {pooled(refined.rms_after):.4f}, DLT {pooled(dlt.report.rms):.3f}")
    assert abs(pooled(refined.rms_after) - 1) < 0.05
    assert pooled(dlt.report.rms) > 2.0  # the DLT cannot model the distortion
    assert bool(np.all(refined.ok)) and np.all(np.asarray(refined.iterations) < 100)
    seed_rms = mc.reprojection_report(zero_skew(dlt.cameras), world, pixels, mask).rms
    np.testing.assert_allclose(refined.rms_before, seed_rms, rtol=1e-12)
    # the distortion comes back
    np.testing.assert_allclose(np.median(refined.cameras.dist[:, :2], 0), DIST[:2], atol=0.02)


def test_float32_data_with_x64_on_is_refined_in_float32(rig32):
    """float32 arrays in a process with x64 on (a float32 pipeline beside float64 code): every
    solve that takes optimistix's Levenberg–Marquardt raised "Vector and operator structures do
    not match" (its trust region's step size is float64 there). Now refined in float32, to the
    float64 answer's RMS within float32's precision."""
    cams, world, pixels, mask, _, refined = rig32
    world32, pixels32 = (np.asarray(x, np.float32) for x in (world, pixels))
    seed = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32), cams[:4])
    out = mc.refine(seed, world32, pixels32[:4], mask[:4])
    assert out.cameras.R.dtype == np.float32 and bool(np.all(out.ok))
    np.testing.assert_allclose(out.rms_after, refined.rms_after[:4], rtol=1e-3)
    points = mc.triangulate(out.cameras, pixels32[:4, :10], mask[:4, :10], refine=True).points
    cams64 = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), out.cameras)
    points64 = mc.triangulate(cams64, pixels[:4, :10], mask[:4, :10], refine=True).points
    assert points.dtype == np.float32
    np.testing.assert_allclose(points, points64, atol=1e-3)  # mm, of a 160 mm target
    rig = mc.refine_rig(out.cameras, world32, pixels32[:4], mask[:4])
    assert rig.cameras.R.dtype == np.float32 and int(rig.result) == 0


def test_calibrate_refine_is_the_same_as_refining_by_hand(rig32):
    cams, world, pixels, mask, dlt, refined = rig32
    one_call = mc.calibrate(world, pixels, mask, refine=True)
    np.testing.assert_allclose(one_call.report.rms, refined.rms_after, rtol=1e-9)
    np.testing.assert_allclose(one_call.cameras.alpha_u, refined.cameras.alpha_u, rtol=1e-9)
    assert one_call.refinement is not None and np.all(np.asarray(one_call.P) == np.asarray(dlt.P))


def opencv_model_residuals(x, world, pixels):
    fx, fy, cx, cy = x[:4]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    proj, _ = cv2.projectPoints(world, x[4:7], x[7:10], K, np.r_[x[10:14], 0.0])
    return (proj[:, 0] - pixels).ravel()


def test_agrees_with_opencv_calibrate_camera_and_scipy(rig32):
    cams, world, pixels, mask, dlt, _ = rig32
    # calibrateCamera takes float32 points only: give all three solvers the same rounded data
    world = np.asarray(world).astype(np.float32).astype(np.float64)
    pixels = np.asarray(pixels[:4]).astype(np.float32).astype(np.float64)
    mask = np.asarray(mask[:4])
    refined = mc.refine(zero_skew(dlt.cameras[:4]), world, pixels, mask)
    for i in range(4):
        px, W = pixels[i][mask[i]], world[mask[i]]
        seed = zero_skew(dlt.cameras)[i]
        ours = refined.cameras[i]
        rms_ours = float(refined.rms_after[i])
        # OpenCV: one view of a non-planar target needs an intrinsic guess; same model (zero
        # skew, k1 k2 p1 p2 free, k3 fixed).
        flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
        rms_cv, K_cv, dist_cv, _, _ = cv2.calibrateCamera(
            [W.astype(np.float32)], [px.astype(np.float32)], IMAGE, np.array(seed.K),
            np.zeros(5), flags=flags, criteria=crit,
        )  # fmt: skip
        K_cv = np.asarray(K_cv)
        # scipy least_squares on OpenCV's projection model (an independent implementation)
        x0 = np.r_[
            float(seed.alpha_u), float(seed.alpha_v), float(seed.u0), float(seed.v0),
            cv2.Rodrigues(np.asarray(seed.R))[0].ravel(), np.asarray(seed.t), np.zeros(4),
        ]  # fmt: skip
        sol = least_squares(
            opencv_model_residuals, x0, args=(W, px), method="lm", xtol=1e-15, ftol=1e-15,
            gtol=1e-15, x_scale="jac",
        )  # fmt: skip
        rms_scipy = np.sqrt(np.sum(sol.fun**2) / len(px))
        assert abs(rms_ours / rms_scipy - 1) < 1e-6, (rms_ours, rms_scipy)
        assert abs(rms_ours / rms_cv - 1) < 1e-6, (rms_ours, rms_cv)
        # parameters agree within their standard errors
        std = {k: float(refined.std(k)[i]) for k in refined.parameter_names}
        for k, theirs, cv_value in (
            ("alpha_u", sol.x[0], K_cv[0, 0]), ("alpha_v", sol.x[1], K_cv[1, 1]),
            ("u0", sol.x[2], K_cv[0, 2]), ("v0", sol.x[3], K_cv[1, 2]),
            ("k1", sol.x[10], dist_cv.ravel()[0]), ("k2", sol.x[11], dist_cv.ravel()[1]),
        ):  # fmt: skip
            value = (
                float(getattr(ours, k)) if k[0] != "k" else float(ours.dist["k1k2".index(k) // 2])
            )
            assert abs(value - theirs) < 0.01 * std[k], (k, value, theirs, std[k])
            assert abs(value - cv_value) < 0.05 * std[k], (k, value, cv_value, std[k])


def test_the_default_road_is_opencvs_zero_skew_model():
    """`refine` seeded straight from the DLT (whose skew is small and noisy) fits the zero-skew
    model, as `cv2.calibrateCamera` does, on every camera; `skew=True` estimates the skew and
    `fix=("skew",)` holds the seed's."""
    cams, world, pixels, mask = distorted_rig(3, 8)
    world = np.asarray(world).astype(np.float32).astype(np.float64)  # what OpenCV sees
    pixels = np.asarray(pixels).astype(np.float32).astype(np.float64)
    mask = np.asarray(mask)
    seed = mc.Camera.from_projection(mc.dlt(world, pixels, mask))
    assert np.all(np.abs(np.asarray(seed.skew)) > 1e-6)  # the DLT's own skew is not zero
    out = mc.refine(seed, world, pixels, mask)
    assert bool(out.ok.all()) and np.all(np.asarray(out.cameras.skew) == 0)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    for i in range(8):
        W, px = world[mask[i]], pixels[i][mask[i]]
        K0 = np.array(zero_skew(seed[i]).K)
        rms_cv = cv2.calibrateCamera(
            [W.astype(np.float32)], [px.astype(np.float32)], IMAGE, K0, np.zeros(5),
            flags=flags, criteria=crit,
        )[0]  # fmt: skip
        assert abs(float(out.rms_after[i]) / rms_cv - 1) < 1e-6, (i, out.rms_after[i], rms_cv)
    with_skew = mc.refine(seed, world, pixels, mask, skew=True)
    assert "skew" in with_skew.parameter_names and "skew" not in out.parameter_names
    assert np.all(np.asarray(with_skew.cameras.skew) != 0)
    assert np.all(np.asarray(with_skew.rms_after) <= np.asarray(out.rms_after) + 1e-9)
    held = mc.refine(seed, world, pixels, mask, fix=("skew",))
    np.testing.assert_array_equal(held.cameras.skew, seed.skew)


def test_true_focal_within_two_standard_errors_in_90_to_99_percent():
    cams, world, pixels, mask = distorted_rig(7, 200)
    seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
    out = mc.refine(seed, world, pixels, mask)
    assert bool(np.all(out.ok))
    z = np.asarray((out.cameras.alpha_u - cams.alpha_u) / out.std("alpha_u"))
    coverage = np.mean(np.abs(z) <= 2)
    print(f"coverage of +-2 SE: {coverage:.3f}; std of z: {np.std(z):.3f}")
    assert 0.90 <= coverage <= 0.99


# The textbook tuning constants (95 % efficiency under Gaussian noise): 1.345 and 2.385 sigma.
ROBUST = [mc.Huber(1.345 * NOISE), mc.Cauchy(2.385 * NOISE)]


@pytest.mark.parametrize("loss", ROBUST, ids=["huber", "cauchy"])
def test_robust_losses_survive_ten_percent_outliers(loss):
    cams, world, pixels, mask = distorted_rig(11, 8)
    rng = np.random.default_rng(0)
    pixels = np.array(pixels)
    outlier = rng.random(mask.shape) < 0.10
    angle = rng.uniform(0, 2 * np.pi, mask.shape)
    pixels[outlier] += 20.0 * np.stack([np.cos(angle), np.sin(angle)], -1)[outlier]
    seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
    plain = mc.refine(seed, world, pixels, mask)
    robust = mc.refine(seed, world, pixels, mask, loss=loss)
    err = lambda r: np.abs(np.asarray(r.cameras.alpha_u / cams.alpha_u) - 1)  # noqa: E731
    print(
        f"{type(loss).__name__}: focal error {err(robust).max():.4f}, plain {err(plain).max():.4f}"
    )
    assert np.all(err(robust) < 0.01)
    assert np.any(err(plain) > 0.01)
    # the inlier masks (final residual within 3 scales) find the outliers
    inl, m = np.asarray(robust.inliers), np.asarray(mask)
    assert np.mean(inl[outlier & m]) < 0.05
    assert np.mean(inl[~outlier & m]) > 0.97


def test_robust_standard_errors_hold_with_wild_points():
    """200 cameras, 5 % of each one's points moved up to 60 px: the true focal length within two
    standard errors in 90-99 % of the cameras, for Huber and Cauchy at their textbook scales and
    Huber at 2 px. The variance was the robust cost over the degrees of freedom, which counts a
    wild point's pull (Huber: 2 scale |r|) as noise: 100 % coverage, standard errors 2.5-3
    times the errors; it is now Huber's M-estimate (`residual_variance`)."""
    cams, world, pixels, mask = distorted_rig(7, 200)
    seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
    rng = np.random.default_rng(0)
    pixels = np.array(pixels)
    for c in range(len(pixels)):
        visible = np.flatnonzero(mask[c])
        wild = rng.choice(visible, round(0.05 * len(visible)), replace=False)
        pixels[c, wild] += rng.uniform(-60, 60, (len(wild), 2))
    for loss in (*ROBUST, mc.Huber(2.0)):
        out = mc.refine(seed, world, pixels, mask, loss=loss)
        assert bool(np.all(out.ok))
        z = np.asarray((out.cameras.alpha_u - cams.alpha_u) / out.std("alpha_u"))
        coverage = np.mean(np.abs(z) <= 2)
        print(f"{loss}: coverage of +-2 SE {coverage:.3f}; std of z {np.std(z):.3f}")
        assert 0.90 <= coverage <= 0.99, loss


def test_cauchy_converges_where_its_gauss_newton_model_crept():
    """256 cameras of a box corner (`random_rig` key 0), two of each camera's 48 dots moved by 50
    px: with `Cauchy(1.0)` six cameras stopped unconverged at 256 steps, focal lengths up to 20 %
    off (until 2026-12-05: the Gauss–Newton model of the residuals scaled by `sqrt(rho / r^2)`,
    which steps twice too far where the loss is flat). Five of them, with Ceres' model
    (`_irls`): converged in 30-123 steps, focal lengths within 1.1 %."""
    rig, world, pixels, mask, _ = box_corners_with_wild_dots(256)
    crept = [11, 31, 115, 127, 189]
    out = mc.calibrate(
        world, pixels[crept], mask[crept], refine=dict(loss=mc.Cauchy(1.0))
    ).refinement
    assert np.all(np.asarray(out.result) == 0), np.asarray(out.iterations)
    error = np.abs(np.asarray(out.cameras.alpha_u) / np.asarray(rig.cameras.alpha_u)[crept] - 1)
    assert error.max() < 0.015, error


def test_a_robust_refinement_starts_from_the_dlt_of_the_points_near_it():
    """With a robust loss, `calibrate(..., refine=...)` seeds the refinement with the DLT fitted
    again without the points far off it (`_dlt.refit_near`): two dots of each box-corner camera
    moved by 50 px, the seed is the DLT of the other points. (On 256 such cameras, with
    `Huber(1.0)`: 2,959 steps in all against 5,602 from the DLT of every point, the largest
    focal-length error 4.8 % against 7.8 %; without the wild points 4.3 %.)"""
    _, world, pixels, mask, clean = box_corners_with_wild_dots(32)
    robust = mc.calibrate(world, pixels, mask, refine=dict(loss=mc.Huber(1.0)))
    oracle = mc.calibrate(world, pixels, clean, max_relative_rms=np.inf)
    unit = lambda P: np.asarray(P) / np.linalg.norm(np.asarray(P), axis=(-2, -1), keepdims=True)  # noqa: E731
    sign = np.sign(np.sum(unit(robust.P) * unit(oracle.P), axis=(-2, -1)))[:, None, None]
    np.testing.assert_allclose(unit(robust.P) * sign, unit(oracle.P), atol=1e-12)
    plain = mc.calibrate(world, pixels, mask, max_relative_rms=np.inf)
    assert np.abs(unit(plain.P) - unit(oracle.P)).max() > 1e-4  # (the wild points' pull)


def test_fix_holds_parameters_and_distortion_choice():
    cams, world, pixels, mask = distorted_rig(17, 2)
    seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
    out = mc.refine(seed, world, pixels, mask, fix=("principal_point",), distortion=("k1",))
    np.testing.assert_array_equal(out.cameras.u0, seed.u0)
    np.testing.assert_array_equal(out.cameras.dist[:, 1:], 0.0)
    assert out.parameter_names == ("alpha_u", "alpha_v", "rx", "ry", "rz", "tx", "ty", "tz", "k1")
    with pytest.raises(ValueError, match="unknown parameter 'focus'"):
        mc.refine(seed, world, pixels, mask, fix=("focus",))
    with pytest.raises(KeyError):
        out.std("k2")


def test_fix_aspect_ratio_agrees_with_opencv():
    """`fix="aspect_ratio"` holds alpha_u / alpha_v at the seed's ratio and estimates the focal
    length, as `cv2.calibrateCamera` does with CALIB_FIX_ASPECT_RATIO from the same guess."""
    cams, world, pixels, mask = distorted_rig(23, 4)
    world = np.asarray(world).astype(np.float32).astype(np.float64)  # what OpenCV sees
    pixels = np.asarray(pixels).astype(np.float32).astype(np.float64)
    mask = np.asarray(mask)
    dlt = mc.calibrate(world, pixels, mask)
    seed = zero_skew(dlt.cameras)
    ratio = np.asarray(seed.alpha_u / seed.alpha_v)
    assert np.abs(ratio / np.asarray(cams.alpha_u / cams.alpha_v) - 1).max() > 1e-4  # not true
    out = mc.refine(seed, world, pixels, mask, fix="aspect_ratio")
    free = mc.refine(seed, world, pixels, mask)
    assert bool(out.ok.all()) and np.all(np.asarray(out.iterations) < 100)
    np.testing.assert_allclose(out.cameras.alpha_u / out.cameras.alpha_v, ratio, rtol=1e-12)
    assert np.all(np.abs(np.asarray(out.cameras.alpha_v / seed.alpha_v) - 1) > 1e-6)  # it moved
    assert np.all(np.asarray(out.rms_after) <= np.asarray(out.rms_before))  # the DLT seed's
    # one constraint more than the free focal lengths: no better fit, and the rest as OpenCV's
    assert np.all(np.asarray(out.rms_after) >= np.asarray(free.rms_after) * (1 - 1e-12))
    assert out.parameter_names == ("alpha_u",) + free.parameter_names[1:]
    np.testing.assert_allclose(out.std("alpha_u"), ratio * out.std("alpha_v"), rtol=1e-12)
    assert np.all(np.asarray(out.std("alpha_v")) > 0)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    for i in range(4):
        W, px = world[mask[i]], pixels[i][mask[i]]
        rms_cv, K_cv, dist_cv, _, _ = cv2.calibrateCamera(
            [W.astype(np.float32)], [px.astype(np.float32)], IMAGE, np.array(seed[i].K),
            np.zeros(5), flags=flags, criteria=crit,
        )  # fmt: skip
        ours = out.cameras[i]
        print(f"camera {i}: alpha_v {float(ours.alpha_v):.6f}, OpenCV's {K_cv[1, 1]:.6f}")
        np.testing.assert_allclose(float(ours.alpha_u), K_cv[0, 0], rtol=1e-6)
        np.testing.assert_allclose(float(ours.alpha_v), K_cv[1, 1], rtol=1e-6)
        assert abs(float(out.rms_after[i]) / rms_cv - 1) < 1e-6, (i, out.rms_after[i], rms_cv)
    # alpha_u held alone is another problem (the same free indices, untied: no program shared)
    alone = mc.refine(seed, world, pixels, mask, fix="alpha_u")
    np.testing.assert_array_equal(alone.cameras.alpha_u, seed.alpha_u)
    moved = np.asarray(alone.cameras.alpha_u / alone.cameras.alpha_v) / ratio - 1
    assert np.abs(moved).min() > 1e-9
    # either focal length held holds both
    held = mc.refine(seed, world, pixels, mask, fix=("aspect_ratio", "alpha_v"))
    np.testing.assert_array_equal(held.cameras.alpha_u, seed.alpha_u)
    np.testing.assert_array_equal(held.cameras.alpha_v, seed.alpha_v)
    assert "alpha_u" not in held.parameter_names and "alpha_v" not in held.parameter_names


def test_the_tied_focal_lengths_jacobian_is_the_chain_rule():
    """With alpha_u tied to alpha_v (`fix="aspect_ratio"`), the written-out Jacobian against
    forward-mode autodiff of `Camera.project` with alpha_u = ratio * alpha_v."""
    from mvcalib import _refine as R

    cams, world, pixels, mask = distorted_rig(29, 1)
    cam = eqx.tree_at(lambda c: c.alpha_u, cams[0], 1.03 * cams[0].alpha_u)
    free = R._free_parameters(DIST_NAMES, "aspect_ratio", False)
    assert free.tied and 0 not in free and 1 in free
    p0 = R._pack(cam)
    ratio = float(cam.alpha_u / cam.alpha_v)
    args = (p0, cam.R, R._scales(p0), world, pixels[0], jnp.asarray(mask[0]), None)
    y = jnp.linspace(-1e-2, 1e-2, len(free))

    def plain(y):
        p = p0.at[jnp.asarray(free)].add(y * args[2][jnp.asarray(free)])
        p = p.at[0].set(ratio * p[1])
        r = jnp.where(mask[0][:, None], R._unpack(p, cam.R).project(world) - pixels[0], 0.0)
        return r.T.reshape(-1)

    _check_written_jacobian(plain, args, free, y)
    np.testing.assert_allclose(R._residuals(y, args, free).reshape(-1), plain(y), atol=1e-9)


def test_fix_aspect_ratio_is_differentiable_through_its_optimum():
    """Implicit derivatives of a refinement with the aspect ratio held: by the pixels, and by
    the seed's alpha_u, which sets the ratio (the free parameters' seed has no influence)."""
    cams, world, pixels, mask = distorted_rig(31, 1)
    seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)[0]
    pixels, mask = pixels[0], mask[0]
    solver = optx.GaussNewton(rtol=1e-12, atol=1e-12)  # converges to rounding here
    w = np.random.default_rng(8).standard_normal(4)

    def f(alpha_u, alpha_v, px):
        start = eqx.tree_at(lambda c: (c.alpha_u, c.alpha_v), seed, (alpha_u, alpha_v))
        out = mc.refine(start, world, px, mask, fix="aspect_ratio", solver=solver)
        c = out.cameras
        return jnp.vdot(w, jnp.stack([c.alpha_u, c.alpha_v, c.u0, c.t[2]])), out.ok

    value_and_grad = jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2), has_aux=True))
    au, av = seed.alpha_u, seed.alpha_v
    (_, ok), (g_au, g_av, g_px) = value_and_grad(au, av, pixels)
    assert bool(ok)
    v = np.random.default_rng(9).standard_normal(pixels.shape) * np.asarray(mask)[:, None]
    h = 1e-5  # px
    at = lambda a, b, px: float(value_and_grad(a, b, px)[0][0])  # noqa: E731
    fd = (at(au, av, pixels + h * v) - at(au, av, pixels - h * v)) / (2 * h)
    np.testing.assert_allclose(np.vdot(g_px, v), fd, rtol=1e-6)
    h = 1e-6 * float(au)  # (the ratio moves the optimum far: at 1e-4, 0.5 % off by curvature)
    fd = (at(au + h, av, pixels) - at(au - h, av, pixels)) / (2 * h)
    np.testing.assert_allclose(float(g_au), fd, rtol=1e-5)
    assert abs(float(g_au)) > 0.1 * abs(fd) > 0
    # the same ratio from another alpha_v: the result moves as the ratio does
    fd = (at(au, av + h, pixels) - at(au, av - h, pixels)) / (2 * h)
    np.testing.assert_allclose(float(g_av), fd, rtol=1e-5)


def test_too_few_points_raise_alone_and_are_flagged_in_a_rig():
    # 4 cameras, as in the OpenCV comparison above: the refinement's compiled program is reused
    cams, world, pixels, mask = distorted_rig(19, 4)
    seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
    m = np.array(mask)
    m[1, 6:] = False
    out = mc.refine(seed, world, pixels, m)
    assert np.asarray(out.result).tolist() == [0, -1, 0, 0]
    assert "too few" in out.messages()[1] and np.isnan(float(out.cameras.alpha_u[1]))
    with pytest.raises(ValueError, match="6 visible points"):
        mc.refine(seed[1], world, pixels[1], m[1])


def rig_with_a_nan_seed():
    """4 distorted cameras and their DLT seed, and the seed with camera 2 NaN (calibrate's
    answer for a camera it could not solve): (world, pixels, mask, seed, broken)."""
    _, world, pixels, mask = distorted_rig(19, 4)
    seed = zero_skew(mc.calibrate(world, pixels, mask).cameras)
    broken = jax.tree_util.tree_map(lambda x: x.at[2].set(jnp.nan), seed)
    return world, pixels, mask, seed, broken


def test_a_seed_calibrate_could_not_solve_is_flagged_at_once():
    # A NaN seed ran 256 steps, holding up its whole chunk, and said "maximum number of
    # steps". It is flagged now, after one step, and the other cameras are as without it.
    world, pixels, mask, seed, broken = rig_with_a_nan_seed()
    out = mc.refine(broken, world, pixels, mask)
    keep = np.array([0, 1, 3])
    alone = mc.refine(seed[keep], world, pixels[keep], mask[keep])
    assert np.asarray(out.result).tolist() == [0, 0, -2, 0]
    assert "non-finite" in out.messages()[2] and int(out.iterations[2]) <= 1
    assert np.isnan(out.rms_before[2]) and np.isnan(out.rms_after[2])
    assert np.isnan(out.cameras.alpha_u[2])
    np.testing.assert_allclose(np.delete(out.rms_after, 2), alone.rms_after, rtol=1e-12)
    with pytest.raises(ValueError, match="non-finite parameter"):
        mc.refine(broken[2], world, pixels[2], mask[2])


def test_a_camera_its_points_do_not_determine_says_so_when_it_runs_out_of_steps():
    # One view of a plane does not pin down free intrinsics: the camera's parameters drift
    # along a flat valley until `max_steps`, and the message says why that may be (optimistix's
    # speaks of root-finds). Its standard errors are large; the other cameras converge.
    target = mc.targets.box_corner_grid(6)
    rig = mc.synthetic.random_rig(jax.random.key(5), 4, target=target, noise=0.3, fill=(0.8, 0.95))
    seed = zero_skew(mc.calibrate(rig.world, rig.pixels, rig.mask).cameras)
    mask = np.asarray(rig.mask).copy()
    on_one_face = np.asarray(rig.world)[:, 0] == 0
    mask[1] &= on_one_face
    out = mc.refine(seed, rig.world, rig.pixels, mask, max_steps=64)
    assert np.asarray(out.ok).tolist() == [True, False, True, True]
    assert "the points may not determine the free parameters" in out.messages()[1]
    relative = np.asarray(out.std("alpha_u") / out.cameras.alpha_u)
    assert relative[1] > 0.05 and np.all(np.delete(relative, 1) < 0.01), relative


def test_gradients_are_finite_beside_cameras_that_are_not_refined():
    # The implicit derivative solved each camera's system at its optimum, singular for a camera
    # that sees nothing or has a NaN seed, and lineax raised for the whole batch.
    world, pixels, mask, seed, broken = rig_with_a_nan_seed()
    hidden = np.asarray(mask).copy()
    hidden[1] = False

    def loss(pixels, seed, mask):
        return jnp.nansum(mc.refine(seed, world, pixels, mask, distortion=()).rms_after)

    grad = jax.grad(loss)(pixels, broken, hidden)
    assert np.isfinite(grad).all() and not np.asarray(grad[1:3]).any()
    keep = np.array([0, 3])
    expected = jax.grad(loss)(pixels[keep], seed[keep], hidden[keep])
    np.testing.assert_allclose(grad[keep], expected, rtol=1e-9, atol=1e-12)


def test_undistort_points_matches_opencv():
    cams, world, pixels, mask = distorted_rig(23, 2, noise=0.0)
    ours = np.asarray(mc.undistort_points(cams, pixels))
    for i in range(2):
        ref = cv2.undistortPoints(
            np.asarray(pixels[i])[:, None], np.asarray(cams.K[i]), DIST,
            P=np.asarray(cams.K[i]),
            criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-15),
        )[:, 0]  # fmt: skip
        np.testing.assert_allclose(ours[i], ref, atol=1e-6)
        # and it inverts the model: the undistorted pixels are the pinhole projections
        pinhole = eqx.tree_at(lambda c: c.dist, cams[i], jnp.zeros(5))
        np.testing.assert_allclose(ours[i], pinhole.project(world), atol=1e-8)


def test_pixels_beyond_the_fold_of_the_distortion_have_no_ray():
    """An OpenCV user's trial: k1 -0.191, k2 6e-4 fitted on a 1280 x 720 camera (its radial
    distortion folds back 723 px from the principal point, inside the image): the corner pixel
    (2, 2) came back as (2554, 1441), the opposite corner, which projects to (2, 2) exactly;
    (1278, 718) 0.99 px from a solution; on a lens that reaches 0.709 (normalised) a pixel at
    0.9 came back as a point 368 px from it. No ray of the lens reaches them: NaN, in
    `undistort_points` and `Camera.rays`, and a view of a point there is hidden by `triangulate`.
    Inside the fold the answers are the exact inverse (ground truth) and OpenCV's."""
    K = np.array([[818.0, 0.0, 646.0], [0.0, 818.0, 364.0], [0.0, 0.0, 1.0]])
    D = np.array([-0.191, 6e-4, 0.0, 0.0, 0.0])
    cam = mc.Camera.from_matrices(K, np.eye(3), np.zeros(3), dist=D)
    # the fold: the slope 1 + 3 k1 s + 5 k2 s^2 of r (1 + k1 r^2 + k2 r^4) is zero at s = r^2
    s = min(np.roots([5 * D[1], 3 * D[0], 1.0]).real)
    reach = 818.0 * np.sqrt(s) * (1 + D[0] * s + D[1] * s**2)  # px from the principal point
    assert 722 < reach < 724
    beyond = np.array([[2.0, 2.0], [1278.0, 718.0], [646.0 + reach + 1.0, 364.0]])
    assert np.isnan(np.asarray(mc.undistort_points(cam, beyond))).all()
    assert np.isnan(np.asarray(cam.rays(beyond))).all()
    # inside: rays up to 99 % of the fold's radius, their projections undistorted back
    rng = np.random.default_rng(0)
    angle, r = rng.uniform(0, 2 * np.pi, 500), np.sqrt(s) * rng.uniform(0, 0.99, 500)
    xy = np.c_[r * np.cos(angle), r * np.sin(angle)]
    observed = np.asarray(cam.project(np.c_[xy, np.ones(500)]))
    ours = np.asarray(mc.undistort_points(cam, observed))
    np.testing.assert_allclose(ours, 818.0 * xy + [646.0, 364.0], atol=1e-7)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    inner = r < 0.8 * np.sqrt(s)  # (OpenCV's fixed-point iteration is slow near the fold)
    ref = cv2.undistortPoints(observed[inner][:, None], K, D, P=K, criteria=criteria)[:, 0]
    np.testing.assert_allclose(ours[inner], ref, atol=1e-6)
    # the lens of the first trial: reaches 0.709 at r = 1.085, then falls
    other = mc.Camera.from_matrices(
        np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]), np.eye(3), np.zeros(3),
        dist=np.array([-0.45, 0.25, 0.0, 0.0, -0.1]),
    )  # fmt: skip
    out = np.asarray(mc.undistort_points(other, np.array([[860.0, 240.0], [700.0, 240.0]])))
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()
    # a NaN answer leaves the derivatives of the others finite
    both = np.array([[2.0, 2.0], [100.0, 100.0]])
    grad = jax.grad(lambda c: mc.undistort_points(c, both)[1].sum())(cam)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(grad))
    # a view beyond the fold is hidden: the point from the other views
    pair = mc.Camera.stack([cam, eqx.tree_at(lambda c: c.t, cam, jnp.array([-0.3, 0.0, 0.0]))])
    X = np.array([[0.1, 0.05, 1.5], [0.3, -0.2, 2.0], [-0.2, 0.1, 1.8]])
    pixels = np.array(pair.project(X))
    pixels[0, 0] = [2.0, 2.0]
    out = mc.triangulate(pair, pixels)
    assert np.asarray(out.views).tolist() == [1, 2, 2]
    assert not bool(out.ok[0]) and bool(out.ok[1:].all())
    np.testing.assert_allclose(out.points[1:], X[1:], atol=1e-9)
    # and rectified: the image's corners, beyond the fold, take the pinhole's rays
    rect = mc.stereo_rectify(pair, (1280, 720))
    assert np.isfinite(np.asarray(rect.P)).all()


# ------------------------------------------------------------------------------ the solver
def test_secant_lm_matches_scipy_on_a_pytree_curve_fit():
    """A generic problem, `y` a dict: a decaying exponential plus offset, against MINPACK."""
    import optimistix as optx

    t = np.linspace(0.0, 4.0, 50)
    rng = np.random.default_rng(3)
    data = 2.5 * np.exp(-1.3 * t) + 0.5 + 0.05 * rng.standard_normal(t.shape)

    def model(a, b, c):
        return a * np.exp(-b * t) + c

    fit = least_squares(
        lambda p: model(*p) - data, [1.0, 0.5, 0.0], method="lm", xtol=1e-15, ftol=1e-15
    )
    std = np.sqrt(np.diag(np.linalg.inv(fit.jac.T @ fit.jac)) * np.sum(fit.fun**2) / (50 - 3))
    fn = lambda y, _: y["a"] * jnp.exp(-y["bc"][0] * t) + y["bc"][1] - data  # noqa: E731
    y0 = {"a": jnp.array(1.0), "bc": jnp.array([0.5, 0.0])}
    sol = optx.least_squares(fn, mc.SecantLM(rtol=1e-8), y0, max_steps=100)
    ours = np.array([float(sol.value["a"]), *np.asarray(sol.value["bc"])])
    # the cost's own rounding (1e-16 of it) resolves the parameters to ~1e-7 standard errors
    assert np.all(np.abs(ours - fit.x) <= 1e-6 * std), (ours - fit.x) / std
    r = np.asarray(fn(sol.value, None))
    np.testing.assert_allclose(r @ r, np.sum(fit.fun**2), rtol=1e-14)
    assert int(sol.result._value) == 0 and int(sol.stats["num_steps"]) < 30  # noqa: SLF001


def test_secant_lm_with_a_given_transposed_jacobian_equals_autodiff():
    """`options={"jacobian_transpose": jac}`, one row per parameter, takes the same steps to the
    same optimum as the solver's own forward-mode Jacobian; a Jacobian in SciPy's orientation
    (one row per residual) is refused by its shape rather than used."""
    import optimistix as optx

    t = jnp.linspace(0.0, 4.0, 50)
    data = 2.5 * jnp.exp(-1.3 * t) + 0.5 + 0.05 * jnp.sin(7.0 * t)
    fn = lambda y, _: y[0] * jnp.exp(-y[1] * t) + y[2] - data  # noqa: E731

    def jac_t(y, _):
        e = jnp.exp(-y[1] * t)
        return jnp.stack([e, -y[0] * t * e, jnp.ones_like(t)])

    y0 = jnp.array([1.0, 0.5, 0.0])
    auto = optx.least_squares(fn, mc.SecantLM(rtol=1e-8), y0, max_steps=100)
    given = optx.least_squares(
        fn, mc.SecantLM(rtol=1e-8), y0, options={"jacobian_transpose": jac_t}, max_steps=100
    )
    np.testing.assert_allclose(given.value, auto.value, rtol=1e-12)
    assert int(given.stats["num_steps"]) == int(auto.stats["num_steps"])
    with pytest.raises((TypeError, ValueError)):
        optx.least_squares(
            fn, mc.SecantLM(), y0, options={"jacobian_transpose": lambda y, a: jac_t(y, a).T}
        )


def test_secant_lm_stops_when_a_trial_loses_only_to_rounding():
    """Linear least squares whose residuals are differences of pixel-sized (~1000) terms: the
    first step lands on the optimum, after which a trial's cost differs from it by rounding of
    those terms (~1e-13 each, more than the cost's own ~1e-16). The solver must take that as
    converged rather than raise the damping until a trial wins (5-9 steps, where 3 do)."""
    import optimistix as optx

    rng = np.random.default_rng(0)
    fn = lambda y, args: (args[1] + args[0] @ y) - args[2]  # noqa: E731
    steps = []
    for _ in range(20):
        A = rng.standard_normal((200, 14)) * np.logspace(0, 3, 14)
        offset = rng.uniform(500.0, 1000.0, 200)
        b = offset + A @ rng.standard_normal(14) + 0.3 * rng.standard_normal(200)
        args = (jnp.asarray(A), jnp.asarray(offset), jnp.asarray(b))
        sol = optx.least_squares(fn, mc.SecantLM(), jnp.zeros(14), args, throw=False)
        x, *_ = np.linalg.lstsq(A, b - offset, rcond=None)
        r = b - offset - A @ x
        std = np.sqrt(np.diag(np.linalg.inv(A.T @ A)) * (r @ r) / (200 - 14))
        assert int(sol.result._value) == 0  # noqa: SLF001
        assert np.all(np.abs(np.asarray(sol.value) - x) <= 1e-4 * std)
        steps.append(int(sol.stats["num_steps"]))
    assert max(steps) <= 4, steps


def test_covariance_inverse_equals_lapack():
    """`_spd_solve` (Gauss–Jordan, no LAPACK) against NumPy's inverse, on normal matrices as
    ill-conditioned as refinement's (~1e8, focal length against distortion); NaN for a matrix
    that is not positive definite, as the step's Cholesky gives."""
    from mvcalib._refine import _spd_solve

    def _spd_inverse(M):
        return _spd_solve(M, jnp.eye(M.shape[0], dtype=M.dtype))

    rng = np.random.default_rng(5)
    for n in (1, 2, 14, 16):
        A = rng.standard_normal((40, n)) * np.logspace(0, 4, n)
        M = A.T @ A
        ours, ref = np.asarray(_spd_inverse(jnp.asarray(M))), np.linalg.inv(M)
        assert np.max(np.abs(ours - ref)) <= 1e-14 * np.max(np.abs(ref)), n
        assert np.max(np.abs(ours @ M - np.eye(n))) <= 1e-10
    assert np.isnan(np.asarray(_spd_inverse(jnp.array([[1.0, 2.0], [2.0, 1.0]])))).all()


# Equal to 1e-10 holds for XLA's default CPU code generation, which rounds a camera's steps
# alike in any batch; the older emitters do not (8e-10 apart), so this runs with the default (in a
# child process: its data are made there, and the seed is the truth with its focal length 2 % off
# and no distortion, so that no DLT is compiled for it).
@pytest.mark.default_codegen
def test_cameras_solved_alone_in_slots_and_all_at_once_agree(monkeypatch):
    """`solve_each`'s three forms: one camera after another (a quick build's), 4 slots each
    given the next camera as its own converges (an optimised build's on one CPU device), all 24
    at once (accelerators'): the same steps, the same answers up to rounding. In slots, a
    camera's answer is the same to the last bit whichever slot it ran in (the rig reversed)."""
    from mvcalib import _refine

    cams, world, pixels, mask = distorted_rig(0, 24)
    seed = eqx.tree_at(
        lambda c: (c.alpha_u, c.dist), cams, (1.02 * cams.alpha_u, jnp.zeros_like(cams.dist))
    )
    assert _refine.slots(24, alone=True) == 1 and _refine.slots(24) == 24  # (fewer than SLOTS)

    def solve(size, reverse=False):
        monkeypatch.setattr(_refine, "slots", lambda n, alone=False: size)
        jax.clear_caches()  # (the programs are traced again, with `size`)
        _refine._refine_all.clear_cache()
        order = slice(None, None, -1 if reverse else 1)
        out = mc.refine(seed[order], world, pixels[order], mask[order])
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[order], out)

    alone, slotted, together = solve(1), solve(4), solve(24)
    assert bool(alone.ok.all()) and float(alone.rms_after.max()) < 2 * NOISE
    for other in (slotted, together):
        np.testing.assert_allclose(alone.cameras.alpha_u, other.cameras.alpha_u, rtol=1e-10)
        np.testing.assert_allclose(alone.cameras.dist, other.cameras.dist, atol=1e-10)
        np.testing.assert_array_equal(alone.iterations, other.iterations)
    reversed_ = solve(4, reverse=True)
    for a, b in zip(jax.tree_util.tree_leaves(slotted), jax.tree_util.tree_leaves(reversed_)):
        if np.asarray(a).dtype != object:
            np.testing.assert_array_equal(a, b)


def test_written_out_jacobians_equal_autodiff_of_camera_project():
    """The refinement's Jacobians (`_pixel_jacobian` behind a custom JVP, and the weighted
    residuals' `_residual_jacobian_t`, transposed, here with a robust loss) against forward-mode
    autodiff of `Camera.project`; without a loss, every refinement's agreement with SciPy tests
    them."""
    from mvcalib import _refine as R

    loss = ROBUST[0]
    cams, world, pixels, mask = distorted_rig(29, 1)
    cam = cams[0]
    mask = np.asarray(mask[0]).copy()
    mask[:5] = False
    pixels = pixels[0] + 2.0 * jnp.sin(jnp.arange(len(mask)))[:, None]  # residuals of ~2 px
    free = R._free_parameters(DIST_NAMES, (), True)  # all 16 parameters
    p0 = R._pack(cam)
    args = (p0, cam.R, R._scales(p0), world, pixels, jnp.asarray(mask), loss)
    y = jnp.linspace(-1e-2, 1e-2, len(free))

    def plain(y):  # the residuals through Camera.project, with no custom derivative
        p = p0.at[jnp.asarray(free)].add(y * args[2][jnp.asarray(free)])
        r = jnp.where(mask[:, None], R._unpack(p, cam.R).project(world) - pixels, 0.0)
        return (r * R._robust_weights(loss, jnp.sum(r * r, -1))[:, None]).T.reshape(-1)

    _check_written_jacobian(plain, args, free, y)


def _check_written_jacobian(plain, args, free, y):
    """`_residual_jacobian_t` (transposed) and the residuals' custom JVP against forward-mode
    autodiff of `plain(y)`, the residuals written without custom derivatives, at `y`; each
    under one jit (op by op, jacfwd's many small operations compile one at a time)."""
    from mvcalib import _refine as R

    expected = jax.jit(jax.jacfwd(plain))(y)
    scale = np.max(np.abs(expected))
    written = jax.jit(lambda y: R._residual_jacobian_t(y, args, free))(y)
    np.testing.assert_allclose(written.T, expected, atol=1e-13 * scale)
    through_jvp = jax.jit(jax.jacfwd(lambda y: R._residuals(y, args, free).reshape(-1)))(y)
    np.testing.assert_allclose(through_jvp, expected, atol=1e-13 * scale)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 3e-3, 0.05, 0.9, 3.0])
def test_rotation_increment_and_its_left_jacobian(angle):
    """`exp_and_left_jacobian(w, R0)` against `rodrigues(w) @ R0`, and
    `d(R X) / dw_k = (J e_k) x (R X)` against the complex-step derivative of Rodrigues' formula in
    its half-angle form (exact to rounding at every angle; `jax.jacfwd(rodrigues)` loses 4e-12
    at 1e-5 rad to the cancellation in 1 - cos), across the Taylor branches' boundaries."""
    from mvcalib._rotation import exp_and_left_jacobian

    rng = np.random.default_rng(7)
    R0 = np.asarray(mc.rodrigues(jnp.asarray(rng.normal(size=3))))
    axis = rng.normal(size=3)
    w = angle * axis / np.linalg.norm(axis)
    X = rng.normal(size=3)

    def half_angle_rodrigues(w):  # complex-safe, no cancellation
        t = np.sqrt(np.sum(w * w))
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        sinc = np.sin(t / 2) / (t / 2) if t != 0 else 1.0
        return np.eye(3) + sinc * np.cos(t / 2) * K + 0.5 * sinc**2 * (K @ K)

    rotation, J = jax.jit(exp_and_left_jacobian)(jnp.asarray(w), jnp.asarray(R0))
    rotation, J = (np.array([[float(e) for e in row] for row in m]) for m in (rotation, J))
    np.testing.assert_allclose(rotation, np.asarray(mc.rodrigues(jnp.asarray(w))) @ R0, atol=3e-16)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-15)
    h = 1e-30 if angle > 0 else 1e-300  # a complex step in w_k; at 0 the first-order terms rule
    for k in range(3):
        step = w + 1j * h * np.eye(3)[k]
        expected = (half_angle_rodrigues(step) @ R0 @ X).imag / h
        np.testing.assert_allclose(np.cross(J[:, k], rotation @ X), expected, atol=4e-16)
