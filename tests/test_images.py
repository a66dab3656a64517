"""From photographs to cameras: calibrate_images, the image demo, the rig file, and the CLI."""

import dataclasses
import json
import os
import re
import subprocess
import sys

import equinox as eqx
import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mvcalib as mc
from mvcalib import demo
from mvcalib.synthetic import render

TARGET = mc.targets.box_corner()


@pytest.fixture(scope="module")
def image_demo(tmp_path_factory):
    figure = tmp_path_factory.mktemp("demo") / "stages.png"
    return demo.run_images(figure=figure)


def test_demo_images_calibrate_within_one_percent_and_half_a_degree(image_demo):
    # The paper's four snapshots, rendered (blur 1 px, noise 3 grey levels, gradient, clutter),
    # then detected, labelled and calibrated with no correspondence given.
    assert image_demo.result.ok.all()
    assert image_demo.result.mask.all()  # all 19 dots labelled in every snapshot
    print(
        f"\nfocal error {np.round(100 * image_demo.focal_error, 3)} %, rotation error "
        f"{np.round(image_demo.rotation_error, 3)} deg"
    )
    assert (image_demo.focal_error < 0.01).all()
    assert (image_demo.rotation_error < 0.5).all()
    # The fixed room point lands on one pixel from every snapshot: measured within 0.015 px
    # (0.11 px without the correction of the dots' perspective bias).
    assert np.ptp(image_demo.unified, axis=0).max() < 0.05


def test_demo_writes_the_processing_stage_figure(image_demo):
    picture = iio.imread(image_demo.figure)
    height, width = image_demo.images[0].shape
    assert picture.shape == (2 * height + 12, 3 * width + 24, 3)
    # Panel 2 (binary) is black and white only; panel 6 (detected) has colour.
    binary = picture[:height, width + 12 : 2 * width + 12]
    assert set(np.unique(binary)) <= {0, 255}
    detected = picture[height + 12 :, 2 * width + 24 :]
    assert np.ptp(detected.astype(int), axis=-1).max() > 100
    assert not list(image_demo.figure.parent.glob(".*.tmp"))  # atomic write left nothing behind


def test_bad_images_are_flagged_and_the_good_ones_calibrated_as_if_alone(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(7), 2)
    good = [render(rig.cameras[i], TARGET, key=i) for i in range(2)]
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    bad = [
        np.zeros((0, 0)),  # empty
        np.full((200, 200), 90, np.uint8),  # constant
        np.ones((200, 200)) + 1j,  # wrong dtype
        corrupt,  # not an image
        tmp_path / "missing.png",
        render(rig.cameras[0], mc.targets.box_corner_grid(4), key=3),  # another target
    ]
    result = mc.calibrate_images(good + bad, TARGET)
    alone = mc.calibrate_images(good, TARGET)
    assert result.ok.tolist() == [True, True] + [False] * len(bad)
    status = np.asarray(result.calibration.status)
    assert (status[2:] == mc.Status.NOT_LABELLED).all()
    for i in range(2):
        np.testing.assert_array_equal(
            np.asarray(result.calibration.P[i]), np.asarray(alone.calibration.P[i])
        )
    assert np.isnan(np.asarray(result.cameras.alpha_u[2:])).all()
    messages = result.messages[2:]
    for message, word in zip(
        messages, ["empty", "constant", "complex", "cannot be read", "no such file", "fiducial"]
    ):
        assert word in message, message
    text = str(result)
    assert "missing.png" in text and "calibrated" in text and "back-projection" in text
    with pytest.raises(mc.CalibrationError, match="6 of 8 images gave no camera"):
        result.raise_if_failed()
    with pytest.raises(mc.CalibrationError):
        mc.calibrate_images(good + bad[:1], TARGET, strict=True)
    # the same read and detected in two worker processes, the bad images' reasons included
    environment = dict(os.environ)
    in_workers = mc.calibrate_images(good + bad, TARGET, workers=2)
    assert in_workers.messages == result.messages and dict(os.environ) == environment
    np.testing.assert_array_equal(in_workers.calibration.P, result.calibration.P)
    with pytest.raises(ValueError, match="at least 1"):
        mc.calibrate_images(good, TARGET, workers=0)


