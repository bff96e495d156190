"""The geometry layer: a projective truncated signed distance field (TSDF) in hashed blocks.

Space is cut into blocks of b×b×b voxels (b = `block_size`, 8 by default, as in nvblox and
Open3D) of edge `voxel_size` (0.05 m by default, its own, beside the semantic layer's). A block
is stored in a slot of a fixed-capacity spatial hash (`hashing`, the semantic layer's) keyed by
its integer block coordinates; a voxel of it holds a truncated signed distance `sdf` (metres,
positive in front of the surface, clipped to ±τ) and a weight. Blocks that do not fit (the
table is full or the probe bound is reached) are dropped and counted, as voxels are.

One frame (docs/equations.md §8):
    depth (H, W) + pose ──ray samples z ∈ [d − τ, d + τ], every 4th pixel──► block keys
    block keys ──grouping.group_pixels──► U distinct blocks ──hashing.insert──► slots
    every voxel of the U blocks ──project into the image──► sdf = (d − z)·‖p‖/z, clipped
    weighted running average of (sdf, weight), weight capped at `max_weight`

`deintegrate` removes a frame integrated earlier (§8.7): the same blocks found by lookup (none
inserted), the same voxels, observations and weights, the running average inverted; exact where
a voxel's weight never reached `max_weight` (`capped_voxels` counts those that did).

The voxel stage runs U blocks in chunks of a `lax.while_loop`, in place and in time
proportional to U. Reverse-mode AD cannot go through that loop, so its VJP is the same update
written densely over every slot with a mask of the blocks this frame touched (slower, paid only
when differentiating): the TSDF is differentiable in depth and pose wherever the set of voxels,
their pixels and the ±τ clip do not change (§8.5).

Shape legend: B block slots (capacity, a power of two), V = b³ voxels per block, H×W pixels,
N = H·W, S ray samples per pixel, G blocks per chunk.
"""

import dataclasses
import functools
import math
import warnings
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxfusion import camera as camera_lib
from jaxfusion import hashing
from jaxfusion import numerics
from jaxfusion import validation
from jaxfusion.grouping import group_pixels

WEIGHTINGS = ("constant", "inverse_square")
DEFAULT_MAX_PROBES = 64
DEFAULT_BLOCK_STRIDE = 4
# Blocks per round of the voxel stage (G): 64 blocks of 512 voxels, 32 768 voxels a round.
_BLOCK_CHUNK = 64
# Distinct blocks placed per round of the insertion loop.
_INSERT_CHUNK = 2**12
# Voxels whose camera depth is below this are behind (or on) the camera plane and not updated.
_MIN_Z = 1e-4
# Relative margin under τ of the semantic gate: a voxel seen only as free space holds τ up to the
# rounding of the running average, so "|sdf| < τ" is tested as |sdf| < (1 − margin)·τ.
_GATE_MARGIN = 1e-4
# De-integration (§8.7) clears a voxel to (0, 0) where its remaining weight W − w is at most
# min(_DEINTEGRATE_RTOL·w, _DEINTEGRATE_CAP_RTOL·max_weight): above the float32 rounding of the
# running sums of weights (each ≤ max_weight), below any weight another observation could have
# left (an inverse-square weight 10³ times smaller than this frame's is a depth 32 times larger).
_DEINTEGRATE_RTOL = 1e-3
_DEINTEGRATE_CAP_RTOL = 1e-6
# A voxel whose weight is within this relative margin of max_weight counts as capped.
_CAP_MARGIN = 1e-6


class MapFullWarning(UserWarning):
  """Some blocks of the geometry layer were dropped (its table was full)."""


@dataclasses.dataclass(frozen=True)
class TSDFConfig:
  """How to build a geometry layer (hashable: it may be a static argument of `jax.jit`).

  Attributes:
    voxel_size: voxel edge in metres (0.05).
    truncation_voxels: τ in voxels (4): distances are clipped to ±τ·voxel_size.
    capacity: block slots B of the hash (a power of two).
    block_size: voxels per block edge b (8).
    weighting: "constant" (1 per observation, Open3D's) or "inverse_square" (1/d², d the
      measured depth in metres: near observations count more, as nvblox's projective weight).
    max_weight: cap of a voxel's weight (nvblox's `max_weight`); past it the TSDF is a moving
      average that follows changes of the scene.
    max_depth: depths beyond it (metres) are not integrated (inf: none).
    gate_semantics: when True the semantic layer fuses only the pixels whose point lies on the
      surface the TSDF held before the frame: |sdf| < τ there, or not yet observed (§8.6).
    max_probes: bound on the hash's linear probe.
    block_stride: blocks are found from every `block_stride`-th pixel of every
      `block_stride`-th row (4, as Open3D's `compute_unique_block_coordinates`; 1: every
      pixel). Each pixel still updates the voxels that project onto it; a coarser lattice only
      risks missing a block whose band slice falls between its rays (§8.2).
  """
  voxel_size: float = 0.05
  truncation_voxels: float = 4.0
  capacity: int = 2**12
  block_size: int = 8
  weighting: str = "constant"
  max_weight: float = 100.0
  max_depth: float = math.inf
  gate_semantics: bool = False
  max_probes: int = DEFAULT_MAX_PROBES
  block_stride: int = DEFAULT_BLOCK_STRIDE

  def __post_init__(self):
    check_config(self)


