"""Stereo pairs: rectification and epipolar matrices against OpenCV and against geometry."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mvcalib as mc

SIZE = (1280, 720)


def _pair(seed: int, vertical: bool = False, distortion: bool = True):
    """Two cameras ~12 cm apart (side by side, or one above the other) looking at a scene ~2 m
    ahead, each turned a little, with their own intrinsics and lens distortion: the cameras,
    and each as OpenCV's `(R, t, K, dist)`."""
    rng = np.random.default_rng(seed)
    baseline = np.array([0.12, 0.01, 0.005])[[1, 0, 2] if vertical else [0, 1, 2]]
    centres = [rng.normal(size=3) * 0.01]
    centres.append(centres[0] + baseline + rng.normal(size=3) * 0.005)
    look = np.array([0.05, 0.0, 2.0]) + rng.normal(size=3) * 0.1
    lenses = [[-0.12, 0.05, 0.001, -0.0008, 0.0], [-0.09, 0.03, -0.0005, 0.0004, 0.0]]
    out = []
    for centre, dist in zip(centres, lenses):
        z = look + rng.normal(size=3) * 0.05 - centre
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        fx, fy = 820 + rng.normal() * 10, 820 + rng.normal() * 10
        K = np.array([[fx, 0, 640 + rng.normal() * 5], [0, fy, 360 + rng.normal() * 5], [0, 0, 1]])
        out.append((R, -R @ centre, K, np.array(dist) if distortion else np.zeros(5)))
    cameras = mc.Camera.stack([mc.Camera.from_matrices(K, R, t, dist=d) for R, t, K, d in out])
    return cameras, out


def _opencv(opencv, alpha, zero_disparity):
    (R0, t0, K0, d0), (R1, t1, K1, d1) = opencv
    R = R1 @ R0.T
    T = (t1 - R @ t0).reshape(3, 1)
    flags = cv2.CALIB_ZERO_DISPARITY if zero_disparity else 0
    a = -1 if alpha is None else alpha
    return cv2.stereoRectify(K0, d0, K1, d1, SIZE, R, T, flags=flags, alpha=a)


