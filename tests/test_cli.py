"""The command line, run as users run it: `python -m mvcalib ...` in a subprocess, on real files
(the Oxford house corners, rendered photographs). Failure paths that stop before any JAX work
are also run in-process through `cli.main`, which is faster and the same code."""

import csv
import json
import os
import pathlib
import re
import subprocess
import sys

import imageio.v3 as iio
import jax
import numpy as np
import pytest
from conftest import data_dir
from test_real_data import load_oxford_house

import mvcalib as mc
from mvcalib import cli


def run(*args, timeout=600, env=None):
    return subprocess.run(
        [sys.executable, "-m", "mvcalib", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


# ---------------------------------------------------------------------------- demo
@pytest.fixture(scope="module")
def noise_free():
    return run("demo", "--noise-free")


def test_demo_prints_table_one_and_one_pixel_from_four_snapshots(noise_free):
    out = noise_free.stdout
    assert noise_free.returncode == 0, noise_free.stderr
    assert "Table I" in out and "mean err x" in out
    pixels = re.findall(
        r"snapshot \d: pixel \(\s*([\d.]+),\s*([\d.]+)\) -> rounded \((\d+), (\d+)\)", out
    )
    assert len(pixels) == 4
    assert len({p[2:] for p in pixels}) == 1  # the same rounded pixel
    xy = [(float(a), float(b)) for a, b, *_ in pixels]
    assert max(abs(a[0] - xy[0][0]) + abs(a[1] - xy[0][1]) for a in xy) < 1e-6 + 1e-4
    spread = float(re.search(r"spread ([\d.e+-]+) px", out).group(1))
    assert spread < 1e-6
    assert "the same rounded pixel" in out


def test_demo_with_noise_reports_expected_scatter():
    result = run("demo")
    assert result.returncode == 0, result.stderr
    assert "expected scatter from 0.3 px" in result.stdout
    rows = re.findall(
        r"^\s*(\d)\s+(-?[\d.]+)\s+(-?[\d.]+)\s+([\d.]+)\s+([\d.]+)\s+8$", result.stdout, re.M
    )
    assert len(rows) == 4  # Table I: four cameras, 8 calibration points each
    assert all(0.05 < float(r[3]) < 0.6 for r in rows)  # RMS near the 0.3 px noise


def test_demo_saves_its_files_and_uses_the_compilation_cache_where_asked(tmp_path, monkeypatch):
    monkeypatch.setenv("MVCALIB_COMPILATION_CACHE", str(tmp_path / "cache"))
    result = run("demo", "--noise-free", "--save", tmp_path / "demo")
    assert result.returncode == 0, result.stderr
    assert any((tmp_path / "cache").iterdir())
    # The saved rig reprojects the saved dots exactly (noise-free), computed here with NumPy.
    rig = json.loads((tmp_path / "demo" / "rig.json").read_text())["cameras"]
    data = mc.io.load_correspondences(tmp_path / "demo" / "correspondences.csv")
    assert [c["name"] for c in rig] == data.cameras == [f"snapshot_{i}" for i in range(1, 5)]
    np.testing.assert_array_equal(data.world, mc.targets.box_corner().points)
    for camera, pixels, mask in zip(rig, data.pixels, data.mask):
        x = data.world @ np.array(camera["R"]).T + camera["t"]
        u = camera["alpha_u"] * x[:, 0] / x[:, 2] + camera["skew"] * x[:, 1] / x[:, 2]
        v = camera["alpha_v"] * x[:, 1] / x[:, 2]
        error = np.c_[u + camera["u0"], v + camera["v0"]][mask] - pixels[mask]
        assert mask.sum() >= 15 and np.abs(error).max() < 1e-6


def test_measured_global_coordinates_show_the_papers_r_is_not_a_rotation():
    result = run("demo", "--global-noise", "0.5")
    assert result.returncode == 0, result.stderr
    paper = re.search(r"paper eqs\. 25-28 .* max \|R\^T R - I\| = ([\d.e+-]+)", result.stdout)
    ours = re.search(r"Procrustes \(default\) .* max \|R\^T R - I\| = ([\d.e+-]+)", result.stdout)
    assert float(paper.group(1)) > 1e-3 and float(ours.group(1)) < 1e-12


# ---------------------------------------------------------------------------- Oxford house
@pytest.fixture(scope="module")
def house(tmp_path_factory):
    """The Oxford house corners as a correspondences file and as a 2-D tracks file, and the
    rig `mvcalib calibrate` makes from them, as JSON (OpenCV's YAML cannot hold the DLT's
    skew)."""
    folder = tmp_path_factory.mktemp("house")
    world, pixels, P = load_oxford_house()
    mask = np.all(np.isfinite(pixels), -1)
    names = [f"house.{v:03d}" for v in range(10)]
    corr = mc.io.save_correspondences(folder / "house.csv", world, pixels, mask, cameras=names)
    tracks = mc.io.save_correspondences(folder / "tracks.csv", None, pixels, mask, cameras=names)
    rig = folder / "rig.json"
    result = run("calibrate", corr, "--image-size", 768, 576, "--out", rig)
    return dict(world=world, pixels=pixels, mask=mask, P=P, names=names, csv=corr,
                tracks=tracks, rig=rig, result=result)  # fmt: skip


def _table(stdout: str) -> dict:
    """Table I rows of the CLI: name -> (mean x, mean y, RMS, max, points)."""
    number = r"\s+(-?[\d.]+)"
    rows = re.findall(rf"^(\S+){number * 4}\s+(\d+)", stdout, re.M)
    return {r[0]: tuple(map(float, r[1:])) for r in rows}


def _rig_matrices(path) -> list:
    """(name, K, R, T (3, 1), dist) per camera of a JSON rig, as plain arrays."""
    cameras, names = mc.io.load_json(path)
    fields = (np.asarray(cameras.K), np.asarray(cameras.R), np.asarray(cameras.t)[..., None],
              np.asarray(cameras.dist))  # fmt: skip
    return list(zip(names, *fields))


def _residuals(K, R, T, dist, world, pixels):
    """Reprojected - observed, by NumPy (the DLT's cameras have skew: up to 26 px here)."""
    assert not np.any(dist)
    x = (world @ R.T + T[:, 0]) @ K.T
    return x[:, :2] / x[:, 2:] - pixels


def test_calibrate_fits_each_view_as_well_as_the_published_cameras(house):
    result = house["result"]
    assert result.returncode == 0, result.stderr
    assert "10 of 10 cameras calibrated; 10 cameras written" in result.stdout
    assert "read 10 cameras, 672 points, 2846 observations" in result.stderr  # progress
    # VGG's world frame is left-handed: every camera is named as seeing it mirrored
    assert f"mirrored: cameras {', '.join(house['names'])} see a mirror image" in result.stdout
    table = _table(result.stdout)
    assert list(table) == house["names"]
    world, pixels, mask = house["world"], house["pixels"], house["mask"]
    for i, (name, K, R, T, dist) in enumerate(_rig_matrices(house["rig"])):
        assert name == house["names"][i]
        r = _residuals(K, R, T, dist, world, pixels[i])[mask[i]]
        ours = np.sqrt(np.mean(np.sum(r**2, -1)))
        x = np.c_[world, np.ones(len(world))] @ house["P"][i].T
        published = np.sqrt(np.mean(np.sum((x[:, :2] / x[:, 2:] - pixels[i])[mask[i]] ** 2, -1)))
        assert ours <= 1.005 * published  # as the library's own Oxford test
        row = table[house["names"][i]]
        assert abs(row[2] - ours) < 1e-4 and row[4] == mask[i].sum()  # the printed RMS
        # the same camera: its centre (the null vector of P) within 2 % of the scene distance
        centre = np.linalg.svd(house["P"][i])[2][-1]
        centre = centre[:3] / centre[3]
        ours_centre = -R.T @ T[:, 0]
        assert np.linalg.norm(ours_centre - centre) < 0.02 * np.linalg.norm(centre - world.mean(0))


def test_report_prints_table_one_and_draws_the_figure(house, tmp_path):
    figure = tmp_path / "report.png"
    result = run("report", house["rig"], house["csv"], "--plot", figure)
    assert result.returncode == 0, result.stderr
    table = _table(result.stdout)
    world, pixels, mask = house["world"], house["pixels"], house["mask"]
    lengths = []
    for i, (name, K, R, T, dist) in enumerate(_rig_matrices(house["rig"])):
        r = _residuals(K, R, T, dist, world, pixels[i])[mask[i]]
        expected = (*r.mean(0), np.sqrt(np.mean(np.sum(r**2, -1))))
        np.testing.assert_allclose(table[name][:3], expected, atol=1e-4)  # the rig's names
        lengths.append(np.linalg.norm(r, axis=-1))
    lengths = np.concatenate(lengths)
    summary = re.search(r"all cameras: (\d+) observations, RMS ([\d.]+) px, median ([\d.]+)",
                        result.stdout)  # fmt: skip
    assert int(summary.group(1)) == mask.sum()
    assert abs(float(summary.group(2)) - np.sqrt(np.mean(lengths**2))) < 1e-4
    assert abs(float(summary.group(3)) - np.median(lengths)) < 1e-4
    picture = iio.imread(figure)
    assert picture.shape[0] > 500 and picture.shape[1] > 1000
    assert picture[..., :3].std() > 10  # something drawn
    assert "drawing the figure" in result.stderr and f"figure written to {figure}" in result.stdout


def test_triangulate_recovers_the_published_points(house, tmp_path):
    out = tmp_path / "points.csv"
    result = run("triangulate", house["rig"], house["tracks"], "--out", out)
    assert result.returncode == 0, result.stderr
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert [r["point"] for r in rows] == [str(i) for i in range(672)]
    points = np.array([[float(r[k]) for k in ("world_x", "world_y", "world_z")] for r in rows])
    np.testing.assert_array_equal([int(r["views"]) for r in rows], house["mask"].sum(0))
    # Measured: median 4.3e-4 from the published points, in a scene 6.2 units wide whose
    # first-order triangulation noise is 1.2e-2 (tests/test_real_data.py).
    distance = np.linalg.norm(points - house["world"], axis=-1)
    assert np.median(distance) < 1e-3
    # VGG's world frame is mirrored: the points are right but behind the cameras, so not ok.
    assert all(r["ok"] == "0" for r in rows) and "frame is mirrored" in result.stdout
    assert "triangulating 672 points from 10 cameras" in result.stderr


# ---------------------------------------------------------------------------- photographs
@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """Three rendered photographs of the box corner (and a corrupt one), their cameras, and
    what `mvcalib detect` makes of them."""
    folder = tmp_path_factory.mktemp("photos")
    target = mc.targets.box_corner()
    centre = target.points.mean(0)
    paths, cameras = [], []
    for k, (azimuth, elevation) in enumerate([(45.0, 35.0), (25.0, 30.0), (65.0, 45.0)]):
        a, e = np.radians(azimuth), np.radians(elevation)
        direction = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        R, t = mc.synthetic.look_at(centre + 650.0 * direction, centre, np.array([0.0, 0, 1]))
        camera = mc.Camera(1400.0, 1392.0, 512.0, 541.0, np.asarray(R), np.asarray(t))
        paths.append(folder / f"cam{k}.png")
        iio.imwrite(paths[-1], mc.synthetic.render(camera, target, key=k, clutter=2))
        cameras.append(camera)
    paths.append(folder / "corrupt.png")
    paths[-1].write_bytes(b"GIF89a and then nothing")
    dots = folder / "dots.csv"
    return dict(paths=paths, cameras=cameras, target=target, dots=dots, folder=folder,
                detect=run("detect", *paths, "--out", dots))  # fmt: skip


def test_detect_labels_the_dots_and_names_the_photo_it_cannot_read(photos):
    result = photos["detect"]
    assert result.returncode == 1, result.stderr  # one photo failed, the others are written
    assert "3 of 4 images labelled" in result.stdout and "cannot be read" in result.stdout
    assert "[1/4]" in result.stderr and "[4/4]" in result.stderr
    data = mc.io.load_correspondences(photos["dots"])
    assert data.cameras == [str(p) for p in photos["paths"]]
    np.testing.assert_array_equal(data.world, photos["target"].points)
    assert data.mask[:3].all() and not data.mask[3].any()
    for camera, pixels in zip(photos["cameras"], data.pixels):
        truth = mc.synthetic.ellipse_centres(camera, photos["target"])  # the dots' image centres
        assert np.abs(pixels - truth).max() < 0.1


def test_calibrate_reads_the_detected_dots_and_records_the_failed_photo(photos, capsys, cache_off):
    # In-process (the same `cli.main`; the subprocess runs above cover the real process).
    out = photos["folder"] / "rig.json"
    assert cli.main(["calibrate", str(photos["dots"]), "--out", str(out), "--quiet"]) == 1
    stdout, stderr = capsys.readouterr()
    assert stderr == "" and "corrupt.png: fewer than 6 visible points" in stdout
    assert "3 of 4 cameras calibrated; 4 cameras written" in stdout
    document = json.loads(out.read_text())
    assert document["meta"] == {"correspondences": str(photos["dots"]), "refined": False}
    cameras = document["cameras"]
    assert [c["name"] for c in cameras] == [str(p) for p in photos["paths"]]
    assert [c["status"] for c in cameras] == [0, 0, 0, int(mc.Status.TOO_FEW_POINTS)]
    assert cameras[3]["alpha_u"] is None  # a failed camera is null, never a guess
    # The centroids keep the dots' perspective bias (calibrate-images removes it; calibrate
    # cannot know the dots' size), a few tenths of a percent in focal length.
    for camera, truth in zip(cameras[:3], photos["cameras"]):
        assert abs(camera["alpha_u"] / 1400.0 - 1) < 0.01
        angle = np.arccos((np.trace(np.array(camera["R"]) @ np.asarray(truth.R).T) - 1) / 2)
        assert np.degrees(angle) < 0.5


def test_refinement_flags_reach_calibrate(photos, capsys, cache_off, monkeypatch):
    seen = []
    real = mc._pipeline.calibrate

    def spy(*args, refine=False, **kwargs):  # records the request; calibrates without it
        seen.append(refine)
        return real(*args, **kwargs)

    monkeypatch.setattr(mc._pipeline, "calibrate", spy)
    out = photos["folder"] / "refined.json"
    for flags in (["--refine"], ["--distortion", "k1,k2"], ["--distortion", "none"]):
        cli.main(["calibrate", str(photos["dots"]), "--out", str(out), "--quiet", *flags])
    assert seen == [{}, {"distortion": ("k1", "k2")}, {"distortion": ()}]
    assert json.loads(out.read_text())["meta"]["distortion"] == []
    capsys.readouterr()


# ---------------------------------------------------------------------------- failures
def test_malformed_file_is_one_line_and_exit_code_2_in_a_real_process(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("camera,point,world_x,world_y,world_z,pixel_x,pixel_y\na,1,0,0,0,1,2\nb,1,x\n")
    result = run("calibrate", bad, "--out", tmp_path / "rig.json")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip() == f"mvcalib: error: {bad}:3: 3 fields; the header has 7."
    assert not (tmp_path / "rig.json").exists()


@pytest.fixture
def cache_off(monkeypatch):
    monkeypatch.setenv("MVCALIB_COMPILATION_CACHE", "0")  # leave this process's JAX alone


@pytest.fixture
def files(tmp_path, monkeypatch, cache_off):
    """Small real input files for the in-process failure tests."""
    monkeypatch.chdir(tmp_path)
    world = mc.targets.box_corner().points
    R = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # looking down at the floor
    t = np.array([[-100.0, 100, 800], [-50.0, 100, 900]])
    rig = mc.Camera.from_matrices(np.diag([1000.0, 1000, 1]), R, t)
    x = world @ R.T + t[:, None]
    pixels = 1000.0 * x[..., :2] / x[..., 2:]
    mc.io.save_json("rig.json", rig, names=["a", "b"])
    mc.io.save_correspondences("corr.csv", world, pixels, cameras=["a", "b"])
    mc.io.save_correspondences("other.csv", world, pixels, cameras=["a", "c"])
    mc.io.save_correspondences("tracks.csv", None, pixels, cameras=["a", "b"])
    mc.io.save_correspondences("five.csv", world[:5], pixels[:, :5])
    image = np.full((120, 160), 220, np.uint8)
    rows, cols = np.mgrid[:120, :160]
    for y, x in ((30, 40), (30, 110), (85, 40), (85, 110), (60, 75)):
        image[(rows - y) ** 2 + (cols - x) ** 2 < 36] = 20
    iio.imwrite("dots.png", image)
    iio.imwrite("other.png", image)
    iio.imwrite("blank.png", np.full((64, 64), 128, np.uint8))
    (tmp_path / "folder.csv").mkdir()
    # a board seen by cameras a and b in one frame (calibrate-rig's input)
    board = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    seen = np.ones((2, 1, 4), bool)
    obs = mc.io.Observations(board, np.zeros((2, 1, 4, 2)), seen, ["a", "b"], np.array([0]),
                             np.arange(4))  # fmt: skip
    mc.io.save_observations("obs.csv", obs)
    # a target file (no fiducial dots) and clicks on it, for calibrate-images
    (tmp_path / "target.txt").write_text("1 0 0 0\n2 10 0 0\n3 0 10 0\n4 10 10 5\n5 5 5 5\n")
    (tmp_path / "four.csv").write_text(
        "image,dot_id,pixel_x,pixel_y\n0,1,40,30\n0,2,110,30\n0,3,40,85\n0,4,110,85\n"
    )
    (tmp_path / "badclicks.csv").write_text("img,id,x,y\n0,2,1,1\n")
    (tmp_path / "image1.csv").write_text("image,dot_id,pixel_x,pixel_y\n1,2,1,1\n")
    (tmp_path / "neither.toml").write_text("[camera]\nname = 'a'\n")
    (tmp_path / "rig.txt").write_text("not JSON\n")
    return tmp_path


@pytest.mark.parametrize(
    "args, code, message",
    [
        (["calibrate", "nowhere.csv", "--out", "r.json"], 2, "no such file: nowhere.csv"),
        (["calibrate", "corr.csv", "--out", "no/r.json"], 2, "the folder of --out does not"),
        (["calibrate", "corr.csv", "--out", "r", "--format", "colmap"], 2, "needs --image-size"),
        (["calibrate", "corr.csv", "--out", "r", "--format", "colmap", "--image-size", "9", "9"],
         2, "needs --refine or --distortion"),
        (["calibrate", "corr.csv", "--out", "r.yml"], 2,
         "--format opencv needs --refine or --distortion (OpenCV's cameras have no skew"),
        (["calibrate", "corr.csv", "--out", "r.json", "--distortion", "k9"], 2, "'k9' is not"),
        (["calibrate", "corr.csv", "--out", "r.json", "--image-size", "100", "100"], 2,
         "visible pixels lie outside the image of `image_size` (100, 100)"),
        (["calibrate", "corr.csv", "--out", "r.json", "--format", "ply"], 2, "invalid choice"),
        (["calibrate", "corr.csv", "--out", "r.txt"], 2,
         "--out r.txt: a .json, .yml/.yaml or .toml file, or a folder with --format colmap"),
        (["calibrate", "corr.csv", "--out", "r.json", "--format", "opencv"], 2,
         "--format opencv writes a .yml or .yaml file; got --out r.json"),
        (["calibrate", "tracks.csv", "--out", "r.json"], 2, "no world_x, world_y, world_z"),
        (["calibrate", "five.csv", "--out", "r.json"], 2, "at least 6 points are needed"),
        (["calibrate", "rig.json", "--out", "r.json"], 2, "not a correspondences file"),
        (["report", "rig.json", "other.csv"], 2, "camera 'c' is not in the rig ('a', 'b')"),
        (["report", "corr.csv", "rig.json"], 2,
         "corr.csv is a CSV file, not a rig: are the arguments swapped? The rig comes first: "
         "mvcalib report RIG CORRESPONDENCES"),
        (["triangulate", "tracks.csv", "rig.json", "--out", "p.csv"], 2,
         "mvcalib triangulate RIG TRACKS"),
        (["report", "neither.toml", "corr.csv"], 2,
         "neither.toml: neither caliscope's camera_array.toml ([cameras.<id>] tables) nor "
         "aniposelib's calibration.toml ([cam_N] tables)"),
        (["report", "rig.txt", "corr.csv"], 2,
         "); a rig is mvcalib's JSON, OpenCV YAML (.yml, .yaml), Kalibr's camchain.yaml, a "
         "COLMAP text model (a folder), or caliscope's camera_array.toml or aniposelib's "
         "calibration.toml."),
        (["calibrate-rig", "obs.csv", "--intrinsics", "neither.toml", "--out", "r.json"], 2,
         "neither caliscope's camera_array.toml"),
        (["calibrate-rig", "obs.csv", "--intrinsics", "corr.csv", "--out", "r.json"], 2,
         "corr.csv: a CSV file is not a rig; a rig is mvcalib's JSON"),
        (["calibrate-rig", "obs.csv", "--fisheye", "--out", "r.json"], 2,
         "--fisheye needs --image-size WIDTH HEIGHT (the photos' size), or --intrinsics with "
         "fisheye cameras"),
        (["calibrate-rig", "obs.csv", "--fisheye", "--intrinsics", "rig.json", "--out", "r.json"],
         2, "--fisheye, but the cameras of --intrinsics rig.json are pinhole cameras: leave out "
         "--fisheye, or give fisheye cameras."),
        (["calibrate-images", "dots.png", "--target", "target.txt", "--clicks", "badclicks.csv",
          "--focal", "900", "--out", "r.json"], 2,
         "badclicks.csv:1: no 'image' column; the header is image,dot_id,pixel_x,pixel_y."),
        (["calibrate-images", "dots.png", "--target", "target.txt", "--clicks", "image1.csv",
          "--out", "r.json"], 2, "image1.csv, line 2: no image '1' among the images given"),
        (["calibrate-images", "dots.png", "--target", "target.txt", "--out", "r.json"], 2,
         "target.txt: this target has no fiducial dots to label the photos from; give --clicks "
         "FILE, the dots clicked in each photo (six or more dots not all on one plane, or four or "
         "more and --focal PX)."),
        (["calibrate-images", "dots.png", "other.png", "--target", "target.txt", "--clicks",
          "four.csv", "--focal", "900", "--out", "r.json"], 2,
         "four.csv: no clicks for other.png; a target without fiducial dots needs clicks in "
         "every photo"),
        (["calibrate-images", "dots.png", "--target", "target.txt", "--clicks", "four.csv",
          "--out", "r.json"], 2,
         "four.csv: 4 clicks for dots.png; give six or more dots not all on one plane, or four "
         "or more and --focal PX (a focal-length guess in pixels)."),
        (["calibrate-images", "dots.png", "--target", "target.txt", "--clicks", "four.csv",
          "--focal", "-5", "--out", "r.json"], 2, "--focal must be positive"),
        (["report", "rig.json", "corr.csv", "--plot", "no/f.png"], 2, "folder of --plot"),
        (["triangulate", "rig.json", "tracks.csv", "--out", "p.json"], 2, "must be a .csv"),
        (["triangulate", "rig.json", "tracks.csv", "--out", "p.csv", "--min-angle", "-1"], 2,
         "--min-angle must be non-negative"),
        (["triangulate", "rig.json", "tracks.csv", "--out", "p.csv", "--max-rms", "0"], 2,
         "--max-rms must be positive"),
        (["detect", "dots.png", "--out", "d.txt"], 2, "must be a .csv or .json"),
        (["detect", "none.png", "--out", "d.csv"], 2, "no such image file: none.png"),
        (["detect", "dots.png", "--no-label", "--out", "folder.csv", "--quiet"], 2,
         "--out folder.csv is a folder; give a file name"),
        pytest.param(["calibrate", "corr.csv", "--out", "/proc/r.json"], 2,
                     "cannot write --out /proc/r.json: ",
                     marks=pytest.mark.skipif(not os.path.isdir("/proc"), reason="no /proc")),
        (["demo", "--noise", "-1"], 2, "noise levels must be non-negative"),
        (["demo", "--noise", "abc"], 2, "invalid float value"),
        (["demo", "--bogus"], 2, "unrecognized arguments: --bogus"),
        (["frobnicate"], 2, "invalid choice: 'frobnicate'"),
    ],
)  # fmt: skip
def test_failures_are_one_line_with_the_documented_exit_code(files, capsys, args, code, message):
    try:
        returned = cli.main([*args, "--quiet"])  # progress lines are not errors
    except SystemExit as exit:  # argparse's errors
        returned = exit.code
    err = capsys.readouterr().err
    assert returned == code, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert err.startswith("mvcalib: error: ") == (code == 2), err  # bad input says `error:`
    assert not list(files.glob(".*.tmp")) and not list(files.glob("folder.csv/*"))
    assert not (files / "r.json").exists()  # nothing written for bad input
    if "(see `" in err:  # a usage error points at the help of the command that was misused
        command = f"mvcalib {args[0]}" if args[0] in cli.COMMANDS else "mvcalib"
        assert err.rstrip().endswith(f"(see `{command} --help`)"), err


def test_convert_writes_a_rig_in_every_format_and_reads_it_back(files, capsys):
    """A rig from one format to another (a user had no way but Python); the cameras project the
    same points to 1e-9 px whatever the way, names kept where the format allows."""
    world = mc.targets.box_corner().points
    rig, names = mc.io.load_json("rig.json")
    (files / "sparse").mkdir()  # (an existing folder takes a COLMAP model)
    steps = [("rig.json", ["--out", "r.yml", "--image-size", "1000", "1100"]),
             ("r.yml", ["--format", "colmap", "--out", "sparse", "--image-size", "1000", "1100"]),
             ("sparse", ["--out", "back.json"])]  # fmt: skip
    for source, options in steps:
        assert cli.main(["convert", source, *options, "--quiet"]) == 0
        assert "2 cameras of " in capsys.readouterr().out
    for path in ("r.yml", "sparse", "back.json"):
        cameras, got = cli._load_rig(path)
        assert got == names
        np.testing.assert_allclose(cameras.project(world), rig.project(world), rtol=0, atol=1e-9)
    with pytest.raises(SystemExit) as exit:
        cli.main(["convert", "rig.json", "--out", "r.txt"])
    assert exit.value.code == 2 and "a .json, .yml/.yaml or .toml file" in capsys.readouterr().err


def test_convert_writes_aniposelibs_calibration_toml(files, capsys):
    rig, names = mc.io.load_json("rig.json")
    args = ["convert", "rig.json", "--out", "calibration.toml", "--quiet"]
    with pytest.raises(SystemExit) as exit:
        cli.main(args)
    assert (
        exit.value.code == 2 and "--format aniposelib needs --image-size" in capsys.readouterr().err
    )
    assert cli.main([*args, "--image-size", "1000", "1100"]) == 0
    assert (
        "2 cameras of rig.json written to calibration.toml (aniposelib)" in capsys.readouterr().out
    )
    back, got = mc.io.load_aniposelib("calibration.toml")
    world = mc.targets.box_corner().points
    assert got == names
    np.testing.assert_allclose(back.project(world), rig.project(world), rtol=0, atol=1e-9)


def test_convert_writes_kalibr_s_camchain_and_reads_it_back(files, capsys):
    """`--format kalibr` (a .yaml, read back as Kalibr's, not OpenCV's, by its `cam0:` map):
    the rig in camera a's frame, projecting as before; refused up front where it cannot hold
    the calibration asked for (k3), before any work."""
    rig, _ = mc.io.load_json("rig.json")
    args = ["convert", "rig.json", "--format", "kalibr", "--out", "camchain.yaml", "--quiet",
            "--metres-per-unit", "0.001"]  # fmt: skip
    with pytest.raises(SystemExit) as exit:
        cli.main(args)
    assert exit.value.code == 2 and "--format kalibr needs --image-size" in capsys.readouterr().err
    assert cli.main([*args, "--image-size", "1000", "1100"]) == 0
    assert "2 cameras of rig.json written to camchain.yaml (kalibr)" in capsys.readouterr().out
    assert "rostopic: /b/image_raw" in pathlib.Path("camchain.yaml").read_text()
    back, names = cli._load_rig("camchain.yaml")
    world = np.asarray(mc.targets.box_corner().points)
    in_a = world @ np.asarray(rig.R[0]).T + np.asarray(rig.t[0])  # (millimetres: metres back)
    assert names == ["cam0", "cam1"]
    np.testing.assert_allclose(back.project(in_a / 1000), rig.project(world), rtol=0, atol=1e-9)
    for wrong, message in (
        (["convert", "rig.json", "--format", "kalibr", "--out", "r.json"], "a .yaml or .yml"),
        (["calibrate", "corr.csv", "--distortion", "k1,k2,k3", "--format", "kalibr", "--out",
          "r.yaml", "--image-size", "1000", "1100"], "not k3"),
    ):  # fmt: skip
        with pytest.raises(SystemExit) as exit:
            cli.main(wrong)
        assert exit.value.code == 2 and message in capsys.readouterr().err
    assert not pathlib.Path("r.yaml").exists()


def test_convert_writes_ros_camera_info_and_reads_a_stereo_pair_back(files, capsys):
    """`--format ros` (a robotics user's trial: the last step needed Python): a file a camera in
    the folder --out, a rig of two as the rectified pair `save_ros` writes, the left camera
    first whatever the rig's order; `convert` reads the pair's two files back to the same
    relative pose, in metres. One file alone holds no pose: refused, with what to do."""
    R = np.stack([np.asarray(mc.rodrigues(np.array([0.0, 0.1, 0.0]))), np.eye(3)])
    pair = mc.Camera(
        [810.0, 800.0],
        [810.0, 800.0],
        [630.0, 640.0],
        [410.0, 400.0],
        R,
        [[-100.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
        dist=[[-0.1, 0.01, 0, 0, 0]] * 2,
    )
    mc.io.save_json("pair.json", pair, names=["right", "left"])  # (the right camera first)
    args = ["convert", "pair.json", "--format", "ros", "--out", "ros", "--metres-per-unit", "0.001"]
    with pytest.raises(SystemExit) as exit:
        cli.main(args)
    assert exit.value.code == 2 and "--format ros needs --image-size" in capsys.readouterr().err
    assert cli.main([*args, "--image-size", "1280", "800"]) == 0
    out = capsys.readouterr()
    assert "2 cameras of pair.json written to ros (ros)" in out.out
    assert "a stereo pair, rectified: left left, right right" in out.err
    assert "camera_name: left" in pathlib.Path("ros/left.yaml").read_text()
    assert (
        cli.main(["convert", "ros/left.yaml", "ros/right.yaml", "--out", "back.json", "--quiet"])
        == 0
    )
    back, names = mc.io.load_json("back.json")
    assert names == ["left", "right"]
    right_in_left = (pair.center[0] - pair.center[1]) @ np.asarray(pair.R[1]).T / 1000  # metres
    np.testing.assert_allclose(back.center[1], right_in_left, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.K, pair.K[::-1], rtol=0, atol=1e-9)
    assert cli.main(["convert", "ros/left.yaml", "--out", "one.json", "--quiet"]) == 2
    assert "intrinsics without poses" in capsys.readouterr().err and not os.path.exists("one.json")
    assert cli.main(["convert", "ros/left.yaml", "pair.json", "--out", "one.json", "--quiet"]) == 2
    assert "not one of these: pair.json" in capsys.readouterr().err
    three = jax.tree_util.tree_map(lambda a: np.concatenate([a, a[:1]]), pair)
    mc.io.save_json("three.json", three, names=["a", "b", "c"])
    options = ["--format", "ros", "--out", "each", "--image-size", "1280", "800"]
    assert cli.main(["convert", "three.json", *options]) == 0
    assert "3 cameras, each on its own" in capsys.readouterr().err
    alone, _ = cli._load_rig("each/c.yaml")  # (an intrinsics file for calibrate-rig)
    np.testing.assert_allclose(alone.K[0], pair.K[0], rtol=0, atol=1e-9)
    assert np.isnan(np.asarray(alone.t)).all()


def test_convert_keeps_a_json_rigs_statuses_rms_and_meta(files, capsys):
    """`convert` set every finite camera OK and dropped the RMS and meta (a POOR_FIT camera went
    into the YAML as a good one): JSON to JSON keeps them, YAML and COLMAP leave out the
    cameras not OK and name them."""
    rig, _ = mc.io.load_json("rig.json")
    four = jax.tree_util.tree_map(lambda a: np.concatenate([a, a[:1], np.nan * a[:1]]), rig)
    # (a failed camera, NaN, kept its reason, not NON_FINITE: a user's trial)
    status = [mc.Status.OK, mc.Status.POOR_FIT, mc.Status.DEGENERATE, mc.Status.NOT_CONNECTED]
    mc.io.save_json("flagged.json", four, names=["a", "b", "c", "d"],
                    rms=[0.3, 41.0, 0.2, float("nan")], status=status,
                    meta={"target": "box"})  # fmt: skip
    assert cli.main(["convert", "flagged.json", "--out", "back.json", "--quiet"]) == 0
    _, names, record = mc.io.load_json("back.json", record=True)
    assert names == ["a", "b", "c", "d"] and record["status"].tolist() == [int(s) for s in status]
    assert record["rms"].tolist()[:3] == [0.3, 41.0, 0.2]
    assert record["meta"] == {"target": "box", "converted_from": "flagged.json"}
    capsys.readouterr()
    assert cli.main(["convert", "flagged.json", "--out", "ok.yml", "--quiet"]) == 0
    out = capsys.readouterr()
    assert "1 camera of flagged.json written" in out.out
    assert "left out, not calibrated: b (POOR_FIT), c (DEGENERATE), d (NOT_CONNECTED)" in out.err
    assert mc.io.load_opencv("ok.yml")[1] == ["a"]


def test_files_naming_cameras_as_opencv_yaml_spells_them_match_a_json_rig(files, capsys):
    """`cal/cam1.tif` is `cal_cam1_tif` in OpenCV's YAML; a file naming the cameras so was
    refused against the JSON rig of the same calibration (the other way round worked)."""
    rig, _ = mc.io.load_json("rig.json")
    mc.io.save_json("named.json", rig, names=["cal/cam 1.tif", "cal/cam 2.tif"])
    data = mc.io.load_correspondences("corr.csv")
    mc.io.save_correspondences("yaml_names.csv", data.world, data.pixels, data.mask,
                               cameras=["cal_cam_1_tif", "cal_cam_2_tif"])  # fmt: skip
    assert cli.main(["report", "named.json", "yaml_names.csv", "--quiet"]) == 0
    assert "all cameras: " in capsys.readouterr().out


def test_output_piped_into_a_reader_that_stops_early_still_writes_the_files(files):
    """`mvcalib calibrate ... | head -1`: the broken pipe stopped the command ("[Errno 32] Broken
    pipe", exit code 1) before it wrote --out, where its table came first."""
    process = subprocess.Popen(
        [sys.executable, "-m", "mvcalib", "calibrate", "corr.csv", "--out", "r.json", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    process.stdout.readline()
    process.stdout.close()  # the reader has gone
    assert process.wait(timeout=600) == 0
    assert "Broken pipe" not in process.stderr.read()
    assert len(mc.io.load_json(files / "r.json")[1]) == 2


def test_triangulate_points_out_ok_points_that_fit_badly(files, capsys):
    world = mc.targets.box_corner().points
    tracks = mc.io.load_correspondences("tracks.csv")
    pixels = np.array(tracks.pixels)
    assert cli.main(["triangulate", "rig.json", "tracks.csv", "--out", "p.csv"]) == 0
    assert "note:" not in capsys.readouterr().out  # a rig and tracks that fit: no note
    pixels[1, :3] += 40.0  # three points that camera b sees 40 px off: in front, badly fit
    mc.io.save_correspondences("off.csv", None, pixels, cameras=["a", "b"])
    # by default a point that reprojects worse than 10 px is not ok (it was, with a note only)
    assert cli.main(["triangulate", "rig.json", "off.csv", "--out", "p.csv"]) == 0
    out = capsys.readouterr().out
    assert (
        f"{len(world) - 3} ok (in front of their cameras, rays >= 1 deg apart, RMS <= 10 px)" in out
    )
    assert "note: 3 points reproject worse than 10 px" in out and "0 of them ok" in out
    with open("p.csv") as f:
        assert [row["ok"] for row in csv.DictReader(f)][:4] == ["0", "0", "0", "1"]
    assert (
        cli.main(["triangulate", "rig.json", "off.csv", "--out", "p.csv", "--max-rms", "inf"]) == 0
    )
    out = capsys.readouterr().out
    assert f"{len(world)} ok (in front of their cameras, rays >= 1 deg apart)" in out
    assert "3 of them ok" in out
    assert (
        cli.main(["triangulate", "rig.json", "off.csv", "--out", "p.csv", "--max-rms", "50"]) == 0
    )
    assert "RMS <= 50 px" in capsys.readouterr().out
    # detections without point ids are not triangulated, and it is said (it was not)
    mc.io.save_correspondences("anon.csv", None, pixels[:, :0], np.zeros((2, 0), bool),
                               cameras=["a", "b"], unlabelled=[pixels[0], pixels[1]])  # fmt: skip
    assert cli.main(["triangulate", "rig.json", "anon.csv", "--out", "p.csv"]) == 1
    out = capsys.readouterr().out
    assert f"note: {2 * len(world)} detections without a point id" in out


def test_calibrate_writes_the_format_its_out_file_names(files, capsys):
    """Without --format, `calibrate` writes what --out's suffix says: .yml is OpenCV's YAML."""
    assert cli.main(["calibrate", "corr.csv", "--refine", "--out", "r.yml", "--quiet"]) == 0
    assert "(opencv)" in capsys.readouterr().out
    cameras, names = mc.io.load_opencv("r.yml")
    assert names == ["a", "b"] and cameras.batch_shape == (2,)


@pytest.mark.parametrize(
    "toml", ["caliscope_4cam/camera_array.toml",
             "aniposelib_mouse_outdoor/calibration_right_4_10_2026_adjusted.toml"],
)  # fmt: skip
def test_report_reads_caliscope_and_aniposelib_rigs(files, capsys, toml):
    folder, name = toml.split("/")
    path = data_dir(folder) / name
    load = mc.io.load_caliscope_cameras if folder.startswith("caliscope") else mc.io.load_aniposelib
    cameras, names = load(path)
    # points around the middle of the cameras' centres, as each camera of the file sees them
    centres = np.einsum("cji,cj->ci", np.asarray(cameras.R), -np.asarray(cameras.t))
    spread = np.ptp(centres, 0).max()
    world = centres.mean(0) + 0.05 * spread * np.random.default_rng(0).standard_normal((20, 3))
    pixels = np.asarray(cameras.project(world))
    mc.io.save_correspondences("seen.csv", world, pixels, cameras=names)
    assert cli.main(["report", str(path), "seen.csv", "--quiet"]) == 0
    out = capsys.readouterr().out
    table = _table(out)
    assert list(table) == names
    assert all(row[2] < 1e-6 and row[4] == 20 for row in table.values())  # RMS, points


def test_calibrate_rig_reads_aniposelib_intrinsics(files, capsys):
    # read as a rig (12 cameras), not refused as "no [cameras.<id>] tables" of caliscope's
    path = data_dir("aniposelib_mouse_outdoor") / "calibration_right_4_10_2026_adjusted.toml"
    args = ["calibrate-rig", "obs.csv", "--intrinsics", str(path), "--out", "r.json", "--quiet"]
    assert cli.main(args) == 2
    assert capsys.readouterr().err == (
        f"mvcalib: error: {path}: 12 cameras; the observations have 2, and no name in common "
        "to match them by.\n"
    )


def test_messages_about_photos_name_no_python_arguments(files, capsys):
    assert cli.main(["detect", "blank.png", "--out", "d.csv"]) == 1
    out, err = capsys.readouterr()
    said = "blank.png: the image is constant: it has no contrast"
    assert said in err and "the image is constant" in out and "`image`" not in out + err
    (files / "r.json").write_text("an earlier rig")
    assert cli.main(["calibrate-images", "blank.png", "--out", "r.json"]) == 1
    out, err = capsys.readouterr()
    assert said in err and "the image is constant" in out and "`image`" not in out + err
    # nothing calibrated: the file there is left alone (it was replaced by NaN cameras)
    assert "no camera could be calibrated; r.json not written" in err
    assert (files / "r.json").read_text() == "an earlier rig"


def test_report_without_matplotlib_says_how_to_install_it(files, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # import fails
    assert cli.main(["report", "rig.json", "corr.csv", "--plot", "f.png"]) == 1
    assert capsys.readouterr().err == (
        "mvcalib: mvcalib's plots need matplotlib: pip install 'mvcalib[plot]'\n"
    )


def test_detect_without_labels_writes_every_blob(files, capsys):
    assert cli.main(["detect", "dots.png", "--no-label", "--out", "blobs.json"]) == 0
    data = mc.io.load_correspondences(files / "blobs.json")
    assert data.world is None and data.pixels.shape == (1, 0, 2)
    found = data.unlabelled[0][np.lexsort(data.unlabelled[0].T[::-1])]
    np.testing.assert_allclose(found, [[40, 30], [40, 85], [75, 60], [110, 30], [110, 85]],
                               atol=0.05)  # fmt: skip
    assert "[1/1] dots.png: 5 dots detected" in capsys.readouterr().err


# ---------------------------------------------------------------------------- help
@pytest.mark.parametrize("command", list(cli.COMMANDS))
def test_every_command_has_help_with_examples(command, capsys):
    with pytest.raises(SystemExit) as exit:
        cli.main([command, "--help"])
    out = capsys.readouterr().out
    assert exit.value.code == 0 and "examples:" in out and f"mvcalib {command}" in out
    assert "exit codes: 0 success, 1 the work failed, 2 bad usage" in out


def test_demo_help_says_float32_draws_another_scene(capsys):
    with pytest.raises(SystemExit):
        cli.main(["demo", "--help"])
    out = capsys.readouterr().out
    assert "the same in single precision" not in out
    assert "a scene drawn and solved in single precision" in out and "other random poses" in out
    # ... as it does: the same seed, other poses (the same intrinsics)
    scenes = [mc.synthetic.paper_scene(noise=0.0, dtype=d) for d in (np.float64, np.float32)]
    assert np.abs(np.asarray(scenes[0].pixels) - np.asarray(scenes[1].pixels)).max() > 10


def test_console_script_and_no_command(capsys):
    from importlib.metadata import entry_points

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "mvcalib"]
    assert script.value == "mvcalib.cli:main"  # `mvcalib` runs what `python -m mvcalib` runs
    assert cli.main([]) == 2 and "examples:" in capsys.readouterr().out
