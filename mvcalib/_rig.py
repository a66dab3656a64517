"""Calibration of a rig from a target moved through its volume: every camera's intrinsics,
distortion and pose, and the target's pose in every frame, from observations `(C, F, N)`.

The closed form first, batched over every (camera, frame) pair: a planar target's homography and
each camera's starting intrinsics (its focal length the median of its frames' own, the principal
point at the centre), then each pair's target pose (a 3-D target: the DLT of each pair); then
each camera's intrinsics, distortion and poses refined from its own frames (the rig's solver
with one camera, for one camera after the other on a CPU; from `OWN_FRAMES` of them at most, the
others posed again with the refined intrinsics). Each pair of cameras' relative pose
is the robust average (Weiszfeld's geometric median) over the frames both saw; the cameras are
chained to the reference over a maximum spanning tree of the camera graph weighted by shared
frames (Prim's algorithm, in a loop of C steps), and each frame's pose is the robust average of
its cameras' views of it. Then one Levenberg–Marquardt over all cameras and frames (an
optimistix solver, `_SchurLM`), whose normal equations are solved with the frames eliminated
(the Schur complement): a step costs `F (C P)^2` for the reduced camera system of `C P`
unknowns, linear in the number of frames. Outside `jit`, a camera that ends `POOR_FIT`, or fits
far worse than the rest, is calibrated against the rest of the rig and the rig solved once more
from there (`calibrate_rig`).
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _buckets, _dlt, _sharding, _small, _status, _validate
from ._camera import (
    LENSES,
    Camera,
    _lens,
    check_lens,
    finite_cameras,
    undistort_points,
    unit_camera,
    where_cameras,
)
from ._pipeline import CalibrationError
from ._planar import (
    MIN_PLANE_POINTS,
    _focal_lengths,
    _homography_kernel,
    _median_rms,
    _out_of_proportion,
    _plane_frame,
    _pose,
)
from ._refine import (
    _MIN_DAMPING,
    _RESULT_MESSAGES,
    POSE_INDICES,
    Cauchy,
    Huber,
    _definite_solve,
    _free_parameters,
    _irls,
    _pack,
    _parameters,
    _pixel_columns,
    _robust_residuals,
    _skew_model,
    _tied_columns,
    _unpack,
    check_loss,
    parameter_names,
    reported_covariance,
    residual_variance,
    warn_held_coefficients,
)
from ._registration import RigidTransform
from ._rotation import exp_and_left_jacobian, nearest_rotation, rodrigues
from ._status import Status

MIN_OBJECT_POINTS = _validate.MIN_POINTS  # the DLT of one (camera, frame) pair of a 3-D target
_ROTATION = POSE_INDICES[:3]
# Rigs of at most this many camera-frame-points are compiled quickly (`_buckets.jit`): the program
# holds two Levenberg–Marquardt solves, and its first call is mostly compiling. 4 cameras x 48
# frames x 48 points: first call 7.8 against 24.2 s, warm 1.0 against 0.3 s; 8 x 100 x 108: 12.0
# against 22.5 s, warm 4.3 against 1.3 s (a loaded machine, load 3).
QUICK_SIZE = 2**17
# A concrete rig's frames are padded up to `_buckets.size(F, MIN_FRAMES, bits=FRAME_BITS)`
# (32, 48, 64, 96, 128, ...: at most half as many again), so that recordings of other lengths
# reuse one compiled program: 4 cameras of a 9 x 12 board, 40, 45, 50 and 60 frames one after the
# other, took 2.8, 2.3, 2.2 and 2.5 s, 0.2 s of each running; now 2.7, 0.2, 2.5 and 0.2 s. The
# warm calls pay for the padded frames: 0.18 against 0.15 s (40 frames), 0.22 against 0.17 (50).
MIN_FRAMES, FRAME_BITS = 32, 2
# ... and its cameras up to `_buckets.size(C, bits=CAMERA_BITS)` (1-4 as they are, then 6, 8, 12,
# 16, 24, ...), with cameras that see nothing; the solves' outputs without a camera axis:
CAMERA_BITS = 2
_RIG_WIDE = frozenset({"target_poses", "rms", "frame_rms", "iterations", "result"})
# The results with a frame axis, and where it is (the rest have none).
_FRAME_AXIS = dict(target_poses=0, frame_rms=0, alone_rms=1, own_poses=1, residuals=1, observed=1,
                   used=1, inliers=1, poor_pairs=1)  # fmt: skip
# The worst camera, if its RMS is more than this many times the median of the rig's calibrated
# cameras, is calibrated again against the rest of the rig (`calibrate_rig`). 16 cameras x 100
# frames of a 6 x 8 board (key 10): camera 2's own frames put its focal length at 10,885 px in
# closed form and 5,020 after its own solve (the truth 1,300), and the joint solve ended in a
# minimum where it had 11.4 px and dragged the others to 0.8-5.4 (median 1.2; all OK: below the
# POOR_FIT bar); started again from its resection, the rig came out at 0.42 px.
_FAR_WORSE = 3.0
# Where every camera fits poorly, the rig is solved again without each of this many cameras (the
# worst fitting first) to find the one that pulled the rest (`_without_one`).
_SUSPECTS = 12
# A camera's Jacobian blocks are built this many frames at a time (on one CPU device), so that
# they stay in cache: the joint solve's step, 16 cameras of a 48-point board, 99 / 145 ms at
# 1000 / 2000 frames against 161 / 565 ms with all frames at once (linear in the frames again).
FRAME_CHUNK = 128
# Each camera's own solve, the start's larger part, takes at most this many of its frames (a
# start needs no more): 16 cameras x 1000 frames of a 6 x 8 board (each camera sees 200-600),
# the start 0.9-1.4 against 5.9-7.5 s warm, the same rig (RMS to 1e-15, the same 10 steps).
OWN_FRAMES = 128
# Two cameras' own poses of the target in a frame they share agree (`_agreeing`) where the
# relative pose they imply departs from the average over all the frames the two share by at most
# this many times the median departure over the rig's pairs of cameras, and no less than this
# many degrees and this fraction of the target's median distance. A `board_rig` of 5 cameras x
# 100 frames (key 15), after each camera's own solve: the frames of the pairs of good cameras
# depart 0.17 degrees and 0.2 % of the distance in the median (0.3 degrees and 0.6 % at most);
# those of a camera whose video was mirrored, 10-57 degrees and 12-80 % (the median of each
# pair): it agrees in none, the good cameras in 79-100 % of theirs. caliscope's recording, 10
# corners a frame: 2.6 degrees and 4 %, and every camera agrees in 69-92 % of its frames.
_AGREE_SPREAD, _AGREE_DEGREES, _AGREE_DISTANCE = 4.0, 5.0, 0.05
_AGREE_SAMPLE = 128
# A camera is judged (`_disagreeing`) on at least this many frames shared with the others (one
# agrees with itself; two of a good camera agree with each other).
_AGREE_MIN_FRAMES = 2
# A camera's frames are out of step with the others' (`_step_spread`) where its own poses of the
# target, taken one frame earlier or later along the frame axis, agree this many times better
# with the other cameras' own poses (the spread of the pairs' relative translations), over at
# least `_STEP_MIN_FRAMES` frames it shares with one of them. A user's trial: one camera of five
# one frame late, a board moving 13 mm a frame (30 frames a second), was OK, 125 mm off against a
# standard error of 2.3 mm, and pulled the others 45-110 mm. Its spread shifted by one frame is
# 3.9-4.7 times smaller over 400 frames of a board moving 10-20 mm a frame, 19 times over 240
# frames at 20 mm, but 1.3-1.5 times over 240 frames at 10-13 mm (not told: the poses of the
# closed form are too noisy); the cameras in step agree 1-16 times worse shifted (those of a
# recording whose frames are not consecutive, far worse). caliscope's recording: 0.4-1.2 times.
_STEP_BETTER, _STEP_MIN_FRAMES = 2.0, 10


# ------------------------------------------------------------------------------ the result
_TOO_FEW_IN_A_RIG = (
    "too few points: no frame shows it enough of the target (4 points of a board, 6 of a 3-D "
    "target) to pose it"
)
_DISAGREEING = (
    "poor fit: its own poses of the target disagree with the other cameras' in most of the "
    "frames they share, so no one place in the rig fits it, and it was left out: is its image "
    "mirrored, are its point ids mirrored or out of order, are its frames out of step with the "
    "others', or are they another camera's?"
)
_DEGENERATE_IN_A_RIG = (
    "degenerate: its frames of the target do not determine its intrinsics (one view of a board, "
    "or views of it from one direction, cannot): record more frames of it at other angles, or "
    "give its intrinsics (`cameras=` with `fix='intrinsics'`; mvcalib calibrate-rig --intrinsics)"
)


class SolveFailed(CalibrationError):
    """`calibrate_rig`'s joint solve left every camera POOR_FIT (a `ValueError`, and the
    `mvcalib.CalibrationError` a strict `calibrate` raises)."""

    def __init__(
        self, rms: float, iterations: int, lens: str = "pinhole", worst: str = "", result=None
    ):
        self.rms, self.iterations, self.lens, self.result = rms, iterations, lens, result
        wide = "; for wide-angle lenses, `lens='fisheye'`" if lens == "pinhole" else ""
        super().__init__(
            "the rig's joint solve failed: every camera reprojects its points with an RMS above "
            f"`max_relative_rms` of their spread (RMS {rms:.3g} px after {iterations} steps"
            f"{worst}). Check that the detections match the target's points (ids, order, "
            "units; a grid without markers numbers its dots only up to its half turn); for "
            "wrong detections, a robust `loss=mc.Huber(2.0)` (or `mc.Cauchy(2.0)` "
            f"for many); or start from known `cameras=`{wide}."
        )


class RigCalibration(eqx.Module):
    """The result of `calibrate_rig`.

    - `cameras`: `(C,)` in the reference frame (camera `reference`'s, or the target's in the
      origin frame); NaN for cameras whose `status` is not OK.
    - `target_poses`: `(F,)` the target's pose in each frame, target to reference frame (`Y = R X
      + t`); NaN for frames no calibrated camera saw with enough points.
    - `status`: `(C,)` per camera (`mvcalib.Status`): OK; TOO_FEW_POINTS (no frame with enough
      points); DEGENERATE (its frames do not determine its intrinsics); NOT_CONNECTED (no chain
      of shared frames links it to the reference camera); POOR_FIT (its reprojection RMS
      exceeds `max_relative_rms` of its pixels' spread: the solve failed, or its detections are
      wrong; or, its RMS NaN, its own poses of the target disagree with the other cameras', and
      it took no part in the solve).
    - `initial`: `(C,)` the closed-form cameras that seeded the refinement.
    - `rms`: reprojection RMS over every observation used (pixels); `camera_rms` `(C,)`,
      `frame_rms` `(F,)` the same per camera and per frame (a POOR_FIT camera's from the solve
      that flagged it).
    - `alone_rms`: `(C, F)` each (camera, frame) pair's RMS with its points fitted alone, by a
      homography (a board) or a DLT (a 3-D target), per degree of freedom: no intrinsics, lens
      or pose held (a given lens's distortion removed first), about the noise of the detections
      where the distortion is small; NaN where the pair's closed form failed. A camera whose
      frames fit several times worse in the rig says so (`messages`).
    - `own_poses`: `(C, F)` each (camera, frame) pair's own pose of the target (target to
      camera), from its points alone and its camera's own solve, before the cameras were
      linked; NaN where the pair had none. `step_spread` `(C, 3)`: how far each camera's own
      poses disagree with the other cameras' (the spread of the pairs' relative translations
      over the target's distance) with its frames shifted by -1, 0 and +1 along the frame axis:
      a camera whose frames are out of step by one agrees better shifted, and says so
      (`messages`); NaN where it shares too few frames.
    - `residuals`: `(C, F, N, 2)` reprojected minus observed for every observation of a
      calibrated camera in a frame with a pose (`observed`, the skipped pairs' too), zero
      elsewhere; `used` `(C, F, N)` the observations that took part in the fit; `inliers` those
      within 3 scales of a robust loss; `rms_observed` the RMS over all of `observed`.
    - `skipped`: `(C, F)` the pairs that had observations but too few points (fewer than 4 of a
      planar target, 6 of a 3-D one) and were left out; `n_skipped` how many.
    - `position_std`: `(C, 3)` standard errors of each camera's centre (world units), and
      `rotation_std` `(C, 3)` of its rotation (degrees, about the camera's axes), in the gauge
      of the solve's reference camera, which has none (`reference`; with `reference="target"`,
      the camera that saw the most frames); `parameter_std` `(C, P)` of the free parameters
      `parameter_names` (with alpha_u, which follows alpha_v, where `fix="aspect_ratio"`), whose
      covariance blocks are `covariance` `(C, P, P)`.
    - `iterations`, `result` (an `optx.RESULTS` index, 0 = successful).
    - `origin_frame`: with `reference="target"`, the frame (an index along the frame axis) whose
      target pose is the world frame; else None.
    """

    cameras: Camera
    target_poses: RigidTransform
    status: Int[Array, " C"]
    initial: Camera
    rms: Float[Array, ""]
    camera_rms: Float[Array, " C"]
    frame_rms: Float[Array, " F"]
    alone_rms: Float[Array, "C F"]
    own_poses: RigidTransform
    residuals: Float[Array, "C F N 2"]
    observed: Bool[Array, "C F N"]
    used: Bool[Array, "C F N"]
    inliers: Bool[Array, "C F N"]
    skipped: Bool[Array, "C F"]
    position_std: Float[Array, "C 3"]
    rotation_std: Float[Array, "C 3"]
    parameter_std: Float[Array, "C P"]
    covariance: Float[Array, "C P P"]
    iterations: Int[Array, ""]
    result: Int[Array, ""]
    parameter_names: tuple[str, ...] = eqx.field(static=True)
    origin_frame: int | None = eqx.field(static=True, default=None)

    @property
    def ok(self) -> Bool[Array, " C"]:
        return _status.ok(self.status)

    @property
    def converged(self) -> Bool[Array, ""]:
        return _validate.derived(lambda xp, r: r == 0, self.result)

    @property
    def rms_observed(self) -> Float[Array, ""]:
        def rms(xp, residuals, observed):
            square = xp.sum(residuals**2, -1)
            return xp.sqrt(xp.sum(square) / xp.maximum(xp.sum(observed), 1))

        return _validate.derived(rms, self.residuals, self.observed)

    @property
    def rms_inliers(self) -> Float[Array, ""]:
        """The RMS over `inliers`: with a robust loss, what the fit makes of the observations it
        believes (`rms` counts the wrong detections it discounted too); else `rms`."""

        def rms(xp, residuals, inliers):
            square = xp.sum(residuals**2, -1)
            return xp.sqrt(xp.sum(xp.where(inliers, square, 0)) / xp.maximum(xp.sum(inliers), 1))

        return _validate.derived(rms, self.residuals, self.inliers)

    @property
    def step_spread(self) -> np.ndarray:
        return _step_spread(np.asarray(self.own_poses.R), np.asarray(self.own_poses.t))

    @property
    def n_skipped(self) -> Int[Array, ""]:
        return _validate.derived(lambda xp, s: xp.sum(s), self.skipped)

    def messages(self) -> list[str]:
        """One line per camera: its status's message, in a rig's words where they differ from
        a single camera's (a degenerate camera's frames did not determine its intrinsics; too
        few points are fewer than a board's 4 or a 3-D target's 6 in every frame; a camera left
        out for poses that disagree with the rest's says so); for a
        calibrated camera, a note where the joint solve stopped before converging, where its
        frames seem one out of step with the other cameras' (`step_spread`), or another
        camera's do, where its frames fit more than 3 times worse in the rig than each alone
        (`alone_rms`, medians over its frames), else where its RMS is more than twice the median
        of the rig's other calibrated cameras (`_misfit_note`; with a robust loss, over the
        observations it believes), where a robust
        loss set aside more than a fifth of its observations, and (least squares) where some
        of its observations lie far beyond the rest (`_far_note`), or another camera's do
        (`_pulled_note`)."""
        in_a_rig = {
            Status.DEGENERATE: _DEGENERATE_IN_A_RIG,
            Status.TOO_FEW_POINTS: _TOO_FEW_IN_A_RIG,
        }
        messages = [in_a_rig.get(int(s), Status(int(s)).message) for s in np.asarray(self.status)]
        if np.ndim(self.status) != 1:
            return messages
        for c in np.flatnonzero(_left_out(self)):
            messages[c] = _DISAGREEING
        used, inliers = np.asarray(self.used), np.asarray(self.inliers)
        robust = bool((used != inliers).any())  # (a robust loss's)
        square = np.sum(np.asarray(self.residuals) ** 2, -1)
        alone = np.asarray(self.alone_rms)
        rms = _camera_rms(square, inliers if robust else used)
        calibrated = np.flatnonzero(np.asarray(self.status) == Status.OK)
        held = _held(self.parameter_names)
        if "intrinsics" in held:
            for c in np.flatnonzero(np.asarray(self.status) == Status.POOR_FIT):
                messages[c] += f"; {_HELD_INTRINSICS}"
        stopped = "" if int(self.result) == 0 else (
            f"; but the joint solve stopped after {int(self.iterations)} steps without "
            "converging (`print` the result for why): its parameters are not the least-squares "
            "answer"
        )  # fmt: skip
        cameras = jax.tree_util.tree_map(np.asarray, self.cameras)
        judged = inliers if robust else used
        frames = {c: _in_rig_and_alone(square[c], judged[c], alone[c]) for c in calibrated}
        # (far observations of a camera whose every frame fits worse in the rig are its model's
        # misfit, not wrong detections: the note about it says so)
        far = {} if robust else {
            c: "" if _systematic(*frames[c]) else _far_note(np.sqrt(square[c][used[c]]))
            for c in calibrated
        }  # fmt: skip
        pulling = [int(c) for c, note in far.items() if note]
        spread = self.step_spread
        steps = {c: _step_note(spread[c]) for c in calibrated}
        stepping = [int(c) for c, note in steps.items() if note]
        for c in calibrated:
            messages[c] += stopped
            messages[c] += steps[c] or _stepping_note(stepping)
            if robust:
                messages[c] += _set_aside_note(int(used[c].sum()), int(inliers[c].sum()))
            else:
                messages[c] += far[c] or ("" if "pose" in held else _pulled_note(pulling))
            others = rms[calibrated[calibrated != c]]
            messages[c] += _misfit_note(float(rms[c]), others, held, frames[c])
            if cameras.lens == "pinhole":
                messages[c] += _fold_note(cameras[c])
        return messages

    def __str__(self) -> str:
        return self.table()

    def table(self, names: Sequence[str] | None = None) -> str:
        """The result as text: a headline, and a row per camera (named by `names`, else by its
        index) with its frames, points, RMS, the standard error of its centre and its status (a
        camera not calibrated: the frames where it posed the target alone, `own_poses`, and no
        points; until 2026-12-06 zero of each, which hid the data a camera left out had)."""
        if not _validate.is_concrete(self.status) or np.ndim(self.status) != 1:
            return repr(self)  # (traced, or a batch of results from `jax.vmap`)
        status = np.asarray(self.status)
        names = [str(c) for c in range(len(status))] if names is None else [str(n) for n in names]
        if len(names) != len(status):
            raise ValueError(f"{len(names)} names for the {len(status)} cameras.")
        width = max(6, *map(len, names))
        used, inliers = np.asarray(self.used), np.asarray(self.inliers)
        rms, n = np.asarray(self.camera_rms), used.sum(axis=(1, 2)).astype(object)
        frames = used.any(-1).sum(-1)
        out = status != Status.OK
        frames[out] = np.isfinite(np.asarray(self.own_poses.t)).all(-1).sum(-1)[out]
        n[out] = "-"
        pos = np.asarray(self.position_std)
        # with a robust loss, the RMS of the observations it believes, beside the RMS of all
        robust = bool((used != inliers).any())
        lines = [
            f"rig of {len(status)} cameras, {self.frame_rms.shape[0]} frames: RMS "
            f"{float(self.rms):.3f} px, {_outcome(int(self.result), int(self.iterations))}; "
            f"{int(self.n_skipped)} (camera, frame) pairs skipped (too few points)",
            f"{'camera':<{width}}  frames  points  rms (px)  centre std  status",
        ]
        if robust:
            lines.insert(
                1,
                f"inliers (within 3 scales of the loss): {int(inliers.sum())} of {int(used.sum())} "
                f"observations, RMS {float(self.rms_inliers):.3f} px",
            )
            lines[-1] = (
                f"{'camera':<{width}}  frames  points  rms (px)  inliers  inlier rms  centre std  "
                "status"
            )
            k = inliers.sum(axis=(1, 2))
            rms_in = _camera_rms(np.sum(np.asarray(self.residuals) ** 2, -1), inliers)
        for c in range(len(status)):
            columns = f"{names[c]:<{width}}  {frames[c]:>6}  {n[c]:>6}  {rms[c]:>8.3f}  "
            if robust:
                columns += f"{k[c]:>7}  {rms_in[c]:>10.3f}  "
            lines.append(
                columns + f"{np.linalg.norm(pos[c]):>10.3g}  {Status(int(status[c])).name}"
            )
        gauge = np.flatnonzero((status == Status.OK) & np.all(pos == 0, -1))
        if len(gauge) == 1:  # (the solve's reference: the others' errors are relative to it)
            lines.append(
                f"centre std: in the target's units, relative to camera {names[gauge[0]]}'s "
                "centre (the solve's reference camera, whatever the world frame)"
            )
        if self.origin_frame is not None:
            lines.append(f"world frame: the target in frame {self.origin_frame}")
        return "\n".join(lines)


# ------------------------------------------------------------------------------ closed form
def _weiszfeld(x, w, iterations: int = 20):
    """The weighted geometric median of the rows of `x (F, k)` (Weiszfeld's iteration from the
    weighted mean), robust to a minority of wild rows; NaN where every weight is zero."""
    x = jnp.where(w[:, None] > 0, x, 0.0)
    total = jnp.sum(w)
    m = jnp.sum(w[:, None] * x, 0) / total
    floor = 1e-12 * (jnp.max(jnp.abs(x)) + 1.0)

    def step(m, _):
        d = jnp.maximum(jnp.linalg.norm(x - m, axis=1), floor)
        v = w / d
        return jnp.sum(v[:, None] * x, 0) / jnp.sum(v), None

    return jax.lax.scan(step, m, None, length=iterations)[0]


def _average_pose(R, t, w):
    """The robust average of poses `R (F, 3, 3)`, `t (F, 3)` weighted by `w (F,)`: the nearest
    rotation to the geometric median of the matrices (chordal), the median of the translations."""
    m = _weiszfeld(R.reshape(-1, 9), w).reshape(3, 3)
    return nearest_rotation(m), _weiszfeld(t, w)


def _pair_poses_planar(plane, xy, pixels, mask, K, rcond):
    """Each (camera, frame) pair's target pose from its homography and its status, and each
    camera's K (from its own frames, `_focal_lengths`, unless given)."""
    homography = jax.vmap(
        jax.vmap(functools.partial(_homography_kernel, rcond=rcond), (None, 0, 0)), (None, 0, 0)
    )
    H, status = homography(xy, pixels, mask)
    ok = status == Status.OK
    determined = jnp.ones(ok.shape[0], bool)
    if K is None:
        # not Zhang's closed form: with boards that face one camera each, its five unknowns
        # came out 50-70 % off in focal length for some cameras (16 cameras x 250 frames of a
        # 6 x 8 board), from where no solve recovered
        K, found = jax.vmap(_focal_lengths)(H, ok, pixels, mask & ok[..., None])
        determined = found & (jnp.sum(ok, 1) >= 2)
    R, t = _planar_poses(plane, xy, K, H, mask)
    return K, determined, R, t, status, H


def _planar_poses(plane, xy, K, H, mask):
    """Each (camera, frame) pair's target pose from its homography `H` and its camera's `K`."""
    pose = jax.vmap(jax.vmap(_pose, (None, 0, None, 0)), (0, 0, None, 0))
    R, t = pose(K, H, xy, mask)
    # from the plane's frame back to the target's: x_cam = R (A X + b) + t
    return R @ plane.R, jnp.einsum("cfij,j->cfi", R, plane.t) + t


def _pair_poses_object(target, pixels, mask, K, rcond):
    """Each (camera, frame) pair's camera from the DLT and its status; each camera's K the
    median over its frames unless given."""
    C, F = mask.shape[:2]
    N = target.shape[0]
    P, status, _, _ = _dlt.solve_validated(
        target,
        pixels.reshape(C * F, N, 2),
        mask.reshape(C * F, N),
        rcond,
        _dlt.DEFAULT_MAX_RELATIVE_RMS,
    )
    cams = Camera.from_projection(P.reshape(C, F, 3, 4), skew=False)
    status = status.reshape(C, F)
    ok = status == Status.OK
    determined = jnp.any(ok, 1)
    if K is None:
        med = lambda x: _dlt._masked_median(x, ok, sort=True)  # noqa: E731, SLF001
        au, av, u0, v0 = (med(x) for x in (cams.alpha_u, cams.alpha_v, cams.u0, cams.v0))
        zero = jnp.zeros_like(au)
        K = jnp.stack(
            [
                jnp.stack([au, zero, u0], -1),
                jnp.stack([zero, av, v0], -1),
                jnp.stack([zero, zero, zero + 1.0], -1),
            ],
            -2,
        )
    return K, determined, cams.R, cams.t, status, P.reshape(C, F, 3, 4)


def _alone_rms(projected, pixels, fitted, parameters: int):
    """`(C, F)`: each (camera, frame) pair's RMS where its points `fitted` are fitted alone, by a
    model of `parameters` per pair (a homography's 8, a DLT's 11) that projects them to
    `projected` `(C, F, N, 2)`, counted per degree of freedom (`sqrt(sum / (n - parameters / 2))`:
    what the pixels' noise gives, as a pair's RMS in the rig with its pose alone free does);
    NaN with too few points."""
    square = jnp.sum(jnp.where(fitted[..., None], projected - pixels, 0.0) ** 2, -1)
    dof = jnp.sum(fitted, -1) - parameters / 2
    return jnp.where(dof >= 1, jnp.sqrt(jnp.sum(square, -1) / jnp.maximum(dof, 1)), jnp.nan)


def _relative_poses(R, t, ok, distance):
    """For every pair of cameras (c, d): camera d's frame to camera c's, `(C, C, 3, 3)`,
    `(C, C, 3)`, the robust average over the frames both saw; how many frames they share; and
    in how many of those the two cameras' own poses agree with that average (`_agreeing`)."""

    def from_d(inputs):
        Rd, td, okd = inputs  # (F, 3, 3), (F, 3), (F,)
        Rcd = jnp.einsum("cfij,fkj->cfik", R, Rd)
        tcd = t - jnp.einsum("cfij,fj->cfi", Rcd, td)
        w = (ok & okd[None]).astype(R.dtype)
        Rm, tm = jax.vmap(_average_pose)(Rcd, tcd, w)
        # each frame's departure from the average: the angle between the rotations (from the
        # trace of one times the other's transpose) and the distance between the translations
        cos = (jnp.einsum("cfij,cij->cf", Rcd, Rm) - 1.0) / 2.0
        turned = jnp.rad2deg(jnp.arccos(jnp.clip(cos, -1.0, 1.0)))
        moved = jnp.linalg.norm(tcd - tm[:, None], axis=-1) / distance
        return Rm, tm, w, turned, moved

    eye = jnp.eye(3, dtype=R.dtype)
    safe = lambda a, k: jnp.where(ok.reshape(ok.shape + (1,) * k), a, eye if k == 2 else 0.0)  # noqa: E731
    Rs, ts = safe(R, 2), safe(t, 1)
    # (the map runs over d): Rm[d, c] is d -> c
    Rm, tm, w, turned, moved = (jnp.swapaxes(x, 0, 1) for x in jax.lax.map(from_d, (Rs, ts, ok)))
    return Rm, tm, jnp.sum(w, -1), _agreeing(w > 0, turned, moved)


def _agreeing(both, turned, moved):
    """How many of the frames two cameras share `(C, C)` (`both`, `(C, C, F)`) agree with their
    average relative pose: within `_AGREE_SPREAD` times the median departure over all pairs'
    shared frames, and no less than `_AGREE_DEGREES` and `_AGREE_DISTANCE` of the
    target's distance (a frame's poses are as good as its points: caliscope's recording, 10 of a
    board's corners a frame, departs 2.6 degrees and 4 % of the distance in the median; a
    `board_rig` of 108 corners 0.17 degrees and 0.2 %)."""
    C, _, F = both.shape
    pairs = both & ~jnp.eye(C, dtype=bool)[..., None]
    # (the median from at most `_AGREE_SAMPLE` frames, evenly spread: 64 cameras x 1024 frames
    # took 0.25 s, all of them sorted)
    every = max(1, F // _AGREE_SAMPLE)
    flat = lambda x: x[..., ::every].reshape(-1)  # noqa: E731
    median = lambda x: _dlt._masked_median(flat(x), flat(pairs), sort=True)  # noqa: SLF001, E731
    degrees = jnp.maximum(_AGREE_DEGREES, _AGREE_SPREAD * median(turned))
    distance = jnp.maximum(_AGREE_DISTANCE, _AGREE_SPREAD * median(moved))
    return jnp.sum(both & (turned <= degrees) & (moved <= distance), -1).astype(turned.dtype)


def _step_spread(R, t) -> np.ndarray:
    """`(C, 3)`, in NumPy: for each camera, with its frames shifted by -1, 0 and +1 along the
    frame axis (its frame `f + s` against the others' `f`), the spread of the relative
    translations to every other camera over the frames they share (the median distance from the
    pair's median, over the target's median distance), the median over the other cameras; from
    the pairs' own poses of the target `R (C, F, 3, 3)`, `t (C, F, 3)` (NaN where none), at most
    `_AGREE_SAMPLE` frames evenly spread. NaN where a camera shares fewer than
    `_STEP_MIN_FRAMES` with every other. (The spread against the rig's solution instead, which
    the camera out of step has pulled: 2-3 times where this gives 4-19.)"""
    C, F = t.shape[:2]
    out = np.full((C, 3), np.nan)
    seen = np.isfinite(t).all(-1)
    if F < 3 or not seen.any():
        return out
    distance = np.median(np.linalg.norm(t[seen], axis=-1))
    f = np.arange(1, F - 1, max(1, (F - 2) // _AGREE_SAMPLE))
    # camera d's centre in the target's frame, u = -Rd' td: the relative translation of d to c
    # is tc + Rc u, one matrix product per frame over every pair (c, d)
    u = -np.einsum("dsji,dsj->sid", R[:, f], t[:, f])  # (S, 3, C)
    for k, s in enumerate((-1, 0, 1)):
        Rc = np.swapaxes(R[:, f + s], 0, 1).reshape(len(f), C * 3, 3)
        moved = (Rc @ u).reshape(len(f), C, 3, C) + np.swapaxes(t[:, f + s], 0, 1)[..., None]
        tcd = np.moveaxis(moved, (1, 2, 3, 0), (0, 3, 1, 2))  # (C, C, S, 3)
        off = tcd - _nan_median(tcd, 2)[:, :, None]
        away = np.sqrt(np.sum(off * off, -1)) / distance
        pair = _nan_median(away, 2)
        pair[(np.isfinite(away).sum(-1) < _STEP_MIN_FRAMES) | np.eye(C, dtype=bool)] = np.nan
        out[:, k] = _nan_median(pair, 1)
    return out


def _nan_median(x, axis: int):
    """`np.nanmedian` along `axis` (NaN where every entry is), several times faster and without
    its warnings: NaN sort last, and the middle of the finite entries is picked."""
    x = np.sort(x, axis)
    n = np.isfinite(x).sum(axis, keepdims=True)
    pick = lambda k: np.take_along_axis(x, np.clip(k, 0, x.shape[axis] - 1), axis)  # noqa: E731
    middle = 0.5 * (pick((n - 1) // 2) + pick(n // 2))
    return np.squeeze(np.where(n > 0, middle, np.nan), axis)


def _disagreeing(shared, agree):
    """The cameras `(C,)` whose own poses disagree with the other cameras' in most of the frames
    they share (`_relative_poses`), one at a time, the worst first, each judged without the
    cameras found before it, and while more than two are left: a camera whose image or point ids
    are mirrored, or whose frames are out of step with the rest, has no rigid place in the rig
    (a user's trial: one webcam's video mirrored, and a robust loss kept it, OK at 0.41 px, 35
    degrees and a metre off, and threw out a good camera). Judged on `_AGREE_MIN_FRAMES` shared
    frames or more."""
    C = shared.shape[0]
    others = ~jnp.eye(C, dtype=bool)  # (a camera's frames agree with themselves)

    def step(_, out):
        keep = others & ~out[None, :]
        s = jnp.sum(jnp.where(keep, shared, 0.0), 1)
        a = jnp.sum(jnp.where(keep, agree, 0.0), 1)
        fraction = jnp.where(~out & (s >= _AGREE_MIN_FRAMES), a / jnp.maximum(s, 1.0), jnp.inf)
        worst = jnp.argmin(fraction)
        return out.at[worst].set(out[worst] | (fraction[worst] < 0.5))

    return jax.lax.fori_loop(0, max(C - 2, 0), step, jnp.zeros(C, bool))


def _chain(Rrel, trel, shared, reference):
    """Every camera's pose in the reference camera's frame, over the maximum spanning tree of
    the camera graph weighted by shared frames (Prim's algorithm from `reference`); cameras the
    tree does not reach are not `linked`."""
    C = shared.shape[0]
    dtype = Rrel.dtype
    linked = jnp.arange(C) == reference
    R = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (C, 3, 3))
    t = jnp.zeros((C, 3), dtype)

    def grow(_, state):
        linked, R, t = state
        score = jnp.where(linked[None, :] & ~linked[:, None], shared, -1.0)  # [new c, from d]
        k = jnp.argmax(score)
        c, d = k // C, k % C
        grows = score.reshape(-1)[k] > 0
        Rc = Rrel[c, d] @ R[d]
        tc = Rrel[c, d] @ t[d] + trel[c, d]
        return (
            linked.at[c].set(linked[c] | grows),
            R.at[c].set(jnp.where(grows, Rc, R[c])),
            t.at[c].set(jnp.where(grows, tc, t[c])),
        )

    return jax.lax.fori_loop(0, C - 1, grow, (linked, R, t))


# The rig's start is three programs and its joint solve a fourth, so that XLA compiles each on a
# thread of its own while Python traces the next (`_buckets.chain`): XLA compiles on one core and
# without Python's lock. Caliscope's rig from a fresh process (2 cores): the first call 3.4-4.0 s
# as one program, 2.6-3.0 s as two. Only the middle one, the cameras' own solves, depends on the
# solve's options (`free`, `loss`, `max_steps`): a call with other options compiles the poses of
# every pair, the chain and the averaging no more (the larger part of the start: a 4 x 20 board
# rig's compiled in 1.96 s without the own solves, 3.27 s with them).
@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _start_pairs(data, rcond, *, planar, given):
    """Every (camera, frame) pair's closed form: the cameras' first intrinsics (`Camera`s posed
    by their first frame), the pairs' poses (target to camera) `Rp`, `tp`, which are `ok`, the
    cameras whose intrinsics are `determined`, each pair's status and what its points fit to
    alone, the target's median distance, and the homographies `H` (planar; else None).

    No derivatives flow through the start: `calibrate_rig` passes traced inputs through
    `stop_gradient` before the call, so that under `grad` these programs are not linearised.
    `data`, as each of the start's programs takes it: target, its plane's frame, pixels, mask and
    the given cameras (or None)."""
    target, plane, pixels, mask, cameras = data
    C = mask.shape[0]
    dtype = pixels.dtype
    closed = mask  # the points the closed form takes
    if given:  # the given lens distortion removed first, so that the closed form is exact
        pixels = undistort_points(jax.tree_util.tree_map(lambda x: x[:, None], cameras), pixels)
        closed = mask & jnp.all(jnp.isfinite(pixels), -1)  # (a fisheye's beyond 90: NaN)
        pixels = jnp.where(closed[..., None], pixels, 0.0)
    K = cameras.K if given else None
    H = None
    if planar:
        xy = plane.apply(target)[:, :2]
        K, determined, Rp, tp, pair_status, H = _pair_poses_planar(
            plane, xy, pixels, closed, K, rcond
        )
        x = jnp.einsum("cfij,nj->cfni", H[..., :2], xy) + H[..., None, :, 2]
    else:
        K, determined, Rp, tp, pair_status, P = _pair_poses_object(target, pixels, closed, K, rcond)
        x = jnp.einsum("cfij,nj->cfni", P[..., :3], target) + P[..., None, :, 3]
    ok = pair_status == Status.OK
    # what each pair's points fit to alone, with no intrinsics or lens to hold (`messages`)
    alone = _alone_rms(x[..., :2] / x[..., 2:], pixels, closed, 8 if planar else 11)
    alone = jnp.where(ok, alone, jnp.nan)
    # (a pose that passed its own checks may still not be finite: with exact pixels and all but
    # one visible point of a 3-D target on one face, the DLT's null space is two-dimensional and
    # a rank-one P can come out, which does not decompose)
    finite = jnp.all(jnp.isfinite(Rp), (-2, -1)) & jnp.all(jnp.isfinite(tp), -1)
    ok = ok & determined[:, None] & finite
    distance = _dlt._masked_median(  # noqa: SLF001
        jnp.linalg.norm(tp, axis=-1).reshape(-1), ok.reshape(-1), sort=True
    )
    dist = cameras.dist if given else jnp.zeros((C, 5), dtype)
    own = Camera(
        K[:, 0, 0],
        K[:, 1, 1],
        K[:, 0, 2],
        K[:, 1, 2],
        Rp[:, 0],
        tp[:, 0],
        skew=K[:, 0, 1],
        dist=dist,
        lens=cameras.lens if given else "pinhole",
    )
    return own, Rp, tp, ok, determined, pair_status, alone, distance, H


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _start_own(data, pairs, *, planar, free, loss, max_steps):
    """Each camera alone with its own frames (`_start_pairs`' `pairs`, cameras not given): its
    intrinsics, distortion and the target's poses (the closed form neglects the distortion,
    which the rig's cameras share no frames to fix). Given cameras need none of it: their pixels
    were undistorted with their own lens, and the closed-form poses start the joint solve as well
    (caliscope's rig: the same 8 steps to the same RMS, in 0.04 against 0.29 s a call). Returns
    `pairs` with the cameras and poses refined, and which pairs the solves took."""
    target, plane, pixels, mask, _ = data
    own, Rp, tp, ok, determined, pair_status, alone, distance, H = pairs
    C, F = mask.shape[:2]
    if F <= OWN_FRAMES:
        own, Rp, tp = _refine_own(
            own, Rp, tp, ok, distance, target, pixels, mask, free, loss, max_steps
        )
        return (own, Rp, tp, ok, determined, pair_status, alone, distance, H), ok
    # the same from `OWN_FRAMES` of each camera's frames, evenly spread; the other frames' poses
    # from their homographies again, with the refined K (a 3-D target's DLT poses need no K)
    take = _own_frames(ok, OWN_FRAMES)
    pick = lambda a: jnp.take_along_axis(  # noqa: E731
        a, take.reshape(take.shape + (1,) * (a.ndim - 2)), axis=1
    )
    used = pick(ok)
    own, Rs, ts = _refine_own(
        own, pick(Rp), pick(tp), used, distance, target, pick(pixels), pick(mask), free, loss,
        max_steps,
    )  # fmt: skip
    if planar:
        xy = plane.apply(target)[:, :2]
        Rc, tc = _planar_poses(plane, xy, own.K, H, mask)
        Rp = jnp.where(jnp.all(jnp.isfinite(Rc), (-2, -1))[..., None, None], Rc, Rp)
        tp = jnp.where(jnp.all(jnp.isfinite(tc), -1)[..., None], tc, tp)
    rows = jnp.arange(C)[:, None]
    Rp = Rp.at[rows, take].set(jnp.where(used[..., None, None], Rs, pick(Rp)))
    tp = tp.at[rows, take].set(jnp.where(used[..., None], ts, pick(tp)))
    solved = jnp.zeros_like(ok).at[rows, take].set(used)
    return (own, Rp, tp, ok, determined, pair_status, alone, distance, H), solved


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _start_rig(data, pairs, solved, reference, max_relative_rms, held, robust, *, planar, given):
    """The rig before the joint solve, from the pairs' poses (`_start_pairs`, or `_start_own`'s
    with `solved` the pairs its solves took; None for given cameras): cameras, frame poses
    (target to reference camera), the pairs and frames used, each camera's status, the target's
    median distance, the pairs' RMS alone and their own poses. `held`: the given cameras' poses
    are held; `robust`: the solve's loss is robust (both arrays, so that other options compile
    nothing here)."""
    target, _, pixels, mask, cameras = data
    own, Rp, tp, ok, determined, pair_status, alone, distance, _ = pairs
    C, F = mask.shape[:2]
    dtype = pixels.dtype
    Rrel, trel, shared, agree = _relative_poses(Rp, tp, ok, distance)
    lost = jnp.zeros(C, bool)
    if not given:
        # A camera that cannot fit its own frames, each with a pose of its own (`poor_fit`, as
        # the joint solve judges a camera), links others only where nothing else does: its pairs
        # weigh less than one shared frame. (Left out of the chain altogether, a good camera
        # whose own solve wandered off, which the joint solve brings back, cost a second solve.)
        lost = _own_fit(own, Rp, tp, solved, target, pixels, mask, max_relative_rms)
    # A camera whose own poses disagree with the rest's in most frames (those of the cameras
    # that fit their own frames, where poses are not held) is left out: POOR_FIT. The rest link
    # through the frames where they agree, and through the others only where nothing else does.
    judged = ~lost[:, None] & ~lost[None, :]
    disagreeing = ~held & _disagreeing(
        jnp.where(judged, shared, 0.0), jnp.where(judged, agree, 0.0)
    )
    weight = agree + (shared - agree) / (F + 1)
    weight = jnp.where(lost[:, None] | lost[None, :], shared / (F + 1), weight)
    weight = jnp.where(disagreeing[:, None] | disagreeing[None, :], 0.0, weight)
    linked, R, t = _chain(Rrel, trel, weight, reference)
    if given:  # held: the given poses
        linked = linked | held
        R = jnp.where(held, cameras.R, R)
        t = jnp.where(held, cameras.t, t)
    usable = linked & jnp.any(ok, 1)
    # no frame with enough points is TOO_FEW_POINTS before its intrinsics, which no frame could
    # determine, are DEGENERATE (as the docstring said: a camera that saw 3 corners a frame was
    # told to record more frames at other angles)
    too_few = jnp.all(pair_status == Status.TOO_FEW_POINTS, 1)
    status = jnp.select(
        [too_few | ~jnp.any(ok | ~determined[:, None], 1), ~determined, ~linked],
        [Status.TOO_FEW_POINTS, Status.DEGENERATE, Status.NOT_CONNECTED],
        Status.OK,
    )
    status = jnp.where(
        usable, Status.OK, jnp.where(status == Status.OK, Status.TOO_FEW_POINTS, status)
    )
    status = jnp.where(disagreeing, Status.POOR_FIT, status).astype(jnp.int32)
    usable = usable & ~disagreeing
    pair = ok & usable[:, None]
    # each frame's pose in the reference frame, from every camera that saw it
    Rf = jnp.einsum("cji,cfjk->cfik", R, Rp)
    tf = jnp.einsum("cji,cfj->cfi", R, tp - t[:, None])
    eye = jnp.eye(3, dtype=dtype)
    Rf = jnp.where(pair[..., None, None], Rf, eye)
    tf = jnp.where(pair[..., None], tf, 0.0)
    Rf, tf = jax.vmap(_average_pose, (1, 1, 1))(Rf, tf, pair.astype(dtype))
    frame_ok = jnp.any(pair, 0)
    Rf = jnp.where(frame_ok[:, None, None], Rf, eye)
    tf = jnp.where(frame_ok[:, None], tf, 0.0)
    # The pairs whose own closed form failed take part in the joint solve where other pairs
    # posed their frame: those whose points determine no pose of their own (a board seen along
    # one row and one more corner: `_planar._general_position`; caliscope's recording has five,
    # each in a frame three other cameras saw), and, with a robust loss, any: one wrong
    # detection among a 3-D target's points fails the pair's DLT (its fit check), and with 1 %
    # of the detections moved by 50 px a third of an 8 x 100 object rig's pairs were left out
    # so (until 2026-12-05); and those with enough points of which the closed form could take
    # too few: a fisheye's beyond 90 degrees have no pinhole pixel (a 4-camera rig of a 190
    # degree lens: 13 of 253 pairs, the edge of the field a fisheye calibration needs, were
    # left out of the solve, and not counted as skipped, until 2026-12-06)
    minimum = MIN_PLANE_POINTS if planar else MIN_OBJECT_POINTS
    beyond = (pair_status == Status.TOO_FEW_POINTS) & (jnp.sum(mask, -1) >= minimum)
    failed = jnp.where(robust, jnp.any(mask, -1), (pair_status == Status.DEGENERATE) | beyond)
    pair = pair | (failed & usable[:, None] & frame_ok[None, :])
    initial = eqx.tree_at(lambda c: (c.R, c.t), own, (R, t))
    own_poses = RigidTransform(  # (`RigCalibration.step_spread`)
        jnp.where(ok[..., None, None], Rp, jnp.nan), jnp.where(ok[..., None], tp, jnp.nan)
    )
    return initial, RigidTransform(Rf, tf), pair, frame_ok, status, distance, alone, own_poses


def _own_fit(own, Rp, tp, solved, target, pixels, mask, max_relative_rms):
    """Whether each camera's RMS over the points of the frames `solved`, with its own poses
    `Rp`, `tp` (`(C, F, ...)`, target to camera), is a poor fit (`_dlt.poor_fit`)."""
    C, F, N = mask.shape
    eye = jnp.broadcast_to(jnp.eye(3, dtype=Rp.dtype), (C, 3, 3))
    alone = eqx.tree_at(lambda c: (c.R, c.t), own, (eye, jnp.zeros((C, 3), Rp.dtype)))
    points = jnp.einsum("cfij,nj->cfni", Rp, target) + tp[:, :, None]
    used = mask & solved[..., None]
    projected = jax.vmap(lambda cam, x: cam.project(x))(alone, points)
    square = jnp.sum(jnp.where(used[..., None], projected - pixels, 0.0) ** 2, -1)
    rms = jnp.sqrt(jnp.sum(square, (1, 2)) / jnp.maximum(jnp.sum(used, (1, 2)), 1))
    flat = lambda x: x.reshape((C, F * N) + x.shape[3:])  # noqa: E731
    poor = _dlt.poor_fit(rms, flat(pixels), flat(used), max_relative_rms, True)
    return poor & jnp.any(used, (1, 2))


def _own_frames(ok, n: int):
    """`(C, n)` frame indices per camera: `n` of its frames `ok` evenly spread (in order), or all
    of them followed by others (distinct; the first `sum(ok)` are its frames)."""
    order = jnp.argsort(~ok, axis=1, stable=True)  # its frames first, in order
    count = jnp.maximum(jnp.sum(ok, 1, keepdims=True), n)
    return jnp.take_along_axis(order, (jnp.arange(n) * count) // n, axis=1)


def _refine_own(cams, Rp, tp, ok, distance, target, pixels, mask, free, loss, max_steps):
    """Each camera's free intrinsics and distortion and its frames' poses, from its own frames
    alone: the rig's problem with one camera at the origin, for every camera (one after the other
    on a CPU, side by side elsewhere)."""
    eye = jnp.eye(3, dtype=Rp.dtype)
    pose = jnp.asarray([i in POSE_INDICES for i in free], bool)
    move = (~pose).astype(Rp.dtype)[None]

    def one(cam, Rp, tp, ok, pixels, mask):
        cam = eqx.tree_at(lambda c: (c.R, c.t), cam, (eye, jnp.zeros(3, Rp.dtype)))
        cam = jax.tree_util.tree_map(lambda x: x[None], cam)
        Rp = jnp.where(ok[:, None, None], Rp, eye)
        tp = jnp.where(ok[:, None], tp, jnp.array([0.0, 0.0, 1.0], Rp.dtype) * distance)
        y, _, _, args, _, _ = _refine(
            cam,
            RigidTransform(Rp, tp),
            ok[None],
            ok,
            distance,
            target,
            pixels[None],
            mask[None],
            move,
            free,
            loss,
            max_steps,
            nielsen=False,
        )
        cams, frames = _cameras_and_frames(y, args, free)
        return jax.tree_util.tree_map(lambda x: x[0], cams), frames.R, frames.t

    inputs = (cams, Rp, tp, ok, pixels, mask)
    if _sharding.cpu_chunk(len(ok), 1) is None:  # an accelerator, or several devices: at once
        refined, R, t = jax.vmap(one)(*inputs)
    else:
        # one CPU: one camera after the other, each solve as long as it needs (side by side,
        # every camera waited for the slowest: 16 cameras x 100 frames 2.2 against 1.1 s warm)
        refined, R, t = jax.lax.map(lambda inputs: one(*inputs), inputs)
    # a camera whose own solve failed keeps its closed form
    good = finite_cameras(refined)
    return (
        where_cameras(good, refined, cams),
        jnp.where(good[:, None, None, None], R, Rp),
        jnp.where(good[:, None, None], t, tp),
    )


# ------------------------------------------------------------------------------ refinement
def _frame_pose(yf, R0f, t0f, distance):
    return rodrigues(yf[:3]) @ R0f, t0f + yf[3:] * distance


def _block_residuals(yc, yf, cam, frame, data, free, loss):
    """The weighted residuals `(N, 2)` of one camera in one frame, from the increments `yc`
    (the camera's free parameters, natural units) and `yf` (the frame's pose)."""
    p0, R0, scale, move = cam
    R0f, t0f, move_f, distance = frame
    target, pixels, mask = data
    p = _parameters(yc * move, p0, scale, free) if free else p0
    Rf, tf = _frame_pose(yf * move_f, R0f, t0f, distance)
    r = jnp.where(mask[:, None], _project(_unpack(p, R0), target @ Rf.T + tf, mask) - pixels, 0.0)
    return _robust_residuals(r, loss)


def _project(camera: Camera, world, mask):
    """`camera.project(world)`, with the hidden points (which may lie anywhere, e.g. at the
    camera's centre in a frame nobody saw) replaced by the point on the optical axis before the
    division, so that neither they nor their derivatives are NaN."""
    x, y, z = camera._camera_coordinates(world)  # noqa: SLF001
    x, y, z = jnp.where(mask, x, 0.0), jnp.where(mask, y, 0.0), jnp.where(mask, z, 1.0)
    xd, yd = _lens([x, y, z], camera.dist[..., None, :])
    u = camera.alpha_u[..., None] * xd + camera.skew[..., None] * yd + camera.u0[..., None]
    return jnp.stack([u, camera.alpha_v[..., None] * yd + camera.v0[..., None]], -1)


def _pinned(y, args):
    """Residuals that hold the parameters no observation determines at their seed (the reference
    camera's pose, fixed parameters of unusable cameras, unseen frames), so that the problem
    stays well posed for the solver and for implicit derivatives."""
    move_c, move_f = args[3], args[6]
    return (1.0 - move_c) * y["cams"], (1.0 - move_f)[:, None] * y["frames"]


def _residuals(y, args, free, loss):
    """All residuals: `pixels (C, F, N, 2)` and the pinned parameters."""
    p0, R0, scale, move_c, R0f, t0f, move_f, distance, target, pixels, mask = args
    frame = (R0f, t0f, move_f, distance)

    def camera(yc, p0, R0, scale, move, pixels, mask):
        block = lambda yf, R0f, t0f, mf, px, m: _block_residuals(  # noqa: E731
            yc, yf, (p0, R0, scale, move), (R0f, t0f, mf, distance), (target, px, m), free, loss
        )
        return jax.vmap(block)(y["frames"], *frame[:3], pixels, mask)

    r = jax.vmap(camera)(y["cams"], p0, R0, scale, move_c, pixels, mask)
    pin_c, pin_f = _pinned(y, args)
    return {"pixels": r, "cams": pin_c, "frames": pin_f}


class _Normal(eqx.Module):
    """The normal equations `J^T J`, `J^T r` of the rig's problem, by blocks: `U (C, P, P)`
    per camera, `V (F, 6, 6)` per frame, `W (C, F, P, 6)` between them; `gc`, `gf`; the cost."""

    cost: Array
    U: Array
    V: Array
    W: Array
    gc: Array
    gf: Array


def _block_rows(yc, yf, cam, frame, data, free, loss):
    """The residuals `r (2 N,)` of one camera in one frame (all u, then all v) and their
    derivatives, rows `J (P + 6, 2 N)`: in the camera's increments `yc`, then the frame's `yf`; the
    chain rule written out (`_pixel_columns`), entry by entry over the points. (`jax.jacfwd` of
    `_block_residuals` gave the same to rounding in 4x the time: 1.6 against 0.4 ms for caliscope's
    4 cameras x 48 frames.) Under a robust loss, both scaled for Gauss–Newton's model (`_irls`),
    and the cost; without, the cost is None (that of `r`)."""
    p0, R0, scale, move = cam
    R0f, t0f, move_f, distance = frame
    target, pixels, mask = data
    p = _parameters(yc * move, p0, scale, free) if free else p0
    Rf, Jw = exp_and_left_jacobian(yf[:3] * move_f, R0f)
    X = [target[:, i] for i in range(3)]
    m = [Rf[i][0] * X[0] + Rf[i][1] * X[1] + Rf[i][2] * X[2] for i in range(3)]  # Rf X
    tf = t0f + yf[3:] * move_f * distance
    world = jnp.stack([m[i] + tf[i] for i in range(3)], -1)
    columns, dworld = _pixel_columns(p, R0, world, mask)
    columns = _tied_columns(columns, p0, free)  # (alpha_u following alpha_v: `Free`)
    rows = [columns[k] for k in free]
    # the frame's rotation increments: d(u, v) / d w_k = g . ((Jw e_k) x m) = (Jw e_k) . (m x g)
    Jw = [[row[k] for row in Jw] for k in range(3)]  # its columns
    rows += [tuple(_small.triple(Jw[k], m, g) for g in dworld) for k in range(3)]
    rows += [(dworld[0][k], dworld[1][k]) for k in range(3)]  # the frame's translation
    units = (
        [scale[k] * move[i] for i, k in enumerate(free)] + [move_f] * 3 + [move_f * distance] * 3
    )
    rows = [[jnp.where(mask, d, 0.0) * unit for d in row] for row, unit in zip(rows, units)]
    r = jnp.where(mask[:, None], _project(_unpack(p, R0), world, mask) - pixels, 0.0)
    cost = None  # (least squares: that of the residuals)
    if loss is not None:
        w, rho = _irls(loss, jnp.sum(r * r, axis=-1))
        rows = [[w * d for d in row] for row in rows]
        r, cost = r * w[:, None], jnp.sum(rho)
    # one concatenation of (1, N) pieces, u then v of each row: under vmap the frames come first
    # and each row is contiguous, as the products of `_normal` want them (stacked as (N, 2) and
    # contracted over both axes, XLA copied the Jacobian three times per step)
    J = jnp.concatenate([d.reshape(1, -1) for row in rows for d in row]).reshape(len(rows), -1)
    return jnp.concatenate([r[:, 0], r[:, 1]]), J, cost


def _normal(y, args, free, loss) -> _Normal:
    """The blocks of the normal equations at `y`, camera by camera (a loop: one camera's
    Jacobians at a time, so that memory grows with F, not C F), each camera's over its frames in
    chunks of `FRAME_CHUNK` on a CPU (which stay in cache)."""
    p0, R0, scale, move_c, R0f, t0f, move_f, distance, target, pixels, mask = args

    def camera(inputs):
        yc, p0, R0, scale, move, px, m = inputs

        def block(yf, R0f, t0f, mf, px, m):
            return _block_rows(
                yc, yf, (p0, R0, scale, move), (R0f, t0f, mf, distance), (target, px, m), free, loss
            )

        def frames(*inputs):
            r, J, cost = jax.vmap(block)(*inputs)
            JJ, g = jnp.einsum("fam,fbm->fab", J, J), jnp.einsum("fam,fm->fa", J, r)
            return JJ, g, jnp.sum(r * r, -1) if cost is None else cost

        inputs = (y["frames"], R0f, t0f, move_f, px, m)
        JJ, g, rr = _sharding.chunked_map(frames, inputs, _sharding.cpu_chunk(len(m), FRAME_CHUNK))
        P = len(free)
        return (
            jnp.sum(JJ[:, :P, :P], 0),
            JJ[:, P:, P:],
            JJ[:, :P, P:],
            jnp.sum(g[:, :P], 0),
            g[:, P:],
            jnp.sum(rr),
        )

    U, V, W, gc, gf, cost = jax.lax.map(camera, (y["cams"], p0, R0, scale, move_c, pixels, mask))
    pin_c, pin_f = _pinned(y, args)
    eye_c = jax.vmap(jnp.diag)(1.0 - move_c)
    eye_f = jnp.eye(6, dtype=V.dtype) * (1.0 - move_f)[:, None, None]
    return _Normal(
        cost=jnp.sum(cost) + jnp.sum(pin_c * pin_c) + jnp.sum(pin_f * pin_f),
        U=U + eye_c,
        V=jnp.sum(V, 0) + eye_f,
        W=W,
        gc=gc + (1.0 - move_c) * pin_c,
        gf=jnp.sum(gf, 0) + (1.0 - move_f)[:, None] * pin_f,
    )


def _schur_solve(n: _Normal, damping):
    """The step `-(J^T J + damping diag(J^T J))^-1 J^T r` with the frames eliminated: the
    reduced camera system `S = U - sum_f W_f V_f^-1 W_f^T` (C P unknowns, Cholesky), then each
    frame's step. NaN where a matrix is not positive definite."""
    C, P = n.gc.shape
    dtype = n.gc.dtype
    floor = lambda d: jnp.maximum(d, jnp.finfo(dtype).eps * jnp.max(d, initial=0.0))  # noqa: E731
    dU = floor(jnp.diagonal(n.U, axis1=-2, axis2=-1))
    dV = floor(jnp.diagonal(n.V, axis1=-2, axis2=-1))
    U = n.U + damping * jax.vmap(jnp.diag)(dU)
    V = n.V + damping * jax.vmap(jnp.diag)(dV)
    V_inv = jax.vmap(lambda v: _scaled_solve(v, jnp.eye(v.shape[-1], dtype=dtype)))(V)
    Y = jnp.einsum("cfpi,fij->cfpj", n.W, V_inv)
    S = jnp.einsum("cfpi,dfqi->cpdq", Y, n.W).reshape(C * P, C * P)
    S = _block_diagonal(U) - S
    b = -(n.gc - jnp.einsum("cfpi,fi->cp", Y, n.gf)).reshape(-1)
    dc = _scaled_solve(S, b[:, None])[:, 0].reshape(C, P)
    df = -jnp.einsum("fij,fj->fi", V_inv, n.gf + jnp.einsum("cfpi,cp->fi", n.W, dc))
    return dc, df


def _scaled_solve(M, B):
    """`M^-1 B` for a symmetric positive definite `M`, solved with Jacobi's scaling (unit
    diagonal): the parameters' units span pixels of focal length to unit distortion, and the
    scaled matrix's condition number is orders of magnitude lower (a float32 Cholesky of the
    unscaled reduced camera system failed on 5 cameras x 50 frames)."""
    d = 1.0 / jnp.sqrt(jnp.diagonal(M))
    return d[:, None] * _definite_solve(M * d[:, None] * d[None, :], B * d[:, None])


def _block_diagonal(blocks):
    """`(C, P, P)` blocks as the `(C P, C P)` block-diagonal matrix."""
    C, P, _ = blocks.shape
    eye = jnp.eye(C, dtype=blocks.dtype)
    return jnp.einsum("cd,cpq->cpdq", eye, blocks).reshape(C * P, C * P)


def _quadratic(n: _Normal, dc, df):
    """`dy^T J^T J dy` from the blocks."""
    return (
        jnp.einsum("cp,cpq,cq->", dc, n.U, dc)
        + 2.0 * jnp.einsum("cp,cfpi,fi->", dc, n.W, df)
        + jnp.einsum("fi,fij,fj->", df, n.V, df)
    )


class _SchurLMState(eqx.Module):
    normal: _Normal  # at the current point; zeros before the first step
    step: tuple[Array, Array]  # the next trial's increments of cameras and frames (zero first)
    quadratic: Array  # its `_quadratic`
    fresh: Array  # whether no step was taken yet
    damping: Array
    growth: Array
    done: Array
    num_steps: Array


class _SchurLM(optx.AbstractLeastSquaresSolver):
    """Levenberg–Marquardt (Gauss–Newton model, Marquardt's scaling) for the rig's problem, with
    the normal equations built by blocks (`options["normal"](y, args) -> _Normal`) and solved
    with the frames eliminated (`_schur_solve`). Its steps, damping updates and stopping tests
    are `mvcalib.SecantLM`'s without the secant term, except for the damping's update. With
    `nielsen` (the joint solve), Nielsen's (1999): an accepted step multiplies it by
    `max(1/100, 1 - (2 rho - 1)^3)`, `rho` the actual over the predicted decrease of the cost,
    and rejected ones by 2, 4, 8, ... Without (each camera's own frames, `_refine_own`), a good
    step (rho > 1/4) divides it by 100 and rejected ones multiply it by 10, 20, 40, ... The
    reduced camera system's condition number reaches 1e10 (pixels of focal length against
    distortion), and Marquardt's scaled damping bends the step until it is below ~1e-8: at a
    fixed 10 per good step the solve crept there (30 steps against 10 on 8 cameras x 100
    frames). Along a curved valley (caliscope's rig with its intrinsics free: each camera's
    principal point against its pose) the fixed 100 overshoots the damping that works, every
    good step was followed by two rejected ones, and the solve stopped at 100 steps unconverged
    from every reference camera, float32 and float64; Nielsen's keeps the damping near what
    works: converged from every one (float64 58-88 steps, float32 36-44), the same 7-8 steps on
    8 synthetic rigs. (In the per-camera stage it changed where caliscope's camera 2 ends, a
    focal length its own frames leave free, 106 against 187 px, from where the joint solve
    started at cameras 1 and 2 did not recover in float64: that stage keeps the fixed rule.)
    Converged when an accepted step is shorter than `rtol` standard errors, or a trial changed
    the cost by its rounding only: that trial is taken, nearer the zero gradient the step aimed
    at (the 5 views of tests/test_planar.py: v0 within 4e-11 of OpenCV's, against 3e-9 for the
    point it left, their RMS equal to 1e-15 either way).

    The normal equations are built in one place, the step: each evaluates them at the trial its
    predecessor solved for, then solves for the next trial, and the first evaluates them at the
    seed (a step of zero, always accepted), so that the compiled program holds one copy of their
    Jacobians, not two (the 8 x 100 rig's program: 0.90 against 1.20 MB of HLO, compiled in 18.3
    against 21.8 s on a loaded machine). A next trial already short after an accepted one is
    taken without being evaluated, and ends the solve (`normal` is then that of the point it
    left, within `rtol` standard errors)."""

    rtol: float = 1e-5
    atol: float = 1e-12
    norm: Callable = optx.max_norm
    initial_damping: float = 1e-3
    nielsen: bool = True  # the damping's update (above)

    @property
    def _growth(self) -> float:
        """The damping's first increase after an accepted step."""
        return 2.0 if self.nielsen else 10.0

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, f_struct, aux_struct, tags
        (C, P), (F, k), dtype = y["cams"].shape, y["frames"].shape, y["cams"].dtype
        zeros = lambda *shape: jnp.zeros(shape, dtype)  # noqa: E731
        return _SchurLMState(
            # (not `jax.eval_shape` of the normal equations: that traces them once more)
            normal=_Normal(
                zeros(), zeros(C, P, P), zeros(F, k, k), zeros(C, F, P, k), zeros(C, P), zeros(F, k)
            ),
            step=(zeros(C, P), zeros(F, k)),
            quadratic=zeros(),
            fresh=jnp.asarray(True),
            damping=jnp.asarray(self.initial_damping, dtype),
            growth=jnp.asarray(self._growth, dtype),
            done=jnp.asarray(False),
            num_steps=jnp.asarray(0),
        )

    def step(self, fn, y, args, options, state, tags):
        del fn, tags
        n, fresh, (dc, df), quadratic = state.normal, state.fresh, state.step, state.quadratic
        trial = {"cams": y["cams"] + dc, "frames": y["frames"] + df}
        new = options["normal"](trial, args)
        cost_new = jnp.where(jnp.isnan(new.cost), jnp.inf, new.cost)
        # a trial whose cost differs by its rounding only is the minimum's as much as the point
        # it left, and nearer its zero gradient, which the step aimed at: taken, and the last
        level = jnp.abs(cost_new - n.cost) <= 64 * jnp.finfo(n.cost.dtype).eps * n.cost
        accept = fresh | (cost_new < n.cost) | level
        predicted = -2.0 * (jnp.sum(dc * n.gc) + jnp.sum(df * n.gf)) - quadratic
        actual = n.cost - cost_new
        if self.nielsen:
            rho = actual / jnp.where(predicted > 0, predicted, 1.0)
            factor = jnp.where(predicted > 0, jnp.maximum(0.01, 1 - (2 * rho - 1) ** 3), 1.0)
        else:
            factor = jnp.where(actual > 0.25 * predicted, 0.01, 1.0)
        dof = jnp.maximum(options["n_residuals"] - options["n_parameters"], 1)
        least = jnp.minimum(cost_new, n.cost)
        tolerance = self.rtol**2 * least / dof
        short = lambda dc, df, quadratic, cost: (  # noqa: E731
            (quadratic <= self.rtol**2 * cost / dof)
            | (jnp.maximum(self.norm(dc), self.norm(df)) <= self.atol)
        )
        stalled = ~accept & (jnp.maximum(predicted, jnp.abs(actual)) <= tolerance)
        # (or the residuals are down to the rounding of the pixels' coordinates: a noise-free rig)
        rounding = least <= options["rounding"]
        done = ~fresh & ((accept & short(dc, df, quadratic, least)) | level | stalled | rounding)
        damping = jnp.where(
            accept,
            jnp.where(fresh, state.damping, jnp.maximum(factor * state.damping, _MIN_DAMPING)),
            state.damping * state.growth,
        )
        keep = lambda a, b: jax.tree_util.tree_map(lambda u, v: jnp.where(accept, u, v), a, b)  # noqa: E731
        n = keep(new, n)
        # the next trial; one already short after an accepted trial is taken without being
        # evaluated, and ends the solve (as `SecantLM`'s)
        dc, df = _schur_solve(n, damping)
        quadratic = _quadratic(n, dc, df)
        last = accept & short(dc, df, quadratic, n.cost)
        step = {"cams": jnp.where(last, dc, 0.0), "frames": jnp.where(last, df, 0.0)}
        y = jax.tree_util.tree_map(jnp.add, keep(trial, y), step)
        state = _SchurLMState(
            normal=n,
            step=(dc, df),
            quadratic=quadratic,
            fresh=jnp.asarray(False),
            damping=damping,
            growth=jnp.where(accept, self._growth, 2.0 * state.growth),
            done=done | last,
            num_steps=state.num_steps + 1,
        )
        return y, state, None

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        return state.done, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, state, tags, result
        return y, aux, {}


def _refine(
    initial,
    frames,
    pair,
    frame_ok,
    distance,
    target,
    pixels,
    mask,
    movable,
    free,
    loss,
    max_steps,
    nielsen=True,
):
    """The joint least-squares solution from the closed-form rig: the increments `y` and the
    solver's outcome (`nielsen`: `_SchurLM`'s damping update).

    A redescending loss (`Cauchy`) starts from the closed form as any does. Until 2026-12-05 it
    started from the answer of the convex `Huber` of its scale: with the steps' old model
    (`_block_rows`) its own descent gave up whole frames, sent off to 1e4 px and more, and ended
    at 15-57 px RMS, every camera POOR_FIT. With Ceres' model it needs no such start: 8 x 100
    rigs (boards and 3-D targets, keys 0-7, with and without 1 % of wild detections) converge in
    11-13 steps against 18-21 and end where they did."""
    C, F = pair.shape
    dtype = pixels.dtype
    p0 = jax.vmap(_pack)(initial)
    f = jnp.abs(p0[:, :1])
    one = jnp.ones((C, 1), dtype)
    scale = jnp.concatenate(
        [f.repeat(5, 1), one.repeat(3, 1), (distance * one).repeat(3, 1),
         one.repeat(p0.shape[1] - 11, 1)], 1  # the lens's coefficients
    )  # fmt: skip
    used = mask & pair[..., None]
    pixels = jnp.where(used[..., None], pixels, 0.0)
    move_f = frame_ok.astype(dtype)
    args = (
        p0,
        initial.R,
        scale,
        movable,
        frames.R,
        frames.t,
        move_f,
        distance,
        target,
        pixels,
        used,
    )
    y0 = {"cams": jnp.zeros((C, len(free)), dtype), "frames": jnp.zeros((F, 6), dtype)}
    options = {
        "normal": functools.partial(_normal, free=free, loss=loss),
        "n_residuals": 2 * jnp.sum(used),
        "n_parameters": jnp.sum(movable) + 6 * jnp.sum(frame_ok),
        "rounding": 2 * jnp.sum(used) * (16 * jnp.finfo(dtype).eps * jnp.max(jnp.abs(pixels))) ** 2,
    }
    sol = optx.least_squares(
        functools.partial(_residuals, free=free, loss=loss),
        _SchurLM(nielsen=nielsen),
        y0,
        args,
        options=options,
        max_steps=max_steps,
        throw=False,
        adjoint=optx.ImplicitAdjoint(),
    )
    out = (sol.value, sol.stats["num_steps"], sol.result._value, args, used)  # noqa: SLF001
    return (*out, sol.state.normal)


def _cameras_and_frames(y, args, free):
    p0, R0, scale, move_c, R0f, t0f, move_f, distance = args[:8]
    p = p0
    if free:
        p = jax.vmap(lambda yc, p0, s: _parameters(yc, p0, s, free))(y["cams"] * move_c, p0, scale)
    cams = jax.vmap(_unpack)(p, R0)
    Rf, tf = jax.vmap(_frame_pose, (0, 0, 0, None))(
        y["frames"] * move_f[:, None], R0f, t0f, distance
    )
    return cams, RigidTransform(Rf, tf)


def _held_through(initial: Camera, given: Camera, free) -> Camera:
    """`initial` (`_start`'s cameras, which carry no derivative) with the derivatives of the
    `given` cameras' parameters that the solve holds (those not in `free`), which it copied: a
    held value passes through to the answer, and the other parameters' optimum depends on it
    (implicit derivatives). With `fix="intrinsics"` the derivative of the answer's focal lengths
    by the given ones was zero, not one. The values stay `initial`'s, to the last bit."""
    held = set(parameter_names(given.lens)) - {parameter_names(given.lens)[i] for i in free}
    if getattr(free, "tied", False):
        # alpha_u follows alpha_v at the given ratio: alpha_u carries the ratio's derivative
        # times alpha_v (which is free, and carries none), `d alpha_u - ratio d alpha_v`
        ratio = jax.lax.stop_gradient(given.alpha_u / given.alpha_v)
        given = eqx.tree_at(lambda c: c.alpha_u, given, given.alpha_u - ratio * given.alpha_v)

    def through(x, g, hold):  # x's value, g's derivative where `hold`
        d = g - jax.lax.stop_gradient(g)
        return x + jnp.where(hold & jnp.isfinite(d), d, 0.0)

    fields = {name: name in held for name in ("alpha_u", "alpha_v", "u0", "v0", "skew")}
    fields["R"] = {"rx", "ry", "rz"} <= held
    fields["t"] = {"tx", "ty", "tz"} <= held
    out = initial
    for name, hold in fields.items():
        if hold:
            value = through(getattr(initial, name), getattr(given, name), True)
            out = eqx.tree_at(lambda c, name=name: getattr(c, name), out, value)
    coefficients = jnp.asarray([k in held for k in LENSES[given.lens]])
    return eqx.tree_at(lambda c: c.dist, out, through(initial.dist, given.dist, coefficients))


def _uncertainty(y, args, n: _Normal, residuals, *, free, loss):
    """Covariance of each camera's free parameters `sigma^2 S^-1` (S the reduced camera system
    at the solution, undamped, from the solver's last normal equations `n`; the frames'
    uncertainty is in it; `sigma^2` from the fitted points' `residuals` (C, F, N, 2) as
    `residual_variance` has it for `loss`), and the standard errors of each camera's centre and
    rotation."""
    C, P = n.gc.shape
    move_c, mask = args[3], args[10]
    V_inv = jax.vmap(lambda v: _scaled_solve(v, jnp.eye(6, dtype=v.dtype)))(n.V)
    S = _block_diagonal(n.U) - jnp.einsum("cfpi,fij,dfqj->cpdq", n.W, V_inv, n.W).reshape(
        C * P, C * P
    )
    n_parameters = jnp.sum(move_c) + 6 * jnp.sum(args[6])
    sigma2 = residual_variance(residuals, mask, loss, n_parameters)
    cov_all = sigma2 * _scaled_solve(S, jnp.eye(C * P, dtype=S.dtype)).reshape(C, P, C, P)
    cov = jnp.einsum("cpcq->cpq", cov_all) * move_c[:, :, None] * move_c[:, None, :]
    p0, R0, scale = args[:3]

    def centre(yc, p0, R0, s):
        return _unpack(_parameters(yc, p0, s, free) if free else p0, R0).center

    J = jax.vmap(jax.jacfwd(centre))(y["cams"] * move_c, p0, R0, scale)  # (C, 3, P)
    position = jnp.einsum("cip,cpq,ciq->ci", J, cov, J)
    rotation = jnp.zeros((C, 3), cov.dtype)
    for k, index in enumerate(_ROTATION):
        if index in free:
            j = free.index(index)
            rotation = rotation.at[:, k].set(cov[:, j, j])
    scale_free = scale[:, jnp.asarray(free, dtype=int)]
    cov = cov * scale_free[:, :, None] * scale_free[:, None, :]  # the parameters' own units
    cov = reported_covariance(cov, free, p0)  # (alpha_u's too where it follows alpha_v)
    std = jnp.sqrt(jnp.diagonal(cov, axis1=-2, axis2=-1))
    return cov, std, (jnp.sqrt(position), jnp.rad2deg(jnp.sqrt(rotation)))


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _calibrate_rig(start, target, pixels, mask, observed, reference, max_relative_rms, given=None,
                   *, free, loss, max_steps):  # fmt: skip
    """The joint solve from `_start`'s rig, its uncertainty and report; the parameters the solve
    holds carry the derivatives of the `given` cameras' (`_held_through`)."""
    pose = jnp.asarray([i in POSE_INDICES for i in free], bool)
    initial, frames, pair, frame_ok, status, distance, alone, own_poses = start
    if given is not None:
        initial = _held_through(initial, given, free)
    C = pair.shape[0]
    ok = status == Status.OK
    # what may move: the free parameters of calibrated cameras, not the reference's pose
    movable = ok[:, None] & ~((jnp.arange(C) == reference)[:, None] & pose[None, :])
    y, steps, result, args, used, normal = _refine(
        where_cameras(ok, initial, unit_camera(pixels.dtype, initial.lens)),
        frames,
        pair,
        frame_ok,
        distance,
        target,
        pixels,
        mask,
        movable.astype(pixels.dtype),
        free,
        loss,
        max_steps,
    )
    cams, poses = _cameras_and_frames(y, args, free)
    # the report, from the unweighted residuals
    project = jax.vmap(
        lambda cam, R, t: cam.project(jnp.einsum("fij,nj->fni", R, target) + t[:, None]),
        (0, None, None),
    )
    # every observation of a calibrated camera in a frame with a pose, the skipped ones too
    observed = observed & ok[:, None, None] & frame_ok[None, :, None]
    residuals = jnp.where(observed[..., None], project(cams, poses.R, poses.t) - pixels, 0.0)
    cov, std, (position_std, rotation_std) = _uncertainty(
        *jax.lax.stop_gradient((y, args, normal, residuals)), free=free, loss=loss
    )
    square = jnp.sum(jnp.where(used[..., None], residuals, 0.0) ** 2, -1)
    rms = jnp.sqrt(jnp.sum(square) / jnp.maximum(jnp.sum(used), 1))
    camera_rms = jnp.sqrt(jnp.sum(square, (1, 2)) / jnp.sum(used, (1, 2)))
    frame_rms = jnp.sqrt(jnp.sum(square, (0, 2)) / jnp.sum(used, (0, 2)))
    threshold = jnp.inf if loss is None else 3.0 * loss.scale
    inliers = used & (jnp.sqrt(square) <= threshold)
    # a camera whose fit is out of all proportion to its image of the target (calibrate's check);
    # with a robust loss, its RMS the one its median implies, as for a pair (`_poor_pairs`): a
    # few frames of wrong detections (a symmetric board seen turned by 180 degrees) are the
    # pairs' business, and the camera's RMS over all its points blamed the camera (three of
    # camera 3's 45 frames turned: 72 px, POOR_FIT; 2026-12-05)
    C, F, N = used.shape
    flat = lambda x: x.reshape((C, F * N) + x.shape[3:])  # noqa: E731
    judged = camera_rms if loss is None else _median_rms(flat(square), flat(used))
    poor = _dlt.poor_fit(judged, flat(pixels), flat(used), max_relative_rms, True)
    status = jnp.where(ok & poor, Status.POOR_FIT, status).astype(jnp.int32)
    ok = status == Status.OK
    poor_pairs = _poor_pairs(square, used, pixels, ok, max_relative_rms, loss)
    nan_c = lambda x: jnp.where(ok.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.nan)  # noqa: E731
    nan_f = lambda x: jnp.where(frame_ok.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.nan)  # noqa: E731
    return dict(
        cameras=jax.tree_util.tree_map(nan_c, cams),
        target_poses=jax.tree_util.tree_map(nan_f, poses),
        status=status,
        initial=jax.tree_util.tree_map(nan_c, initial),
        rms=rms,
        camera_rms=camera_rms,
        frame_rms=frame_rms,
        alone_rms=alone,
        own_poses=own_poses,
        residuals=residuals,
        observed=observed,
        used=used,
        inliers=inliers,
        position_std=nan_c(position_std),
        rotation_std=nan_c(rotation_std),
        parameter_std=nan_c(std),
        covariance=nan_c(cov),
        iterations=steps,
        result=result,
        poor_pairs=poor_pairs,
    )


def _camera_rms(square, which):
    """Each camera's RMS `(C,)` over the observations `which` `(C, F, N)`, from the squared
    residual lengths `square` `(C, F, N)` (0 where it has none)."""
    n = which.sum(axis=(1, 2))
    return np.sqrt(np.where(which, square, 0).sum(axis=(1, 2)) / np.maximum(n, 1))


def _fold_radius(dist) -> float:
    """The normalised radius at which a pinhole lens's radial distortion `r (1 + k1 r^2 + k2 r^4
    + k3 r^6)` stops increasing (the first positive root of its slope, a cubic in r^2), or inf:
    beyond it a distorted radius has a second ray, or none."""
    k1, k2, _, _, k3 = (float(k) for k in dist)
    roots = np.roots([7 * k3, 5 * k2, 3 * k1, 1.0])  # (leading zeros are dropped)
    s = [float(z.real) for z in np.atleast_1d(roots) if abs(z.imag) < 1e-12 and z.real > 0]
    return float(np.sqrt(min(s))) if s else np.inf


def _fold_note(camera: Camera) -> str:
    """A note where a pinhole camera's radial distortion folds back inside its image, taking
    the principal point as the image's centre (its corners `hypot(u0 + 0.5, v0 + 0.5)` px
    away). A user's trial, caliscope's recording with free intrinsics: camera 2's k1 0.62, k2
    -6.3 (the board never beyond 169 px of its principal point) folded at 249 px of a 1280 x 720
    image: rays beyond it 27-67 degrees off, and nothing said."""
    r = _fold_radius(camera.dist)
    if not np.isfinite(r):
        return ""
    k1, k2, _, _, k3 = (float(k) for k in camera.dist)
    fold = float(camera.alpha_v) * r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    corner = float(np.hypot(camera.u0 + 0.5, camera.v0 + 0.5))
    if not fold < corner:
        return ""
    return (
        f"; but its lens distortion folds back {fold:.0f} px from the principal point, inside "
        f"the image (its corners ~{corner:.0f} px away): beyond the fold its rays are wrong. "
        "Record the target out to the image's edges, or fit fewer terms (distortion=('k1',); "
        "--distortion k1)"
    )


def _set_aside_note(used: int, inliers: int) -> str:
    """A note where a robust loss set aside (beyond 3 scales) more than a fifth of a camera's
    observations: not a few wrong detections, but a camera its model does not fit. A user's
    trial: one camera's video mirrored, `Huber(2.0)`: OK at 10 px, 1,380 of its 2,315 points
    believed, 77 m off, the good cameras pulled 22-49 mm, and nothing said."""
    if not used or inliers >= 0.8 * used:
        return ""
    return (
        f"; but the robust loss set aside {used - inliers} of its {used} observations (beyond 3 "
        "scales): more than wrong detections do. Is its image mirrored, its ids or order "
        "another's, or its model wrong?"
    )


def _outcome(result: int, steps: int) -> str:
    """The joint solve's outcome in words: "successful after 7 steps", or why it stopped."""
    if result == 0:
        return f"successful after {steps} steps"
    return f"stopped after {steps} steps, {_RESULT_MESSAGES[result]}"


def _far_note(lengths) -> str:
    """A note where at least 3 of a camera's residual lengths (pixels) lie 10 times their median
    or further (and beyond 1 px), or one 50 times (and beyond 5 px): more than Gaussian noise
    gives (with 10^6 observations, the chance of one 10 times away is ~1e-24), as wrong
    detections do. Least squares takes them at full weight: a stereo pair with 2 % of its
    corners moved by 20-50 px came back OK at 5.2 px RMS with its focal lengths 18-20 px off,
    and nothing said why; one corner of 6,783 moved by 100 px in the reference camera put the
    others 37-51 mm off, OK (a user's trial)."""
    if lengths.size < 20:
        return ""
    median = float(np.median(lengths))
    bound = max(10.0 * median, 1.0)
    far = int(np.sum(lengths > bound))
    if far < 3 and not np.any(lengths > max(50.0 * median, 5.0)):
        return ""
    return (
        f"; but {far} of its {lengths.size} observations lie {bound:.2g} px or further (10 times "
        f"the median; the worst {float(lengths.max()):.3g} px): wrong detections, which a robust "
        "loss would set aside (loss=mc.Huber(2.0); mvcalib calibrate-rig --huber 2)"
    )


def _step_note(spread) -> str:
    """A note where a camera's own poses agree `_STEP_BETTER` times better with the other
    cameras' with its frames shifted by one (`RigCalibration.step_spread`, `(3,)`)."""
    shifted = min(spread[0], spread[2])
    if not spread[1] > _STEP_BETTER * shifted:
        return ""
    step = "f - 1" if spread[0] < spread[2] else "f + 1"
    return (
        f"; but its frames agree with the other cameras' {spread[1] / shifted:.1f} times better "
        f"with its frame {step} taken as their frame f: are its frames one out of step (a frame "
        "dropped or doubled, recordings started apart)? It and the cameras it pulls may be "
        "further off than their standard errors say"
    )


def _stepping_note(stepping) -> str:
    """The note of a camera whose frames are in step, where others' are not (`_step_note`)."""
    return _pulled_by(
        stepping, ("seems", "seem"), "one frame out of step with the rest, which pulls"
    )


def _pulled_note(pulling) -> str:
    """A note for a camera without far observations of its own where other cameras have some
    (`_far_note`, least squares): one corner of 6,783 moved by 100 px in the reference camera
    of a user's trial put the other three 37-51 mm off (6 standard errors), each of them OK and
    'calibrated', 0.5-0.8 m at 600 px."""
    return _pulled_by(
        pulling,
        ("has", "have"),
        "observations far beyond the rest (wrong detections), which least squares lets pull",
        " (loss=mc.Huber(2.0); mvcalib calibrate-rig --huber 2)",
    )


def _pulled_by(cameras, verb: tuple[str, str], what: str, advice: str = "") -> str:
    """'; but camera(s) `cameras` `verb` (singular, plural) `what` every camera of the rig: this
    one may be further off ...', or nothing without `cameras`."""
    if not cameras:
        return ""
    which = f"camera {cameras[0]} {verb[0]}" if len(cameras) == 1 else (
        f"cameras {', '.join(map(str, cameras))} {verb[1]}"
    )  # fmt: skip
    return (
        f"; but {which} {what} every camera of the rig: this one may be further off than its "
        f"standard errors say{advice}"
    )


# A calibrated camera whose RMS is more than this many times the median of the rig's other
# calibrated cameras gets a note (`RigCalibration.messages`). A user's trial: a camera given the
# intrinsics of an earlier calibration (its focal length 5 % and principal point 40 px off since)
# and held there came out OK at 0.98 px against the others' 0.42-0.49, its centre 95 mm off
# against a standard error of 1.1 mm, and nothing said.
_MISFIT = 2.0
# The same where a camera's frames fit this many times worse in the rig than each alone
# (`RigCalibration.alone_rms`, the medians over its frames; at least `_ALONE_FRAMES` frames,
# and no less than `_ALONE_FLOOR` px): every camera may be wrong alike, as the median of the rig
# is then. A user's trial: caliscope's recording with every camera's intrinsics taken from a
# calibration at another resolution and held: two cameras OK at 2.6 and 2.9 px, one 0.6 m off
# against a standard error of 11 mm, and nothing said; their frames fit 3.3 and 5.8 times worse
# in the rig. With caliscope's own intrinsics 1.0-2.5 times (its webcams' frames are not quite
# simultaneous: with the intrinsics free, 0.5-1.3 times), synthetic rigs 0.95-1.0.
_ALONE_TIMES, _ALONE_FRAMES, _ALONE_FLOOR = 3.0, 3, 0.02


def _in_rig_and_alone(square, used, alone) -> tuple[float, float]:
    """A camera's median over its frames of its RMS in the rig (from the squared residual
    lengths `square` `(F, N)` of its points `used`) and of `alone` `(F,)`, over the frames that
    have both; NaN with fewer than `_ALONE_FRAMES`."""
    n = used.sum(-1)
    frames = (n > 0) & np.isfinite(alone)
    if frames.sum() < _ALONE_FRAMES:
        return np.nan, np.nan
    in_rig = np.sqrt(np.where(used, square, 0.0).sum(-1)[frames] / n[frames])
    return float(np.median(in_rig)), float(np.median(alone[frames]))


def _systematic(in_rig: float, alone: float) -> bool:
    """Whether a camera's frames fit `_ALONE_TIMES` times worse in the rig than each alone (the
    medians `_in_rig_and_alone`)."""
    return in_rig > _ALONE_TIMES * max(alone, _ALONE_FLOOR)


def _held(parameter_names) -> set:
    """What a solve with these free parameters held: `"intrinsics"` (the principal point and
    focal lengths; alpha_u alone may move with `fix="aspect_ratio"`), `"pose"`."""
    free = set(parameter_names)
    held = {"intrinsics"} if not {"alpha_v", "u0", "v0"} & free else set()
    return held | ({"pose"} if not {"rx", "tx"} & free else set())


# Where a camera whose intrinsics were held fits poorly (a note, `POOR_FIT`'s message, the
# reference's error).
_HELD_INTRINSICS = (
    "its intrinsics were held (`fix`): do they still fit this camera (zoom, focus, resolution)? "
    "Calibrate with them free to compare"
)


def _misfit_note(rms: float, others, held: set, frames=(np.nan, np.nan)) -> str:
    """A note where a camera's frames fit `_ALONE_TIMES` times worse in the rig than each alone
    (`frames`: the medians `_in_rig_and_alone`), else where it fits `_MISFIT` times worse than
    the rig's other calibrated cameras (at least two) do theirs, by RMS: its model (`held`
    intrinsics that no longer fit, poses that moved, a lens its distortion terms miss), its
    frames' timing or its detections are wrong, and its standard errors, which take the model as
    right, understate how far off it may be."""
    if "pose" in held:
        cause = (
            "its pose was held (`fix`): the rig may have moved, or the target's size or units "
            "differ from the rig's"
        )
    elif "intrinsics" in held:
        cause = _HELD_INTRINSICS
    else:
        cause = "its lens model (distortion terms) or its detections may not fit"
    in_rig, alone = frames
    if _systematic(in_rig, alone):
        times = in_rig / max(alone, _ALONE_FLOOR)
        return (
            f"; but its frames fit {times:.1f} times worse in the rig ({in_rig:.3g} px "
            f"in the median frame) than each alone ({alone:.3g} px, a homography or DLT a frame): "
            f"{cause}; or its frames are out of step with the other cameras'. Its standard "
            "errors take its model as right and understate how far off it may be"
        )
    if len(others) < 2 or not rms > _MISFIT * float(np.median(others)):
        return ""
    return (
        f"; but its RMS, {rms:.3g} px, is {rms / float(np.median(others)):.1f} times the median "
        f"of the rig's other cameras ({float(np.median(others)):.3g} px): {cause}. Its standard "
        "errors take its model as right and understate how far off it may be"
    )


def _worst_pairs(result: RigCalibration, count: int = 3) -> str:
    """Where a rig's solve failed: its worst (camera, frame) pairs by RMS, as a list in words
    (empty where no pair was used). (A stereo pair whose second camera saw the board turned by
    180 degrees in one frame was told only that the reference camera, the other one, could not
    be calibrated.)"""
    square = np.sum(np.asarray(result.residuals) ** 2, -1)
    used = np.asarray(result.used)
    n = used.sum(-1)
    rms = np.sqrt(np.where(used, square, 0.0).sum(-1) / np.maximum(n, 1))
    rms = np.where(n > 0, rms, -np.inf)
    worst = np.argsort(rms, axis=None)[::-1][:count]
    pairs = [np.unravel_index(i, rms.shape) for i in worst if np.isfinite(rms.flat[i])]
    return ", ".join(f"camera {c} in frame {f} (RMS {rms[c, f]:.3g} px)" for c, f in pairs)


def _poor_pairs(square, used, pixels, ok, max_relative_rms, loss):
    """`(C, F)`: with a robust `loss`, the (camera, frame) pairs of the cameras `ok` that fit
    out of all proportion, judged as `calibrate_planar` judges a view (`_out_of_proportion`,
    camera by camera): the RMS that the pair's median squared distance `square` implies
    (`_median_rms`) above `max_relative_rms` of its pixels' spread and 3 times the median pair's
    of its camera. A camera's wrong detections in a frame (a symmetric board seen turned by 180
    degrees), or a frame whose pose ended in another minimum: the loss keeps them at a bounded
    cost, but their points pull the camera. None without a loss (least squares takes every
    point). (Until 2026-12-06 against the median pair of the whole rig: a stereo pair whose
    second camera's corners were blurred, 2.7 px against 0.35, lost 8-12 of its 30 sound frames.)"""
    if loss is None:
        return jnp.zeros(used.shape[:2], bool)
    seen = jnp.any(used, -1)
    poor = jax.vmap(_out_of_proportion, in_axes=(0, 0, 0, 0, None))(
        _median_rms(square, used), pixels, used, seen, max_relative_rms
    )
    return ok[:, None] & seen & poor


_OWN_START_FRAMES = 20


def _own_start(target, pixels, mask, image_size, loss, lens="fisheye", which=None) -> Camera:
    """Each camera (of `which`, default all) from its own frames of a planar target: intrinsics
    and distortion by `calibrate_planar(lens=lens, loss=loss)` of up to
    `_OWN_START_FRAMES` of them, evenly spread (so that every camera with as many runs the
    same compiled program; NaN with fewer than 2 frames, or fewer than 2 of them OK); the poses
    are the closed form's business, so these are the identity. (Until 2026-12-05 without the
    loss, and NaN unless every frame was OK: with 1 % of the corners moved by 50 px, two of six
    cameras of `tests/test_fisheye.py`'s ring had no start, and camera 0 failed the rig.)"""
    from ._planar import calibrate_planar

    C = pixels.shape[0]
    K, dist = np.full((C, 3, 3), np.nan), np.full((C, len(LENSES[lens])), np.nan)
    for c in range(C) if which is None else np.flatnonzero(which):
        frames = np.flatnonzero(mask[c].sum(-1) >= MIN_PLANE_POINTS)
        if len(frames) < 2:
            continue
        spread = np.linspace(0, len(frames) - 1, min(len(frames), _OWN_START_FRAMES))
        frames = frames[np.unique(spread.round().astype(int))]
        px = np.where(mask[c, frames, :, None], pixels[c, frames], np.nan)
        own = calibrate_planar(
            target, px, mask[c, frames], lens=lens, image_size=image_size, loss=loss
        )
        if np.sum(np.asarray(own.ok)) >= 2 and np.all(np.isfinite(np.asarray(own.K))):
            K[c], dist[c] = np.asarray(own.K), np.asarray(own.dist)
    eye, zero = np.broadcast_to(np.eye(3), (C, 3, 3)), np.zeros((C, 3))
    return Camera.from_matrices(K, eye, zero, dist, lens=lens)


# ------------------------------------------------------------------------------ public
def calibrate_rig(
    target: Float[Array, "N 3"],
    pixels: Float[Array, "C F N 2"],
    mask: Bool[Array, "C F N"] | None = None,
    *,
    cameras: Camera | None = None,
    fix: str | Sequence[str] = (),
    distortion: Sequence[str] | None = None,
    skew: bool = False,
    reference: int | str = 0,
    origin_frame: int | None = None,
    loss: Huber | Cauchy | None = None,
    rcond: float | None = None,
    max_relative_rms: float = _dlt.DEFAULT_MAX_RELATIVE_RMS,
    max_steps: int = 100,
    verbose: bool = False,
    lens: str | None = None,
    image_size: tuple[int, int] | None = None,
) -> RigCalibration:
    """Calibrate a rig of C cameras from a target moved through its volume over F frames.

    The target's pose in each frame is unknown, each camera may see it in only some frames, and
    only some pairs of cameras share frames. Every camera's intrinsics (unless given), lens
    distortion and pose, and the target's pose in every frame, are found as one least-squares
    problem: a closed-form start batched over all (camera, frame) pairs, cameras chained to the
    reference over the frames they share, then Levenberg–Marquardt with the frames eliminated
    (see the module's docstring). Differentiable: `jax.grad` through the answer uses implicit
    derivatives of the optimum.

    **Arguments:**

    - `target`: `(N, 3)` the target's points in its own frame: a planar board (any plane; z = 0
      keeps the board's x, y) or a 3-D object.
    - `pixels`: `(C, F, N, 2)` where camera c saw point n in frame f; `mask` `(C, F, N)` which
      it saw (default: the finite pixels). A (camera, frame) pair with fewer than 4 points of a
      planar target (6 of a 3-D one) is skipped, and counted in `skipped`.
    - `cameras`: `(C,)` a starting rig (e.g. `mc.io.load_caliscope_cameras`): its intrinsics
      and distortion replace the closed-form ones, and its poses are used where `fix` holds
      them (else the poses come from the frames); needed to `fix` the intrinsics. Its lens is
      the rig's: a fisheye rig starts from fisheye cameras (e.g. each calibrated by
      `mvcalib.calibrate_planar(..., lens="fisheye")`), whose closed-form poses use the points
      within 90 degrees of each camera's axis, and the joint solve all of them.
    - `fix`: parameters held at their starting values, by name or group as for `mvcalib.refine`
      (`"intrinsics"`, `"distortion"`, `"focal"`, `"principal_point"`, ...; OpenCV's
      `CALIB_FIX_INTRINSIC` is `("intrinsics", "distortion")`: `"intrinsics"` is K's four, and
      a given camera's coefficient that `distortion` leaves out, k3, is held with a warning
      while the others are estimated); `"pose"` holds
      every camera's pose as given in `cameras`, in their world frame (`reference` is then
      unused), so that only the target's poses are fitted. `"aspect_ratio"` holds each camera's
      `alpha_u / alpha_v` at its starting ratio, the focal length estimated (OpenCV's
      `CALIB_FIX_ASPECT_RATIO`): that of `cameras` where given (e.g. 1, as OpenCV's own start),
      else of the camera's closed form from its own frames (as `calibrate_planar`'s for a
      board; the median focal lengths of its frames' DLTs for a 3-D target); `initial` has it.
    - `distortion`: the coefficients estimated (default as for `mvcalib.refine`: a pinhole's
      k1, k2, p1, p2; a fisheye's k1..k4); `skew`: estimate it.
    - `reference`: the camera whose frame is the world's (default 0), or `"target"`: the
      target's frame in `origin_frame` (an index along the frame axis of `pixels`, not a frame
      id from a file; default: the frame seen by the most cameras), so that the board sets the
      world's origin and floor. The world's axes are then the target's: x and y along the
      board, z its normal away from the cameras that see it (they see its -z side, as OpenCV's
      chessboard frame): a board lying on the floor puts z down and the cameras below zero. For
      z up, turn the world by 180 degrees about x: `mc.to_global(result.cameras,
      mc.RigidTransform(np.diag([1.0, -1.0, -1.0]), np.zeros(3)))`.
    - `loss`: `mc.Huber(scale)` or `mc.Cauchy(scale)` (pixels) for wrong detections.
    - `rcond`: the closed form's threshold for a degenerate homography or DLT (default
      sqrt(machine epsilon)); `max_steps` of Levenberg–Marquardt.
    - `max_relative_rms`: a camera whose reprojection RMS exceeds this fraction of its pixels'
      spread is `Status.POOR_FIT` and NaN, as in `mvcalib.calibrate` (default 0.05).
    - `verbose`: print the stages and their times to stderr.
    - `lens`: the cameras' lens, `"pinhole"` (default) or `"fisheye"` (default: `cameras`'s).
      Without `cameras`, a fisheye rig needs a planar target and `image_size=(width, height)`:
      each camera's intrinsics and distortion start from `mvcalib.calibrate_planar(...,
      lens="fisheye")` of its own frames (at least 2), then the rig is solved as from given
      cameras. A camera with fewer frames is NaN and flagged.

    Raises `ValueError` for mismatched shapes, NaN or inf among the visible pixels, a rig in
    which nothing is visible, a reference camera that cannot be calibrated, or a `target` that
    is neither planar nor 3-D. Cameras that cannot be calibrated get a status and NaN; the
    others are calibrated as if they were absent. A camera (of three or more) whose own poses of
    the target disagree with the other cameras' in most of the frames they share (a mirrored
    image or mirrored point ids: no one place in the rig fits it) is POOR_FIT before the solve
    and left out of it, its RMS NaN and its message saying why. Any other POOR_FIT camera is
    found by the solve it took part in, where it pulled the others: called with concrete arrays,
    the rig is solved again without it (by the same compiled program) until no camera is newly
    flagged; inside `jax.jit` it is only flagged. (A robust `loss` keeps wrong detections of an
    otherwise good camera from pulling the others.) With a robust `loss` and concrete arrays, so
    are the (camera, frame) pairs that fit out of all proportion (judged as `calibrate_planar`
    judges a view: the RMS their median distance implies, above `max_relative_rms` of their
    pixels' spread and 3 times the median pair's: a camera's wrong detections in a frame, such
    as a board seen turned by 180 degrees), which the loss would keep at a bounded cost while
    they pull the camera; they are not in `used`. Then, with concrete arrays, a camera left out,
    or the worst camera where its RMS is more than 3 times the median camera's (a good camera
    whose own frames left its start loose can end in another minimum), is calibrated from its
    points in the frames the rig posed (unless it sees them mirrored), and the rig solved once
    more from there; that answer is taken if every camera is OK and the cameras fit better
    (`verbose` says so).

    **Example:**

    ```python
    >>> import jax, numpy as np, mvcalib as mc
    >>> rig = mc.synthetic.board_rig(jax.random.key(0), n_cameras=6, n_frames=60, noise=0.3)
    >>> result = mc.calibrate_rig(rig.target, rig.pixels, rig.mask)
    >>> bool(result.ok.all()), bool(result.rms < 0.5)  # 0.3 px of noise in x and in y
    (True, True)
    >>> # camera 2's centre, in camera 0's frame, against the truth (metres)
    >>> truth = rig.cameras[0].to_camera(rig.cameras.center[2:3])[0]
    >>> error = np.linalg.norm(result.cameras.center[2] - truth)
    >>> bool(error < 3 * np.linalg.norm(result.position_std[2]))  # within its standard error
    True

    ```
    """
    tic = time.perf_counter()

    def say(message):
        if verbose:
            print(f"calibrate_rig: {message} ({time.perf_counter() - tic:.2f} s)", file=sys.stderr)

    if cameras is not None and not isinstance(cameras, Camera):
        raise TypeError(
            f"`cameras` is an mvcalib.Camera with a camera axis (a rig); got "
            f"{type(cameras).__name__}."
        )
    if lens is not None:
        check_lens(lens)
    check_loss(loss)
    if isinstance(target, jax.core.Tracer):
        raise ValueError(
            "`target` must be concrete (its plane is found from its values): inside jax.jit, "
            "close over it rather than pass it as an argument."
        )
    target = _validate.floating("target", target, (None, 3), xp=np)
    if target.ndim != 2:
        raise ValueError(f"`target` must have shape (N, 3); got {tuple(target.shape)}.")
    concrete = _validate.is_concrete(pixels, mask)
    xp = np if concrete else jnp
    pixels = _validate.floating("pixels", pixels, (None, 2), xp=xp)
    N = target.shape[0]
    if pixels.ndim != 4 or pixels.shape[2] != N:
        raise ValueError(
            f"`pixels` must have shape (C, F, N, 2) with N = {N} target points; got "
            f"{tuple(pixels.shape)}."
        )
    C, F = pixels.shape[:2]
    if mask is None:
        mask = _validate.finite_pixels(pixels, xp)
    mask = _validate.boolean_mask("mask", mask, (C, F, N), xp=xp)
    if tuple(mask.shape) != (C, F, N):
        raise ValueError(f"`mask` must have shape {(C, F, N)}; got {tuple(mask.shape)}.")
    dtype = _validate.result_dtype(target.dtype, pixels.dtype)
    planar = _validate.is_planar(target)
    minimum = MIN_PLANE_POINTS if planar else MIN_OBJECT_POINTS
    if concrete:
        mask = np.asarray(mask)
        _validate._check_finite(target, pixels, mask)  # noqa: SLF001
        if not mask.any():
            raise ValueError("nothing is visible: `mask` is False everywhere.")
    counts = mask.sum(-1)
    skipped = (counts > 0) & (counts < minimum)
    observed, mask = mask, mask & ~skipped[..., None]
    if concrete and not mask.any():
        raise ValueError(
            f"no (camera, frame) pair sees {minimum} or more points of the target: nothing to "
            "calibrate from."
        )
    if lens is None:
        lens = "pinhole" if cameras is None else cameras.lens
    if image_size is not None:
        _validate.in_image(pixels, mask, image_size)
    if cameras is not None and cameras.lens != lens:
        raise ValueError(f"`lens={lens!r}` but the starting `cameras` are {cameras.lens} cameras.")
    given_cameras = cameras
    if cameras is None and lens == "fisheye":
        if not (planar and concrete) or image_size is None:
            raise ValueError(
                "a fisheye rig without starting `cameras` starts each camera from its own frames "
                "of a planar target: give a planar `target`, concrete arrays and "
                "`image_size=(width, height)`, or fisheye `cameras=`."
            )
        say("each fisheye camera's intrinsics from its own frames (calibrate_planar)")
        cameras = _own_start(target, pixels, mask, image_size, loss)
        # (a camera with frames but no start: its frames do not determine its intrinsics)
        unstarted = ~np.isfinite(np.asarray(cameras.alpha_u))
        unstarted &= (np.asarray(mask).sum(-1) >= MIN_PLANE_POINTS).any(-1)
    names = parameter_names(lens)
    free = _free_parameters(distortion, fix, skew, lens)
    if given_cameras is not None:
        warn_held_coefficients(given_cameras, distortion, fix)
    fixed = set(names) - {names[i] for i in free.reported}  # (a tied alpha_u is not held)
    fixes_intrinsics = bool(fixed & {"alpha_u", "alpha_v", "u0", "v0"})
    if cameras is None and fixes_intrinsics:
        raise ValueError("holding the intrinsics fixed needs the starting rig: pass `cameras=`.")
    if given_cameras is not None and concrete and planar and not fixes_intrinsics:
        # A starting camera with no calibration (NaN: a user's earlier run where it failed)
        # starts from its own frames, as without `cameras=` (it was TOO_FEW_POINTS, "no frame
        # shows it enough of the target", of 28 frames of 108 corners).
        lost = ~np.all(np.isfinite(np.asarray(cameras.K)), axis=(-2, -1))
        if lost.any() and cameras.batch_shape == (C,):
            say(f"camera {', '.join(map(str, np.flatnonzero(lost)))}: no starting values (NaN); "
                "started from its own frames")  # fmt: skip
            own = _own_start(target, pixels, mask, image_size, loss, cameras.lens, lost)
            cameras = where_cameras(jnp.asarray(lost), own, cameras)
    if cameras is not None:
        if cameras.batch_shape != (C,):
            raise ValueError(
                f"`cameras` must be a rig of {C} cameras, one per row of `pixels`; got batch "
                f"shape {cameras.batch_shape}."
            )
        cameras = _skew_model(
            jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), cameras), skew, fix
        )
    # (fixed parameters not given hold the closed form's values: zero distortion, zero skew)
    if isinstance(reference, str) and reference != "target":
        raise ValueError(f"`reference` is a camera index or 'target'; got {reference!r}.")
    if not isinstance(reference, str) and not 0 <= int(reference) < C:
        raise ValueError(f"`reference` {reference} is not a camera of the {C}.")
    if origin_frame is not None:
        _check_origin_frame(origin_frame, reference, F)
    plane = (
        _plane_frame(target, np.ones(N, bool), dtype) if planar else RigidTransform.identity(dtype)
    )
    rcond = float(np.sqrt(np.finfo(dtype).eps)) if rcond is None else float(rcond)
    say(
        f"{C} cameras, {F} frames, {N} points ({'planar' if planar else '3-D'} target); "
        f"{int(np.sum(skipped)) if concrete else '?'} pairs skipped"
    )

    relative_rms = _dlt.check_relative_rms(max_relative_rms)

    def solve(mask, observed):
        # with reference="target", the solve's reference is the camera that saw the most frames
        if not isinstance(reference, str):
            solve_reference = int(reference)
        else:
            solve_reference = 0 if not concrete else int(np.argmax(mask.any(-1).sum(1)))
        # (NumPy for concrete arrays: no program of their own; their frames and cameras padded
        # to a bucket with frames nobody saw and cameras that see nothing, so that a recording
        # of another length, or a rig of another size, reuses the programs)
        frames = _buckets.size(F, MIN_FRAMES, bits=FRAME_BITS) if concrete else F
        rig = _buckets.size(C, bits=CAMERA_BITS) if concrete else C

        def padded(x, fill):
            if not concrete:
                return x
            return _buckets.pad(_buckets.pad(x, 1, frames, fill=fill), 0, rig, fill=fill)

        points, image = xp.asarray(target, dtype), padded(xp.asarray(pixels, dtype), 0.0)
        mask, observed = padded(mask, False), padded(observed, False)
        given = cameras
        if concrete and cameras is not None:  # (the padding's: copies of the last camera)
            given = jax.tree_util.tree_map(lambda x: _buckets.pad(x, 0, rig), cameras)
        quick = rig * frames * N <= QUICK_SIZE
        options = dict(free=free, loss=loss, max_steps=max_steps, quick=quick)
        # (the reference camera as an array, not a constant of the programs: a rig calibrated
        # from another reference, or `reference="target"` on another recording, compiles nothing)
        index = np.int32(solve_reference)
        # `_start`'s rig carries no derivative: under the user's `grad` its inputs go in as
        # values, so that its program is not linearised (the first `jax.grad` of a camera's
        # position by the pixels, 4 cameras x 40 frames, fresh process: 20.0-20.8 against
        # 24.1-24.3 s)
        data = (points, plane, image, mask, given)
        if not concrete:
            data = jax.lax.stop_gradient(data)
        known = cameras is not None
        pairs = functools.partial(
            _start_pairs, data, rcond, planar=planar, given=known, quick=quick
        )
        own = functools.partial(
            _start_own, data, planar=planar, free=free, loss=loss, max_steps=max_steps,
            quick=quick,
        )  # fmt: skip
        posed = functools.partial(
            _start_rig, data, reference=index, max_relative_rms=relative_rms,
            held=np.bool_(known and not any(i in POSE_INDICES for i in free)),
            robust=np.bool_(loss is not None), planar=planar, given=known, quick=quick,
        )  # fmt: skip
        joint = functools.partial(
            _calibrate_rig, target=points, pixels=image, mask=mask, observed=observed,
            reference=index, max_relative_rms=relative_rms, given=given, **options,
        )  # fmt: skip
        if known:  # (no own solves)
            start = (pairs, lambda closed: posed(closed, None))
        else:
            start = (pairs, own, lambda out: posed(*out))
        # (each program compiled on another thread while the next is traced)
        out = _buckets.chain(*start, joint, early=concrete)
        if frames != F:
            out = {k: _buckets.first(v, F, axis=_FRAME_AXIS[k]) if k in _FRAME_AXIS else v
                   for k, v in out.items()}  # fmt: skip
        if rig != C:
            out = {k: v if k in _RIG_WIDE else _buckets.first(v, C, axis=0)
                   for k, v in out.items()}  # fmt: skip
        poor_pairs = out.pop("poor_pairs")
        result = RigCalibration(
            skipped=jax.device_put(skipped) if concrete else skipped,
            parameter_names=tuple(names[i] for i in free.reported),
            **out,
        )
        statuses = np.asarray(result.status) if concrete else None
        if concrete and (statuses == Status.POOR_FIT).all():
            worst = _worst_pairs(result)
            raise SolveFailed(
                float(result.rms), int(result.iterations), result.cameras.lens,
                f"; the worst fits: {worst}" if worst else "", result,
            )  # fmt: skip
        if concrete and (status := int(statuses[solve_reference])) != Status.OK:
            why = Status(status).message
            if planar and status == Status.DEGENERATE:  # (the DLT's words are for 3-D points)
                frames = int(np.asarray(mask)[solve_reference].any(-1).sum())
                seen = (
                    "one frame of the board does"
                    if frames == 1
                    else (f"{frames} frames of the board do")
                )
                why = (
                    f"its {seen} not determine it: record the board in more poses, three or "
                    "more tilted to one another (and check that `pixels` is (C, F, N, 2), "
                    "cameras first)"
                )
            other = ""
            if status == Status.POOR_FIT and "intrinsics" in _held(result.parameter_names):
                other = f"; {_HELD_INTRINSICS}"
            if C > 1 and (worst := _worst_pairs(result)):
                other += f". The worst fits: {worst}"
                if loss is None:
                    other += (
                        "; a robust loss (loss=mc.Huber(2.0)) sets aside a frame whose "
                        "detections are wrong, such as a board seen turned by 180 degrees"
                    )
            if C > 1:
                other += ". Choose another `reference`"
            if C > 1 and C > F:
                other += " (and check that `pixels` is (C, F, N, 2), cameras first)"
            raise ValueError(
                f"the reference camera {solve_reference} cannot be calibrated: {why}{other}."
            )
        return result, solve_reference, poor_pairs

    dropped, dropped_rms = np.zeros(C, bool), np.full(C, np.nan)
    try:
        result, solve_reference, poor_pairs = solve(mask, observed)
    except SolveFailed as failed:
        if C < 3:
            raise
        result, solve_reference, poor_pairs, culprit = _without_one(
            failed, solve, mask, observed, reference, say
        )
        dropped[culprit], dropped_rms[culprit] = True, float(failed.result.camera_rms[culprit])
        result = _marked_poor(result, dropped, dropped_rms)
    # Outside a trace, a POOR_FIT camera, which pulled the others in the solve it took part in,
    # is left out and the rest solved again (by the same compiled program), until none is new;
    # then, with a robust loss, so are the (camera, frame) pairs that fit out of all proportion
    # (`_poor_pairs`): an 8 x 100 `board_rig` whose camera 3 found a symmetric board's corners
    # in reverse order in three frames (the board turned by 180 degrees), `Huber(1.0)`: the two
    # frames other cameras saw are left out, the camera kept.
    gone = np.zeros((C, F), bool)  # the pairs left out
    if concrete and (left_out := _left_out(result)).any():
        say(
            f"camera {', '.join(map(str, np.flatnonzero(left_out)))}: its own poses disagree "
            "with the other cameras'; left out"
        )
        dropped |= left_out
    while concrete:
        poor = (np.asarray(result.status) == Status.POOR_FIT) & ~dropped
        rms = np.asarray(result.camera_rms)
        if poor.any():
            say(
                f"camera {', '.join(map(str, np.flatnonzero(poor)))}: poor fit (RMS "
                f"{', '.join(f'{r:.3g}' for r in rms[poor])} px); solved again without it"
            )
            dropped, dropped_rms = dropped | poor, np.where(poor, rms, dropped_rms)
        elif (new := np.asarray(poor_pairs) & ~gone).any():
            say(f"{int(new.sum())} (camera, frame) pairs: poor fit; solved again without them")
            gone |= new
        else:
            break
        keep = ~dropped[:, None, None]
        result, solve_reference, poor_pairs = solve(mask & keep & ~gone[..., None], observed & keep)
        result = _marked_poor(result, dropped, dropped_rms)
    # A camera left out, or the one that fits far worse than the rest of the rig, may be a good
    # one that started badly (its own frames leave its focal length loose, its own solve wandered
    # off, and the joint solve ended in another minimum): calibrated against the rest of the
    # rig, whose frames' poses make its points 3-D, it starts again from there, and the rig is
    # solved once more (with every camera's start given: no second retry). That answer is taken
    # if every camera is OK, and, where a camera that took part was restarted, the cameras that
    # took part fit better (a lower minimum of the same cost).
    if concrete:
        mask = mask & ~gone[..., None]
    if concrete and cameras is None and lens == "pinhole":
        ok, rms = np.asarray(result.status) == Status.OK, np.asarray(result.camera_rms)
        worst = np.arange(C) == np.argmax(np.where(ok, rms, -np.inf))
        worse = worst & (rms > _FAR_WORSE * np.median(rms[ok]))
        # (none where a camera is neither: the solve from given cameras takes every camera)
        retry = (dropped | worse) & (ok | dropped).all()
        fitted = retry
        if retry.any():
            start, fitted = _resected(result, retry, target, pixels, mask, distortion, skew, dtype)
        if fitted.any():
            which = ", ".join(map(str, np.flatnonzero(fitted)))
            say(f"camera {which}: calibrated against the rest of the rig; solved again from there")
            # (a camera left out and not restarted stays out: NaN, it would start afresh)
            out = (dropped & ~fitted)[:, None, None]
            again = calibrate_rig(
                target, pixels, mask & ~out, cameras=start, fix=fix, distortion=distortion,
                skew=skew,
                reference=solve_reference, loss=loss, rcond=rcond,
                max_relative_rms=max_relative_rms, max_steps=max_steps, verbose=verbose,
            )  # fmt: skip
            better = not worse.any() or _rms_of(again, ok) < _rms_of(result, ok)
            if (np.asarray(again.status) == Status.OK)[ok | fitted].all() and better:
                # (a camera left out and not restarted stays POOR_FIT, its RMS where it took part)
                result = _marked_poor(again, dropped & ~fitted, dropped_rms)
    say(
        f"RMS {float(result.rms):.3f} px after {int(result.iterations)} steps"
        if concrete
        else "traced"
    )
    if concrete and lens == "fisheye" and given_cameras is None:
        # A user's trial: a fisheye camera with one frame of ~100 corners was TOO_FEW_POINTS ("no
        # frame shows it enough of the target"); it lacks frames to start its intrinsics from.
        status = np.asarray(result.status)
        status = np.where(unstarted & (status == Status.TOO_FEW_POINTS), Status.DEGENERATE, status)
        result = eqx.tree_at(lambda r: r.status, result, jax.device_put(status.astype(np.int32)))
    if reference == "target":
        result = _to_target_frame(result, origin_frame, concrete)
    return result


def _marked_poor(result: RigCalibration, dropped, dropped_rms) -> RigCalibration:
    """`result` with the cameras `dropped` (left out of its solve) POOR_FIT, with the RMS they
    had where they took part (`dropped_rms`; NaN where they never did)."""
    status = np.where(dropped, Status.POOR_FIT, np.asarray(result.status)).astype(np.int32)
    rms = np.where(dropped, dropped_rms, np.asarray(result.camera_rms))
    # (from NumPy: no small eager programs)
    return eqx.tree_at(lambda r: (r.status, r.camera_rms), result, jax.device_put((status, rms)))


def _left_out(result: RigCalibration) -> np.ndarray:
    """The POOR_FIT cameras `(C,)` that took no part in the solve (`_disagreeing`): no RMS."""
    poor = np.asarray(result.status) == Status.POOR_FIT
    return poor & np.isnan(np.asarray(result.camera_rms))


def _without_one(failed: SolveFailed, solve, mask, observed, reference, say):
    """Where the joint solve left every camera POOR_FIT, one camera may have pulled the rest
    (a user's trial: one webcam's video mirrored, every camera POOR_FIT, and the error named
    the good cameras' worst frames). The rig is solved again without each camera in turn (the
    `_SUSPECTS` worst fitting), and the camera whose absence leaves the most cameras OK (then
    the lowest RMS) is the one: `(result, solve_reference, poor_pairs, that camera)`, or
    `failed` raised again where no such solve calibrates a camera."""
    rms = np.asarray(failed.result.camera_rms)
    order = np.argsort(-np.where(np.isfinite(rms), rms, -np.inf), kind="stable")
    say("every camera fits poorly: solving again without each camera in turn")
    best, best_key = None, None
    for c in order[:_SUSPECTS]:
        if not isinstance(reference, str) and c == int(reference):
            continue  # (the reference camera stays: choosing another is the user's call)
        keep = (np.arange(len(rms)) != c)[:, None, None]
        try:
            solved = solve(mask & keep, observed & keep)
        except ValueError:  # (SolveFailed, or the reference camera not calibrated)
            continue
        ok = int(np.sum(np.asarray(solved[0].status) == Status.OK))
        key = (ok, -float(solved[0].rms))
        if best_key is None or key > best_key:
            best, best_key = (*solved, int(c)), key
        if ok == len(rms) - 1:
            break  # (every other camera calibrated: none does better)
    if best is None:
        raise failed
    say(f"camera {best[3]}: poor fit; the rest of the rig calibrated without it")
    return best


def _rms_of(result: RigCalibration, cameras: np.ndarray) -> float:
    """The RMS of `result` over the observations of `cameras` (`(C,)` booleans)."""
    n = np.asarray(result.used).sum(axis=(1, 2))[cameras]
    return float(np.sqrt(np.sum(np.asarray(result.camera_rms)[cameras] ** 2 * n) / np.sum(n)))


def _resected(result, which, target, pixels, mask, distortion, skew, dtype) -> tuple:
    """The rig's cameras, each camera `which` replaced by its calibration (`calibrate`, refined)
    from its points in the frames the rig posed; and the `(C,)` mask of those replaced (not a
    camera whose calibration fails or sees the world mirrored, or that sees fewer than the
    DLT's points)."""
    from ._pipeline import calibrate

    posed = np.isfinite(np.asarray(result.target_poses.t)).all(-1)
    R, t = np.asarray(result.target_poses.R), np.asarray(result.target_poses.t)
    points = np.einsum("fij,nj->fni", R[posed], np.asarray(target)) + t[posed][:, None]
    cameras = jax.tree_util.tree_map(np.array, result.cameras)
    refine = {"skew": skew} if distortion is None else {"skew": skew, "distortion": distortion}
    fitted = np.zeros(len(which), bool)
    for c in np.flatnonzero(which):
        seen = np.asarray(mask)[c][posed]
        if seen.sum() < _validate.MIN_POINTS:
            continue
        alone = calibrate(
            points[seen].astype(dtype), np.asarray(pixels)[c][posed][seen].astype(dtype),
            refine=refine,
        )  # fmt: skip
        # (a camera that sees the rig's frames in a mirror, whose image or ids are mirrored, is
        # no camera of this rig: its DLT fits them all, mirrored, and the rig was solved again
        # for nothing, 1.1 s against 0.6 warm)
        fitted[c] = bool(alone.ok) and not bool(alone.mirrored)
        if fitted[c]:
            for rig, one in zip(*map(jax.tree_util.tree_leaves, (cameras, alone.cameras))):
                rig[c] = one
    return jax.device_put(cameras), fitted


def _check_origin_frame(origin_frame, reference, n_frames: int) -> None:
    """`origin_frame` is an index along the frame axis, used with `reference="target"`; a frame's
    id from a file (clamped by JAX's indexing, it chose another frame without a word) or the
    argument without `reference="target"` (ignored) is refused."""
    if reference != "target":
        raise ValueError(
            "`origin_frame` chooses the target's pose that becomes the world frame with "
            f"`reference='target'`; got reference={reference!r}."
        )
    if isinstance(origin_frame, (bool, np.bool_)) or not isinstance(
        origin_frame, (int, np.integer)
    ):
        raise TypeError(f"`origin_frame` is a frame's index, an int; got {origin_frame!r}.")
    if not 0 <= origin_frame < n_frames:
        raise ValueError(
            f"`origin_frame` is an index along the frame axis of `pixels`, 0 to {n_frames - 1}; "
            f"got {origin_frame}. (A frame's id from an observations file is not its index: "
            "`list(observations.frames).index(frame_id)` is.)"
        )


def _to_target_frame(result: RigCalibration, origin_frame, concrete) -> RigCalibration:
    """The result with the target's frame in `origin_frame` as the world's."""
    if origin_frame is None:
        if not concrete:
            raise ValueError("with `reference='target'` inside a trace, give `origin_frame`.")
        origin_frame = int(np.argmax(np.asarray(result.used.any(-1).sum(0))))
    f = int(origin_frame)
    if concrete and not bool(result.used[:, f].any()):
        raise ValueError(f"`origin_frame` {f}: no calibrated camera saw the target in that frame.")
    T = RigidTransform(result.target_poses.R[f], result.target_poses.t[f])  # target -> old world

    def moved(cams: Camera) -> Camera:  # x_cam = R (T X) + t
        pose = RigidTransform(cams.R, cams.t) @ T
        return eqx.tree_at(lambda c: (c.R, c.t), cams, (pose.R, pose.t))

    # the centres' standard errors, rotated into the new frame (per axis, approximately)
    position_std = jnp.sqrt(jnp.einsum("ji,cj->ci", T.R**2, result.position_std**2))
    return dataclasses.replace(
        result,
        cameras=moved(result.cameras),
        initial=moved(result.initial),
        target_poses=T.inverse() @ result.target_poses,
        position_std=position_std,
        origin_frame=f,
    )
