"""The map state: a frozen pytree of fixed-capacity dense arrays, allocated once.

Shape legend: C slots (capacity, a power of two), K classes.
"""

import functools
import math
import warnings
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxfusion import free_space as free_space_lib
from jaxfusion import hashing
from jaxfusion import tsdf as tsdf_lib
from jaxfusion.rules import base as rules_base

DEFAULT_MAX_PROBES = 64


class MapFullWarning(UserWarning):
  """Some voxels could not be stored because the map was full (or probing hit its bound)."""


@struct.dataclass
class MapState:
  """A semantic voxel map. Donated to and returned by `fuse_frame`; never mutate it.

  The per-voxel rows are owned by the rule the map was made for (`rule_name`); a slot whose
  key is EMPTY still holds the rule's prior, so a newly inserted voxel starts from it.
  """
  keys: jax.Array           # [C, 3] int32 voxel coordinates, hashing.EMPTY in unused slots
  hits: jax.Array           # [C] int32 pixels fused into each voxel (saturating)
  rows: Any                 # rule-owned per-voxel state: dict of [C, K] float32
  claims: jax.Array         # [C] int32 scratch for parallel insertion (no meaning between calls)
  num_occupied: jax.Array   # [] int32 voxels stored
  num_dropped: jax.Array    # [] int32 voxel insertions refused (map full / probe bound reached)
  voxel_size: jax.Array     # [] float32 voxel edge in metres
  rule_name: str = struct.field(pytree_node=False)
  max_probes: int = struct.field(pytree_node=False)
  posterior_fn: Callable = struct.field(pytree_node=False)
  confidence_fn: Optional[Callable] = struct.field(pytree_node=False)
  # The geometry layer (a TSDF of its own voxel size and hash), or None: a map without it is
  # the same pytree, and is fused by the same program, as before the layer existed.
  geometry: Optional[tsdf_lib.TSDFState] = None
  # The free-space layer (occupancy log-odds per slot, docs/equations.md §10), or None: the same
  # pytree and program as before the layer existed.
  free_space: Optional[free_space_lib.FreeSpaceState] = None
  # The spatial term's per-class kernel `(K, 3)` of the rule the map was made for (docs/
  # equations.md §4.1), or None: the read-out reports unsmoothed posteriors, as before.
  spatial: Optional[jax.Array] = None

  @property
  def capacity(self) -> int:
    return self.keys.shape[-2]

  @property
  def num_classes(self) -> int:
    return jax.tree.leaves(self.rows)[0].shape[-1]


def capacity_for(num_voxels: int, *, load: float = 0.25, minimum: int = 1024) -> int:
  """The smallest power-of-two capacity that holds `num_voxels` at load factor ≤ `load`.

  `capacity_for(n)` is the map size the commands give a sequence with n GT voxels (4n slots,
  at least `minimum`); keep the load factor below ~0.5 (docs/equations.md §1.3: probes
  lengthen and a full map drops voxels) or use a growing `Mapper`.
  """
  if not 0.0 < load <= 1.0:
    raise ValueError(f"load must lie in (0, 1]; got {load}")
  need = max(int(math.ceil(int(num_voxels) / load)), 2)
  return max(int(minimum), 1 << (need - 1).bit_length())


def _check_positive_int(value, name):
  if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
    raise ValueError(f"{name} must be a positive integer; got {value!r}")
  return int(value)


