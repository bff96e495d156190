"""Segmentation accuracy and the quality of the epistemic uncertainty.

`python -m models.evaluate` loads a checkpoint (the shipped one by default), renders held-out
views of the training domain and of the shifted test domain, and reports pixel accuracy and
mIoU (deterministic and MC-mean predictions) and how well the MC-dropout variance detects the
network's errors: the AUROC of the per-pixel variance as a score for "this pixel is
misclassified" (0.5 is chance, 1 is perfect), and the mean variance on wrong versus right
pixels. Calibration, for the MC mean and for the dropout-off pass: expected calibration error
(ECE, 15 bins of the max-probability), the mean max-probability on wrong and on right pixels,
and the share of errors made with max-probability above 0.9; and the quartiles of the robust
rules' Dirichlet weight α = −log(var of the predicted class) on right and on wrong pixels.
mIoU is given pooled over all pixels (`*_miou`, `metrics.pixel_miou`) and as the per-frame
mIoU (`*_frame_miou`, `metrics.per_frame_miou`: the mean of each frame's own mIoU; not the
map mIoU of the fusion results). `--timing` also measures the cost of MC sampling per frame for
several M.

Shape legend: N images, M Monte-Carlo samples, H×W pixels, K classes.
"""

import argparse
import json
import pathlib
import time
from typing import Any

import jax
import numpy as np
from flax import nnx

from jaxfusion import metrics
from jaxfusion import observations
from jaxfusion import sources

from . import checkpoint, sampling
from . import data as data_lib


def confusion_matrix(pred: np.ndarray, labels: np.ndarray, num_classes: int) -> np.ndarray:
  """`(K, K)` int64 counts, rows = ground truth, columns = prediction.

  `jaxfusion.metrics.confusion_matrix` on pixels, with predictions clipped into `[0, K)`.

  Args:
    pred: int predictions of any shape.
    labels: int ground truth of the same shape; values outside `[0, K)` are ignored.
    num_classes: K.
  """
  pred = np.asarray(pred).ravel().astype(np.int64)
  labels = np.asarray(labels).ravel().astype(np.int64)
  if pred.shape != labels.shape:
    raise ValueError(f"pred {pred.shape} and labels {labels.shape} differ")
  return metrics.confusion_matrix(labels, np.clip(pred, 0, num_classes - 1), num_classes)


def segmentation_metrics(conf: np.ndarray) -> dict[str, Any]:
  """Pixel accuracy, per-class IoU and mIoU (over classes present in truth or prediction)."""
  conf = np.asarray(conf, np.float64)
  iou = metrics.iou_from_confusion(conf)
  return {"pixel_accuracy": float(np.trace(conf) / max(conf.sum(), 1)),
          "miou": metrics.pixel_miou(conf),
          "iou": [None if np.isnan(v) else float(v) for v in iou]}


def load_with_training_size(path, height=None, width=None):
  """Loads a checkpoint for the embedded world's classes; image size defaults to the one it was
  trained at (from its record).

  Returns:
    `(LoadedModel, height, width)`.
  """
  model = checkpoint.load(path, class_names=data_lib.dataset_class_names())
  data = model.metadata.get("record", {}).get("data", {})
  return model, height or data.get("height", 96), width or data.get("width", 128)


def entropy(probs: np.ndarray) -> np.ndarray:
  """Shannon entropy (nats) over the last axis."""
  probs = np.asarray(probs, np.float64)
  return -np.sum(probs * np.log(np.clip(probs, 1e-12, 1.0)), axis=-1)


def expected_calibration_error(probs: np.ndarray, labels: np.ndarray, *,
                               num_bins: int = 15) -> float:
  """ECE of the top-class confidence: `Σ_b (n_b / n) |accuracy_b − mean confidence_b|`.

  Bins are `num_bins` equal-width intervals `((b−1)/B, b/B]` of the max-probability (a
  confidence of exactly 0 goes to the first bin).

  Args:
    probs: `(..., K)` class probabilities.
    labels: `(...)` int ground truth; values outside `[0, K)` are ignored.
    num_bins: B.

  Returns:
    ECE in [0, 1]; NaN when no pixel is labelled.
  """
  if num_bins < 1:
    raise ValueError(f"num_bins must be >= 1; got {num_bins}")
  probs, labels = np.asarray(probs, np.float64), np.asarray(labels)
  if probs.shape[:-1] != labels.shape:
    raise ValueError(f"probs {probs.shape} do not match labels {labels.shape}")
  valid = (labels >= 0) & (labels < probs.shape[-1])
  probs, labels = probs[valid], labels[valid]
  if labels.size == 0:
    return float("nan")
  confidence = probs.max(-1)
  correct = (probs.argmax(-1) == labels).astype(np.float64)
  bins = np.clip(np.ceil(confidence * num_bins).astype(np.int64) - 1, 0, num_bins - 1)
  count = np.bincount(bins, minlength=num_bins)
  gap = np.abs(np.bincount(bins, correct, minlength=num_bins)
               - np.bincount(bins, confidence, minlength=num_bins))
  return float(gap.sum() / labels.size)


