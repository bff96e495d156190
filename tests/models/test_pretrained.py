"""The shipped weights: load without training, match the embedded world's classes, segment both
of its domains far better than chance, and are more uncertain where they are wrong."""

import pathlib
import tomllib

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


@pytest.mark.slow
@pytest.mark.parametrize("domain, min_accuracy, min_miou", [
    # Chance (uniform guessing over 7 classes): pixel accuracy 0.14, mIoU about 0.03.
    ("train", 0.75, 0.3),   # unseen views of the training domain
    ("test", 0.4, 0.08),    # the shifted domain: far above chance, far from perfect
])
def test_shipped_model_segments_both_domains_and_knows_its_errors(model, domain, min_accuracy,
                                                                  min_miou):
  data = model.metadata["record"]["data"]
  rgb, labels = synthetic.sample_views(domain, 4, height=data["height"], width=data["width"],
                                       seed=12345)
  preds = evaluate.predict_arrays(model.graphdef, model.params, rgb, key=jax.random.key(0),
                                  num_samples=8)
  num_classes = len(classes.CLASS_NAMES)
  metrics = evaluate.segmentation_metrics(
      evaluate.confusion_matrix(preds["mc_mean"].argmax(-1), labels, num_classes))
  assert metrics["pixel_accuracy"] > min_accuracy
  assert metrics["miou"] > min_miou
  report = evaluate.uncertainty_report(preds["mc_mean"], preds["mc_var"], labels)
  assert report["mean_var_sum_wrong"] > report["mean_var_sum_right"]
  assert report["auroc_var_sum"] > 0.6


def test_every_shipped_weight_file_is_package_data():
  """A non-editable install carries every file under models/weights (the fitted rules and the
  candidates the docs' commands load included), not only the segmentation net."""
  root = pathlib.Path(__file__).resolve().parents[2]
  config = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
  package = root / config["package-dir"]["jaxfusion_models"]
  covered = {p for g in config["package-data"]["jaxfusion_models"] for p in package.glob(g)
             if p.is_file()}
  shipped = {p for p in (package / "weights").rglob("*") if p.is_file()}
  assert len(shipped) > 10
  assert sorted(str(p.relative_to(package)) for p in shipped - covered) == []


def test_shipped_model_rejects_a_different_class_list():
  with pytest.raises(checkpoint.CheckpointError, match="python -m models.train"):
    checkpoint.load_pretrained(class_names=classes.SCANNET_CLASS_NAMES)


def test_deterministic_pass_runs_at_another_resolution(model):
  rgb = np.zeros((40, 56, 3), np.uint8)
  probs = sampling.deterministic_probs(model.graphdef, model.params, rgb)
  assert probs.shape == (40, 56, len(classes.CLASS_NAMES))


@pytest.mark.slow
def test_figure_command_writes_a_png(tmp_path):
  from models import figure
  # Same batch shape and M as the test above, so the sampler is not compiled again.
  out = figure.main(["--out", str(tmp_path / "fig3.png"), "--num-views", "4",
                     "--num-samples", "8"])
  assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
