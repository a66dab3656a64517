"""`mvcalib calibrate-rig`: a rig from a target moved in front of it, through the command line
(in-process, through `cli.main`): a synthetic rig, caliscope's real recording
(../shared/data/SOURCE.md, section 6), the flags reaching `calibrate_rig`, and one-line
failures."""

import dataclasses
import functools
import json
import re

import imageio.v3 as iio
import jax
import numpy as np
import pytest
from conftest import data_dir

import mvcalib as mc
import mvcalib._rig  # noqa: F401  (mc._rig, loaded on first use otherwise)
from mvcalib import cli

NAMES = ["cam a", "cam b", "cam c", "cam d"]


@pytest.fixture
def cache_off(monkeypatch):
    monkeypatch.setenv("MVCALIB_COMPILATION_CACHE", "0")  # leave this process's JAX alone


def _observations(n_frames):
    rig = mc.synthetic.board_rig(jax.random.key(0), 4, n_frames, noise=0.3)
    mask = np.asarray(rig.mask)
    pixels = np.where(mask[..., None], np.asarray(rig.pixels), np.nan)
    C, F, N = mask.shape
    target = np.asarray(rig.target)
    return rig, mc.io.Observations(target, pixels, mask, NAMES, np.arange(F), np.arange(N))


def _main(*args) -> int:
    try:
        return cli.main([str(a) for a in args])
    except SystemExit as exit:  # argparse's errors
        return exit.code


# ---------------------------------------------------------------------------- synthetic rig
def test_synthetic_rig_is_calibrated_saved_and_drawn(tmp_path, capsys, cache_off, monkeypatch):
    rig, observations = _observations(40)
    path = mc.io.save_observations(tmp_path / "obs.csv", observations)
    out, figure = tmp_path / "rig.json", tmp_path / "rig.png"
    drawn = []  # the figure's image borders: the photos' size given
    report_figure = mc.plot.report_figure
    monkeypatch.setattr(
        mc.plot, "report_figure", lambda *a, **k: drawn.append(k) or report_figure(*a, **k)
    )
    size = ("--image-size", 1280, 800)
    assert _main("calibrate-rig", path, "--out", out, "--plot", figure, *size) == 0
    assert [list(k["image_size"]) for k in drawn] == [[1280, 800]]
    stdout, stderr = capsys.readouterr()
    assert f"read 4 cameras, 40 frames, 108 target points, {observations.mask.sum()} " in stderr
    assert "calibrate_rig: RMS" in stderr  # the library's stage timings, as progress
    assert "4 of 4 cameras calibrated; 4 cameras written to" in stdout
    assert "rig of 4 cameras, 40 frames" in stdout and "cameras: 0 = cam a, 1 = cam b" in stdout
    # the estimated intrinsics with their standard errors, none of them loose here
    assert re.search(r"^cam a\s+[\d.]+ ± [\d.]+\s+[\d.]+ ± [\d.]+\s+[\d.]+ ± [\d.]+", stdout, re.M)
    assert "determines the intrinsics of" not in stdout

    cameras, names = mc.io.load_json(out)
    assert names == NAMES and cameras.batch_shape == (4,)
    document = json.loads(out.read_text())
    assert [c["status"] for c in document["cameras"]] == [0, 0, 0, 0]
    meta = document["meta"]
    assert meta["reference"] == 0 and meta["fix"] == [] and meta["n_skipped"] == 0
    assert 0.3 < meta["rms_observed"] < 0.5 and meta["converged"]  # 0.3 px noise in x and y
    printed = re.search(r"all cameras: (\d+) observations, RMS ([\d.]+) px", stdout)
    assert int(printed.group(1)) == observations.mask.sum()
    assert abs(float(printed.group(2)) - meta["rms_observed"]) < 1e-4
    # camera 0's frame is the world's: the other centres where the truth puts them there
    truth = np.asarray(rig.cameras[0].to_camera(rig.cameras.center))
    error = np.linalg.norm(np.asarray(cameras.center) - truth, axis=-1)
    std = np.linalg.norm(meta["position_std"], axis=-1)
    assert std[0] == 0 and np.all(error[1:] < 4 * std[1:]) and error.max() < 0.02  # metres
    np.testing.assert_allclose(cameras.alpha_u, rig.cameras.alpha_u, rtol=0.01)
    # each centre, its distance from the first camera (a stereo baseline) and rotation from it
    baseline = np.linalg.norm(np.asarray(cameras.center[1] - cameras.center[0]))
    row = re.search(r"^cam b\s+[-\d., e]+?\s{2,}([\d.]+)\s+([\d.]+)°", stdout, re.M)
    assert "from cam a" in stdout and abs(float(row.group(1)) - baseline) < 1e-4 * baseline

    picture = iio.imread(figure)
    assert picture.shape[1] > 1000 and picture[..., :3].std() > 10  # something drawn
    assert f"figure written to {figure}" in stdout


