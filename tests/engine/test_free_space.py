"""Free space for the semantic layer (docs/equations.md §10): the marking against a slow NumPy
version and a ray test, the occupancy numbers by hand, change detection, and the layer's
round trips (growth, files)."""

import math

import hypothesis
import hypothesis.strategies as st
import jax
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import free_space

H, W, K = 24, 32, 4
CAM = jf.Camera(30.0, 30.0, (W - 1) / 2, (H - 1) / 2)
S = 0.1


def _probs(label, k=K, strength=0.7):
  p = np.full((H, W, k), (1 - strength) / (k - 1), np.float32)
  p[..., label] = strength
  return p


def _wall(z, label=0, pose=None):
  """A wall at z-depth `z` (kept off voxel boundaries: a point exactly on one may fall on either
  side in programs that XLA fuses differently)."""
  depth = np.full((H, W), z, np.float32)
  var = np.full((H, W, K), 0.01, np.float32)
  return jf.Frame(depth, np.eye(4, dtype=np.float32) if pose is None else pose, _probs(label),
                  var)


def _reference_free(keys, s, depth, T, cam, margin):
  """Slow NumPy §10.1: per voxel, the window of its footprint cut out of the depth image."""
  keys = np.asarray(keys)
  h, w = depth.shape
  d = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).astype(np.float32)
  s = np.float32(s)
  half = s * np.float32(math.sqrt(3.0) / 2.0)
  R, t = T[:3, :3].astype(np.float32), T[:3, 3].astype(np.float32)
  out = np.zeros(len(keys), bool)
  for i, k in enumerate(keys):
    if k[0] == jf.EMPTY:
      continue
    c = (k.astype(np.float32) + np.float32(0.5)) * s
    rel = c - t
    x, y, z = (rel[0] * R[0, j] + rel[1] * R[1, j] + rel[2] * R[2, j] for j in range(3))
    if not z > half:
      continue
    u = np.floor(np.float32(cam.fx) * x / z + np.float32(cam.cx) + np.float32(0.5))
    v = np.floor(np.float32(cam.fy) * y / z + np.float32(cam.cy) + np.float32(0.5))
    if not (0 <= u < w and 0 <= v < h):
      continue
    u, v = int(u), int(v)
    if not np.isfinite(d[v, u]):
      continue
    r = np.float32(max(cam.fx, cam.fy)) * half / z
    level = 1 if r <= 1 else int(np.ceil(np.log2(np.float32(r)))) + 1
    level = min(max(level, 1), free_space.MAX_LEVEL)
    rad = free_space.window_radius(level)
    window = d[max(v - rad, 0):v + rad + 1, max(u - rad, 0):u + rad + 1]
    out[i] = z + half + np.float32(margin) < window.min()
  return out


