"""Grouping equal int32×3 keys without sorting: which pixels (or ray samples) share a voxel.

Used by the semantic engine (`fusion`: a frame's pixels per voxel), the geometry layer (`tsdf`:
a frame's ray samples per block) and `Mapper` (how many voxels a frame would add).

Shape legend: N keys.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import hashing

# Cells of the per-frame grouping grid (int32 each, 8 MiB, filled once per grouping round). A
# frame whose keys span at most this many cells (a box of 128³ voxels: an indoor frame at 0.1 m
# spans about 60×60×30) is grouped in one collision-free round; larger frames fall back to
# hashing keys into the grid, a few rounds.
_GRID_CELLS = 2**21
_ROUND_SALT = np.uint32(0x9E3779B9)


class PixelGroups(NamedTuple):
  """A frame's valid pixels grouped by voxel (groups numbered 0 … U−1)."""
  segment: jax.Array        # [N] int32 group of each pixel; N for invalid pixels
  first_pixel: jax.Array    # [N] int32 a pixel of group g in row g (rows ≥ num_groups: 0)
  num_groups: jax.Array     # [] int32 U


def group_pixels(keys: jax.Array, valid: jax.Array) -> PixelGroups:
  """Groups pixels with equal voxel keys, without sorting.

  Each round scatters the still-ungrouped pixels into a grid of `_GRID_CELLS` cells with a
  scatter-min of their pixel index; a pixel whose cell's winner has its own key is grouped with
  that winner. When the frame's keys span a box of at most `_GRID_CELLS` cells the cell is the
  key's position in the box, so one round groups every pixel; otherwise cells are hashes of the
  key (salted per round) and the rare keys that collide with another key go to the next round.
  All pixels of one key always share a cell, so they are grouped together, and every round
  groups at least the winner of each occupied cell, so the loop ends.

  Args:
    keys: `(N, 3) int32` voxel key of each pixel.
    valid: `(N,) bool` pixels to group; the others get segment N.

  Returns:
    PixelGroups, groups numbered in the order of their first pixel.
  """
  n = keys.shape[0]
  lanes = jnp.arange(n, dtype=jnp.int32)
  big = np.int32(np.iinfo(np.int32).max)
  low = jnp.min(jnp.where(valid[:, None], keys, big), axis=0)
  high = jnp.max(jnp.where(valid[:, None], keys, -big), axis=0)
  span = (high - low + 1).astype(jnp.float32)
  fits = jnp.prod(span) <= _GRID_CELLS          # also true when no pixel is valid
  rel = jnp.where(valid[:, None], keys - low[None, :], 0)
  span_i = jnp.maximum(high - low + 1, 1)
  box_cell = (rel[:, 0] * span_i[1] + rel[:, 1]) * span_i[2] + rel[:, 2]
  key_hash = hashing.hash_keys(keys)

  def cond(carry):
    _, pending, _ = carry
    return jnp.any(pending)

  def body(carry):
    rep, pending, salt = carry
    hashed = (hashing.fmix32(key_hash ^ salt) & np.uint32(_GRID_CELLS - 1)).astype(jnp.int32)
    cell = jnp.where(pending, jnp.where(fits, box_cell, hashed), _GRID_CELLS)
    grid = jnp.full(_GRID_CELLS, n, jnp.int32).at[cell].min(lanes, mode="drop")
    winner = grid[jnp.minimum(cell, _GRID_CELLS - 1)]
    same = pending & jnp.all(keys[jnp.minimum(winner, n - 1)] == keys, axis=-1)
    return jnp.where(same, winner, rep), pending & ~same, salt + _ROUND_SALT

  rep, _, _ = jax.lax.while_loop(
      cond, body, (jnp.full(n, n, jnp.int32), jnp.asarray(valid, bool), jnp.uint32(0)))
  first = rep == lanes                            # invalid pixels keep rep = n ≠ lane
  group_of_first = jnp.cumsum(first, dtype=jnp.int32) - 1
  segment = jnp.where(valid, group_of_first[jnp.minimum(rep, n - 1)], n)
  first_pixel = jnp.zeros(n, jnp.int32).at[jnp.where(first, group_of_first, n)].set(
      lanes, mode="drop", unique_indices=True)
  return PixelGroups(segment, first_pixel, jnp.sum(first, dtype=jnp.int32))
