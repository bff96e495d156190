"""Guarded numerical operations shared by the whole engine.

Everything that could turn a hard zero, an empty voxel or a zero variance into NaN/inf (in the
value or in its gradient) goes through here, so that the guards live in one place.

Shape legend: K classes; `...` any leading batch shape.
"""

import jax
import jax.numpy as jnp
import numpy as np

# Floor applied before taking the log of a probability (docs/equations.md §5.1: "log(max(p,
# tiny))"), so that a hard zero never gives -inf. The smallest normal float32: log(TINY) ≈ -87.3.
PROB_FLOOR = float(np.finfo(np.float32).tiny)

# Largest value a saturating int32 counter reaches.
INT32_MAX = int(np.iinfo(np.int32).max)


def safe_log(p: jax.Array) -> jax.Array:
  """`log(max(p, PROB_FLOOR))`: finite for p = 0, and with a finite gradient."""
  return jnp.log(jnp.maximum(p, PROB_FLOOR))


def normalize_log(logp: jax.Array) -> jax.Array:
  """Shift `(..., K)` log-weights so that logsumexp over the last axis is 0."""
  return logp - jax.nn.logsumexp(logp, axis=-1, keepdims=True)


def safe_normalize(x: jax.Array) -> jax.Array:
  """`x / Σx` over the last axis; uniform where the sum is not positive.

  Uses the double-`where` trick so that the gradient stays finite for an all-zero row.
  """
  total = jnp.sum(x, axis=-1, keepdims=True)
  ok = total > 0
  safe_total = jnp.where(ok, total, 1.0)
  uniform = jnp.full_like(x, 1.0 / x.shape[-1])
  return jnp.where(ok, x / safe_total, uniform)


def entropy(p: jax.Array) -> jax.Array:
  """Shannon entropy (nats) of `(..., K)` distributions; 0·log 0 = 0."""
  return -jnp.sum(p * safe_log(p), axis=-1)


def saturating_add(counter: jax.Array, increment: jax.Array) -> jax.Array:
  """`counter + increment` for non-negative int32 values, clamped at INT32_MAX (no wrap)."""
  headroom = INT32_MAX - counter
  return jnp.where(increment > headroom, INT32_MAX, counter + increment)
