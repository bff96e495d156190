"""Free space for the semantic layer: occupancy log-odds per voxel, projective free-space marking,
and change detection (docs/equations.md §10).

A map made with `init_map(..., free_space=True)` (or a `FreeSpaceConfig`) carries a
`FreeSpaceState`: one occupancy log-odds `L (C,) float32` per slot. In every `fuse_frame`:

    stored voxel centres ──project──► pixel (u, v), depth z, footprint radius r (pixels)
    depth (H, W) ──min-filter pyramid, radii 0, 1, 2, 4, …, 64──► nearest surface in a window
    free  = the whole cube lies in front of every surface its footprint sees, by a margin
    L    += l_hit where the frame's pixels hit the voxel, else l_miss where it is free
    L     = clip(L, l_min, l_max)                              (OctoMap's hit / miss / clamp)

A voxel with `L ≤ l_occ` is free: it is not read out (`state.observed_slots`). A free voxel that
a pixel hits again restarts as a new voxel would (change detection): its rule row returns to the
prior, its hit count to this frame's pixels and L to `l_hit`, so an object that moved in does not
have to outvote what the voxel held before.

The marking pass is O(C) per frame (every stored voxel is projected) plus O(H·W·levels) for the
pyramid; it runs inside the same jitted `fuse_frame`. A map without the layer (the default) is
the same pytree and the same program as before it existed.

Shape legend: C slots, H×W pixels, L pyramid levels.
"""

import dataclasses
import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxfusion import hashing

# The radius of the largest window of the depth pyramid, in pixels (level L has radius 2^(L−1)).
MAX_LEVEL = 7


def _logit(p: float) -> float:
  return math.log(p / (1.0 - p))


@dataclasses.dataclass(frozen=True)
class FreeSpaceConfig:
  """How free space is marked and how occupancy evolves (hashable; static in the program).

  The probabilities are OctoMap's defaults (`OccupancyOcTreeBase`: hit 0.7, miss 0.4, clamping
  0.1192 / 0.971, occupancy threshold 0.5).

  Attributes:
    prob_hit: occupancy probability of a voxel hit by a frame's pixels (> 0.5).
    prob_miss: occupancy probability of a voxel a frame sees as free (< 0.5).
    clamp_min: lower clamp of the occupancy probability.
    clamp_max: upper clamp of the occupancy probability.
    occupancy: threshold above which a voxel is occupied (read out).
    margin: metres by which a voxel's far side must lie in front of the measured surface to be
      free; None: one voxel edge.
  """
  prob_hit: float = 0.7
  prob_miss: float = 0.4
  clamp_min: float = 0.1192
  clamp_max: float = 0.971
  occupancy: float = 0.5
  margin: Optional[float] = None

  def __post_init__(self):
    for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max", "occupancy"):
      value = getattr(self, name)
      if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
        raise ValueError(f"free space {name} must be a probability in (0, 1); got {value!r}")
    if not self.prob_hit > 0.5 > self.prob_miss:
      raise ValueError(f"free space needs prob_hit > 0.5 > prob_miss; got {self.prob_hit} and "
                       f"{self.prob_miss}")
    if not self.clamp_min < self.occupancy < self.clamp_max:
      raise ValueError(f"free space needs clamp_min < occupancy < clamp_max; got "
                       f"{self.clamp_min}, {self.occupancy}, {self.clamp_max}")
    if not self.clamp_min < self.prob_hit <= self.clamp_max:
      raise ValueError(f"prob_hit {self.prob_hit} must lie in (clamp_min, clamp_max]")
    if self.margin is not None and not (isinstance(self.margin, (int, float)) and
                                        math.isfinite(self.margin) and self.margin >= 0):
      raise ValueError(f"free space margin must be a finite number of metres ≥ 0 or None; got "
                       f"{self.margin!r}")

  @property
  def log_hit(self) -> float:
    return _logit(self.prob_hit)

  @property
  def log_miss(self) -> float:
    return _logit(self.prob_miss)

  @property
  def log_min(self) -> float:
    return _logit(self.clamp_min)

  @property
  def log_max(self) -> float:
    return _logit(self.clamp_max)

  @property
  def log_occupied(self) -> float:
    return _logit(self.occupancy)


