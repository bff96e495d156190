"""Writing a sequence in the layouts of real datasets: ScanNet (SensReader) and TUM RGB-D.

An embedded sequence written this way runs through the very readers of the real data
(`load_scannet`, `load_tum`), so the real-data path can be exercised end to end.

ScanNet, as ScanNet's SensReader (`reader.py --export_*`) and its 2D label archives lay a scene
out (frames named `0, 1, …` without padding):

```
color/<i>.jpg                   colour at `color_size` (default 1296×968), JPEG quality 95
depth/<i>.png                   uint16 millimetres at the sequence's resolution (0 = invalid)
pose/<i>.txt                    4×4 camera-to-world, four rows of space-separated numbers
intrinsic/intrinsic_depth.txt   4×4 depth intrinsics      intrinsic/extrinsic_depth.txt  identity
intrinsic/intrinsic_color.txt   4×4 colour intrinsics     intrinsic/extrinsic_color.txt  identity
label-filt/<i>.png              uint16 NYU40 ids at colour resolution (0 = unannotated)
<scene>_vh_clean_2.labels.ply   optional labelled GT mesh (`plyfile.write_labelled_mesh`)
```

TUM RGB-D, as the benchmark's folders (and `associate.py`'s output) lay a sequence out:

```
rgb/<t>.png, depth/<t>.png      colour; uint16 depth at 5000 units per metre (0 = invalid)
rgb.txt, depth.txt              "timestamp file" per frame, after '#' header lines
groundtruth.txt                 "timestamp tx ty tz qx qy qz qw" (camera-to-world)
associations.txt                "t_rgb rgb/<t>.png t_depth depth/<t>.png" per frame
calibration.txt                 "fx fy cx cy": jaxfusion's own addition, read by `load_tum`
```
Colour, depth and pose carry slightly different timestamps, as a real recording's do, so that
the readers' association by time is exercised.

Both writers refuse a non-empty folder that is not already such an export (`check_target`) unless
`overwrite=True`; every file goes through `io.atomic_write`, and frames left over from an
earlier, longer export are removed.

`embedded_labelled_mesh` builds the labelled GT mesh of an embedded room, for ScanNet's layout.

Shape legend: T frames, H×W depth pixels, V vertices, F triangles, P primitives.
"""

import math
import os
import re

import numpy as np

from jaxfusion import io
from jaxfusion.camera import Camera
from jaxfusion.datasets import classes, plyfile, synthetic
from jaxfusion.datasets.primitives import BOX, CYLINDER, PLANE, SPHERE, Primitives
from jaxfusion.datasets.sequence import RGBDSequence

LAYOUTS = ("scannet", "tum")
SCANNET_DEPTH_SCALE = 1000.0
TUM_DEPTH_SCALE = 5000.0
SCANNET_COLOR_SIZE = (968, 1296)
LABELS_PLY_SUFFIX = "_vh_clean_2.labels.ply"
# Offsets of the TUM depth images and poses from the colour images, in seconds at 30 Hz
# (scaled down for faster rates): well inside `load_tum`'s 0.02 s association tolerance, and
# well under half a frame interval, so every frame is matched with its own images and pose.
TUM_DEPTH_OFFSET = 0.005
TUM_POSE_OFFSET = -0.003
# Default spacing of the labelled mesh's vertices on large faces, in metres.
MESH_SPACING = 0.05

_SCANNET_FRAMES = {"color": ".jpg", "depth": ".png", "pose": ".txt", "label-filt": ".png"}
_SCANNET_INTRINSICS = ("intrinsic_depth.txt", "intrinsic_color.txt", "extrinsic_depth.txt",
                       "extrinsic_color.txt")
_TUM_LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt", "associations.txt", "calibration.txt")
_TUM_IMAGE = re.compile(r"^\d+\.\d+\.png$")


# --- Folders ------------------------------------------------------------------------------------