def check_config(config: TSDFConfig) -> None:
  """Raises ValueError with one clear line for any field of `config` that cannot work."""
  size = config.voxel_size
  if isinstance(size, bool) or not isinstance(size, (int, float, np.floating, np.integer)) or not (
      math.isfinite(size) and size > 0):
    raise ValueError(f"geometry voxel_size must be a positive finite number of metres; got "
                     f"{size!r}")
  tau = config.truncation_voxels
  if not isinstance(tau, (int, float, np.floating, np.integer)) or not math.isfinite(tau) or (
      tau <= 0):
    raise ValueError(f"truncation_voxels must be a positive number of voxels; got {tau!r}")
  if tau < 1:
    raise ValueError(f"truncation_voxels must be at least 1 (a band thinner than a voxel misses "
                     f"voxels and the mesh has holes); got {tau}")
  b = config.block_size
  if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 2 <= b <= 16:
    raise ValueError(f"block_size must be an integer in [2, 16]; got {b!r}")
  if size * b > 100.0:
    raise ValueError(f"geometry voxel_size {size} m does not fit: a block of {b} voxels would be "
                     f"{size * b:g} m wide (at most 100 m)")
  if tau > 2 * b:
    raise ValueError(f"truncation of {tau} voxels does not fit blocks of {b} voxels: keep τ ≤ "
                     f"{2 * b} voxels")
  cap = config.capacity
  if isinstance(cap, bool) or not isinstance(cap, (int, np.integer)) or cap < 1 or cap & (cap - 1) \
      or cap > 2**24:
    raise ValueError(f"geometry capacity must be a power of two in [1, 2**24] blocks; got {cap!r}")
  if config.weighting not in WEIGHTINGS:
    raise ValueError(f"weighting must be one of {WEIGHTINGS}; got {config.weighting!r}")
  if not (config.max_weight > 0):
    raise ValueError(f"max_weight must be positive; got {config.max_weight!r}")
  if not (config.max_depth > 0):
    raise ValueError(f"max_depth must be positive; got {config.max_depth!r}")
  if not isinstance(config.max_probes, (int, np.integer)) or config.max_probes < 1:
    raise ValueError(f"max_probes must be a positive integer; got {config.max_probes!r}")
  stride = config.block_stride
  if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or not (
      1 <= stride <= 64):
    raise ValueError(f"block_stride must be an integer in [1, 64] pixels; got {stride!r}")


@struct.dataclass
class TSDFState:
  """The geometry layer: a frozen pytree of fixed-capacity arrays. Never mutate it.

  A voxel of a stored block with weight 0 has never been observed; its sdf is 0 and means
  nothing (meshing skips it).
  """
  block_keys: jax.Array     # [B, 3] int32 block coordinates, hashing.EMPTY in unused slots
  claims: jax.Array         # [B] int32 scratch for parallel insertion
  sdf: jax.Array            # [B, V] float32 truncated signed distance in metres, in [−τ, τ]
  weight: jax.Array         # [B, V] float32 accumulated weight, in [0, max_weight]
  num_blocks: jax.Array     # [] int32 blocks stored
  num_dropped: jax.Array    # [] int32 block insertions refused (table full / probe bound)
  voxel_size: jax.Array     # [] float32 voxel edge in metres
  max_weight: jax.Array     # [] float32 weight cap
  max_depth: jax.Array      # [] float32 depth limit in metres
  truncation_voxels: float = struct.field(pytree_node=False)
  block_size: int = struct.field(pytree_node=False)
  weighting: str = struct.field(pytree_node=False)
  gate_semantics: bool = struct.field(pytree_node=False)
  max_probes: int = struct.field(pytree_node=False)
  block_stride: int = struct.field(pytree_node=False)

  @property
  def capacity(self) -> int:
    return self.block_keys.shape[-2]

  @property
  def truncation(self) -> jax.Array:
    """τ in metres."""
    return self.voxel_size * self.truncation_voxels

  @property
  def block_edge(self) -> jax.Array:
    return self.voxel_size * self.block_size

  def config(self) -> TSDFConfig:
    """The TSDFConfig this layer was made from (at its current capacity)."""
    return TSDFConfig(
        voxel_size=float(self.voxel_size), truncation_voxels=self.truncation_voxels,
        capacity=self.capacity, block_size=self.block_size, weighting=self.weighting,
        max_weight=float(self.max_weight), max_depth=float(self.max_depth),
        gate_semantics=self.gate_semantics, max_probes=self.max_probes,
        block_stride=self.block_stride)


def init_tsdf(config: Optional[TSDFConfig] = None, **fields) -> TSDFState:
  """Allocates an empty geometry layer at full capacity.

  Args:
    config: a TSDFConfig; or give its fields as keywords (`init_tsdf(voxel_size=0.02)`).
    **fields: TSDFConfig fields overriding `config`'s.

  Returns:
    A TSDFState with every block slot empty.
  """
  config = dataclasses.replace(config or TSDFConfig(), **fields) if fields else (
      config or TSDFConfig())
  if not isinstance(config, TSDFConfig):
    raise TypeError(f"config must be a jaxfusion.tsdf.TSDFConfig; got {type(config).__name__}")
  voxels = config.block_size**3
  return TSDFState(
      block_keys=hashing.empty_table(config.capacity),
      claims=jnp.zeros(config.capacity, jnp.int32),
      sdf=jnp.zeros((config.capacity, voxels), jnp.float32),
      weight=jnp.zeros((config.capacity, voxels), jnp.float32),
      num_blocks=jnp.zeros((), jnp.int32),
      num_dropped=jnp.zeros((), jnp.int32),
      voxel_size=jnp.asarray(config.voxel_size, jnp.float32),
      max_weight=jnp.asarray(config.max_weight, jnp.float32),
      max_depth=jnp.asarray(config.max_depth, jnp.float32),
      truncation_voxels=float(config.truncation_voxels),
      block_size=int(config.block_size),
      weighting=config.weighting,
      gate_semantics=bool(config.gate_semantics),
      max_probes=int(config.max_probes),
      block_stride=int(config.block_stride),
  )


