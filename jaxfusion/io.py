"""Maps on disk: bit-exact save/load (`.npz` with metadata) and class-coloured PLY export.

Writes go to a temporary file that is renamed into place, so an interrupted run never leaves a
half-written file behind. Reads go through `read_npz`, which reads every array eagerly, checks
each one's zip CRC and turns any way a file can be broken (empty, truncated, a flipped byte,
another kind of file, pickled objects) into one `BadFileError` that names the file.
"""

import dataclasses
import hashlib
import io as _bytes_io
import json
import os
import struct
import tempfile
import zipfile
import zlib
from typing import Iterable, Optional, Sequence

import jax.numpy as jnp
import numpy as np

from jaxfusion import rules as rules_lib
from jaxfusion.state import MapState

FORMAT_VERSION = 1


class BadFileError(ValueError):
  """A file exists but is corrupt or holds the wrong kind of data (the message names it)."""


# What reading a damaged archive can raise besides OSError/ValueError: zip and zlib errors,
# numpy's header parser (SyntaxError, struct), and absurd sizes from a flipped length byte.
_READ_ERRORS = (OSError, ValueError, KeyError, EOFError, IndexError, TypeError, AttributeError,
                NotImplementedError, SyntaxError, OverflowError, MemoryError, struct.error,
                zipfile.BadZipFile, zlib.error)


def _npz_problem(path: str, error: BaseException) -> str:
  """A short reason why `path` could not be read as an `.npz` archive."""
  try:
    with open(path, "rb") as f:
      head = f.read(8)
  except OSError:
    head = b""
  if not head:
    return "empty file"
  if head.startswith(b"\x93NUMPY"):
    return "a .npy array, not an .npz archive"
  if isinstance(error, zipfile.BadZipFile) and not head.startswith(b"PK"):
    return f"not an .npz archive: it starts with {head[:4]!r}"
  if isinstance(error, (zipfile.BadZipFile, zlib.error, EOFError)):
    return f"truncated or damaged: {error}"
  return f"{type(error).__name__}: {error}"


def read_npz(path: str, *, what: str, required: Iterable[str] = ()) -> dict:
  """Reads every array of an `.npz` archive eagerly, with its CRC checked.

  Args:
    path: the file.
    what: what the file should be, for messages (e.g. "jaxfusion map file").
    required: names of arrays the file must hold.

  Returns:
    `{name: ndarray}` of all arrays in the file.

  Raises:
    FileNotFoundError: no file at `path`.
    BadFileError: the file is empty, truncated, damaged, not an `.npz`, holds pickled
      objects or lacks a required array; the message is "PATH is not a WHAT (reason)".
  """
  path = os.fspath(path)
  if not os.path.isfile(path):
    raise FileNotFoundError(f"no {what} at {path}")
  arrays = {}
  try:
    with zipfile.ZipFile(path) as zf:
      for name in zf.namelist():
        if not name.endswith(".npy"):
          raise BadFileError(f"{name!r} is not an array")
        # zf.read checks the member's CRC-32: a flipped byte never reads back as data.
        buffer = _bytes_io.BytesIO(zf.read(name))
        arrays[name[:-4]] = np.lib.format.read_array(buffer, allow_pickle=False)
  except _READ_ERRORS as e:
    raise BadFileError(f"{path} is not a {what} ({_npz_problem(path, e)})") from e
  missing = [k for k in required if k not in arrays]
  if missing:
    raise BadFileError(f"{path} is not a {what} (it lacks {missing}; it holds "
                       f"{sorted(arrays)[:8]})")
  return arrays


def check_array(path: str, what: str, name: str, array: np.ndarray, shape, dtype) -> None:
  """Refuses an array read from `path` whose shape or dtype is not the expected one.

  Args:
    path, what: for the message, as in `read_npz`.
    name: the array's name in the file.
    array: the array.
    shape: expected shape; None entries match any size.
    dtype: expected dtype.

  Raises:
    BadFileError: "PATH is not a WHAT ('NAME' is SHAPE DTYPE, expected SHAPE DTYPE)".
  """
  ok = array.dtype == np.dtype(dtype) and array.ndim == len(shape) and all(
      want is None or int(want) == got for want, got in zip(shape, array.shape))
  if not ok:
    want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
    raise BadFileError(f"{path} is not a {what} ({name!r} is {array.shape} {array.dtype}, "
                       f"expected {want} {np.dtype(dtype)})")


