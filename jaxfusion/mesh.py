"""Meshes of the geometry layer: marching cubes on the hashed TSDF, as jitted programs.

A cube is spanned by the centres of 2×2×2 neighbouring voxels; its corners are looked up
through the block hash, so a cube may straddle up to 8 blocks. Each voxel owns the three edges
that leave its centre along +x, +y and +z (as in Open3D's kernel), so a vertex is computed once
and shared by the (up to four) cubes around its edge. Cubes with a corner whose weight is below
`min_weight` are skipped. The case tables are the project's own (`mc_tables`).

Two programs, with fixed shapes throughout:
  1. `_classify`: every allocated voxel's cube case and its owned edges that carry a vertex,
     in chunks of blocks (bounded scratch); prefix sums give vertex and triangle ids.
  2. `_emit`: vertex positions and triangles written into padded buffers of sizes chosen by
     the host from program 1's counts (rounded up to powers of two, so few shapes compile).
The host trims the padding and looks up each vertex's class, confidence and entropy in the
semantic layer (`readout.query`).

Shape legend: B block slots, V = b³ voxels per block, G blocks per chunk, P vertices, F faces,
K classes.
"""

import functools
from typing import NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import hashing
from jaxfusion import mc_tables
from jaxfusion import tsdf as tsdf_lib

# nvblox's default minimum voxel weight for meshing: any voxel observed at all.
DEFAULT_MIN_WEIGHT = 1e-4
# Blocks per chunk of the meshing loops (64 × 512 voxels × 8 corners of scratch).
_MESH_CHUNK = 64
# The 8 neighbour blocks of a block: offset n has bits (x, y, z) = (n & 1, n >> 1 & 1, n >> 2).
_NEIGHBOURS = np.array([[n & 1, (n >> 1) & 1, (n >> 2) & 1] for n in range(8)], np.int32)


class Mesh(NamedTuple):
  """A triangle mesh with per-vertex semantics (host NumPy arrays).

  Attributes:
    vertices: `(P, 3) float32` world positions in metres.
    faces: `(F, 3) int32` vertex indices; counter-clockwise seen from the free side (normals
      point out of the surface, towards where the camera was).
    normals: `(P, 3) float32` unit vertex normals (area-weighted face normals).
    labels: `(P,) int32` class of each vertex in the semantic layer (−1: no semantic voxel
      at it nor, with `fill`, around it; docs/equations.md §9.2).
    confidence: `(P,) float32` the rule's confidence of that voxel (0 where none).
    entropy: `(P,) float32` posterior entropy in nats (log K where none).
    face_labels: `(F,) int32` class at each face's centroid (−1: none); `classes=` and
      `mesh_by_class` select faces by it, so the class meshes partition the mesh.
  """
  vertices: np.ndarray
  faces: np.ndarray
  normals: np.ndarray
  labels: Optional[np.ndarray] = None
  confidence: Optional[np.ndarray] = None
  entropy: Optional[np.ndarray] = None
  face_labels: Optional[np.ndarray] = None

  @property
  def num_vertices(self) -> int:
    return int(self.vertices.shape[0])

  @property
  def num_faces(self) -> int:
    return int(self.faces.shape[0])


def _corner_tables(block_size: int):
  """Static `(V, 8)` tables: for voxel v of a block and cube corner c, which neighbour block
  (0…7, `_NEIGHBOURS`) holds the corner and its voxel index there."""
  b = block_size
  local = tsdf_lib.voxel_offsets(b)                          # (V, 3)
  corner = _NEIGHBOURS                                       # corner c's offset = bits of c
  pos = local[:, None, :] + corner[None, :, :]               # (V, 8, 3)
  over = (pos >= b).astype(np.int32)
  neighbour = over[..., 0] + 2 * over[..., 1] + 4 * over[..., 2]
  wrapped = pos - b * over
  index = wrapped[..., 0] + b * (wrapped[..., 1] + b * wrapped[..., 2])
  return neighbour.astype(np.int32), index.astype(np.int32)


def _occupied_slots(state: tsdf_lib.TSDFState):
  """`(B,) int32` the occupied block slots first (the rest B), and how many there are."""
  capacity = state.capacity
  occupied = state.block_keys[:, 0] != hashing.EMPTY
  slots = jnp.nonzero(occupied, size=capacity, fill_value=capacity)[0].astype(jnp.int32)
  return slots, jnp.sum(occupied, dtype=jnp.int32)


