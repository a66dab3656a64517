"""Calibration targets: the paper's 19-dot object as dots on the three faces of a box corner."""

from __future__ import annotations

import dataclasses
import functools
import itertools

import numpy as np

__all__ = [
    "Target", "from_file", "dot_grid", "plate", "box_corner", "box_corner_grid",
    "BOX_CORNER_FIDUCIALS", "check_target",
]  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Target:
    """A calibration object: dot centres in its own (local) frame.

    **Fields:**

    - `name`: a label.
    - `points`: dot centres `(M, 3)` in the local frame, in `units`.
    - `dot_radius`: radius of the printed dots, in `units`: one number, or one per dot `(M,)`.
    - `global_ids`: indices of the dots whose coordinates were also measured in the global (room)
      frame (the paper measures 18 of its 19).
    - `local_to_global`: the 4 x 4 matrix of the known placement `Y = R X + T` used for
      `global_points`.
    - `fiducials`: indices of the dots printed larger than the rest. Their sizes are what lets
      `mvcalib.label_dots` tell which detected blob is which dot without a human (see there).
    - `ids`: `(M,)` int, each dot's id as the user knows it (a target file's first column;
      clicked seeds name dots by it, `mvcalib.match_dots`); default `0 .. M-1`.
    """

    name: str
    points: np.ndarray
    dot_radius: float
    global_ids: np.ndarray
    local_to_global: np.ndarray
    units: str = "mm"
    fiducials: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=int))
    ids: np.ndarray | None = None

    def __post_init__(self):
        ids = np.arange(len(self.points)) if self.ids is None else np.asarray(self.ids)
        if ids.shape != (len(self.points),) or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"`ids` must be {len(self.points)} integers, one per dot.")
        if len(np.unique(ids)) != len(ids):
            values, counts = np.unique(ids, return_counts=True)
            shared = values[counts > 1][0]
            rows = np.flatnonzero(ids == shared).tolist()
            raise ValueError(
                f"`ids` must be distinct: dots {rows} (from 0, in the target's order; a file's "
                f"lines without its header) share the id {shared}."
            )
        object.__setattr__(self, "ids", ids)

    def index(self, ids) -> np.ndarray:
        """The positions in `points` of the dots with these `ids`; ValueError for an unknown id.

        **Example:**

        ```python
        >>> import numpy as np, mvcalib as mc
        >>> t = mc.targets.Target("t", np.eye(3), 1.0, np.arange(3), np.eye(4), ids=[7, 3, 5])
        >>> t.index([5, 7]).tolist()
        [2, 0]

        ```
        """
        ids = np.asarray(ids).reshape(-1)
        order = np.argsort(self.ids)
        where = np.searchsorted(self.ids, ids, sorter=order)
        where = order[np.minimum(where, len(order) - 1)]
        unknown = ids[self.ids[where] != ids]
        if len(unknown):
            raise ValueError(f"no dot of target {self.name!r} has the id {int(unknown[0])}.")
        return where

    @property
    def radii(self) -> np.ndarray:
        """The radius of every dot, `(M,)`."""
        return np.broadcast_to(np.asarray(self.dot_radius, dtype=float), (len(self.points),))

    @property
    def global_points(self) -> np.ndarray:
        """The `global_ids` dots in the global frame, `(len(global_ids), 3)`."""
        X = self.points[self.global_ids]
        return X @ self.local_to_global[:3, :3].T + self.local_to_global[:3, 3]

    @property
    def center(self) -> np.ndarray:
        return self.points.mean(axis=0)

    def __len__(self) -> int:
        return len(self.points)


def check_target(
    value,
    name: str = "`target`",
    example: str = "mc.targets.box_corner() or mc.targets.from_file(path)",
) -> None:
    """Refuse what is not a `Target` (an array of its points is a common slip), saying how to
    make one."""
    if not isinstance(value, Target):
        raise TypeError(
            f"{name} is an mvcalib.targets.Target, e.g. {example}; got {type(value).__name__}."
        )


