"""Seeded labelling (`mc.match_dots`): synthetic photographs with known cameras, wrong seeds,
bad input, and OpenPTV's real cavity photographs seeded by its own clicked points."""

import functools
import json
import os
import re

import jax
import numpy as np
import pytest
from _real_data import cavity_clicks
from conftest import cavity, data_dir

import mvcalib as mc

TARGET = mc.targets.box_corner_grid(6)  # 108 dots on three faces
IMAGE = (1000, 1100)  # (height, width) as mc.synthetic renders by default


def view(seed, clutter=0, hidden=()):
    camera = mc.synthetic.random_rig(jax.random.key(seed), 1, TARGET).cameras[0]
    image = mc.synthetic.render(camera, TARGET, clutter=clutter, hidden=hidden, key=seed)
    truth = np.asarray(camera.project(TARGET.points))
    return camera, mc.detect_dots(image), truth


def focal_of(camera):
    return float(camera.alpha_u)


def verdict(labels, truth):
    """'right' (every labelled dot within 1.5 px of its own projection), 'flagged', or 'wrong'."""
    if not labels.ok:
        assert not labels.mask.any() and labels.message
        return "flagged"
    error = np.linalg.norm(labels.pixels[labels.mask] - truth[labels.mask], axis=-1)
    return "right" if error.max() < 1.5 else "wrong"


# dots spread over the three faces (18 per face: 0-35 floor, 36-71 wall y, 72-107 wall x)
SIX = [0, 11, 40, 47, 80, 95]
ON_ONE_FACE = [0, 5, 30, 35]  # the floor's corners: coplanar


def test_six_clicks_label_every_dot():
    camera, detection, truth = view(1)
    clicks = truth[SIX] + np.random.default_rng(0).normal(0, 1.0, (6, 2))
    labels = mc.match_dots(detection, TARGET, (clicks, TARGET.ids[SIX]))
    assert verdict(labels, truth) == "right", labels.message
    assert labels.mask.sum() == len(detection) == 108  # every dot, no clutter here
    assert labels.rms < 0.5 and "108 of 108 dots matched" in labels.message


def test_four_coplanar_clicks_and_a_focal_guess():
    camera, detection, truth = view(2)
    labels = mc.match_dots(
        detection, TARGET, (truth[ON_ONE_FACE], ON_ONE_FACE), focal=focal_of(camera)
    )
    assert verdict(labels, truth) == "right" and labels.mask.sum() == 108, labels.message


def test_a_rough_camera_seed_and_clutter_and_hidden_dots():
    camera, detection, truth = view(3, clutter=30, hidden=range(0, 108, 9))
    rough = camera.__class__(
        1.03 * camera.alpha_u, camera.alpha_v, camera.u0 + 8, camera.v0 - 5, camera.R, camera.t
    )
    labels = mc.match_dots(detection, TARGET, rough)
    assert verdict(labels, truth) == "right", labels.message
    assert labels.mask.sum() == 108 - 12 and not labels.mask[::9].any()
    # the clutter blobs that detect_dots kept are left out, as spurious
    assert len(labels.spurious) == len(detection) - 96 > 0


def test_wrong_seeds_are_corrected_or_flagged_never_wrong():
    """A sweep over views: one click 30 px off, two clicks with swapped ids, a focal guess 30 %
    off (with four coplanar clicks)."""
    counts = {}
    for seed in range(6):
        camera, detection, truth = view(10 + seed, clutter=10)
        rng = np.random.default_rng(seed)
        off = truth[SIX].copy()
        off[rng.integers(6)] += 30 * np.array([np.cos(seed), np.sin(seed)])
        swapped = np.array(SIX)
        swapped[[1, 4]] = swapped[[4, 1]]
        for name, labels in {
            "one click 30 px off": mc.match_dots(detection, TARGET, (off, SIX)),
            "two ids swapped": mc.match_dots(detection, TARGET, (truth[SIX], swapped)),
            "focal 30 % off": mc.match_dots(
                detection, TARGET, (truth[ON_ONE_FACE], ON_ONE_FACE), focal=1.3 * focal_of(camera)
            ),
        }.items():
            counts.setdefault(name, {"right": 0, "flagged": 0, "wrong": 0})
            counts[name][verdict(labels, truth)] += 1
    print(counts)
    # Measured: one click off 1 right, 5 flagged (six clicks over-determine the DLT by one
    # equation, which absorbs the error near the bad click: the dots there match their
    # neighbours and the fit is rejected); swapped ids 6 flagged (the clicks misfit); the focal
    # guess 6 right (the pose is refitted to the matches).
    assert all(c["wrong"] == 0 for c in counts.values()), counts
    assert counts["focal 30 % off"]["right"] == 6 and counts["two ids swapped"]["flagged"] == 6


