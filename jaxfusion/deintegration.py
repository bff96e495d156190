"""De-integration and re-integration: take a frame's contribution out of a map exactly, and
apply a pose correction (a loop closure) without fusing the sequence again
(docs/equations.md §11).

    unfuse_frame(state, frame, camera, rule)        the map as if `frame` had never been fused
    reintegrate(state, frames, old_poses, new_poses, camera, rule)
                                                    de-integrate at the old poses, integrate at
                                                    the new ones: one compiled call

A frame is de-integrated by recomputing what fusing it added: the same keys, valid pixels and
per-pixel terms (`fusion._frame_pixels`), reduced per voxel in the same way, then the rule's
inverse `remove` per touched voxel (found by lookup; nothing is inserted) and its pixel counts
taken off the hits. A voxel left with 0 hits returns to the rule's prior and is no longer read
out (its key stays in the table). The geometry layer, when present, is de-integrated by
`tsdf.deintegrate_unchecked`.

Exact inverses exist for the rules whose update is a sum: `sum_probs`, `sum_labels` (counts),
`bayes`, R and GLFS (sums of log-likelihoods). D and D+R keep a running maximum and the learned
rule gates on the voxel's state; free-space clearing and the semantic gate of the geometry layer
depend on the map as it was when the frame came. Those are refused with one line
(`check_invertible`).

Shape legend: T frames, H×W pixels, N = H·W, K classes, C slots.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import fusion
from jaxfusion import hashing
from jaxfusion import tsdf
from jaxfusion import validation
from jaxfusion.rules import base as rules_base
from jaxfusion.state import MapState


def invertible_problem(state: MapState, rule: rules_base.FusionRule):
  """Why `state` fused with `rule` cannot be de-integrated exactly, or None if it can."""
  if rule.remove is None:
    return (f"rule {rule.name!r} cannot be de-integrated: its update is not invertible (a "
            "running maximum or a gate on the voxel's state); de-integration works for "
            "sum_probs, sum_labels, bayes, robust_r and glfs")
  if state.free_space is not None:
    return ("a map with free space cannot be de-integrated: clearing and change detection "
            "depend on the map's state when each frame came")
  if state.geometry is not None and state.geometry.gate_semantics:
    return ("a map whose geometry layer gates semantics cannot be de-integrated: the gate "
            "depends on the surface when each frame came")
  return None


def check_invertible(state: MapState, rule: rules_base.FusionRule) -> None:
  """Raises ValueError with one line if `state` fused with `rule` cannot be de-integrated."""
  problem = invertible_problem(state, rule)
  if problem is not None:
    raise ValueError(problem)


def _find_groups(state: MapState, keys, groups, counts):
  """`(P,) int32` the slot of each of the frame's voxel groups, by lookup (C where the map does
  not hold it: never fused, or dropped when it was)."""
  capacity = state.capacity
  num = counts.shape[0]
  first = groups.first_pixel[:num]
  slots, found = hashing.lookup(state.keys, keys[first], max_probes=state.max_probes)
  is_group = jnp.arange(num) < groups.num_groups
  return jnp.where(found & is_group, slots, capacity)


def _unfuse_frame_of(state: MapState, frames: fusion.Frame, camera: camera_lib.Camera,
                     rule: rules_base.FusionRule, index) -> MapState:
  px = fusion._frame_pixels(state.voxel_size, frames, camera, rule, index)   # pylint: disable=protected-access
  groups, counts, chunk = fusion._pixel_groups(px.keys, px.valid)  # pylint: disable=protected-access
  slot_of_group = _find_groups(state, px.keys, groups, counts)
  rows = fusion._rows_update(rule, chunk, px.observe, kernel=rule.remove)(  # pylint: disable=protected-access
      state.rows, px.probs, px.var, px.ctx, rule.hparams, groups.segment, counts,
      slot_of_group, groups.num_groups, index, None)
  capacity = state.capacity
  read = jnp.minimum(slot_of_group, capacity - 1)
  left = jnp.maximum(state.hits[read] - counts.astype(jnp.int32), 0)
  hits = state.hits.at[slot_of_group].set(left, mode="drop")
  # A voxel with no pixel left holds the prior exactly, as an empty slot does.
  emptied = jnp.where((slot_of_group < capacity) & (left == 0), slot_of_group, capacity)
  prior = rule.init(state.num_classes, rule.hparams)
  rows = jax.tree.map(
      lambda r, p: r.at[emptied].set(jnp.broadcast_to(jnp.asarray(p, r.dtype),
                                                      (emptied.shape[0],) + r.shape[1:]),
                                     mode="drop"), rows, prior)
  geometry = state.geometry
  if geometry is not None:
    geometry = tsdf.deintegrate_unchecked(geometry, px.depth, px.pose, camera)
  return state.replace(rows=rows, hits=hits, geometry=geometry)


def unfuse_frame_unchecked(state: MapState, frame: fusion.Frame, camera: camera_lib.Camera,
                           rule: rules_base.FusionRule) -> MapState:
  """`unfuse_frame`'s pure body: no checks, not jitted, nothing donated (for composing)."""
  return _unfuse_frame_of(state, frame, camera, rule, None)