def _neighbour_slots(state: tsdf_lib.TSDFState, slots):
  """`(n, 8) int32` slots of the 8 blocks at `_NEIGHBOURS` offsets of each block in `slots`
  (capacity where absent)."""
  capacity = state.capacity
  keys = state.block_keys[jnp.minimum(slots, capacity - 1)]
  query = (keys[:, None, :] + jnp.asarray(_NEIGHBOURS)[None]).reshape(-1, 3)
  found_slots, found = hashing.lookup(state.block_keys, query, max_probes=state.max_probes)
  out = jnp.where(found, found_slots, capacity).reshape(-1, 8)
  return jnp.where((slots < capacity)[:, None], out, capacity)


def _corners(state: tsdf_lib.TSDFState, neighbours, tables):
  """`(sdf, weight)` at the 8 cube corners of every voxel of some blocks: `(G, V, 8)` each
  (weight 0 where the corner's block is absent)."""
  capacity = state.capacity
  neighbour, index = tables
  slot = neighbours[:, jnp.asarray(neighbour)]                       # (G, V, 8)
  read = jnp.minimum(slot, capacity - 1)
  sdf = state.sdf[read, jnp.asarray(index)[None]]
  weight = jnp.where(slot < capacity, state.weight[read, jnp.asarray(index)[None]], 0.0)
  return sdf, weight


def _classify_blocks(state, neighbours, tables, min_weight):
  """Cube cases `(G, V) int32` (0 for skipped cubes) and owned-edge vertex flags `(G, V, 3)`."""
  sdf, weight = _corners(state, neighbours, tables)
  ok = weight >= min_weight                                         # (G, V, 8)
  inside = sdf < 0
  bits = jnp.asarray(1 << np.arange(8), jnp.int32)
  cube_ok = jnp.all(ok, axis=-1)
  case = jnp.where(cube_ok, jnp.sum(jnp.where(inside, bits, 0), axis=-1), 0)
  # Voxel v's own edge along axis a joins corner 0 (itself) and corner 1 << a.
  own = [1, 2, 4]
  flags = jnp.stack([ok[..., 0] & ok[..., c] & (inside[..., 0] != inside[..., c]) for c in own],
                    axis=-1)
  return case, flags, sdf


