"""The API reference (mkdocs.yml, docs/api/*.md) builds without a warning and lists every name
in `mvcalib.__all__`; `__all__` lists every public name.

mkdocstrings reads the docstrings from the source (griffe: no import of JAX), so the build takes
a few seconds. Build it by hand with `mkdocs build --strict` (into site/) or `mkdocs serve`.
"""

import importlib.util
import pathlib
import re
import subprocess
import sys

import pytest

import mvcalib as mc

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Modules without a leading underscore that are not Python API: the command line and its demo.
NOT_API = {"cli", "demo"}


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """`mkdocs build --strict` into a temporary directory: (site directory, completed process)."""
    needed = ("mkdocs", "mkdocstrings", "mkdocstrings_handlers.python")
    missing = [name for name in needed if importlib.util.find_spec(name) is None]
    if missing:
        pytest.fail(
            f"{', '.join(missing)} not installed; the docs build needs the dev extra: "
            "pip install -e '.[dev]'",
            pytrace=False,
        )
    site = tmp_path_factory.mktemp("site")
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)]
    run = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    return site, run


def test_api_reference_builds_without_warnings(build):
    _, run = build
    output = run.stdout + run.stderr
    assert run.returncode == 0, output
    assert "WARNING" not in output, output


def test_api_reference_lists_every_public_name(build):
    site, run = build
    assert run.returncode == 0, run.stdout + run.stderr
    pages = list((site / "api").rglob("*.html"))
    ids = {i for page in pages for i in re.findall(r'\bid="([^"]+)"', page.read_text())}
    missing = [name for name in mc.__all__ if f"mvcalib.{name}" not in ids]
    assert not missing, f"not in docs/api/*.md (add `::: mvcalib.NAME`): {missing}"


def test_all_lists_every_public_name():
    """What `dir(mvcalib)` shows in a fresh process, and every public submodule, is in `__all__`
    (the module's own imports, `typing` and the like, are not mvcalib's names)."""
    code = (
        "import __future__, types, mvcalib\n"
        "def ours(value):\n"
        "    if isinstance(value, types.ModuleType):\n"
        "        return value.__name__.startswith('mvcalib.')\n"
        "    return not isinstance(value, __future__._Feature)\n"
        "print(*[n for n in dir(mvcalib) if n[0] != '_' and ours(vars(mvcalib).get(n))])\n"
    )
    listed = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    ).stdout.split()
    assert sorted(listed) == sorted(mc.__all__)
    submodules = {p.stem for p in (ROOT / "mvcalib").glob("*.py") if not p.stem.startswith("_")}
    assert submodules - NOT_API <= set(mc.__all__)
