import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_difference_check

import mvcalib as mc


def normalised(world, pixels, rms):
    """Hartley's similarities T3, T2 (centroid to 0; mean or RMS distance sqrt(d)) and the
    normalised homogeneous points."""

    def similarity(x):
        c = x.mean(0)
        d2 = np.sum((x - c) ** 2, axis=1)
        s = np.sqrt(x.shape[1] / np.mean(d2)) if rms else np.sqrt(x.shape[1]) / np.mean(np.sqrt(d2))
        T = np.eye(x.shape[1] + 1) * s
        T[:-1, -1], T[-1, -1] = -s * c, 1.0
        return T

    T3, T2 = similarity(world), similarity(pixels)
    Xn = np.c_[world, np.ones(len(world))] @ T3.T
    xn = np.c_[pixels, np.ones(len(pixels))] @ T2.T
    return T3, T2, Xn, xn


def numpy_dlt(world, pixels):
    """Independent reference: Hartley-normalised DLT in plain NumPy (mean-distance scaling)."""
    T3, T2, Xn, xn = normalised(world, pixels, rms=False)
    rows = []
    for X, (u, v, _) in zip(Xn, xn):
        rows.append(np.r_[X, np.zeros(4), -u * X])
        rows.append(np.r_[np.zeros(4), X, -v * X])
    P = np.linalg.inv(T2) @ np.linalg.svd(np.array(rows))[2][-1].reshape(3, 4) @ T3
    P = P / np.linalg.norm(P[2, :3])
    return P if np.sum(np.c_[world, np.ones(len(world))] @ P[2]) > 0 else -P


def relative_error(a, b):
    return np.abs(np.asarray(a) - np.asarray(b)) / np.maximum(np.abs(np.asarray(b)), 1e-300)


def test_noise_free_recovers_k_r_t_of_100_cameras():
    rig = mc.synthetic.random_rig(jax.random.key(10), n_cameras=100)
    cams = mc.Camera.from_projection(mc.dlt(rig.world, rig.pixels_true))
    for name in ("alpha_u", "alpha_v", "u0", "v0"):
        assert relative_error(getattr(cams, name), getattr(rig.cameras, name)).max() < 1e-8
    assert np.abs(np.asarray(cams.skew)).max() < 1e-8 * 1000  # |skew| relative to focal scale
    assert np.abs(np.asarray(cams.R - rig.cameras.R)).max() < 1e-8
    assert relative_error(cams.t, rig.cameras.t).max() < 1e-8


def test_median_focal_error_below_one_percent_at_half_pixel_noise():
    rig = mc.synthetic.random_rig(jax.random.key(11), n_cameras=500, noise=0.5)
    cams = mc.Camera.from_projection(mc.dlt(rig.world, rig.pixels))
    err = relative_error(cams.alpha_u, rig.cameras.alpha_u)
    assert np.median(err) < 0.01
    # and the error is noise, not bias: the DLT is not far from the truth on average
    assert abs(np.median(np.asarray(cams.alpha_u / rig.cameras.alpha_u)) - 1) < 0.005


def test_agrees_with_independent_numpy_dlt():
    rig = mc.synthetic.random_rig(jax.random.key(12), n_cameras=8, noise=0.3)
    ours = np.asarray(mc.dlt(rig.world, rig.pixels))
    for i in range(8):
        ref = numpy_dlt(np.asarray(rig.world), np.asarray(rig.pixels[i]))
        # Mean- and RMS-distance normalisation give slightly different least-squares weights:
        # compare what matters, the reprojection, to well below the noise.
        cams = mc.Camera.from_projection(jnp.stack([ours[i], ref]))
        proj = cams.project(rig.world)
        assert np.abs(np.asarray(proj[0] - proj[1])).max() < 0.02
        np.testing.assert_allclose(ours[i], ref, rtol=0.05, atol=1e-3 * np.abs(ref).max())


SIX = [0, 4, 8, 11, 14, 18]  # six of the box corner's dots, on all three faces


