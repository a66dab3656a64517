import re
import subprocess
import sys

import pytest


def run(*args, timeout=300):
    return subprocess.run(
        [sys.executable, "-m", "mvcalib", *args], capture_output=True, text=True, timeout=timeout
    )


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
        r"^\s+(\d)\s+(-?[\d.]+)\s+(-?[\d.]+)\s+([\d.]+)\s+([\d.]+)\s+8$", result.stdout, re.M
    )
    assert len(rows) == 4  # Table I: four cameras, 8 calibration points each
    assert all(0.05 < float(r[3]) < 0.6 for r in rows)  # RMS near the 0.3 px noise


def test_bad_usage_exits_2_with_one_line():
    for args in (
        ["demo", "--noise", "abc"],
        ["demo", "--bogus"],
        ["frobnicate"],
        ["demo", "--noise", "-1"],
    ):
        result = run(*args)
        assert result.returncode == 2, args
        assert "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert run().returncode == 2


def test_help_has_examples():
    result = run("--help")
    assert result.returncode == 0 and "examples:" in result.stdout and "demo" in result.stdout


def test_compilation_cache_goes_where_asked(tmp_path, monkeypatch):
    monkeypatch.setenv("MVCALIB_COMPILATION_CACHE", str(tmp_path / "cache"))
    result = run("demo", "--noise-free")
    assert result.returncode == 0, result.stderr
    assert any((tmp_path / "cache").iterdir())


def test_measured_global_coordinates_show_the_papers_r_is_not_a_rotation():
    result = run("demo", "--global-noise", "0.5")
    assert result.returncode == 0, result.stderr
    paper = re.search(r"paper eqs\. 25-28 .* max \|R\^T R - I\| = ([\d.e+-]+)", result.stdout)
    ours = re.search(r"Procrustes \(default\) .* max \|R\^T R - I\| = ([\d.e+-]+)", result.stdout)
    assert float(paper.group(1)) > 1e-3 and float(ours.group(1)) < 1e-12
