"""The robust rules of the paper: regularisation R (eq. 6), Dirichlet weighting D (eqs. 7–9),
and both together, D+R.

- R:   Bayes on `p̃ = (1−β) p̄ + β/K`.
- D:   `α_j,i = −log(var_j,i + ε)`, `ᾱ_t,i = max(ᾱ_{t−1,i}, max_j α_j,i)` (running max including
       frame t — the paper's "τ < t" would leave ᾱ_1 undefined), and
       `log P_t(i) = (ᾱ_{t−1,i}/ᾱ_t,i)·log P_{t−1}(i) + Σ_j (α_j,i/ᾱ_t,i)·log p̄_j,i`, normalised.
       `ᾱ_0 = α₀`, default `−log(1e-3)` as the authors' released code starts every voxel's
       variance at 1e-3; `α₀ = 0` is the literal reading of the equations.
- D+R: D on p̃.
Variances are clipped to [0, 0.25] (the range of a variance of probabilities), so α ≥
−log(0.25+ε) > 0 and ᾱ > 0 after one hit. The sum over j is taken per frame, which makes the
update independent of the order of pixels within a frame (the released C++ code fuses pixels one
at a time and is order-dependent — a deliberate difference, see SPEC.md).
"""

import math

import jax
import jax.numpy as jnp

from jaxfusion import numerics
from jaxfusion.rules import base
from jaxfusion.rules.baselines import log_init, log_posterior, log_update

DEFAULT_BETA = 0.3
DEFAULT_EPS = 1e-12
DEFAULT_ALPHA0 = -math.log(1e-3)


def regularize(probs, beta):
  """`p̃ = (1−β) p + β/K` for a `(K,)` distribution."""
  return (1.0 - beta) * probs + beta / probs.shape[-1]


def concentration(var, eps):
  """`α = −log(clip(var, 0, 0.25) + ε)` per class."""
  return -jnp.log(jnp.clip(var, 0.0, 0.25) + eps)


def _r_observe(probs, var, hparams):
  del var
  return base.PixelTerms(
      sums={"loglik": numerics.safe_log(regularize(probs, hparams["beta"]))}, maxes={})


def _dirichlet_terms(probs_for_log, var, hparams):
  alpha = concentration(var, hparams["eps"])
  return base.PixelTerms(
      sums={"wloglik": alpha * numerics.safe_log(probs_for_log)}, maxes={"alpha": alpha})


def _d_observe(probs, var, hparams):
  return _dirichlet_terms(probs, var, hparams)


def _dr_observe(probs, var, hparams):
  return _dirichlet_terms(regularize(probs, hparams["beta"]), var, hparams)


def _dirichlet_init(num_classes, hparams):
  row = log_init(num_classes, hparams)
  row["alpha_bar"] = jnp.full(num_classes, hparams["alpha0"], jnp.float32)
  return row


def _dirichlet_update(row, obs, hparams):
  del hparams
  alpha_prev = row["alpha_bar"]
  alpha_bar = jnp.maximum(alpha_prev, obs.maxes["alpha"])
  # ᾱ_t > 0 for any voxel with a pixel; the guard only keeps untouched lanes finite.
  safe = jnp.where(alpha_bar > 0, alpha_bar, 1.0)
  logp = (alpha_prev / safe) * row["logp"] + obs.sums["wloglik"] / safe
  return {"logp": numerics.normalize_log(logp), "alpha_bar": alpha_bar}


def _dirichlet_confidence(row):
  return row["alpha_bar"]


def _check_hparams(beta, eps, alpha0):
  if base.is_concrete(beta) and not 0.0 <= float(beta) <= 1.0:
    raise ValueError(f"beta must lie in [0, 1]; got {float(beta)}")
  if base.is_concrete(eps) and not (math.isfinite(float(eps)) and float(eps) > 0):
    raise ValueError(f"eps must be a positive finite number; got {float(eps)}")
  if base.is_concrete(alpha0) and not (math.isfinite(float(alpha0)) and float(alpha0) >= 0):
    raise ValueError(f"alpha0 must be a non-negative finite number; got {float(alpha0)}")


def robust(*, beta=DEFAULT_BETA, eps=DEFAULT_EPS, regularize=True, dirichlet=True,
           alpha0=DEFAULT_ALPHA0, aggregate: str = "sum") -> base.FusionRule:
  """The paper's robust fusion: R (`dirichlet=False`), D (`regularize=False`) or D+R (both).

  Args:
    beta: regularisation weight β ∈ [0, 1] (a traced leaf; used by R and D+R).
    eps: ε > 0 added to variances before the log (a traced leaf; used by D and D+R).
    regularize: apply `p̃ = (1−β) p̄ + β/K`.
    dirichlet: weight observations by their concentration `α = −log(var + ε)`; needs
      `Frame.var`.
    alpha0: prior concentration ᾱ₀ ≥ 0 (a traced leaf; used by D and D+R).
    aggregate: "sum" (the paper's Σ_j over a voxel's pixels) or "mean" (one observation per
      voxel per frame: mean of the weighted log-likelihoods, max of α).

  Returns:
    A FusionRule named "robust_r", "robust_d" or "robust_dr".
  """
  if not (regularize or dirichlet):
    raise ValueError(
        "robust() with regularize=False and dirichlet=False is plain Bayesian fusion: "
        "use rules.bayes()")
  _check_hparams(beta, eps, alpha0)
  hparams = {
      "beta": base.as_leaf(beta, "beta"),
      "eps": base.as_leaf(eps, "eps"),
      "alpha0": base.as_leaf(alpha0, "alpha0"),
  }
  aggregate = base.check_aggregate(aggregate)
  if not dirichlet:
    return base.FusionRule(
        hparams=hparams, name="robust_r", init=log_init, observe=_r_observe, update=log_update,
        posterior=log_posterior, confidence=None, requires_var=False, aggregate=aggregate)
  return base.FusionRule(
      hparams=hparams, name="robust_dr" if regularize else "robust_d", init=_dirichlet_init,
      observe=_dr_observe if regularize else _d_observe, update=_dirichlet_update,
      posterior=log_posterior, confidence=_dirichlet_confidence, requires_var=True,
      aggregate=aggregate)
