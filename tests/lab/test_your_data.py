"""The research commands on a researcher's own data: a tiny ScanNet-format set written from the
embedded world (`datasets.export`), with precomputed predictions, through `lab.sequences` and
each command's `--data`."""

import json
import os

import numpy as np
import pytest

import jaxfusion as jf
import jaxfusion_models
from jaxfusion import datasets
from jaxfusion.datasets import export
from jaxfusion.lab import cli
from jaxfusion.lab import sequences

SIZE = dict(num_frames=4, height=24, width=32)


def _predictions(folder, seq, *, k=7, seed=0, ids=None, var=True):
  """Dirichlet predictions peaked on the GT label (right on most pixels), one file a frame."""
  rng = np.random.default_rng(seed)
  os.makedirs(folder, exist_ok=True)
  for t in range(len(seq) if ids is None else len(ids)):
    labels = np.maximum(seq.labels[t], 0) % k if seq.labels is not None else np.zeros(
        seq.image_size, np.int64)
    alpha = np.ones(seq.image_size + (k,)) + 6.0 * np.eye(k)[labels]
    mean = alpha / alpha.sum(-1, keepdims=True)
    noise = rng.dirichlet(np.ones(k), seq.image_size)
    mean = (0.7 * mean + 0.3 * noise).astype(np.float32)
    kw = {"var": (0.05 * noise).astype(np.float32)} if var else {}
    fid = t if ids is None else ids[t]
    jf.sources.save_prediction(os.path.join(folder, f"{fid:06d}.npz"), mean=mean, **kw)


@pytest.fixture(scope="module")
def scannet_set(tmp_path_factory):
  """Two ScanNet-format scenes (layout seeds 21 and 22) with labelled meshes and predictions."""
  root = tmp_path_factory.mktemp("scans")
  preds = root / "preds"
  for seed in (21, 22):
    seq = datasets.make_sequence("office", 0, seed=seed, **SIZE)
    path = str(root / f"scene{seed:04d}_00")
    export.save_scannet(seq, path, color_size=(48, 64),
                        labelled_mesh=export.embedded_labelled_mesh("office", seed, 1.0))
    _predictions(str(preds / f"scene{seed:04d}_00"), seq, seed=seed)
  return root


def test_load_reads_predictions_by_frame_id_and_gt_in_the_label_space(scannet_set):
  options = sequences.DataOptions(predictions=str(scannet_set / "preds"),
                                  label_space="embedded")
  item = sequences.load(f"scannet:{scannet_set}/scene0021_00", options)
  assert item.name == "scene0021_00" and item.class_names == datasets.CLASS_NAMES
  assert item.predictions["mean"].shape == (4, 24, 32, 7)
  assert item.predictions["det"] is item.predictions["mean"]   # no det in the files
  embedded = datasets.make_sequence("office", 0, seed=21, **SIZE)
  gt = datasets.gt_voxel_labels(embedded)
  assert len(item.gt["labels"]) == pytest.approx(len(gt["labels"]), rel=0.05)


def test_load_with_stride_matches_frames_by_id(scannet_set):
  options = sequences.DataOptions(predictions=str(scannet_set / "preds"), stride=2,
                                  label_space="embedded")
  item = sequences.load(f"scannet:{scannet_set}/scene0021_00", options)
  full = sequences.load(f"scannet:{scannet_set}/scene0021_00",
                        sequences.DataOptions(predictions=str(scannet_set / "preds"),
                                              label_space="embedded"))
  assert item.sequence.info["frame_ids"] == [0, 2]
  np.testing.assert_array_equal(item.predictions["mean"], full.predictions["mean"][[0, 2]])


def test_missing_predictions_are_an_error_or_skipped(scannet_set, tmp_path):
  seq = datasets.load_spec(f"scannet:{scannet_set}/scene0021_00", label_space="embedded")
  _predictions(str(tmp_path / "scene0021_00"), seq, ids=[0, 1, 3])   # frame 2 has none
  spec = f"scannet:{scannet_set}/scene0021_00"
  base = dict(predictions=str(tmp_path), label_space="embedded")
  with pytest.raises(ValueError, match="no file for 1 of the 4 frames .*frame 2"):
    sequences.load(spec, sequences.DataOptions(**base))
  item = sequences.load(spec, sequences.DataOptions(**base, missing="skip"))
  assert item.skipped == 1 and item.sequence.info["frame_ids"] == [0, 1, 3]
  assert len(item.sequence) == len(item.predictions["mean"]) == 3


