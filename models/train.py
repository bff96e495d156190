"""Trains `SegNet` on the embedded world: `python -m models.train [--quick] [--out PATH]`.

Recipe: AdamW with a warm-up + cosine learning-rate schedule and gradient clipping, dropout on
during training (rate from the config, 0.3 as in the paper), class-weighted cross-entropy
(smoothed inverse frequency, so rare classes such as bottles count), on-device augmentation
(flip, shifted crop, colour jitter, noise), fixed seeds for data, initialisation, batching and
augmentation. After training it evaluates on a held-out split of the training domain and on
the shifted test domain (pixel accuracy, mIoU, AUROC of the epistemic variance as an error
detector) and writes the checkpoint with a JSON record of how it was made.

Everything a run depends on is one frozen `Config` (data and evaluation settings, the
optimisation `TrainConfig` and the architecture `net.SegNetConfig`), written once: the command
line flags, `--recipe` (replaying a run from its JSON record) and the record itself are all
derived from its fields. `python -m models.train --help` lists them;
`train_and_evaluate(config, out)` is the importable entry point.

Shape legend: N training images, B batch, H×W pixels, K classes.
"""

import argparse
import dataclasses
import functools
import hashlib
import json
import pathlib
import platform
import sys
import time
import typing
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from tqdm import tqdm

from . import checkpoint, evaluate, net
from . import data as data_lib


NUM_TRAIN = 1600  # Training views rendered by default.


def option(default: Any, *, help: str, flag: str | None = None, record: str | None = None,
           absent: Any = dataclasses.MISSING, choices: tuple[str, ...] | None = None) -> Any:
  """A config field together with what the command line and the training record need of it.

  Args:
    default: the value when neither a flag nor a recipe sets it.
    help: one line for `--help` (the default is appended there).
    flag: its command-line spelling, when that is not `--field-name` (old spellings stay).
    record: where a record keeps it, as a dotted path into the recipe document
      (`{"config": ..., "record": ...}`); default: `<its section's path>.<field name>`.
    absent: what a record without the field means (the setting of the code from before the
      field existed), or a function of the record's section returning it; without one, a recipe
      must carry the field.
    choices: the allowed values of a `str` field.

  Returns:
    A `dataclasses.field` carrying these in its metadata.
  """
  return dataclasses.field(default=default, metadata=dict(
      help=help, flag=flag, record=record, absent=absent, choices=choices))


def section(cls: type, *, record: str, flags: dict[str, str] | None = None,
            hidden: tuple[str, ...] = ()) -> Any:
  """A nested config dataclass, its fields exposed as flags of their own names.

  A class with `to_dict` / `from_dict` (`net.SegNetConfig`) is stored whole by those; one built
  from `option`s is stored field by field.

  Args:
    cls: the nested dataclass; its default instance is the default.
    record: dotted path of its object in the recipe document.
    flags: `{field name: flag}` spellings for fields of a class that has no `option`s.
    hidden: fields with no flag (set by the run itself, such as the number of classes).

  Returns:
    A `dataclasses.field`.
  """
  return dataclasses.field(default_factory=cls, metadata=dict(
      record=record, flags=flags or {}, hidden=hidden))


def _documented(cls: type) -> type:
  """Appends an `Attributes:` section built from the fields' `help` to the class docstring."""
  lines = [f"    {f.name}: {f.metadata['help']}" for f in dataclasses.fields(cls)
           if "help" in f.metadata]
  cls.__doc__ = (cls.__doc__ or "").rstrip() + "\n\n  Attributes:\n" + "\n".join(lines) + "\n"
  return cls


def _noise_min_absent(train_config: dict[str, Any]) -> float:
  """A record with `noise_max` but no `noise_min` drew the noise level from [0, noise_max]."""
  return 0.0 if "noise_max" in train_config else 0.02


