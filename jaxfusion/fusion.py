"""Fusing frames into the map: projection, grouping of a frame's pixels per voxel, one rule
update per touched voxel — a whole frame at once, with no Python loop over pixels or voxels.

Data flow of `fuse_frame` (shape legend: H×W pixels, N = H·W, K classes, C slots):

    depth (H, W) + T_world_cam + Camera ──► voxel keys (N, 3) int32   (one fused pass)
    keys ──grid scatter-min + cumsum──► group of each pixel (N,), U groups (no sort)
    group keys, 8192 at a time ──hashing.insert──► slots   [no slot → dropped and counted]
    rule.observe per pixel block ──scatter sum / max──► one VoxelObservation per group
    rule.update(rows[slots], observation) ──scatter──► new rows (in place)

Cost per frame: O(N·K) for the per-pixel terms plus O(U·K) per voxel, never O(C): the map's
buffers are donated and only touched through `lax.while_loop`s, which XLA updates in place
(`lax.cond` would copy them), and no `(N, K)` temporary is materialised. bench/RESULTS.md has
the measurements and a profile.

The engine never looks at which rule it runs: it calls the rule's kernels only.
"""

from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import context as context_lib
from jaxfusion import free_space as free_space_lib
from jaxfusion import hashing
from jaxfusion import numerics
from jaxfusion import tsdf
from jaxfusion import validation
from jaxfusion.grouping import PixelGroups  # noqa: F401  (re-exported)
from jaxfusion.grouping import group_pixels
from jaxfusion.rules import base as rules_base
from jaxfusion.state import MapState

# Voxels per chunk of the per-voxel stage. A frame's U voxels are placed and updated in
# ceil(U / _CHUNK) rounds of a `lax.while_loop`, which updates the donated map in place (a
# `lax.cond`/`switch` over static sizes would not: XLA copies its operands, the whole map). An
# indoor 640×480 frame at 0.1 m touches about 5 000 voxels: one round.
_CHUNK = 2**13
# Pixels per block when the per-pixel terms are computed and reduced (bounds their scratch).
_PIXEL_BLOCK = 2**15


class Frame(NamedTuple):
  """One RGB-D observation with the network's class probabilities (a pytree).

  Attributes:
    depth: `(H, W)` float z-depth in metres; 0, negative or non-finite marks a hole.
    T_world_cam: `(4, 4)` float camera-to-world pose.
    probs: `(H, W, K)` float class probabilities (the MC mean for Bayesian nets).
    var: `(H, W, K)` float per-class epistemic variance, or None (rules that need it say so).
    rgb: `(H, W, 3)` colour image (uint8, or float in [0, 1]) registered to the depth, or None;
      only rules that read image context features (docs/equations.md §2.5) need it.
  """
  depth: jax.Array
  T_world_cam: jax.Array
  probs: jax.Array
  var: Optional[jax.Array] = None
  rgb: Optional[jax.Array] = None


def _place_groups(state: MapState, keys, groups: PixelGroups, counts, chunk: int, reset=None):
  """Finds or inserts the frame's U voxels, `chunk` at a time, and adds their pixel counts
  (to 0 instead of the stored count where `reset (C,) bool`: free-space restarts, §10.2).

  Returns:
    `(state, slot_of_group)`: the map with new keys, hits and counters, and `(P,) int32` the slot
    of each group (capacity where it was dropped or is not a group), P = counts' length.
  """
  capacity = state.capacity
  lanes = jnp.arange(chunk, dtype=jnp.int32)

  def body(carry):
    c, table, claims, hits, slot_of_group, new, dropped = carry
    start = c * chunk
    first = jax.lax.dynamic_slice(groups.first_pixel, (start,), (chunk,))
    active = start + lanes < groups.num_groups
    placed = hashing.insert(table, claims, keys[first], active, max_probes=state.max_probes)
    write = jnp.where(placed.found, placed.slots, capacity)
    count = jax.lax.dynamic_slice(counts, (start,), (chunk,)).astype(jnp.int32)
    read = jnp.minimum(write, capacity - 1)
    stored = hits[read] if reset is None else jnp.where(reset[read], 0, hits[read])
    hits = hits.at[write].set(numerics.saturating_add(stored, count), mode="drop")
    return (c + 1, placed.table, placed.claims, hits,
            jax.lax.dynamic_update_slice(slot_of_group, write, (start,)),
            new + jnp.sum(placed.is_new, dtype=jnp.int32),
            dropped + jnp.sum(active & ~placed.found, dtype=jnp.int32))

  init = (jnp.zeros((), jnp.int32), state.keys, state.claims, state.hits,
          jnp.full(counts.shape[0], capacity, jnp.int32), jnp.zeros((), jnp.int32),
          jnp.zeros((), jnp.int32))
  _, table, claims, hits, slot_of_group, new, dropped = jax.lax.while_loop(
      lambda carry: carry[0] * chunk < groups.num_groups, body, init)
  state = state.replace(
      keys=table, claims=claims, hits=hits, num_occupied=state.num_occupied + new,
      num_dropped=numerics.saturating_add(state.num_dropped, dropped))
  return state, slot_of_group


