"""The embedded world: determinism, domains, sequences, save/load, the render command."""

import os

import numpy as np
import pytest

from jaxfusion import datasets
from jaxfusion.lab import data as cli
from jaxfusion.datasets import scene, synthetic
from jaxfusion.datasets.classes import CLASS_COLORS, CLASS_NAMES

SIZE = dict(height=24, width=32)


@pytest.fixture(scope="module")
def office_seq():
  return synthetic.make_sequence("office", 0, num_frames=4, **SIZE)


def test_list_sequences_is_the_papers_two_by_three():
  assert synthetic.list_sequences() == [(e, t) for e in ("office", "house") for t in (0, 1, 2)]


def test_class_table():
  assert CLASS_NAMES == ("background", "bottle", "chair", "table", "plant", "sofa", "tv")
  assert CLASS_COLORS[2].tolist() == [0xFE, 0, 0] and CLASS_COLORS[6].tolist() == [0, 0, 0x9B]


@pytest.mark.parametrize("env", ["office", "house"])
def test_layout_has_every_class_and_is_a_function_of_the_seed(env):
  a, b, c = scene.make_layout(env, 5), scene.make_layout(env, 5), scene.make_layout(env, 6)
  assert {p.label for p in a.placements} == set(range(7))
  pa, pb = scene.build_primitives(a, 1.0), scene.build_primitives(b, 1.0)
  for x, y in zip(pa, pb):
    np.testing.assert_array_equal(x, y)
  assert not np.array_equal(a.room, c.room)


def test_same_seed_same_sequence(office_seq):
  again = synthetic.make_sequence("office", 0, num_frames=4, **SIZE)
  for k, v in office_seq.stacked().items():
    np.testing.assert_array_equal(v, again.stacked()[k])


def test_domains_share_layout_but_not_appearance():
  train = synthetic.make_sequence("house", 1, domain="train", num_frames=2, realism=False, **SIZE)
  test = synthetic.make_sequence("house", 1, domain="test", num_frames=2, realism=False, **SIZE)
  no_shift = synthetic.make_sequence("house", 1, domain="test", shift=0.0, num_frames=2,
                                     realism=False, **SIZE)
  np.testing.assert_array_equal(train.T_world_cam, test.T_world_cam)
  assert np.abs(train.rgb.astype(int) - test.rgb.astype(int)).mean() > 20
  np.testing.assert_array_equal(train.rgb, no_shift.rgb)  # shift 0: test == train
  # Walls and floor do not move between domains: background far away agrees mostly.
  assert (train.labels == test.labels).mean() > 0.8


def test_sequence_interface(office_seq):
  assert len(office_seq) == 4 and office_seq.class_names == CLASS_NAMES
  frame = office_seq[1]
  assert frame.rgb.shape == (24, 32, 3) and frame.rgb.dtype == np.uint8
  assert frame.depth.dtype == np.float32 and frame.labels.dtype == np.int32
  assert frame.T_world_cam.shape == (4, 4) and frame.camera == office_seq.camera
  assert len(list(office_seq)) == 4
  stacked = office_seq.stacked()
  assert stacked["depth"].shape == (4, 24, 32) and stacked["labels"].shape == (4, 24, 32)
  with pytest.raises(IndexError):
    office_seq[4]
  assert len(office_seq.subset(range(0, 4, 2))) == 2


def test_save_load_round_trip(office_seq, tmp_path):
  path = office_seq.save(str(tmp_path / "seq"))
  back = datasets.RGBDSequence.load(path)
  assert back.name == office_seq.name and back.camera == office_seq.camera
  assert back.class_names == office_seq.class_names and back.info == office_seq.info
  for k, v in office_seq.stacked().items():
    np.testing.assert_array_equal(back.stacked()[k], v)
    assert back.stacked()[k].dtype == v.dtype
  os.remove(os.path.join(path, "frames", "000002.npz"))
  with pytest.raises(FileNotFoundError, match="000002.npz"):
    datasets.load_sequence(path)
  with open(os.path.join(path, "frames", "000002.npz"), "wb") as f:
    f.write(b"not a zip")
  with pytest.raises(ValueError, match="000002.npz"):
    datasets.load_sequence(path)


def test_sample_views_shapes_and_classes():
  rgb, labels = synthetic.sample_views("train", 6, height=24, width=32, seed=1,
                                       views_per_scene=6)
  assert rgb.shape == (6, 24, 32, 3) and rgb.dtype == np.uint8
  assert labels.shape == (6, 24, 32) and labels.dtype == np.int32
  assert labels.min() >= 0 and labels.max() < 7 and len(np.unique(labels)) >= 3
  rgb2, labels2 = synthetic.sample_views("train", 6, height=24, width=32, seed=1,
                                         views_per_scene=6)
  np.testing.assert_array_equal(rgb, rgb2)
  np.testing.assert_array_equal(labels, labels2)


