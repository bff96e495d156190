"""The embedded floor (`floor:N`): its spec, its plan, its walk and its frames."""

import numpy as np
import pytest

from jaxfusion.datasets import floor as floor_lib
from jaxfusion.datasets import primitives
from jaxfusion.datasets import specs
from jaxfusion.datasets.classes import CLASS_NAMES
from jaxfusion.datasets.stream import open_stream

SIZE = dict(height=24, width=32)


@pytest.mark.parametrize("text", ["floor:12", "floor:12:s3", "floor:4:train:s1:shift0.5",
                                  "floor:1:shift0"])
def test_spec_parses_and_prints_back(text):
  spec = specs.parse_spec(text)
  assert spec.kind == "floor" and not spec.is_embedded and spec.is_rendered
  assert str(spec) == text
  assert spec.rooms == int(text.split(":")[1])


def test_spec_fields_and_resolution():
  spec = specs.parse_spec("floor:4:train:s1:shift0.5")
  assert (spec.rooms, spec.domain, spec.layout_seed, spec.shift) == (4, "train", 1, 0.5)
  bare = specs.parse_spec("floor:7").resolved(layout_seed=5, shift=0.25)
  assert (bare.layout_seed, bare.shift, bare.domain) == (5, 0.25, "test")


@pytest.mark.parametrize("text", ["floor:", "floor:0", "floor:101", "floor:x", "floor:3:moved",
                                  "floor:3:shift2", "floor:3:s1:s2", "floor:3:train:test",
                                  "floor:-2"])
def test_bad_floor_specs_give_one_line(text):
  with pytest.raises(ValueError) as e:
    specs.parse_spec(text)
  message = str(e.value)
  assert "\n" not in message and "floor:N" in message and repr(text) in message


def test_the_general_error_names_the_floor_syntax():
  with pytest.raises(ValueError, match="floor:N"):
    specs.parse_spec("kitchen:0")


@pytest.mark.parametrize("num_rooms", [1, 5, 10, 17])
def test_a_floor_has_its_rooms_and_they_are_connected(num_rooms):
  floor = floor_lib.make_floor(num_rooms, seed=0)
  assert sum(c.kind == "room" for c in floor.cells) == num_rooms == len(floor.room_layouts)
  assert floor_lib.connected(floor)
  for a, b in ((c.lo, c.hi) for c in floor.cells):          # interiors do not overlap
    assert np.all(b > a)
  room_ids = {i for o in floor.openings for i in o.cells if i < num_rooms}
  assert room_ids == set(range(num_rooms))                    # every room has a doorway
  labels = set(np.unique(floor.world.primitives.label))
  assert labels <= set(range(len(CLASS_NAMES))) and len(labels) >= 4


def test_connected_fails_without_a_doorway():
  floor = floor_lib.make_floor(5, seed=0)
  cut = floor._replace(openings=floor.openings[1:])
  assert not floor_lib.connected(cut)


@pytest.mark.parametrize("num_rooms,seed", [(3, 1), (10, 0)])
def test_the_walk_stays_in_free_space_and_visits_every_cell(num_rooms, seed):
  floor = floor_lib.make_floor(num_rooms, seed=seed)
  poses = floor_lib.walk_poses(floor)
  assert poses.shape[1:] == (4, 4) and len(poses) > 200 * num_rooms
  eye = poses[:, :3, 3]
  assert np.all(floor_lib.in_free_space(floor, eye[:, :2], margin=0.2))
  assert np.all((eye[:, 2] > 1.4) & (eye[:, 2] < floor_lib.HEIGHT - 0.5))
  cells = floor_lib.cell_of(floor, eye[:, :2])
  assert set(cells[cells >= 0]) == set(range(len(floor.cells)))
  # Nothing of the scene is within 10 cm of the camera (furniture included).
  assert primitives.surface_distance(floor.world.primitives, eye[::7]).min() > 0.1
  # Smooth: steps of about STEP, and small turns between frames.
  steps = np.linalg.norm(np.diff(eye, axis=0), axis=1)
  assert steps.max() < 2.5 * floor_lib.STEP
  cos = np.einsum("ti,ti->t", poses[1:, :3, 2], poses[:-1, :3, 2])
  assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 20.0


def test_free_space_refuses_points_in_walls():
  floor = floor_lib.make_floor(3, seed=0)
  room = floor.cells[0]
  wall_x = room.hi[0] + floor_lib.WALL / 4                   # inside the room's east half-wall
  inside = np.array([[wall_x, room.centre[1]], [room.lo[0] - 0.03, room.centre[1]]])
  assert not np.any(floor_lib.in_free_space(floor, inside))
  assert floor_lib.in_free_space(floor, room.centre[None]).all()


def test_frames_render_through_load_spec():
  seq = specs.load_spec("floor:3:s1", num_frames=3, stride=150, **SIZE)
  assert len(seq) == 3 and seq.image_size == (24, 32)
  assert seq.class_names == CLASS_NAMES and seq.name == "floor_3_test"
  depth = seq.depth
  assert np.all(np.isfinite(depth)) and np.all(depth >= 0)
  valid = depth > 0
  assert valid.mean() > 0.5
  assert np.all(depth[valid] <= floor_lib.MAX_RANGE)
  assert set(np.unique(seq.labels)) <= set(range(len(CLASS_NAMES)))
  walk = floor_lib.FloorWalk(floor_lib.make_floor(3, seed=1), num_frames=3, stride=150, **SIZE)
  np.testing.assert_allclose(seq.T_world_cam, walk.T_world_cam, atol=1e-6)
  # The reported poses are the floor's moved by its placement: not axis-aligned.
  assert abs(seq.T_world_cam[0, 2, 0]) > 1e-3 or abs(seq.T_world_cam[0, 2, 1]) > 1e-3


def test_a_stream_renders_the_same_frames_chunk_by_chunk():
  whole = specs.load_spec("floor:2", num_frames=3, stride=90, realism=False, **SIZE)
  stream = open_stream("floor:2", num_frames=3, stride=90, realism=False, **SIZE)
  chunks = list(stream.chunks(2))
  assert [len(c) for c in chunks] == [2, 1]
  np.testing.assert_array_equal(np.concatenate([c.depth for c in chunks]), whole.depth)
  np.testing.assert_array_equal(np.concatenate([c.labels for c in chunks]), whole.labels)


def test_one_seed_is_deterministic_and_seeds_differ():
  a, b, c = (floor_lib.make_floor(3, seed=s) for s in (4, 4, 5))
  for x, y in zip(a.world.primitives, b.world.primitives):
    np.testing.assert_array_equal(x, y)
  np.testing.assert_array_equal(floor_lib.walk_poses(a), floor_lib.walk_poses(b))
  assert (len(a.world.primitives) != len(c.world.primitives)
          or not np.array_equal(a.world.primitives.center, c.world.primitives.center))
  pa, pc = floor_lib.walk_poses(a), floor_lib.walk_poses(c)
  assert len(pa) != len(pc) or not np.allclose(pa, pc)
  fa = floor_lib.FloorWalk(a, num_frames=1, realism=False, **SIZE).frame(0)
  fb = floor_lib.FloorWalk(b, num_frames=1, realism=False, **SIZE).frame(0)
  np.testing.assert_array_equal(fa.depth, fb.depth)
  np.testing.assert_array_equal(fa.rgb, fb.rgb)


def test_make_floor_refuses_bad_sizes():
  for bad in (0, 101, 2.5, True):
    with pytest.raises(ValueError, match="rooms"):
      floor_lib.make_floor(bad)
