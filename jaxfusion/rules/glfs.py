"""GLFS: Bayes with a learned weight per (predicted class × depth bin × incidence bin).

After Marques et al., "On the Overconfidence Problem in Semantic 3D Mapping" (ICRA 2024), whose
learned fusion weights each observation by a table over the predicted class, the depth and the
incidence angle. docs/equations.md §3.10 states what is computed here; in short, with `ĉ_j` the
pixel's predicted class, `z_j` its depth and `cos θ_j` its incidence (§2.5):

    w_j   = W[ĉ_j, bin(z_j), bin(cos θ_j)]            ≥ 0, one weight per pixel
    log P_t = normalise(log P_{t−1} + Σ_j w_j · log p_j)

`W = 1` is Bayes (§3.3) exactly. The bin edges are leaves too (fixed when fitting). What the
paper fixes and what this implementation guesses is listed in docs/results/learned_rule.md.
"""

import jax.numpy as jnp
import numpy as np

from jaxfusion import numerics
from jaxfusion.rules import base
from jaxfusion.rules.baselines import log_init
from jaxfusion.rules.baselines import log_posterior

CONTEXT = ("depth", "incidence")
# Depth bin edges in metres (bins: < 1, 1–2, 2–3, 3–4, ≥ 4) and incidence edges over cos θ
# (bins: cos θ < 0.25, …, ≥ 0.75).
DEPTH_EDGES = (1.0, 2.0, 3.0, 4.0)
ANGLE_EDGES = (0.25, 0.5, 0.75)


def bins(ctx, depth_edges, angle_edges):
  """`(depth bin, angle bin)` int32 of a pixel's `(2,)` context (depth, cos θ)."""
  return (jnp.searchsorted(depth_edges, ctx[0], side="right").astype(jnp.int32),
          jnp.searchsorted(angle_edges, ctx[1], side="right").astype(jnp.int32))


def _check(hparams, num_classes):
  table = jnp.shape(hparams["table"])
  want = (num_classes, jnp.shape(hparams["depth_edges"])[0] + 1,
          jnp.shape(hparams["angle_edges"])[0] + 1)
  if table != want:
    raise ValueError(f"GLFS table must have shape (K, depth bins, angle bins) = {want}; got "
                     f"{table}")


def _init(num_classes, hparams):
  _check(hparams, num_classes)
  return log_init(num_classes, hparams)


def _observe(probs, var, ctx, hparams):
  del var
  _check(hparams, probs.shape[-1])
  d, a = bins(ctx, hparams["depth_edges"], hparams["angle_edges"])
  w = hparams["table"][jnp.argmax(probs), d, a]
  return base.PixelTerms(sums={"wloglik": w * numerics.safe_log(probs)}, maxes={})


def _update(row, obs, hparams):
  del hparams
  return {"logp": numerics.normalize_log(row["logp"] + obs.sums["wloglik"])}


def _remove(row, obs, hparams):
  del hparams
  return {"logp": numerics.normalize_log(row["logp"] - obs.sums["wloglik"])}


def glfs(table=None, *, num_classes: int = None, depth_edges=DEPTH_EDGES,
         angle_edges=ANGLE_EDGES, aggregate: str = "sum") -> base.FusionRule:
  """The GLFS rule (module docstring).

  Args:
    table: `(K, len(depth_edges) + 1, len(angle_edges) + 1)` non-negative weights, or None
      (all ones: Bayes; then `num_classes` is needed).
    num_classes: K, when `table` is None.
    depth_edges: increasing depth bin edges in metres.
    angle_edges: increasing bin edges over cos θ in (0, 1).
    aggregate: "sum" or "mean" (docs/equations.md §2.4).

  Returns:
    A FusionRule named "glfs" with `context = ("depth", "incidence")`.

  Raises:
    ValueError: a wrong shape, negative or non-finite weights, or edges that do not increase.
  """
  depth_edges = np.asarray(depth_edges, np.float32)
  angle_edges = np.asarray(angle_edges, np.float32)
  for name, edges in (("depth_edges", depth_edges), ("angle_edges", angle_edges)):
    if edges.ndim != 1 or not np.all(np.isfinite(edges)) or np.any(np.diff(edges) <= 0):
      raise ValueError(f"{name} must be a finite increasing 1-D sequence; got {edges.tolist()}")
  if table is None:
    if num_classes is None:
      raise ValueError("give a GLFS table or num_classes (for the all-ones table: Bayes)")
    table = np.ones((num_classes, len(depth_edges) + 1, len(angle_edges) + 1), np.float32)
  leaf = jnp.asarray(table, jnp.float32)
  if leaf.ndim != 3 or leaf.shape[1:] != (len(depth_edges) + 1, len(angle_edges) + 1):
    raise ValueError(f"GLFS table must have shape (K, {len(depth_edges) + 1}, "
                     f"{len(angle_edges) + 1}); got {leaf.shape}")
  if base.is_concrete(leaf):
    values = np.asarray(leaf)
    if not np.all(np.isfinite(values)) or np.any(values < 0):
      raise ValueError("GLFS weights must be finite and non-negative")
  hparams = {"table": leaf, "depth_edges": jnp.asarray(depth_edges),
             "angle_edges": jnp.asarray(angle_edges)}
  return base.FusionRule(
      hparams=hparams, name="glfs", init=_init, observe=_observe, update=_update,
      posterior=log_posterior, confidence=None, requires_var=False,
      aggregate=base.check_aggregate(aggregate), context=CONTEXT, remove=_remove)
