"""Bootstrap confidence intervals over independent units (sequences) and paired differences.

The study's statistics are functions of *sums over units*: a method's confusion matrix over a
set of sequences is the sum of the per-sequence matrices, and mIoU / accuracy are computed from
that sum (as the demo does); a share of voxels is a ratio of two sums. So the bootstrap here
resamples units with replacement and re-evaluates the statistic on the resampled sums:

    counts[b, s] = how often unit s is drawn in resample b   (multinomial, S draws of 1/S)
    sums[b]      = Σ_s counts[b, s] · data[s]
    samples[b]   = statistic(sums[b])

The interval is the percentile interval of `samples` (the α/2 and 1 − α/2 quantiles). A
*paired* difference evaluates both methods on the same resample (the same `counts`), so the
variation shared by the two (an easy or hard sequence) cancels, as it should when both methods
fuse the same observations.

Shape legend: S units, B bootstrap resamples, K classes.
"""

from typing import Callable, NamedTuple, Optional

import numpy as np

DEFAULT_RESAMPLES = 2000
DEFAULT_CONFIDENCE = 0.95


class Interval(NamedTuple):
  """A point estimate with a bootstrap interval.

  Attributes:
    estimate: the statistic on the full data (all units once).
    low: lower end of the percentile interval.
    high: upper end of the percentile interval.
  """
  estimate: float
  low: float
  high: float


def resample_counts(num_units: int, num_resamples: int = DEFAULT_RESAMPLES, *,
                    seed: int = 0) -> np.ndarray:
  """How often each unit appears in each bootstrap resample.

  Args:
    num_units: S ≥ 1 units (sequences).
    num_resamples: B ≥ 1 resamples.
    seed: seed of NumPy's generator (the same seed gives the same resamples).

  Returns:
    `(B, S) int64`, each row a multinomial draw of S units with equal probabilities (row sums
    are S).
  """
  if int(num_units) < 1:
    raise ValueError(f"num_units must be at least 1; got {num_units}")
  if int(num_resamples) < 1:
    raise ValueError(f"num_resamples must be at least 1; got {num_resamples}")
  rng = np.random.default_rng([int(seed), 77031])
  return rng.multinomial(int(num_units), np.full(int(num_units), 1.0 / int(num_units)),
                         size=int(num_resamples)).astype(np.int64)


def resampled_sums(data, counts: np.ndarray) -> np.ndarray:
  """Sums of per-unit data over each resample.

  Args:
    data: `(S, ...)` per-unit additive quantities (e.g. confusion matrices `(S, K, K)`).
    counts: `(B, S)` from `resample_counts`.

  Returns:
    `(B, ...) float64`: `Σ_s counts[b, s] · data[s]`.
  """
  data = np.asarray(data, np.float64)
  counts = np.asarray(counts)
  if counts.ndim != 2 or data.ndim < 1 or counts.shape[1] != data.shape[0]:
    raise ValueError(f"counts must be (B, S) and data (S, ...); got {counts.shape} and "
                     f"{data.shape}")
  flat = counts.astype(np.float64) @ data.reshape(data.shape[0], -1)
  return flat.reshape((counts.shape[0],) + data.shape[1:])


def percentile_interval(samples, *, confidence: float = DEFAULT_CONFIDENCE) -> tuple:
  """The `(low, high)` percentile interval of bootstrap samples (NaN samples ignored)."""
  _check_confidence(confidence)
  samples = np.asarray(samples, np.float64).reshape(-1)
  finite = samples[np.isfinite(samples)]
  if finite.size == 0:
    return float("nan"), float("nan")
  tail = 100.0 * (1.0 - confidence) / 2.0
  low, high = np.percentile(finite, [tail, 100.0 - tail])
  return float(low), float(high)


def bootstrap(data, statistic: Callable, *, counts: Optional[np.ndarray] = None,
              num_resamples: int = DEFAULT_RESAMPLES, confidence: float = DEFAULT_CONFIDENCE,
              seed: int = 0) -> Interval:
  """Percentile bootstrap interval of a statistic of sums over units.

  Args:
    data: `(S, ...)` per-unit additive quantities.
    statistic: vectorised map from sums `(B, ...)` to values `(B,)` (e.g. `miou` for confusion
      matrices, `lambda s: s[:, 0] / s[:, 1]` for a ratio, `lambda s: s / S` for a mean).
    counts: `(B, S)` resample counts to reuse (to pair with other statistics); default: drawn
      with `resample_counts(S, num_resamples, seed=seed)`.
    num_resamples: B when `counts` is not given.
    confidence: coverage of the interval in (0, 1).
    seed: seed when `counts` is not given.

  Returns:
    `Interval(estimate, low, high)`; the estimate is the statistic of the plain sum.
  """
  data = np.asarray(data, np.float64)
  counts = _counts_for(data, counts, num_resamples, seed)
  estimate = float(np.asarray(statistic(data.sum(0)[None]))[0])
  low, high = percentile_interval(statistic(resampled_sums(data, counts)),
                                  confidence=confidence)
  return Interval(estimate, low, high)


