"""The engine against the independent NumPy reference (tests/reference.py) on random
multi-frame sequences, for all six rules and both pixel-aggregation modes."""

import numpy as np
import pytest

import jaxfusion as jf
from tests import engine_helpers as h
from tests.reference import ReferenceMap

VOXEL = 0.25


def fuse_both(name, seed, *, aggregate="sum", num_frames=4, **hparams):
  rng = np.random.default_rng(seed)
  rule = jf.rules.by_name(name, aggregate=aggregate, **hparams)
  state = jf.init_map(capacity=1024, num_classes=h.NUM_CLASSES, voxel_size=VOXEL, rule=rule)
  ref = ReferenceMap(name, h.NUM_CLASSES, VOXEL, aggregate=aggregate, **hparams)
  # Frames share a neighbourhood so voxels are revisited across frames.
  for _ in range(num_frames):
    frame = h.random_frame(rng, voxel_size=VOXEL)
    state = jf.fuse_frame(state, frame, h.CAMERA, rule)
    ref.fuse(frame.depth, frame.T_world_cam, frame.probs, frame.var, *h.CAMERA)
  return jf.read_map(state), ref.read()


def assert_maps_match(got, ref, name):
  np.testing.assert_array_equal(got["coords"], ref["coords"])
  np.testing.assert_array_equal(got["hits"], ref["hits"])
  np.testing.assert_allclose(got["posterior"], ref["posterior"], atol=2e-4, rtol=0)
  top2 = np.sort(ref["posterior"], axis=1)[:, -2:]
  clear = top2[:, 1] - top2[:, 0] > 1e-3
  np.testing.assert_array_equal(got["labels"][clear], ref["labels"][clear])
  if name in h.DIRICHLET_RULES:
    np.testing.assert_allclose(got["confidence"], ref["confidence"], rtol=1e-5)
  else:
    assert "confidence" not in got
  assert np.all(np.isfinite(got["posterior"])) and np.all(np.isfinite(got["entropy"]))


@pytest.mark.parametrize("aggregate", ["sum", "mean"])
@pytest.mark.parametrize("name", h.PAPER_RULES)
@pytest.mark.parametrize("seed", h.main_tier_keeps([0, 1], (0,)))
def test_matches_reference(name, aggregate, seed):
  got, ref = fuse_both(name, seed, aggregate=aggregate)
  assert len(got["coords"]) > 20   # the sequence really exercises grouping and revisits
  assert got["hits"].max() > 1
  assert_maps_match(got, ref, name)


@pytest.mark.parametrize("name", ["robust_r", "robust_d", "robust_dr"])
def test_matches_reference_other_hyperparameters(name):
  hparams = {"beta": 0.05, "eps": 1e-6, "alpha0": 0.0}
  got, ref = fuse_both(name, 7, **hparams)
  assert_maps_match(got, ref, name)
