"""Maps that grow: `grow_map` keeps every voxel exactly, and a `Mapper` that starts small ends
with the same map as one started large, without dropping a voxel."""

import warnings

import jax
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import mapper as mapper_lib
from jaxfusion import state as state_lib

K = 5
CAMERA = jf.Camera(24.0, 24.0, 19.5, 14.5)


def _frames(num_frames=14, seed=0):
  """A walk past rough walls at 5 cm voxels: about 1 300 new voxels a frame, ~17 000 in all."""
  rng = np.random.default_rng(seed)
  depth = rng.uniform(1.0, 6.0, (num_frames, 30, 40)).astype(np.float32)
  depth[:, :2] = 0.0                                      # holes are skipped
  poses = np.tile(np.eye(4, dtype=np.float32), (num_frames, 1, 1))
  poses[:, 0, 3] = np.arange(num_frames) * 0.8
  probs = rng.dirichlet(np.ones(K), (num_frames, 30, 40)).astype(np.float32)
  var = rng.uniform(0.0, 0.05, (num_frames, 30, 40, K)).astype(np.float32)
  return jf.Frame(depth, poses, probs, var)


def _fixed(frames, capacity, rule):
  state = jf.init_map(capacity=capacity, num_classes=K, voxel_size=0.05, rule=rule)
  return jf.fuse_sequence(state, frames, CAMERA, rule)


def _assert_same_map(a, b):
  va, vb = jf.read_map(a), jf.read_map(b)
  assert set(va) == set(vb)
  np.testing.assert_array_equal(va["coords"], vb["coords"])
  np.testing.assert_array_equal(va["hits"], vb["hits"])
  np.testing.assert_array_equal(va["labels"], vb["labels"])
  for k in ("posterior", "entropy") + (("confidence",) if "confidence" in va else ()):
    np.testing.assert_allclose(va[k], vb[k], rtol=1e-6, atol=1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["robust_dr", "sum_labels"])
def test_grow_map_keeps_every_voxel_exactly(name):
  rule = jf.rules.by_name(name)
  state = _fixed(_frames(4), 2**14, rule)
  grown = state_lib.grow_map(state, 2**16)
  assert grown.capacity == 2**16 and int(grown.num_occupied) == int(state.num_occupied)
  va, vg = jf.read_map(state), jf.read_map(grown)
  for key in va:
    np.testing.assert_array_equal(va[key], vg[key])        # bit for bit: rows are copied
  # The grown map keeps fusing like a map made that large.
  more = _frames(2, seed=1)
  _assert_same_map(jf.fuse_sequence(grown, more, CAMERA, rule),
                   jf.fuse_sequence(_fixed(_frames(4), 2**16, rule), more, CAMERA, rule))


@pytest.mark.slow
def test_mapper_from_2_14_equals_a_map_started_at_2_18():
  rule = jf.rules.robust(beta=0.3)
  frames = _frames()
  with warnings.catch_warnings():
    warnings.simplefilter("ignore", jf.MapFullWarning)
    small = _fixed(frames, 2**14, rule)
  assert int(small.num_dropped) > 0                       # without growth the map overflows
  big = _fixed(frames, 2**18, rule)
  assert int(big.num_dropped) == 0 and int(big.num_occupied) > 0.7 * 2**14
  for how in ("frame", "sequence"):
    mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**14)
    if how == "frame":
      for t in range(frames.depth.shape[0]):
        mapper.fuse(jax.tree.map(lambda x, t=t: x[t], frames), CAMERA)
    else:
      mapper.fuse_sequence(frames, CAMERA, chunk=4)
    assert mapper.growths and int(mapper.state.num_dropped) == 0, how
    assert int(mapper.state.num_occupied) <= mapper.grow_at * mapper.capacity
    assert mapper.frames_fused == frames.depth.shape[0]
    _assert_same_map(mapper.state, big)


@pytest.mark.slow
def test_new_voxel_count_is_exact_for_depth_valid_frames():
  rule = jf.rules.bayes()
  frames = _frames(3)
  state = _fixed(jax.tree.map(lambda x: x[:1], frames), 2**16, rule)
  count = int(mapper_lib.new_voxel_count(state, frames.depth[1:], frames.T_world_cam[1:],
                                         CAMERA))
  after = jf.fuse_sequence(state, jax.tree.map(lambda x: x[1:], frames), CAMERA, rule)
  before = int(_fixed(jax.tree.map(lambda x: x[:1], frames), 2**16, rule).num_occupied)
  assert count == int(after.num_occupied) - before > 0


