"""Quality measures, each written once: the confusion matrix, per-class IoU, the map mIoU and
accuracy on voxels (the columns of the paper's Tables I and II), the per-frame mIoU of a
segmentation on pixels, and the AUROC of a score as a detector.

Two mIoUs go by different names on purpose:
- `mean_iou` (the **map mIoU**): over voxels, averaged over the classes present in the GT;
- `per_frame_miou` (the **per-frame mIoU**): over each frame's pixels, averaged over the
  classes present in that frame's truth or prediction, then over frames (`pixel_miou` is the
  same average over one pooled confusion matrix).

Convention (as in the paper and the authors' evaluation): a voxel is scored where both the map
and the ground truth have it; GT is the majority label of the GT pixels that fell in the voxel.
Voxels only in the map or only in the GT are not scored, and their numbers are reported. The
confusion matrix is K×K over all matched voxels, background included; rows are GT, columns are
predictions. Shape legend: N voxels, K classes.
"""

import numpy as np


def _as_rows(coords: np.ndarray) -> np.ndarray:
  coords = np.ascontiguousarray(np.asarray(coords, np.int32).reshape(-1, 3))
  return coords.view(np.dtype((np.void, 12))).reshape(-1)


def match_voxels(map_coords, gt_coords) -> tuple[np.ndarray, np.ndarray]:
  """Indices of voxels present in both maps.

  Args:
    map_coords: `(N, 3)` int voxel coordinates of the map.
    gt_coords: `(M, 3)` int voxel coordinates of the ground truth (unique).

  Returns:
    `(map_index, gt_index)`, equal-length int arrays: `map_coords[map_index] ==
    gt_coords[gt_index]` row by row.
  """
  _, map_index, gt_index = np.intersect1d(_as_rows(map_coords), _as_rows(gt_coords),
                                          assume_unique=True, return_indices=True)
  return map_index, gt_index