def init_map(*, capacity: int, num_classes: int, voxel_size: float = 0.1,
             rule: rules_base.FusionRule, max_probes: int = DEFAULT_MAX_PROBES,
             geometry=None, free_space=False) -> MapState:
  """Allocates an empty map at full capacity.

  Args:
    capacity: number of slots C; rounded up to a power of two (with a warning) if it is not one.
      Keep the fill below ~50 % for short probes (docs/equations.md §1.3).
    num_classes: K ≥ 2.
    voxel_size: voxel edge in metres (> 0).
    rule: the FusionRule this map will be fused with; it owns the per-voxel rows. A rule whose
      parameters hold `spatial` (`(K, 3)`, docs/equations.md §4.1) gives the map that kernel:
      its read-out reports smoothed posteriors.
    max_probes: bound on the linear-probing sequence; keys that find no slot within it are
      dropped and counted.
    geometry: switches the geometry layer on: a `tsdf.TSDFConfig` (or a `TSDFState`, e.g. an
      empty one from `tsdf.init_tsdf`); `fuse_frame` then integrates every frame's depth into
      its TSDF in the same call. None (default): semantics only.
    free_space: switches free-space clearing on (docs/equations.md §10): True for OctoMap's
      numbers, or a `free_space.FreeSpaceConfig`. Each frame then marks the stored voxels its
      depth shows as free, keeps an occupancy log-odds per voxel, stops reading out voxels that
      became free and restarts a free voxel that is hit again from the prior. False (default):
      off, and every map is bit-identical to one made without the option.

  Returns:
    A MapState with every slot empty and every row at the rule's prior.
  """
  capacity = _check_positive_int(capacity, "capacity")
  num_classes = _check_positive_int(num_classes, "num_classes")
  max_probes = _check_positive_int(max_probes, "max_probes")
  if num_classes < 2:
    raise ValueError(f"num_classes must be at least 2; got {num_classes}")
  if not isinstance(rule, rules_base.FusionRule):
    raise TypeError(f"rule must be a jaxfusion.rules.FusionRule; got {type(rule).__name__}")
  if capacity & (capacity - 1):
    rounded = 1 << math.ceil(math.log2(capacity))
    warnings.warn(f"capacity {capacity} is not a power of two; rounded up to {rounded}",
                  stacklevel=2)
    capacity = rounded
  if capacity > 2**30:
    raise ValueError(f"capacity must be at most 2**30; got {capacity}")
  if rules_base.is_concrete(voxel_size):
    size = float(np.asarray(voxel_size))
    if not (math.isfinite(size) and size > 0):
      raise ValueError(f"voxel_size must be a positive finite number of metres; got {size}")
  if isinstance(geometry, tsdf_lib.TSDFConfig):
    geometry = tsdf_lib.init_tsdf(geometry)
  elif geometry is not None and not isinstance(geometry, tsdf_lib.TSDFState):
    raise TypeError(f"geometry must be a jaxfusion.tsdf.TSDFConfig, a TSDFState or None; got "
                    f"{type(geometry).__name__}")
  row = rule.init(num_classes, rule.hparams)
  rows = jax.tree.map(lambda x: jnp.tile(jnp.asarray(x, jnp.float32)[None], (capacity, 1)), row)
  spatial = rule.hparams.get("spatial") if isinstance(rule.hparams, dict) else None
  if spatial is not None and jnp.shape(spatial) != (num_classes, 3):
    raise ValueError(f"spatial must have shape (K, 3) = ({num_classes}, 3), one weight per "
                     f"class and neighbour shell; got {jnp.shape(spatial)}")
  return MapState(
      keys=hashing.empty_table(capacity),
      hits=jnp.zeros(capacity, jnp.int32),
      rows=rows,
      claims=jnp.zeros(capacity, jnp.int32),
      num_occupied=jnp.zeros((), jnp.int32),
      num_dropped=jnp.zeros((), jnp.int32),
      voxel_size=jnp.asarray(voxel_size, jnp.float32),
      rule_name=rule.name,
      max_probes=max_probes,
      posterior_fn=rule.posterior,
      confidence_fn=rule.confidence,
      geometry=geometry,
      free_space=free_space_lib.init_free_space(capacity, free_space),
      # A copy: fuse_frame donates the map, and the rule's own leaf must outlive it.
      spatial=None if spatial is None else jnp.array(spatial, jnp.float32, copy=True),
  )


def observed_slots(state: MapState) -> jax.Array:
  """`(..., C) bool`: the slots a read-out reports (docs/equations.md §4, §10.3): a stored key
  with at least one pixel fused (a frame de-integrated to 0 hits leaves its key behind), and,
  with free space on, an occupancy above the threshold. Jittable; on a map without free space
  and de-integration it is exactly `keys != EMPTY`."""
  stored = _fused_slots(state)
  occupied = free_space_lib.occupied(state.free_space)
  return stored if occupied is None else stored & occupied


def _fused_slots(state: MapState) -> jax.Array:
  """`(..., C) bool`: a stored key with at least one pixel fused."""
  return (state.keys[..., 0] != hashing.EMPTY) & (state.hits > 0)


def observed_at(state: MapState, slots: jax.Array) -> jax.Array:
  """`observed_slots` at some slots only (a gather, not a pass over C); slots from a lookup
  that found their key."""
  ok = state.hits[slots] > 0
  occupied = free_space_lib.occupied(state.free_space, slots)
  return ok if occupied is None else ok & occupied


