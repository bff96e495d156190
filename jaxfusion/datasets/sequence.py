"""The one dataset interface: RGB-D frames with poses, and sequences of them on disk.

Every source (the synthetic world, ScanNet, TUM RGB-D) returns an `RGBDSequence`. A sequence
holds its frames in memory as stacked NumPy arrays (loaders take `stride`/`max_frames` to
bound memory), indexes and iterates as `RGBDFrame`s, and saves to / loads from a folder:

```
<path>/meta.json            name, class names, camera, frame count, image size, info
<path>/frames/000000.npz    rgb (H, W, 3) uint8, depth (H, W) float32, T_world_cam (4, 4),
                            and labels / instances (H, W) int32 when present
```
`.npz` keeps depth and labels bit-exact.

Shape legend: T frames, H×W pixels.
"""

import dataclasses
import json
import os
from typing import NamedTuple, Optional

import numpy as np

from jaxfusion import io
from jaxfusion.camera import Camera

FORMAT_VERSION = 1


class RGBDFrame(NamedTuple):
  """One posed RGB-D frame.

  Attributes:
    rgb: `(H, W, 3) uint8` colour image.
    depth: `(H, W) float32` z-depth in metres, 0 where invalid.
    T_world_cam: `(4, 4) float32` camera-to-world pose (OpenCV camera frame).
    camera: pinhole intrinsics of the depth image.
    labels: `(H, W) int32` ground-truth classes (`classes.IGNORE_LABEL` = no label) or None.
    instances: `(H, W) int32` instance ids (0 = none) or None.
  """
  rgb: np.ndarray
  depth: np.ndarray
  T_world_cam: np.ndarray
  camera: Camera
  labels: Optional[np.ndarray] = None
  instances: Optional[np.ndarray] = None


def _check_frames(rgb, depth, T_world_cam, labels, instances):
  if rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.dtype != np.uint8:
    raise ValueError(f"rgb must be (T, H, W, 3) uint8; got {rgb.shape} {rgb.dtype}")
  t, h, w = rgb.shape[:3]
  if depth.shape != (t, h, w):
    raise ValueError(f"depth must be {(t, h, w)}; got {depth.shape}")
  if T_world_cam.shape != (t, 4, 4):
    raise ValueError(f"T_world_cam must be {(t, 4, 4)}; got {T_world_cam.shape}")
  for name, x in (("labels", labels), ("instances", instances)):
    if x is not None and x.shape != (t, h, w):
      raise ValueError(f"{name} must be {(t, h, w)}; got {x.shape}")