def read_json_array(path: str, what: str, array: np.ndarray) -> dict:
  """The JSON object stored as `uint8` bytes in an `.npz` (a map's `metadata`, a cache's meta)."""
  try:
    value = json.loads(bytes(np.asarray(array, np.uint8)).decode())
  except (ValueError, TypeError) as e:
    raise BadFileError(f"{path} is not a {what} (its metadata is not JSON: {e})") from e
  if not isinstance(value, dict):
    raise BadFileError(f"{path} is not a {what} (its metadata is not a JSON object)")
  return value


def array_digest(arrays: dict) -> str:
  """SHA-256 (hex) of named arrays: names, dtypes, shapes and bytes, in name order."""
  h = hashlib.sha256()
  for name in sorted(arrays):
    a = np.ascontiguousarray(arrays[name])
    h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
    h.update(a.tobytes())
  return h.hexdigest()


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


def save_npz(path: str, arrays: dict) -> None:
  """Writes `arrays` as an uncompressed `.npz` at `path`, atomically (`atomic_write`)."""
  def write(tmp):
    with open(tmp, "wb") as f:
      np.savez(f, **arrays)
  atomic_write(path, write)


def rule_metadata(rule: rules_lib.FusionRule) -> dict:
  """JSON-able description of a rule: its name, aggregation, hyperparameter values (scalars
  as numbers, per-class values and tables as nested lists) and, for a rule that reads per-pixel
  context (the learned rule, GLFS), the context's names."""
  def plain(v):
    a = np.asarray(v, np.float64)
    return float(a) if a.ndim == 0 else a.tolist()
  meta = {"name": rule.name, "aggregate": rule.aggregate,
          "hparams": {k: plain(v) for k, v in rule.hparams.items()}}
  if rule.context:
    meta["context"] = list(rule.context)
  return meta


def rule_from_metadata(meta: dict) -> rules_lib.FusionRule:
  """The rule `rule_metadata` describes: a paper rule, the learned rule, GLFS or a member of
  the rule family."""
  hparams = {k: (np.asarray(v, np.float32) if isinstance(v, list) else v)
             for k, v in meta["hparams"].items()}
  if meta["name"] == "learned":
    return rules_lib.learned(hparams, context=tuple(meta.get("context", ())),
                             aggregate=meta["aggregate"])
  if meta["name"] == "glfs":
    return rules_lib.glfs(**hparams, aggregate=meta["aggregate"])
  if meta["name"] == "family":     # its weights read the first F context names (§3.11)
    width = next((np.shape(hparams[n])[-1] for n in ("context_weights", "context_theta")
                  if n in hparams), 0)
    return rules_lib.family(hparams, context=tuple(meta.get("context", ()))[:width],
                            aggregate=meta["aggregate"])
  return rules_lib.by_name(meta["name"], aggregate=meta["aggregate"], **hparams)


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
  if state.geometry is not None:
    meta["geometry"] = dataclasses.asdict(state.geometry.config())
    for name in GEOMETRY_ARRAYS:
      arrays[f"geometry/{name}"] = np.asarray(getattr(state.geometry, name))
  if state.free_space is not None:
    meta["free_space"] = dataclasses.asdict(state.free_space.config)
    arrays["free_space/log_odds"] = np.asarray(state.free_space.log_odds)
  if poses is not None:
    arrays["poses"] = poses
  arrays["metadata"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)

  def write(tmp):
    with open(tmp, "wb") as f:
      np.savez_compressed(f, **arrays)

  atomic_write(path, write)


MAP_FILE = "jaxfusion map file"
# The geometry layer's arrays in a map file (as `geometry/NAME`); its settings are in the
# metadata's "geometry" entry (a TSDFConfig as a dict).
GEOMETRY_ARRAYS = ("block_keys", "claims", "sdf", "weight", "num_blocks", "num_dropped")