def _owned(layout: str, name: str) -> bool:
  """Whether a top-level entry of a folder is one that `layout`'s writer makes."""
  if name.startswith(".tmp-"):   # left by an interrupted `io.atomic_write`
    return True
  if layout == "scannet":
    return name in _SCANNET_FRAMES or name == "intrinsic" or name.endswith(LABELS_PLY_SUFFIX)
  return name in ("rgb", "depth") + _TUM_LISTS


def check_target(path: str, layout: str, *, overwrite: bool = False) -> None:
  """Checks that a sequence can be written to `path` in `layout` ("scannet" or "tum").

  A folder that does not exist, an empty one, or one that holds only what the layout's writer
  writes (an earlier export) is fine; any other folder needs `overwrite=True`.

  Raises:
    ValueError: `path` is a file, or a non-empty folder that is not such an export.
  """
  if layout not in LAYOUTS:
    raise ValueError(f"layout must be one of {LAYOUTS}; got {layout!r}")
  if os.path.exists(path) and not os.path.isdir(path):
    raise ValueError(f"{path} is a file, not a folder to write a {layout} export to")
  if overwrite or not os.path.isdir(path):
    return
  foreign = sorted(n for n in os.listdir(path) if not _owned(layout, n))
  if foreign:
    raise ValueError(f"{path} is not empty and not a {layout} export (it holds {foreign[0]!r}); "
                     "pass overwrite=True (--overwrite) to write into it")


def _clear_stale(path: str, layout: str) -> None:
  """Removes the frames, labels and meshes of an earlier export from `path`."""
  if not os.path.isdir(path):
    return
  if layout == "scannet":
    for sub, ext in _SCANNET_FRAMES.items():
      folder = os.path.join(path, sub)
      if os.path.isdir(folder):
        for name in os.listdir(folder):
          stem, e = os.path.splitext(name)
          if e == ext and stem.isdigit():
            os.remove(os.path.join(folder, name))
    for name in os.listdir(path):
      if name.endswith(LABELS_PLY_SUFFIX) and os.path.isfile(os.path.join(path, name)):
        os.remove(os.path.join(path, name))
    for name in _SCANNET_INTRINSICS:   # rewritten last: a rewrite that breaks off lacks them
      if os.path.isfile(os.path.join(path, "intrinsic", name)):
        os.remove(os.path.join(path, "intrinsic", name))
  else:
    for sub in ("rgb", "depth"):
      folder = os.path.join(path, sub)
      if os.path.isdir(folder):
        for name in os.listdir(folder):
          if _TUM_IMAGE.match(name):
            os.remove(os.path.join(folder, name))
    for name in _TUM_LISTS:   # rewritten last: a rewrite that breaks off lacks them
      if os.path.isfile(os.path.join(path, name)):
        os.remove(os.path.join(path, name))


def _write_bytes(path: str, data: bytes) -> None:
  def write(tmp):
    with open(tmp, "wb") as f:
      f.write(data)
  io.atomic_write(path, write)


def _write_text(path: str, lines) -> None:
  _write_bytes(path, "".join(line + "\n" for line in lines).encode("utf-8"))


def _encode(ext: str, image: np.ndarray, params=()) -> bytes:
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where used)
  ok, buf = cv2.imencode(ext, image, list(params))
  if not ok:
    raise ValueError(f"could not encode a {image.shape} {image.dtype} image as {ext}")
  return buf.tobytes()


def _number(x, dtype=np.float64) -> str:
  """Fixed-point text of `x` with at least 6 decimals (SensReader's `%f`) and as many more as
  the value needs to read back exactly in `dtype`."""
  return np.format_float_positional(dtype(x), unique=True, min_digits=6)


def _matrix_lines(m: np.ndarray, dtype=np.float64) -> list:
  return [" ".join(_number(v, dtype) for v in row) for row in np.asarray(m)]


def _depth_png(depth: np.ndarray, scale: float) -> np.ndarray:
  """`(H, W) uint16` depth image: `round(depth · scale)`, clipped to 65535; 0 where the
  depth is 0, negative or not finite."""
  d = np.asarray(depth, np.float64)
  ok = np.isfinite(d) & (d > 0)
  return np.where(ok, np.clip(np.round(np.where(ok, d, 0.0) * scale), 0, 65535), 0
                  ).astype(np.uint16)


