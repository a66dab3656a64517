"""Derivatives of every public numeric function against central finite differences (float64).

Each check perturbs the inputs along one random direction (each element scaled by its own size,
so that a focal length of 1000 px and a distortion coefficient of 0.1 move by the same relative
step) and compares

- forward mode, `jax.jvp`, with `(f(x + h v) - f(x - h v)) / 2h`, element by element, and
- reverse mode, `jax.grad` of a random linear functional of the outputs, dotted with `v`,

see `check_derivatives`. Directional derivatives rather than full Jacobians keep every check to
one compiled function whatever the input size.

Not differentiable, and not tested here: `detect_dots`, `label_dots`, `read_image`,
`calibrate_images` (NumPy/scikit-image on pixel grids: thresholds, connected components and the
choice of which blob is which dot are discrete, so the output is piecewise constant in the image)
and `bundle_adjust` (a host-side loop that samples tracks and drops outliers by threshold; its
inner `refine_rig` is differentiable). See docs/differentiability.md.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import mvcalib as mc

DIST = jnp.array([-0.2, 0.1, 1e-3, -1e-3, 0.01])  # k1, k2, p1, p2, k3 (OpenCV order)


def _inexact_leaves(tree):
    return [x for x in jax.tree_util.tree_leaves(tree) if eqx.is_inexact_array(x)]


def check_derivatives(f, x, *, reverse=False, rel_step=1e-6, rtol=1e-5, seed=0):
    """Derivatives of `f` at the pytree `x` along a random direction against central differences.

    The direction `v` is standard normal per element, times the size of the element it moves
    (the RMS of its array where the element is zero), and `x +- rel_step * v` are the two
    evaluations. Every floating output array of `jax.jvp` must agree with the difference
    quotient to `rtol` relative to that array's largest entry. With `reverse`, also the
    reverse-mode directional derivative `<jax.grad(<w, f>), v>` (random `w`) must agree with
    `<w, difference quotient>`. One compiled function gives the values and the derivatives, so
    a check costs one compilation. Returns that gradient (a pytree like `x`), or None.
    """
    rng = np.random.default_rng(seed)
    leaves, treedef = jax.tree_util.tree_flatten(x)
    v = []
    for leaf in leaves:
        a = np.abs(np.asarray(leaf))
        rms = float(np.sqrt(np.nanmean(a**2))) or 1.0
        size = np.where(a > 1e-9 * rms, a, rms)
        v.append(jnp.asarray(np.nan_to_num(size) * rng.standard_normal(a.shape), leaf.dtype))
    v = jax.tree_util.tree_unflatten(treedef, v)
    outputs = lambda x: _inexact_leaves(f(x))  # noqa: E731
    w = [rng.standard_normal(np.shape(o)) for o in jax.eval_shape(outputs, x)]

    @jax.jit
    def derivatives(x, v):
        y, jvp = jax.jvp(outputs, (x,), (v,))
        functional = lambda x: sum(jnp.vdot(wi, o) for wi, o in zip(w, outputs(x)))  # noqa: E731
        return y, jvp, jax.grad(functional)(x) if reverse else None

    _, jvp, grad = derivatives(x, v)
    step = lambda s: jax.tree_util.tree_map(lambda a, b: a + s * rel_step * b, x, v)  # noqa: E731
    plus, minus = derivatives(step(1.0), v)[0], derivatives(step(-1.0), v)[0]
    fd = [(np.asarray(p) - np.asarray(m)) / (2 * rel_step) for p, m in zip(plus, minus)]
    assert len(fd) > 0
    for i, (a, b) in enumerate(zip(jvp, fd)):
        a = np.asarray(a)
        assert np.all(np.isfinite(a)), f"output {i}: non-finite forward derivative"
        scale = max(float(np.max(np.abs(b), initial=0.0)), 1e-300)
        np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale, err_msg=f"output {i}")
    if reverse:
        g_leaves = [np.asarray(g) for g in jax.tree_util.tree_leaves(grad)]
        assert all(np.all(np.isfinite(g)) for g in g_leaves), "non-finite gradient"
        along_v = sum(float(np.vdot(g, d)) for g, d in zip(g_leaves, jax.tree_util.tree_leaves(v)))
        expected = sum(float(np.vdot(wi, d)) for wi, d in zip(w, fd))
        np.testing.assert_allclose(along_v, expected, rtol=rtol, err_msg="reverse mode")
    return grad


def look_at(centre, target, focal, principal=(500.0, 550.0)):
    """A camera at `centre` looking at `target` (x right, y down, z up in the world)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


