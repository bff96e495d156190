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


def test_auroc_matches_pairwise_definition_with_ties():
  rng = np.random.default_rng(0)
  scores = rng.integers(0, 5, 200).astype(float)
  positives = rng.random(200) < 0.3
  pos, neg = scores[positives], scores[~positives]
  brute = ((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (
      pos.size * neg.size)
  assert evaluate.auroc(scores, positives) == pytest.approx(brute)
  assert evaluate.auroc(np.arange(4.0), np.array([0, 0, 1, 1], bool)) == 1.0
  assert np.isnan(evaluate.auroc(np.arange(3.0), np.zeros(3, bool)))


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
