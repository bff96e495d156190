"""Reading a map out: per-voxel labels, normalised posteriors, entropy and confidence.

`voxel_posteriors` is jittable and differentiable (for losses on the map); `query` is jittable
and answers for arbitrary world points (a planner's information-gain loop); `read_map` is the
host-side view over occupied voxels as NumPy arrays, optionally restricted to some classes and
an axis-aligned box. Shape legend: C slots, N occupied voxels, K classes, `...` any leading
shape of query points.
"""

import numbers
from typing import NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import hashing
from jaxfusion import numerics
from jaxfusion.state import MapState, observed_at, observed_slots, warn_if_dropped


def voxel_posteriors(state: MapState) -> tuple[jax.Array, jax.Array]:
  """Normalised posterior of every slot, and which slots hold a voxel (jitted; jittable).

  A plain call runs one compiled program per map shape and rule (not op by op over the `(C, K)`
  rows); under a caller's transformation it traces inline.

  Returns:
    `(posterior (C, K) float32, occupied (C,) bool)`; empty slots hold the rule's prior.
    `occupied` is `state.observed_slots`: a stored voxel with hits, not marked free.

  Raises:
    TypeError: `state` is not a MapState.
  """
  if not isinstance(state, MapState):
    raise TypeError(f"voxel_posteriors expects a MapState; got {type(state).__name__}")
  return _voxel_posteriors(state)


@jax.jit
def _voxel_posteriors(state: MapState) -> tuple[jax.Array, jax.Array]:
  posterior = jax.vmap(state.posterior_fn)(state.rows)
  occupied = observed_slots(state)
  if state.spatial is not None:
    smoothed = smooth(state, state.keys, posterior)
    posterior = jnp.where(occupied[:, None], smoothed, posterior)
  return posterior, occupied


# The 26 neighbour offsets of a voxel (x-major, then y, then z) and their shells (docs/
# equations.md §4.1): 0 = a shared face, 1 = an edge, 2 = a corner.
NEIGHBOUR_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1)
                              for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)], np.int32)
NEIGHBOUR_SHELLS = (np.abs(NEIGHBOUR_OFFSETS).sum(axis=1) - 1).astype(np.int32)


def smooth(state: MapState, keys: jax.Array, posterior: jax.Array) -> jax.Array:
  """The spatial term (docs/equations.md §4.1): `(N, K) float32` smoothed posteriors of voxels
  with keys `(N, 3) int32` and unsmoothed posteriors `(N, K)`, from their observed neighbours
  in `state` (jittable; the caller keeps the result only where the voxel itself is observed).

  The 26 neighbours are visited one offset after another (a `lax.scan`: memory O(N·K), not
  O(26·N·K)); each is found through the hash, and its unsmoothed posterior is read from its row.
  """
  num_classes = posterior.shape[-1]

  def visit(carry, item):
    sums, counts = carry
    offset, shell = item
    slots, found = hashing.lookup(state.keys, keys + offset, max_probes=state.max_probes)
    seen = found & observed_at(state, slots)
    near = jax.vmap(state.posterior_fn)(jax.tree.map(lambda r: r[slots], state.rows))
    at = jax.nn.one_hot(shell, 3, dtype=jnp.float32)                      # (3,)
    sums = sums + jnp.where(seen[:, None, None], at[None, :, None] * near[:, None, :], 0.0)
    counts = counts + seen[:, None].astype(jnp.float32) * at[None, :]
    return (sums, counts), None

  n = keys.shape[0]
  init = (jnp.zeros((n, 3, num_classes), jnp.float32), jnp.zeros((n, 3), jnp.float32))
  (sums, counts), _ = jax.lax.scan(
      visit, init, (jnp.asarray(NEIGHBOUR_OFFSETS), jnp.asarray(NEIGHBOUR_SHELLS)))
  means = sums / jnp.maximum(counts, 1.0)[..., None]                      # (N, 3, K)
  evidence = jnp.einsum("nsk,ks->nk", means, state.spatial)
  return jax.nn.softmax(numerics.safe_log(posterior) + evidence, axis=-1)


@jax.jit
def _posteriors_at(state: MapState, slots: jax.Array) -> jax.Array:
  """`(N, K)` posteriors of the voxels at `slots` (smoothed where the map has a spatial
  kernel; the slots are observed ones)."""
  posterior = jax.vmap(state.posterior_fn)(jax.tree.map(lambda r: r[slots], state.rows))
  if state.spatial is not None:
    posterior = smooth(state, state.keys[slots], posterior)
  return posterior


