"""The rule family: one unbounded per-pixel log-weight, made of terms, that contains every
Bayesian rule shipped (Bayes, R, D, D+R, GLFS and the learned rule).

docs/equations.md §3.11 states it; in short, with `ĉ_j` the pixel's predicted class, φ_j its six
moment features and ψ_j its scaled context (§3.9):

    w_j = W[ĉ_j, bin(z_j), bin(cos θ_j)]                    term "table"     (GLFS, §3.10)
          · exp(clip(a_ĉ · φ_j + c_ĉ · ψ_j, −15, 15))         terms "moments", "context"
          · sigmoid(θ_ĉ · φ_j + θᶜ_ĉ · ψ_j + b_ĉ)              term "sigmoid"   (§3.9)
    o_t   = Σ_j w_j · ((1 − δ) + δ · α_j / ᾱ_t) · log p̃_j      terms "beta" (R), "mix" (D)
    log P_t = normalise(s_t ⊙ log P_{t−1} + g_t · o_t)          term "gate"      (§3.9)
    P̃_v = softmax(log P_v + Σ_s λ_{:,s} ⊙ mean_{n in shell s} P_n)   term "spatial" (§4.1)

The spatial term acts at read-out: `init_map` keeps λ in the map, and `voxel_posteriors`,
`read_map`, `query` and the mesh labels smooth with it; fusion never reads it.

A term is present exactly when its parameters are (`terms`), and a rule without it computes
nothing for it: only the table is GLFS's program, nothing is Bayes's, a §3.9 parameter set is
that learned rule's — the same maps bit for bit (tests/engine/test_family.py).

Every parameter is a traced leaf (`jit`, `vmap` over stacks of one structure, `grad`); which
terms are present, the bin edges' count and the context names are static.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import context as context_lib
from jaxfusion import numerics
from jaxfusion.rules import base
from jaxfusion.rules import glfs as glfs_lib
from jaxfusion.rules import learned as learned_lib
from jaxfusion.rules import robust as robust_lib
from jaxfusion.rules.baselines import log_init
from jaxfusion.rules.baselines import log_posterior

# The terms, in the order of the weight and the update; each is present when these parameters
# are given.
TERMS = {"table": ("table",), "moments": ("moment_weights",), "context": ("context_weights",),
         "sigmoid": ("theta", "bias", "context_theta"), "beta": ("beta",), "mix": ("mix",),
         "gate": ("gate",), "spatial": ("spatial",)}
PARAM_NAMES = ("table", "depth_edges", "angle_edges", "moment_weights", "context_weights",
               "theta", "bias", "context_theta", "beta", "mix", "gate", "spatial", "eps",
               "alpha0")
# The exponent of the unbounded factor is clipped to ±CLIP (docs/equations.md §3.11).
CLIP = 15.0
NUM_FEATURES = learned_lib.NUM_FEATURES


def terms(rule_or_hparams) -> tuple:
  """The terms present in a family rule (or its `hparams`), in `TERMS` order."""
  hparams = getattr(rule_or_hparams, "hparams", rule_or_hparams)
  return tuple(t for t, names in TERMS.items() if any(n in hparams for n in names))


def _pick(x, per_class_ndim, pred):
  """`x` itself, or the row of the predicted class `pred` of a per-class `x` (by a mask: see
  `learned.features`)."""
  if jnp.ndim(x) != per_class_ndim:
    return x
  chosen = jax.nn.one_hot(pred, x.shape[0], dtype=bool)
  return jnp.sum(jnp.where(chosen.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0.0), axis=0)


def _needs_features(hparams) -> bool:
  return "moment_weights" in hparams or "theta" in hparams


def _check_shapes(hparams, num_classes, num_context):
  """Shapes against the map's K and the F context features: one clear line each."""
  if "table" in hparams:
    want = (num_classes, jnp.shape(hparams["depth_edges"])[0] + 1,
            jnp.shape(hparams["angle_edges"])[0] + 1)
    if jnp.shape(hparams["table"]) != want:
      raise ValueError(f"the family's table must have shape (K, depth bins, angle bins) = "
                       f"{want}; got {jnp.shape(hparams['table'])}")
  for name, width in (("moment_weights", NUM_FEATURES), ("theta", NUM_FEATURES),
                      ("context_weights", num_context), ("context_theta", num_context)):
    if name not in hparams:
      continue
    shape = jnp.shape(hparams[name])
    if shape not in ((width,), (num_classes, width)):
      raise ValueError(f"{name} must have shape ({width},) or (K, {width}) = ({num_classes}, "
                       f"{width}); got {shape}")
  base.check_class_shapes(hparams, num_classes,
                          tuple(n for n in ("bias", "beta") if n in hparams))
  if "spatial" in hparams and jnp.shape(hparams["spatial"]) != (num_classes, 3):
    raise ValueError(f"spatial must have shape (K, 3) = ({num_classes}, 3), one weight per "
                     f"class and neighbour shell; got {jnp.shape(hparams['spatial'])}")


