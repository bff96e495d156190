"""Side-by-side previews of frames: RGB | depth | labels, written as PNG.

Shape legend: H×W pixels.
"""

import os

import numpy as np

from jaxfusion.datasets.classes import CLASS_COLORS, colorize
from jaxfusion.datasets.sequence import RGBDFrame


def depth_image(depth: np.ndarray, *, max_depth=None) -> np.ndarray:
  """Colour-maps a depth image (invalid = black).

  Args:
    depth: `(H, W) float` metres, 0 = invalid.
    max_depth: depth shown brightest-far; default the 99th percentile of valid depths.

  Returns:
    `(H, W, 3) uint8` RGB image.
  """
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where used)
  depth = np.asarray(depth, np.float32)
  valid = depth > 0
  if max_depth is None:
    max_depth = float(np.percentile(depth[valid], 99)) if valid.any() else 1.0
  scaled = np.clip(depth / max(max_depth, 1e-6), 0.0, 1.0)
  bgr = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
  rgb = bgr[..., ::-1].copy()
  rgb[~valid] = 0
  return rgb


def preview_image(frame: RGBDFrame, *, class_colors=None) -> np.ndarray:
  """The `(H, 3·W, 3) uint8` RGB | depth | labels panel of a frame (labels black if absent)."""
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where used)
  colors = CLASS_COLORS if class_colors is None else np.asarray(class_colors, np.uint8)
  rgb = np.asarray(frame.rgb, np.uint8)
  depth = depth_image(frame.depth)
  if frame.labels is None:
    labels = np.zeros_like(rgb)
  else:
    labels = colorize(frame.labels, colors)
  if depth.shape != rgb.shape:
    depth = cv2.resize(depth, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_NEAREST)
    labels = cv2.resize(labels, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_NEAREST)
  return np.concatenate([rgb, depth, labels], axis=1)


def render_preview(frame: RGBDFrame, path: str, *, class_colors=None, scale: int = 1) -> str:
  """Writes the RGB | depth | labels panel of a frame as a PNG.

  Args:
    frame: an `RGBDFrame`.
    path: output `.png` path (folders are created).
    class_colors: `(K, 3) uint8` label colours; default the synthetic world's `CLASS_COLORS`.
    scale: integer upscaling (nearest neighbour) for small frames.

  Returns:
    The path written.
  """
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where used)
  panel = preview_image(frame, class_colors=class_colors)
  if scale > 1:
    panel = np.repeat(np.repeat(panel, scale, axis=0), scale, axis=1)
  folder = os.path.dirname(os.path.abspath(path))
  os.makedirs(folder, exist_ok=True)
  if not cv2.imwrite(path, panel[..., ::-1]):
    raise OSError(f"could not write {path}")
  return path
