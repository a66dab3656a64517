import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest
from conftest import box_corners_with_wild_dots

import mvcalib as mc
import mvcalib._bundle  # noqa: F401 (mc._bundle, patched below before any call imports it)
from mvcalib._refine import LevenbergMarquardt


def grid_rig(seed, n_cameras, noise=0.3, same_intrinsics=False):
    target = mc.targets.box_corner_grid(5)
    rig = mc.synthetic.random_rig(
        jax.random.key(seed), n_cameras=n_cameras, target=target, noise=noise, fill=(0.8, 0.95)
    )
    if same_intrinsics:  # one physical camera seen in several snapshots
        cams = rig.cameras
        cams = eqx.tree_at(
            lambda c: (c.alpha_u, c.alpha_v, c.u0, c.v0),
            cams,
            tuple(jnp.full(n_cameras, v) for v in (1400.0, 1392.0, 512.0, 541.0)),
        )
        _, pixels, mask = mc.synthetic.observe(
            jax.random.key(seed + 1), cams, rig.world, noise, rig.image_size
        )
        rig = eqx.tree_at(lambda r: (r.cameras, r.pixels, r.mask), rig, (cams, pixels, mask))
    return target, rig


def zero_skew(c):
    return eqx.tree_at(lambda c: c.skew, c, jnp.zeros_like(c.skew))


def anchored_rig():
    """A rig, its target's placement from noisy measured anchors (Procrustes), and the DLT seed
    in the global frame: (rig, seed, T, anchors)."""
    target, rig = grid_rig(0, 6)
    rng = np.random.default_rng(0)
    measured = target.global_points + rng.normal(scale=0.2, size=target.global_points.shape)
    ids = np.arange(0, len(target.points), 4)
    T = mc.procrustes(target.points[ids], measured[ids])
    seed = mc.to_global(zero_skew(mc.calibrate(rig.world, rig.pixels, rig.mask).cameras), T)
    return rig, seed, T, (ids, measured[ids])


def test_joint_rig_with_registration_equals_refine_plus_procrustes():
    rig, seed, T, anchors = anchored_rig()
    cal = mc.calibrate(rig.world, rig.pixels, rig.mask)
    joint = mc.refine_rig(seed, rig.world, rig.pixels, rig.mask, transform=T, anchors=anchors,
                          anchor_sigma=0.2, distortion=())  # fmt: skip
    alone = mc.refine(zero_skew(cal.cameras), rig.world, rig.pixels, rig.mask, distortion=())
    assert bool(joint.ok)
    # with a known target the problem separates: the registration is Procrustes on the anchors
    # and every camera is its own refinement, moved into the global frame
    np.testing.assert_allclose(joint.transform.R, T.R, atol=1e-9)
    np.testing.assert_allclose(joint.transform.t, T.t, atol=1e-6)
    np.testing.assert_allclose(joint.rms_after, alone.rms_after, rtol=1e-7)
    moved = mc.to_global(alone.cameras, T)
    np.testing.assert_allclose(joint.cameras.alpha_u, moved.alpha_u, rtol=1e-7)
    np.testing.assert_allclose(joint.cameras.center, moved.center, atol=1e-4)


