"""Fitting the learned rule (`rules.learned`, docs/equations.md §3.9) by gradient through fusion.

The loss is `tune.sequence_loss` of the fused maps against GT voxel labels (the mean
cross-entropy `−log P(gt)` over the GT voxels the maps hold, by default), differentiated through
the whole `lax.scan` of frames with respect to the rule's parameters, and minimised with Adam.
The parameters are optimised unconstrained (`constrain`): θ, b and γ as they are, `δ =
sigmoid(m)` and `β = sigmoid(u)` (per class), so every step gives a valid rule; ε and α₀ stay
fixed. Early stopping watches the same loss (or, with `select="miou"`, the map mIoU) on a
validation batch (other layouts than the training ones, never those the rule is judged on) every
`eval_every` steps and keeps the best parameters seen.

`fit` works on batches of sequences as `lab.tuning.load_sequence_batch` builds them: a dict
with `frames` `(B, T, …)`, `mask` `(B, T)`, `camera`, `coords` `(B, N, 3)`, `labels` `(B, N)`
and `capacity`.

Shape legend: B sequences, T frames, K classes, N GT voxels.
"""

import dataclasses
import functools
import importlib
import json
import time
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxfusion import batch
from jaxfusion import rules as rules_lib
from jaxfusion import tune

# The module (`jaxfusion.rules.learned` the attribute is the `learned` factory).
learned_lib = importlib.import_module("jaxfusion.rules.learned")

TRAINED = ("theta", "bias", "context_theta", "mix", "gate", "beta")
# Rule families `fit` can fit: the learned rule (§3.9), GLFS (§3.10) and the family (§3.11).
FAMILIES = ("learned", "glfs", "family")
# The family's terms `fit` can fit beside its table (docs/equations.md §3.11).
FAMILY_TERMS = ("moments", "context", "beta", "mix", "spatial")
# Where the family's R and D terms start: nearly absent (β = δ = 10⁻³), so that the fit begins
# at the starting table's maps.
FAMILY_START = {"beta": 1e-3, "mix": 1e-3}
# What early stopping may keep: the lowest validation loss or the highest validation mIoU.
SELECTIONS = ("loss", "miou")
# Where the parameters start (constrained values): D+R at the paper's β, with the weights and the
# gate at sigmoid(3) ≈ 0.95 — inside the sigmoid's slope, so their gradients are not zero (at the
# exact special case, sigmoid(30), they would be).
START = {"theta": np.zeros(learned_lib.NUM_FEATURES, np.float32), "bias": 3.0, "mix": 0.9,
         "gate": np.array([3.0, 0.0, 0.0], np.float32), "beta": 0.3}


def constrain(params: dict) -> dict:
  """Unconstrained parameters → the learned rule's: `mix = sigmoid(mix)`, `beta =
  sigmoid(beta)`, the rest unchanged."""
  out = dict(params)
  for name in ("mix", "beta"):
    if name in out:
      out[name] = jax.nn.sigmoid(out[name])
  return out


def unconstrain(values: dict) -> dict:
  """Inverse of `constrain` (δ and β clamped into [1e-4, 1 − 1e-4] first, as `tune` clamps β)."""
  logit = lambda v: tune.unconstrain({"beta": v})["beta"]
  return {name: logit(value) if name in ("mix", "beta") else jnp.asarray(value, jnp.float32)
          for name, value in values.items()}


def start_params(num_classes: int, *, start: Optional[dict] = None,
                 per_class_beta: bool = True, context=(), per_class_weights: bool = False,
                 gate_size: int = 3) -> dict:
  """Unconstrained starting parameters (`START`, overridden by `start`), β broadcast to K.

  With `context`, the context weights start at 0; with `per_class_weights`, θ, b and the context
  weights are one row per predicted class (GLFS's class interaction); `gate_size=5` adds the
  gate's divergence and frame-count terms (at 0).
  """
  if gate_size not in (3, 5):
    raise ValueError(f"gate_size must be 3 or 5; got {gate_size}")
  values = dict(START)
  values["gate"] = np.concatenate([START["gate"], np.zeros(gate_size - 3, np.float32)])
  if context:
    values["context_theta"] = np.zeros(len(context), np.float32)
  values.update(start or {})
  unknown = set(values) - set(TRAINED)
  if unknown:
    raise ValueError(f"unknown learned-rule parameters to train {sorted(unknown)}; trained are "
                     f"{', '.join(TRAINED)}")
  if per_class_beta:
    values["beta"] = np.broadcast_to(np.asarray(values["beta"], np.float32), (num_classes,))
  if per_class_weights:
    for name, ndim in (("theta", 2), ("bias", 1), ("context_theta", 2)):
      if name in values and np.ndim(values[name]) < ndim:
        value = np.asarray(values[name], np.float32)
        values[name] = np.broadcast_to(value, (num_classes,) + value.shape).copy()
  return unconstrain(values)


