"""calibrate_rig: a rig from a target moved through its volume, against ground truth
(`mc.synthetic.board_rig`) and caliscope's real 4-camera recording."""

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import data_dir

import mvcalib as mc
import mvcalib._rig  # noqa: F401  (mc._rig, loaded on first use otherwise)


@functools.cache
def _rig(target="board", noise=0.3, key=0, n_cameras=8, n_frames=100):
    return mc.synthetic.board_rig(jax.random.key(key), n_cameras, n_frames, target, noise=noise)


def _in_reference_frame(cameras: mc.Camera):
    """The true centres and rotations in camera 0's frame."""
    R0, t0 = np.asarray(cameras.R[0]), np.asarray(cameras.t[0])
    centres = np.asarray(cameras.center) @ R0.T + t0
    return centres, np.asarray(cameras.R) @ R0.T


def _errors(rig, result):
    """Largest centre error over the baseline, rotation error (degrees), intrinsics error
    (relative), and the same errors over their reported standard errors."""
    centres, rotations = _in_reference_frame(rig.cameras)
    baseline = np.linalg.norm(centres - centres[0], axis=1).max()
    d_centre = np.asarray(result.cameras.center) - centres
    # the rotation error as an angle: |R_est - R_true|_F / sqrt(2) = 2 sin(angle / 2)
    d_rotation = np.degrees(
        np.linalg.norm(np.asarray(result.cameras.R) - rotations, axis=(1, 2)) / np.sqrt(2)
    )
    intrinsics = max(
        np.abs(
            np.asarray(getattr(result.cameras, n)) / np.asarray(getattr(rig.cameras, n)) - 1
        ).max()
        for n in ("alpha_u", "alpha_v", "u0", "v0")
    )
    std = np.asarray(result.position_std)[1:]
    sigmas = np.abs(d_centre[1:]) / std
    return np.abs(d_centre).max() / baseline, d_rotation.max(), intrinsics, sigmas.max()


@pytest.mark.parametrize("target", ["board", "object"])
def test_noise_free_rig_is_recovered_exactly(target):
    rig = _rig(target, noise=0.0)
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    assert bool(result.ok.all()), result
    assert bool(result.converged), (int(result.iterations), int(result.result), float(result.rms))
    position, rotation, intrinsics, _ = _errors(rig, result)
    assert position < 1e-8 and np.radians(rotation) < 1e-8 and intrinsics < 1e-8
    dist = np.abs(np.asarray(result.cameras.dist) - np.asarray(rig.cameras.dist)).max()
    assert dist < 1e-8
    # the target's poses too, in camera 0's frame
    T0 = mc.RigidTransform(rig.cameras.R[0], rig.cameras.t[0])
    truth = T0 @ rig.poses
    posed = np.asarray(result.used).any((0, 2))  # the frames some calibrated camera used
    assert np.isnan(np.asarray(result.target_poses.t)[~posed]).all()
    assert np.abs(np.asarray(result.target_poses.t) - np.asarray(truth.t))[posed].max() < 1e-8


def _rotation_errors_over_std(rig, result):
    """Each camera's rotation error about its own axes (`R_est R_true^T` as a rotation vector,
    by SciPy) over its reported `rotation_std`, cameras 1 on (camera 0 is the gauge)."""
    from scipy.spatial.transform import Rotation

    _, rotations = _in_reference_frame(rig.cameras)
    error = np.asarray(result.cameras.R) @ np.transpose(rotations, (0, 2, 1))
    degrees = Rotation.from_matrix(error[1:]).as_rotvec(degrees=True)
    return degrees / np.asarray(result.rotation_std)[1:]


@pytest.mark.parametrize("target", ["board", "object"])
def test_noisy_rig_is_within_its_standard_errors(target):
    """0.3 px of noise, k1 k2: every camera's centre and rotation within 4 of their standard
    errors, the rotations' scatter that of their standard errors (RMS over the 21 components
    0.80 and 1.19 for board and object; over keys 0-2, 0.42-1.30, the largest of 63 components
    1.2-2.4), and the closing note's figures: centres within 0.1 % of the baseline, rotations
    0.1 degrees, the intrinsics 0.3 % (the spec's 0.05 degrees and 0.2 % are 1-2 standard
    errors of this scene: see the issue's note)."""
    rig = _rig(target)
    visible = np.asarray(rig.mask).any(-1).mean(1)
    assert visible.min() >= 0.2 and visible.max() <= 0.6
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    assert bool(result.ok.all()) and bool(result.converged)
    position, rotation, intrinsics, sigmas = _errors(rig, result)
    assert sigmas < 4.0
    z = _rotation_errors_over_std(rig, result)
    assert np.abs(z).max() < 4.0 and 0.4 < np.sqrt(np.mean(z**2)) < 2.0, z
    assert position < 1e-3 and rotation < (0.1 if target == "board" else 0.15)
    assert intrinsics < 3e-3
    assert 0.38 < float(result.rms) < 0.46  # sqrt(2) 0.3 px, less the parameters' share


def test_disconnected_camera_gets_its_status_and_changes_nothing():
    rig = _rig(noise=0.3)
    mask = np.asarray(rig.mask).copy()
    seen = mask.any(-1)
    # camera 3 keeps 12 of its frames and the others lose them: no chain links it to camera 0
    alone = np.flatnonzero(seen[3])[:12]
    mask[:, alone] = False
    mask[3] = False
    mask[3, alone] = np.asarray(rig.mask)[3, alone]
    result = mc.calibrate_rig(rig.target, rig.pixels, mask)
    assert int(result.status[3]) == mc.Status.NOT_CONNECTED
    assert np.isnan(np.asarray(result.cameras.alpha_u[3]))
    assert bool(np.delete(np.asarray(result.ok), 3).all())
    others = np.delete(np.arange(8), 3)
    without = mc.calibrate_rig(rig.target, rig.pixels[others], mask[others])
    a, b = np.asarray(result.cameras.center)[others], np.asarray(without.cameras.center)
    assert np.abs(a - b).max() < 1e-8


def _first_solve_altered(monkeypatch, key: str, alter) -> list:
    """`calibrate_rig`'s joint solves counted (the returned list), the first one's output `key`
    replaced by `alter` of it: a stand-in for a solve that ended badly."""
    joint, calls = mc._rig._calibrate_rig, []

    def altered(*args, **kwargs):
        out = joint(*args, **kwargs)
        calls.append(1)
        if len(calls) == 1:
            out[key] = alter(out[key])
        return out

    monkeypatch.setattr(mc._rig, "_calibrate_rig", altered)
    return calls


def test_a_good_camera_left_out_joins_again_when_it_fits_the_rest(capsys, monkeypatch):
    """A camera that the solve flags POOR_FIT (here by a stand-in for a start that wandered off:
    64 cameras x 250 frames of a 6 x 8 board, camera 39's own solve went from 1404 to 88 px of
    focal length, the truth 996, and the joint solve left it at 284 px RMS) is calibrated
    against the rest of the rig; it fits, so the rig is solved again with it: the answer of a
    solve that never lost it."""
    rig = _rig(noise=0.3)
    clean = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    calls = _first_solve_altered(monkeypatch, "status", lambda s: s.at[1].set(mc.Status.POOR_FIT))
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, verbose=True)
    err = capsys.readouterr().err
    assert "camera 1: poor fit" in err and "camera 1: calibrated against the rest" in err
    assert bool(result.ok.all()) and len(calls) == 3  # flagged, without it, with it again
    a, b = np.asarray(result.cameras.center), np.asarray(clean.cameras.center)
    assert np.abs(a - b).max() < 1e-8


def test_a_camera_far_worse_than_the_rest_starts_again(capsys, monkeypatch):
    """The worst camera, more than 3 times the median camera's RMS after the first solve (here
    camera 1, by a stand-in), is calibrated against the rest of the rig and the rig solved again
    from there; the second answer fits better, and is the answer of a solve that started well."""
    rig = _rig(noise=0.3)
    clean = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    calls = _first_solve_altered(monkeypatch, "camera_rms", lambda r: r.at[1].multiply(20.0))
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, verbose=True)
    assert "camera 1: calibrated against the rest" in capsys.readouterr().err
    assert bool(result.ok.all()) and len(calls) == 2
    a, b = np.asarray(result.cameras.center), np.asarray(clean.cameras.center)
    assert np.abs(a - b).max() < 1e-8