@jax.jit
def _classify(state: tsdf_lib.TSDFState, min_weight):
  """Program 1: cases `(B, V)` and vertex flags `(B, V, 3)` by slot, plus the block
  neighbour table `(B, 8)` and counts."""
  capacity, voxels = state.sdf.shape
  tables = _corner_tables(state.block_size)
  slots, num = _occupied_slots(state)
  chunk = min(_MESH_CHUNK, capacity)
  padded = -(-capacity // chunk) * chunk
  slots = jnp.pad(slots, (0, padded - capacity), constant_values=capacity)

  def body(carry):
    c, cases, flags, neighbours = carry
    these = jax.lax.dynamic_slice(slots, (c * chunk,), (chunk,))
    nb = _neighbour_slots(state, these)
    case, flag, _ = _classify_blocks(state, nb, tables, min_weight)
    return (c + 1, cases.at[these].set(case, mode="drop"),
            flags.at[these].set(flag, mode="drop"), neighbours.at[these].set(nb, mode="drop"))

  init = (jnp.zeros((), jnp.int32), jnp.zeros((capacity, voxels), jnp.int32),
          jnp.zeros((capacity, voxels, 3), bool), jnp.full((capacity, 8), capacity, jnp.int32))
  _, cases, flags, neighbours = jax.lax.while_loop(lambda c: c[0] * chunk < num, body, init)
  num_tris = jnp.asarray(mc_tables.NUM_TRIANGLES, jnp.int32)[cases]
  return cases, flags, neighbours, jnp.sum(flags, dtype=jnp.int32), jnp.sum(num_tris,
                                                                           dtype=jnp.int32)


@functools.partial(jax.jit, static_argnames=("max_vertices", "max_faces"))
def _emit(state: tsdf_lib.TSDFState, cases, flags, neighbours, *, max_vertices: int,
          max_faces: int):
  """Program 2: vertices `(max_vertices, 3)` and faces `(max_faces, 3)` (padding: 0)."""
  capacity, voxels = state.sdf.shape
  b = state.block_size
  tables = _corner_tables(b)
  vertex_id = (jnp.cumsum(flags.reshape(-1), dtype=jnp.int32) - 1).reshape(capacity, voxels, 3)
  num_tris = jnp.asarray(mc_tables.NUM_TRIANGLES, jnp.int32)[cases]
  face_start = (jnp.cumsum(num_tris.reshape(-1), dtype=jnp.int32)
                - num_tris.reshape(-1)).reshape(capacity, voxels)
  slots, num = _occupied_slots(state)
  chunk = min(_MESH_CHUNK, capacity)
  padded = -(-capacity // chunk) * chunk
  slots = jnp.pad(slots, (0, padded - capacity), constant_values=capacity)
  offsets = jnp.asarray(tsdf_lib.voxel_offsets(b))
  # Edge e of a cube at voxel v is owned by voxel v + EDGE_OWNER[e] (corner c = its bits).
  owner_corner = (mc_tables.EDGE_OWNER[:, 0] + 2 * mc_tables.EDGE_OWNER[:, 1]
                  + 4 * mc_tables.EDGE_OWNER[:, 2]).astype(np.int32)
  triangles = jnp.asarray(mc_tables.TRIANGLES, jnp.int32)            # (256, 5, 3)
  edge_axis = jnp.asarray(mc_tables.EDGE_AXIS, jnp.int32)
  neighbour_of, index_of = (jnp.asarray(t) for t in tables)

  def body(carry):
    c, verts, faces = carry
    these = jax.lax.dynamic_slice(slots, (c * chunk,), (chunk,))
    read = jnp.minimum(these, capacity - 1)
    ok = (these < capacity)[:, None]
    nb = neighbours[read]
    _, _, sdf = _classify_blocks(state, nb, tables, 0.0)
    # Vertices on the block's own edges.
    keys = state.block_keys[read]
    origin = (keys[:, None, :] * b + offsets[None]).astype(jnp.float32) + 0.5   # (G, V, 3)
    s0 = sdf[..., 0]
    ids = vertex_id[read]                                                 # (G, V, 3)
    for a, corner in enumerate((1, 2, 4)):
      s1 = sdf[..., corner]
      t = s0 / jnp.where(s0 != s1, s0 - s1, 1.0)
      p = origin.at[..., a].add(t) * state.voxel_size
      write = jnp.where(ok & flags[read][..., a], ids[..., a], max_vertices)
      verts = verts.at[write.reshape(-1)].set(p.reshape(-1, 3), mode="drop")
    # Triangles of each cube: edge → owner voxel (maybe in a neighbour block) → vertex id.
    case = jnp.where(ok, cases[read], 0)                                  # (G, V)
    tri_edges = triangles[case]                                           # (G, V, 5, 3)
    edge = jnp.maximum(tri_edges, 0)
    corner = jnp.asarray(owner_corner)[edge]                              # (G, V, 5, 3)
    v_index = jnp.arange(voxels)[None, :, None, None]
    g_index = jnp.arange(chunk)[:, None, None, None]
    owner_block = nb[g_index, neighbour_of[v_index, corner]]
    owner_voxel = index_of[v_index, corner]
    vid = vertex_id[jnp.minimum(owner_block, capacity - 1), owner_voxel, edge_axis[edge]]
    tri_ok = (tri_edges[..., 0] >= 0) & ok[..., None]                     # (G, V, 5)
    row = face_start[read][..., None] + jnp.arange(5)[None, None, :]
    write = jnp.where(tri_ok, row, max_faces)
    faces = faces.at[write.reshape(-1)].set(vid.reshape(-1, 3), mode="drop")
    return c + 1, verts, faces

  init = (jnp.zeros((), jnp.int32), jnp.zeros((max_vertices, 3), jnp.float32),
          jnp.zeros((max_faces, 3), jnp.int32))
  _, verts, faces = jax.lax.while_loop(lambda c: c[0] * chunk < num, body, init)
  return verts, faces


def _padded(n: int) -> int:
  return 1 << max(int(n) - 1, 0).bit_length() if n > 0 else 1


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """`(P, 3) float32` unit area-weighted vertex normals (zero for unreferenced vertices)."""
  v = np.asarray(vertices, np.float64)
  f = np.asarray(faces, np.int64)
  normals = np.zeros_like(v)
  if len(f):
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for k in range(3):
      np.add.at(normals, f[:, k], cross)
  length = np.linalg.norm(normals, axis=-1, keepdims=True)
  return (normals / np.where(length > 0, length, 1.0)).astype(np.float32)


def marching_cubes(geometry: tsdf_lib.TSDFState, *,
                   min_weight: float = DEFAULT_MIN_WEIGHT) -> tuple[np.ndarray, np.ndarray]:
  """The zero level set of a geometry layer as a triangle mesh (two jitted programs).

  Args:
    geometry: one TSDFState (not a batch).
    min_weight: cubes with a corner of lower weight are skipped (≥ 0).

  Returns:
    `(vertices (P, 3) float32 metres, faces (F, 3) int32)`, every vertex used by a face; both
    empty for an empty layer.
  """
  if not isinstance(geometry, tsdf_lib.TSDFState):
    raise TypeError(f"marching_cubes expects a TSDFState; got {type(geometry).__name__}")
  if geometry.block_keys.ndim != 2:
    raise ValueError("marching_cubes expects one layer; index a batched map first")
  if not (np.isfinite(min_weight) and min_weight >= 0):
    raise ValueError(f"min_weight must be a finite number ≥ 0; got {min_weight!r}")
  cases, flags, neighbours, num_v, num_f = _classify(geometry, jnp.float32(min_weight))
  num_v, num_f = int(num_v), int(num_f)
  if num_f == 0:
    return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
  verts, faces = _emit(geometry, cases, flags, neighbours, max_vertices=_padded(num_v),
                       max_faces=_padded(num_f))
  verts, faces = np.asarray(verts)[:num_v], np.asarray(faces)[:num_f]
  # An edge between two observed voxels whose every cube is skipped (a corner below
  # `min_weight`) carries a vertex no face uses: drop those and renumber.
  used = np.zeros(num_v, bool)
  used[faces.reshape(-1)] = True
  if not used.all():
    index = (np.cumsum(used) - 1).astype(np.int32)
    verts, faces = verts[used], index[faces]
  return verts, faces


def _select_faces(mesh: Mesh, keep: np.ndarray) -> Mesh:
  """The sub-mesh of the faces where `keep`, with its vertices renumbered (unused dropped)."""
  faces = mesh.faces[keep]
  used = np.zeros(mesh.num_vertices, bool)
  used[faces.reshape(-1)] = True
  index = np.cumsum(used) - 1
  pick = lambda x: None if x is None else x[used]
  return Mesh(vertices=mesh.vertices[used], faces=index[faces].astype(np.int32),
              normals=mesh.normals[used], labels=pick(mesh.labels),
              confidence=pick(mesh.confidence), entropy=pick(mesh.entropy),
              face_labels=None if mesh.face_labels is None else mesh.face_labels[keep])


def extract_mesh(state, *, min_weight: float = DEFAULT_MIN_WEIGHT,
                 classes: Optional[Sequence[int]] = None, box: Optional[tuple] = None,
                 fill: bool = True) -> Mesh:
  """The map's surface as a triangle mesh, each vertex labelled from the semantic layer.

  Args:
    state: a MapState with a geometry layer (`init_map(..., geometry=...)`), or a TSDFState
      alone (then the mesh has no labels).
    min_weight: cubes with a corner of lower TSDF weight are skipped.
    fill: a vertex (or face centroid) whose semantic voxel is not in the map reads the nearest
      of the 26 neighbouring voxels that is (docs/equations.md §9.2); False: it stays −1.
    classes: keep only the faces whose class (at the face's centroid) is one of these.
    box: `(min_xyz, max_xyz)` in metres: keep only the faces whose centroid lies in the box.

  Returns:
    A Mesh. A map with nothing integrated yet gives an empty mesh (0 vertices, 0 faces).

  Raises:
    ValueError: a map without a geometry layer, a batched map, or bad `classes` / `box`.
  """
  from jaxfusion import readout   # pylint: disable=import-outside-toplevel
  from jaxfusion.state import MapState   # pylint: disable=import-outside-toplevel
  if isinstance(state, MapState):
    if state.geometry is None:
      raise ValueError("this map has no geometry layer: make it with init_map(..., "
                       "geometry=jaxfusion.tsdf.TSDFConfig()) (or Mapper(..., geometry=...))")
    if state.keys.ndim != 2:
      raise ValueError("extract_mesh expects one map; index a batched map first")
    semantic, geometry = state, state.geometry
  elif isinstance(state, tsdf_lib.TSDFState):
    semantic, geometry = None, state
  else:
    raise TypeError(f"extract_mesh expects a MapState or a TSDFState; got "
                    f"{type(state).__name__}")
  if classes is not None and semantic is None:
    raise ValueError("classes= needs a map with a semantic layer (a MapState)")
  wanted = None if classes is None else readout._check_classes(classes, semantic.num_classes)
  bounds = None if box is None else readout._check_box(box)
  vertices, faces = marching_cubes(geometry, min_weight=min_weight)
  mesh = Mesh(vertices=vertices, faces=faces, normals=vertex_normals(vertices, faces))
  if semantic is not None:
    centroids = vertices[faces].mean(axis=1) if len(faces) else np.zeros((0, 3), np.float32)
    points = np.concatenate([vertices, centroids]).astype(np.float32)
    labels, confidence, entropy = _read_labels(semantic, points, fill=fill)
    n = len(vertices)
    mesh = mesh._replace(labels=labels[:n], confidence=confidence[:n], entropy=entropy[:n],
                         face_labels=labels[n:])
  if wanted is not None or bounds is not None:
    keep = np.ones(len(faces), bool)
    if wanted is not None:
      keep &= np.isin(mesh.face_labels, wanted)
    if bounds is not None:
      c = vertices[faces].mean(axis=1) if len(faces) else np.zeros((0, 3))
      keep &= np.all((c >= bounds[0]) & (c <= bounds[1]), axis=-1)
    mesh = _select_faces(mesh, keep)
  return mesh


# The 26 neighbours of a voxel, x-major then y then z (the tie order of §9.2).
_VOXEL_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1)
                              for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)], np.int32)