class QueryResult(NamedTuple):
  """What the map holds at some world points (`query`); `...` is the points' leading shape."""
  found: jax.Array       # [...] bool, the point's voxel is in the map
  posterior: jax.Array   # [..., K] float32, the voxel's posterior; the prior where not found
  entropy: jax.Array     # [...] float32, entropy of `posterior` in nats
  hits: jax.Array        # [...] int32, pixels fused into the voxel; 0 where not found


def _prior_posterior(state: MapState) -> jax.Array:
  """`(K,) float32` posterior of the rule's prior: the row an empty slot holds (docs/
  equations.md §1.4), read from the first empty slot; uniform if the map has no empty slot."""
  empty = state.keys[:, 0] == hashing.EMPTY
  slot = jnp.argmax(empty)
  prior = state.posterior_fn(jax.tree.map(lambda r: r[slot], state.rows))
  uniform = jnp.full((state.num_classes,), 1.0 / state.num_classes, jnp.float32)
  return jnp.where(empty[slot], prior.astype(jnp.float32), uniform)


def query_keys_unchecked(state: MapState, keys: jax.Array, valid: jax.Array) -> QueryResult:
  """What the map holds at voxel keys `(N, 3) int32` (`valid (N,) bool`: False reads as not
  found): `query` after the point → key step, for callers that hold keys already (the mesh
  labels ask once per distinct voxel, not once per vertex). No input checks."""
  slots, found = hashing.lookup(state.keys, keys, max_probes=state.max_probes)
  found = found & valid & observed_at(state, slots)
  posterior = jax.vmap(state.posterior_fn)(jax.tree.map(lambda r: r[slots], state.rows))
  if state.spatial is not None:       # docs/equations.md §4.1: the voxel's smoothed posterior
    posterior = smooth(state, keys, posterior)
  posterior = jnp.where(found[:, None], posterior, _prior_posterior(state)[None, :])
  hits = jnp.where(found, state.hits[slots], 0)
  return QueryResult(found=found, posterior=posterior, entropy=numerics.entropy(posterior),
                     hits=hits)


def query_unchecked(state: MapState, points_world: jax.Array) -> QueryResult:
  """`query`'s pure body, without the input checks (use `query`)."""
  points = jnp.asarray(points_world, jnp.float32)
  lead = points.shape[:-1]
  keys, in_range = camera_lib.voxel_keys(points.reshape(-1, 3), state.voxel_size)
  q = query_keys_unchecked(state, keys, in_range)
  return QueryResult(
      found=q.found.reshape(lead),
      posterior=q.posterior.reshape(lead + (state.num_classes,)),
      entropy=q.entropy.reshape(lead),
      hits=q.hits.reshape(lead),
  )


_query_jit = jax.jit(query_unchecked)


def key_codes_unchecked(state: MapState, keys: jax.Array, valid: jax.Array) -> jax.Array:
  """`(N,) int32` where the map holds voxel keys `(N, 3) int32`: the slot where
  `query_keys_unchecked` finds the key (observed), −1 where it does not, −2 where not `valid`
  (out of range). For the mesh labels, which ask once per distinct slot
  (`slot_labels_unchecked`). No input checks."""
  slots, found = hashing.lookup(state.keys, keys, max_probes=state.max_probes)
  found = found & valid & observed_at(state, slots)
  return jnp.where(found, slots, jnp.where(valid, -1, -2)).astype(jnp.int32)


def point_codes_unchecked(state: MapState, points_world: jax.Array) -> jax.Array:
  """`key_codes_unchecked` of world points `(N, 3)`, keyed as `query` keys them."""
  keys, in_range = camera_lib.voxel_keys(jnp.asarray(points_world, jnp.float32),
                                         state.voxel_size)
  return key_codes_unchecked(state, keys, in_range)


def slot_labels_unchecked(state: MapState, slots: jax.Array) -> tuple:
  """`(labels (U,) int32, confidence (U,) float32, entropy (U,) float32)` of the voxels at
  held slots `(U,) int32` (< 0: not held, read as `query` reads a voxel it does not find: −1,
  0 and the prior's entropy): what `query` gives at those voxels' keys. No input checks."""
  held = slots >= 0
  q = query_keys_unchecked(state, state.keys[jnp.maximum(slots, 0)], held)
  labels = jnp.where(q.found, jnp.argmax(q.posterior, axis=-1), -1).astype(jnp.int32)
  confidence = jnp.where(q.found, jnp.max(q.posterior, axis=-1), 0.0).astype(jnp.float32)
  return labels, confidence, q.entropy.astype(jnp.float32)