def test_a_rig_that_once_wandered_off_comes_out_right(monkeypatch, request):
    """16 cameras x 100 frames of a 6 x 8 board (key 10), the own solves side by side (`vmap`,
    as on an accelerator). Camera 2's closed-form focal length was 10,885 px (the truth 1,300)
    before the median over frames (1,323 now); its own solve took it to 5,020 and the joint
    solve ended in a minimum at 3.42 px RMS, camera 2 at 11.4 px and every camera OK (caught
    then by the retry from its resection)."""
    monkeypatch.setattr(mc._rig._sharding, "cpu_chunk", lambda n, size: None)
    mc._rig._start_own.clear_cache()  # (traced with the solves side by side: this test only)
    request.addfinalizer(mc._rig._start_own.clear_cache)
    rig = mc.synthetic.board_rig(
        jax.random.key(10), 16, 100, target=mc.synthetic.board(6, 8, 0.05), noise=0.3
    )
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    assert bool(result.ok.all()) and float(result.rms) < 0.43
    assert abs(float(result.cameras.alpha_u[2]) / float(rig.cameras.alpha_u[2]) - 1) < 3e-3


def _hard_start_rig():
    """16 cameras x 250 frames of a 6 x 8 board (key 7), where a least squares over all of a
    camera's frames put camera 10's focal length at 10.1 times the truth, and camera 13's at
    2.8."""
    return mc.synthetic.board_rig(
        jax.random.key(7), 16, 250, target=mc.synthetic.board(6, 8, 0.05), noise=0.3
    )


