"""The FusionRule type: one pure per-voxel update, with its hyperparameters as pytree leaves.

A rule is split into kernels written for one item; the engine vmaps them at the boundary:

- `init(num_classes, hparams) -> row`: the state of one empty voxel (a dict of `(K,)` arrays).
- `observe(probs, var, hparams) -> PixelTerms`: per-pixel terms, from one pixel's `(K,)` class
  probabilities and variances. A rule whose static `context` names per-pixel context features
  (`jaxfusion.context.FEATURES`, docs/equations.md §2.5) is called as
  `observe(probs, var, ctx, hparams)` with that pixel's `(F,)` features in `context` order.
  The engine reduces them over the pixels that fall in a voxel in
  this frame: `sums` are summed (or averaged, under `aggregate="mean"`), `maxes` are maxed.
- `update(row, obs, hparams) -> row`: applies one frame's reduced observation to one voxel.
- `posterior(row) -> (K,)`: the normalised class distribution the voxel reports.
- `confidence(row) -> (K,)` or None: a per-class confidence (ᾱ for the Dirichlet rules).
- `remove(row, obs, hparams) -> row` or None: the inverse of `update` for one frame's reduced
  observation, for rules whose update can be undone (a sum of scores or of log-likelihoods);
  `jaxfusion.deintegration.unfuse_frame` calls it. None: the update cannot be inverted (a
  running maximum, a gate on the voxel's state), and de-integration refuses the rule.

`fuse_frame` only ever calls these five, so a new rule is a new set of functions, never a new
branch in the engine. Hyperparameters users tune or differentiate (β, ε, α₀) are leaves of
`hparams` (the robust rules' β, ε and α₀ may be scalars `()` or per class `(K,)`); everything
that changes code paths (which functions, the aggregation mode) is static, so changing β never
recompiles and a batch of rules with different β can be vmapped.
"""

from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
from flax import struct

AGGREGATIONS = ("sum", "mean")


class PixelTerms(NamedTuple):
  """Per-pixel terms a rule asks the engine to reduce per voxel."""
  sums: dict    # name -> [K] float32, summed over the voxel's pixels
  maxes: dict   # name -> [K] float32, maxed over the voxel's pixels


class VoxelObservation(NamedTuple):
  """One frame's observation of one voxel, reduced over the pixels that fell in it."""
  sums: dict         # name -> [K] float32 (means under aggregate="mean")
  maxes: dict        # name -> [K] float32
  count: jax.Array   # [] float32, number of pixels (≥ 1 for a touched voxel)


@struct.dataclass
class FusionRule:
  """A fusion rule: hyperparameter leaves plus static per-voxel kernels. See module docstring."""
  hparams: dict
  name: str = struct.field(pytree_node=False)
  init: Callable[[int, dict], dict] = struct.field(pytree_node=False)
  observe: Callable[[jax.Array, jax.Array, dict], PixelTerms] = struct.field(pytree_node=False)
  update: Callable[[dict, VoxelObservation, dict], dict] = struct.field(pytree_node=False)
  posterior: Callable[[dict], jax.Array] = struct.field(pytree_node=False)
  confidence: Optional[Callable[[dict], jax.Array]] = struct.field(pytree_node=False)
  requires_var: bool = struct.field(pytree_node=False)
  aggregate: str = struct.field(pytree_node=False)
  context: tuple = struct.field(pytree_node=False, default=())
  remove: Optional[Callable[[dict, VoxelObservation, dict], dict]] = struct.field(
      pytree_node=False, default=None)


def check_aggregate(aggregate: str) -> str:
  if aggregate not in AGGREGATIONS:
    raise ValueError(f"aggregate must be one of {AGGREGATIONS}; got {aggregate!r}")
  return aggregate


def as_class_leaf(value: Any, name: str) -> jax.Array:
  """A hyperparameter that may be given per class: a float32 scalar `()` or vector `(K,)` leaf.

  K is not known here; `check_class_shapes` checks it against the map's K at `init_map` and
  at trace time of `fuse_frame` (shapes are static, so the check also works on traced values).
  """
  leaf = jnp.asarray(value, jnp.float32)
  if leaf.ndim > 1:
    raise ValueError(f"{name} must be a scalar or a (K,) vector with one value per class; got "
                     f"shape {leaf.shape} (stack rules to batch)")
  if leaf.ndim == 1 and leaf.shape[0] < 2:
    raise ValueError(f"{name} given per class needs one value per class (K >= 2); got shape "
                     f"{leaf.shape}")
  return leaf


def check_class_shapes(hparams: dict, num_classes: int, names: tuple) -> None:
  """Raises ValueError if a per-class hyperparameter in `names` is not `()` or `(K,)`."""
  for name in names:
    shape = jnp.shape(hparams[name])
    if shape not in ((), (num_classes,)):
      raise ValueError(f"{name} has shape {shape} but the map has K = {num_classes} classes; "
                       f"give a scalar or one value per class ({num_classes},)")


def is_concrete(x: Any) -> bool:
  return not isinstance(x, jax.core.Tracer)


def stack(rules: list) -> FusionRule:
  """Stacks rules of one kind (e.g. a β grid) into one rule with batched leaves, for `jax.vmap`."""
  if not rules:
    raise ValueError("stack needs at least one rule")
  first = jax.tree.structure(rules[0])
  for r in rules[1:]:
    if jax.tree.structure(r) != first:
      raise ValueError(
          f"can only stack rules of the same kind and aggregation; got {rules[0].name!r} "
          f"and {r.name!r}")
  return jax.tree.map(lambda *xs: jnp.stack(xs), *rules)
