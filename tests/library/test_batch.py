"""Batched fusion: equal to the sequential path, neutral padding, clear errors, and the same
result sharded over 4 (forced CPU) devices, with and without the geometry layer."""

import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import batch
from tests import engine_helpers as h

CAPACITY = 256
VOXEL = 0.25


def sequence(rng, length, height=h.HEIGHT, width=h.WIDTH):
  frames = [h.random_frame(rng, height=height, width=width) for _ in range(length)]
  return jax.tree.map(lambda *x: np.stack(x), *frames)


def sequential(seq, rule, camera=h.CAMERA, free_space=False):
  state = jf.init_map(capacity=CAPACITY, num_classes=h.NUM_CLASSES, voxel_size=VOXEL, rule=rule,
                      free_space=free_space)
  return jf.fuse_sequence(state, seq, camera, rule)


def seen_again(seq, t, source):
  """`seq` whose frame t looks from frame `source`'s pose at a wall 1 m behind all it saw (so
  clearing frees what `source` saw); its own holes stay."""
  depth = np.array(seq.depth)
  seen = np.isfinite(depth[source]) & (depth[source] > 0)
  keep = np.isfinite(depth[t]) & (depth[t] > 0)
  depth[t] = np.where(keep, depth[source][seen].max() + 1.0, depth[t])
  poses = np.array(seq.T_world_cam)
  poses[t] = poses[source]
  return seq._replace(depth=depth, T_world_cam=poses)


def assert_same(a, b):
  """Integer leaves (keys, hits, counters) exactly; float rows to float32 rounding (vmap may
  vectorise a sum differently)."""
  assert jax.tree.structure(a) == jax.tree.structure(b)
  for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
    x, y = np.asarray(x), np.asarray(y)
    if np.issubdtype(x.dtype, np.floating):
      np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    else:
      np.testing.assert_array_equal(x, y)


def item(tree, *index):
  return jax.tree.map(lambda x: x[index], tree)


@pytest.mark.slow
def test_ragged_batch_equals_sequential():
  rng = np.random.default_rng(0)
  seqs = [sequence(rng, 3), sequence(rng, 1, height=5, width=7), sequence(rng, 2)]
  cams = [h.CAMERA, jf.Camera(5.0, 5.0, 3.0, 2.0), h.CAMERA]
  frames, mask = batch.stack_sequences(seqs)
  assert frames.depth.shape == (3, 3, h.HEIGHT, h.WIDTH)
  np.testing.assert_array_equal(mask, [[1, 1, 1], [1, 0, 0], [1, 1, 0]])
  rule = jf.rules.robust(beta=0.3)
  states = batch.fuse_batch(frames, cams, rule, capacity=CAPACITY, voxel_size=VOXEL, mask=mask)
  for b, (seq, cam) in enumerate(zip(seqs, cams)):
    assert_same(item(states, b), sequential(seq, rule, cam))


@pytest.mark.parametrize("free_space", h.main_tier_keeps([False, True], (True,)))
def test_mask_makes_padding_neutral_even_with_real_data(free_space):
  rng = np.random.default_rng(1)
  seq = sequence(rng, 3)
  if free_space:      # frame 2 sees through frame 0; one miss frees a voxel hit once
    seq = seen_again(seq, 2, 0)
    free_space = jf.FreeSpaceConfig(prob_miss=0.2)
  rule = jf.rules.bayes()
  mask = np.array([[True, False, True]])
  batched = jax.tree.map(lambda x: x[None], seq)
  states = batch.fuse_batch(batched, h.CAMERA, rule, capacity=CAPACITY, voxel_size=VOXEL,
                            mask=mask, free_space=free_space)
  kept = jax.tree.map(lambda x: x[np.array([0, 2])], seq)
  one = sequential(kept, rule, free_space=free_space)
  assert_same(item(states, 0), one)
  assert (jf.map_stats(one).get("free", 0) > 0) == bool(free_space)


def test_sweep_equals_one_rule_at_a_time():
  rng = np.random.default_rng(2)
  seq = sequence(rng, 2)
  betas = [0.0, 0.3, 1.0]
  rules, grid = batch.rule_grid(beta=betas, alpha0=[0.0, 5.0])
  np.testing.assert_allclose(grid["beta"], [0, 0, 0.3, 0.3, 1, 1])
  states = batch.fuse_sweep(seq, h.CAMERA, rules, capacity=CAPACITY, voxel_size=VOXEL)
  assert states.keys.shape == (6, CAPACITY, 3)
  for r in range(6):
    rule = jf.rules.robust(beta=grid["beta"][r], alpha0=grid["alpha0"][r])
    assert_same(item(states, r), sequential(seq, rule))


def test_sweep_over_a_batch_has_rule_then_sequence_axes():
  rng = np.random.default_rng(3)
  seqs = [sequence(rng, 2), sequence(rng, 1)]
  frames, mask = batch.stack_sequences(seqs)
  rules = jf.rules.stack([jf.rules.robust(beta=b, dirichlet=False) for b in (0.1, 0.6)])
  states = batch.fuse_sweep(frames, h.CAMERA, rules, capacity=CAPACITY, voxel_size=VOXEL,
                            mask=mask)
  assert states.keys.shape == (2, 2, CAPACITY, 3)
  assert_same(item(states, 1, 1), sequential(seqs[1], jf.rules.robust(beta=0.6,
                                                                        dirichlet=False)))


