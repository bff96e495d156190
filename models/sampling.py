"""Monte-Carlo dropout sampling and deterministic prediction, jitted and batched.

`mc_samples` draws M softmax samples of one frame in a single jitted call. The layers before
the first dropout (input normalisation, stem, first block: `net.apply_shared`) do not depend on
the dropout key, so they run once per image, and the rest (`net.apply_from_shared`) runs under
`jax.vmap` over the M keys; the samples are those of M full passes `net.apply(key_m)`. `jaxfusion.mc_moments` turns the samples into the mean and
the epistemic variance that the robust fusion rule consumes. `deterministic_probs` is the
baselines' single pass with dropout off. The `*_batch` variants add a leading frame axis.

Shape legend: B frames, M Monte-Carlo samples, H×W pixels, K classes.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from jaxfusion import sources

from . import net


def prepare_images(images) -> jax.Array:
  """Validates RGB images and converts them explicitly to float32 in [0, 1].

  Accepted: `uint8` in [0, 255] (divided by 255) or a float dtype already in [0, 1]; shape
  `(H, W, 3)` or `(B, H, W, 3)`. Anything else (grayscale, RGBA, channels-first, integer types
  other than uint8, bool) raises, so a wrong input never silently produces garbage.

  Args:
    images: `(H, W, 3)` or `(B, H, W, 3)` uint8 or float RGB.

  Returns:
    The same shape as float32.

  Raises:
    ValueError: wrong rank or channel count, an image smaller than 2×2, or concrete float
      values above 1.
    TypeError: a dtype other than uint8 or float.
  """
  if not hasattr(images, "dtype"):
    images = np.asarray(images)
  if images.ndim not in (3, 4):
    raise ValueError(
        f"expected an RGB image (H, W, 3) or a batch (B, H, W, 3); got shape {images.shape}")
  if images.shape[-1] != 3:
    hint = (" (it looks channels-first; transpose to (..., H, W, 3))"
            if images.shape[-3] == 3 else "")
    raise ValueError(
        f"expected 3 colour channels in the last axis; got shape {images.shape}{hint}")
  if images.shape[-3] < 2 or images.shape[-2] < 2:
    raise ValueError(f"image too small: shape {images.shape}")
  if images.dtype == jnp.uint8:
    return jnp.asarray(images, jnp.float32) / 255.0
  if jnp.issubdtype(images.dtype, jnp.floating):
    if not isinstance(images, jax.core.Tracer) and images.size:
      high = float(jnp.max(images))
      if high > 1.0 + 1e-3:
        raise ValueError(
            f"float images must be RGB in [0, 1]; got values up to {high:g} (for 0-255 data "
            "pass uint8 or divide by 255)")
    return jnp.asarray(images, jnp.float32)
  raise TypeError(
      f"expected uint8 RGB in [0, 255] or float RGB in [0, 1]; got dtype {images.dtype}")


@functools.partial(jax.jit, static_argnums=0, static_argnames="num_samples")
def _mc_samples(graphdef, params, key, image, *, num_samples):
  keys = jax.random.split(key, num_samples)
  shared = net.apply_shared(graphdef, params, image[None])   # once per image, not per sample

  def one(k):
    logits = net.apply_from_shared(graphdef, params, k, shared, image.shape[:2],
                                   deterministic=False)[0]
    return jax.nn.softmax(logits, axis=-1)

  return jax.vmap(one)(keys)


def mc_samples(graphdef: nnx.GraphDef, params: nnx.State, key: jax.Array, image, *,
               num_samples: int = 32) -> jax.Array:
  """M softmax samples of one frame with dropout on, in one jitted `vmap` over M keys.

  Args:
    graphdef: static graph from `net.init` or `checkpoint.load`.
    params: the network parameters.
    key: PRNG key; the same key gives the same samples.
    image: `(H, W, 3)` uint8 or float RGB (see `prepare_images`).
    num_samples: M; 32 in the paper.

  Returns:
    `(M, H, W, K)` float32 softmax probabilities.
  """
  image = prepare_images(image)
  if image.ndim != 3:
    raise ValueError(f"mc_samples takes one image (H, W, 3); got {image.shape}; "
                     "use mc_samples_batch for a batch")
  if num_samples < 1:
    raise ValueError(f"num_samples must be >= 1; got {num_samples}")
  return _mc_samples(graphdef, params, key, image, num_samples=num_samples)


@functools.partial(jax.jit, static_argnums=0, static_argnames="num_samples")
def _mc_samples_batch(graphdef, params, key, images, *, num_samples):
  keys = jax.random.split(key, images.shape[0])
  return jax.vmap(
      lambda k, im: _mc_samples(graphdef, params, k, im, num_samples=num_samples))(keys, images)


def mc_samples_batch(graphdef: nnx.GraphDef, params: nnx.State, key: jax.Array, images, *,
                     num_samples: int = 32) -> jax.Array:
  """`mc_samples` for a batch of frames, one jitted call (frame b uses `split(key, B)[b]`).

  Args:
    graphdef: static graph.
    params: the network parameters.
    key: PRNG key.
    images: `(B, H, W, 3)` uint8 or float RGB.
    num_samples: M.

  Returns:
    `(B, M, H, W, K)` float32 softmax probabilities.
  """
  images = prepare_images(images)
  if images.ndim != 4:
    raise ValueError(f"mc_samples_batch takes a batch (B, H, W, 3); got {images.shape}")
  if num_samples < 1:
    raise ValueError(f"num_samples must be >= 1; got {num_samples}")
  return _mc_samples_batch(graphdef, params, key, images, num_samples=num_samples)


@functools.partial(jax.jit, static_argnums=0)
def _deterministic_probs(graphdef, params, images):
  return jax.nn.softmax(net.apply(graphdef, params, None, images, deterministic=True), axis=-1)


def deterministic_probs(graphdef: nnx.GraphDef, params: nnx.State, images) -> jax.Array:
  """One pass with dropout off (the baselines' observation model).

  Args:
    graphdef: static graph.
    params: the network parameters.
    images: `(H, W, 3)` or `(B, H, W, 3)` uint8 or float RGB.

  Returns:
    `(H, W, K)` or `(B, H, W, K)` float32 softmax probabilities (same leading shape).
  """
  images = prepare_images(images)
  if images.ndim == 3:
    return _deterministic_probs(graphdef, params, images[None])[0]
  return _deterministic_probs(graphdef, params, images)


def stochastic_apply_fn(graphdef: nnx.GraphDef):
  """`apply_fn(params, key, image) -> (H, W, K)` probabilities, one MC-dropout pass.

  The form `jaxfusion.sources.mc_dropout_source` and `ensemble_source` expect; it is traceable
  (no host-side checks) so the sources can `vmap` and `jit` it.
  """

  def apply_fn(params, key, image):
    image = prepare_images(image)
    logits = net.apply(graphdef, params, key, image[None], deterministic=False)[0]
    return jax.nn.softmax(logits, axis=-1)

  return apply_fn


def deterministic_apply_fn(graphdef: nnx.GraphDef):
  """`apply_fn(params, key, image) -> (H, W, K)` probabilities with dropout off (key unused)."""

  def apply_fn(params, key, image):
    del key  # Dropout is off; the output does not depend on the key.
    image = prepare_images(image)
    logits = net.apply(graphdef, params, None, image[None], deterministic=True)[0]
    return jax.nn.softmax(logits, axis=-1)

  return apply_fn


def mc_dropout_source(graphdef: nnx.GraphDef, params: nnx.State, *, num_samples: int = 32
                      ) -> sources.NetworkSource:
  """This network as a `jaxfusion` probability source: MC mean and variance of M samples."""
  return sources.mc_dropout_source(stochastic_apply_fn(graphdef), params,
                                   num_samples=num_samples)


def deterministic_source(graphdef: nnx.GraphDef, params: nnx.State) -> sources.NetworkSource:
  """This network as a `jaxfusion` probability source with dropout off (var None)."""
  return sources.deterministic_source(deterministic_apply_fn(graphdef), params)


def ensemble_source(graphdef: nnx.GraphDef, params_list) -> sources.NetworkSource:
  """Several trained copies of this architecture as a deep-ensemble source (dropout off)."""
  return sources.ensemble_source(deterministic_apply_fn(graphdef), params_list)
