"""β by gradient through sequences read chunk by chunk: `tune_hparams` in bounded memory.

`tune.tune_hparams` differentiates one `lax.scan` over all frames, which must then be in memory.
`tune_hparams_chunks` computes the same loss and the same gradient for sequences given as
chunks read on demand (`read_chunk(b, k)`), so that a long sequence read from disk is never held
whole. Each Adam step:

1. **Statistics.** Every sequence b is fused chunk by chunk and its statistic `s_b` is taken
   (its cross-entropy over GT voxels, or its soft confusion counts); the loss `L(s_1 … s_B)`
   (the mean cross-entropy, or `1 − soft mIoU` of the pooled counts, as `tune.sequence_loss`)
   and `∂L/∂s_b` follow.
2. **Backward, sequence by sequence.** The chunk maps are fused again keeping the state before
   every `checkpoint`-th chunk; then from the last chunk back to the first, the states of a
   segment are recomputed from its checkpoint and the cotangent of the state is carried back
   through each chunk by its VJP (`jax.vjp` of one chunk's `fuse_sequence`), adding each
   chunk's contribution to the gradient of the hyperparameters. With `checkpoint ≈ √n` for n
   chunks, at most about 2√n states are held.

The loss and gradient are those of `tune.sequence_loss` on the whole sequences (tests check
them against `jax.value_and_grad` of it); each chunk is padded to the first chunk's length with
frames of zero depth, which touch nothing.
"""

import functools
import math
from typing import Callable, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxfusion import batch
from jaxfusion import camera as camera_lib
from jaxfusion import fusion
from jaxfusion import rules as rules_lib
from jaxfusion import state as state_lib
from jaxfusion import tune

_STATIC = ("rule_name", "aggregate", "capacity", "num_classes", "voxel_size", "max_probes")


def _rule(params, fixed, rule_name, aggregate):
  return rules_lib.by_name(rule_name, aggregate=aggregate, **fixed, **tune.constrain(params))


def _first(params, fixed, frames, mask, camera, *, rule_name, aggregate, capacity, num_classes,
           voxel_size, max_probes):
  """The map after the first chunk (`init_map` inside: the prior may depend on the leaves)."""
  rule = _rule(params, fixed, rule_name, aggregate)
  return batch.fuse_masked(frames, mask, camera, rule, capacity=capacity,
                           num_classes=num_classes, voxel_size=voxel_size,
                           max_probes=max_probes)


def _next(state, params, fixed, frames, mask, camera, *, rule_name, aggregate):
  rule = _rule(params, fixed, rule_name, aggregate)
  return fusion.fuse_sequence_unchecked(state, batch.mask_frames(frames, mask), camera, rule)


_first_jit = jax.jit(_first, static_argnames=_STATIC)
_next_jit = jax.jit(_next, static_argnames=("rule_name", "aggregate"))


def _inexact(x) -> bool:
  return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def _floats(tree) -> list:
  """The floating-point leaves of a cotangent (its integer leaves are float0: never passed)."""
  return [x for x in jax.tree.leaves(tree) if _inexact(x)]


def _fill(like, floats):
  """A cotangent for `like` from its floating-point leaves (float0 zeros for integer ones)."""
  leaves, treedef = jax.tree.flatten(like)
  floats = iter(floats)
  return jax.tree.unflatten(treedef, [next(floats) if _inexact(x) else
                                      np.zeros(np.shape(x), jax.dtypes.float0) for x in leaves])


# A sequence's statistic per objective: its cross-entropy, or its soft confusion counts.
_STATISTICS = {"cross_entropy": tune.calibration_loss, "soft_iou": tune.soft_counts}


@functools.partial(jax.jit, static_argnames="objective")
def _statistic(state, coords, labels, *, objective):
  return _STATISTICS[objective](state, coords, labels)


def _combine(stats, objective: str):
  if objective == "cross_entropy":
    return jnp.mean(jnp.stack(stats))
  pooled = jax.tree.map(lambda *xs: sum(xs), *stats)
  return 1.0 - tune.soft_miou(pooled)


@functools.partial(jax.jit, static_argnames="objective")
def _vjp_statistic(state, coords, labels, g, *, objective):
  _, vjp = jax.vjp(lambda s: _STATISTICS[objective](s, coords, labels), state)
  return _floats(vjp(g)[0])