def test_clicks_a_column_off_on_a_periodic_plate_are_flagged():
    """Clicks all one column over on a PIV plate name every dot by its neighbour: the labels
    fit a camera a pitch away as well as the right ones (a user's trial: 688 of 688 labels wrong,
    ok, 0.35 px RMS). The shifted labelling leaves the border column beyond it unexplained,
    which its shift by one lattice step explains: flagged."""
    plate = mc.targets.plate(6, 20, 6.0, dot_radius=0.6)
    centre = plate.points.mean(0)
    camera = mc.Camera(3000.0, 3000.0, 550.0, 200.0, np.diag([1.0, -1.0, -1.0]),
                       -np.diag([1.0, -1.0, -1.0]) @ (centre + [0.0, 0.0, 400.0]))  # fmt: skip
    photo = np.array(mc.synthetic.render(camera, plate, (1100, 400), noise_sigma=2.0, key=1))
    detection = mc.detect_dots(photo)
    corners = np.array([0, 19, 100, 119])  # level 0's corners (row by row, 20 a row)
    pixels = np.asarray(camera.project(plate.points))[corners]
    right = mc.match_dots(detection, plate, (pixels, plate.ids[corners]), focal=3000.0)
    assert right.ok and right.mask.sum() == len(plate.points)
    inner = np.array([1, 19, 101, 119])  # dots 1, 19, 101, 119 clicked ...
    shifted = mc.match_dots(detection, plate, (np.asarray(camera.project(plate.points))[inner],
                                               plate.ids[inner - 1]), focal=3000.0)  # fmt: skip
    assert not shifted.ok and "shifted by one step of the target's lattice" in shifted.message


def test_bad_seeds_raise_with_the_reason():
    camera, detection, truth = view(4)
    with pytest.raises(ValueError, match="no dot of target .* has the id 500"):
        mc.match_dots(detection, TARGET, (truth[:4], [0, 1, 2, 500]), focal=1000.0)
    with pytest.raises(ValueError, match="`focal`"):
        mc.match_dots(detection, TARGET, (truth[ON_ONE_FACE], ON_ONE_FACE))
    with pytest.raises(ValueError, match="`focal`"):
        mc.match_dots(detection, TARGET, (truth[:3], [0, 1, 2]), focal=1000.0)
    with pytest.raises(ValueError, match="clicked twice"):
        mc.match_dots(detection, TARGET, (truth[[0, 0, 5, 30]], [0, 0, 5, 30]), focal=1000.0)
    with pytest.raises(ValueError, match="4 clicked pixels for 5 dot ids"):
        mc.match_dots(detection, TARGET, (truth[:4], [0, 1, 2, 3, 4]), focal=1000.0)
    with pytest.raises(ValueError, match="Camera or clicked"):
        mc.match_dots(detection, TARGET, "camera 1")


def test_a_seed_far_off_is_flagged():
    camera, detection, truth = view(5)
    labels = mc.match_dots(detection, TARGET, (truth[SIX] + [300.0, -200.0], SIX))
    assert verdict(labels, truth) in ("flagged", "right"), labels.message


# ------------------------------------------------------------------------ real photographs
# Dots matched per camera with detect_dots' defaults and with a relaxed ellipse test (the dots'
# highlight crescents give ragged outlines); measured: 36, 40, 69, 66 and 42, 41, 70, 69 of 73
# (cam1 and cam2: two of five rows hidden by a block, 45 dots visible).
MATCHED = {(): (36, 40, 69, 66), (("max_ellipse_error", (2.0, 1.0)),): (42, 41, 70, 69)}


@pytest.mark.parametrize("options", list(MATCHED), ids=["defaults", "relaxed"])
def test_openptv_cavity_from_its_own_clicks(options):
    target, views = cavity(**dict(options))
    for camera, (_, _, labels) in enumerate(views):
        assert labels.ok, labels.message
        n = int(labels.mask.sum())
        dlt = mc.calibrate(target.points, labels.pixels, labels.mask)
        refined = mc.calibrate(target.points, labels.pixels, labels.mask, refine=True)
        print(
            f"cam{camera + 1}: {labels.message}; DLT {float(dlt.report.rms):.3f} px, refined "
            f"{float(refined.report.rms):.3f} px"
        )
        assert n >= MATCHED[options][camera] - 1
        # a pinhole through glass into water: the DLT fits to ~0.3-0.5 px, refinement a bit less
        assert float(dlt.report.rms) < 0.6 and bool(refined.ok)
        assert float(refined.report.rms) <= float(dlt.report.rms) + 1e-9
        if camera < 2:  # the block hides the two lowest rows: 45 dots visible
            assert n <= 45
        # OpenPTV's click on cam1's dot 3 (saturated): said to be left out where no blob matched
        lost = "clicked dots with no blob matched (left out): ids 3"
        if camera == 0:
            dot3 = int(np.flatnonzero(np.asarray(target.ids) == 3)[0])
            assert (lost in labels.message) == (not labels.mask[dot3]), labels.message


