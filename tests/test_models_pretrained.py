"""The shipped weights: load without training, match the embedded world's classes, segment its
shifted test domain far better than chance, and are more uncertain where they are wrong."""

import jax
import numpy as np
import pytest

from jaxfusion.datasets import classes, synthetic
from models import checkpoint, evaluate, sampling


@pytest.fixture(scope="module")
def model():
  return checkpoint.load_pretrained(class_names=classes.CLASS_NAMES)


def test_shipped_checkpoint_is_small_and_documented(model):
  assert checkpoint.PRETRAINED_PATH.stat().st_size < 8e6
  record = model.metadata["record"]
  for field in ("command", "seed", "data", "eval"):
    assert field in record
  assert (checkpoint.WEIGHTS_DIR / "MODEL_CARD.md").is_file()


def test_shipped_model_segments_the_shifted_test_domain(model):
  data = model.metadata["record"]["data"]
  rgb, labels = synthetic.sample_views("test", 3, height=data["height"], width=data["width"],
                                       seed=12345)
  preds = evaluate.predict_arrays(model.graphdef, model.params, rgb, key=jax.random.key(0),
                                  num_samples=8)
  num_classes = len(classes.CLASS_NAMES)
  metrics = evaluate.segmentation_metrics(
      evaluate.confusion_matrix(preds["mc_mean"].argmax(-1), labels, num_classes))
  assert metrics["pixel_accuracy"] > 0.6          # chance: 1/7
  assert metrics["miou"] > 2.0 / num_classes
  report = evaluate.uncertainty_report(preds["mc_mean"], preds["mc_var"], labels)
  assert report["mean_var_sum_wrong"] > report["mean_var_sum_right"]
  assert report["auroc_var_sum"] > 0.6


def test_shipped_model_rejects_a_different_class_list():
  with pytest.raises(checkpoint.CheckpointError, match="python -m models.train"):
    checkpoint.load_pretrained(class_names=classes.SCANNET_CLASS_NAMES)


def test_deterministic_pass_runs_at_another_resolution(model):
  rgb = np.zeros((40, 56, 3), np.uint8)
  probs = sampling.deterministic_probs(model.graphdef, model.params, rgb)
  assert probs.shape == (40, 56, len(classes.CLASS_NAMES))
