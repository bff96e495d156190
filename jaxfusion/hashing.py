"""Spatial hash of int32×3 voxel keys: bounded linear probing, parallel insert and lookup.

The table is a dense `(C, 3) int32` array, C a power of two; an unused slot holds EMPTY in all
three columns. A whole frame's keys are inserted in one vectorised `lax.while_loop`: in round r
every pending key looks at slot `(hash + r) mod C`; keys that find themselves are done, keys
that find an empty slot try to claim it, and one claimant per slot wins (the others probe on).
Keys still pending after `max_probes` rounds are reported as not found, so the caller can count
them as dropped — stored keys are never overwritten. There is no deletion, which keeps the
linear-probing invariant: a stored key sits before the first empty slot of its probe sequence.

Shape legend: C slots, N keys.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

# Sentinel stored in every column of an unused slot. Valid keys are bounded by camera.KEY_LIMIT,
# so no key can ever equal it.
EMPTY = np.int32(np.iinfo(np.int32).min)

_PRIME_X = np.uint32(0x9E3779B1)
_PRIME_Y = np.uint32(0x85EBCA77)
_PRIME_Z = np.uint32(0xC2B2AE3D)


def fmix32(h: jax.Array) -> jax.Array:
  """MurmurHash3's 32-bit finaliser: every input bit affects every output bit."""
  h = h ^ (h >> 16)
  h = h * np.uint32(0x85EBCA6B)
  h = h ^ (h >> 13)
  h = h * np.uint32(0xC2B2AE35)
  return h ^ (h >> 16)


def hash_keys(keys: jax.Array) -> jax.Array:
  """Hashes `(N, 3) int32` keys to `(N,) uint32`."""
  k = jax.lax.bitcast_convert_type(jnp.asarray(keys, jnp.int32), jnp.uint32)
  return fmix32(k[:, 0] * _PRIME_X ^ k[:, 1] * _PRIME_Y ^ k[:, 2] * _PRIME_Z)


def hash_keys_host(keys: np.ndarray) -> np.ndarray:
  """`hash_keys` in NumPy, on the host: `(N, 3) int32` keys to the same `(N,) uint32`."""
  k = np.ascontiguousarray(keys, np.int32).view(np.uint32).reshape(-1, 3)
  return fmix32(k[:, 0] * _PRIME_X ^ k[:, 1] * _PRIME_Y ^ k[:, 2] * _PRIME_Z)


def _home_slots_host(keys: np.ndarray, capacity: int) -> np.ndarray:
  return (hash_keys_host(keys) & np.uint32(capacity - 1)).astype(np.int64)


def on_host(x: jax.Array) -> bool:
  """True when the array lives in host memory (JAX's CPU devices), where NumPy reads it in
  place: the host twins below then serve a growing map with nothing to compile."""
  return all(device.platform == "cpu" for device in x.devices())


def to_device_of(values: np.ndarray, like: jax.Array) -> jax.Array:
  """A NumPy array copied to where `like` lives, committed to its device only if `like` is
  (a committed array would give the jitted programs a new cache key, and a recompile): the
  host twins' results handed back. `jax.device_put` copies in one pass; `jnp.asarray` of a
  fresh NumPy array took two to four times as long at tens of megabytes (a growth's tables).
  """
  if getattr(like, "committed", False):
    return jax.device_put(values, next(iter(like.devices())))
  return jax.device_put(values)


