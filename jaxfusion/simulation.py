"""Simulated Bayesian front ends: MC-dropout-like predictions drawn from the ground truth.

Two stand-ins for a segmentation network, for calibration, tests and sweeps when no trained
network is at hand. Both give what `mc_moments` of an MC-dropout net would give (`Frame.probs`,
`Frame.var`), and both are described in the same words: a pixel *favours* the argmax of its MC
mean; it is *wrong* when that class is not its GT label y (labels outside [0, K) are
unlabelled and never wrong); its *confidence* is the mean probability of the favoured class; and
α = −log var of the favoured class is how strongly the robust rules D and D+R trust it. They
differ in how the errors are drawn:

- **Independent errors**, `simulate_predictions`: every pixel's error is drawn on its own. A
  pixel favours y with probability `accuracy`, else the confusion partner (y + 1) mod K; with
  probability `outlier_rate` it is instead a confident outlier, a near one-hot vote for a
  uniformly drawn wrong class. The moments are those of M softmax samples whose spread is small
  on right pixels and larger on wrong ones (largest on outliers), so the variance flags the
  errors. Since the errors of a voxel's many pixels are independent, they average out and every
  rule looks the same: this is the tuning commands' `--front-end simulated`.
- **View-dependent errors**, `simulate_view_predictions` (one frame) and `simulate_sequence`:
  real segmentation nets err in spatially coherent regions (a whole object, a patch of a
  surface) and, over a trajectory, partly in the same regions in every view (the domain gap)
  and partly in regions that change from view to view (distance, objects cut at the border,
  exposure, motion blur, highlights). This front end simulates such a net, with four knobs
  (fields of `ErrorModel`) that decide what a fusion rule can do: how often a region is wrong, how
  confident the errors are, how well the variance flags them, and how correlated the errors of
  one region are across views. A sweep of fusion rules over them is the application's
  `jaxfusion simulate-sweep` (`jaxfusion.lab.simulate`).

Generative model of the view-dependent errors (one sequence and its PRNG key; everything below
is a deterministic function of the key, the frame index t and the frame's GT):

1. **Regions.** A pixel with GT label y ∈ [0, K) belongs to up to two *regions*, both fixed in
   the world so that "the same region" is defined across views:
   - its *object* — the instance id n > 0 (whole objects, walls and the floor; n ≤ 0: none);
   - its *patch* — the world cell `c = ⌊(p_world + o) / ℓ⌋` of its back-projected point, a cube
     of edge ℓ = `patch_size` metres, with one random offset `o ~ U[0, ℓ)³` per sequence (so
     patch borders do not line up with the voxel grid). Pixels without a valid depth have none.
   `regions` chooses "objects", "patches" or "both".
2. **Latents.** For each region r and view t, two standard normals
   `z_{r,t} = √ρ · g_r + √(1−ρ) · h_{r,t}` (one for the error mask, one for the wrong class),
   where `g_r ~ N(0, 1)` is drawn once per sequence (world-fixed) and `h_{r,t} ~ N(0, 1)` per
   view, all independent. So `z_{r,t} ~ N(0, 1)` in every view and `corr(z_{r,t}, z_{r,t'}) = ρ`
   for t ≠ t' — ρ = `cross_view_correlation`: 0 gives independent views, 1 identical ones.
   Normals are `Φ⁻¹(U)` of uniforms made by hashing the region's id (the instance id, or a
   32-bit hash of the cell) with seed words drawn once from the key (`_uniforms`), so no table
   of regions is needed.
3. **Errors.** A region is wrong in view t iff `z^mask_{r,t} < Φ⁻¹(q)`, with q = e =
   `error_rate` for one kind of region and q = 1 − √(1 − e) for "both" (a pixel is wrong when its
   object or its patch is). Hence `P(pixel wrong) = e` exactly for every labelled pixel that has
   a region of each kind in use (a pixel with only one of the two, under "both": q), and the
   masks of larger e contain those of smaller e. A wrong pixel favours the class
   `f = (y + 1 + ⌊Φ(z^class_{r,t}) · (K − 1)⌋) mod K` (uniform over the K − 1 wrong classes,
   the same in every view when ρ = 1; for "both", the object's latent when the object is
   wrong); a right pixel favours f = y.
4. **Mean.** `p̄_f = c` (`confidence`) on right pixels, `c_e` (`error_confidence`) on wrong
   ones; every other class gets `(1 − p̄_f) / (K − 1)`. Pixels whose label is outside [0, K) get
   the uniform distribution and are never wrong.
5. **Variance.** The moments of a Dirichlet(κ·p̄) posterior over the simplex,
   `var_i = p̄_i (1 − p̄_i) / (κ + 1)`, with κ ≥ 0 chosen per pixel so that the favoured class has
   `α_f = −log var_f = α* = α_R − s · [wrong] + τ · ξ`, ξ ~ N(0, 1) independent per pixel and
   view; α_R = `alpha_right`, s = `variance_separation` (nats of α: 0 = the variance does not
   flag errors at all), τ = `alpha_noise` (the scatter that makes α an imperfect detector:
   AUROC(α → right) = Φ(s / (τ√2)) before the bound below). No distribution on [0, 1] with mean
   p̄_f has a variance above p̄_f (1 − p̄_f), so `var_f = min(e^{−α*}, p̄_f (1 − p̄_f))` (κ = 0);
   `error_model` refuses settings whose *mean* α* on wrong pixels breaks that bound, and
   the sweep reports the realised separation. Every `var_i ∈ [0, 0.25]`.

The outputs are the MC mean and variance plus the error mask and the favoured class
(`SimulatedView`). All parameters are float32 pytree leaves (`ErrorModel`), so a grid of
models is one `jax.vmap` and changing them never recompiles. In a sweep every cell uses the same
key: the cells share their random numbers, and differences between cells are not sampling noise.

Shape legend: T frames, H×W pixels, K classes, M MC samples.
"""

