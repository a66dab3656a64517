"""Per-camera outcomes of batched calibration: values, not exceptions (like `optx.RESULTS`)."""

from __future__ import annotations

import enum

from ._validate import derived


class Status(enum.IntEnum):
    """Why a camera of a batch was or was not calibrated. `int(status) == 0` means success.

    Compare arrays of statuses with members: `result.status == mc.Status.DEGENERATE`.
    """

    OK = 0
    TOO_FEW_POINTS = 1
    DEGENERATE = 2
    NON_FINITE = 3
    POINTS_BEHIND = 4
    NOT_LABELLED = 5
    POOR_FIT = 6
    NOT_CONNECTED = 7

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Status.OK: "calibrated",
    Status.TOO_FEW_POINTS: "fewer than 6 visible points: the 11 unknowns of P are not determined",
    Status.DEGENERATE: (
        "degenerate geometry: the visible world points are coplanar, collinear or repeated, so P "
        "is not unique (use a non-coplanar target, or `mvcalib.calibrate_planar` for a flat one; "
        "the pose alone of a calibrated camera: `mvcalib.solve_pnp`)"
    ),
    Status.NON_FINITE: "NaN or inf among the visible points",
    Status.POINTS_BEHIND: (
        "the visible points lie on both sides of the camera: some correspondences are wrong"
    ),
    Status.POOR_FIT: (
        "the camera reprojects its own points with an RMS above `max_relative_rms` (default 5 %) "
        "of their spread: wrong correspondences (one wild pixel is enough), or noise or lens "
        "distortion too large for a pinhole camera at this image size"
    ),
    Status.NOT_CONNECTED: (
        "shares no frame, directly or through other cameras, with the reference camera: its pose "
        "in the rig is not determined (`calibrate_rig`)"
    ),
    Status.NOT_LABELLED: (
        "the image could not be read, or its dots could not be told apart with certainty "
        "(see the per-image message of `calibrate_images`)"
    ),
}


def ok(status):
    """`status == Status.OK`, computed in NumPy where `status` is concrete (`_validate.derived`:
    no program of its own)."""
    return derived(lambda xp, s: s == Status.OK, status)
