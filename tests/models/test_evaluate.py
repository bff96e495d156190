"""Metrics: confusion/IoU and the AUROC of uncertainty as an error detector."""

import numpy as np
import pytest

from models import evaluate


def test_confusion_and_metrics_on_a_known_case():
  labels = np.array([0, 0, 1, 1, 2, -1])
  pred = np.array([0, 1, 1, 1, 0, 2])
  conf = evaluate.confusion_matrix(pred, labels, 3)
  assert conf.sum() == 5  # the -1 pixel is ignored
  m = evaluate.segmentation_metrics(conf)
  assert m["pixel_accuracy"] == pytest.approx(3 / 5)
  np.testing.assert_allclose(m["iou"], [1 / 3, 2 / 3, 0.0])
  assert m["miou"] == pytest.approx(1 / 3)




def test_uncertainty_report_detects_errors_with_higher_variance():
  rng = np.random.default_rng(1)
  labels = rng.integers(0, 3, (10, 10))
  mean = np.eye(3)[labels] * 0.8 + 0.2 / 3
  wrong = rng.random((10, 10)) < 0.3
  mean[wrong] = np.roll(mean[wrong], 1, axis=-1)
  var = np.where(wrong[..., None], 0.05, 0.001) * np.ones(3)
  report = evaluate.uncertainty_report(mean, var, labels)
  assert report["error_rate"] == pytest.approx(wrong.mean())
  assert report["auroc_var_sum"] == pytest.approx(1.0)
  assert report["mean_var_sum_wrong"] > report["mean_var_sum_right"]


def _four_pixels():
  """Confidences 0.9 (right), 0.85 (wrong), 0.7 (wrong), 0.6 (right), plus one unlabelled."""
  probs = np.array([[0.9, 0.1], [0.85, 0.15], [0.3, 0.7], [0.6, 0.4], [0.99, 0.01]])
  labels = np.array([0, 1, 0, 0, -1])
  return probs, labels




def test_ece_on_hand_computed_cases():
  probs, labels = _four_pixels()
  # 4 bins: (0.75, 1] holds 0.9 (right) and 0.85 (wrong): |0.5 - 0.875| = 0.375;
  # (0.5, 0.75] holds 0.7 (wrong) and 0.6 (right): |0.5 - 0.65| = 0.15. Each bin weighs 1/2.
  assert evaluate.expected_calibration_error(probs, labels, num_bins=4) == pytest.approx(
      0.5 * 0.375 + 0.5 * 0.15)
  # One bin: |accuracy 0.5 - mean confidence 0.7625|.
  assert evaluate.expected_calibration_error(probs, labels, num_bins=1) == pytest.approx(
      0.2625)
  # Confidence 0.5, right half the time: perfectly calibrated.
  tie = np.full((2, 2), 0.5)
  assert evaluate.expected_calibration_error(tie, np.array([0, 1])) == pytest.approx(0.0)
  assert np.isnan(evaluate.expected_calibration_error(tie, np.array([-1, -1])))
  with pytest.raises(ValueError, match="num_bins"):
    evaluate.expected_calibration_error(probs, labels, num_bins=0)


def test_ece_matches_a_per_pixel_loop():
  rng = np.random.default_rng(3)
  logits = rng.normal(size=(300, 4)) * 2
  probs = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
  labels = rng.integers(0, 4, 300)
  bins = 10
  total, hits, conf_sum = np.zeros(bins), np.zeros(bins), np.zeros(bins)
  for p, y in zip(probs, labels):
    c = p.max()
    b = min(max(int(np.ceil(c * bins)) - 1, 0), bins - 1)
    total[b] += 1
    hits[b] += float(np.argmax(p) == y)
    conf_sum[b] += c
  nonempty = total > 0
  expected = np.sum(total[nonempty] / 300 * np.abs(
      hits[nonempty] / total[nonempty] - conf_sum[nonempty] / total[nonempty]))
  assert evaluate.expected_calibration_error(probs, labels, num_bins=bins) == pytest.approx(
      expected)


def test_calibration_report_on_a_hand_computed_case():
  probs, labels = _four_pixels()
  report = evaluate.calibration_report(probs, labels, num_bins=4, high=0.8)
  assert report["mean_maxprob_wrong"] == pytest.approx((0.85 + 0.7) / 2)
  assert report["mean_maxprob_right"] == pytest.approx((0.9 + 0.6) / 2)
  assert report["share_errors_above_high"] == pytest.approx(0.5)  # 0.85 yes, 0.7 no
  assert report["ece"] == pytest.approx(0.2625)


def test_alpha_report_quartiles_of_the_predicted_class():
  # Predicted class 0 everywhere; its variance is e^-2, e^-4, e^-6 on the right pixels and
  # 0.5 (clipped to 0.25 as in the robust rules) on the wrong one.
  mean = np.tile([0.8, 0.2], (4, 1))
  var = np.array([[np.exp(-2.0), 1.0], [np.exp(-4.0), 1.0], [np.exp(-6.0), 1.0], [0.5, 0.0]])
  labels = np.array([0, 0, 0, 1])
  report = evaluate.alpha_report(mean, var, labels)
  assert report["alpha_right_q25"] == pytest.approx(3.0)
  assert report["alpha_right_median"] == pytest.approx(4.0)
  assert report["alpha_right_q75"] == pytest.approx(5.0)
  assert report["alpha_wrong_median"] == pytest.approx(np.log(4.0))
  assert report["alpha_median_ratio"] == pytest.approx(4.0 / np.log(4.0))