def test_bright_dots_searched_as_dark_ones_get_a_hint():
    """A user's trial: OpenPTV's back-lit dots searched as dark dots gave "only 0 blobs found",
    with nothing pointing at `dark_dots`."""
    camera = mc.synthetic.random_rig(jax.random.key(7), 1).cameras[0]
    bright = 255 - np.asarray(render(camera, TARGET, key=0), np.uint8)
    result = mc.calibrate_images([bright], TARGET)
    assert not result.ok[0] and "bright dots on a dark ground?" in result.messages[0]
    assert mc.calibrate_images([bright], TARGET, detect=dict(dark_dots=False)).ok[0]


def test_removing_the_perspective_bias_of_the_dots_brings_the_cameras_closer():
    rig = mc.synthetic.random_rig(jax.random.key(11), 4)
    photos = [render(rig.cameras[i], TARGET, key=i) for i in range(4)]
    raw = mc.calibrate_images(photos, TARGET, bias_iterations=0)
    corrected = mc.calibrate_images(photos, TARGET)
    truth = np.asarray(rig.cameras.projection_matrix())

    def errors(result):
        cameras = result.cameras
        focal = np.abs(np.asarray(cameras.alpha_u) / np.asarray(rig.cameras.alpha_u) - 1)
        centre = np.linalg.norm(np.asarray(cameras.center - rig.cameras.center), axis=-1)
        return focal, centre

    (f0, c0), (f1, c1) = errors(raw), errors(corrected)
    print(
        f"\nfocal error {np.round(100 * f0, 3)} % -> {np.round(100 * f1, 3)} %, "
        f"centre error {np.round(c0, 3)} -> {np.round(c1, 3)} mm"
    )
    assert truth.shape == (4, 3, 4) and corrected.ok.all()
    assert f1.mean() < 0.5 * f0.mean() and c1.mean() < 0.5 * c0.mean()
    assert corrected.bias_removed and not raw.bias_removed
    # a target whose dots' radius is unknown (`targets.from_file`'s default) keeps the raw
    # centroids, and says so (it did silently: a photographer's trial)
    unknown = dataclasses.replace(TARGET, dot_radius=np.nan)
    with pytest.warns(UserWarning, match="dot radius is unknown.*not removed"):
        kept = mc.calibrate_images(photos, unknown)
    assert not kept.bias_removed and "note: the target's dot radius is unknown" in str(kept)
    np.testing.assert_allclose(kept.cameras.alpha_u, raw.cameras.alpha_u, rtol=1e-9)
    # What is left is the centroids' own noise: Table I on the corrected centroids.
    assert float(corrected.calibration.report.rms.max()) < 0.1


def test_colour_and_16_bit_photographs_give_the_same_cameras():
    camera = mc.synthetic.random_rig(jax.random.key(8), 1).cameras[0]
    grey = render(camera, TARGET, key=8)
    variants = [grey, np.repeat(grey[..., None], 3, axis=-1), grey.astype(np.uint16) * 257]
    result = mc.calibrate_images(variants, TARGET)
    assert result.ok.all()
    P = np.asarray(result.calibration.P)
    np.testing.assert_allclose(P[1], P[0], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(P[2], P[0], rtol=1e-6, atol=1e-9)
    assert "mirrored" not in str(result)


def test_a_transposed_photograph_is_named_as_seeing_a_mirror_image():
    """A transposed photo calibrates (a mirror image is a camera too), OK, with the points
    behind it: its result names it below the table, with the likely causes."""
    camera = mc.synthetic.random_rig(jax.random.key(8), 1).cameras[0]
    grey = render(camera, TARGET, key=8)
    result = mc.calibrate_images([grey, grey.T], TARGET)
    assert result.ok.all() and np.asarray(result.calibration.mirrored).tolist() == [False, True]
    assert "mirrored: camera image 1 sees a mirror image of the world (a photo transposed" in str(
        result
    )


@pytest.mark.parametrize(
    "images, message",
    [
        (np.zeros((100, 100)), "one image"),
        (np.zeros((100, 100, 3)), "one image"),
        ([], "empty"),
        (42, "list of images"),
    ],
    ids=["2-D array", "colour array", "empty list", "number"],
)
def test_calibrate_images_refuses_what_is_not_a_list_of_images(images, message):
    with pytest.raises(ValueError, match=message):
        mc.calibrate_images(images)


# ---------------------------------------------------------------------------- rig files
def test_rig_json_round_trip_is_exact_including_failed_cameras(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(9), 3).cameras
    rig = jax.tree_util.tree_map(lambda x: x.at[1].set(jax.numpy.nan), rig)  # a failed camera
    path = mc.io.save_json(tmp_path / "rig.json", rig, names=["a", "b", "c"], status=[0, 5, 0])
    back, names = mc.io.load_json(path)
    assert names == ["a", "b", "c"]
    for field in ("alpha_u", "alpha_v", "u0", "v0", "skew", "R", "t", "dist"):
        np.testing.assert_array_equal(np.asarray(getattr(back, field)), getattr(rig, field))
    document = json.loads(path.read_text())
    assert document["format"] == "mvcalib.rig" and document["version"] == 1
    assert document["cameras"][1]["alpha_u"] is None and document["cameras"][1]["status"] == 5
    assert [p.name for p in tmp_path.iterdir()] == ["rig.json"]  # no temporary file left


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not a readable JSON"),
        ('{"format": "other"}', "not an mvcalib rig"),
        ('{"format": "mvcalib.rig", "version": 99, "cameras": []}', "version 99"),
        ('{"format": "mvcalib.rig", "version": 1, "cameras": []}', "no cameras"),
        ('{"format": "mvcalib.rig", "version": 1, "cameras": [{"alpha_u": 1}]}', "malformed"),
    ],
    ids=["broken", "foreign", "version", "empty", "missing fields"],
)
def test_bad_rig_files_are_refused(tmp_path, content, message):
    path = tmp_path / "rig.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        mc.io.load_json(path)


