"""Reading images, depth maps and matrices from disk with errors that name the file.

Every reader raises `FileNotFoundError` for a missing file and `BadFileError` (a `ValueError`)
for one that exists but cannot be used; loaders catch `BadFileError` to skip broken frames
when asked to, and count them.
"""

import os
import warnings

import numpy as np

from jaxfusion.io import BadFileError  # pylint: disable=unused-import  (re-exported)


def _require(path: str) -> None:
  if not os.path.isfile(path):
    raise FileNotFoundError(f"missing file: {path}")


def _decode(path: str, flags):
  """Decodes an image file with OpenCV; None when it cannot. A JPEG must end with its EOI
  marker: OpenCV decodes a truncated one into a partly grey image without an error."""
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where it is used)
  with open(path, "rb") as f:
    data = f.read()
  if data[:2] == b"\xff\xd8" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
    raise BadFileError(f"truncated JPEG image: {path}")
  if not data:
    return None
  return cv2.imdecode(np.frombuffer(data, np.uint8), flags)


def read_rgb(path: str) -> np.ndarray:
  """`(H, W, 3) uint8` RGB image from a JPEG/PNG file."""
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where it is used)
  _require(path)
  img = _decode(path, cv2.IMREAD_COLOR)
  if img is None:
    raise BadFileError(f"corrupt or unreadable image: {path}")
  return img[..., ::-1].copy()


def read_png16(path: str) -> np.ndarray:
  """`(H, W)` integer image (uint16 depth or label PNG) read without conversion."""
  import cv2  # pylint: disable=import-outside-toplevel
  _require(path)
  img = _decode(path, cv2.IMREAD_UNCHANGED)
  if img is None:
    raise BadFileError(f"corrupt or unreadable image: {path}")
  if img.ndim != 2:
    raise BadFileError(f"expected a single-channel image in {path}; got shape {img.shape}")
  if img.dtype not in (np.uint8, np.uint16):
    raise BadFileError(f"expected an 8- or 16-bit integer image in {path}; got {img.dtype}")
  return img


def read_depth(path: str, scale: float) -> np.ndarray:
  """`(H, W) float32` metres from a uint16 depth PNG holding `scale` units per metre."""
  raw = read_png16(path)
  if raw.dtype != np.uint16:
    raise BadFileError(f"expected a 16-bit depth PNG in {path}; got {raw.dtype}")
  return (raw.astype(np.float32) / np.float32(scale)).astype(np.float32)


def read_matrix(path: str, shape=None) -> np.ndarray:
  """A whitespace-separated float matrix from a text file.

  Args:
    path: the file.
    shape: expected shape, e.g. `(4, 4)`; None accepts any 2-D shape.

  Returns:
    `float64` array (may contain inf/nan; callers decide what is valid).
  """
  _require(path)
  try:
    m = np.loadtxt(path, dtype=np.float64, ndmin=2)
  except (ValueError, OSError) as e:
    raise BadFileError(f"cannot parse a matrix from {path}: {e}") from e
  if shape is not None and m.shape != tuple(shape):
    raise BadFileError(f"expected a {shape[0]}x{shape[1]} matrix in {path}; got {m.shape}")
  return m


def warn_skipped(loader: str, skipped: list) -> None:
  """Reports skipped frames with one warning (never silently); `loader` names the call, e.g.
  `load_tum(PATH)`. Each entry of `skipped` has a `file` and a `reason`."""
  if skipped:
    warnings.warn(f"{loader}: skipped {len(skipped)} frame(s); first: {skipped[0]['file']} "
                  f"({skipped[0]['reason']}); see sequence.info['skipped']", stacklevel=3)

