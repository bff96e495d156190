"""The study: the oracle bound, histogram statistics, the cache key, and a tiny end-to-end run
with a simulated front end (the headroom classification and the pixel→voxel observations it
counts are tested with the library, tests/library/test_observations.py)."""

import json
import os

import jax
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import observations
from jaxfusion.lab import cli
from jaxfusion.lab import frontend
from jaxfusion.lab import stats
from jaxfusion.lab import study
from tests.library.test_observations import plane_scene

# Shapes shared with tests/lab/test_demo.py (the capacity of its `demo` run) and
# tests/lab/test_viewer_scene_data.py, so that compiled fusion steps are reused.
H, W, CAPACITY = 24, 32, 2**17
K = 7


class SimulatedFrontEnd:
  """A deterministic stand-in for the network: a fixed colour → class map plus dropout noise."""
  model_id = "simulated-test"

  def __init__(self):
    rng = np.random.default_rng(0)
    self.weights = rng.normal(0.0, 3.0, (3, K)).astype(np.float32)
    self.calls = 0

  def predict(self, rgb, *, num_samples, key):
    self.calls += 1
    logits = np.asarray(rgb, np.float32) / 255.0 @ self.weights
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    samples = _softmax(logits[None] + rng.normal(0.0, 1.0, (num_samples,) + logits.shape))
    return _softmax(logits), samples.mean(0), samples.var(0)


def _softmax(x):
  e = np.exp(x - x.max(-1, keepdims=True))
  return (e / e.sum(-1, keepdims=True)).astype(np.float32)


def test_the_analyses_of_pixel_observations_keep_their_names_here():
  for name in ("HEADROOM", "alpha_of_prediction", "classify_voxels", "pixel_observations"):
    assert getattr(study, name) is getattr(observations, name), name


