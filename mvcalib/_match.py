"""Seeded labelling: which detected blob is which dot of any target, from a rough start.

`label_dots` needs a target with enlarged fiducial dots. Every other target (a file of dot
coordinates, an OpenPTV or MyPTV target, a printed grid) is labelled from a *seed*: a rough
camera, or a few dots whose pixels a person clicked. From the seed,

1. **A first camera.** Six or more clicked dots, not coplanar: the DLT of the clicks. Four or
   five (or coplanar ones): their pose for a focal-length guess in pixels (the principal point
   at the image centre), from the homography of the clicks' best-fitting plane and then
   Levenberg–Marquardt on all the clicks (`mvcalib.refine`, intrinsics held).
2. **Match.** The camera projects every dot; a dot takes the blob nearest its prediction when
   that blob is nearest to no other prediction (mutually nearest), lies within the *gate*, and
   no second blob is nearly as near (an ambiguous match is dropped, never guessed).
3. **Calibrate again** on all matched dots (the DLT when they are six or more and not coplanar,
   else the pose with the focal guess), shrink the gate to a few times the fit's RMS, and
   repeat until the matches no longer change.

Two dots whose predicted images lie within a blob's diameter and 3 px of each other (two levels
of a plate seen along the line joining them) may make one blob whose centroid is neither's: they
are matched only where each finds a blob of its own, and the message counts those left out.

The labelling is accepted only if enough dots were matched, they fit one camera well (a pinhole;
from 20 dots, one with radial distortion, for a wide-angle lens), and no shift of the labels by
one step of a periodic target's lattice (a row or column of a grid or plate) would match more
blobs; a target that runs out of the photo on both sides along such a step cannot be told from
its shift at all, and its view is flagged unless `trust_seed`. Otherwise the view is flagged
(`Labels.ok` False, with the reason), never labelled wrongly in silence. (Clicks all one
column over on a PIV plate give every dot its neighbour's id and fit a camera a pitch away as
well as the right labels: only the border column the shifted labels leave unexplained tells
them apart.)
"""

from __future__ import annotations

import numpy as np

from . import _label
from ._detect import Detection
from ._label import Labels, _size_ratios
from .targets import Target, _grid_lattice, _grid_symmetries, _marker_ids, _placements

__all__ = ["label_grid", "match_dots"]

# The first gate, as a fraction of the median distance between neighbouring predicted dots: a
# blob farther than that from a dot's prediction would be nearer its neighbour's.
_FIRST_GATE = 0.4
# Later gates: this many times the last fit's RMS (pixels), no less than `_MIN_GATE`.
_GATE_RMS = 5.0
_MIN_GATE = 2.0
# A match is ambiguous when a second blob is within this factor of the nearest's distance.
_AMBIGUITY = 2.0


def _coplanar(points: np.ndarray, tolerance: float = 0.01) -> bool:
    """Whether points lie within `tolerance` of their spread from one plane (or a line)."""
    if len(points) < 4:
        return True
    s = np.linalg.svd(points - points.mean(0), compute_uv=False)
    return bool(s[2] <= tolerance * s[0])


def _mutual(predicted: np.ndarray, blobs: np.ndarray, gate: float) -> np.ndarray:
    """For each predicted dot, the blob it is matched to (mutually nearest, within `gate`, not
    ambiguous), or -1."""
    index = np.full(len(predicted), -1)
    if len(blobs) == 0:
        return index
    d = np.linalg.norm(predicted[:, None] - blobs[None], axis=-1)
    d = np.where(np.isfinite(d), d, np.inf)
    nearest = np.argmin(d, axis=1)
    first = d[np.arange(len(d)), nearest]
    second = np.partition(d, 1, axis=1)[:, 1] if len(blobs) > 1 else np.full(len(d), np.inf)
    back = np.argmin(d, axis=0)  # each blob's nearest prediction
    ok = (first < gate) & (back[nearest] == np.arange(len(d))) & (second > _AMBIGUITY * first)
    index[ok] = nearest[ok]
    return index


def _intrinsics(focal, principal_point, detection: Detection) -> np.ndarray | None:
    """The guessed `K`, or None without a focal length."""
    if focal is None:
        return None
    if principal_point is None:
        if detection.image_shape is None:
            raise ValueError(
                "a focal-length guess needs the principal point: pass `principal_point=(x, y)` "
                "(the detection does not record its image's size)."
            )
        height, width = detection.image_shape
        principal_point = ((width - 1) / 2, (height - 1) / 2)
    focal = float(focal)
    if not np.isfinite(focal) or focal <= 0:
        raise ValueError(f"`focal` is a focal length in pixels, > 0; got {focal}.")
    cx, cy = (float(c) for c in principal_point)
    return np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])


def _guessed_intrinsics(P: np.ndarray) -> np.ndarray | None:
    """`K` of a camera `P` (zero skew), or None if it does not decompose."""
    import jax.numpy as jnp

    from ._camera import Camera

    camera = Camera.from_projection(jnp.asarray(P), skew=False)
    K = np.asarray(camera.K, dtype=np.float64)
    return K if np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 else None


