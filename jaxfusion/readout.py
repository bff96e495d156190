"""Reading a map out: per-voxel labels, normalised posteriors, entropy and confidence.

`voxel_posteriors` is jittable and differentiable (for losses on the map); `read_map` is the
host-side view over occupied voxels as NumPy arrays. Shape legend: C slots, N occupied voxels,
K classes.
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import hashing
from jaxfusion import numerics
from jaxfusion.state import MapState, warn_if_dropped


def voxel_posteriors(state: MapState) -> tuple[jax.Array, jax.Array]:
  """Normalised posterior of every slot, and which slots hold a voxel (jittable).

  Returns:
    `(posterior (C, K) float32, occupied (C,) bool)`; empty slots hold the rule's prior.
  """
  posterior = jax.vmap(state.posterior_fn)(state.rows)
  return posterior, state.keys[:, 0] != hashing.EMPTY


def read_map(state: MapState) -> dict:
  """The occupied voxels of one map as NumPy arrays, sorted by voxel coordinates.

  Warns with `MapFullWarning` if any voxel was dropped because the map was full.

  Returns:
    dict with
      `coords (N, 3) int32` integer voxel indices (world point = (coords + 0.5) · voxel_size),
      `centers (N, 3) float32` voxel centres in metres,
      `labels (N,) int32` argmax of the posterior (of S for sum_probs, N for sum_labels),
      `posterior (N, K) float32` normalised (`S/ΣS`, `N/ΣN`, or `exp(log P)`),
      `hits (N,) int32` pixels fused into the voxel,
      `entropy (N,) float32` of the posterior in nats,
      `confidence (N, K) float32` ᾱ — only for the Dirichlet rules.
  """
  if not isinstance(state, MapState):
    raise TypeError(f"read_map expects a MapState; got {type(state).__name__}")
  if state.keys.ndim != 2:
    raise ValueError("read_map expects one map; index a batched map first, e.g. "
                     "jax.tree.map(lambda x: x[i], state)")
  keys = np.asarray(state.keys)
  occupied = np.nonzero(keys[:, 0] != hashing.EMPTY)[0]
  coords = keys[occupied]
  order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
  slots = occupied[order]
  coords = coords[order]
  rows = jax.tree.map(lambda r: jnp.asarray(r)[slots], state.rows)
  posterior = jax.vmap(state.posterior_fn)(rows)
  out = {
      "coords": coords.astype(np.int32),
      "centers": ((coords + 0.5) * float(state.voxel_size)).astype(np.float32),
      "labels": np.asarray(jnp.argmax(posterior, axis=-1), np.int32),
      "posterior": np.asarray(posterior, np.float32),
      "hits": np.asarray(state.hits)[slots].astype(np.int32),
      "entropy": np.asarray(numerics.entropy(posterior), np.float32),
  }
  if state.confidence_fn is not None:
    out["confidence"] = np.asarray(jax.vmap(state.confidence_fn)(rows), np.float32)
  warn_if_dropped(int(state.num_dropped), state.capacity)
  return out