def _pixel_blocks(n: int) -> int:
  """Number of equal pixel blocks (about `_PIXEL_BLOCK` pixels each) that N splits into."""
  start = -(-n // _PIXEL_BLOCK)
  for blocks in range(start, 4 * start + 1):
    if n % blocks == 0:
      return blocks
  return 1


def _rows_update(rule: rules_base.FusionRule, chunk: int, observe: Callable,
                 kernel: Optional[Callable] = None):
  """The rule's update of the touched rows, as `f(rows, probs, var, ctx, hparams, segment,
  counts, slot_of_group, num_groups, index, fresh) -> rows` (`fresh (P,) bool` or None: groups
  that start from the rule's empty row, free-space restarts), where `observe(probs, var, ctx, hparams)`
  gives the per-pixel terms of `(n, K)` inputs and `(n, F)` context (ctx None when the rule
  reads none).

  The forward pass handles `chunk` voxels per round of a `lax.while_loop`, in place and in time
  proportional to U; within a round the per-pixel terms are computed and scatter-reduced one
  block of pixels at a time, so no `(N, K)` term array is ever materialised. Reverse-mode AD
  cannot go through a while loop whose trip count depends on the data, so the VJP is that of
  `dense`, the same update written at the static size P (all possible groups) — slower, but only
  paid when differentiating.

  `kernel(row, observation, hparams) -> row` is the per-voxel update, `rule.update` by default
  (de-integration passes `rule.remove`).
  """
  kernel = rule.update if kernel is None else kernel

  def apply(rows, hparams, sums, maxes, counts, slots, fresh):
    """Applies reduced observations (raw per-group sums and maxes) at `slots`; a group where
    `fresh` (or None) starts from the rule's empty row instead of the stored one."""
    capacity = jax.tree.leaves(rows)[0].shape[0]
    ok = slots < capacity
    if rule.aggregate == "mean":
      sums = jax.tree.map(lambda x: x / jnp.maximum(counts, 1.0)[:, None], sums)
    sums = jax.tree.map(lambda x: jnp.where(ok[:, None], x, 0.0), sums)
    maxes = jax.tree.map(lambda x: jnp.where(ok[:, None], x, 1.0), maxes)
    observation = rules_base.VoxelObservation(sums, maxes, jnp.where(ok, counts, 1.0))
    read_slot = jnp.where(ok, slots, 0)
    old = jax.tree.map(lambda r: r[read_slot], rows)
    if fresh is not None:
      prior = rule.init(jax.tree.leaves(rows)[0].shape[-1], hparams)
      old = jax.tree.map(lambda o, p: jnp.where(fresh[:, None], jnp.asarray(p, o.dtype)[None], o),
                         old, prior)
    new = jax.vmap(kernel, in_axes=(0, 0, None))(old, observation, hparams)
    return jax.tree.map(lambda r, x: r.at[slots].set(x.astype(r.dtype), mode="drop"), rows, new)

  def dense(rows, probs, var, ctx, hparams, segment, counts, slot_of_group, index, fresh):
    probs, var = _frame_of(probs, index), _frame_of(var, index)
    num_rows = counts.shape[0]
    segment = jnp.minimum(segment, num_rows)
    terms = observe(probs, var, ctx, hparams)
    sums = jax.tree.map(
        lambda t: jax.ops.segment_sum(t, segment, num_segments=num_rows + 1)[:num_rows],
        terms.sums)
    maxes = jax.tree.map(
        lambda t: jax.ops.segment_max(t, segment, num_segments=num_rows + 1)[:num_rows],
        terms.maxes)
    return apply(rows, hparams, sums, maxes, counts, slot_of_group, fresh)

  @jax.custom_vjp
  def update(rows, probs, var, ctx, hparams, segment, counts, slot_of_group, num_groups, index,
             fresh):
    n, num_classes = probs.shape[-2:]
    blocks = _pixel_blocks(n)
    size = n // blocks
    shapes = jax.eval_shape(observe, probs.reshape(-1, num_classes)[:1],
                            var.reshape(-1, num_classes)[:1],
                            None if ctx is None else ctx[:1], hparams)

    def pixel_block(x, b):
      # A block of frame `index` read straight from a (T, n, K) stack: slicing the frame out
      # first would copy it (a while loop's operand is materialised), 3 ms a frame at 640×480.
      if x.ndim == 2:
        return jax.lax.dynamic_slice(x, (b * size, 0), (size, num_classes))
      return jax.lax.dynamic_slice(x, (index, b * size, 0), (1, size, num_classes))[0]

    def reduce_block(b, acc, start):
      sums, maxes = acc
      p = pixel_block(probs, b)
      v = pixel_block(var, b)
      local = jax.lax.dynamic_slice(segment, (b * size,), (size,)) - start
      local = jnp.where((local >= 0) & (local < chunk), local, chunk)
      c = None if ctx is None else jax.lax.dynamic_slice_in_dim(ctx, b * size, size)
      terms = observe(p, v, c, hparams)
      sums = jax.tree.map(lambda a, t: a.at[local].add(t), sums, terms.sums)
      maxes = jax.tree.map(lambda a, t: a.at[local].max(t), maxes, terms.maxes)
      return sums, maxes

    def body(carry):
      c, rows = carry
      start = c * chunk
      acc = (jax.tree.map(lambda x: jnp.zeros((chunk + 1,) + x.shape[1:], x.dtype), shapes.sums),
             jax.tree.map(lambda x: jnp.full((chunk + 1,) + x.shape[1:], -jnp.inf, x.dtype),
                          shapes.maxes))
      sums, maxes = jax.lax.fori_loop(0, blocks, lambda b, a: reduce_block(b, a, start), acc)
      sums, maxes = jax.tree.map(lambda x: x[:chunk], (sums, maxes))
      return c + 1, apply(rows, hparams, sums, maxes,
                          jax.lax.dynamic_slice(counts, (start,), (chunk,)),
                          jax.lax.dynamic_slice(slot_of_group, (start,), (chunk,)),
                          None if fresh is None else
                          jax.lax.dynamic_slice(fresh, (start,), (chunk,)))

    _, rows = jax.lax.while_loop(lambda carry: carry[0] * chunk < num_groups, body,
                                 (jnp.zeros((), jnp.int32), rows))
    return rows

  def fwd(rows, probs, var, ctx, hparams, segment, counts, slot_of_group, num_groups, index,
          fresh):
    out = update(rows, probs, var, ctx, hparams, segment, counts, slot_of_group, num_groups,
                 index, fresh)
    return out, (rows, probs, var, ctx, hparams, segment, counts, slot_of_group, index, fresh)

  def bwd(residuals, cotangent):
    # The context is a function of the frame that is not differentiated (its cotangent is 0).
    rows, probs, var, ctx, hparams, segment, counts, slot_of_group, index, fresh = residuals
    _, vjp = jax.vjp(
        lambda r, p, v, h, c: dense(r, p, v, ctx, h, segment, c, slot_of_group, index, fresh),
        rows, probs, var, hparams, counts)
    d_rows, d_probs, d_var, d_hparams, d_counts = vjp(cotangent)
    d_ctx = None if ctx is None else jnp.zeros_like(ctx)
    return d_rows, d_probs, d_var, d_ctx, d_hparams, None, d_counts, None, None, None, None

  update.defvjp(fwd, bwd)
  return update


def _frame_of(x, index):
  """Frame `index` of a stack with a leading T axis, or the frame's array itself (index None)."""
  return x if index is None else jax.lax.dynamic_index_in_dim(x, index, keepdims=False)


def fuse_frame_unchecked(state: MapState, frame: Frame, camera: camera_lib.Camera,
                         rule: rules_base.FusionRule) -> MapState:
  """`fuse_frame`'s pure body: no input checks, not jitted, nothing donated.

  For code that composes the engine inside its own traced function (`batch`, `tune`, a user's
  `jax.jit`); call `fuse_frame` everywhere else. Same arguments and result as `fuse_frame`.
  """
  return _fuse_frame_of(state, frame, camera, rule, None)


class _Pixels(NamedTuple):
  """One frame's pixels as the per-voxel stage reads them (`_frame_pixels`)."""
  depth: jax.Array      # (H, W) float32
  pose: jax.Array       # (4, 4) the frame's T_world_cam
  keys: jax.Array       # (N, 3) int32 voxel keys
  valid: jax.Array      # (N,) bool valid pixels (§2.1)
  probs: jax.Array      # (N, K) or (T, N, K) float32 (a stack is read in place)
  var: jax.Array        # like probs (probs again when the frame has no variance)
  ctx: Optional[jax.Array]   # (N, F) context features, or None
  observe: Callable     # observe(p, v, c, hparams) -> PixelTerms of a block of pixels


def _frame_pixels(voxel_size, frames: Frame, camera: camera_lib.Camera,
                  rule: rules_base.FusionRule, index) -> _Pixels:
  """Keys, valid pixels, guarded per-pixel terms and context of one frame (`frames` itself, or
  frame `index` of a stack) at `voxel_size` (`() float32`, the map's), shared by fusing and
  de-integrating (`jaxfusion.deintegration`)."""
  height, width, num_classes = frames.probs.shape[-3:]
  n = height * width
  stack = lambda x: jnp.asarray(x, jnp.float32).reshape(np.shape(x)[:-3] + (n, num_classes))

  # Geometry: every pixel → world point → voxel key, in one fused elementwise pass.
  depth = jnp.asarray(_frame_of(frames.depth, index), jnp.float32)
  pose = _frame_of(frames.T_world_cam, index)
  keys, in_range = camera_lib.depth_to_voxel_keys(depth, pose, camera, voxel_size)

  # Valid pixels: positive finite depth, finite probabilities (and variances if given).
  probs = stack(frames.probs)
  valid = in_range & (depth.reshape(n) > 0) & jnp.all(
      jnp.isfinite(_frame_of(probs, index)), axis=-1)
  if frames.var is not None:
    var = stack(frames.var)
    valid = valid & jnp.all(jnp.isfinite(_frame_of(var, index)), axis=-1)
  # Double-where: no NaN/inf reaches the kernels (nor their gradients). Invalid pixels are sent to
  # a junk group, so their terms are never used and only need to be finite; the guard is
  # therefore per element, not a per-pixel mask broadcast over K, which XLA's CPU loops cannot
  # vectorise (it doubled the cost of the per-pixel logarithms). It runs inside `observe`, block
  # by block, so the guarded copies are never materialised either.
  has_var = frames.var is not None

  # Per-pixel context (docs/equations.md §2.5), only for rules that ask for it: a rule with an
  # empty `context` is traced exactly as before.
  ctx = None
  if rule.context:
    rgb = None if frames.rgb is None else _frame_of(frames.rgb, index)
    ctx = context_lib.pixel_context(
        depth, _frame_of(frames.probs, index), camera, rule.context, rgb).reshape(n, -1)

  def observe(p, v, c, hparams):
    p = jnp.where(jnp.isfinite(p), jnp.maximum(p, 0.0), 1.0 / num_classes)
    v = jnp.where(jnp.isfinite(v), v, 0.0) if has_var else jnp.zeros_like(p)
    if c is None:
      return jax.vmap(rule.observe, in_axes=(0, 0, None))(p, v, hparams)
    return jax.vmap(rule.observe, in_axes=(0, 0, 0, None))(p, v, c, hparams)

  return _Pixels(depth, pose, keys, valid, probs, var if has_var else probs, ctx, observe)


def _pixel_groups(keys, valid):
  """`(groups, counts, chunk)`: the frame's pixels grouped per voxel, `first_pixel` padded to
  whole chunks, and the valid pixels of each group `(P,) float32`."""
  n = keys.shape[0]
  groups = group_pixels(keys, valid)
  chunk = min(_CHUNK, n)
  padded = -(-n // chunk) * chunk        # whole chunks, so that no dynamic slice is clamped
  first_pixel = jnp.pad(groups.first_pixel, (0, padded - n))
  groups = groups._replace(first_pixel=first_pixel)
  # Pixel counts per group; invalid pixels (segment n) fall in the padding or are dropped.
  counts = jax.ops.segment_sum(valid.astype(jnp.float32), groups.segment,
                               num_segments=padded)
  counts = jnp.where(jnp.arange(padded) < groups.num_groups, counts, 0.0)
  return groups, counts, chunk


def _fuse_frame_of(state: MapState, frames: Frame, camera: camera_lib.Camera,
                   rule: rules_base.FusionRule, index) -> MapState:
  """Fuses one frame: `frames` itself (`index` None), or frame `index` (traced int) of a stack
  whose fields carry a leading T axis, read in place (`fuse_sequence_unchecked`)."""
  px = _frame_pixels(state.voxel_size, frames, camera, rule, index)
  valid = px.valid

  # The geometry layer, when the map has one, integrates the same depth and pose in the same
  # program; with `gate_semantics` only pixels on the surface it held before the frame fuse
  # semantics (docs/equations.md §8.6).
  geometry = state.geometry
  if geometry is not None:
    if geometry.gate_semantics:
      valid = valid & tsdf.surface_gate(geometry, px.depth, px.pose, camera)
    geometry = tsdf.integrate_unchecked(geometry, px.depth, px.pose, camera)

  groups, counts, chunk = _pixel_groups(px.keys, valid)
  state = _fuse_groups(state, px, groups, counts, chunk, camera, rule, index)
  return state.replace(geometry=geometry)


def _fuse_groups(state: MapState, px: _Pixels, groups: PixelGroups, counts, chunk: int,
                 camera: camera_lib.Camera, rule: rules_base.FusionRule, index) -> MapState:
  """The semantic layer's half of a frame that reads the map: the frame's voxel groups placed,
  free space marked (when the map has the layer) and each touched voxel's rows updated once.
  `state.geometry` is passed through untouched."""
  # Free space (docs/equations.md §10), when the map has the layer: a free voxel the frame hits
  # restarts (its hits from 0, its row from the rule's prior).
  reset = fresh = None
  if state.free_space is not None:
    reset = free_space_lib.is_free(state.free_space)

  # Place the frame's voxels in the map, then reduce the rule's per-pixel terms per voxel and
  # update each touched voxel once.
  state, slot_of_group = _place_groups(state, px.keys, groups, counts, chunk, reset)
  if state.free_space is not None:
    # The voxels the depth shows as free, marked after the placement (a voxel new in this frame
    # is hit, and a hit wins: the same result as marking before it, and the loop above keeps
    # updating the keys in place).
    free = free_space_lib.mark(state, px.depth, px.pose, camera)
    fresh = reset[jnp.minimum(slot_of_group, state.capacity - 1)]
    state = free_space_lib.apply(state, free, slot_of_group)
  rows = _rows_update(rule, chunk, px.observe)(
      state.rows, px.probs, px.var, px.ctx, rule.hparams, groups.segment, counts,
      slot_of_group, groups.num_groups, index, fresh)
  return state.replace(rows=rows)


class PreparedFrame(NamedTuple):
  """The half of a frame's fusion that does not read the map (`prepare_frame_unchecked`).

  A `fuse_frame` is one program, compiled for the map's capacity: a map that grows compiles
  it again, grouping and all. The `Mapper` runs a frame as this capacity-free half (compiled
  once) and the halves that read the tables (`fuse_prepared_unchecked`, and
  `tsdf.integrate_blocks_unchecked` for the geometry layer), so a growth recompiles only the
  grown table's half; the result is that of `fuse_frame`. It also says how many voxels and
  blocks the frame touches: the `Mapper`'s room check.
  """
  keys: jax.Array                       # (N, 3) int32 the voxel key of every pixel
  groups: PixelGroups                   # valid pixels per voxel, first_pixel padded to chunks
  counts: jax.Array                     # (P,) float32 valid pixels of each group
  blocks: Optional[tsdf.FrameBlocks]    # the geometry layer's blocks, or None
  frame: Frame                          # the frame itself, as device arrays (for the halves:
                                        # a frame of NumPy arrays is copied in only once)


def prepare_frame_unchecked(voxel_size, frame: Frame, camera: camera_lib.Camera,
                            rule: rules_base.FusionRule,
                            geometry: Optional[tsdf.TSDFState] = None) -> PreparedFrame:
  """A frame's voxel keys grouped per voxel, and its geometry layer's blocks (pure, no checks).

  Args:
    voxel_size: `() float32` the map's voxel edge (`state.voxel_size`).
    frame: one Frame (no leading axis).
    camera: intrinsics.
    rule: the map's FusionRule.
    geometry: the map's geometry layer as `tsdf.settings_only(...)` (its settings; any arrays
      would tie the program to a capacity), or None for a map without one. A layer with
      `gate_semantics` cannot be prepared apart: its gate reads the layer's table.

  Returns:
    A PreparedFrame; `groups.num_groups` voxels and `blocks.num_groups` blocks are what the
    frame touches, an upper bound of what it adds.
  """
  if geometry is not None and geometry.gate_semantics:
    raise ValueError("a geometry layer with gate_semantics cannot be prepared apart from its "
                     "table: use fuse_frame")
  px = _frame_pixels(voxel_size, frame, camera, rule, None)
  groups, counts, _ = _pixel_groups(px.keys, px.valid)
  blocks = None if geometry is None else tsdf.frame_blocks(geometry, px.depth, px.pose, camera)
  return PreparedFrame(px.keys, groups, counts, blocks, frame)


def fuse_prepared_unchecked(state: MapState, prepared: PreparedFrame, camera: camera_lib.Camera,
                            rule: rules_base.FusionRule) -> MapState:
  """The semantic layer's half of `fuse_frame` that reads the map, given the frame's
  `prepare_frame_unchecked` (pure, no checks).

  Args:
    state: the map without its geometry layer (`state.replace(geometry=None)`: the layer's
      arrays would tie the program to its capacity; `tsdf.integrate_blocks_unchecked` fuses it).
    prepared: the frame's PreparedFrame at `state.voxel_size` (it carries the frame).
    camera, rule: as for `fuse_frame`.

  Returns:
    The new MapState (geometry None): equal to `fuse_frame`'s semantic layer.
  """
  if state.geometry is not None:
    raise ValueError("fuse_prepared_unchecked fuses the semantic layer: pass "
                     "state.replace(geometry=None) and integrate the geometry layer apart")
  px = _frame_pixels(state.voxel_size, prepared.frame, camera, rule, None)._replace(
      keys=prepared.keys)
  chunk = min(_CHUNK, prepared.keys.shape[0])
  return _fuse_groups(state, px, prepared.groups, prepared.counts, chunk, camera, rule, None)


def _fuse_prepared_counted(state, prepared, camera, rule):
  state = fuse_prepared_unchecked(state, prepared, camera, rule)
  return state, state.num_occupied


prepare_frame = jax.jit(prepare_frame_unchecked)
# The semantic half, donated, as `(new state, () int32 its occupied count)`: the count is a
# buffer of its own, so the `Mapper` can read it after the next frame has donated the state.
fuse_prepared_donating = jax.jit(_fuse_prepared_counted, donate_argnums=0)


# `fuse_frame_unchecked` compiled, with the map's buffers donated (what `fuse_frame` calls on
# concrete arrays), and without donation (under a transformation).
fuse_frame_donating = jax.jit(fuse_frame_unchecked, donate_argnums=0)
_fuse_frame_copying = jax.jit(fuse_frame_unchecked)


def under_transformation(*trees) -> bool:
  """True when a leaf of `trees` is a tracer: the call is being traced by `jit`, `grad`, `vmap`…

  The public entry points donate the map's buffers only when this is False. A transformation
  may keep an input for later (reverse-mode AD saves it as a residual of the forward pass), so a
  buffer it sees must never be donated; inside an outer `jit` donation is moot anyway (XLA plans
  the buffers of the whole program).
  """
  return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trees))


