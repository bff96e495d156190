"""The simulated view-dependent front end: its error rate, cross-view correlation and variance
separation against the generative model's closed forms (statistical tolerances), valid outputs,
the deterministic map from errors to moments against NumPy, validation, the rule equivalences the
sweep relies on, and a tiny sweep and its command. The front end with independent errors lives
in the same module (its old name in `tune` is the same function)."""

import argparse
import functools
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

import jaxfusion as jf
from jaxfusion import simulation as sim
from jaxfusion import tune
from jaxfusion.lab import simulate
from tests import engine_helpers as h

K = 5
VOXEL = 0.25
CAM = jf.Camera(12.0, 12.0, 15.5, 11.5)
H, W, T = 24, 32, 4


def block_of(keys):
  """A 2×2-voxel block index of each voxel key (x, y), and its GT label."""
  block = (keys[..., 0] // 2) * 1000 + (keys[..., 1] // 2)
  label = ((keys[..., 0] // 2) + 2 * (keys[..., 1] // 2)) % K
  return block, label


def tiny_scene(num_frames=T):
  """A slanted wall seen from a sliding camera: labels and instance ids fixed in the world."""
  depths, poses, labels, instances, keys = [], [], [], [], []
  v, u = np.mgrid[0:H, 0:W]
  for t in range(num_frames):
    T_wc = np.eye(4, dtype=np.float32)
    T_wc[:3, :3] = h.rotation(np.array([0.0, 0.05 * t, 0.0]))
    T_wc[:3, 3] = [0.2 * t, 0.05 * t, 0.0]
    depth = (2.0 + 0.02 * u + 0.01 * v).astype(np.float32)
    depth = h.drop_ambiguous_pixels(depth, T_wc, CAM, VOXEL)
    d = depth.astype(np.float64)
    p_cam = np.stack([d * (u - CAM.cx) / CAM.fx, d * (v - CAM.cy) / CAM.fy, d], -1)
    key = np.floor((p_cam @ T_wc[:3, :3].T.astype(np.float64) + T_wc[:3, 3]) / VOXEL
                   ).astype(np.int32)
    block, label = block_of(key)
    ok = depth > 0
    labels.append(np.where(ok, label, -1).astype(np.int32))
    instances.append(np.where(ok, 1 + block % 997, 0).astype(np.int32))
    keys.append(key[ok])
    depths.append(depth)
    poses.append(T_wc)
  coords = np.unique(np.concatenate(keys), axis=0)
  return {"name": "tiny", "labels": np.stack(labels), "instances": np.stack(instances),
          "depth": np.stack(depths), "T_world_cam": np.stack(poses), "camera": CAM,
          "gt": {"coords": coords, "labels": block_of(coords)[1].astype(np.int32)},
          "num_classes": K}


@pytest.fixture(scope="module")
def scene():
  return tiny_scene()


def grid_scene(num_frames=2, size=4):
  """Labels and instance ids on a fixed image grid of size×size-pixel objects (same in every
  frame, so an object's mask can be compared across views); no depth needed."""
  v, u = np.mgrid[0:H, 0:W]
  inst = 1 + (v // size) * (W // size) + (u // size)
  labels = inst % K
  return (np.broadcast_to(labels, (num_frames, H, W)).astype(np.int32),
          np.broadcast_to(inst, (num_frames, H, W)).astype(np.int32))


@functools.partial(jax.jit, static_argnames=("regions", "num_draws"))
def _draws(seed, labels, instances, depth, poses, model, *, regions, num_draws):
  """`num_draws` sequences (independent keys), each T frames: SimulatedView with (D, T, …)."""
  keys = jax.random.split(jax.random.PRNGKey(seed), num_draws)
  camera = jf.Camera(*(jnp.float32(c) for c in CAM))

  frame = functools.partial(sim.simulate_frame,
                            num_classes=K, regions=regions)

  def one(key):
    return jax.vmap(frame, in_axes=(None, 0, 0, 0, 0, 0, None, None))(
        key, labels, instances, jnp.arange(labels.shape[0]), depth, poses, camera, model)

  return jax.vmap(one)(keys)


def draws(scene_dict, model, regions, num_draws=200, seed=0):
  return _draws(seed, scene_dict["labels"], scene_dict["instances"], scene_dict["depth"],
                scene_dict["T_world_cam"], model, regions=regions, num_draws=num_draws)


# --- the error mask ---------------------------------------------------------------------------
def _grid_dict(num_frames=2):
  labels, inst = grid_scene(num_frames)
  return {"labels": labels, "instances": inst, "depth": np.zeros(labels.shape, np.float32),
          "T_world_cam": np.tile(np.eye(4, dtype=np.float32), (num_frames, 1, 1))}


@pytest.mark.parametrize("regions", sim.REGIONS)
@pytest.mark.parametrize("rate", h.main_tier_keeps([0.15, 0.5], (0.5,)))
def test_error_rate_matches_on_average(scene, regions, rate):
  model = sim.error_model(error_rate=rate, cross_view_correlation=0.6, patch_size=0.3)
  if regions == "objects":    # the image-grid objects of the correlation tests (one compile)
    scene = _grid_dict()
  view = draws(scene, model, regions)
  valid = (scene["labels"] >= 0) & ((scene["depth"] > 0) | (regions == "objects"))
  per_draw = np.asarray(view.wrong)[:, valid].mean(axis=1)      # (D,)
  se = per_draw.std() / math.sqrt(len(per_draw))
  assert abs(per_draw.mean() - rate) < 4 * se + 1e-3, (per_draw.mean(), se)
  assert not np.any(np.asarray(view.wrong)[:, ~valid])         # unlabelled: never wrong


def test_error_rate_edges(scene):
  for rate, expected in ((0.0, False), (1.0, True)):
    view = draws(scene, sim.error_model(error_rate=rate), "both")
    valid = (scene["labels"] >= 0) & (scene["depth"] > 0)
    assert np.all(np.asarray(view.wrong)[:, valid] == expected)


def _object_masks(rho, num_draws=200):
  model = sim.error_model(error_rate=0.3, cross_view_correlation=rho)
  view = draws(_grid_dict(), model, "objects", num_draws=num_draws)
  wrong = np.asarray(view.wrong)[:, :, ::4, ::4]    # one pixel per object: (D, 2, 6, 8)
  fav = np.asarray(view.favoured)[:, :, ::4, ::4]
  return wrong[:, 0].reshape(-1), wrong[:, 1].reshape(-1), fav, np.asarray(view.wrong)


def test_objects_are_wrong_as_a_whole():
  *_, full = _object_masks(0.4)
  blocks = full.reshape(200, 2, H // 4, 4, W // 4, 4)
  assert np.all(blocks == blocks[:, :, :, :1, :, :1])


def test_correlation_one_repeats_the_same_errors_in_every_view():
  a, b, fav, _ = _object_masks(1.0)
  np.testing.assert_array_equal(a, b)
  np.testing.assert_array_equal(fav[:, 0], fav[:, 1])     # the same wrong class too
  assert 0.2 < a.mean() < 0.4


@pytest.mark.parametrize("rho", [0.0, 0.5])
def test_cross_view_agreement_matches_the_bivariate_normal(rho):
  a, b, _, _ = _object_masks(rho)
  # Reference: P(wrong in both views) = Φ₂(Φ⁻¹(e), Φ⁻¹(e); ρ), from SciPy.
  z = stats.norm.ppf(0.3)
  both = stats.multivariate_normal([0, 0], [[1, rho], [rho, 1]]).cdf([z, z])
  observed = np.mean(a & b)
  se = math.sqrt(both * (1 - both) / len(a))
  assert abs(observed - both) < 4 * se + 2e-3, (observed, both)
  if rho == 0.0:       # independent views: the phi coefficient is ~0
    phi = np.corrcoef(a, b)[0, 1]
    assert abs(phi) < 4 / math.sqrt(len(a))


def test_wrong_class_is_uniform_over_the_other_classes():
  _, _, fav, full = _object_masks(0.0)
  labels, _ = grid_scene()
  y = labels[0, ::4, ::4]
  wrong = full[:, :, ::4, ::4]
  offsets = ((fav - y) % K)[wrong]
  assert not np.any(offsets == 0)
  counts = np.bincount(offsets, minlength=K)[1:]
  expected = np.full(K - 1, len(offsets) / (K - 1))
  assert stats.chisquare(counts, expected).pvalue > 1e-4


# --- the variance ------------------------------------------------------------------------------
@pytest.mark.parametrize("separation", [0.0, 2.0])
def test_variance_separation_in_nats(scene, separation):
  model = sim.error_model(error_rate=0.4, variance_separation=separation, alpha_noise=1.0,
                          cross_view_correlation=0.0)
  view = draws(scene, model, "both")
  valid = np.broadcast_to((scene["labels"] >= 0) & (scene["depth"] > 0), view.wrong.shape)
  s = sim.view_statistics(view, valid)
  assert abs(s["alpha_separation"] - separation) < 0.1, s
  # Closed form before the bound: AUROC(α → right) = Φ(s / (τ √2)).
  assert abs(s["auroc"] - stats.norm.cdf(separation / math.sqrt(2.0))) < 0.02, s
  assert abs(s["alpha_right_median"] - 7.0) < 0.1


def test_moments_against_numpy(scene):
  """τ = 0: the deterministic map from (wrong, favoured) to the Dirichlet moments."""
  model = sim.error_model(error_rate=0.5, error_confidence=0.6, confidence=0.9,
                          variance_separation=3.0, alpha_right=6.0, alpha_noise=0.0)
  view = draws(scene, model, "both")
  wrong, fav = np.asarray(view.wrong), np.asarray(view.favoured)
  labelled = np.broadcast_to(scene["labels"] >= 0, wrong.shape)
  y = np.broadcast_to(scene["labels"], wrong.shape)
  np.testing.assert_array_equal(wrong, labelled & (fav != y))
  c = np.where(wrong, 0.6, 0.9)
  c = np.where(labelled, c, 1.0 / K)
  one_hot = np.eye(K)[fav]
  probs = one_hot * c[..., None] + (1 - one_hot) * ((1 - c) / (K - 1))[..., None]
  var_f = np.minimum(np.exp(-(6.0 - 3.0 * wrong)), c * (1 - c))
  var = probs * (1 - probs) * (var_f / (c * (1 - c)))[..., None]
  np.testing.assert_allclose(np.asarray(view.probs), probs, rtol=1e-6, atol=1e-7)
  np.testing.assert_allclose(np.asarray(view.var), var, rtol=1e-5, atol=1e-9)


@settings(max_examples=8, deadline=None)
@given(rate=st.floats(0, 1), conf=st.floats(0.25, 0.99), conf_e=st.floats(0.25, 0.99),
       rho=st.floats(0, 1), noise=st.floats(0, 3), frac=st.floats(0, 0.98),
       seed=st.integers(0, 2**31 - 1))
def test_outputs_are_valid_distributions(scene, rate, conf, conf_e, rho, noise, frac, seed):
  alpha_right = 8.0
  max_sep = alpha_right + math.log(conf_e * (1 - conf_e))
  model = sim.error_model(error_rate=rate, confidence=conf, error_confidence=conf_e,
                          cross_view_correlation=rho, alpha_noise=noise,
                          variance_separation=frac * max_sep, alpha_right=alpha_right)
  view = sim.simulate_sequence(jax.random.PRNGKey(seed), scene["labels"], scene["instances"],
                               num_classes=K, depth=scene["depth"],
                               T_world_cam=scene["T_world_cam"], camera=CAM, model=model)
  probs, var = np.asarray(view.probs), np.asarray(view.var)
  assert np.all(np.isfinite(probs)) and np.all(np.isfinite(var))
  assert np.all(probs >= 0)
  np.testing.assert_allclose(probs.sum(-1), 1.0, atol=1e-5)
  assert np.all(var >= 0) and np.all(var <= 0.25)
  assert np.all(var <= probs * (1 - probs) + 1e-7)
  labelled = np.broadcast_to(scene["labels"] >= 0, view.wrong.shape)
  np.testing.assert_array_equal(np.argmax(probs, -1)[labelled],
                                np.asarray(view.favoured)[labelled])


# --- the public entry points --------------------------------------------------------------------
def test_frame_function_is_deterministic_and_vmaps_to_the_sequence(scene):
  kwargs = dict(num_classes=K, camera=CAM, error_rate=0.4, cross_view_correlation=0.3)
  seq = sim.simulate_sequence(jax.random.PRNGKey(3), scene["labels"], scene["instances"],
                              depth=scene["depth"], T_world_cam=scene["T_world_cam"], **kwargs)
  for t in (0, T - 1):
    one = sim.simulate_view_predictions(
        jax.random.PRNGKey(3), scene["labels"][t], scene["instances"][t], t,
        depth=scene["depth"][t], T_world_cam=scene["T_world_cam"][t], **kwargs)
    for a, b in zip(one, seq):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[t])
  again = sim.simulate_sequence(jax.random.PRNGKey(3), scene["labels"], scene["instances"],
                                depth=scene["depth"], T_world_cam=scene["T_world_cam"],
                                **kwargs)
  np.testing.assert_array_equal(np.asarray(seq.var), np.asarray(again.var))
  other = sim.simulate_sequence(jax.random.PRNGKey(4), scene["labels"], scene["instances"],
                                depth=scene["depth"], T_world_cam=scene["T_world_cam"],
                                **kwargs)
  assert not np.array_equal(np.asarray(seq.var), np.asarray(other.var))
  assert seq.probs.shape == (T, H, W, K) and seq.var.dtype == jnp.float32
  assert seq.wrong.shape == (T, H, W) and seq.wrong.dtype == jnp.bool_


@pytest.mark.parametrize("kwargs, match", [
    (dict(regions="pixels"), "regions must be one of"),
    (dict(error_rate=1.5), "error_rate must be in"),
    (dict(cross_view_correlation=-0.1), "cross_view_correlation must be in"),
    (dict(confidence=0.1), r"confidence must be in \(1/K, 1\)"),
    (dict(error_confidence=1.0), "error_confidence must be in"),
    (dict(variance_separation=-1.0), "variance_separation must be"),
    (dict(variance_separation=6.0), "below −log"),
    (dict(alpha_right=1.0), "mean α on right pixels"),
    (dict(patch_size=0.0), "patch_size must be"),
    (dict(alpha_noise=float("nan")), "must be finite"),
    (dict(num_classes=1), "num_classes must be an int"),
])
def test_validation(scene, kwargs, match):
  args = dict(num_classes=K, depth=scene["depth"][0], T_world_cam=scene["T_world_cam"][0],
              camera=CAM)
  args.update(kwargs)
  with pytest.raises(ValueError, match=match):
    sim.simulate_view_predictions(jax.random.PRNGKey(0), scene["labels"][0],
                                  scene["instances"][0], 0, **args)


def test_validation_of_inputs(scene):
  key = jax.random.PRNGKey(0)
  labels, inst = scene["labels"][0], scene["instances"][0]
  with pytest.raises(ValueError, match="needs depth, T_world_cam and camera"):
    sim.simulate_view_predictions(key, labels, inst, 0, num_classes=K, regions="patches")
  with pytest.raises(ValueError, match="needs instance_ids"):
    sim.simulate_view_predictions(key, labels, None, 0, num_classes=K, regions="objects")
  with pytest.raises(ValueError, match="labels must have shape"):
    sim.simulate_view_predictions(key, labels[0], inst[0], 0, num_classes=K,
                                  regions="objects")
  with pytest.raises(TypeError, match="labels must be an integer array"):
    sim.simulate_view_predictions(key, labels.astype(np.float32), inst, 0, num_classes=K,
                                  regions="objects")
  with pytest.raises(ValueError, match="instance_ids must have the shape"):
    sim.simulate_view_predictions(key, labels, inst[:5], 0, num_classes=K, regions="objects")
  with pytest.raises(TypeError, match="unknown parameters"):
    sim.simulate_view_predictions(key, labels, inst, 0, num_classes=K, regions="objects",
                                  error_rat=0.2)
  with pytest.raises(ValueError, match="either model= or parameters"):
    sim.simulate_view_predictions(key, labels, inst, 0, num_classes=K, regions="objects",
                                  model=sim.error_model(), error_rate=0.2)
  with pytest.raises(ValueError, match="frame_index must be a scalar"):
    sim.simulate_view_predictions(key, labels, inst, [0, 1], num_classes=K, regions="objects")


def test_both_front_ends_live_here_and_tune_keeps_the_old_name():
  assert tune.simulate_predictions is sim.simulate_predictions


def test_auroc_against_brute_force():
  rng = np.random.default_rng(0)
  pos, neg = rng.integers(0, 5, 40).astype(float), rng.integers(0, 5, 30).astype(float)
  brute = np.mean((pos[:, None] > neg[None]) + 0.5 * (pos[:, None] == neg[None]))
  assert jf.metrics.auroc_of_samples(pos, neg) == pytest.approx(brute)


# --- the sweep -----------------------------------------------------------------------------------
def test_sweep_rule_stacks_equal_the_named_rules():
  """The sweep fuses Bayes as R with β = 0 and D as D+R with β = 0: the same kernels give the
  same per-pixel terms and the same voxel updates (the engine only calls the kernels)."""
  rng = np.random.default_rng(0)
  probs = jnp.asarray(rng.dirichlet(np.ones(K), 50), jnp.float32)
  var = jnp.asarray(rng.uniform(0, 0.2, (50, K)), jnp.float32)
  r_stack, dr_stack = simulate._sweep_rules(0.3)  # pylint: disable=protected-access
  first = lambda stack: jax.tree.map(lambda x: x[0], stack)
  for stacked, named in ((first(r_stack), jf.rules.bayes()),
                         (first(dr_stack), jf.rules.robust(regularize=False))):
    ours = jax.vmap(stacked.observe, in_axes=(0, 0, None))(probs, var, stacked.hparams)
    theirs = jax.vmap(named.observe, in_axes=(0, 0, None))(probs, var, named.hparams)
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs)):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    row = stacked.init(K, stacked.hparams)
    assert jax.tree.structure(row) == jax.tree.structure(named.init(K, named.hparams))
    obs = jf.rules.base.VoxelObservation(
        jax.tree.map(lambda t: t.sum(0), ours.sums), jax.tree.map(lambda t: t.max(0), ours.maxes),
        jnp.float32(50))
    for a, b in zip(jax.tree.leaves(stacked.update(row, obs, stacked.hparams)),
                    jax.tree.leaves(named.update(row, obs, named.hparams))):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.fixture(scope="module")
def tiny_sweep(scene):
  return simulate.sweep_grid([scene], x_param="cross_view_correlation", x_values=[0.0, 1.0],
                        y_param="error_rate", y_values=[0.0, 0.4], voxel_size=VOXEL,
                        base={"alpha_noise": 0.5}, num_draws=1, progress=False)


def test_tiny_sweep(tiny_sweep):
  out = tiny_sweep
  assert out["miou"].shape == (2, 2, 1, len(simulate.SWEEP_RULES))
  acc = out["accuracy"]
  # No errors: every rule maps every voxel right.
  assert np.all(acc[0] >= 0.99), acc[0]
  # Errors cost accuracy, and the oracle is never below Bayes (it keeps all right evidence).
  bayes, oracle = acc[..., 0], acc[..., simulate.SWEEP_RULES.index("Oracle")]
  assert np.all(acc[1, :, :, 0] < 0.99)
  assert np.all(oracle >= bayes - 1e-12)
  np.testing.assert_allclose(out["error_rate"][0], 0.0)
  assert np.all(np.abs(out["error_rate"][1] - 0.4) < 0.25)
  # Common random numbers: at e = 0 the cells are identical whatever ρ.
  np.testing.assert_array_equal(out["confusion"][0, 0], out["confusion"][0, 1])


def test_sweep_writes_heatmap_and_tables(tiny_sweep, tmp_path):
  paths = simulate.write_results(str(tmp_path), tiny_sweep)
  with open(paths[0], "rb") as f:
    assert f.read(8) == b"\x89PNG\r\n\x1a\n"
  rows = open(paths[1]).read().strip().splitlines()
  assert len(rows) == 1 + 4 and "miou_DR_minus_Bayes" in rows[0]
  payload = json.load(open(paths[2]))
  assert payload["rules"] == list(simulate.SWEEP_RULES) and len(payload["cells"]) == 4


def test_sweep_validation(scene):
  with pytest.raises(ValueError, match="a sweep axis must be one of"):
    simulate.sweep_grid([scene], x_param="beta", x_values=[0], y_param="error_rate", y_values=[0])
  with pytest.raises(ValueError, match="the two axes must differ"):
    simulate.sweep_grid([scene], x_param="error_rate", x_values=[0], y_param="error_rate",
                   y_values=[0])
  with pytest.raises(ValueError, match="error_rate must be in"):
    simulate.sweep_grid([scene], x_param="error_rate", x_values=[2.0], y_param="alpha_noise",
                   y_values=[0])


def test_command(scene, tmp_path, monkeypatch, capsys):
  from jaxfusion.lab import cli
  monkeypatch.setattr(simulate, "load_sequence", lambda spec, **kw: scene)
  parser = cli.build_parser()
  args = parser.parse_args(["simulate-sweep", "--quick", "--out", str(tmp_path),
                            "--x-values", "0,1", "--y-values", "0,0.4", "--y", "error_rate",
                            "--voxel-size", str(VOXEL), "--alpha-noise", "0.5"])
  assert args.func(args) == 0
  assert "D+R − Bayes" in capsys.readouterr().out
  assert os.path.exists(tmp_path / "heatmap.png")
  with pytest.raises(SystemExit):
    parser.parse_args(["simulate-sweep", "--x", "beta"])
  assert isinstance(args, argparse.Namespace)


# --- the learned rule's column -------------------------------------------------------------------
@pytest.mark.slow
def test_learned_column_with_the_paper_rules_special_cases_matches_their_columns(scene):
  """A learned rule set to Bayes (resp. D+R at the sweep's β) in every cell fuses the same views
  as the sweep's own columns, so its confusions match theirs."""
  grid = dict(x_param="cross_view_correlation", x_values=[0.0, 1.0], y_param="error_rate",
              y_values=[0.4], voxel_size=VOXEL, base={"alpha_noise": 0.5}, num_draws=1,
              progress=False)
  for name, column in (("bayes", "Bayesian"), ("robust_dr", "D+R")):
    rule = jf.rules.learned(jf.rules.learned_special_case(name, beta=0.3))
    out = simulate.sweep_grid([scene], **grid, beta=0.3, learned=[[rule, rule]])
    assert out["rules"] == list(simulate.SWEEP_RULES) + [simulate.LEARNED]
    cms = out["confusion"][..., :, :]
    ours, theirs = cms[..., -1, :, :], cms[..., out["rules"].index(column), :, :]
    # The same equations through other XLA fusions: at most a voxel or two flips on a near tie.
    assert np.abs(ours - theirs).sum() <= 4, (name, ours, theirs)
  with pytest.raises(ValueError, match="one per cell"):
    simulate.sweep_grid([scene], **grid, learned=[[rule]])


@pytest.mark.slow
def test_simulated_batch_and_per_cell_fits(scene, tmp_path):
  model = sim.error_model(num_classes=K, error_rate=0.3, alpha_noise=0.5)
  data = simulate.simulated_batch([scene, scene], model, seed=3)
  assert data["frames"].probs.shape == (2,) + scene["labels"].shape + (K,)
  assert data["mask"].all() and data["capacity"] >= len(scene["gt"]["labels"])
  np.testing.assert_allclose(np.asarray(data["frames"].probs).sum(-1), 1.0, atol=1e-5)
  # The batch is the sweep's own view of the sequence: sequence i, key fold_in(key(seed), i).
  probs, _ = simulate._simulated_moments(  # pylint: disable=protected-access
      jax.random.fold_in(jax.random.PRNGKey(3), 1), jnp.asarray(scene["labels"]),
      jnp.asarray(scene["instances"]), jnp.asarray(scene["depth"]),
      jnp.asarray(scene["T_world_cam"]), CAM, model, num_classes=K, regions="both")
  np.testing.assert_array_equal(np.asarray(data["frames"].probs[1]), np.asarray(probs))
  fits = simulate.fit_learned_rules([scene], [scene], x_param="cross_view_correlation",
                                    x_values=[0.0], y_param="variance_separation",
                                    y_values=[0.0, 4.0], base={"error_rate": 0.3}, steps=3,
                                    eval_every=1, patience=2, voxel_size=VOXEL, progress=False)
  assert [len(r) for r in fits] == [1, 1]
  for (fit,) in fits:
    assert fit.steps_run >= 1 and np.all(np.isfinite(fit.train_losses))
  out = simulate.sweep_grid([scene], x_param="cross_view_correlation", x_values=[0.0],
                            y_param="variance_separation", y_values=[0.0, 4.0],
                            base={"error_rate": 0.3}, voxel_size=VOXEL, progress=False,
                            learned=[[f.rule for f in row] for row in fits])
  paths = simulate.write_results(str(tmp_path), out)
  header = open(paths[1]).read().splitlines()[0]
  assert "miou_Learned_minus_DR" in header and "oracle_share_Learned" in header


def test_command_with_learned_column_refuses_the_judged_seed(scene, tmp_path, monkeypatch):
  from jaxfusion.lab import cli
  monkeypatch.setattr(simulate, "load_sequence", lambda spec, **kw: scene)
  args = cli.build_parser().parse_args(["simulate-sweep", "--quick", "--out", str(tmp_path),
                                        "--learned", "--learned-seeds", "0", "12"])
  with pytest.raises(ValueError, match="must differ"):
    args.func(args)