@dataclasses.dataclass(frozen=True, eq=False)
class RGBDSequence:
  """A posed RGB-D sequence with optional per-pixel ground truth.

  Attributes:
    name: identifier, e.g. `"office_0_test"` or a folder name.
    class_names: names of the label classes (empty if unlabelled).
    camera: intrinsics shared by all frames (of the depth image, which the colour matches).
    rgb: `(T, H, W, 3) uint8`.
    depth: `(T, H, W) float32` metres, 0 = invalid.
    T_world_cam: `(T, 4, 4) float32` camera-to-world poses.
    labels: `(T, H, W) int32` or None.
    instances: `(T, H, W) int32` or None.
    info: JSON-serialisable provenance: source, skipped frames and why, parameters.
  """
  name: str
  class_names: tuple
  camera: Camera
  rgb: np.ndarray
  depth: np.ndarray
  T_world_cam: np.ndarray
  labels: Optional[np.ndarray] = None
  instances: Optional[np.ndarray] = None
  info: dict = dataclasses.field(default_factory=dict)

  def __post_init__(self):
    object.__setattr__(self, "rgb", np.asarray(self.rgb, np.uint8))
    object.__setattr__(self, "depth", np.asarray(self.depth, np.float32))
    object.__setattr__(self, "T_world_cam", np.asarray(self.T_world_cam, np.float32))
    for field in ("labels", "instances"):
      value = getattr(self, field)
      if value is not None:
        object.__setattr__(self, field, np.asarray(value, np.int32))
    object.__setattr__(self, "class_names", tuple(self.class_names))
    object.__setattr__(self, "camera", Camera(*(float(x) for x in self.camera)))
    _check_frames(self.rgb, self.depth, self.T_world_cam, self.labels, self.instances)

  def __len__(self) -> int:
    return int(self.rgb.shape[0])

  def __getitem__(self, index: int) -> RGBDFrame:
    if not -len(self) <= index < len(self):
      raise IndexError(f"frame {index} out of range for a sequence of {len(self)} frames")
    return RGBDFrame(
        rgb=self.rgb[index], depth=self.depth[index], T_world_cam=self.T_world_cam[index],
        camera=self.camera,
        labels=None if self.labels is None else self.labels[index],
        instances=None if self.instances is None else self.instances[index])

  def __iter__(self):
    return (self[i] for i in range(len(self)))

  def __repr__(self) -> str:
    h, w = self.image_size
    return (f"RGBDSequence(name={self.name!r}, frames={len(self)}, size={h}x{w}, "
            f"classes={len(self.class_names)}, labels={self.labels is not None})")

  @property
  def image_size(self) -> tuple:
    """`(H, W)`."""
    return tuple(int(x) for x in self.rgb.shape[1:3])

  @property
  def num_classes(self) -> int:
    return len(self.class_names)

  def stacked(self) -> dict:
    """All frames as stacked arrays for batch fusion.

    Returns:
      dict with `rgb (T, H, W, 3) uint8`, `depth (T, H, W) float32`,
      `T_world_cam (T, 4, 4) float32`, and `labels` / `instances` `(T, H, W) int32` when
      present.
    """
    out = {"rgb": self.rgb, "depth": self.depth, "T_world_cam": self.T_world_cam}
    if self.labels is not None:
      out["labels"] = self.labels
    if self.instances is not None:
      out["instances"] = self.instances
    return out

  def subset(self, indices) -> "RGBDSequence":
    """A sequence of the selected frames (e.g. `range(0, len(seq), 5)`).

    The `info` entries that name frames follow them (`changes`): the per-frame `true_poses`
    are picked, and the frame ranges `gt_frames` (`[start, stop]`) and `passes` (a list of
    them) are renumbered to the positions of their selected frames.

    Raises:
      ValueError: the selected frames of such a range are not consecutive in the subset.
    """
    idx = np.asarray(list(indices), np.int64)
    pick = lambda x: None if x is None else x[idx]
    return dataclasses.replace(self, rgb=self.rgb[idx], depth=self.depth[idx],
                               T_world_cam=self.T_world_cam[idx], labels=pick(self.labels),
                               instances=pick(self.instances), info=_subset_info(self.info, idx))

  def save(self, path: str) -> str:
    """Writes the sequence to a folder (created if needed; existing frames are replaced).

    Args:
      path: destination folder.

    Returns:
      The folder path.
    """
    frames_dir = os.path.join(path, "frames")
    os.makedirs(frames_dir, exist_ok=True)
    for old in os.listdir(frames_dir):
      if old.endswith(".npz"):
        os.remove(os.path.join(frames_dir, old))
    for i, frame in enumerate(self):
      arrays = {"rgb": frame.rgb, "depth": frame.depth, "T_world_cam": frame.T_world_cam}
      if frame.labels is not None:
        arrays["labels"] = frame.labels
      if frame.instances is not None:
        arrays["instances"] = frame.instances
      io.atomic_write(os.path.join(frames_dir, f"{i:06d}.npz"),
                      lambda tmp, arrays=arrays: np.savez_compressed(tmp, **arrays))
    meta = {
        "format_version": FORMAT_VERSION, "name": self.name,
        "class_names": list(self.class_names), "camera": dict(self.camera._asdict()),
        "num_frames": len(self), "image_size": list(self.image_size),
        "has_labels": self.labels is not None, "has_instances": self.instances is not None,
        "info": self.info,
    }

    def write_meta(tmp):
      with open(tmp, "w") as f:
        json.dump(meta, f, indent=1)

    # meta.json last: a save that breaks off leaves no folder that reads back as whole.
    io.atomic_write(os.path.join(path, "meta.json"), write_meta)
    return path

  @classmethod
  def load(cls, path: str, frames=None) -> "RGBDSequence":
    """Reads a folder written by `save` (all of it, or some of its frames).

    Args:
      path: the folder.
      frames: the frame indices to read (default all): a long sequence can be read in chunks.
        The `info` entries that name frames follow them, as in `subset`.

    Returns:
      The sequence, bit-identical to the one saved.

    Raises:
      FileNotFoundError: `meta.json` or a frame file is missing.
      ValueError: a file is corrupt or disagrees with `meta.json`.
    """
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
      raise FileNotFoundError(f"not a saved sequence: {meta_path} is missing")
    try:
      with open(meta_path, "rb") as f:
        meta = json.loads(f.read().decode("utf-8"))
      camera = Camera(**{k: float(v) for k, v in meta["camera"].items()})
      num_frames = int(meta["num_frames"])
      h, w = (int(s) for s in meta["image_size"])
      name, class_names = str(meta["name"]), tuple(str(c) for c in meta["class_names"])
      if num_frames < 0 or h < 1 or w < 1:
        raise ValueError(f"{num_frames} frames of {h}x{w} pixels")
    except (ValueError, KeyError, TypeError, AttributeError, OSError) as e:
      raise io.BadFileError(f"corrupt sequence metadata {meta_path}: {type(e).__name__}: {e}"
                            ) from e
    expected = {"rgb": ((h, w, 3), np.uint8), "depth": ((h, w), np.float32),
                "T_world_cam": ((4, 4), np.float32)}
    if meta.get("has_labels"):
      expected["labels"] = ((h, w), np.int32)
    if meta.get("has_instances"):
      expected["instances"] = ((h, w), np.int32)
    keys = list(expected)
    data = {k: [] for k in keys}
    indices = range(num_frames) if frames is None else [int(i) for i in frames]
    bad = [i for i in indices if not 0 <= i < num_frames]
    if bad:
      raise IndexError(f"frame {bad[0]} out of range: {meta_path} lists {num_frames} frames")
    for i in indices:
      frame_path = os.path.join(path, "frames", f"{i:06d}.npz")
      if not os.path.isfile(frame_path):
        raise FileNotFoundError(f"{frame_path} is missing ({meta_path} lists {num_frames} frames)")
      z = io.read_npz(frame_path, what="frame file of a saved sequence", required=keys)
      for k, (shape, dtype) in expected.items():
        io.check_array(frame_path, "frame file of a saved sequence", k, z[k], shape, dtype)
        data[k].append(z[k])
    if not indices:
      empty = {"rgb": np.zeros((0, h, w, 3), np.uint8), "depth": np.zeros((0, h, w), np.float32),
               "T_world_cam": np.zeros((0, 4, 4), np.float32),
               "labels": np.zeros((0, h, w), np.int32), "instances": np.zeros((0, h, w), np.int32)}
      stacked = {k: empty[k] for k in keys}
    else:
      stacked = {k: np.stack(v) for k, v in data.items()}
    return cls(name=name, class_names=class_names, camera=camera,
               rgb=stacked["rgb"], depth=stacked["depth"], T_world_cam=stacked["T_world_cam"],
               labels=stacked.get("labels"), instances=stacked.get("instances"),
               info=meta.get("info", {}) if frames is None else _subset_info(
                   meta.get("info", {}), np.asarray(indices, np.int64)))