def _pose(K: np.ndarray, world: np.ndarray, pixels: np.ndarray, found: np.ndarray, start=None):
    """`P = K [R | t]` of the pose that best projects `world[found]` onto `pixels[found]`, from
    `start (R, t)` or from the homography of the points' best-fitting plane; and its RMS. None
    where that homography is not finite (points seen on a line).

    Least squares over a rotation (a rotation vector applied to the start's) and `t` by SciPy's
    Levenberg-Marquardt, the start from Zhang's eq. 10 (as `_planar._pose`): a few dozen points
    on the host, where JAX would compile for seconds for every number of them.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    points, observed = world[found], pixels[found]
    if start is None:  # the plane through the points: x_plane = A (X - c)
        c = points.mean(0)
        A = np.linalg.svd(points - c)[2]
        A[2] = np.cross(A[0], A[1])
        q = (points - c) @ A[:2].T
        with np.errstate(divide="ignore", invalid="ignore"):
            H = _homography(q, observed)
        if not np.all(np.isfinite(H)):
            return None  # (the points lie on a line, as seen: no pose from them)
        M = np.linalg.solve(K, H)
        scale = 2.0 / (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1]))
        scale *= -1.0 if np.sum(q @ M[2, :2] + M[2, 2]) < 0 else 1.0  # the points in front
        r1, r2 = scale * M[:, 0], scale * M[:, 1]
        U, _, Vt = np.linalg.svd(np.stack([r1, r2, np.cross(r1, r2)], -1))
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt @ A
        start = (R, scale * M[:, 2] - R @ c)

    def rotation(p):
        return Rotation.from_rotvec(p[:3]).as_matrix() @ start[0]

    def residuals(p):
        x = (points @ rotation(p).T + p[3:]) @ K.T
        return (x[:, :2] / x[:, 2:] - observed).ravel()

    fit = least_squares(residuals, np.r_[0.0, 0.0, 0.0, start[1]], method="lm", x_scale="jac")
    R, t = rotation(fit.x), fit.x[3:]
    rms = float(np.sqrt(np.mean(np.sum(fit.fun.reshape(-1, 2) ** 2, -1))))
    return K @ np.c_[R, t], (R, t), rms


# The labelling is trusted where the matched dots fit a camera to this share of their spacing;
# from this many dots, a camera with radial distortion may show it (a wide-angle lens, k1 =
# -0.4: a pinhole fitted 450 rightly matched dots of a rendered plate to 1.42 px, where 1.26
# were trusted, a user's trial).
_MAX_RMS_SHARE, _RADIAL_DOTS = 0.05, 20


def _radial_rms(P, world, pixels, found) -> float:
    """The RMS (pixels) of the camera `P` with radial distortion (k1, k2) fitted to the dots
    `found`: SciPy's Levenberg–Marquardt over the focal lengths, principal point, pose, k1 and
    k2, from `P`'s (inf if `P` does not decompose)."""
    import jax.numpy as jnp
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from ._camera import Camera

    camera = Camera.from_projection(jnp.asarray(P), skew=False)
    K, R, t = (np.asarray(x, np.float64) for x in (camera.K, camera.R, camera.t))
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R))):
        return np.inf
    points, observed = world[found], pixels[found]

    def residuals(p):
        c = points @ Rotation.from_rotvec(p[4:7]).as_matrix().T @ R.T + p[7:10]
        x = c[:, :2] / c[:, 2:]
        r2 = np.sum(x * x, -1, keepdims=True)
        x = x * (1.0 + p[10] * r2 + p[11] * r2 * r2)
        return (x * p[:2] + p[2:4] - observed).ravel()

    start = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0.0, 0.0, 0.0, t, 0.0, 0.0]
    with np.errstate(all="ignore"):
        fit = least_squares(residuals, start, method="lm", x_scale="jac")
    rms = float(np.sqrt(np.mean(np.sum(fit.fun.reshape(-1, 2) ** 2, -1))))
    return rms if np.isfinite(rms) else np.inf


def _fit(world, pixels, found, K, pose):
    """The camera of the matched dots: the DLT where they determine one, else the pose for the
    focal guess; `(P, pose, rms)` or None."""
    if found.sum() >= 6 and not _coplanar(world[found]):
        # (however poorly they fit: `_trimmed_fit` drops wrong matches by their residuals)
        P = _label._fit(world, np.where(found[:, None], pixels, 0.0), found, np.inf)  # noqa: SLF001
        if np.isfinite(P).all():
            residual = _label._project(P, world)[found] - pixels[found]  # noqa: SLF001
            return P, None, float(np.sqrt(np.nanmean(np.sum(residual**2, -1))))
    if K is None or found.sum() < 4:
        return None
    return _pose(K, world, pixels, found, pose)


def _trimmed_fit(world, pixels, found, K, pose, rounds: int = 3):
    """`_fit`, then again without the matches whose residual exceeds three robust standard
    deviations (1.4826 median) and 1 px: wrong matches near right ones, from a rough camera.
    Returns the fit (or None) and the matches kept."""
    for _ in range(rounds):
        fit = _fit(world, pixels, found, K, pose)
        if fit is None:
            return None, found
        residual = np.linalg.norm(_label._project(fit[0], world) - pixels, axis=-1)  # noqa: SLF001
        residual = np.where(found, residual, 0.0)
        bad = found & (residual > max(3 * 1.4826 * np.median(residual[found]), 1.0))
        if not bad.any() or found.sum() - bad.sum() < 6:
            return fit, found
        found = found & ~bad
    return _fit(world, pixels, found, K, pose), found