def from_file(path, *, dot_radius: float = float("nan"), units: str = "mm") -> Target:
    r"""A target from a text file: one dot per line, `id x y z` (whitespace, as OpenPTV's
    `target_on_a_side.txt`), or CSV with a header naming `id,x,y,z` (any order, other columns
    ignored). The file's ids are kept as `target.ids`; `global_ids` are all dots and the placement
    is the identity (the file's frame is the world's).

    **Example:**

    ```python
    >>> import pathlib, tempfile, mvcalib as mc
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "target.txt"
    >>> _ = path.write_text("1 -40 -25 8\n2 -40 0 -8\n5 -35 -15 0\n")
    >>> target = mc.targets.from_file(path)
    >>> target.ids.tolist(), target.points[1].tolist()
    ([1, 2, 5], [-40.0, 0.0, -8.0])

    ```
    """
    import pathlib

    from .io import ENCODING

    path = pathlib.Path(path)
    try:
        text = path.read_text(encoding=ENCODING)
    except UnicodeDecodeError:  # (an image given as the target: "'utf-8' codec can't decode")
        raise ValueError(
            f"{path} is not a target file (text: `id x y z` per line, or CSV with a header)."
        ) from None
    if not text.strip():
        raise ValueError(f"target file {path} is empty.")
    first = text.lstrip().split("\n", 1)[0]
    delimiter = "," if "," in first else None
    try:
        try:  # a first line of numbers is data; anything else is a header
            [float(x) for x in first.split(delimiter)]
            header = None
        except ValueError:
            header = [n.strip().lower() for n in first.split(delimiter)]
        if header is not None:  # checked first: a mistyped number makes line 1 no header
            missing = [n for n in ("id", "x", "y", "z") if n not in header]
            if missing:
                raise ValueError(
                    f"line 1 is neither numbers nor a header naming id, x, y, z (no {missing[0]!r})"
                )
        rows = np.loadtxt(path, delimiter=delimiter, skiprows=int(header is not None), ndmin=2)
        if header is not None:
            rows = rows[:, [header.index(n) for n in ("id", "x", "y", "z")]]
    except ValueError as error:
        raise ValueError(f"cannot read target file {path}: {error}") from None
    if rows.ndim != 2 or rows.shape[1] < 4 or len(rows) == 0:
        raise ValueError(f"target file {path}: expected lines of `id x y z`; got {rows.shape}.")
    ids = rows[:, 0]
    if not np.all(ids == np.round(ids)):
        raise ValueError(f"target file {path}: the first column (the dot ids) must be integers.")
    if not np.all(np.isfinite(rows[:, 1:4])):
        raise ValueError(f"target file {path}: a coordinate is not a finite number.")
    return Target(
        name=path.stem,
        points=rows[:, 1:4].astype(float),
        dot_radius=dot_radius,
        global_ids=np.arange(len(rows)),
        local_to_global=np.eye(4),
        units=units,
        ids=ids.astype(int),
    )