def _renumber(span, idx: np.ndarray, key: str) -> list:
  """The frame range `[start, stop]` renumbered to the positions `idx` puts its frames at."""
  start, stop = (int(x) for x in span)
  inside = np.flatnonzero((idx >= start) & (idx < stop))
  if len(inside) == 0:
    first = int(np.sum(idx < start))
    return [first, first]
  if inside[-1] - inside[0] + 1 != len(inside):
    raise ValueError(f"a subset must keep the frames of info[{key!r}] ({start} … {stop}) "
                     "together; pick its frames in order")
  return [int(inside[0]), int(inside[-1]) + 1]


def _subset_info(info: dict, idx: np.ndarray) -> dict:
  """`info` for the frames `idx` of a sequence (see `RGBDSequence.subset`)."""
  if not any(k in info for k in ("true_poses", "gt_frames", "passes")):
    return info
  info = dict(info)
  if "true_poses" in info:
    info["true_poses"] = [info["true_poses"][i] for i in idx]
  if "gt_frames" in info:
    info["gt_frames"] = _renumber(info["gt_frames"], idx, "gt_frames")
  if "passes" in info:
    info["passes"] = [_renumber(span, idx, "passes") for span in info["passes"]]
  return info


def load_sequence(path: str) -> RGBDSequence:
  """Reads a folder written by `RGBDSequence.save`."""
  return RGBDSequence.load(path)