def test_predictions_of_another_label_space_are_refused(scannet_set, tmp_path):
  seq = datasets.load_spec(f"scannet:{scannet_set}/scene0021_00", label_space="embedded")
  _predictions(str(tmp_path / "scene0021_00"), seq, k=5)
  spec = f"scannet:{scannet_set}/scene0021_00"
  with pytest.raises(ValueError, match="predictions have 5 classes but the GT's label space has "
                                       "12"):
    sequences.load(spec, sequences.DataOptions(predictions=str(tmp_path)))   # scannet12 GT
  with pytest.raises(FileNotFoundError, match="no folder .*scene0022_00"):
    sequences.load(f"scannet:{scannet_set}/scene0022_00",
                   sequences.DataOptions(predictions=str(tmp_path)))


def _main(argv, capsys):
  code = cli.main(argv)
  out, err = capsys.readouterr()
  return code, out, err


def test_run_takes_every_rule_of_the_study(scannet_set, tmp_path, capsys):
  spec = f"scannet:{scannet_set}/scene0021_00"
  args = ["run", "--data", spec, "--predictions", str(scannet_set / "preds" / "scene0021_00"),
          "--label-space", "embedded", "--no-geometry", "--out", str(tmp_path)]
  code, out, _ = _main(args + ["--rule", "glfs"], capsys)
  assert code == 0 and "mIoU" in out
  state, rule, _ = jf.io.load_map(str(tmp_path / "scene0021_00_glfs.npz"))   # saved whole
  assert rule.name == "glfs" and rule.context == ("depth", "incidence")
  seq = datasets.load_spec(spec)
  _predictions(str(tmp_path / "p12"), seq, k=12)         # the paper's 12 classes: GLFS has 7
  code, _, err = _main(["run", "--data", spec, "--predictions", str(tmp_path / "p12"),
                        "--no-geometry", "--rule", "glfs", "--out", str(tmp_path)], capsys)
  lines = [line for line in err.splitlines() if line.startswith("jaxfusion")]
  assert code == 2 and len(lines) == 1 and "fitted for 7 classes, the data has 12" in lines[0]


def test_run_with_the_shipped_family_rule_saves_its_spatial_kernel(scannet_set, tmp_path,
                                                                   capsys):
  spec = f"scannet:{scannet_set}/scene0021_00"
  code, out, _ = _main(["run", "--data", spec, "--predictions",
                        str(scannet_set / "preds" / "scene0021_00"), "--label-space", "embedded",
                        "--no-geometry", "--rule", "family", "--out", str(tmp_path)], capsys)
  assert code == 0 and "mIoU" in out
  state, rule, _ = jf.io.load_map(str(tmp_path / "scene0021_00_family.npz"))
  _, params = jf.learn.load_rule(str(jaxfusion_models.FAMILY_RULE_PATH))
  assert rule.name == "family"
  np.testing.assert_array_equal(np.asarray(state.spatial), np.asarray(params["spatial"],
                                                                      np.float32))
  smoothed = jf.read_map(state)["posterior"]
  plain = jf.read_map(state.replace(spatial=None))["posterior"]
  assert np.all(np.isfinite(smoothed)) and not np.allclose(smoothed, plain)


@pytest.mark.slow
def test_study_on_a_scannet_set(scannet_set, tmp_path, capsys):
  out_dir = tmp_path / "study"
  code, out, _ = _main(["study", "--data", f"scannet:{scannet_set}/scene00*", "--predictions",
                        str(scannet_set / "preds"), "--label-space", "embedded",
                        "--resamples", "20", "--out", str(out_dir)], capsys)
  assert code == 0
  summary = json.loads((out_dir / "study.json").read_text())["summary"]
  assert list(summary) == ["data"] and summary["data"]["num_sequences"] == 2
  methods = summary["data"]["methods"]
  assert {"Bayesian", "D+R", "Learned", "GLFS", "Oracle"} <= set(methods)
  assert methods["Oracle"]["miou"]["estimate"] >= methods["Bayesian"]["miou"]["estimate"]
  assert "your data" in out


