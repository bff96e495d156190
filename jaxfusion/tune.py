"""Tuning fusion hyperparameters: batched β sweeps and gradient descent on a map-quality surrogate.

- `sweep`: R stacked rules (a β grid, or any `batch.rule_grid`) fused and scored against GT voxel
  labels in one compiled call — per-rule confusion matrices, mIoU, accuracy and the surrogate loss.
- `calibration_loss`: the differentiable surrogate of map quality — the mean cross-entropy
  `−log P(gt label)` of the fused voxel posteriors over the GT voxels the map holds. It is a
  smooth function of β, ε and α₀ (voxel keys and slots do not depend on them), so `jax.grad`
  flows through the whole `lax.scan` of frames.
- `tune_hparams`: an optax (Adam) loop on that loss, run as one jitted `lax.scan` over steps.
  Hyperparameters are optimised in an unconstrained parameterisation (`constrain`):
  `β = sigmoid(u)` (always in (0, 1), so the rule constructor's [0, 1] check never fires),
  `ε = exp(v)` (the gradient in v stays in [−1, 0] per unit of α even at zero variance), and
  `α₀ = softplus(w)` (non-negative).
- `simulate_predictions`: a simulated noisy Bayesian network (MC samples from GT labels, with
  confusions and confident-looking outliers of high epistemic variance), for calibration when
  no trained network is at hand.
- `add_sweep_parser` / `add_tune_beta_parser`: the `jaxfusion sweep` and `jaxfusion tune-beta`
  commands on the embedded synthetic world.

Shape legend: R rules, B sequences, T frames, H×W pixels, K classes, C slots, N GT voxels,
M MC samples.
"""

import argparse
import functools
import json
import math
import time
from typing import NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxfusion import batch
from jaxfusion import camera as camera_lib
from jaxfusion import fusion
from jaxfusion import hashing
from jaxfusion import metrics
from jaxfusion import numerics
from jaxfusion import readout
from jaxfusion import rules as rules_lib
from jaxfusion import state as state_lib
from jaxfusion import sources

# Which continuous hyperparameters each robust rule actually uses.
USED_HPARAMS = {
    "robust_r": ("beta",),
    "robust_d": ("eps", "alpha0"),
    "robust_dr": ("beta", "eps", "alpha0"),
}
_BETA_MARGIN = 1e-4


# --- scoring the map against GT voxels (jittable) ---------------------------------------------
def match_ground_truth(state: state_lib.MapState, gt_coords: jax.Array, gt_labels: jax.Array
                       ) -> tuple[jax.Array, jax.Array]:
  """Posterior of each GT voxel in the map (jittable, differentiable in the rule's leaves).

  Args:
    state: one fused map.
    gt_coords: `(N, 3) int32` GT voxel coordinates.
    gt_labels: `(N,) int32` GT labels; a label outside [0, K) (e.g. padding −1) is not scored.

  Returns:
    `(posterior (N, K) float32, valid (N,) bool)`: valid where the voxel is in the map and has a
    label; invalid rows hold the rule's prior.
  """
  slots, found = hashing.lookup(state.keys, jnp.asarray(gt_coords, jnp.int32),
                                max_probes=state.max_probes)
  posterior, _ = readout.voxel_posteriors(state)
  labels = jnp.asarray(gt_labels, jnp.int32)
  valid = found & (labels >= 0) & (labels < state.num_classes)
  return posterior[slots], valid


def calibration_loss(state: state_lib.MapState, gt_coords: jax.Array, gt_labels: jax.Array
                     ) -> jax.Array:
  """Mean cross-entropy `−log P(gt)` over the GT voxels the map holds (`[] float32`).

  Finite for one-hot posteriors (`log max(p, tiny)`) and 0 when no GT voxel is in the map.
  """
  posterior, valid = match_ground_truth(state, gt_coords, gt_labels)
  labels = jnp.clip(jnp.asarray(gt_labels, jnp.int32), 0, state.num_classes - 1)
  p_true = jnp.take_along_axis(posterior, labels[:, None], axis=-1)[:, 0]
  nll = jnp.where(valid, -numerics.safe_log(p_true), 0.0)
  return jnp.sum(nll) / jnp.maximum(jnp.sum(valid), 1).astype(jnp.float32)