# For the mesh labels (jaxfusion.mesh), on host-padded arrays.
_key_codes_jit = jax.jit(key_codes_unchecked)
_point_codes_jit = jax.jit(point_codes_unchecked)
_slot_labels_jit = jax.jit(slot_labels_unchecked)


def query(state: MapState, points_world: jax.Array) -> QueryResult:
  """What the map holds at world points: found, posterior, entropy and hits (jittable).

  A point falls in the voxel `floor(p / voxel_size)` (docs/equations.md §1.1), computed by the
  same function and in the same float32 arithmetic as the engine's keys, so any point inside a
  fused voxel (its centre included) finds that voxel. Points that are not finite or whose key
  is out of range (±KEY_LIMIT) are simply not found.

  A point whose voxel is not in the map (never observed, out of range, or dropped because the
  map was full) reports what an unobserved voxel holds: the posterior of the rule's prior —
  the row every empty slot holds (§1.4), uniform `1/K` for all six rules of the paper, so the
  entropy is `log K` — and 0 hits. A custom rule with a non-uniform prior reports that prior.
  It is read from an empty slot (one pass over the keys); a map with no empty slot at all
  reports uniform.

  Jitted (no host sync), and jittable, vmappable and differentiable as a whole: `jax.jit(query)`
  takes the state as an argument and compiles once per map and points shape; the posterior is a
  gather of the map's rows, so gradients flow to the rows and, through `fuse_frame`, to the
  rule's hyperparameters. Batched maps: `jax.vmap(query, in_axes=(0, None))`.

  A planner scores a candidate view by back-projecting the depth it expects to see and
  averaging `query(state, p_world).entropy` (README, "Queries").

  Args:
    state: one map (not a batched one).
    points_world: `(..., 3)` float world points in metres, any leading shape (NaN/inf allowed).

  Returns:
    A QueryResult of `found (...,) bool`, `posterior (..., K) float32`, `entropy (...,)
    float32` (nats) and `hits (...,) int32`.

  Raises:
    TypeError: `state` is not a MapState, or the points are not a float array.
    ValueError: a batched map, or points whose last axis is not 3.
  """
  if not isinstance(state, MapState):
    raise TypeError(f"query expects a MapState; got {type(state).__name__}")
  if state.keys.ndim != 2:
    raise ValueError("query expects one map; index a batched map first, e.g. "
                     "jax.tree.map(lambda x: x[i], state), or jax.vmap(query, in_axes=(0, None))")
  if not isinstance(points_world, (jax.Array, np.ndarray)):
    try:
      points_world = np.asarray(points_world)      # a list: one leaf, not one per number
    except (TypeError, ValueError):
      raise TypeError("points_world must be a float array of world points (..., 3) in metres; "
                      f"got {type(points_world).__name__}") from None
  shape, dtype = points_world.shape, points_world.dtype
  if not jnp.issubdtype(dtype, jnp.floating):
    raise TypeError(f"points_world must be a float array of world points in metres; got dtype "
                    f"{dtype}")
  if len(shape) < 1 or shape[-1] != 3:
    raise ValueError(f"points_world must have shape (..., 3); got {tuple(shape)}")
  return _query_jit(state, points_world)


def _check_classes(classes, num_classes: int) -> np.ndarray:
  """`classes` (an index or a sequence of indices) as a sorted `(M,) int64` array."""
  items = [classes] if isinstance(classes, numbers.Integral) else classes
  try:
    items = list(items)
  except TypeError:
    raise TypeError(f"classes must be a sequence of class indices; got {classes!r}") from None
  for c in items:
    if isinstance(c, (bool, np.bool_)) or not isinstance(c, numbers.Integral):
      raise TypeError(f"classes must be integer class indices; got {c!r} in {classes!r}")
    if not 0 <= int(c) < num_classes:
      raise ValueError(f"class index {int(c)} out of range for a map of {num_classes} classes "
                       f"(0 … {num_classes - 1})")
  return np.unique(np.asarray([int(c) for c in items], np.int64))


def _check_box(box) -> tuple[np.ndarray, np.ndarray]:
  """`box = (min_xyz, max_xyz)` in metres as two finite `(3,) float64` arrays with min ≤ max."""
  try:
    lo, hi = box
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
  except (TypeError, ValueError):
    raise TypeError("box must be a pair (min_xyz, max_xyz) of 3 numbers each, in metres; got "
                    f"{box!r}") from None
  if lo.shape != (3,) or hi.shape != (3,):
    raise ValueError(f"box corners must each have shape (3,); got {lo.shape} and {hi.shape}")
  if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
    raise ValueError(f"box corners must be finite; got {lo.tolist()} and {hi.tolist()}")
  if np.any(lo > hi):
    raise ValueError(f"box min must be ≤ max on every axis; got min {lo.tolist()} and max "
                     f"{hi.tolist()}")
  return lo, hi


