"""Maps on disk: bit-exact save/load (`.npz` with metadata) and class-coloured PLY export.

Writes go to a temporary file that is renamed into place, so an interrupted run never leaves a
half-written file behind.
"""

import json
import os
import tempfile
from typing import Optional, Sequence

import jax.numpy as jnp
import numpy as np

from jaxfusion import rules as rules_lib
from jaxfusion.state import MapState

FORMAT_VERSION = 1


def atomic_write(path: str, write) -> None:
  """Calls `write(tmp_path)` and renames the result to `path` (same folder, atomic).

  The file gets the permissions an ordinary `open(path, "w")` would give it.
  """
  folder = os.path.dirname(os.path.abspath(path))
  os.makedirs(folder, exist_ok=True)
  suffix = os.path.splitext(path)[1]
  fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=suffix)
  os.close(fd)
  try:
    write(tmp)
    # mkstemp creates 0600; give the result the permissions a plain open() would (0666 − umask).
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)
  except BaseException:
    if os.path.exists(tmp):
      os.remove(tmp)
    raise


def rule_metadata(rule: rules_lib.FusionRule) -> dict:
  """JSON-able description of a rule: its name, aggregation and hyperparameter values."""
  return {"name": rule.name, "aggregate": rule.aggregate,
          "hparams": {k: float(v) for k, v in rule.hparams.items()}}


def rule_from_metadata(meta: dict) -> rules_lib.FusionRule:
  return rules_lib.by_name(meta["name"], aggregate=meta["aggregate"], **meta["hparams"])


def _check_trajectory(poses, camera, image_size):
  """Validates the optional trajectory of `save_map`; returns `(poses or None, camera meta)`."""
  if poses is None:
    if camera is not None or image_size is not None:
      raise ValueError("camera and image_size describe the poses: pass poses too")
    return None, None
  poses = np.asarray(poses, np.float32)
  if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
    raise ValueError(f"poses must be (T, 4, 4) camera-to-world matrices; got shape "
                     f"{poses.shape}")
  if not np.all(np.isfinite(poses)):
    raise ValueError("poses must be finite")
  if camera is None:
    if image_size is not None:
      raise ValueError("image_size needs the camera intrinsics too")
    return poses, None
  if image_size is None or len(image_size) != 2 or min(int(s) for s in image_size) < 1:
    raise ValueError(f"image_size must be (H, W) with H, W ≥ 1 when a camera is given; got "
                     f"{image_size!r}")
  values = [float(v) for v in camera[:4]]
  if not all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
    raise ValueError(f"camera intrinsics must be finite with fx, fy > 0; got {values}")
  meta = dict(zip(("fx", "fy", "cx", "cy"), values))
  meta.update(height=int(image_size[0]), width=int(image_size[1]))
  return poses, meta


def save_map(path: str, state: MapState, rule: rules_lib.FusionRule, *,
             class_names: Optional[Sequence[str]] = None, extra: Optional[dict] = None,
             poses: Optional[np.ndarray] = None, camera=None,
             image_size: Optional[Sequence[int]] = None) -> None:
  """Saves a map with its metadata (classes, voxel size, rule and hyperparameters) as `.npz`.

  Args:
    path: destination, conventionally ending in `.npz`.
    state: the map.
    rule: the rule it was fused with (stored by name and hyperparameters).
    class_names: optional K class names.
    extra: optional JSON-able metadata (e.g. the sequence, the model).
    poses: optional `(T, 4, 4)` camera-to-world poses of the fused frames (OpenCV camera
      axes: +x right, +y down, +z forward), read back by `load_trajectory`.
    camera: optional intrinsics of those frames (a `Camera` or `(fx, fy, cx, cy)`); needs
      `poses` and `image_size`.
    image_size: `(H, W)` of the frames, with `camera`.
  """
  if state.keys.ndim != 2:
    raise ValueError("save_map expects one map, not a batch")
  if rule.name != state.rule_name:
    raise ValueError(f"map was made for rule {state.rule_name!r}, not {rule.name!r}")
  if class_names is not None and len(class_names) != state.num_classes:
    raise ValueError(f"{len(class_names)} class names for a map of {state.num_classes} classes")
  poses, camera_meta = _check_trajectory(poses, camera, image_size)
  meta = {
      "format_version": FORMAT_VERSION,
      "rule": rule_metadata(rule),
      "num_classes": state.num_classes,
      "capacity": state.capacity,
      "max_probes": state.max_probes,
      "class_names": list(class_names) if class_names is not None else None,
      "extra": extra or {},
      "camera": camera_meta,
  }
  arrays = {
      "keys": np.asarray(state.keys), "hits": np.asarray(state.hits),
      "claims": np.asarray(state.claims),
      "num_occupied": np.asarray(state.num_occupied),
      "num_dropped": np.asarray(state.num_dropped), "voxel_size": np.asarray(state.voxel_size),
  }
  for name, value in state.rows.items():
    arrays[f"rows/{name}"] = np.asarray(value)
  if poses is not None:
    arrays["poses"] = poses
  arrays["metadata"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)

  def write(tmp):
    with open(tmp, "wb") as f:
      np.savez_compressed(f, **arrays)

  atomic_write(path, write)