# ----------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def scene():
    """Three cameras around the 19-dot box corner (built in NumPy: no compilation), pixels.

    Returns `(pinhole, distorted, world, pixels, distorted_pixels)`; `pixels` is
    `(2, 3, 19, 2)`: noise-free and with 0.3 px of noise; `distorted_pixels` noisy.
    """
    world = mc.targets.box_corner().points
    middle = world.mean(0)
    directions = np.array([[1.0, 0.8, 0.9], [0.7, 1.2, 0.8], [1.1, 1.0, 1.3]])
    poses = [look_at(middle + 800 * d / np.linalg.norm(d), middle, 0) for d in directions]
    R, t = (np.stack(a) for a in zip(*poses))
    focal = np.array([1200.0, 1500.0, 1000.0])
    pinhole = mc.Camera(focal, 1.01 * focal, [500.0, 480, 520], [550.0, 560, 530], R, t)
    distorted = eqx.tree_at(lambda c: c.dist, pinhole, jnp.broadcast_to(DIST, (3, 5)))
    noise = 0.3 * np.random.default_rng(0).standard_normal((3, 19, 2))
    exact = np.asarray(pinhole.project(world))
    pixels = jnp.asarray(np.stack([exact, exact + noise]))
    return pinhole, distorted, jnp.asarray(world), pixels, distorted.project(world) + noise


# ------------------------------------------------------------------------ the camera model
def test_project_and_derived_quantities_are_differentiable(scene):
    _, cams, world, _, _ = scene

    def f(a):
        c, w = a
        return c.project(w), c.K, c.center, c.projection_matrix(), c.depth(w)

    grad = check_derivatives(f, (cams, world), reverse=True)
    # the gradient with respect to a camera is a camera
    assert isinstance(grad[0], mc.Camera)
    assert jax.tree_util.tree_structure(grad[0]) == jax.tree_util.tree_structure(cams)
    check_derivatives(lambda m: mc.Camera.from_matrices(*m, dist=DIST), (cams.K, cams.R, cams.t))


def test_distort_and_undistort_points_are_differentiable(scene):
    # undistort_points: its derivative is the implicit one of the exact inverse (not of its
    # Newton steps), w.r.t. the pixels and every camera parameter (distortion included)
    _, cams, _, _, pixels = scene
    xy = jnp.asarray(np.random.default_rng(1).uniform(-0.5, 0.5, (20, 2)))
    check_derivatives(
        lambda a: (mc.distort(a[0], a[1]), mc.undistort_points(a[2], a[3])),
        (xy, DIST, cams, pixels),
        reverse=True,
    )


def test_image_plane_conversions_are_differentiable():
    xy = jnp.asarray(np.random.default_rng(2).normal(size=(5, 2)))
    check_derivatives(
        lambda a: (
            mc.image_to_pixel(a, (0.0045, 0.0047), image_size=(1000, 1100)),
            mc.pixel_to_image(a, (0.0045, 0.0047), center=(500, 550)),
        ),
        xy,
    )


def test_rotations_are_differentiable_also_where_the_svd_derivative_is_not():
    # rodrigues at 0 (its Taylor branch) and elsewhere; nearest_rotation of general matrices and
    # of exact rotations, whose three singular values are all 1 (there the SVD's derivative
    # divides by zero; the optimality-condition derivative is exact)
    rng = np.random.default_rng(3)
    rvec = jnp.asarray(np.concatenate([np.zeros((1, 3)), rng.normal(size=(3, 3))]))
    H = jnp.concatenate([jnp.asarray(rng.normal(size=(3, 3, 3))), mc.rodrigues(rvec)])
    check_derivatives(lambda a: (mc.rodrigues(a[0]), mc.nearest_rotation(a[1])), (rvec, H),
                      reverse=True)  # fmt: skip