def _intrinsics_4x4(camera: Camera) -> np.ndarray:
  K = np.eye(4)
  K[:3, :3] = camera.matrix()
  return K


def nyu40_ids(class_names) -> np.ndarray:
  """The NYU40 id written for each class of a label space, for ScanNet's label images.

  For the embedded world's classes this is `classes.EMBEDDED_TO_NYU40`; for the other label
  spaces of `classes.LABEL_SPACES` it is the smallest NYU40 id that reads back as the class,
  so that `load_scannet(..., label_space=...)` returns the same labels.

  Args:
    class_names: the sequence's K class names.

  Returns:
    `(K,) int32` NYU40 ids.

  Raises:
    ValueError: the classes are not those of a label space.
  """
  names = tuple(class_names)
  if names == tuple(classes.CLASS_NAMES):
    return np.asarray(classes.EMBEDDED_TO_NYU40, np.int32)
  for space_names, lut in classes.LABEL_SPACES.values():
    if names == tuple(space_names):
      return np.array([np.flatnonzero(lut == k)[0] for k in range(len(names))], np.int32)
  raise ValueError(f"the sequence's classes {names[:3]}... are not those of a label space "
                   f"({', '.join(classes.LABEL_SPACES)}): its labels have no NYU40 ids")


def resized_camera(camera: Camera, size, new_size) -> Camera:
  """The intrinsics of the same camera with the image resized from `size` to `new_size`
  (each `(H, W)`), pixel centres at integer coordinates as in `surfaces.upsampled_camera`:
  `f' = f·s`, `c' = (c + 0.5)·s − 0.5`."""
  sy, sx = new_size[0] / size[0], new_size[1] / size[1]
  return Camera(camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5,
                (camera.cy + 0.5) * sy - 0.5)


# --- ScanNet ------------------------------------------------------------------------------------

