"""A rig watching a moving target: observation files (exact round trips, one-line errors) and
caliscope's `xy.csv` and `camera_array.toml` (../shared/data/SOURCE.md, section 6)."""

import csv

import numpy as np
import pytest
from conftest import data_dir

import mvcalib as mc

HEADER = "camera,frame,point,target_x,target_y,target_z,pixel_x,pixel_y\n"
XY_HEADER = (
    "sync_index,cam_id,frame_index,frame_time,object_id,keypoint_id,"
    "img_loc_x,img_loc_y,obj_loc_x,obj_loc_y\n"
)


def _same(a: mc.io.Observations, b: mc.io.Observations):
    for name in ("target", "pixels", "mask", "frames", "points"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape and x.dtype == y.dtype, name
        assert np.array_equal(x, y, equal_nan=True), name  # bit-exact doubles but NaN == NaN
    assert a.cameras == b.cameras


def _random(rng, C=4, F=6, N=9):
    """Observations with extreme doubles, a camera that saw nothing, a frame and a point that
    nobody saw, unsorted camera names, and ids that are neither 0, 1, ... nor positive."""
    target = rng.standard_normal((N, 3)) * 10.0 ** rng.integers(-12, 12, (N, 3))
    target[: N // 2, 2] = 0.0  # partly a board
    pixels = rng.uniform(-10, 1300, (C, F, N, 2)) * 10.0 ** rng.integers(-8, 8, (C, F, N, 2))
    mask = rng.random((C, F, N)) < 0.5
    mask[rng.integers(C)] = False  # a camera that saw nothing
    mask[:, rng.integers(F)] = False  # a frame in which nobody saw anything
    mask[:, :, rng.integers(N)] = False  # a point nobody saw
    pixels = np.where(mask[..., None], pixels, np.nan)
    frames = np.sort(rng.choice(np.arange(-50, 10**6), F, replace=False))
    points = np.sort(rng.choice(np.arange(-5, 100), N, replace=False))
    cameras = [f"cam {c}" for c in rng.permutation(C)]
    return mc.io.Observations(target, pixels, mask, cameras, frames, points)


# ---------------------------------------------------------------------------- caliscope, real
def test_caliscope_real_data_has_1725_observations_of_12_corners_by_4_cameras_in_48_frames():
    root = data_dir("caliscope_4cam")
    o = mc.io.load_caliscope(root / "xy.csv")
    assert int(o.mask.sum()) == 1725
    assert o.cameras == ["cam_0", "cam_1", "cam_2", "cam_3"]
    assert o.frames.shape == (48,) and np.all(np.diff(o.frames) > 0)
    assert o.points.tolist() == list(range(12))
    assert o.pixels.shape == (4, 48, 12, 2) and o.target.shape == (12, 3)
    assert np.all(o.target[:, 2] == 0) and np.ptp(o.target[:, 0]) > 0.1  # a 5.4 cm grid
    assert np.array_equal(np.isfinite(o.pixels[..., 0]), o.mask)
    # every row of the file is where it should be, to the bit
    with open(root / "xy.csv", newline="") as f:
        for row in csv.DictReader(f):
            c, n = int(row["cam_id"]), int(row["keypoint_id"])
            f_ = int(np.searchsorted(o.frames, int(row["sync_index"])))
            assert o.pixels[c, f_, n].tolist() == [float(row["img_loc_x"]), float(row["img_loc_y"])]
            assert o.target[n].tolist() == [float(row["obj_loc_x"]), float(row["obj_loc_y"]), 0]
    _, names = mc.io.load_caliscope_cameras(root / "camera_array.toml")
    assert names == o.cameras


def test_caliscope_xy_with_its_recorder_s_column_names_reads_the_same(tmp_path):
    """caliscope's recorder (its `XYSchema`) names two columns `port` and `point_id`, the
    bundled recording `cam_id` and `keypoint_id`: a user's file with the former was refused
    with "no 'cam_id' column"."""
    root = data_dir("caliscope_4cam")
    text = (root / "xy.csv").read_text()
    header, body = text.split("\n", 1)
    renamed = header.replace("cam_id", "port").replace("keypoint_id", "point_id")
    (tmp_path / "xy.csv").write_text(renamed + "\n" + body)
    _same(mc.io.load_caliscope(tmp_path / "xy.csv"), mc.io.load_caliscope(root / "xy.csv"))


def test_caliscope_real_observations_survive_the_observations_file(tmp_path):
    o = mc.io.load_caliscope(data_dir("caliscope_4cam") / "xy.csv")
    path = mc.io.save_observations(tmp_path / "obs.csv", o)
    assert len(path.read_text().splitlines()) == 1 + 1725  # no frame, point or camera unseen
    _same(mc.io.load_observations(path), o)


def test_caliscope_cameras_project_like_opencv():
    cv2 = pytest.importorskip("cv2")
    import tomllib

    path = data_dir("caliscope_4cam") / "camera_array.toml"
    cameras, names = mc.io.load_caliscope_cameras(path)
    tables = tomllib.loads(path.read_text())["cameras"]
    assert names == [f"cam_{k}" for k in sorted(tables, key=int)] and len(names) == 4
    rng = np.random.default_rng(0)
    for i, key in enumerate(sorted(tables, key=int)):
        table = tables[key]
        K, R = np.array(table["matrix"]), np.array(table["rotation"])
        t, dist = np.array(table["translation"]), np.array(table["distortions"])
        # points the camera sees: over its 1280 x 720 image, 0.5 to 3 m away
        uv = np.c_[rng.uniform([0, 0], [1280, 720], (50, 2)), np.ones(50)]
        x_cam = np.linalg.solve(K, uv.T).T * rng.uniform(0.5, 3.0, (50, 1))
        world = (x_cam - t) @ R  # R^T (x_cam - t), row by row
        expected = cv2.projectPoints(world, cv2.Rodrigues(R)[0], t, K, dist)[0][:, 0]
        np.testing.assert_allclose(np.asarray(cameras[i].project(world)), expected, atol=1e-9)


# ---------------------------------------------------------------------------- caliscope, files
def test_caliscope_cameras_older_rodrigues_rotation_ids_in_number_order_and_uncalibrated(tmp_path):
    cv2 = pytest.importorskip("cv2")
    rvec, t = np.array([0.1, -0.2, 0.3]), np.array([0.05, -0.1, 1.2])
    K = [[700.0, 0.0, 630.0], [0.0, 705.0, 350.0], [0.0, 0.0, 1.0]]
    dist = [0.19, -0.26, 0.0028, -0.0052]  # four: k3 = 0
    path = tmp_path / "camera_array.toml"
    path.write_text(
        f"[cameras.10]\nmatrix = {K}\ndistortions = {dist}\n"
        f"rotation = {rvec.tolist()}\ntranslation = {t.tolist()}\n"
        f'[cameras.2]\nmatrix = {K}\nrotation = "null"\nignore = true\n'
    )
    cameras, names = mc.io.load_caliscope_cameras(path)
    assert names == ["cam_2", "cam_10"]
    assert np.isnan(np.asarray(cameras.R[0])).all() and np.isnan(np.asarray(cameras.t[0])).all()
    assert np.asarray(cameras.K[0]).tolist() == K
    assert np.asarray(cameras.dist[0]).tolist() == [0] * 5
    world = np.random.default_rng(1).uniform(-0.3, 0.3, (20, 3))
    expected = cv2.projectPoints(world, rvec, t, np.array(K), np.array(dist))[0][:, 0]
    np.testing.assert_allclose(np.asarray(cameras[1].project(world)), expected, atol=1e-9)


@pytest.mark.parametrize(
    "text, message",
    [
        ("[cam_0]\nmatrix = 1\n", "no [cameras.<id>] tables"),
        ("[cameras.0]\nmatrix = [[1.0, 0.0], [0.0, 1.0]]\n", "[cameras.0] is malformed"),
        ("[cameras.0]\nfisheye = true\n[cameras.1]\nmatrix = 1\n", "different lenses"),
        ("[cameras.0]\ndistortions = [1, 2, 3, 4, 5, 6]\n", "6 distortions"),
        ("[cameras.0\n", "not a readable TOML"),
    ],
)
def test_malformed_caliscope_cameras_are_refused(tmp_path, text, message):
    path = tmp_path / "camera_array.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        mc.io.load_caliscope_cameras(path)
    assert message in str(info.value) and str(path) in str(info.value)


def test_caliscope_xy_reads_obj_loc_z_and_ignores_column_order_and_extra_columns(tmp_path):
    path = tmp_path / "xy.csv"
    path.write_text(
        "keypoint_id,cam_id,sync_index,img_loc_y,img_loc_x,obj_loc_x,obj_loc_y,obj_loc_z,note\n"
        "5,3,9,2.5,1.5,0.1,0.2,0.3,x\n"
        "5,0,9.0,4.5,3.5,0.1,0.2,0.3,y\n"  # pandas may write ids as floats
    )
    o = mc.io.load_caliscope(path)
    assert o.cameras == ["cam_0", "cam_3"] and o.frames.tolist() == [9]
    assert o.target.tolist() == [[0.1, 0.2, 0.3]] and o.points.tolist() == [5]
    assert o.pixels[:, 0, 0].tolist() == [[3.5, 4.5], [1.5, 2.5]]


ROW = "416,1,413,48033.0,0,0,710.9,507.4,0.05400000140070915,0.05400000140070915\n"


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        (XY_HEADER.replace(",img_loc_y", ""), ":1: no 'img_loc_y' column"),
        (XY_HEADER + ROW.replace("710.9", "x"), ":2: img_loc_x, img_loc_y = 'x', '507.4' are not"),
        (XY_HEADER + ROW.replace("710.9", "nan"), ":2: NaN or inf in img_loc_x, img_loc_y"),
        (XY_HEADER + ROW.replace("416,1", "416,b"), ":2: cam_id 'b' is not an integer"),
        (XY_HEADER + ROW.replace("416,1", "416.5,1"), ":2: sync_index '416.5' is not an"),
        (XY_HEADER + ROW.replace("416,1", "1e30,1"), ":2: sync_index '1e30' is out of range"),
        (XY_HEADER + ROW + ROW.replace("413", "414"), ":3: camera 1 saw keypoint 0 in frame 416"),
        # float32 values written out: the same corner must be the same string of digits
        (
            XY_HEADER + ROW + ROW.replace("416", "417").replace("0.05400000140070915,", "0.054,"),
            ":3: keypoint 0 is at other board coordinates than on line 2",
        ),
        (XY_HEADER + ROW + ROW.replace(",0,0,", ",1,0,").replace("416", "417"), ":3: another"),
        (XY_HEADER + ROW.replace("0,0,710.9", "0,,710.9"), ":2: no keypoint_id"),
        (XY_HEADER + ROW.replace("48033.0,", ""), ":2: 9 fields; the header has 10"),
        (XY_HEADER, "no observations"),
    ],
)
def test_malformed_caliscope_xy_gives_one_line_naming_file_and_line(tmp_path, text, message):
    path = tmp_path / "xy.csv"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        mc.io.load_caliscope(path)
    assert message in str(info.value) and str(path) in str(info.value)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------- observation files
