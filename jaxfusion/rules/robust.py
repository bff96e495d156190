"""The robust rules of the paper: regularisation R (eq. 6), Dirichlet weighting D (eqs. 7–9),
and both together, D+R.

- R:   Bayes on `p̃ = (1−β) p̄ + β/K`.
- D:   `α_j,i = −log(var_j,i + ε)`, `ᾱ_t,i = max(ᾱ_{t−1,i}, max_j α_j,i)` (running max including
       frame t — the paper's "τ < t" would leave ᾱ_1 undefined), and
       `log P_t(i) = (ᾱ_{t−1,i}/ᾱ_t,i)·log P_{t−1}(i) + Σ_j (α_j,i/ᾱ_t,i)·log p̄_j,i`, normalised.
       `ᾱ_0 = α₀`, default `−log(1e-3)` as the authors' released code starts every voxel's
       variance at 1e-3; `α₀ = 0` is the literal reading of the equations.
- D+R: D on p̃.

**Per-class hyperparameters** (docs/equations.md §3.7; the paper's future work). β, ε and α₀ may
each be a scalar or a `(K,)` vector with one value per class:
- β per class: `p̃_j,i = ((1−β_i) p̄_j,i + β_i/K) / Z_j` with `Z_j = Σ_i ((1−β_i) p̄_j,i + β_i/K)`,
  so p̃_j stays a distribution (it is the class-i mixing weight, not the β of the pixel's
  predicted class, which would make p̃ a non-smooth function of p̄ at argmax ties). A scalar β
  takes the path without Z (bit-identical to R, §3.4); all-equal β_i give Z_j = 1 up to
  rounding.
- ε per class: `α_j,i = −log(var_j,i + ε_i)` — elementwise already, so free.
- α₀ per class: `ᾱ_0,i = α₀_i` — natural, because ᾱ is a per-class running maximum.
All three stay traced leaves whatever their shape: changing their values never recompiles (a
new shape does, once), and a stack of per-class rules has `(R, K)` leaves for `jax.vmap`.
A vector whose length is not the map's K raises at `init_map` and when `fuse_frame` traces.

Variances are clipped to [0, 0.25] (the range of a variance of probabilities), so α ≥
−log(0.25+ε) > 0 and ᾱ > 0 after one hit. The sum over j is taken per frame, which makes the
update independent of the order of pixels within a frame (the released C++ code fuses pixels one
at a time and is order-dependent — a deliberate difference, see docs/equations.md §6.4).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import numerics
from jaxfusion.rules import base
from jaxfusion.rules.baselines import log_init, log_posterior, log_remove, log_update

DEFAULT_BETA = 0.3
DEFAULT_EPS = 1e-12
DEFAULT_ALPHA0 = -math.log(1e-3)


PER_CLASS_HPARAMS = ("beta", "eps", "alpha0")


def regularize(probs, beta):
  """`p̃ = (1−β) p + β/K` for a `(K,)` distribution and a scalar β (§3.4); for a per-class
  `(K,)` β, `p̃_i = ((1−β_i) p_i + β_i/K) / Z` with `Z = Σ_i ((1−β_i) p_i + β_i/K)` (§3.7;
  uniform where Z = 0, i.e. an all-zero p with β = 0)."""
  mixed = (1.0 - beta) * probs + beta / probs.shape[-1]
  if jnp.ndim(beta) == 0:
    return mixed   # the scalar path stays exactly §3.4 (Z = 1, no division)
  return numerics.safe_normalize(mixed)


def concentration(var, eps):
  """`α = −log(clip(var, 0, 0.25) + ε)` per class."""
  return -jnp.log(jnp.clip(var, 0.0, 0.25) + eps)


def _check_shapes(hparams, num_classes):
  base.check_class_shapes(hparams, num_classes, PER_CLASS_HPARAMS)


def _r_init(num_classes, hparams):
  _check_shapes(hparams, num_classes)
  return log_init(num_classes, hparams)


def _r_observe(probs, var, hparams):
  del var
  _check_shapes(hparams, probs.shape[-1])
  return base.PixelTerms(
      sums={"loglik": numerics.safe_log(regularize(probs, hparams["beta"]))}, maxes={})


def _dirichlet_terms(probs_for_log, var, hparams):
  shifted = jnp.clip(var, 0.0, 0.25) + hparams["eps"]
  # max_j α_j = −log(min_j (var_j + ε)), −log being decreasing: the voxel's ᾱ is taken from the
  # pixels' smallest shifted variance (max of its negative), so α is computed once per pixel for
  # the weighted sum only, and its logarithm per voxel (`_dirichlet_update`) — the same value.
  return base.PixelTerms(
      sums={"wloglik": -jnp.log(shifted) * numerics.safe_log(probs_for_log)},
      maxes={"neg_shifted_var": -shifted})


def _d_observe(probs, var, hparams):
  _check_shapes(hparams, probs.shape[-1])
  return _dirichlet_terms(probs, var, hparams)


def _dr_observe(probs, var, hparams):
  _check_shapes(hparams, probs.shape[-1])
  return _dirichlet_terms(regularize(probs, hparams["beta"]), var, hparams)


def dirichlet_row(num_classes, hparams):
  """An empty voxel of the Dirichlet rules: the uniform `logp` and `ᾱ_0 = α₀` (`()` or `(K,)`)."""
  row = log_init(num_classes, hparams)
  row["alpha_bar"] = jnp.full(num_classes, hparams["alpha0"], jnp.float32)
  return row


def running_concentration(alpha_prev, obs):
  """`(ᾱ_t, safe ᾱ_t)` from `ᾱ_{t−1}` and a frame's reduced `max_j −(var_j + ε)`.

  The frame's `max_j α_j = −log(min_j (var_j + ε))`; lanes without a pixel (max −inf) and
  untouched lanes (1) get no new concentration, with a finite gradient. `ᾱ_t > 0` for any voxel
  with a pixel; the safe copy (1 where it is not) only keeps untouched lanes finite.
  """
  least = -obs.maxes["neg_shifted_var"]
  seen = jnp.isfinite(least) & (least > 0)
  alpha_frame = jnp.where(seen, -jnp.log(jnp.where(seen, least, 1.0)), -jnp.inf)
  alpha_bar = jnp.maximum(alpha_prev, alpha_frame)
  return alpha_bar, jnp.where(alpha_bar > 0, alpha_bar, 1.0)


def _dirichlet_init(num_classes, hparams):
  _check_shapes(hparams, num_classes)
  return dirichlet_row(num_classes, hparams)


def _dirichlet_update(row, obs, hparams):
  del hparams
  alpha_prev = row["alpha_bar"]
  alpha_bar, safe = running_concentration(alpha_prev, obs)
  logp = (alpha_prev / safe) * row["logp"] + obs.sums["wloglik"] / safe
  return {"logp": numerics.normalize_log(logp), "alpha_bar": alpha_bar}


def _dirichlet_confidence(row):
  return row["alpha_bar"]


def _shown(x):
  x = np.asarray(x, np.float64)
  return float(x) if x.ndim == 0 else x.tolist()


def check_hparams(beta, eps, alpha0):
  """Value checks where the values are concrete (scalars or per-class vectors, elementwise)."""
  if base.is_concrete(beta):
    b = np.asarray(beta, np.float64)
    if not np.all((b >= 0.0) & (b <= 1.0)):
      raise ValueError(f"beta must lie in [0, 1]; got {_shown(b)}")
  if base.is_concrete(eps):
    e = np.asarray(eps, np.float64)
    if not np.all(np.isfinite(e) & (e > 0)):
      raise ValueError(f"eps must be a positive finite number; got {_shown(e)}")
  if base.is_concrete(alpha0):
    a = np.asarray(alpha0, np.float64)
    if not np.all(np.isfinite(a) & (a >= 0)):
      raise ValueError(f"alpha0 must be a non-negative finite number; got {_shown(a)}")


def robust(*, beta=DEFAULT_BETA, eps=DEFAULT_EPS, regularize=True, dirichlet=True,
           alpha0=DEFAULT_ALPHA0, aggregate: str = "sum") -> base.FusionRule:
  """The paper's robust fusion: R (`dirichlet=False`), D (`regularize=False`) or D+R (both).

  Args:
    beta: regularisation weight β ∈ [0, 1] (a traced leaf; used by R and D+R): a scalar, or a
      `(K,)` vector of per-class weights (`p̃_i ∝ (1−β_i) p̄_i + β_i/K`, see the module doc).
    eps: ε > 0 added to variances before the log (a traced leaf; used by D and D+R); scalar or
      `(K,)`.
    regularize: apply `p̃ = (1−β) p̄ + β/K`.
    dirichlet: weight observations by their concentration `α = −log(var + ε)`; needs
      `Frame.var`.
    alpha0: prior concentration ᾱ₀ ≥ 0 (a traced leaf; used by D and D+R); scalar or `(K,)`.
    aggregate: "sum" (the paper's Σ_j over a voxel's pixels) or "mean" (one observation per
      voxel per frame: mean of the weighted log-likelihoods, max of α).

  Returns:
    A FusionRule named "robust_r", "robust_d" or "robust_dr".

  Raises:
    ValueError: β outside [0, 1], ε ≤ 0 or α₀ < 0 (checked where concrete), or a
      hyperparameter that is neither a scalar nor a vector. A vector's length is checked
      against K by `init_map` and `fuse_frame`.

  Example:
    >>> rules.robust(beta=[0.1, 0.5, 0.3])   # per-class β for a 3-class map
  """
  if not (regularize or dirichlet):
    raise ValueError(
        "robust() with regularize=False and dirichlet=False is plain Bayesian fusion: "
        "use rules.bayes()")
  check_hparams(beta, eps, alpha0)
  hparams = {
      "beta": base.as_class_leaf(beta, "beta"),
      "eps": base.as_class_leaf(eps, "eps"),
      "alpha0": base.as_class_leaf(alpha0, "alpha0"),
  }
  aggregate = base.check_aggregate(aggregate)
  if not dirichlet:
    return base.FusionRule(
        hparams=hparams, name="robust_r", init=_r_init, observe=_r_observe, update=log_update,
        posterior=log_posterior, confidence=None, requires_var=False, aggregate=aggregate,
        remove=log_remove)
  return base.FusionRule(
      hparams=hparams, name="robust_dr" if regularize else "robust_d", init=_dirichlet_init,
      observe=_dr_observe if regularize else _d_observe, update=_dirichlet_update,
      posterior=log_posterior, confidence=_dirichlet_confidence, requires_var=True,
      aggregate=aggregate)