def test_opencv_yaml_and_the_world_on_the_board_of_a_frame_id(tmp_path, capsys, cache_off):
    """`--out rig.yml` writes OpenCV's YAML (it wrote JSON under that name), and
    `--reference target --origin-frame ID` puts the world on the board of the frame with that id
    in the file (ids 100 on here, not indices): the cameras where the truth puts them in that
    board's frame, as `calibrate_rig(..., origin_frame=index)` does."""
    rig, observations = _observations(40)
    observations = dataclasses.replace(observations, frames=observations.frames + 100)
    path = mc.io.save_observations(tmp_path / "obs.csv", observations)
    f = int(np.argmax(observations.mask.any(-1).sum(0) == 2))  # a frame two cameras saw
    out = tmp_path / "rig.yml"
    args = ["--reference", "target", "--origin-frame", 100 + f, "--quiet"]
    assert _main("calibrate-rig", path, "--out", out, *args) == 0
    stdout = capsys.readouterr().out
    assert f"(frame {f} counts the frames from 0; its id in {path} is {100 + f})" in stdout
    assert "(opencv)" in stdout
    assert out.read_text().startswith("%YAML:1.0")
    cameras, names = mc.io.load_opencv(out)
    assert names == [n.replace(" ", "_") for n in NAMES]
    truth = np.asarray(rig.poses[f].inverse().apply(rig.cameras.center))  # in that board's
    assert np.abs(np.asarray(cameras.center) - truth).max() < 0.02  # metres
    python = mc.calibrate_rig(observations.target, observations.pixels, observations.mask,
                              reference="target", origin_frame=f)  # fmt: skip
    assert python.origin_frame == f and f"world frame: the target in frame {f}" in str(python)
    np.testing.assert_allclose(cameras.center, python.cameras.center, rtol=1e-6, atol=1e-9)


def test_origin_frame_is_an_index_of_a_frame_and_needs_the_target_as_reference():
    """A frame id from the file was clamped by JAX's indexing to the last frame: the world on
    another board pose, without a word; the argument without `reference="target"` was ignored."""
    rig, observations = _observations(3)
    call = functools.partial(mc.calibrate_rig, rig.target, rig.pixels, rig.mask)
    with pytest.raises(ValueError, match=r"frame axis of `pixels`, 0 to 2; got 3\."):
        call(reference="target", origin_frame=3)
    with pytest.raises(ValueError, match="0 to 2; got -1"):
        call(reference="target", origin_frame=-1)
    with pytest.raises(TypeError, match="a frame's index, an int; got 1.0"):
        call(reference="target", origin_frame=1.0)
    with pytest.raises(ValueError, match="with `reference='target'`; got reference=0"):
        call(origin_frame=1)


# ---------------------------------------------------------------------------- caliscope
def test_caliscope_recording_with_its_intrinsics_held_beats_its_own_error(
    tmp_path, capsys, cache_off
):
    root = data_dir("caliscope_4cam")
    out = tmp_path / "rig.json"
    toml = root / "camera_array.toml"
    args = ["--intrinsics", toml, "--fix", "intrinsics,distortion", "--reference", "1"]
    assert _main("calibrate-rig", root / "xy.csv", "--out", out, *args, "--quiet") == 0
    stdout, stderr = capsys.readouterr()
    assert stderr == ""  # --quiet: no progress, nor the library's stage timings
    printed = re.search(r"all cameras: 1725 observations, RMS ([\d.]+) px", stdout)
    assert float(printed.group(1)) < 0.94  # caliscope's own rig: 0.94 px (SOURCE.md)
    meta = json.loads(out.read_text())["meta"]
    assert meta["rms_observed"] < 0.94 and meta["fix"] == ["intrinsics", "distortion"]
    cameras, names = mc.io.load_json(out)
    theirs, their_names = mc.io.load_caliscope_cameras(toml)
    assert names == their_names == ["cam_0", "cam_1", "cam_2", "cam_3"]
    np.testing.assert_array_equal(cameras.K, theirs.K)  # held
    np.testing.assert_array_equal(cameras.dist, theirs.dist)
    np.testing.assert_allclose(cameras.R[1], np.eye(3), atol=1e-12)  # camera 1 is the world
    np.testing.assert_allclose(cameras.t[1], 0, atol=1e-12)