@_documented
@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Optimisation and augmentation hyperparameters (the architecture is `net.SegNetConfig`).

  A record lacking one of the later augmentation fields means that augmentation was off.
  """

  steps: int = option(3000, help="optimisation steps (--quick: 40)")
  batch_size: int = option(12, help="images per step")
  learning_rate: float = option(3e-3, flag="--lr",
                                help="peak of the warm-up + cosine learning-rate schedule")
  warmup_steps: int = option(60, flag="--warmup", help="steps of linear learning-rate warm-up")
  weight_decay: float = option(1e-4, help="AdamW weight decay")
  clip_norm: float = option(1.0, absent=1.0, help="global gradient-norm clip")
  class_weight_power: float = option(
      0.5, absent=0.5, help="exponent of the inverse-frequency class weights (0: unweighted)")
  class_weight_max: float = option(8.0, absent=8.0, help="clip bound of the class weights")
  color_strength: float = option(
      1.0, help="scale of the colour augmentation (0 = geometry and noise only)")
  blur_prob: float = option(0.0, absent=0.0, help="probability of a Gaussian blur per image")
  blur_max_sigma: float = option(1.5, absent=1.5,
                                 help="largest blur standard deviation in pixels")
  noise_min: float = option(0.02, absent=_noise_min_absent,
                            help="smallest sensor-noise standard deviation (drawn per image)")
  noise_max: float = option(0.02, absent=0.02, help="largest sensor-noise standard deviation")
  zoom_max: float = option(1.0, absent=1.0, help="largest zoom-in factor (1 = no zoom)")
  region_color_prob: float = option(
      0.0, absent=0.0, help="probability per image of recolouring each class region on its own")
  texture_prob: float = option(
      0.0, absent=0.0, help="probability per region of a random stripe/check/wave pattern")


@_documented
@dataclasses.dataclass(frozen=True)
class Config:
  """Everything a training run depends on: its record replays it (`--recipe`).

  `model.num_classes` is set from the embedded world's class list when the run starts.
  """

  seed: int = option(0, record="record.seed",
                     help="seed of the data, initialisation, batching, augmentation, dropout")
  height: int = option(96, record="record.data.height", help="image height H in pixels")
  width: int = option(128, record="record.data.width", help="image width W in pixels")
  num_train: int = option(NUM_TRAIN, record="record.data.train.num_images",
                          help="training views rendered (--quick: 64)")
  num_eval: int = option(48, record="record.data.test.num_images",
                         help="images per evaluation split (--quick: 16)")
  shift: float = option(1.0, record="record.data.test.shift", help="test-domain shift strength")
  sensing: str = option(
      "off", choices=("on", "off"), record="record.data.sensing", absent="off",
      help="render the views with the embedded world's view-dependent camera model "
           "(sample_views' default) or with the plain sensor model (SensingConfig.off(), "
           "what the shipped weights were trained with)")
  eval_samples: int = option(16, record="record.eval_num_samples", absent=16,
                             help="M for the MC evaluation")
  train: TrainConfig = section(TrainConfig, record="record.train_config")
  model: net.SegNetConfig = section(net.SegNetConfig, record="config",
                                    flags={"dropout_rate": "--dropout"},
                                    hidden=("num_classes",))


# What `--quick` changes: a tiny run (minutes) for smoke tests.
QUICK = {"steps": 40, "num_train": 64, "num_eval": 16}


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


# ---------------------------------------------------------------------------------------------
# The config's fields as flags, recipes and records: all of it derived from `Config`.


class _Leaf(NamedTuple):
  """One settable field of `Config`, wherever it is nested."""

  name: str                        # field name, unique over the config ("learning_rate")
  owner: tuple[str, ...]           # attributes leading to its dataclass: (), ("train",), ...
  kind: Any                        # its type annotation
  default: Any
  flag: str
  help: str
  choices: tuple[str, ...] | None
  record: str                      # dotted path in the recipe document
  absent: Any                      # dataclasses.MISSING: a recipe must carry it


def _attribute_docs(cls: type) -> dict[str, str]:
  """`{field: first sentence}` from a Google-style `Attributes:` docstring section."""
  docs, name, inside = {}, None, False
  for line in (cls.__doc__ or "").splitlines():
    text = line.strip()
    if text == "Attributes:":
      inside = True
    elif inside and ":" in text and text.split(":")[0].isidentifier():
      name, body = text.split(":", 1)
      docs[name] = body.strip()
    elif inside and text and name:
      docs[name] += " " + text
    elif inside and not text and docs:
      break
  return {k: v.split(". ")[0].rstrip(".") for k, v in docs.items()}


@functools.cache
def _leaves(cls: type = Config, owner: tuple[str, ...] = (), record: str = "",
            flags: tuple[tuple[str, str], ...] = (), hidden: tuple[str, ...] = ()
            ) -> tuple[_Leaf, ...]:
  """The settable fields of `cls` and of its sections, in declaration order."""
  hints = typing.get_type_hints(cls)
  defaults, docs, out = cls(), _attribute_docs(cls), []
  for f in dataclasses.fields(cls):
    kind, meta = hints[f.name], f.metadata
    if dataclasses.is_dataclass(kind):
      out += _leaves(kind, owner + (f.name,), meta["record"],
                     tuple(sorted(meta.get("flags", {}).items())), tuple(meta.get("hidden", ())))
      continue
    if f.name in hidden:
      continue
    flag = meta.get("flag") or dict(flags).get(f.name) or "--" + f.name.replace("_", "-")
    absent = meta.get("absent", dataclasses.MISSING)
    out.append(_Leaf(f.name, owner, kind, getattr(defaults, f.name), flag,
                     meta.get("help", docs.get(f.name, "")), meta.get("choices"),
                     meta.get("record") or f"{record or 'record'}.{f.name}", absent))
  names = [leaf.name for leaf in out]
  assert len(set(names)) == len(names), f"config field names must be unique: {names}"
  return tuple(out)


def _leaf_by_name() -> dict[str, _Leaf]:
  return {leaf.name: leaf for leaf in _leaves()}


def _get(config: Config, leaf: _Leaf) -> Any:
  obj = config
  for attr in leaf.owner:
    obj = getattr(obj, attr)
  return getattr(obj, leaf.name)


def _format(value: Any) -> str:
  """A value as its flag text (`(24, 48)` → `24,48`)."""
  return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def _parse_bool(text: str) -> bool:
  if text.lower() in ("1", "true", "yes", "on"):
    return True
  if text.lower() in ("0", "false", "no", "off"):
    return False
  raise ValueError(f"not a boolean: {text!r}")


def _text_parser(kind: Any) -> Callable[[str], Any]:
  """Parses a flag's text into a value of the annotation `kind`."""
  if kind is bool:
    return _parse_bool
  if typing.get_origin(kind) is tuple:
    item = typing.get_args(kind)[0]

    def items(text: str) -> tuple[Any, ...]:
      return tuple(item(v) for v in text.split(",") if v.strip())

    items.__name__ = f"comma-separated {item.__name__}"  # argparse names it in its errors
    return items
  return kind


