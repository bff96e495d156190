"""Reader for the TUM RGB-D benchmark layout.

```
rgb.txt          "timestamp rgb/<file>.png" per line ('#' comments)
depth.txt        "timestamp depth/<file>.png" per line; uint16 PNGs, 5000 units per metre
groundtruth.txt  "timestamp tx ty tz qx qy qz qw" (camera-to-world, optical frame)
```
Frames are driven by the depth images: each depth image is associated with the RGB image and
the ground-truth pose nearest in time, if within `max_time_diff` seconds. Depth images without
a match are skipped, counted in `info["skipped"]` and reported with a warning (never silently).
Missing or corrupt image files raise an error naming the file, or are skipped and counted with
`skip_bad=True`.

TUM folders carry no intrinsics: the default is the ROS default camera the benchmark recommends
(`fx = fy = 525, cx = 319.5, cy = 239.5` for 640×480, scaled to other image sizes); pass
`camera=` for the calibrated values of a specific sensor (freiburg1/2/3).

jaxfusion's own addition to the layout: an optional `calibration.txt` holding one line
`fx fy cx cy` (pixels, of the depth image) gives the camera when `camera=` is not passed.
`export.save_tum` writes it, since the camera it exports is not TUM's default.
"""

import os

import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.datasets import files
from jaxfusion.datasets.sequence import RGBDSequence

DEPTH_SCALE = 5000.0
DEFAULT_CAMERA = Camera(525.0, 525.0, 319.5, 239.5)  # for 640×480
CALIBRATION_FILE = "calibration.txt"  # jaxfusion's addition: "fx fy cx cy"


def read_calibration(path: str) -> Camera:
  """The camera of a `calibration.txt`: one line `fx fy cx cy` in pixels.

  Raises:
    FileNotFoundError: the file is missing.
    BadFileError: it does not hold four numbers that make a pinhole camera.
  """
  m = files.read_matrix(path)
  if m.shape != (1, 4):
    raise files.BadFileError(f"expected one line 'fx fy cx cy' in {path}; got a {m.shape[0]}x"
                             f"{m.shape[1]} table")
  try:
    return Camera(*(float(x) for x in m[0]))
  except ValueError as e:
    raise files.BadFileError(f"not a pinhole camera in {path}: {e}") from e


def read_list(path: str, num_fields: int) -> list:
  """Rows of a TUM list file as `(timestamp, fields...)`; '#' lines are comments.

  Raises:
    FileNotFoundError: the file is missing.
    BadFileError: a line has the wrong number of fields or a non-numeric timestamp.
  """
  if not os.path.isfile(path):
    raise FileNotFoundError(f"missing file: {path}")
  rows = []
  try:
    with open(path, encoding="utf-8") as f:
      for n, line in enumerate(f, 1):
        if not line.endswith("\n") and line.strip() and not line.lstrip().startswith("#"):
          # The benchmark's lists end in a newline: without one the last row may be cut short
          # (a number losing digits still parses).
          raise files.BadFileError(f"{path}:{n}: the last line has no newline; the file may "
                                   "be cut off (add the newline if it is whole)")
        line = line.strip()
        if not line or line.startswith("#"):
          continue
        parts = line.replace(",", " ").split()
        if len(parts) != num_fields:
          raise files.BadFileError(f"{path}:{n}: expected {num_fields} fields; got {line!r}")
        try:
          rows.append((float(parts[0]),) + tuple(parts[1:]))
        except ValueError as e:
          raise files.BadFileError(f"{path}:{n}: bad timestamp in {line!r}") from e
  except UnicodeDecodeError as e:
    raise files.BadFileError(f"{path} is not a TUM list (text): {e}") from e
  return rows


def quat_to_pose(t, q) -> np.ndarray:
  """`(4, 4) float64` pose from a translation `(3,)` and a quaternion `(qx, qy, qz, qw)`."""
  x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
  R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
  T = np.eye(4)
  T[:3, :3], T[:3, 3] = R, t
  return T


def _nearest(stamps: np.ndarray, t: float):
  """Index of the stamp nearest `t` and its distance in seconds."""
  i = int(np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1)) if len(stamps) > 1 else 0
  if len(stamps) > 1 and abs(stamps[i - 1] - t) <= abs(stamps[i] - t):
    i -= 1
  return i, abs(stamps[i] - t)