def test_caliscope_with_its_intrinsics_free_says_they_are_loose(tmp_path, capsys, cache_off):
    """Intrinsics estimated from caliscope's 48 frames (SOURCE.md: weakly determined): the board
    trial found cam_1's u0 101 px from caliscope's at RMS 0.88 px, every camera OK, and the
    command printed no intrinsics. It prints them with their standard errors, and a note."""
    root = data_dir("caliscope_4cam")
    assert _main("calibrate-rig", root / "xy.csv", "--out", tmp_path / "r.json", "--quiet") == 0
    out = capsys.readouterr().out
    assert re.search(r"^cam_1\s+[\d.]+ ± [\d.]+", out, re.M)
    assert "note: the recording determines the intrinsics of cam_0, cam_1" in out
    assert "--fix intrinsics" in out


# ---------------------------------------------------------------------------- flags
class _Spied(ValueError):
    pass


def test_flags_reach_calibrate_rig(tmp_path, capsys, cache_off, monkeypatch):
    seen = []

    def spy(target, pixels, mask, **kwargs):  # records the request, stops before any work
        seen.append((pixels.shape, kwargs))
        raise _Spied("spied")

    monkeypatch.setattr("mvcalib._rig.calibrate_rig", spy)
    rig, observations = _observations(3)
    path = mc.io.save_observations(tmp_path / "obs.csv", observations)
    reversed_ = [3, 2, 1, 0]  # a starting rig with the cameras in another order: by name
    start = jax.tree_util.tree_map(lambda a: a[np.array(reversed_)], rig.cameras)
    mc.io.save_json(tmp_path / "start.json", start, names=[NAMES[i] for i in reversed_])
    base = ["calibrate-rig", path, "--out", tmp_path / "r.json", "--quiet"]
    assert _main(*base) == 2
    assert _main(*base, "--huber", "2", "--reference", "target", "--distortion", "k1,k2") == 2
    assert _main(*base, "--reference", "cam c", "--intrinsics", tmp_path / "start.json",
                 "--fix", "intrinsics, k3") == 2  # fmt: skip
    assert _main(*base, "--cauchy", "1.5") == 2
    assert capsys.readouterr().err.count("mvcalib: error: spied") == 4
    assert _main(*base, "--cauchy", "1.5", "--huber", "2") == 2  # one loss
    assert "not allowed with argument" in capsys.readouterr().err
    (shape, plain), (_, robust), (_, started), (_, cauchy) = seen
    assert cauchy["loss"] == mc.Cauchy(1.5)
    assert shape == (4, 3, 108, 2)
    # (distortion None: the lens's default, k1 k2 p1 p2 of a pinhole, k1..k4 of a fisheye)
    assert plain == dict(cameras=None, fix=(), distortion=None, reference=0,
                         origin_frame=None, loss=None, verbose=False)  # fmt: skip
    assert robust["loss"] == mc.Huber(2.0) and robust["reference"] == "target"
    assert robust["distortion"] == ("k1", "k2")
    assert started["reference"] == 2 and started["fix"] == ("intrinsics", "k3")
    np.testing.assert_array_equal(started["cameras"].K, rig.cameras.K)  # back in file order


def test_intrinsics_are_matched_by_name_or_in_an_announced_order(tmp_path, capsys, cache_off):
    """A lab's intrinsics file holding more cameras is matched by name; one whose names are all
    different is taken in order, and says so (names half right were taken in order silently:
    the trial's focal lengths 20 % off at RMS 6 px, every camera OK)."""
    rig, observations = _observations(10)
    path = mc.io.save_observations(tmp_path / "obs.csv", observations)
    extra = mc.synthetic.board_rig(jax.random.key(9), 2, 1).cameras
    lab = jax.tree_util.tree_map(lambda *a: np.concatenate(a), extra[:1], rig.cameras[::-1])
    lab_names = ["spare", *NAMES[::-1]]
    mc.io.save_json(tmp_path / "lab.json", lab, names=lab_names)
    mc.io.save_json(tmp_path / "other.json", rig.cameras, names=["a", "b", "c", "d"])
    # (a user's trial: cam0.. against cam_0.., in another order, were taken in order)
    spelled = ["CAM-D", "cam_c", "Cam B", "cama"]
    mc.io.save_json(tmp_path / "spelled.json", rig.cameras[::-1], names=spelled)
    fixed = ["--fix", "intrinsics,distortion", "--quiet"]
    for name, note, theirs in (
        ("lab.json", None, NAMES),
        ("other.json", "cam a = a, cam b = b, cam c = c, cam d = d", ["a", "b", "c", "d"]),
        ("spelled.json", "aside: cam a = cama, cam b = Cam B, cam c = cam_c", spelled[::-1]),
    ):
        out = tmp_path / f"from_{name}"
        assert _main("calibrate-rig", path, "--intrinsics", tmp_path / name, "--out", out,
                     *fixed) == 0  # fmt: skip
        stdout = capsys.readouterr().out
        assert ("note: the cameras of --intrinsics" in stdout) == (note is not None)
        assert note is None or note in stdout, stdout
        cameras, _ = mc.io.load_json(out)
        np.testing.assert_array_equal(cameras.K, rig.cameras.K)  # each camera its own
        meta = json.loads(out.read_text())["meta"]
        assert meta["intrinsics_cameras"] == theirs


