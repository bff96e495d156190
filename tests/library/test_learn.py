"""Fitting the learned rule by gradient through fusion: the fit lowers the training loss, keeps the
best validation point, stops early, returns a valid rule, and refuses bad settings."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import learn
from tests.library.test_tune import batch_of


@pytest.fixture(scope="module")
def batches():
  return batch_of([0, 1]), batch_of([2, 3])


def test_constrain_round_trip_and_start_is_dr_like():
  values = {"theta": np.arange(6.0), "bias": 2.0, "mix": 0.3, "gate": [1.0, 2.0, 3.0],
            "beta": [0.1, 0.5, 0.9]}
  back = learn.constrain(learn.unconstrain(values))
  for name, value in values.items():
    np.testing.assert_allclose(np.asarray(back[name]), np.asarray(value), rtol=1e-5, atol=1e-6)
  start = learn.constrain(learn.start_params(4))
  assert np.asarray(start["beta"]).shape == (4,)
  np.testing.assert_allclose(np.asarray(start["beta"]), 0.3, rtol=1e-5)
  assert float(start["mix"]) == pytest.approx(0.9)
  with pytest.raises(ValueError, match="unknown learned-rule parameters to train"):
    learn.start_params(4, start={"eps": 1.0})


@pytest.mark.slow
def test_fit_lowers_the_loss_and_keeps_the_best_validation_point(batches):
  train, validation = batches
  seen = []
  res = learn.fit(train, validation, steps=8, learning_rate=0.1, eval_every=2, patience=10,
                  voxel_size=0.25,
                  progress=lambda step, loss, val: seen.append((step, loss, val)))
  assert res.steps_run == 8 and not res.stopped_early and len(seen) == 8
  assert res.train_losses[-1] < res.train_losses[0]
  steps, losses = zip(*res.validation)
  assert steps == (0, 2, 4, 6, 8)
  assert res.best_step == steps[int(np.argmin(losses))]
  assert res.rule.name == "learned" and np.asarray(res.params["beta"]).shape == (4,)
  assert 0.0 <= res.params["mix"] <= 1.0
  assert all(0.0 <= b <= 1.0 for b in res.params["beta"])
  json.dumps(res.params)                           # plain floats and lists
  # The returned rule is the kept parameters: its validation loss is the best one recorded.
  from jaxfusion import tune  # pylint: disable=import-outside-toplevel
  loss = tune.sequence_loss(res.rule, validation["frames"], validation["camera"],
                            validation["coords"], validation["labels"],
                            capacity=validation["capacity"], voxel_size=0.25,
                            mask=validation["mask"])
  assert float(loss) == pytest.approx(min(losses), rel=1e-4)


@pytest.mark.slow
def test_fit_stops_when_validation_does_not_improve(batches):
  train, validation = batches
  # A huge step size overshoots at once: validation never beats the start, patience 1 stops it.
  res = learn.fit(train, validation, steps=50, learning_rate=50.0, eval_every=1, patience=1,
                  voxel_size=0.25)
  assert res.stopped_early and res.steps_run < 50
  if res.best_step == 0:
    start = learn.constrain(learn.start_params(4))
    np.testing.assert_allclose(res.params["beta"], np.asarray(start["beta"]), rtol=1e-5)


@pytest.mark.slow
def test_fit_selecting_by_miou_keeps_the_best_validation_miou(batches):
  train, validation = batches
  res = learn.fit(train, validation, steps=6, learning_rate=0.3, eval_every=2, patience=10,
                  voxel_size=0.25, select="miou")
  steps, mious = zip(*res.validation_miou)
  assert steps == (0, 2, 4, 6) and [s for s, _ in res.validation] == list(steps)
  assert res.best_step == steps[int(np.argmax(mious))]      # the first of equal maxima
  # The kept rule's pooled validation mIoU is the best one recorded, computed independently:
  # fuse each validation sequence and score its map with metrics.
  from jaxfusion import tune  # pylint: disable=import-outside-toplevel
  cms = [np.asarray(tune.confusion(
      jf.batch.fuse_masked(jax.tree.map(lambda x, b=b: x[b], validation["frames"]),
                           validation["mask"][b], validation["camera"], res.rule,
                           capacity=validation["capacity"], num_classes=4, voxel_size=0.25,
                           max_probes=jf.state.DEFAULT_MAX_PROBES),
      validation["coords"][b], validation["labels"][b]))
         for b in range(len(validation["names"]))]
  assert jf.metrics.mean_iou(sum(cms)) == pytest.approx(max(mious), abs=1e-6)
  assert learn.fit(train, validation, steps=2, voxel_size=0.25).validation_miou == []


def test_fit_refuses_bad_settings(batches):
  train, validation = batches
  with pytest.raises(ValueError, match="steps must be >= 1"):
    learn.fit(train, validation, steps=0)
  with pytest.raises(ValueError, match="patience must be >= 1"):
    learn.fit(train, validation, patience=0)
  with pytest.raises(ValueError, match="objective"):
    learn.fit(train, validation, objective="miou")
  with pytest.raises(ValueError, match="select must be one of"):
    learn.fit(train, validation, select="accuracy")


def test_weight_grid_matches_the_rule_and_is_in_range():
  rule = jf.rules.learned(theta=[1.0, -2.0, 0.5, 0.8, -1.0, 0.3], bias=0.2)
  alphas = jnp.linspace(1.0, 12.0, 5)
  tops = jnp.linspace(0.3, 1.0, 4)
  grid = np.asarray(learn.weight_grid(rule.hparams, alphas, tops, num_classes=4))
  assert grid.shape == (5, 4) and np.all((grid >= 0) & (grid <= 1))
  assert grid.std() > 1e-3
  jf_learned = __import__("importlib").import_module("jaxfusion.rules.learned")
  probs = jnp.asarray([0.3, 0.7 / 3, 0.7 / 3, 0.7 / 3])
  var = jnp.asarray([np.exp(-1.0) - 1e-12, 0.0, 0.0, 0.0])
  w = jf_learned.pixel_weight(jf_learned.features(probs, var, 1e-12), rule.hparams)
  assert float(w) == pytest.approx(float(grid[0, 0]), rel=1e-5)


def test_start_params_shapes_for_context_per_class_weights_and_gate():
  start = learn.constrain(learn.start_params(4, context=("depth", "radius"),
                                             per_class_weights=True, gate_size=5))
  assert np.shape(start["theta"]) == (4, 6) and np.shape(start["bias"]) == (4,)
  assert np.shape(start["context_theta"]) == (4, 2) and np.shape(start["gate"]) == (5,)
  np.testing.assert_array_equal(np.asarray(start["gate"])[3:], 0.0)
  with pytest.raises(ValueError, match="gate_size"):
    learn.start_params(4, gate_size=4)


@pytest.mark.slow
@pytest.mark.parametrize("family", ["learned", "glfs"])
def test_fit_other_families_and_round_trip_their_files(batches, family, tmp_path):
  train, validation = batches
  kw = dict(context=("depth", "incidence", "label_edge"), per_class_weights=True, gate_size=5)
  res = learn.fit(train, validation, steps=2, learning_rate=0.1, eval_every=1, patience=5,
                  voxel_size=0.25, family=family, **(kw if family == "learned" else {}))
  assert res.steps_run == 2 and res.train_losses[-1] < res.train_losses[0]
  assert res.rule.name == family
  if family == "learned":
    assert res.params["context"] == list(kw["context"])
    assert np.shape(res.params["context_theta"]) == (4, 3)
    assert res.rule.context == kw["context"]
  else:
    table = np.asarray(res.params["table"])
    assert table.shape == (4, 5, 4) and np.all(table > 0)
  path = tmp_path / "params.json"
  path.write_text(json.dumps({"rule": family, "params": res.params}))
  loaded_family, params = learn.load_rule(str(path))
  assert loaded_family == family
  rule = learn.rule_of(family, params)
  for a, b in zip(jax.tree.leaves(rule.hparams), jax.tree.leaves(res.rule.hparams)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6)
  path.write_text(json.dumps({"rule": "nope", "params": {}}))
  with pytest.raises(ValueError, match="unknown 'rule'"):
    learn.load_rule(str(path))
  with pytest.raises(ValueError, match="family must be one of"):
    learn.fit(train, validation, family="mlp")


def _table(k=4, seed=0):
  return np.random.default_rng(seed).uniform(0.2, 4.0, (k, 5, 4)).astype(np.float32)


def test_family_start_begins_at_its_table_and_refuses_bad_starts():
  table = _table()
  start = learn.constrain_family(learn.family_start(4, table=table,
                                                    terms=("moments", "context", "beta", "mix"),
                                                    context=("depth",), per_class_weights=True))
  np.testing.assert_allclose(np.asarray(start["table"]), table, rtol=1e-6)
  assert np.shape(start["moment_weights"]) == (4, 6) and np.shape(start["context_weights"]) == (4, 1)
  np.testing.assert_array_equal(np.asarray(start["moment_weights"]), 0.0)
  np.testing.assert_allclose(np.asarray(start["beta"]), 1e-3, rtol=1e-3)
  assert float(start["mix"]) == pytest.approx(1e-3, rel=1e-3)
  with pytest.raises(ValueError, match="unknown family terms"):
    learn.family_start(4, table=table, terms=("gate",))
  with pytest.raises(ValueError, match="context term needs context features"):
    learn.family_start(4, table=table, terms=("context",))
  with pytest.raises(ValueError, match=r"starting table must be \(4, 5, 4\)"):
    learn.family_start(4, table=_table(k=5))
  with pytest.raises(ValueError, match="starting table"):
    learn.family_start(4, table=np.full((4, 5, 4), np.nan))


def _family_loss(batch, terms=("moments",), context=()):
  """The fit's training loss of the family as a function of its unconstrained parameters."""
  make = lambda p: jf.rules.family({**learn.constrain_family(p), "eps": 1e-12}, context=context)
  return learn._loss_fn(batch, make=make, voxel_size=0.25, objective="soft_iou")  # pylint: disable=protected-access


