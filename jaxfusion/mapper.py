"""A map that grows: fuse frames without choosing the capacity up front.

`fuse_frame` and `fuse_sequence` work on a fixed-capacity map (its arrays are allocated once
and a full map drops voxels, counted). `Mapper` holds a map and, before each frame or stack of
frames, checks whether fusing it could push the load factor past `grow_at`; if so it first
rehashes the map into a table `growth_factor` times as large with `grow_map`, which keeps every
posterior, ᾱ and hit count exactly. So a long run never drops a voxel for lack of room, and the
cost per frame stays near that of `fuse_frame` between growths: the check is host-side arithmetic
in the common case, and it waits for no frame still running, so a plain loop of `Mapper.fuse`
prepares a frame while the one before computes, as one of `fuse_frame` does (see
`Mapper._fuse_prepared`).

A growth is cheap because little is compiled for the new size: `Mapper.fuse` runs a frame as
its capacity-free half (`fusion.prepare_frame`: projection and grouping, compiled once) and
each table's half (placement and update, a smaller program per capacity), and on the CPU the
rehash and the exact room counts run in NumPy on the tables in place (`state.grown_map_host`,
`hashing.lookup_host`), compiling nothing; the grown half compiles while a worker thread
rehashes (`_grown_while_compiling`). bench/RESULTS.md, "A map that grows over a long walk", has
the measurements.

Example:
  >>> mapper = jaxfusion.Mapper(jaxfusion.rules.robust(), num_classes=7, capacity=2**14)
  >>> for frame in frames:
  ...   mapper.fuse(frame, camera)
  >>> voxels = jaxfusion.read_map(mapper.state)

Shape legend: T frames, H×W pixels, K classes, C slots.
"""

import collections
import concurrent.futures
import functools
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import deintegration
from jaxfusion import fusion
from jaxfusion import grouping
from jaxfusion import hashing
from jaxfusion import state as state_lib
from jaxfusion import tsdf as tsdf_lib
from jaxfusion.rules import base as rules_base


@jax.jit
def _frame_voxel_groups(depth: jax.Array, T_world_cam: jax.Array, camera: camera_lib.Camera,
                        voxel_size) -> tuple[jax.Array, jax.Array]:
  """`(keys (T·N, 3) int32, is_group (T·N,) bool)`: a key of each distinct voxel the
  valid-depth pixels of a stack of frames `(T, H, W)` fall in, in the first rows. Independent
  of the map: it compiles once whatever the capacity."""
  keys, in_range = jax.vmap(camera_lib.depth_to_voxel_keys, in_axes=(0, 0, None, None))(
      depth, T_world_cam, camera, voxel_size)
  depth = jnp.asarray(depth, jnp.float32)
  valid = in_range & (depth > 0).reshape(in_range.shape) & jnp.isfinite(depth).reshape(
      in_range.shape)
  keys, valid = keys.reshape(-1, 3), valid.reshape(-1)
  groups = grouping.group_pixels(keys, valid)
  return keys[groups.first_pixel], jnp.arange(keys.shape[0]) < groups.num_groups


def new_voxel_count(state: state_lib.MapState, depth: jax.Array, T_world_cam: jax.Array,
                    camera: camera_lib.Camera) -> jax.Array:
  """How many voxels not yet in the map a stack of frames would add at most (jittable).

  Counts the distinct voxel keys of the frames' valid-depth pixels that the map does not hold.
  It is an upper bound of what `fuse_sequence` inserts (pixels whose probabilities turn out
  invalid are counted too). Two programs: the frames' distinct voxels (compiled once whatever
  the capacity) and their lookup (`hashing.count_missing`, a small program per capacity), so a
  growing map recompiles only the small one.

  Args:
    state: the map.
    depth: `(T, H, W)` float depth.
    T_world_cam: `(T, 4, 4)` float poses.
    camera: intrinsics.

  Returns:
    `() int32` the number of new voxels.
  """
  keys, is_group = _frame_voxel_groups(depth, T_world_cam, camera, state.voxel_size)
  return hashing.count_missing(state.keys, keys, is_group, max_probes=state.max_probes)


