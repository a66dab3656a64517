import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_difference_check
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import mvcalib as mc


def random_transform(seed, batch=()):
    rng = np.random.default_rng(seed)
    R = (
        Rotation.random(int(np.prod(batch)) or 1, random_state=rng)
        .as_matrix()
        .reshape(*batch, 3, 3)
    )
    t = rng.normal(scale=500.0, size=(*batch, 3))
    return mc.RigidTransform(jnp.asarray(R), jnp.asarray(t))


def test_procrustes_recovers_a_known_transform_without_noise():
    T = random_transform(0, (50,))
    src = jnp.asarray(np.random.default_rng(1).normal(scale=100.0, size=(50, 18, 3)))
    est = mc.procrustes(src, T.apply(src))
    np.testing.assert_allclose(est.R, T.R, atol=1e-10)
    np.testing.assert_allclose(est.t, T.t, atol=1e-10 * 500)


def test_procrustes_matches_scipy_with_weights_under_noise():
    rng = np.random.default_rng(2)
    T = random_transform(3)
    src = rng.normal(scale=100.0, size=(30, 3))
    dst = np.asarray(T.apply(jnp.asarray(src))) + rng.normal(scale=2.0, size=(30, 3))
    w = rng.uniform(0.1, 2.0, size=30)
    est = mc.procrustes(src, dst, w)
    cs, cd = np.average(src, 0, w), np.average(dst, 0, w)
    ref, _ = Rotation.align_vectors(dst - cd, src - cs, weights=w)
    np.testing.assert_allclose(est.R, ref.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(est.t, cd - ref.as_matrix() @ cs, atol=1e-8)


def test_zero_weights_remove_points():
    rng = np.random.default_rng(4)
    T = random_transform(5)
    src = rng.normal(size=(10, 3))
    dst = np.array(T.apply(jnp.asarray(src)))
    dst[7:] += 100.0  # outliers, weighted out
    w = np.r_[np.ones(7), np.zeros(3)]
    est = mc.procrustes(src, dst, w)
    np.testing.assert_allclose(est.R, T.R, atol=1e-10)


def test_procrustes_returns_a_proper_rotation_on_reflected_points():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(20, 3))
    mirror = np.diag([1.0, 1.0, -1.0])
    for noise in (0.0, 0.01, 0.3):
        dst = src @ mirror.T + noise * rng.normal(size=src.shape)
        with pytest.warns(UserWarning, match="no rigid motion fits the points"):
            R = np.asarray(mc.procrustes(src, dst).R)
        assert abs(np.linalg.det(R) - 1.0) < 1e-12
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    # nearly planar points, nearer a reflection than a rotation: still det +1
    flat = src * np.array([1.0, 1.0, 1e-3])
    R = np.asarray(mc.procrustes(flat, flat @ mirror.T).R)
    assert abs(np.linalg.det(R) - 1.0) < 1e-12


