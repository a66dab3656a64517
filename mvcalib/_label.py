"""Labelling: which detected blob is which dot of the target, found without a human.

The paper measured its dots by hand. Here the target carries a few larger dots, the fiducials
(`Target.fiducials`), and the labels come from hypothesise-and-verify:

1. **Fiducial candidates.** A dot's image has a major axis of about its diameter over its
   distance, whatever the obliquity; a fiducial's is larger than its neighbours' (which are at
   about the same distance). Blobs whose major axis exceeds `min_ratio` times the median of their
   nearest neighbours' are the candidates.
2. **Hypotheses.** Six candidates (the likeliest sets first), and every way they can be six of
   the target's fiducials, each give a camera by the DLT: 20,160 six-point DLTs for the box
   corner's eight fiducials, solved in one batched call.
3. **Verification.** Each hypothesis's camera predicts every dot; the number of dots landing on a
   detected blob scores it. The best few are refined (match, DLT on all matched dots, match
   again) and the best refined labelling is kept if it explains enough dots, fits them well, and
   no different labelling explains as many. Otherwise the view is flagged, never labelled
   wrongly in silence.

A wrong assignment of six fiducials cannot bring the other dots onto blobs: the dots are not
coplanar and the target has no symmetry that maps its fiducials onto each other.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from ._detect import Detection
from .targets import Target, check_target

__all__ = ["Labels", "label_dots"]

_MAX_HYPOTHESES = 200_000


@dataclasses.dataclass(frozen=True)
class Labels:
    """Which detected blob is which dot of a target, for one image.

    **Fields:**

    - `pixels`: `(M, 2)` the centroid of each target dot's blob, `(x, y)`; NaN where missing.
    - `mask`: `(M,)` bool, the dots found (the visibility mask for `mvcalib.calibrate`).
    - `index`: `(M,)` int, the detection each dot was matched to, -1 where missing (or found
      by `mvcalib.second_look`, which measures the image, not a blob).
    - `spurious`: indices of the detections that are no dot of the target (clutter).
    - `ok`: whether the labelling is trustworthy; when False, `mask` is all False.
    - `rms`: RMS distance in pixels between the labelled blobs and the dots projected by the DLT
      camera fitted to them (lens distortion and perspective bias of the centroids included).
    - `message`: why the labelling failed, or a one-line summary.
    """

    pixels: np.ndarray
    mask: np.ndarray
    index: np.ndarray
    spurious: np.ndarray
    ok: bool
    rms: float
    message: str

    @classmethod
    def matched(cls, blobs: np.ndarray, index: np.ndarray, rms: float, message: str) -> Labels:
        """The labelling that gives dot `m` the blob `index[m]` of `blobs (K, 2)` (-1: none)."""
        found = index >= 0
        return cls(
            pixels=np.where(found[:, None], blobs[np.maximum(index, 0)], np.nan),
            mask=found,
            index=index,
            spurious=np.setdiff1d(np.arange(len(blobs)), index[found]),
            ok=True,
            rms=rms,
            message=message,
        )

    @classmethod
    def failed(cls, n_dots: int, n_blobs: int, message: str) -> Labels:
        return cls(
            pixels=np.full((n_dots, 2), np.nan),
            mask=np.zeros(n_dots, bool),
            index=np.full(n_dots, -1),
            spurious=np.arange(n_blobs),
            ok=False,
            rms=float("nan"),
            message=message,
        )


def _fit(world, pixels, mask, max_relative_rms=None) -> np.ndarray:
    """One camera's P `(3, 4)` by mvcalib's DLT on the visible dots; NaN if it fails (with
    `max_relative_rms`, default `calibrate`'s, also if it fits them that poorly:
    `_dlt.poor_fit`)."""
    # (JAX imported here only: `label_grid` in `_photos`' worker processes needs none of it)
    import jax.numpy as jnp

    from . import _dlt
    from ._pipeline import calibrate

    if max_relative_rms is None:
        max_relative_rms = _dlt.DEFAULT_MAX_RELATIVE_RMS
    # `calibrate`'s program of the rig's shape bucket: the one the photos' calibration runs
    # afterwards, so that labelling compiles no DLT of its own
    dtype = jnp.result_type(float)  # float64 where the user enabled x64
    world, pixels = np.asarray(world, dtype), np.asarray(pixels, dtype)
    result = calibrate(world, pixels, np.asarray(mask), max_relative_rms=max_relative_rms)
    return np.asarray(result.P, dtype=np.float64)


def _normalise(points, used=None):
    """Hartley normalisation of `(..., N, d)` point sets, over the points `used (..., N)` (all by
    default): normalised points (all of them), scale `(..., 1, 1)`, centroid `(..., 1, d)`. (The
    NumPy twin of `_dlt._similarity`, for the host.)"""
    w = (np.ones(points.shape[:-1]) if used is None else np.asarray(used, float))[..., None]
    count = w.sum(axis=-2, keepdims=True)
    centroid = (w * points).sum(axis=-2, keepdims=True) / count
    square = w * np.sum((points - centroid) ** 2, axis=-1, keepdims=True)
    rms = np.sqrt(square.sum(axis=-2, keepdims=True) / count)
    scale = np.sqrt(points.shape[-1]) / np.maximum(rms, 1e-300)
    return (points - centroid) * scale, scale, centroid


def _six_point_cameras(world, pixels):
    """Cameras `(H, 3, 4)` from H hypotheses of six correspondences, `world (H, 6, 3)` against
    the same six blobs `pixels (6, 2)`, and each one's RMS misfit on its six points.

    Tens of thousands of these per image, so not `mvcalib.dlt`'s SVD: after Hartley
    normalisation the world centroid projects at finite depth, so `p34 = 1` can be fixed and
    the 12 x 11 system solved by its normal equations, batched in one LAPACK call. Six points
    over-determine the 11 unknowns by one equation: a wrong assignment shows as a misfit.
    """
    X, sw, cw = _normalise(world)
    x, sp, cp = _normalise(pixels)
    sp = float(sp.squeeze())
    Xh = np.concatenate([X, np.ones(X.shape[:-1] + (1,))], axis=-1)  # (H, 6, 4)
    zero = np.zeros_like(Xh)
    rows_u = np.concatenate([Xh, zero, -x[:, 0:1] * Xh], axis=-1)
    rows_v = np.concatenate([zero, Xh, -x[:, 1:2] * Xh], axis=-1)
    L = np.concatenate([rows_u, rows_v], axis=-2)  # (H, 12, 12)
    A, b = L[..., :11], -L[..., 11]
    with np.errstate(all="ignore"):
        a = np.linalg.solve(
            np.swapaxes(A, -1, -2) @ A + 1e-12 * np.eye(11),
            np.swapaxes(A, -1, -2) @ b[..., None],
        )[..., 0]
    Pn = np.concatenate([a, np.ones(a.shape[:-1] + (1,))], axis=-1).reshape(-1, 3, 4)
    # Undo the normalisations: P = Tp^-1 Pn Tw.
    Tw = np.zeros((len(Pn), 4, 4))
    Tw[:, :3, :3] = sw[:, 0, :1, None] * np.eye(3)
    Tw[:, :3, 3] = -sw[:, 0] * cw[:, 0]
    Tw[:, 3, 3] = 1.0
    Tp_inv = np.array([[1 / sp, 0, cp[0, 0]], [0, 1 / sp, cp[0, 1]], [0, 0, 1]], dtype=float)
    P = Tp_inv @ Pn @ Tw
    misfit = _project(P, world) - pixels
    rms = np.sqrt(np.mean(np.sum(misfit**2, axis=-1), axis=-1))
    return P, np.nan_to_num(rms, nan=np.inf)


def _project(P: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Pixels `(..., M, 2)` of `world`, `(M, 3)` or one set per camera `(..., M, 3)`, by
    `P (..., 3, 4)`; NaN behind the camera. The sign of P is chosen so that most points are in
    front."""
    h = world @ np.swapaxes(P[..., :3], -1, -2) + P[..., None, :, 3]
    h = h * np.where(np.sum(np.sign(h[..., 2]), axis=-1) < 0, -1.0, 1.0)[..., None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        px = h[..., :2] / h[..., 2:]
    return np.where(h[..., 2:] > 0, px, np.nan)


# Two dots are crowded where their images lie within a blob's diameter (its moment ellipse's
# major axis) and this many pixels of each other. Rendered two-level plates (dots 2-3 px wide,
# blur 0.7 px; 4 views of 450 dots, blobs 4.8 px across): pairs up to 2.1-2.3 px more than a
# diameter apart had merged into one blob, whose centroid lay 0.4-0.7 px (up to 2 px) from
# either dot; pairs that had not merged were measured as well as a lone dot (0.03 px median).
CROWDED_MARGIN = 3.0


def crowd_reach(major) -> float:
    """The distance (pixels) within which two dots' images crowd, for blobs whose major axes
    are `major`: their median, and `CROWDED_MARGIN`."""
    major = np.asarray(major, np.float64)
    return float(np.median(major)) + CROWDED_MARGIN if len(major) else 0.0


def close_pairs(predicted: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """`(a, b)`: the pairs of dots whose predicted images `predicted (M, 2)` (NaN: not seen) lie
    within `reach` pixels of each other (two dots of a multi-level plate, or of two faces of a
    3-D target, seen along the line that joins them)."""
    from scipy.spatial import cKDTree

    seen = np.flatnonzero(np.all(np.isfinite(predicted), axis=1))
    if len(seen) < 2 or not reach > 0:
        return np.zeros(0, int), np.zeros(0, int)
    a, b = seen[cKDTree(predicted[seen]).query_pairs(reach, output_type="ndarray")].T
    return a, b


def unlabelled_pairs(predicted: np.ndarray, reach: float, mask: np.ndarray) -> np.ndarray:
    """Where a dot is unlabelled (`mask` False) and so is a neighbour whose image lies within
    `reach` (`close_pairs`): one blob between them may be both, so neither is looked for."""
    a, b = close_pairs(predicted, reach)
    both = ~mask[a] & ~mask[b]
    out = np.zeros(len(predicted), bool)
    out[a[both]] = out[b[both]] = True
    return out


def crowded(predicted: np.ndarray, reach: float, index: np.ndarray, blobs: np.ndarray):
    """Where a dot's blob may be both its own and a close neighbour's merged into one, whose
    centroid is neither's (`close_pairs`): the dot is matched, `index (M,)` into `blobs (K, 2)`
    (-1: none), the neighbour is not, and the neighbour's nearest blob is the dot's. (A
    neighbour unmatched for another reason, its own blob beyond the gate, is no merger.)"""
    from scipy.spatial import cKDTree

    out = np.zeros(len(predicted), bool)
    a, b = close_pairs(predicted, reach)
    if not len(a) or not len(blobs):
        return out
    nearest = np.full(len(predicted), -1)
    ends = np.union1d(a, b)
    nearest[ends] = cKDTree(blobs).query(predicted[ends])[1]
    for x, y in ((a, b), (b, a)):  # x matched, y not, y's nearest blob x's
        merged = (index[x] >= 0) & (index[y] < 0) & (nearest[y] == index[x])
        out[x[merged]] = True
    return out


def _match(predicted: np.ndarray, blobs: np.ndarray, tol: float) -> np.ndarray:
    """One-to-one: each predicted dot's nearest blob within `tol`, nearer claims first; -1 if
    none."""
    d = np.linalg.norm(predicted[:, None] - blobs[None], axis=-1)
    d = np.where(np.isfinite(d), d, np.inf)
    index = np.full(len(predicted), -1)
    taken = np.zeros(len(blobs), bool)
    for flat in np.argsort(d, axis=None):
        m, j = divmod(int(flat), len(blobs))
        if d[m, j] >= tol:
            break
        if index[m] < 0 and not taken[j]:
            index[m], taken[j] = j, True
    return index


def _refined(P, world, blobs, tol, iterations=3):
    """Match, fit a DLT to all matched dots, match again; returns (index, P, rms) or None."""
    index = _match(_project(P, world), blobs, tol)
    for _ in range(iterations):
        found = index >= 0
        if found.sum() < 6:
            return None
        pixels = np.where(found[:, None], blobs[np.maximum(index, 0)], 0.0)
        P = _fit(world, pixels, found)
        if not np.isfinite(P).all():
            return None
        new = _match(_project(P, world), blobs, tol)
        if np.array_equal(new, index):
            break
        index = new
    found = index >= 0
    if found.sum() < 6:
        return None
    residual = _project(P, world)[found] - blobs[index[found]]
    return index, P, float(np.sqrt(np.mean(np.sum(residual**2, axis=-1))))


def _candidates(major, distances, min_ratio: float, max_candidates: int) -> np.ndarray:
    """Blobs markedly larger than their neighbours, largest ratio first.

    A blob is compared with the second smallest of its six nearest neighbours: near it in the
    image and so (mostly) at about its distance from the camera, and, since fiducials are under
    half of the dots and never side by side, a small dot. `distances` is the blobs' distance
    matrix with an infinite diagonal.
    """
    ratio = _size_ratios(major, distances)
    order = np.argsort(-ratio, kind="stable")
    return order[ratio[order] > min_ratio][:max_candidates]


def _size_ratios(major, distances) -> np.ndarray:
    """Each blob's major axis over the second smallest of its six nearest neighbours' (see
    `_candidates`): how much larger than its neighbours a dot is printed."""
    k = min(6, len(major) - 1)
    neighbours = np.argsort(distances, axis=1)[:, :k]
    reference = np.sort(major[neighbours], axis=1)[:, min(1, k - 1)]
    return major / reference


def _score(P, world, blobs, tol) -> np.ndarray:
    """How many dots each hypothesis `P (H, 3, 4)` projects within `tol` of some blob."""
    score = np.zeros(len(P), int)
    for start in range(0, len(P), 2048):  # chunks bound the (H, M, K) distance array
        px = _project(P[start : start + 2048], world)
        d2 = (px[..., 0, None] - blobs[:, 0]) ** 2 + (px[..., 1, None] - blobs[:, 1]) ** 2
        with np.errstate(invalid="ignore"):
            score[start : start + 2048] = np.sum(d2.min(-1) < tol * tol, axis=1)
    return score


def check_kinds(function: str, detection, target=None) -> None:
    """Refuse what is not a `Detection` (an image given in its place is a common slip) or, with
    `target`, not a `Target`, saying what to pass."""
    if not isinstance(detection, Detection):
        raise TypeError(
            f"{function} takes the dots `mc.detect_dots(image)` found, a Detection; got "
            f"{type(detection).__name__}."
        )
    if target is not None:
        check_target(target, f"{function}'s `target`")


def label_dots(
    detection: Detection,
    target: Target,
    *,
    tolerance: float = 0.3,
    max_rms: float | None = None,
    min_dots: int | None = None,
    min_ratio: float = 1.3,
    max_candidates: int = 8,
    keep: int = 8,
    max_sets: int = 12,
) -> Labels:
    """Tell which detected blob is which dot of `target`, with no human in the loop.

    See the module notes for the method (fiducial dots, batched 6-point DLT hypotheses, and
    verification against every other dot). A view it cannot label with certainty comes back with
    `ok=False` and an empty mask, never with a wrong label.

    **Arguments:**

    - `detection`: the blobs found in one image (`mvcalib.detect_dots`).
    - `target`: the target photographed; it needs 6 to 9 `fiducials`, not all coplanar
      (`mvcalib.targets.box_corner()` has eight, so that up to two may be hidden).
    - `tolerance`: how far a blob may lie from a dot's predicted position and still be that dot,
      as a fraction of the typical distance between neighbouring blobs. Generous, because the
      first predictions come from only six dots; the final fit is judged by `max_rms`.
    - `max_rms`: the largest RMS fit (pixels) of the DLT camera to the labelled dots that is
      trusted; default 5 % of the typical distance between neighbouring blobs, which admits the
      few pixels strong lens distortion leaves in a linear camera.
    - `min_dots`: the fewest labelled dots that make a labelling; default 10 (so at least four
      dots confirm what six fiducials proposed).
    - `min_ratio`: how much larger (major axis) than its neighbours a blob must look to be a
      fiducial candidate. The box corner's fiducials are 1.75 times larger.
    - `max_candidates`: the most fiducial candidates tried (the largest ratios first): clutter of
      dot size can add some.
    - `keep`: how many of the best-scoring hypotheses of each set are refined.
    - `max_sets`: how many sets of six candidates are tried before the view is flagged.

    **Returns:** `Labels` (see there).

    **Example:**

    ```python
    >>> import jax, mvcalib as mc
    >>> target = mc.targets.box_corner()
    >>> camera = mc.synthetic.random_rig(jax.random.key(0), 1).cameras[0]
    >>> image = mc.synthetic.render(camera, target, key=0)
    >>> labels = mc.label_dots(mc.detect_dots(image), target)
    >>> labels.ok, int(labels.mask.sum())
    (True, 19)

    ```
    """
    check_kinds("label_dots", detection, target)
    fiducials = np.asarray(target.fiducials, dtype=int)
    world = np.asarray(target.points, dtype=np.float64)
    M, K, F = len(world), len(detection), len(fiducials)
    if F < 6 or F > 9:
        raise ValueError(
            f"target {target.name!r} has {F} fiducial dots; labelling needs 6 to 9 "
            "(larger dots, `Target.fiducials`), e.g. `mvcalib.targets.box_corner()`."
        )
    min_dots = 10 if min_dots is None else int(min_dots)
    if K < min_dots:
        return Labels.failed(M, K, f"only {K} blobs found; labelling needs {min_dots}")
    blobs = np.asarray(detection.centroids, dtype=np.float64)
    d = np.linalg.norm(blobs[:, None] - blobs[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    spacing = float(np.median(d.min(axis=1)))
    tol = tolerance * spacing
    max_rms = 0.05 * spacing if max_rms is None else float(max_rms)

    candidates = _candidates(np.asarray(detection.major), d, min_ratio, max_candidates)
    if len(candidates) < 6:
        return Labels.failed(
            M,
            K,
            f"found {len(candidates)} of the {F} fiducial dots (larger than their "
            "neighbours); 6 are needed",
        )
    # 2. Hypotheses: six candidate blobs (the likeliest sets first), and every way they can be
    # six of the target's fiducials. One DLT each, all in one batched call per set.
    maps = np.array(list(itertools.permutations(range(F), 6)))  # blob k is fiducial maps[:, k]
    if len(maps) > _MAX_HYPOTHESES:
        raise ValueError(f"target has {F} fiducials: {len(maps)} hypotheses per set; use fewer.")
    message = f"no assignment of the fiducials explains {min_dots} dots"
    for subset in itertools.islice(itertools.combinations(candidates, 6), max_sets):
        P, misfit = _six_point_cameras(world[fiducials[maps]], blobs[list(subset)])
        # 3. Verify: the six must fit a camera, which must bring the other dots onto blobs;
        # refine the best few.
        plausible = np.flatnonzero(misfit < tol)
        P = P[plausible]
        score = _score(P, world, blobs, tol)
        best = []
        for h in np.argsort(-score, kind="stable")[:keep]:
            if score[h] < min_dots:
                break
            refined = _refined(P[h], world, blobs, tol)
            if refined is not None:
                best.append(refined)
        if not best:
            continue
        best.sort(key=lambda r: (-(r[0] >= 0).sum(), r[2]))
        index, _, rms = best[0]
        n = int((index >= 0).sum())
        rivals = [r for r in best[1:] if not np.array_equal(r[0], index)]
        if rivals and (rivals[0][0] >= 0).sum() >= n and rivals[0][2] <= 2 * rms:
            message = "ambiguous: two different labellings explain the dots equally well"
        elif n < min_dots:
            message = f"only {n} dots labelled; need {min_dots}"
        elif not rms <= max_rms:
            message = f"the labelled dots fit a camera to {rms:.2f} px RMS only (max {max_rms:.2f})"
        else:
            break
    else:
        return Labels.failed(M, K, message)
    message = f"{n} of {M} dots labelled, {K - n} other blobs, fit {rms:.2f} px RMS"
    return Labels.matched(blobs, index, rms, message)
