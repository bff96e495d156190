"""One contract test run over every rule: finite output, dtypes kept, works under jit, vmap and
grad, and no recompilation when data or hyperparameters change."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import fusion
from tests import engine_helpers as h

ROBUST = ("robust_r", "robust_d", "robust_dr")


def make(name, **hp):
  rule = jf.rules.by_name(name, **h.rule_kwargs(name, **hp))
  return rule, jf.init_map(capacity=512, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)


@pytest.fixture(autouse=True)
def strict_rank_promotion():
  # Strict numerics are asserted explicitly (finite states, posteriors and gradients), not with
  # `jax.debug_nans`, which changes how JAX dispatches and so hid a donation bug of the very
  # behaviour under test (issue 11).
  with jax.numpy_rank_promotion("raise"):
    yield


def assert_finite(tree):
  for leaf in jax.tree.leaves(tree):
    assert bool(jnp.all(jnp.isfinite(leaf))), "non-finite values"


@pytest.mark.parametrize("name", h.PAPER_RULES)
def test_finite_and_dtypes_kept(name):
  rng = np.random.default_rng(3)
  rule, state = make(name)
  dtypes = jax.tree.map(lambda x: x.dtype, state)
  for _ in range(3):
    state = jf.fuse_frame(state, h.random_frame(rng), h.CAMERA, rule)
  assert jax.tree.map(lambda x: x.dtype, state) == dtypes
  for leaf in jax.tree.leaves(state.rows):
    assert bool(jnp.all(jnp.isfinite(leaf)))
  assert int(state.num_occupied) > 0


@pytest.mark.parametrize("name", h.main_tier_keeps(h.PAPER_RULES, ("sum_labels", "robust_dr")))
def test_under_jit_equals_eager_entry_point(name):
  rng = np.random.default_rng(4)
  frame = h.random_frame(rng)
  rule, s1 = make(name)
  _, s2 = make(name)
  a = jf.fuse_frame(s1, frame, h.CAMERA, rule)
  b = jax.jit(jf.fuse_frame, static_argnums=())(s2, frame, h.CAMERA, rule)
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("name", h.main_tier_keeps(h.PAPER_RULES, ("bayes", "robust_dr")))
def test_vmap_over_maps_and_frames(name):
  rng = np.random.default_rng(5)
  frames = [h.random_frame(rng) for _ in range(2)]
  rule, _ = make(name)
  states = jax.tree.map(lambda *x: jnp.stack(x), *[make(name)[1] for _ in range(2)])
  stacked = jax.tree.map(lambda *x: np.stack(x), *frames)   # NumPy: the holes hold NaN
  batched = jax.vmap(jf.fuse_frame, in_axes=(0, 0, None, None))(states, stacked, h.CAMERA, rule)
  assert_finite(batched.rows)
  assert not any(x.is_deleted() for x in jax.tree.leaves(states))   # nothing donated under vmap
  for i, frame in enumerate(frames):
    _, single = make(name)
    single = jf.fuse_frame(single, frame, h.CAMERA, rule)
    got = jf.read_map(jax.tree.map(lambda x: x[i], batched))
    want = jf.read_map(single)
    np.testing.assert_array_equal(got["coords"], want["coords"])
    np.testing.assert_allclose(got["posterior"], want["posterior"], atol=1e-6)


@pytest.mark.parametrize("name", h.main_tier_keeps(ROBUST, ("robust_dr",)))
def test_vmap_over_a_beta_grid(name):
  rng = np.random.default_rng(6)
  frames = [h.random_frame(rng) for _ in range(2)]
  betas = [0.0, 0.3, 0.9]
  grid = jf.rules.stack([jf.rules.by_name(name, beta=b, alpha0=1.0) for b in betas])

  def run(rule):
    state = jf.init_map(capacity=512, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)
    for f in frames:
      state = jf.fuse_frame(state, f, h.CAMERA, rule)
    return jf.voxel_posteriors(state)[0]

  batched = jax.vmap(run)(grid)
  assert_finite(batched)
  for i, b in enumerate(betas):
    np.testing.assert_allclose(batched[i], run(jf.rules.by_name(name, beta=b, alpha0=1.0)),
                               atol=1e-6)
  if name != "robust_d":   # D ignores β; R and D+R must respond to it
    assert float(jnp.max(jnp.abs(batched[0] - batched[2]))) > 1e-3


def _loss(name, frames, **hp):
  rule = jf.rules.by_name(name, **hp)
  state = jf.init_map(capacity=512, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  post, occupied = jf.voxel_posteriors(state)
  target = jax.nn.one_hot(jnp.arange(post.shape[0]) % h.NUM_CLASSES, h.NUM_CLASSES)
  return -jnp.sum(jnp.where(occupied[:, None], target * jnp.log(post + 1e-6), 0.0))


@pytest.mark.slow
@pytest.mark.parametrize("name,params", [
    ("robust_r", ("beta",)), ("robust_d", ("eps", "alpha0")),
    ("robust_dr", ("beta", "eps", "alpha0"))])
def test_grad_of_hyperparameters_matches_finite_differences(name, params):
  # One gradient with respect to every hyperparameter the rule uses (one backward pass to
  # compile per rule), each component against its own central difference.
  rng = np.random.default_rng(8)
  frames = [h.random_frame(rng) for _ in range(3)]
  point = {k: {"beta": 0.3, "eps": 1e-3, "alpha0": 2.0}[k] for k in params}
  f = lambda hp: _loss(name, frames, **{"eps": 1e-3, **hp})
  grad = jax.grad(f)({k: jnp.float32(v) for k, v in point.items()})
  assert set(grad) == set(params)
  for param, x in point.items():
    g = float(grad[param])
    step = x * 1e-2
    fd = (float(f({**point, param: x + step})) - float(f({**point, param: x - step}))) / (2 * step)
    assert np.isfinite(g) and np.isfinite(fd), param
    np.testing.assert_allclose(g, fd, rtol=2e-2, atol=1e-3 * max(1.0, abs(fd)), err_msg=param)


@pytest.mark.parametrize("name", h.main_tier_keeps(h.PAPER_RULES, ("sum_labels", "robust_dr")))
def test_grad_wrt_probabilities_is_finite_with_one_hot_and_zero_variance(name):
  rng = np.random.default_rng(9)
  frame = h.random_frame(rng)
  rule, _ = make(name)

  def loss(probs):
    _, state = make(name)
    state = jf.fuse_frame(state, frame._replace(probs=probs), h.CAMERA, rule)
    post, occupied = jf.voxel_posteriors(state)
    return jnp.sum(jnp.where(occupied[:, None], post * post, 0.0))

  g = jax.grad(loss)(jnp.asarray(frame.probs))
  assert bool(jnp.all(jnp.isfinite(g)))


@pytest.mark.parametrize("name", h.PAPER_RULES)
def test_no_recompilation_on_second_call(name):
  rng = np.random.default_rng(10)
  rule, state = make(name)
  state = jf.fuse_frame(state, h.random_frame(rng), h.CAMERA, rule)
  before = fusion.fuse_frame_donating._cache_size()
  other = jf.rules.by_name(name, **h.rule_kwargs(name, beta=0.55, eps=1e-5, alpha0=3.0))
  state = jf.fuse_frame(state, h.random_frame(rng), h.CAMERA, other)
  state = jf.fuse_frame(state, h.random_frame(rng), jf.Camera(7.0, 6.5, 3.0, 2.0), rule)
  assert fusion.fuse_frame_donating._cache_size() == before