def insert_host(capacity: int, keys: np.ndarray, *, max_probes: int, with_table: bool = True):
  """Places distinct keys into an empty table of `capacity` slots, in NumPy on the host: the
  rehash of a growing map without a program compiled for its capacity.

  The same probing as `insert`: in round r every pending key looks at slot
  `(hash + r) mod C`, one key per empty slot wins it (the first in order) and the others probe
  on, up to `max_probes` rounds. So the table keeps `insert`'s invariant (a key sits before the
  first empty slot of its probe sequence) and `lookup` and `insert` find every key placed.

  Args:
    capacity: C, a power of two.
    keys: `(N, 3) int32` distinct keys.
    max_probes: the table's probe bound.
    with_table: False: only the slots (the table is None), for a caller that builds the table
      elsewhere (`rehash_host`, whose table `grown_rows` builds).

  Returns:
    `(table (C, 3) int32, slots (N,) int32, found (N,) bool)`: keys not found did not fit.
  """
  keys = np.ascontiguousarray(keys, np.int32).reshape(-1, 3)
  table = np.full((capacity, 3), EMPTY, np.int32) if with_table else None
  home = _home_slots_host(keys, capacity)
  slots = np.zeros(keys.shape[0], np.int32)
  pending = np.arange(keys.shape[0])
  taken = np.zeros(capacity, bool)
  for probe in range(max_probes):
    if not pending.size:
      break
    slot = (home[pending] + probe) & (capacity - 1)
    free = ~taken[slot]
    # One winner per free slot: the first pending key that looks at it.
    _, first = np.unique(slot[free], return_index=True)
    won = np.flatnonzero(free)[first]
    if with_table:
      table[slot[won]] = keys[pending[won]]
    taken[slot[won]] = True
    slots[pending[won]] = slot[won]
    placed = np.zeros(pending.size, bool)
    placed[won] = True
    pending = pending[~placed]
  found = np.ones(keys.shape[0], bool)
  found[pending] = False
  return table, slots, found


def lookup_host(table: np.ndarray, keys: np.ndarray, *, max_probes: int):
  """`lookup` in NumPy on the host: `(slots (N,) int32, found (N,) bool)` of keys `(N, 3)` in
  a table `(C, 3) int32` (a NumPy array, or a JAX array in host memory, read in place). The
  same probe sequence, so it finds exactly what `lookup` finds; it compiles nothing."""
  table = np.asarray(table)
  keys = np.ascontiguousarray(keys, np.int32).reshape(-1, 3)
  capacity = table.shape[0]
  home = _home_slots_host(keys, capacity)
  slots = np.zeros(keys.shape[0], np.int32)
  found = np.zeros(keys.shape[0], bool)
  pending = np.arange(keys.shape[0])
  for probe in range(max_probes):
    if not pending.size:
      break
    slot = (home[pending] + probe) & (capacity - 1)
    stored = table[slot]
    match = np.all(stored == keys[pending], axis=-1)
    found[pending[match]] = True
    slots[pending[match]] = slot[match]
    pending = pending[~match & (stored[:, 0] != EMPTY)]
  return slots, found


def rehash_host(table: np.ndarray, capacity: int, *, max_probes: int):
  """The slots of a table `(C, 3) int32` (NumPy, or a JAX array in host memory, read in place)
  rehashed into `capacity` slots by `insert_host`, its stored keys offered in slot order; the
  table itself is built by `grown_rows`, with the other arrays.

  Returns:
    `(src, dest, lost)`: the key of old slot `src[i]` went to new slot `dest[i]` (`(M,) int`
    each), and `lost` keys found no slot within `max_probes`.
  """
  table = np.asarray(table)
  old = np.flatnonzero(table[:, 0] != EMPTY)
  _, slots, found = insert_host(capacity, table[old], max_probes=max_probes, with_table=False)
  return old[found], slots[found], int(np.count_nonzero(~found))


# From this many bytes of grown arrays on, a host rehash moves the rows with one compiled
# program (`moved_rows`) instead of NumPy: NumPy's new arrays are copied again when handed to
# XLA, and at these sizes (fresh pages, huge ones where the commands ask for them) writing the
# memory twice costs more than the ~0.1 s compile (bench/RESULTS.md, "A building-sized map").
HOST_MOVE_BYTES = 2**28


def moves_on_device(capacity: int, old_arrays) -> bool:
  """Whether a host rehash into `capacity` slots of the `(C, ...)` arrays `old_arrays` (a
  pytree) should move them with `moved_rows`: when the grown arrays hold `HOST_MOVE_BYTES` or
  more."""
  leaves = jax.tree.leaves(old_arrays)
  row_bytes = sum(x.dtype.itemsize * int(np.prod(x.shape[1:], dtype=np.int64)) for x in leaves)
  return capacity * row_bytes >= HOST_MOVE_BYTES


def slot_map(old_capacity: int, capacity: int, src: np.ndarray, dest: np.ndarray) -> np.ndarray:
  """`(C,) int32`: the new slot of each old slot (`dest[i]` for `src[i]`), `capacity` for the
  others (dropped by `moved_rows`)."""
  where = np.full(old_capacity, capacity, np.int32)
  where[src] = dest
  return where