def test_round_trip_names_unseen_points_frames_and_silent_cameras(tmp_path):
    pixels = np.full((3, 3, 3, 2), np.nan)
    pixels[2, 0, 0] = [1.5, 2.0]
    pixels[1, 2, 1] = [1e-300, -0.0]
    o = mc.io.Observations(
        target=np.array([[0.0, 0.0, 0.0], [0.1, 0.2, 0.0], [1 / 3, 2.0, 0.0]]),
        pixels=pixels,
        mask=np.isfinite(pixels[..., 0]),
        cameras=["z, the last", 'a "quoted" one', "silent"][::-1],
        frames=np.array([-3, 7, 1000]),
        points=np.array([2, 5, 11]),
    )
    path = mc.io.save_observations(tmp_path / "obs.csv", o)
    assert path.read_text() == (
        HEADER
        + ",,11,0.3333333333333333,2.0,0.0,,\n"  # a point nobody saw
        + ",7,,,,,,\n"  # a frame in which nobody saw anything
        + "silent,,,,,,,\n"  # a camera that saw nothing
        + '"a ""quoted"" one",1000,5,0.1,0.2,0.0,1e-300,-0.0\n'
        + '"z, the last",-3,2,0.0,0.0,0.0,1.5,2.0\n'
    )
    _same(mc.io.load_observations(path), o)
    # saved by a spreadsheet as "CSV UTF-8": a byte-order mark before the header, CRLF lines
    # (the header's first column was "\ufeffcamera", an unknown column)
    excel = tmp_path / "excel.csv"
    excel.write_bytes(b"\xef\xbb\xbf" + path.read_text().replace("\n", "\r\n").encode())
    _same(mc.io.load_observations(excel), o)