@pytest.mark.slow   # compiles fuse_sequence with a geometry layer at two capacities: ~18 s
def test_room_checks_are_exact_and_compile_their_heavy_half_once():
  """`new_voxel_count`, `tsdf.new_block_count` and `tsdf.count_new_blocks` count what fusing
  the frames adds, at two capacities; the frames' voxel grouping (the heavy program) compiles
  once for both, only the small lookup (`hashing.count_missing`) per capacity."""
  rule = jf.rules.bayes()
  frames = _frames(3)
  first = jax.tree.map(lambda x: x[:1], frames)
  rest = jax.tree.map(lambda x: x[1:], frames)
  voxel_programs = mapper_lib._frame_voxel_groups._cache_size()
  for capacity, blocks in ((2**15, 2**11), (2**16, 2**12)):
    config = jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=blocks)
    state = jf.init_map(capacity=capacity, num_classes=K, voxel_size=0.05, rule=rule,
                        geometry=config)
    state = jf.fuse_sequence(state, first, CAMERA, rule)
    voxels = int(mapper_lib.new_voxel_count(state, rest.depth, rest.T_world_cam, CAMERA))
    new_blocks = int(jf.tsdf.new_block_count(state.geometry, rest.depth, rest.T_world_cam,
                                             CAMERA))
    assert jf.tsdf.count_new_blocks(state.geometry, rest.depth, rest.T_world_cam,
                                    CAMERA) == new_blocks
    before, before_blocks = int(state.num_occupied), int(state.geometry.num_blocks)
    after = jf.fuse_sequence(state, rest, CAMERA, rule)
    assert voxels == int(after.num_occupied) - before > 0
    assert new_blocks == int(after.geometry.num_blocks) - before_blocks > 0
  assert mapper_lib._frame_voxel_groups._cache_size() - voxel_programs <= 1


@pytest.mark.slow
def test_mapper_stops_at_max_capacity_and_counts_drops():
  rule = jf.rules.bayes()
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**12, max_capacity=2**13)
  with warnings.catch_warnings():
    warnings.simplefilter("ignore", jf.MapFullWarning)
    mapper.fuse_sequence(_frames(6), CAMERA)
  assert mapper.capacity == 2**13 and int(mapper.state.num_dropped) > 0


def test_grow_map_and_mapper_validate():
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=2**10, num_classes=K, rule=rule)
  with pytest.raises(ValueError, match="shrink"):
    state_lib.grow_map(state, 2**9)
  with pytest.raises(ValueError, match="power of two"):
    state_lib.grow_map(state, 3000)
  with pytest.raises(ValueError, match="does not match"):
    state_lib.grow_map(state, 2**11, rule=jf.rules.robust())
  with pytest.raises(ValueError, match="grow_at"):
    jf.Mapper(rule, num_classes=K, grow_at=1.5)
  with pytest.raises(ValueError, match="growth_factor must be 2, 4 or 8; got 3"):
    jf.Mapper(rule, num_classes=K, growth_factor=3)
  with pytest.raises(ValueError, match=r"\(T, H, W\)"):
    jf.Mapper(rule, num_classes=K).fuse_sequence(jax.tree.map(lambda x: x[0], _frames(1)),
                                                 CAMERA)


def _blocks(layer) -> dict:
  keys = np.asarray(layer.block_keys)
  stored = keys[:, 0] != jf.hashing.EMPTY
  sdf, weight = np.asarray(layer.sdf), np.asarray(layer.weight)
  return {tuple(k): (s, w) for k, s, w in zip(keys[stored], sdf[stored], weight[stored])}


@pytest.mark.slow
def test_mapper_grows_its_geometry_layer_without_losing_a_block():
  """A Mapper whose block table starts tiny grows it (the room check's cheap bounds and its
  exact count) and ends with the layer a large fixed table holds: every block, its sdf and
  weight, bit for bit, none dropped."""
  rule = jf.rules.bayes()
  frames = _frames()
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**15,
                     geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**5))
  for t in range(frames.depth.shape[0]):
    mapper.fuse(jax.tree.map(lambda x, t=t: x[t], frames), CAMERA)
  fixed = jf.init_map(capacity=2**15, num_classes=K, voxel_size=0.05, rule=rule,
                      geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**13))
  fixed = jf.fuse_sequence(fixed, frames, CAMERA, rule)
  grown = mapper.state.geometry
  assert len(mapper.geometry_growths) >= 2
  assert int(grown.num_dropped) == 0 == int(fixed.geometry.num_dropped)
  assert int(grown.num_blocks) <= 0.5 * grown.capacity
  a, b = _blocks(grown), _blocks(fixed.geometry)
  assert a.keys() == b.keys()
  for key, (sdf, weight) in a.items():
    np.testing.assert_array_equal(sdf, b[key][0])
    np.testing.assert_array_equal(weight, b[key][1])