def test_a_rig_file_whose_R_is_not_a_rotation_is_refused(tmp_path, monkeypatch):
    """Any 3 x 3 matrix was taken as R (JSON and OpenCV's YAML), and projected as given. The
    writers refuse such a rig too; a file written otherwise (by hand, by another tool: here
    the writers' check turned off) is refused by the readers."""
    rig = mc.synthetic.random_rig(jax.random.key(0), 2).cameras
    cases = ((np.diag([1.0, 1.0, 1.01]), "R^T R is 0.02 off the identity"),
             (np.diag([1.0, 1.0, -1.0]), "its determinant is -1: a reflection"))  # fmt: skip
    for R, said in cases:
        bad = eqx.tree_at(lambda c: c.R, rig, rig.R.at[1].set(R))
        for save, load, name in ((mc.io.save_json, mc.io.load_json, "rig.json"),
                                 (mc.io.save_opencv, mc.io.load_opencv, "rig.yml")):  # fmt: skip
            with pytest.raises(ValueError, match=re.escape("camera 1: R is not a rotation")):
                save(tmp_path / name, bad)
            with monkeypatch.context() as m:
                m.setattr(mc.io, "_check_cameras", lambda cameras, function: None)
                path = save(tmp_path / name, bad)
            with pytest.raises(
                ValueError, match=re.escape(f"'cam_1': R is not a rotation ({said}")
            ):
                load(path)
    # a hand-written R rounded to six digits is a rotation to that rounding
    rounded = eqx.tree_at(lambda c: c.R, rig, jnp.round(rig.R, 6))
    mc.io.load_json(mc.io.save_json(tmp_path / "rig.json", rounded))


