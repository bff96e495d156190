"""The three baselines of docs/equations.md §3.1–§3.3: sum of probabilities, label voting, and
Bayesian fusion."""

import jax
import jax.numpy as jnp

from jaxfusion import numerics
from jaxfusion.rules import base


# --- sum_probs (Fusion++ style): S_i += Σ_j p̄_j,i ---------------------------------------------
def _score_init(num_classes, hparams):
  del hparams
  return {"score": jnp.zeros(num_classes, jnp.float32)}


def _sum_probs_observe(probs, var, hparams):
  del var, hparams
  return base.PixelTerms(sums={"score": probs}, maxes={})


def _score_update(row, obs, hparams):
  del hparams
  return {"score": row["score"] + obs.sums["score"]}


def _score_remove(row, obs, hparams):
  """The inverse of `_score_update`; a score is a sum of non-negative terms, so the rounding of
  the subtraction is clipped at 0."""
  del hparams
  return {"score": jnp.maximum(row["score"] - obs.sums["score"], 0.0)}


def _score_posterior(row):
  return numerics.safe_normalize(row["score"])


def sum_probs(*, aggregate: str = "sum") -> base.FusionRule:
  """Sum of probabilities: `S_i += Σ_j p̄_j,i`, posterior `S / ΣS`, label `argmax S`.

  Unlike the authors' released code (which adds only the winning class's probability) the whole
  vector is added, as Fusion++ averages probabilities (docs/equations.md §6.6).
  """
  return base.FusionRule(
      hparams={}, name="sum_probs", init=_score_init, observe=_sum_probs_observe,
      update=_score_update, posterior=_score_posterior, confidence=None, requires_var=False,
      aggregate=base.check_aggregate(aggregate), remove=_score_remove)


# --- sum_labels (voting): N_i += Σ_j [argmax p̄_j = i] ------------------------------------------
def _sum_labels_observe(probs, var, hparams):
  del var, hparams
  vote = jax.nn.one_hot(jnp.argmax(probs), probs.shape[-1], dtype=jnp.float32)
  return base.PixelTerms(sums={"score": vote}, maxes={})


def sum_labels(*, aggregate: str = "sum") -> base.FusionRule:
  """Label voting: `N_i += Σ_j [argmax p̄_j = i]`, posterior `N / ΣN`, label `argmax N`."""
  return base.FusionRule(
      hparams={}, name="sum_labels", init=_score_init, observe=_sum_labels_observe,
      update=_score_update, posterior=_score_posterior, confidence=None, requires_var=False,
      aggregate=base.check_aggregate(aggregate), remove=_score_remove)


# --- bayes (SemanticFusion, paper eq. 2) --------------------------------------------------------
def log_init(num_classes, hparams):
  """Uniform prior, stored normalised: `log P_0 = −log K`."""
  del hparams
  return {"logp": jnp.full(num_classes, -jnp.log(num_classes), jnp.float32)}


def log_posterior(row):
  return jax.nn.softmax(row["logp"])


def _bayes_observe(probs, var, hparams):
  del var, hparams
  return base.PixelTerms(sums={"loglik": numerics.safe_log(probs)}, maxes={})


def log_update(row, obs, hparams):
  """`log P_t = normalise(log P_{t−1} + Σ_j log p_j)`."""
  del hparams
  return {"logp": numerics.normalize_log(row["logp"] + obs.sums["loglik"])}


def log_remove(row, obs, hparams):
  """The inverse of `log_update`: `log P_{t−1} = normalise(log P_t − Σ_j log p_j)` (the
  normalisation is a shift, so it is undone by the next one)."""
  del hparams
  return {"logp": numerics.normalize_log(row["logp"] - obs.sums["loglik"])}


def bayes(*, aggregate: str = "sum") -> base.FusionRule:
  """Bayesian fusion: `log P_t(i) = log P_{t−1}(i) + Σ_j log p̄_j,i`, then normalise."""
  return base.FusionRule(
      hparams={}, name="bayes", init=log_init, observe=_bayes_observe, update=log_update,
      posterior=log_posterior, confidence=None, requires_var=False,
      aggregate=base.check_aggregate(aggregate), remove=log_remove)