@pytest.mark.slow
def test_family_fit_step_gradient_matches_finite_differences(batches):
  train, _ = batches
  loss = jax.jit(_family_loss(train))
  rng = np.random.default_rng(3)
  params = {"table": jnp.log(jnp.asarray(_table())),
            "moment_weights": jnp.asarray(rng.normal(0, 0.3, 6), jnp.float32)}
  grads = jax.grad(loss)(params)
  assert np.all(np.isfinite(np.asarray(grads["moment_weights"])))
  assert np.any(np.asarray(grads["moment_weights"]) != 0)
  step = 1e-2
  for i in (0, 2, 5):                       # max probability, entropy, relative variance
    e = np.zeros(6, np.float32)
    e[i] = step
    up = {**params, "moment_weights": params["moment_weights"] + e}
    down = {**params, "moment_weights": params["moment_weights"] - e}
    fd = (float(loss(up)) - float(loss(down))) / (2 * step)
    assert float(grads["moment_weights"][i]) == pytest.approx(fd, rel=0.05, abs=2e-4)
  # And one table entry that the frames use (predicted class 0, the nearest bins).
  flat = np.asarray(grads["table"]).ravel()
  j = int(np.argmax(np.abs(flat)))
  e = np.zeros(flat.size, np.float32)
  e[j] = step
  e = e.reshape(params["table"].shape)
  fd = (float(loss({**params, "table": params["table"] + e}))
        - float(loss({**params, "table": params["table"] - e}))) / (2 * step)
  assert flat[j] == pytest.approx(fd, rel=0.05, abs=2e-4)