import functools
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy import special

from jaxfusion import camera as camera_lib
from jaxfusion import hashing
from jaxfusion import metrics

REGIONS = ("objects", "patches", "both")
# Parameters a sweep may vary (every field of ErrorModel).
SWEEP_PARAMS = ("error_rate", "error_confidence", "confidence", "variance_separation",
                "cross_view_correlation", "alpha_right", "alpha_noise", "patch_size")


class ErrorModel(NamedTuple):
  """The simulated front end's parameters: float32 scalars (stack them to vmap over a grid).

  Attributes:
    error_rate: e ∈ [0, 1], probability that a labelled pixel is wrong in a view.
    error_confidence: c_e ∈ (1/K, 1), mean probability of the wrong class on a wrong pixel.
    confidence: c ∈ (1/K, 1), mean probability of the true class on a right pixel.
    variance_separation: s ≥ 0, nats by which α = −log var of the favoured class is lower on
      wrong pixels than on right ones (0: the variance does not flag errors).
    cross_view_correlation: ρ ∈ [0, 1], correlation of a region's latents across views
      (0: errors drawn independently per view; 1: the same regions wrong in every view).
    alpha_right: α_R, mean α of the favoured class on right pixels.
    alpha_noise: τ ≥ 0, standard deviation of α around its mean (nats), per pixel and view.
    patch_size: ℓ > 0, edge of the world-fixed patch cells in metres.
  """
  error_rate: jax.Array
  error_confidence: jax.Array
  confidence: jax.Array
  variance_separation: jax.Array
  cross_view_correlation: jax.Array
  alpha_right: jax.Array
  alpha_noise: jax.Array
  patch_size: jax.Array


class SimulatedView(NamedTuple):
  """Output of the simulated front end for one frame (or T, with a leading axis).

  Attributes:
    probs: `(H, W, K) float32` MC mean (`Frame.probs`).
    var: `(H, W, K) float32` per-class variance in [0, 0.25] (`Frame.var`).
    wrong: `(H, W) bool` True where the favoured class is not the GT label.
    favoured: `(H, W) int32` the class the pixel favours (its argmax).
  """
  probs: jax.Array
  var: jax.Array
  wrong: jax.Array
  favoured: jax.Array


def _is_concrete(x) -> bool:
  return not isinstance(x, jax.core.Tracer)


