"""Tuning: the surrogate's gradients against finite differences and finite at the edges, the
sweep against the sequential path and metrics.evaluate_map, the tuner, and the commands."""

import argparse
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import batch
from jaxfusion import metrics
from jaxfusion import simulation
from jaxfusion import tune
from jaxfusion.lab import tuning
from tests import engine_helpers as h

K = 4
VOXEL = 0.25
CAPACITY = 512
CAM = jf.Camera(8.0, 8.0, 4.5, 3.5)


def label_of(keys):
  """GT label of a voxel: a 2×2-voxel checkerboard of K classes in x, y."""
  return ((keys[..., 0] // 2) + 2 * (keys[..., 1] // 2)) % K


def scene(seed=0, num_frames=4, height=8, width=10):
  """A wavy surface seen from nearby poses, GT voxel labels, and a simulated noisy net."""
  rng = np.random.default_rng(seed)
  depths, poses, labels, keys = [], [], [], []
  v, u = np.mgrid[0:height, 0:width]
  for t in range(num_frames):
    T = np.eye(4, dtype=np.float32)
    T[:3, :3] = h.rotation(rng.normal(0, 0.05, 3))
    T[:3, 3] = [0.15 * t, 0.1 * np.sin(t), 0.0]
    depth = (1.2 + 0.15 * np.sin(0.7 * u + t) + 0.1 * np.cos(0.5 * v)).astype(np.float32)
    depth = h.drop_ambiguous_pixels(depth, T, CAM, VOXEL)
    d = depth.astype(np.float64)
    p_cam = np.stack([d * (u - CAM.cx) / CAM.fx, d * (v - CAM.cy) / CAM.fy, d], -1)
    key = np.floor((p_cam @ T[:3, :3].T.astype(np.float64) + T[:3, 3]) / VOXEL).astype(np.int32)
    labels.append(np.where(depth > 0, label_of(key), -1))
    keys.append(key[depth > 0])
    depths.append(depth)
    poses.append(T)
  labels = np.stack(labels)
  # An RBG key: XLA on CPU compiles threefry's random ops in seconds each, rbg in a fraction.
  probs, var = simulation.simulate_predictions(jax.random.key(seed, impl="rbg"), labels,
                                               num_classes=K, num_samples=4, outlier_rate=0.15)
  frames = jf.Frame(np.stack(depths), np.stack(poses), np.asarray(probs), np.asarray(var))
  coords = np.unique(np.concatenate(keys), axis=0)
  return frames, coords, label_of(coords).astype(np.int32)


@pytest.fixture(scope="module")
def data():
  return scene()


@functools.partial(jax.jit, static_argnames=("name", "objective"))
def loss_and_grad(hp, frames, coords, labels, *, name="D+R", objective="cross_entropy"):
  def f(hp):
    rule = jf.rules.by_name(name, aggregate="mean", **hp)
    return tune.sequence_loss(rule, frames, CAM, coords, labels, capacity=CAPACITY,
                              voxel_size=VOXEL, objective=objective)
  return jax.value_and_grad(f)(hp)


def with_empty_and_padding(coords, labels):
  """GT voxels the map never sees (empty voxels), and padding rows with label -1."""
  far = coords + 1000
  return (np.concatenate([coords, far, np.zeros((3, 3), np.int32)]),
          np.concatenate([labels, label_of(far), -np.ones(3, np.int32)]))


def f32(hp):
  return {k: jnp.float32(v) for k, v in hp.items()}


# The references below score maps with these, jitted (eagerly they dispatch op by op).
calibration_loss = jax.jit(tune.calibration_loss)
soft_iou_loss = jax.jit(tune.soft_iou_loss)


def test_gradients_match_finite_differences(data):
  frames, coords, labels = data
  coords, labels = with_empty_and_padding(coords, labels)
  hp = {"beta": 0.3, "eps": 1e-3, "alpha0": 2.0}
  value, grad = loss_and_grad(f32(hp), frames, coords, labels)
  assert 0 < float(value) < 20
  for name, step in [("beta", 1e-2), ("eps", 1e-4), ("alpha0", 1e-1)]:
    up = loss_and_grad(f32(dict(hp, **{name: hp[name] + step})), frames, coords, labels)[0]
    down = loss_and_grad(f32(dict(hp, **{name: hp[name] - step})), frames, coords, labels)[0]
    fd = (float(up) - float(down)) / (2 * step)
    np.testing.assert_allclose(float(grad[name]), fd, rtol=5e-2, atol=1e-4, err_msg=name)
  assert abs(float(grad["beta"])) > 1e-3   # β matters on this data


def test_gradients_finite_at_zero_variance_one_hot_and_empty_voxels(data):
  frames, coords, labels = data
  coords, labels = with_empty_and_padding(coords, labels)
  one_hot = jax.nn.one_hot(np.argmax(frames.probs, -1), K)
  frames = frames._replace(probs=np.asarray(one_hot), var=np.zeros_like(frames.var))
  for beta in (0.0, 0.5, 1.0):
    value, grad = loss_and_grad(f32({"beta": beta, "eps": 1e-12, "alpha0": 0.0}), frames,
                                coords, labels)
    assert np.isfinite(float(value))
    assert all(np.isfinite(float(g)) for g in grad.values()), grad
  # No scored GT voxel at all: loss 0, gradient 0.
  value, grad = loss_and_grad(f32({"beta": 0.3, "eps": 1e-12, "alpha0": 0.0}), frames, coords,
                              -np.ones_like(labels))
  assert float(value) == 0.0 and float(grad["beta"]) == 0.0


@pytest.mark.slow
def test_sweep_equals_sequential_maps_scored_with_metrics(data):
  frames, coords, labels = data
  betas = [0.0, 0.3, 0.9]
  out = tune.sweep_beta(frames, CAM, coords, labels, betas=betas, rule="D+R",
                        capacity=CAPACITY, voxel_size=VOXEL)
  gt = {"coords": coords, "labels": labels}
  for r, beta in enumerate(betas):
    rule = jf.rules.robust(beta=beta)
    state = jf.init_map(capacity=CAPACITY, num_classes=K, voxel_size=VOXEL, rule=rule)
    state = jf.fuse_sequence(state, frames, CAM, rule)
    ref = metrics.evaluate_map(jf.read_map(state), gt, K)
    np.testing.assert_array_equal(out["confusion"][r], ref["confusion"])
    assert out["miou"][r] == pytest.approx(ref["miou"])
    assert out["accuracy"][r] == pytest.approx(ref["accuracy"])
    assert out["loss"][r] == pytest.approx(
        float(calibration_loss(state, coords, labels)), rel=1e-5)
  assert out["dropped"].sum() == 0


def test_tuner_lowers_the_loss_and_keeps_beta_in_range(data):
  frames, coords, labels = data
  res = tune.tune_hparams(frames, CAM, coords, labels, rule="D+R", init={"beta": 1.5},
                          train=("beta", "eps"), steps=4, learning_rate=0.3,
                          capacity=CAPACITY, voxel_size=VOXEL)
  assert res.losses.shape == (5,) and res.path["beta"].shape == (5,)
  assert res.path["beta"][0] == pytest.approx(1 - 1e-4, abs=1e-6)   # clamped by the sigmoid
  assert np.all((res.path["beta"] > 0) & (res.path["beta"] < 1))
  assert res.losses[-1] < res.losses[0]
  assert res.rule.name == "robust_dr" and 0 < res.hparams["beta"] < 1
  assert res.hparams["eps"] > 0 and np.all(np.isfinite(res.grads["eps"]))


def test_constrain_round_trip_and_tuner_errors(data):
  hp = {"beta": 0.3, "eps": 1e-6, "alpha0": 6.9}
  back = tune.constrain(tune.unconstrain(hp))
  for k, v in hp.items():
    assert float(back[k]) == pytest.approx(v, rel=1e-5)
  assert 0 < float(tune.constrain({"beta": jnp.float32(-40.0)})["beta"]) < 1e-10 + 1
  frames, coords, labels = data
  kw = dict(capacity=CAPACITY, voxel_size=VOXEL, steps=1)
  with pytest.raises(ValueError, match="only the robust rules"):
    tune.tune_hparams(frames, CAM, coords, labels, rule="bayes", **kw)
  with pytest.raises(ValueError, match="tunes"):
    tune.tune_hparams(frames, CAM, coords, labels, rule="R", train=("eps",), **kw)
  with pytest.raises(ValueError, match="eps must be"):
    tune.tune_hparams(frames, CAM, coords, labels, init={"eps": -1.0}, **kw)
  with pytest.raises(ValueError, match="GT must be"):
    tune.sweep_beta(frames, CAM, coords[:, :2], labels, betas=[0.3], capacity=CAPACITY)


@pytest.mark.slow
def test_commands_run(data, tmp_path, monkeypatch):
  """The sweep and tune-beta commands end to end, on the small scene instead of the rendered
  synthetic world (which `load_calibration_sequence` renders at the sizes given)."""
  frames, coords, labels = data

  def load(spec, **kwargs):
    del kwargs
    return {"name": spec, "frames": frames, "camera": CAM, "num_classes": K,
            "gt": {"coords": coords, "labels": labels}, "source": "test scene",
            "capacity": CAPACITY}

  monkeypatch.setattr(tuning, "load_calibration_sequence", load)
  parser = argparse.ArgumentParser()
  sub = parser.add_subparsers()
  tuning.add_sweep_parser(sub)
  tuning.add_tune_beta_parser(sub)
  args = parser.parse_args(["sweep", "--num-betas", "3", "--beta-max", "0.9", "--voxel-size",
                            str(VOXEL), "--json", str(tmp_path / "s.json"),
                            "--plot", str(tmp_path / "s.png")])
  assert args.func(args) == 0
  swept = json.loads((tmp_path / "s.json").read_text())
  assert len(swept["miou"]) == 3 and (tmp_path / "s.png").exists()
  args = parser.parse_args(["tune-beta", "--steps", "4", "--learning-rate", "0.3", "--tune",
                            "beta,eps", "--held-out", "a:1,b:2", "--voxel-size", str(VOXEL),
                            "--json", str(tmp_path / "t.json")])
  assert args.func(args) == 0
  tuned = json.loads((tmp_path / "t.json").read_text())
  assert 0 < tuned["hparams"]["beta"] < 1 and len(tuned["held_out"]) == 2


# --- the soft-IoU objective, per-class tuning, the protocol ------------------------------------
def test_soft_iou_equals_hard_iou_on_one_hot_posteriors():
  """Hand-computed: labels [0,0,1,1,2,2], predictions [0,1,1,1,0,2] (+ a class-3 prediction on a
  row that is not valid, + class 3 absent from the GT): IoU 1/3, 2/3, 1/2 → mIoU 0.5."""
  labels = np.array([0, 0, 1, 1, 2, 2, 2], np.int32)
  pred = np.array([0, 1, 1, 1, 0, 2, 3])
  valid = np.array([True] * 6 + [False])
  posterior = jax.nn.one_hot(pred, 4)
  counts = tune.soft_confusion(posterior, jnp.asarray(labels), jnp.asarray(valid))
  np.testing.assert_allclose(counts["intersection"], [1, 2, 1, 0])
  np.testing.assert_allclose(counts["pred"], [2, 3, 1, 0])
  np.testing.assert_allclose(counts["gt"], [2, 2, 2, 0])
  assert float(tune.soft_miou(counts)) == pytest.approx(0.5, abs=1e-7)
  cm = metrics.confusion_matrix(labels[valid], pred[valid], 4)
  assert float(tune.soft_miou(counts)) == pytest.approx(metrics.mean_iou(cm), abs=1e-7)
  # Soft posteriors count partially: class 0 I = 0.6, P = 0.9, G = 1 → 0.6 / 1.3; class 1
  # I = 0.7, P = 1.1, G = 1 → 0.7 / 1.4.
  soft = tune.soft_confusion(jnp.array([[0.6, 0.4], [0.3, 0.7]]), jnp.array([0, 1]),
                             jnp.array([True, True]))
  assert float(tune.soft_miou(soft)) == pytest.approx((0.6 / 1.3 + 0.7 / 1.4) / 2, rel=1e-6)


def test_soft_iou_gradient_matches_finite_differences_and_is_finite(data):
  frames, coords, labels = data
  coords, labels = with_empty_and_padding(coords, labels)
  hp = {"beta": 0.3, "eps": 1e-3, "alpha0": 2.0}
  value, grad = loss_and_grad(f32(hp), frames, coords, labels, objective="soft_iou")
  assert 0 < float(value) < 1
  step = 1e-2
  up = loss_and_grad(f32(dict(hp, beta=0.3 + step)), frames, coords, labels,
                     objective="soft_iou")[0]
  down = loss_and_grad(f32(dict(hp, beta=0.3 - step)), frames, coords, labels,
                       objective="soft_iou")[0]
  fd = (float(up) - float(down)) / (2 * step)
  np.testing.assert_allclose(float(grad["beta"]), fd, rtol=5e-2, atol=1e-5)
  assert all(np.isfinite(float(g)) for g in grad.values())
  # One-hot posteriors at zero variance, β = 0 and 1: still finite.
  one_hot = jax.nn.one_hot(np.argmax(frames.probs, -1), K)
  hard = frames._replace(probs=np.asarray(one_hot), var=np.zeros_like(frames.var))
  for beta in (0.0, 1.0):
    value, grad = loss_and_grad(f32({"beta": beta, "eps": 1e-12, "alpha0": 0.0}), hard, coords,
                                labels, objective="soft_iou")
    assert np.isfinite(float(value)) and all(np.isfinite(float(g)) for g in grad.values())


def batch_of(seeds):
  scenes = [scene(seed=s) for s in seeds]
  frames, mask = jf.stack_sequences([f for f, _, _ in scenes])
  coords, labels = tune.pad_ground_truth([{"coords": c, "labels": l} for _, c, l in scenes])
  return {"names": [f"scene_{s}" for s in seeds], "frames": frames, "mask": mask, "camera": CAM,
          "coords": coords, "labels": labels, "capacity": CAPACITY, "num_classes": K,
          "source": "test scenes", "scenes": scenes}


# The tests below share compiled shapes: one batch of two scenes, rule stacks of R = 2 scalar
# and R = 1 per-class rules (the protocol's and the comparison's shapes), aggregate "sum".
@pytest.fixture(scope="module")
def two():
  return batch_of([0, 1])


@pytest.mark.slow
def test_objective_selection_and_per_class_tuning(two):
  args = (two["frames"], CAM, two["coords"], two["labels"])
  kw = dict(rule="D+R", steps=2, learning_rate=0.3, capacity=CAPACITY, voxel_size=VOXEL,
            mask=two["mask"])
  # The batch losses each objective starts from, as the sweep reports them (pooled counts).
  out = tune.sweep(*args, jf.rules.stack([jf.rules.robust(beta=0.3), jf.rules.robust(beta=0.5)]),
                   capacity=CAPACITY, voxel_size=VOXEL, mask=two["mask"])
  start = {"cross_entropy": out["loss_mean"][0], "soft_iou": out["soft_iou_loss_pooled"][0]}
  for objective in tune.OBJECTIVES:
    res = tune.tune_hparams(*args, objective=objective, **kw)
    assert res.objective == objective
    assert res.losses[0] == pytest.approx(float(start[objective]), rel=1e-5)
  assert start["cross_entropy"] != pytest.approx(start["soft_iou"], rel=1e-2)
  assert tune.tune_hparams.__kwdefaults__["objective"] == tune.DEFAULT_OBJECTIVE
  res = tune.tune_hparams(*args, per_class=True, **kw)
  beta = res.hparams["beta"]
  assert isinstance(beta, np.ndarray) and beta.shape == (K,)
  assert np.all((beta > 0) & (beta < 1)) and len(set(np.round(beta, 6))) > 1
  assert res.path["beta"].shape == (3, K) and res.grads["beta"].shape == (2, K)
  assert res.rule.hparams["beta"].shape == (K,) and res.losses[-1] < res.losses[0]
  with pytest.raises(ValueError, match="objective must be one of"):
    tune.tune_hparams(*args, objective="miou", **kw)
  with pytest.raises(ValueError, match=r"beta has shape \(3,\)"):
    tune.tune_hparams(*args, init={"beta": [0.3] * 3}, **kw)


@pytest.mark.slow
def test_evaluate_rules_mixes_scalar_and_per_class_rules_exactly(two):
  rules = [jf.rules.robust(beta=0.3), jf.rules.robust(beta=[0.1, 0.9, 0.3, 0.5]),
           jf.rules.robust(beta=0.7)]
  outs = tune.evaluate_rules(rules, two["frames"], CAM, two["coords"], two["labels"],
                             capacity=CAPACITY, voxel_size=VOXEL, mask=two["mask"])
  for rule, out in zip(rules, outs):
    for b, (frames, coords, labels) in enumerate(two["scenes"]):
      state = jf.init_map(capacity=CAPACITY, num_classes=K, voxel_size=VOXEL, rule=rule)
      state = jf.fuse_sequence(state, frames, CAM, rule)
      ref = metrics.evaluate_map(jf.read_map(state), {"coords": coords, "labels": labels}, K)
      np.testing.assert_array_equal(out["confusion"][b], ref["confusion"])
      assert out["soft_iou_loss"][b] == pytest.approx(
          float(soft_iou_loss(state, coords, labels)), rel=1e-5)


@pytest.mark.slow
def test_protocol_and_comparison_commands(two, tmp_path, monkeypatch):
  """tune-protocol and tune-compare end to end (the same two scenes stand in for both splits,
  to reuse compiled shapes): intervals, paired differences, per-class β and the PNGs."""
  seen = []

  def load(units, **kwargs):
    seen.append((units, kwargs["front_end"]))
    return two

  monkeypatch.setattr(tuning, "load_sequence_batch", load)
  parser = argparse.ArgumentParser()
  sub = parser.add_subparsers()
  tuning.add_tune_protocol_parser(sub)
  tuning.add_tune_compare_parser(sub)
  common = ["--envs", "office", "--trajectories", "0", "--calibration-seeds", "1",
            "--held-out-seeds", "3", "--steps", "2", "--voxel-size", str(VOXEL)]
  args = parser.parse_args(["tune-protocol", *common, "--resamples", "50", "--out",
                            str(tmp_path / "p")])
  assert args.func(args) == 0
  assert seen == [([("office", 0, 1)], None), ([("office", 0, 3)], None)]
  out = json.loads((tmp_path / "p" / "protocol.json").read_text())
  methods = out["methods"]
  assert list(methods) == ["β = 0.3", "scalar β*", "per-class β*"]
  assert len(methods["per-class β*"]["beta"]) == K and 0 < methods["scalar β*"]["beta"] < 1
  for m in methods.values():
    assert m["miou"]["low"] <= m["miou"]["estimate"] <= m["miou"]["high"]
    assert len(m["miou_per_sequence"]) == 2
  assert methods["β = 0.3"]["vs_baseline"] is None
  diff = methods["scalar β*"]["vs_baseline"]
  assert diff["estimate"] == pytest.approx(
      methods["scalar β*"]["miou"]["estimate"] - methods["β = 0.3"]["miou"]["estimate"])
  assert (tmp_path / "p" / "per_class_beta.png").stat().st_size > 1000
  args = parser.parse_args(["tune-compare", *common, "--num-betas", "2", "--out",
                            str(tmp_path / "c")])
  assert args.func(args) == 0
  out = json.loads((tmp_path / "c" / "compare.json").read_text())
  assert set(out["objectives"]) == set(tune.OBJECTIVES)
  assert len(out["grid"]["held_out"]["miou"]) == 2
  assert (tmp_path / "c" / "compare.png").stat().st_size > 1000
  with pytest.raises(ValueError, match="disjoint"):
    tuning._protocol_batches(parser.parse_args(  # pylint: disable=protected-access
        ["tune-protocol", "--calibration-seeds", "1", "--held-out-seeds", "1"]))
