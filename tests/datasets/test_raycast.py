"""Ray caster against hand-computed depths, and rendered depth against the primitives."""

import jax
import numpy as np
import pytest

from jaxfusion.camera import Camera
from jaxfusion.datasets import primitives as P
from jaxfusion.datasets import raycast, synthetic, trajectories

H, W = 25, 33
CAM = Camera(20.0, 20.0, 16.0, 12.0)  # pixel (16, 12) is on the optical axis
MAT = P.Material(np.full(3, 0.5), np.full(3, 0.2), P.PLAIN, 1.0, 0.0)


def _cast(parts, T):
  prims = P.to_table([(p, label, i + 1) for i, (p, label) in enumerate(parts)])
  return raycast.cast(raycast.pack(prims), T, CAM, height=H, width=W), prims


def _wall_x(x):
  """An infinite plane x = `x` (local z mapped onto world x)."""
  return P.part(P.PLANE, (x, 0.0, 0.0), (1, 1, 1), MAT, rotation=P.rot_y(np.pi / 2))


LOOK_X = trajectories.look_at((0.0, 0.0, 1.0), (1.0, 0.0, 1.0))  # eye at z=1 looking along +x


def test_look_at_is_opencv_camera_to_world():
  R = LOOK_X[:3, :3]
  np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-6)
  np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-6)  # z forward
  np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-6)  # y down


def test_plane_at_known_distance_gives_constant_z_depth():
  hits, _ = _cast([(_wall_x(3.0), 2)], LOOK_X)
  np.testing.assert_allclose(np.asarray(hits.depth), 3.0, rtol=1e-5)
  assert np.all(np.asarray(hits.label) == 2)
  np.testing.assert_allclose(np.asarray(hits.normal)[..., 0], -1.0, atol=1e-5)


def test_box_seen_head_on():
  box = P.part(P.BOX, (5.0, 0.0, 1.0), (0.5, 1.0, 0.5), MAT)  # front face at x = 4.5
  hits, _ = _cast([(box, 3), (_wall_x(10.0), 0)], LOOK_X)
  depth, label = np.asarray(hits.depth), np.asarray(hits.label)
  assert depth[12, 16] == pytest.approx(4.5, rel=1e-5)
  # The face spans |x_cam| ≤ 1, |y_cam| ≤ 0.5 at z = 4.5: |u − cx| ≤ 4.44, |v − cy| ≤ 2.22.
  u, v = np.meshgrid(np.arange(W) - CAM.cx, np.arange(H) - CAM.cy)
  inside = (np.abs(u) < 4.4) & (np.abs(v) < 2.2)
  outside = (np.abs(u) > 4.5) | (np.abs(v) > 2.3)
  np.testing.assert_allclose(depth[inside], 4.5, rtol=1e-5)
  np.testing.assert_allclose(depth[outside], 10.0, rtol=1e-5)
  assert np.all(label[inside] == 3) and np.all(label[outside] == 0)


def test_sphere_and_cylinder_on_the_axis():
  sphere = P.part(P.SPHERE, (4.0, 0.0, 1.0), (0.5, 0.5, 0.5), MAT)
  hits, _ = _cast([(sphere, 1), (_wall_x(10.0), 0)], LOOK_X)
  assert float(hits.depth[12, 16]) == pytest.approx(3.5, rel=1e-5)
  cyl = P.cylinder_on(MAT, 4.0, 0.0, 0.0, 0.5, 2.0)
  hits, _ = _cast([(cyl, 1), (_wall_x(10.0), 0)], LOOK_X)
  assert float(hits.depth[12, 16]) == pytest.approx(3.5, rel=1e-5)
  # Looking straight down onto the cap (top at z = 2) from z = 5.
  down = trajectories.look_at((4.0, 0.0, 5.0), (4.0, 0.0, 0.0))
  hits, _ = _cast([(cyl, 1)], down)
  assert float(hits.depth[12, 16]) == pytest.approx(3.0, rel=1e-5)
  np.testing.assert_allclose(np.asarray(hits.normal)[12, 16], [0, 0, 1], atol=1e-5)


@pytest.mark.slow
def test_rendered_depth_backprojects_onto_the_surfaces():
  world = synthetic.make_scene("office", seed=3)
  cam = synthetic.default_camera(H, W)
  for T in trajectories.trajectory(world.layout.room, 0, 3):
    frame = synthetic.render(world, T, cam, height=H, width=W)
    ok = frame.depth > 0
    assert ok.mean() > 0.99  # closed room: every ray hits something
    v, u = np.nonzero(ok)
    d = frame.depth[ok].astype(np.float64)
    p_cam = np.stack([d * (u - cam.cx) / cam.fx, d * (v - cam.cy) / cam.fy, d], -1)
    p_world = p_cam @ T[:3, :3].T.astype(np.float64) + T[:3, 3]
    assert np.max(P.surface_distance(world.primitives, p_world)) < 2e-3
    noisy = synthetic.render(world, T, cam, height=H, width=W, realism=True,
                             key=jax.random.PRNGKey(1))
    both = ok & (noisy.depth > 0)
    err = np.abs(noisy.depth[both] - frame.depth[both])
    sigma = 0.0012 + 0.0019 * (frame.depth[both] - 0.4) ** 2
    assert np.all(err <= 6 * sigma + 1e-3)


@pytest.mark.parametrize("env,trajectory", [("house", 2),
                                             pytest.param("office", 0, marks=pytest.mark.slow)])
def test_tiled_cast_equals_casting_against_everything(env, trajectory):
  world = synthetic.make_scene(env, seed=1)
  cam = synthetic.default_camera(H, W)
  packed = raycast.pack(world.primitives)
  poses = trajectories.trajectory(world.layout.room, trajectory, 3)
  # The longest lists over the poses, as a sequence renderer passes them: one compilation.
  sizes = np.max([raycast.list_sizes(raycast.tile_lists(packed, T, cam, height=H, width=W,
                                                         tile=8)) for T in poses], axis=0)
  for T in poses:
    tiles = raycast.tile_lists(packed, T, cam, height=H, width=W, tile=8,
                               min_sizes=tuple(int(x) for x in sizes))
    assert raycast.list_sizes(tiles) == tuple(int(x) for x in sizes)
    assert raycast.list_sizes(tiles)[0] < packed.boxes.index.shape[0]  # tiles do cull
    a = raycast.cast(packed, T, cam, height=H, width=W)
    b = raycast.cast(packed, T, cam, height=H, width=W, tiles=tiles, tile=8)
    np.testing.assert_array_equal(np.asarray(a.prim), np.asarray(b.prim))
    np.testing.assert_allclose(np.asarray(a.depth), np.asarray(b.depth), rtol=1e-5)