def test_a_failed_write_leaves_the_old_rig_file_whole(tmp_path, monkeypatch):
    path = tmp_path / "rig.json"
    path.write_text("old contents")

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(mc.io.os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        mc.io.write_atomic(path, "new contents")
    assert path.read_text() == "old contents"
    assert [p.name for p in tmp_path.iterdir()] == ["rig.json"]


# ---------------------------------------------------------------------------- command line
def _cli(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "mvcalib", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=cwd,
    )


def test_cli_calibrate_images_writes_the_rig_and_flags_bad_files(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(10), 2)
    paths = []
    for i in range(2):
        paths.append(tmp_path / f"cam{i}.png")
        iio.imwrite(paths[-1], render(rig.cameras[i], TARGET, key=i, clutter=3))
    out = tmp_path / "rig.json"
    result = _cli("calibrate-images", *paths, "--out", out)
    assert result.returncode == 0, result.stderr
    assert "2 of 2 cameras calibrated" in result.stdout
    assert "[1/2]" in result.stderr and "[2/2]" in result.stderr  # progress, per image
    cameras, names = mc.io.load_json(out)
    assert names == [str(p) for p in paths]
    api = mc.calibrate_images(paths, TARGET)
    np.testing.assert_allclose(np.asarray(cameras.K), np.asarray(api.cameras.K), rtol=1e-9)
    truth = np.asarray(rig.cameras.alpha_u)
    assert np.abs(np.asarray(cameras.alpha_u) / truth - 1).max() < 0.01
    # OpenCV's YAML by --out's suffix (it wrote JSON into rig.yml), and the labelled dots, which
    # `report` checks the rig against
    yml, dots = tmp_path / "rig.yml", tmp_path / "dots.csv"
    result = _cli("calibrate-images", *paths, "--refine", "--out", yml, "--dots", dots, "--quiet")
    assert result.returncode == 0, result.stderr
    assert "2 cameras written to" in result.stdout and "(opencv)" in result.stdout
    from_yaml, _ = mc.io.load_opencv(yml)
    refined = mc.calibrate_images(paths, TARGET, refine=True).cameras
    np.testing.assert_allclose(np.asarray(from_yaml.K), np.asarray(refined.K), rtol=1e-12)
    without = _cli("calibrate-images", *paths, "--out", yml, "--quiet")  # (the DLT's skew)
    assert without.returncode == 2 and "--format opencv needs --refine" in without.stderr
    data = mc.io.load_correspondences(dots)
    assert data.pixels.shape == (2, len(TARGET.points), 2)
    np.testing.assert_array_equal(data.mask, api.mask)
    report = _cli("report", out, dots, "--quiet")
    assert report.returncode == 0 and "all cameras" in report.stdout, report.stderr
    wrong = _cli("calibrate-images", *paths, "--out", yml, "--format", "json")
    assert wrong.returncode == 2 and "--format json writes a .json file" in wrong.stderr

    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"GIF89a and then nothing")
    result = _cli("calibrate-images", paths[0], corrupt, "--out", out, "--quiet")
    # The work partly failed (exit code 1); the rig is written all the same, quietly.
    assert result.returncode == 1 and result.stderr == ""
    document = json.loads(out.read_text())
    assert [c["status"] for c in document["cameras"]] == [0, int(mc.Status.NOT_LABELLED)]
    assert "cannot be read" in result.stdout


def test_cli_refuses_fewer_than_one_worker(tmp_path):
    (tmp_path / "a.png").write_bytes(b"not read: the arguments are checked first")
    for command in (["calibrate-images", "a.png"], ["observe-grid", "--grid", "3", "3", "1",
                                                     "--camera", "a.png"]):  # fmt: skip
        result = _cli(*command, "--out", "out.csv", "--workers", "0", cwd=tmp_path)
        assert result.returncode == 2 and "--workers must be at least 1" in result.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["calibrate-images", "nowhere.png", "--out", "rig.json"], "no such image file"),
        (["calibrate-images", "--out", "rig.json"], "required"),
        (["calibrate-images", "x.png"], "--out"),
        (["demo", "--bogus"], "unrecognized arguments"),
        (
            ["calibrate-images", "a.png", "b.png", "--out", "r.json", "--names", "a"],
            "--names takes one name a photo",
        ),
        (
            ["calibrate-images", "a.png", "--out", "r.json", "--trust-clicks"],
            "--trust-clicks is about the ids of --clicks",
        ),
        (
            ["calibrate-images", "a.png", "--out", "r.json", "--huber", "0"],
            "--huber must be positive",
        ),
        (
            ["calibrate-images", "a.png", "--out", "r.json", "--dot-radius", "2"],
            "--dot-radius is the --target file's dots' radius",
        ),
    ],
    ids=["missing file", "no images", "no --out", "bad flag", "names", "trust", "huber", "radius"],
)
def test_cli_bad_usage_is_one_line_and_exit_code_2(tmp_path, args, message):
    for name in ("a.png", "b.png"):  # (files that exist: the arguments are checked first)
        (tmp_path / name).write_bytes(b"not read")
    result = _cli(*args, cwd=tmp_path)
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "rig.json").exists()


