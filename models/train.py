"""Trains `SegNet` on the embedded world: `python -m models.train [--quick] [--out PATH]`.

Recipe: AdamW with a warm-up + cosine learning-rate schedule and gradient clipping, dropout on
during training (rate from the config, 0.3 as in the paper), class-weighted cross-entropy
(smoothed inverse frequency, so rare classes such as bottles count), on-device augmentation
(flip, shifted crop, colour jitter, noise), fixed seeds for data, initialisation, batching and
augmentation. After training it evaluates on a held-out split of the training domain and on
the shifted test domain (pixel accuracy, mIoU, AUROC of the epistemic variance as an error
detector) and writes the checkpoint with a JSON record of how it was made.

Shape legend: N training images, B batch, H×W pixels, K classes.
"""

import argparse
import functools
import hashlib
import json
import pathlib
import platform
import subprocess
import sys
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from tqdm import tqdm

from . import checkpoint, evaluate, net


NUM_TRAIN = 1600  # Training views rendered by default.


class TrainConfig(NamedTuple):
  """Optimisation hyperparameters (the architecture lives in `net.SegNetConfig`)."""

  steps: int = 3000
  batch_size: int = 12
  learning_rate: float = 3e-3
  warmup_steps: int = 60
  weight_decay: float = 1e-4
  clip_norm: float = 1.0
  class_weight_power: float = 0.5
  class_weight_max: float = 8.0
  color_strength: float = 1.0
  blur_prob: float = 0.0
  blur_max_sigma: float = 1.5
  noise_min: float = 0.02
  noise_max: float = 0.02
  zoom_max: float = 1.0
  region_color_prob: float = 0.0
  texture_prob: float = 0.0


def class_weights(labels: np.ndarray, num_classes: int, *, power: float = 0.5,
                  max_weight: float = 8.0) -> np.ndarray:
  """Smoothed inverse-frequency class weights for rare classes.

  `w_c = clip((median_freq / freq_c) ** power, 1 / max_weight, max_weight)`, then rescaled so
  that the average weight of a training pixel is 1. Absent classes get `max_weight`.

  Args:
    labels: `(N, H, W)` int labels; values outside `[0, K)` are ignored.
    num_classes: K.
    power: 1 is median-frequency balancing, 0 is unweighted.
    max_weight: clip bound.

  Returns:
    `(K,)` float32 weights.
  """
  labels = np.asarray(labels).ravel()
  labels = labels[(labels >= 0) & (labels < num_classes)]
  counts = np.bincount(labels, minlength=num_classes)[:num_classes]
  freq = counts / max(counts.sum(), 1)
  present = freq > 0
  median = np.median(freq[present]) if present.any() else 1.0
  ratio = np.where(present, median / np.maximum(freq, 1e-12), max_weight ** (1 / max(power, 1e-6)))
  weights = np.clip(ratio ** power, 1.0 / max_weight, max_weight)
  mean_pixel_weight = float((weights * freq).sum()) if present.any() else 1.0
  return (weights / max(mean_pixel_weight, 1e-12)).astype(np.float32)


def _hue_rotation(theta: jax.Array) -> jax.Array:
  """`(3, 3)` RGB matrix rotating hue by `theta` radians about the YIQ luma axis."""
  to_yiq = jnp.array([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322],
                      [0.211, -0.523, 0.312]], jnp.float32)
  c, s = jnp.cos(theta), jnp.sin(theta)
  rot = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], jnp.float32)
  rot = rot.at[1, 1].set(c).at[1, 2].set(-s).at[2, 1].set(s).at[2, 2].set(c)
  return jnp.linalg.inv(to_yiq) @ rot @ to_yiq


def gaussian_blur(image: jax.Array, sigma: jax.Array, *, radius: int = 3) -> jax.Array:
  """Separable Gaussian blur with a traced standard deviation (reflect padding).

  Args:
    image: `(H, W, C)` float32.
    sigma: scalar standard deviation in pixels; values <= 0.05 leave the image unchanged.
    radius: half-width of the `(2 radius + 1)`-tap kernel.

  Returns:
    `(H, W, C)` float32.
  """
  offsets = jnp.arange(-radius, radius + 1, dtype=jnp.float32)
  safe = jnp.maximum(sigma, 0.05)
  taps = jnp.exp(-0.5 * (offsets / safe) ** 2)
  taps = jnp.where(sigma > 0.05, taps / jnp.sum(taps), (offsets == 0).astype(jnp.float32))
  h, w = image.shape[:2]
  padded = jnp.pad(image, ((radius, radius), (0, 0), (0, 0)), mode="reflect")
  image = sum(taps[i] * padded[i:i + h] for i in range(2 * radius + 1))
  padded = jnp.pad(image, ((0, 0), (radius, radius), (0, 0)), mode="reflect")
  return sum(taps[i] * padded[:, i:i + w] for i in range(2 * radius + 1))


