"""The benchmark suite's timing helper (`benchmarks/_common.py`), on fake workloads."""

import hashlib
import importlib
import json
import os
import pathlib
import re
import subprocess
import sys
import time

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def benchmark_module(name):
    """`benchmarks.<name>`, imported from the repository root (not an installed package)."""
    sys.path.insert(0, str(ROOT))
    try:
        return importlib.import_module(f"benchmarks.{name}")
    finally:
        sys.path.remove(str(ROOT))


common = benchmark_module("_common")


def paths_cold_after_a_switch(cold=0.02, warm=0.001):
    """Two callables that each take `cold` seconds on the first call after the other one ran
    (caches and threads taken over by another path) and `warm` seconds after that."""
    last = [None]

    def path(name):
        def call():
            time.sleep(cold if last[0] != name else warm)
            last[0] = name

        return call

    return {"a": path("a"), "b": path("b")}


def test_measure_times_warm_calls_after_an_untimed_warmup():
    # blocks of 10 ms, and blocks of one call each
    for min_time in (0.03, 0.0):
        stats = common.measure(paths_cold_after_a_switch(), min_time=min_time, rounds=3)
        for name, st in stats.items():
            assert st["median"] < 0.005, name  # the warm 1 ms calls, not the cold 20 ms one
            assert st["repeats"] >= 3
    # without the warm-up every block's first (and here only) call is a cold one
    cold = common.measure(paths_cold_after_a_switch(), min_time=0.03, rounds=3, warmup=0.0)
    assert all(st["median"] >= 0.015 for st in cold.values())


def test_profile_dlt_attributes_the_kernels_to_the_dlt_stages(capsys):
    profile_dlt = benchmark_module("profile_dlt")
    assert profile_dlt.stage_of("jit(f)/jit(solve_validated)/eigen/while/body/mul") == "eigen"
    assert profile_dlt.stage_of("jit(f)/jit(_decompose)/vmap()/dot_general") == "decompose"
    assert profile_dlt.stage_of("jit(f)/broadcast_in_dim") == "other"
    profile_dlt.main(["--cameras", "64", "--calls", "2"])
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines() if line}
    for stage in ("moments", "eigen", "cameras", "decompose"):
        assert float(rows[stage][1]) > 0, stage  # µs per camera
        assert int(rows[stage][3]) > 0, stage  # kernels per call


def test_floor_refine_takes_each_piece_at_its_best_batch(capsys):
    floor_refine = benchmark_module("floor_refine")
    floor_refine.main(["--cameras", "8", "--scipy-cameras", "2", "--calls", "2"])
    out = capsys.readouterr().out
    lines = out.splitlines()
    rows = [line.split() for line in lines if line.split() and line.split()[0].isdigit()]
    (best,) = [line.split()[1:] for line in lines if line.startswith(" best")]
    assert [int(r[0]) for r in rows] == [8, 16, 32]  # up to 4x the rig
    table = np.array([[float(x) for x in r[1:]] for r in rows])
    assert np.all(table > 0)
    np.testing.assert_allclose(table[:, :3].sum(1), table[:, 3], atol=0.011)  # rounding
    np.testing.assert_allclose([float(x) for x in best[:3]], table[:, :3].min(0))
    floor = float(best[3])
    steps = float(re.search(r"per camera \(mean over 8\): ([\d.]+)", out).group(1))
    scipy = float(re.search(r"SciPy lm loop: ([\d.]+)", out).group(1))
    ceiling = float(re.search(r"camera-step\): ([\d.]+)x", out).group(1))
    assert ceiling == pytest.approx(scipy / (steps * floor), rel=0.02, abs=0.06)


def test_suite_smoke_run_writes_its_results_where_asked(tmp_path):
    # `python -m benchmarks --smoke`: the suite end to end at tiny sizes (the parts that have a
    # smoke mode: bound, dlt, triangulate), every path timed against mvcalib; nothing written
    # into the repository's results
    def digest():
        files = sorted((ROOT / "benchmarks" / "results").iterdir())
        return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}

    before = digest()
    env = {**os.environ, "JAX_DISABLE_MOST_OPTIMIZATIONS": "0"}  # the suite compiles as users do
    command = [sys.executable, "-m", "benchmarks", "--smoke", "--results", str(tmp_path)]
    proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["mode"] == "smoke" and not summary["failed"]
    assert {"bound", "dlt", "triangulate"} <= set(summary["parts"])
    rows = summary["summary"]
    assert {r["benchmark"] for r in rows} >= {"DLT + decomposition", "triangulation"}
    assert all(r["us"] > 0 for r in rows)
    assert any(r["path"] == "mvcalib" and r["peer_over_mvcalib"] == 1.0 for r in rows)
    assert (tmp_path / "summary.png").stat().st_size > 0
    assert digest() == before