# ------------------------------------------------------------------- DLT and decomposition
def test_dlt_and_decomposition_are_differentiable_and_ignore_hidden_points(scene):
    # Noise-free pixels (the DLT system's smallest singular value is zero: the derivative needs
    # only the gap to the next one; the decomposed R is orthogonal) and noisy ones (R is
    # re-orthogonalised); both decompositions (with skew, and the paper's). Two points are
    # hidden, one of them NaN: it must reach neither the values nor the derivatives.
    _, _, world, pixels, _ = scene
    hidden = [2, 11]
    mask = np.ones(pixels.shape[1:3], bool)
    mask[:, hidden] = False
    pixels = pixels.at[:, :, 2].set(jnp.nan)

    def f(a):  # what mc.calibrate does in one call
        w, p = a
        P = mc.dlt(w, p, mask)
        cameras = mc.Camera.from_projection(P)
        paper = mc.Camera.from_projection(P, skew=False)
        report = mc.reprojection_report(cameras, w, p, mask)
        # (the RMS of exactly zero residuals, a norm at 0, has no derivative: noisy ones only)
        return P, cameras, paper, report.rms[1], report.mean_x, report.mean_y

    g_world, g_pixels = check_derivatives(f, (world, pixels), reverse=True)
    assert np.all(np.asarray(g_pixels)[:, :, hidden] == 0.0)
    assert np.all(np.asarray(g_world)[hidden] == 0.0)
    assert np.all(np.abs(np.asarray(g_pixels)[:, :, mask[0]]).sum(-1) > 0)


def test_dlt_second_derivatives_are_finite_for_a_symmetric_target():
    # The eight corners of a cube seen head-on: the normalised DLT system has repeated singular
    # values besides the zero one, where JAX's SVD derivative (and so the second derivative of
    # a rule built on it) divides by zero. Hessian-vector products must equal central
    # differences of the gradient. (Found by notebook 04, which needs jacfwd inside grad.)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    world = 100.0 * corners
    h = (world + [0.0, 0.0, 800.0]) @ np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]]).T
    pixels = jnp.asarray(h[:, :2] / h[:, 2:])

    def f(p):
        return jnp.sum(mc.dlt(world, p) ** 3)

    @jax.jit
    def grad_and_hessian(p):
        # Forward over reverse, as `jax.hessian`: column k of H is the jvp of the gradient along
        # the k-th unit vector, and the primal output is the gradient, so that the differences
        # of the gradient need no second compilation.
        units = jnp.eye(p.size, dtype=p.dtype).reshape(-1, *p.shape)
        g, H = jax.vmap(lambda v: jax.jvp(jax.grad(f), (p,), (v,)))(units)
        return g[0], jnp.moveaxis(H, 0, -1).reshape(p.shape + p.shape)

    _, H = grad_and_hessian(pixels)
    assert np.isfinite(np.asarray(H)).all()
    direction = np.random.default_rng(0).standard_normal(pixels.shape)
    step = 1e-5
    fd = (grad_and_hessian(pixels + step * direction)[0]
          - grad_and_hessian(pixels - step * direction)[0]) / (2 * step)  # fmt: skip
    np.testing.assert_allclose(
        jnp.tensordot(H, direction, axes=2), fd, rtol=0, atol=1e-7 * float(jnp.abs(fd).max())
    )


# ---------------------------------------------------------------------------- registration
def test_procrustes_is_differentiable_also_at_a_symmetric_configuration():
    # Batch 0: the corners of a cube, moved exactly: the cross-covariance is a multiple of a
    # rotation, with three equal singular values, where the SVD's derivative is undefined.
    # Batch 1: random points with noise and random weights.
    rng = np.random.default_rng(5)
    cube = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * 100.0
    src = jnp.asarray(np.stack([cube, rng.normal(scale=100.0, size=(8, 3))]))
    T = mc.RigidTransform(mc.rodrigues(jnp.array([0.3, -0.2, 0.5])), jnp.array([10.0, 0, 5]))
    dst = T.apply(src) + jnp.asarray(np.stack([np.zeros((8, 3)), rng.normal(size=(8, 3))]))
    w = jnp.asarray(np.stack([np.ones(8), rng.uniform(0.5, 2.0, size=8)]))
    check_derivatives(
        lambda a: (mc.procrustes(*a), mc.procrustes_paper(a[0], a[1])), (src, dst, w), reverse=True
    )


