"""Figures (mvcalib.plot), drawn with the Agg backend and checked against NumPy geometry."""

import sys

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")

import mvcalib as mc  # noqa: E402
import mvcalib.plot as mp  # noqa: E402

WORLD = mc.targets.box_corner().points  # (19, 3), around (70, 70, 70)


def _rig():
    """Three cameras looking at the box corner from the positive octant (NumPy ground truth)."""
    centre = WORLD.mean(0)
    K, R, t = [], [], []
    for k, (azimuth, elevation) in enumerate([(45.0, 35.0), (10.0, 25.0), (80.0, 50.0)]):
        a, e = np.radians(azimuth), np.radians(elevation)
        position = centre + 700.0 * np.array(
            [np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]
        )
        z = (centre - position) / np.linalg.norm(centre - position)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        Rk = np.stack([x, np.cross(z, x), z])
        K.append([[1400.0 + 50 * k, 3.0, 500.0], [0.0, 1390.0, 540.0], [0.0, 0.0, 1.0]])
        R.append(Rk)
        t.append(-Rk @ position)
    K, R, t = np.array(K), np.array(R), np.array(t)
    return mc.Camera.from_matrices(K, R, t), K, R, t


def _project(K, R, t, X):
    """Pixels and depths of points X (N, 3) in one camera or a rig (leading axis)."""
    camera = np.einsum("...ij,nj->...ni", R, X) + t[..., None, :]
    x = np.einsum("...ij,...nj->...ni", K, camera)
    return x[..., :2] / x[..., 2:], camera[..., 2]


def test_frusta_start_at_the_centres_and_reach_the_image_corners():
    cameras, K, R, t = _rig()
    ax = mp.plot_rig(cameras, WORLD, image_size=(1000, 1100), frustum_depth=100.0)
    lines = [np.array(line.get_data_3d()).T for line in ax.lines]
    assert len(lines) == 3 * 5 + 3  # four rays and a rectangle per camera; X, Y, Z
    corners = [[-0.5, -0.5], [999.5, -0.5], [999.5, 1099.5], [-0.5, 1099.5]]
    for c in range(3):
        rays, rectangle = lines[5 * c : 5 * c + 4], lines[5 * c + 4]
        for k, ray in enumerate(rays):
            np.testing.assert_allclose(ray[0], -R[c].T @ t[c], atol=1e-9)  # the centre
            pixel, depth = _project(K[c], R[c], t[c], ray[1][None])
            np.testing.assert_allclose(pixel[0], corners[k], atol=1e-6)
            np.testing.assert_allclose(depth, 100.0, rtol=1e-9)
        np.testing.assert_allclose(rectangle[:4], [r[1] for r in rays], atol=1e-9)
    for k, axis in enumerate(lines[-3:]):  # the world frame's axes at the origin
        assert np.all(axis[0] == 0) and axis[1][k] > 0 and np.count_nonzero(axis[1]) == 1
    (points,) = ax.collections
    np.testing.assert_allclose(np.array(points._offsets3d).T, WORLD)


def test_a_mirrored_world_frame_draws_the_frustum_towards_the_points():
    cameras, K, R, t = _rig()
    centre = -R[0].T @ t[0]
    behind = 2 * centre - WORLD  # the points reflected through the camera: negative depth
    ax = mp.plot_rig(cameras[:1], behind, frustum_depth=50.0)
    corner = np.array(ax.lines[0].get_data_3d()).T[1]
    assert _project(K[0], R[0], t[0], corner[None])[1][0] == pytest.approx(-50.0)


def test_residual_arrows_are_the_known_errors_magnified():
    cameras, K, R, t = _rig()
    clean, _ = _project(K, R, t, WORLD)  # (3, 19, 2)
    error = np.random.default_rng(0).normal(0, 0.4, clean.shape)
    mask = np.ones(clean.shape[:2], bool)
    mask[1, :5] = False  # hidden: not drawn
    observed = clean + error
    observed[1, :5] = np.nan  # and NaN there does no harm
    axes, scale = mp.plot_residuals(cameras, WORLD, observed, mask, image_size=(1000, 1100))
    assert scale in {1, 2, 5, 10, 20, 50, 100, 200, 500}
    for c, ax in enumerate(axes):
        (arrows,) = [a for a in ax.collections if isinstance(a, matplotlib.quiver.Quiver)]
        seen = mask[c]
        np.testing.assert_allclose(np.c_[arrows.X, arrows.Y], observed[c, seen], atol=1e-9)
        # reprojected - observed = -error, drawn `scale` times longer
        np.testing.assert_allclose(np.c_[arrows.U, arrows.V], -scale * error[c, seen], atol=1e-6)
        rms = np.sqrt(np.mean(np.sum(error[c, seen] ** 2, -1)))
        assert f"RMS {rms:.3g} px, {seen.sum()} points" in ax.get_title()


def test_histograms_count_every_visible_observation_once():
    cameras, K, R, t = _rig()
    clean, _ = _project(K, R, t, WORLD)
    error = np.random.default_rng(1).normal(0, 0.5, clean.shape)
    error[0, 0] = (40.0, 0.0)  # one outlier, beyond 5 RMS: counted, not drawn
    mask = np.random.default_rng(2).random(clean.shape[:2]) < 0.8
    components, lengths = mp.plot_histograms(cameras, WORLD, clean + error, mask)
    assert sum(bar.get_height() for bar in lengths.patches) == mask.sum() - 1  # not the outlier
    assert "1 beyond" in lengths.get_title()
    assert f"({mask.sum()} observations)" in components.get_title()
    assert len(components.patches) == 2  # the x and y step histograms


def test_report_figure_is_saved_atomically_and_survives_a_failed_camera(tmp_path):
    cameras, K, R, t = _rig()
    clean, _ = _project(K, R, t, WORLD)
    rig = mc.Camera.from_matrices(
        np.concatenate([K, np.full((1, 3, 3), np.nan)]), np.concatenate([R, R[:1]]),
        np.concatenate([t, t[:1]]),
    )  # fmt: skip
    pixels = np.concatenate([clean + 0.3, np.full((1, 19, 2), np.nan)])
    figure = mp.report_figure(rig, WORLD, pixels, names=["a", "b", "/some/where/c.png", "d"])
    titles = [ax.get_title() for ax in figure.axes]
    assert any(t.startswith("2: c.png: RMS") for t in titles)  # a file name, numbered as the tables
    assert any(t == "3: d: no points" for t in titles)
    path = mp.save_figure(figure, tmp_path / "report.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["report.png"]  # no temporary file left


def test_without_matplotlib_the_error_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    cameras, *_ = _rig()
    with pytest.raises(ImportError, match=r"pip install 'mvcalib\[plot\]'"):
        mp.plot_rig(cameras)
