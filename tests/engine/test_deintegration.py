"""Exact de-integration and re-integration (docs/equations.md §11): unfuse ∘ fuse = identity for
every invertible rule, reintegrate = fusing at the new poses from scratch, the Mapper's kept
frames, and one clear line for what cannot be inverted."""

import hypothesis
import hypothesis.strategies as st
import jax
import numpy as np
import pytest

import jaxfusion as jf

H, W, K = 24, 32, 4
CAM = jf.Camera(30.0, 30.0, (W - 1) / 2, (H - 1) / 2)


def _frame(seed, *, onehot=False):
  rng = np.random.default_rng(seed)
  depth = rng.uniform(1.4, 2.2, (H, W)).astype(np.float32)
  depth[rng.random((H, W)) < 0.05] = 0.0
  T = np.eye(4, dtype=np.float32)
  T[:3, 3] = rng.normal(0, 0.1, 3)
  probs = rng.dirichlet(np.full(K, 0.5), (H, W)).astype(np.float32)
  if onehot:
    probs = np.eye(K, dtype=np.float32)[probs.argmax(-1)]
  probs[0, 0] = np.nan        # bad data inside a frame: skipped in both directions
  var = rng.uniform(0, 0.02, (H, W, K)).astype(np.float32)
  return jf.Frame(depth, T, probs, var, rng.integers(0, 255, (H, W, 3), dtype=np.uint8))


def _glfs():
  table = np.random.default_rng(5).uniform(0.3, 3.0, (K, 5, 4)).astype(np.float32)
  return jf.rules.glfs(table)


INVERTIBLE = {
    "sum_probs": jf.rules.sum_probs, "sum_labels": jf.rules.sum_labels,
    "bayes": jf.rules.bayes, "robust_r": lambda: jf.rules.robust(dirichlet=False),
    "robust_r_per_class": lambda: jf.rules.robust(dirichlet=False, beta=[0.1, 0.2, 0.3, 0.4]),
    "bayes_mean": lambda: jf.rules.bayes(aggregate="mean"), "glfs": _glfs,
}


def _fused(rule, frames, **kw):
  state = jf.init_map(capacity=8192, num_classes=K, rule=rule, **kw)
  for frame in frames:
    state = jf.fuse_frame(state, frame, CAM, rule)
  return state


def _assert_same_map(a, b, *, atol=1e-5):
  ra, rb = jf.read_map(a), jf.read_map(b)
  np.testing.assert_array_equal(ra["coords"], rb["coords"])
  np.testing.assert_array_equal(ra["hits"], rb["hits"])
  np.testing.assert_allclose(ra["posterior"], rb["posterior"], atol=atol)


def _rows_at(state, name):
  coords = jf.read_map(state)["coords"]
  slots, found = jf.hashing.lookup(state.keys, coords, max_probes=state.max_probes)
  assert np.all(np.asarray(found))
  return np.asarray(state.rows[name])[np.asarray(slots)]


@pytest.mark.slow
@pytest.mark.parametrize("name", list(INVERTIBLE))
def test_unfuse_equals_the_map_without_the_frame(name):
  rule = INVERTIBLE[name]()
  frames = [_frame(s) for s in range(4)]
  state = jf.unfuse_frame(_fused(rule, frames), frames[1], CAM, rule)
  _assert_same_map(state, _fused(rule, [frames[0], frames[2], frames[3]]))


def test_label_counts_come_back_exactly():
  rule = jf.rules.sum_labels()
  frames = [_frame(s) for s in range(3)]
  state = jf.unfuse_frame(_fused(rule, frames), frames[2], CAM, rule)
  want = _fused(rule, frames[:2])
  np.testing.assert_array_equal(_rows_at(state, "score"), _rows_at(want, "score"))


@hypothesis.settings(max_examples=6, deadline=None)
@hypothesis.given(seeds=st.lists(st.integers(0, 10**6), min_size=2, max_size=4, unique=True),
                  which=st.integers(0, 3), onehot=st.booleans())
