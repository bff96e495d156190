"""Fusing frames into the map: projection, grouping of a frame's pixels per voxel, one rule
update per touched voxel — a whole frame at once, with no Python loop over pixels or voxels.

Data flow of `fuse_frame` (shape legend: H×W pixels, N = H·W, K classes, C slots):

    depth (H, W) + T_world_cam + Camera ──► world points (N, 3) ──► voxel keys (N, 3) int32
    keys ──sort──► segment id per pixel (N,) + unique keys (≤ N)
    rule.observe per pixel ──segment sum / max──► one VoxelObservation per unique key
    unique keys ──hashing.insert──► slots              [no slot → dropped and counted]
    rule.update(rows[slots], observation) ──scatter──► new rows

The engine never looks at which rule it runs: it calls the rule's kernels only.
"""

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import hashing
from jaxfusion import numerics
from jaxfusion import validation
from jaxfusion.rules import base as rules_base
from jaxfusion.state import MapState

_SORT_SENTINEL = np.int32(np.iinfo(np.int32).max)


class Frame(NamedTuple):
  """One RGB-D observation with the network's class probabilities (a pytree).

  Attributes:
    depth: `(H, W)` float z-depth in metres; 0, negative or non-finite marks a hole.
    T_world_cam: `(4, 4)` float camera-to-world pose.
    probs: `(H, W, K)` float class probabilities (the MC mean for Bayesian nets).
    var: `(H, W, K)` float per-class epistemic variance, or None (rules that need it say so).
  """
  depth: jax.Array
  T_world_cam: jax.Array
  probs: jax.Array
  var: Optional[jax.Array] = None


class PixelGroups(NamedTuple):
  """A frame's valid pixels grouped by voxel."""
  segment: jax.Array        # [N] int32 group of each pixel; N for invalid pixels
  keys: jax.Array           # [N, 3] int32 key of group g in row g (rows ≥ num_groups: junk)
  is_group: jax.Array       # [N] bool, row g is a real group (g < number of groups)


def group_pixels(keys: jax.Array, valid: jax.Array) -> PixelGroups:
  """Groups pixels with equal voxel keys by one lexicographic sort.

  Args:
    keys: `(N, 3) int32` voxel key of each pixel.
    valid: `(N,) bool` pixels to group; the others get segment N.

  Returns:
    PixelGroups, groups numbered in sorted key order.
  """
  n = keys.shape[0]
  masked = jnp.where(valid[:, None], keys, _SORT_SENTINEL)
  kx, ky, kz, order = jax.lax.sort(
      (masked[:, 0], masked[:, 1], masked[:, 2], jnp.arange(n, dtype=jnp.int32)), num_keys=3)
  sorted_keys = jnp.stack([kx, ky, kz], axis=-1)
  sorted_valid = kx != _SORT_SENTINEL   # valid keys are bounded by camera.KEY_LIMIT
  starts = jnp.concatenate(
      [jnp.ones(1, bool), jnp.any(sorted_keys[1:] != sorted_keys[:-1], axis=-1)])
  sorted_segment = jnp.where(sorted_valid, jnp.cumsum(starts, dtype=jnp.int32) - 1, n)
  segment = jnp.zeros(n, jnp.int32).at[order].set(sorted_segment, unique_indices=True)
  group_keys = jnp.zeros((n, 3), jnp.int32).at[
      jnp.where(starts & sorted_valid, sorted_segment, n)].set(sorted_keys, mode="drop")
  num_groups = jnp.sum(starts & sorted_valid, dtype=jnp.int32)
  return PixelGroups(segment, group_keys, jnp.arange(n, dtype=jnp.int32) < num_groups)


def _reduce_terms(terms: rules_base.PixelTerms, segment, num_rows, counts, aggregate, ok):
  """Per-group sums (or means) and maxes of per-pixel terms; rows that are not `ok` are set to
  harmless finite values so that no NaN/inf reaches the update (or its gradient)."""

  def seg_sum(t):
    s = jax.ops.segment_sum(t, segment, num_segments=num_rows + 1)[:num_rows]
    if aggregate == "mean":
      s = s / jnp.maximum(counts, 1.0)[:, None]
    return jnp.where(ok[:, None], s, 0.0)

  def seg_max(t):
    m = jax.ops.segment_max(t, segment, num_segments=num_rows + 1)[:num_rows]
    return jnp.where(ok[:, None], m, 1.0)

  return jax.tree.map(seg_sum, terms.sums), jax.tree.map(seg_max, terms.maxes)