def voxel_offsets(block_size: int) -> np.ndarray:
  """`(V, 3) int32` offsets of a block's voxels; voxel `i + b·(j + b·k)` sits at `(i, j, k)`."""
  i = np.arange(block_size**3)
  return np.stack([i % block_size, (i // block_size) % block_size, i // block_size**2],
                  axis=-1).astype(np.int32)


def ray_samples(truncation_voxels: float, block_size: int) -> int:
  """S: samples per pixel along [d − τ, d + τ] that find every block the band crosses, spaced at
  most half a block edge apart (3 for τ = 4 voxels and blocks of 8)."""
  return max(2, int(math.ceil(2.0 * truncation_voxels / (0.5 * block_size))) + 1)


def _valid_depth(state: TSDFState, depth: jax.Array) -> jax.Array:
  return jnp.isfinite(depth) & (depth > 0) & (depth <= state.max_depth)


def band_block_keys(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                    camera: camera_lib.Camera) -> tuple[jax.Array, jax.Array]:
  """Block keys of S samples along the ray of every `block_stride`-th pixel of every
  `block_stride`-th row (pixels (u, v) with u, v multiples of the stride), z ∈ [d − τ, d + τ]
  (§8.2).

  Args:
    state: the geometry layer.
    depth: `(H, W)` float32 depth in metres (holes: 0 or non-finite).
    T_world_cam: `(4, 4)` float32 camera-to-world pose.
    camera: intrinsics.

  Returns:
    `(keys (S·n, 3) int32, valid (S·n,) bool)`, n = ⌈H/stride⌉·⌈W/stride⌉ lattice pixels.
  """
  stride = state.block_stride
  depth = jnp.asarray(depth, jnp.float32)[::stride, ::stride]
  T = jnp.asarray(T_world_cam, jnp.float32)
  height, width = depth.shape
  samples = ray_samples(state.truncation_voxels, state.block_size)
  ok = _valid_depth(state, depth)
  d = jnp.where(ok, depth, 1.0)
  rx = (stride * jnp.arange(width, dtype=jnp.float32)[None, :] - camera.cx) / camera.fx
  ry = (stride * jnp.arange(height, dtype=jnp.float32)[:, None] - camera.cy) / camera.fy
  tau = state.truncation
  keys, valid = [], []
  for s in range(samples):
    z = d + tau * (2.0 * s / (samples - 1) - 1.0)
    x, y = rx * z, ry * z
    scaled = [jnp.floor((x * T[i, 0] + y * T[i, 1] + z * T[i, 2] + T[i, 3]) / state.block_edge)
              for i in range(3)]
    in_range = ok & (z > _MIN_Z)
    for c in scaled:
      in_range = in_range & jnp.isfinite(c) & (jnp.abs(c) < camera_lib.KEY_LIMIT // 16)
    keys.append(jnp.stack([jnp.where(in_range, c, 0.0).astype(jnp.int32) for c in scaled], -1))
    valid.append(in_range)
  keys = jnp.stack(keys).reshape(samples * height * width, 3)
  return keys, jnp.stack(valid).reshape(samples * height * width)


def _place_blocks(state: TSDFState, keys, first, num_groups):
  """Finds or inserts the frame's U blocks, `_INSERT_CHUNK` at a time.

  Returns:
    `(state, slot_of_group)`: `(P,) int32` the slot of each group (capacity where dropped or not
    a group), P = `first`'s length, a multiple of `_INSERT_CHUNK`.
  """
  capacity = state.capacity
  chunk = min(_INSERT_CHUNK, first.shape[0])
  lanes = jnp.arange(chunk, dtype=jnp.int32)

  def body(carry):
    c, table, claims, slot_of_group, new, dropped = carry
    start = c * chunk
    rows = jax.lax.dynamic_slice(first, (start,), (chunk,))
    active = start + lanes < num_groups
    placed = hashing.insert(table, claims, keys[rows], active, max_probes=state.max_probes)
    write = jnp.where(placed.found, placed.slots, capacity)
    return (c + 1, placed.table, placed.claims,
            jax.lax.dynamic_update_slice(slot_of_group, write, (start,)),
            new + jnp.sum(placed.is_new, dtype=jnp.int32),
            dropped + jnp.sum(active & ~placed.found, dtype=jnp.int32))

  init = (jnp.zeros((), jnp.int32), state.block_keys, state.claims,
          jnp.full(first.shape[0], capacity, jnp.int32), jnp.zeros((), jnp.int32),
          jnp.zeros((), jnp.int32))
  _, table, claims, slot_of_group, new, dropped = jax.lax.while_loop(
      lambda carry: carry[0] * chunk < num_groups, body, init)
  state = state.replace(block_keys=table, claims=claims, num_blocks=state.num_blocks + new,
                        num_dropped=numerics.saturating_add(state.num_dropped, dropped))
  return state, slot_of_group


def _voxel_observation(block_keys, depth, T_world_cam, camera, params, *, block_size: int,
                       truncation_voxels: float, weighting: str):
  """What one frame observes at every voxel of some blocks (§8.3–8.4), elementwise: the
  selection, the clipped distance and the weight that `integrate` and `deintegrate` share.

  Args:
    block_keys: `(G, 3) int32` the blocks' coordinates.
    depth: `(H, W)` float32.
    T_world_cam: `(4, 4)` float32.
    camera: intrinsics.
    params: `(voxel_size, max_weight, max_depth)` float32 scalars.

  Returns:
    `(seen, s, w)`, `(G, V)` each: `seen` bool, the voxel projects onto a valid pixel with
    distance ≥ −τ; `s` float32 its observation min(η, τ) in metres; `w` float32 its weight
    (meaningful where `seen`).
  """
  voxel_size, _, max_depth = params
  height, width = depth.shape
  tau = voxel_size * truncation_voxels
  offsets = jnp.asarray(voxel_offsets(block_size))
  index = block_keys[:, None, :] * block_size + offsets[None, :, :]          # (G, V, 3) int32
  centre = (index.astype(jnp.float32) + 0.5) * voxel_size
  T = jnp.asarray(T_world_cam, jnp.float32)
  R, t = T[:3, :3], T[:3, 3]
  rel = [centre[..., i] - t[i] for i in range(3)]
  # p_cam = Rᵀ (p_world − t), per coordinate (one fused loop, no (G·V, 3) matrix product).
  x, y, z = (rel[0] * R[0, i] + rel[1] * R[1, i] + rel[2] * R[2, i] for i in range(3))
  front = z > _MIN_Z
  zs = jnp.where(front, z, 1.0)
  u = jnp.floor(camera.fx * x / zs + camera.cx + 0.5)
  v = jnp.floor(camera.fy * y / zs + camera.cy + 0.5)
  inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
  pixel = jnp.where(inside, v * width + u, 0.0).astype(jnp.int32)
  d = depth.reshape(-1)[pixel]
  seen = inside & jnp.isfinite(d) & (d > 0) & (d <= max_depth)
  d = jnp.where(seen, d, zs)
  ray = jnp.sqrt(jnp.where(front, x * x + y * y + z * z, 1.0)) / zs      # ‖p_cam‖ / z ≥ 1
  distance = (d - zs) * ray
  seen = seen & (distance >= -tau)
  s = jnp.minimum(distance, tau)
  w = jnp.ones_like(d) if weighting == "constant" else 1.0 / (d * d)
  return seen, s, w


def _observe_voxels(sdf, weight, block_keys, depth, T_world_cam, camera, params, *,
                    block_size: int, truncation_voxels: float, weighting: str):
  """The projective update of every voxel of some blocks (§8.3–8.4), elementwise.

  Args:
    sdf, weight: `(G, V)` float32 the blocks' current rows.
    block_keys: `(G, 3) int32` their block coordinates.
    depth: `(H, W)` float32.
    T_world_cam: `(4, 4)` float32.
    camera: intrinsics.
    params: `(voxel_size, max_weight, max_depth)` float32 scalars.

  Returns:
    `(sdf, weight)`, `(G, V)` float32 each: the rows after this frame.
  """
  seen, s, w = _voxel_observation(block_keys, depth, T_world_cam, camera, params,
                                  block_size=block_size, truncation_voxels=truncation_voxels,
                                  weighting=weighting)
  max_weight = params[1]
  total = weight + w
  new_sdf = jnp.where(seen, (weight * sdf + w * s) / jnp.where(seen, total, 1.0), sdf)
  new_weight = jnp.where(seen, jnp.minimum(total, max_weight), weight)
  return new_sdf, new_weight


def _unobserve_voxels(sdf, weight, block_keys, depth, T_world_cam, camera, params, *,
                      block_size: int, truncation_voxels: float, weighting: str):
  """`_observe_voxels` inverted (§8.7): the rows before a frame that was integrated, from the
  rows after it. Exact (to rounding) where the weight stayed below `max_weight`.

  Args:
    sdf, weight: `(G, V)` float32 the blocks' current rows.
    block_keys: `(G, 3) int32` their block coordinates.
    depth: `(H, W)` float32, the frame's depth as it was integrated.
    T_world_cam: `(4, 4)` float32, its pose.
    camera: intrinsics.
    params: `(voxel_size, max_weight, max_depth)` float32 scalars.

  Returns:
    `(sdf, weight)`, `(G, V)` float32 each: the rows without this frame; a voxel whose
    remaining weight is at most the tolerance gets exactly `(0, 0)`, never observed.
  """
  seen, s, w = _voxel_observation(block_keys, depth, T_world_cam, camera, params,
                                  block_size=block_size, truncation_voxels=truncation_voxels,
                                  weighting=weighting)
  voxel_size, max_weight, _ = params
  tau = voxel_size * truncation_voxels
  rest = weight - w
  small = jnp.minimum(_DEINTEGRATE_RTOL * w, _DEINTEGRATE_CAP_RTOL * max_weight)
  keep = seen & (rest > small)
  gone = seen & ~keep
  old_sdf = jnp.clip((weight * sdf - w * s) / jnp.where(keep, rest, 1.0), -tau, tau)
  new_sdf = jnp.where(keep, old_sdf, jnp.where(gone, 0.0, sdf))
  new_weight = jnp.where(keep, rest, jnp.where(gone, 0.0, weight))
  return new_sdf, new_weight


def _chunked_update(kernel, sdf, weight, block_keys, slot_of_group, num_groups):
  """Applies `kernel(sdf_rows, weight_rows, key_rows) -> (sdf_rows, weight_rows)` to the blocks
  in slots `slot_of_group[:num_groups]` (capacity: skipped), `_BLOCK_CHUNK` blocks a round of a
  `lax.while_loop`, in place: time proportional to `num_groups`, not to the capacity."""
  capacity = sdf.shape[0]
  chunk = min(_BLOCK_CHUNK, slot_of_group.shape[0])

  def body(carry):
    c, sdf, weight = carry
    slots = jax.lax.dynamic_slice(slot_of_group, (c * chunk,), (chunk,))
    read = jnp.minimum(slots, capacity - 1)
    new_sdf, new_weight = kernel(sdf[read], weight[read], block_keys[read])
    return (c + 1, sdf.at[slots].set(new_sdf, mode="drop"),
            weight.at[slots].set(new_weight, mode="drop"))

  _, sdf, weight = jax.lax.while_loop(lambda carry: carry[0] * chunk < num_groups, body,
                                      (jnp.zeros((), jnp.int32), sdf, weight))
  return sdf, weight


def _voxel_update(static):
  """The voxel stage as `f(sdf, weight, depth, T, camera, params, block_keys, slot_of_group,
  num_groups) -> (sdf, weight)`: a while loop over chunks of the U touched blocks forward, the
  masked dense update over all B slots for the VJP."""
  observe = functools.partial(_observe_voxels, **static)

  def dense(sdf, weight, depth, T, camera, params, block_keys, slot_of_group):
    capacity = sdf.shape[0]
    touched = jnp.zeros(capacity, bool).at[slot_of_group].set(True, mode="drop")
    new_sdf, new_weight = observe(sdf, weight, block_keys, depth, T, camera, params)
    return (jnp.where(touched[:, None], new_sdf, sdf),
            jnp.where(touched[:, None], new_weight, weight))

  @jax.custom_vjp
  def update(sdf, weight, depth, T, camera, params, block_keys, slot_of_group, num_groups):
    kernel = lambda sdf, weight, keys: observe(sdf, weight, keys, depth, T, camera, params)
    return _chunked_update(kernel, sdf, weight, block_keys, slot_of_group, num_groups)

  def fwd(sdf, weight, depth, T, camera, params, block_keys, slot_of_group, num_groups):
    out = update(sdf, weight, depth, T, camera, params, block_keys, slot_of_group, num_groups)
    return out, (sdf, weight, depth, T, camera, params, block_keys, slot_of_group)

  def bwd(residuals, cotangent):
    sdf, weight, depth, T, camera, params, block_keys, slot_of_group = residuals
    _, vjp = jax.vjp(lambda *a: dense(*a, block_keys, slot_of_group), sdf, weight, depth, T,
                     camera, params)
    return vjp(cotangent) + (None, None, None)

  update.defvjp(fwd, bwd)
  return update


class FrameBlocks(NamedTuple):
  """The blocks one frame's band touches, found without reading the block table
  (`frame_blocks`): what `integrate` inserts and `deintegrate` looks up."""
  keys: jax.Array         # (S·n, 3) int32 the block key of every ray sample
  first: jax.Array        # (P,) int32 a sample of each distinct block in row g (padded to whole
                          # insertion chunks; rows ≥ num_groups: 0)
  num_groups: jax.Array   # () int32 U, the distinct blocks


def frame_blocks(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                 camera: camera_lib.Camera) -> FrameBlocks:
  """The block key of every ray sample of the frame's band (§8.2), grouped per block (pure,
  jittable). Reads the layer's settings only, never its arrays, so a layer whose arrays have
  no slots (`settings_only`) gives the same result and a program of it compiles once for every
  capacity."""
  keys, valid = band_block_keys(state, depth, T_world_cam, camera)
  groups = group_pixels(keys, valid)
  n = keys.shape[0]
  chunk = min(_INSERT_CHUNK, n)
  padded = -(-n // chunk) * chunk
  return FrameBlocks(keys, jnp.pad(groups.first_pixel, (0, padded - n)), groups.num_groups)


def settings_only(state: TSDFState) -> TSDFState:
  """The layer with its settings and scalars but table arrays of no slots: what
  `frame_blocks` reads, in a form whose shapes do not change when the layer grows. Every
  array is a copy, so it stays valid when the layer is donated."""
  copy = lambda x: jnp.array(x, copy=True)
  return state.replace(block_keys=state.block_keys[:0], claims=state.claims[:0],
                       sdf=state.sdf[:0], weight=state.weight[:0],
                       num_blocks=copy(state.num_blocks), num_dropped=copy(state.num_dropped),
                       voxel_size=copy(state.voxel_size), max_weight=copy(state.max_weight),
                       max_depth=copy(state.max_depth))


def _voxel_settings(state: TSDFState):
  """`(static, params)` of the voxel stage: the layer's static settings as keywords and its
  traced `(voxel_size, max_weight, max_depth)`."""
  static = dict(block_size=state.block_size, truncation_voxels=state.truncation_voxels,
                weighting=state.weighting)
  return static, (state.voxel_size, state.max_weight, state.max_depth)


def integrate_unchecked(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                        camera: camera_lib.Camera) -> TSDFState:
  """`integrate`'s pure body (no checks, not jitted, nothing donated): for code that composes
  the layer inside its own traced function (`fusion`, a user's `jax.jit`)."""
  depth = jnp.asarray(depth, jnp.float32)
  return integrate_blocks_unchecked(state, frame_blocks(state, depth, T_world_cam, camera), depth,
                                    T_world_cam, camera)


def integrate_blocks_unchecked(state: TSDFState, blocks: FrameBlocks, depth: jax.Array,
                               T_world_cam: jax.Array, camera: camera_lib.Camera) -> TSDFState:
  """The half of `integrate_unchecked` that reads the block table: the frame's blocks
  (`frame_blocks` of the same depth and pose) placed and their voxels updated (§8.3–8.4).
  `integrate_unchecked` is `frame_blocks` then this; the `Mapper` runs them as two programs
  so that a growth recompiles this one only."""
  depth = jnp.asarray(depth, jnp.float32)
  keys, first, num_groups = blocks
  state, slot_of_group = _place_blocks(state, keys, first, num_groups)
  static, params = _voxel_settings(state)
  sdf, weight = _voxel_update(static)(
      state.sdf, state.weight, depth, jnp.asarray(T_world_cam, jnp.float32), camera, params,
      state.block_keys, slot_of_group, num_groups)
  return state.replace(sdf=sdf, weight=weight)


_integrate_donating = jax.jit(integrate_unchecked, donate_argnums=0)
_integrate_copying = jax.jit(integrate_unchecked)
def _integrate_blocks_counted(state, blocks, depth, T_world_cam, camera):
  state = integrate_blocks_unchecked(state, blocks, depth, T_world_cam, camera)
  return state, state.num_blocks


# The table half alone, donated, as `(new layer, () int32 its block count)`: what the `Mapper`
# runs after `frame_blocks` (the count, a buffer of its own, outlives the next donation).
integrate_blocks_donating = jax.jit(_integrate_blocks_counted, donate_argnums=0)


def check_frame_geometry(depth, T_world_cam, camera, *, batch_dims: int = 0) -> None:
  """Shape, dtype and value checks of a depth image and pose (one clear line each)."""
  validation.check_camera(camera)
  depth_shape, pose_shape = np.shape(depth), np.shape(T_world_cam)
  if len(depth_shape) != 2 + batch_dims:
    raise ValueError(f"depth must have {2 + batch_dims} dimensions; got shape {depth_shape}")
  if pose_shape != depth_shape[:batch_dims] + (4, 4):
    raise ValueError(f"T_world_cam must have shape {depth_shape[:batch_dims] + (4, 4)}; got "
                     f"{pose_shape}")
  for name, x in (("depth", depth), ("T_world_cam", T_world_cam)):
    dtype = np.asarray(x).dtype if not hasattr(x, "dtype") else x.dtype
    if not jnp.issubdtype(dtype, jnp.floating):
      raise TypeError(f"{name} must be a float array; got dtype {dtype}")
  if not isinstance(T_world_cam, jax.core.Tracer):
    poses = np.asarray(T_world_cam, np.float64).reshape(-1, 4, 4)
    for pose in poses:
      validation.check_pose_values(pose)


def integrate(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
              camera: camera_lib.Camera) -> TSDFState:
  """Integrates one depth image into the geometry layer (jitted; `state` is donated).

  For a map with both layers call `fuse_frame`, which updates both in one call; this is the
  geometry layer alone. Under a transformation (any argument a tracer) nothing is donated.

  Args:
    state: the layer (from `init_tsdf`). Do not use it after this call.
    depth: `(H, W)` float depth in metres; 0, negative or non-finite marks a hole.
    T_world_cam: `(4, 4)` float camera-to-world pose.
    camera: intrinsics.

  Returns:
    The new TSDFState.
  """
  if not isinstance(state, TSDFState):
    raise TypeError(f"state must be a TSDFState from init_tsdf; got {type(state).__name__}")
  check_frame_geometry(depth, T_world_cam, camera)
  trees = (state, depth, T_world_cam, camera)
  if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trees)):
    return _integrate_copying(state, depth, T_world_cam, camera)
  return _integrate_donating(state, depth, T_world_cam, camera)


def _find_blocks(state: TSDFState, keys, first, num_groups):
  """Looks up the frame's U blocks without inserting, `_INSERT_CHUNK` at a time.

  Returns:
    `(slot_of_found, num_found)`: `(P,) int32` the slots of the stored blocks among the U in
    rows `0 … num_found − 1` (capacity after them), P = `first`'s length; `[] int32` their
    count. Blocks not stored are skipped.
  """
  capacity = state.capacity
  padded = first.shape[0]
  chunk = min(_INSERT_CHUNK, padded)
  lanes = jnp.arange(chunk, dtype=jnp.int32)

  def body(carry):
    c, slot_of_found, count = carry
    start = c * chunk
    rows = jax.lax.dynamic_slice(first, (start,), (chunk,))
    slots, found = hashing.lookup(state.block_keys, keys[rows], max_probes=state.max_probes)
    found = found & (start + lanes < num_groups)
    row = count + jnp.cumsum(found, dtype=jnp.int32) - 1
    slot_of_found = slot_of_found.at[jnp.where(found, row, padded)].set(
        slots, mode="drop", unique_indices=True)
    return c + 1, slot_of_found, count + jnp.sum(found, dtype=jnp.int32)

  init = (jnp.zeros((), jnp.int32), jnp.full(padded, capacity, jnp.int32),
          jnp.zeros((), jnp.int32))
  _, slot_of_found, num_found = jax.lax.while_loop(
      lambda carry: carry[0] * chunk < num_groups, body, init)
  return slot_of_found, num_found


def deintegrate_unchecked(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                          camera: camera_lib.Camera) -> TSDFState:
  """`deintegrate`'s pure body (no checks, not jitted, nothing donated; not differentiable)."""
  depth = jnp.asarray(depth, jnp.float32)
  keys, first, num_groups = frame_blocks(state, depth, T_world_cam, camera)
  slot_of_found, num_found = _find_blocks(state, keys, first, num_groups)
  static, params = _voxel_settings(state)
  T = jnp.asarray(T_world_cam, jnp.float32)
  kernel = lambda sdf, weight, block_keys: _unobserve_voxels(
      sdf, weight, block_keys, depth, T, camera, params, **static)
  sdf, weight = _chunked_update(kernel, state.sdf, state.weight, state.block_keys, slot_of_found,
                                num_found)
  return state.replace(sdf=sdf, weight=weight)


_deintegrate_donating = jax.jit(deintegrate_unchecked, donate_argnums=0)
_deintegrate_copying = jax.jit(deintegrate_unchecked)


def deintegrate(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                camera: camera_lib.Camera) -> TSDFState:
  """Removes a frame integrated earlier from the geometry layer (jitted; `state` is donated).

  The inverse of `integrate` (§8.7): the frame's band blocks are looked up (never inserted;
  blocks not stored are skipped) and every voxel that the frame updated, with the same
  observation `s` and weight `w`, gets `W ← W − w`, `sdf ← (W·sdf − w·s) / (W − w)`; a voxel
  left with weight at most a small tolerance (only this frame saw it) gets exactly
  `sdf = 0, W = 0`, never observed. Blocks stay stored. Give the depth, pose and camera exactly
  as integrated, on the same layer configuration. Voxels whose weight reached `max_weight` are
  not restored exactly (the cap forgot how much weight came before); count them with
  `capped_voxels` first. Not differentiable. Under a transformation nothing is donated.

  Args:
    state: the layer. Do not use it after this call.
    depth: `(H, W)` float depth in metres, the frame's as integrated.
    T_world_cam: `(4, 4)` float camera-to-world pose, as integrated.
    camera: intrinsics, as integrated.

  Returns:
    The TSDFState without this frame.
  """
  if not isinstance(state, TSDFState):
    raise TypeError(f"state must be a TSDFState from init_tsdf; got {type(state).__name__}")
  check_frame_geometry(depth, T_world_cam, camera)
  trees = (state, depth, T_world_cam, camera)
  if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trees)):
    return _deintegrate_copying(state, depth, T_world_cam, camera)
  return _deintegrate_donating(state, depth, T_world_cam, camera)


