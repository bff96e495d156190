"""One real RGB-D frame: the Middlebury 2014 "Motorcycle" pair shipped with scikit-image.

`skimage.data.stereo_motorcycle()` returns a rectified stereo pair downsampled 4× and its
ground-truth disparity. With the calibration in its docstring (valid for the downsampled
images) the disparity becomes metric z-depth: `Z = baseline · f / (d + doffs)`.
"""

import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.datasets.sequence import RGBDFrame

# Calibration of the downsampled pair (from the docstring of skimage.data.stereo_motorcycle).
FOCAL_PX = 994.978
CX, CY = 311.193, 254.877
DOFFS_PX = 31.086  # x-difference of the principal points of the two cameras
BASELINE_M = 0.193001


def disparity_to_depth(disp: np.ndarray) -> np.ndarray:
  """`(H, W) float32` z-depth in metres from Middlebury disparities (non-finite → 0)."""
  disp = np.asarray(disp, np.float64)
  ok = np.isfinite(disp) & (disp + DOFFS_PX > 0)
  depth = np.where(ok, BASELINE_M * FOCAL_PX / np.where(ok, disp + DOFFS_PX, 1.0), 0.0)
  return depth.astype(np.float32)


def middlebury_frame(*, T_world_cam=None) -> RGBDFrame:
  """The left Motorcycle image with metric depth from the ground-truth disparity.

  Args:
    T_world_cam: `(4, 4)` pose to give the frame; default identity.

  Returns:
    `RGBDFrame` with `rgb (500, 741, 3) uint8`, `depth (500, 741) float32` (0 where the
    disparity is unknown), the calibrated `Camera`, and no labels.

  Raises:
    ImportError: scikit-image (a dev dependency) is not installed.
  """
  try:
    from skimage import data  # pylint: disable=g-import-not-at-top
  except ImportError as e:
    raise ImportError("middlebury_frame needs scikit-image, which ships the Middlebury "
                      "Motorcycle pair: pip install 'jaxfusion[dev]' (or scikit-image)") from e
  left, _, disp = data.stereo_motorcycle()
  T = np.eye(4, dtype=np.float32) if T_world_cam is None else np.asarray(T_world_cam, np.float32)
  return RGBDFrame(rgb=np.asarray(left, np.uint8), depth=disparity_to_depth(disp), T_world_cam=T,
                   camera=Camera(FOCAL_PX, FOCAL_PX, CX, CY))
