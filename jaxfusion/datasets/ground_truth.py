"""Ground-truth voxel labels: from label images, computed with the engine itself, or from a
labelled mesh (docs/equations.md §7.1–§7.3).

**Label images.** The GT label of a voxel is the majority of the GT pixel labels that fall
into it over the whole sequence (or over the frames its `info["gt_frames"]` names: those that
saw the final scene of a changing world, `changes`): every frame's GT labels are turned into
one-hot "probabilities" and fused with the voting rule `rules.sum_labels()`, so the voxel grid,
keys and back-projection are exactly those of the maps being evaluated. Ties go to the lowest class
index (argmax). Pixels with `IGNORE_LABEL` (or a label outside the class range) and pixels
without depth are not fused. `gt_from_frames` fuses a stream of frame chunks, so memory does
not grow with the sequence; `gt_voxel_labels` does it for a whole `RGBDSequence`, and `gt_part`
picks the frames (and true poses) a chunk read on its own adds to the GT, for streamed GT.

**Labelled mesh** (ScanNet's `*_vh_clean_2.labels.ply`, NYU40 ids per vertex). The faces are
sampled on an even deterministic grid; each sample takes the label of its face's nearest
vertex, read into a label space (`classes.LABEL_SPACES`); `gt_from_mesh` takes the majority per
voxel, `surface_from_mesh` thins the samples to the true surface of a mesh study.

Shape legend: N voxels, K classes, T frames (t in one chunk), H×W pixels, V vertices, F faces,
S samples, G surface points.
"""

from typing import Iterable, Mapping, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import fusion, mapper as mapper_lib, readout, rules, state as state_lib
from jaxfusion.datasets.classes import IGNORE_LABEL

# The first capacity of a growing GT map (`Mapper` doubles it before it could fill).
INITIAL_CAPACITY = 2**16
# One chunk of `gt_voxel_labels` holds at most this many one-hot values (64 MiB of float32).
CHUNK_VALUES = 2**24
# Mesh samples made at once: bounds the scratch memory of the mesh functions.
MESH_CHUNK = 2**20


def count_voxels(sequence, *, voxel_size: float) -> int:
  """Number of distinct voxels hit by the valid, labelled pixels of a sequence (NumPy)."""
  keys = []
  cam = sequence.camera
  h, w = sequence.image_size
  u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
  for frame in sequence:
    ok = frame.depth > 0
    if frame.labels is not None:
      ok &= (frame.labels >= 0) & (frame.labels < sequence.num_classes)
    d = frame.depth[ok].astype(np.float64)
    p_cam = np.stack([d * (u[ok] - cam.cx) / cam.fx, d * (v[ok] - cam.cy) / cam.fy, d],
                     -1)
    T = frame.T_world_cam.astype(np.float64)
    p_world = p_cam @ T[:3, :3].T + T[:3, 3]
    keys.append(np.unique(np.floor(p_world / voxel_size).astype(np.int64), axis=0))
  return len(np.unique(np.concatenate(keys), axis=0)) if keys else 0


def _field(chunk, name: str):
  value = chunk.get(name) if isinstance(chunk, Mapping) else getattr(chunk, name, None)
  return None if value is None else np.asarray(value)


def _chunk_arrays(chunk) -> tuple:
  """`(depth (t, H, W) float32, T_world_cam (t, 4, 4) float32, labels (t, H, W) int32)` of a
  chunk (or of one frame, given a time axis)."""
  depth, poses, labels = (_field(chunk, n) for n in ("depth", "T_world_cam", "labels"))
  if depth is None or poses is None:
    raise ValueError(f"a chunk needs depth and T_world_cam; got a {type(chunk).__name__}")
  if labels is None:
    raise ValueError("a chunk has no ground-truth labels")
  if depth.ndim == 2:                       # one frame (an `RGBDFrame`)
    depth, poses, labels = depth[None], poses[None], labels[None]
  if depth.ndim != 3 or labels.shape != depth.shape or poses.shape != (len(depth), 4, 4):
    raise ValueError(f"a chunk needs depth (t, H, W), T_world_cam (t, 4, 4) and labels "
                     f"(t, H, W); got {depth.shape}, {poses.shape} and {labels.shape}")
  if not np.issubdtype(labels.dtype, np.integer):
    raise ValueError(f"labels must be integers; got {labels.dtype}")
  return depth.astype(np.float32), poses.astype(np.float32), labels.astype(np.int32)


