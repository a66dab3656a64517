"""Correspondence files (CSV and JSON): exact round trips, and one-line errors for bad files."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import mvcalib as mc

FORMATS = ["csv", "json"]


def _equal(a, b):
    np.testing.assert_array_equal(a, b)  # NaN == NaN here, and bit-exact otherwise


def _sample(rng, C=3, P=7, world=True):
    pixels = rng.uniform(-10, 1100, (C, P, 2)) * 10.0 ** rng.integers(-8, 8, (C, P, 2))
    mask = rng.random((C, P)) < 0.7
    mask[:, 0] = True
    mask[1] = False  # a camera that saw nothing
    mask[:, -1] = False  # a point that nobody saw
    xyz = rng.standard_normal((P, 3)) * 10.0 ** rng.integers(-12, 12, (P, 3)) if world else None
    return xyz, pixels, mask


@pytest.mark.parametrize("kind", FORMATS)
@pytest.mark.parametrize("world", [True, False], ids=["correspondences", "tracks"])
def test_round_trip_is_exact_with_unseen_points_silent_cameras_and_unlabelled_dots(
    tmp_path, kind, world
):
    xyz, pixels, mask = _sample(np.random.default_rng(1), world=world)
    names = ["left cam", "b,c", 'quote"d']  # CSV quoting
    points = [f"p{i}" for i in range(pixels.shape[1])]
    unlabelled = [np.zeros((0, 2)), np.array([[1.5, 2.25], [0.1, 1e-300]]), np.array([[3.0, 4]])]
    path = mc.io.save_correspondences(
        tmp_path / f"c.{kind}", xyz, pixels, mask, cameras=names, points=points,
        unlabelled=unlabelled,
    )  # fmt: skip
    back = mc.io.load_correspondences(path)
    assert back.cameras == names and back.points == points
    _equal(back.mask, mask)
    _equal(back.pixels, np.where(mask[..., None], pixels, np.nan))
    if world:
        _equal(back.world, xyz)
    else:
        assert back.world is None
    assert len(back.unlabelled) == 3
    for a, b in zip(back.unlabelled, unlabelled):
        _equal(a, b)
    # and writing what was read gives the same file
    again = mc.io.save_correspondences(
        tmp_path / f"again.{kind}", back.world, back.pixels, back.mask, cameras=back.cameras,
        points=back.points, unlabelled=back.unlabelled,
    )  # fmt: skip
    assert again.read_text() == path.read_text()


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=30, deadline=None)
@given(
    pixels=hnp.arrays(np.float64, (2, 4, 2), elements=finite),
    world=hnp.arrays(np.float64, (4, 3), elements=finite),
    kind=st.sampled_from(FORMATS),
)
def test_every_double_survives_the_round_trip(tmp_path_factory, pixels, world, kind):
    # Points are named, so equal world coordinates (which hypothesis likes) stay two points.
    path = tmp_path_factory.mktemp("rt") / f"c.{kind}"
    back = mc.io.load_correspondences(mc.io.save_correspondences(path, world, pixels))
    _equal(back.world, world)
    _equal(back.pixels, pixels)
    assert back.mask.all()


def test_csv_without_point_names_identifies_points_by_their_world_coordinates(tmp_path):
    path = tmp_path / "hand.csv"
    path.write_text(
        "# written by hand\n"
        "camera,world_x,world_y,world_z,pixel_x,pixel_y\n"
        "a,0,0,0,10,20\n"
        "a,1,0,0,30,40\n"
        "b,1,0,0,31,41\n"
        "b,0,0,0,11,21\n"
        "\n"
    )
    c = mc.io.load_correspondences(path)
    _equal(c.world, [[0, 0, 0], [1, 0, 0]])
    _equal(c.pixels, [[[10, 20], [30, 40]], [[11, 21], [31, 41]]])
    assert c.cameras == ["a", "b"] and c.mask.all()


@pytest.mark.parametrize("world", [True, False], ids=["correspondences", "tracks"])
def test_plain_files_are_read_column_by_column_as_row_by_row(tmp_path, monkeypatch, world):
    """`_plain_columns`, the reader's NumPy path for plain rows (a million in ~1 s), answers as
    the row-by-row reader does, to the bit: names in order of appearance, hidden points, NaN
    rows (unseen) and whitespace around the fields included."""
    rig = mc.synthetic.random_rig(jax.random.key(3), 5, noise=0.3)
    path = mc.io.save_correspondences(tmp_path / "c.csv", rig.world if world else None,
                                      rig.pixels, rig.mask, cameras=list("edcba"))  # fmt: skip
    lines = path.read_text().splitlines()
    lines = [lines[0]] + lines[:0:-1]  # (rows in another order: names by first appearance)
    xyz = ",".join(repr(float(v)) for v in np.asarray(rig.world)[4]) + "," if world else ""
    lines.insert(3, f"a , 4 ,{xyz}nan, nan")  # unseen, spaced
    lines = [ln for ln in lines if not ln.startswith("a,4,")]
    path.write_text("\n".join(lines) + "\n")
    plain, answers = mc.io._plain_columns, []
    monkeypatch.setattr(
        mc.io, "_plain_columns", lambda *a: answers.append(plain(*a)) or answers[-1]
    )
    fast = mc.io.load_correspondences(path)
    assert answers[-1] is not None  # (the file is read column by column)
    monkeypatch.setattr(mc.io, "_plain_columns", lambda *args: None)
    slow = mc.io.load_correspondences(path)
    assert fast.cameras == slow.cameras and fast.points == slow.points
    for name in ("world", "pixels", "mask"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert (a is None and b is None) or np.array_equal(a, b, equal_nan=True), name


def test_blank_or_nan_pixels_say_the_camera_did_not_see_the_point(tmp_path):
    """Every camera x point row, NaN (NumPy's, pandas') or blank where a camera did not see the
    point, as PTV data often comes: read as unseen (it was refused, NaN or inf / no pixel)."""
    path = tmp_path / "t.csv"
    path.write_text("camera,point,pixel_x,pixel_y\na,1,10,20\nb,1,NaN,nan\na,2,,\nb,2,11,21\n")
    c = mc.io.load_correspondences(path)
    assert c.cameras == ["a", "b"] and c.points == ["1", "2"]
    _equal(c.mask, [[True, False], [False, True]])
    _equal(c.pixels[0, 0], [10, 20])
    _equal(c.pixels[1, 1], [11, 21])


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        ("camera,point,pixel_x\n", "no 'pixel_y' column"),
        ("camera,point,pixel_x,pixel_y,colour\n", "unknown column 'colour'"),
        ("camera,pixel_x,pixel_y\na,1,2\n", "needs a 'point' column"),
        ("camera,point,pixel_x,pixel_y\na,1,2\n", ":2: 3 fields"),
        ("camera,point,pixel_x,pixel_y\na,1,2,x\n", ":2: pixel_x, pixel_y = '2', 'x' are not all"),
        ("camera,point,pixel_x,pixel_y\na,1,2,nan\n", ":2: NaN or inf"),
        ("camera,point,pixel_x,pixel_y\na,1,2,3\na,1,2,3\n", ":3: camera 'a' saw point '1' on"),
        (
            "camera,point,world_x,world_y,world_z,pixel_x,pixel_y\na,1,0,0,0,2,3\nb,1,0,0,1,2,3\n",
            ":3: point '1' has other world coordinates",
        ),
        ("camera,point,world_x,world_y,world_z,pixel_x,pixel_y\na,1,,,,2,3\n", "no world"),
        ("camera,point,pixel_x,pixel_y\n,1,2,3\n", "without a camera"),
        # a spreadsheet's export with ';' (a comma-decimal locale), tabs, no header
        ("camera;point;pixel_x;pixel_y\na;1;2,5;3\n", "separated by semicolons; mvcalib reads"),
        ("camera\tpoint\tpixel_x\tpixel_y\na\t1\t2\t3\n", "separated by tabs"),
        (
            "cam1,p1,2.5,3\n",
            "unknown column 'cam1'; the header is camera,point,world_x,world_y,"
            "world_z,pixel_x,pixel_y (world_* columns optional, point optional with world_*): the "
            "file's first line must be that header.",
        ),  # fmt: skip
    ],
)
def test_malformed_csv_gives_one_line_naming_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        mc.io.load_correspondences(path)
    assert message in str(info.value) and str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_opencv_yaml_says_which_names_cannot_be_keys(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(0), 2).cameras
    with pytest.raises(ValueError, match="not starting with a digit: '10', '11' cannot name"):
        mc.io.save_opencv(tmp_path / "r.yml", rig, names=["10", "11"])
    # calibrate_images names its cameras by their photos' paths (a user's trial): the error
    # says how to spell them, and that spelling is written and read back
    names = ["cal/cam1.tif", "cal/cam2.tif"]
    with pytest.raises(ValueError, match="'cal/cam1.tif' as 'cal_cam1_tif'"):
        mc.io.save_opencv(tmp_path / "r.yml", rig, names=names)
    mc.io.save_opencv(tmp_path / "r.yml", rig, names=[mc.io.opencv_name(n) for n in names])
    assert mc.io.load_opencv(tmp_path / "r.yml")[1] == ["cal_cam1_tif", "cal_cam2_tif"]


def test_camera_names_a_csv_would_read_as_comments_are_refused(tmp_path):
    """A camera named `#1` was written, then its rows skipped as comments: its observations
    were gone, without a word."""
    rig = mc.synthetic.random_rig(jax.random.key(0), 2)
    with pytest.raises(ValueError, match="camera names must not start with '#'"):
        mc.io.save_correspondences(tmp_path / "p.csv", rig.world, rig.pixels, rig.mask,
                                   cameras=["#1", "#2"])  # fmt: skip
    assert not (tmp_path / "p.csv").exists()


def test_a_rig_read_in_float32_says_so(tmp_path):
    """With JAX's default float32 a loaded rig was rounded to ~7 digits and saved back so
    (`u0 = 639.3` became 639.2999877929688), silently; the readers say so (a fresh process:
    the tests run in float64)."""
    import subprocess
    import sys

    path = mc.io.save_json(
        tmp_path / "r.json", mc.synthetic.random_rig(jax.random.key(0), 2).cameras
    )
    code = f"import mvcalib as mc; mc.io.load_json({str(path)!r})"
    for x64, warned in (("0", True), ("1", False)):
        env = {**__import__("os").environ, "JAX_ENABLE_X64": x64}
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
        assert run.returncode == 0, run.stderr
        assert ("load_json: the rig is held in float32" in run.stderr) == warned, run.stderr


def test_json_rig_gives_back_what_was_stored_for_the_record(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(0), 3).cameras
    path = mc.io.save_json(tmp_path / "r.json", rig, status=[0, 6, 0], rms=[0.25, 9.5, np.nan],
                           meta={"target": "box"})  # fmt: skip
    cameras, names, record = mc.io.load_json(path, record=True)
    np.testing.assert_array_equal(np.asarray(cameras.K), np.asarray(rig.K))
    assert record["status"].tolist() == [0, 6, 0] and record["meta"] == {"target": "box"}
    np.testing.assert_array_equal(record["rms"], [0.25, 9.5, np.nan])
    _, _, bare = mc.io.load_json(mc.io.save_json(tmp_path / "s.json", rig), record=True)
    assert bare == {"status": None, "rms": None, "meta": {}}


def test_malformed_json_and_wrong_suffix_are_refused(tmp_path):
    good = mc.io.save_correspondences(tmp_path / "c.json", np.eye(3), np.ones((1, 3, 2)))
    document = json.loads(good.read_text())
    document["pixels"][0][1] = [1.0, None]
    (tmp_path / "nan.json").write_text(json.dumps(document))
    document["pixels"] = [[[1, 2]]]
    (tmp_path / "short.json").write_text(json.dumps(document))
    (tmp_path / "rig.json").write_text('{"format": "mvcalib.rig"}')
    (tmp_path / "broken.json").write_text("{")
    for name, message in [
        ("nan.json", "NaN or inf"),
        ("short.json", "must be 1 lists of 3"),
        ("rig.json", "not a correspondences file"),
        ("broken.json", "not valid JSON"),
        ("missing.json", "cannot be read"),
    ]:
        with pytest.raises(ValueError, match=message):
            mc.io.load_correspondences(tmp_path / name)
    with pytest.raises(ValueError, match=r"\.csv or \.json"):
        mc.io.save_correspondences(tmp_path / "c.txt", np.eye(3), np.ones((1, 3, 2)))
    with pytest.raises(ValueError, match="NaN or inf entries where `mask` is True"):
        mc.io.save_correspondences(
            tmp_path / "c.csv", None, np.full((1, 3, 2), np.nan), np.ones((1, 3), bool)
        )
    assert not (tmp_path / "c.csv").exists()  # nothing written


def test_written_files_get_the_permissions_a_plain_open_would_give(tmp_path):
    import os

    umask = os.umask(0o027)
    try:
        new = mc.io.write_atomic(tmp_path / "new.txt", "x")
        assert new.stat().st_mode & 0o777 == 0o640  # 0666 less the umask, not mkstemp's 0600
        old = tmp_path / "old.txt"
        old.write_text("before")
        old.chmod(0o604)
        mc.io.write_atomic(old, "after")
        assert old.stat().st_mode & 0o777 == 0o604 and old.read_text() == "after"
    finally:
        os.umask(umask)


def test_a_file_that_cannot_be_written_is_named_in_the_error_not_its_temporary(tmp_path):
    (tmp_path / "folder.json").mkdir()
    for path, error in (
        (tmp_path / "no" / "r.json", FileNotFoundError),  # the temporary file cannot be made
        (tmp_path / "folder.json", IsADirectoryError),  # nor renamed onto a folder
    ):
        with pytest.raises(error, match=f"cannot write {path}: "):
            mc.io.write_atomic(path, "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.json"]  # nothing left behind


def test_saving_a_calibration_result_says_to_pass_its_cameras(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(0), 3)
    result = mc.calibrate(rig.world, rig.pixels)
    board = mc.synthetic.board_rig(jax.random.key(0), n_cameras=1, n_frames=6)
    planar = mc.calibrate_planar(board.target, board.pixels[0], board.mask[0], refine=False)
    for save in (mc.io.save_json, mc.io.save_opencv, lambda p, c: mc.io.save_colmap(p, c, (9, 9))):
        for wrong, field in ((result, "cameras"), (planar, "camera")):
            with pytest.raises(TypeError, match=rf"got {type(wrong).__name__}: .*`result.{field}`"):
                save(tmp_path / "out", wrong)
    assert not list(tmp_path.iterdir())  # nothing written, no folder made


@pytest.mark.parametrize(
    "save", ["save_json", "save_opencv", "save_colmap", "save_aniposelib", "save_kalibr"]
)
def test_writers_refuse_a_camera_no_reader_would_load(tmp_path, save):
    """A JAX user's trial: a Camera-shaped gradient (`eqx.filter_grad`) was written by
    `save_json` and refused later by `load_json` (its R is no rotation). The writers refuse it,
    and a traced Camera, with the reason."""
    rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=3)
    cameras = eqx.tree_at(lambda c: (c.skew, c.dist), rig.cameras, replace_fn=jnp.zeros_like)
    gradient = eqx.filter_grad(lambda c: c.project(rig.world).sum())(cameras)
    path = tmp_path / ("rig.toml" if save == "save_aniposelib" else "rig")
    sized = save in ("save_colmap", "save_aniposelib", "save_kalibr")
    scaled = {"metres_per_unit": 1e-3} if save == "save_kalibr" else {}  # (a rig in millimetres)
    write = lambda c: getattr(mc.io, save)(path, c, *([(1000, 1100)] if sized else []), **scaled)  # noqa: E731
    with pytest.raises(ValueError, match=rf"{save}: camera 0: R is not a rotation"):
        write(gradient)
    with pytest.raises(TypeError, match="concrete cameras, outside jax.jit"):
        jax.jit(write)(cameras)
    write(cameras)  # (the cameras themselves are written)


# ---------------------------------------------------------------------------- Kalibr camchain
def _lensed_rig(lens):
    """A rig of 4 cameras with distortion and no skew, as Kalibr holds them, in metres."""
    rig = mc.synthetic.random_rig(jax.random.key(3), n_cameras=4)  # (millimetres)
    rig = eqx.tree_at(lambda r: (r.world, r.cameras.t), rig, replace_fn=lambda x: x / 1000.0)
    if lens == "pinhole":
        dist = np.array([[-0.21, 0.05, 1e-3, -2e-3, 0.0]] * 4)
    else:
        dist = np.array([[0.05, -0.01, 3e-3, -1e-3]] * 4)
    cameras = eqx.tree_at(lambda c: c.skew, rig.cameras, replace_fn=jnp.zeros_like)
    return mc.Camera(*(getattr(cameras, f) for f in ("alpha_u", "alpha_v", "u0", "v0", "R", "t")),
                     dist=dist, lens=lens), rig.world  # fmt: skip


def test_kalibr_chain_holds_each_camera_from_the_previous(tmp_path):
    """Kalibr's `T_cn_cnm1` maps a point from camera n-1's frame to camera n's; checked by
    reading the file with PyYAML and moving points with it, not with `load_kalibr`."""
    import yaml

    cameras, world = _lensed_rig("pinhole")
    path = mc.io.save_kalibr(tmp_path / "camchain.yaml", cameras, (1000, 1100))
    data = yaml.safe_load(path.read_text())
    assert sorted(data) == ["cam0", "cam1", "cam2", "cam3"] and "T_cn_cnm1" not in data["cam0"]
    frames = [np.asarray(world) @ np.asarray(cameras.R[i]).T + np.asarray(cameras.t[i])
              for i in range(4)]  # fmt: skip
    for i in range(1, 4):
        T = np.asarray(data[f"cam{i}"]["T_cn_cnm1"])
        np.testing.assert_allclose(frames[i - 1] @ T[:3, :3].T + T[:3, 3], frames[i], atol=1e-9)
        np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    cam = data["cam2"]
    assert cam["camera_model"] == "pinhole" and cam["distortion_model"] == "radtan"
    assert cam["intrinsics"] == [float(cameras.alpha_u[2]), float(cameras.alpha_v[2]),
                                 float(cameras.u0[2]), float(cameras.v0[2])]  # fmt: skip
    assert cam["distortion_coeffs"] == [-0.21, 0.05, 1e-3, -2e-3]
    assert cam["resolution"] == [1000, 1100] and cam["rostopic"] == "/cam2/image_raw"


@pytest.mark.parametrize("lens", ["pinhole", "fisheye"])
def test_kalibr_round_trip_projects_as_before_in_cam0_s_frame(tmp_path, lens):
    """Kalibr has no world frame: the rig comes back in camera 0's, where every camera projects
    the points as before (to 1e-9 px) and camera 0 sits at the origin."""
    cameras, world = _lensed_rig(lens)
    path = mc.io.save_kalibr(tmp_path / "camchain.yaml", cameras, (1000, 1100))
    back, names = mc.io.load_kalibr(path)
    assert names == ["cam0", "cam1", "cam2", "cam3"] and back.lens == lens
    in_cam0 = np.asarray(world) @ np.asarray(cameras.R[0]).T + np.asarray(cameras.t[0])
    np.testing.assert_allclose(back.project(in_cam0), cameras.project(world), rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.R[0], np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(back.dist, cameras.dist)
    np.testing.assert_array_equal(back.K, cameras.K)


def test_kalibr_refuses_what_its_file_cannot_hold(tmp_path):
    cameras, _ = _lensed_rig("pinhole")
    path = tmp_path / "camchain.yaml"
    skewed = eqx.tree_at(lambda c: c.skew, cameras, replace_fn=lambda s: s + 0.5)
    with pytest.raises(ValueError, match="no skew"):
        mc.io.save_kalibr(path, skewed, (1000, 1100))
    k3 = eqx.tree_at(lambda c: c.dist, cameras, replace_fn=lambda d: d.at[:, 4].set(0.01))
    with pytest.raises(ValueError, match="k1 k2 p1 p2, not k3"):
        mc.io.save_kalibr(path, k3, (1000, 1100))
    failed = eqx.tree_at(lambda c: c.u0, cameras, replace_fn=lambda u: u.at[2].set(jnp.nan))
    with pytest.raises(ValueError, match=r"camera\(s\) \[2\] have no calibration"):
        mc.io.save_kalibr(path, failed, (1000, 1100))
    with pytest.raises(ValueError, match="3 topics for 4 cameras"):
        mc.io.save_kalibr(path, cameras, (1000, 1100), topics=["/a", "/b", "/c"])
    assert not path.exists()
    # Kalibr's metres: a rig in millimetres (a user's trial: "2.3 km" baselines) warns, and
    # `metres_per_unit` scales it
    in_mm = eqx.tree_at(lambda c: c.t, cameras, replace_fn=lambda t: 1000.0 * t)
    with pytest.warns(UserWarning, match="is the rig in millimetres"):
        mc.io.save_kalibr(path, in_mm, (1000, 1100))
    mc.io.save_kalibr(path, in_mm, (1000, 1100), metres_per_unit=0.001)
    back, _ = mc.io.load_kalibr(path)
    np.testing.assert_allclose(np.linalg.norm(back.center[1]),
                               np.linalg.norm(cameras.center[1] - cameras.center[0]))  # fmt: skip


def test_load_kalibr_reads_kalibr_s_block_style_and_imu_chains(tmp_path):
    """Kalibr writes its files with PyYAML, in block style in its recent versions; a
    camchain-imucam.yaml adds IMU terms, left out. Values as in Kalibr's EuRoC example."""
    import yaml

    T = [[0.99999, -0.00230, -0.00034, -0.11007], [0.00231, 0.99994, 0.01021, 0.00040],
         [0.00032, -0.01021, 0.99995, -0.00085], [0.0, 0.0, 0.0, 1.0]]  # fmt: skip
    R, _ = np.linalg.qr(np.asarray(T)[:3, :3])
    R *= np.sign(np.diag(R))  # (the nearest rotation: the printed digits are rounded)
    T = np.block([[R, np.asarray(T)[:3, 3:]], [np.eye(4)[3]]])
    chain = {
        "cam0": {"T_cam_imu": np.eye(4).tolist(), "cam_overlaps": [1], "camera_model": "pinhole",
                 "distortion_coeffs": [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
                 "distortion_model": "radtan", "intrinsics": [458.654, 457.296, 367.215, 248.375],
                 "resolution": [752, 480], "rostopic": "/cam0/image_raw"},
        "cam1": {"T_cn_cnm1": T.tolist(), "cam_overlaps": [0], "camera_model": "pinhole",
                 "distortion_coeffs": [0.1, 0.01, 0.002, 0.001], "distortion_model": "equidistant",
                 "intrinsics": [457.587, 456.134, 379.999, 255.238], "resolution": [752, 480],
                 "rostopic": "/cam1/image_raw"},
    }  # fmt: skip
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(yaml.safe_dump(chain, default_flow_style=False))
    with pytest.raises(ValueError, match="different lenses"):  # (cam1 is a fisheye)
        mc.io.load_kalibr(path)
    chain["cam1"]["distortion_model"] = "radtan"
    path.write_text(yaml.safe_dump(chain, default_flow_style=False))
    back, names = mc.io.load_kalibr(path)
    assert names == ["cam0", "cam1"] and back.lens == "pinhole"
    np.testing.assert_array_equal(back.K[1], [[457.587, 0, 379.999], [0, 456.134, 255.238],
                                              [0, 0, 1]])  # fmt: skip
    np.testing.assert_array_equal(back.dist[0], [-0.28340811, 0.07395907, 0.00019359,
                                                 1.76187114e-05, 0.0])  # fmt: skip
    np.testing.assert_allclose(back.R[1], T[:3, :3], atol=1e-15)
    np.testing.assert_allclose(back.t[1], T[:3, 3], atol=1e-15)
    chain["cam1"]["camera_model"] = "omni"
    path.write_text(yaml.safe_dump(chain))
    with pytest.raises(ValueError, match="camera_model 'omni'"):
        mc.io.load_kalibr(path)
    path.write_text("cameras: [a]\n")
    with pytest.raises(ValueError, match="not a Kalibr camera chain"):
        mc.io.load_kalibr(path)


# ---------------------------------------------------------------------------- ROS camera_info
ROS_FILE = """image_width: 1280
image_height: 800
camera_name: narrow_stereo
camera_matrix:
    rows: 3
    cols: 3
    data: [415.12614, 0., 665.52373,
           0., 410.49986, 460.14929,
           0., 0., 1.               ]
distortion_model: plumb_bob
distortion_coefficients:
    rows: 1
    cols: 5
    data: [-0.017697, -0.007270, 0.005751, -0.000139, 0.]
rectification_matrix:
    rows: 3
    cols: 3
    data: [1., 0., 0.,
           0., 1., 0.,
           0., 0., 1.]
projection_matrix:
    rows: 3
    cols: 4
    data: [415.12614, 0., 665.52373, 0.,
           0., 410.27547, 459.89776, 0.,
           0., 0., 1., 0.]
"""


def test_load_ros_reads_a_camera_info_file_as_ros_writes_it(tmp_path):
    """Matrices over several lines, as ROS's calibrator writes them; no pose in the file."""
    path = tmp_path / "ost.yaml"
    path.write_text(ROS_FILE)
    camera, names = mc.io.load_ros(path)
    assert names == ["narrow_stereo"] and camera.batch_shape == () and camera.lens == "pinhole"
    _equal(camera.K, [[415.12614, 0, 665.52373], [0, 410.49986, 460.14929], [0, 0, 1]])
    _equal(camera.dist, [-0.017697, -0.007270, 0.005751, -0.000139, 0.0])
    assert bool(jnp.isnan(camera.t).all())
    with pytest.raises(ValueError, match=r"ROS camera_info file; read it with mc.io.load_ros"):
        mc.io.load_opencv(path)
    # as PyYAML writes it (block lists indented as their keys), and with comments
    import yaml

    commented = ROS_FILE.replace("plumb_bob", "plumb_bob  # k1 k2 p1 p2 k3").replace(
        "camera_name: narrow_stereo", "# the left camera\ncamera_name: 'narrow_stereo'  # #1"
    )
    for text in (yaml.dump(yaml.safe_load(ROS_FILE)), commented):
        path.write_text(text)
        again, names = mc.io.load_ros(path)
        assert names == ["narrow_stereo"]
        _equal(again.K, camera.K)
        _equal(again.dist, camera.dist)
    path.write_text(ROS_FILE.replace("camera_matrix:", "camera_matrx:"))
    with pytest.raises(ValueError, match="camera_matrix is missing or malformed.*camera_info"):
        mc.io.load_ros(path)


def _ros_pair(lens="pinhole"):
    R = np.stack([np.eye(3), np.asarray(mc.rodrigues(np.array([0.02, 0.08, -0.01])))])
    dist = [[-0.12, 0.03, 1e-3, -5e-4, 0.0]] if lens == "pinhole" else [[0.05, -0.01, 2e-3, 0.0]]
    return mc.Camera([800.0, 820.0], [805.0, 818.0], [640.0, 628.0], [400.0, 410.0], R,
                     [[0.0, 0.0, 0.0], [-0.12, 0.004, 0.01]], dist=dist * 2, lens=lens)  # fmt: skip


def _ros_matrices(path):
    import yaml

    info = yaml.safe_load(path.read_text())
    return {k: np.reshape(v["data"], (v["rows"], v["cols"])) for k, v in info.items()
            if isinstance(v, dict)}  # fmt: skip


def test_save_ros_writes_opencvs_new_camera_matrix_and_reads_back(tmp_path):
    import cv2

    camera = _ros_pair()[0]
    (path,) = mc.io.save_ros(tmp_path / "cam.yaml", camera, (1280, 800))
    written = _ros_matrices(path)  # read with PyYAML, not with load_ros
    K, D = np.asarray(camera.K), np.asarray(camera.dist)
    new, _ = cv2.getOptimalNewCameraMatrix(K, D, (1280, 800), 0.0)
    # (OpenCV's five undistortion steps stop short with k1 -0.12: 1.4e-3 px, docs/reliability)
    np.testing.assert_allclose(written["projection_matrix"][:, :3], new, atol=3e-3)  # px
    _equal(written["rectification_matrix"], np.eye(3))
    back, names = mc.io.load_ros(path)
    assert names == ["cam"]
    _equal(back.K, camera.K)
    _equal(back.dist, camera.dist)


@pytest.mark.parametrize("lens", ["pinhole", "fisheye"])
def test_a_stereo_pair_goes_through_ros_with_its_rectification_and_pose(tmp_path, lens):
    import cv2

    pair = _ros_pair(lens)
    paths = mc.io.save_ros([tmp_path / "left.yaml", tmp_path / "right.yaml"], pair, (1280, 800))
    left, right = (_ros_matrices(p) for p in paths)
    # R1, R2, P1, P2 as OpenCV's rectification of the pair (alpha 0, ROS's calibrator's)
    K1, K2, D1, D2 = (np.asarray(x) for x in (pair.K[0], pair.K[1], pair.dist[0], pair.dist[1]))
    R, T = np.asarray(pair.R[1]), np.asarray(pair.t[1])[:, None]  # camera 0 is the world
    rectify = cv2.stereoRectify if lens == "pinhole" else cv2.fisheye.stereoRectify
    flags = cv2.CALIB_ZERO_DISPARITY
    if lens == "pinhole":
        R1, R2, P1, P2 = rectify(K1, D1, K2, D2, (1280, 800), R, T, flags=flags, alpha=0.0)[:4]
        np.testing.assert_allclose(left["rectification_matrix"], R1, atol=1e-8)
        np.testing.assert_allclose(right["rectification_matrix"], R2, atol=1e-8)
        # (to 4e-6 of f': OpenCV undistorts the image's border in five steps that stop short)
        np.testing.assert_allclose(right["projection_matrix"], P2, rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(left["projection_matrix"], P1, rtol=1e-5, atol=1e-9)
    back, names = mc.io.load_ros(*paths)
    assert names == ["left", "right"] and back.lens == lens
    _equal(back.K, pair.K)
    _equal(back.dist, pair.dist)
    np.testing.assert_allclose(back.R, pair.R, atol=1e-12)
    np.testing.assert_allclose(back.t, pair.t, atol=1e-12)
    # files that are not a rectified pair: no pose
    single = mc.io.save_ros(tmp_path / "one.yaml", pair[0], (1280, 800))
    assert bool(jnp.isnan(mc.io.load_ros(paths[0], *single)[0].R).all())


def test_save_ros_refuses_what_ros_cannot_hold(tmp_path):
    pair = _ros_pair()
    skewed = eqx.tree_at(lambda c: c.skew, pair, jnp.array([0.5, 0.0]))
    with pytest.raises(ValueError, match="no skew"):
        mc.io.save_ros([tmp_path / "a.yaml", tmp_path / "b.yaml"], skewed, (1280, 800))
    with pytest.raises(ValueError, match=r"one camera to one path or a stereo pair to two"):
        mc.io.save_ros(tmp_path / "a.yaml", pair, (1280, 800))
    with pytest.raises(ValueError, match="image_size"):
        mc.io.save_ros(tmp_path / "a.yaml", pair[0], 1280)
    # the right camera first (a robotics user's trial: swapped files, silently)
    swapped = jax.tree_util.tree_map(lambda x: x[::-1], pair)
    with pytest.raises(ValueError, match=r"second camera stands to the left.*cameras\[::-1\]"):
        mc.io.save_ros([tmp_path / "a.yaml", tmp_path / "b.yaml"], swapped, (1280, 800))
    assert not list(tmp_path.iterdir())
    # ROS's metres: a pair in millimetres warns, and `metres_per_unit` scales it
    in_mm = eqx.tree_at(lambda c: c.t, pair, pair.t * 1000.0)
    paths = [tmp_path / "a.yaml", tmp_path / "b.yaml"]
    with pytest.warns(UserWarning, match=r"stand 120.\d+ m apart.*millimetres"):
        mc.io.save_ros(paths, in_mm, (1280, 800))
    mc.io.save_ros(paths, in_mm, (1280, 800), metres_per_unit=0.001)
    np.testing.assert_allclose(mc.io.load_ros(*paths)[0].t, pair.t, atol=1e-12)