def calibration_report(probs: np.ndarray, labels: np.ndarray, *, num_bins: int = 15,
                       high: float = 0.9) -> dict[str, float]:
  """How (over)confident a prediction is where it is wrong.

  Args:
    probs: `(..., K)` class probabilities (MC mean or the dropout-off softmax).
    labels: `(...)` int ground truth; values outside `[0, K)` are ignored.
    num_bins: bins of the ECE.
    high: the confidence above which an error counts as confident.

  Returns:
    `ece`, `mean_maxprob_wrong`, `mean_maxprob_right`, and `share_errors_above_high` (the
    fraction of wrong pixels whose max-probability exceeds `high`); NaN where a set is empty.
  """
  probs, labels = np.asarray(probs, np.float64), np.asarray(labels)
  valid = (labels >= 0) & (labels < probs.shape[-1])
  confidence = probs.max(-1)[valid]
  wrong = probs.argmax(-1)[valid] != labels[valid]
  nan = float("nan")
  return {
      "ece": expected_calibration_error(probs, labels, num_bins=num_bins),
      "mean_maxprob_wrong": float(confidence[wrong].mean()) if wrong.any() else nan,
      "mean_maxprob_right": float(confidence[~wrong].mean()) if (~wrong).any() else nan,
      "share_errors_above_high": float((confidence[wrong] > high).mean()) if wrong.any() else nan,
  }


def alpha_report(mean: np.ndarray, var: np.ndarray, labels: np.ndarray, *,
                 eps: float = 1e-12) -> dict[str, float]:
  """Quartiles of the Dirichlet weight of the predicted class on right and wrong pixels.

  `α = −log(clip(var_ŷ, 0, 0.25) + ε)` with `ŷ = argmax mean`, exactly the concentration the
  robust rules D and D+R give an observation (`jaxfusion.observations.alpha_of_prediction`).

  Args:
    mean: `(..., K)` MC-mean probabilities.
    var: `(..., K)` epistemic variances.
    labels: `(...)` int ground truth; values outside `[0, K)` are ignored.
    eps: ε of the robust rules.

  Returns:
    `alpha_{right,wrong}_{q25,median,q75}`, and `alpha_median_ratio` (right / wrong).
  """
  mean, var, labels = np.asarray(mean), np.asarray(var, np.float64), np.asarray(labels)
  valid = (labels >= 0) & (labels < mean.shape[-1])
  pred = mean.argmax(-1)[valid]
  alpha = observations.alpha_of_prediction(var[valid], pred, eps=eps)
  wrong = pred != labels[valid]
  out = {}
  for name, subset in (("right", alpha[~wrong]), ("wrong", alpha[wrong])):
    q = np.quantile(subset, [0.25, 0.5, 0.75]) if subset.size else [float("nan")] * 3
    out.update({f"alpha_{name}_q25": float(q[0]), f"alpha_{name}_median": float(q[1]),
                f"alpha_{name}_q75": float(q[2])})
  out["alpha_median_ratio"] = out["alpha_right_median"] / out["alpha_wrong_median"]
  return out


_moments_batch = jax.jit(jax.vmap(sources.mc_moments))


