"""N-view triangulation against ground truth, OpenCV, and first-order error theory."""

import warnings

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_difference_check

import mvcalib as mc

TARGET = mc.targets.box_corner_grid(6)  # 108 points on three faces


def ring(n_cameras, seed=0, distortion=False):
    """Cameras all round the target's octant, looking at it from 25-65 degrees of elevation."""
    rig = mc.synthetic.random_rig(
        jax.random.key(seed), n_cameras, TARGET, max_angle=40.0, focal=(900.0, 1600.0)
    )
    cameras = rig.cameras
    if distortion:
        dist = jnp.broadcast_to(jnp.array([-0.2, 0.1, 1e-3, 1e-3, 0.0]), (n_cameras, 5))
        cameras = mc.Camera.from_matrices(cameras.K, cameras.R, cameras.t, dist)
    return cameras, jnp.asarray(TARGET.points)


@pytest.mark.parametrize("distortion", [False, True], ids=["pinhole", "distorted"])
def test_noise_free_points_come_back_exactly(distortion):
    cameras, world = ring(6, seed=1, distortion=distortion)
    pixels = cameras.project(world)
    out = mc.triangulate(cameras, pixels)
    np.testing.assert_allclose(out.points, world, rtol=0, atol=1e-9 * 200)  # 1e-9 of the target
    assert np.asarray(out.ok).all() and (np.asarray(out.views) == 6).all()
    assert float(out.rms.max()) < 1e-8
    # Every pair of views alone also gives the point.
    for a, b in [(0, 1), (2, 5)]:
        pair = mc.triangulate(cameras[jnp.array([a, b])], pixels[jnp.array([a, b])])
        np.testing.assert_allclose(pair.points, world, atol=1e-9 * 200)


def test_two_views_agree_with_opencv():
    cameras, world = ring(2, seed=2)
    P = np.asarray(cameras.projection_matrix())
    pixels = np.asarray(cameras.project(world))
    for noise in (0.0, 0.5):
        px = pixels + noise * np.random.default_rng(2).standard_normal(pixels.shape)
        X = cv2.triangulatePoints(P[0], P[1], px[0].T.copy(), px[1].T.copy())
        theirs = (X[:3] / X[3]).T
        ours = mc.triangulate(cameras, px)
        if noise == 0:
            np.testing.assert_allclose(ours.points, theirs, rtol=0, atol=1e-8)
            continue
        # With noise the two linear solutions differ by how the equations are weighted (OpenCV:
        # raw pixel rows; mvcalib: normalised rows weighted by focal length). Both are within
        # the noise of the truth, and ours reprojects no worse.
        err = lambda X: np.linalg.norm(X - np.asarray(world), axis=-1)  # noqa: E731
        assert np.median(err(np.asarray(ours.points))) < 1.1 * np.median(err(theirs))
        rms_theirs = np.sqrt(np.mean(np.sum((cameras.project(theirs) - px) ** 2, -1)))
        rms_ours = np.sqrt(np.mean(np.asarray(ours.rms) ** 2))
        assert rms_ours <= 1.001 * rms_theirs


def test_error_falls_as_views_are_added_like_one_over_root_n():
    cameras, world = ring(32, seed=3)
    pixels = cameras.project(world)
    noise = 0.5 * jax.random.normal(jax.random.key(3), (100,) + pixels.shape)  # 100 trials
    curve = {}
    for k in (2, 4, 8, 16, 32):
        # The first k views, the others hidden by the mask (no influence: the next test but one),
        # so that one compiled program serves every k; point sets: the trials.
        first_k = jnp.broadcast_to((jnp.arange(32) < k)[:, None], noise.shape[:-1])
        out = mc.triangulate(cameras, pixels + noise, first_k)
        curve[k] = float(jnp.sqrt(jnp.mean(jnp.sum((out.points - world) ** 2, -1))))
    print("\n3-D RMS error (mm) by number of views:", {k: round(v, 4) for k, v in curve.items()})
    ks = sorted(curve)
    assert all(curve[a] > curve[b] for a, b in zip(ks, ks[1:]))
    # From 4 to 32 views (8x) the error should fall by about sqrt(8) = 2.8 (random geometry
    # makes the first views count differently, hence the band).
    assert 2.0 < curve[4] / curve[32] < 4.0


