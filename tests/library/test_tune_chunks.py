"""`tune_chunks.tune_hparams_chunks`: the loss and gradient of sequences read chunk by chunk are
those of `tune.sequence_loss` on the whole sequences, and the fit follows `tune.tune_hparams`."""

import jax
import numpy as np
import pytest

from jaxfusion import datasets
from jaxfusion import fusion
from jaxfusion import rules as rules_lib
from jaxfusion import tune
from jaxfusion import tune_chunks

T, H, W, K = 5, 16, 20, 7
CAPACITY = 2**12


@pytest.fixture(scope="module")
def case():
  seqs, gts = [], []
  rng = np.random.default_rng(0)
  for traj in (0, 1):
    seq = datasets.make_sequence("office", traj, num_frames=T, height=H, width=W, seed=2)
    labels = np.maximum(seq.labels, 0)
    onehot = np.eye(K, dtype=np.float32)[labels]
    noise = rng.dirichlet(np.ones(K), (T, H, W)).astype(np.float32)
    probs = 0.5 * onehot + 0.5 * noise
    var = (0.05 * rng.random((T, H, W, K)) * (1 - onehot)).astype(np.float32)
    seqs.append(fusion.Frame(seq.depth, seq.T_world_cam, probs, var))
    gts.append(datasets.gt_voxel_labels(seq))
  return seqs, gts, seq.camera


def _reader(seqs, size):
  def read(b, k):
    return fusion.Frame(*(None if x is None else x[k * size:(k + 1) * size] for x in seqs[b]))
  return read, [int(np.ceil(T / size))] * len(seqs)


@pytest.mark.parametrize("objective,size,checkpoint", [
    pytest.param("cross_entropy", 2, 2, marks=pytest.mark.slow),
    pytest.param("cross_entropy", 2, 1, marks=pytest.mark.slow),
    pytest.param("cross_entropy", 5, None, marks=pytest.mark.slow),
    pytest.param("soft_iou", 2, 1, marks=pytest.mark.slow),
    pytest.param("soft_iou", 2, 2, marks=pytest.mark.slow),
    pytest.param("soft_iou", 5, None, marks=pytest.mark.slow)])
def test_one_step_loss_and_gradient_equal_the_whole_scan(case, objective, size, checkpoint):
  seqs, gts, camera = case
  frames, mask = __import__("jaxfusion").batch.stack_sequences(seqs)
  coords, labels = tune.pad_ground_truth(gts)

  def loss(u):
    rule = rules_lib.by_name("D+R", **tune.constrain({"beta": u}))
    return tune.sequence_loss(rule, frames, camera, coords, labels, capacity=CAPACITY,
                              mask=mask, objective=objective)

  u0 = tune.unconstrain({"beta": np.float32(0.3)})["beta"]
  want_loss, want_grad = jax.value_and_grad(loss)(u0)
  read, counts = _reader(seqs, size)
  got = tune_chunks.tune_hparams_chunks(read, counts, camera, gts, num_classes=K, steps=1,
                                        capacity=CAPACITY, objective=objective,
                                        checkpoint=checkpoint, learning_rate=0.1)
  np.testing.assert_allclose(got.losses[0], want_loss, rtol=1e-5)
  np.testing.assert_allclose(got.grads["beta"][0], want_grad, rtol=1e-4, atol=1e-7)


@pytest.mark.slow
def test_the_fit_follows_tune_hparams(case):
  seqs, gts, camera = case
  frames, mask = __import__("jaxfusion").batch.stack_sequences(seqs)
  coords, labels = tune.pad_ground_truth(gts)
  whole = tune.tune_hparams(frames, camera, coords, labels, steps=3, capacity=CAPACITY,
                            mask=mask, objective="cross_entropy", per_class=True)
  read, counts = _reader(seqs, 2)
  got = tune_chunks.tune_hparams_chunks(read, counts, camera, gts, num_classes=K, steps=3,
                                        capacity=CAPACITY, objective="cross_entropy",
                                        per_class=True)
  np.testing.assert_allclose(got.losses, whole.losses, rtol=1e-4)
  np.testing.assert_allclose(got.hparams["beta"], whole.hparams["beta"], rtol=1e-4, atol=1e-6)
  assert got.rule.name == "robust_dr"


def test_bad_arguments_are_refused(case):
  seqs, gts, camera = case
  read, counts = _reader(seqs, 2)
  with pytest.raises(ValueError, match="robust rules"):
    tune_chunks.tune_hparams_chunks(read, counts, camera, gts, num_classes=K, rule="bayes",
                                    capacity=CAPACITY)
  with pytest.raises(ValueError, match="one GT per sequence"):
    tune_chunks.tune_hparams_chunks(read, counts, camera, gts[:1], num_classes=K,
                                    capacity=CAPACITY)