@struct.dataclass
class FreeSpaceState:
  """The free-space layer of a map: one occupancy log-odds per slot (0 in empty slots)."""
  log_odds: jax.Array       # [C] float32 occupancy log-odds
  config: FreeSpaceConfig = struct.field(pytree_node=False)


def init_free_space(capacity: int, config=True) -> Optional[FreeSpaceState]:
  """The free-space layer of a map of `capacity` slots, or None.

  Args:
    capacity: C.
    config: True (the defaults), a `FreeSpaceConfig`, or False / None (no layer).
  """
  if config is None or config is False:
    return None
  if config is True:
    config = FreeSpaceConfig()
  if not isinstance(config, FreeSpaceConfig):
    raise TypeError(f"free_space must be True, False or a jaxfusion.free_space.FreeSpaceConfig; "
                    f"got {type(config).__name__}")
  return FreeSpaceState(log_odds=jnp.zeros(capacity, jnp.float32), config=config)


def occupied(free: Optional[FreeSpaceState], slots=None) -> Optional[jax.Array]:
  """`(C,) bool`: slots whose occupancy is above the threshold, or only at `slots` (a gather,
  not a pass over C); None without the layer."""
  if free is None:
    return None
  log_odds = free.log_odds if slots is None else free.log_odds[slots]
  return log_odds > free.config.log_occupied


def _min_shifted(x, step: int, axis: int):
  """`min(x[i − step], x[i + step])` along `axis`, indices clamped to the image (edge values
  repeated: a window centred off the image, cut to it, is contained in the window of the
  nearest edge pixel, which is what the min-filter needs). One edge pad; the two slices fuse
  into the minimum."""
  n = x.shape[axis]
  k = min(step, n)
  pad = [(0, 0)] * x.ndim
  pad[axis] = (k, k)
  padded = jnp.pad(x, pad, mode="edge")
  return jnp.minimum(jax.lax.slice_in_dim(padded, 0, n, axis=axis),
                     jax.lax.slice_in_dim(padded, 2 * k, 2 * k + n, axis=axis))


def window_radius(level: int) -> int:
  """The half-width in pixels of pyramid level `level`: 0, 1, 2, 4, …, 2^(level−1)."""
  return 0 if level == 0 else 1 << (level - 1)


def depth_pyramid(depth: jax.Array, levels: int = MAX_LEVEL) -> jax.Array:
  """`(levels + 1, H, W) float32`: level k holds, at each pixel, the smallest valid depth in the
  square window of radius `window_radius(k)` around it, cut to the image. Holes (0, negative,
  non-finite) count as +inf: they see no surface.

  Level k + 1 comes from level k by two shifted minima per axis (windows of radius r at ±r
  cover radius 2r), so the pyramid costs O(H·W) per level."""
  d = jnp.asarray(depth, jnp.float32)
  d = jnp.where(jnp.isfinite(d) & (d > 0), d, jnp.inf)
  out = [d]
  for level in range(1, levels + 1):
    step = 1 if level == 1 else window_radius(level) // 2
    m = out[-1]
    for axis in (0, 1):
      shifted = _min_shifted(m, step, axis)
      m = jnp.minimum(m, shifted) if level == 1 else shifted
    out.append(m)
  return jnp.stack(out)


