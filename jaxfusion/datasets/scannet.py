"""Reader for ScanNet sequences exported with ScanNet's `SensReader` (`export_sens`).

Layout of a scene folder:

```
color/<i>.jpg                  colour (typically 1296×968), resized here to the depth size
depth/<i>.png                  uint16 depth in millimetres (typically 640×480)
pose/<i>.txt                   4×4 camera-to-world; rows of -inf mark frames without a pose
intrinsic/intrinsic_depth.txt  4×4 (or 3×3) depth intrinsics
label-filt/<i>.png             optional GT labels as NYU40 ids (see `label_tsv` for raw ids)
```
Labels are mapped to the paper's 12 classes with `classes.NYU40_TO_SCANNET12`; NYU40 ids with
no class (unannotated 0, wall 1, anything > 40) become `classes.IGNORE_LABEL` (-1).

Frames with an invalid (non-finite) pose are always skipped, counted in
`sequence.info["skipped"]` and reported with a warning. Missing, mismatched or corrupt files
raise an error naming the file, unless `skip_bad=True`, in which case the frame is skipped and
counted the same way. A bad intrinsics file is always an error.
"""

import csv
import os

import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.datasets import classes
from jaxfusion.datasets import files
from jaxfusion.datasets.classes import IGNORE_LABEL, NYU40_TO_SCANNET12
from jaxfusion.datasets.sequence import RGBDSequence

DEPTH_SCALE = 1000.0  # ScanNet depth PNGs hold millimetres
_EXT = {"color": ".jpg", "depth": ".png", "pose": ".txt", "label-filt": ".png"}


def _ids(folder: str, ext: str) -> dict:
  """`{frame id: path}` of the files named `<int>.<ext>` in a folder."""
  out = {}
  for name in os.listdir(folder):
    stem, e = os.path.splitext(name)
    if e.lower() == ext and stem.isdigit():
      out[int(stem)] = os.path.join(folder, name)
  return out


def read_intrinsics(path: str) -> Camera:
  """Depth intrinsics from `intrinsic_depth.txt` (4×4 or 3×3), checked for sanity."""
  m = files.read_matrix(path)
  if m.shape not in ((4, 4), (3, 3)):
    raise files.BadFileError(f"expected a 4x4 or 3x3 intrinsics matrix in {path}; got {m.shape}")
  if not np.all(np.isfinite(m)) or m[0, 0] <= 0 or m[1, 1] <= 0 or m[2, 2] != 1.0:
    raise files.BadFileError(f"not a pinhole intrinsics matrix in {path}:\n{m}")
  return Camera.from_matrix(m)


def read_label_tsv(path: str) -> np.ndarray:
  """Raw ScanNet label id → NYU40 id lookup from `scannetv2-labels.combined.tsv`.

  Returns:
    `(M,) int32` table indexed by raw id (0 where unknown).
  """
  if not os.path.isfile(path):
    raise FileNotFoundError(f"missing file: {path}")
  pairs = []
  try:
    with open(path, newline="", encoding="utf-8") as f:
      reader = csv.DictReader(f, delimiter="\t")
      if reader.fieldnames is None or not {"id", "nyu40id"} <= set(reader.fieldnames):
        raise files.BadFileError(f"{path} lacks the 'id' and 'nyu40id' columns")
      for row in reader:
        try:
          pairs.append((int(row["id"]), int(row["nyu40id"])))
        except (ValueError, TypeError) as e:
          raise files.BadFileError(f"bad row in {path}: {row}") from e
        if pairs[-1][0] < 0:
          raise files.BadFileError(f"bad row in {path}: negative id in {row}")
  except (UnicodeDecodeError, csv.Error) as e:
    raise files.BadFileError(f"{path} is not a label table (tab-separated text): {e}") from e
  lut = np.zeros((max([r for r, _ in pairs], default=0) + 1,), np.int32)
  for raw, nyu in pairs:
    lut[raw] = nyu
  return lut


def nyu40_to_classes(nyu40: np.ndarray, lut: np.ndarray = NYU40_TO_SCANNET12) -> np.ndarray:
  """`(H, W) int32` class labels from NYU40 ids through a label space's lookup (default the
  paper's 12 classes; unknown ids → `IGNORE_LABEL`)."""
  nyu40 = np.asarray(nyu40, np.int64)
  ok = (nyu40 >= 0) & (nyu40 < len(lut))
  return np.where(ok, lut[np.where(ok, nyu40, 0)], IGNORE_LABEL).astype(np.int32)