def random_zoom(key: jax.Array, image: jax.Array, label: jax.Array, max_zoom: float
                ) -> tuple[jax.Array, jax.Array]:
  """Zooms into a random window (scale in `[1, max_zoom]`, never outside the image).

  Colour is resampled bilinearly, labels by nearest neighbour, so the label set is unchanged.

  Args:
    key: PRNG key.
    image: `(H, W, 3)` float32.
    label: `(H, W)` int32.
    max_zoom: largest magnification; 1 disables the zoom.

  Returns:
    `(image, label)` of the same shapes.
  """
  k_scale, k_y, k_x = jax.random.split(key, 3)
  h, w = label.shape
  scale = jax.random.uniform(k_scale, (), minval=1.0, maxval=max_zoom)
  # Window of size (h / scale, w / scale) whose top-left corner keeps it inside the image.
  y0 = jax.random.uniform(k_y, ()) * (h - h / scale)
  x0 = jax.random.uniform(k_x, ()) * (w - w / scale)
  rows = y0 + (jnp.arange(h, dtype=jnp.float32) + 0.5) / scale - 0.5
  cols = x0 + (jnp.arange(w, dtype=jnp.float32) + 0.5) / scale - 0.5
  rr, cc = jnp.meshgrid(jnp.clip(rows, 0, h - 1), jnp.clip(cols, 0, w - 1), indexing="ij")
  image = jnp.stack([jax.scipy.ndimage.map_coordinates(image[..., c], [rr, cc], order=1)
                     for c in range(image.shape[-1])], axis=-1)
  label = label[jnp.round(rr).astype(jnp.int32), jnp.round(cc).astype(jnp.int32)]
  return image, label


def region_recolor(key: jax.Array, image: jax.Array, label: jax.Array, *, num_classes: int,
                   color_prob: float, texture_prob: float) -> jax.Array:
  """Recolours and retextures each region of one image independently (domain randomisation).

  Global colour jitter keeps the colour *relations* of a scene (a dark chair stays darker than
  its floor), so a net can still learn "this palette means chair". Here the image is cut into
  regions, each class's pixels on either side of a random straight line, and each region gets
  its own transform: a hue rotation, per-channel gains and, sometimes, an inverted brightness
  (with probability `color_prob` per image), and, independently per region with probability
  `texture_prob`, a multiplicative pattern (stripes, checks or waves at a random frequency,
  orientation and contrast) in image coordinates. Nothing is taken from any rendered domain:
  the transforms are generic, and the labels are only used to find the regions.

  Args:
    key: PRNG key.
    image: `(H, W, 3)` float32 in [0, 1].
    label: `(H, W)` int32; values outside `[0, num_classes)` are treated as class 0.
    num_classes: K.
    color_prob: probability that the image's regions are recoloured.
    texture_prob: probability that a region gets a pattern.

  Returns:
    `(H, W, 3)` float32 in [0, 1].
  """
  h, w = label.shape
  (k_on, k_phi, k_cut, k_theta, k_gain, k_inv, k_tex_on, k_freq, k_angle, k_kind,
   k_con, k_phase) = jax.random.split(key, 12)
  num_regions = 2 * num_classes
  yy, xx = jnp.meshgrid(jnp.linspace(-1.0, 1.0, h), jnp.linspace(-1.0, 1.0, w) * (w / h),
                        indexing="ij")
  phi = jax.random.uniform(k_phi, (), minval=0.0, maxval=2 * jnp.pi)
  cut = jax.random.uniform(k_cut, (), minval=-0.7, maxval=0.7)
  side = (xx * jnp.cos(phi) + yy * jnp.sin(phi) > cut).astype(jnp.int32)
  cls = jnp.where((label >= 0) & (label < num_classes), label, 0)
  region = cls + num_classes * side
  if color_prob > 0:
    theta = jax.random.uniform(k_theta, (num_regions,), minval=-jnp.pi, maxval=jnp.pi)
    mats = jax.vmap(_hue_rotation)(theta)
    gain = jnp.exp(jax.random.uniform(k_gain, (num_regions, 3), minval=-0.4, maxval=0.4))
    invert = jax.random.bernoulli(k_inv, 0.2, (num_regions,))
    out = jnp.einsum("hwij,hwj->hwi", mats[region], image) * gain[region]
    out = jnp.clip(out, 0.0, 1.0)
    out = jnp.where(invert[region][..., None], 1.0 - out, out)
    image = jnp.where(jax.random.bernoulli(k_on, color_prob), out, image)
  if texture_prob > 0:
    on = jax.random.bernoulli(k_tex_on, texture_prob, (num_regions,))
    freq = jnp.exp(jax.random.uniform(k_freq, (num_regions,), minval=jnp.log(2.0),
                                      maxval=jnp.log(20.0)))[region]  # cycles per image height
    angle = jax.random.uniform(k_angle, (num_regions,), minval=0.0, maxval=jnp.pi)[region]
    phase = jax.random.uniform(k_phase, (num_regions,), minval=0.0, maxval=2 * jnp.pi)[region]
    kind = jax.random.randint(k_kind, (num_regions,), 0, 3)[region]
    u = jnp.pi * freq * (xx * jnp.cos(angle) + yy * jnp.sin(angle)) + phase
    v = jnp.pi * freq * (-xx * jnp.sin(angle) + yy * jnp.cos(angle))
    stripes = (jnp.sin(u) > 0).astype(jnp.float32)
    checks = ((jnp.sin(u) > 0) ^ (jnp.sin(v) > 0)).astype(jnp.float32)
    waves = 0.5 + 0.5 * jnp.sin(u + 1.5 * jnp.sin(0.7 * v))
    pattern = jnp.select([kind == 0, kind == 1], [stripes, checks], waves)
    contrast = jnp.where(on, jax.random.uniform(k_con, (num_regions,), minval=0.15,
                                                maxval=0.6), 0.0)[region]
    image = image * (1.0 - contrast * pattern)[..., None]
  return image