def _coerce(leaf: _Leaf, value: Any) -> Any:
  """A value read from JSON as the field's type (`1` → `1.0` for a float, list → tuple)."""
  if leaf.kind is float and isinstance(value, int) and not isinstance(value, bool):
    return float(value)
  if typing.get_origin(leaf.kind) is tuple and isinstance(value, list):
    return tuple(value)
  return value


def replace_fields(config: Config, values: dict[str, Any]) -> Config:
  """`dataclasses.replace` by field name, wherever the field is nested.

  Args:
    config: the config to start from.
    values: `{field name: value}`, e.g. `{"learning_rate": 1e-3, "widths": (32, 64)}`.

  Returns:
    The new `Config` (each section is rebuilt once, so its checks see all changes together).

  Raises:
    ValueError: an unknown field name, or values a section refuses.
  """
  leaves = _leaf_by_name()
  unknown = sorted(set(values) - set(leaves))
  if unknown:
    raise ValueError(f"unknown config fields {unknown}; known: {sorted(leaves)}")

  def rebuild(obj, owner):
    changes = {k: v for k, v in values.items() if leaves[k].owner == owner}
    for f in dataclasses.fields(obj):
      sub = getattr(obj, f.name)
      if dataclasses.is_dataclass(sub):
        new = rebuild(sub, owner + (f.name,))
        if new is not sub:
          changes[f.name] = new
    return dataclasses.replace(obj, **changes) if changes else obj

  return rebuild(config, ())


