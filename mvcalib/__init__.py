"""mvcalib: calibrate rigs of cameras and reconstruct what several of them see, in JAX.

The public API is what this module re-exports; everything else is private.

The names are imported on first use (PEP 562): `import mvcalib` itself costs next to nothing
beyond JAX and Equinox, and SciPy, scikit-image, Optimistix and Lineax are only imported
where a name needs them. `_EXPORTS` says where each name lives; the imports under
`TYPE_CHECKING` say the same to type checkers and editors (tests/test_imports.py checks that the
two agree).

>>> import mvcalib as mc
>>> mc.Camera.__module__
'mvcalib._camera'
>>> "calibrate" in mc.__all__ and "calibrate" in dir(mc)
True
"""

from __future__ import annotations

import importlib
import typing

__version__ = "0.1.0"

# Public submodules, and the public names of the private modules, by module.
_SUBMODULES = ("io", "plot", "synthetic", "targets")  # plot imports matplotlib only to draw
_EXPORTS = {
    "_buckets": ("quick_compiler_options",),
    "_bundle": ("BundleAdjustment", "RigRefinement", "bundle_adjust", "refine_rig"),
    "_cache": ("enable_compilation_cache",),
    "_camera": ("Camera", "distort", "image_to_pixel", "pixel_to_image", "undistort_points"),
    "_detect": ("Detection", "detect_dots"),
    "_dlt": ("dlt",),
    "_images": ("ImageCalibration", "calibrate_images", "observe_grid"),
    "_label": ("Labels", "label_dots"),
    "_match": ("label_grid", "match_dots"),
    "_photos": ("read_image",),
    "_pipeline": ("Calibration", "CalibrationError", "calibrate"),
    "_planar": ("PlanarCalibration", "calibrate_planar"),
    "_pnp": ("solve_pnp",),
    "_refine": ("Cauchy", "Huber", "Refinement", "SecantLM", "refine"),
    "_registration": ("RigidTransform", "procrustes", "procrustes_paper", "to_global"),
    "_report": ("ReprojectionReport", "reprojection_report"),
    "_rig": ("RigCalibration", "calibrate_rig"),
    "_rotation": ("nearest_rotation", "rodrigues"),
    "_second_look": ("second_look",),
    "_sharding": ("shard",),
    "_status": ("Status",),
    "_stereo": (
        "StereoRectification",
        "essential_matrix",
        "fundamental_matrix",
        "stereo_rectify",
        "undistorted",
        "undistortion_maps",
    ),  # fmt: skip
    "_triangulate": ("Triangulation", "reproject", "triangulate"),
    "targets": ("Target",),
}
_ORIGIN = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = [*_SUBMODULES, *_ORIGIN]


def __getattr__(name: str) -> typing.Any:
    """Import a public name's module on first use, and keep the name here from then on."""
    if name in _SUBMODULES:
        module = name
    elif name in _ORIGIN:
        module = _ORIGIN[name]
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from ._gc import collector_paused  # here, so that `import mvcalib` imports no submodule

    with collector_paused():  # the first names import JAX's libraries: long-lived objects
        value = importlib.import_module(f"{__name__}.{module}")
    if name in _ORIGIN:
        value = getattr(value, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


if typing.TYPE_CHECKING:
    from . import io as io
    from . import plot as plot
    from . import synthetic as synthetic
    from . import targets as targets
    from ._buckets import quick_compiler_options as quick_compiler_options
    from ._bundle import BundleAdjustment as BundleAdjustment
    from ._bundle import RigRefinement as RigRefinement
    from ._bundle import bundle_adjust as bundle_adjust
    from ._bundle import refine_rig as refine_rig
    from ._cache import enable_compilation_cache as enable_compilation_cache
    from ._camera import Camera as Camera
    from ._camera import distort as distort
    from ._camera import image_to_pixel as image_to_pixel
    from ._camera import pixel_to_image as pixel_to_image
    from ._camera import undistort_points as undistort_points
    from ._detect import Detection as Detection
    from ._detect import detect_dots as detect_dots
    from ._dlt import dlt as dlt
    from ._images import ImageCalibration as ImageCalibration
    from ._images import calibrate_images as calibrate_images
    from ._images import observe_grid as observe_grid
    from ._label import Labels as Labels
    from ._label import label_dots as label_dots
    from ._match import label_grid as label_grid
    from ._match import match_dots as match_dots
    from ._photos import read_image as read_image
    from ._pipeline import Calibration as Calibration
    from ._pipeline import CalibrationError as CalibrationError
    from ._pipeline import calibrate as calibrate
    from ._planar import PlanarCalibration as PlanarCalibration
    from ._planar import calibrate_planar as calibrate_planar
    from ._pnp import solve_pnp as solve_pnp
    from ._refine import Cauchy as Cauchy
    from ._refine import Huber as Huber
    from ._refine import Refinement as Refinement
    from ._refine import SecantLM as SecantLM
    from ._refine import refine as refine
    from ._registration import RigidTransform as RigidTransform
    from ._registration import procrustes as procrustes
    from ._registration import procrustes_paper as procrustes_paper
    from ._registration import to_global as to_global
    from ._report import ReprojectionReport as ReprojectionReport
    from ._report import reprojection_report as reprojection_report
    from ._rig import RigCalibration as RigCalibration
    from ._rig import calibrate_rig as calibrate_rig
    from ._rotation import nearest_rotation as nearest_rotation
    from ._rotation import rodrigues as rodrigues
    from ._second_look import second_look as second_look
    from ._sharding import shard as shard
    from ._status import Status as Status
    from ._stereo import StereoRectification as StereoRectification
    from ._stereo import essential_matrix as essential_matrix
    from ._stereo import fundamental_matrix as fundamental_matrix
    from ._stereo import stereo_rectify as stereo_rectify
    from ._stereo import undistorted as undistorted
    from ._stereo import undistortion_maps as undistortion_maps
    from ._triangulate import Triangulation as Triangulation
    from ._triangulate import reproject as reproject
    from ._triangulate import triangulate as triangulate
    from .targets import Target as Target