def test_opencv_yaml_round_trip_is_exact_and_opencv_reads_the_same_numbers(tmp_path):
    cv2 = pytest.importorskip("cv2")
    rig = mc.synthetic.random_rig(jax.random.key(12), 3).cameras
    dist = np.array([[-0.21, 0.093, 1.2e-3, -7e-4, 0.011]] * 3)
    rig = mc.Camera.from_matrices(rig.K, rig.R, rig.t, dist)
    path = mc.io.save_opencv(tmp_path / "rig.yml", rig, image_size=(1000, 1100))
    back, names = mc.io.load_opencv(path)
    assert names == ["cam_0", "cam_1", "cam_2"]
    for field in ("K", "R", "t", "dist"):
        np.testing.assert_array_equal(np.asarray(getattr(back, field)), getattr(rig, field))
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    for i in range(3):
        node = storage.getNode(f"cam_{i}")
        np.testing.assert_array_equal(node.getNode("camera_matrix").mat(), np.asarray(rig.K[i]))
        np.testing.assert_array_equal(node.getNode("R").mat(), np.asarray(rig.R[i]))
        np.testing.assert_array_equal(node.getNode("T").mat()[:, 0], np.asarray(rig.t[i]))
        np.testing.assert_array_equal(
            node.getNode("distortion_coefficients").mat()[0], np.asarray(rig.dist[i])
        )
        assert int(node.getNode("image_width").real()) == 1000
    storage.release()
    # A file OpenCV writes (one camera, top-level keys, data over several lines) reads back too.
    written = tmp_path / "opencv.yml"
    storage = cv2.FileStorage(str(written), cv2.FILE_STORAGE_WRITE)
    for key, value in (("camera_matrix", np.asarray(rig.K[1])), ("R", np.asarray(rig.R[1])),
                       ("T", np.asarray(rig.t[1])[:, None]),
                       ("distortion_coefficients", np.asarray(rig.dist[1])[None])):  # fmt: skip
        storage.write(key, value)
    storage.release()
    single, _ = mc.io.load_opencv(written)
    assert single.batch_shape == ()
    np.testing.assert_array_equal(np.asarray(single.K), np.asarray(rig.K[1]))
    np.testing.assert_array_equal(np.asarray(single.dist), np.asarray(rig.dist[1]))
    bad = tmp_path / "bad.yml"
    bad.write_text("%YAML:1.0\n---\ncamera_matrix: 3\n")
    with pytest.raises(ValueError, match="lacks"):
        mc.io.load_opencv(bad)


def test_opencv_yaml_as_filestorage_writes_it_and_what_opencv_cannot_hold(tmp_path):
    """Files `cv2.FileStorage` writes itself: `cameras` as a block sequence and `R` as a
    rotation vector were refused ("lacks camera_matrix"); they read now and project as
    `cv2.projectPoints` does. XML and JSON are named as such. A pinhole with skew is refused
    (`cv2.projectPoints` ignores K[0,1]: the file put points up to 10 px off on Oxford's house),
    as is a camera named `cameras`, the key that lists them."""
    cv2 = pytest.importorskip("cv2")
    rig = mc.synthetic.random_rig(jax.random.key(14), 2).cameras
    dist = np.array([[-0.21, 0.093, 1.2e-3, -7e-4, 0.011]] * 2)
    rig = mc.Camera.from_matrices(rig.K, rig.R, rig.t, dist)
    path = tmp_path / "cv.yml"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.startWriteStruct("cameras", cv2.FileNode_SEQ)
    for name in ("left", "right"):
        storage.write("", name)
    storage.endWriteStruct()
    for i, name in enumerate(("left", "right")):
        storage.startWriteStruct(name, cv2.FileNode_MAP)
        rvec = cv2.Rodrigues(np.asarray(rig.R[i]))[0]
        for key, value in (("camera_matrix", np.asarray(rig.K[i])), ("R", rvec),
                           ("T", np.asarray(rig.t[i])[:, None]),
                           ("distortion_coefficients", np.asarray(rig.dist[i])[None])):  # fmt: skip
            storage.write(key, value)
        storage.endWriteStruct()
    storage.release()
    assert "   - left" in path.read_text()
    back, names = mc.io.load_opencv(path)
    assert names == ["left", "right"]
    world = np.asarray(mc.targets.box_corner().points)
    for i in range(2):
        rvec = cv2.Rodrigues(np.asarray(rig.R[i]))[0]
        theirs = cv2.projectPoints(world, rvec, np.asarray(rig.t[i]), np.asarray(rig.K[i]),
                                   np.asarray(rig.dist[i]))[0][:, 0]  # fmt: skip
        np.testing.assert_allclose(np.asarray(back[i].project(world)), theirs, atol=1e-9)
    # the intrinsics alone, as OpenCV's calibration samples save them: "lacks R, T" (an
    # OpenCV user's trial); now K and the distortion as written, the pose unknown (NaN)
    alone = tmp_path / "intrinsics.yml"
    storage = cv2.FileStorage(str(alone), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.asarray(rig.K[0]))
    storage.write("distortion_coefficients", np.asarray(rig.dist[0])[None])
    storage.release()
    camera, _ = mc.io.load_opencv(alone)
    np.testing.assert_array_equal(np.asarray(camera.K), np.asarray(rig.K[0]))
    np.testing.assert_array_equal(np.asarray(camera.dist), np.asarray(rig.dist[0]))
    assert np.isnan(np.asarray(camera.R)).all() and np.isnan(np.asarray(camera.t)).all()
    # four coefficients and no distortion_model: a pinhole's k1 k2 p1 p2 or a cv2.fisheye's?
    # Read as the pinhole's, as before, and said (a fisheye's read so projects wide angles wrong)
    four = tmp_path / "four.yml"
    storage = cv2.FileStorage(str(four), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.asarray(rig.K[0]))
    storage.write("distortion_coefficients", np.asarray(rig.dist[0])[None, :4])
    storage.release()
    with pytest.warns(UserWarning, match="no distortion_model: read as a pinhole's k1 k2 p1 p2"):
        camera, _ = mc.io.load_opencv(four)
    assert camera.lens == "pinhole"
    np.testing.assert_array_equal(np.asarray(camera.dist)[:4], np.asarray(rig.dist[0])[:4])
    storage = cv2.FileStorage(str(alone), cv2.FILE_STORAGE_APPEND)
    storage.write("R", np.eye(3))  # (a pose without its T is still refused)
    storage.release()
    with pytest.raises(ValueError, match="camera 'camera' lacks T"):
        mc.io.load_opencv(alone)
    for kind in ("xml", "json"):
        other = tmp_path / f"cv.{kind}"
        storage = cv2.FileStorage(str(other), cv2.FILE_STORAGE_WRITE)
        storage.write("camera_matrix", np.eye(3))
        storage.release()
        with pytest.raises(ValueError, match=f"a FileStorage {kind.upper()} file"):
            mc.io.load_opencv(other)
    skewed = eqx.tree_at(lambda c: c.skew, rig, rig.skew + 1.5)
    with pytest.raises(ValueError, match="OpenCV's pinhole model has no skew"):
        mc.io.save_opencv(tmp_path / "s.yml", skewed)
    with pytest.raises(ValueError, match="may not be named 'cameras'"):
        mc.io.save_opencv(tmp_path / "n.yml", rig, names=["cameras", "b"])
    assert not (tmp_path / "s.yml").exists() and not (tmp_path / "n.yml").exists()
    one = mc.io.save_opencv(tmp_path / "one.yml", rig[0], names=["left"])  # (its name was lost)
    assert mc.io.load_opencv(one)[1] == ["left"]