def test_jacobian_gives_the_covariance_monte_carlo_confirms():
    cameras, world = ring(4, seed=4)
    pixels = cameras.project(world[:5])
    sigma = 0.3

    def points(px):
        return mc.triangulate(cameras, px).points

    J = jax.jacfwd(points)(pixels)  # (5, 3, C, 5, 2)
    J = J.reshape(5, 3, -1)
    predicted = sigma**2 * jnp.einsum("pik,pjk->pij", J, J)  # (5, 3, 3)
    noise = sigma * jax.random.normal(jax.random.key(4), (4000,) + pixels.shape)
    samples = mc.triangulate(cameras, pixels + noise).points  # (4000, 5, 3)
    d = samples - samples.mean(0)
    observed = jnp.einsum("spi,spj->pij", d, d) / (len(samples) - 1)
    ratio = jnp.trace(observed, axis1=-2, axis2=-1) / jnp.trace(predicted, axis1=-2, axis2=-1)
    print("\nMonte Carlo / first-order variance per point:", np.round(np.asarray(ratio), 3))
    assert np.all(np.abs(np.asarray(ratio) - 1) < 0.1)


def test_hidden_views_have_no_influence_even_nan():
    # 6 cameras, as in the first test: its compiled programs are reused
    cameras, world = ring(6, seed=5)
    pixels = np.array(cameras.project(world)) + 0.3 * np.random.default_rng(5).standard_normal(
        (6, len(world), 2)
    )
    mask = np.ones(pixels.shape[:2], bool)
    mask[2] = False
    poisoned = pixels.copy()
    poisoned[2] = np.nan
    with_mask = mc.triangulate(cameras, poisoned, mask)
    without = mc.triangulate(cameras[jnp.array([0, 1, 3, 4, 5])], pixels[[0, 1, 3, 4, 5]])
    np.testing.assert_allclose(with_mask.points, without.points, rtol=1e-12, atol=1e-10)
    # NaN pixels are hidden by default.
    np.testing.assert_allclose(mc.triangulate(cameras, poisoned).points, without.points, atol=1e-10)
    g = jax.grad(lambda px: mc.triangulate(cameras, px, mask).points.sum())(jnp.asarray(pixels))
    assert np.all(np.asarray(g)[2] == 0)
    # A camera that calibrate could not solve (NaN) sees nothing, even where its pixels are
    # finite: it made every point NaN (a zero weight times NaN).
    broken = jax.tree_util.tree_map(lambda x: x.at[2].set(jnp.nan), cameras)
    out = mc.triangulate(broken, pixels)
    np.testing.assert_allclose(out.points, without.points, rtol=1e-12, atol=1e-10)
    np.testing.assert_array_equal(out.views, without.views)


def test_diagnostics_flag_what_cannot_be_trusted():
    cameras, world = ring(3, seed=6)
    pixels = np.array(cameras.project(world))
    mask = np.ones(pixels.shape[:2], bool)
    mask[1:, 0] = False  # point 0 seen once
    out = mc.triangulate(cameras, pixels, mask)
    assert int(out.views[0]) == 1 and not bool(out.ok[0]) and np.isnan(out.points[0]).all()
    assert np.asarray(out.ok[1:]).all() and (np.asarray(out.angle[1:]) > 5).all()
    # Two nearly coincident cameras: a tiny ray angle, not ok with the default 1 degree.
    shifted = mc.Camera(
        cameras.alpha_u[0], cameras.alpha_v[0], cameras.u0[0], cameras.v0[0], cameras.R[0],
        cameras.t[0] + jnp.array([0.5, 0.0, 0.0]),
    )  # fmt: skip
    pair = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), cameras[0], shifted)
    narrow = mc.triangulate(pair, pair.project(world))
    assert (np.asarray(narrow.angle) < 1).all() and not np.asarray(narrow.ok).any()