def capped_voxels(state: TSDFState) -> int:
  """Host-side count of voxels whose weight reached the cap (≥ `max_weight`·(1 − 10⁻⁶)).

  `deintegrate` does not restore these exactly: past the cap the running average no longer
  records how much weight came before. A caller about to de-integrate can warn when it is > 0.

  Args:
    state: one layer (not batched).

  Returns:
    The number of capped voxels, an int.
  """
  if not isinstance(state, TSDFState):
    raise TypeError(f"capped_voxels expects a TSDFState; got {type(state).__name__}")
  if state.weight.ndim != 2:
    raise ValueError("capped_voxels expects one layer; index a batched one first")
  return int(jnp.sum(state.weight >= state.max_weight * (1.0 - _CAP_MARGIN)))


def voxel_of(state: TSDFState, p_world: jax.Array):
  """The voxel holding each world point: `(slots (N,) int32, voxel (N,) int32, found (N,) bool)`
  for `(N, 3)` points (not found: block not stored, or the point not finite)."""
  p = jnp.asarray(p_world, jnp.float32)
  scaled = jnp.floor(p / state.voxel_size)
  ok = jnp.all(jnp.isfinite(scaled) & (jnp.abs(scaled) < camera_lib.KEY_LIMIT), axis=-1)
  index = jnp.where(ok[:, None], scaled, 0.0).astype(jnp.int32)
  b = state.block_size
  block = jnp.floor_divide(index, b)
  local = index - block * b
  slots, found = hashing.lookup(state.block_keys, block, max_probes=state.max_probes)
  voxel = local[:, 0] + b * (local[:, 1] + b * local[:, 2])
  return slots, voxel, found & ok