def svd_dlt(world, pixels):
    """Our normalisation (RMS distance sqrt(d)) with LAPACK's SVD of L: the same least-squares
    problem, solved the textbook way. Returns P (||m3|| = 1, points in front) and the condition
    number as `calibrate` defines it, ||L||_F / s_11."""
    T3, T2, Xn, xn = normalised(world, pixels, rms=True)
    zero = np.zeros_like(Xn)
    L = np.stack([np.c_[Xn, zero, -xn[:, :1] * Xn], np.c_[zero, Xn, -xn[:, 1:2] * Xn]], 1)
    _, sv, vt = np.linalg.svd(L.reshape(-1, 12))
    P = np.linalg.inv(T2) @ vt[-1].reshape(3, 4) @ T3
    P = P / np.linalg.norm(P[2, :3])
    P = P if np.sum(np.c_[world, np.ones(len(world))] @ P[2]) > 0 else -P
    return P, np.sqrt(np.sum(sv**2)) / sv[-2]


@pytest.mark.parametrize(
    "noise, points", [(0.0, slice(None)), (0.5, slice(None)), (10.0, slice(None)), (0.5, SIX)]
)
def test_inverse_iteration_equals_lapack_svd(noise, points):
    # The DLT solves L^T L by inverse iteration: the same vector as the SVD's to rounding, also
    # where the two smallest eigenvalues are closest (heavy noise, the minimal six points).
    rig = mc.synthetic.random_rig(jax.random.key(13), n_cameras=40, noise=noise)
    world, pixels = np.asarray(rig.world)[points], np.asarray(rig.pixels)[:, points]
    result = mc.calibrate(world, pixels, max_relative_rms=np.inf)
    assert np.all(np.asarray(result.ok))
    for i in range(len(pixels)):
        P, condition = svd_dlt(world, pixels[i])
        np.testing.assert_allclose(result.P[i], P, rtol=0, atol=1e-9 * np.abs(P).max())
        # the condition number is estimated, from below, within 5 %
        assert 0.95 * condition <= float(result.condition[i]) <= condition * (1 + 1e-9)


def test_condition_estimate_stays_below_the_svds_where_v_converges_slowly():
    # Six points at 10 px: the two smallest eigenvalues of L^T L are close (ratio ~0.2), so v is
    # still moving when the second vector's iterates stop (after `_Z_STEPS`). The estimate of
    # s_11 must stay on its side (from above, so the condition number from below) all the same.
    rig = mc.synthetic.random_rig(jax.random.key(104), n_cameras=200, noise=10.0)
    world, pixels = np.asarray(rig.world)[SIX], np.asarray(rig.pixels)[:, SIX]
    result = mc.calibrate(world, pixels, max_relative_rms=np.inf)
    ratio = np.array(
        [float(result.condition[i]) / svd_dlt(world, p)[1] for i, p in enumerate(pixels)]
    )
    assert np.all(ratio <= 1 + 1e-9) and np.all(ratio >= 0.95), (ratio.min(), ratio.max())


def test_close_smallest_singular_values_still_give_the_svds_answer():
    # Six points at 10 px: for a few cameras the two smallest singular values of L are close
    # (s_12 / s_11 up to ~0.8), where inverse iteration on v alone moves the error by only
    # (s_12 / s_11)^2 a step: camera 117 of these came out 35 % off the SVD's P after its 8
    # steps, with status OK, and its condition number above the SVD's. v and the second vector
    # go on as a block, turned by Rayleigh-Ritz, at the rate of the third singular value.
    rig = mc.synthetic.random_rig(jax.random.key(1100), n_cameras=500, noise=10.0)
    world, pixels = np.asarray(rig.world)[SIX], np.asarray(rig.pixels)[:, SIX]
    result = mc.calibrate(world, pixels, max_relative_rms=np.inf)
    ok = np.flatnonzero(np.asarray(result.ok))  # some put a point behind them at this noise
    assert len(ok) > 450
    worst = []
    for i in ok:
        P, condition = svd_dlt(world, pixels[i])
        worst.append(np.max(np.abs(np.asarray(result.P[i]) - P)) / np.abs(P).max())
        assert 0.95 * condition <= float(result.condition[i]) <= condition * (1 + 1e-9), i
    assert max(worst) < 1e-9, (int(np.argmax(worst)), max(worst))


