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
from jaxfusion import stats
from jaxfusion import state as state_lib
from jaxfusion.rules import base as rules_base
from jaxfusion import sources

# Which continuous hyperparameters each robust rule actually uses.
USED_HPARAMS = {
    "robust_r": ("beta",),
    "robust_d": ("eps", "alpha0"),
    "robust_dr": ("beta", "eps", "alpha0"),
}
_BETA_MARGIN = 1e-4
# Surrogates of map quality `tune_hparams` can minimise (see `sequence_loss`). The default is
# the one whose optimum tracked the mIoU optimum of a β sweep better (`jaxfusion tune-compare`,
# README): on the simulated network the soft IoU falls monotonically towards β = 0 (it rewards
# peaked posteriors more than it rewards correct labels), the cross-entropy's optimum lies
# nearer the mIoU optimum.
OBJECTIVES = ("cross_entropy", "soft_iou")
DEFAULT_OBJECTIVE = "cross_entropy"


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


def soft_confusion(posterior: jax.Array, labels: jax.Array, valid: jax.Array) -> dict:
  """Soft per-class counts of posteriors against GT labels, summed over the valid rows.

  With one-hot posteriors these are a confusion matrix's marginals: `intersection` = TP,
  `pred` = TP + FP, `gt` = TP + FN. They are sums, so the counts of several maps add up to
  the counts of their union (as confusion matrices do).

  Args:
    posterior: `(N, K) float32` class distributions.
    labels: `(N,) int32` GT labels.
    valid: `(N,) bool`, which rows count.

  Returns:
    dict of `(K,) float32`: `intersection` `Σ_n P_n,c [y_n = c]`, `pred` `Σ_n P_n,c`, `gt`
    `Σ_n [y_n = c]`.
  """
  num_classes = posterior.shape[-1]
  onehot = jax.nn.one_hot(jnp.clip(labels, 0, num_classes - 1), num_classes,
                          dtype=jnp.float32)
  onehot = jnp.where(valid[:, None], onehot, 0.0)
  p = jnp.where(valid[:, None], posterior, 0.0)
  return {"intersection": jnp.sum(p * onehot, axis=0), "pred": jnp.sum(p, axis=0),
          "gt": jnp.sum(onehot, axis=0)}


def soft_miou(counts: dict) -> jax.Array:
  """Soft mIoU `[] float32` from `soft_confusion` counts (or their sum over maps).

  `IoU_c = I_c / (P_c + G_c − I_c)`, averaged over the classes present in the GT (`G_c > 0`),
  as `metrics.mean_iou` averages the hard IoU; equal to the hard mIoU for one-hot posteriors,
  and differentiable in the posteriors. 0 when no class is present. Counts with leading axes
  `(…, K)` give `(…)`.
  """
  present = counts["gt"] > 0
  union = counts["pred"] + counts["gt"] - counts["intersection"]
  iou = jnp.where(present, counts["intersection"] / jnp.where(present, union, 1.0), 0.0)
  return jnp.sum(iou, axis=-1) / jnp.maximum(jnp.sum(present, axis=-1), 1).astype(jnp.float32)


