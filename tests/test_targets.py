"""Targets from files and generators, their ids, and OpenPTV's clicked seeds."""

import numpy as np
import pytest

import mvcalib as mc


def test_a_whitespace_file_keeps_its_ids(tmp_path):
    path = tmp_path / "target.txt"
    path.write_text("7 -40 -25 8\n3 -40 0 -8\n\n11 30 25.5 8\n")
    target = mc.targets.from_file(path)
    assert target.ids.tolist() == [7, 3, 11] and target.name == "target"
    np.testing.assert_array_equal(target.points, [[-40, -25, 8], [-40, 0, -8], [30, 25.5, 8]])
    assert target.index([11, 7]).tolist() == [2, 0]
    with pytest.raises(ValueError, match="has the id 5"):
        target.index([3, 5])


def test_a_csv_file_with_a_header_in_any_order(tmp_path):
    path = tmp_path / "dots.csv"
    path.write_text("z,name_unused,x,id,y\n1.5,0,10,4,20\n0,0,-1,9,2\n")
    target = mc.targets.from_file(path)
    assert target.ids.tolist() == [4, 9]
    np.testing.assert_array_equal(target.points, [[10, 20, 1.5], [-1, 2, 0]])
    headerless = tmp_path / "plain.csv"
    headerless.write_text("4,10,20,1.5\n9,-1,2,0\n")
    np.testing.assert_array_equal(mc.targets.from_file(headerless).points, target.points)


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "is empty"),
        ("id,x,y\n1,2,3\n", "header naming id, x, y, z .no 'z'"),
        ("1.5 0 0 0\n2 1 1 1\n", "must be integers"),
        ("1 0 0 0\n2 5 5 5\n1 1 1 1\n", r"dots \[0, 2\] .* share the id 1\."),
        ("1 0 0 nan\n", "not a finite number"),
        ("1 0 0\n", "expected lines of `id x y z`"),
        ("1 0 0 zero\n", "line 1 is neither numbers nor a header"),
        ("1 0 0 0\n2 0 0 zero\n", "cannot read target file"),
    ],
)
def test_bad_target_files_are_refused_with_the_reason(tmp_path, text, message):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        mc.targets.from_file(path)


def test_an_image_given_as_the_target_file_is_named(tmp_path):
    """It said only "'utf-8' codec can't decode byte 0x89 in position 0"."""
    path = tmp_path / "photo.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff")
    with pytest.raises(ValueError, match="photo.png is not a target file"):
        mc.targets.from_file(path)


def test_a_clicks_file_serves_any_of_its_photos(tmp_path):
    """One file of clicks for four cameras, two of them calibrated again: rows naming the others
    are passed over (it was an error); a file naming none of the photos is still one."""
    path = tmp_path / "clicks.csv"
    path.write_text("image,dot_id,pixel_x,pixel_y\ncam1.tif,3,10,20\ncam2.tif,4,11,21\n"
                    "cam3.tif,5,12,22\n")  # fmt: skip
    target = mc.targets.box_corner()
    seeds = mc.io.load_clicks(path, ["cal/cam3.tif", "cal/cam1.tif"], target)
    assert seeds[0][1].tolist() == [5] and seeds[1][1].tolist() == [3]
    with pytest.raises(ValueError, match="line 2: no image 'cam1.tif' among the images given"):
        mc.io.load_clicks(path, ["cam9.tif"], target)
    with pytest.raises(ValueError, match="no image '5' among the images given"):
        path.write_text("image,dot_id,pixel_x,pixel_y\n5,3,10,20\n")
        mc.io.load_clicks(path, ["cam9.tif"], target)


def test_every_target_has_ids_by_default():
    assert mc.targets.box_corner().ids.tolist() == list(range(19))
    with pytest.raises(ValueError, match="one per dot"):
        mc.targets.Target("t", np.zeros((3, 3)), 1.0, np.arange(3), np.eye(4), ids=[1, 2])


def test_dot_grids_and_plates():
    grid = mc.targets.dot_grid(4, 3, 10.0)
    assert grid.points.shape == (12, 3) and np.all(grid.points[:, 2] == 0)
    assert grid.radii[0] == 2.0 and grid.points[-1].tolist() == [20.0, 30.0, 0.0]
    asym = mc.targets.dot_grid(4, 3, 10.0, asymmetric=True)  # OpenCV's asymmetric circles grid
    assert asym.points[3].tolist() == [5.0, 5.0, 0.0] and asym.points[6].tolist() == [0, 10, 0]
    plate = mc.targets.plate(3, 4, 6.0, levels=(0.0, -1.0, -2.0))
    levels = plate.points.reshape(3, 12, 3)
    assert [set(level[:, 2]) for level in levels] == [{0.0}, {-1.0}, {-2.0}]
    np.testing.assert_allclose(levels[1, :, :2] - levels[0, :, :2], 2.0)  # 6 / 3 levels
    # every level faces +z: the dots off z = 0 failed `dot_normals`, and with them `render`
    # and `calibrate_images`' perspective-bias step (a user's trial, 2026-12-06)
    np.testing.assert_array_equal(mc.synthetic.dot_normals(plate), np.tile([0, 0, 1.0], (36, 1)))
    camera = mc.Camera(900.0, 900.0, 320.0, 240.0, np.diag([1.0, -1.0, -1.0]), [-9.0, 6.0, 120.0])
    assert mc.synthetic.render(camera, plate, (640, 480)).min() < 100  # (dots drawn)
    with pytest.raises(ValueError, match="rows, cols >= 2"):
        mc.targets.dot_grid(1, 5, 1.0)