def family_start(num_classes: int, *, table, terms=("moments",), context=(),
                 per_class_weights: bool = False) -> dict:
  """Unconstrained starting parameters of the family (docs/equations.md §3.11): `table =
  exp(u)` at the given table (e.g. the shipped GLFS table, so that the fit begins where GLFS
  ends), the moment and context weights at 0 (`(K, ·)` with `per_class_weights`), β (per class)
  and δ at `FAMILY_START`, the spatial kernel (docs/equations.md §4.1) at 0.

  Raises:
    ValueError: an unknown term, a context term without names (or names without it), or a
      table that is not `(K, depth bins, angle bins)` of finite non-negative weights.
  """
  unknown = set(terms) - set(FAMILY_TERMS)
  if unknown:
    raise ValueError(f"unknown family terms {sorted(unknown)}; the terms fitted beside the "
                     f"table are {', '.join(FAMILY_TERMS)}")
  if ("context" in terms) != bool(context):
    raise ValueError("the family's context term needs context features, and context features "
                     "need the context term")
  table = np.asarray(table, np.float32)
  want = (num_classes, len(rules_lib.glfs_lib.DEPTH_EDGES) + 1,
          len(rules_lib.glfs_lib.ANGLE_EDGES) + 1)
  if table.shape != want or not np.all(np.isfinite(table)) or np.any(table < 0):
    raise ValueError(f"the family's starting table must be {want} finite non-negative weights; "
                     f"got shape {table.shape}")
  shape = lambda width: (num_classes, width) if per_class_weights else (width,)
  params = {"table": jnp.log(jnp.maximum(jnp.asarray(table), 1e-6))}
  if "moments" in terms:
    params["moment_weights"] = jnp.zeros(shape(learned_lib.NUM_FEATURES), jnp.float32)
  if "context" in terms:
    params["context_weights"] = jnp.zeros(shape(len(context)), jnp.float32)
  if "beta" in terms:
    params["beta"] = unconstrain({"beta": np.full(num_classes, FAMILY_START["beta"],
                                                  np.float32)})["beta"]
  if "mix" in terms:
    params["mix"] = unconstrain({"mix": FAMILY_START["mix"]})["mix"]
  if "spatial" in terms:
    params["spatial"] = jnp.zeros((num_classes, 3), jnp.float32)
  return params


def constrain_family(params: dict) -> dict:
  """Unconstrained family parameters → the rule's: `table = exp(u)`, β and δ through a
  sigmoid, the weights as they are."""
  out = constrain(params)
  if "table" in out:
    out["table"] = jnp.exp(out["table"])
  return out


def glfs_start(num_classes: int) -> dict:
  """Unconstrained GLFS parameters at Bayes: `table = exp(u)`, u = 0."""
  return {"table": jnp.zeros((num_classes, len(rules_lib.glfs_lib.DEPTH_EDGES) + 1,
                               len(rules_lib.glfs_lib.ANGLE_EDGES) + 1), jnp.float32)}


@dataclasses.dataclass
class FitResult:
  """Output of `fit`.

  Attributes:
    params: the learned rule's parameters at the kept validation point (floats and lists).
    rule: `rules.learned(params, aggregate=...)`.
    train_losses: the training loss before each step.
    validation: `(step, loss)` pairs, one per evaluation (step 0 is the start).
    best_step: the step whose parameters were kept.
    steps_run: steps taken before stopping.
    stopped_early: True if the patience ran out before `steps`.
    seconds: wall time of the fit.
    validation_miou: `(step, pooled validation mIoU)` pairs when the fit selects by mIoU
      (`select="miou"`), else empty.
  """
  params: dict
  rule: rules_lib.FusionRule
  train_losses: list
  validation: list
  best_step: int
  steps_run: int
  stopped_early: bool
  seconds: float
  validation_miou: list = dataclasses.field(default_factory=list)


def _loss_fn(data: dict, *, make: Callable, voxel_size: float, objective: str) -> Callable:
  frames = jax.tree.map(jnp.asarray, data["frames"])
  mask = jnp.asarray(data["mask"])
  coords = jnp.asarray(data["coords"], jnp.int32)
  labels = jnp.asarray(data["labels"], jnp.int32)
  camera, _ = batch.camera_batch(data["camera"], None)
  capacity = int(data["capacity"])

  def loss(params):
    rule = make(params)
    return tune.sequence_loss(rule, frames, camera, coords, labels, capacity=capacity,
                              voxel_size=voxel_size, mask=mask, objective=objective)
  return loss