def load_map(path: str) -> tuple[MapState, rules_lib.FusionRule, dict]:
  """Loads a map saved by `save_map`: `(state, rule, metadata)`, bit-exact."""
  if not os.path.exists(path):
    raise FileNotFoundError(f"no map file at {path}")
  try:
    data = np.load(path)
    meta = json.loads(bytes(data["metadata"]).decode())
  except (OSError, ValueError, KeyError) as e:
    raise ValueError(f"{path} is not a jaxfusion map file ({e})") from e
  if meta.get("format_version") != FORMAT_VERSION:
    raise ValueError(f"{path}: unsupported map format version {meta.get('format_version')}")
  from jaxfusion.state import init_map   # deferred: keeps io importable on its own
  rule = rule_from_metadata(meta["rule"])
  state = init_map(capacity=meta["capacity"], num_classes=meta["num_classes"],
                   voxel_size=float(data["voxel_size"]), rule=rule,
                   max_probes=meta["max_probes"])
  rows = {name: jnp.asarray(data[f"rows/{name}"]) for name in state.rows}
  state = state.replace(
      keys=jnp.asarray(data["keys"]), hits=jnp.asarray(data["hits"]), rows=rows,
      claims=jnp.asarray(data["claims"]),
      num_occupied=jnp.asarray(data["num_occupied"]),
      num_dropped=jnp.asarray(data["num_dropped"]),
      voxel_size=jnp.asarray(data["voxel_size"]))
  return state, rule, meta


def load_trajectory(path: str) -> Optional[dict]:
  """The camera trajectory saved with a map, or None for a map saved without poses.

  Maps written before poses were saved load as None.

  Returns:
    dict with `T_world_cam (T, 4, 4) float32` camera-to-world poses and `camera`: a dict of
    `fx, fy, cx, cy, height, width`, or None when the intrinsics were not saved.
  """
  if not os.path.exists(path):
    raise FileNotFoundError(f"no map file at {path}")
  try:
    with np.load(path) as data:
      meta = json.loads(bytes(data["metadata"]).decode())
      poses = np.asarray(data["poses"], np.float32) if "poses" in data.files else None
  except (OSError, ValueError, KeyError) as e:
    raise ValueError(f"{path} is not a jaxfusion map file ({e})") from e
  if poses is None:
    return None
  return {"T_world_cam": poses, "camera": meta.get("camera")}


def default_palette(num_classes: int) -> np.ndarray:
  """`(K, 3) uint8` distinct colours for maps without a class colour table."""
  import matplotlib
  cmap = matplotlib.colormaps["tab20"]
  return (np.array([cmap(i % 20)[:3] for i in range(num_classes)]) * 255).astype(np.uint8)


def export_ply(path: str, voxels: dict, *, voxel_size: float,
               colors: Optional[np.ndarray] = None, mode: str = "cubes",
               labels: Optional[np.ndarray] = None) -> None:
  """Writes a class-coloured PLY of a map (the dict of `read_map`, or GT voxel labels).

  Args:
    path: `.ply` destination.
    voxels: dict with `coords (N, 3)` and `labels (N,)`.
    voxel_size: voxel edge in metres.
    colors: `(K, 3) uint8` colour per class (default: a tab20 palette).
    mode: "cubes" (a coloured cube mesh per voxel) or "points" (one coloured vertex per voxel
      centre).
    labels: optional labels overriding `voxels["labels"]`.
  """
  import trimesh
  coords = np.asarray(voxels["coords"], np.float64)
  labels = np.asarray(voxels["labels"] if labels is None else labels, np.int64)
  if colors is None:
    colors = default_palette(int(labels.max(initial=0)) + 1)
  colors = np.asarray(colors, np.uint8)
  if np.any(labels >= len(colors)) or np.any(labels < 0):
    raise ValueError(f"labels must index the {len(colors)} colours")
  rgba = np.concatenate([colors[labels], np.full((len(labels), 1), 255, np.uint8)], axis=1)
  centers = (coords + 0.5) * voxel_size
  if mode == "points":
    geometry = trimesh.PointCloud(centers, colors=rgba)
  elif mode == "cubes":
    box = trimesh.creation.box(extents=(voxel_size,) * 3)
    n = len(centers)
    vertices = (centers[:, None, :] + box.vertices[None]).reshape(-1, 3)
    faces = (box.faces[None] + (np.arange(n) * len(box.vertices))[:, None, None]).reshape(-1, 3)
    geometry = trimesh.Trimesh(vertices, faces,
                               vertex_colors=np.repeat(rgba, len(box.vertices), axis=0),
                               process=False)
  else:
    raise ValueError(f"mode must be 'cubes' or 'points'; got {mode!r}")

  def write(tmp):
    geometry.export(tmp, file_type="ply")

  atomic_write(path, write)