def paired_difference(data_a, data_b, statistic: Callable, *,
                      counts: Optional[np.ndarray] = None,
                      num_resamples: int = DEFAULT_RESAMPLES,
                      confidence: float = DEFAULT_CONFIDENCE, seed: int = 0) -> Interval:
  """Paired bootstrap interval of `statistic(A) − statistic(B)` over the same units.

  Both methods are evaluated on the same resamples, so the interval reflects the variation of
  the *difference* across units, not the (larger) variation of each method.

  Args:
    data_a: `(S, ...)` per-unit data of method A.
    data_b: `(S, ...)` per-unit data of method B, the same units in the same order.
    statistic: as in `bootstrap`.
    counts: `(B, S)` resample counts to reuse; default drawn from `seed`.
    num_resamples: B when `counts` is not given.
    confidence: coverage in (0, 1).
    seed: seed when `counts` is not given.

  Returns:
    `Interval` of the difference A − B (identical data give exactly 0, 0, 0).
  """
  data_a = np.asarray(data_a, np.float64)
  data_b = np.asarray(data_b, np.float64)
  if data_a.shape != data_b.shape:
    raise ValueError(f"paired data must have the same shape; got {data_a.shape} and "
                     f"{data_b.shape}")
  counts = _counts_for(data_a, counts, num_resamples, seed)
  estimate = float(np.asarray(statistic(data_a.sum(0)[None]))[0]
                   - np.asarray(statistic(data_b.sum(0)[None]))[0])
  diff = statistic(resampled_sums(data_a, counts)) - statistic(resampled_sums(data_b, counts))
  low, high = percentile_interval(diff, confidence=confidence)
  return Interval(estimate, low, high)


def headroom_share(data_a, data_base, data_bound, statistic: Callable, *,
                   counts: Optional[np.ndarray] = None,
                   num_resamples: int = DEFAULT_RESAMPLES,
                   confidence: float = DEFAULT_CONFIDENCE, seed: int = 0) -> Interval:
  """Paired bootstrap interval of the share of a bound's gain that method A recovers.

  The share is `(statistic(A) − statistic(base)) / (statistic(bound) − statistic(base))`, all
  three evaluated on the same resamples (e.g. a rule's mIoU gain over Bayes as a share of the
  oracle's). Resamples where the bound does not beat the base give NaN and are left out.

  Args:
    data_a: `(S, ...)` per-unit data of method A.
    data_base: `(S, ...)` of the base method, the same units in the same order.
    data_bound: `(S, ...)` of the bound.
    statistic, counts, num_resamples, confidence, seed: as in `paired_difference`.

  Returns:
    `Interval` of the share (1: A gains what the bound gains; 0: what the base does; NaN where
    the bound does not beat the base on the full data).
  """
  data = [np.asarray(d, np.float64) for d in (data_a, data_base, data_bound)]
  if len({d.shape for d in data}) != 1:
    raise ValueError(f"paired data must have the same shape; got {[d.shape for d in data]}")
  counts = _counts_for(data[0], counts, num_resamples, seed)

  def share(a, base, bound):
    gain = bound - base
    with np.errstate(invalid="ignore", divide="ignore"):
      return np.where(gain > 0, (a - base) / np.where(gain > 0, gain, 1.0), np.nan)

  full = [np.asarray(statistic(d.sum(0)[None]))[0] for d in data]
  samples = share(*(statistic(resampled_sums(d, counts)) for d in data))
  low, high = percentile_interval(samples, confidence=confidence)
  return Interval(float(share(*full)), low, high)


def miou(confusions) -> np.ndarray:
  """Mean IoU of a stack of confusion matrices, as `metrics.mean_iou` for each.

  Args:
    confusions: `(..., K, K)` counts, rows = GT class, columns = prediction.

  Returns:
    `(...) float64`: the mean over classes present in the GT (rows with a count) of
    TP / (TP + FP + FN); NaN where no class is present.
  """
  cm = np.asarray(confusions, np.float64)
  if cm.ndim < 2 or cm.shape[-1] != cm.shape[-2]:
    raise ValueError(f"confusions must be (..., K, K); got shape {cm.shape}")
  tp = np.diagonal(cm, axis1=-2, axis2=-1)
  rows, cols = cm.sum(-1), cm.sum(-2)
  denom = rows + cols - tp
  iou = np.where(denom > 0, tp / np.where(denom > 0, denom, 1.0), 0.0)
  present = rows > 0
  num_present = present.sum(-1)
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(num_present > 0, (iou * present).sum(-1) / num_present, np.nan)


def accuracy(confusions) -> np.ndarray:
  """Share of correct voxels `trace / total` of a stack `(..., K, K)`; NaN where empty."""
  cm = np.asarray(confusions, np.float64)
  if cm.ndim < 2 or cm.shape[-1] != cm.shape[-2]:
    raise ValueError(f"confusions must be (..., K, K); got shape {cm.shape}")
  total = cm.sum((-2, -1))
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(total > 0, np.trace(cm, axis1=-2, axis2=-1) / np.where(total > 0, total, 1),
                    np.nan)


def ratio(sums) -> np.ndarray:
  """`sums[..., 0] / sums[..., 1]` (NaN where the denominator is 0): a share of two sums."""
  sums = np.asarray(sums, np.float64)
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(sums[..., 1] > 0, sums[..., 0] / np.where(sums[..., 1] > 0, sums[..., 1], 1),
                    np.nan)


def _counts_for(data, counts, num_resamples, seed):
  if data.ndim < 1 or data.shape[0] < 1:
    raise ValueError(f"data must have a leading unit axis with at least one unit; got shape "
                     f"{data.shape}")
  if counts is None:
    return resample_counts(data.shape[0], num_resamples, seed=seed)
  counts = np.asarray(counts)
  if counts.ndim != 2 or counts.shape[1] != data.shape[0]:
    raise ValueError(f"counts must be (B, {data.shape[0]}); got shape {counts.shape}")
  return counts


def _check_confidence(confidence):
  if not 0.0 < float(confidence) < 1.0:
    raise ValueError(f"confidence must lie in (0, 1); got {confidence}")
