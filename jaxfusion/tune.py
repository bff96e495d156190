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
- `simulate_predictions`: kept here as an alias; the simulated network (independent per-pixel
  errors) lives in `jaxfusion.simulation`, beside the one with view-dependent errors.
- `evaluate_rules`: scores a list of rules (any mix of kinds) on one batch of sequences.

The commands and protocols built on these (`jaxfusion sweep`, `tune-beta`, `tune-compare`,
`tune-protocol`) live in the application, `jaxfusion.lab.tuning`.

Shape legend: R rules, B sequences, T frames, H×W pixels, K classes, C slots, N GT voxels,
M MC samples.
"""

import functools
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
from jaxfusion import simulation
from jaxfusion import state as state_lib
from jaxfusion.rules import base as rules_base

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
  valid = found & state_lib.observed_at(state, slots) & (labels >= 0) & (
      labels < state.num_classes)
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


def soft_counts(state: state_lib.MapState, gt_coords: jax.Array, gt_labels: jax.Array) -> dict:
  """`soft_confusion` of the map's posteriors at its GT voxels (what `soft_iou_loss` reads)."""
  posterior, valid = match_ground_truth(state, gt_coords, gt_labels)
  return soft_confusion(posterior, jnp.asarray(gt_labels, jnp.int32), valid)


def soft_iou_loss(state: state_lib.MapState, gt_coords: jax.Array, gt_labels: jax.Array
                  ) -> jax.Array:
  """`1 − soft mIoU` of the fused voxel posteriors over the GT voxels the map holds
  (`[] float32`): a differentiable surrogate of the map's voxel mIoU (1 when nothing scores)."""
  return 1.0 - soft_miou(soft_counts(state, gt_coords, gt_labels))


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
  soft = soft_counts(state, coords, labels)
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
  mask = batch.check_batch_frames(frames, mask, rules, batch_dims=batch_dims,
                                   num_classes=num_classes)
  coords = np.asarray(gt_coords, np.int32)
  labels = np.asarray(gt_labels, np.int32)
  lead = mask.shape[:batch_dims - 1]
  if coords.shape[:-2] != lead or coords.shape[-1] != 3 or labels.shape != coords.shape[:-1]:
    raise ValueError(f"GT must be coords {lead + ('N', 3)} and labels {lead + ('N',)}; got "
                     f"{coords.shape} and {labels.shape}")
  camera, _ = batch.camera_batch(camera, None)
  size = batch.padded_size(num_rules, mesh)
  rules = batch.pad_leading(rules, size)
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


# --- a sweep of a long sequence, chunk by chunk -------------------------------------------------
@functools.partial(jax.jit, static_argnames=("capacity", "num_classes", "voxel_size",
                                             "max_probes"))
def _sweep_first(frames, mask, camera, rules, *, capacity, num_classes, voxel_size, max_probes):
  return jax.vmap(lambda r: batch.fuse_masked(
      frames, mask, camera, r, capacity=capacity, num_classes=num_classes,
      voxel_size=voxel_size, max_probes=max_probes))(rules)


@functools.partial(jax.jit, donate_argnums=0)
def _sweep_more(states, frames, mask, camera, rules):
  frames = batch.mask_frames(frames, mask)
  return jax.vmap(lambda s, r: fusion.fuse_sequence_unchecked(s, frames, camera, r))(states,
                                                                                       rules)


@jax.jit
def _sweep_scores(states, coords, labels):
  def one(state):
    out = _score(state, coords, labels)
    out["occupied"] = state.num_occupied
    out["dropped"] = state.num_dropped
    return out
  return jax.vmap(one)(states)


def padded_chunk(frames: fusion.Frame, size: int) -> tuple:
  """A chunk padded to `size` frames of zero depth (which touch nothing), and its mask."""
  t = int(np.shape(frames.depth)[0])
  if t > size:
    raise ValueError(f"a chunk of {t} frames is longer than the first one ({size})")
  pad = lambda x: None if x is None else np.concatenate(
      [np.asarray(x), np.zeros((size - t,) + np.shape(x)[1:], np.asarray(x).dtype)])
  frames = fusion.Frame(*(pad(getattr(frames, f)) for f in frames._fields))
  if t < size:   # padded poses must still be rigid transforms
    poses = np.asarray(frames.T_world_cam).copy()
    poses[t:] = np.eye(4, dtype=poses.dtype)
    frames = frames._replace(T_world_cam=poses)
  return frames, np.arange(size) < t