def test_a_grid_s_markers_are_larger_dots_that_break_its_symmetry():
    grid = mc.targets.dot_grid(4, 5, 10.0, markers=(0, 1, 2, 5), marker_scale=1.5)
    assert grid.fiducials.tolist() == [0, 1, 2, 5]
    assert grid.radii[[0, 1, 2, 5]].tolist() == [3.0] * 4 and set(grid.radii[3:5]) == {2.0}
    # an L with equal arms looks the same from the board's back: a mirroring about a diagonal
    with pytest.raises(ValueError, match="look the same after a turn or a mirroring"):
        mc.targets.dot_grid(5, 5, 10.0, markers=(0, 1, 5))
    with pytest.raises(ValueError, match="look the same after a turn or a mirroring"):
        mc.targets.dot_grid(4, 5, 10.0, markers=(0, 19))  # opposite corners: the half turn
    with pytest.raises(ValueError, match="dot ids, 0 to 19"):
        mc.targets.dot_grid(4, 5, 10.0, markers=(20,))


def test_a_grid_s_symmetries_and_layout_are_found_from_its_dots():
    """The moves of a grid onto itself, found by one search (`targets._placements`) for any
    layout: a rectangle's half turn and two mirrorings, a square's eight, and OpenCV's
    asymmetric circles grid's one: its mirroring across the rows when they are odd in number
    (no turn: its ids need no markers), its half turn when they are even."""
    from mvcalib.targets import _grid_lattice, _layout, _placements

    def moves(rows, cols, asymmetric=False):
        ids, det, _ = _placements(*[_grid_lattice(rows, cols, asymmetric)] * 2)
        return {tuple(move) for move in ids}, sorted(det.tolist())

    rectangle, det = moves(3, 4)
    assert det == [-1, -1, 1, 1] and tuple(range(12))[::-1] in rectangle  # (the half turn)
    assert len(moves(4, 4)[0]) == 8
    odd, det = moves(5, 3, asymmetric=True)
    assert det == [-1, 1] and tuple(np.arange(15).reshape(5, 3)[::-1].ravel()) in odd
    even, det = moves(4, 3, asymmetric=True)
    assert det == [1, 1] and tuple(range(12))[::-1] in even
    with pytest.raises(ValueError, match="look the same after a turn or a mirroring"):
        mc.targets.dot_grid(4, 3, 10.0, asymmetric=True, markers=(0, 11))
    # a grid with a border row lost fits one row over too; a stray dot beside it only slack
    keys = _grid_lattice(5, 3, asymmetric=True)
    assert len(_placements(keys[3:], keys[:, :])[0]) == 4
    ids, _, off = _placements(np.r_[keys, [[-1, -1]]], keys, slack=1)
    assert off.min() == 1 and np.sum(off == 1) == 2 and set(ids[off == 1][:, -1]) == {-1}
    for rows, cols, asymmetric in [(3, 4, False), (5, 3, True), (4, 4, True)]:
        grid = mc.targets.dot_grid(rows, cols, 0.05, asymmetric=asymmetric, units="m")
        assert _layout(grid) == (rows, cols, asymmetric)
    with pytest.raises(ValueError, match="not a grid of dots"):
        _layout(mc.targets.plate(3, 4, 6.0))


def test_openptv_clicks_are_read_and_bad_ones_refused(tmp_path):
    par, dat = tmp_path / "man_ori.par", tmp_path / "man_ori.dat"
    par.write_text("2\n3\n71\n73\n1\n3\n69\n73\n")
    dat.write_text("".join(f"{x} {x + 1}\n" for x in range(8)))
    ids, pixels = mc.io.load_openptv_clicks(par, dat)
    assert ids.tolist() == [[2, 3, 71, 73], [1, 3, 69, 73]] and pixels.shape == (2, 4, 2)
    assert pixels[1, 0].tolist() == [3.5, 4.5]  # OpenPTV's pixel corner to mvcalib's centre
    dat.write_text("1 2\n3 4\n")
    with pytest.raises(ValueError, match="expected 8 lines"):
        mc.io.load_openptv_clicks(par, dat)
    par.write_text("2\n3\n71\n")
    dat.write_text("1 2\n3 4\n5 6\n")
    with pytest.raises(ValueError, match="not 4 per camera"):
        mc.io.load_openptv_clicks(par, dat)


def test_openptv_clicks_seed_the_images_in_order(tmp_path):
    """`load_clicks` of OpenPTV's `man_ori.par` (the CLI's `--clicks`): a seed per camera."""
    target = mc.targets.Target(
        "t", np.zeros((4, 3)), 1.0, np.arange(4), np.eye(4), ids=[2, 3, 71, 73]
    )
    par, dat = tmp_path / "man_ori.par", tmp_path / "man_ori.dat"
    par.write_text("2\n3\n71\n73\n73\n71\n3\n2\n")
    dat.write_text("".join(f"{x} {x + 1}\n" for x in range(8)))
    seeds = mc.io.load_clicks(par, ["a.tif", "b.tif"], target)
    assert [seed[1].tolist() for seed in seeds] == [[2, 3, 71, 73], [73, 71, 3, 2]]
    assert seeds[1][0][0].tolist() == [3.5, 4.5]
    with pytest.raises(ValueError, match="clicks for 2 cameras, and 3 images given"):
        mc.io.load_clicks(par, ["a.tif", "b.tif", "c.tif"], target)
    par.write_text("2\n3\n71\n73\n73\n71\n4\n2\n")
    with pytest.raises(ValueError, match="man_ori.par, line 7: the target has no dot 4"):
        mc.io.load_clicks(par, ["a.tif", "b.tif"], target)
    dat.unlink()
    with pytest.raises(ValueError, match="man_ori.dat, are not beside it"):
        mc.io.load_clicks(par, ["a.tif", "b.tif"], target)