def confusion(state: state_lib.MapState, gt_coords: jax.Array, gt_labels: jax.Array
              ) -> jax.Array:
  """`(K, K) int32` confusion matrix (rows GT, columns argmax prediction) over the GT voxels
  the map holds — `metrics.confusion_matrix` computed inside a jitted call."""
  posterior, valid = match_ground_truth(state, gt_coords, gt_labels)
  num_classes = state.num_classes
  pred = jnp.argmax(posterior, axis=-1)
  gt = jnp.clip(jnp.asarray(gt_labels, jnp.int32), 0, num_classes - 1)
  cell = jnp.where(valid, gt * num_classes + pred, num_classes * num_classes)
  counts = jax.ops.segment_sum(jnp.ones_like(cell), cell,
                               num_segments=num_classes * num_classes + 1)
  return counts[:-1].reshape(num_classes, num_classes)


def _score(state, coords, labels):
  return {"confusion": confusion(state, coords, labels),
          "loss": calibration_loss(state, coords, labels)}


# --- batched sweep ------------------------------------------------------------------------------
def pad_ground_truth(gts: Sequence[dict]) -> tuple[np.ndarray, np.ndarray]:
  """Stacks B GT voxel sets (dicts with `coords (N_b, 3)` and `labels (N_b,)`) into
  `(coords (B, N_max, 3) int32, labels (B, N_max) int32)`; padded rows get label −1 (not scored)."""
  n_max = max(len(g["labels"]) for g in gts)
  coords = np.zeros((len(gts), n_max, 3), np.int32)
  labels = np.full((len(gts), n_max), -1, np.int32)
  for b, g in enumerate(gts):
    coords[b, :len(g["labels"])] = g["coords"]
    labels[b, :len(g["labels"])] = g["labels"]
  return coords, labels


@functools.partial(jax.jit, static_argnames=(
    "capacity", "num_classes", "voxel_size", "max_probes", "frames_axis", "mesh"))
def _sweep_jit(frames, mask, camera, rules, coords, labels, *, capacity, num_classes,
               voxel_size, max_probes, frames_axis, mesh):

  def one(frames, mask_and_gt, camera, rule):
    mask, coords, labels = mask_and_gt
    state = batch.fuse_masked(frames, mask, camera, rule, capacity=capacity,
                              num_classes=num_classes, voxel_size=voxel_size,
                              max_probes=max_probes)
    out = _score(state, coords, labels)
    out["occupied"] = state.num_occupied
    out["dropped"] = state.num_dropped
    return out

  fn = batch.map_over(one, frames_axis=frames_axis, rule_axis=True, camera_axis=False)
  fn = batch.shard_leading(fn, mesh, (False, False, False, True))
  return fn(frames, (mask, coords, labels), camera, rules)