def _fuse_frame(state: MapState, frame: Frame, camera: camera_lib.Camera,
                rule: rules_base.FusionRule) -> MapState:
  height, width, num_classes = frame.probs.shape
  n = height * width
  capacity = state.capacity

  # Geometry: every pixel → world point → voxel key.
  depth = jnp.asarray(frame.depth, jnp.float32)
  p_cam = camera_lib.backproject(depth, camera).reshape(n, 3)
  p_world = camera_lib.transform_points(frame.T_world_cam, p_cam)
  keys, in_range = camera_lib.voxel_keys(p_world, state.voxel_size)

  # Valid pixels: positive finite depth, finite probabilities (and variances if given).
  probs = jnp.asarray(frame.probs, jnp.float32).reshape(n, num_classes)
  valid = in_range & (depth.reshape(n) > 0) & jnp.all(jnp.isfinite(probs), axis=-1)
  if frame.var is not None:
    var = jnp.asarray(frame.var, jnp.float32).reshape(n, num_classes)
    valid = valid & jnp.all(jnp.isfinite(var), axis=-1)
  else:
    var = jnp.zeros_like(probs)
  # Double-where: invalid pixels never feed NaN into the kernels (nor into their gradients).
  probs = jnp.where(valid[:, None], jnp.maximum(probs, 0.0), 1.0 / num_classes)
  var = jnp.where(valid[:, None], var, 0.0)

  groups = group_pixels(keys, valid)
  counts = jax.ops.segment_sum(valid.astype(jnp.float32), groups.segment,
                               num_segments=n + 1)[:n]

  # Place the frame's voxels in the map.
  placed = hashing.insert(state.keys, state.claims, groups.keys, groups.is_group,
                          max_probes=state.max_probes)
  ok = groups.is_group & placed.found

  # Reduce the rule's per-pixel terms per voxel and update each touched voxel once.
  terms = jax.vmap(rule.observe, in_axes=(0, 0, None))(probs, var, rule.hparams)
  sums, maxes = _reduce_terms(terms, groups.segment, n, counts, rule.aggregate, ok)
  observation = rules_base.VoxelObservation(sums, maxes, jnp.where(ok, counts, 1.0))
  read_slot = jnp.where(ok, placed.slots, 0)
  rows = jax.tree.map(lambda r: r[read_slot], state.rows)
  new_rows = jax.vmap(rule.update, in_axes=(0, 0, None))(rows, observation, rule.hparams)

  write_slot = jnp.where(ok, placed.slots, capacity)   # out of range: dropped, never written
  rows = jax.tree.map(
      lambda r, new: r.at[write_slot].set(new.astype(r.dtype), mode="drop"),
      state.rows, new_rows)
  slot_hits = state.hits[read_slot]
  hits = state.hits.at[write_slot].set(
      numerics.saturating_add(slot_hits, counts.astype(jnp.int32)), mode="drop")
  return state.replace(
      keys=placed.table,
      claims=placed.claims,
      rows=rows,
      hits=hits,
      num_occupied=state.num_occupied + jnp.sum(ok & placed.is_new, dtype=jnp.int32),
      num_dropped=numerics.saturating_add(
          state.num_dropped, jnp.sum(groups.is_group & ~placed.found, dtype=jnp.int32)),
  )


_fuse_frame_jit = jax.jit(_fuse_frame, donate_argnums=0)


def _check_inputs(state, frame, camera, rule, *, batch_dims):
  if not isinstance(state, MapState):
    raise TypeError(f"state must be a MapState from init_map; got {type(state).__name__}")
  if not isinstance(frame, Frame):
    raise TypeError(f"frame must be a jaxfusion.Frame; got {type(frame).__name__}")
  validation.check_rule_matches_map(state, rule)
  validation.check_camera(camera)
  validation.check_frame(frame, num_classes=state.num_classes, requires_var=rule.requires_var,
                         rule_name=rule.name, batch_dims=batch_dims)


def fuse_frame(state: MapState, frame: Frame, camera: camera_lib.Camera,
               rule: rules_base.FusionRule) -> MapState:
  """Fuses one frame into the map (jitted; `state`'s buffers are donated and updated in place).

  Every valid pixel is back-projected, pixels are grouped per voxel, and the rule's update is
  applied once per touched voxel with the frame's reduced observation (SPEC.md's Σ_j). Voxels
  that cannot be placed because the map is full are dropped and counted in `num_dropped`.

  Args:
    state: the map (from `init_map` with the same rule). Do not use it after this call.
    frame: `Frame(depth (H, W), T_world_cam (4, 4), probs (H, W, K), var (H, W, K) | None)`.
    camera: pinhole intrinsics of the depth image.
    rule: the FusionRule (its hyperparameters are traced: changing β does not recompile).

  Returns:
    The new MapState.

  Example:
    >>> rule = jaxfusion.rules.robust(beta=0.3)
    >>> state = jaxfusion.init_map(capacity=2**16, num_classes=7, rule=rule)
    >>> state = jaxfusion.fuse_frame(state, jaxfusion.Frame(depth, T, mean, var), cam, rule)
  """
  _check_inputs(state, frame, camera, rule, batch_dims=0)
  return _fuse_frame_jit(state, frame, camera, rule)


def _fuse_sequence(state, frames, camera, rule):
  def step(s, frame):
    return _fuse_frame(s, frame, camera, rule), None
  state, _ = jax.lax.scan(step, state, frames)
  return state


_fuse_sequence_jit = jax.jit(_fuse_sequence, donate_argnums=0)


def fuse_sequence(state: MapState, frames: Frame, camera: camera_lib.Camera,
                  rule: rules_base.FusionRule) -> MapState:
  """Fuses a stack of frames in order with one `lax.scan` (one compiled call).

  Equal to calling `fuse_frame` on each frame in turn. To leave a frame out of a padded stack,
  give it all-zero depth: it then touches nothing.

  Args:
    state: the map; donated.
    frames: a Frame whose fields carry a leading time axis: `depth (T, H, W)`,
      `T_world_cam (T, 4, 4)`, `probs (T, H, W, K)`, `var (T, H, W, K)` or None.
    camera: intrinsics shared by all frames.
    rule: the FusionRule.

  Returns:
    The new MapState.
  """
  _check_inputs(state, frames, camera, rule, batch_dims=1)
  return _fuse_sequence_jit(state, frames, camera, rule)