def reintegrate_unchecked(state: MapState, frames: fusion.Frame, old_poses: jax.Array,
                          new_poses: jax.Array, camera: camera_lib.Camera,
                          rule: rules_base.FusionRule) -> MapState:
  """`reintegrate`'s pure body: a scan de-integrating every frame at its old pose, then
  `fusion.fuse_sequence_unchecked` at the new poses."""
  old = frames._replace(T_world_cam=jnp.asarray(old_poses, jnp.float32))
  new = frames._replace(T_world_cam=jnp.asarray(new_poses, jnp.float32))

  def step(s, t):
    return _unfuse_frame_of(s, old, camera, rule, t), None
  state, _ = jax.lax.scan(step, state, jnp.arange(frames.depth.shape[0], dtype=jnp.int32))
  return fusion.fuse_sequence_unchecked(state, new, camera, rule)


_unfuse_donating = jax.jit(unfuse_frame_unchecked, donate_argnums=0)
_unfuse_copying = jax.jit(unfuse_frame_unchecked)
_reintegrate_donating = jax.jit(reintegrate_unchecked, donate_argnums=0)
_reintegrate_copying = jax.jit(reintegrate_unchecked)


class CappedWeightWarning(UserWarning):
  """Some geometry voxels reached the TSDF's weight cap: their de-integration is approximate."""


def warn_if_capped(state: MapState) -> None:
  """Warns (`CappedWeightWarning`) when the map's geometry layer has voxels at its weight cap,
  whose de-integration cannot be exact (docs/equations.md §8.7)."""
  if state.geometry is None:
    return
  capped = tsdf.capped_voxels(state.geometry)
  if capped:
    warnings.warn(f"{capped} geometry voxels are at the weight cap "
                  f"({float(state.geometry.max_weight):g}): their de-integration is approximate; "
                  "raise TSDFConfig.max_weight for exact de-integration", CappedWeightWarning,
                  stacklevel=3)


def _check(state, frame, camera, rule, batch_dims):
  if not isinstance(state, MapState):
    raise TypeError(f"state must be a MapState from init_map; got {type(state).__name__}")
  if not isinstance(frame, fusion.Frame):
    raise TypeError(f"frames must be a jaxfusion.Frame; got {type(frame).__name__}")
  validation.check_rule_matches_map(state, rule)
  check_invertible(state, rule)
  validation.check_camera(camera)
  validation.check_frame(frame, num_classes=state.num_classes, requires_var=rule.requires_var,
                         rule_name=rule.name, batch_dims=batch_dims, sample=batch_dims == 0,
                         context=rule.context)