def load_map(path: str) -> tuple[MapState, rules_lib.FusionRule, dict]:
  """Loads a map saved by `save_map`: `(state, rule, metadata)`, bit-exact.

  Raises:
    FileNotFoundError: no file at `path`.
    BadFileError: (a `ValueError`) the file is damaged, is not a map, or holds arrays whose
      shapes or dtypes disagree with its metadata; the message names the file.
  """
  if not os.path.exists(path):
    raise FileNotFoundError(f"no map file at {path}")
  data = read_npz(path, what=MAP_FILE, required=("metadata", "voxel_size"))
  meta = read_json_array(path, MAP_FILE, data["metadata"])
  if meta.get("format_version") != FORMAT_VERSION:
    raise BadFileError(f"{path}: unsupported map format version {meta.get('format_version')}")
  check_array(path, MAP_FILE, "voxel_size", data["voxel_size"], (), np.float32)
  from jaxfusion.state import init_map   # deferred: keeps io importable on its own
  from jaxfusion import tsdf as tsdf_lib
  try:
    rule = rule_from_metadata(meta["rule"])
    geometry = meta.get("geometry")
    if geometry is not None:
      geometry = tsdf_lib.TSDFConfig(**geometry)
    free = meta.get("free_space")
    if free is not None:
      from jaxfusion import free_space as free_space_lib
      free = free_space_lib.FreeSpaceConfig(**free)
    state = init_map(capacity=int(meta["capacity"]), num_classes=int(meta["num_classes"]),
                     voxel_size=float(data["voxel_size"]), rule=rule,
                     max_probes=int(meta["max_probes"]), geometry=geometry,
                     free_space=free if free is not None else False)
    names = meta.get("class_names")
    if names is not None and len(names) != state.num_classes:
      raise ValueError(f"{len(names)} class names for {state.num_classes} classes")
  except (KeyError, TypeError, ValueError, AttributeError) as e:
    raise BadFileError(f"{path} is not a {MAP_FILE} (bad metadata: {type(e).__name__}: {e})"
                       ) from e
  fields = ("keys", "hits", "claims", "num_occupied", "num_dropped")
  expected = {name: np.asarray(getattr(state, name)) for name in fields}
  expected.update({f"rows/{name}": np.asarray(v) for name, v in state.rows.items()})
  if state.geometry is not None:
    expected.update({f"geometry/{name}": np.asarray(getattr(state.geometry, name))
                     for name in GEOMETRY_ARRAYS})
  if state.free_space is not None:
    expected["free_space/log_odds"] = np.asarray(state.free_space.log_odds)
  stored_rows = {k for k in data if k.startswith("rows/")}
  if stored_rows != {k for k in expected if k.startswith("rows/")}:
    raise BadFileError(f"{path} is not a {MAP_FILE} (rows {sorted(stored_rows)} do not match "
                       f"rule {rule.name!r})")
  for name, template in expected.items():
    if name not in data:
      raise BadFileError(f"{path} is not a {MAP_FILE} (it lacks {name!r})")
    check_array(path, MAP_FILE, name, data[name], template.shape, template.dtype)
  rows = {name: jnp.asarray(data[f"rows/{name}"]) for name in state.rows}
  state = state.replace(
      keys=jnp.asarray(data["keys"]), hits=jnp.asarray(data["hits"]), rows=rows,
      claims=jnp.asarray(data["claims"]),
      num_occupied=jnp.asarray(data["num_occupied"]),
      num_dropped=jnp.asarray(data["num_dropped"]),
      voxel_size=jnp.asarray(data["voxel_size"]))
  if state.geometry is not None:
    state = state.replace(geometry=state.geometry.replace(
        **{name: jnp.asarray(data[f"geometry/{name}"]) for name in GEOMETRY_ARRAYS}))
  if state.free_space is not None:
    state = state.replace(free_space=state.free_space.replace(
        log_odds=jnp.asarray(data["free_space/log_odds"])))
  return state, rule, meta


