import cv2
import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_difference_check

import mvcalib as mc


def random_camera_with_skew(key, n):
    rig = mc.synthetic.random_rig(key, n_cameras=n)
    skew = jax.random.uniform(jax.random.fold_in(key, 1), (n,), minval=-5.0, maxval=5.0)
    return eqx.tree_at(lambda c: c.skew, rig.cameras, skew), rig.world


def test_project_matches_opencv_with_distortion():
    rig = mc.synthetic.random_rig(jax.random.key(3), n_cameras=3)
    dist = jnp.array([[-0.2, 0.1, 1e-3, -1e-3, 0.01], [0.05, 0, 0, 0, 0], [0, 0, 0, 2e-3, 0]])
    cams = eqx.tree_at(lambda c: c.dist, rig.cameras, dist)
    ours = np.asarray(cams.project(rig.world))
    for i in range(3):
        rvec, _ = cv2.Rodrigues(np.asarray(cams.R[i]))
        ref, _ = cv2.projectPoints(
            np.asarray(rig.world),
            rvec,
            np.asarray(cams.t[i]),
            np.asarray(cams.K[i]),
            np.asarray(cams.dist[i]),
        )
        np.testing.assert_allclose(ours[i], ref[:, 0], atol=1e-9)


def test_projection_matrix_projects_like_project():
    cams, world = random_camera_with_skew(jax.random.key(0), 5)
    P = cams.projection_matrix()
    Xh = jnp.concatenate([world, jnp.ones((len(world), 1))], -1)
    x = jnp.einsum("cij,nj->cni", P, Xh)
    np.testing.assert_allclose(x[..., :2] / x[..., 2:], cams.project(world), atol=1e-9)


def test_center_has_zero_depth_and_is_where_the_rays_meet():
    cams, _ = random_camera_with_skew(jax.random.key(1), 4)
    c = cams.center
    np.testing.assert_allclose(cams.to_camera(c[:, None])[:, 0], 0.0, atol=1e-9)
    Ph = cams.projection_matrix() @ jnp.concatenate([c, jnp.ones((4, 1))], -1)[..., None]
    np.testing.assert_allclose(Ph, 0.0, atol=1e-6)


def test_from_projection_recovers_100_noise_free_cameras():
    cams, _ = random_camera_with_skew(jax.random.key(2), 100)
    scale = jax.random.uniform(jax.random.key(9), (100, 1, 1), minval=-3.0, maxval=3.0)
    back = mc.Camera.from_projection(scale * cams.projection_matrix())
    for name in ("alpha_u", "alpha_v", "u0", "v0"):
        np.testing.assert_allclose(getattr(back, name), getattr(cams, name), rtol=1e-10)
    np.testing.assert_allclose(back.skew, cams.skew, atol=1e-8)
    np.testing.assert_allclose(back.R, cams.R, atol=1e-12)
    np.testing.assert_allclose(back.t, cams.t, rtol=1e-10)


def test_paper_decomposition_equals_general_one_without_skew():
    rig = mc.synthetic.random_rig(jax.random.key(4), n_cameras=10)
    P = rig.cameras.projection_matrix()
    a, b = mc.Camera.from_projection(P), mc.Camera.from_projection(P, skew=False)
    for leaf_a, leaf_b in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(leaf_a, leaf_b, rtol=1e-10, atol=1e-10)


def test_paper_decomposition_reorthogonalises_r_when_data_has_skew():
    cams, _ = random_camera_with_skew(jax.random.key(5), 10)
    paper = mc.Camera.from_projection(cams.projection_matrix(), skew=False)
    RtR = jnp.swapaxes(paper.R, -1, -2) @ paper.R
    np.testing.assert_allclose(RtR, np.broadcast_to(np.eye(3), RtR.shape), atol=1e-12)
    np.testing.assert_allclose(jnp.linalg.det(paper.R), 1.0, atol=1e-12)


def test_decomposition_agrees_with_opencv():
    rig = mc.synthetic.random_rig(jax.random.key(6), n_cameras=20, noise=0.5)
    P = np.asarray(mc.dlt(rig.world, rig.pixels))  # estimated P: carries some skew
    cams = mc.Camera.from_projection(P)
    for i in range(20):
        K, R, C = cv2.decomposeProjectionMatrix(P[i])[:3]
        K = K / K[2, 2]
        np.testing.assert_allclose(np.asarray(cams.K[i]), K, rtol=1e-6, atol=1e-6 * K[0, 0])
        np.testing.assert_allclose(np.asarray(cams.R[i]), R, atol=1e-6)
        np.testing.assert_allclose(np.asarray(cams.center[i]), C[:3, 0] / C[3, 0], rtol=1e-6)