def _read_labels(semantic, points: np.ndarray, *, fill: bool) -> tuple:
  """`(labels (N,) int32, confidence (N,) float32, entropy (N,) float32)` of world points from
  the semantic layer, as §9.2 states (with `fill`, an empty voxel reads its nearest neighbour
  in the map)."""
  from jaxfusion import camera as camera_lib   # pylint: disable=import-outside-toplevel
  from jaxfusion import readout   # pylint: disable=import-outside-toplevel
  n = len(points)
  if n == 0:
    return np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0, np.float32)
  q = readout.query(semantic, points)
  found = np.array(q.found)
  posterior = np.array(q.posterior)
  entropy = np.array(q.entropy, np.float32)
  missing = np.flatnonzero(~found & np.all(np.isfinite(points), axis=1))
  if fill and len(missing):
    size = np.float32(semantic.voxel_size)
    keys, _ = camera_lib.voxel_keys(points[missing], semantic.voxel_size)
    keys = np.asarray(keys, np.int64)
    centres = ((keys[:, None, :] + _VOXEL_NEIGHBOURS[None]).astype(np.float32) + 0.5) * size
    near = readout.query(semantic, centres.reshape(-1, 3))
    near_found = np.asarray(near.found).reshape(len(missing), len(_VOXEL_NEIGHBOURS))
    # Vertices often lie exactly between two voxel centres: distances in float64, rounded to
    # a micrometre, so that such ties go to the first neighbour whatever the rounding.
    exact = (keys[:, None, :] + _VOXEL_NEIGHBOURS[None] + 0.5) * np.float64(size)
    distance = np.round(np.linalg.norm(exact - points[missing][:, None, :].astype(np.float64),
                                       axis=-1), 6)
    distance = np.where(near_found, distance, np.inf)
    best = np.argmin(distance, axis=1)                    # the first of equal distances
    ok = np.isfinite(distance[np.arange(len(missing)), best])
    pick = (np.arange(len(missing)) * len(_VOXEL_NEIGHBOURS) + best)[ok]
    rows = missing[ok]
    found[rows] = True
    posterior[rows] = np.asarray(near.posterior).reshape(-1, posterior.shape[1])[pick]
    entropy[rows] = np.asarray(near.entropy, np.float32).reshape(-1)[pick]
  labels = np.where(found, posterior.argmax(-1), -1).astype(np.int32)
  confidence = np.where(found, posterior.max(-1), 0.0).astype(np.float32)
  return labels, confidence, entropy


def mesh_by_class(state, *, min_weight: float = DEFAULT_MIN_WEIGHT) -> dict:
  """One mesh per class present: `{class: Mesh}` (faces selected by their centroid's class, so
  the meshes partition `extract_mesh(state)`; faces with no semantic voxel are left out)."""
  mesh = extract_mesh(state, min_weight=min_weight)
  if mesh.face_labels is None:
    raise ValueError("mesh_by_class needs a map with a semantic layer (a MapState)")
  return {int(c): _select_faces(mesh, mesh.face_labels == c)
          for c in np.unique(mesh.face_labels) if c >= 0}
