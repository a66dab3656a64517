"""Everything the README shows runs, and prints what it says.

Every ```python block runs in a process of its own, in the README's order, in one temporary
directory shared by the whole file: the recipes write files there (photos, a rig, tracks,
observations) that the command-line examples read. Every line of a ```bash block runs with bash
in that directory after the Python blocks above it, except the install commands: their test
command must be exactly the one CI runs (`.ci/run`), and what they run after installing (the
demo) runs here. `mvcalib` and `python` resolve to this interpreter's environment.
"""

import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TEXT = README.read_text()
BLOCKS = re.findall(r"^```(\w*)\n(.*?)^```", TEXT, re.S | re.M)  # (language, code), in order
PYTHON = [i for i, (lang, _) in enumerate(BLOCKS) if lang == "python"]
TIMEOUT = 300  # seconds, per block or command (most take 3-15 s)
INSTALL = re.compile(r"python -m venv .*?pip install [^&]*&& (.*)")


def _commands():
    """(block index, command) for every command line of the bash blocks; an install line gives
    what it runs after installing, unless that is the test suite itself."""
    out = []
    for i, (lang, code) in enumerate(BLOCKS):
        if lang != "bash":
            continue
        for line in code.splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            install = INSTALL.fullmatch(line)
            if install:
                if "pytest" in install.group(1):
                    continue  # checked against .ci/run instead
                line = install.group(1)
            out.append((i, line))
    return out


COMMANDS = _commands()
COMMAND_IDS = [command.split(" #")[0].rstrip() for _, command in COMMANDS]


def _block_with(text: str) -> int:
    """The index of the one Python block that contains `text`."""
    found = [i for i in PYTHON if text in BLOCKS[i][1]]
    assert len(found) == 1, f"{len(found)} Python blocks of the README contain {text!r}"
    return found[0]


class Readme:
    """Runs the README's blocks once each, in its working directory, and remembers the results."""

    def __init__(self, cwd: pathlib.Path, cache_home: pathlib.Path):
        self.cwd = cwd
        path = os.pathsep.join([str(pathlib.Path(sys.executable).parent), os.environ["PATH"]])
        self.env = {**os.environ, "PATH": path, "XDG_CACHE_HOME": str(cache_home)}
        if "JAX_COMPILATION_CACHE_DIR" in os.environ:  # the suite's cache (conftest.py): the CLI's
            self.env["MVCALIB_COMPILATION_CACHE"] = os.environ["JAX_COMPILATION_CACHE_DIR"]
        self.done: dict[int, subprocess.CompletedProcess] = {}

    def python(self, i: int) -> subprocess.CompletedProcess:
        if i not in self.done:
            self.done[i] = subprocess.run(
                [sys.executable, "-c", BLOCKS[i][1]],
                cwd=self.cwd,
                env=self.env,
                capture_output=True,
                text=True,
                timeout=TIMEOUT,
            )
        return self.done[i]

    def python_before(self, block: int):
        """Run every Python block above `block` (the files they write), each successfully."""
        for i in PYTHON:
            if i < block:
                run = self.python(i)
                assert run.returncode == 0, f"README block {i} failed:\n{run.stderr[-3000:]}"

    def shell(self, command: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["bash", "-c", command],
            cwd=self.cwd,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=TIMEOUT,
        )


@pytest.fixture(scope="module")
def readme(tmp_path_factory):
    return Readme(tmp_path_factory.mktemp("readme"), tmp_path_factory.mktemp("xdg_cache"))


def test_readme_has_only_python_and_bash_blocks_and_both():
    """A block in another language would not be run here."""
    assert {lang for lang, _ in BLOCKS} == {"python", "bash"}, [lang for lang, _ in BLOCKS]
    assert len(PYTHON) >= 7 and len(COMMANDS) >= 7


@pytest.mark.parametrize("i", PYTHON, ids=[f"block{i}" for i in PYTHON])
def test_readme_python_block_runs(readme, i):
    run = readme.python(i)
    assert run.returncode == 0, f"README block {i}:\n{BLOCKS[i][1]}\n{run.stderr[-3000:]}"


@pytest.mark.parametrize("block, command", COMMANDS, ids=COMMAND_IDS)
def test_readme_command_runs(readme, block, command):
    """Exit code 0, every file it says it writes written, and every "n of m cameras / images /
    points" it reports with n = m (all of them calibrated, labelled, triangulated)."""
    readme.python_before(block)
    run = readme.shell(command)
    output = run.stdout + run.stderr
    assert run.returncode == 0, f"{command}\n{output[-3000:]}"
    for option in ("--out", "--plot", "--save"):
        for path in re.findall(rf"{option} (\S+)", command):
            written = readme.cwd / path
            assert written.exists() and (written.is_dir() or written.stat().st_size > 0), path
    counts = re.findall(r"\b(\d+) of (\d+) (?:cameras|images|points)\b", output)
    assert all(a == b for a, b in counts), output[-3000:]
    if command.startswith("python -m mvcalib demo"):
        assert "Table I" in run.stdout and "fixed room point" in run.stdout


