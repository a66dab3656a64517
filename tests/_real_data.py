"""Readers of the real data sets (../shared/data, see its SOURCE.md), shared by the tests and
benchmarks/real_data.py. NumPy and mvcalib only: importing this module leaves JAX's
configuration alone (conftest.py sets the tests' own: no XLA optimisation, older emitters, a
persistent compilation cache), so that a benchmark can use it and still measure what users
run."""

import numpy as np

import mvcalib as mc


def read_oxford_house(root):
    """Oxford VGG's Model House in the folder `root`: `(world (672, 3), pixels (10, 672, 2),
    P (10, 3, 4))`, NaN where a view does not see a corner."""
    world = np.loadtxt(root / "3D" / "house.p3d")
    rows = [line.split() for line in (root / "2D" / "house.nview-corners").read_text().splitlines()]
    P, views = [], []
    for v in range(10):
        corners = np.loadtxt(root / "2D" / f"house.{v:03d}.corners")
        idx = np.array([int(r[v]) if r[v] != "*" else -1 for r in rows])
        pixels = np.where((idx >= 0)[:, None], corners[np.maximum(idx, 0)], np.nan)
        P.append(np.loadtxt(root / "3D" / f"house.{v:03d}.P"))
        views.append(pixels)
    return world, np.stack(views), np.stack(P)


def cavity_clicks(root, path, rows=None):
    """OpenPTV's clicked dots of the cavity in the folder `root` (`man_ori`), written to `path`
    as the CLI's clicks file (`image,dot_id,pixel_x,pixel_y`), with `rows` appended."""
    ids, pixels = mc.io.load_openptv_clicks(
        root / "parameters" / "man_ori.par", root / "parameters" / "man_ori.dat"
    )
    lines = ["image,dot_id,pixel_x,pixel_y"]
    for c in range(4):
        lines += [f"cam{c + 1}.tif,{i},{x},{y}" for i, (x, y) in zip(ids[c], pixels[c])]
    path.write_text("\n".join(lines + (rows or [])) + "\n")
    return path
