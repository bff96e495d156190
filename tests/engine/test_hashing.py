"""Properties of the spatial hash (hypothesis): every inserted key is found, no two keys share a
slot, overflow is counted exactly, collisions are handled, stored keys are never corrupted."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings, strategies as st

from jaxfusion import hashing

CAPACITY = 32
BATCH = 48


@functools.partial(jax.jit, static_argnames="max_probes")
def _insert(table, claims, keys, active, max_probes):
  return hashing.insert(table, claims, keys, active, max_probes=max_probes)


@functools.partial(jax.jit, static_argnames="max_probes")
def _lookup(table, keys, max_probes):
  return hashing.lookup(table, keys, max_probes=max_probes)


def padded(keys):
  out = np.zeros((BATCH, 3), np.int32)
  out[:len(keys)] = keys
  active = np.arange(BATCH) < len(keys)
  return out, active


coords = st.integers(min_value=-(2**30) + 1, max_value=2**30 - 1)
small = st.integers(min_value=-3, max_value=3)   # dense clusters: many hash collisions
key_sets = st.lists(st.tuples(st.one_of(coords, small), st.one_of(coords, small),
                              st.one_of(coords, small)),
                    unique=True, min_size=0, max_size=BATCH)


@settings(max_examples=40, deadline=None)
@given(batches=st.lists(key_sets, min_size=1, max_size=3))
def test_insert_then_lookup(batches):
  table = hashing.empty_table(CAPACITY)
  claims = jnp.zeros(CAPACITY, jnp.int32)
  stored = {}        # key -> slot, what the table must hold
  dropped = 0
  for batch in batches:
    keys, active = padded(np.array(batch, np.int32).reshape(-1, 3))
    res = _insert(table, claims, keys, active, max_probes=CAPACITY)
    table, claims = res.table, res.claims
    found = np.asarray(res.found)
    slots = np.asarray(res.slots)
    assert not np.any(found[~active])
    for i, key in enumerate(map(tuple, keys[:len(batch)])):
      if key in stored:
        # Already stored: found again at the same slot, not re-inserted.
        assert found[i] and slots[i] == stored[key] and not res.is_new[i]
      elif found[i]:
        assert res.is_new[i]
        stored[key] = int(slots[i])
      else:
        dropped += 1
    # With max_probes == capacity, a key is dropped only when the table is full.
    if dropped:
      assert len(stored) == CAPACITY
  table_np = np.asarray(table)
  occupied = table_np[:, 0] != hashing.EMPTY
  assert occupied.sum() == len(stored)                       # nothing lost, nothing extra
  assert len(set(stored.values())) == len(stored)            # no two keys share a slot
  for key, slot in stored.items():                           # stored keys intact
    assert tuple(table_np[slot]) == key
  if stored:
    q = np.array(list(stored), np.int32)
    slots, found = _lookup(table, q, max_probes=CAPACITY)
    assert np.all(np.asarray(found))
    np.testing.assert_array_equal(np.asarray(slots), list(stored.values()))
  total = sum(len(b) for b in batches)
  distinct = len({k for b in batches for k in b})
  assert len(stored) == min(CAPACITY, distinct)
  assert len(stored) + dropped <= total


@settings(max_examples=30, deadline=None)
@given(batch=key_sets, absent=key_sets)
def test_lookup_of_absent_keys_fails(batch, absent):
  table = hashing.empty_table(CAPACITY)
  keys, active = padded(np.array(batch, np.int32).reshape(-1, 3))
  res = _insert(table, jnp.zeros(CAPACITY, jnp.int32), keys, active, max_probes=CAPACITY)
  query = [k for k in absent if k not in set(batch)]
  if not query:
    return
  _, found = _lookup(res.table, np.array(query, np.int32), max_probes=CAPACITY)
  assert not np.any(np.asarray(found))


def test_overflow_count_is_exact_with_short_probes():
  # 200 distinct keys into 64 slots with a short probe bound: found + not found = 200, and the
  # found keys are exactly the occupied slots.
  rng = np.random.default_rng(0)
  keys = np.unique(rng.integers(-50, 50, (200, 3)), axis=0)[:160].astype(np.int32)
  table = hashing.empty_table(64)
  res = hashing.insert(table, jnp.zeros(64, jnp.int32), keys, np.ones(len(keys), bool),
                       max_probes=4)
  found = np.asarray(res.found)
  assert 0 < found.sum() <= 64
  assert (np.asarray(res.table)[:, 0] != hashing.EMPTY).sum() == found.sum()


def test_hash_spreads_neighbouring_keys():
  g = np.stack(np.meshgrid(np.arange(16), np.arange(16), np.arange(16), indexing="ij"), -1)
  h = np.asarray(hashing.hash_keys(g.reshape(-1, 3).astype(np.int32))) & (4096 - 1)
  # 4096 neighbouring keys into 4096 buckets: a good hash fills ~63 % of them (1 − 1/e).
  assert len(np.unique(h)) > 0.55 * 4096


# --- the host (NumPy) twins that a growing map on the CPU uses: no program per capacity ------

@settings(max_examples=40, deadline=None)
@given(keys=key_sets)
def test_host_hash_equals_the_device_hash(keys):
  keys = np.asarray(keys, np.int32).reshape(-1, 3)
  np.testing.assert_array_equal(hashing.hash_keys_host(keys),
                                np.asarray(hashing.hash_keys(jnp.asarray(keys))))


def _probe_distance(slot, home, capacity):
  return (slot - home) % capacity


@settings(max_examples=60, deadline=None)
@given(keys=key_sets, max_probes=st.integers(1, 8))
def test_host_insert_keeps_the_probing_invariant_and_the_device_lookup_finds_it(keys,
                                                                                max_probes):
  """Every key `insert_host` places sits within `max_probes` of its home slot behind occupied
  slots only (what `lookup` and `insert` rely on), no two share a slot, the device `lookup`
  finds each at that slot, and exactly the keys reported lost are absent."""
  keys = np.asarray(keys, np.int32).reshape(-1, 3)
  table, slots, found = hashing.insert_host(CAPACITY, keys, max_probes=max_probes)
  occupied = table[:, 0] != hashing.EMPTY
  assert occupied.sum() == found.sum() == len(np.unique(slots[found]))
  assert found.sum() == min(len(keys), CAPACITY) or max_probes < CAPACITY
  home = hashing.hash_keys_host(keys).astype(np.int64) & (CAPACITY - 1)
  for key, slot, h, ok in zip(keys, slots, home, found):
    if ok:
      np.testing.assert_array_equal(table[slot], key)
      distance = _probe_distance(slot, h, CAPACITY)
      assert distance < max_probes
      assert all(occupied[(h + r) % CAPACITY] for r in range(distance))
    else:   # lost: every slot of its probe sequence was taken
      assert all(occupied[(h + r) % CAPACITY] for r in range(max_probes))
  if len(keys):
    query, _ = padded(keys)
    dev_slots, dev_found = _lookup(jnp.asarray(table), query, max_probes)
    np.testing.assert_array_equal(np.asarray(dev_found)[:len(keys)], found)
    np.testing.assert_array_equal(np.asarray(dev_slots)[:len(keys)][found], slots[found])


@settings(max_examples=40, deadline=None)
@given(stored=key_sets, queries=key_sets)
def test_host_lookup_equals_the_device_lookup(stored, queries):
  """On a table the device `insert` built (short probes, so chains and refusals happen),
  `lookup_host` finds exactly what `lookup` finds, at the same slots."""
  table, claims = hashing.empty_table(CAPACITY), jnp.zeros(CAPACITY, jnp.int32)
  keys, active = padded(np.asarray(stored, np.int32).reshape(-1, 3))
  table = _insert(table, claims, keys, active, 4).table
  # Half stored keys, then near misses (a stored key with one coordinate moved), then others.
  near = [(x, y, z + 1) for x, y, z in stored[:BATCH // 4]]
  query = np.asarray(list(stored[:BATCH // 4]) + near + list(queries), np.int64)
  query = np.clip(query, -(2**30), 2**30).astype(np.int32).reshape(-1, 3)[:BATCH]
  padded_query, _ = padded(query)
  dev_slots, dev_found = _lookup(table, padded_query, 4)
  slots, found = hashing.lookup_host(np.asarray(table), query, max_probes=4)
  np.testing.assert_array_equal(found, np.asarray(dev_found)[:len(query)])
  np.testing.assert_array_equal(slots[found], np.asarray(dev_slots)[:len(query)][found])


def test_a_host_rehash_moves_its_rows_on_the_device_from_the_byte_bound():
  rows = {"keys": np.zeros((4, 3), np.int32), "rows": np.zeros((4, 5), np.float32)}  # 32 B a row
  bound = hashing.HOST_MOVE_BYTES // 32
  assert not hashing.moves_on_device(bound // 2, rows)
  assert hashing.moves_on_device(bound, rows)
  assert not hashing.moves_on_device(bound, {"keys": rows["keys"]})   # 12 B a row


def test_moved_rows_places_each_old_slot_and_fills_the_rest():
  old = np.arange(12, dtype=np.float32).reshape(4, 3)
  keys = np.array([[1, 1, 1], [hashing.EMPTY] * 3, [2, 2, 2], [3, 3, 3]], np.int32)
  where = hashing.slot_map(4, 8, np.array([0, 2, 3]), np.array([6, 1, 3]))
  np.testing.assert_array_equal(where, [6, 8, 1, 3])          # slot 1 was empty: dropped
  moved, claims = hashing.moved_rows({"keys": keys, "rows": old},
                                     {"keys": hashing.EMPTY, "rows": np.float32([7, 8, 9])},
                                     where, capacity=8)
  expect = np.tile(np.float32([7, 8, 9]), (8, 1))
  expect[[6, 1, 3]] = old[[0, 2, 3]]
  np.testing.assert_array_equal(np.asarray(moved["rows"]), expect)
  assert [tuple(k) for k in np.asarray(moved["keys"])[[6, 1, 3]]] == [(1, 1, 1), (2, 2, 2),
                                                                      (3, 3, 3)]
  assert (np.asarray(moved["keys"])[[0, 2, 4, 5, 7]] == hashing.EMPTY).all()
  assert np.asarray(claims).shape == (8,) and not np.asarray(claims).any()
