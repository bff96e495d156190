"""Per-class hyperparameters (docs/equations.md §3.7): β, ε and α₀ given as `(K,)` vectors.

Against the independent NumPy reference on random multi-frame sequences, a hand-computed
regularisation, the scalar path kept bit-identical to R (§3.4), all-equal per-class β equal to the
scalar, and the contract (jit, vmap over a stack, grad against finite differences, no
recompilation, clear errors)."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import fusion
from jaxfusion import numerics
from tests import engine_helpers as h
from tests.reference import per_class_regularize
from tests.engine.test_engine_reference import assert_maps_match, fuse_both

# The module (the package re-exports the factory `robust` under the same name).
robust_lib = importlib.import_module("jaxfusion.rules.robust")
K = h.NUM_CLASSES
BETA = [0.05, 0.6, 0.3, 0.9]
ALPHA0 = [0.0, 2.0, 6.9, 1.0]
EPS = [1e-12, 1e-4, 1e-6, 1e-3]


@pytest.fixture(autouse=True)
def strict_numerics():
  # Rank promotion raises (silent broadcasting is a bug); NaN-freeness is asserted explicitly,
  # never with `jax.debug_nans`, which changes how JAX dispatches and once hid a donation bug.
  with jax.numpy_rank_promotion("raise"):
    yield


def frames_of(seed, n=3):
  rng = np.random.default_rng(seed)
  return [h.random_frame(rng) for _ in range(n)]


def fuse(rule, frames, state=None):
  # Capacity and voxel size as in test_engine_reference, so compiled shapes are shared.
  state = state or jf.init_map(capacity=1024, num_classes=K, voxel_size=0.25, rule=rule)
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  return state


# --- the definition ------------------------------------------------------------------------------
def test_hand_computed_per_class_regularisation():
  p = jnp.array([0.7, 0.2, 0.1], jnp.float32)
  beta = jnp.array([0.5, 0.0, 0.0], jnp.float32)
  # mixed = [0.35 + 0.5/3, 0.2, 0.1] = [0.516667, 0.2, 0.1], Z = 0.816667.
  want = np.array([0.516667, 0.2, 0.1]) / 0.816667
  np.testing.assert_allclose(robust_lib.regularize(p, beta), want, rtol=1e-5)
  np.testing.assert_allclose(per_class_regularize(np.asarray(p, np.float64), beta), want,
                             rtol=1e-5)
  # A distribution whatever β, and uniform where Z = 0 (all-zero pixel with β = 0).
  total = jnp.sum(robust_lib.regularize(p, jnp.array([1.0, 0.2, 0.7])))
  assert float(total) == pytest.approx(1.0)
  np.testing.assert_allclose(robust_lib.regularize(jnp.zeros(3), jnp.zeros(3)),
                             np.full(3, 1 / 3))


def test_scalar_beta_is_rule_4_bit_for_bit_and_equal_vector_beta_matches():
  """A scalar β takes no normalisation: same bits as `(1−β) p + β/K` fused through the engine;
  an all-equal per-class β gives the same maps up to float32 rounding of Z."""
  frames = frames_of(11, n=2)

  def old_dr_observe(probs, var, hparams):
    b = hparams["beta"]
    shifted = jnp.clip(var, 0.0, 0.25) + hparams["eps"]
    p = (1.0 - b) * probs + b / K
    return jf.rules.PixelTerms(sums={"wloglik": -jnp.log(shifted) * numerics.safe_log(p)},
                               maxes={"neg_shifted_var": -shifted})

  # D+R only: R and D+R share `regularize` (and R's scalar path is in test_engine_reference).
  rule = jf.rules.robust(beta=0.37)
  got = fuse(rule, frames)
  want = fuse(rule.replace(observe=old_dr_observe), frames)
  for a, b in zip(jax.tree.leaves(got.rows), jax.tree.leaves(want.rows)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  # All-equal per-class β: Z = 1 up to rounding.
  vec = fuse(jf.rules.robust(beta=[0.37] * K, alpha0=[robust_lib.DEFAULT_ALPHA0] * K), frames)
  np.testing.assert_array_equal(np.asarray(vec.keys), np.asarray(got.keys))
  for a, b in zip(jax.tree.leaves(vec.rows), jax.tree.leaves(got.rows)):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=2e-5, rtol=1e-6)


# --- against the NumPy reference -----------------------------------------------------------------
@pytest.mark.parametrize("name,aggregate,hparams", [
    ("robust_r", "sum", {"beta": BETA}),
    ("robust_dr", "sum", {"beta": BETA, "alpha0": ALPHA0}),
    ("robust_dr", "mean", {"beta": BETA, "alpha0": ALPHA0, "eps": EPS}),
    ("robust_d", "sum", {"alpha0": ALPHA0, "eps": EPS}),
])
def test_per_class_matches_reference(name, aggregate, hparams):
  got, ref = fuse_both(name, 3, aggregate=aggregate, **hparams)
  assert len(got["coords"]) > 20 and got["hits"].max() > 1
  assert_maps_match(got, ref, name)


# --- contract ------------------------------------------------------------------------------------
def test_jit_vmap_over_a_stack_and_no_recompilation():
  frames = frames_of(13, n=2)
  grid = [BETA, [0.0] * K, [1.0, 0.0, 0.5, 0.2]]
  stacked = jf.rules.stack([jf.rules.robust(beta=b, alpha0=ALPHA0) for b in grid])
  assert stacked.hparams["beta"].shape == (3, K)

  def run(rule):
    return jf.voxel_posteriors(fuse(rule, frames))[0]

  batched = jax.jit(jax.vmap(run))(stacked)
  for i, b in enumerate(grid):
    np.testing.assert_allclose(batched[i], run(jf.rules.robust(beta=b, alpha0=ALPHA0)),
                               atol=1e-6)
  # Same shapes, other values: the jitted fuse_frame is reused.
  state = fuse(jf.rules.robust(beta=BETA, alpha0=ALPHA0), frames[:1])
  before = fusion.fuse_frame_donating._cache_size()  # pylint: disable=protected-access
  other = jf.rules.robust(beta=[0.9, 0.1, 0.2, 0.0], alpha0=[1.0] * K)
  fuse(other, frames[1:], state)
  assert fusion.fuse_frame_donating._cache_size() == before  # pylint: disable=protected-access


def test_grad_of_per_class_vectors_matches_finite_differences():
  frames = frames_of(14, n=2)

  @jax.jit
  def f(hp):
    rule = jf.rules.robust(eps=1e-3, **hp)
    post, occupied = jf.voxel_posteriors(fuse(rule, frames))
    target = jax.nn.one_hot(jnp.arange(post.shape[0]) % K, K)
    return -jnp.sum(jnp.where(occupied[:, None], target * jnp.log(post + 1e-6), 0.0))

  x0 = {"beta": jnp.asarray(BETA, jnp.float32),
        "alpha0": jnp.asarray([1.0, 2.0, 3.0, 0.5], jnp.float32)}
  grads = jax.jit(jax.grad(f))(x0)
  for name, g in grads.items():
    g = np.asarray(g)
    assert g.shape == (K,) and np.all(np.isfinite(g))
    assert len({round(float(v), 3) for v in g}) > 1   # each class gets its own gradient
    for i in range(K):
      step = 1e-2 * max(float(x0[name][i]), 0.3)
      up = dict(x0, **{name: x0[name].at[i].add(step)})
      down = dict(x0, **{name: x0[name].at[i].add(-step)})
      fd = (float(f(up)) - float(f(down))) / (2 * step)
      np.testing.assert_allclose(g[i], fd, rtol=3e-2, atol=2e-3 * max(1.0, abs(fd)),
                                 err_msg=f"{name}[{i}]")


def test_wrong_length_and_bad_values_raise_clearly():
  rule5 = jf.rules.robust(beta=[0.3] * 5)
  with pytest.raises(ValueError, match=r"beta has shape \(5,\) but the map has K = 4"):
    jf.init_map(capacity=64, num_classes=K, rule=rule5)
  with pytest.raises(ValueError, match=r"alpha0 has shape \(3,\)"):
    jf.init_map(capacity=64, num_classes=K, rule=jf.rules.robust(alpha0=[1.0] * 3))
  state = jf.init_map(capacity=64, num_classes=K, voxel_size=0.25, rule=jf.rules.robust())
  with pytest.raises(ValueError, match=r"beta has shape \(5,\) but the map has K = 4"):
    jf.fuse_frame(state, frames_of(15, n=1)[0], h.CAMERA, rule5)
  r_state = jf.init_map(capacity=64, num_classes=K, voxel_size=0.25,
                        rule=jf.rules.robust(dirichlet=False))
  with pytest.raises(ValueError, match=r"beta has shape \(5,\)"):
    jf.fuse_frame(r_state, frames_of(15, n=1)[0], h.CAMERA,
                  jf.rules.robust(beta=[0.3] * 5, dirichlet=False))
  with pytest.raises(ValueError, match=r"beta must lie in \[0, 1\]; got \[0.3, 1.2"):
    jf.rules.robust(beta=[0.3, 1.2, 0.0, 0.1])
  with pytest.raises(ValueError, match="beta must lie"):
    jf.rules.robust(beta=[0.3, float("nan"), 0.0, 0.1])
  with pytest.raises(ValueError, match="eps must be"):
    jf.rules.robust(eps=[1e-3, 0.0, 1e-3, 1e-3])
  with pytest.raises(ValueError, match="alpha0 must be"):
    jf.rules.robust(alpha0=[1.0, -1.0, 1.0, 1.0])
  with pytest.raises(ValueError, match="scalar or a \\(K,\\) vector"):
    jf.rules.robust(beta=np.full((2, K), 0.3))
  with pytest.raises(ValueError, match="one value per class"):
    jf.rules.robust(beta=[0.3])