def sweep(frames: fusion.Frame, camera: camera_lib.Camera, gt_coords, gt_labels,
          rules: rules_lib.FusionRule, *, capacity: int, voxel_size: float = 0.1, mask=None,
          max_probes: int = state_lib.DEFAULT_MAX_PROBES, mesh=None) -> dict:
  """Fuses one sequence (or B) with each of R stacked rules and scores every map, in one call.

  Args:
    frames: one sequence (`depth (T, H, W)`, …) or B of them (`depth (B, T, H, W)`, …; see
      `batch.stack_sequences`).
    camera: the intrinsics shared by all frames.
    gt_coords: `(N, 3)` GT voxel coordinates, or `(B, N, 3)` for B sequences
      (`pad_ground_truth`).
    gt_labels: `(N,)` or `(B, N)` GT labels (−1: not scored).
    rules: R stacked rules (`rules.stack`, `batch.rule_grid`).
    capacity: slots C of every map.
    voxel_size: voxel edge in metres (the one the GT was made with).
    mask: `(T,)` / `(B, T) bool`, False for padded frames.
    max_probes: hash probe bound.
    mesh: shard the R rules over this mesh's devices (`batch.make_mesh`).

  Returns:
    dict of NumPy arrays with leading `(R,)` (or `(R, B)`): `confusion (…, K, K)`,
    `iou (…, K)`, `miou`, `accuracy`, `loss` (the surrogate), `occupied`, `dropped`; for B
    sequences also `miou_mean` / `accuracy_mean` `(R,)` averaged over the sequences.
  """
  num_rules = batch._num_rules(rules)  # pylint: disable=protected-access
  batch_dims = 2 if np.ndim(frames.depth) == 4 else 1
  num_classes = np.shape(frames.probs)[-1]
  mask = batch._check_batch_frames(frames, mask, rules, batch_dims=batch_dims,  # pylint: disable=protected-access
                                   num_classes=num_classes)
  coords = np.asarray(gt_coords, np.int32)
  labels = np.asarray(gt_labels, np.int32)
  lead = mask.shape[:batch_dims - 1]
  if coords.shape[:-2] != lead or coords.shape[-1] != 3 or labels.shape != coords.shape[:-1]:
    raise ValueError(f"GT must be coords {lead + ('N', 3)} and labels {lead + ('N',)}; got "
                     f"{coords.shape} and {labels.shape}")
  camera, _ = batch._cameras(camera, None)  # pylint: disable=protected-access
  size = batch._padded_size(num_rules, mesh)  # pylint: disable=protected-access
  rules = batch._pad_leading(rules, size)  # pylint: disable=protected-access
  frames = jax.tree.map(np.asarray, frames)
  if mesh is not None:
    frames, mask, camera, coords, labels = batch.put_sharded(
        (frames, mask, camera, coords, labels), mesh, sharded=False)
    rules = batch.put_sharded(rules, mesh, sharded=True)
  out = _sweep_jit(frames, mask, camera, rules, coords, labels, capacity=capacity,
                   num_classes=num_classes, voxel_size=float(voxel_size),
                   max_probes=max_probes, frames_axis=batch_dims == 2, mesh=mesh)
  out = jax.tree.map(lambda x: np.asarray(x)[:num_rules], batch.gather(out))
  return _summarise(out)


def _summarise(out: dict) -> dict:
  cms = out["confusion"]
  flat = cms.reshape((-1,) + cms.shape[-2:])
  out["iou"] = np.stack([metrics.iou_from_confusion(c) for c in flat]).reshape(cms.shape[:-1])
  out["miou"] = np.array([metrics.mean_iou(c) for c in flat]).reshape(cms.shape[:-2])
  out["accuracy"] = np.array([metrics.accuracy(c) for c in flat]).reshape(cms.shape[:-2])
  if cms.ndim == 4:
    out["miou_mean"] = np.nanmean(out["miou"], axis=1)
    out["accuracy_mean"] = np.nanmean(out["accuracy"], axis=1)
  return out


def sweep_beta(frames: fusion.Frame, camera: camera_lib.Camera, gt_coords, gt_labels, *,
               betas, rule: str = "D+R", capacity: int, voxel_size: float = 0.1, mask=None,
               mesh=None, **hparams) -> dict:
  """`sweep` over a list of β for one robust rule (`"R"` or `"D+R"`); adds `beta (R,)`.

  Extra keyword hyperparameters (`eps`, `alpha0`, `aggregate`) are held fixed.
  """
  stacked = rules_lib.stack([rules_lib.by_name(rule, beta=float(b), **hparams) for b in betas])
  out = sweep(frames, camera, gt_coords, gt_labels, stacked, capacity=capacity,
              voxel_size=voxel_size, mask=mask, mesh=mesh)
  out["beta"] = np.asarray(betas, np.float32)
  return out


# --- differentiable tuning ----------------------------------------------------------------------
def constrain(params: dict) -> dict:
  """Unconstrained parameters → hyperparameters: `beta = sigmoid(beta)`, `eps = exp(eps)`,
  `alpha0 = softplus(alpha0)`. Any real input gives a valid rule."""
  fns = {"beta": jax.nn.sigmoid, "eps": jnp.exp, "alpha0": jax.nn.softplus}
  return {k: fns[k](v) for k, v in params.items()}