def predict_arrays(graphdef: nnx.GraphDef, params: nnx.State, images: np.ndarray, *,
                   key: jax.Array, num_samples: int, batch_size: int = 4
                   ) -> dict[str, np.ndarray]:
  """Deterministic and MC-dropout predictions for a stack of images.

  Args:
    graphdef: static graph.
    params: the network parameters.
    images: `(N, H, W, 3)` uint8 or float RGB.
    key: PRNG key for the dropout masks.
    num_samples: M.
    batch_size: frames per jitted call.

  Returns:
    Dict of NumPy arrays: `det_probs`, `mc_mean`, `mc_var`, all `(N, H, W, K)` float32.
  """
  out = {"det_probs": [], "mc_mean": [], "mc_var": []}
  n = images.shape[0]
  for start in range(0, n, batch_size):
    chunk = images[start:start + batch_size]
    out["det_probs"].append(np.asarray(sampling.deterministic_probs(graphdef, params, chunk)))
    samples = sampling.mc_samples_batch(graphdef, params, jax.random.fold_in(key, start), chunk,
                                        num_samples=num_samples)
    mean, var = _moments_batch(samples)
    out["mc_mean"].append(np.asarray(mean))
    out["mc_var"].append(np.asarray(var))
  return {k: np.concatenate(v) for k, v in out.items()}


def uncertainty_report(mean: np.ndarray, var: np.ndarray, labels: np.ndarray
                       ) -> dict[str, float]:
  """How well the epistemic variance flags the MC-mean prediction's errors.

  Scores per pixel: `var_sum` = Σ_k var_k (total epistemic variance), `var_pred` = the
  variance of the predicted class, and, for context, the entropy of the MC mean.

  Args:
    mean: `(..., K)` MC-mean probabilities.
    var: `(..., K)` epistemic variances.
    labels: `(...)` int ground truth; values outside `[0, K)` are ignored.

  Returns:
    AUROCs of each score as an error detector, the error rate, and the mean `var_sum` on
    wrong and on right pixels.
  """
  valid = (labels >= 0) & (labels < mean.shape[-1])
  pred = np.argmax(mean, axis=-1)[valid]
  wrong = pred != labels[valid]
  var, mean = var[valid], mean[valid]
  var_sum = var.sum(-1)
  var_pred = np.take_along_axis(var, pred[..., None], axis=-1)[..., 0]
  return {
      "error_rate": float(wrong.mean()),
      "auroc_var_sum": metrics.auroc(var_sum, wrong),
      "auroc_var_pred": metrics.auroc(var_pred, wrong),
      "auroc_entropy": metrics.auroc(entropy(mean), wrong),
      "mean_var_sum_wrong": float(var_sum[wrong].mean()) if wrong.any() else float("nan"),
      "mean_var_sum_right": float(var_sum[~wrong].mean()) if (~wrong).any() else float("nan"),
  }


def evaluate_arrays(graphdef: nnx.GraphDef, params: nnx.State, images: np.ndarray,
                    labels: np.ndarray, *, key: jax.Array, num_samples: int, num_classes: int,
                    batch_size: int = 4) -> dict[str, Any]:
  """Accuracy, mIoU and uncertainty quality on one split.

  Args:
    graphdef: static graph.
    params: the network parameters.
    images: `(N, H, W, 3)` uint8 RGB.
    labels: `(N, H, W)` int ground truth.
    key: PRNG key for the dropout masks.
    num_samples: M for the MC evaluation.
    num_classes: K.
    batch_size: frames per jitted call.

  Returns:
    `{"summary": {...flat floats...}, "iou_deterministic": [...], "iou_mc": [...]}`.
  """
  preds = predict_arrays(graphdef, params, images, key=key, num_samples=num_samples,
                         batch_size=batch_size)
  labels = np.asarray(labels)
  det = segmentation_metrics(
      confusion_matrix(preds["det_probs"].argmax(-1), labels, num_classes))
  mc = segmentation_metrics(confusion_matrix(preds["mc_mean"].argmax(-1), labels, num_classes))
  unc = uncertainty_report(preds["mc_mean"], preds["mc_var"], labels)
  valid = (labels >= 0) & (labels < num_classes)
  det_wrong = (preds["det_probs"].argmax(-1) != labels)[valid]
  prefixed = lambda prefix, d: {f"{prefix}_{k}": v for k, v in d.items()}
  summary = {
      "num_images": int(images.shape[0]),
      "num_samples": num_samples,
      "det_pixel_accuracy": det["pixel_accuracy"], "det_miou": det["miou"],
      "mc_pixel_accuracy": mc["pixel_accuracy"], "mc_miou": mc["miou"],
      "det_frame_miou": metrics.per_frame_miou(preds["det_probs"].argmax(-1), labels, num_classes),
      "mc_frame_miou": metrics.per_frame_miou(preds["mc_mean"].argmax(-1), labels, num_classes),
      **unc,
      "det_auroc_entropy": metrics.auroc(entropy(preds["det_probs"][valid]), det_wrong),
      # The same MC variance as a detector of the dropout-off pass's errors.
      "det_auroc_var_sum": metrics.auroc(preds["mc_var"][valid].sum(-1), det_wrong),
      **prefixed("mc", calibration_report(preds["mc_mean"], labels)),
      **prefixed("det", calibration_report(preds["det_probs"], labels)),
      **alpha_report(preds["mc_mean"], preds["mc_var"], labels),
      "chance_pixel_accuracy": float(1.0 / num_classes),
  }
  summary = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in summary.items()}
  return {"summary": summary, "iou_deterministic": det["iou"], "iou_mc": mc["iou"]}


