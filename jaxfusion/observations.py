"""Pixel observations of ground-truth voxels: which GT voxel each pixel observes and which class
it votes for, how the votes of a GT voxel divide, and the weight α the robust rules give a
prediction.

A fusion rule only weighs the observations a voxel gets, so these say what any rule can win
against the ground truth, whatever front end made the probabilities. They need only the
library's inputs (depth, poses, a `Camera`, per-pixel probabilities and variances) and GT voxels
(`coords`, `labels`, e.g. from `datasets.gt_voxel_labels`). The study (`jaxfusion study`) counts
them per sequence; the network's evaluation reports α (`models.evaluate.alpha_report`).

Definitions (a GT voxel's label y is the majority of its GT pixel labels):

* **Pixel observation**: a pixel with valid depth and finite probabilities whose voxel (the
  engine's key, `camera.depth_to_voxel_keys`) is a GT voxel; it *votes* for the argmax of its
  probabilities (`pixel_observations`). It is **right** when that class is y, **wrong**
  otherwise.
* **Headroom** (`classify_voxels`): with n_k the votes for class k over a whole sequence, an
  observed GT voxel is *mostly right* when n_y > max_{k≠y} n_k (a plurality vote is right),
  *outvoted right* when 0 < n_y ≤ max_{k≠y} n_k (some observations are right but are outvoted
  or tied: only here can a better weighting of the observations win), and *never right* when
  n_y = 0 (`HEADROOM`, in that order).
* **α** of a prediction (`alpha_of_prediction`): `−log(clip(var_c, 0, 0.25) + ε)` of its
  predicted class c, the concentration the robust rules D and D+R give it.

Shape legend: T frames, H×W pixels, N = H·W, K classes, G GT voxels, P pixel observations.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib
from jaxfusion import context as context_lib
from jaxfusion.rules.learned import FEATURE_NAMES as MOMENT_FEATURES
from jaxfusion.rules.learned import features as moment_features
from jaxfusion.rules.robust import DEFAULT_EPS

# The headroom categories of `classify_voxels`, by code (−1: not observed).
HEADROOM = ("mostly right", "outvoted right", "never right")


@jax.jit
def _frame_keys(depth, T_world_cam, camera, voxel_size):
  keys, in_range = jax.vmap(camera_lib.depth_to_voxel_keys, in_axes=(0, 0, None, None))(
      depth, T_world_cam, camera, voxel_size)
  d = depth.reshape(depth.shape[0], -1)
  return keys, in_range & jnp.isfinite(d) & (d > 0)


def _rows(coords) -> np.ndarray:
  coords = np.ascontiguousarray(np.asarray(coords, np.int32).reshape(-1, 3))
  return coords.view(np.dtype((np.void, 12))).reshape(-1)


def pixel_observations(depth, T_world_cam, camera, probs, gt_coords, *,
                       voxel_size: float) -> dict:
  """Which GT voxel each pixel observes and which class it votes for.

  Args:
    depth: `(T, H, W)` float depth (invalid: 0, negative or non-finite).
    T_world_cam: `(T, 4, 4)` camera-to-world poses.
    camera: intrinsics.
    probs: `(T, H, W, K)` probabilities whose argmax is the vote (pixels with non-finite
      probabilities are not observations, as in the engine).
    gt_coords: `(G, 3)` int GT voxel coordinates (unique).
    voxel_size: voxel edge in metres (the maps' and the GT's).

  Returns:
    dict with `gt_index (T, N) int64` (the pixel's GT voxel, −1 for no observation) and
    `pred (T, N) int64` (the argmax class).
  """
  depth = np.asarray(depth, np.float32)
  probs = np.asarray(probs)
  if depth.ndim != 3 or probs.shape[:3] != depth.shape:
    raise ValueError(f"depth must be (T, H, W) and probs (T, H, W, K); got {depth.shape} and "
                     f"{probs.shape}")
  t = depth.shape[0]
  keys, valid = _frame_keys(jnp.asarray(depth), jnp.asarray(T_world_cam, jnp.float32), camera,
                            jnp.float32(voxel_size))
  keys, valid = np.asarray(keys).reshape(-1, 3), np.array(valid).reshape(-1)
  flat_probs = probs.reshape(-1, probs.shape[-1])
  valid &= np.all(np.isfinite(flat_probs), axis=-1)
  gt_rows = _rows(gt_coords)
  pix_rows = _rows(keys[valid])
  _, inverse = np.unique(np.concatenate([gt_rows, pix_rows]), return_inverse=True)
  inverse = inverse.reshape(-1)
  lookup = np.full(int(inverse.max()) + 1 if inverse.size else 0, -1, np.int64)
  lookup[inverse[:len(gt_rows)]] = np.arange(len(gt_rows))
  gt_index = np.full(valid.shape, -1, np.int64)
  gt_index[valid] = lookup[inverse[len(gt_rows):]]
  pred = np.argmax(flat_probs, axis=-1).astype(np.int64)
  return {"gt_index": gt_index.reshape(t, -1), "pred": pred.reshape(t, -1)}


def classify_voxels(gt_labels, gt_index, pred, num_classes: int) -> np.ndarray:
  """The headroom category of every GT voxel from its pixel votes (see the module docstring).

  Args:
    gt_labels: `(G,)` int GT label y per voxel.
    gt_index: `(P,)` int GT voxel of each pixel observation (entries < 0 are ignored).
    pred: `(P,)` int class each observation votes for.
    num_classes: K.

  Returns:
    `(G,) int8`: 0 mostly right, 1 outvoted right, 2 never right, −1 not observed.
  """
  y = np.asarray(gt_labels, np.int64).reshape(-1)
  gt_index = np.asarray(gt_index, np.int64).reshape(-1)
  pred = np.asarray(pred, np.int64).reshape(-1)
  if gt_index.shape != pred.shape:
    raise ValueError(f"gt_index and pred must have the same length; got {gt_index.shape} and "
                     f"{pred.shape}")
  return classify_votes(y, voxel_votes(gt_index, pred, len(y), num_classes))


def voxel_votes(gt_index, pred, num_voxels: int, num_classes: int) -> np.ndarray:
  """`(G, K) int64` pixel votes per GT voxel and class: observation i (`gt_index[i] ≥ 0`)
  votes for class `pred[i]` of voxel `gt_index[i]`; entries < 0 are not observations."""
  gt_index = np.asarray(gt_index, np.int64).reshape(-1)
  pred = np.asarray(pred, np.int64).reshape(-1)
  keep = gt_index >= 0
  return np.bincount(gt_index[keep] * num_classes + pred[keep],
                     minlength=num_voxels * num_classes).reshape(num_voxels, num_classes)


def classify_votes(gt_labels, votes) -> np.ndarray:
  """`classify_voxels` from the votes themselves: `votes (G, K) int`, the observations of each
  GT voxel per class (summed over the chunks of a long sequence).

  Returns:
    `(G,) int8`: 0 mostly right, 1 outvoted right, 2 never right, −1 not observed.
  """
  y = np.asarray(gt_labels, np.int64).reshape(-1)
  votes = np.asarray(votes, np.int64)
  g, num_classes = votes.shape
  rows = np.arange(g)
  right = votes[rows, y]
  others = votes.copy()
  others[rows, y] = -1
  best_other = others.max(1) if num_classes > 1 else np.zeros(g, np.int64)
  category = np.where(right > best_other, 0, 1)
  category = np.where(right == 0, 2, category)
  return np.where(votes.sum(1) == 0, -1, category).astype(np.int8)


def alpha_of_prediction(var, pred, *, eps: float = DEFAULT_EPS) -> np.ndarray:
  """`α = −log(clip(var_c, 0, 0.25) + ε)` of the predicted class c (the D rules' weight).

  The concentration `rules.robust.concentration` gives an observation of class c, in NumPy and
  float64 for statistics over many pixels.

  Args:
    var: `(..., K)` per-class MC variance.
    pred: `(...)` int predicted class.
    eps: ε of the robust rules.

  Returns:
    `(...) float64` α.
  """
  var = np.asarray(var)
  v = np.take_along_axis(var, np.asarray(pred)[..., None], axis=-1)[..., 0]
  return -np.log(np.clip(v.astype(np.float64), 0.0, 0.25) + eps)


# Per-pixel features whose power to tell right from wrong observations is measured
# (`feature_histograms`): the learned rule's six moment features (docs/equations.md §3.9) and
# every context feature (§2.5), each binned over a fixed range (values outside are clipped in).
FEATURE_RANGES = {
    "max_prob": (0.0, 1.0), "margin": (0.0, 1.0), "entropy": (0.0, 1.0),
    "alpha_pred": (0.0, 2.8), "sqrt_sum_var": (0.0, 1.0), "rel_var_pred": (0.0, 1.0),
    "depth": (0.0, 8.0), "incidence": (0.0, 1.0), "depth_edge": (0.0, 16.0),
    "label_edge": (0.0, 16.0), "radius": (0.0, 1.0), "sharpness": (0.0, 0.5),
    "luminance": (0.0, 1.0), "clipped": (0.0, 1.0)}
FEATURE_BINS = 128


@functools.partial(jax.jit, static_argnames=("names",))
def _pixel_features(depth, probs, var, rgb, camera, names):
  """`(H·W, 6 + F)`: the moment features of every pixel, then its context features `names`."""
  k = probs.shape[-1]
  flat_p = jnp.where(jnp.isfinite(probs), jnp.maximum(probs, 0.0), 1.0 / k).reshape(-1, k)
  flat_v = jnp.where(jnp.isfinite(var), var, 0.0).reshape(-1, k)
  moments = jax.vmap(lambda p, v: moment_features(p, v, DEFAULT_EPS))(flat_p, flat_v)
  ctx = context_lib.pixel_context(depth, probs, camera, names, rgb)
  return jnp.concatenate([moments, ctx.reshape(moments.shape[0], -1)], -1)


def feature_histograms(depth, probs, var, rgb, camera, right, observed) -> dict:
  """Histograms of every feature of `FEATURE_RANGES` over right and wrong pixel observations.

  Args:
    depth: `(T, H, W)` depth.
    probs: `(T, H, W, K)` MC mean; var: `(T, H, W, K)` MC variance.
    rgb: `(T, H, W, 3)` colour images, or None (then the image features are left out).
    camera: intrinsics.
    right: `(T, H·W)` (or flat) bool, right observations, frame-major.
    observed: the same shape, bool: pixel observations.

  Returns:
    dict feature name → `(2, FEATURE_BINS)` int64 counts, right then wrong
    (`metrics.auroc_from_histograms` takes them).
  """
  ctx_names = tuple(n for n in context_lib.FEATURES
                    if rgb is not None or n not in context_lib.IMAGE_FEATURES)
  names = tuple(MOMENT_FEATURES) + ctx_names
  fn = _pixel_features
  t = np.shape(depth)[0]
  values = np.concatenate([np.asarray(fn(np.asarray(depth[i], np.float32),
                                         np.asarray(probs[i], np.float32),
                                         np.asarray(var[i], np.float32),
                                         None if rgb is None else np.asarray(rgb[i]),
                                         camera, ctx_names))
                           for i in range(t)])
  right = np.asarray(right, bool).reshape(-1)
  wrong = np.asarray(observed, bool).reshape(-1) & ~right
  out = {}
  for f, name in enumerate(names):
    lo, hi = FEATURE_RANGES[name]
    edges = np.linspace(lo, hi, FEATURE_BINS + 1)
    x = np.clip(values[:, f], lo, hi)
    out[name] = np.stack([np.histogram(x[right], edges)[0],
                          np.histogram(x[wrong], edges)[0]]).astype(np.int64)
  return out