def test_from_projection_gradient_matches_finite_differences():
    cams, _ = random_camera_with_skew(jax.random.key(7), 1)
    P = cams[0].projection_matrix()

    def f(P):
        c = mc.Camera.from_projection(P)
        return jnp.concatenate([c.K.ravel(), c.R.ravel(), c.t])

    central_difference_check(f, P, eps=1e-7, rtol=1e-4, atol=1e-6)


def test_project_gradient_in_points_and_parameters():
    cams, world = random_camera_with_skew(jax.random.key(8), 1)
    cam = cams[0]
    central_difference_check(lambda X: cam.project(X), world, eps=1e-5, rtol=1e-6)
    flat, unravel = jax.flatten_util.ravel_pytree(cam)
    central_difference_check(
        lambda p: unravel(p).project(world), flat, eps=1e-6, rtol=1e-5, atol=1e-6
    )


def test_rig_indexing_and_shapes():
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=6)
    cams = rig.cameras
    assert len(cams) == 6 and cams.batch_shape == (6,)
    assert cams[2].batch_shape == () and cams[1:4].batch_shape == (3,)
    np.testing.assert_allclose(cams[2].project(rig.world), cams.project(rig.world)[2])
    assert cams.project(rig.world).shape == (6, 19, 2)
    assert cams.project(jnp.broadcast_to(rig.world, (6, 19, 3))).shape == (6, 19, 2)
    with pytest.raises(TypeError):
        len(cams[0])


def test_a_concrete_rig_is_indexed_and_its_arrays_derived_with_one_program_each(caplog):
    """`rig[i]` of concrete arrays compiles nothing (NumPy indexing), `K`, `center` and
    `projection_matrix` one program each (not one per `jnp` operation), `procrustes` and
    `to_global` too; all as JAX's own indexing and the traced code give them."""
    import logging

    rig = mc.synthetic.random_rig(jax.random.key(5), n_cameras=7).cameras
    keep = np.array([True, False, True, True, False, False, True])
    indices = (0, -1, slice(1, 4), keep, jnp.asarray(keep), np.array([6, 0]))
    T = mc.RigidTransform(mc.rodrigues(jnp.array([0.1, -0.2, 0.3])), jnp.array([1.0, 2.0, 3.0]))
    src = np.random.default_rng(1).uniform(size=(11, 3))
    jax.clear_caches()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        picked = [rig[i] for i in indices]
        derived = [rig.K, rig.center, rig.projection_matrix()]
        moved = mc.to_global(rig, T)
        fitted = mc.procrustes(src, np.asarray(T.apply(src)))
    compiled = [r.getMessage() for r in caplog.records if "Compiling" in r.getMessage()]
    names = ("_intrinsic_matrix", "_center", "_projection_matrix", "_to_global", "_apply",
             "_procrustes")  # fmt: skip
    assert len(compiled) == len(names) and all(
        any(f"jit({name})" in c for c in compiled) for name in names
    ), compiled
    for i, camera in zip(indices, picked):
        by_jax = jax.tree_util.tree_map(lambda x: x[i], rig)  # noqa: B023
        jax.tree_util.tree_map(np.testing.assert_array_equal, camera, by_jax)
    traced = jax.jit(lambda c: (c.K, c.center, c.projection_matrix()))(rig)
    jax.tree_util.tree_map(np.testing.assert_array_equal, tuple(derived), traced)
    np.testing.assert_array_equal(moved.R, jax.jit(mc.to_global)(rig, T).R)
    np.testing.assert_allclose(fitted.R, T.R, atol=1e-12)
    np.testing.assert_allclose(fitted.t, T.t, atol=1e-12)