@pytest.mark.parametrize("vertical", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stereo_rectify_is_opencvs(seed, vertical):
    """R1 R2 P1 P2 Q and the valid regions of `cv2.stereoRectify`, for every `alpha` and both
    principal-point rules: rotations to 1e-12, the rest to OpenCV's float32 corners (its
    undistortion stops after 5 iterations; mvcalib's converges): 1e-5 px, regions to a pixel."""
    cameras, opencv = _pair(seed, vertical)
    for alpha in (None, 0.0, 0.4, 1.0):
        for zero_disparity in (True, False):
            R1, R2, P1, P2, Q, roi1, roi2 = _opencv(opencv, alpha, zero_disparity)
            rect = mc.stereo_rectify(cameras, SIZE, alpha=alpha, zero_disparity=zero_disparity)
            assert bool(rect.vertical) == vertical
            assert np.abs(np.asarray(rect.R) - np.stack([R1, R2])).max() < 1e-12
            P = np.stack([P1, P2])
            assert np.abs(np.asarray(rect.P) - P).max() < 1e-5 * np.abs(P).max()
            assert np.abs(np.asarray(rect.P)[:, :2, 2] - P[:, :2, 2]).max() < 1e-4  # px
            assert np.abs(np.asarray(rect.Q) - Q).max() < 1e-5 * np.abs(Q).max()
            assert np.abs(np.asarray(rect.roi) - np.array([roi1, roi2])).max() <= 1


@pytest.mark.parametrize("vertical", [False, True])
def _fisheye_pair(seed: int):
    """Two fisheye cameras (about 100 degrees across a 1280 x 720 image) side by side: the
    cameras and OpenCV's `K`, `D` of each and `R`, `T` between them."""
    rng = np.random.default_rng(seed)
    K = [np.array([[500 + rng.normal() * 20, 0, 640 + rng.normal() * 5],
                   [0, 500 + rng.normal() * 20, 360 + rng.normal() * 5], [0, 0, 1]])
         for _ in range(2)]  # fmt: skip
    D = [np.array([0.05, -0.01, 0.002, -0.0005]) + rng.normal(size=4) * 0.005 for _ in range(2)]
    R0 = cv2.Rodrigues(rng.normal(size=3) * 0.1)[0]
    R = cv2.Rodrigues(rng.normal(size=3) * 0.05)[0]
    t0 = rng.normal(size=3) * 0.1
    T = np.array([-0.12, 0.01, 0.005]) + rng.normal(size=3) * 0.005
    poses = [(R0, t0), (R @ R0, R @ t0 + T)]
    cameras = mc.Camera.stack(
        [mc.Camera.from_matrices(k, r, t, dist=d, lens="fisheye") for k, d, (r, t) in
         zip(K, D, poses)]
    )  # fmt: skip
    return cameras, K, D, R, T


@pytest.mark.parametrize("seed", [0, 1])
def test_fisheye_pairs_are_rectified_as_cv2_fisheye_does(seed):
    """`cv2.fisheye.stereoRectify`'s R1 R2 P1 P2 Q for every `balance` (`alpha`), `fov_scale`
    and principal-point rule (to 1e-10 px: no float32 inside), and `maps` its
    `initUndistortRectifyMap`; a point's rectified pixels share their row."""
    cameras, K, D, R, T = _fisheye_pair(seed)
    for balance in (None, 0.0, 0.4, 1.0):
        for fov_scale in (1.0, 1.4):
            for zero_disparity in (True, False):
                R1, R2, P1, P2, Q = cv2.fisheye.stereoRectify(
                    K[0], D[0], K[1], D[1], SIZE, R, T.reshape(3, 1),
                    flags=cv2.CALIB_ZERO_DISPARITY if zero_disparity else 0,
                    balance=0.0 if balance is None else balance, fov_scale=fov_scale,
                )  # fmt: skip
                rect = mc.stereo_rectify(
                    cameras, SIZE, alpha=balance, zero_disparity=zero_disparity,
                    fov_scale=fov_scale,
                )  # fmt: skip
                assert np.abs(np.asarray(rect.R) - np.stack([R1, R2])).max() < 1e-12
                assert np.abs(np.asarray(rect.P) - np.stack([P1, P2])).max() < 1e-10
                assert np.abs(np.asarray(rect.Q) - Q).max() < 1e-9
    rect = mc.stereo_rectify(cameras, SIZE)
    map_x, map_y = rect.maps()
    for i in range(2):
        R_i, P_i = np.asarray(rect.R[i]), np.asarray(rect.P[i])
        cv_x, cv_y = cv2.fisheye.initUndistortRectifyMap(K[i], D[i], R_i, P_i, SIZE, cv2.CV_32FC1)
        assert np.abs(map_x[i] - cv_x).max() < 1e-3 and np.abs(map_y[i] - cv_y).max() < 1e-3
    world = np.random.default_rng(0).uniform([-0.5, -0.3, 1.5], [0.5, 0.3, 2.5], (50, 3))
    rows = np.asarray(rect.cameras.project(world))[..., 1]
    assert np.abs(rows[0] - rows[1]).max() < 1e-9
    assert (np.asarray(rect.roi)[:, 2:] > 0).all()


@pytest.mark.parametrize("vertical", [False, True])
def test_rectified_cameras_share_rows_and_Q_gives_depth(vertical):
    """A world point's rectified pixels share their row (column, one above the other); `Q` of
    its pixel and disparity is the point in rectified camera 0's coordinates; the rectified
    pixels triangulate to the point; the rectified cameras' projections are `P`'s."""
    cameras, _ = _pair(3, vertical)
    rect = mc.stereo_rectify(cameras, SIZE, alpha=0.0)
    world = np.random.default_rng(0).uniform([-0.5, -0.3, 1.5], [0.5, 0.3, 2.5], (50, 3))
    pixels = np.asarray(rect.cameras.project(world))
    along, across = (1, 0) if vertical else (0, 1)
    assert np.abs(pixels[0, :, across] - pixels[1, :, across]).max() < 1e-9
    disparity = pixels[0, :, along] - pixels[1, :, along]
    assert (disparity > 0).all()  # the usual sign: camera 1 right of (below) camera 0
    uvd1 = np.stack([pixels[0, :, 0], pixels[0, :, 1], disparity, np.ones(50)], -1)
    X = uvd1 @ np.asarray(rect.Q).T
    truth = np.asarray(rect.cameras.to_camera(world))[0]
    assert np.abs(X[:, :3] / X[:, 3:] - truth).max() < 1e-9
    points = np.asarray(mc.triangulate(rect.cameras, pixels).points)
    assert np.abs(points - world).max() < 1e-9
    # P, in rectified camera 0's coordinates
    homogeneous = np.concatenate([truth, np.ones((50, 1))], -1)
    seen = np.einsum("cij,nj->cni", np.asarray(rect.P), homogeneous)
    assert np.abs(seen[..., :2] / seen[..., 2:] - pixels).max() < 1e-9


def test_maps_are_opencvs_and_carry_a_point_home():
    """`maps` equals `cv2.initUndistortRectifyMap` from the same R and P (float32), and looked
    up (bilinearly) at a world point's rectified pixel gives its pixel in the original, distorted
    image, to 1e-3 px."""
    cameras, opencv = _pair(4)
    rect = mc.stereo_rectify(cameras, SIZE, alpha=0.0)
    map_x, map_y = rect.maps()
    assert map_x.shape == (2, SIZE[1], SIZE[0]) and map_x.dtype == np.float32
    for i, (_, _, K, dist) in enumerate(opencv):
        R, P = np.asarray(rect.R[i]), np.asarray(rect.P[i])
        cv_x, cv_y = cv2.initUndistortRectifyMap(K, dist, R, P, SIZE, cv2.CV_32FC1)
        assert np.abs(map_x[i] - cv_x).max() < 1e-3 and np.abs(map_y[i] - cv_y).max() < 1e-3
    world = np.random.default_rng(1).uniform([-0.4, -0.2, 1.8], [0.4, 0.2, 2.2], (40, 3))
    rectified = np.asarray(rect.cameras.project(world))
    original = np.asarray(cameras.project(world))
    for i in range(2):
        home = [_bilinear(m[i].astype(float), rectified[i]) for m in (map_x, map_y)]
        assert np.abs(np.stack(home, -1) - original[i]).max() < 1e-3


def _bilinear(image, points):
    """`image` interpolated bilinearly at `points` `(N, 2)` as (x, y)."""
    x0, y0 = np.floor(points).astype(int).T
    fx, fy = (points - np.floor(points)).T
    return (
        image[y0, x0] * (1 - fx) * (1 - fy)
        + image[y0, x0 + 1] * fx * (1 - fy)
        + image[y0 + 1, x0] * (1 - fx) * fy
        + image[y0 + 1, x0 + 1] * fx * fy
    )


def test_essential_and_fundamental_matrices_are_stereo_calibrates():
    """E and F as `cv2.stereoCalibrate` returns them for the same cameras (intrinsics fixed,
    exact corners of a board in 8 poses), and the epipolar constraint on undistorted pixels."""
    cameras, opencv = _pair(5, distortion=False)
    (R0, t0, K0, d0), (R1, t1, K1, d1) = opencv
    board = np.stack(np.meshgrid(np.arange(9), np.arange(6)), -1).reshape(-1, 2) * 0.03
    board = np.concatenate([board - board.mean(0), np.zeros((54, 1))], -1)
    rng = np.random.default_rng(0)
    objects, left, right = [], [], []
    for _ in range(8):
        pose = mc.rodrigues(jnp.asarray(rng.normal(size=3) * 0.3))
        world = board @ np.asarray(pose).T + [0.05, 0.0, 2.0] + rng.normal(size=3) * 0.1
        pixels = np.asarray(cameras.project(world))
        objects.append(board.astype(np.float32))
        left.append(pixels[0].astype(np.float32))
        right.append(pixels[1].astype(np.float32))
    flags = cv2.CALIB_FIX_INTRINSIC
    out = cv2.stereoCalibrate(objects, left, right, K0, d0, K1, d1, SIZE, flags=flags)
    E_cv, F_cv = out[7], out[8]
    E, F = np.asarray(mc.essential_matrix(cameras)), np.asarray(mc.fundamental_matrix(cameras))
    # (OpenCV's from float32 corners: its R, T to ~1e-6)
    assert np.abs(E - E_cv).max() < 1e-4 * np.abs(E).max()
    assert np.abs(F - F_cv).max() < 1e-3 * np.abs(F).max() and F[2, 2] == pytest.approx(1.0)
    world = rng.uniform([-0.5, -0.3, 1.5], [0.5, 0.3, 2.5], (30, 3))
    p = np.concatenate([np.asarray(cameras.project(world)), np.ones((2, 30, 1))], -1)
    lines = p[0] @ F.T  # epipolar lines in camera 1
    distance = np.abs(np.sum(lines * p[1], -1)) / np.hypot(lines[:, 0], lines[:, 1])
    assert distance.max() < 1e-9


def test_stereo_rectify_is_differentiable_and_jits():
    """Inside `jax.jit`, the same answer; `jax.grad` of the rectified baseline term `P[1][0, 3]`
    (focal length times baseline) with respect to camera 1's translation equals central
    differences."""
    cameras, _ = _pair(6)
    eager = mc.stereo_rectify(cameras, SIZE)
    jitted = jax.jit(lambda c: mc.stereo_rectify(c, SIZE).Q)(cameras)
    assert np.abs(np.asarray(jitted) - np.asarray(eager.Q)).max() < 1e-12 * np.abs(eager.Q).max()

    def term(t1):
        moved = mc.Camera.from_matrices(cameras.K, cameras.R, cameras.t.at[1].set(t1), cameras.dist)
        return mc.stereo_rectify(moved, SIZE).P[1, 0, 3]

    t1 = cameras.t[1]
    gradient = np.asarray(jax.grad(term)(t1))
    h = 1e-6
    numeric = [(term(t1.at[i].add(h)) - term(t1.at[i].add(-h))) / (2 * h) for i in range(3)]
    assert np.abs(gradient - np.asarray(numeric)).max() < 1e-5 * np.abs(gradient).max()


def test_bad_input_is_refused_with_the_reason():
    cameras, _ = _pair(0)
    three = mc.Camera.stack([cameras[0], cameras[1], cameras[0]])
    with pytest.raises(ValueError, match="pair of cameras"):
        mc.stereo_rectify(three, SIZE)
    with pytest.raises(TypeError, match="pair of cameras"):
        mc.stereo_rectify(np.eye(3), SIZE)
    with pytest.raises(ValueError, match="image_size"):
        mc.stereo_rectify(cameras, (1280.5, 720))
    with pytest.raises(ValueError, match="image_size"):
        mc.stereo_rectify(cameras, 1280)
    with pytest.raises(ValueError, match="alpha"):
        mc.stereo_rectify(cameras, SIZE, alpha=1.5)
    fisheye = mc.Camera.stack(
        [
            mc.Camera(800.0, 800.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3), lens="fisheye"),
            mc.Camera(800.0, 800.0, 640.0, 360.0, jnp.eye(3), jnp.ones(3), lens="fisheye"),
        ]
    )
    with pytest.raises(ValueError, match="fisheye"):
        mc.fundamental_matrix(fisheye)
    with pytest.raises(ValueError, match="fov_scale"):
        mc.stereo_rectify(fisheye, SIZE, fov_scale=0.0)
    # a fisheye whose image edges lie beyond 90 degrees off axis (a 180-degree lens: f = 330 px
    # across 1280 px): no pinhole holds it; all NaN before, silently (a fisheye user's trial)
    wide = mc.Camera.stack(
        [
            mc.Camera(330.0, 330.0, 640.0, 360.0, jnp.eye(3), jnp.zeros(3), lens="fisheye"),
            mc.Camera(
                330.0, 330.0, 640.0, 360.0, jnp.eye(3), jnp.array([-0.1, 0, 0]), lens="fisheye"
            ),
        ]
    )
    with pytest.raises(ValueError, match="more than 90 degrees off the rectified axis"):
        mc.stereo_rectify(wide, SIZE)
    traced = jax.jit(lambda c: mc.stereo_rectify(c, SIZE).P)(wide)
    assert np.isnan(np.asarray(traced)).any()