def unconstrain(hparams: dict) -> dict:
  """Inverse of `constrain`; β is first clamped into [1e-4, 1 − 1e-4] and α₀ to ≥ 1e-6 (the
  endpoints have no finite preimage)."""
  out = {}
  for k, v in hparams.items():
    v = jnp.asarray(v, jnp.float32)
    if k == "beta":
      b = jnp.clip(v, _BETA_MARGIN, 1.0 - _BETA_MARGIN)
      out[k] = jnp.log(b) - jnp.log1p(-b)
    elif k == "eps":
      out[k] = jnp.log(v)
    elif k == "alpha0":
      a = jnp.maximum(v, 1e-6)
      out[k] = a + jnp.log(-jnp.expm1(-a))   # softplus⁻¹(a) = log(eᵃ − 1)
    else:
      raise ValueError(f"unknown hyperparameter {k!r}; tunable: beta, eps, alpha0")
  return out


def sequence_loss(rule: rules_lib.FusionRule, frames: fusion.Frame, camera: camera_lib.Camera,
                  gt_coords, gt_labels, *, capacity: int, voxel_size: float = 0.1, mask=None,
                  max_probes: int = state_lib.DEFAULT_MAX_PROBES) -> jax.Array:
  """`calibration_loss` of the map fused from `frames` with `rule` (pure; jit / grad it).

  Differentiable in `rule.hparams`. With `depth (B, T, H, W)` frames and `(B, N)` GT the loss
  is the mean over the B sequences.
  """
  batched = frames.depth.ndim == 4
  if mask is None:
    mask = jnp.ones(frames.depth.shape[:2 if batched else 1], bool)
  num_classes = frames.probs.shape[-1]

  def one(frames, mask_and_gt, camera, rule):
    mask, coords, labels = mask_and_gt
    state = batch.fuse_masked(frames, mask, camera, rule, capacity=capacity,
                              num_classes=num_classes, voxel_size=voxel_size,
                              max_probes=max_probes)
    return calibration_loss(state, coords, labels)

  fn = batch.map_over(one, frames_axis=batched, rule_axis=False, camera_axis=False)
  return jnp.mean(fn(frames, (mask, gt_coords, gt_labels), camera, rule))


class TuneResult(NamedTuple):
  """Output of `tune_hparams`."""
  hparams: dict        # name -> float, the fitted (and the fixed) hyperparameters
  rule: rules_lib.FusionRule   # the rule built with them
  losses: np.ndarray   # [steps + 1] surrogate loss before each step, then after the last
  path: dict           # name -> [steps + 1] value of each tuned hyperparameter along the way
  grads: dict          # name -> [steps] gradient of the loss in the unconstrained parameter


@functools.partial(jax.jit, static_argnames=(
    "rule_name", "aggregate", "steps", "capacity", "num_classes", "voxel_size", "max_probes"))