def _check_inputs(state, frame, camera, rule, *, batch_dims, sample=False):
  if not isinstance(state, MapState):
    raise TypeError(f"state must be a MapState from init_map; got {type(state).__name__}")
  if not isinstance(frame, Frame):
    raise TypeError(f"frame must be a jaxfusion.Frame; got {type(frame).__name__}")
  validation.check_rule_matches_map(state, rule)
  validation.check_camera(camera)
  validation.check_frame(frame, num_classes=state.num_classes, requires_var=rule.requires_var,
                         rule_name=rule.name, batch_dims=batch_dims, sample=sample,
                         context=rule.context)


def fuse_frame(state: MapState, frame: Frame, camera: camera_lib.Camera,
               rule: rules_base.FusionRule) -> MapState:
  """Fuses one frame into the map (jitted; `state`'s buffers are donated and updated in place).

  Under `jax.grad`, `jax.vmap` or any other transformation (any argument a tracer) nothing is
  donated, so a plain Python loop of `fuse_frame` can be differentiated or batched as written.

  Every valid pixel is back-projected, pixels are grouped per voxel, and the rule's update is
  applied once per touched voxel with the frame's reduced observation (the Σ_j of
  docs/equations.md §2.4). Voxels that cannot be placed because the map is full are dropped
  and counted in `num_dropped`.

  Input checks cost microseconds: shapes, dtypes and the pose are checked in full, the signs of
  `probs` and `var` on a strided sample of pixels (`validation.SAMPLED_PIXELS`), which catches
  logits and log-probabilities; `fuse_sequence` checks every value. The engine reads
  probabilities as `max(p, 0)` and skips pixels with non-finite values either way.

  Args:
    state: the map (from `init_map` with the same rule). Do not use it after this call.
    frame: `Frame(depth (H, W), T_world_cam (4, 4), probs (H, W, K), var (H, W, K) | None)`.
    camera: pinhole intrinsics of the depth image.
    rule: the FusionRule (its hyperparameters are traced: changing β does not recompile).

  Returns:
    The new MapState.

  Example (a wall 2 m in front of a 8×6-pixel camera, seen with uniform probabilities):
    >>> import numpy as np, jaxfusion
    >>> rule = jaxfusion.rules.robust(beta=0.3)
    >>> state = jaxfusion.init_map(capacity=2**12, num_classes=3, rule=rule)
    >>> cam = jaxfusion.Camera(fx=8.0, fy=8.0, cx=3.5, cy=2.5)
    >>> mean = np.full((6, 8, 3), 1 / 3, np.float32)
    >>> var = np.full((6, 8, 3), 0.01, np.float32)
    >>> depth = np.full((6, 8), 2.0, np.float32)
    >>> frame = jaxfusion.Frame(depth, np.eye(4, dtype=np.float32), mean, var)
    >>> state = jaxfusion.fuse_frame(state, frame, cam, rule)
    >>> jaxfusion.map_stats(state)["occupied"] > 0
    True
  """
  _check_inputs(state, frame, camera, rule, batch_dims=0, sample=True)
  if under_transformation(state, frame, camera, rule):
    return _fuse_frame_copying(state, frame, camera, rule)
  return fuse_frame_donating(state, frame, camera, rule)