def test_rigid_transforms_and_to_global_are_differentiable(scene):
    _, cams, world, _, _ = scene
    rng = np.random.default_rng(6)
    a = mc.RigidTransform(mc.rodrigues(jnp.asarray(rng.normal(size=3))), rng.normal(size=3))
    b = mc.RigidTransform(mc.rodrigues(jnp.asarray(rng.normal(size=3))), 100 * rng.normal(size=3))

    def f(x):
        a, b, c = x
        return (a @ b).apply(world), a.inverse().as_matrix(), mc.to_global(c, b)

    check_derivatives(f, (a, b, cams))


# --------------------------------------------------------------- reports and reconstruction
def test_reprojection_report_is_differentiable(scene):
    _, cams, world, _, pixels = scene
    mask = np.ones(pixels.shape[:2], bool)
    mask[1, :4] = False

    def report(a):
        r = mc.reprojection_report(*a, mask)
        return r.mean_x, r.mean_y, r.rms, r.max, r.residuals

    check_derivatives(report, (cams, world, pixels))


def test_triangulate_and_reproject_are_differentiable_beside_points_with_too_few_views(scene):
    # With distortion: undistortion, normalisation and the 4 x 4 eigenvector are all inside.
    # Point 0 is seen by one camera, point 1 by none: neither has a 3-D point (NaN), and they
    # must not touch the others' derivatives, forward or reverse (0 * inf in a branch that
    # `where` selects away would make every camera's gradient NaN).
    _, cams, world, _, pixels = scene
    mask = np.ones((3, 8), bool)
    mask[1:, 0] = False
    mask[:, 1] = False

    def f(a):
        c, px, w = a
        good = mc.triangulate(c, px, mask).points[2:]
        return good, mc.reproject(c, w), mc.reproject(c, good)

    g_cams, g_px, _ = check_derivatives(f, (cams, pixels[:, :8], world), reverse=True)
    assert np.all(np.asarray(g_px)[:, :2] == 0.0)


def test_triangulate_is_differentiable_in_a_distortion_that_is_zero(scene):
    # A rig without distortion skips undistortion; its derivative in the coefficients must stay
    # (gradient descent on them from zero, as usual, never moved: a JAX user's trial)
    cams, _, _, pixels, _ = scene
    grad = check_derivatives(lambda a: mc.triangulate(*a).points, (cams, pixels[1]), reverse=True)
    assert float(jnp.abs(grad[0].dist).max()) > 0


@pytest.mark.parametrize("refine", [False, True])
def test_diagnostics_and_refined_points_are_differentiable_beside_points_seen_once(scene, refine):
    # A point seen once had a stand-in position at its camera's centre: zero depth and a zero
    # ray gave NaN partials behind the `where` that makes its `rms` and `angle` NaN (and arccos'
    # slope at its cosine of 1 is infinite), so the others' gradients were NaN; and its
    # refinement, an underdetermined least squares, made lineax raise in the backward pass.
    _, cams, _, _, pixels = scene
    one_view = np.ones((3, 8), bool)
    one_view[1:, 0] = False

    def loss(c):
        tri = mc.triangulate(c, pixels[:, :8], one_view, refine=refine)
        return jnp.sum(tri.points[1:]) + jnp.sum(tri.rms[1:]) + jnp.sum(tri.angle[1:])

    grad = jax.grad(loss)(cams)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree_util.tree_leaves(grad))
    assert np.isnan(mc.triangulate(cams, pixels[:, :8], one_view).rms[0])


def test_triangulate_with_refinement_is_differentiable(scene):
    # The polished point is the minimum of its reprojection error: implicit derivative. The
    # solver stops at a relative step of 1e-10, so the differences take a larger step.
    _, cams, _, _, pixels = scene
    check_derivatives(
        lambda p: mc.triangulate(cams, p, refine=True).points, pixels[:, :3], rel_step=1e-4,
        rtol=1e-4,
    )  # fmt: skip


