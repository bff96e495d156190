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
