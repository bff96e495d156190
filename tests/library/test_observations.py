"""Pixel observations of GT voxels: the headroom classification against a hand-built case and a
loop, the pixel→voxel observations against a dict lookup, and α of the prediction against the
robust rules' concentration."""

import importlib
import types

import numpy as np

import jaxfusion as jf
from jaxfusion import camera as camera_lib
from jaxfusion import observations

# The module (`jaxfusion.rules.robust` is also the name of the rule's factory).
robust = importlib.import_module("jaxfusion.rules.robust")

# The study's tests (tests/lab/test_study.py) fuse `plane_scene` at these sizes: the same
# shapes as the demo's tests, so that compiled fusion steps are reused.
H, W = 24, 32
K = 7


def test_classify_voxels_hand_built():
  # votes per voxel (K = 3): [3,1,0] y=0 | [2,1,0] y=1 | [1,1,1] y=2 (tie) | [0,2,0] y=0 | none
  votes = {0: [0, 0, 0, 1], 1: [0, 0, 1], 2: [0, 1, 2], 3: [1, 1]}
  gt_index = np.array([v for v, preds in votes.items() for _ in preds])
  pred = np.array([p for preds in votes.values() for p in preds])
  got = observations.classify_voxels(np.array([0, 1, 2, 0, 1]), gt_index, pred, 3)
  np.testing.assert_array_equal(got, [0, 1, 1, 2, -1])


def test_classify_voxels_against_a_loop():
  rng = np.random.default_rng(4)
  g, k = 40, 4
  labels = rng.integers(0, k, g)
  gt_index = rng.integers(-1, g, 300)
  pred = rng.integers(0, k, 300)
  got = observations.classify_voxels(labels, gt_index, pred, k)
  for v in range(g):
    n = np.array([np.sum((gt_index == v) & (pred == c)) for c in range(k)])
    others = max(n[c] for c in range(k) if c != labels[v])
    want = -1 if n.sum() == 0 else 2 if n[labels[v]] == 0 else 0 if n[labels[v]] > others else 1
    assert got[v] == want, v


def plane_scene(rng, num_frames=4, voxel_size=0.5):
  """Frames of a wall 2 m ahead seen from shifted positions; GT by voxel column."""
  cam = jf.Camera(16.0, 16.0, (W - 1) / 2, (H - 1) / 2)
  depth = np.full((num_frames, H, W), 2.0, np.float32)
  depth[:, :2, :3] = 0.0                                    # a hole: not observations
  poses = np.tile(np.eye(4, dtype=np.float32), (num_frames, 1, 1))
  poses[:, 0, 3] = np.linspace(0.0, 0.7, num_frames)
  poses[:, 1, 3] = 0.05
  keys = np.stack([np.asarray(camera_lib.depth_to_voxel_keys(depth[t], poses[t], cam,
                                                             voxel_size)[0])
                   for t in range(num_frames)])             # (T, N, 3)
  valid = depth.reshape(num_frames, -1) > 0
  coords = np.unique(keys[valid], axis=0)
  labels = (coords[:, 0] * 5 + coords[:, 1] * 3) % K
  seq = types.SimpleNamespace(depth=depth, T_world_cam=poses, camera=cam)
  return seq, {"coords": coords.astype(np.int32), "labels": labels.astype(np.int32)}, keys, valid


def test_pixel_observations_against_a_dict_lookup():
  rng = np.random.default_rng(1)
  seq, gt, keys, valid = plane_scene(rng)
  keep = rng.uniform(size=len(gt["coords"])) < 0.7          # some voxels are not in the GT
  gt = {k: v[keep] for k, v in gt.items()}
  probs = rng.dirichlet(np.ones(K), seq.depth.shape).astype(np.float32)
  probs[0, 5, 5] = np.nan                                   # not an observation
  obs = observations.pixel_observations(seq.depth, seq.T_world_cam, seq.camera, probs,
                                        gt["coords"], voxel_size=0.5)
  index = {tuple(c): i for i, c in enumerate(gt["coords"])}
  want = np.array([[index.get(tuple(keys[t, n]), -1) if valid[t, n] else -1
                    for n in range(H * W)] for t in range(len(keys))])
  want[0, 5 * W + 5] = -1
  np.testing.assert_array_equal(obs["gt_index"], want)
  np.testing.assert_array_equal(obs["pred"], np.argmax(probs, -1).reshape(len(keys), -1))


def test_alpha_of_prediction_is_the_robust_rules_concentration_of_the_predicted_class():
  rng = np.random.default_rng(3)
  var = rng.uniform(0.0, 0.4, (5, 6, K)).astype(np.float32)   # some above the 0.25 clip
  var[0, 0] = 0.0
  pred = rng.integers(0, K, (5, 6))
  for eps in (robust.DEFAULT_EPS, 1e-3):
    got = observations.alpha_of_prediction(var, pred, eps=eps)
    assert got.shape == pred.shape and got.dtype == np.float64 and np.all(np.isfinite(got))
    want = np.take_along_axis(np.asarray(robust.concentration(var, eps)), pred[..., None],
                              axis=-1)[..., 0]
    np.testing.assert_allclose(got, want, rtol=1e-6)
  np.testing.assert_array_equal(observations.alpha_of_prediction(var, pred),
                                observations.alpha_of_prediction(var, pred,
                                                                 eps=robust.DEFAULT_EPS))
  assert observations.alpha_of_prediction(np.full((1, K), 0.3), np.zeros(1, int))[0] == (
      -np.log(0.25 + robust.DEFAULT_EPS))
