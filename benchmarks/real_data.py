"""Real data that mvcalib did not make: the tables behind the tests in tests/test_real_data.py.

- Oxford VGG *Model House* (10 views, 672 points with published 3-D coordinates and P): per
  view, the reprojection RMS of the published P, of our DLT and of our refined camera (skew, no
  distortion) on the same corners; then every corner triangulated with the published cameras
  and with ours, against the published 3-D points.
- Middlebury *templeRing* (47 published K, R, t): `Camera.from_projection(K [R | t])` against
  the published values, and the 47 cameras registered into a moved frame by Procrustes.
- aniposelib's 12-camera outdoor rig (rough starting calibration with distortion, tracks of
  176,868 points): triangulation of all tracks, then `mc.bundle_adjust` (rounds of
  triangulate / drop outliers / `refine_rig` with free points), and the median per-point
  reprojection error over the points seen by >= 3 cameras before and after, with the time.
- OpenPTV's cavity photographs (4 cameras, its target file and its four clicked dots per camera,
  `man_ori`): a user's whole wait, `mvcalib calibrate-images ... --out rig.json` in a fresh
  process with the persistent compilation cache off (import, detection, labelling, second look,
  calibration, writing), with and without `--refine`; per camera the dots labelled and the RMS,
  and the dots found misplaced on the target.

Data are read from `$MVCALIB_DATA` (default `../shared/data`); see its SOURCE.md.
`--quick` samples fewer tracks for the bundle adjustment (1000 instead of `bundle_adjust`'s
default 2000, 2 rounds instead of 3). Run from the repository root:
`python benchmarks/real_data.py [--quick]`; results go to `benchmarks/results/real_data.json`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _common import machine_info, write_results  # noqa: E402
from first_call import child_env  # noqa: E402

import mvcalib as mc  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MVCALIB_DATA", ROOT / ".." / "shared" / "data")).resolve()
RESULTS = ROOT / "benchmarks" / "results" / "real_data.json"
sys.path.insert(0, str(ROOT / "tests"))
from _real_data import cavity_clicks, read_oxford_house  # noqa: E402  (not conftest's settings)


def oxford_house() -> dict:
    world, pixels, P_published = read_oxford_house(DATA / "oxford_house")
    mask = np.all(np.isfinite(pixels), -1)
    pixels = np.nan_to_num(pixels)
    published = mc.Camera.from_projection(P_published)
    dlt = mc.calibrate(world, pixels, mask, strict=True).cameras
    refined = mc.refine(dlt, world, pixels, mask, distortion=(), skew=True).cameras
    rms = {
        name: np.asarray(mc.reprojection_report(cams, world, pixels, mask).rms)
        for name, cams in (("published", published), ("dlt", dlt), ("refined", refined))
    }
    print("Oxford VGG Model House: reprojection RMS per view (px)")
    print(f"{'view':>4}{'points':>8}{'published':>11}{'DLT':>9}{'DLT/pub':>9}{'refined/pub':>13}")
    for v in range(len(P_published)):
        print(
            f"{v:>4}{int(mask[v].sum()):>8}{rms['published'][v]:>11.4f}{rms['dlt'][v]:>9.4f}"
            f"{rms['dlt'][v] / rms['published'][v]:>9.4f}"
            f"{rms['refined'][v] / rms['published'][v]:>13.7f}"
        )
    distances = {}
    for name, cams in (("published", published), ("dlt", dlt), ("refined", refined)):
        out = mc.triangulate(cams, pixels, mask)
        seen = np.asarray(out.views) >= 2
        distances[name] = float(
            np.median(np.linalg.norm(np.asarray(out.points)[seen] - world[seen], axis=-1))
        )
    print(
        "triangulated corners vs published 3-D points, median distance: "
        + ", ".join(f"{k} cameras {v:.2e}" for k, v in distances.items())
        + f" (scene {np.ptp(world, 0).max():.1f} units)\n"
    )
    return {k: v.tolist() for k, v in rms.items()} | {"median_distance": distances}


def temple_ring() -> dict:
    root = DATA / "middlebury_templeRing"
    lines = (root / "templeR_par.txt").read_text().split("\n")
    n = int(lines[0])
    values = np.array([[float(x) for x in line.split()[1:]] for line in lines[1 : n + 1]])
    K, R, t = values[:, :9].reshape(-1, 3, 3), values[:, 9:18].reshape(-1, 3, 3), values[:, 18:]
    cams = mc.Camera.from_projection(K @ np.concatenate([R, t[..., None]], -1))
    errors = {
        "K_rel": float(np.abs(np.asarray(cams.K)[K != 0] / K[K != 0] - 1).max()),
        "R_abs": float(np.abs(np.asarray(cams.R) - R).max()),
        "t_abs": float(np.abs(np.asarray(cams.t) - t).max()),
    }
    T = mc.RigidTransform(mc.rodrigues(np.array([0.3, -0.2, 0.1])), np.array([1.0, 2.0, 3.0]))
    moved = mc.to_global(cams, T)
    back = mc.procrustes(np.asarray(cams.center), np.asarray(moved.center))
    errors["registration_R"] = float(np.abs(np.asarray(back.R) - np.asarray(T.R)).max())
    print(
        f"Middlebury templeRing, {n} cameras: from_projection(K [R|t]) max errors: K "
        f"{errors['K_rel']:.1e} (relative), R {errors['R_abs']:.1e}, t {errors['t_abs']:.1e}; "
        f"registration of the rig into a moved frame: R to {errors['registration_R']:.1e}\n"
    )
    return errors


def aniposelib(quick: bool) -> dict:
    root = DATA / "aniposelib_mouse_outdoor"
    cameras, _ = mc.io.load_aniposelib(root / "calibration_right_4_10_2026_adjusted.toml")
    tracks = np.load(root / "points_right_4_10_2026_sub.npz")["p2d"]
    views = np.isfinite(tracks[..., 0]).sum(0)
    seen3 = views >= 3

    def median_error(rig):
        start = time.perf_counter()
        points = mc.triangulate(rig, tracks).points
        jax.block_until_ready(points)
        seconds = time.perf_counter() - start
        error = np.linalg.norm(np.asarray(rig.project(points)) - tracks, axis=-1)
        per_point = np.nanmean(error, axis=0)
        return float(np.nanmedian(per_point[seen3])), float(np.nanmedian(per_point)), seconds

    before, before_all, tri_s = median_error(cameras)
    start = time.perf_counter()
    out = mc.bundle_adjust(
        cameras,
        tracks,
        max_points=1000 if quick else 2000,
        thresholds=(50.0, 20.0) if quick else (50.0, 20.0, 10.0),
        progress=True,
    )
    ba_s = time.perf_counter() - start
    after, after_all, _ = median_error(out.cameras)
    print(
        f"aniposelib outdoor rig: 12 cameras, {tracks.shape[1]} tracks ({seen3.sum()} seen by "
        f">= 3 cameras); triangulating all of them: {tri_s:.1f} s (incl. compile)\n"
        f"  median per-point reprojection error, points seen by >= 3 cameras: {before:.2f} px "
        f"-> {after:.2f} px (all points: {before_all:.2f} -> {after_all:.2f})\n"
        f"  bundle adjustment: {len(out.rounds)} rounds, {ba_s:.0f} s in all"
    )
    return {
        "tracks": int(tracks.shape[1]),
        "tracks_seen_by_3": int(seen3.sum()),
        "median_error_before_px": before,
        "median_error_after_px": after,
        "median_error_all_before_px": before_all,
        "median_error_all_after_px": after_all,
        "triangulate_all_s": tri_s,
        "bundle_adjust_s": ba_s,
        "rounds": out.rounds,
    }


def cavity_photos() -> dict:
    """The CLI on the cavity photos from a fresh process, as a user runs it (cache off)."""
    import json
    import subprocess
    import tempfile

    root = DATA / "openptv_cavity"
    out = {}
    with tempfile.TemporaryDirectory() as folder:
        cavity_clicks(root, Path(folder) / "clicks.csv")
        for refine in ([], ["--refine"]):
            rig = Path(folder) / "rig.json"
            command = [
                sys.executable, "-m", "mvcalib", "calibrate-images",
                *(str(root / "cal" / f"cam{c}.tif") for c in range(1, 5)),
                "--target", str(root / "cal" / "target_on_a_side.txt"),
                "--clicks", str(Path(folder) / "clicks.csv"),
                "--focal", str(70.0 / 0.012), "--bright-dots", "--quiet", "--out", str(rig),
                *refine,
            ]  # fmt: skip
            start = time.perf_counter()
            done = subprocess.run(
                command, env=child_env(), capture_output=True, text=True, cwd=ROOT
            )
            seconds = time.perf_counter() - start
            if done.returncode != 0:
                raise RuntimeError(f"calibrate-images failed:\n{done.stderr[-2000:]}")
            saved = json.loads(rig.read_text())
            rms = [camera["rms"] for camera in saved["cameras"]]
            name = "refined" if refine else "dlt"
            out[name] = {
                "fresh_process_s": seconds,
                "rms_px": rms,
                "misplaced": saved["meta"].get("misplaced", {}),
                "messages": saved["meta"]["messages"],
            }
            print(
                f"cavity photos, calibrate-images{' --refine' if refine else ''}: {seconds:.1f} s "
                f"from a fresh process (cache off); RMS {np.round(rms, 3).tolist()} px; "
                f"misplaced dots {list(out[name]['misplaced'])}"
            )
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller bundle adjustment")
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        sys.exit(f"real data not found: MVCALIB_DATA={DATA}")
    wall = time.perf_counter()
    results = {
        "oxford_house": oxford_house(),
        "temple_ring": temple_ring(),
        "aniposelib": aniposelib(args.quick),
        "cavity_photos": cavity_photos(),
    }
    wall = time.perf_counter() - wall
    print(f"\ntotal wall time {wall:.1f} s")
    write_results(
        RESULTS, "real_data", quick=args.quick, machine=machine_info(), wall_time_s=wall, **results
    )


if __name__ == "__main__":
    main()