def augment(key: jax.Array, images: jax.Array, labels: jax.Array, *,
            strength: float = 1.0, blur_prob: float = 0.0, blur_max_sigma: float = 1.5,
            noise_min: float = 0.02, noise_max: float = 0.02, zoom_max: float = 1.0,
            region_color_prob: float = 0.0, texture_prob: float = 0.0, num_classes: int = 7
            ) -> tuple[jax.Array, jax.Array]:
  """Random flip, shifted crop, zoom, colour randomisation, blur and noise, per image.

  All of it is generic photometric / geometric augmentation: nothing here is derived from the
  shifted test domain's appearance.

  Args:
    key: PRNG key.
    images: `(B, H, W, 3)` float32 in [0, 1].
    labels: `(B, H, W)` int32.
    strength: scale of the colour randomisation (0: geometry, blur and noise only).
    blur_prob: probability of a Gaussian blur with sigma uniform in `[0, blur_max_sigma]` px
      (defocus, motion, resolution loss).
    blur_max_sigma: largest blur standard deviation in pixels.
    noise_min: smallest per-image sensor-noise standard deviation.
    noise_max: largest one; the standard deviation is drawn uniformly in
      `[noise_min, noise_max]` per image (fixed when they are equal).
    zoom_max: largest zoom-in factor (objects seen closer); 1 disables it.
    region_color_prob: probability per image of recolouring each region on its own
      (`region_recolor`); 0 disables it.
    texture_prob: probability per region of a random multiplicative pattern; 0 disables it.
    num_classes: K, to find the regions (labels outside `[0, K)` count as class 0).

  Returns:
    Augmented `(images, labels)` of the same shapes and dtypes.
  """

  def one(k, image, label):
    # 14 keys when the zoom, blur and noise-level draws are all off: bit-identical to the
    # recipe of the first shipped weights (segnet_v1); 18 when any is on.
    extra = zoom_max > 1.0 or blur_prob > 0 or noise_min != noise_max
    keys = jax.random.split(k, 18 if extra else 14)
    (k_flip, k_dx, k_dy, k_gain, k_bright, k_con, k_sat, k_noise, k_hue, k_hue_on, k_perm,
     k_perm_on, k_gray, k_gamma) = keys[:14]
    k_zoom, k_blur, k_blur_on, k_noise_level = keys[14:] if extra else (None,) * 4
    flip = jax.random.bernoulli(k_flip)
    image = jnp.where(flip, image[:, ::-1], image)
    label = jnp.where(flip, label[:, ::-1], label)
    h, w = label.shape
    pad_h, pad_w = max(h // 8, 1), max(w // 8, 1)
    image_p = jnp.pad(image, ((pad_h, pad_h), (pad_w, pad_w), (0, 0)), mode="reflect")
    label_p = jnp.pad(label, ((pad_h, pad_h), (pad_w, pad_w)), mode="reflect")
    dy = jax.random.randint(k_dy, (), 0, 2 * pad_h + 1)
    dx = jax.random.randint(k_dx, (), 0, 2 * pad_w + 1)
    image = jax.lax.dynamic_slice(image_p, (dy, dx, 0), (h, w, 3))
    label = jax.lax.dynamic_slice(label_p, (dy, dx), (h, w))
    if zoom_max > 1.0:
      image, label = random_zoom(k_zoom, image, label, zoom_max)
    if region_color_prob > 0 or texture_prob > 0:
      # Its own key stream, so recipes without it keep their random numbers bit for bit.
      image = region_recolor(jax.random.fold_in(k, 1_000_003), image, label,
                             num_classes=num_classes, color_prob=region_color_prob,
                             texture_prob=texture_prob)
    if strength > 0:
      # Colour randomisation so that the net leans on shape and layout rather than on the
      # training palette: hue rotation, channel shuffles, grey-scale, gamma, saturation,
      # contrast, brightness and per-channel gain, each scaled by `strength`.
      theta = jnp.where(jax.random.bernoulli(k_hue_on, 0.5 * min(strength, 1.0)),
                        jax.random.uniform(k_hue, (), minval=-jnp.pi, maxval=jnp.pi), 0.0)
      image = jnp.clip(image @ _hue_rotation(theta).T, 0.0, 1.0)
      perm = jax.random.permutation(k_perm, 3)
      image = jnp.where(jax.random.bernoulli(k_perm_on, 0.25 * min(strength, 1.0)),
                        image[..., perm], image)
      gamma = jnp.exp(jax.random.uniform(k_gamma, (), minval=-0.4, maxval=0.4) * strength)
      image = image ** gamma
      gray = jnp.mean(image, axis=-1, keepdims=True)
      sat = jnp.where(jax.random.bernoulli(k_gray, 0.15 * min(strength, 1.0)), 0.0,
                      1.0 + strength * jax.random.uniform(k_sat, (), minval=-0.5, maxval=0.5))
      image = gray + sat * (image - gray)
      contrast = 1.0 + strength * jax.random.uniform(k_con, (), minval=-0.4, maxval=0.4)
      bright = strength * jax.random.uniform(k_bright, (), minval=-0.15, maxval=0.15)
      image = (image - 0.5) * contrast + 0.5 + bright
      image = image * (1.0 + strength * jax.random.uniform(k_gain, (3,), minval=-0.2,
                                                          maxval=0.2))
    if blur_prob > 0:
      sigma = jnp.where(jax.random.bernoulli(k_blur_on, blur_prob),
                        jax.random.uniform(k_blur, (), minval=0.0, maxval=blur_max_sigma), 0.0)
      image = gaussian_blur(image, sigma)
    noise = (noise_max if noise_min == noise_max else
             jax.random.uniform(k_noise_level, (), minval=noise_min, maxval=noise_max))
    image = image + noise * jax.random.normal(k_noise, image.shape)
    return jnp.clip(image, 0.0, 1.0), label

  keys = jax.random.split(key, images.shape[0])
  return jax.vmap(one)(keys, images, labels)


def weighted_cross_entropy(logits: jax.Array, labels: jax.Array,
                           weights: jax.Array) -> jax.Array:
  """Mean of `w[y] * CE(logits, y)` over pixels, normalised by the summed weights.

  Args:
    logits: `(B, H, W, K)` float32.
    labels: `(B, H, W)` int32 in `[0, K)`; other values (e.g. -1, no ground truth) are
      ignored.
    weights: `(K,)` float32 class weights.

  Returns:
    Scalar float32 loss.
  """
  valid = (labels >= 0) & (labels < logits.shape[-1])
  safe = jnp.where(valid, labels, 0)
  ce = optax.softmax_cross_entropy_with_integer_labels(logits, safe)
  w = jnp.where(valid, weights[safe], 0.0)
  return jnp.sum(w * ce) / jnp.maximum(jnp.sum(w), 1e-12)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
  """AdamW on a warm-up + cosine schedule, after global-norm clipping."""
  schedule = optax.warmup_cosine_decay_schedule(
      init_value=0.0, peak_value=cfg.learning_rate,
      warmup_steps=min(cfg.warmup_steps, max(cfg.steps - 1, 1)),
      decay_steps=max(cfg.steps, 2), end_value=cfg.learning_rate * 0.02)
  return optax.chain(optax.clip_by_global_norm(cfg.clip_norm),
                     optax.adamw(schedule, weight_decay=cfg.weight_decay))


@functools.partial(jax.jit, static_argnums=(0, 1), static_argnames="augmentation",
                   donate_argnums=(2, 3))
def train_step(graphdef: nnx.GraphDef, optimizer: optax.GradientTransformation,
               params: nnx.State, opt_state: optax.OptState, key: jax.Array,
               images: jax.Array, labels: jax.Array, weights: jax.Array, *,
               augmentation: tuple[tuple[str, float], ...] = ()):
  """One AdamW step on a batch (augmented here, dropout on).

  Args:
    graphdef: static graph.
    optimizer: static optax transformation (hashable: build it once).
    params: parameters (donated).
    opt_state: optimiser state (donated).
    key: PRNG key for augmentation and dropout.
    images: `(B, H, W, 3)` uint8.
    labels: `(B, H, W)` int32.
    weights: `(K,)` float32 class weights.
    augmentation: static `((name, value), ...)` keyword arguments of `augment` (see
      `augment_kwargs`); empty means `augment`'s defaults.

  Returns:
    `(params, opt_state, loss)`.
  """
  k_aug, k_drop = jax.random.split(key)
  x, y = augment(k_aug, images.astype(jnp.float32) / 255.0, labels, num_classes=weights.shape[0],
                 **dict(augmentation))

  def loss_fn(p):
    logits = net.apply(graphdef, p, k_drop, x, deterministic=False)
    return weighted_cross_entropy(logits, y, weights)

  loss, grads = jax.value_and_grad(loss_fn)(params)
  updates, opt_state = optimizer.update(grads, opt_state, params)
  return optax.apply_updates(params, updates), opt_state, loss


def augment_kwargs(cfg: TrainConfig) -> tuple[tuple[str, float], ...]:
  """The augmentation settings of `cfg` as hashable keyword arguments of `augment`."""
  return (("strength", float(cfg.color_strength)), ("blur_prob", float(cfg.blur_prob)),
          ("blur_max_sigma", float(cfg.blur_max_sigma)), ("noise_min", float(cfg.noise_min)),
          ("noise_max", float(cfg.noise_max)),
          ("zoom_max", float(cfg.zoom_max)),
          ("region_color_prob", float(cfg.region_color_prob)),
          ("texture_prob", float(cfg.texture_prob)))


def fit(graphdef: nnx.GraphDef, params: nnx.State, images: np.ndarray, labels: np.ndarray, *,
        key: jax.Array, cfg: TrainConfig, weights: np.ndarray | None = None,
        progress: bool = True, callback: Callable[[int, nnx.State, np.ndarray], None] | None = None,
        callback_every: int = 0) -> tuple[nnx.State, np.ndarray]:
  """Trains on in-memory arrays; batches are drawn without replacement per epoch.

  Args:
    graphdef: static graph.
    params: initial parameters (not modified; a copy is trained).
    images: `(N, H, W, 3)` uint8.
    labels: `(N, H, W)` int labels.
    key: PRNG key (batch order, augmentation, dropout).
    cfg: optimisation hyperparameters.
    weights: `(K,)` class weights; default from `class_weights(labels)`.
    progress: show a tqdm bar.
    callback: called as `callback(steps_done, params, losses[:steps_done])` every
      `callback_every` steps (e.g. to save a checkpoint a partial run can use); it must not
      keep references to `params` (the next step donates them).
    callback_every: period of `callback` in steps; 0 never calls it.

  Returns:
    `(params, losses)` with `losses` `(steps,)` float32.
  """
  if callback_every < 0:
    raise ValueError(f"callback_every must be >= 0; got {callback_every}")
  images = np.asarray(images)
  labels = np.asarray(labels, np.int32)
  if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] != 3:
    raise ValueError(f"fit expects (N, H, W, 3) uint8 images; got {images.shape} {images.dtype}")
  if labels.shape != images.shape[:3]:
    raise ValueError(f"labels {labels.shape} do not match images {images.shape}")
  num_classes = _num_classes(params)
  if weights is None:
    weights = class_weights(labels, num_classes, power=cfg.class_weight_power,
                            max_weight=cfg.class_weight_max)
  weights = jnp.asarray(weights, jnp.float32)
  optimizer = make_optimizer(cfg)
  params = jax.tree_util.tree_map(jnp.array, params)  # Own copy: train_step donates it.
  opt_state = optimizer.init(params)
  n = images.shape[0]
  batch = min(cfg.batch_size, n)
  rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
  order = rng.permutation(n)
  cursor = 0
  losses = np.zeros((cfg.steps,), np.float32)
  bar = tqdm(range(cfg.steps), disable=not progress, desc="train", mininterval=5.0)
  for step in bar:
    if cursor + batch > n:
      order, cursor = rng.permutation(n), 0
    idx = np.sort(order[cursor:cursor + batch])
    cursor += batch
    params, opt_state, loss = train_step(
        graphdef, optimizer, params, opt_state, jax.random.fold_in(key, step),
        jnp.asarray(images[idx]), jnp.asarray(labels[idx]), weights,
        augmentation=augment_kwargs(cfg))
    losses[step] = float(loss)
    if progress and (step % 10 == 0 or step == cfg.steps - 1):
      bar.set_postfix(loss=f"{losses[max(step - 9, 0):step + 1].mean():.3f}")
    if callback is not None and callback_every and (step + 1) % callback_every == 0:
      callback(step + 1, params, losses[:step + 1])
  return params, losses