def test_refine_gradient_is_implicit_and_ignores_the_seed():
    """The refined camera is a function of the data only: implicit differentiation through the
    optimum gives the pixels' influence, and zero for the seed's free parameters."""
    world = mc.targets.box_corner_grid(3).points
    R, t = look_at(world.mean(0) + np.array([500.0, 400.0, 450.0]), world.mean(0), 0)
    truth = mc.Camera(1100.0, 1110.0, 510.0, 540.0, R, t, dist=DIST)
    noise = 0.3 * np.random.default_rng(7).standard_normal((len(world), 2))
    pixels = truth.project(world) + noise
    seed = eqx.tree_at(lambda c: (c.alpha_u, c.dist), truth, (1.01 * truth.alpha_u, jnp.zeros(5)))
    # Gauss-Newton converges to rounding here, so the finite differences measure the optimum's
    # motion rather than where Levenberg-Marquardt's iterations happen to stop; the implicit
    # derivative is the same whichever solver found the optimum.
    solver = optx.GaussNewton(rtol=1e-12, atol=1e-12)
    w = np.random.default_rng(8).standard_normal(5)

    def f(seed, px):
        out = mc.refine(seed, world, px, distortion=("k1", "k2"), solver=solver)
        c = out.cameras
        return jnp.vdot(w, jnp.stack([c.alpha_u, c.v0, c.dist[0], c.t[2], c.R[0, 2]])), out.ok

    value_and_grad = jax.jit(jax.value_and_grad(f, argnums=(0, 1), has_aux=True))
    (_, ok), (g_seed, g_px) = value_and_grad(seed, pixels)
    assert bool(ok)
    v = np.random.default_rng(9).standard_normal(pixels.shape)
    h = 1e-5  # px
    at = lambda s: float(value_and_grad(seed, pixels + s * h * v)[0][0])  # noqa: E731
    np.testing.assert_allclose(np.vdot(g_px, v), (at(1) - at(-1)) / (2 * h), rtol=1e-6)
    # The seed's free parameters have no influence on the optimum, nor has a rotation of the
    # seed's R (the tangent hat(omega) R); the fixed ones (p1, p2, k3) are held at the seed's
    # values and do; the skew of the zero-skew model is zero whatever the seed's.
    for name in ("alpha_u", "alpha_v", "u0", "v0", "t"):
        np.testing.assert_allclose(getattr(g_seed, name), 0.0, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(g_seed.dist[:2], 0.0, atol=1e-9)
    for omega in np.eye(3):
        tangent = np.cross(omega, np.asarray(seed.R), axisb=0, axisc=0)  # hat(omega) @ R
        assert abs(np.vdot(g_seed.R, tangent)) < 1e-9 * np.abs(g_seed.R).max()
    assert np.abs(g_seed.dist[2:]).max() > 0 and float(g_seed.skew) == 0.0


@pytest.mark.parametrize("fix", [(), "principal_point"])
def test_calibrate_with_refinement_is_differentiable_whatever_it_holds(fix):
    """`calibrate(..., refine=...)`: the refined cameras' derivatives by the pixels equal central
    differences. With nothing held at the DLT's values the seed's derivatives are not carried
    through the solve (they cancel: `_pipeline._seed_is_forgotten`); with the principal point
    held at the DLT's, they are, and reach the answer through it."""
    rig = mc.synthetic.random_rig(jax.random.key(3), n_cameras=3, noise=0.3)
    world, pixels, mask = rig.world, rig.pixels, np.asarray(rig.mask)
    # (Gauss-Newton to rounding: the differences measure the optimum, not where a solve stopped)
    options = dict(fix=fix, solver=optx.GaussNewton(rtol=1e-12, atol=1e-12))
    w = np.random.default_rng(3).standard_normal((3, 5))

    def f(px):
        c = mc.calibrate(world, px, mask, refine=options).cameras
        return jnp.vdot(w, jnp.stack([c.alpha_u, c.u0, c.v0, c.center[:, 0], c.dist[:, 0]], -1))

    value_and_grad = jax.jit(jax.value_and_grad(f))
    g = value_and_grad(pixels)[1]
    v = np.random.default_rng(4).standard_normal(pixels.shape) * mask[..., None]
    h = 1e-5  # px
    at = lambda s: float(value_and_grad(pixels + s * h * v)[0])  # noqa: E731
    np.testing.assert_allclose(np.vdot(g, v), (at(1) - at(-1)) / (2 * h), rtol=1e-6)


@pytest.mark.parametrize("failure", ["sees nothing", "sees 5 points", "sees a plane"])
@pytest.mark.parametrize("refine", [False, True])
def test_a_failed_camera_leaves_the_others_world_gradient_alone(failure, refine):
    """A JAX user's trial: one camera of a rig that fails (sees nothing, too few points, only
    a plane) made `jax.grad` of a healthy camera's centre with respect to the shared world
    points NaN in every entry; `jax.jacfwd` was right. Now it equals the gradient of the rig
    without that camera."""
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=4, noise=0.3)
    world, pixels, mask = rig.world, rig.pixels, np.asarray(rig.mask).copy()
    floor = np.abs(np.asarray(world)[:, 0] - np.asarray(world)[:, 0].min()) < 1e-9
    mask[3] = {"sees nothing": False, "sees 5 points": np.arange(19) < 5, "sees a plane": floor}[
        failure
    ]
    status = mc.calibrate(world, pixels, mask).status
    assert int(status[3]) != mc.Status.OK and (np.asarray(status[:3]) == mc.Status.OK).all()

    def centre_x(w, pixels, mask):
        return mc.calibrate(w, pixels, mask, refine=refine).cameras.center[0, 0]

    mask = jnp.asarray(mask)  # (as a JAX array, as the trial had it)
    gradient = jax.grad(centre_x)(world, pixels, mask)
    alone = jax.grad(centre_x)(world, pixels[:3], mask[:3])
    assert np.isfinite(np.asarray(gradient)).all()
    np.testing.assert_allclose(gradient, alone, rtol=1e-7, atol=1e-10 * np.abs(alone).max())