def test_a_mirrored_world_is_behind_every_camera_and_said_so():
    """The Oxford house's cameras see a mirrored world (a user's trial: every point accurate,
    every point not ok, nothing saying why): `in_front` tells, and a warning."""
    cameras, world = ring(3, seed=6)
    pixels = np.array(cameras.project(world))
    mask = np.ones(pixels.shape[:2], bool)
    mask[1:, 0] = False  # point 0 seen once
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = mc.triangulate(cameras, pixels, mask)
    assert not out.in_front[0] and np.asarray(out.in_front[1:]).all()
    flip = np.diag([1.0, 1.0, -1.0])  # the world's z mirrored, so that the pixels stay
    mirrored = mc.Camera(cameras.alpha_u, cameras.alpha_v, cameras.u0, cameras.v0,
                         -cameras.R @ flip, -cameras.t)  # fmt: skip
    assert np.allclose(mirrored.project(world @ flip), pixels, atol=1e-9)  # (z = -X_c's)
    with pytest.warns(UserWarning, match="points lie behind the cameras") as caught:
        behind = mc.triangulate(mirrored, pixels, mask)
    assert len(caught) == 1 and caught[0].filename == __file__
    assert np.abs(np.asarray(behind.points[1:]) - (world @ flip)[1:]).max() < 1e-9
    assert not np.asarray(behind.in_front).any() and not np.asarray(behind.ok).any()


# The gradient at the optimum is checked to 1e-6, within a factor of a few of where rounding
# decides the solver's last step (1.2e-6 with XLA's older CPU emitters): run as users compile.
@pytest.mark.default_codegen
def test_refinement_minimises_reprojection_error_with_distortion():
    cameras, world = ring(4, seed=7, distortion=True)
    pixels = cameras.project(world)
    noisy = pixels + 0.5 * jax.random.normal(jax.random.key(7), pixels.shape)
    linear = mc.triangulate(cameras, noisy)
    refined = mc.triangulate(cameras, noisy, refine=True)
    assert np.all(np.asarray(refined.rms) <= np.asarray(linear.rms) + 1e-9)
    assert float(jnp.mean(refined.rms)) < 0.99 * float(jnp.mean(linear.rms))
    # At the optimum the reprojection error's gradient in the point vanishes.
    g = jax.vmap(
        jax.grad(lambda X, px: jnp.sum((cameras.project(X[None])[:, 0] - px) ** 2)),
        in_axes=(0, 1),
    )(refined.points, noisy)
    assert float(jnp.abs(g).max()) < 1e-6


def test_point_sets_batch_like_separate_calls_and_gradients_are_right():
    cameras, world = ring(3, seed=8)
    pixels = cameras.project(world[:10])
    sets = pixels + 0.2 * jax.random.normal(jax.random.key(8), (4,) + pixels.shape)
    batched = mc.triangulate(cameras, sets)
    assert batched.points.shape == (4, 10, 3) and batched.ok.shape == (4, 10)
    # the same to rounding at the points' scale (a coordinate near 0 differs by ~1e-13 mm, far
    # beyond rtol of itself: the batched program is compiled, and rounds, differently)
    scale = float(np.abs(world).max())
    for s in range(4):
        np.testing.assert_allclose(
            batched.points[s], mc.triangulate(cameras, sets[s]).points, rtol=1e-12,
            atol=1e-14 * scale,
        )  # fmt: skip
    central_difference_check(lambda px: mc.triangulate(cameras, px).points, sets[0], eps=1e-5)