def _vjp_first(params, fixed, frames, mask, camera, g_state, **static):
  out, vjp = jax.vjp(lambda p: _first(p, fixed, frames, mask, camera, **static), params)
  return vjp(_fill(out, g_state))[0]


def _vjp_next(state, params, fixed, frames, mask, camera, g_state, **static):
  out, vjp = jax.vjp(lambda s, p: _next(s, p, fixed, frames, mask, camera, **static), state,
                     params)
  g_s, g_p = vjp(_fill(out, g_state))
  return _floats(g_s), g_p


_vjp_first = jax.jit(_vjp_first, static_argnames=_STATIC)
_vjp_next = jax.jit(_vjp_next, static_argnames=("rule_name", "aggregate"))


def _padded(frames: fusion.Frame, size: int) -> tuple:
  frames, mask = tune.padded_chunk(frames, size)
  return jax.tree.map(jnp.asarray, frames), jnp.asarray(mask)


class _Sequences:
  """Chunk access with padding to one length and the static arguments of the kernels."""

  def __init__(self, read_chunk, num_chunks, camera, static, size=None):
    self.read, self.num_chunks, self.camera, self.static = read_chunk, num_chunks, camera, static
    self.size = size

  def chunk(self, b: int, k: int):
    frames = self.read(b, k)
    if self.size is None:
      self.size = int(np.shape(frames.depth)[0])
    return _padded(frames, self.size)

  def forward(self, b, params, fixed, keep=()):
    """The final map of sequence b; with `keep`, also `{k: state before chunk k}`."""
    kept, state = {}, None
    for k in range(self.num_chunks[b]):
      frames, mask = self.chunk(b, k)
      if k in keep:
        kept[k] = state
      if state is None:
        state = _first_jit(params, fixed, frames, mask, self.camera, **self.static)
      else:
        state = _next_jit(state, params, fixed, frames, mask, self.camera,
                          rule_name=self.static["rule_name"], aggregate=self.static["aggregate"])
    return state, kept

  def backward(self, b, params, fixed, g_final, checkpoint: int):
    """The gradient in `params` of `<g_final, final map of b>`, by chunk VJPs in reverse."""
    n = self.num_chunks[b]
    marks = set(range(0, n, checkpoint))
    _, kept = self.forward(b, params, fixed, keep=marks)
    short = {"rule_name": self.static["rule_name"], "aggregate": self.static["aggregate"]}
    grad = jax.tree.map(jnp.zeros_like, params)
    g_state = g_final
    for start in sorted(marks, reverse=True):
      stop = min(start + checkpoint, n)
      states = {start: kept[start]}
      for k in range(start, stop - 1):      # recompute the states inside the segment
        frames, mask = self.chunk(b, k)
        states[k + 1] = (_first_jit(params, fixed, frames, mask, self.camera, **self.static)
                         if states[k] is None else
                         _next_jit(states[k], params, fixed, frames, mask, self.camera, **short))
      for k in range(stop - 1, start - 1, -1):
        frames, mask = self.chunk(b, k)
        if states[k] is None:
          g_params = _vjp_first(params, fixed, frames, mask, self.camera, g_state, **self.static)
          g_state = None
        else:
          g_state, g_params = _vjp_next(states[k], params, fixed, frames, mask, self.camera,
                                        g_state, **short)
        grad = jax.tree.map(jnp.add, grad, g_params)
        del states[k]
    return grad