def test_fix_aspect_ratio_in_a_joint_rig_is_each_cameras_own(monkeypatch):
    """`fix="aspect_ratio"`: a joint rig of a known target is each camera's own refinement with
    the ratio held (`mc.refine`, checked against OpenCV), dense or matrix-free; with shared
    intrinsics the ratio is the first camera's; in bundle adjustment each seed's."""
    rig, seed, T, anchors = anchored_rig()
    cal = mc.calibrate(rig.world, rig.pixels, rig.mask)
    ratio = np.asarray(seed.alpha_u / seed.alpha_v)
    options = dict(transform=T, anchors=anchors, anchor_sigma=0.2, distortion=())
    joint = mc.refine_rig(seed, rig.world, rig.pixels, rig.mask, fix="aspect_ratio", **options)
    alone = mc.refine(zero_skew(cal.cameras), rig.world, rig.pixels, rig.mask, distortion=(),
                      fix="aspect_ratio")  # fmt: skip
    assert bool(joint.ok) and bool(alone.ok.all())
    np.testing.assert_allclose(joint.cameras.alpha_u / joint.cameras.alpha_v, ratio, rtol=1e-12)
    np.testing.assert_allclose(joint.rms_after, alone.rms_after, rtol=1e-7)
    np.testing.assert_allclose(joint.cameras.alpha_v, alone.cameras.alpha_v, rtol=1e-7)
    assert np.all(np.abs(np.asarray(joint.cameras.alpha_v / seed.alpha_v) - 1) > 1e-6)
    monkeypatch.setattr(mc._bundle, "TARGET_DENSE_LIMIT", 0)  # the matrix-free steps
    free = mc.refine_rig(seed, rig.world, rig.pixels, rig.mask, fix="aspect_ratio", **options)
    monkeypatch.undo()
    np.testing.assert_allclose(free.cameras.alpha_u / free.cameras.alpha_v, ratio, rtol=1e-12)
    np.testing.assert_allclose(free.cameras.alpha_v, joint.cameras.alpha_v, rtol=1e-7)
    # one camera in several snapshots: its ratio is the first snapshot's
    _, one = grid_rig(2, 6, same_intrinsics=True)
    snapshots = zero_skew(mc.calibrate(one.world, one.pixels, one.mask).cameras)
    shared = mc.refine_rig(snapshots, one.world, one.pixels, one.mask, fix="aspect_ratio",
                           shared_intrinsics=True, distortion=())  # fmt: skip
    assert bool(shared.ok)
    first = float(snapshots.alpha_u[0] / snapshots.alpha_v[0])
    np.testing.assert_allclose(shared.cameras.alpha_u / shared.cameras.alpha_v, first, rtol=1e-12)
    assert np.all(np.asarray(shared.cameras.alpha_v) == float(shared.cameras.alpha_v[0]))
    # bundle adjustment: the points free too (the rows by forward mode, `_bundle_normal`)
    world = np.asarray(rig.world)
    rough = world + np.random.default_rng(1).normal(scale=0.5, size=world.shape)  # mm
    start = zero_skew(mc.calibrate(rough, rig.pixels, rig.mask).cameras)
    ids = np.arange(0, len(world), 5)
    ba = mc.refine_rig(start, rough, rig.pixels, rig.mask, anchors=(ids, world[ids]),
                       anchor_sigma=0.05, points="free", distortion=(),
                       fix="aspect_ratio")  # fmt: skip
    assert bool(ba.ok)
    np.testing.assert_allclose(ba.cameras.alpha_u / ba.cameras.alpha_v,
                               start.alpha_u / start.alpha_v, rtol=1e-12)  # fmt: skip
    assert np.all(np.asarray(ba.rms_after) < np.asarray(ba.rms_before))


def test_free_points_bundle_adjustment_recovers_the_target():
    target, rig = grid_rig(1, 8)
    rng = np.random.default_rng(1)
    rough = np.asarray(rig.world) + rng.normal(scale=0.5, size=rig.world.shape)  # mm
    cal = mc.calibrate(rough, rig.pixels, rig.mask)
    ids = np.arange(0, len(target.points), 5)
    out = mc.refine_rig(zero_skew(cal.cameras), rough, rig.pixels, rig.mask,
                        anchors=(ids, np.asarray(rig.world)[ids]), anchor_sigma=0.05,
                        points="free", distortion=())  # fmt: skip
    assert bool(out.ok), out.messages()
    before = np.abs(rough - np.asarray(rig.world)).mean()
    after = np.abs(np.asarray(out.world - rig.world)).mean()
    print(f"point error {before:.3f} -> {after:.3f} mm, RMS {np.asarray(out.rms_after).mean():.3f}")
    assert after < before / 4
    assert np.all(np.asarray(out.rms_after) < 0.45)  # 0.3 px noise: ~0.41 at the optimum
    assert np.all(np.asarray(out.rms_before) > 1.0)


def test_shared_intrinsics_pool_all_snapshots():
    target, rig = grid_rig(2, 6, same_intrinsics=True)
    cal = mc.calibrate(rig.world, rig.pixels, rig.mask)
    alone = mc.refine(zero_skew(cal.cameras), rig.world, rig.pixels, rig.mask, distortion=())
    joint = mc.refine_rig(zero_skew(cal.cameras), rig.world, rig.pixels, rig.mask,
                          shared_intrinsics=True, distortion=())  # fmt: skip
    assert bool(joint.ok)
    f = np.asarray(joint.cameras.alpha_u)
    assert np.all(f == f[0])  # one camera
    err_joint = abs(f[0] / 1400.0 - 1)
    err_alone = np.abs(np.asarray(alone.cameras.alpha_u) / 1400.0 - 1)
    print(f"focal error joint {err_joint:.5f}, per snapshot {err_alone.round(5)}")
    assert err_joint < np.mean(err_alone)
    assert err_joint < 0.002


