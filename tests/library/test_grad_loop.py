"""`jax.grad` and `jax.vmap` through the donating entry points, written as a user writes them
(no `jit`, no `debug_nans`): issue 11's plain Python loop of `fuse_frame`, `fuse_sequence`, the
batch functions and the tuning loss. Gradients are checked against central finite differences
of the same eager code and against each other (`fuse_sequence` equals the loop)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import camera as camera_lib
from jaxfusion import tune

# --- issue 11's snippet, as written -----------------------------------------------------------
# pylint: disable-next=multiple-statements
rng = np.random.default_rng(5); K = 4; cam = jf.Camera(16.0, 16.0, 9.5, 7.5)
frames = []
for t in range(3):
  s = rng.dirichlet(np.ones(K), (6, 16, 20)).astype(np.float32)
  frames.append(jf.Frame(rng.uniform(0.6, 2.0, (16, 20)).astype(np.float32),
                         np.eye(4, dtype=np.float32), s.mean(0), s.var(0)))


def loss(beta):
  rule = jf.rules.robust(beta=beta)
  st = jf.init_map(capacity=2048, num_classes=K, voxel_size=0.1, rule=rule)
  for f in frames:
    st = jf.fuse_frame(st, f, cam, rule)
  post, occ = jf.voxel_posteriors(st)
  return jnp.sum(jnp.where(occ[:, None], post * post, 0.0))
# ------------------------------------------------------------------------------------------------

SEQUENCE = jax.tree.map(lambda *x: np.stack(x), *frames)
BETA = 0.3


def posterior_loss(state):
  post, occ = jf.voxel_posteriors(state)
  return jnp.sum(jnp.where(occ[:, None], post * post, 0.0))


def central_difference(f, x, step):
  return (float(f(x + step)) - float(f(x - step))) / (2 * step)


@pytest.fixture(scope="module")
def snippet_grad():
  return float(jax.grad(loss)(BETA))   # RuntimeError "Array has been deleted" before the fix


def test_issue_snippet_grad_is_finite_and_matches_finite_differences(snippet_grad):
  assert np.isfinite(snippet_grad)
  assert abs(snippet_grad) > 1e-3      # β changes this map's posteriors: a real derivative
  fd = central_difference(loss, BETA, 1e-2)
  np.testing.assert_allclose(snippet_grad, fd, rtol=2e-2, atol=1e-3)


def test_fuse_frame_still_donates_outside_transformations():
  rule = jf.rules.robust(beta=BETA)
  state = jf.init_map(capacity=2048, num_classes=K, voxel_size=0.1, rule=rule)
  new = jf.fuse_frame(state, frames[0], cam, rule)
  assert all(x.is_deleted() for x in jax.tree.leaves(state.rows))   # updated in place
  assert int(new.num_occupied) > 0


def test_vmap_of_the_plain_loop_over_beta_equals_one_beta_at_a_time():
  betas = jnp.array([0.1, BETA])
  batched = jax.vmap(loss)(betas)
  for i, b in enumerate([0.1, BETA]):
    np.testing.assert_allclose(float(batched[i]), float(loss(b)), rtol=1e-5)


def test_vmap_over_frames_with_a_shared_map_donates_nothing():
  rule = jf.rules.robust(beta=BETA)
  state = jf.init_map(capacity=2048, num_classes=K, voxel_size=0.1, rule=rule)
  batched = jax.vmap(lambda f: posterior_loss(jf.fuse_frame(state, f, cam, rule)))(SEQUENCE)
  assert not any(x.is_deleted() for x in jax.tree.leaves(state))
  for i, f in enumerate(frames):
    fresh = jf.init_map(capacity=2048, num_classes=K, voxel_size=0.1, rule=rule)
    np.testing.assert_allclose(float(batched[i]),
                               float(posterior_loss(jf.fuse_frame(fresh, f, cam, rule))),
                               rtol=1e-5)


@pytest.mark.slow
def test_grad_and_vmap_of_fuse_sequence_equal_the_loop(snippet_grad):
  def seq_loss(beta):
    rule = jf.rules.robust(beta=beta)
    st = jf.init_map(capacity=2048, num_classes=K, voxel_size=0.1, rule=rule)
    return posterior_loss(jf.fuse_sequence(st, SEQUENCE, cam, rule))

  np.testing.assert_allclose(float(jax.grad(seq_loss)(BETA)), snippet_grad, rtol=1e-4)
  np.testing.assert_allclose(np.asarray(jax.vmap(seq_loss)(jnp.array([0.1, BETA]))),
                             [float(loss(0.1)), float(loss(BETA))], rtol=1e-5)


@pytest.mark.slow
def test_grad_of_fuse_batch_and_fuse_sweep_equal_the_loop(snippet_grad):
  def batch_loss(beta):
    states = jf.fuse_batch(jax.tree.map(lambda x: x[None], SEQUENCE), cam,
                           jf.rules.robust(beta=beta), capacity=2048)
    return posterior_loss(jax.tree.map(lambda x: x[0], states))

  def sweep_loss(beta):
    stacked = jf.rules.stack([jf.rules.robust(beta=beta), jf.rules.robust(beta=0.9)])
    return posterior_loss(jax.tree.map(lambda x: x[0], jf.fuse_sweep(SEQUENCE, cam, stacked,
                                                                     capacity=2048)))

  np.testing.assert_allclose(float(jax.grad(batch_loss)(BETA)), snippet_grad, rtol=1e-4)
  np.testing.assert_allclose(float(jax.grad(sweep_loss)(BETA)), snippet_grad, rtol=1e-4)


@pytest.mark.slow
def test_grad_of_the_tuning_loss_without_jit_matches_finite_differences():
  keys, ok = camera_lib.depth_to_voxel_keys(frames[0].depth, frames[0].T_world_cam, cam, 0.1)
  coords = np.unique(np.asarray(keys)[np.asarray(ok)], axis=0)[::4]   # GT voxels the map holds
  labels = np.arange(len(coords), dtype=np.int32) % K

  def tune_loss(beta):
    return tune.sequence_loss(jf.rules.robust(beta=beta), SEQUENCE, cam, coords, labels,
                              capacity=2048)

  g = float(jax.grad(tune_loss)(BETA))
  assert np.isfinite(g) and abs(g) > 1e-4
  fd = central_difference(jax.jit(tune_loss), BETA, 1e-2)   # one compile for both points
  np.testing.assert_allclose(g, fd, rtol=2e-2, atol=1e-4)