def coordinate_order(coords: np.ndarray) -> np.ndarray:
  """`(N,) int64`: the order that sorts distinct voxel coordinates `(N, 3) int32` by x, then y,
  then z (what `np.lexsort` of the columns gives), by one sort of an int64 code. The code is
  the coordinates relative to their minimum in mixed radix, which orders them the same way;
  three stable sorts (`lexsort`) took half of `read_map` at 10⁷ voxels. Coordinates spanning
  more than 2^63 codes (a box wider than ~2·10⁶ voxels on each axis) fall back to `lexsort`."""
  coords = np.asarray(coords)
  if len(coords) == 0:
    return np.zeros(0, np.int64)
  low = coords.min(axis=0).astype(np.int64)
  span = coords.max(axis=0).astype(np.int64) - low + 1
  if int(span[0]) * int(span[1]) * int(span[2]) >= 2**63:
    return np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
  rel = coords.astype(np.int64) - low
  code = (rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2]
  return np.argsort(code)


def read_map(state: MapState, *, classes: Optional[Sequence[int]] = None,
             box: Optional[tuple] = None) -> dict:
  """The occupied voxels of one map as NumPy arrays, sorted by voxel coordinates.

  Warns with `MapFullWarning` if any voxel was dropped because the map was full.

  Args:
    state: one map (not a batched one).
    classes: keep only the voxels whose label is one of these class indices (`0 … K−1`).
    box: `(min_xyz, max_xyz)` in metres, each `(3,)`: keep only the voxels whose centre (the
      float32 `centers` below) lies in this axis-aligned box, faces included.

  Returns:
    dict with
      `coords (N, 3) int32` integer voxel indices (world point = (coords + 0.5) · voxel_size),
      `centers (N, 3) float32` voxel centres in metres,
      `labels (N,) int32` argmax of the posterior (of S for sum_probs, N for sum_labels),
      `posterior (N, K) float32` normalised (`S/ΣS`, `N/ΣN`, or `exp(log P)`),
      `hits (N,) int32` pixels fused into the voxel,
      `entropy (N,) float32` of the posterior in nats,
      `confidence (N, K) float32` ᾱ — only for the Dirichlet rules.

  Raises:
    TypeError: `state` is not a MapState, or `classes`/`box` are not of the types above.
    ValueError: a batched map, a class index out of range, or a box that is not finite, not of
      shape (3,) per corner, or has min > max on some axis.
  """
  if not isinstance(state, MapState):
    raise TypeError(f"read_map expects a MapState; got {type(state).__name__}")
  if state.keys.ndim != 2:
    raise ValueError("read_map expects one map; index a batched map first, e.g. "
                     "jax.tree.map(lambda x: x[i], state)")
  wanted = None if classes is None else _check_classes(classes, state.num_classes)
  bounds = None if box is None else _check_box(box)
  keys = np.asarray(state.keys)
  occupied = np.nonzero(np.asarray(observed_slots(state)))[0]
  coords = keys[occupied]
  order = coordinate_order(coords)
  slots = occupied[order]
  coords = coords[order]
  rows = jax.tree.map(lambda r: jnp.asarray(r)[slots], state.rows)
  if state.spatial is None:
    posterior = jax.vmap(state.posterior_fn)(rows)
  else:   # padded to a power of two: a few compiled programs for every map size
    padded = np.zeros(1 << max(int(len(slots)) - 1, 0).bit_length(), np.int32)
    padded[:len(slots)] = slots
    posterior = _posteriors_at(state, jnp.asarray(padded))[:len(slots)]
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
  # Selected on the host after reading every voxel out, so that the JAX operations above see
  # one shape per map, whatever the selection (no compilation per box or class set).
  if wanted is not None or bounds is not None:
    keep = np.ones(len(slots), bool)
    if wanted is not None:
      keep &= np.isin(out["labels"], wanted)
    if bounds is not None:
      keep &= np.all((out["centers"] >= bounds[0]) & (out["centers"] <= bounds[1]), axis=-1)
    out = {name: value[keep] for name, value in out.items()}
  warn_if_dropped(int(state.num_dropped), state.capacity)
  return out