def dot_grid(
    rows: int,
    cols: int,
    spacing: float,
    *,
    asymmetric: bool = False,
    markers=(),
    marker_scale: float = 1.6,
    dot_radius: float | None = None,
    units: str = "mm",
) -> Target:
    """A printed grid of `rows x cols` dots on the plane z = 0, `spacing` apart (ids row by row).
    `asymmetric=True` is OpenCV's asymmetric circles grid: every other row shifted by half a
    spacing, rows half a spacing apart. The dots' radius defaults to a fifth of the spacing.

    `markers`: ids of dots printed `marker_scale` times larger (the target's `fiducials`), from
    which `mvcalib.label_grid` tells the grid's orientation: without them a symmetric grid is
    labelled up to its half turn (and a square one up to its quarter turns), which keeps one
    camera's planar calibration but not the dots' identity across the cameras of a rig. They
    must look different after every turn or mirroring that maps the grid onto itself (which
    side of the board a camera sees is told by them too), e.g. four dots in an L with unequal
    arms at one corner, `(0, 1, 2, cols)`.

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> grid = mc.targets.dot_grid(3, 4, 10.0)
    >>> grid.points.shape, grid.points[5].tolist()
    ((12, 3), [10.0, 10.0, 0.0])

    ```
    """
    rows, cols = int(rows), int(cols)
    if rows < 2 or cols < 2 or not spacing > 0:
        raise ValueError(f"a dot grid needs rows, cols >= 2 and spacing > 0; got {rows, cols}.")
    r, c = (x.ravel() for x in np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij"))
    x = (c + 0.5 * (r % 2) * asymmetric) * spacing
    y = r * spacing * (0.5 if asymmetric else 1.0)
    points = np.c_[x, y, np.zeros_like(x)].astype(float)
    name = f"{'asymmetric ' if asymmetric else ''}dot grid {rows} x {cols}"
    grid = _printed(name, points, spacing, dot_radius, units)
    markers = _marker_ids(markers, rows * cols)
    if not len(markers):
        return grid
    moves = _grid_symmetries(rows, cols, asymmetric)
    moved = [np.sort(move[markers]) for move in moves if np.any(move != np.arange(len(move)))]
    if any(np.array_equal(ids, markers) for ids in moved):
        raise ValueError(
            f"the markers {markers.tolist()} look the same after a turn or a mirroring of the "
            "grid, so they cannot tell its orientation: e.g. four dots in an L with unequal "
            "arms at one corner, (0, 1, 2, cols)."
        )
    radius = np.where(np.isin(np.arange(rows * cols), markers), marker_scale, 1.0) * grid.radii
    return dataclasses.replace(grid, dot_radius=radius, fiducials=markers)


def _marker_ids(markers, M: int) -> np.ndarray:
    """A grid's `markers` as sorted distinct dot ids; ValueError for one outside `0 .. M-1`."""
    markers = np.unique(np.asarray(markers, dtype=int).reshape(-1))
    if len(markers) and (markers.min() < 0 or markers.max() >= M):
        raise ValueError(f"`markers` are dot ids, 0 to {M - 1}; got {markers.tolist()}.")
    return markers


def _grid_lattice(rows: int, cols: int, asymmetric: bool = False) -> np.ndarray:
    """A dot grid's dots (ids row by row) as integer coordinates `(M, 2)` in a basis of its
    shortest displacements, turning as the board's x towards its y: `(col, row)`; for an
    asymmetric grid, whose nearest neighbours are diagonal, `(u, v)` with `x = (u - v) s / 2`
    and `y = (u + v) s / 2` for spacing `s`."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    if not asymmetric:
        return np.c_[c, r]
    x = 2 * c + r % 2  # (in half spacings)
    return np.c_[(r + x) // 2, (r - x) // 2]


# The integer 2 x 2 maps of determinant +-1 with entries up to 3: those that take one basis of a
# lattice to another (of vectors short enough to be a grid's nearest neighbours in a photo).
_UNIMODULAR = np.array(
    [u for u in itertools.product(range(-3, 4), repeat=4) if abs(u[0] * u[3] - u[1] * u[2]) == 1]
).reshape(-1, 2, 2)


def _placements(keys: np.ndarray, lattice: np.ndarray, slack: int = 0):
    """Every way the integer points `keys (n, 2)` lie on a grid's `lattice (M, 2)`
    (`_grid_lattice`), all but at most `slack` of them: a map of `_UNIMODULAR`, then a shift,
    that takes them onto distinct dots (those left over a step outside the grid at most).

    **Returns:** under each placement, the dot id of every key, -1 where it is off the grid,
    `(P, n)`; each placement's determinant `(P,)` (+1 keeps the keys' handedness: the board seen
    from the side they assume; -1 mirrors it); and how many keys each leaves off the grid `(P,)`.
    `_placements(lattice, lattice)[0]` are the grid's symmetries (`_grid_symmetries`).
    """
    keys, lattice = np.asarray(keys, int).reshape(-1, 2), np.asarray(lattice, int)
    pad = int(slack > 0)  # (keys a step beyond the grid, off it)
    lo, size = lattice.min(0) - pad, lattice.max(0) - lattice.min(0) + 1 + 2 * pad
    where = np.full(size, -1)
    where[tuple((lattice - lo).T)] = np.arange(len(lattice))
    ids, dets = [], []
    for U in _UNIMODULAR:
        moved = keys @ U.T
        free = size - (moved.max(0) - moved.min(0) + 1)  # how far the keys' box can shift
        if np.any(free < 0):
            continue
        shifts = np.stack(np.meshgrid(*map(np.arange, free + 1), indexing="ij"), -1)
        at = (moved - moved.min(0)) + shifts.reshape(-1, 1, 2)  # (shifts, n, 2)
        ids.append(where[at[..., 0], at[..., 1]])
        dets += [round(np.linalg.det(U))] * len(at)
    ids = np.concatenate(ids) if ids else np.zeros((0, len(keys)), int)
    off = np.sum(ids < 0, axis=-1)
    keep = off <= slack
    return ids[keep], np.array(dets, int).reshape(-1)[keep], off[keep]


@functools.cache
def _grid_symmetries(rows: int, cols: int, asymmetric: bool = False) -> np.ndarray:
    """The moves of a grid onto itself `(S, M)`, each as the ids its dots move to (the identity
    among them): `_placements` of its lattice on itself, once a layout (`label_grid` asks for
    every photo)."""
    lattice = _grid_lattice(rows, cols, asymmetric)
    moves = _placements(lattice, lattice)[0]
    moves.flags.writeable = False  # (shared by every caller)
    return moves


def _grid_turns(rows: int, cols: int, asymmetric: bool = False) -> int:
    """How many of the grid's moves onto itself (`_grid_symmetries`) are turns in its plane,
    the identity among them, not mirror images: with more than one, a photo's orientation
    alone fixes its dots' ids only up to them (markers fix them)."""
    lattice = _grid_lattice(rows, cols, asymmetric).astype(float)
    design = np.c_[lattice, np.ones(len(lattice))]
    turns = 0
    for move in _grid_symmetries(rows, cols, asymmetric):
        A = np.linalg.lstsq(design, lattice[move], rcond=None)[0][:2]
        turns += np.linalg.det(A) > 0
    return int(turns)