def test_points_no_rigid_motion_fits_are_warned_about():
    """A benchmark trial registered a target measured in mm to a room measured in metres: a
    residual of 110.7 m on a 0.22 m room, silently. Noise well within the spread: no word."""
    rng = np.random.default_rng(7)
    T = random_transform(8)
    src = rng.normal(scale=100.0, size=(18, 3))  # mm
    dst = np.asarray(T.apply(jnp.asarray(src)))
    with pytest.warns(UserWarning, match=r"in the same units \(mm and m\?\)"):
        mc.procrustes(src, dst / 1000.0)
    with pytest.warns(UserWarning, match=r"\(at batch index \(1,\)\)"):
        mc.procrustes(np.stack([src, src]), np.stack([dst, dst / 1000.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mc.procrustes(src, dst + rng.normal(scale=2.0, size=dst.shape))


def test_procrustes_gradient_matches_finite_differences():
    rng = np.random.default_rng(7)
    T = random_transform(8)
    src = jnp.asarray(rng.normal(scale=10.0, size=(12, 3)))
    dst = T.apply(src) + jnp.asarray(rng.normal(scale=0.1, size=(12, 3)))
    w = jnp.asarray(rng.uniform(0.5, 1.5, size=12))

    def flat(T):  # t is ~500 in size: central differences are good to ~1e-7 absolute there
        return jnp.concatenate([T.R.ravel(), T.t / 500.0])

    central_difference_check(lambda s: flat(mc.procrustes(s, dst, w)), src, rtol=1e-5, atol=1e-8)
    central_difference_check(lambda d: flat(mc.procrustes(src, d, w)), dst, rtol=1e-5, atol=1e-8)
    central_difference_check(lambda w: flat(mc.procrustes(src, dst, w)), w, rtol=1e-5, atol=1e-8)


def test_gradient_exists_where_the_svd_derivative_does_not():
    # The corners of a cube: the cross-covariance has three equal singular values, where JAX's
    # own SVD derivative is NaN. The optimal rotation is still unique, and so is its derivative.
    cube = jnp.array([[x, y, z] for x in (-1.0, 1) for y in (-1.0, 1) for z in (-1.0, 1)])
    T = random_transform(9)
    g = central_difference_check(
        lambda d: mc.procrustes(cube, d).R.ravel(), T.apply(cube), rtol=1e-5, atol=1e-8
    )
    assert np.all(np.isfinite(g))
    # Re-orthogonalising an exact rotation (the paper's R = U V^T step) likewise.
    R = T.R
    central_difference_check(lambda M: mc.nearest_rotation(M).ravel(), R, rtol=1e-5, atol=1e-8)
    assert np.all(np.isfinite(np.asarray(jax.grad(lambda M: mc.nearest_rotation(M)[0, 1])(R))))


def test_paper_variant_is_not_orthogonal_under_noise_and_less_accurate():
    rng = np.random.default_rng(10)
    target = mc.targets.box_corner()
    src = jnp.asarray(target.points[target.global_ids])
    ortho_err, paper_err, ortho_dev = [], [], []
    for trial in range(50):
        T = random_transform(100 + trial)
        dst = T.apply(src) + jnp.asarray(rng.normal(scale=0.5, size=src.shape))
        test = jnp.asarray(rng.uniform(-300, 300, size=(100, 3)))  # anywhere near the target
        for est, errs in (
            (mc.procrustes(src, dst), ortho_err),
            (mc.procrustes_paper(src, dst), paper_err),
        ):
            errs.append(float(jnp.sqrt(jnp.mean((est.apply(test) - T.apply(test)) ** 2))))
        R = np.asarray(mc.procrustes_paper(src, dst).R)
        ortho_dev.append(np.abs(R.T @ R - np.eye(3)).max())
    assert np.median(ortho_dev) > 1e-3  # the paper's R is not a rotation
    assert np.mean(paper_err) > 1.5 * np.mean(ortho_err)
    # and without noise both are exact
    T = random_transform(11)
    np.testing.assert_allclose(mc.procrustes_paper(src, T.apply(src)).R, T.R, atol=1e-10)


def test_to_global_keeps_every_pixel():
    rig = mc.synthetic.random_rig(jax.random.key(20), n_cameras=4)
    T = random_transform(12)
    glob = mc.to_global(rig.cameras, T)
    np.testing.assert_allclose(
        glob.project(T.apply(rig.world)), rig.cameras.project(rig.world), atol=1e-8
    )
    np.testing.assert_allclose(glob.center, T.apply(rig.cameras.center), atol=1e-8)
    # one transform per camera broadcasts too
    Ts = random_transform(13, (4,))
    glob = mc.to_global(rig.cameras, Ts)
    np.testing.assert_allclose(
        glob.project(Ts.apply(rig.world)), rig.cameras.project(rig.world), atol=1e-8
    )
    # linear in t: central differences are exact but for rounding (~|t| 1e-16 / eps, and the
    # translations are ~1e3), which a large step keeps far below the tolerance
    central_difference_check(
        lambda t: mc.to_global(rig.cameras, mc.RigidTransform(T.R, t)).t, T.t, eps=1e-2, rtol=1e-6
    )


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 2**31 - 1))
@example(1821, 0)  # |t| = 1570: the translation of a a^-1 is 1.1e-12 from 0, all rounding
def test_rigid_transform_group_laws(seed_a, seed_b):
    a, b = random_transform(seed_a), random_transform(seed_b)
    x = jnp.asarray(np.random.default_rng(seed_a ^ seed_b).normal(size=(5, 3)))
    np.testing.assert_allclose((a @ b).apply(x), a.apply(b.apply(x)), atol=1e-9)
    np.testing.assert_allclose(a.inverse().apply(a.apply(x)), x, atol=1e-9)
    identity = np.asarray((a @ a.inverse()).as_matrix())
    np.testing.assert_allclose(identity[:3, :3], np.eye(3), atol=1e-12)
    # the translation R (-R^T t) + t cancels terms of |t| (up to ~2000 here): its rounding is a
    # few eps |t|, not a fixed 1e-12
    t_scale = np.linalg.norm(np.asarray(a.t))
    np.testing.assert_allclose(identity[:3, 3], 0.0, atol=16 * np.finfo(float).eps * t_scale)
    np.testing.assert_array_equal(identity[3], [0.0, 0.0, 0.0, 1.0])
    M = np.asarray(a.as_matrix())
    np.testing.assert_allclose((np.c_[x, np.ones(5)] @ M.T)[:, :3], a.apply(x), atol=1e-9)


def test_a_batch_of_transforms_is_indexed_as_a_rig_is():
    """`poses[f]` of a batch (e.g. `calibrate_rig`'s `target_poses`) as JAX's own indexing gives
    it, concrete and traced; a single transform has no length and no index."""
    poses = mc.synthetic.board_rig(jax.random.key(0), n_cameras=2, n_frames=9).poses
    keep = np.arange(9) % 3 == 0
    assert poses.batch_shape == (9,) and len(poses) == 9
    for i in (0, -1, slice(2, 5), keep, jnp.asarray(keep), np.array([8, 1])):
        by_jax = jax.tree_util.tree_map(lambda x: x[i], poses)  # noqa: B023
        jax.tree_util.tree_map(np.testing.assert_array_equal, poses[i], by_jax)
    np.testing.assert_array_equal(jax.jit(lambda p: p[4].t)(poses), poses.t[4])
    assert poses[4].batch_shape == ()
    with pytest.raises(TypeError, match="cannot be indexed"):
        poses[4][0]
    with pytest.raises(TypeError, match="has no length"):
        len(poses[4])


def test_rodrigues_second_derivatives_just_above_its_series():
    """`(1 - cos t) / t^2` lost its second derivative to cancellation just above the switch to
    the Taylor series (2e-5, relative, at t = 2e-6); the half-angle form keeps it to 1e-9. The
    reference: the series to t^4, exact there."""

    def series(w):
        t2 = jnp.sum(w * w)
        K = jnp.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        a, b = 1 - t2 / 6 + t2**2 / 120, 0.5 - t2 / 24 + t2**2 / 720
        return jnp.eye(3) + a * K + b * (K @ K)

    v = jnp.array([0.3, -1.2, 0.7])
    for t in (2e-6, 1e-5, 1e-4):
        w = t * jnp.array([0.6, 0.0, 0.8])
        exact = jax.hessian(lambda w: jnp.sum(series(w) @ v))(w)
        ours = jax.hessian(lambda w: jnp.sum(mc.rodrigues(w) @ v))(w)
        np.testing.assert_allclose(ours, exact, atol=1e-9)
