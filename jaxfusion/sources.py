"""Sources of per-pixel class probabilities, and their Monte-Carlo moments.

Shape legend: M Monte-Carlo samples, H×W pixels, K classes.
"""

import jax
import jax.numpy as jnp


def mc_moments(samples: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Mean and per-class epistemic variance of Monte-Carlo class probabilities.

  As in SPEC.md: `p̄ = mean_s p^(s)` and `var_i = mean_s (p^(s)_i − p̄_i)^2` (the diagonal
  of the paper's Σe, population variance over the M samples).

  Args:
    samples: `(M, H, W, K)` float softmax samples, one per dropout key / ensemble member.

  Returns:
    `(mean, var)`, both `(H, W, K)` float32. With M = 1 the variance is exactly zero.
  """
  samples = jnp.asarray(samples)
  if samples.ndim != 4:
    raise ValueError(
        f"mc_moments expects samples of shape (M, H, W, K); got shape {samples.shape}")
  if not jnp.issubdtype(samples.dtype, jnp.floating):
    raise TypeError(f"mc_moments expects float probabilities; got dtype {samples.dtype}")
  samples = samples.astype(jnp.float32)
  mean = jnp.mean(samples, axis=0)
  var = jnp.mean(jnp.square(samples - mean[None]), axis=0)
  return mean, var