def _check_model(model: ErrorModel, num_classes: Optional[int]) -> None:
  """ValueError for out-of-range concrete parameters (traced ones are not checked)."""
  values = {}
  for name, value in model._asdict().items():
    if not _is_concrete(value):
      continue
    arr = np.asarray(value, np.float64)
    if not np.all(np.isfinite(arr)):
      raise ValueError(f"{name} must be finite; got {value}")
    values[name] = arr

  def check(name, ok, what):
    if name in values and not np.all(ok(values[name])):
      raise ValueError(f"{name} must be {what}; got {values[name].tolist()}")

  low = 0.0 if num_classes is None else 1.0 / num_classes
  check("error_rate", lambda v: (v >= 0) & (v <= 1), "in [0, 1]")
  check("cross_view_correlation", lambda v: (v >= 0) & (v <= 1), "in [0, 1]")
  for name in ("confidence", "error_confidence"):
    check(name, lambda v: (v > low) & (v < 1),
          f"in (1/K, 1) = ({low:.4g}, 1) so that the favoured class is the argmax")
  check("variance_separation", lambda v: v >= 0, "≥ 0")
  check("alpha_noise", lambda v: v >= 0, "≥ 0")
  check("patch_size", lambda v: v > 0, "> 0 (metres)")
  # −log(c (1 − c)) is the smallest α a distribution with mean c can have.
  alpha = values.get("alpha_right")
  for name, side, shift in (("confidence", "right", 0.0),
                            ("error_confidence", "wrong", values.get("variance_separation"))):
    if name not in values or alpha is None or shift is None:
      continue
    c = values[name]
    bound = -np.log(c * (1 - c))
    mean_alpha = alpha - shift
    if np.any(mean_alpha < bound):
      formula = "alpha_right" if side == "right" else "alpha_right − variance_separation"
      raise ValueError(
          f"the mean α on {side} pixels ({formula} = {np.round(mean_alpha, 3).tolist()}) is "
          f"below −log(c (1 − c)) = {np.round(bound, 3).tolist()} for {name} = {c.tolist()}: "
          "no distribution with that mean has so high a variance; lower the separation or "
          "raise alpha_right")


def error_model(*, error_rate=0.2, error_confidence=0.8, confidence=0.8,
                variance_separation=2.0, cross_view_correlation=0.5, alpha_right=7.0,
                alpha_noise=1.0, patch_size=0.5, num_classes: Optional[int] = None
                ) -> ErrorModel:
  """Builds (and checks) an `ErrorModel`; see the module docstring for what each knob does.

  The defaults: errors as confident as right predictions (0.8), α on right pixels 7 (variance
  ≈ 1e-3, near the D rule's prior α₀ = −log 1e-3 and 5 nats above the bound at confidence
  0.8, which leaves room to sweep the separation up to about 4 nats), τ = 1 nat of scatter.

  Args:
    error_rate: e ∈ [0, 1].
    error_confidence: c_e ∈ (1/K, 1).
    confidence: c ∈ (1/K, 1).
    variance_separation: s ≥ 0 nats.
    cross_view_correlation: ρ ∈ [0, 1].
    alpha_right: α_R, with α_R ≥ −log(c(1−c)) and α_R − s ≥ −log(c_e(1−c_e)).
    alpha_noise: τ ≥ 0 nats.
    patch_size: ℓ > 0 metres.
    num_classes: K, to check the confidences against 1/K (optional here; the simulators check).

  Returns:
    An ErrorModel of float32 scalars (or of arrays if arrays were passed, for a grid).

  Raises:
    ValueError: a parameter out of range.
  """
  model = ErrorModel(*(jnp.asarray(v, jnp.float32) for v in (
      error_rate, error_confidence, confidence, variance_separation, cross_view_correlation,
      alpha_right, alpha_noise, patch_size)))
  _check_model(model, num_classes)
  return model