def test_colmap_export_round_trips_and_refuses_skew(tmp_path):
    rig = mc.synthetic.random_rig(jax.random.key(13), 3).cameras
    rig = mc.Camera.from_matrices(
        rig.K, rig.R, rig.t, np.array([[-0.2, 0.1, 1e-3, 2e-3, 0.0]] * 2 + [[0.1, 0, 0, 0, 0.05]])
    )
    folder = mc.io.save_colmap(tmp_path / "sparse", rig, (1000, 1100), names=["a.png", "b.png",
                                                                              "c.png"])  # fmt: skip
    lines = (folder / "cameras.txt").read_text().splitlines()
    assert lines[2].split()[1] == "OPENCV" and lines[4].split()[1] == "FULL_OPENCV"
    # COLMAP's pixel origin is the corner of the first pixel: cx = u0 + 0.5.
    assert float(lines[2].split()[6]) == float(rig.u0[0]) + 0.5
    back, names = mc.io.load_colmap(folder)
    assert names == ["a.png", "b.png", "c.png"]
    for field in ("alpha_u", "alpha_v", "u0", "v0", "dist", "t"):
        np.testing.assert_allclose(
            getattr(back, field), getattr(rig, field), rtol=1e-15, atol=1e-12
        )
    np.testing.assert_allclose(back.R, rig.R, atol=1e-15)  # through a quaternion
    skewed = eqx.tree_at(lambda c: c.skew, rig, rig.skew + 0.5)
    with pytest.raises(ValueError, match="skew"):
        mc.io.save_colmap(tmp_path / "x", skewed, (1000, 1100))


def test_a_truncated_tiff_is_refused_without_a_readers_noise(tmp_path, caplog):
    """tifffile logged "<tifffile.TiffPages @...> invalid offset to first page" to stderr
    before the error (a photographer's trial): the error says it alone."""
    import io

    import tifffile

    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.zeros((64, 64), np.uint8))
    path = tmp_path / "cut.tif"
    path.write_bytes(buffer.getvalue()[:200])  # (its tags point past the end)
    with pytest.raises(ValueError, match="cut.tif: cannot be read as an image"):
        mc.read_image(path)
    assert not [r for r in caplog.records if r.name.startswith("tifffile")]