@pytest.mark.parametrize("seed", range(8))
def test_randomized_round_trip_is_exact(tmp_path, seed):
    rng = np.random.default_rng(seed)
    o = _random(rng, *rng.integers(1, 7, 3))
    back = mc.io.load_observations(mc.io.save_observations(tmp_path / "obs.csv", o))
    _same(back, o)
    assert back.frames.dtype == back.points.dtype == np.int64


@pytest.mark.parametrize("shape", [(2, 3, 4), (1, 0, 0), (1, 2, 0), (2, 0, 3)])
def test_round_trip_when_nobody_saw_anything(tmp_path, shape):
    C, F, N = shape
    o = mc.io.Observations(
        np.arange(3.0 * N).reshape(N, 3), np.full((C, F, N, 2), np.nan), np.zeros(shape, bool),
        [f"c{i}" for i in range(C)], np.arange(F) * 2, np.arange(N) + 1,
    )  # fmt: skip
    _same(mc.io.load_observations(mc.io.save_observations(tmp_path / "obs.csv", o)), o)


def test_hand_written_file_with_comments_any_column_order_and_out_of_order_rows(tmp_path):
    path = tmp_path / "hand.csv"
    path.write_text(
        "# by hand\n"
        "pixel_x,pixel_y,camera,point,frame,target_x,target_y,target_z\n"
        "10,20,b,4,9,1,0,0\n"
        "\n"
        "11,21,a,4,3,1,0,0\n"
        "12,22,a,0,9,0,0,0\n"
    )
    o = mc.io.load_observations(path)
    assert o.cameras == ["b", "a"] and o.frames.tolist() == [3, 9] and o.points.tolist() == [0, 4]
    assert o.target.tolist() == [[0, 0, 0], [1, 0, 0]] and int(o.mask.sum()) == 3
    assert o.pixels[1, 1, 0].tolist() == [12, 22] and o.pixels[0, 1, 1].tolist() == [10, 20]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        ("# nothing but a comment\n", "empty"),
        (HEADER.replace(",pixel_y", ""), ":1: no 'pixel_y' column"),
        (HEADER.replace("\n", ",colour\n"), ":1: unknown column 'colour'"),
        (HEADER.replace("\n", ",frame\n"), ":1: a repeated column"),
        (HEADER + "a,1,0,0,0,0,2\n", ":2: 7 fields; the header has 8"),
        (HEADER + "a,1,0,0,0,0,2,x\n", ":2: pixel_x, pixel_y = '2', 'x' are not all numbers"),
        (HEADER + "a,1,0,0,0,0,,744.9\n", ":2: pixel_x, pixel_y = '', '744.9' are not all numbers"),
        (HEADER + "a,1,0,0,0,0,2,nan\n", ":2: NaN or inf in pixel_x, pixel_y"),
        (HEADER + "a,1,0,0,inf,0,2,3\n", ":2: NaN or inf in target_x, target_y, target_z"),
        (HEADER + "a,1.5,0,0,0,0,2,3\n", ":2: frame '1.5' is not an integer"),
        (HEADER + "a,1,p,0,0,0,2,3\n", ":2: point 'p' is not an integer"),
        (HEADER + "a,1e30,0,0,0,0,2,3\n", ":2: frame '1e30' is out of range"),
        (HEADER + f"a,{2**63},0,0,0,0,2,3\n", f":2: frame '{2**63}' is out of range"),
        (
            HEADER + "a,1,0,0,0,0,2,3\nb,2,0,0,0,1,2,3\n",
            ":3: point 0 has other target coordinates than on line 2",
        ),
        (HEADER + ",,0,0,0,0,,\na,2,0,0,0,1e-300,2,3\n", ":3: point 0 has other target"),
        (
            HEADER + "a,1,0,0,0,0,2,3\na,1,0,0,0,0,2,3\n",
            ":3: camera 'a' saw point 0 in frame 1 on line 2 too",
        ),
        (HEADER + "a,1,0,,,,2,3\n", ":2: a point needs its target coordinates"),
        (HEADER + "a,1,,1,2,3,2,3\n", ":2: a point needs its target coordinates"),
        (HEADER + "a,1,0,0,0,0,,\n", ":2: camera 'a' without a frame, a point and a pixel"),
        (HEADER + "a,,0,0,0,0,2,3\n", ":2: camera 'a' without a frame, a point and a pixel"),
        (HEADER + ",1,0,0,0,0,2,3\n", ":2: a pixel (or an empty row) without a camera"),
        (HEADER + ",,,,,,,\n", ":2: a pixel (or an empty row) without a camera"),
        (HEADER + ",,0,0,0,0,,\n,4,,,,,,\n", "no cameras"),
    ],
)
def test_malformed_observations_give_one_line_naming_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        mc.io.load_observations(path)
    assert message in str(info.value) and str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_files_are_a_value_error(tmp_path):
    for load in (mc.io.load_observations, mc.io.load_caliscope, mc.io.load_caliscope_cameras):
        with pytest.raises(ValueError, match="cannot be read|not a readable"):
            load(tmp_path / "missing")


