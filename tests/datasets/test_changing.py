"""Changing embedded worlds: objects moved between two passes, and drifting odometry poses."""

import dataclasses
import json

import numpy as np
import pytest

from jaxfusion import datasets
from jaxfusion.datasets import changes, scene, synthetic

SIZE = dict(height=48, width=64)
FRAMES = 10  # two passes of 5 frames, each along the whole trajectory (the same poses)
HALF = FRAMES // 2


@pytest.fixture(scope="module")
def moved():
  return changes.make_changing_sequence("office", 0, change="moved", num_frames=FRAMES,
                                        realism=False, **SIZE)


@pytest.fixture(scope="module")
def final():
  return changes.make_changing_sequence("office", 0, change="final", num_frames=FRAMES,
                                        realism=False, **SIZE)


def _by_id(layout):
  return {pl.instance: pl for pl in layout.placements}


@pytest.mark.parametrize("env,seed", [("office", 0), ("house", 3)])
def test_changed_layout_differs_in_exactly_the_recorded_objects(env, seed):
  layout = scene.make_layout(env, seed)
  changed, record = changes.changed_layout(layout)
  assert json.loads(json.dumps(record)) == record
  assert len(record["moved"]) == 2 and len(record["removed"]) == 1 and len(record["added"]) == 1
  old, new = _by_id(layout), _by_id(changed)
  assert set(new) == set(old) - set(record["removed"]) | set(record["added"])
  for i in set(old) & set(new):
    a, b = old[i], new[i]
    assert (a.kind, a.label) == (b.kind, b.label)
    np.testing.assert_array_equal(a.size, b.size)
    np.testing.assert_array_equal(a.u, b.u)
    if i in record["moved"]:
      assert not np.allclose(a.position, b.position)
      np.testing.assert_allclose(b.position, record["new_positions"][str(i)], atol=1e-6)
      np.testing.assert_allclose(a.position, record["old_positions"][str(i)], atol=1e-6)
    else:
      np.testing.assert_array_equal(a.position, b.position)
      assert a.yaw == b.yaw
  assert record["kinds"][str(record["added"][0])] in ("chair", "box")
  np.testing.assert_array_equal(changed.room, layout.room)
  np.testing.assert_array_equal(changed.light_u, layout.light_u)
  # A function of (env, seed); another seed changes other objects or other spots.
  assert changes.changed_layout(layout)[1] == record
  assert changes.changed_layout(layout, seed=seed + 1)[1] != record


@pytest.mark.parametrize("env", ["office", "house"])
def test_moved_objects_go_far_and_overlap_nothing(env):
  for seed in range(6):
    layout = scene.make_layout(env, seed)
    changed, record = changes.changed_layout(layout)
    circles = changes.footprints(changed)
    lx, ly = changed.room[:2]
    for i in record["moved"] + record["added"]:
      x, y, r = circles[i]
      assert changes.INTERIOR_MARGIN + r <= x <= lx - changes.INTERIOR_MARGIN - r
      assert changes.INTERIOR_MARGIN + r <= y <= ly - changes.INTERIOR_MARGIN - r
      for j, (cx, cy, cr) in circles.items():
        assert j == i or np.hypot(x - cx, y - cy) >= r + cr, (env, seed, i, j)
    for i in record["moved"]:
      step = np.subtract(record["new_positions"][str(i)], record["old_positions"][str(i)])
      assert np.hypot(*step[:2]) >= changes.MIN_MOVE
    # Nothing stood on a moved or removed object.
    old = _by_id(layout)
    for i in record["moved"] + record["removed"]:
      base = old[i]
      top = base.position[2] + base.size[2]
      for pl in layout.placements:
        on_it = (pl.position[2] > 0 and abs(pl.position[2] - top) < 1e-6 and
                 np.hypot(*(pl.position[:2] - base.position[:2])) < 0.5 * np.hypot(*base.size[:2]))
        assert not on_it, (env, seed, i, pl.instance)


def test_spec_names_a_change_and_round_trips(moved):
  spec = datasets.parse_spec("office:0:moved")
  assert spec.change == "moved" and str(spec) == "office:0:moved"
  spec = datasets.parse_spec("office:0:s2:moved:shift0.5")
  assert (spec.layout_seed, spec.shift, spec.change) == (2, 0.5, "moved")
  assert datasets.parse_spec(str(spec)) == spec
  assert datasets.parse_spec("house:1:drift:train").change == "drift"
  assert datasets.parse_spec("office:0").change is None
  assert datasets.SequenceSpec("synthetic", "office", 0, "test").change is None
  loaded = datasets.load_spec("office:0:moved", num_frames=FRAMES, realism=False, **SIZE)
  assert loaded.name == "office_0_test_moved" and loaded.info == moved.info
  np.testing.assert_array_equal(loaded.rgb, moved.rgb)


@pytest.mark.parametrize("text,match", [
    ("office:0:moved:drift", "one change at most"), ("office:0:final:final", "one change"),
    ("office:0:dev", r"\[:CHANGE\]"),
])
def test_bad_specs_are_refused(text, match):
  with pytest.raises(ValueError, match=match):
    datasets.parse_spec(text)


def test_bad_arguments_are_refused():
  with pytest.raises(ValueError, match="change must be one of moved|final|drift"):
    changes.make_changing_sequence("office", 0, change="swapped", num_frames=2, **SIZE)
  with pytest.raises(ValueError, match="num_frames must be ≥ 2"):
    changes.make_changing_sequence("office", 0, change="moved", num_frames=1, **SIZE)


