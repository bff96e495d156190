"""A map that grows: fuse frames without choosing the capacity up front.

`fuse_frame` and `fuse_sequence` work on a fixed-capacity map (its arrays are allocated once
and a full map drops voxels, counted). `Mapper` holds a map and, before each frame or stack of
frames, checks whether fusing it could push the load factor past `grow_at`; if so it first
rehashes the map into a table twice as large (or larger) with `grow_map`, which keeps every
posterior, ᾱ and hit count exactly. So a long run never drops a voxel for lack of room, and the
cost per frame stays that of `fuse_frame` between growths (the check is a host-side count in the
common case; see `Mapper.fuse`).

Example:
  >>> mapper = jaxfusion.Mapper(jaxfusion.rules.robust(), num_classes=7, capacity=2**14)
  >>> for frame in frames:
  ...   mapper.fuse(frame, camera)
  >>> voxels = jaxfusion.read_map(mapper.state)

Shape legend: T frames, H×W pixels, K classes, C slots.
"""

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import fusion
from jaxfusion import grouping
from jaxfusion import hashing
from jaxfusion import state as state_lib
from jaxfusion import tsdf as tsdf_lib
from jaxfusion.rules import base as rules_base


@jax.jit
def new_voxel_count(state: state_lib.MapState, depth: jax.Array, T_world_cam: jax.Array,
                    camera: camera_lib.Camera) -> jax.Array:
  """How many voxels not yet in the map a stack of frames would add at most (jittable).

  Counts the distinct voxel keys of the frames' valid-depth pixels that the map does not hold.
  It is an upper bound of what `fuse_sequence` inserts (pixels whose probabilities turn out
  invalid are counted too).

  Args:
    state: the map.
    depth: `(T, H, W)` float depth.
    T_world_cam: `(T, 4, 4)` float poses.
    camera: intrinsics.

  Returns:
    `() int32` the number of new voxels.
  """
  keys, in_range = jax.vmap(camera_lib.depth_to_voxel_keys, in_axes=(0, 0, None, None))(
      depth, T_world_cam, camera, state.voxel_size)
  depth = jnp.asarray(depth, jnp.float32)
  valid = in_range & (depth > 0).reshape(in_range.shape) & jnp.isfinite(depth).reshape(
      in_range.shape)
  keys, valid = keys.reshape(-1, 3), valid.reshape(-1)
  groups = grouping.group_pixels(keys, valid)
  group_keys = keys[groups.first_pixel]
  _, found = hashing.lookup(state.keys, group_keys, max_probes=state.max_probes)
  is_group = jnp.arange(keys.shape[0]) < groups.num_groups
  return jnp.sum(is_group & ~found, dtype=jnp.int32)


def _valid_depth_count(depth) -> int:
  depth = np.asarray(depth)
  return int(np.count_nonzero(np.isfinite(depth) & (depth > 0)))