def test_a_robust_loss_sets_wild_points_aside_in_few_steps():
    """4 box-corner cameras (`random_rig` key 0), two of each camera's dots moved by 50 px: least
    squares ends with focal lengths up to 12 % from those of the clean dots' solve; `Cauchy(1.0)`
    within 0.5 %, in 16 steps (32 until 2026-12-05, when the steps' Gauss–Newton model was that
    of the residuals scaled by `sqrt(rho / r^2)`; now Ceres', `_refine._irls`)."""
    rig, world, pixels, mask, _ = box_corners_with_wild_dots(4)
    clean = np.asarray(rig.pixels)
    reference = mc.refine_rig(mc.calibrate(world, clean, mask).cameras, world, clean, mask)
    error = lambda r: np.abs(np.asarray(r.cameras.alpha_u / reference.cameras.alpha_u) - 1).max()  # noqa: E731
    seed = mc.calibrate(world, pixels, mask, max_relative_rms=np.inf).cameras  # (every one)
    assert error(mc.refine_rig(seed, world, pixels, mask)) > 0.05
    robust = mc.refine_rig(seed, world, pixels, mask, loss=mc.Cauchy(1.0))
    assert int(robust.result) == 0 and int(robust.iterations) <= 20
    assert error(robust) < 5e-3


def test_optimistix_lm_steps_take_the_robust_model_too():
    """The matrix-free solver of large rigs is optimistix's LM (`_refine.LevenbergMarquardt`):
    with a loss its steps linearise Ceres' model as `SecantLM`'s do (`options["model"]`). On
    4 cameras with wild dots (key 1), `Huber(1.0)` takes 25 steps against 40 when it linearised
    the weighted residuals, to the default solver's answer."""
    rig, world, pixels, mask, _ = box_corners_with_wild_dots(4, key=1)
    seed = mc.calibrate(world, pixels, mask, max_relative_rms=np.inf).cameras
    lm = mc.refine_rig(seed, world, pixels, mask, loss=mc.Huber(1.0),
                       solver=LevenbergMarquardt(rtol=1e-7, atol=1e-7))  # fmt: skip
    default = mc.refine_rig(seed, world, pixels, mask, loss=mc.Huber(1.0))
    assert int(lm.result) == 0 and int(lm.iterations) <= 30
    np.testing.assert_allclose(lm.cameras.alpha_u, default.cameras.alpha_u, rtol=1e-7)
    np.testing.assert_allclose(lm.rms_after, default.rms_after, rtol=1e-7)


def test_refine_rig_input_errors():
    target, rig = grid_rig(3, 2)
    cal = mc.calibrate(rig.world, rig.pixels, rig.mask)
    with pytest.raises(ValueError, match="free points need `anchors`"):
        mc.refine_rig(cal.cameras, rig.world, rig.pixels, points="free")
    with pytest.raises(ValueError, match="rig of 2 cameras"):
        mc.refine_rig(cal.cameras[0], rig.world, rig.pixels)
    with pytest.raises(ValueError, match='"fixed" or "free"'):
        mc.refine_rig(cal.cameras, rig.world, rig.pixels, points="loose")
    nan = jax.tree_util.tree_map(lambda x: x * np.nan, cal.cameras)
    with pytest.raises(ValueError, match="no camera of the rig has a finite seed"):
        mc.refine_rig(nan, rig.world, rig.pixels)


def _rig_with_an_unsolved_camera():
    """`anchored_rig` where camera 2 sees only the target's face z = 0, so that `calibrate`
    cannot solve it (DEGENERATE: its seed is NaN): (rig, seed, mask, keywords)."""
    rig, _, T, anchors = anchored_rig()
    mask = np.asarray(rig.mask).copy()
    mask[2] &= np.asarray(rig.world)[:, 2] == 0
    cal = mc.calibrate(rig.world, rig.pixels, mask)
    assert int(cal.status[2]) == mc.Status.DEGENERATE and bool(cal.ok[np.arange(6) != 2].all())
    seed = mc.to_global(zero_skew(cal.cameras), T)
    return rig, seed, mask, dict(transform=T, anchors=anchors, anchor_sigma=0.2)