def test_first_call_times_fresh_processes_against_opencv(tmp_path, monkeypatch, capsys):
    # two tiny rigs of refine=True, each in its own fresh process with the persistent caches
    # off, against OpenCV's loop timed on 4 cameras (and scaled to 8); the break-even from them
    first_call = benchmark_module("first_call")
    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path)
    payload = first_call.main(["--only", "refine", "--cameras", "4,8", "--opencv-cameras", "4"])
    assert json.loads((tmp_path / "first_call.json").read_text()) == json.loads(json.dumps(payload))
    rows = payload["results"]
    assert [(r["task"], r["n_cameras"]) for r in rows] == [
        ("refine", 4), ("refine", 8), ("opencv", 4), ("opencv", 8),
    ]  # fmt: skip
    for r in rows:
        assert r["ok"] == r.get("cameras_timed", r["n_cameras"]), r
        assert 0 < r["startup_s"] < r["import_s"] < r["first_answer_s"] < r["exit_s"], r
        assert r["first_answer_s"] == pytest.approx(r["import_s"] + r["call_s"])
        if r["task"] == "refine":  # this checkout's mvcalib, its caches off
            assert r["mvcalib"].startswith(str(ROOT)) and not r["cache_enabled"]
    opencv = {r["n_cameras"]: r for r in rows if r["task"] == "opencv"}
    assert opencv[8]["cameras_timed"] == 4
    assert opencv[8]["call_s"] == pytest.approx(2 * opencv[8]["call_timed_s"])
    # both fit the same model to the same points: the same minimum, up to float32 rounding
    refine = {r["n_cameras"]: r for r in rows if r["task"] == "refine"}
    assert refine[4]["median_rms_px"] == pytest.approx(opencv[4]["median_rms_px"], rel=1e-3)
    even = payload["break_even"]
    assert even["mvcalib_refine"]["through"] == even["opencv"]["through"] == [4, 8]
    out = capsys.readouterr().out
    assert "break-even" in out and "cv2.calibrateCamera loop" in out


def test_grid_photos_benchmark_smoke(tmp_path, monkeypatch, capsys):
    # photos of OpenCV's asymmetric circles grid labelled by mvcalib and by findCirclesGrid,
    # clean and cluttered, then through observe_grid in one process and in workers
    grid_photos = benchmark_module("grid_photos")
    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path)
    payload = grid_photos.main(["--smoke"])
    assert json.loads((tmp_path / "grid_photos.json").read_text()) == json.loads(
        json.dumps(payload)
    )
    rows = {(r["sweep"], r["labeller"]): r for r in payload["results"]}
    assert rows["clean", "mvcalib"]["right"] == rows["clutter", "mvcalib"]["right"] == 3
    assert rows["clean", "OpenCV"]["right"] + rows["clean", "OpenCV"]["flagged"] == 3
    assert rows["clean", "mvcalib"]["rms_px_right_views"] < 0.05
    assert all(r["photos_labelled"] == 3 for r in payload["observe_grid_workers"].values())
    assert "OpenCV's time over mvcalib's" in capsys.readouterr().out


def test_fisheye_benchmark_smoke(tmp_path, monkeypatch, capsys):
    # mvcalib's fisheye lens against cv2.fisheye at toy sizes: projection, unprojection, planar
    # calibration and pose refinement, each timed against OpenCV and checked against it
    fisheye = benchmark_module("fisheye")
    monkeypatch.setattr(common, "RESULTS_DIR", tmp_path)
    payload = fisheye.main(["--smoke"])
    assert json.loads((tmp_path / "fisheye.json").read_text()) == json.loads(json.dumps(payload))
    assert payload["mode"] == "quick" and payload["settings"]["mode"] == "smoke"
    rows = {r["path"]: r for r in payload["results"]}
    assert all(r["median_s"] > 0 and r["repeats"] >= 1 for r in rows.values())
    # the same model: OpenCV's pixels and ideal pixels are mvcalib's, up to rounding
    assert rows["cv2.fisheye.projectPoints"]["max_abs_diff_vs_mvcalib_px"] < 1e-9
    assert rows["mvcalib undistort_points"]["max_abs_error_vs_exact_px"] < 1e-9
    assert rows["cv2.fisheye.undistortPoints tight"]["max_abs_diff_vs_mvcalib_px"] < 1e-9
    # the same optimum of the planar calibration; mvcalib from the image size alone
    theirs = rows["cv2.fisheye.calibrate (K guess)"]
    assert rows["mvcalib calibrate_planar"]["ok"] and theirs["rms_rel_diff_vs_mvcalib"] < 1e-6
    assert rows["mvcalib calibrate_planar"]["compile_s"] > 0
    # pose refinement: every camera converges; solvePnP minimises on the normalised plane, so
    # its pixel RMS is never below mvcalib's while its own cost is never above
    C = payload["settings"]["refinement"]["n_cameras"]
    pose, pnp = rows["mvcalib refine pose"], rows["cv2.fisheye.solvePnP loop"]
    assert pose["ok"] == C and pose["rms_report_vs_projection_max_abs_diff_px"] < 1e-9
    assert pnp["cameras_with_rms_below_mvcalib"] == 0
    assert pnp["cameras_with_normalised_cost_at_most_mvcalib"] == C
    assert pnp["rotation_max_diff_vs_mvcalib_rad"] < 0.05
    cloud = payload["details"]["refinement"]["cv2_fisheye_calibrate_on_3d_cloud"]
    assert cloud["raised"] + cloud["finished"] == cloud["cameras"] > 0
    assert payload["summary"] and all(r["us"] > 0 for r in payload["summary"])
    mvcalib_rows = [r for r in payload["summary"] if r["path"].startswith("mvcalib")]
    assert mvcalib_rows and all(r["peer_over_mvcalib"] == 1.0 for r in mvcalib_rows)
    assert "peer/mvcalib" in capsys.readouterr().out