def soft_iou_loss(state: state_lib.MapState, gt_coords: jax.Array, gt_labels: jax.Array
                  ) -> jax.Array:
  """`1 − soft mIoU` of the fused voxel posteriors over the GT voxels the map holds
  (`[] float32`): a differentiable surrogate of the map's voxel mIoU (1 when nothing scores)."""
  posterior, valid = match_ground_truth(state, gt_coords, gt_labels)
  return 1.0 - soft_miou(soft_confusion(posterior, jnp.asarray(gt_labels, jnp.int32), valid))


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
  posterior, valid = match_ground_truth(state, coords, labels)
  soft = soft_confusion(posterior, jnp.asarray(labels, jnp.int32), valid)
  return {"confusion": confusion(state, coords, labels),
          "loss": calibration_loss(state, coords, labels),
          "soft_iou_loss": 1.0 - soft_miou(soft),
          "soft": soft}


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
    `iou (…, K)`, `miou`, `accuracy`, `loss` (the cross-entropy surrogate),
    `soft_iou_loss` (1 − soft mIoU), `soft` (dict of `(…, K)` soft counts, `soft_confusion`),
    `occupied`, `dropped`; for B sequences also `miou_mean` / `accuracy_mean` `(R,)` averaged
    over the sequences, and the pooled scores over the B sequences — `confusion_pooled
    (R, K, K)` (summed), `miou_pooled`, `accuracy_pooled`, `loss_mean` and
    `soft_iou_loss_pooled` `(R,)`, the last two being exactly what `sequence_loss` optimises
    on the batch for each objective.
  """
  num_rules = batch.num_stacked_rules(rules)
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
    pooled = cms.sum(axis=1)
    out["confusion_pooled"] = pooled
    out["miou_pooled"] = np.array([metrics.mean_iou(c) for c in pooled])
    out["accuracy_pooled"] = np.array([metrics.accuracy(c) for c in pooled])
    out["loss_mean"] = np.mean(out["loss"], axis=1)
    out["soft_iou_loss_pooled"] = 1.0 - np.asarray(
        soft_miou({k: v.sum(axis=1) for k, v in out["soft"].items()}))
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


def check_objective(objective: str) -> str:
  if objective not in OBJECTIVES:
    raise ValueError(f"objective must be one of {OBJECTIVES}; got {objective!r}")
  return objective


def sequence_loss(rule: rules_lib.FusionRule, frames: fusion.Frame, camera: camera_lib.Camera,
                  gt_coords, gt_labels, *, capacity: int, voxel_size: float = 0.1, mask=None,
                  max_probes: int = state_lib.DEFAULT_MAX_PROBES,
                  objective: str = "cross_entropy") -> jax.Array:
  """The surrogate loss of the map fused from `frames` with `rule` (pure; jit / grad it).

  Differentiable in `rule.hparams`. `objective="cross_entropy"`: `calibration_loss`; with
  `depth (B, T, H, W)` frames and `(B, N)` GT, the mean over the B sequences.
  `objective="soft_iou"`: `1 − soft mIoU`; over B sequences the soft counts are summed first
  (as confusion matrices are pooled over sequences), then the IoU is taken. (The default here
  stays the cross-entropy this function always computed; `tune_hparams` defaults to
  `DEFAULT_OBJECTIVE`.)
  """
  check_objective(objective)
  batched = frames.depth.ndim == 4
  if mask is None:
    mask = jnp.ones(frames.depth.shape[:2 if batched else 1], bool)
  num_classes = frames.probs.shape[-1]

  def one(frames, mask_and_gt, camera, rule):
    mask, coords, labels = mask_and_gt
    state = batch.fuse_masked(frames, mask, camera, rule, capacity=capacity,
                              num_classes=num_classes, voxel_size=voxel_size,
                              max_probes=max_probes)
    if objective == "cross_entropy":
      return calibration_loss(state, coords, labels)
    posterior, valid = match_ground_truth(state, coords, labels)
    return soft_confusion(posterior, jnp.asarray(labels, jnp.int32), valid)

  fn = batch.map_over(one, frames_axis=batched, rule_axis=False, camera_axis=False)
  out = fn(frames, (mask, gt_coords, gt_labels), camera, rule)
  if objective == "cross_entropy":
    return jnp.mean(out)
  if batched:
    out = jax.tree.map(lambda x: jnp.sum(x, axis=0), out)
  return 1.0 - soft_miou(out)


class TuneResult(NamedTuple):
  """Output of `tune_hparams`."""
  hparams: dict        # name -> float, or (K,) ndarray per class: fitted and fixed values
  rule: rules_lib.FusionRule   # the rule built with them
  losses: np.ndarray   # [steps + 1] surrogate loss before each step, then after the last
  path: dict           # name -> [steps + 1] (or [steps + 1, K]) value along the way
  grads: dict          # name -> [steps] (or [steps, K]) gradient in the unconstrained parameter
  objective: str = DEFAULT_OBJECTIVE   # the surrogate that was minimised


@functools.partial(jax.jit, static_argnames=(
    "rule_name", "aggregate", "steps", "capacity", "num_classes", "voxel_size", "max_probes",
    "objective"))
def _tune_loop(params, fixed, learning_rate, frames, mask, camera, coords, labels, *,
               rule_name, aggregate, steps, capacity, num_classes, voxel_size, max_probes,
               objective):
  optimizer = optax.inject_hyperparams(optax.adam)(learning_rate=learning_rate)
  del num_classes

  def loss(params):
    rule = rules_lib.by_name(rule_name, aggregate=aggregate, **fixed, **constrain(params))
    return sequence_loss(rule, frames, camera, coords, labels, capacity=capacity,
                         voxel_size=voxel_size, mask=mask, max_probes=max_probes,
                         objective=objective)

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
                 max_probes: int = state_lib.DEFAULT_MAX_PROBES,
                 objective: str = DEFAULT_OBJECTIVE, per_class: bool = False) -> TuneResult:
  """Fits β (and ε, α₀ if asked) by Adam on a map-quality surrogate, in one jitted call.

  Args:
    frames: the calibration sequence (`depth (T, H, W)`, …) or B of them (`(B, T, H, W)`).
    camera: intrinsics.
    gt_coords: `(N, 3)` (or `(B, N, 3)`) int32 GT voxel coordinates.
    gt_labels: `(N,)` (or `(B, N)`) int32 GT labels (−1: not scored).
    rule: a robust rule by name: "R", "D" or "D+R".
    init: starting hyperparameters (default: the rule's defaults, β = 0.3), scalars or `(K,)`;
      β is clamped into (0, 1) by the sigmoid parameterisation (see `constrain`).
    train: which of `beta`, `eps`, `alpha0` to fit; the others stay at `init`.
    steps: Adam steps.
    learning_rate: Adam step size in the unconstrained parameters.
    capacity: slots C of the map.
    voxel_size: voxel edge in metres (the GT's).
    mask: `(T,)` / `(B, T) bool` of real frames.
    aggregate: "sum" or "mean" (see `rules.robust`).
    max_probes: hash probe bound.
    objective: the surrogate to minimise: "soft_iou" (`1 − soft mIoU` of the fused voxel
      posteriors, pooled over the sequences) or "cross_entropy" (`calibration_loss`, averaged
      over the sequences); see `compare_objectives` for how their optima track the mIoU's.
    per_class: fit one value per class (`(K,)`, SPEC rule 7) for every hyperparameter in
      `train`, starting from `init` broadcast to K.

  Returns:
    TuneResult: fitted hyperparameters, the rule, the loss curve and the path.

  Raises:
    ValueError: a non-robust rule, a hyperparameter the rule does not use, `steps < 1`, an
      unknown objective, or a per-class `init` whose length is not K.
  """
  check_objective(objective)
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
  num_classes = np.shape(frames.probs)[-1]
  hparams = {k: np.asarray(v, np.float32) for k, v in probe.hparams.items()}
  for k, v in (init or {}).items():
    if k not in hparams:
      raise ValueError(f"unknown hyperparameter {k!r}; the rule has {sorted(hparams)}")
    hparams[k] = np.asarray(v, np.float32)
  if per_class:
    for k in train:
      hparams[k] = np.broadcast_to(hparams[k], (num_classes,)).copy()
  rules_base.check_class_shapes(hparams, num_classes, tuple(hparams))
  rules_lib.by_name(rule, aggregate=aggregate, **{k: v for k, v in hparams.items()
                                                  if k not in train})   # checks fixed values
  batch_dims = 2 if np.ndim(frames.depth) == 4 else 1
  mask = batch._check_batch_frames(frames, mask, probe, batch_dims=batch_dims,  # pylint: disable=protected-access
                                   num_classes=num_classes)
  params = unconstrain({k: hparams[k] for k in train})
  fixed = {k: jnp.asarray(v, jnp.float32) for k, v in hparams.items() if k not in train}
  camera, _ = batch._cameras(camera, None)  # pylint: disable=protected-access
  final, losses, path, grads = _tune_loop(
      params, fixed, jnp.float32(learning_rate), jax.tree.map(jnp.asarray, frames),
      jnp.asarray(mask), camera, jnp.asarray(gt_coords, jnp.int32),
      jnp.asarray(gt_labels, jnp.int32), rule_name=probe.name, aggregate=aggregate,
      steps=int(steps), capacity=capacity, num_classes=num_classes,
      voxel_size=float(voxel_size), max_probes=max_probes, objective=objective)
  hparams.update({k: np.asarray(v, np.float32) for k, v in final.items()})
  hparams = {k: float(v) if v.ndim == 0 else v for k, v in hparams.items()}
  return TuneResult(
      hparams=hparams, rule=rules_lib.by_name(rule, aggregate=aggregate, **hparams),
      losses=np.asarray(losses), path={k: np.asarray(v) for k, v in path.items()},
      grads={k: np.asarray(v) for k, v in grads.items()}, objective=objective)


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


# --- scoring lists of rules ----------------------------------------------------------------------
def evaluate_rules(rules: Sequence[rules_lib.FusionRule], frames: fusion.Frame,
                   camera: camera_lib.Camera, gt_coords, gt_labels, *, capacity: int,
                   voxel_size: float = 0.1, mask=None, mesh=None) -> list:
  """Scores each rule of a list (scalar and per-class rules may be mixed) on the same data.

  Rules whose hyperparameters have the same shapes are stacked and scored in one `sweep` call,
  so a scalar rule is scored with its scalar (bit-exact rule 4) path, never as a broadcast
  vector.

  Returns:
    One dict per rule, in order: the `sweep` outputs without the leading R axis.
  """
  if not rules:
    raise ValueError("evaluate_rules needs at least one rule")
  groups = {}
  for i, r in enumerate(rules):
    if not isinstance(r, rules_lib.FusionRule):
      raise TypeError(f"rules must be FusionRules; got {type(r).__name__}")
    key = (r.name, r.aggregate, tuple((k, np.shape(v)) for k, v in sorted(r.hparams.items())))
    groups.setdefault(key, []).append(i)
  results = [None] * len(rules)
  for idx in groups.values():
    out = sweep(frames, camera, gt_coords, gt_labels, rules_lib.stack([rules[i] for i in idx]),
                capacity=capacity, voxel_size=voxel_size, mask=mask, mesh=mesh)
    for j, i in enumerate(idx):
      results[i] = jax.tree.map(lambda x, j=j: x[j], out)
  return results


# --- data: embedded sequences with a simulated network or the shipped one ----------------------
DEFAULT_CACHE_DIR = "outputs/cache"
FRONT_ENDS = ("simulated", "shipped")


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
                              key_seed: int = 0, shift: float = 1.0, front_end=None,
                              cache_dir: Optional[str] = None) -> dict:
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
      per-frame `.npz` predictions (`sources.precomputed_source`).
    num_samples: M (MC-dropout samples of the network, or of the simulated one).
    key_seed: PRNG seed of the MC samples.
    shift: the test domain's shift in [0, 1] (`datasets.make_sequence`).
    front_end: a network front end (`experiments.FrontEnd()`, the shipped weights; or any
      object with `model_id` and `predict(rgb, *, num_samples, key) -> (det, mean, var)`): its
      MC mean and variance are computed once per sequence and cached on disk
      (`experiments.cached_predictions`). None, and no `predictions`: `simulate_predictions`.
    cache_dir: the front end's cache folder (default `outputs/cache`, the study's layout).

  Returns:
    dict with `name` (`<sequence>_s<seed>`), `frames` (a Frame with a leading T axis),
    `camera`, `gt` (dict with `coords`, `labels`), `num_classes`, `capacity` (a power of two ≥
    4× the GT voxels), `source`.
  """
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  from jaxfusion.datasets import ground_truth  # pylint: disable=import-outside-toplevel
  if front_end is not None and predictions is not None:
    raise ValueError("give either a front end or a predictions folder, not both")
  env, traj = _parse_spec(spec)
  seq = datasets.make_sequence(env, traj, domain=domain, num_frames=num_frames, height=height,
                               width=width, seed=seed, shift=shift)
  gt = ground_truth.gt_voxel_labels(seq, voxel_size=voxel_size)
  num_classes = seq.num_classes
  if front_end is not None:
    from jaxfusion import experiments  # pylint: disable=import-outside-toplevel
    cache_dir = cache_dir or DEFAULT_CACHE_DIR
    config = experiments.ExperimentConfig(
        num_frames=num_frames, height=height, width=width, num_samples=num_samples,
        domain=domain, shift=float(shift), scene_seed=int(seed), seed=int(key_seed),
        voxel_size=voxel_size)
    preds = experiments.cached_predictions(front_end, seq, config, cache_dir)
    probs, var = preds["mean"], preds["var"]
    source = f"network {front_end.model_id} (MC dropout, M={num_samples}; cache {cache_dir})"
  elif predictions is None:
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
  return {"name": f"{seq.name}_s{seed}", "frames": frames, "camera": seq.camera, "gt": gt,
          "num_classes": num_classes, "source": source,
          "capacity": max(1024, _next_pow2(4 * len(gt["labels"])))}


def load_sequence_batch(units: Sequence[tuple], **kwargs) -> dict:
  """B sequences as one padded batch, for `tune_hparams`, `sweep` and `evaluate_rules`.

  Args:
    units: `[(env, trajectory, layout_seed)]`.
    **kwargs: passed to `load_calibration_sequence` (sizes, front end, …).

  Returns:
    dict with `names` (B), `frames` (`(B, T, …)`), `mask` `(B, T)`, `camera`, `coords`
    `(B, N, 3)`, `labels` `(B, N)` (−1 padding), `capacity`, `num_classes`, `source`.
  """
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  if not units:
    raise ValueError("load_sequence_batch needs at least one (env, trajectory, seed) unit")
  datas = [load_calibration_sequence(f"{env}:{traj}", seed=int(seed), **kwargs)
           for env, traj, seed in tqdm(units, desc="sequences", leave=False)]
  cameras = {tuple(float(c) for c in d["camera"]) for d in datas}
  if len(cameras) != 1:
    raise ValueError(f"the sequences of a batch must share one camera; got {sorted(cameras)}")
  frames, mask = batch.stack_sequences([d["frames"] for d in datas])
  coords, labels = pad_ground_truth([d["gt"] for d in datas])
  return {"names": [d["name"] for d in datas], "frames": frames, "mask": mask,
          "camera": datas[0]["camera"], "coords": coords, "labels": labels,
          "capacity": max(d["capacity"] for d in datas), "num_classes": datas[0]["num_classes"],
          "source": datas[0]["source"]}


# --- do the surrogates' optima track the mIoU's? -----------------------------------------------
def _ranks(x: np.ndarray) -> np.ndarray:
  """Average ranks (ties share the mean rank)."""
  x = np.asarray(x, np.float64)
  order = np.argsort(x, kind="stable")
  ranks = np.empty(len(x))
  ranks[order] = np.arange(len(x), dtype=np.float64)
  for value in np.unique(x):
    tie = x == value
    ranks[tie] = ranks[tie].mean()
  return ranks


def spearman(a, b) -> float:
  """Spearman rank correlation of two equal-length vectors (NaN if one is constant)."""
  ra, rb = _ranks(a), _ranks(b)
  ra, rb = ra - ra.mean(), rb - rb.mean()
  denom = math.sqrt(float(np.sum(ra * ra) * np.sum(rb * rb)))
  return float(np.sum(ra * rb) / denom) if denom > 0 else float("nan")


def compare_objectives(calibration: dict, held_out: dict, *, rule: str = "D+R", betas=None,
                       steps: int = 40, learning_rate: float = 0.1, init_beta: float = 0.3,
                       aggregate: str = "sum", voxel_size: float = 0.1, mesh=None) -> dict:
  """How well each surrogate's optimum matches the mIoU optimum of a β sweep.

  For each objective in `OBJECTIVES`, β is tuned by gradient on the calibration batch
  (`tune_hparams`), and scored on the held-out batch; a β grid is swept on both batches to
  give the mIoU curve and each surrogate's curve (the exact batch losses `tune_hparams`
  minimises). mIoU is pooled over the sequences of a batch (confusions summed).

  Args:
    calibration: a batch from `load_sequence_batch` to tune on.
    held_out: a batch to judge on.
    rule: "R" or "D+R".
    betas: the sweep grid (default 0, 0.05, …, 1).
    steps: Adam steps of each tuning run.
    learning_rate: Adam step size (in logit β).
    init_beta: start of each tuning run.
    aggregate: pixel aggregation of the rule.
    voxel_size: voxel edge (the GT's).
    mesh: shard the sweeps over devices.

  Returns:
    dict with `betas`, `grid` (per batch: `miou`, and per objective its loss, each `(R,)`),
    `best_beta` (per batch: the grid's mIoU argmax), `objectives` (per objective: `beta_star`
    (gradient), `grid_argmin` (per batch), `spearman` (per batch: rank correlation of −loss
    with mIoU over the grid), `held_out_miou` at β*, `distance` |β* − held-out best β| and
    `regret` (held-out best grid mIoU − mIoU at β*), `losses`, `seconds`).
  """
  betas = np.round(np.linspace(0.0, 1.0, 21), 4) if betas is None else np.asarray(betas)
  grid, best = {}, {}
  for name, data in (("calibration", calibration), ("held_out", held_out)):
    out = sweep_beta(data["frames"], data["camera"], data["coords"], data["labels"],
                     betas=betas, rule=rule, capacity=data["capacity"], voxel_size=voxel_size,
                     mask=data["mask"], mesh=mesh, aggregate=aggregate)
    grid[name] = {"miou": out["miou_pooled"], "cross_entropy": out["loss_mean"],
                  "soft_iou": out["soft_iou_loss_pooled"]}
    best[name] = float(betas[int(np.nanargmax(out["miou_pooled"]))])
  tuned, seconds = {}, {}
  for objective in OBJECTIVES:
    start = time.perf_counter()
    tuned[objective] = tune_hparams(
        calibration["frames"], calibration["camera"], calibration["coords"],
        calibration["labels"], rule=rule, init={"beta": init_beta}, steps=steps,
        learning_rate=learning_rate, capacity=calibration["capacity"], voxel_size=voxel_size,
        mask=calibration["mask"], aggregate=aggregate, objective=objective)
    seconds[objective] = time.perf_counter() - start
  evals = evaluate_rules([res.rule for res in tuned.values()], held_out["frames"],
                         held_out["camera"], held_out["coords"], held_out["labels"],
                         capacity=held_out["capacity"], voxel_size=voxel_size,
                         mask=held_out["mask"], mesh=mesh)
  report = {}
  for (objective, res), ev in zip(tuned.items(), evals):
    beta_star = float(res.hparams["beta"])
    report[objective] = {
        "beta_star": beta_star,
        "grid_argmin": {n: float(betas[int(np.nanargmin(g[objective]))])
                        for n, g in grid.items()},
        "spearman": {n: spearman(-g[objective], g["miou"]) for n, g in grid.items()},
        "held_out_miou": float(ev["miou_pooled"]),
        "distance": abs(beta_star - best["held_out"]),
        "regret": float(np.nanmax(grid["held_out"]["miou"]) - ev["miou_pooled"]),
        "losses": res.losses.tolist(), "seconds": seconds[objective]}
  return {"betas": betas, "grid": grid, "best_beta": best, "objectives": report,
          "rule": rule, "aggregate": aggregate, "steps": steps, "init_beta": init_beta,
          "calibration": calibration["names"], "held_out": held_out["names"],
          "source": calibration["source"]}


def format_comparison(result: dict) -> str:
  """A Markdown table of `compare_objectives`."""
  best = result["best_beta"]
  held = result["grid"]["held_out"]["miou"]
  lines = [
      f"rule {result['rule']} ({result['aggregate']}), {len(result['calibration'])} "
      f"calibration / {len(result['held_out'])} held-out sequences, {result['source']}; "
      f"β grid optimum (mIoU): calibration {best['calibration']:.2f}, held-out "
      f"{best['held_out']:.2f} ({100 * np.nanmax(held):.2f} mIoU)", "",
      "| objective | β* (gradient) | grid argmin cal. / held-out | Spearman(−loss, mIoU) cal. / "
      "held-out | held-out mIoU at β* | regret | |β* − best β| |",
      "|---|---|---|---|---|---|---|"]
  for name, r in result["objectives"].items():
    lines.append(
        f"| {name} | {r['beta_star']:.3f} | {r['grid_argmin']['calibration']:.2f} / "
        f"{r['grid_argmin']['held_out']:.2f} | {r['spearman']['calibration']:.2f} / "
        f"{r['spearman']['held_out']:.2f} | {100 * r['held_out_miou']:.2f} | "
        f"{100 * r['regret']:.2f} | {r['distance']:.3f} |")
  return "\n".join(lines)


def plot_comparison(path: str, result: dict) -> None:
  """PNG: mIoU and the two surrogates (rescaled to [0, 1], higher is better) against β on the
  calibration and held-out batches, with each objective's β*."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  from jaxfusion import io  # pylint: disable=import-outside-toplevel
  betas = result["betas"]
  colors = {"soft_iou": "tab:orange", "cross_entropy": "tab:green"}
  fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharex=True)
  for ax, name in zip(axes, ("calibration", "held_out")):
    g = result["grid"][name]
    ax.plot(betas, 100 * g["miou"], "o-", ms=3, color="tab:blue", label="mIoU")
    ax.set_ylabel("mIoU (%)")
    ax.set_xlabel("β")
    ax.set_title(name.replace("_", "-"))
    twin = ax.twinx()
    for obj, color in colors.items():
      loss = np.asarray(g[obj], np.float64)
      span = np.nanmax(loss) - np.nanmin(loss)
      score = (np.nanmax(loss) - loss) / span if span > 0 else np.zeros_like(loss)
      twin.plot(betas, score, "--", color=color, label=f"−{obj} (rescaled)")
      ax.axvline(result["objectives"][obj]["beta_star"], color=color, lw=1)
    twin.set_ylim(-0.05, 1.05)
    twin.set_yticks([])
    if name == "held_out":
      lines = ax.get_legend_handles_labels()
      more = twin.get_legend_handles_labels()
      ax.legend(lines[0] + more[0], lines[1] + more[1], fontsize=7, loc="lower left")
  fig.suptitle("surrogate optima (vertical lines: β* by gradient on calibration)", fontsize=9)
  fig.tight_layout()
  io.atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
  plt.close(fig)


# --- the protocol: tune on calibration seeds, judge on held-out seeds ----------------------------
def tune_protocol(calibration: dict, held_out: dict, *, rule: str = "D+R",
                  objective: str = DEFAULT_OBJECTIVE, baseline_beta: float = 0.3,
                  steps: int = 40, learning_rate: float = 0.1, aggregate: str = "sum",
                  voxel_size: float = 0.1, num_resamples: int = stats.DEFAULT_RESAMPLES,
                  confidence: float = stats.DEFAULT_CONFIDENCE, seed: int = 0,
                  mesh=None) -> dict:
  """Scalar β*, per-class β* and the paper's β side by side on held-out sequences.

  β is tuned by gradient (`tune_hparams`, `objective`) on the calibration batch, once as one
  scalar and once per class (SPEC rule 7); the three rules are then fused on every held-out
  sequence and scored against GT voxel labels. Intervals are percentile bootstraps over the
  held-out sequences (`stats.bootstrap` of the pooled confusion's mIoU), and the differences
  to the baseline are paired bootstraps on the same resamples (`stats.paired_difference`).

  Args:
    calibration: a batch from `load_sequence_batch` (e.g. layout seeds A).
    held_out: a batch on other layouts (seeds B).
    rule: "R" or "D+R".
    objective: the tuning surrogate (see `tune_hparams`).
    baseline_beta: the paper's β.
    steps: Adam steps per tuning run.
    learning_rate: Adam step size.
    aggregate: pixel aggregation.
    voxel_size: voxel edge (the GT's).
    num_resamples: bootstrap resamples.
    confidence: interval coverage.
    seed: bootstrap seed.
    mesh: shard the evaluations over devices.

  Returns:
    dict with `methods` (name → `beta` (float or list of K), `miou` / `accuracy`
    `stats.Interval` on the held-out sequences, `vs_baseline` (paired Interval of the mIoU
    difference, None for the baseline), `iou` (per class, pooled), `miou_calibration`,
    `miou_per_sequence`), `tuning` (per tuned method: losses, seconds), and the settings.
  """
  check_objective(objective)
  tuned, timing = {}, {}
  for name, per_class in (("scalar β*", False), ("per-class β*", True)):
    start = time.perf_counter()
    tuned[name] = tune_hparams(
        calibration["frames"], calibration["camera"], calibration["coords"],
        calibration["labels"], rule=rule, init={"beta": baseline_beta}, steps=steps,
        learning_rate=learning_rate, capacity=calibration["capacity"], voxel_size=voxel_size,
        mask=calibration["mask"], aggregate=aggregate, objective=objective,
        per_class=per_class)
    timing[name] = time.perf_counter() - start
  baseline = f"β = {baseline_beta:g}"
  rules = {baseline: rules_lib.by_name(rule, beta=baseline_beta, aggregate=aggregate)}
  rules.update({name: res.rule for name, res in tuned.items()})
  scored = {}
  for split, data in (("held_out", held_out), ("calibration", calibration)):
    outs = evaluate_rules(list(rules.values()), data["frames"], data["camera"], data["coords"],
                          data["labels"], capacity=data["capacity"], voxel_size=voxel_size,
                          mask=data["mask"], mesh=mesh)
    scored[split] = dict(zip(rules, outs))
  counts = stats.resample_counts(len(held_out["names"]), num_resamples, seed=seed)
  base_cms = scored["held_out"][baseline]["confusion"]
  methods = {}
  for name, rule_obj in rules.items():
    out = scored["held_out"][name]
    cms = out["confusion"]   # (S, K, K), one per held-out sequence
    beta = np.asarray(rule_obj.hparams["beta"])
    methods[name] = {
        "beta": float(beta) if beta.ndim == 0 else beta.tolist(),
        "miou": stats.bootstrap(cms, stats.miou, counts=counts, confidence=confidence),
        "accuracy": stats.bootstrap(cms, stats.accuracy, counts=counts, confidence=confidence),
        "vs_baseline": (None if name == baseline else stats.paired_difference(
            cms, base_cms, stats.miou, counts=counts, confidence=confidence)),
        "iou": metrics.iou_from_confusion(out["confusion_pooled"]).tolist(),
        "miou_calibration": float(scored["calibration"][name]["miou_pooled"]),
        "miou_per_sequence": [float(m) for m in out["miou"]]}
  return {"methods": methods, "baseline": baseline, "rule": rule, "objective": objective,
          "aggregate": aggregate, "steps": steps, "learning_rate": learning_rate,
          "calibration": calibration["names"], "held_out": held_out["names"],
          "source": calibration["source"], "confidence": confidence,
          "num_resamples": num_resamples,
          "tuning": {name: {"losses": res.losses.tolist(), "seconds": timing[name]}
                     for name, res in tuned.items()}}


def format_protocol(result: dict, class_names: Sequence[str]) -> str:
  """Markdown tables of `tune_protocol`: mIoU with intervals, and per-class β and IoU."""
  pct = lambda iv: f"{100 * iv.estimate:.2f} [{100 * iv.low:.2f}, {100 * iv.high:.2f}]"
  sgn = lambda iv: (f"{100 * iv.estimate:+.2f} [{100 * iv.low:+.2f}, {100 * iv.high:+.2f}]"
                    if iv is not None else "—")
  conf = int(round(100 * result["confidence"]))
  lines = [
      f"rule {result['rule']} ({result['aggregate']}), tuned by {result['objective']} on "
      f"{len(result['calibration'])} calibration sequences, judged on "
      f"{len(result['held_out'])} held-out sequences ({result['source']}); {conf} % bootstrap "
      f"intervals over held-out sequences ({result['num_resamples']} resamples)", "",
      f"| method | β | held-out mIoU | Δ mIoU vs {result['baseline']} (paired) | held-out acc. "
      f"| calibration mIoU |", "|---|---|---|---|---|---|"]
  for name, m in result["methods"].items():
    beta = (f"{m['beta']:.3f}" if isinstance(m["beta"], float)
            else "per class (below)")
    lines.append(f"| {name} | {beta} | {pct(m['miou'])} | {sgn(m['vs_baseline'])} | "
                 f"{pct(m['accuracy'])} | {100 * m['miou_calibration']:.2f} |")
  lines += ["", "| | " + " | ".join(class_names) + " |",
            "|---|" + "---|" * len(class_names)]
  for name, m in result["methods"].items():
    beta = m["beta"] if isinstance(m["beta"], list) else [m["beta"]] * len(class_names)
    lines.append(f"| β ({name}) | " + " | ".join(f"{b:.3f}" for b in beta) + " |")
  for name, m in result["methods"].items():
    lines.append(f"| IoU ({name}) | " + " | ".join(
        "—" if v is None or not np.isfinite(v) else f"{100 * v:.1f}" for v in m["iou"]) + " |")
  return "\n".join(lines)


def plot_per_class_beta(path: str, result: dict, class_names: Sequence[str]) -> None:
  """PNG: the per-class β* as bars, the scalar β* and the baseline as lines."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  from jaxfusion import io  # pylint: disable=import-outside-toplevel
  methods = result["methods"]
  per_class = methods["per-class β*"]["beta"]
  fig, ax = plt.subplots(figsize=(6, 3.2))
  x = np.arange(len(class_names))
  ax.bar(x, per_class, color="tab:orange", label="per-class β*")
  ax.axhline(methods["scalar β*"]["beta"], color="tab:green", ls="--",
             label=f"scalar β* = {methods['scalar β*']['beta']:.3f}")
  ax.axhline(methods[result["baseline"]]["beta"], color="grey", ls=":",
             label=result["baseline"])
  ax.set_xticks(x)
  ax.set_xticklabels(class_names, rotation=30, ha="right")
  ax.set_ylabel("β")
  ax.set_ylim(0, 1)
  ax.set_title(f"{result['rule']}: β tuned by {result['objective']} on "
               f"{len(result['calibration'])} calibration sequences", fontsize=9)
  ax.legend(fontsize=7)
  fig.tight_layout()
  io.atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
  plt.close(fig)


def _jsonable(x):
  if isinstance(x, stats.Interval):
    return {"estimate": x.estimate, "low": x.low, "high": x.high}
  if isinstance(x, dict):
    return {k: _jsonable(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_jsonable(v) for v in x]
  if isinstance(x, np.ndarray):
    return x.tolist()
  if isinstance(x, (np.floating, np.integer)):
    return x.item()
  return x


# --- command line --------------------------------------------------------------------------------
def _add_data_args(parser: argparse.ArgumentParser, *, rule_help: str = "robust rule: R, D "
                   "or D+R") -> None:
  parser.add_argument("--frames", type=int, default=20, help="frames per sequence")
  parser.add_argument("--height", type=int, default=60)
  parser.add_argument("--width", type=int, default=80)
  parser.add_argument("--voxel-size", type=float, default=0.1)
  parser.add_argument("--rule", default="D+R", help=rule_help)
  parser.add_argument("--aggregate", choices=("sum", "mean"), default="sum")
  parser.add_argument("--front-end", choices=FRONT_ENDS, default="simulated",
                      help="'shipped': the packaged MC-dropout network, run once per sequence "
                           "and cached (--cache-dir); 'simulated': simulate_predictions")
  parser.add_argument("--checkpoint", default=None,
                      help="weights for --front-end shipped (default: the packaged ones)")
  parser.add_argument("--cache-dir", default=DEFAULT_CACHE_DIR,
                      help="front-end cache folder (shared with `jaxfusion study`'s layout)")
  parser.add_argument("--predictions", default=None,
                      help="folder of precomputed predictions, one sub-folder per sequence "
                           "(instead of a front end)")
  parser.add_argument("--num-samples", type=int, default=8, help="MC samples M")
  parser.add_argument("--shift", type=float, default=1.0, help="test-domain shift in [0, 1]")
  parser.add_argument("--seed", type=int, default=0, help="layout seed of the synthetic world")
  parser.add_argument("--devices", type=int, default=None,
                      help="shard the sweep over this many devices (default: one)")
  parser.add_argument("--json", default=None, help="write the results as JSON here")


def _front_end(args):
  if args.front_end == "simulated":
    return None
  if args.predictions is not None:
    raise ValueError("--predictions and --front-end shipped exclude each other")
  from jaxfusion import experiments  # pylint: disable=import-outside-toplevel
  return experiments.FrontEnd(args.checkpoint)


def _data_kwargs(args, front_end=None) -> dict:
  return {"num_frames": args.frames, "height": args.height, "width": args.width,
          "voxel_size": args.voxel_size, "predictions": args.predictions,
          "num_samples": args.num_samples, "shift": args.shift, "front_end": front_end,
          "cache_dir": args.cache_dir}


def _mesh(args):
  return None if args.devices in (None, 1) else batch.make_mesh(args.devices)


def _write_text(path: str, text: str) -> None:
  from jaxfusion import io  # pylint: disable=import-outside-toplevel

  def write(tmp):
    with open(tmp, "w", encoding="utf-8") as f:
      f.write(text)

  io.atomic_write(path, write)


def _write_json(path: Optional[str], payload: dict) -> None:
  if path:
    _write_text(path, json.dumps(_jsonable(payload), indent=2))
    print(f"wrote {path}")


def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `sweep`: mIoU / accuracy / surrogate losses for a grid of β, as one compiled call."""
  parser = subparsers.add_parser(
      "sweep", help="fuse one synthetic sequence with a grid of β in one compiled call",
      description="Fuses a synthetic sequence with R values of β at once (jax.vmap over the "
                  "stacked rules, optionally sharded over devices) and reports mIoU, accuracy "
                  "and both tuning surrogates (cross-entropy, 1 − soft mIoU) per β. The "
                  "network is simulated, the shipped one (--front-end shipped) or "
                  "precomputed (--predictions).")
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
      description="Fits β = sigmoid(u) (and optionally ε = exp(v), α₀ = softplus(w)), one "
                  "value or one per class, with Adam on a surrogate of map quality (the "
                  "cross-entropy by default, or 1 − soft mIoU) of the fused voxel posteriors "
                  "against GT voxel labels of a calibration trajectory, then reports mIoU at "
                  "β* and at a baseline β on held-out trajectories.")
  parser.add_argument("--calibration", default="office:0", help="ENV:TRAJECTORY")
  parser.add_argument("--held-out", default="office:1,office:2,house:0,house:1,house:2",
                      help="comma-separated ENV:TRAJECTORY list")
  parser.add_argument("--steps", type=int, default=40)
  parser.add_argument("--learning-rate", type=float, default=0.1)
  parser.add_argument("--init-beta", type=float, default=0.3)
  parser.add_argument("--baseline-beta", type=float, default=0.3)
  parser.add_argument("--tune", default="beta",
                      help="comma-separated hyperparameters to fit: beta, eps, alpha0")
  parser.add_argument("--objective", choices=OBJECTIVES, default=DEFAULT_OBJECTIVE,
                      help="surrogate to minimise")
  parser.add_argument("--per-class", action="store_true",
                      help="fit one value per class for each tuned hyperparameter")
  _add_data_args(parser)
  parser.set_defaults(func=tune_beta_command)
  return parser


def _add_protocol_args(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--envs", nargs="+", choices=("office", "house"),
                      default=["office", "house"])
  parser.add_argument("--trajectories", nargs="+", type=int, choices=(0, 1, 2),
                      default=[0, 1, 2])
  parser.add_argument("--calibration-seeds", nargs="+", type=int, default=[1],
                      help="layout seeds of the calibration sequences (A)")
  parser.add_argument("--held-out-seeds", nargs="+", type=int, default=[2, 3],
                      help="layout seeds of the held-out sequences (B, disjoint from A)")
  parser.add_argument("--steps", type=int, default=40)
  parser.add_argument("--learning-rate", type=float, default=0.1)
  parser.add_argument("--out", default="outputs/tune", help="output folder")
  _add_data_args(parser, rule_help="robust rule with β: R or D+R")


def add_tune_compare_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `tune-compare`: which surrogate's optimum tracks the mIoU optimum of a β sweep."""
  parser = subparsers.add_parser(
      "tune-compare", help="compare the tuning objectives against a β sweep's mIoU optimum",
      description="Tunes β by gradient with each objective (soft IoU, cross-entropy) on "
                  "calibration layouts, sweeps a β grid on calibration and held-out layouts, "
                  "and reports where each objective's optimum lands relative to the mIoU "
                  "optimum (writes compare.md/.json/.png under --out).")
  _add_protocol_args(parser)
  parser.add_argument("--init-beta", type=float, default=0.3)
  parser.add_argument("--num-betas", type=int, default=21, help="grid 0..1")
  parser.set_defaults(func=tune_compare_command)
  return parser


def add_tune_protocol_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `tune-protocol`: scalar β*, per-class β* and β = 0.3 on held-out layouts."""
  parser = subparsers.add_parser(
      "tune-protocol", help="tune scalar and per-class β on calibration layouts, judge them "
                            "against β = 0.3 on held-out layouts with bootstrap intervals",
      description="Tunes β (one scalar, and one per class) by gradient on the calibration "
                  "layout seeds, fuses the held-out layout seeds with β = 0.3, β* and the "
                  "per-class β*, and reports held-out mIoU with bootstrap intervals over "
                  "sequences (writes protocol.md/.json and per_class_beta.png under --out).")
  _add_protocol_args(parser)
  parser.add_argument("--objective", choices=OBJECTIVES, default=DEFAULT_OBJECTIVE)
  parser.add_argument("--baseline-beta", type=float, default=0.3)
  parser.add_argument("--resamples", type=int, default=stats.DEFAULT_RESAMPLES,
                      help="bootstrap resamples")
  parser.set_defaults(func=tune_protocol_command)
  return parser


def sweep_command(args) -> int:
  """Runs `jaxfusion sweep`; returns the exit status."""
  data = load_calibration_sequence(args.sequence, seed=args.seed,
                                   **_data_kwargs(args, _front_end(args)))
  betas = np.linspace(args.beta_min, args.beta_max, args.num_betas)
  start = time.perf_counter()
  out = sweep_beta(data["frames"], data["camera"], data["gt"]["coords"], data["gt"]["labels"],
                   betas=betas, rule=args.rule, capacity=data["capacity"],
                   voxel_size=args.voxel_size, mesh=_mesh(args), aggregate=args.aggregate)
  seconds = time.perf_counter() - start
  best = int(np.nanargmax(out["miou"]))
  print(f"{data['name']} ({data['source']}), rule {args.rule}, aggregate={args.aggregate}: "
        f"{len(betas)} β in one call, {seconds:.1f} s including compilation")
  print("   beta    mIoU     acc   xent  1-softIoU")
  for b, m, a, l, q in zip(out["beta"], out["miou"], out["accuracy"], out["loss"],
                           out["soft_iou_loss"]):
    print(f"  {b:5.3f}  {100 * m:6.2f}  {100 * a:6.2f}  {l:6.3f}  {q:6.4f}")
  print(f"best β = {out['beta'][best]:.3f}: mIoU {100 * out['miou'][best]:.2f}; surrogate "
        f"minima: cross-entropy at β = {out['beta'][int(np.nanargmin(out['loss']))]:.3f}, soft "
        f"IoU at β = {out['beta'][int(np.nanargmin(out['soft_iou_loss']))]:.3f}")
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
    plt.close(fig)
    print(f"wrote {args.plot}")
  _write_json(args.json, {
      "sequence": data["name"], "source": data["source"], "rule": args.rule,
      "aggregate": args.aggregate, "seconds": seconds, "beta": out["beta"].tolist(),
      "miou": out["miou"].tolist(), "accuracy": out["accuracy"].tolist(),
      "loss": out["loss"].tolist(), "soft_iou_loss": out["soft_iou_loss"].tolist()})
  return 0


def _fmt(value) -> str:
  v = np.asarray(value)
  return f"{float(v):.4g}" if v.ndim == 0 else "[" + ", ".join(f"{x:.3g}" for x in v) + "]"


def tune_beta_command(args) -> int:
  """Runs `jaxfusion tune-beta`; returns the exit status."""
  train = tuple(t.strip() for t in args.tune.split(",") if t.strip())
  kwargs = _data_kwargs(args, _front_end(args))
  cal = load_calibration_sequence(args.calibration, seed=args.seed, **kwargs)
  start = time.perf_counter()
  result = tune_hparams(cal["frames"], cal["camera"], cal["gt"]["coords"],
                        cal["gt"]["labels"], rule=args.rule, init={"beta": args.init_beta},
                        train=train, steps=args.steps, learning_rate=args.learning_rate,
                        capacity=cal["capacity"], voxel_size=args.voxel_size,
                        aggregate=args.aggregate, objective=args.objective,
                        per_class=args.per_class)
  seconds = time.perf_counter() - start
  print(f"calibration {cal['name']} ({cal['source']}), rule {args.rule}, "
        f"aggregate={args.aggregate}, objective {args.objective}: {args.steps} Adam steps in "
        f"{seconds:.1f} s")
  print(f"  loss {result.losses[0]:.4f} -> {result.losses[-1]:.4f}; fitted "
        + ", ".join(f"{k} = {_fmt(result.hparams[k])}" for k in train))
  baseline = rules_lib.by_name(args.rule, beta=args.baseline_beta, aggregate=args.aggregate)
  held_out = []
  for spec in [s.strip() for s in args.held_out.split(",") if s.strip()]:
    data = load_calibration_sequence(spec, seed=args.seed, **kwargs)
    base_out, tuned_out = evaluate_rules(
        [baseline, result.rule], data["frames"], data["camera"], data["gt"]["coords"],
        data["gt"]["labels"], capacity=data["capacity"], voxel_size=args.voxel_size,
        mesh=_mesh(args))
    held_out.append({"sequence": data["name"],
                     "miou_baseline": float(base_out["miou"]),
                     "miou_tuned": float(tuned_out["miou"]),
                     "accuracy_baseline": float(base_out["accuracy"]),
                     "accuracy_tuned": float(tuned_out["accuracy"])})
    print(f"  {data['name']:>18}: mIoU {100 * held_out[-1]['miou_baseline']:6.2f} at β = "
          f"{args.baseline_beta:.3f}, {100 * held_out[-1]['miou_tuned']:6.2f} at β*")
  if held_out:
    mean_base = float(np.mean([h["miou_baseline"] for h in held_out]))
    mean_tuned = float(np.mean([h["miou_tuned"] for h in held_out]))
    print(f"  {'mean':>18}: mIoU {100 * mean_base:6.2f} at β = {args.baseline_beta:.3f}, "
          f"{100 * mean_tuned:6.2f} at β*")
  _write_json(args.json, {
      "calibration": cal["name"], "source": cal["source"], "rule": args.rule,
      "aggregate": args.aggregate, "objective": args.objective, "per_class": args.per_class,
      "hparams": result.hparams, "losses": result.losses.tolist(),
      "beta_path": result.path.get("beta", np.array([])).tolist(),
      "seconds": seconds, "held_out": held_out})
  return 0


def _protocol_batches(args) -> tuple:
  overlap = set(args.calibration_seeds) & set(args.held_out_seeds)
  if overlap:
    raise ValueError(f"calibration and held-out layout seeds must be disjoint; both have "
                     f"{sorted(overlap)}")
  kwargs = _data_kwargs(args, _front_end(args))
  units = lambda seeds: [(e, t, s) for s in seeds for e in args.envs for t in args.trajectories]
  return (load_sequence_batch(units(args.calibration_seeds), **kwargs),
          load_sequence_batch(units(args.held_out_seeds), **kwargs))


def tune_compare_command(args) -> int:
  """Runs `jaxfusion tune-compare`; returns the exit status."""
  import os  # pylint: disable=import-outside-toplevel
  cal, held = _protocol_batches(args)
  result = compare_objectives(cal, held, rule=args.rule,
                              betas=np.round(np.linspace(0.0, 1.0, args.num_betas), 4),
                              steps=args.steps, learning_rate=args.learning_rate,
                              init_beta=args.init_beta, aggregate=args.aggregate,
                              voxel_size=args.voxel_size, mesh=_mesh(args))
  table = format_comparison(result)
  print(table)
  os.makedirs(args.out, exist_ok=True)
  _write_text(os.path.join(args.out, "compare.md"), table + "\n")
  plot_comparison(os.path.join(args.out, "compare.png"), result)
  _write_json(args.json or os.path.join(args.out, "compare.json"), result)
  print(f"wrote {args.out}/compare.md, compare.png")
  return 0


def tune_protocol_command(args) -> int:
  """Runs `jaxfusion tune-protocol`; returns the exit status."""
  import os  # pylint: disable=import-outside-toplevel
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  cal, held = _protocol_batches(args)
  result = tune_protocol(cal, held, rule=args.rule, objective=args.objective,
                         baseline_beta=args.baseline_beta, steps=args.steps,
                         learning_rate=args.learning_rate, aggregate=args.aggregate,
                         voxel_size=args.voxel_size, num_resamples=args.resamples,
                         mesh=_mesh(args))
  names = list(datasets.CLASS_NAMES)[:cal["num_classes"]]
  table = format_protocol(result, names)
  print(table)
  os.makedirs(args.out, exist_ok=True)
  _write_text(os.path.join(args.out, "protocol.md"), table + "\n")
  plot_per_class_beta(os.path.join(args.out, "per_class_beta.png"), result, names)
  _write_json(args.json or os.path.join(args.out, "protocol.json"),
              dict(result, class_names=names, settings={
                  "frames": args.frames, "height": args.height, "width": args.width,
                  "num_samples": args.num_samples, "shift": args.shift,
                  "front_end": args.front_end, "voxel_size": args.voxel_size}))
  print(f"wrote {args.out}/protocol.md, per_class_beta.png")
  return 0