# --- independent errors: a simulated MC-dropout network -------------------------------------
@functools.partial(jax.jit, static_argnames=("num_classes", "num_samples"))
def simulate_predictions(key: jax.Array, labels: jax.Array, *, num_classes: int,
                         num_samples: int = 8, accuracy: float = 0.75,
                         outlier_rate: float = 0.08, strength: float = 3.0
                         ) -> tuple[jax.Array, jax.Array]:
  """The front end with independent errors: MC-dropout-like predictions from GT labels.

  Each pixel's error is drawn on its own. Its logits favour its true class (`strength`) with
  probability `accuracy`, else a fixed confusion partner (class `(y + 1) mod K`); with
  probability `outlier_rate` a pixel is a confident outlier — a near one-hot vote for a random
  wrong class whose M samples disagree strongly (high epistemic variance), the case the paper's
  robust rules address. Labels outside [0, K) get uniform-ish logits.

  Args:
    key: PRNG key.
    labels: `(..., H, W) int` GT labels.
    num_classes: K.
    num_samples: M dropout-like samples.
    accuracy: probability that a (non-outlier) pixel favours its true class.
    outlier_rate: fraction of confident outliers.
    strength: logit margin of the favoured class.

  Returns:
    `(probs, var)`, both `(..., H, W, K) float32`: the MC mean and variance (`mc_moments`).
  """
  labels = jnp.asarray(labels, jnp.int32)
  k_conf, k_out, k_cls, k_base, k_samp, k_amp = jax.random.split(key, 6)
  valid = (labels >= 0) & (labels < num_classes)
  y = jnp.where(valid, labels, 0)
  confused = jax.random.uniform(k_conf, labels.shape) > accuracy
  favoured = jnp.where(confused, (y + 1) % num_classes, y)
  outlier = jax.random.uniform(k_out, labels.shape) < outlier_rate
  wrong = (y + 1 + jax.random.randint(k_cls, labels.shape, 0, num_classes - 1)) % num_classes
  favoured = jnp.where(outlier, wrong, favoured)
  margin = jnp.where(outlier, 3.0 * strength, strength) * valid
  logits = margin[..., None] * jax.nn.one_hot(favoured, num_classes)
  logits = logits + 0.5 * jax.random.normal(k_base, logits.shape)
  # Sample spread: low for honest pixels, high for confused and outlier pixels.
  spread = jnp.where(outlier, 4.0, jnp.where(confused, 1.5, 0.4))[..., None]
  spread = spread * jax.random.uniform(k_amp, labels.shape + (1,), minval=0.5, maxval=1.5)
  noise = jax.random.normal(k_samp, (num_samples,) + logits.shape)
  samples = jax.nn.softmax(logits[None] + spread[None] * noise, axis=-1)
  mean = jnp.mean(samples, axis=0)
  var = jnp.mean(jnp.square(samples - mean[None]), axis=0)
  return mean, var


# --- view-dependent errors: the simulator (one frame; vmap over frames and models) ------------
_GOLDEN = np.uint32(0x9E3779B9)
# Seed words drawn from the key (one Threefry call per sequence): 3 per latent stream.
_STREAMS = {"object_world": 0, "object_view": 3, "patch_world": 6, "patch_view": 9,
            "offset": 12, "alpha": 15}
_NUM_WORDS = 18


def _view_words(words: jax.Array, frame_index) -> jax.Array:
  """The seed words of view t: a stream's words mixed with the frame index (distinct per t)."""
  t = jnp.asarray(frame_index).astype(jnp.uint32)
  return hashing.fmix32(words + hashing.fmix32(t * _GOLDEN + np.uint32(1)))


def _uniforms(words: jax.Array, ids: jax.Array, count: int) -> jax.Array:
  """`(N, count)` uniforms in (0, 1), a deterministic function of (3 seed words, id).

  A counter-based generator: each id is mixed with the seed words by MurmurHash3's finaliser
  (a bijection of 32-bit words with full avalanche), and the top 24 bits of each output word
  give U = (b + ½)·2⁻²⁴. A few integer operations per pixel: a Threefry call per pixel
  compiled and ran several times slower on CPU.
  """
  mixed = hashing.fmix32(hashing.fmix32(ids ^ words[0]) + words[1])
  out = jnp.stack([hashing.fmix32(mixed ^ (words[2] + np.uint32((j * 0x9E3779B9) & 0xFFFFFFFF)))
                   for j in range(1, count + 1)], axis=-1)
  return ((out >> 8).astype(jnp.float32) + 0.5) * np.float32(2.0**-24)


def _mixed(world_words, view_words, region, rho):
  """`(N, 2)` latents `√ρ g_r + √(1−ρ) h_{r,t}` of each pixel's region (`Φ⁻¹` of uniforms)."""
  g = special.ndtri(_uniforms(world_words, region, 2))
  h = special.ndtri(_uniforms(view_words, region, 2))
  return jnp.sqrt(rho) * g + jnp.sqrt(1.0 - rho) * h