def unfuse_frame(state: MapState, frame: fusion.Frame, camera: camera_lib.Camera,
                 rule: rules_base.FusionRule) -> MapState:
  """Takes one fused frame out of the map (jitted; `state`'s buffers are donated).

  The result equals, up to float32 rounding, the map fused from the other frames only
  (docs/equations.md §11): hits exactly, posteriors to ~1e-6. Give the frame exactly as it was
  fused (its depth, pose, probabilities, variances and colour). A frame that was never fused
  into this map corrupts it: nothing can tell the two apart.

  Args:
    state: the map; do not use it after this call.
    frame: the `Frame` to remove, as it was fused.
    camera: its intrinsics.
    rule: the map's rule; it must have an inverse (`FusionRule.remove`).

  Returns:
    The new MapState.

  Raises:
    ValueError: a rule that cannot be inverted (D, D+R, learned), a map with free space or a
      semantic gate, or the usual input errors of `fuse_frame`.
  """
  _check(state, frame, camera, rule, 0)
  if fusion.under_transformation(state, frame, camera, rule):
    return _unfuse_copying(state, frame, camera, rule)
  warn_if_capped(state)
  return _unfuse_donating(state, frame, camera, rule)


def check_poses(poses, count: int, name: str) -> np.ndarray:
  """`(T, 4, 4)` finite rigid poses, T = `count`, or one ValueError line."""
  array = np.asarray(poses)
  if array.shape != (count, 4, 4):
    raise ValueError(f"{name} must have shape ({count}, 4, 4), one pose per frame; got "
                     f"{array.shape}")
  for t in range(count):
    validation.check_pose_values(array[t].astype(np.float64), f"{name}[{t}]")
  return array


def reintegrate(state: MapState, frames: fusion.Frame, old_poses, new_poses,
                camera: camera_lib.Camera, rule: rules_base.FusionRule) -> MapState:
  """Applies a pose correction: every frame de-integrated at its old pose and fused again at its
  new one, in one compiled call (jitted; `state`'s buffers are donated).

  Equal, up to float32 rounding, to fusing every frame of the map at its corrected pose from
  scratch (docs/equations.md §11.2). The map must have room for the voxels the new poses reach
  (a `Mapper` grows first; `Mapper.reintegrate`).

  Args:
    state: the map.
    frames: a stack `Frame` (`depth (T, H, W)`, …) of the frames to move; `T_world_cam` is
      ignored (the poses below are used).
    old_poses: `(T, 4, 4)` the poses they were fused with.
    new_poses: `(T, 4, 4)` the corrected poses.
    camera: intrinsics shared by the frames.
    rule: the map's rule (invertible).

  Returns:
    The new MapState.

  Raises:
    ValueError: poses of another length or not rigid, a rule that cannot be inverted, a map
      with free space or a semantic gate, or the input errors of `fuse_sequence`.
  """
  if not isinstance(frames, fusion.Frame):
    raise TypeError(f"frames must be a jaxfusion.Frame; got {type(frames).__name__}")
  count = int(np.shape(frames.depth)[0]) if np.ndim(frames.depth) == 3 else -1
  if count < 0:
    raise ValueError(f"reintegrate takes a stack of frames, depth (T, H, W); got depth of shape "
                     f"{np.shape(frames.depth)}")
  concrete = not fusion.under_transformation(old_poses, new_poses)
  if concrete:
    old_poses = check_poses(old_poses, count, "old_poses")
    new_poses = check_poses(new_poses, count, "new_poses")
  _check(state, frames._replace(T_world_cam=jnp.asarray(new_poses)), camera, rule, 1)
  if fusion.under_transformation(state, frames, camera, rule, old_poses, new_poses):
    return _reintegrate_copying(state, frames, old_poses, new_poses, camera, rule)
  warn_if_capped(state)
  return _reintegrate_donating(state, frames, old_poses, new_poses, camera, rule)