def _one_hot_frames(depth, T_world_cam, labels, num_classes: int) -> fusion.Frame:
  """The GT labels of a chunk as a `Frame` stack: one-hot probabilities, depth 0 where the
  label is outside `[0, num_classes)` (so the pixel is not fused)."""
  labels = jnp.asarray(labels, jnp.int32)
  ok = (labels >= 0) & (labels < num_classes)
  depth = jnp.where(ok, jnp.asarray(depth, jnp.float32), 0.0)
  probs = jax.nn.one_hot(jnp.where(ok, labels, 0), num_classes, dtype=jnp.float32)
  return fusion.Frame(depth, jnp.asarray(T_world_cam, jnp.float32), probs)


_one_hot_frames_jit = jax.jit(_one_hot_frames, static_argnames="num_classes")


def _pad(depth, T_world_cam, labels, length: int) -> tuple:
  """A chunk padded to `length` frames with frames of zero depth (they touch nothing)."""
  extra = length - len(depth)
  if extra <= 0:
    return depth, T_world_cam, labels
  eye = np.broadcast_to(np.eye(4, dtype=np.float32), (extra, 4, 4))
  return (np.concatenate([depth, np.zeros((extra,) + depth.shape[1:], np.float32)]),
          np.concatenate([T_world_cam, eye]),
          np.concatenate([labels, np.full((extra,) + labels.shape[1:], -1, np.int32)]))


def gt_from_frames(chunks: Iterable, *, camera: camera_lib.Camera, num_classes: int,
                   voxel_size: float = 0.1, capacity: Optional[int] = None) -> dict:
  """Majority GT label per voxel of a stream of labelled frames, fused chunk by chunk.

  Each chunk's GT labels become one-hot probabilities fused with `rules.sum_labels()`
  (`fuse_sequence`, one compiled scan per chunk): a pixel votes once for its label when its
  depth is valid and its label lies in `[0, num_classes)`; the label of a voxel is the class
  with the most votes, ties to the lowest class index (docs/equations.md §7.1). Only one chunk
  is held at a time, so memory does not grow with the number of frames. A chunk shorter than
  the first is padded with frames of zero depth, which touch nothing (one compilation for a
  stream of equal chunks and a shorter last one).

  Args:
    chunks: an iterable of chunks, each with `depth (t, H, W) float32` metres (0 = none),
      `T_world_cam (t, 4, 4)` camera-to-world poses and `labels (t, H, W) int32` (as
      attributes or keys): an `RGBDSequence` (`seq.subset(...)`), its `stacked()` dict, or
      one `RGBDFrame` (`(H, W)` fields).
    camera: intrinsics of the depth images.
    num_classes: K ≥ 2; labels outside `[0, K)` (`IGNORE_LABEL`) do not vote.
    voxel_size: voxel edge in metres (use the same as the maps you evaluate).
    capacity: a fixed map capacity (a power of two; a full map drops voxels, counted and
      warned about, `MapFullWarning`), or None: a map that grows as needed (`Mapper`).

  Returns:
    dict with `coords (N, 3) int32` voxel indices (`floor(p_world / voxel_size)`), sorted,
    `labels (N,) int32` majority label, and `hits (N,) int32` votes (labelled pixels) per voxel.

  Raises:
    ValueError: a chunk without labels, or of mismatched shapes.
  """
  rule = rules.sum_labels()
  if capacity is None:
    grower = mapper_lib.Mapper(rule, num_classes=num_classes, voxel_size=voxel_size,
                               capacity=INITIAL_CAPACITY)
    state = None
  else:
    grower = None
    state = state_lib.init_map(capacity=capacity, num_classes=num_classes,
                               voxel_size=voxel_size, rule=rule)
  length = None
  for chunk in chunks:
    depth, poses, labels = _chunk_arrays(chunk)
    if len(depth) == 0:
      continue
    length = len(depth) if length is None else length
    frames = _one_hot_frames_jit(*_pad(depth, poses, labels, length), num_classes=num_classes)
    if grower is not None:
      grower.fuse_sequence(frames, camera)
    else:
      state = fusion.fuse_sequence(state, frames, camera, rule)
  out = readout.read_map(grower.state if grower is not None else state)
  return {"coords": out["coords"], "labels": out["labels"], "hits": out["hits"]}