def simulate_frame(key, labels, instance_ids, frame_index, depth, T_world_cam, camera,
                    model: ErrorModel, *, num_classes: int, regions: str) -> SimulatedView:
  """The generative model of the module docstring for one frame (pure, jittable, vmappable)."""
  height, width = labels.shape
  n = height * width
  k = num_classes
  words = jax.random.bits(key, (_NUM_WORDS,), jnp.uint32)
  stream = lambda name: words[_STREAMS[name]:_STREAMS[name] + 3]
  y = jnp.asarray(labels, jnp.int32).reshape(n)
  labelled = (y >= 0) & (y < k)
  y = jnp.where(labelled, y, 0)
  rho = jnp.clip(model.cross_view_correlation, 0.0, 1.0)
  e = model.error_rate
  q = e if regions != "both" else 1.0 - jnp.sqrt(jnp.maximum(1.0 - e, 0.0))
  threshold = special.ndtri(q)          # −inf at q = 0, +inf at q = 1

  wrong = jnp.zeros(n, bool)
  z_class = jnp.zeros(n, jnp.float32)
  if regions in ("patches", "both"):
    offset = _uniforms(stream("offset"), jnp.zeros(1, jnp.uint32), 3)[0] * model.patch_size
    T = jnp.asarray(T_world_cam, jnp.float32).at[:3, 3].add(offset)
    cells, in_range = camera_lib.depth_to_voxel_keys(depth, T, camera, model.patch_size)
    has_patch = in_range & (jnp.asarray(depth, jnp.float32).reshape(n) > 0)
    z = _mixed(stream("patch_world"), _view_words(stream("patch_view"), frame_index),
               hashing.hash_keys(cells), rho)
    wrong = has_patch & (z[:, 0] < threshold)
    z_class = z[:, 1]
  if regions in ("objects", "both"):
    inst = jnp.asarray(instance_ids, jnp.int32).reshape(n)
    z = _mixed(stream("object_world"), _view_words(stream("object_view"), frame_index),
               jax.lax.bitcast_convert_type(inst, jnp.uint32), rho)
    wrong_object = (inst > 0) & (z[:, 0] < threshold)
    z_class = jnp.where(wrong_object, z[:, 1], z_class)
    wrong = wrong | wrong_object
  wrong = wrong & labelled
  offset_class = 1 + jnp.minimum(jnp.floor(special.ndtr(z_class) * (k - 1)), k - 2).astype(
      jnp.int32)
  favoured = jnp.where(wrong, (y + offset_class) % k, y)

  c = jnp.where(wrong, model.error_confidence, model.confidence)
  c = jnp.where(labelled, c, 1.0 / k)
  one_hot = jax.nn.one_hot(favoured, k, dtype=jnp.float32)
  probs = one_hot * c[:, None] + (1.0 - one_hot) * ((1.0 - c) / (k - 1))[:, None]

  pixel = jnp.arange(n, dtype=jnp.uint32)
  xi = special.ndtri(_uniforms(_view_words(stream("alpha"), frame_index), pixel, 1)[:, 0])
  alpha = model.alpha_right - model.variance_separation * wrong + model.alpha_noise * xi
  bound = c * (1.0 - c)
  var_f = jnp.minimum(jnp.exp(-alpha), bound)
  var = probs * (1.0 - probs) * (var_f / bound)[:, None]
  return SimulatedView(probs.reshape(height, width, k), var.reshape(height, width, k),
                       wrong.reshape(height, width), favoured.reshape(height, width))


def check_regions(regions: str) -> None:
  if regions not in REGIONS:
    raise ValueError(f"regions must be one of {REGIONS}; got {regions!r}")


def _check_num_classes(num_classes) -> None:
  if not isinstance(num_classes, (int, np.integer)) or num_classes < 2:
    raise ValueError(f"num_classes must be an int ≥ 2; got {num_classes!r}")