def test_the_start_focal_lengths_are_the_median_over_frames():
    """Each camera's starting focal length, the median of its frames' own: every camera of
    the rig within 15 % of the truth (the principal point at the centre of the pixels seen)."""
    rig = _hard_start_rig()
    target, pixels, mask = (jnp.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
    plane = mc._rig._plane_frame(np.asarray(target), np.ones(len(target), bool), jnp.float64)
    xy = plane.apply(target)[:, :2]
    K, determined, *_ = mc._rig._pair_poses_planar(plane, xy, pixels, mask, None, 1.5e-8)
    assert bool(determined.all())
    for name, i in (("alpha_u", 0), ("alpha_v", 1)):
        ratio = np.asarray(K[:, i, i]) / np.asarray(getattr(rig.cameras, name))
        assert np.abs(ratio - 1).max() < 0.15, ratio


def test_a_rig_whose_start_pulled_cameras_off_is_solved_at_once(monkeypatch):
    """The rig of the test above: from the start of the least squares, the joint solve of the
    optimised build ended with every camera POOR_FIT (ValueError: the reference camera cannot
    be calibrated; the tests' quick build, rounding otherwise, came through). From the median's
    start: one solve, every camera OK, in either build."""
    rig = _hard_start_rig()
    calls = _first_solve_altered(monkeypatch, "status", lambda s: s)
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    assert bool(result.ok.all()) and bool(result.converged) and len(calls) == 1
    assert 0.40 < float(result.rms) < 0.43


def test_a_solve_that_fails_every_camera_says_so(monkeypatch):
    """Every camera POOR_FIT (here by a stand-in for the first solve): not "choose another
    reference", which could not help, but what failed and what to check."""
    rig = _rig(noise=0.3)
    # (every solve: the rig is solved again without each camera in turn first)
    joint = mc._rig._calibrate_rig

    def failed(*args, **kwargs):
        out = joint(*args, **kwargs)
        return {**out, "status": out["status"].at[:].set(mc.Status.POOR_FIT)}

    monkeypatch.setattr(mc._rig, "_calibrate_rig", failed)
    # (an mc.CalibrationError, as a strict calibrate raises: a photographer's trial caught that)
    with pytest.raises(mc.CalibrationError, match="every camera reprojects its points"):
        mc.calibrate_rig(rig.target, rig.pixels, rig.mask)


def test_own_frames_are_spread_evenly_and_distinct():
    ok = np.zeros((3, 10), bool)
    ok[0, [1, 2, 4, 5, 7, 8, 9]] = True  # 7 frames: 4 of them, evenly
    ok[1, [3, 6]] = True  # 2 frames: both, then others
    take = np.asarray(mc._rig._own_frames(jnp.asarray(ok), 4))
    assert take[0].tolist() == [1, 2, 5, 8]  # its frames 0, 1.75, 3.5, 5.25, floored
    assert take[1, :2].tolist() == [3, 6] and not ok[1, take[1, 2:]].any()
    assert not ok[2, take[2]].any()
    assert all(len(set(row)) == 4 for row in take.tolist())


@pytest.mark.parametrize("target", ["board", "object"])
def test_own_solves_from_some_of_the_frames_reach_the_same_rig(target, monkeypatch, request):
    """Each camera's own solve from `OWN_FRAMES` of its frames (here 24 of its 20-60), the other
    frames posed from their homographies with the refined intrinsics (a 3-D target: the DLT's
    poses): the joint solve reaches the rig of own solves from every frame."""
    rig = _rig(target)
    every = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    monkeypatch.setattr(mc._rig, "OWN_FRAMES", 24)
    mc._rig._start_own.clear_cache()  # (traced with the smaller cap, for this test only)
    request.addfinalizer(mc._rig._start_own.clear_cache)
    some = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    assert bool(some.ok.all()) and bool(some.converged)
    a, b = np.asarray(some.cameras.center), np.asarray(every.cameras.center)
    assert np.abs(a - b).max() < 1e-6 * np.abs(b).max()
    assert abs(float(some.rms) - float(every.rms)) < 1e-9


def test_a_camera_that_fits_nothing_is_not_let_back_in():
    """Its calibration against the rest of the rig fails too: it stays out (the garbage camera of
    the test above, 60 px of noise)."""
    rig = _rig(noise=0.3)
    pixels = np.asarray(rig.pixels).copy()
    pixels[2] += np.random.default_rng(0).normal(scale=60.0, size=pixels[2].shape)
    left_out = jax.tree_util.tree_map(np.asarray, mc.calibrate_rig(rig.target, pixels, rig.mask))
    start, fitted = mc._rig._resected(
        left_out, np.arange(8) == 2, rig.target, pixels, rig.mask, None, False, np.float64
    )
    assert not fitted.any() and np.isnan(np.asarray(start.alpha_u)[2])
    assert np.isfinite(np.asarray(start.alpha_u)[np.arange(8) != 2]).all()


def test_a_camera_that_fits_nothing_links_no_other(monkeypatch):
    """The same garbage camera shares frames with the others, and the chain of relative poses
    took camera 3 through it: its start 6-12 % of the baseline off (until 2026-12-05; the
    joint solve brought it back). A camera whose own solve fits its frames poorly (85 px here)
    links others only where nothing else does: every other camera starts within 1 % of the
    baseline."""
    rig = _rig(noise=0.3)
    pixels = np.asarray(rig.pixels).copy()
    pixels[2] += np.random.default_rng(0).normal(scale=60.0, size=pixels[2].shape)
    joint, starts = mc._rig._calibrate_rig, []

    def recorded(start, *args, **kwargs):
        out = joint(start, *args, **kwargs)  # (a stand-in's call, compiling ahead, raises)
        starts.append(start)
        return out

    monkeypatch.setattr(mc._rig, "_calibrate_rig", recorded)
    result = mc.calibrate_rig(rig.target, pixels, rig.mask)
    assert np.asarray(result.status).tolist() == [0, 0, 6, 0, 0, 0, 0, 0]
    centres, _ = _in_reference_frame(rig.cameras)
    baseline = np.linalg.norm(centres - centres[0], axis=1).max()
    error = np.linalg.norm(np.asarray(starts[0][0].center) - centres, axis=1)
    assert np.delete(error, 2).max() < 0.01 * baseline, error / baseline


@pytest.mark.parametrize("loss", [mc.Huber(1.0), mc.Cauchy(1.0)])
def test_robust_loss_keeps_the_accuracy_with_one_percent_wild_detections(loss):
    """A redescending loss (Cauchy) from the closed form: with the steps' old model it gave up
    whole frames and ended with every camera POOR_FIT (ValueError), and so it started from the
    Huber answer (until 2026-12-05); with Ceres' model it needs no such start."""
    rig = _rig(noise=0.3)
    rng = np.random.default_rng(0)
    pixels, mask = np.asarray(rig.pixels).copy(), np.asarray(rig.mask)
    where = np.argwhere(mask)
    wild = where[rng.choice(len(where), len(where) // 100, replace=False)]
    angle = rng.uniform(0, 2 * np.pi, len(wild))
    pixels[tuple(wild.T)] += 50.0 * np.c_[np.cos(angle), np.sin(angle)]
    result = mc.calibrate_rig(rig.target, pixels, mask, loss=loss)
    assert bool(result.ok.all()) and bool(result.converged)
    position, rotation, intrinsics, sigmas = _errors(rig, result)
    assert position < 1e-3 and rotation < 0.1 and intrinsics < 3e-3
    assert not np.asarray(result.inliers)[tuple(wild.T)].any()  # every wild one is flagged
    # the standard errors those of the clean rig, a little more (Huber's bounded pull); they
    # were 9-11 times larger with Huber: the wild points' cost counted as noise
    clean = mc.calibrate_rig(rig.target, rig.pixels, mask)
    ratio = np.asarray(result.position_std)[1:] / np.asarray(clean.position_std)[1:]
    assert 0.9 < ratio.min() and ratio.max() < 1.3, ratio
    assert sigmas < 4.0
    assert abs(float(result.rms_inliers) - float(clean.rms)) < 0.01  # px


def _wild(pixels, mask, seed):
    """`pixels` with 1 % of the visible ones moved by 50 px, in random directions."""
    rng = np.random.default_rng(seed)
    pixels = pixels.copy()
    where = np.argwhere(mask)
    wild = where[rng.choice(len(where), len(where) // 100, replace=False)]
    d = rng.normal(size=(len(wild), 2))
    pixels[tuple(wild.T)] += 50 * d / np.linalg.norm(d, axis=1, keepdims=True)
    return pixels


def test_a_robust_loss_converges_as_least_squares_does():
    """16 x 250 (key 1), 1 % of the corners moved by 50 px: `Huber(1.0)` stopped unconverged at
    100 steps, frame 37 left at 224 px in camera 11, its focal length 0.37 % off (10 standard
    errors), and `Cauchy(1.0)` raised on a 3-D target's rig (8 x 100, key 2: every camera
    POOR_FIT), until 2026-12-05. The robust solves' Gauss–Newton model was that of the residuals
    scaled by `sqrt(rho / r^2)`, which steps twice too far where a point's loss is linear, and
    the damping crept. It is Ceres' now (`_refine._irls`): 9 steps, every pair used, every focal
    length within 0.03 %."""
    rig = mc.synthetic.board_rig(
        jax.random.key(1), 16, 250, target=mc.synthetic.board(6, 8, 0.05), noise=0.3
    )
    target, pixels, mask = (np.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
    result = mc.calibrate_rig(target, _wild(pixels, mask, seed=1), mask, loss=mc.Huber(1.0))
    assert bool(result.ok.all()) and bool(result.converged)
    assert int(result.iterations) <= 15, int(result.iterations)  # (least squares: 8 steps)
    observed = mask.any(-1) & ~np.asarray(result.skipped)
    assert (observed == np.asarray(result.used).any(-1)).all()
    error = np.abs(np.asarray(result.cameras.alpha_u) / np.asarray(rig.cameras.alpha_u) - 1)
    assert error.max() < 5e-4, error


def test_views_of_a_board_turned_by_180_degrees_are_left_out_not_the_camera():
    """A symmetric board's corners found in the reverse order (the board seen turned by 180
    degrees) in three of camera 3's frames, 1 % of all corners moved by 50 px, `Huber(1.0)`:
    the two turned frames that other cameras saw fit nothing and are left out; the one only
    camera 3 saw is a pose of its own. (Until 2026-12-05 the camera was judged by its RMS over
    all its points, 72 px, and left out as POOR_FIT.)"""
    rig = _rig("board", noise=0.3)
    target, pixels, mask = (np.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
    pixels = _wild(pixels, mask, seed=0)
    turned = [12, 15, 21]  # camera 3 sees every corner in these; frame 12 alone
    assert mask[3, turned].all() and mask[:, 12].any(-1).sum() == 1
    pixels[3, turned] = pixels[3, turned, ::-1]
    result = mc.calibrate_rig(target, pixels, mask, loss=mc.Huber(1.0))
    assert bool(result.ok.all()) and bool(result.converged)
    observed = mask.any(-1) & ~np.asarray(result.skipped)
    assert np.argwhere(observed & ~np.asarray(result.used).any(-1)).tolist() == [[3, 15], [3, 21]]
    clean = mc.calibrate_rig(target, np.asarray(rig.pixels), mask)
    errors, clean_errors = _errors(rig, result)[:3], _errors(rig, clean)[:3]
    assert all(e < 1.3 * c for e, c in zip(errors, clean_errors)), (errors, clean_errors)


def test_a_stereo_pair_goes_into_opencvs_rectification_as_it_is():
    """A stereo pair is a rig of two: camera 0's frame is the world, so OpenCV's stereo R, T
    are camera 1's (T as a column: cv2.stereoRectify refuses (3,)), the distortion in OpenCV's
    order. Rectified with them, the board's corners lie on the same rows in both images (to
    the noise), and the baseline is the true one; started from cameras calibrated one by one
    (`Camera.stack`) with their intrinsics held, too."""
    cv2 = pytest.importorskip("cv2")
    rig = _rig("board", noise=0.3)  # cameras 0 and 1, neighbours in the ring
    target, pixels, mask = (
        np.asarray(rig.target),
        np.asarray(rig.pixels)[:2],
        np.asarray(rig.mask)[:2],
    )
    result = mc.calibrate_rig(target, pixels, mask)
    K, dist = np.asarray(result.cameras.K), np.asarray(result.cameras.dist)
    R, T = np.asarray(result.cameras.R[1]), np.asarray(result.cameras.t[1]).reshape(3, 1)
    R1, R2, P1, P2 = cv2.stereoRectify(K[0], dist[0], K[1], dist[1], (1280, 800), R, T)[:4]
    both = mask[0] & mask[1]
    rows = [cv2.undistortPoints(pixels[c][both].reshape(-1, 1, 2), K[c], dist[c], R=r, P=p)[:, 0, 1]
            for c, r, p in ((0, R1, P1), (1, R2, P2))]  # fmt: skip
    assert np.sqrt(np.mean((rows[0] - rows[1]) ** 2)) < 0.6  # px (noise 0.3 px in each)
    truth = np.linalg.norm(np.asarray(rig.cameras.center[1] - rig.cameras.center[0]))
    assert abs(np.linalg.norm(T) / truth - 1) < 1e-3
    alone = [mc.calibrate_planar(target, pixels[c][mask[c].all(-1)]).camera[0] for c in (0, 1)]
    held = mc.calibrate_rig(target, pixels, mask, cameras=mc.Camera.stack(alone), fix="intrinsics")
    assert bool(held.ok.all())
    np.testing.assert_array_equal(np.asarray(held.cameras.K), np.asarray(mc.Camera.stack(alone).K))
    # An OpenCV user's trial: cameras from `cv2.calibrateCamera` (five coefficients, k3 too)
    # with `fix="intrinsics"`: k1 k2 p1 p2 moved and k3 was held, nothing said, 0.3 % of the
    # baseline from `cv2.stereoCalibrate(..., CALIB_FIX_INTRINSIC)`. Now that warns, and
    # holding the distortion too is OpenCV's solve.
    full = mask[0].all(-1) & mask[1].all(-1)
    views = [[p.astype(np.float32) for p in pixels[c][full]] for c in (0, 1)]
    board = [target.astype(np.float32)] * int(full.sum())
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    opencv = [cv2.calibrateCamera(board, views[c], (1280, 800), None, None, criteria=criteria)[1:3]
              for c in (0, 1)]  # fmt: skip
    stereo = cv2.stereoCalibrate(board, *views, *opencv[0], *opencv[1], (1280, 800),
                                 flags=cv2.CALIB_FIX_INTRINSIC, criteria=criteria)  # fmt: skip
    start = mc.Camera.stack([mc.Camera.from_matrices(k, np.eye(3), np.zeros(3), dist=d.ravel())
                             for k, d in opencv])  # fmt: skip
    assert np.abs(np.asarray(start.dist)[:, 4]).min() > 1e-3  # (k3 is not zero)
    with pytest.warns(UserWarning, match=r"k3 \(camera 0: .* is held at its value"):
        mc.calibrate_rig(target, pixels, mask, cameras=start, fix="intrinsics")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        same = mc.calibrate_rig(target, pixels, mask & full[:, None], cameras=start,
                                fix=("intrinsics", "distortion"))  # (OpenCV's frames)  # fmt: skip
    np.testing.assert_allclose(np.asarray(same.cameras.R[1]), stereo[5], atol=1e-6)
    np.testing.assert_allclose(np.asarray(same.cameras.t[1]), stereo[6].ravel(), atol=1e-6 * truth)


def test_a_camera_that_never_sees_enough_of_the_board_is_told_so_in_a_rigs_words():
    """Its status is TOO_FEW_POINTS, whose message was the DLT's ("fewer than 6 visible points:
    the 11 unknowns of P"), where a board needs 4 points a frame."""
    rig = _rig("board", noise=0.3)
    target, pixels, mask = (np.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
    mask = mask.copy()
    mask[5] &= np.arange(mask.shape[-1]) < 3  # camera 5: 3 corners a frame at most
    # (until 2026-12-06 DEGENERATE, "record more frames at other angles", unless its intrinsics
    # were given)
    for given in ({}, {"cameras": rig.cameras, "fix": "intrinsics"}):
        result = mc.calibrate_rig(target, pixels, mask, **given)
        assert int(result.status[5]) == mc.Status.TOO_FEW_POINTS
        assert "4 points of a board" in result.messages()[5]
        assert np.flatnonzero(~np.asarray(result.ok)).tolist() == [5]


def test_a_blurred_camera_keeps_its_sound_frames_under_a_robust_loss():
    """A stereo user's second camera saw the board blurred (2.7 px against 0.35): judged against
    the median pair of the whole rig, 8-12 of its ~30 sound frames were left out silently.
    Each pair is judged against its own camera's pairs now; a turned board is still left out
    (the test above)."""
    rig = _rig("board", noise=0.3)
    target, pixels, mask = (np.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
    pixels = pixels.copy()
    # ~7 px RMS: judged against the whole rig's median pair (0.4 px), 20 of its 32 pairs went
    pixels[2] += np.random.default_rng(5).normal(scale=5.0, size=pixels[2].shape)
    result = mc.calibrate_rig(target, pixels, mask, loss=mc.Huber(1.0))
    assert bool(result.ok.all())
    observed = mask.any(-1) & ~np.asarray(result.skipped)
    assert (observed == np.asarray(result.used).any(-1)).all()  # no pair left out


def test_wild_detections_fitted_by_least_squares_are_pointed_out():
    """2 % of a stereo pair's corners moved by 20-50 px: both cameras came back OK at 5.2 px
    RMS, focal lengths 18-20 px off, and nothing said why. A calibrated camera with 3 or more
    observations 10 times the median residual away says so, naming the robust loss; a clean
    rig, or one fitted with a loss, does not."""
    rig = _rig("board", noise=0.3)
    target, pixels, mask = (np.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
    assert all(m == "calibrated" for m in mc.calibrate_rig(target, pixels, mask).messages())
    wild = _wild(pixels, mask, seed=3)
    messages = mc.calibrate_rig(target, wild, mask).messages()
    assert all("observations lie" in m and "loss=mc.Huber(2.0)" in m for m in messages), messages
    robust = mc.calibrate_rig(target, wild, mask, loss=mc.Huber(1.0)).messages()
    assert all(m == "calibrated" for m in robust), robust


def test_a_camera_that_fits_far_worse_than_the_rest_is_pointed_out():
    """A user's trial: one camera given the intrinsics of an earlier calibration (focal length
    5 % and principal point 40 px off since) and held there came out OK at 0.98 px against the
    others' 0.42-0.49, its centre 95 mm off against a standard error of 1.1 mm, and nothing
    said. A calibrated camera whose RMS is more than twice the median of the rig's others says
    so, naming the held intrinsics; held true intrinsics give no note."""
    rig = mc.synthetic.board_rig(jax.random.key(4), n_cameras=4, n_frames=80, noise=0.3)
    truth = jax.tree_util.tree_map(np.asarray, rig.cameras)
    held = dict(fix=["intrinsics", "distortion"])
    clean = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=truth, **held)
    assert clean.messages() == ["calibrated"] * 4
    stale = eqx.tree_at(
        lambda c: (c.alpha_u, c.alpha_v, c.u0),
        truth,
        (truth.alpha_u.copy(), truth.alpha_v.copy(), truth.u0.copy()),
    )
    stale.alpha_u[2] *= 1.05
    stale.alpha_v[2] *= 1.05
    stale.u0[2] += 40.0
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=stale, **held)
    messages = result.messages()
    assert bool(result.ok.all())
    assert (
        messages[2].startswith("calibrated; but its RMS")
        and "intrinsics were held" in (messages[2])
    ), messages
    assert [m for i, m in enumerate(messages) if i != 2] == ["calibrated"] * 3


def _moving_board(frames=240, late=None, metres_a_second=0.4, fps=30.0, key=27):
    """A board moved smoothly through a 5-camera rig's volume and filmed at `fps`: position and
    turn on Lissajous curves. Camera `late`'s frames one out of step: its image of frame f is
    labelled f + 1 (0.4 m/s at 30 frames a second: 13 mm a frame)."""
    rig = mc.synthetic.board_rig(jax.random.key(key), n_cameras=5, n_frames=10, noise=0.0)
    cameras, target = rig.cameras, np.asarray(rig.target) - np.asarray(rig.target).mean(0)
    s, time = metres_a_second / 0.4, np.arange(frames) / fps
    where = np.stack([0.4 * np.sin(0.9 * s * time), 0.3 * np.sin(1.3 * s * time + 1),
                      0.4 * np.sin(0.7 * s * time + 2)], -1)  # fmt: skip
    turn = np.stack([0.6 * np.sin(0.5 * s * time), 2.5 * np.sin(0.23 * s * time),
                     0.5 * np.sin(0.8 * s * time + 1)], -1)  # fmt: skip
    R = np.asarray(jax.vmap(mc.rodrigues)(turn))
    world = np.einsum("fij,nj->fni", R, target) + where[:, None]
    rng = np.random.default_rng(key)
    pixels = np.zeros((5, frames, len(target), 2))
    mask = np.zeros((5, frames, len(target)), bool)
    for c in range(5):
        p = np.array(cameras[c].project(world.reshape(-1, 3))).reshape(frames, -1, 2)
        p += rng.normal(0.0, 0.3, p.shape)
        towards = np.asarray(cameras.center[c]) - where
        towards /= np.linalg.norm(towards, axis=-1, keepdims=True)
        facing = np.abs(np.sum(R[:, :, 2] * towards, -1)) > np.cos(np.radians(65))
        seen = (p > 0).all(-1) & (p[..., 0] < 1280) & (p[..., 1] < 800) & facing[:, None]
        if c == late:
            p, seen = np.roll(p, 1, 0), np.roll(seen, 1, 0)
            seen[0] = False
        pixels[c], mask[c] = p, seen
    return cameras, target, pixels, mask


def test_a_camera_one_frame_out_of_step_is_pointed_out():
    """A user's trial: one camera of five one frame late, a board moving 13 mm a frame: every
    camera OK and 'calibrated', the late one 125 mm off against a standard error of 2.3 mm and
    the others pulled 45-110 mm. At 20 mm a frame its own poses of the board agree with the
    other cameras' 19 times better shifted by one frame (the others' 4-6 times worse shifted):
    it says so, and the others that it may have pulled them; in step, nothing is said. (At 13
    mm a frame, 3.9 times over 400 frames, but 1.3 over 240: not told.)"""
    cameras, target, pixels, mask = _moving_board(late=3, metres_a_second=0.6)
    result = mc.calibrate_rig(target, pixels, mask)
    messages = result.messages()
    assert "times better with its frame f + 1 taken as their frame f" in messages[3], messages
    for c in (0, 1, 2, 4):
        assert "camera 3 seems one frame out of step" in messages[c], messages[c]
    cameras, target, pixels, mask = _moving_board(metres_a_second=0.6)
    result = mc.calibrate_rig(target, pixels, mask)
    assert not any("out of step" in m for m in result.messages()), result.messages()
    spread = np.asarray(result.step_spread)
    assert np.all(spread[:, 1] < np.minimum(spread[:, 0], spread[:, 2])), spread


def test_alone_rms_is_the_noise_of_the_detections():
    """Each pair's points fitted alone (a homography of a board, a DLT of a 3-D target), per
    degree of freedom, the lens's distortion removed: the noise's RMS length, sqrt(2) sigma.
    Without a lens to remove (intrinsics not given), a pair's is what OpenCV's homography of
    its pixels leaves."""
    import cv2

    for target in ("board", "object"):
        rig = _rig(target, n_cameras=4, n_frames=40)
        held = dict(cameras=rig.cameras, fix=("intrinsics", "distortion"))
        result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, **held)
        alone = np.asarray(result.alone_rms)
        assert np.isfinite(alone).sum() >= 30  # (each camera sees 20-60 % of the frames)
        assert abs(np.nanmedian(alone) / (0.3 * np.sqrt(2)) - 1) < 0.05, np.nanmedian(alone)
    rig = _rig("board", n_cameras=4, n_frames=40)
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    alone, mask = np.asarray(result.alone_rms), np.asarray(rig.mask)
    points, pixels = np.asarray(rig.target)[:, :2], np.asarray(rig.pixels)
    for c, f in zip(*np.nonzero(np.isfinite(alone))[:2]):
        m = mask[c, f]
        H, _ = cv2.findHomography(points[m], pixels[c, f, m], 0)
        x = np.c_[points[m], np.ones(m.sum())] @ H.T
        theirs = np.sqrt(np.sum((x[:, :2] / x[:, 2:] - pixels[c, f, m]) ** 2) / (m.sum() - 4))
        assert abs(alone[c, f] / theirs - 1) < 0.01, (c, f, alone[c, f], theirs)


def test_held_intrinsics_without_poses_start_the_rig_as_with_them():
    """A file of the intrinsics alone (OpenCV's calibration samples save no pose;
    `io.load_opencv` gives them a NaN pose): its cameras start a rig whose intrinsics are held
    as the same cameras with their poses do, bit for bit (the poses come from the frames)."""
    rig = _rig("board", n_cameras=4, n_frames=40)  # (the programs of the test above)
    fix = ("intrinsics", "distortion")
    nan = np.full((4, 3, 3), np.nan), np.full((4, 3), np.nan)
    unknown = eqx.tree_at(lambda c: (c.R, c.t), rig.cameras, nan)
    out = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=unknown, fix=fix)
    known = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=rig.cameras, fix=fix)
    assert bool(out.ok.all())
    np.testing.assert_array_equal(np.asarray(out.cameras.center), np.asarray(known.cameras.center))


def test_a_held_rig_that_does_not_fit_says_what_was_held():
    """A user's trial: a rig checked against a board printed 2 % too large (every parameter of
    the cameras held) was OK at 4 times the noise, and the notes blamed wrong detections and
    said that least squares let them pull every camera (none could move). The camera whose
    frames fit 5 times worse in the rig than each alone names the held pose, the board's size
    and its units; none speaks of a pull."""
    rig = mc.synthetic.board_rig(jax.random.key(24), n_cameras=4, n_frames=60, noise=0.3)
    fix = ["intrinsics", "distortion", "pose"]
    board = np.asarray(rig.target) * 1.02
    result = mc.calibrate_rig(board, rig.pixels, rig.mask, cameras=rig.cameras, fix=fix)
    messages = result.messages()
    assert any("pose was held" in m and "target's size or units" in m for m in messages)
    assert not any("pull" in m for m in messages), messages
    right = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=rig.cameras, fix=fix)
    assert right.messages() == ["calibrated"] * 4


def test_one_mirrored_camera_is_poor_fit_and_the_rest_calibrated(capsys):
    """A user's trial: one webcam's video mirrored (selfie mode). Without a loss the joint solve
    left every camera POOR_FIT and raised SolveFailed, naming the good cameras' worst frames;
    with its corner ids mirrored instead and a Huber loss, it was left out as TOO_FEW_POINTS ("no
    frame shows it enough of the target", of 28 frames of all 108 corners); with `Cauchy(2.0)`
    it was OK at 0.41 px, 35 degrees and a metre off, and a good camera NOT_CONNECTED (until
    2026-12-06). Its own poses of the board disagree with the other cameras' in every frame
    they share (10-57 degrees from the pairs' averages, the good pairs' within 0.3): it is left
    out before the solve, POOR_FIT, and says why."""
    rig = mc.synthetic.board_rig(jax.random.key(15), n_cameras=5, n_frames=100, noise=0.3)
    pixels, mask = np.array(rig.pixels), np.array(rig.mask)
    centres, rotations = _in_reference_frame(rig.cameras)
    mirrored = pixels.copy()
    mirrored[2, ..., 0] = 1279.0 - mirrored[2, ..., 0]
    flipped = np.arange(108).reshape(9, 12)[:, ::-1].ravel()
    ids = pixels.copy()
    ids[2], mask_ids = pixels[2][:, flipped], mask.copy()
    mask_ids[2] = mask[2][:, flipped]
    cases = (
        (mirrored, mask, None),
        (ids, mask_ids, mc.Huber(2.0)),
        (mirrored, mask, mc.Cauchy(2.0)),
    )
    for pixels_, mask_, loss in cases:
        result = mc.calibrate_rig(rig.target, pixels_, mask_, loss=loss, verbose=True)
        # (calibrated against the rest of the rig, it fits mirrored: no second solve for it)
        said = capsys.readouterr().err
        assert "camera 2: its own poses disagree" in said and "against the rest" not in said
        status = np.asarray(result.status)
        assert status[2] == mc.Status.POOR_FIT, (loss, status)
        assert "disagree with the other cameras'" in result.messages()[2]
        assert (np.delete(status, 2) == mc.Status.OK).all(), (loss, status)
        # the table shows the frames it posed alone (it showed 0 frames, 0 points)
        row = next(r.split() for r in str(result).splitlines() if r.startswith("2 "))
        assert row[:3] == ["2", str(int(mask_[2].any(-1).sum())), "-"], row
        good = np.arange(5) != 2
        off = np.linalg.norm(np.asarray(result.cameras.center)[good] - centres[good], axis=1)
        assert off.max() < 0.005, off  # metres; a baseline of ~2.5 m


def test_a_mirrored_camera_is_found_whichever_the_reference():
    """The same trial, other rigs (keys 490-492, camera k mirrored, camera k + 1 the reference):
    before the start left it out, with Huber(2.0) it was OK 15 m off (key 491), without a loss
    two good cameras were POOR_FIT (491) or 0.3-0.6 m off (492), with Cauchy(2.0) it was OK 2.3 m
    off (490). Now only it is POOR_FIT (9 of 9 rigs and losses)."""
    for k, loss in ((1, mc.Huber(2.0)), (2, None)):
        rig = mc.synthetic.board_rig(jax.random.key(490 + k), n_cameras=5, n_frames=100, noise=0.3)
        pixels = np.array(rig.pixels)
        pixels[k, ..., 0] = 1279.0 - pixels[k, ..., 0]
        result = mc.calibrate_rig(rig.target, pixels, rig.mask, loss=loss, reference=k + 1)
        expected = np.where(np.arange(5) == k, mc.Status.POOR_FIT, mc.Status.OK)
        np.testing.assert_array_equal(np.asarray(result.status), expected)
        R0, t0 = np.asarray(rig.cameras.R[k + 1]), np.asarray(rig.cameras.t[k + 1])
        truth = np.delete(np.asarray(rig.cameras.center) @ R0.T + t0, k, axis=0)
        found = np.delete(np.asarray(result.cameras.center), k, axis=0)
        assert np.linalg.norm(found - truth, axis=1).max() < 0.005  # metres


def test_a_solve_stopped_by_max_steps_says_so_for_every_camera():
    """A user's trial: `max_steps=2` left every camera OK and 'calibrated', 93-164 mm off, and
    the headline read "... else raise `max_steps` after 2 steps"."""
    rig = mc.synthetic.board_rig(jax.random.key(31), n_cameras=4, n_frames=60, noise=0.3)
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, max_steps=2)
    assert not bool(result.converged)
    assert all("stopped after 2 steps without converging" in m for m in result.messages())
    assert "stopped after 2 steps, not converged within `max_steps`" in str(result)
    done = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    assert done.messages() == ["calibrated"] * 4
    assert f"successful after {int(done.iterations)} steps;" in str(done)


def test_a_starting_camera_without_values_starts_from_its_own_frames():
    """A user's trial: re-run from an earlier rig in which camera 2 had failed (NaN), its
    detections since mended: camera 2 was TOO_FEW_POINTS ("no frame shows it enough of the
    target") though it saw the board in 28 frames. It starts from its own frames now, as
    without `cameras=`; held intrinsics still need values."""
    rig = mc.synthetic.board_rig(jax.random.key(4), n_cameras=4, n_frames=60, noise=0.3)
    truth = jax.tree_util.tree_map(np.asarray, rig.cameras)
    start = eqx.tree_at(lambda c: c.alpha_u, truth, truth.alpha_u.copy())
    start.alpha_u[2] = np.nan
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=start)
    assert bool(result.ok.all()), result.messages()
    focal = float(result.cameras.alpha_u[2])
    assert abs(focal / float(truth.alpha_u[2]) - 1) < 0.005, focal


def test_a_camera_whose_observations_a_robust_loss_mostly_sets_aside_is_pointed_out():
    """A user's trial: camera 1's video mirrored, `Huber(2.0)`: every camera OK and
    "calibrated", camera 1 at 10 px RMS with 935 of its 2,315 observations set aside, 77 m
    off, the good cameras pulled 22-49 mm. (A mirrored camera is now left out before the solve:
    `test_a_mirrored_camera_is_found_whichever_the_reference`.) A camera of which the loss sets
    aside more than a fifth of its observations, here 30 % moved by 40 px, says so; the others
    do not."""
    rig = mc.synthetic.board_rig(jax.random.key(491), n_cameras=5, n_frames=100, noise=0.3)
    pixels, mask = np.array(rig.pixels), np.asarray(rig.mask)
    rng = np.random.default_rng(0)
    seen = np.argwhere(mask[1])
    wild = seen[rng.choice(len(seen), int(0.3 * len(seen)), replace=False)]
    angle = rng.uniform(0, 2 * np.pi, len(wild))
    pixels[1, wild[:, 0], wild[:, 1]] += 40 * np.c_[np.cos(angle), np.sin(angle)]
    result = mc.calibrate_rig(rig.target, pixels, mask, loss=mc.Huber(2.0), reference=2)
    messages = result.messages()
    assert bool(result.ok.all()), messages
    assert "the robust loss set aside" in messages[1], messages
    assert not any("set aside" in m for i, m in enumerate(messages) if i != 1), messages


def test_one_wild_detection_in_one_camera_is_pointed_out_on_every_camera():
    """A user's trial: one corner of 6,783 moved by 100 px in the reference camera, least
    squares: cameras 1-3 OK and 'calibrated', 37-51 mm off (6 standard errors); only camera 0's
    message named the wild observation. The others now say that another camera's far
    observations may have pulled them; with a robust loss, none is pulled and none says so."""
    rig = mc.synthetic.board_rig(jax.random.key(8), n_cameras=4, n_frames=60, noise=0.3)
    pixels, mask = np.array(rig.pixels), np.asarray(rig.mask)
    frame, point = np.argwhere(mask[0])[0]
    pixels[0, frame, point, 0] += 100.0
    messages = mc.calibrate_rig(rig.target, pixels, mask).messages()
    assert "observations lie" in messages[0], messages
    assert all("camera 0 has observations far beyond the rest" in m for m in messages[1:])
    robust = mc.calibrate_rig(rig.target, pixels, mask, loss=mc.Huber(2.0)).messages()
    assert robust == ["calibrated"] * 4, robust


def test_a_failed_reference_names_the_worst_pairs_and_the_robust_loss():
    """A stereo pair, the board turned by 180 degrees in one of camera 1's frames: the error
    blamed the reference camera 0 ("choose another reference"), naming neither the frame nor
    a robust loss, which calibrates the pair."""
    rig = _rig("board", noise=0.3)  # cameras 0 and 1, neighbours in the ring, 45 degrees apart
    target, pixels, mask = (np.asarray(a)[:2] if a is not rig.target else np.asarray(a)
                            for a in (rig.target, rig.pixels, rig.mask))  # fmt: skip
    both = np.flatnonzero(mask[1].all(-1) & mask[0].any(-1))[0]  # camera 1 sees it whole
    pixels = pixels.copy()
    pixels[1, both] = pixels[1, both, ::-1]
    try:
        mc.calibrate_rig(target, pixels, mask)
    except ValueError as error:
        assert f"in frame {both} (RMS" in str(error) and "loss=mc.Huber(2.0)" in str(error)
    else:  # (the joint solve may absorb one turned frame; then the loss has nothing to add)
        pytest.skip("the turned frame did not fail the reference camera")
    assert bool(mc.calibrate_rig(target, pixels, mask, loss=mc.Huber(2.0)).ok.all())


@pytest.mark.parametrize("key, loss", [(0, mc.Huber(1.0)), (2, mc.Cauchy(1.0))])
def test_a_robust_loss_keeps_the_pairs_whose_own_closed_form_failed(key, loss):
    """A 3-D target, 1 % of the detections moved by 50 px: a pair with one wrong detection fails
    its own DLT's fit check, and a third of the pairs (110-125 of ~315) were left out of the
    joint solve so (until 2026-12-05). The loss takes them now, wherever other cameras posed the
    frame: every pair left out is in a frame nobody posed. The cameras come out within 1.3 times
    the clean rig's errors (position, rotation, intrinsics; before: 2.9, 1.8 and 1.5 times), or
    within issue 40's figures, and within 3 of their standard errors. (Key 2 with `Cauchy`:
    raised, see `test_a_robust_loss_converges_as_least_squares_does`.)"""
    rig = _rig("object", noise=0.3, key=key)
    target, pixels, mask = (np.asarray(a) for a in (rig.target, rig.pixels, rig.mask))
    result = mc.calibrate_rig(target, _wild(pixels, mask, seed=key), mask, loss=loss)
    assert bool(result.ok.all()) and bool(result.converged)
    used = np.asarray(result.used).any(-1)
    posed = np.isfinite(np.asarray(result.target_poses.t)).all(-1)
    observed = mask.any(-1) & ~np.asarray(result.skipped)
    assert not (observed & posed[None] & ~used).any()
    assert (observed & ~used).sum() < 0.1 * observed.sum()
    clean = mc.calibrate_rig(target, np.asarray(rig.pixels), mask)
    errors, clean_errors = _errors(rig, result), _errors(rig, clean)
    bounds = (1e-3, 0.05, 2e-3)  # 0.1 % of the baseline, 0.05 degrees, 0.2 %
    assert all(e < max(1.3 * c, b) for e, c, b in zip(errors, clean_errors, bounds)), errors
    assert errors[3] < 3.0, errors


def test_gradient_of_a_camera_position_equals_central_differences():
    rig = _rig(noise=0.3, n_cameras=4, n_frames=40, key=3)
    mask = np.asarray(rig.mask)

    def x_of_camera_2(pixels):
        return mc.calibrate_rig(rig.target, pixels, mask).cameras.center[2, 0]

    pixels = jnp.asarray(rig.pixels)
    gradient = jax.grad(x_of_camera_2)(pixels)
    v = np.random.default_rng(1).normal(size=pixels.shape) * mask[..., None]
    h = 1e-2  # the solves converge to 1e-5 standard errors: a smaller step measures that
    numeric = (x_of_camera_2(pixels + h * v) - x_of_camera_2(pixels - h * v)) / (2 * h)
    analytic = float(jnp.sum(gradient * v))
    assert abs(analytic - float(numeric)) <= 1e-4 * abs(float(numeric))


def test_gradient_through_the_cameras_it_holds_equals_central_differences():
    """With `fix="intrinsics"` the given focal lengths pass through to the answer (derivative
    one) and move the other cameras' poses (implicit derivatives). Both were zero: `_start`,
    which copies them, stops every derivative."""
    rig = _rig(noise=0.3, n_cameras=4, n_frames=20, key=0)
    given = mc.calibrate_rig(rig.target, rig.pixels, rig.mask).cameras

    def solve(alpha_u):
        cameras = eqx.tree_at(lambda c: c.alpha_u, given, alpha_u)
        return mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=cameras,
                                fix="intrinsics").cameras  # fmt: skip

    a = given.alpha_u
    np.testing.assert_array_equal(jax.grad(lambda a: solve(a).alpha_u.sum())(a), np.ones(4))
    gradient = jax.grad(lambda a: solve(a).center[1, 0])(a)
    h = 1e-2  # px of a ~1000 px focal length
    numeric = [(solve(a.at[i].add(h)).center[1, 0] - solve(a.at[i].add(-h)).center[1, 0]) / (2 * h)
               for i in range(4)]  # fmt: skip
    assert np.abs(np.asarray(gradient)).max() > 1e-5  # (not zero)
    np.testing.assert_allclose(gradient, numeric, rtol=1e-5, atol=1e-9)


def test_fix_aspect_ratio_holds_each_cameras_starting_ratio():
    """`fix="aspect_ratio"`: each camera's alpha_u / alpha_v stays its start's (the closed
    form's, or the given cameras'), the focal length estimated. Started from the true ratios
    (and focal lengths 2 % off), the rig lands within the noise of the truth, as the free one
    does; the standard error of alpha_u is the ratio times alpha_v's; the given ratio's
    derivative reaches the answer (central differences)."""
    rig = _rig(noise=0.3, n_cameras=4, n_frames=20, key=0)
    truth = np.asarray(rig.cameras.alpha_u / rig.cameras.alpha_v)
    free = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    held = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, fix="aspect_ratio")
    assert bool(held.ok.all()) and bool(held.converged)
    start = np.asarray(held.initial.alpha_u / held.initial.alpha_v)
    np.testing.assert_allclose(held.cameras.alpha_u / held.cameras.alpha_v, start, rtol=1e-12)
    assert np.abs(start / truth - 1).max() > 1e-3 and float(held.rms) > float(free.rms)
    # from the true ratios
    cams = free.cameras
    given = eqx.tree_at(lambda c: (c.alpha_u, c.alpha_v), cams,
                        (1.02 * truth * cams.alpha_v, 1.02 * cams.alpha_v))  # fmt: skip
    out = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=given, fix="aspect_ratio")
    assert bool(out.ok.all()) and bool(out.converged)
    np.testing.assert_allclose(out.cameras.alpha_u / out.cameras.alpha_v, truth, rtol=1e-12)
    names = out.parameter_names
    assert names[:2] == ("alpha_u", "alpha_v") and names == free.parameter_names
    std = np.asarray(out.parameter_std)
    error = np.asarray(out.cameras.alpha_v - rig.cameras.alpha_v)
    error_free = np.asarray(free.cameras.alpha_v - rig.cameras.alpha_v)
    print(f"alpha_v off by {error.round(2)} px, {(error / std[:, 1]).round(2)} standard errors "
          f"(free: {error_free.round(2)} px)")  # fmt: skip
    assert np.abs(error / std[:, 1]).max() < 4.0
    assert np.abs(error).max() < 1.5 * np.abs(error_free).max()
    assert abs(float(out.rms) / float(free.rms) - 1) < 1e-3  # (one constraint, true)
    np.testing.assert_allclose(std[:, 0], truth * std[:, 1], rtol=1e-9)
    assert np.all(std[:, 1] > 0)

    def solve(alpha_u):
        cameras = eqx.tree_at(lambda c: c.alpha_u, given, alpha_u)
        return mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=cameras,
                                fix="aspect_ratio").cameras  # fmt: skip

    a = given.alpha_u
    gradient = jax.grad(lambda a: solve(a).alpha_v[1])(a)
    h = 1e-2  # px of a ~1000 px focal length
    numeric = (solve(a.at[1].add(h)).alpha_v[1] - solve(a.at[1].add(-h)).alpha_v[1]) / (2 * h)
    assert abs(float(numeric)) > 1e-3  # (the ratio moves the focal length)
    np.testing.assert_allclose(gradient[1], numeric, rtol=1e-4)