def free_voxels(keys: jax.Array, voxel_size: jax.Array, depth: jax.Array,
                T_world_cam: jax.Array, camera, margin: jax.Array) -> jax.Array:
  """Which stored voxels a frame's depth shows as free (docs/equations.md §10.1).

  A voxel of edge s with centre c is free when c lies in front of the camera, projects to a
  pixel (u, v) of the image whose depth is valid, and `z_c + s·√3/2 + margin` is smaller than
  every valid depth in the square window of radius ≥ the projected half-diagonal
  `f·s·(√3/2)/z_c` around (u, v) (the largest window, radius 64 pixels, where it would be
  larger): the whole cube lies in front of every surface seen through it.

  Args:
    keys: `(C, 3) int32` voxel keys (EMPTY slots are never free).
    voxel_size: `() float32` s.
    depth: `(H, W)` float depth.
    T_world_cam: `(4, 4)` pose.
    camera: intrinsics.
    margin: `() float32` metres.

  Returns:
    `(C,) bool`.
  """
  depth = jnp.asarray(depth, jnp.float32)
  height, width = depth.shape
  # Materialised once: left to itself XLA may fuse the chain of minima into the gathers below.
  pyramid = jax.lax.optimization_barrier(depth_pyramid(depth))
  s = jnp.asarray(voxel_size, jnp.float32)
  centre = (keys.astype(jnp.float32) + 0.5) * s
  T = jnp.asarray(T_world_cam, jnp.float32)
  R, t = T[:3, :3], T[:3, 3]
  rel = [centre[:, i] - t[i] for i in range(3)]
  x, y, z = (rel[0] * R[0, i] + rel[1] * R[1, i] + rel[2] * R[2, i] for i in range(3))
  half = s * np.float32(math.sqrt(3.0) / 2.0)
  front = z > half
  zs = jnp.where(front, z, 1.0)
  u = jnp.floor(camera.fx * x / zs + camera.cx + 0.5)
  v = jnp.floor(camera.fy * y / zs + camera.cy + 0.5)
  inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
  radius = jnp.maximum(camera.fx, camera.fy) * half / zs
  # The smallest level k ≥ 1 whose window radius 2^(k−1) covers the footprint (the largest
  # where none does): one comparison per level, no logarithm.
  level = jnp.ones_like(radius, dtype=jnp.int32)
  for k in range(1, MAX_LEVEL):
    level = level + (radius > window_radius(k)).astype(jnp.int32)
  pixel = jnp.where(inside, v * width + u, 0.0).astype(jnp.int32)
  centre_depth = pyramid[0].reshape(-1)[pixel]
  nearest = pyramid.reshape(MAX_LEVEL + 1, -1)[level, pixel]
  stored = keys[:, 0] != hashing.EMPTY
  return (stored & inside & jnp.isfinite(centre_depth)
          & (zs + half + jnp.asarray(margin, jnp.float32) < nearest))


def mark(state, depth: jax.Array, T_world_cam: jax.Array, camera) -> jax.Array:
  """`(C,) bool` the voxels of `state` (a MapState with a free-space layer) that the frame
  shows as free. The engine marks after placing the frame's voxels: the new ones are hit, and a
  hit wins (`apply`), so the result is that of marking before."""
  config = state.free_space.config
  margin = state.voxel_size if config.margin is None else jnp.float32(config.margin)
  return free_voxels(state.keys, state.voxel_size, depth, T_world_cam, camera, margin)


def is_free(layer: FreeSpaceState) -> jax.Array:
  """`(C,) bool`: slots at or below the occupancy threshold (free, or never hit: empty)."""
  return ~occupied(layer)


def apply(state, free: jax.Array, slot_of_group: jax.Array):
  """One frame's occupancy update, after its voxels were placed (docs/equations.md §10.2).

  The restart of re-hit free voxels happens in the engine: their hits are counted from 0
  (`fusion._place_groups`) and their rule rows start from the prior (`fusion._rows_update`).

  Args:
    state: the MapState with the frame's voxels placed.
    free: `(C,) bool` from `mark`.
    slot_of_group: `(P,) int32` the slot of each of the frame's voxel groups (C: none).

  Returns:
    The MapState with the new log-odds.
  """
  layer = state.free_space
  config = layer.config
  hit = jnp.zeros(state.capacity, bool).at[slot_of_group].set(True, mode="drop")
  was_free = is_free(layer)
  log_odds = jnp.where(hit, jnp.where(was_free, 0.0, layer.log_odds) + config.log_hit,
                       jnp.where(free, layer.log_odds + config.log_miss, layer.log_odds))
  log_odds = jnp.clip(log_odds, config.log_min, config.log_max)
  return state.replace(free_space=layer.replace(log_odds=log_odds))