@pytest.mark.parametrize("alpha", [0.0, 0.3, 1.0])
def test_undistorted_is_opencvs_new_camera_matrix(alpha):
    """`undistorted`: `cv2.getOptimalNewCameraMatrix` for a pinhole (to 1e-6 px with a mild
    lens: with a strong one OpenCV's 5-iteration undistortion of the image corners is itself
    0.06 px off its model, and mvcalib's is not), `estimateNewCameraMatrixForUndistortRectify`
    for a fisheye (to 1e-10 px); `undistortion_maps` is `initUndistortRectifyMap` from that K."""
    K = np.array([[800.0, 0, 645], [0, 805, 355], [0, 0, 1]])
    D = np.array([-0.02, 0.005, 0.0001, -0.00005, 0.0])
    camera = mc.Camera.from_matrices(K, np.eye(3), np.zeros(3), dist=D)
    new = mc.undistorted(camera, SIZE, alpha=alpha)
    expected, _ = cv2.getOptimalNewCameraMatrix(K, D, SIZE, alpha)
    assert new.lens == "pinhole" and not np.asarray(new.dist).any()
    assert np.abs(np.asarray(new.K) - expected).max() < 1e-6
    map_x, map_y = mc.undistortion_maps(camera, new, SIZE)
    cv_x, cv_y = cv2.initUndistortRectifyMap(K, D, None, np.asarray(new.K), SIZE, cv2.CV_32FC1)
    assert np.abs(map_x - cv_x).max() < 1e-3 and np.abs(map_y - cv_y).max() < 1e-3
    cameras, Ks, Ds, _, _ = _fisheye_pair(0)
    new = mc.undistorted(cameras, SIZE, alpha=alpha, fov_scale=1.2)  # a rig of two
    for i in range(2):
        expected = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
            Ks[i], Ds[i], SIZE, np.eye(3), balance=alpha, fov_scale=1.2
        )
        assert np.abs(np.asarray(new.K[i]) - expected).max() < 1e-10
    map_x, map_y = mc.undistortion_maps(cameras, new, SIZE)
    assert map_x.shape == (2, SIZE[1], SIZE[0])
    cv_x, cv_y = cv2.fisheye.initUndistortRectifyMap(
        Ks[1], Ds[1], np.eye(3), np.asarray(new.K[1]), SIZE, cv2.CV_32FC1
    )
    assert np.abs(map_x[1] - cv_x).max() < 1e-3 and np.abs(map_y[1] - cv_y).max() < 1e-3