def test_one_camera_with_one_frame_of_the_board_is_told_to_record_more_poses():
    """One photo of a board, one camera (a user's first try): the message spoke of array shapes
    and of choosing another reference camera, there being none."""
    rig = _rig(noise=0.3)
    f = int(np.argmax(np.asarray(rig.mask)[0].sum(-1)))
    pixels, mask = np.asarray(rig.pixels)[:1, f : f + 1], np.asarray(rig.mask)[:1, f : f + 1]
    with pytest.raises(ValueError, match="record the board in more poses") as error:
        mc.calibrate_rig(rig.target, pixels, mask)
    assert "Choose another" not in str(error.value)


def test_a_camera_with_one_frame_of_the_board_is_degenerate_in_a_rigs_words():
    """One view of a plane does not determine a camera's intrinsics; the message was the DLT's
    ("use a non-coplanar target, or calibrate_planar"), wrong advice in a rig."""
    rig = _rig(noise=0.3)
    mask = np.asarray(rig.mask).copy()
    frames = np.flatnonzero(mask[4].any(-1))
    mask[4, frames[1:]] = False
    result = mc.calibrate_rig(rig.target, rig.pixels, mask)
    assert int(result.status[4]) == mc.Status.DEGENERATE
    assert "frames of the target do not determine its intrinsics" in result.messages()[4]
    assert bool(np.delete(np.asarray(result.ok), 4).all())