class SDFQuery(struct.PyTreeNode):
  """What the geometry layer holds at some points (`query_sdf`); `...` the points' shape."""
  sdf: jax.Array       # [...] float32 metres (0 where not observed)
  weight: jax.Array    # [...] float32 (0 where not observed)
  observed: jax.Array  # [...] bool, the voxel is stored with weight > 0


def query_sdf(state: TSDFState, p_world: jax.Array) -> SDFQuery:
  """The TSDF of the voxel that holds each point (nearest voxel, no interpolation; jittable).

  Args:
    state: the geometry layer.
    p_world: `(..., 3)` float world points in metres.

  Returns:
    An SDFQuery of `(...)`-shaped arrays.
  """
  p = jnp.asarray(p_world, jnp.float32)
  lead = p.shape[:-1]
  slots, voxel, found = voxel_of(state, p.reshape(-1, 3))
  sdf = jnp.where(found, state.sdf[slots, voxel], 0.0)
  weight = jnp.where(found, state.weight[slots, voxel], 0.0)
  return SDFQuery(sdf=sdf.reshape(lead), weight=weight.reshape(lead),
                  observed=(weight > 0).reshape(lead))


def surface_gate(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                 camera: camera_lib.Camera) -> jax.Array:
  """`(H·W,) bool`: the pixels whose back-projected point the layer holds on its surface —
  |sdf| < τ, or not observed yet (§8.6). Evaluate it on the layer *before* the frame."""
  p_cam = camera_lib.backproject(jnp.asarray(depth, jnp.float32), camera)
  p_world = camera_lib.transform_points(T_world_cam, p_cam).reshape(-1, 3)
  q = query_sdf(state, p_world)
  near = jnp.abs(q.sdf) < (1.0 - _GATE_MARGIN) * state.truncation
  return ~q.observed | near


