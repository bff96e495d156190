"""The true surface of a sequence (jaxfusion.datasets.surfaces): on the primitives, with their
class, thinned to one point per cell, only what the cameras see, in the world frame."""

import types

import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion.datasets import primitives as prim
from jaxfusion.datasets import surfaces

MATTE = prim.Material(np.full(3, 0.5), np.full(3, 0.5), prim.PLAIN, 1.0, 0.0)
FLOOR, BOX_CLASS = 0, 4
CAMERA = jf.Camera(20.0, 20.0, 15.5, 11.5)      # 32 × 24 pixels
SIZE = (24, 32)


def _world():
  """A floor (box 6 × 6 × 0.02 m, top at z = 0) and a 0.6 m cube standing on it."""
  floor = prim.part(prim.BOX, (0, 0, -0.01), (3.0, 3.0, 0.01), MATTE)
  cube = prim.box_on(MATTE, 0.0, 0.0, 0.0, 0.6, 0.6, 0.6)
  table = prim.to_table([(floor, FLOOR, 1), (cube, BOX_CLASS, 2)])
  return types.SimpleNamespace(primitives=table)


def _looking_down(x=0.0, y=0.0, height=2.0):
  T = np.diag([1.0, -1.0, -1.0, 1.0]).astype(np.float32)   # camera z → world −z
  T[:3, 3] = [x, y, height]
  return T


def test_points_lie_on_the_primitives_with_their_class_one_per_cell():
  world = _world()
  s = surfaces.seen_surface(world, _looking_down()[None], CAMERA, SIZE, spacing=0.02)
  d = prim.surface_distance(world.primitives, s["points"])
  assert np.max(d) < 1e-5
  np.testing.assert_array_equal(s["labels"], world.primitives.label[s["primitive"]])
  cells = np.floor(s["points"] / 0.02).astype(np.int64)
  assert len(np.unique(cells, axis=0)) == len(cells)
  # The cube's top (z = 0.6) is seen, the floor under it is not (occluded).
  top = np.abs(s["points"][:, 2] - 0.6) < 1e-4
  assert np.all(s["labels"][top] == BOX_CLASS) and top.sum() > 100
  under = (np.abs(s["points"][:, :2]).max(1) < 0.29) & (np.abs(s["points"][:, 2]) < 1e-4)
  assert not under.any()
  # Even: with cells larger than a pixel's footprint (7 cm on the cube's top), each of the
  # top's 6 × 6 cells of 10 cm holds exactly one point (7 × 7 if the face met a cell edge).
  coarse = surfaces.seen_surface(world, _looking_down()[None], CAMERA, SIZE, spacing=0.1)
  coarse_top = np.abs(coarse["points"][:, 2] - 0.6) < 1e-4
  assert 36 <= coarse_top.sum() <= 49


def test_the_room_placement_moves_poses_and_points_together():
  world = _world()
  T_world_room = np.eye(4)
  T_world_room[:3, :3] = prim.rot_z(0.7)
  T_world_room[:3, 3] = [1.5, -2.0, 0.3]
  plain = surfaces.seen_surface(world, _looking_down()[None], CAMERA, SIZE, spacing=0.05)
  moved_pose = (T_world_room @ _looking_down()).astype(np.float32)
  moved = surfaces.seen_surface(world, moved_pose[None], CAMERA, SIZE, spacing=0.05,
                                T_world_room=T_world_room)
  back = (moved["points"] - T_world_room[:3, 3]) @ T_world_room[:3, :3]
  assert np.max(prim.surface_distance(world.primitives, back)) < 1e-4
  # The same surface (thinned on another grid): every point has a neighbour in the other set
  # within a cell's diagonal.
  from scipy.spatial import cKDTree   # pylint: disable=import-outside-toplevel
  assert np.max(cKDTree(back).query(plain["points"])[0]) < 0.05 * np.sqrt(3)
  assert np.max(cKDTree(plain["points"]).query(back)[0]) < 0.05 * np.sqrt(3)


def test_more_views_see_more_and_upsampling_fills_cells():
  world = _world()
  one = surfaces.seen_surface(world, _looking_down()[None], CAMERA, SIZE, spacing=0.01)
  two = surfaces.seen_surface(world, np.stack([_looking_down(), _looking_down(x=1.5)]),
                              CAMERA, SIZE, spacing=0.01)
  dense = surfaces.seen_surface(world, _looking_down()[None], CAMERA, SIZE, spacing=0.01,
                                upsample=3)
  assert len(two["points"]) > 1.3 * len(one["points"])
  assert len(dense["points"]) > 2 * len(one["points"])   # 1 cm cells: 32 × 24 rays are sparse
  np.testing.assert_allclose(surfaces.upsampled_camera(CAMERA, 2),
                             jf.Camera(40.0, 40.0, 31.5, 23.5))


@pytest.mark.parametrize("kwargs, message", [
    (dict(spacing=0.0), "spacing must be positive"),
    (dict(upsample=0), "upsample must be a positive integer"),
    (dict(T_world_room=np.full((4, 4), np.nan)), "T_world_room must be a finite"),
])
def test_bad_input_gets_one_clear_error(kwargs, message):
  with pytest.raises(ValueError, match=message):
    surfaces.seen_surface(_world(), _looking_down()[None], CAMERA, SIZE, **kwargs)
  with pytest.raises(ValueError, match="T_world_cam must be finite"):
    surfaces.seen_surface(_world(), np.full((1, 4, 4), np.nan), CAMERA, SIZE)
