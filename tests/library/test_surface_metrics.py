"""Surface quality measures (jaxfusion.surface_metrics) on hand-computed cases and against
brute-force distances."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxfusion import surface_metrics as sm

SQUARE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def _plane_points(z, n=60):
  g = (np.arange(n) + 0.5) / n
  x, y = np.meshgrid(g, g)
  return np.stack([x.ravel(), y.ravel(), np.full(n * n, z)], 1)


def test_identical_surfaces_score_perfectly():
  p = _plane_points(0.0)
  s = sm.reconstruction_scores(p, p)
  assert s["accuracy"] == s["completeness"] == s["chamfer_l1"] == 0.0
  assert s["fscore@0.05"] == s["fscore@0.02"] == 1.0


def test_plane_shifted_by_3cm():
  s = sm.reconstruction_scores(_plane_points(0.03), _plane_points(0.0))
  np.testing.assert_allclose([s["accuracy"], s["completeness"], s["chamfer_l1"]], 0.03,
                             atol=1e-9)
  assert s["fscore@0.05"] == 1.0 and s["fscore@0.02"] == 0.0


def test_empty_prediction():
  s = sm.reconstruction_scores(np.zeros((0, 3)), _plane_points(0.0))
  assert np.isnan(s["accuracy"]) and s["completeness"] == np.inf and s["fscore@0.05"] == 0.0
  points, face, bary = sm.sample_mesh(np.zeros((0, 3)), np.zeros((0, 3), int), count=10,
                                      rng=np.random.default_rng(0))
  assert points.shape == (0, 3)


def test_samples_are_even_and_on_the_mesh():
  rng = np.random.default_rng(0)
  v = np.concatenate([SQUARE_V, SQUARE_V * [2, 1, 1] + [0, 0, 1]])
  f = np.concatenate([SQUARE_F, SQUARE_F + 4])            # areas 1 and 2
  points, face, bary = sm.sample_mesh(v, f, spacing=0.02, rng=rng)
  assert abs(len(points) - 3 / 0.02**2) <= 1
  upper = face >= 2                                       # the second square's faces
  np.testing.assert_allclose(points[upper, 2], 1.0)
  np.testing.assert_allclose(points[~upper, 2], 0.0)
  assert abs(upper.mean() - 2 / 3) < 0.02                 # 4 binomial sigmas at 7 500 draws
  np.testing.assert_allclose(bary.sum(1), 1.0)
  assert np.all((points[~upper, :2] >= 0) & (points[~upper, :2] <= 1))
  np.testing.assert_allclose(sm.vertex_areas(v, f).sum(), 3.0)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_scores_match_brute_force_and_swap_symmetrically(seed):
  rng = np.random.default_rng(seed)
  a, b = rng.normal(size=(40, 3)) * 0.1, rng.normal(size=(55, 3)) * 0.1
  s, t = sm.reconstruction_scores(a, b), sm.reconstruction_scores(b, a)
  d = np.linalg.norm(a[:, None] - b[None], axis=-1)
  np.testing.assert_allclose(s["accuracy"], d.min(1).mean())
  np.testing.assert_allclose(s["completeness"], d.min(0).mean())
  assert s["accuracy"] == pytest.approx(t["completeness"])
  assert s["precision@0.05"] == t["recall@0.05"] and s["fscore@0.05"] == pytest.approx(
      t["fscore@0.05"])


def test_mesh_semantic_scores_weigh_by_area():
  # Two squares side by side: left (area 1) labelled 0, right (area 1) — vertex labels 1 on the
  # right edge; GT says left half class 0, right half class 1.
  v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
  f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
  labels = np.array([0, 0, 0, 0, 1, 1])
  gt_points = np.array([[0.2, 0.5, 0], [1.8, 0.5, 0], [0.9, 0.5, 0]])
  gt_labels = np.array([0, 1, 0])
  s = sm.mesh_semantic_scores(v, f, labels, gt_points, gt_labels, num_classes=2)
  area = sm.vertex_areas(v, f)
  # vertices 1, 2 (x = 1) are nearest to GT (0.9): class 0; vertices 4, 5 class 1.
  np.testing.assert_allclose(s["accuracy"], 1.0)
  np.testing.assert_allclose(s["confusion"].sum(), area.sum())
  labels[4] = 0
  s = sm.mesh_semantic_scores(v, f, labels, gt_points, gt_labels, num_classes=2)
  np.testing.assert_allclose(s["accuracy"], 1 - area[4] / area.sum())
  iou1 = area[5] / (area[5] + area[4])
  iou0 = area[[0, 1, 2, 3]].sum() / area[[0, 1, 2, 3, 4]].sum()
  np.testing.assert_allclose(s["iou"], [iou0, iou1])
  np.testing.assert_allclose(s["vertex_accuracy"], 5 / 6)


def test_unlabelled_vertices_count_as_missed_and_sums_of_padded_confusions_agree():
  v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
  f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
  gt_points = np.array([[0.2, 0.5, 0], [1.8, 0.5, 0], [0.9, 0.5, 0]])
  gt_labels = np.array([0, 1, 0])
  area = sm.vertex_areas(v, f)
  labels = np.array([0, 0, 0, 0, -1, 1])          # vertex 4 (GT class 1) has no label
  s = sm.mesh_semantic_scores(v, f, labels, gt_points, gt_labels, num_classes=2)
  np.testing.assert_allclose(s["unlabelled"], [0.0, area[4]])
  np.testing.assert_allclose(s["iou"], [1.0, area[5] / (area[4] + area[5])])
  np.testing.assert_allclose(s["accuracy"], 1 - area[4] / area.sum())
  # Two "sequences": the padded confusions summed give the IoU of the pooled areas.
  t = sm.mesh_semantic_scores(v, f, np.array([1, 1, 1, 1, 1, 1]), gt_points, gt_labels,
                              num_classes=2)
  pooled = (sm.padded_confusion(s["confusion"], s["unlabelled"])
            + sm.padded_confusion(t["confusion"], t["unlabelled"]))
  iou, miou, acc = sm.iou_from_padded(pooled)
  class0 = area[:4].sum()                        # right in s, predicted 1 in t
  class1 = area[4:].sum()
  tp0, tp1 = class0, area[5] + class1
  np.testing.assert_allclose(iou, [tp0 / (2 * class0), tp1 / (2 * class1 + class0)])
  np.testing.assert_allclose(miou, np.mean(iou))
  np.testing.assert_allclose(acc, (tp0 + tp1) / (2 * area.sum()))
