"""GT voxel labels (engine + sum_labels) against a direct count, and the real Middlebury frame."""

import collections

import numpy as np
import pytest

import jaxfusion
from jaxfusion import datasets
from jaxfusion.datasets import synthetic
from jaxfusion.datasets.classes import IGNORE_LABEL


def direct_majority(seq, voxel_size):
  """Slow reference: a dict of voxels counting GT labels; ties go to the lowest label."""
  votes = collections.defaultdict(lambda: np.zeros(seq.num_classes, np.int64))
  cam = seq.camera
  for f in seq:
    for v, u in zip(*np.nonzero((f.depth > 0) & (f.labels >= 0))):
      d = float(f.depth[v, u])
      p = np.array([d * (u - cam.cx) / cam.fx, d * (v - cam.cy) / cam.fy, d])
      T = f.T_world_cam.astype(np.float32)
      p_world = T[:3, :3].astype(np.float64) @ p + T[:3, 3]
      votes[tuple(np.floor(p_world / voxel_size).astype(int))][f.labels[v, u]] += 1
  return {k: (int(np.argmax(c)), int(c.sum())) for k, c in votes.items()}


def test_gt_voxel_labels_match_a_direct_count():
  seq = synthetic.make_sequence("office", 2, num_frames=2, height=24, width=32)
  labels = seq.labels.copy()
  labels[:, :2] = IGNORE_LABEL  # ignored pixels are not fused
  seq = datasets.RGBDSequence(seq.name, seq.class_names, seq.camera, seq.rgb, seq.depth,
                              seq.T_world_cam, labels)
  gt = datasets.gt_voxel_labels(seq, voxel_size=0.1)
  ref = direct_majority(seq, 0.1)
  got = {tuple(c): (int(l), int(h)) for c, l, h in zip(gt["coords"], gt["labels"], gt["hits"])}
  # float32 (engine) and float64 (reference) may disagree on points within 1e-6 of a voxel face.
  common = set(got) & set(ref)
  assert len(common) >= 0.98 * len(ref) and len(got) <= 1.02 * len(ref)
  agree = np.mean([got[k] == ref[k] for k in common])
  assert agree > 0.97
  assert gt["hits"].sum() == ((seq.depth > 0) & (seq.labels >= 0)).sum()
  assert gt["coords"].dtype == np.int32 and gt["labels"].dtype == np.int32


def test_gt_voxel_labels_need_labels():
  unlabelled = datasets.RGBDSequence("empty", (), jaxfusion.Camera(4.0, 4.0, 3.5, 3.5),
                                     np.zeros((1, 8, 8, 3), np.uint8), np.ones((1, 8, 8)),
                                     np.eye(4)[None])
  with pytest.raises(ValueError, match="no ground-truth labels"):
    datasets.gt_voxel_labels(unlabelled)


def test_middlebury_frame_backprojects_into_the_map():
  pytest.importorskip("skimage")
  frame = datasets.middlebury_frame()
  assert frame.rgb.shape == (500, 741, 3) and frame.depth.shape == (500, 741)
  valid = frame.depth[frame.depth > 0]
  assert valid.size > 0.9 * frame.depth.size
  assert 1.5 < np.median(valid) < 4.0 and valid.max() < 10.0  # a motorcycle a few metres away
  step = 4  # fuse a subsampled frame to keep the test fast
  depth = frame.depth[::step, ::step]
  cam = frame.camera
  camera = jaxfusion.Camera(cam.fx / step, cam.fy / step, cam.cx / step, cam.cy / step)
  probs = np.zeros(depth.shape + (2,), np.float32)
  probs[..., 0] = 1.0
  rule = jaxfusion.rules.sum_labels()
  state = jaxfusion.init_map(capacity=2**15, num_classes=2, voxel_size=0.05, rule=rule)
  state = jaxfusion.fuse_frame(state, jaxfusion.Frame(depth, frame.T_world_cam, probs), camera,
                               rule)
  out = jaxfusion.read_map(state)
  assert len(out["coords"]) > 1000
  assert out["hits"].sum() == int((depth > 0).sum())
  z = out["centers"][:, 2]
  assert z.min() > 1.5 and z.max() < 5.5
