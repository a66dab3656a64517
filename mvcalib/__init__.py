"""mvcalib: calibrate rigs of cameras and reconstruct what several of them see, in JAX.

The public API is what this module re-exports; everything else is private.
"""

from . import io as io
from . import synthetic as synthetic
from . import targets as targets
from ._bundle import BundleAdjustment as BundleAdjustment
from ._bundle import RigRefinement as RigRefinement
from ._bundle import bundle_adjust as bundle_adjust
from ._bundle import refine_rig as refine_rig
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
from ._images import read_image as read_image
from ._label import Labels as Labels
from ._label import label_dots as label_dots
from ._pipeline import Calibration as Calibration
from ._pipeline import CalibrationError as CalibrationError
from ._pipeline import calibrate as calibrate
from ._planar import PlanarCalibration as PlanarCalibration
from ._planar import calibrate_planar as calibrate_planar
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
from ._rotation import nearest_rotation as nearest_rotation
from ._rotation import rodrigues as rodrigues
from ._sharding import shard as shard
from ._status import Status as Status
from ._triangulate import Triangulation as Triangulation
from ._triangulate import reproject as reproject
from ._triangulate import triangulate as triangulate
from .targets import Target as Target

__version__ = "0.1.0"
