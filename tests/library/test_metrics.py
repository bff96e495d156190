"""Metrics against hand-computed confusion matrices."""

import math

import numpy as np
import pytest

from jaxfusion import metrics


def test_confusion_iou_miou_accuracy_by_hand():
  gt = [0, 0, 0, 1, 1, 2, 2, 2, 2]
  pred = [0, 0, 1, 1, 2, 2, 2, 2, 0]
  cm = metrics.confusion_matrix(gt, pred, 4)
  np.testing.assert_array_equal(cm, [[2, 1, 0, 0], [0, 1, 1, 0], [1, 0, 3, 0], [0, 0, 0, 0]])
  iou = metrics.iou_from_confusion(cm)
  # class 0: TP 2, FP 1, FN 1 → 2/4; class 1: 1/(1+1+1); class 2: 3/(3+1+1); class 3: absent.
  np.testing.assert_allclose(iou[:3], [0.5, 1 / 3, 0.6])
  assert math.isnan(iou[3])
  assert metrics.mean_iou(cm) == pytest.approx((0.5 + 1 / 3 + 0.6) / 3)
  assert metrics.accuracy(cm) == pytest.approx(6 / 9)


def test_class_predicted_but_absent_from_gt_lowers_nothing_in_miou_but_costs_fp():
  cm = metrics.confusion_matrix([0, 0], [0, 1], 2)
  assert metrics.iou_from_confusion(cm)[1] == 0.0
  assert metrics.mean_iou(cm) == pytest.approx(0.5)   # only class 0 is present in GT


def test_ignore_label_and_bad_predictions():
  cm = metrics.confusion_matrix([0, 255, 1], [0, 1, 1], 2, ignore_label=255)
  np.testing.assert_array_equal(cm, [[1, 0], [0, 1]])
  with pytest.raises(ValueError, match="predicted labels"):
    metrics.confusion_matrix([0], [5], 2)
  with pytest.raises(ValueError, match="same length"):
    metrics.confusion_matrix([0, 1], [0], 2)


def test_evaluate_map_matches_voxels_and_reports_unmatched():
  voxels = {"coords": np.array([[0, 0, 0], [1, 0, 0], [5, 5, 5]], np.int32),
            "labels": np.array([1, 0, 1])}
  gt = {"coords": np.array([[1, 0, 0], [0, 0, 0], [-1, 0, 0], [2, 0, 0]], np.int32),
        "labels": np.array([0, 1, 0, 1])}
  out = metrics.evaluate_map(voxels, gt, 2)
  assert out["matched"] == 2 and out["map_only"] == 1 and out["gt_only"] == 2
  np.testing.assert_array_equal(out["confusion"], [[1, 0], [0, 1]])
  assert out["miou"] == 1.0 and out["accuracy"] == 1.0


def test_auroc_matches_pairwise_definition_with_ties():
  rng = np.random.default_rng(0)
  scores = rng.integers(0, 5, 200).astype(float)
  positives = rng.random(200) < 0.3
  pos, neg = scores[positives], scores[~positives]
  brute = ((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (
      pos.size * neg.size)
  assert metrics.auroc(scores, positives) == pytest.approx(brute)
  assert metrics.auroc_of_samples(pos, neg) == pytest.approx(brute)
  assert metrics.auroc(np.arange(4.0), np.array([0, 0, 1, 1], bool)) == 1.0
  assert np.isnan(metrics.auroc(np.arange(3.0), np.zeros(3, bool)))


def test_auroc_on_a_hand_computed_case_and_from_histograms():
  # Positives score 0.35 and 0.8, negatives 0.1 and 0.4: 3 of the 4 pairs are ordered.
  assert metrics.auroc(np.array([0.1, 0.4, 0.35, 0.8]),
                       np.array([0, 0, 1, 1], bool)) == pytest.approx(0.75)
  assert metrics.auroc(np.array([0.5, 0.5]), np.array([0, 1], bool)) == pytest.approx(0.5)
  # The same four scores binned into [0, 0.3), [0.3, 0.6), [0.6, 1): ties within a bin count ½.
  hist = np.array([[0, 1, 1], [1, 1, 0]])
  assert metrics.auroc_from_histograms(hist) == pytest.approx((1 * 1.5 + 1 * 2) / 4)
  assert np.isnan(metrics.auroc_from_histograms(np.zeros((2, 3))))


def test_per_frame_miou_averages_each_frames_own_miou():
  labels = np.array([[[0, 0], [0, 0]], [[0, 0], [1, 1]]])
  pred = np.zeros_like(labels)
  # Frame 1: only class 0, perfect (1.0). Frame 2: IoU 0.5 for class 0, 0 for class 1.
  assert metrics.per_frame_miou(pred, labels, 2) == pytest.approx((1.0 + 0.25) / 2)
  # The map mIoU of the pooled voxels is another number: over classes present in the GT.
  cm = metrics.confusion_matrix(labels.ravel(), pred.ravel(), 2)
  assert metrics.pixel_miou(cm) == pytest.approx((6 / 8 + 0.0) / 2)
  with pytest.raises(ValueError, match="per_frame_miou"):
    metrics.per_frame_miou(pred[0], labels[0], 2)


def test_calibration_bins_and_ece_by_hand():
  # Two voxels at confidence 0.9 (one right), one at 0.55 (right), K = 2.
  post = np.array([[0.9, 0.1], [0.1, 0.9], [0.55, 0.45]])
  labels = np.array([0, 0, 0])
  bins = metrics.calibration_bins(post, labels, num_bins=10)
  assert bins[9].tolist() == [2.0, 1.0, 1.8] and bins[5].tolist() == [1.0, 1.0, 0.55]
  assert bins.sum(0)[0] == 3
  # ECE = (2/3)·|0.5 − 0.9| + (1/3)·|1 − 0.55|
  assert float(metrics.ece_from_bins(bins)) == pytest.approx(2 / 3 * 0.4 + 1 / 3 * 0.45)
  # Counts of two maps add up; the ECE of a perfectly calibrated map is 0; no voxels: NaN.
  both = metrics.calibration_bins(post[:2], labels[:2], num_bins=10) + metrics.calibration_bins(
      post[2:], labels[2:], num_bins=10)
  np.testing.assert_allclose(both, bins)
  assert float(metrics.ece_from_bins(metrics.calibration_bins(
      np.array([[1.0, 0.0]]), np.array([0])))) == 0.0
  assert np.isnan(metrics.ece_from_bins(np.zeros((15, 3))))
  # A NumPy loop over voxels gives the same ECE on random posteriors.
  rng = np.random.default_rng(0)
  post = rng.dirichlet(np.ones(4), 500)
  labels = rng.integers(0, 4, 500)
  conf, pred = post.max(1), post.argmax(1)
  ece = 0.0
  for b in range(15):
    inside = (conf >= b / 15) & ((conf < (b + 1) / 15) if b < 14 else (conf <= 1))
    if inside.any():
      ece += inside.mean() * abs((pred[inside] == labels[inside]).mean() - conf[inside].mean())
  assert float(metrics.ece_from_bins(metrics.calibration_bins(post, labels))) == pytest.approx(
      ece, abs=1e-9)