def test_pairs_with_too_few_points_are_skipped_and_counted():
    rig = _rig(noise=0.3)
    mask = np.asarray(rig.mask).copy()
    c, f = np.argwhere(mask.any(-1))[0]
    mask[c, f, 3:] = False  # three points of the board left
    result = mc.calibrate_rig(rig.target, rig.pixels, mask)
    assert bool(result.skipped[c, f]) and int(result.n_skipped) == 1
    assert not np.asarray(result.used)[c, f].any() and np.asarray(result.observed)[c, f].any()


def test_a_pair_that_sees_one_row_and_one_more_corner_is_left_out():
    """A board seen along one row and one more corner determines no homography, whatever the
    noise makes of it (`_planar._general_position`): the pair is left out of the closed form,
    and joins the joint solve only where other pairs posed its frame. Its pose came out 105
    degrees off, and with the intrinsics given the joint solve ended there after 100 steps at
    0.83 px RMS (that frame at 16 px); now 6 steps, 0.42 px."""
    from mvcalib._planar import _homography_kernel

    rig = _rig(key=0, n_cameras=5, n_frames=41)
    mask, plane = np.asarray(rig.mask), jnp.asarray(rig.target)[:, :2]
    assert np.flatnonzero(mask[1, 7]).tolist() == [6, 7, 8, 9, 10, 11, 23]  # (the case)
    out = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, cameras=rig.cameras,
                           fix="intrinsics")  # fmt: skip
    assert int(out.iterations) < 20 and float(out.rms) < 0.45, (out.iterations, out.rms)
    assert np.isnan(out.frame_rms[7]) and not np.asarray(out.used)[1, 7].any()
    # the same in a frame that two other cameras saw: the pair's points join the joint solve
    c, f = next((c, f) for c, f in np.argwhere(mask.all(-1)) if mask[:, f].any(-1).sum() > 2)
    mask = mask.copy()
    mask[c, f, 12:] = False  # the board's first row of 12 corners,
    mask[c, f, 30] = True  # and one more
    assert (
        _homography_kernel(plane, jnp.asarray(rig.pixels[c, f]), mask[c, f], 1e-8)[1]
        == mc.Status.DEGENERATE
    )
    out = mc.calibrate_rig(rig.target, rig.pixels, mask, cameras=rig.cameras, fix="intrinsics")
    assert np.asarray(out.used)[c, f].sum() == 13 and float(out.rms) < 0.45
    for ids, status in [([6, 7, 8, 9, 10, 11, 23], mc.Status.DEGENERATE),
                        ([6, 7, 8, 9, 10, 11, 22, 23], mc.Status.OK)]:  # fmt: skip
        seen = np.isin(np.arange(len(plane)), ids)
        assert _homography_kernel(plane, jnp.asarray(rig.pixels[1, 7]), seen, 1e-8)[1] == status


