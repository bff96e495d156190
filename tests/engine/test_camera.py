"""The fused per-pixel key computation the engine uses equals the obvious composition
back-project → transform → floor, including holes and out-of-range points; a Camera refuses
non-positive or non-finite intrinsics but stays a pytree JAX can rebuild freely."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import camera
from tests import engine_helpers as h


def test_depth_to_voxel_keys_equals_the_composition():
  rng = np.random.default_rng(0)
  cam = jf.Camera(7.0, 6.0, 3.5, 2.5)
  for _ in range(5):
    frame = h.random_frame(rng, camera=cam, voxel_size=0.25)
    depth = frame.depth.copy()
    depth[0, 0] = 1e12   # a point far past the key range: invalid, never wrapped
    keys, ok = camera.depth_to_voxel_keys(depth, frame.T_world_cam, cam, 0.25)
    p_world = camera.transform_points(frame.T_world_cam,
                                      camera.backproject(depth, cam).reshape(-1, 3))
    want_keys, want_ok = camera.voxel_keys(p_world, 0.25)
    np.testing.assert_array_equal(np.asarray(ok), np.asarray(want_ok))
    assert not bool(ok[0])
    np.testing.assert_array_equal(np.asarray(keys)[np.asarray(ok)],
                                  np.asarray(want_keys)[np.asarray(want_ok)])
    assert np.asarray(ok).sum() > 0


@pytest.mark.parametrize("fx,fy", [(0.0, 5.0), (5.0, -1.0), (-525.0, 525.0), (0, 1)])
def test_camera_rejects_non_positive_focal_lengths(fx, fy):
  with pytest.raises(ValueError, match="focal length in pixels"):
    jf.Camera(fx, fy, 3.0, 2.0)
  with pytest.raises(ValueError, match="focal length in pixels"):
    jf.Camera.from_matrix([[fx, 0, 3], [0, fy, 2], [0, 0, 1]])
  with pytest.raises(ValueError, match="focal length in pixels"):
    jf.Camera(np.float32(fx), jnp.float32(fy), 3.0, 2.0)


def test_camera_rejects_non_finite_intrinsics_and_batched_bad_values():
  with pytest.raises(ValueError, match="cx must be finite"):
    jf.Camera(5.0, 5.0, np.nan, 2.0)
  with pytest.raises(ValueError, match="fy must be finite"):
    jf.Camera(5.0, np.inf, 3.0, 2.0)
  with pytest.raises(ValueError, match="fx .*positive"):
    jf.Camera(np.array([5.0, -5.0]), np.ones(2), np.zeros(2), np.zeros(2))


def test_camera_stays_a_pytree_that_jax_can_rebuild():
  cam = jf.Camera(7.0, 6.0, 3.5, 2.5)
  # Gradients, tree maps and vmapped outputs may hold zero or negative values: not checked.
  g = jax.grad(lambda c: -c.fx + 0.0 * c.fy)(cam)
  assert isinstance(g, jf.Camera) and float(g.fx) == -1.0 and float(g.fy) == 0.0
  assert jax.tree.map(lambda x: -x, cam).fx == -7.0
  assert jax.jit(lambda c: c.fx * c.fy)(cam) == 42.0
  assert jax.tree_util.keystr(jax.tree_util.tree_flatten_with_path(cam)[0][1][0]) == ".fy"
  # Built under a transformation (tracers): not checked at trace time, still fuses.
  assert float(jax.jit(lambda f: jf.Camera(f, f, 0.0, 0.0).fx)(3.0)) == 3.0
