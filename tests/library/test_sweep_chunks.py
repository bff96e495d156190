"""`tune.sweep_chunks`: a sweep of a sequence given chunk by chunk equals `tune.sweep`."""

import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import datasets
from jaxfusion import fusion
from jaxfusion import tune


@pytest.fixture(scope="module")
def case():
  seq = datasets.make_sequence("office", 0, num_frames=7, height=20, width=24, seed=1)
  rng = np.random.default_rng(0)
  probs = rng.dirichlet(np.ones(7), (7, 20, 24)).astype(np.float32)
  var = (0.02 * rng.random((7, 20, 24, 7))).astype(np.float32)
  gt = datasets.gt_voxel_labels(seq)
  rules = jf.rules.stack([jf.rules.by_name("D+R", beta=b) for b in (0.0, 0.3, 1.0)])
  return fusion.Frame(seq.depth, seq.T_world_cam, probs, var), seq.camera, gt, rules


@pytest.mark.slow
@pytest.mark.parametrize("size", [1, 3, 7])
def test_chunks_equal_the_whole_sequence(case, size):
  frames, camera, gt, rules = case
  whole = tune.sweep(frames, camera, gt["coords"], gt["labels"], rules, capacity=2**13)
  cut = lambda lo, hi: fusion.Frame(*(None if x is None else x[lo:hi] for x in frames))
  chunks = [cut(i, i + size) for i in range(0, 7, size)]
  got = tune.sweep_chunks(chunks, camera, gt["coords"], gt["labels"], rules, capacity=2**13)
  for key in ("confusion", "miou", "accuracy", "occupied", "dropped"):   # the maps are the same
    np.testing.assert_array_equal(got[key], whole[key], err_msg=key)
  for key in ("loss", "soft_iou_loss"):       # float sums reduced by another program: ≤ 1 ulp
    np.testing.assert_allclose(got[key], whole[key], rtol=1e-6, err_msg=key)


def test_no_chunks_or_a_longer_later_chunk_is_refused(case):
  frames, camera, gt, rules = case
  with pytest.raises(ValueError, match="no frames"):
    tune.sweep_chunks([], camera, gt["coords"], gt["labels"], rules, capacity=2**13)
  cut = lambda lo, hi: fusion.Frame(*(None if x is None else x[lo:hi] for x in frames))
  chunks = [cut(0, 2), cut(2, 6)]
  with pytest.raises(ValueError, match="longer than the first"):
    tune.sweep_chunks(chunks, camera, gt["coords"], gt["labels"], rules, capacity=2**13)
