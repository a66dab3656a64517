"""The paper's experiment on a synthetic scene: `python -m mvcalib demo`."""

from __future__ import annotations

import dataclasses
import functools
import pathlib
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _buckets
from ._pipeline import Calibration, calibrate
from ._registration import RigidTransform, procrustes, procrustes_paper, to_global
from ._render import render
from ._report import format_table
from .io import write_atomic
from .synthetic import PaperScene, paper_scene
from .targets import box_corner

# the paper's snapshots are numbered from 1 (its Table I)
_SNAPSHOTS = tuple(str(i) for i in range(1, 5))

if TYPE_CHECKING:  # the photographs' demo imports scikit-image: only where it runs
    from ._detect import Detection
    from ._images import ImageCalibration
    from ._label import Labels

PIXEL_SIZE_MM = (0.0045, 0.0045)  # sensor element pitch for the image-plane coordinates


@dataclasses.dataclass
class DemoResult:
    scene: PaperScene
    calibration: Calibration
    registration: RigidTransform
    registration_paper: RigidTransform
    unified: np.ndarray  # (4, 2): the fixed point's pixel from each snapshot's global camera
    unified_paper: np.ndarray
    unified_sigma: np.ndarray  # (4, 2): its first-order standard deviation from the pixel noise
    noise: float
    global_noise: float


def _unified(scene: PaperScene, pixels, registration: RigidTransform):
    """Steps 2-6 for all four snapshots at once: DLT on 8 dots, decomposition, to_global."""
    calib = np.zeros(len(scene.world), bool)
    calib[list(scene.calibration_ids)] = True
    calibration = calibrate(scene.world, pixels, scene.mask & calib)
    cameras = to_global(calibration.cameras, registration)
    return cameras.project(scene.fixed_point[None])[:, 0], calibration


@functools.partial(_buckets.jit, jit=eqx.filter_jit)
def _pipeline(scene: PaperScene, noise):
    # Step 5: each snapshot's local frame into the room frame, from the 18 dots measured in both.
    local = scene.world[np.asarray(scene.registration_ids)]
    registration = procrustes(local, scene.world_global)
    registration_paper = procrustes_paper(local, scene.world_global)

    # How far the four answers may scatter: propagate the pixel noise to first order through the
    # whole pipeline (DLT, decomposition, registration, projection) with its Jacobian. The
    # answers themselves come with it (one trace of the pipeline, not three).
    def fixed_pixel(pixels):
        unified, calibration = _unified(scene, pixels, registration)
        return unified, (unified, calibration)

    J, (unified, calibration) = jax.jacfwd(fixed_pixel, has_aux=True)(scene.pixels)
    paper = to_global(calibration.cameras, registration_paper)
    unified_paper = paper.project(scene.fixed_point[None])[:, 0]
    J = jnp.stack([J[k, :, k].reshape(2, -1) for k in range(J.shape[0])])
    sigma = noise * jnp.sqrt(jnp.sum(J**2, axis=-1))
    return calibration, registration, registration_paper, unified, unified_paper, sigma


def run(
    *, noise: float = 0.3, global_noise: float = 0.0, seed: int = 2010, dtype=None
) -> DemoResult:
    """Run the paper's pipeline on `synthetic.paper_scene` and return every intermediate result.

    The scene is drawn in `dtype` too, so float32 and float64 give different scenes from one
    `seed` (the same intrinsics, other random poses): compare their accuracy, not their numbers.
    """
    make = functools.partial(
        paper_scene, jax.random.key(seed), noise=noise, global_noise=global_noise, dtype=dtype
    )
    # the scene's and the pipeline's programs compile at once, on other threads
    if (scene := _buckets.ahead(make)) is not None:
        _buckets.ahead(_pipeline, scene, noise, quick=True)
    scene = make()
    # four snapshots of 19 dots: a small program, compiled quickly (`_buckets.jit`)
    calibration, reg, reg_paper, unified, unified_paper, sigma = _pipeline(scene, noise, quick=True)
    calibration.raise_if_failed()
    return DemoResult(
        scene,
        calibration,
        reg,
        reg_paper,
        np.asarray(unified),
        np.asarray(unified_paper),
        np.asarray(sigma),
        noise,
        global_noise,
    )