# A vector between neighbouring dots is a step of the target's lattice if this fraction of its
# dots has it among their nearest `_NEIGHBOURS`.
_LATTICE_SHARE, _NEIGHBOURS = 0.25, 8


def _lattice_steps(world: np.ndarray) -> np.ndarray:
    """`(S, 3)` the steps of a periodic target's lattice: the vectors from a dot to one of its
    nearest neighbours that a quarter of its dots share (none for an irregular target)."""
    from scipy.spatial import cKDTree

    k = min(_NEIGHBOURS, len(world) - 1)
    if k < 1:
        return np.zeros((0, 3))
    _, near = cKDTree(world).query(world, k + 1)
    steps = (world[near[:, 1:]] - world[:, None]).reshape(-1, 3)
    scale = max(float(np.abs(world).max()), 1.0)
    keys, counts = np.unique(np.round(steps / scale, 9), axis=0, return_counts=True)
    return keys[counts >= _LATTICE_SHARE * len(world)] * scale


def _margin(n: int) -> float:
    """How many more blobs than the `n` matched a shifted labelling must explain to be told
    better (detection's misses and clutter at the image's edges)."""
    return max(2.0, 0.005 * n)


def _shifted_labelling(world, blobs, P, n: int, gate: float, reach: float):
    """`(step, count)` where the labels shifted by one step of the target's lattice (the camera
    `P`'s prediction of the dots moved by it) would match more blobs than the `n` matched;
    else None. Clicks all one column off on a periodic plate give every dot its neighbour's id
    and a camera a pitch away that fits as well (a two-level PIV plate, 704 dots: 688 of 688
    labels wrong, ok, 0.35 px RMS); that labelling leaves the border column beyond it
    unexplained, which its shift explains (704 blobs)."""
    best = None
    for step in _lattice_steps(world):
        predicted = _label._project(P, world + step)  # noqa: SLF001
        count = int(np.sum(_matches(predicted, blobs, gate, reach) >= 0))
        if count > n + _margin(n) and (best is None or count > best[1]):
            best = (step, count)
    return best