def test_unfuse_after_fuse_is_the_identity(seeds, which, onehot):
  """Property: for random frames (one-hot probabilities included), fusing a frame and taking it
  out again leaves the map that the other frames make."""
  rule = jf.rules.bayes()
  frames = [_frame(s, onehot=onehot) for s in seeds]
  which = which % len(frames)
  state = jf.unfuse_frame(_fused(rule, frames), frames[which], CAM, rule)
  rest = [f for i, f in enumerate(frames) if i != which]
  _assert_same_map(state, _fused(rule, rest), atol=1e-5)
  assert np.all(np.isfinite(np.asarray(state.rows["logp"])))


def test_unfusing_every_frame_empties_the_map():
  rule = jf.rules.robust(dirichlet=False)
  frames = [_frame(s) for s in range(3)]
  state = _fused(rule, frames)
  for frame in (frames[1], frames[0], frames[2]):
    state = jf.unfuse_frame(state, frame, CAM, rule)
  assert len(jf.read_map(state)["coords"]) == 0
  assert int(np.asarray(state.hits).max()) == 0
  prior = np.asarray(jf.init_map(capacity=8192, num_classes=K, rule=rule).rows["logp"])
  np.testing.assert_array_equal(np.asarray(state.rows["logp"]), prior)
  assert not np.any(np.asarray(jf.query(state, np.zeros((1, 3), np.float32)).found))