def format_result(result: DemoResult) -> str:
    # Everything below is host-side formatting: move the arrays to NumPy once, so that printing
    # does not dispatch (and compile) one small XLA computation per expression.
    scene, cal = jax.tree_util.tree_map(np.asarray, (result.scene, result.calibration))
    true, est = scene.local_cameras, cal.cameras
    out = []
    w = out.append
    w("mvcalib demo: the paper's experiment (Chaudhury et al.) on a synthetic scene")
    w(
        f"  one camera, image {scene.image_size[0]} x {scene.image_size[1]} px; the 19-dot "
        "box-corner target put down in 4 placements, so each snapshot sees it from another"
    )
    w(
        f"  position; {len(scene.calibration_ids)} dots per snapshot for the DLT, "
        f"{len(scene.registration_ids)} measured in both frames for registration"
    )
    w("")
    w("1. Camera parameters per snapshot (estimate / truth); centre in the snapshot's local frame")
    w(
        f"{'snap':>4} {'alpha_u':>17} {'alpha_v':>17} {'u0':>15} {'v0':>15} {'skew':>7} "
        f"{'centre error':>12}"
    )
    centre = lambda c: -np.einsum("...ji,...j->...i", c.R, c.t)  # noqa: E731
    centre_err = np.linalg.norm(centre(est) - centre(true), axis=-1)
    for i in range(len(true)):
        cells = [
            f"{float(getattr(est, k)[i]):8.2f}/{float(getattr(true, k)[i]):<8.2f}"
            for k in ("alpha_u", "alpha_v")
        ] + [
            f"{float(getattr(est, k)[i]):7.2f}/{float(getattr(true, k)[i]):<7.2f}"
            for k in ("u0", "v0")
        ]
        w(
            f"{i + 1:>4} {cells[0]:>17} {cells[1]:>17} {cells[2]:>15} {cells[3]:>15} "
            f"{float(est.skew[i]):7.3f} {centre_err[i]:9.3f} mm"
        )
    w("")
    w("2. M on the calibration dots")
    w(format_table(cal.report, names=_SNAPSHOTS))
    w("")
    w("3. Local -> global registration from 18 dots (Y = R X + T)")
    local = scene.world[np.asarray(scene.registration_ids)]
    for name, T in (
        ("Procrustes (default)", result.registration),
        ("paper eqs. 25-28", result.registration_paper),
    ):
        R, t = np.asarray(T.R), np.asarray(T.t)
        resid = np.linalg.norm(
            local @ np.swapaxes(R, -1, -2) + t[:, None] - scene.world_global, axis=-1
        )
        RtR = np.swapaxes(R, -1, -2) @ R - np.eye(3)
        rms = np.sqrt((resid**2).mean(-1))
        w(
            f"   {name:<21} residual RMS per snapshot (mm): "
            + " ".join(f"{r:.3f}" for r in rms)
            + f"   max |R^T R - I| = {np.abs(RtR).max():.1e}"
        )
    if result.global_noise == 0:
        w(
            "   (global coordinates exact here; `--global-noise 0.5` measures them with 0.5 mm "
            "noise, and the paper's R stops being a rotation)"
        )
    w("")
    w("4. The fixed room point seen through every snapshot's camera in the global frame")
    cam = scene.camera
    xc = cam.R @ scene.fixed_point + cam.t
    true_px = (cam.alpha_u * xc[0] / xc[2] + cam.u0, cam.alpha_v * xc[1] / xc[2] + cam.v0)
    w(
        f"   (true pixel ({true_px[0]:.1f}, {true_px[1]:.1f}); image-plane coordinates for a "
        f"{PIXEL_SIZE_MM[0] * 1000:.1f} um pixel, centre at the array midpoint)"
    )
    centre_px = np.array(scene.image_size) / 2.0  # Tsai: the array midpoint, as the paper
    image_xy = (result.unified - centre_px) * np.array(PIXEL_SIZE_MM)
    for i, (px, xy) in enumerate(zip(result.unified, image_xy)):
        w(
            f"   snapshot {i + 1}: pixel ({px[0]:9.4f}, {px[1]:9.4f}) -> rounded "
            f"({int(np.rint(px[0]))}, {int(np.rint(px[1]))});  image plane "
            f"({xy[0]:+.4f}, {xy[1]:+.4f}) mm"
        )
    rounded = {tuple(np.rint(p).astype(int).tolist()) for p in result.unified}
    spread = np.ptp(result.unified, axis=0).max()
    spread_paper = np.ptp(result.unified_paper, axis=0).max()
    verdict = (
        f"the same rounded pixel {rounded.pop()} from all four snapshots"
        if len(rounded) == 1
        else f"{len(rounded)} different rounded pixels"
    )
    w(
        f"   -> {verdict}; spread {spread:.2e} px "
        f"(with the paper's registration: {spread_paper:.2e} px)"
    )
    if result.noise > 0:
        w(
            f"   expected scatter from {result.noise} px pixel noise (first order, per snapshot): "
            f"sigma x {result.unified_sigma[:, 0].mean():.2f} px, "
            f"y {result.unified_sigma[:, 1].mean():.2f} px"
        )
    return "\n".join(out)