def test_undistorted_with_alpha_0_shows_only_the_image():
    """A strong barrel lens: with `alpha=0` every pixel of the undistorted image comes from
    inside the original one (the map of its border within the image, to rounding), and a world
    point's undistorted pixel is where the new pinhole projects it."""
    K = np.array([[800.0, 0, 645], [0, 805, 355], [0, 0, 1]])
    D = np.array([-0.2, 0.05, 0.001, -0.0005, 0.0])
    camera = mc.Camera.from_matrices(K, np.eye(3), np.zeros(3), dist=D)
    new = mc.undistorted(camera, SIZE)
    map_x, map_y = mc.undistortion_maps(camera, new, SIZE)
    # (OpenCV's rule samples the border 9 x 9 times: between, it bulges by ~1e-3 px)
    border = np.concatenate([map_x[[0, -1]].ravel(), map_x[:, [0, -1]].ravel()])
    assert border.min() > -0.01 and border.max() < SIZE[0] - 1 + 0.01
    border = np.concatenate([map_y[[0, -1]].ravel(), map_y[:, [0, -1]].ravel()])
    assert border.min() > -0.01 and border.max() < SIZE[1] - 1 + 0.01
    world = np.random.default_rng(2).uniform([-0.3, -0.2, 1.0], [0.3, 0.2, 1.5], (20, 3))
    ideal = np.asarray(mc.undistort_points(camera, camera.project(world)))
    seen = np.asarray(new.project(world))
    scale = np.asarray(new.K)[[0, 1], [0, 1]] / K[[0, 1], [0, 1]]
    centre = np.asarray(new.K)[:2, 2]
    np.testing.assert_allclose(seen, (ideal - K[:2, 2]) * scale + centre, atol=1e-9)
