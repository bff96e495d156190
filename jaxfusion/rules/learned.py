"""A learned fusion rule: weighted, regularised Bayes with a per-pixel weight `w_j = f_θ(φ_j)`.

docs/equations.md §3.9 states it; in short, with `p̃_j` the regularised probabilities of §3.4 /
§3.7 (per-class β), `α_j,i = −log(clip(var_j,i, 0, 0.25) + ε)` and `ᾱ` the running maximum of
§3.5:

    w_j   = sigmoid(θ · φ_j + b)                        ∈ [0, 1], one weight per pixel
    s_t,i = (1 − δ) + δ · ᾱ_{t−1,i} / ᾱ_t,i             how much of the prior is kept
    o_t,i = Σ_j w_j · ((1 − δ) + δ · α_j,i / ᾱ_t,i) · log p̃_j,i
    g_t   = sigmoid(γ₀ + γ₁ · agree_t + γ₂ · H(P_{t−1}) / log K)    one gate per voxel and frame
    log P_t = normalise(s_t ⊙ log P_{t−1} + g_t · o_t)

`φ_j` are six features of the pixel's MC moments (`features`): the largest mean probability,
the margin to the second, the entropy of the mean over log K, the predicted class's α / 10, the
root of the summed variance, and the predicted class's variance over its largest possible value
`p(1 − p)`. `agree_t = Σ_i P_{t−1}(i) · softmax(o_t)_i` is how much the frame's observation agrees
with what the voxel already holds.

Special cases: θ = 0, b = γ₀ = 30, γ₁ = γ₂ = 0 make every weight and gate exactly 1 in float32
(`sigmoid(30) = 1`), and then δ = 0, β = 0 is Bayes (§3.3); δ = 0 is R (§3.4); δ = 1 is D+R
(§3.6); δ = 1, β = 0 is D (§3.5) — the same maps up to float32 rounding of the same terms.
`learned()` with no arguments is D+R at the paper's β; `special_case(name)` gives the others.

The second version (docs/equations.md §3.9, "With context"): `learned(params, context=names)`
adds `θᶜ · ψ_j` to the weight's logit, ψ_j the pixel's context features (`jaxfusion.context`,
§2.5) times fixed scales; θ, b and θᶜ may be one row per predicted class (`(K, 6)`, `(K,)`,
`(K, F)`); γ `(5,)` adds the Jensen–Shannon divergence between the frame's observation and the
voxel's posterior and the voxel's frame count to the gate. The special cases hold as before.

All of θ, b, θᶜ, δ, γ, β (and ε, α₀) are traced leaves: `jit`, `vmap` over a stack of parameter
sets and `grad` work without recompiling when values change; the context names are static.
13 + K parameters in the first version (β per class), 118 at K = 7 with every feature, per-class
weights and γ `(5,)`.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import context as context_lib
from jaxfusion import numerics
from jaxfusion.rules import base
from jaxfusion.rules import robust as robust_lib
from jaxfusion.rules.baselines import log_posterior

NUM_FEATURES = 6
FEATURE_NAMES = ("max_prob", "margin", "entropy", "alpha_pred", "sqrt_sum_var", "rel_var_pred")
# A logit whose sigmoid is exactly 1.0 in float32: the "always on" weight and gate.
ON = 30.0
# Scale of the α feature: α of a typical MC-dropout pixel lies in about 2–12.
_ALPHA_SCALE = 10.0
PARAM_NAMES = ("theta", "bias", "context_theta", "mix", "gate", "beta", "eps", "alpha0")


def features(probs: jax.Array, var: jax.Array, eps) -> jax.Array:
  """The six per-pixel features `φ` of one pixel's `(K,)` MC mean and variance (`(6,)` float32),
  ε the scalar variance shift of α.

  Every feature is finite for any probabilities in [0, 1] and variances ≥ 0, including one-hot
  means and zero variances.
  """
  k = probs.shape[-1]
  # The predicted class by a mask, not by indexing: under the engine's vmap over pixels, `x[pred]`
  # and `top_k` become a gather and a sort per pixel, 9× the cost of the rest on XLA-CPU
  # (bench/context.py). The values are the same bit for bit.
  chosen = jax.nn.one_hot(jnp.argmax(probs), k, dtype=bool)
  p_pred = jnp.max(probs)
  second = jnp.max(jnp.where(chosen, -jnp.inf, probs))
  v_pred = jnp.clip(jnp.sum(jnp.where(chosen, var, 0.0)), 0.0, 0.25)
  bound = p_pred * (1.0 - p_pred)
  rel = jnp.where(bound > 0, jnp.minimum(v_pred / jnp.where(bound > 0, bound, 1.0), 1.0), 0.0)
  sum_var = jnp.sum(jnp.clip(var, 0.0, 0.25))
  return jnp.stack([
      p_pred,
      p_pred - second,
      numerics.entropy(probs) / math.log(k),
      -jnp.log(v_pred + eps) / _ALPHA_SCALE,
      jnp.sqrt(sum_var + 1e-12),
      rel,
  ]).astype(jnp.float32)


# Fixed scales of the context features (docs/equations.md §2.5) in the weight: each about [0, 1]
# on indoor frames, so that one step size fits every weight.
CONTEXT_SCALE = {"depth": 0.25, "incidence": 1.0, "depth_edge": 1.0 / 16, "label_edge": 1.0 / 16,
                 "radius": 1.0, "sharpness": 4.0, "luminance": 1.0, "clipped": 1.0}
# Scale of the voxel's frame count in the gate: log1p(n) / log1p(32).
_FRAMES_SCALE = 1.0 / math.log1p(32.0)


def pixel_weight(phi: jax.Array, hparams: dict, ctx: jax.Array = None,
                 pred: jax.Array = None) -> jax.Array:
  """`w = sigmoid(θ_ĉ · φ + θᶜ_ĉ · ψ + b_ĉ)`: the weight of a pixel's log-likelihood.

  Args:
    phi: `(6,)` moment features (`features`).
    hparams: the rule's parameters; `theta` `(6,)` or per class `(K, 6)`, `bias` `()` or `(K,)`,
      `context_theta` `(F,)` or `(K, F)` (only read when `ctx` is given).
    ctx: `(F,)` scaled context features ψ (`scaled_context`), or None.
    pred: `()` int predicted class ĉ, needed when a parameter is per class.
  """
  def pick(x, per_class_ndim):
    if jnp.ndim(x) != per_class_ndim:
      return x
    chosen = jax.nn.one_hot(pred, x.shape[0], dtype=bool)   # ĉ's row by a mask (`features`)
    return jnp.sum(jnp.where(chosen.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0.0), axis=0)
  z = jnp.sum(phi * pick(hparams["theta"], 2), axis=-1) + pick(hparams["bias"], 1)
  if ctx is not None:
    z = z + jnp.sum(ctx * pick(hparams["context_theta"], 2), axis=-1)
  return jax.nn.sigmoid(z)


def scaled_context(ctx: jax.Array, names: tuple) -> jax.Array:
  """`(…, F)` context features times their fixed `CONTEXT_SCALE`."""
  return ctx * jnp.asarray([CONTEXT_SCALE[n] for n in names], jnp.float32)


def _check_fixed_shapes(hparams):
  """The shapes that do not depend on K: θ `(6,)` or `(·, 6)`, γ `(3,)` or `(5,)`, b `()` or
  `(·,)`, and δ, ε, α₀ scalars."""
  theta, gate = jnp.shape(hparams["theta"]), jnp.shape(hparams["gate"])
  if theta[-1:] != (NUM_FEATURES,) or len(theta) > 2 or gate not in ((3,), (5,)):
    raise ValueError(f"theta must have shape ({NUM_FEATURES},) or (K, {NUM_FEATURES}) and gate "
                     f"(3,) or (5,); got {theta} and {gate}")
  if jnp.ndim(hparams["bias"]) > 1:
    raise ValueError(f"bias must be a scalar or (K,); got shape {jnp.shape(hparams['bias'])}")
  for name in ("mix", "eps", "alpha0"):
    if jnp.shape(hparams[name]) != ():
      raise ValueError(f"{name} must be a scalar; got shape {jnp.shape(hparams[name])}")


def _check_context_shape(hparams, num_features):
  shape = jnp.shape(hparams["context_theta"])
  if shape[-1:] != (num_features,) or len(shape) > 2:
    raise ValueError(f"context_theta must have shape ({num_features},) or (K, {num_features}), "
                     f"one weight per context feature; got {shape}")


def _check_shapes(hparams, num_classes):
  base.check_class_shapes(hparams, num_classes, ("beta", "bias"))
  _check_fixed_shapes(hparams)
  for name in ("theta", "context_theta"):
    if name not in hparams:
      continue
    shape = jnp.shape(hparams[name])
    if len(shape) == 2 and shape[0] != num_classes:
      raise ValueError(f"{name} has shape {shape} but the map has K = {num_classes} classes; "
                       f"give one row per class ({num_classes}, {shape[1]}) or one shared row")


def _init(num_classes, hparams):
  _check_shapes(hparams, num_classes)
  row = robust_lib.dirichlet_row(num_classes, hparams)
  if jnp.shape(hparams["gate"]) == (5,):
    row["frames"] = jnp.zeros(1, jnp.float32)
  return row


def _observe_terms(probs, var, hparams, ctx, names):
  _check_shapes(hparams, probs.shape[-1])
  shifted = jnp.clip(var, 0.0, 0.25) + hparams["eps"]
  pred = jnp.argmax(probs)
  psi = None if ctx is None else scaled_context(ctx, names)
  w = pixel_weight(features(probs, var, hparams["eps"]), hparams, psi, pred)
  loglik = numerics.safe_log(robust_lib.regularize(probs, hparams["beta"]))
  wloglik = w * loglik
  return base.PixelTerms(
      sums={"wloglik": wloglik, "walpha_loglik": -jnp.log(shifted) * wloglik},
      maxes={"neg_shifted_var": -shifted})


def _observe(probs, var, hparams):
  return _observe_terms(probs, var, hparams, None, ())


@functools.lru_cache(maxsize=None)
def _context_observer(names):
  """The observe kernel for a tuple of context names, one per tuple, so that rules with the same
  context share it (the same static field: stacking and the jit cache see equal rules)."""
  def observe(probs, var, ctx, hparams):
    return _observe_terms(probs, var, hparams, ctx, names)
  return observe


def _js_divergence(p, q):
  """Jensen–Shannon divergence of two `(K,)` distributions over log 2, in [0, 1]."""
  m = 0.5 * (p + q)
  kl = lambda a: jnp.sum(jnp.where(a > 0, a * (numerics.safe_log(a) - numerics.safe_log(m)), 0.0))
  return jnp.clip(0.5 * (kl(p) + kl(q)) / math.log(2.0), 0.0, 1.0)


def _update(row, obs, hparams):
  mix = hparams["mix"]
  alpha_prev = row["alpha_bar"]
  alpha_bar, safe = robust_lib.running_concentration(alpha_prev, obs)
  keep = (1.0 - mix) + mix * (alpha_prev / safe)
  observation = (1.0 - mix) * obs.sums["wloglik"] + mix * (obs.sums["walpha_loglik"] / safe)
  prior = jax.nn.softmax(row["logp"])
  frame_dist = jax.nn.softmax(observation)
  agree = jnp.sum(prior * frame_dist)
  spread = numerics.entropy(prior) / math.log(prior.shape[-1])
  gamma = hparams["gate"]
  logit = gamma[0] + gamma[1] * agree + gamma[2] * spread
  out = {}
  if gamma.shape[0] == 5:
    seen = row["frames"][0]
    logit = (logit + gamma[3] * _js_divergence(frame_dist, prior)
             + gamma[4] * jnp.log1p(seen) * _FRAMES_SCALE)
    out["frames"] = row["frames"] + 1.0
  gate = jax.nn.sigmoid(logit)
  out.update(logp=numerics.normalize_log(keep * row["logp"] + gate * observation),
             alpha_bar=alpha_bar)
  return out


def _confidence(row):
  return row["alpha_bar"]


def _concrete_checks(hparams):
  for name, value in hparams.items():
    if base.is_concrete(value) and not np.all(np.isfinite(np.asarray(value, np.float64))):
      raise ValueError(f"{name} must be finite; got {np.asarray(value).tolist()}")
  mix = hparams["mix"]
  if base.is_concrete(mix) and not 0.0 <= float(mix) <= 1.0:
    raise ValueError(f"mix must lie in [0, 1]; got {float(mix)}")
  robust_lib.check_hparams(hparams["beta"], hparams["eps"], hparams["alpha0"])


def learned(params: dict = None, *, context=(), aggregate: str = "sum",
            **overrides) -> base.FusionRule:
  """The learned rule of docs/equations.md §3.9 (module docstring), from a parameter dict.

  Args:
    params: any of `theta` `(6,)` or per class `(K, 6)`, `bias` `()` or `(K,)`, `mix` `()` δ ∈
      [0, 1], `gate` `(3,)` or `(5,)` γ (the last two read the frame's divergence from the voxel
      and the voxel's frame count), `beta` `()` or `(K,)` ∈ [0, 1], `eps` `()` > 0, `alpha0` `()`
      ≥ 0, and with `context` `context_theta` `(F,)` or `(K, F)`; missing ones take the D+R
      values (θ = 0, b = 30, δ = 1, γ = (30, 0, 0), β = 0.3, ε = 1e-12, α₀ = −log 1e-3, context
      weights 0). Values may be lists, NumPy or JAX arrays, or tracers (for `grad` and `vmap`).
      A `"context"` entry (a list of names, as `params.json` stores it) is the same as the
      keyword.
    context: names of per-pixel context features the weight reads (`jaxfusion.context.FEATURES`,
      docs/equations.md §2.5), F of them; static (a different tuple is a different program).
    aggregate: "sum" or "mean" (docs/equations.md §2.4).
    **overrides: the same names as keywords, applied over `params`.

  Returns:
    A FusionRule named "learned" (`requires_var`: its features and D's weighting read the MC
    variance).

  Raises:
    ValueError: an unknown parameter or context name, a wrong shape, a non-finite value, or δ,
      β, ε, α₀ out of range (checked where concrete).
  """
  given = {**(params or {}), **overrides}
  if "context" in given:
    stored = tuple(given.pop("context"))
    if context and tuple(context) != stored:
      raise ValueError(f"context given twice: {list(context)} and {list(stored)}")
    context = stored
  context = context_lib.check_names(context)
  values = {"theta": np.zeros(NUM_FEATURES, np.float32), "bias": ON, "mix": 1.0,
            "gate": np.array([ON, 0.0, 0.0], np.float32), "beta": robust_lib.DEFAULT_BETA,
            "eps": robust_lib.DEFAULT_EPS, "alpha0": robust_lib.DEFAULT_ALPHA0}
  if context:
    values["context_theta"] = np.zeros(len(context), np.float32)
  unknown = set(given) - set(values)
  if unknown:
    extra = ("; context_theta needs context=(...)" if "context_theta" in unknown and not context
             else "")
    raise ValueError(f"unknown learned-rule parameters {sorted(unknown)}; the names are "
                     f"{', '.join(PARAM_NAMES)}{extra}")
  values.update(given)
  hparams = {name: jnp.asarray(value, jnp.float32) for name, value in values.items()}
  hparams["beta"] = base.as_class_leaf(values["beta"], "beta")
  _check_fixed_shapes(hparams)
  if context:
    _check_context_shape(hparams, len(context))
  _concrete_checks(hparams)
  return base.FusionRule(
      hparams=hparams, name="learned", init=_init,
      observe=_context_observer(context) if context else _observe, update=_update,
      posterior=log_posterior, confidence=_confidence, requires_var=True,
      aggregate=base.check_aggregate(aggregate), context=context)


def num_parameters(rule: base.FusionRule) -> int:
  """Number of values in the rule's fitted parameters (all but ε and α₀)."""
  return int(sum(np.size(v) for k, v in rule.hparams.items() if k not in ("eps", "alpha0")))


def special_case(name: str, *, beta=robust_lib.DEFAULT_BETA) -> dict:
  """Parameters that make `learned` one of the paper's rules: "bayes", "robust_r", "robust_d"
  or "robust_dr" (every weight and gate exactly 1)."""
  mixes = {"bayes": 0.0, "robust_r": 0.0, "robust_d": 1.0, "robust_dr": 1.0}
  if name not in mixes:
    raise ValueError(f"the learned rule contains bayes, robust_r, robust_d and robust_dr; got "
                     f"{name!r}")
  return {"mix": mixes[name], "beta": beta if name in ("robust_r", "robust_dr") else 0.0}