def test_refine_gradient_in_float32_is_float64s():
    """A user's trial: in float32 (JAX's default), the gradient of a refined camera's centre
    with respect to its pixels came out 73-78 % off float64's, signs flipped, once distortion
    was estimated: the implicit derivatives' pseudo-inverse dropped the distortion directions
    (`_refine._adjoint`). The same inputs (rounded to float32) in both precisions: within 2 %."""
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=8, noise=0.3)
    data = [np.asarray(x, np.float32) for x in (rig.world, rig.pixels)]
    mask = np.asarray(rig.mask)
    gradients = []
    for dtype in (np.float64, np.float32):
        world, pixels = (jnp.asarray(x, dtype) for x in data)
        seed = mc.calibrate(world, pixels, mask).cameras

        def centre_x(px, seed=seed, world=world):
            return mc.refine(seed, world, px, mask).cameras.center[0, 0]

        gradient = jax.grad(centre_x)(pixels)
        assert gradient.dtype == dtype
        gradients.append(np.asarray(gradient, np.float64))
    g64, g32 = gradients
    assert np.abs(g32 - g64).max() < 0.02 * np.abs(g64).max()


# ------------------------------------------------------------------------ pytrees compose
def test_camera_and_transform_are_pytrees(scene):
    _, cams, world, _, _ = scene
    T = mc.RigidTransform(mc.rodrigues(jnp.array([0.1, 0.2, 0.3])), jnp.array([1.0, 2, 3]))
    for tree in (cams, T):
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        back = jax.tree_util.tree_unflatten(treedef, leaves)
        assert type(back) is type(tree)
        assert all(np.array_equal(a, b) for a, b in zip(leaves, jax.tree_util.tree_leaves(back)))
    doubled = jax.tree_util.tree_map(lambda x: 2 * x, cams)
    np.testing.assert_allclose(doubled.alpha_u, 2 * cams.alpha_u)


def test_filter_jit_and_filter_vmap_see_through_cameras(scene):
    _, cams, world, _, _ = scene
    expected = np.asarray(cams.project(world))
    project = eqx.filter_jit(lambda c, w: c.project(w))
    np.testing.assert_allclose(project(cams, world), expected, rtol=1e-12)
    # one camera in the function, the rig's axis by vmap: the same as the batched call
    one_by_one = eqx.filter_vmap(lambda c: c.project(world))(cams)
    np.testing.assert_allclose(one_by_one, expected, rtol=1e-12)
    # one transform per camera, vmapped together with the cameras
    T = mc.RigidTransform(mc.rodrigues(0.2 * jnp.eye(3)), 10.0 * jnp.eye(3))
    moved = eqx.filter_vmap(lambda t, c: mc.to_global(c, t).project(t.apply(world)))(T, cams)
    np.testing.assert_allclose(moved, expected, rtol=1e-9)
    # per-camera gradients: vmap of grad over the rig, jitted; a Camera comes back
    grads = eqx.filter_jit(jax.vmap(jax.grad(lambda c: jnp.sum(c.project(world)))))(cams)
    assert isinstance(grads, mc.Camera) and grads.batch_shape == (3,)
    np.testing.assert_allclose(
        grads.u0, np.full(3, len(world)), rtol=1e-12
    )  # d(sum of pixels)/du0 = N