def test_nearly_coplanar_points_with_noise_give_the_svds_answer():
    # The 19 dots squashed to 1e-4 of their depth (condition ~5e4) with 0.1 px of noise: three or
    # four small singular values close together, where v alone and the block of two do not
    # settle (before: P up to ~25 % off the SVD's, status OK). Where the iteration stops at a
    # limit unsettled, LAPACK's eigenvector of G answers: as good as G allows (cond^2 eps).
    rig = mc.synthetic.random_rig(jax.random.key(21), n_cameras=300, noise=0.0)
    world = np.asarray(rig.world).copy()
    world[:, 2] = world[:, 2].mean() + 1e-4 * (world[:, 2] - world[:, 2].mean())
    rng = np.random.default_rng(0)
    pixels = np.asarray(rig.cameras.project(world)) + 0.1 * rng.standard_normal((300, 19, 2))
    result = mc.calibrate(world, pixels, max_relative_rms=np.inf)
    ok = np.flatnonzero(np.asarray(result.ok))
    assert len(ok) > 280
    worst = max(
        np.max(np.abs(np.asarray(result.P[i]) - svd_dlt(world, pixels[i])[0]))
        / np.abs(svd_dlt(world, pixels[i])[0]).max()
        for i in ok
    )
    assert worst < 1e-4, worst


def test_a_camera_that_sees_a_small_part_of_a_shared_target_gets_the_svds_answer():
    # A shared target's moments come from its own coordinates, moved to each camera's
    # normalisation by a congruence, which loses ~eps (distance / spread)^2 where a camera sees
    # only a small part of the target far from its origin: for a hundredth of its extent P came
    # out 5e-10 off the SVD's. Such cameras get the moments of their own normalised points.
    box = np.asarray(mc.targets.box_corner().points)
    lo, hi = box.min(0), box.max(0)
    rng = np.random.default_rng(7)
    cameras = mc.synthetic.random_cameras(jax.random.key(1), 8, image_size=(1000, 1000))
    worst = {}
    for part in (1.0, 0.1, 0.01):  # the seen patch's side, of the target's
        target = lo + (hi - lo) * rng.uniform(0, 1, (500, 3))  # hidden in every camera
        patch = lo + (hi - lo) * (0.7 + part * rng.uniform(0, 1, (30, 3)))
        world = np.r_[target, patch]
        pixels = np.asarray(cameras.project(world)) + 0.3 * part * rng.standard_normal((8, 530, 2))
        mask = np.zeros((8, 530), bool)
        mask[:, 500:] = True
        result = mc.calibrate(world, pixels, mask, max_relative_rms=np.inf)
        assert np.all(np.asarray(result.ok))
        worst[part] = max(
            np.max(np.abs(np.asarray(result.P[i]) - P)) / np.abs(P).max()
            for i, P in enumerate(svd_dlt(patch, pixels[i, 500:])[0] for i in range(8))
        )
    assert max(worst.values()) < 1e-10, worst


def test_masked_median_equals_numpy_median_with_ties_and_hidden_points():
    # the sorting-network (N <= 32) and sorting branches of the POOR_FIT check's median, odd and
    # even N and counts; sorting orders the floats' bits as integers: negative values, signed
    # zeros and large exponents included
    rng = np.random.default_rng(0)
    cases = [(1, np.float64), (2, np.float64), (7, np.float64), (19, np.float64)]
    cases += [(20, np.float64), (32, np.float32), (33, np.float64), (100, np.float32)]
    for n, dtype in cases:
        x = np.round(3 * rng.standard_normal((500, n)))  # many ties, -0.0 among them
        x[250:] = rng.standard_normal((250, n)) * 10.0 ** rng.integers(-30, 30, (250, 1))
        x = x.astype(dtype)
        mask = rng.uniform(size=(500, n)) > rng.uniform(0.0, 0.9, (500, 1))
        mask[0], mask[1] = False, True
        ours = np.asarray(mc._dlt._masked_median(jnp.asarray(x), jnp.asarray(mask)))
        ref = [np.median(row[keep]) if keep.any() else np.nan for row, keep in zip(x, mask)]
        np.testing.assert_array_equal(ours, np.asarray(ref, dtype), err_msg=f"{n} {dtype}")


