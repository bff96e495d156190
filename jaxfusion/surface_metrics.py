"""Geometry and semantic quality of a mesh against a true surface (the indoor RGB-D convention of
NICE-SLAM and Atlas): both surfaces sampled evenly, nearest neighbours both ways.

- accuracy: mean distance from predicted samples to the nearest GT sample;
- completeness: mean distance from GT samples to the nearest predicted sample;
- Chamfer-L1: (accuracy + completeness) / 2;
- precision@d / recall@d: share of predicted / GT samples within d of the other surface;
  F-score@d their harmonic mean.

Distances are in metres. Shape legend: P vertices, F faces, S samples, G GT samples, K classes.
"""

from typing import Optional

import numpy as np


def _kdtree(points):
  from scipy.spatial import cKDTree   # pylint: disable=import-outside-toplevel
  return cKDTree(np.asarray(points, np.float64))


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """`(F,) float64` triangle areas."""
  v = np.asarray(vertices, np.float64)
  f = np.asarray(faces, np.int64).reshape(-1, 3)
  return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def sample_mesh(vertices: np.ndarray, faces: np.ndarray, *, count: Optional[int] = None,
                spacing: Optional[float] = None, rng: np.random.Generator):
  """Area-weighted even samples of a triangle mesh.

  Args:
    vertices: `(P, 3)` float.
    faces: `(F, 3)` int.
    count: number of samples; or
    spacing: about one sample per `spacing²` of area (metres).
    rng: random generator.

  Returns:
    `(points (S, 3) float64, face_index (S,) int64, barycentric (S, 3) float64)`; empty arrays
    for an empty mesh.
  """
  if (count is None) == (spacing is None):
    raise ValueError("give exactly one of count and spacing")
  area = face_areas(vertices, faces)
  total = float(area.sum())
  if spacing is not None:
    if not spacing > 0:
      raise ValueError(f"spacing must be positive; got {spacing}")
    count = int(round(total / spacing**2))
  if len(area) == 0 or total <= 0 or count <= 0:
    return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3))
  face = rng.choice(len(area), size=count, p=area / total)
  r1, r2 = rng.random(count), rng.random(count)
  s = np.sqrt(r1)
  bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
  v = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)[face]]   # (S, 3, 3)
  return np.einsum("sk,skd->sd", bary, v), face.astype(np.int64), bary


def reconstruction_scores(pred_points: np.ndarray, gt_points: np.ndarray, *,
                          thresholds=(0.05, 0.02)) -> dict:
  """Accuracy, completeness, Chamfer-L1 and precision / recall / F-score at each threshold.

  An empty prediction has accuracy nan, completeness and Chamfer inf, precision, recall and F 0.

  Returns:
    dict with `accuracy`, `completeness`, `chamfer_l1` (metres) and `precision@d`, `recall@d`,
    `fscore@d` (fractions) for every d in `thresholds` (keys formatted with `:g`).
  """
  pred = np.asarray(pred_points, np.float64).reshape(-1, 3)
  gt = np.asarray(gt_points, np.float64).reshape(-1, 3)
  if len(gt) == 0:
    raise ValueError("the GT surface has no samples")
  out = {}
  if len(pred) == 0:
    out.update(accuracy=float("nan"), completeness=float("inf"), chamfer_l1=float("inf"))
    for d in thresholds:
      out.update({f"precision@{d:g}": 0.0, f"recall@{d:g}": 0.0, f"fscore@{d:g}": 0.0})
    return out
  to_gt, _ = _kdtree(gt).query(pred)
  to_pred, _ = _kdtree(pred).query(gt)
  out.update(accuracy=float(to_gt.mean()), completeness=float(to_pred.mean()))
  out["chamfer_l1"] = 0.5 * (out["accuracy"] + out["completeness"])
  for d in thresholds:
    p, r = float(np.mean(to_gt < d)), float(np.mean(to_pred < d))
    out.update({f"precision@{d:g}": p, f"recall@{d:g}": r,
                f"fscore@{d:g}": 2 * p * r / (p + r) if p + r > 0 else 0.0})
  return out


def nearest_points(points: np.ndarray, surface_points: np.ndarray) -> np.ndarray:
  """`(P,) int64` index of the nearest of `surface_points (G, 3)` to each of `points (P, 3)`
  (`mesh_semantic_scores`' `nearest=`, to score several labellings of one mesh)."""
  _, index = _kdtree(surface_points).query(np.asarray(points, np.float64))
  return np.asarray(index, np.int64)


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
  """`(P,) float64` a third of the area of each vertex's faces (they sum to the mesh's area)."""
  area = face_areas(vertices, faces)
  out = np.zeros(len(vertices))
  for k in range(3):
    np.add.at(out, np.asarray(faces, np.int64)[:, k], area / 3.0)
  return out


