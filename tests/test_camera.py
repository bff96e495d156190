"""The fused per-pixel key computation the engine uses equals the obvious composition
back-project → transform → floor, including holes and out-of-range points."""

import numpy as np

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
