import jax
import numpy as np
import pytest

import mvcalib as mc


def rig_with_problems():
    """Six cameras; camera 1 sees only coplanar points, camera 3 only five points, camera 4
    sees its points mirrored (y up, fine but flagged), camera 5 has points on both sides."""
    rig = mc.synthetic.random_rig(jax.random.key(30), n_cameras=6, noise=0.3)
    world = np.broadcast_to(np.asarray(rig.world), (6, 19, 3)).copy()
    pixels = np.asarray(rig.pixels).copy()
    mask = np.ones((6, 19), bool)
    mask[1, 6:] = False  # ids 0-5: the floor z = 0 only
    world[1, :6, 2] = 0.0
    mask[3, 5:] = False
    pixels[4, :, 1] = 1100 - pixels[4, :, 1]
    # camera 5: move four world points behind the camera, keeping their (wrong) pixels
    c = np.asarray(rig.cameras.center[5])
    world[5, :4] = c + 0.8 * (c - world[5, :4])
    return rig, world, pixels, mask


def test_bad_cameras_get_a_status_and_the_rest_are_untouched():
    rig, world, pixels, mask = rig_with_problems()
    result = mc.calibrate(world, pixels, mask)
    S = mc.Status
    assert np.asarray(result.status).tolist() == [
        S.OK,
        S.DEGENERATE,
        S.OK,
        S.TOO_FEW_POINTS,
        S.OK,
        S.POINTS_BEHIND,
    ]
    assert np.asarray(result.ok).tolist() == [True, False, True, False, True, False]
    assert np.asarray(result.mirrored).tolist() == [False, False, False, False, True, False]
    # the mirrored camera still reproduces its pixels
    assert float(result.report.rms[4]) < 1.0
    for i in (0, 2):
        alone = mc.calibrate(world[i], pixels[i], mask[i])
        np.testing.assert_allclose(result.P[i], alone.P, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(result.report.rms[i], alone.report.rms, rtol=1e-12)
    assert np.all(np.isnan(np.asarray(result.P)[~np.asarray(result.ok)]))
    failed = ~np.asarray(result.ok)  # and no error to report: NaN, not a zero largest error
    for name in ("mean_x", "mean_y", "rms", "max"):
        assert np.all(np.isnan(np.asarray(getattr(result.report, name))[failed])), name
    assert "degenerate" in result.messages()[1] and "coplanar" in result.messages()[1]
    text = str(result)
    assert "too_few_points" in text and "points_behind" in text
    # the mirrored camera is named below the table (pixels given as (y, x) look the same)
    assert "mirrored: camera 4 sees a mirror image of the world" in text
    # a batch of two axes keeps its indices (numbered 0 to 5, a (2, 3) batch lost its shape)
    batch = mc.calibrate(world.reshape(2, 3, -1, 3), pixels.reshape(2, 3, -1, 2),
                         mask.reshape(2, 3, -1))  # fmt: skip
    rows = [line.split()[:2] for line in str(batch).splitlines()[2:8]]
    assert rows == [[f"{i},", str(j)] for i in range(2) for j in range(3)]
    assert "mirrored: camera 1, 1 sees a mirror image" in str(batch)


def test_strict_and_raise_if_failed_name_the_failed_cameras():
    rig, world, pixels, mask = rig_with_problems()
    with pytest.raises(mc.CalibrationError, match="camera 1: degenerate"):
        mc.calibrate(world, pixels, mask, strict=True)
    ok = mc.calibrate(world[0], pixels[0], mask[0], strict=True)
    assert ok.raise_if_failed() is ok


def test_refine_keeps_the_statuses_of_failed_cameras_in_a_rig_and_alone():
    # With refine=True a failed camera stays failed and NaN, in a rig and alone; alone it was
    # refused by `refine` ("0 visible points") instead of returning its status.
    rig, world, pixels, mask = rig_with_problems()
    result = mc.calibrate(world, pixels, mask, refine=dict(distortion=()))
    plain = mc.calibrate(world, pixels, mask)
    np.testing.assert_array_equal(result.status, plain.status)
    failed = ~np.asarray(plain.ok)
    assert np.isnan(np.asarray(result.cameras.alpha_u)[failed]).all()
    assert np.isfinite(np.asarray(result.cameras.alpha_u)[~failed]).all()
    for i in (1, 3, 5):
        alone = mc.calibrate(world[i], pixels[i], mask[i], refine=dict(distortion=()))
        assert int(alone.status) == int(plain.status[i]) and np.isnan(float(alone.cameras.alpha_u))
    alone = mc.calibrate(world[0], pixels[0], mask[0], refine=dict(distortion=()))
    np.testing.assert_allclose(alone.cameras.alpha_u, result.cameras.alpha_u[0], rtol=1e-9)


def test_collinear_points_are_degenerate():
    world = np.c_[np.linspace(0, 100, 10), 2 * np.linspace(0, 100, 10), np.full(10, 5.0)]
    pixels = np.random.default_rng(0).uniform(0, 500, size=(10, 2))
    assert int(mc.calibrate(world, pixels).status) == mc.Status.DEGENERATE


def test_nothing_raises_inside_jit_and_nan_in_traced_input_is_flagged():
    rig = mc.synthetic.random_rig(jax.random.key(31), n_cameras=3, noise=0.3)
    pixels = np.asarray(rig.pixels).copy()
    pixels[1, 4, 0] = np.nan
    result = jax.jit(lambda px: mc.calibrate(rig.world, px, strict=True))(pixels)
    assert np.asarray(result.status).tolist() == [0, mc.Status.NON_FINITE, 0]
    with pytest.raises(ValueError, match="non-finite"):  # at the boundary it is an error
        mc.calibrate(rig.world, pixels)


def test_report_is_table_one():
    rig = mc.synthetic.random_rig(jax.random.key(32), n_cameras=3, noise=0.5)
    mask = np.asarray(rig.mask).copy()
    mask[0, :3] = False
    report = mc.reprojection_report(rig.cameras, rig.world, rig.pixels, mask)
    err = np.asarray(rig.cameras.project(rig.world) - rig.pixels)
    for i in range(3):
        e = err[i][mask[i]]
        np.testing.assert_allclose(report.mean_x[i], e[:, 0].mean(), rtol=1e-12)
        np.testing.assert_allclose(report.mean_y[i], e[:, 1].mean(), rtol=1e-12)
        np.testing.assert_allclose(report.rms[i], np.sqrt((e**2).sum(1).mean()), rtol=1e-12)
        np.testing.assert_allclose(report.max[i], np.sqrt((e**2).sum(1)).max(), rtol=1e-12)
    assert np.asarray(report.n_points).tolist() == [16, 19, 19]
    # the noise is 0.5 px per axis: the true cameras' RMS is about 0.5 * sqrt(2)
    assert 0.4 < float(np.mean(report.rms)) < 1.0
    text = str(report)
    assert "mean err x" in text and text.count("\n") == 4


def test_calibrate_fits_better_than_the_truth_and_close_to_it():
    rig = mc.synthetic.random_rig(jax.random.key(33), n_cameras=50, noise=0.3)
    result = mc.calibrate(rig.world, rig.pixels)
    truth = mc.reprojection_report(rig.cameras, rig.world, rig.pixels)
    assert np.all(np.asarray(result.report.rms) <= np.asarray(truth.rms))
    assert np.all(np.asarray(result.condition) < 1e4)
    centre_err = np.linalg.norm(np.asarray(result.cameras.center - rig.cameras.center), axis=-1)
    distance = np.linalg.norm(np.asarray(rig.cameras.center - rig.world.mean(0)), axis=-1)
    assert np.median(centre_err / distance) < 0.01


def test_paper_scene_noise_free_gives_one_pixel_from_all_four_snapshots():
    from mvcalib import demo

    result = demo.run(noise=0.0, global_noise=0.0)
    true = np.asarray(result.scene.camera.project(result.scene.fixed_point[None])[0])
    assert np.abs(result.unified - true).max() < 1e-6
    assert np.ptp(result.unified, axis=0).max() < 1e-6
    # the registration recovers the target's placements exactly
    np.testing.assert_allclose(result.registration.R, result.scene.placements.R, atol=1e-10)


def test_paper_scene_scatter_with_noise_matches_first_order_prediction():
    from mvcalib import demo

    errors, sigmas = [], []
    for seed in range(12):
        result = demo.run(noise=0.3, seed=seed)
        true = np.asarray(result.scene.camera.project(result.scene.fixed_point[None])[0])
        errors.append(result.unified - true)
        sigmas.append(result.unified_sigma)
    z = np.concatenate(errors) / np.concatenate(sigmas)
    # standardised errors: unit variance if the pipeline and its Jacobian are right
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.5