def associate(path: str, *, max_time_diff: float = 0.02) -> tuple:
  """The association of a TUM folder's lists by time (no image is read).

  Returns:
    `(matched, skipped)`: `[(timestamp, depth file, rgb file, groundtruth row)]` in time order
    for every depth image with an RGB image and a pose within `max_time_diff` seconds, and the
    depth images without (`{"timestamp", "file", "reason"}`).
  """
  path = os.path.abspath(path)
  rgb_rows = read_list(os.path.join(path, "rgb.txt"), 2)
  depth_rows = read_list(os.path.join(path, "depth.txt"), 2)
  gt_path = os.path.join(path, "groundtruth.txt")
  gt_rows = read_list(gt_path, 8)
  if not rgb_rows or not depth_rows or not gt_rows:
    empty = next(name for name, rows in (("rgb.txt", rgb_rows), ("depth.txt", depth_rows),
                                         ("groundtruth.txt", gt_rows)) if not rows)
    raise ValueError(f"empty TUM list {os.path.join(path, empty)} (rgb: {len(rgb_rows)}, "
                     f"depth: {len(depth_rows)}, groundtruth: {len(gt_rows)})")
  rgb_rows.sort()
  gt_rows.sort()
  rgb_t = np.array([r[0] for r in rgb_rows])
  gt_t = np.array([r[0] for r in gt_rows])
  skipped = []
  matched = []
  for t, depth_file in sorted(depth_rows):
    i, dt_rgb = _nearest(rgb_t, t)
    j, dt_gt = _nearest(gt_t, t)
    if dt_rgb > max_time_diff:
      skipped.append({"timestamp": t, "file": depth_file, "reason": "no rgb image in time"})
    elif dt_gt > max_time_diff:
      skipped.append({"timestamp": t, "file": depth_file, "reason": "no ground-truth pose in time"})
    else:
      matched.append((t, depth_file, rgb_rows[i][1], gt_rows[j]))
  return matched, skipped


def load_tum(path: str, *, camera=None, stride: int = 1, max_frames=None,
             max_time_diff: float = 0.02, skip_bad: bool = False,
             depth_scale: float = DEPTH_SCALE, name=None, first: int = 0) -> RGBDSequence:
  """Loads a TUM RGB-D sequence folder as an `RGBDSequence` (no labels).

  Args:
    path: the folder with `rgb.txt`, `depth.txt`, `groundtruth.txt`.
    camera: intrinsics; default: those of the folder's `calibration.txt` when it has one,
      else `DEFAULT_CAMERA` scaled to the image size.
    stride: keep every `stride`-th associated frame.
    max_frames: keep at most this many frames after striding.
    first: skip this many associated frames after striding (with `max_frames`, a chunk of a
      long sequence).
    max_time_diff: association tolerance in seconds.
    skip_bad: skip frames with missing/corrupt images or poses instead of raising.
    depth_scale: depth PNG units per metre (5000 for TUM).
    name: sequence name (default: the folder name).

  Returns:
    `RGBDSequence` with `labels=None`; `info` lists the timestamps and the skipped frames.
  """
  if stride < 1:
    raise ValueError(f"stride must be ≥ 1; got {stride}")
  path = os.path.abspath(path)
  calibration = os.path.join(path, CALIBRATION_FILE)
  if camera is None and os.path.isfile(calibration):
    camera = read_calibration(calibration)
  gt_path = os.path.join(path, "groundtruth.txt")
  matched, skipped = associate(path, max_time_diff=max_time_diff)
  positions = list(range(len(matched)))[::stride][int(first):]
  matched = matched[::stride][int(first):]
  kept_ids = []
  rgbs, depths, poses, stamps = [], [], [], []
  size = None
  for position, (t, depth_file, rgb_file, gt) in zip(positions, matched):
    if max_frames is not None and len(stamps) >= max_frames:
      break
    current, listing = os.path.join(path, depth_file), "depth.txt"
    try:
      values = np.array([float(v) for v in gt[1:]])
      if not np.all(np.isfinite(values)) or np.linalg.norm(values[3:]) < 1e-6:
        raise files.BadFileError(f"{gt_path}: invalid pose at timestamp {gt[0]}")
      d = files.read_depth(current, depth_scale)
      current, listing = os.path.join(path, rgb_file), "rgb.txt"
      rgb = files.read_rgb(current)
      if rgb.shape[:2] != d.shape:
        raise files.BadFileError(f"{current} is {rgb.shape[:2]}, its depth image {depth_file} "
                                 f"is {d.shape}")
      if size is None:
        size = d.shape
      elif d.shape != size:
        raise files.BadFileError(f"{current} is {d.shape}, other frames are {size}")
    except (files.BadFileError, FileNotFoundError) as e:
      if not skip_bad and isinstance(e, FileNotFoundError):
        raise FileNotFoundError(f"{e} (listed in {os.path.join(path, listing)})") from None
      if not skip_bad:
        raise
      skipped.append({"timestamp": t, "file": current, "reason": str(e)})
      continue
    rgbs.append(rgb)
    depths.append(d)
    poses.append(quat_to_pose(values[:3], values[3:]).astype(np.float32))
    stamps.append(t)
    kept_ids.append(position)
  files.warn_skipped(f"load_tum({path})", skipped)
  if not stamps:
    raise ValueError(f"no valid frames in TUM folder {path}")
  if camera is None:
    sx, sy = size[1] / 640.0, size[0] / 480.0
    c = DEFAULT_CAMERA
    camera = Camera(c.fx * sx, c.fy * sy, (c.cx + 0.5) * sx - 0.5, (c.cy + 0.5) * sy - 0.5)
  return RGBDSequence(
      name=name or os.path.basename(path), class_names=(), camera=camera, rgb=np.stack(rgbs),
      depth=np.stack(depths), T_world_cam=np.stack(poses),
      info={"source": "tum", "path": path, "timestamps": stamps, "frame_ids": kept_ids,
            "stride": stride,
            "skipped": skipped, "num_skipped": len(skipped)})