@pytest.mark.parametrize("C", [1, 7, 64, 4096])
def test_batched_call_equals_per_camera_calls(C):
    rig = mc.synthetic.random_rig(jax.random.key(C), n_cameras=C, noise=0.3)
    P = mc.dlt(rig.world, rig.pixels, rig.mask)
    assert P.shape == (C, 3, 4)
    idx = np.random.default_rng(C).choice(C, size=min(C, 12), replace=False)
    for i in idx:
        single = mc.dlt(rig.world, rig.pixels[i], rig.mask[i])
        np.testing.assert_allclose(P[i], single, rtol=1e-10, atol=1e-10 * np.abs(single).max())


def test_a_camera_that_needs_more_steps_leaves_the_others_unchanged(monkeypatch):
    # Inverse iteration goes on while any camera has not converged; the converged ones keep their
    # vectors, so their answers (and condition estimates) are bitwise those of a batch in which
    # every camera stops after `_MIN_STEPS`, from the same compiled program.
    # 40 x 19: the program of the test above
    clean = mc.synthetic.random_rig(jax.random.key(5), n_cameras=40, noise=0.5)
    noisy = mc.synthetic.random_rig(jax.random.key(6), n_cameras=1, noise=20.0)
    world, pixels = np.asarray(clean.world), np.asarray(clean.pixels)
    mixed = np.concatenate([np.asarray(noisy.pixels), pixels[1:]])
    results = [mc.calibrate(world, batch, max_relative_rms=np.inf) for batch in (pixels, mixed)]
    for field in ("P", "condition", "status"):
        a, b = (np.asarray(getattr(r, field))[1:] for r in results)
        np.testing.assert_array_equal(a, b, err_msg=field)

    # (the noisy camera does take more steps: stopped after `_MIN_STEPS`, its vector is another)
    visible = np.ones(mixed[:2].shape[:2], bool)
    # (4, 10, 2): the noisy camera and a clean one
    S = jax.jit(lambda x: mc._dlt._moments(world, x, visible)[0])(mixed[:2])

    def eigenvectors():  # traced anew: `_MAX_STEPS` as it is now
        return np.asarray(jax.jit(lambda S: mc._dlt._eigen(S)[0])(S))

    v = eigenvectors()
    monkeypatch.setattr(mc._dlt, "_MAX_STEPS", mc._dlt._MIN_STEPS)
    stopped = eigenvectors()
    assert np.abs(stopped[:, 0] - v[:, 0]).max() > 1e-12
    np.testing.assert_array_equal(stopped[:, 1], v[:, 1])