def frame_ids(path: str, *, stride: int = 1, max_frames=None, skip_bad: bool = False) -> list:
  """The frame ids `load_scannet` would read, from the file names alone (no image is read):
  ids with every file present (without `skip_bad`, a missing one is an error), every
  `stride`-th, at most `max_frames` (frames whose pose turns out invalid are skipped on
  reading, so a chunked read may hold fewer)."""
  if stride < 1:
    raise ValueError(f"stride must be ≥ 1; got {stride}")
  path = os.path.abspath(path)
  for sub in ("color", "depth", "pose"):
    if not os.path.isdir(os.path.join(path, sub)):
      raise FileNotFoundError(f"not a ScanNet export: folder {os.path.join(path, sub)} is missing")
  sources = {sub: _ids(os.path.join(path, sub), _EXT[sub]) for sub in ("color", "depth", "pose")}
  label_dir = os.path.join(path, "label-filt")
  if os.path.isdir(label_dir):
    sources["label-filt"] = _ids(label_dir, _EXT["label-filt"])
  ids = []
  for i in sorted(set().union(*[set(s) for s in sources.values()])):
    missing = [sub for sub, s in sources.items() if i not in s]
    if not missing:
      ids.append(i)
    elif not skip_bad:
      raise FileNotFoundError(f"mismatched ScanNet files: missing "
                              f"{os.path.join(path, missing[0], f'{i}{_EXT[missing[0]]}')} "
                              "(pass skip_bad=True to skip such frames)")
  ids = ids[::stride]
  return ids if max_frames is None else ids[:max_frames]


def _check_aspect(path: str, shape, depth_shape) -> None:
  """Refuses a colour or label image whose aspect ratio is not the depth image's (within 5%):
  resized to the depth size, another picture would otherwise pass as this frame's."""
  aspect, depth_aspect = shape[1] / shape[0], depth_shape[1] / depth_shape[0]
  if abs(aspect / depth_aspect - 1) > 0.05:
    raise files.BadFileError(f"{path} is {shape[1]}x{shape[0]}, not the shape of its "
                             f"{depth_shape[1]}x{depth_shape[0]} depth image")