def _init(num_classes, hparams):
  _check_shapes(hparams, num_classes, _num_context(hparams))
  row = (robust_lib.dirichlet_row(num_classes, hparams) if "mix" in hparams
         else log_init(num_classes, hparams))
  if "gate" in hparams and jnp.shape(hparams["gate"]) == (5,):
    row["frames"] = jnp.zeros(1, jnp.float32)
  return row


def _num_context(hparams):
  for name in ("context_weights", "context_theta"):
    if name in hparams:
      return jnp.shape(hparams[name])[-1]
  return 0


def _observe_terms(probs, var, ctx, hparams, names, table_at):
  """Per-pixel terms; `names` the F context features the weights read (the first F of `ctx`),
  `table_at` the positions of depth and incidence in `ctx` (for the table)."""
  _check_shapes(hparams, probs.shape[-1], len(names))
  w = None
  if "table" in hparams:     # GLFS's operations, in its order (the same program: tested)
    at = ctx if table_at == (0, 1) else (ctx[table_at[0]], ctx[table_at[1]])
    d, a = glfs_lib.bins(at, hparams["depth_edges"], hparams["angle_edges"])
    w = hparams["table"][jnp.argmax(probs), d, a]
  weighted = any(n in hparams for n in ("moment_weights", "context_weights", "theta"))
  pred = jnp.argmax(probs) if weighted else None   # XLA merges it with the table's
  phi = learned_lib.features(probs, var, hparams["eps"]) if _needs_features(hparams) else None
  psi = learned_lib.scaled_context(ctx[:len(names)], names) if names else None
  z = None
  if "moment_weights" in hparams:
    z = jnp.sum(phi * _pick(hparams["moment_weights"], 2, pred), axis=-1)
  if "context_weights" in hparams:
    zc = jnp.sum(psi * _pick(hparams["context_weights"], 2, pred), axis=-1)
    z = zc if z is None else z + zc
  if z is not None:
    factor = jnp.exp(jnp.clip(z, -CLIP, CLIP))
    w = factor if w is None else w * factor
  if "theta" in hparams:
    factor = learned_lib.pixel_weight(phi, hparams,
                                      psi if "context_theta" in hparams else None, pred)
    w = factor if w is None else w * factor
  p = robust_lib.regularize(probs, hparams["beta"]) if "beta" in hparams else probs
  loglik = numerics.safe_log(p)
  wloglik = loglik if w is None else w * loglik
  if "mix" not in hparams:
    return base.PixelTerms(sums={"wloglik": wloglik}, maxes={})
  shifted = jnp.clip(var, 0.0, 0.25) + hparams["eps"]
  return base.PixelTerms(
      sums={"wloglik": wloglik, "walpha_loglik": -jnp.log(shifted) * wloglik},
      maxes={"neg_shifted_var": -shifted})


@functools.lru_cache(maxsize=None)
def _observer(names, table_at):
  """The observe kernel for static context names and table positions, one per pair, so that
  equal rules share it (stacking and the jit cache compare the static fields)."""
  if not names and table_at is None:
    def observe(probs, var, hparams):
      return _observe_terms(probs, var, None, hparams, (), None)
  else:
    def observe(probs, var, ctx, hparams):
      return _observe_terms(probs, var, ctx, hparams, names, table_at)
  return observe