def _sections() -> dict[str, tuple[type, str, bool]]:
  """`{field: (class, record path, stored whole)}` of `Config`'s nested configs."""
  hints = typing.get_type_hints(Config)
  return {f.name: (hints[f.name], f.metadata["record"], hasattr(hints[f.name], "from_dict"))
          for f in dataclasses.fields(Config) if dataclasses.is_dataclass(hints[f.name])}


def _lookup(doc: dict[str, Any], path: str) -> Any:
  """`doc["a"]["b"]` for `path="a.b"`; a missing key is a `KeyError` naming `path`."""
  node = doc
  for part in path.split("."):
    if not isinstance(node, dict) or part not in node:
      raise KeyError(path)
    node = node[part]
  return node


def config_from_recipe(recipe: dict[str, Any]) -> Config:
  """The configuration a recipe (a run's JSON record, e.g. `segnet.json`) was trained with.

  Every field is read from its place in the record (`option(record=...)`); a field the record
  lacks takes its `absent` value (the setting of the code that wrote such records), and is an
  error if it has none. A section stored whole (the architecture) is read by its own
  `from_dict`; a section stored field by field (`record.train_config`) must not hold fields
  this code does not know (written by other code, it would not replay).

  Args:
    recipe: `{"config": SegNetConfig dict, "record": {"seed", "data", "train_config", ...}}`.

  Returns:
    The `Config`.

  Raises:
    ValueError: a field is missing, unknown or invalid.
  """
  values, whole = {}, {}
  try:
    for name, (cls, path, stored_whole) in _sections().items():
      node = _lookup(recipe, path)
      if stored_whole:
        whole[name] = cls.from_dict(node)
        continue
      unknown = sorted(set(node) - {f.name for f in dataclasses.fields(cls)})
      if unknown:
        raise ValueError(f"the recipe's {path} sets {unknown}, which this code does not know; "
                         "it cannot replay that run")
    for leaf in _leaves():
      if leaf.owner and leaf.owner[0] in whole:
        continue
      parent, _, key = leaf.record.rpartition(".")
      node = _lookup(recipe, parent)
      if key in node:
        values[leaf.name] = _coerce(leaf, node[key])
      elif leaf.absent is dataclasses.MISSING:
        raise KeyError(leaf.record)
      else:
        values[leaf.name] = leaf.absent(node) if callable(leaf.absent) else leaf.absent
  except KeyError as e:
    raise ValueError(f"the recipe lacks field {e.args[0]!r}; pass a segnet.json written by "
                     "this command") from None
  except (TypeError, AttributeError) as e:
    raise ValueError(f"the recipe has a malformed field ({type(e).__name__}: {e}); pass a "
                     "segnet.json written by this command") from None
  return dataclasses.replace(replace_fields(Config(), values), **whole)


def read_recipe(path: str | pathlib.Path) -> dict[str, Any]:
  """The JSON document of a recipe file (a run's record, e.g. `segnet.json`).

  Raises:
    ValueError: no such file, not UTF-8 JSON, or not a JSON object; the message names the file.
  """
  path = pathlib.Path(path)
  if not path.is_file():
    raise ValueError(f"--recipe: no such file {str(path)!r}")
  try:
    recipe = json.loads(path.read_bytes().decode("utf-8"))
  except (OSError, ValueError, RecursionError) as e:
    raise ValueError(f"--recipe {path} is not a JSON recipe ({type(e).__name__}: {e})") from None
  if not isinstance(recipe, dict):
    raise ValueError(f"--recipe {path} is not a JSON recipe (a JSON object with 'config' and "
                     "'record')")
  return recipe


def load_recipe(path: str | pathlib.Path) -> Config:
  """The configuration of a recipe file: `config_from_recipe(read_recipe(path))`.

  Raises:
    ValueError: as `read_recipe` and `config_from_recipe`; the message names the file.
  """
  recipe = read_recipe(path)
  try:
    return config_from_recipe(recipe)
  except ValueError as e:
    raise ValueError(f"--recipe {path}: {e}") from None