def check_frame_arrays(labels, instance_ids, depth, T_world_cam, camera, regions, lead=()):
  shape = np.shape(labels)
  if len(shape) != len(lead) + 2:
    raise ValueError(f"labels must have shape {lead + ('H', 'W')}; got {shape}")
  for name, x in (("labels", labels), ("instance_ids", instance_ids)):
    if x is not None and not jnp.issubdtype(jnp.result_type(x), jnp.integer):
      raise TypeError(f"{name} must be an integer array; got dtype {jnp.result_type(x)}")
  if regions in ("objects", "both"):
    if instance_ids is None:
      raise ValueError(f"regions={regions!r} needs instance_ids")
    if np.shape(instance_ids) != shape:
      raise ValueError(f"instance_ids must have the shape of labels {shape}; got "
                       f"{np.shape(instance_ids)}")
  if regions in ("patches", "both"):
    if depth is None or T_world_cam is None or camera is None:
      raise ValueError(f"regions={regions!r} needs depth, T_world_cam and camera (patches are "
                       "cells of the world)")
    if np.shape(depth) != shape:
      raise ValueError(f"depth must have the shape of labels {shape}; got {np.shape(depth)}")
    if np.shape(T_world_cam) != lead + (4, 4):
      raise ValueError(f"T_world_cam must have shape {lead + (4, 4)}; got "
                       f"{np.shape(T_world_cam)}")
    if not isinstance(camera, camera_lib.Camera):
      raise TypeError(f"camera must be a jaxfusion.Camera; got {type(camera).__name__}")


def _fill(labels, instance_ids, depth, T_world_cam, camera, lead=()):
  """Placeholders for inputs the chosen regions do not read (keeps one code path)."""
  shape = np.shape(labels)
  if instance_ids is None:
    instance_ids = jnp.zeros(shape, jnp.int32)
  if depth is None:
    depth = jnp.zeros(shape, jnp.float32)
  if T_world_cam is None:
    T_world_cam = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), lead + (4, 4))
  if camera is None:
    camera = camera_lib.Camera(1.0, 1.0, 0.0, 0.0)
  camera = camera_lib.Camera(*(jnp.asarray(v, jnp.float32) for v in camera))
  return instance_ids, depth, T_world_cam, camera


simulate_frame_jit = jax.jit(simulate_frame, static_argnames=("num_classes", "regions"))


def simulate_view_predictions(key: jax.Array, labels: jax.Array, instance_ids, frame_index, *,
                              num_classes: int, depth=None,
                              T_world_cam=None, camera: Optional[camera_lib.Camera] = None,
                              regions: str = "both", model: Optional[ErrorModel] = None,
                              **params) -> SimulatedView:
  """One frame of the simulated front end with view-dependent, spatially coherent errors.

  Pure and deterministic given `(key, frame_index)`: call it with the same key for every frame
  of a sequence (the world-fixed latents come from the key, the per-view ones from the frame
  index). Jittable and vmappable over frames (`jax.vmap` over labels, instance ids, frame index,
  depth and pose); `simulate_sequence` does that for a whole sequence.

  Args:
    key: PRNG key of the sequence.
    labels: `(H, W) int` GT labels; outside [0, K): unlabelled (uniform, never wrong).
    instance_ids: `(H, W) int` instance ids (> 0; ≤ 0: no object), or None with
      regions="patches".
    frame_index: `[] int` the view's index t in the sequence.
    num_classes: K ≥ 2.
    depth: `(H, W)` z-depth in metres (0: hole); needed for "patches"/"both".
    T_world_cam: `(4, 4)` camera-to-world pose; needed for "patches"/"both".
    camera: intrinsics; needed for "patches"/"both".
    regions: "objects", "patches" or "both".
    model: an `ErrorModel` (e.g. from `error_model`); or give its fields as keyword arguments
      (`error_rate=…`, `variance_separation=…`, …; the rest take `error_model`'s defaults).

  Returns:
    SimulatedView: `probs`, `var` `(H, W, K) float32`, `wrong (H, W) bool`,
    `favoured (H, W) int32`.

  Raises:
    ValueError / TypeError: bad shapes, dtypes, regions or parameters.
  """
  _check_num_classes(num_classes)
  check_regions(regions)
  model = _resolve_model(model, params, num_classes)
  check_frame_arrays(labels, instance_ids, depth, T_world_cam, camera, regions)
  if np.ndim(frame_index) != 0:
    raise ValueError(f"frame_index must be a scalar; got shape {np.shape(frame_index)}")
  instance_ids, depth, T_world_cam, camera = _fill(labels, instance_ids, depth, T_world_cam,
                                                   camera)
  return simulate_frame_jit(key, jnp.asarray(labels), jnp.asarray(instance_ids),
                             jnp.asarray(frame_index, jnp.int32), jnp.asarray(depth,
                                                                             jnp.float32),
                             jnp.asarray(T_world_cam, jnp.float32), camera, model,
                             num_classes=int(num_classes), regions=regions)