def fuse_sequence_unchecked(state, frames, camera, rule):
  """`fuse_sequence`'s pure body: one `lax.scan` of `fuse_frame_unchecked`, no checks.

  The scan runs over frame indices and each step reads its frame from the stacks in place: a
  scan over the frames themselves would slice every frame's `(H, W, K)` probabilities and
  variances into copies first.
  """
  def step(s, t):
    return _fuse_frame_of(s, frames, camera, rule, t), None
  state, _ = jax.lax.scan(step, state, jnp.arange(frames.depth.shape[0], dtype=jnp.int32))
  return state


fuse_sequence_donating = jax.jit(fuse_sequence_unchecked, donate_argnums=0)
_fuse_sequence_copying = jax.jit(fuse_sequence_unchecked)


def fuse_sequence(state: MapState, frames: Frame, camera: camera_lib.Camera,
                  rule: rules_base.FusionRule) -> MapState:
  """Fuses a stack of frames in order with one `lax.scan` (one compiled call).

  Equal to calling `fuse_frame` on each frame in turn. To leave a frame out of a padded stack,
  give it all-zero depth: it then touches nothing.

  Args:
    state: the map; donated (except under a transformation, as for `fuse_frame`).
    frames: a Frame whose fields carry a leading time axis: `depth (T, H, W)`,
      `T_world_cam (T, 4, 4)`, `probs (T, H, W, K)`, `var (T, H, W, K)` or None.
    camera: intrinsics shared by all frames.
    rule: the FusionRule.

  Returns:
    The new MapState.
  """
  _check_inputs(state, frames, camera, rule, batch_dims=1)
  if under_transformation(state, frames, camera, rule):
    return _fuse_sequence_copying(state, frames, camera, rule)
  return fuse_sequence_donating(state, frames, camera, rule)