def test_bad_arguments():
  with pytest.raises(ValueError, match="environment"):
    synthetic.make_sequence("garage", 0, num_frames=1, **SIZE)
  with pytest.raises(ValueError, match="trajectory"):
    synthetic.make_sequence("office", 3, num_frames=1, **SIZE)
  with pytest.raises(ValueError, match="domain"):
    synthetic.make_sequence("office", 0, domain="val", num_frames=1, **SIZE)
  with pytest.raises(ValueError, match="shift"):
    synthetic.sample_views("test", 1, shift=1.5, **SIZE)


def test_render_command_writes_a_three_panel_png(tmp_path, capsys):
  out = str(tmp_path / "frame.png")
  assert cli.run(["render", "--env", "office", "--trajectory", "0", "--frame", "1",
                   "--num-frames", "4", "--height", "24", "--width", "32", "--out", out]) == 0
  import cv2  # pylint: disable=g-import-not-at-top
  img = cv2.imread(out)
  assert img.shape == (24, 96, 3)
  assert cli.run(["list"]) == 0
  assert "house\t2" in capsys.readouterr().out


def test_public_functions_take_optional_arguments_by_keyword_only():
  import inspect  # pylint: disable=g-import-not-at-top
  for name in datasets.__all__:
    obj = getattr(datasets, name)
    if inspect.isfunction(obj):
      for p in inspect.signature(obj).parameters.values():
        if p.default is not inspect.Parameter.empty:
          assert p.kind == p.KEYWORD_ONLY, f"{name}({p.name}=...) should be keyword-only"


def _world_points(seq) -> np.ndarray:
  """`(N, 3)` world points of every valid pixel (NumPy back-projection, float64)."""
  cam = seq.camera
  v, u = np.mgrid[0:seq.depth.shape[1], 0:seq.depth.shape[2]]
  points = []
  for depth, T in zip(seq.depth.astype(np.float64), seq.T_world_cam.astype(np.float64)):
    m = depth > 0
    ray = np.stack([(u[m] - cam.cx) / cam.fx, (v[m] - cam.cy) / cam.fy, np.ones(m.sum())], -1)
    points.append((ray * depth[m, None]) @ T[:3, :3].T + T[:3, 3])
  return np.concatenate(points)


def _near_face_share(points, voxel=0.1, within=0.005) -> np.ndarray:
  """`(3,)` share of points within `within` m of a face of the `voxel` grid, per axis."""
  r = points / voxel
  return (np.abs(r - np.round(r)) * voxel < within).mean(0)


@pytest.mark.parametrize("env,seed", [("office", 0), ("house", 3)])
def test_surfaces_lie_on_no_voxel_grid(env, seed):
  # Without depth noise the room's own frame puts large surfaces on the 0.1 m grid (the issue
  # measured 57 % of points within 5 mm of a z face, where an unaligned surface gives 10 %);
  # the reported world frame must not, along any axis, nor on a 0.05 m grid.
  seq = synthetic.make_sequence(env, 0, num_frames=6, realism=False, seed=seed, **SIZE)
  world = _world_points(seq)
  T_world_room = synthetic.placement(env, seed)
  np.testing.assert_allclose(np.asarray(seq.info["T_world_room"]), T_world_room)
  room = (world - T_world_room[:3, 3]) @ T_world_room[:3, :3]   # the same points, room frame
  assert _near_face_share(room).max() > 0.2                  # the room frame is aligned...
  for voxel, within in ((0.1, 0.005), (0.05, 0.0025)):       # ...the world frame is not
    share = _near_face_share(world, voxel, within)
    np.testing.assert_allclose(share, 0.1, atol=0.03, err_msg=f"voxel {voxel}")


def test_placement_is_a_rigid_transform_drawn_from_the_layout_seed():
  a, b = synthetic.placement("office", 4), synthetic.placement("office", 4)
  np.testing.assert_array_equal(a, b)
  assert not np.allclose(a, synthetic.placement("office", 5))
  assert not np.allclose(a, synthetic.placement("house", 4))
  for T in (a, synthetic.placement("house", 0)):
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) > 0 and np.all((0 <= T[:3, 3]) & (T[:3, 3] < 0.1))
    tilt = np.degrees(np.arccos(T[2, 2]))                  # the vertical leans 1.4–4.2°
    assert 1.0 < tilt < 4.5
  with pytest.raises(ValueError, match="env"):
    synthetic.placement("garden", 0)
