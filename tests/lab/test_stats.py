"""The bootstrap against known answers, and the vectorised mIoU / accuracy against metrics."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jaxfusion import metrics
from jaxfusion.lab import stats


def test_interval_of_a_mean_matches_the_normal_theory_interval():
  # For the mean of n normal samples, the bootstrap percentile interval approaches
  # mean ± 1.96 · s / sqrt(n) (s with ddof = 0: the bootstrap's plug-in variance).
  rng = np.random.default_rng(3)
  n = 400
  x = rng.normal(2.0, 1.5, n)
  ci = stats.bootstrap(x, lambda s: s / n, num_resamples=4000, seed=1)
  half = 1.959964 * x.std() / np.sqrt(n)
  assert ci.estimate == pytest.approx(x.mean(), abs=1e-12)
  assert ci.low == pytest.approx(x.mean() - half, abs=0.12 * half)
  assert ci.high == pytest.approx(x.mean() + half, abs=0.12 * half)


def test_coverage_of_the_true_mean_is_near_nominal():
  rng = np.random.default_rng(0)
  covered = 0
  trials = 200
  for t in range(trials):
    x = rng.normal(0.0, 1.0, 60)
    ci = stats.bootstrap(x, lambda s: s / 60, num_resamples=500, seed=t)
    covered += ci.low <= 0.0 <= ci.high
  # Percentile intervals of a mean under-cover slightly at n = 60; binomial sd ≈ 1.6 %.
  assert 0.88 <= covered / trials <= 0.99


def test_constant_data_give_a_zero_width_interval():
  cm = np.tile(np.array([[5, 1], [2, 7]]), (6, 1, 1))   # every sequence the same
  ci = stats.bootstrap(cm, stats.miou, num_resamples=300)
  assert ci.low == ci.high == pytest.approx(ci.estimate)
  assert ci.estimate == pytest.approx(metrics.mean_iou(cm.sum(0)))


def test_paired_difference_of_identical_data_is_exactly_zero():
  rng = np.random.default_rng(1)
  cm = rng.integers(0, 50, (9, 4, 4))
  ci = stats.paired_difference(cm, cm.copy(), stats.miou, num_resamples=300)
  assert (ci.estimate, ci.low, ci.high) == (0.0, 0.0, 0.0)


def test_paired_interval_is_narrower_than_the_unpaired_spread():
  # A shares B's large per-unit variation plus a small constant gain: the paired interval of
  # A − B sits tightly around the gain although each method alone varies a lot.
  rng = np.random.default_rng(2)
  b = rng.normal(10.0, 5.0, 40)
  a = b + 0.5 + rng.normal(0.0, 0.05, 40)
  mean = lambda s: s / 40
  diff = stats.paired_difference(a, b, mean, seed=4)
  alone = stats.bootstrap(b, mean, seed=4)
  assert diff.low > 0.4 and diff.high < 0.6
  assert (diff.high - diff.low) < 0.1 * (alone.high - alone.low)


def test_resample_counts_are_multinomial_rows():
  counts = stats.resample_counts(7, 50, seed=3)
  assert counts.shape == (50, 7) and np.all(counts.sum(1) == 7) and counts.min() >= 0
  np.testing.assert_array_equal(counts, stats.resample_counts(7, 50, seed=3))


def test_resampled_sums_against_a_loop():
  rng = np.random.default_rng(5)
  data = rng.integers(0, 9, (5, 3, 3))
  counts = stats.resample_counts(5, 4, seed=0)
  sums = stats.resampled_sums(data, counts)
  for b in range(4):
    ref = sum(counts[b, s] * data[s] for s in range(5))
    np.testing.assert_array_equal(sums[b], ref)


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 5), st.integers(0, 2**31 - 1))
def test_vectorised_miou_and_accuracy_equal_metrics(k, seed):
  rng = np.random.default_rng(seed)
  cms = rng.integers(0, 6, (3, k, k)) * (rng.uniform(size=(3, k, 1)) < 0.7)  # absent GT rows
  got_miou, got_acc = stats.miou(cms), stats.accuracy(cms)
  for i, cm in enumerate(cms):
    np.testing.assert_allclose(got_miou[i], metrics.mean_iou(cm), equal_nan=True)
    np.testing.assert_allclose(got_acc[i], metrics.accuracy(cm), equal_nan=True)


def test_ratio_and_bad_input():
  np.testing.assert_allclose(stats.ratio(np.array([[1.0, 4.0], [0.0, 0.0]])), [0.25, np.nan])
  with pytest.raises(ValueError, match="confidence"):
    stats.percentile_interval(np.ones(3), confidence=1.5)
  with pytest.raises(ValueError, match="same shape"):
    stats.paired_difference(np.ones((3, 2)), np.ones((4, 2)), stats.ratio)
  with pytest.raises(ValueError, match="counts must be"):
    stats.bootstrap(np.ones(3), lambda s: s, counts=np.ones((5, 4), int))
  with pytest.raises(ValueError, match="num_units"):
    stats.resample_counts(0)


def test_headroom_share_by_hand_and_against_a_loop():
  # Three units of (correct, total) sums under `ratio`: base 50 %, bound 90 %, A 60 % over all
  # units, so A gains a quarter of what the bound gains.
  base = np.array([[5, 10], [10, 20], [10, 20]])
  bound = np.array([[9, 10], [18, 20], [18, 20]])
  a = np.array([[6, 10], [12, 20], [12, 20]])
  ci = stats.headroom_share(a, base, bound, stats.ratio, num_resamples=200)
  assert ci.estimate == pytest.approx(0.25)
  assert ci.low == pytest.approx(0.25) and ci.high == pytest.approx(0.25)  # the same in every unit
  # Unequal units: each resample's share from its own sums, as a loop computes it.
  rng = np.random.default_rng(3)
  base, bound, a = (np.stack([rng.integers(1, 9, 7), np.full(7, 10)], -1) for _ in range(3))
  bound = bound + np.stack([np.full(7, 10), np.full(7, 10)], -1)   # bound > base everywhere
  counts = stats.resample_counts(7, 100, seed=1)
  loop = []
  for c in counts:
    s = [(c[:, None] * d).sum(0) for d in (a, base, bound)]
    r = [x[0] / x[1] for x in s]
    loop.append((r[0] - r[1]) / (r[2] - r[1]))
  ci = stats.headroom_share(a, base, bound, stats.ratio, counts=counts)
  lo, hi = np.percentile(loop, [2.5, 97.5])
  assert ci.low == pytest.approx(lo) and ci.high == pytest.approx(hi)
  # No headroom: NaN, not a division by zero.
  assert np.isnan(stats.headroom_share(a, base, base, stats.ratio, num_resamples=20).estimate)
  with pytest.raises(ValueError, match="same shape"):
    stats.headroom_share(a, base, bound[:3], stats.ratio)