def config_to_recipe(config: Config) -> dict[str, Any]:
  """The inverse of `config_from_recipe`: `{"config": {...}, "record": {...}}`, JSON-ready.

  Each field goes to its place in the record, so records keep the layout that earlier code
  wrote and reads (`record.train_config` is `dataclasses.asdict(config.train)`, `config` is
  `config.model.to_dict()`).
  """
  doc = {}

  def put(path, value):
    *parents, key = path.split(".")
    node = doc
    for part in parents:
      node = node.setdefault(part, {})
    node[key] = list(value) if isinstance(value, tuple) else value

  whole = {name: path for name, (_, path, stored_whole) in _sections().items() if stored_whole}
  for name, path in whole.items():
    put(path, getattr(config, name).to_dict())
  for leaf in _leaves():
    if not (leaf.owner and leaf.owner[0] in whole):
      put(leaf.record, _get(config, leaf))
  return doc


def to_argv(config: Config) -> list[str]:
  """Flags that re-create `config` from the defaults (those of fields that differ)."""
  argv, default = [], Config()
  for leaf in _leaves():
    value = _get(config, leaf)
    if value == _get(default, leaf):
      continue
    if leaf.kind is bool:
      argv.append(leaf.flag if value else "--no-" + leaf.flag[2:])
    else:
      argv += [leaf.flag, _format(value)]
  return argv


class _SetField(argparse.Action):
  """`--set name=value`: sets a config field by name, exactly as its own flag would."""

  def __call__(self, parser, namespace, text, option_string=None):
    name, sep, value = text.partition("=")
    leaf = _leaf_by_name().get(name.strip().replace("-", "_"))
    if not sep or leaf is None:
      parser.error(f"--set {text}: expected NAME=VALUE with NAME one of "
                   f"{', '.join(sorted(_leaf_by_name()))}")
    try:
      parsed = _text_parser(leaf.kind)(value)
    except ValueError as e:
      parser.error(f"--set {text}: {e}")
    if leaf.choices is not None and parsed not in leaf.choices:
      parser.error(f"--set {text}: choose from {', '.join(leaf.choices)}")
    setattr(namespace, leaf.name, parsed)


def build_parser() -> argparse.ArgumentParser:
  """The command line: one flag per `Config` field, plus how to run (`--out`, ...).

  Config flags default to "not given", so a recipe's values survive unless a flag (or `--set`)
  overrides them; `--help` shows the `Config` defaults.
  """
  p = argparse.ArgumentParser(
      prog=checkpoint.TRAIN_COMMAND, description=__doc__.split("\n")[0],
      usage="%(prog)s [--recipe RECIPE] [--quick] [--out OUT] [--set NAME=VALUE] "
            "[--FIELD VALUE ...]")
  run = p.add_argument_group("run")
  run.add_argument("--out", default="outputs/segnet.msgpack",
                   help="checkpoint path (default outputs/segnet.msgpack: a run never overwrites "
                        "the packaged weights unless asked to; `--recipe "
                        "models/weights/segnet.json` re-creates them)")
  run.add_argument("--quick", action="store_true",
                   help="a tiny run (minutes): fewer images and steps; for smoke tests")
  run.add_argument("--recipe", default=None,
                   help="a training record (e.g. models/weights/segnet.json): its architecture, "
                        "data and optimisation settings become the defaults, so "
                        "`--recipe models/weights/segnet.json` re-runs the shipped recipe")
  run.add_argument("--set", action=_SetField, metavar="NAME=VALUE", default=argparse.SUPPRESS,
                   help="set any config field by its name (e.g. --set learning_rate=1e-3); "
                        "like the field's flag, it overrides --recipe and --quick")
  run.add_argument("--save-every", type=int, default=250,
                   help="steps between partial checkpoints (<out>.partial.msgpack); 0 = never")
  run.add_argument("--cache", default=None, help="folder to cache rendered views in")
  groups = {(): p.add_argument_group("data and evaluation (Config)")}
  for name, (cls, _, _) in _sections().items():
    groups[(name,)] = p.add_argument_group(f"{name}: {cls.__name__}")
  for leaf in _leaves():
    text = f"{leaf.help} [{leaf.name}; default {_format(leaf.default)}]"
    group = groups[leaf.owner]
    if leaf.kind is bool:
      group.add_argument(leaf.flag, dest=leaf.name, action=argparse.BooleanOptionalAction,
                         default=argparse.SUPPRESS, help=text)
    else:
      group.add_argument(leaf.flag, dest=leaf.name, type=_text_parser(leaf.kind),
                         choices=leaf.choices, default=argparse.SUPPRESS, help=text,
                         metavar=None if leaf.choices else leaf.name.upper())
  return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
  """Parses the command line into the run's `Config`.

  Precedence, lowest first: the `Config` defaults, `--quick`, `--recipe`, then the flags and
  `--set` in the order given.

  Returns:
    `Namespace(config, out, cache, save_every, recipe, quick)`.
  """
  p = build_parser()
  args = p.parse_args(argv)
  config = replace_fields(Config(), QUICK) if args.quick else Config()
  try:
    if args.recipe is not None:
      config = load_recipe(args.recipe)
    given = {leaf.name: getattr(args, leaf.name) for leaf in _leaves()
             if hasattr(args, leaf.name)}
    config = replace_fields(config, given)
  except ValueError as e:
    p.error(str(e))
  return argparse.Namespace(config=config, out=args.out, cache=args.cache,
                            save_every=args.save_every, recipe=args.recipe, quick=args.quick)