def tune_hparams_chunks(read_chunk: Callable, num_chunks: Sequence[int],
                        camera: camera_lib.Camera, gt: Sequence[dict], *, num_classes: int,
                        rule: str = "D+R", init: Optional[dict] = None,
                        train: Sequence[str] = ("beta",), steps: int = 40,
                        learning_rate: float = 0.1, capacity: int, voxel_size: float = 0.1,
                        aggregate: str = "sum", max_probes: int = state_lib.DEFAULT_MAX_PROBES,
                        objective: str = tune.DEFAULT_OBJECTIVE, per_class: bool = False,
                        checkpoint: Optional[int] = None, chunk_size: Optional[int] = None,
                        progress=None) -> tune.TuneResult:
  """`tune.tune_hparams` on B sequences read chunk by chunk (module docstring).

  Args:
    read_chunk: `read_chunk(b, k) -> Frame` with a leading time axis: chunk k of sequence b
      (`depth (t, H, W)`, `T_world_cam`, `probs (t, H, W, K)`, `var`), at most `chunk_size`
      frames (padded to it with frames that touch nothing).
    num_chunks: chunks per sequence, `(B,)`.
    camera: the intrinsics shared by all frames.
    gt: per sequence, GT voxels `coords (N, 3)` and `labels (N,)`.
    num_classes: K.
    rule, init, train, steps, learning_rate, capacity, voxel_size, aggregate, max_probes,
      objective, per_class: as `tune.tune_hparams`.
    checkpoint: chunks per segment of the backward pass (default `⌈√n⌉` of the longest).
    chunk_size: the chunks' length (default: the first chunk's).
    progress: optional `progress(step, loss)` called after each step.

  Returns:
    A `tune.TuneResult` (`grads` of the unconstrained parameters per step).
  """
  tune.check_objective(objective)
  probe, train, hparams = tune.start_hparams(rule, aggregate=aggregate, init=init, train=train,
                                             steps=steps, num_classes=num_classes,
                                             per_class=per_class)
  if len(num_chunks) != len(gt) or not num_chunks or min(num_chunks) < 1:
    raise ValueError(f"give at least one chunk per sequence and one GT per sequence; got "
                     f"{list(num_chunks)} chunks and {len(gt)} GTs")
  params = tune.unconstrain({k: hparams[k] for k in train})
  fixed = {k: jnp.asarray(v, jnp.float32) for k, v in hparams.items() if k not in train}
  camera, _ = batch.camera_batch(camera, None)
  static = dict(rule_name=probe.name, aggregate=aggregate, capacity=int(capacity),
                num_classes=int(num_classes), voxel_size=float(voxel_size),
                max_probes=int(max_probes))
  seqs = _Sequences(read_chunk, list(num_chunks), camera, static, chunk_size)
  checkpoint = int(checkpoint or max(1, math.ceil(math.sqrt(max(num_chunks)))))
  coords = [jnp.asarray(g["coords"], jnp.int32) for g in gt]
  labels = [jnp.asarray(g["labels"], jnp.int32) for g in gt]

  def loss_and_cotangents(params):
    finals = [seqs.forward(b, params, fixed)[0] for b in range(len(gt))]
    stats = [_statistic(s, c, l, objective=objective) for s, c, l in zip(finals, coords, labels)]
    value, g_stats = jax.value_and_grad(lambda st: _combine(st, objective))(stats)
    g_finals = [_vjp_statistic(s, c, l, g, objective=objective)
                for s, c, l, g in zip(finals, coords, labels, g_stats)]
    return value, g_finals

  optimizer = optax.adam(learning_rate)
  opt_state = optimizer.init(params)
  losses, path, grads = [], [], []
  for step in range(int(steps)):
    value, g_finals = loss_and_cotangents(params)
    grad = jax.tree.map(jnp.zeros_like, params)
    for b, g_final in enumerate(g_finals):
      grad = jax.tree.map(jnp.add, grad, seqs.backward(b, params, fixed, g_final, checkpoint))
    losses.append(float(value))
    path.append({k: np.asarray(v) for k, v in tune.constrain(params).items()})
    grads.append({k: np.asarray(v) for k, v in grad.items()})
    updates, opt_state = optimizer.update(grad, opt_state, params)
    params = optax.apply_updates(params, updates)
    if progress is not None:
      progress(step, float(value))
  final_value, _ = loss_and_cotangents(params)
  losses.append(float(final_value))
  final = {k: np.asarray(v, np.float32) for k, v in tune.constrain(params).items()}
  path.append(final)
  hparams.update(final)
  hparams = {k: float(v) if np.ndim(v) == 0 else v for k, v in hparams.items()}
  return tune.TuneResult(
      hparams=hparams, rule=rules_lib.by_name(rule, aggregate=aggregate, **hparams),
      losses=np.asarray(losses, np.float32),
      path={k: np.stack([p[k] for p in path]) for k in final},
      grads={k: np.stack([g[k] for g in grads]) for k in final}, objective=objective)