@pytest.mark.slow
def test_family_fit_starts_at_its_table_and_round_trips(batches, tmp_path):
  train, validation = batches
  table = _table()
  res = learn.fit(train, validation, steps=2, learning_rate=0.1, eval_every=1, patience=5,
                  voxel_size=0.25, family="family", terms=("moments", "beta"),
                  per_class_weights=True, start_table=table, select="miou", objective="soft_iou")
  # Step 0 is the starting table's GLFS maps (β ≈ 10⁻³ the only difference).
  glfs = jf.rules.glfs(table)
  start_miou = dict(res.validation_miou)[0]
  assert start_miou == pytest.approx(learn._miou_fn(validation, make=lambda p: glfs,  # pylint: disable=protected-access
                                                    voxel_size=0.25)(None), abs=0.02)
  assert res.rule.name == "family" and res.steps_run == 2
  assert set(jf.rules.family_lib.terms(res.rule)) == {"table", "moments", "beta"}
  assert np.shape(res.params["moment_weights"]) == (4, 6)
  path = tmp_path / "params.json"
  path.write_text(json.dumps({"rule": "family", "params": res.params}))
  family, params = learn.load_rule(str(path))
  rule = learn.rule_of(family, params)
  for a, b in zip(jax.tree.leaves(rule.hparams), jax.tree.leaves(res.rule.hparams)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6)


def test_map_calibration_counts_every_held_gt_voxel_once(batches):
  train, _ = batches
  out = learn.map_calibration(jf.rules.bayes(), train, voxel_size=0.25)
  bins = np.asarray(out["bins"])
  held = 0
  for scene_frames, coords, labels in train["scenes"]:
    state = jf.init_map(capacity=train["capacity"], num_classes=4, voxel_size=0.25,
                        rule=jf.rules.bayes())
    voxels = jf.read_map(jf.fuse_sequence(state, scene_frames, train["camera"], jf.rules.bayes()))
    held += int(jf.metrics.evaluate_map(voxels, {"coords": coords, "labels": labels},
                                        4)["confusion"].sum())
  assert bins[:, 0].sum() == held > 0
  assert 0.0 <= out["ece"] <= 1.0
  assert out["ece"] == pytest.approx(float(jf.metrics.ece_from_bins(bins)))
