"""Ground-truth voxel labels, computed with the engine itself.

The GT label of a voxel is the majority of the GT pixel labels that fall into it over the
whole sequence: every frame's GT labels are turned into one-hot "probabilities" and fused with
the voting rule `rules.sum_labels()`, so the voxel grid, keys and back-projection are exactly
those of the maps being evaluated. Ties go to the lowest class index (argmax). Pixels with
`IGNORE_LABEL` (or a label outside the class range) and pixels without depth are not fused.

Shape legend: N voxels, K classes.
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import fusion, readout, rules, state as state_lib


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


def gt_voxel_labels(sequence, *, voxel_size: float = 0.1, capacity=None) -> dict:
  """Majority GT label per voxel, by fusing one-hot GT labels with `rules.sum_labels()`.

  Args:
    sequence: an `RGBDSequence` with `labels`.
    voxel_size: voxel edge in metres (use the same as the maps you evaluate).
    capacity: map capacity (power of two); default: twice the number of distinct voxels,
      rounded up to a power of two (counted with a NumPy pass first).

  Returns:
    dict with `coords (N, 3) int32` voxel indices (`floor(p_world / voxel_size)`),
    `labels (N,) int32` majority label, and `hits (N,) int32` labelled pixels per voxel.

  Raises:
    ValueError: the sequence has no labels.
  """
  if sequence.labels is None:
    raise ValueError(f"sequence {sequence.name!r} has no ground-truth labels")
  num_classes = sequence.num_classes
  if capacity is None:
    capacity = state_lib.capacity_for(count_voxels(sequence, voxel_size=voxel_size), load=0.5)
  rule = rules.sum_labels()
  state = state_lib.init_map(capacity=capacity, num_classes=num_classes, voxel_size=voxel_size,
                             rule=rule)
  for frame in sequence:
    labels = jnp.asarray(frame.labels, jnp.int32)
    ok = (labels >= 0) & (labels < num_classes)
    depth = jnp.where(ok, jnp.asarray(frame.depth, jnp.float32), 0.0)
    probs = jax.nn.one_hot(jnp.where(ok, labels, 0), num_classes, dtype=jnp.float32)
    state = fusion.fuse_frame(state, fusion.Frame(depth, frame.T_world_cam, probs),
                              sequence.camera, rule)
  out = readout.read_map(state)
  return {"coords": out["coords"], "labels": out["labels"], "hits": out["hits"]}