def main(
    *, noise: float = 0.3, global_noise: float = 0.0, seed: int = 2010, float32: bool = False
) -> int:
    dtype = jnp.float32 if float32 else jnp.float64
    print(format_result(run(noise=noise, global_noise=global_noise, seed=seed, dtype=dtype)))
    return 0


# ---------------------------------------------------------------------------- from photographs
@dataclasses.dataclass
class ImageDemoResult:
    scene: PaperScene
    images: list  # the four rendered photographs
    result: ImageCalibration
    focal_error: np.ndarray  # (4,) relative error of alpha_u
    rotation_error: np.ndarray  # (4,) degrees between estimated and true R
    unified: np.ndarray  # (4, 2) the fixed point's pixel from each snapshot
    figure: pathlib.Path | None


def _angle_deg(R_est, R_true) -> np.ndarray:
    cos = (np.trace(R_est @ np.swapaxes(R_true, -1, -2), axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _grey8(image) -> np.ndarray:
    image = np.asarray(image, dtype=np.float64)
    lo, hi = image.min(), image.max()
    return np.uint8(np.rint(255 * (image - lo) / (hi - lo if hi > lo else 1.0)))


def stages_figure(
    image, detection: Detection, labels: Labels | None = None, fiducials=()
) -> np.ndarray:
    """The paper's Fig. 3 as one RGB picture: 2 x 3 panels, in reading order: the photograph,
    binarised, inverted, background (grey opening), background subtracted, and the detected dots
    (each kept blob in its own colour, labelled dots' centroids marked with a white cross,
    fiducials with a larger one).

    `detection` must come from `detect_dots(image, return_stages=True)`.
    """
    from skimage import color, draw

    stages = detection.stages
    if stages is None:
        raise ValueError("pass a detection made with `detect_dots(..., return_stages=True)`.")
    panels = [
        _grey8(image if np.ndim(image) == 2 else color.rgb2gray(image)),
        _grey8(stages["binary"]),
        _grey8(stages["inverted"]),
        _grey8(stages["background"]),
        _grey8(stages["subtracted"]),
    ]
    panels = [np.repeat(p[..., None], 3, axis=-1) for p in panels]
    detected = np.uint8(255 * color.label2rgb(stages["detected"], bg_label=0, bg_color=(0, 0, 0)))
    height, width = detected.shape[:2]
    if labels is not None:
        for m in np.flatnonzero(labels.mask):
            x, y = labels.pixels[m]
            arm = 14 if m in set(np.asarray(fiducials).tolist()) else 8
            for dr, dc in ((0, 1), (1, 0)):
                rr, cc = draw.line(
                    int(round(y - arm * dr)), int(round(x - arm * dc)),
                    int(round(y + arm * dr)), int(round(x + arm * dc)),
                )  # fmt: skip
                keep = (rr >= 0) & (rr < height) & (cc >= 0) & (cc < width)
                detected[rr[keep], cc[keep]] = 255
    panels.append(detected)
    gap = 12
    canvas = np.full((2 * height + gap, 3 * width + 2 * gap, 3), 255, np.uint8)
    for k, panel in enumerate(panels):
        r, c = divmod(k, 3)
        canvas[r * (height + gap) : r * (height + gap) + height, c * (width + gap) :][:, :width] = (
            panel
        )
    return canvas


def run_images(*, seed: int = 2010, figure=None, clutter: int = 3) -> ImageDemoResult:
    """The paper's pipeline from rendered photographs of the four snapshots (see `run`)."""
    from ._detect import detect_dots
    from ._images import calibrate_images
    from ._label import label_dots

    scene = paper_scene(jax.random.key(seed), noise=0.0)
    target = box_corner()
    images = [
        render(scene.local_cameras[i], target, scene.image_size, key=seed + i, clutter=clutter)
        for i in range(len(scene.local_cameras))
    ]
    result = calibrate_images(images, target)
    cameras = jax.tree_util.tree_map(np.asarray, result.cameras)
    true = jax.tree_util.tree_map(np.asarray, scene.local_cameras)
    focal_error = np.abs(cameras.alpha_u / true.alpha_u - 1.0)
    rotation_error = _angle_deg(cameras.R, true.R)
    local = scene.world[np.asarray(scene.registration_ids)]
    registration = procrustes(local, scene.world_global)
    unified = to_global(result.cameras, registration).project(scene.fixed_point[None])[:, 0]
    written = None
    if figure is not None:
        detection = detect_dots(images[0], return_stages=True)
        labels = label_dots(detection, target)
        buffer = _png_bytes(stages_figure(images[0], detection, labels, target.fiducials))
        written = write_atomic(figure, buffer)
    return ImageDemoResult(
        scene, images, result, focal_error, rotation_error, np.asarray(unified), written
    )


def _png_bytes(picture: np.ndarray) -> bytes:
    import imageio.v3 as iio  # scikit-image's own image I/O

    return iio.imwrite("<bytes>", picture, extension=".png")


def format_images(demo: ImageDemoResult) -> str:
    scene = demo.scene
    out = [
        "mvcalib demo --images: the paper's pipeline from photographs (rendered, 1000 x 1100 px,",
        "  blur 1 px, noise 3 grey levels, illumination gradient, 3 clutter blobs per image)",
        "",
        "1. Dots detected (binarise, invert, background by opening, subtract, label, keep dots)",
        "   and labelled from the eight large fiducial dots, per snapshot:",
    ]
    for name, message in zip(demo.result.names, demo.result.messages):
        out.append(f"   {name}: {message}")
    out += ["", "2. Camera per snapshot from its labelled dots (estimate vs truth)"]
    cameras = jax.tree_util.tree_map(np.asarray, demo.result.cameras)
    true = scene.local_cameras
    for i in range(len(demo.images)):
        out.append(
            f"   snapshot {i + 1}: alpha_u {cameras.alpha_u[i]:8.2f} / {float(true.alpha_u[i]):.2f}"
            f"  ({100 * demo.focal_error[i]:.3f} %), rotation off by "
            f"{demo.rotation_error[i]:.3f} deg"
        )
    table = format_table(demo.result.calibration.report, names=_SNAPSHOTS)
    out += ["", "3. On the labelled dots", table, ""]
    out.append("4. The fixed room point from every snapshot's camera in the global frame")
    for i, px in enumerate(demo.unified):
        out.append(f"   snapshot {i + 1}: pixel ({px[0]:9.3f}, {px[1]:9.3f})")
    spread = np.ptp(demo.unified, axis=0).max()
    out.append(
        f"   spread {spread:.3f} px (centroids corrected for the dots' perspective bias, "
        "which would otherwise move them by up to a few pixels)"
    )
    if demo.figure is not None:
        out += [
            "",
            f"Processing stages of snapshot 1 written to {demo.figure}",
            "  (panels: photograph, binary, inverted, background, subtracted, detected + labels)",
        ]
    return "\n".join(out)


def main_images(*, seed: int = 2010, figure="mvcalib_stages.png") -> int:
    demo = run_images(seed=seed, figure=figure)
    print(format_images(demo))
    return 0 if demo.result.ok.all() else 1