class Mapper:
  """A map that grows before it could fill up (see the module docstring).

  Args:
    rule: the FusionRule of the map.
    num_classes: K.
    voxel_size: voxel edge in metres.
    capacity: the initial capacity (a power of two).
    grow_at: load factor the map is kept under, in (0, 1). The default, 0.5, keeps the linear
      probes short: in `bench/growth.py` (frames of ~4 800 new, scattered voxels) a map at
      load 0.65 already refused a few insertions at the 64-probe bound, none at ≤ 0.6.
    max_capacity: the largest capacity it may grow to (at most 2**30); beyond it the map stays
      and a full map drops voxels (counted, `MapFullWarning`), as a fixed one does.
    max_probes: the map's probe bound.
    geometry: a `tsdf.TSDFConfig` to carry a geometry layer (None: semantics only); its block
      table grows by the same rule, `grow_at` of its capacity, up to 2**24 blocks.

  Attributes:
    state: the current MapState (a new object after every call; do not keep old ones, they are
      donated to `fuse_frame`).
    growths: `[(frames_fused, old_capacity, new_capacity)]`, one entry per growth.
    geometry_growths: the same for the geometry layer's block table.
    frames_fused: frames fused so far.
  """

  def __init__(self, rule: rules_base.FusionRule, *, num_classes: int,
               voxel_size: float = 0.1, capacity: int = 2**16, grow_at: float = 0.5,
               max_capacity: int = 2**30,
               max_probes: int = state_lib.DEFAULT_MAX_PROBES, geometry=None):
    if not 0.0 < grow_at < 1.0:
      raise ValueError(f"grow_at must lie in (0, 1); got {grow_at}")
    if not isinstance(max_capacity, (int, np.integer)) or max_capacity > 2**30:
      raise ValueError(f"max_capacity must be an int ≤ 2**30; got {max_capacity}")
    self.rule = rule
    self.grow_at = float(grow_at)
    self.max_capacity = int(max_capacity)
    self.state = state_lib.init_map(capacity=capacity, num_classes=num_classes,
                                    voxel_size=voxel_size, rule=rule, max_probes=max_probes,
                                    geometry=geometry)
    # The most blocks one call has added so far: the geometry layer's cheap room check.
    self._blocks_per_call = None
    if self.state.capacity > self.max_capacity:
      raise ValueError(f"capacity {self.state.capacity} exceeds max_capacity {max_capacity}")
    self.growths = []
    self.geometry_growths = []
    self.frames_fused = 0

  @property
  def capacity(self) -> int:
    return self.state.capacity

  def _ensure_room(self, depth, T_world_cam, camera) -> None:
    """Grows the map (and its geometry layer) first if the frames `(T, H, W)` could push it
    past `grow_at`."""
    if self.state.geometry is not None:
      self._ensure_geometry_room(depth, T_world_cam, camera)
    occupied = int(self.state.num_occupied)
    limit = self.grow_at * self.state.capacity
    if occupied + _valid_depth_count(depth) <= limit:
      return   # even if every valid pixel were a new voxel (the usual case: no device work)
    new = int(new_voxel_count(self.state, jnp.asarray(depth, jnp.float32),
                              jnp.asarray(T_world_cam, jnp.float32), camera))
    need = occupied + new
    if need <= limit:
      return
    capacity = self.state.capacity
    while need > self.grow_at * capacity and capacity < self.max_capacity:
      capacity *= 2
    if capacity == self.state.capacity:
      return   # at max_capacity: fuse anyway; what does not fit is dropped and counted
    old = self.state.capacity
    self.state = state_lib.grow_map(self.state, capacity, rule=self.rule)
    self.growths.append((self.frames_fused, old, capacity))

  def _ensure_geometry_room(self, depth, T_world_cam, camera) -> None:
    """Grows the geometry layer's block table before frames that could fill it past
    `grow_at`. The exact count (`tsdf.new_block_count`, a grouping of the frames' ray samples)
    runs only when four times the most blocks a call has added so far could cross the line."""
    geometry = self.state.geometry
    blocks = int(geometry.num_blocks)
    limit = self.grow_at * geometry.capacity
    if self._blocks_per_call is not None and blocks + 4 * self._blocks_per_call <= limit:
      return
    new = int(tsdf_lib.new_block_count(geometry, jnp.asarray(depth, jnp.float32),
                                       jnp.asarray(T_world_cam, jnp.float32), camera))
    self._blocks_per_call = max(self._blocks_per_call or 0, new)
    capacity = geometry.capacity
    while blocks + new > self.grow_at * capacity and capacity < 2**24:
      capacity *= 2
    if capacity != geometry.capacity:
      self.state = self.state.replace(geometry=tsdf_lib.grow_tsdf(geometry, capacity))
      self.geometry_growths.append((self.frames_fused, geometry.capacity, capacity))

  def fuse(self, frame: fusion.Frame, camera: camera_lib.Camera) -> state_lib.MapState:
    """Fuses one frame (`fuse_frame`), growing the map first if it could overfill."""
    if not isinstance(frame, fusion.Frame):
      raise TypeError(f"frame must be a jaxfusion.Frame; got {type(frame).__name__}")
    depth = np.asarray(frame.depth)
    if depth.ndim != 2:
      raise ValueError(f"depth must have shape (H, W); got {depth.shape} (use fuse_sequence "
                       "for a stack)")
    self._ensure_room(depth[None], np.asarray(frame.T_world_cam)[None], camera)
    self.state = fusion.fuse_frame(self.state, frame, camera, self.rule)
    self.frames_fused += 1
    return self.state

  def fuse_sequence(self, frames: fusion.Frame, camera: camera_lib.Camera, *,
                    chunk: Optional[int] = None) -> state_lib.MapState:
    """Fuses a stack of frames (`fuse_sequence`), `chunk` frames per compiled scan (default
    all), growing the map before any chunk that could overfill it."""
    if not isinstance(frames, fusion.Frame):
      raise TypeError(f"frames must be a jaxfusion.Frame; got {type(frames).__name__}")
    depth = np.asarray(frames.depth)
    if depth.ndim != 3:
      raise ValueError(f"depth must have shape (T, H, W); got {depth.shape}")
    total = depth.shape[0]
    step = total if chunk is None else int(chunk)
    if step < 1:
      raise ValueError(f"chunk must be at least 1; got {chunk}")
    for start in range(0, total, step):
      part = jax.tree.map(lambda x, s=start: x[s:s + step], frames)
      self._ensure_room(np.asarray(part.depth), np.asarray(part.T_world_cam), camera)
      self.state = fusion.fuse_sequence(self.state, part, camera, self.rule)
      self.frames_fused += int(np.shape(part.depth)[0])
    return self.state
