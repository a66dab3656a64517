"""Command line: `mvcalib COMMAND ...` (also `python -m mvcalib COMMAND ...`).

Commands: `calibrate` (correspondences file -> rig), `calibrate-rig` (a target moved in front
of a rig over frames -> rig), `detect` (photographs -> dots, labelled), `report` (Table I, a
summary and a figure of a rig on a correspondences file), `triangulate` (rig + 2-D tracks ->
3-D points), `calibrate-images` (photographs -> rig in one go) and `demo` (the paper's
experiment). `mvcalib COMMAND --help` shows each one's options and examples.

Exit codes: 0 success; 1 the work failed (a camera could not be calibrated, a photograph not
labelled, no point triangulated, an output not written); 2 bad usage or bad input (an unknown
flag, a missing or malformed file). Errors are one line on stderr, never a traceback. Progress
goes to stderr (`--quiet` silences it), results to stdout; every output file is written to a
temporary file and renamed, so none is ever left half-written.

The CLI keeps JAX's persistent compilation cache in `$XDG_CACHE_HOME/mvcalib/jax` (default
`~/.cache/mvcalib/jax`), so that only the first run pays for compiling; set
`MVCALIB_COMPILATION_CACHE=0` to turn it off, or to a directory to put it elsewhere.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import sys
import tempfile
import warnings

EXAMPLES = {
    "calibrate": """\
  mvcalib calibrate points.csv --out rig.json
                                  a camera for each camera named in the file (DLT, Table I)
  mvcalib calibrate points.csv --refine --format opencv --out rig.yml
                                  refined with distortion k1 k2 p1 p2, as OpenCV YAML
  mvcalib calibrate points.csv --distortion none --format colmap --image-size 1000 1100 \\
      --out sparse/               refined pinhole cameras as a COLMAP text model""",
    "calibrate-rig": """\
  mvcalib calibrate-rig observations.csv --out rig.json
                                  every camera's intrinsics, distortion and pose (camera 0's
                                  frame is the world's) and the target's pose in each frame
  mvcalib calibrate-rig xy.csv --intrinsics camera_array.toml --fix intrinsics,distortion \\
      --reference target --out rig.json
                                  caliscope's detections with its intrinsics held; the board
                                  in the frame most cameras saw is the world's floor
  mvcalib calibrate-rig observations.csv --huber 2 --plot rig.png --out rig.json
                                  robust to wrong detections, with a figure of the residuals
  mvcalib calibrate-rig observations.csv --fisheye --image-size 1280 960 --out rig.json
                                  fisheye cameras, nothing known but the photos' size
  mvcalib calibrate-rig new.csv --intrinsics rig.json --fix intrinsics,distortion,pose \\
      --out check.json            a rig checked against another recording: only the target's
                                  poses are fitted; the table gives each camera's RMS
  mvcalib calibrate-rig observations.csv --reference target --origin-frame 120 --out rig.yml
                                  the board in frame 120 (the file's id) is the world's; OpenCV
                                  YAML (JSON keeps the statuses and standard errors too)""",
    "detect": """\
  mvcalib detect cam*.png --out dots.csv
                                  the dots of the box-corner target in each photo, labelled
  mvcalib detect photo.tif --no-label --bright-dots --out blobs.json
                                  bright blobs, unlabelled""",
    "report": """\
  mvcalib report rig.json points.csv
                                  Table I and a summary of the residuals
  mvcalib report rig.json points.csv --plot report.png
                                  ... and a figure: the rig in 3-D, residuals, histograms""",
    "triangulate": """\
  mvcalib triangulate rig.json tracks.csv --out points3d.csv
                                  a 3-D point per tracked point seen by two cameras or more""",
    "convert": """\
  mvcalib convert rig.json --out rig.yml --image-size 1280 1024
                                  a rig as OpenCV's YAML (cv2.FileStorage)
  mvcalib convert calibration.toml --format colmap --image-size 1280 1024 --out sparse/
                                  aniposelib's rig as a COLMAP text model
  mvcalib convert rig.json --out calibration.toml --image-size 1280 1024
                                  a rig for anipose (aniposelib's CameraGroup.load)""",
    "calibrate-images": """\
  mvcalib calibrate-images cam*.png --out rig.json
                                  one camera per photo of the box-corner target
  mvcalib calibrate-images cam1.tif cam2.tif --target dots.txt --clicks clicks.csv \\
      --focal 5800 --bright-dots --out rig.json
                                  any target (id x y z per line), labelled from clicked dots
  mvcalib calibrate-images cal/cam[1-4].tif --target cal/target_on_a_side.txt \\
      --clicks parameters/man_ori.par --focal 5800 --bright-dots --refine --out rig.json
                                  an OpenPTV set-up: its four clicked dots per camera
  mvcalib calibrate-images cam*.png --refine --out rig.yml --dots dots.csv
                                  as OpenCV YAML; then mvcalib report rig.yml dots.csv""",
    "observe-grid": """\
  mvcalib observe-grid --grid 7 9 0.05 --markers 0 1 2 9 --camera cam0/*.png \\
      --camera cam1/*.png --out observations.csv
                                  a marked dot grid's dots in every photo, labelled
  mvcalib calibrate-rig observations.csv --out rig.json
                                  ... and the rig from them""",
    "demo": """\
  mvcalib demo                    the paper's experiment with 0.3 px noise
  mvcalib demo --noise-free       no noise: the four snapshots agree to 1e-6 px
  mvcalib demo --float32          a scene drawn and solved in single precision: the same
                                  intrinsics as the default's, other random poses
  mvcalib demo --images           the whole pipeline from rendered photographs, and a figure
                                  of the detection stages (mvcalib_stages.png)
  mvcalib demo --save demo && mvcalib report demo/rig.json demo/correspondences.csv \\
      --plot rig.png              the demo's files, and their report with a figure""",
}

FILES = """\
files:
  correspondences  CSV with the header camera,point,world_x,world_y,world_z,pixel_x,pixel_y
                   (one row per observation), or JSON (mvcalib.io.save_correspondences);
                   pixels are (x = column, y = row), origin at the centre of the top-left pixel
  tracks           the same without the world_* columns
  observations     CSV with the header camera,frame,point,target_x,target_y,target_z,pixel_x,
                   pixel_y (mvcalib.io.save_observations: a target moved over frames), or
                   caliscope's xy.csv
  rig              JSON (mvcalib.io.save_json), OpenCV YAML (.yml, .yaml), a COLMAP text
                   model (a folder), caliscope's camera_array.toml or aniposelib's
                   calibration.toml; cameras are matched to the files' camera names

exit codes: 0 success, 1 the work failed, 2 bad usage or bad input"""

_DISTORTION = ("k1", "k2", "p1", "p2", "k3", "k4")  # a pinhole's and a fisheye's (k1..k4)
# `triangulate`'s --max-rms by default: `mvcalib.triangulate`'s (`_triangulate.MAX_RMS`)
FAR_PX = 10.0


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line and exit code 2, no usage dump or traceback
        self.exit(2, f"mvcalib: error: {message} (see `{self.prog} --help`)\n")


class _Failed(Exception):
    """The work failed (exit code 1); the message is printed as one line."""


def _distortion(text: str) -> tuple[str, ...]:
    names = () if text.strip().lower() == "none" else tuple(re.split(r"[,\s]+", text.strip()))
    unknown = [n for n in names if n not in _DISTORTION]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"{unknown[0]!r} is not one of {', '.join(_DISTORTION)} (or 'none')"
        )
    return names


def _names(text: str) -> tuple[str, ...]:
    return tuple(n for n in re.split(r"[,\s]+", text.strip()) if n)


