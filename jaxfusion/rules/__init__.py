"""Fusion rules: each a `FusionRule` of pure per-voxel kernels with hyperparameters as leaves.

    rules.sum_probs()   rules.sum_labels()   rules.bayes()
    rules.robust(beta=0.3, eps=1e-12, regularize=True, dirichlet=True)   # D+R
    rules.robust(beta=[0.1, 0.4, …])   # per-class β (and ε, α₀): one value per class, (K,)
    rules.learned(params)               # weighted, regularised Bayes with learned weights
    rules.learned(params, context=("depth", "incidence", ...))   # … reading per-pixel context
    rules.glfs(table)                   # GLFS: a weight per class × depth bin × incidence bin
    rules.family(params)                # one unbounded log-weight of terms: all of the above
"""

from jaxfusion.rules.base import AGGREGATIONS
from jaxfusion.rules.base import FusionRule
from jaxfusion.rules.base import PixelTerms
from jaxfusion.rules.base import VoxelObservation
from jaxfusion.rules.base import stack
from jaxfusion.rules.baselines import bayes
from jaxfusion.rules.baselines import sum_labels
from jaxfusion.rules.baselines import sum_probs
from jaxfusion.rules import family as family_lib
from jaxfusion.rules import glfs as glfs_lib
from jaxfusion.rules.family import family
from jaxfusion.rules.glfs import glfs
from jaxfusion.rules.learned import learned
from jaxfusion.rules.learned import special_case as learned_special_case
from jaxfusion.rules.robust import DEFAULT_ALPHA0
from jaxfusion.rules.robust import robust

# The six rules of the paper, in its table order: name -> (display name, factory).
PAPER_RULES = {
    "sum_probs": ("Sum probs", sum_probs),
    "sum_labels": ("Sum labels", sum_labels),
    "bayes": ("Bayesian", bayes),
    "robust_r": ("R", lambda **kw: robust(regularize=True, dirichlet=False, **kw)),
    "robust_d": ("D", lambda **kw: robust(regularize=False, dirichlet=True, **kw)),
    "robust_dr": ("D+R", lambda **kw: robust(regularize=True, dirichlet=True, **kw)),
}


def by_name(name: str, **hparams) -> FusionRule:
  """Builds one of the six paper rules by name (`sum_probs`, …, `robust_dr`; also R, D, D+R).

  Keyword hyperparameters (beta, eps, alpha0, aggregate) are passed to the factory.
  """
  aliases = {display.lower(): key for key, (display, _) in PAPER_RULES.items()}
  key = aliases.get(name.lower(), name.lower())
  if key not in PAPER_RULES:
    names = ", ".join(list(PAPER_RULES) + ["R", "D", "D+R"])
    raise ValueError(f"unknown rule {name!r}; choose one of: {names}")
  factory = PAPER_RULES[key][1]
  if key in ("sum_probs", "sum_labels", "bayes"):
    unknown = set(hparams) - {"aggregate"}
    if unknown:
      raise ValueError(f"rule {key!r} takes no hyperparameters {sorted(unknown)}")
  return factory(**hparams)


def display_name(rule: FusionRule) -> str:
  """The paper's name of a rule ("Sum probs", "Bayesian", "D+R", …)."""
  names = {"learned": "Learned", "glfs": "GLFS", "family": "Family"}
  return PAPER_RULES.get(rule.name, (names.get(rule.name, rule.name), None))[0]


__all__ = sorted([
    "AGGREGATIONS", "DEFAULT_ALPHA0", "FusionRule", "PAPER_RULES", "PixelTerms",
    "VoxelObservation", "bayes", "by_name", "display_name", "family", "family_lib", "glfs",
    "glfs_lib", "learned",
    "learned_special_case",
    "robust", "stack",
    "sum_labels",
    "sum_probs",
])
