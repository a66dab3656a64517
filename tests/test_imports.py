"""`import mvcalib` is cheap: public names are imported on first use (PEP 562).

No timings here (the machines are noisy); the heavy dependencies staying out of `sys.modules`
is what keeps the import cheap.
"""

import ast
import pathlib
import subprocess
import sys

import mvcalib as mc

HEAVY = ("skimage", "scipy", "matplotlib", "optimistix", "lineax")


def test_import_leaves_heavy_dependencies_out():
    code = (
        "import sys, mvcalib\n"
        f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))\n"
        "print(sorted(m for m in sys.modules if m.startswith('mvcalib.')))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert out == ["[]", "[]"]


def test_photo_workers_import_no_jax():
    """The worker processes that read photos and label grids (`_photos._in_workers`) import
    `_photos` and `_match` only: no JAX, so that each starts in a fraction of a second."""
    code = (
        "import sys, mvcalib._photos, mvcalib._match\n"
        "print(sorted(m for m in ('jax', 'equinox') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["[]"]


def test_a_first_call_takes_lapack_without_the_rest_of_scipy_linalg():
    """jaxlib takes LAPACK from SciPy at its first lowering of an SVD, and imported all of
    `scipy.linalg` for it (70 ms of every first call); mvcalib hands it the two modules it reads
    (`_buckets._lapack_from_scipy`) and leaves `sys.modules` as it was, so that `scipy.linalg`
    imports later as usual."""
    code = (
        "import sys, numpy as np, mvcalib as mc\n"
        "rng = np.random.default_rng(0)\n"
        "world = rng.uniform(-1, 1, (12, 3))\n"
        "K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])\n"
        "h = (K @ (world + [0, 0, 5]).T).T\n"
        "result = mc.calibrate(world, h[:, :2] / h[:, 2:])\n"
        "print(round(float(result.cameras.alpha_u), 2))  # (float32)\n"
        "print(sorted(m for m in sys.modules if m.startswith('scipy.linalg')))\n"
        "import scipy.linalg, scipy.linalg.cython_blas\n"
        "print(scipy.linalg.cython_lapack.__name__, scipy.linalg.svdvals(np.eye(2)).tolist())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == ["800.0", "[]", "scipy.linalg.cython_lapack [1.0, 1.0]"]


def test_a_first_refinement_imports_its_libraries_with_the_collector_paused():
    """Optimistix and Lineax, imported at the first refinement (200-odd classes made), are
    imported with Python's cyclic collector paused, as mvcalib's own modules are (`_gc`), and
    the collector runs again afterwards."""
    code = (
        "import builtins, gc, sys, jax, mvcalib as mc\n"
        "seen, load = {}, builtins.__import__\n"
        "def spy(name, *args, **kwargs):\n"
        "    if name in ('optimistix', 'lineax') and name not in sys.modules:\n"
        "        seen[name] = gc.isenabled()\n"
        "    return load(name, *args, **kwargs)\n"
        "builtins.__import__ = spy\n"
        "rig = mc.synthetic.random_rig(jax.random.key(0), n_cameras=2, noise=0.3)\n"
        "result = mc.calibrate(rig.world, rig.pixels, rig.mask, refine=True)\n"
        "print(sorted(seen.items()), gc.isenabled(), bool(result.ok.all()))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split("\n")[-2] == "[('lineax', False), ('optimistix', False)] True True"


def test_every_public_name_resolves():
    assert len(mc.__all__) == len(set(mc.__all__))
    for name in mc.__all__:
        value = getattr(mc, name)
        assert value is not None
        assert vars(mc)[name] is value  # cached after the first use
    assert mc.io.load_json and mc.synthetic.random_rig and mc.targets.box_corner
    assert mc.Target is mc.targets.Target
    from mvcalib import Camera, SecantLM, calibrate

    assert (Camera, SecantLM, calibrate) == (mc.Camera, mc.SecantLM, mc.calibrate)


def test_dir_lists_public_names():
    listed = dir(mc)
    assert set(mc.__all__) <= set(listed)
    assert listed == sorted(listed)


def test_unknown_names_raise_attribute_error():
    try:
        mc.no_such_name  # noqa: B018
    except AttributeError as error:
        assert "no_such_name" in str(error)
    else:
        raise AssertionError("mvcalib.no_such_name resolved")
    from mvcalib import cli  # a submodule outside `__all__` still imports as one

    assert cli.main is mc.cli.main


def test_type_checking_imports_match_the_lazy_table():
    """The imports that type checkers see name the same modules as the runtime table."""
    tree = ast.parse(pathlib.Path(mc.__file__).read_text())
    (block,) = [
        node
        for node in tree.body
        if isinstance(node, ast.If) and ast.unparse(node.test) == "typing.TYPE_CHECKING"
    ]
    seen = {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.level == 1
        for alias in node.names:
            assert alias.asname == alias.name  # `import x as x`: a re-export
            seen[alias.name] = node.module or alias.name
    table = {name: name for name in mc._SUBMODULES}
    table.update(mc._ORIGIN)
    assert seen == table
    assert sorted(seen) == sorted(mc.__all__)