@pytest.mark.parametrize("path", ["dense", "matrix-free"])
def test_a_camera_calibrate_could_not_solve_takes_no_part(monkeypatch, path):
    # calibrate, then refine the rig: a camera the DLT could not solve has a NaN seed, which
    # made the whole rig fail (256 steps on the dense path, NaN matrix-free). It takes no part
    # now, comes back NaN, and the others are refined as they are without it (the cameras are
    # coupled here through the placement of the target, which the anchors determine).
    rig, seed, mask, kwargs = _rig_with_an_unsolved_camera()
    if path == "matrix-free":
        monkeypatch.setattr(mc._bundle, "TARGET_DENSE_LIMIT", 0)
    out = mc.refine_rig(seed, rig.world, rig.pixels, mask, distortion=("k1",), **kwargs)
    keep = np.arange(6) != 2
    alone = mc.refine_rig(
        seed[keep], rig.world, rig.pixels[keep], mask[keep], distortion=("k1",), **kwargs
    )
    assert bool(out.ok) and bool(alone.ok), (out.messages(), alone.messages())
    np.testing.assert_array_equal(out.used, keep)
    assert "cameras [2] took no part" in out.messages()
    assert np.isnan(out.cameras.alpha_u[2]) and np.isnan(out.cameras.R[2]).all()
    assert np.isnan(out.rms_before[2]) and np.isnan(out.rms_after[2])
    np.testing.assert_allclose(out.rms_after[keep], alone.rms_after, rtol=1e-9)
    np.testing.assert_allclose(out.cameras.alpha_u[keep], alone.cameras.alpha_u, rtol=1e-7)
    np.testing.assert_allclose(out.transform.t, alone.transform.t, atol=1e-6)


def test_gradients_are_finite_beside_cameras_that_take_no_part():
    # The implicit derivative solves with the Jacobian at the optimum, which a camera without a
    # visible point (or without a finite seed) left singular: lineax raised. Such a camera's
    # parameters are held at their seed by a residual of their own now; the others' gradient
    # is the one of the rig without it.
    rig, seed, mask, kwargs = _rig_with_an_unsolved_camera()
    keep = np.arange(6) != 2
    hidden = mask.copy()
    hidden[4] = False  # and a camera with a finite seed that sees nothing

    def loss(pixels, seed, mask):
        out = mc.refine_rig(seed, rig.world, pixels, mask, distortion=("k1",), **kwargs)
        return jnp.nansum(out.rms_after)

    grad = jax.grad(loss)(rig.pixels, seed, hidden)
    assert np.isfinite(grad).all()
    assert not np.asarray(grad[2]).any() and not np.asarray(grad[4]).any()
    expected = jax.grad(loss)(rig.pixels[keep], seed[keep], hidden[keep])
    np.testing.assert_allclose(grad[keep], expected, rtol=1e-6, atol=1e-9)


def test_bundle_adjust_from_tracks_alone_recovers_perturbed_cameras():
    # No target: tracks of 48 points seen by 5 cameras, the cameras' poses and focal lengths
    # perturbed; rounds of triangulate / refine bring the reprojection error to the noise.
    rig = mc.synthetic.random_rig(jax.random.key(30), 5, mc.targets.box_corner_grid(4))
    noisy = np.asarray(rig.pixels) + 0.3 * np.random.default_rng(30).standard_normal(
        rig.pixels.shape
    )
    noisy[0, :3] += 40.0  # three wrong detections
    start = eqx.tree_at(
        lambda c: (c.t, c.alpha_u),
        rig.cameras,
        (rig.cameras.t + 3.0, rig.cameras.alpha_u * 1.02),
    )
    mask = np.asarray(rig.mask)
    out = mc.bundle_adjust(start, noisy, mask, distortion=(), thresholds=(50.0, 3.0), max_points=48)
    assert [r["threshold"] for r in out.rounds] == [50.0, 3.0]
    # the last round keeps fewer points, padded to the first round's size (one compilation)
    assert out.rounds[1]["points"] < out.rounds[0]["points"] == out.refinement.world.shape[0]
    # The wrong detections are dropped (with their tracks: a 40 px error drags the linear
    # triangulation of the point off all its views; measured 225 of 240 observations kept).
    assert 200 <= out.rounds[-1]["observations"] <= mask.sum() - 3
    assert out.rounds[0]["before"] > 1.0 and out.rounds[-1]["after"] < 0.4
    # Tracks alone pin focal lengths only loosely (the scene's scale and shape are free too,
    # held by four soft anchors at their first, perturbed positions): measured within 1.6 %.
    np.testing.assert_allclose(out.cameras.alpha_u, rig.cameras.alpha_u, rtol=0.03)