def _scene_depth(rng):
  """A wall with a box in front of it and some holes."""
  depth = np.full((H, W), rng.uniform(2.0, 3.0), np.float32)
  r0, c0 = rng.integers(0, H // 2), rng.integers(0, W // 2)
  depth[r0:r0 + rng.integers(3, H // 2), c0:c0 + rng.integers(3, W // 2)] = rng.uniform(0.8, 1.6)
  holes = rng.random((H, W)) < 0.05
  depth[holes] = rng.choice([0.0, np.nan, -1.0])
  return depth


def _pose(rng):
  angle = rng.normal(0, 0.05, 3)
  c, s_ = np.cos(angle[2]), np.sin(angle[2])
  T = np.eye(4, dtype=np.float32)
  T[:2, :2] = [[c, -s_], [s_, c]]
  T[:3, 3] = rng.normal(0, 0.1, 3)
  return T


def test_pyramid_is_the_window_minimum():
  rng = np.random.default_rng(3)
  depth = _scene_depth(rng)
  pyramid = np.asarray(free_space.depth_pyramid(depth))
  d = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf)
  for level in range(free_space.MAX_LEVEL + 1):
    r = free_space.window_radius(level)
    for v, u in [(0, 0), (5, 7), (H - 1, W - 1), (12, 3), (20, 30)]:
      want = d[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1].min()
      assert pyramid[level, v, u] == want, (level, v, u)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_marking_matches_numpy(seed):
  rng = np.random.default_rng(seed)
  depth = _scene_depth(rng)
  T = _pose(rng)
  # Voxels all over the frustum: in front of the wall, inside the box, behind, outside.
  keys = rng.integers([-15, -12, -2], [16, 13, 35], size=(3000, 3)).astype(np.int32)
  keys[::17] = jf.EMPTY
  want = _reference_free(keys, S, depth, T, CAM, S)
  got = np.asarray(free_space.free_voxels(keys, np.float32(S), depth, T, CAM, np.float32(S)))
  assert want.sum() > 100 and (~want).sum() > 100
  np.testing.assert_array_equal(got, want)


@hypothesis.settings(max_examples=25, deadline=None)
@hypothesis.given(seed=st.integers(0, 2**31 - 1))
def test_a_free_voxel_holds_no_measured_point(seed):
  """The ray test: a voxel marked free contains no back-projected point of a valid pixel, and
  the ray through its centre pixel passes beyond it."""
  rng = np.random.default_rng(seed)
  depth = _scene_depth(rng)
  T = _pose(rng)
  keys = rng.integers([-10, -8, 0], [11, 9, 32], size=(2000, 3)).astype(np.int32)
  free = np.asarray(free_space.free_voxels(keys, np.float32(S), depth, T, CAM, np.float32(0.0)))
  v, u = np.mgrid[0:H, 0:W]
  ok = np.isfinite(depth) & (depth > 0)
  z = depth[ok].astype(np.float64)
  cam_pts = np.stack([(u[ok] - CAM.cx) / CAM.fx * z, (v[ok] - CAM.cy) / CAM.fy * z, z], -1)
  world = cam_pts @ T[:3, :3].T.astype(np.float64) + T[:3, 3]
  point_keys = {tuple(k) for k in np.floor(world / S).astype(np.int64)}
  for k in keys[free]:
    assert tuple(k) not in point_keys
  # Every free voxel's centre is nearer than the depth at its pixel.
  centres = (keys[free] + 0.5) * S
  pc = (centres - T[:3, 3]) @ T[:3, :3].astype(np.float64)
  pu = np.floor(CAM.fx * pc[:, 0] / pc[:, 2] + CAM.cx + 0.5).astype(int)
  pv = np.floor(CAM.fy * pc[:, 1] / pc[:, 2] + CAM.cy + 0.5).astype(int)
  assert np.all(pc[:, 2] < depth[pv, pu])


def test_occupancy_by_hand_and_clearing():
  """Three hits of a wall at 2 m give L = 3·logit(0.7); a wall at 4 m then sees through it, and
  the 7th miss (L = 2.542 − 7·0.405 < 0) frees it: no longer read out, not found."""
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=4096, num_classes=K, rule=rule, free_space=True)
  for _ in range(3):
    state = jf.fuse_frame(state, _wall(2.03), CAM, rule)
  near = jf.read_map(state)
  slots, found = jf.hashing.lookup(state.keys, near["coords"], max_probes=64)
  assert np.all(np.asarray(found))
  log_odds = np.asarray(state.free_space.log_odds)[np.asarray(slots)]
  np.testing.assert_allclose(log_odds, 3 * math.log(0.7 / 0.3), rtol=1e-6)
  point = near["centers"][len(near["centers"]) // 2][None]
  for miss in range(1, 8):
    state = jf.fuse_frame(state, _wall(4.07, label=1), CAM, rule)
    assert bool(jf.query(state, point).found[0]) == (miss < 7), miss
  stats = jf.map_stats(state)
  assert stats["free"] == len(near["coords"])
  coords = jf.read_map(state)["coords"]
  assert not ({tuple(c) for c in near["coords"]} & {tuple(c) for c in coords})
  posterior, occupied = jf.voxel_posteriors(state)
  assert int(np.asarray(occupied).sum()) == len(coords)


def test_clamping_bounds_the_log_odds():
  rule = jf.rules.sum_labels()
  state = jf.init_map(capacity=4096, num_classes=K, rule=rule, free_space=True)
  for _ in range(12):
    state = jf.fuse_frame(state, _wall(2.03), CAM, rule)
  stored = np.asarray(state.keys[:, 0] != jf.EMPTY)
  np.testing.assert_allclose(np.asarray(state.free_space.log_odds)[stored],
                             math.log(0.971 / 0.029), rtol=1e-6)
  for _ in range(20):
    state = jf.fuse_frame(state, _wall(4.07), CAM, rule)
  np.testing.assert_allclose(np.asarray(state.free_space.log_odds)[stored],
                             math.log(0.1192 / 0.8808), rtol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(jf.rules.PAPER_RULES))
def test_a_moved_object_leaves_no_ghost_and_restarts(name):
  """With every rule: the wall at 2 m (class 0) is seen through until free, then a class-2 wall
  comes back at 2 m. With free space on it restarts from the prior and reads class 2 with this
  frame's pixels only; without, Bayes-like rules still read class 0."""
  rule = jf.rules.by_name(name)
  for on in (True, False):
    state = jf.init_map(capacity=4096, num_classes=K, rule=rule, free_space=on)
    for _ in range(10):
      state = jf.fuse_frame(state, _wall(2.03, label=0), CAM, rule)
    before = jf.read_map(state)
    for _ in range(10):
      state = jf.fuse_frame(state, _wall(4.07, label=1), CAM, rule)
    old = {tuple(c) for c in before["coords"]}
    kept = [tuple(c) for c in jf.read_map(state)["coords"] if tuple(c) in old]
    assert (len(kept) == 0) == on
    state = jf.fuse_frame(state, _wall(2.03, label=2), CAM, rule)
    back = jf.read_map(state)
    mask = np.array([tuple(c) in old for c in back["coords"]])
    if on:
      assert mask.sum() == len(old)
      assert np.all(back["labels"][mask] == 2)
      hits_one_frame = jf.read_map(jf.fuse_frame(
          jf.init_map(capacity=4096, num_classes=K, rule=rule), _wall(2.03, label=2), CAM, rule))
      np.testing.assert_array_equal(back["hits"][mask], hits_one_frame["hits"])
      np.testing.assert_allclose(back["posterior"][mask], hits_one_frame["posterior"], atol=1e-6)
    elif name not in ("sum_probs", "sum_labels"):
      assert np.all(back["labels"][mask] == 0)


def test_a_static_view_keeps_every_row_bit_identical():
  """Nothing in front of the surface: the layer changes no row, hit or read-out."""
  rule = jf.rules.robust()
  frames = [_wall(2.03 + 0.011 * t, label=t % K)._replace(
      probs=np.random.default_rng(t).dirichlet(np.ones(K), (H, W)).astype(np.float32))
      for t in range(4)]
  out = []
  for on in (False, True):
    state = jf.init_map(capacity=4096, num_classes=K, rule=rule, free_space=on)
    for frame in frames:
      state = jf.fuse_frame(state, frame, CAM, rule)
    out.append(state)
  a, b = jf.read_map(out[0]), jf.read_map(out[1])
  for key in a:
    np.testing.assert_array_equal(a[key], b[key])
  assert out[1].free_space is not None and out[0].free_space is None


def test_growth_and_files_keep_the_layer(tmp_path):
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=2048, num_classes=K, rule=rule,
                      free_space=jf.FreeSpaceConfig(margin=0.05))
  for z in (2.03, 2.03, 4.07):
    state = jf.fuse_frame(state, _wall(z), CAM, rule)
  grown = jf.grow_map(state, 4096)
  for key, value in jf.read_map(state).items():
    np.testing.assert_array_equal(jf.read_map(grown)[key], value)
  assert grown.free_space.config == state.free_space.config
  path = str(tmp_path / "map.npz")
  jf.io.save_map(path, grown, rule)
  loaded, _, _ = jf.io.load_map(path)
  np.testing.assert_array_equal(np.asarray(loaded.free_space.log_odds),
                                np.asarray(grown.free_space.log_odds))
  assert loaded.free_space.config.margin == 0.05


def test_batched_maps_clear_too():
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=4096, num_classes=K, rule=rule, free_space=True)
  stack = jax.tree.map(lambda x: np.stack([x, x]), state)
  fuse = jax.jit(jax.vmap(jf.fusion.fuse_frame_unchecked, in_axes=(0, None, None, None)))
  for z in [2.03] * 2 + [4.07] * 8:
    stack = fuse(stack, _wall(z), CAM, rule)
  one = jf.init_map(capacity=4096, num_classes=K, rule=rule, free_space=True)
  for z in [2.03] * 2 + [4.07] * 8:
    one = jf.fuse_frame(one, _wall(z), CAM, rule)
  np.testing.assert_array_equal(np.asarray(stack.free_space.log_odds[1]),
                                np.asarray(one.free_space.log_odds))


def test_bad_settings_get_one_line():
  with pytest.raises(ValueError, match="prob_hit > 0.5 > prob_miss"):
    jf.FreeSpaceConfig(prob_hit=0.4)
  with pytest.raises(ValueError, match="clamp_min < occupancy < clamp_max"):
    jf.FreeSpaceConfig(clamp_min=0.6)
  with pytest.raises(ValueError, match="margin"):
    jf.FreeSpaceConfig(margin=-1.0)
  with pytest.raises(TypeError, match="free_space must be"):
    jf.init_map(capacity=1024, num_classes=K, rule=jf.rules.bayes(), free_space="yes")