def tsdf_stats(state: TSDFState) -> dict:
  """Host-side summary of one layer; warns with MapFullWarning if blocks were dropped.

  Returns:
    dict with `capacity` (blocks), `blocks`, `load_factor`, `dropped`, `voxels` (allocated),
    `observed_voxels` (weight > 0), `voxel_size`, `truncation` (metres), `block_size`,
    `bytes_per_voxel` (the layer's device arrays over its allocated voxels).
  """
  if state.block_keys.ndim != 2:
    raise ValueError("tsdf_stats expects one layer; index a batched one first")
  blocks = int(state.num_blocks)
  dropped = int(state.num_dropped)
  if dropped:
    warnings.warn(f"the geometry layer is full: {dropped} block insertions were dropped "
                  f"(capacity {state.capacity} blocks); make a larger one", MapFullWarning,
                  stacklevel=2)
  voxels = blocks * state.block_size**3
  nbytes = sum(int(x.size) * x.dtype.itemsize for x in jax.tree.leaves(state))
  return {
      "capacity": state.capacity, "blocks": blocks, "load_factor": blocks / state.capacity,
      "dropped": dropped, "voxels": voxels,
      "observed_voxels": int(jnp.sum(state.weight > 0)),
      "voxel_size": float(state.voxel_size), "truncation": float(state.truncation),
      "block_size": state.block_size,
      "bytes_per_voxel": nbytes / voxels if voxels else float("nan"),
  }