def test_a_failed_joint_solve_says_what_to_try_in_the_command_line(tmp_path, capsys, cache_off):
    """1 % of the corners wild without a robust loss: every camera POOR_FIT. The library's
    words (`max_relative_rms`, `cameras=`) are Python's; the command line names its own flags,
    and exits 1 (the work failed) rather than 2 (bad usage)."""
    rig, observations = _observations(40)
    pixels, mask = observations.pixels.copy(), observations.mask
    where = np.argwhere(mask)
    wild = where[np.random.default_rng(0).choice(len(where), len(where) // 100, replace=False)]
    pixels[tuple(wild.T)] += 300.0
    wild_obs = dataclasses.replace(observations, pixels=pixels)
    path = mc.io.save_observations(tmp_path / "wild.csv", wild_obs)
    with pytest.raises(mc._rig.SolveFailed, match=r"loss=mc.Huber\(2.0\).*lens='fisheye'"):
        mc.calibrate_rig(wild_obs.target, np.nan_to_num(pixels), mask)
    assert _main("calibrate-rig", path, "--out", tmp_path / "r.json", "--quiet") == 1
    err = capsys.readouterr().err
    assert "for wrong detections, --huber 2 (or --cauchy 2 for many)" in err
    # (fisheye data fitted as pinholes fails so too, and said nothing of the lens)
    assert "for wide-angle lenses, --fisheye --image-size W H." in err
    assert "max_relative_rms" not in err and len(err.strip().splitlines()) == 1
    assert _main("calibrate-rig", path, "--out", tmp_path / "r.json", "--huber", "2",
                 "--quiet") == 0  # fmt: skip
    assert "inliers of the Huber loss (within 6 px)" in capsys.readouterr().out


def test_a_reference_camera_on_its_own_is_named_with_the_way_out(tmp_path, capsys, cache_off):
    """Camera 0 (the default reference) shares no frame with the others: they were all
    NOT_CONNECTED with no hint that another reference calibrates them. The table names the
    cameras (it numbered them)."""
    rig, observations = _observations(40)
    mask = observations.mask.copy()
    mine = np.flatnonzero(mask[0].any(-1))[:10]
    mask[0] = False
    mask[0, mine] = observations.mask[0, mine]
    mask[1:, mine] = False
    path = mc.io.save_observations(
        tmp_path / "obs.csv", dataclasses.replace(observations, mask=mask)
    )
    assert _main("calibrate-rig", path, "--out", tmp_path / "r.json", "--quiet") == 1
    out = capsys.readouterr().out
    assert "note: 3 cameras share no frames with the reference camera cam a: --reference" in out
    # (its row counts the frames it posed alone, and no points)
    frames = int((mask[1].sum(-1) >= 4).sum())
    assert re.search(rf"^cam b\s+{frames}\s+-\s+nan\s+nan\s+NOT_CONNECTED$", out, re.M), out
    best = re.search(r"--reference (cam \w) \(or", out).group(1)
    assert (
        _main("calibrate-rig", path, "--out", tmp_path / "r.json", "--reference", best, "--quiet")
        == 1
    )  # (camera 0 on its own now)
    assert "3 of 4 cameras calibrated" in capsys.readouterr().out


def test_a_rig_is_checked_against_another_recording(tmp_path, capsys, cache_off):
    """Calibrated from the first 40 frames, held whole (`--fix intrinsics,distortion,pose`) on
    the last 40: only the board's poses are fitted, the cameras come back as given, and their
    RMS is the noise's (0.3 px in x and y)."""
    rig, observations = _observations(80)
    half = lambda x: dataclasses.replace(  # noqa: E731
        observations, pixels=observations.pixels[:, x], mask=observations.mask[:, x],
        frames=observations.frames[x],
    )  # fmt: skip
    first = mc.io.save_observations(tmp_path / "first.csv", half(slice(0, 40)))
    second = mc.io.save_observations(tmp_path / "second.csv", half(slice(40, 80)))
    assert _main("calibrate-rig", first, "--out", tmp_path / "rig.json", "--quiet") == 0
    held = ["--intrinsics", tmp_path / "rig.json", "--fix", "intrinsics,distortion,pose"]
    assert _main("calibrate-rig", second, *held, "--out", tmp_path / "check.json", "--quiet") == 0
    out = capsys.readouterr().out
    rms = float(re.search(r"all cameras: \d+ observations, RMS ([\d.]+) px", out.split("\n\n")[-1]
                          .replace("\n", " ")).group(1))  # fmt: skip
    assert 0.35 < rms < 0.5
    given, _ = mc.io.load_json(tmp_path / "rig.json")
    checked, _ = mc.io.load_json(tmp_path / "check.json")
    jax.tree_util.tree_map(np.testing.assert_array_equal, checked, given)


# ---------------------------------------------------------------------------- failures
@pytest.fixture
def files(tmp_path, monkeypatch, cache_off):
    """A small observations file of 4 cameras, rigs of 4 and of 2 cameras, a caliscope-style
    camera_array.toml of 2 cameras, and a correspondences file (not observations)."""
    monkeypatch.chdir(tmp_path)
    rig, observations = _observations(3)
    mc.io.save_observations("obs.csv", observations)
    mc.io.save_json("four.json", rig.cameras, names=NAMES)
    mc.io.save_json("two.json", rig.cameras[:2], names=NAMES[:2])
    mc.io.save_json("typo.json", rig.cameras, names=[*NAMES[:3], "Cam d"])
    toml = "".join(
        f"[cameras.{c}]\nmatrix = [[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]]\n"
        "rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\n"
        "translation = [0.0, 0.0, 1.5]\n"
        for c in range(2)
    )
    (tmp_path / "two.toml").write_text(toml)
    world = mc.targets.box_corner().points
    mc.io.save_correspondences("corr.csv", world, np.zeros((1, len(world), 2)))
    return tmp_path


RIG = ["calibrate-rig", "obs.csv", "--out", "r.json"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["calibrate-rig", "nowhere.csv", "--out", "r.json"], "no such file: nowhere.csv"),
        ([*RIG, "--intrinsics", "none.toml"], "no such file: none.toml"),
        (["calibrate-rig", "obs.csv", "--out", "no/r.json"], "the folder of --out does not"),
        ([*RIG, "--plot", "no/f.png"], "the folder of --plot does not"),
        ([*RIG, "--fix", "intrinsics"], "--fix intrinsics needs --intrinsics"),
        ([*RIG, "--fix", "pose"], "--fix pose needs --intrinsics"),
        ([*RIG, "--intrinsics", "two.json"],
         "two.json has no camera named 'cam c', 'cam d' (it has 'cam a', 'cam b'): name every"),
        ([*RIG, "--intrinsics", "two.toml", "--fix", "intrinsics"],
         "two.toml: 2 cameras; the observations have 4, and no name in common"),
        ([*RIG, "--intrinsics", "typo.json"], "typo.json has no camera named 'cam d'"),
        ([*RIG, "--intrinsics", "obs.csv"], "obs.csv: a CSV file is not a rig; a rig is"),
        ([*RIG, "--intrinsics", "four.json", "--fix", "focus"], "unknown parameter 'focus'"),
        ([*RIG, "--reference", "7"], "`reference` 7 is not a camera of the 4"),
        ([*RIG, "--reference", "left"], "--reference 'left' is neither a camera index"),
        ([*RIG, "--huber", "0"], "--huber must be positive"),
        ([*RIG, "--distortion", "k9"], "'k9' is not one of"),
        (["calibrate-rig", "corr.csv", "--out", "r.json"], "corr.csv:1: "),
        (["calibrate-rig", "four.json", "--out", "r.json"], "four.json:1: "),
        (["calibrate-rig", "obs.csv", "--out", "r.txt"], "--out r.txt: a .json, .yml/.yaml or"),
        ([*RIG, "--format", "colmap"], "--format colmap needs --image-size"),
        ([*RIG, "--format", "opencv"], "--format opencv writes a .yml or .yaml file"),
        ([*RIG, "--origin-frame", "2"], "--origin-frame chooses the world frame with --reference"),
        ([*RIG, "--reference", "target", "--origin-frame", "9"],
         "--origin-frame 9: no frame of that id in obs.csv (its frames are 0 to 2)"),
    ],
)  # fmt: skip
def test_failures_are_one_line_and_exit_code_2(files, capsys, args, message):
    returned = _main(*args, "--quiet")
    err = capsys.readouterr().err
    assert returned == 2, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and not (files / "r.json").exists()
    assert not list(files.glob(".*.tmp"))