def test_readme_links_point_to_files():
    """Every relative link and image of the README names a file of the repository (and an anchor
    into a Markdown file, one of its headings)."""
    links = re.findall(r"\]\(([^)\s]+)\)", TEXT)
    assert links
    for link in links:
        if re.match(r"[a-z]+://", link):
            continue
        path, _, anchor = link.partition("#")
        assert (ROOT / path).exists(), link
        if anchor:
            headings = re.findall(r"^#+ (.*)$", (ROOT / path).read_text(), re.M)
            slugs = {re.sub(r"[^a-z0-9 _-]", "", h.lower()).strip() for h in headings}
            slugs = {s.replace(" ", "-") for s in slugs}
            assert anchor in slugs, link


def test_ci_runs_exactly_the_readme_test_command():
    command = re.search(r"# install and run the tests.*\n(.*)\n", TEXT).group(1)
    ci = (ROOT / ".ci" / "run").read_text()
    assert command.strip() in ci.splitlines()
    demo = re.search(r"# install and run the demo.*\n(.*)\n", TEXT).group(1)
    assert INSTALL.fullmatch(demo.strip()).group(1) == "python -m mvcalib demo"


def test_readme_python_example_runs_and_prints_what_it_says(readme):
    run = readme.python(PYTHON[0])
    assert run.returncode == 0, run.stderr
    first = run.stdout.splitlines()[0].split()
    assert first[0] == "True" and abs(float(first[1]) - 0.357) < 0.001
    assert "(1000, 3)" in run.stdout


def test_readme_compilation_cache_example_runs(tmp_path):
    """The cache block turns the cache on where it says (in a process with its own home)."""
    code = BLOCKS[_block_with("enable_compilation_cache")][1]
    check = "\nimport jax\nprint(jax.config.jax_compilation_cache_dir)\n"
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-c", code + check], capture_output=True, text=True, timeout=120, env=env
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == str(tmp_path / "mvcalib" / "jax")
    assert (tmp_path / "mvcalib" / "jax").is_dir()


def test_readme_rig_from_a_moving_board_runs(readme):
    """The calibrate_rig block: every camera calibrated, the table printed, the file written."""
    run = readme.python(_block_with("calibrate_rig"))
    assert run.returncode == 0, run.stderr
    assert "rig of 6 cameras, 60 frames" in run.stdout and "successful" in run.stdout
    assert run.stdout.count(" OK") == 6
    assert (readme.cwd / "observations.csv").read_text().startswith("camera,frame,point,")


def test_readme_photographs_are_calibrated(readme):
    """Every rendered photo labelled and calibrated; the focal lengths within 0.1 % of the truth."""
    run = readme.python(_block_with("calibrate_images"))
    assert run.returncode == 0, run.stderr
    assert run.stdout.count("calibrated") == 4
    assert float(run.stdout.split()[-1]) < 1e-3
    assert sorted(p.name for p in readme.cwd.glob("cam*.png")) == [f"cam{i}.png" for i in range(4)]


def test_readme_triangulation_is_accurate(readme):
    """All 1000 points ok, within a millimetre RMS (0.3 px noise on a 160 mm cube)."""
    run = readme.python(_block_with("mc.triangulate("))
    assert run.returncode == 0, run.stderr
    ok, rms = run.stdout.split()
    assert ok == "True" and 0 < float(rms) < 1.0


def test_readme_derivative_predicts_the_errors(readme):
    """The first-order standard deviations are positive and the actual focal-length errors lie
    within 4 of them (a wrong or zero derivative fails this)."""
    run = readme.python(_block_with("jax.jacfwd"))
    assert run.returncode == 0, run.stderr
    numbers = [float(x) for x in re.findall(r"-?\d+\.\d*", run.stdout)]
    assert len(numbers) == 16, run.stdout
    std, error = numbers[:8], numbers[8:]
    assert all(s > 0 for s in std)
    assert all(abs(e) <= 4 * s for e, s in zip(error, std)), run.stdout


def test_readme_fisheye_prints_what_it_says(readme):
    """The fisheye block's printed pixel and ray are those in its comment."""
    i = _block_with('lens="fisheye"')
    run = readme.python(i)
    assert run.returncode == 0, run.stderr
    said = BLOCKS[i][1].split("# [[", 1)[1]
    numbers = lambda text: [float(x) for x in re.findall(r"-?\d+\.?\d*", text)]  # noqa: E731
    assert numbers(run.stdout) == numbers("[[" + said)


def test_readme_sharding_splits_the_cameras(readme):
    run = readme.python(_block_with("mc.shard("))
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "2 True [(32, 3, 4), (32, 3, 4)]"


def test_the_api_table_names_every_public_name():
    import mvcalib

    text = README.read_text()
    missing = [name for name in mvcalib.__all__ if f"`{name}`" not in text]
    assert not missing, f"README does not name {missing}"