@pytest.mark.parametrize(
    "change, message",
    [
        ({"frames": np.array([3, 1, 2])}, "`frames` must be strictly ascending"),
        ({"points": np.array([0.0, 1.0, 2.0, 3.0])}, "`points` must be a 1-D array of integer"),
        ({"cameras": ["a", "a"]}, "different camera names"),
        ({"cameras": ["a", " b"]}, "different camera names"),
        ({"cameras": ["a", "b\nc"]}, "line breaks"),
        ({"cameras": ["a", "#b"]}, "nor start with '#'"),  # it would read as a comment
        ({"target": np.full((4, 3), np.nan)}, "`target` must be finite"),
        ({"pixels": np.ones((2, 3, 4, 3))}, "`pixels` must be (C, F, N, 2)"),
        ({"mask": np.ones((2, 3, 4), int)}, "`mask` must be bool"),
        ({"mask": np.ones((2, 3, 4), bool)}, "NaN or inf entries where `mask` is True"),
        (
            {"cameras": [], "pixels": np.ones((0, 3, 4, 2)), "mask": np.ones((0, 3, 4), bool)},
            "one or more",
        ),
    ],
)
def test_save_refuses_inconsistent_observations_and_writes_nothing(tmp_path, change, message):
    o = _random(np.random.default_rng(0), 2, 3, 4)
    fields = {k: getattr(o, k) for k in ("target", "pixels", "mask", "cameras", "frames", "points")}
    with pytest.raises(ValueError) as info:
        mc.io.save_observations(tmp_path / "obs.csv", mc.io.Observations(**{**fields, **change}))
    assert message in str(info.value)
    assert not (tmp_path / "obs.csv").exists()


def test_integral_float_ids_are_read_as_integers(tmp_path):
    """pandas writes an integer column with gaps as floats (`109.0`): such frame and point ids
    were refused ("frame '109.0' is not an integer"); 1.5 still is."""
    path = tmp_path / "obs.csv"
    path.write_text(HEADER + "a,109.0,3.0,0,0,0,2,3\na,109,4,1,0,0,5,6\n")
    o = mc.io.load_observations(path)
    assert o.frames.tolist() == [109] and o.points.tolist() == [3, 4]
    assert o.mask.tolist() == [[[True, True]]]