def test_fitting_a_rig_inside_a_users_own_loss(scene):
    """A user's loss on top of Camera.project (a pseudo-Huber reprojection error of their own),
    minimised by plain gradient steps: no optimistix, no optax."""
    _, cams, world, _, pixels = scene
    # start from the true rig, each camera turned by ~1 degree and moved by ~1 %
    rng = np.random.default_rng(6)
    start = eqx.tree_at(
        lambda c: (c.R, c.t),
        cams,
        (
            mc.rodrigues(jnp.asarray(rng.normal(scale=0.01, size=(3, 3)))) @ cams.R,
            cams.t * (1 + 0.01 * rng.normal(size=(3, 1))),
        ),
    )
    distance = jnp.linalg.norm(start.t, axis=-1, keepdims=True)

    # parameters: an axis-angle increment per camera (so that R stays a rotation) and the
    # translation in units of the camera's distance
    def rig_from(params):
        R = mc.rodrigues(params["w"]) @ start.R
        return eqx.tree_at(lambda c: (c.R, c.t), start, (R, start.t + params["t"] * distance))

    def loss(params):
        r = rig_from(params).project(world) - pixels
        return jnp.mean(jnp.sqrt(1.0 + jnp.sum(r * r, -1)) - 1.0)

    params = {"w": jnp.zeros((3, 3)), "t": jnp.zeros((3, 3))}
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    history = []
    for _ in range(50):
        value, g = value_and_grad(params)
        history.append(float(value))
        params = jax.tree_util.tree_map(lambda p, d: p - 3e-6 * d, params, g)
    history.append(float(loss(params)))
    print(f"user loss {history[0]:.3f} -> {history[-1]:.3f}")
    assert np.all(np.diff(history) < 0)
    assert history[-1] < 0.6 * history[0]

    def angle(c):  # radians from the true rotation
        return np.arccos((np.trace(c.R @ np.swapaxes(cams.R, -1, -2), axis1=1, axis2=2) - 1) / 2)

    assert np.mean(angle(rig_from(params))) < 0.9 * np.mean(angle(start))


# ------------------------------------------------------------------------ whole-rig solvers
def check_directional(f, x, direction, *, step=1e-4, rtol=1e-5):
    """`jax.jvp` and `jax.grad` of the scalar `f` at `x` along `direction` against a central
    difference, without `jit` (these entry points validate their input eagerly).

    `f` returns `(value, aux)`. As in `check_derivatives`, the values for the difference come
    from the program that computes the forward derivative (its primal output), so that `f`
    itself is not compiled a third time. Returns `aux` at `x`."""
    at = lambda x: jax.jvp(f, (x,), (direction,), has_aux=True)  # noqa: E731
    _, jvp, aux = at(x)
    grad, _ = jax.grad(f, has_aux=True)(x)
    assert np.isfinite(np.asarray(grad)).all()
    fd = (at(x + step * direction)[0] - at(x - step * direction)[0]) / (2 * step)
    np.testing.assert_allclose(float(jvp), float(fd), rtol=rtol)
    np.testing.assert_allclose(float(jnp.vdot(grad, direction)), float(fd), rtol=rtol)
    return aux


def test_refine_rig_is_differentiable_through_its_optimum():
    rig = mc.synthetic.random_rig(jax.random.key(2), n_cameras=3, noise=0.3)
    seed = mc.calibrate(rig.world, rig.pixels).cameras
    seed = eqx.tree_at(lambda c: c.skew, seed, jnp.zeros(3))
    solver = optx.GaussNewton(rtol=1e-12, atol=1e-12)  # converges to rounding here
    w = np.random.default_rng(1).standard_normal(3)

    def f(pixels):
        c = mc.refine_rig(seed, rig.world, pixels, distortion=("k1",), solver=solver).cameras
        return jnp.vdot(w, jnp.stack([c.alpha_u[1], c.dist[0, 0], c.t[2, 2]])), None

    direction = jnp.asarray(np.random.default_rng(2).standard_normal(rig.pixels.shape))
    check_directional(f, rig.pixels, direction)


