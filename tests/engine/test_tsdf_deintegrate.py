"""De-integration of the geometry layer (jaxfusion.tsdf.deintegrate, docs/equations.md §8.7):
integrating A, B, C and removing B equals integrating A and C; removing every frame leaves no
observed voxel; a frame whose blocks are not stored changes nothing; the weight cap; bad input."""

import jax
import numpy as np
import pytest

from jaxfusion import tsdf
from tests import engine_helpers as h
from tests.engine.test_tsdf import CAM
from tests.engine.test_tsdf import _observed
from tests.engine.test_tsdf import _plane_depth
from tests.engine.test_tsdf import _pose
from tests.engine.test_tsdf import _sphere_depth

# One layer shape for every test, so that each weighting compiles integrate and deintegrate once.
CAPACITY = 2**11
VOXEL = 0.05


@pytest.fixture(autouse=True)
def strict_rank_promotion():
  with jax.numpy_rank_promotion("raise"):
    yield


def _scene_depth(T):
  """`(36, 48) float32` depth of a tilted wall 2 m away with a ball in front of it."""
  wall = _plane_depth(T, np.array([0.1, -0.1, 1.0]) / np.linalg.norm([0.1, -0.1, 1.0]), 2.0)
  ball = _sphere_depth(T, np.array([0.1, 0.0, 1.4]), 0.35)
  depth = np.where(ball > 0, np.minimum(ball, np.where(wall > 0, wall, np.inf)), wall)
  depth[3, 5] = np.nan                                   # a hole and a bad value
  depth[20, 11] = 0.0
  return depth.astype(np.float32)


def _frames(seed=0, count=3):
  rng = np.random.default_rng(seed)
  poses = [_pose(*rng.uniform(-0.15, 0.15, 3), yaw=rng.uniform(-0.15, 0.15))
           for _ in range(count)]
  return [(_scene_depth(T), T) for T in poses]


def _layer(frames, **fields):
  state = tsdf.init_tsdf(voxel_size=VOXEL, capacity=CAPACITY, **fields)
  for depth, T in frames:
    state = tsdf.integrate(state, depth, T, CAM)
  return state


def _assert_same_observed(got, want):
  assert set(got) == set(want)
  index = sorted(want)
  np.testing.assert_allclose([got[i][0] for i in index], [want[i][0] for i in index], atol=1e-5)
  np.testing.assert_allclose([got[i][1] for i in index], [want[i][1] for i in index], rtol=1e-5,
                             atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("weighting", ["constant", "inverse_square"])
def test_removing_the_middle_frame_equals_never_integrating_it(weighting):
  a, b, c = _frames()
  state = _layer([a, b, c], weighting=weighting)
  assert tsdf.capped_voxels(state) == 0
  with_b = _observed(state)
  blocks = int(state.num_blocks)
  state = tsdf.deintegrate(state, *b, CAM)
  got, want = _observed(state), _observed(_layer([a, c], weighting=weighting))
  assert len(set(with_b) - set(want)) > 100           # B saw voxels A and C did not
  assert sum(not np.allclose(with_b[i], want[i], atol=1e-4) for i in want) > 1000
  _assert_same_observed(got, want)
  assert int(state.num_blocks) == blocks               # B's blocks stay, unobserved
  assert np.all(np.isfinite(np.asarray(state.sdf)))


@pytest.mark.parametrize("weighting", h.main_tier_keeps(["constant", "inverse_square"],
                                                       ("inverse_square",)))
def test_removing_every_frame_leaves_nothing_observed(weighting):
  frames = _frames(seed=1)
  state = _layer(frames, weighting=weighting)
  assert len(_observed(state)) > 1000
  for depth, T in (frames[1], frames[0], frames[2]):
    state = tsdf.deintegrate(state, depth, T, CAM)
  assert np.count_nonzero(np.asarray(state.weight)) == 0
  assert np.count_nonzero(np.asarray(state.sdf)) == 0


def test_a_frame_whose_blocks_are_not_stored_changes_nothing():
  frames = _frames(seed=2)
  state = _layer(frames)
  before = jax.tree.map(np.array, state)
  far = _pose(50.0, 0.0, -30.0)
  state = tsdf.deintegrate(state, _scene_depth(_pose()), far, CAM)
  for name in ("block_keys", "sdf", "weight", "num_blocks", "num_dropped"):
    np.testing.assert_array_equal(np.asarray(getattr(state, name)), getattr(before, name))


def test_capped_voxels_are_counted_and_only_they_are_not_restored():
  """Weights only grow, so a voxel below the cap after A, B, C never reached it: those voxels
  come back exactly; capped ones (seen by all three at max_weight 2) keep too little weight."""
  a, b, c = _frames(seed=3)
  state = _layer([a, b, c], max_weight=2.0)
  capped = tsdf.capped_voxels(state)
  assert capped > 0
  at_cap = {i for i, (_, w) in _observed(state).items() if w >= 2.0}
  assert len(at_cap) == capped
  got, want = _observed(tsdf.deintegrate(state, *b, CAM)), _observed(_layer([a, c],
                                                                            max_weight=2.0))
  exact = set(want) - at_cap
  _assert_same_observed({i: got[i] for i in set(got) - at_cap}, {i: want[i] for i in exact})
  assert any(got[i][1] < want[i][1] for i in at_cap & set(want))


def test_bad_input_is_refused_like_integrate():
  state = tsdf.init_tsdf(capacity=2**6)
  with pytest.raises(ValueError, match="depth must have 2 dimensions") as info:
    tsdf.deintegrate(state, np.ones((2, 36, 48), np.float32), _pose(), CAM)
  assert "\n" not in str(info.value)
  with pytest.raises(ValueError, match="T_world_cam must have shape"):
    tsdf.deintegrate(state, np.ones((36, 48), np.float32), np.eye(3, dtype=np.float32), CAM)
  with pytest.raises(TypeError, match="depth must be a float array"):
    tsdf.deintegrate(state, np.ones((36, 48), np.int32), _pose(), CAM)
  with pytest.raises(TypeError, match="TSDFState"):
    tsdf.deintegrate({"sdf": 0}, np.ones((36, 48), np.float32), _pose(), CAM)
  batched = jax.tree.map(lambda x: np.stack([x, x]), state)
  with pytest.raises(ValueError, match="one layer"):
    tsdf.capped_voxels(batched)