def _blind_step(world, P, found, detection: Detection, margin: float):
    """A step of the target's lattice along which the photo cannot tell the labels from the
    labels shifted by it, or None: where the target runs out of the photo on both sides, so
    that no dot in view lies on its border across the step (a blob the shifted labels leave
    unexplained) and no place in view lies one step beyond it (where they predict a dot).
    With a plate larger than the view and clicks one column off, every dot was labelled a
    pitch off, fitting as well as the right labels (a user's trial: 268 of 268 wrong, OK)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(world)
    for step in _lattice_steps(world):
        near = 0.25 * float(np.linalg.norm(step))
        first = tree.query(world - step, distance_upper_bound=near)[0] == np.inf
        last = tree.query(world + step, distance_upper_bound=near)[0] == np.inf
        seen = found[first] & _in_image(P, world[first], detection)
        beyond = _in_image(P, world[last] + step, detection)
        if seen.sum() + beyond.sum() <= 2 * margin:
            return step
    return None


def _matches(predicted, blobs, gate: float, reach: float) -> np.ndarray:
    """`_mutual`, less the dots whose blob may be theirs and a neighbour's merged: another dot's
    image within `reach` found no blob, and its nearest is theirs (`_label.crowded`)."""
    index = _mutual(predicted, blobs, gate)
    return np.where(_label.crowded(predicted, reach, index, blobs), -1, index)


def _in_image(P, world, detection: Detection) -> np.ndarray:
    """Where `P` projects `world` into the image searched (anywhere in front, if its size is not
    known)."""
    predicted = _label._project(P, world)  # noqa: SLF001
    inside = np.all(np.isfinite(predicted), axis=1)
    if detection.image_shape is not None:
        height, width = detection.image_shape
        inside &= np.all((predicted >= -0.5) & (predicted <= (width - 0.5, height - 0.5)), axis=1)
    return inside


def _vector(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _spread(points: np.ndarray) -> float:
    """The largest distance between finite points (their extent)."""
    points = points[np.all(np.isfinite(points), -1)]
    return float(np.ptp(points, axis=0).max()) if len(points) else 0.0


def _spacing(points: np.ndarray) -> float:
    """The median distance from each finite point to its nearest neighbour."""
    points = points[np.all(np.isfinite(points), -1)]
    if len(points) < 2:
        return np.inf
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(1)))


def match_dots(
    detection: Detection,
    target: Target,
    seed,
    *,
    focal: float | None = None,
    principal_point: tuple[float, float] | None = None,
    max_rms: float | None = None,
    min_dots: int | None = None,
    max_rounds: int = 20,
    trust_seed: bool = False,
) -> Labels:
    """Tell which detected blob is which dot of `target`, from a rough camera or a few clicks.

    See the module notes for the method. A view it cannot label with certainty comes back with
    `ok=False`, an empty mask and the reason, never with a wrong label.

    **Arguments:**

    - `detection`: the blobs found in one image (`mvcalib.detect_dots`).
    - `target`: the target photographed, e.g. `mvcalib.targets.from_file(path)`; clicks name
      its dots by `target.ids`.
    - `seed`: a rough `Camera` of this view, or clicked correspondences `(pixels (k, 2),
      dot_ids (k,))`: six or more, not all on one plane, are enough alone; four or five (or
      coplanar ones) need `focal`. A camera must put most dots within 40 % of their spacing
      of their blobs (the first gate); one further off (OpenPTV's `.ori` cameras of a set-up
      behind glass and water, without their refraction: 55-112 px off the cavity's dots, a
      user's trial) is flagged: click four dots instead.
    - `focal`: a focal-length guess in pixels (e.g. the lens's focal length over the pixel
      pitch); `principal_point`: `(x, y)` in pixels, default the image's centre.
    - `max_rms`: the largest RMS (pixels) of the final camera's fit to the matched dots that is
      trusted; default 5 % of the distance between neighbouring dots' images (as `label_dots`).
    - `min_dots`: the fewest matched dots that make a labelling; default 10 (or the target's
      size, if smaller).
    - `max_rounds`: of match and calibrate.
    - `trust_seed`: take the seed's word where the photo cannot check it: a periodic target
      (a grid, a plate) that runs out of the photo on both sides along a step of its lattice
      looks the same with every dot's id one step over, so the ids rest on the seed alone.
      Such a view is flagged unless `trust_seed` is True (check the clicks first).

    **Returns:** `Labels` (see there; `message` summarises the matching or says why it failed).

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> target = mc.targets.box_corner_grid(4)
    >>> camera = mc.synthetic.random_rig(jax.random.key(1), 1, target).cameras[0]
    >>> detection = mc.detect_dots(mc.synthetic.render(camera, target, key=0))
    >>> clicks = np.asarray(camera.project(target.points[[0, 5, 20, 26, 40, 47]]))
    >>> labels = mc.match_dots(detection, target, (clicks + 1.0, [0, 5, 20, 26, 40, 47]))
    >>> labels.ok, int(labels.mask.sum())
    (True, 48)

    ```
    """
    _label.check_kinds("match_dots", detection, target)
    from ._camera import Camera  # (JAX: imported where a camera is used, see `_photos`)

    world = np.asarray(target.points, dtype=np.float64)
    blobs = np.asarray(detection.centroids, dtype=np.float64).reshape(-1, 2)
    M, B = len(world), len(blobs)
    min_dots = min(10, M) if min_dots is None else int(min_dots)
    K = _intrinsics(focal, principal_point, detection)
    clicks = None
    if isinstance(seed, Camera):
        if seed.batch_shape:
            raise ValueError(f"`seed` must be one camera; got a rig of shape {seed.batch_shape}.")
        P, pose = np.asarray(seed.projection_matrix(), dtype=np.float64), None
    else:
        try:
            pixels, ids = seed
        except (TypeError, ValueError):
            raise ValueError(
                "`seed` is a Camera or clicked correspondences (pixels (k, 2), dot_ids (k,))."
            ) from None
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        where = target.index(ids)
        if len(where) != len(pixels):
            raise ValueError(f"{len(pixels)} clicked pixels for {len(where)} dot ids.")
        if len(np.unique(where)) != len(where):
            raise ValueError("a dot id is clicked twice.")
        if not np.all(np.isfinite(pixels)):
            raise ValueError("a clicked pixel is not finite.")
        clicks = (pixels, where)
        found = np.zeros(M, bool)
        found[where] = True
        at = np.zeros((M, 2))
        at[where] = pixels
        enough = len(where) >= 6 and not _coplanar(world[where])
        if not enough and (K is None or len(where) < 4):
            plane = " on one plane, or within 1 % of their extent of one" if len(where) >= 6 else ""
            raise ValueError(
                f"{len(where)} clicks{plane}: give six or more dots not all on one plane, or "
                "four or more and `focal` (a focal-length guess in pixels)."
            )
        # (six or more: their DLT; where that is degenerate, the pose for `focal` if given)
        first = _fit(world, at, found, K, None)
        if first is None and K is None:
            return Labels.failed(
                M, B, f"the {len(where)} clicked dots do not determine a camera alone (too many "
                "of them on one plane or line): click dots spread over the target's depth, or "
                "give `focal` (a focal-length guess in pixels)",
            )  # fmt: skip
        if first is None:
            return Labels.failed(
                M, B, "the clicks do not fit one camera: check their dot ids and positions"
            )
        P, pose, _ = first
    if K is None:  # the seed's own intrinsics: the pose fallback for coplanar matches
        K = _guessed_intrinsics(P)
    if B < min_dots:
        return Labels.failed(M, B, f"only {B} blobs found; matching needs {min_dots}")

    spacing = _spacing(_label._project(P, world))  # noqa: SLF001
    if not np.isfinite(spacing):
        return Labels.failed(M, B, "the seed camera sees fewer than two dots of the target")
    gate = _FIRST_GATE * spacing
    # two dots whose images lie within a blob's diameter and 3 px, one blob for both, are left out
    reach = _label.crowd_reach(detection.major)
    # Clicks: the seed's camera is best around them, so the matching grows from there, the
    # radius around the clicks doubling each round; a camera seed predicts everywhere alike.
    radius = 2 * spacing if clicks is not None else np.inf
    index, rms, rounds = None, np.inf, 0
    for rounds in range(1, max_rounds + 1):  # noqa: B007 (reported below)
        predicted = _label._project(P, world)  # noqa: SLF001
        if clicks is not None:
            near = np.min(np.linalg.norm(predicted[:, None] - clicks[0][None], axis=-1), axis=1)
            predicted = np.where((near <= radius)[:, None], predicted, np.nan)
        new = _matches(predicted, blobs, gate, reach)
        found = new >= 0
        if found.sum() < 4:
            return Labels.failed(
                M, B, f"only {found.sum()} dots lie near their predicted position: check the seed"
            )
        pixels = np.where(found[:, None], blobs[np.maximum(new, 0)], 0.0)
        fit, found = _trimmed_fit(world, pixels, found, K, pose)
        # a fit that fails (wrong matches, from a poor seed) is tried again on the nearer half
        # of the matches
        distance = np.linalg.norm(pixels - predicted, axis=-1)
        while fit is None and found.sum() >= 8:
            found = found & (distance <= np.median(distance[found]))
            fit, found = _trimmed_fit(world, pixels, found, K, pose)
        if fit is None:
            return Labels.failed(
                M,
                B,
                f"the {int((new >= 0).sum())} dots near their predicted position do not fit "
                "one camera: check the seed",
            )
        new = np.where(found, new, -1)
        converged = index is not None and np.array_equal(new, index) and np.isinf(radius)
        index = new
        if converged:
            break
        P, pose, rms = fit
        if np.isinf(radius):  # (while it grows, the camera extrapolates: the gate stays wide)
            gate = min(gate, max(_GATE_RMS * rms, _MIN_GATE))
        radius *= 2  # (once it spans the predicted target, every dot is in: no radius)
        if radius >= _spread(_label._project(P, world)):  # noqa: SLF001
            radius = np.inf
    else:
        return Labels.failed(M, B, f"the matches did not settle in {max_rounds} rounds")
    found = index >= 0
    n = int(found.sum())
    spacing = _spacing(blobs[index[found]])
    max_rms = _MAX_RMS_SHARE * spacing if max_rms is None else float(max_rms)
    if n < min_dots:
        return Labels.failed(M, B, f"only {n} dots matched; need {min_dots}")
    lens = ""
    if not rms <= max_rms and n >= _RADIAL_DOTS:  # a lens's distortion, which P does not model?
        radial = _radial_rms(P, world, np.where(found[:, None], blobs[index], 0.0), found)
        if radial <= max_rms:
            rms, lens = radial, " with radial distortion (k1, k2)"
        else:
            lens = f"; with radial distortion (k1, k2), {radial:.2f} px"
    if not rms <= max_rms:
        return Labels.failed(
            M, B, f"the matched dots fit a camera to {rms:.2f} px RMS only, where up to "
            f"{max_rms:.2f} px is trusted ({_MAX_RMS_SHARE:.0%} of the dots' spacing{lens}): "
            "wrong matches, or blobs that are no dots; `max_rms` sets the limit",
        )  # fmt: skip
    blind = _blind_step(world, P, found, detection, _margin(n))
    # (where the photo cannot tell a shift, counting the blobs each labelling explains cannot)
    better = None if blind is not None else _shifted_labelling(world, blobs, P, n, gate, reach)
    if blind is not None and not trust_seed:
        return Labels.failed(
            M, B, f"the target runs out of the photo on both sides along its lattice step "
            f"{_vector(blind)}: with every id one step over the dots fit as well, so which dot is "
            "which rests on the seed alone; check it, and pass `trust_seed=True` (the CLI's "
            "--trust-clicks)",
        )  # fmt: skip
    if better is not None:
        step, count = better
        return Labels.failed(
            M, B, f"the labels shifted by one step of the target's lattice ({_vector(step)}) "
            f"would match {count} blobs, not {n}: the seed is a row or column off "
            + ("(clicks on a periodic target: check their dot ids)" if clicks is not None else
               "(a seed camera this far off a periodic target: click four or more dots)"),
        )  # fmt: skip
    message = f"{n} of {M} dots matched in {rounds} rounds, {rms:.2f} px RMS{lens}"
    if blind is not None:
        message += f"; the ids along {_vector(blind)} rest on the seed (trusted)"
    predicted = _label._project(P, world)  # noqa: SLF001
    mutual = _mutual(predicted, blobs, gate)
    merged = _label.crowded(predicted, reach, mutual, blobs)
    if merged.any():
        message += (
            f"; {int(merged.sum())} dots left out: their blob is also the nearest of another "
            f"dot's image within {reach:.1f} px (merged blobs)"
        )
    if clicks is not None:  # clicks the final labelling disagrees with are reported, not used
        pixels, where = clicks
        off = np.linalg.norm(blobs[index[where]] - pixels, axis=-1)
        moved = found[where] & (off > max(_FIRST_GATE * spacing, 3 * _MIN_GATE))
        for name, which in (
            ("clicks corrected (to the blob the camera puts there)", moved),
            ("clicked dots with no blob matched (left out)", ~found[where]),
        ):
            if which.any():
                message += f"; {name}: ids " + ", ".join(
                    str(int(i)) for i in target.ids[where[which]]
                )
    return Labels.matched(blobs, index, rms, message)


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The homography `(3, 3)` taking `src (n, 2)` to `dst (n, 2)`, n >= 4, by the normalised
    DLT (NumPy: a few dozen points on the host, no compile; `_planar._homography_kernel` is the
    batched, differentiable one)."""
    return _homographies(src[None], dst[None], np.ones((1, len(src)), bool))[0]


def _homographies(src: np.ndarray, dst: np.ndarray, used: np.ndarray) -> np.ndarray:
    """The homographies `(B, 3, 3)` taking each batch's points `src (B, n, 2)` to `dst (B, n,
    2)`, of the points `used (B, n)` (at least 4 a batch), by the normalised DLT: Hartley's
    similarity of each side's used points (`_label._normalise`'s), then the SVD of the
    equations' rows, those of unused points zero (rows of zeros leave the right singular
    vectors as they are). One LAPACK call for the batch: `label_grid`'s local fits were a
    Python loop of ~600 SVDs a photo."""

    def normalised(points):  # the points, and the similarity that normalised them
        a, scale, centroid = _label._normalise(points, used)  # noqa: SLF001
        T = np.zeros(points.shape[:-2] + (3, 3))
        T[..., 0, 0] = T[..., 1, 1] = scale[..., 0, 0]
        T[..., :2, 2] = -scale[..., 0, :] * centroid[..., 0, :]
        T[..., 2, 2] = 1.0
        return a, T

    (a, T1), (b, T2) = normalised(src), normalised(dst)
    (x, y), (u, v) = np.moveaxis(a, -1, 0), np.moveaxis(b, -1, 0)
    one, zero = np.ones_like(x), np.zeros_like(x)
    rows = np.stack(
        [np.stack([x, y, one, zero, zero, zero, -u * x, -u * y, -u], -1),
         np.stack([zero, zero, zero, x, y, one, -v * x, -v * y, -v], -1)], -2
    ) * used[..., None, None]  # fmt: skip
    rows = rows.reshape(len(rows), -1, 9)
    # (the least right singular vector; with 4 points, 8 rows, only the full V holds it)
    h = np.linalg.svd(rows, full_matrices=rows.shape[1] < 9)[2][:, -1].reshape(-1, 3, 3)
    H = np.linalg.inv(T2) @ h @ T1
    return H / H[:, 2:, 2:]  # (the SVD's sign is arbitrary; points in front have h_3 > 0)


def _cross(a, b) -> float:
    """The z of the cross product of two 2-vectors."""
    return float(a[0] * b[1] - a[1] * b[0])


# A lattice node's neighbourhood for its local homography: nodes within this many steps along
# each axis, at least `_LOCAL_POINTS` of them matched.
_LOCAL_STEPS, _LOCAL_POINTS = 3, 10
_LOCAL_GATE = 0.2
# A lattice must hold this fraction of the grid's dots: a view of a fisheye at 75 degrees whose
# lattice had 40 of 63 was shifted by a row (the pinhole views of the tests hold 95 %).
_MIN_COVERAGE = 0.75
# With all of its markers found on large blobs, and no other placement near as good, a lattice
# is placed by them: a board half out of the image, which the rule above flagged (a trial's
# photos of a 7 x 9 grid: 30 of 46 labelled -> 39, none wrong).
_MIN_MARKED_COVERAGE = 0.4


def _local_predictions(H, nodes, known, pixels):
    """The pixels of lattice `nodes (n, 2)`: each through a homography fitted to the `known`
    nodes (matched to `pixels`) around it, where enough of them are, else through `H`. A board
    seen through a wide-angle or fisheye lens is no homography as a whole, but is one locally."""
    out = _apply(H, nodes)
    if len(known) < _LOCAL_POINTS:
        return out
    near = np.max(np.abs(known[None] - nodes[:, None]), axis=-1) <= _LOCAL_STEPS  # (nodes, known)
    local = near.sum(1) >= _LOCAL_POINTS
    if not local.any():
        return out
    # each node's near points first, then as many unused ones as the most crowded node has near
    near = near[local]
    order = np.argsort(~near, axis=1, kind="stable")[:, : near.sum(1).max()]
    fitted = _homographies(known[order], pixels[order], np.take_along_axis(near, order, 1))
    out[local] = _apply(fitted, nodes[local])
    return out


def _extent(keys: np.ndarray) -> str:
    """The box around lattice `keys (n, 2)`, e.g. `'8 x 12'`."""
    width, height = keys.max(0) - keys.min(0) + 1
    return f"{width} x {height}"


def _apply(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`points (n, 2)` through the homography `H (3, 3)`, or each through its own `(n, 3, 3)`;
    NaN behind it."""
    h = np.einsum("...ij,...j->...i", H[..., :2], points) + H[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(h[:, 2:] > 0, h[:, :2] / h[:, 2:], np.nan)


def label_grid(
    detection: Detection,
    rows: int,
    cols: int,
    *,
    asymmetric: bool = False,
    markers=(),
    min_ratio: float = 1.3,
    max_rounds: int = 30,
) -> Labels:
    """Label the dots of a printed `rows x cols` grid (`mvcalib.targets.dot_grid`) with no seed:
    the grid's topology from neighbouring blobs, grown by homographies; flagged rather than
    guessed where the grid's position is not determined.

    From the blob nearest the others' median, the two shortest independent displacements to its
    neighbours give a lattice; its predictions through homographies fitted to the dots matched
    so far (each node's from the matched nodes within 3 steps of it, where 10 are: a board seen
    through a wide-angle or fisheye lens is a homography only locally; mutually nearest within
    0.4 of the local spacing, then a few times the fit's RMS but no less than a fifth of the
    spacing; ambiguous ones dropped) grow it ring by ring until nothing changes. The lattice found
    must lie on the grid's dots in one place only, up to the grid's own turns and mirrorings (a
    lattice that also fits one row or column over has lost a border row or column, and the
    grid's position is unknown) and hold three quarters of them; else the view is flagged.

    Of the placements the grid's symmetries leave, a rectangular grid is labelled as a camera on
    the board's +z side sees it, dot 0 nearest the image's top left: up to its half turn (a
    square one up to its quarter turns), which keeps a planar calibration (the board's pose
    absorbs the turn) but not the ids' identity across cameras. `asymmetric=True` is OpenCV's
    asymmetric circles grid (`targets.dot_grid(..., asymmetric=True)`), which no turn maps onto
    itself when its rows are odd in number: its ids are the same from every camera on one side
    of the board. With `markers` (the ids of dots printed larger, `targets.dot_grid(...,
    markers=)`, a grid's `fiducials`) the labelling is the placement (a turn, or a mirroring: the
    board seen from its other side) that puts them on blobs larger than their neighbours (major
    axis over `min_ratio` times theirs, as `mvcalib.label_dots` finds fiducials), and small ones
    elsewhere: all of the markers found, or all but one, and every other placement off by two
    blobs or more; else the view is flagged. With all of them found, they also place a lattice
    that has lost border rows or columns (a board partly out of the image) and hold 40 % of its
    dots: the placement (a shift too) that puts the markers on the large blobs, if no other
    comes within two blobs of it.

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> grid = mc.targets.dot_grid(6, 9, 20.0)
    >>> R = np.diag([1.0, -1.0, -1.0])
    >>> camera = mc.Camera(1000.0, 1000.0, 480.0, 360.0, R, -R @ np.array([80.0, 50.0, 400.0]))
    >>> image = mc.synthetic.render(camera, grid, (960, 720), key=0)
    >>> labels = mc.label_grid(mc.detect_dots(image), 6, 9)
    >>> labels.ok, int(labels.mask.sum())
    (True, 54)

    ```
    """
    _label.check_kinds("label_grid", detection)
    blobs = np.asarray(detection.centroids, dtype=np.float64).reshape(-1, 2)
    M, B = rows * cols, len(blobs)
    markers = _marker_ids(markers, M)
    grid = _grid_lattice(rows, cols, asymmetric)
    if B < 6:
        return Labels.failed(M, B, f"only {B} blobs found")
    d = np.linalg.norm(blobs[:, None] - blobs[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    seed = int(np.argmin(np.linalg.norm(blobs - np.median(blobs, 0), axis=-1)))
    order = np.argsort(d[seed])[:8]
    a = blobs[order[0]] - blobs[seed]
    b = next(
        (blobs[k] - blobs[seed] for k in order[1:]
         if abs(_cross(a, blobs[k] - blobs[seed])) > 0.7 * np.linalg.norm(a) * d[seed, k]),
        None,
    )  # fmt: skip
    if b is None:
        return Labels.failed(M, B, "no lattice around the central blob")
    if _cross(a, b) > 0:  # the board's x, y as a camera in front of it sees them (y down)
        b = -b
    # the lattice near the seed, affine: (i, j) -> seed + i a + j b
    H = np.array([[a[0], b[0], blobs[seed, 0]], [a[1], b[1], blobs[seed, 1]], [0.0, 0.0, 1.0]])
    span, lattice, index, gate = 1, {}, None, np.inf
    for _ in range(max_rounds):
        ij = np.array(
            [(i, j) for i in range(-span, span + 1) for j in range(-span, span + 1)], float
        )
        known = np.array(list(lattice), float).reshape(-1, 2)
        if len(known):  # a step from the lattice so far, not far out where only clutter lies
            ij = ij[np.abs(ij[:, None] - known[None]).max(-1).min(-1) <= 1]
        predicted = _local_predictions(H, ij, known, blobs[list(lattice.values())])
        gate = min(gate, _FIRST_GATE * _spacing(predicted))
        new = _mutual(predicted, blobs, gate)
        found = new >= 0
        if found.sum() < 6:
            return Labels.failed(M, B, f"only {found.sum()} blobs form a lattice")
        H = _homography(ij[found], blobs[new[found]])
        # the gate shrinks to a few times the fit, so that clutter beside the grid stays out
        residual = _apply(H, ij[found]) - blobs[new[found]]
        # (no tighter than a fifth of the spacing: the next ring is extrapolated, which a lens's
        # curvature bends by a few pixels however well the ring so far fits)
        floor = max(_MIN_GATE, _LOCAL_GATE * _spacing(blobs[new[found]]))
        gate = min(gate, max(_GATE_RMS * np.sqrt(np.mean(np.sum(residual**2, -1))), floor))
        lattice = {tuple(ij[k].astype(int)): int(new[k]) for k in np.flatnonzero(found)}
        keys = np.array(list(lattice))
        grown = keys.min(0).min() > -span and keys.max(0).max() < span  # an empty ring: done
        if grown and index is not None and lattice == index:
            break
        index = lattice
        span = span + 1 if not grown else span
    else:
        return Labels.failed(M, B, f"the lattice did not settle in {max_rounds} rounds")
    # Where the lattice lies on the grid: its keys count steps along the two shortest
    # displacements near the seed, which may be any short vectors of the grid's lattice (a
    # diagonal at a steep angle). It must lie on the grid's dots in one place, up to the grid's
    # own symmetries: else a border row or column is missing. A key or two a step off the grid
    # are blobs beside it that joined the lattice (clutter), dropped if every other placement
    # leaves two more off.
    keys = np.array(list(lattice))
    symmetries = len(_grid_symmetries(rows, cols, asymmetric))
    spare = max(1, len(keys) // 30)  # (keys that may be dropped as clutter)
    placements, det, off = _placements(keys, grid, slack=spare + 1)
    fewest = off.min(initial=spare + 1)
    rivals = np.sum(off <= fewest + (fewest > 0))  # (with keys dropped, two more for the others)
    if fewest > spare:
        width, height = keys.max(0) - keys.min(0) + 1
        why = "blobs beside the grid joined it"
        if len(keys) == width * height:  # a whole, clean lattice: likely the grid's own size
            # (a photographer's trial gave 9 x 14 for a 10 x 14 grid and was told of blobs)
            why = (f"is the grid {min(width, height)} x {max(width, height)} (rows, cols)? Else "
                   f"{why}")  # fmt: skip
        return Labels.failed(
            M, B, f"the lattice found is {_extent(keys)} dots, which fits nowhere on the "
            f"{rows} x {cols} grid: {why}",
        )  # fmt: skip
    # with markers in view, they place a lattice that has lost a border row or column too (a
    # board half out of the image); not with clutter in it, whose keys differ by placement
    partial = rivals != symmetries and len(markers) > 0 and fewest == 0
    if rivals != symmetries and not partial:
        return Labels.failed(
            M, B, f"the lattice found is {_extent(grid[placements[0][placements[0] >= 0]])} "
            f"dots, which fit {rivals // symmetries} places on the grid: a border row or column "
            "is missing, so the grid's position is unknown",
        )  # fmt: skip
    placements, det = placements[off == fewest], det[off == fewest]
    on = placements[0] >= 0  # (the same keys are on the grid under each of the grid's symmetries)
    keys, placements = keys[on], placements[:, on]
    members = np.array(list(lattice.values()))[on]
    pixels = blobs[members]
    too_few = Labels.failed(
        M, B, f"only {len(keys)} of the grid's {M} dots form its lattice: too few to trust "
        "where its rows and columns fall",
    )  # fmt: skip
    if len(keys) < (_MIN_MARKED_COVERAGE if len(markers) else _MIN_COVERAGE) * M:
        return too_few
    if len(markers):  # the placement that puts the markers on the large blobs, and them only
        large = _size_ratios(np.asarray(detection.major, float).reshape(-1), d)[members] > min_ratio
        misfits = np.array([np.sum(large != np.isin(ids, markers)) for ids in placements])
        best = int(np.argmin(misfits))
        found = int(np.sum(large & np.isin(placements[best], markers)))
        rival = np.sort(misfits)[1] if len(misfits) > 1 else np.inf
        if found < max(1, len(markers) - 1) or rival < misfits[best] + 2:
            where = "place and orientation" if partial else "orientation"
            return Labels.failed(
                M, B, f"the markers do not tell the grid's {where}: {found} of "
                f"{len(markers)} found as large blobs, and the grid's turns and mirrorings "
                f"misplace {np.sort(misfits).tolist()[:8]} large or small blobs",
            )  # fmt: skip
        if len(keys) < _MIN_COVERAGE * M and found < len(markers):
            return too_few  # (a part of the grid is placed by all of its markers only)
    else:  # as a camera on the board's +z side sees it, dot 0 nearest the image's top left
        seen = np.flatnonzero(det > 0)
        best = seen[np.argmin([np.sum(pixels[np.argmin(placements[k])]) for k in seen])]
    ids = placements[best]
    index = np.full(M, -1)
    index[ids] = members
    P = _homography(grid[ids].astype(float), pixels)  # grid steps -> pixels
    residual = _apply(P, grid[ids].astype(float)) - pixels
    rms = float(np.sqrt(np.mean(np.sum(residual**2, -1))))
    return Labels.matched(
        blobs, index, rms, f"{len(ids)} of {M} grid dots labelled, homography fit {rms:.2f} px"
    )