def test_many_small_point_sets_are_triangulated_as_one_set():
    """1000 frames of 6 body parts from 12 cameras (DeepLabCut's layout) took 1.2-1.6 s warm
    against 0.02 s flat: each frame's 6 points were padded to a bucket of 352. Called from
    Python, the sets' points are one set now: the answer is the flat call's, bit for bit (and
    the user's `jax.jit`, which vmaps over the sets, agrees to rounding)."""
    cameras, world = ring(12, seed=10)
    world = np.random.default_rng(10).uniform(-50.0, 50.0, (6000, 3)) + np.asarray(world).mean(0)
    pixels = np.array(cameras.project(world))
    pixels[np.random.default_rng(11).random(pixels.shape[:2]) < 0.3] = np.nan
    sets = np.moveaxis(pixels.reshape(12, 1000, 6, 2), 1, 0)  # (frames, C, parts, 2)
    flat, batched = mc.triangulate(cameras, pixels), mc.triangulate(cameras, sets)
    assert batched.points.shape == (1000, 6, 3) and batched.views.shape == (1000, 6)
    for field in ("points", "views", "rms", "angle", "ok"):
        a, b = np.asarray(getattr(batched, field)), np.asarray(getattr(flat, field))
        np.testing.assert_array_equal(a.reshape(b.shape), b, err_msg=field)
    traced = jax.jit(lambda p: mc.triangulate(cameras, p))(sets)
    np.testing.assert_allclose(traced.points, batched.points, rtol=1e-12, atol=1e-10)


def test_reproject_predicts_every_view():
    cameras, world = ring(3, seed=9)
    pixels = cameras.project(world)
    out = mc.triangulate(cameras, pixels)
    np.testing.assert_allclose(mc.reproject(cameras, out), pixels, atol=1e-8)
    report = mc.reprojection_report(cameras, out.points, pixels)
    assert float(report.rms.max()) < 1e-8


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda c, p: mc.triangulate(c[0], p[0]), "rig"),
        (lambda c, p: mc.triangulate(c, p[:2]), "C = 3"),
        (lambda c, p: mc.triangulate(c, p, np.ones(p.shape[:2], int)), "boolean"),
        (lambda c, p: mc.triangulate(c, p.astype(np.complex64)), "real floating"),
        (lambda c, p: mc.triangulate(c[:1], p[:1]), "at least 2 cameras"),
    ],
    ids=["one camera", "wrong C", "int mask", "complex", "single view"],
)
def test_bad_input_raises_value_error(call, message):
    cameras, world = ring(3, seed=10)
    pixels = np.asarray(cameras.project(world))
    with pytest.raises(ValueError, match=message):
        call(cameras, pixels)


def test_points_match_a_per_point_numpy_svd_reference():
    # The same normalised, focal-weighted linear system as mvcalib, solved per point by
    # numpy's SVD of the 2C x 4 rows: the two must agree to rounding, noise or not.
    cameras, world = ring(8, seed=12)
    pixels = np.asarray(cameras.project(world))
    pixels = pixels + 0.5 * np.random.default_rng(12).standard_normal(pixels.shape)
    out = mc.triangulate(cameras, pixels)
    K_inv = np.linalg.inv(np.asarray(cameras.K))
    R, t = np.asarray(cameras.R), np.asarray(cameras.t)
    centres = -np.einsum("cji,cj->ci", R, t)
    middle = centres.mean(0)
    spread = np.sqrt(np.mean(np.sum((centres - middle) ** 2, -1)))
    focal = np.sqrt(np.asarray(cameras.alpha_u * cameras.alpha_v))
    weight = focal / focal.mean()
    P = weight[:, None, None] * np.concatenate([R, ((R @ middle + t) / spread)[..., None]], axis=-1)
    reference = []
    for n in range(len(world)):
        xn = np.einsum("cij,cj->ci", K_inv, np.concatenate([pixels[:, n], np.ones((8, 1))], -1))
        rows = np.concatenate([xn[:, :1] * P[:, 2] - P[:, 0], xn[:, 1:2] * P[:, 2] - P[:, 1]])
        v = np.linalg.svd(rows)[2][-1]
        reference.append(middle + spread * v[:3] / v[3])
    reference = np.array(reference)
    np.testing.assert_allclose(out.points, reference, rtol=1e-9, atol=1e-9 * 200)
    assert float(np.sqrt(np.mean(np.sum((reference - np.asarray(world)) ** 2, -1)))) > 1e-3