@functools.partial(jax.jit, static_argnames=("capacity",))
def moved_rows(values, fills, where: jax.Array, *, capacity: int):
  """Each leaf of `values` (`(C, ...)` rows) in a table of `capacity` slots: old slot `i`'s row
  at `where[i]` (`capacity`: nowhere, `slot_map`), every other slot the leaf's `fills` (a
  scalar, or one row). Jitted per pair of capacities; the host rehash's move for large tables
  (`moves_on_device`), where writing the grown arrays once, in XLA's own memory, is cheaper
  than NumPy's arrays copied in.

  Returns:
    `(moved, claims)`: the pytree of `values` with `(capacity, ...)` leaves, and a zeroed
    `(capacity,) int32` scratch for the grown table's claims, placed as they are.
  """
  def move(old, fill):
    fresh = jnp.broadcast_to(jnp.asarray(fill, old.dtype), (capacity,) + old.shape[1:])
    return fresh.at[where].set(old, mode="drop")
  return jax.tree.map(move, values, fills), jnp.zeros(capacity, jnp.int32)


def grown_rows(values, fills, src: np.ndarray, dest: np.ndarray, *, capacity: int,
               on_device=None):
  """A host rehash's arrays in `capacity` slots: each leaf of `values` (`(C, ...)` rows, the
  key table among them) with old slot `src[i]`'s row at `dest[i]` (`rehash_host`) and the
  leaf's `fills` elsewhere, handed back placed as the old arrays. Moved in NumPy, or with one
  compiled `moved_rows` (`on_device`; None: `moves_on_device`).

  Returns:
    `(moved, claims)` as `moved_rows`.
  """
  if on_device is None:
    on_device = moves_on_device(capacity, values)
  like = jax.tree.leaves(values)[0]
  if on_device:
    return moved_rows(values, fills, slot_map(like.shape[0], capacity, src, dest),
                      capacity=capacity)

  def move(old, fill):
    old, fill = np.asarray(old), np.asarray(fill, old.dtype)
    new = np.zeros((capacity,) + old.shape[1:], old.dtype)
    if fill.any():   # zero rows stay the system's zeroed pages
      new[...] = fill
    new[dest] = old[src]
    return to_device_of(new, like)

  return (jax.tree.map(move, values, fills),
          to_device_of(np.zeros(capacity, np.int32), like))


def empty_table(capacity: int) -> jax.Array:
  """A `(C, 3) int32` table with every slot EMPTY."""
  return jnp.full((capacity, 3), EMPTY, jnp.int32)


def _home_slots(keys: jax.Array, capacity: int) -> jax.Array:
  return (hash_keys(keys) & np.uint32(capacity - 1)).astype(jnp.int32)


def _probe_slot(home: jax.Array, probe: jax.Array, pending: jax.Array,
                capacity: int) -> jax.Array:
  """`(N,) int32`: the slot each pending key looks at in round `probe`, and slot 0 for the
  others. The probing loops run until the longest chain ends, and every round reads a row for
  every lane; a lane that is done would read a random row of a table of gigabytes (a cache and
  TLB miss) only to be masked out. Slot 0 is one row, in cache after the first such read."""
  return jnp.where(pending, (home + probe) & (capacity - 1), 0)


class InsertResult(NamedTuple):
  """Output of `insert`."""
  table: jax.Array    # [C, 3] int32, the table with the new keys placed
  claims: jax.Array   # [C] int32, scratch (meaningless between calls)
  slots: jax.Array    # [N] int32, slot of each key where found
  found: jax.Array    # [N] bool, key is stored (already there or newly placed)
  is_new: jax.Array   # [N] bool, key was placed by this call


class _InsertCarry(NamedTuple):
  table: jax.Array     # [C, 3] int32
  claims: jax.Array    # [C] int32
  slots: jax.Array     # [N] int32
  pending: jax.Array   # [N] bool
  is_new: jax.Array    # [N] bool
  probe: jax.Array     # [] int32