def _num_classes(params: nnx.State) -> int:
  """K, read from the classifier's bias."""
  return int(jax.tree_util.tree_leaves(params["classifier"]["bias"])[0].shape[-1])


def load_domain(domain: str, num_images: int, *, height: int, width: int, seed: int,
                shift: float = 1.0, cache_dir: str | None = None, sensing: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
  """Renders `num_images` views of the embedded world (`jaxfusion.datasets.synthetic`).

  Args:
    domain: "train" or "test" (shifted palettes, textures, lighting and shapes).
    num_images: N.
    height: H.
    width: W.
    seed: scene/view seed.
    shift: test-domain shift strength.
    cache_dir: if given, rendered views are stored there as `.npz` and reused when the same
      split is asked for again (rendering dominates start-up time on a CPU).
    sensing: render with the view-dependent camera model (`SensingConfig()`), else with
      `SensingConfig.off()` (the plain renderer).

  Returns:
    `(rgb (N, H, W, 3) uint8, labels (N, H, W) int32)`.
  """
  cache = None
  if cache_dir is not None:
    cache = pathlib.Path(cache_dir) / (
        f"{domain}_n{num_images}_{height}x{width}_seed{seed}_shift{shift:g}_"
        f"sensing{'on' if sensing else 'off'}_"
        f"{dataset_version()}.npz")
    if cache.is_file():
      with np.load(cache) as data:
        return data["rgb"], data["labels"]
  from jaxfusion.datasets import synthetic  # Application layer: only the commands need it.
  from jaxfusion.datasets import SensingConfig
  rgb, labels = synthetic.sample_views(domain, num_images, height=height, width=width,
                                       seed=seed, shift=shift,
                                       sensing=SensingConfig() if sensing else SensingConfig.off())
  rgb, labels = np.asarray(rgb, np.uint8), np.asarray(labels, np.int32)
  if cache is not None:
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, rgb=rgb, labels=labels)
  return rgb, labels