def _resolve_model(model, params, num_classes) -> ErrorModel:
  if model is not None and params:
    raise ValueError(f"pass either model= or parameters, not both; got {sorted(params)}")
  if model is None:
    unknown = sorted(set(params) - set(SWEEP_PARAMS))
    if unknown:
      raise TypeError(f"unknown parameters {unknown}; the model's parameters are "
                      f"{list(SWEEP_PARAMS)}")
    return error_model(num_classes=num_classes, **params)
  if not isinstance(model, ErrorModel):
    raise TypeError(f"model must be an ErrorModel; got {type(model).__name__}")
  _check_model(model, num_classes)
  return model


@functools.partial(jax.jit, static_argnames=("num_classes", "regions"))
def _simulate_sequence_jit(key, labels, instance_ids, depth, poses, camera, model, *,
                           num_classes, regions):
  frames = jnp.arange(labels.shape[0], dtype=jnp.int32)
  one = functools.partial(simulate_frame, num_classes=num_classes, regions=regions)
  return jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0, None, None))(
      key, labels, instance_ids, frames, depth, poses, camera, model)


def simulate_sequence(key: jax.Array, labels, instance_ids, *, num_classes: int,
                      depth=None, T_world_cam=None, camera: Optional[camera_lib.Camera] = None,
                      regions: str = "both", model: Optional[ErrorModel] = None,
                      **params) -> SimulatedView:
  """`simulate_view_predictions` for the T frames of a sequence (frame t has index t), in one
  vmapped call.

  Args:
    key: PRNG key of the sequence.
    labels: `(T, H, W) int` GT labels.
    instance_ids: `(T, H, W) int` instance ids, or None with regions="patches".
    num_classes: K.
    depth: `(T, H, W)` z-depth.
    T_world_cam: `(T, 4, 4)` poses.
    camera: intrinsics.
    regions: "objects", "patches" or "both".
    model: an ErrorModel, or its fields as keyword arguments.

  Returns:
    SimulatedView with a leading `(T,)` axis on every field.
  """
  _check_num_classes(num_classes)
  check_regions(regions)
  model = _resolve_model(model, params, num_classes)
  lead = (np.shape(labels)[0],) if np.ndim(labels) == 3 else ("T",)
  check_frame_arrays(labels, instance_ids, depth, T_world_cam, camera, regions, lead=lead)
  instance_ids, depth, T_world_cam, camera = _fill(labels, instance_ids, depth, T_world_cam,
                                                   camera, lead=lead)
  return _simulate_sequence_jit(key, jnp.asarray(labels), jnp.asarray(instance_ids),
                                jnp.asarray(depth, jnp.float32),
                                jnp.asarray(T_world_cam, jnp.float32), camera, model,
                                num_classes=int(num_classes), regions=regions)


# --- statistics of a simulated sequence -------------------------------------------------------
def view_statistics(view: SimulatedView, valid) -> dict:
  """Realised error rate and α = −log var of the favoured class, right vs wrong pixels.

  Args:
    view: a SimulatedView (any leading axes).
    valid: bool mask of the pixels to count (e.g. labelled pixels with depth), shape of `wrong`.

  Returns:
    dict with `error_rate`, `alpha_right_median`, `alpha_wrong_median`, `alpha_separation`
    (difference of the medians), `auroc` (α as a detector of right pixels; 0.5 = useless).
  """
  valid = np.asarray(valid, bool)
  wrong = np.asarray(view.wrong)[valid]
  var = np.asarray(view.var)
  fav = np.asarray(view.favoured)[..., None]
  alpha = -np.log(np.take_along_axis(var, fav, axis=-1)[..., 0][valid] + 1e-12)
  right_a, wrong_a = alpha[~wrong], alpha[wrong]
  med_r = float(np.median(right_a)) if len(right_a) else float("nan")
  med_w = float(np.median(wrong_a)) if len(wrong_a) else float("nan")
  return {"error_rate": float(np.mean(wrong)) if len(wrong) else float("nan"),
          "alpha_right_median": med_r, "alpha_wrong_median": med_w,
          "alpha_separation": med_r - med_w, "auroc": metrics.auroc_of_samples(right_a, wrong_a)}
