"""Meshes of the geometry layer: marching cubes on the hashed TSDF, as jitted programs.

A cube is spanned by the centres of 2×2×2 neighbouring voxels; its corners are looked up
through the block hash, so a cube may straddle up to 8 blocks. Each voxel owns the three edges
that leave its centre along +x, +y and +z (as in Open3D's kernel), so a vertex is computed once
and shared by the (up to four) cubes around its edge. Cubes with a corner whose weight is below
`min_weight` are skipped. The case tables are the project's own (`mc_tables`).

Two programs, with fixed shapes throughout:
  1. `_classify`: every allocated voxel's cube case and its owned edges that carry a vertex,
     in chunks of blocks (each voxel coded inside / usable in one byte, a block's codes joined
     with its +x/+y/+z neighbours' by slicing; bounded scratch), kept as prefix counts within
     each block.
  2. `_emit`: each vertex and each triangle computed from its own index (a search of the
     blocks' counts, then within its block), into padded buffers of sizes chosen by the host
     from program 1's counts (powers of two, so few shapes compile); gathers only.
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

from jaxfusion import camera as camera_lib
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


def _rank_codes(state: tsdf_lib.TSDFState, slots, min_weight):
  """`(R + 1, V) int8` each ranked block's voxel codes, bit 0 inside (sdf < 0), bit 1 usable
  (weight ≥ `min_weight`), and a last all-zero row for an absent block: computed once per
  block, so that the chunks below read a byte per neighbour voxel, not its sdf and weight."""
  capacity = state.capacity
  read = jnp.minimum(slots, capacity - 1)
  usable = (slots < capacity)[:, None] & (state.weight[read] >= min_weight)
  codes = usable.astype(jnp.int8) * 2 + (state.sdf[read] < 0).astype(jnp.int8)
  return jnp.concatenate([codes, jnp.zeros((1, codes.shape[1]), jnp.int8)])


def _block_grid(rows, b: int):
  """The codes on the `(b+1)³` voxel centres of a block and its +x/+y/+z neighbours,
  `(G, b+1, b+1, b+1) int8` indexed `[z, y, x]`, from the 8 blocks' code rows `(G, 8, V)` at
  `_NEIGHBOURS` offsets, joined by slicing (no per-corner gathers)."""
  g = rows.shape[0]
  # Voxel i + b·(j + b·k) of block n sits at (x, y, z) = (i, j, k): rows reshape to [z, y, x].
  r = rows.reshape(g, 8, b, b, b)
  own_x = jnp.concatenate([r[:, 0], r[:, 1, :, :, :1]], axis=3)                # (G, b, b, b+1)
  y_face = jnp.concatenate([r[:, 2, :, :1, :], r[:, 3, :, :1, :1]], axis=3)     # (G, b, 1, b+1)
  slab = jnp.concatenate([own_x, y_face], axis=2)                              # (G, b, b+1, b+1)
  z_rows = jnp.concatenate([r[:, 4, :1], r[:, 5, :1, :, :1]], axis=3)          # (G, 1, b, b+1)
  z_edge = jnp.concatenate([r[:, 6, :1, :1, :], r[:, 7, :1, :1, :1]], axis=3)  # (G, 1, 1, b+1)
  z_face = jnp.concatenate([z_rows, z_edge], axis=2)                           # (G, 1, b+1, b+1)
  return jnp.concatenate([slab, z_face], axis=1)


def _prefix(x):
  """Inclusive prefix sums along axis 1 (`associative_scan`: on XLA's CPU faster than
  `jnp.cumsum`, which lowers to a `reduce_window` over the whole axis)."""
  return jax.lax.associative_scan(jnp.add, x, axis=1)


# Owned-edge bits of a voxel (bit a: its edge along axis a carries a vertex): how many are set,
# which axis the j-th set bit is, and how many set bits lie below axis a.
_EDGE_COUNT = np.array([bin(m).count("1") for m in range(8)], np.int32)
_EDGE_AXIS_OF = np.array([[([a for a in range(3) if m >> a & 1] + [0, 0, 0])[j]
                           for j in range(3)] for m in range(8)], np.int32)
_EDGES_BELOW = np.array([[bin(m & ((1 << a) - 1)).count("1") for a in range(3)]
                         for m in range(8)], np.int32)


class _Plan(NamedTuple):
  """Program 1's output, by block rank r (the r-th occupied slot, slot order; R ranks, a power
  of two ≥ the occupied blocks): the slots `(R,) int32` (capacity past the occupied ones), cube
  cases `(R, V) uint8`, each voxel's owned-edge bits `(R, V) uint8` (bit a: its edge along
  axis a carries a vertex), inclusive prefix counts within each block of those vertices and of
  triangles `(R, V) int16` each, the 8 neighbour blocks' slots and ranks `(R, 8) int32`
  (capacity / R where absent), and the totals."""
  slots: jax.Array
  cases: jax.Array
  edges: jax.Array
  vertex_cum: jax.Array
  face_cum: jax.Array
  neighbour_slots: jax.Array
  neighbour_ranks: jax.Array
  num_vertices: jax.Array
  num_faces: jax.Array


@functools.partial(jax.jit, static_argnames=("max_blocks",))
def _classify(state: tsdf_lib.TSDFState, min_weight, *, max_blocks: int) -> _Plan:
  """Program 1: every occupied block's cube cases, owned-edge vertex bits and triangle counts
  (chunks of `_MESH_CHUNK` blocks), as prefix counts per block, for the first `max_blocks`
  occupied slots (the host passes at least their number)."""
  capacity, voxels = state.sdf.shape
  b = state.block_size
  all_slots, num = _occupied_slots(state)
  chunk = min(_MESH_CHUNK, max_blocks)
  padded = -(-max_blocks // chunk) * chunk
  slots = jnp.pad(all_slots[:max_blocks], (0, padded - max_blocks), constant_values=capacity)
  rank_of_slot = jnp.full(capacity + 1, max_blocks, jnp.int32).at[slots].set(
      jnp.arange(padded, dtype=jnp.int32), mode="drop")
  rank_of_slot = rank_of_slot.at[capacity].set(max_blocks)
  codes = _rank_codes(state, slots, min_weight)                       # (padded + 1, V)
  num_tris_of = jnp.asarray(mc_tables.NUM_TRIANGLES, jnp.int32)

  def body(carry):
    c, cases, edges, vertex_cum, face_cum, neighbours = carry
    these = jax.lax.dynamic_slice(slots, (c * chunk,), (chunk,))
    nb = _neighbour_slots(state, these)
    rank = rank_of_slot[jnp.minimum(nb, capacity)]
    grid = _block_grid(codes[jnp.where(rank < max_blocks, rank, padded)], b)
    # Corner c of the cube at each voxel (offset bits (x, y, z) of c), `(G, V) int8` each.
    corner = [grid[:, z:z + b, y:y + b, x:x + b].reshape(chunk, voxels)
              for x, y, z in _NEIGHBOURS]
    usable = functools.reduce(jnp.bitwise_and, corner) & 2
    inside = [(x & 1).astype(jnp.int32) for x in corner]
    case = jnp.where(usable != 0, sum(inside[k] << k for k in range(8)), 0)
    # Voxel v's own edge along axis a joins corner 0 (itself) and corner 1 << a.
    bits = sum(jnp.where(((corner[0] & corner[1 << a] & 2) != 0) & (inside[0] != inside[1 << a]),
                         1 << a, 0) for a in range(3))
    # Both prefix counts in one scan: vertices in the low 16 bits, triangles in the high ones
    # (a block has at most 3V = 1536 vertices and 5V = 2560 triangles).
    both = _prefix(jnp.asarray(_EDGE_COUNT)[bits] + (num_tris_of[case] << 16))
    at = (c * chunk, 0)
    return (c + 1, jax.lax.dynamic_update_slice(cases, case.astype(jnp.uint8), at),
            jax.lax.dynamic_update_slice(edges, bits.astype(jnp.uint8), at),
            jax.lax.dynamic_update_slice(vertex_cum, (both & 0xFFFF).astype(jnp.int16), at),
            jax.lax.dynamic_update_slice(face_cum, (both >> 16).astype(jnp.int16), at),
            jax.lax.dynamic_update_slice(neighbours, nb, at))

  init = (jnp.zeros((), jnp.int32), jnp.zeros((padded, voxels), jnp.uint8),
          jnp.zeros((padded, voxels), jnp.uint8), jnp.zeros((padded, voxels), jnp.int16),
          jnp.zeros((padded, voxels), jnp.int16), jnp.full((padded, 8), capacity, jnp.int32))
  _, cases, edges, vertex_cum, face_cum, neighbours = jax.lax.while_loop(
      lambda carry: (carry[0] * chunk < num) & (carry[0] * chunk < padded), body, init)
  return _Plan(slots, cases, edges, vertex_cum, face_cum, neighbours,
               rank_of_slot[jnp.minimum(neighbours, capacity)],
               jnp.sum(vertex_cum[:, -1], dtype=jnp.int32),
               jnp.sum(face_cum[:, -1], dtype=jnp.int32))


def _search_rows(cum, rows, target):
  """For each i, the smallest e with `cum[rows[i], e] > target[i]` (rows nondecreasing):
  a batched binary search, `ceil(log2 L) + 1` gathers per item."""
  length = cum.shape[1]
  lo = jnp.zeros(rows.shape, jnp.int32)
  hi = jnp.full(rows.shape, length, jnp.int32)
  for _ in range(int(np.ceil(np.log2(max(length, 2)))) + 1):
    mid = (lo + hi) // 2
    right = cum[rows, jnp.minimum(mid, length - 1)].astype(jnp.int32) <= target
    active = lo < hi
    lo = jnp.where(active & right, mid + 1, lo)
    hi = jnp.where(active & ~right, mid, hi)
  return lo


def _locate(block_cum, within_cum, k):
  """Item k of a block-major enumeration: `(block, position in it, items before it)`, given
  each block's inclusive prefix counts `within_cum (R, L)` and their totals' inclusive prefix
  `block_cum (R,)`."""
  ranks = block_cum.shape[0]
  rank = jnp.minimum(jnp.searchsorted(block_cum, k, side="right"), ranks - 1)
  before = block_cum[rank] - within_cum[rank, -1].astype(jnp.int32)
  position = _search_rows(within_cum, rank, k - before)
  return rank.astype(jnp.int32), jnp.minimum(position, within_cum.shape[1] - 1), before


@functools.partial(jax.jit, static_argnames=("max_vertices", "max_faces"))
def _emit(state: tsdf_lib.TSDFState, plan: _Plan, *, max_vertices: int, max_faces: int):
  """Program 2: vertices `(max_vertices, 3)` and faces `(max_faces, 3)` (entries past the
  counts are padding), each computed from its own index: its block by a search of the blocks'
  running counts, its voxel by a search within the block — only gathers, no scatter."""
  capacity = state.capacity
  b = state.block_size
  ranks = plan.cases.shape[0]
  offsets = jnp.asarray(tsdf_lib.voxel_offsets(b))
  neighbour_of, index_of = (jnp.asarray(t) for t in _corner_tables(b))
  block_vertices = plan.vertex_cum[:, -1].astype(jnp.int32)
  vertex_block_cum = jnp.cumsum(block_vertices, dtype=jnp.int32)
  face_block_cum = jnp.cumsum(plan.face_cum[:, -1].astype(jnp.int32), dtype=jnp.int32)
  vertex_start = vertex_block_cum - block_vertices
  edge_count = jnp.asarray(_EDGE_COUNT)

  # Vertex k: the j-th owned edge with a sign change of voxel v, along axis a.
  k = jnp.arange(max_vertices, dtype=jnp.int32)
  rank, v, before = _locate(vertex_block_cum, plan.vertex_cum, k)
  bits = plan.edges[rank, v].astype(jnp.int32)
  j = k - before - (plan.vertex_cum[rank, v].astype(jnp.int32) - edge_count[bits])
  a = jnp.asarray(_EDGE_AXIS_OF)[bits, jnp.clip(j, 0, 2)]
  corner = jnp.left_shift(1, a)                                       # 1, 2 or 4
  slot = jnp.minimum(plan.slots[rank], capacity - 1)
  other = plan.neighbour_slots[rank, neighbour_of[v, corner]]
  s0 = state.sdf[slot, v]
  s1 = state.sdf[jnp.minimum(other, capacity - 1), index_of[v, corner]]
  t = s0 / jnp.where(s0 != s1, s0 - s1, 1.0)
  origin = (state.block_keys[slot] * b + offsets[v]).astype(jnp.float32) + 0.5
  verts = (origin + t[:, None] * jax.nn.one_hot(a, 3, dtype=jnp.float32)) * state.voxel_size

  # Face f: triangle q of the cube at voxel v; its edges' vertices are their owners' ids.
  f = jnp.arange(max_faces, dtype=jnp.int32)
  rank, v, before = _locate(face_block_cum, plan.face_cum, f)
  ntri = jnp.asarray(mc_tables.NUM_TRIANGLES, jnp.int32)
  case = plan.cases[rank, v].astype(jnp.int32)
  q = f - before - (plan.face_cum[rank, v].astype(jnp.int32) - ntri[case])
  edges = jnp.asarray(mc_tables.TRIANGLES, jnp.int32)[case, jnp.clip(q, 0, 4)]   # (F, 3)
  edges = jnp.maximum(edges, 0)
  owner_corner = jnp.asarray(
      mc_tables.EDGE_OWNER[:, 0] + 2 * mc_tables.EDGE_OWNER[:, 1]
      + 4 * mc_tables.EDGE_OWNER[:, 2], jnp.int32)[edges]              # (F, 3)
  owner = plan.neighbour_ranks[rank[:, None], neighbour_of[v[:, None], owner_corner]]
  owner = jnp.minimum(owner, ranks - 1)
  owner_voxel = index_of[v[:, None], owner_corner]
  axis = jnp.asarray(mc_tables.EDGE_AXIS, jnp.int32)[edges]
  owner_bits = plan.edges[owner, owner_voxel].astype(jnp.int32)
  faces = (vertex_start[owner] + plan.vertex_cum[owner, owner_voxel].astype(jnp.int32)
           - edge_count[owner_bits] + jnp.asarray(_EDGES_BELOW)[owner_bits, axis])
  return verts, faces


def _padded(n: int) -> int:
  """The power of two ≥ n (≥ 1): padded sizes, so that inputs of every size compile a few
  programs."""
  return 1 << max(int(n) - 1, 0).bit_length() if n > 0 else 1


def _bucket(n: int) -> int:
  """n rounded up to 8 steps an octave (at most 1/8 above n; powers of two up to 16): the
  meshing buffers' sizes, whose every entry is computed, so a power of two would waste up to
  half the work (16,443 faces → 32,768) for one compile per octave."""
  n = max(int(n), 1)
  if n <= 16:
    return _padded(n)
  step = 1 << (n.bit_length() - 4)
  return -(-n // step) * step


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """`(P, 3) float32` unit area-weighted vertex normals (zero for unreferenced vertices)."""
  v = np.asarray(vertices, np.float64)
  f = np.asarray(faces)
  normals = np.zeros_like(v)
  if len(f):
    # Edge vectors and their cross product one coordinate at a time (the same float64 numbers
    # as np.cross of the (F, 3) edges, without their gathers and copies).
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    i0, i1, i2 = f[:, 0], f[:, 1], f[:, 2]
    ax, ay, az = x[i1] - x[i0], y[i1] - y[i0], z[i1] - z[i0]
    bx, by, bz = x[i2] - x[i0], y[i2] - y[i0], z[i2] - z[i0]
    cross = (ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx)
    # Each face's cross product added to its three corners: one bincount per axis, summing in
    # the order of the corners listed (corner 0 of every face, then 1, then 2).
    corners = f.T.reshape(-1)
    for axis in range(3):
      normals[:, axis] = np.bincount(corners, weights=np.concatenate([cross[axis]] * 3),
                                     minlength=len(v))
  length = np.sqrt(np.einsum("ij,ij->i", normals, normals))[:, None]
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
  plan = _classify(geometry, jnp.float32(min_weight),
                   max_blocks=min(_padded(max(int(geometry.num_blocks), 1)), geometry.capacity))
  num_v, num_f = int(plan.num_vertices), int(plan.num_faces)
  if num_f == 0:
    return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
  verts, faces = _emit(geometry, plan, max_vertices=_bucket(num_v), max_faces=_bucket(num_f))
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
    mesh = label_mesh(mesh, semantic, fill=fill)
  if wanted is not None or bounds is not None:
    keep = np.ones(len(faces), bool)
    if wanted is not None:
      keep &= np.isin(mesh.face_labels, wanted)
    if bounds is not None:
      c = _centroids(vertices, faces)
      keep &= np.all((c >= bounds[0]) & (c <= bounds[1]), axis=-1)
    mesh = _select_faces(mesh, keep)
  return mesh


def label_mesh(mesh: Mesh, state, *, fill: bool = True) -> Mesh:
  """`mesh` with its vertices' and faces' labels, confidence and entropy read from the
  semantic layer of `state` (a MapState), as `extract_mesh` does (docs/equations.md §9.2):
  e.g. one geometry layer's mesh labelled by the maps of several rules.

  Raises:
    ValueError: `state` is not one MapState.
  """
  from jaxfusion.state import MapState   # pylint: disable=import-outside-toplevel
  if not isinstance(state, MapState) or state.keys.ndim != 2:
    raise ValueError("label_mesh needs one MapState (its semantic layer labels the mesh)")
  vertices, faces = mesh.vertices, mesh.faces
  points = np.concatenate([vertices, _centroids(vertices, faces)]).astype(np.float32)
  labels, confidence, entropy = _read_labels(state, points, fill=fill)
  n = len(vertices)
  return mesh._replace(labels=labels[:n], confidence=confidence[:n], entropy=entropy[:n],
                       face_labels=labels[n:])


# Points per round of the fill's nearest-neighbour search (bounds its scratch to ~25 MB).
_FILL_CHUNK = 2**16
# The 26 neighbours of a voxel, x-major then y then z (the tie order of §9.2).
_VOXEL_NEIGHBOURS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1)
                              for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)], np.int32)


_voxel_keys_jit = jax.jit(camera_lib.voxel_keys)


def _point_keys(semantic, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """`(keys (N, 3) int32, in_range (N,) bool)` of world points in the semantic layer: the
  engine's own `voxel_keys` (the same float32 arithmetic as `query`), padded to a power of two
  so that meshes of every size compile a few programs."""
  n = len(points)
  padded = np.zeros((_padded(n), 3), np.float32)
  padded[:n] = points
  keys, in_range = _voxel_keys_jit(padded, semantic.voxel_size)
  return np.asarray(keys)[:n], np.asarray(in_range)[:n]


def _unique_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """`(unique (U, 3) int32, inverse (M,) int64)` of voxel keys `(M, 3) int32`, so that
  `unique[inverse] == keys`. Keys of a mesh fill a compact box: a mark per cell of that box
  finds them in O(M + box) without a sort; a sparse set of keys falls back to `np.unique`."""
  if len(keys) == 0:
    return np.zeros((0, 3), np.int32), np.zeros(0, np.int64)
  lo = keys.min(axis=0).astype(np.int64)
  span = keys.max(axis=0).astype(np.int64) - lo + 1
  cells = int(span[0]) * int(span[1]) * int(span[2])
  if cells >= 2**62:
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    return unique.astype(np.int32), inverse.reshape(-1).astype(np.int64)
  k = keys.astype(np.int64) - lo
  linear = (k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2]
  if cells <= max(4 * len(keys), 1 << 20):
    mark = np.zeros(cells, bool)
    mark[linear] = True
    cell = np.flatnonzero(mark)
    index = np.zeros(cells, np.int64)
    index[cell] = np.arange(len(cell))
    inverse = index[linear]
  else:
    cell, inverse = np.unique(linear, return_inverse=True)
  x, rest = np.divmod(cell, span[1] * span[2])
  y, z = np.divmod(rest, span[2])
  unique = (np.stack([x, y, z], axis=1) + lo).astype(np.int32)
  return unique, inverse.reshape(-1).astype(np.int64)


def _point_codes(semantic, points: np.ndarray) -> np.ndarray:
  """`readout.point_codes_unchecked` of world points `(N, 3)` (padded to a power of two, so
  that meshes of every size compile a few programs): `(N,) int32` the slot of each point's
  voxel where the map holds it, −1 where it does not, −2 out of range."""
  from jaxfusion import readout   # pylint: disable=import-outside-toplevel
  n = len(points)
  padded = np.zeros((_padded(n), 3), np.float32)
  padded[:n] = points
  return np.asarray(readout._point_codes_jit(semantic, padded))[:n]  # pylint: disable=protected-access


def _key_codes(semantic, keys: np.ndarray) -> np.ndarray:
  """`readout.key_codes_unchecked` of voxel keys `(N, 3) int32` (padded; keys beyond the
  engine's range read as out of range)."""
  from jaxfusion import readout   # pylint: disable=import-outside-toplevel
  n = len(keys)
  padded = np.zeros((_padded(n), 3), np.int32)
  padded[:n] = keys
  valid = np.zeros(len(padded), bool)
  valid[:n] = np.all(np.abs(keys.astype(np.int64)) < camera_lib.KEY_LIMIT, axis=1)
  return np.asarray(readout._key_codes_jit(semantic, padded, valid))[:n]  # pylint: disable=protected-access


def _unique_slots(slots: np.ndarray, capacity: int) -> tuple[np.ndarray, np.ndarray]:
  """`(unique (U,) int32, index (C,) int32)` of held slots: the distinct ones in slot order (a
  mark per slot of the table: O(M + C), no sort) and where each sits in that list
  (`unique[index[s]] == s` for every s of `slots`)."""
  mark = np.zeros(capacity, bool)
  mark[slots] = True
  unique = np.flatnonzero(mark).astype(np.int32)
  index = np.zeros(capacity, np.int32)
  index[unique] = np.arange(len(unique), dtype=np.int32)
  return unique, index


def _slot_labels(semantic, unique: np.ndarray) -> tuple:
  """`(labels, confidence, entropy)` of the voxels at `unique (U,)` held slots
  (`readout.slot_labels_unchecked`, padded), as host arrays of U + 1 rows: the last one what a
  point whose voxel is not held reads (−1, 0, the prior's entropy)."""
  from jaxfusion import readout   # pylint: disable=import-outside-toplevel
  u = len(unique)
  padded = np.full(_padded(u + 1), -1, np.int32)
  padded[:u] = unique
  out = readout._slot_labels_jit(semantic, padded)  # pylint: disable=protected-access
  return tuple(np.asarray(x)[:u + 1] for x in out)


def _read_labels(semantic, points: np.ndarray, *, fill: bool) -> tuple:
  """`(labels (N,) int32, confidence (N,) float32, entropy (N,) float32)` of world points from
  the semantic layer, as §9.2 states (with `fill`, an empty voxel reads its nearest neighbour
  in the map).

  What a `query` of every point would give, with the posterior worked out once per distinct
  voxel held: a mesh has several vertices and face centroids in each voxel (about 20 per 10 cm
  voxel at 2 cm meshing). Each point's voxel is looked up in the hash (its slot), the distinct
  slots are found by a mark per slot, and only those are read.
  """
  n = len(points)
  if n == 0:
    return np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0, np.float32)
  codes = _point_codes(semantic, points)
  held = codes >= 0
  missing = np.flatnonzero(codes == -1)                 # in range, but the voxel is not held
  wanted = codes[held]
  near = None
  if fill and len(missing):
    keys = _point_keys(semantic, points[missing])[0]
    holes, hole_of = _unique_keys(keys)
    around = (holes[:, None, :] + _VOXEL_NEIGHBOURS[None]).reshape(-1, 3)
    near = _key_codes(semantic, around).reshape(len(holes), len(_VOXEL_NEIGHBOURS))  # (H, 26)
    wanted = np.concatenate([wanted, near[near >= 0]])
  unique, index = _unique_slots(wanted, semantic.capacity)
  unique_labels, unique_confidence, unique_entropy = _slot_labels(semantic, unique)
  rows = np.full(n, len(unique), np.int64)       # not held or out of range: the last row
  rows[held] = index[codes[held]]
  labels, confidence, entropy = unique_labels[rows], unique_confidence[rows], unique_entropy[rows]
  if near is not None:
    near_found = near >= 0
    # Only points whose empty voxel has a neighbour in the map can be filled.
    has_near = near_found.any(axis=1)[hole_of]
    candidates, hole, keys = missing[has_near], hole_of[has_near], keys[has_near]
    best = np.empty(len(candidates), np.int64)
    for start in range(0, len(candidates), _FILL_CHUNK):
      part = slice(start, start + _FILL_CHUNK)
      best[part] = _nearest_found(keys[part], points[candidates[part]],
                                  near_found[hole[part]], semantic.voxel_size)
    pick = index[near[hole, best]]
    labels[candidates] = unique_labels[pick]
    confidence[candidates] = unique_confidence[pick]
    entropy[candidates] = unique_entropy[pick]
  return labels, confidence, entropy