def test_bad_input_raises_with_the_reason():
    rig = _rig(noise=0.3)
    with pytest.raises(ValueError, match="shape"):
        mc.calibrate_rig(rig.target, rig.pixels[:, :, :10], rig.mask)
    with pytest.raises(ValueError, match="shape"):
        mc.calibrate_rig(rig.target, rig.pixels, rig.mask[:, :5])
    pixels = np.asarray(rig.pixels).copy()
    c, f, n = np.argwhere(np.asarray(rig.mask))[0]
    pixels[c, f, n] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        mc.calibrate_rig(rig.target, pixels, rig.mask)
    with pytest.raises(ValueError, match="nothing is visible"):
        mc.calibrate_rig(rig.target, rig.pixels, np.zeros_like(rig.mask))
    with pytest.raises(ValueError, match="collinear"):
        line = np.c_[np.arange(108.0), np.zeros(108), np.zeros(108)]
        mc.calibrate_rig(line, rig.pixels, rig.mask)
    with pytest.raises(ValueError, match="cameras="):
        mc.calibrate_rig(rig.target, rig.pixels, rig.mask, fix="intrinsics")
    # the frame and camera axes swapped: the reference "camera" has a frame or two of the board,
    # said as such (the DLT's words were "use a non-coplanar target")
    board = mc.synthetic.board_rig(jax.random.key(0), n_cameras=4, n_frames=20, noise=0.3)
    swapped = np.swapaxes(np.asarray(board.pixels), 0, 1), np.swapaxes(np.asarray(board.mask), 0, 1)
    with pytest.raises(ValueError, match=r"of the board do(es)? not determine it: record the "
                       r".*check that `pixels` is \(C, F, N, 2\), cameras first\)"):  # fmt: skip
        mc.calibrate_rig(board.target, *swapped)