@functools.partial(jax.jit, static_argnames=("capacity",))
def grown_tsdf(state: TSDFState, *, capacity: int):
  """`grow_tsdf`'s program (jitted, `capacity` static): the layer rehashed into `capacity`
  block slots, every old slot offered in slot order (the empty ones inactive), so its shapes
  depend on the two capacities only (one compile per pair of sizes).

  Returns:
    `(grown, lost)`: the layer, and `() int32` blocks that found no slot (refused if > 0).
  """
  stored = state.block_keys[:, 0] != hashing.EMPTY
  result = hashing.insert(hashing.empty_table(capacity), jnp.zeros(capacity, jnp.int32),
                          state.block_keys, stored, max_probes=state.max_probes)
  dest = jnp.where(stored & result.found, result.slots, capacity)
  voxels = state.block_size**3
  sdf = jnp.zeros((capacity, voxels), jnp.float32).at[dest].set(state.sdf, mode="drop")
  weight = jnp.zeros((capacity, voxels), jnp.float32).at[dest].set(state.weight, mode="drop")
  lost = jnp.sum(stored & ~result.found, dtype=jnp.int32)
  return state.replace(block_keys=result.table, claims=jnp.zeros(capacity, jnp.int32), sdf=sdf,
                       weight=weight), lost