def test_opencv_shaped_rotation_and_translation_are_refused_not_broadcast():
    """OpenCV's (3, 1) tvec made a rig of three cameras with t = (1, 1, 1), (2, 2, 2), ..."""
    with pytest.raises(ValueError, match=r"got \(3, 1\): OpenCV's \(3, 1\) tvec"):
        mc.Camera(1000.0, 1000.0, 500.0, 500.0, np.eye(3), np.array([[1.0], [2.0], [3.0]]))
    with pytest.raises(ValueError, match=r"got \(3,\): a rotation vector\? `mc.rodrigues`"):
        mc.Camera(1000.0, 1000.0, 500.0, 500.0, np.array([0.1, 0.2, 0.3]), np.zeros(3))
    assert mc.Camera(1000.0, 1000.0, 500.0, 500.0, np.eye(3), np.zeros(3)).batch_shape == ()
    # and the distortion vectors OpenCV hands back: `cv2.fisheye.calibrate`'s (4, 1), and
    # FileStorage's (1, 4), which failed inside JAX ("Cannot broadcast to shape with fewer
    # dimensions")
    for shape, said in (
        ((4, 1), r"got \(4, 1\): OpenCV's \(4, 1\) column\? pass `dist.reshape"),
        ((1, 4), r"`dist` \(1, 4\) has more cameras .* OpenCV's \(1, 4\) row"),
    ):
        with pytest.raises(ValueError, match=said):
            mc.Camera(300.0, 300.0, 640.0, 480.0, np.eye(3), np.zeros(3), dist=np.zeros(shape),
                      lens="fisheye")  # fmt: skip
    # an OpenCV user's trial: a pinhole's four (k1 k2 p1 p2, k3 zero) were pointed to the
    # fisheye, another lens model; the rational model's eight said nothing
    for n, said in (
        (4, r"got \(4,\) \(OpenCV's k1 k2 p1 p2\? append a zero k3"),
        (8, r"got \(8,\) \(OpenCV's 8-coefficient model\? its first five"),
    ):
        with pytest.raises(ValueError, match=said):
            mc.Camera(300.0, 300.0, 640.0, 480.0, np.eye(3), np.zeros(3), dist=np.zeros(n))


def test_distort_says_it_takes_a_pinholes_five_coefficients():
    """A fisheye's four gave an IndexError."""
    with pytest.raises(ValueError, match=r"got \(4,\) \(a fisheye's four\? `Camera"):
        mc.distort(np.zeros(2), np.zeros(4))


def test_camera_is_a_pytree_for_jit_and_vmap():
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=3)
    projected = jax.vmap(lambda c: c.project(rig.world))(rig.cameras)
    np.testing.assert_allclose(projected, rig.cameras.project(rig.world))
    np.testing.assert_allclose(jax.jit(lambda c: c.K)(rig.cameras), rig.cameras.K)


def test_tsai_conversion_round_trip_and_paper_centre():
    np.testing.assert_allclose(
        mc.image_to_pixel([0.0, 0.0], (0.01, 0.01), image_size=(1000, 1100)), [500.0, 550.0]
    )
    xy = jnp.array([[1.25, -0.5], [-3.0, 2.0]])
    px = mc.image_to_pixel(xy, (0.005, 0.006), center=(320.0, 240.0), sx=1.1)
    np.testing.assert_allclose(px[0], [320 + 1.1 * 1.25 / 0.005, 240 - 0.5 / 0.006])
    back = mc.pixel_to_image(px, (0.005, 0.006), center=(320.0, 240.0), sx=1.1)
    np.testing.assert_allclose(back, xy, atol=1e-12)
    with pytest.raises(ValueError, match="exactly one"):
        mc.image_to_pixel(xy, (0.01, 0.01))


def test_project_on_concrete_arrays_is_one_program_and_the_traced_code(caplog):
    """Called eagerly, `project` compiles one program for a new shape (not one per operation),
    and gives what the same code traced into the caller's program gives."""
    import logging

    rig = mc.synthetic.random_rig(jax.random.key(3), 3).cameras
    world = np.random.default_rng(0).uniform(0.0, 150.0, (23, 3))  # a shape nothing else uses
    jax.clear_caches()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        eager = rig.project(world)
    compiled = [r.getMessage() for r in caplog.records if "Compiling" in r.getMessage()]
    assert len(compiled) == 1 and "_projection" in compiled[0], compiled
    traced = jax.jit(lambda c, w: c.project(w))(rig, world)
    np.testing.assert_allclose(eager, traced, rtol=0, atol=1e-9)
    jaxpr = str(jax.make_jaxpr(lambda c, w: c.project(w))(rig, world))
    assert "pjit" not in jaxpr and "jit[" not in jaxpr  # (inlined: no nested program)


def test_mismatched_batch_shapes_are_refused_with_the_fix():
    """A JAX user's trial: JAX's own broadcast and matmul errors, naming no argument."""
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4)
    frames = jnp.stack([rig.world, rig.world])  # (2, N, 3) for a rig of 4
    with pytest.raises(ValueError, match=r"leading axes \(2,\) do not broadcast .* \(4,\)"):
        rig.cameras.project(frames)
    assert rig.cameras.project(frames[:, None]).shape == (2, 4, 19, 2)
    two = mc.RigidTransform(jnp.stack([jnp.eye(3)] * 2), jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"batch shape \(2,\) does not broadcast .* \(4,\)"):
        mc.to_global(rig.cameras, two)
