"""mvcalib: calibrate rigs of cameras and reconstruct what several of them see, in JAX.

The public API is what this module re-exports; everything else is private.
"""

from . import synthetic as synthetic, targets as targets
from ._rotation import nearest_rotation as nearest_rotation, rodrigues as rodrigues
from ._status import Status as Status
from ._camera import (
    Camera as Camera,
    distort as distort,
    image_to_pixel as image_to_pixel,
    pixel_to_image as pixel_to_image,
)
from ._dlt import dlt as dlt
from ._pipeline import (
    Calibration as Calibration,
    CalibrationError as CalibrationError,
    calibrate as calibrate,
)
from ._registration import (
    RigidTransform as RigidTransform,
    procrustes as procrustes,
    procrustes_paper as procrustes_paper,
    to_global as to_global,
)
from ._report import ReprojectionReport as ReprojectionReport, reprojection_report as reprojection_report
from .targets import Target as Target

__version__ = "0.1.0"