def dataset_class_names() -> tuple[str, ...]:
  """The embedded world's class names, in label order."""
  from jaxfusion.datasets import synthetic
  names = getattr(synthetic, "CLASS_NAMES", None)
  if names is None:
    from jaxfusion.datasets import classes
    names = classes.CLASS_NAMES
  return tuple(names)


def dataset_version() -> str:
  """Identifies the data generator: its declared version, else the git commit of its folder.

  A working tree with uncommitted changes under `jaxfusion/datasets` gets a `-dirty` suffix;
  the training record also stores SHA-256 digests of the rendered arrays.
  """
  from jaxfusion.datasets import synthetic
  declared = getattr(synthetic, "VERSION", getattr(synthetic, "__version__", None))
  if declared is not None:
    return str(declared)
  folder = pathlib.Path(synthetic.__file__).resolve().parent
  try:
    commit = subprocess.run(["git", "log", "-1", "--format=%h", "--", "."], cwd=folder,
                            capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "."], cwd=folder,
                           capture_output=True, text=True, timeout=10, check=True).stdout.strip()
  except (OSError, subprocess.SubprocessError):
    return "unversioned"
  return (commit or "uncommitted") + ("-dirty" if dirty else "")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m models.train", description=__doc__.split("\n")[0])
  p.add_argument("--out", default="outputs/segnet.msgpack",
                 help="checkpoint path (default outputs/segnet.msgpack: a run never overwrites the "
                      "packaged weights unless asked to; `--recipe models/weights/segnet.json` "
                      "re-creates them)")
  p.add_argument("--quick", action="store_true",
                 help="a tiny run (minutes): fewer images and steps; for smoke tests")
  p.add_argument("--steps", type=int, default=None)
  p.add_argument("--batch-size", type=int, default=TrainConfig().batch_size)
  p.add_argument("--lr", type=float, default=TrainConfig().learning_rate)
  p.add_argument("--weight-decay", type=float, default=TrainConfig().weight_decay)
  p.add_argument("--warmup", type=int, default=TrainConfig().warmup_steps)
  p.add_argument("--color-strength", type=float, default=TrainConfig().color_strength,
                 help="scale of the colour augmentation (0 = geometry and noise only)")
  p.add_argument("--blur-prob", type=float, default=TrainConfig().blur_prob)
  p.add_argument("--blur-max-sigma", type=float, default=TrainConfig().blur_max_sigma)
  p.add_argument("--noise-min", type=float, default=TrainConfig().noise_min)
  p.add_argument("--noise-max", type=float, default=TrainConfig().noise_max)
  p.add_argument("--sensing", choices=("on", "off"), default="off",
                 help="render the views with the embedded world's view-dependent camera model "
                      "(sample_views' default since datasets ecb82f6) or without it (the "
                      "renderer the shipped weights were trained with)")
  p.add_argument("--zoom-max", type=float, default=TrainConfig().zoom_max)
  p.add_argument("--region-color-prob", type=float, default=TrainConfig().region_color_prob,
                 help="probability per image of recolouring each class region on its own")
  p.add_argument("--texture-prob", type=float, default=TrainConfig().texture_prob,
                 help="probability per region of a random stripe/check/wave pattern")
  p.add_argument("--input-norm", action=argparse.BooleanOptionalAction,
                 default=net.SegNetConfig.input_norm,
                 help="standardise each image per channel inside the network")
  p.add_argument("--save-every", type=int, default=250,
                 help="steps between partial checkpoints (<out>.partial.msgpack); 0 = never")
  p.add_argument("--height", type=int, default=96)
  p.add_argument("--width", type=int, default=128)
  p.add_argument("--num-train", type=int, default=None)
  p.add_argument("--num-eval", type=int, default=None, help="images per evaluation split")
  p.add_argument("--eval-samples", type=int, default=16, help="M for the MC evaluation")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--shift", type=float, default=1.0, help="test-domain shift strength")
  p.add_argument("--cache", default=None, help="folder to cache rendered views in")
  p.add_argument("--stem-width", type=int, default=net.SegNetConfig.stem_width)
  p.add_argument("--widths", default=",".join(map(str, net.SegNetConfig.widths)))
  p.add_argument("--strides", default=",".join(map(str, net.SegNetConfig.strides)))
  p.add_argument("--dilations", default=",".join(map(str, net.SegNetConfig.dilations)))
  p.add_argument("--blocks-per-stage", type=int, default=net.SegNetConfig.blocks_per_stage)
  p.add_argument("--aspp-width", type=int, default=net.SegNetConfig.aspp_width)
  p.add_argument("--aspp-rates", default=",".join(map(str, net.SegNetConfig.aspp_rates)))
  p.add_argument("--norm-groups", type=int, default=net.SegNetConfig.norm_groups)
  p.add_argument("--dropout", type=float, default=net.SegNetConfig.dropout_rate)
  p.add_argument("--recipe", default=None,
                 help="a training record (e.g. models/weights/segnet.json): its architecture, "
                      "data and optimisation settings become the defaults, so "
                      "`--recipe models/weights/segnet.json` re-runs the shipped recipe")
  known, _ = p.parse_known_args(argv)
  if known.recipe is not None:
    p.set_defaults(**recipe_defaults(json.loads(pathlib.Path(known.recipe).read_text())))
  return p.parse_args(argv)