def time_sampling(graphdef: nnx.GraphDef, params: nnx.State, *, height: int, width: int,
                  num_samples_list=(1, 8, 32), repeats: int = 3) -> dict[str, dict[str, float]]:
  """Compile time and median wall time of `mc_samples` + `mc_moments` for one frame.

  Also times `deterministic_probs` (one pass, dropout off) as `"deterministic"`.
  """
  image = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
  key = jax.random.key(0)
  moments = jax.jit(sources.mc_moments)
  results = {}

  def run_mc(m):
    return moments(sampling.mc_samples(graphdef, params, key, image, num_samples=m))

  cases = {f"M={m}": (lambda m=m: run_mc(m)) for m in num_samples_list}
  cases["deterministic"] = lambda: sampling.deterministic_probs(graphdef, params, image)
  for name, fn in cases.items():
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
      t0 = time.perf_counter()
      jax.block_until_ready(fn())
      runs.append(time.perf_counter() - t0)
    results[name] = {"first_call_s": round(compile_s, 3),
                     "median_s": round(float(np.median(runs)), 4)}
  return results


def main(argv: list[str] | None = None) -> dict[str, Any]:
  p = argparse.ArgumentParser(prog="python -m models.evaluate",
                              description=__doc__.split("\n")[0])
  p.add_argument("--checkpoint", default=str(checkpoint.PRETRAINED_PATH))
  p.add_argument("--num-images", type=int, default=48)
  p.add_argument("--num-samples", type=int, default=32)
  p.add_argument("--height", type=int, default=None, help="default: the training size")
  p.add_argument("--width", type=int, default=None)
  p.add_argument("--seed", type=int, default=None, help="default: the training record's")
  p.add_argument("--shift", type=float, default=1.0)
  p.add_argument("--timing", action="store_true",
                 help="also time MC sampling per frame for M = 1, 8, 32 at 120x160")
  p.add_argument("--json", default=None, help="write the results here as JSON")
  p.add_argument("--cache", default=None, help="folder to cache rendered views in")
  p.add_argument("--sensing", choices=("on", "off"), default="on",
                 help="render the views with the embedded world's view-dependent camera model "
                      "(its default) or with the plain sensor model (SensingConfig.off())")
  args = p.parse_args(argv)

  try:
    model, height, width = load_with_training_size(args.checkpoint, args.height, args.width)
  except (ValueError, FileNotFoundError) as e:   # a CheckpointError is a ValueError
    p.error(str(e))
  seed = args.seed if args.seed is not None else model.metadata.get("record", {}).get("seed", 0)
  key = jax.random.key(seed + 7)
  results = {"checkpoint": args.checkpoint, "height": height, "width": width,
             "sensing": args.sensing}
  splits = {"train_heldout": ("train", seed + 10_000, 1.0),
            "test_shifted": ("test", seed + 20_000, args.shift)}
  for i, (name, (domain, split_seed, shift)) in enumerate(splits.items()):
    x, y = data_lib.load_domain(domain, args.num_images, height=height, width=width,
                                seed=split_seed, shift=shift, cache_dir=args.cache,
                                sensing=args.sensing == "on")
    res = evaluate_arrays(model.graphdef, model.params, x, y, key=jax.random.fold_in(key, i),
                          num_samples=args.num_samples, num_classes=model.config.num_classes)
    results[name] = res
    print(f"{name}: {json.dumps(res['summary'])}", flush=True)
  if args.timing:
    results["timing_120x160"] = time_sampling(model.graphdef, model.params, height=120,
                                              width=160)
    results["timing_120x160"]["devices"] = str(jax.devices())
    print(f"timing 120x160: {json.dumps(results['timing_120x160'])}", flush=True)
  if args.json:
    pathlib.Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
  return results


if __name__ == "__main__":
  main()