def load_trajectory(path: str) -> Optional[dict]:
  """The camera trajectory saved with a map, or None for a map saved without poses.

  Maps written before poses were saved load as None.

  Returns:
    dict with `T_world_cam (T, 4, 4) float32` camera-to-world poses and `camera`: a dict of
    `fx, fy, cx, cy, height, width`, or None when the intrinsics were not saved.

  Raises:
    FileNotFoundError / BadFileError: as `load_map`; also for poses that are not `(T, 4, 4)`
      finite float32 or a camera that is not a dict of numbers.
  """
  if not os.path.exists(path):
    raise FileNotFoundError(f"no map file at {path}")
  data = read_npz(path, what=MAP_FILE, required=("metadata",))
  meta = read_json_array(path, MAP_FILE, data["metadata"])
  if "poses" not in data:
    return None
  poses = data["poses"]
  check_array(path, MAP_FILE, "poses", poses, (None, 4, 4), np.float32)
  if len(poses) == 0 or not np.all(np.isfinite(poses)):
    raise BadFileError(f"{path} is not a {MAP_FILE} (its poses are empty or not finite)")
  camera = meta.get("camera")
  keys = ("fx", "fy", "cx", "cy", "height", "width")
  if camera is not None and not (isinstance(camera, dict) and all(
      isinstance(camera.get(k), (int, float)) for k in keys)):
    raise BadFileError(f"{path} is not a {MAP_FILE} (its camera is not {list(keys)})")
  return {"T_world_cam": poses, "camera": camera}


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


MESH_FORMATS = ("ply", "obj", "glb")
MESH_COLORINGS = ("class", "confidence", "entropy")
# Colour of vertices with no semantic voxel (label −1).
UNLABELLED_RGB = (160, 160, 160)


def mesh_colors(mesh, *, color_by: str = "class", colors: Optional[np.ndarray] = None,
                num_classes: Optional[int] = None) -> np.ndarray:
  """`(P, 4) uint8` RGBA per vertex of a `mesh.Mesh`: its class in the palette, or its
  confidence (viridis over [0, 1]) or entropy (viridis over [0, log K]); grey where the vertex
  has no semantic voxel (label −1) or the mesh has no labels."""
  import matplotlib
  if color_by not in MESH_COLORINGS:
    raise ValueError(f"color_by must be one of {MESH_COLORINGS}; got {color_by!r}")
  n = mesh.num_vertices
  rgba = np.empty((n, 4), np.uint8)
  rgba[:, :3] = UNLABELLED_RGB
  rgba[:, 3] = 255
  if mesh.labels is None:
    return rgba
  labelled = mesh.labels >= 0
  if color_by == "class":
    k = num_classes if num_classes is not None else int(mesh.labels.max(initial=0)) + 1
    palette = np.asarray(default_palette(k) if colors is None else colors, np.uint8)
    if np.any(mesh.labels >= len(palette)):
      raise ValueError(f"labels must index the {len(palette)} colours")
    rgba[labelled, :3] = palette[mesh.labels[labelled]]
    return rgba
  if color_by == "confidence":
    value = mesh.confidence
  else:
    k = num_classes if num_classes is not None else int(mesh.labels.max(initial=0)) + 1
    value = mesh.entropy / np.log(max(k, 2))
  cmap = matplotlib.colormaps["viridis"]
  rgba[labelled, :3] = (np.asarray(cmap(np.clip(value[labelled], 0.0, 1.0)))[:, :3]
                        * 255).astype(np.uint8)
  return rgba


def save_mesh(path: str, mesh, *, color_by: str = "class", colors: Optional[np.ndarray] = None,
              num_classes: Optional[int] = None) -> None:
  """Writes a `mesh.Mesh` as PLY, OBJ or GLB (by the file's extension, through trimesh), its
  vertices coloured by class, confidence or entropy (`mesh_colors`). PLY also keeps each
  vertex's label, confidence and entropy as vertex properties."""
  import trimesh
  fmt = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
  if fmt not in MESH_FORMATS:
    raise ValueError(f"mesh files must end in one of {['.' + f for f in MESH_FORMATS]}; got "
                     f"{os.fspath(path)!r}")
  rgba = mesh_colors(mesh, color_by=color_by, colors=colors, num_classes=num_classes)
  geometry = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64),
                             np.asarray(mesh.faces, np.int64), vertex_colors=rgba,
                             vertex_normals=np.asarray(mesh.normals, np.float64), process=False)
  if fmt == "ply" and mesh.labels is not None:
    geometry.vertex_attributes["label"] = np.asarray(mesh.labels, np.int32)
    geometry.vertex_attributes["confidence"] = np.asarray(mesh.confidence, np.float32)
    geometry.vertex_attributes["entropy"] = np.asarray(mesh.entropy, np.float32)

  def write(tmp):
    kwargs = {"include_attributes": True} if fmt == "ply" else {}
    data = geometry.export(file_type=fmt, **kwargs)
    with open(tmp, "wb") as f:
      f.write(data if isinstance(data, bytes) else data.encode())

  atomic_write(path, write)