# Training-config fields the command line does not expose: a recipe must use their defaults.
_FIXED_TRAIN_FIELDS = ("clip_norm", "class_weight_power", "class_weight_max")


def recipe_defaults(recipe: dict[str, Any]) -> dict[str, Any]:
  """Command-line defaults that reproduce a run from its JSON record (`segnet.json`).

  Args:
    recipe: `{"config": SegNetConfig dict, "record": {"seed", "data", "train_config", ...}}`.

  Returns:
    `{argparse dest: value}`.

  Raises:
    ValueError: the record lacks a field, or fixes a setting the command line cannot set to a
      value other than this code's default.
  """
  try:
    config = net.SegNetConfig.from_dict(recipe["config"])
    record = recipe["record"]
    data, tc = record["data"], record["train_config"]
    defaults = {
        "seed": record["seed"], "height": data["height"], "width": data["width"],
        "num_train": data["train"]["num_images"], "num_eval": data["test"]["num_images"],
        "shift": data["test"]["shift"],
        "steps": tc["steps"], "batch_size": tc["batch_size"], "lr": tc["learning_rate"],
        "warmup": tc["warmup_steps"], "weight_decay": tc["weight_decay"],
        "color_strength": tc["color_strength"],
        "eval_samples": record.get("eval_num_samples", 16),
    }
  except KeyError as e:
    raise ValueError(f"the recipe lacks field {e}; pass a segnet.json written by this command")
  # Augmentation fields added after the first records; absent means "off" (the old recipe).
  defaults.update(blur_prob=tc.get("blur_prob", 0.0), blur_max_sigma=tc.get("blur_max_sigma", 1.5),
                  noise_max=tc.get("noise_max", 0.02), zoom_max=tc.get("zoom_max", 1.0),
                  region_color_prob=tc.get("region_color_prob", 0.0),
                  texture_prob=tc.get("texture_prob", 0.0),
                  sensing=data.get("sensing", "off"))
  # A record with noise_max but no noise_min drew the level from [0, noise_max].
  defaults["noise_min"] = tc.get("noise_min", 0.0 if "noise_max" in tc else 0.02)
  for name in _FIXED_TRAIN_FIELDS:
    if name in tc and tc[name] != getattr(TrainConfig(), name):
      raise ValueError(f"the recipe sets {name}={tc[name]}, which the command line cannot "
                       f"set (this code uses {getattr(TrainConfig(), name)})")
  defaults.update(
      stem_width=config.stem_width, widths=",".join(map(str, config.widths)),
      strides=",".join(map(str, config.strides)),
      dilations=",".join(map(str, config.dilations)),
      blocks_per_stage=config.blocks_per_stage, aspp_width=config.aspp_width,
      aspp_rates=",".join(map(str, config.aspp_rates)), dropout=config.dropout_rate)
  defaults["norm_groups"] = config.norm_groups
  defaults["input_norm"] = config.input_norm
  return defaults


