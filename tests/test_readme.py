import os
import pathlib
import re
import subprocess
import sys

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs_and_prints_what_it_says():
    code = re.search(r"```python\n(.*?)```", README.read_text(), re.S).group(1)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    first = out.stdout.splitlines()[0].split()
    assert first[0] == "True" and abs(float(first[1]) - 0.357) < 0.001
    assert "(1000, 3)" in out.stdout


def test_ci_runs_exactly_the_readme_test_command():
    text = README.read_text()
    command = re.search(r"# install and run the tests.*\n(.*)\n", text).group(1)
    ci = (README.parent / ".ci" / "run").read_text()
    assert command.strip() in ci


def test_readme_compilation_cache_example_runs(tmp_path):
    """The README's second Python block turns the cache on where it says."""
    code = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)[1]
    assert "enable_compilation_cache" in code
    check = "\nimport jax\nprint(jax.config.jax_compilation_cache_dir)\n"
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-c", code + check], capture_output=True, text=True, timeout=120, env=env
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(tmp_path / "mvcalib" / "jax")
    assert (tmp_path / "mvcalib" / "jax").is_dir()


def test_readme_rig_from_a_moving_board_runs():
    """The README's calibrate_rig block: every camera calibrated, the table printed."""
    code = next(
        c
        for c in re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
        if "calibrate_rig" in c
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "rig of 6 cameras, 60 frames" in out.stdout and "successful" in out.stdout
    assert out.stdout.count(" OK") == 6
