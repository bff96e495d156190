"""The geometry layer (jaxfusion.tsdf): against the NumPy reference, the analytic signed distance
of a plane and a sphere, growth, gradients, batching, and bad input."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import tsdf
from tests.tsdf_reference import ReferenceTSDF


@pytest.fixture(autouse=True)
def strict_rank_promotion():
  """The engine broadcasts explicitly: users may run with jax_numpy_rank_promotion='raise'."""
  with jax.numpy_rank_promotion("raise"):
    yield


CAM = jf.Camera(fx=40.0, fy=40.0, cx=23.5, cy=17.5)     # 48 × 36 pixels


def _pose(tx=0.013, ty=-0.021, tz=0.007, yaw=0.0):
  T = np.eye(4, dtype=np.float32)
  c, s = math.cos(yaw), math.sin(yaw)
  T[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float32)
  T[:3, 3] = [tx, ty, tz]
  return T


def _observed(state):
  """`{voxel index: (sdf, weight)}` of every voxel with weight > 0."""
  keys = np.asarray(state.block_keys)
  sdf, weight = np.asarray(state.sdf), np.asarray(state.weight)
  offsets = tsdf.voxel_offsets(state.block_size)
  out = {}
  for slot in np.nonzero(keys[:, 0] != jf.EMPTY)[0]:
    base = keys[slot] * state.block_size
    for v in np.nonzero(weight[slot] > 0)[0]:
      out[tuple(int(c) for c in base + offsets[v])] = (sdf[slot, v], weight[slot, v])
  return out


def _centres(indices, voxel_size):
  return (np.asarray(indices, np.float64) + 0.5) * voxel_size


def _plane_depth(T, n_world, offset, height=36, width=48, cam=CAM):
  """Depth image of the plane {p: n·p = offset} seen from pose T (z-depth, 0 where missed)."""
  u, v = np.meshgrid(np.arange(width), np.arange(height))
  ray_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
  ray = ray_cam @ T[:3, :3].T.astype(np.float64)
  denom = ray @ n_world
  z = (offset - n_world @ T[:3, 3]) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
  return np.where(np.isfinite(z) & (z > 0), z, 0.0).astype(np.float32)


def _sphere_depth(T, centre, radius, height=36, width=48, cam=CAM):
  u, v = np.meshgrid(np.arange(width), np.arange(height))
  ray_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
  ray = ray_cam @ T[:3, :3].T.astype(np.float64)
  oc = T[:3, 3] - centre
  a = np.sum(ray * ray, -1)
  b = 2 * ray @ oc
  c = oc @ oc - radius**2
  disc = b * b - 4 * a * c
  z = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
  return np.where(disc > 0, z, 0.0).astype(np.float32)


@pytest.mark.parametrize("weighting, stride", [("constant", 1), ("inverse_square", 4)])
def test_matches_numpy_reference_over_frames(weighting, stride):
  cfg = dict(voxel_size=0.1, truncation_voxels=3.0, weighting=weighting, max_weight=2.5,
             block_stride=stride)
  state = tsdf.init_tsdf(capacity=2**9, **cfg)
  ref = ReferenceTSDF(**cfg)
  n = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
  for t, T in enumerate([_pose(), _pose(0.11, 0.05, -0.2, 0.2), _pose(-0.1, 0.0, 0.1, -0.15)]):
    depth = _plane_depth(T, n, 1.6)
    depth[5, 7] = np.nan                                  # a hole and a bad value
    depth[9, 30] = 0.0
    state = tsdf.integrate(state, depth, T, CAM)
    ref.integrate(depth, T, CAM)
  got = _observed(state)
  assert set(got) == set(ref.voxels)
  assert len(got) > 500
  for index, (s, w) in ref.voxels.items():
    np.testing.assert_allclose(got[index], (s, w), rtol=1e-4, atol=2e-6)
  assert max(w for _, w in got.values()) <= 2.5
  assert int(state.num_blocks) == len(ref.blocks)


def test_frontal_plane_is_the_analytic_ray_distance():
  """A plane 2 m in front: each voxel holds (2 − z)·‖p‖/z clipped to ±τ (the distance along its
  ray), which is the plane's signed distance 2 − z scaled by the ray's obliquity (≤ 1.1 here)."""
  T = _pose()
  state = tsdf.integrate(tsdf.init_tsdf(voxel_size=0.05, capacity=2**10),
                         np.full((36, 48), 2.0, np.float32), T, CAM)
  got = _observed(state)
  p = _centres(list(got), 0.05) - T[:3, 3]
  sdf = np.array([s for s, _ in got.values()])
  z = p[:, 2]
  ray = np.linalg.norm(p, axis=1) / z
  np.testing.assert_allclose(sdf, np.minimum((2.0 - z) * ray, 0.2), atol=2e-6)
  signed = 2.0 - z
  assert np.all(np.sign(sdf[np.abs(signed) > 1e-6]) == np.sign(signed[np.abs(signed) > 1e-6]))
  assert np.all(np.abs(sdf - np.clip(signed, -0.2, 0.2)) <= (ray - 1) * np.abs(signed) + 1e-5)
  assert sdf.min() >= -0.2 - 1e-6 and sdf.max() <= 0.2 + 1e-6


def test_sphere_zero_crossing_is_the_analytic_surface():
  """Voxels near a sphere: the TSDF's sign is the analytic one, and its value is the Euclidean
  signed distance to within the ray's obliquity to the surface and a pixel's footprint."""
  centre, radius = np.array([0.03, -0.02, 1.5]), 0.4
  state = tsdf.init_tsdf(voxel_size=0.02, capacity=2**11)
  cam = jf.Camera(80.0, 80.0, 47.5, 35.5)
  for T in [_pose(0, 0, 0), _pose(0.05, 0.02, 0.0, 0.05)]:
    state = tsdf.integrate(state, _sphere_depth(T, centre, radius, 72, 96, cam), T, cam)
  got = _observed(state)
  p = _centres(list(got), 0.02)
  sdf = np.array([s for s, _ in got.values()])
  euclid = np.linalg.norm(p - centre, axis=1) - radius
  # Facing the first camera (at the origin) within 60°: off the rim, where a pixel's footprint
  # (1.6 cm at 1.3 m) spans a large change of depth.
  facing = np.sum((p - centre) * -p, axis=1) > 0.5 * np.linalg.norm(p - centre, axis=1) * (
      np.linalg.norm(p, axis=1))
  near = facing & (np.abs(euclid) < 0.02)
  assert near.sum() > 500
  clear = near & (np.abs(euclid) > 0.005)
  assert np.all(np.sign(sdf[clear]) == np.sign(euclid[clear]))
  assert np.median(np.abs(sdf[near] - euclid[near])) < 0.003
  deep = euclid < -0.081                     # well behind the visible surface: never updated
  assert not np.any(deep & (sdf > 0.0))


def test_growth_keeps_the_tsdf_exactly_and_integrates_alike():
  T = _pose()
  depth = _sphere_depth(T, np.array([0.0, 0.0, 1.2]), 0.5)
  small = tsdf.integrate(tsdf.init_tsdf(voxel_size=0.05, capacity=2**8), depth, T, CAM)
  big = tsdf.init_tsdf(voxel_size=0.05, capacity=2**11)
  big = tsdf.integrate(big, depth, T, CAM)
  grown = tsdf.grow_tsdf(small, 2**11)
  assert _observed(grown) == _observed(small)
  assert int(grown.num_blocks) == int(small.num_blocks)
  T2 = _pose(0.1, 0.0, 0.05, 0.1)
  depth2 = _sphere_depth(T2, np.array([0.0, 0.0, 1.2]), 0.5)
  a = _observed(tsdf.integrate(grown, depth2, T2, CAM))
  b = _observed(tsdf.integrate(big, depth2, T2, CAM))
  assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
  with pytest.raises(ValueError, match="cannot shrink"):
    tsdf.grow_tsdf(grown, 2**8)


def test_full_table_drops_and_counts_blocks():
  T = _pose()
  state = tsdf.integrate(tsdf.init_tsdf(voxel_size=0.02, capacity=4),
                         np.full((36, 48), 1.5, np.float32), T, CAM)
  assert int(state.num_blocks) == 4 and int(state.num_dropped) > 0
  with pytest.warns(tsdf.MapFullWarning, match="dropped"):
    tsdf.tsdf_stats(state)


def test_gradient_matches_finite_differences_inside_the_band():
  """d Σ sdf / d(depth offset, pose translation) against central differences, over voxels that
  stay inside the band (no clip, no voxel entering or leaving)."""
  base = np.full((36, 48), 1.3, np.float32)

  def field(delta, shift):
    T = jnp.asarray(_pose()).at[2, 3].add(shift)
    state = tsdf.integrate(tsdf.init_tsdf(voxel_size=0.05, capacity=2**10), base + delta, T, CAM)
    return state.sdf, state.weight

  sdf0, w0 = field(0.0, 0.0)
  inner = (w0 > 0) & (jnp.abs(sdf0) < 0.1)
  loss = lambda d, s: jnp.sum(jnp.where(inner, field(d, s)[0], 0.0))
  g_depth, g_shift = jax.grad(loss, argnums=(0, 1))(0.0, 0.0)
  h = 2e-3
  fd_depth = (loss(h, 0.0) - loss(-h, 0.0)) / (2 * h)
  fd_shift = (loss(0.0, h) - loss(0.0, -h)) / (2 * h)
  assert float(g_depth) > 0 and float(g_shift) > 0   # moving the camera back or the wall away
  np.testing.assert_allclose(float(g_depth), float(fd_depth), rtol=2e-2)
  np.testing.assert_allclose(float(g_shift), float(fd_shift), rtol=2e-2)


def test_vmap_over_sequences_equals_each_alone():
  poses = np.stack([_pose(), _pose(0.2, 0.0, 0.0, 0.1)])
  depths = np.stack([np.full((36, 48), 1.4, np.float32),
                     _sphere_depth(poses[1], np.array([0.2, 0.0, 1.3]), 0.4)])
  fresh = tsdf.init_tsdf(voxel_size=0.05, capacity=2**10)
  batched = jax.jit(jax.vmap(tsdf.integrate_unchecked, in_axes=(None, 0, 0, None)))(
      fresh, depths, poses, CAM)
  for b in range(2):
    alone = tsdf.integrate(tsdf.init_tsdf(voxel_size=0.05, capacity=2**10), depths[b], poses[b],
                           CAM)
    one = jax.tree.map(lambda x: x[b], batched)
    assert _observed(one) == _observed(alone)


def test_query_sdf_reads_the_voxel_of_each_point():
  T = _pose()
  state = tsdf.integrate(tsdf.init_tsdf(voxel_size=0.05, capacity=2**10),
                         np.full((36, 48), 2.0, np.float32), T, CAM)
  got = _observed(state)
  index = next(iter(got))
  q = tsdf.query_sdf(state, _centres([index, (10**6, 0, 0)], 0.05).astype(np.float32))
  assert bool(q.observed[0]) and not bool(q.observed[1])
  assert float(q.sdf[0]) == got[index][0]


@pytest.mark.parametrize("fields, message", [
    (dict(truncation_voxels=0.0), "truncation_voxels must be a positive number"),
    (dict(truncation_voxels=-2.0), "truncation_voxels must be a positive number"),
    (dict(truncation_voxels=0.5), "at least 1"),
    (dict(voxel_size=0.0), "voxel_size must be a positive finite"),
    (dict(voxel_size=float("inf")), "voxel_size must be a positive finite"),
    (dict(voxel_size=20.0), "does not fit"),
    (dict(capacity=1000), "power of two"),
    (dict(weighting="linear"), "weighting must be one of"),
])
def test_bad_configuration_gets_one_clear_line(fields, message):
  with pytest.raises(ValueError, match=message) as info:
    tsdf.TSDFConfig(**fields)
  assert "\n" not in str(info.value)


def test_bad_frame_input_is_refused():
  state = tsdf.init_tsdf(capacity=2**6)
  with pytest.raises(ValueError, match="depth must have 2 dimensions"):
    tsdf.integrate(state, np.ones((2, 36, 48), np.float32), _pose(), CAM)
  with pytest.raises(TypeError, match="depth must be a float array"):
    tsdf.integrate(state, np.ones((36, 48), np.int32), _pose(), CAM)
  bad = _pose()
  bad[0, 3] = np.nan
  with pytest.raises(ValueError, match="T_world_cam"):
    tsdf.integrate(state, np.ones((36, 48), np.float32), bad, CAM)


def test_a_coarser_block_lattice_finds_a_subset_of_the_blocks():
  """Every `block_stride`-th pixel and row (§8.2) is a subset of all pixels: the blocks found
  are a subset of stride 1's, and every voxel they hold has the same value as with stride 1."""
  T = _pose(yaw=0.3)
  depth = _sphere_depth(T, np.array([0.2, 0.1, 1.4]), 0.5)
  layers = {}
  for stride in (1, 3):
    state = tsdf.init_tsdf(voxel_size=0.04, capacity=2**10, block_stride=stride)
    layers[stride] = _observed(tsdf.integrate(state, depth, T, CAM))
  assert set(layers[3]) <= set(layers[1]) and len(layers[3]) > 0.5 * len(layers[1])
  for index, value in layers[3].items():
    np.testing.assert_array_equal(value, layers[1][index])