def _layout(target: Target) -> tuple[int, int, bool]:
    """`(rows, cols, asymmetric)` of a grid made by `dot_grid` (ids row by row); ValueError for
    any other target."""
    points = np.asarray(target.points, float)
    ys = np.unique(np.round(points[:, 1] - points[0, 1], 9))
    rows = len(ys)
    cols = len(points) // max(rows, 1)
    for asymmetric in (False, True):
        if rows < 2 or cols < 2 or rows * cols != len(points):
            break
        spacing = (ys[1] - ys[0]) * (2.0 if asymmetric else 1.0)
        grid = dot_grid(rows, cols, spacing, asymmetric=asymmetric).points + points[0]
        if np.allclose(points, grid, rtol=0.0, atol=1e-9 * spacing * (rows + cols)):
            return rows, cols, asymmetric
    raise ValueError(f"{target.name!r} is not a grid of dots (`mvcalib.targets.dot_grid`).")


def plate(
    rows: int,
    cols: int,
    spacing: float,
    *,
    levels=(0.0, -2.0),
    dot_radius: float | None = None,
    units: str = "mm",
) -> Target:
    """A PIV calibration plate: a `rows x cols` dot grid on each of several levels (z =
    `levels[k]`, facing +z), each level's grid shifted by `spacing / len(levels)` in x and y from
    the one before, so that no dot hides another seen from above (as on two-level plates). Ids
    level by level, row by row.

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> p = mc.targets.plate(2, 3, 5.0)
    >>> len(p), sorted(set(p.points[:, 2].tolist()))
    (12, [-2.0, 0.0])

    ```
    """
    grid = dot_grid(rows, cols, spacing).points
    shift = spacing / len(levels)
    points = np.concatenate(
        [grid + [k * shift, k * shift, float(z)] for k, z in enumerate(levels)], axis=0
    )
    name = f"plate of {len(levels)} levels, {rows} x {cols} dots each"
    return _printed(name, points, spacing, dot_radius, units)