# ---------------------------------------------------------------------------- real data
@functools.cache
def _caliscope():
    root = data_dir("caliscope_4cam")
    observations = mc.io.load_caliscope(root / "xy.csv")
    cameras, _ = mc.io.load_caliscope_cameras(root / "camera_array.toml")
    return observations, cameras


def test_caliscope_rig_reproduces_its_own_reprojection_error():
    """SOURCE.md: caliscope's cameras held, each frame's board pose fitted: 0.94 px RMS."""
    o, cameras = _caliscope()
    fix = ("intrinsics", "distortion", "pose")
    result = mc.calibrate_rig(o.target, o.pixels, o.mask, cameras=cameras, fix=fix)
    assert int(result.observed.sum()) == 1725
    assert abs(float(result.rms_observed) - 0.9436) < 5e-4


# (intrinsics free: k1 k2 p1 p2 estimated, caliscope's k3 held, said so to keep it quiet)
@pytest.mark.parametrize("fix", [("intrinsics", "distortion"), ("k3",)])
def test_caliscope_recording_calibrated_below_caliscopes_own_error(fix):
    o, cameras = _caliscope()
    result = mc.calibrate_rig(o.target, o.pixels, o.mask, cameras=cameras, fix=fix, reference=1)
    assert int(result.observed.sum()) == 1725 and bool(result.ok.all())
    assert float(result.rms_observed) < 0.94
    # the baselines stay within 2 cm of caliscope's
    ours = np.linalg.norm(np.asarray(result.cameras.center), axis=1)
    theirs = np.asarray(cameras.center) - np.asarray(cameras.center)[1]
    assert np.abs(ours - np.linalg.norm(theirs, axis=1)).max() < 0.02


