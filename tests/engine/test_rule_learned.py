"""The learned rule (docs/equations.md §3.9): the paper's rules as exact special cases, the NumPy
reference on random parameters, finite values on hard inputs, gradients against finite
differences, vmap over parameter stacks and no recompilation when the values change."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import fusion
from tests import engine_helpers as h
from tests.reference import ReferenceMap, learned_features

learned_lib = importlib.import_module("jaxfusion.rules.learned")
VOXEL = 0.25


def fuse(rule, frames, capacity=1024):
  state = jf.init_map(capacity=capacity, num_classes=h.NUM_CLASSES, voxel_size=VOXEL, rule=rule)
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  return state


def frames_of(seed, n=3):
  rng = np.random.default_rng(seed)
  return [h.random_frame(rng, voxel_size=VOXEL) for _ in range(n)]


def random_params(rng, per_class_beta=True):
  return {"theta": rng.normal(0, 2, learned_lib.NUM_FEATURES), "bias": rng.normal(0.5, 1),
          "mix": rng.uniform(0.2, 0.8), "gate": [1.5, rng.normal(0, 1), rng.normal(0, 1)],
          "beta": rng.uniform(0, 0.6, h.NUM_CLASSES) if per_class_beta else 0.2,
          "eps": 1e-4, "alpha0": 1.5}


def assert_same_map(ours, paper, dirichlet):
  # Every weight and gate is exactly 1; what remains is float32 rounding of the same terms
  # (XLA contracts `0·a + b` and `1·a·b` differently from `b` and `a·b`: one ulp here and there).
  np.testing.assert_array_equal(np.asarray(ours.keys), np.asarray(paper.keys))
  np.testing.assert_allclose(np.asarray(ours.rows["logp"]), np.asarray(paper.rows["logp"]),
                             rtol=1e-6, atol=1e-6)
  np.testing.assert_array_equal(jf.read_map(ours)["labels"], jf.read_map(paper)["labels"])
  if dirichlet:
    np.testing.assert_array_equal(np.asarray(ours.rows["alpha_bar"]),
                                  np.asarray(paper.rows["alpha_bar"]))


@pytest.mark.parametrize("name", h.main_tier_keeps(["bayes", "robust_r", "robust_d", "robust_dr"],
                                                   ("bayes", "robust_dr")))
def test_contains_the_paper_rules(name):
  frames = frames_of(1)
  paper = fuse(jf.rules.by_name(name), frames)
  ours = fuse(jf.rules.learned(learned_lib.special_case(name)), frames)
  assert_same_map(ours, paper, name in h.DIRICHLET_RULES)


def test_default_is_dr_and_weights_and_gates_are_exactly_one():
  assert float(jax.nn.sigmoid(jnp.float32(learned_lib.ON))) == 1.0
  frames = frames_of(2, n=2)
  assert_same_map(fuse(jf.rules.learned(), frames), fuse(jf.rules.robust(), frames), True)
  assert jf.rules.display_name(jf.rules.learned()) == "Learned"


@pytest.mark.parametrize("aggregate", ["sum", "mean"])
@pytest.mark.parametrize("seed", h.main_tier_keeps([0, 1], (0,)))
def test_matches_reference_on_random_parameters(seed, aggregate):
  rng = np.random.default_rng(100 + seed)
  params = random_params(rng, per_class_beta=seed == 0)
  rule = jf.rules.learned(params, aggregate=aggregate)
  ref = ReferenceMap("learned", h.NUM_CLASSES, VOXEL, beta=params["beta"], eps=params["eps"],
                     alpha0=params["alpha0"], aggregate=aggregate, learned=params)
  state = jf.init_map(capacity=1024, num_classes=h.NUM_CLASSES, voxel_size=VOXEL, rule=rule)
  for frame in frames_of(seed, n=4):
    state = jf.fuse_frame(state, frame, h.CAMERA, rule)
    ref.fuse(frame.depth, frame.T_world_cam, frame.probs, frame.var, *h.CAMERA)
  got, want = jf.read_map(state), ref.read()
  assert len(got["coords"]) > 20 and got["hits"].max() > 1
  np.testing.assert_array_equal(got["coords"], want["coords"])
  np.testing.assert_array_equal(got["hits"], want["hits"])
  np.testing.assert_allclose(got["posterior"], want["posterior"], atol=2e-4, rtol=0)
  np.testing.assert_allclose(got["confidence"], want["confidence"], rtol=1e-5)


def test_features_match_the_reference_and_stay_finite_on_hard_pixels():
  rng = np.random.default_rng(3)
  k = 5
  cases = [rng.dirichlet(np.ones(k)) for _ in range(20)] + [np.eye(k)[2], np.full(k, 1 / k)]
  variances = [rng.uniform(0, 0.05, k) for _ in range(20)] + [np.zeros(k), np.full(k, 0.3)]
  for p, s in zip(cases, variances):
    got = learned_lib.features(jnp.asarray(p, jnp.float32), jnp.asarray(s, jnp.float32), 1e-12)
    assert bool(jnp.all(jnp.isfinite(got)))
    np.testing.assert_allclose(np.asarray(got), learned_features(p, s, 1e-12), rtol=1e-4,
                               atol=1e-5)


def _loss(params, frames):
  rule = jf.rules.learned(params)
  state = fuse(rule, frames, capacity=512)
  post, occupied = jf.voxel_posteriors(state)
  target = jax.nn.one_hot(jnp.arange(post.shape[0]) % h.NUM_CLASSES, h.NUM_CLASSES)
  return -jnp.sum(jnp.where(occupied[:, None], target * jnp.log(post + 1e-6), 0.0))


@pytest.mark.slow
def test_grad_of_every_parameter_matches_finite_differences():
  frames = frames_of(4, n=3)
  point = {"theta": jnp.asarray([0.5, -1.0, 0.8, 0.3, -0.6, 0.4], jnp.float32),
           "bias": jnp.float32(0.2), "mix": jnp.float32(0.5),
           "gate": jnp.asarray([0.5, 1.0, -0.5], jnp.float32),
           "beta": jnp.asarray([0.1, 0.3, 0.2, 0.4], jnp.float32), "eps": jnp.float32(1e-3),
           "alpha0": jnp.float32(2.0)}
  f = lambda p: _loss(p, frames)
  grad = jax.grad(f)(point)
  assert set(grad) == set(point)
  checks = [("theta", 0), ("theta", 3), ("bias", None), ("mix", None), ("gate", 1),
            ("beta", 2), ("alpha0", None)]
  for name, index in checks:
    g = float(grad[name] if index is None else grad[name][index])
    step = 1e-2

    def moved(delta):
      value = point[name] + delta if index is None else point[name].at[index].add(delta)
      return float(f({**point, name: value}))
    fd = (moved(step) - moved(-step)) / (2 * step)
    assert np.isfinite(g) and np.isfinite(fd), name
    np.testing.assert_allclose(g, fd, rtol=3e-2, atol=2e-3 * max(1.0, abs(fd)),
                               err_msg=f"{name}[{index}]")


def test_grad_wrt_probabilities_is_finite_with_one_hot_and_zero_variance():
  rng = np.random.default_rng(9)
  frame = h.random_frame(rng, voxel_size=VOXEL)
  rule = jf.rules.learned(random_params(rng))

  def loss(probs, var):
    state = fuse(rule, [frame._replace(probs=probs, var=var)], capacity=512)
    post, occupied = jf.voxel_posteriors(state)
    return jnp.sum(jnp.where(occupied[:, None], post * post, 0.0))

  gp, gv = jax.grad(loss, argnums=(0, 1))(jnp.asarray(frame.probs), jnp.asarray(frame.var))
  assert bool(jnp.all(jnp.isfinite(gp))) and bool(jnp.all(jnp.isfinite(gv)))


@pytest.mark.slow
def test_vmap_over_a_parameter_stack_and_no_recompilation():
  frames = frames_of(5, n=2)
  rng = np.random.default_rng(6)
  sets = [random_params(rng) for _ in range(3)]
  stacked = jf.rules.stack([jf.rules.learned(p) for p in sets])

  def run(rule):
    return jf.voxel_posteriors(fuse(rule, frames, capacity=512))[0]

  batched = jax.vmap(run)(stacked)
  for i, p in enumerate(sets):
    np.testing.assert_allclose(batched[i], run(jf.rules.learned(p)), atol=1e-6)
  assert float(jnp.max(jnp.abs(batched[0] - batched[1]))) > 1e-3
  state = fuse(jf.rules.learned(sets[0]), frames[:1], capacity=512)
  before = fusion.fuse_frame_donating._cache_size()  # pylint: disable=protected-access
  jf.fuse_frame(state, frames[1], h.CAMERA, jf.rules.learned(sets[1]))
  assert fusion.fuse_frame_donating._cache_size() == before  # pylint: disable=protected-access


@pytest.mark.parametrize("params,match", [
    ({"theta": [1.0, 2.0]}, r"theta must have shape \(6,\)"),
    ({"gate": [1.0]}, r"gate \(3,\)"),
    ({"mix": 1.5}, r"mix must lie in \[0, 1\]"),
    ({"bias": float("nan")}, "bias must be finite"),
    ({"beta": 1.2}, "beta must lie in"),
    ({"temperature": 1.0}, "unknown learned-rule parameters"),
    ({"mix": [0.5, 0.5]}, "mix must be a scalar"),
])
def test_bad_parameters_fail_clearly(params, match):
  with pytest.raises(ValueError, match=match):
    jf.rules.learned(params)


def test_per_class_beta_of_wrong_length_fails_at_init_map():
  with pytest.raises(ValueError, match=r"beta has shape \(3,\)"):
    jf.init_map(capacity=64, num_classes=h.NUM_CLASSES,
                rule=jf.rules.learned(beta=[0.1, 0.2, 0.3]))