def test_a_rig_solved_in_chunks_equals_one_batch(monkeypatch):
    # On one CPU device, large rigs are solved in equal chunks of cameras (padded with copies of
    # the last camera): every camera's answer is its one-batch answer, failures too.
    assert mc._dlt._chunk_size(4096, 19) is None  # one batch
    assert mc._dlt._chunk_size(65536, 19) == 4311  # 16 chunks of 4096
    assert mc._dlt._chunk_size(4096, 2000) == 64  # the least chunk
    rig = mc.synthetic.random_rig(jax.random.key(21), n_cameras=50, noise=0.5)
    pixels, mask = np.asarray(rig.pixels).copy(), np.asarray(rig.mask).copy()
    mask[3, :14] = False  # 5 points left: TOO_FEW_POINTS
    pixels[7, 2] += 300.0  # a wild pixel: POOR_FIT
    mask[49, 4:] = False  # the camera the padding copies: TOO_FEW_POINTS

    def solve(world, chunk):
        monkeypatch.setattr(mc._dlt, "_chunk_size", lambda n_cameras, n_points: chunk)
        mc._dlt.solve_validated.clear_cache()  # traced anew with this chunk
        return [np.asarray(x) for x in mc._dlt.solve(world, pixels, mask)]

    for world in (rig.world, np.broadcast_to(rig.world, (50, 19, 3))):  # shared, per camera
        whole, chunked = solve(world, None), solve(world, 16)  # four chunks of 13
        np.testing.assert_array_equal(chunked[1], whole[1])  # status
        assert {3, 7, 49} <= set(np.flatnonzero(whole[1] != mc.Status.OK))
        # P, NaN alike, to rounding of each camera's largest entry: XLA's vectorised loops over
        # 13 and over 50 cameras round differently in the last bits (measured 2e-14 of the
        # largest entry; entry by entry, 2e-12 of an entry a millionth of it)
        scale = np.abs(whole[0]).max(axis=(1, 2), initial=0.0, where=np.isfinite(whole[0]))
        scale = np.where(scale > 0, scale, 1.0)[:, None, None]
        np.testing.assert_allclose(chunked[0] / scale, whole[0] / scale, rtol=0, atol=1e-13)
        # condition; where s_11 is zero (five points) it is rounding, at any batch size > 1/rcond
        solved = whole[1] != mc.Status.TOO_FEW_POINTS
        # The estimate is not the same to rounding everywhere: where v went on as a block with
        # the second vector, the block stops at the step where v stops changing in its last
        # bits, and its Ritz value moves ~1e-3 a step where s_11 and s_10 are close (0.79 apart
        # here): on an AMD EPYC one camera's block stopped a step earlier in a chunk (7.6116
        # against 7.6174; the SVD's 7.6317). Most cameras agree to rounding, and every one is
        # within the estimate's accuracy of the SVD's (`test_inverse_iteration_equals_...`).
        same = np.isclose(chunked[2][solved], whole[2][solved], rtol=1e-12, atol=0)
        assert same.mean() >= 0.9, np.flatnonzero(~same)
        for i in np.flatnonzero(whole[1] == mc.Status.OK):
            visible = mask[i]
            exact = svd_dlt(np.asarray(rig.world)[visible], pixels[i][visible])[1]
            for condition in (chunked[2][i], whole[2][i]):
                assert 0.95 * exact <= condition <= exact * (1 + 1e-9), (i, condition, exact)
        assert np.all(chunked[2][~solved] > 1e8) and np.all(whole[2][~solved] > 1e8)
        np.testing.assert_array_equal(chunked[3], whole[3])  # mirrored


def test_any_leading_axes_and_broadcast_world():
    rig = mc.synthetic.random_rig(jax.random.key(13), n_cameras=6, noise=0.3)
    P = mc.dlt(rig.world, rig.pixels)
    P2 = mc.dlt(jnp.broadcast_to(rig.world, (2, 3, 19, 3)), rig.pixels.reshape(2, 3, 19, 2))
    assert P2.shape == (2, 3, 3, 4)
    np.testing.assert_allclose(P2.reshape(6, 3, 4), P, rtol=1e-10, atol=1e-12)


def test_masked_points_have_no_influence():
    rig = mc.synthetic.random_rig(jax.random.key(14), n_cameras=5, noise=0.3)
    mask = np.asarray(rig.mask).copy()
    mask[:, [1, 5, 11]] = False
    mask[2, 14] = False
    P = mc.dlt(rig.world, rig.pixels, mask)
    # wild values, even NaN and inf, in the hidden entries change nothing, bit for bit
    world = np.broadcast_to(np.asarray(rig.world), (5, 19, 3)).copy()
    P_own = mc.dlt(world, rig.pixels, mask)  # world points per camera
    pixels = np.asarray(rig.pixels).copy()
    pixels[~mask] = np.array([1e7, np.nan])
    world[~mask] = np.inf
    np.testing.assert_array_equal(mc.dlt(world, pixels, mask), P_own)
    np.testing.assert_array_equal(mc.dlt(rig.world, pixels, mask), P)
    # (a shared target's moments come from its own coordinates, moved to each camera's
    # normalisation by a congruence: the same to rounding of each row's largest entry; measured
    # 1.5e-12 and 1.0e-11 of an entry that cancels to 1e-3 of its row, 8e-15 of the row)
    scale = np.abs(np.asarray(P)).max(-1, keepdims=True)
    assert np.all(np.abs(np.asarray(P_own) - np.asarray(P)) <= 1e-13 * scale)
    # and the result is the DLT of the visible points alone
    keep = mask[2]
    np.testing.assert_allclose(
        mc.dlt(rig.world[keep], rig.pixels[2][keep]), P[2], rtol=1e-10, atol=1e-12
    )