def load_scannet(path: str, *, stride: int = 1, max_frames=None, skip_bad: bool = False,
                 label_tsv=None, depth_scale: float = DEPTH_SCALE, name=None,
                 label_space: str = "scannet12", frame_ids=None) -> RGBDSequence:
  """Loads an exported ScanNet scene as an `RGBDSequence`.

  Args:
    path: the scene folder (with `color/`, `depth/`, `pose/`, `intrinsic/`).
    stride: keep every `stride`-th frame (by frame id order), e.g. 10 for ScanNet's 30 Hz.
    max_frames: keep at most this many frames after striding.
    skip_bad: skip frames with missing or corrupt files instead of raising (they are counted
      in `info["skipped"]` and reported with a warning).
    label_tsv: optional `scannetv2-labels.combined.tsv`; give it when `label-filt/` holds raw
      ScanNet ids rather than NYU40 ids.
    depth_scale: depth PNG units per metre.
    name: sequence name (default: the folder name).
    label_space: the classes the NYU40 GT labels are read into (`classes.LABEL_SPACES`:
      "scannet12", the paper's, by default; "scannet20", "nyu40", "embedded").
    frame_ids: read only these frame ids (e.g. a chunk of `frame_ids(path, stride=...)`; the
      stride is then not applied again).

  Returns:
    `RGBDSequence` with the depth intrinsics, colour resized to the depth resolution, and
    `labels` over the label space's classes when `label-filt/` exists (else None).

  Raises:
    FileNotFoundError: a required folder or file is missing (without `skip_bad`).
    ValueError: counts do not match, a file is corrupt, or no valid frame remains.
  """
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where used)
  if stride < 1:
    raise ValueError(f"stride must be ≥ 1; got {stride}")
  class_names, lut = classes.label_space(label_space)
  path = os.path.abspath(path)
  for sub in ("color", "depth", "pose"):
    if not os.path.isdir(os.path.join(path, sub)):
      raise FileNotFoundError(f"not a ScanNet export: folder {os.path.join(path, sub)} is missing")
  intr_path = os.path.join(path, "intrinsic", "intrinsic_depth.txt")
  camera = read_intrinsics(intr_path)
  raw_to_nyu = None if label_tsv is None else read_label_tsv(label_tsv)
  color, depth, pose = (_ids(os.path.join(path, sub), _EXT[sub])
                        for sub in ("color", "depth", "pose"))
  label_dir = os.path.join(path, "label-filt")
  labels = _ids(label_dir, _EXT["label-filt"]) if os.path.isdir(label_dir) else None
  sources = {"color": color, "depth": depth, "pose": pose}
  if labels is not None:
    sources["label-filt"] = labels
  all_ids = sorted(set().union(*[set(s) for s in sources.values()]))
  skipped = []
  ids = []
  for i in all_ids:
    missing = [os.path.join(path, sub, f"{i}{_EXT[sub]}") for sub, s in sources.items()
               if i not in s]
    if not missing:
      ids.append(i)
    elif skip_bad:
      skipped.append({"frame": i, "file": missing[0], "reason": "missing file"})
    else:
      counts = ", ".join(f"{sub}: {len(s)}" for sub, s in sources.items())
      raise FileNotFoundError(f"mismatched ScanNet files ({counts}); missing {missing[0]} "
                              "(pass skip_bad=True to skip such frames)")
  if frame_ids is None:
    ids = ids[::stride]
  else:
    wanted = {int(i) for i in frame_ids}
    ids = [i for i in ids if i in wanted]
  rgbs, depths, poses, labs, kept = [], [], [], [], []
  size = None
  for i in ids:
    if max_frames is not None and len(kept) >= max_frames:
      break
    current = pose[i]
    try:
      T = files.read_matrix(pose[i], (4, 4))
      if not np.all(np.isfinite(T)):
        skipped.append({"frame": i, "file": pose[i], "reason": "invalid pose (non-finite)"})
        continue
      if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-4):
        raise files.BadFileError(f"pose in {pose[i]} is not a rigid 4x4 transform")
      current = depth[i]
      d = files.read_depth(depth[i], depth_scale)
      if size is None:
        size = d.shape
        if not (0 <= camera.cx < size[1] and 0 <= camera.cy < size[0]):
          # A plain ValueError: a wrong intrinsics file is never skipped as a bad frame.
          raise ValueError(
              f"intrinsics in {intr_path} (cx={camera.cx}, cy={camera.cy}) do not fit the "
              f"{size[1]}x{size[0]} depth images")
      if d.shape != size:
        raise files.BadFileError(f"depth {depth[i]} is {d.shape}, other frames are {size}")
      current = color[i]
      colour = files.read_rgb(color[i])
      _check_aspect(color[i], colour.shape[:2], size)
      rgb = cv2.resize(colour, (size[1], size[0]), interpolation=cv2.INTER_AREA)
      lab = None
      if labels is not None:
        current = labels[i]
        raw = files.read_png16(labels[i]).astype(np.int64)
        _check_aspect(labels[i], raw.shape, size)
        if raw_to_nyu is not None:
          raw = np.where(raw < len(raw_to_nyu), raw_to_nyu[np.minimum(raw, len(raw_to_nyu) - 1)],
                         0)
        raw = cv2.resize(raw.astype(np.int32), (size[1], size[0]),
                         interpolation=cv2.INTER_NEAREST_EXACT)
        lab = nyu40_to_classes(raw, lut)
    except (files.BadFileError, FileNotFoundError) as e:
      if not skip_bad:
        raise
      skipped.append({"frame": i, "file": current, "reason": str(e)})
      continue
    rgbs.append(rgb)
    depths.append(d)
    poses.append(T.astype(np.float32))
    labs.append(lab)
    kept.append(i)
  files.warn_skipped(f"load_scannet({path})", skipped)
  if not kept:
    raise ValueError(f"no valid frames in ScanNet folder {path}")
  return RGBDSequence(
      name=name or os.path.basename(path), class_names=class_names, camera=camera,
      rgb=np.stack(rgbs), depth=np.stack(depths), T_world_cam=np.stack(poses),
      labels=None if labels is None else np.stack(labs),
      info={"source": "scannet", "path": path, "frame_ids": kept, "stride": stride,
            "skipped": skipped, "num_skipped": len(skipped), "label_space": label_space})