def _missing(table: jax.Array, keys: jax.Array, first: jax.Array, num_groups: jax.Array, *,
             max_probes: int) -> int:
  """How many of the groups `keys[first[g]]`, g < num_groups, the table `(C, 3)` lacks: a
  prepared frame's exact count of new voxels or blocks. A table in host memory (the CPU) is
  read in place by NumPy (`hashing.lookup_host`: nothing to compile for a new capacity);
  elsewhere it is `hashing.count_missing`, a small program per capacity."""
  if hashing.on_host(table):
    count = _read(num_groups)
    rows = np.asarray(first)[:count]
    _, found = hashing.lookup_host(table, np.asarray(keys)[rows], max_probes=max_probes)
    return int(count - np.count_nonzero(found))
  is_group = jnp.arange(first.shape[0]) < num_groups
  return _read(hashing.count_missing(table, keys[first], is_group, max_probes=max_probes))


# How many of the latest calls the geometry layer's cheap room check remembers, and the load
# a block table may reach if a call adds more than that check expects (bench/growth.py: frames
# of ~4 800 new blocks or voxels, none refused at the 64-probe bound at load ≤ 0.6).
_RECENT_CALLS = 32
_SAFE_LOAD = 0.6


class _InFlight(NamedTuple):
  """A staged frame dispatched whose tables' counts the `Mapper` has not read yet."""
  occupied: jax.Array                 # () int32 the semantic table's count after the frame
  blocks: Optional[jax.Array]         # () int32 the block table's, or None (no geometry layer)
  touched: jax.Array                  # () int32 voxels the frame touches (its preparation's)
  voxels: int                         # its pixels: at most the voxels it adds
  most_blocks: int                    # its ray samples' blocks: at most the blocks it adds


def _is_ready(x: jax.Array) -> bool:
  """Whether a device value is computed (reading it would not wait)."""
  return x.is_ready()


def _read(x: jax.Array) -> int:
  """A device count as a Python int: every read the room checks make (it waits until the
  count is computed)."""
  return int(x)


# Whether a growth on the CPU compiles the grown table's half while a worker thread rehashes
# (`_grown_while_compiling`); False: one after the other (the comparison of bench/growth.py).
_COMPILE_WHILE_GROWING = True