def test_refine_rig_matrix_free_gradient_equals_the_dense_one(monkeypatch):
    # Large rigs solve each step by block-preconditioned LSMR; the derivative is the implicit
    # one at the optimum, as on the dense path.
    rig = mc.synthetic.random_rig(jax.random.key(2), n_cameras=3, noise=0.3)
    seed = mc.calibrate(rig.world, rig.pixels).cameras
    seed = eqx.tree_at(lambda c: c.skew, seed, jnp.zeros(3))
    w = np.random.default_rng(1).standard_normal(3)

    def f(pixels):
        c = mc.refine_rig(seed, rig.world, pixels, distortion=("k1",)).cameras
        return jnp.vdot(w, jnp.stack([c.alpha_u[1], c.dist[0, 0], c.t[2, 2]]))

    dense = jax.grad(f)(rig.pixels)
    monkeypatch.setattr(mc._bundle, "TARGET_DENSE_LIMIT", 0)  # the matrix-free path
    free = jax.grad(f)(rig.pixels)
    assert np.isfinite(np.asarray(free)).all()
    np.testing.assert_allclose(free, dense, atol=1e-6 * float(jnp.max(jnp.abs(dense))))


def _planar_scene():
    """Four views of a 7 x 5 grid (30 mm) with radial distortion and 0.3 px of noise, one point
    hidden: `(grid, pixels, mask)`."""
    grid = np.array([[x, y] for y in range(5) for x in range(7)], float) * 30.0
    views = []
    for rvec, centre in (
        ([0.4, 0.1, 0.0], [-90, -60, 700]),
        ([-0.35, 0.2, 0.1], [-80, -70, 650]),
        ([0.1, 0.45, -0.1], [-100, -50, 720]),
        ([0.2, -0.4, 0.2], [-85, -65, 680]),
    ):
        R = np.asarray(mc.rodrigues(jnp.asarray(rvec)))
        camera = mc.Camera(900.0, 905.0, 320.0, 240.0, R, np.asarray(centre, float),
                           dist=jnp.array([-0.2, 0.1, 0.0, 0.0, 0.0]))  # fmt: skip
        views.append(np.asarray(camera.project(np.c_[grid, np.zeros(len(grid))])))
    pixels = np.stack(views) + 0.3 * np.random.default_rng(3).standard_normal((4, len(grid), 2))
    mask = np.ones(pixels.shape[:2], bool)
    mask[1, 5] = False
    return grid, pixels, mask


@pytest.mark.parametrize(("whole", "fix"), [(True, ()), (False, ()), (False, "principal_point")])
def test_calibrate_planar_is_differentiable_through_its_optimum(whole, fix):
    # Zhang's method on four views of a 7 x 5 grid with radial distortion. The fixed parameters
    # (skew, p1, p2, k3) are zero columns of the Jacobian, which made the implicit derivative's
    # linear solve return NaN (fixed: a least-squares solve). One point hidden. `whole`: an
    # optimistix solver on the whole problem; else the default step, which eliminates the views'
    # poses (`_planar._refine_as_rig`, the fixed parameters pinned by residuals of their own).
    # With the principal point held at the closed form's, the closed form's derivatives reach
    # the answer through it (else they are not carried: `_planar._forgets_its_start`).
    grid, pixels, mask = _planar_scene()
    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12) if whole else None
    w = np.random.default_rng(1).standard_normal(4)

    def f(px):
        out = mc.calibrate_planar(grid, px, mask, solver=solver, fix=fix)
        c = out.camera
        return jnp.vdot(w, jnp.stack([out.K[0, 0], out.K[1, 2], c.dist[0, 0], c.t[1, 2]])), out

    direction = np.random.default_rng(2).standard_normal(pixels.shape) * mask[..., None]
    # A step of 1e-3 px: the solver stops within ~1e-8 of the optimum, which a central difference
    # divides by the step (at 1e-4 px that noise alone was 0.7-1.6e-4 of the derivative,
    # depending on the last bits of the data; at 1e-3, 3-5e-6 with the truncation error).
    out = check_directional(f, jnp.asarray(pixels), jnp.asarray(direction), step=1e-3, rtol=1e-4)
    assert int(out.result) == 0  # converged