@pytest.mark.slow
def test_oracle_bounds_every_rule_and_recovers_every_outvoted_voxel():
  rng = np.random.default_rng(2)
  seq, gt, keys, valid = plane_scene(rng)
  seq.rgb = rng.integers(0, 256, seq.depth.shape + (3,), dtype=np.uint8)
  index = {tuple(c): i for i, c in enumerate(gt["coords"])}
  g = np.array([[index.get(tuple(k), 0) for k in frame] for frame in keys]).reshape(
      seq.depth.shape)                                      # GT voxel of each pixel
  t = np.arange(len(keys))[:, None, None]
  # Errors are coherent per voxel and frame: in frame t all pixels of voxel v vote for v's
  # wrong class with probability p_v (p_v = 1 for a fifth of the voxels: never right). Right
  # pixels are 0.6-confident with a low variance; wrong ones 0.8-confident, half of them with
  # a high variance.
  num_gt = len(gt["coords"])
  p_wrong = np.where(rng.uniform(size=num_gt) < 0.2, 1.0, rng.uniform(size=num_gt))
  wrong_class = (gt["labels"] + rng.integers(1, K, num_gt)) % K
  wrong = (rng.uniform(size=(len(keys), num_gt)) < p_wrong)[t, g]
  y = gt["labels"][g]
  vote = np.where(wrong, wrong_class[g], y)
  conf = np.where(wrong, 0.8, 0.6)
  probs = np.full(y.shape + (K,), 0.0, np.float32)
  probs[...] = ((1 - conf) / (K - 1))[..., None]
  np.put_along_axis(probs, vote[..., None], conf[..., None], -1)
  var = np.where((wrong & (rng.uniform(size=y.shape) < 0.5))[..., None], 0.05, 0.002)
  preds = {"det": probs, "mean": probs, "var": var.astype(np.float32) * np.ones_like(probs)}
  config = study.StudyConfig.of(height=H, width=W, capacity=CAPACITY, voxel_size=0.5)
  res = study.analyze_sequence(seq, preds, gt, config)
  head = res["headroom"]
  assert np.all(head > 0), head                            # every category occurs
  assert head.sum() == len(gt["coords"])
  oracle = res["correct"][study.ORACLE]
  np.testing.assert_array_equal(oracle[:2], head[:2])
  assert oracle[2] == res["correct"]["bayes"][2]
  for name in config.run.rules:
    cm_rule, cm_oracle = res["confusion"][name], res["confusion"][study.ORACLE]
    assert res["correct"][name].sum() == np.trace(cm_rule), name
    assert np.all(res["correct"][name] <= oracle), name
    assert stats.accuracy(cm_oracle) >= stats.accuracy(cm_rule), name
    assert stats.miou(cm_oracle) >= stats.miou(cm_rule), name
  # α histograms hold every pixel observation once, split by right / wrong.
  n_obs = int(valid.sum())
  assert res["alpha_hist"].sum() == n_obs == res["pixels"]["right"] + res["pixels"]["wrong"]

  # The learned rule as a seventh method: set to D+R at the run's β it labels as D+R does (the
  # same equations through other XLA fusions: a near tie may flip), and the oracle bounds it.
  learned = jf.rules.learned_special_case("robust_dr", beta=config.run.beta)
  with_learned = study.StudyConfig.of(height=H, width=W, capacity=CAPACITY, voxel_size=0.5,
                                      learned=learned)
  assert with_learned.methods == list(config.run.rules) + [study.LEARNED, study.ORACLE]
  res = study.analyze_sequence(seq, preds, gt, with_learned)
  assert np.abs(res["confusion"][study.LEARNED] - res["confusion"]["robust_dr"]).sum() <= 2
  assert np.all(res["correct"][study.LEARNED] <= oracle)

  # GLFS with the all-ones table is Bayes on the MC mean; a variant is one more learned row
  # (here D+R again, reading context at zero weight); both stay under the oracle.
  glfs = {"table": np.ones((K, 5, 4)).tolist()}
  variant = {**learned, "context": ["depth", "luminance"], "context_theta": [0.0, 0.0]}
  # A member of the rule family with the same table is one more row, compared with GLFS.
  member = ("fam", {"table": glfs["table"], "moment_weights": [0.0] * 6}, "family")
  more = study.StudyConfig.of(height=H, width=W, capacity=CAPACITY, voxel_size=0.5,
                              learned=learned, glfs=glfs, variants=(("ctx", variant), member))
  assert more.methods == list(config.run.rules) + [study.LEARNED, study.GLFS, "learned:ctx",
                                                   "learned:fam", study.ORACLE]
  assert ("learned:fam", study.GLFS) in more.comparisons and (
      study.LEARNED, "learned:fam") not in more.comparisons
  assert ("learned:ctx", "bayes") in more.comparisons and (study.LEARNED, study.GLFS) in \
      more.comparisons and more.comparisons[-1] == (study.ORACLE, "bayes")
  res = study.analyze_sequence(seq, preds, gt, more)
  state = jf.init_map(capacity=more.run.capacity, num_classes=K,
                      voxel_size=more.run.voxel_size, rule=jf.rules.bayes())
  bayes_mean = jf.read_map(jf.fuse_sequence(state, jf.Frame(seq.depth, seq.T_world_cam,
                                                            preds["mean"]), seq.camera,
                                            jf.rules.bayes()))
  np.testing.assert_array_equal(
      res["confusion"][study.GLFS],
      jf.metrics.evaluate_map(bayes_mean, gt, K)["confusion"])
  np.testing.assert_array_equal(res["confusion"]["learned:fam"], res["confusion"][study.GLFS])
  assert np.abs(res["confusion"]["learned:ctx"] - res["confusion"][study.LEARNED]).sum() <= 2
  for name in (study.GLFS, "learned:ctx"):
    assert np.all(res["correct"][name] <= oracle)
  assert study.display("learned:ctx") == "Learned (ctx)" and study.display("glfs") == "GLFS"
  # Reliability counts cover the GT voxels each map holds.
  for name in (study.GLFS, "learned:ctx", "bayes"):
    assert res["calibration"][name].shape == (jf.metrics.CALIBRATION_BINS, 3)
    assert res["calibration"][name][:, 0].sum() == res["confusion"][name].sum()
  # Per-feature histograms hold every observation once, right then wrong.
  assert set(res["feature_hist"]) == set(observations.FEATURE_RANGES)
  for counts in res["feature_hist"].values():
    assert counts.shape == (2, observations.FEATURE_BINS)
    assert counts[0].sum() == res["pixels"]["right"] and counts[1].sum() == res["pixels"]["wrong"]


def test_histogram_auroc_and_median_against_direct_computation():
  rng = np.random.default_rng(3)
  right = rng.integers(0, 20, 300)
  wrong = rng.integers(0, 14, 200)
  edges = np.arange(21.0)
  hist = np.stack([np.histogram(right, edges)[0], np.histogram(wrong, edges)[0]])
  direct = np.mean((right[:, None] > wrong[None]) + 0.5 * (right[:, None] == wrong[None]))
  assert jf.metrics.auroc_from_histograms(hist[None])[0] == pytest.approx(direct)
  assert study.histogram_median(np.bincount(np.full(5, 3), minlength=20), edges) == 3.5
  assert np.isnan(jf.metrics.auroc_from_histograms(np.zeros((2, 20))))