def _miou_fn(data: dict, *, make: Callable, voxel_size: float) -> Callable:
  """`params → pooled map mIoU` of the batch's hard labels (one compiled `tune.sweep` call)."""
  def miou(params):
    rule = make(params)
    out = tune.sweep(data["frames"], data["camera"], data["coords"], data["labels"],
                     rules_lib.stack([rule]), capacity=int(data["capacity"]),
                     voxel_size=voxel_size, mask=data["mask"])
    return float(np.asarray(out["miou_pooled"])[0])
  return miou


def fit(train: dict, validation: dict, *, steps: int = 200, learning_rate: float = 0.05,
        eval_every: int = 10, patience: int = 5, start: Optional[dict] = None,
        per_class_beta: bool = True, eps: float = 1e-12,
        alpha0: float = rules_lib.DEFAULT_ALPHA0, aggregate: str = "sum",
        voxel_size: float = 0.1, objective: str = "cross_entropy", select: str = "loss",
        progress: Optional[Callable[[int, float, Optional[float]], None]] = None,
        family: str = "learned", context=(), per_class_weights: bool = False,
        gate_size: int = 3, terms=("moments",), start_table=None) -> FitResult:
  """Fits the learned rule (or GLFS) on `train` with Adam, stopping early on `validation`.

  Args:
    train: the training batch (see the module docstring).
    validation: a batch of other layouts, for early stopping.
    steps: at most this many Adam steps.
    learning_rate: Adam step size in the unconstrained parameters.
    eval_every: evaluate the validation loss every this many steps.
    patience: stop after this many evaluations without a better value of the measure `select`
      names.
    start: starting values (constrained) of some of `TRAINED` (default `START`, D+R-like).
    per_class_beta: fit one β per class (else one scalar).
    eps: ε of α, fixed.
    alpha0: α₀, fixed.
    aggregate: "sum" or "mean".
    voxel_size: voxel edge in metres (the GT's).
    objective: `tune.OBJECTIVES`.
    select: what early stopping keeps: "loss", the parameters with the lowest validation loss;
      "miou", those with the highest pooled validation map mIoU (hard labels, `tune.sweep`), for
      front ends where the loss and mIoU part ways. The patience counts evaluations without a
      better value of the selected measure; both are recorded.
    progress: called as `progress(step, train_loss, validation_loss or None)` after each step.
    family: "learned" (§3.9), "glfs" (§3.10: only its table is fitted, `table = exp(u)`;
      `start`, `per_class_beta`, `context`, `per_class_weights` and `gate_size` are the learned
      rule's and are ignored) or "family" (§3.11: its table and `terms`, from
      `family_start(start_table, ...)`).
    context: context features the learned rule's weight (or the family's context term) reads
      (`jaxfusion.context.FEATURES`); the batches need `frames.rgb` for the image ones.
    per_class_weights: the learned weight's θ, b and context weights per predicted class (the
      family's moment and context weights).
    gate_size: 3 (agreement and spread) or 5 (also the divergence and the frame count).
    terms: the family's terms fitted beside its table (`FAMILY_TERMS`).
    start_table: the family's starting table `(K, depth bins, angle bins)` (e.g. the shipped
      GLFS table); None: all ones (Bayes).

  Returns:
    FitResult.

  Raises:
    ValueError: steps, eval_every or patience < 1, batches with different K, an unknown
      objective or start parameter.
  """
  for name, value in (("steps", steps), ("eval_every", eval_every), ("patience", patience)):
    if int(value) < 1:
      raise ValueError(f"{name} must be >= 1; got {value}")
  if select not in SELECTIONS:
    raise ValueError(f"select must be one of {SELECTIONS}; got {select!r}")
  tune.check_objective(objective)
  if family not in FAMILIES:
    raise ValueError(f"family must be one of {FAMILIES}; got {family!r}")
  num_classes = int(np.shape(train["frames"].probs)[-1])
  if int(np.shape(validation["frames"].probs)[-1]) != num_classes:
    raise ValueError("the training and validation batches must have the same classes (K)")
  fixed = {"eps": jnp.float32(eps), "alpha0": jnp.float32(alpha0)}
  context = tuple(context)
  if family == "family":
    terms = tuple(terms)
    fixed = {"depth_edges": jnp.asarray(rules_lib.glfs_lib.DEPTH_EDGES, jnp.float32),
             "angle_edges": jnp.asarray(rules_lib.glfs_lib.ANGLE_EDGES, jnp.float32)}
    if "moments" in terms or "mix" in terms:
      fixed["eps"] = jnp.float32(eps)
    if "mix" in terms:
      fixed["alpha0"] = jnp.float32(alpha0)
    family_context = context if "context" in terms else ()
    make = lambda p: rules_lib.family({**fixed, **constrain_family(p)}, context=family_context,
                                      aggregate=aggregate)
    values_of = lambda p: {**{k: _plain(v) for k, v in fixed.items()},
                           **{k: _plain(v) for k, v in constrain_family(p).items()}}
  elif family == "glfs":
    fixed = {}
    make = lambda p: rules_lib.glfs(jnp.exp(p["table"]), aggregate=aggregate)
    values_of = lambda p: {"table": _plain(jnp.exp(p["table"])),
                           "depth_edges": list(rules_lib.glfs_lib.DEPTH_EDGES),
                           "angle_edges": list(rules_lib.glfs_lib.ANGLE_EDGES)}
  else:
    make = lambda p: rules_lib.learned({**fixed, **constrain(p)}, context=context,
                                       aggregate=aggregate)
    values_of = lambda p: {**{k: float(v) for k, v in fixed.items()},
                           **{k: _plain(v) for k, v in constrain(p).items()}}
  settings = dict(make=make, voxel_size=voxel_size, objective=objective)
  train_loss = _loss_fn(train, **settings)
  val_loss = jax.jit(_loss_fn(validation, **settings))
  optimizer = optax.adam(learning_rate)

  @jax.jit
  def step_fn(params, opt_state):
    value, grads = jax.value_and_grad(train_loss)(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, value

  val_miou = _miou_fn(validation, make=make, voxel_size=voxel_size)

  def evaluate(params, step):
    """The validation loss, and the measure to maximise (−loss or mIoU)."""
    loss = float(val_loss(params))
    history.append((step, loss))
    if select == "loss":
      return loss, -loss
    value = val_miou(params)
    miou_history.append((step, value))
    return loss, value

  started = time.perf_counter()
  if family == "family":
    table = (np.ones((num_classes, len(rules_lib.glfs_lib.DEPTH_EDGES) + 1,
                      len(rules_lib.glfs_lib.ANGLE_EDGES) + 1), np.float32)
             if start_table is None else start_table)
    params = family_start(num_classes, table=table, terms=terms, context=family_context,
                          per_class_weights=per_class_weights)
  elif family == "glfs":
    params = glfs_start(num_classes)
  else:
    params = start_params(num_classes, start=start, per_class_beta=per_class_beta,
                          context=context, per_class_weights=per_class_weights,
                          gate_size=gate_size)
  opt_state = optimizer.init(params)
  history, miou_history, losses, waited, step = [], [], [], 0, 0
  best = (evaluate(params, 0)[1], 0, params)
  while step < steps and waited < patience:
    params, opt_state, value = step_fn(params, opt_state)
    step += 1
    losses.append(float(value))
    current = None
    if step % eval_every == 0 or step == steps:
      current, measure = evaluate(params, step)
      if measure > best[0]:
        best, waited = (measure, step, params), 0
      else:
        waited += 1
    if progress is not None:
      progress(step, losses[-1], current)
  values = values_of(best[2])
  if family == "learned" and context:
    values["context"] = list(context)
  if family == "family" and family_context:
    values["context"] = list(family_context)
  return FitResult(params=values, rule=rule_of(family, values, aggregate=aggregate),
                   train_losses=losses, validation=history, best_step=best[1], steps_run=step,
                   stopped_early=step < steps, seconds=time.perf_counter() - started,
                   validation_miou=miou_history)


def _plain(x):
  x = np.asarray(x, np.float64)
  return float(x) if x.ndim == 0 else x.tolist()


@functools.partial(jax.jit, static_argnames=("num_classes",))
def weight_grid(hparams: dict, alpha_pred: jax.Array, max_prob: jax.Array, *,
                num_classes: int) -> jax.Array:
  """The learned per-pixel weight `w` on a grid of (α of the predicted class, max probability),
  for figures: each grid pixel is a K-class mean with that max probability, the rest spread
  evenly, and the predicted class's variance `exp(−α) − ε` (the others 0).

  Args:
    hparams: the rule's parameters (`rule.hparams`).
    alpha_pred: `(A,)` α values.
    max_prob: `(P,)` max probabilities in [1/K, 1].

  Returns:
    `(A, P)` float32 weights in [0, 1].
  """
  def one(alpha, top):
    rest = (1.0 - top) / (num_classes - 1)
    probs = jnp.full(num_classes, rest).at[0].set(top)
    var = jnp.zeros(num_classes).at[0].set(jnp.maximum(jnp.exp(-alpha) - hparams["eps"], 0.0))
    return learned_lib.pixel_weight(learned_lib.features(probs, var, hparams["eps"]), hparams,
                                    pred=jnp.argmax(probs))
  return jax.vmap(lambda a: jax.vmap(lambda p: one(a, p))(max_prob))(alpha_pred)


def map_calibration(rule: rules_lib.FusionRule, data: dict, *, voxel_size: float = 0.1) -> dict:
  """The ECE of the maps `rule` fuses from a batch (`fit`'s batches), against its GT voxels.

  Each sequence is fused alone (`fuse_sequence`, masked frames left out), its posteriors at the
  GT voxels it holds are binned (`metrics.calibration_bins`) and the counts summed over the
  batch.

  Returns:
    dict with `ece` (float) and `bins` (`(B, 3)` list).
  """
  from jaxfusion import fusion  # pylint: disable=import-outside-toplevel
  from jaxfusion import metrics  # pylint: disable=import-outside-toplevel
  from jaxfusion import readout  # pylint: disable=import-outside-toplevel
  from jaxfusion import state as state_lib  # pylint: disable=import-outside-toplevel
  frames, mask = data["frames"], np.asarray(data["mask"])
  camera, _ = batch.camera_batch(data["camera"], None)
  total = np.zeros((metrics.CALIBRATION_BINS, 3))
  num_classes = int(np.shape(frames.probs)[-1])
  for b in range(mask.shape[0]):
    seq = jax.tree.map(lambda x, b=b: None if x is None else np.asarray(x[b]), frames)
    seq = seq._replace(depth=np.where(mask[b][:, None, None], seq.depth, 0.0))
    state = state_lib.init_map(capacity=int(data["capacity"]), num_classes=num_classes,
                               voxel_size=voxel_size, rule=rule)
    voxels = readout.read_map(fusion.fuse_sequence(state, seq, camera, rule))
    labels = np.asarray(data["labels"][b])
    keep = labels >= 0
    map_index, gt_index = metrics.match_voxels(voxels["coords"],
                                               np.asarray(data["coords"][b])[keep])
    total += metrics.calibration_bins(np.asarray(voxels["posterior"])[map_index],
                                      labels[keep][gt_index])
  return {"ece": float(metrics.ece_from_bins(total)), "bins": total.tolist()}


def rule_of(family: str, params: dict, *, aggregate: str = "sum") -> rules_lib.FusionRule:
  """The FusionRule of a fitted family's parameters ("learned", "glfs" or "family", as
  `params.json` stores them)."""
  if family == "glfs":
    return rules_lib.glfs(**params, aggregate=aggregate)
  if family == "family":
    return rules_lib.family(params, aggregate=aggregate)
  if family == "learned":
    return rules_lib.learned(params, aggregate=aggregate)
  raise ValueError(f"unknown rule family {family!r}; the fitted families are {FAMILIES}")


def load_rule(path: str, *, aggregate: str = "sum") -> tuple:
  """`(family, params)` of a `params.json` of `jaxfusion learn-rule` (either family).

  Raises:
    ValueError: not such a file, or parameters the family refuses.
  """
  try:
    with open(path, encoding="utf-8") as f:
      payload = json.load(f)
  except json.JSONDecodeError as e:
    raise ValueError(f"{path} is not a learned-rule parameter file (not JSON: {e})") from e
  params = payload.get("params") if isinstance(payload, dict) else None
  family = payload.get("rule", "learned") if isinstance(payload, dict) else None
  if not isinstance(params, dict) or family not in FAMILIES:
    raise ValueError(f"{path} is not a learned-rule parameter file (no 'params' object or an "
                     f"unknown 'rule' {family!r})")
  try:
    rule_of(family, params, aggregate=aggregate)
  except (TypeError, ValueError) as e:
    raise ValueError(f"{path}: {e}") from e
  return family, params


def load_params(path: str) -> dict:
  """The parameters in a `params.json` written by `jaxfusion learn-rule` (for `rules.learned`).

  Raises:
    ValueError: not such a file, or parameters `rules.learned` refuses (names, shapes, ranges).
  """
  family, params = load_rule(path)      # validates names, shapes and ranges
  if family != "learned":
    raise ValueError(f"{path} holds a {family!r} rule, not the learned rule's parameters")
  return params