def _update(row, obs, hparams):
  logp = row["logp"]
  out = {}
  if "mix" in hparams:
    mix = hparams["mix"]
    alpha_prev = row["alpha_bar"]
    alpha_bar, safe = robust_lib.running_concentration(alpha_prev, obs)
    keep = (1.0 - mix) + mix * (alpha_prev / safe)
    observation = (1.0 - mix) * obs.sums["wloglik"] + mix * (obs.sums["walpha_loglik"] / safe)
  else:
    keep, observation = None, obs.sums["wloglik"]
  gate = None
  if "gate" in hparams:
    prior = jax.nn.softmax(logp)
    frame_dist = jax.nn.softmax(observation)
    gamma = hparams["gate"]
    logit = (gamma[0] + gamma[1] * jnp.sum(prior * frame_dist)
             + gamma[2] * numerics.entropy(prior) / math.log(prior.shape[-1]))
    if gamma.shape[0] == 5:
      seen = row["frames"][0]
      logit = (logit + gamma[3] * learned_lib._js_divergence(frame_dist, prior)  # pylint: disable=protected-access
               + gamma[4] * jnp.log1p(seen) * learned_lib._FRAMES_SCALE)          # pylint: disable=protected-access
      out["frames"] = row["frames"] + 1.0
    gate = jax.nn.sigmoid(logit)
  if keep is None and gate is None:
    new = logp + observation
  else:
    new = (logp if keep is None else keep * logp) + (
        observation if gate is None else gate * observation)
  out["logp"] = numerics.normalize_log(new)
  if "mix" in hparams:
    out["alpha_bar"] = alpha_bar
  return out


def _remove(row, obs, hparams):
  del hparams
  return {"logp": numerics.normalize_log(row["logp"] - obs.sums["wloglik"])}


def _confidence(row):
  return row["alpha_bar"]


def _concrete_checks(hparams):
  for name, value in hparams.items():
    if base.is_concrete(value) and not np.all(np.isfinite(np.asarray(value, np.float64))):
      raise ValueError(f"{name} must be finite; got {np.asarray(value).tolist()}")
  if "table" in hparams and base.is_concrete(hparams["table"]):
    if np.any(np.asarray(hparams["table"]) < 0):
      raise ValueError("the family's table weights must be non-negative")
  if "mix" in hparams and base.is_concrete(hparams["mix"]):
    if not 0.0 <= float(hparams["mix"]) <= 1.0:
      raise ValueError(f"mix must lie in [0, 1]; got {float(hparams['mix'])}")
  robust_lib.check_hparams(hparams.get("beta", 0.0), hparams.get("eps", 1.0),
                           hparams.get("alpha0", 0.0))