def _tune_loop(params, fixed, learning_rate, frames, mask, camera, coords, labels, *,
               rule_name, aggregate, steps, capacity, num_classes, voxel_size, max_probes):
  optimizer = optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)
  del num_classes

  def loss(params):
    rule = rules_lib.by_name(rule_name, aggregate=aggregate, **fixed, **constrain(params))
    return sequence_loss(rule, frames, camera, coords, labels, capacity=capacity,
                         voxel_size=voxel_size, mask=mask, max_probes=max_probes)

  def step(carry, _):
    params, opt_state = carry
    value, grads = jax.value_and_grad(loss)(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    new_params = optax.apply_updates(params, updates)
    return (new_params, opt_state), (value, constrain(params), grads)

  (params, _), (losses, path, grads) = jax.lax.scan(
      step, (params, optimizer.init(params)), length=steps)
  final = constrain(params)
  losses = jnp.concatenate([losses, loss(params)[None]])
  path = jax.tree.map(lambda p, f: jnp.concatenate([p, f[None]]), path, final)
  return final, losses, path, grads


def tune_hparams(frames: fusion.Frame, camera: camera_lib.Camera, gt_coords, gt_labels, *,
                 rule: str = "D+R", init: Optional[dict] = None, train: Sequence[str] = ("beta",),
                 steps: int = 40, learning_rate: float = 0.1, capacity: int,
                 voxel_size: float = 0.1, mask=None, aggregate: str = "sum",
                 max_probes: int = state_lib.DEFAULT_MAX_PROBES) -> TuneResult:
  """Fits β (and ε, α₀ if asked) by Adam on the calibration cross-entropy, in one jitted call.

  Args:
    frames: the calibration sequence (`depth (T, H, W)`, …) or B of them (`(B, T, H, W)`).
    camera: intrinsics.
    gt_coords: `(N, 3)` (or `(B, N, 3)`) int32 GT voxel coordinates.
    gt_labels: `(N,)` (or `(B, N)`) int32 GT labels (−1: not scored).
    rule: a robust rule by name: "R", "D" or "D+R".
    init: starting hyperparameters (default: the rule's defaults, β = 0.3); β is clamped into
      (0, 1) by the sigmoid parameterisation (see `constrain`).
    train: which of `beta`, `eps`, `alpha0` to fit; the others stay at `init`.
    steps: Adam steps.
    learning_rate: Adam step size in the unconstrained parameters.
    capacity: slots C of the map.
    voxel_size: voxel edge in metres (the GT's).
    mask: `(T,)` / `(B, T) bool` of real frames.
    aggregate: "sum" or "mean" (see `rules.robust`).
    max_probes: hash probe bound.

  Returns:
    TuneResult: fitted hyperparameters, the rule, the loss curve and the path.

  Raises:
    ValueError: a non-robust rule, a hyperparameter the rule does not use, or `steps < 1`.
  """
  probe = rules_lib.by_name(rule, aggregate=aggregate)
  if probe.name not in USED_HPARAMS:
    raise ValueError(f"only the robust rules (R, D, D+R) have continuous hyperparameters to "
                     f"tune; got {rule!r}")
  train = tuple(train)
  unused = [k for k in train if k not in USED_HPARAMS[probe.name]]
  if unused or not train:
    raise ValueError(f"rule {probe.name!r} tunes {USED_HPARAMS[probe.name]}; got {train}")
  if steps < 1:
    raise ValueError(f"steps must be >= 1; got {steps}")
  hparams = {k: float(v) for k, v in probe.hparams.items()}
  for k, v in (init or {}).items():
    if k not in hparams:
      raise ValueError(f"unknown hyperparameter {k!r}; the rule has {sorted(hparams)}")
    hparams[k] = float(v)
  rules_lib.by_name(rule, aggregate=aggregate, **{k: v for k, v in hparams.items()
                                                  if k not in train})   # checks fixed values
  batch_dims = 2 if np.ndim(frames.depth) == 4 else 1
  mask = batch._check_batch_frames(frames, mask, probe, batch_dims=batch_dims,  # pylint: disable=protected-access
                                   num_classes=np.shape(frames.probs)[-1])
  params = unconstrain({k: hparams[k] for k in train})
  fixed = {k: jnp.float32(v) for k, v in hparams.items() if k not in train}
  camera, _ = batch._cameras(camera, None)  # pylint: disable=protected-access
  final, losses, path, grads = _tune_loop(
      params, fixed, jnp.float32(learning_rate), jax.tree.map(jnp.asarray, frames),
      jnp.asarray(mask), camera, jnp.asarray(gt_coords, jnp.int32),
      jnp.asarray(gt_labels, jnp.int32), rule_name=probe.name, aggregate=aggregate,
      steps=int(steps), capacity=capacity, num_classes=np.shape(frames.probs)[-1],
      voxel_size=float(voxel_size), max_probes=max_probes)
  hparams.update({k: float(v) for k, v in final.items()})
  return TuneResult(
      hparams=hparams, rule=rules_lib.by_name(rule, aggregate=aggregate, **hparams),
      losses=np.asarray(losses), path={k: np.asarray(v) for k, v in path.items()},
      grads={k: np.asarray(v) for k, v in grads.items()})


# --- a simulated Bayesian network --------------------------------------------------------------
@functools.partial(jax.jit, static_argnames=("num_classes", "num_samples"))
def simulate_predictions(key: jax.Array, labels: jax.Array, *, num_classes: int,
                         num_samples: int = 8, accuracy: float = 0.75,
                         outlier_rate: float = 0.08, strength: float = 3.0
                         ) -> tuple[jax.Array, jax.Array]:
  """MC-dropout-like predictions from GT labels: a stand-in network for calibration and tests.

  Each pixel's logits favour its true class (`strength`) with probability `accuracy`, else a
  fixed confusion partner (class `(y + 1) mod K`); with probability `outlier_rate` a pixel is a
  confident outlier — a near one-hot vote for a random wrong class whose M samples disagree
  strongly (high epistemic variance), the case the paper's robust rules address. Labels
  outside [0, K) get uniform-ish logits.

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


# --- command line --------------------------------------------------------------------------------
def _next_pow2(n: int) -> int:
  return 1 << max(int(n) - 1, 1).bit_length()


def _parse_spec(spec: str) -> tuple[str, int]:
  try:
    env, traj = spec.split(":")
    return env, int(traj)
  except ValueError:
    raise ValueError(f"a sequence is ENV:TRAJECTORY, e.g. office:0; got {spec!r}") from None


def load_calibration_sequence(spec: str, *, num_frames: int, height: int, width: int,
                              voxel_size: float, domain: str = "test", seed: int = 0,
                              predictions: Optional[str] = None, num_samples: int = 8,
                              key_seed: int = 0) -> dict:
  """A synthetic sequence with GT voxel labels and network outputs, ready to sweep or tune.

  Args:
    spec: "ENV:TRAJECTORY", e.g. "office:0".
    num_frames: T.
    height: H.
    width: W.
    voxel_size: voxel edge in metres for the GT (and the maps).
    domain: "train" or "test" appearance.
    seed: layout seed of the synthetic world.
    predictions: a folder with one sub-folder per sequence name (e.g. `office_0_test/`) of
      per-frame `.npz` predictions (`sources.precomputed_source`); None: `simulate_predictions`.
    num_samples: M for the simulated network.
    key_seed: PRNG seed of the simulated network.

  Returns:
    dict with `name`, `frames` (a Frame with a leading T axis), `camera`, `gt` (dict with
    `coords`, `labels`), `num_classes`, `capacity` (a power of two ≥ 4× the GT voxels), `source`.
  """
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  from jaxfusion.datasets import ground_truth  # pylint: disable=import-outside-toplevel
  env, traj = _parse_spec(spec)
  seq = datasets.make_sequence(env, traj, domain=domain, num_frames=num_frames, height=height,
                               width=width, seed=seed)
  gt = ground_truth.gt_voxel_labels(seq, voxel_size=voxel_size)
  num_classes = seq.num_classes
  if predictions is None:
    key = jax.random.fold_in(jax.random.PRNGKey(key_seed), 97 * traj + len(env))
    probs, var = simulate_predictions(key, seq.labels, num_classes=num_classes,
                                      num_samples=num_samples)
    source = f"simulated network (M={num_samples})"
  else:
    src = sources.precomputed_source(f"{predictions}/{seq.name}")
    preds = [src.predict(jax.random.PRNGKey(0), seq.rgb[i], index=i) for i in range(len(seq))]
    probs = np.stack([np.asarray(p.probs) for p in preds])
    var = (None if preds[0].var is None else np.stack([np.asarray(p.var) for p in preds]))
    source = f"precomputed predictions in {predictions}/{seq.name}"
  frames = fusion.Frame(np.asarray(seq.depth, np.float32), np.asarray(seq.T_world_cam,
                                                                      np.float32),
                        np.asarray(probs, np.float32),
                        None if var is None else np.asarray(var, np.float32))
  return {"name": seq.name, "frames": frames, "camera": seq.camera, "gt": gt,
          "num_classes": num_classes, "source": source,
          "capacity": max(1024, _next_pow2(4 * len(gt["labels"])))}


def _add_data_args(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--frames", type=int, default=20, help="frames per sequence")
  parser.add_argument("--height", type=int, default=60)
  parser.add_argument("--width", type=int, default=80)
  parser.add_argument("--voxel-size", type=float, default=0.1)
  parser.add_argument("--rule", default="D+R", help="robust rule: R, D or D+R")
  parser.add_argument("--aggregate", choices=("sum", "mean"), default="sum")
  parser.add_argument("--predictions", default=None,
                      help="folder of precomputed predictions, one sub-folder per sequence "
                           "(default: a simulated MC-dropout network)")
  parser.add_argument("--num-samples", type=int, default=8, help="M of the simulated network")
  parser.add_argument("--seed", type=int, default=0, help="layout seed of the synthetic world")
  parser.add_argument("--devices", type=int, default=None,
                      help="shard the sweep over this many devices (default: one)")
  parser.add_argument("--json", default=None, help="write the results as JSON here")


def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `sweep`: mIoU / accuracy / surrogate loss for a grid of β, as one compiled call."""
  parser = subparsers.add_parser(
      "sweep", help="fuse one synthetic sequence with a grid of β in one compiled call",
      description="Fuses a synthetic sequence with R values of β at once (jax.vmap over the "
                  "stacked rules, optionally sharded over devices) and reports mIoU, accuracy "
                  "and the calibration cross-entropy per β.")
  parser.add_argument("--sequence", default="office:0", help="ENV:TRAJECTORY")
  parser.add_argument("--num-betas", type=int, default=32)
  parser.add_argument("--beta-min", type=float, default=0.0)
  parser.add_argument("--beta-max", type=float, default=1.0)
  parser.add_argument("--plot", default=None, help="save a plot of mIoU against β here (PNG)")
  _add_data_args(parser)
  parser.set_defaults(func=sweep_command)
  return parser


def add_tune_beta_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `tune-beta`: fit β (and ε, α₀) on a calibration trajectory, score held-out ones."""
  parser = subparsers.add_parser(
      "tune-beta", help="fit β by gradient descent on a calibration trajectory",
      description="Fits β = sigmoid(u) (and optionally ε = exp(v), α₀ = softplus(w)) with Adam "
                  "on the cross-entropy of the fused voxel posteriors against GT voxel labels "
                  "of a calibration trajectory, then reports mIoU at β* and at a baseline β on "
                  "held-out trajectories.")
  parser.add_argument("--calibration", default="office:0", help="ENV:TRAJECTORY")
  parser.add_argument("--held-out", default="office:1,office:2,house:0,house:1,house:2",
                      help="comma-separated ENV:TRAJECTORY list")
  parser.add_argument("--steps", type=int, default=40)
  parser.add_argument("--learning-rate", type=float, default=0.1)
  parser.add_argument("--init-beta", type=float, default=0.3)
  parser.add_argument("--baseline-beta", type=float, default=0.3)
  parser.add_argument("--tune", default="beta",
                      help="comma-separated hyperparameters to fit: beta, eps, alpha0")
  _add_data_args(parser)
  parser.set_defaults(func=tune_beta_command)
  return parser


def _data_kwargs(args) -> dict:
  return {"num_frames": args.frames, "height": args.height, "width": args.width,
          "voxel_size": args.voxel_size, "seed": args.seed, "predictions": args.predictions,
          "num_samples": args.num_samples}


def _mesh(args):
  return None if args.devices in (None, 1) else batch.make_mesh(args.devices)


def _write_json(path: Optional[str], payload: dict) -> None:
  if path:
    with open(path, "w", encoding="utf-8") as f:
      json.dump(payload, f, indent=2)
    print(f"wrote {path}")


def sweep_command(args) -> int:
  """Runs `jaxfusion sweep`; returns the exit status."""
  data = load_calibration_sequence(args.sequence, **_data_kwargs(args))
  betas = np.linspace(args.beta_min, args.beta_max, args.num_betas)
  start = time.perf_counter()
  out = sweep_beta(data["frames"], data["camera"], data["gt"]["coords"], data["gt"]["labels"],
                   betas=betas, rule=args.rule, capacity=data["capacity"],
                   voxel_size=args.voxel_size, mesh=_mesh(args), aggregate=args.aggregate)
  seconds = time.perf_counter() - start
  best = int(np.nanargmax(out["miou"]))
  print(f"{data['name']} ({data['source']}), rule {args.rule}, aggregate={args.aggregate}: "
        f"{len(betas)} β in one call, {seconds:.1f} s including compilation")
  print("   beta    mIoU     acc   xent")
  for b, m, a, l in zip(out["beta"], out["miou"], out["accuracy"], out["loss"]):
    print(f"  {b:5.3f}  {100 * m:6.2f}  {100 * a:6.2f}  {l:6.3f}")
  print(f"best β = {out['beta'][best]:.3f}: mIoU {100 * out['miou'][best]:.2f}")
  if args.plot:
    import matplotlib  # pylint: disable=import-outside-toplevel
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.plot(out["beta"], 100 * out["miou"], "o-", ms=3)
    ax.set_xlabel("β")
    ax.set_ylabel("mIoU (%)")
    ax.set_title(f"{data['name']}, {args.rule} ({args.aggregate})")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.plot, dpi=120)
    print(f"wrote {args.plot}")
  _write_json(args.json, {
      "sequence": data["name"], "source": data["source"], "rule": args.rule,
      "aggregate": args.aggregate, "seconds": seconds, "beta": out["beta"].tolist(),
      "miou": out["miou"].tolist(), "accuracy": out["accuracy"].tolist(),
      "loss": out["loss"].tolist()})
  return 0


def tune_beta_command(args) -> int:
  """Runs `jaxfusion tune-beta`; returns the exit status."""
  train = tuple(t.strip() for t in args.tune.split(",") if t.strip())
  kwargs = _data_kwargs(args)
  cal = load_calibration_sequence(args.calibration, **kwargs)
  start = time.perf_counter()
  result = tune_hparams(cal["frames"], cal["camera"], cal["gt"]["coords"],
                        cal["gt"]["labels"], rule=args.rule, init={"beta": args.init_beta},
                        train=train, steps=args.steps, learning_rate=args.learning_rate,
                        capacity=cal["capacity"], voxel_size=args.voxel_size,
                        aggregate=args.aggregate)
  seconds = time.perf_counter() - start
  beta_star = result.hparams["beta"]
  print(f"calibration {cal['name']} ({cal['source']}), rule {args.rule}, "
        f"aggregate={args.aggregate}: {args.steps} Adam steps in {seconds:.1f} s")
  print(f"  loss {result.losses[0]:.4f} -> {result.losses[-1]:.4f}; fitted "
        + ", ".join(f"{k} = {result.hparams[k]:.4g}" for k in train))
  pair = rules_lib.stack([
      rules_lib.by_name(args.rule, beta=args.baseline_beta, aggregate=args.aggregate),
      result.rule])   # the baseline at the rule's defaults, and the fitted rule
  held_out = []
  for spec in [s.strip() for s in args.held_out.split(",") if s.strip()]:
    data = load_calibration_sequence(spec, **kwargs)
    out = sweep(data["frames"], data["camera"], data["gt"]["coords"], data["gt"]["labels"],
                pair, capacity=data["capacity"], voxel_size=args.voxel_size, mesh=_mesh(args))
    baseline = {k: out[k][:1] for k in ("miou", "accuracy")}
    tuned = {k: out[k][1:] for k in ("miou", "accuracy")}
    held_out.append({"sequence": data["name"],
                     "miou_baseline": float(baseline["miou"][0]),
                     "miou_tuned": float(tuned["miou"][0]),
                     "accuracy_baseline": float(baseline["accuracy"][0]),
                     "accuracy_tuned": float(tuned["accuracy"][0])})
    print(f"  {data['name']:>16}: mIoU {100 * held_out[-1]['miou_baseline']:6.2f} at β = "
          f"{args.baseline_beta:.3f}, {100 * held_out[-1]['miou_tuned']:6.2f} at β* = "
          f"{beta_star:.3f}")
  if held_out:
    mean_base = float(np.mean([h["miou_baseline"] for h in held_out]))
    mean_tuned = float(np.mean([h["miou_tuned"] for h in held_out]))
    print(f"  {'mean':>16}: mIoU {100 * mean_base:6.2f} at β = {args.baseline_beta:.3f}, "
          f"{100 * mean_tuned:6.2f} at β*")
  _write_json(args.json, {
      "calibration": cal["name"], "source": cal["source"], "rule": args.rule,
      "aggregate": args.aggregate, "hparams": result.hparams,
      "losses": result.losses.tolist(), "beta_path": result.path.get("beta", np.array([])
                                                                     ).tolist(),
      "seconds": seconds, "held_out": held_out})
  return 0