def test_bundle_adjust_leaves_out_a_camera_without_parameters():
    # One camera of the starting rig is NaN (not calibrated): its tracks used to make every
    # triangulated point NaN, and the first round stopped with "keeps 0 points".
    rig = mc.synthetic.random_rig(jax.random.key(32), 5, mc.targets.box_corner_grid(4))
    noisy = np.asarray(rig.pixels) + 0.3 * np.random.default_rng(32).standard_normal(
        rig.pixels.shape
    )
    start = eqx.tree_at(lambda c: c.alpha_u, rig.cameras, rig.cameras.alpha_u.at[1].set(np.nan))
    out = mc.bundle_adjust(start, noisy, distortion=(), thresholds=(5.0,), max_steps=10)
    np.testing.assert_array_equal(out.refinement.used, [True, False, True, True, True])
    assert np.isnan(out.cameras.alpha_u[1]) and np.isfinite(np.delete(out.cameras.alpha_u, 1)).all()
    assert out.rounds[0]["observations"] == 4 * 48 and out.rounds[0]["after"] < 0.4


def test_bundle_adjust_and_aniposelib_files_refuse_bad_input(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(31), 3)
    with pytest.raises(ValueError, match=r"\(C, N, 2\)"):
        mc.bundle_adjust(rig.cameras, rig.pixels[:2])
    with pytest.raises(ValueError, match="seen by >= 3"):
        mc.bundle_adjust(rig.cameras, np.full(rig.pixels.shape, np.nan))
    off = np.asarray(rig.pixels) + 100.0  # every observation beyond the threshold
    with pytest.raises(ValueError, match="keeps 0 points"):
        mc.bundle_adjust(rig.cameras, off, thresholds=(5.0,))
    # cameras that see a mirrored world (the Oxford house's): every point behind them
    c = rig.cameras
    flip = np.diag([1.0, 1.0, -1.0])
    mirrored = mc.Camera(c.alpha_u, c.alpha_v, c.u0, c.v0, -c.R @ flip, -c.t)
    with pytest.raises(ValueError, match="behind the cameras that see them: the cameras see a"):
        mc.bundle_adjust(mirrored, rig.pixels)
    bad = tmp_path / "calibration.toml"
    bad.write_text("[cam_0]\nmatrix = 3\n")
    with pytest.raises(ValueError, match="malformed|TOML"):
        mc.io.load_aniposelib(bad)
    bad.write_text("title = 'no cameras'\n")
    with pytest.raises(ValueError, match="no \\[cam_N\\]"):
        mc.io.load_aniposelib(bad)


def _matrix_free_cases():
    """The three joint problems above, with radial distortion: (name, arguments, keywords)."""
    rig, seed, T, anchors = anchored_rig()
    yield (
        "anchors",
        (seed, rig.world, rig.pixels, rig.mask),
        dict(transform=T, anchors=anchors, anchor_sigma=0.2),
    )
    target, rig = grid_rig(1, 8)
    rng = np.random.default_rng(1)
    rough = np.asarray(rig.world) + rng.normal(scale=0.5, size=rig.world.shape)
    seed = zero_skew(mc.calibrate(rough, rig.pixels, rig.mask).cameras)
    ids = np.arange(0, len(target.points), 5)
    yield (
        "free points",
        (seed, rough, rig.pixels, rig.mask),
        dict(anchors=(ids, np.asarray(rig.world)[ids]), anchor_sigma=0.05, points="free"),
    )
    target, rig = grid_rig(2, 6, same_intrinsics=True)
    seed = zero_skew(mc.calibrate(rig.world, rig.pixels, rig.mask).cameras)
    yield "shared", (seed, rig.world, rig.pixels, rig.mask), dict(shared_intrinsics=True)


def test_matrix_free_solve_reaches_the_dense_optimum(monkeypatch):
    # Large rigs are solved matrix-free (LSMR, block-preconditioned). Unpreconditioned, LSMR
    # returned NaN after one step on the first two of these problems (distortion with anchors,
    # free points); here every one must reach the optimum of the dense solver (SecantLM).
    for name, args, kwargs in _matrix_free_cases():
        dense = mc.refine_rig(*args, distortion=("k1", "k2"), **kwargs)
        monkeypatch.setattr(mc._bundle, "DENSE_LIMIT", 0)  # every problem is "large"
        monkeypatch.setattr(mc._bundle, "TARGET_DENSE_LIMIT", 0)
        free = mc.refine_rig(*args, distortion=("k1", "k2"), **kwargs)
        monkeypatch.undo()
        assert bool(dense.ok) and bool(free.ok), (name, dense.messages(), free.messages())
        assert np.all(np.asarray(free.rms_after) < np.asarray(free.rms_before)), name
        np.testing.assert_allclose(free.rms_after, dense.rms_after, rtol=1e-7, err_msg=name)
        np.testing.assert_allclose(free.cameras.alpha_u, dense.cameras.alpha_u, rtol=1e-7)
        # (k2 to 1e-6 of ~0.02: a thousandth of its standard error)
        np.testing.assert_allclose(free.cameras.dist, dense.cameras.dist, atol=1e-5)
        np.testing.assert_allclose(free.cameras.center, dense.cameras.center, atol=1e-5)
        np.testing.assert_allclose(free.world, dense.world, atol=1e-6)
        np.testing.assert_allclose(free.transform.t, dense.transform.t, atol=1e-7)