def _nearest_found(keys: np.ndarray, points: np.ndarray, near_found: np.ndarray,
                   voxel_size) -> np.ndarray:
  """`(M,) int64` which of the 26 neighbours of each point's voxel is nearest to the point
  among those in the map (`near_found (M, 26) bool`, at least one True per row), the first of
  equal distances: distances to the neighbours' centres in float64, rounded to a micrometre,
  so that a point exactly between two centres goes to the first whatever the rounding
  (§9.2). One axis at a time, `(M, 26)` arrays: no `(M, 26, 3)` temporary."""
  size = np.float64(np.float32(voxel_size))
  squared = np.zeros(near_found.shape, np.float64)
  for axis in range(3):
    centre = (keys[:, axis, None] + _VOXEL_NEIGHBOURS[None, :, axis] + 0.5) * size
    delta = centre - points[:, axis, None].astype(np.float64)
    squared += delta * delta
  distance = np.round(np.sqrt(squared), 6)
  distance[~near_found] = np.inf
  return np.argmin(distance, axis=1)


def _centroids(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """`(F, 3)` face centroids, the same numbers as `vertices[faces].mean(axis=1)` (corners
  summed in order, then divided by 3) without the `(F, 3, 3)` gather."""
  if len(faces) == 0:
    return np.zeros((0, 3), vertices.dtype)
  total = vertices[faces[:, 0]] + vertices[faces[:, 1]] + vertices[faces[:, 2]]
  return total / total.dtype.type(3)


def mesh_by_class(state, *, min_weight: float = DEFAULT_MIN_WEIGHT) -> dict:
  """One mesh per class present: `{class: Mesh}` (faces selected by their centroid's class, so
  the meshes partition `extract_mesh(state)`; faces with no semantic voxel are left out)."""
  mesh = extract_mesh(state, min_weight=min_weight)
  if mesh.face_labels is None:
    raise ValueError("mesh_by_class needs a map with a semantic layer (a MapState)")
  return {int(c): _select_faces(mesh, mesh.face_labels == c)
          for c in np.unique(mesh.face_labels) if c >= 0}