def _block_arrays(state: TSDFState) -> dict:
  """The arrays with a row per block slot that a rehash moves (the key table among them)."""
  return {"block_keys": state.block_keys, "sdf": state.sdf, "weight": state.weight}


def grows_in_numpy(state: TSDFState, capacity: int) -> bool:
  """Whether `grow_tsdf(state, capacity)` runs entirely in NumPy, compiling nothing: a layer
  in host memory whose grown arrays stay under `hashing.HOST_MOVE_BYTES` (larger ones move
  with one compiled `hashing.moved_rows`)."""
  return hashing.on_host(state.block_keys) and not hashing.moves_on_device(
      capacity, _block_arrays(state))


def grown_tsdf_host(state: TSDFState, *, capacity: int, on_device: Optional[bool] = None):
  """`grown_tsdf` with the rehash in NumPy on the host (`hashing.rehash_host`; what `grow_tsdf`
  runs on the CPU, where it compiles no rehash): `(grown, lost)` as `grown_tsdf`. The blocks
  move as `hashing.grown_rows` moves them: in NumPy, or for large tables (`on_device`; None:
  `hashing.moves_on_device`) with one compiled `hashing.moved_rows`."""
  arrays = _block_arrays(state)
  fills = {"block_keys": hashing.EMPTY, "sdf": 0.0, "weight": 0.0}
  src, dest, lost = hashing.rehash_host(state.block_keys, capacity, max_probes=state.max_probes)
  moved, claims = hashing.grown_rows(arrays, fills, src, dest, capacity=capacity,
                                     on_device=on_device)
  grown = state.replace(block_keys=moved["block_keys"], claims=claims, sdf=moved["sdf"],
                        weight=moved["weight"])
  return grown, lost


def grow_tsdf(state: TSDFState, capacity: int) -> TSDFState:
  """The same layer in a larger table: every block keeps its sdf and weight exactly.

  Not jittable (the capacity is a shape): on the CPU a NumPy rehash (`grown_tsdf_host`,
  nothing compiled), elsewhere one compiled program per old and new capacity (`grown_tsdf`);
  `Mapper` calls it between frames.

  Args:
    state: one layer; not donated.
    capacity: the new number of block slots, a power of two ≥ the current one.

  Returns:
    A TSDFState with `capacity` slots and the same blocks, rows and counters.
  """
  if not isinstance(state, TSDFState):
    raise TypeError(f"grow_tsdf expects a TSDFState; got {type(state).__name__}")
  if state.block_keys.ndim != 2:
    raise ValueError("grow_tsdf expects one layer; index a batched one first")
  if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)) or capacity < 1 \
      or capacity & (capacity - 1) or capacity > 2**24:
    raise ValueError(f"capacity must be a power of two ≤ 2**24; got {capacity!r}")
  if capacity < state.capacity:
    raise ValueError(f"grow_tsdf cannot shrink a layer: capacity {capacity} < {state.capacity}")
  if hashing.on_host(state.block_keys):
    grown, lost = grown_tsdf_host(state, capacity=capacity)
  else:
    grown, lost = grown_tsdf(state, capacity=capacity)
  if int(lost):
    raise ValueError(f"{int(lost)} blocks found no slot within {state.max_probes} probes at "
                     f"capacity {capacity}: grow to a larger one")
  return grown


def _stack_band_keys(state: TSDFState, depth, T_world_cam, camera: camera_lib.Camera):
  """`band_block_keys` of a stack of frames `(T, H, W)`, flattened: `(keys (T·S·n, 3) int32,
  valid (T·S·n,) bool)`, what both room checks below look up."""
  keys, valid = jax.vmap(band_block_keys, in_axes=(None, 0, 0, None))(
      state, jnp.asarray(depth, jnp.float32), jnp.asarray(T_world_cam, jnp.float32), camera)
  return keys.reshape(-1, 3), valid.reshape(-1)


@jax.jit
def new_block_count(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                    camera: camera_lib.Camera) -> jax.Array:
  """How many blocks not yet stored a stack of frames `(T, H, W)` would add (jittable)."""
  keys, valid = _stack_band_keys(state, depth, T_world_cam, camera)
  groups = group_pixels(keys, valid)
  _, found = hashing.lookup(state.block_keys, keys[groups.first_pixel],
                            max_probes=state.max_probes)
  return jnp.sum((jnp.arange(keys.shape[0]) < groups.num_groups) & ~found, dtype=jnp.int32)


@jax.jit
def _missing_samples(state: TSDFState, depth: jax.Array, T_world_cam: jax.Array,
                     camera: camera_lib.Camera):
  """`(keys (S·n·T, 3) int32, missing (S·n·T,) bool)`: the block key of every ray sample of a
  stack of frames and whether the layer lacks it (a lookup per sample, no grouping)."""
  keys, valid = _stack_band_keys(state, depth, T_world_cam, camera)
  _, found = hashing.lookup(state.block_keys, keys, max_probes=state.max_probes)
  return keys, valid & ~found


def count_new_blocks(state: TSDFState, depth, T_world_cam, camera: camera_lib.Camera) -> int:
  """`new_block_count` on the host side, cheaper for a few frames: every ray sample looked up
  (one small program), the distinct keys of the missing ones counted by NumPy. A frame samples
  a few thousand keys, of which few are new; the grouping `new_block_count` runs instead has a
  fixed cost of its own (a grid fill a round). Not jittable; the same number."""
  keys, missing = _missing_samples(state, depth, T_world_cam, camera)
  missing = np.asarray(missing)
  if not missing.any():
    return 0
  return len(np.unique(np.asarray(keys)[missing], axis=0))