def save_scannet(sequence: RGBDSequence, path: str, *, color_size=SCANNET_COLOR_SIZE,
                 labelled_mesh=None, scene_name=None, overwrite: bool = False) -> str:
  """Writes a sequence in the layout of a ScanNet scene exported by SensReader.

  Colour is resized to `color_size` (bilinear) and stored as JPEG (quality 95); depth stays
  at the sequence's resolution, in millimetres. The label images hold NYU40 ids
  (`nyu40_ids`; `IGNORE_LABEL` → 0, unannotated) at colour resolution, upsampled by nearest
  pixel centre (`cv2.INTER_NEAREST_EXACT`), as ScanNet's 2D labels are rendered at colour
  resolution. The colour intrinsics are the depth ones rescaled (`resized_camera`), the
  extrinsics the identity (colour and depth come from the same camera).

  Read it back with `load_scannet(path, label_space="embedded")` for an embedded sequence.
  Its depth comes back rounded to the millimetre; its labels exactly at ScanNet's sizes (the
  reader resizes them back by pixel centre, `cv2.INTER_NEAREST_EXACT`); at a tiny size with a
  ratio near an integer, a pixel next to a label edge may take its neighbour's label.

  Args:
    sequence: the frames (`rgb (T, H, W, 3) uint8`, `depth (T, H, W) float32` metres,
      `T_world_cam (T, 4, 4)`, optional `labels (T, H, W) int32`).
    path: the scene folder (created if needed).
    color_size: `(H, W)` of the colour and label images; its aspect ratio must be the depth
      images' (within 5 %, as `load_scannet` checks).
    labelled_mesh: optional GT mesh, a dict with `vertices (V, 3)`, `faces (F, 3)`,
      `labels (V,)` NYU40 ids (and optionally `colors (V, 3|4) uint8`), e.g.
      `embedded_labelled_mesh(...)`; written as `<scene>_vh_clean_2.labels.ply`.
    scene_name: the `<scene>` of the mesh file (default: the folder's name).
    overwrite: write into a non-empty folder that is not a ScanNet export.

  Returns:
    The folder path.

  Raises:
    ValueError: a bad `color_size`, classes without NYU40 ids, or a target refused by
      `check_target`.
  """
  import cv2  # pylint: disable=import-outside-toplevel  (heavy: imported where used)
  check_target(path, "scannet", overwrite=overwrite)
  try:
    color_size = tuple(int(s) for s in color_size)
  except (TypeError, ValueError) as e:
    raise ValueError(f"color_size must be (H, W); got {color_size!r}") from e
  if len(color_size) != 2 or min(color_size) < 1:
    raise ValueError(f"color_size must be two positive sizes (H, W); got {color_size!r}")
  h, w = sequence.image_size
  if abs((color_size[1] / color_size[0]) / (w / h) - 1) > 0.05:
    raise ValueError(f"color_size {color_size[0]}x{color_size[1]} (HxW) does not have the "
                     f"aspect ratio of the {h}x{w} depth images; load_scannet would refuse it")
  lut = None
  if sequence.labels is not None:
    lut = nyu40_ids(sequence.class_names)
    labels = sequence.labels
    if np.any((labels < classes.IGNORE_LABEL) | (labels >= len(lut))):
      raise ValueError(f"labels must lie in [{classes.IGNORE_LABEL}, {len(lut)}) for "
                       f"{len(lut)} classes")
  if labelled_mesh is not None:
    plyfile.check_labelled_mesh(labelled_mesh)   # fail before writing anything
  scene_name = scene_name or os.path.basename(os.path.abspath(path))
  _clear_stale(path, "scannet")
  label_dir = os.path.join(path, "label-filt")
  if lut is None and os.path.isdir(label_dir) and not os.listdir(label_dir):
    os.rmdir(label_dir)  # an empty label folder would read as a scene whose labels are missing
  dsize = (color_size[1], color_size[0])
  for i, frame in enumerate(sequence):
    colour = cv2.resize(frame.rgb, dsize, interpolation=cv2.INTER_LINEAR)
    _write_bytes(os.path.join(path, "color", f"{i}.jpg"),
                 _encode(".jpg", colour[..., ::-1], (cv2.IMWRITE_JPEG_QUALITY, 95)))
    _write_bytes(os.path.join(path, "depth", f"{i}.png"),
                 _encode(".png", _depth_png(frame.depth, SCANNET_DEPTH_SCALE)))
    _write_text(os.path.join(path, "pose", f"{i}.txt"),
                _matrix_lines(frame.T_world_cam, np.float32))
    if lut is not None:
      nyu = np.where(frame.labels >= 0, lut[np.maximum(frame.labels, 0)], 0).astype(np.uint16)
      nyu = cv2.resize(nyu, dsize, interpolation=cv2.INTER_NEAREST_EXACT)
      _write_bytes(os.path.join(path, "label-filt", f"{i}.png"), _encode(".png", nyu))
  if labelled_mesh is not None:
    plyfile.write_labelled_mesh(os.path.join(path, scene_name + LABELS_PLY_SUFFIX),
                                labelled_mesh)
  color_camera = resized_camera(sequence.camera, (h, w), color_size)
  # The intrinsics last: an export that breaks off lacks them, and does not read as whole.
  for name, m in zip(_SCANNET_INTRINSICS, (_intrinsics_4x4(sequence.camera),
                                           _intrinsics_4x4(color_camera), np.eye(4), np.eye(4))):
    _write_text(os.path.join(path, "intrinsic", name), _matrix_lines(m))
  return path


# --- The labelled mesh of an embedded room ------------------------------------------------------

def _grid_faces(nu: int, nv: int) -> np.ndarray:
  """`(2·nu·nv, 3)` triangles of a `(nu + 1) × (nv + 1)` vertex grid (row-major over u),
  wound so that their normal is `∂u × ∂v`."""
  i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
  a = (i * (nv + 1) + j).ravel()
  b, c, d = a + nv + 1, a + nv + 2, a + 1
  return np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])