def test_the_null_vector_is_lapacks_smallest_eigenvector():
    """The point's 4 x 4 null vector, by inverse iteration with the adjugate, against NumPy's
    determinant and inverse and LAPACK's eigenvectors, down to a matrix of rank 2 (every view's
    ray the same line), where it must stay finite."""
    from mvcalib import _small, _triangulate

    rng = np.random.default_rng(3)
    A = rng.standard_normal((6, 4, 4))
    for a in A:
        adj = np.array(_small.adjugate([[a[i, j] for j in range(4)] for i in range(4)]), float)
        expected = np.linalg.det(a) * np.linalg.inv(a)
        np.testing.assert_allclose(adj, expected, atol=1e-13 * np.abs(expected).max())
    # symmetric positive semi-definite, smallest eigenvalue from 0 to 1e-2 of the largest
    Q = np.linalg.qr(rng.standard_normal((7, 4, 4)))[0]
    values = np.array([[3.0, 2.0, 1.0, e] for e in (0.0, 1e-12, 1e-8, 1e-4, 1e-2, 0.0, 0.0)])
    values[5, 2:] = [1e-3, 0.0]  # two small: the next one 1e-3
    values[6, 2:] = 0.0  # rank 2
    G = np.einsum("kij,kj,klj->kil", Q, values, Q)
    v = np.asarray(_triangulate._null_vector(jnp.asarray(np.moveaxis(G, 0, -1))))  # (4, 7)
    assert np.all(np.isfinite(v))
    for k in range(6):
        w = np.linalg.eigh(G[k])[1][:, 0]
        np.testing.assert_allclose(abs(w @ v[:, k]), 1.0, atol=1e-12, err_msg=str(values[k]))


def test_widest_angle_is_the_same_by_pairs_and_by_views(monkeypatch):
    """Up to `_PAIRED_VIEWS` views every pair is written out, beyond by a loop over the views:
    both give the same angle, with hidden views (and points seen once) taken out alike."""
    from mvcalib import _triangulate

    cameras, world = ring(6, seed=4)
    pixels = cameras.project(world)
    mask = jax.random.uniform(jax.random.key(4), pixels.shape[:-1]) > 0.4
    paired = mc.triangulate(cameras, pixels, mask)
    monkeypatch.setattr(_triangulate, "_PAIRED_VIEWS", 0)
    # the threshold is read while tracing: without this the cached paired program would run again
    jax.clear_caches()
    looped = mc.triangulate(cameras, pixels, mask)
    jax.clear_caches()  # (nor may the looped program serve the tests after this one)
    assert np.isnan(paired.angle).any() and (np.asarray(paired.views) > 2).any()
    np.testing.assert_array_equal(np.isnan(paired.angle), np.isnan(looped.angle))
    np.testing.assert_allclose(paired.angle, looped.angle, rtol=1e-12)
    # against the rays' angles in NumPy, pair by pair
    X, centres = np.asarray(paired.points), np.asarray(cameras.center)
    for n in np.flatnonzero(np.asarray(paired.views) >= 2)[:20]:
        rays = X[n] - centres[np.asarray(mask[:, n])]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        widest = np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1, 1)))
        np.testing.assert_allclose(paired.angle[n], widest, rtol=1e-9)