def _grown_while_compiling(grow, compile_half):
  """`grow()`'s result (a table rehashed into its new capacity, in NumPy) computed on a worker
  thread while this thread runs `compile_half()` (the grown table's half of a frame compiled
  for the shapes the rehash will have): the two costs of a growth on the CPU, overlapped. An
  error of either is raised here, after both have finished."""
  if not _COMPILE_WHILE_GROWING:
    grown = grow()
    compile_half()
    return grown
  with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="jaxfusion-growth") as pool:
    future = pool.submit(grow)
    compile_half()
    return future.result()


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
    free_space: free-space clearing (`init_map`'s option, docs/equations.md §10).
    growth_factor: how many times larger each growth makes a table (2, 4 or 8). A growth's
      cost is mostly compiling the grown table's half of a frame for the new size, so fewer,
      larger growths cost less (8 leaves tables as little as 1/16 full); JAX's persistent
      compilation cache (which the `jaxfusion` commands turn on) makes a repeat run's growths
      a fraction of that. The measurements: bench/RESULTS.md, "A map that grows over a long
      walk" (`bench/growth.py`).
    keep_frames: how many of the latest fused frames to keep on the host (0: none), so that
      `unfuse`, `reintegrate` and `rebuild` can undo or move them (docs/equations.md §11.3).
      A frame costs its arrays' size (a 640×480 frame with K = 13 probabilities and variances:
      about 33 MB).

  Attributes:
    state: the current MapState (a new object after every call; do not keep old ones, they are
      donated to `fuse_frame`).
    growths: `[(frames_fused, old_capacity, new_capacity)]`, one entry per growth.
    geometry_growths: the same for the geometry layer's block table.
    frames_fused: frames fused so far.
    kept: the frames held, `{frame_id: (Frame, Camera)}` in the order fused (oldest first).
  """

  def __init__(self, rule: rules_base.FusionRule, *, num_classes: int,
               voxel_size: float = 0.1, capacity: int = 2**16, grow_at: float = 0.5,
               max_capacity: int = 2**30,
               max_probes: int = state_lib.DEFAULT_MAX_PROBES, geometry=None,
               free_space=False, keep_frames: int = 0, growth_factor: int = 4):
    if not 0.0 < grow_at < 1.0:
      raise ValueError(f"grow_at must lie in (0, 1); got {grow_at}")
    if not isinstance(max_capacity, (int, np.integer)) or max_capacity > 2**30:
      raise ValueError(f"max_capacity must be an int ≤ 2**30; got {max_capacity}")
    if isinstance(keep_frames, bool) or not isinstance(keep_frames, (int, np.integer)) or (
        keep_frames < 0):
      raise ValueError(f"keep_frames must be an integer ≥ 0; got {keep_frames!r}")
    if growth_factor not in (2, 4, 8):
      raise ValueError(f"growth_factor must be 2, 4 or 8; got {growth_factor!r}")
    self.rule = rule
    self.growth_factor = int(growth_factor)
    self.keep_frames = int(keep_frames)
    self.kept = collections.OrderedDict()
    self._free_space = free_space
    self.grow_at = float(grow_at)
    self.max_capacity = int(max_capacity)
    self.state = state_lib.init_map(capacity=capacity, num_classes=num_classes,
                                    voxel_size=voxel_size, rule=rule, max_probes=max_probes,
                                    geometry=geometry, free_space=free_space)
    # Blocks the latest calls added (the geometry layer's cheap room check) and the layer's
    # block count when the last one started.
    self._recent_blocks = collections.deque(maxlen=_RECENT_CALLS)
    self._most_blocks = 0
    self._blocks_before = None
    # The staged frames whose counts are not read yet and the counts before them (`_counts`);
    # they describe `state` while `_counted` (setting `state` clears it).
    self._in_flight = collections.deque()
    self._known = (0, None)
    self._counted = False
    if self.state.capacity > self.max_capacity:
      raise ValueError(f"capacity {self.state.capacity} exceeds max_capacity {max_capacity}")
    # The geometry layer's settings for `fusion.prepare_frame` (None: fuse frames as one
    # `fuse_frame`, which a gate_semantics layer needs).
    layer = self.state.geometry
    self._staged = layer is None or not layer.gate_semantics
    self._settings = None if layer is None else tsdf_lib.settings_only(layer)
    self._camera = (None, None)   # the last Camera fused and its device copy
    self.growths = []
    self.geometry_growths = []
    self.frames_fused = 0

  @property
  def state(self) -> state_lib.MapState:
    return self._state

  @state.setter
  def state(self, state: state_lib.MapState) -> None:
    self._state = state
    self._counted = False      # a map set from outside `_fuse_prepared` is counted afresh

  @property
  def capacity(self) -> int:
    return self.state.capacity

  def _ensure_room(self, depth, T_world_cam, camera) -> None:
    """Grows the map (and its geometry layer) first if the frames `(T, H, W)` could push it
    past `grow_at`."""
    if self.state.geometry is not None:
      self._ensure_geometry_room(depth, T_world_cam, camera)
    occupied = _read(self.state.num_occupied)
    limit = self.grow_at * self.state.capacity
    if occupied + _valid_depth_count(depth) <= limit:
      return   # even if every valid pixel were a new voxel (the usual case: no device work)
    new = _read(new_voxel_count(self.state, jnp.asarray(depth, jnp.float32),
                              jnp.asarray(T_world_cam, jnp.float32), camera))
    if occupied + new > limit:
      self._grow_for(occupied + new)

  def _ensure_geometry_room(self, depth, T_world_cam, camera, prepared=None,
                            blocks=None, in_flight=0) -> bool:
    """Grows the geometry layer's block table before frames that could fill it past
    `grow_at`. The count of the blocks the frames add is skipped when even a call whose every
    ray sample found a new block stays under `grow_at`, or when four times the most blocks one
    of the last `_RECENT_CALLS` calls added does and four times the most any call has added
    would still leave the table under `_SAFE_LOAD` (the calls' blocks are read from the
    layer's block count: the first frame's, all new, set the safety margin but not the
    everyday one). The count is exact: of a `prepared` frame, the blocks it touches and, if
    those could overfill the table, the ones the table lacks (`_missing`); of a stack, every
    ray sample looked up (`tsdf.count_new_blocks`). `blocks`: the layer's block count, when
    the caller has read it, or a bound of it (`in_flight`: the count before frames still in
    flight plus a bound of what they add, `Mapper._bounds`).

    Returns:
      False when the bounds leave the question open and frames are in flight (the exact count
      needs their blocks: the caller reads them and asks again), else True.
    """
    geometry = self.state.geometry
    if blocks is None:
      blocks = _read(geometry.num_blocks)
      self._note_blocks(blocks)
    limit = self.grow_at * geometry.capacity
    most = self._most_new_blocks(depth)
    if blocks + most <= limit:
      return True
    if (self._recent_blocks and blocks + 4 * max(max(self._recent_blocks), 1) <= limit
        and blocks + 4 * self._most_blocks <= max(_SAFE_LOAD, self.grow_at) * geometry.capacity):
      return True
    if in_flight:
      return False
    if prepared is None:
      new = tsdf_lib.count_new_blocks(geometry, jnp.asarray(depth, jnp.float32),
                                      jnp.asarray(T_world_cam, jnp.float32), camera)
    else:
      touched = prepared.blocks
      new = _read(touched.num_groups)
      if blocks + new > limit:
        new = _missing(geometry.block_keys, touched.keys, touched.first, touched.num_groups,
                       max_probes=geometry.max_probes)
    self._most_blocks = max(self._most_blocks, new)
    capacity = geometry.capacity
    while blocks + new > self.grow_at * capacity and capacity < 2**24:
      capacity = min(capacity * self.growth_factor, 2**24)
    if capacity != geometry.capacity:
      grow = functools.partial(tsdf_lib.grow_tsdf, geometry, capacity)
      if prepared is not None and tsdf_lib.grows_in_numpy(geometry, capacity):
        shape = jax.eval_shape(functools.partial(tsdf_lib.grown_tsdf, capacity=capacity),
                               geometry)[0]
        frame = prepared.frame
        grown = _grown_while_compiling(grow, lambda: tsdf_lib.integrate_blocks_donating.lower(
            shape, prepared.blocks, frame.depth, frame.T_world_cam, self._camera[1]).compile())
      else:
        grown = grow()
      self.state = self.state.replace(geometry=grown)
      self.geometry_growths.append((self.frames_fused, geometry.capacity, capacity))
    return True

  def _most_new_blocks(self, depth) -> int:
    """The blocks frames `(T, H, W)` could add at most: every ray sample a new block."""
    geometry = self.state.geometry
    frames, height, width = np.shape(depth)
    stride = geometry.block_stride
    return frames * tsdf_lib.ray_samples(geometry.truncation_voxels, geometry.block_size) * (
        -(-height // stride)) * (-(-width // stride))

  def _note_blocks(self, blocks: int) -> None:
    """Records the blocks the last call added, from the layer's count `blocks` after it."""
    if self._blocks_before is not None:
      added = max(blocks - self._blocks_before, 0)
      self._recent_blocks.append(added)
      self._most_blocks = max(self._most_blocks, added)
    self._blocks_before = blocks

  def _counts(self, keep: int = 1) -> tuple:
    """`(occupied, blocks, in_flight)`: the tables' exact counts before the staged frames
    still in flight (`_InFlight`, oldest first; `blocks` None without a geometry layer).
    Reads the counts of the frames already computed, and of the older ones until at most
    `keep` are left (waiting for their programs to finish: with `keep=1`, the frame before
    the latest, which has had the latest's host work to finish in). A map this `Mapper` did
    not leave (another call or the user replaced `state`) is read afresh."""
    geometry = self.state.geometry
    if not self._counted:
      self._in_flight.clear()
      self._known = (_read(self.state.num_occupied),
                     None if geometry is None else _read(geometry.num_blocks))
      if geometry is not None:
        self._note_blocks(self._known[1])
      self._counted = True
    while self._in_flight:
      frame = self._in_flight[0]
      if len(self._in_flight) <= keep and not all(
          _is_ready(x) for x in frame[:2] if x is not None):
        break
      self._in_flight.popleft()
      self._known = (_read(frame.occupied),
                     None if frame.blocks is None else _read(frame.blocks))
      if frame.blocks is not None:
        self._note_blocks(self._known[1])
    return self._known + (tuple(self._in_flight),)

  def fuse(self, frame: fusion.Frame, camera: camera_lib.Camera, *,
           frame_id=None) -> state_lib.MapState:
    """Fuses one frame (as `fuse_frame`), growing the map first if it could overfill.

    The frame runs as two or three programs (`fusion.prepare_frame`, then the semantic and
    geometry tables' halves: see `fusion.PreparedFrame`), so a growth recompiles only the
    grown table's half; with a `gate_semantics` geometry layer it runs as one `fuse_frame`.
    The result is `fuse_frame`'s. The call returns once the frame is dispatched (JAX's
    asynchronous dispatch); it waits for the frame two before it (the host stays one frame
    ahead), and for the one before only when the room check cannot be settled without that
    frame's counts.

    `frame_id` names the frame for `unfuse` / `reintegrate` when frames are kept (default: the
    number of frames fused before it)."""
    if not isinstance(frame, fusion.Frame):
      raise TypeError(f"frame must be a jaxfusion.Frame; got {type(frame).__name__}")
    depth = np.asarray(frame.depth)
    if depth.ndim != 2:
      raise ValueError(f"depth must have shape (H, W); got {depth.shape} (use fuse_sequence "
                       "for a stack)")
    frame_id = self._new_id(frame_id, self.frames_fused)
    if not self._staged:
      self._ensure_room(depth[None], np.asarray(frame.T_world_cam)[None], camera)
      self.state = fusion.fuse_frame(self.state, frame, camera, self.rule)
    else:
      self._fuse_prepared(frame, depth, camera)
    self.frames_fused += 1
    self._keep(frame_id, frame, camera)
    return self.state

  def _fuse_prepared(self, frame: fusion.Frame, depth: np.ndarray, camera) -> None:
    """`fuse`'s staged path: prepare the frame (compiled once), make room by what it touches,
    then run each table's half.

    The room check waits for nothing while its bounds settle it: the tables' counts are
    those of the frames already computed, and each frame still in flight counts as adding the
    voxels its preparation found (its pixels until that has run) and blocks by the geometry
    layer's expectation (`_bounds`). So in a plain loop the host prepares a frame while the
    one before still runs, as with `fuse_frame`. Only a frame the bounds cannot place waits
    for the counts of the frame before it."""
    check = fusion._check_inputs   # pylint: disable=protected-access
    check(self.state, frame, camera, self.rule, batch_dims=0, sample=True)
    occupied, blocks, in_flight = self._counts()
    if camera is not self._camera[0]:
      # Its scalars as device arrays once, not converted by each of three programs per frame.
      self._camera = (camera, jax.tree.map(jnp.float32, camera))
    camera = self._camera[1]
    prepared = fusion.prepare_frame(self.state.voxel_size, frame, camera, self.rule,
                                    self._settings)
    if not self._make_room(prepared, occupied, blocks, depth, in_flight):
      occupied, blocks, in_flight = self._counts(keep=0)
      self._make_room(prepared, occupied, blocks, depth, in_flight)
    geometry, frame = self.state.geometry, prepared.frame
    state, occupied = fusion.fuse_prepared_donating(self.state.replace(geometry=None),
                                                    prepared, camera, self.rule)
    most_blocks = 0
    if geometry is not None:
      most_blocks = self._most_new_blocks(depth[None])
      geometry, blocks = tsdf_lib.integrate_blocks_donating(
          geometry, prepared.blocks, frame.depth, frame.T_world_cam, camera)
    self.state = state.replace(geometry=geometry)
    self._counted = True
    self._in_flight.append(_InFlight(occupied, None if geometry is None else blocks,
                                     prepared.groups.num_groups, depth.size, most_blocks))

  def _bounds(self, in_flight: tuple) -> tuple:
    """`(voxels, blocks)`: what the frames `in_flight` add to the tables, without waiting.
    Voxels at most: those a frame touches once its preparation has run (it usually has while
    its tables' halves still run), else its pixels. Blocks as the geometry layer's room
    check expects of a call (`_ensure_geometry_room`: four times the most one of the recent
    calls added), at most its ray samples."""
    voxels = blocks = 0
    expected = 4 * max(max(self._recent_blocks), 1) if self._recent_blocks else None
    for frame in in_flight:
      voxels += _read(frame.touched) if _is_ready(frame.touched) else frame.voxels
      blocks += frame.most_blocks if expected is None else min(frame.most_blocks, expected)
    return voxels, blocks

  def _make_room(self, prepared: fusion.PreparedFrame, occupied: int, blocks: Optional[int],
                 depth: np.ndarray, in_flight: tuple) -> bool:
    """Grows a table before a prepared frame that could push it past `grow_at`. In turn, until
    one leaves room: a host-side bound (every valid pixel a new voxel, every ray
    sample a new block; for the geometry layer also the recent frames' additions: no device
    work), the voxels and blocks the frame touches (its preparation's counts), and the exact
    count of those the table lacks (`_missing`, a small program per capacity). `occupied`
    and `blocks` are the tables' counts before the frames `in_flight`, whose additions
    `_bounds` adds. Returns False, having changed nothing, when only exact counts can settle
    it and frames are in flight (the caller then reads them, waiting, and asks again)."""
    added, added_blocks = self._bounds(in_flight)
    if self.state.geometry is not None:
      # The pose and camera serve the stack's count only; a prepared frame has its own.
      if not self._ensure_geometry_room(depth[None], None, None, prepared,
                                        blocks + added_blocks, in_flight=len(in_flight)):
        return False
    limit = self.grow_at * self.state.capacity
    if (occupied + added + depth.size <= limit
        or occupied + added + _valid_depth_count(depth) <= limit):
      return True
    if in_flight:
      return False
    groups = prepared.groups
    if occupied + _read(groups.num_groups) <= limit:
      return True
    first = groups.first_pixel[:prepared.counts.shape[0]]
    self._grow_for(occupied + _missing(self.state.keys, prepared.keys, first, groups.num_groups,
                                       max_probes=self.state.max_probes), prepared)
    return True

  def _grow_for(self, need: int, prepared: Optional[fusion.PreparedFrame] = None) -> None:
    """Grows the semantic table until `need` voxels stay under `grow_at` of it (or it reaches
    `max_capacity`: then what does not fit is dropped and counted). Before a `prepared` frame
    on the CPU, its half for the new capacity compiles while the table is rehashed
    (`_grown_while_compiling`)."""
    capacity = self.state.capacity
    while need > self.grow_at * capacity and capacity < self.max_capacity:
      capacity = min(capacity * self.growth_factor, self.max_capacity)
    if capacity == self.state.capacity:
      return
    old, state = self.state.capacity, self.state
    grow = functools.partial(state_lib.grow_map, state, capacity, rule=self.rule)
    if prepared is not None and state_lib.grows_in_numpy(state, capacity):
      semantic = state.replace(geometry=None)
      shape = jax.eval_shape(functools.partial(state_lib.grown_map, capacity=capacity),
                             semantic, state_lib.prior_row(semantic, self.rule))[0]
      self.state = _grown_while_compiling(grow, lambda: fusion.fuse_prepared_donating.lower(
          shape, prepared, self._camera[1], self.rule).compile())
    else:
      self.state = grow()
    self.growths.append((self.frames_fused, old, capacity))

  # --- kept frames: de-integration, re-integration, rebuild (docs/equations.md §11.3) -------
  def _new_id(self, frame_id, default):
    frame_id = default if frame_id is None else frame_id
    if self.keep_frames and frame_id in self.kept:
      raise ValueError(f"frame id {frame_id!r} is already held by this Mapper")
    return frame_id

  def _keep(self, frame_id, frame: fusion.Frame, camera) -> None:
    if not self.keep_frames:
      return
    host = fusion.Frame(*(None if x is None else np.array(x) for x in frame))
    self.kept[frame_id] = (host, camera)
    while len(self.kept) > self.keep_frames:
      self.kept.popitem(last=False)

  def _held(self, frame_ids) -> list:
    if not self.keep_frames:
      raise ValueError("this Mapper keeps no frames: make it with keep_frames=N to unfuse or "
                       "reintegrate them")
    ids = list(frame_ids)
    for frame_id in ids:
      if frame_id not in self.kept:
        raise ValueError(f"frame id {frame_id!r} is not held by this Mapper (it holds the last "
                         f"{len(self.kept)} of {self.frames_fused} frames fused, keep_frames="
                         f"{self.keep_frames})")
    if len(set(ids)) != len(ids):
      raise ValueError(f"frame ids repeat: {ids}")
    return ids

  def unfuse(self, frame_id) -> state_lib.MapState:
    """Takes a kept frame out of the map exactly (`deintegration.unfuse_frame`) and forgets it.

    Raises:
      ValueError: a frame id not held, or a rule / map that cannot be de-integrated.
    """
    self._held([frame_id])
    frame, camera = self.kept[frame_id]
    self.state = deintegration.unfuse_frame(self.state, frame, camera, self.rule)
    del self.kept[frame_id]
    self.frames_fused -= 1
    return self.state

  def reintegrate(self, frame_ids, new_poses) -> state_lib.MapState:
    """Moves kept frames to corrected poses (a loop closure): each is de-integrated at the pose
    it was fused with and fused again at its new one (`deintegration.reintegrate`, one call per
    camera), after growing the map if the new poses could overfill it. The kept frames then
    carry their new poses.

    Args:
      frame_ids: ids of kept frames, T of them.
      new_poses: `(T, 4, 4)` their corrected camera-to-world poses.

    Raises:
      ValueError: an id not held, poses of another length or not rigid, or a rule / map that
        cannot be de-integrated (use `rebuild`).
    """
    ids = self._held(frame_ids)
    poses = deintegration.check_poses(new_poses, len(ids), "new_poses")
    deintegration.check_invertible(self.state, self.rule)
    by_camera = collections.OrderedDict()
    for frame_id, pose in zip(ids, poses):
      by_camera.setdefault(self.kept[frame_id][1], []).append((frame_id, pose))
    for camera, items in by_camera.items():
      frames = [self.kept[frame_id][0] for frame_id, _ in items]
      stack = jax.tree.map(lambda *x: np.stack(x), *frames)
      new = np.stack([pose for _, pose in items]).astype(np.float32)
      self._ensure_room(np.asarray(stack.depth), new, camera)
      self.state = deintegration.reintegrate(self.state, stack, stack.T_world_cam, new, camera,
                                             self.rule)
      for (frame_id, _), frame, pose in zip(items, frames, new):
        self.kept[frame_id] = (frame._replace(T_world_cam=pose), camera)
    return self.state

  def rebuild(self, new_poses: Optional[dict] = None) -> state_lib.MapState:
    """Fuses every kept frame again, in order, from an empty map of the current capacity, at the
    poses of `new_poses` (`{frame_id: (4, 4)}`; frames not named keep theirs). The way to apply
    a pose correction with a rule that cannot be de-integrated (D, D+R, learned) or a map with
    free space; it needs every fused frame kept.

    Raises:
      ValueError: some fused frames are no longer kept, or an id of `new_poses` is not held.
    """
    if not self.keep_frames or len(self.kept) != self.frames_fused:
      raise ValueError(f"rebuild needs every fused frame kept: {len(self.kept)} of "
                       f"{self.frames_fused} are (keep_frames={self.keep_frames})")
    new_poses = dict(new_poses or {})
    self._held(new_poses)
    for frame_id, pose in new_poses.items():
      deintegration.check_poses(np.asarray(pose)[None], 1, f"new_poses[{frame_id!r}]")
    geometry = self.state.geometry
    self.state = state_lib.init_map(
        capacity=self.state.capacity, num_classes=self.state.num_classes,
        voxel_size=float(self.state.voxel_size), rule=self.rule,
        max_probes=self.state.max_probes,
        geometry=None if geometry is None else geometry.config(), free_space=self._free_space)
    kept, self.kept = self.kept, collections.OrderedDict()
    self.frames_fused = 0
    for frame_id, (frame, camera) in kept.items():
      if frame_id in new_poses:
        frame = frame._replace(T_world_cam=np.asarray(new_poses[frame_id], np.float32))
      self.fuse(frame, camera, frame_id=frame_id)
    return self.state

  def fuse_sequence(self, frames: fusion.Frame, camera: camera_lib.Camera, *,
                    chunk: Optional[int] = None, frame_ids=None) -> state_lib.MapState:
    """Fuses a stack of frames (`fuse_sequence`), `chunk` frames per compiled scan (default
    all), growing the map before any chunk that could overfill it. `frame_ids` (T of them)
    name the frames when frames are kept (default: their running numbers)."""
    if not isinstance(frames, fusion.Frame):
      raise TypeError(f"frames must be a jaxfusion.Frame; got {type(frames).__name__}")
    depth = np.asarray(frames.depth)
    if depth.ndim != 3:
      raise ValueError(f"depth must have shape (T, H, W); got {depth.shape}")
    total = depth.shape[0]
    step = total if chunk is None else int(chunk)
    if step < 1:
      raise ValueError(f"chunk must be at least 1; got {chunk}")
    ids = list(range(self.frames_fused, self.frames_fused + total)) if frame_ids is None else (
        list(frame_ids))
    if len(ids) != total:
      raise ValueError(f"frame_ids must name the {total} frames; got {len(ids)}")
    if self.keep_frames:
      for frame_id in ids:
        self._new_id(frame_id, None)
    for start in range(0, total, step):
      part = jax.tree.map(lambda x, s=start: x[s:s + step], frames)
      self._ensure_room(np.asarray(part.depth), np.asarray(part.T_world_cam), camera)
      self.state = fusion.fuse_sequence(self.state, part, camera, self.rule)
      self.frames_fused += int(np.shape(part.depth)[0])
    if self.keep_frames:
      host = jax.tree.map(np.asarray, frames)     # one transfer, not one per kept frame
      for t, frame_id in enumerate(ids[-self.keep_frames:], start=max(total - self.keep_frames,
                                                                        0)):
        self._keep(frame_id, jax.tree.map(lambda x, t=t: x[t], host), camera)
    return self.state