def gt_voxel_labels(sequence, *, voxel_size: float = 0.1, capacity=None,
                    chunk: Optional[int] = None) -> dict:
  """Majority GT label per voxel, by fusing one-hot GT labels with `rules.sum_labels()`.

  `gt_from_frames` over the sequence in chunks of frames; the result does not depend on the
  chunk size. A sequence whose world changes (`changes`) says which frames the GT is of:
  with `info["gt_frames"] = [start, stop]` only frames `start … stop - 1` are fused (those
  that saw the final scene), and with `info["true_poses"]` (a drifting sequence) the frames
  are placed at those true poses rather than at the stored `T_world_cam`.

  Args:
    sequence: an `RGBDSequence` with `labels`.
    voxel_size: voxel edge in metres (use the same as the maps you evaluate).
    capacity: a fixed map capacity (power of two); None: a map that grows as needed.
    chunk: frames fused per compiled call; default: as many as keep a chunk's one-hot labels
      within `CHUNK_VALUES` values (at least 1, at most 16).

  Returns:
    dict with `coords (N, 3) int32` voxel indices (`floor(p_world / voxel_size)`),
    `labels (N,) int32` majority label, and `hits (N,) int32` labelled pixels per voxel.

  Raises:
    ValueError: the sequence has no labels, or a malformed `gt_frames` / `true_poses`.
  """
  if sequence.labels is None:
    raise ValueError(f"sequence {sequence.name!r} has no ground-truth labels")
  h, w = sequence.image_size
  if chunk is None:
    chunk = int(np.clip(CHUNK_VALUES // max(h * w * sequence.num_classes, 1), 1, 16))
  if chunk < 1:
    raise ValueError(f"chunk must be at least 1; got {chunk}")
  first, stop = _gt_span(sequence)
  _true_poses(sequence)                  # a malformed entry is refused before any fusing
  chunks = (gt_part(sequence.subset(range(start, min(start + chunk, stop))))
            for start in range(first, stop, chunk))
  return gt_from_frames(chunks, camera=sequence.camera, num_classes=sequence.num_classes,
                        voxel_size=voxel_size, capacity=capacity)


def gt_part(chunk):
  """What of a labelled chunk the GT is made of, by `gt_voxel_labels`' rule: the chunk's frames
  within its `info["gt_frames"]`, placed at its `info["true_poses"]` when it has them.

  For GT computed chunk by chunk (`gt_from_frames` over `SequenceStream.chunks`, or over
  `seq.subset(...)` pieces): `RGBDSequence.subset` renumbers `gt_frames` and picks
  `true_poses` for the frames it keeps, so each chunk says for itself which of its frames count.

  Args:
    chunk: an `RGBDSequence` (or subset of one); anything else (a dict of arrays, a frame) is
      returned unchanged.

  Returns:
    The chunk itself when its info names neither; else its GT frames (none, for a chunk of the
    first pass of a changing world), as an `RGBDSequence` or, with true poses, a dict of
    `depth (t, H, W)`, `T_world_cam (t, 4, 4)` (the true poses) and `labels (t, H, W)`.

  Raises:
    ValueError: a malformed `gt_frames` / `true_poses`.
  """
  info = getattr(chunk, "info", None)
  if not isinstance(info, Mapping) or not ("gt_frames" in info or "true_poses" in info):
    return chunk
  start, stop = _gt_span(chunk)
  true_poses = _true_poses(chunk)
  part = chunk if (start, stop) == (0, len(chunk)) else chunk.subset(range(start, stop))
  if true_poses is None:
    return part
  return {"depth": part.depth, "T_world_cam": true_poses[start:stop], "labels": part.labels}


def _true_poses(sequence) -> Optional[np.ndarray]:
  """`(T, 4, 4) float32` the true poses of a drifting sequence (`info["true_poses"]`), or None."""
  true_poses = sequence.info.get("true_poses")
  if true_poses is None:
    return None
  true_poses = np.asarray(true_poses, np.float32)
  if true_poses.shape != sequence.T_world_cam.shape:
    raise ValueError(f"info['true_poses'] must be {sequence.T_world_cam.shape}; got "
                     f"{true_poses.shape}")
  return true_poses


def _gt_span(sequence) -> tuple:
  """`(start, stop)`: the frames the GT of a sequence is made of (`info["gt_frames"]`)."""
  span = sequence.info.get("gt_frames")
  if span is None:
    return 0, len(sequence)
  try:
    start, stop = (int(x) for x in span)
  except (TypeError, ValueError):
    start, stop = -1, -1
  if not 0 <= start <= stop <= len(sequence):
    raise ValueError(f"info['gt_frames'] must be [start, stop] within 0 … {len(sequence)}; "
                     f"got {span!r}")
  return start, stop


# ---- Labelled meshes -----------------------------------------------------------------------


def _check_mesh(vertices, faces, labels) -> tuple:
  """`(vertices (V, 3) float64, faces (F, 3) int64, labels (V,) int64)`, checked."""
  v = np.asarray(vertices, np.float64)
  f = np.asarray(faces)
  lab = np.asarray(labels)
  if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
    raise ValueError(f"vertices must be finite (V, 3); got shape {v.shape}")
  if f.size == 0:
    f = f.reshape(0, 3)
  if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
    raise ValueError(f"faces must be (F, 3) integers; got shape {f.shape} {f.dtype}")
  if f.size and (f.min() < 0 or f.max() >= len(v)):
    raise ValueError(f"faces index vertices 0 … {len(v) - 1}; got {f.min()} … {f.max()}")
  if lab.shape != (len(v),) or not np.issubdtype(lab.dtype, np.integer):
    raise ValueError(f"labels must be ({len(v)},) integers, one per vertex; got shape "
                     f"{lab.shape} {lab.dtype}")
  return v, f.astype(np.int64), lab.astype(np.int64)


def _check_positive(value, name: str) -> float:
  value = float(value)
  if not (np.isfinite(value) and value > 0):
    raise ValueError(f"{name} must be positive and finite; got {value}")
  return value


def _face_rows(tri: np.ndarray, spacing: float) -> tuple:
  """The sample rows of every face (docs/equations.md §7.2).

  A face is taken with its longest edge AB as the base and C opposite; rows parallel to AB
  run from `A + a(C − A)` to `B + a(C − B)` at `a = k/m`, `k = 0 … m`, `m = ⌈h/spacing⌉` (h the
  height of C over AB), and a row of length ℓ carries `⌈ℓ/spacing⌉ + 1` evenly spaced points,
  ends included.

  Args:
    tri: `(F, 3, 3) float64` the faces' corners.
    spacing: the largest gap between samples, metres.

  Returns:
    `(face (R,) int64, start (R, 3) float64, end (R, 3) float64, count (R,) int64)` per row.
  """
  edges = np.roll(tri, -1, axis=1) - tri                           # edge i: corner i → i+1
  length = np.linalg.norm(edges, axis=-1)                          # (F, 3)
  base = np.argmax(length, axis=1)
  order = (base[:, None] + np.arange(3)) % 3
  a, b, c = np.moveaxis(np.take_along_axis(tri, order[:, :, None], axis=1), 1, 0)
  base_len = length[np.arange(len(tri)), base]
  twice_area = np.linalg.norm(np.cross(b - a, c - a), axis=-1)
  height = np.divide(twice_area, base_len, out=np.zeros_like(base_len), where=base_len > 0)
  steps = np.ceil(height / spacing).astype(np.int64)               # m
  face = np.repeat(np.arange(len(tri)), steps + 1)
  first = np.cumsum(steps + 1) - (steps + 1)
  k = np.arange(len(face)) - np.repeat(first, steps + 1)
  m = steps[face]
  frac = np.divide(k, m, out=np.zeros(len(face)), where=m > 0)[:, None]
  start = a[face] + frac * (c - a)[face]
  end = b[face] + frac * (c - b)[face]
  count = np.ceil(base_len[face] * (1.0 - frac[:, 0]) / spacing).astype(np.int64) + 1
  return face, start, end, count


def _mesh_samples(vertices, faces, labels, *, spacing: float):
  """Yields `(points (S, 3) float64, labels (S,) int64)` chunks of the even samples of a mesh
  (`_face_rows`), in face order; each sample has the label of its face's nearest vertex (of
  equally near ones, the first in the face's order)."""
  tri = vertices[faces]                                            # (F, 3, 3)
  face, start, end, count = _face_rows(tri, spacing)
  ends = np.cumsum(count)
  lo = 0
  while lo < len(count):
    # Rows [lo, hi): at most MESH_CHUNK samples, at least one row.
    hi = max(int(np.searchsorted(ends, (ends[lo - 1] if lo else 0) + MESH_CHUNK, "right")),
             lo + 1)
    n = count[lo:hi]
    row = np.repeat(np.arange(lo, hi), n)
    q = np.arange(len(row)) - np.repeat(np.cumsum(n) - n, n)
    t = (q / np.maximum(count[row] - 1, 1))[:, None]
    points = start[row] + t * (end[row] - start[row])
    f = face[row]
    nearest = np.argmin(np.sum((tri[f] - points[:, None, :])**2, axis=-1), axis=1)
    yield points, labels[faces[f, nearest]]
    lo = hi


def _classes(ids: np.ndarray, lut) -> np.ndarray:
  """`(S,) int64` classes of NYU40 ids through a label space's lookup (`IGNORE_LABEL` for ids
  outside it)."""
  lut = np.asarray(lut)
  if lut.ndim != 1 or not np.issubdtype(lut.dtype, np.integer):
    raise ValueError(f"lut must be a 1-D integer lookup (a label space's); got {lut.shape} "
                     f"{lut.dtype}")
  ok = (ids >= 0) & (ids < len(lut))
  return np.where(ok, lut[np.where(ok, ids, 0)], IGNORE_LABEL).astype(np.int64)


def _voxel_keys(points: np.ndarray, size: float) -> np.ndarray:
  keys = np.floor(points / size)
  if keys.size and np.abs(keys).max() >= 2**30:
    raise ValueError(f"mesh points lie beyond the key range ±2**30 voxels of {size} m")
  return keys.astype(np.int64)


def gt_from_mesh(vertices, faces, labels, *, lut, voxel_size: float = 0.1,
                 spacing: Optional[float] = None) -> dict:
  """Majority GT label per voxel of a labelled mesh (docs/equations.md §7.2).

  Every face is sampled on an even grid (`spacing` apart at most, along rows parallel to its
  longest edge); each sample takes the label of its face's nearest vertex (of equally near
  ones, the first in the face's order), read into the label space through `lut`; samples whose
  id has no class there (`IGNORE_LABEL`, e.g. unannotated 0) are dropped. A voxel's label is
  the class with the most samples in it, ties to the lowest class index, as for label images.
  NumPy, vectorised over faces, in chunks of `MESH_CHUNK` samples.

  Args:
    vertices: `(V, 3) float` positions, metres, in the world frame of the sequence.
    faces: `(F, 3) int` vertex indices of the triangles.
    labels: `(V,) int` per-vertex ids, NYU40 for ScanNet's `*_vh_clean_2.labels.ply`.
    lut: `(L,) int32` id → class lookup of a label space (`classes.label_space(name)[1]`);
      ids outside `[0, L)` have no class.
    voxel_size: voxel edge in metres; keys `floor(p / voxel_size)` as the maps'.
    spacing: the largest gap between samples (default `voxel_size / 4`).

  Returns:
    dict with `coords (N, 3) int32` voxel indices, sorted as `read_map`'s,
    `labels (N,) int32` majority class, and `hits (N,) int32` samples per voxel.

  Raises:
    ValueError: malformed arrays, a non-positive voxel size or spacing.
  """
  vertices, faces, labels = _check_mesh(vertices, faces, labels)
  voxel_size = _check_positive(voxel_size, "voxel_size")
  spacing = _check_positive(voxel_size / 4 if spacing is None else spacing, "spacing")
  parts, counts = [], []
  for points, ids in _mesh_samples(vertices, faces, labels, spacing=spacing):
    cls = _classes(ids, lut)
    keep = cls >= 0
    rows = np.concatenate([_voxel_keys(points[keep], voxel_size), cls[keep, None]], axis=1)
    rows, n = np.unique(rows, axis=0, return_counts=True)     # (voxel, class) pairs, counted
    parts.append(rows)
    counts.append(n)
  if not parts or not sum(len(p) for p in parts):
    empty = np.zeros(0, np.int32)
    return {"coords": np.zeros((0, 3), np.int32), "labels": empty, "hits": empty.copy()}
  rows, inverse = np.unique(np.concatenate(parts), axis=0, return_inverse=True)
  votes = np.bincount(inverse.reshape(-1), weights=np.concatenate(counts)).astype(np.int64)
  # Per voxel: most votes first, then the lowest class; the first row of each voxel wins.
  order = np.lexsort((rows[:, 3], -votes, rows[:, 2], rows[:, 1], rows[:, 0]))
  rows, votes = rows[order], votes[order]
  new = np.ones(len(rows), bool)
  new[1:] = np.any(rows[1:, :3] != rows[:-1, :3], axis=1)
  voxel = np.cumsum(new) - 1
  hits = np.bincount(voxel, weights=votes).astype(np.int32)
  return {"coords": rows[new, :3].astype(np.int32), "labels": rows[new, 3].astype(np.int32),
          "hits": hits}


def surface_from_mesh(vertices, faces, labels, *, lut, spacing: float = 0.01) -> dict:
  """The true surface of a labelled mesh: its even samples thinned to one per cell of a
  `spacing` grid (docs/equations.md §7.3), as `surfaces.seen_surface` thins ray hits.

  The faces are sampled `spacing / 2` apart (as in `gt_from_mesh`, labels from the nearest
  vertex through `lut`); of the samples in one cell `floor(p / spacing)` the first (in face
  and sample order) is kept. Samples whose id has no class keep their place in the geometry
  with label `IGNORE_LABEL` (score them with `surface_metrics.mesh_semantic_scores(...,
  ignore_label=IGNORE_LABEL)`).

  Args:
    vertices: `(V, 3) float` positions, metres.
    faces: `(F, 3) int` vertex indices.
    labels: `(V,) int` per-vertex ids (NYU40 for ScanNet).
    lut: `(L,) int32` id → class lookup of a label space.
    spacing: thinning grid edge in metres (> 0).

  Returns:
    dict with `points (G, 3) float64` on the mesh and `labels (G,) int32` (class or
    `IGNORE_LABEL`).

  Raises:
    ValueError: malformed arrays or a non-positive spacing.
  """
  vertices, faces, labels = _check_mesh(vertices, faces, labels)
  spacing = _check_positive(spacing, "spacing")
  points, classes = [], []
  for p, ids in _mesh_samples(vertices, faces, labels, spacing=spacing / 2):
    _, first = np.unique(_voxel_keys(p, spacing), axis=0, return_index=True)
    first = np.sort(first)
    points.append(p[first])
    classes.append(_classes(ids[first], lut))
  if not points:
    return {"points": np.zeros((0, 3)), "labels": np.zeros(0, np.int32)}
  points, classes = np.concatenate(points), np.concatenate(classes)
  _, first = np.unique(_voxel_keys(points, spacing), axis=0, return_index=True)
  first = np.sort(first)
  return {"points": points[first], "labels": classes[first].astype(np.int32)}