@pytest.mark.parametrize("case", ["anchors", "free points"])
def test_block_preconditioner_whitens_the_step_normal_matrix(monkeypatch, case):
    # The matrix-free step solves [J; sqrt(lambda) I] dy = [r; 0] by LSMR on dy = M dz. With
    # anchors, the normal matrix of dz is the identity (each camera's block, and the placement's
    # through its Schur complement with the cameras following it). With free points, the points
    # follow the cameras: identity on every point's block and every camera's, no camera-point
    # coupling (cameras that share points stay coupled). The full Jacobian here by autodiff, of
    # the problem refine_rig builds; and the step solved is the damped Gauss-Newton step.
    args, kwargs = next((a, k) for name, a, k in _matrix_free_cases() if name == case)
    captured = {}

    def spy(fn, args, y0, solver, max_steps):
        captured.update(args=args, y0=y0, solver=solver)
        raise StopIteration

    monkeypatch.setattr(mc._bundle, "DENSE_LIMIT", 0)
    monkeypatch.setattr(mc._bundle, "TARGET_DENSE_LIMIT", 0)
    monkeypatch.setattr(mc._bundle, "_solve", spy)
    with pytest.raises(StopIteration), jax.disable_jit():  # (the problem as arrays, not tracers)
        mc.refine_rig(*args, distortion=("k1",), **kwargs)
    problem, y0 = captured["args"], captured["y0"]
    linear_solver = captured["solver"].descent.linear_solver
    assert isinstance(linear_solver, mc._bundle._BlockLSMR)
    lam = 0.3

    @eqx.filter_jit  # one compiled program: run op by op, these took ~35 s a case
    def whitened_and_step(problem, y0, linear_solver):
        _, jvp = jax.linearize(lambda y: mc._bundle._residuals(y, problem), y0)

        def damped(y):
            return jvp(y), jax.tree_util.tree_map(lambda x: np.sqrt(lam) * x, y)

        operator = lx.FunctionLinearOperator(damped, jax.eval_shape(lambda: y0))
        M = mc._bundle._preconditioner(operator, linear_solver.anchor_ids)
        flat, unravel = jax.flatten_util.ravel_pytree(y0)
        ravel = lambda x: jax.flatten_util.ravel_pytree(x)[0]  # noqa: E731
        A = jax.jacfwd(lambda z: ravel(damped(mc._bundle._precondition(M, unravel(z)))))(flat)
        r = mc._bundle._residuals(y0, problem)
        zero = jax.tree_util.tree_map(jnp.zeros_like, y0)
        sol = lx.linear_solve(operator, (r, zero), linear_solver)
        J = jax.jacfwd(lambda z: ravel(jvp(unravel(z))))(flat)
        return A.T @ A, J, ravel(r), ravel(sol.value)

    N, J, r_flat, step = map(np.asarray, whitened_and_step(problem, y0, linear_solver))
    if case == "anchors":
        np.testing.assert_allclose(N, np.eye(len(N)), atol=1e-7)
    else:  # ravel_pytree orders the keys: "X" before "cams"
        n_X = y0["X"].size
        C, p = y0["cams"].shape
        np.testing.assert_allclose(N[:n_X, :], np.eye(len(N))[:n_X, :], atol=1e-7)
        for c in range(C):
            block = slice(n_X + c * p, n_X + (c + 1) * p)
            np.testing.assert_allclose(N[block, block], np.eye(p), atol=1e-7)
        assert np.abs(N[n_X:, n_X:] - np.eye(C * p)).max() > 0.01  # coupled through the points
    expected = np.linalg.solve(J.T @ J + lam * np.eye(J.shape[1]), J.T @ r_flat)
    np.testing.assert_allclose(step, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_the_matrix_free_lm_accepts_a_trial_that_lost_to_rounding_only():
    # At the optimum a trial wins or loses by rounding; optimistix's trust region rejected the
    # losers and shrank the step until one won (7 of 13 steps on 12 cameras, one hidden).
    search = mc._refine._RoundingTrustRegion()
    J = lx.MatrixLinearOperator(jnp.eye(2))
    y, r = jnp.zeros(2), jnp.array([3.0, 4.0])
    info = optx.FunctionInfo.ResidualJac(r, J)
    state = search.init(y, info)
    eps = float(jnp.finfo(r.dtype).eps)
    y_eval = y - 1e-3 * r  # a step the model says lowers the loss
    for relative, accepted in [(4 * eps, True), (1e-9, False)]:  # the loss rises by 2x that
        trial = optx.FunctionInfo.ResidualJac(r * (1 + relative), J)
        for s, expected in [(search, accepted), (optx.ClassicalTrustRegion(), False)]:
            accept = s.step(jnp.array(False), y, y_eval, info, trial, state)[1]
            assert bool(accept) == expected, (type(s).__name__, relative)


def test_default_solver_is_dense_for_small_problems_and_bundle_adjustment():
    def matrix_free(n_residuals, n_parameters, free_points):
        solver = mc._bundle.default_solver(
            jnp.float64, n_residuals, n_parameters, free_points=free_points
        )
        if isinstance(solver, mc.SecantLM):
            return False
        assert isinstance(solver.descent.linear_solver, mc._bundle._BlockLSMR)
        return True

    assert not matrix_free(900, 78, free_points=False)  # 6 cameras of 75 points
    assert matrix_free(27_648, 390, free_points=False)  # 32 cameras of 432 points: 14x faster
    assert not matrix_free(3_600, 618, free_points=True)  # bundle adjustment: SecantLM's steps
    assert matrix_free(645_434, 640 + 15_129, free_points=True)  # beyond memory


@pytest.mark.parametrize("p", [3, 6, 14])
def test_the_preconditioner_blocks_written_out_equal_lapacks(monkeypatch, p):
    # Where batched LAPACK can hang (several CPU devices) the blocks' inverse Cholesky factors
    # are written out entry by entry; they must be the same, down to the fallbacks.
    rng = np.random.default_rng(p)
    A = rng.normal(size=(6, p, 3 * p)) * np.logspace(-3, 3, p)[:, None]
    G = A @ np.swapaxes(A, -1, -2)
    G[1] = 0.0  # a block of parameters with no effect
    G[2, 0, :] = G[2, :, 0] = 0.0  # one parameter without effect
    G[3] = -np.eye(p)  # not definite
    G = jnp.asarray(G)
    lapack = mc._bundle._inverse_cholesky_transpose(G)
    monkeypatch.setattr(mc._bundle._sharding, "batched_lapack_may_hang", lambda: True)
    written = mc._bundle._inverse_cholesky_transpose(G)
    np.testing.assert_allclose(written, lapack, rtol=1e-9, atol=0)
    WtGW = np.einsum("bki,bkl,blj->bij", written, G, written)
    np.testing.assert_allclose(WtGW[[0, 4, 5]], np.broadcast_to(np.eye(p), (3, p, p)), atol=1e-9)


@pytest.mark.parametrize("lens", ["pinhole", "fisheye"])
def test_aniposelib_file_projects_as_aniposelib_does_in_its_own_camera_order(tmp_path, lens):
    """`save_aniposelib` writes what `CameraGroup.load` reads: aniposelib projects with
    `cv2.projectPoints` (`cv2.fisheye`'s with `fisheye = true`) from the file's numbers, and
    orders the tables as strings (`cam_10` before `cam_2`, which permuted rigs of more than ten
    cameras): the tables are `cam_00`, `cam_01`, ..., in that order either way."""
    import tomllib

    cv2 = pytest.importorskip("cv2")
    rig = mc.synthetic.random_rig(jax.random.key(32), 12).cameras
    dist = [-0.2, 0.05, 1e-3, -2e-3, 0.01] if lens == "pinhole" else [0.05, -0.01, 2e-3, -1e-4]
    rig = mc.Camera.from_matrices(rig.K, rig.R, rig.t, np.tile(dist, (12, 1)), lens=lens)
    names = [f"Kamera {i}" for i in range(12)]
    path = mc.io.save_aniposelib(tmp_path / "calibration.toml", rig, (1000, 1100), names=names)
    document = tomllib.loads(path.read_text())
    cameras = [document[key] for key in sorted(document) if key != "metadata"]  # aniposelib's
    assert [c["name"] for c in cameras] == names and "metadata" in document
    world = np.random.default_rng(3).uniform(0.0, 160.0, (30, 3))
    project = cv2.fisheye.projectPoints if lens == "fisheye" else cv2.projectPoints
    for i, c in enumerate(cameras):
        assert c["size"] == [1000, 1100] and c.get("fisheye", False) == (lens == "fisheye")
        K, D = np.array(c["matrix"]), np.array(c["distortions"])
        theirs = project(world[:, None], np.array(c["rotation"]), np.array(c["translation"]), K, D)
        np.testing.assert_allclose(rig[i].project(world), theirs[0][:, 0], rtol=0, atol=1e-9)
    back, got = mc.io.load_aniposelib(path)
    assert got == names and back.lens == lens
    np.testing.assert_allclose(np.asarray(back.R), np.asarray(rig.R), rtol=0, atol=1e-15)


def test_aniposelib_file_refuses_what_aniposelib_cannot_hold(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(33), 2).cameras
    path = tmp_path / "calibration.toml"
    with pytest.raises(ValueError, match="no skew"):
        mc.io.save_aniposelib(path, eqx.tree_at(lambda c: c.skew, rig, rig.skew + 1.0), (9, 9))
    with pytest.raises(ValueError, match="not calibrated"):
        mc.io.save_aniposelib(path, eqx.tree_at(lambda c: c.u0, rig, rig.u0 * np.nan), (9, 9))
    with pytest.raises(ValueError, match="image_size"):
        mc.io.save_aniposelib(path, rig, None)
    assert not path.exists()


def test_bundle_adjust_names_a_camera_whose_observations_it_dropped():
    """On the real 12-camera rig one camera started ~250 px off, kept none of its observations
    within the thresholds, and came back "0.00 px, used": a fit it never had. A camera that saw
    none of the points has no RMS (NaN), and one that kept less than half of what it saw is
    `doubtful`, named in `messages()`."""
    rig = mc.synthetic.random_rig(jax.random.key(34), 12, mc.targets.box_corner_grid(3))
    tracks = np.asarray(rig.pixels).copy()
    tracks[2] += 30.0  # camera 2's tracks wrong: its reprojections ~34 px off, the others' 4-10
    out = mc.bundle_adjust(rig.cameras, tracks, distortion=(), thresholds=(20.0,), max_steps=10)
    last = out.rounds[-1]
    assert last["saw"][2] == 27 and last["kept"][2] == 0 and min(np.delete(last["kept"], 2)) > 20
    assert np.isnan(out.refinement.rms_after[2]) and bool(out.refinement.used[2])
    assert np.flatnonzero(out.doubtful).tolist() == [2] and not out.ok
    assert "camera 2 kept 0 of the 27 observations it saw within 20 px" in out.messages()
    assert "cameras [2] saw none of the points" in out.messages()
    np.testing.assert_array_equal(out.cameras.t[2], rig.cameras.t[2])  # held where it was


def test_bundle_adjust_with_one_lens_for_every_camera():
    rig = mc.synthetic.random_rig(jax.random.key(35), 6, mc.targets.box_corner_grid(3))
    K = jnp.broadcast_to(rig.cameras.K[0], rig.cameras.K.shape)
    one_lens = mc.Camera.from_matrices(K, rig.cameras.R, rig.cameras.t)
    pixels = one_lens.project(rig.world)
    start = eqx.tree_at(
        lambda c: c.alpha_u, one_lens, one_lens.alpha_u * (1 + 0.01 * jnp.arange(6))
    )
    out = mc.bundle_adjust(start, pixels, distortion=(), thresholds=(20.0,), max_steps=20,
                           shared_intrinsics=True)  # fmt: skip
    assert np.ptp(np.asarray(out.cameras.alpha_u)) == 0.0  # one lens
    assert out.rounds[-1]["after"] < 0.1 < out.rounds[-1]["before"]


def test_bundle_adjust_unconverged_says_what_to_try_for_bundle_adjustment():
    """It said refine's words ("one view of a plane with free intrinsics"), which fit no
    bundle adjustment."""
    rig = mc.synthetic.random_rig(jax.random.key(37), 6, mc.targets.box_corner_grid(3))
    start = eqx.tree_at(lambda c: c.alpha_u, rig.cameras, rig.cameras.alpha_u * 1.05)
    out = mc.bundle_adjust(start, rig.pixels, thresholds=(200.0,), max_steps=2)
    assert not bool(out.refinement.ok)
    assert "bundle adjustment's steps creep" in out.messages() and "plane" not in out.messages()
