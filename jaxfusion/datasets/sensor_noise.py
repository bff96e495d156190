"""Optional sensor realism: depth noise and holes, image blur and noise.

Depth follows the axial noise model of a structured-light sensor (Nguyen et al., 2012):
`σ(z) = 0.0012 + 0.0019·(z − 0.4)²` metres, quantised to millimetres. Depth is missing
(0) on grazing surfaces, on part of the pixels along depth discontinuities, and on a small
random fraction of pixels. Colour images get a slight Gaussian blur, vignetting and pixel noise.

Shape legend: H×W pixels.
"""

import jax
import jax.numpy as jnp


def _neighbour_jump(depth):
  """`(H, W)` largest absolute depth difference to the 4-neighbours."""
  p = jnp.pad(depth, 1, mode="edge")
  c = p[1:-1, 1:-1]
  diffs = [jnp.abs(c - p[:-2, 1:-1]), jnp.abs(c - p[2:, 1:-1]),
           jnp.abs(c - p[1:-1, :-2]), jnp.abs(c - p[1:-1, 2:])]
  return jnp.max(jnp.stack(diffs), axis=0)


@jax.jit
def noisy_depth(key, depth, normal, view_dir):
  """Adds sensor noise and holes to a clean depth image.

  Args:
    key: PRNG key.
    depth: `(H, W) float32` clean z-depth (0 = no return).
    normal: `(H, W, 3) float32` unit surface normals.
    view_dir: `(H, W, 3) float32` unit ray directions.

  Returns:
    `(H, W) float32` depth in metres with 0 where the sensor gives no measurement.
  """
  k_noise, k_edge, k_drop = jax.random.split(key, 3)
  sigma = 0.0012 + 0.0019 * jnp.square(depth - 0.4)
  noisy = depth + sigma * jax.random.normal(k_noise, depth.shape)
  noisy = jnp.round(noisy * 1000.0) / 1000.0
  cos = jnp.abs(jnp.sum(normal * view_dir, axis=-1))
  grazing = cos < 0.12
  edge = (_neighbour_jump(depth) > 0.05 + 0.03 * depth) & (jax.random.uniform(k_edge,
                                                                              depth.shape) < 0.6)
  dropout = jax.random.uniform(k_drop, depth.shape) < 0.003
  invalid = grazing | edge | dropout | (depth <= 0)
  return jnp.where(invalid, 0.0, jnp.maximum(noisy, 0.0)).astype(jnp.float32)


def _blur(img, sigma):
  """Separable Gaussian blur (3-tap) of an `(H, W, C)` image with edge padding."""
  w = jnp.exp(-0.5 * jnp.square(jnp.array([-1.0, 0.0, 1.0]) / sigma))
  w = w / jnp.sum(w)
  p = jnp.pad(img, ((1, 1), (0, 0), (0, 0)), mode="edge")
  img = w[0] * p[:-2] + w[1] * p[1:-1] + w[2] * p[2:]
  p = jnp.pad(img, ((0, 0), (1, 1), (0, 0)), mode="edge")
  return w[0] * p[:, :-2] + w[1] * p[:, 1:-1] + w[2] * p[:, 2:]


@jax.jit
def noisy_image(key, rgb):
  """Blur, vignetting and pixel noise.

  Args:
    key: PRNG key.
    rgb: `(H, W, 3) float32` colour in [0, 1].

  Returns:
    `(H, W, 3) float32` colour in [0, 1].
  """
  height, width = rgb.shape[:2]
  img = _blur(rgb, 0.7)
  y = (jnp.arange(height) - (height - 1) / 2) / max(height, width)
  x = (jnp.arange(width) - (width - 1) / 2) / max(height, width)
  r2 = y[:, None] ** 2 + x[None, :] ** 2
  img = img * (1.0 - 0.35 * r2)[..., None]
  img = img + 0.015 * jax.random.normal(key, img.shape)
  return jnp.clip(img, 0.0, 1.0)