def sweep_chunks(chunks, camera: camera_lib.Camera, gt_coords, gt_labels,
                 rules: rules_lib.FusionRule, *, capacity: int, voxel_size: float = 0.1,
                 max_probes: int = state_lib.DEFAULT_MAX_PROBES) -> dict:
  """`sweep` of one sequence given chunk by chunk: a long sequence in bounded memory.

  The R maps are carried from chunk to chunk (each chunk one compiled call, padded to the
  first chunk's length with frames of zero depth, which touch nothing), then scored as
  `sweep` scores them: the results equal `sweep` of the whole sequence.

  Args:
    chunks: an iterable of Frames with a leading time axis (`depth (t, H, W)`, …), in order.
    camera: the intrinsics.
    gt_coords: `(N, 3)` GT voxel coordinates.
    gt_labels: `(N,)` GT labels (−1: not scored).
    rules: R stacked rules (`rules.stack`, `batch.rule_grid`).
    capacity: slots C of every map.
    voxel_size: voxel edge in metres.
    max_probes: hash probe bound.

  Returns:
    As `sweep` for one sequence: leading `(R,)`.
  """
  num_rules = batch.num_stacked_rules(rules)
  states, size, num_classes = None, None, None
  for frames in chunks:
    if states is None:
      size = int(np.shape(frames.depth)[0])
      num_classes = int(np.shape(frames.probs)[-1])
      batch.check_batch_frames(frames, None, rules, batch_dims=1, num_classes=num_classes)
      frames, mask = padded_chunk(frames, size)
      states = _sweep_first(jax.tree.map(np.asarray, frames), mask, camera, rules,
                            capacity=capacity, num_classes=num_classes,
                            voxel_size=float(voxel_size), max_probes=max_probes)
    else:
      frames, mask = padded_chunk(frames, size)
      states = _sweep_more(states, jax.tree.map(np.asarray, frames), mask, camera, rules)
  if states is None:
    raise ValueError("sweep_chunks got no frames")
  out = _sweep_scores(states, np.asarray(gt_coords, np.int32), np.asarray(gt_labels, np.int32))
  return _summarise(jax.tree.map(lambda x: np.asarray(x)[:num_rules], out))


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
    return soft_counts(state, coords, labels)

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


def start_hparams(rule: str, *, aggregate: str, init: Optional[dict], train: Sequence[str],
                  steps: int, num_classes: int, per_class: bool) -> tuple:
  """The checked start of a fit of a robust rule's hyperparameters.

  Returns:
    `(probe rule, train names, hparams)`: the rule with its defaults, the names to fit, and
    every hyperparameter's start value (`init` over the defaults; per class `(K,)` for the
    fitted ones with `per_class`).

  Raises:
    ValueError: a non-robust rule, a hyperparameter the rule does not use, `steps < 1`, or a
      per-class value whose length is not K.
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
  hparams = {k: np.asarray(v, np.float32) for k, v in probe.hparams.items()}
  for k, v in (init or {}).items():
    if k not in hparams:
      raise ValueError(f"unknown hyperparameter {k!r}; the rule has {sorted(hparams)}")
    hparams[k] = np.asarray(v, np.float32)
  if per_class:
    for k in train:
      hparams[k] = np.broadcast_to(hparams[k], (num_classes,)).copy()
  rules_base.check_class_shapes(hparams, num_classes, tuple(hparams))
  return probe, train, hparams


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
    per_class: fit one value per class (`(K,)`, docs/equations.md §3.7) for every hyperparameter in
      `train`, starting from `init` broadcast to K.

  Returns:
    TuneResult: fitted hyperparameters, the rule, the loss curve and the path.

  Raises:
    ValueError: a non-robust rule, a hyperparameter the rule does not use, `steps < 1`, an
      unknown objective, or a per-class `init` whose length is not K.
  """
  check_objective(objective)
  num_classes = np.shape(frames.probs)[-1]
  probe, train, hparams = start_hparams(rule, aggregate=aggregate, init=init, train=train,
                                        steps=steps, num_classes=num_classes,
                                        per_class=per_class)
  rules_lib.by_name(rule, aggregate=aggregate, **{k: v for k, v in hparams.items()
                                                  if k not in train})   # checks fixed values
  batch_dims = 2 if np.ndim(frames.depth) == 4 else 1
  mask = batch.check_batch_frames(frames, mask, probe, batch_dims=batch_dims,
                                   num_classes=num_classes)
  params = unconstrain({k: hparams[k] for k in train})
  fixed = {k: jnp.asarray(v, jnp.float32) for k, v in hparams.items() if k not in train}
  camera, _ = batch.camera_batch(camera, None)
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


# --- the simulated network's old home ---------------------------------------------------------
# `simulate_predictions` lives with the other simulated front end in `jaxfusion.simulation`; this
# name is kept so that existing callers of `tune.simulate_predictions` keep working.
simulate_predictions = simulation.simulate_predictions


# --- scoring lists of rules ----------------------------------------------------------------------
def evaluate_rules(rules: Sequence[rules_lib.FusionRule], frames: fusion.Frame,
                   camera: camera_lib.Camera, gt_coords, gt_labels, *, capacity: int,
                   voxel_size: float = 0.1, mask=None, mesh=None) -> list:
  """Scores each rule of a list (scalar and per-class rules may be mixed) on the same data.

  Rules whose hyperparameters have the same shapes are stacked and scored in one `sweep` call,
  so a scalar rule is scored with its scalar (bit-exact, docs/equations.md §3.4) path, never as a
  broadcast vector.

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