def main(argv: list[str] | None = None) -> dict[str, Any]:
  args = parse_args(argv)
  steps = args.steps if args.steps is not None else (40 if args.quick else TrainConfig().steps)
  num_train = args.num_train if args.num_train is not None else (64 if args.quick else NUM_TRAIN)
  num_eval = args.num_eval if args.num_eval is not None else (16 if args.quick else 48)
  ints = lambda text: tuple(int(v) for v in text.split(","))
  class_names = dataset_class_names()
  config = net.SegNetConfig(
      num_classes=len(class_names), stem_width=args.stem_width, widths=ints(args.widths),
      strides=ints(args.strides), dilations=ints(args.dilations),
      blocks_per_stage=args.blocks_per_stage, aspp_width=args.aspp_width,
      aspp_rates=ints(args.aspp_rates), dropout_rate=args.dropout,
      norm_groups=args.norm_groups, input_norm=args.input_norm)
  cfg = TrainConfig(steps=steps, batch_size=args.batch_size, learning_rate=args.lr,
                    warmup_steps=args.warmup, weight_decay=args.weight_decay,
                    color_strength=args.color_strength, blur_prob=args.blur_prob,
                    blur_max_sigma=args.blur_max_sigma, noise_min=args.noise_min,
                    noise_max=args.noise_max,
                    zoom_max=args.zoom_max, region_color_prob=args.region_color_prob,
                    texture_prob=args.texture_prob)
  size = dict(height=args.height, width=args.width, cache_dir=args.cache,
              sensing=args.sensing == "on")

  t0 = time.time()
  print(f"rendering data: {num_train} train, {num_eval} val, {num_eval} test at "
        f"{args.height}x{args.width}", flush=True)
  train_x, train_y = load_domain("train", num_train, seed=args.seed, **size)
  val_x, val_y = load_domain("train", num_eval, seed=args.seed + 10_000, **size)
  test_x, test_y = load_domain("test", num_eval, seed=args.seed + 20_000, shift=args.shift,
                               **size)
  data_s = time.time() - t0
  weights = class_weights(train_y, config.num_classes, power=cfg.class_weight_power,
                          max_weight=cfg.class_weight_max)
  print(f"data in {data_s:.0f} s; class frequencies "
        f"{np.round(np.bincount(train_y.ravel(), minlength=config.num_classes) / train_y.size, 4)}"
        f"; weights {np.round(weights, 2)}", flush=True)

  key = jax.random.key(args.seed)
  k_init, k_train, k_eval = jax.random.split(key, 3)
  graphdef, params = net.init(config, key=k_init)
  print(f"SegNet: {net.count_params(params):,} parameters, output stride "
        f"{config.output_stride}", flush=True)
  partial_path = pathlib.Path(args.out).with_suffix(".partial.msgpack")
  t1 = time.time()

  def save_partial(done, current, losses_so_far):
    elapsed = time.time() - t1
    print(f"step {done}/{steps}: loss(last 50) {losses_so_far[-50:].mean():.3f}, "
          f"{done / elapsed:.2f} steps/s, elapsed {elapsed / 60:.1f} min, "
          f"ETA {(steps - done) * elapsed / done / 60:.1f} min", flush=True)
    checkpoint.save(partial_path, current, config=config, class_names=class_names,
                    record={"partial": True, "steps_done": done, "train_config": cfg._asdict(),
                            "command": "python -m models.train " + " ".join(
                                sys.argv[1:] if argv is None else argv)})

  params, losses = fit(graphdef, params, train_x, train_y, key=k_train, cfg=cfg,
                       weights=weights, callback=save_partial, callback_every=args.save_every)
  train_s = time.time() - t1
  print(f"trained {steps} steps in {train_s:.0f} s; loss {losses[:10].mean():.3f} -> "
        f"{losses[-10:].mean():.3f}", flush=True)

  t2 = time.time()
  results = {}
  for name, (x, y) in {"train_heldout": (val_x, val_y), "test_shifted": (test_x, test_y)}.items():
    results[name] = evaluate.evaluate_arrays(
        graphdef, params, x, y, key=jax.random.fold_in(k_eval, len(results)),
        num_samples=args.eval_samples, num_classes=config.num_classes)
    print(f"{name}: {json.dumps(results[name]['summary'])}", flush=True)
  eval_s = time.time() - t2

  record = {
      "command": "python -m models.train " + " ".join(sys.argv[1:] if argv is None else argv),
      "seed": args.seed,
      "data": {"generator": "jaxfusion.datasets.synthetic.sample_views",
               "version": dataset_version(), "height": args.height, "width": args.width,
               "sensing": args.sensing,
               "train_sha256": hashlib.sha256(train_x.tobytes() + train_y.tobytes()).hexdigest(),
               "test_sha256": hashlib.sha256(test_x.tobytes() + test_y.tobytes()).hexdigest(),
               "train": {"domain": "train", "num_images": num_train, "seed": args.seed},
               "heldout": {"domain": "train", "num_images": num_eval,
                           "seed": args.seed + 10_000},
               "test": {"domain": "test", "num_images": num_eval, "seed": args.seed + 20_000,
                        "shift": args.shift}},
      "train_config": cfg._asdict(),
      "class_weights": [round(float(w), 4) for w in weights],
      "num_params": net.count_params(params),
      "loss_first10": float(losses[:10].mean()), "loss_last10": float(losses[-10:].mean()),
      "seconds": {"data": round(data_s, 1), "train": round(train_s, 1),
                  "eval": round(eval_s, 1)},
      "eval": {k: v["summary"] for k, v in results.items()},
      "eval_num_samples": args.eval_samples,
      "platform": {"jax": jax.__version__, "python": platform.python_version(),
                   "machine": platform.machine(), "devices": str(jax.devices())},
  }
  out = checkpoint.save(args.out, params, config=config, class_names=class_names,
                        record=record)
  record_path = pathlib.Path(out).with_suffix(".json")
  record_path.write_text(json.dumps({"config": config.to_dict(), "class_names": class_names,
                                     "record": record}, indent=2) + "\n")
  partial_path.unlink(missing_ok=True)  # The finished checkpoint supersedes it.
  print(f"wrote {out} ({pathlib.Path(out).stat().st_size / 1e6:.2f} MB) and {record_path}",
        flush=True)
  return record


if __name__ == "__main__":
  main()