def _printed(name, points, spacing, dot_radius, units) -> Target:
    """A generated target in its own frame (all dots global, the identity placement); dots a
    fifth of the spacing in radius unless given."""
    return Target(
        name=name,
        points=points,
        dot_radius=0.2 * spacing if dot_radius is None else float(dot_radius),
        global_ids=np.arange(len(points)),
        local_to_global=np.eye(4),
        units=units,
    )


def box_corner_grid(n: int = 6, size: float = 200.0) -> Target:
    """A denser box corner: an `n x n` grid of dots on each of its three faces (`3 n^2` dots).

    Enough points to refine a camera with lens distortion from one view (the 19-dot target is
    too sparse to separate distortion from the pose). All dots have global coordinates under
    the same placement as `box_corner`.

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> mc.targets.box_corner_grid(6).points.shape
    (108, 3)

    ```
    """
    g = (np.arange(n) + 0.75) * size / (n + 0.5)
    u, v = (x.ravel() for x in np.meshgrid(g, g))
    zero = np.zeros_like(u)
    points = np.concatenate([np.c_[u, v, zero], np.c_[u, zero, v], np.c_[zero, u, v]], axis=0)
    corner = box_corner(size)
    return Target(
        name=f"box corner, {n}x{n} dots per face",
        points=points,
        dot_radius=0.25 * size / (n + 0.5),
        global_ids=np.arange(len(points)),
        local_to_global=corner.local_to_global,
    )


# Eight dots, three on two faces and two on the third, none next to the corner (where grazing
# views can merge dot images) and no two side by side (so that every dot has small neighbours
# to be compared with). Any six of them visible determine the camera: up to two may be hidden.
BOX_CORNER_FIDUCIALS = (1, 3, 5, 8, 9, 13, 15, 17)


def box_corner(size: float = 200.0, *, fiducial_scale: float = 1.75) -> Target:
    """The paper's 19-dot target, made non-coplanar by putting it on the inside of a box corner.

    Three faces meet at the local origin: the floor `z = 0`, the wall `y = 0` and the wall `x = 0`,
    each `size` wide. Each face carries a 3 x 2 grid of dots (18 dots, ids 0–17, measured in both
    frames as in the paper) and the corner itself is dot 18. Seen from anywhere in the positive
    octant all three faces are visible, and the dots lie on three planes, far from coplanar, so
    eight dots spread over the faces already determine a camera.

    Eight dots (`BOX_CORNER_FIDUCIALS`) are printed `fiducial_scale` times larger
    than the others: the fiducials from which `mvcalib.label_dots` finds which blob is which dot.
    The paper identified its dots by hand and printed them all alike (`fiducial_scale=1`).

    **Example:**

    ```python
    >>> import mvcalib as mc
    >>> target = mc.targets.box_corner()
    >>> target.points.shape, target.global_points.shape
    ((19, 3), (18, 3))

    ```
    """
    a, b, c = 0.2 * size, 0.5 * size, 0.8 * size
    rows, cols = (a, 0.6 * size), (a, b, c)
    floor = [(u, v, 0.0) for v in rows for u in cols]
    wall_y = [(u, 0.0, v) for v in rows for u in cols]
    wall_x = [(0.0, u, v) for v in rows for u in cols]
    points = np.array(floor + wall_y + wall_x + [(0.0, 0.0, 0.0)], dtype=float)
    # A placement in the room: rotated 30 degrees about the vertical, 1.2 m from the room origin.
    angle = np.deg2rad(30.0)
    R = np.array(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1.0]]
    )
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, (1200.0, 300.0, 750.0)
    return Target(
        name="box corner, 19 dots",
        points=points,
        dot_radius=np.where(np.isin(np.arange(19), BOX_CORNER_FIDUCIALS), fiducial_scale, 1.0)
        * 0.04
        * size,
        global_ids=np.arange(18),
        local_to_global=M,
        fiducials=np.array(BOX_CORNER_FIDUCIALS) if fiducial_scale != 1 else np.zeros(0, int),
    )