# ---------------------------------------------------------------------------------------------
# The run.


def data_splits(config: Config) -> dict[str, dict[str, Any]]:
  """The three rendered splits: `{name: load_domain keyword arguments}`, as recorded."""
  return {"train": {"domain": "train", "num_images": config.num_train, "seed": config.seed},
          "heldout": {"domain": "train", "num_images": config.num_eval,
                      "seed": config.seed + 10_000},
          "test": {"domain": "test", "num_images": config.num_eval, "seed": config.seed + 20_000,
                   "shift": config.shift}}


def load_data(config: Config, *, cache_dir: str | None = None
              ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
  """Renders (or reads from `cache_dir`) the splits of `data_splits(config)`.

  Returns:
    `{name: (rgb (N, H, W, 3) uint8, labels (N, H, W) int32)}`.
  """
  return {name: data_lib.load_domain(height=config.height, width=config.width,
                                     cache_dir=cache_dir, sensing=config.sensing == "on",
                                     **split)
          for name, split in data_splits(config).items()}


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
  """`base` updated recursively with `extra`; a leaf present in both must agree."""
  out = dict(base)
  for key, value in extra.items():
    if isinstance(value, dict) and isinstance(out.get(key), dict):
      out[key] = _merge(out[key], value)
    else:
      assert key not in out or out[key] == value, (key, out[key], value)
      out[key] = value
  return out


def train_and_evaluate(config: Config, out: str | pathlib.Path = "outputs/segnet.msgpack", *,
                       cache_dir: str | None = None, save_every: int = 250,
                       command: str | None = None, progress: bool = True) -> dict[str, Any]:
  """Renders the data, trains, evaluates, and writes the checkpoint with its record.

  Writes `out` (a `checkpoint.save` file), `out` with suffix `.json` (the recipe document:
  architecture, class names, record) and, every `save_every` steps while training,
  `<out>.partial.msgpack` (removed at the end).

  Args:
    config: the run; `config.model.num_classes` is replaced by the embedded world's.
    out: checkpoint path.
    cache_dir: folder to cache rendered views in.
    save_every: steps between partial checkpoints; 0 = never.
    command: the command to record; default: the flags that re-create `config`.
    progress: show a tqdm bar.

  Returns:
    The training record (also stored in the checkpoint).
  """
  if command is None:
    command = " ".join([checkpoint.TRAIN_COMMAND, *to_argv(config)])
  class_names = data_lib.dataset_class_names()
  config = dataclasses.replace(config, model=dataclasses.replace(
      config.model, num_classes=len(class_names)))
  model, cfg, steps = config.model, config.train, config.train.steps
  recipe = config_to_recipe(config)

  t0 = time.time()
  print(f"rendering data: {config.num_train} train, {config.num_eval} val, {config.num_eval} "
        f"test at {config.height}x{config.width}", flush=True)
  data = load_data(config, cache_dir=cache_dir)
  (train_x, train_y), (test_x, test_y) = data["train"], data["test"]
  data_s = time.time() - t0
  weights = class_weights(train_y, model.num_classes, power=cfg.class_weight_power,
                          max_weight=cfg.class_weight_max)
  print(f"data in {data_s:.0f} s; class frequencies "
        f"{np.round(np.bincount(train_y.ravel(), minlength=model.num_classes) / train_y.size, 4)}"
        f"; weights {np.round(weights, 2)}", flush=True)

  key = jax.random.key(config.seed)
  k_init, k_train, k_eval = jax.random.split(key, 3)
  graphdef, params = net.init(model, key=k_init)
  print(f"SegNet: {net.count_params(params):,} parameters, output stride "
        f"{model.output_stride}", flush=True)
  partial_path = pathlib.Path(out).with_suffix(".partial.msgpack")
  t1 = time.time()

  def save_partial(done, current, losses_so_far):
    elapsed = time.time() - t1
    print(f"step {done}/{steps}: loss(last 50) {losses_so_far[-50:].mean():.3f}, "
          f"{done / elapsed:.2f} steps/s, elapsed {elapsed / 60:.1f} min, "
          f"ETA {(steps - done) * elapsed / done / 60:.1f} min", flush=True)
    checkpoint.save(partial_path, current, config=model, class_names=class_names,
                    record={**recipe["record"], "partial": True, "steps_done": done,
                            "command": command})

  params, losses = fit(graphdef, params, train_x, train_y, key=k_train, cfg=cfg,
                       weights=weights, progress=progress, callback=save_partial,
                       callback_every=save_every)
  train_s = time.time() - t1
  print(f"trained {steps} steps in {train_s:.0f} s; loss {losses[:10].mean():.3f} -> "
        f"{losses[-10:].mean():.3f}", flush=True)

  t2 = time.time()
  results = {}
  for name, split in {"train_heldout": "heldout", "test_shifted": "test"}.items():
    x, y = data[split]
    results[name] = evaluate.evaluate_arrays(
        graphdef, params, x, y, key=jax.random.fold_in(k_eval, len(results)),
        num_samples=config.eval_samples, num_classes=model.num_classes)
    print(f"{name}: {json.dumps(results[name]['summary'])}", flush=True)
  eval_s = time.time() - t2

  provenance = {
      "data": {"generator": "jaxfusion.datasets.synthetic.sample_views",
               "version": data_lib.dataset_version(),
               "train_sha256": hashlib.sha256(train_x.tobytes() + train_y.tobytes()).hexdigest(),
               "test_sha256": hashlib.sha256(test_x.tobytes() + test_y.tobytes()).hexdigest(),
               **data_splits(config)},
  }
  record = _merge(_merge({"command": command}, recipe["record"]), provenance)
  record.update({
      "class_weights": [round(float(w), 4) for w in weights],
      "num_params": net.count_params(params),
      "loss_first10": float(losses[:10].mean()), "loss_last10": float(losses[-10:].mean()),
      "seconds": {"data": round(data_s, 1), "train": round(train_s, 1),
                  "eval": round(eval_s, 1)},
      "eval": {k: v["summary"] for k, v in results.items()},
      "platform": {"jax": jax.__version__, "python": platform.python_version(),
                   "machine": platform.machine(), "devices": str(jax.devices())},
  })
  out = checkpoint.save(out, params, config=model, class_names=class_names, record=record)
  record_path = pathlib.Path(out).with_suffix(".json")
  record_path.write_text(json.dumps({"config": recipe["config"], "class_names": class_names,
                                     "record": record}, indent=2) + "\n")
  partial_path.unlink(missing_ok=True)  # The finished checkpoint supersedes it.
  print(f"wrote {out} ({pathlib.Path(out).stat().st_size / 1e6:.2f} MB) and {record_path}",
        flush=True)
  return record


def main(argv: list[str] | None = None) -> dict[str, Any]:
  """`python -m models.train`: flags → `Config` → `train_and_evaluate`."""
  args = parse_args(argv)
  command = checkpoint.TRAIN_COMMAND + " " + " ".join(sys.argv[1:] if argv is None else argv)
  return train_and_evaluate(args.config, args.out, cache_dir=args.cache,
                            save_every=args.save_every, command=command)


if __name__ == "__main__":
  main()
