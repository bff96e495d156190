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


@settings(max_examples=60, deadline=None)
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