# ------------------------------------------------------------------------ the command line
def run_cli(*args):
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-m", "mvcalib", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_cli_calibrates_the_cavity_photos_from_openptv_clicks(tmp_path):
    pytest.importorskip("imagecodecs")  # the photos are LZW-compressed TIFFs
    root = data_dir("openptv_cavity")
    images = [root / "cal" / f"cam{c}.tif" for c in range(1, 5)]
    target = root / "cal" / "target_on_a_side.txt"
    clicks = cavity_clicks(root, tmp_path / "clicks.csv")
    common = ["--target", target, "--focal", 70.0 / 0.012, "--bright-dots"]
    man_ori = root / "parameters" / "man_ori.par"  # OpenPTV's clicks as they are
    out = run_cli(
        "calibrate-images", *images, *common, "--clicks", man_ori, "--out", tmp_path / "r.json",
        "--dots", tmp_path / "dots.csv",
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "4 of 4 cameras calibrated" in out.stdout
    assert re.search(r"^ *cam4\.tif +-?0\.\d+ ", out.stdout, re.M), out.stdout  # Table I
    cameras, names = mc.io.load_json(tmp_path / "r.json")
    assert cameras.batch_shape == (4,) and np.all(np.isfinite(np.asarray(cameras.alpha_u)))
    messages = json.loads((tmp_path / "r.json").read_text())["meta"]["messages"]
    assert all("second look:" in m for m in messages), messages  # dots found again in each
    # Dot 68 is beyond the gate in cam1 and cam4: the target file misplaces it (~0.13 mm)
    assert "dot 68: the images put it at" in out.stdout, out.stdout
    # the intrinsics the nearly flat target does not fix are said (in Python's `print` too)
    assert re.search(r"^note: principal points outside the photo: cam1\.tif \(", out.stdout,
                     re.M), out.stdout  # fmt: skip
    misplaced = json.loads((tmp_path / "r.json").read_text())["meta"]["misplaced"]
    assert list(misplaced) == ["68"]
    assert 0.05 < np.linalg.norm(np.subtract(misplaced["68"], (25.0, 25.0, 8.0))) < 0.3
    # the dots file holds the dots the calibration used: `mvcalib report` gives its table
    assert "(not the misplaced dot 68: as in the calibration)" in out.stdout
    dots = mc.io.load_correspondences(tmp_path / "dots.csv")
    assert "68" not in [p for p, seen in zip(dots.points, dots.mask.any(0)) if seen]
    report = run_cli("report", tmp_path / "r.json", tmp_path / "dots.csv")
    table = re.search(r"^ *cam4\.tif .*$", out.stdout, re.M).group(0).split()[1:5]
    assert report.returncode == 0 and " ".join(table) in " ".join(report.stdout.split()), (
        report.stdout
    )
    # an unknown dot id in the clicks: bad input, exit 2, one line naming the row
    bad = cavity_clicks(root, tmp_path / "bad.csv", ["cam1.tif,999,10,10"])
    out = run_cli(
        "calibrate-images", *images, *common, "--clicks", bad, "--out", tmp_path / "b.json"
    )
    assert out.returncode == 2 and out.stderr.startswith("mvcalib: error: ")
    assert "line 18: the target has no dot 999" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr
    # a corrupt photo: that camera flagged with the reason, exit 1, the others calibrated
    broken = tmp_path / "cam2.tif"
    broken.write_bytes(b"II*\x00 not a tiff")
    out = run_cli(
        "calibrate-images", images[0], broken, *images[2:], *common, "--clicks", clicks,
        "--out", tmp_path / "c.json", "--no-second-look", "--distortion", "k1", "--huber", "0.5",
        "--names", "cam1", "cam2", "cam3", "cam4",
    )  # fmt: skip
    assert out.returncode == 1 and "3 of 4 cameras calibrated" in out.stdout, out.stdout
    assert "cam2.tif: cannot be read as an image" in out.stderr, out.stderr
    messages = json.loads((tmp_path / "c.json").read_text())["meta"]["messages"]
    assert not any("second look" in m for m in messages), messages
    assert mc.io.load_json(tmp_path / "c.json")[1] == ["cam1", "cam2", "cam3", "cam4"]
    dist = np.asarray(mc.io.load_json(tmp_path / "c.json")[0].dist)[[0, 2, 3]]
    assert np.all(dist[:, 0] != 0) and np.all(dist[:, 1:] == 0)  # refined, k1 only


# ------------------------------------------------------------------------ printed dot grids
GRID = mc.targets.dot_grid(9, 12, 20.0)  # 220 x 160 mm, dots 8 mm wide
K_TRUE = (1400.0, 1400.0, 639.5, 479.5)


def grid_view(seed, tilt_deg, grid=GRID):
    """A camera looking at the grid's centre from `tilt_deg` off its normal, any azimuth and
    roll, at the distance that keeps the whole grid (of `GRID`'s size) inside a 1280 x 960
    image."""
    rng = np.random.default_rng(seed)
    centre = grid.points.mean(0)
    tilt, azimuth, roll = np.deg2rad(tilt_deg), rng.uniform(0, 2 * np.pi), rng.uniform(-0.5, 0.5)
    direction = np.array(
        [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
    )
    position = centre + rng.uniform(420.0, 480.0) * direction
    z = (centre - position) / np.linalg.norm(centre - position)
    x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R0 = np.stack([x, y, z])
    spin = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    R = spin @ R0
    return mc.Camera(*K_TRUE, R, -R @ position)


def test_dot_grids_are_labelled_without_clicks_and_calibrate_a_camera():
    """Issue 41: 5 % of the dots hidden, clutter, up to 60 degrees of tilt: every view right (up
    to the symmetric grid's half turn) or flagged, none wrong; calibrate_planar from the photos
    recovers the intrinsics."""
    counts = {"right": 0, "flagged": 0, "wrong": 0}
    pixels, masks = [], []
    M = len(GRID)
    for seed, tilt in enumerate(np.linspace(0.0, 60.0, 12)):
        camera = grid_view(seed, tilt)
        hidden = np.random.default_rng(100 + seed).choice(M, int(0.05 * M), replace=False)
        image = mc.synthetic.render(camera, GRID, (1280, 960), clutter=10, hidden=hidden, key=seed)
        labels = mc.label_grid(mc.detect_dots(image), 9, 12)
        truth = np.asarray(camera.project(GRID.points))
        if not labels.ok:
            counts["flagged"] += 1
            continue
        seen = labels.mask
        right = [np.abs(labels.pixels[seen] - t[seen]).max() < 1.5 for t in (truth, truth[::-1])]
        counts["right" if any(right) else "wrong"] += 1
        if any(right):
            pixels.append(np.nan_to_num(labels.pixels))
            masks.append(seen)
    print(counts)
    assert counts["wrong"] == 0 and counts["right"] >= 11, counts  # measured: 12 of 12
    pixels, masks = np.stack(pixels), np.stack(masks)
    out = mc.calibrate_planar(GRID.points, pixels, masks, distortion=())
    found = [float(getattr(out.camera, k)[0]) for k in ("alpha_u", "alpha_v", "u0", "v0")]
    error = np.abs(np.array(found) - K_TRUE) / K_TRUE[0]
    print(f"intrinsics error {error.round(5)} of the focal length, RMS {float(out.rms):.3f} px")
    assert error.max() < 0.002


def rolled_view(seed, tilt_deg, grid=GRID):
    """`grid_view` turned about its axis by any angle: the grid upside down or sideways too."""
    camera = grid_view(seed, tilt_deg, grid)
    a = np.random.default_rng(seed).uniform(0, 2 * np.pi)
    roll = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    R = roll @ np.asarray(camera.R)
    return mc.Camera(*K_TRUE, R, -R @ np.asarray(camera.center))


@pytest.mark.parametrize("rows, cols", [(9, 12), (8, 8)])
def test_marked_grids_are_labelled_in_their_own_orientation(rows, cols):
    """Four dots in an L printed larger (`dot_grid(markers=)`) tell a grid's orientation, so that
    a dot's id is the same in every camera: views at any roll, 5 % hidden, clutter, up to 60
    degrees of tilt, every one right or flagged. Without the markers, a symmetric grid's ids
    hold up to its half turn (a square one's up to its quarter turns) only: measured, 4 of 8 (9
    x 12) and 5 of 8 (8 x 8) views turned."""
    markers = (0, 1, 2, cols)
    grid = mc.targets.dot_grid(rows, cols, 20.0, markers=markers)
    M = rows * cols
    counts = {"right": 0, "flagged": 0, "wrong": 0}
    turned = 0
    for seed, tilt in enumerate(np.linspace(0.0, 60.0, 8)):
        camera = rolled_view(seed, tilt)
        hidden = np.random.default_rng(100 + seed).choice(
            np.setdiff1d(np.arange(M), markers), int(0.05 * M), replace=False
        )
        image = mc.synthetic.render(camera, grid, (1280, 960), clutter=10, hidden=hidden, key=seed)
        detection = mc.detect_dots(image)
        truth = np.asarray(camera.project(grid.points))
        labels = mc.label_grid(detection, rows, cols, markers=markers)
        if labels.ok:
            right = np.abs(labels.pixels[labels.mask] - truth[labels.mask]).max() < 1.5
            counts["right" if right else "wrong"] += 1
        else:
            counts["flagged"] += 1
        plain = mc.label_grid(detection, rows, cols)
        turned += plain.ok and np.abs(plain.pixels[plain.mask] - truth[plain.mask]).max() > 1.5
    print(counts, f"without markers {turned} of 8 turned")
    assert counts["wrong"] == 0 and counts["right"] >= 7, counts  # measured: 8 of 8 each
    assert turned >= 2  # (what the markers are for)


def test_asymmetric_circle_grids_need_no_markers():
    """OpenCV's asymmetric circles grid (`dot_grid(asymmetric=True)`; 11 rows of 4 dots, its
    sample pattern) maps onto itself by no turn, so its dots keep their ids from any roll with
    no markers: views at any roll, 5 % hidden, clutter, up to 60 degrees of tilt, every one
    right or flagged (measured: 8 of 8 right). On the clean photos OpenCV's `findCirclesGrid`
    finds, its centres are ours to 0.1 px, in the order of the grid seen from its other side
    (OpenCV's cameras face the board's -z side): the grid's one mirroring."""
    import cv2

    rows, cols = 11, 4
    grid = mc.targets.dot_grid(rows, cols, 40.0, asymmetric=True)  # 140 x 200 mm
    M = len(grid)
    counts = {"right": 0, "flagged": 0, "wrong": 0}
    found_by_opencv = 0
    for seed, tilt in enumerate(np.linspace(0.0, 60.0, 8)):
        camera = rolled_view(seed, tilt, grid)
        truth = np.asarray(camera.project(grid.points))
        hidden = np.random.default_rng(100 + seed).choice(M, int(0.05 * M), replace=False)
        image = mc.synthetic.render(camera, grid, (1280, 960), clutter=10, hidden=hidden, key=seed)
        labels = mc.label_grid(mc.detect_dots(image), rows, cols, asymmetric=True)
        if labels.ok:
            right = np.abs(labels.pixels[labels.mask] - truth[labels.mask]).max() < 1.5
            counts["right" if right else "wrong"] += 1
        else:
            counts["flagged"] += 1
        clean = mc.synthetic.render(camera, grid, (1280, 960), key=seed)
        ok, centres = cv2.findCirclesGrid(clean, (cols, rows), flags=cv2.CALIB_CB_ASYMMETRIC_GRID)
        if ok:
            ours = mc.label_grid(mc.detect_dots(clean), rows, cols, asymmetric=True)
            mirrored = np.arange(M).reshape(rows, cols)[::-1].ravel()
            assert np.abs(centres.reshape(M, 2) - ours.pixels[mirrored]).max() < 0.1
            found_by_opencv += 1
    print(counts, f"OpenCV found {found_by_opencv} of 8 clean views")
    assert counts["wrong"] == 0 and counts["right"] >= 7, counts
    assert found_by_opencv >= 4  # (measured: 7)


@functools.cache
def marked_grid_rig():
    """Photos of a 7 x 9 dot grid with four markers in 40 poses before 4 cameras (a `board_rig`,
    each camera on the board's printed side, z towards the board, as OpenCV's), where a camera
    sees the whole grid (else None): `(grid, rig, photos[c][f])`."""
    import jax

    grid = mc.targets.dot_grid(7, 9, 0.05, markers=(0, 1, 2, 9), units="m")
    rig = mc.synthetic.board_rig(
        jax.random.key(1), n_cameras=4, n_frames=40, target=grid.points, distortion=False
    )
    C, F, N = rig.mask.shape
    printed_side = np.tile([0.0, 0.0, -1.0], (N, 1))  # the board's -z side faces its cameras
    photos = [[None] * F for _ in range(C)]
    for c, f in zip(*np.nonzero(rig.mask.all(-1))):  # the frames that show the whole grid
        camera = rig.cameras[c]
        R = np.asarray(camera.R) @ np.asarray(rig.poses.R[f])
        t = np.asarray(camera.R) @ np.asarray(rig.poses.t[f]) + np.asarray(camera.t)
        view = mc.Camera(camera.alpha_u, camera.alpha_v, camera.u0, camera.v0, R, t)
        photos[c][f] = mc.synthetic.render(view, grid, rig.image_size, normals=printed_side,
                                           key=int(f))  # fmt: skip
    return grid, rig, photos


def centre_errors(rig, cameras):
    """Each camera's centre error against `rig`'s, both in camera 0's frame (the solve's)."""
    R0, t0 = np.asarray(rig.cameras.R[0]), np.asarray(rig.cameras.t[0])
    truth = np.asarray(rig.cameras.center) @ R0.T + t0
    return np.linalg.norm(np.asarray(cameras.center) - truth, axis=-1)


def test_a_rig_from_photos_of_a_marked_grid_moved_through_the_volume():
    """The rig workflow from photographs (`marked_grid_rig`): `observe_grid` labels each photo
    alone, then `calibrate_rig`: every camera, centres within 1 mm of 2-3 m baselines
    (measured 0.3-0.7 mm), focal lengths within 2e-4."""
    grid, rig, photos = marked_grid_rig()
    obs = mc.observe_grid(photos, grid)
    labelled = obs.mask.any(-1)
    off = np.abs(obs.pixels - np.asarray(rig.pixels_true))[obs.mask]
    assert off.max() < 1 and labelled.sum() >= 30  # measured: all 35 labelled
    out = mc.calibrate_rig(obs.target, obs.pixels, obs.mask)
    assert bool(out.ok.all()), out
    error = centre_errors(rig, out.cameras)
    print(f"{labelled.sum()} photos labelled; centre errors {1000 * error.round(5)} mm")
    assert error.max() < 1e-3
    focal = np.abs(np.asarray(out.cameras.alpha_u) / np.asarray(rig.cameras.alpha_u) - 1)
    assert focal.max() < 2e-4
    with pytest.raises(ValueError, match="as many for every camera"):
        mc.observe_grid([photos[0], photos[1][:3]], grid)
    with pytest.raises(ValueError, match=r"got a photo where a camera's list should be"):
        mc.observe_grid(photos[0], grid)  # one camera's photos, not a list of cameras' lists
    typo = [list(camera) for camera in photos]
    typo[1][2], typo[0][0] = "nowhere/cam1_2.png", "nowhere/cam0_0.png"
    with pytest.raises(ValueError, match=r"no such photo file: nowhere/cam0_0.png \(cam0, frame "
                       r"0\), and 1 more"):  # fmt: skip
        mc.observe_grid(typo, grid)
    with pytest.raises(ValueError, match="not a grid of dots"):
        mc.observe_grid(photos, mc.targets.box_corner())
    # the same grid without its markers: a rig's ids only up to a half turn (a photographer's
    # trial: 864 of 2592 labels half turned, no word), said
    points = np.asarray(grid.points)
    rows, cols = len(np.unique(points[:, 1])), len(np.unique(points[:, 0]))
    unmarked = mc.targets.dot_grid(rows, cols, float(points[1, 0] - points[0, 0]))
    with pytest.warns(UserWarning, match=rf"{rows} x {cols} grid has no markers.*markers="):
        mc.observe_grid([camera[:1] for camera in photos[:2]], unmarked)


def test_photos_labelled_in_worker_processes_give_the_same_observations(tmp_path, capsys):
    """`observe_grid(..., workers=2)`: the photos (arrays and files, one of them not an image)
    read and labelled in two processes give the observations of one process, with progress."""
    import imageio.v3 as iio

    grid, _, photos = marked_grid_rig()
    taken = [photo for photo in photos[0] if photo is not None][:6]
    iio.imwrite(tmp_path / "p0.png", taken[0])
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    camera = [tmp_path / "p0.png", *taken[1:], tmp_path / "broken.png"]
    alone = mc.observe_grid([camera], grid)
    environment = dict(os.environ)
    shared = mc.observe_grid([camera], grid, workers=2, progress=True)
    assert dict(os.environ) == environment  # (the workers' one BLAS thread is theirs only)
    np.testing.assert_array_equal(shared.pixels, alone.pixels)
    assert shared.mask.any(-1).tolist() == [[True] * 6 + [False]]
    err = capsys.readouterr().err
    assert "cam0, frame 6: " in err and "cannot be read" in err
    assert "observe_grid: 7 of 7 photos, 6 labelled" in err
    with pytest.raises(ValueError, match="at least 1"):
        mc.observe_grid([camera], grid, workers=0)


def _dies_in_a_worker(x):
    """`2 x` here; a worker process that calls it dies."""
    import multiprocessing

    if multiprocessing.parent_process() is not None:
        os._exit(3)
    return 2 * x


def test_photos_whose_workers_die_are_read_here(capsys):
    """Workers that die (a script without the main guard, a sandbox, memory) lose no photo: the
    ones not done are done in this process, with a line on stderr saying why."""
    from mvcalib import _photos

    assert list(_photos._in_workers(_dies_in_a_worker, [1, 2, 3], 2)) == [2, 4, 6]
    assert "worker processes stopped after 0 of 3 photos" in capsys.readouterr().err


def test_cli_observes_a_marked_grid_and_calibrates_the_rig(tmp_path):
    """`mvcalib observe-grid` then `mvcalib calibrate-rig`, on the photos as PNG files."""
    import imageio.v3 as iio

    grid, rig, photos = marked_grid_rig()
    cameras = []
    for c, camera in enumerate(photos):
        cameras.append(["--camera"])
        for f, photo in enumerate(camera):
            path = tmp_path / f"cam{c}_{f:02d}.png"
            if photo is not None:
                iio.imwrite(path, photo)
            cameras[-1].append(path if photo is not None else "-")
    observations = tmp_path / "observations.csv"
    flags = ["--grid", 7, 9, 0.05, "--markers", 0, 1, 2, 9, "--out", observations]
    out = run_cli("observe-grid", *flags, *[a for camera in cameras for a in camera])
    assert out.returncode == 0, out.stderr
    assert "cam1: " in out.stdout and "photos labelled" in out.stdout
    out = run_cli("calibrate-rig", observations, "--out", tmp_path / "rig.json", "--quiet")
    assert out.returncode == 0, out.stdout + out.stderr
    rig_cameras, names = mc.io.load_json(tmp_path / "rig.json")
    assert names == ["cam0", "cam1", "cam2", "cam3"]
    assert centre_errors(rig, rig_cameras).max() < 1e-3
    out = run_cli("observe-grid", *flags, "--camera", cameras[0][1], "--camera", "-", "-")
    assert out.returncode == 2 and "as many photos" in out.stderr, out.stderr
    # one camera's photos alone calibrate that camera, as OpenCV's calibrateCamera does
    alone = [path for path in cameras[0][1:] if path != "-"]
    one = [*flags[:-1], tmp_path / "one.csv"]
    assert run_cli("observe-grid", *one, "--camera", *alone).returncode == 0
    out = run_cli("calibrate-rig", tmp_path / "one.csv", "--out", tmp_path / "one.json", "--quiet")
    assert out.returncode == 0, out.stdout + out.stderr
    camera, _ = mc.io.load_json(tmp_path / "one.json")
    focal = np.asarray(camera.alpha_u) / np.asarray(rig.cameras.alpha_u[0]) - 1
    assert len(alone) >= 6 and np.abs(focal).max() < 1e-3, (len(alone), focal)


def test_observe_grid_and_its_cli_take_an_asymmetric_grid(tmp_path):
    """Two cameras half a turn apart about their axes see an asymmetric circles grid: the same
    ids from both, through `observe_grid` (which reads the layout from the grid) and through
    `mvcalib observe-grid --asymmetric`."""
    import imageio.v3 as iio

    grid = mc.targets.dot_grid(11, 4, 40.0, asymmetric=True)
    cameras = [rolled_view(seed, 30.0, grid) for seed in (3, 4)]
    photos = [[mc.synthetic.render(c, grid, (1280, 960), key=0)] for c in cameras]
    truth = np.stack([np.asarray(c.project(grid.points)) for c in cameras])[:, None]
    obs = mc.observe_grid(photos, grid)
    assert obs.mask.all() and np.abs(obs.pixels - truth).max() < 0.5
    paths = [tmp_path / f"cam{c}.png" for c in range(2)]
    for path, camera in zip(paths, photos):
        iio.imwrite(path, camera[0])
    out_csv = tmp_path / "observations.csv"
    flags = ["--grid", 11, 4, 40.0, "--asymmetric", "--out", out_csv]
    out = run_cli("observe-grid", *flags, "--camera", paths[0], "--camera", paths[1])
    assert out.returncode == 0, out.stderr
    np.testing.assert_allclose(mc.io.load_observations(out_csv).pixels, obs.pixels, atol=1e-6)


def test_a_grid_of_another_size_is_named():
    """A whole 9 x 12 grid labelled as 8 x 12: the lattice found fits nowhere, and the message
    asks about the size rather than blaming blobs beside the grid (a photographer's trial)."""
    image = mc.synthetic.render(grid_view(0, 20.0), GRID, (1280, 960), key=0)
    labels = mc.label_grid(mc.detect_dots(image), 8, 12)
    assert not labels.ok and "is the grid 9 x 12 (rows, cols)?" in labels.message, labels.message


def test_a_grid_with_a_missing_border_row_is_flagged():
    camera = grid_view(0, 20.0)
    image = mc.synthetic.render(camera, GRID, (1280, 960), hidden=range(0, 12), key=0)
    labels = mc.label_grid(mc.detect_dots(image), 9, 12)
    assert not labels.ok and "8 x 12" in labels.message or "12 x 8" in labels.message


def test_a_marked_grid_half_out_of_the_image_is_placed_by_its_markers():
    """A board whose far columns leave the image has lost border columns: its lattice fits
    several places on the grid, and the view was flagged even with the four markers in view
    (a trial's photos: 16 of 46 flagged, 11 of them so). Its markers now place it: views at any
    roll and up to 45 degrees of tilt with 3-6 of the 12 columns gone, every one right or
    flagged; without markers every one is flagged."""
    markers = (0, 1, 2, 12)
    grid = mc.targets.dot_grid(9, 12, 20.0, markers=markers)
    counts = {"right": 0, "flagged": 0, "wrong": 0}
    plain_ok = 0
    for seed, tilt in enumerate(np.linspace(0.0, 45.0, 8)):
        camera = rolled_view(seed, tilt)
        gone = 3 + seed % 4  # the last columns, as if out of the image
        hidden = [r * 12 + c for r in range(9) for c in range(12 - gone, 12)]
        image = mc.synthetic.render(camera, grid, (1280, 960), hidden=hidden, key=seed)
        detection = mc.detect_dots(image)
        truth = np.asarray(camera.project(grid.points))
        labels = mc.label_grid(detection, 9, 12, markers=markers)
        if labels.ok:
            right = np.abs(labels.pixels[labels.mask] - truth[labels.mask]).max() < 1.5
            counts["right" if right else "wrong"] += 1
            assert not labels.mask[hidden].any()
        else:
            counts["flagged"] += 1
        plain_ok += mc.label_grid(detection, 9, 12).ok
    print(counts)
    assert counts["wrong"] == 0 and counts["right"] >= 6, counts
    assert plain_ok == 0


def oblique_plate_view(levels, dist, key, n=12, hidden=(), distance=420.0):
    """An `n x n` plate of two levels seen 25 degrees to the side and 20 up, 420 mm away, by a
    2500 px lens with distortion `dist` (dots 2-3 px wide in a 1280 x 1024 photo): the
    camera, the target, the photo, the dots' true pixels and clicks on level 0's corners."""
    plate = mc.targets.plate(n, n, 10.0, levels=levels, dot_radius=0.22)
    centre = plate.points.mean(0)
    a, e = np.radians(25.0), np.radians(20.0)
    eye = centre + distance * np.array([np.sin(a) * np.cos(e), np.sin(e), np.cos(a) * np.cos(e)])
    z = (centre - eye) / np.linalg.norm(centre - eye)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    camera = mc.Camera(2500.0, 2500.0, 640.0, 512.0, R, -R @ eye, dist=dist)
    photo = mc.synthetic.render(
        camera, plate, (1280, 1024), noise_sigma=3.0, hidden=hidden, key=key
    )
    photo = np.array(photo)
    truth = np.asarray(camera.project(plate.points))
    corners = np.array([0, n - 1, n * n - n, n * n - 1])
    return camera, plate, photo, truth, (truth[corners] + 1.0, plate.ids[corners])


def test_dots_whose_images_merge_are_left_out_not_labelled_wrongly():
    """A two-level plate seen 30 degrees off its normal: dots of the two levels line up and
    their images merge into one blob (a user's trial: matched as one of the two dots, 0.4-2 px
    off it, the camera's principal point 17-19 px off and its centre 2.6-2.8 mm, status OK; the
    second look gave the other dot the same blob). Such dots are left out and said so; every
    dot labelled is where it should be, once."""
    _, plate, photo, truth, clicks = oblique_plate_view((0.0, -10.0), [-0.12, 0.08, 0, 0, 0], 2)
    detection = mc.detect_dots(photo)
    labels = mc.match_dots(detection, plate, clicks, focal=2400.0)
    assert labels.ok, labels.message
    crowd = np.sort(np.linalg.norm(truth[:, None] - truth[None], axis=-1), axis=1)[:, 1]
    diameter = float(np.median(detection.major))
    assert np.sum(crowd < diameter) > 20  # (the view has merged dots to leave out)
    calibrated = mc.calibrate(plate.points, labels.pixels, labels.mask, refine=True).cameras
    looked = mc.second_look(photo, labels, plate, calibrated, detection=detection)
    for found in (labels, looked):
        pixels = found.pixels[found.mask]
        assert np.abs(pixels - truth[found.mask]).max() < 0.25
        apart = np.sort(np.linalg.norm(pixels[:, None] - pixels[None], axis=-1), axis=1)[:, 1]
        assert apart.min() > diameter  # no blob labelled twice
        assert found.mask[crowd >= diameter + 3.0].all()  # (measured: 200 labelled, 33 left out)
    assert "33 dots left out" in labels.message, labels.message


def test_a_wide_angle_lens_is_labelled_through_its_distortion():
    """k1 = -0.4: a pinhole fits the rightly matched dots to more than 5 % of their spacing (a
    user's trial: every view NOT_LABELLED at 1.42 px against 1.26); with radial distortion they
    fit, and are labelled."""
    camera, plate, photo, truth, clicks = oblique_plate_view(
        (0.0, -4.0), [-0.4, 0.2, 0, 0, 0], 3, n=15
    )
    labels = mc.match_dots(mc.detect_dots(photo), plate, clicks, focal=2400.0)
    assert labels.ok and "with radial distortion (k1, k2)" in labels.message, labels.message
    assert verdict(labels, truth) == "right" and labels.mask.sum() > 0.9 * len(plate.points)


def test_six_clicks_that_do_not_determine_a_camera_say_so_and_take_the_focal_guess():
    """Three clicks on a row and a fourth on the same level, two on the other: six, not
    coplanar, but their DLT is degenerate (a user's trial: "check their dot ids and
    positions", also with `focal`)."""
    _, plate, photo, truth, _ = oblique_plate_view((0.0, -4.0), [-0.12, 0.08, 0, 0, 0], 4)
    ids = np.array([0, 5, 11, 132, 144, 155])  # row 0 of level 0 (3), its last row, level -4 (2)
    clicks = (truth[plate.index(ids)], ids)
    detection = mc.detect_dots(photo)
    alone = mc.match_dots(detection, plate, clicks)
    assert not alone.ok and "do not determine a camera alone" in alone.message
    guided = mc.match_dots(detection, plate, clicks, focal=2400.0)
    assert guided.ok and verdict(guided, truth) == "right", guided.message


def test_a_lens_the_dots_leave_unknown_at_the_photos_corners_is_noted():
    """Dots in the middle fifth of the photo fit any distortion beyond them (a user's trial:
    every camera OK at 0.03 px, k2 = -35 against a true 0.08): the refinement's standard error
    of the distortion at the photo's corners says so, in `print(result)`."""
    patch = [k * 144 + 12 * r + c for k in (0, 1) for r in range(4, 8) for c in range(4, 8)]
    hidden = np.setdiff1d(np.arange(288), patch)
    dist = [-0.12, 0.08, 0, 0, 0]
    _, plate, photo, truth, _ = oblique_plate_view((0.0, -4.0), dist, 5, hidden=hidden)
    ids = np.array([52, 55, 144 + 88, 144 + 91])  # the patch's corners, one level each side
    seeds = [(truth[plate.index(ids)], ids)]
    options = dict(focal=2400.0, refine=True, progress=False)
    small = mc.calibrate_images([photo], plate, seeds=seeds, **options)
    assert small.ok.all() and small.mask.sum() == len(patch)
    assert "corners unknown, to a standard error of" in str(small), str(small)
    _, plate, photo, truth, clicks = oblique_plate_view((0.0, -4.0), dist, 5)
    full = mc.calibrate_images([photo], plate, seeds=[clicks], **options)
    assert full.ok.all() and "corners unknown" not in str(full), str(full)


def test_a_plate_larger_than_the_photo_rests_on_the_clicks_and_says_so():
    """A plate whose edges lie outside the photo looks the same with every id one column over
    (a user's trial: clicks one column off gave 268 of 268 labels wrong, OK, 0.02 px RMS; right
    clicks were refused as "a row or column off"). Such a view is flagged, right or wrong,
    unless the user vouches for the clicks."""
    _, plate, photo, truth, _ = oblique_plate_view((0.0, -4.0), [-0.12, 0.08, 0, 0, 0], 6,
                                                   n=15, distance=230.0)  # fmt: skip
    inside = np.all((truth >= 0) & (truth < (1280, 1024)), axis=1)
    assert 0.4 < inside.mean() < 0.8  # (the plate's edges out of view)
    ids = np.array([80, 84, 225 + 140, 225 + 144])  # inner dots of both levels
    detection = mc.detect_dots(photo)
    for shift in (0, 1):
        clicks = (truth[plate.index(ids)] + 0.7, ids + shift)
        flagged = mc.match_dots(detection, plate, clicks, focal=2400.0)
        assert not flagged.ok and "runs out of the photo" in flagged.message, flagged.message
    trusted = mc.match_dots(detection, plate, (truth[plate.index(ids)], ids), focal=2400.0,
                            trust_seed=True)  # fmt: skip
    assert trusted.ok and verdict(trusted, truth) == "right", trusted.message
    assert "rest on the seed (trusted)" in trusted.message
    assert trusted.mask.sum() > 0.9 * inside.sum()