def family(params: dict = None, *, context=(), aggregate: str = "sum",
           **overrides) -> base.FusionRule:
  """A member of the rule family of docs/equations.md §3.11 (module docstring).

  Args:
    params: the terms' parameters; the terms present are those whose names are given:
      `table` `(K, len(depth_edges) + 1, len(angle_edges) + 1)` ≥ 0 (with `depth_edges`,
      `angle_edges`: GLFS's by default); `moment_weights` `(6,)` or `(K, 6)`; `context_weights`
      `(F,)` or `(K, F)`; the sigmoid factor `theta` `(6,)` or `(K, 6)`, `bias` `()` or `(K,)`,
      `context_theta` `(F,)` or `(K, F)` (missing ones of the three at θ = 0, b = 30, θᶜ = 0);
      `beta` `()` or `(K,)` in [0, 1] (R); `mix` `()` δ in [0, 1] (D, with `alpha0`); `gate`
      `(3,)` or `(5,)`; `spatial` `(K, 3)` the read-out's kernel over the face, edge and
      corner neighbours (docs/equations.md §4.1); `eps` and `alpha0` the fixed leaves of α (defaults of §3.8). A
      `"context"` entry (a list of names, as `params.json` stores it) is the same as the
      keyword. None or `{}`: Bayes.
    context: the F per-pixel context features (`jaxfusion.context.FEATURES`) that the context
      weights read; static. The table reads depth and incidence whether or not they are named.
    aggregate: "sum" or "mean" (docs/equations.md §2.4).
    **overrides: the same names as keywords, applied over `params`.

  Returns:
    A FusionRule named "family". Its `context` is `context`, then depth and incidence where the
    table needs them and `context` lacks them. It can be de-integrated when it has neither D
    nor a gate.

  Raises:
    ValueError: an unknown parameter or context name, context weights without context names
      (or names without weights), a wrong shape, a non-finite or negative weight, δ or β out
      of range, edges that do not increase.
  """
  given = {**(params or {}), **overrides}
  if "context" in given:
    stored = tuple(given.pop("context"))
    if context and tuple(context) != stored:
      raise ValueError(f"context given twice: {list(context)} and {list(stored)}")
    context = stored
  context = context_lib.check_names(context)
  unknown = set(given) - set(PARAM_NAMES)
  if unknown:
    raise ValueError(f"unknown rule-family parameters {sorted(unknown)}; the names are "
                     f"{', '.join(PARAM_NAMES)}")
  reads_context = "context_weights" in given or "context_theta" in given
  if context and not reads_context:
    raise ValueError(f"context {list(context)} given, but no context_weights or context_theta "
                     f"to read it")
  if reads_context and not context:
    raise ValueError("context_weights and context_theta need context=(names, ...)")
  values = dict(given)
  if "table" in values:
    for name, edges in (("depth_edges", glfs_lib.DEPTH_EDGES),
                        ("angle_edges", glfs_lib.ANGLE_EDGES)):
      values[name] = np.asarray(values.get(name, edges), np.float32)
      if (values[name].ndim != 1 or not np.all(np.isfinite(values[name]))
          or np.any(np.diff(values[name]) <= 0)):
        raise ValueError(f"{name} must be a finite increasing 1-D sequence; got "
                         f"{values[name].tolist()}")
  elif "depth_edges" in values or "angle_edges" in values:
    raise ValueError("depth_edges and angle_edges are the table's; give a table with them")
  if any(n in values for n in TERMS["sigmoid"]):
    values.setdefault("theta", np.zeros(NUM_FEATURES, np.float32))
    values.setdefault("bias", learned_lib.ON)
    if context and "context_theta" not in values and "context_weights" not in values:
      values["context_theta"] = np.zeros(len(context), np.float32)
  if _needs_features(values) or "mix" in values:
    values.setdefault("eps", robust_lib.DEFAULT_EPS)
  if "mix" in values:
    values.setdefault("alpha0", robust_lib.DEFAULT_ALPHA0)
  hparams = {name: jnp.asarray(value, jnp.float32) for name, value in values.items()}
  for name in ("beta", "bias"):
    if name in hparams:
      hparams[name] = base.as_class_leaf(values[name], name)
  for name in ("mix", "eps", "alpha0"):
    if name in hparams and jnp.shape(hparams[name]) != ():
      raise ValueError(f"{name} must be a scalar; got shape {jnp.shape(hparams[name])}")
  if "gate" in hparams and jnp.shape(hparams["gate"]) not in ((3,), (5,)):
    raise ValueError(f"gate must have shape (3,) or (5,); got {jnp.shape(hparams['gate'])}")
  if "spatial" in hparams and (jnp.ndim(hparams["spatial"]) != 2
                               or jnp.shape(hparams["spatial"])[1] != 3):
    raise ValueError(f"spatial must have shape (K, 3), one weight per class and neighbour "
                     f"shell (face, edge, corner); got {jnp.shape(hparams['spatial'])}")
  if "table" in hparams and jnp.ndim(hparams["table"]) != 3:
    raise ValueError(f"the family's table must have shape (K, depth bins, angle bins); got "
                     f"{jnp.shape(hparams['table'])}")
  for name in ("moment_weights", "theta", "context_weights", "context_theta"):
    width = NUM_FEATURES if name in ("moment_weights", "theta") else len(context)
    if name in hparams and (jnp.shape(hparams[name])[-1:] != (width,)
                            or jnp.ndim(hparams[name]) > 2):
      raise ValueError(f"{name} must have shape ({width},) or (K, {width}); got "
                       f"{jnp.shape(hparams[name])}")
  _concrete_checks(hparams)
  rule_context, table_at = context, None
  if "table" in hparams:
    rule_context = context + tuple(n for n in glfs_lib.CONTEXT if n not in context)
    table_at = tuple(rule_context.index(n) for n in glfs_lib.CONTEXT)
  invertible = "mix" not in hparams and "gate" not in hparams
  return base.FusionRule(
      hparams=hparams, name="family", init=_init, observe=_observer(context, table_at),
      update=_update, posterior=log_posterior,
      confidence=_confidence if "mix" in hparams else None,
      requires_var=_needs_features(hparams) or "mix" in hparams,
      aggregate=base.check_aggregate(aggregate), context=rule_context,
      remove=_remove if invertible else None)


def of_glfs(rule: base.FusionRule) -> base.FusionRule:
  """The family member that is a GLFS rule (`rules.glfs`): its table and edges."""
  return family({k: rule.hparams[k] for k in ("table", "depth_edges", "angle_edges")},
                aggregate=rule.aggregate)


def of_learned(rule: base.FusionRule) -> base.FusionRule:
  """The family member that is a learned rule (`rules.learned`): the same parameters."""
  return family(dict(rule.hparams), context=rule.context, aggregate=rule.aggregate)


def num_parameters(rule: base.FusionRule) -> int:
  """Number of fitted values (all but the edges, ε and α₀)."""
  return int(sum(np.size(v) for k, v in rule.hparams.items()
                 if k not in ("depth_edges", "angle_edges", "eps", "alpha0")))