@pytest.mark.slow
def test_the_geometry_layer_is_de_integrated_too():
  rule = jf.rules.bayes()
  geometry = jf.TSDFConfig(capacity=1024)
  frames = [_frame(s) for s in range(3)]
  state = jf.unfuse_frame(_fused(rule, frames, geometry=geometry), frames[0], CAM, rule)
  want = _fused(rule, frames[1:], geometry=geometry)
  _assert_same_map(state, want)
  seen = lambda g: int(np.count_nonzero(np.asarray(g.weight) > 0))
  assert seen(state.geometry) == seen(want.geometry) > 0
  mesh_a, mesh_b = jf.extract_mesh(state), jf.extract_mesh(want)
  assert len(mesh_a.faces) == len(mesh_b.faces) > 0
  np.testing.assert_allclose(np.sort(mesh_a.vertices, axis=0), np.sort(mesh_b.vertices, axis=0),
                             atol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bayes", "sum_labels", "glfs"])
def test_reintegrate_equals_fusing_at_the_new_poses(name):
  rule = INVERTIBLE[name]()
  frames = [_frame(s) for s in range(4)]
  moved = [1, 3]
  new = np.stack([frames[i].T_world_cam for i in moved]).copy()
  new[:, :3, 3] += [0.13, -0.07, 0.05]
  stack = jax.tree.map(lambda *x: np.stack(x), *[frames[i] for i in moved])
  state = jf.reintegrate(_fused(rule, frames), stack, stack.T_world_cam, new, CAM, rule)
  corrected = [f._replace(T_world_cam=new[moved.index(i)]) if i in moved else f
               for i, f in enumerate(frames)]
  _assert_same_map(state, _fused(rule, corrected))


@pytest.mark.slow
def test_the_mapper_unfuses_reintegrates_and_rebuilds():
  rule = jf.rules.bayes()
  frames = [_frame(s) for s in range(5)]
  mapper = jf.Mapper(rule, num_classes=K, capacity=1024, keep_frames=5)
  for t, frame in enumerate(frames):
    mapper.fuse(frame, CAM, frame_id=f"f{t}")
  mapper.unfuse("f2")
  rest = [frames[i] for i in (0, 1, 3, 4)]
  _assert_same_map(mapper.state, _fused(rule, rest))
  new = np.stack([frames[0].T_world_cam, frames[4].T_world_cam])
  new[:, 0, 3] += 0.2
  mapper.reintegrate(["f0", "f4"], new)
  corrected = [rest[0]._replace(T_world_cam=new[0]), rest[1], rest[2],
               rest[3]._replace(T_world_cam=new[1])]
  _assert_same_map(mapper.state, _fused(rule, corrected))
  assert np.allclose(mapper.kept["f4"][0].T_world_cam, new[1])
  # A rule that cannot be inverted rebuilds from the kept frames instead.
  dr = jf.rules.robust()
  m = jf.Mapper(dr, num_classes=K, capacity=1024, keep_frames=3, free_space=True)
  for frame in frames[:3]:
    m.fuse(frame, CAM)
  with pytest.raises(ValueError, match="cannot be de-integrated"):
    m.reintegrate([0], new[:1])
  m.rebuild({1: new[0]})
  want = jf.init_map(capacity=m.capacity, num_classes=K, rule=dr, free_space=True)
  for frame in (frames[0], frames[1]._replace(T_world_cam=new[0]), frames[2]):
    want = jf.fuse_frame(want, frame, CAM, dr)
  for key, value in jf.read_map(want).items():
    np.testing.assert_array_equal(jf.read_map(m.state)[key], value)


def test_the_mapper_keeps_a_bounded_number_of_frames():
  mapper = jf.Mapper(jf.rules.bayes(), num_classes=K, capacity=1024, keep_frames=2)
  frames = [_frame(s) for s in range(4)]
  stack = jax.tree.map(lambda *x: np.stack(x), *frames[:3])
  mapper.fuse_sequence(stack, CAM)
  mapper.fuse(frames[3], CAM)
  assert list(mapper.kept) == [2, 3]
  with pytest.raises(ValueError, match="frame id 0 is not held"):
    mapper.unfuse(0)
  with pytest.raises(ValueError, match="rebuild needs every fused frame kept"):
    mapper.rebuild()
  with pytest.raises(ValueError, match="already held"):
    mapper.fuse(frames[0], CAM, frame_id=3)
  with pytest.raises(ValueError, match="keeps no frames"):
    jf.Mapper(jf.rules.bayes(), num_classes=K).unfuse(0)


@pytest.mark.slow
def test_what_cannot_be_inverted_gets_one_line():
  frames = [_frame(s) for s in range(2)]
  stack = jax.tree.map(lambda *x: np.stack(x), *frames)
  for rule in (jf.rules.robust(), jf.rules.robust(regularize=False), jf.rules.learned()):
    with pytest.raises(ValueError, match=f"rule {rule.name!r} cannot be de-integrated"):
      jf.unfuse_frame(_fused(rule, frames), frames[0], CAM, rule)
  bayes = jf.rules.bayes()
  with pytest.raises(ValueError, match="free space cannot be de-integrated"):
    jf.unfuse_frame(_fused(bayes, frames, free_space=True), frames[0], CAM, bayes)
  gated = jf.TSDFConfig(capacity=1024, gate_semantics=True)
  with pytest.raises(ValueError, match="gates semantics"):
    jf.unfuse_frame(_fused(bayes, frames, geometry=gated), frames[0], CAM, bayes)
  state = _fused(bayes, frames)
  with pytest.raises(ValueError, match=r"new_poses must have shape \(2, 4, 4\)"):
    jf.reintegrate(state, stack, stack.T_world_cam, stack.T_world_cam[:1], CAM, bayes)
  bad = np.array(stack.T_world_cam)
  bad[1, 0, 0] = np.nan
  with pytest.raises(ValueError, match="old_poses"):
    jf.reintegrate(state, stack, bad, stack.T_world_cam, CAM, bayes)
  with pytest.raises(ValueError, match="K"):
    jf.unfuse_frame(state, frames[0]._replace(probs=frames[0].probs[..., :3],
                                              var=frames[0].var[..., :3]), CAM, bayes)


def test_unfuse_composes_under_jit():
  rule = jf.rules.bayes()
  frames = [_frame(s) for s in range(3)]
  state = _fused(rule, frames)
  f = jax.jit(lambda s, fr: jf.deintegration.unfuse_frame_unchecked(s, fr, CAM, rule))
  _assert_same_map(f(state, frames[2]), _fused(rule, frames[:2]))