def warn_if_dropped(num_dropped: int, capacity: int) -> None:
  if num_dropped > 0:
    warnings.warn(
        f"the map is full: {num_dropped} voxel insertions were dropped (capacity {capacity}); "
        "make a map with a larger capacity", MapFullWarning, stacklevel=3)


def map_stats(state: MapState) -> dict:
  """Host-side summary of a (single, unbatched) map; warns with MapFullWarning if it overflowed.

  Returns:
    dict with `capacity`, `num_classes`, `occupied` (keys stored), `load_factor`, `dropped`,
    `voxel_size`, `rule`, `max_probes`; with free space on also `free` (stored voxels that a
    frame has since shown as free, not read out).
  """
  if state.keys.ndim != 2:
    raise ValueError("map_stats expects one map; index a batched map first, e.g. "
                     "jax.tree.map(lambda x: x[i], state)")
  occupied = int(state.num_occupied)
  dropped = int(state.num_dropped)
  warn_if_dropped(dropped, state.capacity)
  stats = {
      "capacity": state.capacity,
      "num_classes": state.num_classes,
      "occupied": occupied,
      "load_factor": occupied / state.capacity,
      "dropped": dropped,
      "voxel_size": float(state.voxel_size),
      "rule": state.rule_name,
      "max_probes": state.max_probes,
  }
  if state.free_space is not None:
    stats["free"] = int(np.count_nonzero(_fused_slots(state))) - int(
        np.count_nonzero(observed_slots(state)))
  return stats


@functools.partial(jax.jit, static_argnames=("capacity",))
def grown_map(state: MapState, prior, *, capacity: int):
  """`grow_map`'s program (jitted, `capacity` static): the map rehashed into `capacity` slots.

  Every slot of the old table is offered to the new one in slot order, the empty ones
  inactive, so the program's shapes depend on the two capacities only (not on how many voxels
  the map holds): one compile per pair of sizes, kept by JAX's persistent compilation cache.

  Args:
    state: an unbatched map of C slots (not donated).
    prior: the rule's prior row, a dict of `(K,) float32` like one slot of `state.rows`.
    capacity: the new number of slots C' ≥ C (a power of two).

  Returns:
    `(grown, lost)`: the map of C' slots, and `() int32` the voxels that found no slot within
    the probe bound (the caller refuses a result with `lost > 0`).
  """
  occupied = state.keys[:, 0] != hashing.EMPTY
  result = hashing.insert(hashing.empty_table(capacity), jnp.zeros(capacity, jnp.int32),
                          state.keys, occupied, max_probes=state.max_probes)
  # Where each old slot's voxel goes; empty slots (and lost voxels) go nowhere.
  dest = jnp.where(occupied & result.found, result.slots, capacity)

  def move(old_rows, prior_row):
    fresh = jnp.tile(jnp.asarray(prior_row, jnp.float32)[None], (capacity, 1))
    return fresh.at[dest].set(old_rows, mode="drop")

  rows = jax.tree.map(move, state.rows, prior)
  hits = jnp.zeros(capacity, jnp.int32).at[dest].set(state.hits, mode="drop")
  free = state.free_space
  if free is not None:
    free = free.replace(
        log_odds=jnp.zeros(capacity, jnp.float32).at[dest].set(free.log_odds, mode="drop"))
  lost = jnp.sum(occupied & ~result.found, dtype=jnp.int32)
  return state.replace(keys=result.table, rows=rows, hits=hits, free_space=free,
                       claims=jnp.zeros(capacity, jnp.int32)), lost


def _slot_arrays(state: MapState) -> dict:
  """The arrays with a row per slot that a rehash moves (the key table among them)."""
  free = state.free_space
  return {"keys": state.keys, "rows": state.rows, "hits": state.hits,
          "log_odds": None if free is None else free.log_odds}


def grows_in_numpy(state: MapState, capacity: int) -> bool:
  """Whether `grow_map(state, capacity)` runs entirely in NumPy, compiling nothing: a map in
  host memory whose grown arrays stay under `hashing.HOST_MOVE_BYTES` (larger ones move with
  one compiled `hashing.moved_rows`)."""
  return hashing.on_host(state.keys) and not hashing.moves_on_device(capacity,
                                                                     _slot_arrays(state))