def build_parser() -> argparse.ArgumentParser:
    everything = "\n".join(EXAMPLES.values())
    parser = _Parser(
        prog="mvcalib",
        description="Calibrate rigs of cameras (DLT + SVD, closed-form decomposition, "
        "registration into one global frame), detect and label the dots of the target in "
        "photographs, and triangulate what several cameras see.",
        epilog=f"examples:\n{everything}\n\n{FILES}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from . import __version__

    parser.add_argument("--version", action="version", version=f"mvcalib {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    parser.commands = {}  # each command's parser, whose errors point at its own help

    def command(name, help, description):
        parser.commands[name] = sub.add_parser(
            name,
            help=help,
            description=description,
            epilog=f"examples:\n{EXAMPLES[name]}\n\n{FILES}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
            parents=[common],
        )
        return parser.commands[name]

    size = dict(nargs=2, type=int, metavar=("WIDTH", "HEIGHT"))

    calibrate = command(
        "calibrate",
        "calibrate every camera of a correspondences file",
        "Calibrate one camera per camera named in a file of 3-D/2-D correspondences: "
        "normalised DLT, closed-form decomposition and Table I, optionally refined by "
        "Levenberg-Marquardt with lens distortion. Cameras that cannot be calibrated are "
        "named with the reason (exit code 1); the JSON rig records their status.",
    )
    calibrate.add_argument("correspondences", metavar="CORRESPONDENCES", help=".csv or .json")
    _rig_output(
        calibrate, "records failed cameras too", "--image-size and --refine or --distortion"
    )
    calibrate.add_argument(
        "--refine",
        action="store_true",
        help="refine by Levenberg-Marquardt with zero skew and distortion k1 k2 p1 p2",
    )
    calibrate.add_argument(
        "--distortion",
        type=_distortion,
        metavar="LIST",
        help="the distortion coefficients to refine, e.g. k1,k2 or none (implies --refine). "
        "Fit only those the lens needs: from a few points each one adds variance (19 dots of "
        "a lens without distortion: focal lengths 0.42 %% off with none, 0.73 %% with k1,k2,p1,p2, "
        "median of 200 cameras)",
    )
    calibrate.add_argument(
        "--image-size", **size, help="written to OpenCV's, COLMAP's and aniposelib's files"
    )

    rig = command(
        "calibrate-rig",
        "calibrate a rig from a target moved in front of it over frames",
        "Calibrate a rig of cameras from their views of a target (a board or a 3-D object) "
        "moved through its volume, whose pose in each frame is unknown: every camera's "
        "intrinsics, lens distortion and pose, and the target's pose in each frame, as one "
        "least-squares problem (a closed-form start, then Levenberg-Marquardt with the frames "
        "eliminated). Prints a table per camera (frames, points, RMS, the standard error of "
        "its centre, status) and writes the rig as JSON; cameras that cannot be calibrated are "
        "named with the reason (exit code 1) and recorded with their status.",
    )
    rig.add_argument(
        "observations",
        metavar="OBSERVATIONS",
        help="observations .csv (mvcalib.io.save_observations) or caliscope's xy.csv",
    )
    _rig_output(
        rig, "records failed cameras, the standard errors and the settings too", "--image-size"
    )
    rig.add_argument(
        "--intrinsics",
        metavar="RIG",
        help="starting cameras, one per camera of the observations (matched by name, else in "
        "order): a rig file (JSON, .yml, COLMAP folder, caliscope's or aniposelib's .toml)",
    )
    rig.add_argument(
        "--fix",
        type=_names,
        default=(),
        metavar="LIST",
        help="held at the --intrinsics values, e.g. intrinsics,distortion (groups: intrinsics, "
        "focal, principal_point, distortion, pose; or names: alpha_u, k1, ...); aspect_ratio "
        "holds alpha_u / alpha_v at the start's ratio, the focal length fitted",
    )
    rig.add_argument(
        "--distortion",
        type=_distortion,
        metavar="LIST",
        help="the distortion coefficients estimated (default k1,k2,p1,p2; of fisheye cameras "
        "from --intrinsics k1,k2,k3,k4; or none)",
    )
    rig.add_argument(
        "--fisheye",
        action="store_true",
        help="fisheye cameras (cv2.fisheye's model): with no --intrinsics, each camera starts "
        "from its own frames of a planar target; needs --image-size",
    )
    rig.add_argument(
        "--image-size",
        **size,
        help="the photos' size: the image borders of --plot (default: guessed from the principal "
        "points and pixels), and needed with --fisheye",
    )
    rig.add_argument(
        "--reference",
        default="0",
        metavar="CAMERA",
        help="the camera (index or name) whose frame is the world's (default 0), or 'target': "
        "the target in the frame most cameras saw (or --origin-frame's)",
    )
    rig.add_argument(
        "--origin-frame",
        type=int,
        metavar="FRAME",
        help="with --reference target: the frame (its id in the observations file) whose "
        "target pose is the world, e.g. the board lying on the floor (z along the board's "
        "normal, away from the cameras that see it: down, for a board on the floor)",
    )
    robust = rig.add_mutually_exclusive_group()
    robust.add_argument(
        "--huber",
        type=float,
        metavar="PX",
        help="Huber loss of this scale (pixels) for wrong detections, e.g. 2",
    )
    robust.add_argument(
        "--cauchy",
        type=float,
        metavar="PX",
        help="Cauchy loss of this scale (pixels): for more wrong detections than Huber's takes "
        "(5 %% moved tens of pixels), e.g. 2",
    )
    rig.add_argument(
        "--plot", metavar="PNG", help="a figure of the rig and its residuals (.png, .pdf, .svg)"
    )

    detect = command(
        "detect",
        "detect (and label) the target's dots in photographs",
        "Detect the dots in each photograph (the paper's morphological steps, sub-pixel "
        "centroids) and label them from the box-corner target's large fiducial dots. Writes a "
        "correspondences file (one camera per photograph, named by its path) that `mvcalib "
        "calibrate` reads; dots that could not be labelled are kept in it as unlabelled. "
        "Photos that cannot be read or labelled are named with the reason (exit code 1).",
    )
    detect.add_argument("images", nargs="+", metavar="IMG", help="photographs (PNG, TIFF, ...)")
    detect.add_argument("--out", required=True, metavar="FILE", help="dots file: .csv or .json")
    detect.add_argument("--bright-dots", action="store_true", help="bright dots on dark ground")
    detect.add_argument("--no-label", action="store_true", help="detect only; do not label")

    report = command(
        "report",
        "Table I, a summary and a figure of a rig on correspondences",
        "Reproject the correspondences' world points with a saved rig and compare with their "
        "pixels: Table I (mean signed error in x and y, RMS, max per camera), a summary over "
        "all cameras and, with --plot, a figure (the rig in 3-D with the points, each camera's "
        "residuals over its image, residual histograms).",
    )
    report.add_argument("rig", metavar="RIG", help="rig file (JSON, .yml, .toml) or COLMAP folder")
    report.add_argument("correspondences", metavar="CORRESPONDENCES", help=".csv or .json")
    report.add_argument("--plot", metavar="PNG", help="write the figure here (.png, .pdf, .svg)")
    report.add_argument("--image-size", **size, help="image size for the figure")

    convert = command(
        "convert",
        "a rig file in another format",
        "Read a rig (mvcalib's JSON, OpenCV's or Kalibr's YAML, a COLMAP text model, "
        "caliscope's or aniposelib's TOML, ROS camera_info files) and write it as JSON, OpenCV's "
        "YAML, a COLMAP model, aniposelib's TOML, Kalibr's camchain.yaml or ROS camera_info "
        "files. Cameras that are not calibrated (NaN, or a status other than OK in a JSON rig) "
        "are kept in JSON, with their status, RMS and notes, and left out of the others.",
    )
    convert.add_argument(
        "rig",
        nargs="+",
        metavar="RIG",
        help="rig file (JSON, .yml, .toml) or COLMAP folder; or ROS camera_info files, a stereo "
        "pair's two (left first) giving their poses",
    )
    _rig_output(convert, "every camera", "--image-size")
    convert.add_argument(
        "--image-size", **size, help="written to OpenCV's YAML; COLMAP and aniposelib need it"
    )

    triangulate = command(
        "triangulate",
        "3-D points from a rig and 2-D tracks",
        "Triangulate every tracked point seen by two cameras or more (N-view linear "
        "triangulation, optionally polished by Levenberg-Marquardt) and write a CSV: point, "
        "world_x, world_y, world_z, views, rms_px (reprojection RMS), angle_deg (the widest "
        "angle between its rays) and ok (in front of its cameras, rays at least --min-angle "
        "apart, reprojection RMS at most --max-rms). Points seen once are written with empty "
        "coordinates; a view a camera did not see is a row left out, or NaN or blank pixels. If "
        "the tracks file has world coordinates, the distance to them is reported.",
    )
    triangulate.add_argument(
        "rig", metavar="RIG", help="rig file (JSON, .yml, .toml) or COLMAP folder"
    )
    triangulate.add_argument("tracks", metavar="TRACKS", help=".csv or .json")
    triangulate.add_argument("--out", required=True, metavar="CSV", help="3-D points to write")
    triangulate.add_argument("--refine", action="store_true", help="minimise reprojection error")
    triangulate.add_argument(
        "--min-angle", type=float, default=1.0, metavar="DEG", help="for ok (default 1 degree)"
    )
    triangulate.add_argument(
        "--max-rms",
        type=float,
        default=FAR_PX,
        metavar="PX",
        help=f"for ok: the largest reprojection RMS (default {FAR_PX:g}; inf: any)",
    )

    images = command(
        "calibrate-images",
        "calibrate one camera per photograph of the dot target",
        "Detect the dots in each photograph (the paper's morphological steps), label them from "
        "the target's large fiducial dots, and calibrate one camera per image (DLT, "
        "closed-form decomposition, Table I). Images that cannot be labelled with certainty "
        "are flagged, never calibrated wrongly; the rig file records their status.",
    )
    images.add_argument("images", nargs="+", metavar="IMG", help="photographs (PNG, TIFF, ...)")
    _rig_output(images, "every photo's camera, its status, RMS and messages", "--refine")
    images.add_argument(
        "--dots",
        metavar="CSV",
        help="also write the labelled dots (camera = photo, point = dot id, target and pixel "
        "coordinates), for `mvcalib report RIG DOTS` and `mvcalib triangulate`",
    )
    images.add_argument(
        "--refine",
        action="store_true",
        help="refine each camera by Levenberg-Marquardt with radial/tangential distortion",
    )
    images.add_argument(
        "--distortion",
        type=_distortion,
        metavar="LIST",
        help="the distortion coefficients to refine, e.g. k1 or none (implies --refine; default "
        "k1,k2,p1,p2): fewer where the dots fill a small part of the photos",
    )
    images.add_argument(
        "--huber",
        type=float,
        metavar="PX",
        help="refine with a Huber loss of this scale (pixels; implies --refine): for dots whose "
        "centres something pulls (a particle or a speck touching them), e.g. 0.2",
    )
    images.add_argument("--bright-dots", action="store_true", help="bright dots on dark ground")
    images.add_argument(
        "--target",
        metavar="FILE",
        help="the target's dots, `id x y z` per line (or CSV with a header id,x,y,z); default "
        "mvcalib's box corner, labelled from its fiducials",
    )
    images.add_argument(
        "--dot-radius",
        type=float,
        metavar="R",
        help="the --target's dots' radius, in its units: the dots' perspective bias is removed "
        "only where it is known",
    )
    images.add_argument(
        "--clicks",
        metavar="FILE",
        help="clicked seeds, CSV with the header image,dot_id,pixel_x,pixel_y (image: the file's "
        "name as given, or its position from 0), or OpenPTV's man_ori.par (its man_ori.dat "
        "beside it; cameras in the order of the images); 6+ dots per image, or 4+ with --focal",
    )
    images.add_argument(
        "--focal", type=float, metavar="PX", help="focal-length guess in pixels, for the clicks"
    )
    images.add_argument(
        "--names",
        nargs="+",
        metavar="NAME",
        help="the cameras' names in the rig and --dots file, one a photo (default: the photos' "
        "paths as given), e.g. cam1 cam2 cam3 cam4, as the tracks to triangulate name them",
    )
    images.add_argument(
        "--trust-clicks",
        action="store_true",
        help="with --clicks on a grid or plate larger than the photos: take the clicks' dot ids "
        "as right (the photos cannot tell every id one step over; checked by you)",
    )
    images.add_argument("--workers", **_WORKERS)
    images.add_argument(
        "--no-second-look",
        action="store_true",
        help="with --clicks: keep the dots matched to detected blobs only, without looking again "
        "where the calibrated camera predicts the missed ones (mvcalib.second_look)",
    )

    grid = command(
        "observe-grid",
        "a rig's observations of a marked dot grid, from photos",
        "Detect and label a printed dot grid (`mvcalib.targets.dot_grid`) in every photo of "
        "every camera, the grid moved through the rig's volume, and write the observations "
        "for `mvcalib calibrate-rig`. A few dots printed larger (--markers), or OpenCV's "
        "asymmetric grid of odd rows (--asymmetric), give every dot the same id in every "
        "camera; photos that cannot be labelled with certainty are left out. With one --camera, "
        "calibrate-rig then calibrates that camera alone.",
    )
    grid.add_argument(
        "--grid", nargs=3, required=True, type=float, metavar=("ROWS", "COLS", "SPACING"),
        help="the grid's rows and columns of dots and their spacing (the rig's units)",
    )  # fmt: skip
    grid.add_argument(
        "--markers", nargs="+", type=int, default=(), metavar="ID",
        help="ids (row by row from 0) of the dots printed larger, e.g. 0 1 2 COLS",
    )  # fmt: skip
    grid.add_argument(
        "--marker-scale", type=float, default=1.6, help="markers' size over the others' (1.6)"
    )
    grid.add_argument(
        "--asymmetric", action="store_true",
        help="OpenCV's asymmetric circles grid: every other row shifted by half a spacing, rows "
        "half a spacing apart (with an odd number of rows its ids need no markers)",
    )  # fmt: skip
    grid.add_argument(
        "--camera", nargs="+", action="append", required=True, metavar="IMG",
        help="one camera's photos in frame order ('-' where it took none); once per camera",
    )  # fmt: skip
    grid.add_argument("--bright-dots", action="store_true", help="bright dots on dark ground")
    grid.add_argument("--workers", **_WORKERS)
    grid.add_argument("--out", required=True, metavar="CSV", help="observations file to write")

    demo = command(
        "demo",
        "run the paper's 4-snapshot experiment on a synthetic scene",
        "Run the paper's experiment on a synthetic scene: DLT per snapshot, Table I, "
        "registration into the global frame, and the fixed point's pixel from every snapshot.",
    )
    demo.add_argument("--noise", type=float, default=0.3, help="pixel noise sigma (default 0.3)")
    demo.add_argument(
        "--global-noise",
        type=float,
        default=0.0,
        help="noise sigma of the measured global coordinates, mm (default 0)",
    )
    demo.add_argument("--noise-free", action="store_true", help="set both noises to zero")
    demo.add_argument("--seed", type=int, default=2010, help="PRNG seed of the scene")
    demo.add_argument(
        "--float32",
        action="store_true",
        help="draw the scene and compute in single precision (the random poses differ from the "
        "default's: the same seed draws other numbers in float32)",
    )
    demo.add_argument(
        "--images",
        action="store_true",
        help="start from rendered photographs: detect, label, calibrate, register",
    )
    demo.add_argument(
        "--figure",
        default="mvcalib_stages.png",
        metavar="PNG",
        help="with --images: where to write the processing-stage figure "
        "(default mvcalib_stages.png; '' for none)",
    )
    demo.add_argument(
        "--save",
        metavar="DIR",
        help="also write the snapshots' cameras (DIR/rig.json) and their dots "
        "(DIR/correspondences.csv) for `mvcalib report`",
    )
    return parser


def _enable_compilation_cache() -> None:
    from ._cache import enable_compilation_cache

    setting = os.environ.get("MVCALIB_COMPILATION_CACHE", "")
    if setting != "0":
        enable_compilation_cache(setting or None)


def _check_usage(parser, args) -> None:
    """Everything that can be checked before any work: files to read exist, folders to write
    into exist, the flags go together. `parser.error` exits with code 2."""
    inputs = {
        "calibrate": ["correspondences"],
        "calibrate-rig": ["observations", "intrinsics"],
        "report": ["rig", "correspondences"],
        "triangulate": ["rig", "tracks"],
    }.get(args.command, [])
    for name in inputs:
        if getattr(args, name) is not None and not pathlib.Path(getattr(args, name)).exists():
            parser.error(f"no such file: {getattr(args, name)}")
    if args.command in ("detect", "calibrate-images"):
        missing = [p for p in args.images if not pathlib.Path(p).is_file()]
        if missing:
            parser.error(f"no such image file: {missing[0]}")
    if args.command == "observe-grid":
        photos = [p for camera in args.camera for p in camera if p != "-"]
        missing = [p for p in photos if not pathlib.Path(p).is_file()]
        if missing:
            parser.error(f"no such image file: {missing[0]}")
        if len({len(camera) for camera in args.camera}) > 1:
            parser.error(
                f"every --camera takes as many photos, one per frame ('-' where a camera took "
                f"none); got {[len(camera) for camera in args.camera]}"
            )
        rows, cols, spacing = args.grid
        if rows != int(rows) or cols != int(cols) or rows < 2 or cols < 2 or not spacing > 0:
            parser.error(f"--grid ROWS COLS SPACING: got {' '.join(map(str, args.grid))}")
    if getattr(args, "workers", None) is not None and args.workers < 1:
        parser.error(f"--workers must be at least 1; got {args.workers}")
    if args.command == "calibrate-images":
        for flag in ("target", "clicks"):
            if getattr(args, flag) and not pathlib.Path(getattr(args, flag)).is_file():
                parser.error(f"no such file: {getattr(args, flag)}")
        if args.clicks and not args.target:
            parser.error("--clicks name dots of a --target file")
        if args.dot_radius is not None and not (args.target and args.dot_radius > 0):
            parser.error("--dot-radius is the --target file's dots' radius, a positive number")
    if (
        args.command in ("report", "triangulate")
        and pathlib.Path(args.rig).suffix.lower() == ".csv"
    ):
        data = "CORRESPONDENCES" if args.command == "report" else "TRACKS"
        parser.error(
            f"{args.rig} is a CSV file, not a rig: are the arguments swapped? The rig comes "
            f"first: mvcalib {args.command} RIG {data}"
        )
    for flag in ("out", "plot", "save"):
        value = getattr(args, flag, None)
        folder = flag == "out" and getattr(args, "format", None) in _FOLDERS
        if value and not (folder and pathlib.Path(value).is_dir()):
            _check_writable(parser, flag, pathlib.Path(value))
    suffix = pathlib.Path(getattr(args, "out", "") or "").suffix.lower()
    if args.command == "detect" and suffix not in (".csv", ".json"):
        parser.error(f"--out must be a .csv or .json file; got {args.out}")
    if args.command in ("triangulate", "observe-grid") and suffix != ".csv":
        parser.error(f"--out must be a .csv file; got {args.out}")
    if args.command in ("calibrate", "calibrate-rig", "calibrate-images", "convert"):
        _check_format(parser, args, suffix)
        if args.format in _SIZED and getattr(args, "image_size", 0) is None:
            parser.error(f"--format {args.format} needs --image-size WIDTH HEIGHT")
    no_skew = {
        "colmap": "COLMAP's",
        "opencv": "OpenCV's",
        "aniposelib": "aniposelib's",
        "kalibr": "Kalibr's",
        "ros": "ROS's",
    }.get(getattr(args, "format", None))
    if not getattr(args, "metres_per_unit", 1.0) > 0:
        parser.error("--metres-per-unit must be positive (0.001 for a target in millimetres)")
    if getattr(args, "format", None) == "kalibr" and "k3" in (getattr(args, "distortion", 0) or ()):
        if not getattr(args, "fisheye", False):  # (refused before the work, not after it)
            parser.error("--format kalibr: Kalibr's radtan distortion has k1 k2 p1 p2, not k3")
    if args.command == "calibrate-images" and no_skew and not args.refine:
        parser.error(
            f"--format {args.format} needs --refine ({no_skew} cameras have no skew; the DLT's "
            "have)"
        )
    if args.command == "calibrate-images" and args.dots:
        if pathlib.Path(args.dots).suffix.lower() != ".csv":
            parser.error(f"--dots must be a .csv file; got {args.dots}")
    if args.command == "calibrate-rig" and args.origin_frame is not None:
        if args.reference != "target":
            parser.error("--origin-frame chooses the world frame with --reference target")
    if args.command == "calibrate" and no_skew:
        if not args.refine and args.distortion is None:
            parser.error(
                f"--format {args.format} needs --refine or --distortion ({no_skew} cameras have "
                "no skew; the DLT's have)"
            )
    if args.command == "demo" and (args.noise < 0 or args.global_noise < 0):
        parser.error("noise levels must be non-negative")
    if args.command == "triangulate" and not args.min_angle >= 0:
        parser.error("--min-angle must be non-negative")
    if args.command == "triangulate" and not args.max_rms > 0:
        parser.error("--max-rms must be positive")
    if args.command == "calibrate-images" and args.names is not None:
        if len(args.names) != len(args.images) or len(set(args.names)) != len(args.names):
            parser.error(
                f"--names takes one name a photo, each its own: {len(args.names)} names for "
                f"{len(args.images)} photos"
            )
    if args.command == "calibrate-images" and args.trust_clicks and not args.clicks:
        parser.error("--trust-clicks is about the ids of --clicks: give --clicks FILE")
    for loss in ("huber", "cauchy"):
        if args.command in ("calibrate-rig", "calibrate-images"):
            if getattr(args, loss, None) is not None and not getattr(args, loss) > 0:
                parser.error(f"--{loss} must be positive")
    if (
        args.command == "calibrate-rig"
        and args.fisheye
        and not (args.image_size or args.intrinsics)
    ):
        parser.error(
            "--fisheye needs --image-size WIDTH HEIGHT (the photos' size), or --intrinsics with "
            "fisheye cameras"
        )
    if args.command == "calibrate-images" and args.focal is not None and not args.focal > 0:
        parser.error("--focal must be positive (a focal-length guess in pixels)")


_FORMATS = {".json": "json", ".yml": "opencv", ".yaml": "opencv", ".toml": "aniposelib"}  # --out's
_SUFFIXES = {"kalibr": (".yaml", ".yml")}  # a format's files, where not `_FORMATS`'s
_SIZED = ("colmap", "aniposelib", "kalibr", "ros")  # the formats whose cameras need an image size
_FOLDERS = ("colmap", "ros")  # the formats written into the folder --out


def _rig_output(parser, json_holds: str, colmap_needs: str) -> None:
    """A rig's --out and --format (`calibrate`'s and `calibrate-rig`'s; `_check_format`)."""
    parser.add_argument("--out", required=True, metavar="PATH", help="rig file (or folder)")
    parser.add_argument(
        "--format",
        choices=("json", "opencv", "colmap", "aniposelib", "kalibr", "ros"),
        help=f"json ({json_holds}), opencv (FileStorage YAML), colmap (text model in the "
        f"folder --out; needs {colmap_needs}), aniposelib (calibration.toml; needs it too), "
        "kalibr (Kalibr's camchain.yaml; needs it too) or ros (ROS camera_info files, NAME.yaml "
        "a camera, in the folder --out: a rig of two as a rectified stereo pair, the left "
        "camera first; needs it too); default from --out: .json, .yml or .yaml (opencv), .toml",
    )
    parser.add_argument(
        "--metres-per-unit",
        type=float,
        default=1.0,
        metavar="M",
        help="--format kalibr or ros: metres per unit of the rig, their translations being "
        "metres (0.001 for a target in millimetres; default 1)",
    )


def _check_writable(parser, flag: str, path: pathlib.Path) -> None:
    """Refuse an output path that cannot be written, before any work: a missing or read-only
    folder, or a folder where a file should go (a file is written beside it, then renamed)."""
    folder = path.resolve().parent
    if not folder.is_dir():
        parser.error(f"the folder of --{flag} does not exist: {path.parent}")
    if path.is_dir():
        parser.error(f"--{flag} {path} is a folder; give a file name")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        parser.error(f"cannot write --{flag} {path}: {error.strerror or error}")


def _check_format(parser, args, suffix: str) -> None:
    """A rig's --format, from --out's suffix where not given; a file whose suffix says another
    format is a usage error (a JSON rig in `rig.txt` was written silently, and `calibrate-rig
    --out rig.yml` and `calibrate-images --out rig.yml` wrote JSON)."""
    if args.format is None:
        if suffix not in _FORMATS:
            parser.error(
                f"--out {args.out}: a .json, .yml/.yaml or .toml file, or a folder with "
                "--format colmap or ros"
            )
        args.format = _FORMATS[suffix]
    elif args.format not in _FOLDERS:
        own = [k for k, v in _FORMATS.items() if v == args.format]
        suffixes = _SUFFIXES.get(args.format, own)
        if suffix not in suffixes:
            wanted = " or ".join(suffixes)
            parser.error(f"--format {args.format} writes a {wanted} file; got --out {args.out}")


class _PipeSafe:
    """Standard output that, once its reader has gone (`mvcalib ... | head`), swallows the rest:
    the command goes on and writes its files (it stopped with "[Errno 32] Broken pipe", exit
    code 1, before writing them where the table came first)."""

    def __init__(self, stream):
        self._stream, self._gone = stream, False

    def write(self, text):
        if not self._gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._gone_now()
        return len(text)

    def flush(self):
        if not self._gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._gone_now()

    def _gone_now(self):
        self._gone = True
        try:  # (else the interpreter's last flush of the stream reports the broken pipe)
            devnull = os.open(os.devnull, os.O_WRONLY)
        except OSError:
            return
        try:
            os.dup2(devnull, self._stream.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        finally:
            os.close(devnull)  # (the stream's descriptor holds /dev/null now)

    def __getattr__(self, name):
        return getattr(self._stream, name)


class _stdout_closed_early_is_fine:  # noqa: N801 (a context manager, used as a statement)
    def __enter__(self):
        self._saved, sys.stdout = sys.stdout, _PipeSafe(sys.stdout)

    def __exit__(self, *exc):
        sys.stdout.flush()
        sys.stdout = self._saved


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if unknown:  # (the command's own error, which points at its help)
        parser.commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    _check_usage(parser.commands[args.command], args)
    try:
        import jax

        jax.config.update("jax_enable_x64", True)
        _enable_compilation_cache()
        with _stdout_closed_early_is_fine():
            return COMMANDS[args.command](args)
    except KeyboardInterrupt:
        print("mvcalib: interrupted", file=sys.stderr)
        return 130
    except _Failed as error:
        print(f"mvcalib: {_one_line(error)}", file=sys.stderr)
        return 1
    except ValueError as error:  # bad input: a malformed file, too few points, ...
        print(f"mvcalib: error: {_one_line(error)}", file=sys.stderr)
        return 2
    except OSError as error:  # an output could not be written (inputs raise ValueError)
        print(f"mvcalib: {_one_line(error)}", file=sys.stderr)
        return 1


def _one_line(error: BaseException) -> str:
    return "; ".join(line.strip() for line in str(error).splitlines() if line.strip())


def _progress(args):
    def say(message: str) -> None:
        if not args.quiet:
            print(message, file=sys.stderr, flush=True)

    return say


# ---------------------------------------------------------------------------- shared helpers
_RIGS = (
    "a rig is mvcalib's JSON, OpenCV YAML (.yml, .yaml), Kalibr's camchain.yaml, a COLMAP text "
    "model (a folder), or caliscope's camera_array.toml or aniposelib's calibration.toml"
)


def _load_rig(path, *, record: bool = False):
    """`(cameras (C,), names)` from a JSON rig, an OpenCV or Kalibr YAML file, a COLMAP folder,
    or caliscope's or aniposelib's TOML; `ValueError` saying which formats are read otherwise.
    With `record`, `(cameras, names, record)`: a JSON rig's stored status, RMS and meta
    (`io.load_json(..., record=True)`), None for the other formats."""
    import jax

    from . import io

    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    stored = []  # (a JSON rig's record, read with it)
    if path.is_dir():
        cameras, names = io.load_colmap(path)
    elif suffix in (".yml", ".yaml"):
        load = {"ros": io.load_ros, "kalibr": io.load_kalibr}.get(_yaml_kind(path), io.load_opencv)
        cameras, names = load(path)
    elif suffix == ".toml":
        cameras, names = _load_toml_rig(path)
    elif suffix == ".csv":
        raise ValueError(f"{path}: a CSV file is not a rig; {_RIGS}.")
    else:
        try:
            cameras, names, *stored = io.load_json(path, record=record)
        except ValueError as error:  # (any name but .json: say what else a rig may be)
            if suffix == ".json":
                raise
            raise ValueError(f"{_one_line(error).rstrip('.')}; {_RIGS}.") from None
    if cameras.batch_shape == ():
        cameras = jax.tree_util.tree_map(lambda a: a[None], cameras)
    if not record:
        return cameras, names
    return cameras, names, stored[0] if stored else None


def _convert(args) -> int:
    import numpy as np

    from ._status import Status

    cameras, names, record = _load_rigs(args.rig)
    status = np.where(_calibrated(cameras), Status.OK, Status.NON_FINITE).astype(np.int32)
    rms, meta = np.full(len(names), np.nan), {}
    if record is not None:  # a JSON rig's statuses, RMS and meta carry over
        if record["status"] is not None:  # (a NaN camera keeps its reason, POOR_FIT, ...)
            stored = np.asarray(record["status"])
            keep = (status == Status.OK) | (stored != Status.OK)
            status = np.where(keep, stored, status).astype(np.int32)
        rms = rms if record["rms"] is None else record["rms"]
        meta = record["meta"]
    source = ", ".join(map(str, args.rig))
    meta = {**meta, "converted_from": source}
    written = _write_rig(args, cameras, names, status, rms, meta)
    print(f"{_count(written, 'camera')} of {source} written to {args.out} ({args.format})")
    if written < len(names):
        left = [f"{n} ({Status(s).name})" for n, s in zip(names, status) if s != Status.OK]
        print(f"left out, not calibrated: {', '.join(left)}", file=sys.stderr)
    return 0


def _load_rigs(paths):
    """`convert`'s input: one rig (`_load_rig`, with its record), or several ROS camera_info
    files (`io.load_ros`: a stereo pair's two give their poses). Cameras whose intrinsics were
    read but not their poses (a single camera_info) are refused with what to do instead."""
    import numpy as np

    from . import io

    paths = [pathlib.Path(p) for p in paths]
    if len(paths) == 1:
        cameras, names, record = _load_rig(paths[0], record=True)
    else:
        others = [str(p) for p in paths if _yaml_kind(p) != "ros"]
        if others:
            raise ValueError(
                f"convert takes one rig, or the camera_info files of ROS cameras; not one of "
                f"these: {', '.join(others)}"
            )
        cameras, names = io.load_ros(*paths)
        record = None
    focal = np.asarray(cameras.alpha_u) * np.asarray(cameras.alpha_v)
    posed = np.isfinite(np.asarray(cameras.R)).any() or np.isfinite(np.asarray(cameras.t)).any()
    if np.isfinite(focal).all() and not posed:
        raise ValueError(
            f"{', '.join(map(str, paths))}: intrinsics without poses (a camera_info holds none; "
            "a stereo pair's two files give theirs). Use them as calibrate-rig --intrinsics, "
            "which finds the poses from the frames."
        )
    return cameras, names, record


def _yaml_kind(path: pathlib.Path) -> str:
    """Which rig a YAML file holds: `"ros"` (a camera_info: top-level `image_width:` and a
    `camera_matrix:` map), `"kalibr"` (a camera chain: a top-level `cam0:` map with
    `camera_model`), else `"opencv"` (FileStorage; also a file that cannot be read, whose reader
    says why)."""
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except OSError:
        return "opencv"
    if all(re.search(rf"^{key}:", text, re.M) for key in ("image_width", "camera_matrix")):
        return "ros"
    if re.search(r"^cam0:\s*$", text, re.M) and "camera_model:" in text:
        return "kalibr"
    return "opencv"


def _load_toml_rig(path: pathlib.Path):
    """caliscope's `camera_array.toml` or aniposelib's `calibration.toml`, told apart by their
    tables (`[cameras.<id>]` or `[cam_N]`)."""
    from . import io

    document = io._read_toml(path)
    if isinstance(document.get("cameras"), dict):
        return io.load_caliscope_cameras(path)
    if any(re.fullmatch(r"cam_\d+", key) for key in document):
        return io.load_aniposelib(path)
    raise ValueError(
        f"{path}: neither caliscope's camera_array.toml ([cameras.<id>] tables) nor "
        "aniposelib's calibration.toml ([cam_N] tables), the TOML rigs mvcalib reads."
    )


def _opencv_name(name: str) -> str:
    from .io import opencv_name

    return opencv_name(name)


def _no_spaces(name: str) -> str:
    """A camera name as COLMAP's image names allow."""
    return re.sub(r"\s", "_", name)


def _align(names, data, path):
    """The file's pixels and mask in the rig's camera order, `(C_rig, P, ...)`; the file's
    cameras are matched to the rig's by name, either one also as written to OpenCV or COLMAP
    files (`cal/cam1.tif` is `cal_cam1_tif` in OpenCV's YAML: a file naming that one was refused
    against the JSON rig of the same calibration)."""
    import numpy as np

    index = {name: i for i, name in enumerate(names)}
    for i, name in enumerate(names):
        for spelling in (_opencv_name(name), _no_spaces(name)):
            index.setdefault(spelling, i)
    P = len(data.points)
    pixels = np.full((len(names), P, 2), np.nan)
    mask = np.zeros((len(names), P), bool)
    for j, camera in enumerate(data.cameras):
        spellings = (camera, _opencv_name(camera), _no_spaces(camera))
        i = next((index[n] for n in spellings if n in index), None)
        if i is None:
            shown = ", ".join(repr(n) for n in names[:4]) + (", ..." if len(names) > 4 else "")
            raise ValueError(f"{path}: camera {camera!r} is not in the rig ({shown}).")
        pixels[i], mask[i] = data.pixels[j], data.mask[j]
    return pixels, mask


def _calibrated(cameras):
    """Per camera: are all its parameters finite (failed cameras are saved as NaN)?"""
    import numpy as np

    from ._camera import finite_cameras

    return np.asarray(finite_cameras(cameras))


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "s")


# ---------------------------------------------------------------------------- calibrate
def _calibrate(args) -> int:
    import numpy as np

    from . import _validate, io
    from ._pipeline import calibrate, mirror_note
    from ._report import format_table
    from ._status import Status

    say = _progress(args)
    data = io.load_correspondences(args.correspondences)
    if data.world is None:
        raise ValueError(
            f"{args.correspondences}: no world_x, world_y, world_z columns; calibrate needs "
            "3-D/2-D correspondences (2-D tracks go to `mvcalib triangulate`)."
        )
    C, P = data.mask.shape
    say(
        f"read {_count(C, 'camera')}, {_count(P, 'point')}, "
        f"{_count(int(data.mask.sum()), 'observation')} from {args.correspondences}"
    )
    if args.image_size is not None:  # (written to the files: (width, height), as the pixels)
        _validate.in_image(data.pixels, data.mask, args.image_size)
    refine = False
    if args.refine or args.distortion is not None:
        refine = {} if args.distortion is None else {"distortion": args.distortion}
    steps = "DLT, decomposition" + (
        ", Levenberg-Marquardt refinement" if refine is not False else ""
    )
    say(f"calibrating: {steps} (the first run compiles)")
    result = calibrate(data.world, np.nan_to_num(data.pixels), data.mask, refine=refine)
    status = np.asarray(result.status)
    ok = status == Status.OK
    words = [Status(int(s)).name.lower() for s in status]
    print(format_table(result.report, status=words, names=data.cameras))
    if note := mirror_note(result, data.cameras):
        print(note)
    meta = {"correspondences": str(args.correspondences), "refined": refine is not False}
    if refine is not False:
        meta["distortion"] = list(refine.get("distortion", ("k1", "k2", "p1", "p2")))
    written = _write_rig(args, result.cameras, data.cameras, status, result.report.rms, meta)
    print()
    for i in np.flatnonzero(~ok):
        print(f"{data.cameras[i]}: {Status(int(status[i])).message}")
    print(
        f"{int(ok.sum())} of {C} cameras calibrated; {_count(written, 'camera')} written to "
        f"{args.out} ({args.format})"
    )
    return 0 if ok.all() else 1


def _write_rig(args, cameras, names, status, rms, meta) -> int:
    """The rig to `args.out` in `args.format`: JSON holds every camera with its status, RMS and
    `meta`; OpenCV's YAML, COLMAP's model, aniposelib's TOML, Kalibr's YAML and ROS's files the
    calibrated ones. Returns how many were written. Where no camera was calibrated nothing is
    written (a rig file there, perhaps a good one from an earlier run, was replaced by one of
    NaN cameras)."""
    import numpy as np

    from . import io
    from ._status import Status

    out = pathlib.Path(args.out)
    keep = np.flatnonzero(np.asarray(status) == Status.OK)
    if not keep.size:
        raise _Failed(f"no camera could be calibrated; {out} not written.")
    if args.format == "json":
        io.save_json(out, cameras, names=names, status=status, rms=rms, meta=meta)
        return len(names)
    cameras, names = cameras[keep], [names[i] for i in keep]
    if args.format == "opencv":
        io.save_opencv(
            out, cameras, names=_unique(map(_opencv_name, names)), image_size=args.image_size
        )
    elif args.format == "aniposelib":
        io.save_aniposelib(out, cameras, args.image_size, names=names)
    elif args.format == "kalibr":
        topics = [f"/{name}/image_raw" for name in _unique(map(_opencv_name, names))]
        io.save_kalibr(
            out, cameras, args.image_size, topics=topics, metres_per_unit=args.metres_per_unit
        )
    elif args.format == "ros":
        _write_ros(out, cameras, names, args)
    else:
        io.save_colmap(out, cameras, args.image_size, names=_unique(map(_no_spaces, names)))
    return len(keep)


def _write_ros(folder: pathlib.Path, cameras, names, args) -> None:
    """ROS camera_info files in `folder`, `NAME.yaml` a camera: two cameras as a rectified stereo
    pair (`io.save_ros`, the left camera first, in whichever order the rig gives them), any
    other number each on its own (a camera_info holds no pose: ROS keeps a rig's poses in tf)."""
    from . import io

    say = _progress(args)
    folder.mkdir(parents=True, exist_ok=True)
    names = _unique(map(_opencv_name, names))
    paths = [folder / f"{name}.yaml" for name in names]
    size = args.image_size
    if len(names) == 2:
        pair = dict(metres_per_unit=args.metres_per_unit)
        try:
            io.save_ros(paths, cameras, size, names=names, **pair)
        except ValueError as error:  # (ROS's pair is the left camera first: the other order?)
            try:
                io.save_ros(paths[::-1], cameras[::-1], size, names=names[::-1], **pair)
            except ValueError:
                raise error from None
            names = names[::-1]
        say(f"a stereo pair, rectified: {names[0]} left, {names[1]} right")
        return
    for i, path in enumerate(paths):
        io.save_ros(path, cameras[i], size, names=[names[i]])
    if len(names) > 2:
        say(
            f"{len(names)} cameras, each on its own (a camera_info holds no pose; a rig of two "
            "is written as a rectified stereo pair)"
        )


def _unique(names) -> list[str]:
    out, seen = [], set()
    for name in names:
        candidate, k = name, 1
        while candidate in seen:
            k += 1
            candidate = f"{name}_{k}"
        seen.add(candidate)
        out.append(candidate)
    return out


# ---------------------------------------------------------------------------- calibrate-rig
def _calibrate_rig(args) -> int:
    import numpy as np

    from . import _validate
    from ._camera import LENSES
    from ._refine import GROUPS, Cauchy, Huber
    from ._rig import SolveFailed, calibrate_rig
    from ._status import Status

    say = _progress(args)
    held = {p for name in args.fix for p in GROUPS.get(name, (name,))}
    if args.intrinsics is None and held & {*GROUPS["intrinsics"], *GROUPS["pose"]}:
        raise ValueError(
            f"--fix {','.join(args.fix)} needs --intrinsics: the cameras whose values it holds."
        )
    if args.plot:
        from . import plot

        try:
            plot.require_matplotlib()
        except ImportError as error:
            raise _Failed(str(error)) from None
    obs = _load_observations(args.observations)
    C, F, N = obs.mask.shape
    say(
        f"read {_count(C, 'camera')}, {_count(F, 'frame')}, {_count(N, 'target point')}, "
        f"{_count(int(obs.mask.sum()), 'observation')} from {args.observations}"
    )
    if args.image_size is not None:
        _validate.in_image(obs.pixels, obs.mask, args.image_size)
    cameras = started_from = None
    if args.intrinsics is not None:
        cameras, started_from = _starting_rig(args.intrinsics, obs.cameras)
        if args.fisheye and cameras.lens != "fisheye":
            raise ValueError(
                f"--fisheye, but the cameras of --intrinsics {args.intrinsics} are "
                f"{cameras.lens} cameras: leave out --fisheye, or give fisheye cameras."
            )
    if args.reference == "target":
        reference = "target"
    elif args.reference in obs.cameras:
        reference = obs.cameras.index(args.reference)
    elif re.fullmatch(r"\d+", args.reference):
        reference = int(args.reference)
    else:
        raise ValueError(
            f"--reference {args.reference!r} is neither a camera index (0 to {C - 1}), a camera "
            "name nor 'target'."
        )
    origin_frame = None
    if args.origin_frame is not None:
        found = np.flatnonzero(np.asarray(obs.frames) == args.origin_frame)
        if not found.size:
            raise ValueError(
                f"--origin-frame {args.origin_frame}: no frame of that id in "
                f"{args.observations} (its frames are {obs.frames[0]} to {obs.frames[-1]})."
            )
        origin_frame = int(found[0])
    loss, loss_name = None, None
    if args.huber is not None:
        loss, loss_name = Huber(args.huber), "huber"
    elif args.cauchy is not None:
        loss, loss_name = Cauchy(args.cauchy), "cauchy"
    say("calibrating the rig: closed form, then Levenberg-Marquardt (the first run compiles)")
    try:
        result = calibrate_rig(
            obs.target,
            obs.pixels,
            obs.mask,
            cameras=cameras,
            fix=args.fix,
            distortion=args.distortion,
            reference=reference,
            origin_frame=origin_frame,
            loss=loss,
            verbose=not args.quiet,
            **(dict(lens="fisheye", image_size=args.image_size) if args.fisheye else {}),
        )
    except SolveFailed as error:  # (the library's words are Python's)
        raise _Failed(
            f"the rig's joint solve failed: every camera reprojects its points with an RMS of "
            f"{error.rms:.3g} px after {error.iterations} steps. Check that the detections match "
            "the target's points (ids, order, units); for wrong detections, --huber 2 (or "
            "--cauchy 2 for many); or start from known cameras with --intrinsics"
            + ("." if args.fisheye else "; for wide-angle lenses, --fisheye --image-size W H.")
        ) from None
    status = np.asarray(result.status)
    ok = status == Status.OK
    print(result.table(names=obs.cameras))
    print("cameras: " + ", ".join(f"{c} = {name}" for c, name in enumerate(obs.cameras)))
    alone = status == Status.NOT_CONNECTED
    if isinstance(reference, int) and alone.sum() > ok.sum():  # the reference on its own
        seen = obs.mask.any(-1).sum(-1)  # frames per camera
        best = obs.cameras[int(np.argmax(np.where(alone, seen, -1)))]
        print(
            f"note: {_count(int(alone.sum()), 'camera')} share no frames with the reference "
            f"camera {obs.cameras[reference]}: --reference {best} (or --reference target) makes "
            f"the world {best}'s frame and calibrates the cameras linked to it."
        )
    origin = None if result.origin_frame is None else int(obs.frames[result.origin_frame])
    if origin is not None:
        print(f"(frame {result.origin_frame} counts the frames from 0; its id in "
              f"{args.observations} is {origin})")  # fmt: skip

    def number(x):
        return float(x) if np.isfinite(x) else None

    n_inliers = int(np.asarray(result.inliers).sum())

    meta = {
        "observations": str(args.observations),
        "intrinsics": None if args.intrinsics is None else str(args.intrinsics),
        "intrinsics_cameras": started_from,  # the file's camera for each camera
        "fix": list(args.fix),
        "distortion": [n for n in result.parameter_names if n in LENSES[result.cameras.lens]],
        "reference": reference,
        "origin_frame": origin,
        "loss": None if loss is None else {loss_name: float(loss.scale)},
        "rms": number(result.rms),
        "rms_observed": number(result.rms_observed),
        "rms_inliers": number(result.rms_inliers),
        "n_inliers": n_inliers,
        "iterations": int(result.iterations),
        "converged": bool(result.converged),
        "n_skipped": int(result.n_skipped),
        "position_std": [[number(v) for v in row] for row in np.asarray(result.position_std)],
        "rotation_std_deg": [[number(v) for v in row] for row in np.asarray(result.rotation_std)],
    }
    written = _write_rig(args, result.cameras, obs.cameras, status, result.camera_rms, meta)
    print()
    _print_intrinsics(result, obs.cameras)
    _print_poses(result, obs.cameras)
    messages = result.messages()
    for i, message in enumerate(messages):
        if not ok[i] or message != Status.OK.message:  # (an OK camera's notes too)
            print(f"{obs.cameras[i]}: {message}")
    n_observed = int(np.asarray(result.observed).sum())
    print(
        f"all cameras: {_count(n_observed, 'observation')}, RMS "
        f"{float(result.rms_observed):.4f} px ({int(np.asarray(result.used).sum())} used in the "
        f"fit: RMS {float(result.rms):.4f} px)"
    )
    if loss is not None:
        print(
            f"inliers of the {type(loss).__name__} loss (within {3 * loss.scale:g} px): "
            f"{_count(n_inliers, 'observation')}, RMS "
            f"{float(result.rms_inliers):.4f} px"
        )
    print(
        f"{int(ok.sum())} of {C} cameras calibrated; {_count(written, 'camera')} written to "
        f"{args.out} ({args.format})"
    )
    if args.plot:
        say("drawing the figure")
        poses = result.target_poses
        world = np.asarray(poses.apply(np.broadcast_to(obs.target, (F, N, 3))))  # (F, N, 3)
        posed = np.all(np.isfinite(world), (1, 2))
        mask = np.asarray(result.observed)[:, posed] & ok[:, None, None]
        figure = plot.report_figure(
            result.cameras,
            world[posed].reshape(-1, 3),
            obs.pixels[:, posed].reshape(C, -1, 2),
            mask.reshape(C, -1),
            names=obs.cameras,
            image_size=args.image_size,
            title=f"{_count(C, 'camera')}, {_count(int(posed.sum()), 'frame')}, "
            f"{_count(int(mask.sum()), 'observation')}, RMS "
            f"{float(result.rms_observed):.3g} px",
        )
        plot.save_figure(figure, args.plot)
        extra = int(mask.sum()) - int(np.asarray(result.used).sum())
        print(
            f"figure written to {args.plot}"
            + (  # (its counts and RMS are over every observation: the table's over those used)
                f" (every observation of a calibrated camera in a posed frame: {extra} more "
                "than the table's, from the pairs skipped or left out of the fit)"
                if extra > 0
                else ""
            )
        )
    return 0 if ok.all() else 1


# The estimated intrinsics of a camera whose standard errors exceed these (pixels; a fraction of
# the focal length) are noted as weakly determined: in the board trial, caliscope's cam_1 with its
# intrinsics free put u0 101 px from caliscope's (15 px standard error) at RMS 0.88 px, OK.
_LOOSE_CENTRE_PX, _LOOSE_FOCAL = 5.0, 0.01


def _print_intrinsics(result, names) -> None:
    """The estimated focal lengths and principal points with their standard errors, one row a
    calibrated camera, and a note for those the recording determines poorly (nothing if the
    intrinsics were held)."""
    import numpy as np

    estimated = [n for n in ("alpha_u", "alpha_v", "u0", "v0") if n in result.parameter_names]
    if not estimated:
        return
    value = {n: np.asarray(getattr(result.cameras, n)) for n in ("alpha_u", "alpha_v", "u0", "v0")}
    std = np.asarray(result.parameter_std)
    spread = {n: std[:, result.parameter_names.index(n)] if n in estimated else None
              for n in value}  # fmt: skip
    width = max(6, *map(len, map(str, names)))
    print(f"{'camera':<{width}}  {'alpha_u':>16}  {'alpha_v':>16}  {'u0':>14}  {'v0':>14}  (px)")
    loose = []
    for c in np.flatnonzero(np.asarray(result.ok)):
        cells = [
            f"{value[n][c]:.1f}" + ("" if spread[n] is None else f" ± {spread[n][c]:.2g}")
            for n in value
        ]
        a_u, a_v, u0, v0 = cells
        print(f"{names[c]:<{width}}  {a_u:>16}  {a_v:>16}  {u0:>14}  {v0:>14}")
        centre = max((spread[n][c] for n in ("u0", "v0") if spread[n] is not None), default=0)
        focal = max(
            (spread[n][c] / value[n][c] for n in ("alpha_u", "alpha_v") if spread[n] is not None),
            default=0,
        )
        if centre > _LOOSE_CENTRE_PX or focal > _LOOSE_FOCAL:
            loose.append(names[c])
    if loose:
        print(
            f"note: the recording determines the intrinsics of {', '.join(map(str, loose))} "
            f"poorly (a principal point's standard error above {_LOOSE_CENTRE_PX:g} px or a focal "
            f"length's above {_LOOSE_FOCAL:.0%}): record them at more angles and across the "
            "whole image, or hold known ones with --intrinsics ... --fix intrinsics"
        )
    print()


def _print_poses(result, names) -> None:
    """Each calibrated camera's centre in the world frame (the target's units), its distance
    from the first calibrated camera (a stereo pair's baseline) and its rotation from it
    (degrees), with the centre's standard error: what a stereo user reads off OpenCV's R, T."""
    import numpy as np

    ok = np.flatnonzero(np.asarray(result.ok))
    if len(ok) < 2:
        return
    centre, R = np.asarray(result.cameras.center), np.asarray(result.cameras.R)
    std = np.linalg.norm(np.asarray(result.position_std), axis=-1)
    first = ok[0]
    width = max(6, *map(len, map(str, names)))
    print(
        f"{'camera':<{width}}  {'centre (x, y, z)':>32}  {f'from {names[first]}':>12}  "
        f"{'rotation':>9}  {'centre std':>10}"
    )
    for c in ok:
        cosine = (np.trace(R[c] @ R[first].T) - 1.0) / 2.0
        angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
        xyz = ", ".join(f"{v + 0.0:.4g}" for v in centre[c])  # (+ 0.0: no "-0")
        print(
            f"{names[c]:<{width}}  {xyz:>32}  {np.linalg.norm(centre[c] - centre[first]):>12.5g}  "
            f"{angle:>8.3f}°  {std[c]:>10.2g}"
        )
    print()


def _load_observations(path):
    """Observations from an mvcalib observations CSV or caliscope's `xy.csv` (by its header)."""
    from . import io

    try:
        with open(path, newline="", encoding=io.ENCODING) as f:
            first = next((line for line in f if line.strip()), "")
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not a readable observations file ({error})") from None
    header = {h.strip() for h in first.split(",")}
    if {"sync_index", "img_loc_x"} <= header:
        return io.load_caliscope(path)
    return io.load_observations(path)


def _starting_rig(path, names):
    """The rig of `path` (any that `_load_rig` reads) in the order of the observations' camera
    `names`, and the file's name for each: matched by name where the file has every one of them
    (it may hold more cameras, e.g. a lab's), or every one with case and punctuation aside
    (`cam0` = `cam_0`); in order where it has none of them and as many cameras (announced:
    nothing checks that the order is right); else refused. Some names
    matched and others not was taken in order, silently: focal lengths 20 % off, RMS 6 px, OK."""
    import jax
    import numpy as np

    cameras, theirs = _load_rig(path)
    plain = lambda name: re.sub(r"[^0-9a-z]", "", str(name).lower())  # noqa: E731
    ours_plain, theirs_plain = [plain(n) for n in names], [plain(n) for n in theirs]
    if len(set(theirs)) == len(theirs) and set(names) <= set(theirs):
        order = [theirs.index(n) for n in names]
    elif (
        not set(names) & set(theirs)
        and len(set(theirs_plain)) == len(theirs)
        and set(ours_plain) <= set(theirs_plain)
    ):  # (a user's trial: cam0.. against cam_0.., the observations' first camera cam2, taken in
        # order: every camera another's intrinsics, all OK at 5 px RMS)
        order = [theirs_plain.index(n) for n in ours_plain]
        print(
            f"note: the cameras of --intrinsics {path} matched by name, case and punctuation "
            "aside: " + ", ".join(f"{ours} = {theirs[i]}" for ours, i in zip(names, order))
        )
    elif not set(names) & set(theirs) and len(theirs) == len(names):
        order = list(range(len(names)))
        print(
            f"note: the cameras of --intrinsics {path} have none of the observations' names: "
            "taken in their order, "
            + ", ".join(f"{ours} = {theirs[i]}" for ours, i in zip(names, order))
        )
    elif set(names) & set(theirs):
        missing = [n for n in names if n not in theirs]
        raise ValueError(
            f"{path} has no camera named {', '.join(map(repr, missing))} (it has "
            f"{', '.join(map(repr, theirs))}): name every camera of the observations, or none "
            "(then they are taken in order)."
        )
    else:
        raise ValueError(
            f"{path}: {_count(len(theirs), 'camera')}; the observations have {len(names)}, and "
            "no name in common to match them by."
        )
    if order != list(range(len(theirs))):
        cameras = jax.tree_util.tree_map(lambda a: a[np.array(order)], cameras)
    return cameras, [theirs[i] for i in order]


# ---------------------------------------------------------------------------- detect
def _detect(args) -> int:
    import numpy as np

    from . import io
    from ._detect import detect_dots
    from ._images import read_image
    from ._label import label_dots
    from .targets import box_corner

    say = _progress(args)
    target = box_corner()
    M = 0 if args.no_label else len(target.points)
    names, pixels, masks, unlabelled, rows, failed = [], [], [], [], [], 0
    for k, path in enumerate(args.images):
        name = str(path)
        names.append(name)
        pixels.append(np.full((M, 2), np.nan))
        masks.append(np.zeros(M, bool))
        blobs, found = "-", 0
        try:
            detection = detect_dots(read_image(path), dark_dots=not args.bright_dots)
        except ValueError as error:
            unlabelled.append(np.zeros((0, 2)))
            message, failed = str(error).removeprefix(f"{name}: "), failed + 1
        else:
            blobs, centroids = len(detection), np.asarray(detection.centroids)
            if args.no_label:
                unlabelled.append(centroids)
                message = f"{_count(len(detection), 'dot')} detected"
            else:
                labels = label_dots(detection, target)
                message = labels.message
                if labels.ok:
                    pixels[-1], masks[-1] = labels.pixels, labels.mask
                    unlabelled.append(centroids[labels.spurious])
                    found = int(labels.mask.sum())
                else:
                    unlabelled.append(centroids)
                    failed += 1
        rows.append((name, blobs, found, message))
        say(f"[{k + 1}/{len(args.images)}] {name}: {message}")
    io.save_correspondences(
        args.out,
        None if args.no_label else target.points,
        np.stack(pixels).reshape(len(names), M, 2),
        np.stack(masks).reshape(len(names), M),
        cameras=names,
        points=[str(i) for i in range(M)],
        unlabelled=unlabelled,
    )
    width = max(5, *(len(n) for n in names))
    print(f"{'image':<{width}}  blobs  {'labelled' if not args.no_label else '':>8}  result")
    for name, blobs, found, message in rows:
        labelled = "" if args.no_label else str(found)
        print(f"{name:<{width}}  {blobs!s:>5}  {labelled:>8}  {message}")
    what = "read" if args.no_label else "labelled"
    print(f"\n{len(names) - failed} of {len(names)} images {what}; dots written to {args.out}")
    return 0 if not failed else 1


# ---------------------------------------------------------------------------- report
def _report(args) -> int:
    import jax
    import numpy as np

    from . import io
    from ._report import format_table, reprojection_report

    say = _progress(args)
    if args.plot:
        from . import plot

        try:
            plot.require_matplotlib()
        except ImportError as error:
            raise _Failed(str(error)) from None
    cameras, names = _load_rig(args.rig)
    data = io.load_correspondences(args.correspondences)
    if data.world is None:
        raise ValueError(
            f"{args.correspondences}: no world_x, world_y, world_z columns to "
            "reproject; a report needs 3-D/2-D correspondences."
        )
    pixels, mask = _align(names, data, args.correspondences)
    calibrated = _calibrated(cameras)
    mask &= calibrated[:, None]
    if not mask.any():
        raise ValueError(
            f"no calibrated camera of {args.rig} sees a point of {args.correspondences}."
        )
    n_seen = _count(int(mask.sum()), "observation")
    say(f"reprojecting {n_seen} with {_count(len(names), 'camera')}")
    # One compiled computation rather than a string of eager ops (each compiled on its own).
    report = jax.jit(reprojection_report)(cameras, data.world, np.nan_to_num(pixels), mask)
    status = ["" if c else "not calibrated" for c in calibrated]
    status = [s or ("no points" if n == 0 else "") for s, n in zip(status, report.n_points)]
    print(format_table(report, status=status if any(status) else None, names=names))
    r = np.asarray(report.residuals)[mask]
    length = np.linalg.norm(r, axis=-1)
    c, p = np.argwhere(mask)[np.argmax(length)]
    print(
        f"\nall cameras: {_count(len(length), 'observation')}, RMS "
        f"{np.sqrt(np.mean(length**2)):.4f} px, median {np.median(length):.4f} px, 95th "
        f"percentile {np.percentile(length, 95):.4f} px, max {length.max():.4f} px "
        f"(camera {names[c]!r}, point {data.points[p]!r})"
    )
    if args.plot:
        say("drawing the figure")
        figure = plot.report_figure(
            cameras, data.world, pixels, mask, names=names, image_size=args.image_size
        )
        plot.save_figure(figure, args.plot)
        print(f"figure written to {args.plot}")
    return 0


# ---------------------------------------------------------------------------- triangulate
def _triangulate(args) -> int:
    import csv
    import io as text_io

    import numpy as np

    from . import io
    from ._triangulate import triangulate

    say = _progress(args)
    cameras, names = _load_rig(args.rig)
    tracks = io.load_correspondences(args.tracks)
    pixels, mask = _align(names, tracks, args.tracks)
    calibrated = _calibrated(cameras)
    mask &= calibrated[:, None]
    P = len(tracks.points)
    anonymous = sum(len(u) for u in tracks.unlabelled)
    if anonymous:  # (they were left out without a word: "0 of 0 points triangulated")
        print(
            f"note: {_count(anonymous, 'detection')} without a point id (rows with an empty point) "
            "not triangulated: a point is triangulated from the rows that name it in two cameras "
            "or more (which detection is which point across the cameras is not searched for)"
        )
    say(
        f"triangulating {_count(P, 'point')} from {_count(len(names), 'camera')} "
        f"({_count(int(mask.sum()), 'observation')})" + (", refined" if args.refine else "")
    )
    out = triangulate(
        cameras,
        np.nan_to_num(pixels),
        mask,
        refine=args.refine,
        min_angle=args.min_angle,
        max_rms=args.max_rms,
    )
    points, views, rms, angle, ok = (
        np.asarray(a) for a in (out.points, out.views, out.rms, out.angle, out.ok)
    )
    made = views >= 2
    buffer = text_io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(
        ["point", "world_x", "world_y", "world_z", "views", "rms_px", "angle_deg", "ok"]
    )
    # (Python floats, not NumPy's one at a time: 100,000 points written in 0.6 s, not 3.8)
    numbers = np.c_[points, rms, angle].tolist()
    rows = zip(tracks.points, numbers, made.tolist(), views.tolist(), ok.tolist())
    for name, values, seen, n_views, good in rows:
        values = [repr(v) for v in values] if seen else [""] * 5
        writer.writerow([name, *values[:3], int(n_views), *values[3:], int(good)])
    io.write_atomic(args.out, buffer.getvalue())
    print(
        f"{made.sum()} of {_count(P, 'point')} triangulated (seen by 2 cameras or more), "
        f"{ok.sum()} ok (in front of their cameras, rays >= {args.min_angle:g} deg apart"
        + (f", RMS <= {args.max_rms:g} px)" if np.isfinite(args.max_rms) else ")")
    )
    if made.any():
        print(
            f"reprojection RMS per point: median {np.median(rms[made]):.4f} px, max "
            f"{rms[made].max():.4f} px"
        )
    far = made & (rms > FAR_PX)
    if far.any():
        print(
            f"note: {_count(int(far.sum()), 'point')} reproject worse than {FAR_PX:g} px (the "
            f"worst {rms[far].max():.3g} px; {int((far & ok).sum())} of them ok): check that the "
            "tracks' cameras are the rig's, that the pixels are (x = column, y = row) with no "
            "stand-in for an unseen view (leave its row out), and that the rig is calibrated; "
            "the rms_px column says which points"
        )
    if made.any() and not ok.any():
        R, t = np.asarray(cameras.R), np.asarray(cameras.t)
        depth = np.nan_to_num(points) @ R[:, 2].T + t[:, 2]  # (P, C)
        depth = depth.T
        behind = np.sum(np.where(mask, depth < 0, False), 0) > mask.sum(0) / 2
        if behind[made].mean() > 0.5:
            print(
                "note: the points lie behind the cameras that see them, so none is ok: the "
                "rig's world frame is mirrored (left-handed, as in the Oxford VGG data)"
            )
    if tracks.world is not None and made.any():
        distance = np.linalg.norm(points[made] - tracks.world[made], axis=-1)
        print(
            f"distance to the world coordinates in {args.tracks}: median "
            f"{np.median(distance):.4g}, max {distance.max():.4g}"
        )
    print(f"points written to {args.out}")
    if not made.any():
        raise _Failed("no point is seen by two calibrated cameras of the rig.")
    return 0


# ---------------------------------------------------------------------------- images, demo
def _calibrate_images(args) -> int:
    import numpy as np

    from . import io, targets
    from ._images import calibrate_images
    from ._refine import Huber

    radius = float("nan") if args.dot_radius is None else args.dot_radius
    target = targets.from_file(args.target, dot_radius=radius) if args.target else (
        targets.box_corner())  # fmt: skip
    # (a malformed clicks file, as a malformed --target, is bad input: exit code 2)
    seeds = io.load_clicks(args.clicks, args.images, target) if args.clicks else None
    _check_seeds(args, target, seeds)
    refine = args.refine
    if args.distortion is not None or args.huber is not None:
        refine = {} if args.distortion is None else {"distortion": args.distortion}
        if args.huber is not None:
            refine["loss"] = Huber(args.huber)
    with warnings.catch_warnings():  # (an unknown dot radius: the result's note says it)
        warnings.filterwarnings("ignore", "calibrate_images: the target's dot radius")
        result = calibrate_images(
            args.images,
            target,
            refine=refine,
            detect=dict(dark_dots=not args.bright_dots),
            seeds=seeds,
            focal=args.focal,
            progress=not args.quiet,
            second_look=not args.no_second_look,
            label=dict(trust_seed=True) if args.trust_clicks else None,
            workers=_workers(args, len(args.images)),
        )
    print(result)
    sizes = {d.image_shape[::-1] for d in result.detections if d is not None}
    args.image_size = sizes.pop() if len(sizes) == 1 else None  # (width, height)
    if args.format in _SIZED and args.image_size is None:
        raise ValueError(f"--format {args.format} takes photos of one size; these differ")
    meta = {
        "target": target.name,
        "messages": result.messages,
        "misplaced": {str(i): point.tolist() for i, point in result.misplaced.items()},
        "photos": [str(name) for name in result.names],
    }
    status, rms = result.calibration.status, result.calibration.report.rms
    names = args.names or result.names
    written = _write_rig(args, result.cameras, names, status, rms, meta)
    dots = ""
    if args.dots:
        # the dots the calibration used: a misplaced one (left out of it) is not among them, so
        # that `mvcalib report RIG DOTS` gives the calibration's Table I (a user's trial: it
        # counted dot 68, 1.29 px off, and printed another table)
        ids = [str(int(i)) for i in target.ids]
        used = result.mask & ~np.isin(np.asarray(target.ids), list(result.misplaced))
        io.save_correspondences(
            args.dots, target.points, result.pixels, used, cameras=names, points=ids
        )
        left = ", ".join(str(i) for i in result.misplaced)
        dots = f"; labelled dots written to {args.dots}" + (
            f" (not the misplaced dot {left}: as in the calibration)" if left else ""
        )
    n_ok = int(result.ok.sum())
    print(
        f"\n{n_ok} of {len(result.names)} cameras calibrated; {_count(written, 'camera')} written "
        f"to {args.out} ({args.format}){dots}"
    )
    return 0 if n_ok == len(result.names) else 1


# --workers: processes that read the photos and find their dots (`_photos._in_workers`)
_WORKERS = dict(
    type=int, metavar="N",
    help="processes that read the photos and find their dots (default: one a core, at most 8, "
    "from 16 photos on; else 1)",
)  # fmt: skip
# From this many photos on, the default is a worker a core (each takes ~0.4 s to start and
# ~120 MB), at most `_MAX_WORKERS`.
_MANY_PHOTOS, _MAX_WORKERS = 16, 8


def _workers(args, n_photos: int) -> int:
    """--workers, or its default: a process a core this process may use, at most
    `_MAX_WORKERS`, with `_MANY_PHOTOS` photos or more; else 1."""
    import os

    if args.workers is not None:
        return args.workers
    if n_photos < _MANY_PHOTOS:
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(cores or 1, _MAX_WORKERS))


def _check_seeds(args, target, seeds) -> None:
    """Each photo can be labelled: from the target's fiducial dots, or from its clicks (six or
    more dots not all on one plane, or four or more with --focal), as `label_dots` and
    `match_dots` need; else `ValueError` (exit code 2) before any photo is read."""
    import numpy as np

    from ._match import _coplanar

    need = "six or more dots not all on one plane, or four or more and --focal PX"
    if 6 <= len(target.fiducials) <= 9:  # (what `label_dots` labels from)
        seeds = seeds or [None] * len(args.images)
    elif seeds is None:
        raise ValueError(
            f"{args.target}: this target has no fiducial dots to label the photos from; give "
            f"--clicks FILE, the dots clicked in each photo ({need})."
        )
    elif any(seed is None for seed in seeds):
        missing = args.images[[seed is None for seed in seeds].index(True)]
        raise ValueError(
            f"{args.clicks}: no clicks for {missing}; a target without fiducial dots needs "
            f"clicks in every photo ({need})."
        )
    world = np.asarray(target.points)
    for image, seed in zip(args.images, seeds):
        if seed is None:
            continue
        n = len(seed[1])
        enough = n >= 6 and not _coplanar(world[target.index(seed[1])])
        if not enough and (args.focal is None or n < 4):
            plane = " on one plane" if n >= 6 else ""
            raise ValueError(
                f"{args.clicks}: {_count(n, 'click')}{plane} for {image}; give {need} (a "
                "focal-length guess in pixels)."
            )


def _observe_grid(args) -> int:
    import numpy as np

    from . import io, targets
    from ._images import observe_grid

    rows, cols, spacing = args.grid
    grid = targets.dot_grid(int(rows), int(cols), spacing, asymmetric=args.asymmetric,
                            markers=args.markers, marker_scale=args.marker_scale)  # fmt: skip
    photos = [[None if p == "-" else p for p in camera] for camera in args.camera]
    names = [f"cam{c}" for c in range(len(photos))]
    say = _progress(args)
    say(f"labelling {_count(sum(p is not None for c in photos for p in c), 'photo')} of "
        f"{_count(len(photos), 'camera')}")  # fmt: skip
    workers = _workers(args, sum(p is not None for camera in photos for p in camera))
    obs = observe_grid(photos, grid, names=names, detect=dict(dark_dots=not args.bright_dots),
                       progress=not args.quiet, workers=workers)  # fmt: skip
    labelled = np.asarray(obs.mask).any(-1)
    for name, camera, row in zip(names, photos, labelled):
        print(f"{name}: {int(row.sum())} of {sum(p is not None for p in camera)} photos labelled")
    io.save_observations(args.out, obs)
    print(f"observations written to {args.out}")
    if not labelled.any(-1).all():
        missing = ", ".join(n for n, row in zip(names, labelled) if not row.any())
        raise _Failed(f"no photo of {missing} could be labelled.")
    return 0


def _demo(args) -> int:
    import numpy as np

    from . import demo

    say = _progress(args)
    if args.images:
        say("rendering the 4 snapshots, then detect, label, calibrate, register")
        shown = demo.run_images(seed=args.seed, figure=args.figure or None)
        print(demo.format_images(shown))
        code = 0 if shown.result.ok.all() else 1
        cameras, pixels, mask = shown.result.cameras, shown.result.pixels, shown.result.mask
    else:
        noise, global_noise = (0.0, 0.0) if args.noise_free else (args.noise, args.global_noise)
        say("running the paper's experiment (the first run compiles)")
        dtype = np.float32 if args.float32 else np.float64
        try:
            shown = demo.run(noise=noise, global_noise=global_noise, seed=args.seed, dtype=dtype)
        except ValueError as error:  # includes CalibrationError
            raise _Failed(str(error)) from None
        print(demo.format_result(shown))
        code = 0
        cameras = shown.calibration.cameras
        pixels, mask = np.asarray(shown.scene.pixels), np.asarray(shown.scene.mask)
    if args.save:
        from . import io

        folder = pathlib.Path(args.save)
        folder.mkdir(exist_ok=True)
        names = [f"snapshot_{i + 1}" for i in range(len(mask))]
        io.save_json(folder / "rig.json", cameras, names=names)
        io.save_correspondences(
            folder / "correspondences.csv",
            np.asarray(shown.scene.world),
            np.where(mask[..., None], pixels, np.nan),
            mask,
            cameras=names,
        )
        print(
            f"\nthe snapshots' cameras and dots written to {folder / 'rig.json'} and "
            f"{folder / 'correspondences.csv'}"
        )
    return code


COMMANDS = {
    "convert": _convert,
    "calibrate": _calibrate,
    "calibrate-rig": _calibrate_rig,
    "detect": _detect,
    "report": _report,
    "triangulate": _triangulate,
    "calibrate-images": _calibrate_images,
    "observe-grid": _observe_grid,
    "demo": _demo,
}


if __name__ == "__main__":
    sys.exit(main())