def confusion_matrix(gt_labels, pred_labels, num_classes: int, *, ignore_label=None):
  """`(K, K) int64` counts, rows = GT class, columns = predicted class.

  GT labels equal to `ignore_label` (or outside [0, K)) are left out.
  """
  gt = np.asarray(gt_labels, np.int64).reshape(-1)
  pred = np.asarray(pred_labels, np.int64).reshape(-1)
  if gt.shape != pred.shape:
    raise ValueError(f"gt and pred must have the same length; got {gt.shape} and {pred.shape}")
  keep = (gt >= 0) & (gt < num_classes)
  if ignore_label is not None:
    keep &= gt != ignore_label
  if np.any((pred[keep] < 0) | (pred[keep] >= num_classes)):
    raise ValueError(f"predicted labels must lie in [0, {num_classes})")
  return np.bincount(gt[keep] * num_classes + pred[keep],
                     minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def iou_from_confusion(cm: np.ndarray) -> np.ndarray:
  """Per-class IoU = TP / (TP + FP + FN); NaN for a class absent from both GT and prediction."""
  cm = np.asarray(cm, np.float64)
  tp = np.diag(cm)
  denom = cm.sum(0) + cm.sum(1) - tp
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(denom > 0, tp / np.where(denom > 0, denom, 1), np.nan)


def mean_iou(cm: np.ndarray) -> float:
  """Mean IoU over the classes present in the GT (rows with a voxel)."""
  cm = np.asarray(cm)
  present = cm.sum(1) > 0
  if not np.any(present):
    return float("nan")
  return float(np.mean(np.nan_to_num(iou_from_confusion(cm)[present])))


def pixel_miou(cm: np.ndarray) -> float:
  """Mean IoU over the classes present in the truth *or* the prediction (a segmentation's mIoU;
  NaN when there is none)."""
  iou = iou_from_confusion(cm)
  return float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan")


def per_frame_miou(pred: np.ndarray, labels: np.ndarray, num_classes: int) -> float:
  """Mean over frames of each frame's own `pixel_miou` (the per-frame mIoU of a front end).

  Args:
    pred: `(N, H, W)` int predictions; values are clipped into `[0, K)`.
    labels: `(N, H, W)` int ground truth; values outside `[0, K)` are ignored.
    num_classes: K.

  Returns:
    The average per-frame mIoU; NaN when no frame has a labelled pixel.
  """
  pred, labels = np.asarray(pred), np.asarray(labels)
  if pred.shape != labels.shape or pred.ndim != 3:
    raise ValueError(f"per_frame_miou expects (N, H, W) pred and labels; got {pred.shape}, "
                     f"{labels.shape}")
  values = []
  for p, y in zip(pred, labels):
    y = y.ravel().astype(np.int64)
    p = np.clip(p.ravel().astype(np.int64), 0, num_classes - 1)
    values.append(pixel_miou(confusion_matrix(y, p, num_classes)))
  values = [v for v in values if np.isfinite(v)]
  return float(np.mean(values)) if values else float("nan")


def auroc(scores, positives) -> float:
  """Area under the ROC curve of `scores` as a detector of `positives` (ties count half).

  The probability that a random positive scores higher than a random negative, plus half the
  probability of a tie (Mann–Whitney U / (n_pos · n_neg), average ranks).

  Args:
    scores: float scores of any shape.
    positives: bool of the same shape.

  Returns:
    The AUROC; NaN when either class is empty.
  """
  scores = np.asarray(scores, np.float64).ravel()
  positives = np.asarray(positives, bool).ravel()
  if scores.shape != positives.shape:
    raise ValueError(f"scores {scores.shape} and positives {positives.shape} differ")
  n_pos = int(positives.sum())
  n_neg = positives.size - n_pos
  if n_pos == 0 or n_neg == 0:
    return float("nan")
  _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
  average_rank = np.cumsum(counts) - (counts - 1) / 2.0  # 1-based, ties averaged.
  rank_sum = average_rank[inverse][positives].sum()
  return float((rank_sum - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def auroc_of_samples(positive_scores, negative_scores) -> float:
  """`auroc` given the scores of the positives and of the negatives as two arrays."""
  pos, neg = np.ravel(positive_scores), np.ravel(negative_scores)
  return auroc(np.concatenate([pos, neg]), np.arange(pos.size + neg.size) < pos.size)


def auroc_from_histograms(counts) -> np.ndarray:
  """`auroc` from binned scores: P(positive's bin > negative's bin) + ½ P(same bin).

  Args:
    counts: `(..., 2, B)` counts per bin (bins in increasing score), positives then negatives.

  Returns:
    `(...)` AUROC (NaN without positives or without negatives).
  """
  counts = np.asarray(counts, np.float64)
  pos, neg = counts[..., 0, :], counts[..., 1, :]
  below = np.cumsum(neg, axis=-1) - neg
  num = (pos * (below + 0.5 * neg)).sum(-1)
  den = pos.sum(-1) * neg.sum(-1)
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


# Equal-width bins of the top posterior probability for `calibration_bins` / `ece_from_bins`.
CALIBRATION_BINS = 15


def calibration_bins(posterior, labels, *, num_bins: int = CALIBRATION_BINS) -> np.ndarray:
  """Reliability counts of a map's posteriors against GT labels, for the ECE.

  Args:
    posterior: `(V, K)` normalised class distributions (of the GT voxels the map holds).
    labels: `(V,)` GT labels.
    num_bins: equal-width bins of the top probability over [0, 1].

  Returns:
    `(num_bins, 3) float64`: per bin the number of voxels, how many are labelled right (argmax
    = GT) and the sum of their top probabilities. Counts of several maps add up.
  """
  posterior = np.asarray(posterior, np.float64).reshape(-1, np.shape(posterior)[-1])
  labels = np.asarray(labels).reshape(-1)
  conf = posterior.max(-1) if len(posterior) else np.zeros(0)
  right = (posterior.argmax(-1) == labels) if len(posterior) else np.zeros(0, bool)
  index = np.minimum((conf * num_bins).astype(np.int64), num_bins - 1)
  out = np.zeros((num_bins, 3))
  np.add.at(out[:, 0], index, 1.0)
  np.add.at(out[:, 1], index, right.astype(np.float64))
  np.add.at(out[:, 2], index, conf)
  return out


def ece_from_bins(bins) -> np.ndarray:
  """Expected calibration error `Σ_b (n_b / N)·|acc_b − conf_b|` from `calibration_bins`
  counts `(..., B, 3)`; NaN without voxels."""
  bins = np.asarray(bins, np.float64)
  n, right, conf = bins[..., 0], bins[..., 1], bins[..., 2]
  total = n.sum(-1)
  gap = np.abs(right - conf).sum(-1)          # Σ_b |n_b·acc_b − n_b·conf_b|
  with np.errstate(invalid="ignore", divide="ignore"):
    return np.where(total > 0, gap / np.where(total > 0, total, 1.0), np.nan)


def accuracy(cm: np.ndarray) -> float:
  """Fraction of scored voxels whose predicted label equals the GT label."""
  cm = np.asarray(cm)
  total = cm.sum()
  return float(np.trace(cm) / total) if total else float("nan")


def evaluate_map(voxels: dict, gt: dict, num_classes: int, *, ignore_label=None) -> dict:
  """Scores a map (the dict of `jaxfusion.read_map`) against GT voxel labels.

  Args:
    voxels: dict with `coords (N, 3)` and `labels (N,)`.
    gt: dict with `coords (M, 3)` and `labels (M,)`.
    num_classes: K.
    ignore_label: GT label to leave out (e.g. unmapped ScanNet classes).

  Returns:
    dict with `confusion (K, K)`, `iou (K,)`, `miou`, `accuracy`, `matched` (voxels scored),
    `map_only` (map voxels with no GT), `gt_only` (GT voxels the map does not have).
  """
  map_index, gt_index = match_voxels(voxels["coords"], gt["coords"])
  cm = confusion_matrix(np.asarray(gt["labels"])[gt_index],
                        np.asarray(voxels["labels"])[map_index], num_classes,
                        ignore_label=ignore_label)
  return {
      "confusion": cm,
      "iou": iou_from_confusion(cm),
      "miou": mean_iou(cm),
      "accuracy": accuracy(cm),
      "matched": int(len(map_index)),
      "map_only": int(len(voxels["coords"]) - len(map_index)),
      "gt_only": int(len(gt["coords"]) - len(gt_index)),
  }