def test_sweep_over_per_class_rules_equals_one_rule_at_a_time():
  rng = np.random.default_rng(5)
  seqs = [sequence(rng, 2)]
  frames, mask = batch.stack_sequences(seqs)
  k = seqs[0].probs.shape[-1]
  betas = [np.linspace(0.05, 0.9, k, dtype=np.float32), np.full(k, 0.3, np.float32)]
  per_class = [jf.rules.robust(beta=b, dirichlet=False) for b in betas]
  states = batch.fuse_sweep(frames, h.CAMERA, jf.rules.stack(per_class), capacity=CAPACITY,
                            voxel_size=VOXEL, mask=mask)
  for r, rule in enumerate(per_class):
    assert_same(item(states, r, 0), sequential(seqs[0], rule))


def test_bad_batches_raise():
  rng = np.random.default_rng(4)
  a, b = sequence(rng, 2), sequence(rng, 3)
  with pytest.raises(ValueError, match="differ in length"):
    batch.stack_sequences([a, b], pad=False)
  with pytest.raises(ValueError, match="image size"):
    batch.stack_sequences([a, sequence(rng, 2, height=4)], pad=False)
  with pytest.raises(ValueError, match="same number of classes"):
    batch.stack_sequences([a, a._replace(probs=a.probs[..., :3], var=a.var[..., :3])])
  with pytest.raises(ValueError, match="either every sequence has var"):
    batch.stack_sequences([a, b._replace(var=None)])
  frames, mask = batch.stack_sequences([a, b])
  rule = jf.rules.robust()
  with pytest.raises(ValueError, match="mask must be a bool array"):
    batch.fuse_batch(frames, h.CAMERA, rule, capacity=CAPACITY, mask=mask[:, :2])
  with pytest.raises(ValueError, match=r"\(B, T, H, W\)"):
    batch.fuse_batch(a, h.CAMERA, rule, capacity=CAPACITY)
  with pytest.raises(ValueError, match="one per sequence"):
    batch.fuse_batch(frames, [h.CAMERA], rule, capacity=CAPACITY, mask=mask)
  with pytest.raises(ValueError, match="stack of rules"):
    batch.fuse_sweep(a, h.CAMERA, rule, capacity=CAPACITY)
  with pytest.raises(ValueError, match="beta must lie in"):
    batch.rule_grid(beta=[0.5, 1.5])


_SHARDED_SCRIPT = textwrap.dedent("""
    import jax, numpy as np
    import jaxfusion as jf
    from jaxfusion import batch
    from tests import engine_helpers as h
    assert jax.device_count() == 4, jax.devices()
    rng = np.random.default_rng(5)
    def seq(n):
      return jax.tree.map(lambda *x: np.stack(x), *[h.random_frame(rng) for _ in range(n)])
    frames, mask = batch.stack_sequences([seq(2), seq(1), seq(2)])   # B = 3, not a multiple of 4
    rule = jf.rules.robust(beta=0.3)
    mesh = batch.make_mesh()
    kw = dict(capacity=256, voxel_size=0.25, mask=mask)
    one = batch.fuse_batch(frames, h.CAMERA, rule, **kw)
    many = batch.fuse_batch(frames, h.CAMERA, rule, mesh=mesh, **kw)
    rules, _ = batch.rule_grid(beta=np.linspace(0, 1, 5))             # R = 5
    s_one = batch.fuse_sweep(frames, h.CAMERA, rules, **kw)
    s_many = batch.fuse_sweep(frames, h.CAMERA, rules, mesh=mesh, **kw)
    geometry = jf.TSDFConfig(voxel_size=0.1, capacity=2**8)           # with the TSDF layer
    g_one = batch.fuse_batch(frames, h.CAMERA, rule, geometry=geometry, **kw)
    g_many = batch.fuse_batch(frames, h.CAMERA, rule, geometry=geometry, mesh=mesh, **kw)
    assert int(g_one.geometry.num_blocks.sum()) > 0
    for a, b in [(one, many), (s_one, s_many), (g_one, g_many)]:
      for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-7)
    print("SHARDED_OK")
""")


@pytest.mark.slow
def test_sharded_over_four_devices_equals_one_device():
  env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4",
             JAX_PLATFORMS="cpu")
  root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
  env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
  proc = subprocess.run([sys.executable, "-c", _SHARDED_SCRIPT], env=env, cwd=root,
                        capture_output=True, text=True, timeout=300, check=False)
  assert proc.returncode == 0 and "SHARDED_OK" in proc.stdout, proc.stderr[-3000:]


def test_far_from_the_origin_a_batch_puts_pixels_where_fuse_sequence_does():
  # Found by bench/fuzz.py: with the voxel size a compile-time constant, XLA's rounding of the
  # division put points 10⁴–10⁵ m away into other voxels than `fuse_sequence` did.
  rule = jf.rules.sum_probs()
  height, width, k = 16, 20, 4
  camera = jf.Camera(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2)
  rng = np.random.default_rng(0)
  for scale in (1e4, 1e5):
    depth = rng.uniform(0.5, 6.0, (1, 1, height, width)).astype(np.float32)
    pose = np.eye(4, dtype=np.float32)[None, None].copy()
    pose[0, 0, :3, 3] = [scale, -scale / 3, scale / 7]
    frames = jf.Frame(depth, pose, np.full((1, 1, height, width, k), 0.25, np.float32), None)
    batched = jf.fuse_batch(frames, camera, rule, capacity=1024, voxel_size=0.05)
    single = jf.fuse_sequence(jf.init_map(capacity=1024, num_classes=k, voxel_size=0.05,
                                          rule=rule),
                              jax.tree.map(lambda x: x[0], frames), camera, rule)
    stored = lambda keys: {tuple(r) for r in np.asarray(keys) if r[0] != jf.EMPTY}
    assert stored(batched.keys[0]) == stored(single.keys), scale