def test_study_refuses_a_set_that_names_nothing(tmp_path, capsys):
  code, _, err = _main(["study", "--data", f"scannet:{tmp_path}/nothing*", "--out",
                        str(tmp_path)], capsys)
  assert code == 2 and "no folder matches" in err


@pytest.mark.slow
def test_fitted_rows_of_another_label_space_are_left_out(scannet_set, tmp_path, capsys):
  seq = datasets.load_spec(f"scannet:{scannet_set}/scene0021_00")
  _predictions(str(tmp_path / "preds" / "scene0021_00"), seq, k=12)
  code, out, _ = _main(["study", "--data", f"scannet:{scannet_set}/scene0021_00",
                        "--predictions", str(tmp_path / "preds"), "--resamples", "10",
                        "--out", str(tmp_path / "study")], capsys)
  assert code == 0
  assert "Learned is left out" in out and "GLFS is left out" in out
  summary = json.loads((tmp_path / "study" / "study.json").read_text())["summary"]
  assert "GLFS" not in summary["data"]["methods"]


@pytest.mark.slow
def test_sweep_and_tune_beta_on_a_scannet_set(scannet_set, capsys):
  a, b = (f"scannet:{scannet_set}/scene00{s}_00" for s in (21, 22))
  common = ["--predictions", str(scannet_set / "preds"), "--label-space", "embedded"]
  code, out, _ = _main(["sweep", "--data", a, "--num-betas", "3"] + common, capsys)
  assert code == 0 and "best β" in out
  code, out, _ = _main(["tune-beta", "--calibration-data", a, "--data", b, "--steps", "2"]
                       + common, capsys)
  assert code == 0 and "scene0022_00" in out
  code, _, err = _main(["tune-beta", "--calibration-data", a, "--data", a] + common, capsys)
  assert code == 2 and "share" in err


@pytest.mark.slow
def test_learn_rule_and_mesh_study_on_a_scannet_set(scannet_set, tmp_path, capsys):
  a, b = (f"scannet:{scannet_set}/scene00{s}_00" for s in (21, 22))
  common = ["--predictions", str(scannet_set / "preds"), "--label-space", "embedded"]
  code, out, _ = _main(["learn-rule", "--calibration-data", a, "--validation-data", b,
                        "--steps", "2", "--eval-every", "1", "--out", str(tmp_path / "lr")]
                       + common, capsys)
  assert code == 0
  params = tmp_path / "lr" / "params.json"
  assert params.exists()
  code, out, _ = _main(["mesh-study", "--data", a, b, "--resamples", "10", "--learned-rule",
                        str(params), "--out", str(tmp_path / "ms")] + common, capsys)
  assert code == 0 and "Learned" in out
  record = json.loads((tmp_path / "ms" / "mesh_study.json").read_text())
  assert record["classes"] == list(datasets.CLASS_NAMES)
  assert record["summary"]["geometry"]["fscore@0.05"] > 0.25   # 24x32 frames: a sparse mesh


@pytest.mark.slow
def test_tune_beta_streamed_fits_what_the_in_memory_fit_fits(scannet_set, tmp_path, capsys):
  a, b = (f"scannet:{scannet_set}/scene00{s}_00" for s in (21, 22))
  common = ["tune-beta", "--calibration-data", a, "--data", b, "--steps", "2",
            "--predictions", str(scannet_set / "preds"), "--label-space", "embedded"]
  code, _, _ = _main(common + ["--json", str(tmp_path / "memory.json")], capsys)
  assert code == 0
  code, out, _ = _main(common + ["--stream", "--json", str(tmp_path / "stream.json")], capsys)
  assert code == 0 and "streamed in chunks" in out
  memory = json.loads((tmp_path / "memory.json").read_text())
  stream = json.loads((tmp_path / "stream.json").read_text())
  np.testing.assert_allclose(stream["losses"], memory["losses"], rtol=1e-4)
  np.testing.assert_allclose(stream["hparams"]["beta"], memory["hparams"]["beta"], rtol=1e-4)
  assert [h["sequence"] for h in stream["held_out"]] == ["scene0022_00"]
  code, _, err = _main(["tune-beta", "--stream"], capsys)
  assert code == 2 and "--stream reads --calibration-data" in err