def insert(table: jax.Array, claims: jax.Array, keys: jax.Array, active: jax.Array, *,
           max_probes: int) -> InsertResult:
  """Finds or places every active key, in parallel.

  Args:
    table: `(C, 3) int32` hash table, C a power of two.
    claims: `(C,) int32` scratch buffer of the same capacity (donated along with the table so
      that claiming needs no per-call allocation of size C).
    keys: `(N, 3) int32` keys; the active ones must be distinct.
    active: `(N,) bool`, which keys to insert.
    max_probes: static bound on the probe sequence length.

  Returns:
    An InsertResult. Active keys with `found == False` did not fit (table full, or no free slot
    within `max_probes`); nothing was written for them.
  """
  capacity = table.shape[0]
  num_keys = keys.shape[0]
  home = _home_slots(keys, capacity)
  lanes = jnp.arange(num_keys, dtype=jnp.int32)

  def cond(c: _InsertCarry):
    return (c.probe < max_probes) & jnp.any(c.pending)

  def body(c: _InsertCarry) -> _InsertCarry:
    # Lanes already done read slot 0 (one cached row) instead of a random one: a round then
    # costs a random access per pending key only, not per key (see `_probe_slot`).
    slot = _probe_slot(home, c.probe, c.pending, capacity)
    stored = c.table[slot]
    match = c.pending & jnp.all(stored == keys, axis=-1)
    empty = c.pending & (stored[:, 0] == EMPTY)
    # Every lane that saw an empty slot writes its id; the id read back is the one winner.
    claims = c.claims.at[jnp.where(empty, slot, capacity)].set(lanes, mode="drop")
    won = empty & (claims[slot] == lanes)
    table = c.table.at[jnp.where(won, slot, capacity)].set(keys, mode="drop")
    done = match | won
    return _InsertCarry(
        table=table,
        claims=claims,
        slots=jnp.where(done, slot, c.slots),
        pending=c.pending & ~done,
        is_new=c.is_new | won,
        probe=c.probe + 1,
    )

  init = _InsertCarry(
      table=table,
      claims=claims,
      slots=jnp.zeros(num_keys, jnp.int32),
      pending=jnp.asarray(active, bool),
      is_new=jnp.zeros(num_keys, bool),
      probe=jnp.zeros((), jnp.int32),
  )
  out = jax.lax.while_loop(cond, body, init)
  found = jnp.asarray(active, bool) & ~out.pending
  return InsertResult(out.table, out.claims, out.slots, found, out.is_new)


class _LookupCarry(NamedTuple):
  slots: jax.Array     # [N] int32
  pending: jax.Array   # [N] bool
  found: jax.Array     # [N] bool
  probe: jax.Array     # [] int32


def lookup(table: jax.Array, keys: jax.Array, *, max_probes: int) -> tuple[jax.Array, jax.Array]:
  """Finds keys without inserting.

  Args:
    table: `(C, 3) int32` hash table.
    keys: `(N, 3) int32` query keys.
    max_probes: static bound, the same as used for insertion.

  Returns:
    `(slots, found)`: `(N,) int32` slot of each key (0 where absent) and `(N,) bool`.
  """
  capacity = table.shape[0]
  num_keys = keys.shape[0]
  home = _home_slots(keys, capacity)

  def cond(c: _LookupCarry):
    return (c.probe < max_probes) & jnp.any(c.pending)

  def body(c: _LookupCarry) -> _LookupCarry:
    slot = _probe_slot(home, c.probe, c.pending, capacity)
    stored = table[slot]
    match = c.pending & jnp.all(stored == keys, axis=-1)
    empty = c.pending & (stored[:, 0] == EMPTY)
    return _LookupCarry(
        slots=jnp.where(match, slot, c.slots),
        pending=c.pending & ~(match | empty),
        found=c.found | match,
        probe=c.probe + 1,
    )

  init = _LookupCarry(
      slots=jnp.zeros(num_keys, jnp.int32),
      pending=jnp.ones(num_keys, bool),
      found=jnp.zeros(num_keys, bool),
      probe=jnp.zeros((), jnp.int32),
  )
  out = jax.lax.while_loop(cond, body, init)
  return out.slots, out.found


@functools.partial(jax.jit, static_argnames=("max_probes",))
def count_missing(table: jax.Array, keys: jax.Array, is_key: jax.Array, *,
                  max_probes: int) -> jax.Array:
  """`() int32`: how many of the keys `(N, 3) int32` where `is_key (N,) bool` the table
  `(C, 3)` does not hold (jitted: the capacity-dependent half of the `Mapper`'s room checks, a
  small program per capacity)."""
  _, found = lookup(table, keys, max_probes=max_probes)
  return jnp.sum(is_key & ~found, dtype=jnp.int32)