class _Images:
  """What `cached_predictions` reads of a sequence: name, rgb, length."""
  name = "fake_0_test"

  def __init__(self, rgb):
    self.rgb = rgb

  def __len__(self):
    return len(self.rgb)


def test_cache_key_changes_with_the_images(tmp_path):
  front = SimulatedFrontEnd()
  rgb = np.zeros((2, 4, 5, 3), np.uint8)
  for value in (0, 0, 9):
    seq = _Images(rgb + np.uint8(value))
    frontend.cached_predictions(front, seq, layout_seed=0, shift=1.0, num_samples=2, mc_seed=0,
                                cache_dir=str(tmp_path))
  assert len(os.listdir(tmp_path)) == 2 and front.calls == 2


@pytest.mark.slow
def test_tiny_study_end_to_end(tmp_path):
  # Layout seed 0, office, trajectory 0, 3 frames at 24×32: the scene of test_demo.py,
  # so that the renderer's compiled shapes are shared when both run.
  config = study.StudyConfig.of(layout_seeds=(0,), shifts=(0.0, 1.0), envs=("office",),
                                trajectories=(0,), num_frames=3, height=H, width=W,
                                num_samples=3, capacity=CAPACITY, num_resamples=50)
  front = SimulatedFrontEnd()
  out = study.run_study(config, str(tmp_path), front_end=front)
  for name in ("study.md", "study.csv", "study.json", "miou_vs_shift.png",
               "differences_vs_shift.png", "headroom.png", "alpha_hist.png"):
    path = tmp_path / name
    assert path.exists() and path.stat().st_size > 200, name
    if name.endswith(".png"):
      assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
  with open(tmp_path / "study.json") as f:
    payload = json.load(f)
  assert set(payload["summary"]) == {"0", "1"} and len(payload["sequences"]) == 2
  shift0 = payload["summary"]["0"]
  assert set(shift0["methods"]) == {"Sum probs", "Sum labels", "Bayesian", "R", "D", "D+R",
                                    "Oracle"}
  assert "D+R − Bayesian" in shift0["differences"]
  # One sequence per shift: every interval collapses onto its estimate.
  for iv in (shift0["methods"]["D+R"]["miou"], shift0["differences"]["D+R − Bayesian"]["miou"]):
    assert iv["low"] == iv["high"] == pytest.approx(iv["estimate"])
  shares = [shift0["headroom"][c]["estimate"] for c in study.HEADROOM]
  assert sum(shares) == pytest.approx(1.0)
  assert "| D+R − Bayesian |" in out["table"] and "Oracle" in out["table"]
  assert len(os.listdir(tmp_path / "cache")) == 2 and front.calls == 2
  study.run_study(config, str(tmp_path), front_end=front)
  assert front.calls == 2                                   # the cache was reused
  # A learned rule is a seventh row with its paired differences and share of the headroom.
  learned = study.StudyConfig.of(layout_seeds=(0,), shifts=(0.0, 1.0), envs=("office",),
                                 trajectories=(0,), num_frames=3, height=H, width=W,
                                 num_samples=3, capacity=CAPACITY, num_resamples=50,
                                 learned=jf.rules.learned_special_case("bayes"),
                                 learned_source="the Bayesian special case")
  out = study.run_study(learned, str(tmp_path / "learned"), front_end=front,
                        cache_dir=str(tmp_path / "cache"))
  shift1 = out["summary"]["1"]
  assert "Learned" in shift1["methods"] and "Learned − D+R" in shift1["differences"]
  assert set(shift1["oracle_share"]) == {"Sum probs", "Sum labels", "R", "D", "D+R", "Learned"}
  assert "| Learned |" in out["table"]
  # Per-class IoU from the summed confusions, as metrics computes it for one matrix.
  summed = sum(np.asarray(r["confusion"][study.LEARNED]) for r in out["sequences"]
               if r["shift"] == 1.0)
  np.testing.assert_allclose(shift1["class_iou"]["Learned"], jf.metrics.iou_from_confusion(summed))
  assert "## Per-class IoU (%) at shift 1" in out["table"]
  assert "the Bayesian special case" in (tmp_path / "learned" / "study.md").read_text()
  assert front.calls == 2
  # Every feature's AUROC per shift is in the summary and the tables.
  aurocs = shift1["feature_auroc"]
  assert set(aurocs) == set(observations.FEATURE_RANGES)
  assert all(0.0 <= v["estimate"] <= 1.0 for v in aurocs.values() if v["estimate"] is not None)
  assert "## Per-pixel features: AUROC" in out["table"] and "| incidence |" in out["table"]
  # Map calibration per method (not the oracle), from the summed reliability counts.
  assert set(shift1["ece"]) == set(shift1["methods"]) - {"Oracle"}
  bins = sum(r["calibration"][study.LEARNED] for r in out["sequences"] if r["shift"] == 1.0)
  assert shift1["ece"]["Learned"]["estimate"] == pytest.approx(
      float(jf.metrics.ece_from_bins(bins)))
  assert "## Map calibration: ECE" in out["table"]
  # Each rule's ECE against Bayes's, paired: the estimate is the difference of the two ECEs.
  assert set(shift1["ece_differences"]) == {f"{m} − Bayesian" for m in shift1["ece"]
                                            if m != "Bayesian"}
  bayes_bins = sum(r["calibration"]["bayes"] for r in out["sequences"] if r["shift"] == 1.0)
  dr_bins = sum(r["calibration"]["robust_dr"] for r in out["sequences"] if r["shift"] == 1.0)
  dr = shift1["ece_differences"]["D+R − Bayesian"]
  assert dr["estimate"] == pytest.approx(float(jf.metrics.ece_from_bins(dr_bins))
                                         - float(jf.metrics.ece_from_bins(bayes_bins)), abs=1e-9)
  assert all(v["low"] <= v["estimate"] + 1e-12 and v["estimate"] <= v["high"] + 1e-12
             for v in shift1["ece_differences"].values())
  assert "## Paired differences of map ECE" in out["table"]