def mesh_semantic_scores(vertices, faces, vertex_labels, gt_points, gt_labels, *,
                         num_classes: int, ignore_label: Optional[int] = None,
                         nearest: Optional[np.ndarray] = None) -> dict:
  """Each vertex's label against the label of its nearest GT surface sample, weighted by the
  vertex's share of the mesh's area.

  A vertex without a label (−1) counts as wrong (it is in no class's TP). Classes are scored
  when present in the GT or the prediction; mIoU is over classes present in the GT. `nearest`
  `(P,)`: each vertex's nearest GT sample (`nearest_points`), computed when None.

  Returns:
    dict with `confusion (K, K)` (area, rows GT, columns predicted), `unlabelled (K,)` (area
    of vertices without a label, by GT class), `iou (K,)` (nan where the class is in neither),
    `miou`, `accuracy` (area-weighted), and `vertex_accuracy` / `vertex_miou` (each vertex
    counted once). `padded_confusion(confusion, unlabelled)` stacks the first two so that sums
    over sequences give the same IoU (`iou_from_padded`).
  """
  labels = np.asarray(vertex_labels, np.int64)
  gt_labels = np.asarray(gt_labels, np.int64)
  if len(labels) == 0:
    return {"confusion": np.zeros((num_classes, num_classes)),
            "unlabelled": np.zeros(num_classes), "iou": np.full(num_classes, np.nan),
            "miou": float("nan"), "accuracy": float("nan"), "vertex_accuracy": float("nan"),
            "vertex_miou": float("nan")}
  if nearest is None:
    nearest = nearest_points(vertices, gt_points)
  truth = gt_labels[np.asarray(nearest, np.int64)]
  keep = np.ones(len(truth), bool) if ignore_label is None else truth != ignore_label
  keep &= (truth >= 0) & (truth < num_classes)

  def scores(weight):
    confusion = np.zeros((num_classes, num_classes))
    ok = keep & (labels >= 0) & (labels < num_classes)
    np.add.at(confusion, (truth[ok], labels[ok]), weight[ok])
    missed = np.zeros(num_classes)
    np.add.at(missed, truth[keep & ~ok], weight[keep & ~ok])
    iou, miou, accuracy = iou_from_padded(padded_confusion(confusion, missed))
    return confusion, missed, iou, miou, accuracy

  confusion, missed, iou, miou, accuracy = scores(vertex_areas(vertices, faces))
  _, _, _, vertex_miou, vertex_accuracy = scores(np.ones(len(labels)))
  return {"confusion": confusion, "unlabelled": missed, "iou": iou, "miou": miou,
          "accuracy": accuracy, "vertex_accuracy": vertex_accuracy, "vertex_miou": vertex_miou}


def padded_confusion(confusion: np.ndarray, unlabelled: np.ndarray) -> np.ndarray:
  """`(K + 1, K + 1)`: `confusion (K, K)` with a column K for `unlabelled (K,)` (predicted as
  "no label", which is never right) and an empty row K (no GT surface is "no label")."""
  confusion = np.asarray(confusion, np.float64)
  k = confusion.shape[0]
  out = np.zeros((k + 1, k + 1))
  out[:k, :k] = confusion
  out[:k, k] = np.asarray(unlabelled, np.float64)
  return out


def iou_from_padded(padded: np.ndarray) -> tuple:
  """`(iou (K,), miou, accuracy)` of a `padded_confusion`: IoU_c = TP / (GT_c + pred_c − TP)
  (GT_c counts the class's unlabelled area), nan where class c is in neither; mIoU over the
  classes present in the GT; accuracy = ΣTP / Σ GT area."""
  padded = np.asarray(padded, np.float64)
  k = padded.shape[0] - 1
  tp = np.diag(padded)[:k]
  gt, predicted = padded[:k].sum(1), padded[:, :k].sum(0)
  denominator = gt + predicted - tp
  iou = np.where(denominator > 0, tp / np.where(denominator > 0, denominator, 1), np.nan)
  present = gt > 0
  total = gt.sum()
  return (iou, float(np.mean(iou[present])) if present.any() else float("nan"),
          float(tp.sum() / total) if total > 0 else float("nan"))
