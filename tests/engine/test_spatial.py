"""The spatial term at read-out (docs/equations.md §4.1): a NumPy version on a small map, a
hand-computed case, λ = 0, every read-out path (voxel_posteriors, read_map, query, mesh labels,
map files), gradients to λ, and one clear line for a bad kernel."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import io
from jaxfusion import readout
from tests import engine_helpers as h

K = h.NUM_CLASSES
VOXEL = 0.25


def _frames(seed, n=3):
  rng = np.random.default_rng(seed)
  return [h.random_frame(rng, voxel_size=VOXEL) for _ in range(n)]


def _fuse(rule, frames, capacity=2048):
  state = jf.init_map(capacity=capacity, num_classes=K, voxel_size=VOXEL, rule=rule)
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  return state


def _numpy_smooth(keys, posterior, spatial):
  """§4.1 by dictionary lookups: `keys (N, 3)`, `posterior (N, K)` of every observed voxel."""
  index = {tuple(k): i for i, k in enumerate(keys.tolist())}
  out = np.zeros_like(posterior, np.float64)
  for i, key in enumerate(keys.tolist()):
    sums, counts = np.zeros((3, posterior.shape[1])), np.zeros(3)
    for dx in (-1, 0, 1):
      for dy in (-1, 0, 1):
        for dz in (-1, 0, 1):
          if (dx, dy, dz) == (0, 0, 0):
            continue
          j = index.get((key[0] + dx, key[1] + dy, key[2] + dz))
          if j is not None:
            shell = abs(dx) + abs(dy) + abs(dz) - 1
            sums[shell] += posterior[j]
            counts[shell] += 1
    means = sums / np.maximum(counts, 1)[:, None]
    z = np.log(np.maximum(posterior[i], np.finfo(np.float32).tiny)) + (means.T * spatial).sum(1)
    z = np.exp(z - z.max())
    out[i] = z / z.sum()
  return out


def _kernel(seed=0):
  return np.random.default_rng(seed).normal(0, 2.0, (K, 3)).astype(np.float32)


def test_read_map_matches_numpy_and_lambda_zero_is_the_plain_map():
  frames = _frames(0)
  table = np.random.default_rng(1).uniform(0.5, 2.0, (K, 5, 4))
  plain_rule = jf.rules.family({"table": table})
  plain = jf.read_map(_fuse(plain_rule, frames))
  spatial = _kernel()
  smoothed = jf.read_map(_fuse(jf.rules.family({"table": table, "spatial": spatial}), frames))
  assert len(plain["coords"]) > 50
  np.testing.assert_array_equal(smoothed["coords"], plain["coords"])
  want = _numpy_smooth(plain["coords"], plain["posterior"].astype(np.float64), spatial)
  np.testing.assert_allclose(smoothed["posterior"], want, atol=2e-5, rtol=1e-4)
  assert np.any(smoothed["labels"] != plain["labels"])        # the kernel changes labels
  np.testing.assert_array_equal(smoothed["labels"], want.argmax(-1))
  zero = jf.read_map(_fuse(jf.rules.family({"table": table, "spatial": np.zeros((K, 3))}),
                           frames))
  np.testing.assert_allclose(zero["posterior"], plain["posterior"], atol=1e-6)
  # A map of a rule without the term carries none: the same pytree as before the term existed.
  assert _fuse(plain_rule, frames[:1]).spatial is None


def test_hand_computed_case_of_one_face_neighbour():
  # Two voxels side by side, one frame each, at different classes; λ only on faces.
  k = 3
  spatial = np.zeros((k, 3), np.float32)
  spatial[:, 0] = [1.0, 2.0, 0.0]
  rule = jf.rules.family({"spatial": spatial})
  cam = jf.Camera(fx=4.0, fy=4.0, cx=0.5, cy=0.1)
  depth = np.full((1, 2), 1.0, np.float32)         # two pixels, x = ∓0.125 m at z = 1 m
  probs = np.array([[[0.7, 0.2, 0.1], [0.1, 0.6, 0.3]]], np.float32)
  state = jf.init_map(capacity=64, num_classes=k, voxel_size=0.25, rule=rule)
  state = jf.fuse_frame(state, jf.Frame(depth, np.eye(4, dtype=np.float32), probs), cam, rule)
  out = jf.read_map(state)
  assert len(out["coords"]) == 2 and abs(int(out["coords"][0, 0]) - int(out["coords"][1, 0])) == 1
  p, q = probs[0]
  for row, (own, other) in zip(out["posterior"], ((p, q), (q, p))):
    z = np.log(own) + np.array([1.0, 2.0, 0.0]) * other
    np.testing.assert_allclose(row, np.exp(z) / np.exp(z).sum(), rtol=1e-5)


def test_every_read_out_path_uses_it():
  frames = _frames(2)
  rule = jf.rules.family({"beta": 0.2, "spatial": _kernel(2)})
  state = _fuse(rule, frames)
  out = jf.read_map(state)
  posterior, occupied = jf.voxel_posteriors(state)
  keys = np.asarray(state.keys)
  slot_of = {tuple(k): s for s, k in enumerate(keys.tolist())}
  slots = np.array([slot_of[tuple(c)] for c in out["coords"].tolist()])
  assert np.all(np.asarray(occupied)[slots])
  np.testing.assert_allclose(np.asarray(posterior)[slots], out["posterior"], atol=1e-6)
  q = jf.query(state, out["centers"])
  assert np.all(np.asarray(q.found))
  np.testing.assert_allclose(np.asarray(q.posterior), out["posterior"], atol=1e-6)


def test_a_map_file_keeps_the_kernel(tmp_path):
  frames = _frames(3, n=2)
  rule = jf.rules.family({"moment_weights": np.full(6, 0.3), "spatial": _kernel(3)})
  state = _fuse(rule, frames)
  io.save_map(str(tmp_path / "m.npz"), state, rule)
  loaded, loaded_rule, _ = io.load_map(str(tmp_path / "m.npz"))
  np.testing.assert_array_equal(np.asarray(loaded.spatial), np.asarray(state.spatial))
  assert jf.rules.family_lib.terms(loaded_rule) == ("moments", "spatial")
  np.testing.assert_array_equal(jf.read_map(loaded)["posterior"], jf.read_map(state)["posterior"])


@pytest.mark.slow
def test_mesh_labels_read_the_smoothed_posterior():
  frames = _frames(4)
  config = jf.tsdf.TSDFConfig(voxel_size=VOXEL / 2, capacity=2**9)
  rule = jf.rules.family({"spatial": _kernel(4) * 3})
  state = jf.init_map(capacity=2048, num_classes=K, voxel_size=VOXEL, rule=rule, geometry=config)
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  mesh = jf.extract_mesh(state)
  assert len(mesh.vertices) > 0
  q = jf.query(state, mesh.vertices)
  found = np.asarray(q.found)
  np.testing.assert_array_equal(mesh.labels[found], np.asarray(q.posterior).argmax(-1)[found])
  plain = state.replace(spatial=None)
  assert np.any(jf.label_mesh(mesh, plain).labels[found] != mesh.labels[found])


@pytest.mark.slow
def test_gradient_reaches_the_kernel():
  frames = _frames(5, n=2)

  def loss(spatial):
    rule = jf.rules.family({"spatial": spatial})
    state = jf.init_map(capacity=1024, num_classes=K, voxel_size=VOXEL, rule=rule)
    for f in frames:
      state = jf.fuse_frame(state, f, h.CAMERA, rule)
    posterior, occupied = readout.voxel_posteriors(state)
    return -jnp.sum(jnp.log(posterior[:, 0] + 1e-6) * occupied)

  spatial = jnp.asarray(_kernel(5) * 0.3)
  g = np.asarray(jax.grad(loss)(spatial))
  assert np.all(np.isfinite(g)) and np.any(g != 0)
  step = 1e-2
  for i, s in ((0, 0), (1, 1), (2, 2)):
    e = np.zeros((K, 3), np.float32)
    e[i, s] = step
    fd = (float(loss(spatial + e)) - float(loss(spatial - e))) / (2 * step)
    assert g[i, s] == pytest.approx(fd, rel=0.05, abs=1e-2)


def test_bad_kernels_are_one_clear_line():
  with pytest.raises(ValueError, match=r"spatial must have shape \(K, 3\)"):
    jf.rules.family({"spatial": np.zeros((K, 2))})
  with pytest.raises(ValueError, match="spatial must be finite"):
    jf.rules.family({"spatial": np.full((K, 3), np.nan)})
  with pytest.raises(ValueError, match=rf"spatial must have shape \(K, 3\) = \({K}, 3\)"):
    jf.init_map(capacity=64, num_classes=K, rule=jf.rules.family({"spatial": np.zeros((K + 1, 3))}))