def test_pass_two_sees_the_changed_room(moved, final):
  record = moved.info["changes"]
  assert moved.name == "office_0_test_moved" and final.name == "office_0_test_final"
  assert moved.info["change"] == "moved" and final.info["change"] == "final"
  for seq in (moved, final):
    assert seq.info["passes"] == [[0, HALF], [HALF, FRAMES]]
    assert seq.info["gt_frames"] == [HALF, FRAMES] and seq.info["changes"] == record
    json.dumps(seq.info)
  one, two = moved.instances[:HALF], moved.instances[HALF:]
  np.testing.assert_array_equal(moved.T_world_cam[:HALF], moved.T_world_cam[HALF:])
  (removed,), (added,) = record["removed"], record["added"]
  assert (one == removed).any() and not (two == removed).any()
  assert (two == added).any() and not (one == added).any()
  for i in record["moved"]:  # seen in both passes, at other pixels from the same poses
    assert (one == i).any() and (two == i).any()
    assert not np.array_equal(one == i, two == i)
  # Pass 2 is the same in both kinds; "final" walks the changed room twice.
  for name in ("rgb", "depth", "labels", "instances", "T_world_cam"):
    np.testing.assert_array_equal(getattr(final, name)[HALF:], getattr(moved, name)[HALF:])
    np.testing.assert_array_equal(getattr(final, name)[:HALF], getattr(final, name)[HALF:])
  # Pass 1 of "moved" is the static sequence.
  static = synthetic.make_sequence("office", 0, num_frames=HALF, realism=False, **SIZE)
  np.testing.assert_array_equal(moved.rgb[:HALF], static.rgb)
  np.testing.assert_array_equal(moved.T_world_cam[:HALF], static.T_world_cam)


def test_with_realism_pass_two_is_the_same_and_the_camera_restarts():
  small = dict(num_frames=4, height=24, width=32)
  a = changes.make_changing_sequence("house", 1, change="moved", **small)
  b = changes.make_changing_sequence("house", 1, change="final", **small)
  for name in ("rgb", "depth", "labels"):
    np.testing.assert_array_equal(getattr(a, name)[2:], getattr(b, name)[2:])
  states = a.info["camera_states"]
  assert len(states["exposure"]) == 4 and len(states["frame_interval_s_per_pass"]) == 2
  assert not np.array_equal(a.depth[0], a.depth[2])  # independent sensor noise in pass 2


def test_gt_is_made_of_the_final_frames(moved):
  gt = datasets.gt_voxel_labels(moved, chunk=HALF)
  alone = dataclasses.replace(moved.subset(range(HALF, FRAMES)), info={})
  ref = datasets.gt_voxel_labels(alone, chunk=HALF)
  for k in ("coords", "labels", "hits"):
    np.testing.assert_array_equal(gt[k], ref[k])
  every = datasets.gt_voxel_labels(dataclasses.replace(moved, info={}), chunk=HALF)
  assert every["hits"].sum() > gt["hits"].sum()


def test_subset_and_saved_strides_renumber_the_passes(moved, tmp_path):
  even = moved.subset(range(0, FRAMES, 2))                       # frames 0 2 4 | 6 8
  assert even.info["passes"] == [[0, 3], [3, 5]] and even.info["gt_frames"] == [3, 5]
  back = moved.subset(range(FRAMES - 1, -1, -1))                 # reversed: pass 2 first
  assert back.info["gt_frames"] == [0, HALF]
  assert moved.subset(range(HALF)).info["gt_frames"] == [HALF, HALF]
  assert moved.info["gt_frames"] == [HALF, FRAMES]               # the original is untouched
  with pytest.raises(ValueError, match="keep the frames of info"):
    moved.subset([HALF, 0, HALF + 1])
  moved.save(str(tmp_path / "m"))
  again = datasets.load_spec(f"saved:{tmp_path / 'm'}", stride=2)
  assert again.info["gt_frames"] == [3, 5] and again.info["frame_ids"] == [0, 2, 4, 6, 8]


def test_drift_poses_drift_from_the_true_ones():
  seq = changes.make_changing_sequence("office", 0, change="drift", num_frames=12,
                                       realism=False, **SIZE)
  static = synthetic.make_sequence("office", 0, num_frames=12, realism=False, **SIZE)
  assert seq.name == "office_0_test_drift" and seq.info["change"] == "drift"
  assert "passes" not in seq.info and "gt_frames" not in seq.info
  for name in ("rgb", "depth", "labels", "instances"):
    np.testing.assert_array_equal(getattr(seq, name), getattr(static, name))
  true = np.asarray(seq.info["true_poses"])
  np.testing.assert_array_equal(true, static.T_world_cam)
  np.testing.assert_array_equal(seq.T_world_cam[0], true[0])
  err = np.linalg.norm(seq.T_world_cam[:, :3, 3] - true[:, :3, 3], axis=-1)
  assert 0.02 < err[-1] < 0.3, err
  assert err[6:].mean() > err[1:6].mean() > 0
  turn = np.einsum("tij,tik->tjk", seq.T_world_cam[:, :3, :3].astype(np.float64), true[:, :3, :3])
  angle = np.degrees(np.arccos(np.clip((np.trace(turn, axis1=1, axis2=2) - 1) / 2, -1, 1)))
  assert 0.1 < angle[-1] < 5.0, angle
  # The GT of a drifting sequence stands at the true poses.
  gt, ref = datasets.gt_voxel_labels(seq, chunk=HALF), datasets.gt_voxel_labels(static, chunk=HALF)
  for k in ("coords", "labels", "hits"):
    np.testing.assert_array_equal(gt[k], ref[k])
  # No drift: the true poses back.
  none = changes.drift_poses(true, seed=0, translation=0.0, rotation_deg=0.0)
  np.testing.assert_allclose(none, true, atol=1e-5)
  assert seq.subset([3, 1]).info["true_poses"] == [seq.info["true_poses"][i] for i in (3, 1)]