def test_masked_points_get_zero_gradient():
    rig = mc.synthetic.random_rig(jax.random.key(15), n_cameras=1, noise=0.3)
    mask = np.ones(19, bool)
    mask[[3, 8]] = False
    g = jax.grad(lambda px: jnp.sum(mc.dlt(rig.world, px, mask) ** 2))(rig.pixels[0])
    assert np.all(np.asarray(g)[~mask] == 0) and np.all(np.isfinite(np.asarray(g)))
    assert np.abs(np.asarray(g)[mask]).max() > 0


def test_normalisation_scale_and_sign():
    rig = mc.synthetic.random_rig(jax.random.key(16), n_cameras=10, noise=0.3)
    P = mc.dlt(rig.world, rig.pixels)
    np.testing.assert_allclose(jnp.linalg.norm(P[:, 2, :3], axis=-1), 1.0, rtol=1e-12)
    depth = jnp.einsum("cj,nj->cn", P[:, 2, :3], rig.world) + P[:, 2, 3:]
    assert bool(jnp.all(depth > 0))


def test_dlt_gradient_matches_finite_differences_noise_free_and_noisy():
    for noise in (0.0, 0.3):
        rig = mc.synthetic.random_rig(jax.random.key(17), n_cameras=1, noise=noise)
        world, pixels = rig.world, rig.pixels[0]
        check = dict(eps=1e-6, rtol=1e-5, atol=1e-9)
        central_difference_check(lambda px, w=world: mc.dlt(w, px), pixels, **check)
        central_difference_check(lambda X, px=pixels: mc.dlt(X, px), world, **check)


def test_dlt_works_under_user_jit_and_grad():
    rig = mc.synthetic.random_rig(jax.random.key(18), n_cameras=3, noise=0.3)
    f = jax.jit(lambda px: mc.dlt(rig.world, px, rig.mask))
    np.testing.assert_allclose(f(rig.pixels), mc.dlt(rig.world, rig.pixels, rig.mask))
    loss = lambda px: jnp.sum(mc.calibrate(rig.world, px, rig.mask).cameras.alpha_u)  # noqa: E731
    assert np.all(np.isfinite(np.asarray(jax.grad(loss)(rig.pixels))))


def test_float32_rms_within_twice_float64_on_the_demo_rig():
    rms = {}
    for dtype in (jnp.float64, jnp.float32):
        scene = mc.synthetic.paper_scene(noise=0.3, dtype=dtype)
        result = mc.calibrate(scene.world, scene.pixels, scene.mask)
        assert result.cameras.alpha_u.dtype == dtype
        true = mc.reprojection_report(scene.local_cameras, scene.world, scene.pixels, scene.mask)
        rms[dtype] = np.asarray(result.report.rms)
        assert np.all(np.asarray(result.ok))
        # both are fits to the same noisy pixels: below the true cameras' RMS
        assert np.all(rms[dtype] <= np.asarray(true.rms) * 1.001)
    assert np.all(rms[jnp.float32] <= 2 * rms[jnp.float64])
    # and the float32 path also works on a rig of many realistic cameras
    rig32 = mc.synthetic.random_rig(jax.random.key(19), n_cameras=200, noise=0.3, dtype=jnp.float32)
    rig64 = mc.synthetic.random_rig(jax.random.key(19), n_cameras=200, noise=0.3)
    r32 = mc.calibrate(rig32.world, rig32.pixels).report.rms
    r64 = mc.calibrate(rig64.world, rig64.pixels).report.rms
    assert np.median(np.asarray(r32) / np.asarray(r64)) < 1.05
    assert np.all(np.asarray(r32) < 2 * np.asarray(r64))