def test_chunks_of_points_equal_one_batch(monkeypatch):
    # On a CPU, points are triangulated in equal chunks (padded with copies of the last point); the
    # chunked answer must be the one-batch answer, hidden views and all.
    from mvcalib import _triangulate

    cameras, _ = ring(4, seed=13)
    world = np.random.default_rng(13).uniform(0.0, 160.0, (601, 3))
    pixels = np.asarray(cameras.project(world))
    pixels = pixels + 0.3 * np.random.default_rng(14).standard_normal(pixels.shape)
    mask = np.random.default_rng(15).random(pixels.shape[:2]) > 0.2
    monkeypatch.setattr(_triangulate, "CHUNK", 10**9)
    assert _triangulate._chunk_size(4, 601) is None
    whole = mc.triangulate(cameras, pixels, mask)
    monkeypatch.setattr(_triangulate, "CHUNK", 4 * 256)
    assert _triangulate._chunk_size(4, 601) == 256  # three equal chunks of 201: 2 padded
    chunked = mc.triangulate(cameras, pixels, mask)
    for name in ("points", "rms", "angle"):
        np.testing.assert_allclose(
            getattr(chunked, name), getattr(whole, name), rtol=1e-12, atol=1e-12, err_msg=name
        )
    for name in ("views", "ok"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)
    assert np.isnan(np.asarray(whole.points)).any()  # some points have fewer than two views


def test_max_rms_leaves_points_whose_pixels_disagree_out_of_ok():
    """`max_rms` adds the pixels' agreement to the geometry's, in the same compiled program (a
    traced threshold: no new compile for another value); by default 10 px (two users' trials:
    wrong correspondences ok at 50-130 px), `np.inf` for the geometry alone."""
    rig = mc.synthetic.random_rig(jax.random.key(6), n_cameras=4, noise=0.3)
    pixels = np.array(rig.pixels)
    pixels[1, :3] += 40.0  # three points that camera 1 sees 40 px off
    loose = mc.triangulate(rig.cameras, pixels, max_rms=np.inf)
    strict = mc.triangulate(rig.cameras, pixels, max_rms=2.0)
    assert bool(np.all(loose.ok))
    default = mc.triangulate(rig.cameras, pixels)
    np.testing.assert_array_equal(default.ok, np.asarray(loose.rms) <= 10.0)
    assert not np.any(np.asarray(default.ok)[:3]) and np.all(np.asarray(default.ok)[3:])
    np.testing.assert_array_equal(strict.ok, np.asarray(loose.rms) <= 2.0)
    assert not np.any(np.asarray(strict.ok)[:3]) and np.all(np.asarray(strict.ok)[3:])
    np.testing.assert_array_equal(strict.points, loose.points)  # the points themselves the same
    with pytest.raises(ValueError, match="`max_rms` is a positive number"):
        mc.triangulate(rig.cameras, pixels, max_rms=0.0)


def test_nan_pixels_the_mask_calls_visible_are_hidden_with_a_warning():
    """A JAX user's trial: a NaN pixel with `mask` True gave the point from the other views,
    `ok`, without a word (`calibrate` raises on the same input). Now it is hidden as before, and
    said; without a mask, NaN is how a point is marked unseen: no warning."""
    cameras, world = ring(4, seed=12)
    pixels = np.array(cameras.project(world))
    pixels[1, 3] = np.nan
    mask = np.ones(pixels.shape[:-1], bool)
    with pytest.warns(UserWarning, match=r"1 pixels that the mask calls visible .* \(1, 3\)"):
        stale = mc.triangulate(cameras, pixels, mask)
    hidden = mask.copy()
    hidden[1, 3] = False
    expected = mc.triangulate(cameras, pixels, hidden)
    assert np.array_equal(np.asarray(stale.points), np.asarray(expected.points))
    assert int(stale.views[3]) == 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mc.triangulate(cameras, pixels)


def test_placeholder_pixels_for_unseen_points_are_warned_about():
    """Trackers write (-1, -1) or (0, 0) for "not found"; taken as detections they gave points
    13,000 px off, silently (an animal-pose trial)."""
    cameras, world = ring(4, seed=12)
    pixels = np.array(cameras.project(world))
    pixels[1, :5] = -1.0
    with pytest.warns(UserWarning, match="5 of the .* visible pixels are exactly .-1, -1."):
        mc.triangulate(cameras, pixels)
    with pytest.warns(UserWarning, match="exactly .-1, -1."):
        mc.calibrate(world, pixels)
    mask = np.all(pixels != -1.0, -1)  # masked out: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mc.triangulate(cameras, pixels, mask)