def grown_map_host(state: MapState, prior, *, capacity: int, on_device: Optional[bool] = None):
  """`grown_map` with the rehash in NumPy on the host: the same voxels, rows, hits and log-odds
  in a table of `capacity` slots placed by `hashing.rehash_host`, returned as device arrays.
  The slots come from NumPy, so a growing map on the CPU compiles no rehash (bench/RESULTS.md,
  "A map that grows over a long walk"); the slots a voxel lands in may differ from
  `grown_map`'s where keys collide, the map read out does not. The rows move as
  `hashing.grown_rows` moves them: in NumPy, or for large tables (`on_device`; None:
  `hashing.moves_on_device`) with one compiled `hashing.moved_rows`.

  Returns:
    `(grown, lost)` as `grown_map`: the map of C' slots and the voxels that found no slot.
  """
  free = state.free_space
  arrays = _slot_arrays(state)
  fills = {"keys": hashing.EMPTY, "rows": prior, "hits": 0,
           "log_odds": None if free is None else 0.0}
  src, dest, lost = hashing.rehash_host(state.keys, capacity, max_probes=state.max_probes)
  moved, claims = hashing.grown_rows(arrays, fills, src, dest, capacity=capacity,
                                     on_device=on_device)
  if free is not None:
    free = free.replace(log_odds=moved["log_odds"])
  grown = state.replace(keys=moved["keys"], rows=moved["rows"], hits=moved["hits"],
                        free_space=free, claims=claims)
  return grown, lost


def prior_row(state: MapState, rule: Optional[rules_base.FusionRule] = None):
  """The prior row of `state`'s rule (a dict of `(K,) float32`): the rule's, or the rows of an
  empty slot (a slot whose key is EMPTY still holds the prior)."""
  if rule is not None:
    return jax.tree.map(lambda r: jnp.asarray(r, jnp.float32),
                        rule.init(state.num_classes, rule.hparams))
  occupied = np.asarray(state.keys[:, 0]) != hashing.EMPTY
  if occupied.all():
    raise ValueError("the map has no empty slot to take the prior from: pass its rule")
  empty_slot = int(np.argmin(occupied))
  return jax.tree.map(lambda r: r[empty_slot], state.rows)


def grow_map(state: MapState, capacity: int, *,
             rule: Optional[rules_base.FusionRule] = None) -> MapState:
  """The same map in a larger table: every voxel keeps its rows (posterior, ᾱ, …) and hit
  count exactly; only the slots change.

  Not jittable (the capacity is an array shape). On the CPU it rehashes in NumPy, the arrays
  read in place (`grown_map_host`: nothing compiled); on an accelerator it runs one compiled
  program per old and new capacity (`grown_map`). Call it between frames (the `Mapper` does,
  before a frame could push the load factor past its threshold).

  Args:
    state: an unbatched map; it is not donated and stays valid.
    capacity: the new number of slots, a power of two ≥ the current capacity.
    rule: the map's rule, for the prior of the new empty slots; needed only when the old map
      has no empty slot to copy the prior from.

  Returns:
    A MapState with `capacity` slots, the same voxels, rows, hits, occupancy log-odds (with
    free space on), dropped count, voxel size and rule.

  Raises:
    ValueError: a batched map, a capacity that is not a power of two or is smaller than the
      current one, a rule that does not match, or a table too full to rehash within
      `max_probes` (pick a larger capacity).
  """
  if not isinstance(state, MapState):
    raise TypeError(f"grow_map expects a MapState; got {type(state).__name__}")
  if state.keys.ndim != 2:
    raise ValueError("grow_map expects one map; index a batched map first")
  capacity = _check_positive_int(capacity, "capacity")
  if capacity & (capacity - 1) or capacity > 2**30:
    raise ValueError(f"capacity must be a power of two ≤ 2**30; got {capacity}")
  if capacity < state.capacity:
    raise ValueError(f"grow_map cannot shrink a map: capacity {capacity} < {state.capacity}")
  if rule is not None and rule.name != state.rule_name:
    raise ValueError(f"rule {rule.name!r} does not match the map's {state.rule_name!r}")
  if hashing.on_host(state.keys):
    grown, lost = grown_map_host(state, prior_row(state, rule), capacity=capacity)
  else:
    grown, lost = grown_map(state, prior_row(state, rule), capacity=capacity)
  lost = int(lost)
  if lost:
    raise ValueError(f"{lost} of {int(state.num_occupied)} voxels found no slot within "
                     f"{state.max_probes} probes at capacity {capacity}: grow to a larger one")
  return grown