@pytest.mark.parametrize("reference", [0, 1, 2, 3])
def test_caliscope_recording_calibrated_from_its_detections_alone(reference):
    # No starting rig: each camera's intrinsics from its own frames, then the joint solve, whose
    # principal points and poses trade along a curved valley. With the damping divided by 100 per
    # good step it stopped at the default 100 steps unconverged from every reference camera; with
    # Nielsen's update (float64) 58-88 steps to RMS 0.8796 px.
    o, _ = _caliscope()
    result = mc.calibrate_rig(o.target, o.pixels, o.mask, reference=reference)
    assert bool(result.ok.all()) and bool(result.converged), int(result.iterations)
    assert float(result.rms_observed) < 0.94
    # A user's trial: camera 2's board never beyond 169 px of its principal point, its k1 0.62
    # and k2 -6.3 fold back ~250 px from it, in a 1280 x 720 image, with no word; camera 3's
    # ~550 px (caliscope's own intrinsics fold nowhere in the image: no note, below). From
    # camera 1 the solve ends in another minimum (RMS 0.8752 against 0.8799 px), camera 2's k2
    # -0.2 there: no fold.
    folds = ["lens distortion folds back" in m for m in result.messages()]
    k2 = float(result.cameras.dist[2, 1])
    assert folds == [False, False, k2 < -1, True], (k2, result.messages())


def test_held_intrinsics_of_another_resolution_are_pointed_out_on_every_camera():
    """A user's trial: caliscope's recording (1280 x 720) with every camera's intrinsics from a
    1920 x 1080 calibration (1.5 times) held. Two cameras came out POOR_FIT, and two OK at 2.6
    and 2.9 px, one 0.6 m from where the right intrinsics put it against a standard error of 11
    mm, with nothing said: the rig's median, the other note's yardstick, was as wrong. Their
    frames fit 3.3 and 5.8 times worse in the rig than each alone; with caliscope's own
    intrinsics 1.0-2.5 times (its webcams' frames are not quite simultaneous), and no note."""
    o, cameras = _caliscope()
    fix = ("intrinsics", "distortion")
    pixel = lambda x: (x + 0.5) * 1.5 - 0.5  # noqa: E731  (pixel centres at integers)
    big = eqx.tree_at(
        lambda c: (c.alpha_u, c.alpha_v, c.u0, c.v0),
        cameras,
        (cameras.alpha_u * 1.5, cameras.alpha_v * 1.5, pixel(cameras.u0), pixel(cameras.v0)),
    )
    # Their own fits sit at their limit (5 % of their pixels' spread, to a percent): a camera
    # comes out POOR_FIT, saying that its intrinsics were held, or calibrated with the note; a
    # reference that is POOR_FIT raises, saying so too. Never OK without a word.
    noted = 0
    for reference in range(4):
        try:
            result = mc.calibrate_rig(o.target, o.pixels, o.mask, cameras=big, fix=fix,
                                      reference=reference)  # fmt: skip
        except ValueError as error:
            assert f"reference camera {reference} cannot be calibrated" in str(error), error
            assert "its intrinsics were held (`fix`)" in str(error), error
            continue
        for c, message in enumerate(result.messages()):
            poor = int(result.status[c]) == mc.Status.POOR_FIT
            assert "its intrinsics were held (`fix`)" in message or (not poor and c == reference)
            noted += not poor
    assert noted >= 1
    right = mc.calibrate_rig(o.target, o.pixels, o.mask, cameras=cameras, fix=fix)
    assert not any("times worse in the rig" in m for m in right.messages()), right.messages()


def test_a_lens_whose_distortion_folds_inside_its_image_is_pointed_out():
    """The note's counterpart: caliscope's own cameras, calibrated from dedicated videos, fold
    nowhere in their images, and held so they get no note; the fold radius is that of the
    radial slope's first root (k1 -0.25, k2 -0.05: slope 1 - 0.75 r^2 - 0.25 r^4 = 0 at r = 1)."""
    from mvcalib._rig import _fold_radius

    o, cameras = _caliscope()
    fix = ("intrinsics", "distortion")
    result = mc.calibrate_rig(o.target, o.pixels, o.mask, cameras=cameras, fix=fix, reference=1)
    assert not any("folds back" in m for m in result.messages()), result.messages()
    assert _fold_radius([-0.25, -0.05, 0, 0, 0]) == pytest.approx(1.0, rel=1e-12)
    assert _fold_radius([-0.1, 0.01, 0, 0, 0]) == np.inf  # (slope 1 - 0.3 s + 0.05 s^2 > 0)


def test_reference_target_puts_the_world_on_the_board():
    rig = _rig(noise=0.0)
    result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask, reference="target", origin_frame=5)
    T = mc.RigidTransform(rig.poses.R[5], rig.poses.t[5])  # board in frame 5 -> true world
    centres = np.asarray(T.inverse().apply(rig.cameras.center))
    assert np.abs(np.asarray(result.cameras.center) - centres).max() < 1e-8
    assert np.abs(np.asarray(result.target_poses.t[5])).max() < 1e-8
    # the standard errors stay relative to the solve's reference: the camera of the most frames
    gauge = int(np.argmax(np.asarray(rig.mask).any(-1).sum(1)))
    assert np.all(np.asarray(result.position_std)[gauge] == 0)
    assert f"centre std: in the target's units, relative to camera {gauge}'s centre" in str(result)


def test_a_camera_whose_fit_fails_is_flagged_poor_fit_and_left_out(capsys):
    rig = _rig(noise=0.3)
    pixels = np.asarray(rig.pixels).copy()
    pixels[2] += np.random.default_rng(0).normal(scale=60.0, size=pixels[2].shape)  # garbage
    result = mc.calibrate_rig(rig.target, pixels, rig.mask, verbose=True)
    assert "camera 2: poor fit" in capsys.readouterr().err
    assert int(result.status[2]) == mc.Status.POOR_FIT
    assert np.isnan(np.asarray(result.cameras.alpha_u[2]))
    assert float(result.camera_rms[2]) > 30.0  # its RMS from the solve that flagged it
    others = np.delete(np.arange(8), 2)
    assert bool(np.asarray(result.ok)[others].all())
    # the others solved again without it (in the solve it took part in they ended at 1.4-3.5 px
    # RMS against 0.3 px of noise): as calibrated without camera 2
    assert float(np.asarray(result.camera_rms)[others].max()) < 0.46
    without = mc.calibrate_rig(rig.target, pixels[others], np.asarray(rig.mask)[others])
    a, b = np.asarray(result.cameras.center)[others], np.asarray(without.cameras.center)
    assert np.abs(a - b).max() < 1e-8