def test_cli_study_help_and_bad_input(capsys):
  with pytest.raises(SystemExit) as e:
    cli.main(["study", "--help"])
  assert e.value.code == 0 and "--quick" in capsys.readouterr().out
  assert cli.main(["study", "--shifts", "1.5"]) == 2
  err = capsys.readouterr().err
  assert "shifts must lie in [0, 1]" in err and "Traceback" not in err
  with pytest.raises(ValueError, match="bayes"):
    study.StudyConfig.of(rules=("robust_dr",)).validate()
  assert cli.main(["study", "--variant", "no-equals-sign"]) == 2
  assert "--variant takes TAG=PARAMS_JSON" in capsys.readouterr().err
  assert cli.main(["study", "--glfs", "models/weights/learned_rule/params.json"]) == 2
  assert "not a GLFS table" in capsys.readouterr().err


def test_analyze_sequence_rejects_mismatched_predictions():
  seq, gt, _, _ = plane_scene(np.random.default_rng(0))
  probs = np.full(seq.depth.shape + (K,), 1.0 / K, np.float32)
  config = study.StudyConfig.of(height=H, width=W, capacity=CAPACITY)
  with pytest.raises(ValueError, match="missing"):
    study.analyze_sequence(seq, {"det": probs, "mean": probs}, gt, config)
  with pytest.raises(ValueError, match=r"\(T, H, W, K\)"):
    study.analyze_sequence(seq, {"det": probs, "mean": probs[:, :-1], "var": probs}, gt, config)


@pytest.mark.slow
def test_the_analysis_of_chunks_is_the_analysis_of_the_whole_sequence():
  """`SequenceAnalysis` fed a sequence in chunks (the streamed path of `study --data`) counts
  exactly what `analyze_sequence` counts on the whole sequence, in fixed or growing maps."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  from jaxfusion.lab import study as study_lib  # pylint: disable=import-outside-toplevel
  config = study_lib.StudyConfig.quick()
  seq = datasets.make_sequence("office", 0, num_frames=5, height=20, width=24, seed=1)
  rng = np.random.default_rng(1)
  mean = rng.dirichlet(np.ones(7), (5, 20, 24)).astype(np.float32)
  preds = {"det": mean, "mean": mean, "var": (0.03 * rng.random(mean.shape)).astype(np.float32)}
  gt = datasets.gt_voxel_labels(seq, capacity=config.run.capacity)
  whole = study_lib.analyze_sequence(seq, preds, gt, config)
  for grow in (False, True):
    analysis = study_lib.SequenceAnalysis(gt, config, 7, grow=grow)
    for idx in ([0, 1], [2, 3], [4]):
      analysis.add(seq.subset(idx), {k: v[idx] for k, v in preds.items()})
    got = analysis.result()
    for key in ("headroom", "alpha_hist", "matched", "map_only", "gt_only"):
      np.testing.assert_array_equal(got[key], whole[key], err_msg=key)
    assert got["pixels"] == whole["pixels"]
    for m in whole["confusion"]:
      np.testing.assert_array_equal(got["confusion"][m], whole["confusion"][m], err_msg=m)
      np.testing.assert_array_equal(got["correct"][m], whole["correct"][m], err_msg=m)
    for name in whole["feature_hist"]:
      np.testing.assert_array_equal(got["feature_hist"][name], whole["feature_hist"][name])