def _patch(u: np.ndarray, v: np.ndarray, f) -> tuple:
  """Vertices `f(U, V)` `((nu+1)·(nv+1), 3)` of a parametric grid and its triangles."""
  U, V = np.meshgrid(u, v, indexing="ij")
  return np.stack(f(U, V), -1).reshape(-1, 3), _grid_faces(len(u) - 1, len(v) - 1)


def _count(length: float, spacing, minimum: int = 1) -> int:
  if spacing is None:
    return minimum
  return max(minimum, int(math.ceil(length / spacing - 1e-9)))


def _circle(n: int) -> tuple:
  """`cos, sin` of `n + 1` angles around a circle, the last exactly the first."""
  t = 2 * np.pi * np.arange(n + 1) / n
  c, s = np.cos(t), np.sin(t)
  c[-1], s[-1] = c[0], s[0]
  return c, s


def _unit_patches(kind: int, half: np.ndarray, spacing, segments: int, plane_extent=None):
  """Patches `[(vertices, faces)]` of a primitive in its unit local shape."""
  if kind == BOX:
    counts = [_count(2 * half[a], spacing) for a in range(3)]
    patches = []
    for a in range(3):
      b, c = (a + 1) % 3, (a + 2) % 3
      for sign in (1.0, -1.0):
        ub, uc = np.linspace(-1, 1, counts[b] + 1), np.linspace(-1, 1, counts[c] + 1)

        def face(U, V, a=a, b=b, c=c, sign=sign):
          q = [None] * 3
          q[a], q[b], q[c] = np.full_like(U, sign), U, V
          return q

        if sign > 0:      # e_b × e_c = e_a: outward
          patches.append(_patch(ub, uc, face))
        else:
          patches.append(_patch(uc, ub, lambda U, V, face=face: face(V, U)))
    return patches
  if kind == CYLINDER:
    r = float(max(half[0], half[1]))
    n = _count(2 * np.pi * r, spacing, segments)
    cos, sin = _circle(n)
    theta = np.arange(n + 1)
    z = np.linspace(-1, 1, _count(2 * half[2], spacing) + 1)
    radii = np.linspace(0, 1, _count(r, spacing) + 1)
    side = _patch(theta, z, lambda T, Z: (cos[T], sin[T], Z))
    top = _patch(radii, theta, lambda R, T: (R * cos[T], R * sin[T], np.ones_like(R)))
    bottom = _patch(theta, radii, lambda T, R: (R * cos[T], R * sin[T], -np.ones_like(R)))
    return [side, top, bottom]
  if kind == SPHERE:
    r = float(max(half))
    n = _count(2 * np.pi * r, spacing, segments)
    m = _count(np.pi * r, spacing, max(2, segments // 2))
    cos, sin = _circle(n)
    phi = np.pi * np.arange(m + 1) / m
    cphi, sphi = np.cos(phi), np.sin(phi)
    cphi[0], cphi[-1], sphi[0], sphi[-1] = 1.0, -1.0, 0.0, 0.0
    return [_patch(np.arange(m + 1), np.arange(n + 1),
                   lambda P, T: (sphi[P] * cos[T], sphi[P] * sin[T], cphi[P]))]
  if kind == PLANE:
    (x0, x1), (y0, y1), facing = plane_extent
    u = np.linspace(x0, x1, _count((x1 - x0) * half[0], spacing) + 1)
    v = np.linspace(y0, y1, _count((y1 - y0) * half[1], spacing) + 1)
    vertices, faces = _patch(u, v, lambda U, V: (U, V, np.zeros_like(U)))
    return [(vertices, faces if facing >= 0 else faces[:, ::-1])]
  raise ValueError(f"unknown primitive kind {kind}")


def _merge(patches) -> tuple:
  """One mesh of a primitive's patches: shared seam vertices merged, degenerate triangles
  (at a cap's centre, a sphere's poles) dropped."""
  vertices = np.concatenate([v for v, _ in patches])
  offsets = np.cumsum([0] + [len(v) for v, _ in patches[:-1]])
  faces = np.concatenate([f + o for (_, f), o in zip(patches, offsets)])
  unique, inverse = np.unique(np.round(vertices, 9) + 0.0, axis=0, return_inverse=True)
  faces = inverse.reshape(-1)[faces]
  keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
  return unique, faces[keep]


def primitives_mesh(primitives: Primitives, *, bounds=None, spacing=None,
                    segments: int = 16) -> dict:
  """A triangle mesh of the surfaces of a primitive table.

  Boxes give their six faces, cylinders their side and two caps, spheres (ellipsoids) a
  latitude-longitude mesh; every vertex lies on its primitive's surface. An (infinite) plane
  gives the rectangle that spans `bounds` in its own frame, facing the middle of `bounds`:
  exactly the face of `bounds` for the walls, floor and ceiling of a room. Each primitive is a
  closed mesh of its own (vertices are not shared between primitives), wound outwards.

  Args:
    primitives: the table (P rows).
    bounds: `(2, 3)` lower and upper corner of the box the planes are cut to (needed when
      the table has planes).
    spacing: the longest edge along a face, in metres (faces are split into grids); None:
      the fewest triangles (a box: 8 vertices, 12 triangles; a cylinder: `2·segments + 2`
      vertices, `4·segments` triangles).
    segments: the fewest segments around a cylinder or sphere.

  Returns:
    dict with `vertices (V, 3) float64` (in the primitives' frame), `faces (F, 3) int32`,
    `labels (V,) int32` (the primitive's class) and `primitive (V,) int32` (its row).
  """
  if segments < 3:
    raise ValueError(f"segments must be ≥ 3; got {segments}")
  if spacing is not None and not spacing > 0:
    raise ValueError(f"spacing must be > 0 (or None); got {spacing}")
  kinds = np.asarray(primitives.kind)
  if np.any(kinds == PLANE):
    if bounds is None:
      raise ValueError("the primitives include planes: pass bounds=(lower, upper) to cut them")
    bounds = np.asarray(bounds, np.float64)
    if bounds.shape != (2, 3) or not np.all(bounds[1] > bounds[0]):
      raise ValueError(f"bounds must be (2, 3) lower and upper corners; got {bounds.tolist()}")
    corners = np.array(np.meshgrid(*bounds.T, indexing="ij")).reshape(3, -1).T
  vertices, faces, labels, rows = [], [], [], []
  count = 0
  for p in range(len(primitives)):
    centre = np.asarray(primitives.center[p], np.float64)
    rotation = np.asarray(primitives.rotation[p], np.float64)
    half = np.asarray(primitives.half_size[p], np.float64)
    extent = None
    if kinds[p] == PLANE:
      local = (corners - centre) @ rotation / half
      middle = (bounds.mean(0) - centre) @ rotation
      extent = ((local[:, 0].min(), local[:, 0].max()), (local[:, 1].min(), local[:, 1].max()),
                middle[2])
    v, f = _merge(_unit_patches(int(kinds[p]), half, spacing, segments, extent))
    vertices.append(centre + (v * half) @ rotation.T)
    faces.append(f + count)
    labels.append(np.full(len(v), primitives.label[p], np.int32))
    rows.append(np.full(len(v), p, np.int32))
    count += len(v)
  return {"vertices": np.concatenate(vertices), "faces": np.concatenate(faces).astype(np.int32),
          "labels": np.concatenate(labels), "primitive": np.concatenate(rows)}


def embedded_labelled_mesh(env: str, layout_seed: int, shift: float, *, domain: str = "test",
                           spacing=MESH_SPACING) -> dict:
  """The labelled GT mesh of an embedded room, in the world frame of its sequences.

  The primitives of `synthetic.make_scene(env, seed=layout_seed, domain=domain, shift=shift)`
  (whose proportions depend on the domain) as a mesh (`primitives_mesh`, the walls, floor
  and ceiling cut to the room), moved to where the room sits (`synthetic.placement(env,
  layout_seed)`, as the sequence poses are), each vertex labelled with the NYU40 id of its
  primitive's class (`classes.EMBEDDED_TO_NYU40`) and coloured with the class's colour.

  Args:
    env: "office" or "house".
    layout_seed: the sequence's layout seed.
    shift: the sequence's domain shift.
    domain: "train" or "test".
    spacing: the longest edge along a face in metres (None: the fewest triangles).

  Returns:
    dict with `vertices (V, 3) float64`, `faces (F, 3) int32`, `labels (V,) int32` NYU40 ids
    and `colors (V, 4) uint8`, for `save_scannet(labelled_mesh=...)`.
  """
  world = synthetic.make_scene(env, seed=layout_seed, domain=domain, shift=shift)
  bounds = np.stack([np.zeros(3), np.asarray(world.layout.room, np.float64)])
  mesh = primitives_mesh(world.primitives, bounds=bounds, spacing=spacing)
  T = synthetic.placement(env, layout_seed)
  colors = np.full((len(mesh["labels"]), 4), 255, np.uint8)
  colors[:, :3] = classes.CLASS_COLORS[mesh["labels"]]
  return {"vertices": mesh["vertices"] @ T[:3, :3].T + T[:3, 3], "faces": mesh["faces"],
          "labels": classes.EMBEDDED_TO_NYU40[mesh["labels"]].astype(np.int32),
          "colors": colors}


# --- TUM RGB-D ----------------------------------------------------------------------------------

def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
  """Unit quaternions `(qx, qy, qz, qw)` of rotation matrices, with `qw ≥ 0`.

  Robust for every rotation (Shepperd's method: the largest of the four diagonal
  combinations sets the divisor, so rotations by about 180° lose no precision). The input is
  first made exactly orthonormal (nearest rotation, by SVD), as float32 poses are not.

  Args:
    R: `(..., 3, 3)` rotation matrices.

  Returns:
    `(..., 4) float64`, the inverse of `tum.quat_to_pose`.

  Raises:
    ValueError: a matrix is not finite or is a reflection.
  """
  R = np.asarray(R, np.float64)
  if R.shape[-2:] != (3, 3) or not np.all(np.isfinite(R)):
    raise ValueError(f"rotations must be finite (..., 3, 3) matrices; got shape {R.shape}")
  U, _, Vt = np.linalg.svd(R)
  R = U @ Vt
  if np.any(np.linalg.det(R) < 0):
    raise ValueError("a matrix is a reflection (determinant < 0), not a rotation")
  m = lambda i, j: R[..., i, j]
  diag = np.stack([m(0, 0) + m(1, 1) + m(2, 2), m(0, 0), m(1, 1), m(2, 2)], -1)
  case = np.argmax(diag, axis=-1)
  s = 2.0 * np.sqrt(np.maximum(1.0 + np.stack([
      diag[..., 0], m(0, 0) - m(1, 1) - m(2, 2), m(1, 1) - m(0, 0) - m(2, 2),
      m(2, 2) - m(0, 0) - m(1, 1)], -1), 1e-30))
  s = np.take_along_axis(s, case[..., None], -1)[..., 0]
  wx, wy, wz = m(2, 1) - m(1, 2), m(0, 2) - m(2, 0), m(1, 0) - m(0, 1)
  xy, xz, yz = m(0, 1) + m(1, 0), m(0, 2) + m(2, 0), m(1, 2) + m(2, 1)
  q = np.select([(case == k)[..., None] for k in range(4)], [
      np.stack([wx / s, wy / s, wz / s, s / 4], -1),
      np.stack([s / 4, xy / s, xz / s, wx / s], -1),
      np.stack([xy / s, s / 4, yz / s, wy / s], -1),
      np.stack([xz / s, yz / s, s / 4, wz / s], -1)])
  q = q / np.linalg.norm(q, axis=-1, keepdims=True)
  return np.where(q[..., 3:] < 0, -q, q)


def save_tum(sequence: RGBDSequence, path: str, *, start_time: float = 1305031102.0,
             rate_hz: float = 30.0, overwrite: bool = False) -> str:
  """Writes a sequence in the TUM RGB-D benchmark's layout.

  Frame i is taken at `start_time + i / rate_hz`: its colour image carries that timestamp,
  its depth image one `TUM_DEPTH_OFFSET` later and its pose one `TUM_POSE_OFFSET` off (both
  scaled down above 30 Hz), so that reading it back associates by time as for a real
  recording. Depth is stored at 5000 units per metre (clipped at 13.1 m).

  TUM folders carry no intrinsics, and the embedded camera is not the TUM default that
  `load_tum` assumes without one: the camera is written to `calibration.txt` ("fx fy cx cy",
  jaxfusion's own addition to the layout), which `load_tum(path)` reads; other readers need
  it passed in, e.g. `load_tum(path, camera=sequence.camera)`. Labels are not written (TUM
  has none).

  Args:
    sequence: the frames (`rgb (T, H, W, 3) uint8`, `depth (T, H, W) float32` metres,
      `T_world_cam (T, 4, 4)`).
    path: the sequence folder (created if needed).
    start_time: timestamp of the first frame, in seconds (TUM's are Unix times).
    rate_hz: frame rate, in (0, 1000].
    overwrite: write into a non-empty folder that is not a TUM export.

  Returns:
    The folder path.

  Raises:
    ValueError: a bad `start_time` or `rate_hz`, or a target refused by `check_target`.
  """
  check_target(path, "tum", overwrite=overwrite)
  if not (math.isfinite(start_time) and start_time >= 0):
    raise ValueError(f"start_time must be a finite time ≥ 0 in seconds; got {start_time}")
  if not (math.isfinite(rate_hz) and 0 < rate_hz <= 1000):
    raise ValueError(f"rate_hz must lie in (0, 1000]; got {rate_hz}")
  poses = np.asarray(sequence.T_world_cam, np.float64)
  if not np.all(np.isfinite(poses)):
    raise ValueError("the sequence's poses must be finite (groundtruth.txt holds every pose)")
  quats = rotation_to_quaternion(poses[:, :3, :3])
  scale = min(1.0, 30.0 / rate_hz)
  _clear_stale(path, "tum")
  bag = f"# file: '{' '.join(sequence.name.split())}' (written by jaxfusion)"
  rgb_lines = ["# color images", bag, "# timestamp filename"]
  depth_lines = ["# depth maps", bag, "# timestamp filename"]
  gt_lines = ["# ground truth trajectory", bag, "# timestamp tx ty tz qx qy qz qw"]
  associations = []
  for i, frame in enumerate(sequence):
    t = start_time + i / rate_hz
    t_rgb, t_depth = f"{t:.6f}", f"{t + TUM_DEPTH_OFFSET * scale:.6f}"
    rgb_file, depth_file = f"rgb/{t_rgb}.png", f"depth/{t_depth}.png"
    _write_bytes(os.path.join(path, rgb_file), _encode(".png", frame.rgb[..., ::-1]))
    _write_bytes(os.path.join(path, depth_file),
                 _encode(".png", _depth_png(frame.depth, TUM_DEPTH_SCALE)))
    rgb_lines.append(f"{t_rgb} {rgb_file}")
    depth_lines.append(f"{t_depth} {depth_file}")
    associations.append(f"{t_rgb} {rgb_file} {t_depth} {depth_file}")
    values = (*poses[i, :3, 3], *quats[i])
    gt_lines.append(f"{t + TUM_POSE_OFFSET * scale:.6f} " + " ".join(f"{v:.9f}" for v in values))
  c = sequence.camera
  _write_text(os.path.join(path, "calibration.txt"),
              [" ".join(repr(float(x)) for x in (c.fx, c.fy, c.cx, c.cy))])
  _write_text(os.path.join(path, "associations.txt"), associations)
  _write_text(os.path.join(path, "groundtruth.txt"), gt_lines)
  # The lists last: an export that breaks off lists no image that is not there.
  _write_text(os.path.join(path, "depth.txt"), depth_lines)
  _write_text(os.path.join(path, "rgb.txt"), rgb_lines)
  return path
